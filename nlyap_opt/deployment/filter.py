r"""A CLF-QP safety filter around a certified ``V``: any nominal controller, kept safe.

For a control-affine model :math:`\hat f(x, u) = f_0(x) + g(x)\,u` (the true ``f``, or a
learned :math:`\varphi` whose input enters linearly) the filter applies, at each state
outside the inner ellipse ``E``,

.. math::

    u^*(x) = \arg\min_{u \in U} \|u - u_{nom}(x)\|^2 \quad\text{s.t.}\quad
    \nabla V(x)\cdot(f_0(x) + g(x)u) + m(x) \le -\gamma(x),

with :math:`m(x)` the certificate's margin (0 for the true ``f``;
:math:`\eta\sqrt{\|\nabla_L V\|^2 + s^2}` or ``β`` for a learned φ), the proven decrease
:math:`d(x) = -(\nabla V\cdot\hat f(x, \kappa(x)) + m(x))` and :math:`\gamma = \lambda d`
where :math:`d > 0` (``λ`` = ``decay`` in (0, 1]), :math:`\gamma = d` elsewhere. Inside
``E`` the filter returns ``κ(x)`` itself. One OSQP problem is set up once; each state
updates ``q``, the constraint row of ``A``, ``l`` and ``u`` and warm-starts from the last
solution.

**Theorem.** Let the run's certificate hold (conditions (a), (b), (c), re-verified by
:func:`nlyap_opt.deployment.deploy.load_run`) and let ``κ(x) ∈ U`` on ``Ω_c`` (proved by the
certificate for a learned φ, where ``U`` is the input box of the bound ``‖f − φ‖ ≤ η``; the
system's input box for the true ``f``). Then

1. for every ``x ∈ Ω_c∖B_ε`` the QP is feasible: (a) proves ``d(x) > 0`` there, and
   ``u = κ(x)`` satisfies the constraint with slack ``(1 − λ)·d(x) ≥ 0``;
2. every feasible ``u`` gives ``∇V·f(x, u) ≤ −λ·d(x) < 0`` for the true ``f`` (for φ by
   Cauchy–Schwarz, since ``‖f − φ‖ ≤ η`` on ``X × U``);
3. hence, for any nominal controller, the filtered closed loop keeps ``Ω_c ∪ E`` forward
   invariant and converges to the equilibrium of (c) in ``E`` (the origin, or within ``ε/2``
   of it where ``κ(0)`` is ``u_eq`` only up to rounding): on the compact ``Ω_c∖int E`` (which misses
   ``B_ε``) ``V`` decreases at a rate bounded away from 0, so ``E`` is reached in finite
   time, and on ``E`` the filter is ``κ``, for which (c) proves ``E`` invariant and
   attractive. Outside the certified set the filter promises nothing.

In floating point the QP's answer is accepted only if it satisfies the constraint with half
the demanded decrease (``≤ −λd/2``) after clipping to ``U``; otherwise (an OSQP status other
than solved, or ``κ(x) ∉ U``) the filter returns ``κ(x)``, which satisfies it, and counts it.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np
import scipy.sparse as sp

from ..kernel import deps
from ..kernel.errors import ConfigError
from ..kernel.jsonio import read_json_object, write_atomic
from ..kernel.network import FORMAT as NETWORK_FORMAT
from ..kernel.network import Network
from ..kernel.symbolic import learned_components_of, learned_rhs, robust_lie
from ..kernel.walker import evaluate

__all__ = ["ClfQpFilter", "FilterStats", "NOMINAL_FORMAT", "check_control_affine", "load_nominal",
           "write_linear_nominal"]

#: the ``format`` of a linear nominal controller file ``u = u0 − K x``
NOMINAL_FORMAT = "nlyap-nominal-controller"


def check_control_affine(f, u, what: str) -> None:
    """Refuse an ``f`` that is not affine in ``u``: ``∂f/∂u`` must not depend on ``u``
    (symbolically, so ``∂²f/∂u² ≡ 0``); :class:`ConfigError` otherwise."""
    if u.numel() == 0:
        raise ConfigError(f"{what} has no inputs: there is nothing to filter; use `nlyap "
                          "simulate` without --filter")
    if ca.depends_on(ca.jacobian(f, u), u):
        raise ConfigError(f"{what} is not control-affine (∂f/∂u depends on u), so the CLF-QP "
                          "filter does not apply; use a control-affine model (for a learned "
                          "f: dynamics model 'control_affine')")


def load_nominal(path: str | Path, nx: int, nu: int) -> Callable[[np.ndarray], np.ndarray]:
    """A nominal controller from a JSON file; nothing in it is executed.

    Two forms: a linear gain ``{"format": "nlyap-nominal-controller", "K": [[...]],
    "u0": [...]}`` for ``u = u0 − K x`` (``K``: ``nu × nx``; ``u0`` default 0), or a
    network file (``"format": "nlyap-network"``, ``R^nx → R^nu``). Returns a batched
    ``(N, nx) -> (N, nu)`` function.
    """

    d = read_json_object(path, "nominal controller")
    fmt = d.get("format")
    if fmt == NETWORK_FORMAT:
        net = Network.from_dict(d, source=str(path))
        kind = (d.get("meta") or {}).get("kind") if isinstance(d.get("meta"), dict) else None
        if kind not in (None, "controller"):
            raise ConfigError(f"nominal controller {path} is a network of kind {kind!r} (a "
                              "controller's file says 'controller'); pass a controller")
        if net.n_in != nx or net.n_out != nu:
            raise ConfigError(f"nominal controller {path} maps R^{net.n_in} -> R^{net.n_out}; "
                              f"the system needs R^{nx} -> R^{nu}")
        return net.numpy
    if fmt != NOMINAL_FORMAT:
        raise ConfigError(f"nominal controller {path}: 'format' must be {NOMINAL_FORMAT!r} "
                          f"(a linear gain) or {NETWORK_FORMAT!r} (a network), got {fmt!r}; "
                          "fix the file")
    extra = sorted(set(d) - {"format", "K", "u0", "description"})
    if extra:
        raise ConfigError(f"nominal controller {path}: unknown keys {extra}; allowed: "
                          "format, K, u0, description")
    def numbers(v) -> bool:   # JSON numbers only: "2" and true are not (float() takes them)
        if isinstance(v, list):
            return all(numbers(a) for a in v)
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    if not numbers(d.get("K", [])) or not numbers(d.get("u0", [])):
        raise ConfigError(f"nominal controller {path}: 'K' and 'u0' must hold numbers only "
                          "(not strings or booleans); fix the file")
    try:
        K = np.array(d["K"], dtype=float)
        u0 = np.array(d.get("u0", np.zeros(nu)), dtype=float)
    except KeyError:
        raise ConfigError(f"nominal controller {path} needs 'K' (an {nu} x {nx} list of "
                          "rows); fix the file") from None
    except (TypeError, ValueError):
        raise ConfigError(f"nominal controller {path}: 'K' and 'u0' must hold numbers only; "
                          "fix the file") from None
    if K.shape != (nu, nx) or u0.shape != (nu,):
        raise ConfigError(f"nominal controller {path}: K must be {nu} x {nx} and u0 have {nu} "
                          f"entries, got {K.shape} and {u0.shape}; fix the file")
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(u0))):
        raise ConfigError(f"nominal controller {path}: K and u0 must be finite; fix the file")
    return lambda x: u0 - np.atleast_2d(x) @ K.T


@dataclass
class FilterStats:
    """Counts since construction: QPs solved and accepted, ``κ`` returned inside ``E``, and
    ``κ`` returned because the QP's answer was not accepted."""

    qp: int = 0
    in_ellipse: int = 0
    fallback: int = 0


class ClfQpFilter:
    """The CLF-QP safety filter of a certified run (module docstring: the theorem).

    Parameters
    ----------
    run : nlyap_opt.deployment.deploy.CertifiedRun
    nominal : callable
        ``(N, nx) -> (N, nu)``, e.g. :func:`load_nominal`.
    decay : float
        ``λ ∈ (0, 1]``: the filtered input must achieve ``λ`` times the decrease that the
        certificate proved for ``κ``.
    dynamics : {"true", "learned"}, optional
        The model ``f̂`` of the constraint; default the true ``f`` where the run has a
        CasADi model, else φ (with its margin).
    """

    def __init__(self, run, nominal: Callable, *, decay: float = 0.5,
                 dynamics: str | None = None):
        osqp = deps.osqp()

        if not 0 < decay <= 1:
            raise ConfigError(f"decay must lie in (0, 1], got {decay!r}")
        self.run, self.nominal, self.decay = run, nominal, float(decay)
        problem, sysm = run.problem, run.system
        has_model = getattr(sysm, "has_model", True)
        which = dynamics or ("true" if has_model else "learned")
        if which == "learned" and problem.dynamics is None:
            raise ConfigError(f"run {run.directory} has no learned φ; filter with the true f")
        if which == "true" and not has_model:
            raise ConfigError(f"the system of {run.directory} has no CasADi model to check "
                              "control-affinity; filter with the learned φ")
        self.dynamics = which
        nx, nu = sysm.nx, sysm.nu
        x, u = ca.SX.sym("x", nx), ca.SX.sym("u", nu)
        if which == "true":
            fhat = ca.substitute(sysm.f, ca.vertcat(sysm.x, sysm.u), ca.vertcat(x, u))
            margin = 0
        else:
            fhat = learned_rhs(sysm, problem.dynamics, x, u)
            dec = problem.decrease()      # η, M, s as certified
            if problem.margin_mode == "global":
                margin = dec.margin
            else:
                margin = robust_lie(0, problem.V_expr(x), x, problem.eta, dec.smoothing,
                                    learned_components_of(sysm, problem.dynamics))
        check_control_affine(fhat, u, f"the {'true f' if which == 'true' else 'learned φ'} "
                             f"of {sysm.name!r}")
        Vx = problem.V_expr(x)
        grad = ca.gradient(Vx, x)
        G = ca.substitute(ca.jacobian(fhat, u), u, ca.DM.zeros(nu))
        f0 = ca.substitute(fhat, u, ca.DM.zeros(nu))
        kappa = problem.controller.casadi(x) if problem.controller is not None \
            else ca.DM(sysm.u_eq)
        a = ca.mtimes(G.T, grad)
        e = ca.dot(grad, f0) + margin
        d = -(e + ca.dot(a, kappa))
        # dense: an input that does not enter f leaves a structural zero in a (read by
        # position below)
        self._pieces = ca.Function("clf_qp_pieces", [x],
                                   [ca.densify(v) for v in (a, e, d, kappa)],
                                   ["x"], ["a", "e", "d", "kappa"])
        box = problem.input_box if which == "learned" else sysm.input_box
        self.box = np.asarray(box, dtype=float).reshape(nu, 2)
        self.nu = nu
        E = run.certificate.inner_ellipse
        self._E = E
        P = sp.csc_matrix(2.0 * np.eye(nu))
        A = sp.csc_matrix(np.vstack([np.ones((1, nu)), np.eye(nu)]))
        self._order = self._row0_positions(A)
        self._A_data = A.data.copy()
        self._l = np.concatenate([[-np.inf], self.box[:, 0]])
        self._u = np.concatenate([[0.0], self.box[:, 1]])
        self._qp = osqp.OSQP()
        self._qp.setup(P, np.zeros(nu), A, self._l.copy(), self._u.copy(), verbose=False,
                       eps_abs=1e-9, eps_rel=1e-9, polishing=False, warm_starting=True,
                       max_iter=4000)
        self.stats = FilterStats()

    @staticmethod
    def _row0_positions(A) -> np.ndarray:
        """Positions in ``A.data`` (CSC) of the entries of row 0, column by column."""
        pos = []
        for j in range(A.shape[1]):
            for k in range(A.indptr[j], A.indptr[j + 1]):
                if A.indices[k] == 0:
                    pos.append(k)
        return np.array(pos)

    def pieces(self, pts: np.ndarray) -> tuple[np.ndarray, ...]:
        """``a (N, nu)``, ``e (N,)``, ``d (N,)``, ``κ (N, nu)`` at ``(N, nx)`` points: the
        constraint is ``e + a·u ≤ −γ``; ``d`` the decrease proven for ``κ``."""

        pts = np.atleast_2d(np.asarray(pts, dtype=float))
        if len(pts) == 1:        # one state (a control loop): CasADi's own call is faster
            a, e, d, k = (np.array(v, dtype=float).reshape(1, -1) for v in self._pieces(pts[0]))
        else:
            a, e, d, k = evaluate(self._pieces, [pts])
        return a, e[:, 0], d[:, 0], k

    def solve(self, a: np.ndarray, e: float, d: float, kappa: np.ndarray,
              u_nom: np.ndarray) -> tuple[np.ndarray, str]:
        """One QP (the structure set up once: ``q``, ``A``'s first row, ``l``, ``u``
        updated). Returns ``(u*, OSQP status)``; ``u*`` is ``κ`` when not accepted."""
        gamma = self.decay * d if d > 0 else d
        scale = float(np.max(np.abs(a)))           # the row scaled to max |a_i| = 1
        scale = scale if scale > 0 else 1.0
        self._A_data[self._order] = a / scale
        self._u[0] = (-gamma - e) / scale
        self._qp.update(q=-2.0 * np.asarray(u_nom, dtype=float), Ax=self._A_data, u=self._u)
        res = self._qp.solve(raise_error=False)
        status = res.info.status
        self.stats.qp += 1
        if status == "solved" and np.all(np.isfinite(res.x)):
            us = np.clip(res.x, self.box[:, 0], self.box[:, 1])
            need = -0.5 * gamma if d > 0 else -gamma + 1e-9 * (1 + abs(e))
            if e + float(a @ us) <= need:
                return us, status
        self.stats.fallback += 1
        return np.asarray(kappa, dtype=float).copy(), status

    def __call__(self, pts) -> np.ndarray:
        """The filtered input at ``(N, nx)`` states (``κ`` inside ``E``)."""
        pts = np.atleast_2d(np.asarray(pts, dtype=float))
        a, e, d, k = self.pieces(pts)
        un = np.asarray(self.nominal(pts), dtype=float).reshape(len(pts), self.nu)
        out = k.copy()
        inE = self._E.contains(pts) if self._E is not None else np.zeros(len(pts), bool)
        self.stats.in_ellipse += int(inE.sum())
        for i in np.flatnonzero(~inE):
            out[i] = self.solve(a[i], e[i], d[i], k[i], un[i])[0]
        return out


def write_linear_nominal(path: str | Path, K, u0=None, description: str = "") -> Path:
    """Write a linear nominal controller file ``u = u0 − K x`` (:func:`load_nominal`)."""
    K = np.atleast_2d(np.asarray(K, dtype=float))
    d = {"format": NOMINAL_FORMAT, "K": K.tolist(),
         "u0": (np.zeros(len(K)) if u0 is None else np.asarray(u0, dtype=float)).tolist()}
    if description:
        d["description"] = description
    return write_atomic(path, json.dumps(d, indent=1, allow_nan=False))
