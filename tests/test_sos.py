"""SOS baseline: exact polynomial data, SDP levels re-certified by the interval verifier.

The polynomial data themselves (Polynomial, the walker's polynomial arithmetic) are tested in
``test_polynomial.py``; the reference level of the quadratic V comes from ``vdp_reference.py``
(an independent computation, no toolbox code).
"""

import numpy as np
import pytest
from scipy.optimize import minimize
from vdp_reference import (
    vdp_lyapunov_matrix,
    vdp_quadratic_level,
    vdp_sampled_level,
    vdp_true_roa_area,
)

import systems
from nlyap_opt.candidates.sos import Polynomial, SOSResult, SOSStatus, sos_roa
from nlyap_opt.certification.certificate import (
    CertStatus,
    RoaProblem,
    certify_roa,
    recheck_certificate,
    save_certificate,
)
from nlyap_opt.certification.roa import grid_points

# V = xᵀPx with AᵀP + PA = -I for the linearisation of reversed Van der Pol (μ = 1), and the
# supremum c* of the levels with V̇ < 0 on {V ≤ c} \ {0}: c* = 2.30448 (vdp_reference.py)
P_VDP = vdp_lyapunov_matrix(1.0)
REFERENCE_LEVEL = vdp_quadratic_level(P_VDP, mu=1.0)
#: the area inside the limit cycle, computed independently (SciPy's DOP853 on the forward
#: system and the shoelace formula, vdp_reference.vdp_true_roa_area): 13.7222
TRUE_ROA_AREA = vdp_true_roa_area(1.0)
BOX = np.array([[-3.0, 3.0], [-3.0, 3.0]])


@pytest.fixture(scope="module")
def vdp():
    return systems.get("van_der_pol")


@pytest.fixture(scope="module")
def quadratic(vdp):
    return sos_roa(vdp, degree=2, inner=0.1)


@pytest.fixture(scope="module")
def quartic(vdp):
    return sos_roa(vdp, degree=4, inner=0.1)


def _lie(system, V: Polynomial, pts, h=1e-6):
    """∇V·f at points (central differences of V; f from the system's own evaluator)."""
    grad = np.stack([(V(pts + h * e) - V(pts - h * e)) / (2 * h) for e in np.eye(2)], axis=1)
    return np.einsum("ij,ij->i", grad, system.evaluate(pts))


def _converges(system, pts, t_final=30.0):
    traj = system.simulate(None, pts, t_final, n_steps=3000)
    return np.linalg.norm(traj[-1], axis=1) < 1e-3


# --------------------------------------------------------------------------- reference level
def test_reference_level_is_the_least_v_where_decrease_fails():
    """The ray formula of vdp_reference agrees with a constrained minimisation
    (min V s.t. V̇ = 0, multi-start SLSQP) and is approached from above by a dense grid."""
    np.testing.assert_allclose(P_VDP, [[1.5, -0.5], [-0.5, 1.0]], atol=1e-12)
    assert 2.3044 < REFERENCE_LEVEL < 2.3045

    def vdot(x):
        f = np.array([-x[1], x[0] - x[1] + x[0] ** 2 * x[1]])
        return 2.0 * x @ P_VDP @ f

    best = np.inf
    for x0 in np.random.default_rng(0).uniform(-3, 3, (20, 2)):
        r = minimize(lambda x: x @ P_VDP @ x, x0, method="SLSQP",
                     constraints=[{"type": "eq", "fun": vdot}],
                     options={"ftol": 1e-14, "maxiter": 500})
        if r.success and np.linalg.norm(r.x) > 0.1 and abs(vdot(r.x)) < 1e-9:
            best = min(best, r.fun)
    assert best == pytest.approx(REFERENCE_LEVEL, rel=1e-9)
    sampled = vdp_sampled_level(P_VDP)
    assert REFERENCE_LEVEL <= sampled <= REFERENCE_LEVEL + 2e-3


# --------------------------------------------------------------------------- not applicable
@pytest.mark.parametrize("name, ops", [
    ("inverted_pendulum", ["sin (OP_SIN)"]),
    ("unicycle_path_following", ["sin (OP_SIN)", "cos (OP_COS)", "division (OP_DIV)"]),
])
def test_non_polynomial_system_not_applicable(name, ops):
    res = sos_roa(systems.get(name))
    assert isinstance(res, SOSResult)
    assert res.text.startswith("not applicable: ")
    assert "not polynomial" in res.text and "Taylor" in res.text
    for op in ops:  # the offending operations are named
        assert op in res.text
    assert not res.applicable
    assert {f"{k} ({v})" for k, v in res.non_polynomial.items()} == set(ops)
    assert res.certificate is None and res.problem is None
    assert not res.certified and res.certified_level == 0.0 and res.V is None
    assert res.area(n=50) == 0.0


# --------------------------------------------------------------------------- quadratic V
def test_quadratic_level_certified_within_one_percent(quadratic):
    res = quadratic
    assert res.status is SOSStatus.CERTIFIED, res.text
    assert res.degree == 2
    np.testing.assert_allclose(res.V.to_dict()[(2, 0)], P_VDP[0, 0])
    np.testing.assert_allclose(res.V.to_dict()[(1, 1)], 2 * P_VDP[0, 1])
    # the SDP level cannot exceed c* (beyond the bisection and solver tolerances) ...
    assert res.sdp_level <= REFERENCE_LEVEL * (1 + 1e-3)
    # ... and the certified level is what the verifier proved: at most the SDP level, below
    # c* (no sound certificate reaches it) and within 1 % of it
    assert res.certified_level <= res.sdp_level
    assert 0.99 * REFERENCE_LEVEL <= res.certified_level < REFERENCE_LEVEL
    assert res.certificate.certified and res.certificate.setting == "known"
    assert res.certificate.level == res.certified_level
    assert res.inner_ellipse.status == "certified" and res.inner_ellipse.proved
    assert res.applicable and res.non_polynomial == {}


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
    outer = 1.1 * res.outer  # so that (b) still holds and (a) is what fails
    problem = RoaProblem(vdp, res.V, inner=res.inner, outer=outer)
    cert = certify_roa(problem, raised, search=False, log=lambda m: None)
    assert cert.status is CertStatus.COUNTEREXAMPLE and not cert.certified
    assert cert.checks["(b) V > level on ‖x‖ = r"] == "verified"
    assert cert.checks["(a) decrease"] == "counterexample"
    cex = cert.counterexamples
    assert len(cex) > 0
    # the counterexamples are genuine: inside the raised set, and V does not decrease there
    assert np.all(res.V(cex) <= raised)
    assert np.all(_lie(vdp, res.V, cex) >= -1e-9)
    # searching down from the raised level ends below c*
    lowered = certify_roa(problem, raised, search=True, log=lambda m: None)
    assert lowered.certified and lowered.level < REFERENCE_LEVEL


def test_saved_certificate_rechecks(quadratic, tmp_path):
    """The SOS certificate is the toolbox's one certificate: saved, it re-verifies."""
    res = quadratic
    path = save_certificate(res.certificate, res.problem, tmp_path)
    again = recheck_certificate(path, log=lambda m: None)
    assert again.certified, again.reason
    assert again.level == res.certified_level
    pts, _ = grid_points(BOX, 80)
    np.testing.assert_array_equal(again.contains(pts), res.mask(pts))


# --------------------------------------------------------------------------- higher degree
def test_quartic_v_certified_and_larger(vdp, quadratic, quartic):
    res = quartic
    assert res.status is SOSStatus.CERTIFIED, res.text
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
    res = sos_roa(vdp, degree=6, inner=0.1)
    assert res.status is SOSStatus.CERTIFIED, res.text
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


def test_public_names_kept_after_the_split():
    """``baselines.sos`` still exports what it exported before it was split, and the
    baselines' modules are the core's (moved below the pipeline, which runs SOS too)."""
    import baselines
    import baselines.polynomial as poly
    import baselines.sos as sos
    import baselines.sos_sdp as sdp
    import nlyap_opt.candidates.sos
    import nlyap_opt.design.polynomial
    import nlyap_opt.design.sos_sdp

    assert sos.sos_roa is nlyap_opt.candidates.sos.sos_roa and sos.SOSResult is \
        nlyap_opt.candidates.sos.SOSResult
    assert poly.Polynomial is nlyap_opt.design.polynomial.Polynomial
    assert sdp.vs_iteration is nlyap_opt.design.sos_sdp.vs_iteration

    assert sos.NotPolynomialError is poly.NotPolynomialError
    assert sos.Polynomial is poly.Polynomial
    assert sos.polynomial_closed_loop is poly.polynomial_closed_loop
    assert sos.sos_level is sdp.sos_level and sos.SOSLevel is sdp.SOSLevel
    assert baselines.sos_roa is sos.sos_roa and baselines.SOSResult is sos.SOSResult
    assert set(sos.__all__) >= {"NotPolynomialError", "Polynomial", "SOSLevel", "SOSResult",
                                "polynomial_closed_loop", "sos_level", "sos_roa"}
