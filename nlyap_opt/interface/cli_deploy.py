"""The ``nlyap simulate`` and ``nlyap export`` subcommands: a certificate put to use.

``nlyap simulate RUN_DIR [--points N] [--horizon T] [--true|--learned]
[--filter clf-qp --nominal FILE] --out DIR`` writes ``trajectories.npz``, ``simulate.png``
and ``simulate.json``; exit 0 when every trajectory from the certified set stayed in it,
kept ``V`` non-increasing on ``Ω_c∖B_ε`` and converged, 1 when one left the set or raised
``V`` (a contradiction of the certificate: a bug to report), 2 when one did not converge
within the horizon (a longer ``--horizon`` decides), 3 for a bad input.

``nlyap export RUN_DIR --format c|onnx --out DIR`` writes ``nlyap.c``/``nlyap.h`` or
``V.onnx``/``kappa.onnx`` (:mod:`nlyap_opt.deployment.export`).

Both re-verify the run's certificate from its hashed artifacts first
(:func:`nlyap_opt.deployment.deploy.load_run`).
"""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import systems

from ..deployment.deploy import (
    SIM_HORIZON,
    default_horizon,
    load_run,
    plot_simulation,
    simulate_run,
)
from ..deployment.export import export_c, export_onnx
from ..deployment.filter import ClfQpFilter, load_nominal
from ..kernel.errors import UsageError
from ..kernel.jsonio import write_atomic
from .cli_args import number as _number
from .cli_args import positive as _positive
from .cli_args import recheck_system_args
from .cli_args import seed as _seed
from .cli_args import workers as _count

__all__ = ["register_cli", "cmd_simulate", "cmd_export"]


def _run_dir(path: str) -> Path:
    p = Path(path)
    if not p.exists():
        raise UsageError(f"run directory {p}: no such directory; pass the --out of a finished "
                         "`nlyap run`")
    return p


#: the most states (trajectories times steps) one ``simulate`` keeps in memory
MAX_STORED_STATES = 1e8


def _log(msg: str) -> None:
    print(f"[re-check] {msg.strip()}")


def _check_steps(args, horizon: float) -> None:
    """Refuse a step longer than ``horizon`` or more stored states than memory holds."""
    if args.dt > horizon:
        raise UsageError(f"--dt {args.dt:g} is longer than --horizon {horizon:g}; give a "
                         "step below the horizon")
    steps = horizon / args.dt
    if steps * args.points > MAX_STORED_STATES:
        raise UsageError(f"{args.points} trajectories of {steps:.3g} steps would keep "
                         f"{steps * args.points:.3g} states (at most {MAX_STORED_STATES:.0e}); "
                         "lower --points or --horizon, or raise --dt")


def cmd_simulate(args) -> int:
    """Simulate from the certified set; check the certificate's promises (exit 0/1/2)."""

    if args.filter and not args.nominal:
        raise UsageError("--filter clf-qp needs --nominal FILE (the controller to filter: a "
                         "JSON linear gain or network file)")
    if args.decay is not None and not args.filter:
        raise UsageError("--decay is the safety filter's share of κ's decrease; add "
                         "--filter clf-qp --nominal FILE, or drop --decay")
    args.decay = _DECAY_DEFAULT if args.decay is None else args.decay
    if args.nominal and not args.filter:
        raise UsageError("--nominal FILE is the controller the safety filter keeps safe; add "
                         "--filter clf-qp")
    _check_steps(args, args.horizon or SIM_HORIZON)
    run = load_run(_run_dir(args.run_dir), system=_system(args),
                   allow_factory=args.allow_factory, log=_log)
    if args.filter and not run.system.nu:
        raise UsageError(f"--filter clf-qp chooses the input of a controlled system, and "
                         f"{run.system.name!r} has no inputs; drop --filter and --nominal")
    which = "true" if args.true else "learned" if args.learned else None
    if args.horizon is None:
        args.horizon = default_horizon(run, which)
        if args.horizon > SIM_HORIZON:
            print(f"simulating {args.horizon:.4g} s, not {SIM_HORIZON:g} s: the closed loop "
                  "converges slowly at the origin (its slowest linear mode); --horizon sets "
                  "the time")
            _check_steps(args, args.horizon)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    opts = dict(points=args.points, horizon=args.horizon, dt=args.dt, dynamics=which,
                seed=args.seed)
    nominal_res = None
    title = f"{run.system.name}: closed loop under κ"
    if args.filter:
        nominal = load_nominal(args.nominal, run.system.nx, run.system.nu)
        filt = ClfQpFilter(run, nominal, decay=args.decay, dynamics=which)
        nominal_res = simulate_run(run, feedback=nominal, outside=0, confirm=False, **opts)
        res = simulate_run(run, feedback=filt, **opts)
        title = (f"{run.system.name}: nominal {Path(args.nominal).name} through the CLF-QP "
                 f"filter (orange: unfiltered)")
    else:
        res = simulate_run(run, **opts)
    extra = {} if nominal_res is None else {
        "nominal_inside": nominal_res.inside, "nominal_stayed": nominal_res.stayed,
        "nominal_converged": nominal_res.converged}
    res.save(out / "trajectories.npz", **extra)
    png = plot_simulation(run, res, out / "simulate.png", title=title, nominal=nominal_res)
    summary = {"run": str(run.directory), "certificate_sha256": run.sha256,
               "dynamics": res.dynamics, "points": int(res.inside.shape[1]),
               "stayed": int(res.stayed.sum()), "monotone": int(res.monotone.sum()),
               "converged": int(res.converged.sum()), "horizon": args.horizon,
               # the step taken: --dt, shortened to divide the horizon evenly
               "dt": float(res.t[1] - res.t[0]) if len(res.t) > 1 else args.dt,
               "dt_requested": args.dt, "seed": args.seed, "failures": res.failures}
    if nominal_res is not None:
        summary["filter"] = {"nominal": str(args.nominal), "decay": args.decay,
                             "unfiltered_stayed": int(nominal_res.stayed.sum()),
                             "qp_solves": filt.stats.qp, "in_ellipse": filt.stats.in_ellipse,
                             "fallback_to_kappa": filt.stats.fallback}
        print(f"unfiltered nominal: {int(nominal_res.stayed.sum())} of "
              f"{nominal_res.stayed.size} trajectories stayed in the certified set (no claim)")
        print(f"filtered: {filt.stats.qp} QPs, {filt.stats.fallback} answers replaced by κ, "
              f"{filt.stats.in_ellipse} states in E (κ)")
    write_atomic(out / "simulate.json", json.dumps(summary, indent=1, allow_nan=False))
    print(res.summary())
    print(f"wrote {out / 'trajectories.npz'}, {png} and {out / 'simulate.json'}")
    if res.violated:
        for f in res.failures:
            print(f"nlyap: FAILURE: {f}", file=sys.stderr)
        print("nlyap: FAILURE: a trajectory from the certified set contradicts the certificate; "
              "this is a bug: please report it with the run directory", file=sys.stderr)
        return 1
    if not res.converged.all():
        for f in res.failures:   # the first few (the count follows)
            print(f"nlyap: not converged: {f}", file=sys.stderr)
        print(f"nlyap: not converged: {int((~res.converged).sum())} trajectories have not "
              f"reached ‖x‖ ≤ {res.tol:.3g} by t = {args.horizon:g}; rerun with a longer "
              "--horizon", file=sys.stderr)
        return 2
    return 0


def cmd_export(args) -> int:
    """Write the C or ONNX code of a certified run."""

    if args.format == "onnx":   # refuse a missing exporter before the re-check
        if importlib.util.find_spec("onnx") is None:
            raise UsageError("--format onnx needs the onnx package, which is not installed; "
                             "pip install 'nlyap_opt[onnx]' (or use --format c)")
    run = load_run(_run_dir(args.run_dir), system=_system(args),
                   allow_factory=args.allow_factory, log=_log)
    files = export_c(run, args.out) if args.format == "c" else export_onnx(run, args.out)
    print(f"wrote {', '.join(str(f) for f in files)} (certificate.json sha256 {run.sha256})")
    return 0


_decay_share = _number(lambda v: 0 < v <= 1, "a finite number in (0, 1]")

#: ``--decay`` when not given
_DECAY_DEFAULT = 0.5


def _system(args):
    """The ``--system`` to re-check the run against (registered by the command line, a
    spec file loaded under its own rules), or ``None``."""
    return None if args.system is None else systems.get(args.system)


def register_cli(sub) -> None:
    """Add ``nlyap simulate`` and ``nlyap export`` to a subparsers object."""

    sp = sub.add_parser("simulate", help="closed-loop trajectories from a run's certified set",
                        description="Simulate the closed loop from seeded samples of a run's "
                                    "certified set (re-verified first) and check that every "
                                    "trajectory stays inside and converges.")
    sp.add_argument("run_dir", metavar="RUN_DIR", help="directory of a finished `nlyap run`")
    sp.add_argument("--points", type=_count, default=200,
                    help="starting points in the certified set (default 200; a quarter as "
                         "many outside, for contrast)")
    sp.add_argument("--horizon", type=_positive, default=None,
                    help="simulated time (default 20 s, longer where the closed loop's "
                         "slowest mode at the origin needs it to converge)")
    sp.add_argument("--dt", type=_positive, default=0.01, help="RK4 step (0.01)")
    sp.add_argument("--seed", type=_seed, default=0, help="sampling seed (0)")
    g = sp.add_mutually_exclusive_group()
    g.add_argument("--true", action="store_true",
                   help="simulate the true f (default where the run has it)")
    g.add_argument("--learned", action="store_true", help="simulate the learned φ")
    sp.add_argument("--filter", choices=["clf-qp"],
                    help="filter --nominal through the CLF-QP safety filter (OSQP)")
    sp.add_argument("--nominal", metavar="FILE",
                    help="nominal controller: JSON {\"format\": \"nlyap-nominal-controller\", "
                         "\"K\": [[...]], \"u0\": [...]} (u = u0 - K x) or a network file")
    sp.add_argument("--decay", type=_decay_share, default=None,
                    help="with --filter: λ in (0, 1], the filtered input keeps λ times κ's "
                         f"proven decrease (default {_DECAY_DEFAULT})")
    sp.add_argument("--out", required=True, help="directory for the files (created)")
    recheck_system_args(sp)
    sp.set_defaults(func=cmd_simulate)

    sp = sub.add_parser("export", help="C99 or ONNX code of a run's V, κ and certified set",
                        description="Generate deployment code from a run (re-verified first).")
    sp.add_argument("run_dir", metavar="RUN_DIR", help="directory of a finished `nlyap run`")
    sp.add_argument("--format", required=True, choices=["c", "onnx"],
                    help="c: dependency-free C99 source and header of κ, V, ∇V and the "
                         "certified-set test; onnx: V.onnx and kappa.onnx (needs the onnx "
                         "package)")
    sp.add_argument("--out", required=True, help="directory for the files (created)")
    recheck_system_args(sp)
    sp.set_defaults(func=cmd_export)

