"""Exact rational linear algebra of float64 data (:class:`fractions.Fraction`).

Every float64 is a rational number, so a matrix of floats has an exact rational value and
questions about it (is it positive definite, what is the diagonal of its inverse) have exact
answers. The helpers here compute them without rounding; they are for the small matrices of
quadratic certificates (a few dozen rows at most: the cost grows like ``n³`` operations on
growing integers).
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np

__all__ = ["rational", "rational_matrix", "positive_definite", "inverse", "inverse_diagonal",
           "float_down", "float_up"]


def rational(v) -> Fraction:
    """The exact value of the float ``v`` (refused if it is not finite).

    Raises
    ------
    ValueError
        If ``v`` is NaN or infinite.
    """
    v = float(v)
    if not math.isfinite(v):
        raise ValueError("not finite")
    return Fraction(v)


def rational_matrix(M) -> list[list[Fraction]]:
    """The exact value of a 2-D float array, as a list of rows of :class:`Fraction`."""
    return [[rational(v) for v in row] for row in np.asarray(M, dtype=float)]


def positive_definite(M: list[list[Fraction]]) -> bool:
    """Exact test of ``M ≻ 0`` (symmetric rational ``M``): every pivot of ``LDLᵀ`` > 0."""
    A = [row[:] for row in M]
    n = len(A)
    for k in range(n):
        if A[k][k] <= 0:
            return False
        for i in range(k + 1, n):
            m = A[i][k] / A[k][k]
            if m:
                for j in range(k, n):
                    A[i][j] -= m * A[k][j]
    return True


def inverse(P: list[list[Fraction]]) -> list[list[Fraction]]:
    """The exact inverse of a rational matrix whose leading pivots are nonzero (Gauss–Jordan
    without pivoting; a positive definite ``P`` qualifies).

    Raises
    ------
    ZeroDivisionError
        If a pivot is zero (``P`` singular, or a leading minor vanishes).
    """
    n = len(P)
    A = [row[:] + [Fraction(int(i == j)) for j in range(n)] for i, row in enumerate(P)]
    for k in range(n):
        p = A[k][k]
        A[k] = [a / p for a in A[k]]
        for i in range(n):
            if i != k and A[i][k]:
                m = A[i][k]
                A[i] = [a - m * b for a, b in zip(A[i], A[k])]
    return [row[n:] for row in A]


def inverse_diagonal(P: list[list[Fraction]]) -> list[Fraction]:
    """The exact diagonal of ``P⁻¹`` (``P ≻ 0``; see :func:`inverse`)."""
    Q = inverse(P)
    return [Q[k][k] for k in range(len(Q))]


def float_down(q: Fraction) -> float:
    """The largest float64 ``≤ q``."""
    f = float(q)
    while Fraction(f) > q:
        f = math.nextafter(f, -math.inf)
    return f


def float_up(q: Fraction) -> float:
    """The smallest float64 ``≥ q``."""
    return -float_down(-q)
