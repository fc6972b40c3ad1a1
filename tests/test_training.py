"""The trajectory-cost target, the local (linearisation) term and falsifier-first CEGIS."""

import numpy as np
import pytest
import scipy.linalg
import torch
from certcheck import assert_reverifies

import systems
from baselines.lqr import lqr, saturated_controller
from nlyap_opt.candidates.cegis import CegisConfig, _level_settled, cegis, cost_targets
from nlyap_opt.candidates.learning import LyapunovLearner, TrainConfig, _body_jacobian_at_zero
from nlyap_opt.kernel.simulate import simulate, simulate_converges


def test_trajectory_cost_of_a_linear_system_is_its_lyapunov_quadratic():
    """For x' = Ax, ∫‖x‖² dt = x0ᵀPx0 with AᵀP + PA = −I (up to the tail below tol)."""
    A = np.array([[0.0, 1.0], [-2.0, -1.5]])
    P = scipy.linalg.solve_continuous_lyapunov(A.T, -np.eye(2))
    x0 = np.random.default_rng(0).uniform(-2, 2, (200, 2))
    conv, cost = simulate(lambda x: x @ A.T, x0, t_final=60.0, dt=0.01, tol=1e-4)
    assert conv.all()
    exact = np.einsum("ij,jk,ik->i", x0, P, x0)
    np.testing.assert_allclose(cost, exact, rtol=2e-4, atol=1e-7)  # trapezoidal O(dt²)
    # an unstable system: nothing converges, the cost stays finite up to blow-up
    conv_u, cost_u = simulate(lambda x: -x @ A.T, x0, t_final=60.0, dt=0.01, tol=1e-4)
    assert not conv_u.any() and np.all(cost_u > 0)
    assert np.array_equal(simulate_converges(lambda x: x @ A.T, x0, 60.0, 0.01, 1e-4), conv)


@pytest.mark.parametrize("transform", ["log", "linear"])
def test_cost_targets_are_monotone_capped_and_their_rates_are_derivatives(transform):
    cost = np.linspace(0.0, 100.0, 2001)
    conv = np.ones_like(cost, bool)
    conv[-5:] = False
    T, rate = cost_targets(conv, cost, w_c=20.0, cap=2.0, transform=transform)
    assert T[0] == 0.0 and np.all(np.diff(T) >= 0) and T.max() == 2.0
    np.testing.assert_allclose(np.interp(20.0, cost, T), 1.0, rtol=1e-12)
    assert np.all(T[~conv] == 2.0) and np.all(rate[T >= 2.0] == 0.0)
    live = rate > 0
    dT = np.gradient(T, cost)  # dT/dt = dT/dW · dW/dt = −(dT/dW)‖x‖²: rate = dT/dW
    inner = live & np.roll(live, 1) & np.roll(live, -1)
    inner[[0, -1]] = False
    np.testing.assert_allclose(rate[inner], dT[inner], rtol=1e-3)
    with pytest.raises(ValueError, match="fit_transform"):
        cost_targets(conv, cost, 20.0, 2.0, "cubic")


@pytest.mark.parametrize("act", ["tanh", "square", "linear"])
@pytest.mark.parametrize("name", ["van_der_pol", "inverted_pendulum",
                                  "unicycle_path_following"])
def test_local_term_matches_autograd_hessian_and_jacobian(name, act):
    """∇²V(0) = 2(JᵀJ + εI) with J = ∂N/∂x(0) from the forward-mode Jacobian, for every V
    family (tanh, square: V a polynomial, linear: V quadratic)."""
    s = systems.get(name)
    ctrl = saturated_controller(s, lqr(s).K, 5.0) if s.nu else None
    L = LyapunovLearner(s, ctrl, None, TrainConfig(hidden=[7, 5], features=4, seed=3,
                                                   activation=act))
    want = {"tanh": {"Tanh"}, "square": {"Square"}, "linear": set()}[act]
    assert {type(m).__name__ for m in L.V.body} & {"Tanh", "Square"} == want
    if ctrl is not None:  # a gain away from the LQR start
        with torch.no_grad():
            L.G.add_(0.1 * torch.randn_like(L.G))
    z = torch.zeros(s.nx, dtype=torch.float64)
    H = torch.autograd.functional.hessian(lambda y: L.V(y[None])[0, 0], z)
    A = torch.autograd.functional.jacobian(lambda y: L.rhs(y[None])[0], z)
    J = _body_jacobian_at_zero(L.V.body, s.nx)
    H2 = 2 * (J.T @ J + L.V.eps * torch.eye(s.nx, dtype=torch.float64))
    np.testing.assert_allclose(H2.detach().numpy(), H.numpy(), atol=1e-12)
    np.testing.assert_allclose(L.closed_loop_jacobian().detach().numpy(), A.numpy(),
                               atol=1e-12)
    # the violation is the λ_max of AᵀH + HA + 2τH over tr H (zero iff first-order decrease)
    S = (A.T @ H + H @ A + 2 * L.config.decay * H).numpy()
    want = max(np.linalg.eigvalsh(0.5 * (S + S.T))[-1], 0.0) / np.trace(H.numpy())
    assert L.local_violation().item() == pytest.approx(want, rel=1e-9, abs=1e-15)


def test_local_term_trains_a_lyapunov_quadratic():
    """Minimising the local term alone gives ∇²V(0) with AᵀH + HA ≺ −2τH (Van der Pol)."""
    s = systems.get("van_der_pol")
    L = LyapunovLearner(s, None, None, TrainConfig(hidden=[6], features=3, seed=1,
                                                   decay=0.1))
    opt = torch.optim.Adam(L.V.parameters(), lr=0.02)
    start = L.local_violation().item()
    for _ in range(300):
        loss = L.local_violation()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert start > 0, "the seed should start from a non-Lyapunov quadratic"
    assert L.local_violation().item() == 0.0
    J = _body_jacobian_at_zero(L.V.body, 2).detach().numpy()
    H = 2 * (J.T @ J + L.V.eps * np.eye(2))
    assert np.linalg.eigvalsh(s.A.T @ H + H @ s.A)[-1] < 0


def _assert_stop_rule(history, cfg):
    """CEGIS ended where its stop rule first held, or at the iteration budget."""
    best = 0.0
    for i, h in enumerate(history):
        stop = (h["status"] == "certified" and h["counterexamples"] == 0
                and h["level"] >= cfg.target_fraction * h["candidate_level"]
                and i + 1 >= cfg.min_iterations
                and ((h["candidate_source"] == "sphere" and not cfg.boundary_feedback)
                     or (best > 0 and (1 - cfg.plateau) * best <= h["area"]
                         <= (1 + cfg.plateau) * best)))
        if i < len(history) - 1:
            assert not stop, (i, h)
        elif len(history) < cfg.iterations:
            assert stop, (i, h)
        best = max(best, h["area"])


def test_stop_rule_goes_on_while_decrease_violations_limit_a_growing_level():
    """A candidate on the domain's boundary is final only without boundary feedback; one
    limited by sampled decrease violations (or by ∂D with feedback) is final only once the
    certified area stops growing (plateau fraction)."""
    assert _level_settled("sphere", 1.0, 0.0, 0.01, boundary_feedback=False)
    assert not _level_settled("sphere", 1.0, 0.0, 0.01)       # first certified level
    assert not _level_settled("sphere", 1.02, 1.0, 0.01)      # grew by 2 %
    assert _level_settled("sphere", 1.01, 1.0, 0.01)
    assert not _level_settled("decrease", 1.0, 0.0, 0.01)     # first certified level
    assert not _level_settled("decrease", 1.02, 1.0, 0.01)    # grew by 2 %
    assert _level_settled("decrease", 1.01, 1.0, 0.01)        # grew by 1 %: settled
    assert _level_settled("decrease", 0.995, 1.0, 0.01)       # within 1 % below
    # more than plateau below the best: the current V is behind it and may still grow
    assert not _level_settled("decrease", 0.9, 1.0, 0.01)
    assert not _level_settled("sphere", 0.984, 1.0, 0.01)
    assert not _level_settled("decrease", 1.005, 1.0, 0.0)
    assert _level_settled("decrease", 1.0, 1.0, 0.0)


def test_falsifier_first_cegis_verifies_what_it_returns():
    """With verify_every = 2, only odd iterations (and the last) run the verifier; the
    returned level is one the verifier proved (re-checked here)."""
    s = systems.get("van_der_pol")
    train = TrainConfig(hidden=[8], features=3, steps=300, lr=0.02, w_fit=10.0, w_pde=1.0,
                        w_local=10.0, relative_decrease=True, level_slack=0.5, decay=0.05,
                        lr_schedule="cosine")
    cfg = CegisConfig(inner=0.3, outer=1.5, iterations=4, steps=100, verify_every=2,
                      samples=3000, sphere_samples=500, inner_samples=300,
                      boundary_samples=1000, sim_dt=0.05, train=train, area_points=6400)
    res = cegis(s, None, None, cfg, log=lambda m: None)
    assert len(res.history) >= 2
    for i, h in enumerate(res.history):
        if (i + 1) % 2 and i < len(res.history) - 1:
            # falsifier-only iterations: typed status, the reason says no verifier ran
            assert h["status"] == "not certified" and h["boxes"] == 0, h
            assert h["reason"].startswith("not verified"), h
            assert h["counterexamples"] >= 0
        else:
            assert h["boxes"] > 0, h
    assert res.status == "certified" and res.level > 0 and res.area > 0
    _assert_stop_rule(res.history, cfg)
    assert_reverifies(s, res.V, res.level, inner=0.3, outer=1.5, half=1.5)


def test_tabulated_simulation_rhs_interpolates_the_model():
    """The table used for the training simulations of a learned φ agrees with the model to
    the multilinear interpolation error (here on Van der Pol's f, h = 0.02)."""
    from nlyap_opt.candidates.cegis import _simulation_rhs

    s = systems.get("van_der_pol")
    L = LyapunovLearner(s, None, None, TrainConfig(hidden=[4], features=2))
    cfg = CegisConfig(inner=0.2, outer=2.0, sim_points=40401)
    table = _simulation_rhs(L, s, cfg, tabulate=True)
    direct = _simulation_rhs(L, s, CegisConfig(inner=0.2, outer=2.0, sim_points=0),
                             tabulate=True)
    x = np.random.default_rng(0).uniform(-2, 2, (5000, 2))
    err = np.abs(table(x) - s.evaluate(x, None)).max()
    # |∂²f₂/∂x_i²| ≤ 2|x₂| ≤ 4 and the x₁²x₂ cross term: bilinear error ≤ h²/8·Σ|f_ii| + ...
    assert 0 < err < 1e-3
    np.testing.assert_allclose(direct(x), s.evaluate(x, None), rtol=0, atol=1e-12)


def test_candidate_level_violations_are_sampled_decrease_failures():
    """For V = ‖x‖² on Van der Pol, V̇ = 2(x₁² − 1)x₂² ≥ 0 where |x₁| ≥ 1 (and on the
    axis x₂ = 0, where V̇ = 0 and V ≥ ε²): every returned violation fails the decrease and
    the candidate is no larger than V at any of them."""
    import casadi as ca

    from nlyap_opt.certification.roa import candidate_level
    from nlyap_opt.kernel.symbolic import closed_loop, lie_derivative

    s = systems.get("van_der_pol")
    cl = closed_loop(s, None, None, strict=True)
    V = ca.sumsqr(cl.x)
    lie = lie_derivative(V, cl.x, cl.rhs)
    cand = candidate_level(cl.x, V, lie, inner=0.2, outer=2.0, n_samples=5000)
    pts = cand.violations
    assert cand.source == "decrease" and len(pts) > 10
    assert 0.2**2 - 1e-9 <= cand.level <= np.min(np.sum(pts**2, axis=1)) + 1e-12
    r = np.linalg.norm(pts, axis=1)
    assert np.all((r >= 0.2 - 1e-9) & (r <= 2.0 + 1e-9))
    lie_f = ca.Function("l", [cl.x], [lie])
    assert all(float(lie_f(p)) >= -1e-9 for p in pts)


def test_certify_level_steps_down_gently_after_unknown_verdicts():
    """``V = ‖x‖²``, ``V̇ = −(0.98 − V)²``: the decrease fails (= 0) on the circle ``V = 0.98``
    and is barely negative next to it, so coarse verifier runs above it say ``unknown``. The
    certified level lies below 0.98, and the small first steps keep it above the ×0.9 of a
    single 10 % step."""
    import casadi as ca

    from nlyap_opt.certification.roa import certify_level

    x = ca.MX.sym("x", 2)
    V = ca.sumsqr(x)
    lie = -(0.98 - V) ** 2
    cert = certify_level(x, V, lie, level=1.0, inner=0.1, outer=1.5, margin=0.0,
                         verify_options={"resolution": 2e-3}, log=lambda m: None)
    assert cert.status == "certified", cert.history
    assert any(h["decrease"] == "unknown" for h in cert.history)
    assert 0.9 < cert.level < 0.98


def test_simulate_counts_entering_a_known_roa_set_as_converged():
    """ẋ = −0.1x from ‖x‖ = 1 reaches ‖x‖ = e⁻¹ in 10 s: not ``tol``, but the target disc
    ‖x‖ ≤ 0.5; ẋ = +0.1x never converges, target or not."""
    x0 = np.array([[1.0, 0.0], [0.0, -1.0], [0.3, 0.1]])

    def disc(z):
        return np.einsum("ij,ij->i", z, z) <= 0.25

    assert not simulate_converges(lambda z: -0.1 * z, x0[:2], t_final=10.0).any()
    assert simulate_converges(lambda z: -0.1 * z, x0, t_final=10.0, target=disc).all()
    conv, cost = simulate(lambda z: -0.1 * z, x0[:1], t_final=10.0, target=disc)
    # stopped on entering the disc at t = 10 ln 2: cost ∫ e^(−0.2t) dt = 5 (1 − 1/4)
    assert conv[0] and cost[0] == pytest.approx(3.75, rel=0.02)
    assert not simulate_converges(lambda z: 0.1 * z, x0[:2], t_final=10.0, target=disc).any()


def _stable_focus():
    """x' = −x + (x₂, −x₁)·2: a stable focus, decreasing ‖x‖² everywhere, so a learned V's
    level in the box D is limited by containment on ∂D, never by the decrease."""
    import casadi as ca

    x = ca.SX.sym("x", 2)
    f = ca.vertcat(-x[0] + 2 * x[1], -2 * x[0] - x[1])
    return systems.System("stable_focus", x, ca.SX.sym("u", 0), f,
                          state_box=[[-1.0, 1.0], [-1.0, 1.0]])


@pytest.mark.parametrize("feedback", [0, 100])
def test_boundary_limited_level_keeps_training_on_the_boundary_minima(feedback):
    """A level limited by ∂D: with boundary feedback CEGIS goes on after the first
    certified level (the states of ∂D with the smallest V join the containment training)
    and returns the largest certified area; without it, it stops there."""
    from nlyap_opt.kernel.domain import Box

    s = _stable_focus()
    train = TrainConfig(hidden=[6], features=3, steps=150, lr=0.02, level_slack=0.5,
                        relative_decrease=True, w_local=10.0)
    D = Box([[-1.0, 1.0], [-1.0, 1.0]])
    cfg = CegisConfig(inner=0.1, outer=D.max_norm(), domain=D, iterations=3, steps=100,
                      samples=2000, sphere_samples=400, train=train, area_points=6400,
                      boundary_feedback=feedback, plateau=0.0)
    res = cegis(s, None, None, cfg, log=lambda m: None)
    first = res.history[0]
    assert first["candidate_source"] == "sphere" and first["status"] == "certified", first
    _assert_stop_rule(res.history, cfg)
    if not feedback:
        assert len(res.history) == 1 and "boundary_feedback" not in first
    else:
        assert len(res.history) >= 2 and first["boundary_feedback"] == feedback + 1
    # the returned certificate is the best certified one: the area never goes down
    assert res.certified and res.area == max(h["area"] for h in res.history) >= first["area"]
    # the returned V's minimum over ∂D is the level it certifies (containment-limited)
    pts = D.sample_boundary(20000, np.random.default_rng(1))
    assert res.V.numpy(pts)[:, 0].min() >= res.level
