r"""A bound on ‖f − φ‖ on a sub-box of the sampling box, from a finer grid of its own.

The certificate needs :math:`\|f - \varphi\| \le \eta` only on the states of the verification
region :math:`R` with inputs in :math:`\kappa(R)`, not on the whole sampling box
:math:`Z = X \times U`. Near an equilibrium the second derivatives of :math:`f` (and often
the fit error) are far smaller than their sups over :math:`Z`, so a bound computed on a
sub-box

.. math:: Z_R = X_R \times U_R \subseteq Z, \qquad X_R \supseteq R,\quad
          U_R \supseteq \kappa(X_R),

is smaller. :func:`local_bound` computes every sound bound option of
:func:`nlyap_opt.learned.error_models.compute_bounds` on a regular grid over :math:`Z_R`
itself (both ends of every axis are nodes, so its cells cover :math:`Z_R` exactly):
α̅ is the rigorous maximum of ``‖f − φ‖`` over that grid's nodes, and the curvature or
Lipschitz terms are interval sups over :math:`Z_R`. The proofs of the options hold on any
box on which ``f`` is evaluated at the nodes, so the bound is as rigorous as the global
one, but **only on** :math:`Z_R`: a certificate that uses it must keep its region inside
:math:`X_R` and prove :math:`\kappa(R) \subseteq U_R` (what
:meth:`nlyap_opt.certification.certificate.RoaProblem.decrease` checks for its
``dynamics_box`` and ``input_box``).

The grid's counts put the node budget where the curvature is (:func:`local_counts`): each
axis's interpolation term :math:`g_i^2 \max_k D_{ki}/8` is balanced against the others
(an axis along which ``f − φ`` does not curve gets two nodes). New nodes need values of
``f``: a model or a black-box callable; a sample file has values at its own nodes only.
"""

from __future__ import annotations

import math

import numpy as np

from ..kernel.errors import ConfigError
from ..kernel.network import Network
from .bounds import check_input_range
from .dynamics import Grid
from .error_models import BoundsResult, ErrorModel, compute_bounds
from .interval_sup import counts_for, interval_sup

__all__ = ["local_counts", "local_box", "local_bound", "LOCAL_NODES"]

#: default node budget of a local grid (about the global grids of the 6-D and 8-D presets)
LOCAL_NODES = 1_000_000


def local_counts(D, box, nodes: int = LOCAL_NODES) -> list[int]:
    r"""Nodes per axis of a grid over ``box`` that balances the interpolation terms.

    Starting from two nodes per axis, the axis with the largest term
    :math:`g_i^2 \max_k D_{ki} / 8` (``g_i`` its gap) gets more nodes (its count grows
    by half, at least one) while the grid has at most ``nodes`` nodes. Deterministic.

    Parameters
    ----------
    D : (m, d) array_like
        Upper bounds of ``|∂²e_k/∂z_i²|`` on ``box`` (``inf`` allowed: such an axis gets
        the most nodes the budget allows).
    box : (d, 2) array_like
    nodes : int
        Largest number of grid nodes.

    Returns
    -------
    list of int
        At least 2 per axis.

    Examples
    --------
    >>> local_counts([[0.0, 8.0]], [[0, 1], [0, 1]], nodes=20)
    [2, 10]
    """
    D = np.asarray(D, dtype=float)
    box = np.asarray(box, dtype=float)
    d = box.shape[0]
    if D.ndim != 2 or D.shape[1] != d:
        raise ConfigError(f"D must have shape (m, {d}), got {D.shape}")
    width = box[:, 1] - box[:, 0]
    w = np.max(np.where(np.isnan(D), np.inf, D), axis=0) if D.shape[0] else np.zeros(d)
    counts = [2] * d
    while True:
        gaps = width / (np.array(counts) - 1)
        with np.errstate(invalid="ignore"):
            term = np.where(w > 0, gaps * gaps * w / 8.0, 0.0)
        order = np.argsort(-term, kind="stable")
        i = int(order[0])
        if not term[i] > 0:
            return counts
        new = counts[i] + max(counts[i] // 2, 1)
        size = math.prod(counts) // counts[i] * new
        if size > nodes:
            return counts
        counts[i] = new


def local_box(grid_box, state_box, controller: Network | None = None, *,
              slack: float = 0.25, boxes: int = 4096) -> np.ndarray:
    r"""The sub-box ``X_R × U_R`` of the sampling box for a region with bounding box ``state_box``.

    ``X_R`` is ``state_box``; ``U_R`` encloses the controller's range over ``X_R``
    (interval evaluation on sub-boxes, :func:`nlyap_opt.learned.bounds.check_input_range`)
    widened by ``slack`` times its width on each side (room for a controller trained
    later; every certificate proves its own ``κ(R) ⊆ U_R``), clipped to the sampling box.

    Parameters
    ----------
    grid_box : (d, 2) array_like
        The sampling box ``Z``: ``nx`` state rows, then the input rows (none for a
        control-affine φ or a system without inputs).
    state_box : (nx, 2) array_like
        A box around the verification region; it must lie inside ``Z``'s state rows.
    controller : Network, optional
        ``κ`` (needed when ``Z`` has input rows).

    Raises
    ------
    ConfigError
        ``state_box`` leaves the sampling box, or ``Z`` has input rows and no controller
        is given.
    """
    Z = np.asarray(grid_box, dtype=float)
    X = np.asarray(state_box, dtype=float)
    nx = X.shape[0]
    if Z.ndim != 2 or Z.shape[1] != 2 or Z.shape[0] < nx:
        raise ConfigError(f"grid_box must have at least {nx} rows [lo, hi], got {Z.shape}")
    if np.any(X[:, 0] < Z[:nx, 0]) or np.any(X[:, 1] > Z[:nx, 1]) or \
            np.any(X[:, 0] > X[:, 1]):
        raise ConfigError(f"the region's box {X.tolist()} leaves the sampling box "
                          f"{Z[:nx].tolist()} of φ; shrink the region")
    if Z.shape[0] == nx:
        return X.copy()
    if controller is None:
        raise ConfigError("the sampling box has input rows: give the controller whose range "
                          "the local box must hold")
    Ug = Z[nx:]
    rng = check_input_range(controller, X, Ug, boxes=boxes)
    pad = slack * (rng[:, 1] - rng[:, 0])
    Ur = np.column_stack([np.maximum(rng[:, 0] - pad, Ug[:, 0]),
                          np.minimum(rng[:, 1] + pad, Ug[:, 1])])
    return np.vstack([X, Ur])


def local_bound(system, network: Network, grid_box, sub_box, *, nodes: int = LOCAL_NODES,
                counts=None, options: list[str] | None = None, select: str = "best",
                boxes: int = 16384, check_points: int = 20000, seed: int = 0
                ) -> BoundsResult:
    r"""Every sound bound on ``‖f − φ‖₂`` on ``sub_box``, from a grid over ``sub_box``.

    The result is a :class:`~nlyap_opt.learned.error_models.BoundsResult` like the global
    one, with ``grid`` the local grid (its ``box`` is ``sub_box``: where the bound holds).

    Parameters
    ----------
    system : systems.System
        With values of ``f`` at new points: a model or a black-box callable.
    network : Network
        φ (its sampling box is ``grid_box``).
    grid_box, sub_box : (d, 2) array_like
        The sampling box of φ and the sub-box to bound on (``sub_box ⊆ grid_box``).
    nodes : int
        Node budget of the local grid (:func:`local_counts`), unless ``counts`` is given.
    counts : list of int, optional
        Nodes per axis of the local grid.
    options, select, boxes, check_points, seed
        As in :func:`nlyap_opt.learned.error_models.compute_bounds`; the ``boxes``
        interval sub-boxes split only the axes along which ``f − φ`` curves (for a system
        without a model: along which φ curves), so the sups there are tighter.

    Raises
    ------
    ConfigError
        ``sub_box`` is not inside ``grid_box`` (the bound would rest on values of φ and
        declarations off their box), or ``f`` has no values off its sample nodes.
    """
    Z = np.asarray(grid_box, dtype=float)
    S = np.asarray(sub_box, dtype=float)
    if S.shape != Z.shape:
        raise ConfigError(f"sub_box must have the sampling box's shape {Z.shape}, got {S.shape}")
    if np.any(S[:, 0] < Z[:, 0]) or np.any(S[:, 1] > Z[:, 1]) or np.any(S[:, 0] >= S[:, 1]):
        raise ConfigError(f"the local box {S.tolist()} is not inside the sampling box "
                          f"{Z.tolist()} of φ (or has an empty side); a bound there would "
                          "rest on φ and f off their box: shrink the local box")
    if not getattr(system, "can_simulate", True):
        raise ConfigError(f"system {system.name!r} has values of f at its sample nodes only; "
                          "a local grid needs f at new points (a model or a callable)")
    em = ErrorModel(system, network, S)
    fun = em.D2_e if em.D2_e is not None else em.D2_phi
    D2, _ = interval_sup(fun, S, counts_for(S, boxes), lambda mag, lo, hi: mag)
    D = np.max(D2, axis=0)
    # the interval sups split only the axes along which e curves (a structural zero of
    # every ∂²e_k/∂z_i² stays 0 on any box): the same budget, finer where it matters
    curved = np.max(D, axis=0) > 0
    icounts = [1] * S.shape[0]
    if np.any(curved):
        per = max(int(round(max(int(boxes), 1) ** (1.0 / int(np.sum(curved))))), 1)
        icounts = [per if c else 1 for c in curved]
    if counts is None:
        if em.D2_e is None:     # no model: the declared H (only where the counts go)
            decl = getattr(system, "declarations", None)
            D = D + float(getattr(decl, "hessian", None) or 1.0)
        counts = local_counts(D, S, nodes)
    grid = Grid(S, counts)
    return compute_bounds(system, network, grid, options=options, select=select,
                          counts=icounts, check_points=check_points, seed=seed)
