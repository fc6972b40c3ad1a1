"""The seed systems of the paper, with its default domains."""

from __future__ import annotations

import casadi as ca

from .base import System

__all__ = ["van_der_pol", "unicycle_path_following", "inverted_pendulum"]


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
