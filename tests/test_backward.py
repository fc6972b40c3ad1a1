"""Backward linear bound propagation (verification.backward): sound, exact where it must be,
tighter than the forward affine forms on networks."""

import casadi as ca
import numpy as np
import pytest

from nlyap_opt.kernel.walker import evaluate
from verification import VerificationProblem, lyapunov_problem, verify
from verification.affine import Affine, AffineArithmetic
from verification.backward import backward_bounds


def _mlp(x, sizes, rng, scale=1.0):
    h = x
    for a, b in zip(sizes[:-2], sizes[1:-1]):
        W = ca.DM(rng.normal(size=(b, a)) / np.sqrt(a) * scale)
        h = ca.tanh(ca.mtimes(W, h) + ca.DM(rng.normal(size=b) * 0.1))
    return ca.mtimes(ca.DM(rng.normal(size=(sizes[-1], sizes[-2])) / np.sqrt(sizes[-2])), h)


def _network_problem(seed=0):
    """F = (‖x‖² − 4, V, ∇V·f) for a 2-16-16-1 tanh V and a Van der Pol-like f."""
    rng = np.random.default_rng(seed)
    x = ca.MX.sym("x", 2)
    V = _mlp(x, [2, 16, 16, 1], rng)
    V = V - ca.substitute(V, x, ca.DM.zeros(2))
    f = ca.vertcat(x[1], -x[0] + 0.5 * (1 - x[0] ** 2) * x[1]
                   - 0.1 * ca.sin(x[0]) / (2 + x[1] ** 2))
    return x, ca.Function("F", [x], [ca.vertcat(ca.sumsqr(x) - 4, V, ca.jtimes(V, x, f))])


def _boxes(rng, B, n, lo=-2.0, hi=2.0, wmax=0.4):
    c = rng.uniform(lo, hi, size=(B, n))
    w = rng.uniform(0.001, wmax, size=(B, n))
    return c - w, c + w


def _sampled(F, lo, hi, rng, S=64):
    B, n = lo.shape
    pts = lo[:, None, :] + (hi - lo)[:, None, :] * rng.uniform(size=(B, S, n))
    pts = np.concatenate([pts, lo[:, None, :], hi[:, None, :]], axis=1)  # corners too
    vals = np.array(F(pts.reshape(-1, n).T)).T
    return vals.reshape(B, S + 2, -1)


def test_bounds_hold_at_sampled_points_in_every_direction():
    rng = np.random.default_rng(1)
    _, F = _network_problem()
    lo, hi = _boxes(rng, 300, 2)
    D = np.vstack([np.eye(3), -np.eye(3), rng.normal(size=(4, 3))])
    low, forms = backward_bounds(F, lo, hi, D)
    vals = _sampled(F, lo, hi, rng)  # (B, S, 3)
    proj = np.einsum("mk,bsk->mbs", D, vals).min(axis=2)  # min over samples of d·F
    assert low.shape == (len(D), len(lo))
    assert np.all(np.isfinite(low))
    assert np.all(low <= proj)
    # the forward forms come from the same pass and enclose the samples too
    rng_f = forms.to_interval()
    assert np.all(rng_f.lo <= vals.min(axis=1)) and np.all(rng_f.hi >= vals.max(axis=1))


def test_tighter_than_the_forward_forms_on_a_two_layer_network():
    rng = np.random.default_rng(2)
    _, F = _network_problem(3)
    lo, hi = _boxes(rng, 400, 2, wmax=0.1)
    low, _ = backward_bounds(F, lo, hi, -np.eye(3)[1:])  # upper bounds of V and ∇V·f
    aff = evaluate(F, [Affine.from_box(lo, hi)], AffineArithmetic())[0].to_interval()
    vmax = _sampled(F, lo, hi, rng).max(axis=1)
    for j, k in ((0, 1), (1, 2)):
        gap_b = np.median(-low[j] - vmax[:, k])
        gap_a = np.median(aff.hi[:, k] - vmax[:, k])
        assert gap_b < 0.9 * gap_a, (k, gap_b, gap_a)


def test_linear_functions_are_bounded_exactly():
    x = ca.MX.sym("x", 3)
    A = np.array([[3.0, -2.0, 0.5], [1.0, 1.0, 1.0]])
    F = ca.Function("F", [x], [ca.mtimes(ca.DM(A), x) + ca.DM([1.0, -1.0])])
    lo = np.array([[-1.0, 0.0, 2.0], [0.5, -3.0, -1.0]])
    hi = np.array([[1.0, 1.0, 4.0], [0.75, -2.0, 1.0]])
    D = np.vstack([np.eye(2), -np.eye(2)])
    low, _ = backward_bounds(F, lo, hi, D)
    exact_min = (np.minimum(A[:, None, :] * lo, A[:, None, :] * hi).sum(-1) + [[1.0], [-1.0]])
    exact_max = (np.maximum(A[:, None, :] * lo, A[:, None, :] * hi).sum(-1) + [[1.0], [-1.0]])
    assert np.all(low[:2] <= exact_min) and np.all(low[:2] >= exact_min - 1e-12)
    assert np.all(-low[2:] >= exact_max) and np.all(-low[2:] <= exact_max + 1e-12)


def test_a_square_is_bounded_by_its_secant_from_above():
    x = ca.MX.sym("x")
    F = ca.Function("F", [x], [x**2])
    low, _ = backward_bounds(F, np.array([[-1.0]]), np.array([[2.0]]), np.array([[-1.0], [1.0]]))
    assert 4.0 <= -low[0, 0] <= 4.0 + 1e-12  # x² <= x + 2 on [-1, 2]: max 4 at x = 2
    assert -1.25 - 1e-12 <= low[1, 0] <= 0.0  # tangent at 0.5: x² >= x - 0.25


def test_products_of_varying_values_are_bounded_by_corners():
    x = ca.MX.sym("x", 2)
    F = ca.Function("F", [x], [ca.sin(x[0]) * ca.exp(x[1]) + x[0] * x[1]])
    rng = np.random.default_rng(4)
    lo, hi = _boxes(rng, 200, 2, wmax=0.5)
    low, _ = backward_bounds(F, lo, hi, np.array([[1.0], [-1.0]]))
    vals = _sampled(F, lo, hi, rng)[..., 0]
    assert np.all(low[0] <= vals.min(axis=1)) and np.all(-low[1] >= vals.max(axis=1))


def test_operations_without_a_rule_are_concretised_soundly():
    x = ca.MX.sym("x", 2)
    F = ca.Function("F", [x], [ca.fabs(x[0]) * x[1] + ca.fmax(x[0], x[1]) + ca.atan(x[1])])
    rng = np.random.default_rng(5)
    lo, hi = _boxes(rng, 200, 2, wmax=1.0)
    low, _ = backward_bounds(F, lo, hi, np.array([[1.0], [-1.0]]))
    vals = _sampled(F, lo, hi, rng)[..., 0]
    assert np.all(low[0] <= vals.min(axis=1)) and np.all(-low[1] >= vals.max(axis=1))


def test_a_division_by_a_range_holding_zero_claims_nothing():
    x = ca.MX.sym("x", 2)
    F = ca.Function("F", [x], [x[1] / x[0] + x[1]])
    low, _ = backward_bounds(F, np.array([[-1.0, 1.0], [0.5, 1.0]]),
                             np.array([[1.0, 2.0], [1.0, 2.0]]), np.array([[1.0], [-1.0]]))
    assert np.all(low[:, 0] == -np.inf)  # box 0: x0 crosses 0
    assert np.all(np.isfinite(low[:, 1]))  # box 1: x1/x0 in [1, 4], plus x1
    assert low[0, 1] <= 2.0 and -low[1, 1] >= 6.0


def test_large_magnitudes_keep_the_bounds_sound():
    rng = np.random.default_rng(6)
    x = ca.MX.sym("x", 2)
    W1 = rng.normal(size=(8, 2)) * 1e6
    W2 = rng.normal(size=(1, 8)) * 1e8
    F = ca.Function("F", [x], [ca.mtimes(ca.DM(W2), ca.tanh(ca.mtimes(ca.DM(W1), x) * 1e-6))
                               + 1e8 * x[0] * x[1]])
    lo, hi = _boxes(rng, 200, 2, wmax=0.3)
    low, _ = backward_bounds(F, lo, hi, np.array([[1.0], [-1.0]]))
    vals = _sampled(F, lo, hi, rng)[..., 0]
    assert np.all(low[0] <= vals.min(axis=1)) and np.all(-low[1] >= vals.max(axis=1))


def test_sx_functions_are_walked_too():
    x = ca.SX.sym("x", 2)
    F = ca.Function("F", [x], [ca.vertcat(ca.tanh(x[0] - 2 * x[1]) * x[0], x[0] ** 3)])
    rng = np.random.default_rng(7)
    lo, hi = _boxes(rng, 100, 2, wmax=0.5)
    low, _ = backward_bounds(F, lo, hi, np.vstack([np.eye(2), -np.eye(2)]))
    vals = _sampled(F, lo, hi, rng)
    assert np.all(low[:2].T <= vals.min(axis=1)) and np.all(-low[2:].T >= vals.max(axis=1))


@pytest.mark.parametrize("a, status", [(-1.0, "verified"), (0.3, "counterexample")])
def test_the_verifier_option_keeps_verdicts_and_needs_no_more_boxes(a, status):
    x, _ = _network_problem(8)
    # a quadratic-plus-network V; f stable (a = -1) or unstable along x0 (a = 0.3)
    rng = np.random.default_rng(8)
    V = ca.sumsqr(x) * (1 + 0.1 * ca.tanh(_mlp(x, [2, 12, 12, 1], rng)))
    f = ca.vertcat(a * x[0] + 0.5 * x[1], -x[1] - 0.5 * x[0] + 0.2 * x[0] ** 2)
    p = lyapunov_problem(x, V, ca.jtimes(V, x, f), inner=0.1, outer=1.0, level=0.3)
    plain = verify(p)
    crown = verify(p, backward=True)
    assert plain.status == crown.status == status
    if status == "verified":
        assert crown.boxes <= plain.boxes


def test_a_product_of_two_varying_matrices_is_not_taken_for_a_constant():
    # x x' and x' x (both factors vary) are leaves with input coefficients: their range is
    # c ± (Σ|g| + e), not c ± e (found by a review: the bound was 0.4375 where F is 0.25)
    x = ca.MX.sym("x", 2)
    lo, hi = np.array([[0.5, 0.5]]), np.array([[1.0, 1.0]])
    for out in (ca.mtimes(x.T, x) * x[0], ca.mtimes(ca.mtimes(x, x.T), x)):
        F = ca.Function("F", [x], [out])
        K = out.numel()
        low, _ = backward_bounds(F, lo, hi, np.eye(K))
        assert np.all(low[:, 0] <= 0.25), low  # F = (0.25, 0.25) at (0.5, 0.5)


def test_the_verifier_with_backward_bounds_finds_a_false_property():
    x = ca.MX.sym("x", 2)
    u = (x[0] - 0.1) ** 2
    w = 1 + 1e-9 * x[1]
    prod = ca.mtimes(ca.horzcat(u, u), ca.vertcat(w, w))
    p = 1e-20 - prod * (2 + x[1])  # > 0 on the line x0 = 0.1: the property p < 0 is false
    problem = VerificationProblem(x, [[-1.0, 1.0], [-1.0, 1.0]], [], [p])
    assert verify(problem, backward=True).status == "counterexample"
