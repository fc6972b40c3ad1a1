"""Bounds: K_f, K_φ, every η option against dense sampling, M, κ ∈ U, β, bounds.json, CLI."""

import json

import casadi as ca
import numpy as np
import pytest

import systems
from baselines.lqr import lqr, saturated_controller
from nlyap_opt.interface import cli
from nlyap_opt.kernel.errors import ConfigError, InputRangeError, UnknownNameError
from nlyap_opt.kernel.jsonio import load_with_timings, split_timings
from nlyap_opt.kernel.network import Layer, Network, dense_network
from nlyap_opt.learned.bounds import (
    BOUND_OPTIONS,
    ErrorModel,
    check_input_range,
    compute_bounds,
    gradient_bound,
    lipschitz_f,
    margin,
    subboxes,
)
from nlyap_opt.learned.dynamics import Grid, measure_alpha
from nlyap_opt.learned.lipschitz import lipschitz_sampled

NAMES = ["van_der_pol", "unicycle_path_following", "inverted_pendulum"]


def _jacobian_norms(em: ErrorModel, pts: np.ndarray) -> np.ndarray:
    """‖J_f‖₂ at points, with CasADi's own Jacobian (dense) and numpy's SVD."""
    J = np.array(ca.densify(em.J_f.map(len(pts))(pts.T))).T  # (N, m*d) column-major blocks
    m, d = len(em.comp), em.d
    J = J.reshape(len(pts), d, m).swapaxes(1, 2)
    return np.linalg.norm(J, ord=2, axis=(1, 2))


def _random_points(box, n, rng):
    return rng.uniform(box[:, 0], box[:, 1], size=(n, box.shape[0]))


# ----------------------------------------------------------------------------- sub-boxes
def test_subboxes_cover_the_box(rng):
    box = np.array([[-0.8, 0.8], [-0.8, 0.8], [-5.0, 5.0]])
    lo, hi = subboxes(box, [3, 4, 5])
    assert lo.shape == (60, 3) and np.all(lo < hi)
    pts = _random_points(box, 5000, rng)
    inside = np.all((pts[:, None, :] >= lo) & (pts[:, None, :] <= hi), axis=2)
    assert inside.any(axis=1).all()
    assert np.array_equal(lo.min(axis=0), box[:, 0]) and np.array_equal(hi.max(axis=0), box[:, 1])


# ----------------------------------------------------------------------------- K_f, K_φ
@pytest.mark.parametrize("name", NAMES)
def test_K_f_is_above_every_sampled_jacobian_norm(trained, name, rng):
    res = trained[name]
    em = ErrorModel(res.system, res.network, res.grid.box)
    pts = np.vstack([_random_points(res.grid.box, 20000, rng),
                     np.concatenate(list(res.grid.batches(1 << 16)))])
    Kf = lipschitz_f(em, boxes=4096, sample_points=pts)
    sampled = float(np.max(_jacobian_norms(em, pts)))
    assert Kf.sampled == pytest.approx(sampled, rel=1e-12)
    assert sampled <= Kf.value <= 1.05 * sampled + 1e-9


def test_K_f_van_der_pol_analytic():
    """Learned row of J_f: (1 + 2 x1 x2, x1² − 1); its sup norm on [-1.5, 1.5]² is at (1.5, 1.5)."""
    s = systems.get("van_der_pol")
    net = Network([Layer(np.zeros((1, 2)), [0.0], "tanh"), Layer([[0.0]], [0.0])],
                  meta={"learned_components": [1]})
    em = ErrorModel(s, net, s.state_box)
    exact = float(np.hypot(1 + 2 * 1.5 * 1.5, 1.5**2 - 1))  # 5.6403...
    Kf = lipschitz_f(em, boxes=4096)
    assert exact <= Kf.value <= exact * (1 + 1e-8)  # the corner is a sub-box corner
    Kf_coarse = lipschitz_f(em, counts=[3, 3])
    assert Kf_coarse.value >= exact


@pytest.mark.parametrize("name", NAMES)
def test_K_phi_between_sampled_and_naive(trained, name, rng):
    res = trained[name]
    b = compute_bounds(res.system, res.network, res.grid, res.alpha, options=["global"],
                       boxes=256, check_points=1000)
    W0, b0, W1 = res.network.layers[0].weight, res.network.layers[0].bias, \
        res.network.layers[1].weight
    pts = _random_points(res.grid.box, 20000, rng)
    sampled = lipschitz_sampled(W0, b0, W1, pts)
    naive = b.K_phi.extra["naive"]
    for value in (b.K_phi.value, b.K_phi.extra["lipsdp"], b.K_phi.extra["interval"]):
        assert sampled <= value
    assert b.K_phi.extra["lipsdp"] <= naive * (1 + 1e-12)
    assert b.K_phi.value == min(b.K_phi.extra["lipsdp"], b.K_phi.extra["interval"])
    assert b.K_phi.sampled <= b.K_phi.value


# ----------------------------------------------------------------------------- η soundness
def _dense_max_error(system, net, box, n, rng):
    model, comp = net.meta.get("model", "full"), net.meta["learned_components"]
    z = _random_points(box, n, rng)
    nx = system.nx
    if model == "control_affine":
        u = _random_points(system.input_box, n, rng) if system.nu else np.zeros((n, 0))
        B = np.asarray(net.meta["input_matrix"], dtype=float)
        e = system.evaluate(z, u)[:, comp] - net.numpy(z) - u @ B.T
    else:
        e = system.evaluate(z[:, :nx], z[:, nx:])[:, comp] - net.numpy(z)
    return float(np.max(np.linalg.norm(e, axis=1)))


@pytest.mark.parametrize("name", NAMES)
def test_every_option_bounds_the_error_off_grid(trained, name, rng):
    """η of every option ≥ max ‖f − φ‖ over many random points of the box."""
    res = trained[name]
    b = compute_bounds(res.system, res.network, res.grid, res.alpha, boxes=1024,
                       check_points=20000)
    worst = _dense_max_error(res.system, res.network, res.grid.box, 100000, rng)
    assert set(b.options) == set(BOUND_OPTIONS)
    for opt in b.options.values():
        assert opt.eta >= worst, opt.name
        assert opt.eta >= b.eta_sampled
        assert opt.assumptions
    assert b.eta == min(o.eta for o in b.options.values())


def _wiggly_dynamics(system, box, seed, width=12, gain=6.0, out_gain=10.0):
    """An untrained, strongly curved φ (several wiggles per box): the interpolation terms matter."""
    m = 2 if system.name == "unicycle_path_following" else 1
    net = dense_network([box.shape[0], width, m], seed=seed)
    net.layers[0].weight *= gain / (0.5 * (box[:, 1] - box[:, 0]))[None, :]
    net.layers[1].weight *= out_gain
    net.meta = {"model": "full", "learned_components": [0, 1] if m == 2 else [1]}
    return net


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("name", NAMES)
def test_bounds_are_sound_on_coarse_grids_where_they_are_nearly_tight(name, seed, rng):
    """Coarse 7-node grids, curved error: every η covers 200k random points, and the
    second-order η is within a factor 1.6 of the sampled error (a wrong bound would show)."""
    s = systems.get(name)
    box = np.vstack([s.state_box, s.input_box]) if s.nu else s.state_box
    net = _wiggly_dynamics(s, box, seed)
    grid = Grid(box, [7] * box.shape[0])
    a = measure_alpha(s, net, grid)
    b = compute_bounds(s, net, grid, a, boxes=2048, check_points=1000)
    worst = _dense_max_error(s, net, box, 200000, rng)
    if name == "van_der_pol":
        assert worst > a.alpha  # α alone is not a bound: the h-terms are needed
    for opt in b.options.values():
        assert opt.eta >= worst, (opt.name, opt.eta, worst)
    assert b.options["second_order"].eta < 1.6 * worst


def test_unknown_bound_option_is_refused(trained):
    res = trained["van_der_pol"]
    with pytest.raises(UnknownNameError, match="available: global"):
        compute_bounds(res.system, res.network, res.grid, res.alpha, options=["magic"])


# ----------------------------------------------------------------------------- M, κ ∈ U, β
def test_gradient_bound_quadratic_analytic():
    """V = xᵀPx: ∇V = 2Px, sup over the box at a corner."""
    P = np.array([[1.5, -0.5], [-0.5, 1.0]])
    x = ca.SX.sym("x", 2)
    V = ca.Function("V", [x], [ca.mtimes([x.T, ca.DM(P), x])])
    box = np.array([[-1.0, 1.0], [-2.0, 2.0]])
    corners = np.array([[a, b] for a in box[0] for b in box[1]])
    exact = max(np.linalg.norm(2 * P @ c) for c in corners)
    gb = gradient_bound(V, box, boxes=4096)
    assert exact <= gb.M <= exact * 1.01
    assert gb.sampled <= exact


def test_gradient_bound_network_V(rng):
    net = dense_network([2, 8, 1], seed=3)
    box = np.array([[-1.0, 1.0], [-1.0, 1.0]])
    gb = gradient_bound(net, box, boxes=1024, sample_points=20000)
    assert gb.sampled <= gb.M <= 1.5 * gb.sampled
    assert gb.M <= np.linalg.norm(net.layers[1].weight, 2) * np.linalg.norm(
        net.layers[0].weight, 2) * (1 + 1e-9)


def test_controller_inside_U_is_accepted_and_outside_is_refused():
    s = systems.get("unicycle_path_following")
    K = lqr(s).K
    region = np.array([[-0.8, 0.8], [-0.8, 0.8]])
    ok = saturated_controller(s, K, 5.0)  # u = 5 tanh(Kx + b): inside U = [-5, 5] exactly
    rng_box = check_input_range(ok, region, s.input_box)
    assert np.all(rng_box[:, 0] >= -5.0) and np.all(rng_box[:, 1] <= 5.0)
    too_big = saturated_controller(s, 10 * K, 8.0)  # reaches ±8 on the region
    with pytest.raises(InputRangeError, match="leaves the input box"):
        check_input_range(too_big, region, s.input_box)
    linear = Network([Layer(-20.0 * K, [1.0], "linear")])
    with pytest.raises(InputRangeError, match="leaves the input box"):
        gradient_bound(dense_network([2, 4, 1]), region, controller=linear,
                       input_box=s.input_box)
    # a CasADi Function controller (generic interval enclosure, bisection refines it)
    x = ca.SX.sym("x", 2)
    smooth = ca.Function("k", [x], [6.0 * ca.sin(x[0]) * ca.cos(x[1])])  # |κ| ≤ 4.31 < 5
    rng_box = check_input_range(smooth, region, s.input_box, boxes=16)
    assert -5.0 <= rng_box[0, 0] <= -4.3 and 4.3 <= rng_box[0, 1] <= 5.0
    with pytest.raises(InputRangeError, match="leaves the input box"):
        check_input_range(ca.Function("k", [x], [7.0 * x[0]]), region, s.input_box)
    # a region outside X: the dynamics bound does not apply there
    with pytest.raises(InputRangeError, match="leaves the state box"):
        gradient_bound(dense_network([2, 4, 1]), [[-1.0, 1.0], [-0.5, 0.5]],
                       state_box=s.state_box)


def test_margin_is_rounded_up_and_checked():
    from fractions import Fraction

    # 3 · 0.1 is not a float: the float product rounds to nearest (here below the exact
    # value 3·fl(0.1)), the margin must be the next float up, strictly above it
    exact = Fraction(3) * Fraction(0.1)
    assert Fraction(3.0 * 0.1) < exact or Fraction(3.0 * 0.1) > exact
    b = margin(3.0, 0.1)
    assert b > 3.0 * 0.1 and Fraction(b) >= exact
    assert b == np.nextafter(3.0 * 0.1, np.inf)
    for M, eta in [(1.7, 3.3e-4), (123.456, 0.0123), (0.3, 0.7)]:
        b = margin(M, eta)
        assert Fraction(b) >= Fraction(M) * Fraction(eta) and b > M * eta
    assert margin(0.0, 1.0) >= 0.0
    with pytest.raises(ConfigError):
        margin(-1.0, 0.1)
    with pytest.raises(ConfigError):
        margin(1.0, float("nan"))


# ----------------------------------------------------------------------------- CLI, json
def _cli(argv):
    return cli.main(argv)  # learn-dynamics is a built-in subcommand


def test_cli_learn_dynamics_writes_bounds_json(tmp_path, capsys):
    out = tmp_path / "vdp"
    assert _cli(["learn-dynamics", "van_der_pol", "--fast", "--out", str(out),
                 "--no-progress"]) == 0
    printed = capsys.readouterr().out
    for word in ("K_f", "K_φ", "δ", "α", "η", "second_order"):
        assert word in printed
    d = json.loads((out / "bounds.json").read_text())
    for key in ("alpha", "delta", "K_f", "K_phi", "eta", "grid", "bound_model"):
        assert key in d
    assert "seconds" not in d    # a hashed artifact: the same input gives the same bytes
    assert set(d["grid"]) >= {"spacing", "counts"}
    timed = load_with_timings(out / "bounds.json")      # the timings, kept beside it
    assert set(timed["seconds"]) >= {"data", "training", "bounds"}
    assert split_timings(timed)[0] == d
    assert d["bound_model"]["name"] in BOUND_OPTIONS and d["bound_model"]["assumptions"]
    assert d["eta"] == d["options"][d["bound_model"]["name"]]["eta"]
    assert d["eta"] >= d["check"]["eta_sampled"] and d["check"]["passed"]
    assert d["delta"] == pytest.approx(0.5 * np.linalg.norm(d["grid"]["spacing"]), rel=1e-12)
    net = Network.load(out / "dynamics.json")
    assert net.meta["alpha"] == d["alpha"]


def test_cli_config_file_and_errors(tmp_path, capsys):
    cfg = tmp_path / "c.json"
    cfg.write_text(json.dumps({"grid_counts": [31, 31], "hidden": 6}))
    out = tmp_path / "o"
    assert _cli(["learn-dynamics", "van_der_pol", "--fast", "--config", str(cfg), "--out",
                 str(out), "--bound", "global", "--no-progress"]) == 0
    d = json.loads((out / "bounds.json").read_text())
    assert d["grid"]["counts"] == [31, 31] and d["bound_model"]["name"] == "global"
    cfg.write_text(json.dumps({"grid_count": [31, 31]}))
    assert _cli(["learn-dynamics", "van_der_pol", "--config", str(cfg), "--out",
                 str(out)]) == 3
    err = capsys.readouterr().err
    assert "unknown dynamics config key 'grid_count'" in err and "grid_counts" in err
    cfg.write_text(json.dumps({"time_budget": 10}))
    assert _cli(["learn-dynamics", "van_der_pol", "--config", str(cfg), "--out",
                 str(out)]) == 3
    assert "steps" in capsys.readouterr().err


def test_a_controller_function_with_a_structural_zero_has_all_its_outputs():
    x = ca.MX.sym("x", 2)
    k = ca.Function("k", [x], [ca.vertcat(0.5 * x[0], ca.MX(1, 1))])  # u_1 = 0, not stored
    rng = check_input_range(k, [[-1, 1], [-1, 1]], [[-1, 1], [-1, 1]])
    assert rng.shape == (2, 2)
    assert np.all(rng[1] == 0.0) and rng[0, 0] <= -0.5 and rng[0, 1] >= 0.5
