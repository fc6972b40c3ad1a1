"""The default method: a Zubov-type target of the whole region of attraction, its inner radius.

On x' = −x + x³ (ROA |x| < 1; in 2-D, componentwise, the open square) the trajectory cost
W(x₀) = ∫₀^∞ x(t)² dt is known in closed form, W = −½ log(1 − x₀²), and the Zubov function
Z = 1 − exp(−2W) = x₀² solves ∇Z·f = −ψ(1 − Z) with ψ = 2x². These tests check the
simulated costs, the Zubov equation and the targets and decrease rates the learner fits
(:func:`nlyap_opt.candidates.cegis.cost_targets`) against that, and that the default method is
deterministic.
"""

import numpy as np
import pytest

from nlyap_opt.candidates.cegis import cost_targets
from nlyap_opt.certification.certificate import NOT_CHECKED
from nlyap_opt.kernel.errors import ConfigError
from nlyap_opt.kernel.simulate import simulate


def cubic(x):
    return -x + x ** 3


def exact_cost(x0):
    """∫₀^∞ ‖x(t)‖² dt of x' = −x + x³ (per component, summed)."""
    return np.sum(-0.5 * np.log1p(-np.asarray(x0) ** 2), axis=-1)


def test_trajectory_cost_is_the_closed_form_and_the_roa_is_where_it_is_finite():
    x0 = np.linspace(-0.95, 0.95, 39)[:, None]
    conv, cost = simulate(cubic, x0, t_final=40.0, dt=0.005, tol=1e-7)
    assert conv.all()
    np.testing.assert_allclose(cost, exact_cost(x0), rtol=2e-4, atol=1e-10)
    out = np.array([[-1.05], [1.02], [1.5]])
    conv_out, cost_out = simulate(cubic, out, t_final=40.0, dt=0.005, tol=1e-7)
    assert not conv_out.any()
    # the cost grows without bound towards the boundary |x| = 1
    near = simulate(cubic, np.array([[0.999], [0.99999]]), t_final=40.0, dt=0.005,
                    tol=1e-7)[1]
    assert near[1] > near[0] > cost.max()


def test_zubov_function_of_the_simulated_cost_solves_the_zubov_equation():
    """Z = 1 − exp(−αW) with ψ = α‖x‖²: ∇Z·f = −ψ(1 − Z), Z(0) = 0, Z → 1 at the boundary."""
    alpha = 2.0
    x = np.linspace(-0.9, 0.9, 181)[:, None]
    conv, cost = simulate(cubic, x, t_final=40.0, dt=0.005, tol=1e-7)
    assert conv.all()
    Z = 1.0 - np.exp(-alpha * cost)
    np.testing.assert_allclose(Z, x[:, 0] ** 2, atol=2e-4)   # Z = x² exactly for α = 2
    dZ = np.gradient(Z, x[:, 0])                               # ∇Z from the data
    residual = dZ * cubic(x)[:, 0] + alpha * x[:, 0] ** 2 * (1.0 - Z)
    assert np.max(np.abs(residual[2:-2])) < 2e-3
    assert abs(Z[90]) < 1e-12 and Z.max() < 1.0


@pytest.mark.parametrize("transform", ["log", "linear"])
def test_targets_decrease_along_trajectories_at_their_rates(transform):
    """cost_targets' rate R: T(x(t)) decreases at R(x)·‖x‖², the law fitted by w_pde."""
    rng = np.random.default_rng(0)
    x0 = rng.uniform(-0.9, 0.9, (200, 2))
    W0 = exact_cost(x0)
    w_c = float(np.quantile(W0, 0.9))
    T, R = cost_targets(np.ones(len(x0), bool), W0, w_c, cap=2.0, transform=transform)
    # one small step of the 2-D flow (exact cost along it: W(x(h)) = W0 − ∫₀ʰ‖x‖²)
    h = 1e-4
    x1 = x0 + h * cubic(x0)
    T1 = cost_targets(np.ones(len(x0), bool), exact_cost(x1), w_c, 2.0, transform)[0]
    live = T < 2.0
    assert live.sum() > 150
    rate = (T1 - T) / h
    want = -R * np.sum(x0 ** 2, axis=1)
    np.testing.assert_allclose(rate[live], want[live], rtol=1e-3, atol=1e-7)
    # level 1 at the cost w_c; monotone in the cost; 0 at the origin
    assert cost_targets(np.array([True]), np.array([w_c]), w_c, 2.0, transform)[0][0] == \
        pytest.approx(1.0)
    order = np.argsort(W0)
    assert np.all(np.diff(T[order]) >= 0)
    assert cost_targets(np.array([True]), np.array([0.0]), w_c, 2.0, transform)[0][0] == 0.0


def test_states_outside_the_roa_get_the_cap_and_no_rate():
    """In 2-D the ROA of the componentwise cubic is the open square (−1, 1)²: simulated
    states outside it do not converge and get the cap (rate 0), inside they converge."""
    g = np.linspace(-1.4, 1.4, 15)
    X = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    inside = np.max(np.abs(X), axis=1) < 1.0
    conv, cost = simulate(cubic, X, t_final=40.0, dt=0.01, tol=1e-6)
    np.testing.assert_array_equal(conv, inside)
    np.testing.assert_allclose(cost[inside], exact_cost(X[inside]), rtol=1e-3)
    w_c = float(np.quantile(cost[conv], 0.99))
    T, R = cost_targets(conv, cost, w_c, cap=2.0)
    assert np.all(T[~inside] == 2.0) and np.all(R[~inside] == 0.0)
    assert np.all(T[inside] <= 2.0) and np.all(R[inside & (T < 2.0)] > 0)


def test_default_method_fits_the_zubov_target_and_is_deterministic():
    """make_config(name, preset=None): the Zubov-type fit on the state box; two CEGIS runs
    of it (small budgets) give bit-identical networks and levels."""
    import systems
    from nlyap_opt.candidates.cegis import CegisConfig, cegis
    from nlyap_opt.candidates.learning import TrainConfig
    from nlyap_opt.workflow.configs import domain_of, make_config

    cfg = make_config("van_der_pol", preset=None)
    assert cfg["train"]["w_fit"] > 0 and cfg["train"]["w_pde"] > 0
    s = systems.get("van_der_pol")
    assert cfg["outer"] is None and cfg["domain"] == {"type": "box",
                                                      "box": s.state_box.tolist()}
    cfg = make_config("van_der_pol", preset=None, overrides={
        "train": {"hidden": [8], "steps": 150},
        "cegis": {"iterations": 1, "samples": 2000, "boundary_samples": 1000,
                  "inner_samples": 200, "sim_time": 10.0}})
    D, _ = domain_of(cfg, s.nx)

    def once():
        ccfg = CegisConfig(inner=cfg["inner"], outer=D.max_norm(), domain=D,
                           train=TrainConfig(**cfg["train"]), **cfg["cegis"])
        return cegis(s, None, None, ccfg, log=lambda m: None)

    a, b = once(), once()
    assert a.status == b.status and a.level == b.level
    for la, lb in zip(a.V.layers, b.V.layers):
        np.testing.assert_array_equal(la.weight, lb.weight)
        np.testing.assert_array_equal(la.bias, lb.bias)


def test_a_radius_raised_for_eta_is_listed_and_explains_a_failure():
    """An ε raised from η is an assumption of the certificate; where nothing is certified
    at it, the reason also says that a smaller η would let a smaller ε work (and which keys
    lower η). An ε scaled with a local bound's ball, or the configured one, adds no such
    advice."""
    from types import SimpleNamespace

    from nlyap_opt.certification.certificate import CertStatus, RoaCertificate
    from nlyap_opt.workflow.pipeline import _say_raised_inner

    def cert(status):
        return RoaCertificate(status, "no level certified", "test", "learned", level=0.0,
                              inner=0.4965, outer=3.0)

    ctx = SimpleNamespace(eps=0.4965, eta=0.00241, bounds_file="bounds.json", r=3.0)
    failed = cert(CertStatus.NOT_CERTIFIED)
    _say_raised_inner(failed, ctx, 0.2)
    assert failed.assumptions == ["inner radius ε = 0.4965 chosen by the tool (configured "
                                  "0.2): with η = 0.00241 the robust margin η‖∇V‖ needs it"]
    assert failed.reason == ("no level certified; ε was raised to 0.4965 (configured 0.2) "
                             "for the robust margin of η = 0.00241: a smaller η lets a "
                             "smaller ε work (dynamics.grid_counts, dynamics.steps)")
    ok = cert(CertStatus.CERTIFIED)
    _say_raised_inner(ok, ctx, 0.2)
    assert ok.reason == "no level certified" and len(ok.assumptions) == 1
    local = cert(CertStatus.NOT_CERTIFIED)
    _say_raised_inner(local, SimpleNamespace(**{**vars(ctx), "bounds_file": "bounds_local.json"}),
                      0.2)
    assert local.reason == "no level certified" and "local bound" in local.assumptions[0]
    same = cert(CertStatus.NOT_CERTIFIED)
    _say_raised_inner(same, ctx, 0.4965)
    assert same.reason == "no level certified" and same.assumptions == []


def test_inner_radius_follows_from_eta_and_the_linearisation():
    """x' = −x (2-D): A_cl = −I, P = I/2, the robust term beats the linear decrease inside
    ‖x‖ < 2ηλ_max(P) = η; the tool's ε is INNER_MARGIN_FACTOR times that, only when larger
    than the configured one, and a fixed ε gets a message naming the one that would work."""
    import casadi as ca

    import systems
    from nlyap_opt.kernel.domain import Ball
    from nlyap_opt.workflow.pipeline import INNER_MARGIN_FACTOR, _inner_for_margin

    x = ca.SX.sym("x", 2)
    s = systems.System("test_linear_decay", x, None, -x, state_box=[[-2, 2], [-2, 2]])
    D, said = Ball(2.0, 2), []
    eps = _inner_for_margin(s, None, None, 0.1, 0.05, D, True, said.append)
    assert eps == pytest.approx(INNER_MARGIN_FACTOR * 0.1, rel=1e-9)
    assert "chosen by the tool" in said[-1]
    assert _inner_for_margin(s, None, None, 0.01, 0.05, D, True, said.append) == 0.05
    # a fixed ε: a warning where the margin is thin, one line naming the ε that would work
    # where the linear decrease is already lost at ε itself
    assert _inner_for_margin(s, None, None, 0.03, 0.05, D, False, said.append) == 0.05
    assert f"set inner to {INNER_MARGIN_FACTOR * 0.03:.3g} or more" in said[-1]
    with pytest.raises(ConfigError, match=f"inner = 0.05 cannot work.*set inner to "
                                          f"{INNER_MARGIN_FACTOR * 0.1:.3g} or more") as exc:
        _inner_for_margin(s, None, None, 0.1, 0.05, D, False, said.append)
    assert "\n" not in str(exc.value)
    # an η that no ε inside the domain affords: the configured ε stays, the message says why
    assert _inner_for_margin(s, None, None, 1.0, 0.05, D, True, said.append) == 0.05
    assert "lower η" in said[-1]


def test_domain_gauge_is_one_on_the_boundary_and_homogeneous():
    """The gauge that lifts the fit target near ∂D (train.fit_domain): g(x) = max_i x_i/hi_i
    or x_i/lo_i for a box, ‖x‖/r for a ball; g(t·x) = t·g(x)."""
    from nlyap_opt.kernel.domain import Ball, Box

    B = Box([[-1.0, 2.0], [-0.5, 0.5]])
    pts = np.array([[1.0, 0.0], [-1.0, 0.25], [0.0, -0.1], [4.0, 0.0], [0.0, 0.0]])
    np.testing.assert_allclose(B.gauge(pts), [0.5, 1.0, 0.2, 2.0, 0.0], atol=1e-9)
    # the box's closed form is the bisection of the general region on contains()
    from nlyap_opt.kernel.domain import Region

    y = np.random.default_rng(2).uniform(-3, 3, (200, 2))
    np.testing.assert_allclose(B.gauge(y), Region.gauge(B, y), rtol=1e-9)
    rng = np.random.default_rng(1)
    x = rng.uniform(-3, 3, (50, 3))
    np.testing.assert_allclose(Ball(2.0, 3).gauge(x), np.linalg.norm(x, axis=1) / 2.0,
                               rtol=1e-9)
    np.testing.assert_allclose(Ball(2.0, 3).gauge(0.3 * x), 0.3 * Ball(2.0, 3).gauge(x),
                               rtol=1e-9)


def test_quadratic_sets_have_the_gauge_of_bisection_in_closed_form():
    """Balls and ellipsoids, centred or not (origin inside): the closed-form gauge is the
    root of the quadratic that bisection on ``contains`` approximates; 1 on the boundary;
    a set that does not hold the origin strictly falls back to bisection; NaN is out of
    reach."""
    from nlyap_opt.kernel.domain import Ball, Ellipsoid, Region

    rng = np.random.default_rng(3)
    x = rng.normal(size=(500, 3)) * 2.0
    Q = np.array([[2.0, 0.5, 0.0], [0.5, 1.0, 0.1], [0.0, 0.1, 3.0]])
    for D in (Ball(2.0, 3, centre=[0.5, -0.3, 0.2]), Ellipsoid(np.diag([1.0, 4.0, 0.25])),
              Ellipsoid(Q, centre=[0.1, 0.2, -0.3]), Ball(1.0, 3, centre=[2.0, 0.0, 0.0])):
        np.testing.assert_allclose(D.gauge(x), Region.gauge(D, x), rtol=1e-10)
        g = D.gauge(x)
        if np.all(np.isfinite(g)):
            np.testing.assert_allclose(D.gauge(x / g[:, None]), 1.0, rtol=1e-12)
            assert np.all(D.contains(x / (g[:, None] * (1 + 1e-9))))
            assert not np.any(D.contains(x / (g[:, None] * (1 - 1e-9))))
    assert Ellipsoid(Q).gauge(np.array([[np.nan, 0.0, 0.0], [0.0, 0.0, 0.0]])).tolist() \
        == [np.inf, 0.0]


@pytest.mark.slow
def test_reversed_van_der_pol_mu3_with_default_settings(tmp_path):
    """A peer's system with nothing but its spec file (LyZNet's box): the default method
    certifies most of the true ROA (81.3 % measured; the re-check of the saved files holds)."""
    import json
    from pathlib import Path

    from nlyap_opt.certification.certificate import recheck_certificate
    from nlyap_opt.interface.cli import main

    spec = Path(__file__).resolve().parents[1] / "examples" / "van_der_pol_mu3.toml"
    out = tmp_path / "vdp3"
    assert main(["run", str(spec), "--known-dynamics", "--out", str(out)]) == 0
    cert = json.loads((out / "certificate.json").read_text())
    assert cert["status"] == "certified" and cert["domain"]["type"] == "box"
    assert cert["certified_points_converge_in_simulation"]
    assert cert["fraction_of_true_roa"] >= 0.80
    assert recheck_certificate(out, log=lambda m: None).certified


@pytest.mark.slow
def test_catalogue_van_der_pol_box_lying_mostly_in_the_roa(tmp_path):
    """The catalogue Van der Pol box [−1.5, 1.5]² lies mostly inside the ROA: the certified
    set (in D, forward invariant) holds only states whose trajectories never leave D, 89 %
    of the true ROA in D by simulation; the default method certifies most of that (83.1 %
    measured) and never more than it."""
    import json

    import systems
    from nlyap_opt.certification.roa import grid_points
    from nlyap_opt.interface.cli import main
    from nlyap_opt.kernel.domain import Box

    out = tmp_path / "vdp"
    assert main(["run", "van_der_pol", "--preset", "default", "--known-dynamics",
                 "--out", str(out)]) == 0
    cert = json.loads((out / "certificate.json").read_text())
    assert cert["status"] == "certified" and cert["certified_points_converge_in_simulation"]
    s, D = systems.get("van_der_pol"), Box(cert["domain"]["box"])
    pts, _ = grid_points(np.asarray(cert["eval_box"]), cert["eval_grid"])
    def rhs(z):
        return s.evaluate(z, None)

    roa = simulate(rhs, pts, 60.0, 0.02, 1e-3)[0]
    stays = simulate(rhs, pts, 60.0, 0.02, 1e-3, stay=D.contains)[0]
    ceiling = stays.sum() / roa.sum()
    assert 0.85 < ceiling < 0.95
    assert cert["true_roa_stays_in_domain"] == pytest.approx(ceiling, abs=0.01)  # the report's
    assert 0.78 <= cert["fraction_of_true_roa"] <= ceiling + 0.005


def test_true_roa_estimate_says_which_states_it_could_not_decide():
    """x' = −x³ reaches ‖x‖ < 10⁻³ only after ~5·10⁵ s: within the report's horizon its
    states neither converge nor diverge (undecided, not 'outside'); x' = +x diverges."""
    import casadi as ca

    import systems
    from nlyap_opt.certification.roa import TRUE_ROA_TIME, true_roa_mask

    x = ca.SX.sym("x", 2)
    box = np.array([[-1.0, 1.0], [-1.0, 1.0]])
    slow = systems.System("test_slow", x, None, -x ** 3, state_box=box)
    mask, open_, rest = true_roa_mask(slow, None, box, 11, undecided=True)
    assert TRUE_ROA_TIME == 60.0
    assert not mask[np.abs(np.linspace(-1, 1, 11)) > 0.2].any()
    assert open_.sum() == 11 * 11 - 1 and not open_[5, 5] and mask[5, 5]   # 0 itself
    assert not rest.any()        # slow, not at rest: the Newton step is x/3 > 10⁻³ long
    fast_out = systems.System("test_diverge", x, None, x, state_box=box)
    mask, open_, rest = true_roa_mask(fast_out, None, box, 11, undecided=True)
    assert not open_.any() and not rest.any() and mask.sum() == 1


def test_true_roa_estimate_tells_states_at_rest_at_another_equilibrium():
    """The damped pendulum θ'' = −sin θ − 0.5θ' on [−7, 7]²: states that settle at θ = ±2π
    (stable: eigenvalues −0.25 ± 0.97i) are decided outside the ROA, not 'undecided'; the
    saddles θ = ±π attract only a curve; a periodic orbit is never claimed at rest."""
    import casadi as ca

    import systems
    from nlyap_opt.certification.roa import true_roa_mask
    from nlyap_opt.kernel.simulate import at_other_equilibrium

    x = ca.SX.sym("x", 2)
    box = np.array([[-7.0, 7.0], [-7.0, 7.0]])
    pend = systems.System("test_pend", x, None, ca.vertcat(x[1], -ca.sin(x[0]) - 0.5 * x[1]),
                          state_box=box)
    mask, open_, rest = true_roa_mask(pend, None, box, 21, undecided=True)
    assert rest.sum() > 100 and not (rest & mask).any() and not open_.any()
    c = -7 + 14 * (np.arange(21) + 0.5) / 21                         # cell centres
    th, om = np.meshgrid(c, c, indexing="ij")
    slow = np.abs(om) < 1.0
    assert mask[(np.abs(th) < 1.0) & slow].all() and rest[(np.abs(th) > 6.0) & slow].all()
    # a centre (x'' = −x): every state lies on a cycle, none at rest; the origin itself no
    centre = lambda z: np.stack([z[:, 1], -z[:, 0]], axis=1)    # noqa: E731
    pts = np.array([[1.0, 0.0], [0.0, 0.0], [3.0, 1.0]])
    assert not at_other_equilibrium(centre, pts).any()
    # x' = x − x³ rests at ±1 (rate −2); a state 10⁻² from it is not yet within tol
    bist = lambda z: z - z ** 3                                  # noqa: E731
    got = at_other_equilibrium(bist, np.array([[1.0 + 1e-5], [-1.0], [1.01], [0.0], [1e-4]]))
    assert got.tolist() == [True, True, False, False, False]


def test_report_names_states_at_rest_elsewhere_apart_from_undecided_ones():
    """The report's true-ROA paragraph: states at rest at another equilibrium are decided
    (no 'overestimate' warning); only undecided ones ask for a longer eval_time."""
    from nlyap_opt.workflow.report import _outside_states

    rest = _outside_states({"true_roa_elsewhere": 0.633, "true_roa_undecided": 0.0}, 60.0)
    assert "63.3% of the grid in D came to rest at another stable equilibrium" in rest
    assert "overestimate" not in rest and "eval_time" not in rest
    both = _outside_states({"true_roa_elsewhere": 0.1, "true_roa_undecided": 0.02}, 550.0)
    assert "2.0% of the grid in D neither converged" in both and "550 s" in both
    assert _outside_states({"true_roa_undecided": 0.0}, 60.0) == ""   # an older certificate


def test_a_lightly_damped_loop_is_simulated_long_enough_to_converge():
    """x'' = −x − 0.1x' decays at 0.05 per s: 60 s of simulated time leave most states of
    the box undecided; the horizon from its slowest mode (SLOW_FACTOR·ln(r/tol)/σ, r the
    box's largest norm) decides them, and a well-damped loop keeps its horizon."""
    import casadi as ca

    import systems
    from nlyap_opt.certification.roa import TRUE_ROA_TIME, true_roa_horizon, true_roa_mask
    from nlyap_opt.kernel.simulate import SLOW_FACTOR

    x = ca.SX.sym("x", 2)
    box = np.array([[-2.0, 2.0], [-2.0, 2.0]])
    light = systems.System("test_light", x, None, ca.vertcat(x[1], -x[0] - 0.1 * x[1]),
                           state_box=box)
    t = true_roa_horizon(light, None, box)
    assert t == pytest.approx(SLOW_FACTOR * np.log(np.sqrt(8) / 1e-3) / 0.05, rel=1e-6)
    _, short, _ = true_roa_mask(light, None, box, 9, t_final=TRUE_ROA_TIME, undecided=True)
    mask, open_, _ = true_roa_mask(light, None, box, 9, t_final=t, undecided=True)
    assert short.sum() > 40 and not open_.any() and mask.all()     # a linear loop: all
    damped = systems.System("test_damped", x, None, ca.vertcat(x[1], -x[0] - 2 * x[1]),
                            state_box=box)
    assert true_roa_horizon(damped, None, box) == TRUE_ROA_TIME


def test_simulation_inside_the_domain_counts_only_states_that_never_leave_it():
    """x' = Ax, A = [[−0.2, 1], [−1, −0.2]] (a contracting spiral): x(t) = e^{−0.2t}R(t)x₀
    in closed form. On the box D = [−1, 1] × [−0.5, 0.5] a state counts as converged with
    ``stay=D.contains`` exactly when its exact trajectory never leaves D (away from the
    tangency states, where a step of the scheme decides); the cost of those states is the
    cost without ``stay``."""
    from nlyap_opt.kernel.domain import Box

    A = np.array([[-0.2, 1.0], [-1.0, -0.2]])
    D = Box([[-1.0, 1.0], [-0.5, 0.5]])
    g = np.linspace(-0.98, 0.98, 31)
    X = np.stack(np.meshgrid(g, 0.5 * g), -1).reshape(-1, 2)
    t = np.linspace(0.0, 30.0, 6001)   # e^{-6}·1.2 < 0.5: no exit after 30 s
    c, s = np.cos(t), np.sin(t)
    x1 = np.exp(-0.2 * t)[None] * (c[None] * X[:, :1] + s[None] * X[:, 1:])
    x2 = np.exp(-0.2 * t)[None] * (-s[None] * X[:, :1] + c[None] * X[:, 1:])
    excess = np.maximum(np.abs(x1) - 1.0, np.abs(x2) - 0.5).max(axis=1)  # > 0: leaves D
    def rhs(x):
        return x @ A.T

    conv, cost, peak = simulate(rhs, X, t_final=50.0, dt=0.02, tol=1e-3, track=D.gauge)
    conv_in, cost_in = simulate(rhs, X, t_final=50.0, dt=0.02, tol=1e-3, stay=D.contains)
    assert conv.all()                                       # the origin attracts every state
    clear = np.abs(excess) > 1e-3
    assert (excess[clear] > 0).sum() > 50 and (excess[clear] < 0).sum() > 50
    np.testing.assert_array_equal(conv_in[clear], excess[clear] < 0)
    np.testing.assert_array_equal(cost_in[conv_in], cost[conv_in])
    # track: the largest gauge along the exact trajectory (1 + excess/half-width on a face)
    h = np.maximum(np.abs(x1), 2.0 * np.abs(x2)).max(axis=1)
    np.testing.assert_allclose(peak, h, atol=1e-3)
    assert np.all((h > 1.0 + 1e-3) <= (excess > 0))
    # the report's bound: true_roa_stays on the same loop as a System, same verdicts
    import casadi as ca

    import systems
    from nlyap_opt.certification.roa import true_roa_stays

    z = ca.SX.sym("z", 2)
    spiral = systems.System("test_spiral", z, None, ca.mtimes(ca.DM(A), z),
                            state_box=np.array([[-1.0, 1.0], [-1.0, 1.0]]))
    stays = true_roa_stays(spiral, None, X, D)
    np.testing.assert_array_equal(stays[clear], excess[clear] < 0)
    assert true_roa_stays(spiral, None, np.zeros((0, 2)), D).shape == (0,)


def test_report_gives_the_bound_the_domain_puts_on_every_certificate():
    """The share of the true ROA within D that reaches the origin without leaving D is
    printed as the bound of every certificate in D; the controller advice only with inputs;
    nothing for an older certificate without the entry."""
    from nlyap_opt.workflow.report import _stays_line

    line = _stays_line({"true_roa_stays_in_domain": 0.971}, controlled=True)[0]
    assert line.startswith("Of the true ROA within D, 97.1% reach the origin without leaving D")
    assert "controller" in line
    assert "controller" not in _stays_line({"true_roa_stays_in_domain": 0.5}, False)[0]
    assert _stays_line({"true_roa_stays_in_domain": 1.0}, False)[0].startswith("Every state")
    assert _stays_line({}, True) == []


@pytest.mark.slow  # two small pipeline runs (about 7 s idle)
def test_report_gives_no_true_roa_share_when_too_few_states_converge(tmp_path):
    """x' = Ax, A = [[−1, 1], [−1, −1]]/50: ‖x(t)‖ = e^{−t/50}‖x₀‖. The simulation stops
    a state once it enters the certified inner ellipse E ⊇ B_ε (ε = 0.05). The horizon is
    extended for the slow mode (σ = 0.02 per s) up to 10 × eval_time: with eval_time = 5 s
    (50 s, a factor 0.37) only the states next to the origin get there and the rest stay
    undecided, so the report and certificate.json give no share of the true ROA (never an
    area of 0 or a share of a sliver) and name eval_time; with eval_time = 200 s the
    horizon becomes 1.5 ln(r/tol)/σ (more than 200 s), every state of the box converges, the
    true ROA is all of D and the report prints the horizon."""
    import casadi as ca

    import systems
    from nlyap_opt import make_config, run
    from nlyap_opt.workflow.report import winner_line

    x = ca.SX.sym("x", 2)
    f = ca.vertcat(-0.02 * x[0] + 0.02 * x[1], -0.02 * x[0] - 0.02 * x[1])
    name = "test_slow_linear_report"
    sys_ = systems.System(name, x, None, f, state_box=[[-1.0, 1.0], [-1.0, 1.0]])
    if name not in systems.names():
        systems.register(name, lambda: sys_)
    small = {"outer": 1.0, "inner": 0.2, "eval_points": 400, "quadratic": ["lyapunov"],
             "train": {"hidden": [6], "features": 3, "steps": 200},
             "cegis": {"iterations": 1, "steps": 50, "samples": 2000, "sim_time": 5.0,
                       "boundary_samples": 0, "sphere_samples": 400, "area_points": 400}}
    out = tmp_path / "run"
    res = run(sys_, make_config(name, preset=None, overrides={**small, "eval_time": 5.0}),
              out, known_dynamics=True, log=lambda m: None)
    cert = res.summary
    assert cert["true_roa_time"] == 50.0
    assert cert["true_roa_area"] is None and cert["fraction_of_true_roa"] is None
    why = [a for a in cert["not_available"] if a.startswith("true ROA")]
    assert len(why) == 1 and "raise eval_time" in why[0] and "50 s" in why[0], why
    text = (out / "report.md").read_text()
    assert "no share of the true ROA is given" in text and "raise eval_time" in text
    assert "certified ÷ true" not in text and "true ROA area" not in text
    line = winner_line(cert.get("candidates") or [])
    assert line is not None and line in text          # the quadratic ran beside the neural V
    # the CEGIS history says what limited each candidate level (here ∂D: x' = Ax decreases
    # every positive definite quadratic-like V it is trained on)
    assert "| limited by |" in text
    # a longer horizon decides every state (the same run's stages are reused)
    res = run(sys_, make_config(name, preset=None, overrides={**small, "eval_time": 200.0}),
              out, known_dynamics=True, log=lambda m: None)
    cert = res.summary
    assert 200.0 < cert["true_roa_time"] < 2000.0 and cert["true_roa_undecided"] == 0.0
    # no inputs: all of D, the disc ‖x‖ <= 1 (counted on the 20 × 20 grid)
    assert cert["true_roa_area"] == pytest.approx(np.pi, rel=0.02)
    text = (out / "report.md").read_text()
    assert "certified ÷ true" in text and "no share of the true ROA" not in text
    assert f"each state simulated for up to {cert['true_roa_time']:.4g} s" in text


def test_winner_line_says_plainly_when_a_cheap_v_wins():
    from nlyap_opt.workflow.report import winner_line

    def row(V, status, vol, winner):
        return {"V": V, "controller": None, "status": status, "reason": "", "level": 1.0,
                "inner": 0.1, "certified_volume": vol, "winner": winner}

    assert winner_line([]) is None
    lost = winner_line([row("neural (V.json)", "certified", 2.0, False),
                        row("quadratic lyapunov (V_quadratic.json)", "certified", 3.0, True)])
    assert lost.startswith("**The neural V did not beat the cheap candidate**")
    assert "2" in lost and "3" in lost and "quadratic lyapunov" in lost
    failed = winner_line([row("neural (V.json)", "not certified", 0.0, False),
                          row("SOS (V_sos.json)", "certified", 1.5, True)])
    assert "certifies no level" in failed and "SOS (V_sos.json)" in failed
    # never verified because it could not win: said so, not "certifies no level"
    skipped = row("neural (V.json)", "not certified", 0.0, False)
    skipped["reason"] = (f"{NOT_CHECKED}: at each inner radius tried (ε = 0.2) no "
                         "certificate of it can beat the SOS (at ε = 0.2: volume bound 1.2 "
                         "below its certified 1.5)")
    unchecked = winner_line([skipped, row("SOS (V_sos.json)", "certified", 1.5, True)])
    assert "it was not verified, since at each inner radius tried (ε = 0.2)" in unchecked
    assert "certifies no level" not in unchecked and NOT_CHECKED not in unchecked
    won = winner_line([row("neural (V.json)", "certified", 4.0, True),
                       row("quadratic lyapunov (V_quadratic.json)", "certified", 3.0, False)])
    assert won.startswith("The neural V certifies a larger volume (4)")


@pytest.mark.parametrize("name", ["van_der_pol", "unicycle_path_following", "inverted_pendulum"])
def test_catalogue_default_dynamics_grid_matches_its_model(name):
    """--preset default on a catalogue system: the generic (x, u) grid comes with the full
    model, not the catalogue's learned-dynamics model of another grid (the pendulum's
    control-affine preset samples x only, and the learned run stopped at φ's stage)."""
    from dataclasses import asdict

    import systems
    from nlyap_opt.learned.dynamics import make_grid
    from nlyap_opt.learned.dynamics_config import dynamics_config
    from nlyap_opt.workflow.configs import make_config

    s = systems.get(name)
    dyn = make_config(name, preset=None).dynamics.to_json()
    assert dyn["model"] == "full" and len(dyn["grid_counts"]) == s.nx + s.nu
    # and no η gate of the catalogue's finer grid (path following's 0.015 refused the
    # generic grid's η = 0.023)
    assert dynamics_config(name, dyn).eta_target is None
    # the dynamics stage's own checks of the merged settings: grid against model
    make_grid(s, asdict(dynamics_config(name, dyn)))


def test_label_boundary_states_lie_across_the_boundary_between_labels():
    """States labelled by the unit disc (inside) in the square [−2, 2]²: every drawn state
    lies on a segment between an inside and an outside neighbour, so within one neighbour
    distance of the circle; they surround it; same rng, same states; none without both
    labels."""
    from scipy.spatial import cKDTree

    from nlyap_opt.candidates.learning import BOUNDARY_NEIGHBOURS, label_boundary_states

    rng = np.random.default_rng(3)
    X = rng.uniform(-2.0, 2.0, (4000, 2))
    inside = np.linalg.norm(X, axis=1) < 1.0
    Y = label_boundary_states(X, inside, 3000, np.random.default_rng(7))
    assert Y.shape == (3000, 2)
    reach = cKDTree(X).query(X, k=BOUNDARY_NEIGHBOURS + 1)[0][:, -1].max()
    r = np.linalg.norm(Y, axis=1)
    assert np.all(np.abs(r - 1.0) <= reach)
    # much closer to the circle than uniform draws in the square, and all the way round
    far = np.median(np.abs(np.linalg.norm(X, axis=1) - 1.0))
    assert np.median(np.abs(r - 1.0)) < 0.25 * far
    angles = np.arctan2(Y[:, 1], Y[:, 0])
    assert np.histogram(angles, bins=8, range=(-np.pi, np.pi))[0].min() > 3000 / 8 / 4
    np.testing.assert_array_equal(Y, label_boundary_states(X, inside, 3000,
                                                           np.random.default_rng(7)))
    for labels in (np.ones(len(X), bool), np.zeros(len(X), bool)):
        assert label_boundary_states(X, labels, 100, rng).shape == (0, 2)



def test_a_fixed_inner_radius_is_refused_only_where_no_v_can_decrease():
    """x' = Ax, A = [[−1, 10], [0, −1]] (non-normal): the Lyapunov-equation quadratic loses
    its robust decrease inside ‖x‖ ≈ 0.15 at η = 0.003, but every point of the sphere
    ‖x‖ = 0.05 moves at ≥ σ_min(A)·0.05 ≈ 0.005 > η, so another V may still work: a warning,
    not a refusal. At η = 0.01 a point moves slower than η, where ∇V·φ + η‖∇V‖ ≥ 0 for
    every V: the run stops with one line naming the ε that would."""
    import casadi as ca

    import systems
    from nlyap_opt.kernel.domain import Ball
    from nlyap_opt.workflow.pipeline import _inner_for_margin, _slow_on_sphere

    x = ca.SX.sym("x", 2)
    A = np.array([[-1.0, 10.0], [0.0, -1.0]])
    s = systems.System("test_nonnormal", x, None, ca.mtimes(ca.DM(A), x),
                       state_box=[[-4, 4], [-4, 4]])
    smin = np.linalg.svd(A, compute_uv=False).min()
    said = []
    assert _inner_for_margin(s, None, None, 0.003, 0.05, Ball(4.0, 2), False,
                             said.append) == 0.05
    assert "other V may still certify" in said[-1] and "set inner to" in said[-1]
    assert _slow_on_sphere(s, None, None, 0.003, 0.05) is None
    slow = _slow_on_sphere(s, None, None, 0.01, 0.05)
    assert slow is not None and np.linalg.norm(slow) == pytest.approx(0.05)
    assert smin * 0.05 <= np.linalg.norm(A @ slow) < 0.01
    with pytest.raises(ConfigError, match="inner = 0.05 cannot work.*moves slower than η"):
        _inner_for_margin(s, None, None, 0.01, 0.05, Ball(4.0, 2), False, said.append)


def test_a_centre_keeps_its_horizon():
    """x' = −x³: a finite-difference linearisation gives −10⁻¹² (or +10⁻¹²), no rate: the
    horizon is the configured one, not the 10× cap."""
    import casadi as ca

    import systems
    from nlyap_opt.certification.roa import TRUE_ROA_TIME, true_roa_horizon
    from nlyap_opt.kernel.simulate import horizon

    x = ca.SX.sym("x", 2)
    box = np.array([[-1.0, 1.0], [-1.0, 1.0]])
    cubic = systems.System("test_cubic", x, None, ca.vertcat(-x[0] ** 3, -x[1]),
                           state_box=box)
    assert true_roa_horizon(cubic, None, box) == TRUE_ROA_TIME
    assert horizon(30.0, np.diag([-1e-12, -1.0]), 3.0, 1e-3) == 30.0
    assert horizon(30.0, np.diag([-0.01, -1.0]), 3.0, 1e-3) == 300.0       # the cap
