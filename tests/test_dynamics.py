"""Learned dynamics: the grid's covering radius δ, α on that grid, saved networks, configs."""

import itertools
import json

import casadi as ca
import numpy as np
import pytest
import torch

import systems
from nlyap_opt.dynamics import (
    Grid,
    check_dynamics_network,
    default_config,
    learn_dynamics,
    load_config,
    measure_alpha,
)
from nlyap_opt.errors import ConfigError, DimensionError, NetworkFileError
from nlyap_opt.network import Network, dense_network
from nlyap_opt.symbolic import learned_rhs

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
    # the paper's Van der Pol grid: spacing 1e-3 in 2-D has δ = 7.07e-4, not 5e-4 (PITFALLS P1)
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
    with pytest.raises(ConfigError, match="unknown config keys"):
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
    from nlyap_opt.dynamics import make_grid

    g = make_grid(systems.get("van_der_pol"), cfg)
    assert g.counts.tolist() == [7, 13] and g.spacing.tolist() == [0.5, 0.25]
