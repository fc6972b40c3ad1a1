"""The ``nlyap`` command line."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from .errors import NlyapError

__all__ = ["main"]


def _matrix_arg(text: str | None):
    """Parse ``"1,0;0,1"`` (rows separated by ';') or a scalar into an array."""
    if text is None:
        return None
    rows = [[float(v) for v in r.split(",")] for r in text.split(";")]
    return np.array(rows, dtype=float)


def _write_json(path: str | None, data: dict) -> None:
    if path:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(json.dumps(data, indent=1, allow_nan=False))
        print(f"wrote {path}")


def cmd_systems(args) -> int:
    import systems

    print(f"{'name':26s} {'nx':>3s} {'nu':>3s}  state box / input box")
    for name in systems.names():
        s = systems.get(name)
        box = " x ".join(f"[{lo:g}, {hi:g}]" for lo, hi in s.state_box)
        ubox = " x ".join(f"[{lo:g}, {hi:g}]" for lo, hi in s.input_box) or "-"
        print(f"{name:26s} {s.nx:3d} {s.nu:3d}  {box} / {ubox}   {s.description}")
    return 0


def cmd_lqr(args) -> int:
    import systems
    from baselines.lqr import lqr

    s = systems.get(args.system)
    res = lqr(s, _matrix_arg(args.Q), _matrix_arg(args.R))
    np.set_printoptions(precision=6, suppress=True)
    print(f"system {s.name}: A =\n{s.A}\nB =\n{s.B}")
    if s.nu:
        print(f"K (u = u_eq - K x) =\n{res.K}\nRiccati residual = {res.riccati_residual():.2e}")
    print(f"P (A_clᵀP + P A_cl = -I) =\n{res.P}")
    print(f"closed-loop eigenvalues = {res.eigenvalues}")
    _write_json(args.json, res.to_dict())
    return 0


def cmd_verify(args) -> int:
    import systems
    from verification import closed_loop_problem, verify

    from .network import Network

    s = systems.get(args.system)
    V = Network.load(args.lyapunov)
    ctrl = Network.load(args.controller) if args.controller else None
    dyn = Network.load(args.dynamics) if args.dynamics else None
    if args.margin and dyn is None:
        print("note: --margin without --dynamics tightens the true-f condition", file=sys.stderr)
    problem = closed_loop_problem(s, V, ctrl, dyn, inner=args.inner, outer=args.outer,
                                  level=args.level, margin=args.margin, eta=args.eta,
                                  smoothing=args.smoothing, strict=False)
    opts = {}
    if args.backend == "interval":
        opts = {"resolution": args.resolution, "progress": args.progress}
    elif args.precision is not None:
        opts = {"precision": args.precision}
    res = verify(problem, backend=args.backend, **opts)
    region = f"{args.inner:g} <= |x| <= {args.outer:g}" + (
        f" and V <= {args.level:g}" if args.level is not None else "")
    extra = f" + {args.eta:g}|∇V|" if args.eta else ""
    if args.eta and args.smoothing:
        extra = f" + {args.eta:g}sqrt(|∇V|² + {args.smoothing:g}²)"
    print(f"{res.status}: V > 0 and dV/dt{extra} < -{args.margin:g} on {region} "
          f"({res.boxes} boxes, depth {res.depth}, {res.seconds:.3f} s, {res.backend})")
    if res.counterexample is not None:
        c = res.counterexample
        print(f"  counterexample x = {c.point.tolist()} violates {c.property}: "
              f"value in [{c.value_lower:.6g}, {c.value_upper:.6g}]")
    if res.status == "unknown":
        print(f"  {len(res.undecided)} boxes undecided at resolution {args.resolution}")
    _write_json(args.json, res.to_dict())
    return {"verified": 0, "counterexample": 1}.get(res.status, 2)


def cmd_run(args) -> int:
    from .configs import get_config
    from .pipeline import run

    cfg = get_config(args.system, args.preset, args.config)
    out = args.out or f"runs/{args.system}{'_known' if args.known_dynamics else ''}"
    cert = run(args.system, cfg, out, known_dynamics=args.known_dynamics)
    return 0 if cert["status"] == "certified" else 2


def cmd_compare(args) -> int:
    from baselines.compare import compare

    from .configs import get_config

    cfg = get_config(args.system, args.preset, args.config)
    out = args.out or f"runs/compare_{args.system}"
    rows = compare(args.system, cfg, out, include_neural=not args.no_neural)
    print((Path(out) / "comparison.md").read_text())
    return 0 if all(r["certified"] for r in rows if r["method"].startswith("neural")) else 2


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="nlyap", description=__doc__)
    sub = p.add_subparsers(dest="command", required=True)

    sp = sub.add_parser("systems", help="list the system catalogue")
    sp.set_defaults(func=cmd_systems)

    sp = sub.add_parser("lqr", help="LQR gain and Lyapunov matrix of a catalogue system")
    sp.add_argument("system")
    sp.add_argument("--Q", help="state weight: scalar or rows '1,0;0,1' (default I)")
    sp.add_argument("--R", help="input weight: scalar or rows (default I)")
    sp.add_argument("--json", help="write K, P, eigenvalues to this file")
    sp.set_defaults(func=cmd_lqr)

    sp = sub.add_parser(
        "verify", help="verify V > 0 and the decrease condition on an annulus",
        description="Exit code 0 verified, 1 counterexample, 2 unknown.")
    sp.add_argument("--system", required=True)
    sp.add_argument("--lyapunov", required=True, help="V network JSON")
    sp.add_argument("--controller", help="controller network JSON (feeds the inputs)")
    sp.add_argument("--dynamics", help="learned dynamics network JSON (replaces f)")
    sp.add_argument("--margin", type=float, default=0.0, help="beta: require dV/dt < -beta")
    sp.add_argument("--eta", type=float, default=0.0,
                    help="pointwise robust margin: require dV/dt + eta*|grad V| < -beta")
    sp.add_argument("--smoothing", type=float, default=0.0,
                    help="s: with --eta use sqrt(|grad V|^2 + s^2) (certificate.json's "
                         "norm_smoothing)")
    sp.add_argument("--inner", type=float, required=True, help="inner radius epsilon")
    sp.add_argument("--outer", type=float, required=True, help="outer radius r")
    sp.add_argument("--level", type=float, help="restrict to V(x) <= level")
    sp.add_argument("--backend", default="interval", choices=["interval", "dreal"])
    sp.add_argument("--resolution", type=float, help="smallest box width (interval backend)")
    sp.add_argument("--precision", type=float, help="delta of the dreal backend")
    sp.add_argument("--progress", action="store_true")
    sp.add_argument("--json", help="write status, seconds, boxes, counterexample here")
    sp.set_defaults(func=cmd_verify)

    sp = sub.add_parser("run", help="learn f (unless --known-dynamics), V and κ; certify the ROA")
    sp.add_argument("system")
    sp.add_argument("--config", help="JSON file merged over the preset")
    sp.add_argument("--preset", default="large", help="paper | large | fast (default large)")
    sp.add_argument("--known-dynamics", action="store_true",
                    help="use the true f (the paper's 'actual dynamics' setting)")
    sp.add_argument("--out", help="output directory (default runs/NAME[_known])")
    sp.set_defaults(func=cmd_run)

    sp = sub.add_parser("compare", help="LQR, SOS and neural ROAs, all certified, vs true ROA")
    sp.add_argument("system")
    sp.add_argument("--config", help="JSON file merged over the preset")
    sp.add_argument("--preset", default="large", help="paper | large | fast (default large)")
    sp.add_argument("--out", help="output directory (default runs/compare_NAME)")
    sp.add_argument("--no-neural", action="store_true", help="baselines only")
    sp.set_defaults(func=cmd_compare)

    from .bounds import register_cli as register_learn_dynamics

    for register in [register_learn_dynamics, *_EXTRA]:
        register(sub)
    return p


#: functions adding further subcommands (verify, learn-dynamics, run, compare)
_EXTRA: list = []


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except NlyapError as err:
        print(f"nlyap: error: {err}", file=sys.stderr)
        return 3


if __name__ == "__main__":
    sys.exit(main())
