r"""Learned dynamics :math:`\varphi \approx f` from grid samples, and the sampling terms α, δ.

The certificate of an unknown system rests on

.. math:: \|f(z) - \varphi(z)\|_2 \le \eta \quad \text{for all } z = (x, u) \in X \times U,

with :math:`\eta` built from terms computed here (the rest: :mod:`nlyap_opt.learned.error_models`;
the whole stage with its η gate: :func:`nlyap_opt.learned.dynamics_stage.dynamics_stage`; the
configuration: :class:`nlyap_opt.learned.dynamics_config.DynamicsConfig`):

- a regular :class:`Grid` over the sampling box with per-axis spacing :math:`h`, whose
  covering radius is exact, :math:`\delta = \tfrac12 \|h\|_2` (δ belongs to
  the very sample set on which α is measured, in :math:`(x, u)`-space);
- :math:`\alpha = \max_s \|f(s) - \varphi(s)\|_2` over **all** nodes ``s`` of that grid,
  float64, batched (bounded memory), plus a rigorous rounding allowance ``alpha_upper``;
- the network :math:`\varphi`: one hidden tanh layer, linear output; a learned component
  that a least-squares affine map explains (a linear or stiff linear part) gets that map as
  one fixed neuron and the others fit the residual
  (:func:`~nlyap_opt.learned.phi_training.with_linear`); trained on a random
  subset of the grid nodes (plus nodes on the box faces): Adam (minibatches, cosine
  learning-rate schedule), then Levenberg–Marquardt in float64, then Lawson-reweighted
  Levenberg–Marquardt rounds that lower the *maximum* error (α is a maximum); seeded, with a
  tqdm progress bar; budgets are counts of steps, never a wall-clock time;
  the training loops are in :mod:`nlyap_opt.learned.phi_training`. Saved as a
  :class:`~nlyap_opt.kernel.network.Network` with float64 weights (input/output normalisation
  folded into the weights: the saved network is the verified object, and α is measured on
  it).

Systems without a model (``system.has_model`` False, :mod:`systems.base`): a black-box
callable is sampled on the configured grid like a model; a ``"samples"`` system's grid is
its sample file's (:func:`make_grid`: the nodes and δ of the file, including its offset from
the regular nodes), and α is measured on exactly those nodes. The data are ``f``'s values
up to a declared ``sample_error`` (added to α̅); declarations the data contradict are
refused before training (:func:`check_declared`).

Two dynamics models:

``"full"``
    :math:`\varphi(x, u)` with input :math:`(x, u)`; components in
    ``system.known_state_derivatives`` are not learned (``meta["learned_components"]``
    lists the learned ones, :func:`nlyap_opt.kernel.symbolic.learned_rhs` completes the rest).
``"control_affine"``
    assumes :math:`f(x, u) = f_0(x) + B u` with a known constant input matrix ``B``
    (the linearisation's, checked symbolically against the model in experiments; for a
    system without a model the *declared* ``input_matrix``); learns
    :math:`\varphi_0 \approx f_0` on a grid in **x-space** only and saves a network with input
    ``x`` and ``meta["model"] = "control_affine"``, ``meta["input_matrix"]`` (rows of ``B``
    for the learned components); :func:`nlyap_opt.kernel.symbolic.learned_rhs` builds
    ``φ0(x) + B u`` from it.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from systems.declarations import check_declarations, probe_declarations
from verification.interval import Interval, IntervalArithmetic

from ..kernel.determinism import deterministic_torch
from ..kernel.errors import ConfigError, DimensionError, NetworkFileError
from ..kernel.grid import GridNodes, norm2_up
from ..kernel.network import Network
from ..kernel.rounding import U, gamma
from ..kernel.symbolic import learned_components_of
from ..kernel.walker import compile_function, evaluate
from .dynamics_config import MODELS, DynamicsConfig, dynamics_config, load_dynamics_config
from .phi_training import (
    assemble,
    linear_fit,
    polish,
    progress_bar,
    residual,
    train_component,
    with_linear,
)

__all__ = [
    "Grid", "DynamicsResult", "AlphaResult", "learn_dynamics", "refine_dynamics",
    "measure_alpha", "default_config", "load_config", "merge_config", "as_config",
    "DynamicsConfig", "dynamics_config", "sampling_box", "learned_components",
    "network_error_bound", "check_dynamics_network", "MODELS", "make_grid", "SampleGrid",
    "affine_base_input", "check_declared", "input_columns", "declared_dependencies",
]



# ============================================================================ grid
class Grid(GridNodes):
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
        self.delta = norm2_up(0.5 * self.gaps)

    @classmethod
    def from_spacing(cls, box, spacing) -> Grid:
        """The coarsest grid whose spacing is at most ``spacing`` on every axis."""
        box = np.array(box, dtype=float, ndmin=2)
        spacing = np.broadcast_to(np.asarray(spacing, dtype=float), (box.shape[0],))
        if np.any(spacing <= 0):
            raise ConfigError(f"grid spacing must be positive, got {spacing}")
        counts = [int(math.ceil((hi - lo) / h - 1e-9)) + 1 for (lo, hi), h in zip(box, spacing)]
        return cls(box, counts)

    def to_dict(self) -> dict:
        return {"box": self.box.tolist(), "counts": self.counts.tolist(),
                "spacing": self.spacing.tolist(), "size": self.size, "delta": self.delta}

    def __repr__(self) -> str:
        return f"Grid(counts={self.counts.tolist()}, spacing={self.spacing.tolist()})"


# ============================================================================ models
def learned_components(system, config=None) -> list[int]:
    """Indices of the state derivatives that are learned (the others are known exactly).

    A component that is not learned is taken from the system's model ``f``; that is only
    sound for components the system declares known (``system.known_state_derivatives``),
    so leaving out any other one is a :class:`ConfigError`.
    """
    comp = None if config is None else config.get("learned_components")
    known = set(system.known_state_derivatives)
    if comp is None:
        comp = [i for i in range(system.nx) if i not in known]
    comp = sorted(int(i) for i in comp)
    if not comp or comp[0] < 0 or comp[-1] >= system.nx or len(set(comp)) != len(comp):
        raise ConfigError(
            f"learned_components must be distinct state indices in 0..{system.nx - 1}, got {comp}"
        )
    missing = [i for i in range(system.nx) if i not in comp and i not in known]
    if missing:
        raise ConfigError(
            f"learned_components {comp} leaves out state derivatives {missing} that system "
            f"{system.name!r} does not declare known; learn them (add them to "
            "'learned_components') or declare them in known_state_derivatives"
        )
    return comp


def _declared_input_matrix(system) -> np.ndarray | None:
    """The declared control-affine ``B`` of a system without a model (``None`` if none)."""
    decl = getattr(system, "declarations", None)
    return None if decl is None else decl.B


def _has_model(system) -> bool:
    return bool(getattr(system, "has_model", True))


def _input_matrix(system, comp: list[int]) -> np.ndarray:
    """``B`` rows of ``comp`` for the control-affine model ``f = f0(x) + B u``.

    With a model, ``∂f/∂u`` is checked symbolically to be the constant linearisation ``B``.
    Without one (a black-box callable or samples), ``B`` is the **declared**
    ``input_matrix`` (checked against the data by
    :func:`systems.declarations.check_declarations` where an input axis was sampled).
    """
    if system.nu == 0:
        return np.zeros((len(comp), 0))
    if not _has_model(system):
        B = _declared_input_matrix(system)
        if B is None:
            raise ConfigError(
                f"system {system.name!r} has no model, so the control-affine dynamics model "
                "needs a declared input matrix: declare input_matrix (B) or use model 'full'"
            )
        return B[comp]
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


def affine_base_input(system) -> np.ndarray:
    r"""The input ``u0`` at which the control-affine model reads ``f0(x) = f(x, u0) − B u0``.

    ``0`` for a model (``f0(x) = f(x, 0)``, as before); ``u_eq`` for a black-box callable
    (a declared point of ``U``); for samples, the file's single input level on a sliced
    input axis and ``u_eq`` (a node) on a sampled one.
    """
    if system.nu == 0:
        return np.zeros(0)
    kind = getattr(system, "kind", "model")
    if kind == "samples":
        smp = system.samples
        nx = system.nx
        return np.where(smp.counts[nx:] == 1, smp.box[nx:, 0], system.u_eq).astype(float)
    if kind == "callable":
        return np.asarray(system.u_eq, dtype=float).copy()
    return np.zeros(system.nu)


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


def input_columns(system, model: str, comp: list[int], inputs: str = "all"
                  ) -> list[list[int]]:
    """Per learned component, the grid columns (of ``(x, u)``, or ``x`` for the
    control-affine model) its block of φ takes as inputs.

    ``inputs="model"``: the variables that component of the model ``f`` depends on
    (``casadi.depends_on``, symbolic), or without a model those of the user's declaration
    (``Declarations.depends_on``; a component not listed reads every column); for
    ``control_affine`` the ``x`` of ``f(x, u)``. Every column with ``inputs="all"``, without
    a model or a declaration, or where a component depends on none. The bound η does not
    rest on this choice: it is measured for the φ that results.
    """
    d = system.nx + (0 if model == "control_affine" else system.nu)
    every = list(range(d))
    if inputs == "all":
        return [every for _ in comp]
    if not _has_model(system):
        deps = declared_dependencies(system, d)
        return [list(deps[k]) if deps.get(k) else every for k in comp]
    z = [system.x[i] for i in range(system.nx)]
    if model != "control_affine":
        z += [system.u[j] for j in range(system.nu)]
    out = []
    for k in comp:
        cols = [i for i, zi in enumerate(z) if ca.depends_on(system.f[k], zi)]
        out.append(cols or every)
    return out


def declared_dependencies(system, d: int) -> dict[int, tuple[int, ...]]:
    """``{k: columns}`` of a system's declared ``depends_on`` on a grid of ``d`` columns
    (``(x, u)``, or ``x`` alone for control-affine data: inputs dropped); ``{}`` if none."""
    decl = getattr(system, "declarations", None)
    if decl is None or decl.depends_on is None:
        return {}
    deps = decl.dependencies(system.state_names, system.input_names)
    return {k: tuple(i for i in cols if i < d) for k, cols in deps.items()}


def _widen(blocks, cols: list[list[int]], d: int) -> list:
    """The blocks' hidden weights as ``(H, d)`` matrices: zeros outside each block's columns
    (exact zeros, kept by :func:`nlyap_opt.learned.phi_training.assemble`'s folding)."""
    out = []
    for (W0, b0, w1, b1), c in zip(blocks, cols):
        if len(c) == d:
            out.append((W0, b0, w1, b1))
            continue
        W = np.zeros((W0.shape[0], d))
        W[:, c] = W0
        out.append((W, b0, w1, b1))
    return out


def _target(system, model: str, comp: list[int], z: np.ndarray) -> np.ndarray:
    """The function that φ approximates, at points ``z`` of the sampling box, float64."""
    nx = system.nx
    if model == "control_affine":
        u0 = affine_base_input(system)
        fx = system.evaluate(z[:, :nx], np.broadcast_to(u0, (z.shape[0], system.nu)))
        if np.any(u0 != 0):  # f0(x) = f(x, u0) − B u0
            fx = fx - _input_matrix(system, list(range(nx))) @ u0
        return fx[:, comp]
    return system.evaluate(z[:, :nx], z[:, nx:])[:, comp]


def check_dynamics_network(system, network: Network) -> tuple[str, list[int]]:
    """Validate a (loaded) dynamics network against ``system``; return ``(model, components)``.

    Checked: ``meta["model"]`` is one of :data:`MODELS`; ``meta["learned_components"]`` are
    distinct state indices and every component left out is declared known by the system
    (never silently replaced by the model ``f``); for ``control_affine``,
    ``meta["input_matrix"]`` is present, finite, of shape ``(len(components), nu)`` and
    equal to the system's input matrix on those rows; the sizes; one hidden tanh layer and
    a linear output.

    Raises
    ------
    NetworkFileError
        Any of the above fails (the message names the entry and the fix).
    """
    meta = network.meta if isinstance(network.meta, dict) else {}
    model = meta.get("model", "full")
    if model not in MODELS:
        raise NetworkFileError(
            f"dynamics network meta['model'] is {model!r}; expected one of {MODELS}"
        )
    # in the network's output order: α pairs output k with f's component comp[k], as
    # learned_rhs does (a sorted copy paired a file listing [3, 1] with the wrong rows)
    comp = learned_components_of(system, network)
    if not comp:
        raise NetworkFileError("meta['learned_components'] is empty; list the state "
                               "derivatives the network outputs")
    known = set(system.known_state_derivatives)
    missing = [i for i in range(system.nx) if i not in comp and i not in known]
    if missing:
        raise NetworkFileError(
            f"dynamics network learns components {comp} but system {system.name!r} does not "
            f"declare state derivatives {missing} known; a network for this system must learn "
            "them (the model f is not available for an unknown system)"
        )
    n_in = system.nx if model == "control_affine" else system.nx + system.nu
    if network.n_in != n_in or network.n_out != len(comp):
        raise NetworkFileError(
            f"dynamics network maps R^{network.n_in} -> R^{network.n_out}; system "
            f"{system.name!r} with model {model!r} and learned components {comp} needs "
            f"R^{n_in} -> R^{len(comp)}"
        )
    if model == "control_affine" and system.nu:
        if "input_matrix" not in meta:
            raise NetworkFileError(
                "control_affine dynamics network has no meta['input_matrix'] (B rows of the "
                "learned components); re-create it with nlyap learn-dynamics"
            )
        try:
            B = np.array(meta["input_matrix"], dtype=float)
        except (TypeError, ValueError):
            raise NetworkFileError("meta['input_matrix'] must be a matrix of numbers") from None
        if B.shape != (len(comp), system.nu) or not np.all(np.isfinite(B)):
            raise NetworkFileError(
                f"meta['input_matrix'] must be a finite {len(comp)}x{system.nu} matrix, got "
                f"shape {B.shape}"
            )
        if _has_model(system):
            want = np.asarray(system.B, dtype=float)[comp]
        else:
            declared = _declared_input_matrix(system)
            if declared is None:
                raise NetworkFileError(
                    f"control_affine dynamics network for system {system.name!r}, which has no "
                    "model and declares no input_matrix; declare input_matrix (B) or use a "
                    "network with model 'full'"
                )
            want = declared[comp]
        if not np.array_equal(B, want):
            raise NetworkFileError(
                f"meta['input_matrix'] {B.tolist()} differs from the input matrix "
                f"{want.tolist()} of system {system.name!r}: the network was made for another "
                "system"
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
    :meth:`Network.numpy` on one-hidden-layer tanh networks. A neuron's computed ``|tanh|``
    is at most ``min(1, 2·p + (2n + 5)·2⁻¹⁰⁷⁴)`` with ``p`` the bound of its pre-activation
    (twice: room for the rounding of the pre-activation and of tanh), which keeps the
    allowance of a neuron with a tiny input scale and a large output weight (the linear
    neuron of
    :func:`~nlyap_opt.learned.phi_training.with_linear`) at the size of its output.
    """
    (l0, l1) = network.layers
    n, H = l0.weight.shape[1], l0.weight.shape[0]

    pre = np.abs(l0.weight) @ np.asarray(zmax, dtype=float) + np.abs(l0.bias)
    # ≥ |tanh| of the computed pre-activation (2·pre: its relative rounding and tanh's
    # ulps; the subnormal steps of its 2n + 1 operations added absolutely)
    tmax = np.minimum(1.0, 2.0 * pre + (2 * n + 5) * 2.0**-1074)
    # |t̂ − t|: the relative rounding of the pre-activation's n products and sums, each of
    # those 2n + 1 operations may also lose half a subnormal step (2⁻¹⁰⁷⁵), and 4 ulps of tanh
    err_t = gamma(n + 1) * pre + (n + 1) * 2.0**-1074 + 8 * U * tmax + 4 * 2.0**-1074
    out = np.abs(l1.weight) @ tmax + np.abs(l1.bias)
    err = gamma(H + 1) * out + (H + 1) * 2.0**-1074 + np.abs(l1.weight) @ err_t
    scale = np.abs(np.broadcast_to(network.output_scale, err.shape))
    err = scale * err + 2 * U * scale * out
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
            ae = (np.abs(e) * (1 + 2 * U) + err_phi + err_f(z)) * (1 + 8 * U)
            best_up = max(best_up, float(np.max(norm2_up(ae, axis=1))))
    if err_f is None:
        best_up = float("nan")
    return AlphaResult(best, best_up, arg, grid.size, time.perf_counter() - t0, per)


def _target_rounding(system, model: str, comp: list[int]):
    r"""``z -> bound on |fl(f(z)) − f(z)|`` per learned component (interval at point boxes).

    Without a model the data are ``f``'s values by assumption, up to a declared
    ``sample_error`` ε (:math:`\|s - f(z)\|_2 \le ε` bounds every component by ε); the
    control-affine target ``f(x, u0) − B u0`` with ``u0 ≠ 0`` adds the rounding of that
    subtraction.
    """
    if not _has_model(system):
        decl = getattr(system, "declarations", None)
        eps = float((decl is not None and decl.sample_error) or 0.0)
        u0 = affine_base_input(system) if model == "control_affine" else np.zeros(0)
        shifted = bool(np.any(u0 != 0))
        Bu0 = np.abs(_input_matrix(system, comp) @ u0) if shifted else 0.0

        def data_bound(z):
            out = np.full((z.shape[0], len(comp)), eps)
            if shifted:
                t = np.abs(_target(system, model, comp, z))
                out = out + 4 * U * (2 * t + Bu0)
            return out

        return data_bound


    nx = system.nx
    prog = compile_function(system.f_fun)
    ia = IntervalArithmetic()

    def bound(z):
        x = z[:, :nx]
        u = np.zeros((z.shape[0], system.nu)) if model == "control_affine" else z[:, nx:]
        fx = system.evaluate(x, u)[:, comp]
        out = evaluate(prog, [Interval(x, x.copy()), Interval(u, u.copy())], ia)[0]
        lo, hi = np.asarray(out.lo)[:, comp], np.asarray(out.hi)[:, comp]
        return np.maximum(hi - fx, fx - lo) * (1 + 4 * U)

    return bound


# ============================================================================ configs
def default_config(name: str, fast: bool = False) -> dict:
    """The ``default`` (or ``fast``) configuration of ``name`` as a dict with every key.

    A thin view of :func:`nlyap_opt.learned.dynamics_config.dynamics_config`; the dict can be
    updated and passed to :func:`learn_dynamics` (which validates it again).
    """
    return dynamics_config(name, {"preset": "fast" if fast else "default"}).to_dict()


def load_config(path: str | Path | None, name: str | None = None, fast: bool = False
                ) -> DynamicsConfig:
    """Defaults of ``name`` overridden by the JSON object in ``path`` (unknown keys refused)."""
    return load_dynamics_config(path, name, "fast" if fast else "default")


def merge_config(base: dict, over: dict | None) -> dict:
    """``base`` updated with ``over``; a grid given one way (counts, spacing) replaces the other."""
    cfg = dict(base.to_dict() if isinstance(base, DynamicsConfig) else base)
    over = dict(over or {})
    if over.get("grid_spacing") is not None and "grid_counts" not in over:
        cfg["grid_counts"] = None
    if over.get("grid_counts") is not None and "grid_spacing" not in over:
        cfg["grid_spacing"] = None
    cfg.update(over)
    return cfg


def as_config(system, config: DynamicsConfig | dict | None) -> DynamicsConfig:
    """A validated :class:`DynamicsConfig` for ``system`` from a config or a dict of keys."""
    if isinstance(config, DynamicsConfig):
        return config
    return dynamics_config(system.name, config)


class SampleGrid(Grid):
    r"""The state axes of a sample file's grid, as a :class:`Grid` whose δ is the file's.

    Used by the control-affine model of a ``"samples"`` system: the grid of ``φ0(x)`` is
    the file's nodes in x-space (at the input level ``u0``,
    :func:`affine_base_input`). The nodes are bitwise the file's; ``delta`` is
    :math:`\tfrac12\|g_x\|_2` plus the file's ``offset`` (rows off the ideal nodes), so
    that every point of the box lies within δ of the *row* whose value its node carries.
    """

    def __init__(self, samples, axes: list[int]):
        super().__init__(samples.box[axes], samples.counts[axes])
        for a, i in zip(self.axes, axes):
            if not np.array_equal(a, samples.axes[i]):
                raise ConfigError(
                    f"the sample grid's axis {samples.names[i]!r} differs from its regular "
                    "nodes; reload the samples (systems.load_samples)"
                )
        self.offset = float(samples.offset)
        if self.offset > 0:
            self.delta = float(np.nextafter(self.delta + self.offset, np.inf))
        self.source = samples.source

    def to_dict(self) -> dict:
        return {**super().to_dict(), "offset": self.offset, "source": self.source}


def _samples_grid(system, cfg) -> Grid:
    """The grid of a ``"samples"`` system: the file's nodes (never resampled)."""
    smp = system.samples
    nx, nu = system.nx, system.nu
    model = cfg["model"]
    for key, rows in (("state_box", smp.box[:nx]), ("input_box", system.input_box)):
        given = cfg.get(key)
        if given is not None and not np.array_equal(np.asarray(given, dtype=float), rows):
            raise ConfigError(
                f"dynamics config {key!r} = {np.asarray(given).tolist()} differs from the box "
                f"{rows.tolist()} of the samples of {system.name!r}; leave {key!r} out (the "
                "sample file defines the grid)"
            )
    if cfg.get("grid_spacing") is not None:
        raise ConfigError(
            f"system {system.name!r} is given by samples: the sample file defines the grid; "
            "remove 'grid_spacing' from the dynamics config"
        )
    if model == "control_affine" and nu:
        grid = SampleGrid(smp, list(range(nx)))
    elif smp.input_slice:
        raise ConfigError(
            f"the samples of {system.name!r} hold a single input level: model 'full' needs a "
            "grid over the inputs too; use model 'control_affine' (with the declared "
            "input_matrix) or sample the inputs"
        )
    else:
        grid = smp
    counts = cfg.get("grid_counts")
    if counts is not None and [int(c) for c in counts] != grid.counts.tolist():
        raise ConfigError(
            f"dynamics config grid_counts {list(counts)} differs from the sample file's grid "
            f"{grid.counts.tolist()} of {system.name!r}; remove 'grid_counts' (the samples "
            "define the grid)"
        )
    return grid


def check_declared(system, grid, model: str, *, probe_points: int = 0,
                   seed: int = 0) -> dict | None:
    """Check the declarations of a system without a model against its values on ``grid``.

    The values of every component at every node (``f(x, u0)`` on an x-grid of the
    control-affine model of samples; for a black-box callable with a declared ``B`` the
    x-grid times 3 levels of every input, so that ``B`` is checked too) go to
    :func:`systems.declarations.check_declarations`, which refuses a declared ``K_f``,
    ``H`` or ``B`` that the data contradict. Returns its estimates (``None`` for a model or
    without declarations).

    Raises
    ------
    ConfigError
        A declaration is contradicted by the data (both numbers in the message).

    Notes
    -----
    For a black-box callable (``system.kind == "callable"``) ``probe_points`` evaluations
    at seeded random points *between* the grid nodes follow
    (:func:`systems.declarations.probe_declarations`: difference quotients against ``K_f``,
    second differences against ``H``, changes along variables ``depends_on`` excludes, ``B``):
    a narrow spike between nodes that the grid misses is refused before training. Sample
    files cannot be probed (their ``f`` exists at the nodes only).
    """
    decl = getattr(system, "declarations", None)
    if _has_model(system) or decl is None or decl.empty:
        return None

    nx, nu = system.nx, system.nu
    where = "(x, u)-space"
    if grid.dim == nx and nu and getattr(system, "can_simulate", False) \
            and decl.input_matrix is not None:
        # a black box with a declared B: check B (and K_f, H) across input levels too
        levels = 3 if grid.size * 3**nu <= 4_000_000 else 2
        grid = Grid(np.vstack([grid.box, system.input_box]),
                    list(grid.counts) + [levels] * nu)
        where = f"x-grid × {levels} levels of every input"
    vals = []
    for z in grid.batches():
        if grid.dim == nx and nu:  # x-grid: f(x, u0)
            u = np.broadcast_to(affine_base_input(system), (z.shape[0], nu))
        else:
            u = z[:, nx:]
        with np.errstate(all="ignore"):
            vals.append(system.evaluate(z[:, :nx], u))
    values = np.vstack(vals)
    names = list(system.state_names) + (list(system.input_names) if grid.dim > nx else [])
    out = check_declarations(grid, values, decl, names=names, source=system.source)
    if getattr(system, "kind", None) == "callable" and probe_points > 0:
        box, h = np.asarray(grid.box, dtype=float), np.asarray(grid.spacing, dtype=float)
        if grid.dim == nx and nu:  # an x-grid: probe the inputs over U as well
            ub = np.asarray(system.input_box, dtype=float)
            box, h = np.vstack([box, ub]), np.concatenate([h, (ub[:, 1] - ub[:, 0]) / 2])
        out["probe"] = probe_declarations(
            system.evaluate, box, decl, nx=nx, points=probe_points, seed=seed,
            spacing=h, names=list(system.state_names) + list(system.input_names),
            source=system.source)
    out["grid"] = "x-space at u0 = " + str(affine_base_input(system).tolist()) \
        if grid.dim == nx and nu else where
    return out


def make_grid(system, cfg: dict) -> Grid:
    """The grid of a configuration (``grid_counts`` or ``grid_spacing`` over the model's box).

    For a ``"samples"`` system the grid is the sample file's (its nodes and its δ, which
    includes the file's offset from the ideal nodes): the :class:`systems.SampleSet` for
    model ``full``, its state axes (:class:`SampleGrid`) for ``control_affine``.
    """
    for key, rows in (("state_box", system.nx), ("input_box", system.nu)):
        if cfg.get(key) is not None and np.shape(cfg[key]) != (rows, 2):
            raise ConfigError(
                f"dynamics config {key!r} has shape {np.shape(cfg[key])}; system "
                f"{system.name!r} needs {rows} rows [lo, hi]"
            )
    if getattr(system, "kind", "model") == "samples":
        return _samples_grid(system, cfg)
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
    raise ConfigError(f"the dynamics config of {system.name!r} has no grid (no preset gives "
                      "one): set 'grid_counts' (nodes per axis of its sampling box, e.g. "
                      f"{[11] * box.shape[0]}) or 'grid_spacing' in --config FILE")


# ============================================================================ training
@dataclass
class DynamicsResult:
    """Outcome of :func:`learn_dynamics` (and of :func:`refine_dynamics`).

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
        Wall time per stage (``data``, ``training``, ``alpha``): reported, never used to
        stop anything.
    history : list of dict
        Training log per component (stage, iteration, loss, max error, seconds).
    rounds : int
        Refinement rounds done after the first training (:func:`refine_dynamics`).
    """

    system: object
    config: DynamicsConfig
    network: Network
    grid: Grid
    alpha: AlphaResult
    model: str
    learned_components: list[int]
    seconds: dict = field(default_factory=dict)
    history: list = field(default_factory=list)
    rounds: int = 0
    _state: dict = field(default_factory=dict, repr=False)

    @property
    def delta(self) -> float:
        return self.grid.delta

    @property
    def stopped_by(self) -> str:
        """Always ``"iterations"``: budgets are counted in steps (kept for old callers)."""
        return "iterations"


def learn_dynamics(system, config: DynamicsConfig | dict | None = None, *,
                   progress: bool | None = None) -> DynamicsResult:
    r"""Learn :math:`\varphi \approx f` on a grid and measure α on that same grid.

    Each learned component gets its own hidden neurons (the networks are stacked into one
    network with a block output layer, exactly). Per component: Adam on minibatches of the
    training nodes (cosine learning-rate schedule, float32 by default), then
    Levenberg–Marquardt in float64 on all training nodes (mean squared error), then
    Lawson-reweighted Levenberg–Marquardt rounds that push down the *largest* error (α is a
    maximum). Every budget is a count (``steps``, ``lm_iterations``, ``minimax_rounds``,
    ``minimax_iterations``) and training runs with ``threads`` torch threads and
    deterministic algorithms: the same configuration and seed give a bit-identical φ
    whatever the machine's load.

    Parameters
    ----------
    system : systems.System
    config : DynamicsConfig or dict, optional
        A :class:`~nlyap_opt.learned.dynamics_config.DynamicsConfig`, or a dict of its keys applied
        to the system's preset (``{"preset": "fast", ...}``); validated.
    progress : bool, optional
        tqdm progress bar (default: ``config.progress``).

    Returns
    -------
    DynamicsResult
        ``network`` is the saved object; ``alpha`` was measured on it over every grid node.

    Examples
    --------
    >>> import systems
    >>> res = learn_dynamics(systems.get("van_der_pol"), {"preset": "fast", "progress": False})
    >>> res.grid.size, res.learned_components, res.alpha.alpha < 0.5
    (3721, [1], True)
    """
    cfg = as_config(system, config)
    progress = cfg.progress if progress is None else progress
    model = cfg.model
    comp = learned_components(system, cfg)
    B = _input_matrix(system, comp) if model == "control_affine" else None
    grid = make_grid(system, cfg)
    declared = check_declared(system, grid, model, probe_points=cfg.probe_points,
                              seed=cfg.seed)  # fail fast, before any training
    hidden = [int(h) for h in np.atleast_1d(cfg.hidden)]
    if len(hidden) == 1 and len(comp) > 1:
        hidden = [max(hidden[0] // len(comp), 1)] * len(comp)
    if len(hidden) != len(comp):
        raise ConfigError(
            f"dynamics config 'hidden' lists {len(hidden)} widths for {len(comp)} learned "
            f"components {comp}: give one width per component or a total"
        )
    seconds: dict[str, float] = {}

    # ---- data: random distinct grid nodes plus nodes on the faces, float64 targets
    t0 = time.perf_counter()
    rng = np.random.default_rng(cfg.seed)
    z = np.concatenate([grid.sample(cfg.train_points, rng),
                        _boundary_nodes(grid, cfg.boundary_points, rng)])
    y = _target(system, model, comp, z)
    centre = grid.box.mean(axis=1)
    radius = 0.5 * (grid.box[:, 1] - grid.box[:, 0])
    mu, sigma = y.mean(axis=0), y.std(axis=0)
    sigma = np.where(sigma > 0, sigma, 1.0)
    zn, yn = (z - centre) / radius, (y - mu) / sigma
    seconds["data"] = time.perf_counter() - t0

    # ---- training, one block of neurons per learned component
    t0 = time.perf_counter()
    history: list[dict] = []
    blocks = []
    cols = input_columns(system, model, comp, cfg.inputs)
    linear = []
    with deterministic_torch(cfg.threads):
        for k in range(len(comp)):
            zk = zn if len(cols[k]) == zn.shape[1] else zn[:, cols[k]]
            linear.append(linear_fit(zk, yn[:, k]))
            blocks.append(train_component(
                zk, residual(zk, yn[:, k], linear[k]), hidden[k], cfg, cfg.seed + 7919 * k,
                progress,
                history, f"φ[{comp[k]}] {system.name}", t0))
    seconds["training"] = time.perf_counter() - t0
    state = {"z": z, "centre": centre, "radius": radius, "mu": mu, "sigma": sigma,
             "blocks": blocks, "linear": linear, "inputs": cols, "B": B, "hidden": hidden,
             "declarations_check": declared}
    return _finish(system, cfg, grid, model, comp, state, seconds, history, 0)


def _finish(system, cfg: DynamicsConfig, grid: Grid, model: str, comp: list[int], state: dict,
            seconds: dict, history: list, rounds: int) -> DynamicsResult:
    """Assemble the network from the trained blocks and measure α on every grid node."""
    d = grid.dim
    cols = state.get("inputs") or [list(range(d)) for _ in comp]
    blocks = [with_linear(b, fit) for b, fit in zip(state["blocks"], state["linear"])]
    network = assemble(_widen(blocks, cols, d), state["centre"], state["radius"],
                        state["mu"], state["sigma"], cfg.prune)
    network.meta.update({
        "kind": "dynamics", "system": system.name, "model": model,
        # the configuration that determined φ: the progress bar is a display choice, not
        # an input, and must not change the file's bytes (terminal vs Python API)
        "learned_components": comp, "grid": grid.to_dict(),
        "config": _jsonable({k: v for k, v in cfg.to_dict().items() if k != "progress"}),
    })
    if any(len(c) < d for c in cols):
        network.meta["inputs"] = cols  # per component: the grid columns its block reads
    if rounds:
        network.meta["refinement_rounds"] = rounds
    if state["B"] is not None:
        network.meta["input_matrix"] = state["B"].tolist()
    if state.get("declarations_check") is not None:
        network.meta["declarations_check"] = _jsonable(state["declarations_check"])
    alpha = measure_alpha(system, network, grid, batch_size=cfg.eval_batch)
    seconds["alpha"] = alpha.seconds
    network.meta.update({"alpha": alpha.alpha, "alpha_upper": alpha.alpha_upper,
                         "delta": grid.delta})
    return DynamicsResult(system, cfg, network, grid, alpha, model, comp, seconds, history,
                          rounds, state)


def refine_dynamics(result: DynamicsResult, *, points: int | None = None,
                    progress: bool | None = None) -> DynamicsResult:
    """One more training round of φ, aimed at the largest errors on the grid.

    The ``points`` grid nodes with the largest error ``|f_k − φ_k|`` (per learned component,
    over **every** node) join the training set; then each component runs
    ``lm_iterations`` Levenberg–Marquardt iterations and ``minimax_rounds`` Lawson rounds
    from its current weights (the normalisation is kept). Deterministic: a count of
    iterations, no clock. α is measured again on the new network.

    Parameters
    ----------
    result : DynamicsResult
        From :func:`learn_dynamics` or an earlier :func:`refine_dynamics` (not a reloaded
        file: the training state is needed).
    points : int, optional
        Default ``config.refine_points``.

    Returns
    -------
    DynamicsResult
        A new result (``rounds`` one larger); ``result`` is not changed.
    """
    if not result._state:
        raise ConfigError("refine_dynamics needs a result of learn_dynamics in this process "
                          "(a reloaded network has no training state)")
    cfg, system, grid = result.config, result.system, result.grid
    progress = cfg.progress if progress is None else progress
    points = cfg.refine_points if points is None else int(points)
    st = dict(result._state)
    comp, model = result.learned_components, result.model
    t0 = time.perf_counter()
    worst = _worst_nodes(system, result.network, grid, model, comp, points, cfg.eval_batch)
    z = np.concatenate([st["z"], worst])
    y = _target(system, model, comp, z)
    zn = (z - st["centre"]) / st["radius"]
    yn = (y - st["mu"]) / st["sigma"]
    history = list(result.history)
    blocks = []
    rnd = result.rounds + 1
    cols = st.get("inputs") or [list(range(zn.shape[1])) for _ in comp]
    for k, block in enumerate(st["blocks"]):
        theta = np.concatenate([np.ravel(a) for a in block])
        total = cfg.lm_iterations + cfg.minimax_rounds * cfg.minimax_iterations
        bar = progress_bar(total, progress, f"φ[{comp[k]}] refine {rnd}")
        zk = zn if len(cols[k]) == zn.shape[1] else zn[:, cols[k]]
        blocks.append(polish(zk, residual(zk, yn[:, k], st["linear"][k]), len(block[1]), cfg,
                             theta, bar, history, f"φ[{comp[k]}] {system.name} round {rnd}", t0))
        if bar is not None:
            bar.close()
    seconds = dict(result.seconds)
    seconds["training"] = seconds.get("training", 0.0) + time.perf_counter() - t0
    st.update(z=z, blocks=blocks)
    return _finish(system, cfg, grid, model, comp, st, seconds, history, rnd)


def _worst_nodes(system, network: Network, grid: Grid, model: str, comp: list[int], n: int,
                 batch_size: int) -> np.ndarray:
    """The ``n`` grid nodes with the largest ``|f_k − φ_k|`` for each component (union)."""
    if n <= 0:
        return np.zeros((0, grid.dim))
    best_e = [np.zeros(0) for _ in comp]
    best_i = [np.zeros(0, dtype=np.int64) for _ in comp]
    start = 0
    for z in grid.batches(batch_size):
        e = np.abs(_target(system, model, comp, z) - network.numpy(z))
        idx = np.arange(start, start + len(z))
        start += len(z)
        for k in range(len(comp)):
            ek = np.concatenate([best_e[k], e[:, k]])
            ik = np.concatenate([best_i[k], idx])
            if len(ek) > n:  # a stable sort: ties keep grid order (deterministic)
                keep = np.argsort(-ek, kind="stable")[:n]
                ek, ik = ek[keep], ik[keep]
            best_e[k], best_i[k] = ek, ik
    return grid.points(np.unique(np.concatenate(best_i)))


def _boundary_nodes(grid: Grid, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` random nodes on the faces of the grid box (max errors like to sit there)."""
    if n <= 0:
        return np.zeros((0, grid.dim))
    idx = rng.integers(0, grid.counts, size=(n, grid.dim))
    axis = rng.integers(0, grid.dim, size=n)
    side = rng.integers(0, 2, size=n)
    idx[np.arange(n), axis] = side * (grid.counts[axis] - 1)
    return np.stack([grid.axes[k][idx[:, k]] for k in range(grid.dim)], axis=1)


def _jsonable(obj):
    return json.loads(json.dumps(obj, default=lambda o: np.asarray(o).tolist()))
