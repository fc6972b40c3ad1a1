"""The ``nlyap learn-dynamics`` subcommand: learn φ, bound η, write the files.

``nlyap learn-dynamics NAME [--config FILE] [--fast] --out DIR`` runs
:func:`nlyap_opt.learned.dynamics_stage.dynamics_stage` and writes ``DIR/dynamics.json`` (φ) and
``DIR/bounds.json`` (α, δ, K_f, K_φ, every η option, the gate). Exit codes: 0 ok; 2 η above
the configured ``eta_target`` (the files are written and the advice printed); 3 a bad input
(from :func:`nlyap_opt.interface.cli.main`).
"""

from __future__ import annotations

import sys
from pathlib import Path

import systems

from ..learned import dynamics_stage as stages
from ..learned.dynamics_config import MODELS, load_dynamics_config
from ..learned.error_models import BOUND_OPTIONS, format_table
from .cli_args import seed, time_limit_arg

__all__ = ["register_cli", "cmd_learn_dynamics"]


def cmd_learn_dynamics(args) -> int:
    """Run the dynamics stage for ``args.system``; print the table; 0 ok, 2 η too large."""

    over: dict = {}
    if args.model:
        over["model"] = args.model
    if args.bound is not None:
        over["bound_model"] = args.bound
    if args.seed is not None:
        over["seed"] = args.seed
    if args.no_progress:
        over["progress"] = False
    cfg = load_dynamics_config(args.config, args.system, "fast" if args.fast else "default",
                               over)
    system = systems.get(args.system)
    stage = stages.dynamics_stage(system, cfg, log=None)
    net_path, bounds_path = stage.save(Path(args.out))
    secs = {k: stage.seconds[k] for k in ("data", "training", "alpha", "bounds")
            if k in stage.seconds}
    print(format_table(stage.bounds, secs))
    print(f"wrote {net_path} and {bounds_path}")
    if not stage.ok:
        print(f"nlyap: {stage.status}: {stage.advice}", file=sys.stderr)
        return 2
    return 0


def register_cli(sub) -> None:
    """Add ``nlyap learn-dynamics NAME [--config FILE] --out DIR`` to a subparsers object."""

    sp = sub.add_parser("learn-dynamics",
                        help="learn φ ≈ f on a grid and compute α, δ, K_f, K_φ, η")
    sp.add_argument("system", help="catalogue system name or system spec file (.toml)")
    sp.add_argument("--config", help="JSON file overriding the default configuration")
    sp.add_argument("--out", required=True, help="directory for dynamics.json and bounds.json")
    sp.add_argument("--fast", action="store_true", help="tiny configuration (seconds)")
    sp.add_argument("--model", choices=list(MODELS),
                    help="learned-dynamics model (the config key dynamics.model)")
    sp.add_argument("--bound", help=f"bound option: best or one of {', '.join(BOUND_OPTIONS)}")
    sp.add_argument("--seed", type=seed, help="seed of the training-node draw and of φ "
                    "(the config key dynamics.seed)")
    sp.add_argument("--no-progress", action="store_true", dest="no_progress",
                    help="no progress bars")
    time_limit_arg(sp)
    sp.set_defaults(func=cmd_learn_dynamics)
