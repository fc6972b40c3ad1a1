r"""Optimised relaxation slopes for the backward linear bounds (α-CROWN style).

The backward pass of :mod:`verification.backward` relaxes every nonlinear node by lines:
``f(t) >= α_l t + d_l(α_l)`` where the coefficient ``Λ`` that reaches the node is
non-negative, ``f(t) <= α_u t + d_h(α_u)`` where it is negative (``t²``: the tangent at a
point ``p``, ``t² >= 2 p t − p²``). Any slope gives a sound bound, because the rigorous
pass computes each offset for the slope it is given; which slope gives the *tightest*
bound depends on the box and on the direction, through everything between the node and
the output. α-CROWN (Xu et al., "Fast and complete", ICLR 2021) therefore treats the slopes
as parameters and maximises the final bound by gradient ascent.

:func:`optimise_slopes` does that on a floating-point model of the pass: the same
recorded graph and ranges, the same rules, in ``torch`` (float64) with automatic
differentiation, without the rounding terms, and with the offsets ``d_l(α) = min (f(t) −
α t)`` and ``d_h(α) = max (f(t) − α t)`` taken over a grid of the argument's range (so the
model is slightly optimistic; it only chooses). The slopes are parametrised inside the
range of the secant slopes of ``f`` on that grid (``α = a + (b − a) σ(θ)``), the tangent
points inside the argument's range, all starting from the fixed ones, and ``θ`` is moved by
Adam for ``steps`` steps; for each box and direction the slopes of the step with the best
model bound are returned. :func:`verification.backward.backward_bounds` then runs its
rigorous pass with them and keeps, per box and direction, the larger of that bound and
the fixed slopes' one. The result depends only on the inputs (one torch thread,
deterministic algorithms).

A product ``a b`` of two varying values gets two planes ``sa a + sb b`` (below and
above), ``sa`` in ``b``'s range and ``sb`` in ``a``'s (the corners are McCormick's planes),
starting from the centres; its offsets in the model are exact (the extremes of ``(a − sb)(b
− sa) − sa sb`` lie at the ranges' corners). The ranges the relaxations are taken over
stay those of the forward affine forms.
"""

from __future__ import annotations

import casadi as ca
import numpy as np

from nlyap_opt.kernel import deps
from nlyap_opt.kernel.determinism import deterministic_torch

from .backward import broadcast_axes, centre_radius, is_varying, tail_shape
from .interval import fp_ignore

__all__ = ["optimise_slopes", "GRID", "LEARNING_RATE"]

#: points of the argument's range on which the model takes a relaxation's offsets
GRID = 33
#: Adam's step on the slope parameters ``θ`` (slopes ``a + (b − a) σ(θ)``)
LEARNING_RATE = 0.5
_BIG = 1e12  # ranges are clipped to ±_BIG in the model (only the rigorous pass decides)

_FUNCS = {ca.OP_TANH: "tanh", ca.OP_EXP: "exp", ca.OP_SQRT: "sqrt", ca.OP_INV: "reciprocal",
          ca.OP_SIN: "sin", ca.OP_COS: "cos"}


def _tanh_crit(torch, alpha):
    t = torch.atanh(torch.clamp(torch.sqrt(torch.clamp(1.0 - alpha, 0.0, 1.0)), max=1 - 2**-52))
    return [t, -t]


def _inv_crit(torch, alpha):
    r = 1.0 / torch.sqrt(torch.clamp(-alpha, min=1e-300))
    return [r, -r]


#: where ``f'(t) = α`` (the candidates for the extremes of ``f(t) − α t`` besides the
#: range's ends), for the functions whose derivative inverts in closed form
_CRIT = {
    ca.OP_TANH: _tanh_crit,
    ca.OP_EXP: lambda torch, alpha: [torch.log(torch.clamp(alpha, min=1e-300))],
    ca.OP_SQRT: lambda torch, alpha: [0.25 / torch.clamp(alpha, min=1e-150) ** 2],
    ca.OP_INV: _inv_crit,
}


def _extreme(torch, alpha, t, f, op, fun, lo, hi, upper: bool):
    """The model's ``min`` (``max`` if ``upper``) of ``f(t) − α t`` over the range: at the
    ends and critical points (:data:`_CRIT`), else over the grid ``t`` with values ``f``.
    The points are chosen without gradient, so the gradient in ``α`` is ``−t*`` at the
    extreme ``t*`` (the envelope theorem)."""
    if t is None:
        with torch.no_grad():
            lo_b, hi_b = lo.expand_as(alpha), hi.expand_as(alpha)
            pts = [lo_b, hi_b] + [torch.minimum(torch.maximum(c, lo_b), hi_b)
                                  for c in _CRIT[op](torch, alpha)]
            t = torch.stack(pts, -1)
            f = fun(t)
    v = f - alpha[..., None] * t
    return v.max(-1).values if upper else v.min(-1).values


def _finite(a) -> np.ndarray:
    with fp_ignore():
        return np.nan_to_num(np.clip(np.asarray(a, dtype=float), -_BIG, _BIG), nan=0.0)


class _Model:
    """The floating-point model of one backward pass, with its slope parameters."""

    def __init__(self, torch, nodes, out, D, lo, hi):
        self.torch = torch
        self.nodes, self.out = nodes, out
        self.m, self.B = len(D), len(lo)
        self.D = torch.as_tensor(np.asarray(D, dtype=float))
        self.lo, self.hi = torch.as_tensor(_finite(lo)), torch.as_tensor(_finite(hi))
        self.params: dict[int, tuple] = {}  # id -> (kind, θ tensors, fixed data)
        for n in nodes:
            if n.kind == "relax" and n.data[-1].any() and n.data[0] in _FUNCS:
                self.params[id(n)] = self._relax_params(n)
            elif n.kind == "sq":
                self.params[id(n)] = self._sq_params(n)
            elif n.kind == "mul" and is_varying(n.args[0]) and is_varying(n.args[1]):
                self.params[id(n)] = self._mul_params(n)

    def _t(self, a):
        return self.torch.as_tensor(_finite(a))

    def _relax_params(self, n):
        torch = self.torch
        op, alpha, _, _, ok = n.data
        r = n.args[0].rng()
        shape = (self.m,) + tuple(np.shape(ok))
        lo = np.where(ok, _finite(r.lo), 1.0)  # stand-ins where not ok (never used)
        hi = np.where(ok, _finite(r.hi), 1.0)
        t = torch.as_tensor(lo[..., None] + (hi - lo)[..., None] * np.linspace(0, 1, GRID))
        f = getattr(torch, _FUNCS[op])(t)
        with fp_ignore():
            sec = (f[..., 1:] - f[..., :-1]) / (t[..., 1:] - t[..., :-1])
        sec = torch.nan_to_num(sec, nan=0.0, posinf=0.0, neginf=0.0)
        a = torch.minimum(sec.min(-1).values, torch.as_tensor(alpha))
        b = torch.maximum(sec.max(-1).values, torch.as_tensor(alpha))
        with fp_ignore():
            rel = np.clip((alpha - a.numpy()) / np.maximum(b.numpy() - a.numpy(), 1e-300),
                          0.02, 0.98)
        theta = np.broadcast_to(np.log(rel / (1.0 - rel)), shape)
        th_l = torch.tensor(theta, requires_grad=True)
        th_u = torch.tensor(theta, requires_grad=True)
        fun = getattr(torch, _FUNCS[op])
        if op in _CRIT:  # exact offsets at the ends and the critical points: no grid
            t = f = None
        return "relax", (th_l, th_u), (t, f, a, b, torch.as_tensor(ok),
                                       (op, fun, torch.as_tensor(lo), torch.as_tensor(hi)))

    def _sq_params(self, n):
        torch = self.torch
        r = n.args[0].rng()
        shape = (self.m,) + tuple(np.shape(r.lo))
        th = torch.zeros(shape, dtype=torch.float64, requires_grad=True)  # the centre
        return "sq", (th,), (self._t(r.lo), self._t(r.hi))

    def _mul_params(self, n):
        torch = self.torch
        ra, rb = (x.rng() for x in n.args)
        shape = np.broadcast_shapes(ra.lo.shape, rb.lo.shape)
        rng = tuple(self._t(np.broadcast_to(v, shape)) for v in (ra.lo, ra.hi, rb.lo, rb.hi))
        ths = tuple(torch.zeros((self.m,) + shape, dtype=torch.float64, requires_grad=True)
                    for _ in range(4))  # the centres
        return "mul", ths, rng

    def thetas(self) -> list:
        return [th for _, ths, _ in self.params.values() for th in ths]

    def slopes(self, n, kind, ths, data):
        """The slopes (``relax``: ``α_l, α_u``; ``sq``: ``p``) from the parameters."""
        if kind == "relax":
            a, b = data[2], data[3]
            return tuple(a + (b - a) * self.torch.sigmoid(th) for th in ths)
        if kind == "mul":  # (sa, sb) below, then above: sa in b's range, sb in a's
            al, ah, bl, bh = data
            sig = [self.torch.sigmoid(th) for th in ths]
            return (bl + (bh - bl) * sig[0], al + (ah - al) * sig[1],
                    bl + (bh - bl) * sig[2], al + (ah - al) * sig[3])
        lo, hi = data
        return (lo + (hi - lo) * self.torch.sigmoid(ths[0]),)

    def bound(self):
        """The model's lower bounds ``(m, B)`` for the current parameters."""
        torch = self.torch
        self.lam: dict[int, object] = {}
        self.low = torch.zeros((self.m, self.B), dtype=torch.float64)
        tail = tail_shape(self.out)
        K = int(np.prod(tail, dtype=np.int64))
        L0 = self.D[:, None, :].expand(self.m, self.B, K).reshape((self.m, self.B) + tail)
        self.give(self.out, L0)
        for n in reversed(self.nodes):
            L = self.lam.pop(id(n), None)
            if L is not None:
                self.step(n, L)
        return self.low

    def concretise(self, L, lo, hi) -> None:
        torch = self.torch
        t = torch.where(L > 0, L * lo, L * hi)
        if t.dim() > 2:
            t = t.sum(dim=tuple(range(2, t.dim())))
        self.low = self.low + t

    def give(self, n, L) -> None:
        if not is_varying(n):
            r = n.rng()
            shape = tuple(L.shape[1:])
            self.concretise(L, self._t(np.broadcast_to(r.lo, shape)),
                            self._t(np.broadcast_to(r.hi, shape)))
            return
        tail = tail_shape(n)
        full = tuple(L.shape[:2]) + tail
        if tuple(L.shape) != full:
            axes = broadcast_axes(tuple(L.shape), tail)
            L = L.sum(dim=axes, keepdim=True).reshape(full)
        prev = self.lam.get(id(n))
        self.lam[id(n)] = L if prev is None else prev + L

    def step(self, n, L) -> None:
        k = n.kind
        if k == "input":
            self.concretise(L, self.lo, self.hi)
        elif k == "scale":
            self.give(n.args[0], L * n.data)
        elif k == "add":
            a, b = n.args
            self.give(a, L)
            self.give(b, L if n.data > 0 else -L)
        elif k == "sum":
            a = n.args[0]
            La = L
            for ax in sorted(n.data):
                La = La.unsqueeze(ax + 1)
            self.give(a, La.expand((L.shape[0],) + tuple(a.val.shape)))
        elif k == "relax":
            self._relax(n, L)
        elif k == "sq":
            self._sq(n, L)
        elif k == "mul":
            self._mul(n, L)
        elif k == "matmul":
            self._matmul(n, L)
        elif k == "struct":
            self._struct(n, L)

    def _relax(self, n, L) -> None:
        torch = self.torch
        a = n.args[0]
        r = n.rng()
        par = self.params.get(id(n))
        if par is None:  # fixed slope (an operation the model has no function for)
            _, alpha, dl, dh, ok = n.data
            self.concretise(L, self._t(np.where(ok, dl, r.lo)), self._t(np.where(ok, dh, r.hi)))
            self.give(a, L * self._t(alpha))
            return
        kind, ths, data = par
        al, au = self.slopes(n, kind, ths, data)
        t, f, _, _, ok, (op, fun, lo, hi) = data
        dl = _extreme(torch, al, t, f, op, fun, lo, hi, False)
        dh = _extreme(torch, au, t, f, op, fun, lo, hi, True)
        dl = torch.where(ok, dl, self._t(r.lo))
        dh = torch.where(ok, dh, self._t(r.hi))
        self.concretise(L, dl, dh)
        self.give(a, L * torch.where(L >= 0, torch.where(ok, al, 0.0), torch.where(ok, au, 0.0)))

    def _sq(self, n, L) -> None:
        torch = self.torch
        a = n.args[0]
        kind, ths, data = self.params[id(n)]
        (p,) = self.slopes(n, kind, ths, data)
        lo, hi = data
        self.concretise(L, -p * p, -lo * hi)
        self.give(a, L * torch.where(L >= 0, 2.0 * p, lo + hi))

    def _mul(self, n, L) -> None:
        a, b = n.args
        if not is_varying(b) or not is_varying(a):
            v, c = (a, b) if is_varying(a) else (b, a)
            cc, ce = centre_radius(c)
            mag = np.broadcast_to(_finite(v.mag()), tuple(L.shape[1:]))
            self.low = self.low - self._sumtail(L.abs() * self._t(ce) * self._t(mag))
            self.give(v, L * self._t(cc))
            return
        torch = self.torch
        kind, ths, data = self.params[id(n)]
        sa_l, sb_l, sa_u, sb_u = self.slopes(n, kind, ths, data)
        al, ah, bl, bh = data
        # a b − sa a − sb b = (a − sb)(b − sa) − sa sb: its extremes at the corners
        k_low = torch.stack([(x - sb_l) * (y - sa_l) for x in (al, ah) for y in (bl, bh)]
                            ).min(0).values - sa_l * sb_l
        k_up = torch.stack([(x - sb_u) * (y - sa_u) for x in (al, ah) for y in (bl, bh)]
                           ).max(0).values - sa_u * sb_u
        self.concretise(L, k_low, k_up)
        pos = L >= 0
        self.give(a, L * torch.where(pos, sa_l, sa_u))
        self.give(b, L * torch.where(pos, sb_l, sb_u))

    def _sumtail(self, t):
        return t.sum(dim=tuple(range(2, t.dim()))) if t.dim() > 2 else t

    def _matmul(self, n, L) -> None:
        a, b = n.args
        if not is_varying(a):
            cA = self._t(np.swapaxes(centre_radius(a)[0], -1, -2))
            self.give(b, cA @ L)
        else:
            cA = self._t(np.swapaxes(centre_radius(b)[0], -1, -2))
            self.give(a, L @ cA)

    def _struct(self, n, L) -> None:
        torch = self.torch
        m, B = L.shape[:2]
        Lf = L.reshape(m, B, -1)
        for arg, (sel, src, _, size, tail) in zip(n.args, n.data):
            if not len(sel):
                continue
            Li = torch.zeros((m, B, size), dtype=L.dtype)
            Li = Li.index_add(2, torch.as_tensor(src), Lf[..., torch.as_tensor(sel)])
            self.give(arg, Li.reshape((m, B) + tuple(tail)))


def optimise_slopes(nodes, out, D, lo, hi, steps: int, decided=None) -> dict[int, tuple]:
    """Slopes for :func:`verification.backward._bound`, optimised per box and direction.

    Parameters
    ----------
    nodes, out
        The graph recorded by :func:`verification.backward.backward_bounds` and its output.
    D : (m, K) ndarray
        The directions.
    lo, hi : (B, n) ndarray
        The boxes.
    steps : int
        Adam steps on the slope parameters (at most).
    decided : callable, optional
        ``decided(low)``: per box, whether the bounds ``low`` ``(m, B)`` are enough; the
        steps stop once the best model bounds are enough for every box.

    Returns
    -------
    dict
        Per node id: ``(α_l, α_u)`` (``relax``) or ``(p,)`` (``sq``), float arrays of shape
        ``(m, B) + tail``: the slopes of the step whose model bound was the largest, per
        box and direction. Empty when the graph has nothing to optimise.
    """
    torch = deps.torch()
    with deterministic_torch(1):
        model = _Model(torch, nodes, out, D, lo, hi)
        thetas = model.thetas()
        if not thetas:
            return {}
        opt = torch.optim.Adam(thetas, lr=LEARNING_RATE)
        best = None
        kept: dict[int, list] = {}
        for it in range(steps + 1):
            opt.zero_grad()
            low = model.bound()
            good = torch.isfinite(low)
            with torch.no_grad():
                score = torch.where(good, low, -torch.inf)
                better = score > best if best is not None else torch.ones_like(good)
                best = score if best is None else torch.where(better, score, best)
                for n in model.nodes:
                    par = model.params.get(id(n))
                    if par is None:
                        continue
                    vals = [s.detach() for s in model.slopes(n, *par)]
                    if id(n) not in kept:
                        kept[id(n)] = [v.clone() for v in vals]
                        continue
                    sel = better.reshape(better.shape + (1,) * (vals[0].dim() - 2))
                    kept[id(n)] = [torch.where(sel, v, k) for v, k in zip(vals, kept[id(n)])]
            if it == steps or (decided is not None and decided(best.numpy()).all()):
                break
            objective = -torch.where(good, low, 0.0).sum()
            if not objective.requires_grad:  # every relaxed node reaches the output only
                break                        # through a concretised one: nothing to move
            objective.backward()
            opt.step()
    return {k: tuple(v.numpy() for v in vals) for k, vals in kept.items()}
