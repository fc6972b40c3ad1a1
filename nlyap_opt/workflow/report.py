"""``report.md`` and ``roa.png`` of a run."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..certification.certificate import (
    NOT_CHECKED,
    CertStatus,
    load_artifact,
    status_text,
    unchecked,
)
from ..certification.roa import InnerForm, InnerFormKind, grid_points
from ..kernel import deps
from ..kernel.domain import Ball, parse_set
from ..kernel.errors import raise_if_interrupted
from ..kernel.jsonio import write_atomic, write_figure
from ..kernel.network import Network
from ..kernel.provenance import describe

__all__ = ["write_report", "plot_roa", "status_line", "winner_line",
           "write_compositional_report", "plot_subsystems"]


def _fmt(v, digits=4):
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.{digits}g}"
    return str(v)


def _sets(cert: dict, nx: int):
    """``(D, X_I, is_plain_ball)`` of a certificate dict (version 2: the ball of outer_radius)."""
    D = Ball(cert["outer_radius"], nx) if cert.get("domain") is None else \
        parse_set(cert["domain"], nx)
    XI = None if cert.get("initial_set") is None else \
        parse_set(cert["initial_set"], nx, "initial_set", domain=False)
    return D, XI, D.plain_ball


def _is_blowup(text) -> bool:
    """Whether a stored inner-ellipse form is the weighted blow-up."""
    try:
        return InnerForm.parse(str(text)).kind is InnerFormKind.BLOWUP
    except ValueError:
        return False


def status_line(cert: dict) -> str:
    """The status of a certificate dict in words: ``"certified under the declared
    assumptions: …"`` when it rests on declarations about ``f``
    (:func:`nlyap_opt.certification.certificate.status_text`)."""
    return status_text(cert["status"], cert.get("assumptions_declared_by_user") or [])


def winner_line(candidates: list) -> str | None:
    """One sentence on which ``V`` won the comparison of certified volumes (``certificate.json``'s
    ``candidates``): said plainly when a cheap ``V`` (quadratic, SOS) beats the neural one;
    ``None`` without a comparison."""
    if not candidates:
        return None
    neural = candidates[0]
    win = next((c for c in candidates if c["winner"]), None)
    if win is None:
        return None
    others = [c for c in candidates[1:] if c["status"] == CertStatus.CERTIFIED]
    if win is neural:
        if not others:
            return None
        best = max(others, key=lambda c: c["certified_volume"])
        return (f"The neural V certifies a larger volume ({neural['certified_volume']:.4g}) than "
                f"the best cheap V, {best['V']} ({best['certified_volume']:.4g}).")
    why = neural.get("reason") or neural["status"]
    if neural["status"] == CertStatus.CERTIFIED:
        what = f"it certifies a smaller volume ({neural['certified_volume']:.4g})"
    elif unchecked(neural["status"], neural.get("reason")):
        what = f"it was not verified, since {why.removeprefix(NOT_CHECKED + ': ')}"
    else:
        what = f"it certifies no level ({why})"
    return (f"**The neural V did not beat the cheap candidate**: {what}; "
            f"{win['V']} certifies {win['certified_volume']:.4g}, and the certificate below is "
            f"that of {win['V']}. More training (train.steps, cegis.iterations), a "
            "larger network (train.hidden) or, where the log says that few training states "
            "converge in simulation, a longer cegis.sim_time may change this.")


def _stays_line(cert: dict, controlled: bool) -> list[str]:
    """The bound D puts on every certificate: the share of the true ROA within D whose
    trajectories reach the origin without leaving D (none for an older certificate)."""
    stays = cert.get("true_roa_stays_in_domain")
    if stays is None:
        return []
    return [f"Of the true ROA within D, {100 * stays:.1f}% reach the origin without leaving "
            "D: no certificate in D can hold more (a certified set lies in D and no "
            "trajectory leaves it). A larger D"
            + (", or a controller that keeps more states in D," if controlled else "")
            + " can raise this bound." if stays < 1 else
            "Every state of the true ROA within D reaches the origin without leaving D.", ""]


def _outside_states(cert: dict, horizon: float) -> str:
    """The true ROA's states in D that did not reach the origin but did not diverge either:
    at rest at another stable equilibrium (outside the ROA at any horizon), or undecided
    within ``horizon`` (slow, or a periodic orbit: the share may be an overestimate)."""
    rest, left = cert.get("true_roa_elsewhere"), cert.get("true_roa_undecided")
    return ((f" {100 * rest:.1f}% of the grid in D came to rest at another stable "
             "equilibrium (outside the ROA of the origin)." if rest else "")
            + (f" {100 * left:.1f}% of the grid in D neither converged nor diverged within "
               f"the simulated horizon of {horizon:.4g} s and counts outside the true ROA: the "
               "share above may be an overestimate; raise eval_time if they converge slowly "
               "(states on a periodic orbit stay undecided at any horizon)." if left else ""))


def write_report(out: Path, system, cfg: dict, cert: dict, bounds: dict | None, cg: dict):
    """Write ``report.md`` (parameters, what is certified under which assumptions, times)
    and ``roa.png``."""
    lines = [f"# {system.name}: certified region of attraction", ""]
    lines += [f"**Status: {status_line(cert)}** ({cert['dynamics']})", ""]
    if cert["status"] != CertStatus.CERTIFIED:
        lines += [f"Reason: {cert.get('reason', '')}", ""]
    won = winner_line(cert.get("candidates") or [])
    if won:
        lines += [won, ""]
    lines += ["## Parameters (paper's Table layout)", "",
              "| K_f | K_φ | δ | α | η | M = sup‖∇V‖ | β (margin) | ε | r | level |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    b = bounds or {}
    lines.append("| " + " | ".join(_fmt(v) for v in (
        b.get("K_f"), b.get("K_phi"), b.get("delta"), b.get("alpha"), b.get("eta"),
        cert.get("M"), cert["margin"], cert["inner_radius"], cert["outer_radius"],
        cert["level"])) + " |")
    lines += ["", "## What is certified", ""]
    r, eps = cert["outer_radius"], cert["inner_radius"]
    D, XI, ball = _sets(cert, system.nx)
    if not ball:
        lines += [f"Verification domain D = {D.describe()} (r above: max ‖x‖ over D).", ""]
    region = f"{eps:g} ≤ ‖x‖ ≤ {r:g}" if ball else f"x ∈ D, ‖x‖ ≥ {eps:g}"
    lines += [
        f"- (a) decrease {cert.get('decrease_condition', '')} on "
        f"{{{region}, V(x) ≤ {cert['level']:.6g}}} — interval verifier "
        "(outward rounding);",
        f"- (b) containment: V(x) > {cert['level']:.6g} on "
        + (f"‖x‖ = {r:g};" if ball else "the boundary of D (every face of a box);"),
    ]
    ie = cert.get("inner_ellipse")
    if ie:
        blowup = _is_blowup(ie.get("form", ""))
        lines.append(
            f"- (c) inner ball: E = {{xᵀPx ≤ {ie['level']:.4g}}} ⊇ B_ε; "
            + (f"V̇_q < 0 on E∖{{0}} by a weighted blow-up of the origin ({ie['form']}: "
               "∂ᵐ/∂rᵐ of V̇_q(r^w·u) < 0 for r ∈ [0, R] on the faces of the unit cube; "
               "the linearisation is not exponentially stable) (true f): "
               f"{ie['status']}" if ie.get("proved") and blowup else
               "P·J(y) + J(y)ᵀ·P ≺ 0 verified on a box containing E (true f): "
               f"{ie['status']}" if ie.get("proved") else
               "assumed (paper's Assumption 3) for the unknown f; the tool's check on the "
               f"true f: {ie['status']}"))
    if XI is not None:
        lines.append(f"- (d) initial set X_I = {XI.describe()} ⊆ Ω_c (X_I ⊆ D and V < level "
                     f"on X_I): {cert.get('checks', {}).get('(d) X_I ⊆ Ω_c', 'not run')}")
    lines += ["", "Certified set: Ω_c ∪ E with Ω_c = {x ∈ " + ("B_r" if ball else "D")
              + " : V(x) ≤ level}.", "",
              "### Checks (interval verifier)", ""]
    lines += [f"- {k}: {v}" for k, v in cert.get("checks", {}).items()]
    lines += ["", "### Assumptions", ""] + [f"- {a}" for a in cert["assumptions"]]
    if cert.get("assumptions_declared_by_user"):
        lines += ["", "### Assumptions (declared by the user)", ""] + [
            f"- {a}" for a in cert["assumptions_declared_by_user"]]
    if cert.get("not_available"):
        lines += ["", "### Not available", ""] + [
            f"- {a}" for a in cert["not_available"]]
    n_x = len(cert["eval_box"])
    horizon = cert.get("true_roa_time", 60.0)
    if cert.get("true_roa_area") is None:
        why = [a for a in cert.get("not_available") or [] if a.startswith("true ROA")]
        lines += ["", "## Areas", "", f"Certified area: {cert['certified_area']:.4g} (grid count, "
                  f"{cert['eval_grid']}^{n_x} over {np.asarray(cert['eval_box']).tolist()}); "
                  "no share of the true ROA is given: "
                  + (why[0] if why else "the true ROA is not available") + ".", ""]
    else:
        lines += ["", "## Areas", "",
                  "| certified area | true ROA area | certified ÷ true |", "|---|---|---|",
                  f"| {cert['certified_area']:.4g} | {cert['true_roa_area']:.4g} | "
                  f"{100 * cert['fraction_of_true_roa']:.1f}% |", "",
                  *_stays_line(cert, bool(getattr(system, "nu", 0))),
                  "True ROA: simulated closed loop (true f"
                  + (", under the certificate's controller κ: the ROA of this closed loop, "
                     "not every state some input in U could bring to the origin"
                     if getattr(system, "nu", 0) else "")
                  + f") from a {cert['eval_grid']}^{n_x} "
                  f"grid over {np.asarray(cert['eval_box']).tolist()}"
                  + (", intersected with D" if cert.get("domain") is not None else
                     ", intersected with the ball ‖x‖ ≤ r")
                  + f", each state simulated for up to {horizon:.4g} s"
                  + f". Every certified grid point converges in simulation: "
                  f"{cert['certified_points_converge_in_simulation']}."
                  + _outside_states(cert, horizon), ""]
    tc = cert.get("true_dynamics_check")
    if tc:
        lines += ["## Check against the true dynamics (benchmark, not part of the certificate)",
                  "", f"- decrease of the same V under the true f at the same level: "
                  f"{tc['decrease_true_f']}",
                  f"- inner ellipse under the true f: {tc['inner_ball_true_f']}", ""]
    if cert.get("candidates"):
        lines += ["## Best certificate (the larger certified volume wins)", "",
                  "| V | κ | status | level | ε | certified volume | winner |",
                  "|---|---|---|---|---|---|---|"]
        lines += [f"| {c['V']} | {c['controller'] or '—'} | "
                  + (f"not checked (cannot beat the winner) | – | {c['inner']:g} | – | "
                     if unchecked(c["status"], c.get("reason")) else
                     f"{c['status']} | {c['level']:.6g} | {c['inner']:g} | "
                     f"{c['certified_volume']:.4g} | ")
                  + f"{'**yes**' if c['winner'] else 'no'} |" for c in cert["candidates"]]
        lines.append("")
    lines += ["## CEGIS history", "",
              "The candidate level is limited by the decrease (a state where V does not "
              "decrease) or by ∂D (containment: V is smallest on the boundary there; the "
              "states of ∂D with the smallest V are then trained on).", "",
              "| it | loss | candidate level | limited by | status | level | area "
              f"in {'ball' if ball else 'D'} | margin | verify s |",
              "|---|---|---|---|---|---|---|---|---|"]
    for h in cg.get("history", []):
        src = {"sphere": "∂D", "decrease": "decrease"}.get(h.get("candidate_source"), "–")
        lines.append(f"| {h['iteration']} | {h['loss']:.3g} | "
                     f"{h.get('candidate_level', 0.0):.4g} | {src} | "
                     f"{h['status']} | {h['level']:.4g} | {h['area']:.4g} | "
                     f"{h.get('margin', 0.0):.3g} | {h.get('verify_seconds', 0.0):.2f} |")
    if cert.get("provenance"):
        lines += ["", "## Numeric environment (what determined these numbers)", "",
                  "The same input gives the same certificate bit for bit on the same "
                  "fingerprint; re-checking the certificate gives the same verdict anywhere.",
                  ""] + describe(cert["provenance"])
    lines += ["", "## Times (s)", ""] + [f"- {k}: {v:.1f}" for k, v in
                                         cert.get("seconds", {}).items()]
    lines += ["", "![ROA](roa.png)", ""]
    write_atomic(out / "report.md", "\n".join(lines))
    try:
        plot_roa(out / "roa.png", system, cert, out)
    except Exception as err:  # a plot must never lose a certificate
        raise_if_interrupted(err)
        print(f"warning: roa.png not written: {err}")


def plot_roa(path, system, cert: dict, out: Path):
    """V level curves, certified set, domain, phase portrait, true ROA boundary.

    States beyond the first two are shown as the slice through the origin (the other
    states 0), so a run of any dimension gets its picture.
    """
    plt = deps.pyplot()

    arts = cert.get("artifacts", {})   # the certified V and κ (the neural or a cheap one)
    V = load_artifact(out / arts.get("V", {}).get("file", "V.json"),
                      arts.get("V", {}).get("kind", "network"))
    D, XI, _ = _sets(cert, system.nx)
    cfile = out / arts.get("controller", {}).get("file", "controller.json")
    ctrl = Network.load(cfile) if system.nu and cfile.exists() else None
    box = np.asarray(cert["eval_box"], dtype=float)
    nx = len(box)
    if nx == 1:
        return _plot_1d(path, plt, system, cert, out, V, D, ctrl)
    n = 300

    def lift(p2):  # 2-D points of the slice -> states (others 0)
        z = np.zeros((len(p2), nx))
        z[:, :2] = p2
        return z

    pts2, shape = grid_points(box[:2], n)
    pts = lift(pts2)
    xs = [np.linspace(lo, hi, n) for lo, hi in box[:2]]
    v = V.numpy(pts)[:, 0].reshape(shape)
    fig, ax = plt.subplots(figsize=(7, 6))
    X1, X2 = np.meshgrid(xs[0], xs[1], indexing="ij")
    lv = cert["level"]
    if lv > 0 and cert["status"] == CertStatus.CERTIFIED:
        ax.contour(X1, X2, v, levels=np.linspace(lv / 8, 2 * lv, 9), colors="0.75",
                   linewidths=0.6)
        inside = (v <= lv) & D.contains(pts).reshape(shape)
        ax.contourf(X1, X2, inside.astype(float), levels=[0.5, 1.5], colors=["tab:blue"],
                    alpha=0.35)
        ax.contour(X1, X2, v, levels=[lv], colors="tab:blue", linewidths=2)
    ie = cert.get("inner_ellipse")
    if ie:
        q = np.einsum("ij,jk,ik->i", pts, np.asarray(ie["P"]), pts).reshape(shape)
        ax.contour(X1, X2, q, levels=[ie["level"]], colors="tab:green", linewidths=1.2)
    npz = out / "true_roa.npz"
    if npz.exists() and nx == 2 and cert.get("true_roa_area") is not None:
        m = np.load(npz)["mask"]
        xt = [lo + (hi - lo) * (np.arange(m.shape[0]) + 0.5) / m.shape[0] for lo, hi in box]
        T1, T2 = np.meshgrid(xt[0], xt[1], indexing="ij")
        ax.contour(T1, T2, m.astype(float), levels=[0.5], colors="k", linewidths=1.5)
    th = np.linspace(0, 2 * np.pi, 400)
    ax.plot(*D.outline_2d(0, 1).T, "r--", lw=1)
    rad = cert["inner_radius"]
    ax.plot(rad * np.cos(th), rad * np.sin(th), "r:", lw=1)
    if XI is not None:
        ax.plot(*XI.outline_2d(0, 1).T, color="tab:orange", lw=1.5)
    if getattr(system, "can_simulate", True):
        g = 25
        gp2, gs = grid_points(box[:2], g)
        gp = lift(gp2)
        u = None if ctrl is None else ctrl.numpy(gp)
        with np.errstate(all="ignore"):
            F = system.evaluate(gp, u)
        ax.streamplot(np.linspace(box[0, 0], box[0, 1], g),
                      np.linspace(box[1, 0], box[1, 1], g), F[:, 0].reshape(gs).T,
                      F[:, 1].reshape(gs).T, color="0.6", density=0.8, linewidth=0.5,
                      arrowsize=0.6)
    ax.set_xlim(box[0])
    ax.set_ylim(box[1])
    ax.set_xlabel(system.state_names[0])
    ax.set_ylabel(system.state_names[1])
    share = _share_text(cert)
    where = "" if nx == 2 else f" (slice {', '.join(system.state_names[2:])} = 0)"
    ax.set_title(f"{system.name}: {cert['status']} — {share}{where}\n"
                 "blue: Ω_c (V ≤ level in D), green: E, black: true ROA, red: D, B_ε"
                 + (", orange: X_I" if XI is not None else ""),
                 fontsize=9)
    fig.tight_layout()
    write_figure(fig, path)
    plt.close(fig)


def _share_text(cert: dict) -> str:
    frac = cert.get("fraction_of_true_roa")
    return "true ROA not available" if frac is None else \
        f"certified {100 * frac:.1f}% of the true ROA"


def _plot_1d(path, plt, system, cert: dict, out: Path, V, D, ctrl):
    """The picture of a one-state run: V and the closed loop's x' along the evaluation
    interval, the certified set (V ≤ level in D), the true ROA, D and B_ε."""
    lo, hi = np.asarray(cert["eval_box"], dtype=float)[0]
    x = np.linspace(lo, hi, 1001)[:, None]
    v = V.numpy(x)[:, 0]
    fig, (ax, ay) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    ax.plot(x[:, 0], v, color="tab:blue", lw=1.5, label="V")
    lv = cert["level"]
    if lv > 0 and cert["status"] == CertStatus.CERTIFIED:
        ax.axhline(lv, color="tab:blue", ls=":", lw=1, label="level")
        ax.fill_between(x[:, 0], 0, 1, where=(v <= lv) & D.contains(x),
                        transform=ax.get_xaxis_transform(), color="tab:blue", alpha=0.25,
                        label="Ω_c")
    npz = out / "true_roa.npz"
    if npz.exists() and cert.get("true_roa_area") is not None:
        m = np.load(npz)["mask"].ravel()
        xt = lo + (hi - lo) * (np.arange(len(m)) + 0.5) / len(m)
        ax.plot(xt[m], np.zeros(int(m.sum())), "k|", ms=4, label="true ROA")
    if getattr(system, "can_simulate", True):
        with np.errstate(all="ignore"):
            F = system.evaluate(x, None if ctrl is None else ctrl.numpy(x))[:, 0]
        ay.plot(x[:, 0], F, color="0.3", lw=1.2)
        ay.axhline(0.0, color="0.6", lw=0.6)
        ay.set_ylabel(f"{system.state_names[0]}' (closed loop)")
    for a in (ax, ay):
        for b in D.bounding_box()[0]:
            a.axvline(b, color="r", ls="--", lw=1)
        for b in (-cert["inner_radius"], cert["inner_radius"]):
            a.axvline(b, color="r", ls=":", lw=1)
    ax.set_xlim(lo, hi)
    ax.set_ylabel("V")
    ax.legend(fontsize=8, loc="upper center")
    ay.set_xlabel(system.state_names[0])
    share = _share_text(cert)
    ax.set_title(f"{system.name}: {cert['status']} — {share}\n"
                 "blue: Ω_c (V ≤ level in D), black: true ROA, red: D, B_ε", fontsize=9)
    fig.tight_layout()
    write_figure(fig, path)
    plt.close(fig)


# ============================================================================ compositional
def write_compositional_report(out: Path, system, cert, provenance: dict | None = None):
    """Write ``report.md`` and ``subsystems.png`` of a compositional certificate
    (:class:`nlyap_opt.certification.compositional.CompositionalCertificate`): the status,
    what is certified, one row per subsystem, the checks, the assumptions, the numeric
    environment, and per subsystem the projection of the certified set onto its states."""
    out = Path(out)
    names = system.state_names
    lines = [f"# {system.name}: compositional certificate", "",
             f"**Status: {cert.summary()}**", ""]
    if cert.certified:
        box = ", ".join(f"{names[k]} ∈ [{lo:g}, {hi:g}]"
                        for k, (lo, hi) in enumerate(cert.domain_box))
        lines += [
            "## What is certified", "",
            f"Ω_c = {{x : Σ_i w_i x_iᵀ P_i x_i ≤ c}} with c = {cert.level:.6g} lies in the box "
            f"D ({box}), and dV/dt ≤ −{cert.decay:.4g} V on it: Ω_c is forward invariant and "
            "every solution that starts in it converges exponentially to the origin"
            + (" (the dynamics known to the certificate only through sampled values and a "
               "bound on their second derivatives)" if cert.setting == "data" else "") + ".",
            "",
            f"Each subsystem's box was cut into {cert.split} piece(s) per axis, one exact local "
            "test per piece.", "",
            "## Subsystems", "",
            "| # | states | neighbours | w_i | α_i | β_ij | half-widths of Ω_c along its "
            "states |",
            "|---|---|---|---|---|---|---|"]
        for i, (w, p) in enumerate(zip(cert.weights, cert.pieces)):
            inv = np.diag(np.linalg.inv(np.asarray(p.P, dtype=float)))
            half = np.sqrt(cert.level / w * inv)
            nb = ", ".join(str(j + 1) for j in p.neighbours) or "–"
            beta = ", ".join(f"{b:.3g}" for b in p.beta) or "–"
            lines.append(f"| {i + 1} | {', '.join(names[k] for k in p.states)} | {nb} | "
                         f"{w:.4g} | {p.alpha:.4g} | {beta} | "
                         + ", ".join(f"{names[k]}: {h:.3g}" for k, h in zip(p.states, half))
                         + " |")
    else:
        lines += ["## Why not certified", "", cert.reason or "–"]
    if cert.checks:
        lines += ["", "## Checks", ""] + [f"- {k}: {v}" for k, v in cert.checks.items()]
    lines += ["", "## Assumptions", ""] + [f"- {a}" for a in cert.assumptions]
    if provenance:
        lines += ["", "## Numeric environment (what determined these numbers)", "",
                  "The same input gives the same certificate bit for bit on the same "
                  "fingerprint; re-checking the certificate gives the same verdict anywhere.",
                  ""] + describe(provenance)
    lines += ["", "## Times (s)", "", f"- certification: {cert.seconds:.2f}"]
    if cert.certified:
        lines += ["", "![subsystems](subsystems.png)"]
    write_atomic(out / "report.md", "\n".join(lines) + "\n")
    if cert.certified:
        try:
            plot_subsystems(out / "subsystems.png", system, cert)
        except Exception as err:  # a plot must never lose a certificate
            raise_if_interrupted(err)
            print(f"warning: subsystems.png not written: {err}")


#: at most this many subsystems are drawn in ``subsystems.png``
PLOTTED_SUBSYSTEMS = 25


def plot_subsystems(path, system, cert):
    """Per subsystem (the first :data:`PLOTTED_SUBSYSTEMS`), the projection of the certified
    set onto its states — exactly the ellipse ``w_i x_iᵀ P_i x_i ≤ c`` (the other terms of V
    are ≥ 0 and vanish at 0) — inside the box D; a subsystem of one state is an interval, of
    more than two the slice of its first two states."""
    plt = deps.pyplot()
    pieces = cert.pieces[:PLOTTED_SUBSYSTEMS]
    cols = min(5, len(pieces))
    rows = (len(pieces) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 3.0 * rows), squeeze=False)
    names = system.state_names
    box = cert.domain_box
    t = np.linspace(0, 2 * np.pi, 241)
    for ax, (i, (w, p)) in zip(axes.ravel(), enumerate(zip(cert.weights, pieces))):
        P = np.asarray(p.P, dtype=float)
        ks = list(p.states)
        if len(ks) == 1:
            h = np.sqrt(cert.level / (w * P[0, 0]))
            ax.plot([-h, h], [0, 0], lw=4, color="tab:green")
            ax.set_xlim(box[ks[0]] * 1.05)
            ax.set_yticks([])
            ax.axvline(box[ks[0], 0], color="k")
            ax.axvline(box[ks[0], 1], color="k")
        else:
            # the projection of {w xᵀPx ≤ c} onto two coordinates is {yᵀ S⁻¹ y ≤ c/w},
            # S the 2x2 block of P⁻¹ (the shadow of an ellipsoid is an ellipse)
            S = np.linalg.inv(P)[:2, :2]
            L = np.linalg.cholesky(S * cert.level / w)
            e = L @ np.vstack([np.cos(t), np.sin(t)])
            ax.fill(e[0], e[1], color="tab:green", alpha=0.35, label="certified (projection)")
            ax.plot(e[0], e[1], color="tab:green")
            bx, by = box[ks[0]], box[ks[1]]
            ax.plot([bx[0], bx[1], bx[1], bx[0], bx[0]], [by[0], by[0], by[1], by[1], by[0]],
                    color="k", lw=1, label="box D")
            ax.set_ylabel(names[ks[1]])
            ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel(names[ks[0]])
        ax.set_title(f"subsystem {i + 1}", fontsize=9)
    for ax in axes.ravel()[len(pieces):]:
        ax.axis("off")
    more = len(cert.pieces) - len(pieces)
    fig.suptitle(f"{system.name}: projections of the certified set"
                 + (f" (first {len(pieces)} of {len(cert.pieces)} subsystems)" if more else ""),
                 fontsize=10)
    fig.tight_layout()
    write_figure(fig, path)
    plt.close(fig)
