r"""Certified regions of attraction.

For a level :math:`c`, the set :math:`\Omega_c = \{x \in B_r : V(x) \le c\}` lies in the
region of attraction of the **true** closed loop when

- (a) decrease: :math:`\nabla V \cdot g(x) < -\beta` on :math:`\{\varepsilon \le \|x\| \le r,
  V(x) \le c\}` (``g = φ`` with :math:`\beta > M\eta` for learned dynamics, ``g = f``,
  :math:`\beta = 0` for known dynamics);
- (b) containment: :math:`V(x) > c` on :math:`\|x\| = r` (and, so that the certificate is
  not trivial, :math:`V(x) < c` on :math:`\|x\| = \varepsilon`, i.e.
  :math:`B_\varepsilon \subseteq \Omega_c`);
- (c) inner ball: :math:`B_\varepsilon \subseteq E = \{x^\top P x \le c_q\}` and ``E`` is a
  quadratic Lyapunov sublevel set of the true closed loop. For known ``f`` this is proved by
  verifying :math:`P J(y) + J(y)^\top P \prec 0` for every ``y`` of a box containing ``E``
  (``J`` the closed-loop Jacobian; since :math:`f(x) = \int_0^1 J(sx)\,ds\;x` and the set
  of such matrices is convex, :math:`\dot V_q = x^\top (P\bar J + \bar J^\top P) x < 0`
  on :math:`E \setminus \{0\}`). For unknown ``f`` it is the paper's assumption
  (LQR region of attraction contains :math:`B_\varepsilon`) and is reported as such.

  When the closed loop's linearisation has eigenvalues on the imaginary axis (a centre
  manifold, e.g. :math:`x' = -x^3`), no ``P`` makes ``P J + JᵀP ≺ 0`` at 0; for known, smooth
  ``f`` the non-exponential form :func:`certify_inner_blowup` then proves
  :math:`\dot V_q < 0` on :math:`E \setminus \{0\}` by a weighted blow-up of the origin.
  Where ``P J + JᵀP ≺ 0`` fails somewhere on ``E`` although :math:`\dot V_q < 0` holds, the
  shell form proves :math:`\dot V_q < 0` directly on :math:`E \setminus B_{\varepsilon_s}`
  and the Jacobian form on a small ellipse around :math:`B_{\varepsilon_s}`
  (:func:`_inner_ellipse`).

Every trajectory from :math:`\Omega_c` decreases ``V`` until it enters
:math:`B_\varepsilon \subseteq E`, which is forward invariant and converges to 0; so
:math:`\Omega_c \cup E` is certified.
"""

from __future__ import annotations

import itertools
import math
import re
import time
from dataclasses import dataclass, field
from enum import Enum
from fractions import Fraction

import casadi as ca
import numpy as np
from scipy.linalg import eigh, solve_sylvester

from verification import (
    Counterexample,
    QueryStatus,
    VerificationProblem,
    VerificationResult,
    lyapunov_problem,
)
from verification.interval import CheckedIntervalArithmetic, Interval

from ..design.control import (
    InnerStatus,
    ellipse_candidates,
    lyapunov_matrix,
    polytopic_lyapunov_matrix,
    quadratic_lyapunov,
    verdict_of,
    volume_lyapunov_matrix,
)
from ..design.polynomial import exact_polynomials
from ..distributed import parallel
from ..kernel.domain import Ball, Box, Ellipsoid, as_domain
from ..kernel.errors import UnsupportedOperationError
from ..kernel.exact import (
    float_down,
    float_up,
    inverse,
    inverse_diagonal,
    positive_definite,
    rational,
    rational_matrix,
)
from ..kernel.network import Network
from ..kernel.rounding import EPS, FOLD
from ..kernel.sampling import sample_ball, sample_sphere
from ..kernel.simulate import (
    at_other_equilibrium,
    horizon,
    integration,
    jacobian_at_origin,
    simulate,
)
from ..kernel.symbolic import closed_loop
from ..kernel.walker import REAL, compile_function, evaluate, exact_values
from ..learned.interval_sup import interval_arithmetic

__all__ = [
    "axis_count", "LevelCandidate", "candidate_level", "certify_level", "certify_inner_blowup",
    "quadratic_form", "quadratic_containment", "quadratic_inner_ball", "inner_ellipse_bound",
    "centre_lyapunov_matrix", "mean_value_form", "sliced_enclosure", "seeded_jacobian",
    "split_boxes",
    "TaylorDecrease", "SaturatedLoop", "sector_lyapunov_matrix",
    "certify_inner_ellipse", "grid_area", "inner_ball_level", "true_roa_mask", "true_roa_horizon",
    "true_roa_stays",
    "InnerForm",
    "InnerFormKind",
]


class InnerFormKind(Enum):
    """The kinds of proof of condition (c) (see :func:`certify_inner_ellipse`)."""

    MINORS = "minors"
    FROBENIUS = "frobenius"
    SHELL = "shell"
    BLOWUP = "blow-up"


_JACOBIAN_KINDS = (InnerFormKind.MINORS, InnerFormKind.FROBENIUS)
_FORMS_EXPECTED = ("expected 'minors', 'frobenius', 'shell r=R + minors|frobenius' (R > 0) or "
                   "'blow-up w=[W1, ...], m=M' (positive integers)")
_SHELL = re.compile(r"shell r=(\S+) \+ (minors|frobenius)")
_BLOWUP = re.compile(r"blow-up w=\[([0-9, ]+)\], m=([0-9]+)")


@dataclass(frozen=True)
class InnerForm:
    """How condition (c) was proved: a kind and its parameters.

    Stored in ``certificate.json`` as the text of :meth:`to_str` (``"minors"``,
    ``"frobenius"``, ``"shell r=0.025 + minors"``, ``"blow-up w=[1, 2, 2], m=4"``), read back
    by :meth:`parse`; ``parse(f.to_str()) == f``.

    Parameters
    ----------
    kind : InnerFormKind
        The proof.
    radius : float or None
        ``shell``: the inner radius ``ε_s`` (``0 < ε_s``; the re-check also needs ``≤ ε``).
    core : InnerFormKind or None
        ``shell``: the Jacobian form on the small ellipse (``MINORS`` or ``FROBENIUS``).
    weights : tuple of int
        ``blow-up``: the weights ``w`` of the coordinates.
    order : int or None
        ``blow-up``: the order ``m`` of the leading term.
    """

    kind: InnerFormKind
    radius: float | None = None
    core: InnerFormKind | None = None
    weights: tuple[int, ...] = ()
    order: int | None = None

    def __post_init__(self):
        k = self.kind
        if k is InnerFormKind.SHELL:
            r = self.radius
            if r is None or not (math.isfinite(r) and r > 0) or self.core not in _JACOBIAN_KINDS:
                raise ValueError("a shell form needs a radius r > 0 and the minors or frobenius "
                                 "form inside")
            object.__setattr__(self, "radius", float(r))
        elif k is InnerFormKind.BLOWUP:
            w = tuple(int(v) for v in self.weights)
            if not w or min(w) < 1 or self.order is None or int(self.order) < 0:
                raise ValueError("a blow-up form needs positive integer weights and an order "
                                 "m >= 0")
            object.__setattr__(self, "weights", w)
            object.__setattr__(self, "order", int(self.order))
        elif (self.radius, self.core, self.weights, self.order) != (None, None, (), None):
            raise ValueError(f"the {k.value} form has no parameters")

    def to_str(self) -> str:
        """The stored text (the format of ``certificate.json``'s ``inner_ellipse.form``)."""
        if self.kind is InnerFormKind.SHELL:
            return f"shell r={self.radius!r} + {self.core.value}"
        if self.kind is InnerFormKind.BLOWUP:
            return f"blow-up w={list(self.weights)}, m={self.order}"
        return self.kind.value

    @classmethod
    def parse(cls, text: str) -> InnerForm:
        """The form that :meth:`to_str` wrote as ``text``.

        Raises
        ------
        ValueError
            If ``text`` is none of the forms (the message lists them).
        """
        text = str(text)
        for kind in _JACOBIAN_KINDS:
            if text == kind.value:
                return cls(kind)
        try:
            if m := _SHELL.fullmatch(text):
                return cls(InnerFormKind.SHELL, radius=float(m.group(1)),
                           core=InnerFormKind(m.group(2)))
            if m := _BLOWUP.fullmatch(text):
                return cls(InnerFormKind.BLOWUP, order=int(m.group(2)),
                           weights=tuple(int(v) for v in m.group(1).split(",")))
        except ValueError as exc:      # "r=1..2", "w=[1,,2]", "r=0": the pattern, no form
            raise ValueError(f"{text!r} is not an inner-ellipse form ({exc}); "
                             f"{_FORMS_EXPECTED}") from None
        raise ValueError(f"{text!r} is not an inner-ellipse form; {_FORMS_EXPECTED}")


@dataclass
class LevelCandidate:
    level: float
    argmin: np.ndarray
    source: str          # "decrease" (a Lie-derivative boundary point) or "sphere"
    seconds: float
    violations: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    # sampled decrease violations with the least V (for training: they limit the level)


def _fun(x, *outs):
    return ca.Function("f", [x], list(outs))


def candidate_level(x: ca.MX, V: ca.MX, lie: ca.MX, *, inner: float, outer=None,
                    margin: float = 0.0, n_starts: int = 12, n_samples: int = 20000,
                    seed: int = 0, domain=None) -> LevelCandidate:
    r"""Least ``V`` over :math:`\{x \in D\setminus B_\varepsilon: \nabla V\cdot g \ge -\beta\}
    \cup \partial D`: sampling, then IPOPT from the best samples (multi-start).

    ``D`` is ``domain`` (a :class:`nlyap_opt.kernel.domain.Region`) or the ball ``‖x‖ ≤ outer``.
    The value is a *candidate* only: :func:`certify_level` proves a level.
    """
    t0 = time.perf_counter()
    n = x.numel()
    D = _domain(domain, outer, n)
    rng = np.random.default_rng(seed)

    F = _fun(x, V, lie)
    pts = D.sample(n_samples, rng, inner)
    v, d = (a[:, 0] for a in evaluate(F, [pts]))
    sph = D.sample_boundary(max(2000, n_samples // 10), rng)
    vs = evaluate(F, [sph])[0][:, 0]
    best = (float(vs.min()), sph[np.argmin(vs)], "sphere")
    bad = d >= -margin
    if bad.any():
        i = np.argmin(np.where(bad, v, np.inf))
        if v[i] < best[0]:
            best = (float(v[i]), pts[i], "decrease")
    # IPOPT refinement (multi-start) of both parts
    starts_dec = pts[np.argsort(np.where(bad, v, np.inf))[:n_starts]][: int(bad.sum())]
    starts_dec = np.vstack([starts_dec, pts[np.argsort(-d)[: max(1, n_starts // 3)]]])
    found = least_violation(x, V, lie, starts_dec, inner=inner, domain=D, margin=margin)
    if found is not None and found[0] < best[0]:
        best = (found[0], found[1], "decrease")
    for piece in D.boundary_nlp(x):
        g = piece.get("g")
        nlp_b = ca.nlpsol("lev_sph", "ipopt", {"x": x, "f": V, "g": g if g is not None
                                              else type(x)()}, _IPOPT)
        on = np.flatnonzero(piece["on"](sph))
        for x0 in sph[on[np.argsort(vs[on])[:n_starts]]]:
            kw = {k: piece[k] for k in ("lbg", "ubg", "lbx", "ubx") if k in piece}
            try:
                sol = nlp_b(x0=x0, **kw)
            except RuntimeError:
                continue
            xs = np.array(sol["x"]).ravel()
            if piece["check"](xs):
                vv = float(F(xs)[0])
                if vv < best[0]:
                    best = (vv, xs, "sphere")
    order = np.argsort(np.where(bad, v, np.inf))[: min(int(bad.sum()), 4 * n_starts)]
    viol = pts[order]
    if best[2] == "decrease":
        viol = np.vstack([np.asarray(best[1])[None], viol])
    return LevelCandidate(best[0], np.asarray(best[1]), best[2], time.perf_counter() - t0,
                          viol.reshape(-1, n))


_IPOPT = {"ipopt.print_level": 0, "print_time": 0, "ipopt.sb": "yes", "ipopt.max_iter": 200,
          "ipopt.tol": 1e-10}


def least_violation(x, V, lie, starts, *, inner: float, domain, margin: float = 0.0,
                    tol: float = 1e-9):
    r"""Least ``V`` over :math:`\{x \in D\setminus B_\varepsilon: \nabla V\cdot g + \beta
    \ge 0\}` by IPOPT from each start: ``(V, x)`` of the best point that satisfies the
    constraints when re-evaluated, or ``None``.

    With ``tol = 0`` no level at or above the returned ``V`` can satisfy condition (a): the
    point violates the decrease inside it (a local search: smaller violations may exist).
    IPOPT ends on the constraint ``∇V·g + β ≥ 0`` from inside, a little below zero (about
    −1e-8); ``tol`` accepts such points. Only a level to try comes from here, never a proof.
    """
    D = domain
    F = _fun(x, V, lie)
    r2 = ca.sumsqr(x)
    plain = D.plain_ball   # the ball: ‖x‖² ≤ r² in one row
    region = [] if plain else [g for g, _ in D.constraints(x)]
    ub_r2 = D.radius**2 if plain else np.inf
    nlp = ca.nlpsol("lev_dec", "ipopt",
                    {"x": x, "f": V, "g": ca.vertcat(lie + margin, r2, *region)}, _IPOPT)
    bb = D.bounding_box()
    bounds = {} if plain else {"lbx": bb[:, 0], "ubx": bb[:, 1]}
    best = None
    for x0 in np.atleast_2d(np.asarray(starts, dtype=float)):
        try:
            sol = nlp(x0=x0, lbg=[0.0, inner**2] + [-np.inf] * len(region),
                      ubg=[np.inf, ub_r2] + [0.0] * len(region), **bounds)
        except RuntimeError:
            continue
        xs = np.array(sol["x"]).ravel()
        vv, dd = (float(a) for a in F(xs))
        inside = xs @ xs <= ub_r2 + 1e-9 if plain else bool(D.contains(xs, tol=1e-9)[0])
        ok = dd >= -margin - tol and inner**2 - 1e-9 <= xs @ xs and inside
        if ok and (best is None or vv < best[0]):
            best = (vv, xs)
    return best


#: the level tried when a level search would drop below the inner ball's:
#: ``(1 + INNER_LEVEL_MARGIN)·max_{‖x‖=ε} V`` (room for the strict ``V < c`` on the sphere)
INNER_LEVEL_MARGIN = 0.02


def inner_ball_level(x, V, inner: float, *, n_samples: int = 4000, n_starts: int = 4,
                     seed: int = 0) -> float:
    r"""``max V`` on the sphere :math:`\|x\| = \varepsilon` (sampled, then IPOPT from the
    best samples; every value is ``V`` evaluated at a point of the sphere).

    No level ``c`` at or below it can hold :math:`B_\varepsilon \subseteq \Omega_c` (``V ≥
    c`` at that point of the sphere): a level search that would go there has nothing left
    to try. A lower estimate of the true maximum, used to choose levels, never as a proof
    (condition (b)'s ``V < c`` on the sphere is verified).
    """
    n = x.numel()
    rng = np.random.default_rng(seed)
    d = rng.standard_normal((max(n_samples, 2 * n), n))
    d[:n] = np.eye(n)
    d[n:2 * n] = -np.eye(n)
    pts = inner * d / np.linalg.norm(d, axis=1, keepdims=True)
    Vf = _fun(x, V)
    v = evaluate(Vf, [pts])[0][:, 0]
    best = float(np.max(v))
    nlp = ca.nlpsol("lev_in", "ipopt", {"x": x, "f": -V, "g": ca.sumsqr(x)}, _IPOPT)
    for x0 in pts[np.argsort(-v)[:n_starts]]:
        try:
            xs = np.array(nlp(x0=x0, lbg=inner**2, ubg=inner**2)["x"]).ravel()
        except RuntimeError:
            continue
        nrm = float(np.linalg.norm(xs))
        if np.all(np.isfinite(xs)) and nrm > 0:
            best = max(best, float(Vf(xs * (inner / nrm))))
    return best


def _domain(domain, outer, n: int):
    if domain is None:
        if outer is None:
            raise ValueError("give the outer radius or a domain")
        return as_domain(float(outer), n)
    return as_domain(domain, n)


# ============================================================================ exact quadratics
def quadratic_form(V) -> list[list[Fraction]] | None:
    r"""The exact matrix ``P`` of a ``V`` that is a quadratic form by construction, or ``None``.

    A network with the ``sum_of_squares`` head and only ``linear`` layers (the quadratic
    candidates, :func:`nlyap_opt.design.control.quadratic_lyapunov`) is, in real arithmetic,
    :math:`V(x) = \|s \odot W x\|^2 + e\|x\|^2` with :math:`W = W_L \cdots W_1` (the biases
    cancel in :math:`N(x) - N(0)`), ``s`` the output scale and ``e`` the head's ``eps``:
    :math:`V(x) = x^\top P x` with :math:`P = W^\top \mathrm{diag}(s^2) W + e I`, computed
    here from the stored float64 weights in rational arithmetic: exactly the function whose
    graph the verifier encloses. Any other ``V`` gives ``None``.
    """
    if not isinstance(V, Network) or V.head is None \
            or any(layer.activation != "linear" for layer in V.layers):
        return None
    W = rational_matrix(V.layers[0].weight)
    for layer in V.layers[1:]:
        A = rational_matrix(layer.weight)
        W = [[sum((a * W[k][j] for k, a in enumerate(row)), Fraction(0))
              for j in range(len(W[0]))] for row in A]
    s2 = [rational(v) ** 2 for v in
          np.broadcast_to(np.asarray(V.output_scale, dtype=float), (len(W),))]
    e = rational(V.head["eps"])
    n = len(W[0])
    return [[sum((s2[k] * W[k][i] * W[k][j] for k in range(len(W))), Fraction(0))
             + (e if i == j else 0) for j in range(n)] for i in range(n)]


def _exact_result(t0: float, point=None, prop: str = "", value: float = 0.0
                  ) -> VerificationResult:
    """``verified`` (no ``point``), or the violation of ``prop`` that an exact test proved,
    located at ``point`` (the float approximation of the exact minimiser; ``value`` is the
    property's float value there, its recorded range ``[0, value]``: ``≥ 0`` is exact)."""
    if point is None:
        return VerificationResult(QueryStatus.VERIFIED, seconds=time.perf_counter() - t0,
                                  backend="exact")
    ce = Counterexample(np.asarray(point, dtype=float), prop, 0.0, max(0.0, float(value)))
    return VerificationResult(QueryStatus.COUNTEREXAMPLE, ce, [ce],
                              seconds=time.perf_counter() - t0, backend="exact")


def _minus(A, c: Fraction, B) -> list[list[Fraction]]:
    """``A − c·B`` (``B`` ``None``: the identity)."""
    return [[a - c * (Fraction(int(i == j)) if B is None else B[i][j])
             for j, a in enumerate(row)] for i, row in enumerate(A)]


def quadratic_containment(P: list[list[Fraction]], level: float, domain,
                          piece_box) -> VerificationResult | None:
    r"""Condition (b)'s ``V > level`` on one piece of ``∂D`` for ``V = xᵀPx``, decided
    exactly (``P`` from :func:`quadratic_form`), or ``None`` where this does not decide it
    (the verifier then does).

    - ``D`` the ball ``‖x‖ ≤ r``: :math:`\min_{\|x\| = r} V = \lambda_{\min}(P) r^2`, so
      ``V > c`` on the sphere iff :math:`r^2 P - cI \succ 0`;
    - ``D`` the centred ellipsoid :math:`x^\top Q x \le 1`: iff :math:`P - cQ \succ 0`
      (the least generalised eigenvalue of ``(P, Q)`` exceeds ``c``);
    - ``D`` a box, the face :math:`x_k = t` (``piece_box``): ``V`` on the hyperplane has the
      minimum :math:`t^2 / (P^{-1})_{kk}` at :math:`x^* = t P^{-1} e_k / (P^{-1})_{kk}`, so
      :math:`c\,(P^{-1})_{kk} < t^2` proves ``V > c`` on the face; otherwise a minimiser
      on the face refutes it, and one outside the face leaves the question to the verifier.

    Every test is an exact ``LDLᵀ`` (:func:`nlyap_opt.kernel.exact.positive_definite`) or
    an exact inverse of rationals: the floats ``P``, ``c``, ``r``, ``Q``, ``t`` as they are,
    no rounding. A refutation's point is the float approximation of the minimiser; the
    violation itself (``V ≤ c`` somewhere on the piece) is what the exact test proves.
    """
    t0 = time.perf_counter()
    c = rational(level)
    Pf = _float_matrix(P)

    def refuted(x):
        return _exact_result(t0, x, "V>level on ∂D (exact)", level - x @ Pf @ x)

    if isinstance(domain, Ball) and domain.plain_ball:
        if positive_definite(_minus(P, c / rational(domain.radius) ** 2, None)):
            return _exact_result(t0)
        return refuted(domain.radius * np.linalg.eigh(Pf)[1][:, 0])
    if isinstance(domain, Ellipsoid) and domain.centre is None:
        if positive_definite(_minus(P, c, rational_matrix(domain.Q))):
            return _exact_result(t0)
        return refuted(eigh(Pf, domain.Q)[1][:, 0])    # vᵀQv = 1: on the surface
    if not isinstance(domain, Box) or not positive_definite(P):
        return None
    box = np.asarray(piece_box, dtype=float)
    k = np.flatnonzero(box[:, 0] == box[:, 1])
    if len(k) != 1 or box[k[0], 0] == 0:
        return None
    k = int(k[0])
    t = rational(box[k, 0])
    Pinv = inverse(P)
    d = Pinv[k][k]
    if c * d < t * t:
        return _exact_result(t0)
    xs = [t * Pinv[j][k] / d for j in range(len(P))]
    if all(rational(lo) <= v <= rational(hi) for v, (lo, hi) in zip(xs, box)):
        return refuted(np.array([float(v) for v in xs]))
    return None


def quadratic_inner_ball(P: list[list[Fraction]], level: float,
                         inner: float) -> VerificationResult:
    r"""``V < level`` on the inner sphere ``‖x‖ = ε`` for ``V = xᵀPx``, decided exactly:
    :math:`\max_{\|x\| = \varepsilon} V = \lambda_{\max}(P)\varepsilon^2`, so it holds iff
    :math:`cI - \varepsilon^2 P \succ 0` (exact ``LDLᵀ``, as :func:`quadratic_containment`)."""
    t0 = time.perf_counter()
    e2 = rational(inner) ** 2
    if positive_definite(_minus([[-e2 * v for v in row] for row in P], -rational(level), None)):
        return _exact_result(t0)
    Pf = _float_matrix(P)
    x = inner * np.linalg.eigh(Pf)[1][:, -1]
    return _exact_result(t0, x, "V<level on inner sphere (exact)", x @ Pf @ x - level)


# ============================================================================ Taylor's formula
#: pieces of [0, 1] in the mean-value integral of a Jacobian (:func:`sliced_enclosure`)
TAYLOR_SLICES = 16
#: the toolbox's allowance for CasADi's constant folding, exactly
#: (:data:`nlyap_opt.kernel.rounding.FOLD`)
_FOLD = Fraction(FOLD)


def seeded_jacobian(name: str, g, y) -> ca.Function:
    r"""``H(y, S) = J(y)·S``: the Jacobian of ``g`` in ``y`` by CasADi's forward mode along a
    seed ``S`` that is a *symbol* while the graph is built (evaluate it at ``S = I``).

    CasADi folds operations between numbers it knows into float64 constants as it builds a
    graph; a derivative built by ``ca.jacobian`` holds such folds of ``g``'s own constants
    (``d/dx [(10¹⁶x + x) − 10¹⁶x]`` becomes the constant 0, not 1), and no widening covers
    a fold that cancels. With a symbolic seed every derivative term keeps a symbol
    (``(10¹⁶·S + S) − 10¹⁶·S``), so the interval evaluation at ``S = I`` rounds each
    operation outward like any other and encloses the real derivative."""
    n = y.numel()
    S = (ca.SX if isinstance(y, ca.SX) else ca.MX).sym("S", n, n)
    return ca.Function(name, [y, S], [ca.densify(ca.jtimes(g, y, S))])


def sliced_enclosure(H: ca.Function, box: np.ndarray | None, weights: list[Fraction], *,
                     boxes: tuple[np.ndarray, np.ndarray] | None = None,
                     split: tuple[list[int], int] | None = None
                     ) -> tuple[list[list[Fraction]], list[list[Fraction]]] | None:
    r"""``(C, R)``, exact rational centre and radius of :math:`\sum_k w_k [h](t_k Y)`, ``Y`` =
    ``box`` (a box containing 0), :math:`t_k = (k+1)/K` for the ``K`` weights and ``[h]`` the
    outward-rounded interval enclosure of the matrix that ``H`` computes (any shape), each entry
    widened by CasADi's constant-folding allowance; ``None`` when an enclosure is not
    finite. Since :math:`tY \subseteq t_{k+1} Y` for :math:`t \le t_{k+1}`, an integral
    :math:`\int_0^1 \omega(t)\,h(ty)\,dt` with :math:`w_k = \int_{t_k}^{t_{k+1}}\omega`
    lies in the sum for every ``y ∈ Y``. ``H`` of :func:`seeded_jacobian` (further inputs,
    the seeds) is evaluated at the identity seeds. ``boxes``: the ``K`` boxes themselves
    instead of the slices of ``box`` (``(lo, hi)``, each ``(K, d)``; the caller proves that
    they hold what the sum is about). ``split = (axes, k)``: each box is cut into ``k``
    equal pieces along each of ``axes`` (the pieces share their float edges, so they cover
    it) and ``[h]`` of the box is the hull of the pieces' enclosures, tighter where ``h``
    is a deep graph of those axes (a learned φ)."""
    Interval, ia = interval_arithmetic()
    K = len(weights)
    if boxes is None:
        ts = [Fraction(k, K) for k in range(K + 1)]
        lo_b = np.array([[float_down(t * rational(v)) for v in box[:, 0]] for t in ts[1:]])
        hi_b = np.array([[float_up(t * rational(v)) for v in box[:, 1]] for t in ts[1:]])
    else:
        lo_b, hi_b = (np.asarray(b, dtype=float) for b in boxes)
    pieces = 1
    if split is not None and split[0] and split[1] > 1:
        lo_b, hi_b, pieces = split_boxes(lo_b, hi_b, *split)
    args = [Interval(lo_b, hi_b)]
    for j in range(1, H.n_in()):        # the seeds, at the identity
        eye = np.tile(np.eye(H.size1_in(j)).ravel(order="F"), (K * pieces, 1))
        args.append(Interval(eye, eye.copy()))
    res = evaluate(H, args, ia)[0]
    lo, hi = np.asarray(res.lo, dtype=float), np.asarray(res.hi, dtype=float)
    rows, cols = H.size1_out(0), H.size2_out(0)
    e = rows * cols
    if lo.size not in (e, K * pieces * e) or hi.size != lo.size:
        return None
    lo = np.broadcast_to(lo.reshape(-1, e), (K * pieces, e))   # a constant: (e,)
    hi = np.broadcast_to(hi.reshape(-1, e), (K * pieces, e))
    if pieces > 1:          # the hull of each box's pieces
        lo = lo.reshape(K, pieces, e).min(axis=1)
        hi = hi.reshape(K, pieces, e).max(axis=1)
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        return None
    L = [[Fraction(0)] * cols for _ in range(rows)]
    U = [[Fraction(0)] * cols for _ in range(rows)]
    for k, wk in enumerate(weights):
        # column-major entries of the dense matrix, widened by the fold allowance
        lk, hk = lo[k].reshape(cols, rows).T, hi[k].reshape(cols, rows).T
        for a in range(rows):
            for b in range(cols):
                vl, vh = Fraction(lk[a, b]), Fraction(hk[a, b])
                L[a][b] += wk * (vl - abs(vl) * _FOLD)
                U[a][b] += wk * (vh + abs(vh) * _FOLD)
    C = [[(L[a][b] + U[a][b]) / 2 for b in range(cols)] for a in range(rows)]
    R = [[(U[a][b] - L[a][b]) / 2 for b in range(cols)] for a in range(rows)]
    return C, R


def split_boxes(lo: np.ndarray, hi: np.ndarray, axes: list[int], k: int):
    """Each row box of ``(lo, hi)`` cut into ``k`` pieces along each of ``axes``: ``(lo',
    hi', pieces)`` with the ``pieces = k^len(axes)`` pieces of box ``i`` in rows ``i·pieces``
    onwards. The edges are ``lo + (hi − lo)·j/k`` in floats with the first and last set to
    ``lo`` and ``hi`` exactly, and neighbours share an edge: the pieces cover the box."""
    K, d = lo.shape
    grids = []
    for a in axes:
        e = lo[:, a:a + 1] + (hi[:, a:a + 1] - lo[:, a:a + 1]) * (np.arange(k + 1) / k)
        e[:, 0], e[:, -1] = lo[:, a], hi[:, a]
        grids.append(e)
    idx = np.array(list(itertools.product(range(k), repeat=len(axes))))      # (pieces, len)
    pieces = len(idx)
    new_lo = np.repeat(lo, pieces, axis=0)
    new_hi = np.repeat(hi, pieces, axis=0)
    for j, a in enumerate(axes):
        new_lo[:, a] = grids[j][:, idx[:, j]].ravel()
        new_hi[:, a] = grids[j][:, idx[:, j] + 1].ravel()
    return new_lo, new_hi, pieces


def mean_value_form(P: list[list[Fraction]], C: list[list[Fraction]],
                    R: list[list[Fraction]], d: list[Fraction] | None = None
                    ) -> list[list[Fraction]]:
    r"""The exact symmetric ``N`` with :math:`2 y^\top P \bar J y \le y^\top N y` for every
    ``y`` and every :math:`\bar J \in [C - R, C + R]` (entrywise; all ``n×n`` rationals):

    .. math:: N = PC + C^\top P + \mathrm{diag}\big((|P|R + R^\top |P|)\,\mathbf 1\big).

    With :math:`\bar J = C + \Delta`, :math:`|\Delta| \le R`:
    :math:`2y^\top P\Delta y \le 2\sum_{ab} (|P|R)_{ab}|y_a||y_b| \le \sum_{ab}
    (|P|R)_{ab}(y_a^2 + y_b^2)`. Rows of ``P`` that are 0 (a ``P`` padded to more
    coordinates than ``V`` reads) contribute nothing. With positive weights ``d`` the last
    step is :math:`2|y_a||y_b| \le (d_b/d_a) y_a^2 + (d_a/d_b) y_b^2`, so the diagonal is
    :math:`\sum_b (Q_{ab} + Q_{ba})\,d_b/d_a` (``Q = |P|R``): with ``d`` the half-widths of
    the box, each coordinate pays in proportion to its own extent.
    """
    n = len(P)
    PC = [[sum(P[i][k] * C[k][j] for k in range(n) if P[i][k]) for j in range(n)]
          for i in range(n)]
    Q = [[sum(abs(P[i][k]) * R[k][j] for k in range(n) if P[i][k]) for j in range(n)]
         for i in range(n)]
    if d is None:
        return [[PC[i][j] + PC[j][i] + (sum(Q[i][k] + Q[k][i] for k in range(n))
                                        if i == j else 0) for j in range(n)] for i in range(n)]
    return [[PC[i][j] + PC[j][i] + (sum((Q[i][k] + Q[k][i]) * d[k] for k in range(n)) / d[i]
                                    if i == j else 0) for j in range(n)] for i in range(n)]


#: the most parameters (slopes and inputs) whose box :class:`SaturatedLoop` spans by its
#: corners (``2^p`` of them)
SATURATED_MAX_PARAMETERS = 6
#: :class:`SaturatedLoop` cuts each box of ``(x, u)`` into at most this many pieces, along
#: the axes its Jacobian depends on, and encloses the hull of the pieces
SATURATED_PIECES = 512


def _cleared(prog, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Whether a checked interval walk of ``prog`` (a compiled walker program whose first
    input is the point, any further inputs square seed matrices, set to the identity) on the
    box ``[lo, hi]`` proves every non-smooth operation away from its kink or jump set and
    every partial operation inside its domain, for every output, with finite enclosures.
    A graph of smooth operations is then continuously differentiable on the box (each is on
    the interior of its domain; an argument on a closed domain's edge, ``√x`` at ``x = 0``,
    leaves a derivative graph undefined there, e.g. a division by an interval holding 0, so
    programs that hold the derivatives are checked with them)."""
    args = [Interval(np.asarray(lo, dtype=float)[None, :].copy(),
                     np.asarray(hi, dtype=float)[None, :].copy())]
    for sp in prog.sp_in[1:]:
        eye = np.eye(sp.shape[0]).ravel(order="F")[None, :]
        args.append(Interval(eye, eye.copy()))
    ar = CheckedIntervalArithmetic(1, len(prog.sp_out))
    try:
        with np.errstate(all="ignore"):
            outs = evaluate(prog, args, ar)
    except (ArithmeticError, ValueError):
        return False
    ar.collect(outs)
    finite = all(np.all(np.isfinite(o.lo)) and np.all(np.isfinite(o.hi)) for o in outs)
    return finite and not (ar.jump.any() or ar.maybe_undefined.any())


class SaturatedLoop:
    r"""A closed loop ``g(x) = F(x, κ(x))`` under a one-layer saturated controller
    :math:`\kappa(x) = c \odot \tanh(Wx + b)`, split for :class:`TaylorDecrease`.

    Its Jacobian is :math:`J(x) = F_x(x, u) + F_u(x, u)\,\mathrm{diag}(c)\,
    \mathrm{diag}(\sigma(z))\,W` at ``u = κ(x)``, with the pre-activations ``z = Wx + b``
    and the slopes :math:`\sigma(z) = 1 - \tanh^2 z \in (0, 1]`. The entrywise enclosure of
    ``J`` on a box treats every entry as free, although whole rows move with the ``m`` slopes
    and inputs, and it bounds ``z`` on the box's corners, far outside the ellipsoid the test
    is about (a planar quadrotor: ``|W_i x|`` up to 0.58 on the box, 0.14 on the ellipsoid).
    :meth:`enclose` keeps the slopes and the inputs as parameters and bounds ``z`` on the
    ellipsoid :math:`\{x^\top P x \le c\}`, where :math:`|W_i x| \le \rho_i = \sqrt{c\,W_i
    P^{-1} W_i^\top}` exactly (:meth:`radii`), so ``u`` lies in ``c ⊙ tanh(b ± ρ)``.

    With ``u₀`` the centre of those inputs and ``δ = u − u₀``, the mean value in ``u`` gives
    :math:`F_x(x, u) = F_x(x, u_0) + \sum_i \delta_i G_i` with :math:`G_i` in the hull of
    :math:`\partial F_x/\partial u_i` on the box. So the mean-value Jacobian
    :math:`\bar J(y) = \int_0^1 J(sy)\,ds` satisfies

    .. math:: \bar J \in \Big\{C_0 + \sum_i d_i\,\hat G_i + U\,\mathrm{diag}(c \odot s)\,W
              \Big\} + [-R, R], \quad R = R_0 + \sum_i r_i\,R_{G_i} + R_U,

    ``C₀ ± R₀`` the sliced enclosure of ``F_x(·, u₀)``, ``Ĝ_i ± R_{G_i}`` that of
    ``∂F_x/∂u_i`` on the box of ``(x, u)``, ``r_i = max|δ_i|``, ``U`` (floats) about the
    centre of ``F_u`` there and ``R_U ≥ |(F_u − U)\,\mathrm{diag}(c ⊙ σ)\,W|`` entrywise (the
    interval value of that product's graph, hull over the pieces of the box, with ``σ`` in
    its range: the inputs' terms cancel within a piece as they do in ``J``), and ``(d, s)``
    in the box of the averaged ``δ̄`` and ``σ̄`` (16 nested slices, as
    :func:`sliced_enclosure`; only the inputs that ``F_x`` depends on get a ``d_i``).
    ``yᵀ(P\bar J + \bar J^\top P)y`` is affine in ``(d, s)``, so its largest value is at a
    corner of that box: the decrease is proved when it is proved at every corner. Each box
    of ``(x, u)`` is cut along the axes the derivatives vary most on
    (:data:`SATURATED_PIECES` pieces, hull of their enclosures). All bounds are
    outward-rounded intervals of CasADi graphs of ``F`` and of the controller's own weights;
    every product is exact in rationals. A graph of ``F`` with non-smooth or partial
    operations (the cartpole's division) is used on a box of ``(x, u)`` only where a checked
    walk of ``F`` and its derivatives clears them (:func:`_cleared`); elsewhere
    :meth:`enclose` returns ``None``.
    """

    def __init__(self, x, F_of, controller):
        self.why = ""
        layer = controller.layers[0] if isinstance(controller, Network) and \
            len(controller.layers) == 1 else None
        if layer is None or layer.activation != "tanh" or controller.head is not None:
            self.why = "the controller is not one tanh layer c ⊙ tanh(Wx + b)"
            return
        m, n = layer.weight.shape
        sym = ca.SX if isinstance(x, ca.SX) else ca.MX
        c = np.broadcast_to(np.asarray(controller.output_scale, dtype=float), (m,))
        self.c = [Fraction(v) for v in c]
        self.W = [[Fraction(v) for v in row] for row in layer.weight]
        self.b = [Fraction(v) for v in layer.bias]
        self.n, self.m = n, m
        v = sym.sym("v", n + m)             # (x, u)
        Sx, Su = sym.sym("Sx", n, n), sym.sym("Su", m, m)
        z = sym.sym("z", m)
        try:
            F = F_of(v[:n], v[n:])
            fx = ca.densify(ca.jtimes(F, v, ca.vertcat(Sx, ca.DM.zeros(m, n))))
            self.hx = ca.Function("sat_Fx", [v, Sx], [fx])
            self.hu = ca.Function("sat_Fu", [v, Su], [ca.densify(
                ca.jtimes(F, v, ca.vertcat(ca.DM.zeros(n, m), Su)))])
            # column i: vec(∂F_x/∂u_i), both derivatives along symbolic seeds
            self.hxu = ca.Function("sat_Fxu", [v, Sx, Su], [ca.densify(
                ca.jtimes(ca.vec(fx), v, ca.vertcat(ca.DM.zeros(n, m), Su)))])
            self.sigma = ca.Function("sat_sigma", [z], [1 - ca.tanh(z) ** 2])
            self.kappa = ca.Function("sat_u", [z], [ca.DM(c) * ca.tanh(z)])
            # the remainder of F_u about a matrix U0, times the slopes' gains
            sv, U0 = sym.sym("s", m), sym.sym("U0", n, m)
            fu = ca.jtimes(F, v, ca.vertcat(ca.DM.zeros(n, m), Su))
            scaled = ca.horzcat(*[(fu[:, i] - U0[:, i]) * (float(c[i]) * sv[i])
                                  for i in range(m)])
            self.hq = ca.Function("sat_Fu_rest", [v, Su, sv, U0], [ca.densify(ca.mtimes(
                scaled, ca.DM(layer.weight)))])
            # non-smooth or partial operations of F: usable on a box of (x, u) that a checked
            # walk of F and its derivatives clears (:func:`_cleared`, in :meth:`enclose`)
            self._checked = None
            if any(compile_function(f).checked for f in (
                    ca.Function("sat_F", [v], [F]), self.hx, self.hu, self.hxu, self.hq)):
                self._checked = compile_function(ca.Function(
                    "sat_all", [v, Sx, Su], [F, fx, fu, self.hxu(v, Sx, Su)]))
            # the inputs F_x depends on
            sp = ca.jacobian(ca.vec(fx), v).sparsity()
            self.affine = [i for i in range(m) if sp.colind()[n + i + 1] > sp.colind()[n + i]]
            outs = ca.vertcat(ca.vec(fx), ca.vec(fu), ca.vec(self.hxu(v, Sx, Su)))
            self._dep = ca.Function("sat_dep", [v, Sx, Su], [ca.jacobian(outs, v)])
        except (RuntimeError, UnsupportedOperationError) as err:
            self.why = f"no graph to enclose ({str(err).splitlines()[0][:80]})"
            return
        if m + len(self.affine) > SATURATED_MAX_PARAMETERS:
            self.why = (f"{m + len(self.affine)} slope and input parameters (at most "
                        f"{SATURATED_MAX_PARAMETERS})")

    def _split(self, lo: np.ndarray, hi: np.ndarray):
        """``(axes, k)`` for :func:`sliced_enclosure`: the (at most 3) axes of ``(x, u)``
        along which the derivatives vary most over the box (their sensitivity at its centre
        times its width), each cut into ``k`` pieces; ``None``: none varies. Only tightness
        depends on the choice: the pieces cover the box whatever the axes."""
        n, m = self.n, self.m
        J = np.abs(np.asarray(self._dep(0.5 * (lo + hi), np.eye(n), np.eye(m)), dtype=float))
        score = J.sum(axis=0) * (hi - lo)
        axes = sorted(int(j) for j in np.argsort(-score, kind="stable")[:3] if score[j] > 0)
        k = int(math.floor(SATURATED_PIECES ** (1.0 / len(axes)) + 1e-9)) if axes else 1
        return (axes, k) if k > 1 else None

    def radii(self, P: list[list[Fraction]], level) -> list[Fraction]:
        r"""Rational :math:`\rho_i \ge \sqrt{c\,W_i P^{-1} W_i^\top}`: ``|W_i x| ≤ ρ_i`` on
        :math:`\{x^\top P x \le c\}` (``c`` = ``level``, ``P`` positive definite)."""
        Pinv = inverse(P)
        c = rational(level)
        n = self.n
        return [Fraction(_sqrt_up(c * sum(w[a] * Pinv[a][b] * w[b] for a in range(n)
                                          for b in range(n) if w[a] and w[b])))
                for w in self.W]

    def _ranges(self, H: ca.Function, rho: list[Fraction], ts: list[Fraction]):
        """Rational ``(lo, hi)`` of ``H(z)`` on ``z ∈ b ± tρ`` for each ``t`` of ``ts``
        (outward-rounded, widened by the fold allowance); ``None`` when not finite."""
        Interval, ia = interval_arithmetic()
        lo = np.array([[float_down(bi - t * r) for bi, r in zip(self.b, rho)] for t in ts])
        hi = np.array([[float_up(bi + t * r) for bi, r in zip(self.b, rho)] for t in ts])
        res = evaluate(H, [Interval(lo, hi)], ia)[0]
        out_lo = np.asarray(res.lo, dtype=float).reshape(len(ts), -1)
        out_hi = np.asarray(res.hi, dtype=float).reshape(len(ts), -1)
        if not (np.all(np.isfinite(out_lo)) and np.all(np.isfinite(out_hi))):
            return None
        return ([[Fraction(v) - abs(Fraction(v)) * _FOLD for v in row] for row in out_lo],
                [[Fraction(v) + abs(Fraction(v)) * _FOLD for v in row] for row in out_hi])

    def _rest(self, whole, split, U, s_lo, s_hi):
        """Rational ``R_U ≥ |(F_u − U) diag(c ⊙ σ) W|`` entrywise, ``F_u`` on the box
        ``whole`` of ``(x, u)`` and ``σ ∈ [s_lo, s_hi]``: the hull over the box's pieces of
        the graph's interval values (within a piece the rows of ``F_u − U`` are nearly
        constant, so the inputs' terms cancel as they do in ``J``)."""
        Interval, ia = interval_arithmetic()
        lo, hi = whole
        pieces = 1
        if split is not None:
            lo, hi, pieces = split_boxes(lo, hi, *split)
        n, m = self.n, self.m
        eye = np.tile(np.eye(m).ravel(order="F"), (pieces, 1))
        sl = np.tile([float_down(v) for v in s_lo], (pieces, 1))
        sh = np.tile([float_up(v) for v in s_hi], (pieces, 1))
        u0 = np.tile(np.array([[float(v) for v in row] for row in U]).ravel(order="F"),
                     (pieces, 1))
        res = evaluate(self.hq, [Interval(lo, hi), Interval(eye, eye.copy()),
                                 Interval(sl, sh), Interval(u0, u0.copy())], ia)[0]
        mag = np.maximum(np.abs(np.asarray(res.lo, dtype=float)),
                         np.abs(np.asarray(res.hi, dtype=float))).reshape(-1, n * n)
        if not np.all(np.isfinite(mag)):
            return None
        top = mag.max(axis=0).reshape(n, n).T         # column-major entries
        return [[Fraction(top[a, b]) * (1 + _FOLD) for b in range(n)] for a in range(n)]

    def enclose(self, Y: np.ndarray, rho: list[Fraction], *, pointwise: bool = False):
        """``(corners, R)``: the exact rational matrices ``C₀ + Σ d_i Ĝ_i + U diag(c ⊙ s) W``
        at the corners ``(d, s)`` of the parameter box and the radius ``R``, for ``y`` in
        the box ``Y`` (containing 0) with ``|W_i y| ≤ ρ_i``; ``None`` when an enclosure is
        not finite. The mean-value Jacobian ``J̄(y)``, or with ``pointwise`` ``J(y)``
        itself (one slice: the whole set)."""
        K = 1 if pointwise else TAYLOR_SLICES
        ts = [Fraction(k + 1, K) for k in range(K)]
        sliced = [Fraction(1, K)] * K
        us, ss = self._ranges(self.kappa, rho, ts), self._ranges(self.sigma, rho, ts)
        if us is None or ss is None:
            return None
        (u_lo, u_hi), (s_lo, s_hi) = us, ss
        n, m = self.n, self.m
        u0 = [(u_lo[-1][i] + u_hi[-1][i]) / 2 for i in range(m)]
        y_lo = [[float_down(t * rational(v)) for v in Y[:, 0]] for t in ts]
        y_hi = [[float_up(t * rational(v)) for v in Y[:, 1]] for t in ts]
        at_u0 = (np.array([r + [float_down(w) for w in u0] for r in y_lo]),
                 np.array([r + [float_up(w) for w in u0] for r in y_hi]))
        whole = (np.array([y_lo[-1] + [float_down(w) for w in u_lo[-1]]]),
                 np.array([y_hi[-1] + [float_up(w) for w in u_hi[-1]]]))
        if self._checked is not None and not _cleared(self._checked, whole[0][0], whole[1][0]):
            return None         # every box below lies in ``whole``
        split = self._split(whole[0][0], whole[1][0])
        e0 = sliced_enclosure(self.hx, None, sliced, boxes=at_u0, split=split)
        eu = sliced_enclosure(self.hu, None, [Fraction(1)], boxes=whole, split=split)
        eg = sliced_enclosure(self.hxu, None, [Fraction(1)], boxes=whole, split=split) \
            if self.affine else ([], [])
        if e0 is None or eu is None or eg is None:
            return None
        (C0, R0), (U, _), (G, RG) = e0, eu, eg
        # U rounded to floats (any U works): the graph of the remainder reads it exactly
        U = [[Fraction(float(v)) for v in row] for row in U]
        RU = self._rest(whole, split, U, [s_lo[-1][i] for i in range(m)],
                        [s_hi[-1][i] for i in range(m)])
        if RU is None:
            return None
        # the averaged parameters' boxes: δ̄_i = ū_i − u0_i and σ̄_i
        d_lo = [sum(u_lo[k][i] for k in range(K)) / K - u0[i] for i in range(m)]
        d_hi = [sum(u_hi[k][i] for k in range(K)) / K - u0[i] for i in range(m)]
        r = [max(u0[i] - u_lo[-1][i], u_hi[-1][i] - u0[i]) for i in range(m)]
        smin = [sum(s_lo[k][i] for k in range(K)) / K for i in range(m)]
        smax = [sum(s_hi[k][i] for k in range(K)) / K for i in range(m)]
        # G (n²×m): row a + n·b of column i is (∂F_x/∂u_i)[a][b] (column-major vec)
        R = [[R0[a][b] + RU[a][b] + sum(r[i] * RG[a + n * b][i] for i in self.affine)
              for b in range(n)] for a in range(n)]
        corners = []
        for pick in itertools.product((0, 1), repeat=m + len(self.affine)):
            s = [self.c[i] * (smax[i] if pick[i] else smin[i]) for i in range(m)]
            d = {i: (d_hi[i] if pick[m + j] else d_lo[i]) for j, i in enumerate(self.affine)}
            Us = [[U[a][i] * s[i] for i in range(m)] for a in range(n)]
            corners.append([[C0[a][b] + sum(Us[a][i] * self.W[i][b] for i in range(m))
                             + sum(d[i] * G[a + n * b][i] for i in self.affine)
                             for b in range(n)] for a in range(n)])
        return corners, R


def _sqrt_up(q: Fraction) -> float:
    """A float ``s ≥ √q`` (``q ≥ 0`` rational), the nearest such float or one above it."""
    s = math.sqrt(float_up(q))
    while Fraction(s) ** 2 < q:
        s = math.nextafter(s, math.inf)
    return s


class TaylorDecrease:
    r"""Condition (a) for a quadratic ``V = xᵀPx``, decided on a whole box at once.

    ``g`` is the closed loop's right-hand side (a graph of the true f with the controller).
    With ``J`` its Jacobian and ``Y`` a box containing 0 (so ``sy ∈ Y`` for ``s ∈ [0, 1]``),
    the mean-value form :math:`g(y) = g(0) + \bar J(y)\,y`, :math:`\bar J(y) = \int_0^1
    J(sy)\,ds`, gives

    .. math:: \dot V(y) = 2 y^\top P g(0) + y^\top (P \bar J + \bar J^\top P)\, y .

    :meth:`check` encloses ``J`` on 16 nested slices ``s_k Y`` by outward-rounded interval
    arithmetic (each entry also widened by CasADi's constant-folding allowance of a
    derivative graph), so :math:`\bar J \in [C - R, C + R]` entrywise with rational ``C``,
    ``R``; then :math:`y^\top(P\bar J + \bar J^\top P)y \le y^\top N y` with the exact
    rational :math:`N = PC + C^\top P + \mathrm{diag}((|P|R + R^\top|P|)\mathbf 1)`.
    ``g(0)`` is evaluated at the point 0 in exact rational arithmetic
    (:class:`~nlyap_opt.kernel.walker.ExactPointArithmetic`; no structural or float zero is
    trusted), else enclosed by intervals there: with :math:`b \ge \|P g(0)\|` and ``−N − λI
    ≻ 0`` (exact ``LDLᵀ``) for :math:`\lambda = 2b/\varepsilon`, :math:`\dot V(y) <
    \|y\|(2b - \lambda\|y\|) \le 0` for every ``y ∈ Y`` with ``‖y‖ ≥ ε`` (for ``g(0) = 0``
    exactly, ``b = 0`` and every ``y ≠ 0``).
    ``Y`` is the box that holds :math:`\{x^\top P x \le c\} \cap D`, so this proves condition
    (a) on the whole sublevel set with no bisection. ``P`` enters as the exact rational
    matrix of the stored network (:func:`quadratic_form`), so ``V̇`` is the real derivative
    of the real ``V``. A linear loop has a constant ``J`` (``R`` only the folding allowance):
    the test is then exact up to that allowance at every level. ``g`` must be continuously
    differentiable on ``Y``: a graph with non-smooth or partial operations is used only on
    a ``Y`` where a checked interval walk of ``g`` and ``J`` clears each of them
    (:meth:`_smooth_on`), and :meth:`check` returns ``None`` elsewhere, as it does where the
    enclosure is not tight enough.

    **Learned dynamics** (``g`` the closed loop with φ, ``‖f − φ‖ ≤ η``): the property the
    certificate proves is ``∇V·g + margin < 0`` (``margin``: the global ``M·η``) or
    ``∇V·g + η·sqrt(‖∇_L V‖² + s²) < 0`` (``eta``, ``smoothing`` ``s`` and the learned
    ``components`` ``L``: :func:`nlyap_opt.kernel.symbolic.robust_lie`). With
    ``∇_L V = 2 P_L y`` (the rows ``L`` of ``P``) and ``sqrt(q + s²) ≤ sqrt(q) + s``, the
    property is at most :math:`y^\top N y + 2b\|y\| + 2\eta\|P_L y\| + m` with ``m =
    margin + η s``. For ``‖y‖ ≥ ε`` each term is at most a quadratic form:
    :math:`2b\|y\| + m \le (2b/\varepsilon + m/\varepsilon^2)\|y\|^2` and, for any
    ``t > 0``, :math:`2\eta\|P_L y\| \le 2\eta\|P_L y\|\,\|y\|/\varepsilon \le
    (\eta/\varepsilon)(\|y\|^2/t + t\|P_L y\|^2)`. So the property holds on ``‖y‖ ≥ ε``
    when

    .. math:: -N - \Big(\frac{2b}{\varepsilon} + \frac{m}{\varepsilon^2} +
              \frac{\eta}{\varepsilon t}\Big) I - \frac{\eta t}{\varepsilon}
              P_L^\top P_L \succ 0

    for a ``t`` chosen in floats (:meth:`_weights`: from ``t₀ = 1/‖P_L‖₂``, where the terms
    are at most about ``2η‖P_L‖₂‖y‖²/ε``, below the scalar bound ``2η‖P_L‖_F‖y‖²/ε``, the
    ``t`` that maximises the least eigenvalue); the test at that ``t`` is exact. A ``t``
    away from ``t₀`` puts the margin where ``P_L`` is large, which is where ``−N`` is
    large in a stiff loop.

    **A saturated controller** (``saturated``, a :class:`SaturatedLoop`): where the entrywise
    enclosure of ``J`` fails, the test is made at each corner of the controller's parameter
    box (:meth:`SaturatedLoop.enclose`, on the ellipsoid's own input range), with the
    remainder bounded row by row (:meth:`_bounded_proves`), and holds when it holds at
    every corner.
    """

    def __init__(self, x, g, P: list[list[Fraction]], *, eta: float = 0.0,
                 smoothing: float = 0.0, components=None, margin: float = 0.0,
                 saturated: SaturatedLoop | None = None):
        self.P = P
        self.why = ""
        self._J = None
        self._sat = saturated if saturated is not None and not saturated.why else None
        n0 = len(P)
        rows = range(n0) if components is None else list(components)
        self._eta, self._margin = rational(eta), rational(margin)
        self._s = rational(smoothing)
        self._pl = Fraction(_sqrt_up(sum(P[i][j] ** 2 for i in rows for j in range(n0)))) \
            if self._eta > 0 else Fraction(0)
        # P_Lᵀ P_L, exactly (the matrix form of the robust margin), and the first weight
        # t₀ = 1/‖P_L‖₂ (in floats: any t > 0 is sound)
        self._plpl = [[sum(P[i][a] * P[i][b] for i in rows) for b in range(n0)]
                      for a in range(n0)] if self._eta > 0 else None
        self._t0 = Fraction(0)
        if self._eta > 0 and self._pl > 0:
            norm = float(np.linalg.norm(np.array([[float(P[i][j]) for j in range(n0)]
                                                  for i in rows]), 2))
            self._t0 = Fraction(1.0 / norm) if 0 < norm < math.inf else 1 / self._pl
        n = x.numel()
        # the graph as given (an MX closed loop is not expanded: expanding folds its
        # constant parts, e.g. C·tanh(b) − u_eq of a controller, in floats)
        try:
            self._g = ca.Function("taylor_g", [x], [g])
            J = seeded_jacobian("taylor_J", g, x)
            S = (ca.SX if isinstance(x, ca.SX) else ca.MX).sym("S", n, n)
            prog = compile_function(ca.Function("taylor_gJ", [x, S], [g, J(x, S)]))
        except (RuntimeError, UnsupportedOperationError) as err:
            # a callback (black box), an operation the walker does not support
            self.why = f"the closed loop has no graph to enclose ({str(err).splitlines()[0][:80]})"
            return
        # non-smooth or partial operations: usable on a box where a checked walk proves every
        # one of them away from its kink/jump set and inside its domain (:meth:`_smooth_on`)
        self._checked = prog if prog.checked else None
        try:
            self._Pinv_diag = inverse_diagonal(P)
        except ZeroDivisionError:
            self.why = "P is not positive definite"
            return
        self._J = J

    def applies(self, box) -> bool:
        """Whether the test can decide anything on sets within ``box`` (a finite box, e.g.
        the domain's bounding box): the closed loop has a graph, ``P`` is positive definite,
        and :meth:`_smooth_on` clears the box (a sublevel set's box within it is then cleared
        too: a checked walk's enclosure of a sub-box lies in the box's)."""
        return not self.why and self._smooth_on(np.asarray(box, dtype=float))

    def _smooth_on(self, Y: np.ndarray) -> bool:
        """Whether ``g`` is continuously differentiable on the box ``Y`` with Jacobian ``J``:
        always for a graph of smooth total operations, else where :func:`_cleared` clears
        the graph of ``(g, J)`` on ``Y``. Every set the test encloses lies in ``Y``."""
        return self._checked is None or _cleared(self._checked, Y[:, 0], Y[:, 1])

    def box(self, level: float, domain_box: np.ndarray) -> np.ndarray:
        """A box that holds :math:`\\{x^\\top P x \\le c\\} \\cap D`: the ellipsoid's bounding
        box (half-widths :math:`\\sqrt{c\\,(P^{-1})_{kk}}`, rounded up) within ``D``'s."""
        c = rational(level)
        h = np.array([_sqrt_up(c * d) for d in self._Pinv_diag])
        b = np.asarray(domain_box, dtype=float)
        return np.column_stack([np.maximum(-h, b[:, 0]), np.minimum(h, b[:, 1])])

    def check(self, level: float, domain_box: np.ndarray,
              inner: float = 0.0) -> VerificationResult | None:
        """``verified`` (backend ``"taylor"``) when the test proves ``V̇ < 0`` (with learned
        dynamics: the robust property) on the
        sublevel set ``V ≤ level`` within ``D`` outside the ball of radius ``inner``, else
        ``None``: the test decides nothing else (no counterexample comes from it)."""
        if self._J is None or not level > 0:
            return None
        t0 = time.perf_counter()
        Y = self.box(level, domain_box)
        if not np.all((Y[:, 0] <= 0) & (Y[:, 1] >= 0)) or not self._smooth_on(Y):
            return None
        b = _origin_offset(self._g, self.P)
        if b is None:
            return None
        m = self._margin + self._eta * self._s
        robust = self._eta > 0 and self._pl > 0
        if (b > 0 or m > 0 or robust) and not inner > 0:
            return None
        eps = rational(inner) if inner > 0 else None
        base = (2 * b * eps + m) / (eps * eps) if (b > 0 or m > 0) else Fraction(0)
        CR = sliced_enclosure(self._J, Y, [Fraction(1, TAYLOR_SLICES)] * TAYLOR_SLICES)
        if CR is not None and self._proves([mean_value_form(self.P, *CR)], base, eps):
            return VerificationResult(QueryStatus.VERIFIED, seconds=time.perf_counter() - t0,
                                      backend="taylor")
        enc = self._sat.enclose(Y, self._sat.radii(self.P, level)) \
            if self._sat is not None else None
        d = [max(-rational(lo), rational(hi)) for lo, hi in Y]
        if enc is not None and all(w > 0 for w in d) and self._bounded_proves(
                enc[0], enc[1], d, base, eps):
            return VerificationResult(QueryStatus.VERIFIED, seconds=time.perf_counter() - t0,
                                      backend="taylor")
        return None

    def _bounded_proves(self, corners, R, d, base: Fraction, eps: Fraction | None,
                        Ns: list | None = None) -> bool:
        r"""The test with the Jacobian at each corner ``J_v`` plus a remainder ``|Δ| ≤ R``
        bounded row by row: for a row ``b`` of ``Δ``, ``p_b`` the column ``b`` of ``P`` and
        any ``ν_b > 0``, :math:`2(p_b^\top y)\,\Delta_b y \le (p_b^\top y)^2/\nu_b +
        \nu_b (\sum_c R_{bc}|y_c|)^2` and
        :math:`(\sum_c R_{bc}|y_c|)^2 \le s_b \sum_c (R_{bc}/d_c) y_c^2` (Cauchy–Schwarz,
        :math:`s_b = \sum_c R_{bc} d_c`), so :math:`2y^\top P\Delta y \le y^\top(\sum_b
        p_b p_b^\top/\nu_b + \sum_b \nu_b s_b\,\mathrm{diag}(R_b/d))\,y`. Unlike the
        entrywise bound, the first term lies along ``P``'s
        own columns, where ``−(PJ + JᵀP)`` is large in a stiff loop. The weights ``t`` and
        ``ν`` are chosen in floats (a coordinate search of the least eigenvalue); the test
        at them is exact."""
        n = len(self.P)
        P = self.P
        zero = [[Fraction(0)] * n for _ in range(n)]
        N0 = Ns if Ns is not None else [mean_value_form(P, J, zero) for J in corners]
        rows = [b for b in range(n) if any(R[b])]
        sb = {b: sum(R[b][c] * d[c] for c in range(n)) for b in rows}
        robust = self._eta > 0 and self._pl > 0
        try:
            t, nu = self._weights(N0, R, d, rows, sb, base, eps, robust)
        except (OverflowError, ValueError, ZeroDivisionError, np.linalg.LinAlgError):
            # numbers beyond floats: the starting weights (any positive ones are sound)
            t = self._t0 if robust else Fraction(1)
            nu = {b: Fraction(1) for b in rows}
        diag = base + (self._eta / (eps * t) if robust else 0)
        w = self._eta * t / eps if robust else Fraction(0)
        extra = [[-(w * self._plpl[i][j] if robust else 0)
                  - sum(P[i][b] * P[j][b] / nu[b] for b in rows)
                  - ((diag + sum(nu[b] * sb[b] * R[b][i] / d[i] for b in rows))
                     if i == j else 0) for j in range(n)] for i in range(n)]
        return all(positive_definite([[-N[i][j] + extra[i][j] for j in range(n)]
                                      for i in range(n)]) for N in N0)

    def _weights(self, N0, R, d, rows, sb, base, eps, robust):
        """``(t, {b: ν_b})`` for :meth:`_bounded_proves`: from ``t = 1/p`` and ``ν_b =
        ‖p_b‖/√(s_b max_c R_bc/d_c)``, factors of 2, 1, ½, ¼ (in log₂) up and down, one
        weight at a time, while the least eigenvalue of the worst corner's matrix grows
        (floats; any positive weights are sound)."""
        n = len(self.P)
        Pf = np.array([[float(v) for v in row] for row in self.P])
        Nf = [np.array([[float(v) for v in row] for row in N]) for N in N0]
        Rf = np.array([[float(v) for v in row] for row in R])
        df = np.array([float(v) for v in d])
        plpl = np.array([[float(v) for v in row] for row in self._plpl]) if robust else None
        eta, ef = float(self._eta), float(eps) if eps else 1.0
        nu0 = np.array([np.linalg.norm(Pf[:, b]) / math.sqrt(float(sb[b]) * max(
            Rf[b] / df)) for b in rows])
        nu0[~(np.isfinite(nu0) & (nu0 > 0))] = 1.0
        diagR = [np.diag(Rf[b] / df) * float(sb[b]) for b in rows]
        outer = [np.outer(Pf[:, b], Pf[:, b]) for b in rows]

        t0 = float(self._t0)

        def least(x):
            t = 2.0 ** x[0] * t0 if robust else 1.0
            nu = 2.0 ** x[1:] * nu0
            E = (float(base) + (eta / (ef * t) if robust else 0.0)) * np.eye(n)
            if robust:
                E = E + (eta * t / ef) * plpl
            for k in range(len(rows)):
                E = E + nu[k] * diagR[k] + outer[k] / nu[k]
            vals = [np.linalg.eigvalsh(-N - E)[0] for N in Nf]
            return min(vals) if all(np.isfinite(vals)) else -math.inf

        x = np.zeros(1 + len(rows))
        best = least(x)
        calls = 0
        for step in (2.0, 1.0, 0.5, 0.25):
            improved = True
            while improved and calls < 400:
                improved = False
                calls += 1
                for k in range(len(x)):
                    if k == 0 and not robust:
                        continue
                    for sgn in (1.0, -1.0):
                        y = x.copy()
                        y[k] += sgn * step
                        v = least(y)
                        if v > best:
                            x, best, improved = y, v, True
                            break
        t = Fraction(2.0 ** x[0]) * self._t0 if robust else Fraction(1)
        nu = 2.0 ** x[1:] * nu0
        nu[~(np.isfinite(nu) & (nu > 0))] = 1.0
        return t, {b: Fraction(float(nu[k])) for k, b in enumerate(rows)}

    def contracts(self, level: float, domain_box: np.ndarray, lam) -> bool:
        """Whether ``PJ(y) + J(y)ᵀP + λI ≺ 0`` at every point ``y`` of ``{xᵀPx ≤ level}``
        within ``domain_box`` (``λ`` = ``lam`` ≥ 0): the Jacobian form of condition (c),
        decided on the whole set. First with ``J`` enclosed entrywise on the set's box
        ``Y`` (``J(y) ∈ [C − R, C + R]`` for every ``y ∈ Y``, so
        ``zᵀ(PJ + JᵀP)z ≤ zᵀNz`` for every vector ``z``, ``N`` of :func:`mean_value_form`,
        and ``−N − λI ≻ 0`` is decided by an exact ``LDLᵀ``; tight on a small set, where
        ``J`` hardly varies); then with the controller split (:meth:`SaturatedLoop.enclose`
        with ``pointwise``, the remainder row by row, any positive weights: the claim is
        about every vector ``z``, not only about ``y``). ``False`` where it does not apply
        or does not prove it."""
        if self._J is None or not level > 0 or self._eta > 0:
            return False
        Y = self.box(level, domain_box)
        if not np.all((Y[:, 0] <= 0) & (Y[:, 1] >= 0)) or not self._smooth_on(Y):
            return False
        CR = sliced_enclosure(self._J, None, [Fraction(1)], boxes=(Y[None, :, 0], Y[None, :, 1]))
        if CR is not None and self._proves([mean_value_form(self.P, *CR)], rational(lam), None):
            return True
        if self._sat is None:
            return False
        enc = self._sat.enclose(Y, self._sat.radii(self.P, level), pointwise=True)
        d = [max(-rational(lo), rational(hi)) for lo, hi in Y]
        return enc is not None and all(w > 0 for w in d) and self._bounded_proves(
            enc[0], enc[1], d, rational(lam), None)

    def _proves(self, Ns: list, base: Fraction, eps: Fraction | None) -> bool:
        """Whether ``−N − (base + η/(εt))I − (ηt/ε)P_LᵀP_L ≻ 0`` for every ``N`` of ``Ns``
        at the weight ``t`` of :meth:`_weights` (``base`` alone without a robust margin)."""
        n = len(self.P)
        zero = [[Fraction(0)] * n for _ in range(n)]
        return self._bounded_proves(None, zero, [Fraction(1)] * n, base, eps, Ns=Ns)


#: the box scales (of the seed ellipsoid's bounding box at the inner ball's level) at which
#: :func:`sector_lyapunov_matrix` designs its matrix; the largest ellipsoid wins
SECTOR_SCALES = (1.0, 1.25, 1.6, 2.0, 2.5, 3.2)


def sector_lyapunov_matrix(saturated: SaturatedLoop, x, rhs, seed: np.ndarray, *,
                           inner: float, limit: np.ndarray, inside=None, eta: float = 0.0,
                           components=None, constant: float = 0.0) -> np.ndarray | None:
    r"""A ``P`` designed for :class:`TaylorDecrease` under a saturated controller: the
    ellipsoid ``{xᵀPx ≤ 1}`` holds ``B_ε`` (``ε`` = ``inner``) and passes the whole-set test
    with every slope and input the controller takes on it.

    From the ``seed`` matrix's ellipsoid at the level that holds ``B_ε`` (bounding box ``h₀``,
    controller ranges ``ρ₀``, :meth:`SaturatedLoop.radii`), for each scale ``s`` of
    :data:`SECTOR_SCALES` the closed loop (``rhs`` in ``x``) is enclosed on the box ``s·h₀``
    (within ``limit``, half-widths) and the ranges ``s·ρ₀``
    (:meth:`SaturatedLoop.enclose`), and
    :func:`nlyap_opt.design.control.polytopic_lyapunov_matrix` finds the largest ellipsoid
    that the test proves with those enclosures (robust margin ``eta`` on ``components`` and
    ``constant`` with learned dynamics; ``inside``: the domain's shape matrix). The largest
    over the scales is returned, ``None`` if none: only a candidate, which the exact test then
    certifies or not."""
    n = seed.shape[0]
    g0 = np.asarray(ca.Function("g", [x], [rhs])(np.zeros(n)), dtype=float).ravel()
    c0 = (1 + INNER_LEVEL_MARGIN) * np.linalg.eigvalsh(seed)[-1] * inner ** 2
    h0 = np.sqrt(c0 * np.diag(np.linalg.inv(seed)))
    Pq = quadratic_form(quadratic_lyapunov(seed))
    if Pq is None or not np.all(np.isfinite(g0)):
        return None
    rho0 = saturated.radii(Pq, c0)
    gains = [[float(v) for v in row] for row in saturated.W]
    best = None
    for scale in SECTOR_SCALES:
        h = np.minimum(scale * h0, limit)
        rho = [Fraction(scale) * r for r in rho0]
        enc = saturated.enclose(np.column_stack([-h, h]), rho)
        if enc is None:
            continue
        P = polytopic_lyapunov_matrix(
            [[[float(v) for v in row] for row in J] for J in enc[0]],
            [[float(v) for v in row] for row in enc[1]], half_widths=h, inner=inner, eta=eta,
            components=components, offset=g0, constant=constant, inside=inside,
            gains=gains, radii=[float(r) for r in rho])
        if P is not None and (best is None or np.linalg.slogdet(P)[1]
                              < np.linalg.slogdet(best)[1]):
            best = P
    return best


def _float_matrix(P: list[list[Fraction]]) -> np.ndarray:
    """The rational matrix rounded to float64 (to locate a refutation's point only)."""
    return np.array([[float(v) for v in row] for row in P])


#: With ``follow_violations``: the first step of :func:`certify_level` after an ``unknown``
#: at a level set by a followed decrease violation (that least violation is a local minimum
#: of ``V`` over the violation set; the verifier cannot separate the level from it, and the
#: 0.5 % steps of a near-tangency waste the tries there). The climb back recovers the step.
FOLLOWED_UNKNOWN_STEP = 0.135
#: With ``follow_violations``: :func:`certify_level` climbs back from a verified level by
#: bisection until the least failed level above it is within this fraction of it.
CLIMB_GAP = 0.01


@dataclass
class LevelCertificate:
    """Result of :func:`certify_level`."""

    status: str                       # "certified" or the reason it is not
    level: float
    decrease: object = None           # VerificationResult of (a)
    containment: object = None        # VerificationResult of (b)
    history: list = field(default_factory=list)
    counterexamples: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    seconds: float = 0.0


#: :func:`certify_level`'s reason when its search ended at ``least`` (the caller tells
#: such an end from the others by it)
BELOW_LEAST = "no level below"


def certify_level(x, V, lie, *, level: float, inner: float, outer=None, margin: float,
                  max_tries: int = 8, shrink: float = 1e-3, verify_options: dict | None = None,
                  log=print, domain=None, follow_violations: bool = False,
                  quadratic: list[list[Fraction]] | None = None,
                  rhs=None, robust: dict | None = None,
                  taylor_only: bool = False,
                  saturated: SaturatedLoop | None = None,
                  least: tuple[float, str] | None = None) -> LevelCertificate:
    """Prove (a) and (b) at the largest level we can reach from ``level`` downwards.

    The region is ``domain`` (a :class:`nlyap_opt.kernel.domain.Region`) or the ball
    ``‖x‖ ≤ outer``; (b) is checked on every piece of its boundary (each face of a box).
    Counterexamples lower the level to just below ``V`` at the counterexample; ``unknown``
    verdicts lower it by 0.5 %, then 1.5 %, 4.5 %, 13.5 %, 30 %, ... (an ``unknown`` is
    usually a near-tangency that a small step resolves). A search never goes to a level at
    or below :func:`inner_ball_level` (no such ``Ω_c`` holds ``B_ε``): the first step that
    would tries ``(1 +`` :data:`INNER_LEVEL_MARGIN` ``)`` times it instead, the smallest level
    that can hold the inner ball, and the search ends after that. A starting level below
    ``V`` at one of 512 seeded points of the inner sphere is not checked at all (no level up
    to it can hold the ball). Each try is one entry of
    the ``history``. Returns the certified level or why none was found.

    With ``follow_violations`` (off by default, so that existing certificates do not move):

    - a decrease counterexample is followed down by :func:`least_violation` (IPOPT from the
      counterexamples) and the level drops to just below the least ``V`` found: in 4-D and
      up the violation set is thin and the counterexamples' own ``V`` only creeps down;
    - an ``unknown`` at a level so set starts the steps at :data:`FOLLOWED_UNKNOWN_STEP`
      (13.5 %, then 30 %) instead of 0.5 %: the least violation found is a local minimum
      only, and the verifier's ``unknown`` next to it is rarely resolved by a small step;
    - once a level is verified, the tries left bisect between it and the least level above
      it that failed (``unknown``, or a counterexample: then at most the counterexample's
      ``V``) until they are within :data:`CLIMB_GAP` of each other. The certificate is the
      largest level whose (a), (b) and inner-ball checks were all verified; a bisection try
      that fails only narrows the bracket.

    ``quadratic``: the exact matrix of ``V`` when ``V = xᵀPx`` by construction
    (:func:`quadratic_form`); condition (b) (``V > c`` on ``∂D``, ``V < c`` on the inner
    sphere) is then decided exactly by :func:`quadratic_containment` and
    :func:`quadratic_inner_ball` (the verifier only for a piece of ``∂D`` they leave open).
    Each history entry records how (b) was decided (``containment_backend``). With
    ``quadratic`` and ``rhs`` (the closed loop's right-hand side ``g`` with ``lie = ∇V·g``,
    or with learned dynamics its robust form: ``robust`` holds the ``eta``, ``smoothing`` and
    learned ``components`` of :func:`nlyap_opt.kernel.symbolic.robust_lie`, and ``margin``
    the global one) condition (a) is first tried by :class:`TaylorDecrease` on
    the sublevel set's bounding box (no bisection; exact for a linear closed loop), and the verifier
    decides where that test does not apply or does not prove it (``decrease_backend``:
    ``taylor`` or the verifier's). ``taylor_only``: where that test does not prove (a) the
    level is ``unknown`` and the search steps down, without the verifier's bisection (a
    cheap whole-set search; the caller falls back to a smaller set).

    ``least = (c_min, name)``: no level below ``c_min`` can give a certificate larger than
    ``name``'s (the caller's volume bound); the search stops instead of stepping below it.
    """

    t0 = time.perf_counter()
    opts = dict(verify_options or {})
    Vf = _fun(x, V)
    r2 = ca.sumsqr(x)
    n = x.numel()
    D = _domain(domain, outer, n)
    box = D.bounding_box()
    pieces = D.boundary_pieces(x)
    c = level * (1.0 - shrink)
    drop = 0.005
    hist, cexs = [], []
    floor = {}          # max V on the inner sphere, computed when a step first needs it
    best = None         # (level, res_a, res_b) of the largest level verified so far
    above = math.inf    # the least level above ``best`` that failed (or a violation's V)
    followed = False    # ``c`` was set by a followed decrease violation
    # (a) for a quadratic V and known dynamics: Taylor's formula on the sublevel set's box
    taylor = TaylorDecrease(x, rhs, quadratic, margin=margin, saturated=saturated,
                            **(robust or {})) \
        if quadratic is not None and rhs is not None else None

    def lower(c_old, c_new):
        """The next level: ``c_new``, the inner ball's level instead, or ``None`` (stop)."""
        c_next = _lower(c_old, c_new)
        if least is not None and c_next is not None and 0 < c_next < least[0]:
            floor["least"] = True
            log(f"    level {c_next:.6g} cannot beat the {least[1]} (no level below "
                f"{least[0]:.6g} can): the search ends")
            return None
        return c_next

    def _lower(c_old, c_new):
        if inner <= 0 or not c_new > 0:
            return c_new
        if "m" not in floor:
            floor["m"] = inner_ball_level(x, V, inner)
        m = floor["m"]
        if c_new > m:
            return c_new
        target = m * (1.0 + INNER_LEVEL_MARGIN)
        if target < c_old:
            log(f"    level {c_new:.6g} would not hold the inner ball (max V = {m:.6g} on "
                f"‖x‖ = {inner:g}): trying {target:.6g}, the smallest that can")
            return target
        return None

    def check(c):
        """(b), then (a) if (b) holds, then ``V < c`` on the inner sphere if (a) holds too:
        ``(res_b, res_a, res_d)``, the ones not run ``None``; one history entry."""
        res_b, how = None, []
        for pbox, cons, label in pieces:   # V > c on each piece of the boundary
            r = None if quadratic is None else quadratic_containment(quadratic, c, D, pbox)
            if r is None:
                prob_b = VerificationProblem(x, pbox, [g for g, _ in cons], [c - V],
                                             [nm for _, nm in cons], [f"V>level on {label}"])
                r = parallel.check(prob_b, **opts)
            how.append(r.backend)
            if res_b is not None:
                r.seconds += res_b.seconds
                r.boxes += res_b.boxes
            res_b = r
            if r.status != "verified":
                break
        res_a = None
        if res_b.status == "verified":
            prob_a = res_a = None
            if taylor is not None and not taylor_only and parallel.proving_active():
                # a re-check with a proof: a decrease check it holds the tree of was
                # bisected when it was recorded (the closed form did not decide it then),
                # so its leaves come first; if they do not all hold, as without a proof
                prob_a = lyapunov_problem(x, V, lie, inner=inner, domain=D, level=c,
                                          margin=margin, box=box, check_positive=False)
                res_a = parallel.from_proof(prob_a, **opts)
            if res_a is None and taylor is not None:
                res_a = taylor.check(c, box, inner)
            if res_a is None and taylor_only:   # undecided here: no bisection asked for
                res_a = VerificationResult(QueryStatus.UNKNOWN, backend="taylor")
            if res_a is None:
                if prob_a is None:
                    prob_a = lyapunov_problem(x, V, lie, inner=inner, domain=D, level=c,
                                              margin=margin, box=box, check_positive=False)
                res_a = parallel.check(prob_a, **opts)
        hist.append({"level": c, "containment": res_b.status,
                     "decrease": None if res_a is None else res_a.status,
                     "seconds": res_b.seconds + (res_a.seconds if res_a else 0.0),
                     "boxes": res_b.boxes + (res_a.boxes if res_a else 0),
                     "containment_backend": "+".join(sorted(set(how)))})
        if res_a is not None:
            hist[-1]["decrease_backend"] = res_a.backend
        log(f"    level {c:.6g}: containment {res_b.status}, decrease "
            f"{hist[-1]['decrease']}")
        res_d = None
        if res_a is not None and res_a.status == "verified":
            # B_ε ⊆ Ω_c: V < c on the inner sphere (else Ω_c may lie inside B_ε: a trivial
            # certificate resting on condition (c) alone)
            if quadratic is not None:
                res_d = quadratic_inner_ball(quadratic, c, inner)
            else:
                prob_d = VerificationProblem(x, box, [r2 - inner**2, inner**2 - r2], [V - c],
                                             ["inner", "sphere"], ["V<level on inner sphere"])
                res_d = parallel.check(prob_d, **opts)
            hist[-1]["contains_inner_ball"] = res_d.status
        return res_b, res_a, res_d

    def result():
        cx = np.array(cexs).reshape(-1, n)
        lv, res_a, res_b = best
        return LevelCertificate("certified", lv, res_a, res_b, hist, cx,
                                time.perf_counter() - t0)

    if inner > 0 and c > 0:
        # V at seeded points of the inner sphere: a level below one of them cannot hold
        # B_ε (condition (b) would refute it after (a) and (b) had been checked: minutes in
        # 6-D), and every lower level neither, so nothing is checked
        d = np.random.default_rng(0).standard_normal((max(512, 2 * n), n))
        d[:n], d[n:2 * n] = np.eye(n), -np.eye(n)
        seen = float(np.max(evaluate(Vf, [inner * d / np.linalg.norm(d, axis=1,
                                                                      keepdims=True)])[0]))
        if c < seen * (1.0 - 1e-9):
            floor["m"], floor["sampled"] = seen, True
            log(f"    level {c:.6g} cannot hold the inner ball (V = {seen:.6g} at a point of "
                f"‖x‖ = {inner:g}): not checked")
            c = None

    for k in range(max_tries):
        if c is None or not c > 0:
            break
        res_b, res_a, res_d = check(c)
        last_try = k + 1 == max_tries
        if res_d is not None and res_d.status == "verified":
            best = (c, res_a, res_b)
            if not follow_violations or last_try or not above > c * (1.0 + CLIMB_GAP) \
                    or not math.isfinite(above):
                return result()
            c = 0.5 * (c + above)           # climb back: bisect towards the failed level
            log(f"    level {best[0]:.6g} verified: bisecting up to {c:.6g}")
            continue
        if res_d is not None and best is None:   # (a), (b) hold, Ω_c misses the inner ball
            return LevelCertificate(f"level {c:.4g} does not contain the inner ball "
                                    f"({res_d.status})", c, res_a, res_b, hist,
                                    np.array(cexs).reshape(-1, n), time.perf_counter() - t0)
        bad = res_b if res_b.status != "verified" else res_a if res_d is None else res_d
        vmin = math.inf
        if bad.status == "counterexample" and bad is not res_d:
            pts = np.array([ce.point for ce in bad.counterexamples])
            cexs += list(pts)
            vmin = float(np.min(evaluate(Vf, [pts])[0]))
        if best is not None:                # a failed bisection try: narrow the bracket
            above = min(above, c, vmin)
            if last_try or not above > best[0] * (1.0 + CLIMB_GAP):
                return result()
            c = 0.5 * (best[0] + above)
            log(f"    bisecting up to {c:.6g}")
            continue
        above = min(above, c, vmin)
        if last_try:                        # no try left: no next level to look for
            break
        if bad.status == "counterexample" and bad is not res_d:
            followed = False
            if follow_violations and bad is res_a:   # the least V of a violation nearby
                found = least_violation(x, V, lie, pts[:4], inner=inner, domain=D,
                                        margin=margin, tol=1e-7)
                if found is not None:   # a level to try, not a counterexample (tol)
                    followed = found[0] < vmin
                    vmin = min(vmin, found[0])
            c = lower(c, min(vmin * (1.0 - 1e-3), c * 0.995))
        else:
            if follow_violations and followed:
                drop = max(drop, FOLLOWED_UNKNOWN_STEP)
            followed = False
            c = lower(c, c * (1.0 - drop))
            drop = min(3.0 * drop, 0.3)
    if best is not None:
        return result()
    why = "no level certified"
    if c is None and floor.get("least"):
        why += (f" (none of the levels checked held, and {BELOW_LEAST} {least[0]:.6g} "
                f"could beat the {least[1]})")
    elif c is None and floor.get("sampled"):
        why += (f" (the candidate level {level * (1.0 - shrink):.6g} is below V = "
                f"{floor['m']:.6g} at a point of ‖x‖ = {inner:g}: no level up to it holds "
                "the inner ball; none was checked)")
    elif c is None:
        why += (f" (none above the inner ball's level {floor['m']:.6g}, max V on ‖x‖ = "
                f"{inner:g}, holds)")
    return LevelCertificate(why, 0.0, None, None, hist,
                            np.array(cexs).reshape(-1, n), time.perf_counter() - t0)


def _leading_minors(S):
    """Leading principal minors of a small symbolic matrix (cofactor expansion)."""

    def det(M):
        k = M.shape[0]
        if k == 1:
            return M[0, 0]
        if k == 2:
            return M[0, 0] * M[1, 1] - M[0, 1] * M[1, 0]
        total = 0
        for j in range(k):
            minor = ca.horzcat(M[1:, :j], M[1:, j + 1:])
            total = total + (-1) ** j * M[0, j] * det(minor)
        return total

    return [det(S[:k, :k]) for k in range(1, S.shape[0] + 1)]


def certify_inner_ellipse(system, controller, inner: float, *, P=None,
                          form: str | InnerForm | None = None,
                          verify_options: dict | None = None) -> dict:
    r"""Condition (c) for the true closed loop: ``E = {xᵀPx ≤ c_q} ⊇ B_ε`` is a certified
    quadratic Lyapunov sublevel set (``P J(y) + J(y)ᵀ P ≺ 0`` on ``E``, or ``V̇_q < 0`` on a
    shell of ``E`` and that on a small ellipse inside (:func:`_inner_ellipse`), or
    :func:`certify_inner_blowup` where the linearisation has a centre).

    Without ``P``, the candidates of :func:`nlyap_opt.design.control.ellipse_candidates` for the
    closed-loop linearisation ``A_cl`` are tried in turn; the first one that certifies is
    returned. With ``P`` and ``form`` (``InnerEllipse.form`` of a saved certificate:
    ``"minors"``, ``"frobenius"``, ``"shell r=… + …"`` or ``"blow-up w=[…], m=…"``, or the
    :class:`InnerForm` itself), exactly that claim is
    checked again, without any search
    (:func:`nlyap_opt.certification.certificate.recheck_certificate`). Returns a dict with
    ``verdict`` (:class:`nlyap_opt.design.control.InnerStatus`), ``status`` (the verdict in words,
    saved with a certificate), ``P``, ``level`` (``c_q``), ``box``, ``form``.
    """

    cl = closed_loop(system, controller, strict=True)
    J = ca.jacobian(cl.rhs, cl.x)
    A_cl = np.array(_fun(cl.x, J)(np.zeros(system.nx)), dtype=float)
    sat = _true_loop_split(cl, system, controller)
    if form and P is None:
        raise ValueError("form names the saved P's form: give P with it")
    if P is not None:
        P = np.asarray(P, dtype=float)
        n = system.nx
        if P.shape != (n, n) or not np.all(np.isfinite(P)) or not np.array_equal(P, P.T) \
                or np.linalg.eigvalsh(P)[0] <= 0:
            return {"status": f"inner ellipse not proved (P must be a symmetric positive "
                              f"definite {n}x{n} matrix)", "verdict": InnerStatus.NOT_PROVED,
                    "P": np.eye(n), "level": 0.0,
                    "box": np.zeros(n), "result": None, "form": form or ""}
    spec = None
    if form:
        text = form.to_str() if isinstance(form, InnerForm) else str(form)
        try:
            spec = form if isinstance(form, InnerForm) else InnerForm.parse(text)
        except ValueError as exc:
            c_q, a = ellipse_around_ball(P, inner)
            return {"status": f"inner ellipse not proved (the form does not apply: {exc})",
                    "verdict": InnerStatus.NOT_PROVED, "P": P, "level": c_q, "box": a,
                    "result": None, "form": text}
        form = text
    if spec is not None and spec.kind is InnerFormKind.BLOWUP:
        w = spec.weights
        out = None
        if len(w) == system.nx:
            out = certify_inner_blowup(cl, A_cl, inner, verify_options=verify_options,
                                       candidates=[(P, w)])
        if out is None:
            c_q, a = ellipse_around_ball(P, inner)
            out = {"status": f"inner ellipse not proved ({form} does not apply to this "
                             "closed loop)", "verdict": InnerStatus.NOT_PROVED, "P": P,
                   "level": c_q, "box": a, "result": None, "form": form}
        return out
    blowup = None
    if P is not None:
        candidates = [P]
    else:
        # a centre of _centre_split is on the imaginary axis exactly, whatever the rounding
        # of the eigenvalues says
        hurwitz = np.max(np.linalg.eigvals(A_cl).real) < 0
        if not hurwitz or _centre_split(A_cl) is not None:
            blowup = certify_inner_blowup(cl, A_cl, inner, verify_options=verify_options)
            if blowup is not None and (not hurwitz or
                                       blowup["verdict"] is InnerStatus.CERTIFIED):
                return blowup
            if not hurwitz:
                return {"status": "closed-loop linearisation not Hurwitz",
                        "verdict": InnerStatus.NOT_HURWITZ, "P": np.eye(system.nx),
                        "level": 0.0, "box": np.zeros(system.nx), "result": None}
        candidates = ellipse_candidates(A_cl)   # Hurwitz as rounded: the Jacobian forms too
        if sat is not None:     # the matrix designed for the whole-set test of the shell
            sector = (_sector_candidate(sat, cl, A_cl, system, inner) for _ in (0,))  # lazy
            candidates = itertools.chain(sector, candidates) \
                if system.nx > SECTOR_FIRST_STATES else itertools.chain(candidates, sector)
    first = None
    for Pc in candidates:
        if Pc is None or not np.array_equal(Pc, Pc.T):   # a saved P must be symmetric too
            continue
        out = _inner_ellipse(cl, J, Pc, inner, verify_options, only=spec, saturated=sat)
        if out["verdict"] is InnerStatus.CERTIFIED:
            return out
        first = first or out
    return first if first is not None else blowup


#: a sampled ``V̇_q`` above this fraction of the sum of its terms' magnitudes is positive
#: beyond any rounding of its float evaluation (about ``1e-15`` of that sum)
_VDOT_SLACK = 1e-9


def inner_ellipse_bound(system, controller, inner: float, pts: np.ndarray, *,
                        samples: int = 4000, seed: int = 0) -> np.ndarray | None:
    r"""Which ``pts`` may lie in condition (c)'s ellipse ``E`` at radius ``inner`` (the true
    closed loop with ``controller``), without verifying (c): an over-approximation, to bound
    the volume a certificate can reach before its (expensive) verification is attempted.

    Without a saved form, :func:`certify_inner_ellipse` proves (c) with one of the
    candidates ``P`` of :func:`nlyap_opt.design.control.ellipse_candidates` on
    ``E = {xᵀPx ≤ c_q}`` (:func:`ellipse_around_ball`), and every form it proves implies
    :math:`\dot V_q = 2x^\top P f(x) < 0` on :math:`E \setminus \{0\}`. A candidate whose
    ellipse holds a sampled point (``samples`` seeded points inside and on ``E``) with
    :math:`\dot V_q` clearly positive (beyond :data:`_VDOT_SLACK` of its terms) can
    therefore not be proved; the mask is the union of the other candidates' ellipses. Under a
    saturated controller (:class:`SaturatedLoop`) the candidates include the ``sector`` matrix
    that :func:`certify_inner_ellipse` also tries (:func:`_sector_candidate`, computed here
    too). ``None`` (no bound) where (c) would take another route: a linearisation that is not
    Hurwitz or has a centre (the weighted blow-up).
    """
    cl = closed_loop(system, controller, strict=True)
    n = system.nx
    A_cl = np.array(_fun(cl.x, ca.jacobian(cl.rhs, cl.x))(np.zeros(n)), dtype=float)
    if not np.all(np.isfinite(A_cl)) or np.max(np.linalg.eigvals(A_cl).real) >= 0 \
            or _centre_split(A_cl) is not None:
        return None
    candidates = list(ellipse_candidates(A_cl))
    sat = _true_loop_split(cl, system, controller)
    if sat is not None:
        candidates.append(_sector_candidate(sat, cl, A_cl, system, inner))
    F = _fun(cl.x, cl.rhs)
    rng = np.random.default_rng(seed)
    u = np.vstack([sample_ball(samples // 2, n, 1.0, rng),
                   sample_sphere(samples - samples // 2, n, 1.0, rng)])
    mask = np.zeros(len(pts), dtype=bool)
    for P in candidates:
        if P is None or not np.all(np.isfinite(P)):
            continue
        c_q, _ = ellipse_around_ball(P, inner)
        try:    # x = sqrt(c_q)·L⁻ᵀu maps the unit ball onto E (P = L Lᵀ)
            x = math.sqrt(c_q) * np.linalg.solve(np.linalg.cholesky(P).T, u.T).T
        except (np.linalg.LinAlgError, ValueError):
            x = None                       # no samples: the ellipse stays in the bound
        if x is not None:
            terms = 2.0 * (x @ P) * evaluate(F, [x])[0]
            if np.any(terms.sum(axis=1) > _VDOT_SLACK * np.abs(terms).sum(axis=1)):
                continue
        mask |= np.einsum("ij,jk,ik->i", pts, P, pts) <= c_q * (1 + 1e-9)
    return mask


def _origin_offset(F: ca.Function, P: list[list[Fraction]]) -> Fraction | None:
    r"""A rational ``b ≥ ‖P g(0)‖₂`` for the closed loop ``g`` (the graph ``F``) at the
    origin, ``P`` exact: ``0`` when ``g(0) = 0`` exactly (an SX graph evaluated in exact
    rational arithmetic, :class:`~nlyap_opt.kernel.walker.ExactPointArithmetic`, or an
    interval enclosure that is ``[0, 0]``; no structural or float-folded zero is trusted);
    ``None`` when the enclosure is not finite.

    A closed loop's equilibrium is the origin only up to rounding (``C·tanh(b) = u_eq`` of a
    controller holds in floats). :class:`TaylorDecrease` pays for ``b`` near the inner ball;
    the forms of :func:`_inner_ellipse` prove ``PJ + JᵀP + λI ≺ 0`` on ``E`` with ``λ =
    4b/ε``, so that ``V̇_q = 2xᵀPg(0) + xᵀS̄x < 2b‖x‖ − λ‖x‖² ≤ 0`` on ``∂E`` (``‖x‖ ≥ ε``
    there): ``E`` is forward invariant, and the loop contracts on it to its one equilibrium
    in ``E``, within ``ε/2`` of the origin."""
    n = len(P)
    exact = exact_values(F, [0] * n)     # SX graphs only (None for MX)
    if exact is not None and all(isinstance(v, Fraction) and v == 0 for v in exact):
        return Fraction(0)
    Interval, ia = interval_arithmetic()
    z = np.zeros((1, n))
    res = evaluate(F, [Interval(z, z.copy())], ia)[0]
    lo = np.asarray(res.lo, dtype=float).ravel()
    hi = np.asarray(res.hi, dtype=float).ravel()
    if lo.size != n or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        return None
    m = [max(abs(Fraction(u)), abs(Fraction(v))) for u, v in zip(lo, hi)]
    if not any(m):
        return Fraction(0)
    w = [sum(abs(P[i][j]) * m[j] for j in range(n)) for i in range(n)]
    return Fraction(_sqrt_up(sum(t * t for t in w)))


def _whole_space(n: int) -> np.ndarray:
    """The box of all of ``R^n``: a whole-set test then works on the ellipsoid's own box."""
    return np.array([[-np.inf, np.inf]] * n)


#: condition (c) tries the matrix of :func:`sector_lyapunov_matrix` first in more than this
#: many states (where the other candidates' bisection forms take minutes), last otherwise
SECTOR_FIRST_STATES = 3


def _true_loop_split(cl, system, controller) -> SaturatedLoop | None:
    """The true closed loop ``cl`` split by its saturated controller, or ``None`` where the
    split does not apply (no controller, not one tanh layer, no graph to enclose)."""
    sat = SaturatedLoop(cl.x, system.f_fun, controller) if controller is not None else None
    return None if sat is None or sat.why else sat


def _sector_candidate(sat: SaturatedLoop, cl, A_cl: np.ndarray, system, inner: float):
    """Condition (c)'s candidate for a saturated controller: :func:`sector_lyapunov_matrix`
    of the true closed loop at ``ε`` (seeded with the largest Lyapunov ellipsoid in the unit
    ball, within the system's state box), or ``None``."""
    seed = volume_lyapunov_matrix(A_cl, 0.05)
    box = np.asarray(system.state_box, dtype=float) if system.state_box is not None else None
    if seed is None or box is None or not np.all((box[:, 0] < 0) & (box[:, 1] > 0)):
        return None
    return sector_lyapunov_matrix(sat, cl.x, cl.rhs, seed, inner=inner,
                                  limit=np.minimum(-box[:, 0], box[:, 1]))


def _inner_ellipse(cl, J, P, inner, verify_options, only: InnerForm | None = None, *,
                   shell: bool = True, saturated: SaturatedLoop | None = None):
    """Verify condition (c) for ``P`` on ``E = {xᵀPx ≤ c_q}`` (``c_q = λ_max(P) ε²``).

    Three sufficient forms; the first that verifies wins:

    - ``minors``: ``S(y) = P J(y) + J(y)ᵀP ≺ 0`` on ``E`` by Sylvester's criterion, the
      leading minors of ``S`` alternate in sign. Exact at a point (its counterexample is a
      point where ``S`` is not negative definite), but the interval enclosure of a k×k
      determinant loosens quickly with k.
    - ``frobenius``: ``S(y) ≺ 0`` on ``E`` with ``T`` the eigenvectors of ``S(0)`` scaled so
      that ``TᵀS(0)T = −I`` and ``E(y) = Tᵀ(S(y) − S(0))T``: ``‖E(y)‖_F < 1 − d``, with
      ``d`` a bound of the rounding residual ``‖TᵀS(0)T + I‖_F``. Then ``TᵀS(y)T`` has
      ``λ_max ≤ −1 + d + ‖E‖₂ ≤ −1 + d + ‖E‖_F < 0``, and ``T`` is invertible, so
      ``S(y) ≺ 0``. One smooth property, zero at ``y = 0``, whose terms
      are quadratic in the variation of ``J`` (no cancellation of large entries for the
      intervals to lose, no kink to disable the mean-value and affine forms). Measured on
      the cartpole's saturated LQR loop with the round ``P`` at ε = 0.05: verified in
      5.6·10⁵ boxes, while the minors stay unknown after 10⁶.
    - ``shell r=ε_s + minors|frobenius`` (:func:`_inner_shell`): ``V̇_q = 2xᵀP g(x) < 0``
      verified directly on the shell ``E ∖ B_{ε_s}`` (``ε_s`` = :data:`SHELL_FRACTION`·ε),
      and one of the two forms above on the small ellipse ``E_s ⊇ B_{ε_s}`` of the same
      ``P``. ``S(y) ≺ 0`` at every point of ``E`` is far more than ``V̇_q < 0`` asks (the
      decrease averages ``J`` along each ray): the learned-f cartpole's controller with the
      round ``P`` at ε = 0.1 has sampled ``λ_max(S(y))`` up to −0.074 on ``E`` (the
      Frobenius form fails, the minors stay unknown after 10 minutes) but
      ``V̇_q ≤ −0.478‖x‖²``; the shell form verifies it in 8.7·10⁵ + 5.7·10⁴ boxes, 21 s.

    Order: up to 3 dimensions minors, Frobenius, shell (the minors are cheap and exact
    there); from 4 on Frobenius, shell, minors. ``only``: check that form alone (the
    re-check of a saved claim, a shell's ``ε_s`` and inner form included). ``shell``:
    whether the shell form may be tried (not inside a shell).
    """

    n = P.shape[0]
    c_q, a = ellipse_around_ball(P, inner)
    if only is not None and only.kind is InnerFormKind.SHELL:
        if not (shell and only.radius <= inner):
            return {"status": f"inner ellipse not proved (the form {only.to_str()!r} does not "
                              "apply: a shell needs 0 < r ≤ ε and the minors or frobenius "
                              "form)", "verdict": InnerStatus.NOT_PROVED, "P": P,
                    "level": c_q, "box": a, "result": None, "form": only.to_str()}
        return _inner_shell(cl, J, P, inner, verify_options, eps_s=only.radius,
                            only=only.core, saturated=saturated)
    S = ca.mtimes(ca.DM(P), J)
    S = S + S.T
    b = _origin_offset(ca.Function("g_origin", [cl.x], [cl.rhs]), rational_matrix(P))
    if b is None:
        return {"status": "inner ellipse not proved (the closed loop at the origin is not "
                          "finite)", "verdict": InnerStatus.NOT_PROVED, "P": P, "level": c_q,
                "box": a, "result": None, "form": "" if only is None else only.to_str()}
    lam = 0.0
    if b > 0:   # S + λI ≺ 0 with λ = 4b/ε: V̇_q < 2b‖x‖ − λ‖x‖² ≤ 0 for ‖x‖ ≥ ε/2, on ∂E
        lam = float(np.nextafter(4.0 * float_up(b) / inner, np.inf))
        S = S + lam * ca.DM.eye(n)
    # the Jacobian forms' claim S ≺ 0 on E, tried on the whole set first
    whole = TaylorDecrease(cl.x, cl.rhs, rational_matrix(P), saturated=saturated)
    # J only matters on E (convex: it holds every segment [0, x]); the box's corners reach
    # V = n·c_q, so the region is E itself
    Vq = ca.bilin(ca.DM(P), cl.x, cl.x)
    box = np.stack([-a, a], axis=1)
    minors = _leading_minors(S)
    forms = {"minors": [-((-1) ** k) * m for k, m in enumerate(minors, start=1)]}
    S0 = np.array(_fun(cl.x, S)(np.zeros(n)), dtype=float)
    w, T = np.linalg.eigh(0.5 * (S0 + S0.T))
    if np.all(np.isfinite(w)) and w[-1] < 0:
        Tn = T / np.sqrt(-w)
        E = ca.mtimes([ca.DM(Tn).T, S - ca.DM(S0), ca.DM(Tn)])
        # TᵀS(0)T is −I only up to rounding: λ_max(TᵀS(y)T) ≤ −1 + d + ‖E‖₂ with d ≥
        # ‖TᵀS(0)T + I‖_F (float residual plus the bound γ_2n |T|ᵀ|S(0)||T| of the products)
        d = (np.linalg.norm(Tn.T @ S0 @ Tn + np.eye(n))
             + 4 * n * EPS * np.linalg.norm(np.abs(Tn).T @ np.abs(S0)
                                                            @ np.abs(Tn))) * (1 + 1e-6)
        if d < 0.5:     # (1 − d)² is the bound only while d < 1
            forms["frobenius"] = [ca.sumsqr(E) - (1.0 - d) ** 2]
        if shell:       # S(0) ≺ 0: the small ellipse E_s is certifiable for a small ε_s
            forms["shell"] = None
    order = [only.kind.value] if only is not None else \
        ["minors", "frobenius", "shell"] if n <= 3 else ["frobenius", "shell", "minors"]
    if not any(f in forms for f in order):
        return {"status": f"inner ellipse not proved (the {only.to_str()} form does not apply "
                          "to this P)", "verdict": InnerStatus.NOT_PROVED, "P": P,
                "level": c_q, "box": a, "result": None, "form": only.to_str()}
    contracts = None
    for form in [f for f in order if f in forms]:
        if forms[form] is None:
            out = _inner_shell(cl, J, P, inner, verify_options, saturated=saturated)
        else:
            if contracts is None:  # S ≺ 0 on E, whichever form states it (decided once)
                contracts = whole.contracts(c_q, _whole_space(n), lam)
            if contracts:
                res = VerificationResult(QueryStatus.VERIFIED, backend="taylor")
            else:  # the form's own check (its problem built only when it is needed)
                props = forms[form]
                res = parallel.check(VerificationProblem(
                    cl.x, box, [Vq - c_q], props, ["ellipse"],
                    [f"{form}{k}" for k in range(1, len(props) + 1)]),
                    **(verify_options or {}))
            out = {"status": "certified" if res.success else f"inner ellipse {res.status}",
                   "verdict": verdict_of(res.status), "P": P, "level": c_q, "box": a,
                   "result": res, "form": form}
        if out["verdict"] is InnerStatus.CERTIFIED:
            break
    return out


#: the inner radius ``ε_s`` of condition (c)'s shell form, as a fraction of ε (measured on
#: the learned-f cartpole's round ``P`` at ε = 0.1: ε/2 took 57 s, ε/4 21 s, ε/8 21 s)
SHELL_FRACTION = 0.25


def _inner_shell(cl, J, P, inner, verify_options, *, eps_s: float | None = None,
                 only: InnerFormKind | None = None,
                 saturated: SaturatedLoop | None = None) -> dict:
    r"""The shell form of condition (c): ``V̇_q = 2xᵀP g(x) < 0`` on ``E ∖ B_{ε_s}``, and
    ``S ≺ 0`` (minors or Frobenius form, ``only``: that one) on ``E_s = {xᵀPx ≤ c_s} ⊇
    B_{ε_s}``, ``c_s = λ_max(P) ε_s²``, ``0 < ε_s ≤ ε``.

    Then ``E_s ⊆ E`` is forward invariant and converges to 0 (the Jacobian form), and on
    ``E ∖ B_{ε_s}`` the quadratic decreases, at a rate bounded away from 0 (a continuous
    ``V̇_q < 0`` on a compact set): a trajectory from ``E`` stays in ``E`` and enters
    ``B_{ε_s} ⊆ E_s`` in finite time. A counterexample of the shell is a point of
    ``E ∖ {0}`` where ``V̇_q ≥ 0``: this ``P`` cannot certify this ``E``. The shell is first
    tried as a whole (:class:`TaylorDecrease` on ``E``'s box outside ``B_{ε_s}``, with the
    split of a saturated controller, ``saturated``), then by bisection.
    """

    eps_s = float(inner * SHELL_FRACTION if eps_s is None else eps_s)
    c_q, a = ellipse_around_ball(P, inner)
    x = cl.x
    Vq = ca.bilin(ca.DM(P), x, x)
    dV = 2 * ca.dot(x, ca.mtimes(ca.DM(P), cl.rhs))
    prob = VerificationProblem(x, np.stack([-a, a], axis=1), [Vq - c_q, eps_s**2 - ca.sumsqr(x)],
                               [dV], ["ellipse", "shell"], ["dVq/dt<0 on the shell"])
    # a saved claim (``only``) is expected to hold: on a cluster its core runs beside the
    # shell (both are narrow chains of bisection levels); it is used only if the shell holds,
    # as serially
    with parallel.ahead(_inner_ellipse, cl, J, P, eps_s, verify_options,
                        only=None if only is None else InnerForm(only), shell=False,
                        saturated=saturated, when=only is not None) as core_job:
        res = TaylorDecrease(x, cl.rhs, rational_matrix(P), saturated=saturated).check(
            c_q, _whole_space(len(a)), eps_s)             # on all of E ∖ B_{ε_s}
        if res is None:
            res = parallel.check(prob, **(verify_options or {}))
        if not res.success:
            return {"status": f"inner ellipse {res.status}", "verdict": verdict_of(res.status),
                    "P": P, "level": c_q, "box": a, "result": res,
                    "form": f"shell r={eps_s!r}"}
        core = core_job.result()
    form = InnerForm(InnerFormKind.SHELL, radius=eps_s, core=InnerFormKind(core["form"]))
    ok = core["verdict"] is InnerStatus.CERTIFIED
    return {"status": core["status"], "verdict": core["verdict"], "P": P, "level": c_q,
            "box": a, "result": res if ok else core["result"],
            "form": form.to_str()}


def ellipse_around_ball(P, inner: float) -> tuple[float, np.ndarray]:
    """``(c_q, a)``: the least level with ``B_ε ⊆ E = {xᵀPx ≤ c_q}`` (rounded up) and the
    half-widths of a box containing ``E`` (``a_i = sqrt(c_q (P⁻¹)_ii)``, rounded up).

    ``c_q = λ_max(P)·ε²·(1 + 10⁻⁹)`` rounded up to 12 significant digits: the factor covers
    LAPACK's error in λ_max by far, and the rounding makes the level the same number on
    machines whose eigensolvers differ in the last bits, so that a certificate re-checked
    elsewhere finds the level it stores."""
    c = float(np.linalg.eigvalsh(P)[-1]) * inner**2 * (1 + 1e-9)
    if c > 0 and math.isfinite(c):
        q = 10.0 ** (math.floor(math.log10(c)) - 11)
        c = math.ceil(c / q) * q
    return c, np.sqrt(c * np.diag(np.linalg.inv(P))) * (1 + 1e-9)


#: the weight of the non-centre coordinates in :func:`certify_inner_blowup`, in the order tried
BLOWUP_WEIGHTS = (2, 3, 4)
#: the highest order ``m`` of the blow-up's leading term (its derivative graphs grow with ``m``)
BLOWUP_MAX_ORDER = 8


def _centre_split(A_cl: np.ndarray):
    """``(centre, hyp, T)`` for a linearisation with a centre, or ``None``.

    The centre coordinates ``c`` are the largest set whose rows of ``A_cl`` vanish outside
    their own columns, with ``A_cc`` skew-symmetric (0, or a rotation ``x1' = x2``,
    ``x2' = -x1``: ``V = ‖x_c‖²`` is constant under it); the others' block ``A_hh`` must be
    Hurwitz. A linear drive of the others by the centre (``y' = -y + x``) tilts the
    centre subspace off the axes, to ``x_h = M x_c`` with ``A_hh M - M A_cc = -A_hc``; ``T``
    is the shear ``x = T z``: the identity with ``T[h, c] = M`` (its inverse negates that
    block, exactly in floating point), so that ``z_h = x_h - M x_c`` and the centre is the
    ``z_c`` axes. ``T`` is the identity when nothing is driven.
    """
    n = A_cl.shape[0]
    scale = max(1.0, float(np.max(np.abs(A_cl))))
    A = np.where(np.abs(A_cl) <= 1e-12 * scale, 0.0, A_cl)
    centre = [i for i in range(n) if A[i, i] == 0.0]
    while True:
        keep = [i for i in centre if not np.any(np.delete(A[i], centre))]
        if keep == centre:
            break
        centre = keep
    if not centre:
        return None
    A_cc = A[np.ix_(centre, centre)]
    if np.any(A_cc + A_cc.T != 0.0):
        return None
    hyp = [i for i in range(n) if i not in centre]
    T = np.eye(n)
    if hyp:
        A_hh = A[np.ix_(hyp, hyp)]
        if np.max(np.linalg.eigvals(A_hh).real) >= 0:
            return None
        A_hc = A[np.ix_(hyp, centre)]
        if np.any(A_hc):
            M = solve_sylvester(A_hh, -A_cc, -A_hc)
            if not np.all(np.isfinite(M)):
                return None
            T[np.ix_(hyp, centre)] = M
    return centre, hyp, T


def _shear_inverse(T: np.ndarray) -> np.ndarray:
    """``T⁻¹`` of a shear of :func:`_centre_split` (exact: the off-diagonal block negated)."""
    S = -T
    np.fill_diagonal(S, 1.0)
    return S


def _blowup_candidates(A_cl: np.ndarray):
    """``(P, w)`` pairs for a linearisation with eigenvalues on the imaginary axis.

    In the coordinates ``z = T⁻¹x`` of :func:`_centre_split` (``z_c = x_c`` the centre,
    ``z_h = x_h - M x_c`` the rest), ``P_z`` is the identity on the centre block and the
    Lyapunov matrix of ``A_hh`` (then the identity) on the rest, and ``P = T⁻ᵀ P_z T⁻¹``
    (``P_z`` itself when ``T`` is the identity); the centre coordinates get weight 1, the
    others :data:`BLOWUP_WEIGHTS` (a centre decaying like ``x' = -x^{2k+1}`` balances a
    hyperbolic ``y' = -y`` under the weights ``(1, k + 1)``). A candidate is only tried:
    :func:`certify_inner_blowup` proves it or not.
    """

    n = A_cl.shape[0]
    split = _centre_split(A_cl)
    if split is None:
        return []
    centre, hyp, T = split
    Ps = [np.eye(n)]
    if hyp:
        P = np.eye(n)
        P[np.ix_(hyp, hyp)] = lyapunov_matrix(A_cl[np.ix_(hyp, hyp)])
        Ps.insert(0, P)
    if np.any(T != np.eye(n)):
        S = _shear_inverse(T)
        Ps = [S.T @ Pz @ S for Pz in Ps]
        Ps = [0.5 * (P + P.T) for P in Ps]
    weights = [(1,) * n] if not hyp else [
        tuple(1 if i in centre else k for i in range(n)) for k in BLOWUP_WEIGHTS]
    return [(P, w) for P in Ps for w in weights]


def centre_lyapunov_matrix(A_cl) -> np.ndarray | None:
    r"""The ``P`` of :func:`certify_inner_blowup`'s first candidate for a linearisation with
    a centre: the identity on the centre coordinates, the Lyapunov matrix of the Hurwitz
    block on the others (``None`` when there is no centre on the coordinate axes, or the
    rest is not Hurwitz).

    :math:`V = x^\top P x` is then a candidate Lyapunov function of the whole closed loop
    whose derivative is :math:`-\|x_h\|^2` plus higher-order terms: along the centre it
    decreases like the leading terms of ``f`` (``x' = -x³``: like :math:`-\|x\|^4`).

    Examples
    --------
    >>> centre_lyapunov_matrix(np.diag([0.0, -1.0]))
    array([[1. , 0. ],
           [0. , 0.5]])
    >>> centre_lyapunov_matrix(-np.eye(2)) is None
    True
    """
    A = np.asarray(A_cl, dtype=float)
    if A.ndim != 2 or A.shape[0] != A.shape[1] or not np.all(np.isfinite(A)):
        return None
    found = _blowup_candidates(A)
    return found[0][0] if found else None


def _leading_term(h_sub, r, u, max_order: int, order: int | None = None):
    """``(m, D_m)``: the least ``m`` whose ``∂ᵐh/∂rᵐ`` at ``r = 0`` is not exactly zero for
    every ``u`` (or ``order``, when the exact expansion gave it), and that derivative as a
    function of ``(r, u)`` (``None`` past ``max_order``).

    "Exactly zero" is the derivative graph evaluated at ``r = 0`` in exact rational
    arithmetic with every ``u_i`` standing for any real
    (:class:`~nlyap_opt.kernel.walker.ExactPointArithmetic`): a substitution of ``r = 0``
    into the graph folds constants in floats and could show a 0 that is not one. A graph
    the exact arithmetic cannot show to be 0 ends the search at that order, and the
    verifier then has to prove that term negative."""
    D = h_sub
    ru = ca.vertcat(r, u)
    point = [0] + [REAL] * u.numel()
    for m in range(max_order + 1):
        if order is not None:
            if m == order:
                return m, D
        else:
            vals = exact_values(ca.Function("d", [ru], [D]), point)
            if vals is None or not all(isinstance(v, Fraction) and v == 0 for v in vals):
                return m, D
        D = ca.jacobian(D, r)
    return None, None


def _exact_order(F, P, T, w) -> int | None:
    """The least power of ``r`` in ``h(r, u) = 2xᵀP f(x)``, ``x = T(r^w ⊙ u)``, computed in
    exact rational arithmetic (``None``: ``f`` is not an exact polynomial, or ``h ≡ 0``).

    Its coefficients below that power vanish identically in ``u``, exactly: the condition
    of Taylor's remainder in :func:`certify_inner_blowup` where cancellations (a shear, a
    rotation in the centre) are numeric and no symbolic zero shows them."""
    n = len(w)
    q = [[Fraction(float(v)) for v in row] for row in np.asarray(T)]
    xs = []
    for j in range(n):
        p = {}
        for k in range(n):
            if q[j][k] != 0:
                e = [0] * (n + 1)
                e[0], e[k + 1] = int(w[k]), 1
                p[tuple(e)] = q[j][k]
        xs.append(p)
    fx = exact_polynomials(F, xs, n + 1)
    if fx is None:
        return None
    h: dict = {}
    Pq = [[Fraction(float(v)) for v in row] for row in np.asarray(P)]
    for i in range(n):
        for j in range(n):
            if Pq[i][j] == 0:
                continue
            for (e1, c1), (e2, c2) in itertools.product(xs[i].items(), fx[j].items()):
                e = tuple(a + b for a, b in zip(e1, e2))
                h[e] = h.get(e, Fraction(0)) + 2 * Pq[i][j] * c1 * c2
    orders = [e[0] for e, c in h.items() if c != 0]
    return min(orders) if orders else None


def certify_inner_blowup(cl, A_cl, inner: float, *, verify_options: dict | None = None,
                         candidates=None):
    r"""Condition (c) without exponential stability: :math:`\dot V_q < 0` on
    :math:`E \setminus \{0\}`, ``E = {xᵀPx ≤ c_q} ⊇ B_ε``, by a weighted blow-up.

    Every ``x ≠ 0`` with :math:`|x_i| \le R^{w_i}` is :math:`x = r^w \odot u` with
    :math:`r = \max_i |x_i|^{1/w_i} \in (0, R]` and ``u`` on a face of the unit cube
    (:math:`|u_j| \le 1`, :math:`u_i = \pm 1` for the maximising ``i``). Let
    :math:`h(r, u) = \nabla V_q \cdot f(r^w \odot u)`, :math:`V_q = x^\top P x`, and ``m``
    the least order whose :math:`\partial_r^m h(0, u)` is not exactly zero for every ``u``
    (CasADi's symbolic derivatives, evaluated at ``r = 0`` in exact rational arithmetic).
    Taylor's theorem with the Lagrange remainder gives
    :math:`h(r, u) = \frac{r^m}{m!}\,\partial_r^m h(\xi, u)` for some
    :math:`\xi \in (0, r)`, so :math:`\partial_r^m h(s, u) < 0` for every
    :math:`s \in [0, R]` and ``u`` on each of the ``2n`` faces (interval verifier) proves
    :math:`\dot V_q(x) < 0` on that box minus the origin, which contains ``E``: ``E`` is
    then forward invariant and every trajectory in it converges to 0 (Lyapunov). Needs a
    closed loop that is smooth on all of :math:`\mathbb{R}^n` (no kink, jump or partial
    operation of the walker's op table; constant arguments excepted), so that ``h`` is
    :math:`C^m` along every segment.

    Where the centre rotates (``A_cc ≠ 0``) or drives the other states linearly
    (``y' = -y + x``: the centre subspace leaves the axes), the lower orders of ``h``
    cancel only numerically: ``m`` is then the least power of ``r`` in ``h`` expanded in
    exact rational arithmetic (:func:`_exact_order`; a polynomial closed loop only), and
    the blow-up is taken in the sheared coordinates ``z = T⁻¹x`` of :func:`_centre_split`,
    ``h(r, u) = ∇V_q·f(T(r^w ⊙ u))``, after the interval verifier has proved
    :math:`|(T^{-1}x)_i| < R^{w_i}` on ``E`` (every ``x ∈ E∖{0}`` is such a point). The
    claim stays about :math:`V_q = x^\top P x`; ``T`` is recomputed from the linearisation
    on a re-check (any ``T`` proves the same claim).

    Returns ``None`` when no candidate applies (unstable or non-smooth closed loop, no
    centre of :func:`_centre_split`), else the dict of :func:`certify_inner_ellipse` with
    ``form = "blow-up w=…, m=…"``: the first ``(P, w)`` of :func:`_blowup_candidates`
    whose leading term is negative on sampled face points and then verifies, or the last
    verified failure. ``candidates``: these ``(P, w)`` pairs instead (a saved claim).
    """

    n = A_cl.shape[0]
    if np.max(np.linalg.eigvals(A_cl).real) > 1e-9 * max(1.0, float(np.max(np.abs(A_cl)))):
        return None
    F = ca.Function("f", [cl.x], [cl.rhs])
    if isinstance(cl.x, ca.MX):
        F = F.expand()
    if compile_function(F).checked:
        return None
    x = ca.SX.sym("x", n)
    rhs = F(x)
    r = ca.SX.sym("r")
    u = ca.SX.sym("u", n)
    rng = np.random.default_rng(0)
    split = _centre_split(A_cl)
    T = np.eye(n) if split is None else split[2]
    sheared = bool(np.any(T != np.eye(n)))
    rotating = split is not None and bool(np.any(A_cl[np.ix_(split[0], split[0])]))
    S = _shear_inverse(T)
    Fx = ca.Function("f", [x], [rhs])
    first = None
    for P, w in (_blowup_candidates(A_cl) if candidates is None else candidates):
        h = 2 * ca.dot(x, ca.mtimes(ca.DM(P), rhs))
        zw = ca.vertcat(*[r**wi * u[i] for i, wi in enumerate(w)])
        h_sub = ca.substitute(h, x, ca.mtimes(ca.DM(T), zw) if sheared else zw)
        order = None
        if sheared or rotating:     # numeric cancellations: the order from exact rationals
            order = _exact_order(Fx, P, T, w)
            if order is None:
                continue
        m, D = _leading_term(h_sub, r, u, BLOWUP_MAX_ORDER, order)
        if m is None:
            continue
        form = InnerForm(InnerFormKind.BLOWUP, weights=tuple(w), order=m).to_str()
        c_q, a = ellipse_around_ball(P, inner)
        bz = a
        if sheared:     # half-widths of E in z = T⁻¹x (the cover is verified below)
            bz = np.sqrt(c_q * np.diag(S @ np.linalg.inv(P) @ S.T)) * (1 + 1e-6)
        R = float(np.max(bz ** (1.0 / np.asarray(w, dtype=float)))) * (1 + 1e-9)
        # the leading term at r = 0 must be negative on the faces: a cheap sampled screen
        U = rng.uniform(-1, 1, size=(4000, n))
        U[np.arange(len(U)), rng.integers(0, n, len(U))] = rng.choice([-1.0, 1.0], len(U))
        lead = np.array(_fun(u, ca.substitute(D, r, ca.SX(0)))(U.T), dtype=float).ravel()
        if not np.all(lead < 0):
            # not a counterexample of V̇_q < 0 (higher orders may still decide): unproved
            first = first or {"status": f"inner ellipse not proved ({form}: leading term "
                                        f"≥ 0 at a face point)",
                              "verdict": InnerStatus.NOT_PROVED, "P": P, "level": c_q,
                              "box": a, "result": None, "form": form}
            continue
        res = None
        if sheared:
            # every x ∈ E is T(r^w ⊙ u) with r ≤ R: |(T⁻¹x)_i| < R^{w_i} on E (verified)
            zx = ca.mtimes(ca.DM(S), x)
            res = parallel.check(VerificationProblem(
                x, np.stack([-a, a], axis=1), [ca.bilin(ca.DM(P), x, x) - c_q],
                [zx[i] ** 2 - R ** (2 * wi) for i, wi in enumerate(w)], ["ellipse"],
                [f"|z{i + 1}| < R^{wi} on E" for i, wi in enumerate(w)]),
                **(verify_options or {}))
            if res.status != "verified":   # R too small: no counterexample of V̇_q < 0
                first = first or {"status": f"inner ellipse not proved ({form}: the blow-up's "
                                            f"box does not cover E: {res.status})",
                                  "verdict": InnerStatus.NOT_PROVED, "P": P, "level": c_q,
                                  "box": a, "result": res, "form": form}
                continue
        for i in range(n):
            for sign in (-1.0, 1.0):
                free = [j for j in range(n) if j != i]
                z = ca.SX.sym("z", n)     # (s, u without u_i)
                uz = [None] * n
                uz[i] = ca.SX(sign)
                for k, j in enumerate(free):
                    uz[j] = z[k + 1]
                prop = ca.substitute(D, ca.vertcat(r, u), ca.vertcat(z[0], *uz))
                box = np.array([[0.0, R]] + [[-1.0, 1.0]] * (n - 1))
                prob = VerificationProblem(z, box, [], [prop],
                                           [], [f"d^{m}h/dr^{m} < 0 on face u{i + 1}={sign:+g}"])
                res = parallel.check(prob, **(verify_options or {}))
                if res.status != "verified":
                    break
            if res.status != "verified":
                break
        out = {"status": "certified" if res.success else f"inner ellipse {res.status}",
               "verdict": verdict_of(res.status), "P": P, "level": c_q, "box": a,
               "result": res, "form": form}
        if out["verdict"] is InnerStatus.CERTIFIED:
            return out
        first = first or out
    return first


def grid_area(mask: np.ndarray, box: np.ndarray) -> float:
    """Area (volume) of a boolean grid mask over ``box`` (cell-centred grid)."""
    cells = np.prod((box[:, 1] - box[:, 0]) / np.array(mask.shape))
    return float(mask.sum() * cells)


def axis_count(points: int, dim: int) -> int:
    """Nodes per axis of a grid with at most ``points`` nodes in ``dim`` dimensions (≥ 2).

    Every grid of a run configuration is a total point budget, so that a setting keeps its
    cost in any dimension (200 per axis is 40,000 points in 2-D, but 1.6·10⁹ in 4-D).

    >>> axis_count(40000, 2), axis_count(14641, 4), axis_count(10, 3)
    (200, 11, 2)
    """
    n = max(2, int(round(points ** (1.0 / dim))))
    while n > 2 and n**dim > points:
        n -= 1
    return n


def grid_points(box: np.ndarray, n: int) -> tuple[np.ndarray, tuple]:
    """Cell centres of an ``n^d`` grid over ``box``: ``(n^d, d)`` points and the grid shape."""
    axes = [lo + (hi - lo) * (np.arange(n) + 0.5) / n for lo, hi in box]
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.stack([m.ravel() for m in mesh], axis=1), tuple([n] * len(box))


#: simulated horizon of :func:`true_roa_mask` (seconds of model time)
TRUE_ROA_TIME = 60.0


def _loop_rhs(system, feedback):
    """The closed loop ``x' = f(x, feedback(x))`` on a batch of states."""
    def rhs(z):
        return system.evaluate(z, None if feedback is None else feedback(z))
    return rhs


def true_roa_horizon(system, feedback, box: np.ndarray, t_final: float = TRUE_ROA_TIME,
                     tol: float = 1e-3) -> float:
    """The horizon :func:`true_roa_mask` is given for ``t_final`` requested: ``t_final``,
    longer for a closed loop with a slow mode at the origin
    (:func:`nlyap_opt.kernel.simulate.horizon`, from the box's largest norm to ``tol``)."""
    box = np.asarray(box, dtype=float)
    A = jacobian_at_origin(_loop_rhs(system, feedback), len(box))
    return horizon(t_final, A, float(np.linalg.norm(np.max(np.abs(box), axis=1))), tol)


def _true_loop(system, feedback, nx: int, dt: float, ellipse):
    """What the true-ROA simulations share: the closed loop's right-hand side, the target
    set (the certified ellipse ``(P, c)``, or ``None``) and the integration (a stiff closed
    loop, a fast mode at the origin, gets a step RK4 is stable for, or ROS2: an unstable
    fast mode would count converging states outside the true ROA)."""
    rhs = _loop_rhs(system, feedback)
    target = None
    if ellipse is not None:
        P, c = np.asarray(ellipse[0], dtype=float), float(ellipse[1])

        def target(z):
            return np.einsum("ij,jk,ik->i", z, P, z) <= c

    return rhs, target, integration(dt, jacobian_at_origin(rhs, nx))


def true_roa_stays(system, feedback, pts: np.ndarray, domain, t_final: float = TRUE_ROA_TIME,
                   dt: float = 0.02, tol: float = 1e-3, ellipse=None) -> np.ndarray:
    """Per state of ``pts``: does its simulated closed loop reach the origin (or the
    certified ellipse) without leaving ``domain`` (a :class:`nlyap_opt.kernel.domain.Region`)?

    A certified sublevel set lies in the domain and is forward invariant, so it holds only
    such states: their share of the true ROA within the domain bounds what any certificate
    there can reach. Same simulation as :func:`true_roa_mask` (a trajectory that leaves the
    domain stops and counts as not reaching the origin).
    """
    pts = np.asarray(pts, dtype=float)
    if not len(pts):
        return np.zeros(0, bool)
    rhs, target, how = _true_loop(system, feedback, pts.shape[1], dt, ellipse)
    return simulate(rhs, pts, t_final, how.dt, tol, target=target, stay=domain.contains,
                    jacobian=how.jacobian)[0]


def true_roa_mask(system, feedback, box: np.ndarray, n: int = 200,
                  t_final: float = TRUE_ROA_TIME,
                  dt: float = 0.02, tol: float = 1e-3, ellipse=None,
                  undecided: bool = False):
    """Grid mask of initial states whose simulated closed loop converges to the origin.

    Fixed-step RK4 on all grid points at once (``dt``, shortened for a stiff loop; for a
    very stiff one the linearly implicit ROS2 at ``dt``:
    :func:`nlyap_opt.kernel.simulate.integration`); a state counts as converged once
    ``‖x‖ < tol`` or, given ``ellipse = (P, c)`` (a certified quadratic ROA of this closed
    loop, :func:`certify_inner_ellipse`), once ``xᵀPx ≤ c`` (it is then dropped from the
    integration); as diverged once it leaves ``1e6`` or becomes non-finite. With
    ``undecided``, returns ``(mask, undecided_mask, elsewhere_mask)``: the third marks the
    states that came to rest at another asymptotically stable equilibrium
    (:func:`nlyap_opt.kernel.simulate.at_other_equilibrium`), the second those that did
    neither of the three within ``t_final``; the estimate counts both outside the ROA.
    """
    pts, shape = grid_points(box, n)
    rhs, target, how = _true_loop(system, feedback, pts.shape[1], dt, ellipse)
    done, _, open_, x_end = simulate(rhs, pts, t_final, how.dt, tol, target=target,
                                     return_undecided=True, jacobian=how.jacobian, final=True)
    if not undecided:
        return done.reshape(shape)
    elsewhere = np.zeros_like(open_)
    elsewhere[open_] = at_other_equilibrium(rhs, x_end[open_], tol)
    return done.reshape(shape), (open_ & ~elsewhere).reshape(shape), elsewhere.reshape(shape)
