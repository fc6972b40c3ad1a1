r"""Verification problems and results.

A problem asks: on the region :math:`R = \{x \in B : g_i(x) \le 0\ \forall i\}` inside the
root box :math:`B`, do all properties hold strictly, :math:`p_j(x) < 0\ \forall j`?
The falsification formula is :math:`x \in R \wedge \exists j: p_j(x) \ge 0`.

Outcomes (never blurred):

- ``verified``: no point of ``R`` violates a property (rigorous, interval arithmetic with
  outward rounding);
- ``counterexample``: a concrete point, inside ``R`` and violating a property, both
  *confirmed* by rigorous evaluation at that point (or, property ``"domain of OP_..."``,
  a point of ``R`` at which a property is certainly undefined: some operation of its
  graph is applied outside its domain, e.g. ``sqrt`` of a negative number);
- ``unknown``: some boxes narrower than the resolution could be decided neither way.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum

import casadi as ca
import numpy as np

from nlyap_opt.kernel.domain import as_domain
from nlyap_opt.kernel.errors import DimensionError, UnsupportedOperationError
from nlyap_opt.kernel.symbolic import closed_loop, learned_components_of, lie_derivative, robust_lie
from nlyap_opt.kernel.walker import compile_function

__all__ = [
    "VerificationProblem", "VerificationResult", "Counterexample", "lyapunov_problem",
    "closed_loop_problem", "QueryStatus",
]


class QueryStatus(str, Enum):
    """Outcome of one verification query (a ``str``: saved and compared as its word)."""

    VERIFIED = "verified"
    COUNTEREXAMPLE = "counterexample"
    UNKNOWN = "unknown"

    #: hashed as its word, so that a member finds the word's entry of a dict or set
    __hash__ = str.__hash__

    def __str__(self) -> str:
        return self.value


@dataclass
class VerificationProblem:
    """Region constraints ``g_i(x) ≤ 0`` and properties ``p_j(x) < 0`` over a root box.

    Parameters
    ----------
    x : casadi.MX or casadi.SX, shape (n, 1)
        The variables (one symbol).
    box : (n, 2) array_like
        Root box, rows ``(lower, upper)``.
    constraints : sequence of scalar casadi expressions
        Region ``g_i(x) ≤ 0`` (a ball, an annulus, ``V(x) - level``, ...).
    properties : sequence of scalar casadi expressions
        Must hold strictly on the region: ``p_j(x) < 0``.
    constraint_names, property_names : sequence of str, optional

    Notes
    -----
    Builds once the CasADi Functions ``F(x) = (g, p)`` and its Jacobian, which the
    verifier evaluates with interval arithmetic (natural extension intersected with the
    mean-value form). ``checked`` tells whether the graph holds non-smooth or partial
    operations (then ``function_checked`` / ``function_jacobian_checked``, with one output
    per constraint and property, carry the per-box kink/jump and domain checks).

    A constraint or property is defined at a point when every operation it depends on is
    applied inside its domain there (``nlyap_opt.kernel.walker.OP_TABLE``; CasADi's ``if_else``
    evaluates both branches, and a branch that is not taken does not count). The
    properties must be defined on the region; a constraint that is undefined somewhere
    prunes nothing there.
    """

    x: ca.MX
    box: np.ndarray
    constraints: Sequence
    properties: Sequence
    constraint_names: Sequence[str] | None = None
    property_names: Sequence[str] | None = None

    def __post_init__(self):
        self.box = np.asarray(self.box, dtype=float)
        n = self.x.numel()
        if self.box.shape != (n, 2) or np.any(self.box[:, 0] > self.box[:, 1]):
            raise DimensionError(
                f"box must have shape ({n}, 2) with lower <= upper, got {self.box.shape}"
            )
        if not self.properties:
            raise ValueError("a verification problem needs at least one property p(x) < 0")
        exprs = list(self.constraints) + list(self.properties)
        for e in exprs:
            if e.shape != (1, 1):
                raise DimensionError(f"constraints and properties must be scalars, got {e.shape}")
        # a structural zero (CasADi stores no entry for it: ``MX(1, 1)``, the Lie derivative
        # of a zero f) must keep its column: the verifier reads constraints and properties
        # by position in F
        exprs = [ca.densify(e) for e in exprs]
        self.n_constraints = len(self.constraints)
        self.n_properties = len(self.properties)
        self.constraint_names = list(self.constraint_names
                                     or [f"g{i}" for i in range(self.n_constraints)])
        self.property_names = list(self.property_names
                                   or [f"p{j}" for j in range(self.n_properties)])
        F = ca.vertcat(*exprs)
        J = ca.densify(ca.jacobian(F, self.x))
        self.function = ca.Function("F", [self.x], [F])
        self.jacobian = ca.Function("J", [self.x], [J])
        # one pass gives both (shared subexpressions): the verifier's hot path
        self.function_jacobian = ca.Function("FJ", [self.x], [F, J])
        self.constraints = exprs[:self.n_constraints]
        self.properties = exprs[self.n_constraints:]
        self._build_checked(exprs, J)

    def _build_checked(self, exprs, J) -> None:
        """Functions with one output per constraint/property, where the graph needs checks.

        When ``F`` holds a non-smooth or partial operation (``nlyap_opt.kernel.walker.CHECKED_OPS``,
        not made harmless by constant arguments), the interval verifier evaluates
        ``function_checked`` (outputs ``g_0, …, g_{m-1}, p_0, …, p_{k-1}``) and
        ``function_jacobian_checked`` (the same and ``J``) with
        :class:`~verification.interval.CheckedIntervalArithmetic`, which tells per box and
        per output whether a kink/jump may lie inside (no mean-value form) and whether every
        operation is proved inside its domain. ``checked`` is False (and both are ``None``)
        otherwise: the verifier then runs its plain, faster path.
        """
        try:
            self.checked = compile_function(self.function_jacobian).checked
        except UnsupportedOperationError:  # the interval backend reports it when it runs
            self.checked = False
        self.function_checked = self.function_jacobian_checked = None
        if self.checked:
            self.function_checked = ca.Function("F_checked", [self.x], exprs)
            self.function_jacobian_checked = ca.Function("FJ_checked", [self.x], exprs + [J])

    @property
    def n(self) -> int:
        return self.x.numel()

    @property
    def second_order_functions(self) -> tuple[ca.Function, ca.Function]:
        """``(G, H)``: the properties' gradient graph ``G(x)`` (``(k, n)``) and their Hessian
        graphs ``H(x)`` (``k`` outputs, ``(n, n)`` each), for the verifier's second-order
        centred form (option ``second_order``). Built on first use from the property
        expressions and kept (they travel with the pickled problem)."""
        fns = getattr(self, "_second_order", None)
        if fns is None:
            if self.properties is None:  # unpickled before they were built
                raise ValueError("the second-order functions of an unpickled problem must be "
                                 "built before pickling; call second_order_functions first")
            P = ca.vertcat(*self.properties)
            G = ca.densify(ca.jacobian(P, self.x))
            Hs = [ca.densify(ca.jacobian(G[j, :].T, self.x)) for j in range(self.n_properties)]
            fns = (ca.Function("PG", [self.x], [G]), ca.Function("PH", [self.x], Hs))
            self._second_order = fns
        return fns

    def restricted(self, box) -> VerificationProblem:
        """The same problem on a sub-box (used to split work across executors)."""
        return VerificationProblem(self.x, box, self.constraints, self.properties,
                                   self.constraint_names, self.property_names)

    def __getstate__(self):  # casadi Functions serialise; MX expressions are rebuilt
        return {"function": self.function.serialize(), "jacobian": self.jacobian.serialize(),
                "function_jacobian": self.function_jacobian.serialize(),
                "checked": self.checked,
                "function_checked": None if self.function_checked is None
                else self.function_checked.serialize(),
                "function_jacobian_checked": None if self.function_jacobian_checked is None
                else self.function_jacobian_checked.serialize(),
                "box": self.box, "n_constraints": self.n_constraints,
                "n_properties": self.n_properties,
                "constraint_names": self.constraint_names,
                "property_names": self.property_names, "n": self.n,
                "second_order": None if getattr(self, "_second_order", None) is None
                else tuple(f.serialize() for f in self._second_order)}

    def __setstate__(self, st):
        self.function = _deserialize(st["function"])
        self.jacobian = _deserialize(st["jacobian"])
        self.function_jacobian = _deserialize(st["function_jacobian"])
        self.checked = st["checked"]
        self.function_checked = self.function_jacobian_checked = None
        if self.checked:
            self.function_checked = _deserialize(st["function_checked"])
            self.function_jacobian_checked = _deserialize(st["function_jacobian_checked"])
        self.box = st["box"]
        self.n_constraints = st["n_constraints"]
        self.n_properties = st["n_properties"]
        self.constraint_names = st["constraint_names"]
        self.property_names = st["property_names"]
        self.x = ca.MX.sym("x", st["n"])
        so = st.get("second_order")
        self._second_order = None if so is None else tuple(_deserialize(f) for f in so)
        self.constraints = self.properties = None


@functools.lru_cache(maxsize=32)   # a few problems of a few graphs each
def _deserialize(text: str) -> ca.Function:
    """``ca.Function.deserialize``, one Function object per serialised text in a process.

    The walker compiles each Function object once
    (:func:`nlyap_opt.kernel.walker.compile_function`); a worker that receives the same problem in
    many tasks (sub-boxes of one verification, the level steps of a certificate) then compiles its
    graphs once, not once per task.
    """
    return ca.Function.deserialize(text)


@dataclass
class Counterexample:
    """A confirmed violation: ``point`` lies in the region and ``property`` fails there."""

    point: np.ndarray
    property: str
    value_lower: float  # rigorous lower bound of p(point) (>= 0: the property fails)
    value_upper: float

    def to_dict(self) -> dict:
        return {"point": self.point.tolist(), "property": self.property,
                "value": [self.value_lower, self.value_upper]}


@dataclass
class VerificationResult:
    """Outcome of :func:`verification.verify`.

    Attributes
    ----------
    status : QueryStatus
        ``VERIFIED``, ``COUNTEREXAMPLE`` or ``UNKNOWN`` (given as the word or the member)
    counterexample : Counterexample or None
    counterexamples : list of Counterexample   all confirmed ones found (for CEGIS)
    undecided : (k, n, 2) ndarray   boxes at the resolution that stayed undecided
    boxes : int                     boxes processed
    depth : int                     deepest bisection level
    seconds : float
    leaves : list of dict or None   decided leaf boxes with their enclosures (``keep_leaves``)
    open : (k, n, 2) ndarray or None  ``hand_back``: halves still to decide, not evaluated
                                    (the status is then ``unknown`` unless a counterexample
                                    was found)
    partition : dict or None        ``partition``: the bisection tree a verified run decided
                                    (``verification.verify.partition_leaves`` gives its leaves)
    """

    status: QueryStatus
    counterexample: Counterexample | None = None
    counterexamples: list = field(default_factory=list)
    undecided: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 2)))
    boxes: int = 0
    depth: int = 0
    seconds: float = 0.0
    leaves: list | None = None
    backend: str = "interval"
    open: np.ndarray | None = None
    partition: dict | None = None

    def __post_init__(self):
        self.status = QueryStatus(self.status)   # a word that is no status: ValueError

    @property
    def success(self) -> bool:
        return self.status is QueryStatus.VERIFIED

    def to_dict(self) -> dict:
        return {
            "status": self.status,
            "seconds": self.seconds,
            "boxes": self.boxes,
            "depth": self.depth,
            "backend": self.backend,
            "counterexample": None if self.counterexample is None
            else self.counterexample.to_dict(),
            "undecided": int(len(self.undecided)),
        }


def lyapunov_problem(x, V, lie, *, inner: float, outer=None, level: float | None = None,
                     margin: float = 0.0, box=None, check_positive: bool = True,
                     domain=None) -> VerificationProblem:
    r"""The Lyapunov falsification problem on :math:`\{x \in D : \|x\|_2 \ge \varepsilon\}`.

    Properties: :math:`V(x) > 0` (as ``-V < 0``) and
    :math:`\nabla V \cdot g(x) < -\beta` (as ``lie + margin < 0``); region: the domain ``D``
    (``domain``, a :class:`nlyap_opt.kernel.domain.Region`; default the ball ``‖x‖ ≤ outer``) minus
    the open inner ball, intersected with :math:`V(x) \le c` when ``level`` is given.
    """

    n = x.numel()
    if domain is None:
        if outer is None:
            raise ValueError("give the outer radius or a domain")
        domain = as_domain(float(outer), n)
    if not (0 <= inner < domain.inradius()):
        raise ValueError(f"need 0 <= inner < {domain.inradius():g} (the inner ball inside "
                         f"the domain {domain.describe()}), got inner={inner}")
    if margin < 0:
        raise ValueError(f"margin must be >= 0, got {margin}")
    r2 = ca.sumsqr(x)
    region = domain.constraints(x)
    cons = [g for g, _ in region]
    names = [nm for _, nm in region]
    if inner > 0:
        cons.append(inner**2 - r2)
        names.append("inner")
    if level is not None:
        cons.append(V - level)
        names.append("level")
    props, pnames = [], []
    if check_positive:
        props.append(-V)
        pnames.append("V>0")
    props.append(lie + margin if margin else lie)
    pnames.append("decrease")
    box = domain.bounding_box() if box is None else box
    return VerificationProblem(x, box, cons, props, names, pnames)


def closed_loop_problem(system, V, controller=None, dynamics=None, *, inner: float,
                        outer=None, level: float | None = None, margin: float = 0.0,
                        eta: float = 0.0, smoothing: float = 0.0, strict: bool = False,
                        check_positive: bool = True, domain=None) -> VerificationProblem:
    """Lyapunov problem for saved networks: ``V``, ``κ`` and optionally learned ``φ``.

    Parameters
    ----------
    system : systems.System
    V, controller, dynamics : nlyap_opt.kernel.network.Network
        ``dynamics`` (learned φ) replaces the system's ``f`` in the Lie derivative; ``V``
        may also be a :class:`~nlyap_opt.design.polynomial.Polynomial`.
    inner, outer : float      annulus ``inner ≤ ‖x‖₂ ≤ outer``
    domain : Region, optional ``D`` in place of the ball ``‖x‖ ≤ outer``
    level : float, optional   intersect with ``V(x) ≤ level``
    margin : float            β: require ``∇V·g < −β``
    eta : float               pointwise robust margin: require ``∇V·g + η‖∇_L V‖ < −β``
                              (with ``g = φ`` this implies ``∇V·f < −β`` where ``‖f − φ‖ ≤ η``;
                              ``L``: φ's learned components, the others known exactly)
    smoothing : float         ``s``: use ``sqrt(‖∇V‖² + s²)`` for ``‖∇V‖`` (stronger, and
                              cheaper to verify; see :func:`nlyap_opt.kernel.symbolic.robust_lie`)
    strict : bool             raise (True) or warn (False) if 0 is not an equilibrium
    """

    # a network, or a polynomial V (an SOS certificate: nx variables, one value)
    n_in, n_out = getattr(V, "n_in", getattr(V, "nx", None)), getattr(V, "n_out", 1)
    if n_in != system.nx or n_out != 1:
        raise DimensionError(
            f"V must map R^{system.nx} -> R (system {system.name!r}), got "
            f"R^{n_in} -> R^{n_out}"
        )
    cl = closed_loop(system, controller, dynamics, strict=strict)
    Vx = V.casadi(cl.x)
    lie = lie_derivative(Vx, cl.x, cl.rhs)
    if eta:
        comps = None if dynamics is None else learned_components_of(system, dynamics)
        lie = robust_lie(lie, Vx, cl.x, eta, smoothing, comps)
    return lyapunov_problem(cl.x, Vx, lie, inner=inner, outer=outer, level=level,
                            margin=margin, check_positive=check_positive, domain=domain)
