r"""One formula builder for the dReal backend and the SMT-LIB export.

The SX expansion of a problem's CasADi Function is walked (``nlyap_opt.kernel.walker``) with
:class:`FormulaArithmetic`, whose values are :class:`Term` nodes of one hash-consed
expression DAG (:class:`TermTable`). The result, a :class:`Formula`, is what both consumers
read: :func:`verification.smtlib.to_smtlib` writes it as SMT-LIB text (``let`` bindings for
shared nodes) and the dReal backend turns it into dReal ``Expression`` objects (one Python
object per DAG node, reused wherever the node is used). Nothing is encoded twice.

Compactness (dReal works on terms without sharing, so the size of the *expanded* tree is
what it pays for):

- structurally equal subterms are one node (hash-consing);
- exact real-arithmetic identities only: ``x + 0 → x``, ``x·1 → x``, ``x·0 → 0``,
  ``x·(−1) → −x``, ``−(−x) → x``, ``x − x → 0``, ``x/1 → x``, ``x^1 → x``; constants are
  folded only where the result is exactly a float64 (checked with rationals), so every
  constant of the formula is the exact value of a float64 of the graph;
- ``sq(x)`` is ``x^2`` (``x`` once), ``twice(x)`` is ``2·x``; the gradient of a tanh layer
  stays CasADi's ``(1 − t^2)`` with ``t`` the shared node of the forward pass;
- linear combinations are regrouped where that makes the expanded tree smaller
  (:class:`CollectingArithmetic`, exact: distributivity and commutativity only). CasADi's
  reverse-mode gradient repeats every network output once per neuron; regrouped, the Lie
  derivative is about the size of the one written by hand (``bench/encoding.py``: 0.85–1.14
  of a hand-written encoding on the published network sizes, where the former encoding
  was 1.4–2.6; a 2-30-30 V: 3.0 M expanded nodes instead of 87 M).

Partial operations (domain conditions)
--------------------------------------
dReal is not domain-aware, so every partial operation met while walking records the
condition under which it is undefined, as an atom (``sqrt a``: ``a < 0``; ``log a``:
``a ≤ 0``; ``a / b``, ``1/a``: ``b = 0``; ``tan a``: ``cos a = 0``; ``asin, acos``:
``|a| > 1``; ``log1p a``: ``a ≤ −1``; ``acosh a``: ``a < 1``; ``atanh a``: ``|a| ≥ 1``;
``atan2(a, b)``: ``a = b = 0``; ``a^e``: ``a = 0`` for a negative integer ``e``, ``a < 0``
for a positive non-integer ``e``, ``a ≤ 0`` for a negative non-integer or non-constant
``e``). Two of these are stricter than ``nlyap_opt.kernel.walker.OP_TABLE``'s domains, which is
conservative: ``atan2(0, 0)`` (0 by C's convention) and ``a^e`` with a non-constant ``e``
(defined at ``a < 0`` for integer ``e``). These atoms are *violations*: the falsification formula is

.. math:: x \in B \;\wedge\; g_i(x) \le 0\ \forall i \;\wedge\;
          \big(\exists j: p_j(x) \ge 0 \;\vee\; \exists k: \text{violation}_k(x)\big),

so ``unsat`` (verified) also proves that every partial operation is defined on the region
(the set of points of the box where every ``g_i`` is defined and ``≤ 0``). Conditions are
recorded before any simplification (a ``0·log(x)`` that folds to ``0`` still asks
``x > 0``), which is conservative. A violation found by dReal is a δ-SAT box like any other:
it becomes a counterexample only if a point is confirmed by rigorous evaluation.

Operations with no real-arithmetic counterpart in dReal (``floor``, ``ceil``, ``fmod``,
``erf``) raise :class:`~nlyap_opt.kernel.errors.UnsupportedOperationError` naming the operation.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from fractions import Fraction

import casadi as ca
import numpy as np

from nlyap_opt.kernel.errors import UnsupportedOperationError
from nlyap_opt.kernel.walker import compile_function, evaluate, op_name

from .terms import Term, TermTable, evaluate_terms, topological

__all__ = [
    "Term", "TermTable", "FormulaArithmetic", "CollectingArithmetic", "Formula",
    "build_formula", "SUPPORTED_OPS", "UNSUPPORTED_OPS", "topological", "evaluate_terms",
]

# --------------------------------------------------------------------------- the arithmetic
_CMP_EXACT = {"<=": lambda p, q: p <= q, "<": lambda p, q: p < q, ">=": lambda p, q: p >= q,
              ">": lambda p, q: p > q, "=": lambda p, q: p == q}


class FormulaArithmetic:
    """Walker arithmetic whose values are :class:`Term` nodes (SX expansion only).

    Every CasADi elementwise operation of the walker is either implemented (exactly, in
    real arithmetic) or refused with :class:`UnsupportedOperationError` naming it.
    ``violations`` collects the domain-violation atoms of the partial operations met.
    """

    name = "formula"
    symbolic = True

    def __init__(self, table: TermTable | None = None):
        self.t = table or TermTable()
        self.violations: list[Term] = []
        self._seen: set[int] = set()
        t = self.t
        c = t.const
        fn = t.fn
        self._unary: dict[int, Callable[[Term], Term]] = {
            ca.OP_NEG: t.neg,
            ca.OP_SQ: lambda a: t.pow(a, c(2.0)),
            ca.OP_TWICE: lambda a: t.mul(c(2.0), a),
            ca.OP_ASSIGN: lambda a: a,
            ca.OP_SQRT: lambda a: self._dom(fn("sqrt", a), t.cmp("<", a, t.zero)),
            ca.OP_EXP: lambda a: fn("exp", a),
            ca.OP_LOG: lambda a: self._dom(fn("log", a), t.cmp("<=", a, t.zero)),
            ca.OP_SIN: lambda a: fn("sin", a),
            ca.OP_COS: lambda a: fn("cos", a),
            ca.OP_TAN: lambda a: self._dom(fn("tan", a), t.cmp("=", fn("cos", a), t.zero)),
            ca.OP_TANH: lambda a: fn("tanh", a),
            ca.OP_ATAN: lambda a: fn("atan", a),
            ca.OP_SINH: lambda a: fn("sinh", a),
            ca.OP_COSH: lambda a: fn("cosh", a),
            ca.OP_FABS: lambda a: fn("abs", a),
            ca.OP_INV: lambda a: self._dom(t.div(t.one, a), t.cmp("=", a, t.zero)),
            ca.OP_ASIN: lambda a: self._dom(fn("asin", a), self._outside(a, 1.0, True)),
            ca.OP_ACOS: lambda a: self._dom(fn("acos", a), self._outside(a, 1.0, True)),
            ca.OP_EXPM1: lambda a: t.sub(fn("exp", a), t.one),
            ca.OP_LOG1P: lambda a: self._dom(fn("log", t.add(t.one, a)),
                                             t.cmp("<=", a, c(-1.0))),
            ca.OP_ASINH: lambda a: fn("log", t.add(a, fn("sqrt", t.add(t.pow(a, c(2.0)),
                                                                          t.one)))),
            ca.OP_ACOSH: lambda a: self._dom(
                fn("log", t.add(a, fn("sqrt", t.sub(t.pow(a, c(2.0)), t.one)))),
                t.cmp("<", a, t.one)),
            ca.OP_ATANH: lambda a: self._dom(
                t.mul(c(0.5), fn("log", t.div(t.add(t.one, a), t.sub(t.one, a)))),
                self._outside(a, 1.0, False)),
            ca.OP_SIGN: lambda a: t.ite(t.cmp(">", a, t.zero), t.one,
                                        t.ite(t.cmp("<", a, t.zero), c(-1.0), t.zero)),
            ca.OP_NOT: lambda a: t.ite(t.cmp("=", a, t.zero), t.one, t.zero),
        }
        self._binary: dict[int, Callable[[Term, Term], Term]] = {
            ca.OP_ADD: t.add,
            ca.OP_SUB: t.sub,
            ca.OP_MUL: t.mul,
            ca.OP_DIV: lambda a, b: self._dom(t.div(a, b), t.cmp("=", b, t.zero)),
            ca.OP_POW: self._pow,
            ca.OP_CONSTPOW: self._pow,
            ca.OP_FMIN: lambda a, b: t.op2("min", a, b),
            ca.OP_FMAX: lambda a, b: t.op2("max", a, b),
            ca.OP_ATAN2: lambda a, b: self._dom(
                t.op2("atan2", a, b),
                t.and_(t.cmp("=", a, t.zero), t.cmp("=", b, t.zero))),
            ca.OP_HYPOT: lambda a, b: fn("sqrt", t.add(t.pow(a, c(2.0)), t.pow(b, c(2.0)))),
            ca.OP_LT: lambda a, b: t.ite(t.cmp("<", a, b), t.one, t.zero),
            ca.OP_LE: lambda a, b: t.ite(t.cmp("<=", a, b), t.one, t.zero),
            ca.OP_EQ: lambda a, b: t.ite(t.cmp("=", a, b), t.one, t.zero),
            ca.OP_NE: lambda a, b: t.ite(t.cmp("=", a, b), t.zero, t.one),
            ca.OP_AND: lambda a, b: t.ite(t.or_(t.cmp("=", a, t.zero), t.cmp("=", b, t.zero)),
                                          t.zero, t.one),
            ca.OP_OR: lambda a, b: t.ite(t.and_(t.cmp("=", a, t.zero),
                                                t.cmp("=", b, t.zero)), t.zero, t.one),
            ca.OP_COPYSIGN: lambda a, b: t.ite(t.cmp("<", b, t.zero), t.neg(fn("abs", a)),
                                               fn("abs", a)),
            ca.OP_IF_ELSE_ZERO: lambda a, b: t.ite(t.cmp("=", a, t.zero), t.zero, b),
        }

    # ------------------------------------------------------------------ helpers
    def _dom(self, value: Term, violation: Term) -> Term:
        if violation.op in _CMP_EXACT and all(a.is_const for a in violation.args):
            p, q = (Fraction(a.value) for a in violation.args)
            if not _CMP_EXACT[violation.op](p, q):  # decided: never violated
                return value
        if id(violation) not in self._seen:
            self._seen.add(id(violation))
            self.violations.append(violation)
        return value

    def _outside(self, a: Term, r: float, closed: bool) -> Term:
        """``|a| > r`` (``closed``: the domain ``[-r, r]``) or ``|a| ≥ r``."""
        op = ">" if closed else ">="
        return self.t.cmp(op, self.t.fn("abs", a), self.t.const(r))

    def _pow(self, a: Term, e: Term) -> Term:
        t = self.t
        if e.is_const and float(e.value).is_integer():
            if e.value < 0:
                self._dom(None, t.cmp("=", a, t.zero))
        elif e.is_const and e.value > 0:
            self._dom(None, t.cmp("<", a, t.zero))
        else:
            self._dom(None, t.cmp("<=", a, t.zero))
        return t.pow(a, e)

    # ------------------------------------------------------------------ walker protocol
    def constant(self, value) -> Term:
        v = np.asarray(value, dtype=float)
        if v.ndim:
            raise UnsupportedOperationError(
                "the formula builder walks the SX expansion (scalar registers only); "
                "call Function.expand() first")
        return self.t.const(float(v))

    def unary(self, op: int, a: Term) -> Term:
        try:
            f = self._unary[op]
        except KeyError:
            raise _unsupported(op, list(self._unary) + list(self._binary)) from None
        return f(a)

    def binary(self, op: int, a: Term, b: Term) -> Term:
        try:
            f = self._binary[op]
        except KeyError:
            raise _unsupported(op, list(self._unary) + list(self._binary)) from None
        return f(a, b)

    def structural(self, fn, *args):
        return fn(*args)


class _Lin:
    """A value of :class:`CollectingArithmetic`: the graph's own form and linear forms.

    ``orig`` is the term in the graph's structure. ``forms`` holds the same value as
    linear combinations ``Σ atom·coef`` (``atom`` a node or ``1``, ``coef`` a term):
    ``forms[0]`` over non-linear atoms (tanh nodes, variables, products kept whole),
    ``forms[1]`` over coarser atoms (a sum scaled by a constant stays one atom); ``None``
    where a form grew past ``MAX_ATOMS``. :attr:`term` is the smallest of them.
    """

    __slots__ = ("orig", "forms", "is_sum", "_term", "_t")

    def __init__(self, t: TermTable, orig: Term, forms, is_sum: bool = False):
        self._t = t
        self.orig = orig
        self.forms = forms
        self.is_sum = is_sum
        self._term = None

    @property
    def term(self) -> Term:
        if self._term is None:
            best = self.orig
            for lin in self.forms:
                if lin is not None and len(lin) > 1:
                    alt = _collect(self._t, lin)
                    if alt.size < best.size:
                        best = alt
            self._term = best
        return self._term

    def form(self, k: int) -> dict:
        """Linear form ``k`` (a value without one is one atom with coefficient 1)."""
        lin = self.forms[k]
        if lin is not None:
            return lin
        return {id(self.term): (self.term, self._t.one)}


def _collect(t: TermTable, lin: dict) -> Term:
    acc = None
    for atom, coef in lin.values():
        if coef is t.zero:
            continue
        z = coef if atom is t.one else t.mul(coef, atom)
        acc = z if acc is None else t.add(acc, z)
    return t.zero if acc is None else acc


class CollectingArithmetic(FormulaArithmetic):
    """:class:`FormulaArithmetic` that also regroups linear combinations (exactly).

    Besides the graph's own form of each value it keeps the value as linear combinations
    ``Σ atom·coef`` with term coefficients, over two choices of atoms (non-linear nodes;
    or coarser: a sum scaled by a constant kept whole): sums and constant multiples merge
    the combinations, and a product of two non-constant factors distributes the smaller
    factor over the other's combinations. Wherever a value is used by a non-linear
    operation or is an output, the smallest expanded tree of the forms is taken. Example:
    CasADi's reverse-mode gradient of a tanh network sums ``w_ji (1 − t_j²)·Σ_k w'_kj y_k``
    over the neurons ``j``, repeating every output ``y_k`` once per neuron; regrouped it is
    ``Σ_k y_k·(Σ_j w_ji w'_kj (1 − t_j²))``, the chain rule as one writes it by hand.
    Distributivity and commutativity are exact in real arithmetic; no constant is rounded
    (products of weights stay products).
    """

    name = "formula-collect"
    #: largest linear form kept (beyond it the value is used whole)
    MAX_ATOMS = 512

    def _wrap(self, v) -> _Lin:
        if isinstance(v, _Lin):
            return v
        t = self.t
        if v is t.zero:
            lin = {}
        elif v.is_const:
            lin = {id(t.one): (t.one, v)}
        else:
            lin = {id(v): (v, t.one)}
        return _Lin(t, v, (lin, dict(lin)))

    def _merge(self, a: dict | None, b: dict | None, sign: int) -> dict | None:
        if a is None or b is None:
            return None
        t = self.t
        out = dict(a)
        for k, (atom, coef) in b.items():
            if k in out:
                c0 = out[k][1]
                out[k] = (atom, t.add(c0, coef) if sign > 0 else t.sub(c0, coef))
            else:
                out[k] = (atom, coef if sign > 0 else t.neg(coef))
        return out if len(out) <= self.MAX_ATOMS else None

    def _scale(self, c: Term, a: dict | None) -> dict | None:
        if a is None:
            return None
        t = self.t
        return {k: (atom, t.mul(c, coef)) for k, (atom, coef) in a.items()}

    def constant(self, value) -> _Lin:
        return self._wrap(super().constant(value))

    def unary(self, op: int, a) -> _Lin:
        a = self._wrap(a)
        t = self.t
        if op == ca.OP_ASSIGN:
            return a
        if op == ca.OP_NEG:
            m1 = t.const(-1.0)
            return _Lin(t, t.neg(a.orig), tuple(self._scale(m1, f) for f in a.forms),
                        a.is_sum)
        if op == ca.OP_TWICE:
            return self._mul(self._wrap(t.const(2.0)), a)
        return self._wrap(super().unary(op, a.term))

    def binary(self, op: int, a, b) -> _Lin:
        a, b = self._wrap(a), self._wrap(b)
        t = self.t
        if op in (ca.OP_ADD, ca.OP_SUB):
            sign = 1 if op == ca.OP_ADD else -1
            orig = t.add(a.orig, b.orig) if sign > 0 else t.sub(a.orig, b.orig)
            forms = tuple(self._merge(fa, fb, sign) for fa, fb in zip(a.forms, b.forms))
            return _Lin(t, orig, forms, True)
        if op == ca.OP_MUL:
            return self._mul(a, b)
        return self._wrap(super().binary(op, a.term, b.term))

    def _mul(self, a: _Lin, b: _Lin) -> _Lin:
        t = self.t
        if b.orig.is_const and not a.orig.is_const:
            a, b = b, a
        if a.orig.is_const:  # constant multiple: linear
            c = a.orig
            fine = self._scale(c, b.forms[0])
            coarse = ({id(b.term): (b.term, c)} if b.is_sum
                      else self._scale(c, b.forms[1]))
            return _Lin(t, t.mul(c, b.orig), (fine, coarse))
        A, B = a.term, b.term
        orig = t.mul(A, B)
        small, other = (A, b) if A.size <= B.size else (B, a)
        forms = []
        for k in range(2):
            f = other.form(k)
            forms.append(self._scale(small, f) if len(f) > 1 else {id(orig): (orig, t.one)})
        return _Lin(t, orig, tuple(forms))

    @staticmethod
    def term(v) -> Term:
        """The term of a value (its smallest form)."""
        return v.term if isinstance(v, _Lin) else v


def _unsupported(op: int, supported) -> UnsupportedOperationError:
    names = ", ".join(sorted(op_name(o) for o in supported))
    return UnsupportedOperationError(
        f"CasADi operation {op_name(op)} has no exact encoding for dReal / SMT-LIB (real "
        f"arithmetic without integers); the formula builder supports: {names}. Rewrite the "
        "expression with supported operations or verify with the interval backend."
    )


_FA = FormulaArithmetic()
#: CasADi op codes the formula arithmetic encodes exactly
SUPPORTED_OPS: frozenset[int] = frozenset(_FA._unary) | frozenset(_FA._binary)
#: CasADi elementwise op codes it refuses (no real-arithmetic counterpart in dReal)
UNSUPPORTED_OPS: frozenset[int] = frozenset({ca.OP_FLOOR, ca.OP_CEIL, ca.OP_FMOD, ca.OP_ERF})
del _FA


# --------------------------------------------------------------------------- the formula
@dataclass
class Formula:
    """The falsification formula of a verification problem, as one expression DAG.

    Attributes
    ----------
    table : TermTable
    variables : tuple of Term      one ``var`` node per state component
    box : (n, 2) ndarray
    constraints : tuple of Term    region ``g_i ≤ 0``
    properties : tuple of Term     violated where ``p_j ≥ 0``
    violations : tuple of Term     boolean atoms: a partial operation is undefined
    constraint_names, property_names : list of str
    """

    table: TermTable
    variables: tuple
    box: np.ndarray
    constraints: tuple
    properties: tuple
    violations: tuple = ()
    constraint_names: list = field(default_factory=list)
    property_names: list = field(default_factory=list)

    def region_atoms(self) -> list[Term]:
        t = self.table
        return [t.cmp("<=", g, t.zero) for g in self.constraints]

    def violation_atoms(self) -> list[Term]:
        """Property violations ``p_j ≥ 0`` followed by the domain violations."""
        t = self.table
        return [t.cmp(">=", p, t.zero) for p in self.properties] + list(self.violations)

    def box_atoms(self) -> list[Term]:
        t = self.table
        out = [t.cmp("<=", t.const(lo), v) for v, lo in zip(self.variables, self.box[:, 0])]
        out += [t.cmp("<=", v, t.const(hi)) for v, hi in zip(self.variables, self.box[:, 1])]
        return out

    def body(self) -> Term:
        """``g ≤ 0 ∀i ∧ (∃j p_j ≥ 0 ∨ a domain violation)`` (the box not included)."""
        t = self.table
        return t.and_(*self.region_atoms(), t.or_(*self.violation_atoms()))

    def falsification(self) -> Term:
        """The whole formula: box atoms and :meth:`body`; ``unsat`` means verified."""
        return self.table.and_(*self.box_atoms(), self.body())

    def expanded_size(self) -> int:
        """Nodes of :meth:`falsification` as a tree (shared nodes counted at each use)."""
        return self.falsification().size

    def dag_size(self) -> int:
        """Distinct nodes of :meth:`falsification` (what ``let`` sharing writes)."""
        return len(topological([self.falsification()]))

    def evaluate(self, points) -> dict[str, np.ndarray]:
        """Float64 evaluation at points ``(N, n)`` (for tests and debugging; not rigorous).

        Returns
        -------
        dict
            ``"constraints"`` ``(N, m)``, ``"properties"`` ``(N, p)``, ``"violations"``
            ``(N, k)`` (bool), ``"body"`` ``(N,)`` (bool; the box not included).
        """
        X = np.atleast_2d(np.asarray(points, dtype=float))
        env = {v.value: X[:, i] for i, v in enumerate(self.variables)}
        body = self.body()
        val = evaluate_terms([body, *self.constraints, *self.properties, *self.violations],
                             env, len(X))
        m, p = len(self.constraints), len(self.properties)

        def cols(ts):
            return np.stack([val[id(x)] for x in ts], -1) if ts else np.zeros((len(X), 0))

        return {"constraints": cols(self.constraints), "properties": cols(self.properties),
                "violations": cols(self.violations).astype(bool),
                "body": np.asarray(val[id(body)], dtype=bool), "m": m, "p": p}


def build_formula(problem, *, var_names: Sequence[str] | None = None,
                  table: TermTable | None = None, collect: bool = True) -> Formula:
    """The :class:`Formula` of a :class:`~verification.problem.VerificationProblem`.

    Parameters
    ----------
    problem : VerificationProblem
    var_names : sequence of str, optional
        Names of the state variables (default ``x0, x1, ...``).
    table : TermTable, optional
        Node table to build in (shared with other formulas, e.g. to compare encodings).
    collect : bool
        Regroup linear combinations where that makes the expanded tree smaller
        (:class:`CollectingArithmetic`, default); ``False``: the graph's structure as is.

    Returns
    -------
    Formula
        The only encoding of the problem: :func:`verification.smtlib.to_smtlib` and the
        dReal backend both consume it.
    """
    fun = problem.function.expand() if problem.function.is_a("MXFunction") \
        else problem.function
    names = list(var_names) if var_names is not None else [f"x{i}" for i in range(problem.n)]
    if len(names) != problem.n or len(set(names)) != problem.n:
        raise ValueError(f"need {problem.n} distinct variable names, got {names}")
    ar = (CollectingArithmetic if collect else FormulaArithmetic)(table)
    xs = [ar.t.var(v) for v in names]
    arg = np.empty(problem.n, dtype=object)
    arg[:] = xs
    out = [CollectingArithmetic.term(v) for v in evaluate(compile_function(fun), [arg], ar)[0]]
    m = problem.n_constraints
    return Formula(ar.t, tuple(xs), np.asarray(problem.box, dtype=float), tuple(out[:m]),
                   tuple(out[m:]), tuple(ar.violations), list(problem.constraint_names),
                   list(problem.property_names))
