r"""Learned dynamics :math:`\varphi \approx f` from grid samples, and the sampling terms α, δ.

The certificate of an unknown system rests on

.. math:: \|f(z) - \varphi(z)\|_2 \le \eta \quad \text{for all } z = (x, u) \in X \times U,

with :math:`\eta` built from terms computed here (see :mod:`nlyap_opt.bounds` for the rest):

- a regular :class:`Grid` over the sampling box with per-axis spacing :math:`h`, whose
  covering radius is exact, :math:`\delta = \tfrac12 \|h\|_2` (PITFALLS P1: δ belongs to
  the very sample set on which α is measured, in :math:`(x, u)`-space);
- :math:`\alpha = \max_s \|f(s) - \varphi(s)\|_2` over **all** nodes ``s`` of that grid,
  float64, batched (bounded memory), plus a rigorous rounding allowance ``alpha_upper``;
- the network :math:`\varphi`: one hidden tanh layer, linear output, trained on a random
  subset of the grid nodes (plus nodes on the box faces): Adam (minibatches, cosine
  learning-rate schedule), then Levenberg–Marquardt in float64, then Lawson-reweighted
  Levenberg–Marquardt rounds that lower the *maximum* error (α is a maximum); seeded, with a
  tqdm progress bar and a time budget. Saved as a :class:`~nlyap_opt.network.Network` with
  float64 weights (input/output normalisation folded into the weights: the saved network is
  the verified object, and α is measured on it).

Two dynamics models:

``"full"``
    :math:`\varphi(x, u)` with input :math:`(x, u)`; components in
    ``system.known_state_derivatives`` are not learned (``meta["learned_components"]``
    lists the learned ones, :func:`nlyap_opt.symbolic.learned_rhs` completes the rest).
``"control_affine"``
    assumes :math:`f(x, u) = f_0(x) + B u` with a known constant input matrix ``B``
    (the linearisation's, checked symbolically against the model in experiments); learns
    :math:`\varphi_0 \approx f_0` on a grid in **x-space** only and saves a network with input
    ``x`` and ``meta["model"] = "control_affine"``, ``meta["input_matrix"]`` (rows of ``B``
    for the learned components); :func:`nlyap_opt.symbolic.learned_rhs` builds
    ``φ0(x) + B u`` from it.
"""

from __future__ import annotations

import copy
import json
import math
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from .errors import ConfigError, DimensionError, NetworkFileError
from .network import Layer, Network

__all__ = [
    "Grid", "DynamicsResult", "AlphaResult", "learn_dynamics", "measure_alpha", "default_config",
    "DEFAULT_CONFIGS", "FAST_CONFIGS", "load_config", "sampling_box",
    "learned_components", "network_error_bound", "check_dynamics_network", "MODELS", "make_grid",
    "check_config", "merge_config",
]

MODELS = ("full", "control_affine")
_U = 2.0 ** -53  # unit roundoff of float64


# ============================================================================ grid
class Grid:
    r"""A regular grid over a box, with its exact covering radius.

    Node ``k`` on axis ``i`` is ``lo_i + k h_i``, ``h_i = (hi_i - lo_i) / (n_i - 1)``; both box
    ends are nodes. Every point of the box lies within :math:`\delta = \tfrac12\|h\|_2` of its
    nearest node, and the cell centres are exactly that far: δ is the covering radius.

    Parameters
    ----------
    box : (d, 2) array_like
        Rows ``(lo_i, hi_i)``.
    counts : (d,) sequence of int
        Nodes per axis, each at least 2.

    Attributes
    ----------
    axes : list of (n_i,) ndarray
        The float64 node coordinates per axis (first and last equal the box ends exactly).
    spacing : (d,) ndarray
        Nominal spacing ``h``.
    gaps : (d,) ndarray
        Largest gap between consecutive float64 nodes per axis, rounded up (``≥ h`` by at most
        a few ulps; the sound version of ``h`` used in the bounds).
    delta : float
        Covering radius ``½‖gaps‖₂``, rounded up.

    Examples
    --------
    >>> g = Grid([[-1, 1], [0, 1]], [3, 2])
    >>> g.size, g.spacing.tolist(), round(g.delta, 12)
    (6, [1.0, 1.0], 0.707106781187)
    >>> next(g.batches(4)).tolist()
    [[-1.0, 0.0], [-1.0, 1.0], [0.0, 0.0], [0.0, 1.0]]
    """

    def __init__(self, box, counts: Sequence[int]):
        box = np.array(box, dtype=float, ndmin=2)
        if box.ndim != 2 or box.shape[1] != 2:
            raise DimensionError(f"box must have shape (d, 2) with rows (lo, hi), got {box.shape}")
        if not np.all(np.isfinite(box)) or np.any(box[:, 0] >= box[:, 1]):
            raise ConfigError(f"grid box needs finite bounds with lo < hi on every row, got {box}")
        counts = [int(c) for c in np.atleast_1d(counts)]
        if len(counts) != box.shape[0]:
            raise ConfigError(
                f"grid counts has {len(counts)} entries but the box has {box.shape[0]} axes"
            )
        if min(counts) < 2:
            raise ConfigError(f"every grid axis needs at least 2 nodes, got counts {counts}")
        self.box = box
        self.counts = np.array(counts, dtype=np.int64)
        self.axes = [np.linspace(lo, hi, n) for (lo, hi), n in zip(box, counts)]
        for ax, (lo, hi) in zip(self.axes, box):  # np.linspace keeps both ends exact
            ax[0], ax[-1] = lo, hi
        self.spacing = (box[:, 1] - box[:, 0]) / (self.counts - 1)
        self.gaps = np.array([np.nextafter(np.max(np.diff(ax)), np.inf) for ax in self.axes])
        self.delta = _norm2_up(0.5 * self.gaps)

    @classmethod
    def from_spacing(cls, box, spacing) -> Grid:
        """The coarsest grid whose spacing is at most ``spacing`` on every axis."""
        box = np.array(box, dtype=float, ndmin=2)
        spacing = np.broadcast_to(np.asarray(spacing, dtype=float), (box.shape[0],))
        if np.any(spacing <= 0):
            raise ConfigError(f"grid spacing must be positive, got {spacing}")
        counts = [int(math.ceil((hi - lo) / h - 1e-9)) + 1 for (lo, hi), h in zip(box, spacing)]
        return cls(box, counts)

    @property
    def dim(self) -> int:
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

    def to_dict(self) -> dict:
        return {"box": self.box.tolist(), "counts": self.counts.tolist(),
                "spacing": self.spacing.tolist(), "size": self.size, "delta": self.delta}

    def __repr__(self) -> str:
        return f"Grid(counts={self.counts.tolist()}, spacing={self.spacing.tolist()})"


def _norm2_up(v, axis=None):
    """Upper bound of ``‖v‖₂`` in float64 (covers the rounding of squares, sum and sqrt)."""
    v = np.abs(np.asarray(v, dtype=float))
    n = v.size if axis is None else v.shape[axis]
    s = np.sum(v * v, axis=axis) * (1.0 + 2.0 * (n + 2) * _U)
    r = np.nextafter(np.nextafter(np.sqrt(s), np.inf), np.inf)
    return float(r) if np.ndim(r) == 0 else r


# ============================================================================ models
def learned_components(system, config: dict | None = None) -> list[int]:
    """Indices of the state derivatives that are learned (the others are known exactly)."""
    config = config or {}
    comp = config.get("learned_components")
    if comp is None:
        comp = [i for i in range(system.nx) if i not in set(system.known_state_derivatives)]
    comp = sorted(int(i) for i in comp)
    if not comp or comp[0] < 0 or comp[-1] >= system.nx or len(set(comp)) != len(comp):
        raise ConfigError(
            f"learned_components must be distinct state indices in 0..{system.nx - 1}, got {comp}"
        )
    return comp


def _input_matrix(system, comp: list[int]) -> np.ndarray:
    """``B`` rows of ``comp`` after checking ``f = f0(x) + B u`` with constant ``B`` (symbolic)."""
    if system.nu == 0:
        return np.zeros((len(comp), 0))
    ju = ca.jacobian(system.f, system.u)
    if ca.depends_on(ju, ca.vertcat(system.x, system.u)):
        raise ConfigError(
            f"system {system.name!r} is not control-affine with a constant input matrix "
            "(∂f/∂u depends on x or u); use model 'full'"
        )
    B = np.array(ca.DM(ca.evalf(ju)), dtype=float).reshape(system.nx, system.nu)
    if not np.allclose(B, system.B, rtol=0, atol=0):
        raise ConfigError("∂f/∂u differs from the linearisation's B; use model 'full'")
    return B[comp]


def sampling_box(system, model: str = "full", config: dict | None = None) -> np.ndarray:
    """The box the grid covers: ``X × U`` (model ``full``) or ``X`` (``control_affine``)."""
    config = config or {}
    xbox = config.get("state_box")
    xbox = np.array(system.state_box if xbox is None else xbox, dtype=float)
    if model == "control_affine" or system.nu == 0:
        return xbox.reshape(system.nx, 2)
    ubox = config.get("input_box")
    ubox = np.array(system.input_box if ubox is None else ubox, dtype=float)
    return np.vstack([xbox.reshape(system.nx, 2), ubox.reshape(system.nu, 2)])


def _target(system, model: str, comp: list[int], z: np.ndarray) -> np.ndarray:
    """The function that φ approximates, at points ``z`` of the sampling box, float64."""
    nx = system.nx
    if model == "control_affine":
        u = np.zeros((z.shape[0], system.nu))
        return system.evaluate(z[:, :nx], u)[:, comp]  # f0(x) = f(x, 0)
    return system.evaluate(z[:, :nx], z[:, nx:])[:, comp]


def check_dynamics_network(system, network: Network) -> tuple[str, list[int]]:
    """Validate a (loaded) dynamics network against ``system``; return ``(model, components)``.

    Raises
    ------
    NetworkFileError
        Wrong input/output sizes, bad ``meta`` entries, or not one hidden tanh layer with a
        linear output.
    """
    model = network.meta.get("model", "full")
    if model not in MODELS:
        raise NetworkFileError(f"dynamics network meta['model'] is {model!r}; expected {MODELS}")
    comp = network.meta.get("learned_components", list(range(system.nx)))
    try:
        comp = sorted(int(i) for i in comp)
    except (TypeError, ValueError):
        raise NetworkFileError("meta['learned_components'] must be a list of ints") from None
    if not comp or comp[0] < 0 or comp[-1] >= system.nx:
        raise NetworkFileError(f"meta['learned_components'] {comp} is not a set of state indices")
    n_in = system.nx if model == "control_affine" else system.nx + system.nu
    if network.n_in != n_in or network.n_out != len(comp):
        raise NetworkFileError(
            f"dynamics network maps R^{network.n_in} -> R^{network.n_out}; system "
            f"{system.name!r} with model {model!r} and learned components {comp} needs "
            f"R^{n_in} -> R^{len(comp)}"
        )
    acts = [layer.activation for layer in network.layers]
    if acts != ["tanh", "linear"]:
        raise NetworkFileError(
            f"dynamics network layers have activations {acts}; the bounds need one hidden tanh "
            "layer and a linear output"
        )
    return model, comp


# ============================================================================ alpha
def network_error_bound(network: Network, zmax: np.ndarray) -> np.ndarray:
    """Rigorous bound on ``|fl(φ(z)) − φ(z)|`` per output for ``|z| ≤ zmax`` (float64 numpy).

    Standard forward error analysis of ``W1 tanh(W0 z + b0) + b1`` (any summation order,
    ``γ_k = k u / (1 − k u)``) with a libm allowance of 4 ulps for ``tanh``; valid for
    :meth:`Network.numpy` on one-hidden-layer tanh networks.
    """
    (l0, l1) = network.layers
    n, H = l0.weight.shape[1], l0.weight.shape[0]

    def gamma(k):
        return k * _U / (1.0 - k * _U)

    pre = np.abs(l0.weight) @ np.asarray(zmax, dtype=float) + np.abs(l0.bias)
    err_t = gamma(n + 1) * pre + 8 * _U  # |t̂ − t| (|t| ≤ 1)
    out = np.abs(l1.weight) @ np.ones(H) + np.abs(l1.bias)
    err = gamma(H + 1) * out + np.abs(l1.weight) @ err_t
    scale = np.abs(np.broadcast_to(network.output_scale, err.shape))
    err = scale * err + 2 * _U * scale * out
    return err * (1 + 1e-6) + 1e-300


@dataclass
class AlphaResult:
    """``α = max_s ‖f(s) − φ(s)‖₂`` over a grid, with its rigorous upper bound."""

    alpha: float
    alpha_upper: float
    argmax: np.ndarray
    n_points: int
    seconds: float
    per_component: np.ndarray


def measure_alpha(system, network: Network, grid: Grid, *, batch_size: int = 1 << 17,
                  rigorous: bool = True) -> AlphaResult:
    """α over **every** node of ``grid`` (the grid that defines δ), float64, batched.

    Only learned components enter (the known ones are exact). ``alpha_upper`` adds a rigorous
    allowance for the float64 rounding of ``f`` (outward-rounded interval evaluation of the
    CasADi model at the nodes) and of ``φ`` (:func:`network_error_bound`); ``rigorous=False``
    skips it (``alpha_upper`` is then NaN).

    Raises
    ------
    NetworkFileError
        The network does not fit the system, or ``f − φ`` is not finite on the grid.
    """
    t0 = time.perf_counter()
    model, comp = check_dynamics_network(system, network)
    if grid.dim != network.n_in:
        raise DimensionError(f"grid has {grid.dim} axes but the network takes {network.n_in}")
    zmax = np.max(np.abs(grid.box), axis=1)
    err_phi = network_error_bound(network, zmax)
    err_f = _target_rounding(system, model, comp) if rigorous else None
    best, best_up, arg = -1.0, -1.0, None
    per = np.zeros(len(comp))
    for z in grid.batches(batch_size):
        with np.errstate(all="ignore"):
            e = _target(system, model, comp, z) - network.numpy(z)
        if not np.all(np.isfinite(e)):
            raise NetworkFileError("f − φ is not finite on the grid (NaN/inf in the model?)")
        nrm = np.sqrt(np.sum(e * e, axis=1))
        k = int(np.argmax(nrm))
        if nrm[k] > best:
            best, arg = float(nrm[k]), z[k].copy()
        per = np.maximum(per, np.max(np.abs(e), axis=0))
        if err_f is not None:  # |e_true| ≤ |fl(f̂ − φ̂)|(1 + u) + |f − f̂| + |φ − φ̂|, rounded up
            ae = (np.abs(e) * (1 + 2 * _U) + err_phi + err_f(z)) * (1 + 8 * _U)
            best_up = max(best_up, float(np.max(_norm2_up(ae, axis=1))))
    if err_f is None:
        best_up = float("nan")
    return AlphaResult(best, best_up, arg, grid.size, time.perf_counter() - t0, per)


def _target_rounding(system, model: str, comp: list[int]):
    """``z -> bound on |fl(f(z)) − f(z)|`` per learned component (interval at point boxes)."""
    from verification.interval import Interval, IntervalArithmetic

    from .walker import compile_function, evaluate

    nx = system.nx
    prog = compile_function(system.f_fun)
    ia = IntervalArithmetic()

    def bound(z):
        x = z[:, :nx]
        u = np.zeros((z.shape[0], system.nu)) if model == "control_affine" else z[:, nx:]
        fx = system.evaluate(x, u)[:, comp]
        out = evaluate(prog, [Interval(x, x.copy()), Interval(u, u.copy())], ia)[0]
        lo, hi = np.asarray(out.lo)[:, comp], np.asarray(out.hi)[:, comp]
        return np.maximum(hi - fx, fx - lo) * (1 + 4 * _U)

    return bound


# ============================================================================ configs
#: Default configurations (``nlyap learn-dynamics NAME``); ``--config FILE`` overrides keys.
DEFAULT_CONFIGS: dict[str, dict] = {
    "van_der_pol": {
        "model": "full", "hidden": 100, "grid_counts": [601, 601],
        "train_points": 8000, "boundary_points": 1000, "steps": 2000,
        "lm_iterations": 100, "minimax_rounds": 5, "minimax_iterations": 10,
        "time_budget": 60.0,
    },
    "unicycle_path_following": {
        "model": "full", "hidden": [20, 150], "grid_counts": [321, 81, 21],
        "train_points": 6000, "boundary_points": 1500, "steps": 2000,
        "lm_iterations": 100, "minimax_rounds": 5, "minimax_iterations": 10,
        "time_budget": 85.0,
    },
    "inverted_pendulum": {
        "model": "control_affine", "hidden": 100, "grid_counts": [401, 401],
        "train_points": 6000, "boundary_points": 1000, "steps": 2000,
        "lm_iterations": 200, "minimax_rounds": 5, "minimax_iterations": 10,
        "time_budget": 80.0,
    },
}

#: Tiny configurations for tests (a few seconds each).
FAST_CONFIGS: dict[str, dict] = {
    "van_der_pol": {"model": "full", "hidden": 12, "grid_counts": [61, 61],
                    "train_points": 600, "boundary_points": 100, "steps": 200,
                    "lm_iterations": 30, "minimax_rounds": 1, "minimax_iterations": 5,
                    "time_budget": 10.0, "interval_boxes": 1024, "check_points": 20000},
    "unicycle_path_following": {"model": "full", "hidden": 12, "grid_counts": [21, 21, 9],
                                "train_points": 600, "boundary_points": 100, "steps": 200,
                                "lm_iterations": 30, "minimax_rounds": 1,
                                "minimax_iterations": 5, "time_budget": 10.0,
                                "interval_boxes": 1024, "check_points": 20000},
    "inverted_pendulum": {"model": "full", "hidden": 12, "grid_counts": [21, 21, 9],
                          "train_points": 600, "boundary_points": 100, "steps": 200,
                          "lm_iterations": 30, "minimax_rounds": 1, "minimax_iterations": 5,
                          "time_budget": 10.0, "interval_boxes": 1024, "check_points": 20000},
}

_COMMON: dict = {
    "model": "full", "hidden": 100, "grid_counts": None, "grid_spacing": None,
    "learned_components": None, "state_box": None, "input_box": None,
    "train_points": 8000, "boundary_points": 1000,
    "steps": 2000, "batch_size": 256, "lr": 1e-2, "lr_final": 1e-4, "train_dtype": "float32",
    "lm_iterations": 100, "minimax_rounds": 5, "minimax_iterations": 10, "lm_ridge": 1e-14,
    "prune": 1e-12, "time_budget": 60.0, "seed": 0,
    "bound_model": "best", "bound_options": None, "interval_boxes": 16384,
    "interval_counts": None, "check_points": 200000, "eval_batch": 1 << 17, "progress": True,
}
_ALLOWED = set(_COMMON) | {"system", "comment"}


def default_config(name: str, fast: bool = False) -> dict:
    """The default (or tiny ``fast``) configuration of a catalogue system, all keys filled."""
    table = FAST_CONFIGS if fast else DEFAULT_CONFIGS
    base = copy.deepcopy(_COMMON)
    base.update(copy.deepcopy(table.get(name, {})))
    base["system"] = name
    return base


def load_config(path: str | Path | None, name: str | None = None, fast: bool = False) -> dict:
    """Defaults of ``name`` overridden by the JSON object in ``path`` (unknown keys refused)."""
    over: dict = {}
    if path is not None:
        from .configs import read_json_object

        over = read_json_object(path)
    name = name or over.get("system")
    if name is None:
        raise ConfigError("no system named: pass NAME or put 'system' in the config file")
    if over.get("system", name) != name:
        raise ConfigError(f"config {path} is for system {over['system']!r}, not {name!r}")
    cfg = merge_config(default_config(name, fast), over)
    cfg["system"] = name
    return check_config(cfg)


def merge_config(base: dict, over: dict | None) -> dict:
    """``base`` updated with ``over``; a grid given one way (counts, spacing) replaces the other."""
    cfg = dict(base)
    over = dict(over or {})
    if over.get("grid_spacing") is not None and "grid_counts" not in over:
        cfg["grid_counts"] = None
    if over.get("grid_counts") is not None and "grid_spacing" not in over:
        cfg["grid_spacing"] = None
    cfg.update(over)
    return cfg


def check_config(cfg: dict) -> dict:
    """Validate a configuration dict (unknown keys, types, ranges); return it."""
    unknown = set(cfg) - _ALLOWED
    if unknown:
        raise ConfigError(
            f"unknown config keys {sorted(unknown)}; allowed keys: {', '.join(sorted(_ALLOWED))}"
        )
    if cfg["model"] not in MODELS:
        raise ConfigError(f"config 'model' must be one of {MODELS}, got {cfg['model']!r}")
    if cfg["train_dtype"] not in ("float32", "float64"):
        raise ConfigError("config 'train_dtype' must be 'float32' or 'float64'")
    for key in ("train_points", "batch_size"):
        if int(cfg[key]) < 1:
            raise ConfigError(f"config {key!r} must be a positive integer, got {cfg[key]!r}")
    for key in ("lm_ridge", "prune"):
        if not float(cfg[key]) >= 0:
            raise ConfigError(f"config {key!r} must be non-negative, got {cfg[key]!r}")
    for key in ("steps", "lm_iterations", "minimax_rounds", "minimax_iterations",
                "boundary_points", "check_points"):
        if int(cfg[key]) < 0:
            raise ConfigError(f"config {key!r} must be a non-negative integer, got {cfg[key]!r}")
    hidden = cfg["hidden"]
    if not all(int(h) >= 1 for h in np.atleast_1d(hidden)):
        raise ConfigError(f"config 'hidden' must be a positive int or a list of them: {hidden}")
    if float(cfg["time_budget"]) <= 0:
        raise ConfigError("config 'time_budget' must be positive (seconds)")
    return cfg


def make_grid(system, cfg: dict) -> Grid:
    """The grid of a configuration (``grid_counts`` or ``grid_spacing`` over the model's box)."""
    box = sampling_box(system, cfg["model"], cfg)
    if cfg.get("grid_counts") is not None:
        if len(cfg["grid_counts"]) != box.shape[0]:
            raise ConfigError(
                f"grid_counts has {len(cfg['grid_counts'])} entries; model {cfg['model']!r} "
                f"of {system.name!r} samples a {box.shape[0]}-dimensional box "
                f"({'x' if box.shape[0] == system.nx else '(x, u)'})"
            )
        return Grid(box, cfg["grid_counts"])
    if cfg.get("grid_spacing") is not None:
        return Grid.from_spacing(box, cfg["grid_spacing"])
    raise ConfigError("config needs 'grid_counts' (nodes per axis) or 'grid_spacing'")


# ============================================================================ training
@dataclass
class DynamicsResult:
    """Outcome of :func:`learn_dynamics`.

    Attributes
    ----------
    network : Network
        φ with float64 weights; ``meta`` holds the model, learned components, grid, α.
    grid : Grid
        The grid that defines δ and on which α was measured.
    alpha : AlphaResult
    model : str
    learned_components : list of int
    seconds : dict
        Wall time per stage: ``data``, ``training``, ``alpha``.
    history : list of dict
        Training log per component (stage, iteration, loss, max error, seconds).
    stopped_by : str
        ``"iterations"`` or ``"time_budget"``.
    """

    system: object
    config: dict
    network: Network
    grid: Grid
    alpha: AlphaResult
    model: str
    learned_components: list[int]
    seconds: dict = field(default_factory=dict)
    history: list = field(default_factory=list)
    stopped_by: str = "iterations"

    @property
    def delta(self) -> float:
        return self.grid.delta


def learn_dynamics(system, config: dict | None = None, *, progress: bool | None = None
                   ) -> DynamicsResult:
    r"""Learn :math:`\varphi \approx f` on a grid and measure α on that same grid.

    Each learned component gets its own hidden neurons (the networks are stacked into one
    network with a block output layer, exactly). Per component: Adam on minibatches of the
    training nodes (cosine learning-rate schedule, float32 by default), then
    Levenberg–Marquardt in float64 on all training nodes (mean squared error), then
    Lawson-reweighted Levenberg–Marquardt rounds that push down the *largest* error (α is a
    maximum). Everything is seeded; ``time_budget`` caps the training wall time.

    Parameters
    ----------
    system : systems.System
    config : dict, optional
        Keys of :data:`DEFAULT_CONFIGS` / :func:`default_config` (missing keys take the
        system's defaults): ``model`` (``"full"`` | ``"control_affine"``), ``hidden``
        (total or per component), ``grid_counts`` or ``grid_spacing``, ``train_points``
        (random distinct grid nodes) and ``boundary_points`` (random nodes on the box faces),
        ``steps``, ``batch_size``, ``lr``, ``lr_final`` (Adam), ``lm_iterations``,
        ``minimax_rounds``, ``minimax_iterations``, ``time_budget`` (s), ``seed``.
    progress : bool, optional
        tqdm progress bar (default: ``config["progress"]``).

    Returns
    -------
    DynamicsResult
        ``network`` is the saved object; ``alpha`` was measured on it over every grid node.

    Examples
    --------
    >>> import systems
    >>> res = learn_dynamics(systems.get("van_der_pol"), default_config("van_der_pol", fast=True)
    ...                      | {"progress": False})
    >>> res.grid.size, res.learned_components, res.alpha.alpha < 0.5
    (3721, [1], True)
    """
    cfg = check_config(merge_config(default_config(system.name), config))
    progress = cfg["progress"] if progress is None else progress
    model = cfg["model"]
    comp = learned_components(system, cfg)
    B = _input_matrix(system, comp) if model == "control_affine" else None
    grid = make_grid(system, cfg)
    hidden = [int(h) for h in np.atleast_1d(cfg["hidden"])]
    if len(hidden) == 1 and len(comp) > 1:
        hidden = [max(hidden[0] // len(comp), 1)] * len(comp)
    if len(hidden) != len(comp):
        raise ConfigError(f"'hidden' lists {len(hidden)} widths for {len(comp)} learned components")
    seconds: dict[str, float] = {}

    # ---- data: random distinct grid nodes plus nodes on the faces, float64 targets
    t0 = time.perf_counter()
    rng = np.random.default_rng(int(cfg["seed"]))
    z = np.concatenate([grid.sample(int(cfg["train_points"]), rng),
                        _boundary_nodes(grid, int(cfg["boundary_points"]), rng)])
    y = _target(system, model, comp, z)
    centre = grid.box.mean(axis=1)
    radius = 0.5 * (grid.box[:, 1] - grid.box[:, 0])
    mu, sigma = y.mean(axis=0), y.std(axis=0)
    sigma = np.where(sigma > 0, sigma, 1.0)
    zn, yn = (z - centre) / radius, (y - mu) / sigma
    seconds["data"] = time.perf_counter() - t0

    # ---- training, one block of neurons per learned component
    t0 = time.perf_counter()
    budget = float(cfg["time_budget"])
    history: list[dict] = []
    blocks = []
    stopped = "iterations"
    for k in range(len(comp)):
        deadline = t0 + budget * sum(hidden[:k + 1]) / sum(hidden)
        params, out_of_time = _train_component(
            zn, yn[:, k], hidden[k], cfg, int(cfg["seed"]) + 7919 * k, deadline, progress,
            history, f"φ[{comp[k]}] {system.name}", t0)
        blocks.append(params)
        stopped = "time_budget" if out_of_time else stopped
    seconds["training"] = time.perf_counter() - t0

    network = _assemble(blocks, centre, radius, mu, sigma, float(cfg["prune"]))
    network.meta.update({
        "kind": "dynamics", "system": system.name, "model": model,
        "learned_components": comp, "grid": grid.to_dict(), "config": _jsonable(cfg),
    })
    if B is not None:
        network.meta["input_matrix"] = B.tolist()

    # ---- α over the same grid that defines δ (float64, every node)
    alpha = measure_alpha(system, network, grid, batch_size=int(cfg["eval_batch"]))
    seconds["alpha"] = alpha.seconds
    network.meta.update({"alpha": alpha.alpha, "alpha_upper": alpha.alpha_upper,
                         "delta": grid.delta})
    return DynamicsResult(system, cfg, network, grid, alpha, model, comp, seconds, history,
                          stopped)


def _boundary_nodes(grid: Grid, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` random nodes on the faces of the grid box (max errors like to sit there)."""
    if n <= 0:
        return np.zeros((0, grid.dim))
    idx = rng.integers(0, grid.counts, size=(n, grid.dim))
    axis = rng.integers(0, grid.dim, size=n)
    side = rng.integers(0, 2, size=n)
    idx[np.arange(n), axis] = side * (grid.counts[axis] - 1)
    return np.stack([grid.axes[k][idx[:, k]] for k in range(grid.dim)], axis=1)


def _train_component(zn, y, H, cfg, seed, deadline, progress, history, desc, t_start):
    """Adam, then Levenberg–Marquardt, then minimax (Lawson) rounds, for one output."""
    import torch

    total = int(cfg["steps"]) + int(cfg["lm_iterations"]) \
        + int(cfg["minimax_rounds"]) * int(cfg["minimax_iterations"])
    bar = _bar(total, progress, desc)
    dtype = torch.float32 if cfg["train_dtype"] == "float32" else torch.float64
    with torch.random.fork_rng(devices=[]):  # seeded init without touching the caller's RNG
        torch.manual_seed(seed)
        net = torch.nn.Sequential(torch.nn.Linear(zn.shape[1], H), torch.nn.Tanh(),
                                  torch.nn.Linear(H, 1)).to(dtype)
    Z = torch.as_tensor(zn, dtype=dtype)
    Y = torch.as_tensor(y[:, None], dtype=dtype)
    gen = torch.Generator().manual_seed(seed)
    steps, bs = int(cfg["steps"]), min(int(cfg["batch_size"]), zn.shape[0])
    lr0, lr1 = float(cfg["lr"]), float(cfg["lr_final"])
    opt = torch.optim.Adam(net.parameters(), lr=lr0)
    out_of_time = False
    perm, pos = torch.randperm(Z.shape[0], generator=gen), 0
    for step in range(steps):
        for g in opt.param_groups:  # cosine schedule lr0 -> lr1
            g["lr"] = lr1 + 0.5 * (lr0 - lr1) * (1 + math.cos(math.pi * step / steps))
        if pos + bs > Z.shape[0]:
            perm, pos = torch.randperm(Z.shape[0], generator=gen), 0
        idx = perm[pos:pos + bs]
        pos += bs
        loss = torch.mean((net(Z[idx]) - Y[idx]) ** 2)
        opt.zero_grad()
        loss.backward()
        opt.step()
        if bar is not None:
            bar.update(1)
        if step % 500 == 0 or step == steps - 1:
            history.append({"component": desc, "stage": "adam", "iteration": step,
                            "loss": loss.item(), "seconds": time.perf_counter() - t_start})
            if bar is not None:
                bar.set_postfix(stage="adam", loss=f"{loss.item():.2e}")
        if time.perf_counter() > deadline:
            out_of_time = True
            break
    theta = np.concatenate([net[0].weight.detach().double().numpy().ravel(),
                            net[0].bias.detach().double().numpy(),
                            net[2].weight.detach().double().numpy().ravel(),
                            net[2].bias.detach().double().numpy()])
    lm = _LevenbergMarquardt(zn, y, H, float(cfg["lm_ridge"]))
    if not out_of_time:
        theta, out_of_time = lm.run(theta, int(cfg["lm_iterations"]), None, deadline, bar,
                                    history, desc, "lm", t_start)
    weights = np.ones(zn.shape[0])
    best, best_err = theta, float(np.max(np.abs(lm.residual(theta))))
    for r in range(int(cfg["minimax_rounds"])):
        if out_of_time:
            break
        res = np.abs(lm.residual(theta))  # Lawson: weight up where the error is large
        weights = np.clip(weights * res / max(np.mean(res), 1e-300), 1e-6, None)
        weights = np.clip(weights / np.mean(weights), 1e-4, 1e4)
        theta, out_of_time = lm.run(theta, int(cfg["minimax_iterations"]), weights, deadline,
                                    bar, history, desc, f"minimax{r}", t_start)
        err = float(np.max(np.abs(lm.residual(theta))))
        if err < best_err:  # Lawson rounds may oscillate: keep the best maximum error
            best, best_err = theta, err
    if bar is not None:
        bar.close()
    return lm.unpack(best), out_of_time


class _LevenbergMarquardt:
    """Levenberg–Marquardt (Marquardt scaling) for ``w1·tanh(W0 z + b0) + b1 ≈ y``, float64."""

    def __init__(self, Z: np.ndarray, y: np.ndarray, H: int, ridge: float = 0.0):
        self.Z, self.y, self.H = np.asarray(Z, float), np.asarray(y, float), H
        self.d = Z.shape[1]
        self.lam = 1e-3
        # ρ N ‖W0‖² keeps hidden slopes moderate: a steep neuron with a negligible output
        # weight costs nothing in the fit but ruins the curvature and Lipschitz bounds
        self.ridge = float(ridge) * Z.shape[0]

    def unpack(self, th):
        H, d = self.H, self.d
        return (th[:H * d].reshape(H, d), th[H * d:H * d + H], th[H * d + H:H * d + 2 * H],
                th[-1:])

    def _forward(self, th):
        W0, b0, w1, b1 = self.unpack(th)
        T = np.tanh(self.Z @ W0.T + b0)
        return T, T @ w1 + b1[0] - self.y

    def residual(self, th):
        return self._forward(th)[1]

    def run(self, th, iters, weights, deadline, bar, history, desc, stage, t_start):
        from scipy.linalg import LinAlgError, cho_factor, cho_solve

        N, H, d = self.Z.shape[0], self.H, self.d
        w = np.ones(N) if weights is None else weights
        sw = np.sqrt(w)
        T, r = self._forward(th)
        nW = H * d
        L = float(np.sum(w * r * r)) + self.ridge * float(th[:nW] @ th[:nW])
        for it in range(iters):
            w1 = self.unpack(th)[2]
            A = (1.0 - T * T) * w1
            J = np.empty((N, H * (d + 2) + 1))
            J[:, :H * d] = (A[:, :, None] * self.Z[:, None, :]).reshape(N, H * d)
            J[:, H * d:H * d + H] = A
            J[:, H * d + H:H * d + 2 * H] = T
            J[:, -1] = 1.0
            J *= sw[:, None]
            G = J.T @ J
            g = J.T @ (r * sw)
            G[np.arange(nW), np.arange(nW)] += self.ridge
            g[:nW] += self.ridge * th[:nW]
            dg = np.diag(G).copy() + 1e-12
            improved = False
            while self.lam < 1e10:
                try:
                    step = cho_solve(cho_factor(G + self.lam * np.diag(dg)), g)
                except (LinAlgError, ValueError):
                    self.lam *= 10.0
                    continue
                th2 = th - step
                T2, r2 = self._forward(th2)
                L2 = float(np.sum(w * r2 * r2)) + self.ridge * float(th2[:nW] @ th2[:nW])
                if np.isfinite(L2) and L2 < L:
                    th, T, r, L = th2, T2, r2, L2
                    self.lam = max(self.lam / 3.0, 1e-12)
                    improved = True
                    break
                self.lam *= 4.0
            if bar is not None:
                bar.update(1)
            if it % 10 == 0 or it == iters - 1 or not improved:
                history.append({"component": desc, "stage": stage, "iteration": it,
                                "loss": float(L / np.sum(w)), "max_error": float(np.max(np.abs(r))),
                                "seconds": time.perf_counter() - t_start})
                if bar is not None:
                    bar.set_postfix(stage=stage, max_err=f"{np.max(np.abs(r)):.2e}")
            if not improved:
                self.lam = 1e-3
                break
            if time.perf_counter() > deadline:
                return th, True
        return th, False


def _assemble(blocks, centre, radius, mu, sigma, prune: float = 0.0) -> Network:
    """One network from per-component blocks, in original units (normalisation folded in).

    Block ``k`` computes ``y_k = σ_k (w1_k · tanh(W0_k (z − c)/r + b0_k) + b1_k) + μ_k``; the
    hidden layers are stacked and the output layer is block-structured (exact). Neurons with
    ``|σ_k w1_j| ≤ prune`` are dropped (α is measured afterwards, on the saved network).
    """
    if prune > 0:
        kept = []
        for k, (W0, b0, w1, b1) in enumerate(blocks):
            keep = np.abs(sigma[k] * w1) > prune
            if not np.any(keep):
                keep[np.argmax(np.abs(w1))] = True
            kept.append((W0[keep], b0[keep], w1[keep], b1))
        blocks = kept
    W0 = np.vstack([b[0] for b in blocks]) / radius[None, :]
    b0 = np.concatenate([b[1] for b in blocks]) - W0 @ centre
    m, H = len(blocks), W0.shape[0]
    W1 = np.zeros((m, H))
    b1 = np.zeros(m)
    start = 0
    for k, (_, _, w1, bk) in enumerate(blocks):
        W1[k, start:start + w1.size] = sigma[k] * w1
        b1[k] = sigma[k] * bk[0] + mu[k]
        start += w1.size
    return Network([Layer(W0, b0, "tanh"), Layer(W1, b1, "linear")])


def _bar(total: int, enabled: bool, desc: str):
    if not enabled or total <= 0:
        return None
    try:
        from tqdm.auto import tqdm
    except ImportError:  # pragma: no cover
        return None
    return tqdm(total=total, desc=desc, leave=False, mininterval=0.5)


def _jsonable(obj):
    return json.loads(json.dumps(obj, default=lambda o: np.asarray(o).tolist()))
