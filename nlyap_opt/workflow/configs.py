"""Run configurations: presets of the seed systems and one validated schema for all of them.

A run configuration is a JSON object, held as a :class:`RunConfig` (a frozen tree of
:class:`Section` objects with typed attribute access and the schema's defaults; it reads
like the JSON mapping and writes back the same JSON). Presets: ``paper`` (the paper's discs),
``large`` (aim at the whole true ROA) and ``fast`` (coarse, for the test suite).
:func:`make_config` (the one-shot public entry) and :func:`get_config` (the command line's)
merge a JSON file and a dict of overrides over a preset and validate the result **before**
any stage runs. Sections and keys:

- ``outer`` (r), ``inner`` (ε): the verification annulus, finite, ``0 < inner < outer``;
- ``domain``: the verification domain ``D`` in place of the ball ``‖x‖ ≤ outer`` (a box,
  an ellipsoid or a ball, :func:`nlyap_opt.kernel.domain.parse_set`; ``outer`` is then null),
  ``initial_set``: a set ``X_I`` the certificate must prove inside the certified set;
- ``controller_scale`` (C): actuator limit of ``u = C·tanh(Kx + b)`` (``null`` for a system
  without inputs, a positive number otherwise);
- ``lqr``: ``{"Q": ..., "R": ...}`` weights of the initial LQR gain (scalar or matrix;
  Q symmetric positive semidefinite, R symmetric positive definite);
- ``train``: the fields of :class:`nlyap_opt.candidates.learning.TrainConfig`;
- ``cegis``: the fields of :class:`nlyap_opt.candidates.cegis.CegisConfig` except ``inner``,
  ``outer`` and ``train`` (given above);
- ``eval_box`` (one ``[lo, hi]`` row per state), ``eval_points`` (total point budget): box and
  grid of the areas and of the simulated true ROA; ``eval_time``: its simulated horizon;
- ``dynamics``: the learned-dynamics stage, keys of
  :class:`nlyap_opt.learned.dynamics_config.DynamicsConfig` (``preset``: ``"default"`` or
  ``"fast"``);
- ``system``, ``preset``, ``comment``: informational (``system`` and ``preset`` must match).

The ``train`` and ``cegis`` keys are *derived* from the dataclasses by introspection
(:func:`dataclasses.fields` and their type hints), so each key is defined once, where it is
used; :data:`_RULES` adds the ranges and choices that a type cannot say. Unknown keys are
refused with a "did you mean", and so are wrong types, NaN, inf and values out of range:
every error is a :class:`~nlyap_opt.kernel.errors.ConfigError` naming the key.

Examples
--------
>>> cfg = make_config("van_der_pol", "fast", overrides={"train": {"steps": 50}})
>>> cfg.train.steps, cfg.outer, cfg.cegis.margin_mode
(50, 1.0, 'pointwise')
>>> make_config("van_der_pol", "fast", overrides={"train": {"stpes": 50}})  # doctest: +ELLIPSIS
Traceback (most recent call last):
...
nlyap_opt...ConfigError: run config: unknown key 'train.stpes'; did you mean 'train.steps'?
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import functools
import json
import math
import os
import types
import typing
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from numbers import Integral, Real
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

import systems
from verification.verify import file_options, option_conflict

from ..candidates.quadratic import QUADRATIC_CANDIDATES
from ..candidates.sos import SOSConfig, choose_degree
from ..design.control import lqr
from ..kernel.domain import Ball, parse_set
from ..kernel.errors import ConfigError, UnknownNameError
from ..kernel.jsonio import read_json_object
from ..learned.dynamics_config import MAX_ARRAY_NUMBERS, DynamicsConfig, dynamics_config

__all__ = [
    "DEFAULT_CEGIS", "DEFAULT_TRAIN", "PRESETS", "Key", "RunConfig", "Section",
    "UndeclaredKeyError", "check_dynamics_box", "check_lqr_weights", "config_reference",
    "get_config", "make_config", "read_json_object", "schema", "validate_config",
]


# ============================================================================ presets
_VDP_BOX = [[-3.0, 3.0], [-3.0, 3.0]]

PRESETS: dict[str, dict[str, dict]] = {
    "van_der_pol": {
        "paper": {
            "outer": 1.2, "inner": 0.2, "controller_scale": None,
            "train": {"hidden": [16], "features": 4, "steps": 1500, "lr": 0.01},
            "cegis": {"iterations": 4, "steps": 500},
            "eval_box": _VDP_BOX, "eval_points": 90000,
            "dynamics": {"preset": "default"},
        },
        "large": {
            "outer": 3.0, "inner": 0.2, "controller_scale": None,
            # V fitted to the simulated trajectory cost (its sublevel sets grow to the ROA)
            # plus the decrease terms; the verifier runs every third iteration
            "train": {"hidden": [20, 20], "features": 6, "steps": 1500, "lr": 0.01,
                      "lr_schedule": "cosine", "decay": 0.05, "level_slack": 0.5,
                      "relative_decrease": True, "w_fit": 10.0, "w_pde": 1.0,
                      "w_local": 10.0},
            "cegis": {"iterations": 6, "steps": 500, "verify_every": 3, "sim_time": 30.0,
                      "sim_dt": 0.04, "sim_points": 90601,
                      "inner_samples": 2000, "boundary_samples": 20000},
            "eval_box": _VDP_BOX, "eval_points": 90000,
            # φ must be bounded on a box that holds the verification ball r = 3
            "dynamics": {"preset": "default", "state_box": [[-3.0, 3.0], [-3.0, 3.0]],
                         "grid_counts": [1201, 1201]},
        },
        "fast": {
            # ε = 0.3: with the fast φ (η ≈ 0.035) the robust decrease η‖∇V‖ outweighs
            # Van der Pol's weak linear decrease on a 0.2 ring
            "outer": 1.0, "inner": 0.3, "controller_scale": None,
            "train": {"hidden": [6], "features": 3, "steps": 300, "lr": 0.02},
            "cegis": {"iterations": 2, "steps": 100, "samples": 4000},
            "eval_box": _VDP_BOX, "eval_points": 10000,
            "dynamics": {"preset": "fast"},
        },
    },
    "unicycle_path_following": {
        "paper": {
            "outer": 0.8, "inner": 0.1, "controller_scale": 5.0,
            "train": {"hidden": [16], "features": 4, "steps": 1500, "lr": 0.01},
            # sim_points: the training simulations run on a table of the learned φ
            "cegis": {"iterations": 6, "steps": 500, "sim_points": 90601},
            "eval_box": [[-0.8, 0.8], [-0.8, 0.8]], "eval_points": 40000,
            "dynamics": {"preset": "default"},
        },
        "fast": {
            "outer": 0.8, "inner": 0.1, "controller_scale": 5.0,
            "train": {"hidden": [6], "features": 3, "steps": 300, "lr": 0.02},
            "cegis": {"iterations": 2, "steps": 100, "samples": 4000},
            "eval_box": [[-0.8, 0.8], [-0.8, 0.8]], "eval_points": 10000,
            # the full-model fast φ of path following has η ≈ 0.4, too coarse for ε = 0.1;
            # the control-affine model on a 161² x-grid reaches η ≈ 0.01 in ~13 s
            "dynamics": {"preset": "fast", "model": "control_affine", "hidden": 60,
                         "grid_counts": [161, 161], "train_points": 4000, "steps": 800,
                         "lm_iterations": 60, "minimax_rounds": 3,
                         "interval_boxes": 4096},
        },
    },
    "inverted_pendulum": {
        "paper": {
            "outer": 4.0, "inner": 0.4, "controller_scale": 20.0,
            # more derivative weight than Q = I: with Q = I only 71% of the disc stays in the
            # disc along trajectories (no certificate inside B_r can exceed that); with
            # Q = diag(1, 20) 97% does (measured by simulation)
            "lqr": {"Q": [[1.0, 0.0], [0.0, 20.0]], "R": 1.0},
            # w_local: first-order decrease at the origin (the ring next to B_ε failed in
            # some iterations without it); at least two iterations, the best area kept
            "train": {"hidden": [32], "features": 8, "steps": 3000, "lr": 0.01,
                      "w_inside": 1.0, "w_local": 10.0, "lr_schedule": "cosine"},
            "cegis": {"iterations": 4, "min_iterations": 2, "steps": 500, "sim_points": 90601},
            "eval_box": [[-4.0, 4.0], [-4.0, 4.0]], "eval_points": 40000,
            "dynamics": {"preset": "default"},
        },
        "fast": {
            "outer": 4.0, "inner": 0.4, "controller_scale": 20.0,
            "lqr": {"Q": [[1.0, 0.0], [0.0, 20.0]], "R": 1.0},
            "train": {"hidden": [6], "features": 3, "steps": 300, "lr": 0.02},
            "cegis": {"iterations": 2, "steps": 100, "samples": 4000},
            "eval_box": [[-4.0, 4.0], [-4.0, 4.0]], "eval_points": 10000,
            "dynamics": {"preset": "fast", "model": "control_affine", "hidden": 40,
                         "grid_counts": [201, 201], "train_points": 3000, "steps": 600,
                         "lm_iterations": 40, "minimax_rounds": 2,
                         "interval_boxes": 4096},
        },
    },
}
# 4-D / 6-D catalogue systems. Areas are volumes on coarse grids (n^4, n^6 points);
# CEGIS's area grid is coarse for the same reason. Their input matrices depend on θ, so the
# learned-dynamics model is "full" (φ of the unknown components on X × U), known state
# derivatives (p' = v, θ' = ω; x' = ẋ, ...) taken from the model. The verifier runs with its
# second-order centred form: without it, condition (a) next to the inner ball needs > 10^7
# interval boxes in 4-D (bench/scale.py); with it the LQR quadratic certifies in 4-D and 6-D
# (tests/test_highdim.py). The trained V of these presets is not certified yet (CEGIS finds
# true decrease counterexamples: a training matter).
_CARTPOLE_BOX = [[-1.0, 1.0]] * 4
_QUAD_BOX = [[-1.0, 1.0]] * 6
PRESETS["cartpole"] = {
    "fast": {
        "outer": 0.5, "inner": 0.1, "controller_scale": 10.0,
        "train": {"hidden": [8], "features": 4, "steps": 300, "lr": 0.02},
        "cegis": {"iterations": 2, "steps": 100, "samples": 4000, "area_points": 14641,
                  "verify_options": {"second_order": True}},
        "eval_box": _CARTPOLE_BOX, "eval_points": 14641,
        "dynamics": {"preset": "fast", "model": "full", "hidden": 24,
                     "grid_counts": [5, 5, 13, 13, 9], "train_points": 3000,
                     "boundary_points": 300, "steps": 300, "lm_iterations": 30,
                     "minimax_rounds": 1, "minimax_iterations": 5,
                     "interval_boxes": 4096, "check_points": 20000},
    },
    "large": {
        "outer": 1.0, "inner": 0.1, "controller_scale": 10.0,
        # Q = diag(10, 1, 1, 1): the best-conditioned LQR P of a small weight scan (cond 330)
        "lqr": {"Q": [[10.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]],
                "R": 1.0},
        # the cheap certificates first (nlyap_opt.candidates.quadratic): the LQR P certifies level
        # 0.0192 (volume 0.0031), the round P level 0.999 (volume 0.154, 48 times), the
        # volume P (largest Lyapunov ellipsoid in the ball) volume 0.52 (learned f: 0.235,
        # the round P 0.048); the neural V must beat the best one or the quadratic is the
        # run's certificate
        "quadratic": ["lyapunov", "round", "volume"],
        "train": {"hidden": [16], "features": 6, "steps": 1500, "lr": 0.01,
                  "w_local": 10.0, "lr_schedule": "cosine"},
        # max_boxes: with learned f the round quadratic's decrease at the smallest level
        # holding ε = 0.1 (0.61) verifies in 2.43·10⁶ boxes (the default budget is 2·10⁶)
        "cegis": {"iterations": 4, "steps": 500, "samples": 20000, "area_points": 50625,
                  "verify_options": {"second_order": True, "max_boxes": 4_000_000}},
        "eval_box": _CARTPOLE_BOX, "eval_points": 50625,
        # φ's blocks read (θ, ω, F) only (inputs: model): f − φ is constant along the
        # cart's position and velocity, two nodes there suffice, and the θ axis (where f
        # curves most) gets 161: η = 0.0041 (second-order bound) against 0.0193 on a
        # 9·9·41·41·21 grid with every input
        "dynamics": {"preset": "default", "model": "full", "hidden": 100, "inputs": "model",
                     "grid_counts": [2, 2, 161, 41, 41], "train_points": 8000,
                     "boundary_points": 1000, "steps": 2000, "interval_boxes": 16384},
    },
}
PRESETS["planar_quadrotor"] = {
    "fast": {
        "outer": 0.5, "inner": 0.1, "controller_scale": 0.486 * 9.81,  # m g
        "train": {"hidden": [8], "features": 6, "steps": 300, "lr": 0.02},
        "cegis": {"iterations": 2, "steps": 100, "samples": 4000, "area_points": 117649,
                  "verify_options": {"second_order": True}},
        "eval_box": _QUAD_BOX, "eval_points": 117649,
        "dynamics": {"preset": "fast", "model": "full", "hidden": 36,
                     "grid_counts": [3, 3, 9, 3, 3, 3, 7, 7], "train_points": 3000,
                     "boundary_points": 300, "steps": 300, "lm_iterations": 30,
                     "minimax_rounds": 1, "minimax_iterations": 5,
                     "interval_boxes": 4096, "check_points": 20000},
    },
    "large": {
        "outer": 1.0, "inner": 0.1, "controller_scale": 0.486 * 9.81,  # m g
        # the cheap certificates first: the LQR P certifies level 0.00526 at ε = 0.025 (exact
        # ellipsoid volume 1.85e-5) in 39 s; the volume P's decrease is proved in the Hessian
        # coordinates of the decrease (verifier option precondition): level 0.08 in 1.6·10⁵
        # boxes, where the axis-aligned boxes left it unknown after 1.5·10⁶; its level search
        # certifies level 0.258 (volume 0.0067, 362 times the LQR P's). The round P
        # (cond 71) stays unknown even at level 0.01 and is not listed. The sector P
        # (designed for the saturated controller's slopes and inputs on its own ellipsoid)
        # is the one whose decrease the whole-set test proves with learned dynamics
        "quadratic": ["lyapunov", "sector", "volume"],
        "train": {"hidden": [16], "features": 8, "steps": 1500, "lr": 0.01,
                  "w_local": 10.0, "lr_schedule": "cosine"},
        "cegis": {"iterations": 4, "steps": 500, "samples": 20000, "area_points": 531441,
                  "verify_options": {"second_order": True, "precondition": True}},
        "eval_box": _QUAD_BOX, "eval_points": 531441,
        # φ's blocks read (θ, u₁, u₂) and (u₁, u₂) only (inputs: model): two nodes on the
        # other axes. The pitch acceleration l(u₁ − u₂)/J spans ±620 over U: its fit sets α,
        # so it gets 60 neurons and LM a weaker ridge (1e-13; α 0.0024 against 0.0082 at
        # 1e-8). η on the whole box stays far above what the margin affords; the run's
        # local stage bounds it again near hover (0.0016 on the box of ‖x‖ ≤ 0.25)
        "dynamics": {"preset": "default", "model": "full", "hidden": [20, 20, 60],
                     "inputs": "model", "grid_counts": [2, 2, 41, 2, 2, 2, 21, 21],
                     "train_points": 8000, "boundary_points": 1000, "steps": 2000,
                     "lm_iterations": 300, "minimax_rounds": 10, "lm_ridge": 1e-13,
                     "interval_boxes": 16384},
    },
}

# the path-following and pendulum "large" configurations are the paper's discs: the true ROA
# of the closed loop covers them, so the target is the whole disc
PRESETS["unicycle_path_following"]["large"] = PRESETS["unicycle_path_following"]["paper"]
# The pendulum's CEGIS may lose its level for an iteration when counterexamples come in (seed
# 1 of bench/seeds.py: areas 37.4, 9.4, 10.7, 42.7, 46.7 over its first five iterations):
# a budget of 8 iterations (the stop rule ends good seeds after 2-3) lets such seeds recover.
PRESETS["inverted_pendulum"]["large"] = copy.deepcopy(PRESETS["inverted_pendulum"]["paper"])
PRESETS["inverted_pendulum"]["large"]["cegis"]["iterations"] = 8

#: The default method (``make_config(name, preset=None)``, every system without a preset):
#: V is fitted to a Zubov-type function of the whole region of attraction inside the domain
#: (:func:`nlyap_opt.candidates.cegis.cost_targets` of the simulated trajectory costs of the model,
#: the true f or φ, and the residual of its decrease law), with the decrease, containment and
#: first-order terms; CEGIS and the verified level as for every preset. Budgets are step
#: counts. The domain, inner radius and controller scale come from the system's boxes
#: (:func:`systems.default_run_settings`: the domain is the state box).
DEFAULT_TRAIN: dict = {
    "hidden": [32, 32], "features": 6, "steps": 3000, "lr": 0.01, "lr_schedule": "cosine",
    "decay": 0.0, "level_slack": 0.5, "relative_decrease": True, "w_fit": 10.0,
    "w_pde": 1.5, "w_local": 10.0, "fit_domain": True, "w_outside": 10.0, "w_inward": 10.0,
}
#: CEGIS of the default method: the verifier every third iteration and the last, on the
#: most promising iterate since its last call, training resumed from the best certified
#: iterate when the current one collapsed; training states near the model's ROA
#: boundary; simulations on a table of φ (learned f, <= 3-D)
DEFAULT_CEGIS: dict = {
    "iterations": 8, "extend": 3, "steps": 1000, "verify_every": 3, "sim_time": 30.0,
    "sim_dt": 0.04,
    "sim_points": 90601, "inner_samples": 2000, "boundary_samples": 20000,
    "sim_in_domain": True, "best_iterate": True, "gain_scan": True, "fit_fallback": True,
}

#: the base of ``make_config(name, preset=None, ...)`` for a system without a preset; the
#: system's boxes then give the domain, ``inner`` (and ``controller_scale`` for a system
#: with inputs), a spec file's ``[run]`` table and the caller's overrides come last
#: The cheap certificates run first by default: the quadratic ones, and an SOS V where it
#: applies (``sos.degree = "auto"``: the true f, a polynomial closed loop, small SDPs;
#: :func:`nlyap_opt.candidates.sos.choose_degree`). Where the neural V does not beat them
#: (e.g. a domain lying wholly in the ROA, where the Zubov-type target has no shape), the
#: run still certifies their sets, and says which certificate won.
_GENERIC: dict = {"controller_scale": None, "train": DEFAULT_TRAIN, "cegis": DEFAULT_CEGIS,
                  "eval_points": 40000, "dynamics": {"preset": "default"},
                  "quadratic": ["lyapunov", "round", "domain"], "sos": {"degree": "auto"}}


# ============================================================================ schema
@dataclass(frozen=True)
class Key:
    """One key of the run configuration: its type, default and admissible values.

    Attributes
    ----------
    name : str
        Dotted name (``"train.lr"``).
    kind : str
        ``"int"``, ``"float"``, ``"bool"``, ``"str"``, ``"int_list"``, ``"dict"``,
        ``"matrix"``, ``"box"``, ``"section"`` or ``"any"``.
    default : object
        Default value (``None`` where the preset or the caller must give it).
    optional : bool
        ``None`` (JSON ``null``) is accepted.
    lo, hi : float, optional
        Bounds; ``lo_open`` / ``hi_open`` make them strict.
    choices : tuple
        Admissible values of a ``"str"``, ``"str_list"`` or ``"int"`` key.
    doc : str
        One line for :func:`config_reference`.
    """

    name: str
    kind: str
    default: object = None
    optional: bool = False
    lo: float | None = None
    lo_open: bool = False
    hi: float | None = None
    hi_open: bool = False
    choices: tuple = ()
    doc: str = ""

    def describe(self) -> str:
        """What the key accepts, in words (``"an integer >= 1"``)."""
        if self.choices and self.kind == "str_list":
            want = "a list of names from " + ", ".join(repr(c) for c in self.choices)
        elif self.choices:
            want = "one of " + ", ".join(repr(c) for c in self.choices)
        else:
            want = {"int": "an integer", "float": "a finite number", "bool": "true or false",
                    "str": "a string", "int_list": "a non-empty list of integers",
                    "dict": "a JSON object", "matrix": "a finite number or a square matrix",
                    "box": "a list of [lo, hi] rows with finite lo < hi",
                    "section": "a JSON object", "any": "a JSON value",
                    "set": "a set: a JSON object with 'type' ball, box or ellipsoid",
                    "scale": "a finite number or a list of them (one per input)"}[self.kind]
            rng = []
            if self.lo is not None:
                rng.append(f"{'>' if self.lo_open else '>='} {self.lo:g}")
            if self.hi is not None:
                rng.append(f"{'<' if self.hi_open else '<='} {self.hi:g}")
            if rng:
                want += (" (each " if self.kind == "int_list" else " ") + " and ".join(rng) + \
                    (")" if self.kind == "int_list" else "")
        return want + (" or null" if self.optional else "")


_POS = {"lo": 0, "lo_open": True}
_NONNEG = {"lo": 0}
_COUNT = {"lo": 1}
_UNIT = {"lo": 0, "lo_open": True, "hi": 1}

#: ranges and choices of the dataclass fields (types and defaults come from the dataclasses;
#: a field's ``metadata`` may carry the same keys and then wins)
_RULES: dict[str, dict[str, dict]] = {
    "train": {
        "hidden": _COUNT, "features": _COUNT, "eps": _POS, "lr": _POS, "steps": _COUNT,
        "batch": _COUNT, "decay": _NONNEG, "level_slack": _NONNEG, "w_decrease": _NONNEG,
        "w_inside": _NONNEG, "w_outside": _NONNEG, "w_grad": _NONNEG, "w_anchor": _NONNEG,
        "w_inward": _NONNEG,
        "w_fit": _NONNEG, "fit_quantile": _UNIT, "fit_cap": _POS,
        "fit_transform": {"choices": ("log", "linear")}, "w_pde": _NONNEG,
        "w_local": _NONNEG, "lr_schedule": {"choices": ("constant", "cosine")},
        "activation": {"choices": ("tanh", "square", "linear")},
        "init": {"choices": ("random", "quadratic", "sos")},
        "seed": _NONNEG, "threads": _COUNT,
    },
    "cegis": {
        "iterations": _COUNT, "samples": _COUNT, "sphere_samples": _COUNT,
        "max_counterexamples": _COUNT, "neighbours": _NONNEG, "first_steps": _COUNT,
        "steps": _COUNT, "later_lr": _POS, "extend": _NONNEG, "verify_every": _COUNT,
        "target_fraction": _UNIT,
        "min_iterations": _COUNT, "plateau": _NONNEG, "area_points": {"lo": 4}, "seed": _NONNEG,
        "inner_samples": _NONNEG, "boundary_samples": _NONNEG, "sim_dt": _POS,
        "boundary_feedback": _NONNEG,
        "sim_points": _NONNEG, "sim_time": _POS, "sim_tol": _POS,
        "margin_mode": {"choices": ("pointwise", "global")}, "norm_smoothing": _NONNEG,
        "initial_samples": _NONNEG,
    },
}

#: dataclass fields that are not configuration keys: given elsewhere in the run config
#: (inner, outer, train), or removed (wall-clock budgets: the same config must give the same
#: result on any load)
_EXCLUDED = {"train": {"time_budget"},
             "cegis": {"inner", "outer", "train", "time_budget", "domain", "initial_set"}}

#: keys that are gone, with the fix to print
_REMOVED = {
    "eval_grid": "grids are total point budgets now: use 'eval_points' (n per axis = "
                 "n^nx points, e.g. 200 per axis in 2-D is eval_points 40000)",
    "area_grid": "grids are total point budgets now: use 'cegis.area_points' (n^nx points)",
    "sim_grid": "grids are total point budgets now: use 'cegis.sim_points' (n^nx points)",
    "time_budget": "wall-clock budgets were removed (the same config must give "
                   "the same result on any machine load); budgets are counted in steps: "
                   "set 'steps' / 'iterations' instead",
}

_TOP_DOCS = {
    "outer": "r: outer radius of the verification ball (null when 'domain' is given)",
    "inner": "ε: radius of the excluded inner ball (0 < inner < outer; B_ε inside the domain)",
    "domain": "verification domain D instead of the ball: {\"type\": \"box\", \"box\": "
              "[[lo, hi], ...]}, {\"type\": \"ellipsoid\", \"semi_axes\": [...]} or "
              "{... \"matrix\": Q}, {\"type\": \"ball\", \"radius\": r}; the origin inside",
    "initial_set": "X_I (same forms, a centre allowed): proved inside the certified set "
                   "(X_I ⊆ D and V < level on it), else the run is not certified",
    "controller_scale": "C of u = C·tanh(Kx + b); null for a system without inputs",
    "lqr": "weights {Q, R} of the initial LQR gain",
    "train": "V and κ training (nlyap_opt.candidates.learning.TrainConfig)",
    "cegis": "CEGIS loop (nlyap_opt.candidates.cegis.CegisConfig)",
    "eval_box": "box of the area grid and of the simulated true ROA",
    "eval_points": "total point budget of that grid (per axis: the largest n with n^nx <= it)",
    "eval_time": "simulated horizon (s) of the true ROA on that grid: a state counts in it "
                 "once it reaches the origin within this time; a closed loop whose slowest "
                 "linear mode at the origin decays slowly is simulated longer (1.5·ln(r/tol)/σ "
                 "for decay rate σ, r the grid box's largest norm, tol = 1e-3; at most 10 "
                 "times this)",
    "dynamics": "learned-dynamics stage (nlyap_opt.learned.dynamics_config.DynamicsConfig)",
    "quadratic": "quadratic V = xᵀPx certified before the neural stage, under the initial "
                 "controller ('lyapunov': A_clᵀP + PA_cl = -I, 'round': min cond P, "
                 "'volume': largest ellipsoid in the unit ball, 'domain': largest ellipsoid "
                 "in D, 'centre': a linearisation with a centre); the larger certified "
                 "volume wins ([]: off; nlyap_opt.candidates.quadratic)",
    "sos": "an SOS V certified before the neural stage where the closed loop is polynomial "
           "(the model of f; with learned dynamics and no input, a polynomial fitted to φ, "
           "the V then certified on φ) (nlyap_opt.candidates.sos.SOSConfig: degree, 0 off, "
           "'auto' chosen from the SDP sizes; iterations); the largest certified volume wins",
    "system": "informational; must name the system being run",
    "preset": "informational; must name the preset the file is merged over",
    "comment": "free text",
    "auto_inner": "learned f: raise inner to the smallest ε whose robust margin η‖∇V‖ the "
                  "linearisation affords, 4ηλ_max(P) with A_clᵀP + PA_cl = −I (with a "
                  "centre: from the centre quadratic's sampled decrease), when the "
                  "configured one is smaller (the default method sets it; false: keep inner, "
                  "and stop with exit code 3 naming the ε that would work where inner "
                  "cannot)",
}


#: one line per key of the dataclass-derived sections (what ``nlyap config --keys`` and the
#: documentation print); a field's ``metadata["doc"]`` wins where the dataclass gives one
_FIELD_DOCS: dict[str, dict[str, str]] = {
    "train": {
        "hidden": "hidden-layer widths of N in V(x) = ‖N(x) − N(0)‖² + eps‖x‖²",
        "features": "outputs of N (the number of squares summed in V)",
        "activation": "activation of N's hidden layers: tanh; square (V a polynomial, "
                      "Fossil's square activation); linear (V a quadratic form)",
        "eps": "ε of the eps‖x‖² term of V: V > 0 away from 0 by construction",
        "lr": "Adam learning rate of V and κ",
        "steps": "training steps of the first CEGIS iteration (unless cegis.first_steps)",
        "batch": "training states per step (plus a quarter batch of counterexamples and "
                 "of boundary states)",
        "decay": "τ: the decrease hinge asks for dV/dt ≤ −β − τ·V",
        "level_slack": "s: the decrease is trained on V ≤ 1 + s and containment asks "
                       "V ≥ 1 + s on the boundary of the domain",
        "w_decrease": "weight of the decrease hinge (condition (a))",
        "w_inside": "weight of relu(V − 1) on converging training states (pulls the level "
                    "set outwards)",
        "w_outside": "weight of relu(1 + s − V) on the domain's boundary (containment (b))",
        "w_grad": "weight of mean ‖∇V‖ (keeps M and the margin β = M·η small; 0: off)",
        "train_controller": "train the gain K of κ(x) = C·tanh(Kx + b) with V (false: keep "
                            "the LQR gain)",
        "w_anchor": "weight of ‖G − G_lqr‖², keeping the trained gain near its LQR start",
        "w_inward": "weight of mean relu(n·g/‖g‖) on ∂D (n the outward normal): the trained "
                    "κ turns the closed loop inward on the domain's boundary where it can",
        "w_fit": "weight of fitting V to the simulated trajectory cost target (0: off)",
        "fit_quantile": "target level 1 = this quantile of the converging states' "
                        "trajectory cost",
        "fit_cap": "target of states that do not converge (and cap of the others)",
        "fit_transform": "g of the target g(W)/g(W_c): log (tames the rise near the ROA "
                         "boundary) or linear",
        "w_pde": "weight of the relative residual of the target's decrease law (0: off)",
        "fit_domain": "raise the fit target to (1 + level_slack)·g(x)^8 where larger (g the "
                      "domain's gauge, 1 on its boundary): the target's level sets stay "
                      "inside D where the ROA leaves it",
        "w_local": "weight of the first-order decrease at the origin, "
                   "relu(λ_max(AᵀH + HA + 2τH))/tr H (0: off)",
        "relative_decrease": "divide the decrease hinge by ‖x‖² (states next to the inner "
                             "ball weigh as much as the rest)",
        "lr_schedule": "constant, or cosine: lr anneals to lr/100 over each training call",
        "init": "where V starts: random (seeded), quadratic (the run's best certified "
                "quadratic; needs 'quadratic') or sos (the certified SOS V; needs 'sos')",
        "seed": "seed of V's initialisation and of the training minibatches",
        "threads": "torch threads while training (fixed, so results do not depend on "
                   "the machine)",
    },
    "cegis": {
        "iterations": "most CEGIS iterations (train, candidate level, verify)",
        "samples": "training states drawn in the domain",
        "sphere_samples": "training states drawn on the domain's boundary (containment)",
        "max_counterexamples": "most counterexamples (with neighbours) kept for training; "
                               "the newest win",
        "neighbours": "jittered copies added around each counterexample",
        "first_steps": "training steps of the first iteration (null: train.steps)",
        "steps": "training steps of each later iteration",
        "extend": "at most this many more iterations, verify_every at a time, while the "
                  "verifier call of the last one certified an area more than plateau above "
                  "the best before it (the budget ended on a growing certificate)",
        "later_lr": "the learning rate of each later iteration, as a fraction of train.lr "
                    "(fine-tuning the trained V and κ; 1: each round starts at train.lr)",
        "verify_every": "run the verifier every k-th iteration and the last; in between "
                        "the sampled violations are the counterexamples",
        "target_fraction": "stop once the certified level reaches this fraction of the "
                           "candidate level",
        "min_iterations": "... but not before this many iterations (the best area is kept)",
        "plateau": "a level limited by sampled decrease violations (or by ∂D, with "
                   "boundary_feedback) stops CEGIS only once the certified area is within "
                   "this fraction of the best earlier one (neither grew by more nor is "
                   "further behind)",
        "boundary_feedback": "a level limited by containment on ∂D: this many states of ∂D "
                             "with the smallest V (and the level-limiting point) join the "
                             "containment training and CEGIS goes on (0: it stops there)",
        "best_iterate": "verify the iterate with the largest candidate set since the last "
                        "verification; after it, train on from the best certified iterate "
                        "when the current one's candidate set is below 0.9 of its area",
        "area_points": "total point budget of the grid on which certified areas are "
                       "compared",
        "verify_options": "options of the interval verifier (the cegis.verify_options.* "
                          "keys)",
        "seed": "seed of the training states, counterexample jitter and level search",
        "inner_samples": "extra training states in ε ≤ ‖x‖ ≤ 3ε (0: none)",
        "boundary_samples": "extra training states near the model's ROA boundary, half "
                            "where the target is high, half on segments between converging "
                            "and non-converging neighbours (with train.w_fit; 0: none)",
        "sim_dt": "RK4 step of the training simulations",
        "sim_points": "learned φ: total nodes of a table of φ for the training simulations "
                      "(0: evaluate the network)",
        "sim_time": "simulated horizon of the training states (convergence, cost); "
                    "longer for a model loop whose slowest linear mode decays slowly "
                    "(1.5·ln(r/sim_tol)/σ, r the domain's largest norm; at most 10 times this)",
        "sim_tol": "a training state converges once ‖x‖ < sim_tol within sim_time",
        "sim_in_domain": "a training state whose simulated trajectory leaves the domain "
                         "counts as not converging (a certified set lies in D and is "
                         "invariant)",
        "margin_mode": "learned f: pointwise verifies ∇V·φ + η‖∇_L V‖ < 0; global the "
                       "paper's ∇V·φ < −β, β = M·η",
        "norm_smoothing": "pointwise mode: s = norm_smoothing·M in sqrt(‖∇_L V‖² + s²) "
                          "(costs at most this fraction of β)",
        "initial_samples": "training states drawn in initial_set, pulled into V ≤ level",
        "gain_scan": "a trained controller starts from the LQR weighting (Q = I, or one "
                     "state weighed 3, 10 or 30 times the others) that keeps the most "
                     "sampled states of D in D on their way to the origin under the model, "
                     "if it beats the start by more than 5 points (off where lqr.Q or lqr.R "
                     "is given)",
        "fit_fallback": "a model closed loop stiffer than 50 at the origin (fastest mode's "
                        "speed over the slowest mode's decay rate) trains V with the "
                        "Lyapunov-risk terms (w_fit = w_pde = 0, decay 0.1, w_inside 1, "
                        "level_slack 0.1, w_outside 1) instead of the fit to trajectory "
                        "costs; false keeps the fit",
    },
    "dynamics": {
        "system": "catalogue name the settings were made for (informational)",
        "preset": "default or fast: the per-system values the other keys override",
        "comment": "free text, kept in the saved network's metadata",
        "model": "full (φ(x, u) on a grid over X × U) or control_affine (φ0(x) on a grid "
                 "over X, f = f0(x) + B u with the known B)",
        "hidden": "hidden tanh neurons of φ: a total, or one width per learned component",
        "grid_counts": "nodes per axis of the sampling grid (or grid_spacing)",
        "grid_spacing": "largest spacing per axis: the coarsest grid within it (or "
                        "grid_counts)",
        "learned_components": "state derivatives to learn (null: those not known exactly)",
        "inputs": "all: each learned block of φ reads every grid variable; model: only "
                  "those that component of f depends on",
        "state_box": "sampling box of the states, rows [lo, hi] (null: the system's X); "
                     "must hold the verification domain",
        "input_box": "sampling box of the inputs (null: the system's U)",
        "train_points": "random distinct grid nodes φ is trained on",
        "boundary_points": "random nodes on the box faces added to training",
        "steps": "Adam steps per learned component",
        "batch_size": "Adam minibatch size",
        "lr": "Adam learning rate (cosine-annealed to lr_final)",
        "lr_final": "Adam learning rate at the end of the schedule",
        "train_dtype": "float32 or float64 for the Adam stage (LM runs in float64)",
        "lm_iterations": "Levenberg–Marquardt iterations (mean squared error) after Adam",
        "minimax_rounds": "Lawson-reweighted LM rounds lowering the maximum error",
        "minimax_iterations": "LM iterations per minimax round",
        "lm_ridge": "ridge weight on the hidden-layer weights in LM (per sample, in "
                    "normalised units: keeps hidden slopes moderate)",
        "probe_points": "evaluations of a black-box callable between grid nodes before "
                        "training, refuting declared K_f, H or depends_on that they "
                        "contradict (0: off)",
        "prune": "neurons whose output weight is at most this in absolute value are "
                 "removed before α is measured",
        "seed": "seed of the training-node draw and of φ's initialisation",
        "threads": "torch threads while training (fixed, so results do not depend on "
                   "the machine)",
        "bound_model": "best, or one η bound model (nlyap_opt.learned.bounds.BOUND_OPTIONS)",
        "bound_options": "η bound models computed (null: all)",
        "interval_boxes": "about this many sub-boxes for the interval bounds (K_f, K_φ, "
                          "L_i, D)",
        "interval_counts": "sub-boxes per axis instead of interval_boxes",
        "check_points": "random off-grid points where ‖f − φ‖ is evaluated as a test of η",
        "eval_batch": "grid nodes per batch when α is measured",
        "progress": "show progress bars",
        "eta_target": "η gate: above it, up to eta_rounds refinement rounds, then the run "
                      "stops before CEGIS with the cause (exit 2); null: no gate",
        "eta_rounds": "most refinement rounds when η exceeds eta_target",
        "refine_points": "grid nodes of largest error added to training per refinement "
                         "round",
    },
    "cegis.verify_options": {
        "resolution": "boxes narrower than this are left unknown (null: 10⁻⁴ of the "
                      "widest side of the region)",
        "max_boxes": "budget of interval boxes per check; beyond it the verdict is unknown",
        "batch": "boxes evaluated per vectorised pass",
        "mean_value": "mean-value form F(c) + J(X)(X − c): true on every box; null on the "
                      "boxes the affine bounds leave undecided (on every box without them)",
        "affine": "intersect the interval enclosures with affine-form ranges",
        "backward": "with affine: also backward linear bound propagation (CROWN style); "
                    "fewer boxes on deep networks, about twice the cost per box",
        "slope_steps": "with backward: optimise the relaxations' slopes per box by this many "
                       "gradient steps on the boxes the fixed slopes leave undecided "
                       "(α-CROWN style; 0: fixed slopes)",
        "presearch": "sampled points (with gradient ascent) searched for a counterexample "
                     "before bisection (0: none)",
        "presearch_boundary": "where those find none, points moved onto the region's "
                              "boundary tried too (0: none)",
        "stop_at_first": "stop at the first confirmed counterexample",
        "keep_leaves": "keep the decided boxes in the result (diagnostics)",
        "seed": "seed of the presearch samples",
        "initial_boxes": "about this many sub-boxes in the starting grid",
        "n_tasks": "sub-box tasks of a distributed check (null: 8)",
        "second_order": "also the second-order centred form on undecided boxes (pays off "
                        "from 3–4 states on)",
        "precondition": "verify in the coordinates z = |H|^½ x of the decrease's Hessian at "
                        "the centre, where it is definite (stiff loops in 4 and more states)",
    },
}

def _kind_of(tp) -> tuple[str, bool]:
    """``(kind, optional)`` of a type hint."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        rest = [a for a in args if a is not type(None)]
        if len(rest) == 1 and len(rest) < len(args):
            return _kind_of(rest[0])[0], True
        return "any", type(None) in args
    if tp is bool:
        return "bool", False
    if tp is int:
        return "int", False
    if tp is float:
        return "float", False
    if tp is str:
        return "str", False
    if tp is dict or origin is dict:
        return "dict", False
    if origin is list and args == (int,):
        return "int_list", False
    return "any", False


def _keys_of(cls, section: str) -> Mapping[str, Key]:
    """The :class:`Key` of every field of the dataclass ``cls`` (introspection), read-only."""
    hints = typing.get_type_hints(cls)
    out = {}
    for f in dataclasses.fields(cls):
        if f.name in _EXCLUDED.get(section, ()):
            continue
        kind, optional = _kind_of(hints[f.name])
        if f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:
            default = f.default_factory()
        else:
            default = None
        rule = {"doc": _FIELD_DOCS.get(section, {}).get(f.name, ""),
                **_RULES.get(section, {}).get(f.name, {}),
                **{k: v for k, v in f.metadata.items()
                   if k in ("lo", "lo_open", "hi", "hi_open", "choices", "doc")}}
        out[f.name] = Key(f"{section}.{f.name}", kind, default, optional, **rule)
    return MappingProxyType(out)


def _dynamics_keys() -> Mapping[str, Key]:
    keys = dict(_keys_of(DynamicsConfig, "dynamics"))
    keys["preset"] = dataclasses.replace(keys["preset"], choices=("default", "fast"))
    return MappingProxyType(keys)


def _verify_option_keys() -> Mapping[str, Key]:
    """Keyword options of the interval verifier that a JSON file can hold (read-only)."""
    out = {}
    for name, (hint, default, lo, lo_open) in file_options().items():
        kind, optional = _kind_of(hint)
        rule = {} if lo is None else {"lo": lo, "lo_open": lo_open}
        rule["doc"] = _FIELD_DOCS["cegis.verify_options"].get(name, "")
        out[name] = Key(f"cegis.verify_options.{name}", kind, default, optional, **rule)
    return MappingProxyType(out)


def _quadratic_names() -> tuple:
    return tuple(QUADRATIC_CANDIDATES)


@functools.cache
def schema() -> Mapping[str, Mapping[str, Key]]:
    """Every key of the run configuration: ``{section: {key: Key}}``, ``""`` the top level.

    Read-only (it is computed once and shared): a caller cannot change the keys every
    later check reads.

    The ``train`` and ``cegis`` sections are derived from
    :class:`~nlyap_opt.candidates.learning.TrainConfig` and
    :class:`~nlyap_opt.candidates.cegis.CegisConfig`, the ``dynamics`` section from
    :class:`~nlyap_opt.learned.dynamics_config.DynamicsConfig`.
    """
    from ..candidates.cegis import CegisConfig  # lazy: torch, heavy (CEGIS trains with it)
    from ..candidates.learning import TrainConfig  # lazy: torch, heavy (the learner trains with it)

    d = _TOP_DOCS
    top = {
        "outer": Key("outer", "float", None, True, **_POS, doc=d["outer"]),
        "inner": Key("inner", "float", None, False, **_POS, doc=d["inner"]),
        "domain": Key("domain", "set", None, True, doc=d["domain"]),
        "initial_set": Key("initial_set", "set", None, True, doc=d["initial_set"]),
        "controller_scale": Key("controller_scale", "scale", None, True, **_POS,
                                doc=d["controller_scale"]),
        "lqr": Key("lqr", "section", {}, doc=d["lqr"]),
        "train": Key("train", "section", {}, doc=d["train"]),
        "cegis": Key("cegis", "section", {}, doc=d["cegis"]),
        "eval_box": Key("eval_box", "box", None, doc=d["eval_box"]),
        "eval_points": Key("eval_points", "int", 40000, lo=4, doc=d["eval_points"]),
        "eval_time": Key("eval_time", "float", 60.0, **_POS, doc=d["eval_time"]),
        "dynamics": Key("dynamics", "section", {}, doc=d["dynamics"]),
        "quadratic": Key("quadratic", "str_list", [], choices=_quadratic_names(),
                         doc=d["quadratic"]),
        "sos": Key("sos", "section", {}, doc=d["sos"]),
        "system": Key("system", "str", doc=d["system"]),
        "preset": Key("preset", "str", optional=True, doc=d["preset"]),
        "comment": Key("comment", "str", doc=d["comment"]),
        "auto_inner": Key("auto_inner", "bool", False, doc=d["auto_inner"]),
    }
    return MappingProxyType({
        "": MappingProxyType(top),
        "lqr": MappingProxyType({
            "Q": Key("lqr.Q", "matrix", None, True, doc="state weight (default I)"),
            "R": Key("lqr.R", "matrix", None, True, doc="input weight (default I)")}),
        "train": _keys_of(TrainConfig, "train"),
        "cegis": _keys_of(CegisConfig, "cegis"),
        "dynamics": _dynamics_keys(),
        "sos": _keys_of(SOSConfig, "sos"),
        "cegis.verify_options": _verify_option_keys(),
    })


# ============================================================================ validation
def _is_int(v) -> bool:
    return isinstance(v, Integral) and not isinstance(v, bool)


def _is_real(v) -> bool:
    return isinstance(v, Real) and not isinstance(v, bool)


def _show(v) -> str:
    """A value as JSON would write it (``true``, ``NaN``), else its repr."""
    try:
        return json.dumps(v)
    except (TypeError, ValueError):
        return repr(v)


def _in_range(key: Key, v) -> bool:
    if key.lo is not None and (v < key.lo or (key.lo_open and v == key.lo)):
        return False
    if key.hi is not None and (v > key.hi or (key.hi_open and v == key.hi)):
        return False
    return True


def _check_value(key: Key, v, where: str) -> None:
    """Refuse a value ``v`` that ``key`` does not accept (one line naming the key, what it
    accepts and what came)."""
    if v is None:
        if not key.optional:
            _bad(key, v, where)
        return
    check = _KIND_CHECKS.get(key.kind)
    if check is not None and not check(key, v, where):
        _bad(key, v, where)


def _bad(key: Key, v, where: str):
    raise ConfigError(f"{where}: {key.name} must be {key.describe()}, got {_show(v)}; "
                      "correct that value")


def _suggest(key: Key, v: str, where: str, what: str):
    close = difflib.get_close_matches(v, key.choices, n=1)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    raise ConfigError(f"{where}: {key.name} must be {key.describe()}, got {v!r}{what}{hint}")


def _ok_str(key: Key, v, where: str) -> bool:
    if isinstance(v, str) and key.choices and v not in key.choices:
        _suggest(key, v, where, "")
    return isinstance(v, str)


#: the largest integer a setting takes (float64 represents every integer up to it; a
#: count beyond it is an edit or a typo, not a budget)
MAX_INT_SETTING = 2**53


def _ok_int(key: Key, v, where: str) -> bool:
    if _is_int(v) and abs(v) > MAX_INT_SETTING:
        raise ConfigError(f"{where}: {key.name} = {_show(v)} is beyond {MAX_INT_SETTING} "
                          "(2^53); give a smaller integer")
    return _is_int(v) and _in_range(key, v) and (not key.choices or v in key.choices)


def _ok_float(key: Key, v, where: str) -> bool:
    if _is_int(v) and abs(v) > MAX_INT_SETTING:   # math.isfinite overflows on such an int
        return False
    return _is_real(v) and math.isfinite(v) and _in_range(key, v)


def _ok_scale(key: Key, v, where: str) -> bool:
    vals = v if isinstance(v, (list, tuple)) else [v]
    return bool(vals) and all(_ok_float(key, a, where) for a in vals)


def _ok_str_list(key: Key, v, where: str) -> bool:
    if not isinstance(v, (list, tuple)) or not all(isinstance(h, str) for h in v):
        return False
    for h in v:
        if h not in key.choices:
            _suggest(key, h, where, " in it")
    if len(set(v)) != len(v):
        raise ConfigError(f"{where}: {key.name} lists a name twice ({_show(v)}); list "
                          "each candidate once")
    return True


def _ok_int_list(key: Key, v, where: str) -> bool:
    return isinstance(v, (list, tuple)) and bool(v) and \
        all(_is_int(h) and _in_range(key, h) for h in v)


def _ok_box(key: Key, v, where: str) -> bool:
    return isinstance(v, (list, tuple)) and bool(v) and all(
        isinstance(r, (list, tuple)) and len(r) == 2 and all(_is_real(a) for a in r)
        and math.isfinite(r[0]) and math.isfinite(r[1]) and r[0] < r[1] for r in v)


def _ok_matrix(key: Key, v, where: str) -> bool:
    _matrix(key, v, where)
    return True


#: the check of each kind of :class:`Key` (``"any"``: every value)
_KIND_CHECKS = {
    "bool": lambda key, v, where: isinstance(v, bool), "str": _ok_str, "int": _ok_int,
    "float": _ok_float, "scale": _ok_scale, "str_list": _ok_str_list,
    "int_list": _ok_int_list, "box": _ok_box, "matrix": _ok_matrix,
    **dict.fromkeys(("dict", "section", "set"), lambda key, v, where: isinstance(v, dict)),
    # a key of several types (sos.degree: "auto" or a number) lists what it accepts
    "any": lambda key, v, where: not key.choices or (
        (isinstance(v, str) or _is_int(v)) and v in key.choices),
}


def _matrix(key: Key, v, where: str):
    """A finite scalar or a rectangular 2-D list as an ndarray (else ConfigError)."""
    if isinstance(v, np.ndarray) and v.ndim <= 2 and v.size and \
            np.issubdtype(v.dtype, np.number):
        M = np.atleast_2d(v.astype(float))
    elif _is_real(v):
        M = np.array([[float(v)]])
    elif isinstance(v, (list, tuple)) and v and all(isinstance(r, (list, tuple)) for r in v) \
            and len({len(r) for r in v}) == 1 and all(_is_real(a) for r in v for a in r):
        M = np.array(v, dtype=float)
    else:
        raise ConfigError(f"{where}: {key.name} must be a number or a square matrix "
                          f"(a list of equal-length rows of numbers), got {v!r}")
    if not np.all(np.isfinite(M)):
        raise ConfigError(f"{where}: {key.name} must be finite (no NaN or inf), got {v!r}")
    return M


def _unknown(section: str, name, known: dict, where: str, sch: dict) -> ConfigError:
    dotted = f"{section}.{name}" if section else str(name)
    if not isinstance(name, str):
        return ConfigError(f"{where}: config keys must be strings, got {name!r}")
    if name in _REMOVED:
        return ConfigError(f"{where}: unknown key {dotted!r}; {_REMOVED[name]}")
    close = difflib.get_close_matches(name, list(known), n=1, cutoff=0.6)
    if close:
        full = f"{section}.{close[0]}" if section else close[0]
        return ConfigError(f"{where}: unknown key {dotted!r}; did you mean {full!r}?")
    if not section:  # a section key at the top level?
        homes = [s for s in ("train", "cegis", "dynamics", "lqr", "sos") if name in sch[s]]
        if homes:
            return ConfigError(f"{where}: unknown top-level key {name!r}; it belongs in a "
                               f"section: {' or '.join(f'{s}.{name}' for s in homes)}")
    scope = f"section {section!r}" if section else "the top level"
    return ConfigError(f"{where}: unknown key {dotted!r}; keys of {scope}: "
                       f"{', '.join(known)}")


def _check_keys(cfg: dict, where: str) -> None:
    """Refuse unknown keys anywhere in ``cfg`` (a full config or an override)."""
    sch = schema()
    if not isinstance(cfg, dict):
        raise ConfigError(f"{where}: a run config must be a JSON object, "
                          f"got {type(cfg).__name__}")
    for name, v in cfg.items():
        if name not in sch[""]:
            raise _unknown("", name, sch[""], where, sch)
        if sch[""][name].kind == "section" and (name != "dynamics" or sch["dynamics"]):
            if not isinstance(v, dict):
                raise ConfigError(f"{where}: {name} must be a JSON object {{...}}, got {v!r}")
            for sub, sv in v.items():
                if sub not in sch[name]:
                    raise _unknown(name, sub, sch[name], where, sch)
                if name == "cegis" and sub == "verify_options" and isinstance(sv, dict):
                    for opt in sv:
                        if opt not in sch["cegis.verify_options"]:
                            raise _unknown("cegis.verify_options", opt,
                                           sch["cegis.verify_options"], where, sch)


def validate_config(cfg: Mapping, system: str, *, where: str = "run config") -> Mapping:
    """Check a complete run configuration of ``system``; return it unchanged.

    Parameters
    ----------
    cfg : dict or RunConfig
        Every key of the top level (sections may be partial: the dataclass defaults fill
        them).
    system : str
        A registered system name (its dimensions check ``eval_box``, ``lqr`` and
        ``controller_scale``).
    where : str
        Prefix of the error messages (the file the config came from).

    Returns
    -------
    dict or RunConfig
        ``cfg``.

    Raises
    ------
    ConfigError
        The first problem found, naming the key, what it accepts and what came.
    """
    data = cfg.to_json() if isinstance(cfg, Section) else cfg
    _check_keys(data, where)
    rc = RunConfig._build("", data)
    _check_values(rc, where)
    s = systems.get(system)
    _check_region(rc, s, where)
    _check_start(rc, s, where)
    _check_cegis(rc, where)
    _check_sizes(rc, s.nx, where)
    _check_controller(rc, s, where)
    _check_dynamics(rc.dynamics.to_json(), system, where)
    return cfg




def _check_sizes(rc: RunConfig, nx: int, where: str) -> None:
    """Settings whose arrays would exceed :data:`MAX_ARRAY_NUMBERS` (states × dimension,
    V's weights, states × hidden width)."""
    widths = [nx, *rc.train.hidden, rc.train.features]
    width = max(widths)
    sizes = [("train.hidden", rc.train.hidden,
              sum((a + 1) * b for a, b in zip(widths, widths[1:])), "weights of V's network")]
    for name, points in (("eval_points", rc.eval_points),
                         ("cegis.area_points", rc.cegis.area_points),
                         ("cegis.sim_points", rc.cegis.sim_points)):
        sizes.append((name, points, points * nx, "state coordinates of its grid"))
    for name, points in (("cegis.samples", rc.cegis.samples),
                         ("cegis.sphere_samples", rc.cegis.sphere_samples),
                         ("cegis.boundary_samples", rc.cegis.boundary_samples),
                         ("cegis.inner_samples", rc.cegis.inner_samples),
                         ("train.batch", rc.train.batch)):
        sizes.append((name, points, points * width, "training activations (states × "
                      "widest layer; or narrow train.hidden)"))
    for name, value, numbers, what in sizes:
        if numbers > MAX_ARRAY_NUMBERS:
            raise ConfigError(f"{where}: {name} = {_show(value)} makes {numbers:.3g} {what}, "
                              f"beyond the {MAX_ARRAY_NUMBERS:.0e} numbers one array may hold "
                              "(0.8 GB); lower it")


def _check_values(rc: RunConfig, where: str) -> None:
    """The keys every run needs, and each given value against its :class:`Key`."""
    sch = schema()
    for name in ("inner", "eval_box", "eval_points"):
        if name not in rc:
            raise ConfigError(f"{where}: missing key {name!r} ({_TOP_DOCS[name]}); add it")
    if rc.outer is None and rc.domain is None:
        raise ConfigError(f"{where}: missing key 'outer' (the radius of the verification "
                          "ball) or 'domain' (a box, ellipsoid or ball); add one of them")
    if rc.outer is not None and rc.domain is not None:
        raise ConfigError(f"{where}: both 'outer' ({rc.outer}) and 'domain' are given; "
                          "the domain replaces the ball ‖x‖ ≤ outer: set outer to null or drop "
                          "the domain")
    for name, v in rc.items():   # JSON values: a section as its object
        key = sch[""][name]
        _check_value(key, v, where)
        if key.kind == "section" and name in ("lqr", "train", "cegis", "sos"):
            for sub, sv in v.items():
                _check_value(sch[name][sub], sv, where)
    for opt, ov in rc.cegis.verify_options.items():
        _check_value(sch["cegis.verify_options"][opt], ov, where)
    conflict = option_conflict(rc.cegis.verify_options)
    if conflict:
        raise ConfigError(f"{where}: cegis.verify_options: {conflict}")


def _check_region(rc: RunConfig, s, where: str) -> None:
    """``inner`` against ``outer`` or the domain; the initial set inside the domain."""
    inner, outer = rc.inner, rc.outer
    limit = systems.base.BOX_LIMIT
    if outer is not None and outer > limit:
        raise ConfigError(f"{where}: outer = {outer:g} is beyond {limit:g} (squares of the "
                          "states must stay finite); rescale the system's states, or lower "
                          "outer")
    if outer is not None and not inner < outer:
        raise ConfigError(f"{where}: need 0 < inner < outer, got inner = {inner:g}, "
                          f"outer = {outer:g}; make inner smaller than outer")
    D, XI = domain_of(rc, s.nx, where)
    if outer is None and not inner < D.inradius():
        raise ConfigError(f"{where}: the inner ball ‖x‖ < {inner:g} leaves the domain "
                          f"{D.describe()} (distance from 0 to its boundary "
                          f"{D.inradius():.6g}); make inner smaller")
    if XI is not None and not np.all((XI.bounding_box()[:, 0] >= D.bounding_box()[:, 0])
                                     & (XI.bounding_box()[:, 1] <= D.bounding_box()[:, 1])):
        raise ConfigError(f"{where}: the initial set {XI.describe()} leaves the bounding box "
                          f"of the domain {D.describe()}; shrink initial_set or enlarge the "
                          "domain")


def _check_start(rc: RunConfig, s, where: str) -> None:
    """``train.init``: the certificate V starts at must be configured, and fit V's form."""
    init = rc.train.init
    if init == "quadratic" and not rc.quadratic:
        raise ConfigError(f"{where}: train.init 'quadratic' starts V at the best certified "
                          "quadratic, but no quadratic candidates are listed; set e.g. "
                          "quadratic: [\"lyapunov\", \"round\"] or init 'random'")
    degree = rc.sos.degree
    if init == "sos":   # the start needs the true f (checked by the run): resolve for it
        choice = choose_degree(s, degree, known=True)
        if not choice.degree:
            raise ConfigError(f"{where}: train.init 'sos' starts V at the certified SOS V, but "
                              f"the SOS stage is off ({choice.describe()}); set "
                              "sos: {\"degree\": 4} (or 2) or init 'random'")
        degree = choice.degree
    if init != "random":
        from ..candidates.learning import check_start_architecture  # lazy: torch, heavy (the
                                                                    # learner)

        try:
            check_start_architecture(init, s.nx, rc.train.activation, rc.train.hidden,
                                     rc.train.features, degree)
        except ConfigError as err:
            raise ConfigError(f"{where}: {err}") from None


def _check_cegis(rc: RunConfig, where: str) -> None:
    cg = rc.cegis
    if cg.min_iterations > cg.iterations:
        raise ConfigError(f"{where}: cegis.min_iterations ({cg.min_iterations}) exceeds "
                          f"cegis.iterations ({cg.iterations}); lower it or raise iterations")
    if 0 < cg.sim_points < 4:
        raise ConfigError(f"{where}: cegis.sim_points must be 0 (no table) or >= 4, got "
                          f"{cg.sim_points}")


def _check_controller(rc: RunConfig, s, where: str) -> None:
    """``eval_box`` rows; ``controller_scale`` and ``lqr`` for the system's inputs; an LQR
    start must exist."""
    if len(rc.eval_box) != s.nx:
        raise ConfigError(f"{where}: eval_box has {len(rc.eval_box)} rows; {s.name} has "
                          f"{s.nx} states, give one [lo, hi] row per state")
    scale = rc.controller_scale
    if s.nu and scale is None:
        raise ConfigError(f"{where}: controller_scale is null but {s.name} has {s.nu} "
                          "input(s); give the actuator limit C > 0 of u = C·tanh(Kx + b)")
    if isinstance(scale, (list, tuple)) and len(scale) != s.nu:
        raise ConfigError(f"{where}: controller_scale has {len(scale)} entries; {s.name} has "
                          f"{s.nu} input(s): give one number or one per input")
    if not s.nu and scale is not None:
        raise ConfigError(f"{where}: {s.name} has no inputs; set controller_scale to null")
    Q, R = check_lqr_weights(s, rc.lqr.Q, rc.lqr.R, where=where)
    if s.nu and getattr(s, "has_model", True):
        # the controller stage comes after the dynamics stage: fail now, not then (without a
        # model the LQR start linearises the learned φ, known only after the dynamics stage)
        try:
            with warnings.catch_warnings():  # the failure is reported, not its warnings
                warnings.simplefilter("ignore", RuntimeWarning)
                lqr(s, Q, R)
        except ValueError as err:  # NotStabilizableError, LinAlgError of the Riccati solver
            k = systems.spec.centre_dimension(s)
            if k:
                raise ConfigError(
                    f"{where}: {s.name} has {k} eigenvalue(s) on the imaginary axis that no "
                    "input moves (a centre): the LQR start of a run with inputs cannot "
                    "stabilise it; drop the inputs if the other states are stable without "
                    "them (an autonomous system with a centre is supported), or let an input "
                    "reach the centre") from None
            unstable = systems.spec.unstable_origin(s)   # no weights can help: say so
            if unstable:
                raise ConfigError(f"{where}: {unstable}") from None
            raise ConfigError(f"{where}: no LQR start for {s.name} with these lqr weights "
                              f"({' '.join(str(err).split())}); use moderate weights") from None


def check_lqr_weights(system, Q=None, R=None, *, where: str = "lqr",
                      names: tuple[str, str] = ("lqr.Q", "lqr.R")):
    """LQR weights of ``system`` as arrays, checked (``None`` stays ``None``).

    Parameters
    ----------
    system : systems.System
    Q, R : float or (n, n) array_like or None
        A scalar means that multiple of the identity. ``Q`` must be symmetric positive
        semidefinite and ``nx × nx``; ``R`` symmetric positive definite and ``nu × nu``.
    where : str
        Prefix of the error messages.
    names : (str, str)
        How the messages call ``Q`` and ``R`` (``"--Q"`` on the command line).

    Returns
    -------
    (Q, R) : ndarray or None

    Raises
    ------
    ConfigError
        Not a finite number or rectangular matrix, wrong size, not symmetric, not
        positive (semi)definite, or ``R`` for a system without inputs.
    """
    out = []
    for value, name, n, strict in ((Q, names[0], system.nx, False),
                                   (R, names[1], system.nu, True)):
        if value is None:
            out.append(None)
            continue
        if n == 0:
            raise ConfigError(f"{where}: {system.name} has no inputs; drop {name}")
        M = _matrix(Key(name, "matrix"), value, where)
        if M.shape == (1, 1):
            M = M[0, 0] * np.eye(n)
        if M.shape != (n, n):
            raise ConfigError(f"{where}: {name} must be a number or {n}x{n} for "
                              f"{system.name}, got {M.shape[0]}x{M.shape[1]}")
        if not np.allclose(M, M.T):
            raise ConfigError(f"{where}: {name} must be symmetric, got {M.tolist()}")
        ev = float(np.min(np.linalg.eigvalsh(0.5 * M + 0.5 * M.T)))
        if ev <= 0 if strict else ev < 0:
            what = "positive definite" if strict else "positive semidefinite"
            raise ConfigError(f"{where}: {name} must be {what} (smallest eigenvalue "
                              f"{ev:.3g}); use positive weights")
        out.append(M)
    return tuple(out)


def check_dynamics_box(cfg: Mapping) -> None:
    """Refuse, before training, a verification ball ``‖x‖ ≤ outer`` that leaves the box on
    which the learned dynamics (and so ``‖f − φ‖ ≤ η``) will be established.

    Parameters
    ----------
    cfg : RunConfig or dict
        A run configuration (its ``system`` names a registered system).

    Raises
    ------
    ConfigError
        Naming the box and the fixes (a larger ``dynamics.state_box`` or a smaller ``outer``).
    """
    rc = RunConfig.from_json(cfg)
    s = systems.get(rc.system)
    box = rc.dynamics.state_box
    box = np.asarray(s.state_box if box is None else box, dtype=float)
    D = domain_of(rc, s.nx)[0]
    bb = D.bounding_box()
    if np.any(box[:, 0] > bb[:, 0]) or np.any(box[:, 1] < bb[:, 1]):
        what = f"ball r = {rc.outer:g}" if rc.outer is not None else \
            f"domain {D.describe()}"
        raise ConfigError(
            f"the verification {what} leaves the box {box.tolist()} on which "
            "‖f − φ‖ ≤ η will be established; set dynamics.state_box to cover "
            f"{bb.tolist()} or shrink the {'outer radius' if rc.outer else 'domain'}"
        )


def domain_of(cfg: Mapping, nx: int, where: str = "run config"):
    """``(D, X_I)`` of a run configuration: the :class:`~nlyap_opt.kernel.domain.Region` of its
    ``domain`` (else the ball of radius ``outer``) and of its ``initial_set`` (or ``None``).

    Parameters
    ----------
    cfg : RunConfig or dict
        A run configuration, or a view of it declaring ``outer``, ``domain`` and
        ``initial_set``.
    nx : int
        The system's state dimension.
    where : str
        Prefix of the error messages.

    Raises
    ------
    ConfigError
        A malformed set, one of the wrong dimension, or a domain without the origin inside.
    """
    rc = cfg if isinstance(cfg, RunConfig) else RunConfig.from_json(cfg, where=where)
    try:
        D = Ball(float(rc.outer), nx) if rc.domain is None else \
            parse_set(rc.domain, nx, "domain")
        XI = None if rc.initial_set is None else \
            parse_set(rc.initial_set, nx, "initial_set", domain=False)
    except ConfigError as err:
        raise ConfigError(f"{where}: {err}") from None
    return D, XI


def _check_dynamics(dyn, system: str, where: str) -> None:
    if not isinstance(dyn, dict):
        raise ConfigError(f"{where}: dynamics must be a JSON object {{...}}, got {dyn!r}")
    try:
        dynamics_config(system, dyn)
    except (ConfigError, UnknownNameError, ValueError, TypeError) as err:
        raise ConfigError(f"{where}: {err}") from None


# ============================================================================ the config object
class UndeclaredKeyError(RuntimeError):
    """A stage read a configuration key it does not declare: a bug of the program, not of
    the input (its stage key would not cover that key, and a changed value would leave the
    stage stale), so it is no :class:`~nlyap_opt.kernel.errors.NlyapError` and ``nlyap`` exits
    with code 4."""


def _section_paths() -> frozenset[str]:
    """The dotted paths of every section of the schema (``"train"``,
    ``"cegis.verify_options"``; ``""`` the top level)."""
    return frozenset(schema())


@dataclass(frozen=True, eq=False)
class Section(Mapping):
    """One section of a :class:`RunConfig`: the keys given, their defaults from the schema.

    Two faces of the same content:

    - attributes (``cfg.train.steps``): the value given, else the default of
      :func:`schema` (the one place defaults are defined); a sub-section is a
      :class:`Section`; an unknown name raises ``AttributeError`` with a "did you mean";
    - a read-only mapping over the keys *given* (``cfg["train"]["steps"]``,
      ``TrainConfig(**cfg["train"])``), a sub-section read as its JSON object: what
      :meth:`RunConfig.to_json` writes.

    Values are copied on every read (nothing a caller holds can change the config). A
    *view* (:meth:`RunConfig.view`) exposes only the keys a stage declares; reading another
    raises :class:`UndeclaredKeyError`.

    Attributes
    ----------
    _path : str
        Dotted path of the section in the schema (``""``: the top level).
    _given : tuple of (str, object)
        The keys given, in order, with their values (sub-sections as :class:`Section`).
    _only : frozenset of str or None
        The dotted keys (relative to this section) a view may read; ``None``: every key.
    """

    _path: str
    _given: tuple[tuple[str, Any], ...]
    _only: frozenset[str] | None = None

    @classmethod
    def _build(cls, path: str, obj: Mapping) -> Section:
        sections = _section_paths()
        given = []
        for k, v in obj.items():
            sub = f"{path}.{k}" if path else k
            if sub in sections and isinstance(v, Mapping):
                v = Section._build(sub, v)
            else:
                v = copy.deepcopy(v)
            given.append((k, v))
        return cls(path, tuple(given))

    def _dotted(self, name: str) -> str:
        return f"{self._path}.{name}" if self._path else name

    def _sub_only(self, name: str) -> frozenset[str] | None:
        """The keys a view may read below ``name`` (``None``: all); raises when ``name`` is
        not declared."""
        if self._only is None or name in self._only:
            return None
        below = frozenset(o[len(name) + 1:] for o in self._only if o.startswith(name + "."))
        if not below:
            raise UndeclaredKeyError(
                f"configuration key {self._dotted(name)!r} is read but not declared by this "
                f"stage (it declares {', '.join(sorted(self._only))}); add it to the stage's "
                "fields in nlyap_opt.workflow.pipeline")
        return below

    def _value(self, name: str, default):
        only = self._sub_only(name)
        for k, v in self._given:
            if k == name:
                break
        else:
            v = default
        if isinstance(v, Section):
            return v if only is None else Section(v._path, v._given, only)
        return copy.deepcopy(v)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):   # dunder probes (copy, pickle) and the private fields
            raise AttributeError(name)
        keys = schema()[self._path]
        if name not in keys and name not in dict(self._given):
            close = difflib.get_close_matches(name, list(keys), n=1)
            hint = f"; did you mean {close[0]!r}?" if close else ""
            raise AttributeError(f"no configuration key {self._dotted(name)!r}{hint}")
        key = keys.get(name)
        sub = self._dotted(name)
        default = Section(sub, ()) if sub in _section_paths() else \
            None if key is None else key.default
        return self._value(name, default)

    def __getitem__(self, name: str):
        if name not in dict(self._given):
            self._sub_only(name)   # an undeclared key fails loudly, not as "absent"
            raise KeyError(name)
        v = self._value(name, None)
        return v.to_json() if isinstance(v, Section) else v

    def __iter__(self):
        return iter([k for k, _ in self._given if self._readable(k)])

    def __len__(self) -> int:
        return sum(1 for k, _ in self._given if self._readable(k))

    def __contains__(self, name) -> bool:
        return name in dict(self._given) and self._readable(name)

    def __eq__(self, other) -> bool:
        if isinstance(other, Section):
            other = other.to_json()
        return isinstance(other, Mapping) and self.to_json() == dict(other)

    __hash__ = None   # a mapping of mutable JSON values

    def _readable(self, name: str) -> bool:
        try:
            self._sub_only(name)
        except UndeclaredKeyError:
            return False
        return True

    def __dir__(self):
        return sorted(set(super().__dir__()) | set(schema()[self._path]))

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.to_json()!r})"

    def to_json(self) -> dict:
        """The keys given (those a view may read), in order, as a JSON-ready dict."""
        return {k: v.to_json() if isinstance(v, Section) else copy.deepcopy(v)
                for k, v in self._given if self._readable(k)}


@dataclass(frozen=True, eq=False, repr=False)
class RunConfig(Section):
    """A validated run configuration: a frozen tree of :class:`Section` objects.

    Built by :func:`make_config` (which validates it for its system) or
    :meth:`from_json`; written back by :meth:`to_json` as the JSON it was built from (same
    keys, order and values: ``nlyap config`` prints it). The sections mirror the JSON:
    the problem (``outer``, ``inner``, ``domain``, ``initial_set``, ``auto_inner``), the
    controller (``controller_scale``, ``lqr``), ``dynamics``, ``train``, ``cegis`` (with
    ``cegis.verify_options``), ``sos``, ``quadratic`` and the evaluation grid
    (``eval_box``, ``eval_points``); :func:`config_reference` documents every key.

    Examples
    --------
    >>> cfg = make_config("van_der_pol", "fast")
    >>> cfg.train.steps, cfg.cegis.margin_mode, cfg["train"]["steps"]
    (300, 'pointwise', 300)
    >>> dict(cfg.view(("inner", "cegis.margin_mode")).declared())
    {'cegis.margin_mode': None, 'inner': 0.3}
    """

    @classmethod
    def from_json(cls, obj: Mapping, *, where: str = "run config") -> RunConfig:
        """A :class:`RunConfig` of a JSON object (a dict or another config), its keys and
        section types checked (:func:`validate_config` checks it for a system).

        Raises
        ------
        ConfigError
            Not a JSON object, an unknown key or a section that is not an object.
        """
        if isinstance(obj, RunConfig) and obj._only is None:
            return obj
        obj = obj.to_json() if isinstance(obj, Section) else obj
        _check_keys(obj, where)
        return cls._build("", obj)

    def view(self, fields: tuple[str, ...]) -> RunConfig:
        """The same configuration restricted to the dotted keys ``fields`` (a key names its
        whole value or section): what a stage reads, and all it may read."""
        return RunConfig(self._path, self._given, frozenset(fields))

    def declared(self) -> Mapping[str, Any]:
        """``{dotted key: value given or None}`` of a view's declared keys, read-only and
        sorted: the JSON its stage key hashes (a default is not filled in: a stated
        default and an absent key differ only in a recomputation)."""
        if self._only is None:
            raise UndeclaredKeyError("declared() needs a view: call view(fields) first")
        data = RunConfig(self._path, self._given).to_json()
        out = {}
        for dotted in sorted(self._only):
            node = data
            for part in dotted.split("."):
                node = node.get(part) if isinstance(node, dict) else None
            out[dotted] = node
        return MappingProxyType(out)
def _merge_into(out: dict, over: Mapping) -> None:
    """Merge the layer ``over`` into the configuration JSON ``out`` (in place; ``out`` is the
    caller's own copy, values of ``over`` are copied)."""
    # a region given one way replaces the other way of the layer below: a domain replaces
    # the ball's radius, a radius the domain
    if over.get("domain") is not None and "outer" not in over:
        out["outer"] = None
    if over.get("outer") is not None and "domain" not in over:
        out.pop("domain", None)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict) and \
                k not in ("domain", "initial_set"):   # a set is replaced whole
            sub = out[k]
            if k == "dynamics":  # a grid given one way replaces the preset's other way
                for a, b in (("grid_spacing", "grid_counts"), ("grid_counts", "grid_spacing")):
                    if v.get(a) is not None and b not in v:
                        sub.pop(b, None)
            _merge_into(sub, v)
        else:
            out[k] = copy.deepcopy(v)


def make_config(system: str, preset: str | None = "large", overrides: dict | None = None,
                file: str | Path | None = None) -> RunConfig:
    """A validated run configuration: ``preset`` ← JSON ``file`` ← ``overrides``.

    Parameters
    ----------
    system : str
        A registered system (:func:`systems.names`).
    preset : str or None
        ``"paper"``, ``"large"`` or ``"fast"`` (see :data:`PRESETS`); ``None`` starts from
        the dataclass defaults, for a system without a preset: ``outer``, ``inner``
        (and ``controller_scale`` for a system with inputs) must then come from ``file``
        or ``overrides``; ``eval_box`` defaults to the system's state box.
    overrides : dict, optional
        Nested like the config (``{"train": {"steps": 100}}``), merged last.
    file : str or Path, optional
        A JSON object merged over the preset.

    Returns
    -------
    RunConfig
        The merged configuration with ``system`` and ``preset`` set (typed attributes,
        read-only mapping reads; :meth:`RunConfig.to_json` gives the JSON); pass it to
        :func:`nlyap_opt.workflow.pipeline.run`.

    Raises
    ------
    UnknownNameError
        An unknown system or preset.
    ConfigError
        An unknown key, a wrong type, NaN/inf, or a value out of range (checked before
        anything runs).

    Examples
    --------
    >>> cfg = make_config("inverted_pendulum", "fast", overrides={"cegis": {"iterations": 1}})
    >>> cfg.cegis.iterations, cfg.preset, cfg["cegis"]["iterations"]
    (1, 'fast', 1)
    """
    if not isinstance(system, str):
        raise ConfigError(f"system must be a name (str), got {system!r}")
    _check_file_argument(file)
    s = systems.get(system)  # UnknownNameError listing the catalogue
    if preset is None:
        cfg = copy.deepcopy(_GENERIC)
        cfg["eval_box"] = s.state_box.tolist()
        if not s.nu:
            cfg["controller_scale"] = None
        # a new system's settings come from its boxes, then from its spec file's [run] table
        _merge_into(cfg, systems.default_run_settings(s))
        if getattr(s, "run_overrides", None):
            _check_keys(s.run_overrides, f"system {system!r} [run]")
            _merge_into(cfg, s.run_overrides)
    elif system not in PRESETS:
        raise UnknownNameError(
            f"no preset for system {system!r} (presets exist for {', '.join(PRESETS)}); "
            f"in Python call nlyap_opt.workflow.configs.make_config({system!r}, preset=None, "
            "overrides={'outer': R, 'inner': EPS, 'controller_scale': C}) and pass it to "
            "nlyap_opt.workflow.pipeline.run; on the command line omit --preset"
        )
    elif preset not in PRESETS[system]:
        close = difflib.get_close_matches(str(preset), list(PRESETS[system]), n=1)
        hint = f"; did you mean {close[0]!r}?" if close else ""
        raise UnknownNameError(
            f"unknown preset {preset!r} for {system}; available: "
            f"{', '.join(PRESETS[system])}{hint}"
        )
    else:
        cfg = copy.deepcopy(PRESETS[system][preset])
    where = _spec_where(s) if preset is None else "run config"
    for src, over in ((file, None), (None, overrides)):
        if src is not None:
            where = f"config {src}"
            over = read_json_object(src)
        if over is None:
            continue
        if not isinstance(over, dict):
            raise ConfigError(f"overrides must be a dict, got {type(over).__name__}")
        _check_keys(over, where)
        for k, want in (("system", system), ("preset", preset)):
            if over.get(k) is not None and want is not None and over[k] != want:
                raise ConfigError(f"{where}: is for {k} {over[k]!r}, not {want!r}; fix its "
                                  f"{k!r} key or drop it")
        _merge_into(cfg, over)
    if file is not None and overrides is not None:
        where = f"config {file} with overrides"
    cfg["system"], cfg["preset"] = system, preset
    validate_config(cfg, system, where=where)
    return RunConfig._build("", cfg)


def _check_file_argument(file) -> None:
    if file is not None and (isinstance(file, bytes) or not isinstance(file, (str, os.PathLike))):
        raise ConfigError(f"file must be the path of a JSON config file (a str or "
                          f"pathlib.Path), got {file!r}")


def _spec_where(s) -> str:
    """How errors name a configuration whose values came from a spec's ``[run]`` table."""
    if not getattr(s, "run_overrides", None):
        return "run config"
    return f"{getattr(s, 'source', '') or f'system {s.name!r}'} [run] (run config)"


def get_config(system: str, preset: str = "large", path: str | Path | None = None
               ) -> RunConfig:
    """The validated configuration ``preset`` of ``system`` with a JSON file merged over it.

    Same as ``make_config(system, preset, file=path)``; see :func:`make_config`.
    """
    return make_config(system, preset, file=path)


def config_reference() -> str:
    """Every run-configuration key as Markdown: one table per section with the key, what it
    accepts (type and range), its default and a description (``nlyap config --keys``)."""
    titles = {"": "Top level", "lqr": "lqr", "train": "train (V and κ training)",
              "cegis": "cegis (the CEGIS loop)",
              "cegis.verify_options": "cegis.verify_options (the interval verifier)",
              "sos": "sos (an SOS certificate before the neural stage)",
              "dynamics": "dynamics (the learned-dynamics stage; ranges checked by "
                          "nlyap_opt.learned.dynamics_config.dynamics_config)"}

    def cell(text: str) -> str:
        return text.replace("|", "\\|")

    out = []
    sch = schema()
    for section, title in titles.items():
        out += ["" if not out else "", f"## {title}", "",
                "| key | accepts | default | description |", "| --- | --- | --- | --- |"]
        for key in sch[section].values():
            if key.kind == "section":
                out.append(f"| `{key.name}` | a JSON object (section) | | {cell(key.doc)} |")
                continue
            default = "" if key.default is None and not key.optional else \
                f"`{json.dumps(key.default)}`"
            out.append(f"| `{key.name}` | {cell(key.describe())} | {default} | "
                       f"{cell(key.doc)} |")
    return "\n".join(out).lstrip("\n")
