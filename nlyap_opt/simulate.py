"""Vectorised fixed-step simulation (one RK4 for every consumer)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

__all__ = ["rk4_step", "simulate_converges"]


def rk4_step(rhs: Callable[[np.ndarray], np.ndarray], x: np.ndarray, dt: float) -> np.ndarray:
    """One classical Runge–Kutta step for a batch ``x`` of shape ``(N, nx)``."""
    k1 = rhs(x)
    k2 = rhs(x + 0.5 * dt * k1)
    k3 = rhs(x + 0.5 * dt * k2)
    k4 = rhs(x + dt * k3)
    return x + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)


def simulate_converges(rhs: Callable[[np.ndarray], np.ndarray], x0, t_final: float = 30.0,
                       dt: float = 0.02, tol: float = 1e-3, blow_up: float = 1e6
                       ) -> np.ndarray:
    """Per initial state: does ``x' = rhs(x)`` reach ``‖x‖ < tol`` within ``t_final``?

    All states are integrated at once; a state is dropped once it has converged or left
    ``blow_up`` (or become non-finite).
    """
    x = np.array(x0, dtype=float)
    done = np.zeros(len(x), bool)
    alive = np.ones(len(x), bool)
    with np.errstate(all="ignore"):
        for _ in range(int(np.ceil(t_final / dt))):
            idx = np.nonzero(alive)[0]
            if not len(idx):
                break
            z = rk4_step(rhs, x[idx], dt)
            x[idx] = z
            conv = np.linalg.norm(z, axis=1) < tol
            blow = ~np.all(np.isfinite(z), axis=1) | (np.max(np.abs(z), axis=1) > blow_up)
            done[idx[conv]] = True
            alive[idx[conv | blow]] = False
    return done
