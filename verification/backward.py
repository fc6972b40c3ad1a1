r"""Backward linear bound propagation (CROWN style) over the walker's graphs.

For an output ``o(x)`` of a CasADi Function on a box ``X`` and a direction ``d``, a
*linear bound* ``d·o(x) >= Λ_x·x + b`` for all ``x`` in ``X`` is built backwards through
the graph, as CROWN (Zhang et al., 2018) does for networks: start from ``Λ_o = d`` and,
node by node from the output to the input, replace ``Λ_y·y`` by a lower bound that is
linear in the node's arguments:

- linear operations (``+``, ``-``, scaling, sums, matrix products with a constant or
  interval matrix, and every rearrangement: indexing, reshape, concatenation, ...) pass
  ``Λ`` on exactly (``Λ_a = Aᵀ Λ_y`` for ``y = A a``);
- a smooth unary ``f`` (``tanh``, ``exp``, ``sin``, ``cos``, ``sqrt``, ``1/x``) uses the
  sound relaxation ``f(t) − α t ∈ [d_l, d_h]`` over the argument's range
  (:func:`verification.affine.relaxation`): ``Λ_a = α Λ_y`` and the offset
  ``d_l`` where ``Λ_y >= 0``, ``d_h`` where ``Λ_y < 0``;
- ``t²`` uses the tangent at the range's centre below and the secant above (two different
  slopes, picked by the sign of ``Λ_y``);
- a product ``a b`` of two varying values uses the plane through the ranges' centres
  ``b_c a + a_c b`` with the offset ``a b − b_c a − a_c b = (a − a_c)(b − b_c) − a_c b_c``
  enclosed by interval arithmetic on the ranges; with one factor that does
  not vary with the input beyond an interval ``c ± e``: ``Λ_a = c Λ_y`` and
  ``−|Λ_y| e |a|`` in the offset;
- every other operation (and a product of two varying matrices) is *concretised*: its
  value's range gives ``Λ_y·y >= Σ min(Λ_y y_lo, Λ_y y_hi)``.

At the input, ``Λ_x·x >= Σ min(Λ_x lo, Λ_x hi)`` closes the bound. The ranges the
relaxations need are those of the forward affine forms (:mod:`verification.affine`),
computed in the same walker pass that records the graph. The gain over the forward forms:
each relaxation's error enters with the coefficient ``|Λ_y|`` that the rest of the graph
actually gives it (``|Σ_i Λ_i W_ij|``), where the forward forms carry it as an
independent remainder (``Σ_i |Λ_i| |W_ij|``), and ``t²`` and products get one-sided
planes.

Soundness
---------
Invariant, for every direction and box: ``d·o(x) >= Σ_p Λ_p·p(x) + low − res`` for all
real points ``x`` of the box, where ``p`` runs over the nodes not yet processed that hold
a ``Λ`` (real values of the graph's registers), ``low`` is a sum of rigorous lower bounds
and ``res >= 0`` an upper bound of everything the float ``Λ`` arrays err by. Every float
step ``Λ_a = fl(·)`` adds to ``res`` a bound of its error times ``|a| <= M_a`` (the
magnitude of ``a``'s range): ``γ_k |A|ᵀ|Λ_y|`` for a ``k``-term product, ``2u |Λ_a|`` plus
the underflow ``2⁻¹⁰⁷⁴`` for an elementwise one (Higham's ``γ_k``, :mod:`rounding`);
offsets are summed as rigorous lower bounds (the float sum less ``γ_{k+1}`` times the
sum of magnitudes, rounded down); exact steps (sign changes, doubling, sums,
rearrangements) add nothing. Relaxations and corner bounds are rigorous in real
arithmetic over the forward ranges, which enclose the registers' real values. A NaN or an
unbounded range where ``Λ ≠ 0`` makes the bound ``−inf`` (nothing claimed).

Slopes
------
By default the slopes are fixed: the relaxations' Chebyshev slopes (one slope for both
sides), the tangent at the range's centre for ``t²``, the centre planes of products. With
``slope_steps`` the slopes of ``tanh``, ``exp``, ``sin``, ``cos``, ``sqrt``, ``1/x`` (a lower
and an upper one) and the tangent points of ``t²`` are optimised per box and direction
(:mod:`verification.slopes`), as α-CROWN does; any float slope is sound, because each
offset is computed rigorously for the slope given, so the optimiser's own arithmetic needs
no care. Intermediate ranges come from the forward forms, not from backward passes of
their own; the product planes stay fixed.
"""

from __future__ import annotations

import threading

import casadi as ca
import numpy as np

from nlyap_opt.kernel.rounding import ETA, U, dn, dn_sum, gamma, up, up_roundings, up_sum
from nlyap_opt.kernel.walker import evaluate

from .affine import Affine, AffineArithmetic, relaxation
from .interval import Interval, IntervalArithmetic, fp_ignore, to_shape

__all__ = ["backward_bounds"]

_AA = AffineArithmetic()
_IA = IntervalArithmetic()
_INF = np.inf


class _Node:
    """One register value: its forward affine form, and how it was computed.

    ``kind`` is ``None`` for a *leaf* (a constant, or a value only its range is used of);
    else the backward rule (``"input"``, ``"scale"``, ``"add"``, ``"sum"``, ``"mul"``,
    ``"sq"``, ``"relax"``, ``"matmul"``, ``"struct"``) with its arguments ``args`` and
    ``data``. ``batched``: the value has the leading box axis (every non-leaf has).
    """

    __slots__ = ("val", "kind", "args", "data", "batched", "_rng", "_tape")

    def __init__(self, val: Affine, kind, args, data, batched: bool, tape):
        self.val = val
        self.kind = kind
        self.args = args
        self.data = data
        self.batched = batched
        self._rng = None
        self._tape = tape

    @property
    def shape(self) -> tuple[int, ...]:
        return self.val.shape

    @property
    def ndim(self) -> int:
        return self.val.ndim

    def __getitem__(self, idx):  # SX programs index their inputs directly
        return self._tape.structural(lambda v: v[idx], self)

    def rng(self) -> Interval:
        """The (cached) range of the forward form."""
        if self._rng is None:
            r = self.val.to_interval()
            self._rng = Interval(to_shape(r.lo, self.val.shape), to_shape(r.hi, self.val.shape))
        return self._rng

    def mag(self):
        """An upper bound of ``|value|`` per entry (``inf`` where unknown)."""
        r = self.rng()
        with fp_ignore():
            m = np.maximum(np.abs(r.lo), np.abs(r.hi))
        return np.where(m == m, m, _INF)


def is_varying(n: _Node) -> bool:
    """Whether node ``n`` varies with the input (it has a backward rule; else a leaf)."""
    return n.kind is not None


class _Tape:
    """Walker arithmetic that computes the affine forms and records the graph.

    One module-level instance (the walker caches constant values per arithmetic object);
    the list of recorded nodes is per thread.
    """

    name = "backward"
    cache_constants = True

    def __init__(self):
        self._local = threading.local()

    @property
    def nodes(self) -> list:
        return self._local.nodes

    def start(self) -> None:
        self._local.nodes = []

    def _leaf(self, val: Affine, batched: bool) -> _Node:
        return _Node(val, None, (), None, batched, self)

    def _new(self, val: Affine, kind: str, args, data=None) -> _Node:
        n = _Node(val, kind, tuple(args), data, True, self)
        self._local.nodes.append(n)
        return n

    def _node(self, x) -> _Node:
        return x if isinstance(x, _Node) else self.constant(x)

    def input(self, lo, hi) -> _Node:
        return self._new(Affine.from_box(lo, hi), "input", (), None)

    def constant(self, value) -> _Node:
        return self._leaf(_AA.constant(value), False)

    def unary(self, op: int, a) -> _Node:
        a = self._node(a)
        if op == ca.OP_ASSIGN:
            return a
        if not is_varying(a):
            return self._leaf(_AA.unary(op, a.val), a.batched)
        if op in (ca.OP_NEG, ca.OP_TWICE):
            return self._new(_AA.unary(op, a.val), "scale", [a],
                             -1.0 if op == ca.OP_NEG else 2.0)
        if op == ca.OP_SQ:
            return self._new(_AA.unary(op, a.val), "sq", [a])
        with fp_ignore():
            r = a.rng()
            relaxed = relaxation(op, r.lo, r.hi)
        if relaxed is None:
            return self._leaf(_AA.unary(op, a.val), True)
        return self._new(_AA.unary(op, a.val, relaxed), "relax", [a], (op,) + tuple(relaxed))

    def binary(self, op: int, a, b) -> _Node:
        a = self._node(a)
        b = self._node(b)
        if not (is_varying(a) or is_varying(b)):
            return self._leaf(_AA.binary(op, a.val, b.val), a.batched or b.batched)
        if op in (ca.OP_ADD, ca.OP_SUB):
            return self._new(_AA.binary(op, a.val, b.val), "add", [a, b],
                             1.0 if op == ca.OP_ADD else -1.0)
        if op == ca.OP_MUL:
            return self._new(_AA.binary(op, a.val, b.val), "mul", [a, b])
        if op == ca.OP_DIV:  # a / b = a · (1/b), as the forward forms relax it
            return self.binary(ca.OP_MUL, a, self.unary(ca.OP_INV, b))
        if op in (ca.OP_POW, ca.OP_CONSTPOW) and is_varying(a) and not is_varying(b):
            k = _small_power(b.val)
            if k is not None:
                return self._ipow(a, k)
        return self._leaf(_AA.binary(op, a.val, b.val), True)

    def _ipow(self, a: _Node, k: int) -> _Node:
        if k == 1:
            return a
        if k == 2:
            return self.unary(ca.OP_SQ, a)
        h2 = self.unary(ca.OP_SQ, self._ipow(a, k // 2))
        return self.binary(ca.OP_MUL, h2, a) if k % 2 else h2

    def matmul(self, a, b) -> _Node:
        a = self._node(a)
        b = self._node(b)
        val = _AA.matmul(a.val, b.val)
        if is_varying(a) != is_varying(b) and a.val.ndim >= 2 and b.val.ndim >= 2:
            return self._new(val, "matmul", [a, b])
        return self._leaf(val, a.batched or b.batched)

    def sum(self, a, axis=None) -> _Node:
        a = self._node(a)
        val = _AA.sum(a.val, axis)
        if not is_varying(a):
            return self._leaf(val, a.batched)
        nd = a.val.ndim
        axes = tuple(range(nd)) if axis is None else (
            (axis,) if np.ndim(axis) == 0 else tuple(axis))
        axes = tuple(sorted({int(ax) % nd for ax in axes}))
        if 0 in axes:  # over the boxes: not a walker operation; keep it a leaf
            return self._leaf(val, True)
        return self._new(val, "sum", [a], axes)

    def structural(self, fn, *args) -> _Node:
        nodes = [self._node(x) for x in args]
        val = _AA.structural(fn, *[n.val for n in nodes])
        batched = any(n.batched for n in nodes)
        if not any(is_varying(n) for n in nodes):
            return self._leaf(val, batched)
        maps = _struct_map(fn, nodes, val.shape)
        if maps is None:
            return self._leaf(val, True)
        return self._new(val, "struct", nodes, maps)

    def nonneg(self, a) -> _Node:
        return self._node(a)


_TAPE = _Tape()


def _small_power(b: Affine) -> int | None:
    """The exponent ``k`` in ``1..8`` of ``a**b`` when ``b`` is that exact integer."""
    if b.g is not None or np.ndim(b.c) or np.any(b.e):
        return None
    v = float(b.c)
    return int(v) if v == np.floor(v) and 1 <= v <= 8 else None


def _point_mul(p, q):
    """Enclosure ``(lo, hi)`` of the real products of float arrays ``p``, ``q``."""
    r = _IA.binary(ca.OP_MUL, Interval(p, p), Interval(q, q))
    return r.lo, r.hi


def _diff(a: tuple, b: tuple):
    """Enclosure of ``a - b`` for enclosures ``a``, ``b``."""
    r = _IA.binary(ca.OP_SUB, Interval(*a), Interval(*b))
    return r.lo, r.hi


def broadcast_axes(shape: tuple, tail: tuple) -> tuple[int, ...]:
    """The axes of a ``Λ`` of ``shape`` (``(m, B) + ...``) to sum for a node of per-box
    shape ``tail`` that was broadcast to it: the leading extra axes and those where the
    node has length 1."""
    extra = len(shape) - 2 - len(tail)
    return tuple(range(2, 2 + extra)) + tuple(
        2 + extra + i for i, t in enumerate(tail) if t == 1 and shape[2 + extra + i] != 1)


def tail_shape(n: _Node) -> tuple[int, ...]:
    """The shape of one box's value of node ``n`` (without the boxes' axis)."""
    return tuple(n.val.shape[1:]) if n.batched else tuple(n.val.shape)


def _struct_map(fn, nodes, out_shape):
    """Which argument entry each output entry of a rearrangement copies (or ``None``).

    ``fn`` is applied to the entries' numbers ``1, 2, ...`` (one box) and to their squares:
    an output that copies one entry (or is 0) gives ``id`` and ``id²``; a sum of several
    would not (``(Σ id)² > Σ id²``), and such a map is refused (the node stays a leaf).
    """
    arrays, spans, off = [], [], 0
    for n in nodes:
        tail = tail_shape(n)
        size = int(np.prod(tail, dtype=np.int64))
        ids = np.arange(off + 1, off + size + 1, dtype=float)
        arrays.append(ids.reshape(((1,) if n.batched else ()) + tail))
        spans.append((off, size, tail))
        off += size
    if off >= 2**26:
        return None
    try:
        with fp_ignore():
            first = np.asarray(fn(*arrays), dtype=float)
            second = np.asarray(fn(*[a * a for a in arrays]), dtype=float)
    except Exception:  # noqa: BLE001 - a rearrangement that needs the boxes' axis
        return None
    if first.shape != (1,) + tuple(out_shape[1:]) or not np.array_equal(first * first, second):
        return None
    flat = first.reshape(-1)
    if not np.array_equal(flat, np.floor(flat)) or (flat < 0).any():
        return None
    flat = flat.astype(np.int64)
    maps = []
    for o, size, tail in spans:
        sel = np.flatnonzero((flat > o) & (flat <= o + size))
        src = flat[sel] - o - 1
        maps.append((sel, src, len(np.unique(src)) == len(src), size, tail))
    return maps


# --------------------------------------------------------------------------- rigorous sums
def _tail_axes(a) -> tuple[int, ...]:
    return tuple(range(2, a.ndim))


def _lower_dot(L, kl, ku):
    """Rigorous lower bound ``(m, B)`` of ``Σ_tail Λ·t`` where ``t - (offset) ∈ [kl, ku]``:
    the term ``Λ kl`` where ``Λ > 0``, ``Λ ku`` where ``Λ < 0`` (``kl``, ``ku`` real bounds,
    broadcast to ``Λ``'s trailing shape)."""
    with fp_ignore():
        t = np.where(L > 0, L * kl, np.where(L < 0, L * ku, 0.0))
        axes = _tail_axes(t)
        k = int(np.prod([t.shape[a] for a in axes], dtype=np.int64)) if axes else 1
        s = np.sum(t, axis=axes) if axes else t
        mag = np.sum(np.abs(t), axis=axes) if axes else np.abs(t)
        err = up_roundings(gamma(k + 1) * mag + k * ETA, k + 4)
        low = dn(s - err)
    return np.where(low == low, low, -_INF)


def _resid(A, M):
    """Rigorous upper bound ``(m, B)`` of ``Σ_tail A·M`` for ``A, M >= 0`` (floats that are
    upper bounds already); ``0`` where ``A = 0`` even if ``M = inf``."""
    with fp_ignore():
        p = np.where(A == 0, 0.0, A * M)
        axes = _tail_axes(p)
        k = int(np.prod([p.shape[a] for a in axes], dtype=np.int64)) if axes else 1
        s = np.sum(p, axis=axes) if axes else p
        r = up_roundings(s, k + 2)
    return np.where(r == r, r, _INF)


class _Pass:
    """One backward pass: ``Λ`` per node, the offsets ``low`` and the residual ``res``."""

    def __init__(self, m: int, B: int, lo, hi):
        self.lam: dict[int, np.ndarray] = {}
        self.low = np.zeros((m, B))
        self.res = np.zeros((m, B))
        self.B = B
        self.lo, self.hi = lo, hi

    def add_low(self, v) -> None:
        with fp_ignore():
            s = dn_sum(self.low + v)
        self.low = np.where(s == s, s, -_INF)

    def add_res(self, v) -> None:
        with fp_ignore():
            s = up_sum(self.res + v)
        self.res = np.where(s == s, s, _INF)

    def give(self, n: _Node, L) -> None:
        """Hand ``Λ`` (``(m, B) + tail``, broadcastable to ``n``) to node ``n``."""
        if not is_varying(n):  # concretise on the leaf's range
            r = n.rng()
            shape = L.shape[1:]
            self.add_low(_lower_dot(L, np.broadcast_to(r.lo, shape),
                                    np.broadcast_to(r.hi, shape)))
            return
        tail = tail_shape(n)
        full = L.shape[:2] + tail
        if L.shape != full:  # sum over the axes ``n`` was broadcast along (float sums)
            axes = broadcast_axes(tuple(L.shape), tail)
            k = int(np.prod([L.shape[a] for a in axes], dtype=np.int64))
            with fp_ignore():
                summed = np.sum(L, axis=axes, keepdims=True)
                absum = np.sum(np.abs(L), axis=axes, keepdims=True)
            summed = summed.reshape(full)
            self.add_res(_resid(up_roundings(gamma(k) * absum.reshape(full), k + 2), n.mag()))
            L = summed
        prev = self.lam.get(id(n))
        if prev is None:
            self.lam[id(n)] = np.array(L, dtype=float)
            return
        with fp_ignore():
            s = prev + L
        self.add_res(_resid(2.0 * U * np.abs(s), n.mag()))
        self.lam[id(n)] = s

    def times(self, a: _Node, L, coef, width=None) -> None:
        """Hand ``fl(Λ coef)`` to ``a``, with its rounding (and ``|Λ| width``) as residual."""
        with fp_ignore():
            La = L * coef
            err = 2.0 * U * np.abs(La) + ETA
            if width is not None:
                err = err + np.abs(L) * width
            err = np.where(L == 0, 0.0, up_roundings(err, 4))  # Λ = 0: La = 0 exactly
        self.add_res(_resid(err, np.broadcast_to(a.mag(), La.shape[1:])))
        self.give(a, La)


def _step(P: _Pass, n: _Node, L, slopes: dict | None = None) -> None:
    """Replace ``Λ_n·n`` by a bound linear in ``n``'s arguments (module docstring).

    ``slopes``: per node id, the slopes of :mod:`verification.slopes` (``relax``: the
    lower and upper slopes; ``sq``: the tangent points; ``mul`` of two varying values: the
    planes' slopes ``(sa, sb)`` below and above), ``(m, B) + tail`` each, instead of the
    fixed ones.
    """
    k = n.kind
    if k == "input":
        P.add_low(_lower_dot(L, P.lo, P.hi))
    elif k == "scale":
        P.give(n.args[0], L * n.data)  # -1, 2: exact
    elif k == "add":
        a, b = n.args
        P.give(a, L)
        P.give(b, L if n.data > 0 else -L)
    elif k == "sum":
        a = n.args[0]
        La = np.broadcast_to(np.expand_dims(L, tuple(ax + 1 for ax in n.data)),
                             L.shape[:1] + a.val.shape)
        P.give(a, La)
    elif k == "relax":
        if slopes is not None and id(n) in slopes:
            _relax_given(P, n, L, *slopes[id(n)])
            return
        a = n.args[0]
        _, alpha, dl, dh, ok = n.data
        r = n.rng()
        P.add_low(_lower_dot(L, np.where(ok, dl, r.lo), np.where(ok, dh, r.hi)))
        if ok.any():
            P.times(a, L, alpha)
    elif k == "sq":
        _sq_step(P, n, L, slopes[id(n)][0] if slopes is not None and id(n) in slopes else None)
    elif k == "mul":
        _mul_step(P, n, L, slopes.get(id(n)) if slopes is not None else None)
    elif k == "matmul":
        _matmul_step(P, n, L)
    elif k == "struct":
        _struct_step(P, n, L)
    else:  # pragma: no cover - every kind above
        raise AssertionError(k)


def _relax_given(P: _Pass, n: _Node, L, alpha_l, alpha_u) -> None:
    """The ``relax`` step with slopes ``alpha_l`` below (where ``Λ >= 0``) and
    ``alpha_u`` above (where ``Λ < 0``): each with the rigorous offset of
    :func:`~verification.affine.relaxation` for that slope; where one is not ``ok``,
    slope 0 and the node's range."""
    a = n.args[0]
    op = n.data[0]
    ra, r = a.rng(), n.rng()
    shape = L.shape
    lo, hi = np.broadcast_to(ra.lo, shape), np.broadcast_to(ra.hi, shape)
    with fp_ignore():
        s_l, dl, _, ok_l = relaxation(op, lo, hi, alpha_l)
        s_u, _, dh, ok_u = relaxation(op, lo, hi, alpha_u)
    kl = np.where(ok_l, dl, np.broadcast_to(r.lo, shape))
    ku = np.where(ok_u, dh, np.broadcast_to(r.hi, shape))
    P.add_low(_lower_dot(L, kl, ku))
    P.times(a, L, np.where(L >= 0, np.where(ok_l, s_l, 0.0), np.where(ok_u, s_u, 0.0)))


def _sq_step(P: _Pass, n: _Node, L, points=None) -> None:
    """``t²``: the tangent at ``points`` (``(m, B) + tail``; default: the range's centre)
    below, the secant above."""
    a = n.args[0]
    r = a.rng()
    with fp_ignore():
        lo, hi = r.lo, r.hi
        p = np.minimum(np.maximum(0.5 * lo + 0.5 * hi, lo), hi) if points is None else \
            np.where(np.isfinite(points), points, 0.0)
        s_low = 2.0 * p  # tangent at p: t² - 2 p t = (t - p)² - p² >= -p² (any float p)
        k_low = -up(p * p)
        s_up = lo + hi  # secant slope (any float: t² - s t is convex, its max at an end)
        k_up = np.maximum(_sq_minus(lo, s_up), _sq_minus(hi, s_up))
        fin = np.isfinite(lo) & np.isfinite(hi)
        s_low = np.where(fin, s_low, 0.0)
        s_up = np.where(fin, s_up, 0.0)
        k_low = np.where(fin, k_low, n.rng().lo)
        k_up = np.where(fin, k_up, n.rng().hi)
    P.add_low(_lower_dot(L, k_low, k_up))
    P.times(a, L, np.where(L >= 0, s_low, s_up))


def _sq_minus(t, s):
    """Upper bound of ``t² - s t`` at float points ``t``."""
    return _diff(_point_mul(t, t), _point_mul(s, t))[1]


def centre_radius(n: _Node):
    """``(c, e)`` with ``[c - e, c + e]`` holding the value of leaf ``n`` on the box.

    A leaf's form may still have input coefficients (a product of two varying matrices,
    and whatever is computed from it): its range is then the whole of
    ``c ± (Σ|g_i| + e)``, not ``c ± e``.
    """
    val = n.val if n.val.g is None else Affine.from_interval(n.rng())
    return to_shape(val.c, val.shape), to_shape(val.e, val.shape)


def _mul_step(P: _Pass, n: _Node, L, planes=None) -> None:
    """``a b``: one factor constant (a centre and radius), or the planes of
    :func:`mul_planes` (``planes``: the slopes ``(sa, sb)`` below, then above)."""
    a, b = n.args
    if not is_varying(b) or not is_varying(a):
        v, c = (a, b) if is_varying(a) else (b, a)  # v varies, c = centre ± radius
        cc, ce = centre_radius(c)
        P.times(v, L, cc, ce)
        return
    if planes is None:
        sa, sb, k_low, k_up = mul_planes(n)
    else:  # a plane below (where Λ >= 0) and one above (where Λ < 0)
        sa_l, sb_l, k_low, _ = mul_planes(n, planes[0], planes[1])
        sa_u, sb_u, _, k_up = mul_planes(n, planes[2], planes[3])
        sa, sb = np.where(L >= 0, sa_l, sa_u), np.where(L >= 0, sb_l, sb_u)
    P.add_low(_lower_dot(L, k_low, k_up))
    P.times(a, L, sa)
    P.times(b, L, sb)


def mul_planes(n: _Node, sa=None, sb=None):
    """``(sa, sb, k_low, k_up)`` of a product ``a b`` of two varying values: the plane
    ``sa a + sb b`` (default: through the ranges' centres; ``sa``, ``sb`` given: any
    floats, broadcast with the ranges) and rigorous bounds ``[k_low, k_up]`` of
    ``a b − sa a − sb b`` over the ranges (slopes 0 and the product's range where a range
    or a slope is not finite)."""
    a, b = n.args
    ra, rb = a.rng(), b.rng()
    with fp_ignore():
        shape = np.broadcast_shapes(ra.lo.shape, rb.lo.shape, np.shape(sa) if sa is not None
                                    else (), np.shape(sb) if sb is not None else ())
        al, ah = np.broadcast_to(ra.lo, shape), np.broadcast_to(ra.hi, shape)
        bl, bh = np.broadcast_to(rb.lo, shape), np.broadcast_to(rb.hi, shape)
        fin = np.isfinite(al) & np.isfinite(ah) & np.isfinite(bl) & np.isfinite(bh)
        if sa is None:
            sa = np.minimum(np.maximum(0.5 * bl + 0.5 * bh, bl), bh)  # b's centre
            sb = np.minimum(np.maximum(0.5 * al + 0.5 * ah, al), ah)
        else:
            sa = np.broadcast_to(np.asarray(sa, dtype=float), shape)
            sb = np.broadcast_to(np.asarray(sb, dtype=float), shape)
            fin = fin & np.isfinite(sa) & np.isfinite(sb)
        sa = np.where(fin, sa, 0.0)
        sb = np.where(fin, sb, 0.0)
        # a b - sa a - sb b = (a - sb)(b - sa) - sa sb exactly (real arithmetic): one
        # interval product of the shifted ranges, less the product of the two floats
        da = _IA.binary(ca.OP_SUB, Interval(al, ah), Interval(sb, sb))
        db = _IA.binary(ca.OP_SUB, Interval(bl, bh), Interval(sa, sa))
        k = _IA.binary(ca.OP_SUB, _IA.binary(ca.OP_MUL, da, db), Interval(*_point_mul(sa, sb)))
        k_low = np.where(k.lo == k.lo, k.lo, -_INF)
        k_up = np.where(k.hi == k.hi, k.hi, _INF)
        y = n.rng()  # where a range is unbounded: slopes 0 and the product's own range
        k_low = np.where(fin, k_low, np.broadcast_to(y.lo, shape))
        k_up = np.where(fin, k_up, np.broadcast_to(y.hi, shape))
    return sa, sb, k_low, k_up


def _matmul_step(P: _Pass, n: _Node, L) -> None:
    a, b = n.args
    if not is_varying(a):  # y = A X: Λ_X = Aᵀ Λ_y
        cA, eA = (np.swapaxes(v, -1, -2) for v in centre_radius(a))
        r = a.val.shape[-2]
        with fp_ignore():
            LX = cA @ L
            R = up_roundings((gamma(r + 2) * np.abs(cA) + eA) @ np.abs(L), r + 4)
        x = b
    else:  # y = X A: Λ_X = Λ_y Aᵀ
        cA, eA = (np.swapaxes(v, -1, -2) for v in centre_radius(b))
        c = b.val.shape[-1]
        with fp_ignore():
            LX = L @ cA
            R = up_roundings(np.abs(L) @ (gamma(c + 2) * np.abs(cA) + eA), c + 4)
        x = a
    P.add_res(_resid(R + ETA, np.broadcast_to(x.mag(), LX.shape[1:])))
    P.give(x, LX)


def _struct_step(P: _Pass, n: _Node, L) -> None:
    m, B = L.shape[:2]
    Lf = L.reshape(m, B, -1)
    for arg, (sel, src, unique, size, tail) in zip(n.args, n.data):
        if not len(sel):
            continue
        Li = np.zeros((m, B, size))
        if unique:
            Li[..., src] = Lf[..., sel]
        else:
            np.add.at(Li, (slice(None), slice(None), src), Lf[..., sel])
            Ai = np.zeros((m, B, size))
            np.add.at(Ai, (slice(None), slice(None), src), np.abs(Lf[..., sel]))
            cnt = int(np.bincount(src).max())
            mag = np.broadcast_to(arg.mag(), (B,) + tail).reshape(B, size)
            P.add_res(_resid(up_roundings(gamma(cnt) * Ai, cnt + 2), mag))
        P.give(arg, Li.reshape((m, B) + tail))


def backward_bounds(fun: ca.Function, lo: np.ndarray, hi: np.ndarray,
                    directions: np.ndarray, slope_steps: int = 0,
                    decided=None) -> tuple[np.ndarray, Affine]:
    """Lower bounds of ``d·F(x)`` over boxes for each direction ``d``, and ``F``'s forms.

    Parameters
    ----------
    fun : casadi.Function
        One input ``n`` wide; its first output, ``K`` entries, is bounded.
    lo, hi : (B, n) ndarray
        The boxes.
    directions : (m, K) ndarray
        Directions ``d`` (``e_k`` bounds output ``k`` from below, ``-e_k`` from above).
    slope_steps : int, optional
        ``0`` (default): the fixed slopes. ``k > 0``: also optimise the slopes of the
        relaxations (one lower and one upper slope per ``tanh``, ``exp``, ... entry, one
        tangent point per ``t²`` entry, per box and direction) by ``k`` gradient steps on
        a floating-point model of the bound (:mod:`verification.slopes`, as α-CROWN does),
        run the rigorous pass again with them and keep the larger of the two bounds.
    decided : callable, optional
        With ``slope_steps``: ``decided(low)`` for bounds ``low`` ``(m, B)`` says per box
        whether they are enough; the optimisation stops once the model's bounds are enough
        for every box.

    Returns
    -------
    lower : (m, B) ndarray
        Rigorous lower bounds of ``d·F(x)`` over each box (``-inf``: nothing known).
    forms : Affine
        The forward affine forms of ``F`` (as :class:`~verification.affine.AffineArithmetic`
        gives them), computed in the same pass.
    """
    lo = np.asarray(lo, dtype=float)
    hi = np.asarray(hi, dtype=float)
    D = np.asarray(directions, dtype=float)
    _TAPE.start()
    try:
        out = _TAPE._node(evaluate(fun, [_TAPE.input(lo, hi)], _TAPE)[0])
        nodes = _TAPE.nodes
    finally:
        _TAPE.start()  # drop the references of this pass
    low = _bound(nodes, out, D, lo, hi, None)
    if slope_steps > 0 and nodes and len(lo):
        from .slopes import optimise_slopes  # lazy: torch, only when slopes are optimised

        slopes = optimise_slopes(nodes, out, D, lo, hi, int(slope_steps), decided)
        if slopes:
            low = np.maximum(low, _bound(nodes, out, D, lo, hi, slopes))
    return low, out.val


def _bound(nodes, out: _Node, D, lo, hi, slopes) -> np.ndarray:
    """One rigorous backward pass over the recorded ``nodes`` (``slopes``: see
    :func:`_step`); the lower bounds ``(m, B)``."""
    m, B = len(D), len(lo)
    P = _Pass(m, B, lo, hi)
    K = int(np.prod(tail_shape(out), dtype=np.int64))
    L0 = np.broadcast_to(D[:, None, :], (m, B, K)).reshape((m, B) + tail_shape(out))
    P.give(out, L0)
    for n in reversed(nodes):
        L = P.lam.pop(id(n), None)
        if L is not None:
            _step(P, n, L, slopes)
    with fp_ignore():
        low = dn_sum(P.low - P.res)
    return np.where(low == low, low, -_INF)
