"""Seed-portfolio benchmark: K seeds on 1 vs 2 Dask workers.

Runs :func:`nlyap_opt.workflow.portfolio.run_portfolio` twice with the same seeds (``fast`` preset
by default), each time into a fresh directory on a ``LocalCluster`` started by the call, and
prints the wall-clock seconds, the speed-up and the chosen seed (which must not depend on
the worker count): MEASURED. Figures are printed, not asserted. ``--warm``: each cluster is
started and every worker warmed (:func:`nlyap_opt.workflow.portfolio.warm_workers`: imports,
torch's first optimiser step, matplotlib) before the clock starts, as on a cluster kept for
many runs; without it the seconds include the cluster's start. The table gives each
seed's wall and CPU seconds summed: CPU well below wall means the workers waited for a core.

``--model 4 8 16`` adds MODELLED rows: the seeds run one after another in this process on
a :class:`nlyap_opt.distributed.parallel.SimulatedCluster` (each seed one task, its cost its
CPU seconds here, after one unrecorded warm-up seed so that no seed pays this process's
start), and are list-scheduled on each worker count
(:meth:`~nlyap_opt.distributed.parallel.SimulatedCluster.replay`); every virtual worker
pays a process start before its first seed: the CPU seconds of a fresh process that
imports the tool and runs the first seed, less that seed's warm CPU seconds. The model
leaves out the scheduler's latency per task (milliseconds against seconds per seed).

    python bench/portfolio.py [--system van_der_pol] [--seeds 4] [--preset fast] [--learned]
                              [--workers 1 2] [--model 4 8 16] [--warm]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from nlyap_opt.distributed.parallel import dask_client
from nlyap_opt.workflow.configs import get_config
from nlyap_opt.workflow.portfolio import run_portfolio, warm_workers

_FRESH = """
import resource, sys, tempfile, time
from nlyap_opt.workflow.configs import get_config
from nlyap_opt.workflow.portfolio import _run_seed, seed_config
cfg = get_config({system!r}, {preset!r})
with tempfile.TemporaryDirectory() as tmp:
    t = time.thread_time()
    _run_seed({system!r}, seed_config(cfg, {seed}), tmp, {known}, None, {seed})
    seed = time.thread_time() - t
ru = resource.getrusage(resource.RUSAGE_SELF)
print(ru.ru_utime + ru.ru_stime, seed)
"""


def model_rows(args, cfg) -> None:
    """MODELLED speed-ups of the portfolio on ``args.model`` workers (see the module's text)."""
    import subprocess
    import sys

    from nlyap_opt.distributed.parallel import SimulatedCluster
    from nlyap_opt.workflow.portfolio import _run_seed, seed_config

    known = not args.learned
    seeds = list(range(args.seeds))
    with tempfile.TemporaryDirectory(prefix="nlyap-portfolio-model-") as tmp:
        # a fresh process: imports and the first seed (its CPU in all, and the seed's own)
        out = subprocess.run([sys.executable, "-c", _FRESH.format(
            system=args.system, preset=args.preset, seed=seeds[0], known=known)],
            check=True, capture_output=True, text=True)
        fresh_total, fresh_seed = (float(v) for v in out.stdout.split()[-2:])
        # warm this process with the same seed (not recorded), then measure its warm cost
        _run_seed(args.system, seed_config(cfg, seeds[0]), str(Path(tmp) / "warm"), known,
                  None, seeds[0])
        t = time.thread_time()
        _run_seed(args.system, seed_config(cfg, seeds[0]), str(Path(tmp) / "warm2"), known,
                  None, seeds[0])
        warm = time.thread_time() - t
        startup = max(0.0, fresh_total - warm)
        sim = SimulatedCluster(max(args.model), cost="cpu", startup=startup)
        res = run_portfolio(args.system, cfg, Path(tmp) / "model", seeds=seeds, client=sim,
                            known_dynamics=known, log=lambda m: None)
    costs = [c for _, c in sim._plain["log"]]
    print(f"MODELLED: {args.system}, preset {args.preset}, "
          f"{'learned φ' if args.learned else 'true f'}, {len(seeds)} seeds; process start "
          f"{startup:.2f} CPU s (fresh process {fresh_total:.2f} CPU s in all, its first seed "
          f"{fresh_seed:.2f}, the same seed warm {warm:.2f}); seeds {min(costs):.2f} to "
          f"{max(costs):.2f} CPU s, {sum(costs):.1f} in all")
    print("| workers | modelled seconds | speed-up vs 1 worker | efficiency |")
    print("|---|---|---|---|")
    one = sim.replay(1)["makespan"]
    for w in sorted({1, *args.model}):
        span = sim.replay(w)["makespan"]
        print(f"| {w} (MODELLED) | {span:.1f} | {one / span:.2f} | {one / span / w:.2f} |")
    best = res.best
    print(f"best seed {'–' if best is None else best.seed}, "
          f"{sum(r.certified for r in res.runs)}/{len(res.runs)} certified")
    print()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--system", default="van_der_pol")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--workers", type=int, nargs="*", default=[1, 2])
    ap.add_argument("--learned", action="store_true", help="learned φ (default: true f)")
    ap.add_argument("--model", type=int, nargs="*", default=[],
                    help="worker counts to model (SimulatedCluster), e.g. 4 8 16")
    ap.add_argument("--warm", action="store_true",
                    help="start and warm each cluster before the clock (a kept cluster)")
    args = ap.parse_args(argv)
    cfg = get_config(args.system, args.preset)
    if args.model:
        model_rows(args, cfg)
    if not args.workers:
        return
    load = os.getloadavg()[0]
    rows = []
    with tempfile.TemporaryDirectory(prefix="nlyap-portfolio-") as tmp:
        for w in args.workers:
            if args.warm:
                with dask_client(workers=w) as client:
                    warm_workers(client)
                    t = time.perf_counter()
                    res = run_portfolio(args.system, cfg, Path(tmp) / f"w{w}",
                                        seeds=args.seeds, client=client,
                                        known_dynamics=not args.learned, log=lambda m: None)
                    rows.append((w, time.perf_counter() - t, res))
                continue
            t = time.perf_counter()
            res = run_portfolio(args.system, cfg, Path(tmp) / f"w{w}", seeds=args.seeds,
                                workers=w, known_dynamics=not args.learned,
                                log=lambda m: None)
            rows.append((w, time.perf_counter() - t, res))
    base = rows[0][1]
    print(f"{args.system}, preset {args.preset}, {'learned φ' if args.learned else 'true f'}, "
          f"{args.seeds} seeds; load average before: {load:.2f}, after: "
          f"{os.getloadavg()[0]:.2f} ({os.cpu_count()} cores); "
          f"{'warm clusters (start excluded)' if args.warm else 'cluster start included'}")
    print("| workers | seconds | speed-up | efficiency | sum of seed seconds | "
          "sum of seed CPU s | best seed | best area | certified seeds |")
    print("|---|---|---|---|---|---|---|---|---|")
    for w, sec, res in rows:
        best = res.best
        print(f"| {w} | {sec:.1f} | {base / sec:.2f} | {base / sec * rows[0][0] / w:.2f} | "
              f"{sum(r.seconds for r in res.runs):.1f} | "
              f"{sum(r.cpu_seconds for r in res.runs):.1f} | "
              f"{'–' if best is None else best.seed} | "
              f"{'–' if best is None else f'{best.certified_area:.4g}'} | "
              f"{sum(r.certified for r in res.runs)}/{len(res.runs)} |")
    same = len({(None if r.best is None else r.best.seed) for _, _, r in rows}) == 1
    print(f"same choice on every worker count: {'yes' if same else 'NO'}")


if __name__ == "__main__":
    main()
