"""One walker over CasADi instruction lists, with pluggable arithmetic.

A CasADi ``Function`` (``SXFunction`` or ``MXFunction``) is compiled once into a
list of small Python steps, one per instruction (``instruction_id``,
``instruction_input``, ``instruction_output``, ``instruction_constant`` /
``instruction_MX``). Evaluating the program with an *arithmetic* object gives:

- :class:`ArrayArithmetic` (numpy): many points at once, float64;
- :class:`ArrayArithmetic` (torch): differentiable evaluation for training;
- ``verification.interval.IntervalArithmetic``: rigorous enclosures over many boxes;
- the dReal and SMT-LIB arithmetics of the verifier (on the SX expansion).

Conventions
-----------
Inputs and outputs are *nonzero vectors* with a leading batch shape: an input of
sparsity ``(r, c)`` with ``nnz`` nonzeros is passed as an array of shape
``(..., nnz)`` (column-major nonzero order, as CasADi stores it). In SX programs
every register holds a batch of scalars, shape ``(...)``; in MX programs every
register holds a dense batch of matrices, shape ``(..., r, c)``, so network layers
evaluate as matrix products, not scalar by scalar.

Facts relied on (casadi 3.8): output slots are reused registers, not node ids;
``OP_SQ`` and ``OP_TWICE`` appear; ``str(SX)`` prints 6 significant digits, so
constants are read from ``instruction_constant`` (SX) or ``evalf`` (MX).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

import casadi as ca
import numpy as np
from scipy.special import erf as _erf

from . import deps
from .errors import DimensionError, UnsupportedOperationError

__all__ = [
    "ArrayArithmetic", "Program", "compile_function", "evaluate", "op_name", "NUMPY", "OpInfo",
    "OP_TABLE", "UNARY_OPS", "BINARY_OPS", "CHECKED_OPS", "ExactPointArithmetic", "exact_values",
    "REAL", "UNDEFINED",
]

OP_NAMES: dict[int, str] = {getattr(ca, a): a for a in dir(ca) if a.startswith("OP_")}


def op_name(op: int) -> str:
    """Return the ``OP_...`` name of a CasADi operation code."""
    return OP_NAMES.get(op, f"op#{op}")


@dataclass(frozen=True)
class OpInfo:
    """What the verifier must know about one elementwise CasADi operation.

    Attributes
    ----------
    name : str
        ``OP_...`` name (``"OP_SIGN"``).
    arity : int
        1 or 2 (``OP_ATAN2`` is ``atan2(a, b)``, ``OP_IF_ELSE_ZERO`` is ``a ? b : 0``).
    kind : {"smooth", "lipschitz", "discontinuous"}
        ``"smooth"``: continuously differentiable on the interior of its domain;
        ``"lipschitz"``: continuous with kinks (``fabs``, ``fmin``, ...), where CasADi's
        derivative is a one-sided choice; ``"discontinuous"``: jumps (``sign``, ``floor``,
        comparisons, ...), where CasADi's derivative is 0 across the jump. The mean-value
        form of the interval verifier needs a derivative over the whole box: boxes where
        a non-smooth operation's argument meets its kink or jump set use the natural
        interval extension only.
    domain : str or None
        ``None`` for an operation defined on all reals, else the condition on the argument
        (``x``; binary: ``x`` and ``y``) for which the real-valued operation is defined.
        An expression is defined at a point when every operation it depends on is applied
        inside its domain there; CasADi's ``if_else`` evaluates both branches, and a branch
        that is not taken does not count.
    """

    name: str
    arity: int
    kind: str
    domain: str | None = None


def _op_table() -> dict[int, OpInfo]:
    S, L, D = "smooth", "lipschitz", "discontinuous"
    rows = [
        # unary
        ("OP_ASSIGN", 1, S, None), ("OP_NEG", 1, S, None), ("OP_SQ", 1, S, None),
        ("OP_TWICE", 1, S, None), ("OP_SQRT", 1, S, "x >= 0"), ("OP_EXP", 1, S, None),
        ("OP_EXPM1", 1, S, None), ("OP_LOG", 1, S, "x > 0"), ("OP_LOG1P", 1, S, "x > -1"),
        ("OP_SIN", 1, S, None), ("OP_COS", 1, S, None),
        ("OP_TAN", 1, S, "x != pi/2 + k*pi"), ("OP_ASIN", 1, S, "-1 <= x <= 1"),
        ("OP_ACOS", 1, S, "-1 <= x <= 1"), ("OP_ATAN", 1, S, None), ("OP_SINH", 1, S, None),
        ("OP_COSH", 1, S, None), ("OP_TANH", 1, S, None), ("OP_ASINH", 1, S, None),
        ("OP_ACOSH", 1, S, "x >= 1"), ("OP_ATANH", 1, S, "-1 < x < 1"),
        ("OP_ERF", 1, S, None), ("OP_INV", 1, S, "x != 0"),
        ("OP_FABS", 1, L, None), ("OP_SIGN", 1, D, None), ("OP_FLOOR", 1, D, None),
        ("OP_CEIL", 1, D, None), ("OP_NOT", 1, D, None),
        # binary
        ("OP_ADD", 2, S, None), ("OP_SUB", 2, S, None), ("OP_MUL", 2, S, None),
        ("OP_DIV", 2, S, "y != 0"),
        ("OP_POW", 2, S, "x > 0, or x = 0 and y > 0, or y integer and (y >= 0 or x != 0)"),
        ("OP_CONSTPOW", 2, S,
         "x > 0, or x = 0 and y > 0, or y integer and (y >= 0 or x != 0)"),
        ("OP_HYPOT", 2, L, None), ("OP_FMIN", 2, L, None), ("OP_FMAX", 2, L, None),
        ("OP_ATAN2", 2, D, None),  # jumps by 2 pi across y = 0, x < 0
        ("OP_LT", 2, D, None), ("OP_LE", 2, D, None), ("OP_EQ", 2, D, None),
        ("OP_NE", 2, D, None), ("OP_AND", 2, D, None), ("OP_OR", 2, D, None),
        ("OP_COPYSIGN", 2, D, None), ("OP_FMOD", 2, D, "y != 0"),
        ("OP_IF_ELSE_ZERO", 2, D, None),
    ]
    return {getattr(ca, n): OpInfo(n, a, k, d) for n, a, k, d in rows}


#: Every elementwise CasADi operation the walker supports (the one op table: the numpy,
#: torch and interval arithmetics implement each of them, a test checks it).
OP_TABLE: dict[int, OpInfo] = _op_table()
#: Derived views of :data:`OP_TABLE` (operation codes by arity).
UNARY_OPS = frozenset(op for op, info in OP_TABLE.items() if info.arity == 1)
BINARY_OPS = frozenset(op for op, info in OP_TABLE.items() if info.arity == 2)
#: Operations whose use must be checked on every box: not smooth, or not total.
CHECKED_OPS = frozenset(op for op, info in OP_TABLE.items()
                        if info.kind != "smooth" or info.domain is not None)


# --------------------------------------------------------------------------- arithmetic
class ArrayArithmetic:
    """Plain floating-point arithmetic on numpy arrays or torch tensors.

    Parameters
    ----------
    lib : {"numpy", "torch"}
        Array library. ``"torch"`` keeps autograd graphs (used in training).

    Examples
    --------
    >>> import casadi as ca, numpy as np
    >>> x = ca.SX.sym("x")
    >>> f = ca.Function("f", [x], [ca.sin(x) * x])
    >>> evaluate(f, [np.array([[0.5], [1.0]])])[0].ravel().round(6)
    array([0.239713, 0.841471])
    """

    def __init__(self, lib: str = "numpy"):
        if lib == "numpy":
            xp = np
            self.asarray = lambda v: np.asarray(v, dtype=float)
            self._sum = lambda a, axis: np.sum(a, axis=axis)
            self._bool = lambda m: m.astype(float)
            self._where = lambda m, a: np.where(m, a, 0.0)

            def erf(a):
                return _erf(a)
            fn = {"atan": np.arctan, "atan2": np.arctan2, "asin": np.arcsin,
                  "acos": np.arccos, "asinh": np.arcsinh, "acosh": np.arccosh,
                  "atanh": np.arctanh, "erf": erf}
        elif lib == "torch":
            torch = deps.torch()

            xp = torch
            self.asarray = lambda v: torch.as_tensor(np.asarray(v, dtype=float))
            self._sum = lambda a, axis: torch.sum(a, dim=axis)
            self._bool = lambda m: m.to(torch.float64)
            self._where = lambda m, a: torch.where(m, a, torch.zeros((), dtype=a.dtype))
            fn = {"atan": torch.atan, "atan2": torch.atan2, "asin": torch.asin,
                  "acos": torch.acos, "asinh": torch.asinh, "acosh": torch.acosh,
                  "atanh": torch.atanh, "erf": torch.erf}
        else:
            raise ValueError(f"lib must be 'numpy' or 'torch', got {lib!r}")
        self.name = lib
        self.lib = xp
        b = self._bool
        self._unary: dict[int, Callable] = {
            ca.OP_NEG: lambda a: -a,
            ca.OP_SQ: lambda a: a * a,
            ca.OP_TWICE: lambda a: a + a,
            ca.OP_SQRT: xp.sqrt, ca.OP_EXP: xp.exp, ca.OP_LOG: xp.log, ca.OP_SIN: xp.sin,
            ca.OP_COS: xp.cos, ca.OP_TAN: xp.tan, ca.OP_TANH: xp.tanh, ca.OP_ATAN: fn["atan"],
            ca.OP_FABS: xp.abs, ca.OP_INV: lambda a: 1.0 / a, ca.OP_ASSIGN: lambda a: a,
            ca.OP_SINH: xp.sinh, ca.OP_COSH: xp.cosh, ca.OP_SIGN: xp.sign,
            ca.OP_EXPM1: xp.expm1, ca.OP_LOG1P: xp.log1p, ca.OP_ASIN: fn["asin"],
            ca.OP_ACOS: fn["acos"], ca.OP_ASINH: fn["asinh"], ca.OP_ACOSH: fn["acosh"],
            ca.OP_ATANH: fn["atanh"], ca.OP_ERF: fn["erf"], ca.OP_FLOOR: xp.floor,
            ca.OP_CEIL: xp.ceil, ca.OP_NOT: lambda a: b(a == 0),
        }
        self._binary: dict[int, Callable] = {
            ca.OP_ADD: lambda a, c: a + c,
            ca.OP_SUB: lambda a, c: a - c,
            ca.OP_MUL: lambda a, c: a * c,
            ca.OP_DIV: lambda a, c: a / c,
            ca.OP_POW: lambda a, c: a**c,
            ca.OP_CONSTPOW: lambda a, c: a**c,
            ca.OP_FMIN: xp.fmin, ca.OP_FMAX: xp.fmax, ca.OP_ATAN2: fn["atan2"],
            ca.OP_HYPOT: xp.hypot, ca.OP_COPYSIGN: xp.copysign, ca.OP_FMOD: xp.fmod,
            # comparisons and logic give 0.0 / 1.0 (they appear in derivatives of fmax)
            ca.OP_LT: lambda a, c: b(a < c),
            ca.OP_LE: lambda a, c: b(a <= c),
            ca.OP_EQ: lambda a, c: b(a == c),
            ca.OP_NE: lambda a, c: b(a != c),
            ca.OP_AND: lambda a, c: b((a != 0) & (c != 0)),
            ca.OP_OR: lambda a, c: b((a != 0) | (c != 0)),
            # CasADi: c == 0 ? 0 : y (a NaN condition selects y)
            ca.OP_IF_ELSE_ZERO: lambda a, c: self._where(a != 0, c),
        }

    def constant(self, value: np.ndarray) -> Any:
        """Return a constant (exact float64 value) as an array of this library."""
        return self.asarray(value)

    def unary(self, op: int, a: Any) -> Any:
        """Apply unary CasADi operation ``op`` elementwise."""
        try:
            return self._unary[op](a)
        except KeyError:
            raise _unsupported(op, self.name, list(self._unary)) from None

    def binary(self, op: int, a: Any, b: Any) -> Any:
        """Apply binary CasADi operation ``op`` elementwise (with broadcasting)."""
        try:
            return self._binary[op](a, b)
        except KeyError:
            raise _unsupported(op, self.name, list(self._binary)) from None

    def matmul(self, a: Any, b: Any) -> Any:
        """Batched matrix product ``a @ b``."""
        return a @ b

    def sum(self, a: Any, axis: int | tuple[int, ...]) -> Any:
        """Sum over ``axis``."""
        return self._sum(a, axis)

    def structural(self, fn: Callable, *args: Any) -> Any:
        """Apply an exact rearrangement ``fn`` (indexing, reshape, transpose, concatenation)."""
        return fn(*args)


NUMPY = ArrayArithmetic("numpy")


def _unsupported(op: int, arith: str, supported) -> UnsupportedOperationError:
    names = ", ".join(sorted(op_name(o) for o in supported))
    return UnsupportedOperationError(
        f"CasADi operation {op_name(op)} is not supported by the {arith!r} arithmetic; "
        f"supported: {names}. Rewrite the expression with supported operations."
    )


# --------------------------------------------------------------------------- array helpers
def _is_torch(a) -> bool:
    return type(a).__module__.startswith("torch")


def _zeros_like_batch(a, shape):
    if _is_torch(a):
        return a.new_zeros(shape)
    return np.zeros(shape, dtype=np.result_type(a, float))


def _broadcast_batch(arrays: Sequence, tail_dims: Sequence[int]):
    """Broadcast the leading (batch) dimensions of arrays with given trailing ranks."""
    batches = [tuple(a.shape[: a.ndim - t]) for a, t in zip(arrays, tail_dims)]
    batch = np.broadcast_shapes(*batches)
    out = []
    for a, t in zip(arrays, tail_dims):
        shape = batch + tuple(a.shape[a.ndim - t:])
        if tuple(a.shape) != shape:
            a = a.expand(shape) if _is_torch(a) else np.broadcast_to(a, shape)
        out.append(a)
    return out, batch


def _concat(arrays: Sequence, axis: int):
    arrays, _ = _broadcast_batch(arrays, [2] * len(arrays))
    if _is_torch(arrays[0]):
        torch = deps.torch()

        return torch.cat(list(arrays), dim=axis)
    return np.concatenate(arrays, axis=axis)


def _scatter(v, rows, cols, shape):
    """Dense ``(..., r, c)`` array with ``v[..., k]`` at ``(rows[k], cols[k])``."""
    out = _zeros_like_batch(v, tuple(v.shape[:-1]) + tuple(shape))
    out[..., rows, cols] = v
    return out


class _Sp:
    """Sparsity pattern: shape and nonzero positions in CasADi's (column-major) order."""

    __slots__ = ("shape", "rows", "cols", "nnz", "dense")

    def __init__(self, sp: ca.Sparsity):
        self.shape = (sp.size1(), sp.size2())
        r, c = sp.get_triplet()
        self.rows = np.asarray(r, dtype=np.intp)
        self.cols = np.asarray(c, dtype=np.intp)
        self.nnz = sp.nnz()
        self.dense = sp.is_dense()

    def to_nz(self, arith, a):
        if self.dense:  # C-order dense matrix -> column-major nonzeros (a view, no gather)
            r, c = self.shape
            if c == 1:
                return arith.structural(lambda x: x.reshape(tuple(x.shape[:-2]) + (r,)), a)
            return arith.structural(
                lambda x: x.swapaxes(-1, -2).reshape(tuple(x.shape[:-2]) + (r * c,)), a)
        rows, cols = self.rows, self.cols
        return arith.structural(lambda x: x[..., rows, cols], a)

    def from_nz(self, arith, v):
        rows, cols, shape = self.rows, self.cols, self.shape
        if self.dense:  # column-major nonzeros -> C-order dense matrix
            r, c = shape
            return arith.structural(
                lambda x: x.reshape(tuple(x.shape[:-1]) + (c, r)).swapaxes(-1, -2), v
            )
        return arith.structural(lambda x: _scatter(x, rows, cols, shape), v)


def _top_register(fun: ca.Function, k: int) -> int:
    """The largest register instruction ``k`` reads or writes (``-1`` if none); an input's
    own numbers (input, nonzero) and an output's are not registers."""
    op = fun.instruction_id(k)
    regs = [] if op == ca.OP_INPUT else list(fun.instruction_input(k))
    regs += [] if op == ca.OP_OUTPUT else list(fun.instruction_output(k))
    return max(regs + [-1])


def _slice_indices(info: dict, n_hint: int | None = None) -> np.ndarray:
    """Nonzero index vector of a Get/SetNonzeros node from its ``info()``."""
    if "nz" in info:
        return np.asarray(info["nz"], dtype=np.intp)
    if "slice" in info and "inner" not in info:
        s = info["slice"]
        return np.arange(s["start"], s["stop"], s["step"], dtype=np.intp)
    if "inner" in info and "outer" in info:
        i, o = info["inner"], info["outer"]
        inner = np.arange(i["start"], i["stop"], i["step"], dtype=np.intp)
        outer = np.arange(o["start"], o["stop"], o["step"], dtype=np.intp)
        return (outer[:, None] + inner[None, :]).ravel()
    raise UnsupportedOperationError(f"cannot read nonzero indices from node info {info!r}")


# --------------------------------------------------------------------------- programs
class Program:
    """A CasADi Function compiled into walker steps (built once, evaluated many times)."""

    def __init__(self, fun: ca.Function):
        if not isinstance(fun, ca.Function):
            raise TypeError(f"expected a casadi.Function, got {type(fun).__name__}")
        self.fun = fun
        self.is_sx = fun.is_a("SXFunction")
        if not (self.is_sx or fun.is_a("MXFunction")):
            raise UnsupportedOperationError(
                f"Function {fun.name()!r} is a {fun.class_name()}; the walker evaluates "
                "SXFunction and MXFunction only (call .expand() or wrap it in an MX Function)."
            )
        self.n_in = fun.n_in()
        self.n_out = fun.n_out()
        self.sp_in = [_Sp(fun.sparsity_in(i)) for i in range(self.n_in)]
        self.sp_out = [_Sp(fun.sparsity_out(i)) for i in range(self.n_out)]
        # registers by index (``sz_w`` counts the doubles of an MX work vector, which
        # leaves out registers of values without nonzeros)
        self.n_registers = max([fun.sz_w()] + [_top_register(fun, k) + 1
                                              for k in range(fun.n_instructions())])
        self.ops: list[int] = []
        #: True when some operation needs a per-box check (see :data:`CHECKED_OPS`): an
        #: arithmetic with a ``check`` method is then told about it (steps built below)
        self.checked = False
        self._feeds = self._liveness()
        self.steps = self._compile_sx() if self.is_sx else self._compile_mx()

    def _liveness(self) -> list[int] | None:
        """Per instruction, the outputs it feeds (bit ``j``: output ``j``), or ``None``.

        Backward liveness over the register file (registers are reused). Computed only
        when the Function holds an operation of :data:`CHECKED_OPS` or a call.
        """
        f = self.fun
        n = f.n_instructions()
        ops = [f.instruction_id(k) for k in range(n)]
        if not any(op in CHECKED_OPS or op == ca.OP_CALL for op in ops):
            return None
        live: dict[int, int] = {}
        feeds = [0] * n
        #: per call instruction, per output of the callee: the outputs that output feeds
        self._call_feeds: dict[int, list[int]] = {}
        for k in range(n - 1, -1, -1):
            op = ops[k]
            i = f.instruction_input(k)
            o = f.instruction_output(k)
            if op == ca.OP_OUTPUT:
                live[i[0]] = live.get(i[0], 0) | (1 << o[0])
                continue
            per = [live.pop(reg, 0) if reg >= 0 else 0 for reg in o]
            m = 0
            for b in per:
                m |= b
            feeds[k] = m
            if op == ca.OP_CALL:
                self._call_feeds[k] = per
            if op in (ca.OP_INPUT, ca.OP_CONST):
                continue
            for reg in i:
                if reg >= 0:
                    live[reg] = live.get(reg, 0) | m
        return feeds

    def _check_feeds(self, k, op, ins, consts) -> np.ndarray | None:
        """The outputs instruction ``k`` feeds when its op must report checks
        (:data:`CHECKED_OPS`, arguments not statically safe), else ``None``."""
        if op not in CHECKED_OPS or _statically_safe(op, [consts.get(j) for j in ins]):
            return None
        self.checked = True
        m = self._feeds[k] if self._feeds is not None else -1
        return np.array([j for j in range(self.n_out) if (m >> j) & 1], dtype=np.intp)

    def _elementwise(self, k, op, o, ins, consts, base):
        """Step of an elementwise op; a checked step where :data:`CHECKED_OPS` asks."""
        feeds = self._check_feeds(k, op, ins, consts)
        if feeds is not None:
            return _checked(op, o, ins, feeds, base)
        if len(ins) == 1:
            return _unary(op, o, ins[0])
        return _binary(op, o, ins[0], ins[1])

    def _on_nonzeros(self, k, op, o, ins, consts, node):
        """Step of an elementwise MX op whose result has structural zeros, or ``None``.

        CasADi computes such an op on the result's nonzeros only (``y / x`` with a
        structural zero in ``y`` is a structural zero, whatever ``x`` is there). The dense
        registers hold ``0`` at structural zeros, so the op is applied to the result's
        nonzeros alone: a partial op is not evaluated, nor checked, outside them.
        """
        sp = node.sparsity()
        if sp.is_dense():
            return None
        out = _Sp(sp)
        rows, cols = out.rows, out.cols
        picks = []
        for j in range(len(ins)):
            shape = (node.dep(j).size1(), node.dep(j).size2())
            if shape == out.shape:
                picks.append(lambda x: x[..., rows, cols])
            elif shape == (1, 1):
                picks.append(lambda x: x[..., 0, :])
            else:
                return None
        return _mx_on_nonzeros(op, o, ins, picks, out, self._check_feeds(k, op, ins, consts))

    # -- SX: every register a batch of scalars
    def _compile_sx(self):
        f = self.fun
        steps = []
        consts: dict[int, np.ndarray] = {}  # registers holding a graph constant
        for k in range(f.n_instructions()):
            op = f.instruction_id(k)
            self.ops.append(op)
            i = f.instruction_input(k)
            o = f.instruction_output(k)
            n_steps = len(steps)
            if op == ca.OP_CONST:
                val = float(f.instruction_constant(k))
                consts[o[0]] = np.asarray(val)
                steps.append(_sx_const(o[0], val))
            elif op == ca.OP_INPUT:
                steps.append(_sx_input(o[0], i[0], i[1]))
            elif op == ca.OP_OUTPUT:
                steps.append(_sx_output(o[0], o[1], i[0]))
            elif op in UNARY_OPS:
                steps.append(self._elementwise(k, op, o[0], [i[0]], consts, 0))
            elif op in BINARY_OPS:
                steps.append(self._elementwise(k, op, o[0], [i[0], i[1]], consts, 0))
            else:
                raise UnsupportedOperationError(
                    f"SX operation {op_name(op)} in Function {f.name()!r} is not supported "
                    "by the instruction walker."
                )
            if op not in (ca.OP_CONST, ca.OP_OUTPUT) and len(steps) > n_steps:
                consts.pop(o[0], None)  # the register now holds a computed value
        return steps

    # -- MX: every register a batch of dense matrices
    def _compile_mx(self):
        f = self.fun
        steps = []
        prims = [e.primitives() for e in f.call(f.mx_in())]  # symbolic re-evaluation
        self.n_segments = [len(p) for p in prims]
        seen_out: dict[int, int] = {}
        zero_regs: set[int] = set()  # registers that hold an all-zero constant
        consts: dict[int, np.ndarray] = {}  # registers holding a graph constant
        fixed: set[int] = set()  # registers holding a value computed from constants only
        for k in range(f.n_instructions()):
            op = f.instruction_id(k)
            self.ops.append(op)
            i = list(f.instruction_input(k))
            o = list(f.instruction_output(k))
            z_in = op == ca.OP_MTIMES and i[0] in zero_regs
            zero_regs.difference_update(o)
            written = [reg for reg in o if reg >= 0] if op != ca.OP_OUTPUT else []
            from_consts = op in _FOLDABLE and all(reg in fixed for reg in i if reg >= 0)
            fixed.difference_update(written)
            n_steps = len(steps)
            if op == ca.OP_OUTPUT:  # outputs may be written in several primitive segments
                seg = seen_out.get(o[0], 0)
                seen_out[o[0]] = seg + 1
                prim = prims[o[0]][seg]
                steps.append(_mx_output(o[0], seg, i[0], _Sp(prim.sparsity())))
                continue
            node = f.instruction_MX(k)
            if op == ca.OP_CONST:
                val = np.array(ca.evalf(node), dtype=float).reshape(node.size1(), node.size2())
                steps.append(_sx_const(o[0], val))
                consts[o[0]] = val
                if not val.any() and not np.signbit(val).any():  # +0.0 only
                    zero_regs.add(o[0])
            elif op == ca.OP_INPUT:
                off = int(node.info().get("offset", 0))
                steps.append(_mx_input(o[0], i[0], off, _Sp(node.sparsity())))
            elif op in UNARY_OPS or op in BINARY_OPS:
                ins = [i[0]] if op in UNARY_OPS else [i[0], i[1]]
                sparse = self._on_nonzeros(k, op, o[0], ins, consts, node)
                steps.append(sparse if sparse is not None
                             else self._elementwise(k, op, o[0], ins, consts, 2))
            elif op == ca.OP_MTIMES:
                px, py = _product_patterns(node.dep(1).sparsity(), node.dep(2).sparsity())
                pout = _result_pattern(node)
                steps.append(_mx_mtimes(o[0], i[0], i[1], i[2], z_in, px, py, pout))
            elif op == ca.OP_DOT:
                pa = None
                if i[0] != i[1]:
                    sa, sb = node.dep(0).sparsity(), node.dep(1).sparsity()
                    both = sa * sb  # the entries CasADi multiplies
                    if both.nnz() < max(sa.nnz(), sb.nnz()):
                        pa = _Sp(both)
                steps.append(_mx_dot(o[0], i[0], i[1], pa))
            elif op == ca.OP_BILIN:  # xᵀ A y with inputs [A, x, y]
                sA, sx = node.dep(0).sparsity(), node.dep(1).sparsity()
                pA, py = _product_patterns(sA, node.dep(2).sparsity())
                rx, cx = (np.asarray(v, dtype=np.intp) for v in sx.get_triplet())
                used = np.isin(rx, np.asarray(sA.get_triplet()[0], dtype=np.intp))
                steps.append(_mx_bilin(o[0], i[0], i[1], i[2],
                                       (pA, _keep(sx, rx, cx, used), py)))
            elif op == ca.OP_TRANSPOSE:
                steps.append(_mx_struct(o[0], [i[0]], lambda a: a.swapaxes(-1, -2)))
            elif op == ca.OP_RESHAPE:
                steps.append(_mx_reshape(o[0], i[0], _Sp(node.dep(0).sparsity()),
                                         _Sp(node.sparsity())))
            elif op == ca.OP_PROJECT:  # the argument's entries at the node's pattern
                sp = _Sp(node.sparsity())
                steps.append(_mx_reshape(o[0], i[0], sp, sp))
            elif op == ca.OP_SPARSITY_CAST:  # the argument's nonzeros, in the node's pattern
                steps.append(_mx_reshape(o[0], i[0], _Sp(node.dep(0).sparsity()),
                                         _Sp(node.sparsity())))
            elif op == ca.OP_VERTCAT:
                steps.append(_mx_struct(o[0], i, lambda *a: _concat(a, -2)))
            elif op == ca.OP_HORZCAT:
                steps.append(_mx_struct(o[0], i, lambda *a: _concat(a, -1)))
            elif op in (ca.OP_HORZSPLIT, ca.OP_VERTSPLIT):
                offs = node.info()["offset"]
                sp_in = _Sp(node.dep(0).sparsity())
                outs = [(o[j], offs[j], offs[j + 1], _Sp(node.get_output(j).sparsity()))
                        for j in range(len(o)) if o[j] >= 0]
                steps.append(_mx_split(i[0], sp_in, outs))
            elif op == ca.OP_GETNONZEROS:
                nz = _slice_indices(node.info())
                steps.append(_mx_getnz(o[0], i[0], nz, _Sp(node.dep(0).sparsity()),
                                       _Sp(node.sparsity())))
            elif op in (ca.OP_SETNONZEROS, ca.OP_ADDNONZEROS):
                info = node.info()
                nz = _slice_indices(info)
                add = bool(info.get("add", op == ca.OP_ADDNONZEROS))
                steps.append(_mx_setnz(o[0], i[0], i[1], nz, add, _Sp(node.sparsity()),
                                       _Sp(node.dep(1).sparsity())))
            elif op == ca.OP_CALL:
                callee = node.which_function()
                prog = compile_function(callee)
                self.checked = self.checked or prog.checked
                per = self._call_feeds.get(k) if self._feeds is not None else None
                feeds = [np.array([j for j in range(self.n_out) if (m >> j) & 1], dtype=np.intp)
                         for m in (per or [-1] * prog.n_out)]
                steps.append(_mx_call(prog, i, o, feeds))
            else:
                raise UnsupportedOperationError(
                    f"MX operation {op_name(op)} in Function {f.name()!r} is not supported by "
                    "the instruction walker; supported are elementwise ops, mtimes, dot, "
                    "transpose, reshape, concatenation, splits, (get/set)nonzeros and calls."
                )
            if op == ca.OP_CONST:
                fixed.update(written)
            elif (from_consts and len(steps) == n_steps + 1 and len(written) == 1
                  and steps[-1].__name__ != "checked_step"):
                # the same value on every evaluation: once per caching arithmetic
                steps[-1] = _fixed(steps[-1], written[0])
                fixed.update(written)
            if op != ca.OP_CONST:
                for reg in written:  # the register now holds a computed value
                    consts.pop(reg, None)
        for j, n in enumerate(self.n_segments):
            if seen_out.get(j, 0) != n:
                raise UnsupportedOperationError(
                    f"output {j} of {f.name()!r} is written in {seen_out.get(j, 0)} segments, "
                    f"expected {n}; wrap the outputs in a fresh Function"
                )
        return steps

    def __call__(self, args: Sequence, arith=NUMPY) -> list:
        """Evaluate with ``args[i]`` of shape ``(..., nnz_in_i)``; return ``(..., nnz_out_j)``."""
        if len(args) != self.n_in:
            raise ValueError(
                f"Function {self.fun.name()!r} takes {self.n_in} inputs, got {len(args)}"
            )
        regs: list = [None] * self.n_registers
        outs: list = [None] * self.n_out
        ctx = (arith, args, outs)
        for step in self.steps:
            step(regs, ctx)
        if self.is_sx:
            return _finish_sx_outputs(self, outs, arith)
        return [_finish_mx_output(parts, n, arith) for parts, n in zip(outs, self.n_segments)]


# step factories (closures keep evaluation free of dispatch)
def _sx_const(o, value):
    cache: dict = {}  # per arithmetic that declares ``cache_constants`` (immutable values)

    def step(r, ctx):
        ar = ctx[0]
        c = cache.get(ar)
        if c is None:
            c = ar.constant(value)
            if getattr(ar, "cache_constants", False):
                cache[ar] = c
        r[o] = c
    return step


def _sx_input(o, ind, nz):
    def step(r, ctx):
        v = ctx[1][ind][..., nz]
        # symbolic arithmetics pass object arrays: hand them the element, not a 0-d array
        r[o] = v.item() if isinstance(v, np.ndarray) and v.dtype.kind == "O" and v.ndim == 0 else v
    return step


def _sx_output(ind, nz, src):
    def step(r, ctx):
        outs = ctx[2]
        if outs[ind] is None:
            outs[ind] = {}
        outs[ind][nz] = r[src]
    return step


def _unary(op, o, a):
    def step(r, ctx):
        r[o] = ctx[0].unary(op, r[a])
    return step


def _binary(op, o, a, b):
    def step(r, ctx):
        r[o] = ctx[0].binary(op, r[a], r[b])
    return step


def _checked(op, o, ins, feeds, base):
    """Elementwise step that reports its arguments and result to ``arith.check``.

    ``feeds``: the outputs of the Function this instruction feeds; ``base``: the number
    of trailing (non-batch) dimensions of a register (0 in SX, 2 in MX programs).
    """
    unary = len(ins) == 1
    a = ins[0]
    b = ins[-1]

    def checked_step(r, ctx):
        ar = ctx[0]
        args = (r[a],) if unary else (r[a], r[b])
        y = ar.unary(op, args[0]) if unary else ar.binary(op, args[0], args[1])
        chk = getattr(ar, "check", None)
        if chk is not None:
            chk(op, feeds, base, args, y)
        r[o] = y
    return checked_step


def _mx_on_nonzeros(op, o, ins, picks, out, feeds):
    """Elementwise MX step on the nonzeros of the result's sparsity ``out`` only.

    ``picks[j]`` takes argument ``j``'s entries there (shape ``(..., nnz)``, or
    ``(..., 1)`` for a scalar argument); ``feeds`` as in :func:`_checked`, or ``None``
    when the op reports no checks.
    """
    unary = len(ins) == 1

    def apply(r, ctx):
        ar = ctx[0]
        args = [ar.structural(pick, r[j]) for pick, j in zip(picks, ins)]
        y = ar.unary(op, args[0]) if unary else ar.binary(op, args[0], args[1])
        return ar, args, y

    if feeds is None:
        def step(r, ctx):
            ar, _, y = apply(r, ctx)
            r[o] = out.from_nz(ar, y)
        return step

    def checked_step(r, ctx):
        ar, args, y = apply(r, ctx)
        chk = getattr(ar, "check", None)
        if chk is not None:
            chk(op, feeds, 1, tuple(args), y)
        r[o] = out.from_nz(ar, y)
    return checked_step


#: MX operations whose value depends on their arguments only (no checks, no calls): with
#: constant arguments, computed once per arithmetic that caches constants (:func:`_fixed`)
_FOLDABLE = frozenset(UNARY_OPS | BINARY_OPS | {
    ca.OP_MTIMES, ca.OP_DOT, ca.OP_BILIN, ca.OP_TRANSPOSE, ca.OP_RESHAPE, ca.OP_PROJECT,
    ca.OP_SPARSITY_CAST, ca.OP_VERTCAT, ca.OP_HORZCAT, ca.OP_GETNONZEROS})


def _fixed(step, o):
    """``step``, whose arguments are graph constants or values computed from them only,
    evaluated once per arithmetic that declares ``cache_constants`` (its values are
    immutable and its operations pure: the same arguments give the same value) and reused
    afterwards, as :func:`_sx_const` reuses constants: a network's ``N(0)`` and the
    transposed weights of a derivative graph are not recomputed on every pass."""
    cache: dict = {}

    def fixed_step(r, ctx):
        ar = ctx[0]
        v = cache.get(ar)
        if v is None:
            step(r, ctx)
            if getattr(ar, "cache_constants", False):
                cache[ar] = r[o]
            return
        r[o] = v
    return fixed_step


def _statically_safe(op: int, consts: list) -> bool:
    """A checked operation whose constant arguments make it smooth and defined everywhere.

    ``consts[i]`` is the value of argument ``i`` when it is a graph constant, else ``None``.
    """
    info = OP_TABLE[op]
    if info.kind != "smooth" and any(c is None for c in consts):
        return False  # a varying argument may cross a kink or a jump
    if info.domain is None:
        return True
    with np.errstate(all="ignore"):
        if op in (ca.OP_DIV, ca.OP_FMOD):
            y = consts[1]
            return y is not None and bool(np.all(np.isfinite(y) & (y != 0)))
        if op in (ca.OP_POW, ca.OP_CONSTPOW):
            x, y = consts
            if y is not None and bool(np.all((np.floor(y) == y) & (y >= 0) & np.isfinite(y))):
                return True
            return x is not None and bool(np.all((x > 0) & np.isfinite(x)))
        if op == ca.OP_INV:
            x = consts[0]
            return x is not None and bool(np.all(np.isfinite(x) & (x != 0)))
    return False


def _mx_input(o, ind, off, sp):
    whole = off == 0

    def step(r, ctx):
        v = ctx[1][ind]
        if not (whole and v.shape[-1] == sp.nnz):
            v = ctx[0].structural(lambda a: a[..., off:off + sp.nnz], v)
        r[o] = sp.from_nz(ctx[0], v)
    return step


def _mx_output(ind, seg, src, sp):
    def step(r, ctx):
        outs = ctx[2]
        if outs[ind] is None:
            outs[ind] = {}
        outs[ind][seg] = sp.to_nz(ctx[0], r[src])
    return step


def _product_patterns(sx: ca.Sparsity, sy: ca.Sparsity):
    """Patterns ``(px, py)`` that the factors of ``x y`` are projected onto, or ``None``.

    CasADi multiplies nonzeros only: a nonzero ``x_ik`` whose row ``k`` of ``y`` is
    structurally zero (or ``y_kj`` whose column ``k`` of ``x`` is) takes no part, so
    a value there that is not finite (``log`` of a negative number) must not reach the
    product as ``0 · nan``. The projection drops them (``None``: nothing to drop).
    """
    rx, cx = (np.asarray(v, dtype=np.intp) for v in sx.get_triplet())
    ry, cy = (np.asarray(v, dtype=np.intp) for v in sy.get_triplet())
    if sx.size2() != sy.size1():  # a scalar factor (no inner dimension to match)
        return None, None
    used_x = np.isin(cx, ry)  # x_ik meets some y_kj
    used_y = np.isin(ry, cx)
    return _keep(sx, rx, cx, used_x), _keep(sy, ry, cy, used_y)


def _keep(sp: ca.Sparsity, rows, cols, used):
    """The pattern of ``sp``'s nonzeros marked ``used`` (``None`` when that is all)."""
    if used.all():
        return None
    return _Sp(ca.Sparsity.triplet(sp.size1(), sp.size2(), rows[used].tolist(),
                                   cols[used].tolist()))


def _result_pattern(node) -> _Sp | None:
    """The pattern of ``z + x y`` (``mac``) when the dense product has entries outside it.

    CasADi computes a product's result on the nonzeros of its own pattern, which its
    derivatives make smaller than the product's (``mac(a, b, zeros(pattern))``); the dense
    product holds values at the other entries, which must read as structural zeros.
    """
    so = node.sparsity()
    if so.is_dense():
        return None
    sz, sx, sy = (node.dep(j).sparsity() for j in range(3))

    def mask(sp):
        m = np.zeros((sp.size1(), sp.size2()), dtype=bool)
        r, c = sp.get_triplet()
        m[np.asarray(r, dtype=np.intp), np.asarray(c, dtype=np.intp)] = True
        return m

    if sx.size2() != sy.size1():  # a scalar factor: the product has the other's pattern
        prod = mask(sx) if sy.numel() == 1 else mask(sy)
    else:
        prod = (mask(sx).astype(np.int64) @ mask(sy).astype(np.int64)) > 0
    if prod.shape != mask(so).shape:
        return _Sp(so)
    outside = (prod | mask(sz)) & ~mask(so)
    return _Sp(so) if outside.any() else None


def _project(ar, sp, v):
    """``v`` (a dense register) with the entries outside pattern ``sp`` set to 0."""
    return v if sp is None else sp.from_nz(ar, sp.to_nz(ar, v))


def _mx_mtimes(o, z, x, y, z_is_zero=False, px=None, py=None, pout=None):
    if px is not None or py is not None or pout is not None:
        def step(r, ctx):
            ar = ctx[0]
            prod = ar.matmul(_project(ar, px, r[x]), _project(ar, py, r[y]))
            r[o] = _project(ar, pout, prod if z_is_zero else ar.binary(ca.OP_ADD, r[z], prod))
        return step
    if z_is_zero:  # z + x y with z = +0: adding zero is exact (same shape (r, c))
        def step(r, ctx):
            r[o] = ctx[0].matmul(r[x], r[y])
        return step

    def step(r, ctx):
        ar = ctx[0]
        r[o] = ar.binary(ca.OP_ADD, r[z], ar.matmul(r[x], r[y]))
    return step


def _mx_dot(o, a, b, both=None):
    # dot(v, v) (``sumsqr``: V = ‖N(x) − N(0)‖², ‖x‖², ‖∇V‖²) as a sum of squares: an
    # interval arithmetic then encloses it by ``[0, ...]`` instead of the product of two
    # independent copies of ``v`` (e.g. [-0.75, 5] for ‖x‖² on [-1, 1] × [0.5, 2]); one
    # register holds one value, so the rewrite is exact
    def step(r, ctx):
        ar = ctx[0]
        if a == b:
            total = ar.sum(ar.unary(ca.OP_SQ, r[a]), (-2, -1))
            nonneg = getattr(ar, "nonneg", None)  # a sum of squares is >= 0 (e.g. under sqrt)
            if nonneg is not None:
                total = nonneg(total)
        else:  # over the entries both hold (``both``: where that is not all of them)
            total = ar.sum(ar.binary(ca.OP_MUL, _project(ar, both, r[a]),
                                     _project(ar, both, r[b])), (-2, -1))
        r[o] = ar.structural(lambda v: v[..., None, None], total)
    return step


def _mx_bilin(o, A, x, y, patterns=(None, None, None)):
    pA, px, py = patterns  # as for a product (:func:`_product_patterns`)

    def step(r, ctx):
        ar = ctx[0]
        prod = ar.binary(ca.OP_MUL, _project(ar, px, r[x]),
                         ar.matmul(_project(ar, pA, r[A]), _project(ar, py, r[y])))
        r[o] = ar.structural(lambda v: v[..., None, None], ar.sum(prod, (-2, -1)))
    return step


def _mx_struct(o, ins, fn):
    def step(r, ctx):
        r[o] = ctx[0].structural(fn, *[r[j] for j in ins])
    return step


def _mx_reshape(o, a, sp_in, sp_out):
    def step(r, ctx):
        ar = ctx[0]
        r[o] = sp_out.from_nz(ar, sp_in.to_nz(ar, r[a]))
    return step


def _mx_split(a, sp_in, outs):
    def step(r, ctx):
        ar = ctx[0]
        nz = sp_in.to_nz(ar, r[a])
        for reg, lo, hi, sp in outs:
            part = ar.structural(lambda v, lo=lo, hi=hi: v[..., lo:hi], nz)
            r[reg] = sp.from_nz(ar, part)
    return step


def _mx_getnz(o, a, nz, sp_in, sp_out):
    valid = nz >= 0
    if valid.all():
        def pick(v):
            return v[..., nz]
    else:
        safe = np.where(valid, nz, 0)

        def pick(v):
            return v[..., safe] * valid

    def step(r, ctx):
        ar = ctx[0]
        r[o] = sp_out.from_nz(ar, ar.structural(pick, sp_in.to_nz(ar, r[a])))
    return step


def _rounds(dst: np.ndarray, src: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(dst, src)`` pairs split into rounds without a repeated ``dst``: round ``k`` holds
    the ``k``-th occurrence of each index, in order. CasADi adds (or assigns) repeated
    indices one after the other; one fancy-indexed write would keep only one of them."""
    seen: dict[int, int] = {}
    parts: list[list[int]] = []
    for i, d in enumerate(dst.tolist()):
        k = seen.get(d, 0)
        seen[d] = k + 1
        if k == len(parts):
            parts.append([])
        parts[k].append(i)
    return [(dst[np.asarray(p, dtype=np.intp)], src[np.asarray(p, dtype=np.intp)])
            for p in parts]


def _mx_setnz(o, y, x, nz, add, sp_out, sp_x):
    valid = nz >= 0
    rounds = _rounds(nz[valid], np.nonzero(valid)[0])

    def put_at(dst, src=None):  # out[dst] = s, or s[src]
        def put(b, s):
            (b, s), _ = _broadcast_batch([b, s], [1, 1])
            out = b.clone() if _is_torch(b) else np.array(b, dtype=float)
            out[..., dst] = s if src is None else s[..., src]
            return out
        return put

    def step(r, ctx):
        ar = ctx[0]
        res = sp_out.to_nz(ar, r[y])
        val = sp_x.to_nz(ar, r[x])
        for dst, src in rounds:
            if add:  # adding is arithmetic: do it with the arithmetic (rounding matters)
                part = ar.binary(ca.OP_ADD, ar.structural(lambda b, dst=dst: b[..., dst], res),
                                 ar.structural(lambda v, src=src: v[..., src], val))
                res = ar.structural(put_at(dst), res, part)
            else:
                res = ar.structural(put_at(dst, src), res, val)
        r[o] = sp_out.from_nz(ar, res)
    return step


def _mx_call(prog: Program, ins, outs, feeds):
    """A call step; ``feeds[j]``: the caller's outputs that the callee's output ``j`` feeds."""
    def step(r, ctx):
        ar = ctx[0]
        args = [prog.sp_in[j].to_nz(ar, r[ins[j]]) for j in range(prog.n_in)]
        enter = getattr(ar, "enter_call", None) if prog.checked else None
        if enter is None:
            res = prog(args, ar)
        else:  # checks inside the callee: to the caller's outputs its outputs feed
            token = enter(feeds)
            try:
                res = prog(args, ar)
            finally:
                ar.exit_call(token)
        for j, reg in enumerate(outs):
            if reg >= 0:
                r[reg] = prog.sp_out[j].from_nz(ar, res[j])
    return step


# --------------------------------------------------------------------------- public API
_CACHE: dict[int, tuple[ca.Function, Program]] = {}


def compile_function(fun: ca.Function) -> Program:
    """Compile (once, cached per Function object) a CasADi Function into a :class:`Program`."""
    key = id(fun)
    hit = _CACHE.get(key)
    if hit is not None and hit[0] is fun:
        return hit[1]
    prog = Program(fun)
    _CACHE[key] = (fun, prog)
    return prog


def _finish_sx_outputs(prog: Program, outs: list, arith) -> list:
    res = []
    for j, parts in enumerate(outs):
        n = prog.sp_out[j].nnz
        if n == 0:
            res.append(None)
            continue
        if not parts or len(parts) != n:  # every output nonzero is written by OP_OUTPUT
            raise UnsupportedOperationError(f"output {j} has unwritten nonzeros")
        cols = [parts[k] for k in range(n)]
        if getattr(arith, "symbolic", False):  # symbolic arithmetics (dReal, SMT-LIB): lists
            res.append(cols)
        else:
            res.append(arith.structural(_stack_last, *cols))
    return res


def _finish_mx_output(parts, n, arith):
    if n == 0 or parts is None:
        return None
    if n == 1:
        return parts[0]
    return arith.structural(_concat_last, *[parts[k] for k in range(n)])


def _concat_last(*parts):
    b = np.broadcast_shapes(*[tuple(p.shape[:-1]) for p in parts])
    if _is_torch(parts[0]):
        torch = deps.torch()

        return torch.cat([p.expand(b + (p.shape[-1],)) for p in parts], dim=-1)
    return np.concatenate([p if p.shape == b + (p.shape[-1],) else
                           np.broadcast_to(p, b + (p.shape[-1],)) for p in parts], axis=-1)


def _stack_last(*cols):
    b = np.broadcast_shapes(*[tuple(c.shape) for c in cols])
    if _is_torch(cols[0]):
        torch = deps.torch()

        return torch.stack([c.expand(b) for c in cols], dim=-1)
    return np.stack([c if c.shape == b else np.broadcast_to(c, b) for c in cols], axis=-1)


def evaluate(fun: ca.Function | Program, args: Sequence, arith=NUMPY) -> list:
    """Evaluate a CasADi Function on a batch of points with the given arithmetic.

    Parameters
    ----------
    fun : casadi.Function or Program
        An ``SXFunction`` or ``MXFunction``.
    args : sequence of arrays
        ``args[i]`` has shape ``(..., nnz_in_i)``: the nonzeros of input ``i``
        (for a column vector input of size ``n``: shape ``(..., n)``).
    arith : arithmetic, optional
        :data:`NUMPY` (default), ``ArrayArithmetic("torch")``, an interval
        arithmetic, ... Each input must be a value of that arithmetic.

    Returns
    -------
    list
        One value per output, of shape ``(..., nnz_out_j)``.
    """
    if not isinstance(fun, (ca.Function, Program)):
        raise DimensionError(f"evaluate needs a casadi.Function, got {type(fun).__name__}; "
                             "build one with casadi.Function(name, [x], [expression])")
    prog = fun if isinstance(fun, Program) else compile_function(fun)
    if arith is None or isinstance(arith, (str, bytes, int, float)):
        raise DimensionError(f"arith must be an arithmetic (the default NUMPY, "
                             f"ArrayArithmetic('torch'), an interval arithmetic), got {arith!r}")
    if isinstance(args, (str, bytes, np.ndarray)) or not hasattr(args, "__len__") or \
            len(args) != prog.n_in:
        got = f"{len(args)} array(s)" if isinstance(args, (list, tuple)) else \
            type(args).__name__
        raise DimensionError(f"Function {prog.fun.name()!r} takes {prog.n_in} input(s): pass a "
                             f"list of one array per input, got {got}")
    if arith is NUMPY or getattr(arith, "name", "") == "numpy":
        try:
            args = [np.asarray(a, dtype=float) for a in args]
        except (TypeError, ValueError):
            raise DimensionError(f"the inputs of Function {prog.fun.name()!r} must be arrays "
                                 "of numbers") from None
    for a, sp in zip(args, prog.sp_in):
        shape = getattr(a, "shape", ())
        if not shape or shape[-1] != sp.nnz:
            raise DimensionError(
                f"input of Function {prog.fun.name()!r} needs a trailing dimension of "
                f"{sp.nnz} (nonzeros of a {sp.shape[0]}x{sp.shape[1]} input), got shape "
                f"{tuple(shape)}"
            )
    return prog(args, arith)


# --------------------------------------------------------------------------- exact values
class _Real:
    """A real number the exact arithmetic does not compute (defined and finite), or, for
    :data:`UNDEFINED`, a value outside an operation's domain (``log(0)``, ``1/0``)."""

    __slots__ = ("name",)

    def __init__(self, name: str):
        self.name = name

    def __repr__(self) -> str:
        return self.name


#: a defined real number whose exact value is not computed (``sin(1)``)
REAL = _Real("REAL")
#: not a real number: an operation applied outside its domain
UNDEFINED = _Real("UNDEFINED")

# value of an elementary function at the rational points where it is rational
_SPECIAL = {
    ca.OP_EXP: {0: 1}, ca.OP_EXPM1: {0: 0}, ca.OP_LOG: {1: 0}, ca.OP_LOG1P: {0: 0},
    ca.OP_SIN: {0: 0}, ca.OP_COS: {0: 1}, ca.OP_TAN: {0: 0}, ca.OP_ASIN: {0: 0},
    ca.OP_ACOS: {1: 0}, ca.OP_ATAN: {0: 0}, ca.OP_SINH: {0: 0}, ca.OP_COSH: {0: 1},
    ca.OP_TANH: {0: 0}, ca.OP_ASINH: {0: 0}, ca.OP_ACOSH: {1: 0}, ca.OP_ATANH: {0: 0},
    ca.OP_ERF: {0: 0},
}
# the domain of the partial elementary functions (rational arguments)
_DOMAIN = {
    ca.OP_LOG: lambda q: q > 0, ca.OP_LOG1P: lambda q: q > -1, ca.OP_SQRT: lambda q: q >= 0,
    ca.OP_ASIN: lambda q: -1 <= q <= 1, ca.OP_ACOS: lambda q: -1 <= q <= 1,
    ca.OP_ACOSH: lambda q: q >= 1, ca.OP_ATANH: lambda q: -1 < q < 1,
    ca.OP_INV: lambda q: q != 0,
}
_MAX_EXACT_POWER = 64
#: a rational whose numerator or denominator needs more bits than this becomes REAL (a
#: chain of squarings doubles the size each time: the evaluation must stay fast)
_MAX_EXACT_BITS = 4096


def _capped(q):
    """``q``, or :data:`REAL` when it has grown past :data:`_MAX_EXACT_BITS`."""
    if isinstance(q, Fraction) and (q.numerator.bit_length() > _MAX_EXACT_BITS
                                    or q.denominator.bit_length() > _MAX_EXACT_BITS):
        return REAL
    return q


def _rational_sqrt(q: Fraction):
    """``√q`` when it is rational, else :data:`REAL` (``q ≥ 0``)."""
    a, b = math.isqrt(q.numerator), math.isqrt(q.denominator)
    return Fraction(a, b) if a * a == q.numerator and b * b == q.denominator else REAL


class ExactPointArithmetic:
    """Exact evaluation of an SX graph at a point, for the questions "is ``f(0)`` exactly 0"
    that float evaluation cannot answer.

    Every value is a :class:`fractions.Fraction` (the exact real value: every float constant
    of the graph is the rational it denotes, and ``+ - * /``, integer powers, ``fabs``,
    ``fmin``, comparisons, ... are exact), :data:`REAL` (a defined real number the
    arithmetic does not compute: ``sin(1)``, ``√2``) or :data:`UNDEFINED` (an operation
    outside its domain, or a partial one whose argument is only known to be real). The
    elementary functions are exact at the points where their value is rational (``sin 0 =
    0``, ``exp 0 = 1``, ``log 1 = 0``, ...). ``0 · REAL = 0`` exactly, so a term that
    vanishes at the point vanishes whatever its other factor is. Nothing is rounded: an
    output found to be ``Fraction(0)`` is the real number 0, which no float evaluation (and
    no substitution into a CasADi graph, which folds constants in float64) can prove. A
    rational that grows past 4096 bits becomes ``REAL``. Signed zeros are not modelled:
    ``-0.0`` is the rational 0, so ``copysign`` and ``atan2`` at a zero argument are those of
    ``+0`` (CasADi's floats tell the zeros apart); both are non-smooth operations, which the
    callers refuse before they evaluate.

    Examples
    --------
    >>> x = ca.SX.sym("x")
    >>> exact_values(ca.Function("f", [x], [((x**2 + 1e16) + 1) - 1e16]), [0])
    [Fraction(1, 1)]
    >>> exact_values(ca.Function("f", [x], [ca.sin(x) * ca.exp(x + 1)]), [0])
    [Fraction(0, 1)]
    """

    name = "exact point"
    symbolic = True   # scalar values, one per register; outputs as lists

    def constant(self, value):
        v = float(np.asarray(value, dtype=float))
        return Fraction(v) if math.isfinite(v) else UNDEFINED

    def unary(self, op: int, a):
        return _capped(self._unary(op, a))

    def binary(self, op: int, a, b):
        return _capped(self._binary(op, a, b))

    def _unary(self, op: int, a):
        if op not in OP_TABLE or OP_TABLE[op].arity != 1:
            raise _unsupported(op, self.name, UNARY_OPS)
        if a is UNDEFINED:
            return UNDEFINED
        if a is REAL:
            # a partial function of an unknown real may leave its domain
            return UNDEFINED if OP_TABLE[op].domain is not None else REAL
        if op in _DOMAIN and not _DOMAIN[op](a):
            return UNDEFINED
        if op == ca.OP_NEG:
            return -a
        if op in (ca.OP_ASSIGN,):
            return a
        if op == ca.OP_SQ:
            return a * a
        if op == ca.OP_TWICE:
            return a + a
        if op == ca.OP_FABS:
            return abs(a)
        if op == ca.OP_INV:
            return 1 / a
        if op == ca.OP_SQRT:
            return _rational_sqrt(a)
        if op == ca.OP_SIGN:
            return Fraction((a > 0) - (a < 0))
        if op == ca.OP_FLOOR:
            return Fraction(math.floor(a))
        if op == ca.OP_CEIL:
            return Fraction(math.ceil(a))
        if op == ca.OP_NOT:
            return Fraction(int(a == 0))
        special = _SPECIAL.get(op, {})
        return Fraction(special[a]) if a in special else REAL

    def _binary(self, op: int, a, b):
        if op not in OP_TABLE or OP_TABLE[op].arity != 2:
            raise _unsupported(op, self.name, BINARY_OPS)
        if op == ca.OP_IF_ELSE_ZERO:           # c ? y : 0, the branch not taken does not count
            if isinstance(a, Fraction):
                return b if a != 0 else Fraction(0)
            if a is UNDEFINED or b is UNDEFINED:
                return UNDEFINED
            return Fraction(0) if b == 0 else REAL
        if a is UNDEFINED or b is UNDEFINED:
            return UNDEFINED
        if op == ca.OP_MUL and (isinstance(a, Fraction) and a == 0
                                or isinstance(b, Fraction) and b == 0):
            return Fraction(0)
        exact = isinstance(a, Fraction) and isinstance(b, Fraction)
        if op in (ca.OP_DIV, ca.OP_FMOD):
            if not (isinstance(b, Fraction) and b != 0):
                return UNDEFINED
            if isinstance(a, Fraction) and a == 0:
                return Fraction(0)
            if not exact:
                return REAL
            return a / b if op == ca.OP_DIV else a - b * int(a / b)   # C fmod: truncation
        if op in (ca.OP_POW, ca.OP_CONSTPOW):
            return self._pow(a, b)
        if not exact:
            total = OP_TABLE[op].domain is None
            return REAL if total else UNDEFINED
        if op == ca.OP_ADD:
            return a + b
        if op == ca.OP_SUB:
            return a - b
        if op == ca.OP_MUL:
            return a * b
        if op == ca.OP_FMIN:
            return min(a, b)
        if op == ca.OP_FMAX:
            return max(a, b)
        if op == ca.OP_HYPOT:
            return _rational_sqrt(a * a + b * b)
        if op == ca.OP_COPYSIGN:
            return abs(a) if b >= 0 else -abs(a)   # (copysign(x, -0.0): -0.0 is the rational 0)
        if op == ca.OP_ATAN2:
            return Fraction(0) if a == 0 and b >= 0 else REAL
        compare = {ca.OP_LT: a < b, ca.OP_LE: a <= b, ca.OP_EQ: a == b, ca.OP_NE: a != b,
                   ca.OP_AND: a != 0 and b != 0, ca.OP_OR: a != 0 or b != 0}
        return Fraction(int(compare[op]))

    @staticmethod
    def _pow(a, b):
        if not isinstance(b, Fraction):
            return UNDEFINED if not (isinstance(a, Fraction) and a > 0) else REAL
        if b.denominator == 1:
            k = int(b)
            if k == 0:
                return Fraction(1)
            if not isinstance(a, Fraction):
                return REAL if k > 0 else UNDEFINED
            if a == 0:
                return Fraction(0) if k > 0 else UNDEFINED
            return a ** k if abs(k) <= _MAX_EXACT_POWER else REAL
        if not isinstance(a, Fraction) or a < 0:
            return UNDEFINED
        if a in (0, 1):
            return Fraction(a) if b > 0 or a == 1 else UNDEFINED
        return REAL

    def structural(self, fn, *args):
        return fn(*args)


def exact_values(fun: ca.Function, point) -> list | None:
    """The outputs of the single-input ``fun`` at ``point`` in :class:`ExactPointArithmetic`
    (a flat list over the nonzeros of every output; ``None`` when the graph is not an SX
    graph the arithmetic can walk). ``point``: floats or :class:`fractions.Fraction`, or
    :data:`REAL` for a coordinate that stands for every real number (an output exactly 0
    is then 0 for all of them)."""
    if fun.n_in() != 1 or not fun.is_a("SXFunction"):
        return None
    pt = np.empty(len(point), dtype=object)
    for i, v in enumerate(point):
        pt[i] = v if isinstance(v, (Fraction, _Real)) else Fraction(float(v))
    try:
        outs = evaluate(fun, [pt], ExactPointArithmetic())
    except UnsupportedOperationError:
        return None
    return [v for out in outs if out is not None for v in out]
