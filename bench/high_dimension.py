"""Quadratic certificates of the 4-D cartpole and the 6-D planar quadrotor: which ``P``.

For the saturated LQR loop of each system's ``large`` preset (true f), the candidate
matrices of :mod:`nlyap_opt.candidates.quadratic` (``--candidates``, by default all of them:
e.g. ``lyapunov`` (``A_clᵀP + PA_cl = −I``), ``round`` (smallest condition number),
``volume`` (largest Lyapunov ellipsoid in the unit ball,
:func:`nlyap_opt.design.control.volume_lyapunov_matrix`) and ``sector`` (designed for the
whole-set test under the saturated controller, for the run's problem)), each with:

- the *sampled* level: the least ``V`` of a sampled decrease violation or of the domain's
  boundary (``‖x‖ = 1``), over ``--samples`` uniform points of the ellipsoid;
- the exact ellipsoid volume at that level, ``vol(B)·c^{n/2}/sqrt(det P)``;
- with ``--certify``: the certified level and volume of :func:`certify_quadratics` (the
  run's quadratic stage; ``ε`` a quarter of the preset's), and its seconds.

Figures only (no assertions)::

    python bench/high_dimension.py [--systems cartpole planar_quadrotor] [--certify]
                                   [--candidates lyapunov round volume] [--verbose]

Measured (2-core machine shared with other work, 2026-11-26; ``--certify`` on the cartpole
only): see ``docs/topics/high_dimension.md``.
"""

from __future__ import annotations

import argparse
import inspect
import math
import time

import casadi as ca
import numpy as np

import systems
from nlyap_opt.candidates.quadratic import QUADRATIC_CANDIDATES, certify_quadratics
from nlyap_opt.certification.certificate import RoaProblem
from nlyap_opt.certification.roa import axis_count
from nlyap_opt.design.control import lqr, quadratic_lyapunov, saturated_controller
from nlyap_opt.kernel.symbolic import closed_loop
from nlyap_opt.kernel.walker import evaluate
from nlyap_opt.workflow.configs import make_config

__all__ = ["loop", "sampled_level", "main"]


def loop(name: str) -> tuple[object, object, np.ndarray, dict]:
    """``(system, saturated LQR controller, A_cl, config)`` of the ``large`` preset."""
    s = systems.get(name)
    cfg = make_config(name, "large")
    lq = cfg.get("lqr", {})
    res = lqr(s, lq.get("Q"), lq.get("R"))
    return s, saturated_controller(s, res.K, cfg["controller_scale"]), res.A - res.B @ res.K, cfg


def sampled_level(s, ctrl, P: np.ndarray, *, inner: float, samples: int, seed: int = 0
                  ) -> float:
    """Least ``xᵀPx`` of a sampled decrease violation (``‖x‖ ≥ inner``) or of the unit
    sphere (``λ_min(P)``)."""
    x = ca.SX.sym("x", s.nx)
    cl = closed_loop(s, ctrl, x=x)
    F = ca.Function("f", [x], [cl.rhs])
    rng = np.random.default_rng(seed)
    lam = float(np.linalg.eigvalsh(P)[0])
    z = rng.normal(size=(samples, s.nx))
    z *= rng.random((samples, 1)) ** (1 / s.nx) / np.linalg.norm(z, axis=1, keepdims=True)
    X = np.linalg.solve(np.linalg.cholesky(P).T, z.T).T * math.sqrt(lam)
    X = X[np.linalg.norm(X, axis=1) >= inner]
    f = evaluate(F, [X])[0]
    bad = np.einsum("ij,jk,ik->i", X, P, f) >= 0
    v = np.einsum("ij,jk,ik->i", X[bad], P, X[bad])
    return min(lam, float(v.min()) if len(v) else math.inf)


def _volume(P: np.ndarray, c: float) -> float:
    n = len(P)
    return math.pi ** (n / 2) / math.gamma(n / 2 + 1) * c ** (n / 2) / math.sqrt(
        np.linalg.det(P))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--systems", nargs="+", default=["cartpole", "planar_quadrotor"])
    ap.add_argument("--candidates", nargs="+", default=list(QUADRATIC_CANDIDATES))
    ap.add_argument("--samples", type=int, default=200_000)
    ap.add_argument("--certify", action="store_true")
    ap.add_argument("--verbose", action="store_true", help="print the level search's tries")
    a = ap.parse_args(argv)
    print("| system | P | cond P | sampled level | volume (sampled) | certified level | "
          "volume (certified, exact / grid) | seconds |")
    print("|---|---|---|---|---|---|---|---|")
    for name in a.systems:
        s, ctrl, A, cfg = loop(name)
        eps = 0.25 * cfg["inner"]
        prob = RoaProblem(s, quadratic_lyapunov(np.eye(s.nx)), ctrl, inner=cfg["inner"],
                          outer=cfg["outer"], verify_options=cfg["cegis"]["verify_options"])
        for cand in a.candidates:
            plug = QUADRATIC_CANDIDATES[cand]   # "sector" designs P for the run's problem
            kw = {"problem": prob} if "problem" in inspect.signature(plug).parameters else {}
            P = plug(A, True, prob.domain, **kw)
            if P is None:
                print(f"| {name} | {cand} | no matrix | | | | | |", flush=True)
                continue
            c = sampled_level(s, ctrl, P, inner=eps, samples=a.samples)
            row = [name, cand, f"{np.linalg.cond(P):.3g}", f"{c:.4g}", f"{_volume(P, c):.4g}"]
            if a.certify:
                t = time.perf_counter()
                box = np.asarray(cfg["eval_box"], dtype=float)
                q = certify_quadratics(prob, [cand], box=box,
                                       n=axis_count(cfg["eval_points"], s.nx),
                                       log=print if a.verbose else lambda m: None)[0]
                lv = q.certificate.level if q.certified else 0.0
                row += [f"{lv:.4g}" if q.certified else q.certificate.status.value,
                        f"{_volume(P, lv):.4g} / {q.volume:.4g}" if q.certified else "–",
                        f"{time.perf_counter() - t:.0f}"]
            else:
                row += ["", "", ""]
            print("| " + " | ".join(row) + " |", flush=True)


if __name__ == "__main__":
    main()
