"""Configuration of the learned-dynamics stage: one typed dataclass, presets, one validator.

:class:`DynamicsConfig` lists every setting of the stage (sampling grid, network φ, its
training, the bounds on η, and the η gate) with its type and default. Presets
(:data:`PRESETS`: ``"default"`` and ``"fast"``) give per-system values; a run configuration's
``dynamics`` section and ``nlyap learn-dynamics --config FILE`` override them key by key
through :func:`dynamics_config`, which refuses unknown keys (with a "did you mean"), wrong
types and out-of-range values with a :class:`~nlyap_opt.kernel.errors.ConfigError` naming the key.

Every training budget is a count (steps, iterations, rounds), never a wall-clock time
: the same configuration and seed give the same φ on any machine load.

Examples
--------
>>> cfg = dynamics_config("van_der_pol", {"preset": "fast", "hidden": 8})
>>> cfg.hidden, cfg.grid_counts, cfg.preset
(8, [61, 61], 'fast')
>>> dynamics_config("van_der_pol", {"hiden": 8})
Traceback (most recent call last):
...
nlyap_opt.kernel.errors.ConfigError: unknown dynamics config key 'hiden' (did you mean 'hidden'?)
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import math
import typing
from dataclasses import dataclass
from numbers import Integral, Real
from pathlib import Path

from ..kernel.errors import ConfigError, UnknownNameError
from ..kernel.jsonio import read_json_object

__all__ = [
    "DynamicsConfig", "dynamics_config", "PRESETS", "MODELS", "config_keys",
    "load_dynamics_config",
]

MODELS = ("full", "control_affine")
_BOUND_NAMES = ("global", "anisotropic", "second_order")


@dataclass
class DynamicsConfig:
    """Every setting of the learned-dynamics stage, with its type and default.

    Attributes
    ----------
    system : str
        Catalogue name the configuration was made for (informational; ``""`` if none).
    preset : str
        ``"default"`` or ``"fast"``: the per-system values the overrides were applied to.
    comment : str
        Free text (kept in the saved network's metadata).
    model : str
        ``"full"`` (φ(x, u) on a grid over X × U) or ``"control_affine"`` (φ0(x) on a grid
        over X, f = f0(x) + B u with the known constant B).
    hidden : int or list of int
        Hidden tanh neurons: a total (split evenly over the learned components) or one
        width per learned component.
    grid_counts : list of int, optional
        Nodes per axis of the sampling grid (give this or ``grid_spacing``).
    grid_spacing : float or list of float, optional
        Largest spacing per axis (the coarsest grid with at most that spacing).
    learned_components : list of int, optional
        State derivatives to learn (default: those not in
        ``system.known_state_derivatives``).
    inputs : {"all", "model"}
        The inputs of each learned component's block of φ: ``"all"`` (default) every grid
        variable; ``"model"`` the grid variables that component of the model ``f`` depends
        on (symbolically), or for a system without a model those its declaration
        ``depends_on`` lists (:class:`systems.Declarations`; every variable where nothing
        is declared; the second-order bound then drops ``H`` along the others). The cartpole's
        accelerations depend on ``(θ, ω, F)`` only: φ then ignores the cart's position and
        velocity, so ``f − φ`` is constant along those axes and two grid nodes per such
        axis suffice (their interpolation term is exactly 0).
    state_box, input_box : list of [lo, hi], optional
        Sampling box (default: the system's X and U).
    train_points, boundary_points : int
        Random distinct grid nodes, and random nodes on the box faces, φ is trained on.
    steps : int
        Adam steps per learned component.
    batch_size : int
        Adam minibatch size.
    lr, lr_final : float
        Adam learning rate, cosine-annealed from ``lr`` to ``lr_final``.
    train_dtype : str
        ``"float32"`` or ``"float64"`` for the Adam stage (LM runs in float64).
    lm_iterations : int
        Levenberg–Marquardt iterations (mean squared error) after Adam.
    minimax_rounds, minimax_iterations : int
        Lawson-reweighted LM rounds (lowering the maximum error) and iterations per round.
    lm_ridge : float
        Ridge weight ρ on the hidden-layer weights in LM: the fit minimises
        Σ_i r_i² + ρ·N·‖W₀‖², in normalised units (inputs scaled to [−1, 1] by the grid's
        centre and radius, outputs standardised), so the default does not depend on the
        system's units or the number N of training points. It keeps hidden slopes moderate:
        a steep neuron with a negligible output weight costs nothing in the fit but inflates
        K_φ and the curvature, hence η, and which neuron turns steep depends on the last bits
        of the BLAS kernel. 1e-8 is the default: on the seed systems' fast presets it gives
        η equal to 5 digits on OpenBLAS's SkylakeX and Haswell kernels and below the η of
        ρ = 1e-14 (path following 0.0062 vs 0.0070, pendulum 0.0141 vs 0.0176); 1e-6 already
        costs accuracy (pendulum 0.057).
    prune : float
        Neurons with ``|output weight| ≤ prune`` are removed before α is measured.
    seed : int
        Seed of the training-node draw and of the network initialisation.
    threads : int
        torch threads during training (set and restored around it): fixed so that results
        do not depend on the machine.
    bound_model : str
        ``"best"`` or a bound option name (:data:`nlyap_opt.learned.bounds.BOUND_OPTIONS`).
    bound_options : list of str, optional
        Options computed (default: all).
    interval_boxes : int
        About this many sub-boxes for the interval bounds (K_f, K_φ, L_i, D).
    interval_counts : list of int, optional
        Sub-boxes per axis instead of ``interval_boxes``.
    check_points : int
        Random off-grid points where ‖f − φ‖ is evaluated as a test of η.
    probe_points : int
        Evaluations of a black-box callable at seeded random points between the grid
        nodes, before training, that refute a declared ``K_f``, ``H``, ``depends_on`` or
        ``B`` they contradict (``0``: grid check only; sample files cannot be probed).
    eval_batch : int
        Grid nodes per batch when α is measured.
    progress : bool
        tqdm progress bars.
    eta_target : float, optional
        The η gate of :func:`nlyap_opt.learned.dynamics.dynamics_stage`: above it, training goes on
        for at most ``eta_rounds`` refinement rounds, then the stage stops with status
        ``"eta_too_large"`` and advice. ``None`` disables the gate.
    eta_rounds : int
        Most refinement rounds when η exceeds ``eta_target``.
    refine_points : int
        Grid nodes with the largest error added to the training set in each refinement round.
    """

    system: str = ""
    preset: str = "default"
    comment: str = ""
    model: str = "full"
    hidden: int | list[int] = 100
    grid_counts: list[int] | None = None
    grid_spacing: float | list[float] | None = None
    learned_components: list[int] | None = None
    inputs: str = "all"
    state_box: list[list[float]] | None = None
    input_box: list[list[float]] | None = None
    train_points: int = 8000
    boundary_points: int = 1000
    steps: int = 2000
    batch_size: int = 256
    lr: float = 1e-2
    lr_final: float = 1e-4
    train_dtype: str = "float32"
    lm_iterations: int = 100
    minimax_rounds: int = 5
    minimax_iterations: int = 10
    lm_ridge: float = 1e-8
    prune: float = 1e-12
    seed: int = 0
    threads: int = 1
    bound_model: str = "best"
    bound_options: list[str] | None = None
    interval_boxes: int = 16384
    interval_counts: list[int] | None = None
    check_points: int = 200000
    probe_points: int = 30000
    eval_batch: int = 1 << 17
    progress: bool = True
    eta_target: float | None = None
    eta_rounds: int = 2
    refine_points: int = 2000

    def __post_init__(self):
        _validate(self)

    def to_dict(self) -> dict:
        """Every key and value (JSON-able); :func:`dynamics_config` accepts it back."""
        return {f.name: copy.deepcopy(getattr(self, f.name)) for f in dataclasses.fields(self)}

    def replace(self, **changes) -> DynamicsConfig:
        """A validated copy with ``changes`` applied (same rules as :func:`dynamics_config`)."""
        return _apply(self, changes)

    # dict-style read access: older code reads ``cfg["steps"]``
    def __getitem__(self, key: str):
        if key not in _FIELDS:
            raise KeyError(key)
        return getattr(self, key)

    def get(self, key: str, default=None):
        return getattr(self, key) if key in _FIELDS else default


_FIELDS = {f.name: f for f in dataclasses.fields(DynamicsConfig)}


def config_keys() -> dict[str, str]:
    """``{key: type as text}`` of every accepted key (for other validators and docs)."""
    hints = typing.get_type_hints(DynamicsConfig)
    return {k: _type_text(hints[k]) for k in _FIELDS}


# ============================================================================ presets
#: per-system values of the ``default`` preset (``nlyap learn-dynamics NAME``). The budgets
#: are step counts; the eta targets are explained in :func:`dynamics_config`.
_DEFAULT: dict[str, dict] = {
    "van_der_pol": {
        "model": "full", "hidden": 100, "grid_counts": [601, 601],
        "train_points": 8000, "boundary_points": 1000, "steps": 2000,
        "lm_iterations": 100, "minimax_rounds": 5, "minimax_iterations": 10,
        "eta_target": 0.025,
    },
    "unicycle_path_following": {
        "model": "full", "hidden": [20, 150], "grid_counts": [321, 81, 21],
        "train_points": 6000, "boundary_points": 1500, "steps": 2000,
        "lm_iterations": 100, "minimax_rounds": 5, "minimax_iterations": 10,
        "eta_target": 0.015,
    },
    "inverted_pendulum": {
        "model": "control_affine", "hidden": 100, "grid_counts": [401, 401],
        "train_points": 6000, "boundary_points": 1000, "steps": 2000,
        "lm_iterations": 200, "minimax_rounds": 5, "minimax_iterations": 10,
        "eta_target": 0.05,
    },
}

#: per-system values of the ``fast`` preset (tests; seconds each)
_FAST: dict[str, dict] = {
    "van_der_pol": {"model": "full", "hidden": 12, "grid_counts": [61, 61],
                    "train_points": 600, "boundary_points": 100, "steps": 200,
                    "lm_iterations": 30, "minimax_rounds": 1, "minimax_iterations": 5,
                    "interval_boxes": 1024, "check_points": 20000},
    "unicycle_path_following": {"model": "full", "hidden": 12, "grid_counts": [21, 21, 9],
                                "train_points": 600, "boundary_points": 100, "steps": 200,
                                "lm_iterations": 30, "minimax_rounds": 1,
                                "minimax_iterations": 5, "interval_boxes": 1024,
                                "check_points": 20000},
    "inverted_pendulum": {"model": "full", "hidden": 12, "grid_counts": [21, 21, 9],
                          "train_points": 600, "boundary_points": 100, "steps": 200,
                          "lm_iterations": 30, "minimax_rounds": 1, "minimax_iterations": 5,
                          "interval_boxes": 1024, "check_points": 20000},
}

#: ``{preset: {system: overrides}}``; systems not listed take the dataclass defaults
PRESETS: dict[str, dict[str, dict]] = {"default": _DEFAULT, "fast": _FAST}


# ============================================================================ entry point
def dynamics_config(system_name: str, overrides: dict | None = None) -> DynamicsConfig:
    """The validated dynamics configuration of ``system_name`` with ``overrides`` applied.

    ``overrides["preset"]`` (``"default"`` or ``"fast"``) chooses the per-system base values
    (:data:`PRESETS`); the other keys replace them. A grid given one way (``grid_counts`` or
    ``grid_spacing``) replaces a preset's grid given the other way.

    Parameters
    ----------
    system_name : str
        Catalogue name (any name works; unlisted systems take the dataclass defaults and must
        give a grid).
    overrides : dict, optional
        Keys of :class:`DynamicsConfig`.

    Returns
    -------
    DynamicsConfig

    Raises
    ------
    ConfigError
        An unknown key (with the closest known key), a value of the wrong type, or one out
        of range; the message names the key and what it accepts.
    UnknownNameError
        An unknown preset.

    Notes
    -----
    The default presets carry an ``eta_target`` (the η gate of
    :func:`nlyap_opt.learned.dynamics_stage.dynamics_stage`): half the η at which the robust term
    ``η·‖∇V‖`` outweighs the linearised decrease of the LQR quadratic certificate on the
    paper presets' inner rings (:func:`nlyap_opt.learned.dynamics_stage.eta_limit_linear`), 10–20
    times the η their step budgets reach. The fast presets have none (their φ is coarse on
    purpose; a run configuration may set one).
    """
    if overrides is not None and not isinstance(overrides, dict):
        raise ConfigError(
            f"the dynamics config must be a JSON object (dict), got {type(overrides).__name__}"
        )
    over = dict(overrides or {})
    preset = over.get("preset", "default")
    if preset not in PRESETS:
        raise UnknownNameError(
            f"unknown dynamics preset {preset!r}; available: {', '.join(PRESETS)}"
        )
    _check_keys(over)
    base = dict(PRESETS[preset].get(system_name, {}))
    if over.get("grid_spacing") is not None and "grid_counts" not in over:
        base["grid_counts"] = None
    if over.get("grid_counts") is not None and "grid_spacing" not in over:
        base["grid_spacing"] = None
    base.update(over)
    base["preset"] = preset
    base.setdefault("system", system_name)
    if base["system"] in (None, ""):
        base["system"] = system_name
    if base["system"] != system_name:
        raise ConfigError(
            f"dynamics config is for system {base['system']!r}, not {system_name!r}: fix its "
            "'system' key or drop it"
        )
    return DynamicsConfig(**base)


def load_dynamics_config(path: str | Path | None, system_name: str | None = None,
                         preset: str = "default", overrides: dict | None = None
                         ) -> DynamicsConfig:
    """:func:`dynamics_config` of ``system_name`` over a JSON file (and then ``overrides``)."""
    over: dict = {}
    if path is not None:
        over = read_json_object(path)
    name = system_name or over.get("system")
    if not name:
        raise ConfigError("no system named: pass NAME or put 'system' in the config file")
    over = {"preset": preset, **over, **(overrides or {})}
    return dynamics_config(name, over)


# ============================================================================ validation
def _check_keys(over: dict) -> None:
    for key in over:
        if key not in _FIELDS:
            if not isinstance(key, str):
                raise ConfigError(f"dynamics config keys must be strings, got {key!r}")
            close = difflib.get_close_matches(key, list(_FIELDS), n=1, cutoff=0.6)
            hint = f" (did you mean {close[0]!r}?)" if close else \
                f"; known keys: {', '.join(_FIELDS)}"
            if key == "time_budget":
                hint = ("; budgets are counted in steps, never wall time: set 'steps', "
                        "'lm_iterations' or 'minimax_rounds' instead")
            raise ConfigError(f"unknown dynamics config key {key!r}{hint}")


def _apply(cfg: DynamicsConfig, changes: dict) -> DynamicsConfig:
    _check_keys(changes)
    d = cfg.to_dict()
    if changes.get("grid_spacing") is not None and "grid_counts" not in changes:
        d["grid_counts"] = None
    if changes.get("grid_counts") is not None and "grid_spacing" not in changes:
        d["grid_spacing"] = None
    d.update(changes)
    return DynamicsConfig(**d)


def _type_text(tp) -> str:
    return str(tp).replace("typing.", "").replace("NoneType", "None")


def _fail(key: str, value, want: str):
    raise ConfigError(f"dynamics config {key!r} must be {want}, got {value!r}")


def _is_int(v) -> bool:
    return isinstance(v, Integral) and not isinstance(v, bool)


def _is_real(v) -> bool:
    return isinstance(v, Real) and not isinstance(v, bool)


def _int(cfg, key, lo):
    v = getattr(cfg, key)
    if not _is_int(v) or v < lo:
        _fail(key, v, f"an integer >= {lo}")
    if v > 2**53:  # an edit or a typo, no budget (torch cannot seed with it)
        _fail(key, v, "an integer <= 2^53")
    setattr(cfg, key, int(v))


def _real(cfg, key, *, positive=False, optional=False):
    v = getattr(cfg, key)
    if v is None and optional:
        return
    if not _is_real(v) or not math.isfinite(float(v)) or float(v) < 0 or \
            (positive and float(v) == 0):
        _fail(key, v, "a finite number > 0" if positive else "a finite number >= 0")
    setattr(cfg, key, float(v))


def _int_list(cfg, key, lo, optional=True):
    v = getattr(cfg, key)
    if v is None and optional:
        return
    if not isinstance(v, (list, tuple)) or not v or not all(_is_int(c) and c >= lo for c in v):
        _fail(key, v, f"a non-empty list of integers >= {lo}")
    setattr(cfg, key, [int(c) for c in v])


def _box(cfg, key):
    v = getattr(cfg, key)
    if v is None:
        return
    ok = isinstance(v, (list, tuple)) and v and all(
        isinstance(r, (list, tuple)) and len(r) == 2 and all(_is_real(a) for a in r)
        and math.isfinite(r[0]) and math.isfinite(r[1]) and r[0] < r[1] for r in v)
    if not ok:
        _fail(key, v, "a list of [lo, hi] rows with finite lo < hi")
    setattr(cfg, key, [[float(a), float(b)] for a, b in v])


def _validate(cfg: DynamicsConfig) -> None:
    for key in ("system", "preset", "comment"):
        if not isinstance(getattr(cfg, key), str):
            _fail(key, getattr(cfg, key), "a string")
    if cfg.model not in MODELS:
        _fail("model", cfg.model, f"one of {', '.join(MODELS)}")
    if cfg.inputs not in ("model", "all"):
        _fail("inputs", cfg.inputs, "'model' or 'all'")
    if cfg.train_dtype not in ("float32", "float64"):
        _fail("train_dtype", cfg.train_dtype, "'float32' or 'float64'")
    h = cfg.hidden
    if _is_int(h):
        if h < 1:
            _fail("hidden", h, "a positive integer or a list of them")
        cfg.hidden = int(h)
    else:
        _int_list(cfg, "hidden", 1, optional=False)
    _int_list(cfg, "grid_counts", 2)
    g = cfg.grid_spacing
    if g is not None:
        vals = g if isinstance(g, (list, tuple)) else [g]
        if not vals or not all(_is_real(a) and math.isfinite(a) and a > 0 for a in vals):
            _fail("grid_spacing", g, "a positive number or a list of them")
        cfg.grid_spacing = [float(a) for a in vals] if isinstance(g, (list, tuple)) \
            else float(g)
    if cfg.learned_components is not None:
        _int_list(cfg, "learned_components", 0)
        if len(set(cfg.learned_components)) != len(cfg.learned_components):
            _fail("learned_components", cfg.learned_components, "distinct state indices")
    _box(cfg, "state_box")
    _box(cfg, "input_box")
    for key in ("train_points", "batch_size", "threads", "interval_boxes", "eval_batch"):
        _int(cfg, key, 1)
    for key in ("boundary_points", "steps", "lm_iterations", "minimax_rounds",
                "minimax_iterations", "check_points", "probe_points", "seed", "eta_rounds",
                "refine_points"):
        _int(cfg, key, 0)
    _real(cfg, "lr", positive=True)
    _real(cfg, "lr_final", positive=True)
    _real(cfg, "lm_ridge")
    _real(cfg, "prune")
    _real(cfg, "eta_target", positive=True, optional=True)
    if not isinstance(cfg.progress, bool):
        _fail("progress", cfg.progress, "true or false")
    if cfg.bound_model != "best" and cfg.bound_model not in _BOUND_NAMES:
        _fail("bound_model", cfg.bound_model, f"'best' or one of {', '.join(_BOUND_NAMES)}")
    if cfg.bound_options is not None:
        b = cfg.bound_options
        if not isinstance(b, (list, tuple)) or not b or any(x not in _BOUND_NAMES for x in b):
            _fail("bound_options", b, f"a non-empty list from {', '.join(_BOUND_NAMES)}")
        cfg.bound_options = list(b)
        if cfg.bound_model != "best" and cfg.bound_model not in b:
            _fail("bound_model", cfg.bound_model, f"'best' or one of bound_options {b}")
    _int_list(cfg, "interval_counts", 1)
    _check_sizes(cfg)


#: the most numbers one array that a dynamics setting sizes may hold (0.8 GB of float64);
#: the run configuration's own settings have the same limit
MAX_ARRAY_NUMBERS = 10**8


def _check_sizes(cfg: DynamicsConfig) -> None:
    """Grids, point sets and networks whose arrays would exceed :data:`MAX_ARRAY_NUMBERS`
    are refused before anything runs (instead of ending the run out of memory)."""
    hidden = sum(cfg.hidden) if isinstance(cfg.hidden, list) else cfg.hidden
    dims = max(len(cfg.grid_counts or []), len(cfg.interval_counts or []), 1)
    sizes = [("grid_counts", cfg.grid_counts, math.prod(cfg.grid_counts or [0]) * dims,
              "grid coordinates"),
             ("interval_counts", cfg.interval_counts,
              math.prod(cfg.interval_counts or [0]) * 2 * dims, "box bounds"),
             ("interval_boxes", cfg.interval_boxes, cfg.interval_boxes * 2 * dims, "box bounds"),
             ("hidden", cfg.hidden, hidden * (cfg.train_points + cfg.boundary_points),
              "hidden activations of the training points"),
             ("check_points", cfg.check_points, cfg.check_points * dims, "coordinates"),
             ("probe_points", cfg.probe_points, cfg.probe_points * dims, "coordinates"),
             ("eval_batch", cfg.eval_batch, cfg.eval_batch * max(hidden, dims),
              "activations per batch")]
    for key, value, numbers, what in sizes:
        if numbers > MAX_ARRAY_NUMBERS:
            raise ConfigError(f"dynamics config {key!r} = {value!r} makes {numbers:.3g} {what}, "
                              f"beyond the {MAX_ARRAY_NUMBERS:.0e} numbers one array may hold "
                              "(0.8 GB); lower it")
