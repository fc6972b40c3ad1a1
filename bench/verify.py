"""Verifier benchmark: seconds, boxes and verdict for three queries.

(i)   2-D, 6-neuron tanh V with the true Van der Pol f on the annulus 0.2 ≤ ‖x‖ ≤ 1.2;
(ii)  the same V with a 200-neuron learned dynamics network inside the Lie derivative;
(iii) a 2×30 tanh V on Van der Pol, radius 2.5 (decrease on the annulus ∩ {V ≤ level});
(iv)  query (ii) with the pointwise robust decrease ∇V·φ + η·sqrt(‖∇V‖² + s²) < 0 of the
      learned-dynamics runs, η = 0.005, for s = 0 and s = 10⁻³·max‖∇V‖ (sampled).

Small queries first: the seed paper's three systems with networks of its published size
(2-6 tanh V: bench/data/vdp_V6.json for Van der Pol, no input; path following and pendulum:
V and the saturated controller of ``nlyap run NAME --preset fast --known-dynamics``, seed 0,
saved as bench/data/NAME_fast_V.json and NAME_fast_K.json), the true f, one query each: V > 0
and the decrease on the preset's annulus, as the paper hands it to dReal (dReal takes
0.06-0.15 s per such query; the bench has no per-system dReal figures and prints that range).
Printed per system: building the problem, the first verification (its graphs compiled in this
process), the warm verification (best of runs, wall and CPU), the verdict and boxes, and the
warm CPU seconds, verdict and boxes with the boundary pre-search (``presearch_boundary=500``:
points moved onto the annulus' circles tried before bisection; off by default).

Networks are made once (seeded) and cached in bench/data/; delete them to rebuild.
Targets on 2 cores: (i) ≤ 0.03 s, (ii) ≤ 0.04 s (≤ 0.1 s and ≥ 5× fewer boxes
than intervals with the mean-value form), (iii) ≤ 30 s.

Every query runs with the default verifier (affine arithmetic intersected with the interval
enclosure, splitting by the affine sensitivities) and, in the last two columns, with
``affine=False`` (interval enclosure ∩ mean-value form, splitting by the Jacobian's smear:
the verifier before the linear relaxation; ``--no-compare`` skips it).

    python bench/verify.py [--repeat 5] [--no-compare] [--small]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import casadi as ca
import numpy as np

import systems
from nlyap_opt.candidates.learning import LyapunovLearner, TrainConfig, sample_ball, sample_sphere
from nlyap_opt.certification.roa import candidate_level, certify_level
from nlyap_opt.kernel.network import Layer, Network
from nlyap_opt.kernel.symbolic import closed_loop, lie_derivative
from verification import closed_loop_problem, verify

DATA = Path(__file__).parent / "data"


def _train_V(name, hidden, features, outer, steps, seed=0) -> Network:
    path = DATA / f"{name}.json"
    if path.exists():
        return Network.load(path)
    s = systems.get("van_der_pol")
    cfg = TrainConfig(hidden=hidden, features=features, steps=steps, seed=seed)
    L = LyapunovLearner(s, None, None, cfg)
    rng = np.random.default_rng(seed)
    X = sample_ball(20000, 2, outer, rng)
    S = sample_sphere(2000, 2, outer, rng)
    L.train(X, S, 0.0)
    V, _ = L.export()
    return Network.load(V.save(path))


def _dynamics_200() -> Network:
    """A 2-200-2 tanh network fitted to Van der Pol on [-1.5, 1.5]² (random features + ridge)."""
    path = DATA / "vdp_phi_200.json"
    if path.exists():
        return Network.load(path)
    rng = np.random.default_rng(0)
    W0 = rng.normal(0, 1.0, (200, 2))
    b0 = rng.uniform(-1.5, 1.5, 200)
    Z = rng.uniform(-1.5, 1.5, (20000, 2))
    H = np.tanh(Z @ W0.T + b0)
    Y = systems.get("van_der_pol").evaluate(Z)
    H1 = np.hstack([H, np.ones((len(H), 1))])
    coef = np.linalg.solve(H1.T @ H1 + 1e-8 * np.eye(201), H1.T @ Y)
    net = Network([Layer(W0, b0, "tanh"), Layer(coef[:200].T, coef[200], "linear")],
                  meta={"kind": "dynamics", "fit": "random features + ridge, bench only"})
    err = np.abs(net.numpy(Z) - Y).max()
    net.meta["max_abs_error_on_fit_points"] = float(err)
    return Network.load(net.save(path))


def _timed(fn, repeat):
    """Best wall-clock and best CPU (process) seconds over ``repeat`` runs, and a result.

    CPU time is the steadier figure on a shared, loaded machine.
    """
    best, cpu, res = np.inf, np.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        c = time.process_time()
        res = fn()
        cpu = min(cpu, time.process_time() - c)
        best = min(best, time.perf_counter() - t)
    return (best, cpu), res


_PHASES = """
import time
t0 = time.perf_counter()
import systems
from nlyap_opt.kernel.network import Network
from verification import closed_loop_problem, verify
t1 = time.perf_counter()
V = Network.load({path!r})
p = closed_loop_problem(systems.get("van_der_pol"), V, inner=0.2, outer=1.2)
t2 = time.perf_counter()
r = verify(p)
t3 = time.perf_counter()
verify(p)
t4 = time.perf_counter()
print(t1 - t0, t2 - t1, t3 - t2, t4 - t3, r.status)
"""


def per_query(repeat: int) -> None:
    """Fixed costs of one small query in a fresh process: ``nlyap verify`` end to end, and
    its phases (imports, building the problem, the first and a second verification)."""
    import os
    import subprocess
    import sys

    env = dict(os.environ)
    cmd = [sys.executable, "-m", "nlyap_opt.interface.cli", "verify", "--system", "van_der_pol",
           "--lyapunov", str(DATA / "vdp_V6.json"), "--inner", "0.2", "--outer", "1.2"]
    walls, phases = [], []
    for _ in range(repeat):
        t = time.perf_counter()
        subprocess.run(cmd, check=True, capture_output=True, env=env)
        walls.append(time.perf_counter() - t)
        out = subprocess.run([sys.executable, "-c", _PHASES.format(path=str(DATA / "vdp_V6.json"))],
                             check=True, capture_output=True, text=True, env=env)
        phases.append([float(v) for v in out.stdout.split()[:4]])
    ph = np.min(np.array(phases), axis=0)
    print("Per query, query (i) in a fresh process (best of runs; seconds):")
    print("| `nlyap verify` end to end | imports | build the problem | first verify | "
          "second verify (warm) |")
    print("|---|---|---|---|---|")
    print(f"| {min(walls):.3f} | {ph[0]:.3f} | {ph[1]:.3f} | {ph[2]:.3f} | {ph[3]:.3f} |")
    print()


#: dReal's seconds per small query of the seed paper (a range over its systems, not per system)
DREAL_SMALL_QUERY = "0.06-0.15 s"

#: the seed paper's systems: (name, annulus inner, outer) of the fast presets (Van der Pol:
#: bench/verify.py's query (i))
SEED_SYSTEMS = (("van_der_pol", 0.2, 1.2), ("unicycle_path_following", 0.1, 0.8),
                ("inverted_pendulum", 0.4, 4.0))


def _seed_networks(name: str):
    """(V, κ or None) of published size for a seed-paper system (made once, cached)."""
    if name == "van_der_pol":
        return _train_V("vdp_V6", [6], 3, 1.4, 1500), None
    v_path, k_path = DATA / f"{name}_fast_V.json", DATA / f"{name}_fast_K.json"
    if not (v_path.exists() and k_path.exists()):
        import shutil
        import tempfile

        from nlyap_opt import make_config, run

        with tempfile.TemporaryDirectory() as tmp:
            res = run(systems.get(name), make_config(name, "fast"), tmp, known_dynamics=True,
                      log=lambda m: None)
            if not res.certified:
                raise SystemExit(f"{name}: the fast preset did not certify ({res.reason})")
            shutil.copyfile(Path(tmp) / "V.json", v_path)
            shutil.copyfile(Path(tmp) / "controller.json", k_path)
    return Network.load(v_path), Network.load(k_path)


def seed_queries(repeat: int) -> None:
    """One small query per seed-paper system (see the module's text)."""
    print("Small queries: the seed paper's systems, published-size networks, true f, "
          "V > 0 and decrease on the annulus (seconds; CPU s in brackets; last columns: "
          "warm, with presearch_boundary=500):")
    print("| system | annulus | build the problem | first verify | warm verify (best) | "
          "verdict | boxes | boundary pre-search: warm CPU s | verdict | boxes | "
          "dReal per query |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, inner, outer in SEED_SYSTEMS:
        s = systems.get(name)
        V, K = _seed_networks(name)
        (tb, cb), p = _timed(lambda s=s, V=V, K=K, inner=inner, outer=outer:
                             closed_loop_problem(s, V, K, inner=inner, outer=outer), 1)
        (tf, cf), _ = _timed(lambda p=p: verify(p), 1)
        (tw, cw), r = _timed(lambda p=p: verify(p), max(3, repeat))
        (_, cb2), r2 = _timed(lambda p=p: verify(p, presearch_boundary=500), max(3, repeat))
        print(f"| {name} | {inner:g} ≤ ‖x‖ ≤ {outer:g} | {tb:.4f} ({cb:.4f}) | {tf:.4f} "
              f"({cf:.4f}) | {tw:.4f} ({cw:.4f}) | {r.status} | {r.boxes} | {cb2:.4f} | "
              f"{r2.status} | {r2.boxes} | {DREAL_SMALL_QUERY} |")
    print()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--no-compare", dest="compare", action="store_false",
                    help="skip the runs without affine arithmetic")
    ap.add_argument("--small", action="store_true",
                    help="only the small queries of the seed paper's systems")
    args = ap.parse_args(argv)
    DATA.mkdir(exist_ok=True)
    if args.small:
        seed_queries(args.repeat)
        return
    s = systems.get("van_der_pol")
    V6 = _train_V("vdp_V6", [6], 3, 1.4, 1500)
    phi = _dynamics_200()
    V30 = _train_V("vdp_V30x30", [30, 30], 4, 2.5, 2500)
    seed_queries(args.repeat)
    per_query(max(1, args.repeat // 2))
    rows = []

    def run(p, repeat):
        """Default verifier, and (with --compare) without affine arithmetic."""
        t, r = _timed(lambda: verify(p), repeat)
        old = _timed(lambda: verify(p, affine=False), repeat) if args.compare else None
        return t, r, old

    p1 = closed_loop_problem(s, V6, inner=0.2, outer=1.2)
    rows.append(("(i) V 2-6 tanh, true f, 0.2≤‖x‖≤1.2", *run(p1, args.repeat), 0.03))

    # φ in place of f (the Van der Pol system has no input: φ takes (x) only, nu = 0)
    p2 = closed_loop_problem(s, V6, dynamics=phi, inner=0.2, outer=1.2, margin=0.01)
    rows.append(("(ii) same V, 200-neuron φ, margin 0.01", *run(p2, args.repeat), 0.1))

    x = ca.MX.sym("x", 2)
    grad = ca.Function("g", [x], [ca.gradient(V6.casadi(x), x)])
    pts = sample_ball(20000, 2, 1.2, np.random.default_rng(0))
    gmax = float(np.max(np.linalg.norm(np.array(grad(pts.T)), axis=0)))
    for smooth in (0.0, 1e-3 * gmax):
        p4 = closed_loop_problem(s, V6, dynamics=phi, inner=0.2, outer=1.2, eta=0.005,
                                 smoothing=smooth)
        rows.append((f"(iv) (ii) with η = 0.005 pointwise, s = {smooth:.2g}",
                     *run(p4, args.repeat), None))

    cl = closed_loop(s)
    Vx = V30.casadi(cl.x)
    lie = lie_derivative(Vx, cl.x, cl.rhs)
    cand = candidate_level(cl.x, Vx, lie, inner=0.2, outer=2.5)
    cert = certify_level(cl.x, Vx, lie, level=cand.level, inner=0.2, outer=2.5, margin=0.0,
                         log=lambda m: None)
    from verification import lyapunov_problem

    p3 = lyapunov_problem(cl.x, Vx, lie, inner=0.2, outer=2.5, level=cert.level)
    rows.append((f"(iii) V 2-30-30 tanh, r=2.5, level {cert.level:.4g}",
                 *run(p3, max(1, args.repeat // 5)), 30.0))

    print("| query | seconds (best of runs) | CPU s (best) | boxes | depth | verdict | target s "
          "| without affine: boxes | CPU s |")
    print("|---|---|---|---|---|---|---|---|---|")
    for label, (t, c), r, old, target in rows:
        tail = "– | –"
        if old is not None:
            (_, c_old), r_old = old
            assert r_old.status == r.status, (label, r_old.status, r.status)
            tail = f"{r_old.boxes} | {c_old:.4f}"
        print(f"| {label} | {t:.4f} | {c:.4f} | {r.boxes} | {r.depth} | {r.status} "
              f"| {'–' if target is None else f'≤ {target:g}'} | {tail} |")


if __name__ == "__main__":
    main()
