"""The ``"domain"`` quadratic candidate: the largest Lyapunov ellipsoid inside the run's
domain (:func:`nlyap_opt.design.control.domain_lyapunov_matrix`), checked against its
constraints and against the candidates it must beat."""

import math

import numpy as np
import pytest

from nlyap_opt.candidates.quadratic import QUADRATIC_CANDIDATES
from nlyap_opt.design.control import (
    domain_lyapunov_matrix,
    round_lyapunov_matrix,
    volume_lyapunov_matrix,
)
from nlyap_opt.kernel.domain import Ball, Box, Ellipsoid


def _box_volume(P, half):
    """Volume of the largest sublevel set of ``xᵀPx`` inside the box ``|x_k| ≤ half_k``."""
    Pi = np.linalg.inv(P)
    c = min(h * h / Pi[k, k] for k, h in enumerate(half))
    n = len(P)
    return math.pi ** (n / 2) / math.gamma(n / 2 + 1) * c ** (n / 2) / math.sqrt(np.linalg.det(P))


def _chain(n):
    A = np.diag(np.ones(n - 1), 1)
    A[-1, :] = -np.poly(-np.geomspace(0.5, 20.0, n))[1:][::-1]
    return A


@pytest.mark.parametrize("n", [2, 4])
def test_its_constraints_hold_and_it_beats_the_other_candidates_in_a_box(n):
    A = _chain(n)
    half = np.linspace(0.5, 2.0, n)
    frac = 0.05
    P = domain_lyapunov_matrix(A, frac, half_widths=half)
    assert P is not None and np.linalg.eigvalsh(P)[0] > 0
    alpha = frac * -np.max(np.linalg.eigvals(A).real)
    # the decay LMI (solver tolerance relative to P's scale)
    lmi = A.T @ P + P @ A + 2 * alpha * P
    assert np.linalg.eigvalsh(lmi)[-1] <= 1e-6 * np.linalg.norm(P)
    # {xᵀPx ≤ 1} inside the box
    assert np.all(np.diag(np.linalg.inv(P)) <= half ** 2 * (1 + 1e-6))
    # the round and volume matrices, scaled into the box, are feasible points of the same
    # problem (their decay rate is at least α): the optimum is at least as large
    best = _box_volume(P, half)
    for other in (round_lyapunov_matrix(A, 0.1), volume_lyapunov_matrix(A, frac)):
        assert best >= _box_volume(other, half) * (1 - 1e-3)


def test_a_long_thin_box_gets_a_long_thin_ellipsoid():
    A = -np.eye(2)
    P = domain_lyapunov_matrix(A, 0.05, half_widths=[4.0, 0.5])
    axes = np.sqrt(np.diag(np.linalg.inv(P)))
    assert axes[0] == pytest.approx(4.0, rel=1e-3) and axes[1] == pytest.approx(0.5, rel=1e-3)


def test_ball_ellipsoid_and_refusals():
    A = _chain(3)
    for dom in (Ball(2.0, 3), Ellipsoid.from_semi_axes([1.0, 2.0, 0.5])):
        P = QUADRATIC_CANDIDATES["domain"](A, True, dom)
        assert P is not None
        pts = np.random.default_rng(0).standard_normal((20000, 3))
        pts /= np.sqrt(np.einsum("ij,jk,ik->i", pts, P, pts))[:, None]   # on xᵀPx = 1
        assert np.all(dom.contains(pts, tol=1e-6))
    assert QUADRATIC_CANDIDATES["domain"](np.array([[0.1, 0], [0, -1.0]]), True,
                                         Box([[-1, 1], [-1, 1]])) is None   # not Hurwitz
    assert QUADRATIC_CANDIDATES["domain"](A, True, None) is None
    assert domain_lyapunov_matrix(A) is None                                   # no bound


# ---------------------------------------------------------------- thin sublevel sets
def _thin_problem(A, box, rhs=None):
    import casadi as ca

    import systems
    from nlyap_opt.certification.certificate import RoaProblem
    from nlyap_opt.design.control import quadratic_lyapunov

    n = len(A)
    z = ca.SX.sym("z", n)
    f = ca.DM(A) @ z if rhs is None else rhs(z)
    sys_ = systems.System("thin", z, None, f, state_box=box)
    return RoaProblem(sys_, quadratic_lyapunov(np.eye(n)), None, None, inner=0.1,
                      domain=Box(box))


def test_a_thin_quadratic_gets_an_inner_radius_its_sublevel_set_holds():
    """A 3-D chain with a badly conditioned Lyapunov matrix on the box [-1, 1]³: the
    radius is half the shortest semi-axis at the box's exact plane level, below the
    policy's smallest radius, and its ball lies in that sublevel set; the candidate is then
    certified at that radius with the decrease decided by Taylor's formula."""
    from nlyap_opt.candidates.quadratic import certify_quadratics, quadratic_policy, thin_radius
    from nlyap_opt.design.control import lyapunov_matrix

    A = np.diag([1.0, 1.0], 1)
    A[-1, :] = [-90000.0, -93030.0, -3031.0]       # poles -1, -30, -3000 (cond P 1.8·10⁵)
    P = lyapunov_matrix(A)
    problem = _thin_problem(A, [[-1.0, 1.0]] * 3)
    policy = quadratic_policy(True)
    eps = thin_radius(problem, P, policy)
    smallest = policy.inner_fraction * problem.inner * min(policy.factors)
    assert eps is not None and 0 < 2 * eps < smallest    # the semi-axis is 2ε
    c = float(np.min(1.0 / np.diag(np.linalg.inv(P))))
    assert eps == pytest.approx(0.5 * np.sqrt(c / np.max(np.linalg.eigvalsh(P))))
    ball = np.random.default_rng(0).standard_normal((5000, 3))
    ball *= eps / np.linalg.norm(ball, axis=1)[:, None]
    assert np.all(np.einsum("ij,jk,ik->i", ball, P, ball) < c)
    # a round matrix needs no such radius; learned dynamics and a non-smooth f get none
    assert thin_radius(problem, np.eye(3), policy) is None
    from types import SimpleNamespace
    learned = SimpleNamespace(**{k: getattr(problem, k) for k in ("system", "domain", "inner",
                                                                  "controller")}, known=False)
    assert thin_radius(learned, P, policy) is None
    import casadi as ca
    kinked = _thin_problem(A, [[-1.0, 1.0]] * 3, rhs=lambda z: ca.DM(A) @ z
                           + ca.vertcat(0, 0, 0.01 * ca.fabs(z[0]) * z[0]))
    assert thin_radius(kinked, P, policy) is None

    cand = certify_quadratics(problem, ["lyapunov"], box=np.array([[-1.0, 1.0]] * 3), n=9,
                              log=lambda m: None)[0]
    assert cand.certified
    assert cand.certificate.inner == pytest.approx(eps)
