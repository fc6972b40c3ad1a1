"""Comparison benchmark: every method on every seed system, one markdown table.

    python bench/compare.py [--preset large] [--out runs/bench_compare] [SYSTEM ...]

Runs ``baselines.compare.compare`` (LQR, SOS, neural with learned φ, neural with the true f;
every row certified by the same interval verifier) and prints one table with areas as
fractions of the simulated true ROA and wall times. Finished pipeline stages are reused
(delete the output directory for a cold run).
"""

from __future__ import annotations

import argparse
import time

import systems
from baselines.compare import compare
from nlyap_opt.workflow.configs import get_config


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("systems", nargs="*", default=list(systems.SEED_SYSTEMS))
    ap.add_argument("--preset", default="large")
    ap.add_argument("--out", default="runs/bench_compare")
    args = ap.parse_args(argv)
    table = ["| system | method | certified | level | area | % of true ROA | seconds |",
             "|---|---|---|---|---|---|---|"]
    for name in args.systems:
        t0 = time.perf_counter()
        rows = compare(name, get_config(name, args.preset), f"{args.out}/{name}",
                       log=lambda m: None)
        for r in (row.to_json() for row in rows):
            table.append(f"| {name} | {r['method']} | {'yes' if r['certified'] else 'no'} | "
                         f"{r['level']:.5g} | {r.get('area', 0):.4g} | "
                         f"{100 * r.get('fraction_of_true_roa', 0):.1f} | {r['seconds']:.1f} |")
        print(f"{name}: {time.perf_counter() - t0:.0f} s", flush=True)
    print("\n".join(table))


if __name__ == "__main__":
    main()
