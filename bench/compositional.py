"""Compositional certificates of LyZNet's 10-D system and its chains: time and certified region.

Usage: python bench/compositional.py [--repeat 2]

Runs ``nlyap run NAME [--known-dynamics]`` and ``nlyap verify --certificate`` as fresh
processes for ``lyznet_10d`` (on [-1, 1]^10) and ``lyznet_chain`` (20 states), then, in
this process, :func:`nlyap_opt.certification.compositional.certify_compositional` for larger domains
and longer chains, each in both settings: ``known`` (the model's Jacobian graph) and
``data`` (sampled values of f and a second-derivative bound, what ``nlyap run`` does without
``--known-dynamics``). Per row: the best wall time, the status, the level ``c`` of
``V = Σ w_i x_iᵀ P_i x_i``, the proved decay rate ``γ`` (``dV/dt ≤ -γ V``), the certified
set's semi-axes along the coordinates (smallest and largest, as a fraction of the box's
half-width) and ``log10`` of its volume over the box's.
"""

from __future__ import annotations

import argparse
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def _cli(argv: list[str]) -> float:
    cmd = [sys.executable, "-m", "nlyap_opt.interface.cli", *argv]
    t = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode not in (0, 2):
        raise SystemExit(f"{' '.join(cmd)} failed ({p.returncode}): {p.stderr.strip()[-300:]}")
    return time.perf_counter() - t


def _region(cert) -> tuple[float, float, float]:
    """Smallest and largest semi-axis along a coordinate (over the box half-width), and
    log10(volume of {V ≤ c} / volume of the box)."""
    half = (cert.domain_box[:, 1] - cert.domain_box[:, 0]) / 2
    ext, logvol = [], 0.0
    for w, p in zip(cert.weights, cert.pieces):
        P = np.asarray(p.P)
        ext += list(np.sqrt(cert.level / w * np.diag(np.linalg.inv(P))) / half[list(p.states)])
        n = len(p.states)
        logvol += (n / 2) * math.log(cert.level / w) - 0.5 * math.log(np.linalg.det(P))
    n = cert.domain_box.shape[0]
    # {Σ w_i V_i ≤ c} is not the product of the ellipsoids: its volume is
    # vol(unit ball of R^n) · c^{n/2} / sqrt(Π det(w_i P_i))
    logvol = (n / 2) * math.log(math.pi) - math.lgamma(n / 2 + 1) + logvol
    logbox = float(np.sum(np.log(2 * half)))
    return min(ext), max(ext), (logvol - logbox) / math.log(10)


def main() -> None:
    import systems
    from nlyap_opt.certification.compositional import certify_compositional, recheck_compositional
    from nlyap_opt.kernel.provenance import fingerprint, fingerprint_id

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    fp = fingerprint()
    print(f"machine: {fp['cpu']['model']} ({os.cpu_count()} CPUs), fingerprint "
          f"{fingerprint_id(fp)}; command: python bench/compositional.py --repeat "
          f"{args.repeat}")
    print(f"{'system':<40} {'n':>4} {'run s':>6} {'verify s':>8}  {'status':<14} "
          f"{'level c':>9} {'γ':>7} {'axes/half-width':>16} {'log10 vol':>9}")
    with tempfile.TemporaryDirectory() as tmp:
        for name in ("lyznet_10d", "lyznet_chain"):
            for setting, flag in (("known", ["--known-dynamics"]), ("data", [])):
                out = Path(tmp) / f"{name}_{setting}"
                t_run = min(_cli(["run", name, *flag, "--out", str(out)])
                            for _ in range(args.repeat))
                t_chk = min(_cli(["verify", "--certificate", str(out)])
                            for _ in range(args.repeat))
                cert = recheck_compositional(out)
                lo, hi, lv = _region(cert) if cert.certified else (0, 0, -math.inf)
                print(f"{f'{name} (CLI, {setting})':<40} {cert.domain_box.shape[0]:4d} "
                      f"{t_run:6.2f} {t_chk:8.2f}  {cert.status.value:<14} {cert.level:9.4g} "
                      f"{cert.decay:7.4f} {lo:7.3f}..{hi:<7.3f} {lv:9.2f}")
    rows = [("lyznet_10d", {"radius": r}) for r in (4.0, 6.0, 10.0)] + \
        [("lyznet_chain", {"blocks": b}) for b in (5, 10)]
    for name, params in rows:
        s = systems.get(name, **params)
        for setting in ("known", "data"):
            best, cert = math.inf, None
            for _ in range(args.repeat):
                t = time.perf_counter()
                cert = certify_compositional(s, setting=setting, log=lambda m: None)
                best = min(best, time.perf_counter() - t)
            label = f"{name} " + ",".join(f"{k}={v:g}" for k, v in params.items()) + \
                f" ({setting})"
            lo, hi, lv = _region(cert) if cert.certified else (0, 0, -math.inf)
            print(f"{label:<40} {s.nx:4d} {best:6.2f} {'-':>8}  {cert.status.value:<14} "
                  f"{cert.level:9.4g} {cert.decay:7.4f} {lo:7.3f}..{hi:<7.3f} {lv:9.2f}")


if __name__ == "__main__":
    main()
