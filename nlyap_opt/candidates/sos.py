r"""Sum-of-squares (SOS) region-of-attraction estimates, re-certified by our verifier.

The SOS programs are written directly as semidefinite programs in cvxpy (no SOS toolbox):
a polynomial :math:`p` is SOS when :math:`p(x) = z(x)^\top Q z(x)` for a vector of monomials
:math:`z` and a Gram matrix :math:`Q \succeq 0`; the identity is imposed by matching the
coefficients of every monomial.

Modules: :mod:`nlyap_opt.design.polynomial` (exact polynomials; the closed loop expanded by the
instruction walker), :mod:`nlyap_opt.design.sos_sdp` (the SDPs below), this module
(:func:`sos_roa`, the re-certification and :class:`SOSResult`).

Level of a fixed :math:`V` (S-procedure, bisection on the level :math:`c`)
    .. math::
        -\dot V(x) - \epsilon \|x\|^2 - s(x)\,\bigl(c - V(x)\bigr) \in \Sigma, \qquad
        s \in \Sigma,

    with :math:`\dot V = \nabla V \cdot f` for the polynomial closed loop ``f``. If it holds,
    :math:`\dot V(x) \le -\epsilon\|x\|^2 < 0` on :math:`\{V \le c\} \setminus \{0\}`. For a
    fixed ``c`` this is an SDP feasibility problem; the largest feasible ``c`` is found by
    bisection (one SDP per step).

Enlarging :math:`V` (V–s iteration, degree 4 or 6)
    ``V`` is scaled so that its largest SOS level is 1. Each round alternates (i) the level
    step above with :math:`V` fixed, which also gives a multiplier ``s`` at the slightly
    lower level :math:`c = 1 - \text{backoff}` (so that the next step has an interior
    point), and (ii) a :math:`V` step with ``s`` and ``c`` fixed, linear in ``V``:

    .. math::
        V - \epsilon\|x\|^2 \in \Sigma \;(\text{so } V(0) = 0,\ V > 0), \qquad
        -\dot V - \epsilon\|x\|^2 - s\,(c - V) \in \Sigma, \qquad
        V(y_k) \le c \ \ \forall k,

    minimising the mean of :math:`V(\text{push}\cdot y_k)`, where the :math:`y_k` are
    ray-sampled points of the boundary of the previous set :math:`\{V_{prev} \le c\}`
    (the sampled containment keeps the previous set inside the new one; it is a search
    heuristic and no part of any claim). Degrees are raised one stage at a time
    (2 → 4 → 6), each stage warm-started from the best ``V`` of the previous one; the
    iterate of largest area is kept.

Certification (what makes a result a claim)
    The SDP solver works in floating point with tolerances, so an SDP level is only a
    *candidate*. Every result is re-certified on the system's true CasADi closed loop by
    :func:`nlyap_opt.certification.certificate.certify_roa`, the one definition of the certificate
    used by every method (interval verifier: (a) decrease on
    :math:`\{\varepsilon \le \|x\| \le r,\ V \le c\}`, (b) :math:`V > c` on
    :math:`\|x\| = r` and :math:`B_\varepsilon \subseteq \Omega_c`, lowering ``c`` on
    counterexamples, (c) the inner ellipse). Only ``certified_level`` is a claim;
    ``sdp_level`` is reported beside it.

Non-polynomial closed loops (``sin``, ``cos``, ``1/(1 - d)``, ``tanh`` controllers) are not
handled: :func:`sos_roa` returns ``status = "not applicable: ..."`` with the reason.

Learned dynamics (no input)
    ``φ`` is a tanh network, and an unknown system has no model to expand. The programs then
    run on a least-squares polynomial model of ``φ`` on the domain's box
    (:func:`learned_model`, :func:`nlyap_opt.design.polynomial.fit_polynomial_model`: the
    least degree of 1, 2, 3 that fits to 10⁻³ of each component's RMS, else 3), started
    from the Lyapunov matrix of the model's linear part. The model is a search model only:
    the resulting ``V`` is a candidate like any other, certified on ``φ`` with the robust
    margin of ``η`` (``∇V·φ + η‖∇_L V‖ < 0``), at the run's ``ε``. The search never uses
    the model of f. For a polynomial system the fit is exact up to φ's own error, so the SOS ``V``
    with learned dynamics is close to the one of the true f (a 2-D cubic system: certified
    91.6 % of the true ROA against 91.8 % with the model, where the neural V alone reached
    72.8 %).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from enum import Enum

import casadi as ca
import numpy as np

from ..certification.certificate import (
    InnerEllipse,
    LevelPolicy,
    RoaCertificate,
    RoaProblem,
    certify_candidate,
    certify_roa,
)
from ..certification.roa import grid_area, grid_points
from ..design.control import lqr, lyapunov_matrix
from ..design.polynomial import (
    NotPolynomialError,
    Polynomial,
    PolynomialFit,
    fit_polynomial_model,
    polynomial_closed_loop,
)
from ..design.sos_sdp import (
    SOSLevel,
    boundary_points,
    gram_size,
    sos_level,
    star_area,
    vs_iteration,
)
from ..kernel.errors import NotStabilizableError
from ..kernel.symbolic import closed_loop
from .quadratic import INNER_FRACTION, LEARNED_INNER_FRACTION

__all__ = [
    "AUTO", "AUTO_DEGREES", "AUTO_GRAM_LIMIT", "NotPolynomialError", "Polynomial", "SOSChoice",
    "SOSConfig", "SOSLevel", "SOSResult", "SOSStatus", "certify_sos", "choose_degree",
    "learned_model", "polynomial_closed_loop", "sos_level", "sos_may_fit", "sos_policy",
    "sos_roa",
]


#: the V–s iteration's strictness as a fraction of the starting quadratic's decrease rate
#: (:func:`sos_roa`'s ``strictness``)
STRICTNESS = 0.001


class SOSStatus(str, Enum):
    """Outcome of :func:`sos_roa` / :func:`certify_sos` (the reason is kept beside it)."""

    CERTIFIED = "certified"
    NOT_CERTIFIED = "not certified"
    NOT_APPLICABLE = "not applicable"
    NO_LEVEL = "no SOS level"

    def __str__(self) -> str:
        return self.value


# --------------------------------------------------------------------------- results
@dataclass
class SOSResult:
    r"""Result of :func:`sos_roa`.

    Attributes
    ----------
    status : SOSStatus
        ``CERTIFIED``; ``NOT_APPLICABLE`` (non-polynomial closed loop, learned dynamics);
        ``NO_LEVEL`` (no SDP level); ``NOT_CERTIFIED``.
    degree : int
        Degree of ``V``.
    V : Polynomial or None
        The Lyapunov function (``V.casadi(x)`` gives the CasADi expression).
    sdp_level : float
        Level found by the SDP bisection (a candidate, not a claim).
    certified_level : float
        Level proved by the interval verifier (0 if none). The certified set is
        :math:`\{\|x\| \le r,\ V \le c\} \cup E` with ``r = outer`` and ``E`` the inner
        ellipse.
    seconds : float
        Wall time (SOS and certification).
    notes : list of str
    inner, outer : float
        Radii of the excluded ball and of the verification ball.
    history : list of dict
        One entry per V–s iteration (``degree``, ``sdp_level``, ``seconds``, ``area``).
    certificate : nlyap_opt.certification.certificate.RoaCertificate or None
        The claim: :func:`nlyap_opt.certification.certificate.certify_roa` on :attr:`problem`.
    problem : nlyap_opt.certification.certificate.RoaProblem or None
        What was certified (``save_certificate(res.certificate, res.problem, out)`` writes a
        ``certificate.json`` that ``nlyap verify --certificate`` re-checks).
    non_polynomial : dict
        Readable name -> ``OP_...`` name of the operations that make the closed loop
        non-polynomial (empty when SOS applies).
    sdp_seconds, certify_seconds : float
    reason : str
        Why not ``CERTIFIED`` (empty when certified).
    """

    status: SOSStatus
    degree: int
    V: Polynomial | None = None
    sdp_level: float = 0.0
    certified_level: float = 0.0
    seconds: float = 0.0
    notes: list = field(default_factory=list)
    inner: float = 0.0
    outer: float = 0.0
    history: list = field(default_factory=list)
    certificate: RoaCertificate | None = None
    problem: RoaProblem | None = None
    non_polynomial: dict = field(default_factory=dict)
    sdp_seconds: float = 0.0
    certify_seconds: float = 0.0
    reason: str = ""

    @property
    def text(self) -> str:
        """The status in words: ``"certified"`` or ``"<status>: <reason>"``."""
        return f"{self.status.value}: {self.reason}" if self.reason else self.status.value

    @property
    def certified(self) -> bool:
        """True when the verifier proved conditions (a), (b) and (c) at ``certified_level``."""
        return self.status is SOSStatus.CERTIFIED

    @property
    def applicable(self) -> bool:
        """False when the closed loop is not polynomial (no SOS program was set up)."""
        return not self.non_polynomial

    @property
    def inner_ellipse(self) -> InnerEllipse | None:
        """Condition (c): the certified inner ellipse ``E`` (``None`` if not run)."""
        return None if self.certificate is None else self.certificate.inner_ellipse

    def casadi(self, x):
        """``V`` as a CasADi expression of ``x``."""
        if self.V is None:
            raise ValueError(f"no V in this result (status: {self.text})")
        return self.V.casadi(x)

    def mask(self, points) -> np.ndarray:
        """Boolean: which ``(N, nx)`` points lie in the certified set (all ``False`` if none)."""
        if not self.certified:
            return np.zeros(len(np.atleast_2d(points)), dtype=bool)
        return self.certificate.contains(points)

    def area(self, box=((-3.0, 3.0), (-3.0, 3.0)), n: int = 400) -> float:
        """Area (volume) of the certified set by counting cell centres of an ``n^nx`` grid."""
        box = np.asarray(box, dtype=float)
        pts, shape = grid_points(box, n)
        return grid_area(self.mask(pts).reshape(shape), box)

    def to_json(self) -> dict:
        """JSON-ready summary (the certificate in its own ``certificate.json`` form)."""
        return {
            "method": f"SOS (degree {self.degree})",
            "status": self.text, "degree": self.degree,
            "V": None if self.V is None else self.V.as_json(),
            "sdp_level": self.sdp_level, "certified_level": self.certified_level,
            "level": self.certified_level, "certified": self.certified,
            "inner": self.inner, "outer": self.outer, "seconds": self.seconds,
            "sdp_seconds": self.sdp_seconds, "certify_seconds": self.certify_seconds,
            "certificate": None if self.certificate is None else self.certificate.to_dict(),
            "non_polynomial": dict(self.non_polynomial),
            "history": self.history, "notes": list(self.notes),
        }


# --------------------------------------------------------------------------- entry point
def sos_roa(system, *, degree: int = 2, inner: float = 0.1, controller=None, V0=None,
            multiplier_degree: int | None = None, epsilon: float = 1e-6,
            strictness: float = STRICTNESS, iterations: int = 20, backoff: float = 0.01,
            push: float = 1.05, solver: str = "CLARABEL",
            outer_margin: float = 0.05, certify: bool = True,
            verify_options: dict | None = None, domain=None, keep_in=None,
            f: list[Polynomial] | None = None,
            log: Callable[[str], None] | None = None) -> SOSResult:
    r"""SOS estimate of the region of attraction, certified by the interval verifier.

    Steps: (1) the closed loop as exact polynomials (:func:`polynomial_closed_loop`);
    (2) the quadratic :math:`V = x^\top P x` (``P`` from :func:`nlyap_opt.design.control.lqr`, or
    ``V0``) and its largest SOS level by bisection (:func:`sos_level`); (3) for
    ``degree > 2`` the V–s iteration (see the module docstring) for at most ``iterations``
    rounds (a count: no wall clock decides the result); (4) certification of the final
    ``(V, c)`` on the true CasADi closed loop:
    :func:`nlyap_opt.certification.certificate.certify_roa` (conditions (a), (b), (c), the level
    searched downwards from the SDP level) with ``inner = ε`` and ``outer = r``, the ray-sampled
    extent of :math:`\{V \le c\}` times ``1 + outer_margin``.

    Parameters
    ----------
    system : systems.System
    degree : {2, 4, 6, ...}
        Degree of ``V`` (even).
    inner : float
        Radius ``ε`` of the excluded ball.
    controller : nlyap_opt.kernel.network.Network, optional
        Feedback ``κ`` (``None``: ``u_eq``). Must give a polynomial closed loop.
    V0 : (nx, nx) array_like, optional
        Matrix of the initial quadratic ``V`` (default: the closed-loop Lyapunov matrix).
    domain : nlyap_opt.kernel.domain.Region, optional
        Certify on this verification domain ``D`` (a declared domain: the same set as the
        other rows of a comparison) instead of the ball around the SOS level set.
    f : list of Polynomial, optional
        The polynomial closed loop the SOS programs use (default: the exact expansion of
        the system's model under ``controller``); a model fitted to a learned ``φ``
        (:func:`learned_model`) only with ``certify=False``: the claim is then made by
        the caller on ``φ``.
    keep_in : nlyap_opt.kernel.domain.Region, optional
        Where the V–s iteration's set crosses the boundary of this region (on seeded
        samples of it) and its SDPs are small (Gram matrices of order at most
        20, half the automatic budget), the iteration runs again with its sets kept inside
        (:func:`nlyap_opt.design.sos_sdp.vs_iteration`'s ``outside``) and the ``V`` whose
        set inside the region is larger is kept (a search heuristic: a set across the
        boundary of the run's domain would be cut down by containment (b) when certified).
    multiplier_degree : int, optional
        Degree of the S-procedure multiplier ``s`` (default: the least that matches for the
        level of the quadratic ``V``; two more in the V–s iteration, which needs the room).
    epsilon : float
        Strictness of the SOS decrease and positivity constraints of the quadratic ``V``'s
        level, and the least strictness of the V–s iteration.
    strictness : float
        The V–s iteration asks ``-V̇ ≥ ε_vs ‖x‖²`` with ``ε_vs`` this fraction of the least
        rate ``λ_min(-(AᵀP + PA))`` of the starting quadratic ``V`` at its level (``A`` the
        closed loop's linear part), at least ``epsilon``. With a vanishing strictness the
        SDPs drive ``V̇`` towards 0 wherever that gains area, and the interval verifier
        cannot prove a decrease that small (the 3-D Genesio–Tesi system, whose slowest mode
        decays at 0.022 per s: decrease "unknown" at every level of the final degree-4
        ``V``); a strictness relative to the start's own rate is the same in any units.
    iterations : int
        Budget of the V–s iteration (``degree > 2``): rounds per degree.
    backoff : float
        The multiplier of each V step is taken at level ``(1 - backoff)`` times the
        largest SOS level, so that the V step has an interior point.
    push : float
        The V step minimises the mean of ``V`` at the previous boundary scaled by ``push``.
    solver : str
        cvxpy SDP solver (``"CLARABEL"`` or ``"SCS"``).
    outer_margin : float
        Relative margin of the verification ball over the extent of the level set.
    certify : bool
        Run the verifier (``False`` only for experiments; the result is then not certified).
    verify_options : dict, optional
        Options of :func:`verification.verify`.
    log : callable, optional

    Returns
    -------
    SOSResult
        ``status`` ``"certified"`` with ``certified_level`` proved by the verifier, or
        ``"not applicable: ..."`` for non-polynomial closed loops, or why not certified.

    Examples
    --------
    >>> import systems
    >>> res = sos_roa(systems.get("van_der_pol"), log=None)  # doctest: +SKIP
    >>> res.status, round(res.certified_level, 3)             # doctest: +SKIP
    ('certified', 2.302)
    """
    say = log or (lambda msg: None)
    t0 = time.perf_counter()
    if degree < 2 or degree % 2:
        raise ValueError(f"degree must be an even integer >= 2, got {degree!r}")
    if not inner > 0:
        raise ValueError(f"inner must be > 0 (condition (c) covers the ball), got {inner}")
    if f is not None and certify:
        raise ValueError("a given polynomial model f is a search model: certify on the "
                         "system's closed loop with certify=True needs f = None")
    try:
        f = polynomial_closed_loop(system, controller) if f is None else list(f)
    except NotPolynomialError as err:
        reason = (
            f"the closed loop of {system.name!r} is {err}. SOS certificates need polynomial "
            "data. A sound treatment would need an exact polynomial recast (sin/cos as extra "
            "states on the circle s² + c² = 1, rational terms such as 1/(1 - d) as further "
            "states: an equality-constrained SOS program in 3-4 dimensions) or a Taylor model "
            "f = p + r with a rigorous envelope |r_i(x)| <= γ_i ‖x‖^(k+1) on the box entering "
            "as a bounded disturbance (robust SOS with extra multipliers; a constant remainder "
            "bound would not vanish at the origin and could not prove decrease near 0). "
            "Neither is implemented; the LQR and neural rows cover this system."
        )
        return SOSResult(SOSStatus.NOT_APPLICABLE, degree, seconds=time.perf_counter() - t0,
                         notes=[reason], inner=inner, non_polynomial=err.operations,
                         reason=reason)
    nx = system.nx
    if V0 is None:
        try:
            V0 = lqr(system).P
        except NotStabilizableError as err:
            reason = (f"no quadratic V to start the SOS programs from: {err}. The V-s "
                      "iteration starts at a quadratic Lyapunov function of the "
                      "linearisation; the neural V covers such systems")
            return SOSResult(SOSStatus.NO_LEVEL, degree, notes=[reason],
                             seconds=time.perf_counter() - t0, inner=inner, reason=reason)
    P = np.asarray(V0, dtype=float)
    if P.shape != (nx, nx) or np.min(np.linalg.eigvalsh(0.5 * (P + P.T))) <= 0:
        raise ValueError(f"V0 must be a positive definite ({nx}, {nx}) matrix, got {P}")
    Vq = Polynomial.quadratic(P)
    radius = 2.0 * float(np.abs(system.state_box).max())
    notes: list[str] = []
    ls = sos_level(Vq, f, multiplier_degree=multiplier_degree, epsilon=epsilon,
                   solver=solver, radius=radius)
    say(f"[sos] quadratic V: SDP level {ls.level:.6g} ({ls.solves} SDPs)")
    history = [{"degree": 2, "round": 0, "sdp_level": ls.level,
                "seconds": time.perf_counter() - t0, "area": star_area(Vq, ls.level)}]
    V, level = Vq, ls.level
    if ls.level <= 0:
        notes.append("no positive level is SOS-feasible for the quadratic V")
    elif degree > 2:
        kw = dict(t0=t0, multiplier_degree=multiplier_degree,
                  epsilon=_vs_strictness(P, f, ls.level, epsilon, strictness, notes),
                  iterations=iterations, backoff=backoff, push=push, solver=solver, say=say,
                  edge=None if keep_in is None else keep_in.sample_boundary(
                      _KEEP_IN_SAMPLES * nx, np.random.default_rng(0)))
        V, level = _vs_search(Vq, ls.level, f, degree, history, notes, radius, None, kw)
        if keep_in is not None and V.degree > 2:
            V, level = _keep_inside(V, level, Vq, ls.level, f, degree, history,
                                    notes, radius, kw)
    sdp_seconds = time.perf_counter() - t0
    res = SOSResult(SOSStatus.NOT_CERTIFIED, V.degree, V, level, 0.0, 0.0, notes, inner,
                    history=history, sdp_seconds=sdp_seconds)
    if not certify or level <= 0:
        res.status, res.reason = (SOSStatus.NOT_CERTIFIED, "certify=False") if level > 0 \
            else (SOSStatus.NO_LEVEL, "")
        res.seconds = time.perf_counter() - t0
        return res
    # ---- re-certification on the true closed loop (the only claim)
    t1 = time.perf_counter()
    extent = float(np.linalg.norm(boundary_points(V, level), axis=1).max())
    res.outer = outer = extent * (1 + outer_margin) if domain is None else domain.max_norm()
    if domain is None and not outer > inner:
        res.reason = (f"the SOS level set (extent {extent:.4g}) does not contain the "
                      f"excluded ball B_ε (ε = {inner:g})")
        res.seconds = time.perf_counter() - t0
        return res
    res.problem = RoaProblem(system, V, controller, inner=inner, outer=outer, domain=domain,
                             verify_options=dict(verify_options or {}))
    cert = certify_roa(res.problem, level, search=True,
                       log=(lambda m: say("[sos] certify" + m)))
    res.certificate = cert
    res.certify_seconds = time.perf_counter() - t1
    _record(res, cert)
    res.seconds = time.perf_counter() - t0
    say(f"[sos] degree {V.degree}: SDP level {level:.6g}, certified {res.certified_level:.6g} "
        f"({res.text}, {res.seconds:.2f} s)")
    return res


def _vs_strictness(P: np.ndarray, f: list[Polynomial], level: float, epsilon: float,
                   strictness: float, notes: list) -> float:
    """The V–s iteration's ``ε_vs``: ``strictness`` times the start ``xᵀPx``'s decrease rate
    at its SDP ``level`` (at least ``epsilon``); a note says when it is larger."""
    # the same ε asks V - ε‖x‖² ∈ Σ: at most half the start's own λ_min(P) at its level, so
    # that the start stays feasible for a fast loop (a rate above 1000 λ_min(P))
    P = 0.5 * (P + P.T)
    cap = 0.5 * float(np.linalg.eigvalsh(P)[0]) / level
    eps_vs = max(epsilon, min(strictness * _start_rate(P, f) / level, cap))
    if eps_vs > epsilon:
        notes.append(f"V-s iteration with strictness {eps_vs:.3g} (a fraction "
                     f"{strictness:g} of the starting V's decrease rate)")
    return eps_vs


def _start_rate(P: np.ndarray, f: list[Polynomial]) -> float:
    """``λ_min(-(AᵀP + PA))`` for the linear part ``A`` of the polynomial closed loop ``f``:
    the least rate at which ``xᵀPx`` decreases relative to ``‖x‖²`` near the origin (0 when
    it does not decrease there)."""
    nx = len(P)
    unit = [tuple(int(i == j) for i in range(nx)) for j in range(nx)]
    A = np.array([[p.to_dict().get(e, 0.0) for e in unit] for p in f], dtype=float)
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(P))):
        return 0.0
    lam = float(np.linalg.eigvalsh(-(A.T @ P + P @ A))[0])
    return lam if np.isfinite(lam) and lam > 0 else 0.0


def _vs_search(Vq: Polynomial, level_q: float, f, degree: int, history: list, notes: list,
               radius: float, outside, kw: dict) -> tuple[Polynomial, float]:
    """The V–s iteration from the quadratic ``Vq`` at its SDP level ``level_q``; where no V
    step succeeds, again in scaled units. ``outside``: boundary samples of a domain the
    sets are kept in (``None``: none)."""
    nx = Vq.nx
    V, level = vs_iteration(Vq, level_q, f, degree, history, notes, radius=radius,
                            outside=outside, **kw)
    if V.degree == 2:
        # no V step succeeded: again in units of the quadratic set's extent R (x = R·y).
        # With monomials of degree 6 and more at |x| ~ 8 the SDPs are too badly scaled
        # for the solvers (Fossil's NonPoly2: the first V step fails unscaled and
        # succeeds scaled); where the unscaled iteration works it is kept (Van der Pol:
        # areas 11.7 / 13.5 unscaled, 9.4 / 12.4 scaled, degree 4 / 6). Levels are the
        # same in both units, areas scale with R^nx.
        R = float(np.linalg.norm(boundary_points(Vq, level_q) if outside is None
                                 else boundary_points(V, level), axis=1).max())
        kw["say"](f"[sos] no V step succeeded; the V-s iteration again with x = {R:.4g}·y")
        notes.append(f"the V-s iteration was repeated in units x = {R:.4g}·y (the SDPs "
                     "in x failed)")
        # the same strictness in x: -V̇ >= ε‖x‖² = ε R² ‖y‖²
        Vy, level_y = vs_iteration(Vq.substituted(R), level_q,
                                   [p.substituted(R).scaled(1.0 / R) for p in f], degree,
                                   history, notes, radius=radius / R, area_scale=R ** nx,
                                   outside=None if outside is None else outside / R,
                                   **dict(kw, epsilon=kw["epsilon"] * R ** 2,
                                          edge=None if kw["edge"] is None else kw["edge"] / R))
        if Vy.degree > 2:
            V, level = Vy.substituted(1.0 / R), level_y
    return V, level


def _keep_inside(V: Polynomial, level: float, Vq: Polynomial, level_q: float, f,
                 degree: int, history: list, notes: list, radius: float,
                 kw: dict) -> tuple[Polynomial, float]:
    """``(V, level)``, or where its set crosses the boundary of the domain (on its seeded
    samples ``kw["edge"]``), the V–s iteration's result with its sets kept inside when that
    one's set inside the domain is larger. A set across ∂D would be cut down by containment (b) when
    certified (Van der Pol on its box [-1.5, 1.5]²: certified area 4.10 -> 6.97)."""
    out = kw["edge"]     # seeded samples of ∂D (sos_roa)
    edge = float(V(out).min())
    if edge >= level:
        return V, level
    order = gram_size(Vq.nx, degree, max(1, max(p.degree for p in f)))
    if order > _KEEP_IN_GRAM_LIMIT:
        notes.append(f"the set crosses the domain's boundary; not searched again inside it "
                     f"(Gram matrices of order {order} > {_KEEP_IN_GRAM_LIMIT})")
        return V, level
    kw["say"](f"[sos] the set crosses the domain's boundary (least V there {edge:.4g} < "
              f"level {level:.4g}): the V-s iteration again inside the domain")
    V2, level2 = _vs_search(Vq, level_q, f, degree, history, notes, radius, out, kw)
    inside = star_area(V, min(level, edge))
    inside2 = star_area(V2, min(level2, float(V2(out).min())))
    notes.append(f"the V-s iteration was repeated inside the domain: area in it "
                 f"{inside2:.4g} against {inside:.4g}")
    return (V2, level2) if inside2 > inside else (V, level)


# --------------------------------------------------------------------------- the pipeline's
#: boundary samples per state of the region the V–s iteration keeps its sets in (``keep_in``)
_KEEP_IN_SAMPLES = 200
#: the second search inside the domain (``keep_in``) repeats the SOS programs: it runs only
#: where their Gram matrices have order at most this (half the automatic budget; a 2-D cubic
#: at degree 6: 20; Fossil's NonPoly2 at degree 4, 34, doubled its SOS time to ~80 CPU s)
_KEEP_IN_GRAM_LIMIT = 20

#: ``sos.degree = "auto"``: the degree is chosen from the size of the SDPs
#: (:func:`choose_degree`)
AUTO = "auto"
#: the degrees the automatic choice tries, largest first; degree 2 (a quadratic V) is left to
#: the quadratic candidates, which the default method runs anyway
AUTO_DEGREES: tuple[int, ...] = (6, 4)
#: the automatic choice's budget: the largest order of a Gram matrix its SOS programs may set
#: up (:func:`nlyap_opt.design.sos_sdp.gram_size`; a size, never a time)
AUTO_GRAM_LIMIT = 40


@dataclass
class SOSConfig:
    """The ``sos`` section of a run configuration: an SOS certificate before the neural stage.

    Attributes
    ----------
    degree : {"auto", 0, 2, 4, 6}
        Degree of the SOS ``V`` (0: no SOS stage; ``"auto"``: chosen by
        :func:`choose_degree`, off where SOS does not apply).
    iterations : int
        Budget of the V–s iteration, in rounds per degree (``degree > 2``).
    """

    degree: int | str = field(default=0, metadata={
        "choices": (AUTO, 0, 2, 4, 6),
        "doc": "degree of an SOS V certified before the neural stage where the closed loop "
               "is polynomial (with learned f and no input: a polynomial model fitted to φ; "
               "0: off; 'auto': the largest of 6, 4 whose "
               f"SDPs have Gram matrices of order <= {AUTO_GRAM_LIMIT}, off for a "
               "non-polynomial closed loop or larger SDPs; nlyap_opt.candidates.sos)"})
    iterations: int = field(default=20, metadata={
        "lo": 1, "doc": "V-s iteration rounds per degree (a count, never a time)"})


@dataclass(frozen=True)
class SOSChoice:
    """The SOS degree a run uses (:func:`choose_degree`) and why.

    Attributes
    ----------
    degree : int
        0: no SOS stage.
    reason : str
        One line: why this degree (or why off).
    configured : int or str
        The configured ``sos.degree`` (``"auto"`` or a number).
    gram : int
        Order of the largest Gram matrix of its SDPs (0 when off).
    """

    degree: int
    reason: str
    configured: int | str
    gram: int = 0

    @property
    def automatic(self) -> bool:
        """True when the degree was chosen by the rule (``sos.degree = "auto"``)."""
        return self.configured == AUTO

    def describe(self) -> str:
        """``sos.degree 'auto' -> degree 6: why`` (one line for the log and ``nlyap config``)."""
        what = f"degree {self.degree}" if self.degree else "off"
        return f"sos.degree {self.configured!r} -> {what}: {self.reason}"


def choose_degree(system, degree: int | str = AUTO, *, known: bool = True,
                  controller=None, model: PolynomialFit | None = None) -> SOSChoice:
    r"""The degree of the SOS candidate of a run: ``degree`` when it is a number, else chosen.

    The automatic choice (``degree = "auto"``) runs SOS only where it applies and is cheap:

    1. the model of ``f`` is used (``known``), or, with learned dynamics, ``model``, a
       polynomial model fitted to ``φ`` (:func:`learned_model`; ``φ`` is a tanh network,
       and an unknown system has no polynomial model of its own), whose degree counts as
       ``f``'s below;
    2. the closed loop is polynomial: no inputs, or a polynomial ``controller`` (the pipeline's
       ``C·tanh(Kx + b)`` is not), and ``f`` expands exactly
       (:func:`nlyap_opt.design.polynomial.polynomial_closed_loop`);
    3. the largest degree of :data:`AUTO_DEGREES` whose SDPs have Gram matrices of order at
       most :data:`AUTO_GRAM_LIMIT` (:func:`nlyap_opt.design.sos_sdp.gram_size` of the state
       dimension, the degree and the degree of ``f``): 6 for a cubic ``f`` in 2-D (order 20),
       4 for a cubic in 3-D (34); off for a quartic in 3-D (55 at degree 4) and in 4 or
       more states whatever ``f`` (at least 69; ``f`` is then not expanded). The budget is a
       size of the programs, never a time: the same system gets the same degree on any
       machine.

    Parameters
    ----------
    system : systems.System
    degree : {"auto", 0, 2, 4, 6}
        The configured ``sos.degree``.
    known : bool
        The run uses the model of ``f`` (``--known-dynamics``).
    controller : nlyap_opt.kernel.network.Network, optional
        The run's initial controller (``None`` for a system without inputs).
    model : PolynomialFit, optional
        With learned dynamics: the polynomial model of ``φ`` the SOS programs would use.

    Returns
    -------
    SOSChoice
        The degree (0: off) and the reason in one line.
    """
    if degree != AUTO:
        why = "off as configured" if not degree else "as configured"
        return SOSChoice(int(degree), why, degree)
    learned = not known or not getattr(system, "has_model", True)
    if system.nu and (controller is None or learned):
        return SOSChoice(0, "the closed loop under the controller C·tanh(Kx + b) is not "
                            "polynomial", degree)
    if learned and model is None:
        return SOSChoice(0, "learned dynamics: the SOS programs need the polynomial model of f",
                         degree)
    low = AUTO_DEGREES[-1]
    least = gram_size(system.nx, low, 1)   # whatever f: no expansion where nothing would fit
    if least > AUTO_GRAM_LIMIT:
        return SOSChoice(0, f"n = {system.nx}: {_too_large(low, f'>= {least}')}", degree)
    if learned:
        f = model.polynomials
    else:
        try:
            f = polynomial_closed_loop(system, controller)
        except NotPolynomialError as err:
            ops = ", ".join(err.operations) or "a non-polynomial operation"
            return SOSChoice(0, f"the closed loop is not polynomial: it applies {ops}", degree)
    deg_f = max(1, max(p.degree for p in f))
    what = (f"a degree-{model.degree} model of φ (residual {model.residual:.2g}) for learned "
            "dynamics, " if learned else "")
    for d in AUTO_DEGREES:
        m = gram_size(system.nx, d, deg_f)
        if m <= AUTO_GRAM_LIMIT:
            return SOSChoice(d, f"{what}n = {system.nx}, deg f = {deg_f}: Gram matrices of "
                                f"order {m} <= {AUTO_GRAM_LIMIT}", degree, m)
    m = gram_size(system.nx, low, deg_f)
    return SOSChoice(0, f"n = {system.nx}, deg f = {deg_f}: {_too_large(low, m)}", degree)


def _too_large(degree: int, order) -> str:
    """Why the automatic choice is off: the least degree's SDPs exceed the budget."""
    return (f"degree {degree} needs Gram matrices of order {order} > {AUTO_GRAM_LIMIT}; the "
            f"quadratic candidates cover degree 2, and sos.degree {degree} runs it anyway")


def certify_sos(problem, config: SOSConfig, *, inner_fraction: float | None = None,
                model: PolynomialFit | None = None, log=print) -> SOSResult:
    r"""The pipeline's SOS candidate: :func:`sos_roa`'s ``V`` certified on ``problem``.

    The SOS programs run on the polynomial closed loop of ``problem.system`` under
    ``problem.controller``; the resulting ``(V, c)`` is then certified by
    :func:`nlyap_opt.certification.certificate.certify_roa` on ``problem`` with its ``V`` replaced
    (the run's verification domain, initial set and verifier options; the level searched downwards
    from the SDP level), so that the SOS certificate and the neural one claim sets of the
    same kind and are compared on the same grid.

    With learned dynamics (no inputs) the SOS programs run on a polynomial model fitted to
    ``φ`` (:func:`learned_model`: ``φ`` is a tanh network, and an unknown system has no
    model of its own), started from the Lyapunov matrix of the model's linear part; their
    ``V`` is only a candidate, certified on ``φ`` with the robust margin of ``η`` like every
    learned-dynamics certificate. Not applicable (``status`` ``"not applicable: ..."``, no
    SDP solved) when the closed loop is not polynomial (a saturated ``tanh`` controller,
    ``sin``, ...; with learned dynamics: any input).

    Parameters
    ----------
    problem : RoaProblem
        The run's problem; its ``V`` is ignored.
    config : SOSConfig
        ``degree`` (> 0; ``"auto"`` is resolved by :func:`choose_degree` first) and
        ``iterations``.
    inner_fraction : float, optional
        The SOS certificate's ``ε`` as a fraction of ``problem.inner`` (default: as the
        quadratic candidates, :func:`sos_policy`).
    model : PolynomialFit, optional
        With learned dynamics: the polynomial model of ``φ`` already fitted
        (:func:`learned_model`; fitted here when not given).
    log : callable

    Returns
    -------
    SOSResult
        With :attr:`~SOSResult.certificate` and :attr:`~SOSResult.problem` set when the
        verifier ran.
    """
    if not isinstance(config.degree, int) or not config.degree:
        raise ValueError(f"SOSConfig.degree is {config.degree!r}: the SOS stage is off (0) or "
                         "not resolved ('auto': choose_degree gives the degree)")
    policy = sos_policy(inner_fraction, known=problem.known)
    eps = problem.inner * policy.inner_fraction
    t0 = time.perf_counter()
    kw = {}
    if not problem.known:
        if problem.system.nu or problem.dynamics is None:
            reason = ("learned dynamics with inputs: the closed loop under the controller "
                      "C·tanh(Kx + b) is not polynomial; the quadratic candidates and the "
                      "neural V cover this run")
            return SOSResult(SOSStatus.NOT_APPLICABLE, config.degree, notes=[reason],
                             inner=eps, non_polynomial={"learned dynamics": "φ"},
                             reason=reason)
        if model is None:
            try:
                model = learned_model(problem.system, problem.dynamics,
                                      problem.domain.bounding_box())
            except ValueError as err:
                reason = f"no polynomial model of φ: {err}"
                return SOSResult(SOSStatus.NOT_APPLICABLE, config.degree, notes=[reason],
                                 inner=eps, non_polynomial={"learned dynamics": "φ"},
                                 reason=reason)
        V0 = _start_matrix(model.linear_part)
        if V0 is None:
            reason = ("the polynomial model of φ has no quadratic Lyapunov function at the "
                      "origin (its linear part is not Hurwitz with a margin): no V starts the "
                      "SOS programs")
            return SOSResult(SOSStatus.NO_LEVEL, config.degree, notes=[reason], inner=eps,
                             reason=reason)
        kw = dict(f=model.polynomials, V0=V0)
        log(f"  learned dynamics: the SOS programs run on a degree-{model.degree} "
            f"least-squares model of φ (residual {model.residual:.2g} of its RMS on D's "
            "box); their V is a candidate, certified on φ with η")
    res = sos_roa(problem.system, degree=config.degree, inner=eps,
                  controller=problem.controller, iterations=config.iterations,
                  certify=False, keep_in=problem.domain, log=log, **kw)
    if not res.applicable or res.V is None or not res.sdp_level > 0:
        return res
    res.problem = replace(problem, V=res.V, inner=eps)
    t1 = time.perf_counter()
    # the SDP level is a candidate on R^n; on the run's domain D the level must also keep
    # {V <= c} off ∂D: the policy starts at the lesser of the SDP level and the least V on
    # ∂D or at a sampled / IPOPT decrease violation
    cert = certify_candidate(replace(problem, V=res.V), policy, cap=res.sdp_level,
                             log=lambda m: log("  " + m))
    res.certificate, res.certify_seconds = cert, time.perf_counter() - t1
    res.outer = float(problem.domain.max_norm())
    _record(res, cert)
    res.seconds = time.perf_counter() - t0
    return res


def _start_matrix(A: np.ndarray) -> np.ndarray | None:
    """The Lyapunov matrix of ``A`` (``AᵀP + PA = −I``) when it is positive definite and
    finite, else ``None`` (a linear part stable only up to rounding gives no usable P)."""
    if not (np.all(np.isfinite(A)) and np.max(np.linalg.eigvals(A).real) < 0):
        return None
    P = lyapunov_matrix(A)
    if not np.all(np.isfinite(P)) or not np.linalg.eigvalsh(0.5 * (P + P.T))[0] > 0:
        return None
    return P


def sos_policy(inner_fraction: float | None = None, known: bool = True) -> LevelPolicy:
    """The certification policy of the pipeline's SOS candidate: ε = ``inner_fraction`` of
    the run's (default: as the quadratic candidates,
    :data:`nlyap_opt.candidates.quadratic.INNER_FRACTION` with the true ``f`` and
    :data:`~nlyap_opt.candidates.quadratic.LEARNED_INNER_FRACTION` with learned dynamics,
    where the robust margin ``η‖∇_L V‖`` outweighs the decrease near the origin), that
    radius only, searched down from the lesser of the SDP level and the candidate level,
    decrease violations followed down."""
    if inner_fraction is None:
        inner_fraction = INNER_FRACTION if known else LEARNED_INNER_FRACTION
    return LevelPolicy(inner_fraction, (1.0,), follow_violations=True)


def sos_may_fit(nx: int) -> bool:
    """Whether ``"auto"`` can pick a degree for ``nx`` states whatever ``f`` (the least
    degree's SDPs with a linear ``f`` within :data:`AUTO_GRAM_LIMIT`): else no model of a
    learned ``φ`` is fitted."""
    return gram_size(nx, AUTO_DEGREES[-1], 1) <= AUTO_GRAM_LIMIT


def learned_model(system, dynamics, box) -> PolynomialFit:
    """The polynomial search model of a learned closed loop without inputs: ``φ`` (with the
    exactly known components of ``system``) fitted on ``box`` by
    :func:`nlyap_opt.design.polynomial.fit_polynomial_model`. Only the SOS programs use it;
    every claim is made on ``φ`` with its bound ``η`` (the SOS search never uses the model
    of f; the known components of ``system`` enter φ's closed loop as everywhere)."""
    x = ca.MX.sym("x", system.nx)
    cl = closed_loop(system, None, dynamics, x=x, strict=False)
    return fit_polynomial_model(ca.Function("phi_closed_loop", [x], [cl.rhs]), box)


def _record(res: SOSResult, cert: RoaCertificate) -> None:
    """The verdict of ``cert`` into ``res``."""
    if cert.certified:
        res.status, res.reason = SOSStatus.CERTIFIED, ""
        res.certified_level = float(cert.level)
    else:
        res.status, res.reason = SOSStatus.NOT_CERTIFIED, cert.reason
