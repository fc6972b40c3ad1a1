"""Systems without a model: callables, sample files (regular grids, exact δ), declarations."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import systems
from nlyap_opt.kernel.errors import ConfigError, DimensionError, EquilibriumError
from nlyap_opt.learned.dynamics import Grid
from systems import Declarations, ModelUnavailableError, SampleSet, check_declarations

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _example(name):
    spec = importlib.util.spec_from_file_location(f"_ex_{name}", EXAMPLES / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def bb():
    return _example("blackbox_pendulum")


def _pend(X, U):
    return np.stack([X[:, 1], 19.62 * np.sin(X[:, 0]) - X[:, 1] + U[:, 0]], axis=1)


def _callable_pendulum(**kw):
    args = dict(nx=2, nu=1, state_box=[[-1, 1], [-1, 1]], input_box=[[-2, 2]], u_eq=[0.0])
    args.update(kw)
    return systems.System.from_callable("p", _pend, **args)


# ============================================================================ kinds
def test_callable_system_has_no_model_and_says_so():
    s = _callable_pendulum(known_rhs={0: lambda x, u: x[1]})
    assert s.kind == "callable" and not s.has_model
    for attr in ("A", "B", "f", "f_fun"):
        with pytest.raises(ModelUnavailableError, match="is unknown.*black-box callable"):
            getattr(s, attr)
    assert not hasattr(s, "A")  # an AttributeError: feature tests see "no model"
    with pytest.raises(ModelUnavailableError):
        s.closed_loop()
    with pytest.raises(ModelUnavailableError):
        s.evaluate_torch(None)
    X = np.array([[0.3, -0.2], [0.0, 1.0]])
    U = np.array([[1.0], [-1.0]])
    np.testing.assert_array_equal(s.evaluate(X, U), _pend(X, U))
    assert s.known_state_derivatives == (0,)
    assert str(s.known_rhs[0]) == str(s.x[1])
    traj = s.simulate(lambda x: -30.0 * x[:, :1] - 5 * x[:, 1:], [[0.2, 0.0]], 4.0, n_steps=400)
    assert np.abs(traj[-1]).max() < 0.05  # the callable can be simulated


def test_model_system_unchanged():
    s = systems.get("inverted_pendulum")
    assert s.kind == "model" and s.has_model
    assert s.known_rhs == {0: s.f[0]} or str(s.known_rhs[0]) == str(s.f[0])
    np.testing.assert_allclose(s.B.ravel(), [0.0, 1 / (0.15 * 0.25)])
    assert s.declarations is None and s.run_overrides == {}


def test_callable_checks():
    with pytest.raises(EquilibriumError, match=r"f\(0, u_eq=\[0.5\]\).*tolerance 1e-09"):
        _callable_pendulum(u_eq=[0.5])
    s = _callable_pendulum(u_eq=[1e-12])  # within the stated tolerance
    assert s.u_eq[0] == 1e-12
    with pytest.raises(ConfigError, match="declare the equilibrium input u_eq"):
        _callable_pendulum(u_eq=None)
    with pytest.raises(ConfigError, match="known component x1' .* disagrees"):
        _callable_pendulum(known_rhs={0: lambda x, u: 2 * x[1]})
    with pytest.raises(ConfigError, match="uses symbols other than"):
        _callable_pendulum(known_rhs={0: ca.SX.sym("w")})
    bad = systems.System.from_callable(
        "b", lambda X, U: X[:, :1], nx=1, nu=0, state_box=[[-1, 1]])
    bad._callable = lambda X, U: X.T  # wrong shape after construction
    with pytest.raises(DimensionError, match="must return"):
        bad.evaluate(np.zeros((3, 1)))


def test_samples_system_lookup_only_at_nodes():
    smp = systems.sample_function(_pend, [[-1, 1], [-1, 1], [-2, 2]], [5, 5, 5], nx=2)
    s = systems.System.from_samples("ps", smp, u_eq=[0.0], known_rhs={0: lambda x, u: x[1]})
    assert s.kind == "samples" and not s.has_model and not s.can_simulate
    assert s.summary()["samples"]["counts"] == [5, 5, 5]
    z = smp.points([7, 60])
    np.testing.assert_array_equal(s.evaluate(z[:, :2], z[:, 2:]), _pend(z[:, :2], z[:, 2:]))
    with pytest.raises(ConfigError, match="not a node of the sample grid"):
        s.evaluate([[0.1, 0.0]], [[0.0]])
    with pytest.raises(ModelUnavailableError, match="samples"):
        s.simulate(None, [[0.1, 0.0]], 1.0)
    with pytest.raises(ModelUnavailableError):
        s.A
    with pytest.raises(ConfigError, match="differs from the sample grid's box"):
        systems.System.from_samples("ps", smp, u_eq=[0.0], state_box=[[-2, 2], [-1, 1]])


def test_samples_without_equilibrium_node_refused():
    smp = systems.sample_function(_pend, [[-1, 1], [-1, 1], [-2, 2]], [4, 5, 5], nx=2)
    with pytest.raises(ConfigError, match=r"no node at \(x = 0, u = u_eq"):
        systems.System.from_samples("ps", smp, u_eq=[0.0])
    shifted = systems.sample_function(lambda X, U: _pend(X, U) + 1.0,
                                      [[-1, 1], [-1, 1], [-2, 2]], [5, 5, 5], nx=2)
    with pytest.raises(EquilibriumError, match=r"= \[1.0, 1.0\] by the samples"):
        systems.System.from_samples("ps", shifted, u_eq=[0.0])


# ============================================================================ grids and δ
def test_callable_and_csv_give_the_same_grid_and_delta(bb, tmp_path):
    s = bb.make()
    counts = [21, 17, 9]
    grid = Grid(s.sampling_box, counts)
    vals = s.evaluate(*np.split(np.vstack(list(grid.batches())), [2], axis=1))
    path = tmp_path / "p.csv"
    systems.save_samples(path, np.vstack(list(grid.batches())), vals,
                         states=["theta", "omega"], inputs=["torque"])
    loaded = systems.load_samples(path, states=["theta", "omega"], inputs=["torque"])
    assert loaded.delta == grid.delta  # bit for bit
    assert loaded.offset == 0.0
    np.testing.assert_array_equal(loaded.box, grid.box)
    np.testing.assert_array_equal(loaded.counts, grid.counts)
    for a, b in zip(loaded.axes, grid.axes):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(loaded.gaps, grid.gaps)
    np.testing.assert_array_equal(loaded.values, vals)
    np.testing.assert_array_equal(loaded.points(np.arange(grid.size)),
                                  np.vstack(list(grid.batches())))
    # npz too, and rows in any order
    perm = np.random.default_rng(0).permutation(grid.size)
    pts = np.vstack(list(grid.batches()))
    systems.save_samples(tmp_path / "p.npz", pts[perm], vals[perm],
                         states=["theta", "omega"], inputs=["torque"])
    again = systems.load_samples(tmp_path / "p.npz", states=["theta", "omega"],
                                 inputs=["torque"])
    assert again.delta == grid.delta
    np.testing.assert_array_equal(again.values, vals)


def test_write_pendulum_csv_script_gives_model_grid(bb, tmp_path):
    mod = _example("write_pendulum_csv")
    out = tmp_path / "p.csv"
    assert mod.main(["--out", str(out), "--counts", "41", "21"]) == 0
    smp = systems.load_samples(out, states=["theta", "omega"], inputs=["torque"])
    assert smp.input_slice and smp.counts.tolist() == [41, 21, 1]
    g = Grid(bb.make().state_box, [41, 21])  # the control-affine model's x-grid
    assert smp.delta == g.delta
    x = g.points(np.arange(g.size))
    np.testing.assert_array_equal(smp.lookup(x, np.zeros((g.size, 1))),
                                  bb.make().evaluate(x, np.zeros((g.size, 1))))
    # a slice needs the declared B, and an input box
    with pytest.raises(ConfigError, match="single input level"):
        systems.System.from_samples("p", smp, u_eq=[0.0])
    s = systems.System.from_samples("p", smp, u_eq=[0.0], input_box=[[-20, 20]],
                                    declarations=bb.DECLARED)
    assert s.input_box.tolist() == [[-20.0, 20.0]]


def test_inexact_coordinates_enlarge_delta(tmp_path):
    g = Grid([[-1, 1], [-1, 1]], [11, 7])
    pts = np.vstack(list(g.batches()))
    rough = np.round(pts, 12)  # a csv printed with 12 decimals: not the float64 nodes
    vals = np.stack([pts[:, 1], -pts[:, 0]], axis=1)
    smp = SampleSet(rough, vals, nx=2)
    assert smp.offset > 0
    assert smp.delta >= g.delta + smp.offset  # covering radius of the rows actually sampled
    np.testing.assert_array_equal(smp.counts, g.counts)


@pytest.mark.parametrize("mutate, msg", [
    (lambda p, v: (np.vstack([p, p[:1]]), np.vstack([v, v[:1]])), "appears twice"),
    (lambda p, v: (p[1:], v[1:]), "incomplete: node .* is missing"),
    (lambda p, v: (np.where(p == p[3, 0], p + 0.01 * (p == p[3, 0]), p), v),
     "not equally spaced"),
    (lambda p, v: (p, np.where(np.arange(len(v))[:, None] == 5, np.nan, v)), "is nan"),
    (lambda p, v: (np.where(np.arange(len(p))[:, None] == 2, np.inf, p), v), "is inf"),
])
def test_bad_grids_refused(mutate, msg):
    g = Grid([[-1, 1], [0, 1]], [5, 4])
    pts = np.vstack(list(g.batches()))
    vals = np.stack([pts[:, 1], -pts[:, 0]], axis=1)
    p, v = mutate(pts, vals)
    with pytest.raises(ConfigError, match=msg):
        SampleSet(p, v, nx=2)


def test_irregular_axis_message():
    pts = np.array([[0.0], [0.1], [0.3]])
    with pytest.raises(ConfigError, match=r"coordinate 0.1 is .* from the nearest node 0.15"):
        SampleSet(pts, pts, nx=1)


# ============================================================================ declarations
@pytest.fixture(scope="module")
def pend_samples():
    return systems.sample_function(_pend, [[-1, 1], [-1, 1], [-2, 2]], [21, 21, 11], nx=2,
                                   names=["theta", "omega", "u"])


def test_declared_lipschitz_below_slope_refused(pend_samples):
    est = check_declarations(pend_samples, pend_samples.values, Declarations(lipschitz=25.0))
    slope = est["slope"]
    assert 19.0 < slope < 22.5  # ~ |∂f2/∂θ| = 19.62 cos θ, combined with the ω and u slopes
    with pytest.raises(ConfigError) as err:
        check_declarations(pend_samples, pend_samples.values, Declarations(lipschitz=5.0),
                           names=pend_samples.names)
    msg = str(err.value)
    assert "declared K_f = 5 is below the finite-difference slope" in msg
    assert f"{slope:.6g}" in msg and "declare K_f ≥" in msg and "\n" not in msg
    # just above the slope passes; just below fails: the check can fail
    check_declarations(pend_samples, pend_samples.values, Declarations(lipschitz=slope))
    with pytest.raises(ConfigError):
        check_declarations(pend_samples, pend_samples.values,
                           Declarations(lipschitz=slope * (1 - 1e-4)))
    with pytest.raises(ConfigError, match=r"component 1 \(omega'\) = 10"):
        check_declarations(pend_samples, pend_samples.values,
                           Declarations(lipschitz=[1.5, 10.0]), names=pend_samples.names)


def test_declared_hessian_and_input_matrix(pend_samples):
    est = check_declarations(pend_samples, pend_samples.values,
                             Declarations(hessian=19.7, input_matrix=[[0.0], [1.0]]))
    assert 15.0 < est["second_difference"] <= 19.62  # |∂²f2/∂θ²| = 19.62 |sin θ|
    assert est["input_matrix_error"] < 1e-12
    with pytest.raises(ConfigError, match=r"declared H = 10 is below .*∂²f_1/∂theta∂theta"):
        check_declarations(pend_samples, pend_samples.values, Declarations(hessian=10.0),
                           names=pend_samples.names)
    with pytest.raises(ConfigError, match="input matrix B is contradicted"):
        check_declarations(pend_samples, pend_samples.values,
                           Declarations(input_matrix=[[0.0], [1.1]]))
    # a system that is not control-affine is caught with the right B at the origin
    nonaff = systems.sample_function(
        lambda X, U: np.stack([X[:, 1], U[:, 0] + 0.5 * U[:, 0] ** 2 * X[:, 0]], 1),
        [[-1, 1], [-1, 1], [-2, 2]], [5, 5, 5], nx=2)
    with pytest.raises(ConfigError, match="not control-affine"):
        check_declarations(nonaff, nonaff.values, Declarations(input_matrix=[[0.0], [1.0]]))


def test_exact_linear_data_not_refused_by_rounding():
    smp = systems.sample_function(lambda X, U: np.stack([2 * X[:, 0], 0 * X[:, 1]], 1),
                                  [[-1, 1], [-1, 1]], [101, 11], nx=2)
    est = check_declarations(smp, smp.values, Declarations(lipschitz=2.0, hessian=1e-300))
    assert est["slope"] <= 2.0 * (1 + 1e-9)


def test_samples_system_checks_declarations_on_load(pend_samples):
    with pytest.raises(ConfigError, match="declared K_f = 3"):
        systems.System.from_samples("p", pend_samples, u_eq=[0.0],
                                    declarations=Declarations(lipschitz=3.0))


def test_declarations_describe_and_bound():
    d = Declarations(lipschitz=[1.0, 34.0], hessian=26.0, input_matrix=[[0.0], [26.5]])
    lines = d.describe(["theta", "omega"], ["torque"])
    assert len(lines) == 3
    assert "theta': 1, omega': 34" in lines[0]
    assert "H = 26" in lines[1] and "B = [0; 26.5]" in lines[2]
    assert d.lipschitz_bound() >= np.hypot(1.0, 34.0)
    assert d.lipschitz_bound([1]) >= 34.0
    assert Declarations().empty and Declarations().describe() == []
    for bad in ({"lipschitz": -1}, {"lipschitz": "a"}, {"hessian": float("nan")},
                {"input_matrix": [[1.0], [float("inf")]]}):
        with pytest.raises(ConfigError, match="declared"):
            Declarations(**bad)
    with pytest.raises(ConfigError, match=r"shape \(1, 1\); the system needs \(2, 1\)"):
        _callable_pendulum(declarations=Declarations(input_matrix=[[1.0]]))


def test_blackbox_example_declarations_hold(bb):
    s = bb.make()
    lines = s.describe_assumptions()
    assert s.kind == "callable" and len(lines) == 6
    assert lines[3].startswith("Data (assumed): the black-box callable returns the exact")
    assert lines[4].startswith("Equilibrium (declared): f(0, u_eq) = 0 with u_eq = [0.0]")
    assert lines[5].startswith("Known components (declared, checked on the data): theta' = "
                               "omega")
    est = s.check_declarations(Grid(s.sampling_box, [41, 41, 5]))
    assert est["slope"] < 34.5 and est["second_difference"] < 26.0


def test_known_function_for_every_kind():
    for s in (systems.get("inverted_pendulum"),
              _callable_pendulum(known_rhs={"x1": lambda x, u: x[1]})):
        kf = s.known_function()
        assert kf(ca.DM([0.3, -0.7]), ca.DM([0.1])).full().ravel().tolist() == [-0.7]
    assert _callable_pendulum().known_function().numel_out() == 0


def test_sample_error_declaration():
    d = Declarations(lipschitz=1.0, sample_error=1e-3)
    assert d.describe()[-1].startswith("Sample error (declared)")
    s = _callable_pendulum(declarations=d)
    assert not any(x.startswith("Data (assumed)") for x in s.describe_assumptions())
    for bad in (-1.0, float("inf"), "x", True):
        with pytest.raises(ConfigError, match="sample_error"):
            Declarations(sample_error=bad)
    # noise up to sample_error does not make a correct K_f look wrong
    smp = systems.sample_function(lambda X, U: X + 1e-3 * np.sin(1e4 * X), [[-1, 1]], [201],
                                  nx=1)
    with pytest.raises(ConfigError):
        check_declarations(smp, smp.values, Declarations(lipschitz=1.0))
    check_declarations(smp, smp.values, Declarations(lipschitz=1.0, sample_error=1e-3))


def test_sample_set_is_a_drop_in_grid(rng):
    g = Grid([[-1, 1], [0, 2], [-3, 3]], [7, 5, 3])
    smp = systems.sample_function(lambda X, U: X[:, :2] * U, g.box, g.counts, nx=2)
    np.testing.assert_array_equal(smp.sample(10, np.random.default_rng(1)),
                                  g.sample(10, np.random.default_rng(1)))
    assert [b.tolist() for b in smp.batches(17)] == [b.tolist() for b in g.batches(17)]
    for key in ("box", "counts", "spacing", "size", "delta"):
        assert smp.to_dict()[key] == g.to_dict()[key]


def test_blackbox_declared_constants_are_true(bb):
    """K_f and H of the example hold for its formula (dense evaluation of the derivatives)."""
    th, om = np.meshgrid(np.linspace(-4, 4, 801), np.linspace(-4, 4, 801), indexing="ij")
    k, c, inertia = bb.K_SMOOTH, bb.C_COUL, bb.INERTIA
    sech2 = 1.0 / np.cosh(k * om) ** 2
    j_th = bb.G / bb.L * np.cos(th)                     # ∂ω'/∂θ
    j_om = -(bb.B_VISC + c * k * sech2) / inertia       # ∂ω'/∂ω
    j_u = 1.0 / inertia                                 # ∂ω'/∂u
    # ‖J‖₂ ≤ ‖J‖_F, rows (0, 1, 0) and (j_th, j_om, j_u)
    assert np.sqrt(1.0 + j_th**2 + j_om**2 + j_u**2).max() <= 34.5
    d2_th = np.abs(bb.G / bb.L * np.sin(th))
    d2_om = np.abs(c * 2 * k**2 * np.tanh(k * om) * sech2 / inertia)
    assert max(d2_th.max(), d2_om.max()) <= 26.0
    assert bb.DECLARED.B[1, 0] == 1.0 / inertia


def test_csv_with_bom_and_crlf(tmp_path):
    g = Grid([[-1, 1]], [3])
    path = tmp_path / "a.csv"
    path.write_bytes("\ufeffx,x_dot\r\n-1.0,1.0\r\n0.0,0.0\r\n1.0,-1.0\r\n".encode("utf-8"))
    smp = systems.load_samples(path, states=["x"])
    assert smp.delta == g.delta and smp.values.ravel().tolist() == [1.0, 0.0, -1.0]


def test_check_on_a_state_grid_with_declared_b(bb):
    s = bb.make()
    g = Grid(s.state_box, [41, 41])  # the control-affine model's grid over x
    x = g.points(np.arange(g.size))
    vals = s.evaluate(x, np.zeros((g.size, 1)))
    est = check_declarations(g, vals, bb.DECLARED)
    assert est["input_matrix_error"] is None and est["slope"] < 34.5
    with pytest.raises(ConfigError, match="declared K_f = 10"):
        check_declarations(g, vals, Declarations(lipschitz=10.0, input_matrix=[[0], [1]]))


# ============================================================================ Jacobian from data
def test_jacobian_from_data_contains_the_true_jacobian(bb):
    from systems.jacobian import jacobian_from_data

    truth = np.array([[0.0, 1.0, 0.0],
                      [bb.G / bb.L, -(bb.B_VISC + bb.C_COUL * bb.K_SMOOTH) / bb.INERTIA,
                       1.0 / bb.INERTIA]])
    c = bb.make()
    jb = jacobian_from_data(c)  # callable: tiny steps, tiny error
    assert np.all(np.abs(jb.J - truth) <= jb.error) and jb.error.max() < 1e-3
    smp = systems.sample_function(c.evaluate, c.sampling_box, [41, 41, 21], nx=2)
    s = systems.System.from_samples("p", smp, u_eq=[0.0], declarations=bb.DECLARED)
    jb = jacobian_from_data(s)  # grid spacing 0.2: error H h / 2 = 2.6
    assert jb.source == "samples" and np.all(np.abs(jb.J - truth) <= jb.error)
    np.testing.assert_allclose(jb.error[:, 0], 26.0 * 0.2 / 2, rtol=1e-12)
    assert np.all(jb.error > 0)
    # the bound is not loose by orders of magnitude: the true error is a sizeable part of it
    assert np.abs(jb.J - truth).max() > 0.05 * jb.error.max()
    # a model (evaluated as a black box) agrees with its own linearisation
    m = systems.get("inverted_pendulum")
    m.declarations = Declarations(hessian=20.0)
    jm = jacobian_from_data(m, step=1e-3)
    assert np.all(np.abs(jm.J - np.hstack([m.A, m.B])) <= jm.error)
    with pytest.raises(ConfigError, match="declare hessian"):
        jacobian_from_data(_callable_pendulum())


def test_jacobian_from_slice_uses_declared_b(bb, tmp_path):
    from systems.jacobian import jacobian_from_data

    s = bb.make()
    g = Grid(s.state_box, [41, 41])
    x = g.points(np.arange(g.size))
    smp = SampleSet(np.hstack([x, np.zeros((g.size, 1))]), s.evaluate(x, np.zeros((g.size, 1))),
                    nx=2, nu=1)
    ps = systems.System.from_samples("p", smp, u_eq=[0.0], input_box=[[-20, 20]],
                                     declarations=bb.DECLARED)
    jb = jacobian_from_data(ps)
    np.testing.assert_array_equal(jb.B, bb.DECLARED.B)
    assert np.all(jb.error[:, 2] == 0)
    edge = SampleSet(np.hstack([x[x[:, 0] >= 0], np.zeros((int(np.sum(x[:, 0] >= 0)), 1))]),
                     s.evaluate(x[x[:, 0] >= 0], np.zeros((int(np.sum(x[:, 0] >= 0)), 1))),
                     nx=2, nu=1)
    # the origin on the grid's boundary: refused when the system is built
    with pytest.raises(ConfigError, match="does not contain the origin in its interior"):
        systems.System.from_samples("e", edge, u_eq=[0.0], input_box=[[-20, 20]],
                                    declarations=bb.DECLARED)


def test_declared_hessian_per_component(pend_samples):
    """One H per state derivative: θ' = ω is linear (H = 0 holds), ω' has |∂²f/∂θ²| up to
    19.62; each component is checked against its own bound, and the shapes are validated."""
    d = Declarations(hessian=[0.0, 19.7])
    check_declarations(pend_samples, pend_samples.values, d)
    assert d.hessian_of(0) == 0.0 and d.hessian_max() == 19.7
    assert d.to_dict()["hessian"] == [0.0, 19.7]
    assert "theta': 0, omega': 19.7" in d.describe(["theta", "omega"])[0]
    with pytest.raises(ConfigError, match=r"declared H = 10 is below .*∂²f_1/∂theta∂theta"):
        check_declarations(pend_samples, pend_samples.values, Declarations(hessian=[100.0, 10.0]),
                           names=pend_samples.names)
    with pytest.raises(ConfigError, match=r"declared H = 0 is below .*∂²f_1"):
        check_declarations(pend_samples, pend_samples.values, Declarations(hessian=[19.7, 0.0]),
                           names=pend_samples.names)
    for bad, words in (([1.0, -1.0], ">= 0"), ([True, 1.0], "not strings or booleans"),
                       ([[1.0]], "one number per state")):
        with pytest.raises(ConfigError, match=words):
            Declarations(hessian=bad)
    with pytest.raises(ConfigError, match="declared hessian has 3 entries"):
        Declarations(hessian=[1.0, 2.0, 3.0]).validate(2, 1)
