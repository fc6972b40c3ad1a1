"""Condition (b) of a quadratic ``V = xᵀPx`` decided exactly (rational ``LDLᵀ``): no
disagreement with the interval verifier away from the threshold, the threshold itself, and
the level search and its re-check through the certificate."""

from fractions import Fraction

import casadi as ca
import numpy as np
import pytest

import systems
from nlyap_opt.certification.certificate import RoaProblem, certify_roa
from nlyap_opt.certification.roa import (
    certify_level,
    quadratic_containment,
    quadratic_form,
    quadratic_inner_ball,
)
from nlyap_opt.design.control import quadratic_lyapunov
from nlyap_opt.kernel.domain import Ball, Box, Ellipsoid
from nlyap_opt.kernel.exact import inverse, positive_definite, rational_matrix
from nlyap_opt.kernel.network import Layer, Network
from verification import VerificationProblem, verify


def _spd(rng, n, cond=20.0):
    U = np.linalg.qr(rng.standard_normal((n, n)))[0]
    return U @ np.diag(np.geomspace(1.0, cond, n)) @ U.T


def _verifier(V, x, level, domain, piece):
    box, cons, label = piece
    prob = VerificationProblem(x, box, [g for g, _ in cons], [level - V],
                               [nm for _, nm in cons], [f"V>level on {label}"])
    return verify(prob, max_boxes=200000).status


def _min_on_piece(P, domain, box, rng, m=200000):
    """Sampled ``min V`` on a piece of ``∂D`` (an upper bound of the true minimum)."""
    if isinstance(domain, Box):
        pts = box[:, 0] + (box[:, 1] - box[:, 0]) * rng.random((m, len(P)))
    else:
        pts = domain.sample_boundary(m, rng)
    return float(np.min(np.einsum("ij,jk,ik->i", pts, P, pts)))


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("kind", ["ball", "ellipsoid", "box"])
def test_the_exact_verdict_agrees_with_the_interval_verifier(seed, kind):
    rng = np.random.default_rng(seed)
    n = 2 if kind == "box" else 3
    V_net = quadratic_lyapunov(_spd(rng, n, 8.0))
    Pq = quadratic_form(V_net)
    P = np.array([[float(v) for v in row] for row in Pq])
    domain = {"ball": Ball(1.5, n), "ellipsoid": Ellipsoid.from_semi_axes([1.0, 2.0, 0.7]),
              "box": Box([[-1.0, 2.0], [-0.5, 1.0]])}[kind]
    x = ca.SX.sym("x", n)
    V = V_net.casadi(x)
    decided = 0
    for piece in domain.boundary_pieces(x):
        m = _min_on_piece(P, domain, piece[0], rng)
        for level in (0.9 * m, 1.1 * m):    # away from the threshold, on both sides
            exact = quadratic_containment(Pq, level, domain, piece[0])
            if exact is None:               # a box face: the verifier decides, as before
                assert kind == "box"
                continue
            decided += 1
            # the verifier never contradicts the exact verdict: below the threshold both
            # prove it; above it the verifier finds a counterexample or (a point exactly on
            # a curved surface cannot be confirmed in floats) stays unknown
            other = _verifier(V, x, level, domain, piece)
            if level < m:
                assert exact.status == other == "verified", (piece[2], level)
            else:
                assert exact.status == "counterexample" and other != "verified", piece[2]
            if exact.status == "counterexample":
                pt = exact.counterexample.point
                assert pt @ P @ pt <= level * (1 + 1e-9)
                assert domain.contains(pt, tol=1e-9)[0]
    assert decided >= 2


def test_a_level_at_lambda_min_r2_is_refused_and_just_below_is_proved():
    # V = x1² + 2 x2² + 3 x3², r = 2: min V on the sphere is exactly 4 (at ±2 e1)
    V = Network([Layer(np.diag([1.0, np.sqrt(2.0), np.sqrt(3.0)]), np.zeros(3))],
                head={"type": "sum_of_squares"})
    Pq = quadratic_form(V)
    lam_r2 = 4 * min(Pq[i][i] for i in range(3))     # exact: diagonal P
    c = float(lam_r2)
    D = Ball(2.0, 3)
    assert quadratic_containment(Pq, c, D, None).status == "counterexample"
    assert quadratic_containment(Pq, np.nextafter(c, 10.0), D, None).status == "counterexample"
    assert quadratic_containment(Pq, np.nextafter(c, 0.0), D, None).status == "verified"
    # the inner sphere ‖x‖ = 0.5: max V is exactly 0.25·λ_max
    lam_max = 0.25 * max(Pq[i][i] for i in range(3))
    assert quadratic_inner_ball(Pq, float(lam_max), 0.5).status == "counterexample"
    assert quadratic_inner_ball(Pq, np.nextafter(float(lam_max), 10.0), 0.5).status == "verified"


def test_a_near_threshold_matrix_is_decided_in_rationals():
    # P = [[1 + δ, 1], [1, 1 + δ]], δ = 2⁻⁴⁶: λ_min = δ exactly, far below the absolute
    # error of a float eigenvalue solver on a matrix of norm 2 (about 4e-16 = 28 δ·1e-3)
    d = 2.0 ** -46
    Pq = rational_matrix([[1 + d, 1.0], [1.0, 1 + d]])
    D = Ball(1.0, 2)
    assert quadratic_containment(Pq, d, D, None).status == "counterexample"
    assert quadratic_containment(Pq, np.nextafter(d, 0.0), D, None).status == "verified"
    assert quadratic_containment(Pq, d * (1 + 2 ** -40), D, None).status == "counterexample"
    # the same threshold on an ellipsoid domain Q = I/r², r = 2: P − cQ ≻ 0 iff c < 4δ
    E = Ellipsoid.from_semi_axes([2.0, 2.0])
    assert quadratic_containment(Pq, 4 * d, E, None).status == "counterexample"
    assert quadratic_containment(Pq, np.nextafter(4 * d, 0.0), E, None).status == "verified"


def test_the_box_face_test_is_the_hyperplane_minimum_exactly():
    rng = np.random.default_rng(7)
    P = _spd(rng, 3, 5.0)
    Pq = rational_matrix(P)
    assert positive_definite(Pq)
    Pinv = inverse(Pq)
    # inverse is exact: P·P⁻¹ = I in rationals
    assert all(sum(Pq[i][k] * Pinv[k][j] for k in range(3)) == (i == j)
               for i in range(3) for j in range(3))
    D = Box([[-10.0, 1.0], [-10.0, 10.0], [-10.0, 10.0]])
    face = D.bounding_box()
    face[0] = [1.0, 1.0]                        # x0 = 1: min V = 1/(P⁻¹)_00
    m = Fraction(1) / Pinv[0][0]
    below, at = float(m) * (1 - 1e-12), float(m) * (1 + 1e-12)
    assert quadratic_containment(Pq, below, D, face).status == "verified"
    # the minimiser lies well inside this face: a refutation, located on the face
    res = quadratic_containment(Pq, at, D, face)
    assert res.status == "counterexample" and res.counterexample.point[0] == 1.0
    # a face too small to hold the minimiser: left to the verifier
    narrow = Box([[-10.0, 1.0], [-1e-3, 1e-3], [-1e-3, 1e-3]])
    f2 = narrow.bounding_box()
    f2[0] = [1.0, 1.0]
    x_star = np.linalg.solve(P, np.eye(3)[0]) / np.linalg.solve(P, np.eye(3)[0])[0]
    assert np.any(np.abs(x_star[1:]) > 1e-3)
    assert quadratic_containment(Pq, at, narrow, f2) is None


def test_only_a_quadratic_by_construction_is_recognised():
    rng = np.random.default_rng(3)
    W1, W2 = rng.standard_normal((4, 3)), rng.standard_normal((2, 4))
    lin = Network([Layer(W1, rng.standard_normal(4)), Layer(W2, rng.standard_normal(2))],
                  output_scale=[2.0, 0.5], head={"type": "sum_of_squares", "eps": 0.25})
    Pq = quadratic_form(lin)
    W = np.diag([2.0, 0.5]) @ W2 @ W1
    np.testing.assert_allclose(np.array(Pq, dtype=float), W.T @ W + 0.25 * np.eye(3),
                               rtol=1e-12)
    pts = rng.standard_normal((50, 3))
    np.testing.assert_allclose(lin.numpy(pts)[:, 0],
                               np.einsum("ij,jk,ik->i", pts, np.array(Pq, dtype=float), pts),
                               rtol=1e-10)
    tanh = Network([Layer(W1, np.zeros(4), "tanh"), Layer(W2, np.zeros(2))],
                   head={"type": "sum_of_squares"})
    assert quadratic_form(tanh) is None
    assert quadratic_form(Network([Layer(W1, np.zeros(4))])) is None     # no head


def test_the_level_search_decides_containment_exactly_and_a_recheck_agrees():
    """``V = xᵀPx`` for a linear loop on the ball: the level search refutes ``1.2·λ_min`` at
    the exact minimiser and certifies just below ``λ_min`` (where the verifier's search also
    ends certified); the re-check at that level (``certify_roa``, no search) decides (b)
    exactly too."""
    x = ca.SX.sym("x", 2)
    V_net = quadratic_lyapunov(np.array([[2.0, 0.3], [0.3, 1.0]]))
    V = V_net.casadi(x)
    A = np.array([[-1.0, 0.5], [-0.5, -1.0]])
    lie = ca.jacobian(V, x) @ (ca.DM(A) @ x)
    Pq = quadratic_form(V_net)
    lam = np.linalg.eigvalsh(np.array(Pq, dtype=float))[0]
    kw = dict(level=1.2 * lam, inner=0.1, outer=1.0, margin=0.0, max_tries=6,
              log=lambda m: None)
    exact = certify_level(x, V, lie, quadratic=Pq, **kw)
    plain = certify_level(x, V, lie, **kw)
    assert exact.status == plain.status == "certified"
    assert 0.99 * lam < exact.level < lam and plain.level < lam
    assert exact.history[0]["containment"] == "counterexample"
    assert {h["containment_backend"] for h in exact.history} == {"exact"}
    assert {h["containment_backend"] for h in plain.history} == {"interval"}

    z = ca.SX.sym("z", 2)
    lin = systems.System("linear_exact", z, None, ca.DM(A) @ z, state_box=[[-1, 1]] * 2)
    problem = RoaProblem(lin, V_net, None, None, inner=0.1, outer=1.0)
    again = certify_roa(problem, exact.level, check_inner_ellipse=False, log=lambda m: None)
    assert again.certified and again.level == exact.level
    assert again.history[0]["containment_backend"] == "exact"
    refused = certify_roa(problem, float(lam), check_inner_ellipse=False, log=lambda m: None)
    assert refused.status.value == "counterexample"
