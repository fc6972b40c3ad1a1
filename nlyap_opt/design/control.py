r"""The LQR start of the method (the control layer): LQR on the CasADi linearisation,
quadratic Lyapunov matrices, saturated controllers (``baselines.lqr`` re-exports them).

Convention: :math:`u = u_{eq} - K x`, with :math:`K = R^{-1} B^\top S` from the
continuous algebraic Riccati equation :math:`A^\top S + S A - S B R^{-1} B^\top S + Q = 0`.
The Lyapunov matrix :math:`P` solves :math:`A_{cl}^\top P + P A_{cl} = -Q_V` for the
closed loop :math:`A_{cl} = A - BK` (or :math:`A` for input-free systems).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from enum import Enum

import casadi as ca
import numpy as np
from scipy.linalg import solve_continuous_are, solve_continuous_lyapunov

from ..kernel import deps
from ..kernel.errors import (
    ConfigError,
    DimensionError,
    NotStabilizableError,
    raise_if_interrupted,
)
from ..kernel.network import Layer, Network
from ..kernel.symbolic import learned_rhs

__all__ = [
    "InnerStatus", "LQRResult", "ellipse_candidates", "verdict_of", "lqr", "linearisation",
    "lyapunov_matrix", "round_lyapunov_matrix", "saturated_controller", "volume_lyapunov_matrix",
    "domain_lyapunov_matrix", "polytopic_lyapunov_matrix",
    "linear_controller",
    "quadratic_lyapunov",
]


class InnerStatus(Enum):
    """The verdict on condition (c), the inner ellipse ``E ⊇ B_ε`` (a result's ``"verdict"``;
    its ``"status"`` says it in words)."""

    CERTIFIED = "certified"
    #: the verifier found a point of ``E`` where the claimed decrease fails
    COUNTEREXAMPLE = "counterexample"
    #: the closed loop's linearisation is not Hurwitz: no such ellipse exists
    NOT_HURWITZ = "not Hurwitz"
    #: undecided, or no form applies (no claim either way)
    NOT_PROVED = "not proved"
    #: no model to check it: the paper's assumption, unchecked
    ASSUMED = "assumed"


def verdict_of(query_status) -> InnerStatus:
    """The inner ellipse's verdict from the verifier's status of its check."""
    return {"verified": InnerStatus.CERTIFIED,
            "counterexample": InnerStatus.COUNTEREXAMPLE}.get(query_status,
                                                              InnerStatus.NOT_PROVED)


@dataclass
class LQRResult:
    """Result of :func:`lqr`.

    Attributes
    ----------
    K : (nu, nx) ndarray     gain, ``u = u_eq - K x`` (empty for input-free systems)
    S : (nx, nx) ndarray     Riccati solution (zeros for input-free systems)
    P : (nx, nx) ndarray     Lyapunov matrix of the closed loop, ``A_clᵀP + P A_cl = -I``
    eigenvalues : (nx,) complex ndarray   closed-loop eigenvalues
    A, B, Q, R : ndarray
    """

    K: np.ndarray
    S: np.ndarray
    P: np.ndarray
    eigenvalues: np.ndarray
    A: np.ndarray
    B: np.ndarray
    Q: np.ndarray
    R: np.ndarray

    def riccati_residual(self) -> float:
        """Max-abs residual of the Riccati equation (0 for input-free systems)."""
        if self.B.shape[1] == 0:
            return 0.0
        A, B, S, Q, R = self.A, self.B, self.S, self.Q, self.R
        res = A.T @ S + S @ A - S @ B @ np.linalg.solve(R, B.T @ S) + Q
        return float(np.max(np.abs(res)))

    def to_dict(self) -> dict:
        ev = self.eigenvalues
        return {"K": self.K.tolist(), "P": self.P.tolist(),
                "eigenvalues": [[float(e.real), float(e.imag)] for e in ev]}


def _matrix(M, n, what):
    """``M`` as a symmetric ``(n, n)`` float matrix (a scalar times the identity), else a
    :class:`ConfigError` naming ``what``."""
    try:
        M = np.atleast_2d(np.asarray(M, dtype=float))
    except (TypeError, ValueError):
        raise ConfigError(f"{what} must be a matrix of numbers (or a scalar), got "
                          f"{str(M)[:40]!r}; pass a numpy array or nested lists") from None
    if M.shape == (1, 1) and n > 1:
        M = M[0, 0] * np.eye(n)
    if M.shape != (n, n):
        raise DimensionError(f"{what} must be ({n}, {n}) (or a scalar), got {M.shape}")
    if not np.all(np.isfinite(M)):
        raise ConfigError(f"{what} has entries that are not finite (NaN or inf); pass finite "
                          "numbers")
    if not np.allclose(M, M.T):
        raise ConfigError(f"{what} must be symmetric; pass (M + Mᵀ)/2 if that is meant")
    return M


def _check_stabilisable(A, B):
    n = A.shape[0]
    for lam in np.linalg.eigvals(A):
        if lam.real >= 0:
            rank = np.linalg.matrix_rank(np.hstack([A - lam * np.eye(n), B.astype(complex)]),
                                         tol=1e-9)
            if rank < n:
                raise NotStabilizableError(
                    f"(A, B) is not stabilisable: the mode with eigenvalue {lam:.4g} cannot be "
                    "moved by the inputs (PBH test). Change the inputs or the model."
                )


def lyapunov_matrix(A_cl, Q=None) -> np.ndarray:
    """Solve ``A_clᵀ P + P A_cl = -Q`` (``Q = I`` by default) for a Hurwitz ``A_cl``.

    SciPy's Bartels-Stewart solver, called as python-control's ``lyap`` calls it without
    slycot (the same numbers; importing python-control costs about a CPU second per
    process, paid by every ``nlyap verify`` and every portfolio worker).
    """

    A_cl = np.asarray(A_cl, dtype=float)
    n = A_cl.shape[0]
    if np.max(np.linalg.eigvals(A_cl).real) >= 0:
        raise NotStabilizableError(
            f"A_cl is not Hurwitz (eigenvalues {np.linalg.eigvals(A_cl)}); no quadratic "
            "Lyapunov function exists"
        )
    Q = np.eye(n) if Q is None else _matrix(Q, n, "Q")
    P = solve_continuous_lyapunov(np.array(A_cl.T, ndmin=2), -np.array(Q, ndmin=2))
    return 0.5 * (P + P.T)


def _lqr(A, B, Q, R) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(K, S, E)``: gain, Riccati solution and closed-loop eigenvalues of the LQR.

    SciPy's Riccati solver and the gain ``R⁻¹BᵀS``, computed as python-control's ``lqr``
    does without slycot (the same numbers, without importing python-control).
    """
    A, B, Q, R = (np.array(M, ndmin=2, dtype=float) for M in (A, B, Q, R))
    S = solve_continuous_are(A, B, Q, R)
    K = np.linalg.solve(R, B.T @ S)
    E, _ = np.linalg.eig(A - B @ K)
    return K, S, E


def _positive_solution(problem, X) -> np.ndarray | None:
    """Solve ``problem`` with CLARABEL, else SCS (those installed), and return the symmetrised
    value of the matrix variable ``X`` from the first solve that gives a finite, positive
    definite one (``None``: none did; a failed solve only loses a candidate)."""
    cp = deps.cvxpy()
    installed = set(cp.installed_solvers())
    for solver in [s for s in ("CLARABEL", "SCS") if s in installed]:
        try:
            problem.solve(solver=solver)
        except Exception as exc:  # a failed solve only loses a candidate
            raise_if_interrupted(exc)
            continue
        if X.value is None:
            continue
        Xv = 0.5 * (X.value + X.value.T)
        if np.all(np.isfinite(Xv)) and np.linalg.eigvalsh(Xv)[0] > 0:
            return Xv
    return None


def round_lyapunov_matrix(A_cl, decay_fraction: float = 0.1) -> np.ndarray | None:
    r"""The Lyapunov matrix of ``A_cl`` with the smallest condition number (an SDP).

    Solves :math:`\min t` subject to :math:`I \preceq P \preceq tI` and
    :math:`A_{cl}^\top P + P A_{cl} \preceq -2\alpha P`, with :math:`\alpha` the fraction
    ``decay_fraction`` of the closed loop's stability margin :math:`\min_i -\mathrm{Re}\,
    \lambda_i`. The ellipse :math:`\{x^\top P x \le \lambda_{max} \varepsilon^2\}`
    that must contain :math:`B_\varepsilon` reaches :math:`\varepsilon
    \sqrt{\mathrm{cond}\,P}` from the origin, so a round ``P`` keeps condition (c)'s
    region small in many dimensions (cartpole: condition number 328 for the Lyapunov
    matrix of ``Q_V = I``, 60 here; planar quadrotor: 1194 and 71).

    Only a candidate: whatever ``P`` is returned, condition (c) is then *verified* with it.
    Returns ``None`` when ``A_cl`` is not Hurwitz or no SDP solver succeeds.
    """
    cp = deps.cvxpy()

    A_cl = np.asarray(A_cl, dtype=float)
    n = A_cl.shape[0]
    margin = -float(np.max(np.linalg.eigvals(A_cl).real))
    if not np.all(np.isfinite(A_cl)) or margin <= 0:
        return None
    P = cp.Variable((n, n), symmetric=True)
    t = cp.Variable()
    alpha = decay_fraction * margin
    cons = [P >> np.eye(n), P << t * np.eye(n), A_cl.T @ P + P @ A_cl + 2 * alpha * P << 0]
    return _positive_solution(cp.Problem(cp.Minimize(t), cons), P)


def volume_lyapunov_matrix(A_cl, decay_fraction: float = 0.1, *, rounds: int = 40,
                           tol: float = 1e-7) -> np.ndarray | None:
    r"""The Lyapunov matrix of ``A_cl`` whose ellipsoid inside the unit ball is largest.

    Among the ``P`` with :math:`P \succeq I` (the ellipsoid :math:`\{x^\top P x \le 1\}`
    lies in the unit ball) and :math:`A_{cl}^\top P + P A_{cl} \preceq -2\alpha P` (the
    decay rate ``α`` of :func:`round_lyapunov_matrix`), the one of least
    :math:`\log\det P`, i.e. of largest volume :math:`\mathrm{vol}(B)/\sqrt{\det P}`.
    :math:`\log\det` is concave, so each round minimises its tangent
    :math:`\mathrm{tr}(P_k^{-1} P)` (majorisation-minimisation): :math:`\log\det P_k`
    never increases, from the round matrix until it changes by less than ``tol``.

    The round matrix makes the ellipsoid's *axes* alike; the whole ball is a better guide:
    a quadratic V's certified set must lie in the domain, and only the directions the decay
    LMI pins need be thin (cartpole LQR loop: ellipsoid volume 0.47 in the unit ball
    against 0.155 for the round matrix; planar quadrotor 0.37 against 0.0022).

    Only a candidate: the certificate proves the decrease of ``xᵀPx`` on the nonlinear loop
    at a verified level. Returns ``None`` when ``A_cl`` is not Hurwitz or no SDP solver
    succeeds.
    """
    cp = deps.cvxpy()

    P = round_lyapunov_matrix(A_cl, decay_fraction)
    if P is None:
        return None
    A_cl = np.asarray(A_cl, dtype=float)
    n = A_cl.shape[0]
    alpha = decay_fraction * -float(np.max(np.linalg.eigvals(A_cl).real))
    X = cp.Variable((n, n), symmetric=True)
    cons = [X >> np.eye(n), A_cl.T @ X + X @ A_cl + 2 * alpha * X << 0]
    return _log_det_descent(X, cons, P / np.linalg.eigvalsh(P)[0], rounds=rounds, tol=tol)


def _log_det_descent(X, cons, start: np.ndarray | None = None, *, rounds: int,
                     tol: float = 0.0, solvers=("CLARABEL", "SCS")) -> np.ndarray | None:
    r"""The least :math:`\log\det X` over the constraints ``cons`` by its tangents: each round
    minimises :math:`\mathrm{tr}(X_k^{-1} X)` (majorisation-minimisation, ``X₀`` = ``start``,
    a feasible point, or the identity's tangent without one), and :math:`\log\det X_k`
    never increases; it stops when a round does not decrease it, decreases it by less than
    ``tol``, or no solver of ``solvers`` gives a finite, positive definite ``X``. Returns
    the last ``X_k`` (``start`` if no round improved it)."""
    cp = deps.cvxpy()
    installed = set(cp.installed_solvers())
    best = start
    logdet = np.linalg.slogdet(start)[1] if start is not None else np.inf
    # one problem with the tangent W as a parameter: cvxpy compiles it once
    # and each round only substitutes W
    W = cp.Parameter(X.shape)
    W.value = np.linalg.inv(start) if start is not None else np.eye(X.shape[0])
    prob = cp.Problem(cp.Minimize(cp.trace(W @ X)), cons)
    for _ in range(rounds):
        new = None
        for solver in [s for s in solvers if s in installed]:
            try:
                with warnings.catch_warnings():     # an inaccurate solve is only a candidate
                    warnings.simplefilter("ignore")
                    prob.solve(solver=solver)
            except Exception as exc:  # a failed solve only ends the descent
                raise_if_interrupted(exc)
                continue
            if X.value is not None and np.all(np.isfinite(X.value)):
                new = 0.5 * (X.value + X.value.T)
                break
        if new is None or np.linalg.eigvalsh(new)[0] <= 0:
            break
        new_logdet = np.linalg.slogdet(new)[1]
        if not new_logdet < logdet:
            break
        done = logdet - new_logdet < tol
        best, logdet, W.value = new, new_logdet, np.linalg.inv(new)
        if done:
            break
    return best


def domain_lyapunov_matrix(A_cl, decay_fraction: float = 0.1, *, inside=None,
                           half_widths=None) -> np.ndarray | None:
    r"""The Lyapunov matrix of ``A_cl`` whose ellipsoid inside the domain is largest.

    With :math:`Q = P^{-1}` (the ellipsoid :math:`\{x^\top P x \le 1\}` has the shape
    matrix ``Q``) the problem is convex: maximise :math:`\log\det Q` subject to
    :math:`A_{cl} Q + Q A_{cl}^\top \preceq -2\alpha Q` (the decay rate ``α`` of
    :func:`round_lyapunov_matrix`; equivalent to :math:`A_{cl}^\top P + P A_{cl} \preceq
    -2\alpha P`) and the ellipsoid in the domain: :math:`Q \preceq` ``inside`` (a ball of
    radius ``r``: :math:`r^2 I`; a centred ellipsoid :math:`x^\top E x \le 1`:
    :math:`E^{-1}`) and :math:`Q_{kk} \le h_k^2` for the box :math:`|x_k| \le h_k`
    (``half_widths``). Where :func:`volume_lyapunov_matrix` fits the ellipsoid to the unit
    ball, this one fits it to the domain's own shape (a long, thin box gets a long, thin
    ellipsoid).

    Only a candidate: the certificate proves the decrease of ``xᵀPx`` on the nonlinear loop
    at a verified level. Returns ``None`` when ``A_cl`` is not Hurwitz, no bound is given
    or no SDP solver succeeds.
    """
    cp = deps.cvxpy()

    A_cl = np.asarray(A_cl, dtype=float)
    n = A_cl.shape[0]
    margin = -float(np.max(np.linalg.eigvals(A_cl).real))
    if not np.all(np.isfinite(A_cl)) or margin <= 0 or (inside is None and half_widths is None):
        return None
    Q = cp.Variable((n, n), symmetric=True)
    alpha = decay_fraction * margin
    cons = [A_cl @ Q + Q @ A_cl.T + 2 * alpha * Q << 0]
    if inside is not None:
        cons.append(Q << np.asarray(inside, dtype=float))
    if half_widths is not None:
        cons += [Q[k, k] <= float(h) ** 2 for k, h in enumerate(half_widths)]
    Qv = _positive_solution(cp.Problem(cp.Maximize(cp.log_det(Q)), cons), Q)
    if Qv is None:
        return None
    P = np.linalg.inv(Qv)
    return 0.5 * (P + P.T)


def polytopic_lyapunov_matrix(corners, radius, *, half_widths, inner: float, eta: float = 0.0,
                              components=None, offset=None, constant: float = 0.0,
                              inside=None, gains=None, radii=None, slack: float = 1.02,
                              rounds: int = 8) -> np.ndarray | None:
    r"""A ``P`` whose whole ellipsoid ``{xᵀPx ≤ 1}`` passes the mean-value decrease test
    with the Jacobian in a polytope plus a remainder (an SDP, then its volume).

    The test (:class:`nlyap_opt.certification.roa.TaylorDecrease`) proves ``V̇ < 0`` (with
    learned dynamics the robust ``∇V·φ + η‖∇_L V‖ < 0``) on ``ε ≤ ‖y‖``, ``y`` in the box
    ``|y_k| ≤ h_k``, when for every corner ``J_v`` of the Jacobian's polytope and weights
    ``t, ν_b > 0``

    .. math:: -(PJ_v + J_v^\top P) - \sum_b \Big(\frac{p_b p_b^\top}{\nu_b} + \nu_b s_b\,
              \mathrm{diag}(R_b/h)\Big) - \Big(\frac{2b}{\varepsilon} +
              \frac{m}{\varepsilon^2} + \frac{\eta}{\varepsilon t}\Big) I -
              \frac{\eta t}{\varepsilon} P_L^\top P_L \succ 0

    (``R`` = ``radius``, ``s_b = Σ_c R_bc h_c``, ``p_b`` the columns of ``P``, ``b ≥ ‖P
    g(0)‖`` with ``offset`` = ``g(0)``, ``m`` = ``constant``). With ``τ = 1/t`` and Schur
    complements for the ``p_b p_bᵀ/ν_b`` and ``P_LᵀP_L`` terms this is linear in ``(P, ν, τ,
    b)``; it is solved in the coordinates ``z = y/h`` and time scaled by the largest entry
    of ``J_v`` (the same conditions, better conditioned numbers). The SDP adds: the
    ellipsoid inside the box (``(P⁻¹)_kk ≤ h_k²``), holding ``B_ε`` (``P ⪯ I/(1.03ε²)``),
    inside the domain (``P ⪰ 1.01·inside⁻¹``, ``inside`` the shape matrix of a ball or
    centred ellipsoid ``D``) and, for the rows ``w_i`` of ``gains``, ``|w_i x| ≤ ρ_i`` on it
    (``radii``: ``w_i P⁻¹ w_iᵀ ≤ ρ_i²``, the ranges the polytope was enclosed on); among
    those ``P`` it takes the largest volume by the tangents of ``log det P`` (as
    :func:`volume_lyapunov_matrix`).

    ``R``, ``η``, ``m`` and ``g(0)`` enter multiplied by ``slack``: the exact test chooses its
    own weights (in floats), and ``P`` is rounded to the stored network's floats.

    Only a candidate: the caller certifies ``xᵀPx`` with the exact test. Returns ``None``
    when no solver finds such a ``P``.
    """
    cp = deps.cvxpy()
    corners = [np.asarray(J, dtype=float) for J in corners]
    R = slack * np.asarray(radius, dtype=float)
    eta, constant = slack * eta, slack * constant
    n = R.shape[0]
    h = np.asarray(half_widths, dtype=float)
    if not (np.all(np.isfinite(R)) and all(np.all(np.isfinite(J)) for J in corners)
            and np.all(h > 0) and inner > 0):
        return None
    H, Hi = np.diag(h), np.diag(1.0 / h)
    scale = max(1.0, max(float(np.max(np.abs(Hi @ J @ H))) for J in corners))
    Js = [Hi @ J @ H / scale for J in corners]
    Rs = Hi @ R @ H / scale
    rows = [b for b in range(n) if np.any(Rs[b] > 0)]
    learned = list(range(n)) if components is None else list(components)
    P = cp.Variable((n, n), symmetric=True)          # z-coordinates: P_y = Hi P Hi
    tau, b = cp.Variable(nonneg=True), cp.Variable(nonneg=True)
    nu = cp.Variable(len(rows), nonneg=True) if rows else None
    eye = np.eye(n)
    # the terms in ‖y‖² of the test, in z: yᵀy = zᵀH²z
    shift = ((2 / inner) * b + constant / inner ** 2) / scale * (H @ H)
    if eta > 0:
        shift = shift + (eta / (inner * scale)) * tau * (H @ H)
    spread = sum(nu[k] * Rs[r].sum() * np.diag(Rs[r]) for k, r in enumerate(rows)) \
        if rows else 0
    g0 = np.zeros(n) if offset is None else slack * np.asarray(offset, dtype=float)
    cons = [P << H @ H / (1.03 * inner ** 2), b >= cp.norm(Hi @ P @ Hi @ g0) * (1 + 1e-6)]
    PyL = (Hi @ P)[learned, :]
    for J in Js:
        M = -(P @ J + J.T @ P) - spread - shift - 1e-7 * eye
        cols = [P[:, rows]] if rows else []
        blocks = [[M] + cols + ([PyL.T] if eta > 0 else [])]
        if rows:
            blocks.append([P[rows, :], cp.diag(nu)]
                          + ([np.zeros((len(rows), len(learned)))] if eta > 0 else []))
        if eta > 0:
            blocks.append([PyL] + ([np.zeros((len(learned), len(rows)))] if rows else [])
                          + [(inner * scale / eta) * tau * np.eye(len(learned))])
        big = cp.bmat(blocks) if len(blocks) > 1 else M
        cons.append(0.5 * (big + big.T) >> 0)
    for k in range(n):
        e = np.zeros((n, 1))
        e[k] = 1.0
        cons.append(cp.bmat([[P, e], [e.T, np.array([[1.0]])]]) >> 0)
    if inside is not None:
        cons.append(P >> 1.01 * H @ np.linalg.inv(np.asarray(inside, dtype=float)) @ H)
    for w, r in zip(np.zeros((0, n)) if gains is None else np.asarray(gains, dtype=float),
                    [] if radii is None else radii):
        wz = (w @ H).reshape(n, 1)
        cons.append(cp.bmat([[P, wz], [wz.T, np.array([[float(r) ** 2]])]]) >> 0)
    best = _log_det_descent(P, cons, rounds=rounds, solvers=("CLARABEL",))
    if best is None:
        return None
    X = Hi @ best @ Hi
    return 0.5 * (X + X.T)          # exactly symmetric (the products round unevenly)


def ellipse_candidates(A_cl):
    """Candidate matrices ``P`` of condition (c)'s quadratic ``xᵀPx``, in the order tried.

    The Lyapunov matrix of ``Q_V = I``; the round one (:func:`round_lyapunov_matrix`);
    then those of ``Q_V = I`` with one diagonal entry scaled by 100 or 0.01. Each is only a
    candidate: the caller verifies condition (c) with it. A generator: a caller that stops
    at the first certified candidate solves no SDP when ``Q_V = I`` already certifies.
    """
    n = np.asarray(A_cl).shape[0]
    yield lyapunov_matrix(A_cl)
    P = round_lyapunov_matrix(A_cl)
    if P is not None:
        yield P
    for i in range(n):
        for f in (100.0, 0.01):
            w = np.ones(n)
            w[i] = f
            yield lyapunov_matrix(A_cl, np.diag(w))


def linearisation(system, dynamics: Network | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``(A, B)`` at ``(0, u_eq)``: of the model, or of a learned ``φ`` (CasADi Jacobians).

    Without a model (a black-box or sampled system) the learned ``φ`` is the only
    linearisation the tool has: the LQR start then comes from φ's graph.
    """
    if dynamics is None:
        return system.A, system.B


    x, u = ca.MX.sym("x", system.nx), ca.MX.sym("u", system.nu)
    rhs = learned_rhs(system, dynamics, x, u)
    F = ca.Function("AB", [x, u], [ca.jacobian(rhs, x), ca.jacobian(rhs, u)])
    A, B = F(np.zeros(system.nx), system.u_eq if system.nu else np.zeros(0))
    return np.array(A, dtype=float).reshape(system.nx, system.nx), \
        np.array(B, dtype=float).reshape(system.nx, system.nu)


def lqr(system, Q=None, R=None, *, dynamics: Network | None = None) -> LQRResult:
    """LQR gain and Lyapunov matrix for ``system`` linearised at the origin.

    Parameters
    ----------
    system : systems.System
    Q : (nx, nx) array_like or float, optional   state weight (identity by default)
    R : (nu, nu) array_like or float, optional   input weight (identity by default)
    dynamics : Network, optional
        Linearise this learned ``φ`` instead of the model (required for systems without a
        model; :func:`linearisation`).

    Returns
    -------
    LQRResult

    Examples
    --------
    >>> import systems
    >>> lqr(systems.get("inverted_pendulum")).K.round(5).tolist()
    [[1.97725, 0.97624]]
    """
    if not hasattr(system, "nx"):
        raise ConfigError(f"lqr needs a System (e.g. systems.get(name)), got "
                          f"{type(system).__name__} {str(system)[:40]!r}")
    A, B = linearisation(system, dynamics)
    nx, nu = system.nx, system.nu
    Q = np.eye(nx) if Q is None else _matrix(Q, nx, "Q")
    if nu == 0:
        P = lyapunov_matrix(A)
        return LQRResult(np.zeros((0, nx)), np.zeros((nx, nx)), P, np.linalg.eigvals(A),
                         A, B, Q, np.zeros((0, 0)))
    R = np.eye(nu) if R is None else _matrix(R, nu, "R")
    if np.min(np.linalg.eigvalsh(R)) <= 0:
        raise ConfigError(f"R must be positive definite (its least eigenvalue is "
                          f"{np.min(np.linalg.eigvalsh(R)):.3g}); pass a positive weight")
    _check_stabilisable(A, B)
    K, S, E = _lqr(A, B, Q, R)
    cl = np.linalg.eigvals(A - B @ K)
    if not np.all(np.isfinite(cl)) or np.max(cl.real) >= 0:
        # (A, B) is stabilisable, so the exact LQR gain stabilises: the solver lost accuracy
        raise NotStabilizableError(
            f"the LQR gain computed with these weights does not stabilise the linearisation "
            f"(closed-loop eigenvalues {cl}): the Riccati solver lost accuracy; use moderate "
            "weights (Q and R between about 1e-6 and 1e6)")
    P = lyapunov_matrix(A - B @ K)
    return LQRResult(K, S, P, np.asarray(E), A, B, Q, R)


def saturated_controller(system, K, scale) -> Network:
    r"""The controller :math:`\kappa(x) = C \tanh(K' x + b)` that linearises to ``u_eq - K x``.

    ``b`` solves :math:`C \tanh(b) = u_{eq}` (so that ``f(0, κ(0)) = 0``) and
    :math:`K' = -\mathrm{diag}(C (1 - \tanh^2 b))^{-1} K`.

    Parameters
    ----------
    system : systems.System
    K : (nu, nx) array_like   LQR gain (``u = u_eq - K x``)
    scale : float or (nu,) array_like   actuator limit ``C`` (``|u| < C``)
    """
    K = np.atleast_2d(np.asarray(K, dtype=float))
    if K.shape != (system.nu, system.nx):
        raise DimensionError(f"K must be ({system.nu}, {system.nx}), got {K.shape}")
    C = np.broadcast_to(np.asarray(scale, dtype=float), (system.nu,)).copy()
    if np.any(C <= 0) or np.any(np.abs(system.u_eq) >= C):
        raise ValueError(
            f"the actuator limit C={C} must exceed |u_eq|={np.abs(system.u_eq)} so that "
            "C·tanh(b) = u_eq has a solution"
        )
    b = np.arctanh(system.u_eq / C)
    slope = C * (1.0 - np.tanh(b) ** 2)
    Kp = -K / slope[:, None]
    return Network([Layer(Kp, b, "tanh")], C if system.nu > 1 else float(C[0]),
                   {"kind": "controller", "form": "C*tanh(Kx+b)"})


def linear_controller(system, K) -> Network:
    """The unsaturated LQR feedback ``u = u_eq − K x`` as a one-layer linear network."""
    K = np.atleast_2d(np.asarray(K, dtype=float))
    if K.shape != (system.nu, system.nx):
        raise DimensionError(f"K must be ({system.nu}, {system.nx}), got {K.shape}")
    return Network([Layer(-K, system.u_eq.copy(), "linear")], 1.0,
                   {"kind": "controller", "form": "u_eq - Kx"})


def quadratic_lyapunov(P) -> Network:
    """``V(x) = xᵀPx`` as a network: ``‖Lᵀx‖²`` with ``P = L Lᵀ`` (sum-of-squares head)."""
    if np.ndim(P) != 2 or np.shape(P)[0] != np.shape(P)[1]:
        raise DimensionError(f"P must be a square matrix, got shape {np.shape(P)}")
    try:
        P = np.asarray(P, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError("P must be a matrix of numbers") from None
    if not np.all(np.isfinite(P)):
        raise ConfigError("P has entries that are not finite (NaN or inf); pass finite numbers")
    S = 0.5 * (P + P.T)     # xᵀPx is xᵀSx: only the symmetric part matters
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        raise ConfigError(f"P must be positive definite (the least eigenvalue of (P + Pᵀ)/2 is "
                          f"{np.min(np.linalg.eigvalsh(S)):.3g}); V = xᵀPx is no Lyapunov "
                          "function candidate otherwise") from None
    return Network([Layer(L.T, np.zeros(len(P)), "linear")], head={"type": "sum_of_squares"},
                   meta={"kind": "lyapunov", "form": "x'Px"})
