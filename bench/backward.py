"""Backward linear bound propagation (``verify(..., backward=True)``) against the forward
affine forms alone.

Part 1, enclosures: seeded random tanh networks V (two hidden layers of 32 in 4-D and 6-D,
of 30 in 2-D) and one-layer tanh controllers (16 units, weights scaled by 0.3), closed
with the cartpole's, the planar quadrotor's and Van der Pol's true f; 1000 random boxes of
side ``w`` in [-0.5, 0.5]^n. Printed: the median over boxes of (upper bound - largest of
34 sampled values) of V and of ∇V·f, for the forward affine forms, for their meet with
the backward bound, and for the backward bound with ``--slope-steps`` optimisation steps
of its slopes (α-CROWN style), and the seconds of one pass of each over the 1000 boxes.

Part 2, verification: the queries of ``bench/verify.py`` (seed-paper networks, the
200-neuron φ, the 2-30-30 V, the 4-D coupled oscillators) with the default verifier, with
``backward=True`` and with ``backward=True, slope_steps=K``: boxes and CPU seconds (best
of ``--repeat``).

    python bench/backward.py [--repeat 3] [--part 1 2] [--slope-steps 20]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import casadi as ca
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

import systems  # noqa: E402
from nlyap_opt.kernel.network import Layer, Network  # noqa: E402
from nlyap_opt.kernel.symbolic import closed_loop, lie_derivative  # noqa: E402
from nlyap_opt.kernel.walker import evaluate  # noqa: E402
from verification import closed_loop_problem, lyapunov_problem, verify  # noqa: E402
from verification.affine import Affine, AffineArithmetic  # noqa: E402
from verification.backward import backward_bounds  # noqa: E402


def _net(rng, sizes, scale=1.0) -> Network:
    layers = []
    for a, b in zip(sizes[:-1], sizes[1:]):
        act = "linear" if b == sizes[-1] else "tanh"
        layers.append(Layer(rng.normal(size=(b, a)) / np.sqrt(a) * scale,
                            rng.normal(size=b) * 0.1, act))
    return Network(layers)


def enclosures(steps: int) -> None:
    rng = np.random.default_rng(1)
    print(f"| system | V, κ | w | V: affine | V: with backward | V: {steps} slope steps | "
          f"∇V·f: affine | ∇V·f: with backward | ∇V·f: {steps} slope steps | s affine | "
          "s backward | s slopes |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name, Vs, Ks in (("cartpole", [4, 32, 32, 1], [4, 16, 1]),
                         ("planar_quadrotor", [6, 32, 32, 1], [6, 16, 2]),
                         ("van_der_pol", [2, 30, 30, 1], None)):
        s = systems.get(name)
        V = _net(rng, Vs)
        K = _net(rng, Ks, 0.3) if Ks else None
        with warnings.catch_warnings():  # a random κ need not vanish at 0: only bounds here
            warnings.simplefilter("ignore")
            cl = closed_loop(s, K, strict=False)
        Vx = V.casadi(cl.x)
        F = ca.Function("F", [cl.x], [ca.vertcat(Vx, lie_derivative(Vx, cl.x, cl.rhs))])
        n = s.nx
        for w in (0.2, 0.05):
            B, S = 1000, 32
            c = rng.uniform(-0.5, 0.5, size=(B, n))
            lo, hi = c - w / 2, c + w / 2
            t = time.perf_counter()
            aff = evaluate(F, [Affine.from_box(lo, hi)], AffineArithmetic())[0].to_interval()
            ta = time.perf_counter() - t
            t = time.perf_counter()
            low, _ = backward_bounds(F, lo, hi, -np.eye(2))
            tb = time.perf_counter() - t
            t = time.perf_counter()
            opt, _ = backward_bounds(F, lo, hi, -np.eye(2), slope_steps=steps)
            to = time.perf_counter() - t
            pts = lo[:, None, :] + (hi - lo)[:, None, :] * rng.uniform(size=(B, S, n))
            pts = np.concatenate([pts, lo[:, None], hi[:, None]], axis=1)
            vals = np.array(F(pts.reshape(-1, n).T)).T.reshape(B, S + 2, 2).max(axis=1)
            gaps = []
            for k in range(2):
                if np.any(-low[k] < vals[:, k]) or np.any(-opt[k] < vals[:, k]):
                    raise SystemExit("backward bound below a sampled value: unsound")
                gaps += [np.median(aff.hi[:, k] - vals[:, k]),
                         np.median(np.minimum(aff.hi[:, k], -low[k]) - vals[:, k]),
                         np.median(np.minimum(aff.hi[:, k], -opt[k]) - vals[:, k])]
            arch = "-".join(map(str, Vs)) + (", " + "-".join(map(str, Ks)) if Ks else "")
            print(f"| {name} | {arch} | {w:g} | " + " | ".join(f"{g:.3g}" for g in gaps)
                  + f" | {ta:.3f} | {tb:.3f} | {to:.3f} |")
    print()


def queries(repeat: int, steps: int) -> None:
    import distributed_verify as dv
    import verify as bv

    from nlyap_opt.certification.roa import candidate_level

    rows = []
    for name, inner, outer in bv.SEED_SYSTEMS:
        V, K = bv._seed_networks(name)
        rows.append((name, closed_loop_problem(systems.get(name), V, K, inner=inner,
                                               outer=outer)))
    s = systems.get("van_der_pol")
    V6 = Network.load(bv.DATA / "vdp_V6.json")
    phi = Network.load(bv.DATA / "vdp_phi_200.json")
    rows.append(("(ii) V6, 200-neuron φ", closed_loop_problem(s, V6, dynamics=phi, inner=0.2,
                                                              outer=1.2, margin=0.01)))
    V30 = Network.load(bv.DATA / "vdp_V30x30.json")
    cl = closed_loop(s)
    Vx = V30.casadi(cl.x)
    lie = lie_derivative(Vx, cl.x, cl.rhs)
    cand = candidate_level(cl.x, Vx, lie, inner=0.2, outer=2.5)
    rows.append(("(iii) V 2-30-30, 0.97 of the candidate level",
                 lyapunov_problem(cl.x, Vx, lie, inner=0.2, outer=2.5, level=0.97 * cand.level)))
    rows.append(("4-D coupled oscillators (16 tanh units)", dv.problem_4d()))
    print("| query | verdict | boxes | CPU s | with backward: verdict | boxes | CPU s | "
          f"with {steps} slope steps: verdict | boxes | CPU s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for label, p in rows:
        verify(p)  # compile
        (_, ca_), r = bv._timed(lambda p=p: verify(p), repeat)  # best CPU seconds
        (_, cb), rb = bv._timed(lambda p=p: verify(p, backward=True), repeat)
        (_, co), ro = bv._timed(lambda p=p: verify(p, backward=True, slope_steps=steps),
                                repeat)
        print(f"| {label} | {r.status} | {r.boxes} | {ca_:.3f} | {rb.status} | {rb.boxes} | "
              f"{cb:.3f} | {ro.status} | {ro.boxes} | {co:.3f} |")
    print()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--part", type=int, nargs="*", default=[1, 2], choices=[1, 2])
    ap.add_argument("--slope-steps", type=int, default=20,
                    help="optimisation steps of the slopes in the third variant")
    args = ap.parse_args(argv)
    from distributed_verify import machine

    print(f"`python bench/backward.py --repeat {args.repeat} --slope-steps {args.slope_steps}`"
          f" on {machine()}\n")
    if 1 in args.part:
        enclosures(args.slope_steps)
    if 2 in args.part:
        queries(args.repeat, args.slope_steps)


if __name__ == "__main__":
    main()
