"""The catalogue: the seed systems of the paper (2-D) and higher-dimensional benchmarks.

The seed systems (Van der Pol, path following, pendulum) come with the paper's default
domains; :func:`cartpole` (4 states) and :func:`planar_quadrotor` (6 states) are the usual
benchmarks of the neural-Lyapunov-control literature, with their published parameters.
:func:`lyznet_10d` and :func:`lyznet_chain` are interconnected systems of 2-D subsystems
that declare their structure (``subsystems``): they are certified compositionally
(:mod:`nlyap_opt.certification.compositional`).
"""

from __future__ import annotations

import casadi as ca

from .base import System

__all__ = ["van_der_pol", "unicycle_path_following", "inverted_pendulum", "cartpole",
           "planar_quadrotor", "lyznet_10d", "lyznet_chain"]


def van_der_pol(mu: float = 1.0) -> System:
    r"""Reversed-time Van der Pol oscillator (no input).

    .. math:: \dot x_1 = -x_2, \qquad \dot x_2 = x_1 + \mu (x_1^2 - 1) x_2

    The origin is asymptotically stable; its region of attraction is the inside of the
    (unstable) limit cycle, of area 13.72 for ``mu = 1``.
    """
    x = ca.SX.sym("x", 2)
    f = ca.vertcat(-x[1], x[0] + mu * (x[0] ** 2 - 1) * x[1])
    return System(
        "van_der_pol", x, None, f,
        state_box=[[-1.5, 1.5], [-1.5, 1.5]],
        params={"mu": mu},
        state_names=["x1", "x2"],
        description="reversed-time Van der Pol oscillator",
        known_state_derivatives=(0,),
    )


def unicycle_path_following(v: float = 1.0, curvature: float = 1.0,
                            max_turn_rate: float = 5.0) -> System:
    r"""Kinematic unicycle following a circle: distance and heading errors.

    .. math:: \dot d_e = v \sin\theta_e, \qquad
              \dot\theta_e = \omega - \frac{v \kappa \cos\theta_e}{1 - d_e \kappa}

    Input: the turn rate ``ω`` in ``[-max_turn_rate, max_turn_rate]``; equilibrium input
    ``ω = v κ``.
    """
    x = ca.SX.sym("x", 2)
    u = ca.SX.sym("u", 1)
    d, th = x[0], x[1]
    f = ca.vertcat(v * ca.sin(th), u - v * curvature * ca.cos(th) / (1 - d * curvature))
    return System(
        "unicycle_path_following", x, u, f,
        state_box=[[-0.8, 0.8], [-0.8, 0.8]],
        input_box=[[-max_turn_rate, max_turn_rate]],
        params={"v": v, "curvature": curvature, "max_turn_rate": max_turn_rate},
        state_names=["d_e", "theta_e"], input_names=["omega"],
        description="unicycle path following (unit circle)",
    )


def inverted_pendulum(m: float = 0.15, l: float = 0.5, g: float = 9.81, b: float = 0.1,  # noqa: E741
                      max_torque: float = 20.0) -> System:
    r"""Inverted pendulum with viscous friction.

    .. math:: \dot\theta = \omega, \qquad
              \dot\omega = \frac{m g l \sin\theta + u - b\,\omega}{m l^2}
    """
    x = ca.SX.sym("x", 2)
    u = ca.SX.sym("u", 1)
    f = ca.vertcat(x[1], (m * g * l * ca.sin(x[0]) + u[0] - b * x[1]) / (m * l**2))
    return System(
        "inverted_pendulum", x, u, f,
        state_box=[[-4.0, 4.0], [-4.0, 4.0]],
        input_box=[[-max_torque, max_torque]],
        params={"m": m, "l": l, "g": g, "b": b, "max_torque": max_torque},
        state_names=["theta", "omega"], input_names=["torque"],
        description="inverted pendulum with friction",
        known_state_derivatives=(0,),
    )


def cartpole(M: float = 1.0, m: float = 0.1, l: float = 0.5, g: float = 9.8,  # noqa: E741
             max_force: float = 10.0) -> System:
    r"""Cart-pole (inverted pendulum on a cart), upright equilibrium at the origin.

    States ``(p, v, θ, ω)``: cart position and velocity, pole angle from the upright (rad),
    pole angular velocity; input: the horizontal force ``F`` on the cart. Frictionless
    equations of Barto, Sutton & Anderson (1983), as in OpenAI Gym's ``CartPole``:

    .. math::
        \dot p = v, \qquad \dot\theta = \omega, \qquad
        \dot\omega = \frac{g \sin\theta - \cos\theta\, h}
                             {l \left(\tfrac43 - \tfrac{m \cos^2\theta}{M + m}\right)},
        \qquad
        \dot v = h - \frac{m l\, \dot\omega \cos\theta}{M + m},
        \qquad h = \frac{F + m l \omega^2 \sin\theta}{M + m}.

    Parameters (Barto, Sutton & Anderson, "Neuronlike adaptive elements that can solve
    difficult learning control problems", IEEE Trans. SMC 13(5), 1983; the same values in
    Gym's ``CartPole-v1``): cart mass ``M = 1.0`` kg, pole mass ``m = 0.1`` kg, pole
    half-length ``l = 0.5`` m, ``g = 9.8`` m/s², force limit ``|F| ≤ 10`` N (Gym's
    ``force_mag``). Equilibrium input ``u_eq = 0``.

    Notes
    -----
    ``∂f/∂F`` depends on ``θ``: the system is control-affine with a state-dependent input
    matrix, so the learned-dynamics model ``"control_affine"`` (constant ``B``) does not
    apply; learn the ``"full"`` model of the unknown components ``v̇, ω̇``.
    """
    x = ca.SX.sym("x", 4)
    u = ca.SX.sym("u", 1)
    v, th, om = x[1], x[2], x[3]
    total = M + m
    h = (u[0] + m * l * om**2 * ca.sin(th)) / total
    om_dot = (g * ca.sin(th) - ca.cos(th) * h) / (l * (4.0 / 3.0 - m * ca.cos(th) ** 2 / total))
    v_dot = h - m * l * om_dot * ca.cos(th) / total
    f = ca.vertcat(v, v_dot, om, om_dot)
    return System(
        "cartpole", x, u, f,
        state_box=[[-1.0, 1.0], [-1.0, 1.0], [-1.0, 1.0], [-1.0, 1.0]],
        input_box=[[-max_force, max_force]],
        u_eq=[0.0],
        params={"M": M, "m": m, "l": l, "g": g, "max_force": max_force},
        state_names=["p", "v", "theta", "omega"], input_names=["force"],
        description="cart-pole (Barto-Sutton-Anderson 1983), pole upright",
        known_state_derivatives=(0, 2),
    )


def planar_quadrotor(m: float = 0.486, l: float = 0.25, J: float = 0.00383,  # noqa: E741
                     g: float = 9.81, max_thrust: float | None = None) -> System:
    r"""Planar (2-D) quadrotor at hover, two rotor thrusts.

    States ``(x, y, θ, ẋ, ẏ, θ̇)``: horizontal and vertical position, pitch angle (rad) and
    their rates; inputs: the thrusts ``u₁, u₂`` of the two rotors at distance ``l`` from
    the centre of mass:

    .. math::
        \ddot x = -\frac{(u_1 + u_2) \sin\theta}{m}, \qquad
        \ddot y = \frac{(u_1 + u_2) \cos\theta}{m} - g, \qquad
        \ddot\theta = \frac{l (u_1 - u_2)}{J}.

    Parameters as in Dai, Landry, Yang, Pavone & Tedrake, "Lyapunov-stable neural-network
    control", RSS 2021 (and the later verification-aware NN-Lyapunov papers that reuse
    their planar quadrotor): ``m = 0.486`` kg, ``l = 0.25`` m, ``J = 0.00383`` kg·m²,
    ``g = 9.81`` m/s². Hover input ``u_eq = m g / 2`` per rotor. The input box is
    ``[-max_thrust, max_thrust]`` per rotor (default ``max_thrust = m g``, twice the
    hover thrust): it is symmetric because the toolbox's saturated controller
    ``C·tanh(Kx + b)`` is; thrusts are not constrained to be non-negative here.

    Notes
    -----
    The input matrix depends on ``θ`` (not the ``"control_affine"`` learned model).
    """
    if max_thrust is None:
        max_thrust = m * g
    x = ca.SX.sym("x", 6)
    u = ca.SX.sym("u", 2)
    th = x[2]
    thrust = u[0] + u[1]
    f = ca.vertcat(x[3], x[4], x[5],
                   -thrust * ca.sin(th) / m,
                   thrust * ca.cos(th) / m - g,
                   l * (u[0] - u[1]) / J)
    u_eq = 0.5 * m * g
    return System(
        "planar_quadrotor", x, u, f,
        state_box=[[-1.0, 1.0]] * 6,
        input_box=[[-max_thrust, max_thrust]] * 2,
        u_eq=[u_eq, u_eq],
        params={"m": m, "l": l, "J": J, "g": g, "max_thrust": max_thrust},
        state_names=["x", "y", "theta", "x_dot", "y_dot", "theta_dot"],
        input_names=["thrust_1", "thrust_2"],
        description="planar quadrotor (Dai et al. 2021 parameters), hover",
        known_state_derivatives=(0, 1, 2),
    )


def _lyznet_block(x, link=None) -> list:
    """The ten right-hand sides of one LyZNet 10-D block in the states ``x[0:10]``.

    Five damped oscillators ``(x_{2k-1}, x_{2k})``, ``ẋ_{2k-1} = -x_{2k-1} + 0.5 x_{2k}``,
    ``ẋ_{2k} = -0.5 x_{2k-1} - x_{2k}``, coupled by the quadratic terms of the published
    example; ``link`` (an expression, or None) is added to the equation of ``x7``, the one
    oscillator without an input in the published block.
    """
    f = [
        -x[0] + 0.5 * x[1] - 0.1 * x[8] ** 2,
        -0.5 * x[0] - x[1],
        -x[2] + 0.5 * x[3] - 0.1 * x[0] ** 2,
        -0.5 * x[2] - x[3],
        -x[4] + 0.5 * x[5] + 0.1 * x[6] ** 2,
        -0.5 * x[4] - x[5],
        -x[6] + 0.5 * x[7],
        -0.5 * x[6] - x[7],
        -x[8] + 0.5 * x[9],
        -0.5 * x[8] - x[9] + 0.1 * x[1] ** 2,
    ]
    if link is not None:
        f[6] = f[6] + link
    return f


def lyznet_10d(radius: float = 1.0) -> System:
    r"""LyZNet's 10-D interconnected system (no input) on :math:`[-r, r]^{10}` (``radius``
    ``r = 1`` by default).

    .. math::
        \dot x_1 &= -x_1 + 0.5 x_2 - 0.1 x_9^2, & \dot x_2 &= -0.5 x_1 - x_2, \\
        \dot x_3 &= -x_3 + 0.5 x_4 - 0.1 x_1^2, & \dot x_4 &= -0.5 x_3 - x_4, \\
        \dot x_5 &= -x_5 + 0.5 x_6 + 0.1 x_7^2, & \dot x_6 &= -0.5 x_5 - x_6, \\
        \dot x_7 &= -x_7 + 0.5 x_8, & \dot x_8 &= -0.5 x_7 - x_8, \\
        \dot x_9 &= -x_9 + 0.5 x_{10}, & \dot x_{10} &= -0.5 x_9 - x_{10} + 0.1 x_2^2.

    Five 2-D subsystems ``(x1, x2), …, (x9, x10)`` coupled by the quadratic terms. The
    equations and the domain are those of the 10-D example of the LyZNet toolbox (file
    ``examples/hscc24/ex4a_10d_system_monolith_domain_1.py`` of its repository; Liu, Meng,
    Fitzsimmons & Zhou, "LyZNet: a lightweight Python tool for learning and verifying
    neural Lyapunov functions and regions of attraction", HSCC 2024), whose compositional
    variant (``ex4b_10d_system_vector``) uses the same five subsystems; LyZNet's other
    examples use the domains :math:`[-4, 4]^{10}` and :math:`[-10, 10]^{10}`
    (``radius``).
    """
    x = ca.SX.sym("x", 10)
    return System(
        "lyznet_10d", x, None, ca.vertcat(*_lyznet_block(x)),
        state_box=[[-radius, radius]] * 10,
        params={"radius": radius},
        state_names=[f"x{i + 1}" for i in range(10)],
        description="LyZNet 10-D interconnected system (5 coupled oscillators)",
        subsystems=[(2 * k, 2 * k + 1) for k in range(5)],
    )


def lyznet_chain(blocks: int = 2, link: float = 0.1, radius: float = 1.0) -> System:
    r"""A chain of ``blocks`` copies of :func:`lyznet_10d` (``10·blocks`` states, no input).

    Block ``b`` (states ``x_{10b+1} … x_{10b+10}``) has the equations of
    :func:`lyznet_10d`; for ``b ≥ 1`` its ``x_{10b+7}`` equation also receives
    ``link · x_{10(b-1)+1}²`` from the previous block (with ``link = 0`` the blocks are
    decoupled, as in LyZNet's ``20d_system`` example). The domain is
    :math:`[-\text{radius}, \text{radius}]^{10·\text{blocks}}`; the subsystems are the
    ``5·blocks`` oscillators.
    """
    blocks = int(blocks)
    if blocks < 1:
        raise ValueError(f"lyznet_chain needs blocks >= 1, got {blocks}")
    n = 10 * blocks
    x = ca.SX.sym("x", n)
    f = []
    for b in range(blocks):
        xb = x[10 * b:10 * b + 10]
        f += _lyznet_block(xb, None if b == 0 else link * x[10 * (b - 1)] ** 2)
    return System(
        "lyznet_chain", x, None, ca.vertcat(*f),
        state_box=[[-radius, radius]] * n,
        params={"blocks": blocks, "link": link, "radius": radius},
        state_names=[f"x{i + 1}" for i in range(n)],
        description=f"chain of {blocks} LyZNet 10-D blocks ({n} states)",
        subsystems=[(2 * k, 2 * k + 1) for k in range(5 * blocks)],
    )
