r"""Exact real polynomials, and the walker arithmetic that expands CasADi graphs into them.

:class:`Polynomial` stores :math:`p(x) = \sum_k c_k\, x^{\alpha_k}` as exponent rows and
coefficients. :class:`PolynomialArithmetic` is an arithmetic of the instruction walker
(:mod:`nlyap_opt.kernel.walker`) whose values are exact polynomials (dicts ``exponent tuple ->
coefficient``): walking a CasADi SX function of ``x`` with it gives the coefficients of the
function, or names the operations that make it non-polynomial.

Which CasADi operations are polynomial
    - always (:data:`POLYNOMIAL_OPS`): ``add``, ``sub``, ``mul``, ``neg``, ``sq``, ``twice``,
      ``assign``;
    - with a constant argument (:data:`CONDITIONAL_OPS`): ``div`` by a nonzero constant,
      ``pow`` / ``constpow`` with a constant integer exponent in ``0..64``,
      ``if_else_zero`` with a constant condition;
    - any operation whose arguments are all constants is folded in float64 (as CasADi itself
      folds constant subexpressions), by the walker's numpy arithmetic;
    - every other operation of the walker's op table applied to a function of the state
      (``sin``, ``exp``, ``fabs``, ``fmin``, comparisons, ...) is refused with
      :class:`NotPolynomialError` (an :class:`~nlyap_opt.kernel.errors.UnsupportedOperationError`)
      naming the operation.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from fractions import Fraction

import casadi as ca
import numpy as np
from threadpoolctl import threadpool_limits

from ..kernel.errors import UnsupportedOperationError
from ..kernel.symbolic import closed_loop
from ..kernel.walker import NUMPY, evaluate, op_name

__all__ = [
    "CONDITIONAL_OPS", "ExactPolynomialArithmetic", "NotPolynomialError", "POLYNOMIAL_OPS",
    "Polynomial", "PolynomialArithmetic", "exact_polynomials", "expand_polynomials",
    "FIT_DEGREES", "FIT_POINTS", "FIT_TOLERANCE", "PolynomialFit", "fit_polynomial_model",
    "monomial_matrix", "monomials", "polynomial_closed_loop",
]

#: CasADi operations that map polynomials to polynomials for any arguments.
POLYNOMIAL_OPS: frozenset[int] = frozenset({
    ca.OP_ADD, ca.OP_SUB, ca.OP_MUL, ca.OP_NEG, ca.OP_SQ, ca.OP_TWICE, ca.OP_ASSIGN,
})

#: CasADi operations that are polynomial when one argument is a constant: op -> the condition.
CONDITIONAL_OPS: dict[int, str] = {
    ca.OP_DIV: "a constant nonzero divisor",
    ca.OP_POW: "a constant integer exponent in 0..64",
    ca.OP_CONSTPOW: "a constant integer exponent in 0..64",
    ca.OP_IF_ELSE_ZERO: "a constant condition",
}

_MAX_POWER = 64

# readable names in messages (the rest: the OP_ name in lower case)
_FRIENDLY = {ca.OP_DIV: "division", ca.OP_INV: "the reciprocal", ca.OP_SIN: "sin",
             ca.OP_COS: "cos", ca.OP_TANH: "tanh", ca.OP_EXP: "exp", ca.OP_SQRT: "sqrt"}


class NotPolynomialError(UnsupportedOperationError, ValueError):
    """A CasADi expression is not a polynomial in the state (SOS needs polynomial data).

    Attributes
    ----------
    operations : dict
        Readable name -> ``OP_...`` name of each offending operation.
    """

    def __init__(self, message: str, operations: dict[str, str] | None = None):
        super().__init__(message)
        self.operations = dict(operations or {})


# --------------------------------------------------------------------------- exponents
def _unit(nx: int, i: int, power: int = 1) -> tuple:
    """The exponent of :math:`x_i^{power}`."""
    e = [0] * nx
    e[i] = power
    return tuple(e)


def _add_exponents(e1, e2) -> tuple:
    """The exponent of the product of two monomials."""
    return tuple(a + b for a, b in zip(e1, e2))


def monomials(nx: int, lo: int, hi: int) -> list[tuple]:
    """Exponent tuples of total degree ``lo..hi`` (graded).

    Examples
    --------
    >>> monomials(2, 1, 2)
    [(1, 0), (0, 1), (2, 0), (1, 1), (0, 2)]
    """
    out = []
    for d in range(lo, hi + 1):
        for c in itertools.combinations_with_replacement(range(nx), d):
            e = [0] * nx
            for i in c:
                e[i] += 1
            out.append(tuple(e))
    return out


def monomial_matrix(X, exponents) -> np.ndarray:
    """``Z[k, j] = X[k] ** exponents[j]`` (integer powers by repeated multiplication).

    Parameters
    ----------
    X : (N, nx) array_like
    exponents : (m, nx) array_like of int

    Returns
    -------
    (N, m) ndarray
    """
    X = np.atleast_2d(np.asarray(X, dtype=float))
    E = np.asarray(exponents, dtype=int).reshape(-1, X.shape[1])
    powers = [np.ones_like(X)]
    for _ in range(int(E.max(initial=0))):
        powers.append(powers[-1] * X)
    Z = np.ones((len(X), len(E)))
    for j, e in enumerate(E):
        for i, a in enumerate(e):
            if a:
                Z[:, j] *= powers[a][:, i]
    return Z


# --------------------------------------------------------------------------- dict algebra
def _padd(p: dict, q: dict, sign: float = 1.0) -> dict:
    out = dict(p)
    for e, c in q.items():
        out[e] = out.get(e, 0.0) + sign * c
    return {e: c for e, c in out.items() if c != 0.0}


def _pmul(p: dict, q: dict) -> dict:
    out: dict = {}
    for (e1, c1), (e2, c2) in itertools.product(p.items(), q.items()):
        e = _add_exponents(e1, e2)
        out[e] = out.get(e, 0.0) + c1 * c2
    return {e: c for e, c in out.items() if c != 0.0}


def _polynomial_op(op: int, a: dict, b: dict, kb, add, mul, one: dict) -> dict:
    """``a op b`` for the polynomial operations (+, −, ×, ÷ by the constant ``kb``, an
    integer power ``kb``) in one coefficient arithmetic: ``add``/``mul`` and the unit
    polynomial ``one`` (float or exact)."""
    if op == ca.OP_ADD:
        return add(a, b)
    if op == ca.OP_SUB:
        return add(a, b, -1)
    if op == ca.OP_MUL:
        return mul(a, b)
    if op == ca.OP_DIV:
        return {e: v / kb for e, v in a.items()}
    p = one  # pow / constpow with an integer exponent
    for _ in range(int(kb)):
        p = mul(p, a)
    return p


def _pscale(p: dict, factor: float) -> dict:
    return {e: factor * c for e, c in p.items() if factor * c != 0.0}


def _constant_of(p: dict) -> float | None:
    """The value of a constant polynomial, or ``None`` if ``p`` depends on ``x``."""
    if any(any(e) for e in p):
        return None
    return next(iter(p.values()), 0.0)


# --------------------------------------------------------------------------- Polynomial
@dataclass(frozen=True)
class Polynomial:
    r"""A real polynomial :math:`p(x) = \sum_k c_k\, x^{\alpha_k}` in ``nx`` variables.

    Attributes
    ----------
    exponents : (k, nx) int ndarray   the monomials :math:`\alpha_k`
    coefficients : (k,) ndarray       the coefficients :math:`c_k`

    Examples
    --------
    >>> p = Polynomial.from_dict({(2, 0): 1.5, (1, 1): -1.0, (0, 2): 1.0})
    >>> float(p(np.array([[1.0, 2.0]]))[0]), p.degree
    (3.5, 2)
    """

    exponents: np.ndarray
    coefficients: np.ndarray

    @classmethod
    def from_dict(cls, terms: dict, nx: int | None = None) -> Polynomial:
        """Build from ``{exponent tuple: coefficient}`` (zero coefficients dropped)."""
        items = sorted(((tuple(int(a) for a in e), float(c)) for e, c in terms.items()
                        if c != 0), key=lambda t: (sum(t[0]), tuple(-a for a in t[0])))
        if nx is None:
            if not terms:
                raise ValueError("give nx for the zero polynomial")
            nx = len(next(iter(terms)))
        exps = np.array([e for e, _ in items], dtype=int).reshape(-1, nx)
        return cls(exps, np.array([c for _, c in items], dtype=float))

    @classmethod
    def quadratic(cls, P) -> Polynomial:
        r"""The quadratic form :math:`x^\top P x` of an ``(nx, nx)`` matrix ``P``.

        Examples
        --------
        >>> str(Polynomial.quadratic([[1.5, -0.5], [-0.5, 1.0]]))
        '1.5*x1^2 -1*x1*x2 +1*x2^2'
        """
        P = np.asarray(P, dtype=float)
        nx = P.shape[0]
        terms: dict = {}
        for i, j in itertools.product(range(nx), repeat=2):
            e = _add_exponents(_unit(nx, i), _unit(nx, j))
            terms[e] = terms.get(e, 0.0) + float(P[i, j])
        return cls.from_dict(terms, nx)

    def to_dict(self) -> dict:
        """``{exponent tuple: coefficient}``."""
        return {tuple(int(a) for a in e): float(c)
                for e, c in zip(self.exponents, self.coefficients)}

    @property
    def nx(self) -> int:
        """Number of variables."""
        return self.exponents.shape[1]

    @property
    def degree(self) -> int:
        """Total degree (0 for the zero polynomial)."""
        return int(self.exponents.sum(axis=1).max()) if len(self.coefficients) else 0

    def scaled(self, factor: float) -> Polynomial:
        """The polynomial ``factor · p``."""
        return Polynomial(self.exponents, self.coefficients * factor)

    def substituted(self, scale: float) -> Polynomial:
        """The polynomial ``y -> p(scale·y)`` (each coefficient times ``scale^|α|``).

        Examples
        --------
        >>> p = Polynomial.from_dict({(2, 0): 1.0, (0, 1): 3.0})
        >>> str(p.substituted(2.0))
        '6*x2 +4*x1^2'
        """
        return Polynomial(self.exponents,
                          self.coefficients * float(scale) ** self.exponents.sum(axis=1))

    def __call__(self, X) -> np.ndarray:
        """Evaluate on a batch ``X`` of shape ``(N, nx)``; returns ``(N,)``."""
        return monomial_matrix(X, self.exponents) @ self.coefficients

    def casadi(self, x):
        """The polynomial as a CasADi expression of the column symbol ``x`` (MX or SX)."""
        if x.numel() != self.nx:
            raise ValueError(f"x must have {self.nx} entries, got {x.numel()}")
        total = 0
        for e, c in zip(self.exponents, self.coefficients):
            term = float(c)
            for i, a in enumerate(e):
                if a == 1:
                    term = term * x[i]
                elif a > 1:
                    term = term * x[i] ** int(a)
            total = total + term
        return total if not isinstance(total, int) else x[0] * 0

    def __str__(self) -> str:
        parts = []
        for e, c in zip(self.exponents, self.coefficients):
            mono = "*".join(f"x{i + 1}" + (f"^{a}" if a > 1 else "")
                            for i, a in enumerate(e) if a)
            parts.append(f"{c:+.6g}" + (f"*{mono}" if mono else ""))
        return " ".join(parts).lstrip("+") or "0"

    def as_json(self) -> dict:
        """``{"exponents": [[...], ...], "coefficients": [...]}``."""
        return {"exponents": self.exponents.tolist(), "coefficients": self.coefficients.tolist()}

    @classmethod
    def from_json(cls, d) -> Polynomial:
        """Inverse of :meth:`as_json`; a malformed object raises ``ValueError`` naming what
        is wrong (a saved file is checked, not trusted)."""
        try:
            exps = np.asarray(d["exponents"])
            coef = np.asarray(d["coefficients"], dtype=float)
        except (TypeError, KeyError, ValueError) as err:
            raise ValueError(f"a polynomial needs 'exponents' and 'coefficients' lists: "
                             f"{err}") from None
        if exps.ndim != 2 or exps.shape[0] != coef.shape[0] or coef.ndim != 1 or \
                exps.shape[1] < 1 or not np.issubdtype(exps.dtype, np.integer) or \
                np.any(exps < 0) or not np.all(np.isfinite(coef)):
            raise ValueError("a polynomial needs a (k, nx) array of non-negative integer "
                             "exponents and k finite coefficients")
        return cls(exps.astype(int), coef)


# --------------------------------------------------------------------------- arithmetic
class PolynomialArithmetic:
    """Walker arithmetic over exact polynomials (dicts exponent-tuple -> coefficient).

    Parameters
    ----------
    nx : int
        Number of state variables.
    collect : bool
        ``False`` (default): a non-polynomial operation on a function of the state raises
        :class:`NotPolynomialError` naming it. ``True``: it gives the value ``None``
        (propagated by every later operation) and is recorded in :attr:`refused`, so that
        one walk names every offending operation (see :func:`expand_polynomials`).

    Attributes
    ----------
    refused : dict
        Readable name -> ``OP_...`` name of each refused operation (``collect=True``).

    Notes
    -----
    Operations on constants only are folded in float64 by the walker's numpy arithmetic,
    as CasADi itself would. See the module docstring for the polynomial operations.

    Examples
    --------
    >>> ar = PolynomialArithmetic(2)
    >>> x1, x2 = ar.variables()
    >>> ar.binary(ca.OP_MUL, ar.unary(ca.OP_SQ, x1), ar.unary(ca.OP_TWICE, x2))
    {(2, 1): 2.0}
    """

    name = "polynomial"
    symbolic = True

    def __init__(self, nx: int, *, collect: bool = False):
        self.nx = nx
        self.collect = collect
        self.zero = (0,) * nx
        self.refused: dict[str, str] = {}

    def variables(self) -> np.ndarray:
        """The state ``x`` as an object array of ``nx`` polynomials ``x_i``."""
        xs = np.empty(self.nx, dtype=object)
        for i in range(self.nx):
            xs[i] = {_unit(self.nx, i): 1.0}
        return xs

    def constant(self, value) -> dict:
        """A constant polynomial (the empty dict for 0)."""
        c = float(value)
        return {self.zero: c} if c != 0 else {}

    def unary(self, op: int, a):
        """Apply unary CasADi operation ``op`` to the polynomial ``a``."""
        if a is None:
            return None if op in POLYNOMIAL_OPS else self._refuse(op, "a non-polynomial")
        c = _constant_of(a)
        if c is not None:
            return self._fold(op, c)
        if op == ca.OP_NEG:
            return _pscale(a, -1.0)
        if op == ca.OP_SQ:
            return _pmul(a, a)
        if op == ca.OP_TWICE:
            return _pscale(a, 2.0)
        if op == ca.OP_ASSIGN:
            return a
        return self._refuse(op, "a function of the state")

    def binary(self, op: int, a, b):
        """Apply binary CasADi operation ``op`` to the polynomials ``a``, ``b``."""
        ka = None if a is None else _constant_of(a)
        kb = None if b is None else _constant_of(b)
        if op == ca.OP_IF_ELSE_ZERO and ka is not None:  # selection by a constant condition
            return b if ka != 0 else {}
        allowed = (op in POLYNOMIAL_OPS
                   or (op == ca.OP_DIV and kb not in (None, 0.0))
                   or (op in (ca.OP_POW, ca.OP_CONSTPOW) and _integer_exponent(kb)))
        if a is None or b is None:
            return None if allowed else self._refuse(op, "a non-polynomial")
        if ka is not None and kb is not None:
            return self._fold(op, ka, kb)
        if not allowed:
            if op in CONDITIONAL_OPS:
                return self._refuse(op, "a function of the state (polynomial only with "
                                        f"{CONDITIONAL_OPS[op]})")
            return self._refuse(op, "functions of the state")
        return _polynomial_op(op, a, b, kb, _padd, _pmul, {self.zero: 1.0})

    def structural(self, fn, *args):
        """Apply an exact rearrangement (indexing, stacking)."""
        return fn(*args)

    def _fold(self, op, *consts):
        if len(consts) == 1:
            val = NUMPY.unary(op, np.array(consts[0]))
        else:
            val = NUMPY.binary(op, np.array(consts[0]), np.array(consts[1]))
        return self.constant(float(val))

    def _refuse(self, op, applied_to: str):
        name = op_name(op)
        friendly = _FRIENDLY.get(op, name.removeprefix("OP_").lower())
        if not self.collect:
            raise NotPolynomialError(
                f"CasADi operation {name} ({friendly}) applied to {applied_to} is not "
                "polynomial; the polynomial arithmetic supports "
                + ", ".join(sorted(op_name(o) for o in POLYNOMIAL_OPS))
                + " and " + "; ".join(f"{op_name(o)} with {w}"
                                      for o, w in CONDITIONAL_OPS.items()) + ".",
                {friendly: name})
        self.refused.setdefault(friendly, name)
        return None


def _integer_exponent(k: float | None) -> bool:
    return k is not None and float(k).is_integer() and 0 <= k <= _MAX_POWER


# --------------------------------------------------------------------------- expansion
def expand_polynomials(fun: ca.Function) -> list[Polynomial]:
    """Exact expansion of an SX Function ``x -> y`` into polynomials, through the walker.

    Parameters
    ----------
    fun : casadi.Function
        SX function of one input ``x`` (``nx`` nonzeros) and one output.

    Returns
    -------
    list of Polynomial
        One per nonzero of the output.

    Raises
    ------
    NotPolynomialError
        Naming every operation that makes an output non-polynomial in ``x``.

    Examples
    --------
    >>> x = ca.SX.sym("x", 2)
    >>> [str(p) for p in expand_polynomials(ca.Function("f", [x], [x[0] * (x[1] + 2) / 4]))]
    ['0.5*x1 +0.25*x1*x2']
    """
    nx = fun.nnz_in(0)
    ar = PolynomialArithmetic(nx, collect=True)
    outs = evaluate(fun, [ar.variables()], ar)[0]
    if any(p is None for p in outs):
        what = ", ".join(f"{k} ({v})" for k, v in ar.refused.items())
        raise NotPolynomialError(
            f"not polynomial in x: it applies {what} to state-dependent expressions",
            ar.refused)
    return [Polynomial.from_dict(p, nx) for p in outs]


def polynomial_closed_loop(system, controller=None) -> list[Polynomial]:
    r"""The closed loop :math:`f(x, \kappa(x))` as exact polynomials, one per state.

    The CasADi graph is expanded instruction by instruction with
    :class:`PolynomialArithmetic`; any non-polynomial operation on a function of the state
    raises :class:`NotPolynomialError` naming it.

    Parameters
    ----------
    system : systems.System
    controller : nlyap_opt.kernel.network.Network, optional
        Feedback ``κ``; ``None`` applies ``u_eq``.

    Returns
    -------
    list of Polynomial
        ``nx`` polynomials, ``f_i(x)``.

    Examples
    --------
    >>> import systems
    >>> [str(p) for p in polynomial_closed_loop(systems.get("van_der_pol"))]
    ['-1*x2', '1*x1 -1*x2 +1*x1^2*x2']
    """
    cl = closed_loop(system, controller, strict=True)
    return expand_polynomials(ca.Function("cl", [cl.x], [cl.rhs]).expand())



#: degrees of :func:`fit_polynomial_model`, in the order tried
FIT_DEGREES = (1, 2, 3)
#: :func:`fit_polynomial_model` keeps the least degree whose residual is at most this
#: fraction of every component's root mean square on the grid
FIT_TOLERANCE = 1e-3
#: points of :func:`fit_polynomial_model`: a grid of ``round(FIT_POINTS^(1/n))`` per axis (at
#: least the highest degree + 1) while it holds at most ``4·FIT_POINTS`` points, else this
#: many seeded uniform points of the box (at least 20 per monomial)
FIT_POINTS = 20000


@dataclass(frozen=True)
class PolynomialFit:
    """A least-squares polynomial model of a vector field (:func:`fit_polynomial_model`).

    Attributes
    ----------
    polynomials : list of Polynomial
        One per state; no constant terms, so the model vanishes at the origin.
    degree : int
        The degree fitted.
    residual : float
        The largest, over the components, root mean square of the residual on the grid
        divided by the component's root mean square there.
    """

    polynomials: list
    degree: int
    residual: float

    @property
    def linear_part(self) -> np.ndarray:
        """The ``(n, n)`` matrix of the degree-1 coefficients (the model's Jacobian at 0)."""
        n = len(self.polynomials)
        A = np.zeros((n, n))
        for i, p in enumerate(self.polynomials):
            for j in range(n):
                A[i, j] = p.to_dict().get(_unit(n, j), 0.0)
        return A


def fit_polynomial_model(fun: ca.Function, box, *, degrees=FIT_DEGREES,
                         tol: float = FIT_TOLERANCE, points: int = FIT_POINTS) -> PolynomialFit:
    r"""A polynomial model of the vector field ``fun`` on ``box``, by least squares on a grid.

    Each degree ``d`` of ``degrees`` fits every component by the monomials of degree
    ``1..d`` (no constant term: the model vanishes at 0, as a closed loop at its equilibrium
    does); the first degree whose :attr:`PolynomialFit.residual` is at most ``tol`` is
    returned, else the last one. The model is a search model only (the SOS programs of a
    learned ``φ`` run on it): nothing claimed rests on it, so its error needs no bound.
    The fits run with one BLAS thread (the same bits whatever the machine's thread count).

    Parameters
    ----------
    fun : casadi.Function
        ``x -> f(x)``, ``n`` inputs and ``n`` outputs.
    box : (n, 2) array_like
        Where to fit (the grid's bounds).

    Returns
    -------
    PolynomialFit

    Examples
    --------
    >>> x = ca.SX.sym("x", 2)
    >>> fit = fit_polynomial_model(ca.Function("f", [x], [ca.vertcat(-x[1], x[0] - x[1]
    ...                            + x[0] ** 2 * x[1])]), [[-2, 2], [-2, 2]])
    >>> fit.degree, fit.residual < 1e-12
    (3, True)
    """
    box = np.asarray(box, dtype=float).reshape(-1, 2)
    n = len(box)
    k = max(max(degrees) + 1, int(round(points ** (1.0 / n))))
    if k ** n <= 4 * points:
        axes = [np.linspace(lo, hi, k) for lo, hi in box]
        X = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, n)
    else:       # many states: seeded points (a grid of k ≥ degree + 1 per axis is too large)
        m = max(points, 20 * len(monomials(n, 1, max(degrees))))
        X = np.random.default_rng(0).uniform(box[:, 0], box[:, 1], (m, n))
    F = np.asarray(fun.map(len(X))(X.T), dtype=float).reshape(n, -1).T
    if not np.all(np.isfinite(F)):
        raise ValueError("the vector field is not finite on the fit's grid")
    rms = np.sqrt(np.mean(F ** 2, axis=0))
    rms = np.where(rms > 0, rms, 1.0)
    fit = None
    with threadpool_limits(limits=1, user_api="blas"):
        for d in degrees:
            exps = monomials(n, 1, d)
            Z = monomial_matrix(X, exps)
            cn = np.linalg.norm(Z, axis=0)
            cn = np.where(cn > 0, cn, 1.0)
            C = np.linalg.lstsq(Z / cn, F, rcond=None)[0] / cn[:, None]
            res = float(np.max(np.sqrt(np.mean((F - Z @ C) ** 2, axis=0)) / rms))
            fit = PolynomialFit([Polynomial.from_dict(dict(zip(exps, C[:, i])), n)
                                 for i in range(n)], d, res)
            if res <= tol:
                break
    return fit

# --------------------------------------------------------------------------- exact rationals
def _qadd(p: dict, q: dict, sign: int = 1) -> dict:
    out = dict(p)
    for e, c in q.items():
        out[e] = out.get(e, Fraction(0)) + sign * c
    return {e: c for e, c in out.items() if c != 0}


def _qmul(p: dict, q: dict) -> dict:
    out: dict = {}
    for (e1, c1), (e2, c2) in itertools.product(p.items(), q.items()):
        e = _add_exponents(e1, e2)
        out[e] = out.get(e, Fraction(0)) + c1 * c2
    return {e: c for e, c in out.items() if c != 0}


class ExactPolynomialArithmetic(PolynomialArithmetic):
    """:class:`PolynomialArithmetic` in exact rational arithmetic (``fractions.Fraction``
    coefficients): every float constant of the graph is the rational it denotes, and
    every operation, constant ones included, is exact (``add``, ``sub``, ``mul``, ``neg``,
    ``sq``, ``twice``, ``assign``, ``div`` by a nonzero constant, integer ``pow``).
    Anything else -- a ``sin`` even of a constant -- is refused (``collect``: the value
    ``None``), so that a coefficient found zero is zero, not rounded to it.

    Examples
    --------
    >>> ar = ExactPolynomialArithmetic(1)
    >>> (x,) = ar.variables()
    >>> third = ar.binary(ca.OP_DIV, ar.constant(1.0), ar.constant(3.0))
    >>> ar.binary(ca.OP_SUB, ar.binary(ca.OP_MUL, x, third), ar.binary(ca.OP_MUL, third, x))
    {}
    """

    name = "exact polynomial"

    def variables(self) -> np.ndarray:
        xs = np.empty(self.nx, dtype=object)
        for i in range(self.nx):
            xs[i] = {_unit(self.nx, i): Fraction(1)}
        return xs

    def constant(self, value) -> dict:
        c = Fraction(float(value))
        return {self.zero: c} if c != 0 else {}

    def unary(self, op: int, a):
        if a is None:
            return None if op in POLYNOMIAL_OPS else self._refuse(op, "a non-polynomial")
        if op == ca.OP_NEG:
            return {e: -c for e, c in a.items()}
        if op == ca.OP_SQ:
            return _qmul(a, a)
        if op == ca.OP_TWICE:
            return {e: 2 * c for e, c in a.items()}
        if op == ca.OP_ASSIGN:
            return a
        return self._refuse(op, "an exact polynomial")

    def binary(self, op: int, a, b):
        ka = None if a is None else _constant_of(a)
        kb = None if b is None else _constant_of(b)
        if op == ca.OP_IF_ELSE_ZERO and ka is not None:
            return b if ka != 0 else {}
        allowed = (op in POLYNOMIAL_OPS
                   or (op == ca.OP_DIV and kb is not None and kb != 0)
                   or (op in (ca.OP_POW, ca.OP_CONSTPOW) and kb is not None
                       and kb.denominator == 1 and 0 <= kb <= _MAX_POWER))
        if a is None or b is None or not allowed:
            return None if allowed else self._refuse(op, "an exact polynomial")
        return _polynomial_op(op, a, b, kb, _qadd, _qmul, {self.zero: Fraction(1)})


def exact_polynomials(fun: ca.Function, args=None, nvars: int | None = None
                      ) -> list[dict] | None:
    """The outputs of an SX Function as exact polynomials (``{exponent: Fraction}``), or
    ``None`` when an operation is not exact-polynomial (:class:`ExactPolynomialArithmetic`).

    ``args``: the input as exact polynomials in ``nvars`` other variables (a sequence of
    dicts), substituted for it; default: the input's own variables.

    Examples
    --------
    >>> x = ca.SX.sym("x", 2)
    >>> exact_polynomials(ca.Function("f", [x], [x[0] * x[1] / 4 - x[1] * x[0] / 4]))
    [{}]
    """
    ar = ExactPolynomialArithmetic(fun.nnz_in(0) if args is None else int(nvars))
    xs = ar.variables() if args is None else np.array(list(args) + [None], dtype=object)[:-1]
    ar.collect = True
    outs = evaluate(fun, [xs], ar)[0]
    if any(p is None for p in outs):
        return None
    return [dict(p) for p in outs]
