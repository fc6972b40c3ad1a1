"""Condition (a) of a quadratic ``V = xᵀPx`` decided on the sublevel set's box by Taylor's
formula (:class:`nlyap_opt.certification.roa.TaylorDecrease`): proofs only where the
decrease holds, refusals where the test does not apply, and the level search using it."""

from fractions import Fraction

import casadi as ca
import numpy as np
import pytest
from scipy.linalg import solve_continuous_lyapunov

from nlyap_opt.certification.roa import TaylorDecrease, certify_level, quadratic_form
from nlyap_opt.design.control import quadratic_lyapunov
from nlyap_opt.kernel.domain import Box
from nlyap_opt.kernel.exact import inverse_diagonal


def _lie(V, x, g):
    return ca.jacobian(V, x) @ g


def _setup(P, g_of_x, n):
    x = ca.SX.sym("x", n)
    V_net = quadratic_lyapunov(P)
    V = V_net.casadi(x)
    return x, V, _lie(V, x, g_of_x(x)), quadratic_form(V_net)


def _sampled_max(x, V, lie, level, box, rng, m=200000):
    """Largest sampled ``dV/dt`` on ``{V ≤ level} ∩ box`` minus a tiny ball."""
    n = box.shape[0]
    pts = box[:, 0] + (box[:, 1] - box[:, 0]) * rng.random((m, n))
    f = ca.Function("f", [x], [V, lie])
    v, d = (np.asarray(a).ravel() for a in f(pts.T))
    keep = (v <= level) & (np.linalg.norm(pts, axis=1) > 1e-3)
    return float(np.max(d[keep]))


def _stiff_chain(n):
    """x0' = x1, ..., x_{n-1}' = -Σ a_k x_k: a stiff linear chain (poles -1, -2, ... scaled)."""
    poles = -np.geomspace(0.5, 60.0, n)
    coef = np.poly(poles)[1:][::-1]              # characteristic polynomial, low order first
    A = np.diag(np.ones(n - 1), 1)
    A[-1, :] = -coef
    return A


@pytest.mark.parametrize("n", [2, 4, 6])
def test_a_linear_loop_is_proved_at_every_level_and_sampling_agrees(n):
    """A linear closed loop has a constant Hessian: the test is exact, so it proves the
    decrease at any level (also past ``D``'s box), and sampling finds no violation."""
    A = _stiff_chain(n)
    P = solve_continuous_lyapunov(A.T, -np.eye(n))
    x, V, lie, Pq = _setup(P, lambda z: ca.DM(A) @ z, n)
    t = TaylorDecrease(x, lie, Pq)
    assert t.why == ""
    box = np.array([[-1.0, 1.0]] * n)
    rng = np.random.default_rng(n)
    for level in (1e-4, 0.3, 50.0):
        res = t.check(level, box)
        assert res is not None and res.status == "verified" and res.backend == "taylor"
        Y = t.box(level, box)
        assert _sampled_max(x, V, lie, level, Y, rng, 50000) < 0


def test_an_unstable_loop_is_never_proved():
    """One unstable mode: ``A_clᵀP + PA_cl`` is indefinite for the stable block's ``P``, and
    the test proves nothing at any level (sampling finds the increase)."""
    A = np.array([[0.2, 1.0], [0.0, -1.0]])
    P = np.array([[1.0, 0.0], [0.0, 1.0]])
    x, V, lie, Pq = _setup(P, lambda z: ca.DM(A) @ z, 2)
    t = TaylorDecrease(x, lie, Pq)
    box = np.array([[-1.0, 1.0]] * 2)
    for level in (1e-3, 0.5):
        assert t.check(level, box) is None
        assert _sampled_max(x, V, lie, level, t.box(level, box), np.random.default_rng(0)) > 0


def test_a_nonlinear_loop_is_proved_inside_and_not_at_the_roa_boundary():
    """``x' = -x + x³`` (ROA |x| < 1), ``V = x²``: ``dV/dt = -2x²(1 - x²)``. Taylor's
    remainder with the 16 slices proves the decrease for ``|x| ≤ 0.5`` (``M ≤ -2 + 2x²``);
    at ``|x| ≤ 1`` the decrease vanishes at ±1 and nothing may be proved, past it the
    decrease fails."""
    x, V, lie, Pq = _setup(np.array([[1.0]]), lambda z: -z + z ** 3, 1)
    t = TaylorDecrease(x, lie, Pq)
    box = np.array([[-3.0, 3.0]])
    assert t.check(0.25, box).status == "verified"
    assert t.check(0.8, box).status == "verified"      # M ≤ -2 + 2·0.8 + slicing slack
    assert t.check(1.0, box) is None
    assert t.check(1.21, box) is None
    # the box of D cuts the ellipse's: |x| ≤ 0.6 within D = [-0.6, 3]
    assert np.allclose(t.box(4.0, np.array([[-0.6, 3.0]])), [[-0.6, 2.0]])
    assert t.check(4.0, np.array([[-0.6, 0.6]])).status == "verified"


def test_the_box_holds_the_ellipsoid():
    rng = np.random.default_rng(3)
    U = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    P = U @ np.diag([1.0, 10.0, 300.0]) @ U.T
    x, V, lie, Pq = _setup(P, lambda z: -z, 3)
    t = TaylorDecrease(x, lie, Pq)
    Y = t.box(0.7, np.array([[-10.0, 10.0]] * 3))
    # extreme points of the ellipsoid xᵀPx = c along each axis: ±√(c (P⁻¹)_kk), held
    # exactly (rationals) and with at most a few ulps to spare
    d = inverse_diagonal(Pq)
    assert all(Fraction(hk) ** 2 >= Fraction(0.7) * dk for hk, dk in zip(Y[:, 1], d))
    h = np.sqrt(0.7 * np.array([float(v) for v in d]))
    assert np.all(Y[:, 1] <= h * (1 + 1e-12))
    assert np.array_equal(Y[:, 0], -Y[:, 1])


@pytest.mark.parametrize("case, why", [
    ("offset", "not structurally 0"),
    ("abs", "non-smooth"),
    ("slope", "not structurally 0"),
    ("sqrt", "non-smooth or partial"),
    ("division", "non-smooth or partial"),
])
def test_the_test_refuses_what_taylors_formula_does_not_cover(case, why):
    x = ca.SX.sym("x", 2)
    V_net = quadratic_lyapunov(np.eye(2))
    V = V_net.casadi(x)
    base = _lie(V, x, -x)
    lie = {"offset": base + 1e-3,                      # F(0) ≠ 0
           "abs": base + 0.1 * ca.fabs(x[0]) * x[0] ** 2,   # not C²
           "slope": base + 1e-3 * x[1],                # ∇F(0) ≠ 0
           "sqrt": base + 0.01 * ca.norm_2(x),         # a robust-margin-like term
           "division": base * x[0] ** 2 / (x[0] ** 2 + x[1] ** 2)}[case]   # 0/0 at 0
    t = TaylorDecrease(x, lie, quadratic_form(V_net))
    assert why in t.why
    assert t.check(0.5, np.array([[-1.0, 1.0]] * 2)) is None


def test_the_level_search_uses_it_and_agrees_with_the_verifier():
    """A 4-D stiff linear loop on the box [-1, 1]⁴: the level search proves the decrease by
    Taylor at the containment level; without the exact matrix (no ``quadratic``) the
    interval verifier must bisect and the certified level is not larger."""
    A = _stiff_chain(4)
    P = solve_continuous_lyapunov(A.T, -np.eye(4))
    P = P / np.max(np.linalg.eigvalsh(P))
    x, V, lie, Pq = _setup(P, lambda z: ca.DM(A) @ z, 4)
    D = Box([[-1.0, 1.0]] * 4)
    kw = dict(level=10.0, inner=0.01, margin=0.0, max_tries=4, log=lambda m: None, domain=D)
    res = certify_level(x, V, lie, quadratic=Pq, **kw)
    assert res.status == "certified"
    assert res.history[-1]["decrease_backend"] == "taylor"
    # the certified level is the largest the box allows: min over faces of 1/(P⁻¹)_kk
    c_max = 1.0 / np.max(np.diag(np.linalg.inv(np.array(Pq, dtype=float))))
    assert 0.98 * c_max < res.level < c_max
    # a margin (learned dynamics) leaves the decision to the verifier
    with_margin = certify_level(x, V, lie, quadratic=Pq, **{**kw, "margin": 1e-9,
                                                             "max_tries": 1})
    assert all(h.get("decrease_backend") != "taylor" for h in with_margin.history)
