"""Seed-portfolio benchmark: K seeds on 1 vs 2 Dask workers.

Runs :func:`nlyap_opt.workflow.portfolio.run_portfolio` twice with the same seeds (``fast`` preset
by default), each time into a fresh directory on a ``LocalCluster`` started by the call, and
prints the wall-clock seconds, the speed-up and the chosen seed (which must not depend on
the worker count). Figures are printed, not asserted.

    python bench/portfolio.py [--system van_der_pol] [--seeds 4] [--preset fast] [--learned]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from nlyap_opt.workflow.configs import get_config
from nlyap_opt.workflow.portfolio import run_portfolio


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--system", default="van_der_pol")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--learned", action="store_true", help="learned φ (default: true f)")
    args = ap.parse_args(argv)
    cfg = get_config(args.system, args.preset)
    load = os.getloadavg()[0]
    rows = []
    with tempfile.TemporaryDirectory(prefix="nlyap-portfolio-") as tmp:
        for w in args.workers:
            t = time.perf_counter()
            res = run_portfolio(args.system, cfg, Path(tmp) / f"w{w}", seeds=args.seeds,
                                workers=w, known_dynamics=not args.learned,
                                log=lambda m: None)
            rows.append((w, time.perf_counter() - t, res))
    base = rows[0][1]
    print(f"{args.system}, preset {args.preset}, {'learned φ' if args.learned else 'true f'}, "
          f"{args.seeds} seeds; load average before: {load:.2f}, after: "
          f"{os.getloadavg()[0]:.2f} ({os.cpu_count()} cores)")
    print("| workers | seconds | speed-up | efficiency | sum of seed seconds | best seed | "
          "best area | certified seeds |")
    print("|---|---|---|---|---|---|---|---|")
    for w, sec, res in rows:
        best = res.best
        print(f"| {w} | {sec:.1f} | {base / sec:.2f} | {base / sec * rows[0][0] / w:.2f} | "
              f"{sum(r.seconds for r in res.runs):.1f} | "
              f"{'–' if best is None else best.seed} | "
              f"{'–' if best is None else f'{best.certified_area:.4g}'} | "
              f"{sum(r.certified for r in res.runs)}/{len(res.runs)} |")
    same = len({(None if r.best is None else r.best.seed) for _, _, r in rows}) == 1
    print(f"same choice on every worker count: {'yes' if same else 'NO'}")


if __name__ == "__main__":
    main()
