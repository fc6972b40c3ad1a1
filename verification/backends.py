"""Verifier backends behind one base class, in a registry (``BACKENDS``)."""

from __future__ import annotations

import importlib.util
import time

import numpy as np

from nlyap_opt.kernel import deps
from nlyap_opt.kernel.errors import (
    BackendUnavailableError,
    UnknownNameError,
    UnsupportedOperationError,
)

from .formula import Formula, build_formula, topological
from .problem import VerificationProblem, VerificationResult
from .verify import confirm_points, verify_interval

__all__ = [
    "Backend", "IntervalBackend", "DrealBackend", "BACKENDS", "get_backend", "formula_to_dreal",
]


class Backend:
    """A verifier backend: ``name``, ``is_available()``, ``verify(problem, **options)``."""

    name = "base"
    install_hint = ""

    @classmethod
    def is_available(cls) -> bool:
        return True

    def verify(self, problem: VerificationProblem, **options) -> VerificationResult:
        raise NotImplementedError


class IntervalBackend(Backend):
    """Built-in sound interval branch-and-prune (default)."""

    name = "interval"

    def verify(self, problem, **options):
        return verify_interval(problem, **options)


def formula_to_dreal(formula: Formula, dreal) -> tuple[list, object]:
    """dReal variables and formula of ``formula.falsification()`` (``unsat``: verified).

    One dReal object per DAG node: a node used many times is the *same* Python
    ``Expression`` at every use (dReal's terms share it in memory).

    Parameters
    ----------
    formula : verification.formula.Formula
    dreal : module
        The imported ``dreal`` module (passed in: it is imported only when the backend runs).

    Returns
    -------
    (list of dreal.Variable, dreal.Formula)
    """
    d = dreal
    fun = {"sqrt": d.sqrt, "exp": d.exp, "log": d.log, "sin": d.sin, "cos": d.cos,
           "tan": d.tan, "tanh": d.tanh, "atan": d.atan, "asin": d.asin, "acos": d.acos,
           "sinh": d.sinh, "cosh": d.cosh, "abs": abs}
    op2 = {"+": lambda a, b: a + b, "-": lambda a, b: a - b, "*": lambda a, b: a * b,
           "/": lambda a, b: a / b, "^": lambda a, b: a**b, "atan2": d.atan2, "min": d.Min,
           "max": d.Max, "<=": lambda a, b: a <= b, "<": lambda a, b: a < b,
           ">=": lambda a, b: a >= b, ">": lambda a, b: a > b, "=": lambda a, b: a == b}

    def conn(f):
        return lambda *xs: xs[0] if len(xs) == 1 else f(*xs)

    nary = {"and": conn(d.And), "or": conn(d.Or)}
    xs = [d.Variable(v.value) for v in formula.variables]
    by_name = {v.value: x for v, x in zip(formula.variables, xs)}
    root = formula.falsification()
    val: dict[int, object] = {}
    for node in topological([root]):
        a = [val[id(x)] for x in node.args]
        op = node.op
        if op == "const":
            r = d.Expression(node.value)
        elif op == "var":
            r = by_name[node.value]
        elif op == "neg":
            r = -a[0]
        elif op in fun:
            r = fun[op](a[0])
        elif op in op2:
            r = op2[op](a[0], a[1])
        elif op in nary:
            r = nary[op](*a)
        elif op == "not":
            r = d.Not(a[0])
        elif op == "ite":
            r = d.if_then_else(a[0], a[1], a[2])
        else:  # pragma: no cover - TermTable creates no other op
            raise UnsupportedOperationError(f"formula op {op!r} has no dReal counterpart")
        val[id(node)] = r
    return xs, val[id(root)]


class DrealBackend(Backend):
    """dReal 4 (optional): ``CheckSatisfiability(formula, δ)``.

    The formula is :func:`~verification.formula.build_formula`'s, the one the SMT-LIB export
    writes (domain conditions of partial operations included). ``unsat`` proves the property
    (verified). A δ-SAT box is *not* a counterexample (dReal's δ-SAT only says that a
    δ-weakening holds): points of the box (clipped to the root box) are re-checked
    rigorously with the interval arithmetic, and
    the result is ``counterexample`` only if one is confirmed, else ``unknown``.

    Constants reach dReal as the graph's float64 values; dReal's ``Expression`` folds
    constant subterms (products of weights) in double precision, as its SMT-LIB reader does.
    """

    name = "dreal"
    install_hint = ("dReal is optional and not installable from the registries here; "
                    "install it with `pip install dreal` where a libibex is available, "
                    "or export SMT-LIB with verification.to_smtlib and run the dReal binary")

    @classmethod
    def is_available(cls) -> bool:
        try:
            return importlib.util.find_spec("dreal") is not None
        except (ImportError, ValueError):
            return False

    def verify(self, problem, *, precision: float = 1e-3, samples: int = 256, **options):
        """Decide ``problem`` with dReal at δ = ``precision``.

        ``samples`` random points of a δ-SAT box (plus its centre and corners) are checked
        rigorously; ``counterexample`` only for a confirmed one.
        """
        if options:
            raise UnknownNameError(f"unknown dReal backend option(s) {', '.join(options)}; "
                                   "available: precision, samples")
        if not self.is_available():
            raise BackendUnavailableError(f"the 'dreal' backend needs dreal: {self.install_hint}")
        dreal = deps.dreal()

        t0 = time.perf_counter()
        xs, formula = formula_to_dreal(build_formula(problem), dreal)
        box = dreal.CheckSatisfiability(formula, precision)
        if box is None:
            return VerificationResult("verified", seconds=time.perf_counter() - t0,
                                      backend="dreal")
        lo = np.array([box[v].lb() for v in xs], dtype=float)
        hi = np.array([box[v].ub() for v in xs], dtype=float)
        rng = np.random.default_rng(0)
        cands = np.vstack([0.5 * (lo + hi), lo, hi,
                           lo + (hi - lo) * rng.random((samples, problem.n))])
        cands = np.clip(cands, problem.box[:, 0], problem.box[:, 1])
        found = confirm_points(problem, cands)
        if found:
            return VerificationResult("counterexample", found[0], found,
                                      seconds=time.perf_counter() - t0, backend="dreal")
        return VerificationResult("unknown", undecided=np.stack([lo, hi], -1)[None],
                                  seconds=time.perf_counter() - t0, backend="dreal")


BACKENDS: dict[str, type[Backend]] = {"interval": IntervalBackend, "dreal": DrealBackend}


def get_backend(name: str) -> Backend:
    """Instantiate the backend ``name``; unknown or unavailable names say what exists."""
    try:
        cls = BACKENDS[name]
    except KeyError:
        raise UnknownNameError(
            f"unknown verifier backend {name!r}; available: {', '.join(BACKENDS)}"
        ) from None
    if not cls.is_available():
        raise BackendUnavailableError(f"backend {name!r} is not installed: {cls.install_hint}")
    return cls()
