"""SMT-LIB 2 export (dReal dialect) of a falsification formula, through the walker.

The SX expansion of the problem Function is walked with :class:`SmtArithmetic`, which
emits one ``let`` binding per instruction (a 2-64-64-1 Lie derivative is ~22 k
instructions, while its fully expanded term is millions of characters). Constants are
written as their *exact* decimal expansion (every float64 is a finite decimal), so the
formula is about the very function that was saved.
"""

from __future__ import annotations

import math
from decimal import Decimal
from pathlib import Path

import casadi as ca
import numpy as np

from nlyap_opt.walker import _unsupported, compile_function, evaluate

from .problem import VerificationProblem

__all__ = ["SmtArithmetic", "to_smtlib", "evaluate_smtlib", "write_smtlib"]

_UNARY = {
    ca.OP_NEG: "-", ca.OP_SQRT: "sqrt", ca.OP_EXP: "exp", ca.OP_LOG: "log", ca.OP_SIN: "sin",
    ca.OP_COS: "cos", ca.OP_TAN: "tan", ca.OP_TANH: "tanh", ca.OP_ATAN: "atan",
    ca.OP_FABS: "abs", ca.OP_SINH: "sinh", ca.OP_COSH: "cosh", ca.OP_ASIN: "asin",
    ca.OP_ACOS: "acos",
}
_BINARY = {
    ca.OP_ADD: "+", ca.OP_SUB: "-", ca.OP_MUL: "*", ca.OP_DIV: "/", ca.OP_POW: "^",
    ca.OP_CONSTPOW: "^", ca.OP_FMIN: "min", ca.OP_FMAX: "max", ca.OP_ATAN2: "atan2",
}


def _num(v: float) -> str:
    if not math.isfinite(v):
        raise ValueError(f"cannot write non-finite constant {v} to SMT-LIB")
    d = format(Decimal(v).copy_abs(), "f")  # exact decimal expansion of the float64
    if "." not in d:
        d += ".0"
    return f"(- {d})" if v < 0 else d


class SmtArithmetic:
    """Walker arithmetic whose values are SMT-LIB term names; it records the bindings."""

    name = "smtlib"
    symbolic = True

    def __init__(self):
        self.bindings: list[tuple[str, str]] = []

    def _bind(self, term: str) -> str:
        name = f"t{len(self.bindings)}"
        self.bindings.append((name, term))
        return name

    def constant(self, value):
        v = np.asarray(value, dtype=float)
        if v.ndim:
            raise ValueError("SMT-LIB export walks the SX expansion (scalar registers only)")
        return _num(float(v))

    def unary(self, op, a):
        if op == ca.OP_SQ:
            return self._bind(f"(* {a} {a})")
        if op == ca.OP_TWICE:
            return self._bind(f"(* 2.0 {a})")
        if op == ca.OP_INV:
            return self._bind(f"(/ 1.0 {a})")
        if op == ca.OP_ASSIGN:
            return a
        if op not in _UNARY:
            raise _unsupported(op, self.name, list(_UNARY) + [ca.OP_SQ, ca.OP_TWICE, ca.OP_INV])
        return self._bind(f"({_UNARY[op]} {a})")

    def binary(self, op, a, b):
        if op not in _BINARY:
            raise _unsupported(op, self.name, list(_BINARY))
        return self._bind(f"({_BINARY[op]} {a} {b})")

    def structural(self, fn, *args):
        return fn(*args)


def _sx_terms(problem: VerificationProblem, names: list[str]):
    fun = problem.function.expand() if problem.function.is_a("MXFunction") \
        else problem.function
    ar = SmtArithmetic()
    x = np.array(names, dtype=object)
    out = evaluate(compile_function(fun), [x], ar)[0]
    return ar, list(out)


def to_smtlib(problem: VerificationProblem, *, var_names: list[str] | None = None) -> str:
    """SMT-LIB 2 text of the falsification formula of ``problem``.

    ``∃x ∈ box: g_i(x) ≤ 0 ∀i ∧ ∨_j p_j(x) ≥ 0`` — ``unsat`` means *verified*.
    """
    names = var_names or [f"x{i}" for i in range(problem.n)]
    ar, terms = _sx_terms(problem, names)
    m = problem.n_constraints
    lines = ["(set-logic QF_NRA)"]
    lines += [f"(declare-fun {v} () Real)" for v in names]
    for v, (lo, hi) in zip(names, problem.box):
        lines.append(f"(assert (<= {_num(float(lo))} {v}))")
        lines.append(f"(assert (<= {v} {_num(float(hi))}))")
    region = [f"(<= {t} 0.0)" for t in terms[:m]]
    viol = [f"(>= {t} 0.0)" for t in terms[m:]]
    body = "(and " + " ".join(region + ["(or " + " ".join(viol) + ")"]) + ")" \
        if region else "(or " + " ".join(viol) + ")"
    opened = "".join(f"(let (({n} {t}))\n" for n, t in ar.bindings)
    lines.append("(assert " + opened + body + ")" * len(ar.bindings) + ")")
    lines += ["(check-sat)", "(exit)"]
    return "\n".join(lines) + "\n"


def write_smtlib(problem: VerificationProblem, path: str | Path) -> Path:
    """Write :func:`to_smtlib` to ``path``."""
    path = Path(path)
    path.write_text(to_smtlib(problem))
    return path


# --------------------------------------------------------------------------- reader (checks)
def _tokens(text: str):
    return text.replace("(", " ( ").replace(")", " ) ").split()


def _parse(tokens, i=0):
    if tokens[i] == "(":
        out = []
        i += 1
        while tokens[i] != ")":
            node, i = _parse(tokens, i)
            out.append(node)
        return out, i + 1
    return tokens[i], i + 1


_FUN = {
    "sqrt": math.sqrt, "exp": math.exp, "log": math.log, "sin": math.sin, "cos": math.cos,
    "tan": math.tan, "tanh": math.tanh, "atan": math.atan, "abs": abs, "sinh": math.sinh,
    "cosh": math.cosh, "asin": math.asin, "acos": math.acos,
}


def _eval(node, env):
    if isinstance(node, str):
        return env[node] if node in env else float(node)
    head = node[0]
    if head == "let":
        env = dict(env)
        for name, term in node[1]:
            env[name] = _eval(term, env)
        return _eval(node[2], env)
    args = [_eval(a, env) for a in node[1:]]
    if head == "+":
        return sum(args)
    if head == "-":
        return -args[0] if len(args) == 1 else args[0] - sum(args[1:])
    if head == "*":
        return math.prod(args)
    if head == "/":
        return args[0] / args[1]
    if head == "^":
        return args[0] ** args[1]
    if head in ("min", "max"):
        return (min if head == "min" else max)(args)
    if head == "atan2":
        return math.atan2(args[0], args[1])
    if head in ("<=", ">=", "<", ">"):
        a, b = args
        return {"<=": a <= b, ">=": a >= b, "<": a < b, ">": a > b}[head]
    if head == "and":
        return all(args)
    if head == "or":
        return any(args)
    return _FUN[head](*args)


def evaluate_smtlib(text: str, point) -> tuple[bool, list[float]]:
    """Evaluate an exported formula at a point (float arithmetic; for tests and debugging).

    Returns the truth value of the final assertion (box bounds ignored) and the values of
    the formula's atoms in order (region terms, then properties).
    """
    import sys

    lines = [ln for ln in text.splitlines() if ln.startswith("(declare-fun")]
    names = [ln.split()[1] for ln in lines]
    env = {n: float(v) for n, v in zip(names, point)}
    start = text.index("(assert (let") if "(assert (let" in text else text.rindex("(assert")
    end = text.index("(check-sat)")
    old = sys.getrecursionlimit()
    sys.setrecursionlimit(max(old, 20 * len(text.split("(let")) + 1000))
    try:
        tree, _ = _parse(_tokens(text[start:end]))
        node = tree[1]
        # unwind the let chain iteratively, then evaluate the body
        while isinstance(node, list) and node and node[0] == "let":
            for name, term in node[1]:
                env[name] = _eval(term, env)
            node = node[2]
        atoms = [_eval(a[1], env) for a in _atoms(node)]
        return bool(_eval(node, env)), atoms
    finally:
        sys.setrecursionlimit(old)


def _atoms(node):
    if isinstance(node, list) and node and node[0] in ("and", "or"):
        out = []
        for a in node[1:]:
            out += _atoms(a)
        return out
    return [node]
