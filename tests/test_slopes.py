"""Optimised relaxation slopes of the backward bounds (verification.slopes, α-CROWN style):
sound for any slope, tighter than the fixed slopes, deterministic, and refused where they
would do nothing."""

import casadi as ca
import numpy as np
import pytest
from test_backward import _boxes, _mlp, _network_problem, _sampled

from nlyap_opt.kernel.errors import ConfigError
from verification import lyapunov_problem, verify
from verification.affine import relaxation
from verification.backward import _TAPE, _bound, backward_bounds
from verification.verify import check_file_options, option_conflict

# (op, numpy function, range of the range's ends)
OPS = [(ca.OP_TANH, np.tanh, (-4.0, 4.0)), (ca.OP_EXP, np.exp, (-3.0, 3.0)),
       (ca.OP_SQRT, np.sqrt, (0.01, 5.0)), (ca.OP_INV, lambda t: 1.0 / t, (0.2, 4.0)),
       (ca.OP_INV, lambda t: 1.0 / t, (-4.0, -0.2)), (ca.OP_SIN, np.sin, (-2.0, 2.0)),
       (ca.OP_COS, np.cos, (-1.0, 3.0))]


@pytest.mark.parametrize("op, fn, span", OPS)
def test_any_given_slope_gets_offsets_that_enclose_f_minus_the_line(op, fn, span):
    rng = np.random.default_rng(0)
    a, b = np.sort(rng.uniform(*span, size=(2, 400)), axis=0)
    alpha = rng.normal(scale=3.0, size=400)  # far from the Chebyshev slopes as well
    alpha[:5] = [0.0, np.inf, np.nan, -1e300, 1e-300]
    s, dl, dh, ok = relaxation(op, a, b, alpha)
    assert not ok[1] and not ok[2]  # a non-finite slope claims nothing
    assert np.count_nonzero(ok) > 300
    assert np.all(s[ok] == alpha[ok])  # the slopes given are the slopes used
    t = a[:, None] + (b - a)[:, None] * np.linspace(0.0, 1.0, 257)
    d = fn(t) - s[:, None] * t
    tol = 1e-12 * (1 + np.abs(fn(t)) + np.abs(s[:, None] * t))
    assert np.all((dl[:, None] <= d + tol)[ok]) and np.all((d - tol <= dh[:, None])[ok])


def test_the_rigorous_pass_is_sound_for_arbitrary_slopes():
    # the optimiser's choices are never trusted: random, huge and non-finite slopes, tangent
    # points and planes still give lower bounds of every sampled value
    rng = np.random.default_rng(1)
    _, F = _network_problem(2)
    lo, hi = _boxes(rng, 150, 2)
    D = np.vstack([np.eye(3), -np.eye(3)])
    _TAPE.start()
    from nlyap_opt.kernel.walker import evaluate
    out = _TAPE._node(evaluate(F, [_TAPE.input(lo, hi)], _TAPE)[0])
    nodes = _TAPE.nodes
    _TAPE.start()
    slopes = {}
    for n in nodes:
        shape = (len(D),) + n.val.shape
        if n.kind == "relax":
            slopes[id(n)] = tuple(rng.normal(scale=5.0, size=shape) for _ in range(2))
        elif n.kind == "sq":
            slopes[id(n)] = (rng.normal(scale=5.0, size=shape),)
        elif n.kind == "mul":
            slopes[id(n)] = tuple(rng.normal(scale=5.0, size=shape) for _ in range(4))
    some = next(iter(slopes.values()))[0]
    some.flat[::7] = np.nan
    low = _bound(nodes, out, D, lo, hi, slopes)
    vals = _sampled(F, lo, hi, rng)
    proj = np.einsum("mk,bsk->mbs", D, vals).min(axis=2)
    assert np.all(low <= proj)
    assert np.count_nonzero(np.isfinite(low)) > 0.5 * low.size  # not sound by being -inf


def test_optimised_slopes_are_sound_tighter_and_deterministic():
    rng = np.random.default_rng(3)
    _, F = _network_problem(3)
    lo, hi = _boxes(rng, 200, 2, wmax=0.15)
    D = -np.eye(3)[1:]  # upper bounds of V and ∇V·f
    fixed, _ = backward_bounds(F, lo, hi, D)
    opt, _ = backward_bounds(F, lo, hi, D, slope_steps=20)
    again, _ = backward_bounds(F, lo, hi, D, slope_steps=20)
    assert np.array_equal(opt, again)
    vmax = _sampled(F, lo, hi, rng).max(axis=1)
    assert np.all(-opt.T >= vmax[:, 1:])
    assert np.all(opt >= fixed)
    for j, k in ((0, 1), (1, 2)):
        gap_f = np.median(-fixed[j] - vmax[:, k])
        gap_o = np.median(-opt[j] - vmax[:, k])
        assert gap_o < 0.9 * gap_f, (k, gap_o, gap_f)


def test_the_optimisation_stops_once_every_box_is_decided():
    rng = np.random.default_rng(4)
    _, F = _network_problem(3)
    lo, hi = _boxes(rng, 50, 2, wmax=0.1)
    calls = []

    def decided(low):
        calls.append(1)
        return np.ones(low.shape[1], bool)

    backward_bounds(F, lo, hi, -np.eye(3)[1:], slope_steps=50, decided=decided)
    assert len(calls) == 1


def test_the_verifier_with_optimised_slopes_keeps_verdicts_with_fewer_boxes():
    x = ca.MX.sym("x", 2)
    rng = np.random.default_rng(8)
    V = ca.sumsqr(x) * (1 + 0.3 * ca.tanh(_mlp(x, [2, 12, 12, 1], rng)))
    for a, status in ((-1.0, "verified"), (0.3, "counterexample")):
        f = ca.vertcat(a * x[0] + 0.5 * x[1], -x[1] - 0.5 * x[0] + 0.2 * x[0] ** 2)
        p = lyapunov_problem(x, V, ca.jtimes(V, x, f), inner=0.1, outer=2.0, level=0.3)
        crown = verify(p, backward=True)
        alpha = verify(p, backward=True, slope_steps=10)
        assert crown.status == alpha.status == status
        if status == "verified":
            assert alpha.boxes < crown.boxes


def test_slope_steps_without_backward_bounds_are_refused():
    assert option_conflict({"slope_steps": 10}) is not None
    assert option_conflict({"slope_steps": 10, "backward": True, "affine": False}) is not None
    assert option_conflict({"backward": True, "affine": False}) is not None
    assert option_conflict({"slope_steps": 10, "backward": True}) is None
    assert option_conflict({"slope_steps": 0}) is None
    x, _ = _network_problem(0)
    p = lyapunov_problem(x, ca.sumsqr(x), 2 * ca.dot(x, -x), inner=0.1, outer=1.0, level=0.5)
    with pytest.raises(ValueError, match="slope_steps"):
        verify(p, slope_steps=5)
    with pytest.raises(ConfigError, match="'slope_steps'.*'backward'"):
        check_file_options({"slope_steps": 5}, "certificate.json", "re-run the check")
    with pytest.raises(ConfigError, match="slope_steps.*>= 0"):
        check_file_options({"backward": True, "slope_steps": -1}, "x.json", "fix it")


def test_relaxations_that_never_reach_the_output_are_left_alone():
    # |tanh(x0)| is concretised (no backward rule for fabs): the tanh's slopes move nothing,
    # and the optimisation must stop instead of asking for a gradient (found by a review)
    x = ca.MX.sym("x", 2)
    F = ca.Function("F", [x], [ca.fabs(ca.tanh(x[0])) + x[1] + ca.log(2 + ca.tanh(x[1]))])
    rng = np.random.default_rng(5)
    lo, hi = _boxes(rng, 40, 2, wmax=0.3)
    D = np.vstack([np.eye(1), -np.eye(1)])
    fixed, _ = backward_bounds(F, lo, hi, D)
    opt, _ = backward_bounds(F, lo, hi, D, slope_steps=5)
    assert np.array_equal(opt, fixed)
