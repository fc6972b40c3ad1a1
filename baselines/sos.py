r"""Sum-of-squares (SOS) region-of-attraction estimates, re-certified by our verifier.

The SOS programs are written directly as semidefinite programs in cvxpy (no SOS toolbox):
a polynomial :math:`p` is SOS when :math:`p(x) = z(x)^\top Q z(x)` for a vector of monomials
:math:`z` and a Gram matrix :math:`Q \succeq 0`; the identity is imposed by matching the
coefficients of every monomial.

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
    :func:`nlyap_opt.roa.certify_level` (interval verifier: (a) decrease on
    :math:`\{\varepsilon \le \|x\| \le r,\ V \le c\}`, (b) :math:`V > c` on
    :math:`\|x\| = r`, lowering ``c`` on counterexamples) and
    :func:`nlyap_opt.roa.certify_inner_ellipse` ((c) on the inner ball). Only
    ``certified_level`` is a claim; ``sdp_level`` is reported beside it.

Non-polynomial closed loops (``sin``, ``cos``, ``1/(1 - d)``, ``tanh`` controllers) are not
handled: :func:`sos_roa` returns ``status = "not applicable: ..."`` with the reason.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from nlyap_opt.errors import NlyapError

__all__ = [
    "NotPolynomialError", "Polynomial", "SOSLevel", "SOSResult", "polynomial_closed_loop",
    "sos_level", "sos_roa",
]


class NotPolynomialError(NlyapError, ValueError):
    """A CasADi expression is not a polynomial in the state (SOS needs polynomial data)."""


# --------------------------------------------------------------------------- polynomials
@dataclass(frozen=True)
class Polynomial:
    r"""A real polynomial :math:`p(x) = \sum_k c_k\, x^{\alpha_k}` in ``nx`` variables.

    Attributes
    ----------
    exponents : (k, nx) int ndarray   the monomials :math:`\alpha_k`
    coefficients : (k,) ndarray       the coefficients :math:`c_k`

    Examples
    --------
    >>> p = Polynomial.from_dict({(2, 0): 1.5, (1, 1): -1.0, (0, 2): 1.0})
    >>> float(p(np.array([[1.0, 2.0]]))[0]), p.degree
    (3.5, 2)
    """

    exponents: np.ndarray
    coefficients: np.ndarray

    @classmethod
    def from_dict(cls, terms: dict, nx: int | None = None) -> Polynomial:
        """Build from ``{exponent tuple: coefficient}`` (zero coefficients dropped)."""
        items = sorted(((tuple(int(a) for a in e), float(c)) for e, c in terms.items()
                        if c != 0), key=lambda t: (sum(t[0]), tuple(-a for a in t[0])))
        if nx is None:
            if not terms:
                raise ValueError("give nx for the zero polynomial")
            nx = len(next(iter(terms)))
        exps = np.array([e for e, _ in items], dtype=int).reshape(-1, nx)
        return cls(exps, np.array([c for _, c in items], dtype=float))

    def to_dict(self) -> dict:
        """``{exponent tuple: coefficient}``."""
        return {tuple(int(a) for a in e): float(c)
                for e, c in zip(self.exponents, self.coefficients)}

    @property
    def nx(self) -> int:
        return self.exponents.shape[1]

    @property
    def degree(self) -> int:
        return int(self.exponents.sum(axis=1).max()) if len(self.coefficients) else 0

    def __call__(self, X) -> np.ndarray:
        """Evaluate on a batch ``X`` of shape ``(N, nx)``; returns ``(N,)``."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        top = int(self.exponents.max(initial=0))
        powers = [np.ones_like(X)]
        for _ in range(top):
            powers.append(powers[-1] * X)
        out = np.zeros(len(X))
        for e, c in zip(self.exponents, self.coefficients):
            term = np.full(len(X), c)
            for i, a in enumerate(e):
                if a:
                    term = term * powers[a][:, i]
            out += term
        return out

    def casadi(self, x):
        """The polynomial as a CasADi expression of the column symbol ``x`` (MX or SX)."""
        if x.numel() != self.nx:
            raise ValueError(f"x must have {self.nx} entries, got {x.numel()}")
        total = 0
        for e, c in zip(self.exponents, self.coefficients):
            term = float(c)
            for i, a in enumerate(e):
                if a == 1:
                    term = term * x[i]
                elif a > 1:
                    term = term * x[i] ** int(a)
            total = total + term
        return total if not isinstance(total, int) else x[0] * 0

    def __str__(self) -> str:
        parts = []
        for e, c in zip(self.exponents, self.coefficients):
            mono = "*".join(f"x{i + 1}" + (f"^{a}" if a > 1 else "")
                            for i, a in enumerate(e) if a)
            parts.append(f"{c:+.6g}" + (f"*{mono}" if mono else ""))
        return " ".join(parts).lstrip("+") or "0"

    def as_json(self) -> dict:
        return {"exponents": self.exponents.tolist(), "coefficients": self.coefficients.tolist()}


def _padd(p: dict, q: dict, sign: float = 1.0) -> dict:
    out = dict(p)
    for e, c in q.items():
        out[e] = out.get(e, 0.0) + sign * c
    return {e: c for e, c in out.items() if c != 0.0}


def _pmul(p: dict, q: dict) -> dict:
    out: dict = {}
    for (e1, c1), (e2, c2) in itertools.product(p.items(), q.items()):
        e = tuple(a + b for a, b in zip(e1, e2))
        out[e] = out.get(e, 0.0) + c1 * c2
    return {e: c for e, c in out.items() if c != 0.0}


def _constant_of(p: dict, nx: int) -> float | None:
    """The value of a constant polynomial, or ``None`` if ``p`` depends on ``x``."""
    if any(any(e) for e in p):
        return None
    return p.get((0,) * nx, 0.0)


class PolynomialArithmetic:
    """Walker arithmetic over exact polynomials (dicts exponent-tuple -> coefficient).

    A value is ``None`` once a non-polynomial operation was applied to a state-dependent
    expression; the offending operations are collected in ``bad`` (for the error message).
    Operations on constants are folded in float64, as CasADi itself would.
    """

    name = "polynomial"
    symbolic = True

    def __init__(self, nx: int):
        self.nx = nx
        self.zero = (0,) * nx
        self.bad: dict[str, str] = {}

    def variables(self) -> np.ndarray:
        xs = np.empty(self.nx, dtype=object)
        for i in range(self.nx):
            e = [0] * self.nx
            e[i] = 1
            xs[i] = {tuple(e): 1.0}
        return xs

    def constant(self, value) -> dict:
        c = float(value)
        return {self.zero: c} if c != 0 else {}

    def _refuse(self, op):
        from nlyap_opt.walker import op_name

        self.bad.setdefault(_FRIENDLY.get(op, op_name(op).removeprefix("OP_").lower()),
                            op_name(op))

    def _fold(self, op, consts):
        from nlyap_opt.walker import NUMPY

        val = float(NUMPY.unary(op, np.array(consts[0])) if len(consts) == 1
                    else NUMPY.binary(op, np.array(consts[0]), np.array(consts[1])))
        return {self.zero: val} if val != 0 else {}

    def unary(self, op, a):
        if a is None:
            if op not in _POLY_OPS:
                self._refuse(op)
            return None
        c = _constant_of(a, self.nx)
        if c is not None:
            return self._fold(op, [c])
        if op == ca.OP_NEG:
            return {e: -v for e, v in a.items()}
        if op == ca.OP_SQ:
            return _pmul(a, a)
        if op == ca.OP_TWICE:
            return {e: 2.0 * v for e, v in a.items()}
        if op == ca.OP_ASSIGN:
            return a
        self._refuse(op)
        return None

    def binary(self, op, a, b):
        cb = None if b is None else _constant_of(b, self.nx)
        if a is None or b is None:
            divisor_ok = op == ca.OP_DIV and cb not in (None, 0.0)
            if op not in _POLY_OPS and not divisor_ok:
                self._refuse(op)
            return None
        ca_ = _constant_of(a, self.nx)
        if ca_ is not None and cb is not None:
            return self._fold(op, [ca_, cb])
        if op == ca.OP_ADD:
            return _padd(a, b)
        if op == ca.OP_SUB:
            return _padd(a, b, -1.0)
        if op == ca.OP_MUL:
            return _pmul(a, b)
        if op == ca.OP_DIV and cb is not None and cb != 0:
            return {e: v / cb for e, v in a.items()}
        if (op in (ca.OP_POW, ca.OP_CONSTPOW) and cb is not None
                and float(cb).is_integer() and 0 <= cb <= 64):
            p = {self.zero: 1.0}
            for _ in range(int(cb)):
                p = _pmul(p, a)
            return p
        self._refuse(op)
        return None

    def structural(self, fn, *args):
        return fn(*args)


def _expand_sx(fun: ca.Function, nx: int) -> list[dict]:
    """Exact expansion of an SX Function ``x -> y`` into polynomials, through the walker."""
    from nlyap_opt.walker import evaluate

    ar = PolynomialArithmetic(nx)
    outs = evaluate(fun, [ar.variables()], ar)[0]
    if any(p is None for p in outs):
        what = ", ".join(f"{k} ({v})" for k, v in ar.bad.items())
        raise NotPolynomialError(
            f"not polynomial in x: it applies {what} to state-dependent expressions"
        )
    return list(outs)


_FRIENDLY = {ca.OP_DIV: "division", ca.OP_INV: "the reciprocal", ca.OP_SIN: "sin",
             ca.OP_COS: "cos", ca.OP_TANH: "tanh", ca.OP_EXP: "exp", ca.OP_SQRT: "sqrt"}

_POLY_OPS = {ca.OP_ADD, ca.OP_SUB, ca.OP_MUL, ca.OP_NEG, ca.OP_SQ, ca.OP_TWICE, ca.OP_ASSIGN,
             ca.OP_POW, ca.OP_CONSTPOW}



def polynomial_closed_loop(system, controller=None) -> list[Polynomial]:
    r"""The closed loop :math:`f(x, \kappa(x))` as exact polynomials, one per state.

    The CasADi graph is expanded instruction by instruction with polynomial arithmetic
    (addition, multiplication, integer powers, division by constants); any other operation
    on a function of the state raises :class:`NotPolynomialError` naming it.

    Parameters
    ----------
    system : systems.System
    controller : nlyap_opt.network.Network, optional
        Feedback ``κ``; ``None`` applies ``u_eq``.

    Returns
    -------
    list of Polynomial
        ``nx`` polynomials, ``f_i(x)``.

    Examples
    --------
    >>> import systems
    >>> [str(p) for p in polynomial_closed_loop(systems.get("van_der_pol"))]
    ['-1*x2', '1*x1 -1*x2 +1*x1^2*x2']
    """
    from nlyap_opt.symbolic import closed_loop

    cl = closed_loop(system, controller, strict=True)
    fun = ca.Function("cl", [cl.x], [cl.rhs]).expand()
    polys = _expand_sx(fun, system.nx)
    return [Polynomial.from_dict(p, system.nx) for p in polys]


# --------------------------------------------------------------------------- SOS machinery
def _monomials(nx: int, lo: int, hi: int) -> list[tuple]:
    """Exponent tuples of total degree ``lo..hi`` (graded)."""
    out = []
    for d in range(lo, hi + 1):
        for c in itertools.combinations_with_replacement(range(nx), d):
            e = [0] * nx
            for i in c:
                e[i] += 1
            out.append(tuple(e))
    return out


class _Space:
    """Coefficient vectors over all monomials of degree ``<= D`` and the linear maps on them."""

    def __init__(self, nx: int, D: int):
        self.nx, self.D = nx, D
        self.monos = _monomials(nx, 0, D)
        self.index = {e: k for k, e in enumerate(self.monos)}
        self.N = len(self.monos)

    def vec(self, p: dict) -> np.ndarray:
        v = np.zeros(self.N)
        for e, c in p.items():
            if sum(e) > self.D:
                raise ValueError(f"degree {sum(e)} exceeds the SOS degree {self.D}")
            v[self.index[e]] += c
        return v

    def poly(self, v: np.ndarray) -> dict:
        return {e: float(c) for e, c in zip(self.monos, v) if c != 0.0}

    def gram(self, basis: list[tuple]):
        """Sparse map ``vec(Q)`` (column-major) -> coefficients of ``zᵀ Q z``."""
        from scipy.sparse import coo_matrix

        m = len(basis)
        rows, cols = [], []
        for i, j in itertools.product(range(m), range(m)):
            e = tuple(a + b for a, b in zip(basis[i], basis[j]))
            rows.append(self.index[e])
            cols.append(i + j * m)
        return coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(self.N, m * m)).tocsr()

    def mul(self, p: dict, max_in: int | None = None):
        """Sparse map ``q -> p q`` (for ``q`` of degree ``<= max_in``)."""
        from scipy.sparse import coo_matrix

        rows, cols, vals = [], [], []
        for j, e in enumerate(self.monos):
            if max_in is not None and sum(e) > max_in:
                continue
            for ep, c in p.items():
                t = tuple(a + b for a, b in zip(e, ep))
                if sum(t) > self.D:
                    raise ValueError("product exceeds the SOS degree")
                rows.append(self.index[t])
                cols.append(j)
                vals.append(c)
        return coo_matrix((vals, (rows, cols)), shape=(self.N, self.N)).tocsr()

    def lie(self, f: list[dict], max_in: int):
        """Sparse map ``V -> ∇V · f`` (for ``V`` of degree ``<= max_in``)."""
        from scipy.sparse import coo_matrix

        rows, cols, vals = [], [], []
        for j, e in enumerate(self.monos):
            if sum(e) > max_in or sum(e) == 0:
                continue
            for i in range(self.nx):
                if e[i] == 0:
                    continue
                d = list(e)
                d[i] -= 1
                for ep, c in f[i].items():
                    t = tuple(a + b for a, b in zip(d, ep))
                    rows.append(self.index[t])
                    cols.append(j)
                    vals.append(e[i] * c)
        return coo_matrix((vals, (rows, cols)), shape=(self.N, self.N)).tocsr()


def _vec(Q):
    import cvxpy as cp

    return cp.vec(Q, order="F")


def _even_up(d: int) -> int:
    return d + (d % 2)


@dataclass
class SOSLevel:
    """Result of :func:`sos_level` (an SDP candidate, not a certificate)."""

    level: float            # largest feasible level found (0 if none)
    multiplier: dict        # s at that level
    solves: int
    upper: float            # smallest infeasible level tried (or the sampled bound)
    backoff_level: float    # (1 - backoff)·level, where an interior multiplier was found
    backoff_multiplier: dict


def _sampled_upper(V: Polynomial, f: list[Polynomial], radius: float, inner: float) -> float:
    """Least ``V`` over grid points with ``V̇ ≥ 0`` (an upper bound of any certified level)."""
    g = np.linspace(-radius, radius, 241)
    X = np.stack(np.meshgrid(*[g] * V.nx, indexing="ij"), -1).reshape(-1, V.nx)
    X = X[np.linalg.norm(X, axis=1) >= inner]
    h = 1e-6
    fx = np.stack([p(X) for p in f], axis=1)
    grad = np.stack([(V(X + h * np.eye(V.nx)[i]) - V(X - h * np.eye(V.nx)[i])) / (2 * h)
                     for i in range(V.nx)], axis=1)
    bad = np.einsum("ij,ij->i", grad, fx) >= 0
    return float(V(X[bad]).min()) if bad.any() else float(V(X).max())


def sos_level(V: Polynomial, f: list[Polynomial], *, multiplier_degree: int | None = None,
              epsilon: float = 1e-6, upper: float | None = None, radius: float = 3.0,
              rtol: float = 1e-4, backoff: float = 0.0,
              solver: str = "CLARABEL") -> SOSLevel:
    r"""Largest level ``c`` with :math:`-\dot V - \epsilon\|x\|^2 - s(c - V) \in \Sigma`,
    :math:`s \in \Sigma` (bisection on ``c``, one SDP per step).

    Parameters
    ----------
    V : Polynomial            the Lyapunov candidate (``V(0) = 0``)
    f : list of Polynomial    the polynomial closed loop
    multiplier_degree : int, optional   degree of ``s`` (default: the least that matches)
    epsilon : float           strictness of the decrease
    upper : float, optional   bisection upper end (default: a sampled bound, times 1.01)
    radius : float            half-width of the sampling box for the default ``upper``
    rtol : float              relative width of the final bisection interval
    backoff : float           if > 0, re-solve at ``(1 - backoff)·c`` for an interior ``s``

    Returns
    -------
    SOSLevel
        ``level`` (0 if no level is feasible), ``multiplier`` (``s`` as a dict), ``solves``,
        ``upper`` (least infeasible level tried), ``backoff_level`` and
        ``backoff_multiplier``.
    """
    import cvxpy as cp

    nx = V.nx
    dV = V.degree
    df = max(p.degree for p in f)
    dVdot = dV + df - 1
    ds = multiplier_degree or max(2, _even_up(dVdot - dV))
    D = _even_up(max(dVdot, dV + ds))
    sp = _Space(nx, D)
    vpoly = V.to_dict()
    fpolys = [p.to_dict() for p in f]
    vv = sp.vec(vpoly)
    lieV = sp.lie(fpolys, dV) @ vv
    r2 = sp.vec({tuple(2 * (np.arange(nx) == i)): 1.0 for i in range(nx)})
    zs = _monomials(nx, 1, ds // 2)
    zq = _monomials(nx, 1, D // 2)
    S = cp.Variable((len(zs), len(zs)), PSD=True)
    Q = cp.Variable((len(zq), len(zq)), PSD=True)
    c = cp.Parameter(nonneg=True)
    s = sp.gram(zs) @ _vec(S)
    MV = sp.mul(vpoly, ds)
    lhs = -lieV - epsilon * r2 - c * s + MV @ s
    prob = cp.Problem(cp.Minimize(0), [lhs == sp.gram(zq) @ _vec(Q)])

    def feasible(level: float):
        c.value = level
        if not _solve(prob, solver):
            return None
        return sp.poly(sp.gram(zs) @ S.value.ravel(order="F"))

    hi = upper if upper is not None else 1.01 * _sampled_upper(V, f, radius, 1e-2)
    lo, s_lo, solves = 0.0, {}, 0
    for _ in range(20):  # the upper end must be infeasible: double it until it is
        out = feasible(hi)
        solves += 1
        if out is None:
            break
        lo, s_lo, hi = hi, out, 2.0 * hi
    while hi - lo > rtol * max(hi, 1e-12):
        mid = 0.5 * (lo + hi)
        out = feasible(mid)
        solves += 1
        if out is None:
            hi = mid
        else:
            lo, s_lo = mid, out
        if solves > 60:
            break
    s_back, level_back = s_lo, lo
    if backoff > 0 and lo > 0:
        out = feasible(lo * (1 - backoff))
        solves += 1
        if out is not None:
            s_back, level_back = out, lo * (1 - backoff)
    return SOSLevel(lo, s_lo, solves, hi, level_back, s_back)


def _v_step(V: Polynomial, inside: np.ndarray, level: float, s: dict, f: list[Polynomial],
            degree: int, targets: np.ndarray, *, epsilon: float,
            solver: str) -> Polynomial | None:
    """The ``V`` step of the V–s iteration (``s`` and ``level`` fixed); ``None`` if it fails.

    ``inside``: boundary points of the previous set, kept with ``V ≤ level``; ``targets``:
    points just outside it, where the mean of ``V`` is minimised.
    """
    import cvxpy as cp

    nx = V.nx
    df = max(p.degree for p in f)
    ds = max(sum(e) for e in s) if s else 2
    dVdot = degree + df - 1
    D = _even_up(max(dVdot, degree + ds))
    sp = _Space(nx, D)
    fpolys = [p.to_dict() for p in f]
    r2 = sp.vec({tuple(2 * (np.arange(nx) == i)): 1.0 for i in range(nx)})
    zv = _monomials(nx, 1, degree // 2)
    G = cp.Variable((len(zv), len(zv)), PSD=True)
    v = sp.gram(zv) @ _vec(G) + epsilon * r2
    zq = _monomials(nx, 1, D // 2)
    Q = cp.Variable((len(zq), len(zq)), PSD=True)
    svec = sp.vec(s)
    dec = (-sp.lie(fpolys, degree) @ v - epsilon * r2 - level * svec
           + sp.mul(s, degree) @ v)
    cons = [dec == sp.gram(zq) @ _vec(Q)]
    # the previous set stays inside (sampled on its boundary: a heuristic for monotone
    # growth, not part of any claim), and V is pushed down just outside it
    Zin = _monomial_matrix(inside, sp.monos)
    Zout = _monomial_matrix(targets, sp.monos)
    cons.append(Zin @ v <= level)
    prob = cp.Problem(cp.Minimize(cp.sum(Zout @ v) / len(targets)), cons)
    if not _solve(prob, solver):
        return None
    coeffs = np.asarray(v.value).ravel()
    return Polynomial.from_dict(sp.poly(_clean(coeffs)), nx)


def _monomial_matrix(X: np.ndarray, monos: list[tuple]) -> np.ndarray:
    """``Z[k, j] = X[k]^monos[j]``."""
    E = np.array(monos, dtype=int)
    return np.prod(X[:, None, :] ** E[None, :, :], axis=2)


def _solve(prob, solver: str) -> bool:
    """Solve; ``True`` only for status ``optimal`` (inaccurate solutions count as failures)."""
    import warnings

    import cvxpy as cp

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            prob.solve(solver=solver)
    except cp.SolverError:
        return False
    except BaseException as err:  # Clarabel's Rust panics derive from BaseException
        if type(err).__name__ != "PanicException":
            raise
        return False
    return prob.status == cp.OPTIMAL


def _clean(c: np.ndarray, tol: float = 1e-10) -> np.ndarray:
    c = c.copy()
    c[np.abs(c) < tol * max(np.abs(c).max(), 1.0)] = 0.0
    return c


def _boundary_points(V: Polynomial, level: float, n_dirs: int = 180,
                     r_max: float = 50.0) -> np.ndarray:
    """Points where rays from the origin first reach ``V = level`` (shape ``(n_dirs, nx)``).

    Two-dimensional directions are evenly spaced; in higher dimension they are random
    (seeded).
    """
    nx = V.nx
    if nx == 2:
        th = np.linspace(0, 2 * np.pi, n_dirs, endpoint=False)
        dirs = np.stack([np.cos(th), np.sin(th)], axis=1)
    else:
        d = np.random.default_rng(0).standard_normal((n_dirs, nx))
        dirs = d / np.linalg.norm(d, axis=1, keepdims=True)
    radii = np.geomspace(1e-3, r_max, 400)
    vals = V((dirs[:, None, :] * radii[None, :, None]).reshape(-1, nx)).reshape(n_dirs, -1)
    above = vals > level
    first = np.where(above.any(axis=1), above.argmax(axis=1), len(radii) - 1)
    lo = radii[np.maximum(first - 1, 0)]
    hi = radii[first]
    for _ in range(40):  # bisection along each ray
        mid = 0.5 * (lo + hi)
        up = V(dirs * mid[:, None]) > level
        hi = np.where(up, mid, hi)
        lo = np.where(up, lo, mid)
    return dirs * hi[:, None]


# --------------------------------------------------------------------------- results
@dataclass
class SOSResult:
    r"""Result of :func:`sos_roa`.

    Attributes
    ----------
    status : str
        ``"certified"``; ``"not applicable: <reason>"`` (non-polynomial closed loop);
        or why no level was certified.
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
    inner_ellipse : dict or None
        Condition (c), from :func:`nlyap_opt.roa.certify_inner_ellipse`.
    history : list of dict
        One entry per V–s iteration (``degree``, ``sdp_level``, ``seconds``, ``area``).
    certificate : nlyap_opt.roa.LevelCertificate or None
    sdp_seconds, certify_seconds : float
    """

    status: str
    degree: int
    V: Polynomial | None = None
    sdp_level: float = 0.0
    certified_level: float = 0.0
    seconds: float = 0.0
    notes: list = field(default_factory=list)
    inner: float = 0.0
    outer: float = 0.0
    inner_ellipse: dict | None = None
    history: list = field(default_factory=list)
    certificate: object = None
    sdp_seconds: float = 0.0
    certify_seconds: float = 0.0

    @property
    def certified(self) -> bool:
        return self.status == "certified"

    def casadi(self, x):
        """``V`` as a CasADi expression of ``x``."""
        if self.V is None:
            raise ValueError(f"no V in this result (status: {self.status})")
        return self.V.casadi(x)

    def mask(self, points) -> np.ndarray:
        """Boolean: which ``(N, nx)`` points lie in the certified set (all ``False`` if none)."""
        pts = np.atleast_2d(np.asarray(points, dtype=float))
        out = np.zeros(len(pts), dtype=bool)
        if not self.certified:
            return out
        out |= (np.linalg.norm(pts, axis=1) <= self.outer) & (self.V(pts) <= self.certified_level)
        e = self.inner_ellipse
        if e is not None and e["status"] == "certified":
            out |= np.einsum("ij,jk,ik->i", pts, e["P"], pts) <= e["level"]
        return out

    def area(self, box=((-3.0, 3.0), (-3.0, 3.0)), n: int = 400) -> float:
        """Area (volume) of the certified set by counting cell centres of an ``n^nx`` grid."""
        from nlyap_opt.roa import grid_area, grid_points

        box = np.asarray(box, dtype=float)
        pts, shape = grid_points(box, n)
        return grid_area(self.mask(pts).reshape(shape), box)

    def to_dict(self) -> dict:
        e = self.inner_ellipse
        return {
            "method": f"SOS (degree {self.degree})",
            "status": self.status, "degree": self.degree,
            "V": None if self.V is None else self.V.as_json(),
            "sdp_level": self.sdp_level, "certified_level": self.certified_level,
            "level": self.certified_level, "certified": self.certified,
            "inner": self.inner, "outer": self.outer, "seconds": self.seconds,
            "sdp_seconds": self.sdp_seconds, "certify_seconds": self.certify_seconds,
            "inner_ellipse": None if e is None else {
                "status": e["status"], "P": np.asarray(e["P"]).tolist(),
                "level": float(e["level"])},
            "history": self.history, "notes": list(self.notes),
        }


# --------------------------------------------------------------------------- entry point
def sos_roa(system, *, degree: int = 2, inner: float = 0.1, controller=None, V0=None,
            multiplier_degree: int | None = None, epsilon: float = 1e-6,
            iterations: int = 20, time_budget: float = 60.0, backoff: float = 0.01,
            push: float = 1.05, solver: str = "CLARABEL",
            outer_margin: float = 0.05, certify: bool = True,
            verify_options: dict | None = None,
            log: Callable[[str], None] | None = None) -> SOSResult:
    r"""SOS estimate of the region of attraction, certified by the interval verifier.

    Steps: (1) the closed loop as exact polynomials (:func:`polynomial_closed_loop`);
    (2) the quadratic :math:`V = x^\top P x` (``P`` from :func:`baselines.lqr.lqr`, or
    ``V0``) and its largest SOS level by bisection (:func:`sos_level`); (3) for
    ``degree > 2`` the V–s iteration (see the module docstring) for at most ``iterations``
    rounds or ``time_budget`` seconds; (4) certification of the final ``(V, c)`` on the
    true CasADi closed loop: :func:`nlyap_opt.roa.certify_level` with ``inner = ε``,
    ``outer = r`` (the ray-sampled extent of :math:`\{V \le c\}` times
    ``1 + outer_margin``), ``margin = 0``, and
    :func:`nlyap_opt.roa.certify_inner_ellipse` for condition (c).

    Parameters
    ----------
    system : systems.System
    degree : {2, 4, 6, ...}
        Degree of ``V`` (even).
    inner : float
        Radius ``ε`` of the excluded ball.
    controller : nlyap_opt.network.Network, optional
        Feedback ``κ`` (``None``: ``u_eq``). Must give a polynomial closed loop.
    V0 : (nx, nx) array_like, optional
        Matrix of the initial quadratic ``V`` (default: the closed-loop Lyapunov matrix).
    multiplier_degree : int, optional
        Degree of the S-procedure multiplier ``s`` (default: the least that matches for the
        level of the quadratic ``V``; two more in the V–s iteration, which needs the room).
    epsilon : float
        Strictness of the SOS decrease and positivity constraints.
    iterations, time_budget : int, float
        Budget of the V–s iteration (``degree > 2``): rounds per degree, seconds in all.
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
    from baselines.lqr import lqr

    say = log or (lambda msg: None)
    t0 = time.perf_counter()
    if degree < 2 or degree % 2:
        raise ValueError(f"degree must be an even integer >= 2, got {degree!r}")
    if not inner > 0:
        raise ValueError(f"inner must be > 0 (condition (c) covers the ball), got {inner}")
    try:
        f = polynomial_closed_loop(system, controller)
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
        return SOSResult("not applicable: " + reason, degree, seconds=time.perf_counter() - t0,
                         notes=[reason], inner=inner)
    nx = system.nx
    P = np.asarray(V0 if V0 is not None else lqr(system).P, dtype=float)
    if P.shape != (nx, nx) or np.min(np.linalg.eigvalsh(0.5 * (P + P.T))) <= 0:
        raise ValueError(f"V0 must be a positive definite ({nx}, {nx}) matrix, got {P}")
    Vq = _quadratic(P)
    radius = 2.0 * float(np.abs(system.state_box).max())
    notes: list[str] = []
    ls = sos_level(Vq, f, multiplier_degree=multiplier_degree, epsilon=epsilon,
                   solver=solver, radius=radius)
    say(f"[sos] quadratic V: SDP level {ls.level:.6g} ({ls.solves} SDPs)")
    history = [{"degree": 2, "round": 0, "sdp_level": ls.level,
                "seconds": time.perf_counter() - t0, "area": _area(Vq, ls.level)}]
    V, level = Vq, ls.level
    if ls.level <= 0:
        notes.append("no positive level is SOS-feasible for the quadratic V")
    elif degree > 2:
        V, level = _vs_iteration(Vq, ls.level, f, degree, history, notes, t0=t0,
                                 multiplier_degree=multiplier_degree, epsilon=epsilon,
                                 iterations=iterations, time_budget=time_budget,
                                 backoff=backoff, push=push, radius=radius, solver=solver,
                                 say=say)
    sdp_seconds = time.perf_counter() - t0
    res = SOSResult("not certified", V.degree, V, level, 0.0, 0.0, notes, inner,
                    history=history, sdp_seconds=sdp_seconds)
    if not certify or level <= 0:
        res.status = "not certified (certify=False)" if level > 0 else "no SOS level"
        res.seconds = time.perf_counter() - t0
        return res
    # ---- re-certification on the true closed loop (the only claim)
    t1 = time.perf_counter()
    from nlyap_opt.roa import certify_inner_ellipse, certify_level
    from nlyap_opt.symbolic import closed_loop

    extent = float(np.linalg.norm(_boundary_points(V, level), axis=1).max())
    res.outer = outer = extent * (1 + outer_margin)
    cl = closed_loop(system, controller, strict=True)
    Vx = V.casadi(cl.x)
    lie = ca.dot(ca.gradient(Vx, cl.x), cl.rhs)
    cert = certify_level(cl.x, Vx, lie, level=level, inner=inner, outer=outer, margin=0.0,
                         verify_options=verify_options,
                         log=(lambda m: say("[sos] certify" + m)))
    res.certificate = cert
    ell = certify_inner_ellipse(system, controller, inner, verify_options=verify_options)
    res.inner_ellipse = ell
    res.certify_seconds = time.perf_counter() - t1
    if cert.status != "certified":
        res.status = f"not certified: {cert.status}"
    elif ell["status"] != "certified":
        res.status = f"not certified: condition (c) {ell['status']}"
    else:
        res.status = "certified"
        res.certified_level = float(cert.level)
    res.seconds = time.perf_counter() - t0
    say(f"[sos] degree {V.degree}: SDP level {level:.6g}, certified {res.certified_level:.6g} "
        f"({res.status}, {res.seconds:.2f} s)")
    return res


def _scaled(V: Polynomial, factor: float) -> Polynomial:
    return Polynomial(V.exponents, V.coefficients * factor)


def _vs_iteration(Vq, level_q, f, degree, history, notes, *, t0, multiplier_degree, epsilon,
                  iterations, time_budget, backoff, push, radius, solver, say):
    """V–s iteration with degree continuation 4, 6, ..., ``degree``; the best ``(V, level)``.

    ``V`` is kept scaled so that its SDP level is 1. Each round: the multiplier ``s`` at
    level ``1 - backoff`` (interior), the ``V`` step, the level of the new ``V`` by bisection.
    The best iterate by area is returned; a stage ends when the area stops growing.
    """
    md = multiplier_degree or max(2, _even_up(max(p.degree for p in f) - 1)) + 2
    V = _scaled(Vq, 1.0 / level_q)
    best = (V, 1.0, history[-1]["area"])
    lev = 1.0 - backoff
    ls = sos_level(V, f, multiplier_degree=md, epsilon=epsilon, solver=solver,
                   upper=lev, rtol=1e-3, backoff=backoff)
    s = ls.backoff_multiplier
    for stage in range(4, degree + 1, 2):
        V = best[0]
        if stage > 4:  # multiplier of the best V of the previous stage
            ls = sos_level(V, f, multiplier_degree=md, epsilon=epsilon, solver=solver,
                           upper=lev, rtol=1e-3, backoff=backoff)
            s = ls.backoff_multiplier
        stalled = 0
        for it in range(iterations):
            if time.perf_counter() - t0 > time_budget:
                notes.append(f"V–s iteration stopped by the time budget ({time_budget} s) at "
                             f"degree {stage}, round {it + 1}")
                return best[0], best[1]
            bnd = _boundary_points(V, lev)
            Vn = _v_step(V, bnd, lev, s, f, stage, push * bnd, epsilon=epsilon,
                         solver=solver)
            if Vn is None:
                notes.append(f"degree {stage}, round {it + 1}: V step infeasible or "
                             "inaccurate; stage ended")
                break
            ls = sos_level(Vn, f, multiplier_degree=md, epsilon=epsilon, solver=solver,
                           radius=radius, upper=lev, rtol=1e-3, backoff=backoff)
            if ls.level <= 0 or not ls.backoff_multiplier:
                notes.append(f"degree {stage}, round {it + 1}: no level for the new V; "
                             "stage ended")
                break
            V, s = _scaled(Vn, 1.0 / ls.level), ls.backoff_multiplier
            area = _area(V, 1.0)
            history.append({"degree": stage, "round": it + 1, "sdp_level": ls.level,
                            "seconds": time.perf_counter() - t0, "area": area})
            say(f"[sos] degree {stage}, round {it + 1}: area ≈ {area:.4g}")
            if area > best[2] * (1 + 1e-3):
                best, stalled = (V, 1.0, area), 0
            else:
                stalled += 1
                if stalled >= 2:
                    break
    return best[0], best[1]


def _quadratic(P: np.ndarray) -> Polynomial:
    """``xᵀ P x`` as a :class:`Polynomial`."""
    nx = P.shape[0]
    terms: dict = {}
    for i, j in itertools.product(range(nx), repeat=2):
        e = [0] * nx
        e[i] += 1
        e[j] += 1
        terms[tuple(e)] = terms.get(tuple(e), 0.0) + float(P[i, j])
    return Polynomial.from_dict(terms, nx)


def _area(V: Polynomial, level: float) -> float:
    """Area (volume) of the star-shaped part of ``{V ≤ level}`` from ray sampling (2-D exact
    up to sampling; a progress measure for the V–s iteration only)."""
    if level <= 0:
        return 0.0
    pts = _boundary_points(V, level, n_dirs=720)
    if V.nx != 2:
        return float(np.mean(np.linalg.norm(pts, axis=1)) ** V.nx)
    r = np.linalg.norm(pts, axis=1)
    return float(0.5 * np.sum(r**2) * (2 * math.pi / len(r)))
