"""Vectorised fixed-step simulation (one RK4 for every consumer)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["STIFF_STEP", "IMPLICIT_RATIO", "SLOW_FACTOR", "HORIZON_CAP", "Integration",
           "at_other_equilibrium", "horizon", "integration", "jacobian_at_origin", "linear_modes",
           "rk4_step", "ros2_step", "simulate", "simulate_converges", "stable_step", "trajectories"]

#: a fixed RK4 step h of a closed loop with linearisation A at the origin satisfies
#: h·ρ(A) ≤ STIFF_STEP (ρ the spectral radius): every linear mode then lies well inside RK4's
#: stability region (|R(hλ)| ≤ 1 for Re λ ≤ 0, |hλ| ≤ 2.5) and decays at nearly its rate
#: (|R(−1) − e⁻¹| < 0.01). A step too long for a stiff loop's fast mode (RK4 is unstable
#: for hλ < −2.79) makes no simulated trajectory converge
STIFF_STEP = 1.0


def linear_modes(A) -> tuple[float, float]:
    """``(ρ(A), min |Re λ|)``: the speed of the fastest and the decay rate of the slowest
    mode of the linearisation ``A`` (their ratio is the loop's stiffness)."""
    A = np.asarray(A, dtype=float)
    if not A.size:
        return 0.0, 0.0
    ev = np.linalg.eigvals(A)
    return float(np.max(np.abs(ev))), float(np.min(np.abs(ev.real)))


def stable_step(dt: float, A) -> float:
    """``dt``, shortened to ``STIFF_STEP / ρ(A)`` where the linearisation ``A`` at the origin
    has a faster mode.

    Examples
    --------
    >>> stable_step(0.04, np.array([[0.0, 1.0], [-2.0, -3.0]]))
    0.04
    >>> round(stable_step(0.04, np.diag([-1.0, -200.0])), 6)
    0.005
    """
    rho = linear_modes(A)[0]
    return min(dt, STIFF_STEP / rho) if rho > 0 else dt


#: a simulated horizon is at least this multiple of the time the slowest linear mode at the
#: origin takes to shrink a state from the domain's size to the convergence tolerance
#: (:func:`horizon`): a lightly damped loop (a pendulum with damping 0.1 decays at 0.05 per
#: second) needs minutes of model time where a well-damped one needs seconds
SLOW_FACTOR = 1.5
#: ... and it is extended to at most this multiple of the configured one
HORIZON_CAP = 10.0
#: decay rates at most this fraction of the fastest mode's speed (at least 1 per s) count
#: as none: below the accuracy of a finite-difference linearisation
_RATE_FLOOR = 1e-6


def horizon(t_final: float, A, radius: float, tol: float) -> float:
    r"""``t_final``, extended for a slowly converging loop: at least
    :data:`SLOW_FACTOR` · ``ln(radius / tol) / σ``, where ``σ`` is the decay rate of the
    slowest mode of the linearisation ``A`` at the origin, and at most
    :data:`HORIZON_CAP` · ``t_final``. Unchanged where ``A`` is not Hurwitz or its
    slowest rate is below 10⁻⁶ of its fastest mode's speed (at least 1 per s): a centre,
    of whose decay the linearisation tells nothing, or a rate fast enough.

    Examples
    --------
    >>> horizon(30.0, np.array([[0.0, 1.0], [-2.0, -3.0]]), 3.0, 1e-3)   # σ = 1
    30.0
    >>> round(horizon(60.0, np.array([[0.0, 1.0], [-1.0, -0.1]]), 4.6, 1e-3), 1)  # σ = 0.05
    253.0
    """
    A = np.asarray(A, dtype=float)
    if not A.size or not np.all(np.isfinite(A)) or not radius > tol > 0:
        return float(t_final)
    ev = np.linalg.eigvals(A)
    sigma = float(np.min(-ev.real))
    # a rate below what A can resolve (a finite-difference Jacobian of x' = -x³ is -1e-12)
    # is no rate: a centre, whose decay the linearisation does not tell
    if not sigma > _RATE_FLOOR * max(1.0, float(np.max(np.abs(ev)))):
        return float(t_final)
    need = SLOW_FACTOR * math.log(radius / tol) / sigma
    return float(min(max(t_final, need), HORIZON_CAP * t_final))


#: RK4 at :func:`stable_step` takes ``ρ(A)·dt / STIFF_STEP`` steps per requested step ``dt``;
#: past this many, :func:`integration` steps ``dt`` with the linearly implicit ROS2 instead
#: (a loop whose fastest mode is far faster than the requested step: every catalogue
#: system and example needs at most 5 RK4 steps per step; Fossil's linear chain HighOrd4
#: would need 160 per step of 0.04 s)
IMPLICIT_RATIO = 20.0
#: ROS2's γ (Verwer, Spee, Blom and Hundsdorfer 1999): L-stable, order 2 for any matrix in
#: place of the Jacobian (a W-method)
_ROS2_GAMMA = 1.0 + 1.0 / np.sqrt(2.0)


@dataclass(frozen=True)
class Integration:
    """How a closed loop is simulated: fixed-step RK4 at ``dt`` (``jacobian`` ``None``), or
    the linearly implicit ROS2 at ``dt`` with the closed loop's Jacobian at the origin."""

    dt: float
    jacobian: np.ndarray | None = None

    @property
    def method(self) -> str:
        """``"RK4"`` or ``"ROS2"``."""
        return "RK4" if self.jacobian is None else "ROS2"


def integration(dt: float, A) -> Integration:
    """The integration of a closed loop with linearisation ``A`` at the origin for a requested
    step ``dt``: RK4 at :func:`stable_step`, or, where that would take more than
    :data:`IMPLICIT_RATIO` steps per ``dt`` (a stiff loop), ROS2 at ``dt`` with ``A``.

    Examples
    --------
    >>> integration(0.04, np.diag([-1.0, -200.0]))          # 8 RK4 steps per 0.04 s
    Integration(dt=0.005, jacobian=None)
    >>> integration(0.04, np.diag([-1.0, -4000.0])).method   # 160: implicit
    'ROS2'
    """
    A = np.asarray(A, dtype=float)
    if linear_modes(A)[0] * dt > IMPLICIT_RATIO * STIFF_STEP and np.all(np.isfinite(A)):
        return Integration(float(dt), A)
    return Integration(stable_step(dt, A))


def jacobian_at_origin(rhs: Callable[[np.ndarray], np.ndarray], n: int,
                       h: float = 1e-6) -> np.ndarray:
    """``∂rhs/∂x(0)`` by central differences (``rhs`` maps a batch ``(N, n)`` to ``(N, n)``)."""
    E = h * np.eye(n)
    with np.errstate(all="ignore"):
        return ((rhs(E) - rhs(-E)) / (2 * h)).T


def rk4_step(rhs: Callable[[np.ndarray], np.ndarray], x: np.ndarray, dt: float) -> np.ndarray:
    """One classical Runge–Kutta step for a batch ``x`` of shape ``(N, nx)``."""
    k1 = rhs(x)
    k2 = rhs(x + 0.5 * dt * k1)
    k3 = rhs(x + 0.5 * dt * k2)
    k4 = rhs(x + dt * k3)
    return x + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)


def ros2_step(rhs: Callable[[np.ndarray], np.ndarray], x: np.ndarray, dt: float,
              W_inv: np.ndarray) -> np.ndarray:
    r"""One step of the linearly implicit ROS2 for a batch ``x`` of shape ``(N, nx)``:
    :math:`W k_1 = f(x)`, :math:`W k_2 = f(x + h k_1) - 2 k_1`,
    :math:`x^+ = x + \tfrac32 h k_1 + \tfrac12 h k_2` with :math:`W = I - \gamma h J`
    (``W_inv`` its inverse; ``J`` the Jacobian at the origin). L-stable: the fast modes of a
    stiff loop decay at any step, where RK4 blows up past :math:`h\rho(J) \approx 2.8`."""
    k1 = rhs(x) @ W_inv.T
    k2 = (rhs(x + dt * k1) - 2.0 * k1) @ W_inv.T
    return x + dt * (1.5 * k1 + 0.5 * k2)


def simulate(rhs: Callable[[np.ndarray], np.ndarray], x0, t_final: float = 30.0,
             dt: float = 0.02, tol: float = 1e-3, blow_up: float = 1e6,
             target: Callable[[np.ndarray], np.ndarray] | None = None,
             return_undecided: bool = False,
             stay: Callable[[np.ndarray], np.ndarray] | None = None,
             track: Callable[[np.ndarray], np.ndarray] | None = None,
             jacobian: np.ndarray | None = None,
             final: bool = False) -> tuple[np.ndarray, ...]:
    r"""Integrate ``x' = rhs(x)`` from every row of ``x0`` at once: fixed-step RK4, or ROS2
    (:func:`ros2_step`) with ``jacobian`` given (see :func:`integration`).

    ``target`` (optional, batch of states → bool) marks a set known to lie in the region of
    attraction, e.g. a certified quadratic sublevel set: a state that enters it counts as
    converged there (slowly converging closed loops then need far fewer steps).

    ``stay`` (optional, batch of states → bool) marks a set the trajectory must not leave: a
    state whose trajectory leaves it stops there and does not count as converged. Then
    ``converged`` marks the states that reach the origin *without leaving* the set, the only
    ones a sublevel set inside that set can hold (it must be forward invariant).

    ``track`` (optional, batch of states → float) is a function whose largest value along
    each trajectory is returned (``peak``), e.g. a domain's gauge: the largest gauge
    reached from ``x₀`` on is non-increasing along trajectories.

    Returns
    -------
    converged : (N,) bool
        ``‖x(t)‖ < tol`` was reached within ``t_final``.
    cost : (N,) float
        :math:`\int_0^{t^*} \|x(t)\|^2\,dt` (trapezoidal rule) up to the time :math:`t^*` a
        state converged, left ``blow_up`` (or became non-finite), or ``t_final``. For a
        converged state it is the trajectory cost to the origin up to a tail of order
        ``tol²``: the data-driven Lyapunov (Zubov-type) function whose sublevel sets grow to
        the region of attraction (it decreases along trajectories at rate ``‖x‖²``).
    undecided : (N,) bool, only with ``return_undecided``
        Neither converged nor left ``blow_up`` within ``t_final``: the horizon was too short
        to tell (a slow approach to the origin, or a bounded non-converging orbit).
    peak : (N,) float, only with ``track``
        The largest ``track(x(t))`` from ``t = 0`` until the state converged, stopped or
        ``t_final`` (after ``undecided`` when both are asked for).
    x_end : (N, nx) float, only with ``final``
        The state where each trajectory stopped (converged, left, or at ``t_final``); last.
    """
    x = np.array(x0, dtype=float)
    if jacobian is None:
        def step(z):
            return rk4_step(rhs, z, dt)
    else:
        J = np.asarray(jacobian, dtype=float)
        W_inv = np.linalg.inv(np.eye(len(J)) - _ROS2_GAMMA * dt * J)

        def step(z):
            return ros2_step(rhs, z, dt, W_inv)
    done = np.zeros(len(x), bool)
    alive = np.ones(len(x), bool)
    cost = np.zeros(len(x))
    peak = None if track is None else np.array(track(x), dtype=float)
    with np.errstate(all="ignore"):
        for _ in range(int(np.ceil(t_final / dt))):
            idx = np.nonzero(alive)[0]
            if not len(idx):
                break
            z0 = x[idx]
            z = step(z0)
            x[idx] = z
            cost[idx] += 0.5 * dt * (np.einsum("ij,ij->i", z0, z0) + np.einsum("ij,ij->i", z, z))
            if peak is not None:
                peak[idx] = np.fmax(peak[idx], track(z))
            conv = np.linalg.norm(z, axis=1) < tol
            if target is not None:
                conv |= target(z)
            blow = ~np.all(np.isfinite(z), axis=1) | (np.max(np.abs(z), axis=1) > blow_up)
            if stay is not None:
                blow |= ~conv & ~stay(z)
            done[idx[conv]] = True
            alive[idx[conv | blow]] = False
    cost[~np.isfinite(cost)] = np.inf
    out = (done, cost) + ((alive & ~done,) if return_undecided else ())
    return out + ((peak,) if peak is not None else ()) + ((x,) if final else ())


def at_other_equilibrium(rhs: Callable[[np.ndarray], np.ndarray], x: np.ndarray,
                         tol: float = 1e-3, h: float = 1e-6) -> np.ndarray:
    r"""Per state of the batch ``x``: does it rest at an asymptotically stable equilibrium
    other than the origin?

    A state whose simulation neither converged to the origin nor diverged may be slow, on a
    periodic orbit, or at rest at another attractor, where it stays at any horizon. This
    tells the last case apart: with the Jacobian ``J`` of ``rhs`` at ``x`` (central
    differences, step ``h``), the Newton step ``δ = −J⁻¹ rhs(x)`` to the nearby equilibrium
    ``x* ≈ x + δ`` is at most ``tol`` long, ``x*`` lies at least ``100·tol`` from the origin,
    and every eigenvalue of ``J`` has a real part below ``−10⁻⁶·max(1, max|λ|)`` (``x*``
    attracts its neighbourhood, so the trajectory stays there and does not reach the
    origin). States near a saddle, a non-hyperbolic point or on a cycle are not claimed. A
    simulation estimate, as the true ROA it serves; no certificate rests on it.

    Examples
    --------
    >>> rhs = lambda z: np.stack([z[:, 1], -np.sin(z[:, 0]) - 0.5 * z[:, 1]], axis=1)
    >>> at_other_equilibrium(rhs, np.array([[2 * np.pi, 0.0], [np.pi, 0.0], [0.0, 0.0]]))
    array([ True, False, False])
    """
    x = np.asarray(x, dtype=float)
    N, n = x.shape
    if not N:
        return np.zeros(0, bool)
    with np.errstate(all="ignore"):
        f = rhs(x)
        J = np.empty((N, n, n))
        for j in range(n):
            e = np.zeros(n)
            e[j] = h
            J[:, :, j] = (rhs(x + e) - rhs(x - e)) / (2 * h)
        ok = np.all(np.isfinite(f), axis=1) & np.all(np.isfinite(J), axis=(1, 2))
        ok &= np.abs(np.linalg.det(np.where(ok[:, None, None], J, np.eye(n)))) > 0
        out = np.zeros(N, bool)
        idx = np.nonzero(ok)[0]
        if not len(idx):
            return out
        delta = -np.linalg.solve(J[idx], f[idx][:, :, None])[:, :, 0]
        ev = np.linalg.eigvals(J[idx])
        # decay rates below _RATE_FLOOR of the fastest mode are finite-difference noise
        stable = np.max(ev.real, axis=1) < -_RATE_FLOOR * np.maximum(np.max(np.abs(ev), axis=1), 1)
        near = np.linalg.norm(delta, axis=1) <= tol
        away = np.linalg.norm(x[idx] + delta, axis=1) >= 100 * tol
        out[idx] = stable & near & away
    return out


def simulate_converges(rhs: Callable[[np.ndarray], np.ndarray], x0, t_final: float = 30.0,
                       dt: float = 0.02, tol: float = 1e-3, blow_up: float = 1e6,
                       target: Callable[[np.ndarray], np.ndarray] | None = None
                       ) -> np.ndarray:
    """Per initial state: does ``x' = rhs(x)`` reach ``‖x‖ < tol`` within ``t_final``?

    (The ``converged`` output of :func:`simulate`.)
    """
    return simulate(rhs, x0, t_final, dt, tol, blow_up, target)[0]


def trajectories(rhs: Callable[[np.ndarray], np.ndarray], x0, t_final: float,
                 n_steps: int) -> np.ndarray:
    """The whole trajectories of ``x' = rhs(x)`` from every row of ``x0`` (fixed-step RK4).

    Returns
    -------
    (n_steps + 1, N, nx) ndarray
        ``x(k·t_final/n_steps)``; a trajectory that becomes non-finite is NaN from then on.
    """
    x = np.array(x0, dtype=float, ndmin=2)
    dt = t_final / n_steps
    out = np.empty((n_steps + 1,) + x.shape)
    out[0] = x
    with np.errstate(all="ignore"):
        for k in range(n_steps):
            x = rk4_step(rhs, x, dt)
            x[~np.isfinite(x).all(axis=1)] = np.nan
            out[k + 1] = x
    return out
