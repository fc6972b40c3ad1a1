"""``nlyap compare``: every method's ROA, certified by the same verifier, against the true ROA.

Rows (each certified with conditions (a), (b) and the inner-ball condition (c), exactly as
the neural certificates, so no baseline looks better or worse through a softer standard):

- ``lqr`` — ``V = xᵀPx`` with the LQR controller (linear and saturated variants), true f;
- ``lqr-learned`` — the same with learned φ and the pointwise robust margin η‖∇_L V‖;
- ``sos-2``, ``sos-4`` — SOS (cvxpy) where the closed loop is polynomial, re-certified;
- ``neural-learned`` / ``neural-true`` — the main pipeline with learned φ / with the true f.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from nlyap_opt.errors import InputRangeError
from nlyap_opt.network import Network

__all__ = ["compare", "quadratic_row"]


def quadratic_row(system, cfg: dict, V, controller, *, method: str, dynamics=None,
                  eta: float = 0.0, dynamics_box=None, input_box=None, out=None,
                  log=print) -> dict:
    """Certify the largest level of ``V`` (a Network) under ``controller`` and return a row.

    The level is certified by :func:`nlyap_opt.certificate.certify_roa` (conditions (a), (b),
    (c), exactly as the neural rows); with ``out`` the certificate is saved there
    (``nlyap verify --certificate OUT/certificate.json`` re-checks it).
    """
    from nlyap_opt.certificate import RoaProblem, certify_roa, save_certificate
    from nlyap_opt.roa import candidate_level

    t0 = time.perf_counter()
    # a quadratic V needs no large excluded ball: B_ε only has to lie in the certified inner
    # ellipse, and a thin LQR ellipse cannot contain the neural runs' B_ε (B_ε ⊆ Ω_c fails)
    from nlyap_opt.configs import domain_of

    D = domain_of(cfg, system.nx)[0]
    eps = float(cfg["inner"]) / 4
    problem = RoaProblem(system, V, controller, dynamics, inner=eps, eta=eta, domain=D,
                         dynamics_box=dynamics_box, input_box=input_box)
    try:
        dec = problem.decrease()
    except InputRangeError as err:
        return {"method": method, "level": 0.0, "certified": False,
                "status": f"not certified: {err}", "seconds": time.perf_counter() - t0}
    cand = candidate_level(dec.x, dec.V, dec.lie, inner=eps, domain=D, margin=dec.margin)
    cert = certify_roa(problem, cand.level, search=True, log=lambda m: None)
    row = {"method": method, "level": cert.level if cert.certified else 0.0,
           "certified": cert.certified,
           "status": "certified" if cert.certified else f"{cert.status.value}: {cert.reason}",
           "candidate_level": cand.level, "seconds": time.perf_counter() - t0,
           "_cert": cert}
    if out is not None:
        row["certificate"] = str(save_certificate(cert, problem, out))
    log(f"  {method}: {row['status']}, level {row['level']:.5g} (candidate {cand.level:.5g})")
    return row


def _areas(rows, system, cfg, true_mask, box, n):
    from nlyap_opt.roa import grid_area, grid_points

    pts, shape = grid_points(box, n)
    true_area = grid_area(true_mask, box)
    for row in rows:
        if not row["certified"] or "_cert" not in row:
            row.setdefault("area", 0.0)
            row.setdefault("fraction_of_true_roa", 0.0)
            continue
        row["_mask"] = row["_cert"].contains(pts).reshape(shape)
        row["area"] = grid_area(row["_mask"], box)
        row["fraction_of_true_roa"] = row["area"] / true_area if true_area else 0.0
    return true_area


def compare(system_name: str, cfg: dict, out: str | Path, *, log=print,
            include_neural: bool = True) -> list[dict]:
    """Run every method for ``system_name``; write comparison.{json,md,png} into ``out``."""
    import systems
    from nlyap_opt.certificate import recheck_certificate, save_certificate
    from nlyap_opt.configs import domain_of
    from nlyap_opt.control import linear_controller, lqr, quadratic_lyapunov, saturated_controller
    from nlyap_opt.pipeline import run
    from nlyap_opt.roa import axis_count, true_roa_mask

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    system = systems.get(system_name)
    D = domain_of(cfg, system.nx)[0]
    declared = cfg.get("domain") is not None   # every row (SOS too) on the declared D
    rows: list[dict] = []
    lq = cfg.get("lqr", {})
    res = lqr(system, lq.get("Q"), lq.get("R"))
    V = quadratic_lyapunov(res.P)
    log(f"[compare] {system_name}: LQR / quadratic V")
    if system.nu:
        sat = saturated_controller(system, res.K, cfg["controller_scale"])
        rows.append(quadratic_row(system, cfg, V, linear_controller(system, res.K),
                                  method="lqr (linear u, true f)", out=out / "lqr_linear",
                                  log=log))
        rows.append(quadratic_row(system, cfg, V, sat, method="lqr (saturated u, true f)",
                                  out=out / "lqr_saturated", log=log))
    else:
        sat = None
        rows.append(quadratic_row(system, cfg, V, None, method="lqr (quadratic V, true f)",
                                  out=out / "lqr", log=log))
    # SOS (polynomial closed loops only; others are explained)
    try:
        from .sos import sos_roa

        for deg in (2, 4, 6):
            t0 = time.perf_counter()
            sos = sos_roa(system, degree=deg, inner=cfg["inner"],
                          domain=D if declared else None)
            row = {"method": f"sos (degree {deg}, true f)", "level": sos.certified_level or 0.0,
                   "certified": sos.certified, "status": sos.status,
                   "sdp_level": sos.sdp_level, "seconds": time.perf_counter() - t0,
                   "notes": "; ".join(sos.notes)}
            if sos.certified:
                row["_cert"] = sos.certificate
                row["certificate"] = str(save_certificate(sos.certificate, sos.problem,
                                                          out / f"sos_{deg}"))
            if not sos.applicable:
                row["method"] = "sos (true f)"  # one row: the reason holds for every degree
                rows.append(row)
                log(f"  sos: {sos.status}")
                break
            rows.append(row)
            log(f"  sos degree {deg}: {sos.status}")
    except ImportError as err:
        rows.append({"method": "sos", "level": 0.0, "certified": False,
                     "status": f"not available: {err}", "seconds": 0.0})
    # neural rows from the main pipeline (resumed if already run)
    if include_neural:
        for known, label in ((False, "neural (learned φ)"), (True, "neural (true f)")):
            d = out / ("neural_true" if known else "neural_learned")
            log(f"[compare] {label}: nlyap run into {d}")
            t0 = time.perf_counter()
            res = run(system, cfg, d, known_dynamics=known, log=log)
            cert = res.summary
            row = {"method": label, "level": cert["level"], "certified": res.certified,
                   "status": cert["status"] if res.certified
                   else f"{cert['status']}: {cert['reason']}",
                   "certificate": str(d / "certificate.json"),
                   "seconds": sum(cert["seconds"].values()) if cert.get("seconds")
                   else time.perf_counter() - t0}
            if row["certified"]:
                row["_cert"] = recheck_certificate(d, log=lambda m: None) \
                    if res.certificate is None else res.certificate
            rows.append(row)
            if not known and row["certified"] and (d / "dynamics.json").exists():
                # LQR with learned φ (the unknown-dynamics setting for the baseline)
                b = json.loads((d / "bounds.json").read_text())
                dyn = Network.load(d / "dynamics.json")
                grid_box = np.asarray(b["grid"]["box"], dtype=float)
                rows.append(quadratic_row(
                    system, cfg, V, sat, method="lqr (learned φ)", dynamics=dyn,
                    eta=float(b["eta"]), dynamics_box=grid_box[: system.nx],
                    input_box=grid_box[system.nx:] if len(grid_box) > system.nx
                    else system.input_box, out=out / "lqr_learned", log=log))
    # true ROA and areas
    box = np.asarray(cfg["eval_box"], dtype=float)
    n = axis_count(int(cfg["eval_points"]), system.nx)
    feedback = None if sat is None else (lambda z: sat.numpy(z))
    true_mask = true_roa_mask(system, feedback, box, n)
    if system.nu or declared:   # as in the pipeline: within the disc, or within D
        from nlyap_opt.roa import grid_points

        pts, shape = grid_points(box, n)
        true_mask &= D.contains(pts).reshape(shape)
    true_area = _areas(rows, system, cfg, true_mask, box, n)
    _write(out, system, rows, true_area, true_mask, box, cfg, D)
    return rows


def _write(out, system, rows, true_area, true_mask, box, cfg, D):
    public = [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows]
    (out / "comparison.json").write_text(json.dumps(
        {"system": system.name, "true_roa_area": true_area, "rows": public}, indent=1,
        default=float))
    lines = [f"# {system.name}: certified regions of attraction", "",
             f"True ROA area (simulation, {len(true_mask)}² grid over {box.tolist()}"
             + (f", within D = {D.describe()}"
                if cfg.get("domain") is not None else ", within the disc" if system.nu else "")
             + f"): {true_area:.4g}", "",
             "| method | certified | level | area | % of true ROA | seconds | status |",
             "|---|---|---|---|---|---|---|"]
    for r in public:
        lines.append(f"| {r['method']} | {'yes' if r['certified'] else 'no'} | "
                     f"{r['level']:.5g} | {r.get('area', 0):.4g} | "
                     f"{100 * r.get('fraction_of_true_roa', 0):.1f} | {r['seconds']:.1f} | "
                     f"{r['status']} |")
    notes = [r for r in public if r.get("notes")]
    if notes:
        lines += ["", "Notes:"] + [f"- {r['method']}: {r['notes']}" for r in notes]
    (out / "comparison.md").write_text("\n".join(lines) + "\n")
    _plot(out / "comparison.png", system, rows, true_mask, box, cfg, D)


def _plot(path, system, rows, true_mask, box, cfg, D):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = true_mask.shape[0]
    xs = [lo + (hi - lo) * (np.arange(n) + 0.5) / n for lo, hi in box]
    X1, X2 = np.meshgrid(xs[0], xs[1], indexing="ij")
    fig, ax = plt.subplots(figsize=(7, 6))
    ax.contour(X1, X2, true_mask.astype(float), levels=[0.5], colors="k", linewidths=2)
    handles = [plt.Line2D([], [], color="k", lw=2, label="true ROA")]
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, r in enumerate(rows):
        if "_mask" not in r:
            continue
        c = colors[i % len(colors)]
        ax.contour(X1, X2, r["_mask"].astype(float), levels=[0.5], colors=[c], linewidths=1.5)
        handles.append(plt.Line2D([], [], color=c,
                                  label=f"{r['method']}: {100 * r['fraction_of_true_roa']:.1f}%"))
    ax.plot(*D.outline_2d(0, 1).T, "r--", lw=1)
    handles.append(plt.Line2D([], [], color="r", ls="--", label="verification domain"))
    from nlyap_opt.roa import grid_points

    g = 25
    gp, gs = grid_points(box, g)
    ctrl = None
    if system.nu:
        from .lqr import lqr, saturated_controller

        lq = cfg.get("lqr", {})
        ctrl = saturated_controller(system, lqr(system, lq.get("Q"), lq.get("R")).K,
                                    cfg["controller_scale"])
    with np.errstate(all="ignore"):
        F = system.evaluate(gp, None if ctrl is None else ctrl.numpy(gp))
    ax.streamplot(np.linspace(*box[0], g), np.linspace(*box[1], g), F[:, 0].reshape(gs).T,
                  F[:, 1].reshape(gs).T, color="0.7", density=0.8, linewidth=0.5,
                  arrowsize=0.6)
    ax.set_xlim(box[0])
    ax.set_ylim(box[1])
    ax.set_xlabel(system.state_names[0])
    ax.set_ylabel(system.state_names[1])
    ax.legend(handles=handles, fontsize=7, loc="upper right")
    ax.set_title(f"{system.name}: certified sets (every curve verified) vs true ROA",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
