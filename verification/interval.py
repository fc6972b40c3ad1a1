"""Rigorous, vectorised interval arithmetic with outward rounding.

An :class:`Interval` holds two float64 arrays ``lo`` and ``hi`` (many boxes at once);
:class:`IntervalArithmetic` implements the arithmetic interface of the instruction walker
(``constant``, ``unary``, ``binary``, ``matmul``, ``sum``, ``structural``) so that a CasADi
graph evaluated with it returns *enclosures*: for every real point of the input boxes the
real-valued result lies in ``[lo, hi]``.

Invariants and conventions
--------------------------
- Results satisfy ``lo <= hi``, are never NaN, ``lo < +inf`` and ``hi > -inf`` (a lower
  bound that overflowed becomes ``float_max``, which is still below the true value),
  provided the inputs satisfy the same (boxes of the verifier are finite; constants are
  made so by :meth:`IntervalArithmetic.constant`).
- ``[-inf, inf]`` means "nothing is known". It is returned where a result is undefined or
  cannot be bounded: division by an interval containing 0, a pole of ``tan`` inside the
  box, any NaN that an operation would produce (``_guard``), and inputs that lie *entirely*
  outside the domain of a function (``sqrt([-2, -1])``, ``log([-1, 0])``).
- Inputs *partly* outside the real domain of a function are enclosed over the in-domain
  part (documented domain clipping): ``sqrt([-1, 4]) = [0, 2]``, ``log([-1, 1]) =
  [-inf, 0]``, ``asin([0, 2]) = [0, pi/2]``, ``x**0.5`` for ``x = [-1, 4]`` is ``[0, 2]``.
  Out-of-domain points have no real value, so a verifier that needs the function to be
  defined on the whole box must check the domain separately:
  :class:`CheckedIntervalArithmetic` does (per box and output, with the kink/jump checks
  of non-smooth operations), and ``verification.verify`` uses it.
- Degenerate intervals (``Interval(v, v)``: points, all-integer constants) share one array
  for ``lo`` and ``hi`` (``a.lo is a.hi``); operations use this for cheaper exact paths.
  Results may share memory with their arguments (``OP_ASSIGN``, structural views, ``x**1``):
  treat the bound arrays as read-only.

Cost
----
Every operation is a fixed number of whole-array numpy passes (no Python loops over
elements): about 10 for ``+``/``-``, 20 for ``*``, 2 elementary-function calls plus about
12 passes for ``exp``, ``tanh``, ...; ``matmul`` is 2-3 GEMMs plus about 15 passes over
its operands and result; ``sum`` uses BLAS (``x @ ones``) for trailing axes. The work is
memory-bound, so batches whose registers fit in the L2 cache are fastest.

Rounding model
--------------
numpy computes in IEEE double precision with round-to-nearest. For a correctly rounded
operation (``+ - * /`` and ``sqrt``) the computed ``y`` is within half an ulp of the real
result, so ``dn(y) = min(y*(1-2**-52), y*(1+2**-52)) - 2**-1074`` (at least one float
below ``y``) is a lower bound, and ``up`` symmetrically an upper bound. Sums and
differences drop the ``2**-1074`` (a zero or subnormal sum of two floats is exact), so
``0 + 0`` stays ``[0, 0]``. numpy's float64
elementary functions (``exp``, ``log``, ``sin``, ``tanh``, ``arctan``, ... and
``scipy.special.erf``) are not correctly rounded; numpy documents and tests them to a few
ulps (< 4, ``numpy/_core/tests/data/umath-validation-set-*.csv``) and we measured at most
2.5 ulps against mpmath. Their results are widened by a relative ``2**-48`` (at least 16
ulps) plus an absolute ``2**-1060`` for the subnormal range (``dn_fn``/``up_fn``) and then
clipped to the function's known range. Exact operations (negation, ``fabs``, ``fmin``,
``fmax``, ``floor``, ``sign``, comparisons, structural rearrangements) are not widened;
non-integer graph constants are, by a relative ``2**-50`` (CasADi's constant folding, see
:meth:`IntervalArithmetic.constant`).
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
from collections.abc import Callable

import casadi as ca
import numpy as np
from scipy.special import erf

from nlyap_opt.kernel.errors import UnsupportedOperationError
from nlyap_opt.kernel.rounding import (
    ETA,
    FLOAT_MAX,
    dn,
    dn_fn,
    dn_sum,
    gamma,
    up,
    up_fn,
    up_sum,
)

__all__ = ["Interval", "IntervalArithmetic", "CheckedIntervalArithmetic"]

_INF = np.inf
_TRIG_SLACK = 2.0**-48  # relative slack of the period index (x - phase) / pi
_PI = float(np.pi)  # < pi
_PIO2 = _PI / 2.0  # < pi/2
_PI_UP = float(np.nextafter(_PI, _INF))  # > pi
_PIO2_UP = float(np.nextafter(_PIO2, _INF))  # > pi/2
_SMALL_DEGENERATE = 4096  # array_equal test for degenerate matmul operands up to this size

OP_NAMES: dict[int, str] = {getattr(ca, a): a for a in dir(ca) if a.startswith("OP_")}
_UMIN = np.minimum.reduce  # ufunc reductions without the np.min/np.max wrappers
_UMAX = np.maximum.reduce
_F64 = np.dtype(np.float64)


# --------------------------------------------------------------------------- FP flags
_FP_QUIET = contextvars.ContextVar("nlyap_fp_quiet", default=False)
_NOOP = contextlib.nullcontext()


def fp_ignore():
    """``np.errstate(all="ignore")``, or a no-op inside :func:`fp_ignored`, which holds it
    already (the state costs about 1.5 µs to enter, several thousand times per query)."""
    return _NOOP if _FP_QUIET.get() else np.errstate(all="ignore")


@contextlib.contextmanager
def fp_ignored():
    """Ignore floating-point flags (``np.errstate(all="ignore")``) for a whole walk.

    The arithmetics then skip entering the state per operation; values are unchanged
    (the flags only decide warnings). Scoped to the current thread or task (a context
    variable, as numpy's own state).
    """
    with np.errstate(all="ignore"):
        token = _FP_QUIET.set(True)
        try:
            yield
        finally:
            _FP_QUIET.reset(token)


# --------------------------------------------------------------------------- helpers
def _guard(lo, hi):
    """Replace NaN bounds (undefined or unboundable results) by the whole real line."""
    m = _UMIN(lo, axis=None, initial=0.0)  # min and max propagate NaN (read-only)
    n = _UMAX(hi, axis=None, initial=0.0)
    if m == m and n == n:
        return lo, hi
    bad = np.isnan(lo) | np.isnan(hi)
    return np.where(bad, -_INF, lo), np.where(bad, _INF, hi)


def to_shape(a: np.ndarray, shape: tuple) -> np.ndarray:
    """``np.broadcast_to(a, shape)``, or ``a`` itself when it has that shape already (the
    view costs several µs; callers only read it)."""
    return a if a.shape == shape else np.broadcast_to(a, shape)


def _set(arr, mask, value):
    """``arr`` with ``value`` where ``mask`` (skips the copy when ``mask`` is all False)."""
    if np.any(mask):
        return np.where(mask, value, arr)
    return arr


def _abs_bounds(lo, hi):
    """Exact bounds of ``|x|`` for ``x`` in ``[lo, hi]``."""
    return np.maximum(np.maximum(lo, -hi), 0.0), np.maximum(-lo, hi)


# --------------------------------------------------------------------------- Interval
class Interval:
    """Interval array: lo, hi float64 ndarrays of identical (broadcastable) shape, lo <= hi.

    Parameters
    ----------
    lo, hi : array_like
        Lower and upper bounds; converted to float64 and broadcast to a common shape.
        Passing the same float64 array twice keeps ``lo is hi`` (a degenerate interval).

    Examples
    --------
    >>> x = Interval([0.0, -1.0], [1.0, 2.0])
    >>> x.width
    array([1., 3.])
    """

    __slots__ = ("lo", "hi")

    def __init__(self, lo, hi):
        lo = np.asarray(lo, dtype=np.float64)
        hi = np.asarray(hi, dtype=np.float64)
        if lo.shape != hi.shape:
            lo, hi = np.broadcast_arrays(lo, hi)
        self.lo = lo
        self.hi = hi

    @property
    def shape(self) -> tuple[int, ...]:
        """Shape of the interval array."""
        return self.lo.shape

    @property
    def ndim(self) -> int:
        """Number of dimensions."""
        return self.lo.ndim

    @property
    def width(self) -> np.ndarray:
        """Width ``hi - lo`` (rounded to nearest; for heuristics, not for proofs)."""
        return self.hi - self.lo

    @property
    def mid(self) -> np.ndarray:
        """A float point inside ``[lo, hi]`` near the midpoint (0 for ``[-inf, inf]``)."""
        with np.errstate(all="ignore"):
            m = 0.5 * self.lo + 0.5 * self.hi
            m = np.where(np.isfinite(m), m, 0.0)
            return np.minimum(np.maximum(m, self.lo), self.hi)

    def __getitem__(self, idx) -> Interval:
        """Index ``lo`` and ``hi`` alike."""
        lo = self.lo[idx]
        if self.lo is self.hi:
            return Interval(lo, lo)
        return Interval(lo, self.hi[idx])

    def contains(self, x) -> np.ndarray:
        """Elementwise test ``lo <= x <= hi``.

        Parameters
        ----------
        x : array_like
            Points, broadcast against the interval.

        Returns
        -------
        numpy.ndarray
            Boolean array.
        """
        return (self.lo <= x) & (x <= self.hi)

    def __repr__(self) -> str:
        return f"Interval(lo={self.lo!r}, hi={self.hi!r})"


def _iv(lo, hi) -> Interval:
    """``Interval(lo, hi)`` without conversions when both are float64 arrays of one shape."""
    if (type(lo) is np.ndarray and type(hi) is np.ndarray and lo.dtype is _F64
            and hi.dtype is _F64 and lo.shape == hi.shape):
        x = _NEW(Interval)
        x.lo = lo
        x.hi = hi
        return x
    return Interval(lo, hi)


def _as_interval(x) -> Interval:
    if isinstance(x, Interval):
        return x
    return IntervalArithmetic.constant(x)


_NEW = object.__new__


def _full(shape, value):
    return np.full(shape, value, dtype=np.float64)


def _bshape(*arrays):
    return np.broadcast_shapes(*(np.shape(a) for a in arrays))


# --------------------------------------------------------------------------- elementary ops
def _add(al, ah, bl, bh):
    if al is ah and bl is bh:  # (a user-built degenerate interval may hold inf - inf)
        s = al + bl
        return _guard(dn_sum(s), up_sum(s))
    return dn_sum(al + bl), up_sum(ah + bh)  # no NaN: lo < +inf and hi > -inf


def _sub(al, ah, bl, bh):
    if al is ah and bl is bh:
        s = al - bl
        return _guard(dn_sum(s), up_sum(s))
    return dn_sum(al - bh), up_sum(ah - bl)


def _mul(al, ah, bl, bh):
    if al is ah and bl is not bh:  # put the degenerate operand second
        al, ah, bl, bh = bl, bh, al, ah
    if bl is bh:
        if al is ah:
            p = al * bl
            return _guard(dn(p), up(p))
        if bl.ndim == 0 and np.isfinite(bl):
            c = float(bl)
            if c > 0.0:
                return dn(al * c), up(ah * c)
            if c < 0.0:
                return dn(ah * c), up(al * c)
            z = _full(_bshape(al, bl), 0.0)
            return z, z.copy()
        p1 = al * bl
        p2 = ah * bl
        lo = np.fmin(p1, p2)  # fmin/fmax skip the NaN of 0*inf (its limit value 0 is
        hi = np.fmax(p1, p2)  # attained at the other endpoint product)
    else:
        p1 = al * bl
        p2 = al * bh
        p3 = ah * bl
        p4 = ah * bh
        if type(p1) is type(p3) is np.ndarray and p1.ndim and p1.shape == p2.shape == p3.shape \
                == p4.shape:
            # the same values as below, in fewer buffers
            lo = np.fmin(p1, p2)
            hi = np.fmax(p1, p2, out=p1)
            t = np.fmin(p3, p4)
            np.fmax(p3, p4, out=p3)
            np.fmin(lo, t, out=lo)
            np.fmax(hi, p3, out=hi)
        else:
            lo = np.fmin(np.fmin(p1, p2), np.fmin(p3, p4))
            hi = np.fmax(np.fmax(p1, p2), np.fmax(p3, p4))
    return _guard(dn(lo), up(hi))


def _div(al, ah, bl, bh):
    zero = (bl <= 0.0) & (bh >= 0.0)
    if bl is bh and bl.ndim == 0 and np.isfinite(bl) and not zero:
        c = float(bl)
        if c > 0.0:
            return dn(al / c), up(ah / c)
        return dn(ah / c), up(al / c)
    if al is ah and bl is bh:
        q = al / bl
        lo, hi = q, q
    elif bl is bh:
        q1 = al / bl
        q2 = ah / bl
        lo, hi = np.fmin(q1, q2), np.fmax(q1, q2)
    elif al is ah:
        q1 = al / bl
        q2 = al / bh
        lo, hi = np.fmin(q1, q2), np.fmax(q1, q2)
    else:
        q1 = al / bl
        q2 = al / bh
        q3 = ah / bl
        q4 = ah / bh
        lo = np.fmin(np.fmin(q1, q2), np.fmin(q3, q4))
        hi = np.fmax(np.fmax(q1, q2), np.fmax(q3, q4))
    lo = _set(dn(lo), zero, -_INF)
    hi = _set(up(hi), zero, _INF)
    return _guard(lo, hi)


def _inv(lo, hi):
    zero = (lo <= 0.0) & (hi >= 0.0)
    if lo is hi:
        q = 1.0 / lo
        rl, rh = dn(q), up(q)
    else:
        rl, rh = dn(1.0 / hi), up(1.0 / lo)
    return _guard(_set(rl, zero, -_INF), _set(rh, zero, _INF))


def _sq(lo, hi):
    if lo is hi:
        p = lo * lo
        return np.maximum(dn(p), 0.0), up(p)
    ml, mh = _abs_bounds(lo, hi)
    return np.maximum(dn(ml * ml), 0.0), up(mh * mh)


def _sqrt(lo, hi):
    rl = np.maximum(dn(np.sqrt(np.maximum(lo, 0.0))), 0.0)
    rh = up(np.sqrt(hi))
    out = hi < 0.0  # entirely outside the domain
    return _guard(_set(rl, out, -_INF), _set(rh, out, _INF))


def _monotone(f, lo, hi, clip_lo=None, clip_hi=None, increasing=True):
    """Enclosure of a monotone elementary function (libm accuracy, widened)."""
    if lo is hi:
        v = f(lo)
        rl, rh = dn_fn(v), up_fn(v)
    elif increasing:
        rl, rh = dn_fn(f(lo)), up_fn(f(hi))
    else:
        rl, rh = dn_fn(f(hi)), up_fn(f(lo))
    if clip_lo is not None:
        rl = np.maximum(rl, clip_lo)
    if clip_hi is not None:
        rh = np.minimum(rh, clip_hi)
    return rl, rh


def _exp(lo, hi):
    return _guard(*_monotone(np.exp, lo, hi, clip_lo=0.0))


def _expm1(lo, hi):
    return _guard(*_monotone(np.expm1, lo, hi, clip_lo=-1.0))


def _log_like(f, boundary, lo, hi):
    """``log``/``log1p``: domain ``x > boundary``; ``f(boundary) = -inf``."""
    rl = dn_fn(f(np.maximum(lo, boundary)))
    rh = up_fn(f(hi))
    out = hi <= boundary
    return _guard(_set(rl, out, -_INF), _set(rh, out, _INF))


def _log(lo, hi):
    return _log_like(np.log, 0.0, lo, hi)


def _log1p(lo, hi):
    return _log_like(np.log1p, -1.0, lo, hi)


def _period_index(x, phase, lower: bool):
    """Rigorous integer bound of ``s = (x - phase) / pi``: ceil of a lower / floor of upper.

    With float ``phase`` and ``pi``, ``|fl(s) - s| <= 4u(|s| + 1)``; we use a slack of
    ``2**-48 (|s| + 1)`` (8 times that) so the returned integer range is never too small.
    """
    s = (x - phase) / _PI
    d = (np.abs(s) + 1.0) * _TRIG_SLACK
    return np.ceil(s - d) if lower else np.floor(s + d)


def _sincos(f, phase, lo, hi):
    """sin/cos: extrema at ``phase + k pi``, +1 for even ``k``, -1 for odd ``k``."""
    if lo is hi:
        return _guard(*_monotone(f, lo, hi, clip_lo=-1.0, clip_hi=1.0))
    fa = f(lo)
    fb = f(hi)
    rl = np.maximum(dn_fn(np.minimum(fa, fb)), -1.0)
    rh = np.minimum(up_fn(np.maximum(fa, fb)), 1.0)
    n_lo = _period_index(lo, phase, True)
    n_hi = _period_index(hi, phase, False)
    many = (n_hi - n_lo) >= 1.0  # two consecutive k: both extrema (also infinite bounds)
    one = n_hi == n_lo
    odd = np.fmod(n_lo, 2.0) != 0.0
    has_max = many | (one & ~odd)
    has_min = many | (one & odd)
    rh = _set(rh, has_max, 1.0)
    rl = _set(rl, has_min, -1.0)
    return _guard(rl, rh)


def _sin(lo, hi):
    return _sincos(np.sin, _PIO2, lo, hi)


def _cos(lo, hi):
    return _sincos(np.cos, 0.0, lo, hi)


def _tan(lo, hi):
    rl, rh = _monotone(np.tan, lo, hi)
    if lo is not hi:  # a pole pi/2 + k pi possibly inside: unbounded
        pole = _period_index(hi, _PIO2, False) >= _period_index(lo, _PIO2, True)
        rl = _set(rl, pole, -_INF)
        rh = _set(rh, pole, _INF)
    return _guard(rl, rh)


def _cosh(lo, hi):
    if lo is hi:
        v = np.cosh(lo)
        return _guard(np.maximum(dn_fn(v), 1.0), up_fn(v))
    ml, mh = _abs_bounds(lo, hi)
    return _guard(np.maximum(dn_fn(np.cosh(ml)), 1.0), up_fn(np.cosh(mh)))


def _clipped_domain(f, dlo, dhi, lo, hi, clip_lo, clip_hi, increasing=True, open_=False):
    """Monotone function on the domain ``[dlo, dhi]`` (open if ``open_``), domain-clipped."""
    cl = np.minimum(np.maximum(lo, dlo), dhi)
    ch = np.minimum(np.maximum(hi, dlo), dhi)
    rl, rh = _monotone(f, cl, ch, clip_lo, clip_hi, increasing)
    out = (hi <= dlo) | (lo >= dhi) if open_ else (hi < dlo) | (lo > dhi)
    return _guard(_set(rl, out, -_INF), _set(rh, out, _INF))


def _erf(lo, hi):
    return _guard(*_monotone(erf, lo, hi, clip_lo=-1.0, clip_hi=1.0))


def _truth(lo, hi):
    """(definitely nonzero, possibly nonzero) masks of ``x != 0``."""
    return (lo > 0.0) | (hi < 0.0), ~((lo == 0.0) & (hi == 0.0))


def _bool(lo_mask, hi_mask):
    return lo_mask.astype(np.float64), hi_mask.astype(np.float64)


def _not(lo, hi):
    t, p = _truth(lo, hi)
    return _bool(~p, ~t)


def _fabs(lo, hi):
    if lo is hi:
        v = np.abs(lo)
        return v, v
    return _abs_bounds(lo, hi)


def _neg(lo, hi):
    if lo is hi:
        v = -lo
        return v, v
    return -hi, -lo


def _twice(lo, hi):
    return np.minimum(lo * 2.0, FLOAT_MAX), np.maximum(hi * 2.0, -FLOAT_MAX)  # exact but overflow


def _exact_monotone(f):
    def op(lo, hi):
        if lo is hi:
            v = f(lo)
            return v, v
        return f(lo), f(hi)

    return op


# ---- power
@functools.lru_cache(maxsize=1024)
def _g3(n: int) -> float:
    """``(g + 2**-52)(1 + 2 g)(1 + 2**-48)`` with ``g >= gamma_n``: see ``sum``/``_pow_end``."""
    g = gamma(n)
    return (g + 2.0**-52) * (1.0 + 2.0 * g) * (1.0 + 2.0**-48)


def _pow_end(x, k: int, lower: bool):
    """Rigorous lower (or upper) bound of ``x**k`` for float arrays ``x``, ``k >= 2``.

    Binary powering: a rounding error made at a squaring is raised to the exponent weight
    still to come, and these weights add up to ``k - 1``, so ``p = fl(x**k)`` has
    ``|p - x**k| <= gamma_{k-1} |x**k| + (k - 1) eta`` (not ``gamma_m`` for the ``m``
    multiplications; intermediate magnitudes only decrease when ``|x| < 1``, so underflow
    errors are not amplified). As in ``sum``, ``fl(p -+ e)`` with ``e = fl(fl(|p|
    g3(k - 1)) + 2**-1020)`` is then outward. A NaN there comes only from ``p = +-inf``
    (overflow) and is mapped to ``+-float_max``, a valid bound for a true magnitude beyond
    ``float_max``. For ``k > 64``: libm ``pow`` (measured < 1 ulp), widened by 16 ulps.
    """
    if k > 64:
        v = np.power(x, float(k))
        return dn_fn(v) if lower else up_fn(v)
    k0 = k
    r = None
    b = x
    while True:
        if k & 1:
            r = b if r is None else r * b
        k >>= 1
        if not k:
            break
        b = b * b
    e = np.abs(r) * _g3(k0 - 1)
    e += 2.0**-1020
    if lower:
        return np.fmin(r - e, FLOAT_MAX)
    return np.fmax(r + e, -FLOAT_MAX)


def _ipow(lo, hi, n: int):
    """Enclosure of ``x**n`` for an integer ``n`` (defined for every real ``x`` if n >= 0)."""
    if n == 0:
        one = _full(np.shape(lo), 1.0)
        return one, one.copy()
    if n == 1:
        return lo, hi
    if n == 2:
        return _sq(lo, hi)
    if n == -1:
        return _inv(lo, hi)
    k = abs(n)
    if k % 2 == 0:  # even: through |x|
        ml, mh = _abs_bounds(lo, hi)
        pl = np.maximum(_pow_end(ml, k, True), 0.0)
        ph = _pow_end(mh, k, False)
        if n > 0:
            return pl, ph
        rl = np.maximum(dn(1.0 / ph), 0.0)
        rh = up(1.0 / np.abs(pl))  # 1/0 = +inf when 0 is in x
        out = (lo == 0.0) & (hi == 0.0)  # x = 0 exactly: undefined
        return _guard(_set(rl, out, -_INF), _set(rh, out, _INF))
    pl = _pow_end(lo, k, True)  # odd powers are increasing
    ph = _pow_end(hi, k, False)
    if n > 0:
        return pl, ph
    return _inv(pl, ph)


def _pow_real(al, ah, bl, bh):
    """``x**y = exp(y log x)`` on the domain ``x >= 0`` (domain-clipped)."""
    ll, lh = _log(al, ah)
    pl, ph = _mul(bl, bh, ll, lh)
    rl, rh = _exp(pl, ph)
    # entirely negative x; or negative x with a varying exponent, where x**y is real at
    # the integers y of the range: unbounded
    bad = (ah < 0.0) | ((al < 0.0) & (bl != bh))
    return _guard(_set(rl, bad, -_INF), _set(rh, bad, _INF))


def _is_int(y):
    """Finite integer-valued exponents (every float beyond 2**53 is an even integer)."""
    with np.errstate(invalid="ignore"):
        return (np.floor(y) == y) & np.isfinite(y)


def _pow(al, ah, bl, bh):
    if bl is bh and bl.ndim == 0:
        if _is_int(bl):
            return _ipow(al, ah, int(bl))
        return _pow_real(al, ah, bl, bh)
    int_mask = (bl == bh) & _is_int(bl)
    if not np.any(int_mask):
        return _pow_real(al, ah, bl, bh)
    values = np.unique(bl[int_mask])
    shape = _bshape(al, bl)
    if int_mask.all() and len(values) == 1:
        rl, rh = _ipow(al, ah, int(values[0]))
        return np.broadcast_to(rl, shape), np.broadcast_to(rh, shape)
    rl = _full(shape, np.nan)
    rh = _full(shape, np.nan)
    if not int_mask.all():
        pl, ph = _pow_real(al, ah, bl, bh)
        rl = np.where(int_mask, rl, pl)
        rh = np.where(int_mask, rh, ph)
    for v in values:
        sel = int_mask & (bl == v)
        pl, ph = _ipow(al, ah, int(v))
        rl = np.where(sel, pl, rl)
        rh = np.where(sel, ph, rh)
    return _guard(rl, rh)


# ---- other binary ops
def _fmin(al, ah, bl, bh):
    return np.minimum(al, bl), np.minimum(ah, bh)


def _fmax(al, ah, bl, bh):
    return np.maximum(al, bl), np.maximum(ah, bh)


def _atan2(yl, yh, xl, xh):
    """``atan2(y, x)`` (CasADi's argument order). Continuous off the cut ``y = 0, x <= 0``."""
    c1 = np.arctan2(yl, xl)
    c2 = np.arctan2(yl, xh)
    c3 = np.arctan2(yh, xl)
    c4 = np.arctan2(yh, xh)
    rl = np.maximum(dn_fn(np.minimum(np.minimum(c1, c2), np.minimum(c3, c4))), -_PI_UP)
    rh = np.minimum(up_fn(np.maximum(np.maximum(c1, c2), np.maximum(c3, c4))), _PI_UP)
    # box meets the branch cut or contains the origin: the whole range [-pi, pi]
    cut = (yl <= 0.0) & (yh >= 0.0) & (xl <= 0.0)
    return _guard(_set(rl, cut, -_PI_UP), _set(rh, cut, _PI_UP))


def _hypot(al, ah, bl, bh):
    xl, xh = _abs_bounds(al, ah)
    yl, yh = _abs_bounds(bl, bh)
    rl = np.maximum(dn_fn(np.hypot(xl, yl)), 0.0)
    rh = up_fn(np.hypot(xh, yh))
    return _guard(rl, rh)


def _copysign(al, ah, bl, bh):
    ml, mh = _abs_bounds(al, ah)
    pos = bl > 0.0
    neg = bh < 0.0
    rl = np.where(pos, ml, -mh)
    rh = np.where(neg, -ml, mh)
    return rl, rh


def _fmod(al, ah, bl, bh):
    """C ``fmod``: sign of ``x`` and ``|fmod(x, y)| < |y|``, ``<= |x|``."""
    m = np.maximum(np.abs(bl), np.abs(bh))
    rl = np.minimum(np.maximum(al, -m), 0.0)
    rh = np.maximum(np.minimum(ah, m), 0.0)
    if bl is bh and bl.ndim == 0 and np.isfinite(bl) and bl != 0.0:
        # constant divisor: where trunc(x / |c|) = q on the whole box, fmod = x - q |c|
        c = abs(float(bl))
        q = np.trunc(al / c)
        ql, qh = dn(q * c), up(q * c)
        xl, xh = dn(al - qh), up(ah - ql)
        pos = (al >= 0.0) & (xl >= 0.0) & (xh < c)
        neg = (ah <= 0.0) & (xl > -c) & (xh <= 0.0)
        ok = (pos | neg) & (q == np.trunc(ah / c)) & np.isfinite(xl) & np.isfinite(xh)
        rl = np.where(ok, np.maximum(rl, xl), rl)
        rh = np.where(ok, np.minimum(rh, xh), rh)
    out = (bl == 0.0) & (bh == 0.0)  # fmod(x, 0) is undefined
    return _guard(_set(rl, out, -_INF), _set(rh, out, _INF))


def _lt(al, ah, bl, bh):
    return _bool(ah < bl, al < bh)


def _le(al, ah, bl, bh):
    return _bool(ah <= bl, al <= bh)


def _eq_masks(al, ah, bl, bh):
    possible = (al <= bh) & (bl <= ah)
    certain = (al == ah) & (bl == bh) & (al == bl)
    return certain, possible


def _eq(al, ah, bl, bh):
    return _bool(*_eq_masks(al, ah, bl, bh))


def _ne(al, ah, bl, bh):
    certain, possible = _eq_masks(al, ah, bl, bh)
    return _bool(~possible, ~certain)


def _and(al, ah, bl, bh):
    ta, pa = _truth(al, ah)
    tb, pb = _truth(bl, bh)
    return _bool(ta & tb, pa & pb)


def _or(al, ah, bl, bh):
    ta, pa = _truth(al, ah)
    tb, pb = _truth(bl, bh)
    return _bool(ta | tb, pa | pb)


def _if_else_zero(cl, ch, xl, xh):
    """``c ? x : 0``."""
    t, p = _truth(cl, ch)
    rl = np.where(t, xl, np.minimum(xl, 0.0))
    rh = np.where(t, xh, np.maximum(xh, 0.0))
    rl = np.where(p, rl, 0.0)
    rh = np.where(p, rh, 0.0)
    return rl, rh


_UNARY: dict[int, Callable] = {
    ca.OP_ASSIGN: lambda lo, hi: (lo, hi),
    ca.OP_NEG: _neg,
    ca.OP_FABS: _fabs,
    ca.OP_TWICE: _twice,
    ca.OP_SQ: _sq,
    ca.OP_SQRT: _sqrt,
    ca.OP_INV: _inv,
    ca.OP_EXP: _exp,
    ca.OP_EXPM1: _expm1,
    ca.OP_LOG: _log,
    ca.OP_LOG1P: _log1p,
    ca.OP_SIN: _sin,
    ca.OP_COS: _cos,
    ca.OP_TAN: _tan,
    ca.OP_TANH: lambda lo, hi: _guard(*_monotone(np.tanh, lo, hi, -1.0, 1.0)),
    ca.OP_ATAN: lambda lo, hi: _guard(*_monotone(np.arctan, lo, hi, -_PIO2_UP, _PIO2_UP)),
    ca.OP_SINH: lambda lo, hi: _guard(*_monotone(np.sinh, lo, hi)),
    ca.OP_COSH: _cosh,
    ca.OP_ASINH: lambda lo, hi: _guard(*_monotone(np.arcsinh, lo, hi)),
    ca.OP_ASIN: lambda lo, hi: _clipped_domain(np.arcsin, -1.0, 1.0, lo, hi,
                                               -_PIO2_UP, _PIO2_UP),
    ca.OP_ACOS: lambda lo, hi: _clipped_domain(np.arccos, -1.0, 1.0, lo, hi, 0.0, _PI_UP,
                                               increasing=False),
    ca.OP_ACOSH: lambda lo, hi: _clipped_domain(np.arccosh, 1.0, _INF, lo, hi, 0.0, None),
    ca.OP_ATANH: lambda lo, hi: _clipped_domain(np.arctanh, -1.0, 1.0, lo, hi, None, None,
                                                open_=True),
    ca.OP_ERF: _erf,
    ca.OP_SIGN: _exact_monotone(np.sign),
    ca.OP_FLOOR: _exact_monotone(np.floor),
    ca.OP_CEIL: _exact_monotone(np.ceil),
    ca.OP_NOT: _not,
}

_BINARY: dict[int, Callable] = {
    ca.OP_ADD: _add,
    ca.OP_SUB: _sub,
    ca.OP_MUL: _mul,
    ca.OP_DIV: _div,
    ca.OP_POW: _pow,
    ca.OP_CONSTPOW: _pow,
    ca.OP_FMIN: _fmin,
    ca.OP_FMAX: _fmax,
    ca.OP_ATAN2: _atan2,
    ca.OP_HYPOT: _hypot,
    ca.OP_COPYSIGN: _copysign,
    ca.OP_FMOD: _fmod,
    ca.OP_LT: _lt,
    ca.OP_LE: _le,
    ca.OP_EQ: _eq,
    ca.OP_NE: _ne,
    ca.OP_AND: _and,
    ca.OP_OR: _or,
    ca.OP_IF_ELSE_ZERO: _if_else_zero,
}


def _op_name(op: int) -> str:
    return OP_NAMES.get(op, f"op#{op}")


def _unsupported(op: int, kind: str) -> UnsupportedOperationError:
    names = ", ".join(sorted(_op_name(o) for o in (*_UNARY, *_BINARY)))
    return UnsupportedOperationError(
        f"CasADi operation {_op_name(op)} (code {op}) is not supported as a {kind} operation "
        f"by the 'interval' arithmetic; supported: {names}. Rewrite the expression with "
        "supported operations."
    )


# --------------------------------------------------------------------------- arithmetic
class IntervalArithmetic:
    """Outward-rounded interval arithmetic for the instruction walker.

    Every method returns an enclosure of the real-valued result over all real points of
    its interval arguments; see the module docstring for the rounding and domain rules.

    Examples
    --------
    >>> import casadi as ca
    >>> ia = IntervalArithmetic()
    >>> x = Interval([-1.0], [2.0])
    >>> y = ia.unary(ca.OP_SQ, x)
    >>> bool(y.lo[0] <= 0.0 <= 4.0 <= y.hi[0])
    True
    """

    name = "interval"
    cache_constants = True  # constants are immutable: the walker may reuse them

    @staticmethod
    def constant(value: np.ndarray) -> Interval:
        """Enclose a graph constant: ``[value, value]`` widened by a relative ``2**-50``.

        CasADi folds constant subexpressions in float64 while it builds expressions and
        derivative graphs (``gradient((x * 0.1) * 3)`` holds ``fl(0.1 * 3) =
        0.30000000000000004``, SX turns ``0.1 * (0.3 * x)`` into ``0.03 * x``), so a graph
        constant can differ from the real value of the expression it replaces. The
        widening (at least 3 ulps each side, plus ``2**-1070`` for subnormals) of every
        non-integer constant covers folds within 3 ulps of the real value: products and
        quotients of a few constants, sums without cancellation. Integer-valued constants
        (exponents of powers, counts, ``2`` of ``d(x²)/dx``) stay exact, and an all-integer
        constant stays degenerate (``lo is hi``); a fold that rounds a non-integer real
        value to an integer is not covered.

        Parameters
        ----------
        value : array_like
            Float64 constant. Non-finite entries are not real numbers: NaN becomes
            ``[-inf, inf]``, ``+inf`` becomes ``[float_max, inf]``, ``-inf``
            ``[-inf, -float_max]``.

        Returns
        -------
        Interval
        """
        v = np.asarray(value, dtype=np.float64)
        if np.isfinite(v).all():
            inexact = v != np.round(v)  # integers stay exact: powers, fmod, folds like 2·1
            if not inexact.any():
                return Interval(v, v)
            w = np.where(inexact, np.abs(v) * 2.0**-50 + 2.0**-1070, 0.0)
            return Interval(v - w, v + w)
        lo = np.where(np.isnan(v), -_INF, np.where(v == _INF, FLOAT_MAX, v))
        hi = np.where(np.isnan(v), _INF, np.where(v == -_INF, -FLOAT_MAX, v))
        return Interval(lo, hi)

    def unary(self, op: int, a: Interval) -> Interval:
        """Enclose the unary CasADi operation ``op`` applied elementwise to ``a``.

        Parameters
        ----------
        op : int
            CasADi operation code (``casadi.OP_SIN``, ...).
        a : Interval

        Returns
        -------
        Interval

        Raises
        ------
        UnsupportedOperationError
            (a ``NotImplementedError``) for an operation without a rigorous enclosure.
        """
        f = _UNARY.get(op)
        if f is None:
            raise _unsupported(op, "unary")
        a = _as_interval(a)
        with fp_ignore():
            lo, hi = f(a.lo, a.hi)
        return _iv(lo, hi)

    def binary(self, op: int, a: Interval, b: Interval) -> Interval:
        """Enclose the binary CasADi operation ``op`` elementwise, with broadcasting.

        Parameters
        ----------
        op : int
            CasADi operation code (``casadi.OP_ADD``, ...); ``OP_ATAN2`` is
            ``atan2(a, b)``, ``OP_IF_ELSE_ZERO`` is ``a ? b : 0``.
        a, b : Interval

        Returns
        -------
        Interval

        Raises
        ------
        UnsupportedOperationError
            (a ``NotImplementedError``) for an operation without a rigorous enclosure.
        """
        f = _BINARY.get(op)
        if f is None:
            raise _unsupported(op, "binary")
        a = _as_interval(a)
        b = _as_interval(b)
        with fp_ignore():
            lo, hi = f(a.lo, a.hi, b.lo, b.hi)
        return _iv(lo, hi)

    def sum(self, a: Interval, axis=None) -> Interval:
        """Rigorous sum over ``axis`` (int, tuple of ints or None for all axes).

        Error bound: any floating-point summation order of ``n`` terms (numpy's pairwise
        sum, BLAS kernels with several accumulators or FMA) gives ``S = fl(sum x)`` with
        ``|S - sum x| <= gamma_{n-1} sum |x|`` (Higham, *Accuracy and Stability of
        Numerical Algorithms*, 2nd ed., eq. 4.4; additions never err by underflow), and
        ``A = fl(sum |x|) >= (1 - gamma_{n-1}) sum |x|``. The lower bound is
        ``fl(S - t)`` with ``t = fl(fl(A g3) + 2**-1020)``, which is below the true sum
        because ``fl(S - t) <= S - t + u (|S| + t)`` and ``t (1 - u) >= gamma_{n-1} sum|x|
        + u |S|`` for ``g3 = (g + 2**-52)(1 + 2 g)(1 + 2**-48)``, ``g >= gamma_n``
        (``|S| <= (1 + gamma) sum |x|``); the upper bound is symmetric. Lower bounds are
        summed from ``lo``, upper bounds from ``hi``.

        Parameters
        ----------
        a : Interval
        axis : int or tuple of int or None

        Returns
        -------
        Interval
        """
        a = _as_interval(a)
        lo, hi = a.lo, a.hi
        nd = lo.ndim
        if axis is None:
            axes = tuple(range(nd))
        else:
            axes = (axis,) if np.ndim(axis) == 0 else tuple(axis)
            axes = tuple(sorted({int(ax) % nd for ax in axes})) if nd else ()
        shape = lo.shape
        n = 1
        for ax in axes:
            n *= shape[ax]
        if n <= 1:
            return self.structural(lambda x: np.sum(x, axis=axes), a)
        g3 = _g3(n)
        with fp_ignore():
            if lo is hi:
                s = _reduce(lo, axes)
                t = _reduce(np.abs(lo), axes)
                t *= g3
                t += 2.0**-1020
                return _iv(*_guard(s - t, s + t))
            # lower and upper bounds summed in one stacked reduction (fewer numpy calls)
            x = np.stack((lo, hi))
            axes1 = tuple(ax + 1 for ax in axes)
            s = _reduce(x, axes1)
            t = _reduce(np.abs(x, out=x), axes1)
            t *= g3
            t += 2.0**-1020
            return _iv(*_guard(s[0] - t[0], s[1] + t[1]))

    def matmul(self, a, b) -> Interval:
        """Rigorous ``a @ b`` with numpy ``matmul`` semantics (batch broadcasting).

        Error bound (midpoint-radius, Rump, BIT 39(3), 1999): with ``A = <mA, rhoA>`` and
        ``B = <mB, rhoB>`` (exact radii about float midpoints, 0 for degenerate operands)
        the real products lie in ``mA mB +- R``, ``R = |mA| rhoB + rhoA (|mB| + rhoB)``.
        ``C = fl(mA @ mB)`` errs by at most ``gamma_k |mA||mB| + k eta`` for any order of
        the ``k``-term dot products, FMA or not (``eta = 2**-1074``, ``u = 2**-53``), so
        ``|C| <= (1 + gamma_k)|mA||mB| + k eta``. The final ``lo = fl(C - t)`` is below
        ``C - R - err(C)`` whenever ``t (1 - u) >= R + err(C) + u |C|``, which holds for
        ``t = fl(fl(P F) + abs_c)``: ``P = fl(|mA| @ W1) + fl(rA @ W2)`` with
        ``W1 = fl(fl(g2 |mB|) + rB)``, ``g2 = g + 2**-52 >= gamma_k + u (1 + gamma_k)``,
        ``W2 = fl(|mB| + rB)`` and computed radii ``r >= (1 - u) rho``; nonnegative
        products obey ``M W <= (fl(M W) + k eta) / (1 - gamma_k)``; hence
        ``R + err(C) + u|C| <= P / ((1 - gamma_k)(1 - u)**3) + eta (rowsum|mA| + 5k)``,
        covered by ``F = 1 + 4g + 2**-48 >= 1 / ((1 - gamma_k)(1 - u)**7)`` and
        ``abs_c = 4 eta (k max|mA| + 5k + 2)``. ``hi`` is symmetric. Operands with
        infinite bounds fall back to the elementwise products followed by :meth:`sum`.

        Parameters
        ----------
        a, b : Interval or array_like
            Shapes ``(..., r, k)`` and ``(..., k, c)`` (or 1-D as in numpy); arrays are
            exact constants.

        Returns
        -------
        Interval
        """
        a = _as_interval(a)
        b = _as_interval(b)
        k = a.lo.shape[-1]
        with fp_ignore():
            if k == 0 or not (_finite(a) and _finite(b)):
                return self._matmul_elementwise(a, b)
            g = gamma(k)
            ma, ra, ama = _midrad(a)
            mb, rb, amb = _midrad(b)
            c = _mm(ma, mb)
            w2 = None
            if ra is not None:
                w2 = amb if rb is None else amb + rb
            w1 = np.multiply(amb, g + 2.0**-52, out=amb if w2 is None else None)
            if rb is not None:
                w1 += rb
            t = _mm(ama, w1)
            if ra is not None:
                t += _mm(ra, w2)
            t *= 1.0 + 4.0 * g + 2.0**-48
            amax = float(_UMAX(ama, axis=None)) if ama.size else 0.0
            t += 4.0 * ETA * (k * amax * (1.0 + 2.0**-40) + 5.0 * k + 2.0)
            lo = c - t
            t += c
            return _iv(*_guard(lo, t))

    def _matmul_elementwise(self, a: Interval, b: Interval) -> Interval:
        """``sum_k a[..., :, k, None] * b[..., None, k, :]`` (handles infinite bounds)."""
        va = a.ndim == 1
        vb = b.ndim == 1
        if va:
            a = a[None, :]
        if vb:
            b = b[:, None]
        if a.lo.shape[-1] == 0:
            shape = np.broadcast_shapes(a.shape[:-2], b.shape[:-2]) + (a.shape[-2], b.shape[-1])
            z = _full(shape, 0.0)
            out = Interval(z, z)
        else:
            p = self.binary(ca.OP_MUL, a[..., :, :, None], b[..., None, :, :])
            out = self.sum(p, axis=-2)
        if va:
            out = out[..., 0, :]
        if vb:
            out = out[..., 0]
        return out

    def structural(self, fn: Callable, *args: Interval) -> Interval:
        """Apply an exact rearrangement to ``lo`` and ``hi`` alike.

        Parameters
        ----------
        fn : callable
            Indexing, reshape, transpose, concatenation, ... of arrays.
        *args : Interval

        Returns
        -------
        Interval
            ``Interval(fn(*los), fn(*his))``.
        """
        args = [_as_interval(x) for x in args]
        los = [x.lo for x in args]
        if all(x.lo is x.hi for x in args):
            v = np.asarray(fn(*los), dtype=np.float64)
            return Interval(v, v)
        return _iv(fn(*los), fn(*[x.hi for x in args]))

    @staticmethod
    def nonneg(a: Interval) -> Interval:
        """``a`` with its lower bound raised to 0, for a value known to be ``>= 0``.

        The walker uses it for sums of squares (``dot(v, v)``), whose rigorous summation
        bound may dip below 0 (a square root's domain check then fails).

        Parameters
        ----------
        a : Interval

        Returns
        -------
        Interval
        """
        a = _as_interval(a)
        if a.lo is a.hi:
            v = np.maximum(a.lo, 0.0)
            return Interval(v, v)
        return _iv(np.maximum(a.lo, 0.0), np.maximum(a.hi, 0.0))

    @staticmethod
    def intersect(a: Interval, b: Interval) -> Interval:
        """Elementwise intersection (empty where ``lo > hi``).

        Parameters
        ----------
        a, b : Interval

        Returns
        -------
        Interval
        """
        a = _as_interval(a)
        b = _as_interval(b)
        return _iv(np.maximum(a.lo, b.lo), np.minimum(a.hi, b.hi))

    @staticmethod
    def hull(a: Interval, b: Interval) -> Interval:
        """Elementwise interval hull.

        Parameters
        ----------
        a, b : Interval

        Returns
        -------
        Interval
        """
        a = _as_interval(a)
        b = _as_interval(b)
        return _iv(np.minimum(a.lo, b.lo), np.maximum(a.hi, b.hi))


def _finite(x: Interval) -> bool:
    """All bounds finite and not NaN (``min`` and ``max`` propagate NaN)."""
    if x.lo.size == 0:
        return True
    # lo <= hi (invariant; for a degenerate interval lo is hi): these two bound the others
    return bool(_UMIN(x.lo, axis=None) > -_INF) and bool(_UMAX(x.hi, axis=None) < _INF)


def _midrad(x: Interval):
    """Midpoint, radius ``r >= (1 - u) rho`` (``None`` if degenerate) and ``|midpoint|``.

    ``rho = max(hi - m, m - lo)`` is the exact radius about the float midpoint ``m``; the
    float subtractions err by a relative ``u`` at most (no underflow error).
    """
    lo, hi = x.lo, x.hi
    if lo is hi or (lo.size <= _SMALL_DEGENERATE and np.array_equal(lo, hi)):
        return lo, None, np.abs(lo)
    m = lo + hi
    m *= 0.5
    r = hi - m
    am = np.subtract(m, lo)
    np.maximum(r, am, out=r)
    return m, r, np.abs(m, out=am)  # reuse the buffer for |m|


@functools.lru_cache(maxsize=256)
def _ones(n: int) -> np.ndarray:
    v = np.ones(n)
    v.flags.writeable = False
    return v


def _reduce(x, axes: tuple[int, ...]):
    """Floating sum over ``axes`` (any order); BLAS ``@ ones`` for trailing axes."""
    nd = x.ndim
    k = len(axes)
    if k and axes == tuple(range(nd - k, nd)):
        lead = x.shape[: nd - k]
        n = 1
        for d in x.shape[nd - k:]:
            n *= d
        return (x.reshape(-1, n) @ _ones(n)).reshape(lead)
    return np.sum(x, axis=axes)


def _mm(a, b):
    """``a @ b`` with a single GEMM where a constant matrix meets a batch.

    Only the grouping of the work changes: every entry is the same k-term dot product.
    """
    if a.ndim == 2 and b.ndim > 2:  # (r, k) @ (..., k, c)
        k, c = b.shape[-2:]
        if c == 1:
            return (b[..., 0] @ a.T)[..., None]
        bt = np.swapaxes(b, -1, -2).reshape(-1, k)  # (... * c, k)
        return np.swapaxes((bt @ a.T).reshape(b.shape[:-2] + (c, a.shape[0])), -1, -2)
    if b.ndim == 2 and a.ndim > 2:  # (..., r, k) @ (k, c)
        r, k = a.shape[-2:]
        return (a.reshape(-1, k) @ b).reshape(a.shape[:-2] + (r, b.shape[1]))
    return a @ b


# --------------------------------------------------------------------------- checked walk
# Per-operation predicates over interval arguments, vectorised over boxes. ``_JUMPS[op]``:
# the argument may meet the operation's kink or jump set (the operation is not known to be
# smooth on the box); ``_DOMAINS[op]``: (certainly inside the domain, certainly outside).
# Every non-smooth / partial operation of ``nlyap_opt.kernel.walker.OP_TABLE`` has an entry (a
# test checks it). Interval enclosures are outward, so "certainly" is rigorous.
def _result_varies(args, res):
    """Piecewise-constant operations: constant on the box iff the enclosure is a point."""
    return res[0] != res[1]


def _jump_if_else_zero(args, res):
    t, p = _truth(*args[0])  # the condition may be zero and may be nonzero
    return p & ~t


def _jump_fabs(args, res):
    lo, hi = args[0]
    return (lo < 0.0) & (hi > 0.0)


def _jump_minmax(args, res):
    (al, ah), (bl, bh) = args
    return (al < bh) & (bl < ah)  # a = b somewhere inside (touching ends: one branch)


def _jump_hypot(args, res):
    (al, ah), (bl, bh) = args
    return (al <= 0.0) & (ah >= 0.0) & (bl <= 0.0) & (bh >= 0.0)


def _jump_copysign(args, res):
    (xl, xh), (yl, yh) = args
    return ((yl <= 0.0) & (yh >= 0.0)) | ((xl < 0.0) & (xh > 0.0))


def _jump_atan2(args, res):
    (yl, yh), (xl, xh) = args  # cut y = 0, x <= 0 (and the origin)
    return (yl <= 0.0) & (yh >= 0.0) & (xl <= 0.0)


def _jump_fmod(args, res):
    """``fmod(x, y) = x - trunc(x/y) y`` jumps where ``x/y`` crosses a nonzero integer."""
    (xl, xh), (yl, yh) = args
    ql, qh = _div(xl, xh, yl, yh)  # outward enclosure of x / y (infinite if 0 in y)
    fl, fh = np.floor(ql), np.floor(qh)
    cl, ch = np.ceil(ql), np.ceil(qh)
    smooth = (((ql > -1.0) & (qh < 1.0)) | ((ql >= 0.0) & (fl == fh))
              | ((qh <= 0.0) & (cl == ch)))
    return ~smooth


def _dom_interval(lo_ok, lo_strict, hi_ok, hi_strict):
    """Domain ``(a, b)`` / ``[a, b]`` predicates for monotone range tests."""
    def pred(args):
        lo, hi = args[0]
        ok = np.ones(np.shape(lo), bool)
        out = np.zeros(np.shape(lo), bool)
        if lo_ok is not None:
            ok &= (lo > lo_ok) if lo_strict else (lo >= lo_ok)
            out |= (hi <= lo_ok) if lo_strict else (hi < lo_ok)
        if hi_ok is not None:
            ok &= (hi < hi_ok) if hi_strict else (hi <= hi_ok)
            out |= (lo >= hi_ok) if hi_strict else (lo > hi_ok)
        return ok, out
    return pred


def _dom_nonzero(lo, hi):
    return (lo > 0.0) | (hi < 0.0), (lo == 0.0) & (hi == 0.0)


def _dom_tan(args):
    lo, hi = args[0]
    pole = _period_index(hi, _PIO2, False) >= _period_index(lo, _PIO2, True)
    # a point (lo = hi) is a float, never a pole pi/2 + k pi
    return ~pole | (lo == hi), np.zeros(np.shape(lo), bool)


def _dom_pow(args):
    """``x**y``: ``x > 0``; ``x = 0, y > 0``; ``y`` integer and (``y >= 0`` or ``x != 0``)."""
    (xl, xh), (yl, yh) = args
    y_int = (yl == yh) & _is_int(yl)
    x_nonzero = (xl > 0.0) | (xh < 0.0)
    ok = (xl > 0.0) | ((xl >= 0.0) & (yl > 0.0)) | (y_int & ((yl >= 0.0) | x_nonzero))
    no_int = np.floor(yh) < np.ceil(yl)  # no integer exponent in [yl, yh]
    x_zero = (xl == 0.0) & (xh == 0.0)
    out = ((xh < 0.0) & no_int) | (x_zero & (yh < 0.0))
    return ok, out


_JUMPS: dict[int, Callable] = {
    **{op: _result_varies for op in (
        ca.OP_SIGN, ca.OP_FLOOR, ca.OP_CEIL, ca.OP_NOT, ca.OP_LT, ca.OP_LE, ca.OP_EQ,
        ca.OP_NE, ca.OP_AND, ca.OP_OR)},
    ca.OP_IF_ELSE_ZERO: _jump_if_else_zero,
    ca.OP_FABS: _jump_fabs,
    ca.OP_FMIN: _jump_minmax,
    ca.OP_FMAX: _jump_minmax,
    ca.OP_HYPOT: _jump_hypot,
    ca.OP_COPYSIGN: _jump_copysign,
    ca.OP_ATAN2: _jump_atan2,
    ca.OP_FMOD: _jump_fmod,
}

_DOMAINS: dict[int, Callable] = {
    ca.OP_SQRT: _dom_interval(0.0, False, None, False),
    ca.OP_LOG: _dom_interval(0.0, True, None, False),
    ca.OP_LOG1P: _dom_interval(-1.0, True, None, False),
    ca.OP_ASIN: _dom_interval(-1.0, False, 1.0, False),
    ca.OP_ACOS: _dom_interval(-1.0, False, 1.0, False),
    ca.OP_ACOSH: _dom_interval(1.0, False, None, False),
    ca.OP_ATANH: _dom_interval(-1.0, True, 1.0, True),
    ca.OP_INV: lambda args: _dom_nonzero(*args[0]),
    ca.OP_DIV: lambda args: _dom_nonzero(*args[1]),
    ca.OP_FMOD: lambda args: _dom_nonzero(*args[1]),
    ca.OP_TAN: _dom_tan,
    ca.OP_POW: _dom_pow,
    ca.OP_CONSTPOW: _dom_pow,
}


class _Tainted(Interval):
    """An interval array with per-element "not proved defined" masks (checked walks only).

    ``um``: some partial operation this value depends on may be applied outside its
    domain; ``us``: certainly is (at every point of the box); ``uo``: that operation's code
    where ``us`` (``-1`` elsewhere). Masks have the shape of ``lo`` (possibly broadcast,
    read-only views).
    """

    __slots__ = ("um", "us", "uo")


def _taint(x):
    """``(um, us, uo)`` of a value, or ``None`` when it is proved defined everywhere."""
    if type(x) is _Tainted:
        return x.um, x.us, x.uo
    return None


def _merge(*taints):
    """Elementwise union of taints (broadcasting); ``None`` if all are ``None``."""
    out = None
    for t in taints:
        if t is None:
            continue
        if out is None:
            out = t
            continue
        um, us, uo = out
        um2, us2, uo2 = t
        out = (um | um2, us | us2, np.where(uo >= 0, uo, uo2))
    return out


def _attach(res: Interval, t) -> Interval:
    """``res`` carrying taint ``t`` (broadcast to its shape)."""
    if t is None:
        return res
    um, us, uo = t
    if not np.any(um):
        return res
    x = _NEW(_Tainted)
    x.lo = res.lo
    x.hi = res.hi
    shape = res.lo.shape
    x.um = np.broadcast_to(um, shape)
    x.us = np.broadcast_to(us, shape)
    x.uo = np.broadcast_to(uo, shape)
    return x


def _domain_taint(op, args):
    """Taint created by a partial operation ``op`` on its interval arguments."""
    dom = _DOMAINS.get(op)
    if dom is None:
        return None
    ok, out = dom([(a.lo, a.hi) for a in args])
    if ok.all():
        return None
    return ~ok, out, np.where(out, np.int32(op), np.int32(-1))


class CheckedIntervalArithmetic(IntervalArithmetic):
    """Interval arithmetic that also records, per box and per output, the checks for jumps
    and partial domains.

    Same values and enclosures as :class:`IntervalArithmetic`, plus:

    - kinks and jumps: evaluating a walker ``Program`` whose ``checked`` flag is set
      calls :meth:`check` after every non-smooth operation of
      ``nlyap_opt.kernel.walker.CHECKED_OPS``, with the outputs of the Function that operation
      feeds (static liveness); ``jump[b, j]``: some non-smooth operation feeding output
      ``j`` may meet its kink or jump set on box ``b`` (the mean-value form must not be
      used for that output);
    - domains: every value carries, per element, whether some partial operation it
      depends on may be (or certainly is) applied outside its domain; the taint flows
      through every operation, matrix product, sum and rearrangement, except that
      ``if_else_zero(c, x)`` (CasADi's ``if_else``) drops the taint of ``x`` where ``c`` is
      certainly 0 (``c ? x : 0`` is then 0, as CasADi evaluates it). :meth:`collect` reads
      the outputs' taints into ``maybe_undefined[b, j]`` (output ``j`` is not proved
      defined on box ``b``: its enclosure covers its defined points only and proves
      nothing), ``undefined[b, j]`` (certainly undefined on the whole box) and
      ``undefined_op[b, j]`` (that operation's code, ``-1``: none).

    One instance serves one walk of ``n_boxes`` boxes (inputs of shape ``(n_boxes, n)``);
    instances compare equal so that the walker's constant cache is shared.

    Parameters
    ----------
    n_boxes : int
    n_outputs : int
    """

    def __init__(self, n_boxes: int, n_outputs: int):
        self.n_boxes = int(n_boxes)
        shape = (self.n_boxes, int(n_outputs))
        self.jump = np.zeros(shape, bool)
        self.maybe_undefined = np.zeros(shape, bool)
        self.undefined = np.zeros(shape, bool)
        self.undefined_op = np.full(shape, -1, dtype=np.int32)
        self._override = None

    def __hash__(self) -> int:
        return hash(CheckedIntervalArithmetic)

    def __eq__(self, other) -> bool:
        return type(other) is CheckedIntervalArithmetic

    # -- values with domain taint
    def unary(self, op: int, a: Interval) -> Interval:
        """As :meth:`IntervalArithmetic.unary`, propagating and creating domain taint."""
        a = _as_interval(a)
        res = super().unary(op, a)
        with fp_ignore():
            return _attach(res, _merge(_taint(a), _domain_taint(op, (a,))))

    def binary(self, op: int, a: Interval, b: Interval) -> Interval:
        """As :meth:`IntervalArithmetic.binary`, propagating and creating domain taint."""
        a = _as_interval(a)
        b = _as_interval(b)
        res = super().binary(op, a, b)
        ta, tb = _taint(a), _taint(b)
        if ta is None and tb is None and op not in _DOMAINS:
            return res
        with fp_ignore():
            if op == ca.OP_IF_ELSE_ZERO and tb is not None:
                t, p = _truth(a.lo, a.hi)  # c certainly / possibly nonzero
                um, us, uo = tb
                tb = (um & p, us & t, np.where(us & t, uo, np.int32(-1)))
            return _attach(res, _merge(ta, tb, _domain_taint(op, (a, b))))

    def matmul(self, a, b) -> Interval:
        """As :meth:`IntervalArithmetic.matmul`; an entry is tainted by its row and column."""
        a = _as_interval(a)
        b = _as_interval(b)
        res = super().matmul(a, b)
        ta, tb = _taint(a), _taint(b)
        if ta is None and tb is None:
            return res
        shape = res.lo.shape
        parts = []
        for t, axis, expand in ((ta, -1, -1), (tb, -2, -2)):
            if t is None:
                continue
            um, us, uo = t
            if um.ndim < 2:  # 1-D operand: every entry of the result
                parts.append((np.full(shape, um.any()), np.full(shape, us.any()),
                              np.full(shape, np.int32(uo.max()))))
                continue
            parts.append((np.expand_dims(um.any(axis=axis), expand),
                          np.expand_dims(us.any(axis=axis), expand),
                          np.expand_dims(uo.max(axis=axis), expand)))
        return _attach(res, _merge(*parts))

    def sum(self, a: Interval, axis=None) -> Interval:
        """As :meth:`IntervalArithmetic.sum`; the sum is tainted by any of its terms."""
        a = _as_interval(a)
        res = super().sum(a, axis)
        t = _taint(a)
        if t is None:
            return res
        um, us, uo = t
        nd = a.lo.ndim
        axes = tuple(range(nd)) if axis is None else (
            (axis,) if np.ndim(axis) == 0 else tuple(axis))
        axes = tuple(sorted({int(ax) % nd for ax in axes})) if nd else ()
        return _attach(res, (um.any(axis=axes), us.any(axis=axes), uo.max(axis=axes)))

    def structural(self, fn: Callable, *args: Interval) -> Interval:
        """As :meth:`IntervalArithmetic.structural`; the taint is rearranged alike."""
        args = [_as_interval(x) for x in args]
        res = super().structural(fn, *args)
        taints = [_taint(x) for x in args]
        if all(t is None for t in taints):
            return res
        full = [t if t is not None else (np.zeros(x.lo.shape, bool), np.zeros(x.lo.shape, bool),
                                         np.full(x.lo.shape, -1, dtype=np.int32))
                for x, t in zip(args, taints)]
        um = np.asarray(fn(*[t[0] for t in full])) != 0
        us = np.asarray(fn(*[t[1] for t in full])) != 0
        uo = np.asarray(fn(*[t[2] for t in full])).astype(np.int32)
        return _attach(res, (um, us, np.where(us, uo, np.int32(-1))))

    def nonneg(self, a: Interval) -> Interval:
        """As :meth:`IntervalArithmetic.nonneg`, keeping the taint."""
        return _attach(IntervalArithmetic.nonneg(a), _taint(a))

    def collect(self, outputs) -> None:
        """Read the outputs' domain taints into ``maybe_undefined``, ``undefined``, ``_op``.

        Parameters
        ----------
        outputs : list of Interval
            The walker's outputs, shapes ``(n_boxes, nnz)`` (or constants ``(nnz,)``).
        """
        for j, out in enumerate(outputs):
            t = _taint(out) if out is not None else None
            if t is None:
                continue
            um, us, uo = t
            self.maybe_undefined[:, j] |= self._per_box(um, 1)
            sure = self._per_box(us, 1)
            if sure.any():
                op = self._per_box_op(uo, us)
                new = sure & (self.undefined_op[:, j] < 0)
                self.undefined_op[:, j] = np.where(new, op, self.undefined_op[:, j])
                self.undefined[:, j] |= sure

    def _per_box_op(self, uo, us) -> np.ndarray:
        """One operation code per box from the ``(n_boxes, ...)`` op codes where ``us``."""
        v = np.where(us, uo, -1)
        if v.ndim >= 2 and v.shape[0] == self.n_boxes:
            return v.reshape(self.n_boxes, -1).max(axis=1)
        return np.full(self.n_boxes, int(v.max()) if v.size else -1)

    def _per_box(self, mask, base: int) -> np.ndarray:
        """Reduce an elementwise mask to one flag per box (constants: any, for all boxes)."""
        mask = np.asarray(mask, dtype=bool)
        B = self.n_boxes
        if mask.ndim > base:
            m = mask if mask.ndim == 1 else mask.reshape(mask.shape[0], -1).any(axis=1)
            if m.shape[0] == B:
                return m
            if m.shape[0] == 1:
                return np.broadcast_to(m, (B,))
        return np.full(B, bool(mask.any()))

    def enter_call(self, feeds) -> object:
        """Attribute checks inside a called Function through the call's ``feeds``.

        Parameters
        ----------
        feeds : list of ndarray of int
            Per output ``j`` of the callee, the outputs of the calling Function that it
            feeds. Within the call, a check that feeds the callee's outputs ``J`` is recorded
            for the union of ``feeds[j]``, ``j ∈ J`` (composed through nested calls down to
            the outputs of the Function evaluated at the top).

        Returns
        -------
        object
            The token for :meth:`exit_call`.
        """
        token = self._override
        if token is not None:  # a call inside a call: through the outer call's attribution
            feeds = [self._through(token, f) for f in feeds]
        self._override = feeds
        return token

    def exit_call(self, token: object) -> None:
        """Undo :meth:`enter_call` (``token``: its return value)."""
        self._override = token

    @staticmethod
    def _through(override: list, feeds) -> np.ndarray:
        """The top-level outputs that the current callee's outputs ``feeds`` feed."""
        parts = [override[j] for j in feeds]
        if not parts:
            return np.zeros(0, dtype=np.intp)
        return np.unique(np.concatenate(parts)).astype(np.intp)

    def check(self, op: int, feeds, base: int, args, res: Interval) -> None:
        """Record whether a non-smooth operation may meet its kink or jump set, per box.

        Parameters
        ----------
        op : int
            CasADi operation code (in ``CHECKED_OPS``; partial operations are handled by
            the domain taint of the values instead).
        feeds : ndarray of int
            Outputs of the evaluated Function that this operation feeds.
        base : int
            Trailing non-batch dimensions of a register (0 in SX, 2 in MX programs).
        args : tuple of Interval
            The operation's arguments.
        res : Interval
            Its result.
        """
        if self._override is not None:
            feeds = self._through(self._override, feeds)
        if not len(feeds):
            return
        bounds = [(a.lo, a.hi) for a in map(_as_interval, args)]
        with fp_ignore():
            jump = _JUMPS.get(op)
            if jump is not None:
                m = self._per_box(jump(bounds, (res.lo, res.hi)), base)
                if m.any():
                    self.jump[:, feeds] |= m[:, None]
