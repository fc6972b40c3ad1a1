"""SMT-LIB 2 export (dReal dialect) of a falsification formula.

The text is written from the :class:`~verification.formula.Formula` of
:func:`~verification.formula.build_formula`, the same object the dReal backend consumes.
Every DAG node used more than once is bound once with ``let`` (bindings of equal depth share
one ``let``, so the nesting is the depth of the DAG, not its size); single-use nodes are
written inline. Constants are written as their *exact* decimal expansion (every float64 is
a finite decimal), so the formula is about the very function that was saved. Domain
conditions of partial operations are part of the formula (see :mod:`verification.formula`).
"""

from __future__ import annotations

import math
import re
import sys
from decimal import Decimal
from pathlib import Path

import numpy as np

from .formula import Formula, build_formula, topological
from .problem import VerificationProblem

__all__ = ["to_smtlib", "formula_to_smtlib", "evaluate_smtlib", "write_smtlib"]

_OPS = {"neg": "-", "=": "="}


def _num(v: float) -> str:
    if not math.isfinite(v):
        raise ValueError(f"cannot write non-finite constant {v} to SMT-LIB")
    d = format(Decimal(v).copy_abs(), "f")  # exact decimal expansion of the float64
    if "." not in d:
        d += ".0"
    return f"(- {d})" if v < 0 else d


def formula_to_smtlib(formula: Formula) -> str:
    """SMT-LIB 2 text of a :class:`~verification.formula.Formula` (``unsat``: verified)."""
    names = [v.value for v in formula.variables]
    for v in names:
        if re.fullmatch(r"t\d+", v):
            raise ValueError(f"variable name {v!r} clashes with the let-bound names t<k>")
    body = formula.body()
    order = topological([body])
    uses: dict[int, int] = {}
    for node in order:
        for a in node.args:
            uses[id(a)] = uses.get(id(a), 0) + 1
    text: dict[int, str] = {}
    level: dict[int, int] = {}  # let level a node's text needs (0: no binding inside)
    groups: list[list[tuple[str, str]]] = []
    for node in order:
        if node.op == "const":
            text[id(node)] = _num(node.value)
            level[id(node)] = 0
            continue
        if node.op == "var":
            text[id(node)] = node.value
            level[id(node)] = 0
            continue
        head = _OPS.get(node.op, node.op)
        s = "(" + head + " " + " ".join(text[id(a)] for a in node.args) + ")"
        lv = max((level[id(a)] for a in node.args), default=0)
        if uses.get(id(node), 0) > 1 and node is not body:
            while len(groups) <= lv:
                groups.append([])
            name = f"t{sum(map(len, groups))}"
            groups[lv].append((name, s))
            text[id(node)] = name
            level[id(node)] = lv + 1
        else:
            text[id(node)] = s
            level[id(node)] = lv
    lines = ["(set-logic QF_NRA)"]
    lines += [f"(declare-fun {v} () Real)" for v in names]
    for v, (lo, hi) in zip(names, formula.box):
        lines.append(f"(assert (<= {_num(float(lo))} {v}))")
        lines.append(f"(assert (<= {v} {_num(float(hi))}))")
    opened = "".join("(let (" + " ".join(f"({n} {s})" for n, s in g) + ")\n" for g in groups)
    lines.append("(assert " + opened + text[id(body)] + ")" * len(groups) + ")")
    lines += ["(check-sat)", "(exit)"]
    return "\n".join(lines) + "\n"


def to_smtlib(problem: VerificationProblem, *, var_names: list[str] | None = None) -> str:
    """SMT-LIB 2 text of the falsification formula of ``problem``.

    ``∃x ∈ box: g_i(x) ≤ 0 ∀i ∧ (∨_j p_j(x) ≥ 0 ∨ a partial operation undefined)`` —
    ``unsat`` means *verified*. Built by :func:`~verification.formula.build_formula`.
    """
    return formula_to_smtlib(build_formula(problem, var_names=var_names))


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
    "sqrt": np.sqrt, "exp": np.exp, "log": np.log, "sin": np.sin, "cos": np.cos,
    "tan": np.tan, "tanh": np.tanh, "atan": np.arctan, "abs": np.abs, "sinh": np.sinh,
    "cosh": np.cosh, "asin": np.arcsin, "acos": np.arccos,
}
_CMP = {"<=": np.less_equal, ">=": np.greater_equal, "<": np.less, ">": np.greater,
        "=": np.equal}


def _eval(node, env):
    if isinstance(node, str):
        return env[node] if node in env else np.float64(node)
    head = node[0]
    if head == "let":
        env = dict(env)
        for name, term in node[1]:
            env[name] = _eval(term, env)
        return _eval(node[2], env)
    if head == "ite":
        return _eval(node[2], env) if _eval(node[1], env) else _eval(node[3], env)
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
        return np.power(args[0], args[1])
    if head in ("min", "max"):
        return (min if head == "min" else max)(args)
    if head == "atan2":
        return np.arctan2(args[0], args[1])
    if head in _CMP:
        return bool(_CMP[head](*args))
    if head == "and":
        return all(args)
    if head == "or":
        return any(args)
    if head == "not":
        return not args[0]
    return _FUN[head](*args)


def evaluate_smtlib(text: str, point) -> tuple[bool, list[float]]:
    """Evaluate an exported formula at a point (float arithmetic; for tests and debugging).

    Returns the truth value of the final assertion (box bounds ignored) and the values of
    the formula's atoms in order: region terms ``g_i``, property terms ``p_j``, then the
    arguments of the domain-violation atoms (if any).
    """

    lines = [ln for ln in text.splitlines() if ln.startswith("(declare-fun")]
    names = [ln.split()[1] for ln in lines]
    env = {n: np.float64(v) for n, v in zip(names, point)}
    start = text.index("(assert (let") if "(assert (let" in text else text.rindex("(assert")
    end = text.index("(check-sat)")
    depth = run = 0
    for ch in text[start:end]:
        if ch == "(":
            run += 1
            depth = max(depth, run)
        elif ch == ")":
            run -= 1
    old = sys.getrecursionlimit()
    sys.setrecursionlimit(max(old, 4 * depth + 1000))
    try:
        tree, _ = _parse(_tokens(text[start:end]))
        node = tree[1]
        with np.errstate(all="ignore"):
            # unwind the let chain iteratively, then evaluate the body
            while isinstance(node, list) and node and node[0] == "let":
                for name, term in node[1]:
                    env[name] = _eval(term, env)
                node = node[2]
            atoms = [float(_eval(a[1], env)) for a in _atoms(node)]
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
