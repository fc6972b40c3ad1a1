"""Exact polynomial data for SOS: the Polynomial class and the walker's polynomial arithmetic.

References are independent of the code under test: CasADi's own numeric evaluation
(``casadi.Function`` / ``casadi.DM.unary`` / ``casadi.DM.binary``) and the models' equations.
"""

import casadi as ca
import numpy as np
import pytest

import systems
from nlyap_opt.design.polynomial import (
    CONDITIONAL_OPS,
    POLYNOMIAL_OPS,
    NotPolynomialError,
    Polynomial,
    PolynomialArithmetic,
    expand_polynomials,
    monomial_matrix,
    monomials,
    polynomial_closed_loop,
)
from nlyap_opt.kernel import walker
from nlyap_opt.kernel.errors import UnsupportedOperationError
from nlyap_opt.kernel.walker import op_name

PTS = np.random.default_rng(7).uniform(-2.0, 2.0, (64, 2))


def _op_table():
    table = getattr(walker, "OP_TABLE", None)
    if table is None:
        pytest.skip("nlyap_opt.kernel.walker.OP_TABLE is not there yet (added by the op-table "
                    "work)")
    return table


def _values(p, pts=PTS):
    """Values of a polynomial dict (the arithmetic's value) at ``pts``."""
    return Polynomial.from_dict(p, 2)(pts)


def _casadi_values(expr_of, pts=PTS):
    """CasADi's own float64 evaluation of ``expr_of(x)`` at ``pts`` (the reference)."""
    x = ca.SX.sym("x", 2)
    fun = ca.Function("ref", [x], [expr_of(x)])
    return np.array([float(fun(p)) for p in pts])


# state-dependent arguments used for every op: a = x1 + 0.5, b = x2 - 0.25
def _a(x):
    return x[0] + 0.5


def _b(x):
    return x[1] - 0.25


@pytest.fixture
def args():
    ar = PolynomialArithmetic(2)
    x1, x2 = ar.variables()
    a = ar.binary(ca.OP_ADD, x1, ar.constant(0.5))
    b = ar.binary(ca.OP_SUB, x2, ar.constant(0.25))
    return ar, a, b


# --------------------------------------------------------------------------- Polynomial
def test_polynomial_casadi_equals_numpy():
    p = Polynomial.from_dict({(2, 0): 1.5, (1, 1): -1.0, (0, 2): 1.0, (3, 1): 0.25,
                              (0, 6): -0.125})
    x = ca.MX.sym("x", 2)
    fun = ca.Function("p", [x], [p.casadi(x)])
    pts = np.random.default_rng(1).normal(size=(50, 2))
    got = np.array([float(fun(q)) for q in pts])
    np.testing.assert_allclose(got, p(pts), rtol=1e-14, atol=1e-14)
    assert p.degree == 6


def test_quadratic_is_the_quadratic_form():
    P = np.array([[2.0, -0.3, 0.1], [-0.3, 1.0, 0.4], [0.1, 0.4, 3.0]])
    V = Polynomial.quadratic(P)
    X = np.random.default_rng(3).normal(size=(40, 3))
    np.testing.assert_allclose(V(X), np.einsum("ij,jk,ik->i", X, P, X), rtol=1e-13)
    assert V.degree == 2 and len(V.coefficients) == 6  # x_i x_j, i <= j
    np.testing.assert_allclose(V.scaled(-2.0)(X), -2.0 * V(X), rtol=1e-15)


def test_monomials_and_monomial_matrix():
    monos = monomials(3, 0, 3)
    assert len(monos) == 20 and len(set(monos)) == 20  # C(3 + 3, 3)
    assert [sum(e) for e in monos] == sorted(sum(e) for e in monos)
    X = np.random.default_rng(4).normal(size=(30, 3))
    E = np.array(monos)
    np.testing.assert_allclose(monomial_matrix(X, monos),
                               np.prod(X[:, None, :] ** E[None], axis=2), rtol=1e-13)


def test_zero_polynomial():
    z = Polynomial.from_dict({}, nx=2)
    assert z.degree == 0 and str(z) == "0"
    np.testing.assert_array_equal(z(PTS), 0.0)
    with pytest.raises(ValueError, match="nx"):
        Polynomial.from_dict({})


# --------------------------------------------------------------------------- closed loops
@pytest.mark.parametrize("mu", [1.0, 0.5, 2.0])
def test_vdp_closed_loop_coefficients_exact(mu):
    f = polynomial_closed_loop(systems.get("van_der_pol", mu=mu))
    assert f[0].to_dict() == {(0, 1): -1.0}
    assert f[1].to_dict() == {(1, 0): 1.0, (0, 1): -mu, (2, 1): mu}
    # and the polynomials reproduce the CasADi vector field
    pts = np.random.default_rng(0).uniform(-3, 3, (500, 2))
    ref = systems.get("van_der_pol", mu=mu).evaluate(pts)
    got = np.stack([p(pts) for p in f], axis=1)
    np.testing.assert_allclose(got, ref, rtol=1e-13, atol=1e-13)


# the non-polynomial operations, read off the models' equations:
# pendulum  ω' = (m g l sin θ + u - b ω) / (m l²)            -> sin (the division is by a constant)
# unicycle  d' = v sin θ,  θ' = ω - v κ cos θ / (1 - d κ)     -> sin, cos, division by 1 - dκ
@pytest.mark.parametrize("name, ops", [
    ("inverted_pendulum", {"sin": "OP_SIN"}),
    ("unicycle_path_following", {"sin": "OP_SIN", "cos": "OP_COS", "division": "OP_DIV"}),
])
def test_non_polynomial_refused_with_named_operations(name, ops):
    with pytest.raises(NotPolynomialError) as err:
        polynomial_closed_loop(systems.get(name))
    assert err.value.operations == ops
    for friendly, code in ops.items():
        assert f"{friendly} ({code})" in str(err.value)
    # one error type for "not polynomial": a ValueError and an unsupported operation
    assert isinstance(err.value, ValueError)
    assert isinstance(err.value, UnsupportedOperationError)


def test_expansion_folds_constants_and_matches_casadi():
    def expr(x):
        c = ca.sin(ca.SX(0.3)) + ca.exp(ca.SX(0.1))  # constant: folded in float64
        return ((_a(x) * c - _b(x) / 4) ** 3 + ca.constpow(x[1], 2) * 2 - (-x[0])) / 3

    x = ca.SX.sym("x", 2)
    (p,) = expand_polynomials(ca.Function("f", [x], [expr(x)]))
    assert p.degree == 3
    np.testing.assert_allclose(p(PTS), _casadi_values(expr), rtol=1e-12, atol=1e-12)


def test_expansion_names_every_offending_operation():
    x = ca.SX.sym("x", 2)
    e = ca.vertcat(ca.tanh(x[0]) * x[1], x[0] / (1 + x[1] ** 2), ca.fmax(x[0], 0) + x[1])
    with pytest.raises(NotPolynomialError) as err:
        expand_polynomials(ca.Function("f", [x], [e]))
    assert set(err.value.operations.values()) == {"OP_TANH", "OP_DIV", "OP_FMAX"}


# --------------------------------------------------------------------------- op table
def test_polynomial_ops_are_walker_ops():
    """The arithmetic claims only operations of the walker's table, with the right arity."""
    table = _op_table()
    for op in POLYNOMIAL_OPS | set(CONDITIONAL_OPS):
        assert op in table, f"{op_name(op)} is not in walker.OP_TABLE"
    for op in (ca.OP_NEG, ca.OP_SQ, ca.OP_TWICE, ca.OP_ASSIGN):
        assert table[op].arity == 1, op_name(op)
    for op in (ca.OP_ADD, ca.OP_SUB, ca.OP_MUL, *CONDITIONAL_OPS):
        assert table[op].arity == 2, op_name(op)
    for op in POLYNOMIAL_OPS:  # polynomials are smooth and defined everywhere
        assert table[op].kind == "smooth" and table[op].domain is None, op_name(op)


def test_polynomial_arithmetic_covers_op_table(args):
    """Every elementwise op of the walker's table: exact if polynomial, else refused by name."""
    table = _op_table()
    ar, a, b = args
    checked = refused = 0
    for op, info in sorted(table.items()):
        if info.arity == 1:
            call, ref = (lambda: ar.unary(op, a)), (lambda x: ca.SX.unary(op, _a(x)))
        elif info.arity == 2:
            call, ref = (lambda: ar.binary(op, a, b)), (lambda x: ca.SX.binary(op, _a(x), _b(x)))
        else:
            continue  # not elementwise: never handed to an arithmetic's unary/binary
        if op in POLYNOMIAL_OPS:
            np.testing.assert_allclose(_values(call()), _casadi_values(ref), rtol=1e-12,
                                       atol=1e-12, err_msg=op_name(op))
            checked += 1
        else:
            with pytest.raises(UnsupportedOperationError, match=op_name(op)):
                call()
            refused += 1
    assert checked == len(POLYNOMIAL_OPS)
    assert refused >= 20  # sin, cos, exp, fabs, fmin, comparisons, ...


@pytest.mark.parametrize("op, const, expr", [
    (ca.OP_DIV, 4.0, lambda x, c: _a(x) / c),
    (ca.OP_POW, 3.0, lambda x, c: _a(x) ** c),
    (ca.OP_CONSTPOW, 3.0, lambda x, c: ca.constpow(_a(x), c)),
    (ca.OP_POW, 0.0, lambda x, c: _a(x) ** c),
])
def test_conditional_ops_with_a_constant_are_exact(args, op, const, expr):
    ar, a, _ = args
    p = ar.binary(op, a, ar.constant(const))
    np.testing.assert_allclose(_values(p), _casadi_values(lambda x: expr(x, const)),
                               rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("op, const", [
    (ca.OP_DIV, 0.0),          # division by zero
    (ca.OP_POW, 2.5),          # non-integer exponent
    (ca.OP_CONSTPOW, -1.0),    # negative exponent
    (ca.OP_POW, 65.0),         # beyond the expansion limit
])
def test_conditional_ops_refused_otherwise(args, op, const):
    ar, a, _ = args
    with pytest.raises(NotPolynomialError, match=op_name(op)):
        ar.binary(op, a, ar.constant(const))


def test_if_else_zero_with_a_constant_condition(args):
    ar, a, b = args
    assert ar.binary(ca.OP_IF_ELSE_ZERO, ar.constant(1.0), a) == a
    assert ar.binary(ca.OP_IF_ELSE_ZERO, ar.constant(0.0), a) == {}
    with pytest.raises(NotPolynomialError, match="OP_IF_ELSE_ZERO"):
        ar.binary(ca.OP_IF_ELSE_ZERO, b, a)


@pytest.mark.filterwarnings("ignore:invalid value:RuntimeWarning")  # acosh(0.3), atanh...
def test_constants_fold_like_casadi():
    """Every elementwise op on constants gives CasADi's own float64 value (or is refused)."""
    table = _op_table()
    ar = PolynomialArithmetic(2)
    c1, c2 = 0.3, 0.7
    for op, info in sorted(table.items()):
        if info.arity not in (1, 2):
            continue
        ref = float(ca.DM.unary(op, c1) if info.arity == 1 else ca.DM.binary(op, c1, c2))
        try:
            got = (ar.unary(op, ar.constant(c1)) if info.arity == 1
                   else ar.binary(op, ar.constant(c1), ar.constant(c2)))
        except UnsupportedOperationError as err:
            assert op_name(op) in str(err)
            continue
        value = got.get((0, 0), 0.0)
        assert set(got) <= {(0, 0)}, op_name(op)
        if np.isnan(ref):
            assert np.isnan(value), op_name(op)
        else:
            assert value == pytest.approx(ref, rel=1e-14, abs=0.0), op_name(op)


def test_collect_mode_propagates_and_records(args):
    ar = PolynomialArithmetic(2, collect=True)
    x1, x2 = ar.variables()
    s = ar.unary(ca.OP_SIN, x1)
    assert s is None
    assert ar.binary(ca.OP_MUL, s, x2) is None  # polynomial op on a non-polynomial value
    assert ar.unary(ca.OP_EXP, s) is None
    assert ar.refused == {"sin": "OP_SIN", "exp": "OP_EXP"}
