"""Exact evaluation of a CasADi graph at a point (:class:`nlyap_opt.kernel.walker.
ExactPointArithmetic`): the answers "f(0) is exactly 0" that floats cannot give."""

from __future__ import annotations

from fractions import Fraction

import casadi as ca
import numpy as np
import pytest

from nlyap_opt.kernel.walker import OP_TABLE, REAL, UNDEFINED, ExactPointArithmetic, exact_values

x = ca.SX.sym("x", 2)


def _at(expr, point):
    return exact_values(ca.Function("f", [x], [expr]), point)[0]


def test_rational_operations_are_exact_and_agree_with_floats(rng):
    """Random graphs of + − × ÷, squares and integer powers at random float points: the
    exact value is the rational the float evaluation approximates."""
    for _ in range(200):
        p = rng.uniform(-2, 2, 2)
        c = rng.uniform(-3, 3, 3)
        e = (c[0] * x[0] ** 3 - x[1] / (x[0] ** 2 + c[1] ** 2 + 0.5)
             + (x[0] * x[1] - c[2]) ** 2 - x[1] ** -2 * 0.25)
        got = _at(e, p)
        assert isinstance(got, Fraction)
        ref = float(ca.Function("f", [x], [e])(p))
        assert abs(float(got) - ref) <= 1e-12 * max(1.0, abs(ref))


def test_a_float_fold_that_hides_a_constant_is_seen():
    """``((x² + 10¹⁶) + 1) − 10¹⁶`` is 1 at 0; floats (and substitution, which folds in
    floats) say 0."""
    e = ((x[0] ** 2 + 1e16) + 1) - 1e16
    assert float(ca.substitute(e, x, ca.DM.zeros(2))) == 0.0
    assert _at(e, [0, 0]) == 1


@pytest.mark.parametrize("op", sorted(OP_TABLE, key=str))
def test_every_operation_is_exact_where_it_claims(op, rng):
    """Where an operation returns a Fraction it is the real value: compared with numpy's
    float64 value at float points (tiny and special arguments included)."""
    ar = ExactPointArithmetic()
    info = OP_TABLE[op]
    pts = [0.0, 1.0, -1.0, 0.5, 2.0, -3.0] + list(rng.uniform(-2, 2, 6))
    for a in pts:
        for b in (pts if info.arity == 2 else [None]):
            qa, qb = Fraction(a), (None if b is None else Fraction(b))
            got = ar.unary(op, qa) if b is None else ar.binary(op, qa, qb)
            if not isinstance(got, Fraction):
                continue
            s = ca.SX.sym("s", 2)
            expr = ca.SX.unary(op, s[0]) if b is None else ca.SX.binary(op, s[0], s[1])
            with np.errstate(all="ignore"):
                ref = float(ca.Function("g", [s], [expr])([a, 0.0 if b is None else b]))
            assert np.isfinite(ref), (info.name, a, b)
            assert abs(float(got) - ref) <= 4e-16 * max(1.0, abs(ref)), (info.name, a, b, got)


def test_domains_and_branches():
    assert _at(ca.log(x[0]), [0, 0]) is UNDEFINED
    assert _at(1 / x[0], [0, 1]) is UNDEFINED
    # the branch not taken does not count; a taken undefined one does
    assert _at(ca.if_else(x[0] > 0, ca.log(x[0]), 0), [0, 0]) == 0
    assert _at(ca.if_else(x[0] >= 0, ca.log(x[0]), 0), [0, 0]) is UNDEFINED
    assert _at(ca.sqrt(x[0] ** 2 + 1) - 1, [0, 0]) == 0
    assert _at(ca.sqrt(x[0] + 2), [0, 0]) is REAL


def test_a_coordinate_that_stands_for_every_real():
    """``REAL``: an output exactly 0 is 0 whatever that coordinate is; anything else is not
    claimed."""
    assert _at(x[0] * ca.sin(x[1]) * ca.exp(x[1]), [0, REAL]) == 0
    assert _at(x[0] + x[1], [0, REAL]) is REAL
    assert _at(x[0] * ca.log(x[1]), [0, REAL]) is UNDEFINED   # log of a real may not exist
    assert _at(ca.tanh(x[0]) + ca.cos(x[0]) - 1, [0, REAL]) == 0


def test_huge_rationals_become_real_instead_of_hanging():
    """Thirty squarings of ``x + 3`` would need ~2³⁰-digit integers; past the size cap the
    value is REAL, so the evaluation stays fast and claims no 0 it did not compute."""
    def chain():
        e = x[0] + 3
        for _ in range(30):
            e = e * e
        return e
    e1, e2 = chain(), chain()                   # two graphs of the same value
    assert _at(e1 - e2, [0, 0]) is REAL
    assert _at(e1 * x[0], [0, 0]) == 0
    assert _at(e1 - e2, [-3, 0]) == 0            # small values stay exact
