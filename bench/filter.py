"""CLF-QP safety filter benchmark: microseconds per OSQP solve on a 4-D cartpole certificate.

Reads a certified run directory (``nlyap run cartpole --preset fast --known-dynamics
--config CFG --out DIR``, CFG = ``{"quadratic": ["round", "lyapunov"], "cegis":
{"iterations": 1}}``, about a minute), or, without one, proves the cartpole's LQR quadratic
on a small ball (seconds) into a temporary directory. Samples the certified set (seeded),
and times, per state outside the inner ellipse: the OSQP update and solve (the problem set
up once, warm-started), and the whole filter call (the CasADi pieces ∇V, f₀, g, κ of one
state, then the QP). Prints the CPU model, the command and the figures; the mathematics
(feasibility, the decrease kept) is tested in tests/test_deploy.py.

    python bench/filter.py [RUN_DIR] [--points 20000] [--nominal random|zero]
"""

from __future__ import annotations

import argparse
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _small_cartpole(out: Path) -> Path:
    import systems
    from nlyap_opt.certification.certificate import RoaProblem, certify_roa, save_certificate
    from nlyap_opt.design.control import linear_controller, lqr, quadratic_lyapunov

    s = systems.get("cartpole")
    res = lqr(s)
    ev = np.linalg.eigvalsh(res.P)
    r = 0.05
    level = 0.9 * ev[0] * r**2
    problem = RoaProblem(s, quadratic_lyapunov(res.P), linear_controller(s, res.K),
                         inner=0.5 * np.sqrt(level / ev[-1]), outer=r,
                         verify_options={"max_boxes": 100_000, "second_order": True})
    cert = certify_roa(problem, level, log=lambda m: None)
    assert cert.certified, cert.reason
    save_certificate(cert, problem, out)
    return out


def main(argv=None) -> None:
    from nlyap_opt.deployment.deploy import load_run
    from nlyap_opt.deployment.filter import ClfQpFilter

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", nargs="?", help="a certified run (default: a small cartpole "
                                               "certificate proved here)")
    ap.add_argument("--points", type=int, default=20_000)
    ap.add_argument("--nominal", choices=["random", "zero"], default="random",
                    help="random: N(0, 30²) inputs (the box and the constraint active); "
                         "zero: no force")
    args = ap.parse_args(argv)
    tmp = None
    d = args.run_dir
    if d is None:
        tmp = tempfile.TemporaryDirectory()
        d = _small_cartpole(Path(tmp.name))
    run = load_run(d, log=lambda m: None)
    rng = np.random.default_rng(0)
    pts = run.sample(args.points, rng)
    E = run.certificate.inner_ellipse
    pts = pts[~E.contains(pts)] if E is not None else pts
    nu = run.system.nu
    un = 30.0 * rng.standard_normal((len(pts), nu)) if args.nominal == "random" \
        else np.zeros((len(pts), nu))
    filt = ClfQpFilter(run, lambda x: un[:len(x)])
    a, e, dd, k = filt.pieces(pts)
    times = np.empty(len(pts))
    statuses: dict[str, int] = {}
    for i in range(len(pts)):
        t0 = time.perf_counter()
        _, st = filt.solve(a[i], e[i], dd[i], k[i], un[i])
        times[i] = time.perf_counter() - t0
        statuses[st] = statuses.get(st, 0) + 1
    n_call = min(len(pts), 2000)
    t0 = time.perf_counter()
    for i in range(n_call):
        filt(pts[i:i + 1])
    per_call = (time.perf_counter() - t0) / n_call
    print(f"command: python {' '.join(['bench/filter.py'] + list(argv or sys.argv[1:]))}")
    print(f"machine: {_cpu()}, {platform.system()} {platform.release()}, "
          f"Python {platform.python_version()}")
    print(f"run: {run.directory} ({run.system.name}, nx = {run.system.nx}, nu = {nu}, "
          f"level {run.level:.6g}); {len(pts)} states of Ω_c outside E; nominal {args.nominal}")
    print(f"OSQP update + solve: median {1e6 * np.median(times):.1f} µs, mean "
          f"{1e6 * times.mean():.1f} µs, 99th percentile {1e6 * np.quantile(times, 0.99):.1f} µs")
    print(f"whole filter call (CasADi pieces of one state + QP): {1e6 * per_call:.1f} µs")
    print(f"OSQP statuses: {statuses}; answers replaced by κ: {filt.stats.fallback}")
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()
