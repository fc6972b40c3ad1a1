"""Learned dynamics and η for systems without a model: a black-box callable and sample files.

The black-box pendulum (``examples/blackbox_pendulum.py``) and the same pendulum from a
sample file must give the same grid, the same δ and the same η; δ must be the sample
file's (including its offset from the regular nodes: a δ of the nominal grid is too
small), α must be measured on exactly the sample nodes, and what needs a model is skipped
with a reason, never faked.
"""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

import systems
from nlyap_opt.kernel.errors import ConfigError
from nlyap_opt.learned.dynamics import Grid, learn_dynamics
from nlyap_opt.learned.dynamics_stage import dynamics_stage
from nlyap_opt.learned.error_models import compute_bounds

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

#: a fast configuration (seconds); the grid is given for the callable, the file's for samples.
#: It relies on the default ``lm_ridge`` (1e-8): with 1e-14, 30 LM iterations from 200 Adam
#: steps ended in a fit that depends on the CPU's BLAS kernel: K_φ = 24 (η 1.4) on
#: OpenBLAS's SkylakeX and Sandybridge kernels, a steep neuron with K_φ = 322 (η 52) on its
#: Haswell and Zen kernels; with 1e-8 all four give η = 1.419 (OPENBLAS_CORETYPE set to each)
FAST = {"preset": "fast", "progress": False, "hidden": 12, "train_points": 600,
        "boundary_points": 100, "steps": 200, "lm_iterations": 30, "minimax_rounds": 1,
        "minimax_iterations": 5, "interval_boxes": 1024, "check_points": 20000}


def _example(name: str):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def pend():
    return _example("blackbox_pendulum")


def _slice_samples(pend, counts, path: Path, fmt=repr):
    """The black box on the slice u = 0 of Grid(X, counts), written to ``path`` (csv)."""
    s = pend.make()
    g = Grid(s.state_box, counts)
    X = np.vstack(list(g.batches()))
    U = np.zeros((X.shape[0], 1))
    F = s.evaluate(X, U)
    with open(path, "w") as fh:
        fh.write("theta,omega,torque,theta_dot,omega_dot\n")
        for row in np.hstack([X, U, F]):
            fh.write(",".join(fmt(float(v)) for v in row) + "\n")
    return systems.load_samples(path, states=["theta", "omega"], inputs=["torque"])


def _from_samples(pend, smp, **decl):
    d = pend.DECLARED if not decl else systems.Declarations(**decl)
    return systems.System.from_samples(
        "pendulum_samples", smp, input_box=[[-20.0, 20.0]], u_eq=[0.0],
        known_rhs={"theta": lambda x, u: x[1]}, declarations=d)


def test_callable_and_sample_file_give_the_same_delta_and_eta(pend, tmp_path):
    black = pend.make()
    smp = _slice_samples(pend, [41, 41], tmp_path / "p.csv")
    sampled = _from_samples(pend, smp)
    assert smp.offset == 0.0
    st_c = dynamics_stage(black, FAST | {"model": "control_affine", "grid_counts": [41, 41]},
                          log=None)
    st_s = dynamics_stage(sampled, FAST | {"model": "control_affine"}, log=None)
    for st in (st_c, st_s):
        assert st.status == "ok"
        assert np.isfinite(st.eta) and st.eta < 5.0
        assert st.bounds.K_f.value == 34.5                      # the declared K_f
        assert "anisotropic" in st.bounds.skipped               # needs a model: skipped
        assert "CasADi model" in st.bounds.skipped["anisotropic"]
        d = st.bounds.to_dict()
        assert d["K_f_source"] == "declared" and d["options_skipped"]
        json.dumps(d, allow_nan=False, default=str)
    # the same δ, the same nodes, hence the same φ and the same η (bit for bit)
    assert st_c.grid.delta == st_s.grid.delta == Grid(black.state_box, [41, 41]).delta
    assert st_c.alpha.alpha == st_s.alpha.alpha
    assert st_c.eta == st_s.eta
    # an off-grid test of the bound exists for the callable only
    chk_c, chk_s = st_c.bounds.to_dict()["check"], st_s.bounds.to_dict()["check"]
    assert chk_c["passed"] is True and chk_c["eta_sampled"] <= st_c.eta
    assert chk_s["passed"] is None and "not available" in chk_s["note"]
    # the declarations were checked on the data and the estimates saved with φ
    est = st_c.network.meta["declarations_check"]
    assert 0 < est["slope"] <= 34.5 and est["second_difference"] <= 26.0


def test_full_model_on_a_sample_grid_measures_alpha_on_exactly_its_nodes(pend):
    black = pend.make()
    counts = [15, 15, 5]
    smp = systems.sample_function(black.evaluate, black.sampling_box, counts, nx=2,
                                  names=["theta", "omega", "torque"])
    sampled = systems.System.from_samples(
        "pendulum_full", smp, u_eq=[0.0], known_rhs={"theta": lambda x, u: x[1]},
        declarations=systems.Declarations(lipschitz=34.5, hessian=26.0))
    res = learn_dynamics(sampled, FAST | {"model": "full"})
    assert res.grid is smp and res.grid.delta == smp.delta
    assert smp.delta == Grid(black.sampling_box, counts).delta
    assert res.alpha.n_points == smp.size
    # α by hand: every sample node, the file's values, the saved network
    z = smp.points(np.arange(smp.size))
    e = smp.values[:, res.learned_components] - res.network.numpy(z)
    assert res.alpha.alpha == pytest.approx(np.max(np.linalg.norm(e, axis=1)), rel=0, abs=0)
    b = compute_bounds(sampled, res.network, res.grid, res.alpha, boxes=256,
                       check_points=100)
    assert np.isfinite(b.eta) and b.selected in ("global", "second_order")
    assert b.options["global"].terms["delta"] == smp.delta
    assert np.isnan(b.eta_sampled)  # samples: no off-grid values


def test_sample_file_offset_enters_delta_and_disables_interpolation(pend, tmp_path):
    # 6 significant digits: rows sit off the regular nodes by up to ~5e-6
    smp = _slice_samples(pend, [21, 21], tmp_path / "p6.csv", fmt=lambda v: f"{v:.6g}")
    assert smp.offset > 0
    sampled = _from_samples(pend, smp)
    st = dynamics_stage(sampled, FAST | {"model": "control_affine"}, log=None)
    g0 = Grid(sampled.state_box, [21, 21])
    assert st.grid.delta == smp.delta > g0.delta           # δ includes the offset
    assert st.grid.delta >= g0.delta + smp.offset
    assert "second_order" in st.bounds.skipped and "offset" in st.bounds.skipped["second_order"]
    glob = st.bounds.options["global"]
    assert st.bounds.selected == "global" and glob.terms["delta"] == st.grid.delta
    assert any("offset" in a for a in glob.assumptions)


def test_a_declared_lipschitz_constant_below_the_data_is_refused_before_training(pend):
    wrong = systems.System.from_callable(
        "pend_wrong_K", pend.pendulum_rhs, nx=2, nu=1, state_box=[[-4, 4], [-4, 4]],
        input_box=[[-20, 20]], u_eq=[0.0], known_rhs={0: lambda x, u: x[1]},
        declarations=systems.Declarations(lipschitz=5.0, hessian=26.0,
                                          input_matrix=[[0.0], [1 / pend.INERTIA]]))
    with pytest.raises(ConfigError, match=r"declared K_f = 5 is below the finite-difference"):
        learn_dynamics(wrong, FAST | {"model": "control_affine", "grid_counts": [21, 21],
                                      "steps": 10**6})  # would take minutes if it trained


def test_without_declarations_no_bound_is_faked(pend):
    bare = systems.System.from_callable(
        "pend_bare", pend.pendulum_rhs, nx=2, nu=1, state_box=[[-4, 4], [-4, 4]],
        input_box=[[-20, 20]], u_eq=[0.0], known_rhs={0: lambda x, u: x[1]})
    with pytest.raises(ConfigError, match="declare input_matrix"):
        learn_dynamics(bare, FAST | {"model": "control_affine", "grid_counts": [11, 11]})
    res = learn_dynamics(bare, FAST | {"model": "full", "grid_counts": [7, 7, 3],
                                       "steps": 20, "lm_iterations": 2})
    with pytest.raises(ConfigError, match="no sound bound") as exc:
        compute_bounds(bare, res.network, res.grid, res.alpha, boxes=64, check_points=10)
    assert "K_f" in str(exc.value) and "hessian" in str(exc.value)
    # only H declared: the second-order option alone, global skipped with its reason
    only_h = systems.System.from_callable(
        "pend_h", pend.pendulum_rhs, nx=2, nu=1, state_box=[[-4, 4], [-4, 4]],
        input_box=[[-20, 20]], u_eq=[0.0], known_rhs={0: lambda x, u: x[1]},
        declarations=systems.Declarations(hessian=26.0))
    b = compute_bounds(only_h, res.network, res.grid, res.alpha, boxes=64, check_points=10)
    assert list(b.options) == ["second_order"] and "lipschitz" in b.skipped["global"]
    assert np.isnan(b.K_f.value) and "not available" in b.K_f.method
    with pytest.raises(ConfigError, match="not available"):
        compute_bounds(only_h, res.network, res.grid, res.alpha, select="global", boxes=64)


def test_sample_grid_config_mismatches_are_refused(pend, tmp_path):
    smp = _slice_samples(pend, [11, 11], tmp_path / "p.csv")
    sampled = _from_samples(pend, smp)
    with pytest.raises(ConfigError, match="single input level"):
        learn_dynamics(sampled, FAST | {"model": "full"})
    with pytest.raises(ConfigError, match="grid_counts"):
        learn_dynamics(sampled, FAST | {"model": "control_affine", "grid_counts": [21, 21]})
    with pytest.raises(ConfigError, match="state_box"):
        learn_dynamics(sampled, FAST | {"model": "control_affine",
                                        "state_box": [[-2, 2], [-2, 2]]})


def test_declared_sample_error_is_added_to_alpha(pend):
    noisy = systems.System.from_callable(
        "pend_noisy", pend.pendulum_rhs, nx=2, nu=1, state_box=[[-4, 4], [-4, 4]],
        input_box=[[-20, 20]], u_eq=[0.0], known_rhs={0: lambda x, u: x[1]},
        declarations=systems.Declarations(lipschitz=34.5, input_matrix=[[0.0], [1 / 0.0375]],
                                          sample_error=0.01))
    res = learn_dynamics(noisy, FAST | {"model": "control_affine", "grid_counts": [11, 11],
                                        "steps": 20, "lm_iterations": 2})
    assert res.alpha.alpha_upper >= res.alpha.alpha + 0.01


def test_stage_of_a_sample_file_saves_and_reloads(pend, tmp_path):
    from nlyap_opt.kernel.network import Network

    smp = _slice_samples(pend, [21, 21], tmp_path / "p.csv")
    st = dynamics_stage(_from_samples(pend, smp), FAST | {"model": "control_affine"}, log=None)
    net_path, b_path = st.save(tmp_path / "out")
    net = Network.load(net_path)
    assert net.meta["declarations_check"]["slope"] > 0
    assert net.meta["grid"]["delta"] == smp.delta
    d = json.loads(b_path.read_text())
    assert d["delta"] == smp.delta and d["eta"] == st.eta and d["gate"]["status"] == "ok"
    assert d["grid"]["box"] == smp.box[:2].tolist()
    assert d["options_skipped"]["anisotropic"] and d["check"]["passed"] is None


def test_a_declared_input_matrix_that_the_black_box_contradicts_is_refused(pend):
    wrong = systems.System.from_callable(
        "pend_wrong_B", pend.pendulum_rhs, nx=2, nu=1, state_box=[[-4, 4], [-4, 4]],
        input_box=[[-20, 20]], u_eq=[0.0], known_rhs={0: lambda x, u: x[1]},
        declarations=systems.Declarations(lipschitz=34.5, input_matrix=[[0.0], [20.0]]))
    with pytest.raises(ConfigError, match="declared input matrix B is contradicted"):
        learn_dynamics(wrong, FAST | {"model": "control_affine", "grid_counts": [11, 11]})


# ------------------------------------------------------ declared dependencies (issue 15)
#: the cartpole's learned derivatives read (θ, ω, force) only; p' = v and θ' = ω are known
CARTPOLE_DEPS = {"v": ["theta", "omega", "force"], "omega": ["theta", "omega", "force"]}


def _bb_cartpole(depends_on=None, name="bb_cartpole"):
    """The catalogue cartpole as a black box (a callable), with declared K_f, H (generous
    bounds of the true ones on X × U) and, optionally, its dependency structure."""
    cp = systems.get("cartpole")
    return systems.System.from_callable(
        name, cp.evaluate, nx=4, nu=1, state_box=cp.state_box, input_box=cp.input_box,
        u_eq=[0.0], state_names=cp.state_names, input_names=cp.input_names,
        known_rhs={"p": lambda x, u: x[1], "theta": lambda x, u: x[3]},
        declarations=systems.Declarations(lipschitz=100.0, hessian=200.0,
                                          depends_on=depends_on))


def test_declared_dependencies_shape_phi_and_drop_H_along_the_ignored_axes():
    """A black box with no model: with ``depends_on`` declared, each block of φ reads only
    its component's variables (exact zero weights on p and v), and the second-order bound
    drops H along p and v, where f_k − φ_k is constant; a 2-node grid along them then
    costs nothing. The bound still holds off the grid (the stage's sampled check), and the
    declaration is listed among the certificate's assumptions."""
    cfg = FAST | {"model": "full", "grid_counts": [2, 2, 17, 17, 41], "inputs": "model"}
    st_all = dynamics_stage(_bb_cartpole(), cfg, log=None)
    bb = _bb_cartpole(CARTPOLE_DEPS)
    st_dec = dynamics_stage(bb, cfg, log=None)
    assert st_dec.status == st_all.status == "ok"
    W_dec = st_dec.network.layers[0].weight
    W_all = st_all.network.layers[0].weight
    assert np.all(W_dec[:, :2] == 0) and np.all(np.any(W_dec[:, 2:] != 0, axis=0))
    assert np.any(W_all[:, :2] != 0)
    so_dec, so_all = (st.bounds.options["second_order"] for st in (st_dec, st_all))
    D_dec, D_all = np.array(so_dec.terms["D"]), np.array(so_all.terms["D"])
    assert np.all(D_dec[:, :2] <= 1e-300) and np.all(D_all[:, :2] >= 200.0)  # 0, rounded up
    assert np.all(D_dec[:, 2:] >= 200.0)          # H stays on the variables f_k reads
    # the gaps along p and v are 2: their term H·2²/8 = 100 per axis is gone; the other
    # axes' terms are 200·(0.125² + 0.125² + 0.5²)/8 = 7 per component
    assert so_dec.terms["interpolation_term"] < 0.1 * so_all.terms["interpolation_term"]
    assert so_dec.eta < 0.1 * so_all.eta
    assert any("depends_on" in a for a in so_dec.assumptions)
    chk = st_dec.bounds.to_dict()["check"]
    assert chk["passed"] is True and chk["eta_sampled"] <= st_dec.eta
    said = [a for a in bb.describe_assumptions() if a.startswith("Dependency structure")]
    assert said == ["Dependency structure (declared): v' depends on (theta, omega, force) "
                    "only; omega' depends on (theta, omega, force) only on X × U "
                    "(∂f_k/∂z_i ≡ 0 for every other variable z_i)"]
    assert bb.declarations.to_dict()["depends_on"] == {"omega": ["theta", "omega", "force"],
                                                       "v": ["theta", "omega", "force"]}


def test_a_declared_dependency_the_samples_contradict_is_refused_before_training():
    wrong = _bb_cartpole({"v": ["omega", "force"], "omega": ["theta", "omega", "force"]},
                         name="bb_cartpole_wrong")      # v' depends on θ too
    with pytest.raises(ConfigError, match=r"declared depends_on is contradicted by the "
                                          r"samples: v' changes .* along 'theta'"):
        learn_dynamics(wrong, FAST | {"model": "full", "grid_counts": [2, 2, 5, 5, 3]})


@pytest.mark.parametrize("deps, match", [
    (["v"], "must be a table"), ({"v": "theta"}, "must be a list of variables"),
    ({"v": [1.5]}, "a name or an index"), ({True: [0]}, "a name or an index"),
    ({"vv": ["theta"]}, "names state 'vv'"), ({"v": ["thetaa"]}, "names variable 'thetaa'"),
    ({"v": [7]}, "index 7 is out of range"), ({"v": [2], 1: [3]}, "lists state 'v' twice"),
])
def test_bad_depends_on_declarations_are_config_errors(deps, match):
    with pytest.raises(ConfigError, match=match):
        _bb_cartpole(deps)
