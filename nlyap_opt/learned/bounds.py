r"""The gradient bound M, the input-range check κ ∈ U, and the margin β = M·η.

With :math:`\|f - \varphi\|_2 \le \eta` on the sampling box (:mod:`nlyap_opt.learned.error_models`),
:math:`M \ge \sup_R \|\nabla V\|_2` on the verification region :math:`R` (with
:math:`\kappa(R) \subseteq U` checked, and :math:`R` inside the state box) and the decrease
verified with the margin :math:`\beta = M\eta`, **strictly**:
:math:`\nabla V \cdot \varphi < -\beta` implies
:math:`\nabla V \cdot f \le \nabla V\cdot\varphi + \|\nabla V\|\,\|e\| < -\beta + M\eta = 0`.

Every sup is a rigorous upper bound (:mod:`nlyap_opt.learned.interval_sup`). The κ ∈ U check is a
bisection of its own and not a :func:`verification.verify` call: it needs the non-strict
``κ(x) ∈ U`` with a saturating last layer clamped to its true range (a controller
``C·tanh(·)`` with ``C`` at the actuator limit touches the bound in floating point), which
the verifier's strict properties ``p(x) < 0`` cannot state.

The error model and the η options moved to :mod:`nlyap_opt.learned.error_models`; their names are
re-exported here.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import casadi as ca
import numpy as np

from ..kernel.errors import ConfigError, DimensionError, InputRangeError
from ..kernel.grid import norm2_up
from ..kernel.network import Network
from ..kernel.rounding import mul_up
from ..kernel.walker import evaluate
from .error_models import (
    BOUND_OPTIONS,
    BoundOption,
    BoundsResult,
    ErrorModel,
    LipschitzBound,
    compute_bounds,
    format_table,
    lipschitz_f,
    lipschitz_phi,
    write_bounds,
)
from .interval_sup import counts_for, interval_arithmetic, interval_sup, subboxes

__all__ = [
    "BOUND_OPTIONS", "BoundOption", "BoundsResult", "GradientBound", "LipschitzBound",
    "ErrorModel", "compute_bounds", "lipschitz_f", "lipschitz_phi", "gradient_bound",
    "check_input_range", "margin", "subboxes", "write_bounds", "format_table",
]


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
        if obj.n_out() and not obj.sparsity_out(0).is_dense():  # read by position: densify
            x = ca.MX.sym("x", obj.size_in(0))
            return ca.Function(what, [x], [ca.densify(obj(x))])
        return obj
    if callable(getattr(obj, "casadi", None)) \
            and getattr(obj, "nx", getattr(obj, "n_in", None)) == n_in:
        x = ca.SX.sym("x", n_in)      # a polynomial V (an SOS certificate), or a saved graph
        return ca.Function(what, [x], [obj.casadi(x)])
    raise TypeError(f"{what} must be a Network, a polynomial or a casadi.Function, got "
                    f"{type(obj).__name__}")


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
    counts = counts_for(region, boxes, counts)
    norms, nb = interval_sup(g, region, counts,
                              lambda mag, lo, hi: norm2_up(mag.reshape(mag.shape[0], -1), axis=1))
    M = float(np.max(norms))
    sampled = float("nan")
    if sample_points:
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

    Interval, ia = interval_arithmetic()
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
    lo, hi = subboxes(region, counts_for(region, boxes))
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
    return mul_up(M, eta)
