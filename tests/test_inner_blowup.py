"""Condition (c) without exponential stability: the weighted blow-up of the origin.

``nlyap_opt.certification.roa.certify_inner_blowup`` proves ``V̇_q < 0`` on ``E∖{0}`` when the
closed loop's linearisation has a zero eigenvalue (a centre manifold). The tests check it against
the mathematics: a certified ``E`` has ``V̇_q < 0`` at sampled points, a false property (the
centre unstable, or unstable inside ``E``) is never certified, a non-smooth closed loop is
refused, and the hyperbolic case keeps its exponential forms.
"""

from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import systems
from nlyap_opt.certification.roa import _blowup_candidates, certify_inner_ellipse
from nlyap_opt.design.control import InnerStatus, verdict_of

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _system(rhs, n: int):
    x = ca.SX.sym("x", n)
    return systems.System("t", x, None, ca.vertcat(*rhs(x)), state_box=[[-3.0, 3.0]] * n)


def _vdot(system, P, pts):
    F = ca.Function("f", [system.x, system.u], [system.f])
    f = np.array(F(pts.T, np.zeros((0, len(pts)))), dtype=float).T
    return 2 * np.einsum("ij,jk,ik->i", pts, P, f)


def _points_in(P, level, n, rng, k=20000):
    """Points of E = {xᵀPx ≤ level} minus the origin (radial scaling of random directions)."""
    d = rng.standard_normal((k, n))
    q = np.einsum("ij,jk,ik->i", d, P, d)
    return d * np.sqrt(level / q)[:, None] * rng.uniform(1e-3, 1, (k, 1))


def test_poly1_centre_manifold_is_certified_and_vdot_is_negative():
    """Fossil's Poly1: linearisation diag(0, -1, -4); weights (1, 2, 2), leading order 4."""
    s = systems.load_spec(EXAMPLES / "fossil_poly1.toml")
    out = certify_inner_ellipse(s, None, 0.5)
    assert out["status"] == "certified"
    assert out["form"] == "blow-up w=[1, 2, 2], m=4"
    P = np.asarray(out["P"])
    np.testing.assert_allclose(P, np.diag([1.0, 0.5, 0.125]), atol=1e-12)
    # B_ε ⊆ E and the saved box contains E
    assert out["level"] >= np.linalg.eigvalsh(P)[-1] * 0.25
    a = np.asarray(out["box"])
    assert np.all(a**2 >= out["level"] * np.diag(np.linalg.inv(P)))
    pts = _points_in(P, out["level"], 3, np.random.default_rng(1))
    assert np.all(_vdot(s, P, pts) < 0)


def test_unstable_centre_is_not_certified():
    """x' = +x³: V̇_q = 2x⁴ > 0 off the y axis; the leading term is positive."""
    s = _system(lambda x: [x[0] ** 3, -x[1]], 2)
    out = certify_inner_ellipse(s, None, 0.1)
    assert out["status"] != "certified"


@pytest.mark.parametrize("gain, inner, certified", [(1.0, 0.02, True), (10.0, 0.5, False)])
def test_higher_order_terms_decide_inside_e(gain, inner, certified):
    """x' = −x³ + g·x⁵, y' = −y: V̇_q > 0 where x² > 1/g. With g = 10 and ε = 0.5, E holds
    such points (a false property: never certified); with g = 1, ε = 0.02 it holds on E."""
    s = _system(lambda x: [-x[0] ** 3 + gain * x[0] ** 5, -x[1]], 2)
    out = certify_inner_ellipse(s, None, inner)
    P = np.asarray(out["P"])
    pts = _points_in(P, max(out["level"], np.linalg.eigvalsh(P)[-1] * inner**2), 2,
                     np.random.default_rng(2))
    truth = bool(np.all(_vdot(s, P, pts) < 0))
    assert truth is certified          # g = 10: a false property on E
    assert (out["status"] == "certified") is certified
    assert (out["verdict"] is InnerStatus.CERTIFIED) is certified
    if certified:
        assert out["form"].startswith("blow-up")


def test_non_smooth_closed_loop_is_refused():
    """x' = −x·|x| is C¹ only: Taylor's remainder of order 3 does not apply."""
    s = _system(lambda x: [-x[0] * ca.fabs(x[0]), -x[1]], 2)
    out = certify_inner_ellipse(s, None, 0.1)
    assert out["status"] == "closed-loop linearisation not Hurwitz"
    assert out["verdict"] is InnerStatus.NOT_HURWITZ     # what refutes assumption (c)


def test_centre_off_the_axes_has_no_candidate():
    """The centre direction (1, 1) is not a coordinate axis: no (P, w) is offered."""
    A = np.array([[-1.0, 1.0], [1.0, -1.0]])        # eigenvalues 0 and -2
    assert _blowup_candidates(A) == []
    assert len(_blowup_candidates(np.diag([0.0, -1.0]))) == 6    # 2 P × 3 weights
    assert [w for _, w in _blowup_candidates(np.zeros((2, 2)))] == [(1, 1)]


def test_hyperbolic_loop_keeps_the_exponential_form():
    s = _system(lambda x: [-x[0] + x[1] ** 2, -2 * x[1]], 2)
    out = certify_inner_ellipse(s, None, 0.1)
    assert out["status"] == "certified" and out["form"] in ("minors", "frobenius")


def test_saved_blowup_claim_is_checked_again_without_a_search():
    """A re-check (``P`` and ``form`` of a saved certificate) verifies exactly that claim: the
    Poly1 claim holds again; the same weights on x' = +x³ (a false property) or a form whose
    weights do not fit the state are not certified."""
    s = systems.load_spec(EXAMPLES / "fossil_poly1.toml")
    out = certify_inner_ellipse(s, None, 0.5)
    again = certify_inner_ellipse(s, None, 0.5, P=out["P"], form=out["form"])
    assert again["status"] == "certified" and again["form"] == out["form"]
    assert again["level"] == out["level"]
    wrong = certify_inner_ellipse(s, None, 0.5, P=out["P"], form="blow-up w=[1, 2], m=4")
    assert wrong["status"] != "certified" and "does not apply" in wrong["status"]
    up = _system(lambda x: [x[0] ** 3, -x[1]], 2)
    claim = certify_inner_ellipse(up, None, 0.1, P=np.diag([1.0, 0.5]),
                                  form="blow-up w=[1, 2], m=4")
    assert claim["status"] != "certified"


@pytest.mark.parametrize("P", [np.diag([1.0, -1.0]), np.array([[1.0, 0.5], [0.4, 1.0]]),
                               np.eye(3), np.diag([1.0, np.nan])])
def test_saved_P_must_be_symmetric_positive_definite(P):
    s = _system(lambda x: [-x[0] + x[1] ** 2, -2 * x[1]], 2)
    out = certify_inner_ellipse(s, None, 0.1, P=P, form="minors")
    assert out["status"] != "certified" and "positive definite" in out["status"]


def test_the_verdict_of_a_query():
    """Only a verified check certifies; only a counterexample refutes; anything else (an
    unknown, a word that is no verdict) proves nothing."""
    assert verdict_of("verified") is InnerStatus.CERTIFIED
    assert verdict_of("counterexample") is InnerStatus.COUNTEREXAMPLE
    for other in ("unknown", "verified ", "", None):
        assert verdict_of(other) is InnerStatus.NOT_PROVED
