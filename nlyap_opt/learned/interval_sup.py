"""Rigorous suprema over a box by interval evaluation of CasADi graphs on sub-boxes.

Shared by the dynamics error bounds (:mod:`nlyap_opt.learned.error_models`: ``K_f``, ``K_φ``,
``L_i``, ``D``) and the gradient bound ``M`` (:mod:`nlyap_opt.learned.bounds`): a box is split into
sub-boxes that cover it exactly, a CasADi Function is evaluated on all of them at once with
the outward-rounded :class:`verification.interval.IntervalArithmetic`, and magnitudes are
reduced to upward-rounded norms.

Interval sups are inflated by a relative ``2**-30``: CasADi folds products of constants in
derivative graphs in float64; the interval arithmetic widens non-integer graph constants by
``2**-50`` (folds within 3 ulps), and the inflation is a further allowance for longer folds.
"""

from __future__ import annotations

from collections.abc import Callable

import casadi as ca
import numpy as np

from verification.interval import Interval, IntervalArithmetic

from ..kernel.errors import ConfigError
from ..kernel.grid import norm2_up
from ..kernel.rounding import FOLD, U, next_up
from ..kernel.walker import evaluate

__all__ = ["subboxes", "interval_sup", "matrix_norm_up", "counts_for", "interval_arithmetic"]

#: factor on interval sups for CasADi's constant folding (``FOLD`` of the rounding model)
_FOLD = 1.0 + FOLD


def counts_for(box: np.ndarray, total: int, counts=None) -> list[int]:
    d = box.shape[0]
    if counts is not None:
        counts = [int(c) for c in np.atleast_1d(counts)]
        if len(counts) != d or min(counts) < 1:
            raise ConfigError(f"interval_counts needs {d} positive entries, got {counts}")
        return counts
    n = max(int(round(max(int(total), 1) ** (1.0 / d))), 1)
    return [n] * d


def subboxes(box, counts) -> tuple[np.ndarray, np.ndarray]:
    """A subdivision of ``box`` into ``prod(counts)`` sub-boxes covering it exactly.

    Adjacent sub-boxes share their float64 edges and the outer edges equal the box ends, so
    the union is the whole box. Returns ``(lo, hi)``, each of shape ``(N, d)``.
    """
    box = np.asarray(box, dtype=float)
    edges = []
    for (lo, hi), n in zip(box, counts):
        e = np.linspace(lo, hi, int(n) + 1)
        e[0], e[-1] = lo, hi
        edges.append(e)
    grids = np.meshgrid(*[np.arange(int(n)) for n in counts], indexing="ij")
    idx = [g.ravel() for g in grids]
    lo = np.stack([e[i] for e, i in zip(edges, idx)], axis=1)
    hi = np.stack([e[i + 1] for e, i in zip(edges, idx)], axis=1)
    return lo, hi


def interval_arithmetic():
    return Interval, IntervalArithmetic()


def interval_sup(fun: ca.Function, box, counts, reduce: Callable, chunk: int = 2048):
    """Evaluate ``fun`` with interval arithmetic on every sub-box; reduce each chunk.

    ``reduce(mag, lo_box, hi_box)`` receives ``mag ≥ |value|`` of the (first) output as a dense
    ``(n, rows, cols)`` array per chunk of ``n`` sub-boxes (structural zeros are 0; NaN becomes
    inf) and returns an array; the per-chunk results are concatenated.
    """

    Interval, ia = interval_arithmetic()
    sp = fun.sparsity_out(0)
    rows, cols = (np.asarray(v, dtype=np.intp) for v in sp.get_triplet())
    shape = (sp.size1(), sp.size2())
    lo, hi = subboxes(box, counts)
    out = []
    for a in range(0, lo.shape[0], chunk):
        res = evaluate(fun, [Interval(lo[a:a + chunk], hi[a:a + chunk])], ia)[0]
        nz = np.maximum(np.abs(res.lo), np.abs(res.hi)) * _FOLD
        nz = np.where(np.isnan(nz), np.inf, nz)
        mag = np.zeros((nz.shape[0],) + shape)
        mag[:, rows, cols] = nz
        out.append(reduce(mag, lo[a:a + chunk], hi[a:a + chunk]))
    return np.concatenate(out, axis=0), lo.shape[0]


def matrix_norm_up(mag: np.ndarray) -> np.ndarray:
    """Upper bound of ``‖J‖₂`` for every ``|J| ≤ mag`` (``mag``: ``(N, m, d)``, non-negative).

    ``‖J‖₂ ≤ ‖ |J| ‖₂ ≤ ‖mag‖₂`` (monotone for non-negative matrices), bounded by the smaller
    of the Frobenius norm and the Collatz–Wielandt bound ``λ_max(magᵀmag) ≤ max_i (magᵀmag v)_i
    / v_i`` for a positive vector ``v`` (power iterates), all rounded upward.
    """
    N, m, d = mag.shape
    fro = norm2_up(mag.reshape(N, m * d), axis=1)
    if m == 1 or d == 1 or not np.all(np.isfinite(mag)):
        return fro
    G = np.einsum("nki,nkj->nij", mag, mag)
    v = np.ones((N, d))
    for _ in range(30):
        v = np.einsum("nij,nj->ni", G, v)
        v /= np.maximum(np.max(v, axis=1, keepdims=True), 1e-300)
    v = v + 1e-9  # strictly positive
    w = np.einsum("nki,nk->ni", mag, np.einsum("nkj,nj->nk", mag, v))
    lam = np.max(w / v, axis=1) * (1 + 4 * (m + d + 4) * U)
    cw = next_up(np.sqrt(next_up(lam)), 2)
    return np.minimum(fro, cw)

