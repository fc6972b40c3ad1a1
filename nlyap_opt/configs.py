"""Run configurations of the seed systems: ``paper`` (the paper's discs), ``large`` (aim at
the whole true ROA) and ``fast`` (coarse, for the test suite).

A configuration is a nested dict; :func:`get_config` merges a user's JSON file over a
preset. Keys:

- ``outer`` (r), ``inner`` (ε): the verification annulus;
- ``controller_scale`` (C): actuator limit of ``u = C·tanh(Kx + b)`` (``None``: no input);
- ``lqr``: ``{"Q": ..., "R": ...}`` weights of the initial LQR gain;
- ``train``: :class:`nlyap_opt.learning.TrainConfig` fields;
- ``cegis``: :class:`nlyap_opt.cegis.CegisConfig` fields (besides inner/outer/train);
- ``eval_box``, ``eval_grid``: box and grid for areas and the simulated true ROA;
- ``dynamics``: options of the learned-dynamics stage (``nlyap_opt.dynamics``).
"""

from __future__ import annotations

import copy
import json
from pathlib import Path

from .errors import ConfigError, UnknownNameError

__all__ = ["PRESETS", "get_config", "read_json_object"]


def read_json_object(path: str | Path) -> dict:
    """A configuration file: a JSON object (else :class:`ConfigError` saying why)."""
    try:
        obj = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise ConfigError(f"cannot read config {path}: {err}") from None
    if not isinstance(obj, dict):
        raise ConfigError(f"config {path} must hold a JSON object")
    return obj

_VDP_BOX = [[-3.0, 3.0], [-3.0, 3.0]]

PRESETS: dict[str, dict[str, dict]] = {
    "van_der_pol": {
        "paper": {
            "outer": 1.2, "inner": 0.2, "controller_scale": None,
            "train": {"hidden": [16], "features": 4, "steps": 1500, "lr": 0.01},
            "cegis": {"iterations": 4, "steps": 500},
            "eval_box": _VDP_BOX, "eval_grid": 300,
            "dynamics": {"preset": "default"},
        },
        "large": {
            "outer": 3.0, "inner": 0.2, "controller_scale": None,
            # V fitted to the simulated trajectory cost (its sublevel sets grow to the ROA)
            # plus the decrease terms; the verifier runs every third iteration
            "train": {"hidden": [20, 20], "features": 6, "steps": 1500, "lr": 0.01,
                      "lr_schedule": "cosine", "decay": 0.05, "level_slack": 0.5,
                      "relative_decrease": True, "w_fit": 10.0, "w_pde": 1.0,
                      "w_local": 10.0, "time_budget": 60.0},
            "cegis": {"iterations": 6, "steps": 500, "verify_every": 3, "sim_time": 30.0,
                      "sim_dt": 0.04, "sim_grid": 301,
                      "inner_samples": 2000, "boundary_samples": 20000},
            "eval_box": _VDP_BOX, "eval_grid": 300,
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
            "eval_box": _VDP_BOX, "eval_grid": 100,
            "dynamics": {"preset": "fast"},
        },
    },
    "unicycle_path_following": {
        "paper": {
            "outer": 0.8, "inner": 0.1, "controller_scale": 5.0,
            "train": {"hidden": [16], "features": 4, "steps": 1500, "lr": 0.01},
            # sim_grid: the training simulations run on a table of the learned φ
            "cegis": {"iterations": 6, "steps": 500, "sim_grid": 301},
            "eval_box": [[-0.8, 0.8], [-0.8, 0.8]], "eval_grid": 200,
            "dynamics": {"preset": "default"},
        },
        "fast": {
            "outer": 0.8, "inner": 0.1, "controller_scale": 5.0,
            "train": {"hidden": [6], "features": 3, "steps": 300, "lr": 0.02},
            "cegis": {"iterations": 2, "steps": 100, "samples": 4000},
            "eval_box": [[-0.8, 0.8], [-0.8, 0.8]], "eval_grid": 100,
            # the full-model fast φ of path following has η ≈ 0.4, too coarse for ε = 0.1;
            # the control-affine model on a 161² x-grid reaches η ≈ 0.01 in ~13 s
            "dynamics": {"preset": "fast", "model": "control_affine", "hidden": 60,
                         "grid_counts": [161, 161], "train_points": 4000, "steps": 800,
                         "lm_iterations": 60, "minimax_rounds": 3, "time_budget": 25.0,
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
            "cegis": {"iterations": 4, "min_iterations": 2, "steps": 500, "sim_grid": 301},
            "eval_box": [[-4.0, 4.0], [-4.0, 4.0]], "eval_grid": 200,
            "dynamics": {"preset": "default"},
        },
        "fast": {
            "outer": 4.0, "inner": 0.4, "controller_scale": 20.0,
            "lqr": {"Q": [[1.0, 0.0], [0.0, 20.0]], "R": 1.0},
            "train": {"hidden": [6], "features": 3, "steps": 300, "lr": 0.02},
            "cegis": {"iterations": 2, "steps": 100, "samples": 4000},
            "eval_box": [[-4.0, 4.0], [-4.0, 4.0]], "eval_grid": 100,
            "dynamics": {"preset": "fast", "model": "control_affine", "hidden": 40,
                         "grid_counts": [201, 201], "train_points": 3000, "steps": 600,
                         "lm_iterations": 40, "minimax_rounds": 2, "time_budget": 15.0,
                         "interval_boxes": 4096},
        },
    },
}
# the path-following and pendulum "large" configurations are the paper's discs: the true ROA
# of the closed loop covers them, so the target is the whole disc
PRESETS["unicycle_path_following"]["large"] = PRESETS["unicycle_path_following"]["paper"]
PRESETS["inverted_pendulum"]["large"] = PRESETS["inverted_pendulum"]["paper"]


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def get_config(system: str, preset: str = "large", path: str | Path | None = None) -> dict:
    """The configuration ``preset`` of ``system``, with a JSON file merged over it."""
    if system not in PRESETS:
        raise UnknownNameError(
            f"no run configuration for system {system!r}; configured: {', '.join(PRESETS)} "
            "(pass a full --config FILE for other systems)"
        )
    if preset not in PRESETS[system]:
        raise UnknownNameError(
            f"unknown preset {preset!r}; available: {', '.join(PRESETS[system])}"
        )
    cfg = copy.deepcopy(PRESETS[system][preset])
    if path is not None:
        cfg = _merge(cfg, read_json_object(path))
    if not (0 < cfg["inner"] < cfg["outer"]):
        raise ConfigError(f"need 0 < inner < outer, got {cfg['inner']}, {cfg['outer']}")
    cfg["system"], cfg["preset"] = system, preset
    return cfg
