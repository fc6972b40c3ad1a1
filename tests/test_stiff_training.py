"""The default method on a stiff closed loop: the training simulations' step and the gain.

A saturated controller with a large input range gives a closed loop with a fast mode (the
catalogue pendulum: torque range 27 times the gravity torque). RK4 at a fixed step is
unstable for a mode with h·λ < −2.79: no simulated trajectory converges and no fit target
is made. :func:`nlyap_opt.candidates.cegis.simulation_step` shortens the step to the
loop's fastest linear mode. These tests check that on stiff linear loops the shortened step
converges and gives the exact trajectory cost xᵀPx (AᵀP + PA = −I), that the fixed step
does not, and that a non-stiff loop keeps ``cegis.sim_dt``.
"""

import numpy as np
import pytest
from scipy.linalg import solve_continuous_lyapunov

from nlyap_opt.candidates.cegis import STIFF_STEP, simulation_step
from nlyap_opt.kernel.simulate import simulate


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
    """x' = Ax from states on the circle of radius 2 (at x₃ = 1 in 3-D): with simulation_step(0.04, A) every
    trajectory converges and its cost ∫‖x‖² dt is x₀ᵀPx₀ (AᵀP + PA = −I) within 1 % of the largest; with
    the fixed step 0.04 (h·ρ(A) ≥ 1.6, unstable for the real stiff modes) at least one does
    not converge or its cost is off by more than that."""
    rho = np.max(np.abs(np.linalg.eigvals(A)))
    dt = simulation_step(0.04, A)
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
    assert simulation_step(0.04, np.array([[0.0, 1.0], [-1.0, 1.0]])) == 0.04
    A = np.array([[0.0, 1.0], [19.62 - 26.667 * 1.977, -2.667 - 26.667 * 0.976]])
    assert simulation_step(0.02, A) == 0.02
    assert simulation_step(0.04, A) < 0.04
    assert simulation_step(0.04, np.zeros((2, 2))) == 0.04
