"""Hash-consed expression DAG of the formula builder (:mod:`verification.formula`).

:class:`TermTable` creates each structurally distinct :class:`Term` once and applies only
identities that are exact in real arithmetic (``x + 0``, ``x·1``, ``x·0``, ``−(−x)``,
``x − x``; constants folded only where the result is exactly a float64).
:func:`topological` orders a DAG; :func:`evaluate_terms` evaluates it in float64 (tests).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from fractions import Fraction

import numpy as np

__all__ = ["Term", "TermTable", "topological", "evaluate_terms", "BOOL_OPS", "FUNCTIONS"]

#: boolean-sorted operations of the DAG (comparisons of two reals, connectives)
BOOL_OPS = frozenset({"<=", "<", ">=", ">", "=", "and", "or", "not"})
#: real functions of one argument that dReal and SMT-LIB (dReal dialect) know by this name
FUNCTIONS = ("sqrt", "exp", "log", "sin", "cos", "tan", "tanh", "atan", "asin", "acos",
             "sinh", "cosh", "abs")


class Term:
    """A node of a hash-consed expression DAG (create through a :class:`TermTable`).

    Attributes
    ----------
    op : str
        ``"var"``, ``"const"``, ``"+"``, ``"-"`` (binary), ``"neg"``, ``"*"``, ``"/"``,
        ``"^"``, a function name (:data:`FUNCTIONS`), ``"atan2"``, ``"min"``, ``"max"``,
        ``"ite"`` (boolean, then, else) or a boolean op (:data:`BOOL_OPS`).
    args : tuple of Term
    value : float or str or None
        The float64 value of a constant, the name of a variable.
    size : int
        Nodes of the expanded tree (each use of a shared node counted again).
    """

    __slots__ = ("op", "args", "value", "size")

    def __init__(self, op: str, args: tuple = (), value=None):
        self.op = op
        self.args = args
        self.value = value
        self.size = 1 + sum(a.size for a in args)

    @property
    def is_const(self) -> bool:
        return self.op == "const"

    @property
    def is_bool(self) -> bool:
        return self.op in BOOL_OPS

    def __repr__(self) -> str:
        if self.op == "const":
            return repr(self.value)
        if self.op == "var":
            return str(self.value)
        return f"({self.op} {' '.join(map(repr, self.args))})"


def _exact(v: Fraction) -> float | None:
    """``v`` as a float64 if that is exact, else None."""
    try:
        f = float(v)
    except OverflowError:
        return None
    return f if math.isfinite(f) and Fraction(f) == v else None


class TermTable:
    """Creates :class:`Term` nodes, each structurally distinct node once (hash-consing).

    The constructors apply only identities that are exact in real arithmetic (see the
    module docstring); they never round.
    """

    def __init__(self):
        self._nodes: dict[tuple, Term] = {}
        self.zero = self.const(0.0)
        self.one = self.const(1.0)

    def __len__(self) -> int:
        return len(self._nodes)

    def _mk(self, op: str, args: tuple = (), value=None) -> Term:
        key = (op, tuple(id(a) for a in args), value)
        t = self._nodes.get(key)
        if t is None:
            t = self._nodes[key] = Term(op, args, value)
        return t

    # ------------------------------------------------------------------ leaves
    def var(self, name: str) -> Term:
        return self._mk("var", (), str(name))

    def const(self, value: float) -> Term:
        v = float(value)
        if not math.isfinite(v):
            raise ValueError(f"a formula constant must be finite, got {v}")
        return self._mk("const", (), 0.0 if v == 0 else v)  # -0.0 and 0.0 are one real

    def _fold(self, a: Term, b: Term, fn) -> Term | None:
        if a.is_const and b.is_const:
            v = _exact(fn(Fraction(a.value), Fraction(b.value)))
            if v is not None:
                return self.const(v)
        return None

    # ------------------------------------------------------------------ arithmetic
    def add(self, a: Term, b: Term) -> Term:
        if a is self.zero:
            return b
        if b is self.zero:
            return a
        if b.op == "neg":
            return self.sub(a, b.args[0])
        return self._fold(a, b, lambda p, q: p + q) or self._mk("+", (a, b))

    def sub(self, a: Term, b: Term) -> Term:
        if b is self.zero:
            return a
        if a is self.zero:
            return self.neg(b)
        if a is b:
            return self.zero
        if b.op == "neg":
            return self.add(a, b.args[0])
        return self._fold(a, b, lambda p, q: p - q) or self._mk("-", (a, b))

    def neg(self, a: Term) -> Term:
        if a.op == "neg":
            return a.args[0]
        if a.is_const:
            return self.const(-a.value)
        return self._mk("neg", (a,))

    def mul(self, a: Term, b: Term) -> Term:
        if b.is_const and not a.is_const:  # constants first: c·x
            a, b = b, a
        if a is self.zero or b is self.zero:
            return self.zero
        if a is self.one:
            return b
        if b is self.one:
            return a
        if a.is_const and a.value == -1.0:
            return self.neg(b)
        if a.is_const and b.op == "neg":
            return self.mul(self.const(-a.value), b.args[0])
        return self._fold(a, b, lambda p, q: p * q) or self._mk("*", (a, b))

    def div(self, a: Term, b: Term) -> Term:
        if b is self.one:
            return a
        if a is self.zero:
            return self.zero
        if b.is_const and b.value != 0:
            return self._fold(a, b, lambda p, q: p / q) or self._mk("/", (a, b))
        return self._mk("/", (a, b))

    def pow(self, a: Term, e: Term) -> Term:
        if e.is_const and e.value == 1.0:
            return a
        if e is self.zero:
            return self.one
        return self._mk("^", (a, e))

    def fn(self, name: str, a: Term) -> Term:
        if name not in FUNCTIONS:
            raise ValueError(f"unknown function {name!r}")
        if name == "abs" and a.is_const:
            return self.const(abs(a.value))
        return self._mk(name, (a,))

    def op2(self, name: str, a: Term, b: Term) -> Term:
        if name not in ("atan2", "min", "max"):
            raise ValueError(f"unknown binary function {name!r}")
        if name in ("min", "max") and a is b:
            return a
        return self._mk(name, (a, b))

    def ite(self, c: Term, a: Term, b: Term) -> Term:
        if a is b:
            return a
        return self._mk("ite", (c, a, b))

    # ------------------------------------------------------------------ booleans
    def cmp(self, op: str, a: Term, b: Term) -> Term:
        if op not in ("<=", "<", ">=", ">", "="):
            raise ValueError(f"unknown comparison {op!r}")
        return self._mk(op, (a, b))

    def and_(self, *xs: Term) -> Term:
        xs = tuple(xs)
        return xs[0] if len(xs) == 1 else self._mk("and", xs)

    def or_(self, *xs: Term) -> Term:
        xs = tuple(xs)
        return xs[0] if len(xs) == 1 else self._mk("or", xs)

    def not_(self, a: Term) -> Term:
        return self._mk("not", (a,))


def topological(roots: Iterable[Term]) -> list[Term]:
    """Every node reachable from ``roots`` once, each after its arguments (iterative)."""
    order: list[Term] = []
    done: set[int] = set()
    for root in roots:
        if id(root) in done:
            continue
        stack = [(root, False)]
        while stack:
            node, expanded = stack.pop()
            if id(node) in done:
                continue
            if expanded:
                done.add(id(node))
                order.append(node)
                continue
            stack.append((node, True))
            for a in reversed(node.args):
                if id(a) not in done:
                    stack.append((a, False))
    return order


_NP_FUN = {
    "sqrt": np.sqrt, "exp": np.exp, "log": np.log, "sin": np.sin, "cos": np.cos,
    "tan": np.tan, "tanh": np.tanh, "atan": np.arctan, "asin": np.arcsin,
    "acos": np.arccos, "sinh": np.sinh, "cosh": np.cosh, "abs": np.abs,
}
_NP_OP = {
    "+": np.add, "-": np.subtract, "*": np.multiply, "/": np.divide, "^": np.power,
    "atan2": np.arctan2, "min": np.minimum, "max": np.maximum, "<=": np.less_equal,
    "<": np.less, ">=": np.greater_equal, ">": np.greater, "=": np.equal,
}


def evaluate_terms(roots: Sequence[Term], env: dict, n: int) -> dict[int, np.ndarray]:
    """Float64 values of every node under ``roots`` (keyed by ``id``), variables from ``env``."""
    val: dict[int, np.ndarray] = {}
    with np.errstate(all="ignore"):
        for node in topological(roots):
            a = [val[id(x)] for x in node.args]
            op = node.op
            if op == "const":
                r = np.full(n, node.value)
            elif op == "var":
                r = np.asarray(env[node.value], dtype=float)
            elif op == "neg":
                r = -a[0]
            elif op in _NP_FUN:
                r = _NP_FUN[op](a[0])
            elif op in _NP_OP:
                r = _NP_OP[op](a[0], a[1])
            elif op == "and":
                r = np.logical_and.reduce(a)
            elif op == "or":
                r = np.logical_or.reduce(a)
            elif op == "not":
                r = ~a[0]
            elif op == "ite":
                r = np.where(a[0], a[1], a[2])
            else:  # pragma: no cover - every op of TermTable is listed above
                raise ValueError(f"cannot evaluate op {op!r}")
            val[id(node)] = r
    return val
