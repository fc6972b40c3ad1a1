"""The default method on systems without a preset: certified share of the true ROA and time.

Usage: python bench/default_training.py [--cases vdp3,power,...] [--settings known,learned]
       [--out DIR]

Each case is run as a user would, with default settings: ``nlyap run SPEC
[--known-dynamics] --out DIR`` for a spec file, ``nlyap run NAME --preset default`` for a
catalogue system (its preset is not used). Prints one Markdown row per run (status, the
certified share of the simulated true ROA within the domain, wall seconds) with the command
and the machine. The peers' shares are LyZNet's published ones on the same boxes.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: name: (what nlyap runs, the peer's share or None)
CASES = {
    "vdp3": ("examples/van_der_pol_mu3.toml", 85.2),
    "power": ("examples/two_machine_power.toml", 82.3),
    "khalil": ("examples/box_domain.toml", None),
    "van_der_pol": ("van_der_pol", None),
    "unicycle_path_following": ("unicycle_path_following", None),
    "inverted_pendulum": ("inverted_pendulum", None),
}


def _machine() -> str:
    return (f"{platform.node()}: {platform.processor() or platform.machine()}, "
            f"{os.cpu_count()} CPUs, Python {platform.python_version()}")


def run_case(target: str, known: bool, out: Path) -> tuple[list[str], dict, float]:
    """``nlyap run`` of one case; returns the command, certificate.json and wall seconds."""
    cmd = [sys.executable, "-m", "nlyap_opt.cli", "run", target, "--out", str(out)]
    if not target.endswith(".toml"):
        cmd += ["--preset", "default"]
    if known:
        cmd.append("--known-dynamics")
    t = time.perf_counter()
    subprocess.run(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                   check=False)
    seconds = time.perf_counter() - t
    path = out / "certificate.json"
    cert = json.loads(path.read_text()) if path.exists() else {"status": "failed"}
    return cmd, cert, seconds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="vdp3,power")
    ap.add_argument("--settings", default="known,learned")
    ap.add_argument("--out", default=None, help="keep the runs here (default: a temp dir)")
    args = ap.parse_args()
    base = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="nlyap_default_"))
    print(f"machine: {_machine()}")
    print("| case | f | status | share % | peer % | seconds | command |")
    print("|---|---|---|---|---|---|---|")
    for name in args.cases.split(","):
        target, peer = CASES[name]
        for setting in args.settings.split(","):
            known = setting == "known"
            cmd, cert, sec = run_case(target, known, base / f"{name}_{setting}")
            share = cert.get("fraction_of_true_roa")
            shown = "–" if share is None or cert["status"] != "certified" else \
                f"{100 * share:.1f}"
            command = "nlyap " + " ".join(cmd[3:5]) + (" --preset default" if "--preset"
                                                        in cmd else "") + \
                (" --known-dynamics" if known else "")
            print(f"| {name} | {'true' if known else 'learned'} | {cert['status']} | "
                  f"{shown} | {'' if peer is None else peer} | {sec:.0f} | `{command}` |",
                  flush=True)


if __name__ == "__main__":
    main()
