"""How much slower one worker's verification gets when every core runs one: the ceiling of a
Dask speed-up on this machine.

A speed-up on W workers is at most W divided by the factor by which each worker's CPU
seconds per box grow when W of them run at once (caches, memory bandwidth and clock shared
by the cores), before any scheduling loss. This bench measures that factor directly: the
same verification task (the serial verifier from the root box until ``--budget`` boxes are
processed, batched as ``--batch``) run alone on one Dask worker, then as W identical copies
at once on W workers; it prints the CPU microseconds per box of each (median and slowest
copy) and their ratio, each the best of ``--repeat`` rounds.

The task is the decrease check of the saved certificate given by ``--certificate DIR`` (the
first check its re-check decides by bisection, e.g. query (D) of
``bench/distributed_verify.py``), or, without it, query (A) of that bench (two coupled Van
der Pol oscillators, 4-D).

    python bench/contention.py [--certificate DIR] [--workers W] [--copies 1 4 8 16]
                               [--budget 20000] [--batch 8192 2048] [--repeat 3]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import nlyap_opt.distributed.parallel as par  # noqa: E402
from nlyap_opt.distributed.parallel import cpu_cores, dask_client  # noqa: E402
from verification.verify import verify_interval  # noqa: E402

#: verifier options of a captured check that a plain serial run takes over
_KEPT = ("resolution", "mean_value", "affine", "second_order", "seed", "initial_boxes",
         "stop_at_first")


class _Captured(Exception):
    pass


def certificate_check(path: str):
    """``(problem, options)`` of the first check a re-check of the certificate at ``path``
    hands to a cluster (captured; the re-check stops there)."""
    from nlyap_opt.certification.certificate import recheck_certificate

    got = []

    def capture(problem, client, **options):
        got.append((problem, {k: v for k, v in options.items() if k in _KEPT}))
        raise _Captured

    real = par.verify_distributed
    par.verify_distributed = capture
    try:
        with par.verifying_on(object()):
            try:
                recheck_certificate(Path(path) / "certificate.json", log=lambda m: None)
            except _Captured:
                pass
    finally:
        par.verify_distributed = real
    if not got:
        sys.exit(f"the re-check of {path} hands no check to a cluster (nothing bisects)")
    return got[0]


def _task(problem, options: dict, budget: int, batch: int):
    t = time.thread_time()
    r = verify_interval(problem, max_boxes=budget, presearch=0, **dict(options, batch=batch))
    return r.boxes, time.thread_time() - t


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--certificate", metavar="DIR")
    ap.add_argument("--workers", type=int, default=cpu_cores(),
                    help="the cluster's workers (default: the cores usable)")
    ap.add_argument("--copies", type=int, nargs="+",
                    help="copies run at once, each count in turn (default: 1 and --workers)")
    ap.add_argument("--budget", type=int, default=20000)
    ap.add_argument("--repeat", type=int, default=3,
                    help="rounds per row; the row shows the round of the least median")
    ap.add_argument("--batch", type=int, nargs="+", default=[8192, 2048])
    args = ap.parse_args()
    print("command: python bench/contention.py " + " ".join(sys.argv[1:]))
    from distributed_verify import machine
    print(machine())
    if args.certificate:
        problem, options = certificate_check(args.certificate)
        what = f"the first bisected check of {args.certificate}"
    else:
        from distributed_verify import problem_4d
        problem, options = problem_4d(), {}
        what = "query (A) of bench/distributed_verify.py"
    copies = sorted(set([1] + (args.copies or [args.workers])))
    W = max(args.workers, *copies)
    print(f"task: {what}, {problem.n}-D, the serial verifier from the root box for "
          f"{args.budget} boxes")
    print("| batch | copies at once | boxes | CPU µs per box (median) | slowest copy | "
          "vs alone |")
    print("|---|---|---|---|---|---|")
    if options.get("second_order"):
        problem.second_order_functions  # built before pickling: the workers get them
    with dask_client(workers=W) as client:
        [pf] = client.scatter([problem], broadcast=True, hash=False)
        # every worker runs the task once first (compiling the problem's graphs, warming its
        # caches): not measured
        client.gather([client.submit(_task, pf, options, args.budget, b, pure=False,
                                     workers=[w], allow_other_workers=False)
                       for w in client.scheduler_info()["workers"] for b in args.batch])
        for batch in args.batch:
            alone = None
            for k in copies:
                rounds = []
                for _ in range(max(1, args.repeat)):
                    res = client.gather([client.submit(_task, pf, options, args.budget, batch,
                                                       pure=False) for _ in range(k)])
                    per = sorted(1e6 * c / b for b, c in res)
                    rounds.append((per[len(per) // 2], per))
                med, per = min(rounds)
                alone = med if alone is None else alone
                print(f"| {batch} | {k} | {res[0][0]} | {med:.1f} | {per[-1]:.1f} | "
                      f"{med / alone:.2f}× |", flush=True)
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
