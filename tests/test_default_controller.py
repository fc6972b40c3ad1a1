"""The training simulations of the default method under a stiff closed loop.

A high-gain controller gives the closed loop a fast mode at the origin; a fixed RK4 step
outside RK4's stability region for that mode makes the simulated state oscillate around the
origin instead of reaching it, and every training state would count as outside the region
of attraction. :func:`nlyap_opt.candidates.cegis.simulation_step` shortens the step there.
"""

import numpy as np
import pytest

from nlyap_opt.candidates.cegis import RK4_STABLE_RADIUS, simulation_step
from nlyap_opt.kernel.simulate import simulate


def test_simulation_step_keeps_a_stiff_closed_loop_converging():
    """x' = Ax with eigenvalues −1 and −150: RK4 at h = 0.04 (h·λ = −6) oscillates away from
    the origin, at simulation_step's step it converges with the exact trajectory cost
    x₀ᵀPx₀ (AᵀP + PA = −I) up to an error within the fast mode's own small share of it
    (that mode decays in a few steps, the trapezoidal rule is coarse there)."""
    A = np.diag([-1.0, -150.0])
    X = np.array([[1.0, 0.5], [-0.3, 0.2], [0.5, -1.0]])

    def rhs(x):
        return x @ A.T

    assert not simulate(rhs, X, t_final=30.0, dt=0.04, tol=1e-3)[0].any()
    h = simulation_step(A, 0.04)
    assert h == pytest.approx(RK4_STABLE_RADIUS / 150.0) and h < 0.04
    conv, cost = simulate(rhs, X, t_final=30.0, dt=h, tol=1e-6)
    assert conv.all()
    slow, fast = X[:, 0] ** 2 / 2.0, X[:, 1] ** 2 / 300.0
    assert np.all(np.abs(cost - slow - fast) <= 10 * fast)
    # a slow loop keeps the configured step; so does a complex pair within the radius
    assert simulation_step(np.diag([-1.0, -2.0]), 0.04) == 0.04
    rot = np.array([[-0.5, 20.0], [-20.0, -0.5]])
    assert simulation_step(rot, 0.1) == 0.1 and simulation_step(rot, 0.2) < 0.2


def test_training_simulations_of_a_high_gain_pendulum_reach_the_origin():
    """The catalogue pendulum under the saturated LQR gain of Q = diag(1, 20), R = 1 (closed-
    loop eigenvalues −0.28 and −119 at the origin): at the default method's cegis.sim_dt
    (0.04 s, h·λ = −4.8) no training state reaches ‖x‖ < 0.01; at the step taken from the
    learner's closed-loop Jacobian (which includes κ) all of those in a disc of radius 2
    do (the true ROA holds it)."""
    import systems
    from nlyap_opt.candidates.learning import LyapunovLearner, TrainConfig
    from nlyap_opt.design.control import lqr, saturated_controller
    from nlyap_opt.kernel.sampling import sample_ball

    s = systems.get("inverted_pendulum")
    res = lqr(s, np.diag([1.0, 20.0]), 1.0)
    learner = LyapunovLearner(s, saturated_controller(s, res.K, 20.0), None, TrainConfig())
    A = learner.closed_loop_jacobian().detach().numpy()
    np.testing.assert_allclose(A, res.A - res.B @ res.K, rtol=1e-10)
    h = simulation_step(A, 0.04)
    assert h * np.abs(np.linalg.eigvals(A)).max() == pytest.approx(RK4_STABLE_RADIUS)
    X = sample_ball(200, 2, 2.0, np.random.default_rng(0))

    def rhs(x):
        import torch
        with torch.no_grad():
            return learner.rhs(torch.as_tensor(x)).numpy()

    assert not simulate(rhs, X, t_final=30.0, dt=0.04, tol=1e-2)[0].any()
    assert simulate(rhs, X, t_final=30.0, dt=h, tol=1e-2)[0].all()


def test_inward_term_trains_kappa_to_keep_more_trajectories_in_the_box():
    """The catalogue pendulum on its box D = [−4, 4]² under u = 20·tanh(·) from the LQR gain
    of Q = I, R = I: trained on the inward term alone (mean relu(n·g/‖g‖) on ∂D), κ turns
    the flow inward where the torque can (the faces ω = ±4), the term decreases and the
    share of a 24 × 24 grid whose simulated trajectories converge without leaving D grows.
    The outward normals are those of the box's faces."""
    import systems
    from nlyap_opt.candidates.cegis import outward_normals
    from nlyap_opt.candidates.learning import LyapunovLearner, TrainConfig
    from nlyap_opt.design.control import lqr, saturated_controller
    from nlyap_opt.kernel.domain import Box

    s = systems.get("inverted_pendulum")
    D = Box(s.state_box)
    rng = np.random.default_rng(0)
    S = D.sample_boundary(2000, rng)
    N = outward_normals(D, S)
    face = np.abs(S) >= 4.0 - 1e-12
    np.testing.assert_allclose(np.abs(N)[face.sum(1) == 1], face[face.sum(1) == 1], atol=1e-9)
    np.testing.assert_allclose((N * S).sum(1), np.abs(S).max(1), rtol=1e-6)  # n·x = 4 > 0
    cfg = TrainConfig(hidden=[4], features=2, steps=300, batch=512, lr=0.02, w_decrease=0.0,
                      w_inside=0.0, w_outside=0.0, w_anchor=0.0, w_inward=1.0)
    learner = LyapunovLearner(s, saturated_controller(s, lqr(s).K, 20.0), None, cfg)
    g = np.linspace(-3.9, 3.9, 24)
    X = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)

    def measure():
        import torch
        with torch.no_grad():
            gs = learner.rhs(torch.as_tensor(S)).numpy()
        inward = np.maximum((N * gs).sum(1) / np.linalg.norm(gs, axis=1), 0).mean()
        h = simulation_step(learner.closed_loop_jacobian().detach().numpy(), 0.02)
        _, ctrl = learner.export()
        conv = simulate(lambda x: s.evaluate(x, ctrl.numpy(x)), X, t_final=30.0, dt=h,
                        tol=1e-2, stay=D.contains)[0]
        return inward, conv.mean()

    (out0, stay0) = measure()
    learner.train(X, S, 0.0, sphere_normals=N)
    (out1, stay1) = measure()
    assert out1 < 0.8 * out0
    assert stay1 > stay0 + 0.05


def test_inward_term_is_deterministic_and_leaves_a_system_without_inputs_alone():
    """Two trainings with the inward term give the same V and κ bytes; on Van der Pol (no
    input, no κ) w_inward = 10 and 0 give the same V bytes."""
    import torch

    import systems
    from nlyap_opt.candidates.cegis import outward_normals
    from nlyap_opt.candidates.learning import LyapunovLearner, TrainConfig
    from nlyap_opt.design.control import lqr, saturated_controller
    from nlyap_opt.kernel.domain import Box

    def train(name, w_inward):
        s = systems.get(name)
        D = Box(s.state_box)
        rng = np.random.default_rng(3)
        S, X = D.sample_boundary(500, rng), D.sample(1000, rng)
        ctrl = saturated_controller(s, lqr(s).K, 20.0) if s.nu else None
        L = LyapunovLearner(s, ctrl, None, TrainConfig(hidden=[6], features=3, steps=60,
                                                       batch=256, w_inward=w_inward))
        L.train(X, S, 0.0, sphere_normals=outward_normals(D, S))
        V, k = L.export()
        return b"".join(layer.weight.tobytes() + layer.bias.tobytes()
                        for net in (V, k) if net is not None for layer in net.layers), L

    a, La = train("inverted_pendulum", 10.0)
    b, _ = train("inverted_pendulum", 10.0)
    c, Lc = train("inverted_pendulum", 0.0)
    assert a == b and a != c
    assert not torch.equal(La.G, Lc.G)
    assert train("van_der_pol", 10.0)[0] == train("van_der_pol", 0.0)[0]
