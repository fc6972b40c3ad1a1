"""Condition (c) proved from data and a declared second-derivative bound (issue 14, item 6).

Every "certified" is cross-examined on the true plant: the quadratic decrease
``2xᵀP f(x, κ(x)) < 0`` is sampled densely on the ellipse (interior and boundary). A declared
H far below the truth gives a proof about the functions the declaration describes, which
the real plant may violate (shown below), and the data refuse such an H.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import control
import numpy as np
import pytest

import systems
from nlyap_opt.design.control import saturated_controller
from nlyap_opt.kernel.errors import ConfigError
from nlyap_opt.kernel.network import Layer, Network
from nlyap_opt.learned.dynamics import Grid, check_declared, learn_dynamics
from nlyap_opt.learned.inner_from_data import prove_inner_ellipse_from_data
from systems.jacobian import jacobian_from_data

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _example(name: str):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def pend():
    return _example("blackbox_pendulum")


def _pendulum(pend, name="pend", **decl):
    d = pend.DECLARED if not decl else systems.Declarations(**decl)
    return systems.System.from_callable(
        name, pend.pendulum_rhs, nx=2, nu=1, state_box=[[-4, 4], [-4, 4]],
        input_box=[[-20, 20]], u_eq=[0.0], known_rhs={0: lambda x, u: x[1]},
        declarations=d)


def _lqr_controller(system, jb):
    K, _, _ = control.lqr(jb.A, jb.B, np.eye(system.nx), np.eye(system.nu))
    return saturated_controller(system, K, 20.0)


def _vdp(X, U=None):
    x1, x2 = X[:, 0], X[:, 1]
    return np.stack([-x2, x1 + (x1**2 - 1) * x2], axis=1)


def _vdp_system(H):
    return systems.System.from_callable("rvdp", _vdp, nx=2, nu=0,
                                        state_box=[[-3, 3], [-3, 3]],
                                        declarations=systems.Declarations(hessian=H))


def _max_decrease(res, rhs, feedback=None, n=100000, seed=0):
    """max of 2xᵀP g(x) over random points of E (interior and boundary), x ≠ 0."""
    P, c = np.asarray(res["P"]), float(res["level"])
    rng = np.random.default_rng(seed)
    d = P.shape[0]
    v = rng.normal(size=(n, d))
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    r = np.concatenate([rng.uniform(0, 1, n // 2) ** (1 / d), np.ones(n - n // 2)])
    L = np.linalg.cholesky(np.linalg.inv(P) * c)
    X = (v * r[:, None]) @ L.T
    X = X[np.linalg.norm(X, axis=1) > 1e-9]
    U = feedback(X) if feedback is not None else None
    g = rhs(X, U)
    return float(np.max(2 * np.einsum("ij,jk,ik->i", X, P, g)))


def test_black_box_pendulum_proves_c_for_a_small_inner_radius(pend):
    s = _pendulum(pend)
    jb = jacobian_from_data(s)
    kap = _lqr_controller(s, jb)
    res = prove_inner_ellipse_from_data(s, kap, 0.005, jac=jb)
    assert res["status"] == "certified", res["status"]
    assert {"status", "P", "level", "box", "proved_from"} <= set(res)
    assert "H = 26" in res["proved_from"] and "samples" in res["proved_from"]
    P = res["P"]
    assert res["level"] >= np.max(np.linalg.eigvalsh(P)) * 0.005**2      # B_ε ⊆ E
    assert np.all(res["box"] ** 2 >= res["level"] * np.diag(np.linalg.inv(P)))  # E ⊆ box
    assert _max_decrease(res, s.evaluate, kap.numpy) < 0
    # the same system without a declared B goes through the general remainder bound
    s2 = _pendulum(pend, "pend_noB", lipschitz=34.5, hessian=26.0)
    res2 = prove_inner_ellipse_from_data(s2, kap, 0.002)
    assert res2["status"] == "certified", res2["status"]
    assert "input matrix" not in res2["proved_from"]
    assert res2["terms"]["a_squared"] > 2.0          # ‖(v, J_κ v)‖₁² counts the controller
    assert _max_decrease(res2, s2.evaluate, kap.numpy) < 0


def test_large_inner_radius_or_large_H_fail_honestly(pend):
    s = _pendulum(pend)
    kap = _lqr_controller(s, jacobian_from_data(s))
    res = prove_inner_ellipse_from_data(s, kap, 0.4)
    assert res["status"].startswith("not proved") and "needs ρ ≤" in res["status"]
    limit = res["terms"]["inner_max"]
    assert 0 < limit < 0.4 and f"ε ≤ {limit:.4g}" in res["status"]
    # the advertised radius works
    assert prove_inner_ellipse_from_data(s, kap, 0.9 * limit)["status"] == "certified"
    big = _pendulum(pend, "pend_bigH", hessian=1e4, input_matrix=[[0.0], [1 / pend.INERTIA]])
    res = prove_inner_ellipse_from_data(big, kap, 0.005)
    assert res["status"].startswith("not proved") and "needs ρ ≤" in res["status"]


def test_an_H_far_too_small_proves_only_its_own_declaration_and_the_data_refuse_it():
    small = _vdp_system(0.01)
    res = prove_inner_ellipse_from_data(small, None, 1.5)
    # valid for every f with |∂²f| ≤ 0.01 ... but not for the real plant:
    assert res["status"] == "certified"
    assert _max_decrease(res, _vdp) > 0
    # ... and the samples refuse the declaration before it could be used
    grid = Grid(small.state_box, [31, 31])
    with pytest.raises(ConfigError, match=r"declared H = 0\.01 is below"):
        small.check_declarations(grid)
    with pytest.raises(ConfigError, match=r"declared H = 0\.01 is below"):
        check_declared(small, grid, "full")
    with pytest.raises(ConfigError, match=r"declared H = 0\.01 is below"):
        learn_dynamics(small, {"preset": "fast", "progress": False, "grid_counts": [31, 31]})
    # the true bound (|∂²f₂/∂x₁²| = 2|x₂|, |∂²f₂/∂x₁∂x₂| = 2|x₁| ≤ 6) passes and proves
    ok = _vdp_system(6.0)
    ok.check_declarations(grid)
    res = prove_inner_ellipse_from_data(ok, None, 0.01)
    assert res["status"] == "certified", res["status"]
    assert _max_decrease(res, _vdp) < 0
    assert prove_inner_ellipse_from_data(ok, None, 1.5)["status"].startswith("not proved")


def test_pendulum_from_a_sample_file(pend):
    black = _pendulum(pend)
    g = Grid(black.state_box, [201, 201])
    X = np.vstack(list(g.batches()))
    U = np.zeros((X.shape[0], 1))
    smp = systems.SampleSet(np.hstack([X, U]), black.evaluate(X, U), nx=2, nu=1,
                            names=["theta", "omega", "torque"])
    s = systems.System.from_samples("pend_samples", smp, input_box=[[-20, 20]], u_eq=[0.0],
                                    known_rhs={"theta": lambda x, u: x[1]},
                                    declarations=pend.DECLARED)
    jb = jacobian_from_data(s)
    assert jb.source == "samples" and jb.error.max() == pytest.approx(26 * 0.04 / 2, rel=1e-6)
    kap = _lqr_controller(s, jb)
    res = prove_inner_ellipse_from_data(s, kap, 0.05, jac=jb)
    assert res["status"] == "certified", res["status"]
    assert "Jacobian from samples" in res["proved_from"]
    assert _max_decrease(res, black.evaluate, kap.numpy) < 0       # on the true plant
    assert prove_inner_ellipse_from_data(s, kap, 0.4, jac=jb)["status"].startswith(
        "not proved")


def test_a_coarse_sample_grid_leaves_the_linear_part_unproved():
    out = {}
    for n in (61, 301):
        smp = systems.sample_function(_vdp, [[-3, 3], [-3, 3]], [n, n], nx=2)
        s = systems.System.from_samples("rvdp_samples", smp,
                                        declarations=systems.Declarations(hessian=6.0))
        out[n] = prove_inner_ellipse_from_data(s, None, 0.01)
    # h = 0.1: the finite-difference error H·h/2 = 0.3 per entry swamps the linear decrease
    assert out[61]["status"].startswith("not proved: the linear part"), out[61]["status"]
    assert out[301]["status"] == "certified", out[301]["status"]
    assert _max_decrease(out[301], _vdp) < 0


def test_what_cannot_be_proved_says_why(pend):
    s = _pendulum(pend)
    jb = jacobian_from_data(s)
    kap = _lqr_controller(s, jb)
    # the gain with the wrong sign: the estimated closed loop is unstable
    flipped = Network([Layer(-kap.layers[0].weight, kap.layers[0].bias, "tanh")],
                      kap.output_scale)
    assert "not Hurwitz" in prove_inner_ellipse_from_data(s, flipped, 0.005)["status"]
    # κ(0) ≠ u_eq: the true equilibrium moved
    biased = Network([Layer(kap.layers[0].weight, np.array([1e-3]), "tanh")],
                     kap.output_scale)
    assert "κ(0)" in prove_inner_ellipse_from_data(s, biased, 0.005)["status"]
    # a kink in the controller: not C²
    relu = Network([Layer(kap.layers[0].weight, kap.layers[0].bias, "relu")], 1.0)
    assert "C²" in prove_inner_ellipse_from_data(s, relu, 0.005)["status"]
    # no declared H: the paper's assumption remains
    bare = _pendulum(pend, "bare", lipschitz=34.5)
    res = prove_inner_ellipse_from_data(bare, kap, 0.005)
    assert res["status"].startswith("not available") and "hessian" in res["status"]
    assert res["proved_from"] is None


def test_sample_offset_needs_a_declared_lipschitz_constant(pend, tmp_path):
    black = _pendulum(pend)
    g = Grid(black.state_box, [401, 401])
    X = np.vstack(list(g.batches()))
    U = np.zeros((X.shape[0], 1))
    pts = np.hstack([X, U])
    pts[:, :2] += 1e-12 * np.sign(pts[:, :2])        # rows slightly off the nodes
    smp = systems.SampleSet(pts, black.evaluate(pts[:, :2], U), nx=2, nu=1)
    assert smp.offset > 0
    kw = dict(input_box=[[-20, 20]], u_eq=[0.0], known_rhs={"x1": lambda x, u: x[1]})
    B = [[0.0], [1 / pend.INERTIA]]
    no_k = systems.System.from_samples(
        "off", smp, declarations=systems.Declarations(hessian=26.0, input_matrix=B), **kw)
    kap = _lqr_controller(no_k, jacobian_from_data(no_k))
    res = prove_inner_ellipse_from_data(no_k, kap, 0.003)
    assert res["status"].startswith("not proved") and "lipschitz" in res["status"]
    with_k = systems.System.from_samples(
        "off", smp, declarations=systems.Declarations(lipschitz=34.5, hessian=26.0,
                                                      input_matrix=B), **kw)
    res = prove_inner_ellipse_from_data(with_k, kap, 0.003)
    assert res["status"] == "certified", res["status"]
    assert "Lipschitz" in res["proved_from"]


# a plant whose learned component a tanh network represents exactly (η = 0 is a true bound)
_A2, _D2, _B2 = 19.62, 9.33, 26.67


def _tanh_plant(X, U):
    return np.stack([X[:, 1], _A2 * np.tanh(X[:, 0]) - _D2 * np.tanh(X[:, 1]) + _B2 * U[:, 0]],
                    axis=1)


def test_the_learned_phi_with_eta_extends_the_data_proof_to_a_large_inner_radius():
    s = systems.System.from_callable(
        "tanh_plant", _tanh_plant, nx=2, nu=1, state_box=[[-4, 4], [-4, 4]],
        input_box=[[-20, 20]], u_eq=[0.0], known_rhs={0: lambda x, u: x[1]},
        declarations=systems.Declarations(hessian=16.0, input_matrix=[[0.0], [_B2]]))
    s.check_declarations(Grid(s.sampling_box, [41, 41, 5]))   # H = 16 ≥ 19.62·4/(3√3)
    phi = Network([Layer(np.eye(2), np.zeros(2), "tanh"),
                   Layer(np.array([[_A2, -_D2]]), np.zeros(1), "linear")], 1.0,
                  {"kind": "dynamics", "model": "control_affine", "learned_components": [1],
                   "input_matrix": [[_B2]]})
    kap = _lqr_controller(s, jacobian_from_data(s))
    alone = prove_inner_ellipse_from_data(s, kap, 0.4)
    assert alone["status"].startswith("not proved")
    res = prove_inner_ellipse_from_data(s, kap, 0.4, dynamics=phi, eta=1e-12)
    assert res["status"] == "certified", res["status"]
    part = res["phi_part"]
    assert part["status"] == "verified" and 0 < part["inner_level"] < res["level"]
    assert "learned φ" in res["proved_from"] and "H = 16" in res["proved_from"]
    assert res["level"] >= np.max(np.linalg.eigvalsh(res["P"])) * 0.4**2
    assert _max_decrease(res, s.evaluate, kap.numpy) < 0
    # a large η leaves the outer part unproved: said so, never certified (the margin is
    # η·|(2Px)₁|, the learned component's only: η = 5 is still proved, 10 is not)
    res = prove_inner_ellipse_from_data(s, kap, 0.4, dynamics=phi, eta=10.0)
    assert res["status"].startswith("not proved") and "learned φ" in res["status"]
    # an ellipse that leaves the box where H (and η) hold is refused
    res = prove_inner_ellipse_from_data(s, kap, 1.0, dynamics=phi, eta=1e-12)
    assert res["status"].startswith("not proved") and "leaves the" in res["status"]
