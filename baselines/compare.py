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
from dataclasses import dataclass, field, replace
from enum import Enum
from pathlib import Path

import numpy as np

import systems
from nlyap_opt.candidates.quadratic import quadratic_policy
from nlyap_opt.certification.certificate import (
    RoaCertificate,
    RoaProblem,
    certify_candidate,
    recheck_certificate,
    save_certificate,
)
from nlyap_opt.certification.roa import axis_count, grid_area, grid_points, true_roa_mask
from nlyap_opt.design.control import (
    linear_controller,
    lqr,
    quadratic_lyapunov,
    saturated_controller,
)
from nlyap_opt.kernel import deps
from nlyap_opt.kernel.jsonio import write_atomic, write_figure
from nlyap_opt.kernel.network import Network
from nlyap_opt.workflow.configs import domain_of
from nlyap_opt.workflow.pipeline import run

from .sos import sos_roa

__all__ = ["CompareRow", "RowStatus", "compare", "quadratic_row"]


class RowStatus(str, Enum):
    """Outcome of one ``nlyap compare`` row."""

    CERTIFIED = "certified"
    NOT_CERTIFIED = "not certified"
    COUNTEREXAMPLE = "counterexample"
    ASSUMPTION_REFUTED = "assumption refuted"
    NOT_APPLICABLE = "not applicable"
    NO_LEVEL = "no SOS level"
    NOT_AVAILABLE = "not available"

    def __str__(self) -> str:
        return self.value


@dataclass
class CompareRow:
    """One method's certified region in ``comparison.json`` (:meth:`to_json`).

    ``status`` with ``reason`` is written as ``"certified"`` or ``"<status>: <reason>"``;
    ``certificate`` (the proved claim, for the areas and the plot) and ``mask`` are not
    written.
    """

    method: str
    status: RowStatus
    reason: str = ""
    level: float = 0.0
    seconds: float = 0.0
    extra: dict = field(default_factory=dict)     # further saved fields, in order
    certificate: RoaCertificate | None = None
    mask: np.ndarray | None = None
    area: float = 0.0
    fraction_of_true_roa: float = 0.0

    @property
    def certified(self) -> bool:
        return self.status is RowStatus.CERTIFIED

    @property
    def status_text(self) -> str:
        """The saved status: the word, then the reason after a colon."""
        return self.status.value if self.certified or not self.reason \
            else f"{self.status.value}: {self.reason}"

    def to_json(self) -> dict:
        """The row of ``comparison.json``."""
        out = {"method": self.method, "level": self.level, "certified": self.certified,
               "status": self.status_text, **self.extra, "seconds": self.seconds}
        if self.certificate is not None or self.area:
            out.update(area=self.area, fraction_of_true_roa=self.fraction_of_true_roa)
        else:
            out.update(area=0.0, fraction_of_true_roa=0.0)
        return out


def quadratic_row(system, cfg: dict, V, controller, *, method: str, dynamics=None,
                  eta: float = 0.0, dynamics_box=None, input_box=None, out=None,
                  log=print) -> CompareRow:
    """Certify ``V`` (a Network) under ``controller`` by the quadratic candidates' policy.

    The level and the inner radius are chosen by
    :func:`nlyap_opt.candidates.quadratic.quadratic_policy` through
    :func:`nlyap_opt.certification.certificate.certify_candidate` (conditions (a), (b), (c), exactly
    as the neural rows), so the LQR row and the pipeline's ``"lyapunov"`` quadratic certify the same
    ``P`` at the same level; with ``out`` the certificate is saved there
    (``nlyap verify --certificate OUT/certificate.json`` re-checks it).
    """
    t0 = time.perf_counter()
    D, XI = domain_of(cfg, system.nx)
    # the pipeline's problem: its domain, initial set and verifier options
    problem = RoaProblem(system, V, controller, dynamics, inner=float(cfg["inner"]), eta=eta,
                         domain=D, initial_set=XI, dynamics_box=dynamics_box,
                         input_box=input_box, verify_options=dict(
                             cfg.get("cegis", {}).get("verify_options", {})))
    cert = certify_candidate(problem, quadratic_policy(dynamics is None), log=lambda m: None)
    row = CompareRow(method, RowStatus(cert.status.value), "" if cert.certified
                     else cert.reason, cert.level if cert.certified else 0.0,
                     certificate=cert if cert.certified else None)
    if out is not None:
        saved = save_certificate(cert, replace(problem, inner=cert.inner), out)
        row.extra["certificate"] = str(saved)
    row.seconds = time.perf_counter() - t0
    log(f"  {method}: {row.status_text}, level {row.level:.5g} (ε = {cert.inner:g})")
    return row


def _areas(rows: list[CompareRow], true_mask, box, n) -> float:
    pts, shape = grid_points(box, n)
    true_area = grid_area(true_mask, box)
    for row in rows:
        if not row.certified or row.certificate is None:
            continue
        row.mask = row.certificate.contains(pts).reshape(shape)
        row.area = grid_area(row.mask, box)
        row.fraction_of_true_roa = row.area / true_area if true_area else 0.0
    return true_area


def compare(system_name: str, cfg: dict, out: str | Path, *, log=print,
            include_neural: bool = True) -> list[CompareRow]:
    """Run every method for ``system_name``; write comparison.{json,md,png} into ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    system = systems.get(system_name)
    D = domain_of(cfg, system.nx)[0]
    lq = cfg.get("lqr", {})
    res = lqr(system, lq.get("Q"), lq.get("R"))
    V = quadratic_lyapunov(res.P)
    log(f"[compare] {system_name}: LQR / quadratic V")
    sat = saturated_controller(system, res.K, cfg["controller_scale"]) if system.nu else None
    if system.nu:
        rows = [quadratic_row(system, cfg, V, linear_controller(system, res.K),
                              method="lqr (linear u, true f)", out=out / "lqr_linear", log=log),
                quadratic_row(system, cfg, V, sat, method="lqr (saturated u, true f)",
                              out=out / "lqr_saturated", log=log)]
    else:
        rows = [quadratic_row(system, cfg, V, None, method="lqr (quadratic V, true f)",
                              out=out / "lqr", log=log)]
    rows += _sos_rows(system, cfg, D, out, log)
    if include_neural:
        rows += _neural_rows(system, cfg, V, sat, out, log)
    # true ROA and areas
    box = np.asarray(cfg["eval_box"], dtype=float)
    n = axis_count(int(cfg["eval_points"]), system.nx)
    feedback = None if sat is None else (lambda z: sat.numpy(z))
    true_mask = true_roa_mask(system, feedback, box, n)
    if system.nu or cfg.get("domain") is not None:   # as in the pipeline: within the disc or D
        pts, shape = grid_points(box, n)
        true_mask &= D.contains(pts).reshape(shape)
    true_area = _areas(rows, true_mask, box, n)
    _write(out, system, rows, true_area, true_mask, box, cfg, D)
    return rows


def _sos_rows(system, cfg: dict, D, out: Path, log) -> list[CompareRow]:
    """SOS rows of degree 2, 4, 6 (polynomial closed loops; one explained row otherwise),
    every declared domain honoured."""
    rows: list[CompareRow] = []
    try:   # cvxpy is imported by the first SDP
        for deg in (2, 4, 6):
            t0 = time.perf_counter()
            sos = sos_roa(system, degree=deg, inner=cfg["inner"],
                          domain=D if cfg.get("domain") is not None else None)
            row = CompareRow(f"sos (degree {deg}, true f)", RowStatus(sos.status.value),
                             sos.reason, sos.certified_level or 0.0,
                             extra={"sdp_level": sos.sdp_level},
                             certificate=sos.certificate if sos.certified else None)
            row.seconds = time.perf_counter() - t0
            row.extra["notes"] = "; ".join(sos.notes)
            if sos.certified:
                row.extra["certificate"] = str(save_certificate(sos.certificate, sos.problem,
                                                                out / f"sos_{deg}"))
            if not sos.applicable:
                row.method = "sos (true f)"  # one row: the reason holds for every degree
                log(f"  sos: {row.status_text}")
                return [row]
            rows.append(row)
            log(f"  sos degree {deg}: {row.status_text}")
    except ImportError as err:
        return rows + [CompareRow("sos", RowStatus.NOT_AVAILABLE, str(err))]
    return rows


def _neural_rows(system, cfg: dict, V, sat, out: Path, log) -> list[CompareRow]:
    """The main pipeline's rows (resumed if already run), and the LQR row with its φ."""
    rows = []
    for known, label in ((False, "neural (learned φ)"), (True, "neural (true f)")):
        d = out / ("neural_true" if known else "neural_learned")
        log(f"[compare] {label}: nlyap run into {d}")
        t0 = time.perf_counter()
        res = run(system, cfg, d, known_dynamics=known, log=log)
        cert = res.summary
        row = CompareRow(label, RowStatus(res.status.value),
                         "" if res.certified else cert["reason"], cert["level"],
                         extra={"certificate": str(d / "certificate.json")},
                         seconds=sum(cert["seconds"].values()) if cert.get("seconds")
                         else time.perf_counter() - t0)
        if row.certified:
            row.certificate = recheck_certificate(d, log=lambda m: None) \
                if res.certificate is None else res.certificate
        rows.append(row)
        if not known and row.certified and (d / "dynamics.json").exists():
            # LQR with learned φ (the unknown-dynamics setting for the baseline)
            b = json.loads((d / "bounds.json").read_text())
            dyn = Network.load(d / "dynamics.json")
            grid_box = np.asarray(b["grid"]["box"], dtype=float)
            rows.append(quadratic_row(
                system, cfg, V, sat, method="lqr (learned φ)", dynamics=dyn,
                eta=float(b["eta"]), dynamics_box=grid_box[: system.nx],
                input_box=grid_box[system.nx:] if len(grid_box) > system.nx
                else system.input_box, out=out / "lqr_learned", log=log))
    return rows


def _write(out, system, rows: list[CompareRow], true_area, true_mask, box, cfg, D):
    public = [r.to_json() for r in rows]
    write_atomic(out / "comparison.json", json.dumps(
        {"system": system.name, "true_roa_area": true_area, "rows": public}, indent=1,
        default=float))
    lines = [f"# {system.name}: certified regions of attraction", "",
             f"True ROA area (simulation, {len(true_mask)}² grid over {box.tolist()}"
             + (f", within D = {D.describe()}"
                if cfg.get("domain") is not None else ", within the disc" if system.nu else "")
             + (f"): {true_area:.4g}" if true_area else
                "): not available (no grid state reached the origin within the simulated "
                "horizon; the shares below are not given)"), "",
             "| method | certified | level | area | % of true ROA | seconds | status |",
             "|---|---|---|---|---|---|---|"]
    for r in public:
        lines.append(f"| {r['method']} | {'yes' if r['certified'] else 'no'} | "
                     f"{r['level']:.5g} | {r['area']:.4g} | "
                     + (f"{100 * r['fraction_of_true_roa']:.1f}" if true_area else "–")
                     + f" | {r['seconds']:.1f} | "
                     f"{r['status']} |")
    notes = [r for r in public if r.get("notes")]
    if notes:
        lines += ["", "Notes:"] + [f"- {r['method']}: {r['notes']}" for r in notes]
    write_atomic(out / "comparison.md", "\n".join(lines) + "\n")
    _plot(out / "comparison.png", system, rows, true_mask, box, cfg, D)


def _plot(path, system, rows, true_mask, box, cfg, D):
    plt = deps.pyplot()

    n = true_mask.shape[0]
    xs = [lo + (hi - lo) * (np.arange(n) + 0.5) / n for lo, hi in box]
    X1, X2 = np.meshgrid(xs[0], xs[1], indexing="ij")
    fig, ax = plt.subplots(figsize=(7, 6))
    ax.contour(X1, X2, true_mask.astype(float), levels=[0.5], colors="k", linewidths=2)
    handles = [plt.Line2D([], [], color="k", lw=2, label="true ROA")]
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, r in enumerate(rows):
        if r.mask is None:
            continue
        c = colors[i % len(colors)]
        ax.contour(X1, X2, r.mask.astype(float), levels=[0.5], colors=[c], linewidths=1.5)
        handles.append(plt.Line2D([], [], color=c,
                                  label=f"{r.method}: {100 * r.fraction_of_true_roa:.1f}%"))
    ax.plot(*D.outline_2d(0, 1).T, "r--", lw=1)
    handles.append(plt.Line2D([], [], color="r", ls="--", label="verification domain"))
    g = 25
    gp, gs = grid_points(box, g)
    ctrl = None
    if system.nu:
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
    write_figure(fig, path)
    plt.close(fig)
