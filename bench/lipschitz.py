"""LipSDP benchmark: wall time and the bounds for a trained-size 3-200-2 tanh network.

Prints seconds (wall and as reported), the LipSDP bound, the naive product bound
‖W1‖‖W0‖ and a sampled lower bound, for a few seeded random networks. Figures only; the
mathematics (sampled ≤ K ≤ naive) is tested in tests/test_lipschitz.py.

    python bench/lipschitz.py [--repeat 3]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from nlyap_opt.learned.lipschitz import lipschitz_lipsdp, lipschitz_sampled


def _net(rng, n, h, m, w0_scale=1.5, b0_scale=1.0):
    W0 = rng.normal(size=(h, n)) * w0_scale
    b0 = rng.normal(size=h) * b0_scale
    W1 = rng.normal(size=(m, h)) / math.sqrt(h)
    return W0, b0, W1


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3, help="timed runs per network (best kept)")
    args = ap.parse_args(argv)
    print(f"{'net':>10s} {'best s':>8s} {'reported':>9s} {'L':>10s} {'naive':>10s} "
          f"{'sampled':>10s} {'solver':>8s}")
    for seed, shape in [(16, (3, 200, 2)), (3, (3, 200, 2)), (1, (3, 50, 2)), (0, (2, 100, 1))]:
        rng = np.random.default_rng(seed)
        W0, b0, W1 = _net(rng, *shape)
        walls = []
        for _ in range(max(args.repeat, 1)):
            t0 = time.perf_counter()
            res = lipschitz_lipsdp(W0, b0, W1)
            walls.append(time.perf_counter() - t0)
        low = lipschitz_sampled(W0, b0, W1, rng.uniform(-3, 3, size=(20000, shape[0])))
        name = "-".join(str(k) for k in shape)
        print(f"{name:>10s} {min(walls):8.3f} {res.seconds:9.3f} {res.value:10.6f} "
              f"{res.naive:10.6f} {low:10.6f} {res.solver:>8s}")


if __name__ == "__main__":
    main()
