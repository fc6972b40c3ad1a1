"""Soundness and tightness of the outward-rounded interval arithmetic.

References are computed with mpmath (50 digits) at real (not only floating) points of the
input boxes: the endpoints, interior points, and known extrema.
"""

from __future__ import annotations

import math
from fractions import Fraction

import casadi as ca
import mpmath as mp
import numpy as np
import pytest

from verification.interval import Interval, IntervalArithmetic

mp.mp.dps = 50
IA = IntervalArithmetic()
FRACS = [mp.mpf(0), mp.mpf(1), mp.mpf("0.5"), mp.mpf(1) / 3, mp.mpf("0.9"), mp.mpf("0.01")]


# --------------------------------------------------------------------------- helpers
def _real(v):
    """mpmath value as a real mpf, or None (complex, NaN)."""
    if isinstance(v, mp.mpc):
        if v.imag != 0:
            return None
        v = v.real
    v = mp.mpf(v)
    return None if mp.isnan(v) else v


def _points(lo: float, hi: float, extra=()) -> list:
    """Real points of [lo, hi]: endpoints, interior fractions, and ``extra`` points inside."""
    a, b = mp.mpf(lo), mp.mpf(hi)
    if mp.isinf(a) or mp.isinf(b):
        pts = [p for p in (a, b) if not mp.isinf(p)]
    else:
        pts = [a + t * (b - a) for t in FRACS]
    pts += [mp.mpf(e) for e in extra if a <= e <= b]
    return pts


def _intervals(rng, n: int, lo_mag: float = -6.0, hi_mag: float = 2.0):
    """Random intervals: degenerate, relatively narrow, wide, zero-straddling, negative."""
    c = 10.0 ** rng.uniform(lo_mag, hi_mag, n) * rng.choice([-1.0, 1.0], n)
    kind = rng.integers(0, 5, n)
    rel = 10.0 ** rng.uniform(-15, -1, n) * np.abs(c)
    absw = 10.0 ** rng.uniform(-3, 0.5, n)
    w = np.select([kind == 0, kind == 1, kind == 2], [0.0, rel, absw], absw)
    lo = c - w * rng.uniform(0, 1, n)
    hi = lo + w
    straddle = kind == 4  # contains 0
    lo = np.where(straddle, -absw * rng.uniform(0, 1, n), lo)
    hi = np.where(straddle, absw * rng.uniform(0, 1, n), hi)
    return lo, hi


def _check_unary(op, ref, lo, hi, extrema=None, tight=True, bounded=True):
    """Enclosure of mpmath reference ``ref`` at real points; tightness for narrow boxes."""
    res = IA.unary(op, Interval(lo, hi))
    assert res.shape == np.shape(lo)
    assert not np.isnan(res.lo).any() and not np.isnan(res.hi).any()
    assert (res.lo <= res.hi).all()
    for i in range(len(lo)):
        extra = extrema(lo[i], hi[i]) if extrema else ()
        vals = [v for v in (_real(ref(x)) for x in _points(lo[i], hi[i], extra)) if v is not None]
        rl, rh = mp.mpf(res.lo[i]), mp.mpf(res.hi[i])
        for v in vals:
            assert rl <= v <= rh, (op, lo[i], hi[i], v, res.lo[i], res.hi[i])
        if bounded:
            assert np.isfinite(res.lo[i]) and np.isfinite(res.hi[i]), (lo[i], hi[i], res[i])
        if tight and vals and hi[i] - lo[i] <= 1e-6 * max(1.0, abs(lo[i])):
            finite = [v for v in vals if mp.isfinite(v)]
            true_w = max(finite) - min(finite)
            scale = max(1, max(abs(v) for v in finite))
            assert rh - rl <= true_w + mp.mpf("1e-12") * scale, (op, lo[i], hi[i], res[i])
    return res


def _pi_multiples(step):
    """Extrema ``k * step`` (mpmath) inside [lo, hi]."""
    def f(lo, hi):
        if not (math.isfinite(lo) and math.isfinite(hi)) or hi - lo > 100:
            return ()
        k0 = math.floor(lo / float(step)) - 1
        k1 = math.ceil(hi / float(step)) + 1
        return [k * step for k in range(k0, k1 + 1)]
    return f


def _with_zero(lo, hi):
    return (0,)


def _clip(lo, hi, a, b):
    return np.clip(lo, a, b), np.clip(hi, a, b)


def _shift(lo, hi, a):
    """``[|lo| + a, |lo| + a + width]`` (keeps lo <= hi under rounding)."""
    new = np.abs(lo) + a
    return new, np.maximum(new + (hi - lo), new)


# --------------------------------------------------------------------------- unary ops
UNARY_CASES = {
    # name: (mpmath reference, domain transform of (lo, hi), extrema, tight)
    "NEG": (lambda x: -x, None, None),
    "ASSIGN": (lambda x: x, None, None),
    "TWICE": (lambda x: 2 * x, None, None),
    "FABS": (abs, None, _with_zero),
    "SQ": (lambda x: x * x, None, _with_zero),
    "SQRT": (mp.sqrt, lambda lo, hi: _shift(lo, hi, 0.0), None),
    "INV": (lambda x: 1 / x, lambda lo, hi: _shift(lo, hi, 1e-3), None),
    "EXP": (mp.exp, lambda lo, hi: _clip(lo, hi, -700, 700), None),
    "EXPM1": (mp.expm1, lambda lo, hi: _clip(lo, hi, -700, 700), None),
    "LOG": (mp.log, lambda lo, hi: _shift(lo, hi, 1e-300), None),
    "LOG1P": (mp.log1p, lambda lo, hi: _shift(lo, hi, -0.5), None),
    "SIN": (mp.sin, None, _pi_multiples(mp.pi / 2)),
    "COS": (mp.cos, None, _pi_multiples(mp.pi / 2)),
    "TAN": (mp.tan, lambda lo, hi: (lo * 1e-2, lo * 1e-2 + np.minimum(hi - lo, 1e-3)), None),
    "TANH": (mp.tanh, None, None),
    "ATAN": (mp.atan, None, None),
    "SINH": (mp.sinh, lambda lo, hi: _clip(lo, hi, -700, 700), None),
    "COSH": (mp.cosh, lambda lo, hi: _clip(lo, hi, -700, 700), _with_zero),
    "ASINH": (mp.asinh, None, None),
    "ASIN": (mp.asin, lambda lo, hi: _clip(lo, hi, -1, 1), None),
    "ACOS": (mp.acos, lambda lo, hi: _clip(lo, hi, -1, 1), None),
    "ACOSH": (mp.acosh, lambda lo, hi: _shift(lo, hi, 1.0), None),
    "ATANH": (mp.atanh, lambda lo, hi: _clip(lo, hi, -0.999, 0.999), None),
    "ERF": (mp.erf, None, None),
    "SIGN": (mp.sign, None, _with_zero),
    "FLOOR": (mp.floor, None, None),
    "CEIL": (mp.ceil, None, None),
    "NOT": (lambda x: mp.mpf(x == 0), None, None),
}


@pytest.mark.parametrize("name", sorted(UNARY_CASES))
def test_unary_enclosure_and_tightness(name):
    ref, dom, extrema = UNARY_CASES[name]
    rng = np.random.default_rng(sum(map(ord, name)))
    lo, hi = _intervals(rng, 60)
    lo = np.concatenate([lo, [0.0, -0.0, 1e-300, -2.5, 1.0]])
    hi = np.concatenate([hi, [0.0, 0.0, 1e-300, 2.5, 1.0]])
    if dom is not None:
        lo, hi = dom(lo, hi)
    _check_unary(getattr(ca, "OP_" + name), ref, lo, hi, extrema)


@pytest.mark.parametrize("name", ["SIN", "COS"])
def test_trig_wide_and_large_arguments(name):
    rng = np.random.default_rng(3)
    op, ref = getattr(ca, "OP_" + name), UNARY_CASES[name][0]
    lo = np.concatenate([rng.uniform(-1e5, 1e5, 30), [-1e12, 1e15, 2 * math.pi * 1e6]])
    hi = lo + np.concatenate([rng.uniform(0, 4, 30), [1e-3, 0.0, 0.0]])
    _check_unary(op, ref, lo, hi, _pi_multiples(mp.pi / 2), tight=False)
    # a full period (or more) gives [-1, 1]
    r = IA.unary(op, Interval([0.0, -100.0, 1.0], [2 * math.pi, 100.0, 1.0 + 6.3]))
    np.testing.assert_array_equal(r.lo, -1.0)
    np.testing.assert_array_equal(r.hi, 1.0)
    # extremum inside a narrow box is attained exactly
    p = math.pi / 2 if name == "SIN" else 0.0
    r = IA.unary(op, Interval(p - 1e-9, p + 1e-9))
    assert r.hi == 1.0 and r.lo < 1.0 and 1.0 - r.lo < 1e-14
    # unbounded input
    r = IA.unary(op, Interval(-np.inf, 0.0))
    assert r.lo == -1.0 and r.hi == 1.0


def test_tan_poles():
    r = IA.unary(ca.OP_TAN, Interval([1.5, -1.6, 0.0, 1.0, 4.0], [1.6, -1.5, 3.2, 1.5, 4.5]))
    assert np.all(r.lo[:3] == -np.inf) and np.all(r.hi[:3] == np.inf)
    assert np.all(np.isfinite(r.lo[3:])) and np.all(np.isfinite(r.hi[3:]))
    assert r.lo[3] <= math.tan(1.0) and r.hi[3] >= mp.tan(1.5)
    # float(pi/2) is below pi/2, but too close for the (conservative) pole test
    r = IA.unary(ca.OP_TAN, Interval([0.0, 0.0], [math.pi / 2, 1.57]))
    assert r.hi[0] == np.inf and mp.mpf(r.hi[1]) >= mp.tan(mp.mpf(1.57))


def test_domain_rules():
    x = Interval([-1.0, -2.0, 0.0, -1.0, 0.0], [4.0, -1.0, 1.0, 0.0, 0.0])
    s = IA.unary(ca.OP_SQRT, x)
    assert s.lo[0] == 0.0 and 2.0 <= s.hi[0] < 2.0 + 1e-15  # enclosure on the domain part
    assert s.lo[1] == -np.inf and s.hi[1] == np.inf  # entirely outside: unknown
    assert s.lo[2] == 0.0 and s.hi[2] >= 1.0
    assert s.lo[4] == 0.0 and s.hi[4] < 1e-300  # sqrt(0) = 0
    lg = IA.unary(ca.OP_LOG, x)
    assert lg.lo[2] == -np.inf and 0.0 <= lg.hi[2] < 1e-300  # log([0, 1]) = [-inf, 0]
    assert lg.lo[0] == -np.inf and mp.mpf(lg.hi[0]) >= mp.log(4)
    for i in (1, 3, 4):  # no point of the domain x > 0
        assert lg.lo[i] == -np.inf and lg.hi[i] == np.inf
    l1 = IA.unary(ca.OP_LOG1P, Interval([-1.0, -3.0], [0.0, -1.0]))
    assert l1.lo[0] == -np.inf and l1.hi[1] == np.inf
    a = IA.unary(ca.OP_ASIN, Interval([0.5, 2.0], [2.0, 3.0]))
    assert mp.mpf(a.hi[0]) >= mp.pi / 2 and a.hi[1] == np.inf
    a = IA.unary(ca.OP_ATANH, Interval([0.5, 1.0], [1.0, 2.0]))
    assert a.hi[0] == np.inf and a.lo[1] == -np.inf


def test_division_and_inverse_by_zero_containing():
    a = Interval([1.0, -1.0, 1.0, 0.0], [2.0, 1.0, 2.0, 0.0])
    b = Interval([-1.0, 0.0, -0.0, 0.0], [1.0, 1.0, 0.0, 0.0])
    r = IA.binary(ca.OP_DIV, a, b)
    assert np.all(r.lo == -np.inf) and np.all(r.hi == np.inf)
    r = IA.unary(ca.OP_INV, b)
    assert np.all(r.lo == -np.inf) and np.all(r.hi == np.inf)
    r = IA.binary(ca.OP_DIV, Interval(1.0, 2.0), IA.constant(np.array(0.0)))
    assert r.lo == -np.inf and r.hi == np.inf


def test_outward_rounding_of_basic_operations():
    a, b = IA.constant(np.array(0.1)), IA.constant(np.array(0.2))
    exact = Fraction(0.1) + Fraction(0.2)
    r = IA.binary(ca.OP_ADD, a, b)
    assert Fraction(float(r.lo)) <= exact <= Fraction(float(r.hi))
    assert r.lo < 0.1 + 0.2 and r.hi > 0.30000000000000004 - 1e-16
    assert r.hi - r.lo < 1e-15
    for op, f in [(ca.OP_SUB, lambda x, y: x - y), (ca.OP_MUL, lambda x, y: x * y),
                  (ca.OP_DIV, lambda x, y: x / y)]:
        rng = np.random.default_rng(op)
        x, y = rng.normal(size=200), rng.normal(size=200)
        r = IA.binary(op, IA.constant(x), IA.constant(y))
        for i in range(200):
            e = f(Fraction(x[i]), Fraction(y[i]))
            assert Fraction(r.lo[i]) <= e <= Fraction(r.hi[i])
            assert r.lo[i] < r.hi[i]  # rounded outward even when exact (harmless)
    # underflow: the product of two tiny numbers is not zero in the reals
    r = IA.binary(ca.OP_MUL, IA.constant(np.array(1e-200)), IA.constant(np.array(-1e-200)))
    assert r.lo < 0.0 <= r.hi
    # overflow: a lower bound stays finite, an upper bound becomes inf
    r = IA.binary(ca.OP_MUL, Interval(1e200, 1e200), Interval(1e200, 1e200))
    assert r.lo == np.finfo(float).max and r.hi == np.inf


# --------------------------------------------------------------------------- binary ops
def _check_binary(op, ref, x, y, tight=True, bounded=True):
    res = IA.binary(op, x, y)
    assert not np.isnan(res.lo).any() and not np.isnan(res.hi).any()
    assert (res.lo <= res.hi).all()
    xl, xh = np.broadcast_to(x.lo, res.shape), np.broadcast_to(x.hi, res.shape)
    yl, yh = np.broadcast_to(y.lo, res.shape), np.broadcast_to(y.hi, res.shape)
    for i in np.ndindex(res.shape):
        px = _points(xl[i], xh[i])[:4]
        py = _points(yl[i], yh[i])[:4]
        vals = []
        for a in px:
            for b in py:
                try:
                    v = _real(ref(a, b))
                except (ZeroDivisionError, ValueError):
                    v = None
                if v is not None:
                    vals.append(v)
        rl, rh = mp.mpf(res.lo[i]), mp.mpf(res.hi[i])
        for v in vals:
            assert rl <= v <= rh, (op, xl[i], xh[i], yl[i], yh[i], v, res.lo[i], res.hi[i])
        if bounded:
            assert np.isfinite(res.lo[i]) and np.isfinite(res.hi[i]), (xl[i], xh[i], yl[i], yh[i])
        narrow = (xh[i] - xl[i] <= 1e-9 * max(1, abs(xl[i]))
                  and yh[i] - yl[i] <= 1e-9 * max(1, abs(yl[i])))
        if tight and vals and narrow:
            true_w = max(vals) - min(vals)
            scale = max(1, max(abs(v) for v in vals))
            assert rh - rl <= true_w + mp.mpf("1e-12") * scale, (op, res[i])
    return res


def _pair(rng, n, **kw):
    lo, hi = _intervals(rng, n, **kw)
    lo2, hi2 = _intervals(rng, n, **kw)
    return Interval(lo, hi), Interval(lo2, hi2)


def _away_from_zero(x: Interval) -> Interval:
    s = np.where(x.lo + x.hi >= 0, 1.0, -1.0)
    lo = np.abs(x.lo) + 0.1
    return Interval(np.where(s > 0, lo, -(lo + x.width)), np.where(s > 0, lo + x.width, -lo))


def _positive(x: Interval) -> Interval:
    lo = np.abs(x.lo) + 1e-3
    return Interval(lo, lo + x.width)


def _fmod_ref(a, b):
    """C fmod: ``a - b trunc(a / b)`` (mpmath's fmod follows Python's ``%``)."""
    q = a / b
    return a - b * (mp.floor(q) if q >= 0 else mp.ceil(q))


def _copysign_ref(a, b):
    return abs(a) if b >= 0 else -abs(a)


BINARY_CASES = {
    "ADD": (lambda a, b: a + b, None),
    "SUB": (lambda a, b: a - b, None),
    "MUL": (lambda a, b: a * b, None),
    "DIV": (lambda a, b: a / b, lambda x, y: (x, _away_from_zero(y))),
    "FMIN": (min, None),
    "FMAX": (max, None),
    "HYPOT": (mp.hypot, None),
    "ATAN2": (mp.atan2, lambda x, y: (x, _positive(y))),
    "COPYSIGN": (_copysign_ref, None),
    "FMOD": (_fmod_ref, lambda x, y: (x, _away_from_zero(y))),
    "POW": (mp.power, lambda x, y: (_positive(x), Interval(y.lo / 50, y.hi / 50))),
    "LT": (lambda a, b: mp.mpf(a < b), None),
    "LE": (lambda a, b: mp.mpf(a <= b), None),
    "EQ": (lambda a, b: mp.mpf(a == b), None),
    "NE": (lambda a, b: mp.mpf(a != b), None),
    "AND": (lambda a, b: mp.mpf(bool(a) and bool(b)), None),
    "OR": (lambda a, b: mp.mpf(bool(a) or bool(b)), None),
    "IF_ELSE_ZERO": (lambda c, x: x if c != 0 else mp.mpf(0), None),
}


@pytest.mark.parametrize("name", sorted(BINARY_CASES))
def test_binary_enclosure_and_tightness(name):
    ref, dom = BINARY_CASES[name]
    rng = np.random.default_rng(sum(map(ord, name)) + 7)
    x, y = _pair(rng, 50)
    if dom is not None:
        x, y = dom(x, y)
    tight = name not in ("FMOD",)
    _check_binary(getattr(ca, "OP_" + name), ref, x, y, tight=tight)
    # degenerate operands in either position, and scalar constants
    c = IA.constant(y.lo[:1].reshape(()))
    _check_binary(getattr(ca, "OP_" + name), ref, x, c, tight=tight)
    c = IA.constant(x.lo[:1].reshape(()))
    _check_binary(getattr(ca, "OP_" + name), ref, c, y, tight=tight)


def test_atan2_branch_cut_and_origin():
    y = Interval([-1.0, 0.0, -1.0, 1.0, -2.0], [1.0, 1.0, 1.0, 2.0, -1.0])
    x = Interval([-2.0, -2.0, 0.0, -3.0, -3.0], [-1.0, -1.0, 1.0, -1.0, -1.0])
    r = _check_binary(ca.OP_ATAN2, mp.atan2, y, x, tight=False)
    assert np.all(r.lo[:3] <= -math.pi) and np.all(r.hi[:3] >= math.pi)
    assert r.hi[3] >= math.pi - math.atan(0.5) - 1e-12 and r.lo[3] > 1.5  # upper half, x < 0
    assert r.hi[4] < -1.5  # lower half, x < 0


def test_pow_integer_exponents_and_negative_bases():
    rng = np.random.default_rng(11)
    lo, hi = _intervals(rng, 40, lo_mag=-3, hi_mag=1)
    x = Interval(lo, hi)
    for n in [0, 1, 2, 3, 4, 5, 7, 10, -1, -2, -3, 65, 100]:
        r = _check_binary(ca.OP_CONSTPOW, lambda a, b: a ** int(b), x,
                          IA.constant(np.array(float(n))), tight=True, bounded=False)
        if n >= 0:
            assert np.all(np.isfinite(r.hi))
    # mixed array exponent: integers and non-integers elementwise
    y = IA.constant(np.array([2.0, 0.5, -3.0, 1.5]))
    x = Interval(np.array([-2.0, 0.25, 0.5, 1.0]), np.array([3.0, 4.0, 2.0, 4.0]))
    _check_binary(ca.OP_POW, lambda a, b: a**b, x, y)
    # negative bases: non-integer constant exponent is enclosed on the domain part only;
    # a varying exponent or an entirely negative base gives unknown
    r = IA.binary(ca.OP_POW, Interval([-1.0, -2.0, -1.0], [4.0, -1.0, 4.0]),
                  Interval([0.5, 0.5, 1.5], [0.5, 0.5, 2.5]))
    assert r.lo[0] == 0.0 and 2.0 <= r.hi[0] < 2.0 + 1e-12
    assert r.lo[1] == -np.inf and r.hi[1] == np.inf
    assert r.lo[2] == -np.inf and r.hi[2] == np.inf
    # huge integer exponents are even: negative bases are in the domain
    r = IA.binary(ca.OP_POW, Interval([-3.0, -1.0, -0.5], [1.0, 1.0, 0.5]),
                  IA.constant(np.array([2.0**70, 1e300, 2.0**60])))
    assert r.hi[0] == np.inf and r.lo[0] <= 0.0 and r.hi[1] >= 1.0 and r.lo[2] <= 0.0
    assert 0.0 <= r.hi[2] < 1e-300
    # x^-2 at 0: upper bound infinite; 0^-1: unknown
    r = IA.binary(ca.OP_POW, Interval([-1.0, 0.0], [2.0, 0.0]), IA.constant(np.array(-2.0)))
    assert r.hi[0] == np.inf and 0.0 <= r.lo[0] <= 0.25 and r.lo[1] == -np.inf


@pytest.mark.parametrize("n", [3, 5, 31, 63, 64, 65, 200, -3, -64])
def test_integer_powers_of_points_exact(n):
    """x**n at float points against exact rationals (errors compound in binary powering)."""
    rng = np.random.default_rng(abs(n))
    x = rng.uniform(0.5, 1.5, 300) * rng.choice([-1.0, 1.0], 300)
    x[:5] = [1.0, -1.0, 0.5, 1.0 + 2**-52, 1.0 - 2**-53]
    r = IA.binary(ca.OP_CONSTPOW, Interval(x, x.copy()), IA.constant(np.array(float(n))))
    for i in range(300):
        e = Fraction(x[i]) ** n
        assert Fraction(r.lo[i]) <= e <= Fraction(r.hi[i]), (x[i], n)
        assert r.hi[i] - r.lo[i] <= 1e-13 * abs(float(e))


def test_fmod_constant_divisor_is_tight():
    # a point divisor (graph constants other than integers are widened by 2^-50: the
    # general, looser path then applies)
    two_pi = np.array(2 * math.pi)
    c = Interval(two_pi, two_pi)
    x = Interval([7.0, -7.0, 1.0], [7.5, -6.5, 20.0])
    r = _check_binary(ca.OP_FMOD, _fmod_ref, x, c, tight=False)
    assert r.hi[0] - r.lo[0] < 0.5 + 1e-12 and r.lo[0] > 0.7
    assert r.hi[1] < 0.0 and r.lo[1] > -1.0
    assert r.lo[2] == 0.0 and r.hi[2] >= 2 * math.pi - 1e-9  # wraps: [0, 2 pi]
    # x / c rounds up to the integer 33 although the real quotient is below it: the real
    # fmod is close to c, not close to 0
    x, c = 213.688966280683, 6.475423220626758
    assert x / c == 33.0 and Fraction(x) / Fraction(c) < 33
    for xs in (Interval(x, x), Interval(x, x + 1e-12), Interval(-x, -x)):
        cc = np.array(c)
        _check_binary(ca.OP_FMOD, _fmod_ref, xs, Interval(cc, cc), tight=False)


def test_mul_special_values_never_nan():
    specials = [(0.0, 0.0), (-np.inf, np.inf), (0.0, np.inf), (-np.inf, 0.0), (-1.0, 2.0),
                (3.0, 3.0), (-np.inf, -1.0), (1e308, 1e308)]
    lo = np.array([s[0] for s in specials])
    hi = np.array([s[1] for s in specials])
    x = Interval(lo[:, None], hi[:, None])
    y = Interval(lo[None, :], hi[None, :])
    for op in (ca.OP_ADD, ca.OP_SUB, ca.OP_MUL, ca.OP_DIV, ca.OP_POW, ca.OP_FMIN, ca.OP_FMAX,
               ca.OP_ATAN2, ca.OP_HYPOT, ca.OP_COPYSIGN, ca.OP_FMOD):
        r = IA.binary(op, x, y)
        assert r.shape == (8, 8)
        assert not np.isnan(r.lo).any() and not np.isnan(r.hi).any(), ca.__dict__
        assert (r.lo <= r.hi).all()
        assert (r.lo < np.inf).all() and (r.hi > -np.inf).all()
    # 0 * [1, inf] = 0 .. inf with the 0 * inf = 0 convention
    r = IA.binary(ca.OP_MUL, Interval(0.0, 1.0), Interval(1.0, np.inf))
    assert r.lo <= 0.0 and r.lo > -1e-300 and r.hi == np.inf


def test_unary_special_values_never_nan():
    lo = np.array([0.0, -np.inf, 0.0, -np.inf, -1.0, 1e308, -5.0, -1e308])
    hi = np.array([0.0, np.inf, np.inf, 0.0, 1.0, 1e308, -5.0, 1e308])
    x = Interval(lo, hi)
    for name in UNARY_CASES:
        r = IA.unary(getattr(ca, "OP_" + name), x)
        assert not np.isnan(r.lo).any() and not np.isnan(r.hi).any(), name
        assert (r.lo <= r.hi).all(), name
        assert (r.lo < np.inf).all() and (r.hi > -np.inf).all(), name


def test_semantics_match_casadi_numerics():
    """Enclosures at points contain CasADi's own float results (argument order etc.)."""
    a, b = ca.SX.sym("a"), ca.SX.sym("b")
    exprs = {
        ca.OP_ATAN2: ca.atan2(a, b), ca.OP_FMOD: ca.fmod(a, b), ca.OP_POW: a**b,
        ca.OP_COPYSIGN: ca.copysign(a, b), ca.OP_LT: a < b, ca.OP_LE: a <= b,
        ca.OP_EQ: a == b, ca.OP_NE: a != b, ca.OP_AND: ca.logic_and(a, b),
        ca.OP_OR: ca.logic_or(a, b), ca.OP_IF_ELSE_ZERO: ca.if_else(a, b, 0),
        ca.OP_FMIN: ca.fmin(a, b), ca.OP_FMAX: ca.fmax(a, b), ca.OP_HYPOT: ca.hypot(a, b),
        ca.OP_DIV: a / b,
    }
    pts = np.array([(-2.5, 1.5), (3.0, -2.0), (0.0, 2.0), (1.5, 0.0), (2.0, 2.0),
                    (-1.0, -3.0), (0.7, 0.3), (7.0, 2.5)])
    for op, e in exprs.items():
        f = ca.Function("f", [a, b], [e])
        for x, y in pts:
            v = float(f(x, y))
            if not math.isfinite(v):
                continue
            r = IA.binary(op, IA.constant(np.array(x)), IA.constant(np.array(y)))
            assert r.lo - 1e-12 <= v <= r.hi + 1e-12, (op, x, y, v, r)


# --------------------------------------------------------------------------- sum / matmul
def _frac_sum(values):
    return sum((Fraction(float(v)) for v in values), Fraction(0))


def test_sum_exact_references_with_cancellation():
    rng = np.random.default_rng(5)
    x = rng.normal(size=(7, 33)) * 10.0 ** rng.integers(-8, 8, size=(7, 33))
    x[0, :3] = [1e16, 1.0, -1e16]
    x[1] = 0.1
    x[2, ::2] = 1e300
    x[2, 1::2] = -1e300
    c = IA.sum(IA.constant(x), 1)
    for i in range(7):
        e = _frac_sum(x[i])
        assert Fraction(c.lo[i]) <= e <= Fraction(c.hi[i])
        assert c.hi[i] - c.lo[i] <= 1e-13 * np.abs(x[i]).sum() + 1e-300
    lo = x - np.abs(rng.normal(size=x.shape))
    hi = x + np.abs(rng.normal(size=x.shape))
    s = IA.sum(Interval(lo, hi), (1,))
    for i in range(7):
        assert Fraction(s.lo[i]) <= _frac_sum(lo[i]) and _frac_sum(hi[i]) <= Fraction(s.hi[i])
    s = IA.sum(Interval(lo, hi), axis=None)
    assert Fraction(float(s.lo)) <= _frac_sum(lo.ravel())
    assert _frac_sum(hi.ravel()) <= Fraction(float(s.hi))
    s = IA.sum(Interval(lo, hi), axis=0)
    assert s.shape == (33,)
    s = IA.sum(Interval([-np.inf, 1.0], [2.0, np.inf]), 0)
    assert s.lo == -np.inf and s.hi == np.inf


def _frac_matmul(A, X):
    r, k = A.shape
    c = X.shape[1]
    return [[sum((Fraction(A[i, j]) * Fraction(X[j, m]) for j in range(k)), Fraction(0))
             for m in range(c)] for i in range(r)]


def test_matmul_constant_times_interval_exact_reference():
    rng = np.random.default_rng(6)
    A = rng.normal(size=(3, 5)) * 10.0 ** rng.integers(-3, 3, size=(3, 5))
    A[0] = [1e16, 1.0, -1e16, 3.0, 0.1]
    X = rng.normal(size=(4, 5, 2))
    X[0, :, 0] = 1.0
    rad = np.abs(rng.normal(size=X.shape)) * np.array([0, 1e-12, 1e-3, 1.0])[:, None, None]
    Xi = Interval(X - rad, X + rad)
    r = IA.matmul(A, Xi)
    assert r.shape == (4, 3, 2)
    for b in range(4):
        for corner in range(8):  # random vertices of the box: exact products inside
            sgn = rng.choice([-1.0, 1.0], size=X[b].shape) if corner else 0.0
            P = X[b] + sgn * rad[b]
            assert np.all((P >= Xi.lo[b]) & (P <= Xi.hi[b]))
            E = _frac_matmul(A, P)
            for i in range(3):
                for m in range(2):
                    assert Fraction(r.lo[b, i, m]) <= E[i][m] <= Fraction(r.hi[b, i, m])
    # degenerate: width only from rounding, relative to |A| |X|
    w = r.hi[0] - r.lo[0]
    assert np.all(w <= 1e-14 * (np.abs(A) @ np.abs(X[0])) + 1e-300)
    # the same with the constant given as a degenerate Interval, and matrix @ vector
    r2 = IA.matmul(IA.constant(A), Xi)
    np.testing.assert_array_equal(r.lo, r2.lo)
    v = IA.matmul(Xi[:, :, 0], A[0])  # (4, 5) @ (5,) -> (4,)
    assert v.shape == (4,)
    for b in range(4):
        e = _frac_sum(Fraction(p) * Fraction(q) for p, q in zip(X[b, :, 0], A[0]))
        assert Fraction(v.lo[b]) <= e <= Fraction(v.hi[b])


@pytest.mark.parametrize("k", [1, 2])
def test_matmul_short_dot_products_round_outward(k):
    """For k = 1, 2 the a-priori bound is nearly attained: exact containment of fl errors."""
    rng = np.random.default_rng(20 + k)
    A = rng.uniform(1, 2, size=(400, 1, k)) * rng.choice([-1, 1], size=(400, 1, k))
    X = rng.uniform(1, 2, size=(400, k, 1))
    for r in (IA.matmul(IA.constant(A), IA.constant(X)),
              IA.matmul(Interval(A, A.copy()), Interval(X, X.copy()))):
        for i in range(400):
            e = sum((Fraction(A[i, 0, j]) * Fraction(X[i, j, 0]) for j in range(k)), Fraction(0))
            assert Fraction(r.lo[i, 0, 0]) <= e <= Fraction(r.hi[i, 0, 0])
    s = IA.sum(IA.constant(A[:, 0, :] * 0.1), -1)
    for i in range(400):
        e = sum((Fraction(v) for v in A[i, 0, :] * 0.1), Fraction(0))
        assert Fraction(s.lo[i]) <= e <= Fraction(s.hi[i])


def test_matmul_interval_times_interval_vertices():
    rng = np.random.default_rng(8)
    A = rng.normal(size=(6, 2, 3))
    X = rng.normal(size=(6, 3, 4))
    ra = np.abs(rng.normal(size=A.shape)) * 0.1
    rx = np.abs(rng.normal(size=X.shape)) * 0.1
    Ai, Xi = Interval(A - ra, A + ra), Interval(X - rx, X + rx)
    r = IA.matmul(Ai, Xi)
    assert r.shape == (6, 2, 4)
    for _ in range(10):
        P = A + rng.choice([-1.0, 0.0, 1.0], size=A.shape) * ra
        Q = X + rng.choice([-1.0, 0.0, 1.0], size=X.shape) * rx
        for b in range(6):
            E = _frac_matmul(P[b], Q[b])
            for i in range(2):
                for m in range(4):
                    assert Fraction(r.lo[b, i, m]) <= E[i][m] <= Fraction(r.hi[b, i, m])
    # mid-rad overestimates by at most a factor 1.5 (Rump); check against the
    # elementwise (exact-range per product) enclosure
    e = IA.sum(IA.binary(ca.OP_MUL, Ai[..., :, :, None], Xi[..., None, :, :]), -2)
    assert np.all(r.hi - r.lo <= 1.5 * (e.hi - e.lo) + 1e-12)


def test_matmul_non_finite_operands_fall_back():
    A = IA.constant(np.array([[1.0, 0.0], [2.0, -1.0]]))
    X = Interval(np.array([[-np.inf], [1.0]]), np.array([[5.0], [2.0]]))
    r = IA.matmul(A, X)
    assert r.lo[0, 0] == -np.inf and 5.0 <= r.hi[0, 0] < 5.0 + 1e-12
    assert r.lo[1, 0] == -np.inf and 9.0 <= r.hi[1, 0] < 9.0 + 1e-12
    assert not np.isnan(r.lo).any() and not np.isnan(r.hi).any()


def test_broadcasting_with_constants():
    rng = np.random.default_rng(9)
    N, rr, cc = 5, 2, 3
    lo = rng.normal(size=(N, rr, cc))
    X = Interval(lo, lo + 0.5)
    C = rng.normal(size=(rr, cc))
    for op in (ca.OP_ADD, ca.OP_MUL, ca.OP_SUB, ca.OP_DIV, ca.OP_FMAX):
        r1 = IA.binary(op, X, IA.constant(C))
        r2 = IA.binary(op, IA.constant(C), X)
        assert r1.shape == r2.shape == (N, rr, cc)
        for b in range(N):
            p = X.lo[b] + 0.3
            f = {ca.OP_ADD: np.add, ca.OP_MUL: np.multiply, ca.OP_SUB: np.subtract,
                 ca.OP_DIV: np.divide, ca.OP_FMAX: np.fmax}[op]
            for r, v in ((r1, f(p, C)), (r2, f(C, p))):
                ok = (r.lo[b] <= v + 1e-12 * np.abs(v)) & (v - 1e-12 * np.abs(v) <= r.hi[b])
                assert ok.all()
    s = IA.constant(np.array(2.0))
    x = Interval(rng.normal(size=7), rng.normal(size=7) + 10)
    for op in (ca.OP_MUL, ca.OP_ADD, ca.OP_POW, ca.OP_DIV):
        assert IA.binary(op, x, s).shape == (7,)
        assert IA.binary(op, s, x).shape == (7,)
    assert IA.binary(ca.OP_MUL, x, IA.constant(np.array(0.0))).hi.max() == 0.0
    assert IA.binary(ca.OP_MUL, x, IA.constant(np.array(-2.0))).shape == (7,)


# --------------------------------------------------------------------------- API
def test_interval_api():
    x = Interval(np.array([[0.0, -1.0], [2.0, 3.0]]), np.array([[1.0, 1.0], [2.0, 4.0]]))
    assert x.shape == (2, 2) and x.ndim == 2
    np.testing.assert_array_equal(x.width, [[1.0, 2.0], [0.0, 1.0]])
    assert np.all(x.contains(x.mid))
    assert x[0].shape == (2,) and x[:, 1].hi.tolist() == [1.0, 4.0]
    assert x.contains(np.array([[0.5, 1.5], [2.0, 3.5]])).tolist() == [[True, False],
                                                                      [True, True]]
    assert Interval(0.0, [1.0, 2.0]).shape == (2,)  # broadcast bounds
    m = Interval([-np.inf, -np.inf, 5e-324, 1.0], [np.inf, 3.0, 5e-324, np.inf]).mid
    assert np.all(np.isfinite(m)) and m[2] == 5e-324 and m[1] <= 3.0 and m[3] >= 1.0
    c = IA.constant(np.array([1.0, 2.0]))
    assert c.lo is c.hi and c.lo.dtype == np.float64
    c = IA.constant(np.array([np.nan, np.inf, -np.inf]))
    assert c.lo.tolist()[0] == -np.inf and c.hi[0] == np.inf
    assert c.lo[1] == np.finfo(float).max and c.hi[2] == -np.finfo(float).max
    s = IA.structural(lambda a: a.T, x)
    np.testing.assert_array_equal(s.lo, x.lo.T)
    np.testing.assert_array_equal(s.hi, x.hi.T)
    k = IA.structural(lambda a, b: np.concatenate([a, b]), x, IA.constant(np.zeros((1, 2))))
    assert k.shape == (3, 2)
    i = IA.intersect(Interval(0.0, 2.0), Interval(1.0, 3.0))
    assert (i.lo, i.hi) == (1.0, 2.0)
    h = IA.hull(Interval(0.0, 2.0), Interval(1.0, 3.0))
    assert (h.lo, h.hi) == (0.0, 3.0)
    assert IA.name == "interval"


def test_unsupported_operation_raises_not_implemented():
    x = Interval(0.0, 1.0)
    with pytest.raises(NotImplementedError, match="OP_DETERMINANT") as err:
        IA.unary(ca.OP_DETERMINANT, x)
    assert "OP_SIN" in str(err.value) and "OP_MUL" in str(err.value)
    with pytest.raises(NotImplementedError, match="OP_SOLVE"):
        IA.binary(ca.OP_SOLVE, x, x)
    with pytest.raises(NotImplementedError, match="OP_ADD"):
        IA.unary(ca.OP_ADD, x)  # a binary operation is not a unary one


def test_walker_evaluation_encloses_point_values():
    from nlyap_opt.kernel.walker import evaluate

    x = ca.SX.sym("x", 2)
    e = ca.vertcat(ca.sin(x[0]) * x[1] + ca.exp(-x[0] ** 2), ca.tanh(x[0] - 3 * x[1]) ** 3,
                   ca.sqrt(x[0] ** 2 + x[1] ** 2) - ca.atan(x[1]) / (2 + ca.cos(x[0])))
    f = ca.Function("f", [x], [e])
    rng = np.random.default_rng(10)
    lo = rng.uniform(-2, 2, size=(50, 2))
    hi = lo + rng.uniform(0, 0.3, size=(50, 2))
    enc = evaluate(f, [Interval(lo, hi)], IA)[0]
    pts = lo + rng.uniform(0, 1, size=(20, 50, 2)) * (hi - lo)
    for p in pts:
        v = np.array(f(p.T)).T  # (50, 3)
        tol = 1e-12 * (1 + np.abs(v))
        assert np.all(enc.lo - tol <= v) and np.all(v <= enc.hi + tol)


def test_walker_mx_mtimes_zero_addend_and_cached_constants():
    """``W @ x`` (a zero addend, skipped) and ``W @ x + b`` in MX enclose point values;
    constants reused across passes give identical results."""
    from nlyap_opt.kernel.walker import NUMPY, compile_function, evaluate

    rng = np.random.default_rng(11)
    W = rng.normal(size=(5, 3))
    b = rng.normal(size=(5, 1))
    x = ca.MX.sym("x", 3)
    f = ca.Function("f", [x], [ca.tanh(ca.mtimes(W, x)), ca.mtimes(W, x) + b])
    prog = compile_function(f)
    assert ca.OP_MTIMES in prog.ops
    lo = rng.uniform(-1, 1, size=(40, 3))
    hi = lo + rng.uniform(0, 0.2, size=(40, 3))
    e1, e2 = evaluate(f, [Interval(lo, hi)], IA)
    r1, r2 = evaluate(f, [Interval(lo, hi)], IA)  # second pass: cached constants
    for a, c in ((e1, r1), (e2, r2)):
        assert np.array_equal(a.lo, c.lo) and np.array_equal(a.hi, c.hi)
    # the zero addend adds nothing: same as the rigorous matmul alone
    mm = IA.matmul(IA.constant(W), Interval(lo[:, :, None], hi[:, :, None]))
    th = IA.unary(ca.OP_TANH, mm)
    assert np.array_equal(e1.lo, th.lo[..., 0]) and np.array_equal(e1.hi, th.hi[..., 0])
    for p in lo + rng.uniform(0, 1, size=(20, 40, 3)) * (hi - lo):
        v1, v2 = evaluate(f, [p], NUMPY)
        assert np.all(e1.lo <= v1) and np.all(v1 <= e1.hi)
        assert np.all(e2.lo <= v2) and np.all(v2 <= e2.hi)
        assert np.allclose(v2, p @ W.T + b[:, 0])


def test_walker_mx_dot_of_a_register_with_itself_is_a_sum_of_squares():
    """``sumsqr(v)`` (CasADi ``dot(v, v)``) encloses ``‖v‖²`` by ``[min, max]`` of the squares,
    not the product of two independent copies; ``dot(v, w)`` keeps the product."""
    from nlyap_opt.kernel.walker import NUMPY, evaluate

    x = ca.MX.sym("x", 2)
    W = np.array([[1.0, -2.0], [0.5, 1.0]])
    y = ca.mtimes(W, x)
    f = ca.Function("f", [x], [ca.sumsqr(x), ca.sumsqr(y), ca.dot(x, y)])
    lo, hi = np.array([[-1.0, 0.5], [0.1, -0.3]]), np.array([[1.0, 2.0], [0.4, 0.2]])
    s_x, s_y, d_xy = evaluate(f, [Interval(lo, hi)], IA)
    # ‖x‖² on [-1, 1] × [0.5, 2] is [0.25, 5]; on [0.1, 0.4] × [-0.3, 0.2]: [0.01, 0.25]
    assert s_x.lo[0, 0] == pytest.approx(0.25, rel=1e-12) and s_x.hi[0, 0] >= 5.0
    assert s_x.lo[1, 0] == pytest.approx(0.01, rel=1e-12)
    assert np.all(s_y.lo >= -1e-300)  # a sum of squares (outward rounding: -2⁻¹⁰²⁰·…)
    rng = np.random.default_rng(12)
    for p in lo + rng.uniform(0, 1, size=(200, 2, 2)) * (hi - lo):
        v = [np.ravel(a) for a in evaluate(f, [p], NUMPY)]
        for enc, val in zip((s_x, s_y, d_xy), v):
            assert np.all(enc.lo[:, 0] <= val) and np.all(val <= enc.hi[:, 0])
    # the product of independent copies would reach below zero: x·Wx on the first box
    assert d_xy.lo[0, 0] < 0.0


def test_constants_folded_by_casadi_are_enclosed():
    """CasADi folds ``0.1 * 3`` into ``0.30000000000000004`` in the gradient of
    ``(x * 0.1) * 3``, and SX folds ``0.1 * (0.3 * x)`` into ``0.03 * x``; the enclosures
    must hold the real values ``3 · fl(0.1)`` and ``fl(0.1) · fl(0.3)``."""
    from nlyap_opt.kernel.walker import evaluate

    x = ca.MX.sym("x")
    xs = ca.SX.sym("x")
    cases = [(ca.Function("g", [x], [ca.gradient((x * 0.1) * 3, x)]), 3 * Fraction(0.1)),
             (ca.Function("h", [xs], [0.1 * (0.3 * xs)]), Fraction(0.1) * Fraction(0.3))]
    one = Interval(np.array([[1.0]]), np.array([[1.0]]))
    for f, real in cases:
        enc = evaluate(f, [one], IA)[0]
        lo, hi = float(np.ravel(enc.lo)[0]), float(np.ravel(enc.hi)[0])
        assert Fraction(lo) <= real <= Fraction(hi)
        assert hi - lo < 1e-14  # and stays tight
    # the folded value itself lies outside [real, real]: the widening is needed
    g = float(cases[0][0](1.0))
    assert Fraction(g) != cases[0][1]
    zero = IA.constant(np.zeros(3))
    assert zero.lo is zero.hi


# --------------------------------------------------------------------------- checked walk
def test_sums_keep_exact_zero_lower_bounds_and_round_outward():
    z = Interval([0.0, 0.0], [1.0, 2.0])
    s = IA.binary(ca.OP_ADD, IA.unary(ca.OP_SQ, z), IA.unary(ca.OP_SQ, z))
    assert np.all(s.lo == 0.0)
    # a sum that is not exact still rounds outward
    a = Interval([0.1], [0.1])
    b = Interval([0.2], [0.2])
    r = IA.binary(ca.OP_ADD, a, b)
    assert mp.mpf(0.1) + mp.mpf(0.2) >= r.lo[0] and mp.mpf(0.1) + mp.mpf(0.2) <= r.hi[0]
    assert r.lo[0] < 0.1 + 0.2 < r.hi[0] or r.lo[0] < r.hi[0]
    d = IA.binary(ca.OP_SUB, Interval([1e-310], [1e-310]), Interval([3e-310], [3e-310]))
    assert d.lo[0] <= 1e-310 - 3e-310 <= d.hi[0]  # subnormal differences are exact
    n = IA.nonneg(Interval([-1e-300, -2.0], [3.0, 4.0]))
    assert np.array_equal(n.lo, [0.0, 0.0]) and np.array_equal(n.hi, [3.0, 4.0])


def test_checked_arithmetic_flags_per_box_and_output():
    from nlyap_opt.kernel.walker import compile_function, evaluate
    from verification.interval import CheckedIntervalArithmetic

    x = ca.SX.sym("x", 2)
    f = ca.Function("f", [x], [x[0] + x[1], ca.sign(x[0]) * x[1], ca.sqrt(x[1]) + x[0]])
    assert compile_function(f).checked
    lo = np.array([[-1.0, 0.5], [0.5, -1.0], [0.0, 0.0], [-2.0, -3.0]])
    hi = np.array([[1.0, 1.0], [1.0, -0.5], [0.0, 1.0], [-1.0, -2.0]])
    ar = CheckedIntervalArithmetic(len(lo), 3)
    ar.collect(evaluate(f, [Interval(lo, hi)], ar))
    assert not ar.jump[:, 0].any() and not ar.maybe_undefined[:, :2].any()
    assert ar.jump[:, 1].tolist() == [True, False, False, False]  # sign(0) on a point: no
    assert not ar.jump[:, 2].any()
    assert ar.maybe_undefined[:, 2].tolist() == [False, True, False, True]
    assert ar.undefined[:, 2].tolist() == [False, True, False, True]
    assert (ar.undefined_op[:, 2] == np.where(ar.undefined[:, 2], ca.OP_SQRT, -1)).all()


def test_checked_arithmetic_through_mx_calls_and_constants():
    from nlyap_opt.kernel.walker import compile_function, evaluate
    from verification.interval import CheckedIntervalArithmetic

    xs = ca.SX.sym("x", 2)
    inner = ca.Function("inner", [xs], [ca.vertcat(ca.log(xs[0]), xs[1])])
    xm = ca.MX.sym("x", 2)
    W = ca.DM([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]])
    out = inner(xm)
    f = ca.Function("f", [xm], [out[1] * 2, ca.sumsqr(ca.fmax(ca.mtimes(W, xm), 0)) + out[0]])
    assert compile_function(f).checked
    lo = np.array([[0.5, -1.0], [-0.5, 1.0], [1.0, 1.0]])
    hi = np.array([[1.0, 1.0], [1.0, 2.0], [2.0, 2.0]])
    ar = CheckedIntervalArithmetic(3, 2)
    ar.collect(evaluate(f, [Interval(lo, hi)], ar))
    # the log inside the call flows into output 1 only (domain taint is per value)
    assert ar.maybe_undefined.tolist() == [[False, False], [False, True], [False, False]]
    # fmax(W x, 0) feeds output 1 only; a row of W x crosses 0 in box 0 only
    assert ar.jump[:, 0].tolist() == [False, False, False]
    assert ar.jump[:, 1].tolist() == [True, False, False]


def test_checks_inside_calls_go_to_the_outputs_the_callee_outputs_feed():
    """A kink inside a called Function is recorded for the caller's outputs that the callee's
    output it feeds flows into (through nested calls), not for every output of the call."""
    from nlyap_opt.kernel.walker import evaluate
    from verification.interval import CheckedIntervalArithmetic

    xs = ca.SX.sym("x", 2)
    inner = ca.Function("inner", [xs], [ca.fmax(xs[0], 0), xs[1]])     # kink: output 0
    xm = ca.MX.sym("x", 2)
    a, b = inner(xm)
    mid = ca.Function("mid", [xm], [b * 3, a + b, b - 1])              # kink: output 1
    ym = ca.MX.sym("y", 2)
    p, q, r = mid(ym)
    f = ca.Function("f", [ym], [r, p, q * 2, p + r])                   # kink: output 2
    lo = np.array([[-1.0, 0.0], [0.5, 0.0]])
    hi = np.array([[1.0, 1.0], [1.0, 1.0]])                           # x0 crosses 0: box 0
    for fn, col in ((inner, 0), (mid, 1), (f, 2)):
        ar = CheckedIntervalArithmetic(2, fn.n_out())
        ar.collect(evaluate(fn, [Interval(lo, hi)], ar))
        expect = np.zeros((2, fn.n_out()), bool)
        expect[0, col] = True
        assert (ar.jump == expect).all(), (fn.name(), ar.jump)


def test_statically_safe_operations_are_not_checked():
    from nlyap_opt.kernel.walker import compile_function

    x = ca.SX.sym("x", 2)
    cases = [(x[0] / 3.0, False), (x[0] ** 3, False), (ca.fmax(1.0, 2.0) * x[0], False),
             (x[0] / x[1], True), (x[0] ** 1.5, True), (x[0] ** -2, True),
             (ca.fabs(x[0]), True), (2.0 ** x[0], False), ((-2.0) ** x[0], True)]
    xm = ca.MX.sym("x", 2)
    cases += [(xm / ca.DM([2.0, 4.0]), False), (xm / ca.DM([2.0, 0.0]), True),
              (ca.DM([2.0, 3.0]) ** xm, False)]
    for e, checked in cases:
        xx = xm if isinstance(e, ca.MX) else x
        assert compile_function(ca.Function("f", [xx], [e])).checked == checked, str(e)


def test_domain_taint_flows_through_mx_layers_and_respects_if_else_guards():
    from nlyap_opt.kernel.walker import evaluate
    from verification.interval import CheckedIntervalArithmetic

    xm = ca.MX.sym("x", 2)
    W = ca.DM([[1.0, 2.0], [3.0, 4.0]])
    h = ca.tanh(ca.mtimes(W, ca.vertcat(ca.sqrt(xm[0]), xm[1])))  # row 0 of the input only
    guarded = ca.if_else(xm[1] > 0, ca.sqrt(xm[1]), 0.0)
    f = ca.Function("f", [xm], [ca.sumsqr(h), h[1] + xm[1], guarded])
    lo = np.array([[-1.0, -1.0], [0.5, -2.0], [0.5, 0.5], [-2.0, -2.0]])
    hi = np.array([[1.0, 1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, -1.0]])
    ar = CheckedIntervalArithmetic(len(lo), 3)
    ar.collect(evaluate(f, [Interval(lo, hi)], ar))
    assert ar.maybe_undefined[:, 0].tolist() == [True, False, False, True]
    assert ar.undefined[:, 0].tolist() == [False, False, False, True]
    assert ar.undefined_op[3, 0] == ca.OP_SQRT
    assert ar.maybe_undefined[:, 1].tolist() == [True, False, False, True]
    # sqrt(x1) is out of its domain in boxes 1 and 3, but the guard x1 > 0 is certainly
    # false there: if_else gives 0; box 0 straddles: not proved defined
    assert ar.maybe_undefined[:, 2].tolist() == [True, False, False, False]
    assert not ar.undefined[:, 2].any()
