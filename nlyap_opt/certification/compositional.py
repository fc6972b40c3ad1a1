r"""Compositional certificates for interconnected systems (no bisection of the whole state).

An autonomous system :math:`\dot x = f(x)` whose states split into subsystems
:math:`x = (x_1, \dots, x_N)` (``System(subsystems=...)``) gets the Lyapunov function

.. math:: V(x) = \sum_i w_i V_i(x_i), \qquad V_i(x_i) = x_i^\top P_i x_i, \quad P_i \succ 0,

and the region of attraction :math:`\Omega_c = \{x : V(x) \le c\} \subseteq D` inside the
system's box :math:`D`. What is proved (all of it again by :func:`recheck_compositional`):

1. **Local inequalities.** For every subsystem :math:`i`, with :math:`y_i = (x_i,
   x_{N(i)})` its states and those of the subsystems its equations depend on
   (structurally, from the CasADi graph) and :math:`Y_i` the projection of :math:`D`,

   .. math:: F_i(y_i) = \nabla V_i \cdot f_i(y_i) + \alpha_i V_i(x_i)
             - \sum_{j \in N(i)} \beta_{ij} V_j(x_j) \le 0 \quad \text{on } Y_i.

   ``f(0) = 0`` is proved by evaluating ``f``'s graph at 0 in exact rational arithmetic,
   so the mean-value form :math:`f_i(y) = \bar J_i(y)\,y`, :math:`\bar J_i(y) = \int_0^1
   J_i(ty)\,dt` (``J_i`` the Jacobian of ``f_i``; the box contains 0, so :math:`t y \in
   Y_i`) gives :math:`\nabla V_i \cdot f_i = 2 x_i^\top P_i \bar J_i\, y`. The entries of
   :math:`\bar J_i` are enclosed by outward-rounded interval arithmetic over the CasADi graph
   of ``J_i`` on 16 nested slices :math:`t_k Y_i`; with the centre :math:`C` and radius
   :math:`R` of that enclosure and ``P_i`` padded with zeros to all of ``y``,
   :math:`2 x_i^\top P_i \bar J_i y \le y^\top N y`, :math:`N = PC + C^\top P +
   \mathrm{diag}((|P|R + R^\top|P|)\mathbf 1)`, formed in exact rationals (``P_i`` never
   enters a CasADi graph). Negative definiteness of :math:`N + \mathrm{blockdiag}(\alpha_i
   P_i, -\beta_{ij} P_j)` is decided by an exact :math:`LDL^\top` in
   :class:`fractions.Fraction` arithmetic. The test works on the low-dimensional
   :math:`Y_i` only: nothing bisects the whole state space.
2. **Comparison system.** The Metzler matrix :math:`A_c = -\mathrm{diag}(\alpha) + B`,
   :math:`B_{ij} = \beta_{ij}`, with weights :math:`w > 0` and
   :math:`(w^\top A_c)_j \le -\gamma w_j`, :math:`\gamma > 0`, checked exactly; then
   :math:`\dot V = \sum_i w_i \dot V_i \le \sum_j (w^\top A_c)_j V_j \le -\gamma V` wherever
   every :math:`y_i \in Y_i`.
3. **Level.** :math:`\Omega_c \subseteq D`: :math:`c \le w_i r_k^2 / (P_i^{-1})_{kk}` for
   every state :math:`k` of subsystem :math:`i` (:math:`r_k` the distance from 0 to the
   nearer face of :math:`D`), exactly. Then :math:`\Omega_c` (a compact ellipsoid) lies in
   :math:`D`, so 1–2 hold on it, :math:`V(x(t)) \le V(x(0)) e^{-\gamma t}`: it is forward
   invariant and every solution from it converges exponentially to the origin.

The numbers :math:`P_i, \alpha_i, \beta_{ij}, w, c, \gamma` are chosen in float64 (a
Lyapunov equation per subsystem, generalised eigenvalues, a linear solve); only the exact
checks above decide. The method needs a model ``f`` (the true dynamics) without inputs, built
from smooth operations defined on all of ``D``; anything else is refused with the reason.
"""

from __future__ import annotations

import json
import math
import time
import warnings
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import casadi as ca
import numpy as np
from scipy.linalg import eigh, solve_continuous_lyapunov

from ..kernel import rounding
from ..kernel.errors import ConfigError, UnsupportedOperationError
from ..kernel.exact import (
    float_down,
    float_up,
    inverse_diagonal,
    positive_definite,
    rational,
    rational_matrix,
)
from ..kernel.jsonio import read_file_bytes, save_timings, split_timings
from ..kernel.provenance import fingerprint
from ..kernel.rounding import FOLD, dn, dn_sum, up, up_roundings, up_sum
from ..kernel.walker import compile_function, evaluate, exact_values
from ..learned.interval_sup import interval_arithmetic
from .certificate import (
    CertStatus,
    bound_system,
    read_certificate_file,
    system_binding,
    write_json_atomic,
)
from .roa import TAYLOR_SLICES, mean_value_form, sliced_enclosure, split_boxes

__all__ = ["FORMAT", "VERSION", "Piece", "CompositionalCertificate", "certify_compositional",
           "check_compositional", "recheck_compositional", "save_compositional",
           "is_compositional_file"]

FORMAT = "nlyap-compositional-certificate"
VERSION = 1

#: decay fractions θ tried: α_i = θ·α_i*, α_i* the subsystem's own rate on its box
_THETAS = (0.9, 0.75, 0.5, 0.3, 0.15)

ASSUMPTIONS = [
    "the model f is the true dynamics (a compositional certificate is about the given model)",
    "f is continuously differentiable on the domain box D (its CasADi graph holds "
    "only smooth operations defined everywhere; checked)",
]

#: how the local inequalities enclose the Jacobian of f: ``"known"``, from the model's Jacobian
#: graph (interval arithmetic); ``"data"``, from values of f at finite-difference points and
#: a bound on f's second derivatives (the unknown-dynamics setting of ``nlyap run`` without
#: ``--known-dynamics``)
SETTINGS = ("known", "data")
#: pieces per axis of each subsystem's box that a run tries (both settings)
DATA_SPLITS = (1, 2, 4)
#: the most pieces (``split^m``) of one subsystem's box; a larger split is not tried (and a
#: certificate that asks for one is refused)
MAX_PIECES = 1024
#: a split is tried only while all subsystems' boxes together have at most this many pieces
#: (each piece costs exact rational checks)
MAX_TOTAL_PIECES = 1024

ASSUMPTIONS_DATA = [
    "f is the system's f, known to this certificate only through its values at "
    "finite-difference points of each subsystem's box (sampled from the simulator, each "
    "value enclosed with outward rounding) and a bound H on its second derivatives",
    "f is twice continuously differentiable on the domain box D with "
    "|d2 f_k / dy_a dy_b| <= H[k][a][b] on each subsystem's box (the hessian_bound stored "
    "per subsystem; computed from the simulator's graph by interval evaluation of the "
    "Hessian, checked again by the re-check)",
    "f_i reads only the states of subsystem i and of its neighbours, and f(0) = 0 (from "
    "the simulator's graph, in exact arithmetic)",
]


ASSUMPTIONS_DECLARED = [
    "f is the system's f, known to this certificate only through the simulator's values at "
    "finite-difference points of each subsystem's box, taken as exact (no sample_error may "
    "be declared)",
    "f is twice continuously differentiable on the domain box D with "
    "|d2 f_k / dy_a dy_b| <= H (or H_k, declared per component) for every k, a, b (declared "
    "hessian; 0 along the variables f_k is declared not to depend on)",
    "f_k reads only the states declared in depends_on (every state when it is not declared), "
    "and f(0) = 0 exactly (the simulator returns 0 at the origin)",
]


def assumptions_of(setting: str, system=None) -> list[str]:
    """The assumptions a compositional certificate of ``setting`` about ``system`` lists
    (the data setting of a simulator without a graph rests on its declarations)."""
    if setting != "data":
        return list(ASSUMPTIONS)
    if system is not None and not getattr(system, "has_model", False):
        return list(ASSUMPTIONS_DECLARED)
    return list(ASSUMPTIONS_DATA)


# ============================================================================ the certificate
@dataclass
class Piece:
    """One subsystem: its states, the subsystems its equations read, ``V_i = x_iᵀ P x_i``,
    the proved rate ``α`` and the coupling gains ``β`` (one per neighbour)."""

    states: tuple[int, ...]
    neighbours: tuple[int, ...]
    P: np.ndarray
    alpha: float = 0.0
    beta: tuple[float, ...] = ()
    #: data setting: ``H[k][a][b] ≥ |∂²f_k/∂y_a∂y_b|`` on the subsystem's box (``k`` its
    #: states, ``y`` its and its neighbours' states); ``None`` in the known setting
    hessian: np.ndarray | None = None

    def to_dict(self) -> dict:
        d = {"states": list(self.states), "neighbours": list(self.neighbours),
             "P": np.asarray(self.P, dtype=float).tolist(), "alpha": float(self.alpha),
             "beta": [float(b) for b in self.beta]}
        if self.hessian is not None:
            d["hessian_bound"] = np.asarray(self.hessian, dtype=float).tolist()
        return d


@dataclass
class CompositionalCertificate:
    """A compositional ROA certificate: ``{x : Σ w_i x_iᵀ P_i x_i ≤ level}`` when certified."""

    status: CertStatus
    reason: str
    system: str
    pieces: list[Piece]
    weights: np.ndarray
    level: float
    decay: float
    domain_box: np.ndarray
    checks: dict = field(default_factory=dict)
    assumptions: list = field(default_factory=lambda: list(ASSUMPTIONS))
    seconds: float = 0.0
    #: ``"known"`` or ``"data"`` (:data:`SETTINGS`)
    setting: str = "known"
    #: each subsystem's box is cut into ``split`` pieces along every axis
    split: int = 1

    @property
    def certified(self) -> bool:
        return self.status is CertStatus.CERTIFIED

    def V(self, points) -> np.ndarray:
        """``V(x) = Σ w_i x_iᵀ P_i x_i`` at ``(N, nx)`` points (float64, for display)."""
        pts = np.atleast_2d(np.asarray(points, dtype=float))
        out = np.zeros(len(pts))
        for w, p in zip(self.weights, self.pieces):
            xi = pts[:, list(p.states)]
            out += w * np.einsum("ni,ij,nj->n", xi, np.asarray(p.P), xi)
        return out

    def contains(self, points) -> np.ndarray:
        """Which points lie in the certified set (all False when not certified)."""
        pts = np.atleast_2d(np.asarray(points, dtype=float))
        if not self.certified:
            return np.zeros(len(pts), dtype=bool)
        return self.V(pts) <= self.level

    def summary(self) -> str:
        """One line: status, region, decay rate (or why not)."""
        if self.certified:
            head = ("certified under the declared assumptions: hessian (H); depends_on; "
                    "f(0) = 0" if self.assumptions == ASSUMPTIONS_DECLARED else "certified")
            return (f"{head}: level {self.level:.6g} of V = Σ w_i x_iᵀP_i x_i "
                    f"({len(self.pieces)} subsystems, {self.domain_box.shape[0]} states), "
                    f"dV/dt ≤ -{self.decay:.4g} V, inside the box D ("
                    + ("known dynamics" if self.setting == "known" else
                       "sampled f with a second-derivative bound") + ", compositional"
                    + ")")
        return f"{self.status.value}: {self.reason}"

    def to_dict(self) -> dict:
        return {
            "format": FORMAT, "version": VERSION, "status": self.status.value,
            "reason": self.reason, "system": self.system, "method": "compositional",
            "setting": self.setting,
            **({"split": int(self.split)} if self.setting == "data" or self.split != 1
               else {}),
            "certified_set": "{x : sum_i w_i x_i^T P_i x_i <= level}",
            "decrease_condition": "dV/dt <= -decay * V on the certified set",
            "domain_box": np.asarray(self.domain_box, dtype=float).tolist(),
            "subsystems": [p.to_dict() for p in self.pieces],
            "weights": np.asarray(self.weights, dtype=float).tolist(),
            "level": float(self.level), "decay": float(self.decay),
            "checks": dict(self.checks), "assumptions": list(self.assumptions),
            "seconds": self.seconds,
        }


# ============================================================================ structure
def _structure(system, parts) -> list[tuple[int, ...]]:
    """For each subsystem, the other subsystems its equations depend on: structurally in
    the graph of ``f``, or, for a simulator without one, as declared (``depends_on``; a
    state derivative not declared depends on every state)."""
    owner = {k: i for i, p in enumerate(parts) for k in p}
    out = []
    if not getattr(system, "has_model", False):
        deps = _declared_states(system)
        for i, p in enumerate(parts):
            dep = {owner[k] for r in p for k in deps[r]}
            out.append(tuple(sorted(dep - {i})))
        return out
    f = system.f
    for i, p in enumerate(parts):
        fi = ca.vertcat(*[f[r] for r in p])
        dep = {owner[k] for k in range(system.nx) if ca.depends_on(fi, system.x[k])}
        out.append(tuple(sorted(dep - {i})))
    return out


def _declared_states(system) -> list[tuple[int, ...]]:
    """Per state derivative ``f_k``, the states it is declared to read (all when undeclared)."""
    decl = system.declarations
    deps = {} if decl is None else decl.dependencies(system.state_names, system.input_names)
    return [tuple(c for c in deps[k] if c < system.nx) if k in deps else tuple(range(system.nx))
            for k in range(system.nx)]


def _refusal(system, parts, setting: str = "known") -> str:
    """Why the compositional method does not apply to ``system`` (``""``: it does)."""
    if not getattr(system, "has_model", False):
        if setting == "known":
            return ("a compositional certificate with --known-dynamics needs the model f; this "
                    "system has none: run without --known-dynamics to certify it from the "
                    "simulator's values and a declared second-derivative bound")
        if getattr(system, "kind", "") != "callable":
            return ("a sample file has values at its grid nodes only, and the compositional "
                    "certificate evaluates f at its own finite-difference points: give the "
                    "model ([rhs]) or a simulator (a factory returning System.from_callable), "
                    "or drop the subsystems to run the neural method on the samples")
        decl = system.declarations
        if decl is None or decl.hessian is None:
            return ("the compositional certificate of a simulator needs a bound on f's second "
                    "derivatives: declare hessian (H), and depends_on for the states each "
                    "derivative reads")
        if decl.sample_error:
            return ("the compositional certificate needs f(0) = 0 exactly, which a simulator "
                    f"with a sample error ({decl.sample_error:g} declared) cannot show: give "
                    "the model ([rhs]), or a simulator whose values are exact")
    if system.nu:
        return (f"the compositional method is for systems without inputs; {system.name!r} has "
                f"{system.nu} (close the loop in f first)")
    if parts is None:
        return (f"system {system.name!r} declares no subsystems; give "
                "System(..., subsystems=[(0, 1), (2, 3), ...])")
    return ""  # (a System's state box holds the origin inside: checked when it is built)


def _block_indices(parts, nbrs, i: int) -> list[int]:
    """Subsystem ``i``'s variables ``y``: its states, then its neighbours' in order."""
    return list(parts[i]) + [k for j in nbrs[i] for k in parts[j]]


def _block_function(system, parts, nbrs, i: int):
    """``(idx, y, f_i(y))``: subsystem ``i``'s variables (:func:`_block_indices`), their
    symbol ``y`` and ``f_i`` of them with every other state 0 (``f_i`` reads only these,
    :func:`_structure`)."""
    idx = _block_indices(parts, nbrs, i)
    y = ca.SX.sym("y", len(idx))
    xs = ca.SX.zeros(system.nx)
    for a, k in enumerate(idx):
        xs[k] = y[a]
    return idx, y, ca.substitute(ca.vertcat(*[system.f[r] for r in parts[i]]), system.x, xs)


def _subsystem_name(system, parts, i: int) -> str:
    return f"subsystem {i + 1} ({', '.join(system.state_names[k] for k in parts[i])})"


def _block_jacobian(system, parts, nbrs, i: int):
    """``(idx, y, S, J, why)``: subsystem ``i``'s variables and symbol ``y``, a symbolic
    seed ``S`` and ``J = ∂f_i/∂y · S`` (``n_i × m``; the seed keeps CasADi from folding
    ``f``'s constants into the derivative, see
    :func:`~nlyap_opt.certification.roa.seeded_jacobian`); ``why`` is not empty when the
    graph of ``f_i`` or ``J`` holds a non-smooth or partial operation (the walker's checked
    operations, constant arguments excepted) or one the walker does not evaluate."""
    idx, y, fi = _block_function(system, parts, nbrs, i)
    m = len(idx)
    S = ca.SX.sym("S", m, m)
    J = ca.jtimes(fi, y, S)
    name = _subsystem_name(system, parts, i)
    try:
        checked = compile_function(ca.Function(f"local_{i}", [y, S], [fi, J])).checked
    except UnsupportedOperationError as err:
        return idx, y, S, J, f"{name}: {err}"
    if checked:
        return idx, y, S, J, (f"{name}: f uses non-smooth or partial operations; the "
                              "compositional method needs f continuously differentiable "
                              "on all of D")
    return idx, y, S, J, ""


def _local_bound(system, parts, nbrs, i: int, P) -> tuple[list | None, str]:
    r"""``(N, "")`` with :math:`\nabla V_i \cdot f_i(y) \le y^\top N y` on subsystem
    ``i``'s box ``Y_i`` (its states, then its neighbours' in order), or ``(None, why)``.

    ``P``: the exact rational ``P_i``. The mean-value form :math:`f_i(y) = \bar J_i(y)\,y`
    (``f_i(0) = 0`` proved exactly beforehand), :math:`\bar J_i = \int_0^1 J_i(sy)\,ds`,
    with the Jacobian ``J_i`` of ``f_i`` enclosed on nested slices of ``Y_i``
    (:func:`~nlyap_opt.certification.roa.sliced_enclosure`) and ``P_i`` padded with zeros
    to all of ``y`` (:func:`~nlyap_opt.certification.roa.mean_value_form`). ``P_i`` never
    enters a CasADi graph, so no float folding of its products with ``f``'s constants can
    change a sign. Refused when the graph of ``f_i`` or its Jacobian holds an operation that
    is non-smooth or partial (the walker's checked operations, constant arguments
    excepted): the mean-value form needs ``f`` continuously differentiable on ``D``.
    """
    idx, y, S, J, why = _block_jacobian(system, parts, nbrs, i)
    if why:
        return None, why
    m, ni = len(idx), len(parts[i])
    # the rows of the neighbours' states are 0: V_i reads x_i only
    JS = ca.densify(ca.vertcat(J, ca.SX.zeros(m - ni, m)))
    name = _subsystem_name(system, parts, i)
    try:
        CR = sliced_enclosure(ca.Function(f"jac_{i}", [y, S], [JS]), system.state_box[idx],
                              [Fraction(1, TAYLOR_SLICES)] * TAYLOR_SLICES)
    except UnsupportedOperationError as err:
        return None, f"{name}: {err}"
    if CR is None:
        return None, f"{name}: the Jacobian of f_i is not bounded on its box"
    Pm = [[P[a][b] if a < ni and b < ni else Fraction(0) for b in range(m)] for a in range(m)]
    return mean_value_form(Pm, *CR), ""


# ============================================================================ the data setting
#: the hull of the Hessian's interval enclosures on ``_HESSIAN_PIECES`` per axis of a box
#: of at most 4 dimensions (2 per axis up to 6, else the whole box)
_HESSIAN_PIECES = {4: 4, 6: 2}


def hessian_bound(system, parts, nbrs, i: int) -> tuple[np.ndarray | None, str]:
    r"""``(H, "")`` with :math:`H_{kab} \ge |\partial^2 f_k / \partial y_a \partial y_b|` on
    subsystem ``i``'s box ``Y_i`` (``k`` its states, ``y`` its and its neighbours' states),
    or ``(None, why)``.

    A simulator without a graph: the declared ``H`` for every entry, 0 where ``f_k`` is
    declared not to read ``y_a`` or ``y_b`` (``depends_on``). With a graph: the
    outward-rounded interval enclosure of the second derivatives (forward mode twice along
    symbolic seeds, evaluated at the identity seeds,
    :func:`~nlyap_opt.certification.roa.sliced_enclosure`), the hull of its values on equal
    pieces of ``Y_i``, widened by CasADi's constant-folding allowance. Refused when the graph
    holds a non-smooth or partial operation (``f`` must be :math:`C^2` on ``D``).
    """
    if not getattr(system, "has_model", False):
        idx = _block_indices(parts, nbrs, i)
        reads = _declared_states(system)
        decl = system.declarations
        return np.array([[[decl.hessian_of(k) if idx[a] in reads[k] and idx[b] in reads[k] else 0.0
                           for b in range(len(idx))] for a in range(len(idx))]
                         for k in parts[i]]), ""
    idx, y, fi = _block_function(system, parts, nbrs, i)
    m, ni = len(idx), len(parts[i])
    S1, S2 = ca.SX.sym("S", m, m), ca.SX.sym("T", m, m)
    T = ca.densify(ca.jtimes(ca.vec(ca.jtimes(fi, y, S1)), y, S2))     # (ni·m) × m
    fun = ca.Function(f"hess_{i}", [y, S1, S2], [T])
    name = _subsystem_name(system, parts, i)
    pieces = next((k for d, k in sorted(_HESSIAN_PIECES.items()) if m <= d), 1)
    try:
        if compile_function(ca.Function(f"f2_{i}", [y, S1, S2], [fi, T])).checked:
            return None, (f"{name}: f uses non-smooth or partial operations; the "
                          "compositional method from samples needs f twice continuously "
                          "differentiable on all of D")
        CR = sliced_enclosure(fun, system.state_box[idx], [Fraction(1)],
                              split=(list(range(m)), pieces))
    except UnsupportedOperationError as err:
        return None, f"{name}: {err}"
    if CR is None:
        return None, f"{name}: the second derivatives of f_i are not bounded on its box"
    C, R = CR
    H = np.array([[[float_up(abs(C[k + ni * a][b]) + R[k + ni * a][b]) + 0.0 for b in range(m)]
                   for a in range(m)] for k in range(ni)])
    return H, ""


def _slices(box: np.ndarray, split: int) -> tuple[np.ndarray, np.ndarray, int]:
    r"""The boxes ``(lo, hi)``, shape ``(K·nb, m)`` (slice-major), holding
    :math:`\{t y : t \in [t_k, t_{k+1}], y \in B\}` for the ``nb = split^m`` equal pieces
    ``B`` of ``box`` and :math:`t_k = k/K` (``K``: the Taylor slices of
    :func:`~nlyap_opt.certification.roa.sliced_enclosure`): per axis the hull of
    :math:`t_k B` and :math:`t_{k+1} B` (``t ≥ 0``), rounded outward
    and then cut back to ``box`` (which holds the exact set: ``box`` contains 0)."""
    m = box.shape[0]
    lo, hi = box[None, :, 0].copy(), box[None, :, 1].copy()
    nb = 1
    if split > 1:
        lo, hi, nb = split_boxes(lo, hi, list(range(m)), split)
    K = TAYLOR_SLICES
    t = (np.arange(K + 1) / K)[:, None, None]              # k/16: exact
    a_lo, b_lo = t[:-1] * lo[None], t[1:] * lo[None]
    a_hi, b_hi = t[:-1] * hi[None], t[1:] * hi[None]
    slo = np.maximum(np.minimum(dn(a_lo), dn(b_lo)), box[:, 0])
    shi = np.minimum(np.maximum(up(a_hi), up(b_hi)), box[:, 1])
    return slo.reshape(-1, m), shi.reshape(-1, m), nb


def _difference_jacobian(system, parts, idx, i: int, H: np.ndarray, slo, shi):
    """``(Jlo, Jhi, "")``, each ``(nS, n_i, m)``: the Jacobian of ``f_i`` on each slice box
    from finite differences and ``H`` (:func:`_piece_enclosures`), or ``(None, None, why)``."""
    m, ni = len(idx), len(parts[i])
    name = _subsystem_name(system, parts, i)
    if not np.all(shi > slo):
        return None, None, f"{name}: a slice of its box has no width"
    nS = len(slo)
    s = 0.5 * (slo + shi)
    h = 0.25 * (shi - slo)
    pts = np.repeat(s[:, None, :], 2 * m, axis=1)                  # (nS, 2m, m)
    for j in range(m):
        pts[:, 2 * j, j] = np.minimum(s[:, j] + h[:, j], shi[:, j])
        pts[:, 2 * j + 1, j] = np.maximum(s[:, j] - h[:, j], slo[:, j])
    Flo, Fhi = _values(system, parts, idx, i, pts.reshape(-1, m))
    Flo, Fhi = Flo.reshape(nS, 2 * m, ni), Fhi.reshape(nS, 2 * m, ni)
    if not (np.all(np.isfinite(Flo)) and np.all(np.isfinite(Fhi))):
        return None, None, f"{name}: f_i is not finite on its box"
    if not getattr(system, "has_model", False):
        _refute_hessian(system, parts, idx, i, H, s, pts, Flo, Fhi)
        _refute_curvature(system, parts, idx, i, H)
    rho = up_sum(np.maximum(shi - s, s - slo))                     # (nS, m)
    Jlo = np.zeros((nS, ni, m))
    Jhi = np.zeros((nS, ni, m))
    for j in range(m):
        pp, pm = pts[:, 2 * j, j], pts[:, 2 * j + 1, j]
        dl, dh = dn_sum(pp - pm), up_sum(pp - pm)
        if not np.all(dl > 0):
            return None, None, f"{name}: a difference step vanished"
        nl = dn_sum(Flo[:, 2 * j] - Fhi[:, 2 * j + 1])             # (nS, ni)
        nh = up_sum(Fhi[:, 2 * j] - Flo[:, 2 * j + 1])
        ql = np.minimum(dn(nl / dl[:, None]), dn(nl / dh[:, None]))
        qh = np.maximum(up(nh / dl[:, None]), up(nh / dh[:, None]))
        amax = np.maximum(up_sum(pp - s[:, j]), up_sum(s[:, j] - pm))       # (nS,)
        e = H[None, :, j, j] * amax[:, None] * 0.5 + rho @ H[:, j, :].T       # (nS, ni)
        e = up_roundings(e, 2 * m + 4)
        Jlo[:, :, j] = dn_sum(ql - e)
        Jhi[:, :, j] = up_sum(qh + e)
    if not (np.all(np.isfinite(Jlo)) and np.all(np.isfinite(Jhi))):
        return None, None, f"{name}: the Jacobian enclosure is not finite"
    return Jlo, Jhi, ""


def _interval_jacobian(system, parts, nbrs, i: int, slo, shi):
    """``(Jlo, Jhi, "")``, each ``(nS, n_i, m)``: the outward-rounded interval enclosure of
    the Jacobian graph of ``f_i`` (a symbolic seed, evaluated at the identity:
    :func:`~nlyap_opt.certification.roa.seeded_jacobian`) on each slice box, widened by
    CasADi's constant-folding allowance; or ``(None, None, why)`` (as :func:`_local_bound`)."""
    idx, y, S, J, why = _block_jacobian(system, parts, nbrs, i)
    if why:
        return None, None, why
    m, ni = len(idx), len(parts[i])
    JS = ca.densify(J)                                          # (ni, m)
    name = _subsystem_name(system, parts, i)
    try:
        Interval, ia = interval_arithmetic()
        eye = np.tile(np.eye(m).ravel(order="F"), (len(slo), 1))
        res = evaluate(ca.Function(f"jac_{i}", [y, S], [JS]),
                       [Interval(slo, shi), Interval(eye, eye.copy())], ia)[0]
    except UnsupportedOperationError as err:
        return None, None, f"{name}: {err}"
    lo = np.broadcast_to(np.asarray(res.lo, dtype=float).reshape(-1, ni * m), (len(slo), ni * m))
    hi = np.broadcast_to(np.asarray(res.hi, dtype=float).reshape(-1, ni * m), (len(slo), ni * m))
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        return None, None, f"{name}: the Jacobian of f_i is not bounded on its box"
    # column-major entries; the fold allowance |v|·2⁻³⁰ is exact but for underflow
    lo = dn_sum(lo - up(np.abs(lo) * FOLD)).reshape(-1, m, ni).transpose(0, 2, 1)
    hi = up_sum(hi + up(np.abs(hi) * FOLD)).reshape(-1, m, ni).transpose(0, 2, 1)
    return lo, hi, ""


def _piece_enclosures(system, parts, nbrs, i: int, H: np.ndarray | None, split: int
                      ) -> tuple[list | None, str]:
    r"""``([(C, R), …], "")``: for each of the ``split^m`` pieces ``B`` of subsystem ``i``'s
    box, the exact rational centre and radius of an enclosure of
    :math:`\bar J_i(y) = \int_0^1 J_i(ty)\,dt` for every ``y ∈ B`` (``J_i`` the Jacobian of
    ``f_i`` in ``y``, padded with zero rows to ``m × m``); or ``(None, why)``. With
    ``H`` (the data setting) from values of ``f_i`` and the second-derivative bound ``H``
    only; with ``H = None`` (the known setting) from the interval enclosure of the model's
    Jacobian graph on each slice (:func:`_interval_jacobian`).

    On each slice box ``S`` (:func:`_slices`; ``ty ∈ S`` for ``t`` in its slice) with centre
    ``s``: the difference quotient :math:`q = (f_k(p^+) - f_k(p^-))/(a + b)` at
    :math:`p^\pm = s \pm (a, b)\,e_j` inside ``S`` is :math:`\partial_j f_k(s)` within
    :math:`H_{kjj}(a^2 + b^2)/(2(a + b)) \le H_{kjj}\max(a, b)/2` (Taylor with the Lagrange
    remainder), and for ``z ∈ S``, :math:`|\partial_j f_k(z) - \partial_j f_k(s)| \le
    \sum_i H_{kji} \max_{z \in S}|z_i - s_i|` (mean value theorem; ``S`` is convex). The
    values of ``f_k`` are outward-rounded interval evaluations of the model's graph at the
    float points (a simulator without a graph: its values, widened by the declared
    ``sample_error``), the quotient is rounded outward with the exact ``a + b`` enclosed, and every
    error term is rounded up. The mean over the ``K`` slices (weights ``1/K``) is summed in
    exact rationals.
    """
    idx = _block_indices(parts, nbrs, i)
    m, ni = len(idx), len(parts[i])
    slo, shi, nb = _slices(system.state_box[idx], split)
    if H is None:
        Jlo, Jhi, why = _interval_jacobian(system, parts, nbrs, i, slo, shi)
    else:
        with np.errstate(all="ignore"):
            Jlo, Jhi, why = _difference_jacobian(system, parts, idx, i,
                                                 np.asarray(H, dtype=float), slo, shi)
    if Jlo is None:
        return None, why
    K = TAYLOR_SLICES
    Jlo, Jhi = Jlo.reshape(K, nb, ni, m), Jhi.reshape(K, nb, ni, m)
    # the means over the slices, rounded outward: a K-term float sum is within
    # γ_K Σ|terms| of the exact one; division by K = 16 is exact but for underflow
    with np.errstate(all="ignore"):
        lo_mean = dn(dn_sum(np.sum(Jlo, axis=0) - _sum_error(Jlo)) / K)
        hi_mean = up(up_sum(np.sum(Jhi, axis=0) + _sum_error(Jhi)) / K)
    if not (np.all(np.isfinite(lo_mean)) and np.all(np.isfinite(hi_mean))):
        return None, (f"{_subsystem_name(system, parts, i)}: the Jacobian enclosure is not "
                      "finite (second-derivative bound or values too large)")
    out = []
    zero = Fraction(0)
    for b in range(nb):
        C = [[zero] * m for _ in range(m)]
        R = [[zero] * m for _ in range(m)]
        for k in range(ni):
            for j in range(m):
                L, Uq = Fraction(lo_mean[b, k, j]), Fraction(hi_mean[b, k, j])
                C[k][j], R[k][j] = (L + Uq) / 2, (Uq - L) / 2
        out.append((C, R))
    return out, ""


def _sum_error(terms: np.ndarray) -> np.ndarray:
    """An upper bound of ``|fl(Σ_k t_k) − Σ_k t_k|`` for numpy's sum over axis 0:
    ``γ_K Σ|t_k|`` (Higham), with the rounding of ``Σ|t_k|`` and of the product covered."""
    K = terms.shape[0]
    return up_roundings(rounding.gamma(K) * np.sum(np.abs(terms), axis=0), K + 1)


def _values(system, parts, idx: list[int], i: int, pts: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """Enclosures ``(lo, hi)``, shape ``(N, n_i)``, of ``f_i`` at the points ``pts`` of the
    variables ``idx`` (every other state 0): the model's graph in outward-rounded interval
    arithmetic, or the simulator's values ± its declared ``sample_error``."""
    if getattr(system, "has_model", False):
        _, y, fi = _block_function(system, parts, _structure(system, parts), i)
        Interval, ia = interval_arithmetic()
        val = evaluate(ca.Function(f"f_{i}", [y], [fi]), [Interval(pts, pts.copy())], ia)[0]
        return (np.asarray(val.lo, dtype=float).reshape(len(pts), -1),
                np.asarray(val.hi, dtype=float).reshape(len(pts), -1))
    X = np.zeros((len(pts), system.nx))
    X[:, idx] = pts
    F = _simulate(system, X)[:, list(parts[i])]
    eps = float(system.declarations.sample_error or 0.0)
    if eps == 0.0:
        return F, F.copy()
    return dn_sum(F - eps), up_sum(F + eps)


def _simulate(system, X: np.ndarray) -> np.ndarray:
    """``f`` of a simulator at the states ``X``: a :class:`ConfigError` naming the problem
    when it raises, returns complex numbers, or returns NaN or infinity."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", np.exceptions.ComplexWarning)
            F = np.asarray(system.evaluate(X), dtype=float)
    except (KeyboardInterrupt, ConfigError):
        raise
    except (Exception, SystemExit) as err:   # the user's code: any failure is the simulator's
        raise ConfigError(f"the simulator of {system.name!r} failed ({type(err).__name__}: "
                          f"{err}) when called on {len(X)} state"
                          f"{'' if len(X) == 1 else 's'}; fix the simulator") from None
    if not np.all(np.isfinite(F)):
        k = int(np.argmax(~np.all(np.isfinite(F), axis=1)))
        at = ", ".join(f"{n}={v:.4g}" for n, v in zip(system.state_names, X[k]))
        raise ConfigError(f"the simulator of {system.name!r} returned NaN or infinity at "
                          f"({at}); the compositional certificate needs f finite on the box")
    return F


def _refute_hessian(system, parts, idx, i, H, s, pts, Flo, Fhi) -> None:
    """Raise :class:`ConfigError` when the simulator's values refute its declarations (then
    :func:`_refute_dependencies`). The declared bound:
    the second divided difference ``2[(f(p⁺) − f(s))/a − (f(s) − f(p⁻))/b]/(a + b)`` equals
    ``∂²_j f_k`` at some point of the stencil, so beyond ``H[k][j][j]`` plus what the
    declared sample error (and float rounding) can move it, the declaration is false."""
    m = s.shape[1]
    Clo, Chi = _values(system, parts, idx, i, s)
    centre = 0.5 * (Clo + Chi)
    value = 0.5 * (Flo + Fhi)
    eps = float(system.declarations.sample_error or 0.0)
    for j in range(m):
        a = pts[:, 2 * j, j] - s[:, j]
        b = s[:, j] - pts[:, 2 * j + 1, j]
        d2 = 2.0 * ((value[:, 2 * j] - centre) / a[:, None]
                    - (centre - value[:, 2 * j + 1]) / b[:, None]) / (a + b)[:, None]
        scale = (np.abs(value[:, 2 * j]) + 2 * np.abs(centre) + np.abs(value[:, 2 * j + 1]))
        slack = 2.0 * (2 * eps + 1e-12 * scale) * (1 / a + 1 / b)[:, None] / (a + b)[:, None]
        excess = np.abs(d2) - H[None, :, j, j] - slack
        if np.any(excess > 1e-9 * np.maximum(1.0, H[None, :, j, j])):
            r, k = np.unravel_index(int(np.argmax(excess)), excess.shape)
            at = ", ".join(f"{system.state_names[v]}={s[r, a_]:.4g}" for a_, v in enumerate(idx))
            raise ConfigError(
                f"the simulator refutes its declared hessian: the second difference of "
                f"{system.state_names[parts[i][k]]}' along {system.state_names[idx[j]]} near "
                f"({at}) is {d2[r, k]:.4g}, beyond H = {H[k, j, j]:.4g}; declare a larger "
                "hessian (H ≥ every |second derivative| of f on the box)")
    _refute_dependencies(system, parts, idx, i, s, centre, eps)


#: seeded random points of a subsystem's box at which a simulator's second differences
#: (pure and mixed) are compared with its declared bound
REFUTE_POINTS = 64


def _refute_curvature(system, parts, idx, i: int, H: np.ndarray) -> None:
    """Raise :class:`ConfigError` when the simulator's second differences refute ``H`` at
    :data:`REFUTE_POINTS` seeded random points ``z`` of subsystem ``i``'s box (steps ``h``
    of 1/16 of the box, the stencils inside it): ``(f(z+h_j) − 2f(z) + f(z−h_j))/h_j²`` is
    ``∂²_j f_k`` at some point, ``Δ_jl f / (4 h_j h_l)`` (the four corners ``z ± h_j ± h_l``)
    is ``∂_j∂_l f_k`` at some point; beyond ``H[k][j][l]`` and the float slack, the
    declaration is false (this refutes, it never proves)."""
    box = system.state_box[idx]
    m, ni = len(idx), len(parts[i])
    h = (box[:, 1] - box[:, 0]) / 16
    rng = np.random.default_rng(1)
    z = (box[:, 0] + h) + (box[:, 1] - box[:, 0] - 2 * h) * rng.random((REFUTE_POINTS, m))
    offsets = [np.zeros(m)]
    for j in range(m):
        for sj in (1, -1):
            e = np.zeros(m)
            e[j] = sj * h[j]
            offsets.append(e)
    pairs = [(j, q) for j in range(m) for q in range(j + 1, m)]
    for j, q in pairs:
        for sj, sq in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            e = np.zeros(m)
            e[j], e[q] = sj * h[j], sq * h[q]
            offsets.append(e)
    offs = np.array(offsets)
    pts = np.clip((z[:, None, :] + offs[None]).reshape(-1, m), box[:, 0], box[:, 1])
    lo, hi = _values(system, parts, idx, i, pts)
    F = (0.5 * (lo + hi)).reshape(REFUTE_POINTS, len(offs), ni)
    A = np.abs(F)
    bad = []
    with np.errstate(all="ignore"):
        for j in range(m):
            fp, fm, f0 = F[:, 1 + 2 * j], F[:, 2 + 2 * j], F[:, 0]
            d = (fp - 2 * f0 + fm) / h[j] ** 2
            slack = 1e-12 * (A[:, 1 + 2 * j] + 2 * A[:, 0] + A[:, 2 + 2 * j]) / h[j] ** 2
            bad.append((d, slack, H[:, j, j], j, j))
        base = 1 + 2 * m
        for n, (j, q) in enumerate(pairs):
            c = F[:, base + 4 * n: base + 4 * n + 4]
            d = (c[:, 0] - c[:, 1] - c[:, 2] + c[:, 3]) / (4 * h[j] * h[q])
            slack = 1e-12 * A[:, base + 4 * n: base + 4 * n + 4].sum(axis=1) / (4 * h[j] * h[q])
            bad.append((d, slack, np.maximum(H[:, j, q], H[:, q, j]), j, q))
    for d, slack, Hjq, j, q in bad:
        excess = np.abs(d) - Hjq[None, :] - slack
        if np.any(excess > 1e-9 * np.maximum(1.0, Hjq[None, :])):
            r, k = np.unravel_index(int(np.argmax(excess)), excess.shape)
            at = ", ".join(f"{system.state_names[v]}={z[r, a]:.4g}" for a, v in enumerate(idx))
            along = system.state_names[idx[j]] + ("" if j == q else
                                                  f" and {system.state_names[idx[q]]}")
            raise ConfigError(
                f"the simulator refutes its declared hessian: a second difference of "
                f"{system.state_names[parts[i][k]]}' along {along} near ({at}) is "
                f"{d[r, k]:.4g}, beyond H = {Hjq[k]:.4g}; declare a larger hessian "
                "(H ≥ every |second derivative| of f on the box, mixed ones included)")


def _refute_dependencies(system, parts, idx, i, s, centre, eps: float) -> None:
    """Raise :class:`ConfigError` when the simulator refutes its declared ``depends_on``:
    at the slice centres ``s``, every state a derivative ``f_k`` of subsystem ``i`` is
    declared not to read is moved to a (seeded) random value in the box; ``f_k`` must not
    change beyond twice the declared sample error (and float rounding)."""
    reads = _declared_states(system)
    rng = np.random.default_rng(0)
    lo, hi = system.state_box[:, 0], system.state_box[:, 1]
    for r, k in enumerate(parts[i]):
        others = [v for v in range(system.nx) if v not in reads[k]]
        if not others:
            continue
        X = np.zeros((len(s), system.nx))
        X[:, idx] = s
        X[:, others] = lo[others] + (hi[others] - lo[others]) * rng.random((len(s), len(others)))
        F = _simulate(system, X)[:, k]
        diff = np.abs(F - centre[:, r])
        allowed = 2 * eps + 1e-12 * (np.abs(F) + np.abs(centre[:, r])) + 1e-300
        if np.any(~(diff <= allowed)):
            q = int(np.argmax(np.where(np.isnan(diff), np.inf, diff - allowed)))
            raise ConfigError(
                f"the simulator refutes its declared depends_on: {system.state_names[k]}' "
                f"changes by {diff[q]:.3g} when states it is declared not to read "
                f"({', '.join(system.state_names[v] for v in others)}) move; declare every "
                f"state {system.state_names[k]}' reads")


def _estimated_A(system) -> np.ndarray:
    """The linearisation of a simulator at the origin by central differences (a float
    estimate that only chooses the ``P_i``; nothing is proved with it)."""
    n = system.nx
    box = system.state_box
    h = np.minimum(1e-6 * np.maximum(1.0, np.max(np.abs(box), axis=1)),
                   0.25 * np.min(np.abs(box), axis=1))
    X = np.zeros((2 * n, n))
    X[np.arange(n), np.arange(n)] = h
    X[n + np.arange(n), np.arange(n)] = -h
    F = _simulate(system, X)
    A = ((F[:n] - F[n:]) / (2 * h[:, None])).T
    if not np.all(np.isfinite(A)):
        raise ConfigError(f"the linearisation of {system.name!r} at the origin (central "
                          "differences of the simulator) is not finite")
    return A


def _local_bounds(system, parts, nbrs, i: int, P, setting: str, hessian=None,
                  split: int = 1) -> tuple[list | None, str]:
    """The matrices ``N`` of :func:`_local_bound` for subsystem ``i``, one per piece of its
    box (:func:`_piece_enclosures`; the known setting's one piece is :func:`_local_bound`)."""
    if setting == "known" and split == 1:
        N, why = _local_bound(system, parts, nbrs, i, P)
        return (None if N is None else [N]), why
    encl, why = _piece_enclosures(system, parts, nbrs, i,
                                  hessian if setting == "data" else None, split)
    if encl is None:
        return None, why
    m, ni = len(encl[0][0]), len(parts[i])
    Pm = [[P[a][b] if a < ni and b < ni else Fraction(0) for b in range(m)] for a in range(m)]
    return [mean_value_form(Pm, C, R) for C, R in encl], ""


def _local_matrix(N, sizes, P, alpha, beta) -> list[list[Fraction]]:
    """``-(N + blockdiag(α P_i, -β_j P_j))``: positive definite iff the local test holds."""
    M = [row[:] for row in N]
    off = 0
    for s, (Pk, coef) in enumerate(zip(P, [rational(alpha)] + [-rational(b) for b in beta])):
        n = sizes[s]
        for a in range(n):
            for b in range(n):
                M[off + a][off + b] += coef * rational(Pk[a][b])
        off += n
    return [[-v for v in row] for row in M]


def _equilibrium_refusal(system) -> str:
    """``""`` when ``f(0) = 0`` exactly: the CasADi graph of ``f`` evaluated at ``x = 0`` in
    exact rational arithmetic (:class:`~nlyap_opt.kernel.walker.ExactPointArithmetic`) gives
    the rational 0 in every component. Neither a float evaluation nor a substitution into
    the graph can prove it (both round; ``((x² + 10¹⁶) + 1) − 10¹⁶`` folds to 0 at 0)."""
    if not getattr(system, "has_model", False):
        f0 = _simulate(system, np.zeros((1, system.nx)))[0]
        if np.any(f0 != 0.0):
            return (f"the origin is not an exact equilibrium of the simulator (max |f(0)| = "
                    f"{float(np.max(np.abs(f0))):.3g}); the compositional certificate needs "
                    "f(0) = 0 exactly: shift the state, or make the simulator return 0 there")
        return ""
    vals = exact_values(ca.Function("f0", [system.x], [system.f]), [0] * system.nx)
    if vals is None or not all(isinstance(v, Fraction) and v == 0 for v in vals):
        return ("the origin is not an equilibrium: f(0) is not exactly 0 (evaluated in exact "
                "rational arithmetic); shift the state so that the equilibrium is at 0")
    return ""


# ============================================================================ the checks
def _hessian_refusal(system, parts, nbrs, pieces: list[Piece], setting: str, split) -> str:
    """``""`` when ``split`` is one of :data:`DATA_SPLITS` with at most :data:`MAX_PIECES`
    pieces per subsystem box, and the pieces' second-derivative bounds fit ``setting``: none
    in the known setting; in the data setting a finite ``H ≥ 0`` of shape
    ``(n_i, m_i, m_i)`` per piece, entrywise at least :func:`hessian_bound`."""
    if setting not in SETTINGS:
        return f"unknown setting {setting!r} (one of {', '.join(SETTINGS)})"
    if isinstance(split, bool) or split not in DATA_SPLITS:
        return f"split must be one of {', '.join(map(str, DATA_SPLITS))}, got {split!r}"
    dims = [len(p.states) + sum(len(parts[j]) for j in p.neighbours) for p in pieces]
    for i, m in enumerate(dims):
        if split ** m > MAX_PIECES:
            return (f"subsystem {i + 1}: split {split} cuts its {m}-dimensional box into "
                    f"{split ** m} pieces, more than {MAX_PIECES}")
    if split > 1 and sum(split ** m for m in dims) > MAX_TOTAL_PIECES:
        return (f"split {split} cuts the subsystems' boxes into "
                f"{sum(split ** m for m in dims)} pieces in all, more than {MAX_TOTAL_PIECES}")
    if setting == "known":
        if any(p.hessian is not None for p in pieces):
            return "a certificate of the known setting holds second-derivative bounds"
        return ""
    for i, p in enumerate(pieces):
        m = len(p.states) + sum(len(parts[j]) for j in p.neighbours)
        H = None if p.hessian is None else np.asarray(p.hessian, dtype=float)
        if H is None or H.shape != (len(p.states), m, m) or not np.all(np.isfinite(H)) \
                or np.any(H < 0):
            return (f"subsystem {i + 1}: the second-derivative bound must be finite numbers "
                    f"≥ 0 of shape ({len(p.states)}, {m}, {m})")
        Hm, why = hessian_bound(system, parts, nbrs, i)
        if Hm is None:
            return why
        if np.any(H < Hm):
            return (f"{_subsystem_name(system, parts, i)}: the stored second-derivative bound "
                    "is below the simulator's second derivatives on its box")
    return ""


def check_compositional(system, pieces: list[Piece], weights, level: float,
                        decay: float, *, setting: str = "known", split: int = 1,
                        _local: list | None = None) -> tuple[bool, dict, str]:
    """Prove the certificate's conditions for ``system`` exactly (module docstring, 1–3).

    Parameters
    ----------
    system : systems.System
        With a model, no input, and ``subsystems`` equal to the pieces' states.
    pieces : list of Piece
    weights : (N,) array_like
    level, decay : float
        The claimed ``c`` and ``γ``.
    setting : {"known", "data"}
        How the local inequalities enclose the Jacobian of ``f`` (:data:`SETTINGS`); the
        data setting needs every piece's ``hessian`` (checked to bound the simulator's
        second derivatives) and the pieces per axis ``split`` (one of :data:`DATA_SPLITS`).
    _local : list, optional
        Internal: per subsystem, the matrices ``N`` that :func:`_local_bounds` formed for
        these pieces' ``P``, setting and split, taken as given (the search passes the ones it
        has just formed; the re-check never does, and forms them here).

    Returns
    -------
    (bool, dict, str)
        Whether everything is proved, the per-condition verdicts, and the first failure.
    """
    parts = tuple(tuple(p.states) for p in pieces)
    why = _refusal(system, parts, setting if setting in SETTINGS else "known")
    if not why and parts != tuple(system.subsystems or ()):
        why = "the certificate's subsystems are not the system's declared subsystems"
    if why:
        return False, {"structure": why}, why
    checks: dict[str, str] = {}
    nbrs = _structure(system, parts)
    graph = getattr(system, "has_model", False)
    if any(tuple(p.neighbours) != nb for p, nb in zip(pieces, nbrs)):
        why = ("the neighbours of some subsystem are not those of f's graph" if graph else
               "the neighbours of some subsystem are not those the system declares")
        return False, {"structure": why}, why
    checks["structure"] = ("proved (neighbours from f's graph)" if graph else
                           "declared (neighbours from depends_on)")
    why = _equilibrium_refusal(system)
    if why:
        return False, {**checks, "equilibrium": why}, why
    checks["equilibrium"] = ("proved (f(0) = 0 in exact rational arithmetic)" if graph else
                             "the simulator returns exactly 0 at the origin (declared exact)")
    try:
        w = [rational(v) for v in np.asarray(weights, dtype=float).ravel()]
        c, g = rational(level), rational(decay)
        Ps = [[[rational(v) for v in row] for row in np.asarray(p.P, dtype=float)] for p in pieces]
        alphas = [rational(p.alpha) for p in pieces]
        betas = [[rational(b) for b in p.beta] for p in pieces]
    except (ValueError, TypeError):
        why = "a number of the certificate is not finite, or a matrix has the wrong shape"
        return False, {**checks, "numbers": why}, why
    if len(w) != len(pieces) or any(len(b) != len(p.neighbours) for b, p in zip(betas, pieces)):
        why = "the certificate's weights or gains do not match its subsystems"
        return False, {**checks, "numbers": why}, why
    for i, (p, P) in enumerate(zip(pieces, Ps)):
        n = len(p.states)
        if len(P) != n or any(len(r) != n for r in P) or \
                any(P[a][b] != P[b][a] for a in range(n) for b in range(n)) \
                or not positive_definite(P):
            why = f"P of subsystem {i + 1} is not a symmetric positive definite {n}x{n} matrix"
            return False, {**checks, "positive definite": why}, why
    checks["positive definite"] = "proved (exact LDLᵀ of every P_i)"
    why = _hessian_refusal(system, parts, nbrs, pieces, setting, split)
    if why:
        return False, {**checks, "second derivatives": why}, why
    if setting == "data":
        checks["second derivatives"] = (
            "proved (each stored H bounds the interval enclosure of f's second derivatives on "
            "its subsystem's box)" if graph else
            "declared (each stored H is at least the declared hessian where depends_on allows; "
            "not refuted by the simulator's second differences)")
    for i, p in enumerate(pieces):
        if alphas[i] < 0 or any(b < 0 for b in betas[i]):
            why = f"subsystem {i + 1}: α and β must be ≥ 0"
            return False, {**checks, "local": why}, why
        Ns, why = (_local[i], "") if _local is not None else \
            _local_bounds(system, parts, nbrs, i, Ps[i], setting, p.hessian, split)
        if Ns is None:
            return False, {**checks, "local": why}, why
        sizes = [len(p.states)] + [len(parts[j]) for j in p.neighbours]
        Ploc = [Ps[i]] + [Ps[j] for j in p.neighbours]
        if not all(positive_definite(_local_matrix(N, sizes, Ploc, p.alpha, p.beta))
                   for N in Ns):
            why = (f"subsystem {i + 1} (states {', '.join(system.state_names[k] for k in p.states)}"
                   f"): dV_i/dt ≤ -{p.alpha:.4g} V_i + Σ β_ij V_j is not proved on its box "
                   "(coupling too strong for this domain, or the domain too large)")
            return False, {**checks, "local": why}, why
    dim = max(len(p.states) + sum(len(parts[j]) for j in p.neighbours) for p in pieces)
    if setting == "known":
        checks["local"] = (f"proved on {len(pieces)} boxes of dimension ≤ {dim}"
                           + (f", each cut into {split} pieces per axis" if split > 1 else "")
                           + " (mean-value form of f_i's interval Jacobian, P_i exact, exact "
                           "LDLᵀ)")
    else:
        checks["local"] = (f"proved on {len(pieces)} boxes of dimension ≤ {dim}, each cut into "
                           f"{split} pieces per axis (mean-value form of the Jacobian enclosed "
                           "by finite differences of sampled f and the bound H, P_i exact, "
                           "exact LDLᵀ)")
    if g <= 0 or any(v <= 0 for v in w):
        why = "the weights and the decay rate must be positive"
        return False, {**checks, "comparison": why}, why
    for j in range(len(pieces)):
        col = -alphas[j] * w[j] + sum(w[i] * b for i, p in enumerate(pieces)
                                      for nb, b in zip(p.neighbours, betas[i]) if nb == j)
        if col > -g * w[j]:
            why = (f"the comparison system does not prove dV/dt ≤ -{decay:g} V (subsystem "
                   f"{j + 1}'s column); the interconnection is too strong for these weights")
            return False, {**checks, "comparison": why}, why
    checks["comparison"] = "proved (wᵀ(-diag α + B) ≤ -γ wᵀ exactly)"
    box = system.state_box
    for i, (p, P) in enumerate(zip(pieces, Ps)):
        inv = inverse_diagonal(P)
        for a, k in enumerate(p.states):
            r = min(-rational(box[k, 0]), rational(box[k, 1]))
            if c <= 0 or c * inv[a] > w[i] * r * r:
                why = (f"the level {level:g} is not proved: the set V ≤ level leaves the box D "
                       f"along {system.state_names[k]}")
                return False, {**checks, "level": why}, why
    checks["level"] = "proved ({V ≤ c} ⊆ D exactly)"
    return True, checks, ""


# ============================================================================ the search
def _lyapunov_P(A: np.ndarray) -> np.ndarray | None:
    if A.size and np.max(np.linalg.eigvals(A).real) >= 0:
        return None
    P = solve_continuous_lyapunov(A.T, -np.eye(A.shape[0]))
    return 0.5 * (P + P.T)


def _gains(Ns, sizes, P, theta: float):
    """Float choice of ``α = θ α*`` and one ``β`` for all neighbours (bisection) that suit
    every matrix of ``Ns`` (one per piece of the subsystem's box)."""
    Nf = np.array([[[float(v) for v in row] for row in N] for N in Ns])
    n0 = sizes[0]
    Pf = [np.asarray(p, dtype=float) for p in P]
    a_star = min(float(eigh(-N[:n0, :n0], Pf[0], eigvals_only=True)[0]) for N in Nf)
    if not a_star > 0:
        return None
    alpha = theta * a_star
    k = len(sizes) - 1
    if k == 0:
        return alpha, ()

    def ok(beta):
        M = Nf.copy()
        off = 0
        for s, coef in enumerate([alpha] + [-beta] * k):
            n = sizes[s]
            M[:, off:off + n, off:off + n] += coef * Pf[s]
            off += n
        return np.max(np.linalg.eigvalsh(0.5 * (M + np.swapaxes(M, 1, 2)))) < 0

    hi = 1.0
    while not ok(hi):
        hi *= 2
        if hi > 1e12:
            return None
    lo = 0.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if ok(mid) else (mid, hi)
    return alpha, (hi * (1 + 1e-6) + 1e-12,) * k


def certify_compositional(system, *, setting: str = "known",
                          log=print) -> CompositionalCertificate:
    """Certify a region of attraction of ``system`` compositionally (module docstring).

    Parameters
    ----------
    system : systems.System
        A model without inputs that declares ``subsystems``.
    setting : {"known", "data"}
        ``"known"``: the local inequalities use the model's Jacobian graph. ``"data"`` (the
        unknown-dynamics setting): they use only values of ``f`` at finite-difference
        points and a bound on its second derivatives (:func:`hessian_bound`, stored in the
        certificate). In both settings each subsystem's box is cut into 1, 2 and 4 pieces
        per axis (:data:`DATA_SPLITS`; at most :data:`MAX_PIECES` pieces per box and
        :data:`MAX_TOTAL_PIECES` in all), each piece with its own local matrix, and the
        largest certified set is kept.
    log : callable

    Returns
    -------
    CompositionalCertificate
        ``CERTIFIED`` only when :func:`check_compositional` proves the chosen numbers.

    Raises
    ------
    ConfigError
        The system does not admit the method (no model, inputs, no declared subsystems,
        the origin not inside its box): the message says what to change.
    """
    t0 = time.perf_counter()
    if setting not in SETTINGS:
        raise ConfigError(f"unknown compositional setting {setting!r}; use one of "
                          f"{', '.join(SETTINGS)}")
    parts = system.subsystems
    why = _refusal(system, parts, setting)
    if why:
        raise ConfigError(why)
    nbrs = _structure(system, parts)
    box = system.state_box

    def fail(reason, pieces=()):
        return CompositionalCertificate(CertStatus.NOT_CERTIFIED, reason, system.name,
                                        list(pieces), np.zeros(0), 0.0, 0.0, box,
                                        assumptions=assumptions_of(setting, system),
                                        seconds=time.perf_counter() - t0, setting=setting)

    why = _equilibrium_refusal(system)
    if why:
        return fail(why)
    Ps = []
    A = system.A if getattr(system, "has_model", False) else _estimated_A(system)
    for i, p in enumerate(parts):
        P = _lyapunov_P(A[np.ix_(p, p)])
        if P is None:
            return fail(f"subsystem {i + 1}'s linearisation is not Hurwitz: the compositional "
                        "method needs every subsystem stable on its own")
        Ps.append(P)
    hessians = [None] * len(parts)
    if setting == "data":
        for i in range(len(parts)):
            hessians[i], why = hessian_bound(system, parts, nbrs, i)
            if hessians[i] is None:
                return fail(why)
    why, best = "", None
    dims = [len(_block_indices(parts, nbrs, i)) for i in range(len(parts))]
    for split in DATA_SPLITS:
        if split > 1 and (split ** max(dims) > MAX_PIECES
                          or sum(split ** m for m in dims) > MAX_TOTAL_PIECES):
            break
        bounds = []
        for i in range(len(parts)):
            Ns, why = _local_bounds(system, parts, nbrs, i, rational_matrix(Ps[i]), setting,
                                    hessians[i], split)
            if Ns is None:
                return fail(why)
            bounds.append(Ns)
        cert, why = _search(system, parts, nbrs, Ps, bounds, hessians, setting, split, t0, log)
        if cert is not None and (best is None or _log_volume(cert) > _log_volume(best)):
            best = cert
    if best is not None:
        best.seconds = time.perf_counter() - t0
        return best
    return fail(why)


def _log_volume(cert: CompositionalCertificate) -> float:
    """The log of the volume of ``{V ≤ level}`` up to a constant of the dimensions (float)."""
    return sum(0.5 * len(p.states) * math.log(cert.level / w)
               - 0.5 * math.log(np.linalg.det(p.P)) for w, p in zip(cert.weights, cert.pieces))


def _search(system, parts, nbrs, Ps, bounds, hessians, setting: str, split: int, t0: float,
            log) -> tuple[CompositionalCertificate | None, str]:
    """The float choice of ``α, β, w, c, γ`` for each decay fraction θ, the largest
    ``Ω_c`` first, each proved by :func:`check_compositional`: ``(certificate, "")`` for
    the first proved, else ``(None, why)``."""
    box = system.state_box
    candidates = []
    for theta in _THETAS:
        pieces = []
        for i in range(len(parts)):
            sizes = [len(parts[i])] + [len(parts[j]) for j in nbrs[i]]
            g = _gains(bounds[i], sizes, [Ps[i]] + [Ps[j] for j in nbrs[i]], theta)
            if g is None:
                break
            pieces.append(Piece(tuple(parts[i]), nbrs[i], Ps[i], g[0], g[1], hessians[i]))
        if len(pieces) < len(parts):
            continue
        Ac = -np.diag([p.alpha for p in pieces])
        for i, p in enumerate(pieces):
            for j, b in zip(p.neighbours, p.beta):
                Ac[i, j] += b
        try:
            w = np.linalg.solve(Ac.T, -np.ones(len(pieces)))
        except np.linalg.LinAlgError:
            continue
        if not np.all(w > 0):
            continue
        w = w / w.max()
        gamma = _decay(pieces, w)
        if not gamma > 0:
            continue
        cq = min(Fraction(float(w[i])) * min(-rational(box[k, 0]), rational(box[k, 1])) ** 2 / d
                 for i, p in enumerate(pieces)
                 for k, d in zip(p.states, inverse_diagonal(
                     [[rational(v) for v in row] for row in p.P])))
        level = float_down(cq)
        if not level > 0:
            continue
        logvol = sum(0.5 * len(p.states) * math.log(level / w[i])
                     - 0.5 * math.log(np.linalg.det(p.P)) for i, p in enumerate(pieces))
        candidates.append((-logvol, theta, pieces, w, level, gamma))
    why = ("no decay rates and coupling gains make the comparison system stable: the "
           "interconnection is too strong on this domain (a smaller box may certify)")
    for _, theta, pieces, w, level, gamma in sorted(candidates, key=lambda c: c[:2]):
        ok, checks, why = check_compositional(system, pieces, w, level, gamma,
                                              setting=setting, split=split, _local=bounds)
        seconds = time.perf_counter() - t0
        where = f", {split} pieces per axis" if split > 1 or setting == "data" else ""
        log(f"compositional: {len(pieces)} subsystems{where}, θ = {theta}, level {level:.6g}, "
            f"decay {gamma:.4g}: {'certified' if ok else why} ({seconds:.2f} s)")
        if ok:
            return CompositionalCertificate(
                CertStatus.CERTIFIED, "", system.name, pieces, w, level, gamma, box, checks,
                assumptions_of(setting, system), seconds, setting, split), ""
    return None, why


def _decay(pieces: list[Piece], w: np.ndarray) -> float:
    """The largest float ``γ ≤ min_j -(wᵀA_c)_j / w_j`` (exact), or 0 when that is ≤ 0."""
    wq = [Fraction(float(v)) for v in w]
    col = [-Fraction(p.alpha) * wq[j] for j, p in enumerate(pieces)]
    for i, p in enumerate(pieces):
        for j, b in zip(p.neighbours, p.beta):
            col[j] += wq[i] * Fraction(b)
    g = min(-c / v for c, v in zip(col, wq))
    return float_down(g) if g > 0 else 0.0


# ============================================================================ files
def save_compositional(cert: CompositionalCertificate, system, out: str | Path) -> Path:
    """Write ``out/certificate.json`` (timings in ``timings.json`` beside it); ``nlyap run``
    adds ``report.md`` and ``subsystems.png``
    (:func:`nlyap_opt.workflow.report.write_compositional_report`)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    d = cert.to_dict()
    d["system_binding"] = system_binding(system)
    if getattr(system, "source", ""):
        d["system_source"] = str(system.source)
    d["provenance"] = fingerprint()
    clean, timings = split_timings(d)
    write_json_atomic(out / "certificate.json", clean)
    save_timings(out / "timings.json", timings)
    return out / "certificate.json"


def is_compositional_file(path: str | Path) -> bool:
    """Whether ``path`` (a file or a run directory) holds a compositional certificate."""
    path = Path(path)
    if path.is_dir():
        path = path / "certificate.json"
    try:
        d = json.loads(read_file_bytes(path, "certificate"))
    except (OSError, ValueError, RecursionError, ConfigError):
        return False  # the reader of the certificate says why
    return isinstance(d, dict) and d.get("format") == FORMAT


def _typed(d: dict, key: str, kind, path):
    v = d.get(key)
    if not isinstance(v, kind) or isinstance(v, bool):
        raise ConfigError(f"malformed compositional certificate {path}: {key!r} is missing or "
                          f"not a {getattr(kind, '__name__', 'number')}; rerun the command "
                          "that wrote it")
    return v


def _reals(v, key: str) -> np.ndarray:
    """``v`` (a JSON number or nested lists of them) as a float array; a string, a boolean
    or anything else is an edit (``TypeError``), a ragged list a ``ValueError``."""
    def leaves(x):
        if isinstance(x, list):
            for e in x:
                yield from leaves(e)
        else:
            yield x
    for x in leaves(v):
        if isinstance(x, bool) or not isinstance(x, (int, float)):
            raise TypeError(f"{key} must hold numbers, got {type(x).__name__} {x!r}")
    try:
        return np.asarray(v, dtype=float)
    except OverflowError:
        raise ValueError(f"{key} holds an integer beyond float range") from None


def _ints(v, key: str) -> list[int]:
    """``v`` as a list of JSON integers (never booleans, floats or strings)."""
    if not isinstance(v, list) or any(isinstance(x, bool) or not isinstance(x, int) for x in v):
        raise TypeError(f"{key} must be a list of integers, got {v!r}")
    return list(v)


def recheck_compositional(path: str | Path, *, system=None,
                          allow_factory: bool = False) -> CompositionalCertificate:
    """Prove a saved compositional certificate again, from its numbers and the system.

    Parameters
    ----------
    path : str or Path
        ``certificate.json`` or its directory.
    system : systems.System, str or Path, optional
        As for :func:`nlyap_opt.certification.certificate.recheck_certificate` (default: the
        catalogue system the certificate names, or its spec file, never code named inside it).
    allow_factory : bool

    Returns
    -------
    CompositionalCertificate
        ``CERTIFIED`` only when the system is the certified one (its binding hash) and
        :func:`check_compositional` proves the stored numbers.

    Raises
    ------
    ConfigError
        Not a compositional certificate of a version this nlyap reads, or malformed.
    """
    path, d = read_certificate_file(path)
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise ConfigError(f"{path} is not a compositional certificate (format {FORMAT!r}); "
                          "pass the certificate.json written by `nlyap run`")
    if d.get("version") != VERSION:
        raise ConfigError(f"compositional certificate version {d.get('version')!r} is not "
                          f"supported (this nlyap reads {VERSION}); rerun the command")
    known = {"format", "version", "status", "reason", "system", "method", "setting",
             "certified_set", "decrease_condition", "domain_box", "subsystems", "weights",
             "level", "decay", "checks", "assumptions", "system_binding", "system_source",
             "provenance", "split"}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ConfigError(f"compositional certificate {path} holds fields this nlyap does not "
                          f"know ({', '.join(unknown)}); re-check it with the nlyap that wrote "
                          "it, or rerun the command")
    name = _typed(d, "system", str, path)
    setting = d.get("setting")
    if setting not in SETTINGS:
        raise ConfigError(f"malformed compositional certificate {path}: 'setting' must be one "
                          f"of {', '.join(SETTINGS)}, got {setting!r}; rerun the command that "
                          "wrote it")
    split = d.get("split", 1)
    if setting == "data" and "split" not in d or not isinstance(split, int) \
            or isinstance(split, bool) or split not in DATA_SPLITS:
        raise ConfigError(f"malformed compositional certificate {path}: 'split' must be one of "
                          f"{', '.join(map(str, DATA_SPLITS))}; rerun the command that wrote it")
    try:
        pieces = [Piece(tuple(_ints(s["states"], "states")),
                        tuple(_ints(s["neighbours"], "neighbours")),
                        _reals(s["P"], "P"), float(_reals(s["alpha"], "alpha")),
                        tuple(float(b) for b in _reals(s["beta"], "beta").ravel()),
                        None if "hessian_bound" not in s else
                        _reals(s["hessian_bound"], "hessian_bound")) for s in d["subsystems"]]
        weights = _reals(d["weights"], "weights")
        if weights.ndim != 1:
            raise ValueError(f"weights must be a list of numbers, got shape {weights.shape}")
        level, decay = float(_reals(d["level"], "level")), float(_reals(d["decay"], "decay"))
        dbox = _reals(d["domain_box"], "domain_box")
        assumptions = [str(a) for a in d["assumptions"]]
    except (KeyError, TypeError, ValueError) as err:
        raise ConfigError(f"malformed compositional certificate {path}: {type(err).__name__}: "
                          f"{err}; rerun the command that wrote it") from None
    sysm, refusal = bound_system(d, path, system, allow_factory)

    def result(ok, reason, checks=None):
        return CompositionalCertificate(
            CertStatus.CERTIFIED if ok else CertStatus.NOT_CERTIFIED, reason, name, pieces,
            weights, level, decay, dbox, checks or {}, assumptions, setting=setting,
            split=split)

    if d.get("status") != CertStatus.CERTIFIED.value:
        return result(False, f"the certificate does not claim a region ({d.get('status')!r})")
    if refusal:
        return result(False, refusal)
    if dbox.shape != sysm.state_box.shape or not np.array_equal(dbox, sysm.state_box):
        return result(False, "the certificate's domain box is not the system's state box")
    if assumptions != assumptions_of(setting, sysm):
        return result(False, "the certificate lists other assumptions than this method's "
                      "(an edited certificate.json?); rerun the command that wrote it")
    ok, checks, why = check_compositional(sysm, pieces, weights, level, decay,
                                          setting=setting, split=split)
    return result(ok, why, checks)
