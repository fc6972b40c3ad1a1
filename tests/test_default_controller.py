"""The controller's training in the default method: the inward term on ∂D.

A certified set lies in the domain D and is forward invariant, so it holds only states
whose trajectories never leave D. The inward term trains κ so that the closed loop points
into D on ∂D where the input can make it: mean relu(n·g/‖g‖) over samples of ∂D (n the
outward normal). These tests check the normals, that the term lowers the share of the
flow pointing out and raises the share of simulated trajectories that stay in D, that it
is deterministic and that it leaves a system without inputs bit-identical.
"""

import numpy as np

from nlyap_opt.kernel.simulate import simulate


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
        _, ctrl = learner.export()
        conv = simulate(lambda x: s.evaluate(x, ctrl.numpy(x)), X, t_final=30.0, dt=0.02,
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
