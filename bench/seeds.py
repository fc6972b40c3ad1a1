"""Seed table: certified share and time over training seeds, for known and learned f.

Usage: python bench/seeds.py [--seeds 0-9] [--preset large] [--systems a,b]
       [--settings known,learned]

For each system and setting, runs `nlyap_opt.workflow.pipeline.run` once per seed (the seed of V/κ
training, CEGIS sampling and, for learned f, φ's training) into a temporary directory and
prints one row per run, then the median and minimum certified share (of the simulated true
ROA; for controlled systems within the verification disc) and the median seconds.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

SEED_SYSTEMS = ("van_der_pol", "unicycle_path_following", "inverted_pendulum")


def parse_seeds(text: str) -> list[int]:
    """``"0-4"`` → 0, 1, 2, 3, 4; ``"0,3"`` → 0, 3; ``"2"`` → 2. Raises ValueError
    (with what was wrong) for anything else, and for a seed named twice (its runs would
    share a directory)."""
    try:
        if "-" in text:
            a, b = text.split("-")
            seeds = list(range(int(a), int(b) + 1))
        else:
            seeds = [int(s) for s in text.split(",")]
    except ValueError:
        raise ValueError(f"{text!r} is not a seed list: give K, K1,K2,... or A-B "
                         "(integers >= 0)") from None
    if not seeds or min(seeds) < 0:
        raise ValueError(f"{text!r}: give at least one seed, each an integer >= 0")
    if len(set(seeds)) < len(seeds):
        raise ValueError(f"{text!r} names a seed twice: give each seed once")
    return seeds


def main() -> None:
    from nlyap_opt.workflow.configs import make_config
    from nlyap_opt.workflow.pipeline import run

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-9")
    ap.add_argument("--preset", default="large")
    ap.add_argument("--systems", default=",".join(SEED_SYSTEMS))
    ap.add_argument("--settings", default="known,learned")
    args = ap.parse_args()
    try:
        seeds = parse_seeds(args.seeds)
    except ValueError as err:
        ap.error(f"--seeds: {err}")
    summary = []
    print("| system | f | seed | status | level | share % | seconds |")
    print("|---|---|---|---|---|---|---|")
    for name in args.systems.split(","):
        for setting in args.settings.split(","):
            known = setting == "known"
            shares, times = [], []
            for seed in seeds:
                over = {"train": {"seed": seed}, "cegis": {"seed": seed}}
                if not known:
                    over["dynamics"] = {"seed": seed}
                cfg = make_config(name, args.preset, overrides=over)
                with tempfile.TemporaryDirectory() as tmp:
                    t = time.perf_counter()
                    res = run(name, cfg, Path(tmp), known_dynamics=known, log=lambda m: None)
                    dt = time.perf_counter() - t
                frac = res.summary.get("fraction_of_true_roa") if res.certified else 0.0
                # None: the true ROA could not be estimated (the report says why)
                if frac is not None:
                    shares.append(100 * frac)
                times.append(dt)
                print(f"| {name} | {setting} | {seed} | {res.status.value} | "
                      f"{res.summary.get('level', 0.0):.5g} | "
                      f"{'n/a' if frac is None else f'{100 * frac:.1f}'} | {dt:.0f} |",
                      flush=True)
            shares = shares or [float("nan")]
            summary.append((name, setting, statistics.median(shares), min(shares),
                            statistics.median(times), sum(s > 0 for s in shares)))
    print("\n| system | f | median share % | min share % | certified seeds | median s |")
    print("|---|---|---|---|---|---|")
    for name, setting, med, mn, t, n in summary:
        print(f"| {name} | {setting} | {med:.1f} | {mn:.1f} | {n}/{len(seeds)} | {t:.0f} |")


if __name__ == "__main__":
    main()
