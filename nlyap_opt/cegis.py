"""Counterexample-guided learning of ``V`` and ``κ`` with a certified level (CEGIS).

Each iteration: train on the state samples plus the counterexamples found so far; export
the float64 networks (the verified objects); if the dynamics are learned, recompute the
margin ``β = M·η`` with ``M`` a rigorous bound of ``‖∇V‖`` on the ball; find a candidate
level by NLP; certify conditions (a) and (b) at the largest level reachable from it.
Confirmed counterexamples (and a few neighbours) go back into training. The best
certificate (by certified area) is kept.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from .learning import LyapunovLearner, TrainConfig, sample_ball, sample_sphere
from .network import Network
from .roa import candidate_level, certify_level, grid_area, grid_points
from .simulate import simulate_converges

__all__ = ["CegisConfig", "CegisResult", "cegis"]


@dataclass
class CegisConfig:
    inner: float
    outer: float
    iterations: int = 6
    samples: int = 20000
    sphere_samples: int = 2000
    max_counterexamples: int = 5000
    neighbours: int = 8
    first_steps: int | None = None   # training steps of the first iteration (default: train.steps)
    steps: int = 500                 # training steps of later iterations
    target_fraction: float = 0.99    # stop when certified level >= this fraction of candidate
    area_grid: int = 200
    verify_options: dict = field(default_factory=dict)
    train: TrainConfig = field(default_factory=TrainConfig)
    seed: int = 0
    time_budget: float = 300.0
    # learned dynamics: "pointwise" verifies ∇V·φ + η‖∇V(x)‖ < 0 (Cauchy–Schwarz: implies
    # ∇V·f < 0 wherever ‖f − φ‖ ≤ η); "global" verifies the paper's ∇V·φ < −β, β = M·η
    margin_mode: str = "pointwise"


@dataclass
class CegisResult:
    status: str                  # "certified" or why not
    V: Network | None
    controller: Network | None
    level: float
    margin: float
    M: float | None
    area: float
    history: list
    seconds: float


def cegis(system, controller: Network | None, dynamics: Network | None, cfg: CegisConfig, *,
          eta: float = 0.0, gradient_bound=None, log=print, V0: Network | None = None
          ) -> CegisResult:
    """Learn ``V`` (and ``κ``) and certify a level; see the module docstring.

    Parameters
    ----------
    system : systems.System
    controller : Network or None     initial controller (LQR-initialised)
    dynamics : Network or None       learned φ (``None``: the true f, known-dynamics setting)
    cfg : CegisConfig
    eta : float                      error bound ``‖f − φ‖ ≤ η`` on the box (learned case)
    gradient_bound : callable(V: Network, controller: Network | None) -> float
        Rigorous ``sup ‖∇V‖₂`` on the verification ball (needed when ``eta > 0``); it should
        also refuse a controller that leaves the input box ``U``.
    """
    from .symbolic import closed_loop, lie_derivative, robust_lie

    t0 = time.perf_counter()
    if eta > 0 and gradient_bound is None:
        raise ValueError("learned dynamics (eta > 0) need a rigorous gradient_bound for M")
    rng = np.random.default_rng(cfg.seed)
    n = system.nx
    X = sample_ball(cfg.samples, n, cfg.outer, rng)
    S = sample_sphere(cfg.sphere_samples, n, cfg.outer, rng)
    learner = LyapunovLearner(system, controller, dynamics, cfg.train, V=V0)

    def rhs_np(x):
        import torch

        with torch.no_grad():
            return learner.rhs(torch.as_tensor(x)).numpy()

    weights = simulate_converges(rhs_np, X, t_final=20.0, dt=0.02, tol=1e-2).astype(float)
    log(f"  cegis: {int(weights.sum())}/{len(X)} training states converge under the model")
    pts, shape = grid_points(np.tile([-cfg.outer, cfg.outer], (n, 1)), cfg.area_grid)
    in_ball = np.linalg.norm(pts, axis=1) <= cfg.outer
    box = np.tile([-cfg.outer, cfg.outer], (n, 1))
    cex = np.zeros((0, n))
    best: CegisResult | None = None
    history = []
    margin = 0.0
    M = None
    for it in range(cfg.iterations):
        steps = (cfg.first_steps or cfg.train.steps) if it == 0 else cfg.steps
        pointwise = eta if (eta > 0 and cfg.margin_mode == "pointwise") else 0.0
        info = learner.train(X, S, 0.0 if pointwise else margin, cex if len(cex) else None,
                             steps=steps, inside_weight=weights, eta_pointwise=pointwise)
        V, ctrl = learner.export()
        if eta > 0:
            M = float(gradient_bound(V, ctrl))
            margin = float(np.nextafter(M * eta, np.inf))
        cl = closed_loop(system, ctrl, dynamics, strict=True)
        Vx = V.casadi(cl.x)
        lie = lie_derivative(Vx, cl.x, cl.rhs)
        check_margin = margin
        if eta > 0 and cfg.margin_mode == "pointwise":
            lie = robust_lie(lie, Vx, cl.x, eta)
            check_margin = 0.0
        cand = candidate_level(cl.x, Vx, lie, inner=cfg.inner, outer=cfg.outer,
                               margin=check_margin, seed=cfg.seed + it)
        cert = certify_level(cl.x, Vx, lie, level=cand.level, inner=cfg.inner, outer=cfg.outer,
                             margin=check_margin, verify_options=cfg.verify_options,
                             log=lambda m: log("  " + m))
        area = 0.0
        if cert.status == "certified":
            v = V.numpy(pts)[:, 0]
            area = grid_area((in_ball & (v <= cert.level)).reshape(shape), box)
        entry = {"iteration": it, "loss": info["loss"], "train_steps": info["steps"],
                 "margin_mode": cfg.margin_mode if eta > 0 else "none",
                 "train_seconds": info["seconds"], "candidate_level": cand.level,
                 "candidate_source": cand.source, "status": cert.status,
                 "level": cert.level, "margin": margin, "M": M, "area": area,
                 "verify_seconds": cert.seconds,
                 "boxes": sum((h.get("boxes", 0) for h in cert.history), 0),
                 "counterexamples": int(len(cert.counterexamples))}
        history.append(entry)
        log(f"  cegis iteration {it}: loss {info['loss']:.4g}, candidate level "
            f"{cand.level:.4g} ({cand.source}), {cert.status} level {cert.level:.4g}, "
            f"area {area:.4g}, margin {margin:.3g}")
        if cert.status == "certified" and (best is None or area > best.area):
            best = CegisResult("certified", V, ctrl, cert.level, margin, M, area, history,
                               0.0)
        if cert.status == "certified" and cert.level >= cfg.target_fraction * cand.level \
                and not len(cert.counterexamples):
            break
        new = cert.counterexamples
        if len(new):
            jitter = new[:, None, :] + 0.01 * cfg.outer * rng.standard_normal(
                (len(new), cfg.neighbours, n))
            new = np.vstack([new, jitter.reshape(-1, n)])
            cex = np.vstack([cex, new])[-cfg.max_counterexamples:]
        if time.perf_counter() - t0 > cfg.time_budget:
            log("  cegis: time budget reached")
            break
    seconds = time.perf_counter() - t0
    if best is None:
        V, ctrl = learner.export()
        return CegisResult("no certified level within the iteration budget", V, ctrl, 0.0,
                           margin, M, 0.0, history, seconds)
    best.history, best.seconds = history, seconds
    return best
