"""The cartpole with learned f: a quadratic candidate (default the round one) certified on a
run's φ.

Reads the dynamics and controller stages of a run of ``nlyap run cartpole --preset large``
(learned f: ``dynamics.json``, ``bounds.json`` with ``η``, ``controller_init.json``; the
run may be stopped once its ``stages.json`` lists both stages), then proves conditions (a),
(b), (c) for the round quadratic ``V = xᵀPx``
(:func:`nlyap_opt.design.control.round_lyapunov_matrix` of the learned closed loop's linearisation)
on the learned ``φ`` with the robust decrease ``∇V·(φ + gκ) + η‖∇V‖ < 0``, at the smallest level
that holds the preset's inner ball (``level = (1 + δ)·λ_max(P)·ε²``): near ``B_ε`` the robust margin
is thin (``η‖∇V‖`` against ``−∇V·f``), so this is the certificate with the most room. Condition (c)
is the paper's assumption for learned f, checked here on the true closed loop.

The checks run on a ``LocalCluster`` of ``--workers`` (default 2); the certificate is saved
to ``--out`` (default ``RUN/round_certificate``) and re-checked by
``nlyap verify --certificate OUT``. Figures are printed, not asserted::

    nlyap run cartpole --preset large --out runs/cp_learned      # φ, η, κ (its first stages)
    python bench/cartpole_learned.py --run runs/cp_learned [--workers 2] [--delta 0.02]
                                     [--no-inner-check] [--candidate round|volume|lyapunov]

Measured (2-core machine, 2 workers, the large preset's φ with η = 0.00413, ε = 0.1,
``--delta 0.02``, level 0.6105): **certified**; (a) and (b) in 2,427,470 boxes, (c) on the
true closed loop by the shell form (``shell r=0.025 + frobenius``), 156 s in all;
``nlyap verify --certificate OUT --workers 2`` re-checks it in 146 s. ``nlyap run`` now
takes the same level for its learned-f quadratics
(:data:`nlyap_opt.certification.roa.INNER_LEVEL_MARGIN` is the default ``--delta``).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import systems
from nlyap_opt.candidates.quadratic import QUADRATIC_CANDIDATES, closed_loop_matrix
from nlyap_opt.certification.certificate import RoaProblem, certify_roa, save_certificate
from nlyap_opt.certification.roa import INNER_LEVEL_MARGIN
from nlyap_opt.design.control import quadratic_lyapunov
from nlyap_opt.distributed.parallel import dask_client, verifying_on
from nlyap_opt.kernel.network import Network
from nlyap_opt.workflow.configs import domain_of, make_config


def learned_problem(run: Path, max_boxes: int, candidate: str = "round"
                    ) -> tuple[RoaProblem, np.ndarray]:
    """(problem with the quadratic V of ``candidate``, P) from the run directory's φ, η and
    κ; ``candidate`` a key of :data:`nlyap_opt.candidates.quadratic.QUADRATIC_CANDIDATES` (its
    learned-dynamics matrix)."""
    s = systems.get("cartpole")
    cfg = make_config("cartpole", "large")
    missing = [f for f in ("dynamics.json", "bounds.json", "controller_init.json")
               if not (run / f).is_file()]
    if missing:
        raise SystemExit(f"{run} lacks {', '.join(missing)}: run `nlyap run cartpole --preset "
                         f"large --out {run}` (learned f) at least through its controller stage")
    bounds = json.loads((run / "bounds.json").read_text())
    grid = np.asarray(bounds["grid"]["box"], dtype=float)
    base = RoaProblem(s, quadratic_lyapunov(np.eye(s.nx)),
                      Network.load(run / "controller_init.json"),
                      Network.load(run / "dynamics.json"), inner=float(cfg["inner"]),
                      domain=domain_of(cfg, s.nx)[0], eta=float(bounds["eta"]),
                      dynamics_box=grid[:s.nx], input_box=grid[s.nx:],
                      verify_options=dict(cfg["cegis"]["verify_options"], max_boxes=max_boxes))
    P = QUADRATIC_CANDIDATES[candidate](closed_loop_matrix(base), False)
    if P is None:
        raise SystemExit(f"no {candidate} matrix for the learned closed loop (SDP failed)")
    return replace(base, V=quadratic_lyapunov(P)), P


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, required=True, help="run directory (learned f)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--delta", type=float, default=INNER_LEVEL_MARGIN,
                    help="level = (1 + delta)·λ_max(P)·ε²")
    ap.add_argument("--max-boxes", type=int, default=5_000_000)
    ap.add_argument("--candidate", choices=list(QUADRATIC_CANDIDATES), default="round",
                    help="the quadratic candidate's P (default round)")
    ap.add_argument("--out", type=Path,
                    help="certificate directory (default RUN/CANDIDATE_certificate)")
    ap.add_argument("--no-inner-check", action="store_true",
                    help="prove (a) and (b) only; the certificate then says (c) was not checked")
    args = ap.parse_args(argv)
    problem, P = learned_problem(args.run, args.max_boxes, args.candidate)
    lam = np.linalg.eigvalsh(P)
    level = (1.0 + args.delta) * lam[-1] * problem.inner**2
    print(f"η = {problem.eta:.6g}, ε = {problem.inner:g}, eig P = {np.round(lam, 3).tolist()}, "
          f"level = {level:.6g}", flush=True)
    t = time.perf_counter()
    with dask_client(workers=args.workers) as client, verifying_on(client):
        cert = certify_roa(problem, level, search=False, log=print,
                           check_inner_ellipse=not args.no_inner_check)
    seconds = time.perf_counter() - t
    out = args.out or args.run / f"{args.candidate}_certificate"
    save_certificate(cert, problem, out, extra={"seconds": seconds, "workers": args.workers})
    print(f"{cert.status.value}: {cert.reason} ({seconds:.1f} s on {args.workers} workers)")
    for name, verdict in cert.checks.items():
        print(f"  {name}: {verdict}")
    for a in cert.assumptions:
        print(f"  assumes: {a}")
    print(f"saved to {out}; re-check: nlyap verify --certificate {out}")


if __name__ == "__main__":
    main()
