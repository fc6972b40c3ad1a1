r"""Sound bounds on the dynamics error, the gradient of V, and the margin β.

For learned dynamics :math:`\varphi` (see :mod:`nlyap_opt.dynamics`) the certificate needs

.. math:: \|e(z)\|_2 \le \eta \ \ \forall z \in Z, \qquad e = f - \varphi,

on the sampling box :math:`Z` (:math:`X \times U`, or :math:`X` for the control-affine
model), then :math:`M \ge \sup_R \|\nabla V\|_2` on the verification region :math:`R`
(with :math:`\kappa(R) \subseteq U` checked), and the decrease condition is verified with the
margin :math:`\beta = M\eta`, **strictly**: :math:`\nabla V \cdot \varphi < -\beta` implies
:math:`\nabla V \cdot f \le \nabla V\cdot\varphi + \|\nabla V\|\,\|e\| < -\beta + M\eta = 0`.

Every sup below is a *rigorous* upper bound: CasADi derivative graphs are evaluated with the
outward-rounded :class:`verification.interval.IntervalArithmetic` on a subdivision of the box
(many sub-boxes in one call per chunk), and norms are rounded upward. Interval sups are
inflated by a relative ``2**-30``: CasADi folds products of constants in derivative graphs in
float64; the interval arithmetic widens non-integer graph constants by ``2**-50`` (folds
within 3 ulps), and the inflation is a further allowance for longer folds.

Bound options (:data:`BOUND_OPTIONS`), each sound under the assumptions it prints; ``α̅`` is
the rigorous upper bound of the grid maximum of :math:`\|e\|_2` (float64 max plus a
rounding allowance), ``g_i`` the grid gap on axis ``i`` (``δ = ½‖g‖₂``):

``global`` (the paper's)
    :math:`\eta = \bar\alpha + (K_f + K_\varphi)\,\delta` with :math:`K_f \ge
    \sup\|J_f\|_2` (interval, Frobenius / Perron bound) and :math:`K_\varphi` the smaller
    of the re-certified LipSDP constant and the interval bound of :math:`\sup_Z\|J_\varphi\|_2`
    (a Lipschitz constant on the convex box). Nearest node :math:`s`:
    :math:`\|e(z) - e(s)\| \le (K_f + K_\varphi)\|z - s\| \le (K_f + K_\varphi)\delta`.
``anisotropic``
    :math:`\eta = \bar\alpha + \sum_i L_i g_i/2` with :math:`L_i \ge \sup_Z \|\partial_i
    e\|_2` from the interval Jacobian of :math:`e` itself (:math:`J_f - J_\varphi`, not the
    sum of the two norms). Mean value along the segment :math:`s \to z` (inside the convex
    box): :math:`\|e(z) - e(s)\| \le \sum_i L_i |z_i - s_i|` and the nearest node has
    :math:`|z_i - s_i| \le g_i/2`.
``second_order``
    :math:`\eta = \bar\alpha + \big\|\big(\sum_i \tfrac{g_i^2}{8} D_{ki}\big)_k\big\|_2`
    with :math:`D_{ki} \ge \sup_Z |\partial_i^2 e_k|` (interval, only the diagonal second
    derivatives). Every :math:`z` lies in a grid cell whose :math:`2^d` corners are nodes;
    the multilinear interpolant :math:`Ie` is a convex combination of corner values, so
    :math:`\|Ie(z)\| \le \alpha`, and the tensor-product error
    :math:`e - Ie = \sum_i I_1\cdots I_{i-1}(e - I_i e)` gives
    :math:`|e_k(z) - Ie_k(z)| \le \sum_i g_i^2 D_{ki}/8` (1-D linear interpolation error,
    preserved by the convex operators :math:`I_j`). Needs :math:`f \in C^2` on the box; an
    error of order :math:`h^2` instead of :math:`h`. Uses samples of f only (no derivative
    data), plus the Hessian-diagonal bound of f.

The dynamics model ``control_affine`` (:mod:`nlyap_opt.dynamics`) combines with each option:
the grid lives in x-space and :math:`e(x, u) = f_0(x) - \varphi_0(x)` for every u, under the
assumption :math:`f = f_0(x) + Bu` with the known constant B (checked symbolically on the
model). A per-cell (local-constant) variant is not provided.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from .dynamics import (
    AlphaResult,
    Grid,
    _norm2_up,
    check_dynamics_network,
    measure_alpha,
)
from .errors import ConfigError, DimensionError, InputRangeError, UnknownNameError
from .lipschitz import _up
from .network import Network

__all__ = [
    "BOUND_OPTIONS", "BoundOption", "BoundsResult", "GradientBound", "LipschitzBound",
    "ErrorModel", "compute_bounds", "lipschitz_f", "lipschitz_phi", "gradient_bound",
    "check_input_range", "margin", "subboxes", "write_bounds", "format_table", "register_cli",
]

_U = 2.0 ** -53
#: relative allowance on interval sups: CasADi folds products of constants in derivative graphs
#: in float64 (a relative error of a few units in 2**-53 per fold)
_FOLD = 1.0 + 2.0 ** -30


# ============================================================================ helpers
def _add_up(*vals) -> float:
    s = 0.0
    for v in vals:
        s = _up(s + float(v))
    return s


def _mul_up(a, b) -> float:
    return _up(float(a) * float(b))


def _counts_for(box: np.ndarray, total: int, counts=None) -> list[int]:
    d = box.shape[0]
    if counts is not None:
        counts = [int(c) for c in np.atleast_1d(counts)]
        if len(counts) != d or min(counts) < 1:
            raise ConfigError(f"interval_counts needs {d} positive entries, got {counts}")
        return counts
    n = max(int(round(max(int(total), 1) ** (1.0 / d))), 1)
    return [n] * d


def subboxes(box, counts) -> tuple[np.ndarray, np.ndarray]:
    """A subdivision of ``box`` into ``prod(counts)`` sub-boxes covering it exactly.

    Adjacent sub-boxes share their float64 edges and the outer edges equal the box ends, so
    the union is the whole box. Returns ``(lo, hi)``, each of shape ``(N, d)``.
    """
    box = np.asarray(box, dtype=float)
    edges = []
    for (lo, hi), n in zip(box, counts):
        e = np.linspace(lo, hi, int(n) + 1)
        e[0], e[-1] = lo, hi
        edges.append(e)
    grids = np.meshgrid(*[np.arange(int(n)) for n in counts], indexing="ij")
    idx = [g.ravel() for g in grids]
    lo = np.stack([e[i] for e, i in zip(edges, idx)], axis=1)
    hi = np.stack([e[i + 1] for e, i in zip(edges, idx)], axis=1)
    return lo, hi


def _ia():
    from verification.interval import Interval, IntervalArithmetic

    return Interval, IntervalArithmetic()


def _interval_sup(fun: ca.Function, box, counts, reduce: Callable, chunk: int = 2048):
    """Evaluate ``fun`` with interval arithmetic on every sub-box; reduce each chunk.

    ``reduce(mag, lo_box, hi_box)`` receives ``mag ≥ |value|`` of the (first) output as a dense
    ``(n, rows, cols)`` array per chunk of ``n`` sub-boxes (structural zeros are 0; NaN becomes
    inf) and returns an array; the per-chunk results are concatenated.
    """
    from .walker import evaluate

    Interval, ia = _ia()
    sp = fun.sparsity_out(0)
    rows, cols = (np.asarray(v, dtype=np.intp) for v in sp.get_triplet())
    shape = (sp.size1(), sp.size2())
    lo, hi = subboxes(box, counts)
    out = []
    for a in range(0, lo.shape[0], chunk):
        res = evaluate(fun, [Interval(lo[a:a + chunk], hi[a:a + chunk])], ia)[0]
        nz = np.maximum(np.abs(res.lo), np.abs(res.hi)) * _FOLD
        nz = np.where(np.isnan(nz), np.inf, nz)
        mag = np.zeros((nz.shape[0],) + shape)
        mag[:, rows, cols] = nz
        out.append(reduce(mag, lo[a:a + chunk], hi[a:a + chunk]))
    return np.concatenate(out, axis=0), lo.shape[0]


def _matrix_norm_up(mag: np.ndarray) -> np.ndarray:
    """Upper bound of ``‖J‖₂`` for every ``|J| ≤ mag`` (``mag``: ``(N, m, d)``, non-negative).

    ``‖J‖₂ ≤ ‖ |J| ‖₂ ≤ ‖mag‖₂`` (monotone for non-negative matrices), bounded by the smaller
    of the Frobenius norm and the Collatz–Wielandt bound ``λ_max(magᵀmag) ≤ max_i (magᵀmag v)_i
    / v_i`` for a positive vector ``v`` (power iterates), all rounded upward.
    """
    N, m, d = mag.shape
    fro = _norm2_up(mag.reshape(N, m * d), axis=1)
    if m == 1 or d == 1 or not np.all(np.isfinite(mag)):
        return fro
    G = np.einsum("nki,nkj->nij", mag, mag)
    v = np.ones((N, d))
    for _ in range(30):
        v = np.einsum("nij,nj->ni", G, v)
        v /= np.maximum(np.max(v, axis=1, keepdims=True), 1e-300)
    v = v + 1e-9  # strictly positive
    w = np.einsum("nki,nk->ni", mag, np.einsum("nkj,nj->nk", mag, v))
    lam = np.max(w / v, axis=1) * (1 + 4 * (m + d + 4) * _U)
    cw = np.nextafter(np.nextafter(np.sqrt(np.nextafter(lam, np.inf)), np.inf), np.inf)
    return np.minimum(fro, cw)


# ============================================================================ the error model
class ErrorModel:
    r"""The error :math:`e = f - \varphi` of a dynamics network on its sampling box.

    Builds (once) the CasADi Functions of ``z`` used by the bounds: ``J_f`` (learned rows of
    the Jacobian of the true model w.r.t. the sampled variables ``z``), ``J_phi``, ``J_e``,
    and ``D2_e`` (diagonal second derivatives of ``e``, shape ``m × d``).

    Parameters
    ----------
    system : systems.System
    network : Network
        One hidden tanh layer, linear output, ``meta`` as written by
        :func:`nlyap_opt.dynamics.learn_dynamics`.
    box : (d, 2) array_like
        The sampling box ``Z`` (the grid's box).
    """

    def __init__(self, system, network: Network, box):
        self.system, self.network = system, network
        self.model, self.comp = check_dynamics_network(system, network)
        self.box = np.asarray(box, dtype=float)
        self.d = network.n_in
        if self.box.shape != (self.d, 2):
            raise DimensionError(f"box must have shape ({self.d}, 2), got {self.box.shape}")
        nx = system.nx
        z = ca.SX.sym("z", self.d)
        u = ca.SX.zeros(system.nu) if self.model == "control_affine" else z[nx:]
        fz = system.f_fun(z[:nx], u)[self.comp]
        self.f_fun = ca.Function("f_z", [z], [fz])
        jf = ca.jacobian(fz, z)
        self.J_f = ca.Function("J_f", [z], [jf])
        d2f = ca.horzcat(*[ca.jacobian(jf[:, i], z)[:, i] for i in range(self.d)])
        self.D2_f = ca.Function("D2_f", [z], [d2f])
        zm = ca.MX.sym("z", self.d)
        jphi, d2phi = self._phi_derivatives(zm)
        self.J_phi = ca.Function("J_phi", [zm], [jphi])
        self.J_e = ca.Function("J_e", [zm], [self.J_f(zm) - jphi])
        self.D2_e = ca.Function("D2_e", [zm], [self.D2_f(zm) - d2phi])

    def _phi_derivatives(self, z):
        """Exact ``J_φ`` and diagonal second derivatives of ``φ = c ⊙ (W1 tanh(W0 z + b0) + b1)``.

        ``∂_i φ = c ⊙ W1 (s ⊙ W0[:, i])``, ``∂_i² φ = c ⊙ W1 (−2 t s ⊙ W0[:, i]²)``,
        ``t = tanh(W0 z + b0)``, ``s = 1 − t²``.
        """
        l0, l1 = self.network.layers
        t = ca.tanh(ca.mtimes(ca.DM(l0.weight), z) + ca.DM(l0.bias))
        s = 1 - t**2  # OP_SQ: the exact interval square
        g = -2 * t * s
        W1 = ca.DM(l1.weight)
        J, D2 = [], []
        for i in range(self.d):
            col = ca.DM(l0.weight[:, i])
            J.append(ca.mtimes(W1, s * col))
            D2.append(ca.mtimes(W1, (g * col) * col))  # MX products: rounded by the arithmetic
        J, D2 = ca.horzcat(*J), ca.horzcat(*D2)
        scale = self.network.output_scale
        if scale.ndim > 0 or float(scale) != 1.0:
            c = ca.DM(np.broadcast_to(scale, (self.network.n_out,)))
            J = ca.repmat(c, 1, self.d) * J
            D2 = ca.repmat(c, 1, self.d) * D2
        return J, D2

    def phi_weights(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """``(W0, b0, W1, factor)``: φ's weights with the output scale folded into ``W1``.

        Folding rounds (relative 2⁻⁵³ per entry); ``factor`` (≥ 1) covers that in a Lipschitz
        constant computed from the folded weights.
        """
        l0, l1 = self.network.layers
        scale = np.broadcast_to(self.network.output_scale, (self.network.n_out,))
        if np.all(scale == 1.0):
            return l0.weight, l0.bias, l1.weight, 1.0
        return l0.weight, l0.bias, np.abs(scale)[:, None] * l1.weight, 1.0 + 1e-12


# ============================================================================ Lipschitz bounds
@dataclass
class LipschitzBound:
    """A rigorous Lipschitz bound next to its sampled (lower) estimate."""

    value: float
    sampled: float
    n_boxes: int = 0
    seconds: float = 0.0
    method: str = ""
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"value": self.value, "sampled": self.sampled, "n_boxes": self.n_boxes,
                "seconds": self.seconds, "method": self.method, **self.extra}


def lipschitz_f(em: ErrorModel, *, boxes: int = 16384, counts=None,
                sample_points: np.ndarray | None = None) -> LipschitzBound:
    r"""``K_f ≥ sup_Z ‖J_f‖₂``: interval Jacobian on sub-boxes, Frobenius/Perron bound, upward.

    ``sample_points`` (e.g. grid nodes) give the sampled maximum for comparison.
    """
    t0 = time.perf_counter()
    counts = _counts_for(em.box, boxes, counts)
    m, d = len(em.comp), em.d

    def red(mag, lo, hi):
        return _matrix_norm_up(mag)

    norms, n = _interval_sup(em.J_f, em.box, counts, red)
    value = float(np.max(norms))
    sampled = float("nan")
    if sample_points is not None and len(sample_points):
        from .walker import evaluate

        sp = em.J_f.sparsity_out(0)
        r, c = sp.get_triplet()
        J = np.zeros((len(sample_points), m, d))
        J[:, r, c] = evaluate(em.J_f, [sample_points])[0]
        sampled = float(np.max(np.linalg.norm(J, ord=2, axis=(1, 2))))
    return LipschitzBound(value, sampled, n, time.perf_counter() - t0,
                          "interval Jacobian on sub-boxes; ‖J‖₂ ≤ min(Frobenius, Perron) of |J|")


def lipschitz_phi(em: ErrorModel, *, boxes: int = 16384, counts=None,
                  sample_points: np.ndarray | None = None) -> LipschitzBound:
    """``K_φ``: the smaller of two rigorous bounds, both reported.

    - re-certified LipSDP-Neuron (:func:`nlyap_opt.lipschitz.lipschitz_lipsdp`; global);
    - ``sup ‖J_φ‖₂`` over the box from the interval Jacobian on sub-boxes (a Lipschitz
      constant on the convex box, which is all the bound needs).
    """
    from .lipschitz import lipschitz_lipsdp, lipschitz_sampled

    t0 = time.perf_counter()
    W0, b0, W1, factor = em.phi_weights()
    res = lipschitz_lipsdp(W0, b0, W1)
    lipsdp = _mul_up(res.value, factor)
    t1 = time.perf_counter()
    norms, n = _interval_sup(em.J_phi, em.box, _counts_for(em.box, boxes, counts),
                             lambda mag, lo, hi: _matrix_norm_up(mag))
    box_value = float(np.max(norms))
    sampled = float("nan")
    if sample_points is not None and len(sample_points):
        sampled = float(lipschitz_sampled(W0, b0, W1, sample_points))
    value = min(lipsdp, box_value)
    return LipschitzBound(value, sampled, n, time.perf_counter() - t0,
                          "min(LipSDP-Neuron re-certified, interval sup ‖J_φ‖₂ on the box)",
                          {"lipsdp": lipsdp, "interval": box_value,
                           "naive": float(res.naive), "sdp_value": float(res.sdp_value),
                           "solver": res.solver, "certified": bool(res.certified),
                           "note": res.note, "lipsdp_seconds": t1 - t0})


# ============================================================================ bound options
@dataclass
class BoundOption:
    """One sound bound ``‖f − φ‖₂ ≤ eta`` on the sampling box, with what it assumes."""

    name: str
    eta: float
    assumptions: list[str]
    terms: dict
    seconds: float = 0.0

    def to_dict(self) -> dict:
        return {"name": self.name, "eta": self.eta, "assumptions": self.assumptions,
                "terms": self.terms, "seconds": self.seconds}


def _common_assumptions(em: ErrorModel, grid: Grid) -> list[str]:
    a = [
        f"α̅ = {grid.size} grid nodes' max of ‖f − φ‖₂ (float64) plus a rigorous rounding "
        "allowance; the grid includes both ends of every axis of the sampling box",
        "samples of f are exact at the grid nodes",
    ]
    if em.model == "control_affine":
        a.append("f(x, u) = f0(x) + B u with the known constant input matrix B (checked "
                 "symbolically on the model); φ(x, u) = φ0(x) + B u, grid in x-space only")
    known = [i for i in range(em.system.nx) if i not in em.comp]
    if known:
        a.append(f"state derivatives {known} are known exactly and not learned")
    return a


def _option_global(em: ErrorModel, grid: Grid, alpha: AlphaResult, ctx: dict) -> BoundOption:
    Kf, Kphi = ctx["K_f"], ctx["K_phi"]
    eta = _add_up(alpha.alpha_upper, _mul_up(_add_up(Kf.value, Kphi.value), grid.delta))
    return BoundOption(
        "global", eta,
        _common_assumptions(em, grid) + [
            f"K_f = {Kf.value:.6g} ≥ sup ‖J_f‖₂ over the box (known Lipschitz constant of f; "
            "here rigorous from the CasADi model by interval evaluation)",
            "K_φ = min(re-certified LipSDP, interval sup ‖J_φ‖₂ on the box)",
        ],
        {"alpha_upper": alpha.alpha_upper, "K_f": Kf.value, "K_phi": Kphi.value,
         "delta": grid.delta})


def _option_anisotropic(em: ErrorModel, grid: Grid, alpha: AlphaResult, ctx: dict
                        ) -> BoundOption:
    t0 = time.perf_counter()
    counts = ctx["counts"]

    def red(mag, lo, hi):  # ‖column i of J_e‖₂
        return _norm2_up(mag, axis=1)

    cols, n = _interval_sup(em.J_e, em.box, counts, red)
    L = np.max(cols, axis=0)
    term = 0.0
    for Li, gi in zip(L, grid.gaps):
        term = _add_up(term, _mul_up(Li, _up(0.5 * gi)))
    eta = _add_up(alpha.alpha_upper, term)
    return BoundOption(
        "anisotropic", eta,
        _common_assumptions(em, grid) + [
            f"per-axis constants L_i ≥ sup ‖∂e/∂z_i‖₂ over the box from interval enclosures of "
            f"J_f − J_φ on {n} sub-boxes (needs enclosures of J_f on those sub-boxes: a known "
            "local Jacobian bound of f; here rigorous from the CasADi model)",
        ],
        {"alpha_upper": alpha.alpha_upper, "L": L.tolist(), "gaps": grid.gaps.tolist(),
         "sum_L_h_over_2": term, "n_boxes": n},
        time.perf_counter() - t0)


def _option_second_order(em: ErrorModel, grid: Grid, alpha: AlphaResult, ctx: dict
                         ) -> BoundOption:
    t0 = time.perf_counter()
    m, d = len(em.comp), em.d
    counts = ctx["counts"]

    def red(mag, lo, hi):
        return mag  # (n, m, d)

    D2, n = _interval_sup(em.D2_e, em.box, counts, red)
    D = np.max(D2, axis=0)  # (m, d)
    g2 = np.array([_up(_up(g * g) / 8.0) for g in grid.gaps])  # exact /8, rounded anyway
    per = np.array([
        _add_up(*[_mul_up(D[k, i], g2[i]) for i in range(d)]) for k in range(m)
    ])
    term = _norm2_up(per)
    eta = _add_up(alpha.alpha_upper, term)
    return BoundOption(
        "second_order", eta,
        _common_assumptions(em, grid) + [
            "f is C² on the box with |∂²f_k/∂z_i²| bounded (here rigorous from the CasADi model "
            f"by interval evaluation of the diagonal Hessian of f − φ on {n} sub-boxes)",
            "multilinear interpolation over each grid cell (corners are grid nodes)",
        ],
        {"alpha_upper": alpha.alpha_upper, "D": D.tolist(), "gaps": grid.gaps.tolist(),
         "interpolation_term": term, "n_boxes": n},
        time.perf_counter() - t0)


#: name -> function(error_model, grid, alpha, ctx) -> BoundOption (every one sound)
BOUND_OPTIONS: dict[str, Callable] = {
    "global": _option_global,
    "anisotropic": _option_anisotropic,
    "second_order": _option_second_order,
}


# ============================================================================ all bounds
@dataclass
class BoundsResult:
    """Every term of ``η`` for one dynamics network, per option; see :func:`compute_bounds`."""

    system: str
    model: str
    learned_components: list[int]
    grid: Grid
    alpha: AlphaResult
    K_f: LipschitzBound
    K_phi: LipschitzBound
    options: dict[str, BoundOption]
    selected: str
    eta_sampled: float
    n_check: int
    seconds: dict = field(default_factory=dict)

    @property
    def eta(self) -> float:
        return self.options[self.selected].eta

    @property
    def delta(self) -> float:
        return self.grid.delta

    def to_dict(self) -> dict:
        """The content of ``bounds.json``."""
        sel = self.options[self.selected]
        return {
            "format": "nlyap-dynamics-bounds", "version": 1,
            "system": self.system, "model": self.model,
            "learned_components": self.learned_components,
            "alpha": self.alpha.alpha, "alpha_upper": self.alpha.alpha_upper,
            "alpha_argmax": self.alpha.argmax.tolist(),
            "delta": self.grid.delta,
            "K_f": self.K_f.value, "K_f_sampled": self.K_f.sampled,
            "K_phi": self.K_phi.value, "K_phi_sampled": self.K_phi.sampled,
            "K_phi_naive": self.K_phi.extra.get("naive"),
            "K_phi_lipsdp": self.K_phi.extra.get("lipsdp"),
            "K_phi_interval": self.K_phi.extra.get("interval"),
            "eta": sel.eta,
            "grid": {"box": self.grid.box.tolist(), "counts": self.grid.counts.tolist(),
                     "spacing": self.grid.spacing.tolist(), "gaps": self.grid.gaps.tolist(),
                     "size": self.grid.size},
            "bound_model": {"name": sel.name, "dynamics_model": self.model,
                            "assumptions": sel.assumptions},
            "options": {k: v.to_dict() for k, v in self.options.items()},
            "check": {"eta_sampled": self.eta_sampled, "points": self.n_check,
                      "note": "max ‖f − φ‖₂ at random off-grid points of the box (a test of "
                              "the bound, not part of it)",
                      "passed": bool(all(self.eta_sampled <= o.eta
                                         for o in self.options.values()))},
            "K_f_detail": self.K_f.to_dict(), "K_phi_detail": self.K_phi.to_dict(),
            "seconds": self.seconds,
        }


def compute_bounds(system, network: Network, grid: Grid, alpha: AlphaResult | None = None, *,
                   options: list[str] | None = None, select: str = "best",
                   boxes: int = 16384, counts=None, check_points: int = 100000,
                   seed: int = 0) -> BoundsResult:
    """Compute ``K_f``, ``K_φ`` and ``η`` for every requested bound option.

    Parameters
    ----------
    system : systems.System
    network : Network
        The saved dynamics network (its ``meta`` names the model and learned components).
    grid : Grid
        The grid that defines δ (α must have been measured on it; measured here if
        ``alpha`` is None).
    options : list of str, optional
        Names in :data:`BOUND_OPTIONS` (default: all).
    select : str
        Option reported as ``eta``: a name, or ``"best"`` (smallest η; every option is sound,
        so the minimum is too).
    boxes, counts
        Sub-boxes for the interval bounds: about ``boxes`` in total, or ``counts`` per axis.
    check_points : int
        Random off-grid points where ``‖f − φ‖₂`` is evaluated as a test of the bound.
    """
    t_all = time.perf_counter()
    names = list(options or BOUND_OPTIONS)
    for nm in names:
        if nm not in BOUND_OPTIONS:
            raise UnknownNameError(
                f"unknown bound option {nm!r}; available: {', '.join(BOUND_OPTIONS)}"
            )
    if select != "best" and select not in names:
        raise UnknownNameError(f"selected bound {select!r} is not among the options {names}")
    em = ErrorModel(system, network, grid.box)
    if grid.dim != em.d:
        raise DimensionError(f"grid has {grid.dim} axes, the network takes {em.d} inputs")
    seconds: dict[str, float] = {}
    if alpha is None:
        alpha = measure_alpha(system, network, grid)
        seconds["alpha"] = alpha.seconds
    rng = np.random.default_rng(seed)
    corners = np.array(np.meshgrid(*grid.box, indexing="ij")).reshape(grid.dim, -1).T
    nodes = np.vstack([grid.sample(min(20000, grid.size), rng), corners])  # corners are nodes
    ctx = {"counts": _counts_for(em.box, boxes, counts)}
    t0 = time.perf_counter()
    ctx["K_f"] = lipschitz_f(em, counts=ctx["counts"], sample_points=nodes)
    seconds["K_f"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    ctx["K_phi"] = lipschitz_phi(em, counts=ctx["counts"], sample_points=nodes)
    seconds["K_phi"] = time.perf_counter() - t0
    opts = {}
    for nm in names:
        t0 = time.perf_counter()
        opts[nm] = BOUND_OPTIONS[nm](em, grid, alpha, ctx)
        seconds[nm] = time.perf_counter() - t0
    selected = min(opts, key=lambda k: opts[k].eta) if select == "best" else select
    t0 = time.perf_counter()
    eta_s = _sampled_error(em, int(check_points), rng)
    seconds["check"] = time.perf_counter() - t0
    seconds["bounds"] = time.perf_counter() - t_all - seconds.get("alpha", 0.0)
    return BoundsResult(system.name, em.model, em.comp, grid, alpha, ctx["K_f"], ctx["K_phi"],
                        opts, selected, eta_s, int(check_points), seconds)


def _sampled_error(em: ErrorModel, n: int, rng: np.random.Generator) -> float:
    """max ‖f − φ‖₂ over random points of ``Z`` (for control-affine: random u in U, true f)."""
    s, best = em.system, 0.0
    nx = s.nx
    for a in range(0, n, 1 << 16):
        k = min(1 << 16, n - a)
        z = rng.uniform(em.box[:, 0], em.box[:, 1], size=(k, em.d))
        if em.model == "control_affine":
            u = rng.uniform(s.input_box[:, 0], s.input_box[:, 1], size=(k, s.nu)) if s.nu \
                else np.zeros((k, 0))
            B = np.asarray(em.network.meta.get("input_matrix", np.zeros((len(em.comp), s.nu))),
                           dtype=float).reshape(len(em.comp), s.nu)
            e = s.evaluate(z, u)[:, em.comp] - em.network.numpy(z) - u @ B.T
        else:
            e = s.evaluate(z[:, :nx], z[:, nx:])[:, em.comp] - em.network.numpy(z)
        best = max(best, float(np.max(np.linalg.norm(e, axis=1))))
    return best


# ============================================================================ M, κ ∈ U, β
@dataclass
class GradientBound:
    """``M ≥ sup_R ‖∇V‖₂`` (rigorous) with the sampled maximum and the controller's range."""

    M: float
    sampled: float
    n_boxes: int
    seconds: float
    input_range: np.ndarray | None = None  # (nu, 2) enclosure of κ over R


def _as_function(obj, n_in: int, what: str) -> ca.Function:
    if isinstance(obj, Network):
        if obj.n_in != n_in:
            raise DimensionError(f"{what} network takes {obj.n_in} inputs, expected {n_in}")
        return obj.function(what)
    if isinstance(obj, ca.Function):
        if obj.n_in() != 1 or obj.nnz_in(0) != n_in:
            raise DimensionError(f"{what} Function must take one input of size {n_in}")
        return obj
    raise TypeError(f"{what} must be a Network or a casadi.Function, got {type(obj).__name__}")


def _grad_function(V, n: int) -> ca.Function:
    f = _as_function(V, n, "V")
    if f.nnz_out(0) != 1:
        raise DimensionError(f"V must be scalar, its output has {f.nnz_out(0)} entries")
    if f.is_a("SXFunction"):
        x = ca.SX.sym("x", n)
    else:
        x = ca.MX.sym("x", n)
    return ca.Function("grad_V", [x], [ca.gradient(f(x), x)])


def gradient_bound(V, region_box, *, boxes: int = 4096, counts=None, controller=None,
                   input_box=None, state_box=None, sample_points: int = 10000,
                   seed: int = 0) -> GradientBound:
    r"""Rigorous ``M ≥ sup ‖∇V(x)‖₂`` over a box, and the check ``κ(x) ∈ U`` there.

    Parameters
    ----------
    V : Network or casadi.Function
        Scalar function of ``x`` (``nx`` inputs).
    region_box : (nx, 2) array_like
        A box containing the verification region (e.g. the bounding box of the ball).
    boxes, counts
        Subdivision for the interval gradient: about ``boxes`` sub-boxes, or ``counts`` per axis.
    controller : Network or casadi.Function, optional
        ``κ``; with ``input_box`` its range over the region must lie in ``U``
        (:func:`check_input_range`), else the dynamics bound does not apply.
    state_box : (nx, 2) array_like, optional
        The box X of the dynamics bound; the region must lie inside it.

    Returns
    -------
    GradientBound

    Raises
    ------
    InputRangeError
        The controller's range on the region is not provably inside ``input_box``, or the
        region leaves ``state_box``.
    """
    t0 = time.perf_counter()
    region = np.asarray(region_box, dtype=float)
    if region.ndim != 2 or region.shape[1] != 2 or np.any(region[:, 0] > region[:, 1]):
        raise DimensionError(f"region_box must have shape (nx, 2) with lo <= hi, got {region}")
    n = region.shape[0]
    if state_box is not None:
        X = np.asarray(state_box, dtype=float)
        if np.any(region[:, 0] < X[:, 0]) or np.any(region[:, 1] > X[:, 1]):
            raise InputRangeError(
                f"the region {region.tolist()} leaves the state box {X.tolist()} on which the "
                "dynamics bound η holds; shrink the region or learn φ on a larger box"
            )
    rng_box = None
    if controller is not None:
        if input_box is None:
            raise ConfigError("give input_box (U) to check the controller's range")
        rng_box = check_input_range(controller, region, input_box, boxes=boxes)
    g = _grad_function(V, n)
    counts = _counts_for(region, boxes, counts)
    norms, nb = _interval_sup(g, region, counts,
                              lambda mag, lo, hi: _norm2_up(mag.reshape(mag.shape[0], -1), axis=1))
    M = float(np.max(norms))
    sampled = float("nan")
    if sample_points:
        from .walker import evaluate

        pts = np.random.default_rng(seed).uniform(region[:, 0], region[:, 1],
                                                  size=(int(sample_points), n))
        sampled = float(np.max(np.linalg.norm(evaluate(g, [pts])[0], axis=1)))
    return GradientBound(M, sampled, nb, time.perf_counter() - t0, rng_box)


def _controller_enclosure(controller, lo: np.ndarray, hi: np.ndarray):
    """Interval enclosure of κ on boxes ``[lo, hi]``; a saturating last layer is clamped.

    For a Network whose last activation is ``tanh`` (or ``sigmoid``) the pre-activation is
    enclosed by interval arithmetic and the activation's true range (−1, 1) (or (0, 1)) is
    used to clamp, so ``C·tanh(·)`` is provably within ``[−|C|, |C|]``.
    """
    from .walker import evaluate

    Interval, ia = _ia()
    if isinstance(controller, Network) and controller.layers[-1].activation in ("tanh",
                                                                                 "sigmoid"):
        act = controller.layers[-1].activation
        pre = Network([*controller.layers[:-1],
                       type(controller.layers[-1])(controller.layers[-1].weight,
                                                   controller.layers[-1].bias, "linear")])
        p = evaluate(pre.function("pre"), [Interval(lo, hi)], ia)[0]
        out = ia.unary(ca.OP_TANH, p) if act == "tanh" else \
            ia.binary(ca.OP_DIV, ia.constant(np.ones(1)),
                      ia.binary(ca.OP_ADD, ia.constant(np.ones(1)),
                                ia.unary(ca.OP_EXP, ia.unary(ca.OP_NEG, p))))
        lo_a, hi_a = (-1.0, 1.0) if act == "tanh" else (0.0, 1.0)
        tl, th = np.clip(out.lo, lo_a, hi_a), np.clip(out.hi, lo_a, hi_a)
        c = np.broadcast_to(controller.output_scale, (controller.n_out,))
        with np.errstate(over="ignore"):
            a, b = c * tl, c * th
        ylo = np.nextafter(np.minimum(a, b), -np.inf)
        yhi = np.nextafter(np.maximum(a, b), np.inf)
        cap_lo = np.minimum(c * lo_a, c * hi_a)  # exact: c·(±1), c·0
        cap_hi = np.maximum(c * lo_a, c * hi_a)
        return np.maximum(ylo, cap_lo), np.minimum(yhi, cap_hi)
    f = _as_function(controller, lo.shape[1], "controller")
    out = evaluate(f, [Interval(lo, hi)], ia)[0]
    return out.lo, out.hi


def check_input_range(controller, region_box, input_box, *, boxes: int = 4096,
                      max_depth: int = 12) -> np.ndarray:
    """Prove ``κ(x) ∈ U`` for every ``x`` in ``region_box`` (interval enclosure on sub-boxes).

    Sub-boxes whose enclosure leaves ``U`` are bisected (widest axis) up to ``max_depth``
    times. Returns the ``(nu, 2)`` enclosure of the range.

    Raises
    ------
    InputRangeError
        With a point where κ leaves U when one is found, else the undecided box.
    """
    region = np.asarray(region_box, dtype=float)
    U = np.asarray(input_box, dtype=float).reshape(-1, 2)
    lo, hi = subboxes(region, _counts_for(region, boxes))
    rlo = np.full(U.shape[0], np.inf)
    rhi = np.full(U.shape[0], -np.inf)
    for depth in range(max_depth + 1):
        ylo, yhi = _controller_enclosure(controller, lo, hi)
        if ylo.shape[-1] != U.shape[0]:
            raise DimensionError(f"controller has {ylo.shape[-1]} outputs, U has {U.shape[0]}")
        ok = np.all((ylo >= U[:, 0]) & (yhi <= U[:, 1]), axis=1)
        rlo = np.minimum(rlo, np.min(ylo[ok], axis=0, initial=np.inf))
        rhi = np.maximum(rhi, np.max(yhi[ok], axis=0, initial=-np.inf))
        lo, hi = lo[~ok], hi[~ok]
        if lo.shape[0] == 0:
            return np.stack([rlo, rhi], axis=1)
        mid = 0.5 * (lo + hi)
        f = _as_function(controller, region.shape[0], "controller") \
            if not isinstance(controller, Network) else controller.function("k")
        from .walker import evaluate

        val = evaluate(f, [mid])[0]
        bad = np.any((val < U[:, 0]) | (val > U[:, 1]), axis=1)
        if np.any(bad):
            k = int(np.argmax(bad))
            raise InputRangeError(
                f"the controller leaves the input box U = {U.tolist()} on the region: "
                f"κ({mid[k].tolist()}) = {val[k].tolist()}; the dynamics bound η holds only "
                "for u in U (saturate the controller, e.g. u = C·tanh(·) with C inside U, or "
                "shrink the region)"
            )
        if depth == max_depth or lo.shape[0] > 1 << 16:
            break
        axis = np.argmax(hi - lo, axis=1)
        rows = np.arange(lo.shape[0])
        cut = mid[rows, axis]
        lo2, hi2 = lo.copy(), hi.copy()
        hi[rows, axis] = cut
        lo2[rows, axis] = cut
        lo, hi = np.vstack([lo, lo2]), np.vstack([hi, hi2])
    raise InputRangeError(
        f"could not prove that the controller stays in U = {U.tolist()} on the region "
        f"(box [{lo[0].tolist()}, {hi[0].tolist()}] undecided after {max_depth} bisections); "
        "the dynamics bound needs κ(x) ∈ U: saturate the controller inside U"
    )


def margin(M: float, eta: float) -> float:
    r"""The margin ``β = M·η``, rounded upward; verify :math:`\nabla V\cdot\varphi < -\beta`.

    With :math:`\|\nabla V\| \le M` and :math:`\|f - \varphi\| \le \eta` the strict inequality
    gives :math:`\nabla V \cdot f < 0`. A non-strict check would not.
    """
    M, eta = float(M), float(eta)
    if not (M >= 0 and eta >= 0 and math.isfinite(M) and math.isfinite(eta)):
        raise ConfigError(f"margin needs finite non-negative M and η, got M={M}, η={eta}")
    return _mul_up(M, eta)


# ============================================================================ output
def write_bounds(path, bounds: BoundsResult, extra_seconds: dict | None = None,
                 network_path: str | None = None) -> Path:
    """Write ``bounds.json`` (every term, the option used and its assumptions, timings)."""
    d = bounds.to_dict()
    if extra_seconds:
        d["seconds"] = {**extra_seconds, **d["seconds"]}
        d["seconds"]["total"] = sum(v for k, v in d["seconds"].items()
                                    if k in ("data", "training", "alpha", "bounds"))
    path = Path(path)
    if network_path is not None:
        import hashlib

        network_path = Path(network_path)
        shown = network_path.name if network_path.parent == path.parent else str(network_path)
        d["network"] = {"path": shown,
                        "sha256": hashlib.sha256(Path(network_path).read_bytes()).hexdigest()}
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(_finite(d), indent=1, allow_nan=False, ensure_ascii=False))
    return path


def _finite(obj):
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else str(obj)
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if isinstance(obj, np.generic):
        return _finite(obj.item())
    return obj


def format_table(bounds: BoundsResult, seconds: dict | None = None) -> str:
    """A table like the paper's: K_f, K_φ, δ, α, η per option (and grid, times)."""
    g = bounds.grid
    lines = [
        f"system {bounds.system}  model {bounds.model}  learned components "
        f"{bounds.learned_components}",
        f"grid {' x '.join(str(c) for c in g.counts)} = {g.size} nodes, spacing "
        f"{', '.join(f'{h:.3g}' for h in g.spacing)}",
        f"{'K_f':>10s} {'K_φ':>10s} {'δ':>10s} {'α':>10s} {'α̅':>10s}",
        f"{bounds.K_f.value:10.4g} {bounds.K_phi.value:10.4g} {g.delta:10.3e} "
        f"{bounds.alpha.alpha:10.3e} {bounds.alpha.alpha_upper:10.3e}",
        f"(sampled: K_f {bounds.K_f.sampled:.4g}, K_φ {bounds.K_phi.sampled:.4g}; K_φ: LipSDP "
        f"{bounds.K_phi.extra.get('lipsdp', float('nan')):.4g}, interval "
        f"{bounds.K_phi.extra.get('interval', float('nan')):.4g}, naive "
        f"{bounds.K_phi.extra.get('naive', float('nan')):.4g})",
        f"{'option':14s} {'η':>11s}",
    ]
    for name, opt in bounds.options.items():
        mark = "  <- used" if name == bounds.selected else ""
        lines.append(f"{name:14s} {opt.eta:11.4e}{mark}")
    lines.append(f"check: max ‖f − φ‖ at {bounds.n_check} random points = "
                 f"{bounds.eta_sampled:.3e}")
    if seconds:
        lines.append("seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in seconds.items()))
    return "\n".join(lines)


# ============================================================================ CLI
def cmd_learn_dynamics(args) -> int:
    import systems

    from .dynamics import learn_dynamics, load_config

    cfg = load_config(args.config, args.system, fast=args.fast)
    if args.model:
        cfg["model"] = args.model
    if args.bound:
        cfg["bound_model"] = args.bound
    if args.seed is not None:
        cfg["seed"] = args.seed
    if args.time_budget is not None:
        cfg["time_budget"] = args.time_budget
    if args.no_progress:
        cfg["progress"] = False
    system = systems.get(args.system)
    res = learn_dynamics(system, cfg)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    net_path = res.network.save(out / "dynamics.json")
    b = compute_bounds(system, res.network, res.grid, res.alpha,
                       options=cfg.get("bound_options"), select=cfg["bound_model"],
                       boxes=int(cfg["interval_boxes"]), counts=cfg.get("interval_counts"),
                       check_points=int(cfg["check_points"]), seed=int(cfg["seed"]))
    seconds = {"data": res.seconds["data"], "training": res.seconds["training"],
               "alpha": res.seconds["alpha"]}
    write_bounds(out / "bounds.json", b, seconds, net_path)
    secs = {**seconds, "bounds": b.seconds["bounds"]}
    print(format_table(b, secs))
    print(f"wrote {net_path} and {out / 'bounds.json'}")
    return 0


def register_cli(sub) -> None:
    """Add ``nlyap learn-dynamics NAME [--config FILE] --out DIR`` to a subparsers object."""
    sp = sub.add_parser("learn-dynamics",
                        help="learn φ ≈ f on a grid and compute α, δ, K_f, K_φ, η")
    sp.add_argument("system", help="catalogue system name")
    sp.add_argument("--config", help="JSON file overriding the default configuration")
    sp.add_argument("--out", required=True, help="directory for dynamics.json and bounds.json")
    sp.add_argument("--fast", action="store_true", help="tiny configuration (seconds)")
    sp.add_argument("--model", choices=["full", "control_affine"])
    sp.add_argument("--bound", help=f"bound option: best or one of {', '.join(BOUND_OPTIONS)}")
    sp.add_argument("--seed", type=int)
    sp.add_argument("--time-budget", type=float, dest="time_budget")
    sp.add_argument("--no-progress", action="store_true", dest="no_progress")
    sp.set_defaults(func=cmd_learn_dynamics)
