"""Uniform samples of balls, annuli and spheres (numpy only; the core layer)."""

from __future__ import annotations

import numpy as np

__all__ = ["sample_ball", "sample_sphere"]


def sample_ball(n: int, dim: int, radius: float, rng: np.random.Generator,
                inner: float = 0.0) -> np.ndarray:
    """Uniform samples of the annulus ``inner ≤ ‖x‖ ≤ radius`` in ``dim`` dimensions."""
    d = rng.standard_normal((n, dim))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = (inner**dim + (radius**dim - inner**dim) * rng.random(n)) ** (1.0 / dim)
    return d * r[:, None]


def sample_sphere(n: int, dim: int, radius: float, rng: np.random.Generator) -> np.ndarray:
    """Uniform samples of the sphere ``‖x‖ = radius``."""
    d = rng.standard_normal((n, dim))
    return radius * d / np.linalg.norm(d, axis=1, keepdims=True)
