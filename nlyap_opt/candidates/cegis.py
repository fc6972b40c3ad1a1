"""Counterexample-guided learning of ``V`` and ``κ`` with a certified level (CEGIS).

Each iteration: train on the state samples plus the counterexamples found so far; export
the float64 networks (the verified objects); if the dynamics are learned, recompute the
margin ``β = M·η`` with ``M`` a rigorous bound of ``‖∇V‖`` on the ball; find a candidate
level by NLP; certify conditions (a) and (b) at the largest level reachable from it.
Confirmed counterexamples (and a few neighbours) go back into training. When the level is
limited by containment on the domain's boundary ``∂D`` rather than by the decrease, the
states of ``∂D`` where ``V`` is smallest (and the level-limiting point) join the
containment training states instead, and the loop goes on until the certified area stops
growing. The best certificate (by certified area) is kept. With ``best_iterate`` the
verifier proves the most promising iterate since its last call (the largest candidate set)
and, after the call, training resumes from the best certified iterate when the current one
collapsed (its candidate set, which bounds what it can certify, fell below
``RESUME_BELOW`` of the best certified area).

Before training (the default method): a trained controller may start from another LQR
weighting that keeps more of ``D`` in ``D`` under the model (``gain_scan``); the training
simulations step at most ``STIFF_STEP/ρ(A)`` for the closed loop's fastest mode; and a loop
stiffer than ``STIFF_RATIO`` trains V with the Lyapunov-risk terms instead of the fit to
trajectory costs (``fit_fallback``).
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field, replace

import numpy as np
import torch
from scipy.interpolate import RegularGridInterpolator

from ..certification.certificate import (
    CertStatus,
    RoaCertificate,
    RoaProblem,
    VolumeToBeat,
    certify_roa,
)
from ..certification.roa import axis_count, candidate_level, grid_area, grid_points
from ..design.control import lqr
from ..kernel.determinism import deterministic_torch
from ..kernel.domain import Ball, as_domain, parse_set
from ..kernel.errors import InputRangeError
from ..kernel.network import Network
from ..kernel.simulate import (
    STIFF_STEP,
    Integration,
    horizon,
    integration,
    linear_modes,
    simulate,
)
from .learning import LearnerState, LyapunovLearner, TrainConfig, label_boundary_states, sample_ball
from .quadratic import LEARNED_SEARCH_STATES

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
    later_lr: float = 1.0            # their learning rate, as a fraction of train.lr
    # at most this many more iterations, verify_every at a time, while the verifier call of
    # the last one certified an area more than `plateau` above the best before it
    extend: int = 0
    verify_every: int = 1            # run the verifier every k-th iteration (and the last);
    # in between, the sampled violations of the candidate level are the counterexamples
    target_fraction: float = 0.99    # stop when certified level >= this fraction of candidate
    min_iterations: int = 1          # ... but not before this many iterations (best area kept)
    # ... and, when the candidate is limited by sampled decrease violations (source
    # "decrease", which more training may remove), only once the certified area is within
    # this fraction of the best earlier one (grew by less; an area further below it is a V
    # behind the best, which may still grow)
    plateau: float = 0.01
    # a candidate level limited by ∂D (source "sphere"): this many states of ∂D with the
    # smallest V (from a fresh sample of 4·sphere_samples) and the level-limiting point
    # join the containment training states, and CEGIS goes on until the certified area is
    # within ``plateau`` of the best earlier one; 0: stop at the first such certified level
    boundary_feedback: int = 200
    # the verifier (every verify_every-th iteration) proves the iterate with the largest
    # candidate set D ∩ {V ≤ candidate level} since its last call, not only the last one;
    # after the call, an iterate whose candidate set collapsed below RESUME_BELOW of the best
    # certified area hands training back to the best certified iterate's weights
    best_iterate: bool = False
    area_points: int = 40000         # grid of the certified areas (total points)
    verify_options: dict = field(default_factory=dict)
    train: TrainConfig = field(default_factory=TrainConfig)
    seed: int = 0
    inner_samples: int = 0           # extra training states in ε ≤ ‖x‖ ≤ 3ε
    boundary_samples: int = 0        # extra training states near the model's ROA boundary
    sim_dt: float = 0.02             # RK4 step of those simulations
    sim_points: int = 0              # learned φ: table of it for them, total nodes (0: none)
    sim_time: float = 20.0           # simulated horizon of the training states (convergence, cost)
    # a training state 'converges' once ‖x‖ < sim_tol within sim_time (raise it, up to the
    # inner radius, for an origin that attracts slowly: x' = -x³ takes 5000 s to 0.01)
    sim_tol: float = 1e-2
    # a training state whose simulated trajectory leaves the domain D counts as not
    # converging (target at its cap): a certified sublevel set lies in D and is forward
    # invariant, so it holds only states that reach the origin without leaving D
    sim_in_domain: bool = False
    # learned dynamics: "pointwise" verifies ∇V·φ + η‖∇V(x)‖ < 0 (Cauchy–Schwarz: implies
    # ∇V·f < 0 wherever ‖f − φ‖ ≤ η); "global" verifies the paper's ∇V·φ < −β, β = M·η
    margin_mode: str = "pointwise"
    # pointwise mode: verify with sqrt(‖∇V‖² + s²), s = norm_smoothing·M (costs at most
    # norm_smoothing·β of slack; keeps the verifier's mean-value form near the inner ball)
    norm_smoothing: float = 1e-3
    # the verification domain D (None: the ball of radius outer) and the initial set X_I
    # (given in the run config's top-level 'domain' and 'initial_set' keys)
    domain: object = None
    initial_set: object = None
    initial_samples: int = 2000      # training states in X_I (pulled into V ≤ level)
    # a trained controller starts from the LQR gain of the weighting (Q = I, or one state
    # weighed w in GAIN_WEIGHTS times the others) that keeps the largest share of D's states in D
    # on their way to the origin under the model, when that share beats the given start's by
    # more than GAIN_MARGIN (the caller turns it off where the user chose the LQR weights)
    gain_scan: bool = False
    # a closed loop stiffer than STIFF_RATIO at the origin trains V with the LYAPUNOV_RISK
    # settings instead of the fit (train.w_fit) to trajectory costs
    fit_fallback: bool = False


@dataclass
class CegisResult:
    """Result of :func:`cegis`: the best certified iterate (by area), one history entry per
    iteration. ``status`` is :attr:`CertStatus.CERTIFIED` or ``NOT_CERTIFIED`` (``reason``)."""

    status: CertStatus
    V: Network | None
    controller: Network | None
    level: float
    margin: float
    M: float | None
    area: float
    history: list
    seconds: float
    smoothing: float = 0.0       # s of the pointwise condition (see robust_lie)
    reason: str = ""

    @property
    def certified(self) -> bool:
        return self.status is CertStatus.CERTIFIED


def _simulation_rhs(learner, system, cfg, tabulate: bool, fast: bool = False):
    """The closed-loop model as a numpy function for the training simulations.

    With ``fast`` and untabulated, the true f with a model is evaluated through its CasADi
    graph (numpy) with the current κ: the same numbers as the torch graph to rounding at a
    tenth of its cost per step, for the many short steps of a stiff loop and the gain scan
    (a loop that keeps ``cegis.sim_dt`` keeps the torch graph, and its training stays
    bit-identical to the runs measured before the scan). A learned φ (a wide network) is
    tabulated once on a grid of ``sim_points`` nodes over the ball's box and interpolated
    (multilinear, SciPy) when the state has at most 3 dimensions: the simulations only shape
    the training targets, and a table is an order of magnitude faster than the network over
    ~10⁴ steps.
    """

    if fast and not tabulate and learner.dynamics is None \
            and getattr(system, "has_model", True):
        _, ctrl = learner.export()

        def model_np(x):
            return system.evaluate(x, None if ctrl is None else ctrl.numpy(x))

        return model_np

    def rhs_np(x):
        with torch.no_grad():
            return learner.rhs(torch.as_tensor(x)).numpy()

    if not tabulate or system.nx > 3 or not cfg.sim_points:
        return rhs_np

    m = axis_count(cfg.sim_points, system.nx)
    box = _domain(cfg, system.nx).bounding_box()
    axes = [np.linspace(lo, hi, m) for lo, hi in box]
    nodes = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, system.nx)
    table = rhs_np(nodes).reshape(*[m] * system.nx, system.nx)
    return RegularGridInterpolator(axes, table, bounds_error=False, fill_value=None)


def _domain(cfg: CegisConfig, nx: int):
    """``D`` of the configuration: its ``domain``, else the ball of radius ``outer``."""
    return Ball(cfg.outer, nx) if cfg.domain is None else as_domain(cfg.domain, nx)


def cost_targets(converged: np.ndarray, cost: np.ndarray, w_c: float, cap: float,
                 transform: str = "log") -> tuple[np.ndarray, np.ndarray]:
    r"""Targets for ``V`` from simulated trajectory costs :math:`W` (:func:`simulate`).

    ``W`` decreases along trajectories at rate :math:`\|x\|^2` and grows without bound
    towards the boundary of the region of attraction, so its sublevel sets approach it.
    The target is :math:`T = g(W) / g(W_c)` (``T = 1`` at cost ``w_c``), capped at ``cap``
    (and ``cap`` for states that do not converge); ``g(W) = W`` (``"linear"``) or
    :math:`\log(1 + W/a)`, ``a = w_c / 6`` (``"log"``: tames the steep rise near the
    boundary). Returns ``(T, rates)`` with ``dT/dt = −rate·‖x‖²`` along trajectories
    (rate 0 where ``T`` is capped).
    """
    W = np.where(converged, cost, np.inf)
    if transform == "linear":
        g, dg, gc = W, np.ones_like(W), w_c
    elif transform == "log":
        a = w_c / 6.0
        with np.errstate(invalid="ignore"):
            g, dg, gc = np.log1p(W / a), 1.0 / (a + W), np.log1p(w_c / a)
    else:
        raise ValueError(f"unknown fit_transform {transform!r}; expected 'linear' or 'log'")
    T = g / gc
    capped = ~(T < cap)
    return np.where(capped, cap, T), np.where(capped, 0.0, dg / gc)


#: gain scan (cegis.gain_scan): the LQR weightings tried besides the start are
#: Q = I + (w − 1)·e_i e_iᵀ, one state weighed w times the others, for w in GAIN_WEIGHTS
#: (half decades; a much larger weight makes the slow mode too slow to converge within
#: cegis.sim_time, which the scan's share counts against it)
GAIN_WEIGHTS = (3.0, 10.0, 30.0)
#: ... a weighting replaces the start only when it keeps more than this share more of the
#: sampled states of D in D on their way to the origin (the start wins ties and near-ties)
GAIN_MARGIN = 0.05
#: ... on this many of the training states drawn uniformly in D
GAIN_STATES = 2000


def _stay_share(learner, system, cfg: CegisConfig, D, X: np.ndarray, tabulate: bool) -> float:
    """Share of ``X`` that the model's closed loop with the learner's current gain takes to
    the origin within ``cegis.sim_time`` without leaving ``D``."""
    rhs = _simulation_rhs(learner, system, cfg, tabulate, fast=True)
    how = integration(cfg.sim_dt, learner.closed_loop_jacobian().detach().numpy())
    return float(np.mean(simulate(rhs, X, t_final=cfg.sim_time, dt=how.dt, tol=cfg.sim_tol,
                                  stay=D.contains, jacobian=how.jacobian)[0]))


def _scan_gain(learner, system, dynamics, cfg: CegisConfig, D, X: np.ndarray, log) -> None:
    """``cegis.gain_scan``: start from the LQR weighting whose closed loop keeps the most
    states of ``D`` in ``D`` (see :class:`CegisConfig`); sets the learner's gain."""
    Xs = X[:GAIN_STATES]
    tabulate = dynamics is not None
    start = learner.G.detach().clone()
    best = (_stay_share(learner, system, cfg, D, Xs, tabulate), "the LQR start", start)
    first = best[0]
    n = system.nx
    for i, w in itertools.product(range(n), GAIN_WEIGHTS):
        Q = np.eye(n)
        Q[i, i] = w
        try:
            K = lqr(system, Q, None, dynamics=None if getattr(system, "has_model", True)
                    else dynamics).K
        except (ValueError, np.linalg.LinAlgError):
            continue
        learner.set_gain(torch.as_tensor(K, dtype=torch.float64))
        share = _stay_share(learner, system, cfg, D, Xs, tabulate)
        if share > best[0]:
            best = (share, f"LQR with Q = I, Q[{i},{i}] = {w:g}",
                    learner.G.detach().clone())
    chosen = best if best[0] > first + GAIN_MARGIN else (first, "the LQR start", start)
    learner.set_gain(chosen[2])
    log(f"  cegis: gain scan: the LQR start keeps {100 * first:.1f} % of {len(Xs)} states of "
        f"D in D on their way to the origin, the best weighting ({best[1]}) "
        f"{100 * best[0]:.1f} %; κ starts from {chosen[1]}")


#: cegis.fit_fallback: the Zubov-type fit is not used on a closed loop whose linearisation
#: at the origin is stiffer than this (the fastest mode's speed over the slowest mode's
#: decay rate). Measured on the pendulum: the fit certifies at stiffness 23 (LQR of Q = I)
#: and fails at 133, 217 and 427 (the candidate level stays below 0.06, V near 0.03 on parts
#: of ∂D): the decrease law's residual, relative to R(x)‖x‖², weighs every error of ∇V
#: along the fast direction by that mode's speed, and the trajectory cost barely rises
#: across the fast direction (its transient costs ~d²/(2|λ_fast|))
STIFF_RATIO = 50.0
#: ... such a loop trains V with these train settings instead (the Lyapunov-risk recipe of
#: the catalogue presets: V ≤ 1 pulled on the converging states, the decrease asked at rate
#: τ = decay where V ≤ 1 + level_slack, containment on ∂D; no fit)
LYAPUNOV_RISK = {"w_fit": 0.0, "w_pde": 0.0, "decay": 0.1, "w_inside": 1.0,
                 "relative_decrease": False, "level_slack": 0.1, "w_outside": 1.0}


def stiffness(A) -> float:
    """The stiffness ``ρ(A) / min |Re λ|`` of a linearisation (1 for a single rate; 0 where a
    mode does not decay at all, a centre: its origin is slow, not stiff, and keeps the fit)."""
    fast, slow = linear_modes(A)
    return fast / slow if slow > 1e-9 * max(fast, 1.0) else 0.0


#: fewer converging training states than this share of them: the run says to raise
#: cegis.sim_time (the trajectory-cost fit rests on too few states)
MIN_CONVERGED = 0.01

#: exponent of the domain gauge in the lifted fit target (train.fit_domain): the lift only
#: matters near the domain's boundary
DOMAIN_TARGET_POWER = 8


#: best_iterate: training resumes from the best certified iterate when the current
#: iterate's candidate set is below this share of the best certified area. Smaller dips are
#: trained through: a level often grows again after a round of counterexamples or ∂D states
#: lowered it (power system, true f: 8.3 → 8.0 → 9.2), and resuming at every dip keeps
#: returning to an early iterate
RESUME_BELOW = 0.9
#: ... and each such resumption multiplies the learning rate of the later rounds by this
#: (their steps collapsed V once: smaller ones fine-tune the best iterate instead)
RESUME_LR = 0.5


def _level_settled(source: str, area: float, prev_area: float, plateau: float,
                   boundary_feedback: bool = True) -> bool:
    """Whether CEGIS may stop at a certified level that reaches its candidate.

    A candidate limited by sampled decrease violations (``"decrease"``) may grow when training
    removes them; one limited by the domain's boundary (``"sphere"``) may grow when training
    raises ``V`` where it is smallest on ``∂D`` (``boundary_feedback``; without it, it cannot
    grow and CEGIS stops). Otherwise CEGIS goes on until the certified area stops changing:
    within ``plateau`` (a fraction) of the best earlier certified area. An area more than
    that below it is no plateau: the current V is behind the best one (after a collapse,
    or a resumption from the best), and later rounds may still grow it past the best, which
    is kept whatever they give.
    """
    if source == "sphere" and not boundary_feedback:
        return True
    return prev_area > 0 and (1 - plateau) * prev_area <= area <= (1 + plateau) * prev_area


def _boundary_minima(V: Network, D, n: int, count: int, rng) -> np.ndarray:
    """The ``count`` states of ``n`` fresh samples of ``∂D`` where ``V`` is smallest,
    smallest first (ties in sample order: deterministic for a seeded ``rng``)."""
    pool = D.sample_boundary(n, rng)
    order = np.argsort(V.numpy(pool)[:, 0], kind="stable")
    return pool[order[:count]]


def _feed_boundary(cfg: CegisConfig, V: Network, D, cand, rim: np.ndarray, cap: int, rng,
                   entry: dict, log) -> np.ndarray:
    """Containment on ``∂D`` limits the level: the level-limiting point and the states of
    ``∂D`` where ``V`` is smallest join ``rim`` (the fed-back containment states, at most
    ``cap``, the newest kept); records their number in the history ``entry``."""
    low = _boundary_minima(V, D, 4 * cfg.sphere_samples, cfg.boundary_feedback, rng)
    rim = np.vstack([rim, cand.argmin.reshape(1, -1), low])[-cap:]
    entry["boundary_feedback"] = len(low) + 1
    log(f"  cegis: the level is limited by ∂D; {len(low) + 1} states of ∂D with the "
        f"smallest V join the containment training ({len(rim)} in all)")
    return rim


def cegis(system, controller: Network | None, dynamics: Network | None, cfg: CegisConfig, *,
          eta: float = 0.0, dynamics_box=None, input_box=None, log=print,
          V0: Network | None = None, beat: VolumeToBeat | None = None) -> CegisResult:
    """Learn ``V`` (and ``κ``) and certify a level; see the module docstring.

    Parameters
    ----------
    system : systems.System
    controller : Network or None     initial controller (LQR-initialised)
    dynamics : Network or None       learned φ (``None``: the true f, known-dynamics setting)
    cfg : CegisConfig
    eta : float                      error bound ``‖f − φ‖ ≤ η`` on the box (learned case)
    dynamics_box, input_box : (nx, 2), (nu, 2) array_like
        Where ``‖f − φ‖ ≤ η`` holds (learned dynamics); each iterate is certified with
        :func:`nlyap_opt.certification.certificate.certify_roa`, which checks ``κ ∈ U`` and the
        ball.
    beat : VolumeToBeat, optional
        The run's best cheap certificate: an iterate whose candidate level's volume bound
        (:meth:`~nlyap_opt.certification.certificate.VolumeToBeat.bound`) cannot exceed it is
        not verified (its sampled violations are its counterexamples, as between
        ``verify_every`` iterations); the history entry says why (``skipped``).
    """
    with deterministic_torch(cfg.train.threads):   # fixed threads: bit-identical results
        return _cegis(system, controller, dynamics, cfg, eta, dynamics_box, input_box, log, V0,
                      beat)


def _samples(cfg: CegisConfig, D, XI, rng, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The training states (in ``D``, more next to the inner ball and in ``X_I``) and the
    states on ``∂D``."""
    X = D.sample(cfg.samples, rng)
    if cfg.inner_samples:  # the decrease is hardest to learn next to the inner ball
        near = sample_ball(cfg.inner_samples, n, 3 * cfg.inner, rng, cfg.inner)
        X = np.vstack([X, near[D.contains(near)]])
    S = D.sample_boundary(cfg.sphere_samples, rng)
    if XI is not None and cfg.initial_samples:   # X_I must end inside V ≤ level
        xi = XI.sample(cfg.initial_samples, rng)
        X = np.vstack([X, xi[D.contains(xi)]])
    return X, S


def _fit_targets(cfg: CegisConfig, D, X, rhs_np, rng, scale: float, log, how: Integration):
    """Simulate the training states under the model (``how``): ``(X, weights,
    targets, rates)``, the states (more around the model's ROA boundary when fitting), the
    pull of ``V ≤ 1`` on each and the trajectory-cost targets (``None`` without ``w_fit``)."""
    stay = D.contains if cfg.sim_in_domain else None
    # fit_domain: the largest gauge of D along each simulated trajectory (see below)
    track = D.gauge if cfg.train.w_fit and cfg.train.fit_domain else None
    conv, cost, *peak = simulate(rhs_np, X, t_final=cfg.sim_time, dt=how.dt,
                                 tol=cfg.sim_tol, stay=stay, track=track,
                                 jacobian=how.jacobian)
    log(f"  cegis: {int(conv.sum())}/{len(X)} training states converge under the model"
        + (" without leaving the domain" if stay is not None else ""))
    if cfg.train.w_fit and conv.sum() < max(MIN_CONVERGED * len(X), 1):
        log(f"  cegis: {'no' if not conv.any() else 'too few'} training states reach "
            f"‖x‖ < {cfg.sim_tol:g} within cegis.sim_time = {cfg.sim_time:g} s under the "
            "model for a fit of V to trajectory costs"
            + ("" if conv.any() else " (none is made)")
            + "; raise cegis.sim_time (or cegis.sim_tol, up to the inner radius)")
    weights = conv.astype(float)
    targets, rates = None, None
    tc = cfg.train
    if tc.w_fit and conv.any():
        w_c = float(np.quantile(cost[conv], tc.fit_quantile))
        if cfg.boundary_samples:
            # more states around the model's ROA boundary: half where the cost is high, half
            # on segments across the jump of the target to its cap
            T = cost_targets(conv, cost, w_c, tc.fit_cap, tc.fit_transform)[0]
            near = X[(T >= 0.8) & (T < tc.fit_cap)]
            half = cfg.boundary_samples // 2
            extra = label_boundary_states(X, T < tc.fit_cap, cfg.boundary_samples - half, rng)
            if len(near):
                jit = near[rng.integers(0, len(near), half)]
                extra = np.vstack([extra, jit + 0.03 * scale * rng.standard_normal(jit.shape)])
            if len(extra):
                extra = extra[D.contains(extra)]
                c2, w2, *p2 = simulate(rhs_np, extra, t_final=cfg.sim_time, dt=how.dt,
                                       tol=cfg.sim_tol, stay=stay, track=track,
                                       jacobian=how.jacobian)
                X, conv, cost = np.vstack([X, extra]), np.r_[conv, c2], np.r_[cost, w2]
                peak = [np.r_[peak[0], p2[0]]] if peak else peak
        targets, rates = cost_targets(conv, cost, w_c, tc.fit_cap, tc.fit_transform)
        if tc.fit_domain:
            # containment (b): the target rises to 1 + s where the trajectory from x reaches
            # ∂D. h(x), the largest gauge of D along it (1 on ∂D), is non-increasing along
            # trajectories, so the lifted target keeps the decrease law's direction, and
            # its sublevel sets below 1 + s hold only states whose trajectories stay in D
            rim = np.minimum((1.0 + tc.level_slack) * peak[0] ** DOMAIN_TARGET_POWER,
                             tc.fit_cap)
            lift = rim > targets
            targets, rates = np.where(lift, rim, targets), np.where(lift, 0.0, rates)
        # the pull of V ≤ 1 on the states whose target is at most 1: those with cost ≤ w_c,
        # less those whose target the domain lifted (their trajectories come close to ∂D:
        # pulling them inside would fight containment there)
        weights = (conv & (cost <= w_c)).astype(float)
        log(f"  cegis: fitting V to the trajectory cost ({tc.fit_transform}; level 1 at cost "
            f"{w_c:.4g}, {len(X)} states)")
    return X, weights, targets, rates



@dataclass
class _Iterate:
    """One CEGIS iterate awaiting (or after) its verification."""

    V: Network
    ctrl: Network | None
    problem: RoaProblem
    cand: object                 # its LevelCandidate
    entry: dict                  # its history entry (completed by _record)
    margins: tuple               # (margin, M, smoothing) of its decrease condition
    state: LearnerState | None   # the learner's state after it (best_iterate)
    verified: bool = False       # its entry holds a verifier call's result
    lost: np.ndarray | None = None   # (window's result) the counterexamples of the
    #                                  iterates verified before it that lost


def candidate_area(V: Network, level: float, grid: np.ndarray, in_d: np.ndarray, shape,
                   box) -> float:
    """Area of ``D ∩ {V ≤ level}`` on the area grid (``in_d``: which grid points lie in D).

    For the candidate level this bounds what the iterate can certify: the verifier's search
    only lowers a level, so its certified set lies in this one (up to the inner ellipse,
    which lies in every certified set alike).
    """
    if not level > 0:
        return 0.0
    inside = in_d & (V.numpy(grid)[:, 0] <= level)
    return grid_area(inside.reshape(shape), np.asarray(box, dtype=float))


def _most_promising(pending: list) -> _Iterate:
    """The iterate with the largest candidate set (``candidate_area``), the latest among
    equals, preferring one that can beat the cheap certificate (not ``skipped``); the only
    one without ``best_iterate``."""
    if len(pending) == 1:
        return pending[0]
    return max(reversed(pending),
               key=lambda x: (not x.entry["skipped"], x.entry["candidate_area"]))


def _record(x: _Iterate, cert: RoaCertificate, area: float) -> None:
    """Complete the history entry of iterate ``x`` with its verification ``cert``."""
    margin, M, smoothing = x.margins
    x.entry.update({"status": cert.status.value, "reason": cert.reason, "level": cert.level,
                    "margin": margin, "M": M, "smoothing": smoothing, "area": area,
                    "verify_seconds": cert.seconds, "checks": cert.checks,
                    "boxes": sum((h.get("boxes", 0) for h in cert.history), 0),
                    "counterexamples": int(len(cert.counterexamples))})


def _unverified(x: _Iterate, system, dynamics, cfg: CegisConfig, D) -> RoaCertificate:
    """The record of an iterate the verifier did not run on: its sampled violations."""
    why = x.entry.get("skipped") or "candidate only"
    return RoaCertificate(CertStatus.NOT_CERTIFIED, f"not verified ({why})",
                          system.name, "known" if dynamics is None else "learned", 0.0,
                          cfg.inner, x.problem.outer, counterexamples=x.cand.violations,
                          domain=D)


def _verify_window(pending: list, here: _Iterate, log, beat: VolumeToBeat | None = None,
                   best_area: float = 0.0, areas: _AreaGrid | None = None
                   ) -> tuple[_Iterate, RoaCertificate | None]:
    """Verify the most promising iterate of ``pending`` (the iterates since the last call);
    ``None`` when its candidate level is not positive or it cannot beat the cheap
    certificate (``skipped``). When it certifies no more than ``best_area`` (the best
    certified area so far; measured on ``areas``) — its candidate level held a violation
    the samples missed — the next most promising iterate whose candidate set is larger
    than both is verified too, and so on: the window's result is the first that certifies
    more than ``best_area``, else the one that certified most (the others' entries record
    their own verification); only up to
    :data:`~nlyap_opt.candidates.quadratic.LEARNED_SEARCH_STATES` states, where a
    verification costs seconds. In more than
    :data:`~nlyap_opt.candidates.quadratic.LEARNED_SEARCH_STATES` states, where each level
    check costs minutes, the level search does not go below the least level that can still
    beat it (:meth:`VolumeToBeat.least_level`; the counterexamples of the levels below it
    are then not found)."""
    chosen = _most_promising(pending)
    if chosen is not here:
        log(f"  cegis: iteration {chosen.entry['iteration']} has the largest candidate "
            f"set since the last verification ({chosen.entry['candidate_area']:.4g} "
            f"against {here.entry['candidate_area']:.4g}); it is the one verified")
    cert = _verify_iterate(chosen, log, beat)
    if cert is None or areas is None or len(pending) == 1 or \
            chosen.problem.system.nx > LEARNED_SEARCH_STATES:
        return chosen, cert
    done = [(chosen, cert, cert.area(areas.box, areas.count) if cert.certified else 0.0)]
    while done[-1][2] <= best_area:
        bar = max(best_area, max(a for _, _, a in done))
        rest = [x for x in pending if all(x is not y for y, _, _ in done)
                and x.entry["candidate_area"] > bar and not x.entry["skipped"]]
        if not rest:
            break
        nxt = _most_promising(rest)
        log(f"  cegis: iteration {done[-1][0].entry['iteration']} certified no more than "
            f"the best so far ({best_area:.4g}); iteration {nxt.entry['iteration']}, whose "
            f"candidate set ({nxt.entry['candidate_area']:.4g}) could, is verified too")
        c = _verify_iterate(nxt, log, beat)
        if c is None:
            break
        done.append((nxt, c, c.area(areas.box, areas.count) if c.certified else 0.0))
    # a runner-up that beats the best wins; else the first choice, as without the rule
    win = done[-1] if done[-1][2] > best_area else done[0]
    losers = [(x, c, a) for x, c, a in done if x is not win[0]]
    for x, c, a in losers:
        _record(x, c, a)
        x.verified = True
        _log_iterate(log, x, c.certified)
    if losers:  # their real counterexamples are fed back too
        n = win[0].problem.system.nx
        win[0].lost = np.vstack([np.reshape(c.counterexamples, (-1, n)) for _, c, _ in losers])
    return win[0], win[1]


def _verify_iterate(x: _Iterate, log, beat: VolumeToBeat | None) -> RoaCertificate | None:
    """The verifier's search for the largest certified level of iterate ``x`` from its
    candidate level (``None``: not positive, or ``x`` cannot beat the cheap certificate)."""
    if not x.cand.level > 0 or x.entry["skipped"]:
        return None
    least = beat.least_level(x.problem) \
        if beat is not None and x.problem.system.nx > LEARNED_SEARCH_STATES else 0.0
    return certify_roa(x.problem, x.cand.level, search=True, check_inner_ellipse=False,
                       log=lambda m: log("  " + m),
                       least=(least, beat.label) if least > 0 else None)


def _record_and_log(chosen: _Iterate, here: _Iterate, cert: RoaCertificate, area: float,
                    run: tuple, log) -> None:
    """History entries and log lines of the verified iterate ``chosen`` and, when another,
    of the current one ``here`` (its sampled violations only); ``run`` = (system,
    dynamics, cfg, D)."""
    _record(chosen, cert, area)
    if chosen is not here and not here.verified:  # (verified: recorded by _verify_window)
        _record(here, _unverified(here, *run), 0.0)
    _log_iterate(log, chosen, cert.certified)
    if chosen is not here and not here.verified:
        _log_iterate(log, here, False)


def _extended(limit: int, cfg: CegisConfig, area: float, prev_area: float, log
              ) -> tuple[int, bool]:
    """The iteration budget after the verifier call of its last iteration certified
    ``area``, more than ``plateau`` above the best before (``prev_area``): ``verify_every``
    more iterations, up to ``iterations + extend`` in all; and whether this iteration is
    still the last."""
    new = min(limit + cfg.verify_every, cfg.iterations + cfg.extend)
    if new > limit:
        log(f"  cegis: the last verified area grew ({prev_area:.4g} -> {area:.4g}); "
            f"{new - limit} more iteration(s), {new} in all (cegis.extend)")
    return new, new == limit


def _log_iterate(log, x: _Iterate, certified: bool) -> None:
    e = x.entry
    log(f"  cegis iteration {e['iteration']}: loss {e['loss']:.4g}, candidate level "
        f"{e['candidate_level']:.4g} ({e['candidate_source']}), "
        f"{'certified' if certified else e['reason']} level "
        f"{e['level']:.4g}, area {e['area']:.4g}, margin {e['margin']:.3g}")


def _add_counterexamples(cex: np.ndarray, new: np.ndarray, cfg: CegisConfig, scale: float,
                         rng, extra: np.ndarray | None = None) -> np.ndarray:
    """``new`` counterexamples (and ``extra`` states) and ``cfg.neighbours`` jittered copies
    of each join ``cex`` (the newest ``cfg.max_counterexamples`` kept)."""
    n = cex.shape[1]
    if extra is not None and len(extra):
        new = np.vstack([np.reshape(new, (-1, n)), extra])
    if not len(new):
        return cex
    jitter = new[:, None, :] + 0.01 * scale * rng.standard_normal((len(new), cfg.neighbours, n))
    new = np.vstack([new, jitter.reshape(-1, n)])
    return np.vstack([cex, new])[-cfg.max_counterexamples:]


def _extra_states(chosen: _Iterate, here: _Iterate, cand) -> np.ndarray | None:
    """The states fed back besides the verified iterate's counterexamples: the current
    iterate's sampled violations when another was verified (``cand``: its candidate), and
    the counterexamples of the window's iterates verified before ``chosen`` that lost."""
    parts = [] if chosen is here else [cand.violations]
    if chosen.lost is not None:
        parts.append(chosen.lost)
    parts = [np.reshape(p, (-1, chosen.problem.system.nx)) for p in parts if p is not None]
    return np.vstack(parts) if parts else None


def _resume(learner: LyapunovLearner, best: tuple, area: float, x: _Iterate, log,
            lr_factor: float) -> None:
    """Training goes on from the best certified iterate ``best`` = (iteration, state), the
    later rounds at ``lr_factor`` times their learning rate."""
    x.entry["resumed_from"] = best[0]
    learner.load_state(best[1])
    log(f"  cegis: the candidate set of iteration {x.entry['iteration']} "
        f"({x.entry['candidate_area']:.4g}) is below {RESUME_BELOW:g} of the best certified "
        f"area ({area:.4g}); training goes on from iteration {best[0]}, later rounds at "
        f"{lr_factor:g}× their learning rate")


class _AreaGrid:
    """The grid of the certified areas over ``D``'s bounding box."""

    def __init__(self, D, points: int):
        self.box = D.bounding_box()
        self.count = axis_count(points, D.n)
        self.grid, self.shape = grid_points(self.box, self.count)
        self.in_d = D.contains(self.grid)

    def candidate(self, V: Network, level: float) -> float:
        return candidate_area(V, level, self.grid, self.in_d, self.shape, self.box)


def outward_normals(D, pts: np.ndarray) -> np.ndarray:
    """Unit outward normals of ``∂D`` at ``pts``: the normalised gradient of ``D``'s gauge
    (central differences; at a box's edge, the mean of its faces' normals)."""
    pts = np.asarray(pts, dtype=float)
    h = 1e-6 * max(D.max_norm(), 1e-12)
    grad = np.stack([D.gauge(pts + h * e) - D.gauge(pts - h * e)
                     for e in np.eye(pts.shape[1])], axis=1)
    return grad / np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-300)


def _train_round(learner, cfg: CegisConfig, it: int, eta: float, margin: float, X, S, cex,
                 weights, targets, rates, D=None, lr_scale: float = 1.0):
    """One round of training (``first_steps`` in the first iteration; the later ones at
    ``train.lr · later_lr · lr_scale``)."""
    steps = (cfg.first_steps or cfg.train.steps) if it == 0 else cfg.steps
    lr = learner.config.lr * (1.0 if it == 0 else cfg.later_lr * lr_scale)
    pointwise = eta if (eta > 0 and cfg.margin_mode == "pointwise") else 0.0
    normals = outward_normals(D, S) if cfg.train.w_inward and D is not None else None
    return learner.train(X, S, 0.0 if pointwise else margin, cex if len(cex) else None,
                         steps=steps, inside_weight=weights, eta_pointwise=pointwise,
                         targets=targets, target_rates=rates, sphere_normals=normals, lr=lr)


def _setup(system, controller, dynamics, cfg: CegisConfig, D, X: np.ndarray, V0, log):
    """The learner before training, the model's closed loop for the training simulations,
    their integration, whether V is trained with the Lyapunov-risk terms and the simulated
    horizon (``cegis.sim_time``, longer for a loop with a slow mode:
    :func:`nlyap_opt.kernel.simulate.horizon`): the gain scan
    (``cegis.gain_scan``), the integration for the loop's fastest mode
    (:func:`nlyap_opt.kernel.simulate.integration`: RK4 at a step it is stable for, ROS2 at
    ``cegis.sim_dt`` for a very stiff loop) and,
    on a stiff loop, the recipe without the fit (``cegis.fit_fallback``)."""
    learner = LyapunovLearner(system, controller, dynamics, cfg.train, V=V0)
    if cfg.gain_scan and controller is not None and learner.config.train_controller:
        _scan_gain(learner, system, dynamics, cfg, D, X, log)
    A = learner.closed_loop_jacobian().detach().numpy()
    how = integration(cfg.sim_dt, A)
    rhs_np = _simulation_rhs(learner, system, cfg, tabulate=dynamics is not None,
                             fast=how.dt < cfg.sim_dt or how.jacobian is not None)
    if how.jacobian is not None:
        log(f"  cegis: the training simulations use the linearly implicit ROS2 at "
            f"cegis.sim_dt = {cfg.sim_dt:g} s: the model's closed loop has a mode of speed "
            f"{linear_modes(A)[0]:.4g} at the origin, and RK4 would need "
            f"{linear_modes(A)[0] * cfg.sim_dt / STIFF_STEP:.0f} steps per step")
    elif how.dt < cfg.sim_dt:
        log(f"  cegis: the training simulations step {how.dt:.3g} s, not cegis.sim_dt = "
            f"{cfg.sim_dt:g} s: the model's closed loop has a mode of speed "
            f"{STIFF_STEP / how.dt:.4g} at the origin")
    t = horizon(cfg.sim_time, A, D.max_norm(), cfg.sim_tol)
    if t > cfg.sim_time:
        log(f"  cegis: the training simulations run {t:.4g} s, not cegis.sim_time = "
            f"{cfg.sim_time:g} s: the model's closed loop has a slow mode at the origin "
            f"(decay rate {linear_modes(A)[1]:.3g} per s)")
    risk = cfg.fit_fallback and cfg.train.w_fit > 0 and stiffness(A) > STIFF_RATIO
    if risk:
        slow, fast = linear_modes(A)[1], linear_modes(A)[0]
        log(f"  cegis: the model's closed loop is stiff at the origin (modes from {slow:.3g} "
            f"to {fast:.4g} per s, ratio {stiffness(A):.0f} > {STIFF_RATIO:g}): V is trained "
            "with the Lyapunov-risk terms, not fitted to trajectory costs "
            "(cegis.fit_fallback)")
        gain = None if controller is None else learner.G.detach().clone()
        learner = LyapunovLearner(system, controller, dynamics,
                                  replace(cfg.train, **LYAPUNOV_RISK), V=V0)
        if gain is not None:
            learner.set_gain(gain)
    return learner, rhs_np, how, risk, t


def _cegis(system, controller, dynamics, cfg, eta, dynamics_box, input_box, log, V0, beat):
    t0 = time.perf_counter()
    rng = np.random.default_rng(cfg.seed)
    n = system.nx
    D = _domain(cfg, n)
    XI = None if cfg.initial_set is None else \
        parse_set(cfg.initial_set, n, "initial_set", domain=False)
    scale = D.max_norm()    # the ball's radius; jitter of extra states is relative to it
    X, S = _samples(cfg, D, XI, rng, n)
    rim = np.zeros((0, n))   # boundary states fed back when ∂D limits the level
    learner, rhs_np, how, risk, sim_time = _setup(system, controller, dynamics, cfg, D, X, V0,
                                                  log)
    X, weights, targets, rates = _fit_targets(
        replace(cfg, sim_time=sim_time, **({"train": learner.config} if risk else {})),
        D, X, rhs_np, rng, scale, log, how)
    areas = _AreaGrid(D, cfg.area_points)
    cex = np.zeros((0, n))
    best: CegisResult | None = None
    best_state = None        # (iteration, the learner's state) of the best certified iterate
    pending: list[_Iterate] = []   # iterates since the last verifier call
    history = []
    margin, M, smoothing = 0.0, None, 0.0
    # the budget (grows by `extend` while the last verifier call still gains) and the
    # iteration after the last verifier call (windows of verify_every count from it)
    limit, since = cfg.iterations, 0
    for it in range(cfg.iterations + cfg.extend):
        if it >= limit:
            break
        info = _train_round(learner, cfg, it, eta, margin, X, np.vstack([S, rim]), cex,
                            weights, targets, rates, D,
                            RESUME_LR ** sum("resumed_from" in h for h in history))
        V, ctrl = learner.export()
        problem = RoaProblem(system, V, ctrl, dynamics, inner=cfg.inner, outer=cfg.outer,
                             eta=eta, margin_mode=cfg.margin_mode,
                             norm_smoothing=cfg.norm_smoothing, dynamics_box=dynamics_box,
                             input_box=input_box, verify_options=cfg.verify_options,
                             domain=D, initial_set=XI)
        try:
            dec = problem.decrease()
        except InputRangeError as err:  # κ leaves U: no certificate for this iterate
            log(f"  cegis iteration {it}: {err}")
            history.append({"iteration": it, "loss": info.loss, "status": str(err),
                            "level": 0.0, "area": 0.0})
            continue
        M, margin, smoothing = dec.M, dec.margin, dec.smoothing
        cand = candidate_level(dec.x, dec.V, dec.lie, inner=cfg.inner, domain=D,
                               margin=dec.margin, seed=cfg.seed + it)
        last = it == limit - 1
        here = _new_iterate(it, info, problem, cand, (margin, M, smoothing), cfg, eta, areas,
                            learner, beat, log)
        entry = here.entry
        if risk:
            entry["recipe"] = "lyapunov-risk"
        history.append(entry)
        pending = [*pending, here] if cfg.best_iterate else [here]
        chosen, cert = here, None
        if last or (it + 1 - since) % cfg.verify_every == 0:
            chosen, cert = _verify_window(pending, here, log, beat,
                                          best.area if best is not None else 0.0, areas)
            pending, since = [], it + 1
        # falsifier only: the sampled violations that limit the candidate
        cert = cert or _unverified(chosen, system, dynamics, cfg, D)
        area = cert.area(areas.box, areas.count) if cert.certified else 0.0
        _record_and_log(chosen, here, cert, area, (system, dynamics, cfg, D), log)
        prev_area = best.area if best is not None else 0.0
        if cert.certified and (best is None or area > best.area):
            best = CegisResult(CertStatus.CERTIFIED, chosen.V, chosen.ctrl, cert.level,
                               *chosen.margins[:2], area, history, 0.0, chosen.margins[2])
            best_state = (chosen.entry["iteration"], chosen.state)
        # the stop rule judges the current V: an earlier iterate verified in its place says
        # nothing about where training stands now
        if chosen is here and cert.certified \
                and cert.level >= cfg.target_fraction * chosen.cand.level \
                and not len(cert.counterexamples) and it + 1 >= cfg.min_iterations \
                and _level_settled(chosen.cand.source, area, prev_area, cfg.plateau,
                                   cfg.boundary_feedback > 0):
            break
        if last and cert.certified and area > (1 + cfg.plateau) * prev_area:
            limit, last = _extended(limit, cfg, area, prev_area, log)
        if cfg.best_iterate and best is not None and not last and not pending \
                and entry["candidate_area"] < RESUME_BELOW * best.area:
            # after a verifier call (the window's most promising iterate proved): the current
            # V has collapsed (its candidate set, which bounds what it can certify, is well
            # below the best certified area), so training goes on from the best iterate
            _resume(learner, best_state, best.area, here, log,
                    RESUME_LR ** (1 + sum("resumed_from" in h for h in history)))
        elif cand.source == "sphere" and cfg.boundary_feedback and not last:
            rim = _feed_boundary(cfg, V, D, cand, rim, len(S), rng, entry, log)
        cex = _add_counterexamples(cex, cert.counterexamples, cfg, scale, rng,
                                   _extra_states(chosen, here, cand))
    best = _verify_leftover(pending, best, areas, log, beat)
    return _result(best, learner, history, time.perf_counter() - t0, (margin, M, smoothing))


def _verify_leftover(pending: list, best: CegisResult | None, areas: _AreaGrid, log,
                     beat: VolumeToBeat | None) -> CegisResult | None:
    """The window left open when the budget's last iteration had nothing to verify (its
    controller leaves the input box): its most promising iterate is verified now, and
    wins when it certifies more than ``best`` (no window left open: ``best``)."""
    if not pending:
        return best
    log(f"  cegis: the last iteration had no certificate to check; the window since the "
        f"last verifier call (iterations {pending[0].entry['iteration']} to "
        f"{pending[-1].entry['iteration']}) is verified now")
    chosen, cert = _verify_window(pending, pending[-1], log, beat,
                                  best.area if best is not None else 0.0, areas)
    if cert is None:
        return best
    area = cert.area(areas.box, areas.count) if cert.certified else 0.0
    _record(chosen, cert, area)
    _log_iterate(log, chosen, cert.certified)
    if cert.certified and (best is None or area > best.area):
        return CegisResult(CertStatus.CERTIFIED, chosen.V, chosen.ctrl, cert.level,
                           *chosen.margins[:2], area, [], 0.0, chosen.margins[2])
    return best


def _new_iterate(it: int, info, problem: RoaProblem, cand, margins: tuple, cfg: CegisConfig,
                 eta: float, areas: _AreaGrid, learner: LyapunovLearner,
                 beat: VolumeToBeat | None, log) -> _Iterate:
    """The iterate just trained, with its history entry (completed by :func:`_record`);
    ``skipped`` says why it is never verified when its candidate level's volume bound
    cannot beat ``beat``."""
    skip = beat.cannot_beat(problem, cand.level) if beat is not None and cand.level > 0 else ""
    if skip:
        log(f"  cegis iteration {it}: not verified, {skip}")
    entry = {"iteration": it, "loss": info.loss, "train_steps": info.steps,
             "margin_mode": cfg.margin_mode if eta > 0 else "none",
             "train_seconds": info.seconds, "candidate_level": cand.level,
             "candidate_source": cand.source, "skipped": skip}
    if cfg.best_iterate:
        entry["candidate_area"] = areas.candidate(problem.V, cand.level)
    return _Iterate(problem.V, problem.controller, problem, cand, entry, margins,
                    learner.state() if cfg.best_iterate else None)


def _result(best: CegisResult | None, learner: LyapunovLearner, history: list,
            seconds: float, margins: tuple) -> CegisResult:
    """The best certified iterate, or the last networks with NOT_CERTIFIED."""
    if best is None:
        V, ctrl = learner.export()
        margin, M, smoothing = margins
        return CegisResult(CertStatus.NOT_CERTIFIED, V, ctrl, 0.0, margin, M, 0.0, history,
                           seconds, smoothing,
                           reason="no certified level within the iteration budget")
    best.history, best.seconds = history, seconds
    return best
