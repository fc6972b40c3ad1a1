"""Verifier backends behind one base class, in a registry (``BACKENDS``)."""

from __future__ import annotations

import importlib
import time

import casadi as ca
import numpy as np

from nlyap_opt.errors import BackendUnavailableError, UnknownNameError
from nlyap_opt.walker import _unsupported, compile_function, evaluate

from .problem import VerificationProblem, VerificationResult
from .verify import confirm_points, verify_interval

__all__ = ["Backend", "IntervalBackend", "DrealBackend", "BACKENDS", "get_backend"]


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


class DrealArithmetic:
    """Walker arithmetic producing dReal expressions (on the SX expansion)."""

    name = "dreal"
    symbolic = True

    def __init__(self, dreal):
        self.d = dreal
        d = dreal
        self._unary = {
            ca.OP_NEG: lambda a: -a, ca.OP_SQ: lambda a: a * a, ca.OP_TWICE: lambda a: 2 * a,
            ca.OP_SQRT: d.sqrt, ca.OP_EXP: d.exp, ca.OP_LOG: d.log, ca.OP_SIN: d.sin,
            ca.OP_COS: d.cos, ca.OP_TAN: d.tan, ca.OP_TANH: d.tanh, ca.OP_ATAN: d.atan,
            ca.OP_FABS: abs, ca.OP_INV: lambda a: 1 / a, ca.OP_ASSIGN: lambda a: a,
            ca.OP_SINH: d.sinh, ca.OP_COSH: d.cosh,
        }
        self._binary = {
            ca.OP_ADD: lambda a, b: a + b, ca.OP_SUB: lambda a, b: a - b,
            ca.OP_MUL: lambda a, b: a * b, ca.OP_DIV: lambda a, b: a / b,
            ca.OP_POW: lambda a, b: a**b, ca.OP_CONSTPOW: lambda a, b: a**b,
            ca.OP_FMIN: d.Min, ca.OP_FMAX: d.Max,
        }

    def constant(self, value):
        return float(np.asarray(value, dtype=float))

    def unary(self, op, a):
        if op not in self._unary:
            raise _unsupported(op, self.name, list(self._unary))
        return self._unary[op](a)

    def binary(self, op, a, b):
        if op not in self._binary:
            raise _unsupported(op, self.name, list(self._binary))
        return self._binary[op](a, b)

    def structural(self, fn, *args):
        return fn(*args)


class DrealBackend(Backend):
    """dReal 4 (optional): ``CheckSatisfiability(formula, δ)``.

    ``unsat`` proves the property (verified). A δ-SAT box is *not* a counterexample
    (PITFALLS P7): its points are re-checked rigorously with the interval arithmetic, and
    the result is ``counterexample`` only if one is confirmed, else ``unknown``.
    """

    name = "dreal"
    install_hint = ("dReal is optional and not installable from the registries here; "
                    "install it with `pip install dreal` where a libibex is available, "
                    "or export SMT-LIB with verification.to_smtlib and run the dReal binary")

    @classmethod
    def is_available(cls) -> bool:
        return importlib.util.find_spec("dreal") is not None

    def verify(self, problem, *, precision: float = 1e-3, **options):
        if not self.is_available():
            raise BackendUnavailableError(f"the 'dreal' backend needs dreal: {self.install_hint}")
        import dreal

        t0 = time.perf_counter()
        fun = problem.function.expand() if problem.function.is_a("MXFunction") \
            else problem.function
        xs = [dreal.Variable(f"x{i}") for i in range(problem.n)]
        ar = DrealArithmetic(dreal)
        terms = evaluate(compile_function(fun), [np.array(xs, dtype=object)], ar)[0]
        m = problem.n_constraints
        parts = [v >= float(lo) for v, lo in zip(xs, problem.box[:, 0])]
        parts += [v <= float(hi) for v, hi in zip(xs, problem.box[:, 1])]
        parts += [t <= 0 for t in terms[:m]]
        viol = dreal.Or(*[t >= 0 for t in terms[m:]]) if len(terms) - m > 1 \
            else terms[m] >= 0
        formula = dreal.And(*parts, viol)
        box = dreal.CheckSatisfiability(formula, precision)
        seconds = time.perf_counter() - t0
        if box is None:
            return VerificationResult("verified", seconds=seconds, backend="dreal")
        lo = np.array([box[v].lb() for v in xs])
        hi = np.array([box[v].ub() for v in xs])
        rng = np.random.default_rng(0)
        cands = np.vstack([0.5 * (lo + hi), lo + (hi - lo) * rng.random((64, problem.n))])
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
