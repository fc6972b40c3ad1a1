"""``nlyap run``: from samples to a certified region of attraction, in resumable stages.

Stages (each saves its artifacts in the output directory; a rerun with the same
configuration loads finished stages instead of recomputing them):

1. ``dynamics`` — learn φ on a grid, compute α, δ, K_f, K_φ, η (skipped with
   ``known_dynamics``);
2. ``controller`` — LQR on the linearisation, saturated controller with solved bias;
3. ``cegis`` — learn V and κ, certify conditions (a) and (b) at a level;
4. ``certificate`` — condition (c) (certified for known f; the paper's assumption for
   unknown f), certified and true-ROA areas, and the check of the *same* V and κ against
   the true f (a benchmark, reported separately); ``report.md`` and ``roa.png``.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

import numpy as np

from .cegis import CegisConfig, cegis
from .learning import TrainConfig
from .network import Network

__all__ = ["run"]


def _hash(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _write(path: Path, data: dict):
    path.write_text(json.dumps(data, indent=1, allow_nan=False, default=_jsonable))


def _jsonable(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    return str(o)


#: the configuration keys each stage reads
_STAGE_KEYS = {
    "dynamics": ("dynamics",),
    "controller": ("lqr", "controller_scale"),
    "cegis": ("inner", "outer", "train", "cegis"),
}


class _Stages:
    """Stage bookkeeping: ``DIR/stages.json`` maps stage -> config hash when finished.

    A stage's hash covers the system, the setting (known or learned f), every configuration
    key the stage reads (:data:`_STAGE_KEYS`) and the hashes of the stages it builds on, so
    a changed setting reruns exactly the stages it affects.
    """

    def __init__(self, out: Path, system: str, cfg: dict, log):
        self.out, self.log, self.system = out, log, system
        self.file = out / "stages.json"
        self.done = json.loads(self.file.read_text()) if self.file.exists() else {}
        self.cfg = cfg

    def key(self, stage: str, *deps) -> str:
        return _hash([stage, self.system, self.cfg.get("known_dynamics"),
                      {k: self.cfg.get(k) for k in _STAGE_KEYS[stage]},
                      [self.done.get(d) for d in deps]])

    def finished(self, stage: str, *deps) -> bool:
        ok = self.done.get(stage) == self.key(stage, *deps)
        if ok:
            self.log(f"[{stage}] loaded from {self.out} (finished earlier)")
        return ok

    def mark(self, stage: str, *deps):
        self.done[stage] = self.key(stage, *deps)
        self.file.write_text(json.dumps(self.done, indent=1))


def run(system_name: str, cfg: dict, out: str | Path, *, known_dynamics: bool = False,
        log=print) -> dict:
    """Run the pipeline for ``system_name`` with configuration ``cfg`` into ``out``.

    Returns the content of ``certificate.json``.
    """
    import systems
    from .control import lqr, saturated_controller

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    system = systems.get(system_name)
    cfg = dict(cfg, known_dynamics=known_dynamics)
    stages = _Stages(out, system_name, cfg, log)
    seconds: dict[str, float] = {}
    r, eps = float(cfg["outer"]), float(cfg["inner"])
    ball_box = np.tile([-r, r], (system.nx, 1))

    # ---------------------------------------------------------------- 1. dynamics
    dynamics, eta, bounds_info, dyn_box, input_box = None, 0.0, None, None, None
    if not known_dynamics:
        from .bounds import compute_bounds, write_bounds
        from .dynamics import default_config, learn_dynamics, merge_config

        if not stages.finished("dynamics"):
            t = time.perf_counter()
            dcfg = dict(cfg.get("dynamics", {}))
            preset = dcfg.pop("preset", "default")
            dcfg = merge_config(default_config(system_name, fast=(preset == "fast")), dcfg)
            dcfg["progress"] = dcfg.get("progress", True) and log is print
            log(f"[dynamics] learning φ for {system_name} ({preset} preset)")
            res = learn_dynamics(system, dcfg)
            bounds = compute_bounds(system, res.network, res.grid, res.alpha,
                                    options=dcfg.get("bound_options"),
                                    select=dcfg.get("bound_model", "best"),
                                    boxes=dcfg.get("interval_boxes", 16384),
                                    check_points=dcfg.get("check_points", 200000))
            net_path = res.network.save(out / "dynamics.json")
            write_bounds(out / "bounds.json", bounds, res.seconds, network_path=str(net_path))
            seconds["dynamics"] = time.perf_counter() - t
            stages.mark("dynamics")
        dynamics = Network.load(out / "dynamics.json")
        bounds_info = json.loads((out / "bounds.json").read_text())
        eta = float(bounds_info["eta"])
        grid_box = np.asarray(bounds_info["grid"]["box"], dtype=float)
        dyn_box = grid_box[: system.nx]
        # U of the bound: the grid's input rows (full model) or the system's (control-affine:
        # the error does not depend on u)
        input_box = grid_box[system.nx:] if len(grid_box) > system.nx else system.input_box
        if np.any(ball_box[:, 0] < dyn_box[:, 0]) or np.any(ball_box[:, 1] > dyn_box[:, 1]):
            from .errors import ConfigError

            raise ConfigError(
                f"the verification ball r={r} leaves the box {dyn_box.tolist()} on which "
                "‖f − φ‖ ≤ η was established; enlarge the dynamics box or reduce 'outer'"
            )
        log(f"[dynamics] η = {eta:.4g} ({bounds_info['bound_model']['name']} bound)")

    # ---------------------------------------------------------------- 2. controller
    controller = None
    if system.nu:
        if not stages.finished("controller"):
            lq = cfg.get("lqr", {})
            res = lqr(system, lq.get("Q"), lq.get("R"))
            ctrl = saturated_controller(system, res.K, cfg["controller_scale"])
            ctrl.save(out / "controller_init.json")
            _write(out / "lqr.json", res.to_dict())
            stages.mark("controller")
        controller = Network.load(out / "controller_init.json")

    # ---------------------------------------------------------------- 3. CEGIS
    deps = ("dynamics", "controller")
    if not stages.finished("cegis", *deps):
        t = time.perf_counter()
        train = TrainConfig(**cfg.get("train", {}))
        ccfg = CegisConfig(inner=eps, outer=r, train=train, **cfg.get("cegis", {}))
        grad = None
        if eta > 0:
            from .bounds import gradient_bound

            def grad(V, ctrl):
                """Rigorous M on the ball; refuses a κ leaving U or a ball leaving the box."""
                gb = gradient_bound(V, ball_box, controller=ctrl,
                                    input_box=input_box if system.nu else None,
                                    state_box=dyn_box)
                return gb.M

        log(f"[cegis] learning V{' and κ' if controller is not None else ''} on "
            f"{eps:g} ≤ ‖x‖ ≤ {r:g}" + (f" with η = {eta:.3g}" if eta else " (true f)"))
        res = cegis(system, controller, dynamics, ccfg, eta=eta, gradient_bound=grad, log=log)
        res.V.save(out / "V.json")
        if res.controller is not None:
            res.controller.save(out / "controller.json")
        _write(out / "cegis.json", {"status": res.status, "level": res.level,
                                    "margin": res.margin, "M": res.M,
                                    "smoothing": res.smoothing, "area_in_ball": res.area,
                                    "history": res.history, "seconds": res.seconds})
        seconds["cegis"] = time.perf_counter() - t
        stages.mark("cegis", *deps)
    cg = json.loads((out / "cegis.json").read_text())
    V = Network.load(out / "V.json")
    controller = Network.load(out / "controller.json") if controller is not None else None

    # ---------------------------------------------------------------- 4. certificate
    t = time.perf_counter()
    cert = _certificate(system, cfg, V, controller, dynamics, eta, cg, bounds_info, out, log)
    seconds["certificate"] = time.perf_counter() - t
    prev = json.loads((out / "seconds.json").read_text()) if (out / "seconds.json").exists() \
        else {}
    prev.update(seconds)
    _write(out / "seconds.json", prev)
    cert["seconds"] = prev
    _write(out / "certificate.json", cert)
    from .report import write_report

    write_report(out, system, cfg, cert, bounds_info, cg)
    log(f"[done] status: {cert['status']}; certified area {cert['certified_area']:.4g} = "
        f"{100 * cert['fraction_of_true_roa']:.1f}% of the true ROA "
        f"({cert['true_roa_area']:.4g}); see {out / 'report.md'}")
    return cert


def _certificate(system, cfg, V, controller, dynamics, eta, cg, bounds_info, out, log) -> dict:
    from verification import closed_loop_problem, verify

    from .roa import certify_inner_ellipse, grid_area, grid_points, true_roa_mask

    r, eps = float(cfg["outer"]), float(cfg["inner"])
    level, margin = float(cg["level"]), float(cg["margin"])
    smoothing = float(cg.get("smoothing", 0.0))
    known = dynamics is None
    mode = (cg["history"][-1].get("margin_mode", "none") if cg.get("history") else "none")
    if known:
        condition = "∇V·f(x, κ(x)) < 0"
    elif mode == "pointwise":
        condition = (f"∇V·φ(x, κ(x)) + η·sqrt(‖∇V(x)‖² + s²) < 0 with η = {eta:.4g}, "
                     f"s = {smoothing:.4g} (implies ∇V·f < 0 by Cauchy–Schwarz where "
                     "‖f − φ‖ ≤ η)")
    else:
        condition = f"∇V·φ(x, κ(x)) < −β with β = M·η = {margin:.4g}"
    assumptions = [
        "V and κ are the float64 networks saved in V.json / controller.json (verified as saved)",
    ]
    status = cg["status"]
    inner = None
    if status == "certified":
        log("[certificate] condition (c): quadratic certificate on the inner ball")
        inner = certify_inner_ellipse(system, controller, eps)
        if known and inner["status"] != "certified":
            status = f"inner ball not certified ({inner['status']})"
        if not known:
            assumptions += [
                "f is Lipschitz on the dynamics box with the computed K_f, and ‖f − φ‖ ≤ η "
                f"= {eta:.4g} there ({bounds_info['bound_model']['name']} bound: "
                + "; ".join(bounds_info["bound_model"]["assumptions"]) + ")",
                "the inner ball B_ε lies in a quadratic-Lyapunov ROA of the true closed loop "
                "(the paper's Assumption 3; condition (c) cannot be proved from samples)",
            ]
    # areas
    box = np.asarray(cfg["eval_box"], dtype=float)
    n = int(cfg["eval_grid"])
    pts, shape = grid_points(box, n)
    v = V.numpy(pts)[:, 0]
    omega = (np.linalg.norm(pts, axis=1) <= r) & (v <= level) if status == "certified" \
        else np.zeros(len(pts), bool)
    if inner is not None and inner["status"] == "certified" or (inner is not None and not known):
        P, cq = inner["P"], inner["level"]
        omega |= np.einsum("ij,jk,ik->i", pts, P, pts) <= cq
    omega = omega.reshape(shape)
    cache = out / "true_roa.npz"
    feedback = None if controller is None else (lambda z: controller.numpy(z))
    ckey = _hash([system.name, cfg["eval_box"], n, None if controller is None
                  else controller.to_dict()])
    if cache.exists() and str(np.load(cache)["key"]) == ckey:
        true_mask = np.load(cache)["mask"]
    else:
        log("[certificate] true ROA by simulation on the evaluation grid")
        # the certified inner ellipse of the true closed loop absorbs converging states early
        ell = (inner["P"], inner["level"]) if inner and inner["status"] == "certified" else None
        true_mask = true_roa_mask(system, feedback, box, n, ellipse=ell)
        np.savez_compressed(cache, mask=true_mask, key=ckey)
    if system.nu:  # the paper's comparison for controlled systems: within the disc
        disc = (np.linalg.norm(pts, axis=1) <= r).reshape(shape)
        true_mask = true_mask & disc
    cert_area = grid_area(omega, box)
    true_area = grid_area(true_mask, box)
    sound_vs_sim = bool(np.all(true_mask[omega]) if omega.any() else True)
    # the same V and κ against the true f (benchmark check, not part of the certificate)
    true_check = None
    if status == "certified" and not known:
        prob = closed_loop_problem(system, V, controller, None, inner=eps, outer=r,
                                   level=level, margin=0.0, strict=False, check_positive=False)
        res = verify(prob)
        true_check = {"decrease_true_f": res.status, "inner_ball_true_f": inner["status"],
                      "seconds": res.seconds}
        log(f"[certificate] same V, κ against the true f: decrease {res.status}, "
            f"inner ball {inner['status']}")
    return {
        "system": system.name,
        "status": status,
        "dynamics": "known (true f)" if known else "learned φ",
        "level": level,
        "inner_radius": eps,
        "outer_radius": r,
        "margin": margin,
        "margin_mode": mode,
        "decrease_condition": condition,
        "M": cg.get("M"),
        "norm_smoothing": smoothing if mode == "pointwise" else 0.0,
        "eta": eta if not known else 0.0,
        "inner_ellipse": None if inner is None else {
            "status": inner["status"], "P": inner["P"], "level": inner["level"],
            "box_half_widths": inner["box"]},
        "certified_area": cert_area,
        "true_roa_area": true_area,
        "fraction_of_true_roa": cert_area / true_area if true_area else 0.0,
        "certified_points_converge_in_simulation": sound_vs_sim,
        "assumptions": assumptions,
        "true_dynamics_check": true_check,
        "eval_box": box,
        "eval_grid": n,
    }
