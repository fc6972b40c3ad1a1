r"""Verification in coordinates fitted to the problem: ``x = T z`` (option ``precondition``).

Interval branch-and-prune splits boxes along the coordinate axes, and its bounds are
tight when the functions vary about as much along every axis of a box. A Lie derivative
``p = ∇V·f`` of a stiff closed loop does not: near the equilibrium ``p ≈ ½ xᵀHx`` with a
Hessian ``H`` whose eigenvalues span orders of magnitude, and whose off-diagonal terms the
second-order centred form can only bound by ``|H_ij| h_i h_j``. In the coordinates
``z = Mx`` with ``MᵀM = |H| = U|Λ|Uᵀ`` (rows: the eigenvectors of ``H`` as axes, scaled by
``|λ|^{1/2}``) the same function is ``p ≈ ±|z|²``: no off-diagonal terms, the
same sensitivity along every axis, and boxes aligned with the level sets.

:func:`precondition` builds the problem in ``z``; :func:`hessian_coordinates` proposes
``M``; :func:`solve_preconditioned` runs a verifier on the ``z`` problem and states the
result about the original one.

Soundness
---------
``T`` is a float matrix, the float inverse of ``M`` rounded to 24 significant bits. The
``z`` problem's graphs are built so that no number of ``T`` meets a constant of the original
graphs before the verifier evaluates them:

- values: the original ``function`` is a called node, evaluated at ``x = T z``, a matrix
  product node of the constant ``T`` and ``z`` (intervals: an outward-rounded product;
  affine forms: the form of ``x`` in ``z`` has the float entries of ``T`` as coefficients
  plus a bound of the product's rounding errors). Inside the call every constant of the
  original graph is evaluated as in the original problem (non-integer constants keep their
  widening), so the enclosures in ``z`` hold the exact values of ``g(Tz)`` and ``p(Tz)``
  exactly where the original enclosures hold those of ``g`` and ``p``;
- derivatives: the Jacobian ``J(Tz)·T`` is CasADi's forward mode of the original
  ``function`` along the columns of a seed matrix, and the gradients and Hessians of the
  second-order form are CasADi's derivatives in ``z`` of ``p(Sz)``; in both, the seed ``S``
  is a symbol while the graphs are built (CasADi can fold only numbers it knows), and the
  ``z`` graphs call them with ``T``. Their own constants are those of derivative graphs of
  the original (the verifier widens derivative enclosures for the folds CasADi makes among
  a graph's own constants);
- the region: the original constraints, and an ellipsoid ``Σ_i ((Tz)_i − c_i)²/r_i² ≤ n``
  (and its gradient ``(2(Tz − c)/r²)ᵀT``, written out) that contains the original root box
  ``B`` (centre ``c``, half widths ``r`` rounded up; a superset of ``B``: proving the
  properties on a larger region proves them on ``B``);
- the root box ``Z`` covers ``T⁻¹B``: with ``Δ = I − MT`` enclosed in interval arithmetic
  and ``δ ≥ ‖Δ‖_∞`` (``δ < ½`` required), ``T⁻¹ = (I − Δ)⁻¹M``, so ``z = T⁻¹x`` lies within
  ``δ/(1 − δ)·‖Mx‖_∞`` of ``Mx``, and ``Mx`` over ``B`` is an interval matrix product.

Every point ``x`` of the original region is ``T z`` for a ``z ∈ Z`` that satisfies the ``z``
problem's constraints, so ``verified`` in ``z`` proves the original properties on the
original region, under the same rounding model as a verification in ``x``. A ``z``
counterexample is mapped to ``x = fl(T z)`` and confirmed again on the original problem
(rigorous point evaluation); one that does not confirm there makes the answer ``unknown``,
never a counterexample. Undecided ``z`` boxes come back as boxes of ``x`` that cover their
image (outward-rounded interval product, intersected with ``B``).

Only the graphs (``function``, ``function_checked``) of the original problem are used, not
its expressions, so a problem restored from a pickle is preconditioned as the problem itself.
``M`` does not depend on which eigenbasis a LAPACK build returns (:func:`_eigen_rows`).
"""

from __future__ import annotations

import copy
from collections.abc import Callable
from dataclasses import dataclass

import casadi as ca
import numpy as np

from nlyap_opt.kernel.errors import DimensionError
from nlyap_opt.kernel.rounding import up

from .interval import Interval, IntervalArithmetic
from .problem import VerificationProblem, VerificationResult

__all__ = ["Preconditioned", "precondition", "hessian_coordinates", "solve_preconditioned"]

_IA = IntervalArithmetic()
#: ``hessian_coordinates`` declines Hessians whose eigenvalues' magnitudes span more than
#: this ratio (or of mixed sign): ``M`` would be near singular or the form not ``±|z|²``
_MAX_SPREAD = 1e8
#: eigenvalues closer than this times the largest magnitude form one cluster, whose basis
#: :func:`_eigen_rows` chooses from the eigenspace (an eigenvector's float error grows as
#: ``u‖H‖/gap``: beyond this gap it stays far below the 24-bit rounding of ``M``)
_CLUSTER = 1e-6


@dataclass
class Preconditioned:
    """A problem in the coordinates ``z`` with ``x = T z``.

    Attributes
    ----------
    problem : VerificationProblem
        In ``z``: the original constraints and properties at ``T z`` (graphs that call the
        original ones), an ellipsoid around the original root box ``B`` as one more
        constraint, and a root box covering ``T⁻¹B``.
    original : VerificationProblem
    M, T : (n, n) ndarray
        ``z ≈ M x`` and the exact change ``x = T z`` (``T`` about the inverse of ``M``).
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
        Its ``function`` is differentiated (a problem restored from a pickle works too).
    point : (n,) array_like, optional
        Where ``H`` is taken (default: the root box's centre; for a Lyapunov problem on a
        domain centred at the equilibrium, the equilibrium, where the decrease is
        ``½ xᵀHx`` to second order).

    Returns
    -------
    (n, n) ndarray or None
        Rows: the eigenvectors of ``H`` scaled by ``|λ|^{1/2}``, a basis of each cluster of
        (nearly) repeated eigenvalues chosen from its eigenspace alone, rounded to 24
        significant bits (:func:`_eigen_rows`: the same ``M`` for every eigenbasis a
        LAPACK build returns); ``None`` when ``H`` is not finite, not definite, or its
        eigenvalues' magnitudes span more than :data:`_MAX_SPREAD`, or the root box is
        flat in some dimension (then the problem is verified as it is).
    """
    n = problem.n
    if not np.all(problem.box[:, 1] > problem.box[:, 0]):
        return None
    p = problem.box.mean(axis=1) if point is None else np.asarray(point, dtype=float)
    _, fH = _second_order(problem.function, problem.n_constraints, n)
    outs = fH(p, np.eye(n))   # z = x
    H = np.array(outs[-1] if isinstance(outs, (list, tuple)) else outs, dtype=float)
    H = H.reshape(n, n)
    if not np.all(np.isfinite(H)):
        return None
    w, U = np.linalg.eigh(0.5 * (H + H.T))
    a = np.abs(w)
    if not (np.all(w < 0) or np.all(w > 0)) or a.min() * _MAX_SPREAD < a.max():
        return None
    return _eigen_rows(w, U)


def _eigen_rows(w: np.ndarray, U: np.ndarray) -> np.ndarray:
    """Rows ``|λ|^{1/2} uᵀ`` from an eigen-decomposition ``H = U diag(w) Uᵀ``, the same for
    every orthonormal eigenbasis ``U`` (so for every LAPACK build), rounded to 24 bits.

    An eigenvector of a simple eigenvalue is unique up to sign (fixed: its largest entry
    positive). Within a cluster of eigenvalues closer than :data:`_CLUSTER` times the
    largest magnitude, where a LAPACK build may return any rotation of the basis, the rows
    are instead the eigenvectors of a fixed diagonal matrix ``D`` compressed to the
    cluster's invariant subspace (``B = U_c V`` with ``V`` the eigenvectors of
    ``U_cᵀ D U_c``: for ``U_c R`` in place of ``U_c`` the same ``B``), each scaled by
    ``(bᵀ|H|b)^{1/2}``. Rounded to 24 bits, the last bits in which two builds' results
    differ (about ``u‖H‖/gap`` relative for an eigenvector, below ``2⁻³³`` for the gaps
    outside a cluster) are removed too, unless an entry lies that close to a rounding
    boundary.

    Parameters
    ----------
    w : (n,) ndarray
        Eigenvalues, ascending (as ``numpy.linalg.eigh`` gives them).
    U : (n, n) ndarray
        Orthonormal eigenvectors (columns).

    Returns
    -------
    (n, n) ndarray
        ``M`` with ``MᵀM ≈ |H|``.
    """
    n = len(w)
    a = np.abs(w)
    B = np.array(U, dtype=float)
    scale = np.sqrt(a)
    D = np.exp(0.7390851 * np.arange(n))  # distinct, and not in simple ratios
    start = 0
    for i in range(1, n + 1):
        if i < n and w[i] - w[i - 1] <= _CLUSTER * a.max():
            continue
        if i - start > 1:  # the cluster start..i-1
            Uc = U[:, start:i]
            C = Uc.T @ (D[:, None] * Uc)
            _, V = np.linalg.eigh(0.5 * C + 0.5 * C.T)
            B[:, start:i] = Uc @ V
            scale[start:i] = np.sqrt((V ** 2).T @ a[start:i])    # (bᵀ|H|b)^{1/2}
        start = i
    sign = np.sign(B[np.argmax(np.abs(B), axis=0), np.arange(n)])
    return _coarse((B * sign * scale).T)


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


def _directional(fn: ca.Function, n: int) -> tuple[ca.MX, ca.MX, list]:
    """``(x, S, outs)``: symbols ``x`` (``n``) and ``S`` (``(n, n)``) and ``fn``'s outputs
    at ``x``; derivatives along the columns of ``S`` are then CasADi's forward mode of
    ``fn``'s own graph.

    ``S`` is a symbol while the graphs are built, so no number of it meets a constant of
    ``fn`` before a verifier's arithmetic evaluates them.
    """
    x = ca.MX.sym("x", n)
    S = ca.MX.sym("S", n, n)
    return x, S, fn.call([x])


def _second_order(fn: ca.Function, m: int, n: int) -> tuple[ca.Function, ca.Function]:
    """``(z, S) -> ∇_z p(Sz)`` and ``(z, S) -> (∇²_z p_1(Sz), …, ∇²_z p_k(Sz))`` for the
    properties ``p`` (outputs ``m:`` of ``fn``'s single column output): the gradients
    ``∇p(x)ᵀS`` and Hessians ``Sᵀ∇²p(x)S`` at ``x = Sz`` (CasADi's derivatives of ``fn``'s
    graph composed with the symbolic ``S``)."""
    z = ca.MX.sym("z", n)
    S = ca.MX.sym("S", n, n)
    P = fn.call([ca.mtimes(S, z)])[0][m:, :]
    G = ca.densify(ca.jacobian(P, z))
    Hs = [ca.densify(ca.hessian(P[j], z)[0]) for j in range(P.shape[0])]
    return ca.Function("PG_S", [z, S], [G]), ca.Function("PH_S", [z, S], Hs)


class _Composed(VerificationProblem):
    """The problem in ``z``: graphs that call the original problem's graphs at ``x = T z``.

    Nothing of the original graphs is rebuilt with ``T`` inside: ``x = T z`` is a matrix
    product node, the original Function is a called node, and its derivatives are CasADi's
    derivative graphs of that Function composed with a symbolic matrix ``S``, called with
    ``S = T`` (see the module's Soundness section). Built from the original
    ``function`` (and ``function_checked``) alone, so a problem restored from a pickle (its
    expressions dropped) works too; like such a problem it holds no expressions
    (``constraints`` and ``properties`` are ``None``).
    """

    def __init__(self, original: VerificationProblem, T: np.ndarray, zbox: np.ndarray,
                 c: np.ndarray, r: np.ndarray):
        n, m = original.n, original.n_constraints
        z = ca.MX.sym("z", n)
        Tm = ca.DM(T)
        xz = ca.mtimes(Tm, z)
        # the ellipsoid Σ ((x_i - c_i) / r_i)² ≤ n around the root box B and its gradient
        # (2 (x - c) / r²)ᵀ T, written out (not differentiated: no constant is combined)
        d = (xz - ca.DM(c)) / ca.DM(r)
        ell = ca.sum1(d ** 2) - n
        dell = ca.mtimes((2 * d / ca.DM(r)).T, Tm)

        def rows(F, e):  # the original rows with the ellipsoid's after the constraints
            return ca.vertcat(F[:m, :], e, F[m:, :])

        x, S, outs = _directional(original.function, n)
        FJ = ca.Function("FJ_S", [x, S], [outs[0], ca.jtimes(outs[0], x, S)])
        F, J = FJ.call([xz, Tm])
        self.x = z
        self.box = np.asarray(zbox, dtype=float)
        self.n_constraints = m + 1
        self.n_properties = original.n_properties
        self.constraint_names = list(original.constraint_names) + ["root box"]
        self.property_names = list(original.property_names)
        self.function = ca.Function("F", [z], [rows(original.function.call([xz])[0], ell)])
        self.jacobian = ca.Function("J", [z], [rows(J, dell)])
        self.function_jacobian = ca.Function("FJ", [z], [rows(F, ell), rows(J, dell)])
        self.constraints = self.properties = None
        self.checked = original.checked
        self.function_checked = self.function_jacobian_checked = None
        if self.checked:  # one output per constraint and property, as the original's
            x, S, outs = _directional(original.function_checked, n)
            FJc = ca.Function("FJ_checked_S", [x, S],
                              outs + [ca.jtimes(ca.vertcat(*outs), x, S)])
            outs = original.function_checked.call([xz])
            self.function_checked = ca.Function("F_checked", [z], outs[:m] + [ell] + outs[m:])
            outs = FJc.call([xz, Tm])
            self.function_jacobian_checked = ca.Function(
                "FJ_checked", [z], outs[:m] + [ell] + outs[m:-1] + [rows(outs[-1], dell)])
        self._T = np.array(T, dtype=float)
        self._original_function = original.function
        self._second_order = None

    @property
    def second_order_functions(self) -> tuple[ca.Function, ca.Function]:
        """``(G, H)`` in ``z``: ``∇p(Tz)ᵀT`` and ``Tᵀ∇²p(Tz)T``, CasADi's derivatives in ``z``
        of the original ``function`` at ``x = Sz`` (``S`` a symbol), called with ``T``."""
        if self._second_order is None:
            fn = getattr(self, "_original_function", None)
            if fn is None:  # restored from a pickle before they were built
                return super().second_order_functions   # the error that says what to do
            z = self.x
            Tm = ca.DM(self._T)
            fG, fH = _second_order(fn, self.n_constraints - 1, self.n)
            self._second_order = (ca.Function("PG", [z], fG.call([z, Tm])),
                                  ca.Function("PH", [z], fH.call([z, Tm])))
        return self._second_order

    def restricted(self, box) -> VerificationProblem:
        """The same problem on a sub-box (same graphs)."""
        box = np.asarray(box, dtype=float)
        if box.shape != self.box.shape or np.any(box[:, 0] > box[:, 1]):
            raise DimensionError(f"box must have shape {self.box.shape} with lower <= upper, "
                                 f"got {box.shape}")
        out = copy.copy(self)
        out.box = box
        return out


def precondition(problem: VerificationProblem, M: np.ndarray) -> Preconditioned:
    """The problem in the coordinates ``z = M x`` (``x = T z``, ``T = fl(M⁻¹)``).

    Parameters
    ----------
    problem : VerificationProblem
        Its graphs are used, not its expressions: a problem restored from a pickle works.
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
    # the ellipsoid Σ ((x_i - c_i) / r_i)² ≤ n around the root box B (one constraint, not 2n:
    # each costs a column of every pass); a superset of B, enough: a larger region only
    # asks for more, and a counterexample outside B is not confirmed on the original problem
    c = 0.5 * box[:, 0] + 0.5 * box[:, 1]
    r = up(np.maximum(box[:, 1] - c, c - box[:, 0]))  # >= the exact half widths about c
    return Preconditioned(_Composed(problem, T, zbox, c, r), problem, M, T)


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
