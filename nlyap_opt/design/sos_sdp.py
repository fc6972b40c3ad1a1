r"""The semidefinite programs of the SOS baseline (candidates only; :mod:`nlyap_opt.candidates.sos`
re-certifies every result).

A polynomial :math:`p` is SOS when :math:`p(x) = z(x)^\top Q z(x)` for a vector of monomials
:math:`z` and a Gram matrix :math:`Q \succeq 0`; the identity is imposed by matching the
coefficients of every monomial (no SOS toolbox: cvxpy directly).

- :func:`sos_level`: the largest level ``c`` of a fixed ``V`` with
  :math:`-\dot V - \epsilon\|x\|^2 - s\,(c - V) \in \Sigma`, :math:`s \in \Sigma`
  (bisection on ``c``, one SDP per step);
- :func:`v_step`: the ``V`` step of the V–s iteration (``s`` and ``c`` fixed, linear in ``V``);
- :func:`vs_iteration`: the V–s iteration with degree continuation 4, 6, ...;
- :func:`boundary_points`, :func:`star_area`: ray sampling of :math:`\{V \le c\}` (search
  heuristics of the iteration, no part of any claim);
- :func:`gram_size`: the order of the largest Gram matrix of these programs for a ``V`` of
  a given degree (the size of the SDPs, known before any is solved).
"""

from __future__ import annotations

import contextlib
import itertools
import math
import os
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix

from ..kernel import deps
from .polynomial import Polynomial, monomial_matrix, monomials

__all__ = ["SOSLevel", "boundary_points", "gram_factor", "gram_size", "sos_level", "star_area",
           "v_step", "vs_iteration"]


# --------------------------------------------------------------------------- coefficient space
class _Space:
    """Coefficient vectors over all monomials of degree ``<= D`` and the linear maps on them."""

    def __init__(self, nx: int, D: int):
        self.nx, self.D = nx, D
        self.monos = monomials(nx, 0, D)
        self.index = {e: k for k, e in enumerate(self.monos)}
        self.N = len(self.monos)

    @classmethod
    def for_decrease(cls, nx: int, deg_V: int, deg_f: int, deg_s: int) -> _Space:
        """The space that holds :math:`\\dot V` and :math:`s\\,V` (even degree)."""
        return cls(nx, _even_up(max(deg_V + deg_f - 1, deg_V + deg_s)))

    def vec(self, p: dict) -> np.ndarray:
        v = np.zeros(self.N)
        for e, c in p.items():
            if sum(e) > self.D:
                raise ValueError(f"degree {sum(e)} exceeds the SOS degree {self.D}")
            v[self.index[e]] += c
        return v

    def poly(self, v: np.ndarray) -> dict:
        return {e: float(c) for e, c in zip(self.monos, v) if c != 0.0}

    def squared_norm(self) -> np.ndarray:
        """Coefficients of :math:`\\|x\\|^2`."""
        return self.vec(Polynomial.quadratic(np.eye(self.nx)).to_dict())

    def _sparse(self, rows, cols, vals, ncols):
        return coo_matrix((vals, (rows, cols)), shape=(self.N, ncols)).tocsr()

    def gram(self, basis: list[tuple]):
        """Sparse map ``vec(Q)`` (column-major) -> coefficients of ``zᵀ Q z``."""
        m = len(basis)
        rows, cols = [], []
        for i, j in itertools.product(range(m), range(m)):
            rows.append(self.index[_add(basis[i], basis[j])])
            cols.append(i + j * m)
        return self._sparse(rows, cols, np.ones(len(rows)), m * m)

    def mul(self, p: dict, max_in: int | None = None):
        """Sparse map ``q -> p q`` (for ``q`` of degree ``<= max_in``)."""
        rows, cols, vals = [], [], []
        for j, e in enumerate(self.monos):
            if max_in is not None and sum(e) > max_in:
                continue
            for ep, c in p.items():
                t = _add(e, ep)
                if sum(t) > self.D:
                    raise ValueError("product exceeds the SOS degree")
                rows.append(self.index[t])
                cols.append(j)
                vals.append(c)
        return self._sparse(rows, cols, vals, self.N)

    def lie(self, f: list[dict], max_in: int):
        """Sparse map ``V -> ∇V · f`` (for ``V`` of degree ``<= max_in``)."""
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
                    rows.append(self.index[_add(d, ep)])
                    cols.append(j)
                    vals.append(e[i] * c)
        return self._sparse(rows, cols, vals, self.N)

    def gram_variable(self, degree: int):
        """A PSD Gram matrix over the monomials of degree ``1..degree/2`` and the coefficient
        map of its polynomial: ``(G, M)`` with ``p = M @ vec(G)``."""
        cp = deps.cvxpy()

        z = monomials(self.nx, 1, degree // 2)
        return cp.Variable((len(z), len(z)), PSD=True), self.gram(z)

    def is_sos(self, expr):
        """The constraint ``expr ∈ Σ`` (coefficients of ``expr`` equal those of a Gram form)."""
        Q, M = self.gram_variable(self.D)
        return expr == M @ _vec(Q)


def _add(e1, e2) -> tuple:
    return tuple(a + b for a, b in zip(e1, e2))


def _vec(Q):
    cp = deps.cvxpy()

    return cp.vec(Q, order="F")


def _even_up(d: int) -> int:
    return d + (d % 2)


def _level_multiplier_degree(deg_f: int) -> int:
    """Default degree of the multiplier ``s`` of :func:`sos_level` (the least that matches
    the degree of :math:`\\dot V` of a quadratic ``V``)."""
    return max(2, _even_up(deg_f - 1))


def _vs_multiplier_degree(deg_f: int) -> int:
    """Default degree of ``s`` in :func:`vs_iteration` (two more: the V step needs room)."""
    return _level_multiplier_degree(deg_f) + 2


def gram_size(nx: int, degree: int, deg_f: int) -> int:
    r"""Order of the largest Gram matrix that :func:`sos_level` and :func:`vs_iteration`
    set up, with their default multiplier degrees, for a ``V`` of ``degree`` and a closed
    loop of degree ``deg_f`` in ``nx`` states.

    The decrease constraint :math:`-\dot V - \epsilon\|x\|^2 - s\,(c - V) \in \Sigma`
    has degree :math:`D = \max(\deg V + \deg f - 1, \deg V + \deg s)` (rounded up to
    even); its Gram matrix is indexed by the monomials of degree ``1..D/2``:
    :math:`\binom{nx + D/2}{nx} - 1` of them. ``degree = 2`` is the level bisection of the
    quadratic ``V`` only; a larger degree adds the V–s iteration up to it. The cost of each
    SDP grows with this order (the PSD cone has :math:`m(m+1)/2` entries), so it measures
    what a degree costs before anything is solved.

    Examples
    --------
    >>> gram_size(2, 6, 3), gram_size(3, 4, 3), gram_size(3, 4, 4), gram_size(4, 4, 3)
    (20, 34, 55, 69)
    """
    if degree < 2 or degree % 2 or nx < 1 or deg_f < 1:
        raise ValueError(f"need nx >= 1, an even degree >= 2 and deg_f >= 1, got nx = {nx}, "
                         f"degree = {degree}, deg_f = {deg_f}")
    D = _even_up(max(2 + deg_f - 1, 2 + _level_multiplier_degree(deg_f)))
    if degree > 2:
        D = max(D, _even_up(max(degree + deg_f - 1, degree + _vs_multiplier_degree(deg_f))))
    return math.comb(nx + D // 2, nx) - 1


@contextlib.contextmanager
def _stderr_held():
    """Hold what native code writes to file descriptor 2 (a Rust panic's message and, under
    ``RUST_BACKTRACE``, its backtrace); yields a list whose first item, set to ``True`` by
    the caller, drops it, else it is written out unchanged afterwards (also when an
    exception passes)."""
    drop = [False]
    with contextlib.suppress(AttributeError, OSError, ValueError):
        sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:                       # no file descriptor 2: nothing to hold
        yield drop
        return
    try:
        with tempfile.TemporaryFile() as tmp:
            os.dup2(tmp.fileno(), 2)
            try:
                yield drop
            finally:
                with contextlib.suppress(AttributeError, OSError, ValueError):
                    sys.stderr.flush()
                os.dup2(saved, 2)
                if not drop[0]:
                    tmp.seek(0)
                    text = tmp.read()
                    if text:
                        os.write(2, text)
    finally:
        os.close(saved)


def _solve(prob, solver: str, *, inaccurate: bool = False) -> bool:
    """Solve; ``True`` for status ``optimal``, and for ``optimal_inaccurate`` only with
    ``inaccurate`` (the V step, whose solution is a search direction, never a level).

    A solver that fails -- cvxpy's ``SolverError``, or a panic inside Clarabel's Rust code
    (eigenvalue failures on badly scaled SOS programs of degree 4 in 3-D) -- counts as an
    infeasible program; the panic's message is not printed (it is no error of the run:
    the V-s iteration keeps its last good ``V``)."""
    cp = deps.cvxpy()

    with _stderr_held() as drop:
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                prob.solve(solver=solver)
        except cp.SolverError:
            return False
        except BaseException as err:  # Clarabel's Rust panics derive from BaseException
            if type(err).__name__ != "PanicException":
                raise
            drop[0] = True
            return False
    return prob.status == cp.OPTIMAL or (inaccurate and prob.status == cp.OPTIMAL_INACCURATE)


def _clean(c: np.ndarray, tol: float = 1e-10) -> np.ndarray:
    c = c.copy()
    c[np.abs(c) < tol * max(np.abs(c).max(), 1.0)] = 0.0
    return c


# --------------------------------------------------------------------------- level of a fixed V
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

    If it holds, :math:`\dot V(x) \le -\epsilon\|x\|^2 < 0` on
    :math:`\{V \le c\} \setminus \{0\}` (up to the solver's tolerances: a candidate).

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
    solver : str              cvxpy SDP solver

    Returns
    -------
    SOSLevel
        ``level`` (0 if no level is feasible), ``multiplier`` (``s`` as a dict), ``solves``,
        ``upper`` (least infeasible level tried), ``backoff_level`` and
        ``backoff_multiplier``.
    """
    cp = deps.cvxpy()

    dV = V.degree
    df = max(p.degree for p in f)
    ds = multiplier_degree or _level_multiplier_degree(df)
    sp = _Space.for_decrease(V.nx, dV, df, ds)
    vpoly = V.to_dict()
    lieV = sp.lie([p.to_dict() for p in f], dV) @ sp.vec(vpoly)
    S, MS = sp.gram_variable(ds)
    c = cp.Parameter(nonneg=True)
    s = MS @ _vec(S)
    lhs = -lieV - epsilon * sp.squared_norm() - c * s + sp.mul(vpoly, ds) @ s
    prob = cp.Problem(cp.Minimize(0), [sp.is_sos(lhs)])

    def feasible(level: float):
        c.value = level
        if not _solve(prob, solver):
            return None
        return sp.poly(MS @ S.value.ravel(order="F"))

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


# --------------------------------------------------------------------------- V–s iteration
def v_step(V: Polynomial, inside: np.ndarray, level: float, s: dict, f: list[Polynomial],
           degree: int, targets: np.ndarray, *, epsilon: float,
           solver: str, outside: np.ndarray | None = None) -> Polynomial | None:
    r"""The ``V`` step of the V–s iteration (``s`` and ``level`` fixed); ``None`` if it fails.

    .. math::
        V - \epsilon\|x\|^2 \in \Sigma, \qquad
        -\dot V - \epsilon\|x\|^2 - s\,(c - V) \in \Sigma, \qquad
        V(y_k) \le c \ \ \forall y_k \in \text{inside},

    minimising the mean of ``V`` over ``targets``. ``inside``: boundary points of the
    previous set (kept with ``V ≤ level``: a heuristic for monotone growth, no part of any
    claim); ``targets``: points just outside it; ``outside`` (optional): points where
    ``V ≥ level`` is asked (samples of the boundary of a domain the set should stay in;
    also a heuristic, the certificate checks containment itself).
    """
    cp = deps.cvxpy()

    nx = V.nx
    ds = max(sum(e) for e in s) if s else 2
    sp = _Space.for_decrease(nx, degree, max(p.degree for p in f), ds)
    r2 = sp.squared_norm()
    G, MG = sp.gram_variable(degree)
    v = MG @ _vec(G) + epsilon * r2
    dec = (-sp.lie([p.to_dict() for p in f], degree) @ v - epsilon * r2 - level * sp.vec(s)
           + sp.mul(s, degree) @ v)
    cons = [sp.is_sos(dec), monomial_matrix(inside, sp.monos) @ v <= level]
    if outside is not None and len(outside):
        cons.append(monomial_matrix(outside, sp.monos) @ v >= level)
    Zout = monomial_matrix(targets, sp.monos)
    prob = cp.Problem(cp.Minimize(cp.sum(Zout @ v) / len(targets)), cons)
    if not _solve(prob, solver, inaccurate=True):
        return None
    coeffs = np.asarray(v.value).ravel()
    if not np.all(np.isfinite(coeffs)):      # an inaccurate step may return no usable V
        return None
    return Polynomial.from_dict(sp.poly(_clean(coeffs)), nx)


def vs_iteration(Vq: Polynomial, level_q: float, f: list[Polynomial], degree: int,
                 history: list, notes: list, *, t0: float, multiplier_degree: int | None,
                 epsilon: float, iterations: int, backoff: float,
                 push: float, radius: float, solver: str,
                 say: Callable[[str], None],
                 area_scale: float = 1.0,
                 outside: np.ndarray | None = None,
                 keep_margin: float = 0.2,
                 edge: np.ndarray | None = None) -> tuple[Polynomial, float]:
    """V–s iteration with degree continuation 4, 6, ..., ``degree``; the best ``(V, level)``.

    ``V`` is kept scaled so that its SDP level is 1. Each round: the multiplier ``s`` at
    level ``1 - backoff`` (interior), the ``V`` step, the level of the new ``V`` by bisection.
    The best iterate by area is returned; a stage ends when the area stops growing. With
    ``edge`` (samples of the boundary of the domain ``D`` the certificate must lie in) the
    area is that of ``{V ≤ min(1, least V on edge)}``, the part of the set a certificate in
    ``D`` can keep: a set grown across ``∂D`` does not count as growth.
    ``history`` and ``notes`` are appended to (areas times ``area_scale``: the data may be
    in scaled units). With ``outside`` (samples of the boundary of a domain ``D``), the
    sets grow inside ``D`` instead of across its boundary: each level (the quadratic's
    too) is capped at ``1 - keep_margin`` times the least ``V`` on them (the margin leaves
    the next V step room between the previous set and ``∂D``) and each V step asks
    ``V ≥ level`` there; the level returned is the uncapped one, the lesser of the SDP
    level and the least ``V`` on ``outside`` (an S-procedure multiplier of a level also
    serves every lower level).
    """
    md = multiplier_degree or _vs_multiplier_degree(max(p.degree for p in f))
    lev = 1.0 - backoff

    def level_of(V, **kw):
        return sos_level(V, f, multiplier_degree=md, epsilon=epsilon, solver=solver,
                         upper=lev, rtol=1e-3, backoff=backoff, **kw)

    def capped(V: Polynomial, level: float) -> tuple[float, float]:
        """The level V is scaled by, and the full level in the scaled V's units."""
        if outside is None:
            return level, 1.0
        least = float(V(outside).min())
        scale = min(level, (1.0 - keep_margin) * least)
        return scale, min(level, least) / scale

    def area_of(V: Polynomial) -> float:
        top = 1.0 if edge is None else min(1.0, float(V(edge).min()))
        return star_area(V, top)

    scale, full = capped(Vq, level_q)
    if not scale > 0:
        notes.append("the quadratic V is not positive on the domain's boundary")
        return Vq.scaled(1.0 / level_q), 1.0
    if scale < level_q:
        say(f"[sos] the quadratic's level {level_q:.6g} capped at {scale:.6g} inside the "
            "domain")
    V = Vq.scaled(1.0 / scale)
    best = (V, full, area_of(V))
    s = level_of(V).backoff_multiplier
    for stage in range(4, degree + 1, 2):
        V = best[0]
        if stage > 4:  # multiplier of the best V of the previous stage
            s = level_of(V).backoff_multiplier
        stalled = 0
        for it in range(iterations):
            bnd = boundary_points(V, lev)
            Vn = v_step(V, bnd, lev, s, f, stage, push * bnd, epsilon=epsilon, solver=solver,
                        outside=outside)
            if Vn is None:
                notes.append(f"degree {stage}, round {it + 1}: V step infeasible or "
                             "failed; stage ended")
                break
            ls = level_of(Vn, radius=radius)
            if ls.level <= 0 or not ls.backoff_multiplier:
                notes.append(f"degree {stage}, round {it + 1}: no level for the new V; "
                             "stage ended")
                break
            scale, full = capped(Vn, ls.level)
            if not scale > 0:
                notes.append(f"degree {stage}, round {it + 1}: the new V is not positive on "
                             "the domain's boundary; stage ended")
                break
            V, s = Vn.scaled(1.0 / scale), ls.backoff_multiplier
            area = area_of(V)
            history.append({"degree": stage, "round": it + 1, "sdp_level": ls.level,
                            "seconds": time.perf_counter() - t0, "area": area * area_scale})
            say(f"[sos] degree {stage}, round {it + 1}: area of {{V ≤ 1}}"
                f"{'' if edge is None else ' inside D'} ≈ {area * area_scale:.4g} (the SDP's "
                "estimate, before the level is verified)")
            if area > best[2] * (1 + 1e-3):
                best, stalled = (V, full, area), 0
            else:
                stalled += 1
                if stalled >= 2:
                    break
    return best[0], best[1]


# --------------------------------------------------------------------------- ray sampling
def boundary_points(V: Polynomial, level: float, n_dirs: int = 180,
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


def star_area(V: Polynomial, level: float) -> float:
    """Area (volume) of the star-shaped part of ``{V ≤ level}`` from ray sampling (2-D exact
    up to sampling; a progress measure for the V–s iteration only)."""
    if level <= 0:
        return 0.0
    pts = boundary_points(V, level, n_dirs=720)
    if V.nx != 2:
        return float(np.mean(np.linalg.norm(pts, axis=1)) ** V.nx)
    r = np.linalg.norm(pts, axis=1)
    return float(0.5 * np.sum(r**2) * (2 * math.pi / len(r)))


# --------------------------------------------------------------------------- Gram factor
def gram_factor(V: Polynomial, *, solver: str = "CLARABEL") -> tuple[list[tuple], np.ndarray]:
    r"""A factor ``L`` with :math:`V(x) \approx \|L\,z(x)\|^2`, ``z`` the monomials of degree
    ``1..deg V / 2``.

    One SDP: a Gram matrix :math:`Q \succeq tI` with :math:`z^\top Q z = V` coefficient by
    coefficient, maximising ``t`` (the most interior one, so that rounding its eigenvalues
    at 0 changes little); ``L = diag(√λ) Uᵀ`` from its eigenvalues ``λ`` clipped at 0.
    For a starting point of training (:func:`nlyap_opt.candidates.learning.sos_start`), never for a
    claim.

    Returns
    -------
    z : list of tuple
        The exponents of the monomials.
    L : (len(z), len(z)) ndarray

    Raises
    ------
    ValueError
        ``V`` has odd degree, a constant or linear term, or no Gram matrix was found.
    """
    cp = deps.cvxpy()

    if V.degree % 2 or V.degree < 2:
        raise ValueError(f"a Gram factor needs an even degree >= 2, got {V.degree}")
    if np.any(V.exponents.sum(axis=1) < 2):
        raise ValueError("V has a constant or linear term: it is no Gram form of monomials "
                         "of degree >= 1")
    space = _Space(V.nx, V.degree)
    z = monomials(V.nx, 1, V.degree // 2)
    Q = cp.Variable((len(z), len(z)), symmetric=True)
    t = cp.Variable()
    prob = cp.Problem(cp.Maximize(t), [space.gram(z) @ _vec(Q) == space.vec(V.to_dict()),
                                       Q - t * np.eye(len(z)) >> 0, t <= 1.0])
    if not _solve(prob, solver) or Q.value is None:
        raise ValueError(f"no Gram matrix of V was found (solver status {prob.status})")
    lam, U = np.linalg.eigh(0.5 * (Q.value + Q.value.T))
    return z, np.sqrt(np.clip(lam, 0.0, None))[:, None] * U.T
