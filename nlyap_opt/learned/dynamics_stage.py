r"""The whole learned-dynamics stage, with its η gate: learn φ, bound η, refine or stop.

:func:`dynamics_stage` is the one call the pipeline makes for learned dynamics:

1. learn φ on the configured grid (:func:`nlyap_opt.learned.dynamics.learn_dynamics`; budgets are
   step counts, the result is the same on any machine load);
2. compute every sound bound η (:func:`nlyap_opt.learned.error_models.compute_bounds`);
3. **gate**: if ``eta_target`` is set and η exceeds it, run up to ``eta_rounds`` refinement
   rounds (:func:`nlyap_opt.learned.dynamics.refine_dynamics`: the grid nodes with the largest error
   join the training set, then Levenberg–Marquardt and minimax rounds continue from the
   current weights), keeping the round with the smallest η; if η still exceeds the target
   the stage ends with status ``"eta_too_large"`` and an advice message naming the cause
   (fit error α or grid term), where the error peaks, and the config key to change.

Why a configured ``eta_target``: no CEGIS stage can succeed when the robust term
:math:`\eta\|\nabla V\|` beats the best decrease the closed loop offers near the inner ring.
For the quadratic LQR certificate :math:`V = x^\top P x`, :math:`A_{cl}^\top P + P A_{cl} =
-I`, the linearised decrease on :math:`\|x\| = \epsilon` is :math:`\|x\|^2` and the robust
term at most :math:`2\eta\lambda_{\max}(P)\|x\|`, so that certificate is lost at
:math:`\eta = \epsilon / (2\lambda_{\max}(P))` (:func:`eta_limit_linear`; Van der Pol at
ε = 0.2: 0.055, path following at 0.1: 0.033, pendulum at 0.4: 0.10). The default presets
use about half of that (0.025, 0.015, 0.05), which is 10–20 times the η their step budgets
reach on the seed systems. The limit needs the run's inner radius and controller, which the
dynamics configuration does not know; a run configuration can set ``eta_target`` from it.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import numpy as np
from scipy.linalg import solve_continuous_lyapunov

from ..kernel.errors import ConfigError
from ..kernel.jsonio import write_atomic
from ..kernel.network import Network
from .dynamics import (
    AlphaResult,
    DynamicsResult,
    Grid,
    as_config,
    learn_dynamics,
    refine_dynamics,
)
from .dynamics_config import DynamicsConfig
from .error_models import BoundsResult, compute_bounds, write_bounds

__all__ = ["DynamicsStage", "GateStatus", "dynamics_stage", "eta_advice", "eta_limit_linear",
           "STATUSES"]


class GateStatus(str, Enum):
    """Outcome of the η gate of :func:`dynamics_stage` (``bounds.json``'s ``gate.status``)."""

    OK = "ok"
    ETA_TOO_LARGE = "eta_too_large"

    def __str__(self) -> str:
        return self.value


#: the statuses of :class:`DynamicsStage`
STATUSES = tuple(s.value for s in GateStatus)


@dataclass
class DynamicsStage:
    """Outcome of :func:`dynamics_stage`.

    Attributes
    ----------
    network : Network
        φ (float64 weights; the verified object).
    grid : Grid
        The grid that defines δ and on which α was measured.
    alpha : AlphaResult
    bounds : BoundsResult
        Every η option; ``bounds.eta`` is the one used.
    seconds : dict
        Wall time per part (reported only).
    status : GateStatus
        ``"ok"`` or ``"eta_too_large"`` (η above ``eta_target`` after ``eta_rounds``
        refinement rounds).
    advice : str
        Empty when ``ok``; otherwise the cause and the fix, in one paragraph.
    eta_target : float or None
    rounds : int
        Refinement rounds run.
    history : list of dict
        ``{"round", "alpha", "eta"}`` per training round (0 is the first training).
    config : DynamicsConfig
    result : DynamicsResult
        The training result of the kept round (its history, its training state).
    """

    network: Network
    grid: Grid
    alpha: AlphaResult
    bounds: BoundsResult
    seconds: dict
    status: GateStatus
    advice: str
    eta_target: float | None
    rounds: int
    history: list = field(default_factory=list)
    config: DynamicsConfig | None = None
    result: DynamicsResult | None = field(default=None, repr=False)

    @property
    def eta(self) -> float:
        return self.bounds.eta

    @property
    def ok(self) -> bool:
        return self.status is GateStatus.OK

    def gate(self) -> dict:
        """The gate's record (written into ``bounds.json`` under ``"gate"``)."""
        return {"status": self.status, "eta": self.eta, "eta_target": self.eta_target,
                "rounds": self.rounds, "history": self.history, "advice": self.advice}

    def save(self, out) -> tuple[Path, Path]:
        """Write ``dynamics.json`` and ``bounds.json`` (with the gate) into directory ``out``."""
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        net_path = self.network.save(out / "dynamics.json")
        seconds = {k: v for k, v in self.seconds.items() if k in ("data", "training", "alpha")}
        bpath = write_bounds(out / "bounds.json", self.bounds, seconds, str(net_path))
        d = json.loads(bpath.read_text())
        d["gate"] = self.gate()
        write_atomic(bpath, json.dumps(d, indent=1, allow_nan=False, ensure_ascii=False))
        return net_path, bpath


def dynamics_stage(system, dcfg: DynamicsConfig | dict | None = None, log=print
                   ) -> DynamicsStage:
    """Learn φ, bound η and apply the η gate; one call for the whole dynamics stage.

    Parameters
    ----------
    system : systems.System
    dcfg : DynamicsConfig or dict, optional
        The stage's configuration (:func:`nlyap_opt.learned.dynamics_config.dynamics_config`); a
        dict is validated against the system's preset.
    log : callable, optional
        ``log(str)`` for one line per step (``None``: silent).

    Returns
    -------
    DynamicsStage
        ``status`` ``"ok"``, or ``"eta_too_large"`` with ``advice``: an expected outcome,
        not an exception; the caller stops before CEGIS.

    Examples
    --------
    >>> import systems
    >>> st = dynamics_stage(systems.get("van_der_pol"),
    ...                     {"preset": "fast", "progress": False, "eta_target": 0.5}, log=None)
    >>> st.status, st.eta < 0.5
    ('ok', True)
    """
    log = log or (lambda msg: None)
    cfg = as_config(system, dcfg)
    t_all = time.perf_counter()
    log(f"[dynamics] learning φ for {system.name} ({cfg.preset} preset, {cfg.steps} Adam steps, "
        f"{cfg.lm_iterations} LM iterations, {cfg.minimax_rounds} minimax rounds)")
    res = learn_dynamics(system, cfg)
    bounds = _bounds(system, res, cfg)
    history = [{"round": 0, "alpha": res.alpha.alpha, "eta": bounds.eta}]
    log(f"[dynamics] α = {res.alpha.alpha:.4g}, η = {bounds.eta:.4g} ({bounds.selected} bound)")
    target = cfg.eta_target
    best = (res, bounds)
    rounds = 0
    while target is not None and best[1].eta > target and rounds < cfg.eta_rounds:
        rounds += 1
        log(f"[dynamics] η = {best[1].eta:.4g} > eta_target {target:.4g}: refinement round "
            f"{rounds}/{cfg.eta_rounds} (+{cfg.refine_points} worst grid nodes)")
        res = refine_dynamics(best[0])
        bounds = _bounds(system, res, cfg)
        history.append({"round": rounds, "alpha": res.alpha.alpha, "eta": bounds.eta})
        log(f"[dynamics] round {rounds}: α = {res.alpha.alpha:.4g}, η = {bounds.eta:.4g}")
        if bounds.eta < best[1].eta:
            best = (res, bounds)
    res, bounds = best
    status, advice = GateStatus.OK, ""
    if target is not None and bounds.eta > target:
        status, advice = GateStatus.ETA_TOO_LARGE, eta_advice(system, cfg, res, bounds)
        log(f"[dynamics] stopped: {advice}")
    seconds = dict(res.seconds)
    seconds["bounds"] = bounds.seconds.get("bounds", 0.0)
    seconds["total"] = time.perf_counter() - t_all
    return DynamicsStage(res.network, res.grid, res.alpha, bounds, seconds, status, advice,
                         target, rounds, history, cfg, res)


def _bounds(system, res: DynamicsResult, cfg: DynamicsConfig) -> BoundsResult:
    return compute_bounds(system, res.network, res.grid, res.alpha,
                          options=cfg.bound_options, select=cfg.bound_model,
                          boxes=cfg.interval_boxes, counts=cfg.interval_counts,
                          check_points=cfg.check_points, seed=cfg.seed)


def eta_advice(system, cfg: DynamicsConfig, res: DynamicsResult, bounds: BoundsResult) -> str:
    """One paragraph: η against its target, the dominant term, where it peaks, the fix."""
    eta, target = bounds.eta, cfg.eta_target
    opt = bounds.options[bounds.selected]
    a_up = float(bounds.alpha.alpha_upper)
    grid_term = max(eta - a_up, 0.0)
    names = list(system.state_names) + ([] if res.model == "control_affine"
                                         else list(system.input_names))
    z = np.asarray(res.alpha.argmax, dtype=float)
    where = ", ".join(f"{n} = {v:.4g}" for n, v in zip(names, z))
    box = res.grid.box
    edge = [names[i] for i in range(len(z)) if z[i] in (box[i, 0], box[i, 1])]
    head = (f"η = {eta:.3g} ({bounds.selected} bound) exceeds eta_target = {target:.3g} after "
            f"{res.rounds} refinement round(s) (eta_rounds = {cfg.eta_rounds}); ")
    if a_up >= grid_term:
        hidden = cfg.hidden
        fix = (f"the fit error dominates: α = {res.alpha.alpha:.3g} at the grid point "
               f"({where}){' on the box edge in ' + ', '.join(edge) if edge else ''}. "
               f"Raise 'hidden' (now {hidden}), 'steps' (now {cfg.steps}), 'lm_iterations' "
               f"(now {cfg.lm_iterations}) or 'eta_rounds' (now {cfg.eta_rounds}) in the "
               "dynamics config, or shrink the box ('state_box'/'input_box') to the region "
               "the certificate needs")
    else:
        fix = (f"the grid term dominates: η − α̅ = {grid_term:.3g} from the spacing "
               f"{', '.join(f'{h:.3g}' for h in res.grid.spacing)} (δ = {res.grid.delta:.3g}; "
               f"{opt.name} bound). Raise 'grid_counts' (now {res.grid.counts.tolist()}) in "
               "the dynamics config, or shrink the box ('state_box'/'input_box')")
    return head + fix + f"; or raise 'eta_target' if the certificate tolerates η = {eta:.3g}."


def eta_limit_linear(A_cl, inner: float) -> float:
    r"""The η at which the linearised quadratic certificate is lost on the ring ‖x‖ = ε.

    With :math:`A_{cl}^\top P + P A_{cl} = -I`, :math:`\dot V = -\|x\|^2` to first order and
    :math:`\eta\|\nabla V\| \le 2\eta\lambda_{\max}(P)\|x\|`; the robust decrease holds on
    :math:`\|x\| = \epsilon` iff :math:`\eta < \epsilon / (2\lambda_{\max}(P))`.

    Parameters
    ----------
    A_cl : (n, n) array_like
        Closed-loop Jacobian at the origin (Hurwitz).
    inner : float
        The inner radius ε.

    Raises
    ------
    ConfigError
        ``A_cl`` is not Hurwitz or ``inner`` is not positive.
    """

    A = np.asarray(A_cl, dtype=float)
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ConfigError(f"A_cl must be a square matrix, got shape {A.shape}")
    if not inner > 0:
        raise ConfigError(f"inner radius must be positive, got {inner}")
    if np.max(np.linalg.eigvals(A).real) >= 0:
        raise ConfigError("A_cl is not Hurwitz: no quadratic certificate to compare η with")
    P = solve_continuous_lyapunov(A.T, -np.eye(A.shape[0]))
    return float(inner / (2.0 * np.max(np.linalg.eigvalsh(0.5 * (P + P.T)))))
