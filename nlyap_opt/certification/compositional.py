r"""Compositional certificates for interconnected systems (no bisection of the whole state).

An autonomous system :math:`\dot x = f(x)` whose states split into subsystems
:math:`x = (x_1, \dots, x_N)` (``System(subsystems=...)``) gets the Lyapunov function

.. math:: V(x) = \sum_i w_i V_i(x_i), \qquad V_i(x_i) = x_i^\top P_i x_i, \quad P_i \succ 0,

and the region of attraction :math:`\Omega_c = \{x : V(x) \le c\} \subseteq D` inside the
system's box :math:`D`. What is proved (all of it again by :func:`recheck_compositional`):

1. **Local inequalities.** For every subsystem :math:`i`, with :math:`y_i = (x_i,
   x_{N(i)})` its states and those of the subsystems its equations depend on
   (structurally, from the CasADi graph) and :math:`Y_i` the projection of :math:`D`,

   .. math:: F_i(y_i) = \nabla V_i \cdot f_i(y_i) + \alpha_i V_i(x_i)
             - \sum_{j \in N(i)} \beta_{ij} V_j(x_j) \le 0 \quad \text{on } Y_i.

   ``f(0) = 0`` is proved by evaluating ``f``'s graph at 0 in exact rational arithmetic,
   so the mean-value form :math:`f_i(y) = \bar J_i(y)\,y`, :math:`\bar J_i(y) = \int_0^1
   J_i(ty)\,dt` (``J_i`` the Jacobian of ``f_i``; the box contains 0, so :math:`t y \in
   Y_i`) gives :math:`\nabla V_i \cdot f_i = 2 x_i^\top P_i \bar J_i\, y`. The entries of
   :math:`\bar J_i` are enclosed by outward-rounded interval arithmetic over the CasADi graph
   of ``J_i`` on 16 nested slices :math:`t_k Y_i`; with the centre :math:`C` and radius
   :math:`R` of that enclosure and ``P_i`` padded with zeros to all of ``y``,
   :math:`2 x_i^\top P_i \bar J_i y \le y^\top N y`, :math:`N = PC + C^\top P +
   \mathrm{diag}((|P|R + R^\top|P|)\mathbf 1)`, formed in exact rationals (``P_i`` never
   enters a CasADi graph). Negative definiteness of :math:`N + \mathrm{blockdiag}(\alpha_i
   P_i, -\beta_{ij} P_j)` is decided by an exact :math:`LDL^\top` in
   :class:`fractions.Fraction` arithmetic. The test works on the low-dimensional
   :math:`Y_i` only: nothing bisects the whole state space.
2. **Comparison system.** The Metzler matrix :math:`A_c = -\mathrm{diag}(\alpha) + B`,
   :math:`B_{ij} = \beta_{ij}`, with weights :math:`w > 0` and
   :math:`(w^\top A_c)_j \le -\gamma w_j`, :math:`\gamma > 0`, checked exactly; then
   :math:`\dot V = \sum_i w_i \dot V_i \le \sum_j (w^\top A_c)_j V_j \le -\gamma V` wherever
   every :math:`y_i \in Y_i`.
3. **Level.** :math:`\Omega_c \subseteq D`: :math:`c \le w_i r_k^2 / (P_i^{-1})_{kk}` for
   every state :math:`k` of subsystem :math:`i` (:math:`r_k` the distance from 0 to the
   nearer face of :math:`D`), exactly. Then :math:`\Omega_c` (a compact ellipsoid) lies in
   :math:`D`, so 1–2 hold on it, :math:`V(x(t)) \le V(x(0)) e^{-\gamma t}`: it is forward
   invariant and every solution from it converges exponentially to the origin.

The numbers :math:`P_i, \alpha_i, \beta_{ij}, w, c, \gamma` are chosen in float64 (a
Lyapunov equation per subsystem, generalised eigenvalues, a linear solve); only the exact
checks above decide. The method needs a model ``f`` (the true dynamics) without inputs, built
from smooth operations defined on all of ``D``; anything else is refused with the reason.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import casadi as ca
import numpy as np
from scipy.linalg import eigh, solve_continuous_lyapunov

from ..kernel.errors import ConfigError, UnsupportedOperationError
from ..kernel.exact import (
    float_down,
    inverse_diagonal,
    positive_definite,
    rational,
    rational_matrix,
)
from ..kernel.jsonio import read_file_bytes, save_timings, split_timings
from ..kernel.provenance import fingerprint
from ..kernel.walker import compile_function, exact_values
from .certificate import (
    CertStatus,
    bound_system,
    read_certificate_file,
    system_binding,
    write_json_atomic,
)
from .roa import TAYLOR_SLICES, mean_value_form, sliced_enclosure

__all__ = ["FORMAT", "VERSION", "Piece", "CompositionalCertificate", "certify_compositional",
           "check_compositional", "recheck_compositional", "save_compositional",
           "is_compositional_file"]

FORMAT = "nlyap-compositional-certificate"
VERSION = 1

#: decay fractions θ tried: α_i = θ·α_i*, α_i* the subsystem's own rate on its box
_THETAS = (0.9, 0.75, 0.5, 0.3, 0.15)

ASSUMPTIONS = [
    "the model f is the true dynamics (a compositional certificate is about the given model)",
    "f is continuously differentiable on the domain box D (its CasADi graph holds "
    "only smooth operations defined everywhere; checked)",
]


# ============================================================================ the certificate
@dataclass
class Piece:
    """One subsystem: its states, the subsystems its equations read, ``V_i = x_iᵀ P x_i``,
    the proved rate ``α`` and the coupling gains ``β`` (one per neighbour)."""

    states: tuple[int, ...]
    neighbours: tuple[int, ...]
    P: np.ndarray
    alpha: float = 0.0
    beta: tuple[float, ...] = ()

    def to_dict(self) -> dict:
        return {"states": list(self.states), "neighbours": list(self.neighbours),
                "P": np.asarray(self.P, dtype=float).tolist(), "alpha": float(self.alpha),
                "beta": [float(b) for b in self.beta]}


@dataclass
class CompositionalCertificate:
    """A compositional ROA certificate: ``{x : Σ w_i x_iᵀ P_i x_i ≤ level}`` when certified."""

    status: CertStatus
    reason: str
    system: str
    pieces: list[Piece]
    weights: np.ndarray
    level: float
    decay: float
    domain_box: np.ndarray
    checks: dict = field(default_factory=dict)
    assumptions: list = field(default_factory=lambda: list(ASSUMPTIONS))
    seconds: float = 0.0

    @property
    def certified(self) -> bool:
        return self.status is CertStatus.CERTIFIED

    def V(self, points) -> np.ndarray:
        """``V(x) = Σ w_i x_iᵀ P_i x_i`` at ``(N, nx)`` points (float64, for display)."""
        pts = np.atleast_2d(np.asarray(points, dtype=float))
        out = np.zeros(len(pts))
        for w, p in zip(self.weights, self.pieces):
            xi = pts[:, list(p.states)]
            out += w * np.einsum("ni,ij,nj->n", xi, np.asarray(p.P), xi)
        return out

    def contains(self, points) -> np.ndarray:
        """Which points lie in the certified set (all False when not certified)."""
        pts = np.atleast_2d(np.asarray(points, dtype=float))
        if not self.certified:
            return np.zeros(len(pts), dtype=bool)
        return self.V(pts) <= self.level

    def summary(self) -> str:
        """One line: status, region, decay rate (or why not)."""
        if self.certified:
            return (f"certified: level {self.level:.6g} of V = Σ w_i x_iᵀP_i x_i "
                    f"({len(self.pieces)} subsystems, {self.domain_box.shape[0]} states), "
                    f"dV/dt ≤ -{self.decay:.4g} V, inside the box D (known dynamics, "
                    "compositional)")
        return f"{self.status.value}: {self.reason}"

    def to_dict(self) -> dict:
        return {
            "format": FORMAT, "version": VERSION, "status": self.status.value,
            "reason": self.reason, "system": self.system, "method": "compositional",
            "setting": "known",
            "certified_set": "{x : sum_i w_i x_i^T P_i x_i <= level}",
            "decrease_condition": "dV/dt <= -decay * V on the certified set",
            "domain_box": np.asarray(self.domain_box, dtype=float).tolist(),
            "subsystems": [p.to_dict() for p in self.pieces],
            "weights": np.asarray(self.weights, dtype=float).tolist(),
            "level": float(self.level), "decay": float(self.decay),
            "checks": dict(self.checks), "assumptions": list(self.assumptions),
            "seconds": self.seconds,
        }


# ============================================================================ structure
def _structure(system, parts) -> list[tuple[int, ...]]:
    """For each subsystem, the other subsystems its equations depend on (structurally)."""
    f = system.f
    owner = {k: i for i, p in enumerate(parts) for k in p}
    out = []
    for i, p in enumerate(parts):
        fi = ca.vertcat(*[f[r] for r in p])
        dep = {owner[k] for k in range(system.nx) if ca.depends_on(fi, system.x[k])}
        out.append(tuple(sorted(dep - {i})))
    return out


def _refusal(system, parts) -> str:
    """Why the compositional method does not apply to ``system`` (``""``: it does)."""
    if not getattr(system, "has_model", False):
        return ("the compositional method needs the model f (a proof about the true "
                "dynamics); this system has none")
    if system.nu:
        return (f"the compositional method is for systems without inputs; {system.name!r} has "
                f"{system.nu} (close the loop in f first)")
    if parts is None:
        return (f"system {system.name!r} declares no subsystems; give "
                "System(..., subsystems=[(0, 1), (2, 3), ...])")
    box = system.state_box
    if not np.all((box[:, 0] < 0) & (box[:, 1] > 0)):
        return "the compositional method needs the origin inside the state box (lower < 0 < upper)"
    return ""


def _local_bound(system, parts, nbrs, i: int, P) -> tuple[list | None, str]:
    r"""``(N, "")`` with :math:`\nabla V_i \cdot f_i(y) \le y^\top N y` on subsystem
    ``i``'s box ``Y_i`` (its states, then its neighbours' in order), or ``(None, why)``.

    ``P``: the exact rational ``P_i``. The mean-value form :math:`f_i(y) = \bar J_i(y)\,y`
    (``f_i(0) = 0`` proved exactly beforehand), :math:`\bar J_i = \int_0^1 J_i(sy)\,ds`,
    with the Jacobian ``J_i`` of ``f_i`` enclosed on nested slices of ``Y_i``
    (:func:`~nlyap_opt.certification.roa.sliced_enclosure`) and ``P_i`` padded with zeros
    to all of ``y`` (:func:`~nlyap_opt.certification.roa.mean_value_form`). ``P_i`` never
    enters a CasADi graph, so no float folding of its products with ``f``'s constants can
    change a sign. Refused when the graph of ``f_i`` or its Jacobian holds an operation that
    is non-smooth or partial (the walker's checked operations, constant arguments
    excepted): the mean-value form needs ``f`` continuously differentiable on ``D``.
    """
    idx = list(parts[i]) + [k for j in nbrs[i] for k in parts[j]]
    m, ni = len(idx), len(parts[i])
    y = ca.SX.sym("y", m)
    xs = ca.SX.zeros(system.nx)
    for a, k in enumerate(idx):
        xs[k] = y[a]
    fi = ca.substitute(ca.vertcat(*[system.f[r] for r in parts[i]]), system.x, xs)
    # the rows of the neighbours' states are 0: V_i reads x_i only (a symbolic seed S: no
    # float folding of f's constants in the derivative, see seeded_jacobian)
    S = ca.SX.sym("S", m, m)
    JS = ca.densify(ca.vertcat(ca.jtimes(fi, y, S), ca.SX.zeros(m - ni, m)))
    name = f"subsystem {i + 1} ({', '.join(system.state_names[k] for k in parts[i])})"
    try:
        if compile_function(ca.Function(f"local_{i}", [y, S], [fi, JS])).checked:
            return None, (f"{name}: f uses non-smooth or partial operations; the "
                          "compositional method needs f continuously differentiable "
                          "on all of D")
        CR = sliced_enclosure(ca.Function(f"jac_{i}", [y, S], [JS]), system.state_box[idx],
                              [Fraction(1, TAYLOR_SLICES)] * TAYLOR_SLICES)
    except UnsupportedOperationError as err:
        return None, f"{name}: {err}"
    if CR is None:
        return None, f"{name}: the Jacobian of f_i is not bounded on its box"
    Pm = [[P[a][b] if a < ni and b < ni else Fraction(0) for b in range(m)] for a in range(m)]
    return mean_value_form(Pm, *CR), ""


def _local_matrix(N, sizes, P, alpha, beta) -> list[list[Fraction]]:
    """``-(N + blockdiag(α P_i, -β_j P_j))``: positive definite iff the local test holds."""
    M = [row[:] for row in N]
    off = 0
    for s, (Pk, coef) in enumerate(zip(P, [rational(alpha)] + [-rational(b) for b in beta])):
        n = sizes[s]
        for a in range(n):
            for b in range(n):
                M[off + a][off + b] += coef * rational(Pk[a][b])
        off += n
    return [[-v for v in row] for row in M]


def _equilibrium_refusal(system) -> str:
    """``""`` when ``f(0) = 0`` exactly: the CasADi graph of ``f`` evaluated at ``x = 0`` in
    exact rational arithmetic (:class:`~nlyap_opt.kernel.walker.ExactPointArithmetic`) gives
    the rational 0 in every component. Neither a float evaluation nor a substitution into
    the graph can prove it (both round; ``((x² + 10¹⁶) + 1) − 10¹⁶`` folds to 0 at 0)."""
    vals = exact_values(ca.Function("f0", [system.x], [system.f]), [0] * system.nx)
    if vals is None or not all(isinstance(v, Fraction) and v == 0 for v in vals):
        return ("the origin is not an equilibrium: f(0) is not exactly 0 (evaluated in exact "
                "rational arithmetic); shift the state so that the equilibrium is at 0")
    return ""


# ============================================================================ the checks
def check_compositional(system, pieces: list[Piece], weights, level: float,
                        decay: float) -> tuple[bool, dict, str]:
    """Prove the certificate's conditions for ``system`` exactly (module docstring, 1–3).

    Parameters
    ----------
    system : systems.System
        With a model, no input, and ``subsystems`` equal to the pieces' states.
    pieces : list of Piece
    weights : (N,) array_like
    level, decay : float
        The claimed ``c`` and ``γ``.

    Returns
    -------
    (bool, dict, str)
        Whether everything is proved, the per-condition verdicts, and the first failure.
    """
    parts = tuple(tuple(p.states) for p in pieces)
    why = _refusal(system, parts)
    if not why and parts != tuple(system.subsystems or ()):
        why = "the certificate's subsystems are not the system's declared subsystems"
    if why:
        return False, {"structure": why}, why
    checks: dict[str, str] = {}
    nbrs = _structure(system, parts)
    if any(tuple(p.neighbours) != nb for p, nb in zip(pieces, nbrs)):
        why = "the neighbours of some subsystem are not those of f's graph"
        return False, {"structure": why}, why
    checks["structure"] = "proved (neighbours from f's graph)"
    why = _equilibrium_refusal(system)
    if why:
        return False, {**checks, "equilibrium": why}, why
    checks["equilibrium"] = "proved (f(0) = 0 in exact rational arithmetic)"
    try:
        w = [rational(v) for v in np.asarray(weights, dtype=float).ravel()]
        c, g = rational(level), rational(decay)
        Ps = [[[rational(v) for v in row] for row in np.asarray(p.P, dtype=float)] for p in pieces]
        alphas = [rational(p.alpha) for p in pieces]
        betas = [[rational(b) for b in p.beta] for p in pieces]
    except (ValueError, TypeError):
        why = "a number of the certificate is not finite, or a matrix has the wrong shape"
        return False, {**checks, "numbers": why}, why
    if len(w) != len(pieces) or any(len(b) != len(p.neighbours) for b, p in zip(betas, pieces)):
        why = "the certificate's weights or gains do not match its subsystems"
        return False, {**checks, "numbers": why}, why
    for i, (p, P) in enumerate(zip(pieces, Ps)):
        n = len(p.states)
        if len(P) != n or any(len(r) != n for r in P) or \
                any(P[a][b] != P[b][a] for a in range(n) for b in range(n)) \
                or not positive_definite(P):
            why = f"P of subsystem {i + 1} is not a symmetric positive definite {n}x{n} matrix"
            return False, {**checks, "positive definite": why}, why
    checks["positive definite"] = "proved (exact LDLᵀ of every P_i)"
    for i, p in enumerate(pieces):
        if alphas[i] < 0 or any(b < 0 for b in betas[i]):
            why = f"subsystem {i + 1}: α and β must be ≥ 0"
            return False, {**checks, "local": why}, why
        N, why = _local_bound(system, parts, nbrs, i, Ps[i])
        if N is None:
            return False, {**checks, "local": why}, why
        sizes = [len(p.states)] + [len(parts[j]) for j in p.neighbours]
        Ploc = [Ps[i]] + [Ps[j] for j in p.neighbours]
        if not positive_definite(_local_matrix(N, sizes, Ploc, p.alpha, p.beta)):
            why = (f"subsystem {i + 1} (states {', '.join(system.state_names[k] for k in p.states)}"
                   f"): dV_i/dt ≤ -{p.alpha:.4g} V_i + Σ β_ij V_j is not proved on its box "
                   "(coupling too strong for this domain, or the domain too large)")
            return False, {**checks, "local": why}, why
    dim = max(len(p.states) + sum(len(parts[j]) for j in p.neighbours) for p in pieces)
    checks["local"] = (f"proved on {len(pieces)} boxes of dimension ≤ {dim} (mean-value form "
                       "of f_i's interval Jacobian, P_i exact, exact LDLᵀ)")
    if g <= 0 or any(v <= 0 for v in w):
        why = "the weights and the decay rate must be positive"
        return False, {**checks, "comparison": why}, why
    for j in range(len(pieces)):
        col = -alphas[j] * w[j] + sum(w[i] * b for i, p in enumerate(pieces)
                                      for nb, b in zip(p.neighbours, betas[i]) if nb == j)
        if col > -g * w[j]:
            why = (f"the comparison system does not prove dV/dt ≤ -{decay:g} V (subsystem "
                   f"{j + 1}'s column); the interconnection is too strong for these weights")
            return False, {**checks, "comparison": why}, why
    checks["comparison"] = "proved (wᵀ(-diag α + B) ≤ -γ wᵀ exactly)"
    box = system.state_box
    for i, (p, P) in enumerate(zip(pieces, Ps)):
        inv = inverse_diagonal(P)
        for a, k in enumerate(p.states):
            r = min(-rational(box[k, 0]), rational(box[k, 1]))
            if c <= 0 or c * inv[a] > w[i] * r * r:
                why = (f"the level {level:g} is not proved: the set V ≤ level leaves the box D "
                       f"along {system.state_names[k]}")
                return False, {**checks, "level": why}, why
    checks["level"] = "proved ({V ≤ c} ⊆ D exactly)"
    return True, checks, ""


# ============================================================================ the search
def _lyapunov_P(A: np.ndarray) -> np.ndarray | None:
    if A.size and np.max(np.linalg.eigvals(A).real) >= 0:
        return None
    P = solve_continuous_lyapunov(A.T, -np.eye(A.shape[0]))
    return 0.5 * (P + P.T)


def _gains(N, sizes, P, theta: float):
    """Float choice of ``α = θ α*`` and one ``β`` for all neighbours (bisection)."""
    Nf = np.array([[float(v) for v in row] for row in N])
    n0 = sizes[0]
    Pf = [np.asarray(p, dtype=float) for p in P]
    a_star = float(eigh(-Nf[:n0, :n0], Pf[0], eigvals_only=True)[0])
    if not a_star > 0:
        return None
    alpha = theta * a_star
    k = len(sizes) - 1
    if k == 0:
        return alpha, ()

    def ok(beta):
        M = Nf.copy()
        off = 0
        for s, coef in enumerate([alpha] + [-beta] * k):
            n = sizes[s]
            M[off:off + n, off:off + n] += coef * Pf[s]
            off += n
        return np.max(np.linalg.eigvalsh(0.5 * (M + M.T))) < 0

    hi = 1.0
    while not ok(hi):
        hi *= 2
        if hi > 1e12:
            return None
    lo = 0.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if ok(mid) else (mid, hi)
    return alpha, (hi * (1 + 1e-6) + 1e-12,) * k


def certify_compositional(system, *, log=print) -> CompositionalCertificate:
    """Certify a region of attraction of ``system`` compositionally (module docstring).

    Parameters
    ----------
    system : systems.System
        A model without inputs that declares ``subsystems``.
    log : callable

    Returns
    -------
    CompositionalCertificate
        ``CERTIFIED`` only when :func:`check_compositional` proves the chosen numbers.

    Raises
    ------
    ConfigError
        The system does not admit the method (no model, inputs, no declared subsystems,
        the origin not inside its box): the message says what to change.
    """
    t0 = time.perf_counter()
    parts = system.subsystems
    why = _refusal(system, parts)
    if why:
        raise ConfigError(why)
    nbrs = _structure(system, parts)
    box = system.state_box

    def fail(reason, pieces=()):
        return CompositionalCertificate(CertStatus.NOT_CERTIFIED, reason, system.name,
                                        list(pieces), np.zeros(0), 0.0, 0.0, box,
                                        seconds=time.perf_counter() - t0)

    why = _equilibrium_refusal(system)
    if why:
        return fail(why)
    Ps = []
    for i, p in enumerate(parts):
        P = _lyapunov_P(system.A[np.ix_(p, p)])
        if P is None:
            return fail(f"subsystem {i + 1}'s linearisation is not Hurwitz: the compositional "
                        "method needs every subsystem stable on its own")
        Ps.append(P)
    bounds = []
    for i in range(len(parts)):
        N, why = _local_bound(system, parts, nbrs, i, rational_matrix(Ps[i]))
        if N is None:
            return fail(why)
        bounds.append(N)
    candidates = []
    for theta in _THETAS:
        pieces = []
        for i in range(len(parts)):
            sizes = [len(parts[i])] + [len(parts[j]) for j in nbrs[i]]
            g = _gains(bounds[i], sizes, [Ps[i]] + [Ps[j] for j in nbrs[i]], theta)
            if g is None:
                break
            pieces.append(Piece(tuple(parts[i]), nbrs[i], Ps[i], g[0], g[1]))
        if len(pieces) < len(parts):
            continue
        Ac = -np.diag([p.alpha for p in pieces])
        for i, p in enumerate(pieces):
            for j, b in zip(p.neighbours, p.beta):
                Ac[i, j] += b
        try:
            w = np.linalg.solve(Ac.T, -np.ones(len(pieces)))
        except np.linalg.LinAlgError:
            continue
        if not np.all(w > 0):
            continue
        w = w / w.max()
        gamma = _decay(pieces, w)
        if not gamma > 0:
            continue
        cq = min(Fraction(float(w[i])) * min(-rational(box[k, 0]), rational(box[k, 1])) ** 2 / d
                 for i, p in enumerate(pieces)
                 for k, d in zip(p.states, inverse_diagonal(
                     [[rational(v) for v in row] for row in p.P])))
        level = float_down(cq)
        if not level > 0:
            continue
        logvol = sum(0.5 * len(p.states) * math.log(level / w[i])
                     - 0.5 * math.log(np.linalg.det(p.P)) for i, p in enumerate(pieces))
        candidates.append((-logvol, theta, pieces, w, level, gamma))
    why = ("no decay rates and coupling gains make the comparison system stable: the "
           "interconnection is too strong on this domain (a smaller box may certify)")
    for _, theta, pieces, w, level, gamma in sorted(candidates, key=lambda c: c[:2]):
        ok, checks, why = check_compositional(system, pieces, w, level, gamma)
        seconds = time.perf_counter() - t0
        log(f"compositional: {len(pieces)} subsystems, θ = {theta}, level {level:.6g}, "
            f"decay {gamma:.4g}: {'certified' if ok else why} ({seconds:.2f} s)")
        if ok:
            return CompositionalCertificate(CertStatus.CERTIFIED, "", system.name, pieces, w,
                                            level, gamma, box, checks, seconds=seconds)
    return fail(why)


def _decay(pieces: list[Piece], w: np.ndarray) -> float:
    """The largest float ``γ ≤ min_j -(wᵀA_c)_j / w_j`` (exact), or 0 when that is ≤ 0."""
    wq = [Fraction(float(v)) for v in w]
    col = [-Fraction(p.alpha) * wq[j] for j, p in enumerate(pieces)]
    for i, p in enumerate(pieces):
        for j, b in zip(p.neighbours, p.beta):
            col[j] += wq[i] * Fraction(b)
    g = min(-c / v for c, v in zip(col, wq))
    return float_down(g) if g > 0 else 0.0


# ============================================================================ files
def save_compositional(cert: CompositionalCertificate, system, out: str | Path) -> Path:
    """Write ``out/certificate.json`` (timings in ``timings.json`` beside it)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    d = cert.to_dict()
    d["system_binding"] = system_binding(system)
    if getattr(system, "source", ""):
        d["system_source"] = str(system.source)
    d["provenance"] = fingerprint()
    clean, timings = split_timings(d)
    write_json_atomic(out / "certificate.json", clean)
    save_timings(out / "timings.json", timings)
    return out / "certificate.json"


def is_compositional_file(path: str | Path) -> bool:
    """Whether ``path`` (a file or a run directory) holds a compositional certificate."""
    path = Path(path)
    if path.is_dir():
        path = path / "certificate.json"
    try:
        d = json.loads(read_file_bytes(path, "certificate"))
    except (OSError, ValueError, RecursionError, ConfigError):
        return False  # the reader of the certificate says why
    return isinstance(d, dict) and d.get("format") == FORMAT


def _typed(d: dict, key: str, kind, path):
    v = d.get(key)
    if not isinstance(v, kind) or isinstance(v, bool):
        raise ConfigError(f"malformed compositional certificate {path}: {key!r} is missing or "
                          f"not a {getattr(kind, '__name__', 'number')}; rerun the command "
                          "that wrote it")
    return v


def recheck_compositional(path: str | Path, *, system=None,
                          allow_factory: bool = False) -> CompositionalCertificate:
    """Prove a saved compositional certificate again, from its numbers and the system.

    Parameters
    ----------
    path : str or Path
        ``certificate.json`` or its directory.
    system : systems.System, str or Path, optional
        As for :func:`nlyap_opt.certification.certificate.recheck_certificate` (default: the
        catalogue system the certificate names, or its spec file, never code named inside it).
    allow_factory : bool

    Returns
    -------
    CompositionalCertificate
        ``CERTIFIED`` only when the system is the certified one (its binding hash) and
        :func:`check_compositional` proves the stored numbers.

    Raises
    ------
    ConfigError
        Not a compositional certificate of a version this nlyap reads, or malformed.
    """
    path, d = read_certificate_file(path)
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise ConfigError(f"{path} is not a compositional certificate (format {FORMAT!r}); "
                          "pass the certificate.json written by `nlyap run`")
    if d.get("version") != VERSION:
        raise ConfigError(f"compositional certificate version {d.get('version')!r} is not "
                          f"supported (this nlyap reads {VERSION}); rerun the command")
    known = {"format", "version", "status", "reason", "system", "method", "setting",
             "certified_set", "decrease_condition", "domain_box", "subsystems", "weights",
             "level", "decay", "checks", "assumptions", "system_binding", "system_source",
             "provenance"}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ConfigError(f"compositional certificate {path} holds fields this nlyap does not "
                          f"know ({', '.join(unknown)}); re-check it with the nlyap that wrote "
                          "it, or rerun the command")
    name = _typed(d, "system", str, path)
    try:
        pieces = [Piece(tuple(int(k) for k in s["states"]),
                        tuple(int(j) for j in s["neighbours"]),
                        np.asarray(s["P"], dtype=float), float(s["alpha"]),
                        tuple(float(b) for b in s["beta"])) for s in d["subsystems"]]
        weights = np.asarray(d["weights"], dtype=float)
        if weights.ndim != 1:
            raise ValueError(f"weights must be a list of numbers, got shape {weights.shape}")
        level, decay = float(d["level"]), float(d["decay"])
        dbox = np.asarray(d["domain_box"], dtype=float)
        assumptions = [str(a) for a in d["assumptions"]]
    except (KeyError, TypeError, ValueError) as err:
        raise ConfigError(f"malformed compositional certificate {path}: {type(err).__name__}: "
                          f"{err}; rerun the command that wrote it") from None
    sysm, refusal = bound_system(d, path, system, allow_factory)

    def result(ok, reason, checks=None):
        return CompositionalCertificate(
            CertStatus.CERTIFIED if ok else CertStatus.NOT_CERTIFIED, reason, name, pieces,
            weights, level, decay, dbox, checks or {}, assumptions)

    if d.get("status") != CertStatus.CERTIFIED.value:
        return result(False, f"the certificate does not claim a region ({d.get('status')!r})")
    if refusal:
        return result(False, refusal)
    if dbox.shape != sysm.state_box.shape or not np.array_equal(dbox, sysm.state_box):
        return result(False, "the certificate's domain box is not the system's state box")
    if assumptions != ASSUMPTIONS:
        return result(False, "the certificate lists other assumptions than this method's "
                      "(an edited certificate.json?); rerun the command that wrote it")
    ok, checks, why = check_compositional(sysm, pieces, weights, level, decay)
    return result(ok, why, checks)
