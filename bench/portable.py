"""The cost of portable mode: fast-preset runs with and without ``--portable``.

Usage: python bench/portable.py [--systems a,b] [--repeat 2] [--known]

Runs ``nlyap run NAME --preset fast [--known-dynamics] [--portable]`` as a fresh process for
each system (learned f unless --known), alternating the two modes, and prints the best wall
time of each with the machine's numeric-environment fingerprint, plus whether the networks
(V.json, dynamics.json, controller.json) of the portable runs are identical whatever the
shell's OPENBLAS_CORETYPE (the portable pins override it), with their joint sha256 (first 16
hex digits): run it on two machines and compare that column to see whether portable mode
gives the same networks on both CPU models.

Measured (2-core AMD EPYC with AVX-512, load about 1.5, ``--repeat 2``): Van der Pol 7.9 s
plain / 8.5 s portable (1.08x), path following 12.9 / 13.3 s (1.03x), pendulum 12.1 / 14.9 s
(1.23x); portable networks identical under SkylakeX/Haswell/Zen for all three.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

SEED_SYSTEMS = ("van_der_pol", "unicycle_path_following", "inverted_pendulum")


def _run(name: str, out: Path, portable: bool, known: bool, env: dict | None = None) -> float:
    cmd = [sys.executable, "-m", "nlyap_opt.interface.cli", "run", name, "--preset", "fast",
           "--out", str(out)] + (["--portable"] if portable else []) + \
        (["--known-dynamics"] if known else [])
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if p.returncode not in (0, 2):
        raise SystemExit(f"{' '.join(cmd)} failed ({p.returncode}): {p.stderr.strip()[-300:]}")
    return time.perf_counter() - t


def _digest(d: Path) -> str:
    h = hashlib.sha256()
    for f in ("V.json", "dynamics.json", "controller.json"):
        if (d / f).exists():
            h.update((d / f).read_bytes())
    return h.hexdigest()[:16]


def main() -> None:
    from nlyap_opt.kernel.provenance import fingerprint, fingerprint_id

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--systems", default=",".join(SEED_SYSTEMS))
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--known", action="store_true", help="true f (default: learned f)")
    args = ap.parse_args()
    fp = fingerprint()
    print(f"machine: {fp['cpu']['model']} ({os.cpu_count()} CPUs), fingerprint "
          f"{fingerprint_id(fp)}; command: python bench/portable.py "
          f"--systems {args.systems} --repeat {args.repeat}" + (" --known" if args.known else ""))
    print(f"{'system':<26} {'plain s':>8} {'portable s':>11} {'ratio':>6}  portable networks "
          "identical under OPENBLAS_CORETYPE=SkylakeX/Haswell/Zen")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for name in args.systems.split(","):
            best = {False: float("inf"), True: float("inf")}
            for r in range(args.repeat):
                for portable in (False, True):
                    t = _run(name, tmp / f"{name}_{portable}_{r}", portable, args.known)
                    best[portable] = min(best[portable], t)
            digests = set()
            for core in ("SkylakeX", "Haswell", "Zen"):
                d = tmp / f"{name}_core_{core}"
                _run(name, d, True, args.known, env=dict(os.environ, OPENBLAS_CORETYPE=core))
                digests.add(_digest(d))
            same = f"yes, sha256 {next(iter(digests))}" if len(digests) == 1 else "NO"
            print(f"{name:<26} {best[False]:8.1f} {best[True]:11.1f} "
                  f"{best[True] / best[False]:6.2f}  {same}")


if __name__ == "__main__":
    main()
