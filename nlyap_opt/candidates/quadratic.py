r"""The cheap certificates: quadratic ``V(x) = xᵀPx`` under the initial controller.

Run before the neural stage when the configuration lists ``quadratic`` candidates:
each candidate matrix ``P`` of the closed loop's linearisation ``A_cl`` (of the true
``f``, or of the learned ``φ``) gives ``V = xᵀPx``, certified by exactly the machinery of the
neural certificates (:func:`nlyap_opt.certification.certificate.certify_with_inner_search`:
conditions (a), (b), (c), the robust margin ``η‖∇_L V‖`` for learned dynamics, the same domain and
initial set). The pipeline then re-verifies the best certified quadratic at its saved level and
keeps whichever certificate -- the neural one or the quadratic one -- covers the larger volume.

Candidates (:data:`QUADRATIC_CANDIDATES`, a registry of ``(A_cl, known, domain) -> P or
None``; ``known``: the true f, else learned dynamics; ``domain``: the run's region ``D``, a
:class:`nlyap_opt.kernel.domain.Region`, or ``None``):

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
- ``"domain"``: the Lyapunov matrix whose ellipsoid inside the run's domain ``D`` is largest
  (:func:`nlyap_opt.design.control.domain_lyapunov_matrix`, the same decay rates as
  ``"volume"``): fitted to ``D``'s own shape (a box's half-widths, a centred ellipsoid, a
  ball), where ``"volume"`` fits the unit ball;
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
(``follow_violations``), steps 13.5 % below an ``unknown`` there and climbs back by
bisection from the first proved level (:func:`nlyap_opt.certification.roa.certify_level`):
the LQR ``P`` of the cartpole is certified at level 0.0192 in seven tries (a refuted level,
an ``unknown`` one at the least violation, 0.0168 proved, four bisection tries), where the
creeping search stopped at 0.025 after eight; the ``volume`` ``P`` of the planar quadrotor
at level 0.258 in eight.

With learned dynamics and at most :data:`LEARNED_SEARCH_STATES` states the level is searched
down from the candidate level as with the true f, at the run's ``ε`` (each check takes
seconds: Fossil's 3-D NonPoly2 with φ certifies the ``round`` candidate's whole ball, volume
114.6 in 0.3 s, where the smallest-level policy below gave 16.1); there ``"volume"`` and
``"domain"`` take the true f's decay rate first and the learned one
(:data:`LEARNED_VOLUME_DECAY_FRACTION`) only where that certifies nothing (a 3-D controlled
chain with φ: the ``domain`` quadratic's volume 2.733 → 3.035, the true f's). With more states each
inner radius starts at the smallest level that holds its inner
ball (``smallest_level`` of :func:`nlyap_opt.certification.certificate.certify_with_inner_search`),
the level with the most room for the robust margin: the learned-f cartpole's round ``P`` stayed
"unknown" at levels 0.999 and 0.7 after 2·10⁶ boxes each, while at 0.62, just above
``λ_max(P)·ε² = 0.599``, condition (a) verifies (2.4·10⁶ boxes) and (c) on the true closed
loop too (the shell form). That one level is checked per radius, the radii ε, 2ε, 3ε only
(below ε the robust margin wins, see above); radii whose candidate level lies below their
inner ball's level are skipped.

With learned dynamics each verification costs minutes, so the candidates are verified in the
order of a cheap estimate and one that cannot win is not verified (:func:`volume_bound`: the
grid points of its sublevel set at an upper bound of any level it can be certified at, and of
condition (c)'s ellipse; the learned-f cartpole's ``round`` candidate is bounded by 0.0477,
the volume it certifies, against the ``volume`` candidate's certified 0.2348). The best
candidate is the same as without skipping. Condition (c) does not depend on ``V``: it is
computed once per radius.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from fractions import Fraction
from types import SimpleNamespace

import casadi as ca
import numpy as np

from ..certification.certificate import (
    INNER_FACTORS,
    InnerEllipseCache,
    LevelPolicy,
    VolumeToBeat,
    certify_candidate,
)
from ..certification.roa import (
    INNER_LEVEL_MARGIN,
    TaylorDecrease,
    centre_lyapunov_matrix,
    grid_area,
    grid_points,
    quadratic_form,
    sector_lyapunov_matrix,
)
from ..design.control import (
    domain_lyapunov_matrix,
    lyapunov_matrix,
    quadratic_lyapunov,
    round_lyapunov_matrix,
    volume_lyapunov_matrix,
)
from ..kernel.domain import Ball, Box, Ellipsoid
from ..kernel.errors import ConfigError, InputRangeError
from ..kernel.symbolic import closed_loop

__all__ = ["QUADRATIC_CANDIDATES", "QuadraticCandidate", "certify_quadratics", "thin_radius",
           "closed_loop_matrix", "quadratic_policy", "decided_on_sets", "volume_bound"]


def _lyapunov(A_cl, known: bool = True, domain=None):
    return lyapunov_matrix(A_cl)


def _round(A_cl, known: bool = True, domain=None):
    return round_lyapunov_matrix(A_cl)


def _volume(A_cl, known: bool = True, domain=None):
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

def _domain_shape(domain, n: int):
    """``(inside, half)``: the shape matrix of the centred ellipsoid an ellipsoid ``{xᵀPx ≤
    1}`` must lie in (``P ⪰ inside⁻¹``: a ball about 0, a centred ellipsoid, else the
    inscribed ball of ``D``), or for a box the half-widths of its nearer faces; ``None,
    None`` for a box that does not hold the origin."""
    if isinstance(domain, Box):
        b = domain.bounding_box()
        if not np.all((b[:, 0] < 0) & (b[:, 1] > 0)):
            return None, None
        return None, np.minimum(-b[:, 0], b[:, 1])
    if isinstance(domain, Ellipsoid) and domain.centre is None:
        return np.linalg.inv(domain.Q), None
    r = domain.radius if isinstance(domain, Ball) and domain.centre is None \
        else domain.inradius()
    return r * r * np.eye(n), None


def _domain_fit(A_cl, known: bool = True, domain=None):
    """``"domain"``: the largest Lyapunov ellipsoid inside ``D`` itself."""
    if domain is None:
        return None
    inside, half = _domain_shape(domain, A_cl.shape[0])
    if inside is None and half is None:
        return None
    return domain_lyapunov_matrix(
        A_cl, VOLUME_DECAY_FRACTION if known else LEARNED_VOLUME_DECAY_FRACTION,
        inside=inside, half_widths=half)


def _sector(A_cl, known: bool = True, domain=None, problem=None):
    r"""``"sector"``: the ``P`` whose ellipsoid passes the whole-set decrease test under the
    initial saturated controller, with every slope and input the controller takes on it
    (:func:`nlyap_opt.certification.roa.sector_lyapunov_matrix`, seeded with the
    ``"volume"`` matrix, inside ``D``). ``None`` without a problem, a one-layer tanh
    controller or a smooth closed loop."""
    if problem is None or problem.controller is None or domain is None:
        return None
    try:
        dec = replace(problem, V=quadratic_lyapunov(np.eye(problem.system.nx))).decrease()
    except InputRangeError:     # the problem's bound does not apply: no candidate proves
        return None
    sat = dec.saturated
    if sat is None or sat.why or dec.rhs is None:
        return None
    eps = quadratic_policy(problem.known, nx=problem.system.nx).inner_fraction * problem.inner
    P0 = volume_lyapunov_matrix(
        A_cl, VOLUME_DECAY_FRACTION if known else LEARNED_VOLUME_DECAY_FRACTION)
    if P0 is None or not eps > 0:
        return None
    robust = dec.robust or {}
    outer = domain.bounding_box()
    inside, _ = _domain_shape(domain, A_cl.shape[0])      # a box: its own limit below
    eta = float(robust.get("eta", 0.0))
    return sector_lyapunov_matrix(
        sat, dec.x, dec.rhs, P0, inner=eps, limit=np.minimum(-outer[:, 0], outer[:, 1]),
        inside=inside, eta=eta, components=robust.get("components"),
        constant=eta * float(robust.get("smoothing", 0.0)))


def _centre(A_cl, known: bool = True, domain=None):
    return centre_lyapunov_matrix(A_cl)


#: name -> ``(A_cl, known, domain) -> P`` (``None``: no candidate; those of
#: ``_PROBLEM_CANDIDATES`` also get ``problem=``, the run's problem); the names a
#: configuration may list
QUADRATIC_CANDIDATES: dict[str, Callable] = {"lyapunov": _lyapunov, "round": _round,
                                             "volume": _volume, "domain": _domain_fit,
                                             "centre": _centre, "sector": _sector}
#: the candidates that read the run's problem as well (``problem=``; the registry's other
#: plug-ins take ``(A_cl, known, domain)`` only)
_PROBLEM_CANDIDATES = ("sector",)
#: why a candidate gave no matrix, where "no solution" does not say it
_NO_MATRIX = {"sector": "no sector design: it needs a one-layer tanh controller, a closed "
                        "loop smooth on the design's boxes and a feasible SDP"}
#: the candidates for a linearisation that is not Hurwitz (the others need one)
_NOT_HURWITZ = ("centre",)

#: the ε of the quadratic certificates, as a fraction of the run's ``inner``: true f, learned φ
INNER_FRACTION = 0.25
LEARNED_INNER_FRACTION = 1.0


#: with learned dynamics, systems of at most this many states search each quadratic's level
#: down from its candidate level with the verifier, as with the true f (each check takes
#: seconds there); larger ones check the smallest level (each check takes minutes)
LEARNED_SEARCH_STATES = 3


def quadratic_policy(known: bool, whole_set: bool = False,
                     nx: int | None = None) -> LevelPolicy:
    """The certification policy of a quadratic ``V = xᵀPx`` (the pipeline's candidates and
    ``nlyap compare``'s LQR rows): ε = :data:`INNER_FRACTION` of the run's with the true f,
    every radius of :data:`~nlyap_opt.certification.certificate.INNER_FACTORS`, searched down from
    the candidate level. With learned dynamics ε itself and no radius below it; for at most
    :data:`LEARNED_SEARCH_STATES` states (``nx``) searched down from the candidate level as
    with the true f; otherwise each radius is checked at the smallest level that holds its
    inner ball, after (``whole_set``: the closed loop with φ is smooth, so
    :class:`~nlyap_opt.certification.roa.TaylorDecrease` decides the robust decrease on a whole
    sublevel set without bisection) a search down from the candidate level decided by that
    test alone. Decrease violations are followed down."""
    if known:
        return LevelPolicy(INNER_FRACTION, INNER_FACTORS, follow_violations=True)
    factors = tuple(f for f in INNER_FACTORS if f >= 1)
    if nx is not None and nx <= LEARNED_SEARCH_STATES:
        return LevelPolicy(LEARNED_INNER_FRACTION, factors, follow_violations=True)
    return LevelPolicy(LEARNED_INNER_FRACTION, factors, smallest_level=True,
                       follow_violations=True, whole_sets=whole_set)


def decided_on_sets(problem) -> bool:
    """Whether :class:`~nlyap_opt.certification.roa.TaylorDecrease` applies to the run's
    closed loop on the domain (its graph is smooth there, any partial or non-smooth
    operation cleared on the domain's box: the decrease of a quadratic ``V`` is then decided
    on whole sublevel sets)."""
    try:
        cl = closed_loop(problem.system, problem.controller, problem.dynamics)
    except (ValueError, TypeError):
        return False
    n = problem.system.nx
    eye = [[Fraction(int(i == j)) for j in range(n)] for i in range(n)]
    return TaylorDecrease(cl.x, cl.rhs, eye).applies(problem.domain.bounding_box())


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
    bound : float or None  :func:`volume_bound` (``None``: not computed)
    skipped : str         why it was not verified: its bound cannot beat a certified
                          candidate (``""``: verified)
    """

    name: str
    P: np.ndarray | None
    certificate: object = None
    volume: float = 0.0
    seconds: float = 0.0
    bound: float | None = None
    skipped: str = ""

    @property
    def certified(self) -> bool:
        return self.certificate is not None and self.certificate.certified

    def to_json(self) -> dict:
        """The candidate's record in ``quadratic.json``."""
        c = self.certificate
        status = "skipped" if self.skipped else "no matrix" if c is None else c.status.value
        return {"name": self.name, "P": None if self.P is None else self.P.tolist(),
                "certified": self.certified, "status": status,
                "reason": self.skipped if c is None else c.reason,
                "level": 0.0 if c is None else float(c.level),
                "inner": None if c is None else float(c.inner),
                "volume": self.volume, "volume_bound": self.bound, "seconds": self.seconds}


def closed_loop_matrix(problem) -> np.ndarray:
    """``A_cl``: the Jacobian at 0 of the problem's closed loop (true ``f`` or ``φ``, with
    its controller)."""
    x = ca.SX.sym("x", problem.system.nx)
    rhs = closed_loop(problem.system, problem.controller, problem.dynamics, x=x,
                      strict=True).rhs
    return np.array(ca.Function("J", [x], [ca.jacobian(rhs, x)])(
        np.zeros(problem.system.nx)), dtype=float)


#: relative slack of the bound's comparisons (float evaluation of ``V`` and of the domain
#: test); it only enlarges the bound
BOUND_SLACK = 1e-9


def _boundary_level(P: np.ndarray, domain, n_dirs: int = 2000) -> float:
    """An upper bound of ``min xᵀPx`` over ``∂D``: ``V`` at points outside ``D`` on rays from
    the origin (bisection on ``domain.contains``), along the eigenvectors of ``P`` and
    ``n_dirs`` seeded random directions. Each ray leaves ``D`` through ``∂D`` before such a
    point, and ``V`` grows along it, so each value is at least the minimum."""
    n = len(P)
    vecs = np.linalg.eigh(P)[1].T
    d = np.random.default_rng(0).standard_normal((n_dirs, n))
    dirs = np.vstack([vecs, -vecs, d / np.linalg.norm(d, axis=1, keepdims=True)])
    lo = np.zeros(len(dirs))
    hi = np.full(len(dirs), 2.0 * domain.max_norm() + 1.0)   # beyond every point of D
    for _ in range(64):
        mid = 0.5 * (lo + hi)
        inside = domain.contains(dirs * mid[:, None])
        lo, hi = np.where(inside, mid, lo), np.where(inside, hi, mid)
    pts = dirs * hi[:, None]
    v = np.einsum("ij,jk,ik->i", pts, P, pts)[~domain.contains(pts)]
    return float(v.min()) if len(v) else np.inf


def _radius_levels(problem, P: np.ndarray, policy: LevelPolicy) -> list[tuple[float, float]]:
    """``(ε, c)``: each radius of ``policy`` at which ``xᵀPx`` can be certified, and an upper
    bound of the level it can be certified at there.

    Condition (b) proves ``B_ε ⊆ Ω_c`` (so ``c > max_{‖x‖=ε} V = λ_max(P)ε²``) and ``V > c`` on
    ``∂D`` (so ``c`` is below :func:`_boundary_level`): a radius where these exclude each other
    certifies nothing. With ``smallest_level`` the level checked is ``(1 +``
    :data:`~nlyap_opt.certification.roa.INNER_LEVEL_MARGIN` ``)`` times a sampled value of
    ``V`` on the sphere, at most ``λ_max(P)ε²``."""
    D = problem.domain
    c_b = _boundary_level(P, D) * (1 + BOUND_SLACK)
    lam = float(np.linalg.eigvalsh(P)[-1])
    out = []
    for f in policy.factors:
        eps = problem.inner * policy.inner_fraction * f
        if not 0 < eps < D.inradius() or lam * (1 - BOUND_SLACK) * eps**2 >= c_b:
            continue
        c = min(c_b, lam * (1 + BOUND_SLACK) * eps**2 * (1 + INNER_LEVEL_MARGIN)) \
            if policy.smallest_level else c_b
        out.append((eps, c * (1 + BOUND_SLACK)))
    return out


def volume_bound(problem, P: np.ndarray, policy: LevelPolicy, *, box, n: int,
                 ellipses: InnerEllipseCache | None, beat: float = np.inf) -> float:
    """An upper bound of the volume that :func:`certify_quadratics` can certify with
    ``V = xᵀPx`` on the ``n^nx`` grid over ``box`` (the grid of
    :meth:`~nlyap_opt.certification.certificate.RoaCertificate.area`).

    The certified set is ``{x ∈ D: V ≤ c} ∪ E``: the bound counts, for each radius where the
    candidate can be certified (:func:`_radius_levels`), the grid points of ``D`` with ``V``
    below that radius's level bound or in its ellipse ``E`` of condition (c) (``ellipses``:
    computed there once per radius and shared with the candidates' checks), and takes the
    largest. ``ellipses=None`` leaves ``E`` out: no bound then, a cheap estimate to order
    candidates by. The ellipses are computed only when the sublevel sets alone stay at or
    below ``beat``; otherwise a number above ``beat`` is returned at once.
    """
    pts, shape = grid_points(np.asarray(box, dtype=float), n)
    in_d = problem.domain.contains(pts)
    v = np.einsum("ij,jk,ik->i", pts, P, pts)
    masks = [(eps, in_d & (v <= c)) for eps, c in _radius_levels(problem, P, policy)]
    part = max((grid_area(m.reshape(shape), box) for _, m in masks), default=0.0)
    if ellipses is None or part > beat:
        return part
    V = quadratic_lyapunov(P)
    total = 0.0
    for eps, m in masks:
        res, _ = ellipses.get(replace(problem, V=V, inner=eps))
        Pe = np.asarray(res["P"], dtype=float)
        m = m | (np.einsum("ij,jk,ik->i", pts, Pe, pts)
                 <= float(res["level"]) * (1 + BOUND_SLACK))
        total = max(total, grid_area(m.reshape(shape), box))
    return total


def _candidate_matrix(problem, name: str, A_cl: np.ndarray, hurwitz: bool,
                      whys: dict[str, str]) -> np.ndarray | None:
    """The candidate's matrix ``P``, or ``None`` with the reason put in ``whys[name]``."""
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
    extra = {"problem": problem} if name in _PROBLEM_CANDIDATES else {}
    P = QUADRATIC_CANDIDATES[name](A, problem.known or _searched(problem), problem.domain,
                                   **extra) if fits else None
    if P is None:
        whys[name] = "closed-loop linearisation " + (
            "has no centre" if name in _NOT_HURWITZ else "gave no solution" if fits
            else "not Hurwitz") if name not in _NO_MATRIX or not fits else _NO_MATRIX[name]
    return P


#: the candidates whose decay rate differs with learned dynamics
#: (:data:`LEARNED_VOLUME_DECAY_FRACTION`)
_DECAY_CANDIDATES = ("volume", "domain")


def _searched(problem) -> bool:
    """Learned dynamics in at most :data:`LEARNED_SEARCH_STATES` states: levels are searched
    (checks take seconds), so ``"volume"`` and ``"domain"`` try the true f's decay rate
    first and the learned one only where that certifies nothing."""
    return not problem.known and problem.system.nx <= LEARNED_SEARCH_STATES


#: :func:`thin_radius`: the inner radius as a fraction of the ellipsoid's shortest semi-axis
THIN_RADIUS_FRACTION = 0.5


def thin_radius(problem, P: np.ndarray, policy: LevelPolicy) -> float | None:
    r"""An inner radius ``ε`` for ``V = xᵀPx`` whose sublevel sets are too thin to hold the
    policy's smallest inner ball (the shortest semi-axis at the level below is shorter than
    that radius), or ``None``.

    ``ε`` is :data:`THIN_RADIUS_FRACTION` of the shortest semi-axis of ``{xᵀPx ≤ c}``, ``c`` a
    lower bound of the least ``V`` on ``∂D`` (a box: the least ``V`` on each face's plane,
    :math:`h_k^2/(P^{-1})_{kk}`; otherwise :math:`\lambda_{\min}(P)` times the squared
    inradius), so the sublevel set at that level holds the ball. Only with the true f and
    where :class:`~nlyap_opt.certification.roa.TaylorDecrease` applies to the closed loop on
    the domain:
    it proves the decrease on the whole sublevel set, so the inner ball costs nothing, where
    the verifier would have to bisect next to a tiny ball.
    The radius only chooses what is checked; conditions (a)-(c) are proved at it as at any
    other (a badly conditioned linear chain, Fossil's HighOrd8: shortest semi-axis 0.0024
    at the box's level against the smallest radius tried, 0.0031).
    """
    if not problem.known or not getattr(problem.system, "has_model", False):
        return None
    D = problem.domain
    ev = np.linalg.eigvalsh(P)
    if isinstance(D, Box):          # the least V on each face's plane (a lower bound)
        b = D.bounding_box()
        c = float(np.min(np.minimum(-b[:, 0], b[:, 1]) ** 2 / np.diag(np.linalg.inv(P))))
    else:                           # ∂D lies outside the inscribed ball
        c = float(ev[0]) * D.inradius() ** 2
    lam = float(ev[-1])
    if not (c > 0 and lam > 0):
        return None
    axis = math.sqrt(c / lam)         # the shortest semi-axis of {xᵀPx ≤ c}
    if not 0 < axis < policy.inner_fraction * problem.inner * min(policy.factors):
        return None
    eps = THIN_RADIUS_FRACTION * axis
    cl = closed_loop(problem.system, problem.controller)
    Pq = quadratic_form(quadratic_lyapunov(P))
    if Pq is None or not TaylorDecrease(cl.x, cl.rhs, Pq).applies(D.bounding_box()):
        return None
    return eps


def certify_quadratics(problem, names, *, box, n: int, inner_fraction: float | None = None,
                       prune: bool | None = None, log=print) -> list[QuadraticCandidate]:
    """Certify ``V = xᵀPx`` for each named candidate ``P``; volumes on the ``n^nx`` grid.

    With ``prune`` the candidates are verified in the order of their sublevel-set estimate
    (:func:`volume_bound` without ``E``, largest first) and a candidate whose
    :func:`volume_bound` cannot beat the best one certified so far is not verified: it could
    not have won (a tie goes to the earlier name, as without pruning). The bound is that of
    the levels a search may start from; once a candidate is certified, the next ones are
    also skipped at each radius whose level to check cannot beat it
    (:class:`~nlyap_opt.certification.certificate.VolumeToBeat` with the shared ellipses:
    with the smallest-level policy, the level that holds the inner ball). The best volume is
    thus never smaller than without pruning, and it can be larger: a candidate whose first
    radius would certify a set smaller than the best goes on to its other radii. Condition
    (c) does not depend on ``V``: the candidates share it
    (:class:`~nlyap_opt.certification.certificate.InnerEllipseCache`).

    Parameters
    ----------
    problem : RoaProblem
        The run's problem (system, controller, φ and η, domain, initial set, verifier
        options); its ``V`` is replaced by each quadratic and its ``inner`` by
        ``inner_fraction·inner`` (default :data:`INNER_FRACTION` with the true f,
        :data:`LEARNED_INNER_FRACTION` with learned dynamics).
    names : sequence of str
        Keys of :data:`QUADRATIC_CANDIDATES`.
    box, n :
        The evaluation grid of the volumes (the run's ``eval_box`` and points per axis).
    prune : bool, optional
        Skip the candidates that cannot win (default: with learned dynamics, where each
        verification costs minutes; with the true f every candidate is verified). With
        ``prune``, and with the true f in more than :data:`LEARNED_SEARCH_STATES` states
        (checks of minutes there too), once a candidate is certified the later ones check
        no level that cannot beat it: a level search ends where no lower level can
        (:meth:`~nlyap_opt.certification.certificate.VolumeToBeat.least_level`), and such a
        candidate is recorded as not certified, not with its own smaller volume.

    Returns
    -------
    list of QuadraticCandidate
        One per name, in the order of ``names``.
    """
    unknown = [nm for nm in names if nm not in QUADRATIC_CANDIDATES]
    if unknown:
        raise ConfigError(f"unknown quadratic candidate {unknown[0]!r}; use some of "
                          f"{', '.join(QUADRATIC_CANDIDATES)}")
    nx = problem.system.nx
    policy = quadratic_policy(problem.known, not problem.known and nx > LEARNED_SEARCH_STATES
                              and decided_on_sets(problem), nx)
    if inner_fraction is not None:
        policy = replace(policy, inner_fraction=inner_fraction)
    prune = not problem.known if prune is None else bool(prune)
    floor = prune or nx > LEARNED_SEARCH_STATES
    A_cl = closed_loop_matrix(problem)
    hurwitz = bool(np.all(np.isfinite(A_cl))) and np.max(np.linalg.eigvals(A_cl).real) < 0
    whys: dict[str, str] = {}
    mats = {nm: _candidate_matrix(problem, nm, A_cl, hurwitz, whys) for nm in names}
    # the learned-dynamics decay rate's matrices, verified where the first certifies nothing
    second = {nm: QUADRATIC_CANDIDATES[nm](A_cl, False, problem.domain) for nm in names
              if nm in _DECAY_CANDIDATES and _searched(problem) and mats[nm] is not None}

    def bound(nm, **kw):        # over both matrices a candidate may be certified with
        return max(volume_bound(problem, P, policy, box=box, n=n, **kw)
                   for P in (mats[nm], second.get(nm)) if P is not None)
    order = list(range(len(names)))
    if prune:   # a stable sort: equal estimates keep the order of names
        est = {nm: bound(nm, ellipses=None) for nm, P in mats.items() if P is not None}
        order.sort(key=lambda i: -est.get(names[i], -1.0))
        log("  verified in the order of their sublevel sets' volume at the level bound: "
            + ", ".join(f"{names[i]} {est[names[i]]:.4g}" for i in order
                        if names[i] in est))
    ellipses = InnerEllipseCache()
    found: dict[int, QuadraticCandidate] = {}
    win: int | None = None
    for i in order:
        name, P = names[i], mats[names[i]]
        t0 = time.perf_counter()
        if P is None:
            log(f"  quadratic {name}: no matrix ({whys[name]})")
            found[i] = QuadraticCandidate(name, None, seconds=time.perf_counter() - t0)
            continue
        if prune and win is not None:
            best = found[win]
            b = bound(name, ellipses=ellipses, beat=best.volume)
            if b < best.volume or (b == best.volume and i > win):
                why = (f"cannot beat quadratic {best.name}: volume bound {b:.4g}, "
                       f"certified {best.volume:.4g}")
                found[i] = QuadraticCandidate(name, P, seconds=time.perf_counter() - t0,
                                              bound=b, skipped=why)
                log(f"  quadratic {name}: not verified, {why} ({found[i].seconds:.1f} s)")
                continue
        # the radii whose own level cannot beat the best so far are not checked either,
        # nor a search's levels below the least that can
        beat = VolumeToBeat(found[win].volume, np.asarray(box, dtype=float), n,
                            f"quadratic {found[win].name}", ellipses) \
            if floor and win is not None else None
        cert = certify_candidate(replace(problem, V=quadratic_lyapunov(P)), policy,
                                 ellipses=ellipses, beat=beat, log=lambda m: log("    " + m))
        thin = None if cert.certified else thin_radius(problem, P, policy)
        if thin is not None:
            log(f"    the sublevel sets of xᵀPx are too thin for the inner radii tried: "
                f"trying ε = {thin:.3g}, half the shortest semi-axis at the level of ∂D")
            cert = certify_candidate(
                replace(problem, V=quadratic_lyapunov(P)),
                replace(policy, inner_fraction=thin / problem.inner, factors=(1.0,)),
                ellipses=ellipses, beat=beat, log=lambda m: log("    " + m))
        if not cert.certified and second.get(name) is not None:
            log(f"    decay rate {VOLUME_DECAY_FRACTION:g} of the margin certifies nothing: "
                f"trying {LEARNED_VOLUME_DECAY_FRACTION:g}, the learned-dynamics rate")
            cert2 = certify_candidate(replace(problem, V=quadratic_lyapunov(second[name])),
                                      policy, ellipses=ellipses, beat=beat,
                                      log=lambda m: log("    " + m))
            if cert2.certified:
                P, cert = second[name], cert2
        vol = cert.area(box, n) if cert.certified else 0.0
        found[i] = QuadraticCandidate(name, P, cert, vol, time.perf_counter() - t0)
        if cert.certified and (win is None or vol > found[win].volume
                               or (vol == found[win].volume and i < win)):
            win = i
        log(f"  quadratic {name} (cond P {np.linalg.cond(P):.3g}): {cert.summary()}"
            + (f", volume {vol:.4g}" if cert.certified else "")
            + f" ({found[i].seconds:.1f} s)")
    return [found[i] for i in range(len(names))]
