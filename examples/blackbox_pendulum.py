"""A black-box inverted pendulum with smooth (tanh) Coulomb friction, given as a callable.

The tool never sees a formula: ``make()`` wraps a batched numpy function ``f(X, U)`` (think
of it as a simulator's right-hand side) into a :class:`systems.System` of kind
``"callable"``, with the declared assumptions the certificate needs::

    θ' = ω
    ω' = (m g l sin θ + u − b ω − c tanh(k ω)) / (m l²)

m = 0.15, l = 0.5, g = 9.81, viscous b = 0.1, Coulomb c = 0.05 smoothed with k = 5;
X = [−4, 4]², U = [−20, 20] (the catalogue pendulum's box), u_eq = 0.

Declared (from the formula above, which the user knows and the tool does not):

- K_f = 34.5 ≥ the Frobenius norm of the Jacobian over X × U,
  sqrt(1 + (g/l)² + ((b + c k)/(m l²))² + (1/(m l²))²) = 34.41;
- H = 26 ≥ max(g/l, c k² · 4/(3√3) / (m l²)) = max(19.62, 25.66)
  (|d²/dω² tanh(kω)| ≤ k² · 4/(3√3));
- control-affine with B = (0, 1/(m l²)) = (0, 26.666…).

Run it: ``nlyap run --system examples/blackbox_pendulum.toml`` (spec file pointing to
``make``), or in Python ``examples.blackbox_pendulum.make()``.
"""

from __future__ import annotations

import numpy as np

import systems

M, L, G, B_VISC, C_COUL, K_SMOOTH = 0.15, 0.5, 9.81, 0.1, 0.05, 5.0
INERTIA = M * L**2


def pendulum_rhs(X: np.ndarray, U: np.ndarray) -> np.ndarray:
    """The black box: ``(N, 2), (N, 1) -> (N, 2)`` float64."""
    th, om, u = X[:, 0], X[:, 1], U[:, 0]
    dom = (M * G * L * np.sin(th) + u - B_VISC * om - C_COUL * np.tanh(K_SMOOTH * om)) / INERTIA
    return np.stack([om, dom], axis=1)


DECLARED = systems.Declarations(lipschitz=34.5, hessian=26.0,
                                input_matrix=[[0.0], [1.0 / INERTIA]])


def make() -> systems.System:
    """The black-box pendulum as a :class:`systems.System` (kind ``"callable"``)."""
    return systems.System.from_callable(
        "blackbox_pendulum", pendulum_rhs, nx=2, nu=1,
        state_box=[[-4.0, 4.0], [-4.0, 4.0]], input_box=[[-20.0, 20.0]], u_eq=[0.0],
        state_names=["theta", "omega"], input_names=["torque"],
        known_rhs={"theta": lambda x, u: x[1]},          # θ' = ω is known exactly
        declarations=DECLARED,
        params={"m": M, "l": L, "g": G, "b": B_VISC, "c": C_COUL, "k": K_SMOOTH},
        description="inverted pendulum with smooth Coulomb friction (black box)",
    )


if __name__ == "__main__":
    s = make()
    print(s, "has_model:", s.has_model)
    for line in s.describe_assumptions():
        print(" -", line)
