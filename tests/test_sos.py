"""SOS baseline: exact polynomial data, SDP levels re-certified by the interval verifier."""

import casadi as ca
import numpy as np
import pytest

import systems
from baselines.sos import (
    NotPolynomialError,
    Polynomial,
    SOSResult,
    polynomial_closed_loop,
    sos_roa,
)
from nlyap_opt.roa import certify_level, grid_points
from nlyap_opt.symbolic import closed_loop

REFERENCE_LEVEL = 2.3045  # largest level of xᵀPx inside the decrease region of reversed VdP
P_VDP = np.array([[1.5, -0.5], [-0.5, 1.0]])
TRUE_ROA_AREA = 13.72
BOX = np.array([[-3.0, 3.0], [-3.0, 3.0]])


@pytest.fixture(scope="module")
def vdp():
    return systems.get("van_der_pol")


@pytest.fixture(scope="module")
def quadratic(vdp):
    return sos_roa(vdp, degree=2, inner=0.1)


@pytest.fixture(scope="module")
def quartic(vdp):
    return sos_roa(vdp, degree=4, inner=0.1, time_budget=60.0)


def _lie(system, V: Polynomial, pts, h=1e-6):
    """∇V·f at points (central differences of V; f from the system's own evaluator)."""
    grad = np.stack([(V(pts + h * e) - V(pts - h * e)) / (2 * h) for e in np.eye(2)], axis=1)
    return np.einsum("ij,ij->i", grad, system.evaluate(pts))


def _converges(system, pts, t_final=30.0):
    traj = system.simulate(None, pts, t_final, n_steps=3000)
    return np.linalg.norm(traj[-1], axis=1) < 1e-3


# --------------------------------------------------------------------------- polynomial data
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


def test_polynomial_casadi_equals_numpy():
    p = Polynomial.from_dict({(2, 0): 1.5, (1, 1): -1.0, (0, 2): 1.0, (3, 1): 0.25,
                              (0, 6): -0.125})
    x = ca.MX.sym("x", 2)
    fun = ca.Function("p", [x], [p.casadi(x)])
    pts = np.random.default_rng(1).normal(size=(50, 2))
    got = np.array([float(fun(q)) for q in pts])
    np.testing.assert_allclose(got, p(pts), rtol=1e-14, atol=1e-14)
    assert p.degree == 6


@pytest.mark.parametrize("name, ops", [
    ("inverted_pendulum", ["sin"]),
    ("unicycle_path_following", ["sin", "cos", "division"]),
])
def test_non_polynomial_refused_with_named_operations(name, ops):
    with pytest.raises(NotPolynomialError) as err:
        polynomial_closed_loop(systems.get(name))
    for op in ops:
        assert op in str(err.value)


@pytest.mark.parametrize("name", ["inverted_pendulum", "unicycle_path_following"])
def test_non_polynomial_system_not_applicable(name):
    res = sos_roa(systems.get(name))
    assert isinstance(res, SOSResult)
    assert res.status.startswith("not applicable: ")
    assert "not polynomial" in res.status and "Taylor" in res.status
    assert not res.certified and res.certified_level == 0.0 and res.V is None
    assert res.area(n=50) == 0.0


# --------------------------------------------------------------------------- quadratic V
def test_quadratic_level_certified_within_one_percent(quadratic):
    res = quadratic
    assert res.status == "certified", res.status
    assert res.degree == 2
    np.testing.assert_allclose(res.V.to_dict()[(2, 0)], P_VDP[0, 0])
    np.testing.assert_allclose(res.V.to_dict()[(1, 1)], 2 * P_VDP[0, 1])
    # the SDP level cannot exceed the true largest level (beyond bisection tolerance) ...
    assert res.sdp_level <= REFERENCE_LEVEL * (1 + 1e-3)
    # ... and the certified level is what the verifier proved, at most the SDP level
    assert 0.99 * REFERENCE_LEVEL <= res.certified_level <= min(res.sdp_level, REFERENCE_LEVEL)
    assert res.certificate.status == "certified"
    assert res.certificate.level == res.certified_level
    assert res.inner_ellipse["status"] == "certified"


def test_quadratic_certificate_holds_on_samples(vdp, quadratic):
    """V̇ < 0 on sampled points of the certified annulus; V > level on the outer sphere."""
    res = quadratic
    rng = np.random.default_rng(2)
    pts = rng.uniform(-res.outer, res.outer, (20000, 2))
    r = np.linalg.norm(pts, axis=1)
    inside = (r >= res.inner) & (r <= res.outer) & (res.V(pts) <= res.certified_level)
    assert inside.sum() > 1000
    assert np.all(_lie(vdp, res.V, pts[inside]) < 0)
    th = np.linspace(0, 2 * np.pi, 720)
    sphere = res.outer * np.stack([np.cos(th), np.sin(th)], axis=1)
    assert np.all(res.V(sphere) > res.certified_level)


def test_quadratic_certified_points_converge(vdp, quadratic):
    pts, _ = grid_points(BOX, 60)
    m = quadratic.mask(pts)
    assert m.sum() > 100
    assert np.all(_converges(vdp, pts[m]))


def test_raised_level_is_refused_by_the_verifier(vdp, quadratic):
    """A corrupted result (level 10 % above the certified one) is not certified as is."""
    res = quadratic
    raised = 1.1 * res.certified_level
    cl = closed_loop(vdp)
    V = res.casadi(cl.x)
    lie = ca.dot(ca.gradient(V, cl.x), cl.rhs)
    outer = 1.1 * res.outer  # so that (b) still holds and (a) is what fails
    cert = certify_level(cl.x, V, lie, level=raised, inner=res.inner, outer=outer,
                         margin=0.0, log=lambda m: None)
    assert cert.history[0]["containment"] == "verified"
    assert cert.history[0]["decrease"] == "counterexample"
    cex = cert.counterexamples
    assert len(cex) > 0
    # the counterexamples are genuine: inside the raised set, and V does not decrease there
    assert np.all(res.V(cex) <= raised)
    assert np.all(_lie(vdp, res.V, cex) >= -1e-9)
    # the level it ends at is no larger than the true largest level
    assert cert.level <= REFERENCE_LEVEL


# --------------------------------------------------------------------------- higher degree
def test_quartic_v_certified_and_larger(vdp, quadratic, quartic):
    res = quartic
    assert res.status == "certified", res.status
    assert res.degree == 4
    assert 0 < res.certified_level <= res.sdp_level
    pts, shape = grid_points(BOX, 200)
    m4, m2 = res.mask(pts), quadratic.mask(pts)
    assert np.all(m4[m2]), "the quartic set must contain the quadratic one"
    a4, a2 = res.area(BOX, 200), quadratic.area(BOX, 200)
    assert a4 > 1.5 * a2
    assert a4 < TRUE_ROA_AREA
    sample = pts[m4][:: max(1, m4.sum() // 400)]
    assert np.all(_converges(vdp, sample))
    # the V–s iteration left a history with growing areas
    assert res.history[0]["degree"] == 2 and res.history[-1]["degree"] == 4


@pytest.mark.slow
def test_sextic_v_close_to_true_roa(vdp):
    res = sos_roa(vdp, degree=6, inner=0.1, time_budget=60.0)
    assert res.status == "certified", res.status
    area = res.area(BOX, 300)
    assert 0.9 * TRUE_ROA_AREA < area < TRUE_ROA_AREA
    pts, _ = grid_points(BOX, 100)
    m = res.mask(pts)
    assert np.all(_converges(vdp, pts[m]))


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("kwargs, exc, msg", [
    ({"degree": 3}, ValueError, "even integer"),
    ({"degree": 0}, ValueError, "even integer"),
    ({"inner": 0.0}, ValueError, "inner must be > 0"),
    ({"V0": [[1.0, 0.0], [0.0, -1.0]]}, ValueError, "positive definite"),
    ({"levle": 1.0}, TypeError, "levle"),
])
def test_bad_input(vdp, kwargs, exc, msg):
    with pytest.raises(exc, match=msg):
        sos_roa(vdp, **kwargs)
