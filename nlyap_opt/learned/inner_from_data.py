r"""Condition (c) for an **unknown** f, proved from data and a declared second-derivative bound.

Condition (c) of the certificate needs an ellipse
:math:`E = \{x^\top P x \le c_q\} \supseteq B_\varepsilon` on which
:math:`V_q = x^\top P x` decreases along the *true* closed loop
:math:`g(x) = f(x, \kappa(x))`. With a model this is an interval check of the Jacobian
(:func:`nlyap_opt.certification.roa.certify_inner_ellipse`). Without one,
:func:`prove_inner_ellipse_from_data` proves it for **every** ``f`` that agrees with the data and
the user's declaration

.. math:: f \in C^2(X \times U), \quad
          |\partial^2 f_k / \partial z_i \partial z_j| \le H, \quad f(0, u_{eq}) = 0,

(``z = (x, u)``), so that the certificate rests on that declaration instead of the paper's
Assumption 3 (``B_ε`` in the LQR region of attraction).

The proof
---------
1. **Jacobian at the equilibrium.** Central differences of the samples (or of the black
   box) around :math:`z_{eq} = (0, u_{eq})` give :math:`\hat J = [\hat J_x\ \hat J_u]` with
   :math:`|J(z_{eq}) - \hat J| \le E` entrywise
   (:func:`systems.jacobian.jacobian_from_data`: Taylor with the Lagrange remainder,
   :math:`H(a^2 + b^2)/(2(a + b))`, plus noise and rounding). For a sample file whose rows
   are off the regular nodes (``offset > 0``) the declared Lipschitz constant adds
   :math:`2 K_k\,\text{offset}/(a + b)`. Components known exactly (``system.known_rhs``)
   are differentiated symbolically instead (no error but rounding).
2. **Closed-loop linear part.** :math:`J_g(0) = J_x + J_u J_\kappa(0)`;
   :math:`J_\kappa(0)` is enclosed by outward-rounded interval arithmetic on the
   controller's CasADi graph, and :math:`G = \hat J_x + \hat J_u J_\kappa(0)` by an
   outward-rounded interval matrix product; :math:`G` is its midpoint and
   :math:`|J_g(0) - G| \le D = E_x + E_u |J_\kappa(0)| + \mathrm{rad}` entrywise.
3. **Remainder.** :math:`g(x) = J_g(0)x + R(x)`,
   :math:`R_k(x) = \int_0^1 (1 - s)\,D^2 g_k(sx)[x, x]\,ds`, and
   :math:`D^2 g_k[v, v] = D^2 f_k[w, w] + \sum_j \partial_{u_j} f_k\, D^2\kappa_j[v, v]` with
   :math:`w = (v, J_\kappa v)`. Bounds over the box :math:`[-\rho, \rho]^n \supseteq E`:
   :math:`|D^2 f_k[w, w]| \le H \|w\|_1^2 \le H a^2 \|v\|^2` with
   :math:`a = \sqrt n + \sum_j \sup\|\nabla\kappa_j\|_2` (:math:`a = \sqrt n` under a
   declared control-affine ``B``: then :math:`\partial^2 f/\partial u\,\partial\cdot = 0`);
   :math:`|\partial_{u_j} f_k(z)| \le |\hat J_{u,kj}| + E_{u,kj} + H\|z - z_{eq}\|_1`
   (mean value theorem; exactly :math:`|B_{kj}|` under a declared ``B``);
   :math:`|D^2\kappa_j[v, v]| \le \|\,|\nabla^2\kappa_j|\,\|_F \|v\|^2` from the interval
   Hessian of the controller. So :math:`\|R(x)\|_2 \le \tfrac12 H_g \|x\|^2` with
   :math:`H_g = \|(h_k)_k\|_2`; a known component uses the interval Hessian of its own
   expression.
4. **Decrease.** :math:`\dot V_q = x^\top(PJ_g(0) + J_g(0)^\top P)x + 2x^\top P R(x)`.
   Linear part: :math:`x^\top(PJ_g(0) + J_g(0)^\top P)x \le -\lambda\|x\|^2` with
   :math:`\lambda = \lambda_{\min}(-(PG + G^\top P)) - 2\min(\|P\|_2\|D\|_2,
   \|\,|P|D\,\|_F)` (Weyl; :math:`\|P\Delta\|_2 \le \|\,|P|D\,\|_F` for
   :math:`|\Delta| \le D`). Remainder on :math:`E` (Cauchy–Schwarz in the ``P`` inner
   product, :math:`|R_k| \le \tfrac12 h_k\|x\|^2`):
   :math:`2x^\top P R \le 2\sqrt{x^\top Px}\sqrt{R^\top PR} \le \sqrt{c_q}\,w\,\|x\|^2`
   with :math:`w = \min(\sqrt{\lambda_{\max}(P)}H_g, \sqrt{h^\top|P|h})` (the second
   form is much smaller when the learned rows carry little weight in ``P``). So
   :math:`\dot V_q < 0` on :math:`E \setminus \{0\}` when :math:`\lambda > \sqrt{c_q}\,w`;
   with :math:`c_q = \lambda_{\max}(P)\varepsilon^2` (so :math:`B_\varepsilon \subseteq E`)
   the proof holds for :math:`\varepsilon < \lambda / (\sqrt{\lambda_{\max}(P)}\,w)`
   (``terms["inner_max"]``) — sharper than the ball form
   :math:`\lambda > 2\|P\|(\|\Delta J\| + \tfrac12 H_g\rho)` (docs/method.md). The derivative
   bounds of step 3 are taken over a box containing ``E`` (half-widths
   :math:`\sqrt{c_q (P^{-1})_{ii}}`, with a verified bound of the inverse's diagonal), which
   must lie in ``X``, and :math:`\kappa` must map it into ``U`` (the declaration holds on
   :math:`X \times U`).
5. **Optional: the learned φ on the rest.** The remainder grows with the radius, so the
   data alone prove (c) only for small ε (the black-box pendulum with H = 26: ε ≤ 0.018).
   Given a learned ``φ`` with ``‖f − φ‖₂ ≤ η`` on a box, the data prove the decrease on a
   small ellipse :math:`E_s = \{x^\top P x \le c_s\}` and the interval verifier proves
   :math:`2x^\top P\varphi(x, \kappa(x)) + \eta\|(2Px)_L\|_2 < 0` (``L``: φ's learned
   components, :func:`nlyap_opt.kernel.symbolic.robust_lie`) on
   :math:`c_s \le x^\top P x \le c_q` (Cauchy–Schwarz: then :math:`2x^\top P f < 0` there),
   with the same ``P``: together :math:`\dot V_q < 0` on :math:`E \setminus \{0\}`. This
   needs η below about :math:`\varepsilon_s / (2\lambda_{\max}(P))`.

Rounding: every bound is computed upward (``nextafter`` after each step, relative
allowances :math:`4(n + 2)u` on sums and products); matrix products in float64 carry the
standard :math:`\gamma_n |A||B|` error term; eigenvalues of the symmetric matrices come from
``numpy.linalg.eigvalsh`` widened by :math:`10^{-12}\|S\|_F` (LAPACK's backward error is a
small multiple of :math:`n u \|S\|_2`) plus Weyl's bound for the rounding of ``S`` itself;
interval enclosures of CasADi derivative graphs are widened by a relative :math:`2^{-30}`
(constant folding, as in :mod:`nlyap_opt.learned.interval_sup`); the final inequality is checked
with a relative safety factor :math:`10^{-9}`.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from systems.jacobian import jacobian_from_data
from verification import VerificationProblem
from verification.interval import Interval, IntervalArithmetic

from ..design.control import InnerStatus, ellipse_candidates
from ..distributed import parallel
from ..kernel.errors import DimensionError, InputRangeError
from ..kernel.network import Network
from ..kernel.rounding import FOLD, U, dn_rel, gamma, up_rel
from ..kernel.symbolic import closed_loop, learned_components_of, robust_lie
from ..kernel.walker import CHECKED_OPS, evaluate
from .bounds import check_input_range

__all__ = ["prove_inner_ellipse_from_data", "SAFETY"]

#: relative safety factor of the final strict inequality λ > ‖P‖·H_g·ρ
SAFETY = 1e-9
_EIG = 1e-12         # relative (to ‖S‖_F) allowance on eigvalsh
_SMOOTH = ("tanh", "linear", "sigmoid")


# ============================================================================ rounding helpers
def _fro_up(M) -> float:
    """Upper bound of the Frobenius norm (hence of the spectral norm) of ``M``."""
    M = np.abs(np.asarray(M, dtype=float))
    s = float(np.sum(M * M)) * (1.0 + 2.0 * (M.size + 2) * U)
    return up_rel(np.sqrt(s), 8)


def _matmul_err(A, B) -> np.ndarray:
    """Entrywise bound of ``|fl(A @ B) − A @ B|`` (recursive summation, any order)."""
    k = np.asarray(A).shape[-1]
    g = gamma(k + 2)
    return up_rel(g * (np.abs(A) @ np.abs(B)), 8) + 1e-300


def _pt_times_iv(A, L, Ub):
    """Enclosure ``[lo, hi]`` of ``A @ X`` for every ``L ≤ X ≤ Ub`` (``A`` a point matrix)."""
    A = np.asarray(A, dtype=float)
    p1 = A[:, :, None] * L[None, :, :]
    p2 = A[:, :, None] * Ub[None, :, :]
    lo_t, hi_t = np.minimum(p1, p2), np.maximum(p1, p2)
    k = A.shape[1]
    g = 2.0 * (k + 2) * U
    mag = np.sum(np.maximum(np.abs(lo_t), np.abs(hi_t)), axis=1)
    lo = np.sum(lo_t, axis=1) - g * mag - 1e-300
    hi = np.sum(hi_t, axis=1) + g * mag + 1e-300
    return np.nextafter(lo, -np.inf), np.nextafter(hi, np.inf)


def _eig_bounds(S) -> tuple[float, float]:
    """``(lower bound of λ_min, upper bound of λ_max)`` of a symmetric ``S``.

    ``eigvalsh`` widened by ``1e-12·‖S‖_F`` (LAPACK's symmetric eigensolvers are backward
    stable: each computed eigenvalue is within a small multiple of ``n·u·‖S‖₂`` of the true
    one; the allowance covers that for any ``n`` up to thousands).
    """
    S = np.asarray(S, dtype=float)
    lam = np.linalg.eigvalsh(S)
    m = up_rel(_EIG * _fro_up(S), 8) + 1e-300
    return dn_rel(float(lam[0]) - m, 8), -dn_rel(-(float(lam[-1]) + m), 8)


def _ellipse_box(P, c) -> np.ndarray:
    """Half-widths ``a`` with ``{xᵀPx ≤ c} ⊆ [−a, a]``: ``a_i² = c·(P⁻¹)_ii``, bounded upward.

    ``(P⁻¹)_ii ≤ Y_ii + ‖Y‖_F r/(1 − r)`` for the float inverse ``Y`` and ``r ≥ ‖I − PY‖₂``
    (Neumann series; ``r`` includes the rounding of ``PY``); ``inf`` if ``r ≥ 1/2``.
    """
    P = np.asarray(P, dtype=float)
    n = P.shape[0]
    try:
        Y = np.linalg.inv(P)
    except np.linalg.LinAlgError:
        return np.full(n, np.inf)
    r = up_rel(_fro_up(np.eye(n) - P @ Y) + _fro_up(_matmul_err(P, Y)), 8)
    if not r < 0.5:
        return np.full(n, np.inf)
    err = up_rel(_fro_up(Y) * up_rel(r / (1.0 - r) * (1 + 4 * U), 8), 8)
    d = np.diag(Y) + err
    if np.any(d <= 0):
        return np.full(n, np.inf)
    return up_rel(np.sqrt(up_rel(float(c) * up_rel(d, 8), 8)), 8)


def _smooth_expression(fun: ca.Function) -> bool:
    """True when every operation of an SX Function is smooth and defined on all reals."""

    return not any(fun.instruction_id(k) in CHECKED_OPS for k in range(fun.n_instructions()))


def _enclose(fun: ca.Function, lo, hi) -> list[tuple[np.ndarray, np.ndarray]]:
    """Dense outward enclosures ``(L, Ub)`` of every output of ``fun`` over the box [lo, hi]."""

    outs = evaluate(fun, [Interval(np.asarray(lo, float)[None], np.asarray(hi, float)[None])],
                    IntervalArithmetic())
    res = []
    for j, o in enumerate(outs):
        sp = fun.sparsity_out(j)
        r, c = (np.asarray(v, dtype=np.intp) for v in sp.get_triplet())
        L, Ub = np.zeros(sp.shape), np.zeros(sp.shape)
        nnz = sp.nnz()  # a constant output may come without the batch axis: broadcast
        ol = np.broadcast_to(np.asarray(o.lo, dtype=float), (1, nnz))[0]
        oh = np.broadcast_to(np.asarray(o.hi, dtype=float), (1, nnz))[0]
        ol = np.where(np.isnan(ol), -np.inf, ol)
        oh = np.where(np.isnan(oh), np.inf, oh)
        L[r, c] = np.nextafter(ol - np.abs(ol) * FOLD, -np.inf)
        Ub[r, c] = np.nextafter(oh + np.abs(oh) * FOLD, np.inf)
        res.append((L, Ub))
    return res


def _mag(L, Ub):
    return np.maximum(np.abs(L), np.abs(Ub))


# ============================================================================ the proof
def _fail(status: str, n: int, verdict: InnerStatus = InnerStatus.NOT_PROVED,
          **extra) -> dict:
    out = {"status": status, "verdict": verdict, "P": np.eye(n), "level": 0.0,
           "box": np.zeros(n), "result": None, "proved_from": None}
    out.update(extra)
    return out


def _controller_parts(system, controller):
    """SX functions of the controller: κ, J_κ, the Hessians of each κ_j (stacked rows)."""
    n, m = system.nx, system.nu
    x = ca.SX.sym("x", n)
    k = controller.casadi(x) if m else ca.SX(0, 1)
    Jk = ca.jacobian(k, x) if m else ca.SX(0, n)
    Hk = ca.vertcat(*[ca.hessian(k[j], x)[0] for j in range(m)]) if m else ca.SX(0, n)
    return x, k, Jk, Hk


def prove_inner_ellipse_from_data(system, controller: Network | None, inner: float, *,
                                  jac=None, P=None, dynamics: Network | None = None,
                                  eta: float | None = None, eta_state_box=None,
                                  eta_input_box=None, verify_options: dict | None = None
                                  ) -> dict:
    r"""Prove condition (c) for every ``f`` consistent with the data and the declared ``H``.

    Parameters
    ----------
    system : systems.System
        Any kind; ``system.declarations.hessian`` (``H``) must be declared (a
        ``"model"`` system is treated as a black box: only its values are used).
    controller : Network or None
        ``κ`` (``C·tanh(Kx + b)`` or any network with smooth activations); ``None`` for an
        autonomous system (``nu = 0``). ``κ(0) = u_eq`` must hold exactly.
    inner : float
        The radius ε of the inner ball ``B_ε ⊆ E``.
    jac : systems.JacobianBound, optional
        From :func:`systems.jacobian.jacobian_from_data` (computed when omitted).
    P : (nx, nx) array_like, optional
        The quadratic form; by default the candidates of
        :func:`nlyap_opt.design.control.ellipse_candidates` for ``G`` (as
        :func:`nlyap_opt.certification.roa.certify_inner_ellipse`); the first one that proves is
        returned.
    dynamics, eta : Network, float, optional
        A learned ``φ`` with its bound ``‖f − φ‖₂ ≤ η`` (on ``eta_state_box`` ×
        ``eta_input_box``, default the system's boxes). When the data alone prove (c) only
        on a smaller ellipse ``E_s = {xᵀPx ≤ c_s}`` (the remainder term grows with the
        radius), the rest ``c_s ≤ xᵀPx ≤ c_q`` is verified by the interval verifier on
        ``2xᵀPφ(x, κ(x)) + η‖2Px‖₂ < 0`` (Cauchy–Schwarz: then ``2xᵀPf < 0``), with
        ``κ(E) ⊆ U`` and ``E`` inside the box of η checked. Both parts use the same ``P``.
    verify_options : dict, optional
        Options of :func:`verification.verify` for that part.

    Returns
    -------
    dict
        The keys of :func:`nlyap_opt.certification.roa.certify_inner_ellipse`: ``status``
        (``"certified"``, or ``"not proved: …"`` / ``"not available: …"`` with the reason
        and, where it helps, the radius that would work), ``P``, ``level`` (``c_q``),
        ``box`` (half-widths of a box containing ``E``), ``result`` (``None``); and
        ``proved_from`` (the assumptions the proof rests on, one sentence), ``assumptions``
        (list), ``terms`` (every number of the inequality: ``lambda``, ``P_norm``,
        ``H_g``, ``rho``, ``rho_max``, ``DeltaJ_norm``, ...), ``jacobian``
        (``JacobianBound.to_dict()``).

    Notes
    -----
    See the module docstring for the proof and its rounding. A declared ``H`` below the
    truth gives a proof about the functions the declaration describes, not about the real
    plant: :func:`systems.declarations.check_declarations` refuses an ``H`` that the samples
    contradict (the dynamics stage runs it), but no check can confirm a declaration.
    """
    n, m = system.nx, system.nu
    inner = float(inner)
    if not (np.isfinite(inner) and inner > 0):
        return _fail(f"not proved: the inner radius must be positive, got {inner}", n)
    decl = getattr(system, "declarations", None)
    H = None if decl is None else decl.hessian_max()
    if H is None:
        return _fail("not available: condition (c) from data needs a declared second-"
                     "derivative bound (declare hessian H); it rests on the paper's "
                     "assumption otherwise", n)
    H = float(H)
    if m and controller is None:
        return _fail("not proved: a system with inputs needs the controller κ", n)
    if controller is not None:
        if controller.n_in != n or controller.n_out != m:
            raise DimensionError(
                f"controller maps R^{controller.n_in} -> R^{controller.n_out}; system "
                f"{system.name!r} needs R^{n} -> R^{m}")
        acts = [layer.activation for layer in controller.layers]
        if any(a not in _SMOOTH for a in acts) or controller.head is not None:
            return _fail(f"not proved: the controller must be C² (activations {acts}; "
                         f"smooth ones: {', '.join(_SMOOTH)})", n)
    if jac is None:
        jac = jacobian_from_data(system)
    J_hat = np.asarray(jac.J, dtype=float)
    E = np.asarray(jac.error, dtype=float)
    if J_hat.shape != (n, n + m) or E.shape != (n, n + m):
        raise DimensionError(f"jac.J and jac.error must have shape ({n}, {n + m}), got "
                             f"{J_hat.shape} and {E.shape}")
    if float(jac.hessian) != H:
        return _fail(f"not proved: the Jacobian bound rests on H = {jac.hessian}, the system "
                     f"declares H = {H}; recompute it (jacobian_from_data)", n)
    assumptions = list(system.describe_assumptions()) if hasattr(
        system, "describe_assumptions") else []
    # sample rows off the regular nodes: the difference quotient sees f(row), not f(node)
    smp = getattr(system, "samples", None)
    offset = float(getattr(smp, "offset", 0.0) or 0.0) if getattr(
        system, "kind", "") == "samples" else 0.0
    if offset > 0:
        K = None if decl.lipschitz is None else (
            np.asarray(decl.lipschitz, dtype=float) if isinstance(decl.lipschitz, tuple)
            else np.full(n, float(decl.lipschitz)))
        if K is None:
            return _fail(f"not proved: the sample file's rows are up to {offset:.3g} off the "
                         "regular nodes; declare lipschitz (K_f) to bound what that does to "
                         "the finite differences, or write the file with 17 digits", n)
        steps = np.asarray(jac.steps, dtype=float)
        width = np.sum(steps, axis=1) * (1 - 4 * U)
        for i in range(n + m):
            if width[i] > 0:
                E[:, i] = up_rel(E[:, i] + up_rel(2.0 * K * offset / width[i], 8), 8)

    # ---- the controller: κ(0) = u_eq exactly, J_κ(0) enclosed
    x, ksym, Jk, Hk = _controller_parts(system, controller)
    F0 = ca.Function("k0", [x], [ca.densify(ksym), ca.densify(Jk)])
    zero = np.zeros(n)
    (k0L, k0U), (JK0L, JK0U) = _enclose(F0, zero, zero) if m else (
        (np.zeros((0, 1)), np.zeros((0, 1))), (np.zeros((0, n)), np.zeros((0, n))))
    if m:
        k0 = np.asarray(controller.numpy(zero[None]), dtype=float).ravel()
        exact = _kappa0_exact(controller, system.u_eq)
        if not exact:
            dev = float(np.max(np.abs(k0 - system.u_eq)))
            return _fail(
                f"not proved: κ(0) = {k0.tolist()} equals u_eq = {system.u_eq.tolist()} only "
                f"up to rounding (|κ(0) − u_eq| ≈ {dev:.2g}); the true closed loop's "
                "equilibrium is then not exactly x = 0 (use u_eq = 0 with a zero controller "
                "bias, or a controller u_eq − Kx)", n)

    # ---- closed-loop linear part G and its error D (learned rows from data)
    known = {int(i): e for i, e in (system.known_rhs.items() if hasattr(system, "known_rhs")
                                     else {}.items())}
    Jx, Ju = J_hat[:, :n], J_hat[:, n:]
    Ex, Eu = E[:, :n], E[:, n:]
    if m:
        pl, ph = _pt_times_iv(Ju, JK0L, JK0U)
        GL = np.nextafter(Jx + pl - np.abs(Jx + pl) * 2 * U, -np.inf)
        GU = np.nextafter(Jx + ph + np.abs(Jx + ph) * 2 * U, np.inf)
        D = up_rel(Ex + up_rel(Eu @ _mag(JK0L, JK0U), 8) + _matmul_err(Eu, _mag(JK0L, JK0U)), 8)
    else:
        GL, GU, D = Jx.copy(), Jx.copy(), up_rel(Ex, 8)
    # known components: exact symbolic derivatives of g_k(x) = known_k(x, κ(x))
    known_parts = {}
    # only smooth, total expressions (a jump has CasADi derivative 0, which would hide it)
    if known:
        smooth = {}
        for i, e in known.items():
            e = ca.SX(e)
            if _smooth_expression(ca.Function("e", [system.x, system.u], [e])):
                smooth[i] = e
        known = smooth
    if known:
        gk = ca.vertcat(*[ca.substitute(e, ca.vertcat(system.x, system.u),
                                        ca.vertcat(x, ksym)) for e in known.values()])
        Jg = ca.jacobian(gk, x)
        Fk0 = ca.Function("gk0", [x], [ca.densify(Jg)])
        (KL, KU), = _enclose(Fk0, zero, zero)
        Hg_rows = ca.vertcat(*[ca.densify(ca.hessian(gk[r], x)[0]) for r in range(gk.shape[0])])
        known_parts = {"rows": list(known), "Hfun": ca.Function("gkH", [x], [Hg_rows])}
        for r, i in enumerate(known):
            GL[i], GU[i] = KL[r], KU[r]
            D[i] = 0.0
    G = 0.5 * (GL + GU)
    D = up_rel(D + np.maximum(G - GL, GU - G), 8)
    D_norm = _fro_up(D)
    if not np.all(np.isfinite(G)) or not np.all(np.isfinite(D)):
        return _fail("not proved: the closed-loop Jacobian enclosure is not finite", n)
    if np.max(np.linalg.eigvals(G).real) >= 0:
        return _fail(f"not proved: the estimated closed-loop Jacobian Ĵ_g is not Hurwitz "
                     f"(eigenvalues {np.round(np.linalg.eigvals(G), 6).tolist()})", n,
                     InnerStatus.NOT_HURWITZ, terms={"G": G.tolist(), "D": D.tolist()})

    if P is not None:
        candidates = [np.asarray(P, dtype=float)]
    else:
        candidates = list(ellipse_candidates(G))  # iterated twice below
    ctx = {"system": system, "controller": controller, "x": x, "Jk": Jk, "Hk": Hk,
           "k": ksym, "H": H, "G": G, "D": D, "D_norm": D_norm, "J_hat": J_hat, "E": E,
           "known": known_parts, "inner": inner}
    best = None
    for Pc in candidates:
        out = _check(Pc, ctx)
        if out["verdict"] is InnerStatus.CERTIFIED:
            best = out
            break
        if best is None or out["terms"].get("inner_max", 0.0) > \
                best["terms"].get("inner_max", 0.0):
            best = out
    if best["verdict"] is not InnerStatus.CERTIFIED and dynamics is not None \
            and eta is not None:
        first = None
        for Pc in candidates:
            ext = _extend_with_phi(Pc, ctx, dynamics, float(eta), eta_state_box,
                                   eta_input_box, verify_options)
            if ext is not None and ext["verdict"] is InnerStatus.CERTIFIED:
                best = ext
                break
            first = first or ext
        else:
            if first is not None:
                best["phi_part"] = first.get("phi_part")
                best["status"] += ("; with the learned φ on the rest: "
                                   + first["status"].removeprefix("not proved: "))
            else:
                best["status"] += "; the learned φ cannot help (the linear part fails)"
    B_declared = decl.input_matrix is not None and m > 0
    best["proved_from"] = (
        f"samples and the declared second-derivative bound H = {H:.6g}"
        + (" and the declared input matrix B" if B_declared else "")
        + (f" and the declared Lipschitz constant (sample offset {offset:.3g})"
           if offset > 0 else "")
        + f" (f(0, u_eq) = 0 declared; Jacobian from {jac.source})"
        + (f"; outside the inner ellipse x'Px ≤ {best['phi_part']['inner_level']:.4g}: the "
           f"learned φ with ‖f − φ‖ ≤ η = {best['phi_part']['eta']:.4g} (interval verifier)"
           if best["verdict"] is InnerStatus.CERTIFIED and best.get("phi_part") else ""))
    best["assumptions"] = assumptions
    best["jacobian"] = jac.to_dict()
    best["inner"] = inner
    return best


def _kappa0_exact(controller: Network, u_eq) -> bool:
    """True when the real-valued ``κ(0)`` provably equals ``u_eq``.

    Exact cases: ``u_eq = 0`` with every bias zero and every activation mapping 0 to 0
    (tanh, linear); or one linear layer with output scale 1 and bias ``u_eq``. Otherwise
    ``κ(0) = C·tanh(b)`` equals ``u_eq`` only up to rounding, and the true closed loop's
    equilibrium is not exactly 0.
    """
    u_eq = np.asarray(u_eq, dtype=float).ravel()
    layers = controller.layers
    scale = np.broadcast_to(controller.output_scale, (controller.n_out,))
    if np.all(u_eq == 0) and all(np.all(layer.bias == 0) and layer.activation in
                                 ("tanh", "linear") for layer in layers):
        return True
    if len(layers) == 1 and layers[0].activation == "linear" and np.all(scale == 1.0):
        return bool(np.array_equal(layers[0].bias, u_eq))
    return False


def _check(P, ctx) -> dict:
    """The inequality of step 4 for one ``P``."""
    system = ctx["system"]
    n, m = system.nx, system.nu
    H, G, D_norm = ctx["H"], ctx["G"], ctx["D_norm"]
    P = np.asarray(P, dtype=float)
    if P.shape != (n, n) or not np.all(np.isfinite(P)):
        raise DimensionError(f"P must be a finite ({n}, {n}) matrix, got shape {P.shape}")
    P = np.triu(P) + np.triu(P, 1).T  # exactly symmetric
    pmin, pmax = _eig_bounds(P)
    terms: dict = {"G": G.tolist(), "D": ctx["D"].tolist(), "DeltaJ_norm": D_norm}
    if not pmin > 0:
        return {"status": "not proved: P is not positive definite",
                "verdict": InnerStatus.NOT_PROVED, "P": P, "level": 0.0,
                "box": np.zeros(n), "result": None, "terms": terms}
    P_norm = pmax
    eps = ctx["inner"]
    c_q = up_rel(pmax * up_rel(eps * eps, 8), 8)
    rho = up_rel(np.sqrt(up_rel(c_q / pmin, 8)), 8)
    terms.update({"P_norm": P_norm, "lambda_min_P": pmin, "rho": rho, "level": c_q})
    box = np.minimum(_ellipse_box(P, c_q), rho)     # E ⊆ [−box, box]
    # λ = λ_min(−(PG + GᵀP)) − ‖S − fl(S)‖ − 2‖PΔ‖, ‖PΔ‖₂ ≤ min(‖P‖‖D‖, ‖|P|D‖_F)
    PG = P @ G
    S = -(PG + PG.T)
    s_err = _fro_up(2.0 * _matmul_err(P, G) + up_rel(np.abs(S) * U, 8))
    s_min, _ = _eig_bounds(S)
    D = np.asarray(ctx["D"], dtype=float)
    PD = _fro_up(up_rel(np.abs(P) @ D, 8) + _matmul_err(np.abs(P), D))
    lin = up_rel(2.0 * min(up_rel(P_norm * D_norm, 8), PD), 8)
    lam = dn_rel(s_min - up_rel(s_err + lin, 8), 8)
    terms.update({"lambda_S": s_min, "lambda": lam, "linear_error": lin})
    out = {"verdict": InnerStatus.NOT_PROVED, "P": P, "level": c_q, "box": box,
           "result": None, "terms": terms}
    if not lam > 0:
        out["status"] = (
            f"not proved: the linear part is not certified: λ_min(−(PĴ_g + Ĵ_gᵀP)) = "
            f"{s_min:.4g} does not exceed 2‖PΔJ‖ ≤ {lin:.4g} (‖ΔJ‖ ≤ "
            f"{D_norm:.3g} from the finite-difference error with H = {H:.4g}); sample more "
            "finely around the equilibrium or declare a smaller (true) H")
        terms["inner_max"] = terms["rho_max"] = 0.0
        return out
    # E inside the sampling box: states, and κ(E's box) inside U
    X = np.asarray(system.state_box, dtype=float)
    if np.any(-box < X[:, 0]) or np.any(box > X[:, 1]):
        out["status"] = (f"not proved: the ellipse's box ±{np.round(box, 4).tolist()} leaves the "
                         f"state box {X.tolist()} on which H is declared; use a smaller inner "
                         "radius")
        terms["inner_max"] = terms["rho_max"] = 0.0
        return out
    lo, hi = -box, box
    if m:
        F = ca.Function("kb", [ctx["x"]], [ca.densify(ctx["k"]), ca.densify(ctx["Jk"]),
                                           ca.densify(ctx["Hk"])])
        (kL, kU), (JL, JU), (HL, HU) = _enclose(F, lo, hi)
        Ubox = np.asarray(system.input_box, dtype=float)
        if np.any(kL[:, 0] < Ubox[:, 0]) or np.any(kU[:, 0] > Ubox[:, 1]):
            out["status"] = (f"not proved: κ on the ellipse's box ranges over "
                             f"{np.stack([kL[:, 0], kU[:, 0]], 1).tolist()}, not inside the "
                             f"input box {Ubox.tolist()} on which H is declared")
            terms["inner_max"] = terms["rho_max"] = 0.0
            return out
        Jmag = _mag(JL, JU)                               # (m, n)
        c2 = np.array([_fro_up(_mag(HL[j * n:(j + 1) * n], HU[j * n:(j + 1) * n]))
                       for j in range(m)])                # |D²κ_j[v,v]| ≤ c2_j ‖v‖²
        dk = _mag(kL[:, 0] - system.u_eq, kU[:, 0] - system.u_eq)
        decl = system.declarations
        if decl.input_matrix is not None:                 # f = f0(x) + B u
            a2 = float(n)
            Fu = np.abs(decl.B)
        else:
            a = up_rel(np.sqrt(n) * (1 + 4 * U) + up_rel(np.sum([_fro_up(r) for r in Jmag]), 8), 8)
            a2 = up_rel(a * a, 8)
            r1 = up_rel(up_rel(np.sqrt(n) * rho, 8) + up_rel(np.sum(dk), 8), 8)
            Fu = up_rel(np.abs(ctx["J_hat"][:, n:]) + ctx["E"][:, n:] + up_rel(H * r1, 8), 8)
            if decl.lipschitz is not None:                # |∂f_k/∂u_j| ≤ ‖row k of J‖ ≤ K_k
                K = np.asarray(decl.lipschitz, dtype=float) if isinstance(
                    decl.lipschitz, tuple) else np.full(n, float(decl.lipschitz))
                Fu = np.minimum(Fu, K[:, None])
        h = up_rel(up_rel(H * a2, 8) + up_rel(Fu @ c2, 8) + _matmul_err(Fu, c2[:, None])[:, 0], 8)
        terms.update({"kappa_range": np.stack([kL[:, 0], kU[:, 0]], 1).tolist(),
                      "kappa_hessian_bound": c2.tolist(), "a_squared": a2})
    else:
        h = np.full(n, up_rel(H * float(n), 8))
    known = ctx["known"]
    if known:
        (KHL, KHU), = _enclose(known["Hfun"], lo, hi)
        for r, i in enumerate(known["rows"]):
            h[i] = _fro_up(_mag(KHL[r * n:(r + 1) * n], KHU[r * n:(r + 1) * n]))
    h = np.asarray(h, dtype=float)
    H_g = _fro_up(h)
    # 2xᵀPR ≤ 2 sqrt(xᵀPx)·sqrt(RᵀPR) on E, |R_k| ≤ ½h_k‖x‖²: RᵀPR ≤ ¼‖x‖⁴·min(λ_max(P)‖h‖²,
    # hᵀ|P|h); so 2xᵀPR ≤ sqrt(c_q)·w·‖x‖² with w = min(sqrt(λ_max(P))·H_g, sqrt(hᵀ|P|h))
    Ph = up_rel(np.abs(P) @ h, 8) + _matmul_err(np.abs(P), h[:, None])[:, 0]
    hPh = up_rel(float(h @ Ph) + float(_matmul_err(h[None, :], Ph[:, None])[0, 0]), 8)
    w = min(up_rel(up_rel(np.sqrt(pmax), 8) * H_g, 8), up_rel(np.sqrt(hPh), 8))
    need = up_rel(up_rel(np.sqrt(c_q), 8) * w, 8)
    inner_max = lam / up_rel(up_rel(np.sqrt(pmax), 8) * w, 8) if w > 0 else np.inf
    rho_max = inner_max * np.sqrt(pmax / pmin)  # the radius of E at ε = inner_max
    terms.update({"H": H, "h": h.tolist(), "H_g": H_g, "remainder_weight": w,
                  "remainder_coefficient": need, "inner_max": float(inner_max),
                  "rho_max": float(rho_max)})
    if lam > need * (1.0 + SAFETY):
        out["status"], out["verdict"] = "certified", InnerStatus.CERTIFIED
        return out
    out["verdict"] = InnerStatus.NOT_PROVED
    out["status"] = (
        f"not proved: the decrease λ‖x‖² (λ = {lam:.4g}) beats the remainder "
        f"2xᵀPR(x) ≤ sqrt(c_q)·w·‖x‖² (w = {w:.4g}, H_g = {H_g:.4g}, ‖P‖ = {P_norm:.4g}) only "
        f"for a level c_q = λ_max(P)·ε² with ε < {inner_max:.4g}: needs ρ ≤ {rho_max:.4g} "
        f"(radius of E), but E ⊇ B_ε reaches ρ = {rho:.4g} at ε = {eps:.4g}; use an inner "
        f"radius ε ≤ {inner_max:.4g} or declare a smaller (true) H")
    return out


def _extend_with_phi(P, ctx, dynamics, eta, eta_state_box, eta_input_box, verify_options):
    """The data proof on a small ellipse, the learned φ with η on the rest (same ``P``)."""

    system, controller = ctx["system"], ctx["controller"]
    if not (np.isfinite(eta) and eta >= 0):
        return None
    eps = ctx["inner"]
    big = _check(P, ctx)
    if not big["terms"].get("lambda", 0.0) > 0:
        return None                              # the linear part fails: nothing to extend
    # 1. the largest inner ellipse the data prove with this P (halving from ε)
    eps_s, small = eps, None
    for _ in range(60):
        im = big["terms"].get("inner_max", 0.0) if small is None else \
            small["terms"].get("inner_max", 0.0)
        eps_s = min(0.5 * eps_s, 0.9 * im) if im > 0 else 0.5 * eps_s
        small = _check(P, dict(ctx, inner=eps_s))
        if small["verdict"] is InnerStatus.CERTIFIED:
            break
        if not small["terms"].get("lambda", 0.0) > 0:
            return None
    else:
        return None
    P = big["P"]
    c_s, c_q = float(small["level"]), float(big["level"])
    a = np.asarray(big["box"], dtype=float)
    box = np.stack([-a, a], axis=1)
    phi_part = {"inner_level": c_s, "inner_radius": eps_s, "eta": eta, "level": c_q}
    out = {"verdict": InnerStatus.NOT_PROVED, "P": P, "level": c_q, "box": a, "result": None,
           "terms": dict(big["terms"], inner_part=small["terms"]), "phi_part": phi_part}
    X = np.asarray(system.state_box if eta_state_box is None else eta_state_box, dtype=float)
    if np.any(box[:, 0] < X[:, 0]) or np.any(box[:, 1] > X[:, 1]):
        out["status"] = (f"not proved: the ellipse's box ±{np.round(a, 4).tolist()} leaves the "
                         f"box {X.tolist()} on which η holds; use a smaller inner radius")
        return out
    if system.nu:
        Ubox = np.asarray(system.input_box if eta_input_box is None else eta_input_box,
                          dtype=float)
        try:
            check_input_range(controller, box, Ubox)
        except InputRangeError as exc:
            out["status"] = f"not proved: {exc}"
            return out
    cl = closed_loop(system, controller, dynamics, strict=False)
    x = cl.x
    Px = ca.mtimes(ca.DM(P), x)
    V = ca.dot(x, Px)
    lie = robust_lie(2.0 * ca.dot(Px, cl.rhs), V, x, up_rel(eta, 8),
                     components=learned_components_of(system, dynamics))
    prob = VerificationProblem(x, box, [c_s - V, V - c_q], [lie],
                               ["outside the data-proved ellipse", "inside E"],
                               ["2x'Pφ + η‖(2Px)_L‖ < 0"])
    res = parallel.check(prob, **(verify_options or {}))
    out["result"] = res
    phi_part["status"] = res.status
    out["verdict"] = InnerStatus.CERTIFIED if res.success else InnerStatus.NOT_PROVED
    out["status"] = "certified" if res.success else (
        f"not proved: the data prove (c) for ε ≤ {eps_s:.4g} only, and the learned φ with η = "
        f"{eta:.4g} leaves the rest {res.status}")
    return out
