"""A scalar CasADi graph as plain JSON data, read back without running anything.

A certificate's ``V`` that is not a network (a quadratic or an SOS polynomial) is saved as
the instruction list of its ``SXFunction``: each instruction an operation of
:data:`~nlyap_opt.kernel.walker.OP_TABLE` (or an input, a constant, an output) with its
registers. Reading it rebuilds the expression operation by operation
(``casadi.SX.unary`` / ``casadi.SX.binary``) after checking every field, so a file can
describe arithmetic only. CasADi's own serialised Functions are not read: loading one can
open a shared library or start a compiler named inside the file.
"""

from __future__ import annotations

import math

import casadi as ca

from .errors import ConfigError
from .walker import BINARY_OPS, OP_TABLE, UNARY_OPS, op_name

FORMAT = "nlyap-sx-function"
VERSION = 1
#: the most instructions and registers a file may declare (a quadratic in 20 states has
#: about 900 instructions; an SOS polynomial of degree 6 in 4 states about 2 000)
MAX_INSTRUCTIONS = 2_000_000
#: the largest file :func:`from_json`'s callers read (its instructions at most, as JSON)
MAX_BYTES = 64 << 20

_BY_NAME = {info.name: op for op, info in OP_TABLE.items()}
_SPECIAL = {"OP_CONST": ca.OP_CONST, "OP_INPUT": ca.OP_INPUT, "OP_OUTPUT": ca.OP_OUTPUT}


def to_json(fun: ca.Function) -> dict:
    """The instruction list of ``fun`` (an ``SXFunction`` with one dense column input and
    one output, e.g. ``V(x)``) as JSON data.

    Examples
    --------
    >>> import casadi as ca
    >>> x = ca.SX.sym("x", 2)
    >>> d = to_json(ca.Function("V", [x], [x[0] ** 2 + 3 * x[1]]))
    >>> float(from_json(d)(ca.DM([1.0, 2.0])))
    7.0
    """
    if not fun.is_a("SXFunction") or fun.n_in() != 1 or fun.n_out() != 1:
        raise ValueError("to_json takes an SXFunction of one input and one output")
    if not (fun.sparsity_in(0).is_dense() and fun.sparsity_in(0).size2() == 1):
        raise ValueError("to_json takes a dense column input")
    ins = []
    for k in range(fun.n_instructions()):
        op = fun.instruction_id(k)
        row = [op_name(op), list(fun.instruction_output(k)), list(fun.instruction_input(k))]
        if op == ca.OP_CONST:
            row.append(float(fun.instruction_constant(k)))
        ins.append(row)
    return {"format": FORMAT, "version": VERSION, "n_in": int(fun.nnz_in(0)),
            "n_out": int(fun.nnz_out(0)), "out_rows": int(fun.size1_out(0)),
            "out_cols": int(fun.size2_out(0)), "registers": int(fun.sz_w()),
            "instructions": ins}


def _int(v, what: str, lo: int, hi: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v < hi:
        raise ConfigError(f"{what} must be an integer in [{lo}, {hi}), got {v!r}")
    return v


def from_json(d, name: str = "V") -> ca.Function:
    """The ``SXFunction`` that :func:`to_json` described, rebuilt operation by operation;
    anything else (another format, an unknown operation, a register or index out of range,
    a register read before it is written, a non-finite constant) raises
    :class:`ConfigError`."""
    if not isinstance(d, dict) or d.get("format") != FORMAT or d.get("version") != VERSION:
        raise ConfigError(f"not a {FORMAT} file of version {VERSION}")
    n_in = _int(d.get("n_in"), "n_in", 1, 100_000)
    n_out = _int(d.get("n_out"), "n_out", 0, 100_000)
    rows = _int(d.get("out_rows"), "out_rows", 0, 100_001)
    cols = _int(d.get("out_cols"), "out_cols", 0, 100_001)
    if rows * cols != n_out:
        raise ConfigError(f"out_rows·out_cols ({rows}·{cols}) must equal n_out ({n_out})")
    n_reg = _int(d.get("registers"), "registers", 0, MAX_INSTRUCTIONS)
    ins = d.get("instructions")
    if not isinstance(ins, list) or len(ins) > MAX_INSTRUCTIONS:
        raise ConfigError(f"instructions must be a list of at most {MAX_INSTRUCTIONS}")
    x = ca.SX.sym("x", n_in)
    reg: list = [None] * n_reg
    out: list = [None] * n_out
    for k, row in enumerate(ins):
        if not isinstance(row, list) or len(row) not in (3, 4) or not isinstance(row[0], str):
            raise ConfigError(f"instruction {k} must be [name, outputs, inputs(, constant)]")
        name_k, o, i = row[0], row[1], row[2]
        op = _SPECIAL.get(name_k, _BY_NAME.get(name_k))
        if op is None:
            raise ConfigError(f"instruction {k}: unknown operation {name_k!r}")
        if not (isinstance(o, list) and isinstance(i, list)):
            raise ConfigError(f"instruction {k}: outputs and inputs must be lists")
        where = f"instruction {k} ({name_k})"
        if op == ca.OP_CONST:
            c = row[3] if len(row) == 4 else None
            finite = (isinstance(c, float) and math.isfinite(c)) or (
                isinstance(c, int) and not isinstance(c, bool) and abs(c) <= 2**53)
            if not finite:
                raise ConfigError(f"{where}: the constant must be a finite number")
            if len(o) != 1 or i:
                raise ConfigError(f"{where}: one output register, no arguments")
            reg[_int(o[0], f"{where} output", 0, n_reg)] = ca.SX(float(c))
            continue
        if len(row) != 3:
            raise ConfigError(f"{where}: only constants carry a value")
        if op == ca.OP_INPUT:
            if len(o) != 1 or len(i) != 2:
                raise ConfigError(f"{where}: [register], [input, index]")
            _int(i[0], f"{where} input", 0, 1)
            reg[_int(o[0], f"{where} output", 0, n_reg)] = x[_int(i[1], f"{where} index",
                                                                   0, n_in)]
            continue

        def read(r):
            v = reg[_int(r, f"{where} argument", 0, n_reg)]
            if v is None:
                raise ConfigError(f"{where}: register {r} is read before it is written")
            return v

        if op == ca.OP_OUTPUT:
            if len(o) != 2 or len(i) != 1:
                raise ConfigError(f"{where}: [output, index], [register]")
            _int(o[0], f"{where} output", 0, 1)
            out[_int(o[1], f"{where} index", 0, n_out)] = read(i[0])
            continue
        if len(o) != 1:
            raise ConfigError(f"{where}: one output register")
        dst = _int(o[0], f"{where} output", 0, n_reg)
        if op in UNARY_OPS:
            if len(i) != 1:
                raise ConfigError(f"{where}: one argument")
            reg[dst] = ca.SX.unary(op, read(i[0]))
        elif op in BINARY_OPS:
            if len(i) != 2:
                raise ConfigError(f"{where}: two arguments")
            reg[dst] = ca.SX.binary(op, read(i[0]), read(i[1]))
        else:  # pragma: no cover - the table holds unary and binary operations only
            raise ConfigError(f"{where}: not an elementwise operation")
    if any(v is None for v in out):
        raise ConfigError("not every output entry is written")
    y = ca.reshape(ca.vertcat(*out), rows, cols) if n_out else ca.SX(rows, cols)
    fun = ca.Function(name, [x], [y])
    # CasADi simplifies while it builds (x/x to 1, sq(sqrt(x)) to x): the function is the
    # file's only if it gives back the same instruction list
    if to_json(fun)["instructions"] != ins:
        raise ConfigError("the instructions do not rebuild to themselves (CasADi would "
                          "simplify them); rerun the command that wrote the file")
    return fun
