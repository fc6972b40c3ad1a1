"""Distributed verification benchmark: measured on 1 and 2 Dask workers, modelled up to 16.

Two certificate queries, each decided serially (``verification.verify``), then by
:func:`nlyap_opt.distributed.parallel.verify_distributed` on a ``LocalCluster`` of 1 and of 2
workers, and by the executor hook ``verify(problem, executor=client.get_executor())`` (a fixed split
into ``n_tasks`` sub-boxes) for comparison:

(A) 4-D: two coupled reversed Van der Pol oscillators, a quadratic V with a 64-neuron tanh
    factor, decrease on 0.1 ≤ ‖x‖ ≤ 1.1 (about 6·10⁴ boxes serially);
(B) 2-D: bench/verify.py's 2-30-30 tanh V on Van der Pol, r = 2.5, at 0.99 × the IPOPT
    candidate level (bench/data/vdp_V30x30.json; run bench/verify.py once to create it);
(C) 4-D: the cartpole's LQR quadratic certificate, decrease on the true f
    (``bench/scale.py``'s query, ball ``r``), with the second-order form as its preset.

(D) 4-D: the certificate of ``nlyap run cartpole --preset large --known-dynamics`` (the
    round quadratic under the saturated LQR controller, conditions (a), (b), (c) at the level
    its search certifies, found first, serially, and saved), re-checked as ``nlyap verify
    --certificate DIR [--workers W]`` does:
    :func:`nlyap_opt.certification.certificate.recheck_certificate` serially and inside
    :func:`nlyap_opt.distributed.parallel.verifying_on` (every check on the cluster).
    ``--no-certificate`` skips it (about 3 minutes). ``--save-certificate DIR`` keeps the
    saved certificate in DIR; ``--certificate DIR`` re-checks the one saved there instead of
    certifying it first (e.g. on another machine: a re-check is how a shared certificate is
    trusted).

Seconds are the best of ``--repeat`` runs (cluster start-up excluded). Figures are printed,
not asserted; on a shared machine read them with the load average printed beside them.

*Measured* rows (a real ``LocalCluster``) give the efficiency (speed-up per worker) on the
worker counts this machine has. *Modelled* rows (``--model 4 8 16``) come from
:class:`nlyap_opt.distributed.parallel.SimulatedCluster`: the same task graph that
``verify_distributed`` builds for W workers, run task by task in this process and list-scheduled on
W virtual workers; the cost of a task is the boxes it processed (deterministic) or its CPU seconds
here (which include each walker pass's fixed cost). For (D) the CPU model adds the recheck's
CPU seconds outside the tasks (loading, building the checks) to every worker count and
prints, per check, its modelled seconds on one and on the most workers; it runs ``--repeat``
times (one run's CPU outside the tasks may hold a full garbage collection of this
process) and the run of the median speed-up is printed. As on a cluster,
condition (c) runs beside (a) and (b) (and a saved shell form's two checks side by side):
their tasks share the virtual workers in modelled time. The model leaves out the
scheduler's latency per task (a few ms) and contention between the workers for memory and
caches (it counts each task's CPU seconds on this machine). Each query's
:func:`nlyap_opt.distributed.parallel.pass_boxes` (the least start of a task on more than two
workers) is printed with its modelled rows. ``--workers`` with no count: the model only.

The first lines printed name the command, the machine (CPU model, cores this process may
use) and the load average, which the figures depend on.

    python bench/distributed_verify.py [--repeat 3] [--workers 1 2] [--cartpole-r 0.5]
                                       [--no-certificate | --certificate-only]
                                       [--model 4 8 16]
                                       [--save-certificate DIR | --certificate DIR]
                                       [--proof | --proof-file FILE]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import casadi as ca
import numpy as np

import systems
from nlyap_opt.distributed.parallel import (
    _starts_from_boxes,
    cpu_cores,
    dask_client,
    model_speedups,
    pass_boxes,
    verify_distributed,
)
from nlyap_opt.kernel.network import Network
from verification import lyapunov_problem, verify

DATA = Path(__file__).parent / "data"


def problem_4d(outer: float = 1.1, neurons: int = 16):
    """Two coupled reversed Van der Pol oscillators; ``V = xᵀ(I₂⊗P)x·(1 + 0.05·aᵀtanh(Wx+b)/4)``
    with ``neurons`` tanh units."""
    x = ca.MX.sym("x", 4)
    P = np.array([[1.5, -0.5], [-0.5, 1.0]])

    def vdp(a, b):
        return ca.vertcat(-b, a - (1 - a**2) * b)

    f = ca.vertcat(vdp(x[0], x[1]), vdp(x[2], x[3])) + 0.1 * ca.vertcat(
        x[2] * x[1], 0, -x[0] * x[3], 0)
    rng = np.random.default_rng(0)
    W, b = rng.normal(0, 1, (neurons, 4)), rng.normal(0, 0.5, neurons)
    a = rng.normal(0, 1, neurons) * np.sqrt(16 / neurons)
    h = ca.tanh(ca.mtimes(ca.DM(W), x) + ca.DM(b))
    V = ca.bilin(ca.DM(np.kron(np.eye(2), P)), x, x) * (1 + 0.05 * ca.dot(ca.DM(a), h) / 4)
    lie = ca.dot(ca.gradient(V, x), f)
    return lyapunov_problem(x, V, lie, inner=0.1, outer=outer)


def problem_vdp30():
    from nlyap_opt.certification.roa import candidate_level
    from nlyap_opt.kernel.symbolic import closed_loop, lie_derivative

    path = DATA / "vdp_V30x30.json"
    if not path.exists():
        return None
    cl = closed_loop(systems.get("van_der_pol"))
    Vx = Network.load(path).casadi(cl.x)
    lie = lie_derivative(Vx, cl.x, cl.rhs)
    cand = candidate_level(cl.x, Vx, lie, inner=0.2, outer=2.5)
    return lyapunov_problem(cl.x, Vx, lie, inner=0.2, outer=2.5, level=0.99 * cand.level)


def cartpole_certificate():
    """(problem, level) of the cartpole large preset's certificate with the true f: the round
    quadratic at the level :func:`nlyap_opt.candidates.quadratic.certify_quadratics` certifies."""
    from dataclasses import replace

    from nlyap_opt.candidates.quadratic import certify_quadratics
    from nlyap_opt.certification.certificate import RoaProblem
    from nlyap_opt.design.control import lqr, quadratic_lyapunov, saturated_controller
    from nlyap_opt.workflow.configs import domain_of, make_config

    s = systems.get("cartpole")
    cfg = make_config("cartpole", "large")
    res = lqr(s, cfg["lqr"]["Q"], cfg["lqr"]["R"])
    base = RoaProblem(s, quadratic_lyapunov(res.P),
                      saturated_controller(s, res.K, cfg["controller_scale"]),
                      inner=float(cfg["inner"]), domain=domain_of(cfg, s.nx)[0],
                      verify_options=cfg["cegis"]["verify_options"])
    [cand] = certify_quadratics(base, ["round"], box=cfg["eval_box"], n=4, log=lambda m: None)
    cert = cand.certificate
    if not cert.certified:
        raise SystemExit(f"query (D): the round quadratic was not certified ({cert.reason})")
    return replace(base, V=quadratic_lyapunov(cand.P), inner=cert.inner), cert.level


def certificate_rows(workers, repeat, model=(), saved=None, keep=None, proof=False,
                     proof_file=None):
    """Seconds of ``nlyap verify --certificate`` on query (D): serial, then on clusters of
    ``workers`` (:func:`nlyap_opt.certification.certificate.recheck_certificate` of the saved
    certificate, inside :func:`nlyap_opt.distributed.parallel.verifying_on` as the CLI runs it); the
    model on
    ``model`` workers; ``saved``: the directory of a saved certificate to re-check instead
    (not certified here); ``keep``: a directory to save the certificate into; ``proof``:
    record the re-check's proof (its checks' bisection trees,
    :class:`nlyap_opt.distributed.parallel.Proofs`) by a serial re-check first, and time
    every row with it, as ``nlyap verify --certificate DIR --proof FILE`` runs;
    ``proof_file``: the same with the proof read from that file (recorded elsewhere)."""
    import contextlib
    import tempfile

    from nlyap_opt.certification.certificate import (
        certify_roa,
        recheck_certificate,
        save_certificate,
    )
    from nlyap_opt.distributed.parallel import Proofs, proving, verifying_on

    if saved is None:
        problem, level = cartpole_certificate()
        cert = certify_roa(problem, level, log=lambda m: None)
        if not cert.certified:
            raise SystemExit(f"query (D): not certified at level {level:g} ({cert.reason})")
    where = contextlib.nullcontext(saved or keep) if (saved or keep) else \
        tempfile.TemporaryDirectory()
    with where as tmp:
        path = Path(tmp) / "certificate.json" if saved else save_certificate(cert, problem, tmp)
        if saved:
            cert = recheck_certificate(path, log=lambda m: None)
            if not cert.certified:
                raise SystemExit(f"query (D): {path} does not re-check ({cert.reason})")
            level = cert.level

        proofs = None
        if proof_file:
            proofs = Proofs.load(proof_file)
            print(f"(D) proof read from {proof_file} ({len(proofs.trees)} bisected checks); "
                  "every row below starts from it")
        elif proof:
            proofs = Proofs(record=True)
            t = time.perf_counter()
            with proving(proofs):
                recheck_certificate(path, log=lambda m: None)
            proofs.record = False
            print(f"(D) proof recorded by a serial re-check in {time.perf_counter() - t:.2f} s "
                  f"({len(proofs.trees)} bisected checks); every row below starts from it")

        def once():  # reads the artifacts again: no compiled check is reused between timings
            with proving(proofs):
                return recheck_certificate(path, log=lambda m: None)

        rows = [("serial", *_best(once, repeat))]
        for w in workers:
            with dask_client(workers=w) as client, verifying_on(client):
                client.submit(sum, [1]).result()  # workers up
                rows.append((w, *_best(once, repeat)))
                print(f"(D) {w} workers, every run: "
                      + ", ".join(f"{t:.2f}" for t in _best.last) + " s", flush=True)
        modelled = {}
        other = 0.0
        if model:
            cpu_total = {}

            per_check: dict = {}

            def run(sim, cpu_total=cpu_total, per_check=per_check):
                t = time.process_time()
                with verifying_on(sim):
                    once()
                # as the run would spend it: the compiles timed for the model are its own,
                # those charged to the workers' first tasks are in the tasks' CPU
                cpu_total[sim.workers] = time.process_time() - t - sim.modelling_seconds + \
                    sim.compile_seconds
                per_check[(sim.cost, sim.workers)] = list(sim.calls)

            modelled["boxes"] = model_speedups(run, model, cost="boxes")
            # by CPU s, ``repeat`` times: one run's CPU outside the tasks can hold a full
            # garbage collection of this process (about 0.1 s beside some 0.15 s); the run
            # of the median speed-up on the most workers is the one printed
            tries = []
            for _ in range(max(1, repeat)):
                m = model_speedups(run, model, cost="cpu")
                # the CPU outside the tasks, on every worker count
                other = max(0.0, cpu_total[1] - m[1]["work"])
                one = other + m[1]["makespan"]
                for w, row in m.items():
                    row["speedup"] = one / (other + row["makespan"])
                    row["efficiency"] = row["speedup"] / w
                tries.append((m[max(m)]["speedup"], other, m, dict(per_check)))
            tries.sort(key=lambda t: t[0])
            _, other, modelled["cpu"], per_check = tries[(len(tries) - 1) // 2]
            if len(tries) > 1:
                print(f"(D) MODELLED on {max(modelled['cpu'])} workers by CPU s, each of "
                      f"{len(tries)} runs: " + ", ".join(f"{t[0]:.2f}" for t in tries)
                      + "; the median run is printed")
    print(f"(D) cartpole certificate (round quadratic, level {level:.6g}, ε = "
          f"{cert.inner:g}, (c) by the {cert.inner_ellipse.form} form): "
          "nlyap verify --certificate, conditions (a), (b), (c) re-checked")
    print("| workers | how | seconds (best) | speed-up vs 1 worker | efficiency | status |")
    print("|---|---|---|---|---|---|")
    one = [t for w, t, _ in rows if w == 1]
    for w, t, c in rows:
        up = one[0] / t if one and w != "serial" else None
        eff = f"{up / w:.2f}" if up else "–"
        print(f"| {w} | measured | {t:.2f} | {f'{up:.2f}' if up else '–'} | {eff} | "
              f"{c.status.value} |")
    _print_model(modelled)
    if modelled:
        top = max(modelled["cpu"])
        one, many = per_check[("cpu", 1)], per_check[("cpu", top)]
        print(f"MODELLED per check, in the order they end on 1 worker (CPU s; checks that "
              f"run side by side overlap): on 1 worker | on {top} workers, modelled start and "
              "end (tasks)")
        print(f"| check | 1 worker | {top} workers | start | end | tasks | speed-up |")
        print("|---|---|---|---|---|---|---|")
        left = list(many)
        for i, a in enumerate(one):
            # the same check on many workers: the call that processed as many boxes
            b = next((c for c in left if c["boxes"] == a["boxes"]), None)
            if b is None:
                continue
            left.remove(b)
            print(f"| {i + 1} | {a['makespan']:.2f} | {b['makespan']:.2f} | "
                  f"{b['start']:.2f} | {b['start'] + b['makespan']:.2f} | {b['tasks']} | "
                  f"{a['makespan'] / max(b['makespan'], 1e-12):.2f} |")
        for w in sorted(modelled["cpu"]):
            row = modelled["cpu"][w]
            print(f"MODELLED {w} workers: {row['makespan']:.2f} s of tasks (+ {other:.2f} CPU s "
                  f"outside them), the tasks' CPU {row['work']:.2f} s in all")
    print()


def _print_model(modelled):
    """Rows of modelled speed-ups (boxes and CPU cost) per worker count."""
    if not modelled:
        return
    for w in sorted(modelled["boxes"]):
        b, c = modelled["boxes"][w], modelled["cpu"][w]
        print(f"| {w} | MODELLED (tasks: {b['tasks']}) | – | {b['speedup']:.2f} by boxes, "
              f"{c['speedup']:.2f} by CPU s | {b['efficiency']:.2f}, {c['efficiency']:.2f} "
              "| – |")


def machine() -> str:
    """The CPU model, the cores this process may use and the load average, in one line."""
    model = platform.processor() or "unknown CPU"
    try:
        with open("/proc/cpuinfo") as f:
            model = next((ln.split(":", 1)[1].strip() for ln in f
                          if ln.startswith("model name")), model)
    except OSError:
        pass
    return (f"machine: {model}, {cpu_cores()} cores usable; load average "
            f"{os.getloadavg()[0]:.2f}")


def _best(fn, repeat):
    """The least seconds of ``repeat`` calls and the last result (``_best.last``: every
    call's seconds)."""
    best, res = np.inf, None
    _best.last = []
    for _ in range(repeat):
        t = time.perf_counter()
        res = fn()
        _best.last.append(time.perf_counter() - t)
        best = min(best, _best.last[-1])
    return best, res


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--workers", type=int, nargs="*", default=[1, 2],
                    help="worker counts to measure on a LocalCluster (none: model only)")
    ap.add_argument("--n-tasks", type=int, default=8, help="sub-boxes of the executor hook")
    ap.add_argument("--cartpole-r", type=float, default=0.5,
                    help="ball radius of query (C)")
    only = ap.add_mutually_exclusive_group()
    only.add_argument("--no-certificate", action="store_true",
                      help="skip query (D), the cartpole certificate (about 3 minutes)")
    only.add_argument("--certificate-only", action="store_true",
                      help="query (D) alone (skip queries (A) to (C))")
    ap.add_argument("--model", type=int, nargs="*", default=[],
                    help="worker counts to model (SimulatedCluster), e.g. 4 8 16; each "
                         "costs a serial run per cost measure")
    where = ap.add_mutually_exclusive_group()
    where.add_argument("--save-certificate", metavar="DIR",
                       help="keep query (D)'s certificate in DIR")
    where.add_argument("--certificate", metavar="DIR",
                       help="re-check the certificate saved in DIR as query (D)")
    proof = ap.add_mutually_exclusive_group()
    proof.add_argument("--proof", action="store_true",
                       help="query (D) with a proof: recorded by a serial re-check, then used "
                            "by every row (nlyap verify --certificate DIR --proof FILE)")
    proof.add_argument("--proof-file", metavar="FILE",
                       help="query (D) with the proof in FILE (nlyap verify --certificate DIR "
                            "--save-proof FILE, here or on another machine)")
    args = ap.parse_args(argv)
    print("command: python bench/distributed_verify.py " + " ".join(sys.argv[1:] if argv is None
                                                                   else argv))
    print(machine())
    if not args.no_certificate:
        if args.save_certificate:
            Path(args.save_certificate).mkdir(parents=True, exist_ok=True)
        certificate_rows(args.workers, args.repeat, args.model, saved=args.certificate,
                         keep=args.save_certificate, proof=args.proof,
                         proof_file=args.proof_file)
        print(f"after (D): load average {os.getloadavg()[0]:.2f}")
    if args.certificate_only:
        return
    queries = [("(A) 4-D, 64-neuron V factor", problem_4d(1.1, 64), {})]
    p = problem_vdp30()
    if p is not None:
        queries.append(("(B) 2-D, V 2-30-30, r = 2.5", p, {}))
    from scale import quadratic_queries  # bench/scale.py, beside this file

    cp = quadratic_queries(systems.get("cartpole"), args.cartpole_r)[0]["true f"]
    queries.append((f"(C) 4-D cartpole LQR, r = {args.cartpole_r:g}", cp,
                    {"second_order": True}))
    mode = "batched hand-out of open boxes" if _starts_from_boxes() else \
        "fixed split (verify_interval has no boxes=)"
    print(f"verify_distributed mode: {mode}; load average: {os.getloadavg()[0]:.2f}")
    rows, balance = [], []
    for label, prob, opt in queries:
        t, r = _best(lambda prob=prob, opt=opt: verify(prob, **opt), args.repeat)
        rows.append((label, "serial verify()", "–", t, r))
    for w in args.workers:
        with dask_client(workers=w) as client:
            client.submit(sum, [1]).result()  # workers up
            for label, prob, opt in queries:
                st: dict = {}
                t, r = _best(lambda prob=prob, st=st, opt=opt: verify_distributed(
                    prob, client, stats=st, **opt), args.repeat)
                rows.append((label, "verify_distributed", w, t, r))
                by = list(st["cpu_by_worker"].values()) or [0.0]
                balance.append((label, w, st["tasks"], st["root_cpu"], sum(by), max(by)))
                t, r = _best(lambda prob=prob, opt=opt: verify(
                    prob, executor=client.get_executor(), n_tasks=args.n_tasks, **opt),
                    args.repeat)
                rows.append((label, f"executor hook, n_tasks={args.n_tasks}", w, t, r))
    print("| query | how | workers | seconds (best) | speed-up vs 1 worker | efficiency | "
          "boxes | verdict |")
    print("|---|---|---|---|---|---|---|---|")
    for label, how, w, t, r in rows:
        one = [t1 for lb, h, w1, t1, _ in rows if lb == label and h == how and w1 == 1]
        up = one[0] / t if one and w != "–" else None
        print(f"| {label} | {how} (measured) | {w} | {t:.2f} | "
              f"{f'{up:.2f}' if up else '–'} | {f'{up / w:.2f}' if up else '–'} | "
              f"{r.boxes} | {r.status} |")
    if args.model:
        print()
        print("MODELLED speed-ups (SimulatedCluster: the task graph of W workers, "
              "list-scheduled; cost = boxes | CPU s here):")
        print("| query | workers | tasks | speed-up (boxes) | efficiency (boxes) | "
              "speed-up (CPU s) | efficiency (CPU s) |")
        print("|---|---|---|---|---|---|---|")
        for label, prob, opt in queries:
            mb, mc = (model_speedups(lambda c, prob=prob, opt=opt: verify_distributed(
                prob, c, **opt), args.model, cost=cost) for cost in ("boxes", "cpu"))
            print(f"| {label} (pass_boxes {pass_boxes(prob)}) | | | | | | |")
            for w in sorted(mb):
                print(f"| {label} | {w} | {mb[w]['tasks']} | {mb[w]['speedup']:.2f} | "
                      f"{mb[w]['efficiency']:.2f} | {mc[w]['speedup']:.2f} | "
                      f"{mc[w]['efficiency']:.2f} |")
    print()
    print("Load balance of verify_distributed from the tasks' CPU seconds (last run; other "
          "load on the machine does not enter): the root task runs alone, then the rest is "
          "dealt out; ideal speed-up = (root + Σ workers) / (root + max worker).")
    print("| query | workers | tasks | root CPU s | tasks CPU s (Σ) | busiest worker CPU s | "
          "ideal speed-up |")
    print("|---|---|---|---|---|---|---|")
    for label, w, n, root, tot, top in balance:
        print(f"| {label} | {w} | {n} | {root:.2f} | {tot:.2f} | {top:.2f} | "
              f"{(root + tot) / (root + top):.2f} |")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
