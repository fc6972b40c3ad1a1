"""The rounding model (nlyap_opt.kernel.rounding): every helper against exact arithmetic.

Each helper's guarantee (see the module docstring) is checked with mpmath at a precision
where the reference is exact (sums, products: 2200 bits cover every pair of doubles) or
far below the tolerance (quotients, square roots, elementary functions), on random
doubles spread over the whole exponent range and on adversarial ones: signed zeros,
subnormals, the smallest normal, the largest finite, infinities, powers of two and their
neighbours.
"""

from __future__ import annotations

import math
from fractions import Fraction

import mpmath as mp
import numpy as np
import pytest

from nlyap_opt.kernel import rounding as R

# overflow to +-inf is the safe side of an upper/lower bound, and the helpers allow it
pytestmark = pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")

MAX = R.FLOAT_MAX
TINY_NORMAL = 2.0**-1022
ADVERSARIAL = [0.0, -0.0, R.ETA, -R.ETA, 3 * R.ETA, 2.0**-1060, 2.0**-1023, TINY_NORMAL,
               -TINY_NORMAL, float(np.nextafter(TINY_NORMAL, 0)), 1.0, -1.0,
               float(np.nextafter(1.0, 2)), float(np.nextafter(1.0, 0)), 0.1, -0.3, 2.0**-30,
               1e300, -1e300, 2.0**1000, MAX, -MAX, float(np.nextafter(MAX, 0)), math.pi,
               np.inf, -np.inf]


def _random_doubles(rng, n: int) -> np.ndarray:
    """Doubles of random sign, mantissa and exponent (subnormal to near the largest)."""
    mant = rng.random(n) + 0.5
    expo = rng.integers(-1080, 1024, n)
    x = np.ldexp(mant, expo)
    return np.where(rng.random(n) < 0.5, -x, x)


def _values(n: int = 300, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.concatenate([np.array(ADVERSARIAL), _random_doubles(rng, n),
                           rng.standard_normal(n)])


def _pairs(n: int = 300, seed: int = 1):
    rng = np.random.default_rng(seed)
    a = _values(n, seed)
    b = _values(n, seed + 7)[: len(a)]
    # near-cancelling pairs and subnormal products
    c = _random_doubles(rng, n)
    d = np.concatenate([-np.nextafter(c[: n // 2], np.inf), 2.0**-1000 / np.abs(c[n // 2:])])
    return np.concatenate([a, c]), np.concatenate([b, d])


def _mpf(x) -> mp.mpf:
    return mp.mpf(float(x))


def _exact(op: str, a: float, b: float):
    """The real result of ``a op b`` (None where it is undefined or not finite)."""
    if not (math.isfinite(a) and math.isfinite(b)):
        return None
    A, B = _mpf(a), _mpf(b)
    if op == "+":
        return A + B
    if op == "-":
        return A - B
    if op == "*":
        return A * B
    if op == "/":
        return None if b == 0 else A / B
    if op == "sqrt":
        return None if a < 0 else mp.sqrt(A)
    raise AssertionError(op)


def _float_op(op: str, a, b):
    with np.errstate(all="ignore"):
        return {"+": np.add, "-": np.subtract, "*": np.multiply, "/": np.divide,
                "sqrt": lambda x, _: np.sqrt(x)}[op](a, b)


def _check(lower, exact, upper, what):
    """``lower <= exact <= upper`` exactly (infinite bounds compare as such)."""
    lo, hi = float(lower), float(upper)
    assert not (math.isnan(lo) or math.isnan(hi)), what
    assert lo == -np.inf or _mpf(lo) <= exact, f"lower bound above the exact value: {what}"
    assert hi == np.inf or exact <= _mpf(hi), f"upper bound below the exact value: {what}"


@pytest.mark.parametrize("op", ["+", "-", "*", "/", "sqrt"])
def test_up_dn_and_next_enclose_one_correctly_rounded_operation(op):
    """``dn(y) <= exact <= up(y)`` and ``next_down(y) <= exact <= next_up(y)`` for
    ``y = fl(a op b)``, vectorised and scalar alike."""
    a, b = _pairs()
    y = _float_op(op, a, b)
    lo_v, hi_v = R.dn(y.copy()), R.up(y.copy())
    checked = 0
    with mp.workprec(2200):
        for i in range(len(a)):
            ex = _exact(op, float(a[i]), float(b[i]))
            if ex is None:
                continue
            yi = float(y[i])
            what = f"{a[i]!r} {op} {b[i]!r} = {yi!r}"
            _check(lo_v[i], ex, hi_v[i], what)
            _check(R.dn(yi), ex, R.up(yi), what)
            if math.isfinite(yi):
                _check(R.next_down(yi), ex, R.next_up(yi), what)
            checked += 1
    assert checked > 400


def test_up_dn_never_flip_to_the_wrong_infinity():
    """An overflowed bound is clipped on the safe side: ``dn(+inf) = float_max`` (the exact
    value that overflowed is at least that), ``up(-inf) = -float_max``."""
    assert R.dn(np.inf) == MAX and R.up(-np.inf) == -MAX
    assert R.up(np.inf) == np.inf and R.dn(-np.inf) == -np.inf
    y = np.array([MAX, -MAX]) * np.array([2.0, 2.0])    # both overflow
    assert np.array_equal(R.dn(y.copy()), [MAX, -np.inf])
    assert np.array_equal(R.up(y.copy()), [np.inf, -MAX])


@pytest.mark.parametrize("op", ["+", "-"])
def test_sum_bounds_enclose_and_keep_zero_exact(op):
    """``dn_sum(y) <= exact <= up_sum(y)`` for the rounded sum/difference of two doubles,
    and a zero sum stays the point ``[0, 0]``."""
    a, b = _pairs(seed=3)
    y = _float_op(op, a, b)
    lo_v, hi_v = R.dn_sum(y.copy()), R.up_sum(y.copy())
    with mp.workprec(2200):
        for i in range(len(a)):
            ex = _exact(op, float(a[i]), float(b[i]))
            if ex is not None:
                what = f"{a[i]!r} {op} {b[i]!r}"
                _check(lo_v[i], ex, hi_v[i], what)
                _check(R.dn_sum(float(y[i])), ex, R.up_sum(float(y[i])), what)
    assert R.dn_sum(0.0 + 0.0) == 0.0 == R.up_sum(0.0 + 0.0)
    # the subnormal sum is exact, and the rule leaves it so
    s = 3 * R.ETA + 2 * R.ETA
    assert R.dn_sum(s) == s == R.up_sum(s)


_FUNCTIONS = {
    "exp": (np.exp, mp.exp, (-745.0, 709.0)),
    "log": (np.log, mp.log, (1e-300, 1e300)),
    "tanh": (np.tanh, mp.tanh, (-30.0, 30.0)),
    "sin": (np.sin, mp.sin, (-1e4, 1e4)),
    "arctan": (np.arctan, mp.atan, (-1e6, 1e6)),
}


@pytest.mark.parametrize("name", sorted(_FUNCTIONS))
def test_function_bounds_enclose_numpy_elementary_functions(name):
    """``dn_fn(f(x)) <= f_exact(x) <= up_fn(f(x))`` for numpy's libm (16-ulp budget)."""
    f, g, (lo, hi) = _FUNCTIONS[name]
    rng = np.random.default_rng(4)
    if name == "log":
        x = np.exp(rng.uniform(np.log(lo), np.log(hi), 400))
        x = np.concatenate([x, [R.ETA, TINY_NORMAL, 1.0, float(np.nextafter(1.0, 2)), MAX]])
    else:
        x = np.concatenate([rng.uniform(lo, hi, 400), rng.standard_normal(100) * 1e-3,
                            [0.0, R.ETA, -R.ETA, 1e-310, lo, hi]])
    y = f(x)
    lo_v, hi_v = R.dn_fn(y.copy()), R.up_fn(y.copy())
    with mp.workprec(200):
        for i in range(len(x)):
            ex = g(_mpf(x[i]))
            _check(lo_v[i], ex, hi_v[i], f"{name}({x[i]!r})")


def test_next_up_down_step_exactly_one_float():
    """``next_up(x)`` is the smallest double above ``x`` (scalar: a float; array: an array)."""
    for x in _values(200, seed=5):
        if not math.isfinite(x) or abs(x) == MAX:
            continue
        u, d = R.next_up(x), R.next_down(x)
        assert type(u) is float and u > x and d < x
        with mp.workprec(2200):
            mid_up = (_mpf(x) + _mpf(u)) / 2   # no double strictly between x and u
            assert float(mid_up) in (x, u) or mp.mpf(float(mid_up)) == mid_up
        assert R.next_up(x, 2) == R.next_up(u)
    arr = R.next_up(np.array([0.0, 1.0]))
    assert isinstance(arr, np.ndarray) and arr[0] == R.ETA
    assert R.next_up(MAX) == np.inf and R.next_down(-MAX) == -np.inf


@pytest.mark.parametrize("k", [1, 4, 8, 100])
def test_relative_budgets(k):
    """``up_rel(v, k) >= (1 + k u) v`` for ``v >= 0`` and ``dn_rel(v, k) <= v - k u |v|``."""
    vals = _values(300, seed=6)
    vals = vals[np.isfinite(vals)]
    with mp.workprec(2200):
        f = 1 + k * mp.mpf(2) ** -53
        for v in vals:
            V = _mpf(v)
            lo = R.dn_rel(v, k)
            assert lo == -np.inf or _mpf(lo) <= V - k * mp.mpf(2) ** -53 * abs(V), v
            if v >= 0:
                hi = R.up_rel(v, k)
                assert type(hi) is float
                assert hi == np.inf or f * V <= _mpf(hi), v
    arr = R.up_rel(np.array([1.0, 2.0]), k)
    assert isinstance(arr, np.ndarray) and np.all(arr > [1.0, 2.0])


@pytest.mark.parametrize("m", [1, 2, 5, 40, 10**6])
def test_up_roundings_covers_m_roundings(m):
    """``up_roundings(x, m)`` bounds every real ``w`` whose float ``x >= 0`` came from ``m``
    roundings: ``w <= x / (1 - u)**m`` in the normal range, plus underflow below it."""
    vals = np.abs(_values(300, seed=8))
    vals = vals[np.isfinite(vals)]
    with mp.workprec(2200):
        grow = 1 / (1 - mp.mpf(2) ** -53) ** m
        for x in vals:
            w = _mpf(x) * grow + m * mp.mpf(2) ** -1075    # relative and absolute parts
            b = R.up_roundings(x, m)
            assert b == np.inf or w <= _mpf(b), (x, m)


def test_add_up_mul_up_bound_exact_sum_and_product():
    """Chains rounded up one ulp per operation bound the exact sum and product."""
    rng = np.random.default_rng(9)
    vals = _values(100, seed=9)
    vals = vals[np.isfinite(vals)]
    with mp.workprec(2200):
        for _ in range(300):
            terms = rng.choice(vals, size=rng.integers(1, 6))
            s = R.add_up(*terms)
            assert s == np.inf or mp.fsum([_mpf(t) for t in terms]) <= _mpf(s), terms
            a, b = rng.choice(vals, 2)
            p = R.mul_up(a, b)
            assert p == np.inf or _mpf(a) * _mpf(b) <= _mpf(p), (a, b)


@pytest.mark.parametrize("k", [1, 2, 3, 7, 10, 1000, 12345, 2**20 + 1, 10**9, 10**13])
def test_gamma_is_an_upper_bound_and_gamma_rn_is_nearest(k):
    """``gamma(k) >= k u / (1 - k u)`` exactly; ``gamma_rn(k)`` is within half an ulp."""
    exact = Fraction(k, 2**53 - k)           # k u / (1 - k u) with u = 2**-53
    assert Fraction(R.gamma(k)) >= exact
    assert Fraction(R.gamma(k)) <= exact * (1 + Fraction(1, 10**9))   # and not loose
    g = R.gamma_rn(k)
    half_ulp = Fraction(math.ulp(g)) / 2
    assert abs(Fraction(g) - exact) <= half_ulp


def test_gamma_refuses_sizes_outside_the_analysis():
    with pytest.raises(ValueError, match="split the computation"):
        R.gamma(2**53 // 50)
    with pytest.raises(ValueError, match="split the computation"):
        R.gamma_rn(2**53 // 50)


def test_constants():
    """u, eps, eta and the largest double are what IEEE binary64 says."""
    assert R.U == np.finfo(np.float64).eps / 2 and R.EPS == np.finfo(np.float64).eps
    assert R.ETA == float(np.nextafter(0.0, 1.0)) and R.ETA / 2 == 0.0
    assert R.FLOAT_MAX == np.finfo(np.float64).max and R.FLOAT_MAX * (1 + R.EPS) == np.inf
