"""Where a distributed re-check spends its time: the schedule of each bisected check.

Re-checks the saved certificate in ``--certificate DIR`` as ``nlyap verify --certificate DIR
--workers W`` does (:func:`nlyap_opt.certification.certificate.recheck_certificate` inside
:func:`nlyap_opt.distributed.parallel.verifying_on`), once per worker count of
``--workers``, and prints for every check that bisects on the cluster
(:func:`nlyap_opt.distributed.parallel.verify_distributed`, its ``stats``):

- its wall seconds, boxes, tasks, the tasks' CPU seconds in all and per worker (least to
  most), and the driver's CPU seconds (this process: dealing open boxes out);
- from ``stats["timeline"]``: the time from the check's start to its last task absorbed,
  when each worker ran its first task and its last one, the driver's latency (a task's end
  on its worker to its absorption here: median and largest), and the busy workers in each
  tenth of the check (16 in every tenth is a perfect schedule on 16 workers).

    python bench/schedule.py --certificate DIR [--workers 1 16]

The figures of ``docs/distributed.md`` ("Where query (D)'s time goes on 16 workers") come from
this script with the certificate of ``bench/distributed_verify.py --certificate-only
--save-certificate DIR``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import nlyap_opt.distributed.parallel as par  # noqa: E402
from nlyap_opt.certification.certificate import recheck_certificate  # noqa: E402
from nlyap_opt.distributed.parallel import dask_client, verifying_on  # noqa: E402


def busy_profile(timeline: list, start: float, end: float, parts: int = 10) -> list[float]:
    """Busy workers (task seconds per second) in each of ``parts`` equal slices of
    ``[start, end]``, from a ``verify_distributed`` timeline."""
    span = max(end - start, 1e-9)
    out = []
    for i in range(parts):
        lo, hi = start + span * i / parts, start + span * (i + 1) / parts
        out.append(sum(max(0.0, min(e, hi) - max(s, lo)) for _, s, e, _, _ in timeline)
                   / (hi - lo))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--certificate", metavar="DIR", required=True)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 16])
    args = ap.parse_args()
    print("command: python bench/schedule.py " + " ".join(sys.argv[1:]))
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from distributed_verify import machine
    print(machine())
    path = Path(args.certificate) / "certificate.json"
    real = par.verify_distributed
    calls: list[dict] = []

    def recorded(problem, client, **options):
        st = options.pop("stats", None)
        st = {} if st is None else st
        t, c = time.time(), time.process_time()
        r = real(problem, client, stats=st, **options)
        calls.append({"start": t, "wall": time.time() - t,
                      "driver": time.process_time() - c, "boxes": r.boxes, "stats": st})
        return r

    par.verify_distributed = recorded
    try:
        for W in args.workers:
            with dask_client(workers=W) as client, verifying_on(client):
                client.submit(sum, [1]).result()  # the workers are up
                calls.clear()
                t = time.perf_counter()
                cert = recheck_certificate(path, log=lambda m: None)
                wall = time.perf_counter() - t
            print(f"\n{W} worker(s): re-check {wall:.2f} s, certified {cert.certified}, load "
                  f"average {os.getloadavg()[0]:.1f}")
            for k, c in enumerate(calls):
                st, tl = c["stats"], c["stats"].get("timeline", [])
                per = sorted(st.get("cpu_by_worker", {}).values())
                cpu = sum(per) + (st.get("root_cpu") or 0.0)
                print(f"  check {k + 1}: {c['wall']:.2f} s, {c['boxes']} boxes, "
                      f"{st.get('tasks')} tasks, tasks' CPU {cpu:.2f} s "
                      f"(per worker {per[0] if per else 0:.2f} to {per[-1] if per else 0:.2f}), "
                      f"driver CPU {c['driver']:.2f} s")
                if not tl:
                    continue
                t0 = c["start"]
                end = max(a for *_, a, _ in tl)
                first, last = {}, {}
                for pid, s, e, _, _ in tl:
                    first[pid] = min(first.get(pid, s), s)
                    last[pid] = max(last.get(pid, e), e)
                lat = sorted(a - e for _, _, e, a, _ in tl)
                print(f"    to the last task absorbed {end - t0:.2f} s; first tasks start "
                      f"{min(first.values()) - t0:.2f} to {max(first.values()) - t0:.2f} s, "
                      f"last ones end {min(last.values()) - t0:.2f} to "
                      f"{max(last.values()) - t0:.2f} s; driver latency median "
                      f"{1e3 * lat[len(lat) // 2]:.1f} ms, largest {1e3 * lat[-1]:.1f} ms")
                print("    busy workers per tenth: " + " ".join(
                    f"{u:.1f}" for u in busy_profile(tl, t0, end)))
    finally:
        par.verify_distributed = real


if __name__ == "__main__":
    main()
