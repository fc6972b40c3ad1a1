"""Learned dynamics: the grid's covering radius δ, α on that grid, saved networks, configs."""

import itertools
import json

import casadi as ca
import numpy as np
import pytest
import torch

import systems
from nlyap_opt.kernel.errors import ConfigError, DimensionError, NetworkFileError
from nlyap_opt.kernel.network import Network, dense_network
from nlyap_opt.kernel.symbolic import learned_rhs
from nlyap_opt.learned.dynamics import (
    Grid,
    check_dynamics_network,
    default_config,
    learn_dynamics,
    load_config,
    measure_alpha,
    refine_dynamics,
)
from nlyap_opt.learned.dynamics_config import PRESETS, DynamicsConfig, config_keys, dynamics_config
from nlyap_opt.learned.dynamics_stage import dynamics_stage, eta_limit_linear

NAMES = ["van_der_pol", "unicycle_path_following", "inverted_pendulum"]


# ----------------------------------------------------------------------------- δ
def _brute_force_radius(grid: Grid, probes: np.ndarray) -> float:
    """Largest distance from a probe to its nearest node, by comparing with *every* node."""
    nodes = np.concatenate(list(grid.batches(1000)))
    d2 = ((probes[:, None, :] - nodes[None, :, :]) ** 2).sum(axis=2)
    return float(np.sqrt(d2.min(axis=1)).max())


@pytest.mark.parametrize("box, counts", [
    ([[-1.0, 1.0], [-1.0, 1.0]], [5, 5]),
    ([[-1.5, 1.5], [-1.5, 1.5]], [7, 4]),                 # anisotropic spacing
    ([[0.0, 0.3], [-2.0, 5.0]], [4, 9]),
    ([[-0.8, 0.8], [-0.8, 0.8], [-5.0, 5.0]], [5, 4, 3]),  # (x, u) space, 3-D
])
def test_delta_is_the_brute_force_covering_radius(box, counts, rng):
    g = Grid(box, counts)
    box = np.asarray(box)
    # cell centres: the farthest points from the grid
    centres = np.array(list(itertools.product(
        *[0.5 * (ax[:-1] + ax[1:]) for ax in g.axes])))
    probes = np.vstack([centres, rng.uniform(box[:, 0], box[:, 1], size=(3000, len(counts)))])
    brute = _brute_force_radius(g, probes)
    assert brute <= g.delta  # δ covers the box
    assert g.delta == pytest.approx(brute, rel=1e-12)  # ... and is attained (exact)
    assert g.delta == pytest.approx(0.5 * np.linalg.norm(g.spacing), rel=1e-14)
    # random probes alone never exceed δ either
    assert _brute_force_radius(g, probes[len(centres):]) <= g.delta


def test_grid_batches_cover_every_node_once_with_bounded_memory():
    g = Grid([[-1, 1], [0, 2], [3, 4]], [5, 3, 4])
    seen = [b for b in g.batches(7)]
    assert max(len(b) for b in seen) <= 7
    nodes = np.concatenate(seen)
    assert nodes.shape == (g.size, 3) and nodes.dtype == np.float64
    assert len({tuple(p) for p in nodes}) == g.size
    for k, ax in enumerate(g.axes):  # both box ends are nodes, exactly
        assert ax[0] == g.box[k, 0] and ax[-1] == g.box[k, 1]
    g2 = Grid.from_spacing([[-1.5, 1.5]], 1e-3)
    assert g2.counts.tolist() == [3001] and g2.delta == pytest.approx(5e-4, rel=1e-12)
    # the paper's Van der Pol grid: spacing 1e-3 in 2-D has δ = 7.07e-4 (the half-diagonal),
    # not 5e-4 (the half-spacing)
    assert Grid.from_spacing([[-1.5, 1.5]] * 2, 1e-3).delta == pytest.approx(7.0711e-4, rel=1e-4)


# ----------------------------------------------------------------------------- α
def _independent_alpha(system, net: Network, grid: Grid) -> float:
    """max ‖f − φ‖ over the grid via CasADi's own f_fun (mapped) and a torch float64 forward."""
    z = np.concatenate(list(grid.batches(1 << 16)))
    model = net.meta["model"]
    comp = net.meta["learned_components"]
    nx = system.nx
    x = z[:, :nx]
    u = np.zeros((len(z), system.nu)) if model == "control_affine" else z[:, nx:]
    fmap = system.f_fun.map(len(z))
    f = np.array(fmap(x.T, u.T)).T[:, comp]
    with torch.no_grad():
        phi = net.torch_module()(torch.as_tensor(z, dtype=torch.float64)).numpy()
    return float(np.max(np.linalg.norm(f - phi, axis=1)))


@pytest.mark.parametrize("name", NAMES)
def test_alpha_equals_independent_evaluation(trained, name, tmp_path):
    res = trained[name]
    s = res.system
    indep = _independent_alpha(s, res.network, res.grid)
    assert res.alpha.alpha == pytest.approx(indep, rel=1e-10, abs=1e-13)
    assert res.alpha.n_points == res.grid.size
    # rigorous allowance: above α, but only by rounding-level amounts
    assert res.alpha.alpha <= res.alpha.alpha_upper <= res.alpha.alpha * (1 + 1e-9) + 1e-12
    # the saved file is the verified object: reload, same α bit for bit
    path = res.network.save(tmp_path / "dyn.json")
    net = Network.load(path)
    for a, b in zip(net.layers, res.network.layers):
        assert np.array_equal(a.weight, b.weight) and np.array_equal(a.bias, b.bias)
    assert measure_alpha(s, net, res.grid).alpha == res.alpha.alpha
    meta = json.loads(path.read_text())["meta"]
    assert meta["learned_components"] == res.learned_components
    assert meta["grid"]["counts"] == res.grid.counts.tolist()


def test_only_unknown_components_are_learned(trained):
    assert trained["van_der_pol"].learned_components == [1]
    assert trained["inverted_pendulum"].learned_components == [1]
    assert trained["unicycle_path_following"].learned_components == [0, 1]
    net = trained["inverted_pendulum"].network
    assert (net.n_in, net.n_out) == (3, 1)


def test_alpha_sees_a_feature_on_a_single_column_of_nodes(trained):
    """A narrow bump of height 5 on one column of grid nodes only: α must see it."""
    res = trained["van_der_pol"]
    g = res.grid
    x0 = g.axes[0][g.counts[0] // 2 + 3]
    h = g.spacing[0]
    k = 1e6  # tanh(k(x1 − a)) − tanh(k(x1 − b)) ≈ 2 on (a, b) = (x0 − h/4, x0 + h/4), else ≈ 0
    net = Network.from_dict(res.network.to_dict())
    l0, l1 = net.layers
    l0.weight = np.vstack([l0.weight, [[k, 0.0], [k, 0.0]]])
    l0.bias = np.concatenate([l0.bias, [-k * (x0 - h / 4), -k * (x0 + h / 4)]])
    l1.weight = np.hstack([l1.weight, [[2.5, -2.5]]])
    a = measure_alpha(res.system, net, g)
    assert a.alpha > res.alpha.alpha + 4.9
    assert a.argmax[0] == x0


def test_training_is_seeded(trained):
    cfg = default_config("van_der_pol", fast=True) | {"progress": False}
    again = learn_dynamics(systems.get("van_der_pol"), cfg)
    a, b = again.network.layers, trained["van_der_pol"].network.layers
    assert all(np.array_equal(x.weight, y.weight) for x, y in zip(a, b))


def test_control_affine_model(rng):
    s = systems.get("inverted_pendulum")
    cfg = default_config("inverted_pendulum", fast=True) | {
        "progress": False, "model": "control_affine", "grid_counts": [41, 41]}
    res = learn_dynamics(s, cfg)
    net = res.network
    assert net.n_in == 2 and net.meta["model"] == "control_affine"
    assert net.meta["input_matrix"] == [[pytest.approx(1 / (0.15 * 0.25))]]
    # the CasADi rhs φ0(x) + B u agrees with the true f up to the learned error
    x, u = ca.MX.sym("x", 2), ca.MX.sym("u", 1)
    rhs = ca.Function("r", [x, u], [learned_rhs(s, net, x, u)])
    X = rng.uniform(-4, 4, (200, 2))
    U = rng.uniform(-20, 20, (200, 1))
    r = np.array(rhs.map(200)(X.T, U.T)).T
    f = s.evaluate(X, U)
    assert np.array_equal(r[:, 0], f[:, 0])  # the known component is exact
    # φ(x, u) − f(x, u) = φ0(x) − f(x, 0) for every u (f is affine in u with the same B)
    e0 = net.numpy(X)[:, 0] - s.evaluate(X, np.zeros((200, 1)))[:, 1]
    np.testing.assert_allclose(r[:, 1] - f[:, 1], e0, rtol=0, atol=1e-10)


def test_control_affine_needs_a_constant_input_matrix():
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    s = systems.System("nonaffine", x, u, ca.vertcat(x[1], -x[0] + ca.sin(u) * (1 + x[0] ** 2)),
                       state_box=[[-1, 1], [-1, 1]], input_box=[[-1, 1]])
    cfg = default_config("nonaffine", fast=True) | {
        "model": "control_affine", "grid_counts": [5, 5], "progress": False}
    with pytest.raises(ConfigError, match="not control-affine"):
        learn_dynamics(s, cfg)


# ----------------------------------------------------------------------------- bad input
def test_corrupted_dynamics_files_are_refused(trained, tmp_path):
    s = systems.get("inverted_pendulum")
    good = trained["inverted_pendulum"].network.to_dict()
    text = json.dumps(good)
    bad = tmp_path / "nan.json"
    bad.write_text(text.replace(repr(good["layers"][1]["weight"][0][0]), "NaN", 1))
    with pytest.raises(NetworkFileError):
        Network.load(bad)
    trunc = tmp_path / "trunc.json"
    trunc.write_text(text[: len(text) // 2])
    with pytest.raises(NetworkFileError, match="not valid JSON"):
        Network.load(trunc)
    # a network that does not fit the system / its meta
    wrong_in = dense_network([2, 8, 1])
    wrong_in.meta = {"model": "full", "learned_components": [1]}
    with pytest.raises(NetworkFileError, match="needs R\\^3 -> R\\^1"):
        check_dynamics_network(s, wrong_in)
    deep = dense_network([3, 4, 4, 1])
    deep.meta = {"learned_components": [1]}
    with pytest.raises(NetworkFileError, match="one hidden tanh layer"):
        check_dynamics_network(s, deep)
    bad_meta = Network.from_dict(good)
    bad_meta.meta["learned_components"] = [5]
    with pytest.raises(NetworkFileError, match="learned_components"):
        measure_alpha(s, bad_meta, trained["inverted_pendulum"].grid)


def test_config_errors(tmp_path):
    p = tmp_path / "c.json"
    p.write_text(json.dumps({"hiden": 10}))
    with pytest.raises(ConfigError, match="'hiden' \\(did you mean 'hidden'\\?\\)"):
        load_config(p, "van_der_pol")
    p.write_text(json.dumps({"grid_counts": [11, 11, 11]}))
    cfg = load_config(p, "van_der_pol")
    with pytest.raises(ConfigError, match="grid_counts has 3 entries"):
        learn_dynamics(systems.get("van_der_pol"), cfg)
    with pytest.raises(ConfigError, match="at least 2 nodes"):
        Grid([[0, 1]], [1])
    with pytest.raises(DimensionError):
        Grid([0, 1, 2], [3])


def test_config_file_grid_spacing_replaces_default_counts(tmp_path):
    p = tmp_path / "c.json"
    p.write_text(json.dumps({"grid_spacing": [0.5, 0.25]}))
    cfg = load_config(p, "van_der_pol")
    from nlyap_opt.learned.dynamics import make_grid

    g = make_grid(systems.get("van_der_pol"), cfg)
    assert g.counts.tolist() == [7, 13] and g.spacing.tolist() == [0.5, 0.25]


def test_a_config_without_a_grid_says_where_to_give_one(tmp_path):
    """A system with no dynamics preset (a spec file's) and no grid in the config: the
    message names the system, the two keys and --config, with an example of the right
    length (one count per axis of the sampling box)."""
    from nlyap_opt.learned.dynamics import make_grid

    cfg = load_config(None, "van_der_pol")
    cfg = {**cfg.to_dict(), "grid_counts": None, "grid_spacing": None}
    with pytest.raises(ConfigError, match=r"'van_der_pol' has no grid.*'grid_counts'.*"
                                          r"\[11, 11\].*'grid_spacing' in --config FILE"):
        make_grid(systems.get("van_der_pol"), cfg)


# ----------------------------------------------------------------------------- one config
@pytest.mark.parametrize("over, match", [
    ({"hiden": 10}, r"'hiden' \(did you mean 'hidden'\?\)"),
    ({"lm_iteration": 3}, r"did you mean 'lm_iterations'"),
    ({"time_budget": 60.0}, r"'time_budget'.*counted in steps"),
    ({"steps": -1}, r"'steps' must be an integer >= 0, got -1"),
    ({"steps": 2.5}, r"'steps' must be an integer"),
    ({"steps": True}, r"'steps' must be an integer"),
    ({"hidden": 0}, r"'hidden' must be a positive integer"),
    ({"hidden": [4, "a"]}, r"'hidden'"),
    ({"lr": -0.1}, r"'lr' must be a finite number > 0"),
    ({"lr": float("nan")}, r"'lr'"),
    ({"model": "affine"}, r"'model' must be one of full, control_affine"),
    ({"grid_counts": [61, 1]}, r"'grid_counts' must be a non-empty list of integers >= 2"),
    ({"state_box": [[1.0, -1.0], [0, 1]]}, r"'state_box'"),
    ({"eta_target": 0.0}, r"'eta_target' must be a finite number > 0"),
    ({"bound_model": "tight"}, r"'bound_model'"),
    ({"progress": "yes"}, r"'progress' must be true or false"),
    ({"system": "unicycle_path_following"}, r"is for system 'unicycle_path_following'"),
])
def test_dynamics_config_rejects_bad_keys_types_and_ranges(over, match):
    with pytest.raises(ConfigError, match=match) as err:
        dynamics_config("van_der_pol", over)
    assert "\n" not in str(err.value)  # one line


def test_dynamics_config_presets_and_types():
    d = dynamics_config("van_der_pol")
    assert isinstance(d, DynamicsConfig) and d.preset == "default"
    assert d.grid_counts == PRESETS["default"]["van_der_pol"]["grid_counts"]
    f = dynamics_config("van_der_pol", {"preset": "fast", "grid_spacing": 0.1})
    assert f.grid_counts is None and f.grid_spacing == 0.1  # spacing replaces the counts
    assert f.steps == PRESETS["fast"]["van_der_pol"]["steps"]
    # the dict form round-trips, every field has a type, unknown presets are refused
    assert dynamics_config("van_der_pol", f.to_dict()) == f
    assert set(config_keys()) == set(f.to_dict())
    with pytest.raises(KeyError, match="unknown dynamics preset"):
        dynamics_config("van_der_pol", {"preset": "slow"})
    # no wall-clock key anywhere: budgets are counts
    assert not any("time" in k for k in config_keys())
    # the bound names the config accepts are the ones that exist
    from nlyap_opt.learned.bounds import BOUND_OPTIONS
    from nlyap_opt.learned.dynamics_config import _BOUND_NAMES

    assert set(_BOUND_NAMES) == set(BOUND_OPTIONS)


def test_dynamics_metadata_misuse_is_refused(trained):
    """Unknown model, out-of-range or missing components, a wrong B: never the catalogue f."""
    s = systems.get("inverted_pendulum")
    good = trained["inverted_pendulum"].network.to_dict()
    for meta, match in [
        ({"model": "affine"}, "meta\\['model'\\]"),
        ({"learned_components": [1, 7]}, "learned_components"),
        ({"learned_components": [1, 1]}, "learned_components"),
        ({"learned_components": ["a"]}, "list of ints"),
    ]:
        net = Network.from_dict(good)
        net.meta.update(meta)
        with pytest.raises(NetworkFileError, match=match):
            check_dynamics_network(s, net)
    # a network that learns only component 1 of a system where 0 is not declared known
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    other = systems.System("unknown_both", x, u, ca.vertcat(x[1], -x[0] + u),
                           state_box=[[-1, 1], [-1, 1]], input_box=[[-1, 1]])
    net = Network.from_dict(good)
    with pytest.raises(NetworkFileError, match="does not declare state derivatives \\[0\\]"):
        check_dynamics_network(other, net)
    with pytest.raises(ConfigError, match="leaves out state derivatives \\[0\\]"):
        learn_dynamics(other, {"preset": "fast", "learned_components": [1],
                               "grid_counts": [5, 5, 3], "progress": False})
    # control-affine: the input matrix must be present and be the system's
    ca_net = Network.from_dict(good)
    ca_net.layers[0].weight = ca_net.layers[0].weight[:, :2]
    ca_net.meta["model"] = "control_affine"
    with pytest.raises(NetworkFileError, match="no meta\\['input_matrix'\\]"):
        check_dynamics_network(s, ca_net)
    ca_net.meta["input_matrix"] = [[1.0]]
    with pytest.raises(NetworkFileError, match="differs from the input matrix"):
        check_dynamics_network(s, ca_net)
    ca_net.meta["input_matrix"] = [[1.0, 2.0]]
    with pytest.raises(NetworkFileError, match="finite 1x1"):
        check_dynamics_network(s, ca_net)
    ca_net.meta["input_matrix"] = s.B[[1]].tolist()
    assert check_dynamics_network(s, ca_net) == ("control_affine", [1])


# ----------------------------------------------------------------------------- refinement, gate
def test_refinement_trains_on_the_worst_grid_nodes(trained):
    res = trained["van_der_pol"]
    new = refine_dynamics(res, points=30)
    assert new.rounds == 1 and new.network.meta["refinement_rounds"] == 1
    z_old, z_new = res._state["z"], new._state["z"]
    assert np.array_equal(z_new[:len(z_old)], z_old) and len(z_new) > len(z_old)
    added = z_new[len(z_old):]
    # the node where α was attained is among the added ones, and every added node's error
    # is at least the 30th largest error on the grid
    assert np.any(np.all(added == res.alpha.argmax, axis=1))
    nodes = np.concatenate(list(res.grid.batches()))
    assert res.system.nu == 0 and nodes.shape[1] == 2  # Van der Pol: a grid over x only
    err = np.abs(res.system.evaluate(nodes)[:, 1] - res.network.numpy(nodes)[:, 0])
    kth = np.sort(err)[-30]
    e_added = np.abs(res.system.evaluate(added)[:, 1] - res.network.numpy(added)[:, 0])
    assert np.all(e_added >= kth)
    # the original result is unchanged; α is measured again on the new network
    assert res.rounds == 0
    assert new.alpha.alpha == measure_alpha(res.system, new.network, new.grid).alpha


TINY = {"preset": "fast", "hidden": 2, "steps": 30, "lm_iterations": 3, "minimax_rounds": 0,
        "eta_target": 1e-3, "eta_rounds": 1, "refine_points": 50, "interval_boxes": 256,
        "check_points": 1000, "progress": False}


def test_hopeless_eta_stops_the_stage_with_advice():
    s = systems.get("van_der_pol")
    lines = []
    st = dynamics_stage(s, TINY, log=lines.append)
    assert st.status == "eta_too_large" and not st.ok
    assert st.eta > 1e-3 and st.rounds == 1 and len(st.history) == 2
    assert st.eta == min(h["eta"] for h in st.history)  # the best round is kept
    adv = st.advice
    assert "eta_target" in adv and "hidden" in adv and "state_box" in adv
    z = st.alpha.argmax
    assert f"x1 = {z[0]:.4g}" in adv and f"x2 = {z[1]:.4g}" in adv  # where the error peaks
    assert any("refinement round 1/1" in ln for ln in lines)
    assert "\n" not in adv
    # without a target: no gate
    ok = dynamics_stage(s, TINY | {"eta_target": None}, log=None)
    assert ok.status == "ok" and ok.advice == "" and ok.rounds == 0
    assert ok.eta == st.history[0]["eta"]  # the same first round, bit for bit


def test_learn_dynamics_cli_exits_2_with_advice_on_a_hopeless_eta(tmp_path, capsys):
    from nlyap_opt.interface import cli

    cfg = tmp_path / "tiny.json"
    cfg.write_text(json.dumps({k: v for k, v in TINY.items() if k != "preset"}))
    out = tmp_path / "o"
    assert cli.main(["learn-dynamics", "van_der_pol", "--fast", "--config", str(cfg),
                     "--out", str(out)]) == 2
    assert "eta_too_large" in capsys.readouterr().err
    gate = json.loads((out / "bounds.json").read_text())["gate"]
    assert gate["status"] == "eta_too_large" and gate["eta_target"] == 1e-3
    assert (out / "dynamics.json").exists()


def test_eta_limit_linear_matches_the_closed_form():
    # A = −a I: P = I / (2a), the limit is ε / (2 λmax P) = a ε
    assert eta_limit_linear(-3.0 * np.eye(2), 0.2) == pytest.approx(0.6, rel=1e-12)
    # a non-normal A: compare with the definition on the ring, by sampling
    A = np.array([[0.0, -1.0], [1.0, -1.0]])  # reversed Van der Pol at the origin
    lim = eta_limit_linear(A, 0.2)
    from scipy.linalg import solve_continuous_lyapunov

    P = solve_continuous_lyapunov(A.T, -np.eye(2))
    th = np.linspace(0, 2 * np.pi, 2001)
    x = 0.2 * np.stack([np.cos(th), np.sin(th)], axis=1)
    grad = 2 * x @ P
    # at η just below the limit the linearised robust decrease holds on the whole ring
    assert np.all(-np.sum(x * x, axis=1) + 0.999 * lim * np.linalg.norm(grad, axis=1) < 0)
    with pytest.raises(ConfigError, match="not Hurwitz"):
        eta_limit_linear(np.eye(2), 0.2)


def test_alpha_pairs_each_output_with_its_listed_component():
    """A network that lists its learned components out of order ([1, 0]) is measured in
    that order, as learned_rhs uses it: the same φ with its outputs swapped has the same α
    (a sorted copy of the list paired each output with the other component of f)."""
    import copy

    from nlyap_opt.learned.dynamics import Grid, learn_dynamics, measure_alpha

    s = systems.get("unicycle_path_following")
    res = learn_dynamics(s, {"preset": "fast", "model": "full", "hidden": 8,
                             "grid_counts": [9, 9, 5], "train_points": 300,
                             "boundary_points": 0, "steps": 30, "lm_iterations": 3,
                             "minimax_rounds": 0, "progress": False})
    assert res.network.meta["learned_components"] == [0, 1]
    swapped = copy.deepcopy(res.network)
    out = swapped.layers[-1]
    out.weight, out.bias = out.weight[::-1].copy(), out.bias[::-1].copy()
    swapped.meta["learned_components"] = [1, 0]
    grid = Grid(res.grid.box, [9, 9, 5])
    a, b = measure_alpha(s, res.network, grid), measure_alpha(s, swapped, grid)
    assert b.alpha == pytest.approx(a.alpha, rel=1e-12)
    wrong = copy.deepcopy(swapped)                  # the pairing a sorted list gave
    wrong.meta["learned_components"] = [0, 1]
    assert measure_alpha(s, wrong, grid).alpha > 2 * a.alpha
    x, u = ca.MX.sym("x", 2), ca.MX.sym("u", 1)
    fa = ca.Function("a", [x, u], [learned_rhs(s, res.network, x, u)])
    fb = ca.Function("b", [x, u], [learned_rhs(s, swapped, x, u)])
    np.testing.assert_allclose(np.array(fa([0.2, -0.3], [0.5])),
                               np.array(fb([0.2, -0.3], [0.5])), rtol=1e-13)


def test_a_linear_component_is_carried_by_the_linear_neuron():
    """A stiff linear chain (Fossil's HighOrd4: modes up to 3979/s): every component is linear,
    the least-squares fit explains it, and φ is f to ~10⁻⁸ relative on the whole grid (without
    the neuron the tanh layer left α ≈ 0.6). A nonlinear component is fitted by the neurons
    alone."""
    from nlyap_opt.learned.phi_training import LINEAR_RESIDUAL_MAX, linear_fit
    x = ca.SX.sym("x", 4)
    f = ca.vertcat(x[1], x[2], x[3], -576 * x[0] - 2400 * x[1] - 4180 * x[2] - 3980 * x[3])
    s = systems.System("chain4", x, None, f, state_box=[[-1, 1]] * 4)
    res = learn_dynamics(s, {"grid_counts": [7] * 4, "hidden": 4, "train_points": 400,
                             "boundary_points": 50, "steps": 50, "lm_iterations": 5,
                             "minimax_rounds": 0, "progress": False})
    scale = float(np.max(np.abs(s.evaluate(np.ones((1, 4))))))
    assert res.alpha.alpha < 1e-7 * scale
    assert all(fit is not None for fit in res._state["linear"])
    z = np.linspace(-1, 1, 50)[:, None]
    assert linear_fit(z, np.sin(3 * z[:, 0])) is None          # nonlinear: no neuron
    a, c, r = linear_fit(z, 2 * z[:, 0] + 1 + 1e-3 * z[:, 0] ** 3)
    assert abs(a[0] - 2) < 1e-2 and abs(c - 1) < 1e-12 and r <= LINEAR_RESIDUAL_MAX * 2
