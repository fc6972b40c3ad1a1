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

    for register in _EXTRA:
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
