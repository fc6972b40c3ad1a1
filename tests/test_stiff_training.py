"""The default method on a stiff closed loop: the training simulations' step and the gain.

A saturated controller with a large input range gives a closed loop with a fast mode (the
catalogue pendulum: torque range 27 times the gravity torque). RK4 at a fixed step is
unstable for a mode with h·λ < −2.79: no simulated trajectory converges and no fit target
is made. :func:`nlyap_opt.kernel.simulate.stable_step` shortens the step to the
loop's fastest linear mode. These tests check that on stiff linear loops the shortened step
converges and gives the exact trajectory cost xᵀPx (AᵀP + PA = −I), that the fixed step
does not, and that a non-stiff loop keeps ``cegis.sim_dt``.
"""

import numpy as np
import pytest
from scipy.linalg import solve_continuous_lyapunov

from nlyap_opt.kernel.simulate import STIFF_STEP, simulate, stable_step


def _rk4_amplification(z: np.ndarray) -> np.ndarray:
    return 1 + z + z ** 2 / 2 + z ** 3 / 6 + z ** 4 / 24


def test_the_step_bound_lies_inside_rk4s_stability_region():
    """|R(hλ)| ≤ 1 for every hλ with Re ≤ 0 and |hλ| ≤ STIFF_STEP (a grid of the half disc),
    and R is within 1 % of exp on the negative real axis there."""
    r, phi = np.meshgrid(np.linspace(0, STIFF_STEP, 101), np.linspace(np.pi / 2, 3 * np.pi / 2,
                                                                     181))
    z = r * np.exp(1j * phi)
    assert np.abs(_rk4_amplification(z)).max() <= 1 + 1e-12
    x = -np.linspace(0, STIFF_STEP, 101)
    assert np.max(np.abs(_rk4_amplification(x) - np.exp(x))) < 0.01


@pytest.mark.parametrize("A", [
    np.array([[0.0, 1.0], [-19.6, -120.0]]),        # a stiff damped loop (modes −0.16, −120)
    np.array([[-1.0, 50.0], [0.0, -300.0]]),        # non-normal, modes −1 and −300
    np.array([[-50.0, 40.0, 0.0], [-40.0, -50.0, 0.0], [0.0, 0.0, -0.5]]),  # a fast damped
    # rotation (−50 ± 40i) and a slow mode
])
def test_shortened_step_matches_the_exact_cost_of_a_stiff_linear_loop(A):
    """x' = Ax from states on the circle of radius 2 (at x₃ = 1 in 3-D): with
    stable_step(0.04, A) every trajectory converges and its cost ∫‖x‖² dt is x₀ᵀPx₀
    (AᵀP + PA = −I) within 1 % of the largest; with the fixed step 0.04 (h·ρ(A) ≥ 1.6)
    at least one does not converge or its cost is off by more than that."""
    rho = np.max(np.abs(np.linalg.eigvals(A)))
    dt = stable_step(0.04, A)
    assert dt == pytest.approx(STIFF_STEP / rho) and dt < 0.04
    phi = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    x0 = 2.0 * np.stack([np.cos(phi), np.sin(phi)] + [np.full_like(phi, 0.5)] * (len(A) - 2), 1)
    P = solve_continuous_lyapunov(A.T, -np.eye(len(A)))
    exact = np.einsum("ij,jk,ik->i", x0, P, x0)
    slow = -np.max(np.linalg.eigvals(A).real)
    t_final = 20.0 / slow

    def rhs(x):
        return x @ A.T

    conv, cost = simulate(rhs, x0, t_final=t_final, dt=dt, tol=1e-5)
    assert conv.all()
    # within 1 % of the largest cost (the trapezoidal rule over a fast transient of one
    # step is a few % off on the states along the fast eigenvector, whose cost is tiny)
    np.testing.assert_allclose(cost, exact, rtol=0, atol=1e-2 * exact.max())
    conv_f, cost_f = simulate(rhs, x0, t_final=t_final, dt=0.04, tol=1e-5)
    assert not conv_f.all() or np.max(np.abs(cost_f - exact)) > 1e-2 * exact.max()


def test_a_non_stiff_loop_keeps_the_configured_step():
    """Van der Pol's linearisation (|λ| = 1) and the pendulum's LQR loop of Q = I, R = I
    (modes −1.2, −27.5: 0.04·27.5 = 1.1 > STIFF_STEP, shortened; 0.02·27.5 = 0.55 kept)."""
    assert stable_step(0.04, np.array([[0.0, 1.0], [-1.0, 1.0]])) == 0.04
    A = np.array([[0.0, 1.0], [19.62 - 26.667 * 1.977, -2.667 - 26.667 * 0.976]])
    assert stable_step(0.02, A) == 0.02
    assert stable_step(0.04, A) < 0.04
    assert stable_step(0.04, np.zeros((2, 2))) == 0.04


def _scan(name: str, radius: float, scale: float):
    """Run the gain scan of the default method (cegis.gain_scan) on catalogue system
    ``name`` with the true f on the disc of ``radius``; returns the start gain, the chosen
    gain, the log and the stays-in-D shares of both on a fresh grid."""
    import systems
    from nlyap_opt.candidates import cegis as cg
    from nlyap_opt.candidates.learning import LyapunovLearner, TrainConfig
    from nlyap_opt.design.control import lqr, saturated_controller
    from nlyap_opt.kernel.domain import Ball

    s = systems.get(name)
    D = Ball(radius, 2)
    cfg = cg.CegisConfig(inner=0.1 * radius, outer=radius, sim_time=30.0, sim_dt=0.04,
                         gain_scan=True)
    learner = LyapunovLearner(s, saturated_controller(s, lqr(s).K, scale), None,
                              TrainConfig(hidden=[4], features=2))
    X = D.sample(400, np.random.default_rng(0))
    start = learner.G.detach().numpy().copy()
    lines = []
    cg._scan_gain(learner, s, None, cfg, D, X, lines.append)
    chosen = learner.G.detach().numpy().copy()
    np.testing.assert_array_equal(learner.G0.numpy(), chosen)   # the anchor follows
    g = np.linspace(-radius, radius, 25)
    grid = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    grid = grid[D.contains(grid)]

    def stays(G):
        import torch
        learner.set_gain(torch.as_tensor(G))
        _, k = learner.export()
        dt = stable_step(0.04, learner.closed_loop_jacobian().detach().numpy())
        return simulate(lambda x: s.evaluate(x, k.numpy(x)), grid, 30.0, dt, 1e-2,
                        stay=D.contains)[0].mean()

    return start, chosen, lines, stays(start), stays(chosen)


def test_gain_scan_replaces_a_start_that_lets_trajectories_leave_the_domain():
    """The pendulum on the disc r = 4 with u = 20·tanh(·): the LQR start of Q = I keeps about
    70 % of the disc in it on the way to the origin; the scan starts κ from the LQR gain of
    Q = diag(1, 30) (more derivative action), which keeps more than 90 % (checked on a grid
    the scan did not see), and says so in one log line."""
    start, chosen, lines, s0, s1 = _scan("inverted_pendulum", 4.0, 20.0)
    assert not np.allclose(start, chosen)
    assert chosen[0, 1] > 2 * start[0, 1]          # the ω gain grew
    assert s0 < 0.8 and s1 > 0.9
    assert len(lines) == 1 and "Q[1,1] = 30" in lines[0] and "κ starts from LQR" in lines[0]


def test_gain_scan_keeps_a_start_that_already_keeps_the_domain():
    """Path following on the disc r = 0.8 with u = 5·tanh(·): the LQR start keeps about 97 %
    of the disc in it; no weighting beats it by more than GAIN_MARGIN, so κ starts from it
    unchanged (bit for bit)."""
    start, chosen, lines, s0, s1 = _scan("unicycle_path_following", 0.8, 5.0)
    np.testing.assert_array_equal(start, chosen)
    assert s0 > 0.9 and s0 == s1
    assert "κ starts from the LQR start" in lines[0]


@pytest.mark.parametrize("name, Q, scale, fit", [
    ("inverted_pendulum", None, 20.0, True),                 # modes −1.2, −27.5: ratio 23
    ("inverted_pendulum", [1.0, 10.0], 20.0, False),         # −0.39, −84.6: 217
    ("inverted_pendulum", [1.0, 30.0], 20.0, False),         # −0.23, −146: 635
    ("unicycle_path_following", None, 5.0, True),
    ("van_der_pol", None, None, True),
])
def test_the_fit_is_used_only_on_a_closed_loop_that_is_not_stiff(name, Q, scale, fit):
    """cegis.fit_fallback trains V with the Lyapunov-risk terms where the model's closed loop
    at the origin is stiffer than STIFF_RATIO (fastest speed over slowest decay rate): the
    pendulum's LQR loops of Q = diag(1, 10) and diag(1, 30), on which the fit to trajectory
    costs failed, and not its Q = I loop, path following or Van der Pol, on which it
    certifies. The learner's linearisation is the exact one (LQR's A − BK)."""
    import systems
    from nlyap_opt.candidates.cegis import LYAPUNOV_RISK, STIFF_RATIO, stiffness
    from nlyap_opt.candidates.learning import LyapunovLearner, TrainConfig
    from nlyap_opt.design.control import lqr, saturated_controller

    s = systems.get(name)
    res = lqr(s, None if Q is None else np.diag(Q))
    ctrl = saturated_controller(s, res.K, scale) if s.nu else None
    learner = LyapunovLearner(s, ctrl, None, TrainConfig(hidden=[4], features=2))
    A = learner.closed_loop_jacobian().detach().numpy()
    np.testing.assert_allclose(A, res.A - res.B @ res.K, rtol=1e-9, atol=1e-9)
    assert (stiffness(A) <= STIFF_RATIO) is fit
    assert stiffness(np.diag([-1.0, -100.0])) == pytest.approx(100.0)
    assert stiffness(np.array([[0.0, 1.0], [-1.0, 0.0]])) == 0           # a centre keeps
    assert stiffness(np.diag([0.0, -1.0, -4.0])) == 0                     # the fit
    # the recipe turns the fit off and asks for a decrease rate
    assert LYAPUNOV_RISK["w_fit"] == 0 and LYAPUNOV_RISK["decay"] > 0


@pytest.mark.parametrize("A", [
    np.array([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0],
              [-576.0, -2400.0, -4180.0, -3980.0]]),   # a linear chain, modes 0.31 … 3979
    np.array([[-1.0, 500.0], [0.0, -3000.0]]),          # non-normal, modes −1 and −3000
])
def test_a_very_stiff_loop_is_integrated_implicitly_at_the_configured_step(A):
    """Past IMPLICIT_RATIO RK4 steps per step, ``integration`` keeps the step and switches to
    ROS2: every trajectory converges, the cost is x₀ᵀPx₀ up to the first step's quadrature, the
    state at t = 1 matches expm(A) within 1 % of its norm; RK4 at that step blows up."""
    from scipy.linalg import expm

    from nlyap_opt.kernel.simulate import IMPLICIT_RATIO, integration, ros2_step
    how = integration(0.04, A)
    assert how.method == "ROS2" and how.dt == 0.04
    assert np.max(np.abs(np.linalg.eigvals(A))) * 0.04 > IMPLICIT_RATIO * STIFF_STEP
    rng = np.random.default_rng(1)
    x0 = rng.uniform(-1, 1, (24, len(A)))
    P = solve_continuous_lyapunov(A.T, -np.eye(len(A)))
    exact = np.einsum("ij,jk,ik->i", x0, P, x0)
    slow = -np.max(np.linalg.eigvals(A).real)

    def rhs(x):
        return x @ A.T

    conv, cost = simulate(rhs, x0, t_final=25.0 / slow, dt=how.dt, tol=1e-5,
                          jacobian=how.jacobian)
    assert conv.all()
    # the trapezoidal rule over the first step counts the fast transient as h‖x₀‖²/2
    # (its true cost is ~‖x₀‖²/(2ρ)): that much, plus 2 % of the largest cost
    slack = 2e-2 * exact.max() + 0.5 * 0.04 * np.einsum("ij,ij->i", x0, x0)
    assert np.all(np.abs(cost - exact) <= slack)
    W_inv = np.linalg.inv(np.eye(len(A)) - (1 + 1 / np.sqrt(2)) * 0.04 * A)
    z = x0.copy()
    for _ in range(25):
        z = ros2_step(rhs, z, 0.04, W_inv)
    ref = x0 @ expm(A).T
    assert np.max(np.linalg.norm(z - ref, axis=1)) < 1e-2 * np.max(np.linalg.norm(ref, axis=1))
    conv_f, _ = simulate(rhs, x0, t_final=25.0 / slow, dt=0.04, tol=1e-5)
    assert not conv_f.any()


def test_implicit_labels_agree_with_rk4_on_a_stiff_nonlinear_loop():
    """Khalil's x1' = −x1 + x1²x2, x2' = −x2 (ROA x1x2 < 2) with a fast state
    x3' = −600 x3 + x1²: which states converge, under ROS2 at 0.04 s and under RK4 at its
    stable step, agrees on all but a sliver next to the ROA's boundary."""
    from nlyap_opt.kernel.simulate import integration, jacobian_at_origin

    def rhs(x):
        return np.stack([-x[:, 0] + x[:, 0] ** 2 * x[:, 1], -x[:, 1],
                         -600.0 * x[:, 2] + x[:, 0] ** 2], 1)

    J = jacobian_at_origin(rhs, 3)
    how = integration(0.04, J)
    assert how.method == "ROS2"
    x0 = np.random.default_rng(2).uniform([-4, -1, -1], [4, 1, 1], (1500, 3))
    a = simulate(rhs, x0, t_final=12.0, dt=how.dt, jacobian=how.jacobian)[0]
    b = simulate(rhs, x0, t_final=12.0, dt=1.0 / 600.0)[0]
    truth = x0[:, 0] * x0[:, 1] < 2
    assert np.mean(a == b) > 0.99 and np.mean(a == truth) > 0.99
    assert a.sum() > 0.5 * len(x0)
