r"""The error model of learned dynamics and its sound bounds η (K_f, K_φ, options).

For learned dynamics :math:`\varphi` (see :mod:`nlyap_opt.learned.dynamics`) the certificate needs

.. math:: \|e(z)\|_2 \le \eta \ \ \forall z \in Z, \qquad e = f - \varphi,

on the sampling box :math:`Z` (:math:`X \times U`, or :math:`X` for the control-affine
model). This module builds the error model and every sound bound η; the gradient bound
``M``, the check ``κ(R) ⊆ U`` and the margin ``β = M·η`` are in :mod:`nlyap_opt.learned.bounds`.

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

The dynamics model ``control_affine`` (:mod:`nlyap_opt.learned.dynamics`) combines with each option:
the grid lives in x-space and :math:`e(x, u) = f_0(x) - \varphi_0(x)` for every u, under the
assumption :math:`f = f_0(x) + Bu` with the known constant B (checked symbolically on the
model). A per-cell (local-constant) variant is not provided; the same options on a sub-box of
``Z``, from a grid of its own, are :func:`nlyap_opt.learned.local_bound.local_bound`.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from ..kernel.errors import ConfigError, DimensionError, UnknownNameError
from ..kernel.grid import norm2_up
from ..kernel.jsonio import save_timings, split_timings, write_atomic
from ..kernel.network import Network
from ..kernel.rounding import add_up, mul_up, next_up
from ..kernel.walker import evaluate
from .dynamics import (
    AlphaResult,
    Grid,
    check_dynamics_network,
    declared_dependencies,
    measure_alpha,
)
from .interval_sup import counts_for, interval_sup, matrix_norm_up
from .lipschitz import lipschitz_lipsdp, lipschitz_sampled

__all__ = [
    "BOUND_OPTIONS", "BoundOption", "BoundsResult", "LipschitzBound", "ErrorModel",
    "compute_bounds", "lipschitz_f", "lipschitz_phi", "write_bounds", "format_table",
]


# ============================================================================ the error model
class ErrorModel:
    r"""The error :math:`e = f - \varphi` of a dynamics network on its sampling box.

    Builds (once) the CasADi Functions of ``z`` used by the bounds: ``J_f`` (learned rows of
    the Jacobian of the true model w.r.t. the sampled variables ``z``), ``J_phi``, ``J_e``,
    ``D2_phi`` and ``D2_e`` (diagonal second derivatives, shape ``m × d``). Without a model
    (``system.has_model`` False: a black-box callable or samples) only ``J_phi`` and
    ``D2_phi`` exist (``has_f`` False; the others are ``None``) and ``f`` enters the bounds
    through the user's declarations (:class:`systems.Declarations`).

    Parameters
    ----------
    system : systems.System
    network : Network
        One hidden tanh layer, linear output, ``meta`` as written by
        :func:`nlyap_opt.learned.dynamics.learn_dynamics`.
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
        #: True when the CasADi model of f is available (False: a black box or samples)
        self.has_f = bool(getattr(system, "has_model", True))
        zm = ca.MX.sym("z", self.d)
        jphi, d2phi = self._phi_derivatives(zm)
        self.J_phi = ca.Function("J_phi", [zm], [jphi])
        self.D2_phi = ca.Function("D2_phi", [zm], [d2phi])
        self.f_fun = self.J_f = self.D2_f = self.J_e = self.D2_e = None
        if not self.has_f:  # only φ's derivatives; f enters through declarations
            return
        z = ca.SX.sym("z", self.d)
        u = ca.SX.zeros(system.nu) if self.model == "control_affine" else z[nx:]
        fz = system.f_fun(z[:nx], u)[self.comp]
        self.f_fun = ca.Function("f_z", [z], [fz])
        jf = ca.jacobian(fz, z)
        self.J_f = ca.Function("J_f", [z], [jf])
        d2f = ca.horzcat(*[ca.jacobian(jf[:, i], z)[:, i] for i in range(self.d)])
        self.D2_f = ca.Function("D2_f", [z], [d2f])
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

    Without a model the **declared** Lipschitz constant of the learned components is used
    (:meth:`systems.Declarations.lipschitz_bound`; a per-component declaration gives
    :math:`\|(K_k)_k\|_2`); its ``sampled`` value is the largest finite-difference slope
    between neighbouring grid nodes (a lower bound of any Lipschitz constant), when known.
    Nothing declared: ``value`` is NaN and ``method`` says why (the bounds that need
    ``K_f`` are then skipped, never faked).
    """
    if not em.has_f:
        return _declared_lipschitz(em)
    t0 = time.perf_counter()
    counts = counts_for(em.box, boxes, counts)
    m, d = len(em.comp), em.d

    def red(mag, lo, hi):
        return matrix_norm_up(mag)

    norms, n = interval_sup(em.J_f, em.box, counts, red)
    value = float(np.max(norms))
    sampled = float("nan")
    if sample_points is not None and len(sample_points):
        sp = em.J_f.sparsity_out(0)
        r, c = sp.get_triplet()
        J = np.zeros((len(sample_points), m, d))
        J[:, r, c] = evaluate(em.J_f, [sample_points])[0]
        sampled = float(np.max(np.linalg.norm(J, ord=2, axis=(1, 2))))
    return LipschitzBound(value, sampled, n, time.perf_counter() - t0,
                          "interval Jacobian on sub-boxes; ‖J‖₂ ≤ min(Frobenius, Perron) of |J|")


def _declared_lipschitz(em: ErrorModel) -> LipschitzBound:
    decl = getattr(em.system, "declarations", None)
    check = em.network.meta.get("declarations_check") if isinstance(em.network.meta, dict) \
        else None
    sampled = float("nan")
    if isinstance(check, dict):
        per = check.get("slope_per_component")
        if per is not None and len(per) == em.system.nx:
            sampled = float(np.sqrt(np.sum(np.square(np.asarray(per, float)[em.comp]))))
    value = None if decl is None else decl.lipschitz_bound(em.comp)
    if value is None:
        return LipschitzBound(float("nan"), sampled, 0, 0.0,
                              f"not available: system {em.system.name!r} has no model and "
                              "declares no Lipschitz constant (declare lipschitz)",
                              {"source": "none"})
    return LipschitzBound(float(value), sampled, 0, 0.0,
                          "declared by the user (Declarations.lipschitz); sampled: the largest "
                          "neighbour slope of the grid data (a lower bound)",
                          {"source": "declared",
                           "declared": decl.to_dict()["lipschitz"]})


class _Skip(Exception):
    """A bound option that cannot be computed soundly here (the reason is reported)."""


def lipschitz_phi(em: ErrorModel, *, boxes: int = 16384, counts=None,
                  sample_points: np.ndarray | None = None) -> LipschitzBound:
    """``K_φ``: the smaller of two rigorous bounds, both reported.

    - re-certified LipSDP-Neuron (:func:`nlyap_opt.learned.lipschitz.lipschitz_lipsdp`; global);
    - ``sup ‖J_φ‖₂`` over the box from the interval Jacobian on sub-boxes (a Lipschitz
      constant on the convex box, which is all the bound needs).
    """

    t0 = time.perf_counter()
    W0, b0, W1, factor = em.phi_weights()
    res = lipschitz_lipsdp(W0, b0, W1)
    lipsdp = mul_up(res.value, factor)
    t1 = time.perf_counter()
    norms, n = interval_sup(em.J_phi, em.box, counts_for(em.box, boxes, counts),
                             lambda mag, lo, hi: matrix_norm_up(mag))
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
    ]
    decl = getattr(em.system, "declarations", None)
    eps = None if decl is None else decl.sample_error
    kind = getattr(em.system, "kind", "model")
    if em.has_f:
        a.append("samples of f are exact at the grid nodes")
    elif eps is not None:
        a.append(f"the {kind} data are within the declared sample error ε = {eps:.6g} of f "
                 "(added to α̅)")
    else:
        a.append(f"the {kind} data are the exact values of f at the grid nodes (assumed)")
    offset = float(getattr(grid, "offset", 0.0) or 0.0)
    if offset > 0:
        a.append(f"δ includes the sample file's offset {offset:.3g} of its rows from the "
                 "regular grid nodes")
    if em.model == "control_affine":
        how = "checked symbolically on the model" if em.has_f else \
            "declared by the user, checked on the data where an input axis was sampled"
        a.append(f"f(x, u) = f0(x) + B u with the known constant input matrix B ({how}); "
                 "φ(x, u) = φ0(x) + B u, grid in x-space only")
    known = [i for i in range(em.system.nx) if i not in em.comp]
    if known:
        a.append(f"state derivatives {known} are known exactly and not learned")
    return a


def _option_global(em: ErrorModel, grid: Grid, alpha: AlphaResult, ctx: dict) -> BoundOption:
    Kf, Kphi = ctx["K_f"], ctx["K_phi"]
    if not math.isfinite(Kf.value):
        raise _Skip(f"needs a Lipschitz constant K_f of f: {Kf.method}")
    eta = add_up(alpha.alpha_upper, mul_up(add_up(Kf.value, Kphi.value), grid.delta))
    kf_text = (f"K_f = {Kf.value:.6g} ≥ sup ‖J_f‖₂ over the box (known Lipschitz constant of "
               "f; here rigorous from the CasADi model by interval evaluation)") if em.has_f \
        else (f"K_f = {Kf.value:.6g}: the Lipschitz constant of f on the sampling box "
              "declared by the user (for the learned components); δ is the covering radius "
              "of the very nodes on which α was measured")
    return BoundOption(
        "global", eta,
        _common_assumptions(em, grid) + [
            kf_text,
            "K_φ = min(re-certified LipSDP, interval sup ‖J_φ‖₂ on the box)",
        ],
        {"alpha_upper": alpha.alpha_upper, "K_f": Kf.value, "K_phi": Kphi.value,
         "delta": grid.delta})


def _option_anisotropic(em: ErrorModel, grid: Grid, alpha: AlphaResult, ctx: dict
                        ) -> BoundOption:
    if not em.has_f:
        raise _Skip("needs interval enclosures of J_f on sub-boxes, i.e. a CasADi model of f; "
                    f"system {em.system.name!r} is a {getattr(em.system, 'kind', '?')} system")
    t0 = time.perf_counter()
    counts = ctx["counts"]

    def red(mag, lo, hi):  # ‖column i of J_e‖₂
        return norm2_up(mag, axis=1)

    cols, n = interval_sup(em.J_e, em.box, counts, red)
    L = np.max(cols, axis=0)
    term = 0.0
    for Li, gi in zip(L, grid.gaps):
        term = add_up(term, mul_up(Li, next_up(0.5 * gi)))
    eta = add_up(alpha.alpha_upper, term)
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

    H = None
    if not em.has_f:
        decl = getattr(em.system, "declarations", None)
        H = None if decl is None else decl.hessian_max()
        if H is None:
            raise _Skip("needs a bound on the second derivatives of f: declare hessian (H) "
                        f"(system {em.system.name!r} has no model)")
        if float(getattr(grid, "offset", 0.0) or 0.0) > 0:
            raise _Skip("the sample file's rows are off the regular nodes (offset "
                        f"{grid.offset:.3g}); the interpolation bound needs values at the "
                        "nodes (write the file with 17 significant digits)")
        # |∂²_i e_k| ≤ |∂²_i f_k| + |∂²_i φ_k| ≤ H + sup |∂²_i φ_k|; ∂²_i f_k ≡ 0 along a
        # variable z_i that f_k is declared not to depend on (Declarations.depends_on)
        D2p, n = interval_sup(em.D2_phi, em.box, counts, red)
        deps = declared_dependencies(em.system, d)
        Hk = np.array([[decl.hessian_of(k) if k not in deps or i in deps[k] else 0.0
                        for i in range(d)] for k in em.comp])
        D = np.vectorize(add_up)(Hk, np.max(D2p, axis=0))
    else:
        D2, n = interval_sup(em.D2_e, em.box, counts, red)
        D = np.max(D2, axis=0)  # (m, d)
    g2 = np.array([next_up(next_up(g * g) / 8.0) for g in grid.gaps])  # exact /8, rounded anyway
    per = np.array([
        add_up(*[mul_up(D[k, i], g2[i]) for i in range(d)]) for k in range(m)
    ])
    term = norm2_up(per)
    eta = add_up(alpha.alpha_upper, term)
    how = ("here rigorous from the CasADi model by interval evaluation of the diagonal "
           f"Hessian of f − φ on {n} sub-boxes") if H is None else \
        (("declared by the user: |∂²f_k/∂z_i∂z_j| ≤ "
          + (f"H_k per component (the largest {H:.6g})"
             if isinstance(em.system.declarations.hessian, tuple) else f"H = {H:.6g}"))
         + "; D = H + the interval sup of "
         f"|∂²φ_k/∂z_i²| on {n} sub-boxes"
         + ("; H is 0 along the variables f_k is declared not to depend on (depends_on)"
            if deps else ""))
    return BoundOption(
        "second_order", eta,
        _common_assumptions(em, grid) + [
            f"f is C² on the box with |∂²f_k/∂z_i²| bounded ({how})",
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
    skipped: dict = field(default_factory=dict)
    declarations_check: dict | None = None
    system_kind: str = "model"

    @property
    def eta(self) -> float:
        return self.options[self.selected].eta

    @property
    def delta(self) -> float:
        return self.grid.delta

    def _check_dict(self) -> dict:
        if not math.isfinite(self.eta_sampled):
            return {"eta_sampled": None, "points": 0, "passed": None,
                    "note": "not available: f is known at the sample nodes only (no off-grid "
                            "values to test the bound with)"}
        return {"eta_sampled": self.eta_sampled, "points": self.n_check,
                "note": "max ‖f − φ‖₂ at random off-grid points of the box (a test of "
                        "the bound, not part of it)",
                "passed": bool(all(self.eta_sampled <= o.eta for o in self.options.values()))}

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
            "options_skipped": dict(self.skipped),
            "system_kind": self.system_kind,
            "K_f_source": self.K_f.extra.get("source", "interval"),
            "declarations_check": self.declarations_check,
            "check": self._check_dict(),
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
        Random off-grid points where ``‖f − φ‖₂`` is evaluated as a test of the bound
        (not for a ``"samples"`` system: ``f`` is known at the nodes only).

    Notes
    -----
    For a system without a model the options use what the user declared (``K_f`` for
    ``global``, ``H`` for ``second_order``); an option that cannot be computed soundly is
    skipped and its reason recorded (``skipped``, ``bounds.json["options_skipped"]``).

    Raises
    ------
    ConfigError
        No requested option can be computed (e.g. no model and no declared ``K_f`` or
        ``H``), or ``select`` names a skipped option.
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
    ctx = {"counts": counts_for(em.box, boxes, counts)}
    t0 = time.perf_counter()
    ctx["K_f"] = lipschitz_f(em, counts=ctx["counts"], sample_points=nodes)
    seconds["K_f"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    ctx["K_phi"] = lipschitz_phi(em, counts=ctx["counts"], sample_points=nodes)
    seconds["K_phi"] = time.perf_counter() - t0
    opts, skipped = {}, {}
    for nm in names:
        t0 = time.perf_counter()
        try:
            opts[nm] = BOUND_OPTIONS[nm](em, grid, alpha, ctx)
        except _Skip as why:
            skipped[nm] = str(why)
        seconds[nm] = time.perf_counter() - t0
    if not opts:
        raise ConfigError(
            f"no sound bound on ‖f − φ‖ for system {system.name!r}: "
            + "; ".join(f"{k}: {v}" for k, v in skipped.items())
            + "; declare lipschitz (K_f) or hessian (H)"
        )
    if select != "best" and select in skipped:
        raise ConfigError(f"bound option {select!r} is not available for system "
                          f"{system.name!r}: {skipped[select]}; choose bound_model 'best'")
    selected = min(opts, key=lambda k: opts[k].eta) if select == "best" else select
    t0 = time.perf_counter()
    eta_s = _sampled_error(em, int(check_points), rng)
    seconds["check"] = time.perf_counter() - t0
    seconds["bounds"] = time.perf_counter() - t_all - seconds.get("alpha", 0.0)
    meta = network.meta if isinstance(network.meta, dict) else {}
    return BoundsResult(system.name, em.model, em.comp, grid, alpha, ctx["K_f"], ctx["K_phi"],
                        opts, selected, eta_s, int(check_points), seconds, skipped,
                        meta.get("declarations_check"), getattr(system, "kind", "model"))


def _sampled_error(em: ErrorModel, n: int, rng: np.random.Generator) -> float:
    """max ‖f − φ‖₂ over random points of ``Z`` (for control-affine: random u in U, true f)."""
    s, best = em.system, 0.0
    nx = s.nx
    if not getattr(s, "can_simulate", True):  # samples: f is known at the nodes only
        return float("nan")
    for a in range(0, n, 1 << 16):
        k = min(1 << 16, n - a)
        z = rng.uniform(em.box[:, 0], em.box[:, 1], size=(k, em.d))
        if em.model == "control_affine":
            u = rng.uniform(s.input_box[:, 0], s.input_box[:, 1], size=(k, s.nu)) if s.nu \
                else np.zeros((k, 0))
            # a black box may model B only approximately: this is a test, not a bound
            B = np.asarray(em.network.meta.get("input_matrix", np.zeros((len(em.comp), s.nu))),
                           dtype=float).reshape(len(em.comp), s.nu)
            e = s.evaluate(z, u)[:, em.comp] - em.network.numpy(z) - u @ B.T
        else:
            e = s.evaluate(z[:, :nx], z[:, nx:])[:, em.comp] - em.network.numpy(z)
        best = max(best, float(np.max(np.linalg.norm(e, axis=1))))
    return best


# ============================================================================ output
def write_bounds(path, bounds: BoundsResult, extra_seconds: dict | None = None,
                 network_path: str | None = None) -> Path:
    """Write ``bounds.json`` (every term, the option used and its assumptions; its timings
    go to ``timings.json`` beside it, :func:`~nlyap_opt.kernel.jsonio.load_with_timings`)."""
    d = bounds.to_dict()
    if extra_seconds:
        d["seconds"] = {**extra_seconds, **d["seconds"]}
        d["seconds"]["total"] = sum(v for k, v in d["seconds"].items()
                                    if k in ("data", "training", "alpha", "bounds"))
    path = Path(path)
    if network_path is not None:
        network_path = Path(network_path)
        shown = network_path.name if network_path.parent == path.parent else str(network_path)
        d["network"] = {"path": shown,
                        "sha256": hashlib.sha256(Path(network_path).read_bytes()).hexdigest()}
    path.parent.mkdir(parents=True, exist_ok=True)
    d, timings = split_timings(d)   # a hashed artifact: wall-clock timings go beside it
    write_atomic(path, json.dumps(_finite(d), indent=1, allow_nan=False, ensure_ascii=False))
    save_timings(path, timings)
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
