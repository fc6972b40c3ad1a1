r"""Verification domains ``D`` and initial sets ``X_I``: a ball, a box or an ellipsoid.

General domains: with a domain ``D`` in place of the ball :math:`B_r`,
:math:`\Omega_c = \{x \in D : V(x) \le c\}`; (a) the decrease holds on
:math:`\Omega_c \setminus B_\varepsilon`; (b) :math:`V > c` on :math:`\partial D` (every face
of a box); an initial set :math:`X_I \subseteq D` is certified when :math:`V < c` on it.

A set is one of

- :class:`Ball` ``{‖x − centre‖ ≤ radius}``;
- :class:`Box` ``{lo ≤ x ≤ hi}``;
- :class:`Ellipsoid` ``{(x − centre)ᵀ Q (x − centre) ≤ 1}`` (``Q`` symmetric positive
  definite; :meth:`Ellipsoid.from_semi_axes` for an axis-aligned one).

Each gives what the verifier, the level NLP, training and the plots need: its constraints
``g(x) ≤ 0`` as CasADi expressions, the pieces of its boundary as verification regions, a
bounding box, uniform samples of the set (minus an inner ball) and of its boundary, a
membership test and its JSON form. :func:`parse_set` reads the run-configuration form
(``{"type": "box", "box": [[lo, hi], ...]}``, ...), refusing anything else with the fix.
A domain ``D`` must hold the origin in its interior; an initial set need not.
"""

from __future__ import annotations

import math

import casadi as ca
import numpy as np

from .errors import ConfigError
from .sampling import sample_ball, sample_sphere

__all__ = ["Region", "Ball", "Box", "Ellipsoid", "parse_set", "as_domain", "SET_FORMS"]

#: the accepted JSON forms (for error messages and the config reference)
SET_FORMS = ('{"type": "ball", "radius": R[, "centre": [...]]}',
             '{"type": "box", "box": [[lo, hi], ...]}',
             '{"type": "ellipsoid", "semi_axes": [a1, ...][, "centre": [...]]}',
             '{"type": "ellipsoid", "matrix": Q[, "centre": [...]]} (xᵀQx <= 1)')


class Region:
    """A closed set of states (base class of :class:`Ball`, :class:`Box`, :class:`Ellipsoid`)."""

    kind = ""
    n: int
    #: the origin-centred ball ``‖x‖ ≤ r``: the default region, kept in its original form
    #: (one ``‖x‖² ≤ r²`` row in the level NLP, ``ε ≤ ‖x‖ ≤ r`` in texts)
    plain_ball = False

    # ------------------------------------------------------------------ geometry
    def bounding_box(self) -> np.ndarray:
        """``(n, 2)`` box containing the set."""
        raise NotImplementedError

    def contains(self, pts, tol: float = 0.0) -> np.ndarray:
        """Boolean mask of the ``(N, n)`` points inside the (closed) set, grown by ``tol``."""
        raise NotImplementedError

    def inradius(self) -> float:
        """Distance from the origin to the boundary (``≤ 0`` if 0 is not inside)."""
        raise NotImplementedError

    def max_norm(self) -> float:
        """``max ‖x‖`` over the set (an upper bound)."""
        box = self.bounding_box()
        return float(np.linalg.norm(np.max(np.abs(box), axis=1)))

    def gauge(self, pts, iterations: int = 40) -> np.ndarray:
        """Minkowski gauge ``inf {t > 0 : x/t ∈ D}`` of each ``(N, n)`` point about the
        origin (``< 1`` inside, ``1`` on the boundary of a convex ``D`` holding 0), by
        bisection on :meth:`contains` (to ``2⁻⁴⁰`` relative; used to shape training targets,
        never in a proof)."""
        x = np.asarray(pts, dtype=float)
        lo, hi = np.zeros(len(x)), np.full(len(x), 1.0)
        for _ in range(64):   # grow hi until x/hi lies in D (2⁶⁴: a point out of reach)
            out = ~self.contains(x / hi[:, None])
            if not out.any():
                break
            hi[out] *= 2.0
        else:
            hi[~self.contains(x / hi[:, None])] = np.inf
        for _ in range(iterations):
            mid = 0.5 * (lo + hi)
            inside = self.contains(x / np.maximum(mid, 1e-300)[:, None])
            hi, lo = np.where(inside, mid, hi), np.where(inside, lo, mid)
        return hi

    # ------------------------------------------------------------------ symbolic
    def constraints(self, x) -> list:
        """``[(g, name)]`` with the set ``= {x in bounding_box : g(x) ≤ 0 for all g}``."""
        raise NotImplementedError

    def inequalities(self, x) -> list:
        """``[(g, name)]`` with the set ``= {x : g(x) ≤ 0}`` (no root box needed)."""
        return self.constraints(x)

    def boundary_pieces(self, x) -> list:
        """The boundary as verification regions: ``[(box, [(g, name), ...], label)]``."""
        raise NotImplementedError

    def boundary_nlp(self, x) -> list:
        """The boundary as NLP pieces for the level search
        (:func:`nlyap_opt.certification.roa.candidate_level`): dicts with ``g`` (or ``None``),
        ``lbg``/``ubg`` and/or ``lbx``/``ubx``, ``on(pts)`` (which boundary samples lie on the
        piece: its starting points) and ``check(xs)``
        (the solution lies on the piece)."""
        raise NotImplementedError

    # ------------------------------------------------------------------ sampling
    def sample(self, n: int, rng: np.random.Generator, inner: float = 0.0) -> np.ndarray:
        """``n`` uniform samples of the set minus the open ball ``‖x‖ < inner``."""
        raise NotImplementedError

    def sample_boundary(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` samples of the boundary."""
        raise NotImplementedError

    # ------------------------------------------------------------------ text, JSON
    def describe(self) -> str:
        raise NotImplementedError

    def to_dict(self) -> dict:
        raise NotImplementedError

    def outline_2d(self, i: int = 0, j: int = 1, m: int = 200) -> np.ndarray:
        """``(m, 2)`` closed curve: the boundary of the slice through 0 in axes ``i, j``."""
        raise NotImplementedError

    def __eq__(self, other):
        return isinstance(other, Region) and self.to_dict() == other.to_dict()

    def __repr__(self):
        return f"{type(self).__name__}({self.describe()})"


def _outward(lo, hi) -> np.ndarray:
    """``(n, 2)`` rows ``[lo, hi]``, each bound moved one ulp outwards (rounding)."""
    return np.stack([np.nextafter(lo, -np.inf), np.nextafter(hi, np.inf)], axis=1)


def _reject_inner(draw, n: int, rng, inner: float) -> np.ndarray:
    """``n`` points of ``draw(k, rng)`` with ``‖x‖ ≥ inner`` (vectorised rejection)."""
    if inner <= 0:
        return draw(n, rng)
    out, got = [], 0
    for _ in range(64):
        p = draw(max(2 * (n - got), 64), rng)
        p = p[np.linalg.norm(p, axis=1) >= inner]
        out.append(p)
        got += len(p)
        if got >= n:
            break
    pts = np.vstack(out)
    if len(pts) < n:
        raise ConfigError(f"the set holds almost no point outside the inner ball ‖x‖ < "
                          f"{inner:g}; choose a smaller inner radius")
    return pts[:n]


def _quadratic_gauge(x, Q, c) -> np.ndarray | None:
    """The gauge of ``{(y − c)ᵀQ(y − c) ≤ 1}`` about the origin in closed form, or ``None``
    when the origin is not strictly inside (then :meth:`Region.gauge` bisects).

    ``x/t`` lies in the set iff ``a t² + 2bt − q ≥ 0`` with ``a = 1 − cᵀQc``,
    ``b = cᵀQx``, ``q = xᵀQx``; for ``a > 0`` the gauge is the positive root, written
    without cancellation (``q/(b + d)`` for ``b > 0``, ``(d − b)/a`` otherwise,
    ``d = sqrt(b² + aq)``). Non-finite points are out of reach (``inf``).
    """
    x = np.atleast_2d(np.asarray(x, dtype=float))
    a = 1.0 - float(c @ Q @ c)
    if not a > 0:
        return None
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        q = np.einsum("ij,jk,ik->i", x, Q, x)
        b = np.einsum("ij,j->i", x, Q @ c)     # no BLAS threads: the same bits on any load
        d = np.sqrt(b * b + a * q)
        t = np.where(b > 0, q / np.where(b > 0, b + d, 1.0), (d - b) / a)
    return np.where(np.isfinite(t), t, np.inf)


class Ball(Region):
    """``{‖x − centre‖₂ ≤ radius}``."""

    kind = "ball"

    def __init__(self, radius: float, n: int, centre=None):
        self.radius = float(radius)
        self.n = int(n)
        self.centre = None if centre is None or not np.any(centre) else \
            np.asarray(centre, dtype=float).reshape(self.n)

    @property
    def plain_ball(self):
        return self.centre is None

    def _c(self):
        return np.zeros(self.n) if self.centre is None else self.centre

    def bounding_box(self):
        if self.centre is None:     # exact: [-r, r]
            return np.stack([np.full(self.n, -self.radius), np.full(self.n, self.radius)],
                            axis=1)
        return _outward(self.centre - self.radius, self.centre + self.radius)

    def contains(self, pts, tol=0.0):
        pts = np.atleast_2d(np.asarray(pts, dtype=float))
        if self.centre is not None:
            pts = pts - self.centre
        return np.linalg.norm(pts, axis=1) <= self.radius + tol

    def gauge(self, pts, iterations: int = 40) -> np.ndarray:
        """The gauge in closed form (``‖x‖/r`` when centred at 0); bisection only when the
        origin is not strictly inside."""
        Q = np.eye(self.n) / self.radius ** 2
        g = _quadratic_gauge(pts, Q, self._c())
        return super().gauge(pts, iterations) if g is None else g

    def inradius(self):
        return self.radius - float(np.linalg.norm(self._c()))

    def max_norm(self):
        return self.radius + float(np.linalg.norm(self._c()))

    def _r2(self, x):
        return ca.sumsqr(x if self.centre is None else x - ca.DM(self.centre))

    def constraints(self, x):
        return [(self._r2(x) - self.radius**2, "outer")]

    def boundary_pieces(self, x):
        r2 = self._r2(x)
        return [(self.bounding_box(), [(r2 - self.radius**2, "outer"),
                                       (self.radius**2 - r2, "sphere")], "sphere")]

    def boundary_nlp(self, x):
        r2 = self._r2(x)
        c, R2 = self._c(), self.radius**2
        return [{"g": r2, "lbg": R2, "ubg": R2, "on": lambda p: np.ones(len(p), dtype=bool),
                 "check": lambda xs: abs((xs - c) @ (xs - c) - R2) < 1e-8}]

    def sample(self, n, rng, inner=0.0):
        if self.centre is None:
            return sample_ball(n, self.n, self.radius, rng, inner)
        return _reject_inner(lambda k, g: self.centre + sample_ball(k, self.n, self.radius, g),
                             n, rng, inner)

    def sample_boundary(self, n, rng):
        return self._c() + sample_sphere(n, self.n, self.radius, rng) if self.centre is not None \
            else sample_sphere(n, self.n, self.radius, rng)

    def describe(self):
        if self.centre is None:
            return f"‖x‖ ≤ {self.radius:g}"
        return f"‖x − {self.centre.tolist()}‖ ≤ {self.radius:g}"

    def to_dict(self):
        d = {"type": "ball", "radius": self.radius}
        if self.centre is not None:
            d["centre"] = self.centre.tolist()
        return d

    def outline_2d(self, i=0, j=1, m=200):
        c = self._c()
        rest = np.delete(c, [i, j])
        rr = self.radius**2 - float(rest @ rest)
        th = np.linspace(0, 2 * np.pi, m)
        r = math.sqrt(max(rr, 0.0))
        return np.stack([c[i] + r * np.cos(th), c[j] + r * np.sin(th)], axis=1)


class Box(Region):
    """``{lo ≤ x ≤ hi}`` (componentwise)."""

    kind = "box"

    def __init__(self, box):
        self.box = np.asarray(box, dtype=float).reshape(-1, 2)
        self.n = len(self.box)

    def bounding_box(self):
        return self.box.copy()

    def contains(self, pts, tol=0.0):
        pts = np.atleast_2d(np.asarray(pts, dtype=float))
        return np.all((pts >= self.box[:, 0] - tol) & (pts <= self.box[:, 1] + tol), axis=1)

    def inradius(self):
        return float(np.min(np.minimum(-self.box[:, 0], self.box[:, 1])))

    def gauge(self, pts, iterations: int = 40) -> np.ndarray:
        """The gauge in closed form, ``max_i max(x_i/hi_i, x_i/lo_i)`` (0 strictly inside)."""
        if np.any(self.box[:, 0] >= 0) or np.any(self.box[:, 1] <= 0):
            return super().gauge(pts, iterations)   # 0 on a face: by bisection
        x = np.atleast_2d(np.asarray(pts, dtype=float))
        with np.errstate(invalid="ignore"):
            g = np.max(np.maximum(x / self.box[:, 1], x / self.box[:, 0]), axis=1)
        return np.where(np.isnan(g), np.inf, g)   # a non-finite state: out of reach

    def max_norm(self):
        return float(np.linalg.norm(np.max(np.abs(self.box), axis=1)))

    def constraints(self, x):
        return []           # the box is its own root box

    def inequalities(self, x):
        out = []
        for i, (lo, hi) in enumerate(self.box):
            out += [(x[i] - hi, f"x{i}<={hi:g}"), (lo - x[i], f"x{i}>={lo:g}")]
        return out

    def boundary_pieces(self, x):
        pieces = []
        for i in range(self.n):
            for side, b in (("lower", self.box[i, 0]), ("upper", self.box[i, 1])):
                face = self.box.copy()
                face[i] = [b, b]
                pieces.append((face, [], f"face x{i} = {b:g} ({side})"))
        return pieces

    def boundary_nlp(self, x):
        out = []
        for face, _, _ in self.boundary_pieces(x):
            i = int(np.flatnonzero(face[:, 0] == face[:, 1])[0])
            b = face[i, 0]
            out.append({"g": None, "lbx": face[:, 0], "ubx": face[:, 1],
                        "on": lambda p, i=i, b=b: p[:, i] == b,
                        "check": lambda xs, i=i, b=b: xs[i] == b and bool(
                            self.contains(xs, tol=1e-9)[0])})
        return out

    def _uniform(self, k, rng):
        return self.box[:, 0] + (self.box[:, 1] - self.box[:, 0]) * rng.random((k, self.n))

    def sample(self, n, rng, inner=0.0):
        return _reject_inner(self._uniform, n, rng, inner)

    def sample_boundary(self, n, rng):
        w = self.box[:, 1] - self.box[:, 0]
        area = np.array([np.prod(np.delete(w, i)) for i in range(self.n)])
        face = rng.choice(self.n, size=n, p=area / area.sum())
        side = rng.integers(0, 2, n)
        pts = self._uniform(n, rng)
        pts[np.arange(n), face] = self.box[face, side]
        return pts

    def describe(self):
        return "box " + " × ".join(f"[{lo:g}, {hi:g}]" for lo, hi in self.box)

    def to_dict(self):
        return {"type": "box", "box": self.box.tolist()}

    def outline_2d(self, i=0, j=1, m=200):
        (a, b), (c, d) = self.box[i], self.box[j]
        return np.array([[a, c], [b, c], [b, d], [a, d], [a, c]])


class Ellipsoid(Region):
    """``{(x − centre)ᵀ Q (x − centre) ≤ 1}`` with ``Q`` symmetric positive definite."""

    kind = "ellipsoid"

    def __init__(self, Q, centre=None):
        self.Q = np.asarray(Q, dtype=float)
        self.n = len(self.Q)
        self.centre = None if centre is None or not np.any(centre) else \
            np.asarray(centre, dtype=float).reshape(self.n)
        # x = c + L^{-T} y maps the unit ball onto the ellipsoid (Q = L Lᵀ)
        self._map = np.linalg.inv(np.linalg.cholesky(self.Q)).T

    @classmethod
    def from_semi_axes(cls, axes, centre=None) -> Ellipsoid:
        a = np.asarray(axes, dtype=float).ravel()
        return cls(np.diag(1.0 / a**2), centre)

    def _c(self):
        return np.zeros(self.n) if self.centre is None else self.centre

    def bounding_box(self):
        # half-widths sqrt((Q⁻¹)_ii), widened well beyond the error of the inverse (the
        # verifier's root box must hold the set; the constraint xᵀQx ≤ 1 cuts the rest)
        h = np.sqrt(np.diag(np.linalg.inv(self.Q))) * (1 + 1e-8)
        c = self._c()
        return _outward(c - h, c + h)

    def contains(self, pts, tol=0.0):
        z = np.atleast_2d(np.asarray(pts, dtype=float)) - self._c()
        return np.einsum("ij,jk,ik->i", z, self.Q, z) <= 1.0 + tol

    def gauge(self, pts, iterations: int = 40) -> np.ndarray:
        """The gauge in closed form; bisection only when the origin is not strictly
        inside."""
        g = _quadratic_gauge(pts, self.Q, self._c())
        return super().gauge(pts, iterations) if g is None else g

    def inradius(self):
        # distance from 0 to the boundary: min over the sphere directions, via the centred
        # quadratic when centred; otherwise a lower bound by the smallest semi-axis
        lam = np.linalg.eigvalsh(self.Q)
        return 1.0 / math.sqrt(lam[-1]) - float(np.linalg.norm(self._c()))

    def max_norm(self):
        lam = np.linalg.eigvalsh(self.Q)
        return 1.0 / math.sqrt(lam[0]) + float(np.linalg.norm(self._c()))

    def _q(self, x):
        z = x if self.centre is None else x - ca.DM(self.centre)
        return ca.bilin(ca.DM(self.Q), z, z)

    def constraints(self, x):
        return [(self._q(x) - 1.0, "ellipsoid")]

    def boundary_pieces(self, x):
        q = self._q(x)
        return [(self.bounding_box(), [(q - 1.0, "ellipsoid"), (1.0 - q, "surface")],
                 "surface")]

    def boundary_nlp(self, x):
        c = self._c()
        return [{"g": self._q(x), "lbg": 1.0, "ubg": 1.0,
                 "on": lambda p: np.ones(len(p), dtype=bool),
                 "check": lambda xs: abs((xs - c) @ self.Q @ (xs - c) - 1.0) < 1e-8}]

    def sample(self, n, rng, inner=0.0):
        return _reject_inner(
            lambda k, g: self._c() + sample_ball(k, self.n, 1.0, g) @ self._map.T, n, rng, inner)

    def sample_boundary(self, n, rng):
        return self._c() + sample_sphere(n, self.n, 1.0, rng) @ self._map.T

    def describe(self):
        if np.allclose(self.Q, np.diag(np.diag(self.Q)), rtol=0, atol=0):
            ax = ", ".join(f"{a:.4g}" for a in 1.0 / np.sqrt(np.diag(self.Q)))
            s = f"ellipsoid with semi-axes ({ax})"
        else:
            s = f"ellipsoid xᵀQx ≤ 1, Q = {np.round(self.Q, 6).tolist()}"
        return s if self.centre is None else s + f" centred at {self.centre.tolist()}"

    def to_dict(self):
        d = {"type": "ellipsoid", "matrix": self.Q.tolist()}
        if self.centre is not None:
            d["centre"] = self.centre.tolist()
        return d

    def outline_2d(self, i=0, j=1, m=200):
        # slice through the origin's other coordinates = the centre's (0 for a centred set)
        Q2 = self.Q[np.ix_([i, j], [i, j])]
        c = self._c()
        th = np.linspace(0, 2 * np.pi, m)
        d = np.stack([np.cos(th), np.sin(th)], axis=1)
        r = 1.0 / np.sqrt(np.einsum("ij,jk,ik->i", d, Q2, d))
        return np.stack([c[i] + r * d[:, 0], c[j] + r * d[:, 1]], axis=1)


# ============================================================================ parsing
def _vector(v, n: int, what: str, key: str) -> np.ndarray:
    ok = isinstance(v, (list, tuple)) and len(v) == n and all(
        isinstance(a, (int, float)) and not isinstance(a, bool) and math.isfinite(a) for a in v)
    if not ok:
        raise ConfigError(f"{what}.{key} must be a list of {n} finite numbers (one per state), "
                          f"got {v!r}")
    return np.asarray(v, dtype=float)


def parse_set(spec, n: int, what: str = "domain", *, domain: bool = True) -> Region:
    """A :class:`Region` from its JSON form (see :data:`SET_FORMS`), checked.

    Parameters
    ----------
    spec : dict or Region
    n : int
        State dimension.
    what : str
        The key's name, for messages (``"domain"``, ``"initial_set"``).
    domain : bool
        Require the origin in the interior (a verification domain).

    Raises
    ------
    ConfigError
        Not one of the forms, wrong sizes, non-finite numbers, an empty set, a matrix that
        is not symmetric positive definite, or (``domain``) the origin not inside.
    """
    if isinstance(spec, Region):
        reg = spec
    else:
        forms = "; ".join(SET_FORMS)
        if not isinstance(spec, dict) or spec.get("type") not in ("ball", "box", "ellipsoid"):
            raise ConfigError(f"{what} must be one of {forms}; got {spec!r}")
        kind = spec["type"]
        allowed = {"ball": {"type", "radius", "centre"}, "box": {"type", "box"},
                   "ellipsoid": {"type", "semi_axes", "matrix", "centre"}}[kind]
        extra = set(spec) - allowed
        if extra:
            raise ConfigError(f"{what}: unknown key(s) {sorted(extra)} for a {kind}; keys: "
                              f"{', '.join(sorted(allowed))}")
        centre = _vector(spec["centre"], n, what, "centre") if "centre" in spec else None
        if kind == "ball":
            r = spec.get("radius")
            if isinstance(r, bool) or not isinstance(r, (int, float)) or not math.isfinite(r) \
                    or not r > 0:
                raise ConfigError(f"{what}.radius must be a finite number > 0, got {r!r}")
            reg = Ball(r, n, centre)
        elif kind == "box":
            b = spec.get("box")
            ok = isinstance(b, (list, tuple)) and len(b) == n and all(
                isinstance(row, (list, tuple)) and len(row) == 2 and all(
                    isinstance(a, (int, float)) and not isinstance(a, bool) and math.isfinite(a)
                    for a in row) and row[0] < row[1] for row in b)
            if not ok:
                raise ConfigError(f"{what}.box must be {n} rows [lo, hi] with finite lo < hi "
                                  f"(one per state), got {b!r}")
            reg = Box(b)
        else:
            if ("semi_axes" in spec) == ("matrix" in spec):
                raise ConfigError(f"{what}: an ellipsoid needs exactly one of 'semi_axes' "
                                  "and 'matrix'")
            if "semi_axes" in spec:
                a = _vector(spec["semi_axes"], n, what, "semi_axes")
                if not np.all(a > 0):
                    raise ConfigError(f"{what}.semi_axes must be > 0, got {a.tolist()}")
                reg = Ellipsoid.from_semi_axes(a, centre)
            else:
                Q = spec["matrix"]
                ok = isinstance(Q, (list, tuple)) and len(Q) == n and all(
                    isinstance(r, (list, tuple)) and len(r) == n for r in Q)
                Qa = np.asarray(Q, dtype=float) if ok else None
                if not ok or not np.all(np.isfinite(Qa)):
                    raise ConfigError(f"{what}.matrix must be an {n}x{n} matrix of finite "
                                      f"numbers, got {Q!r}")
                if not np.allclose(Qa, Qa.T, rtol=0, atol=0) or \
                        np.min(np.linalg.eigvalsh(Qa)) <= 0:
                    raise ConfigError(f"{what}.matrix must be symmetric positive definite "
                                      f"(the set is xᵀQx <= 1), got {Q!r}")
                reg = Ellipsoid(Qa, centre)
    if reg.n != n:
        raise ConfigError(f"{what} has dimension {reg.n}; the system has {n} states")
    if domain and not reg.inradius() > 0:
        raise ConfigError(f"{what} {reg.describe()} does not hold the origin in its interior; "
                          "the equilibrium x = 0 must lie inside the verification domain")
    return reg


def as_domain(domain, n: int) -> Region:
    """A :class:`Region` from a region, its JSON form or a number (the ball of that radius)."""
    if isinstance(domain, Region):
        return domain
    if isinstance(domain, (int, float)) and not isinstance(domain, bool):
        return Ball(domain, n)
    return parse_set(domain, n)
