r"""System spec files (TOML): a system without writing Python, parsed safely.

A spec file gives a system in one of three ways: the right-hand side as expression strings
(a CasADi model), a sample file (``[samples]``), or a Python factory (``factory =
"module:function"``, imported only because the file names it). Example::

    name = "pendulum"
    states = ["theta", "omega"]
    inputs = ["torque"]                 # leave out for an autonomous system
    state_box = [[-4, 4], [-4, 4]]
    input_box = [[-20, 20]]
    u_eq = [0.0]                        # optional for expressions (solved), else required
    known = ["theta"]                   # states whose derivative is known exactly
    # subsystems = [["x1", "x2"], ["x3", "x4"]]  # an interconnected system's parts (no inputs)

    [parameters]                        # numbers, or expressions of earlier parameters
    m = 0.15
    l = 0.5

    [rhs]                               # one expression per state
    theta = "omega"
    omega = "(m*9.81*l*sin(theta) + torque - 0.1*omega) / (m*l^2)"

    [declared]                          # assumptions, listed verbatim in the certificate
    lipschitz = 120.0                   # K_f, or one number per state
    hessian = 80.0                      # H: |∂²f_k/∂z_i∂z_j| <= H (or one per state)
    input_matrix = [[0.0], [26.666666666666668]]  # control-affine f = f0(x) + B u
    sample_error = 1e-6                 # data within 1e-6 of f (2-norm); default: exact
    depends_on = { omega = ["theta", "omega", "torque"] }  # f_k reads only these variables

    [run]                               # run-config overrides, passed on as a dict
    outer = 4.0

With ``[samples]`` (``file``, relative to the spec file; optional ``columns`` for a csv
without header) the ``[rhs]`` table may give only the ``known`` components. With
``factory`` the factory returns the :class:`~systems.base.System`; the spec adds
``[declared]`` and ``[run]``. A ``factory`` of the form ``"file.py:function"`` is loaded
from that file (relative to the spec); ``"package.module:function"`` is imported.

Expressions are parsed with :mod:`ast` (never ``eval``) into a whitelisted tree — numbers,
the declared symbols and parameters, ``+ - * / ** ^``, unary minus and the functions
:data:`FUNCTIONS` — built as a SymPy expression and converted to CasADi SX node by node
(:data:`SYMPY_TO_CASADI`). (SymPy's own ``parse_expr`` calls ``eval`` and is not used.)
Every error is one line naming the file, the entry and the problem.
"""

from __future__ import annotations

import ast
import difflib
import importlib
import importlib.util
import inspect
import keyword
import math
import sys
import unicodedata
from collections.abc import Callable
from pathlib import Path

import casadi as ca
import numpy as np
import sympy
import tomllib

from nlyap_opt.kernel.errors import ConfigError
from nlyap_opt.kernel.jsonio import read_file_bytes
from nlyap_opt.kernel.rounding import EPS
from nlyap_opt.kernel.walker import OP_TABLE

from .base import System, user_code
from .declarations import Declarations, check_declarations
from .samples import load_samples, sample_function

__all__ = ["load_spec", "check_spec", "parse_expression", "to_casadi", "default_run_settings",
           "centre_dimension",
           "unstable_modes", "unstable_origin", "FUNCTIONS", "ITERATIONS_3D",
           "SYMPY_TO_CASADI", "SPEC_KEYS"]

#: allowed function names -> (SymPy function, number of arguments; None: two or more)
FUNCTIONS: dict[str, tuple[Callable, int | None]] = {
    "sin": (sympy.sin, 1), "cos": (sympy.cos, 1), "tan": (sympy.tan, 1),
    "asin": (sympy.asin, 1), "acos": (sympy.acos, 1), "atan": (sympy.atan, 1),
    "atan2": (sympy.atan2, 2), "sinh": (sympy.sinh, 1), "cosh": (sympy.cosh, 1),
    "tanh": (sympy.tanh, 1), "exp": (sympy.exp, 1), "log": (sympy.log, 1),
    "sqrt": (sympy.sqrt, 1), "abs": (sympy.Abs, 1), "sign": (sympy.sign, 1),
    "min": (sympy.Min, None), "max": (sympy.Max, None), "pow": (sympy.Pow, 2),
}
#: allowed constants
CONSTANTS = {"pi": sympy.pi}

#: keys of a spec file: top level and tables
SPEC_KEYS = {
    "": {"name", "description", "states", "inputs", "state_box", "input_box", "u_eq", "known",
         "parameters", "rhs", "samples", "factory", "declared", "run", "subsystems"},
    "samples": {"file", "columns"},
    "declared": {"lipschitz", "hessian", "input_matrix", "sample_error", "depends_on"},
}


def _fold(op):
    def f(*args):
        out = args[0]
        for a in args[1:]:
            out = op(out, a)
        return out
    return f


def _pow(base, exp, node):
    e = node.exp
    if e == sympy.Rational(1, 2):
        return ca.sqrt(base)
    if e == -1:
        return 1.0 / base
    if e.is_Integer:
        return base ** int(e)
    return base ** exp


#: SymPy node type -> CasADi builder ``(converted args..., node) -> SX``
SYMPY_TO_CASADI: dict[type, Callable] = {
    sympy.Add: lambda *a: _fold(lambda p, q: p + q)(*a[:-1]),
    sympy.Mul: lambda *a: _fold(lambda p, q: p * q)(*a[:-1]),
    sympy.Pow: _pow,
    sympy.sin: lambda a, n: ca.sin(a), sympy.cos: lambda a, n: ca.cos(a),
    sympy.tan: lambda a, n: ca.tan(a), sympy.asin: lambda a, n: ca.asin(a),
    sympy.acos: lambda a, n: ca.acos(a), sympy.atan: lambda a, n: ca.atan(a),
    sympy.atan2: lambda y, x, n: ca.atan2(y, x), sympy.sinh: lambda a, n: ca.sinh(a),
    sympy.cosh: lambda a, n: ca.cosh(a), sympy.tanh: lambda a, n: ca.tanh(a),
    sympy.exp: lambda a, n: ca.exp(a), sympy.log: lambda a, n: ca.log(a),
    sympy.Abs: lambda a, n: ca.fabs(a), sympy.sign: lambda a, n: ca.sign(a),
    sympy.Min: lambda *a: _fold(ca.fmin)(*a[:-1]),
    sympy.Max: lambda *a: _fold(ca.fmax)(*a[:-1]),
}


class _ExprError(Exception):
    """A problem in one expression (turned into a one-line ConfigError with its location)."""


def _did_you_mean(name: str, options) -> str:
    m = difflib.get_close_matches(name, sorted(options), n=1, cutoff=0.5)
    return f"; did you mean {m[0]!r}?" if m else ""


# ============================================================================ parsing
def parse_expression(text: str, symbols: dict[str, sympy.Expr]) -> sympy.Expr:
    """Parse one expression string into SymPy, allowing only whitelisted constructs.

    Parameters
    ----------
    text : str
        E.g. ``"(m*g*l*sin(theta) + u - b*omega) / (m*l^2)"``; ``^`` is a power.
    symbols : dict
        The names allowed (states, inputs, parameters) and what they stand for.

    Returns
    -------
    sympy.Expr

    Raises
    ------
    ConfigError
        Syntax error, unknown symbol, disallowed function or construct (one line).

    Examples
    --------
    >>> x = sympy.Symbol("x", real=True)
    >>> parse_expression("2*sin(x)^2", {"x": x})
    2*sin(x)**2
    """
    try:
        return _parse(text, symbols)
    except _ExprError as exc:
        raise ConfigError(str(exc)) from None


def _too_deep(text) -> _ExprError:
    return _ExprError(f"is too long or nested too deeply to parse ({len(str(text))} "
                      "characters; a sum of thousands of terms is as deep as thousands of "
                      "parentheses); split it with parameters or simplify it")


def _parse(text: str, symbols: dict) -> sympy.Expr:
    # evaluate(False): the tree stays as written (no rewriting such as exp(log(x)) -> x,
    # which would change the domain the verifier checks)
    try:
        with sympy.evaluate(False):
            return _parse_unevaluated(text, symbols)
    except (RecursionError, MemoryError):
        raise _too_deep(text) from None


def _parse_unevaluated(text: str, symbols: dict) -> sympy.Expr:
    if not isinstance(text, str):
        raise _ExprError(f"must be a string expression, got {type(text).__name__} {text!r}")
    if not text.strip():
        raise _ExprError("is empty; write an expression such as \"-x1 + u\"")
    text = text.strip()
    # '^' is a power, as in maths (Python's '^' would bind looser than '+'): parse the text
    # with '**' in its place and report columns of the text as written
    src = text.replace("^", "**")
    try:
        tree = ast.parse(src, mode="eval")
    except SyntaxError as exc:
        if "too many nested" in str(exc.msg):   # the parser's own depth limit
            raise _too_deep(text) from None
        col = _column(text, (exc.offset or 1) - 1)
        raise _ExprError(f"syntax error at column {col + 1} in {_short(text, 120)} "
                         f"({exc.msg}); write one arithmetic expression of the states, inputs "
                         "and parameters (no ';', '=' or statements)") from None
    return _node(tree.body, symbols, text)


def _column(text: str, col: int) -> int:
    """Column in ``text`` of column ``col`` of ``text`` with every '^' written '**'."""
    shift = 0
    for i, c in enumerate(text):
        if i + shift >= col:
            return i
        shift += c == "^"
    return len(text)


_BINOPS = {
    ast.Add: lambda a, b: a + b, ast.Sub: lambda a, b: a - b, ast.Mult: lambda a, b: a * b,
    ast.Div: lambda a, b: a / b, ast.Pow: lambda a, b: a**b,
}


def _node(n: ast.AST, symbols: dict, text: str) -> sympy.Expr:
    where = f"at column {_column(text, getattr(n, 'col_offset', 0)) + 1} of {text!r}"
    if isinstance(n, ast.Constant):
        v = n.value
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise _ExprError(f"constant {v!r} {where} is not a real number")
        return sympy.Integer(v) if isinstance(v, int) else sympy.Float(v)
    if isinstance(n, ast.Name):
        if n.id in symbols:
            return symbols[n.id]
        if n.id in CONSTANTS:
            return CONSTANTS[n.id]
        if n.id in FUNCTIONS:
            raise _ExprError(f"function {n.id!r} used without arguments {where}")
        allowed = list(symbols) + list(CONSTANTS)
        raise _ExprError(
            f"unknown symbol {n.id!r} {where}{_did_you_mean(n.id, allowed)} "
            f"(known: {', '.join(allowed)})"
        )
    if isinstance(n, ast.BinOp) and type(n.op) in _BINOPS:
        a, b = _node(n.left, symbols, text), _node(n.right, symbols, text)
        return _BINOPS[type(n.op)](a, b)
    if isinstance(n, ast.UnaryOp) and isinstance(n.op, (ast.USub, ast.UAdd)):
        a = _node(n.operand, symbols, text)
        return -a if isinstance(n.op, ast.USub) else a
    if isinstance(n, ast.Call):
        if not isinstance(n.func, ast.Name):
            raise _ExprError(
                f"only plain function calls are allowed {where} (no attributes or methods); "
                f"allowed functions: {', '.join(FUNCTIONS)}"
            )
        name = n.func.id
        if name not in FUNCTIONS:
            raise _ExprError(
                f"function {name!r} is not allowed {where}{_did_you_mean(name, FUNCTIONS)} "
                f"(allowed: {', '.join(FUNCTIONS)})"
            )
        if n.keywords or any(isinstance(a, ast.Starred) for a in n.args):
            raise _ExprError(f"{name}() takes positional arguments only {where}")
        fn, arity = FUNCTIONS[name]
        args = [_node(a, symbols, text) for a in n.args]
        if (arity is None and len(args) < 2) or (arity is not None and len(args) != arity):
            want = "2 or more" if arity is None else str(arity)
            raise _ExprError(f"{name}() takes {want} arguments, got {len(args)} {where}")
        return fn(*args)
    kind = {ast.Attribute: "attribute access", ast.Subscript: "indexing",
            ast.Compare: "comparisons", ast.BoolOp: "and/or", ast.Lambda: "lambda",
            ast.IfExp: "if-else", ast.Tuple: "tuples", ast.List: "lists"}.get(
        type(n), type(n).__name__)
    raise _ExprError(
        f"{kind} is not allowed {where}; use numbers, the declared symbols, + - * / ^ and "
        f"the functions {', '.join(FUNCTIONS)}"
    )


def to_casadi(expr: sympy.Expr, symbols: dict[sympy.Symbol, ca.SX]) -> ca.SX:
    """Convert a SymPy expression to CasADi SX with :data:`SYMPY_TO_CASADI`.

    Parameters
    ----------
    expr : sympy.Expr
    symbols : dict
        SymPy symbol -> CasADi SX scalar.

    Raises
    ------
    ConfigError
        A node without converter (complex or infinite values, an unsupported function).

    Examples
    --------
    >>> x = sympy.Symbol("x", real=True); X = ca.SX.sym("x")
    >>> e = to_casadi(sympy.sin(x) ** 2 + 1, {x: X})
    >>> float(ca.Function("f", [X], [e])(0.0))
    1.0
    """
    try:
        return _convert(expr, symbols)
    except _ExprError as exc:
        raise ConfigError(str(exc)) from None


#: CasADi operations defined on part of the reals only (the walker's table)
_DOMAIN_OPS = frozenset(op for op, info in OP_TABLE.items() if info.domain is not None)
#: SymPy functions defined on part of the reals only (``Pow``: see :func:`_is_partial`)
_PARTIAL_FUNCS = (sympy.log, sympy.asin, sympy.acos, sympy.tan)


def _is_partial(e) -> bool:
    """True for a SymPy node defined on part of the reals only (as written)."""
    if isinstance(e, sympy.Pow):
        x = e.exp
        return not (x.is_Integer and int(x) >= 0)  # 1/b, b^-2, sqrt(b), b^1.5, b^y
    return isinstance(e, _PARTIAL_FUNCS)


def _sx_nodes(roots, stop=frozenset()) -> dict[int, int]:
    """``{node hash: op}`` of every node reachable from the scalar SX ``roots`` (iterative),
    not descending into the nodes whose hash is in ``stop``."""
    seen: dict[int, int] = {}
    todo = list(roots)
    while todo:
        n = todo.pop()
        h = n.element_hash()
        if h in seen or h in stop:
            continue
        seen[h] = -1 if (n.is_symbolic() or n.is_constant()) else n.op()
        todo.extend(n.dep(i) for i in range(n.n_dep()))
    return seen


def _convert(e, symbols, partial: list | None = None) -> ca.SX:
    """SymPy -> CasADi; ``partial`` (if given) collects ``(node, hashes)`` for each partial
    operation with a varying argument: the hashes of the CasADi nodes it created that carry
    its domain (empty: CasADi simplified it away when it was built)."""
    if e.is_Symbol:
        try:
            return symbols[e]
        except KeyError:
            raise _ExprError(f"symbol {e} has no CasADi counterpart") from None
    # class flags and structural tests only: SymPy's assumption queries on unevaluated
    # trees such as 0/0 depend on hash order (a different error on another PYTHONHASHSEED)
    if isinstance(e, (sympy.core.numbers.NaN, sympy.core.numbers.ComplexInfinity,
                      sympy.core.numbers.Infinity, sympy.core.numbers.NegativeInfinity)):
        raise _ExprError("the expression is infinite or undefined (a division by zero?)")
    if e.is_Number or e.is_NumberSymbol:
        try:
            v = float(e)
        except (TypeError, ValueError, OverflowError):
            raise _ExprError(f"the constant {e} is not a finite real number") from None
        if not math.isfinite(v):
            raise _ExprError(f"the constant {e} is not finite")
        return ca.SX(v)
    conv = SYMPY_TO_CASADI.get(type(e)) or SYMPY_TO_CASADI.get(e.func)
    if conv is None:
        raise _ExprError(f"the operation {e.func.__name__} ({e}) has no CasADi converter")
    args = [_convert(a, symbols, partial) for a in e.args]
    out = conv(*args, e)
    if out.is_constant():
        v = float(ca.evalf(out))
        if not math.isfinite(v):
            raise _ExprError(f"the subexpression {e} is {v} (a division by zero or a value "
                             "outside a function's domain)")
    elif partial is not None and _is_partial(e) and not all(a.is_constant() for a in args):
        stop = frozenset(a.element_hash() for a in args)
        made = _sx_nodes([out], stop)
        # ``out`` is kept with the hashes: it holds its nodes alive, so that a hash (the
        # node's address) cannot be reused by another node while the check runs
        partial.append((e, frozenset(h for h, op in made.items() if op in _DOMAIN_OPS), out))
    return out


def _domain_text(e) -> str:
    """The domain condition of the partial SymPy node ``e``, as text."""
    if isinstance(e, sympy.Pow):
        x = e.exp
        if x.is_Integer:
            return f"{e.base} != 0"
        if x.is_Number and x > 0:
            return f"{e.base} >= 0"
        return f"{e.base} > 0" if x.is_Number else f"{e.base} > 0 (or integer powers)"
    a = e.args[0]
    if isinstance(e, sympy.log):
        return f"{a} > 0"
    if isinstance(e, (sympy.asin, sympy.acos)):
        return f"-1 <= {a} <= 1"
    return f"cos({a}) != 0"


def _holds_everywhere(e) -> bool:
    """True when SymPy proves the domain of the partial node ``e`` for every real value of
    the symbols (then nothing is lost when CasADi simplifies ``e`` away, as for
    ``sqrt(x^2)`` = ``|x|``). Anything SymPy cannot decide counts as not proved."""
    try:
        with sympy.evaluate(True):
            if isinstance(e, sympy.Pow):
                b, x = sympy.sympify(e.base.doit()), e.exp
                if x.is_Integer:
                    return b.is_zero is False
                if x.is_Number and x > 0:
                    return b.is_nonnegative is True
                return x.is_Number and b.is_positive is True
            a = sympy.sympify(e.args[0].doit())
            if isinstance(e, sympy.log):
                return a.is_positive is True
            if isinstance(e, (sympy.asin, sympy.acos)):
                return (a - 1).is_nonpositive is True and (a + 1).is_nonnegative is True
    except Exception:  # noqa: BLE001 - an undecided SymPy query proves nothing
        return False
    return False


def _check_partial_kept(partial: list, f: ca.SX) -> None:
    """Refuse a partial operation (with a varying argument) that CasADi's simplification
    dropped from ``f`` (a factor 0, ``sqrt(a)^2 = a``, ``x/x = 1``, ...) unless its domain
    holds for all reals: the verifier proves domains of the operations in the graph only."""
    if not partial:
        return
    kept = _sx_nodes([f[i] for i in range(f.numel())])
    for e, made, _alive in partial:
        if (not made or not made <= kept.keys()) and not _holds_everywhere(e):
            raise _ExprError(
                f"the partial operation {e} (defined only where {_domain_text(e)}) cancels "
                "out of the expression when it is built (a factor 0, or a simplification "
                "such as sqrt(a)^2 = a or x/x = 1), so its domain could not be checked; "
                "remove the term, or write the expression without the cancellation"
            )


# ============================================================================ spec files
def _err(path, where: str, msg: str) -> ConfigError:
    return ConfigError(f"{path}: {where}{': ' if where else ''}{msg}")


def _check_keys(path, table: dict, allowed: set, where: str) -> None:
    for key in table:
        if key not in allowed:
            raise _err(
                path, where or "top level",
                f"unknown key {key!r}{_did_you_mean(key, allowed)} (allowed: "
                f"{', '.join(sorted(allowed))})"
            )


def _short(v, n: int = 40) -> str:
    """``repr(v)``, cut to about ``n`` characters (a 400-digit number in a message)."""
    r = repr(v)
    return r if len(r) <= n else f"{r[:n // 2]}...{r[-8:]} ({len(r)} characters)"


def canonical_name(name: str) -> str:
    """A name as the expression parser reads it: Unicode NFKC (Python's rule for identifiers,
    so that ``𝐱`` (U+1D431) and ``x`` are one name)."""
    return unicodedata.normalize("NFKC", name)


def _canonical(path, where: str, names) -> list[str]:
    """``names`` in NFKC form; two that become one are refused (one line, both named)."""
    out: list[str] = []
    first: dict[str, str] = {}
    for s in names:
        c = canonical_name(s)
        if c in first:
            same = f"{first[c]!r} and {s!r}" if first[c] != s else f"{s!r} twice"
            raise _err(path, where, f"{same} are the same name once Unicode-normalised (NFKC, "
                       "as Python reads identifiers); use distinct names")
        first[c] = s
        out.append(c)
    return out


def _names(path, spec: dict, key: str, required: bool) -> list[str]:
    v = spec.get(key)
    if v is None:
        if required:
            raise _err(path, key, f"missing; give the list of {key} names")
        return []
    if not isinstance(v, list) or not all(isinstance(s, str) for s in v):
        raise _err(path, key, f"must be a list of names, got {v!r}")
    v = _canonical(path, key, v)
    for s in v:
        if not s.isidentifier() or keyword.iskeyword(s) or s.startswith("_") \
                or s in FUNCTIONS or s in CONSTANTS:
            raise _err(path, key, f"{s!r} is not a usable name (an identifier that is not a "
                       "function or constant name and does not start with '_')")
    return v


def _subsystems(path, spec: dict, states: list[str]) -> list[tuple[int, ...]] | None:
    """The state indices of each subsystem named in ``subsystems`` (None: not given)."""
    v = spec.get("subsystems")
    if v is None:
        return None
    if not isinstance(v, list) or not v or not all(
            isinstance(g, list) and g and all(isinstance(n, str) for n in g) for g in v):
        raise _err(path, "subsystems", f"must be a list of lists of state names, e.g. "
                   f"[[\"{states[0]}\"], ...], got {v!r}")
    for g in v:
        for n in g:
            if n not in states:
                raise _err(path, "subsystems", f"{n!r} is not a state{_did_you_mean(n, states)}")
    flat = [n for g in v for n in g]
    if sorted(flat) != sorted(states) or len(set(flat)) != len(flat):
        missing = [n for n in states if n not in flat]
        twice = sorted({n for n in flat if flat.count(n) > 1})
        raise _err(path, "subsystems", "every state must be in exactly one subsystem ("
                   + (f"missing: {missing}" if missing else f"twice: {twice}") + ")")
    return [tuple(states.index(n) for n in g) for g in v]


def _box(path, spec: dict, key: str, n: int, required: bool):
    v = spec.get(key)
    if v is None:
        if required:
            raise _err(path, key, f"missing; give {n} rows [lo, hi]")
        return None
    if not isinstance(v, list) or not all(
            isinstance(r, list) and all(isinstance(a, (int, float)) and not isinstance(a, bool)
                                        for a in r) for r in v):
        raise _err(path, key, f"must be {n} rows [lo, hi] of numbers (not strings or "
                   f"booleans), got {v!r}")
    try:
        b = np.array(v, dtype=float)
    except (TypeError, ValueError):
        raise _err(path, key, f"must be {n} rows [lo, hi] of numbers, got {v!r}") from None
    if b.shape != (n, 2):
        raise _err(path, key, f"has shape {b.shape}; need {n} rows [lo, hi] (one per "
                   f"{'state' if key == 'state_box' else 'input'})")
    if not np.all(np.isfinite(b)) or np.any(b[:, 0] >= b[:, 1]):
        raise _err(path, key, f"needs finite rows with lo < hi, got {b.tolist()}")
    return b


def _parameters(path, spec: dict, reserved: set) -> dict[str, float]:
    table = spec.get("parameters", {})
    if not isinstance(table, dict):
        raise _err(path, "parameters", "must be a table of name = value")
    out: dict[str, float] = {}
    for name, v in zip(_canonical(path, "parameters", table), table.values()):
        where = f"parameters.{name}"
        if not name.isidentifier() or keyword.iskeyword(name) or name.startswith("_") \
                or name in reserved or name in FUNCTIONS or name in CONSTANTS:
            raise _err(path, where, f"{name!r} cannot be a parameter name (it is not an "
                       "identifier, or it is a state, input, function or constant)")
        if isinstance(v, bool):
            raise _err(path, where, f"must be a number or an expression, got {v!r}")
        if isinstance(v, (int, float)):
            try:
                val = float(v)
            except OverflowError:  # a TOML integer of hundreds of digits
                raise _err(path, where, f"the integer {_short(v)} is too large for a float "
                           "(above 1.8e308); give a smaller value") from None
        else:
            try:
                # converted by the same checked route as [rhs] (no SymPy assumption queries:
                # on unevaluated trees such as 0/0 their answers depend on hash order)
                c = _convert(_parse(v, {k: sympy.Float(x) for k, x in out.items()}), {})
                val = float(ca.evalf(c)) if c.is_constant() else math.nan
            except _ExprError as exc:
                raise _err(path, where, str(exc)) from None
            except (TypeError, ValueError, RecursionError):
                val = math.nan
        if not math.isfinite(val):
            raise _err(path, where, f"must evaluate to a finite real number, got {v!r}")
        out[name] = val
    return out


def _expressions(path, table, states, inputs, params, xs, us, only=None) -> dict[int, ca.SX]:
    if not isinstance(table, dict):
        raise _err(path, "rhs", "must be a table: state = \"expression\"")
    syms = {n: sympy.Symbol(n, real=True) for n in states + inputs}
    allowed = {**syms, **{k: sympy.Float(v) for k, v in params.items()}}
    to_ca = {syms[n]: xs[i] for i, n in enumerate(states)}
    to_ca.update({syms[n]: us[i] for i, n in enumerate(inputs)})
    out: dict[int, ca.SX] = {}
    for name, text in zip(_canonical(path, "rhs", table), table.values()):
        where = f"rhs.{name}"
        if name not in states:
            raise _err(path, where, f"{name!r} is not a state{_did_you_mean(name, states)} "
                       f"(states: {', '.join(states)})")
        if only is not None and name not in only:
            raise _err(path, where, "the dynamics come from the sample file; [rhs] may give "
                       f"only the components named in 'known' (add {name!r} to known if its "
                       "derivative is exactly this expression)")
        try:
            try:
                partial: list = []
                fk = _convert(_parse(text, allowed), to_ca, partial)
                _check_partial_kept(partial, fk)
                out[states.index(name)] = fk
            except RecursionError:
                raise _too_deep(text) from None
        except _ExprError as exc:
            raise _err(path, where, str(exc)) from None
    return out


def _declarations(path, spec: dict) -> Declarations | None:
    d = spec.get("declared")
    if d is None:
        return None
    if not isinstance(d, dict):
        raise _err(path, "declared", "must be a table (lipschitz, hessian, input_matrix)")
    _check_keys(path, d, SPEC_KEYS["declared"], "declared")
    dep = d.get("depends_on")
    if isinstance(dep, dict):  # names as the rest of the file reads them (NFKC)
        dep = dict(zip(_canonical(path, "declared.depends_on", dep),
                       [_canonical(path, f"declared.depends_on.{k}", v)
                        if isinstance(v, list) and all(isinstance(n, str) for n in v) else v
                        for k, v in dep.items()]))
    try:
        return Declarations(d.get("lipschitz"), d.get("hessian"), d.get("input_matrix"),
                            d.get("sample_error"), dep, source=str(path))
    except ConfigError as exc:
        raise _err(path, "declared", str(exc)) from None


def _factory_reference(path: Path, ref) -> tuple[str, str, Path | None]:
    """``(module, function, file)`` of a ``factory`` entry, checked without importing
    anything (``file``: the ``.py`` file it names, else ``None``)."""
    if not isinstance(ref, str) or ref.count(":") != 1:
        raise _err(path, "factory", f"must be \"module:function\" or \"file.py:function\", "
                   f"got {ref!r}")
    mod, fn = ref.split(":")
    if not mod.endswith(".py"):
        return mod, fn, None
    file = (path.parent / mod).resolve()
    if not file.is_file():
        raise _err(path, "factory", f"file {str(file)!r} not found")
    return mod, fn, file


def _load_factory(path: Path, ref) -> Callable:
    mod, fn, file = _factory_reference(path, ref)
    if file is not None:
        modname = f"_nlyap_spec_{file.stem}_{abs(hash(str(file)))}"
        spec = importlib.util.spec_from_file_location(modname, file)
        module = importlib.util.module_from_spec(spec)
        sys.modules[modname] = module
        try:
            with user_code():
                spec.loader.exec_module(module)
        except (Exception, SystemExit) as exc:  # sys.exit() in the file: a failure too
            del sys.modules[modname]
            raise _err(path, "factory", f"importing {str(file)!r} failed: {_failure(exc)}; "
                       "fix the file (it is imported to build the system)") from None
    else:
        try:
            with user_code():
                module = importlib.import_module(mod)
        except ImportError as exc:
            raise _err(path, "factory", f"cannot import {mod!r} ({exc}); install it or use "
                       "\"file.py:function\" relative to the spec") from None
        except (Exception, SystemExit) as exc:  # noqa: BLE001 - the module's own code failed
            raise _err(path, "factory", f"importing {mod!r} failed: {_failure(exc)}; fix the "
                       "module (it is imported to build the system)") from None
    f = getattr(module, fn, None)
    if not callable(f):
        raise _err(path, "factory", f"{mod!r} has no function {fn!r}")
    return f


def _failure(exc: BaseException) -> str:
    """``Type: message`` of an exception of the user's code, on one line, the message cut
    to 200 characters (``Type`` alone without one: a bare ``sys.exit()``)."""
    msg = " ".join(str(exc).split())
    if len(msg) > 200:
        msg = msg[:200] + f"… ({len(msg)} characters)"
    return f"{type(exc).__name__}: {msg}" if msg else type(exc).__name__


def _call_factory(path: Path, ref: str, factory: Callable) -> System:
    """Call the factory without arguments; whatever goes wrong is one line naming it."""
    try:
        sig = inspect.signature(factory)
    except (TypeError, ValueError):
        sig = None
    if sig is not None:
        need = [n for n, p in sig.parameters.items() if p.default is p.empty
                and p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
        if need:
            raise _err(path, "factory", f"{ref!r} needs the arguments {need}, but a factory is "
                       "called without arguments; give them defaults or wrap it in a function "
                       "without parameters")
    try:
        with user_code():
            system = factory()
    except (Exception, SystemExit) as exc:  # noqa: BLE001 - the user's code: any failure
        # (sys.exit() included: its code must not become the command's) is an input error
        raise _err(path, "factory", f"{ref!r} raised {_failure(exc)}; fix the factory (it is "
                   "called without arguments and returns a systems.System)") from None
    if not isinstance(system, System):
        raise _err(path, "factory", f"{ref!r} returned {type(system).__name__}, not a "
                   "systems.System; return the System the file describes")
    return system


def _quick_check(system: System, path) -> System:
    """Check declarations against ``f`` on a coarse grid (3 to 11 nodes per axis, ≤ 20 000
    nodes; skipped beyond 9 variables, where 3 nodes per axis pass that: the compositional
    method, the one for such systems, checks its declarations on its own points).

    Only refutes what the data contradict (e.g. a K_f below a slope); a model's rigorous
    constants are the pipeline's business.
    """
    if system.declarations is None or system.kind == "samples":
        return system
    d = system.nx + system.nu
    if 3 ** d > 20_000:
        return system
    n = max(3, min(11, int(20_000 ** (1.0 / d))))
    smp = sample_function(system.evaluate, system.sampling_box, [n] * d, nx=system.nx,
                          names=system.state_names + system.input_names)
    try:
        with np.errstate(all="ignore"):   # a degenerate box: nothing is refuted there
            check_declarations(smp, smp.values, system.declarations, names=smp.names,
                               source=str(path))
    except ConfigError as exc:
        msg = str(exc)
        raise ConfigError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None
    return system


def load_spec(path, *, allow_factory: bool = True) -> System:
    """Build a :class:`~systems.base.System` from a TOML spec file.

    Parameters
    ----------
    path : str or Path
    allow_factory : bool
        Whether a ``factory`` (Python code) may be imported and run. ``False``: a spec with
        one is refused, decided on the same bytes that are parsed (a file changed between a
        caller's own look and this read cannot slip a factory in).

    Returns
    -------
    System
        With ``declarations`` (``[declared]``), ``run_overrides`` (``[run]``, a dict) and
        ``source`` (the path). Declarations are checked against the data: a sample file's
        samples, or ``f`` on a coarse grid (at most 11 nodes per axis, up to 9 variables)
        for expressions and factories.

    Raises
    ------
    ConfigError
        One line naming the file, the entry and the problem (unknown keys with a
        suggestion, unknown symbols, syntax errors, disallowed functions, wrong shapes, a
        missing ``u_eq``, bad sample files, declarations the samples contradict).
    """
    path = Path(path)
    spec = _read_spec(path)
    if "factory" in spec and not allow_factory:
        raise ConfigError(f"{path} defines its system with factory = "
                          f"{_short(str(spec['factory']), 80)}, Python code that is run only "
                          "when asked; read it, then allow it (nlyap verify --allow-factory)")
    try:
        return _load_spec(path, spec)
    except OverflowError as exc:  # a number of hundreds of digits anywhere in the file
        raise _too_large(path, exc) from None


def _too_large(path: Path, exc: OverflowError) -> ConfigError:
    return ConfigError(f"{path}: a number is too large for a float ({exc}); give values "
                       "below 1.8e308")


def check_spec(path) -> System | None:
    """Check a TOML spec file as :func:`load_spec` does, running no code: the
    :class:`~systems.base.System` of an expression or sample-file spec, ``None`` for a
    ``factory`` spec once the file's own entries are checked (the factory, Python code, is
    neither imported nor run). Raises :class:`ConfigError` as :func:`load_spec` does."""
    path = Path(path)
    spec = _read_spec(path)     # read once: what is checked is what was read
    try:
        if "factory" not in spec:
            return _load_spec(path, spec)
        _check_factory_entries(path, spec)
    except OverflowError as exc:  # a number of hundreds of digits anywhere in the file
        raise _too_large(path, exc) from None
    return None


def _read_spec(path: Path) -> dict:
    """The TOML table of a spec file, or the one-line error of why it cannot be read."""
    try:
        return tomllib.loads(read_file_bytes(path, "system spec").decode("utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"system spec {str(path)!r} not found; check the path") from None
    except IsADirectoryError:
        raise ConfigError(f"system spec {str(path)!r} is a directory; give the .toml file") \
            from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.object[exc.start]:#04x} at "
                          f"offset {exc.start}); save the file as UTF-8") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    except RecursionError:
        raise ConfigError(f"{path}: nested too deeply to read; fix the file") from None
    except ValueError as exc:  # an integer of thousands of digits (Python's own limit)
        raise ConfigError(f"{path}: cannot be read ({' '.join(str(exc).split())[:120]}); "
                          "fix the file") from None


def _check_name(path, name) -> None:
    """A system name names the output directory ``runs/NAME``: a plain, printable name."""
    if not isinstance(name, str) or not name:
        raise _err(path, "name", "must be a non-empty string")
    if any(c in name for c in "/\\") or name.startswith(".") or \
            not name.isprintable() or len(name) > 200:
        raise _err(path, "name", "must be a plain name of at most 200 printable characters, "
                   "without '/' or '\\' and not starting with '.' (it names the output "
                   f"directory runs/NAME), got {name!r}; rename the system")


def _common_entries(path: Path, spec: dict) -> tuple:
    """``(name, run, declarations)``: the keys, the name, the ``[run]`` table and the
    ``[declared]`` one, checked as every spec's."""
    _check_keys(path, spec, SPEC_KEYS[""], "")
    name = spec.get("name", path.stem)
    _check_name(path, name)
    run = spec.get("run", {})
    if not isinstance(run, dict):
        raise _err(path, "run", "must be a table of run-config overrides")
    return name, run, _declarations(path, spec)


def _check_factory_entries(path: Path, spec: dict) -> tuple:
    """:func:`_common_entries` of a ``factory`` spec, which takes no entry that defines the
    system: checked before the factory is imported."""
    out = _common_entries(path, spec)
    clash = sorted(set(spec) - {"name", "description", "factory", "declared", "run"})
    if clash:
        raise _err(path, "factory", f"the factory defines the system; remove {clash} "
                   "(a factory spec takes only name, description, declared and run)")
    _factory_reference(path, spec["factory"])
    return out


def _load_spec(path: Path, spec: dict) -> System:
    if "factory" in spec:
        name, run, decl = _check_factory_entries(path, spec)
        system = _call_factory(path, spec["factory"], _load_factory(path, spec["factory"]))
        if decl is not None:
            if system.declarations is not None:
                raise _err(path, "declared", "the factory's system has declarations already; "
                           "declare them in one place")
            try:
                system.declarations = decl.validate(system.nx, system.nu)
                decl.dependencies(system.state_names, system.input_names)
            except ConfigError as exc:
                raise _err(path, "declared", str(exc)) from None
            if system.kind == "samples":
                system.check_declarations(system.samples)
        if "name" in spec:
            system.name = name
        _check_name(path, system.name)      # the factory's own name, when the file gives none
        if "description" in spec:
            system.description = str(spec["description"])
        system.run_overrides = {**system.run_overrides, **run}
        system.source = str(path)
        return _quick_check(system, path)

    name, run, decl = _common_entries(path, spec)
    states = _names(path, spec, "states", True)
    inputs = _names(path, spec, "inputs", False)
    if not states:
        raise _err(path, "states", "needs at least one state")
    clash = set(states) & set(inputs)
    if clash:
        raise _err(path, "inputs", f"{sorted(clash)} are states too; use distinct names")
    nx, nu = len(states), len(inputs)
    if decl is not None:
        try:
            decl.validate(nx, nu)
        except ConfigError as exc:
            raise _err(path, "declared", str(exc)) from None
    params = _parameters(path, spec, set(states) | set(inputs))
    known = _names(path, spec, "known", False)
    for k in known:
        if k not in states:
            raise _err(path, "known", f"{k!r} is not a state{_did_you_mean(k, states)}")
    if not nu and "input_box" in spec:
        raise _err(path, "input_box", "the system has no inputs; remove it")
    u_eq = spec.get("u_eq")
    if not nu and u_eq is not None and np.size(u_eq):
        raise _err(path, "u_eq", "the system has no inputs; remove it")
    if u_eq is not None:
        if not isinstance(u_eq, list) or not all(
                isinstance(a, (int, float)) and not isinstance(a, bool) for a in u_eq):
            raise _err(path, "u_eq", f"must be a list of {nu} numbers (not strings or "
                       f"booleans), e.g. u_eq = [0.0], got {_short(u_eq)}")
        try:
            u_eq = np.array(u_eq, dtype=float).ravel()
        except (TypeError, ValueError):
            raise _err(path, "u_eq", f"must be {nu} numbers, got {u_eq!r}") from None
        if u_eq.shape != (nu,) or not np.all(np.isfinite(u_eq)):
            raise _err(path, "u_eq", f"must be {nu} finite numbers (one per input), got "
                       f"{spec['u_eq']!r}")
    common = dict(params=params, state_names=states, input_names=inputs,
                  description=str(spec.get("description", "")), declarations=decl,
                  run_overrides=run, source=str(path))
    xs, us = System.symbols(nx, nu, states, inputs)
    sources = [k for k in ("rhs", "samples") if k in spec]
    if sources == ["rhs"]:
        xbox = _box(path, spec, "state_box", nx, True)
        ubox = _box(path, spec, "input_box", nu, nu > 0) if nu else None
        rhs = _expressions(path, spec["rhs"], states, inputs, params, xs, us)
        missing = [s for i, s in enumerate(states) if i not in rhs]
        if missing:
            raise _err(path, "rhs", f"no expression for {missing}; give one per state")
        f = ca.vertcat(*[rhs[i] for i in range(nx)])
        parts = _subsystems(path, spec, states)
        if parts is not None and nu:
            raise _err(path, "subsystems", "a compositional certificate is for systems "
                       "without inputs; close the loop in [rhs] or remove subsystems")
        try:
            return _quick_check(System(
                name, xs, us, f, state_box=xbox, input_box=ubox, u_eq=u_eq,
                known_state_derivatives=[states.index(k) for k in known], subsystems=parts,
                **common), path)
        except ConfigError as exc:
            msg = str(exc)
            raise (exc if msg.startswith(str(path)) else _err(path, "", msg)) from None
        except ValueError as exc:  # EquilibriumError and friends: one line with the file
            raise ConfigError(f"{path}: {exc}") from None
    if sources not in (["samples"], ["rhs", "samples"]):
        raise _err(path, "", "give the dynamics in exactly one way: [rhs] expressions, a "
                   "[samples] file, or factory = \"module:function\"")
    # ---- samples
    if "subsystems" in spec:
        raise _err(path, "subsystems", "a compositional certificate evaluates f at its own "
                   "points, which a sample file cannot: give f as [rhs] expressions or a "
                   "simulator (factory), or remove subsystems")
    smp = spec["samples"]
    if not isinstance(smp, dict):
        raise _err(path, "samples", "must be a table with 'file' (and optional 'columns')")
    _check_keys(path, smp, SPEC_KEYS["samples"], "samples")
    if "file" not in smp or not isinstance(smp["file"], str):
        raise _err(path, "samples", "needs file = \"name.csv\" (or .npz), relative to the spec")
    if nu and u_eq is None:
        raise _err(path, "u_eq", f"missing; a system given by samples needs the declared "
                   f"equilibrium input u_eq ({nu} numbers)")
    known_rhs = _expressions(path, spec.get("rhs", {}), states, inputs, params, xs, us,
                             only={k: "samples" for k in known})
    lacking = [k for k in known if states.index(k) not in known_rhs]
    if lacking:
        raise _err(path, "rhs", f"known components {lacking} need an expression in [rhs] "
                   "(without a model nothing else gives them)")
    try:
        samples = load_samples(path.parent / smp["file"], states=states, inputs=inputs,
                               columns=smp.get("columns"))
        return System.from_samples(
            name, samples, state_box=_box(path, spec, "state_box", nx, False),
            input_box=_box(path, spec, "input_box", nu, False) if nu else None,
            u_eq=u_eq, known_rhs=known_rhs, symbols=(xs, us),
            **{k: v for k, v in common.items() if k not in ("state_names", "input_names")})
    except ConfigError as exc:
        msg = str(exc)
        raise ConfigError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None
    except ValueError as exc:
        raise ConfigError(f"{path}: {exc}") from None


def default_run_settings(system: System, *, grid_budget: int = 200_000) -> dict:
    """Proposed run settings for a system without a preset, from its boxes.

    - ``domain``: the state box (a box domain D; ``outer`` is ``None``), so that the
      certificate and the true-ROA share are about the region the user declared;
      ``inner`` = a tenth of the radius of the largest origin-centred ball inside it, raised
      for learned dynamics to what the error bound η affords (``auto_inner``);
    - ``controller_scale`` (``u = C·tanh(Kx + b)`` stays in ``U``): the largest ``C`` with
      ``[-C, C]`` inside every input's range (``None`` without inputs);
    - ``eval_box``: the state box;
    - ``cegis.iterations``: :data:`ITERATIONS_3D` for 3 or more states (else the default
      method's own);
    - ``dynamics.grid_counts``: the sample grid of a ``"samples"`` system (its own, it
      cannot change), else at most ``grid_budget`` nodes over ``X × U``, the same odd
      count on every axis (a symmetric axis then has 0 as a node; equal counts need no
      choice of units); ``dynamics.model`` is ``"control_affine"`` for samples of one
      input level.

    Examples
    --------
    >>> import systems
    >>> d = default_run_settings(systems.get("inverted_pendulum"))
    >>> d["domain"], d["inner"], d["controller_scale"], d["dynamics"]["grid_counts"]
    ({'type': 'box', 'box': [[-4.0, 4.0], [-4.0, 4.0]]}, 0.4, 20.0, [57, 57, 57])
    """
    box = system.state_box  # it holds the origin inside (checked by System)
    inradius = float(np.min(np.minimum(-box[:, 0], box[:, 1])))
    out: dict = {"outer": None, "domain": {"type": "box", "box": box.tolist()},
                 "inner": inradius / 10.0, "auto_inner": True, "controller_scale": None,
                 "eval_box": box.tolist()}
    if system.nu:
        out["controller_scale"] = _input_scale(system)
    if system.samples is not None:
        smp = system.samples
        if smp.input_slice:
            dyn = {"model": "control_affine", "grid_counts": smp.counts[:system.nx].tolist()}
        else:
            dyn = {"model": "full", "grid_counts": smp.counts.tolist()}
    elif system.nu and system.declarations is not None \
            and system.declarations.input_matrix is not None:
        # a declared B: learn φ₀(x) on an x-grid (the control-affine model; u adds B u)
        d = system.nx
        n = int(2 * max(1, math.floor((grid_budget ** (1.0 / d) - 1) / 2)) + 1)
        dyn = {"model": "control_affine", "grid_counts": [n] * d}
    else:
        # a grid over (x, u): the full model, also where a catalogue system's learned-
        # dynamics preset names another one (its grid has other axes), and no η gate (a
        # catalogue preset's eta_target belongs to its own, finer grid)
        d = system.nx + system.nu
        n = int(2 * max(1, math.floor((grid_budget ** (1.0 / d) - 1) / 2)) + 1)
        dyn = {"model": "full", "grid_counts": [n] * d, "eta_target": None}
    out["dynamics"] = dyn
    if system.nx >= 3:
        out["cegis"] = {"iterations": ITERATIONS_3D}
    if centre_dimension(system):
        _merge_centre_settings(out, system, inradius)
    return out


#: the default method's CEGIS budget (iterations) for 3 or more states, twice the 2-D one:
#: there V's candidate set keeps growing after 8 iterations (a 3-D controlled chain, true f:
#: the first certified neural level at iteration 11, 65.2 % of the true ROA against the
#: quadratic's 40.6 % at 8; the controlled Lorenz system: 78.5 % at 8, 89.0 % at 16). The
#: stop rule ends a run whose certified level has settled earlier.
ITERATIONS_3D = 16


#: relative tolerance of :func:`centre_dimension` on the real parts (a multiple of ``‖A‖``)
CENTRE_TOL = 1e-9
#: the inner radius of a system with a centre, as a fraction of the domain's inradius (the
#: decrease along a centre direction is only ~‖x‖⁴: Fossil's Poly1 certifies with ε = 0.5 on
#: the ball r = 3)
CENTRE_INNER_FRACTION = 1.0 / 6.0


def _linearisation(system: System) -> tuple[np.ndarray, np.ndarray] | None:
    """``(A, B)`` of the model at ``(0, u_eq)`` (``B`` with no columns for an autonomous
    system); ``None`` without a model or with a non-finite entry."""
    if not getattr(system, "has_model", False):
        return None
    A = np.asarray(system.A, dtype=float)
    n = A.shape[0]
    B = np.asarray(system.B, dtype=float).reshape(n, -1) if system.nu else np.zeros((n, 0))
    if not np.all(np.isfinite(A)) or not np.all(np.isfinite(B)):
        return None
    return A, B


def unstable_origin(system: System) -> str | None:
    """The one-line refusal of a system whose origin no feedback can stabilise
    (:func:`unstable_modes`), or ``None``."""
    unstable = unstable_modes(system)
    if not unstable:
        return None
    lams = ", ".join(f"{lam.real:.4g}" + (f"{lam.imag:+.4g}i" if lam.imag else "")
                     for lam in unstable)
    return (f"the origin of {system.name!r} is unstable"
            + (" under every feedback" if system.nu else "")
            + f": ∂f/∂x(0) has eigenvalue(s) {lams} with a positive real part"
            + (" that no input moves" if system.nu else "")
            + ", so no region of attraction exists; check the signs of the right-hand side"
            + (" and which states the inputs enter" if system.nu else
               ", or declare an input that acts on that mode"))


def centre_dimension(system: System) -> int:
    r"""The number of eigenvalues of the linearisation ``A = ∂f/∂x(0, u_eq)`` on the
    imaginary axis that no input can move (0 for a system without a model).

    An eigenvalue :math:`\lambda` with :math:`|\mathrm{Re}\,\lambda| \le` :data:`CENTRE_TOL`
    ``·max(1, ‖A‖)`` counts when no input moves it (Hautus): each distinct such
    :math:`\lambda` adds its algebraic multiplicity, at most
    :math:`n - \mathrm{rank}[A - \lambda I,\ B]`; for an autonomous system, every eigenvalue
    on the axis with its algebraic multiplicity. Such a closed-loop linearisation has no
    quadratic Lyapunov function with
    :math:`PA + A^\top P \prec 0`: its origin is at best asymptotically, not exponentially,
    stable.

    Examples
    --------
    >>> import systems
    >>> centre_dimension(systems.load_spec("examples/fossil_poly1.toml"))  # doctest: +SKIP
    1
    """
    AB = _linearisation(system)
    if AB is None:
        return 0
    A, B = AB
    n = A.shape[0]
    tol = CENTRE_TOL * max(1.0, float(np.linalg.norm(A, 2)))
    axis = [lam for lam in np.linalg.eigvals(A) if abs(lam.real) <= tol]
    if not system.nu:
        return len(axis)
    count, seen = 0, []
    for lam in axis:       # each distinct λ: min(algebraic multiplicity, n − rank[A − λI, B])
        if any(abs(lam - mu) <= 1e3 * tol for mu in seen):
            continue
        seen.append(lam)
        alg = sum(abs(lam - mu) <= 1e3 * tol for mu in axis)
        rank = np.linalg.matrix_rank(np.hstack([A - lam * np.eye(n), B]), tol=1e3 * tol)
        count += min(alg, n - rank)
    return count


def _input_scale(system: System) -> float | list[float]:
    """The default ``C`` of the controller ``u = C·tanh(Kx + b)``: per input, the largest
    range ``[−C_i, C_i]`` inside its box (one number when all inputs get the same). The
    range must hold ``u_eq`` inside (``C·tanh(b) = u_eq``); where it cannot, the error names
    the input and the fix (its box shifted by its ``u_eq``)."""
    ub, ueq = system.input_box, np.asarray(system.u_eq, dtype=float).ravel()
    c = np.minimum(-ub[:, 0], ub[:, 1])
    for i in range(system.nu):
        name = system.input_names[i]
        if not ub[i, 0] < ueq[i] < ub[i, 1]:
            raise ConfigError(
                f"input {name!r} of {system.name!r}: its u_eq = {ueq[i]:.6g} is not inside its "
                f"box {ub[i].tolist()}; the input that holds the equilibrium must be one the "
                "actuator can give with room to spare: fix u_eq or the input box")
        if not c[i] > abs(ueq[i]):
            lo, hi = (float(v) - ueq[i] for v in ub[i])
            raise ConfigError(
                f"input {name!r} of {system.name!r}: the controller u = C·tanh(Kx + b) ranges "
                f"over [-C, C], which must lie in its box {ub[i].tolist()} and hold its u_eq "
                f"= {ueq[i]:.6g} inside, and no C does; write the model in u − u_eq (box "
                f"[{lo:.6g}, {hi:.6g}], u_eq = 0) or give controller_scale in [run]")
    return float(c[0]) if np.all(c == c[0]) else [float(v) for v in c]


#: :func:`unstable_modes` counts eigenvalues with a real part above this times
#: ``max(1, ‖A‖)`` (or ``eps^(1/n)`` times it, when larger)
UNSTABLE_TOL = 1e-6


def unstable_modes(system: System) -> list[complex]:
    r"""The eigenvalues of the linearisation ``A = ∂f/∂x(0, u_eq)`` with a positive real part
    that no input can move (empty for a system without a model).

    An eigenvalue :math:`\lambda` with :math:`\mathrm{Re}\,\lambda >`
    ``max(UNSTABLE_TOL, eps^(1/n))·max(1, ‖A‖)`` (well above what rounding does to a
    defective eigenvalue on the imaginary axis) counts when
    :math:`\mathrm{rank}[A - \lambda I,\ B] < n` (Hautus: no state feedback moves it); for
    an autonomous system, every such eigenvalue. With one of them the origin is unstable
    under every feedback (Lyapunov's indirect method): no region of attraction exists.

    Examples
    --------
    >>> import casadi as ca
    >>> x = ca.SX.sym("x", 2)
    >>> saddle = System("saddle", x, None, ca.vertcat(x[1], x[0] - 0.5 * x[1]),
    ...                 state_box=[[-1.0, 1.0], [-1.0, 1.0]])
    >>> [round(v.real, 4) for v in unstable_modes(saddle)]
    [0.7808]
    """
    AB = _linearisation(system)
    if AB is None:
        return []
    A, B = AB
    n = A.shape[0]
    # a refusal only on a clear case: rounding moves an eigenvalue of a Jordan block of
    # size k by about eps^(1/k)·‖A‖ (a nilpotent 2×2 A gets eigenvalues ±2e-8)
    scale = max(1.0, float(np.linalg.norm(A, 2)))
    tol = max(UNSTABLE_TOL, EPS ** (1.0 / n)) * scale
    norms = np.linalg.norm(B, axis=0)
    Bn = B[:, norms > 0] / norms[norms > 0] * scale   # the rank test in B's directions
    return [complex(lam) for lam in np.linalg.eigvals(A) if lam.real > tol
            and np.linalg.matrix_rank(np.hstack([A - lam * np.eye(n), Bn]),
                                      tol=1e3 * CENTRE_TOL * scale) < n]


def _merge_centre_settings(out: dict, system: System, inradius: float) -> None:
    """The defaults of a system with a centre (:func:`centre_dimension`), into ``out``.

    The default method's Zubov-type fit needs trajectories that reach 0 within the simulated
    horizon; along a centre (``x' = -x³``) they take ~1/‖x‖² time units and count as
    diverging. Instead: V is a polynomial (one ``square`` hidden layer of ``2n`` units: V
    of degree 4, able to decrease like ‖x‖⁴) trained on the Lyapunov risk alone; ε is
    :data:`CENTRE_INNER_FRACTION` of the inradius (condition (c) on the ball is then proved by
    the weighted blow-up of ``nlyap_opt.certification.roa``); training states count as
    converging once they reach ``B_ε``.
    """
    n = system.nx
    eps = inradius * CENTRE_INNER_FRACTION
    out["inner"] = eps
    out["quadratic"] = ["centre"]
    out["train"] = {"activation": "square", "hidden": [2 * n], "features": n, "steps": 1000,
                    "lr_schedule": "constant", "decay": 0.1, "level_slack": 0.1,
                    "relative_decrease": False, "w_fit": 0.0, "w_pde": 0.0, "w_local": 0.0}
    out["cegis"] = {"iterations": 6, "steps": 500, "verify_every": 1, "sim_time": 20.0,
                    "sim_dt": 0.02, "inner_samples": 0, "boundary_samples": 0,
                    "sim_tol": eps}
