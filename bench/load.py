"""Same input, same certificate: `nlyap run` idle and beside two CPU-burning processes.

Usage: python bench/load.py [SYSTEM] [--preset fast|large] [--known-dynamics]

Runs the pipeline twice into fresh directories — once on the machine as it is, once with two
`while True: pass` processes beside it — and prints the level, η and the sha256 of V.json,
controller.json and dynamics.json of both runs, whether they are identical bit for bit, and
the ratio of wall times. Budgets are step counts (no wall clock decides anything), so the
certificates must be identical; only the time may differ.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _run(system: str, preset: str, known: bool, out: Path) -> tuple[float, dict]:
    cmd = [sys.executable, "-m", "nlyap_opt.interface.cli", "run", system, "--preset", preset,
           "--out", str(out)] + (["--known-dynamics"] if known else [])
    t = time.perf_counter()
    rc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode
    wall = time.perf_counter() - t
    cert = json.loads((out / "certificate.json").read_text())
    digests = {f: hashlib.sha256((out / f).read_bytes()).hexdigest()[:16]
               for f in ("V.json", "controller.json", "dynamics.json") if (out / f).exists()}
    return wall, {"rc": rc, "status": cert["status"], "level": cert["level"],
                  "eta": cert.get("eta"), **digests}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("system", nargs="?", default="van_der_pol")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--known-dynamics", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        t_idle, idle = _run(args.system, args.preset, args.known_dynamics, Path(tmp) / "idle")
        burners = [subprocess.Popen([sys.executable, "-c", "while True: pass"])
                   for _ in range(2)]
        try:
            t_load, load = _run(args.system, args.preset, args.known_dynamics,
                                Path(tmp) / "load")
        finally:
            for p in burners:
                p.kill()
                p.wait()
    print(f"{args.system} ({args.preset}, {'known' if args.known_dynamics else 'learned'} f)")
    print(f"{'':8s} {'seconds':>8s}  " + "  ".join(f"{k}" for k in idle))
    for name, t, r in (("idle", t_idle, idle), ("loaded", t_load, load)):
        print(f"{name:8s} {t:8.1f}  " + "  ".join(f"{v!r}" for v in r.values()))
    print(f"identical: {idle == load}; time ratio loaded/idle: {t_load / t_idle:.2f}")


if __name__ == "__main__":
    main()
