"""The :class:`System`: dynamics ``x' = f(x, u)``, frozen once built.

Three kinds (:attr:`System.kind`):

``"model"``
    a CasADi SX expression ``f(x, u)`` (``System(name, x, u, f, ...)``): everything is
    available, including the true-f checks, ``K_f`` by intervals, the proof of condition (c)
    and the linearisation ``A, B``;
``"callable"``
    a black-box batched function ``f(X, U) -> Xdot`` (:meth:`System.from_callable`): it can
    be sampled and simulated, but there is no model (``has_model`` is False);
``"samples"``
    values on a complete regular grid (:meth:`System.from_samples`, e.g. from a file):
    ``f`` is known at the grid nodes only.

Without a model, ``f``, ``f_fun``, ``A`` and ``B`` raise :class:`ModelUnavailableError`
(never a stand-in); the components of ``f`` that are known exactly (``θ' = ω``) are given as
expressions in the system's symbols (:attr:`System.known_rhs`) for every kind.
"""

from __future__ import annotations

import contextlib
import re
import sys
from collections.abc import Callable, Sequence

import casadi as ca
import numpy as np
from scipy.optimize import least_squares

from nlyap_opt.kernel import deps
from nlyap_opt.kernel.errors import (
    ArgumentTypeError,
    ConfigError,
    DimensionError,
    EquilibriumError,
    NlyapError,
)
from nlyap_opt.kernel.simulate import trajectories
from nlyap_opt.kernel.walker import ArrayArithmetic, compile_function, evaluate

from .declarations import Declarations, check_declarations
from .samples import SampleSet

__all__ = ["System", "ModelUnavailableError", "KINDS", "EQUILIBRIUM_TOL", "check_box"]

#: the kinds of system: a CasADi model, a black-box callable, samples on a grid
KINDS = ("model", "callable", "samples")
#: absolute tolerance of the equilibrium check ``max_k |f_k(0, u_eq)| <= EQUILIBRIUM_TOL``
EQUILIBRIUM_TOL = 1e-9


class ModelUnavailableError(NlyapError, AttributeError):
    """The system has no CasADi model (a black-box callable or samples): ``f`` is unknown."""


def check_box(box, n: int, what: str) -> np.ndarray:
    """``box`` as an ``(n, 2)`` float array of finite rows ``[lower, upper]`` with lower <
    upper and bounds within ±:data:`BOX_LIMIT`; a one-line :class:`ConfigError` (or
    :class:`DimensionError`) naming ``what`` otherwise."""
    try:
        b = np.asarray(box, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"{what} must be {n} rows [lower, upper] of numbers, got "
                          f"{str(box)[:60]!r}") from None
    if b.shape != (n, 2):
        raise DimensionError(
            f"{what} must be {n} rows [lower, upper] (one per variable), got shape {b.shape}"
        )
    if not np.all(np.isfinite(b)) or np.any(b[:, 0] >= b[:, 1]):
        raise ConfigError(f"{what} needs finite bounds with lower < upper on every row, got "
                          f"{b.tolist()}")
    if np.any(np.abs(b) > BOX_LIMIT):
        raise ConfigError(f"{what} has a bound beyond ±{BOX_LIMIT:g} (squares and widths of "
                         f"such states overflow); rescale the states, got {b.tolist()}")
    return b


#: the largest magnitude of a box bound (a state of 1e100 has a finite square; 1e308 not)
BOX_LIMIT = 1e100


@contextlib.contextmanager
def user_code():
    """Around a call of the user's Python code (a factory, a simulator): the numpy error
    settings it changes are put back (``np.seterr(all="raise")`` in a simulator made the
    tool's own rounding fail), and what it prints goes to standard error (standard output
    carries the tool's results, e.g. ``nlyap config``'s JSON)."""
    with np.errstate(), contextlib.redirect_stdout(sys.stderr):
        yield


def _function_name(name: str) -> str:
    """``name`` as a CasADi Function name: itself where CasADi accepts it (a letter, then
    letters, digits and single underscores), else its letters and digits joined by ``_``
    after ``f_`` (``"my-system"`` → ``"f_my_system"``)."""
    if not isinstance(name, str) or not name:
        raise ArgumentTypeError(f"a system's name must be a non-empty str, got {name!r}")
    if ca.Function.check_name(name):
        return name
    parts = [p for p in re.split(r"[^0-9A-Za-z]+", name) if p]
    return "_".join(["f", *parts])


class System:
    r"""A continuous-time control system :math:`\dot x = f(x, u)`.

    The constructor takes a CasADi model; :meth:`from_callable` and :meth:`from_samples`
    build systems whose ``f`` is unknown (``has_model`` False).

    Parameters
    ----------
    name : str
        Identifier used by the registry and in reports.
    x : casadi.SX, shape (nx, 1)
        State symbols.
    u : casadi.SX, shape (nu, 1), or None
        Input symbols (``None`` or empty for autonomous systems such as Van der Pol).
    f : casadi.SX, shape (nx, 1)
        Right-hand side, an expression of ``x`` and ``u`` only.
    state_box : (nx, 2) array_like
        Working box ``X`` (rows: lower, upper) on which dynamics are sampled.
    input_box : (nu, 2) array_like, optional
        Input bounds ``U``.
    u_eq : (nu,) array_like, optional
        Equilibrium input, ``f(0, u_eq) = 0``. Solved from ``f(0, u) = 0`` when omitted.
    params : dict, optional
        Parameter values (documentation and reports).
    state_names, input_names : sequence of str, optional
    description : str, optional
    known_state_derivatives : sequence of int, optional
        Indices ``i`` of states whose derivative is known exactly (e.g. ``θ' = ω``); learned
        dynamics may model only the other components.
    declarations : Declarations, optional
        Assumptions declared by the user (``K_f``, ``H``, a control-affine ``B``).
    run_overrides : dict, optional
        Run-configuration overrides that travel with the system (a spec file's ``[run]``).
    source : str, optional
        Where the system was defined (a spec file), for messages and reports.
    subsystems : sequence of sequence of int, optional
        A partition of the state indices into the subsystems of an interconnected system
        (each subsystem's states, e.g. ``[(0, 1), (2, 3)]``): declares that a
        compositional certificate (:mod:`nlyap_opt.certification.compositional`) may be tried.

    Attributes
    ----------
    kind : {"model", "callable", "samples"}
    has_model : bool
        True when the CasADi ``f`` is available (true-f checks, ``K_f`` by intervals,
        condition (c) proved, linearisation by CasADi).
    known_rhs : dict of int to casadi.SX
        The exactly known components of ``f`` as expressions of ``x`` and ``u``.

    Notes
    -----
    Derived once at construction: the CasADi Function ``f_fun(x, u)``, the linearisation
    ``A = ∂f/∂x``, ``B = ∂f/∂u`` at ``(0, u_eq)``, and batched evaluators.

    Examples
    --------
    >>> import casadi as ca
    >>> x = ca.SX.sym("x", 2); u = ca.SX.sym("u", 1)
    >>> sys = System("double_integrator", x, u, ca.vertcat(x[1], u),
    ...              state_box=[[-1, 1], [-1, 1]], input_box=[[-1, 1]])
    >>> sys.A.tolist(), sys.B.ravel().tolist()
    ([[0.0, 1.0], [0.0, 0.0]], [0.0, 1.0])
    >>> sys.kind, sys.has_model
    ('model', True)
    """

    def __init__(
        self,
        name: str,
        x: ca.SX,
        u: ca.SX | None,
        f: ca.SX,
        *,
        state_box,
        input_box=None,
        u_eq=None,
        params: dict | None = None,
        state_names: Sequence[str] | None = None,
        input_names: Sequence[str] | None = None,
        description: str = "",
        known_state_derivatives: Sequence[int] = (),
        declarations: Declarations | None = None,
        run_overrides: dict | None = None,
        source: str = "",
        subsystems: Sequence[Sequence[int]] | None = None,
    ):
        if not isinstance(x, ca.SX) or not x.is_column() or not x.is_valid_input():
            raise ArgumentTypeError("x must be a column of casadi.SX symbols, e.g. "
                                    "ca.SX.sym('x', 2)")
        u = ca.SX(0, 1) if u is None else u
        if not isinstance(u, ca.SX) or not (u.is_empty() or u.is_valid_input()):
            raise ArgumentTypeError("u must be a column of casadi.SX symbols or None")
        f = ca.densify(ca.SX(f))  # a structural zero (x_k' = 0) keeps its row in evaluations
        if f.shape != (x.numel(), 1):
            raise DimensionError(
                f"f must have shape ({x.numel()}, 1) to match x, got {f.shape}; "
                "build it with ca.vertcat(...)"
            )
        fun = ca.Function(_function_name(name), [x, u], [f], ["x", "u"], ["f"])
        if fun.has_free():
            raise ValueError(
                f"f depends on symbols other than x and u: {fun.get_free()}; "
                "substitute parameter values before building the System"
            )
        self._setup(name, x, u, "model", state_box=state_box, input_box=input_box,
                    params=params, state_names=state_names, input_names=input_names,
                    description=description, declarations=declarations,
                    run_overrides=run_overrides, source=source)
        self._f, self._f_fun = f, fun
        self.known_state_derivatives = self._known_indices(known_state_derivatives)
        self.subsystems = self._partition(subsystems)
        self.u_eq = self._equilibrium_input(u_eq)
        jac = ca.Function(_function_name("jac_" + name), [x, u],
                          [ca.jacobian(f, x), ca.jacobian(f, u)])
        A, B = jac(np.zeros(self.nx), self.u_eq)
        self._A = np.array(A, dtype=float).reshape(self.nx, self.nx)
        self._B = np.array(B, dtype=float).reshape(self.nx, self.nu)
        self._program = compile_function(fun)

    # ------------------------------------------------------------------ other kinds
    @classmethod
    def from_callable(
        cls,
        name: str,
        fun: Callable[[np.ndarray, np.ndarray], np.ndarray],
        *,
        nx: int,
        nu: int = 0,
        state_box,
        input_box=None,
        u_eq=None,
        known_rhs: dict | None = None,
        equilibrium_tol: float = EQUILIBRIUM_TOL,
        symbols: tuple[ca.SX, ca.SX] | None = None,
        subsystems: Sequence[Sequence[int]] | None = None,
        **kwargs,
    ) -> System:
        r"""A system given by a black-box batched function ``fun(X, U) -> Xdot``.

        Parameters
        ----------
        name : str
        fun : callable
            ``(N, nx), (N, nu) -> (N, nx)`` float64 arrays (a simulator wrapper); it is
            called on batches and must not keep state between calls.
        nx, nu : int
        state_box, input_box : array_like
            As for the constructor.
        u_eq : (nu,) array_like
            The declared equilibrium input (required when ``nu > 0``); ``x = 0`` is the
            equilibrium: ``max_k |fun(0, u_eq)_k| <= equilibrium_tol`` is checked.
        known_rhs : dict, optional
            ``{state index or name: expr}``: components known exactly, as functions
            ``expr(x, u) -> casadi.SX`` of the system's symbols ``x`` ``(nx, 1)`` and ``u``
            ``(nu, 1)``, or SX expressions in ``symbols``; checked against ``fun`` on 64
            seeded points of the box (relative 1e-9).
        equilibrium_tol : float
            Absolute tolerance of the equilibrium check (default 1e-9).
        symbols : (casadi.SX, casadi.SX), optional
            The system's ``x`` and ``u`` (default: new ones from :meth:`symbols`).
        subsystems : sequence of sequence of int, optional
            As for the constructor: an interconnected system's parts, certified
            compositionally from the simulator's values (``nu = 0``; declare ``hessian``,
            and ``depends_on`` for the states each derivative reads).
        **kwargs
            ``params``, ``state_names``, ``input_names``, ``description``,
            ``declarations``, ``run_overrides``, ``source``.

        Examples
        --------
        >>> import numpy as np
        >>> s = System.from_callable(
        ...     "di", lambda X, U: np.stack([X[:, 1], U[:, 0]], axis=1), nx=2, nu=1,
        ...     state_box=[[-1, 1], [-1, 1]], input_box=[[-1, 1]], u_eq=[0.0])
        >>> s.has_model, s.evaluate([[0.5, 1.0]], [[2.0]]).tolist()
        (False, [[1.0, 2.0]])
        """
        if not callable(fun):
            raise ArgumentTypeError(f"fun must be a callable f(X, U) -> Xdot, got "
                                    f"{type(fun).__name__}")
        self = cls.__new__(cls)
        for what, v in (("nx", nx), ("nu", nu)):
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 0:
                raise ArgumentTypeError(f"{what} must be an int >= 0, got {v!r}")
        x, u = cls._given_symbols(symbols, int(nx), int(nu), kwargs)
        self._setup(name, x, u, "callable", state_box=state_box, input_box=input_box, **kwargs)
        self.subsystems = self._partition(subsystems)
        self._callable = fun
        self._set_known_rhs(known_rhs)
        self.u_eq = self._declared_u_eq(u_eq)
        resid = self.evaluate(np.zeros((1, self.nx)), self.u_eq.reshape(1, self.nu))[0]
        self._check_equilibrium(resid, equilibrium_tol, "the callable")
        if self._known:
            rng = np.random.default_rng(0)
            lo, hi = self.sampling_box[:, 0], self.sampling_box[:, 1]
            z = lo + (hi - lo) * rng.random((64, self.nx + self.nu))
            self._check_known(z, self.evaluate(z[:, :self.nx], z[:, self.nx:]), "the callable")
        return self

    @classmethod
    def from_samples(
        cls,
        name: str,
        samples: SampleSet,
        *,
        state_box=None,
        input_box=None,
        u_eq=None,
        known_rhs: dict | None = None,
        equilibrium_tol: float = EQUILIBRIUM_TOL,
        symbols: tuple[ca.SX, ca.SX] | None = None,
        **kwargs,
    ) -> System:
        r"""A system known only by its samples on a complete regular grid.

        Parameters
        ----------
        name : str
        samples : SampleSet
            From :func:`systems.samples.load_samples` (its ``nx``, ``nu`` and names are
            the system's).
        state_box, input_box : array_like, optional
            Default: the grid's box; if given, must equal it (the samples define the box
            on which the error bound holds).
        u_eq : (nu,) array_like
            Declared equilibrium input (required when ``nu > 0``); the grid must contain the
            node ``(0, u_eq)`` and ``max_k |f_k| <= equilibrium_tol`` there.
        known_rhs : dict, optional
            As in :meth:`from_callable`; checked on every node (relative 1e-9).
        equilibrium_tol, symbols
            As in :meth:`from_callable`.
        **kwargs
            ``params``, ``description``, ``declarations``, ``run_overrides``, ``source``.

        Notes
        -----
        ``evaluate`` returns the sampled values at grid nodes and refuses other points;
        declared assumptions are checked against the samples here
        (:func:`~systems.declarations.check_declarations`).
        """
        if not isinstance(samples, SampleSet):
            raise ArgumentTypeError("samples must be a SampleSet (systems.samples.load_samples)")
        nx, nu = samples.nx, samples.nu
        checks = [("state_box", state_box, samples.box[:nx])]
        if not samples.input_slice:
            checks.append(("input_box", input_box, samples.box[nx:]))
        for what, given, rows in checks:
            if given is not None and not np.array_equal(np.asarray(given, dtype=float), rows):
                raise ConfigError(
                    f"{what} {np.asarray(given).tolist()} differs from the sample grid's box "
                    f"{rows.tolist()}; leave {what} out (the samples define it) or resample"
                )
        ubox = samples.box[nx:] if nu else None
        if samples.input_slice:
            decl = kwargs.get("declarations")
            levels = samples.box[nx:, 0][samples.counts[nx:] == 1].tolist()
            if decl is None or decl.input_matrix is None:
                raise ConfigError(
                    f"the samples of {name!r} hold a single input level {levels}; declare "
                    "control-affine structure (input_matrix B) to say what other inputs do, "
                    "or sample a grid over the inputs too"
                )
            if input_box is None:
                raise ConfigError(
                    f"the samples of {name!r} hold a single input level {levels}; give "
                    "input_box (the inputs the controller may use)"
                )
            ubox = check_box(input_box, nu, "input_box")
            inside = (ubox[:, 0] <= samples.box[nx:, 0]) & (samples.box[nx:, 1] <= ubox[:, 1])
            if not np.all(inside):
                raise ConfigError(
                    f"input_box {ubox.tolist()} does not contain the sampled inputs "
                    f"{samples.box[nx:].tolist()}; widen input_box"
                )
        self = cls.__new__(cls)
        kwargs.setdefault("state_names", samples.names[:nx])
        kwargs.setdefault("input_names", samples.names[nx:])
        x, u = cls._given_symbols(symbols, nx, nu, kwargs)
        self._setup(name, x, u, "samples", state_box=samples.box[:nx], input_box=ubox,
                    **kwargs)
        self.samples = samples
        self._set_known_rhs(known_rhs)
        self.u_eq = self._declared_u_eq(u_eq)
        z0 = np.concatenate([np.zeros(nx), self.u_eq])
        if samples.input_slice:  # the equilibrium through the declared B: f(0, u0) + B(u_eq − u0)
            z0[nx:] = np.where(samples.counts[nx:] == 1, samples.box[nx:, 0], self.u_eq)
        k, dist = samples.nearest_node(z0)
        tol = 1e-9 * np.max(samples.spacing)
        if dist > tol:
            raise ConfigError(
                f"the sample grid of {name!r} has no node at (x = 0, u = u_eq = "
                f"{self.u_eq.tolist()}) (nearest node {samples.points([k])[0].tolist()}); "
                "sample a grid that contains the equilibrium (e.g. an odd number of nodes on "
                "a symmetric axis)"
            )
        f0 = samples.values[k]
        if samples.input_slice:
            f0 = f0 + self.declarations.B @ (self.u_eq - z0[nx:])
        self._check_equilibrium(f0, equilibrium_tol, "the samples")
        if self._known:
            self._check_known(samples.points(np.arange(samples.size)), samples.values,
                              "the samples")
        if self.declarations is not None:
            check_declarations(samples, samples.values, self.declarations,
                               names=self.state_names + self.input_names,
                               source=self.source or samples.source)
        return self

    @staticmethod
    def symbols(nx: int, nu: int = 0, state_names: Sequence[str] | None = None,
                input_names: Sequence[str] | None = None) -> tuple[ca.SX, ca.SX]:
        """Symbols ``x`` ``(nx, 1)`` and ``u`` ``(nu, 1)``, one named scalar per entry."""
        sn = list(state_names or [f"x{i + 1}" for i in range(int(nx))])
        un = list(input_names or [f"u{i + 1}" for i in range(int(nu))])
        if len(sn) != int(nx) or len(un) != int(nu):
            raise DimensionError("state_names/input_names must have nx/nu entries")
        x = ca.vertcat(*[ca.SX.sym(n) for n in sn]) if sn else ca.SX(0, 1)
        u = ca.vertcat(*[ca.SX.sym(n) for n in un]) if un else ca.SX(0, 1)
        return ca.SX(x), ca.SX(u)

    @classmethod
    def _given_symbols(cls, symbols, nx: int, nu: int, kwargs: dict) -> tuple[ca.SX, ca.SX]:
        if symbols is None:
            return cls.symbols(nx, nu, kwargs.get("state_names"), kwargs.get("input_names"))
        x, u = symbols
        if not isinstance(x, ca.SX) or x.shape != (nx, 1) or not x.is_valid_input():
            raise ArgumentTypeError(f"symbols[0] must be an SX column of {nx} symbols")
        if not isinstance(u, ca.SX) or u.shape[0] != nu or not (u.is_empty() or
                                                               u.is_valid_input()):
            raise ArgumentTypeError(f"symbols[1] must be an SX column of {nu} symbols")
        return x, u

    # ------------------------------------------------------------------ common set-up
    def _setup(self, name, x, u, kind, *, state_box, input_box=None, params=None,
               state_names=None, input_names=None, description="", declarations=None,
               run_overrides=None, source=""):
        if not isinstance(name, str) or not name:
            raise ArgumentTypeError(f"a system's name must be a non-empty str, got {name!r}")
        self.name = name
        self.kind = kind
        self.x, self.u = x, u
        self.nx, self.nu = x.numel(), u.numel()
        self.state_box = check_box(state_box, self.nx, "state_box")
        if np.any(self.state_box[:, 0] >= 0) or np.any(self.state_box[:, 1] <= 0):
            raise ConfigError(
                f"the state box {self.state_box.tolist()} of {name!r} does not contain the "
                "origin in its interior; the equilibrium x = 0 must be inside X (widen the "
                "box, or shift the state so that the equilibrium is at 0)")
        if self.nu and input_box is None:
            raise ConfigError(f"system {name!r} has inputs: give input_box (nu={self.nu})")
        self.input_box = (check_box(input_box, self.nu, "input_box") if self.nu
                          else np.zeros((0, 2)))
        self.params = dict(params or {})
        self.state_names = list(state_names or [f"x{i + 1}" for i in range(self.nx)])
        self.input_names = list(input_names or [f"u{i + 1}" for i in range(self.nu)])
        if len(self.state_names) != self.nx or len(self.input_names) != self.nu:
            raise DimensionError("state_names/input_names must have nx/nu entries")
        self.description = description
        if declarations is not None and not isinstance(declarations, Declarations):
            raise ArgumentTypeError("declarations must be a systems.Declarations")
        self.declarations = None if declarations is None else declarations.validate(
            self.nx, self.nu)
        if self.declarations is not None:  # depends_on names the system's own variables
            self.declarations.dependencies(self.state_names, self.input_names)
        self.run_overrides = dict(run_overrides or {})
        self.source = str(source)
        self._f = self._f_fun = self._A = self._B = None
        self._program = self._callable = None
        self.samples = None
        self._known: dict[int, ca.SX] = {}
        self._torch = None
        self.subsystems = None

    def _partition(self, parts) -> tuple[tuple[int, ...], ...] | None:
        if parts is None:
            return None
        out = tuple(tuple(int(i) for i in p) for p in parts)
        if any(not p for p in out) or sorted(i for p in out for i in p) != list(range(self.nx)):
            raise ConfigError(f"subsystems must split the {self.nx} state indices 0..{self.nx - 1}"
                              f" into non-empty groups, each index once; got {parts!r}")
        return out

    def _known_indices(self, idx) -> tuple[int, ...]:
        out = tuple(int(i) for i in idx)
        for i in out:
            if not 0 <= i < self.nx:
                raise ConfigError(
                    f"known_state_derivatives index {i} is out of range for {self.nx} states"
                )
        return out

    def _set_known_rhs(self, known_rhs) -> None:
        known: dict[int, ca.SX] = {}
        for key, expr in dict(known_rhs or {}).items():
            if isinstance(key, str):
                if key not in self.state_names:
                    raise ConfigError(
                        f"known_rhs names {key!r}, not a state of {self.name!r} "
                        f"({', '.join(self.state_names)})"
                    )
                key = self.state_names.index(key)
            i = int(key)
            if not 0 <= i < self.nx:
                raise ConfigError(f"known_rhs index {i} is out of range for {self.nx} states")
            e = expr(self.x, self.u) if callable(expr) else expr
            e = ca.densify(ca.SX(e))
            if e.shape != (1, 1):
                raise DimensionError(f"known_rhs[{i}] must be a scalar expression, got {e.shape}")
            if ca.Function("k", [self.x, self.u], [e], {"allow_free": True}).has_free():
                raise ConfigError(
                    f"known_rhs[{i}] ({self.state_names[i]}') uses symbols other than the "
                    "system's x and u; build it from System.symbols or pass a function (x, u)"
                )
            known[i] = e
        self._known = dict(sorted(known.items()))
        self.known_state_derivatives = tuple(self._known)

    def _check_known(self, z: np.ndarray, values: np.ndarray, where: str) -> None:
        fun = ca.Function("known", [self.x, self.u], [ca.vertcat(*self._known.values())])
        prog = compile_function(fun)
        got = evaluate(prog, [z[:, :self.nx], z[:, self.nx:]])[0]
        want = values[:, list(self._known)]
        err = np.abs(got - want)
        bad = err > 1e-9 * (1.0 + np.abs(want))
        if bad.any():
            r, c = np.argwhere(bad)[0]
            i = list(self._known)[c]
            raise ConfigError(
                f"the known component {self.state_names[i]}' of {self.name!r} disagrees with "
                f"{where} at z = {z[r].tolist()}: expression {float(got[r, c])!r}, data "
                f"{float(want[r, c])!r}; fix the expression or do not declare the component known"
            )

    def _declared_u_eq(self, u_eq) -> np.ndarray:
        if not self.nu:
            if u_eq is not None and np.size(u_eq):
                raise ConfigError(f"system {self.name!r} has no inputs; remove u_eq")
            return np.zeros(0)
        if u_eq is None:
            raise ConfigError(
                f"system {self.name!r} has no model to solve f(0, u) = 0 from: declare the "
                f"equilibrium input u_eq ({self.nu} numbers)"
            )
        u = np.asarray(u_eq, dtype=float).ravel()
        if u.shape != (self.nu,) or not np.all(np.isfinite(u)):
            raise ConfigError(f"u_eq must be {self.nu} finite numbers, got {u_eq!r}")
        return self._u_eq_in_box(u)

    def _u_eq_in_box(self, u: np.ndarray) -> np.ndarray:
        """``u``, refused where an input's ``u_eq`` lies outside its box: the actuator
        could not hold the equilibrium, and nothing certified about ``f(x, u_eq + …)``
        would be about the system as declared."""
        box = self.input_box
        for i in range(self.nu):
            if not box[i, 0] <= u[i] <= box[i, 1]:
                raise ConfigError(
                    f"input {self.input_names[i]!r} of {self.name!r}: its equilibrium value "
                    f"u_eq = {u[i]:.6g} lies outside its box {box[i].tolist()}, so the actuator "
                    "cannot hold the equilibrium; fix u_eq or the input box")
        return u

    def _check_equilibrium(self, resid, tol: float, where: str) -> None:
        resid = np.asarray(resid, dtype=float).ravel()
        self._eq_residual = float(np.max(np.abs(resid), initial=0.0))
        self._eq_tol = float(tol)
        if not np.all(np.isfinite(resid)) or np.max(np.abs(resid), initial=0.0) > tol:
            raise EquilibriumError(
                f"the origin is not an equilibrium of {self.name!r}: f(0, u_eq="
                f"{self.u_eq.tolist()}) = {resid.tolist()} by {where} (tolerance {tol:g}); shift "
                "the state so that the equilibrium is at x = 0, or declare the right u_eq"
            )

    def _no_model(self, what: str):
        src = f" from {self.source}" if self.source else ""
        return ModelUnavailableError(
            f"{what} of system {self.name!r} is unknown: it is given by "
            f"{'a black-box callable' if self.kind == 'callable' else 'samples'}{src}, "
            "not a CasADi model; use the learned dynamics φ (or check system.has_model)"
        )

    # ------------------------------------------------------------------ model access
    @property
    def has_model(self) -> bool:
        """True when ``f`` is a CasADi expression (``kind == "model"``)."""
        return self.kind == "model"

    @property
    def can_simulate(self) -> bool:
        """True when ``f`` can be evaluated anywhere (a model or a callable, not samples)."""
        return self.kind in ("model", "callable")

    @property
    def f(self) -> ca.SX:
        """The right-hand side as CasADi SX (model only)."""
        if self._f is None:
            raise self._no_model("the right-hand side f")
        return self._f

    @property
    def f_fun(self) -> ca.Function:
        """CasADi Function ``(x, u) -> f`` (model only)."""
        if self._f_fun is None:
            raise self._no_model("the CasADi function f_fun")
        return self._f_fun

    @property
    def A(self) -> np.ndarray:
        """``∂f/∂x`` at ``(0, u_eq)`` (model only)."""
        if self._A is None:
            raise self._no_model("the linearisation A = ∂f/∂x")
        return self._A

    @property
    def B(self) -> np.ndarray:
        """``∂f/∂u`` at ``(0, u_eq)`` (model only)."""
        if self._B is None:
            raise self._no_model("the linearisation B = ∂f/∂u")
        return self._B

    @property
    def known_rhs(self) -> dict[int, ca.SX]:
        """The exactly known components ``{i: f_i(x, u)}`` as SX in ``x``, ``u`` (every kind)."""
        if self.has_model:
            return {i: self._f[i] for i in self.known_state_derivatives}
        return dict(self._known)

    def known_function(self) -> ca.Function:
        """CasADi Function ``(x, u) -> (f_i)_{i in known_state_derivatives}`` (every kind).

        The exactly known components, in the order of ``known_state_derivatives``; call it
        on SX or MX symbols to complete a learned right-hand side.
        """
        known = self.known_rhs
        out = ca.vertcat(*[known[i] for i in self.known_state_derivatives]) if known \
            else ca.SX(0, 1)
        return ca.Function(_function_name(f"{self.name}_known"), [self.x, self.u], [out],
                           ["x", "u"], ["f"])

    @property
    def sampling_box(self) -> np.ndarray:
        """``X × U`` as one ``(nx + nu, 2)`` box (rows: states, then inputs)."""
        return np.vstack([self.state_box, self.input_box])

    def check_declarations(self, grid, values=None) -> dict:
        """Check :attr:`declarations` against ``f`` at the nodes of ``grid`` (over X × U).

        ``values`` defaults to :meth:`evaluate` at the nodes (not for a ``"samples"`` system
        unless ``grid`` is its grid). Returns the estimates (see
        :func:`~systems.declarations.check_declarations`); raises ConfigError if the data
        contradict a declaration.
        """
        if self.declarations is None:
            return {}
        if values is None:
            z = np.vstack(list(grid.batches())) if hasattr(grid, "batches") else None
            if z is None:
                raise TypeError("grid needs a batches() method, or pass values")
            values = self.evaluate(z[:, :self.nx], z[:, self.nx:])
        return check_declarations(grid, values, self.declarations,
                                  names=self.state_names + self.input_names, source=self.source)

    # ------------------------------------------------------------------ derived
    def _equilibrium_input(self, u_eq) -> np.ndarray:
        zero = np.zeros(self.nx)
        solved = u_eq is None and bool(self.nu)
        if solved:  # solve f(0, u) = 0 in the least-squares sense

            u = ca.SX.sym("u", self.nu)
            r = self.f_fun(zero, u)
            res = ca.Function("r", [u], [r, ca.jacobian(r, u)])
            sol = least_squares(
                lambda v: np.array(res(v)[0], dtype=float).ravel(), np.zeros(self.nu),
                jac=lambda v: np.array(res(v)[1], dtype=float).reshape(self.nx, self.nu),
                xtol=1e-15, ftol=1e-15, gtol=1e-15,
            )
            # a solution on a box edge may come out an ulp outside it: clipped within 1e-12
            # of the box's width (a solution farther out is refused below)
            slack = 1e-12 * (self.input_box[:, 1] - self.input_box[:, 0])
            u_eq = np.where(np.abs(sol.x - np.clip(sol.x, self.input_box[:, 0],
                                                   self.input_box[:, 1])) <= slack,
                            np.clip(sol.x, self.input_box[:, 0], self.input_box[:, 1]), sol.x)
        u_eq = np.zeros(0) if not self.nu else np.asarray(u_eq, dtype=float).reshape(self.nu)
        resid = np.array(self.f_fun(zero, u_eq), dtype=float).ravel()
        if not np.all(np.isfinite(resid)):
            raise EquilibriumError(
                f"f of {self.name!r} is not defined at the origin: f(0, u_eq={u_eq}) = "
                f"{resid.tolist()}; the equilibrium x = 0 must lie where every expression "
                "is defined (check square roots, logarithms and divisions there)")
        if np.max(np.abs(resid), initial=0.0) > EQUILIBRIUM_TOL:
            shift = "shift the state so that the equilibrium is at x = 0"
            fix = (shift if not self.nu else f"no input holds the origin at rest: {shift}"
                   if solved else f"declare the right u_eq (or leave it out to have it "
                   f"solved), or {shift}")
            at = f"f(0, u_eq={u_eq})" if self.nu else "f(0)"
            raise EquilibriumError(
                f"the origin is not an equilibrium of {self.name!r}: {at} = {resid}; {fix}")
        return self._u_eq_in_box(u_eq)

    def evaluate(self, x, u=None) -> np.ndarray:
        """Evaluate ``f`` on a batch, float64.

        A ``"model"`` is evaluated through its CasADi graph, a ``"callable"`` is called, a
        ``"samples"`` system returns the sampled values and refuses points that are not
        grid nodes.

        Parameters
        ----------
        x : (N, nx) array_like
        u : (N, nu) array_like, optional
            Defaults to ``u_eq`` for every sample.

        Returns
        -------
        (N, nx) ndarray
        """
        x = np.asarray(x, dtype=float)
        if x.ndim != 2 or x.shape[1] != self.nx:
            raise DimensionError(f"x must have shape (N, {self.nx}), got {x.shape}")
        if u is None:
            u = np.broadcast_to(self.u_eq, (x.shape[0], self.nu))
        u = np.asarray(u, dtype=float)
        if u.ndim != 2 or u.shape != (x.shape[0], self.nu):
            raise DimensionError(f"u must have shape ({x.shape[0]}, {self.nu}), got {u.shape}")
        if self.kind == "model":
            return evaluate(self._program, [x, u])[0]
        if self.kind == "samples":
            return self.samples.lookup(x, u)
        with user_code():
            raw = self._callable(x, u)
        if np.iscomplexobj(raw):
            raise ConfigError(f"the callable of {self.name!r} returned complex values; return "
                              "real (float64) derivatives")
        try:
            out = np.asarray(raw, dtype=float)
        except (TypeError, ValueError):
            raise ConfigError(f"the callable of {self.name!r} returned "
                              f"{type(raw).__name__}, not an array of numbers; return an "
                              f"(N, {self.nx}) float64 array") from None
        if out.shape != x.shape:
            raise DimensionError(
                f"the callable of {self.name!r} returned shape {out.shape} for {x.shape[0]} "
                f"points; it must return (N, {self.nx}) = {x.shape}"
            )
        return out

    def evaluate_torch(self, x, u=None):
        """Evaluate ``f`` on torch tensors ``(N, nx)``, ``(N, nu)`` (differentiable; model only)."""
        if self._program is None:
            raise self._no_model("a differentiable (torch) evaluation of f")
        if self._torch is None:
            self._torch = ArrayArithmetic("torch")
        if u is None:
            torch = deps.torch()

            u = torch.as_tensor(self.u_eq, dtype=x.dtype).expand(x.shape[0], self.nu)
        return evaluate(self._program, [x, u], self._torch)[0]

    def closed_loop(self, feedback: Callable[[ca.SX], ca.SX] | None = None) -> ca.Function:
        """CasADi Function ``x -> f(x, κ(x))`` for a symbolic feedback ``κ`` (SX -> SX)."""
        u = ca.DM(self.u_eq) if feedback is None else feedback(self.x)
        return ca.Function(_function_name(f"{self.name}_cl"), [self.x], [self.f_fun(self.x, u)])

    def simulate(
        self,
        feedback: Callable[[np.ndarray], np.ndarray] | None,
        x0,
        t_final: float,
        *,
        n_steps: int = 2000,
        method: str = "rk4",
    ) -> np.ndarray:
        """Simulate the closed loop from many initial states at once (fixed-step RK4).

        Works for a ``"model"`` and a ``"callable"``; samples cannot be simulated.

        Parameters
        ----------
        feedback : callable or None
            Batched numpy feedback ``(N, nx) -> (N, nu)``; ``None`` applies ``u_eq``.
        x0 : (N, nx) array_like
        t_final : float
        n_steps : int

        Returns
        -------
        (n_steps + 1, N, nx) ndarray
            The trajectories (non-finite once a trajectory blows up).
        """
        if method != "rk4":
            raise ValueError(f"method must be 'rk4', got {method!r}")
        if self.kind == "samples":
            raise self._no_model("f between the grid nodes (needed to simulate)")
        def rhs(z):
            u = None if feedback is None else np.asarray(feedback(z), dtype=float)
            with np.errstate(all="ignore"):
                return self.evaluate(z, u)


        return trajectories(rhs, x0, t_final, n_steps)

    def describe_assumptions(self) -> list[str]:
        """The assumptions about ``f``, one sentence each (for certificate and report).

        The declared ones (:meth:`Declarations.describe`), and for a system without a
        model the one every certificate from data rests on: the data are ``f``'s values.
        """
        out = [] if self.declarations is None else self.declarations.describe(
            self.state_names, self.input_names)
        if self.has_model:
            return out
        if self.declarations is None or self.declarations.sample_error is None:
            what = ("the black-box callable returns" if self.kind == "callable"
                    else "the sample file holds")
            out.append(f"Data (assumed): {what} the exact values of f (no measurement noise; "
                       "declare sample_error otherwise)")
        out.append(
            f"Equilibrium (declared): f(0, u_eq) = 0 with u_eq = {self.u_eq.tolist()} (the "
            f"data give max_k |f_k(0, u_eq)| = {self._eq_residual:.3g}, checked ≤ "
            f"{self._eq_tol:g})"
        )
        if self._known:
            eqs = "; ".join(f"{self.state_names[i]}' = {ca.SX(e)}" for i, e in
                            self._known.items())
            out.append(f"Known components (declared, checked on the data): {eqs}, in the "
                       f"symbols x = ({', '.join(self.state_names)})"
                       + (f", u = ({', '.join(self.input_names)})" if self.nu else ""))
        return out

    def summary(self) -> dict:
        """Plain-JSON description for reports, certificates and ``nlyap systems --check``."""
        out = {
            "name": self.name, "kind": self.kind, "has_model": self.has_model,
            "can_simulate": self.can_simulate,
            "source": self.source, "description": self.description,
            "states": self.state_names, "inputs": self.input_names,
            "state_box": self.state_box.tolist(), "input_box": self.input_box.tolist(),
            "u_eq": self.u_eq.tolist(), "params": dict(self.params),
            "known_state_derivatives": [self.state_names[i] for i in
                                        self.known_state_derivatives],
            "assumptions_declared": self.describe_assumptions(),
            "declarations": None if self.declarations is None else self.declarations.to_dict(),
            "run_overrides": dict(self.run_overrides),
        }
        if self.samples is not None:
            out["samples"] = self.samples.to_dict()
        if self.subsystems is not None:
            out["subsystems"] = [[self.state_names[i] for i in p] for p in self.subsystems]
        return out

    def __repr__(self) -> str:
        extra = "" if self.kind == "model" else f", kind={self.kind!r}"
        return f"System({self.name!r}, nx={self.nx}, nu={self.nu}{extra})"
