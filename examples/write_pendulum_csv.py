"""Write the black-box pendulum's samples to a csv file (a stand-in for measured data).

Usage::

    python examples/write_pendulum_csv.py                     # examples/data/pendulum.csv
    python examples/write_pendulum_csv.py --counts 21 21 9 --out /tmp/p.csv

Default: the control-affine slice u = 0 on a 401 × 401 grid over X = [−4, 4]² (the grid of
the pendulum's ``default`` dynamics preset; with the declared B it defines f everywhere).
``--counts nθ nω nu`` samples the full grid over X × U instead. Every float is written
with 17 significant digits, so the loaded grid is the model's grid bit for bit and gives
the same δ. Load it with ``nlyap run --system examples/pendulum_csv.toml`` or
``systems.load_spec("examples/pendulum_csv.toml")``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import blackbox_pendulum  # noqa: E402

import systems  # noqa: E402


def write(out: Path, counts: list[int]) -> systems.SampleSet:
    """Sample the black box on the grid ``counts`` and save it; return the sample set."""
    s = blackbox_pendulum.make()
    if len(counts) == 2:  # the slice u = 0
        box = np.vstack([s.state_box, [[0.0, 0.0]]])
        axes = [np.linspace(lo, hi, n) for (lo, hi), n in zip(box[:2], counts)]
        for ax, (lo, hi) in zip(axes, box[:2]):
            ax[0], ax[-1] = lo, hi
        th, om = np.meshgrid(*axes, indexing="ij")
        X = np.stack([th.ravel(), om.ravel()], axis=1)
        U = np.zeros((X.shape[0], 1))
        samples = systems.SampleSet(np.hstack([X, U]), s.evaluate(X, U), nx=2, nu=1,
                                    names=["theta", "omega", "torque"])
    elif len(counts) == 3:
        samples = systems.sample_function(s.evaluate, s.sampling_box, counts, nx=2,
                                          names=["theta", "omega", "torque"])
    else:
        raise SystemExit("--counts takes 2 numbers (slice u = 0) or 3 (grid over X × U)")
    out.parent.mkdir(parents=True, exist_ok=True)
    systems.save_samples(out, samples.points(np.arange(samples.size)), samples.values,
                         states=["theta", "omega"], inputs=["torque"])
    return samples


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path,
                    default=Path(__file__).resolve().parent / "data" / "pendulum.csv")
    ap.add_argument("--counts", type=int, nargs="+", default=[401, 401])
    args = ap.parse_args(argv)
    samples = write(args.out, args.counts)
    print(f"wrote {samples.size} samples to {args.out} (delta = {samples.delta!r})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
