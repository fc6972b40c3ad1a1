r"""The cheap certificates: quadratic ``V(x) = xᵀPx`` under the initial controller.

Run before the neural stage when the configuration lists ``quadratic`` candidates:
each candidate matrix ``P`` of the closed loop's linearisation ``A_cl`` (of the true
``f``, or of the learned ``φ``) gives ``V = xᵀPx``, certified by exactly the machinery of the
neural certificates (:func:`nlyap_opt.certification.certificate.certify_with_inner_search`:
conditions (a), (b), (c), the robust margin ``η‖∇_L V‖`` for learned dynamics, the same domain and
initial set). The pipeline then re-verifies the best certified quadratic at its saved level and
keeps whichever certificate -- the neural one or the quadratic one -- covers the larger volume.

Candidates (:data:`QUADRATIC_CANDIDATES`, a registry of ``(A_cl, known) -> P or None``;
``known``: the true f, else learned dynamics):

- ``"lyapunov"``: ``A_clᵀP + PA_cl = −I``; for the LQR loop this is the ``P`` of the LQR
  baseline (``nlyap compare``);
- ``"round"``: the Lyapunov matrix of smallest condition number
  (:func:`nlyap_opt.design.control.round_lyapunov_matrix`); a round ``P`` keeps its sublevel sets
  away from the thin directions of a badly conditioned one (cartpole: condition number 60
  against 328, a certified volume about 45 times that of the LQR ``P``);
- ``"volume"``: the Lyapunov matrix whose ellipsoid in the unit ball is largest
  (:func:`nlyap_opt.design.control.volume_lyapunov_matrix`, decay rate
  :data:`VOLUME_DECAY_FRACTION`, with learned dynamics :data:`LEARNED_VOLUME_DECAY_FRACTION`):
  only the directions the linearisation pins stay thin (cartpole: certified volume 0.52
  with the true f, 3.5 times the round ``P``'s, and 0.235 with learned dynamics, 4.9 times;
  in 6-D the verifier is the limit, see ``docs/topics/high_dimension.md``);
- ``"centre"``: for a linearisation with eigenvalues on the imaginary axis (a centre along
  coordinate axes, no other candidate applies), the identity on the centre coordinates and
  the Lyapunov matrix of the Hurwitz block
  (:func:`nlyap_opt.certification.roa.centre_lyapunov_matrix`): ``V̇`` decreases like
  ``f``'s leading terms along the centre (``-‖x‖⁴`` for ``x' = -x³``), and condition (c)
  is proved by the weighted blow-up.

The quadratic's inner radius is ``inner_fraction`` times the run's ``ε``. With the true f
the default is 1/4, as the ``nlyap compare`` LQR rows: a quadratic ``V`` needs no large
excluded ball, and condition (c) on a small ball is cheap in many dimensions. With learned
dynamics it is the run's ``ε`` itself, the neural ``V``'s: there the inner ball is the
paper's assumption rather than a proof, and near the origin the robust margin
``η‖∇_L V‖ ~ η‖x‖`` outweighs a quadratic's decrease ``~ ‖x‖²`` (the cartpole's LQR ``P``
with the large preset's η = 0.019 is refuted at every level with ε/4). The level search
follows decrease counterexamples down to the least ``V`` of a violation
(``follow_violations``): the LQR ``P`` of the cartpole is then certified at level 0.0193
after two refuted levels, where the creeping search stopped at 0.025 after eight.

With learned dynamics each inner radius starts at the smallest level that holds its inner
ball (``smallest_level`` of :func:`nlyap_opt.certification.certificate.certify_with_inner_search`),
the level with the most room for the robust margin: the learned-f cartpole's round ``P`` stayed
"unknown" at levels 0.999 and 0.7 after 2·10⁶ boxes each, while at 0.62, just above
``λ_max(P)·ε² = 0.599``, condition (a) verifies (2.4·10⁶ boxes) and (c) on the true closed
loop too (the shell form). That one level is checked per radius, the radii ε, 2ε, 3ε only
(below ε the robust margin wins, see above); radii whose candidate level lies below their
inner ball's level are skipped.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from types import SimpleNamespace

import casadi as ca
import numpy as np

from ..certification.certificate import INNER_FACTORS, LevelPolicy, certify_candidate
from ..certification.roa import centre_lyapunov_matrix
from ..design.control import (
    lyapunov_matrix,
    quadratic_lyapunov,
    round_lyapunov_matrix,
    volume_lyapunov_matrix,
)
from ..kernel.errors import ConfigError
from ..kernel.symbolic import closed_loop

__all__ = ["QUADRATIC_CANDIDATES", "QuadraticCandidate", "certify_quadratics",
           "closed_loop_matrix", "quadratic_policy"]


def _lyapunov(A_cl, known: bool = True):
    return lyapunov_matrix(A_cl)


def _round(A_cl, known: bool = True):
    return round_lyapunov_matrix(A_cl)


def _volume(A_cl, known: bool = True):
    return volume_lyapunov_matrix(
        A_cl, VOLUME_DECAY_FRACTION if known else LEARNED_VOLUME_DECAY_FRACTION)


#: the decay rate of the ``"volume"`` candidate, a fraction of the closed loop's stability
#: margin: a smaller rate leaves more matrices, so a larger ellipsoid (cartpole, true f: 0.05
#: certifies volume 0.49 in 128 s, 0.1 volume 0.45 in 46 s)
VOLUME_DECAY_FRACTION = 0.05
#: with learned dynamics: the decrease must beat the robust margin ``η‖∇_L V‖`` next to the
#: inner ball (cartpole, η = 0.0051, ε = 0.1: 0.05 is refuted by a counterexample at the
#: smallest level holding the ball; 0.2 certifies there, volume 0.235 on the grid)
LEARNED_VOLUME_DECAY_FRACTION = 0.2

def _centre(A_cl, known: bool = True):
    return centre_lyapunov_matrix(A_cl)


#: name -> ``(A_cl, known) -> P`` (``None``: no candidate); the names a configuration may list
QUADRATIC_CANDIDATES: dict[str, Callable] = {"lyapunov": _lyapunov, "round": _round,
                                             "volume": _volume, "centre": _centre}
#: the candidates for a linearisation that is not Hurwitz (the others need one)
_NOT_HURWITZ = ("centre",)

#: the ε of the quadratic certificates, as a fraction of the run's ``inner``: true f, learned φ
INNER_FRACTION = 0.25
LEARNED_INNER_FRACTION = 1.0


def quadratic_policy(known: bool) -> LevelPolicy:
    """The certification policy of a quadratic ``V = xᵀPx`` (the pipeline's candidates and
    ``nlyap compare``'s LQR rows): ε = :data:`INNER_FRACTION` of the run's with the true f,
    every radius of :data:`~nlyap_opt.certification.certificate.INNER_FACTORS`, searched down from
    the candidate level; with learned dynamics ε itself, no radius below it, each checked at the
    smallest level that holds its inner ball. Decrease violations are followed down."""
    if known:
        return LevelPolicy(INNER_FRACTION, INNER_FACTORS, follow_violations=True)
    return LevelPolicy(LEARNED_INNER_FRACTION, tuple(f for f in INNER_FACTORS if f >= 1),
                       smallest_level=True, follow_violations=True)


@dataclass
class QuadraticCandidate:
    """One quadratic candidate and its certificate.

    Attributes
    ----------
    name : str            key of :data:`QUADRATIC_CANDIDATES`
    P : ndarray or None   the matrix (``None``: the candidate gave none)
    certificate : RoaCertificate or None
    volume : float        certified volume on the evaluation grid (0 if not certified)
    seconds : float
    """

    name: str
    P: np.ndarray | None
    certificate: object = None
    volume: float = 0.0
    seconds: float = 0.0

    @property
    def certified(self) -> bool:
        return self.certificate is not None and self.certificate.certified

    def to_json(self) -> dict:
        """The candidate's record in ``quadratic.json``."""
        c = self.certificate
        return {"name": self.name, "P": None if self.P is None else self.P.tolist(),
                "certified": self.certified,
                "status": "no matrix" if c is None else c.status.value,
                "reason": "" if c is None else c.reason,
                "level": 0.0 if c is None else float(c.level),
                "inner": None if c is None else float(c.inner),
                "volume": self.volume, "seconds": self.seconds}


def closed_loop_matrix(problem) -> np.ndarray:
    """``A_cl``: the Jacobian at 0 of the problem's closed loop (true ``f`` or ``φ``, with
    its controller)."""
    x = ca.SX.sym("x", problem.system.nx)
    rhs = closed_loop(problem.system, problem.controller, problem.dynamics, x=x,
                      strict=True).rhs
    return np.array(ca.Function("J", [x], [ca.jacobian(rhs, x)])(
        np.zeros(problem.system.nx)), dtype=float)


def certify_quadratics(problem, names, *, box, n: int, inner_fraction: float | None = None,
                       log=print) -> list[QuadraticCandidate]:
    """Certify ``V = xᵀPx`` for each named candidate ``P``; volumes on the ``n^nx`` grid.

    Parameters
    ----------
    problem : RoaProblem
        The run's problem (system, controller, φ and η, domain, initial set, verifier
        options); its ``V`` is replaced by each quadratic and its ``inner`` by
        ``inner_fraction·inner`` (default :data:`INNER_FRACTION` with the true f,
        :data:`LEARNED_INNER_FRACTION` with learned dynamics).
    names : sequence of str
        Keys of :data:`QUADRATIC_CANDIDATES`, tried in this order.
    box, n :
        The evaluation grid of the volumes (the run's ``eval_box`` and points per axis).

    Returns
    -------
    list of QuadraticCandidate
        One per name, in order.
    """
    unknown = [nm for nm in names if nm not in QUADRATIC_CANDIDATES]
    if unknown:
        raise ConfigError(f"unknown quadratic candidate {unknown[0]!r}; use some of "
                          f"{', '.join(QUADRATIC_CANDIDATES)}")
    policy = quadratic_policy(problem.known)
    if inner_fraction is not None:
        policy = replace(policy, inner_fraction=inner_fraction)
    A_cl = closed_loop_matrix(problem)
    hurwitz = bool(np.all(np.isfinite(A_cl))) and np.max(np.linalg.eigvals(A_cl).real) < 0
    out = []
    for name in names:
        t0 = time.perf_counter()
        # the centre candidate finds its own structure (rounding may put the centre's
        # eigenvalues a hair left of the axis); the others need a Hurwitz A_cl
        fits = hurwitz or name in _NOT_HURWITZ
        A = A_cl
        if name in _NOT_HURWITZ and not problem.known and \
                getattr(problem.system, "has_model", False):
            # φ's linearisation only nearly has the centre: the model's closed loop picks
            # the matrix (a candidate only, certified with φ and η like any other)
            A = closed_loop_matrix(SimpleNamespace(system=problem.system,
                                                   controller=problem.controller,
                                                   dynamics=None))
        P = QUADRATIC_CANDIDATES[name](A, problem.known) if fits else None
        if P is None:
            why = "has no centre" if name in _NOT_HURWITZ else \
                "gave no solution" if fits else "not Hurwitz"
            log(f"  quadratic {name}: no matrix (closed-loop linearisation {why})")
            out.append(QuadraticCandidate(name, None, seconds=time.perf_counter() - t0))
            continue
        cert = certify_candidate(replace(problem, V=quadratic_lyapunov(P)), policy,
                                 log=lambda m: log("    " + m))
        vol = cert.area(box, n) if cert.certified else 0.0
        out.append(QuadraticCandidate(name, P, cert, vol, time.perf_counter() - t0))
        log(f"  quadratic {name} (cond P {np.linalg.cond(P):.3g}): {cert.summary()}"
            + (f", volume {vol:.4g}" if cert.certified else "")
            + f" ({out[-1].seconds:.1f} s)")
    return out
