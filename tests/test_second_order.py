"""The verifier's second-order centred form (option ``second_order``).

Soundness: the enclosure holds the exact values (mpmath, 50 digits) of smooth functions on
random boxes; false properties, tight or across kinks and jumps, are never verified with
it. Use: the quadratic LQR certificate of the 4-D cartpole, which the first-order forms
cannot decide (interval dependency in ``2(Px)·f(x)``), is verified with it.
"""

import pickle

import casadi as ca
import mpmath as mp
import numpy as np
import pytest
from test_soundness_ops import INDICATORS, WIDTHS, _assert_not_verified, _strip_problem

import systems
from nlyap_opt.certification.certificate import RoaProblem
from nlyap_opt.design.control import linear_controller, lqr, quadratic_lyapunov
from nlyap_opt.workflow.configs import make_config
from verification import VerificationProblem, verify
from verification.interval import Interval
from verification.verify import _point_enclosure, _second_order_enclosure

mp.mp.dps = 50


def _x(n=2):
    return ca.MX.sym("x", n)


# (casadi builder, mpmath evaluator) of smooth scalar functions of 2 variables
FUNCTIONS = {
    "quadratic_times_field": (
        lambda x: 2 * (1.5 * x[0] - 0.5 * x[1]) * (-x[1] + 0.3 * x[0] ** 2)
        + 2 * (-0.5 * x[0] + x[1]) * (x[0] - x[1] + x[0] ** 2 * x[1]),
        lambda a, b: 2 * (mp.mpf(1.5) * a - mp.mpf(0.5) * b) * (-b + mp.mpf(0.3) * a ** 2)
        + 2 * (-mp.mpf(0.5) * a + b) * (a - b + a ** 2 * b)),
    "tanh_net": (
        lambda x: ca.tanh(0.7 * x[0] - 1.3 * x[1] + 0.2) * ca.tanh(1.1 * x[0] + 0.4 * x[1])
        - 0.5 * ca.tanh(x[0] * x[1]),
        lambda a, b: mp.tanh(mp.mpf(0.7) * a - mp.mpf(1.3) * b + mp.mpf(0.2))
        * mp.tanh(mp.mpf(1.1) * a + mp.mpf(0.4) * b) - mp.mpf(0.5) * mp.tanh(a * b)),
    "trig_exp": (
        lambda x: ca.sin(3 * x[0]) * ca.cos(x[1]) + ca.exp(-x[0] ** 2) * x[1] ** 3,
        lambda a, b: mp.sin(3 * a) * mp.cos(b) + mp.exp(-a ** 2) * b ** 3),
}


@pytest.mark.parametrize("name", sorted(FUNCTIONS))
@pytest.mark.parametrize("width", [1e-3, 0.1, 1.0])
def test_enclosure_holds_the_exact_values(name, width):
    build, exact = FUNCTIONS[name]
    x = _x()
    problem = VerificationProblem(x, [[-2, 2], [-2, 2]], [], [build(x)])
    rng = np.random.default_rng(7)
    c = rng.uniform(-1.5, 1.5, (40, 2))
    w = width * rng.uniform(0.2, 1.0, (40, 2))
    lo, hi = c - w / 2, c + w / 2
    so = _second_order_enclosure(problem, lo, hi, _point_enclosure(problem, 0.5 * (lo + hi)))
    assert np.all(np.isfinite(so.lo)) and np.all(np.isfinite(so.hi))
    for b in range(len(lo)):
        pts = lo[b] + (hi[b] - lo[b]) * np.r_[rng.random((30, 2)), [[0, 0], [1, 1], [0, 1]]]
        vals = [exact(mp.mpf(float(p[0])), mp.mpf(float(p[1]))) for p in pts]
        assert mp.mpf(float(so.lo[b, 0])) <= min(vals), (b, so.lo[b, 0], min(vals))
        assert max(vals) <= mp.mpf(float(so.hi[b, 0])), (b, so.hi[b, 0], max(vals))
    if width <= 1e-3:  # second order: the overestimation is O(width²) relative to the range
        assert np.all(so.hi - so.lo < 50 * width)


@pytest.mark.parametrize("delta", [1e-9, 1e-6, 1e-3])
@pytest.mark.parametrize("name", sorted(FUNCTIONS))
def test_tight_false_properties_are_never_verified(name, delta):
    """p − (max p − δ) < 0 is false (by δ at the maximiser): never "verified"."""
    from scipy.optimize import minimize

    build, _ = FUNCTIONS[name]
    x = _x()
    f = ca.Function("f", [x], [build(x)])
    box = np.array([[-0.6, 0.7], [-0.5, 0.4]])
    g = np.stack(np.meshgrid(*[np.linspace(lo, hi, 201) for lo, hi in box]), -1).reshape(-1, 2)
    v = np.asarray(f(g.T)).ravel()
    best = minimize(lambda p: -float(f(p)), g[np.argmax(v)], bounds=box, method="L-BFGS-B")
    top = max(float(v.max()), -float(best.fun))
    problem = VerificationProblem(x, box, [], [build(x) - (top - delta)])
    res = verify(problem, second_order=True, presearch=0, max_boxes=20000)
    assert res.status in ("counterexample", "unknown")
    margin = VerificationProblem(x, box, [], [build(x) - (top + 0.02)])
    assert verify(margin, second_order=True, presearch=0).status == "verified"


@pytest.mark.parametrize("w", WIDTHS)
@pytest.mark.parametrize("kind", sorted(INDICATORS))
def test_strips_with_jumps_are_never_verified_with_it(kind, w):
    problem = _strip_problem(INDICATORS[kind], w)
    _assert_not_verified(problem, verify(problem, presearch=0, second_order=True))


def test_a_kink_at_the_centre_is_not_smoothed_away():
    """|x₁| − 0.01 on [−0.02, 0.02]²: at the root box's centre the gradient and Hessian
    graphs of fabs give 0 (the form alone would say ≤ −0.01); the kink flag keeps the
    natural extension, and the split boxes' centres are confirmed counterexamples."""
    x = _x()
    problem = VerificationProblem(x, [[-0.02, 0.02], [-0.02, 0.02]], [],
                                  [ca.fabs(x[0]) - 0.01])
    assert problem.checked
    res = verify(problem, second_order=True, presearch=0, initial_boxes=1)
    assert res.status == "counterexample"
    assert abs(res.counterexample.point[0]) >= 0.01


def _cartpole_decrease(r=0.1):
    """Decrease of the LQR quadratic certificate of the cartpole on the ball r (the dimension
    table of bench/scale.py): level 0.9 λ_min(P) r², ε = ½ sqrt(level / λ_max(P))."""
    from verification import lyapunov_problem

    s = systems.get("cartpole")
    res = lqr(s)
    ev = np.linalg.eigvalsh(res.P)
    level = 0.9 * ev[0] * r**2
    eps = 0.5 * np.sqrt(level / ev[-1])
    dec = RoaProblem(s, quadratic_lyapunov(res.P), linear_controller(s, res.K),
                     inner=eps, outer=r).decrease()
    return lyapunov_problem(dec.x, dec.V, dec.lie, inner=eps, outer=r, level=level,
                            check_positive=False), res.P, level


def test_the_cartpole_quadratic_certificate_needs_it():
    problem, P, level = _cartpole_decrease()
    assert verify(problem, max_boxes=20000).status == "unknown"
    res = verify(problem, second_order=True)
    assert res.status == "verified" and res.boxes < 20000
    # no sample of the region {V ≤ level, ε ≤ ‖x‖ ≤ r} (a thin ellipsoid: sampled inside
    # it, x = sqrt(level) P^(-1/2) z with z in the unit ball) contradicts the verdict
    rng = np.random.default_rng(3)
    z = rng.standard_normal((200_000, 4))
    z *= (rng.random((len(z), 1)) ** 0.25) / np.linalg.norm(z, axis=1, keepdims=True)
    w, U = np.linalg.eigh(P)
    pts = np.sqrt(level) * z @ (U / np.sqrt(w)).T
    F = np.asarray(problem.function(pts.T)).T
    m = problem.n_constraints
    inside = np.all(F[:, :m] <= 0, axis=1)
    assert inside.sum() > 100_000
    assert np.all(F[inside, m:] < 0)


def test_a_pickled_problem_carries_its_second_order_graphs():
    problem = _cartpole_decrease()[0]
    bare = pickle.loads(pickle.dumps(problem))
    with pytest.raises(ValueError, match="before pickling"):
        bare.second_order_functions
    problem.second_order_functions
    copy = pickle.loads(pickle.dumps(problem))
    a, b = verify(problem, second_order=True), verify(copy, second_order=True)
    assert a.status == b.status == "verified" and a.boxes == b.boxes


def test_it_is_a_run_option():
    cfg = make_config("cartpole", "fast",
                      overrides={"cegis": {"verify_options": {"second_order": True}}})
    assert cfg["cegis"]["verify_options"]["second_order"] is True
    lo, hi = np.array([[0.1, 0.2]]), np.array([[0.3, 0.5]])
    x = _x()
    p = VerificationProblem(x, [[0, 1], [0, 1]], [], [x[0] * x[1] - 1])
    so = _second_order_enclosure(p, lo, hi, _point_enclosure(p, 0.5 * (lo + hi)))
    assert isinstance(so, Interval) and so.lo[0, 0] <= 0.02 - 1 and so.hi[0, 0] >= 0.15 - 1
