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
