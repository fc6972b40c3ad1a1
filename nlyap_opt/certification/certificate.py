r"""The region-of-attraction certificate: the one definition of conditions (a), (b), (c).

For a level :math:`c` and :math:`\Omega_c = \{x : \|x\|_2 \le r,\ V(x) \le c\}` the set
:math:`\Omega_c \cup E` lies in the region of attraction of the **true** closed loop when

- (a) decrease on :math:`\{\varepsilon \le \|x\| \le r,\ V(x) \le c\}`:
  :math:`\nabla V\cdot f(x,\kappa(x)) < 0` (true ``f``); for learned :math:`\varphi` with
  :math:`\|f-\varphi\| \le \eta` on the dynamics box, either pointwise
  :math:`\nabla V\cdot\varphi + \eta\sqrt{\|\nabla V\|^2 + s^2} < 0` (Cauchy–Schwarz) or the
  paper's :math:`\nabla V\cdot\varphi < -\beta`, :math:`\beta > M\eta`,
  :math:`M \ge \sup\|\nabla V\|` (rigorous); and :math:`\kappa(x) \in U`, the ball inside the
  dynamics box (else the bound on :math:`\|f - \varphi\|` does not apply);
- (b) containment: :math:`V(x) > c` on :math:`\|x\| = r`, and
  :math:`B_\varepsilon \subseteq \Omega_c` (:math:`V < c` on :math:`\|x\| = \varepsilon`);
- (c) inner ball: :math:`E = \{x^\top P x \le c_q\} \supseteq B_\varepsilon` is a quadratic
  Lyapunov sublevel set of the true closed loop — *proved* for known ``f``
  (:func:`nlyap_opt.certification.roa.certify_inner_ellipse`), the paper's *assumption* for unknown
  ``f``. Where the true ``f`` is available to the tool, the assumption is checked too: a check that
  does not confirm it withholds the certificate (the setting with less information may not
  certify what the known-f setting refuses).

:class:`RoaProblem` holds the objects (saved float64 networks, radii, η), :func:`certify_roa`
proves a level, :class:`RoaCertificate` is the typed result with the certified set's
membership test, its area and its JSON form (``certificate.json``), and
:func:`recheck_certificate` re-verifies a saved certificate from its hashed artifacts.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import time
from dataclasses import dataclass, field, replace
from enum import Enum
from pathlib import Path
from types import SimpleNamespace

import casadi as ca
import numpy as np

import systems
from systems import System
from systems.base import check_box
from verification import VerificationProblem
from verification.verify import check_file_options

from ..design.control import InnerStatus, lyapunov_matrix
from ..distributed import parallel
from ..distributed.parallel import ahead
from ..kernel import sxjson
from ..kernel.domain import Ball, Region, as_domain, parse_set
from ..kernel.errors import ConfigError, DimensionError, InputRangeError, NetworkFileError
from ..kernel.jsonio import MAX_INPUT_BYTES, read_file_bytes, write_atomic
from ..kernel.network import Network
from ..kernel.provenance import fingerprint
from ..kernel.symbolic import (
    closed_loop,
    learned_components_of,
    learned_rhs,
    lie_derivative,
    robust_lie,
)
from ..kernel.walker import evaluate
from ..learned.bounds import gradient_bound
from ..learned.inner_from_data import prove_inner_ellipse_from_data
from .roa import (
    BELOW_LEAST,
    INNER_LEVEL_MARGIN,
    SaturatedLoop,
    candidate_level,
    certify_inner_ellipse,
    certify_level,
    ellipse_around_ball,
    grid_area,
    grid_points,
    inner_ball_level,
    inner_ellipse_bound,
    quadratic_form,
)

__all__ = [
    "CertStatus", "Decrease", "RoaProblem", "RoaCertificate", "InnerEllipse", "certify_roa",
    "recheck_certificate", "recheck_run", "certify_with_inner_search", "load_artifact",
    "sha256_file", "FORMAT", "VERSION", "system_fingerprint", "system_binding", "spec_factory",
    "status_text", "bound_system", "read_certificate_file", "LevelPolicy", "NEURAL_POLICY",
    "certify_candidate", "InnerEllipseCache", "VolumeToBeat",
    "INNER_FACTORS", "NOT_CHECKED", "unchecked",
]

#: the reason of a candidate that was not verified because no certificate of it could beat
#: a certified one (:class:`VolumeToBeat`) starts with this: nothing was found false
NOT_CHECKED = "not checked"
#: how :meth:`VolumeToBeat.cannot_beat` starts its reason
CANNOT_BEAT = "cannot beat"

FORMAT = "nlyap-roa-certificate"
VERSION = 4
#: versions this nlyap reads (2: before domains, its region is the ball of outer_radius; 2
#: and 3: before the system binding, displayed but not re-checked)
READABLE_VERSIONS = (2, 3, 4)


class CertStatus(str, Enum):
    """Outcome of :func:`certify_roa`."""

    CERTIFIED = "certified"
    NOT_CERTIFIED = "not certified"
    #: a check the tool ran refutes an assumption the certificate would rest on
    ASSUMPTION_REFUTED = "assumption refuted"
    COUNTEREXAMPLE = "counterexample"

    def __str__(self) -> str:
        return self.value


#: the largest artifact a certificate may name
MAX_ARTIFACT_BYTES = MAX_INPUT_BYTES


def sha256_file(path: str | Path) -> str:
    """Hex sha256 of a regular file's bytes (a pipe or device raises :class:`ConfigError`,
    without waiting on it; see :func:`~nlyap_opt.kernel.jsonio.read_file_bytes`)."""
    return hashlib.sha256(read_file_bytes(path, "file", MAX_ARTIFACT_BYTES)).hexdigest()


def status_text(status: str, declared) -> str:
    """The status word of a certificate: ``"certified under the declared assumptions: …"``
    when it is certified and rests on declarations about ``f`` (each named by the words
    before its colon), else the status itself."""
    status = str(getattr(status, "value", status))
    if status != CertStatus.CERTIFIED.value or not declared:
        return status
    names = "; ".join(str(a).split(":")[0].strip() for a in declared)
    return f"certified under the declared assumptions: {names}"


# ============================================================================ system binding
def _floats(a) -> list:
    """An array as its shape and the exact hex of each float64 (no rounding, no locale)."""
    a = np.asarray(a, dtype=float)
    return [list(a.shape), [float(v).hex() for v in a.ravel()]]


def _graph(F: ca.Function) -> list:
    """The instruction list of an SX Function: operation codes, work-vector indices and the
    exact constants, with the sparsity of every input and output."""
    out: list = [[list(F.sparsity_in(i).get_triplet()) + [F.size1_in(i), F.size2_in(i)]
                  for i in range(F.n_in())],
                 [list(F.sparsity_out(i).get_triplet()) + [F.size1_out(i), F.size2_out(i)]
                  for i in range(F.n_out())]]
    for k in range(F.n_instructions()):
        op = int(F.instruction_id(k))
        row = [op, [int(i) for i in F.instruction_input(k)],
               [int(i) for i in F.instruction_output(k)]]
        if op == ca.OP_CONST:
            row.append(float(F.instruction_constant(k)).hex())
        out.append(row)
    return out


#: nodes per axis of the grid on which a black-box callable's values enter its fingerprint
CALLABLE_NODES = 3
#: beyond this many grid nodes (2 per axis past 12 variables), a callable's fingerprint uses
#: this many seeded points of its box instead
CALLABLE_POINTS = 3 ** 8


def _system_parts(system) -> dict:
    """What a certificate binds, part by part (plain JSON, deterministic)."""
    parts = {
        "kind": system.kind,
        "dimensions and names": [system.nx, system.nu, list(system.state_names),
                                 list(system.input_names)],
        "state box": _floats(system.state_box),
        "input box": _floats(system.input_box),
        "equilibrium input u_eq": _floats(system.u_eq),
        "known components": [int(i) for i in system.known_state_derivatives],
        "declared assumptions": None if system.declarations is None
        else system.declarations.to_dict(),
    }
    if system.kind == "model":
        parts["f"] = _graph(system.f_fun)
    else:
        parts["known components"].append(_graph(system.known_function()))
        if system.kind == "samples":
            smp = system.samples
            parts["f"] = [_floats(smp.box), [int(c) for c in smp.counts],
                          hashlib.sha256(np.ascontiguousarray(smp.values, dtype="<f8")
                                         .tobytes()).hexdigest()]
        else:   # a callable: its values on a small grid of its sampling box, 12 digits
            box = np.asarray(system.sampling_box, dtype=float)
            n = CALLABLE_NODES if CALLABLE_NODES ** len(box) <= 3 ** 8 else 2
            if n ** len(box) <= CALLABLE_POINTS:
                axes = [np.linspace(lo, hi, n) for lo, hi in box]
                pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(box))
            else:   # beyond 12 variables: seeded points (PCG64: the same on every machine)
                u = np.random.default_rng(0).random((CALLABLE_POINTS, len(box)))
                pts = box[:, 0] + (box[:, 1] - box[:, 0]) * u
            vals = system.evaluate(pts[:, :system.nx], pts[:, system.nx:] if system.nu
                                   else None)
            parts["f"] = [_floats(box), [f"{v:.12e}" for v in np.asarray(vals).ravel()]]
    return parts


def _digest(obj) -> str:
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return hashlib.sha256(text.encode()).hexdigest()


def system_binding(system) -> dict:
    """``{"sha256": …, "parts": {part: sha256}}``: the canonical hash of a system and of
    each of its parts (``f`` as the instruction list of its CasADi graph with the
    parameters substituted and the constants exact; the state and input boxes; ``u_eq``;
    the known components; the declared assumptions; for data, the sample values or a
    callable's values on a fixed grid). Deterministic across processes and machines: no
    Python ``hash()``, no object ids, floats as their exact hex."""
    parts = {k: _digest(v) for k, v in _system_parts(system).items()}
    return {"sha256": _digest(parts), "parts": parts}


def system_fingerprint(system) -> str:
    """The sha256 of :func:`system_binding` (one hex string per system)."""
    return system_binding(system)["sha256"]


def spec_factory(path: str | Path) -> str | None:
    """The ``factory`` a system spec file names (Python code run when it is loaded), or
    ``None``; read as TOML only (nothing imported). A file that cannot be read answers
    ``None``: loading it then reports why."""
    import tomllib  # lazy: tomllib, in the standard library from Python 3.11 only

    try:
        spec = tomllib.loads(read_file_bytes(path, "system spec").decode("utf-8"))
    except (OSError, ConfigError, ValueError, RecursionError):  # TOMLDecodeError included
        return None
    return None if "factory" not in spec else str(spec["factory"])


def _finite(name: str, value, *, low: float | None = None, strict: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise ConfigError(f"{name} must be finite, got {value!r}")
    if low is not None and (v <= low if strict else v < low):
        raise ConfigError(f"{name} must be {'>' if strict else '>='} {low:g}, got {v:g}")
    return v


@dataclass
class InnerEllipse:
    """Condition (c): ``E = {xᵀPx ≤ level}`` with ``B_ε ⊆ E``.

    ``status`` is the verifier's word on ``P·J(y) + J(y)ᵀP ≺ 0`` over a box containing ``E``
    for the **true** closed loop (``"certified"``, ``"inner ellipse counterexample"``, ...);
    ``proved`` says whether the certificate rests on that proof (known f) or on the paper's
    assumption (learned f).
    """

    status: str
    P: np.ndarray
    level: float
    half_widths: np.ndarray
    proved: bool
    #: how ``V̇_q < 0`` on ``E∖{0}`` was proved: ``"minors"`` or ``"frobenius"`` (``P J + JᵀP
    #: ≺ 0``, exponential), ``"shell r=ε_s + minors|frobenius"`` (``V̇_q < 0`` directly on
    #: ``E∖B_{ε_s}``, one of those on a small ellipse), ``"blow-up w=[…], m=…"``
    #: (:func:`nlyap_opt.certification.roa.certify_inner_blowup`, a centre manifold), ``""`` when
    #: not proved
    form: str = ""

    @property
    def certified(self) -> bool:
        """Whether the check of ``E`` on the true closed loop certified it."""
        return self.status == InnerStatus.CERTIFIED.value

    def contains(self, pts: np.ndarray) -> np.ndarray:
        return np.einsum("ij,jk,ik->i", pts, self.P, pts) <= self.level

    def to_dict(self) -> dict:
        return {"status": self.status, "P": np.asarray(self.P).tolist(), "level": self.level,
                "box_half_widths": np.asarray(self.half_widths).tolist(), "proved": self.proved,
                "form": self.form}

    @classmethod
    def from_dict(cls, d: dict) -> InnerEllipse:
        return cls(str(d["status"]), np.asarray(d["P"], dtype=float), float(d["level"]),
                   np.asarray(d.get("box_half_widths", []), dtype=float), bool(d["proved"]),
                   str(d.get("form", "")))


@dataclass
class Decrease:
    """Symbolic pieces of condition (a): ``lie + margin < 0`` where ``V ≤ level``."""

    x: object
    V: object
    lie: object
    margin: float
    M: float | None
    smoothing: float
    rhs: object = None      # the closed loop's right-hand side g (lie = ∇V·g)
    #: learned dynamics, pointwise margin: ``eta``, ``smoothing`` and ``components`` of the
    #: robust ``lie`` (:func:`nlyap_opt.kernel.symbolic.robust_lie`); ``None`` otherwise
    robust: dict | None = None
    #: the closed loop split by its saturated controller (a quadratic ``V`` only;
    #: :class:`~nlyap_opt.certification.roa.SaturatedLoop`), else ``None``
    saturated: object = None


@dataclass
class RoaProblem:
    """What a region-of-attraction certificate is about.

    Parameters
    ----------
    system : systems.System
        The true system (its ``f`` is used for known dynamics and for the checks of (c)).
    V : Network or object with ``casadi(x)``
        Lyapunov function (a saved float64 network, a quadratic, an SOS polynomial).
    controller : Network, optional
        ``κ`` (``None`` for input-free systems).
    dynamics : Network, optional
        Learned ``φ``; ``None``: the true ``f`` (known-dynamics setting).
    inner, outer : float
        ``0 ≤ ε < r``: the excluded ball ``B_ε`` and the verification ball ``B_r``.
    domain : Region or dict, optional
        The verification domain ``D`` (:mod:`nlyap_opt.kernel.domain`: a ball, a box or an
        ellipsoid holding the origin inside) in place of the ball ``B_r``; ``outer`` is then
        ``max ‖x‖`` over ``D`` (information only). ``B_ε`` must lie inside ``D``.
    initial_set : Region or dict, optional
        ``X_I``: a set that must lie in the certified set (``X_I ⊆ D`` and ``V < c`` on it).
    eta : float
        ``‖f − φ‖ ≤ η`` on ``dynamics_box × input_box`` (learned dynamics only).
    margin_mode : {"pointwise", "global"}
        Decrease condition for learned dynamics (module docstring).
    smoothing : float, optional
        ``s ≥ 0`` of the pointwise condition (any ``s`` is sound; it only tightens).
    norm_smoothing : float
        Without ``smoothing``: ``s = norm_smoothing·M`` (``M ≥ sup‖∇V‖``, rigorous).
    dynamics_box, input_box : (nx, 2), (nu, 2) array_like, optional
        Where the bound on ``‖f − φ‖`` holds (learned dynamics: required).
    dynamics_assumptions : list of str
        What the bound on ``‖f − φ‖`` assumes (``bounds.json``), copied into the certificate.
    verify_options : dict
        Options of :func:`verification.verify`.
    """

    system: object
    V: object
    controller: Network | None = None
    dynamics: Network | None = None
    inner: float = 0.1
    outer: float = 1.0
    eta: float = 0.0
    margin_mode: str = "pointwise"
    smoothing: float | None = None
    norm_smoothing: float = 0.0
    dynamics_box: np.ndarray | None = None
    input_box: np.ndarray | None = None
    dynamics_assumptions: list = field(default_factory=list)
    verify_options: dict = field(default_factory=dict)
    domain: Region | None = None
    initial_set: Region | None = None

    def __post_init__(self):
        if not hasattr(self.system, "nx"):
            raise ConfigError(f"system must be a System (e.g. systems.get(name)), got "
                              f"{type(self.system).__name__} {str(self.system)[:40]!r}")
        if not (isinstance(self.V, Network) or callable(getattr(self.V, "casadi", None))):
            raise ConfigError(f"V must be a Network (e.g. Network.load(path)), got "
                              f"{type(self.V).__name__} {str(self.V)[:40]!r}")
        nx = self.system.nx
        self._check_parts()
        self.inner = _finite("inner radius", self.inner, low=0.0)
        if self.domain is None:
            self.outer = _finite("outer radius", self.outer, low=0.0, strict=True)
            self.domain = Ball(self.outer, nx)
        else:
            self.domain = as_domain(self.domain, nx)
            self.outer = self.domain.max_norm()
        if not self.inner < self.domain.inradius():
            raise ConfigError(
                f"need 0 <= inner < {self.domain.inradius():g} (the inner ball inside the "
                f"domain {self.domain.describe()}), got inner={self.inner:g}; choose a "
                "smaller inner radius")
        if self.initial_set is not None:
            self.initial_set = parse_set(self.initial_set, nx, "initial_set", domain=False)
        self.eta = _finite("eta", self.eta, low=0.0)
        if self.smoothing is not None:
            self.smoothing = _finite("smoothing", self.smoothing, low=0.0)
        self.norm_smoothing = _finite("norm_smoothing", self.norm_smoothing, low=0.0)
        if self.margin_mode not in ("pointwise", "global"):
            raise ConfigError(f"margin_mode must be 'pointwise' or 'global', got "
                              f"{self.margin_mode!r}")
        if isinstance(self.V, Network) and (self.V.n_in != nx or self.V.n_out != 1):
            raise DimensionError(f"V must map R^{nx} -> R (system {self.system.name!r}), got "
                                 f"R^{self.V.n_in} -> R^{self.V.n_out}")
        if self.dynamics is None:
            if self.eta:
                raise ConfigError("eta > 0 needs learned dynamics; pass dynamics= or eta=0")
        else:
            if self.dynamics_box is None:
                raise ConfigError("learned dynamics need dynamics_box (the box of ‖f − φ‖ ≤ η)")
            self.dynamics_box = check_box(self.dynamics_box, nx, "dynamics_box")
            if self.system.nu:
                if self.input_box is None:
                    raise ConfigError("learned dynamics with inputs need input_box (U)")
                self.input_box = check_box(self.input_box, self.system.nu, "input_box")

    def _check_parts(self) -> None:
        """The networks are of their kinds and sizes (their ``meta`` kind, where saved
        with one), the radii are numbers, and ``verify_options`` are the verifier's."""
        sysm = self.system
        for name, net, kind in (("V", self.V, "lyapunov"), ("controller", self.controller,
                                                            "controller"),
                                ("dynamics", self.dynamics, "dynamics")):
            if net is None or name == "V" and not isinstance(net, Network):
                continue
            if not isinstance(net, Network):
                raise ConfigError(f"{name} must be a Network (Network.load(path)) or None, got "
                                  f"{type(net).__name__}")
            saved = net.meta.get("kind")
            if saved is not None and saved != kind:
                raise ConfigError(f"{name} is a network of kind {saved!r} (its meta says so), "
                                  f"not a {kind} network; pass the {kind} network")
        if self.controller is not None and (self.controller.n_in != sysm.nx
                                            or self.controller.n_out != sysm.nu):
            raise DimensionError(
                f"controller must map R^{sysm.nx} -> R^{sysm.nu} (system {sysm.name!r}"
                f"{', which has no inputs: pass controller=None' if not sysm.nu else ''}), "
                f"got R^{self.controller.n_in} -> R^{self.controller.n_out}")
        for name in ("inner", "outer"):
            v = getattr(self, name)
            if isinstance(v, (bool, str, bytes)):
                raise ConfigError(f"{name} must be a number, got {v!r}")
        opts = self.verify_options
        if isinstance(opts, dict):   # numpy scalars (a config's np.int64) as Python's
            opts = {k: v.item() if isinstance(v, np.generic) else v for k, v in opts.items()}
        self.verify_options = check_file_options(
            opts, "RoaProblem", "pass options of verification.verify_interval")

    @property
    def known(self) -> bool:
        """True for the known-dynamics setting (``f`` itself in the decrease)."""
        return self.dynamics is None

    @property
    def ball_box(self) -> np.ndarray:
        """The bounding box of the domain ``D``."""
        return self.domain.bounding_box()

    def V_expr(self, x):
        """``V`` as a CasADi expression of ``x``."""
        return self.V.casadi(x)

    def decrease(self) -> Decrease:
        """The symbolic decrease condition ``lie + margin < 0`` (built once, cached).

        For learned dynamics this computes the rigorous ``M ≥ sup_D ‖∇V‖`` and checks
        ``κ(D) ⊆ U`` and ``D ⊆`` dynamics box, all on ``D``'s bounding box
        (:func:`nlyap_opt.learned.bounds.gradient_bound`);
        :class:`~nlyap_opt.kernel.errors.InputRangeError` when they fail.
        """
        if getattr(self, "_decrease", None) is not None:
            return self._decrease

        M, margin, s = None, 0.0, 0.0
        if not self.known:
            gb = gradient_bound(self.V, self.ball_box, controller=self.controller,
                                input_box=self.input_box if self.system.nu else None,
                                state_box=self.dynamics_box)
            M = float(gb.M)
            if self.margin_mode == "global":
                margin = float(np.nextafter(M * self.eta, np.inf))
            else:
                s = self.smoothing if self.smoothing is not None else self.norm_smoothing * M
        cl = closed_loop(self.system, self.controller, self.dynamics, strict=True)
        Vx = self.V_expr(cl.x)
        lie = lie_derivative(Vx, cl.x, cl.rhs)
        robust = None
        if not self.known and self.margin_mode == "pointwise":
            comp = learned_components_of(self.system, self.dynamics)
            lie = robust_lie(lie, Vx, cl.x, self.eta, s, comp)
            robust = {"eta": self.eta, "smoothing": s, "components": comp}
        saturated = None
        if self.controller is not None and quadratic_form(self.V) is not None:
            def F_of(x, w):     # the open loop that closed_loop() composes with κ
                return self.system.f_fun(x, w) if self.dynamics is None else \
                    learned_rhs(self.system, self.dynamics, x, w)
            saturated = SaturatedLoop(cl.x, F_of, self.controller)
        self._decrease = Decrease(cl.x, Vx, lie, margin, M, s, cl.rhs, robust, saturated)
        return self._decrease

    def V_numpy(self, pts: np.ndarray) -> np.ndarray:
        """``V`` at ``(N, nx)`` points (float64)."""
        if isinstance(self.V, Network):
            return self.V.numpy(pts)[:, 0]
        x = ca.SX.sym("x", self.system.nx)
        F = ca.Function("V", [x], [self.V_expr(x)])
        return evaluate(F, [np.asarray(pts, dtype=float)])[0][:, 0]


@dataclass
class RoaCertificate:
    """Typed result of :func:`certify_roa` (and the content of ``certificate.json``).

    The certified set is ``{‖x‖ ≤ outer, V(x) ≤ level} ∪ E`` when ``status`` is
    ``CERTIFIED`` (:meth:`contains`), empty otherwise.
    """

    status: CertStatus
    reason: str
    system: str
    setting: str                       # "known" or "learned"
    level: float
    inner: float
    outer: float
    eta: float = 0.0
    margin_mode: str = "none"
    margin: float = 0.0
    smoothing: float = 0.0
    M: float | None = None
    decrease_condition: str = ""
    checks: dict = field(default_factory=dict)   # condition -> verifier status
    inner_ellipse: InnerEllipse | None = None
    assumptions: list = field(default_factory=list)
    history: list = field(default_factory=list)
    counterexamples: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    seconds: float = 0.0
    artifacts: dict = field(default_factory=dict)  # role -> {"file", "sha256"}
    declared: list = field(default_factory=list)   # assumptions declared by the user
    V: object = field(default=None, repr=False)
    domain: Region | None = None                   # D (None: the ball of radius outer)
    initial_set: Region | None = None              # X_I, proved inside the certified set

    def region_text(self) -> str:
        """``ε ≤ ‖x‖ ≤ r`` (the ball) or ``‖x‖ ≥ ε in D`` in words."""
        if self.domain is None or self.domain.plain_ball:
            return f"{self.inner:g} ≤ ‖x‖ ≤ {self.outer:g}"
        return f"‖x‖ ≥ {self.inner:g} in {self.domain.describe()}"

    @property
    def certified(self) -> bool:
        return self.status is CertStatus.CERTIFIED

    def summary(self) -> str:
        """One line: status, level, reason."""
        if self.certified:
            return (f"{status_text(self.status, self.declared)}: level {self.level:.6g} on "
                    f"{self.region_text()} ({self.setting} dynamics)")
        pts = np.atleast_2d(np.asarray(self.counterexamples, dtype=float)) \
            if self.status is CertStatus.COUNTEREXAMPLE and np.size(self.counterexamples) \
            else None
        where = "" if pts is None else \
            f" (x = {np.array2string(pts[0], precision=6, separator=', ')} violates it)"
        return f"{self.status.value}: {self.reason}{where}"

    # ------------------------------------------------------------------ the certified set
    def contains(self, points) -> np.ndarray:
        """Which ``(N, nx)`` points lie in the certified set (all ``False`` if not certified)."""
        pts = np.atleast_2d(np.asarray(points, dtype=float))
        if not self.certified:
            return np.zeros(len(pts), dtype=bool)
        if self.V is None:
            raise ValueError("this certificate holds no V (loaded without artifacts); "
                             "use recheck_certificate() to load it with its networks")
        v = self.V.numpy(pts)[:, 0] if isinstance(self.V, Network) else _numpy_of(self.V, pts)
        in_d = np.linalg.norm(pts, axis=1) <= self.outer if self.domain is None \
            else self.domain.contains(pts)
        m = in_d & (v <= self.level)
        if self.inner_ellipse is not None:
            m |= self.inner_ellipse.contains(pts)
        return m

    def area(self, box, n: int) -> float:
        """Area (volume) of the certified set by cell counting on an ``n^nx`` grid over box."""

        box = np.asarray(box, dtype=float)
        pts, shape = grid_points(box, n)
        return grid_area(self.contains(pts).reshape(shape), box)

    # ------------------------------------------------------------------ JSON
    def to_dict(self) -> dict:
        return {
            "format": FORMAT, "version": VERSION,
            "status": self.status.value, "reason": self.reason, "system": self.system,
            "setting": self.setting,
            "dynamics": "known (true f)" if self.setting == "known" else "learned φ",
            "level": self.level, "inner_radius": self.inner, "outer_radius": self.outer,
            "eta": self.eta, "margin_mode": self.margin_mode, "margin": self.margin,
            "norm_smoothing": self.smoothing, "M": self.M,
            "decrease_condition": self.decrease_condition, "checks": dict(self.checks),
            "inner_ellipse": None if self.inner_ellipse is None
            else self.inner_ellipse.to_dict(),
            "assumptions": list(self.assumptions),
            "assumptions_declared_by_user": list(self.declared), "history": self.history,
            "counterexamples": np.asarray(self.counterexamples).tolist(),
            "verify_seconds": self.seconds, "artifacts": dict(self.artifacts),
            "state_dimension": None if self.domain is None else self.domain.n,
            "domain": None if self.domain is None else self.domain.to_dict(),
            "initial_set": None if self.initial_set is None else self.initial_set.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> RoaCertificate:
        if isinstance(d, dict) and d.get("format") == "nlyap-compositional-certificate":
            raise ConfigError("a compositional certificate (a sum of quadratic subsystem "
                              "functions, no networks): re-check it with `nlyap verify "
                              "--certificate DIR`; simulate and export need a neural run")
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise ConfigError(f"not an nlyap certificate (expected format {FORMAT!r}); "
                              "pass the certificate.json written by `nlyap run`/`compare`")
        if d.get("version") not in READABLE_VERSIONS:
            raise ConfigError(f"certificate version {d.get('version')!r} is not supported "
                              f"(this nlyap reads versions "
                              f"{', '.join(map(str, READABLE_VERSIONS))}); rerun the command")
        try:
            ce = np.asarray(d["counterexamples"], dtype=float)
            sets = {key: parse_set(d[key], int(d["state_dimension"]), key,
                                   domain=key == "domain")
                    for key in ("domain", "initial_set") if d.get(key) is not None}
            arts = d["artifacts"]
            if not isinstance(arts, dict) or not all(isinstance(a, dict)
                                                     for a in arts.values()):
                raise TypeError("artifacts must map each role to an object")
            words = (d["assumptions"], d.get("assumptions_declared_by_user", []))
            if not all(isinstance(w, list) and all(isinstance(t, str) for t in w)
                       for w in words):
                raise TypeError("assumptions must be lists of strings")
            return cls(
                CertStatus(d["status"]), str(d["reason"]), str(d["system"]), str(d["setting"]),
                _number(d, "level"), _number(d, "inner_radius"), _number(d, "outer_radius"),
                _number(d, "eta"), str(d["margin_mode"]), _number(d, "margin"),
                _number(d, "norm_smoothing"), None if d["M"] is None else _number(d, "M"),
                str(d["decrease_condition"]), dict(d["checks"]),
                None if d["inner_ellipse"] is None
                else InnerEllipse.from_dict(d["inner_ellipse"]),
                list(words[0]), list(d["history"]),
                ce, _number(d, "verify_seconds"),
                dict(arts), list(words[1]),
                domain=sets.get("domain"), initial_set=sets.get("initial_set"))
        except (KeyError, TypeError, ValueError, OverflowError, ConfigError) as err:
            raise ConfigError(f"malformed certificate: {type(err).__name__}: {err}; rerun "
                              "the command that wrote it") from None


def _number(d: dict, key: str) -> float:
    """``d[key]`` as a float: a JSON number, never a string or a boolean (a certificate's
    numbers are written as numbers; anything else is an edit)."""
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise TypeError(f"{key} must be a number, got {type(v).__name__} {v!r}")
    try:
        return float(v)
    except OverflowError:
        raise ValueError(f"{key} is an integer beyond float range") from None


def _numpy_of(V, pts):
    n = pts.shape[1]
    x = ca.SX.sym("x", n)
    return evaluate(ca.Function("V", [x], [V.casadi(x)]), [pts])[0][:, 0]


def _decrease_text(problem: RoaProblem, margin: float, smoothing: float) -> str:
    if problem.known:
        return "∇V·f(x, κ(x)) < 0"
    if problem.margin_mode == "pointwise":
        return (f"∇V·φ(x, κ(x)) + η·sqrt(‖∇V(x)‖² + s²) < 0 with η = {problem.eta:.6g}, "
                f"s = {smoothing:.4g} (implies ∇V·f < 0 by Cauchy–Schwarz where ‖f − φ‖ ≤ η)")
    return f"∇V·φ(x, κ(x)) < −β with β = M·η = {margin:.6g} (rounded up)"


def certify_roa(problem: RoaProblem, level: float, *, search: bool = False,
                check_inner_ellipse: bool = True, follow_violations: bool = False,
                inner_ellipse: InnerEllipse | None = None,
                ellipses: InnerEllipseCache | None = None, taylor_only: bool = False,
                least: tuple[float, str] | None = None, log=print) -> RoaCertificate:
    r"""Prove conditions (a), (b), (c) at ``level`` (or, with ``search``, at the largest level
    reachable from it downwards; see :func:`nlyap_opt.certification.roa.certify_level`).

    Parameters
    ----------
    problem : RoaProblem
    level : float
        The level to prove (``search=False``: exactly this one), > 0 and finite.
    search : bool
        Step the level down after a counterexample or an undecided verdict.
    check_inner_ellipse : bool
        Run condition (c) (``False`` only inside CEGIS iterations, which certify (c) once
        at the end through the pipeline's certificate stage).
    follow_violations : bool
        With ``search``: follow decrease counterexamples down to the least ``V`` of a
        violation, and climb back from a proved level by bisection
        (:func:`nlyap_opt.certification.roa.certify_level`).
    inner_ellipse : InnerEllipse, optional
        A saved certificate's proved ellipse: condition (c) checks exactly its ``P`` in its
        ``form`` instead of searching the candidates (:func:`recheck_certificate`). Used
        where (c) is checked on the true closed loop; ignored otherwise.
    ellipses : InnerEllipseCache, optional
        Condition (c)'s results shared with other candidates ``V`` of the same closed loop
        (without ``inner_ellipse``): computed once per inner radius.
    taylor_only : bool
        Decide condition (a) only by the quadratic test on whole sublevel sets
        (:class:`~nlyap_opt.certification.roa.TaylorDecrease`), never by bisection: a level
        it does not prove is ``unknown`` (a cheap search for a quadratic ``V``).
    least : (float, str), optional
        With ``search``: a level below which no certificate could beat the one named
        (:meth:`VolumeToBeat.least_level`); the search does not go below it.

    Returns
    -------
    RoaCertificate
        ``CERTIFIED`` only when every condition was verified by the interval verifier.
    """
    _check_certify_args(problem, inner_ellipse, ellipses, log)
    level = _finite("level", level, low=0.0, strict=True)
    # (c) does not depend on the level: on a cluster it runs beside (a) and (b), whose
    # narrow checks leave workers idle, when the level is expected to hold (a re-check);
    # in a search, which may end without a level, and serially, it runs after (a) and (b)
    # and only if they hold
    fn = ellipses.get if ellipses is not None and inner_ellipse is None else _inner_ellipse
    job = ahead(fn, problem, inner_ellipse, when=not search) if check_inner_ellipse else None
    with job or contextlib.nullcontext():
        return _certify_roa(problem, level, search, follow_violations, job, log, taylor_only,
                            least)


def _check_certify_args(problem, inner_ellipse, ellipses, log) -> None:
    """One line naming the argument of :func:`certify_roa` that is not of its type."""
    for name, value, kind, how in (
            ("problem", problem, RoaProblem, "RoaProblem(system, V, ...)"),
            ("inner_ellipse", inner_ellipse, InnerEllipse, "a saved certificate's ellipse"),
            ("ellipses", ellipses, InnerEllipseCache, "InnerEllipseCache()")):
        if (value is not None or name == "problem") and not isinstance(value, kind):
            raise ConfigError(f"certify_roa: {name} must be {how}"
                              f"{' or None' if name != 'problem' else ''}, got "
                              f"{type(value).__name__}")
    if not callable(log):
        raise ConfigError(f"certify_roa: log must be a function of one string (print, or "
                          f"lambda m: None for silence), got {log!r}")


def _certify_roa(problem: RoaProblem, level: float, search: bool, follow_violations: bool,
                 inner_job, log, taylor_only: bool = False,
                 least: tuple[float, str] | None = None) -> RoaCertificate:
    """:func:`certify_roa`'s body; ``inner_job``: condition (c)'s :class:`Ahead`, or ``None``."""

    t0 = time.perf_counter()
    sysm = problem.system
    base = _identity(problem)
    assumptions = ["V and κ are the float64 networks saved with this certificate "
                   "(verified as saved)"]
    if not problem.known:
        assumptions.append(
            f"f is Lipschitz on the dynamics box and ‖f − φ‖ ≤ η = {problem.eta:.6g} on "
            f"{np.asarray(problem.dynamics_box).tolist()}"
            + ("" if not sysm.nu else f" × U = {np.asarray(problem.input_box).tolist()}")
            + (" (" + "; ".join(problem.dynamics_assumptions) + ")"
               if problem.dynamics_assumptions else ""))
    try:
        dec = problem.decrease()
    except InputRangeError as err:
        return RoaCertificate(CertStatus.NOT_CERTIFIED, f"the bound ‖f − φ‖ ≤ η does not "
                              f"apply: {err}", level=0.0, assumptions=assumptions,
                              seconds=time.perf_counter() - t0, **base)
    M, margin, smoothing = dec.M, dec.margin, dec.smoothing
    lc = certify_level(dec.x, dec.V, dec.lie, level=level, inner=problem.inner,
                       domain=problem.domain, margin=margin, max_tries=8 if search else 1,
                       shrink=1e-3 if search else 0.0, verify_options=problem.verify_options,
                       log=log, follow_violations=follow_violations,
                       quadratic=quadratic_form(problem.V),
                       rhs=dec.rhs, robust=dec.robust, taylor_only=taylor_only,
                       saturated=dec.saturated, least=least if search else None)
    # the checks of the certified level (a search's later tries may have failed above it)
    last = lc.history[-1] if lc.history else {}
    if lc.status == "certified":
        last = next(h for h in lc.history if h["level"] == lc.level
                    and h.get("contains_inner_ball") == "verified")
    checks = {"(a) decrease": last.get("decrease") or "not run",
              "(b) V > level on ‖x‖ = r" if problem.domain.plain_ball else "(b) V > level on ∂D":
              last.get("containment") or "not run",
              "(b) B_ε ⊆ Ω_c": last.get("contains_inner_ball") or "not run"}
    if problem.initial_set is not None:
        checks["(d) X_I ⊆ Ω_c"] = "not run"
    common = dict(M=M, margin=margin, smoothing=smoothing, checks=checks,
                  decrease_condition=_decrease_text(problem, margin, smoothing),
                  history=lc.history, counterexamples=lc.counterexamples, **base)
    if lc.status != "certified":
        status = CertStatus.COUNTEREXAMPLE if (not search and len(lc.counterexamples)) \
            else CertStatus.NOT_CERTIFIED
        return RoaCertificate(status, lc.status, level=0.0 if search else level,
                              assumptions=assumptions, seconds=time.perf_counter() - t0,
                              **common)
    level = float(lc.level)
    ellipse = None
    status, reason = CertStatus.CERTIFIED, "conditions (a), (b) and (c) verified"
    if problem.initial_set is not None:
        res = _initial_set_check(problem, dec, level)
        checks["(d) X_I ⊆ Ω_c"] = res.status
        if res.status != "verified":
            return RoaCertificate(
                CertStatus.COUNTEREXAMPLE if res.status == "counterexample" and not search
                else CertStatus.NOT_CERTIFIED,
                f"the initial set X_I = {problem.initial_set.describe()} is not proved inside "
                f"Ω_c at level {level:.6g} ({res.status}: X_I must lie in D with V < level "
                "on it); shrink X_I or enlarge the domain", level=0.0 if search else level,
                assumptions=assumptions, seconds=time.perf_counter() - t0, **common)
        reason = "conditions (a), (b), (c) and X_I ⊆ Ω_c verified"
    if inner_job is not None:
        inner, proved_from = inner_job.result()
        verdict = inner["verdict"]
        ok = verdict is InnerStatus.CERTIFIED
        checks["(c) inner ellipse" + ("" if proved_from else ", true f")] = inner["status"]
        proved = problem.known or proved_from is not None
        if ok or not proved:
            ellipse = InnerEllipse(inner["status"], np.asarray(inner["P"]),
                                   float(inner["level"]), np.asarray(inner["box"]),
                                   proved=proved and ok,
                                   form=str(inner.get("form", "")) if ok else "")
        if proved and not ok:
            status, reason = CertStatus.NOT_CERTIFIED, f"condition (c): {inner['status']}"
        elif proved_from is not None:
            assumptions.append(f"condition (c) proved from {proved_from}")
        elif not problem.known:
            assumptions.append(
                "the inner ball B_ε lies in the quadratic-Lyapunov region of attraction E of "
                "the true closed loop (the paper's Assumption 3; condition (c) is not proved "
                "from samples)")
            if inner.get("checked") is False and verdict is InnerStatus.NOT_HURWITZ:
                status, reason = CertStatus.NOT_CERTIFIED, f"condition (c): {inner['status']}"
            elif inner.get("checked") is False:
                assumptions[-1] += "; no model is available to check it"
            elif not ok:
                refuted = verdict in (InnerStatus.COUNTEREXAMPLE, InnerStatus.NOT_HURWITZ)
                status = CertStatus.ASSUMPTION_REFUTED if refuted else CertStatus.NOT_CERTIFIED
                reason = (f"assumption (c) is {'refuted' if refuted else 'not confirmed'} by "
                          f"the tool's true-f check: {inner['status']}")
            else:
                assumptions[-1] += "; the tool's check on the true f agrees (certified)"
    else:
        reason = "conditions (a) and (b) verified; (c) not checked"
    return RoaCertificate(status, reason, level=level, inner_ellipse=ellipse,
                          assumptions=assumptions, seconds=time.perf_counter() - t0, **common)


def _identity(problem: RoaProblem) -> dict:
    """The fields of a :class:`RoaCertificate` that describe the problem, not the verdict."""
    return dict(system=problem.system.name, setting="known" if problem.known else "learned",
                inner=problem.inner, outer=problem.outer, eta=problem.eta,
                margin_mode="none" if problem.known else problem.margin_mode, V=problem.V,
                declared=_declared(problem.system), domain=problem.domain,
                initial_set=problem.initial_set)


def _initial_set_check(problem: RoaProblem, dec: Decrease, level: float):
    """``X_I ⊆ Ω_c``: on ``X_I``, ``V < level`` and every inequality of ``D`` holds strictly."""

    XI = problem.initial_set
    cons = XI.constraints(dec.x)
    dom = problem.domain.inequalities(dec.x)
    prob = VerificationProblem(dec.x, XI.bounding_box(), [g for g, _ in cons],
                               [dec.V - level] + [g for g, _ in dom],
                               [nm for _, nm in cons],
                               ["V<level on X_I"] + [f"X_I in D ({nm})" for _, nm in dom])
    return parallel.check(prob, **problem.verify_options)


def _declared(system) -> list[str]:
    """The user's declarations about f (verbatim), for systems that carry them."""
    describe = getattr(system, "describe_assumptions", None)
    return list(describe()) if describe is not None else []


def _inner_ellipse(problem: RoaProblem, saved: InnerEllipse | None = None
                   ) -> tuple[dict, str | None]:
    """Condition (c): ``(result, proved_from)``.

    With a model: :func:`nlyap_opt.certification.roa.certify_inner_ellipse` on the true closed loop
    (a proof for known f, a check of the assumption for learned φ); of the ``saved`` ellipse alone
    when it was certified there (its ``P`` and ``form``). Without a model: proved from the
    samples when the user declared a second-derivative bound
    (:func:`nlyap_opt.learned.inner_from_data.prove_inner_ellipse_from_data`), else the ellipse of
    the learned closed loop's linearisation, *assumed* (``checked: False``).
    """

    sysm = problem.system
    if getattr(sysm, "has_model", True):
        again = {}
        if saved is not None and saved.certified and saved.form:
            again = {"P": saved.P, "form": saved.form}
        return certify_inner_ellipse(sysm, problem.controller, problem.inner,
                                     verify_options=problem.verify_options, **again), None
    decl = getattr(sysm, "declarations", None)
    if decl is not None and getattr(decl, "hessian", None) is not None:
        res = prove_inner_ellipse_from_data(
            sysm, problem.controller, problem.inner, dynamics=problem.dynamics,
            eta=problem.eta, eta_state_box=problem.dynamics_box,
            eta_input_box=problem.input_box, verify_options=problem.verify_options)
        return res, res.get("proved_from", "samples and the declared bound H")
    return _assumed_ellipse(problem), None


def _assumed_ellipse(problem: RoaProblem) -> dict:
    """The quadratic ellipse ``E ⊇ B_ε`` of the learned closed loop's linearisation."""

    dec = problem.decrease()
    cl_rhs = _learned_closed_loop(problem)
    J = np.array(ca.Function("J", [dec.x], [ca.jacobian(cl_rhs, dec.x)])(
        np.zeros(problem.system.nx)), dtype=float)
    if np.max(np.linalg.eigvals(J).real) >= 0:
        return {"status": "closed-loop linearisation of φ not Hurwitz",
                "verdict": InnerStatus.NOT_HURWITZ, "P": np.eye(len(J)), "level": 0.0,
                "box": np.zeros(len(J)), "checked": False}

    P = lyapunov_matrix(J)
    c_q, a = ellipse_around_ball(P, problem.inner)
    return {"status": "assumed (no model to check it)", "verdict": InnerStatus.ASSUMED,
            "P": P, "level": c_q, "box": a, "checked": False}


def _learned_closed_loop(problem: RoaProblem):
    dec = problem.decrease()
    return closed_loop(problem.system, problem.controller, problem.dynamics, x=dec.x,
                       strict=True).rhs


class InnerEllipseCache:
    """Condition (c)'s results by inner radius, for candidates that differ only in ``V``.

    Condition (c) (the ellipse ``E ⊇ B_ε`` and its check) reads the system, the controller,
    the learned dynamics and its bound, the inner radius and the verifier options, never
    ``V``: the quadratic candidates of one run compute it once per radius
    (:func:`nlyap_opt.candidates.quadratic.certify_quadratics`). A problem that differs in
    anything (c) reads from the first one given is refused (``ValueError``).
    """

    def __init__(self):
        self._of: tuple | None = None
        self._by_inner: dict[float, tuple[dict, str | None]] = {}

    @staticmethod
    def _reads(problem: RoaProblem) -> tuple:
        """What condition (c) reads of ``problem`` except ε (objects by identity)."""
        arrays = tuple(None if a is None else np.asarray(a, dtype=float).tobytes()
                       for a in (problem.dynamics_box, problem.input_box))
        return ((problem.system, problem.controller, problem.dynamics),
                (float(problem.eta), arrays,
                 json.dumps(problem.verify_options, sort_keys=True, default=str)))

    def get(self, problem: RoaProblem, saved: InnerEllipse | None = None
            ) -> tuple[dict, str | None]:
        """``(result, proved_from)`` of condition (c) at ``problem.inner`` (computed on the
        first call for that radius)."""
        if saved is not None:
            raise ValueError("a saved ellipse is checked as saved, not shared")
        reads = self._reads(problem)
        if self._of is None:
            self._of = reads
        elif reads[1] != self._of[1] or any(
                a is not b for a, b in zip(reads[0], self._of[0], strict=True)):
            raise ValueError("InnerEllipseCache serves one closed loop: this problem differs "
                             "in the system, controller, dynamics or verifier options")
        eps = float(problem.inner)
        if eps not in self._by_inner:
            self._by_inner[eps] = _inner_ellipse(problem)
        return self._by_inner[eps]


#: the inner radii of a :class:`LevelPolicy` search, as multiples of the policy's radius
INNER_FACTORS = (1.0, 0.5, 0.25, 2.0, 0.125, 3.0)


@dataclass(frozen=True)
class LevelPolicy:
    r"""How a candidate ``V``'s level and inner radius are chosen: the one certification
    policy of :func:`certify_candidate` (quadratic, SOS and neural candidates, and the rows
    of ``nlyap compare``).

    The level is the largest sublevel set inside the domain that the interval verifier
    proves: the search starts at :func:`nlyap_opt.certification.roa.candidate_level` (the least
    ``V`` on ``∂D`` or at a sampled / IPOPT decrease violation; capped by a candidate's own level,
    e.g. an SDP level) and steps down after each refutation or undecided verdict
    (:func:`nlyap_opt.certification.roa.certify_level`).

    Attributes
    ----------
    inner_fraction : float
        The inner radius ``ε`` as a fraction of the problem's ``inner`` (> 0).
    factors : tuple of float
        Radii ``ε·f`` tried in turn, the first that certifies wins (``(1.0,)``: ``ε`` only).
        With more than one, the certificate's ``history`` lists every radius tried.
    smallest_level : bool
        Check each radius once, at the smallest level that holds its inner ball, instead of
        searching down from the candidate level (learned dynamics: there the robust margin
        has the most room).
    follow_violations : bool
        Follow decrease counterexamples down to the least ``V`` of a violation, and climb
        back from a proved level by bisection
        (:func:`nlyap_opt.certification.roa.certify_level`).
    whole_sets : bool
        With ``smallest_level``, for a quadratic ``V`` whose closed loop is smooth: each
        radius is first searched down from the candidate level with condition (a) decided
        only on whole sublevel sets (``certify_roa(..., taylor_only=True)``, no bisection),
        and checked at the smallest level only if that certifies nothing.
    """

    inner_fraction: float = 1.0
    factors: tuple[float, ...] = INNER_FACTORS
    smallest_level: bool = False
    follow_violations: bool = False
    whole_sets: bool = False

    def __post_init__(self):
        if not (math.isfinite(self.inner_fraction) and self.inner_fraction > 0):
            raise ValueError(f"inner_fraction must be finite and > 0, got "
                             f"{self.inner_fraction!r}")
        f = tuple(float(v) for v in self.factors)
        if not f or not all(math.isfinite(v) and v > 0 for v in f):
            raise ValueError(f"factors must be finite positive numbers, got {self.factors!r}")
        object.__setattr__(self, "factors", f)


#: the neural ``V``: the configured ε (the saved level exactly when one is claimed), then
#: the other radii of :data:`INNER_FACTORS`
NEURAL_POLICY = LevelPolicy()


@dataclass(frozen=True)
class VolumeToBeat:
    """A certified volume on the evaluation grid that another candidate must exceed to win
    (the run's best cheap certificate): a search whose result cannot exceed it is not
    attempted (:func:`certify_candidate`, the CEGIS iterations).

    Attributes
    ----------
    volume : float      the certified volume on the grid
    box : (nx, 2) ndarray, n : int   the evaluation grid (``n`` nodes per axis)
    label : str         how messages name the certificate (``"quadratic volume"``)
    ellipses : InnerEllipseCache, optional
        Condition (c) of the candidates' closed loop, shared with their checks (candidates
        that differ only in ``V``): the bound then counts the ellipse (c) proves (or assumes)
        at each radius, computed once, instead of every ellipse it may prove.
    """

    volume: float
    box: np.ndarray
    n: int
    label: str
    ellipses: InnerEllipseCache | None = None
    #: the last :func:`inner_ellipse_bound` computed, with the system, controller and
    #: radius it is of (a CEGIS iterate asks :meth:`cannot_beat` and :meth:`least_level`
    #: about the same closed loop)
    _memo: list = field(default_factory=list, init=False, repr=False, compare=False)

    def bound(self, problem: RoaProblem, level: float) -> float:
        """An upper bound of the grid volume of a certificate of ``problem`` at any level up to
        ``level``: the grid points of ``{x ∈ D: V(x) ≤ level}`` and of every ellipse that
        condition (c) may prove (:func:`nlyap_opt.certification.roa.inner_ellipse_bound`;
        with learned dynamics too where the system has a model: (c) is then proved on the
        true closed loop, as with the true f). ``inf`` where no such bound is available
        (learned dynamics without a model, whose (c) comes from the samples or is assumed;
        a linearisation that is not Hurwitz or has a centre). With :attr:`ellipses`: the
        grid points of the ellipse of (c) at the problem's radius, as its checks use it
        (any dynamics)."""
        pts, shape = grid_points(np.asarray(self.box, dtype=float), self.n)
        ell = self._ellipse(problem, pts)
        if ell is None:
            return math.inf
        m = problem.domain.contains(pts) & (problem.V_numpy(pts) <= level * (1 + 1e-9))
        return grid_area((m | ell).reshape(shape), self.box)

    def _ellipse(self, problem: RoaProblem, pts: np.ndarray) -> np.ndarray | None:
        """The grid points :meth:`bound` counts for condition (c), or ``None`` (no bound)."""
        if self.ellipses is not None:
            res, _ = self.ellipses.get(problem)
            Pe = np.asarray(res["P"], dtype=float)
            return np.einsum("ij,jk,ik->i", pts, Pe, pts) <= float(res["level"]) * (1 + 1e-9)
        if not problem.known and not getattr(problem.system, "has_model", False):
            return None
        for system, controller, inner, n, ell in self._memo:
            if system is problem.system and controller is problem.controller \
                    and inner == problem.inner and n == len(pts):
                return ell
        ell = inner_ellipse_bound(problem.system, problem.controller, problem.inner, pts)
        self._memo[:] = [(problem.system, problem.controller, problem.inner, len(pts), ell)]
        return ell

    def least_level(self, problem: RoaProblem) -> float:
        """A level below which no level of ``problem`` can win: :meth:`bound` is below
        :attr:`volume` at every level under it (one grid point of slack). ``0.0`` where no
        such level is known, ``inf`` where no level can win. A level search stops there
        (:func:`nlyap_opt.certification.roa.certify_level`'s ``least``): a skip of work,
        never a claim."""
        pts, _ = grid_points(np.asarray(self.box, dtype=float), self.n)
        ell = self._ellipse(problem, pts)
        if ell is None:
            return 0.0
        box = np.asarray(self.box, dtype=float)
        cells = float(np.prod((box[:, 1] - box[:, 0]) / self.n))
        need = self.volume / cells - int(ell.sum())     # grid points still to be counted
        k = math.ceil(need) - 1                          # one point of slack
        if k <= 0:
            return 0.0
        inside = problem.domain.contains(pts) & ~ell
        v = np.sort(problem.V_numpy(pts[inside]))
        if k > v.size:
            return math.inf
        # at this level V ≤ level·(1 + 1e-9) holds at fewer than k of the points: the bound
        # is below the volume here and at every lower level
        return float(v[k - 1]) / (1 + 1e-9) * (1 - 1e-9)

    def cannot_beat(self, problem: RoaProblem, level: float) -> str:
        """Why a certificate of ``problem`` at a level up to ``level`` cannot win (its
        :meth:`bound` is below :attr:`volume`; a tie wins for the other candidate), or
        ``""``."""
        b = self.bound(problem, level)
        if b < self.volume:
            return (f"{CANNOT_BEAT} the {self.label}: volume bound {b:.4g} below its certified "
                    f"{self.volume:.4g}")
        return ""


def _below_inner_ball(tried: list, log, eps: float, lv: float, m: float,
                      least: float) -> bool:
    """Whether the candidate level ``lv`` is at most ``least`` (the inner ball's level
    ``m``, with or without a margin): the radius is then skipped, recorded in ``tried``."""
    if lv > least:
        return False
    tried.append({"inner": eps, "status": f"candidate level {lv:.4g} below the inner "
                  f"ball's level {m:.4g}"})
    log(f"inner radius {eps:g}: candidate level {lv:.4g} lies below the inner ball's level "
        f"{m:.4g}; skipped")
    return True


def certify_candidate(problem: RoaProblem, policy: LevelPolicy = NEURAL_POLICY, *,
                      level: float | None = None, cap: float | None = None,
                      ellipses: InnerEllipseCache | None = None,
                      beat: VolumeToBeat | None = None, log=print) -> RoaCertificate:
    r"""Certify ``problem.V`` by ``policy``: conditions (a), (b), (c) by :func:`certify_roa`.

    The inner radius is a trade-off the user should not have to tune: a small ε makes
    condition (c) easy (a small ellipse around the origin) but the decrease (a) must then hold
    close to the origin, where a robust margin :math:`\eta\|\nabla V\|` (learned f) can beat it;
    a large ε the other way round. The same ``V`` and ``κ`` are checked with ``ε·f`` for
    each of the policy's factors (no retraining); the first radius that certifies wins.

    Parameters
    ----------
    problem : RoaProblem
        The candidate ``V`` on the run's problem; ``ε = policy.inner_fraction·problem.inner``.
    policy : LevelPolicy
    level : float, optional
        A claimed level: checked exactly at the first radius (a re-verification), searched
        from at the others. Without it each radius gets its own candidate level.
    cap : float, optional
        An upper bound of the candidate level (a candidate's own level, e.g. an SOS
        program's); ignored with ``level``.
    ellipses : InnerEllipseCache, optional
        Condition (c) shared with the other candidates of the same closed loop.
    beat : VolumeToBeat, optional
        A radius whose certificate cannot exceed this volume (its
        :meth:`VolumeToBeat.bound` at the level it would check or search from) is not
        checked; the history lists it as skipped, with the reason.
    log : callable

    Returns
    -------
    RoaCertificate
        The first radius's certificate that certifies, else the first radius's refusal;
        ``CERTIFIED`` only when every condition was verified by the interval verifier.

    Raises
    ------
    ConfigError
        When no radius of the policy lies inside the domain.
    """

    base = problem.inner * policy.inner_fraction
    if policy.inner_fraction != 1.0:
        problem = replace(problem, inner=base)
    try:  # the decrease condition does not depend on ε: built once, shared
        dec = problem.decrease()
    except InputRangeError:
        return certify_roa(problem, 1.0 if level is None else level, log=log)
    record = len(policy.factors) > 1
    first, tried = None, []
    refuted = []    # counterexamples of the radii tried so far
    for f in policy.factors:
        eps = base * f
        if not 0 < eps < problem.domain.inradius():
            continue
        p = problem if f == 1.0 else replace(problem, inner=eps)
        p._decrease = dec
        lv = level
        if lv is None:
            lv = candidate_level(dec.x, dec.V, dec.lie, inner=eps, domain=p.domain,
                                 margin=dec.margin).level
            if cap is not None:
                lv = min(lv, cap)
        if not lv > 0:
            tried.append({"inner": eps, "status": "no positive candidate level"})
            continue
        why, below = _refuted_radius(problem, dec, eps, refuted)
        if why:
            tried.append({"inner": eps, "status": "skipped", "reason": why})
            log(f"inner radius {eps:g}: not verified, {why}")
            continue
        if below < lv and (level is None or f != 1.0):   # start below the refuted levels
            lv = below * (1.0 - 1e-3)
        smallest = policy.smallest_level and level is None
        m = inner_ball_level(dec.x, dec.V, eps) if smallest else 0.0
        # no level up to the candidate's holds the ball: nothing to search down from it
        if smallest and _below_inner_ball(tried, log, eps, lv, m, m):
            continue
        if smallest and policy.whole_sets:
            why = "" if beat is None else beat.cannot_beat(p, lv)
            whole = None if why else certify_roa(
                p, lv, search=True, follow_violations=policy.follow_violations,
                ellipses=ellipses, taylor_only=True, log=log)
            if whole is not None and whole.certified:
                tried.append({"inner": eps, "status": whole.status.value,
                              "reason": whole.reason, "level": whole.level})
                if record:
                    whole.history = list(whole.history) + [{"inner_radius_search": tried}]
                return whole
        if smallest:    # the smallest level checked holds the ball with a margin
            if _below_inner_ball(tried, log, eps, lv, m, m * (1.0 + INNER_LEVEL_MARGIN)):
                continue
            lv = m * (1.0 + INNER_LEVEL_MARGIN)
        why = "" if beat is None else beat.cannot_beat(p, lv)
        if why:
            tried.append({"inner": eps, "status": "skipped", "reason": why})
            log(f"inner radius {eps:g}: not verified, {why}")
            continue
        search = (f != 1.0 or level is None) and not smallest
        least = beat.least_level(p) if beat is not None and search else 0.0
        cert = certify_roa(p, lv, search=search, follow_violations=policy.follow_violations,
                           ellipses=ellipses, log=log,
                           least=(least, beat.label) if least > 0 else None)
        if len(cert.counterexamples):
            refuted.append(np.asarray(cert.counterexamples, dtype=float).reshape(
                -1, problem.system.nx))
        tried.append({"inner": eps, "status": cert.status.value, "reason": cert.reason,
                      "level": cert.level})
        first = first or cert
        if least > 0 and not cert.certified and BELOW_LEAST in cert.reason:
            # its levels that could still win failed: the other radii are not tried, as
            # when a level that cannot win is certified here
            log(f"inner radius {eps:g}: no level that could beat the {beat.label} holds; "
                "the other radii are not tried")
            break
        if cert.certified:
            if f != 1.0:
                log(f"inner radius {base:g} refused; certified with ε = {eps:g}")
                cert.assumptions.append(
                    f"inner radius ε = {eps:g} chosen by the tool (configured "
                    f"{base:g}: {tried[0].get('reason', tried[0]['status'])})")
            if record:
                cert.history = list(cert.history) + [{"inner_radius_search": tried}]
            return cert
    if first is None and not tried:
        raise ConfigError(f"no inner radius to try inside the domain "
                          f"{problem.domain.describe()}")
    if first is None:       # every radius skipped before any check: a refusal, not an error
        first = RoaCertificate(CertStatus.NOT_CERTIFIED, _unchecked_reason(tried, beat),
                               level=0.0, assumptions=[], **_identity(problem))
    if record:
        first.history = list(first.history) + [{"inner_radius_search": tried}]
    return first


def unchecked(status: str, reason: str | None) -> bool:
    """Whether a candidate with this ``status`` and ``reason`` was never verified because no
    certificate of it could beat a certified one (its reason starts with
    :data:`NOT_CHECKED`): nothing about it was found false."""
    return status != CertStatus.CERTIFIED and str(reason or "").startswith(NOT_CHECKED)


def _unchecked_reason(tried: list, beat: VolumeToBeat | None) -> str:
    """Why :func:`certify_with_inner_search` checked no radius (each entry of ``tried`` was
    skipped). Where every radius was skipped because no certificate of it could beat
    ``beat``, the reason starts with :data:`NOT_CHECKED`: nothing was found false, the
    candidate was only not worth verifying."""
    if beat is not None and all(t["status"] == "skipped"
                                and t.get("reason", "").startswith(CANNOT_BEAT)
                                for t in tried):
        radii = ", ".join(f"{t['inner']:g}" for t in tried)
        first = tried[0]["reason"].split(": ", 1)[-1]
        return (f"{NOT_CHECKED}: at each inner radius tried (ε = {radii}) no certificate of "
                f"it can beat the {beat.label} (at ε = {tried[0]['inner']:g}: {first})")
    return "no inner radius left to check: " + "; ".join(
        f"ε = {t['inner']:g}: {t['status']}"
        + (f" ({t['reason']})" if t["status"] == "skipped" else "") for t in tried)


def _refuted_radius(problem: RoaProblem, dec, eps: float, refuted: list
                    ) -> tuple[str, float]:
    """``(why, below)``: why no level can certify ``V`` at inner radius ``eps`` (``""``: one
    may), and the least ``V`` of the counterexamples that refute levels there (``inf``:
    none), below which a search at ``eps`` starts.

    A counterexample ``x`` of an earlier radius (of the decrease, or of containment on
    ``∂D``) refutes every level ``c ≥ V(x)`` at every radius ``ε ≤ ‖x‖``: the property it
    violates is the same there. A certificate at ``eps`` needs a level above the inner
    ball's (the largest ``V`` on ``‖x‖ = eps``), so when a counterexample with ``‖x‖ ≥ eps``
    has ``V`` at or below that, the radius cannot certify and is not searched (a skip of
    work, never a claim)."""
    if not refuted:
        return "", math.inf
    pts = np.vstack(refuted)
    far = np.linalg.norm(pts, axis=1) >= eps
    if not far.any():
        return "", math.inf
    vmin = float(np.min(problem.V_numpy(pts[far])))
    m = inner_ball_level(dec.x, dec.V, eps)
    if vmin > m * (1.0 + INNER_LEVEL_MARGIN):
        return "", vmin
    return (f"a counterexample of another radius (V = {vmin:.4g}, outside ‖x‖ = {eps:g}) "
            f"refutes every level that holds the inner ball (V > {m:.4g})"), vmin


def certify_with_inner_search(problem: RoaProblem, level: float | None, *,
                              factors=INNER_FACTORS, follow_violations: bool = False,
                              smallest_level: bool = False, beat: VolumeToBeat | None = None,
                              log=print) -> RoaCertificate:
    """:func:`certify_candidate` with the policy of these arguments at the problem's ε."""
    policy = LevelPolicy(1.0, tuple(factors), smallest_level, follow_violations)
    return certify_candidate(problem, policy, level=level, beat=beat, log=log)


def read_certificate_file(path: str | Path) -> tuple[Path, object]:
    """``(the certificate.json path, its parsed JSON)`` of a run directory or a certificate
    file; a missing, unreadable or non-JSON file raises :class:`ConfigError` naming it and
    the fix (the content is checked by the caller)."""
    path = Path(path)
    if path.is_dir():
        path = path / "certificate.json"
    try:
        d = json.loads(read_file_bytes(path, "certificate").decode("utf-8"))
    except OSError as err:
        raise ConfigError(f"cannot read certificate {path}: {err.strerror or err}; pass the "
                          "certificate.json of a finished run") from None
    except UnicodeDecodeError:
        raise ConfigError(f"certificate {path} is not UTF-8 text; pass the certificate.json "
                          "of a finished run") from None
    except RecursionError:
        raise ConfigError(f"certificate {path} is nested too deeply to read; rerun the "
                          "command that wrote it") from None
    except json.JSONDecodeError as err:
        raise ConfigError(f"certificate {path} is not valid JSON ({err.msg}, line "
                          f"{err.lineno}); rerun the command that wrote it") from None
    except ValueError as err:  # an integer of thousands of digits (Python's own limit)
        raise ConfigError(f"certificate {path} cannot be read ({' '.join(str(err).split())[:120]});"
                          " rerun the command that wrote it") from None
    return path, d


def recheck_certificate(path: str | Path, *, system=None, allow_factory: bool = False,
                        log=print) -> RoaCertificate:
    """Re-verify a saved ``certificate.json`` from its hashed artifacts, as written.

    Parameters
    ----------
    path : str or Path
        The certificate file or the directory holding ``certificate.json``.
    system : systems.System, str or Path, optional
        The system to re-check against: a :class:`~systems.System`, a catalogue name or a
        spec file (TOML). Default: the catalogue system the certificate names, else the
        spec file it names, read as TOML only (one with a ``factory`` is refused).
    allow_factory : bool
        Run the ``factory`` (Python code) of the spec file given as ``system``. Without it
        such a file is refused before anything is imported.
    log : callable

    Returns
    -------
    RoaCertificate
        ``CERTIFIED`` only when every artifact matches its sha256, the system is the
        certified one (:func:`system_binding`: ``"not the certified system: … differs"``
        otherwise; a certificate without the binding is refused with how to rerun), the
        conditions verify again at the saved level with the saved inner ellipse (no
        search), and every stored number is what the re-check proves (the field named
        otherwise).

    Raises
    ------
    ConfigError
        A file that is not a certificate, a system that cannot be found, a factory not
        allowed.
    """
    return recheck_run(path, system=system, allow_factory=allow_factory, log=log)[0]


def recheck_run(path: str | Path, *, system=None, allow_factory: bool = False,
                log=print) -> tuple[RoaCertificate, RoaProblem | None]:
    """:func:`recheck_certificate`, and the problem rebuilt from the hashed artifacts.

    The one loader of a finished run for its users (simulation, code export, the safety
    filter): the problem (``V``, ``κ``, ``φ``, the system, the domain) is ``None`` when an
    artifact is missing, changed or unreadable (the certificate then says why it is not
    ``CERTIFIED``); a returned certificate is ``CERTIFIED`` only when every condition was
    proved again at the saved level. ``system`` and ``allow_factory`` as in
    :func:`recheck_certificate`.
    """

    if not isinstance(path, (str, os.PathLike)):
        raise ConfigError(f"path must be a certificate.json file or its directory (a str or "
                          f"Path), got {type(path).__name__} {str(path)[:40]!r}")
    path, d = read_certificate_file(path)
    saved = RoaCertificate.from_dict(d)
    problem_d = d.get("problem")
    if not isinstance(problem_d, dict):
        raise ConfigError(f"certificate {path} holds no 'problem' section; rerun the command "
                          "that wrote it")
    sysm = _recheck_system(saved, d, path, system, allow_factory)
    base = path.parent
    nets: dict[str, object] = {}
    bounded = None          # (file, sha256 of the φ it bounds) of the bounds artifact
    for role, art in saved.artifacts.items():
        name = art.get("file") if isinstance(art, dict) else None
        if not isinstance(name, str) or not isinstance(art.get("sha256"), str) or \
                name in ("", ".", "..") or Path(name).name != name or "\\" in name:
            return _refused_run(saved, f"artifact entry {role!r} must name a file beside "
                                "certificate.json (no directory part) and its sha256")
        f = base / name
        if not f.exists():
            return _refused_run(saved, f"artifact {art['file']} ({role}) is missing")
        try:   # read once: what is hashed is what is parsed
            data = read_file_bytes(f, "file", MAX_ARTIFACT_BYTES)
        except (ConfigError, OSError) as err:
            return _refused_run(saved, f"artifact {art['file']} ({role}) cannot be read: "
                                f"{err}")
        digest = hashlib.sha256(data).hexdigest()
        if digest != art["sha256"]:
            return _refused_run(saved, f"artifact {art['file']} ({role}) changed since the "
                            f"certificate was written (sha256 {digest[:12]}… ≠ "
                            f"{art['sha256'][:12]}…)")
        if art.get("kind") == "bounds":
            try:
                eta, box, phi_sha = parse_bound(data)
                bounded = (art["file"], phi_sha)
            except (ValueError, KeyError, TypeError, RecursionError, OverflowError) as err:
                return _refused_run(saved, f"artifact {art['file']} cannot be read: "
                                    f"{' '.join(str(err).split())[:200]}")
            if eta != saved.eta:
                return _refused_run(saved, f"the certificate's η = {saved.eta!r} is not the η = "
                                f"{eta!r} of {art['file']}")
            dbox = np.asarray(problem_d.get("dynamics_box") or [], dtype=float)
            if dbox.size == 0 or box.shape[0] < dbox.shape[0] or \
                    not np.array_equal(box[:dbox.shape[0]], dbox):
                return _refused_run(saved, f"the certificate's dynamics box {dbox.tolist()} is "
                                f"not the box of {art['file']}")
            # U of the bound: the file's input rows, or for a control-affine φ (no input
            # rows) the system's U
            ubox = np.asarray(problem_d.get("input_box") or [], dtype=float)
            want = box[dbox.shape[0]:] if box.shape[0] > dbox.shape[0] else \
                np.asarray(sysm.input_box if sysm.nu else [], dtype=float).reshape(-1, 2)
            if want.size and (ubox.shape != want.shape or not np.array_equal(ubox, want)):
                return _refused_run(saved, f"the certificate's input box {ubox.tolist()} is "
                                f"not the input box {want.tolist()} of the bound in "
                                f"{art['file']}")
            continue
        try:
            nets[role] = load_artifact(f, art.get("kind", "network"), data)
        except (NetworkFileError, RuntimeError, ValueError) as err:
            return _refused_run(saved, f"artifact {art['file']} ({role}) cannot be read: {err}")
    if "V" not in nets:
        raise ConfigError(f"certificate {path} lists no V artifact; rerun the command")
    refusal = _missing_pieces(saved, nets, bounded, sysm)
    if refusal:
        return _refused_run(saved, refusal)
    if getattr(nets["V"], "n_in", sysm.nx) != sysm.nx:
        return _refused_run(saved, f"V ({saved.artifacts['V']['file']}) takes "
                            f"{nets['V'].n_in} states, the system has {sysm.nx}")
    dyn_assumed = problem_d.get("dynamics_assumptions", [])
    if not isinstance(dyn_assumed, list) or not all(isinstance(a, str) for a in dyn_assumed):
        raise ConfigError(f"certificate {path}: problem.dynamics_assumptions must be a list of "
                          "strings; rerun the command that wrote it")
    refusal = _binding_refusal(d, sysm)
    if refusal:
        return _refused_run(saved, refusal)
    options = check_file_options(problem_d.get("verify_options"), f"certificate {path}",
                                 "rerun the command that wrote it")
    try:
        problem = RoaProblem(
            sysm, nets["V"], nets.get("controller"), nets.get("dynamics"),
            inner=saved.inner, outer=saved.outer, eta=saved.eta, domain=saved.domain,
            initial_set=saved.initial_set,
            margin_mode=problem_d.get("margin_mode", "pointwise"), smoothing=saved.smoothing,
            dynamics_box=problem_d.get("dynamics_box"), input_box=problem_d.get("input_box"),
            dynamics_assumptions=list(dyn_assumed), verify_options=options)
    except (ConfigError, DimensionError) as err:   # the Python API's words: the file's here
        raise ConfigError(f"certificate {path} does not state a problem this tool can "
                          f"re-check ({str(err).split(';')[0]}); an edited certificate.json? "
                          "rerun the command that wrote it") from None
    refusal = bound_refutation(problem)
    if refusal:
        return _refused_run(saved, refusal)
    if not math.isfinite(saved.level):
        raise ConfigError(f"certificate {path}: its level is {saved.level!r}, not a finite "
                          "number; an edited certificate.json? rerun the command that wrote it")
    if saved.status is not CertStatus.CERTIFIED or saved.level <= 0:
        return _refused_run(saved, f"the certificate does not claim a level ({saved.status.value}: "
                        f"{saved.reason})")
    # (c) is always proved again: the saved ellipse when there is one, else a new one (a
    # certificate.json without its ellipse is never re-checked as (a) and (b) alone)
    new = certify_roa(problem, saved.level, search=False, check_inner_ellipse=True,
                      inner_ellipse=saved.inner_ellipse, log=log)
    new.artifacts = saved.artifacts
    if new.certified:
        wrong = _not_as_proved(saved, new)
        if wrong:
            return _refused_run(new, "the certificate states " + "; ".join(wrong)
                            + ": not what the re-check proves (an edited certificate.json?); "
                            "rerun the command that wrote it")
    return new, problem


def _recheck_system(saved: RoaCertificate, d: dict, path: Path, system, allow_factory: bool):
    """The system a re-check runs against (module docstring of :func:`recheck_certificate`):
    nothing named inside the certificate is executed."""

    if isinstance(system, System):
        return system
    if system is not None:
        if not isinstance(system, (str, Path)):
            raise ConfigError(f"system must be a systems.System, a catalogue name or a spec "
                              f"file, got {type(system).__name__}")
        if isinstance(system, str) and system in systems.names() and not Path(system).is_file():
            return systems.get(system)
        p = Path(system)
        if not p.is_file():
            raise ConfigError(f"system {str(system)!r} is neither a registered system nor a "
                              "spec file; pass a catalogue name (see 'nlyap systems') or the "
                              "TOML file")
        factory = spec_factory(p)
        if factory is not None and not allow_factory:
            raise ConfigError(
                f"system file {p} defines its system with factory = {factory!r}, Python code "
                "that runs only when asked; read it, then pass --system FILE.toml "
                "--allow-factory (Python: allow_factory=True)")
        return systems.load_spec(p, allow_factory=allow_factory)
    if saved.system in systems.CATALOGUE:
        return systems.get(saved.system)
    src = d.get("system_source")
    if src:
        src = Path(str(src))
        if not src.is_file():
            what = "is not a regular file (a directory, pipe or device)" if src.exists() \
                else "does not exist"
            raise ConfigError(f"certificate {path} is about system {saved.system!r} from "
                              f"{src}, which {what}; restore the spec file or pass "
                              "--system FILE.toml")
        factory = spec_factory(src)
        if factory is not None:
            # code named inside a certificate directory is never run on its own
            raise ConfigError(
                f"certificate {path} names the system file {src}, whose factory "
                f"{factory!r} is Python code; a re-check never runs code named inside a "
                "certificate: read the factory, then pass --system FILE.toml --allow-factory "
                "(Python: system=FILE.toml, allow_factory=True)")
        # expressions or samples: parsed, not executed
        return systems.load_spec(src, allow_factory=False)
    if saved.system in systems.names():     # registered in this process by its own code
        return systems.get(saved.system)
    raise ConfigError(f"certificate {path} is about system {saved.system!r}, which is not in "
                      "the catalogue and names no spec file; pass --system NAME or "
                      "--system FILE.toml")


def bound_system(d: dict, path: str | Path, system=None,
                 allow_factory: bool = False) -> tuple[object, str]:
    """``(system, refusal)`` for re-checking the certificate dict ``d`` read from ``path``.

    The system is found as in :func:`recheck_certificate` (nothing named inside the
    certificate is executed); ``refusal`` is ``""`` when it is the system the certificate
    binds (:func:`system_binding`), else why not. Used by other certificate kinds
    (:mod:`nlyap_opt.certification.compositional`).
    """
    sysm = _recheck_system(SimpleNamespace(system=str(d.get("system"))), d, Path(path),
                           system, allow_factory)
    return sysm, _binding_refusal(d, sysm)


def _binding_refusal(d: dict, system) -> str:
    """Why ``system`` is not the one the certificate binds (``""``: it is)."""
    bound = d.get("system_binding")
    if not isinstance(bound, dict) or not isinstance(bound.get("sha256"), str):
        return ("the certificate does not record the system it was made for (no "
                "system_binding: written by an older nlyap); rerun the command that wrote it "
                "to certify again")
    now = system_binding(system)
    if now["sha256"] == bound["sha256"]:
        return ""
    was = bound.get("parts") if isinstance(bound.get("parts"), dict) else {}
    differ = [k for k, v in now["parts"].items() if was.get(k) != v] or ["its hash"]
    return (f"not the certified system: {', '.join(differ)} "
            f"{'differs' if len(differ) == 1 else 'differ'} from the system the certificate "
            f"was made for (sha256 {now['sha256'][:12]}… ≠ {bound['sha256'][:12]}…); "
            "re-check against the certified system or certify this one")


#: relative tolerance of the numbers a re-check derives again (M, β, the inner ellipse's box):
#: the same computation on another machine may differ in the last bits
DERIVED_RTOL = 1e-9


def _close(a, b, rtol: float = DERIVED_RTOL) -> bool:
    if a is None or b is None:
        return a is b
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return a.shape == b.shape and bool(np.all(np.isfinite(a)) and np.all(
        np.abs(a - b) <= rtol * np.maximum(np.abs(a), np.abs(b))))


def _not_as_proved(saved: RoaCertificate, new: RoaCertificate) -> list[str]:
    """The stored fields of ``saved`` that are not what ``new`` (its re-check) proved.

    The level, the radii, η, s, the domain and the inner ellipse's ``P`` and form are used
    as written by the re-check, so they must equal the proved ones exactly; the derived
    numbers (``M``, the margin β, the box around ``E``) to :data:`DERIVED_RTOL`; the inner
    ellipse's level ``c_q`` may not exceed the proved one (a larger ``E`` is not proved);
    every assumption the re-check's proof rests on must be listed (more may be)."""
    out = []

    def field(name, stored, proved, ok):
        if not ok:
            out.append(f"{name} = {stored!r}, the re-check proves {proved!r}")

    for name, a, b in (("level", saved.level, new.level),
                       ("inner_radius", saved.inner, new.inner),
                       ("outer_radius", saved.outer, new.outer), ("eta", saved.eta, new.eta),
                       ("norm_smoothing", saved.smoothing, new.smoothing),
                       ("setting", saved.setting, new.setting),
                       ("margin_mode", saved.margin_mode, new.margin_mode)):
        field(name, a, b, a == b)
    field("margin", saved.margin, new.margin, _close(saved.margin, new.margin))
    field("M", saved.M, new.M, _close(saved.M, new.M))
    field("assumptions_declared_by_user", saved.declared, new.declared,
          list(saved.declared) == list(new.declared))
    missing = [a for a in new.assumptions if a not in saved.assumptions]
    field("assumptions", "a list without " + "; ".join(missing) if missing else "",
          "the proof rests on them", not missing)
    si, ni = saved.inner_ellipse, new.inner_ellipse
    if (si is None) != (ni is None):
        field("inner_ellipse", None if si is None else "an ellipse",
              None if ni is None else "an ellipse", False)
    elif si is not None:
        field("inner_ellipse.P", np.asarray(si.P).tolist(), np.asarray(ni.P).tolist(),
              np.array_equal(si.P, ni.P))
        for name in ("status", "form", "proved"):
            field(f"inner_ellipse.{name}", getattr(si, name), getattr(ni, name),
                  getattr(si, name) == getattr(ni, name))
        field("inner_ellipse.level", si.level, ni.level,
              si.level <= ni.level and _close(si.level, ni.level, 1e-12))
        field("inner_ellipse.box_half_widths", np.asarray(si.half_widths).tolist(),
              np.asarray(ni.half_widths).tolist(), _close(si.half_widths, ni.half_widths))
    # what the proof says of itself: the same words as the re-check's, and no stored check
    # that did not hold beside a certified status
    field("reason", saved.reason, new.reason, saved.reason == new.reason)
    # its words hold β to 6 digits: with the stored β (itself within DERIVED_RTOL of the
    # proved one), the text may show the stored digits
    said = {new.decrease_condition, new.decrease_condition.replace(
        f"= {new.margin:.6g} (rounded up)", f"= {saved.margin:.6g} (rounded up)")}
    field("decrease_condition", saved.decrease_condition, new.decrease_condition,
          saved.decrease_condition in said)
    saved_checks = saved.checks if isinstance(saved.checks, dict) else {}
    for name, verdict in saved_checks.items():
        proved = new.checks.get(name)
        ok = verdict == proved if proved is not None else verdict in ("verified", "certified")
        field(f"checks[{name!r}]", verdict, proved, ok)
    return out


class _CasadiV:
    """A V saved as a CasADi Function (quadratic or SOS baselines)."""

    def __init__(self, fn: ca.Function):
        self.fn = fn

    @property
    def n_in(self) -> int:
        return int(self.fn.nnz_in(0))

    @property
    def n_out(self) -> int:
        return int(self.fn.nnz_out(0))

    def casadi(self, x):
        return self.fn(x)

    def numpy(self, pts):
        return evaluate(self.fn, [np.asarray(pts, dtype=float)])[0]


def load_artifact(path, kind: str = "network", data: bytes | None = None):
    """A saved V, κ or φ of ``certificate.json``'s ``artifacts``: a network file (``kind``
    ``"network"``: :class:`~nlyap_opt.kernel.network.Network`), or the scalar graph of a V
    that is not a network (``"sx"``: an SOS polynomial, :mod:`nlyap_opt.kernel.sxjson`),
    with ``casadi(x)`` and ``numpy(points) -> (N, 1)``. The caller checks the file's
    sha256 first, and passes the bytes it hashed as ``data`` so that what is loaded is
    what was hashed (the file is not read a second time).

    Both are data read by this package's own code. A CasADi serialised Function (``kind``
    ``"casadi"``, written by earlier versions) is refused: loading one can open a shared
    library or start a compiler that the file names, so it would run code from disk."""
    if kind == "network":
        return Network.load(path, data)
    if kind == "sx":
        if data is not None and len(data) > sxjson.MAX_BYTES:
            raise ValueError(f"larger than {sxjson.MAX_BYTES} bytes")
        try:
            d = json.loads(read_file_bytes(path, "artifact", sxjson.MAX_BYTES)
                           if data is None else data)
        except (ValueError, RecursionError) as err:   # not UTF-8, not JSON, huge integers
            raise ValueError(f"not a JSON file ({type(err).__name__})") from None
        try:
            return _CasadiV(sxjson.from_json(d))
        except ConfigError as err:
            raise ValueError(str(err)) from None
    if kind == "casadi":
        raise ValueError("a CasADi serialised Function is not loaded (loading one can run "
                         "code named inside the file); rerun the command that wrote the "
                         "certificate with this version, which saves V as data")
    raise ValueError(f"unknown artifact kind {kind!r} (network or sx)")


def parse_bound(data: bytes) -> tuple[float, np.ndarray, str | None]:
    """η, the ``(n, 2)`` box and the sha256 of the network φ it bounds (``None``: not
    recorded) of a ``bounds.json``'s bytes; ``ValueError`` (or ``KeyError``,
    ``TypeError``) names what is wrong."""
    b = json.loads(data)
    if not isinstance(b, dict) or not isinstance(b.get("grid"), dict):
        raise ValueError("a bounds file is a JSON object with 'eta' and 'grid': {'box': ...}")
    net = b.get("network")
    phi = net.get("sha256") if isinstance(net, dict) else None
    eta = _number(b, "eta")
    if not np.isfinite(eta) or eta < 0:
        raise ValueError(f"eta must be a finite number ≥ 0, got {eta!r}")
    rows = b["grid"].get("box")
    if not isinstance(rows, list) or not all(
            isinstance(r, list) and len(r) == 2 and
            all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in r)
            for r in rows):
        raise ValueError("grid.box must be a list of [low, high] number pairs")
    try:
        box = np.array(rows, dtype=float).reshape(-1, 2)
    except OverflowError:           # an integer beyond float range
        box = None
    if box is None or not np.all(np.isfinite(box)):
        raise ValueError("grid.box holds a number beyond float range")
    return eta, box, phi if isinstance(phi, str) else None


def _missing_pieces(saved: RoaCertificate, nets: dict, bounded: tuple | None,
                    sysm) -> str:
    """Why a certificate's artifacts cannot carry its claim (``""``: they can): a system
    with inputs needs its controller κ; learned dynamics φ need the hashed bound on
    ``‖f − φ‖``, and that bound must be the one computed for this very φ (``bounds.json``
    records the sha256 of the network it bounds)."""
    if sysm.nu and "controller" not in nets:
        return (f"the system {sysm.name} has inputs, but the certificate lists no controller "
                "artifact κ; rerun the command that wrote it")
    if "dynamics" not in nets:
        return ""
    if bounded is None:
        return ("the certificate rests on learned dynamics φ but lists no bound on ‖f − φ‖ "
                "(an artifact of kind 'bounds'); rerun the command that wrote it")
    name, phi_sha = bounded
    if phi_sha is None:
        return (f"{name} does not name the network φ it bounds (its 'network' sha256); "
                "rerun the command that wrote the certificate")
    want = saved.artifacts["dynamics"]["sha256"]
    if phi_sha != want:
        return (f"φ ({saved.artifacts['dynamics']['file']}, sha256 {want[:12]}…) is not the "
                f"network that {name} bounds (sha256 {phi_sha[:12]}…)")
    return ""


#: seeded points of the bound's box at which a re-check compares f and φ (a falsifier of
#: ‖f − φ‖ ≤ η: it refutes a wrong bound, it proves nothing)
BOUND_SPOT_CHECKS = 4096


def bound_refutation(problem: RoaProblem) -> str:
    """Why ``‖f − φ‖ ≤ η`` is false, or ``""``: ``f`` and ``φ`` compared where ``f`` is
    known (a model or a simulator: :data:`BOUND_SPOT_CHECKS` seeded points of
    ``dynamics_box × input_box``; samples: their nodes in that box).

    A learned-dynamics certificate proves the decrease for ``φ`` with the robust term of η,
    which says nothing about the true ``f`` unless the bound holds; a re-check cannot
    recompute η (that needs the learning run's grid and constants), but a point where
    ``f`` and ``φ`` differ by more than η refutes it: φ learned for another ``f`` (a spec
    edited under the same name), an edited ``bounds.json``. Differences within rounding
    (``10⁻⁹`` relative) are not counted.
    """
    sysm, phi = problem.system, problem.dynamics
    if phi is None or problem.dynamics_box is None:
        return ""
    nx, nu = sysm.nx, sysm.nu
    box = np.vstack([problem.dynamics_box,
                     problem.input_box if nu and problem.input_box is not None
                     else np.zeros((0, 2))])
    if getattr(sysm, "kind", "model") == "samples":
        smp = sysm.samples
        if smp.offset > 0:   # values off the nodes: compared there, they would need a slope
            return ""
        Z = smp.points(np.arange(int(np.prod(smp.counts))))
        F = np.asarray(smp.values, dtype=float)
        keep = np.all((Z >= box[:, 0]) & (Z <= box[:, 1]), axis=1)
        Z, F = Z[keep], F[keep]
    elif getattr(sysm, "can_simulate", True) and box.shape[0] == nx + nu:
        rng = np.random.default_rng(20261129)
        Z = box[:, 0] + (box[:, 1] - box[:, 0]) * rng.random((BOUND_SPOT_CHECKS, nx + nu))
        F = np.asarray(sysm.evaluate(Z[:, :nx], Z[:, nx:]), dtype=float)
    else:
        return ""
    if not len(Z):
        return ""
    x, u = ca.MX.sym("x", nx), ca.MX.sym("u", nu)
    G = evaluate(ca.Function("phi", [x, u], [learned_rhs(sysm, phi, x, u)]),
                 [Z[:, :nx], Z[:, nx:]])[0]
    err = np.linalg.norm(F - np.asarray(G, dtype=float).reshape(F.shape), axis=1)
    tol = 1e-9 * (1.0 + problem.eta + np.max(np.abs(F), axis=1))
    worst = int(np.argmax(err - tol))
    if not err[worst] > problem.eta + tol[worst]:
        return ""
    return (f"the bound ‖f − φ‖ ≤ η = {problem.eta:.6g} the certificate rests on does not hold: "
            f"‖f − φ‖ = {err[worst]:.6g} at (x, u) = {np.round(Z[worst], 6).tolist()} of its "
            "box (φ learned for another f, an edited bounds.json, or a declared input "
            "matrix that f does not have); rerun the run that wrote it")


def _refused_run(saved: RoaCertificate, reason: str) -> tuple[RoaCertificate, None]:
    saved.status, saved.reason = CertStatus.NOT_CERTIFIED, reason
    return saved, None


def problem_to_dict(problem: RoaProblem) -> dict:
    """The parts of a problem that are not artifacts (for ``certificate.json``); the
    verifier options are saved so that a re-check spends the same effort."""
    return {"margin_mode": problem.margin_mode,
            "verify_options": dict(problem.verify_options),
            "dynamics_box": None if problem.dynamics_box is None
            else np.asarray(problem.dynamics_box).tolist(),
            "input_box": None if problem.input_box is None
            else np.asarray(problem.input_box).tolist(),
            "dynamics_assumptions": list(problem.dynamics_assumptions)}


def save_certificate(cert: RoaCertificate, problem: RoaProblem, out: str | Path,
                     extra: dict | None = None, *, name: str = "certificate.json",
                     files: dict | None = None) -> Path:
    """Write the certificate with its artifacts into directory ``out``.

    Networks are saved (``V.json``, ``controller.json``, ``dynamics.json``, or the names
    ``files`` gives per role, e.g. ``{"V": "V_quadratic.json"}``; other ``V`` as the data
    of its scalar graph, ``V.sx.json``) unless a file with that name already holds them, and each is
    recorded with its sha256; so is the bound on ``‖f − φ‖`` of learned dynamics
    (``files["bounds"]``, default ``bounds.json``). ``extra`` (areas, true-f checks,
    timings) is stored beside the certificate's own fields. The file is written atomically.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    arts = {}
    for role, obj in (("V", problem.V), ("controller", problem.controller),
                      ("dynamics", problem.dynamics)):
        if obj is None:
            continue
        if isinstance(obj, Network):
            f = out / (files or {}).get(role, f"{role}.json")
            if not f.exists() or Network.load(f).to_dict() != obj.to_dict():
                obj.save(f)
            arts[role] = {"file": f.name, "sha256": sha256_file(f), "kind": "network"}
        else:
            f = out / f"{role}.sx.json"
            x = ca.SX.sym("x", problem.system.nx)
            write_json_atomic(f, sxjson.to_json(ca.Function("V", [x], [obj.casadi(x)])))
            arts[role] = {"file": f.name, "sha256": sha256_file(f), "kind": "sx"}
    bname = (files or {}).get("bounds", "bounds.json")
    if problem.dynamics is not None and (out / bname).exists():
        # η and its box come from the dynamics stage's bounds.json (or the local bound's
        # file that ``files`` names): hashed, and checked against the certificate's own
        # numbers on re-check
        arts["bounds"] = {"file": bname, "sha256": sha256_file(out / bname),
                          "kind": "bounds"}
    cert.artifacts = arts
    d = cert.to_dict()
    d["problem"] = problem_to_dict(problem)
    source = getattr(problem.system, "source", "") or ""
    binding = system_binding(problem.system)
    if str(source).endswith(".toml"):  # a spec-file system: re-checkable in a new process
        d["system_source"] = str(Path(source).resolve())
        if Path(source).is_file():
            binding["spec_sha256"] = sha256_file(source)
    d["system_binding"] = binding
    d.update(extra or {})
    # what determined the numbers (versions, BLAS kernel, SIMD dispatch, CPU): a re-check
    # elsewhere says so; the verdict itself does not depend on it
    d.setdefault("provenance", fingerprint())
    path = out / name
    write_json_atomic(path, d)
    return path


def write_json_atomic(path: str | Path, data) -> None:
    """Write JSON to ``path`` through a temporary file and a rename (never half-written)."""
    path = Path(path)
    text = json.dumps(data, indent=1, allow_nan=False, default=_jsonable)
    try:
        write_atomic(path, text)   # a directory or a pipe there: a ConfigError naming it
    except OSError as err:
        raise ConfigError(f"cannot write {path}: {err.strerror or err}; remove what is in its "
                          "place or write to another directory") from None


def _jsonable(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, Enum):
        return o.value
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"cannot write {type(o).__name__} to JSON")
