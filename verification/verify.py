"""Interval branch-and-prune verifier over CasADi graphs (the default backend).

Each round evaluates a whole batch of boxes in a few walker passes (numpy arrays over boxes):

1. natural interval extension of ``F = (g, p)`` on every box;
2. affine arithmetic (:mod:`verification.affine`, option ``affine``, default on): every
   value an affine form in the box's inputs plus a remainder, with sound linear
   relaxations of the nonlinear operations; the ranges of the output forms are
   intersected with (1) (the tighter bound wins per box and output);
3. mean-value form ``F(c) + J(X)·(X − c)`` with the interval Jacobian from the CasADi
   Jacobian graph, intersected with (1) (option ``mean_value``; by default, with affine
   arithmetic, only on the boxes that (1) and (2) leave undecided: the Jacobian pass is
   the costliest);
4. a box is *decided* when some ``g_i > 0`` on all of it (outside the region) or every
   ``p_j < 0`` on all of it (properties hold), or, with affine forms, on the part of it
   where some ``g_k ≤ 0`` (``p_j − λ g_k < 0`` on the box for a ``λ ≥ 0``: boxes across
   the region's boundary); ``F(c)`` at the centre, evaluated rigorously, confirms
   counterexamples (centre inside the region and some ``p_j ≥ 0``);
5. undecided boxes are bisected along the dimension to which the bounds of the
   undecided outputs are most sensitive: the smear ``max_j |J_ji|·w_i`` of the interval
   Jacobian where the mean-value pass ran, else (``mean_value=False``) the affine forms'
   ``max_j (|g_ji| + e_j w_i / Σ_k w_k)`` for ``c_j + Σ_i g_ji ε_i ± e_j`` (linear part,
   and the remainder shared in proportion to the widths); boxes narrower than
   ``resolution`` are reported ``unknown``.

Non-smooth and partial operations (``nlyap_opt.kernel.walker.OP_TABLE``; problems whose
``checked`` flag is set) are walked with
:class:`~verification.interval.CheckedIntervalArithmetic`, which reports per box and per
constraint/property column:

- kinks and jumps: where an operation feeding a column may meet its kink or jump set
  on the box (``sign``'s argument contains 0, ``floor``'s an integer, the two sides of a
  comparison overlap, the arguments of ``fmin`` cross, ...), that column keeps the
  natural extension only (CasADi's derivative is 0 across a jump, so ``F(c) + J(X)(X − c)``
  would miss it; the affine ranges are not used either, although every non-smooth
  operation runs on intervals there) and the box is bisected along its widest side;
- partial domains: a constraint prunes a box only if every operation feeding it is proved
  inside its domain on the box; a property holds on a box only if it is so proved. A point
  of the region (every constraint proved defined and ``≤ 0`` there) at which a property is
  certainly undefined is a counterexample ``"domain of OP_..."``; a box that can be
  decided neither way ends ``unknown``.

Graphs without such operations (or only with harmless ones: division by a nonzero
constant, integer powers) take the plain path, at unchanged cost.

Before branching, a float pre-search over random points and a few gradient steps proposes
counterexamples, each confirmed by rigorous point evaluation before it is reported; with
``presearch_boundary`` (off by default), where it confirms none, points moved onto the
constraints' zero sets (the outer sphere of a Lyapunov query) are tried too.
"""

from __future__ import annotations

import contextlib
import copy
import ctypes
import glob
import inspect
import os
import time
import types
import typing
from concurrent.futures import Executor

import casadi as ca
import numpy as np

from nlyap_opt.kernel.errors import ConfigError, DimensionError
from nlyap_opt.kernel.walker import NUMPY, compile_function, evaluate, op_name

from .affine import Affine, AffineArithmetic, tight_ranges
from .backward import backward_bounds
from .interval import (
    CheckedIntervalArithmetic,
    Interval,
    IntervalArithmetic,
    fp_ignored,
    to_shape,
)
from .precondition import hessian_coordinates, solve_preconditioned
from .problem import Counterexample, VerificationProblem, VerificationResult

__all__ = ["verify_interval", "split_box", "confirm_points"]

_IA = IntervalArithmetic()
_AA = AffineArithmetic()


def _openblas_threads():
    """(get, set) of the OpenBLAS bundled with numpy, or ``None`` (best effort)."""
    try:
        libs = glob.glob(os.path.join(os.path.dirname(np.__file__) + ".libs", "*openblas*"))
        for path in libs:
            lib = ctypes.CDLL(path)
            for get, put in (("scipy_openblas_get_num_threads64_",
                              "scipy_openblas_set_num_threads64_"),
                             ("openblas_get_num_threads", "openblas_set_num_threads")):
                if hasattr(lib, get) and hasattr(lib, put):
                    return getattr(lib, get), getattr(lib, put)
    except OSError:
        pass
    return None


_BLAS = _openblas_threads()


@contextlib.contextmanager
def _single_thread_blas():
    """Run BLAS single-threaded (restored afterwards).

    The verifier's products are skinny (batch x 200 by 200 x 2, ...): threads add spinning
    CPU time without speed-up (about 2x the CPU time on 2 cores). Rounding bounds do not
    depend on the kernel's summation order, so results stay rigorous either way.
    """
    if _BLAS is None:
        yield
        return
    get, put = _BLAS
    n = get()
    if n <= 1:
        yield
        return
    put(1)
    try:
        yield
    finally:
        put(n)


def _rows(x, N: int):
    """A walker output as ``(N, k)`` rows: constant outputs (the graph folded them) come
    back without the batch dimension. Arrays or :class:`Interval`."""
    if isinstance(x, Interval):
        if x.lo.ndim == 2 and x.lo.shape[0] == N:
            return x
        return Interval(np.broadcast_to(x.lo, (N, x.lo.shape[-1])),
                        np.broadcast_to(x.hi, (N, x.hi.shape[-1])))
    x = np.asarray(x)
    if x.ndim == 2 and x.shape[0] == N:
        return x
    return np.broadcast_to(x, (N, x.shape[-1]))


def _point_enclosure(problem: VerificationProblem, pts: np.ndarray) -> Interval:
    """Rigorous enclosure of ``F`` at points ``(N, n)`` (degenerate boxes)."""
    return _rows(evaluate(problem.function, [Interval(pts, pts.copy())], _IA)[0], len(pts))


def _columns(outs, B: int) -> Interval:
    """``(B, K)`` enclosure from ``K`` scalar outputs (each ``(B, 1)``, or constant)."""
    def col(a):
        a = a.reshape(-1, 1) if a.ndim < 2 else a
        return to_shape(a, (B, 1))
    return Interval(np.concatenate([col(o.lo) for o in outs], axis=1),
                    np.concatenate([col(o.hi) for o in outs], axis=1))


def _checked_eval(problem: VerificationProblem, lo: np.ndarray, hi: np.ndarray,
                  jacobian: bool):
    """Checked walk over boxes: ``(F enclosure (B, K), J or None, checks)``."""
    B = len(lo)
    K = problem.n_constraints + problem.n_properties
    fun = problem.function_jacobian_checked if jacobian else problem.function_checked
    ar = CheckedIntervalArithmetic(B, K + (1 if jacobian else 0))
    outs = evaluate(fun, [Interval(lo, hi)], ar)
    ar.collect(outs[:K])
    return _columns(outs[:K], B), (_rows(outs[K], B) if jacobian else None), _Checks(ar, K)


class _Checks:
    """Per box and per constraint/property column: jump, maybe/surely undefined, op."""

    __slots__ = ("jump", "maybe", "sure", "op")

    def __init__(self, ar=None, K: int = 0, parts=None):
        if parts is not None:
            self.jump, self.maybe, self.sure, self.op = parts
            return
        self.jump = ar.jump[:, :K]
        self.maybe = ar.maybe_undefined[:, :K]
        self.sure = ar.undefined[:, :K]
        self.op = ar.undefined_op[:, :K]

    def __getitem__(self, rows) -> _Checks:
        return _Checks(parts=(self.jump[rows], self.maybe[rows], self.sure[rows],
                              self.op[rows]))


def confirm_points(problem: VerificationProblem, pts: np.ndarray) -> list[Counterexample]:
    """Rigorously check candidate points; return the confirmed counterexamples.

    A point is confirmed when every region constraint is ``≤ 0`` and some property is
    ``≥ 0`` at that point, both by outward-rounded interval evaluation.
    """
    pts = np.atleast_2d(np.asarray(pts, dtype=float))
    if not len(pts):
        return []
    lo, hi = problem.box[:, 0], problem.box[:, 1]
    pts = pts[np.all((pts >= lo) & (pts <= hi), axis=1)]
    if not len(pts):
        return []
    if problem.checked:
        enc, _, checks = _checked_eval(problem, pts, pts.copy(), jacobian=False)
        return _confirmed(problem, pts, enc, checks)
    enc = _point_enclosure(problem, pts)
    return _confirmed(problem, pts, enc)


def _confirmed(problem, pts, enc, checks: _Checks | None = None) -> list[Counterexample]:
    """Confirmed counterexamples among points with rigorous enclosures ``enc`` there.

    With ``checks`` (graphs with partial operations): a point is in the region only if
    every constraint is proved defined there; a property counts only where it is proved
    defined; a property certainly undefined at a point of the region (some operation
    certainly outside its domain) is reported as ``"domain of OP_..."``, with the value
    ``+inf``.
    """
    m = problem.n_constraints
    inside = np.all(enc.hi[:, :m] <= 0, axis=1) if m else np.ones(len(pts), bool)
    viol = enc.lo[:, m:] >= 0
    undefined = np.zeros_like(viol)
    if checks is not None:
        inside &= ~checks.maybe[:, :m].any(axis=1)
        viol &= ~checks.maybe[:, m:]
        undefined = checks.sure[:, m:]
    rows = np.nonzero(inside & (viol.any(axis=1) | undefined.any(axis=1)))[0]
    out = []
    for r in rows:
        if viol[r].any():
            j = int(np.argmax(np.where(viol[r], enc.lo[r, m:], -np.inf)))
            out.append(Counterexample(pts[r].copy(), problem.property_names[j],
                                      float(enc.lo[r, m + j]), float(enc.hi[r, m + j])))
        else:
            j = int(np.argmax(undefined[r]))
            op = int(checks.op[r, m + j])
            out.append(Counterexample(pts[r].copy(), f"domain of {op_name(op)}", np.inf,
                                      np.inf))
    out.sort(key=lambda c: -c.value_lower)
    return out


def _presearch(problem, n_samples: int, rng: np.random.Generator, steps: int = 4):
    """Float sampling plus projected gradient ascent on the worst property; returns points."""
    lo, hi = problem.box[:, 0], problem.box[:, 1]
    pts = lo + (hi - lo) * rng.random((n_samples, problem.n))
    m = problem.n_constraints
    F = _rows(evaluate(problem.function, [pts], NUMPY)[0], len(pts))
    score = _float_score(F, m)
    keep = np.argsort(-score)[: max(8, n_samples // 20)]
    pts = pts[keep]
    step = 0.02 * (hi - lo)
    FJ = problem.function_jacobian  # one pass for F and J (shared subexpressions)
    for _ in range(steps):
        F, J = evaluate(FJ, [pts], NUMPY)
        F, J = _rows(F, len(pts)), _rows(J, len(pts))
        J = np.swapaxes(J.reshape(len(pts), problem.n, -1), 1, 2)  # (N, m + k, n)
        j = m + np.argmax(F[:, m:], axis=1)
        grad = J[np.arange(len(pts)), j]
        # step towards larger violation, then back into the region along violated g
        pts = pts + step * np.sign(grad)
        if m:
            Fg, Jg = evaluate(FJ, [pts], NUMPY)
            Fg, Jg = _rows(Fg, len(pts))[:, :m], _rows(Jg, len(pts))
            Jg = np.swapaxes(Jg.reshape(len(pts), problem.n, -1), 1, 2)[:, :m]
            for i in range(m):
                bad = Fg[:, i] > 0
                if bad.any():
                    gi = Jg[bad, i]
                    nrm = np.maximum(np.sum(gi * gi, axis=1), 1e-300)
                    pts[bad] -= (1.0 + 1e-9) * (Fg[bad, i] / nrm)[:, None] * gi
        pts = np.clip(pts, lo, hi)
        step *= 0.6
    F = _rows(evaluate(problem.function, [pts], NUMPY)[0], len(pts))
    score = _float_score(F, m)
    return pts[np.argsort(-score)][: 64]


def _float_score(F, m):
    """Violation score: worst property value, minus constraint violation."""
    pen = np.maximum(F[:, :m], 0).sum(axis=1) if m else 0.0
    return np.max(F[:, m:], axis=1) - 1e3 * pen


def _boundary_presearch(problem, n_samples: int, rng: np.random.Generator,
                        steps: int = 3) -> np.ndarray:
    """Float points on the region's boundary that may violate a property, best first.

    Random points of the box, the ``k``-th assigned to constraint ``k mod m``, move onto
    ``g_k = −δ``, just inside the constraint's zero set, by Newton steps
    ``x ← x − (g_k + δ) ∇g_k / ‖∇g_k‖²`` (clipped to the box; ``δ``: ``10⁻⁹`` of the box's
    widest side times ``‖∇g_k‖``, well above the rounding of the rigorous confirmation);
    the best tenth then climbs the worst property along the boundary for ``steps`` steps
    (the gradient's component tangent to ``g_k = 0``, normalised, of a length from 5 % of
    the widest side down by 0.6 a step, together with the Newton correction), and two
    more Newton steps put them back on ``g_k = −δ`` (three and ``steps + 3`` float passes
    over the Jacobian graph). Counterexamples of Lyapunov queries
    often lie there (on the outer sphere, where the decrease is weakest), in a sliver
    that samples of the whole box miss. Returns the points (at most 64) whose float score
    (:func:`_float_score`) is ``≥ 0``: proposals for :func:`confirm_points`.
    """
    m = problem.n_constraints
    if not m or n_samples <= 0:
        return np.zeros((0, problem.n))
    lo, hi = problem.box[:, 0], problem.box[:, 1]
    n = problem.n
    width = float(np.max(hi - lo))
    pts = lo + (hi - lo) * rng.random((n_samples, n))
    which = np.arange(n_samples) % m

    def walk(pts, which, lengths):
        """One pass per entry of ``lengths``: a Newton step onto ``g_k = −δ`` plus a
        tangent step of that length up the worst property; then ``F`` at the end."""
        N = len(pts)
        rows = np.arange(N)
        for length in [*lengths, None]:
            F, J = evaluate(problem.function_jacobian, [pts], NUMPY)
            F = _rows(F, N)
            if length is None:
                return pts, F
            J = np.swapaxes(_rows(J, N).reshape(N, n, -1), 1, 2)  # (N, m + k, n)
            g, dg = F[rows, which], J[rows, which]
            nrm = np.sum(dg * dg, axis=1)
            ok = np.isfinite(g) & np.isfinite(nrm) & (nrm > 0)
            safe = np.where(ok, nrm, 1.0)
            move = -np.where(ok, (g + 1e-9 * width * np.sqrt(safe)) / safe, 0.0)[:, None] * dg
            if length:
                dp = J[rows, m + np.argmax(F[:, m:], axis=1)]
                dp = dp - np.where(ok, np.sum(dp * dg, axis=1) / safe, 0.0)[:, None] * dg
                size = np.sqrt(np.sum(dp * dp, axis=1))
                good = np.isfinite(size) & (size > 0)
                move += np.where(good, length / np.where(good, size, 1.0), 0.0)[:, None] * dp
            pts = np.clip(pts + np.where(np.isfinite(move), move, 0.0), lo, hi)

    pts, F = walk(pts, which, [0.0] * 2)
    keep = np.argsort(-_float_score(F, m), kind="stable")[: max(8, n_samples // 10)]
    climb = [0.05 * width * 0.6**i for i in range(steps)]
    pts, F = walk(pts[keep], which[keep], climb + [0.0, 0.0])
    score = _float_score(F, m)
    keep = np.flatnonzero(score >= 0)
    return pts[keep[np.argsort(-score[keep], kind="stable")]][:64]


def _affine_enclosure(problem: VerificationProblem, lo: np.ndarray, hi: np.ndarray):
    """Ranges ``(B, K)`` of the affine forms of ``F`` on boxes, and their sensitivities.

    Returns the ranges (:mod:`verification.affine`) and sensitivities ``(B, K, n)``: how
    much each output's bound owes to each input over the box, ``|g_i|`` (the linear
    part, half widths included) plus the remainder ``e`` shared in proportion to the
    widths (the splitting rule's measure; the share of an unknown remainder: the widths).
    """
    out = evaluate(problem.function, [Affine.from_box(lo, hi)], _AA)[0]
    rng = out.to_interval()
    B, n = lo.shape
    shape = (B, problem.n_constraints + problem.n_properties)
    # the remainder e (nonlinear terms, about quadratic in the half widths r) is shared
    # out in proportion to r_i; an unknown remainder (inf) counts as the widths alone
    r = hi - lo
    frac = r / np.maximum(r.sum(axis=1, keepdims=True), 1e-300)  # (B, n)
    e = to_shape(out.e, shape)
    known = np.isfinite(e) & np.isfinite(rng.lo) & np.isfinite(rng.hi)
    sens = np.where(known, e, 0.0)[..., None] * frac[:, None, :]
    if out.g is not None:
        g = np.moveaxis(np.abs(np.broadcast_to(out.g, (n,) + shape)), 0, -1)
        sens = sens + np.where(np.isfinite(g), g, 0.0)
    sens = np.where(known[..., None], sens, frac[:, None, :])
    lag = _lagrangian_holds(out, problem.n_constraints, shape)
    return (Interval(to_shape(rng.lo, shape), to_shape(rng.hi, shape)), sens,
            lag)


def _lagrangian_holds(out, m: int, shape) -> np.ndarray | None:
    """Per box and property: ``p_j < 0`` on the part of the box where ``g_k <= 0``.

    From the affine forms ``P = c_p + a·ε ± e_p`` and ``G = c_g + b·ε ± e_g`` (same ``ε``):
    for any ``λ >= 0``, ``p <= p - λ g <= c_p - λ c_g + Σ_i |a_i - λ b_i| + e_p + λ e_g``
    wherever ``g <= 0`` (there ``-λ g >= 0``); a negative bound proves the property on the
    region's part of the box although the box meets the constraint's boundary. Tried:
    ``λ = 0`` and the kinks ``λ = a_i / b_i > 0`` of this convex piecewise-linear
    function, one constraint at a time. Rounding: the float evaluation (about ``n + 8``
    operations, each erring by at most ``u`` times the sum ``M`` of the magnitudes of all
    terms) is raised by
    ``2**-40 M + 2**-1000``. ``None`` without constraints or input coefficients.
    """
    B, K = shape
    if not m or out.g is None:
        return None
    n = len(out.g)
    with np.errstate(all="ignore"):
        c = to_shape(out.c, shape)
        e = to_shape(out.e, shape)
        g = np.broadcast_to(out.g, (n,) + shape)
        holds = np.zeros((B, K - m), bool)
        for k in range(m):
            b = g[:, :, k][:, :, None]  # (n, B, 1)
            a = g[:, :, m:]  # (n, B, kp)
            lam = np.where(b != 0, a / np.where(b != 0, b, 1.0), 0.0)  # kinks (n, B, kp)
            lam = np.concatenate([np.zeros((1,) + lam.shape[1:]), lam], axis=0)
            lam = np.where(np.isfinite(lam) & (lam > 0), lam, 0.0)  # (n + 1, B, kp)
            lin = np.abs(a[None] - lam[:, None] * b[None]).sum(axis=1)  # (n + 1, B, kp)
            mag = (np.abs(a)[None] + lam[:, None] * np.abs(b)[None]).sum(axis=1)
            cp, ep = c[:, m:], e[:, m:]
            cg, eg = c[:, k][:, None], e[:, k][:, None]
            val = cp - lam * cg + lin + ep + lam * eg
            mag = mag + np.abs(cp) + lam * np.abs(cg) + ep + lam * eg
            bound = val + mag * 2.0**-40 + 2.0**-1000
            holds |= np.any(bound < 0, axis=0)
    return holds


def _enclose(problem, lo, hi, mean_value: bool, affine: bool = False):
    """See :func:`_enclose_all`; without its last item (affine sensitivities, λ proofs)."""
    return _enclose_all(problem, lo, hi, mean_value, affine)[:5]


def _enclose_all(problem, lo, hi, mean_value: bool, affine: bool = False,
                 second_order: bool = False):
    """Enclosures of F on boxes, F at the centres (rigorous), the interval Jacobian, checks.

    The boxes go through the fused ``(F, J)`` Function (shared subexpressions), the centres
    through ``F`` alone: two walker passes per round. For a problem with ``checked``
    Functions (non-smooth or partial operations) the walks also return per box and column
    the jump and domain flags (``None`` otherwise); a column whose box may hold a kink or
    jump of an operation feeding it, or an operation not proved inside its domain, keeps
    the natural extension only (the mean-value form needs a derivative on the whole box:
    CasADi's derivative is 0 across a jump). ``second_order`` (with ``mean_value``):
    intersect the properties of the boxes still undecided with
    :func:`_second_order_enclosure` (for ``checked`` problems only on the columns whose
    box is proved free of kinks and jumps and inside every domain).
    """
    B, n = lo.shape
    c = _centres(lo, hi)
    checked = problem.checked
    if mean_value == "undecided":
        enc, Fc, _, chk, chk_c, aux = _enclose_all(problem, lo, hi, False, affine)
        enc, J = _mean_value_where_undecided(problem, lo, hi, enc, Fc, chk, aux)
        if second_order:
            enc = _with_second_order(problem, lo, hi, enc, Fc, aux[1] if aux else None, chk,
                                     second_order == "affine")
        return enc, Fc, J, chk, chk_c, aux
    if not mean_value:
        if checked:
            both, _, chk = _checked_eval(problem, np.vstack([lo, c]), np.vstack([hi, c]),
                                         jacobian=False)
            enc, chk_b = both[:B], chk[:B]
            aux = None
            if affine:
                enc, aux = _with_affine(problem, lo, hi, enc, chk_b, _steps(affine))
            return enc, both[B:], None, chk_b, chk[B:], aux
        both = _rows(evaluate(problem.function,
                              [Interval(np.vstack([lo, c]), np.vstack([hi, c]))], _IA)[0],
                     2 * B)
        enc, aux = (_with_affine(problem, lo, hi, both[:B], None, _steps(affine)) if affine
                    else (both[:B], None))
        return enc, both[B:], None, None, None, aux
    chk = chk_c = None
    if checked:
        nat, Jall, chk = _checked_eval(problem, lo, hi, jacobian=True)
        Fc, _, chk_c = _checked_eval(problem, c, c.copy(), jacobian=False)
    else:
        nat, Jall = evaluate(problem.function_jacobian, [Interval(lo, hi)], _IA)
        nat, Jall = _rows(nat, B), _rows(Jall, B)
        Fc = _point_enclosure(problem, c)
    mk = nat.lo.shape[1]
    J = _IA.structural(lambda a: np.swapaxes(a.reshape(B, n, mk), 1, 2), Jall)
    # CasADi folds products of constants in float64 when it builds derivative graphs; the
    # interval arithmetic widens non-integer constants by 2^-50 (folds within 3 ulps), and
    # the mean-value form, which rests on the Jacobian graph being the derivative of F,
    # gets a further allowance: widen J by a relative 2^-30 before relying on it
    mag = np.maximum(np.abs(J.lo), np.abs(J.hi)) * 2.0**-30 + 2.0**-1000
    J = Interval(J.lo - mag, J.hi + mag)
    D = _IA.binary(ca.OP_SUB, Interval(lo, hi), Interval(c, c))  # rigorous X - c
    D = _IA.structural(lambda a: a[:, None, :], D)
    mv = _IA.binary(ca.OP_ADD, Fc, _IA.sum(_IA.binary(ca.OP_MUL, J, D), -1))
    enc = _IA.intersect(nat, mv)
    bad = ~(enc.lo <= enc.hi)  # empty intersection cannot happen for sound enclosures
    if chk is not None:
        bad |= chk.jump | chk.maybe  # no (valid) derivative on the box: natural only
    if bad.any():
        enc = Interval(np.where(bad, nat.lo, enc.lo), np.where(bad, nat.hi, enc.hi))
    aux = None
    if affine:
        enc, aux = _with_affine(problem, lo, hi, enc, chk, _steps(affine))
    if second_order:
        enc = _with_second_order(problem, lo, hi, enc, Fc, aux[1] if aux else None, chk,
                                 second_order == "affine")
    return enc, Fc, J, chk, chk_c, aux


def _mean_value_where_undecided(problem, lo, hi, enc: Interval, Fc: Interval, chk, aux):
    """``enc`` intersected with the mean-value form on the boxes it leaves undecided.

    The default with affine arithmetic: the Jacobian pass (the costliest) only for the
    boxes that the interval and affine bounds leave undecided (the decision rule of the
    branch-and-prune loop), with the per-column rule of :func:`_enclose_all` for kinks,
    jumps and domains. Returns the enclosure and the interval Jacobian ``(B, K, n)`` for
    the splitting rule (zero on decided boxes, which are not split), or ``None``.
    """
    m = problem.n_constraints
    lag = aux[1] if aux is not None else None
    pos = enc.hi[:, m:] < 0
    if lag is not None:
        pos = pos | lag
    g_pos = enc.lo[:, :m] > 0
    if chk is not None:
        defined = ~chk.maybe
        g_pos = g_pos & defined[:, :m]
        pos = pos & defined[:, m:]
    done = np.all(pos, axis=1)
    if m:
        done |= np.any(g_pos, axis=1)
    rows = np.flatnonzero(~done)
    if not len(rows):
        return enc, None
    lo_r, hi_r = lo[rows], hi[rows]
    B, n = lo_r.shape
    if problem.checked:
        nat, Jall, _ = _checked_eval(problem, lo_r, hi_r, jacobian=True)
    else:
        nat, Jall = evaluate(problem.function_jacobian, [Interval(lo_r, hi_r)], _IA)
        nat, Jall = _rows(nat, B), _rows(Jall, B)
    mk = nat.lo.shape[1]
    J = _IA.structural(lambda a: np.swapaxes(a.reshape(B, n, mk), 1, 2), Jall)
    mag = np.maximum(np.abs(J.lo), np.abs(J.hi)) * 2.0**-30 + 2.0**-1000  # as _enclose_all
    J = Interval(J.lo - mag, J.hi + mag)
    c = _centres(lo_r, hi_r)
    D = _IA.binary(ca.OP_SUB, Interval(lo_r, hi_r), Interval(c, c))  # rigorous X - c
    D = _IA.structural(lambda a: a[:, None, :], D)
    Fc_r = Interval(Fc.lo[rows], Fc.hi[rows])
    mv = _IA.binary(ca.OP_ADD, Fc_r, _IA.sum(_IA.binary(ca.OP_MUL, J, D), -1))
    old = Interval(enc.lo[rows], enc.hi[rows])
    new = _IA.intersect(old, _IA.intersect(nat, mv))
    bad = ~(new.lo <= new.hi)  # empty intersection cannot happen for sound enclosures
    if chk is not None:
        bad |= (chk.jump | chk.maybe)[rows]  # no (valid) derivative on the box
    lo_new, hi_new = enc.lo.copy(), enc.hi.copy()
    lo_new[rows] = np.where(bad, old.lo, new.lo)
    hi_new[rows] = np.where(bad, old.hi, new.hi)
    J_lo = np.zeros((len(lo), mk, n))
    J_hi = np.zeros((len(lo), mk, n))
    J_lo[rows] = J.lo
    J_hi[rows] = J.hi
    return Interval(lo_new, hi_new), Interval(J_lo, J_hi)


def _second_order_enclosure(problem, lo: np.ndarray, hi: np.ndarray, Fp: Interval,
                            affine_hessian: bool = False) -> Interval:
    r"""Second-order centred form of the properties on boxes ``[lo, hi]`` (``(B, n)``).

    With ``c`` the centre, ``d = x − c`` (``|d_i| ≤ h_i``), Taylor's theorem with the
    Lagrange remainder (``p`` is C² on the box; see :func:`_with_second_order`) gives
    ``p(x) = p(c) + ∇p(c)·d + ½ dᵀ∇²p(ξ)d`` for a ``ξ`` in the box, hence

    .. math:: p(x) \le \overline{p(c)} + \sum_i \max_{|t| \le h_i}\big(G_i|t| +
              \tfrac12 a_i t^2\big) + \tfrac12 \sum_{i \ne j} |H_{ij}| h_i h_j

    with ``G_i ≥ |∂_i p(c)|`` (the gradient graph evaluated on the point ``c`` in interval
    arithmetic), ``a_i ≥ ∂²_ii p`` and ``|H_ij| ≥ |∂²_ij p|`` on the box (the Hessian graph's
    interval extension); the lower bound is symmetric (``a_i ≥ −∂²_ii p``). The 1-D maximum
    is ``G h + ½ a h²`` when ``a ≥ 0`` or the vertex ``G/|a|`` lies beyond ``h`` (decided
    with a 2^-40 margin), else ``G²/(2|a|)``, an upper bound for every ``t``. Every sum and
    product runs in outward-rounded interval arithmetic. The gradient and Hessian graphs
    are widened by a relative 2^-30 (CasADi folds constants in float64 when it builds
    derivative graphs; as for the mean-value form). The point of the form: ``2(Px)·f(x)``
    enters only through ``∇²p`` on the box, so the interval dependency between ``Px`` and
    ``f(x)`` no longer grows with the box's width relative to ``|x|``.

    ``affine_hessian``: enclose the Hessian by the interval extension intersected with the
    range of its affine forms (:func:`verification.affine.tight_ranges`; tighter where the
    Hessian graph combines correlated terms, at the cost of an affine pass over it).

    Returns the ``(B, k)`` enclosure of the properties (``Fp``: their rigorous values at the
    centres); columns whose graphs give non-finite bounds come back as ``(−inf, inf)``.
    """
    B, n = lo.shape
    fG, fH = problem.second_order_functions
    c = _centres(lo, hi)
    k = problem.n_properties
    G = _rows(evaluate(fG, [Interval(c, c.copy())], _IA)[0], B)
    G = _IA.structural(lambda a: np.swapaxes(a.reshape(B, n, k), 1, 2), G)  # (B, k, n)
    # affine_hessian: the Hessian graph's interval extension ∩ its affine forms' range
    Hs = tight_ranges(fH, lo, hi) if affine_hessian else evaluate(fH, [Interval(lo, hi)], _IA)
    Hs = [_IA.structural(lambda a: np.swapaxes(a.reshape(B, n, n), 1, 2), _rows(h, B))
          for h in (Hs if isinstance(Hs, (list, tuple)) else [Hs])]
    H = Interval(np.stack([h.lo for h in Hs], 1), np.stack([h.hi for h in Hs], 1))  # (B,k,n,n)

    def widen(a: Interval) -> Interval:
        mag = np.maximum(np.abs(a.lo), np.abs(a.hi)) * 2.0**-30 + 2.0**-1000
        return Interval(a.lo - mag, a.hi + mag)

    G, H = widen(G), widen(H)
    D = _IA.binary(ca.OP_SUB, Interval(lo, hi), Interval(c, c))  # rigorous X − c
    h = np.maximum(np.abs(D.lo), np.abs(D.hi))                     # |d_i| <= h_i, exact
    Gm = np.maximum(np.abs(G.lo), np.abs(G.hi))                    # (B, k, n)
    idx = np.arange(n)
    Habs = np.maximum(np.abs(H.lo), np.abs(H.hi))
    Habs[:, :, idx, idx] = 0.0
    # ½ Σ_{i≠j} |H_ij| h_i h_j (outward)
    hh = _IA.binary(ca.OP_MUL, Interval(h[:, :, None], h[:, :, None]),
                    Interval(h[:, None, :], h[:, None, :]))        # (B, n, n)
    off = _IA.sum(_IA.binary(ca.OP_MUL, Interval(Habs, Habs),
                             Interval(hh.lo[:, None], hh.hi[:, None])), (2, 3))
    off = _IA.binary(ca.OP_MUL, off, Interval(np.full_like(off.lo, 0.5),
                                              np.full_like(off.hi, 0.5)))

    def one_d(a: np.ndarray) -> np.ndarray:
        """Upper bounds (B, k) of Σ_i max_{|t| <= h_i} (G_i |t| + ½ a_i t²)."""
        hb = np.broadcast_to(h[:, None, :], a.shape)
        GI, aI, hI3 = Interval(Gm, Gm), Interval(a, a), Interval(hb, hb)
        half = Interval(np.full_like(a, 0.5), np.full_like(a, 0.5))
        edge = _IA.binary(ca.OP_ADD, _IA.binary(ca.OP_MUL, GI, hI3),
                          _IA.binary(ca.OP_MUL, half, _IA.binary(
                              ca.OP_MUL, aI, _IA.unary(ca.OP_SQ, hI3))))
        neg = np.where(a < 0, -a, 1.0)
        vertex = _IA.binary(ca.OP_DIV, _IA.unary(ca.OP_SQ, GI),
                            _IA.binary(ca.OP_MUL, Interval(np.full_like(a, 2.0),
                                                           np.full_like(a, 2.0)),
                                       Interval(neg, neg)))
        inner = (a < 0) & ~(Gm >= -a * hb * (1.0 + 2.0**-40))  # vertex inside [−h, h]
        u = np.where(inner, vertex.hi, edge.hi)
        return _IA.sum(Interval(u, u), 2).hi

    diag = np.arange(n)
    up = one_d(H.hi[:, :, diag, diag])
    down = one_d(-H.lo[:, :, diag, diag])
    with np.errstate(invalid="ignore"):
        hi_b = _IA.sum(Interval(np.stack([Fp.hi, up, off.hi], -1),
                                np.stack([Fp.hi, up, off.hi], -1)), -1).hi
        lo_b = _IA.sum(Interval(np.stack([Fp.lo, -down, -off.hi], -1),
                                np.stack([Fp.lo, -down, -off.hi], -1)), -1).lo
    ok = np.isfinite(lo_b) & np.isfinite(hi_b) & (lo_b <= hi_b)
    return Interval(np.where(ok, lo_b, -np.inf), np.where(ok, hi_b, np.inf))


def _undecided_rows(enc: Interval, m: int, lag) -> np.ndarray:
    """Rows of the boxes that ``enc`` (``m`` constraint columns first) leaves undecided:
    no constraint ``> 0`` on the box, and some property not proved ``< 0`` (by ``enc``
    or, where ``lag`` says so, on the region's part of the box)."""
    pos = enc.hi[:, m:] < 0
    if lag is not None:
        pos = pos | lag
    done = np.all(pos, axis=1)
    if m:
        done |= np.any(enc.lo[:, :m] > 0, axis=1)
    return np.flatnonzero(~done)


def _with_second_order(problem, lo, hi, enc: Interval, Fc: Interval, lag, chk=None,
                       affine_hessian: bool = False, _pass: int = 0) -> Interval:
    """``enc`` intersected with :func:`_second_order_enclosure` on the property columns of
    the boxes that are neither outside the region nor decided; with ``affine_hessian``
    (``second_order="affine"``, set by ``precondition``), then also, on the boxes that this
    still leaves undecided, with the form whose Hessian is enclosed by affine forms too
    (a second pass only where the costlier one is needed).

    For a ``checked`` problem (``chk``: the per box and column flags), a column keeps
    ``enc`` where its box may hold a kink or jump, or an operation not proved inside its
    domain: the form needs ``p`` to be C² on the box. Where the flags clear a box, every
    non-smooth operation feeding the column stays on one smooth branch on all of it, and
    the Hessian graph's interval extension encloses that branch's Hessian (a comparison
    it cannot decide widens to both branches, still an enclosure).
    """
    m = problem.n_constraints
    rows = _undecided_rows(enc, m, lag)
    if not len(rows):
        return enc
    Fp = Interval(Fc.lo[rows, m:], Fc.hi[rows, m:])
    so = _second_order_enclosure(problem, lo[rows], hi[rows], Fp, _pass == 1)
    old = Interval(enc.lo[rows, m:], enc.hi[rows, m:])
    new = _IA.intersect(old, so)
    bad = ~(new.lo <= new.hi)  # cannot happen for sound enclosures: keep the old one
    if chk is not None:
        bad |= (chk.jump | chk.maybe)[rows][:, m:]
    lo_new, hi_new = enc.lo.copy(), enc.hi.copy()
    lo_new[rows, m:] = np.where(bad, old.lo, new.lo)
    hi_new[rows, m:] = np.where(bad, old.hi, new.hi)
    if affine_hessian and _pass == 0:
        return _with_second_order(problem, lo, hi, Interval(lo_new, hi_new), Fc, lag, chk,
                                  True, 1)
    return Interval(lo_new, hi_new)


def _with_affine(problem, lo, hi, enc: Interval, chk, backward: int | None = None):
    """``enc`` intersected with the affine-arithmetic ranges (columns with valid checks).

    Affine arithmetic encloses every operation it evaluates, across jumps too (non-smooth
    operations run on intervals), but the checked path's rule is kept: a column whose box
    may hold a kink or jump, or an operation not proved inside its domain, keeps ``enc``.
    Boxes that ``enc`` decides already are left out of the affine pass. Returns the
    enclosure and ``(sens, lag)``: the sensitivities of :func:`_affine_enclosure` and
    :func:`_lagrangian_holds` (``None``: nothing proved that way).
    """
    m = problem.n_constraints
    B, n = lo.shape
    # boxes that the interval enclosure decides already (outside, or all properties hold)
    # need no affine pass
    decided = np.all(enc.hi[:, m:] < 0, axis=1)
    if m:
        decided |= np.any(enc.lo[:, :m] > 0, axis=1)
    r = hi - lo
    frac = r / np.maximum(r.sum(axis=1, keepdims=True), 1e-300)
    if decided.all():
        return enc, (np.broadcast_to(frac[:, None, :], enc.lo.shape + (n,)), None)
    lag = None
    if decided.any():
        rows = np.flatnonzero(~decided)
        part, part_sens, part_lag = _affine_enclosure(problem, lo[rows], hi[rows])
        sens = np.repeat(frac[:, None, :], enc.lo.shape[1], axis=1)
        sens[rows] = part_sens
        alo, ahi = enc.lo.copy(), enc.hi.copy()
        alo[rows] = part.lo
        ahi[rows] = part.hi
        aff = Interval(alo, ahi)
        if part_lag is not None:
            lag = np.zeros((B, enc.lo.shape[1] - m), bool)
            lag[rows] = part_lag
    else:
        aff, sens, lag = _affine_enclosure(problem, lo, hi)
    if lag is not None and chk is not None:
        # the checked path's rule: only where every column involved is clean on the box
        clean = ~(chk.jump | chk.maybe)
        lag = lag & clean[:, m:] & np.all(clean[:, :m], axis=1, keepdims=True)
    both = _IA.intersect(enc, aff)
    keep = ~(both.lo <= both.hi)  # empty: cannot happen for sound enclosures
    if chk is not None:
        keep |= chk.jump | chk.maybe
    if keep.any():
        both = Interval(np.where(keep, enc.lo, both.lo), np.where(keep, enc.hi, both.hi))
    if backward is not None:
        both = _with_backward(problem, lo, hi, both, lag, keep, backward)
    return both, (sens, lag)


def _with_backward(problem, lo, hi, enc: Interval, lag, keep, slope_steps: int = 0,
                   optimised: bool = False) -> Interval:
    """``enc`` intersected with backward linear bounds on the boxes it leaves undecided.

    Constraints are bounded from below and properties from above (the sides the decision
    rule reads), by :func:`verification.backward.backward_bounds`; columns in ``keep``
    (kinks, jumps, domains: the checked path's rule) are left as they are. With
    ``slope_steps``, the boxes that the fixed slopes still leave undecided get a second
    pass with optimised slopes (``optimised``: this is that pass).
    """
    m = problem.n_constraints
    rows = _undecided_rows(enc, m, lag)
    if optimised:
        rows = rows[_within_reach(problem, lo[rows], hi[rows], enc, rows, m)]
    if not len(rows):
        return enc
    K = enc.lo.shape[1]
    low, _ = backward_bounds(problem.function, lo[rows], hi[rows],
                             np.diag(np.where(np.arange(K) < m, 1.0, -1.0)),
                             slope_steps if optimised else 0,
                             (lambda low: _decides(low, m)) if optimised else None)
    new_lo, new_hi = enc.lo.copy(), enc.hi.copy()
    blo = np.maximum(enc.lo[rows, :m], low[:m].T)
    bhi = np.minimum(enc.hi[rows, m:], -low[m:].T)
    k = keep[rows] if np.ndim(keep) else np.zeros((len(rows), K), bool)
    # both bounds are sound: an empty meet cannot happen, and would keep enc's bound
    new_lo[rows, :m] = np.where(~k[:, :m] & (blo <= enc.hi[rows, :m]), blo, enc.lo[rows, :m])
    new_hi[rows, m:] = np.where(~k[:, m:] & (bhi >= enc.lo[rows, m:]), bhi, enc.hi[rows, m:])
    out = Interval(new_lo, new_hi)
    if slope_steps and not optimised:
        return _with_backward(problem, lo, hi, out, lag, keep, slope_steps, True)
    return out


#: the share of a bound's overestimate (its distance from the value at the box's centre)
#: that optimised slopes are taken to remove at most: boxes that need more keep the fixed
#: slopes' bound (measured on random boxes of tanh networks: they remove 5 % to 65 %)
SLOPE_REACH = 0.5


def _within_reach(problem, lo, hi, enc: Interval, rows, m: int) -> np.ndarray:
    """Which of the boxes (rows ``rows`` of ``enc``) optimised slopes may decide: a
    constraint whose lower bound is below 0 by less than :data:`SLOPE_REACH` of its
    distance from the constraint's value at the centre, or every property not yet below 0
    within that reach of its own (a heuristic: it chooses where to spend the
    optimisation, never what is proved)."""
    if not len(rows):
        return np.zeros(0, bool)
    Fc = _point_enclosure(problem, _centres(lo, hi))
    e_lo, e_hi = enc.lo[rows], enc.hi[rows]
    with fp_ignored():
        reach_c = (e_lo[:, :m] <= 0) & (-e_lo[:, :m] < SLOPE_REACH * (Fc.lo[:, :m] - e_lo[:, :m]))
        prop = (e_hi[:, m:] < 0) | (e_hi[:, m:] < SLOPE_REACH * (e_hi[:, m:] - Fc.hi[:, m:]))
    return np.any(reach_c, axis=1) | np.all(prop, axis=1)


def _decides(low: np.ndarray, m: int) -> np.ndarray:
    """Per box, whether lower bounds ``low`` (``(K, B)``: ``m`` constraints from below,
    then the properties from above, negated) decide it: a constraint above 0, or every
    property below 0."""
    done = np.all(low[m:] > 0, axis=0)
    if m:
        done |= np.any(low[:m] > 0, axis=0)
    return done


class _Backward:
    """The internal ``affine`` flag of a check with backward bounds (true, as ``affine``
    is): the slope steps of its optimised pass (0: fixed slopes only)."""

    __slots__ = ("steps",)

    def __init__(self, steps: int):
        self.steps = int(steps)


def _steps(affine) -> int | None:
    """The slope steps of the backward bounds (``None``: no backward bounds)."""
    return affine.steps if isinstance(affine, _Backward) else None


def _centres(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The centres at which :func:`_enclose` evaluates ``F`` (same float points)."""
    return np.minimum(np.maximum(0.5 * (lo + hi), lo), hi)


def _initial_boxes(box: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
    """A uniform grid of about ``target`` sub-boxes of ``box`` (fewer rounds of bisection)."""
    n = len(box)
    k = max(1, int(np.floor(target ** (1.0 / n))))
    edges = [np.linspace(lo, hi, k + 1) for lo, hi in box]
    idx = np.stack(np.meshgrid(*[np.arange(k)] * n, indexing="ij"), -1).reshape(-1, n)
    lo = np.stack([edges[d][idx[:, d]] for d in range(n)], axis=1)
    hi = np.stack([edges[d][idx[:, d] + 1] for d in range(n)], axis=1)
    return lo, hi


def split_box(box: np.ndarray, parts: int) -> list[np.ndarray]:
    """Split a box into ``parts`` (a power of two) sub-boxes along the widest dimensions."""
    boxes = [np.asarray(box, dtype=float)]
    while len(boxes) < parts:
        nxt = []
        for b in boxes:
            i = int(np.argmax(b[:, 1] - b[:, 0]))
            mid = 0.5 * (b[i, 0] + b[i, 1])
            left, right = b.copy(), b.copy()
            left[i, 1] = mid
            right[i, 0] = mid
            nxt += [left, right]
        boxes = nxt
    return boxes


def verify_interval(
    problem: VerificationProblem,
    *,
    resolution: float | None = None,
    max_boxes: int = 2_000_000,
    batch: int = 8192,
    mean_value: bool | None = None,
    affine: bool = True,
    backward: bool = False,
    slope_steps: int = 0,
    presearch: int = 500,
    presearch_boundary: int = 0,
    stop_at_first: bool = True,
    keep_leaves: bool = False,
    seed: int = 0,
    initial_boxes: int = 256,
    executor: Executor | None = None,
    n_tasks: int | None = None,
    progress: bool = False,
    second_order: bool = False,
    boxes: np.ndarray | None = None,
    hand_back: bool = False,
    hand_back_below: int = 0,
    precondition: bool = False,
    partition: bool = False,
) -> VerificationResult:
    """Decide ``problem`` with interval branch-and-prune; see :func:`verification.verify`.

    ``affine`` (default): intersect the enclosures with the ranges of affine forms
    (:mod:`verification.affine`) and decide boxes across a constraint's boundary by
    ``p − λ g < 0``. ``mean_value``: intersect with the mean-value form
    ``F(c) + J(X)(X − c)`` (one more walker pass, over the Jacobian graph) and split by
    the interval Jacobian's smear; ``None`` (default): on every box without ``affine``,
    with it on the boxes the other bounds leave undecided (the boxes to split);
    ``False`` with ``affine``: split where the affine bounds are most sensitive.
    ``backward`` (with ``affine``; off by default): also bound each constraint from below
    and each property from above by backward linear bound propagation
    (:mod:`verification.backward`, CROWN style, recorded in the affine pass) and keep the
    tighter bound: fewer boxes on deep networks (a 2-30-30 tanh V on Van der Pol: 818
    boxes instead of 1 294) at about twice the cost of the affine pass per box.
    ``slope_steps`` (with ``backward``; default 0): on the boxes the fixed slopes still leave
    undecided, optimise the relaxations' slopes and the product planes per box by this many
    gradient steps (:mod:`verification.slopes`, as α-CROWN does) and keep the tighter
    bound; tens to a hundred times the cost of the fixed-slope pass on those boxes.
    ``second_order``: on the boxes those leave undecided, also the second-order centred
    form of the properties (:func:`_second_order_enclosure`; one more pass, over the
    properties' Hessian graphs; for ``checked`` problems only where a box is proved free
    of kinks and jumps; ignored without ``mean_value``). It removes the interval
    dependency of Lie derivatives such as ``2(Px)·f(x)``, which otherwise needs boxes ever
    smaller next to the inner ball and grows as ``(1/width)^n``; worth its cost from 3 or
    4 states on. ``second_order="affine"`` (what ``precondition`` passes on): on the boxes
    the form still leaves undecided, once more with the Hessian also enclosed by affine
    forms (:func:`verification.affine.tight_ranges`). ``boxes`` (``(k, n, 2)``, sub-boxes
    of the problem's box): start from them, all in one batch, instead of the root box's
    grid (the load-balanced tasks of
    :func:`nlyap_opt.distributed.parallel.verify_distributed`; the verdict is about their union).
    ``hand_back``: once ``max_boxes`` are spent, a box still to bisect is bisected by the
    usual rule and its two halves come back *unevaluated* in ``result.open`` (not in
    ``undecided``), so that the task that takes them on evaluates no box twice.
    ``hand_back_below`` (with ``hand_back``): also hand back, after the first pass, a
    queue that has shrunk below this many boxes (a pass costs a fixed time per graph
    instruction besides its time per box: the caller merges such tails of several tasks
    into one task's passes).
    ``presearch``: random points of the box (and a few gradient steps) tried as
    counterexamples before bisection (0: none; the tasks of a distributed check run
    without); ``presearch_boundary`` (default 0: off): where those confirm none, as many
    random points moved onto the constraints' zero sets
    (:func:`_boundary_presearch`: the outer sphere of a Lyapunov query, where its
    counterexamples often lie) are tried too, a few float passes instead of the rounds of
    bisection that reach such a sliver (the counterexample found can then be another one).
    ``precondition``: verify in the coordinates ``z = |H|^{1/2} x`` of the last property's
    Hessian ``H`` at the root box's centre, where it is definite
    (:mod:`verification.precondition`: for a stiff loop, the decrease becomes about ``±|z|²``;
    the result is stated about ``problem``; ``resolution`` then applies to widths in ``z``).
    ``partition``: a verified result records the bisection tree it decided (up to 127
    states: a node's side is coded in one byte), in ``result.partition``
    (``{"initial_boxes": k, "codes": int8 array}``, see :func:`partition_leaves`): a later
    check of the same problem can start from its leaves (``boxes=partition_leaves(...)``)
    instead of searching for them again.
    """
    conflict = option_conflict({"slope_steps": slope_steps, "backward": backward,
                                "affine": affine})
    if conflict:
        raise ValueError(conflict)
    batch = min(int(batch), memory_batch(problem, second_order))
    if partition and (boxes is not None or hand_back or executor is not None or precondition):
        raise ValueError("partition records a run from the root box's grid: it excludes "
                         "boxes, hand_back, executor and precondition")
    if precondition:
        if boxes is not None or hand_back or keep_leaves:
            raise ValueError("precondition excludes boxes, hand_back and keep_leaves")
        return solve_preconditioned(
            problem, hessian_coordinates(problem),
            lambda p: verify_interval(
                p, resolution=resolution, max_boxes=max_boxes, batch=batch,
                mean_value=mean_value, affine=affine, backward=backward,
                slope_steps=slope_steps, presearch=presearch,
                presearch_boundary=presearch_boundary,
                stop_at_first=stop_at_first, seed=seed, initial_boxes=initial_boxes,
                executor=executor, n_tasks=n_tasks, progress=progress,
                second_order="affine" if second_order else False),
            confirm_points)
    t0 = time.perf_counter()
    if mean_value is None:  # with affine forms: the mean-value form on undecided boxes
        mean_value = "undecided" if affine else True
    box = problem.box
    width = box[:, 1] - box[:, 0]
    if resolution is None:
        resolution = 1e-4 * float(np.max(width))
    # "affine" (passed on by precondition): with the affine Hessian pass; else a bool
    second_order = (second_order if second_order == "affine" else bool(second_order)) \
        if mean_value else False
    if second_order:
        problem.second_order_functions  # built here, so that they travel to workers
    if boxes is not None:
        boxes = np.asarray(boxes, dtype=float)
        if boxes.ndim != 3 or boxes.shape[1:] != (problem.n, 2) or \
                np.any(boxes[:, :, 0] > boxes[:, :, 1]):
            raise DimensionError(f"boxes must have shape (k, {problem.n}, 2) with lower <= "
                                 f"upper, got {boxes.shape}")
        if executor is not None:
            raise ValueError("boxes and executor exclude each other: give one of them")
    if executor is not None:
        return _verify_distributed(problem, executor, n_tasks, t0, resolution=resolution,
                                   max_boxes=max_boxes, batch=batch, mean_value=mean_value,
                                   affine=affine, backward=backward,
                                   slope_steps=slope_steps, presearch=presearch,
                                   presearch_boundary=presearch_boundary,
                                   stop_at_first=stop_at_first, keep_leaves=keep_leaves, seed=seed,
                                   initial_boxes=initial_boxes, second_order=second_order)
    with _single_thread_blas(), fp_ignored():
        return _verify_local(problem, t0, resolution, max_boxes, batch, mean_value, presearch,
                             stop_at_first, keep_leaves, seed, initial_boxes, progress,
                             affine and (_Backward(slope_steps) if backward else True),
                             second_order,
                             boxes, hand_back,
                             int(hand_back_below) if hand_back else 0, presearch_boundary,
                             partition)


def _verify_local(problem, t0, resolution, max_boxes, batch, mean_value, presearch,
                  stop_at_first, keep_leaves, seed, initial_boxes, progress, affine=False,
                  second_order=False, boxes=None, hand_back=False, hand_back_below=0,
                  presearch_boundary=0, partition=False):
    box = problem.box
    compile_function(problem.function_jacobian)
    rng = np.random.default_rng(seed)
    found: list[Counterexample] = []
    if presearch:
        found = confirm_points(problem, _presearch(problem, presearch, rng))
        if found and stop_at_first:
            return VerificationResult("counterexample", found[0], found, boxes=0, depth=0,
                                      seconds=time.perf_counter() - t0)
    if presearch and presearch_boundary and not found:  # after a random pre-search found none
        found = confirm_points(problem, _boundary_presearch(
            problem, presearch_boundary, np.random.default_rng([seed, 1])))
        if found and stop_at_first:
            return VerificationResult("counterexample", found[0], found, boxes=0, depth=0,
                                      seconds=time.perf_counter() - t0)
    m = problem.n_constraints
    if boxes is None:
        queue_lo, queue_hi = _initial_boxes(box, initial_boxes)
    else:   # given sub-boxes of the root box (a task of nlyap_opt.distributed.parallel), all in one
            # batch
        queue_lo, queue_hi = boxes[:, :, 0].copy(), boxes[:, :, 1].copy()
    depth_q = np.zeros(len(queue_lo), dtype=int)
    # partition: the node number of each queued box (the grid's cells first), and per
    # bisected node its split dimension and its children's numbers
    tree = _Tree(len(queue_lo)) if partition and problem.n <= 127 else None  # a byte a side
    undecided: list[np.ndarray] = []
    opened: list[np.ndarray] = []  # hand_back: halves not evaluated here
    leaves: list[dict] | None = [] if keep_leaves else None
    n_boxes = 0
    max_depth = 0
    while len(queue_lo):
        if n_boxes and len(queue_lo) < hand_back_below:  # a thin tail: to be merged
            opened.append(np.stack([queue_lo, queue_hi], axis=-1))
            break
        lo, hi, dq = queue_lo[:batch], queue_hi[:batch], depth_q[:batch]
        queue_lo, queue_hi, depth_q = queue_lo[batch:], queue_hi[batch:], depth_q[batch:]
        if tree is not None:
            ids, tree.queue = tree.queue[:batch], tree.queue[batch:]
        n_boxes += len(lo)
        max_depth = max(max_depth, int(dq.max()))
        enc, Fc, J, chk, chk_c, aux = _enclose_all(problem, lo, hi, mean_value, affine,
                                                   second_order)
        sens, lag = aux if aux is not None else (None, None)
        g_lo, g_hi = enc.lo[:, :m], enc.hi[:, :m]
        p_hi = enc.hi[:, m:]
        if chk is None:
            outside = np.any(g_lo > 0, axis=1) if m else np.zeros(len(lo), bool)
            holds = np.all((p_hi < 0) if lag is None else (p_hi < 0) | lag, axis=1)
        else:
            # partial domains: a constraint prunes the box only if it is defined on all of it
            # (outside the region the properties need not be defined); the properties hold on the
            # box only if each is defined on all of it (then p < 0 at every point of the
            # box, whatever a constraint that is undefined somewhere would have said)
            defined = ~chk.maybe
            outside = (np.any((g_lo > 0) & defined[:, :m], axis=1) if m
                       else np.zeros(len(lo), bool))
            holds = np.all(((p_hi < 0) if lag is None else (p_hi < 0) | lag)
                           & defined[:, m:], axis=1)
        done = outside | holds
        # centre points: rigorous counterexample confirmation
        inside_c = np.all(Fc.hi[:, :m] <= 0, axis=1) if m else np.ones(len(lo), bool)
        viol_c = np.any(Fc.lo[:, m:] >= 0, axis=1)
        if chk_c is not None:
            viol_c |= chk_c.sure[:, m:].any(axis=1)
        viol_c &= inside_c & ~done
        if viol_c.any():
            found += _confirmed(problem, _centres(lo, hi)[viol_c],
                                Interval(Fc.lo[viol_c], Fc.hi[viol_c]),
                                None if chk_c is None else chk_c[viol_c])
            if stop_at_first and found:
                found.sort(key=lambda c: -c.value_lower)
                return VerificationResult("counterexample", found[0], found, boxes=n_boxes,
                                          depth=max_depth, seconds=time.perf_counter() - t0)
        if keep_leaves and done.any():
            leaves.append({"lo": lo[done], "hi": hi[done], "enc_lo": enc.lo[done],
                           "enc_hi": enc.hi[done]})
        rest = ~done
        w = hi - lo
        small = rest & (np.max(w, axis=1) <= resolution)
        if small.any():
            undecided.append(np.stack([lo[small], hi[small]], axis=-1))
        split = rest & ~small
        if not split.any():
            continue
        over = n_boxes + len(queue_lo) > max_boxes
        if over and not hand_back:
            undecided.append(np.stack([lo[split], hi[split]], axis=-1))
            continue
        lo_s, hi_s, w_s = lo[split], hi[split], w[split]
        if J is not None:
            mag = np.maximum(np.abs(J.lo[split]), np.abs(J.hi[split]))  # (b, m+k, n)
            mag = np.where(np.isfinite(mag), mag, 1e300)
            active = np.concatenate(
                [(g_lo[split] <= 0) & (g_hi[split] > 0), p_hi[split] >= 0], axis=1)
            if chk is not None:
                active |= chk.maybe[split]
            smear = np.max(mag * w_s[:, None, :] * active[:, :, None], axis=1)
            dim = np.argmax(smear + 1e-300 * w_s, axis=1)
            flat = np.max(smear, axis=1) <= 0
            if chk is not None:  # no valid derivative on the box: bisect the widest side
                flat |= np.any((chk.jump | chk.maybe)[split], axis=1)
            dim[flat] = np.argmax(w_s[flat], axis=1)
        elif sens is not None:
            # the affine forms' input coefficients |g_ji| (half widths included): split
            # where the active outputs' bounds are most sensitive
            open_p = p_hi[split] >= 0
            if lag is not None:
                open_p &= ~lag[split]
            active = np.concatenate([(g_lo[split] <= 0) & (g_hi[split] > 0), open_p], axis=1)
            if chk is not None:
                active |= chk.maybe[split]
            smear = np.max(sens[split] * active[:, :, None], axis=1)
            dim = np.argmax(smear + 1e-300 * w_s, axis=1)
            flat = np.max(smear, axis=1) <= 0
            if chk is not None:
                flat |= np.any((chk.jump | chk.maybe)[split], axis=1)
            dim[flat] = np.argmax(w_s[flat], axis=1)
        else:
            dim = np.argmax(w_s, axis=1)
        rows = np.arange(len(lo_s))
        mid = 0.5 * (lo_s[rows, dim] + hi_s[rows, dim])
        left_hi = hi_s.copy()
        left_hi[rows, dim] = mid
        right_lo = lo_s.copy()
        right_lo[rows, dim] = mid
        d = dq[split] + 1
        if tree is not None:
            tree.split(ids[split], dim)
        if over:  # hand_back: the halves go to another task, unevaluated
            opened.append(np.stack([np.concatenate([lo_s, right_lo]),
                                    np.concatenate([left_hi, hi_s])], axis=-1))
            continue
        # depth-first-ish: put children in front so the queue stays small
        queue_lo = np.concatenate([lo_s, right_lo, queue_lo])
        queue_hi = np.concatenate([left_hi, hi_s, queue_hi])
        depth_q = np.concatenate([d, d, depth_q])
        if progress and n_boxes % (batch * 10) < batch:
            print(f"  verify: {n_boxes} boxes, {len(queue_lo)} queued, depth {max_depth}",
                  flush=True)
    seconds = time.perf_counter() - t0
    und = np.concatenate(undecided) if undecided else np.zeros((0, problem.n, 2))
    opn = np.concatenate(opened) if opened else np.zeros((0, problem.n, 2))
    if found:
        found.sort(key=lambda c: -c.value_lower)
        return VerificationResult("counterexample", found[0], found, und, n_boxes, max_depth,
                                  seconds, leaves, open=opn if hand_back else None)
    status = "unknown" if len(und) or len(opn) else "verified"
    res = VerificationResult(status, None, [], und, n_boxes, max_depth, seconds, leaves,
                             open=opn if hand_back else None)
    if tree is not None and status == "verified":
        res.partition = {"initial_boxes": int(initial_boxes), "codes": tree.codes()}
    return res


class _Tree:
    """The bisection tree of one serial run (``verify_interval(partition=True)``).

    Nodes are numbered as they are made: the first grid's cells ``0 .. k-1``, then the two
    halves of each bisected box, left then right. ``queue`` holds the numbers of the boxes
    queued, in the verifier's queue order.
    """

    def __init__(self, cells: int):
        self.queue = np.arange(cells, dtype=np.int64)
        self.cells = cells
        self.made = cells
        self.parents: list[np.ndarray] = []
        self.dims: list[np.ndarray] = []
        self.lefts: list[np.ndarray] = []

    def split(self, ids: np.ndarray, dim: np.ndarray) -> None:
        """The boxes ``ids`` are bisected along ``dim``; their halves go to the queue's
        front as the verifier puts them (all left halves, then all right halves)."""
        s = len(ids)
        left = self.made + np.arange(s, dtype=np.int64)
        self.made += 2 * s
        self.parents.append(ids)
        self.dims.append(np.asarray(dim, dtype=np.int64))
        self.lefts.append(left)
        self.queue = np.concatenate([left, left + s, self.queue])

    def codes(self) -> np.ndarray:
        """The tree in breadth-first order: per node ``-1`` (a leaf) or its split
        dimension; the cells first, then each level's children: the left halves of the
        level before's bisected nodes in its order, then their right halves."""
        dim_of = np.full(self.made, -1, dtype=np.int64)
        left_of = np.zeros(self.made, dtype=np.int64)
        right_of = np.zeros(self.made, dtype=np.int64)
        if self.parents:
            p = np.concatenate(self.parents)
            dim_of[p] = np.concatenate(self.dims)
            left = np.concatenate(self.lefts)
            left_of[p] = left
            right_of[p] = left + np.concatenate([np.full(len(x), len(x)) for x in self.lefts])
        level = np.arange(self.cells, dtype=np.int64)
        out = []
        while len(level):
            c = dim_of[level]
            out.append(c)
            sp = level[c >= 0]
            level = np.concatenate([left_of[sp], right_of[sp]])
        return np.concatenate(out).astype(np.int8)


#: the most numbers (nodes times states) in a tree :func:`partition_leaves` decodes: 8
#: million nodes in 4-D, 16 times the default box budget of a check (a level of the tree
#: then needs at most 256 MB)
MAX_PARTITION_ENTRIES = 1 << 25

#: the most levels per state of a tree: a float side is halved to nothing within this
MAX_PARTITION_LEVELS = 1130


def partition_leaves(box: np.ndarray, initial_boxes: int, codes: np.ndarray) -> np.ndarray:
    """The leaf boxes ``(k, n, 2)`` of a bisection tree of ``box`` (``result.partition``).

    The tree starts from the verifier's first grid of ``initial_boxes`` cells and bisects
    each node coded ``d >= 0`` at the midpoint of side ``d``, as the verifier does, so the
    leaves are the boxes a serial run decided, and together they cover ``box`` whatever
    the codes say: a code can change which boxes are checked, never what they cover.

    Raises
    ------
    ValueError
        The codes are not a whole tree of ``box``: a code outside ``-1 .. n-1``, too few
        or too many codes, more nodes than :data:`MAX_PARTITION_ENTRIES` over ``n``, or
        more levels than :data:`MAX_PARTITION_LEVELS` times ``n``.
    """
    box = np.asarray(box, dtype=float)
    n = len(box)
    codes = np.asarray(codes)
    if codes.ndim != 1 or codes.dtype.kind not in "iu":
        raise ValueError("partition codes must be a 1-D integer array")
    if len(codes) * max(n, 1) > MAX_PARTITION_ENTRIES:
        raise ValueError(f"a partition of {len(codes)} nodes in {n}-D is more than the "
                         f"{MAX_PARTITION_ENTRIES // max(n, 1)} that are decoded")
    if len(codes) and (int(codes.min()) < -1 or int(codes.max()) >= n):
        raise ValueError(f"partition codes must lie in -1 .. {n - 1} for a {n}-D box")
    lo, hi = _initial_boxes(box, int(initial_boxes))
    level = np.stack([lo, hi], axis=-1)
    at = 0
    out = []
    depth = 0
    while len(level):
        depth += 1
        if depth > MAX_PARTITION_LEVELS * n + 1:
            raise ValueError(f"the partition is deeper than {MAX_PARTITION_LEVELS * n} levels")
        m = len(level)
        if at + m > len(codes):
            raise ValueError(f"the partition's codes end after {len(codes)} nodes, inside "
                             "the tree")
        c = codes[at:at + m]
        at += m
        split = c >= 0
        out.append(level[~split])
        parent = level[split]
        k = len(parent)
        rows = np.arange(k)
        dim = c[split].astype(np.intp)
        # the verifier's split (_verify_local), on stacked bounds: one copy a level instead
        # of four (a third of the decoding time); tests check the leaves are its boxes
        mid = 0.5 * (parent[rows, dim, 0] + parent[rows, dim, 1])
        level = np.concatenate([parent, parent])  # left halves, then right halves
        level[rows, dim, 1] = mid
        level[k + rows, dim, 0] = mid
    if at != len(codes):
        raise ValueError(f"the partition has {len(codes) - at} codes after its tree ends")
    return np.concatenate(out)


def _run_sub(problem, kwargs):
    return verify_interval(problem, **kwargs)


def _verify_distributed(problem, executor, n_tasks, t0, **kwargs) -> VerificationResult:
    parts = n_tasks or 8
    parts = 1 << max(0, int(np.ceil(np.log2(parts))))
    subs = []
    for b in split_box(problem.box, parts):
        p = copy.copy(problem)
        p.box = b
        subs.append(p)
    futures = [executor.submit(_run_sub, p, kwargs) for p in subs]
    results = [f.result() for f in futures]
    found = sorted([c for r in results for c in r.counterexamples], key=lambda c: -c.value_lower)
    und = [r.undecided for r in results if len(r.undecided)]
    und = np.concatenate(und) if und else np.zeros((0, problem.n, 2))
    boxes = sum(r.boxes for r in results)
    depth = max(r.depth for r in results)
    leaves = None
    if kwargs.get("keep_leaves"):
        leaves = [leaf for r in results for leaf in (r.leaves or [])]
    seconds = time.perf_counter() - t0
    if found:
        return VerificationResult("counterexample", found[0], found, und, boxes, depth, seconds,
                                  leaves)
    return VerificationResult("unknown" if len(und) else "verified", None, [], und, boxes,
                              depth, seconds, leaves)


# ============================================================================ memory
#: the numbers (float64) a pass may hold over the walked graphs' work vectors: a batch of
#: boxes is cut to ``MEMORY_NUMBERS // (largest work vector)`` (1 GiB of float64 for every
#: copy the arithmetic keeps: bounds, affine coefficients)
MEMORY_NUMBERS = 2**27


def memory_batch(problem: VerificationProblem, second_order: bool = False) -> int:
    """The most boxes a pass over ``problem``'s graphs may take: its work vectors (every
    register of the walked Functions: a network's layers, their Jacobians) times the boxes
    stay within :data:`MEMORY_NUMBERS` (at least 16 boxes).

    Graphs of the usual sizes allow far more than the default batch (a 2-30-30 network on
    Van der Pol: about 38 000 boxes); a network of 10⁵ neurons allows about 100, where a
    full batch held tens of GB.
    """
    funs = [problem.function_jacobian_checked if problem.checked else problem.function_jacobian]
    if second_order:
        try:
            funs += list(problem.second_order_functions)
        except ValueError:   # an unpickled problem without them: not walked here either
            pass
    work = max(max(int(f.sz_w()), 1) for f in funs)
    return max(16, MEMORY_NUMBERS // work)


# ============================================================================ options in files
#: keyword options of :func:`verify_interval` that are run-time objects, not settings a file
#: (a run configuration, a certificate) can hold
RUNTIME_OPTIONS = ("executor", "progress", "boxes", "hand_back", "hand_back_below", "partition")


def file_options() -> dict[str, tuple]:
    """The options of :func:`verify_interval` a file may hold, with their ranges:
    ``name -> (type hint, default, lowest value or None, lowest value excluded)``.

    The one definition behind the run configuration's ``cegis.verify_options`` keys
    (:func:`nlyap_opt.workflow.configs.schema`) and the check of the options a certificate was
    proved with (:func:`check_file_options`).
    """

    hints = typing.get_type_hints(verify_interval)
    out = {}
    for name, par in inspect.signature(verify_interval).parameters.items():
        if par.kind is not inspect.Parameter.KEYWORD_ONLY or name in RUNTIME_OPTIONS:
            continue
        hint = hints.get(name, object)
        base = _plain_type(hint)
        lo = (0, True) if base is float else \
            (0 if name in ("seed", "presearch", "presearch_boundary", "slope_steps") else 1,
             False) \
            if base is int else (None, False)
        out[name] = (hint, par.default, *lo)
    return out


def _plain_type(hint):
    """``int`` of ``int | None`` (else the hint itself)."""

    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        rest = [a for a in typing.get_args(hint) if a is not type(None)]
        return rest[0] if len(rest) == 1 else hint
    return hint


def check_file_options(opts, where: str, fix: str) -> dict:
    """Options read from a file, checked against :func:`file_options` (names, types,
    ranges); a one-line :class:`~nlyap_opt.kernel.errors.ConfigError` naming ``where``, the first
    bad option and ``fix``."""

    if opts is None:
        return {}
    known = file_options()
    if not isinstance(opts, dict):
        raise ConfigError(f"{where}: verify_options must be a JSON object of verifier options "
                          f"({', '.join(known)}), got {opts!r}; {fix}")
    for name, v in opts.items():
        if name not in known:
            raise ConfigError(f"{where}: unknown verifier option {name!r} (options: "
                              f"{', '.join(known)}); {fix}")
        hint, default, lo, lo_open = known[name]
        base = _plain_type(hint)
        if v is None:
            ok = base is not hint   # an optional option
        elif base is bool:
            ok = isinstance(v, bool)
        elif base is int:
            ok = isinstance(v, int) and not isinstance(v, bool)
        elif base is float:
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)
        else:
            ok = True
        if ok and v is not None and lo is not None and (v < lo or (lo_open and v == lo)):
            ok = False
        if not ok:
            what = {bool: "true or false", int: "an integer", float: "a finite number"}.get(
                base, str(base))
            rng = "" if lo is None else f" {'>' if lo_open else '>='} {lo}"
            raise ConfigError(f"{where}: verifier option {name!r} must be {what}{rng}, got "
                              f"{v!r}; {fix}")
    conflict = option_conflict(opts)
    if conflict:
        raise ConfigError(f"{where}: {conflict}; {fix}")
    return dict(opts)


def option_conflict(opts: dict) -> str | None:
    """What makes verifier options that are each valid useless together (``None``: nothing):
    an option that works only with another that is off."""
    if opts.get("slope_steps") and not (opts.get("backward") and opts.get("affine", True)):
        return ("verifier option 'slope_steps' optimises the slopes of the backward bounds: "
                "set 'backward' (and 'affine') to true with it, or 'slope_steps' to 0")
    if opts.get("backward") and not opts.get("affine", True):
        return ("verifier option 'backward' works on the affine forms' pass: set 'affine' to "
                "true with it, or 'backward' to false")
    return None
