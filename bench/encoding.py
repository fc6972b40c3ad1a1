"""Size of the dReal encoding: former backend vs formula builder vs direct.

dReal works on terms without ``let`` sharing, so what it pays for is the *expanded* tree:
every use of a shared subterm counted again. For the queries of ``bench/verify.py`` built on
the published network sizes (a 2-6 tanh V, a 200-neuron φ) this prints, per query, the
expanded node count of the whole falsification formula (box atoms, region, properties)

- ``former``: the encoding the dReal backend built before the formula builder (walker on the
  SX expansion, ``sq(a)`` as ``a*a``, ``twice(a)`` as ``2*a``; counted as built in Python,
  before any simplification dReal's own ``Expression`` class may apply);
- ``builder``: :func:`verification.formula.build_formula` (shared by dReal and SMT-LIB);
- ``direct``: V, f and ``∇V·f`` written by hand as a user would for dReal, in the same node
  table: ``t_j = tanh(W1_j·x + b1_j)``, ``y_k = W2_k·t + b2_k − N_k(0)``,
  ``V = Σ y_k² + ε‖x‖²``, ``∂V/∂x_i = Σ_k 2 y_k Σ_j W2_kj (1 − t_j²) W1_ji + 2ε x_i``,
  ``∇V·f = Σ_i ∂V/∂x_i f_i``, φ as nested tanh sums, the true f from its SX expression;

and the distinct (DAG) node count of the builder's formula, which is what the SMT-LIB text
writes with ``let`` bindings and what the dReal backend creates as Python objects.

    python bench/encoding.py
"""

from __future__ import annotations

from pathlib import Path

import casadi as ca
import numpy as np

import systems
from nlyap_opt.kernel.network import Network
from nlyap_opt.kernel.walker import compile_function, evaluate
from verification import closed_loop_problem
from verification.formula import Formula, FormulaArithmetic, TermTable, build_formula

DATA = Path(__file__).parent / "data"


class _FormerCount:
    """Tree size of the former ``DrealArithmetic`` terms (kept here to measure against)."""

    name = "former-count"
    symbolic = True

    def constant(self, value):
        return 1

    def unary(self, op, a):
        if op == ca.OP_ASSIGN:
            return a
        if op == ca.OP_SQ:  # a * a
            return 1 + 2 * a
        if op in (ca.OP_TWICE, ca.OP_INV):  # 2 * a, 1 / a
            return 2 + a
        return 1 + a

    def binary(self, op, a, b):
        return 1 + a + b

    def structural(self, fn, *args):
        return fn(*args)


def former_size(problem) -> int:
    """Expanded size of ``And(box atoms, g ≤ 0 ..., Or(p ≥ 0 ...))`` as the former backend."""
    fun = problem.function.expand()
    arg = np.ones(problem.n, dtype=object)  # a variable is one node
    sizes = evaluate(compile_function(fun), [arg], _FormerCount())[0]
    m = problem.n_constraints
    atom = [2 + s for s in sizes]  # (t <= 0): comparison, term, constant
    viol = sum(atom[m:]) + (1 if len(atom) - m > 1 else 0)
    return 1 + 2 * problem.n * 3 + sum(atom[:m]) + viol


def direct_formula(system, V: Network, phi: Network | None, *, inner, outer, margin=0.0,
                   eta=0.0, smoothing=0.0, table: TermTable | None = None) -> Formula:
    """The same query written by hand (one hidden tanh layer V and φ only)."""
    t = table or TermTable()
    c = t.const
    n = system.nx
    xs = [t.var(f"x{i}") for i in range(n)]

    def lin(W, b, h):
        out = []
        for row, bias in zip(W, b):
            acc = c(bias)
            for w, z in zip(row, h):
                acc = t.add(acc, t.mul(c(w), z))
            out.append(acc)
        return out

    def total(terms):
        acc = terms[0]
        for z in terms[1:]:
            acc = t.add(acc, z)
        return acc

    L1, L2 = V.layers
    if not (L1.activation == "tanh" and L2.activation == "linear"
            and np.all(V.output_scale == 1.0)):
        raise ValueError("direct_formula writes a one-hidden-tanh-layer V only")
    tj = [t.fn("tanh", z) for z in lin(L1.weight, L1.bias, xs)]
    N0 = L2.weight @ np.tanh(L1.bias) + L2.bias  # N(0), a float constant
    y = [t.sub(z, c(n0)) for z, n0 in zip(lin(L2.weight, L2.bias, tj), N0)]
    eps = V.head["eps"]
    sq = [t.pow(z, c(2.0)) for z in xs]
    Vt = t.add(total([t.pow(z, c(2.0)) for z in y]), t.mul(c(eps), total(sq)))
    dt = [t.sub(t.one, t.pow(z, c(2.0))) for z in tj]
    grad = []
    for i in range(n):
        gi = []
        for k in range(len(y)):
            dyk = total([t.mul(t.mul(c(L2.weight[k, j]), dt[j]), c(L1.weight[j, i]))
                         for j in range(len(tj))])
            gi.append(t.mul(t.mul(c(2.0), y[k]), dyk))
        grad.append(t.add(total(gi), t.mul(c(2 * eps), xs[i])))
    if phi is None:
        ar = FormulaArithmetic(t)
        arg = np.empty(n, dtype=object)
        arg[:] = xs
        f = evaluate(compile_function(system.f_fun),
                     [arg, np.empty(system.nu, dtype=object)], ar)[0]
    else:
        P1, P2 = phi.layers
        f = lin(P2.weight, P2.bias, [t.fn("tanh", z) for z in lin(P1.weight, P1.bias, xs)])
    lie = total([t.mul(g, fi) for g, fi in zip(grad, f)])
    if eta:
        q = total([t.pow(g, c(2.0)) for g in grad])
        lie = t.add(lie, t.mul(c(eta), t.fn("sqrt", t.add(q, c(smoothing**2)))
                               if smoothing else t.fn("sqrt", q)))
    if margin:
        lie = t.add(lie, c(margin))
    r2 = total(sq)
    cons = [t.sub(r2, c(outer**2))] + ([t.sub(c(inner**2), r2)] if inner else [])
    box = np.tile([-outer, outer], (n, 1))
    return Formula(t, tuple(xs), box, tuple(cons), (t.neg(Vt), lie))


def queries():
    """(label, problem, direct formula) for the published-size networks."""
    s = systems.get("van_der_pol")
    V6 = Network.load(DATA / "vdp_V6.json")
    phi = Network.load(DATA / "vdp_phi_200.json")
    x = ca.MX.sym("x", 2)
    grad = ca.Function("g", [x], [ca.gradient(V6.casadi(x), x)])
    from nlyap_opt.candidates.learning import sample_ball

    pts = sample_ball(20000, 2, 1.2, np.random.default_rng(0))
    smooth = 1e-3 * float(np.max(np.linalg.norm(np.array(grad(pts.T)), axis=0)))
    common = dict(inner=0.2, outer=1.2)
    yield ("(i) V 2-6 tanh, true f", closed_loop_problem(s, V6, **common),
           direct_formula(s, V6, None, **common))
    yield ("(ii) V 2-6, 200-neuron φ, margin 0.01",
           closed_loop_problem(s, V6, dynamics=phi, margin=0.01, **common),
           direct_formula(s, V6, phi, margin=0.01, **common))
    yield (f"(iv) (ii) with η = 0.005 pointwise, s = {smooth:.2g}",
           closed_loop_problem(s, V6, dynamics=phi, eta=0.005, smoothing=smooth, **common),
           direct_formula(s, V6, phi, eta=0.005, smoothing=smooth, **common))


def main(argv=None):
    rows = []
    s = systems.get("van_der_pol")
    V30 = DATA / "vdp_V30x30.json"
    extra = []
    if V30.exists():  # not a published size: no hand-written counterpart (two hidden layers)
        extra = [("(iii) V 2-30-30 tanh, true f, r = 2.5 (no direct row)",
                  closed_loop_problem(s, Network.load(V30), inner=0.2, outer=2.5), None)]
    for label, problem, direct in [*queries(), *extra]:
        built = build_formula(problem)
        if direct is None:
            rows.append((label, former_size(problem), built.expanded_size(), None,
                         built.dag_size()))
            continue
        # the hand-written formula must be the same function as the graph (float check)
        X = np.random.default_rng(1).uniform(-1.2, 1.2, (200, 2))
        a, b = built.evaluate(X), direct.evaluate(X)
        err = np.abs(a["properties"] - b["properties"]).max()
        if err > 1e-9 * (1 + np.abs(a["properties"]).max()):
            raise AssertionError(f"{label}: direct and built formulas differ by {err:.3g}")
        rows.append((label, former_size(problem), built.expanded_size(), direct.expanded_size(),
                     built.dag_size()))
    print("| query | nodes former | nodes builder | nodes direct | builder / direct "
          "| former / direct | builder DAG nodes |")
    print("|---|---|---|---|---|---|---|")
    for label, old, new, direct, dag in rows:
        if direct is None:
            print(f"| {label} | {old} | {new} | – | – | – | {dag} |")
            continue
        print(f"| {label} | {old} | {new} | {direct} | {new / direct:.2f} "
              f"| {old / direct:.2f} | {dag} |")


if __name__ == "__main__":
    main()
