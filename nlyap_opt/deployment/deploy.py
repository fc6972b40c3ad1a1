r"""Using a certificate: a re-verified run, samples of its certified set, closed-loop runs.

:func:`load_run` opens a finished run directory through
:func:`nlyap_opt.certification.certificate.recheck_run` (the artifacts' sha256 checked, conditions
(a), (b), (c) proved again at the saved level): nothing a run directory holds is used before
that re-check has passed. :class:`CertifiedRun` then gives ``V``, ``κ``, the certified set
``Ω_c ∪ E`` and the closed loop (true ``f`` or learned ``φ``);
:func:`simulate_run` integrates trajectories from seeded samples of the certified set (and,
for contrast, from outside it) and checks what the certificate promises: every trajectory
started inside stays inside, ``V`` does not increase on ``Ω_c∖B_ε``, and it converges.

Sampling. ``Ω_c`` is the connected component of ``{x ∈ D : V(x) ≤ c}`` that holds the
origin. The points kept by rejection are those of the whole sublevel set; no other
component exists when (a) and (b) hold: such a component ``K`` would be compact, miss
``B_ε`` (which lies in the origin's component), and be forward invariant (a solution cannot
raise ``V`` above ``c`` nor cross ``∂D``, where ``V > c``), so ``V`` would attain its
minimum over ``K`` at a point where ``V̇ < 0`` — a contradiction.
"""

from __future__ import annotations

import io
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from ..certification.certificate import RoaCertificate, RoaProblem, recheck_run, sha256_file
from ..kernel import deps
from ..kernel.errors import ConfigError
from ..kernel.jsonio import write_atomic, write_figure
from ..kernel.simulate import horizon, jacobian_at_origin, trajectories
from ..kernel.symbolic import learned_rhs
from ..kernel.walker import evaluate

__all__ = ["CertifiedRun", "SimulationResult", "load_run", "simulate_run", "plot_simulation"]


@dataclass
class CertifiedRun:
    """A run whose certificate was proved again from its hashed artifacts.

    Attributes
    ----------
    directory : Path
    certificate : RoaCertificate     the re-verified certificate (``CERTIFIED``)
    problem : RoaProblem             ``V``, ``κ``, ``φ``, the system, the domain
    sha256 : str                     of ``certificate.json`` (the file re-checked)
    """

    directory: Path
    certificate: RoaCertificate
    problem: RoaProblem
    sha256: str

    @property
    def system(self):
        return self.problem.system

    @property
    def level(self) -> float:
        return self.certificate.level

    def V(self, pts) -> np.ndarray:
        """``V`` at ``(N, nx)`` points."""
        return self.problem.V_numpy(np.atleast_2d(np.asarray(pts, dtype=float)))

    def kappa(self, pts) -> np.ndarray:
        """``κ`` at ``(N, nx)`` points, ``(N, nu)`` (``u_eq`` without a controller)."""
        pts = np.atleast_2d(np.asarray(pts, dtype=float))
        c = self.problem.controller
        if c is None:
            return np.broadcast_to(self.system.u_eq, (len(pts), self.system.nu)).copy()
        return c.numpy(pts)

    def contains(self, pts) -> np.ndarray:
        """Membership of the certified set ``Ω_c ∪ E`` (the certificate's own test)."""
        return self.certificate.contains(pts)

    def in_omega(self, pts) -> np.ndarray:
        """``x ∈ D`` and ``V(x) ≤ c`` (``Ω_c``, see the module docstring)."""
        pts = np.atleast_2d(np.asarray(pts, dtype=float))
        return self.problem.domain.contains(pts) & (self.V(pts) <= self.level)

    def dynamics_available(self) -> list[str]:
        """``"true"`` (the system can be evaluated anywhere) and/or ``"learned"`` (a φ)."""
        out = ["true"] if getattr(self.system, "can_simulate", True) else []
        if self.problem.dynamics is not None:
            out.append("learned")
        return out

    def vector_field(self, which: str, feedback: Callable | None = None) -> Callable:
        """``x ↦ f(x, u(x))`` on ``(N, nx)`` batches; ``which`` is ``"true"`` or ``"learned"``;
        ``feedback`` (``(N, nx) -> (N, nu)``) defaults to ``κ``."""

        sysm = self.system
        if which not in self.dynamics_available():
            have = " or ".join(f"--{w}" for w in self.dynamics_available()) or "nothing"
            raise ConfigError(f"run {self.directory} has no {which} dynamics to simulate; "
                              f"use {have}")
        feedback = feedback or self.kappa
        if which == "true" and not getattr(sysm, "has_model", True):
            return lambda z: sysm.evaluate(z, feedback(z) if sysm.nu else None)

        x, u = ca.SX.sym("x", sysm.nx), ca.SX.sym("u", sysm.nu)
        rhs = sysm.f_fun(x, u) if which == "true" else learned_rhs(
            sysm, self.problem.dynamics, x, u)
        F = ca.Function("f", [x, u], [rhs])
        return lambda z: evaluate(F, [z, np.asarray(feedback(z), dtype=float).reshape(
            len(z), sysm.nu)])[0]

    def sample_box(self) -> np.ndarray:
        """A box holding ``D`` and ``E``: the rejection sampler's box."""
        box = self.problem.domain.bounding_box().copy()
        E = self.certificate.inner_ellipse
        if E is not None and len(E.half_widths) == len(box):
            box[:, 0] = np.minimum(box[:, 0], -E.half_widths)
            box[:, 1] = np.maximum(box[:, 1], E.half_widths)
        return box

    def sample(self, n: int, rng: np.random.Generator, *, inside: bool = True,
               max_draws: int | None = None) -> np.ndarray:
        """``n`` uniform samples of the certified set (``inside``) or of ``D`` outside it,
        by rejection in :meth:`sample_box` (at most ``max_draws``, default
        ``max(10⁷, 10⁴·n)``, draws)."""
        box = self.sample_box() if inside else self.problem.domain.bounding_box()
        max_draws = max(10**7, 10**4 * n) if max_draws is None else max_draws
        keep, drawn = [], 0
        while sum(len(k) for k in keep) < n:
            if drawn >= max_draws:
                raise ConfigError(
                    f"fewer than {n} of {drawn} uniform draws in {box.tolist()} fell "
                    f"{'inside' if inside else 'outside'} the certified set of "
                    f"{self.directory}; ask for fewer points")
            m = max(4 * n, 4096)
            pts = box[:, 0] + (box[:, 1] - box[:, 0]) * rng.random((m, len(box)))
            drawn += m
            ok = self.contains(pts)
            if not inside:
                ok = ~ok & self.problem.domain.contains(pts)
            keep.append(pts[ok])
        return np.vstack(keep)[:n]


def load_run(path: str | Path, *, system=None, allow_factory: bool = False,
             log=print) -> CertifiedRun:
    """Open a run directory (or its ``certificate.json``) for use, after the re-check.

    ``system`` and ``allow_factory``: as for
    :func:`nlyap_opt.certification.certificate.recheck_certificate` (the system to re-check
    against; a spec file's factory runs only with ``allow_factory``).

    Raises
    ------
    ConfigError
        No certificate there, or it does not re-verify (an artifact missing or changed, a
        condition no longer proved, a run that was never certified): one line with the
        reason and the fix.
    """
    path = Path(path)
    cfile = path / "certificate.json" if path.is_dir() else path
    if not cfile.is_file():
        if (path / "portfolio.json").is_file():
            raise ConfigError(f"{path} is the directory of a portfolio (`nlyap run --seeds`): "
                              f"pass its best run, {path / 'best'}, or one seed's directory")
        raise ConfigError(f"{path}: no certificate.json there; pass the directory of a "
                          "finished `nlyap run`")
    cert, problem = recheck_run(cfile, system=system, allow_factory=allow_factory, log=log)
    if problem is None or not cert.certified:
        raise ConfigError(f"run {cfile.parent} holds no certified set that re-verifies "
                          f"({cert.status.value}: {cert.reason}); rerun `nlyap run` (see "
                          f"`nlyap verify --certificate {cfile.parent}`)")
    return CertifiedRun(cfile.parent, cert, problem, sha256_file(cfile))


@dataclass
class SimulationResult:
    """Trajectories from inside and outside the certified set, and the checks.

    ``t``: ``(T + 1,)`` times; ``inside``, ``outside``: ``(T + 1, N, nx)`` trajectories;
    ``V_inside``: ``(T + 1, N)``; the per-trajectory checks of the inside ones are
    ``stayed`` (in the certified set at every step), ``monotone`` (``V`` did not increase
    by more than ``1e-6·c`` over a step that starts in ``Ω_c∖B_ε``) and ``converged``
    (``‖x(T)‖ ≤ tol``; with learned φ: reached ``B_ε``, where the certificate stops
    speaking about φ). ``refined``: trajectories that left the set or raised ``V`` at the
    step asked for and not when integrated again in finer steps (kept as integrated again:
    the step was too coarse for them).
    """

    dynamics: str
    t: np.ndarray
    inside: np.ndarray
    outside: np.ndarray
    V_inside: np.ndarray
    stayed: np.ndarray
    monotone: np.ndarray
    converged: np.ndarray
    tol: float
    refined: int = 0
    failures: list[str] = field(default_factory=list)

    @property
    def violated(self) -> bool:
        """A trajectory left the certified set or raised ``V`` (contradicts the proof)."""
        return not (self.stayed.all() and self.monotone.all())

    @property
    def ok(self) -> bool:
        return not self.violated and bool(self.converged.all())

    def summary(self) -> str:
        n = self.inside.shape[1]
        return (f"{n} trajectories from inside the certified set ({self.dynamics} dynamics): "
                f"{int(self.stayed.sum())} stayed inside, {int(self.monotone.sum())} with V "
                f"non-increasing on Ω_c∖B_ε, {int(self.converged.sum())} converged; "
                f"{self.outside.shape[1]} from outside (no claim)"
                + (f"; {self.refined} integrated again in {RISE_REFINE} sub-steps per step "
                   "(at the step asked for they left the set or raised V: lower --dt)"
                   if self.refined else ""))

    def save(self, path: str | Path, **extra) -> None:
        """``trajectories.npz``: the arrays above (and ``extra`` ones)."""
        buf = io.BytesIO()
        np.savez_compressed(buf, t=self.t, inside=self.inside, outside=self.outside,
                            V_inside=self.V_inside, stayed=self.stayed,
                            monotone=self.monotone, converged=self.converged, **extra)
        path = Path(path)   # as np.savez names it: .npz added where the name lacks it
        write_atomic(path if path.suffix == ".npz" else path.with_name(path.name + ".npz"),
                     buf.getvalue())


#: a step over which V rose is integrated again in this many RK4 sub-steps before it counts
RISE_REFINE = 64


def _confirmed_rises(run: CertifiedRun, f, Xi: np.ndarray, rise: np.ndarray, dt: float,
                     tol: float) -> np.ndarray:
    """``rise`` with each step over which ``V`` rose by more than ``tol`` integrated again
    from its start in :data:`RISE_REFINE` sub-steps: the rise that stays is the refined
    one. The certificate speaks of the flow, and one RK4 step of a stiff closed loop (a
    fast mode, or a safety filter's input that turns within the step) can raise ``V`` by
    its integration error alone (seen: 1.1·10⁻⁵ at ``dt = 0.01``, none at 0.005 and 0.002,
    on a pendulum loop with a mode of speed 120)."""
    jj, kk = np.nonzero(rise > tol)
    if not len(jj):
        return rise
    x0 = Xi[jj, kk]
    x1 = trajectories(f, x0, dt, RISE_REFINE)[-1]
    v1 = np.full(len(x1), np.inf)
    ok = np.isfinite(x1).all(axis=1)
    v1[ok] = run.V(x1[ok])
    out = rise.copy()
    out[jj, kk] = v1 - run.V(x0)
    return out


def _judged(run: CertifiedRun, f, Xi: np.ndarray, h: float):
    """``(inside, V, rise)`` of trajectories ``Xi`` (steps of ``h``): in the certified set at
    each sample, ``V`` there, and ``V``'s rise over each step that starts in ``Ω_c∖B_ε``
    (``-inf`` elsewhere), confirmed by :func:`_confirmed_rises`."""
    flat = Xi.reshape(-1, Xi.shape[-1])
    finite = np.isfinite(flat).all(axis=1)
    inside = np.zeros(len(flat), bool)
    Vf = np.full(len(flat), np.inf)
    inside[finite] = run.contains(flat[finite])
    Vf[finite] = run.V(flat[finite])
    in_omega = np.zeros(len(flat), bool)
    in_omega[finite] = run.in_omega(flat[finite])
    inside, Vt = inside.reshape(Xi.shape[:2]), Vf.reshape(Xi.shape[:2])
    norms = np.linalg.norm(Xi, axis=2)
    step_from = in_omega.reshape(Xi.shape[:2])[:-1] & (norms[:-1] >= run.certificate.inner)
    with np.errstate(invalid="ignore"):   # inf - inf after a blow-up: no rise claimed
        rise = np.where(step_from, Vt[1:] - Vt[:-1], -np.inf)
    rise = _confirmed_rises(run, f, Xi, rise, dt=h, tol=1e-6 * run.level)
    return inside, Vt, rise


def _refined_trajectories(f, x0: np.ndarray, h: float, steps: int, sub: int) -> np.ndarray:
    """The trajectories from ``x0`` integrated with ``sub`` RK4 sub-steps per step of
    ``h``, kept at the ``steps + 1`` times of the coarse grid."""
    out = np.empty((steps + 1,) + x0.shape)
    out[0] = x = x0
    for k in range(steps):
        out[k + 1] = x = trajectories(f, x, h, sub)[-1]
    return out


#: at most this many trajectories that seem to contradict the certificate are integrated
#: again (each costs 72 times its first integration)
REFINE_AT_MOST = 8


def _integrate_again(run: CertifiedRun, f, x_in, bad, h: float, steps: int, arrays,
                     dt: float) -> tuple[int, list[int]]:
    """Integrate the first :data:`REFINE_AT_MOST` trajectories of ``bad`` (which left the
    set or raised ``V`` at the step ``h``) again, with :data:`RISE_REFINE` and with
    ``RISE_REFINE // 8`` sub-steps per step, and put the finer one into ``arrays`` (``Xi,
    inside, V, rise``, updated in place). A contradiction must be the flow's, not the
    integrator's: one stands where the finer integration still shows it and the two
    integrations agree (``|a − b| ≤ 10⁻³(1 + |a|)`` per coordinate) up to it, the sample
    that ends a step over which ``V`` rose included. Returns the number of those
    trajectories that no longer contradict anything, and the indices of those whose
    contradiction stands.

    Raises
    ------
    ConfigError
        No contradiction stands, but one was not resolved (the two integrations disagree)
        or not integrated again: the step ``dt`` is too coarse for this closed loop.
    """
    Xi, inside, Vt, rise = arrays
    pick = bad[:REFINE_AT_MOST]
    fine = _refined_trajectories(f, x_in[pick], h, steps, RISE_REFINE)
    half = _refined_trajectories(f, x_in[pick], h, steps, RISE_REFINE // 8)
    f_in, f_V, f_rise = _judged(run, f, fine, h)
    # a rise over the step j -> j + 1 is shown at its end, sample j + 1
    risen = np.vstack([np.zeros((1, len(pick)), bool), f_rise > 1e-6 * run.level])
    wrong = ~f_in | risen                      # (steps + 1, k): a contradiction at a sample
    upto = np.cumsum(np.cumsum(wrong, axis=0), axis=0) <= 1   # samples up to the first one
    with np.errstate(invalid="ignore"):
        agree = (np.abs(fine - half) <= 1e-3 * (1.0 + np.abs(fine))).all(axis=2)
    resolved = (agree | ~upto).all(axis=0)
    contradicts = wrong.any(axis=0)
    Xi[:, pick], inside[:, pick], Vt[:, pick], rise[:, pick] = fine, f_in, f_V, f_rise
    if not (contradicts & resolved).any() and \
            (len(bad) > len(pick) or (contradicts & ~resolved).any()):
        again = "their finer integrations disagree" if (contradicts & ~resolved).any() else \
            f"the {len(pick)} integrated again in finer steps do not"
        raise ConfigError(f"--dt {dt:g} is too coarse for this closed loop: {len(bad)} "
                          f"trajectories left the certified set or raised V with it, and "
                          f"{again}; lower --dt")
    return int((~contradicts).sum()), [int(k) for k in pick[contradicts & resolved]]


def _first(mask: np.ndarray, confirmed: list[int], n: int = 3) -> list[int]:
    """The first ``n`` trajectories of ``mask``, those in ``confirmed`` (integrated again,
    their contradiction standing) first."""
    return ([k for k in confirmed if mask[k]] +
            [int(k) for k in np.flatnonzero(mask) if k not in confirmed])[:n]


#: ``nlyap simulate``'s horizon where none is given, before :func:`default_horizon` extends it
SIM_HORIZON = 20.0


def default_horizon(run: CertifiedRun, dynamics: str | None = None) -> float:
    """:data:`SIM_HORIZON`, extended for a closed loop whose slowest linear mode at the
    origin needs longer to bring the certified set's states to the convergence tolerance of
    :func:`simulate_run` (:func:`nlyap_opt.kernel.simulate.horizon`: at most ten times as
    long). ``dynamics`` as in :func:`simulate_run`."""
    avail = run.dynamics_available()
    if not avail:
        return SIM_HORIZON
    which = dynamics or avail[0]
    f = run.vector_field(which)
    box = run.sample_box()
    eps = run.certificate.inner
    tol = eps if which == "learned" else 1e-2 * eps
    A = jacobian_at_origin(f, run.system.nx)
    return horizon(SIM_HORIZON, A, float(np.linalg.norm(np.max(np.abs(box), axis=1))), tol)


def simulate_run(run: CertifiedRun, *, points: int = 200, outside: int | None = None,
                 horizon: float = SIM_HORIZON, dt: float = 0.01, dynamics: str | None = None,
                 seed: int = 0, feedback: Callable | None = None,
                 tol: float | None = None, confirm: bool = True) -> SimulationResult:
    """Closed-loop trajectories from ``points`` seeded samples of the certified set.

    Parameters
    ----------
    run : CertifiedRun
    points : int
        Starting points inside (``outside`` defaults to a quarter of it, outside, in ``D``).
    horizon, dt : float
        Simulated time and the RK4 step (:func:`nlyap_opt.kernel.simulate.trajectories`); a
        step over which ``V`` rose is integrated again in finer steps before it counts
        (:func:`_confirmed_rises`).
    dynamics : {"true", "learned"}, optional
        Default: the true ``f`` where the run has it, else ``φ``.
    feedback : callable, optional
        The input law (``(N, nx) -> (N, nu)``), default ``κ`` (the safety filter passes
        its own).
    tol : float, optional
        Convergence radius (default ``10⁻²·`` the inner radius ε).
    confirm : bool
        Integrate trajectories that leave the set or raise ``V`` again in finer steps
        (:func:`_integrate_again`); ``False`` for a run that claims nothing (the unfiltered
        nominal controller of a safety filter).
    """

    if points < 1 or not (horizon > 0 and dt > 0):
        raise ConfigError(f"need points >= 1, horizon > 0 and dt > 0, got {points}, "
                          f"{horizon}, {dt}; fix the values")
    avail = run.dynamics_available()
    if not avail:
        raise ConfigError(f"the system of {run.directory} cannot be simulated (samples only, "
                          "no learned φ saved)")
    which = dynamics or avail[0]
    f = run.vector_field(which, feedback)
    rng = np.random.default_rng(seed)
    x_in = run.sample(points, rng)
    n_out = points // 4 if outside is None else outside
    x_out = run.sample(n_out, rng, inside=False) if n_out else np.zeros((0, run.system.nx))
    steps = int(np.ceil(horizon / dt))
    h = horizon / steps
    X = trajectories(f, np.vstack([x_in, x_out]), horizon, steps)
    Xi, Xo = X[:, :points], X[:, points:]
    inside, Vt, rise = _judged(run, f, Xi, h)
    bad = np.flatnonzero(~inside.all(axis=0) | (rise > 1e-6 * run.level).any(axis=0))
    refined, confirmed = 0, []
    if len(bad) and confirm:
        refined, confirmed = _integrate_again(run, f, x_in, bad, h, steps,
                                              (Xi, inside, Vt, rise), dt)
    c, eps = run.level, run.certificate.inner
    norms = np.linalg.norm(Xi, axis=2)
    monotone = ~(rise > 1e-6 * c).any(axis=0)
    stayed = inside.all(axis=0)
    tol = 1e-2 * eps if tol is None else tol
    if which == "learned":
        converged = (norms <= eps).any(axis=0)
    else:
        converged = norms[-1] <= tol
    res = SimulationResult(which, np.linspace(0.0, steps * h, steps + 1), Xi, Xo, Vt, stayed,
                           monotone, converged, tol, refined=refined)
    for k in _first(~stayed, confirmed):
        j = int(np.argmin(inside[:, k]))
        res.failures.append(f"trajectory {k} from {x_in[k].tolist()} left the certified set at "
                            f"t = {res.t[j]:.4g} (x = {Xi[j, k].tolist()})")
    for k in _first(~monotone, confirmed):
        res.failures.append(f"trajectory {k} from {x_in[k].tolist()}: V rose by "
                            f"{np.max(rise[:, k]):.3g} over one step in Ω_c∖B_ε")
    for k in _first(~converged, []):
        res.failures.append(f"trajectory {k} from {x_in[k].tolist()} has not converged by "
                            f"t = {horizon:g} (‖x‖ = {norms[-1, k]:.3g})")
    return res


def plot_simulation(run: CertifiedRun, res: SimulationResult, out: str | Path,
                    title: str = "", nominal: SimulationResult | None = None) -> Path:
    """``simulate.png``: the trajectories over the certified set (n = 2: the phase plane;
    n > 2: the projection on the two states that move most, over the slice of the set
    through the origin), and ``V(x(t))/c`` below; ``nominal``: an unfiltered run drawn in
    orange for contrast."""
    plt = deps.pyplot()

    n = run.system.nx
    names = list(getattr(run.system, "state_names", [])) or [f"x{i}" for i in range(n)]
    fig, axes = plt.subplots(2, 1, figsize=(7.5, 10), height_ratios=[3, 1.3])
    ax = axes[0]
    if n == 2:
        i, j = 0, 1
    else:
        spread = np.nanmax(np.abs(res.inside), axis=(0, 1))
        i, j = sorted(np.argsort(spread)[-2:].tolist())
    box = run.sample_box()
    pad = 0.15 * (box[:, 1] - box[:, 0])
    lo, hi = box[:, 0] - pad, box[:, 1] + pad
    g = 300 if n == 2 else 200
    gx, gy = np.meshgrid(np.linspace(lo[i], hi[i], g), np.linspace(lo[j], hi[j], g))
    pts = np.zeros((g * g, n))
    pts[:, i], pts[:, j] = gx.ravel(), gy.ravel()
    mask = run.contains(pts).reshape(g, g)
    ax.contourf(gx, gy, mask.astype(float), levels=[0.5, 1.5], colors=["#c8e6c9"])
    ax.contour(gx, gy, mask.astype(float), levels=[0.5], colors=["green"], linewidths=1.5)
    dom = run.problem.domain
    if hasattr(dom, "outline_2d"):
        ol = dom.outline_2d(i, j)
        ax.plot(ol[:, 0], ol[:, 1], "k--", lw=1, label="domain D" + (" (slice)" if n > 2 else ""))
    for k in range(res.outside.shape[1]):
        tr = res.outside[:, k]
        ax.plot(tr[:, i], tr[:, j], color="0.6", lw=0.6, alpha=0.7,
                label="from outside (no claim)" if k == 0 else None)
    if nominal is not None:
        for k in range(nominal.inside.shape[1]):
            tr = nominal.inside[:, k]
            ax.plot(tr[:, i], tr[:, j], color="tab:orange", lw=0.6, alpha=0.8,
                    label="nominal, unfiltered (no claim)" if k == 0 else None)
    for k in range(res.inside.shape[1]):
        tr = res.inside[:, k]
        ax.plot(tr[:, i], tr[:, j], color="tab:red" if not (res.stayed[k] and
                res.converged[k]) else "tab:blue", lw=0.7,
                label="from the certified set" if k == 0 else None)
    ax.plot(res.inside[0, :, i], res.inside[0, :, j], "o", ms=2.5, color="tab:blue")
    ax.plot(0, 0, "k+", ms=10)
    ax.set_xlim(lo[i], hi[i])
    ax.set_ylim(lo[j], hi[j])
    ax.set_xlabel(names[i])
    ax.set_ylabel(names[j])
    where = "" if n == 2 else " (projection; green: slice of the certified set through 0)"
    ax.set_title((title + "\n" if title else "") + f"certified set Ω_c ∪ E (green), "
                 f"{res.dynamics} dynamics{where}", fontsize=9)
    ax.legend(loc="upper right", fontsize=8)
    ax = axes[1]
    c = run.level
    for k in range(res.V_inside.shape[1]):
        ax.semilogy(res.t, np.maximum(res.V_inside[:, k] / c, 1e-12), color="tab:blue",
                    lw=0.6, alpha=0.7)
    ax.axhline(1.0, color="green", lw=1.5, label="level c")
    ax.set_xlabel("t")
    ax.set_ylabel("V(x(t)) / c")
    ax.set_ylim(1e-8, 2.0)
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(res.summary(), fontsize=8, wrap=True)
    fig.tight_layout()
    out = write_figure(fig, out)
    plt.close(fig)
    return out
