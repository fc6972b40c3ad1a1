"""Nodes of a regular grid (the core layer): the one implementation that
:class:`nlyap_opt.learned.dynamics.Grid` (a grid the tool samples) and
:class:`systems.SampleSet` (a grid read from a file) share."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from .rounding import U, next_up

__all__ = ["GridNodes", "norm2_up"]


def norm2_up(v, axis=None):
    """Upper bound of ``‖v‖₂`` in float64 (covers the rounding of squares, sum and sqrt)."""
    v = np.abs(np.asarray(v, dtype=float))
    n = v.size if axis is None else v.shape[axis]
    s = np.sum(v * v, axis=axis) * (1.0 + 2.0 * (n + 2) * U)
    return next_up(np.sqrt(s), 2)


class GridNodes:
    """Node enumeration over ``self.box`` ``(d, 2)``, ``self.counts`` ``(d,)`` and
    ``self.axes`` (the float64 node coordinates per axis), in C order."""

    box: np.ndarray
    counts: np.ndarray
    axes: list

    @property
    def dim(self) -> int:
        """Number of axes."""
        return self.box.shape[0]

    @property
    def size(self) -> int:
        """Number of nodes."""
        return int(np.prod(self.counts))

    def points(self, index) -> np.ndarray:
        """Nodes with flat (C-order) indices ``index``, shape ``(N, d)``."""
        idx = np.unravel_index(np.asarray(index, dtype=np.int64), tuple(self.counts))
        return np.stack([ax[i] for ax, i in zip(self.axes, idx)], axis=-1)

    def batches(self, batch_size: int = 1 << 18) -> Iterator[np.ndarray]:
        """Yield all nodes in C order as float64 arrays of at most ``batch_size`` rows."""
        batch_size = max(int(batch_size), 1)
        for start in range(0, self.size, batch_size):
            yield self.points(np.arange(start, min(start + batch_size, self.size)))

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` distinct random nodes (all nodes, in order, if ``n >= size``)."""
        if n >= self.size:
            return self.points(np.arange(self.size))
        return self.points(np.sort(rng.choice(self.size, size=n, replace=False)))
