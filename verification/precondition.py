r"""Verification in coordinates fitted to the problem: ``x = T z`` (option ``precondition``).

Interval branch-and-prune splits boxes along the coordinate axes, and its bounds are
tight when the functions vary about as much along every axis of a box. A Lie derivative
``p = ∇V·f`` of a stiff closed loop does not: near the equilibrium ``p ≈ ½ xᵀHx`` with a
Hessian ``H`` whose eigenvalues span orders of magnitude, and whose off-diagonal terms the
second-order centred form can only bound by ``|H_ij| h_i h_j``. In the coordinates
``z = Mx`` with ``M = |H|^{1/2}`` (``|H| = U|Λ|Uᵀ``, the eigenvectors of ``H`` as axes,
scaled by ``|λ|^{1/2}``) the same function is ``p ≈ ±|z|²``: no off-diagonal terms, the
same sensitivity along every axis, and boxes aligned with the level sets.

:func:`precondition` builds the problem in ``z``; :func:`hessian_coordinates` proposes
``M``; :func:`solve_preconditioned` runs a verifier on the ``z`` problem and states the
result about the original one.

Soundness
---------
``T`` is a float matrix, the float inverse of ``M`` rounded to 24 significant bits; the
``z`` problem's graphs are the original ones of ``x = T z`` (a constant matrix product,
evaluated by the verifier in outward-rounded arithmetic), its constraints are the original
ones and an ellipsoid ``Σ_i ((Tz)_i − c_i)²/r_i² ≤ n`` that contains the original root box
``B`` (centre ``c``, half widths ``r`` rounded up; a superset of ``B``: proving the
properties on a larger region proves them on ``B``), and its root box ``Z`` covers ``T⁻¹B``:
with ``Δ = I − MT`` enclosed in interval arithmetic and ``δ ≥ ‖Δ‖_∞`` (``δ < ½`` required),
``T⁻¹ = (I − Δ)⁻¹M``, so ``z = T⁻¹x`` lies within ``δ/(1 − δ)·‖Mx‖_∞`` of ``Mx``, and ``Mx``
over ``B`` is an interval matrix product. Every point ``x`` of the original region is
``T z`` for a ``z ∈ Z`` that satisfies the ``z`` problem's constraints, so ``verified`` in ``z``
proves the original properties on the original region. A ``z`` counterexample is mapped to
``x = fl(T z)`` and confirmed again on the original problem (rigorous point evaluation); one
that does not confirm there makes the answer ``unknown``, never a counterexample. Undecided
``z`` boxes come back as boxes of ``x`` that cover their image (outward-rounded interval
product, intersected with ``B``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

from nlyap_opt.kernel.rounding import up

from .interval import Interval, IntervalArithmetic
from .problem import VerificationProblem, VerificationResult

__all__ = ["Preconditioned", "precondition", "hessian_coordinates", "solve_preconditioned"]

_IA = IntervalArithmetic()
#: ``hessian_coordinates`` declines Hessians whose eigenvalues' magnitudes span more than
#: this ratio (or of mixed sign): ``M`` would be near singular or the form not ``±|z|²``
_MAX_SPREAD = 1e8


@dataclass
class Preconditioned:
    """A problem in the coordinates ``z`` with ``x = T z``.

    Attributes
    ----------
    problem : VerificationProblem
        In ``z``: the original constraints and properties of ``T z``, an ellipsoid around
        the original root box ``B`` as one more constraint, and a root box covering ``T⁻¹B``.
    original : VerificationProblem
    M, T : (n, n) ndarray
        ``z ≈ M x`` and the exact substitution ``x = T z`` (``T`` about the inverse of ``M``).
    """

    problem: VerificationProblem
    original: VerificationProblem
    M: np.ndarray
    T: np.ndarray

    def x_boxes(self, zboxes: np.ndarray) -> np.ndarray:
        """Boxes of ``x`` (``(k, n, 2)``) covering ``T·[z boxes]``, within the original root box.

        Parameters
        ----------
        zboxes : (k, n, 2) ndarray

        Returns
        -------
        (k, n, 2) ndarray
        """
        zb = np.asarray(zboxes, dtype=float).reshape(-1, self.T.shape[0], 2)
        if not len(zb):
            return np.zeros((0, self.T.shape[0], 2))
        img = _IA.matmul(self.T, Interval(zb[:, :, 0, None], zb[:, :, 1, None]))
        box = self.original.box
        lo = np.maximum(img.lo[..., 0], box[:, 0])
        hi = np.minimum(img.hi[..., 0], box[:, 1])
        return np.stack([np.minimum(lo, hi), hi], axis=-1)


def hessian_coordinates(problem: VerificationProblem, point=None) -> np.ndarray | None:
    """``M = |H|^{1/2}`` of the last property's Hessian ``H`` at ``point``, or ``None``.

    Parameters
    ----------
    problem : VerificationProblem
    point : (n,) array_like, optional
        Where ``H`` is taken (default: the root box's centre; for a Lyapunov problem on a
        domain centred at the equilibrium, the equilibrium, where the decrease is
        ``½ xᵀHx`` to second order).

    Returns
    -------
    (n, n) ndarray or None
        Rows: the eigenvectors of ``H`` (each with its largest entry positive, so that the
        same ``H`` gives the same ``M``) scaled by ``|λ|^{1/2}``, rounded to 24 significant
        bits; ``None`` when ``H`` is not
        finite, not definite, or its eigenvalues' magnitudes span more than
        :data:`_MAX_SPREAD`, or the root box is flat in some dimension (then the problem
        is verified as it is).
    """
    n = problem.n
    if not np.all(problem.box[:, 1] > problem.box[:, 0]):
        return None
    p = problem.box.mean(axis=1) if point is None else np.asarray(point, dtype=float)
    _, fH = problem.second_order_functions
    outs = fH(p)
    H = np.array(outs[-1] if isinstance(outs, (list, tuple)) else outs, dtype=float)
    H = H.reshape(n, n)
    if not np.all(np.isfinite(H)):
        return None
    w, U = np.linalg.eigh(0.5 * (H + H.T))
    a = np.abs(w)
    if not (np.all(w < 0) or np.all(w > 0)) or a.min() * _MAX_SPREAD < a.max():
        return None
    sign = np.sign(U[np.argmax(np.abs(U), axis=0), np.arange(n)])
    return _coarse((U * sign * np.sqrt(a)).T)


def _coarse(a: np.ndarray, bits: int = 24) -> np.ndarray:
    """``a`` rounded to ``bits`` significant bits: the last bits of an eigen-decomposition
    or an inverse differ between LAPACK builds; rounded, the same ``M`` and ``T`` (so the
    same graphs, boxes and verdicts) come out on other machines too."""
    m, e = np.frexp(np.asarray(a, dtype=float))
    return np.ldexp(np.round(np.ldexp(m, bits)), e - bits)


def _cover(M: np.ndarray, T: np.ndarray, box: np.ndarray) -> np.ndarray:
    """A root box ``(n, 2)`` of ``z`` that contains ``T⁻¹x`` for every ``x`` in ``box``."""
    n = len(M)
    MT = _IA.matmul(M, T)
    eye = np.eye(n)
    D = Interval(eye - MT.hi, eye - MT.lo)  # ⊇ I − MT: the float differences, widened below
    mag = np.maximum(np.abs(D.lo), np.abs(D.hi))
    mag = up(up(mag) * (1.0 + 2.0**-40))   # one rounding each side of the subtraction
    delta = float(np.max(up(_IA.sum(Interval(mag, mag), 1).hi)))
    if not delta < 0.5:
        raise ValueError(f"the coordinate change is too ill-conditioned (‖I − MT‖ ≥ {delta:g}); "
                         "use a better conditioned M")
    y = _IA.matmul(M, Interval(box[:, :1], box[:, 1:]))  # (n, 1)
    ymax = float(np.max(np.maximum(np.abs(y.lo), np.abs(y.hi))))
    one = Interval(np.array(1.0), np.array(1.0))
    d = Interval(np.array(delta), np.array(delta))
    ratio = _IA.binary(ca.OP_DIV, d, _IA.binary(ca.OP_SUB, one, d))
    rho = _IA.binary(ca.OP_MUL, ratio, Interval(np.array(ymax), np.array(ymax))).hi
    r = Interval(np.full(n, -rho), np.full(n, rho))
    z = _IA.binary(ca.OP_ADD, Interval(y.lo[:, 0], y.hi[:, 0]), r)
    return np.stack([z.lo, z.hi], axis=1)


def precondition(problem: VerificationProblem, M: np.ndarray) -> Preconditioned:
    """The problem in the coordinates ``z = M x`` (substituting ``x = T z``, ``T = fl(M⁻¹)``).

    Parameters
    ----------
    problem : VerificationProblem
    M : (n, n) array_like
        Invertible, well enough conditioned that ``‖I − M·fl(M⁻¹)‖_∞ < ½`` is proved.

    Returns
    -------
    Preconditioned

    Raises
    ------
    ValueError
        ``M`` has the wrong shape, is not finite, or is too ill-conditioned.
    """
    n = problem.n
    M = np.asarray(M, dtype=float)
    if M.shape != (n, n) or not np.all(np.isfinite(M)):
        raise ValueError(f"M must be a finite ({n}, {n}) matrix, got shape {M.shape}")
    if not np.all(problem.box[:, 1] > problem.box[:, 0]):
        raise ValueError("precondition needs a root box of positive width in every dimension")
    try:
        T = _coarse(np.linalg.inv(M))   # any T with ‖I − MT‖ < ½ will do (see _cover)
    except np.linalg.LinAlgError:
        raise ValueError("M must be invertible") from None
    box = problem.box
    zbox = _cover(M, T, box)
    z = (ca.MX if isinstance(problem.x, ca.MX) else ca.SX).sym("z", n)
    xz = ca.mtimes(ca.DM(T), z)
    exprs = ca.substitute(list(problem.constraints) + list(problem.properties),
                          [problem.x], [xz])
    m = problem.n_constraints
    # the ellipsoid Σ ((x_i - c_i) / r_i)² ≤ n around the root box B (one constraint, not 2n:
    # each costs a column of every pass); a superset of B, enough: a larger region only
    # asks for more, and a counterexample outside B is not confirmed on the original problem
    c = 0.5 * box[:, 0] + 0.5 * box[:, 1]
    r = up(np.maximum(box[:, 1] - c, c - box[:, 0]))  # >= the exact half widths about c
    ell = ca.sumsqr((xz - ca.DM(c)) / ca.DM(r)) - n
    cons = list(exprs[:m]) + [ell]
    names = list(problem.constraint_names) + ["root box"]
    zp = VerificationProblem(z, zbox, cons, list(exprs[m:]), names, problem.property_names)
    return Preconditioned(zp, problem, M, T)


def solve_preconditioned(problem: VerificationProblem, M: np.ndarray | None,
                         solve: Callable[[VerificationProblem], VerificationResult],
                         confirm: Callable) -> VerificationResult:
    """``solve`` the problem in the coordinates ``z = M x``; the result about ``problem``.

    Parameters
    ----------
    problem : VerificationProblem
    M : (n, n) ndarray or None
        ``None``: ``solve(problem)`` as it is.
    solve : callable
        A verifier, ``VerificationProblem -> VerificationResult``.
    confirm : callable
        ``(problem, points) -> list of Counterexample``: rigorous confirmation of points of
        ``problem`` (:func:`verification.verify.confirm_points`).

    Returns
    -------
    VerificationResult
        ``verified`` as proved in ``z``; counterexamples mapped to ``x`` and confirmed on
        ``problem`` (none confirmed: ``unknown``); undecided boxes as covering boxes of
        ``x``.
    """
    if M is None:
        return solve(problem)
    pre = precondition(problem, M)
    r = solve(pre.problem)
    und = pre.x_boxes(r.undecided) if len(r.undecided) else np.zeros((0, problem.n, 2))
    if r.status == "verified":
        return VerificationResult("verified", None, [], und, r.boxes, r.depth, r.seconds,
                                  backend=r.backend)
    found = []
    if r.counterexamples:
        pts = np.stack([pre.T @ c.point for c in r.counterexamples])
        found = confirm(problem, pts)
    if found:
        return VerificationResult("counterexample", found[0], found, und, r.boxes, r.depth,
                                  r.seconds, backend=r.backend)
    if r.status == "counterexample":  # found in z, not confirmed at a float point of x
        pts = np.stack([c.point for c in r.counterexamples])
        und = np.concatenate([und, pre.x_boxes(np.stack([pts, pts], axis=-1))])
    return VerificationResult("unknown", None, [], und, r.boxes, r.depth, r.seconds,
                              backend=r.backend)
