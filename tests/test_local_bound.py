"""The bound on ‖f − φ‖ on a sub-box of the sampling box (:mod:`nlyap_opt.learned.local_bound`).

A φ learned on a coarse grid over a wide box, for a system whose curvature grows away from
the origin: the local bound near the origin holds at random points of its sub-box (and at
its corners), is far below the global bound, and is refused for a box that leaves the
sampling box. The grid counts balance the interpolation terms; the local box holds the
controller's values.
"""

import casadi as ca
import numpy as np
import pytest
from forge import forge_stage_file

import systems
from nlyap_opt.design.control import saturated_controller
from nlyap_opt.kernel.errors import ConfigError
from nlyap_opt.learned.dynamics import learn_dynamics
from nlyap_opt.learned.error_models import compute_bounds
from nlyap_opt.learned.local_bound import local_bound, local_box, local_counts


def _system():
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    # curvature ∂²f₂/∂x₁² = 1.2·x₁ grows away from 0; f₂ is linear in x₂ and u
    f = ca.vertcat(x[1], -x[0] - 0.5 * x[1] + 0.2 * x[0] ** 3 + u)
    return systems.System("local_cubic", x, u, f, state_box=[[-3, 3], [-3, 3]],
                          input_box=[[-2, 2]], known_state_derivatives=(0,))


@pytest.fixture(scope="module")
def learned():
    s = _system()
    res = learn_dynamics(s, {"grid_counts": [9, 9, 5], "hidden": 12, "train_points": 300,
                             "boundary_points": 50, "steps": 200, "lm_iterations": 20,
                             "minimax_rounds": 1, "minimax_iterations": 3,
                             "progress": False})
    glob = compute_bounds(s, res.network, res.grid, res.alpha, options=["second_order"],
                          boxes=1024, check_points=2000)
    return s, res, glob


def _error(s, phi, z):
    return np.linalg.norm(s.evaluate(z[:, :2], z[:, 2:])[:, [1]] - phi.numpy(z), axis=1)


def test_local_bound_holds_on_its_box_and_is_below_the_global_one(learned):
    s, res, glob = learned
    sub = np.array([[-0.5, 0.5], [-0.5, 0.5], [-1.0, 1.0]])
    loc = local_bound(s, res.network, res.grid.box, sub, nodes=20000, options=["second_order"],
                      boxes=1024, check_points=2000)
    assert np.array_equal(loc.grid.box, sub)          # the bound is stated on the sub-box
    assert 0 < loc.eta < glob.eta / 4
    rng = np.random.default_rng(3)
    z = rng.uniform(sub[:, 0], sub[:, 1], size=(50000, 3))
    corners = np.array(np.meshgrid(*sub, indexing="ij")).reshape(3, -1).T
    err = _error(s, res.network, np.vstack([z, corners]))
    assert np.max(err) <= loc.eta
    # the bound is not vacuous: within a factor of the error it bounds
    assert loc.eta < 50 * np.max(err) + 1e-3
    # and it does not hold off its box: the global error is larger than the local bound
    zg = rng.uniform(res.grid.box[:, 0], res.grid.box[:, 1], size=(50000, 3))
    assert np.max(_error(s, res.network, zg)) > loc.eta


def test_a_box_that_leaves_the_sampling_box_is_refused(learned):
    s, res, _ = learned
    for sub in ([[-0.5, 3.5], [-0.5, 0.5], [-1, 1]],      # leaves X
                [[-0.5, 0.5], [-0.5, 0.5], [-1, 2.5]],    # leaves U
                [[0.5, 0.5], [-0.5, 0.5], [-1, 1]]):      # empty side
        with pytest.raises(ConfigError, match="not inside the sampling box"):
            local_bound(s, res.network, res.grid.box, sub, nodes=1000)


def test_local_counts_balance_the_interpolation_terms():
    box = np.array([[0.0, 1.0], [0.0, 1.0], [0.0, 2.0]])
    D = np.array([[4.0, 0.0, 1.0], [0.5, 0.0, 0.0]])
    counts = local_counts(D, box, nodes=5000)
    assert counts[1] == 2                  # no curvature along axis 1: the two end nodes
    assert np.prod(counts) <= 5000
    gaps = (box[:, 1] - box[:, 0]) / (np.array(counts) - 1)
    term = gaps ** 2 * D.max(axis=0) / 8
    # one more step on the largest term would break the budget; the terms are balanced
    i = int(np.argmax(term))
    assert np.prod(counts) // counts[i] * (counts[i] + max(counts[i] // 2, 1)) > 5000
    assert term[0] < 4 * term[2] and term[2] < 4 * term[0]
    assert local_counts(np.zeros((1, 3)), box, nodes=5000) == [2, 2, 2]


def test_local_box_holds_the_controller_on_the_state_box(learned):
    s, res, _ = learned
    ctrl = saturated_controller(s, np.array([[1.0, 1.5]]), 2.0)
    X = np.array([[-0.5, 0.5], [-0.5, 0.5]])
    box = local_box(res.grid.box, X, ctrl)
    assert np.array_equal(box[:2], X)
    x = np.random.default_rng(1).uniform(X[:, 0], X[:, 1], size=(20000, 2))
    u = ctrl.numpy(x)[:, 0]
    assert box[2, 0] <= u.min() and u.max() <= box[2, 1]
    assert box[2, 0] >= -2 and box[2, 1] <= 2          # inside U
    assert box[2, 1] - box[2, 0] < 4                   # smaller than U
    with pytest.raises(ConfigError, match="leaves the sampling box"):
        local_box(res.grid.box, [[-0.5, 3.5], [-0.5, 0.5]], ctrl)


@pytest.mark.slow
def test_run_verifies_on_a_smaller_ball_with_the_local_bound(tmp_path):
    """η on the whole box (curvature 0.4·x₁³ over gaps 0.5) leaves no room for the robust
    margin on ‖x‖ ≤ 3; the run bounds η on the box of ‖x‖ ≤ 1.5, certifies there, and the
    certificate re-checks from its hashed files; an edited input box is refused."""
    import json

    from nlyap_opt import make_config, run
    from nlyap_opt.certification.certificate import recheck_certificate

    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    f = ca.vertcat(x[1], -x[0] - 0.5 * x[1] + 0.02 * x[0] ** 5 + u)
    s = systems.System("local_quintic", x, u, f, state_box=[[-3, 3], [-3, 3]],
                       input_box=[[-2, 2]], known_state_derivatives=(0,))
    systems.register("local_quintic", lambda: s)
    cfg = make_config("local_quintic", preset=None, overrides={
        "outer": 3.0, "inner": 0.1, "controller_scale": 2.0, "eval_points": 2500,
        "quadratic": ["round"], "train": {"steps": 100},
        "cegis": {"iterations": 1, "steps": 50, "samples": 2000},
        "dynamics": {"grid_counts": [13, 13, 5], "hidden": 16, "train_points": 700,
                     "boundary_points": 50, "steps": 200, "lm_iterations": 60,
                     "minimax_rounds": 1, "minimax_iterations": 3, "interval_boxes": 1024,
                     "check_points": 2000, "progress": False}})
    logs = []
    res = run(s, cfg, tmp_path / "run", log=logs.append)
    d = tmp_path / "run"
    glob = json.loads((d / "bounds.json").read_text())
    loc = json.loads((d / "bounds_local.json").read_text())
    rec = json.loads((d / "local.json").read_text())
    assert any(m.startswith("[local] with η") for m in logs)
    assert rec["radius"] == 1.5 and rec["global_eta"] == glob["eta"]
    assert loc["eta"] < glob["eta"] / 10
    box = np.asarray(loc["grid"]["box"])
    assert np.array_equal(box[:2], [[-1.5, 1.5], [-1.5, 1.5]])
    # the local bound holds at random points of its box
    from nlyap_opt.kernel.network import Network
    phi = Network.load(d / "dynamics.json")
    z = np.random.default_rng(0).uniform(box[:, 0], box[:, 1], size=(50000, 3))
    assert np.max(_error(s, phi, z)) <= loc["eta"]
    assert res.certified
    cert = res.summary
    assert cert["eta"] == loc["eta"] and cert["outer_radius"] == 1.5
    assert cert["inner_radius"] == rec["inner"] == 0.05      # ε scaled with the ball
    assert cert["artifacts"]["bounds"]["file"] == "bounds_local.json"
    assert cert["problem"]["dynamics_box"] == box[:2].tolist()
    assert cert["problem"]["input_box"] == box[2:].tolist()
    assert any("bounds_local.json" in a for a in cert["assumptions"])
    assert recheck_certificate(d, log=lambda m: None).certified
    # a run directory whose local bound was written before bounds files named their φ
    # (recorded consistently in stages.json): resuming computes the bound again
    assert loc["network"]["sha256"] == cert["artifacts"]["dynamics"]["sha256"]
    old = dict(loc)
    old.pop("network")
    (d / "bounds_local.json").write_text(json.dumps(old))
    forge_stage_file(d, "local", "bounds_local.json")
    res = run(s, cfg, d, log=logs.append)
    assert "network" in json.loads((d / "bounds_local.json").read_text())
    assert res.certified and recheck_certificate(d, log=lambda m: None).certified
    c = json.loads((d / "certificate.json").read_text())
    c["problem"]["input_box"] = [[-3.0, 3.0]]
    (d / "certificate.json").write_text(json.dumps(c))
    again = recheck_certificate(d, log=lambda m: None)
    assert not again.certified and "input box" in again.reason
