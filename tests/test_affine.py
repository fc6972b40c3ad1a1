"""Affine arithmetic (verification.affine): every relaxed operation checked against mpmath.

The property tested is the affine one, stronger than a range: for inputs
``x = c + g·ε + e·η`` (``ε ∈ [-1, 1]^n`` shared by all values, ``η ∈ [-1, 1]`` each value's
own remainder), the real result lies within ``z.e`` of ``z.c + z.g·ε`` at the *same* ε,
evaluated exactly (mpmath, 60 digits) from the float coefficients.
"""

from __future__ import annotations

import casadi as ca
import mpmath as mp
import numpy as np
import pytest

from nlyap_opt.kernel.walker import evaluate
from verification import closed_loop_problem, lyapunov_problem, verify
from verification.affine import Affine, AffineArithmetic
from verification.interval import Interval, IntervalArithmetic

mp.mp.dps = 60
AA = AffineArithmetic()
IA = IntervalArithmetic()
N = 2  # inputs (ε dimensions)

_MP = {
    ca.OP_TANH: mp.tanh, ca.OP_EXP: mp.exp, ca.OP_SIN: mp.sin, ca.OP_COS: mp.cos,
    ca.OP_SQRT: mp.sqrt, ca.OP_INV: lambda t: 1 / t, ca.OP_SQ: lambda t: t * t,
    ca.OP_NEG: lambda t: -t, ca.OP_TWICE: lambda t: 2 * t,
}
_MP2 = {
    ca.OP_ADD: lambda a, b: a + b, ca.OP_SUB: lambda a, b: a - b,
    ca.OP_MUL: lambda a, b: a * b, ca.OP_DIV: lambda a, b: a / b,
}


def _centres(rng, op, k):
    """Centres that stress each relaxation: inflection points, large and tiny values."""
    base = rng.uniform(-3, 3, k)
    if op in (ca.OP_SIN, ca.OP_COS):
        near = np.round(base * 3) * (np.pi / 2) + rng.normal(0, 1e-3, k)
        base = np.where(rng.random(k) < 0.5, near, base)
        base = np.where(rng.random(k) < 0.1, base + 1e3, base)
    if op == ca.OP_TANH:
        base = np.where(rng.random(k) < 0.3, rng.normal(0, 1e-3, k), base * 2)
    if op in (ca.OP_SQRT, ca.OP_INV):
        base = np.abs(base) + 0.05
        base = np.where(rng.random(k) < 0.2, base * 1e6, base)
    if op == ca.OP_EXP:
        base = base * 5
    return base


def _forms(rng, op, k):
    """``k`` random input forms (scalars, n = 2) of widths from 1e-12 to 4."""
    c = _centres(rng, op, k)
    width = 10.0 ** rng.uniform(-12, 0.6, k)
    if op in (ca.OP_SQRT, ca.OP_INV):
        width = np.minimum(width, 0.3 * np.abs(c))  # keep inside the domain mostly
    share = rng.dirichlet(np.ones(N + 1), k)  # split the radius into g_1, g_2, e
    sign = rng.choice([-1.0, 1.0], (k, N))
    g = (share[:, :N] * width[:, None] * sign).T.copy()
    e = share[:, N] * width
    return Affine(c, g, e)


def _points(rng, m):
    """ε in the corners and inside, η = ±1 or inside."""
    eps = rng.uniform(-1, 1, (m, N))
    eps[: m // 4] = np.sign(eps[: m // 4])
    eta = rng.uniform(-1, 1, (m, 2))
    eta[m // 4: m // 2] = np.sign(eta[m // 4: m // 2])
    return eps, eta


def _value(a: Affine, j, eps, eta):
    """Exact value of input form ``a`` (element j) at ε, η."""
    v = mp.mpf(float(a.c[j]))
    for i in range(N):
        v += mp.mpf(float(a.g[i, j])) * mp.mpf(float(eps[i]))
    return v + mp.mpf(float(np.broadcast_to(a.e, a.c.shape)[j])) * mp.mpf(float(eta))


def _violations(z: Affine, truth, eps, j) -> int:
    """1 if the exact ``truth`` is not within z.e of z.c + z.g·ε (element j)."""
    e = float(np.broadcast_to(z.e, z.c.shape)[j])
    if not np.isfinite(e):
        return 0
    form = mp.mpf(float(z.c[j]))
    if z.g is not None:
        for i in range(N):
            form += mp.mpf(float(z.g[i, j])) * mp.mpf(float(eps[i]))
    return int(abs(truth - form) > mp.mpf(e))


def _check_unary(op, z: Affine, a: Affine, rng, m=6, fn=None) -> int:
    fn = fn or _MP[op]
    bad = 0
    for j in range(len(a.c)):
        for eps, eta in zip(*_points(rng, m)):
            t = _value(a, j, eps, eta[0])
            if op in (ca.OP_SQRT,) and t < 0 or op == ca.OP_INV and t == 0:
                continue
            bad += _violations(z, fn(t), eps, j)
    return bad


@pytest.mark.parametrize("op", [ca.OP_TANH, ca.OP_EXP, ca.OP_SIN, ca.OP_COS, ca.OP_SQRT,
                                ca.OP_INV, ca.OP_SQ, ca.OP_NEG, ca.OP_TWICE])
def test_unary_forms_enclose_mpmath(op):
    rng = np.random.default_rng(op)
    a = _forms(rng, op, 300)
    z = AA.unary(op, a)
    assert z.c.shape == a.c.shape
    assert _check_unary(op, z, a, rng) == 0
    # the relaxation is used (not only the interval fallback) on most forms
    if op not in (ca.OP_NEG, ca.OP_TWICE):
        assert z.g is not None and np.mean(np.abs(z.g).sum(axis=0) > 0) > 0.5


@pytest.mark.parametrize("op", [ca.OP_ADD, ca.OP_SUB, ca.OP_MUL, ca.OP_DIV])
def test_binary_forms_enclose_mpmath(op):
    rng = np.random.default_rng(100 + op)
    a = _forms(rng, ca.OP_TANH, 200)
    b = _forms(rng, ca.OP_INV if op == ca.OP_DIV else ca.OP_TANH, 200)
    z = AA.binary(op, a, b)
    bad = 0
    for j in range(200):
        for eps, eta in zip(*_points(rng, 6)):
            ta, tb = _value(a, j, eps, eta[0]), _value(b, j, eps, eta[1])
            bad += _violations(z, _MP2[op](ta, tb), eps, j)
    assert bad == 0


def test_products_with_constants_and_cancellation():
    """x·k with a widened constant; in x - x the input coefficients cancel."""
    rng = np.random.default_rng(5)
    a = _forms(rng, ca.OP_TANH, 100)
    k = AA.constant(np.array(0.1))
    z = AA.binary(ca.OP_MUL, a, k)
    bad = 0
    for j in range(100):
        for eps, eta in zip(*_points(rng, 4)):
            bad += _violations(z, _value(a, j, eps, eta[0]) * mp.mpf("0.1"), eps, j)
    assert bad == 0
    d = AA.binary(ca.OP_SUB, a, a).to_interval()  # the g part cancels, the remainders add
    assert np.all(d.hi - d.lo <= 4.0 * (1 + 1e-9) * a.e + 1e-14 * (np.abs(a.c) + 1.0))


def test_matmul_and_sum_enclose_mpmath():
    """A network layer W x + b (W constant, widened) and a sum over it, batched."""
    rng = np.random.default_rng(7)
    B, k, h = 40, 5, 7
    c = rng.uniform(-2, 2, (B, k, 1))
    g = rng.normal(0, 0.2, (N, B, k, 1))
    e = rng.uniform(0, 0.05, (B, k, 1))
    x = Affine(c, g, e)
    W = rng.normal(size=(h, k)) / 3
    y = AA.sum(AA.unary(ca.OP_TANH, AA.matmul(AA.constant(W), x)), (-2, -1))
    bad = 0
    for bi in range(B):
        for eps, _ in zip(*_points(rng, 4)):
            eta = rng.uniform(-1, 1, k)
            xv = [mp.mpf(float(c[bi, i, 0])) + sum(mp.mpf(float(g[n, bi, i, 0]))
                                                    * mp.mpf(float(eps[n])) for n in range(N))
                  + mp.mpf(float(e[bi, i, 0])) * mp.mpf(float(eta[i])) for i in range(k)]
            truth = sum(mp.tanh(sum(mp.mpf(float(W[r, i])) * xv[i] for i in range(k)))
                        for r in range(h))
            form = mp.mpf(float(y.c[bi])) + sum(mp.mpf(float(y.g[n, bi])) * mp.mpf(float(eps[n]))
                                                for n in range(N))
            bad += int(abs(truth - form) > mp.mpf(float(y.e[bi])))
    assert bad == 0


def test_the_checker_can_fail():
    """The mpmath check detects a form whose remainder is too small (halved or zeroed)."""
    rng = np.random.default_rng(11)
    a = _forms(rng, ca.OP_TANH, 200)
    z = AA.unary(ca.OP_TANH, a)
    for shrink in (0.0, 0.5):
        broken = Affine(z.c, z.g, z.e * shrink)
        assert _check_unary(ca.OP_TANH, broken, a, np.random.default_rng(12)) > 0


def test_nan_and_infinite_inputs_give_nothing_known():
    a = Affine(np.array([np.nan, 1.0, 0.0]), np.array([[0.1, np.inf, 0.0]] * N),
               np.array([0.0, 0.0, np.inf]))
    for op in (ca.OP_TANH, ca.OP_SIN, ca.OP_EXP, ca.OP_SQ):
        r = AA.unary(op, a).to_interval()
        assert not np.isnan(r.lo).any() and not np.isnan(r.hi).any()
        if op == ca.OP_SQ:
            assert np.all(r.hi == np.inf)
    r = AA.binary(ca.OP_MUL, a, a).to_interval()
    assert np.all(r.lo == -np.inf) and np.all(r.hi == np.inf)


def _fns(sym=ca.MX):
    x = sym.sym("x", 2)
    rng = np.random.default_rng(3)
    W1, b1, W2 = rng.normal(size=(16, 2)), rng.normal(size=16), rng.normal(size=(1, 16))
    net = ca.mtimes(W2, ca.tanh(ca.mtimes(W1, x) + b1))
    return x, {
        "net": net,
        "lie": ca.dot(ca.gradient(net, x), ca.vertcat(x[1], -ca.sin(x[0]) - 0.5 * x[1])),
        "mixed": (ca.exp(-ca.sumsqr(x)) * ca.cos(3 * x[0]) + ca.sqrt(1 + x[1] ** 2) / (2 + x[0])
                  + x[0] ** 3 - x[1] ** 4 + ca.sin(5 * x[1]) / (3 - x[1])),
        "jumps": ca.fabs(x[0]) + ca.sign(x[1]) * ca.fmax(x[0], x[1]) + ca.floor(2 * x[1]),
    }


@pytest.mark.parametrize("name", ["net", "lie", "mixed", "jumps"])
def test_graph_ranges_contain_samples(name):
    """Walker graphs (MX layers, gradients, non-smooth ops on the interval path): the
    ranges of the forms contain every sampled value; on small boxes they beat intervals."""
    x, fns = _fns()
    f = ca.Function("f", [x], [fns[name]])
    rng = np.random.default_rng(4)
    for width in (1e-3, 0.1, 1.0):
        c = rng.uniform(-1.5, 1.5, (300, 2))
        lo, hi = c - width * rng.random((300, 2)), c + width * rng.random((300, 2))
        r = evaluate(f, [Affine.from_box(lo, hi)], AA)[0].to_interval()
        pts = lo[None] + (hi - lo)[None] * rng.random((100, 300, 2))
        v = evaluate(f, [pts.reshape(-1, 2)])[0].reshape(100, 300)
        assert np.all((v >= r.lo[None, :, 0]) & (v <= r.hi[None, :, 0]))
        if name in ("net", "lie") and width <= 0.1:
            iv = evaluate(f, [Interval(lo, hi)], IA)[0]
            assert np.median(r.hi - r.lo) < 0.7 * np.median(iv.hi - iv.lo)


def test_verifier_with_affine_same_verdicts_fewer_boxes():
    """A tanh-network Lyapunov problem: affine on/off both verify (affine: fewer boxes);
    with an impossible margin both find a confirmed counterexample."""
    x, fns = _fns(ca.SX)
    net = fns["net"]
    V = ca.sumsqr(x) * (1.5 + 0.02 * ca.tanh(net))
    f = ca.vertcat(x[1] - 0.5 * x[0], -x[0] - x[1] + 0.05 * x[0] * ca.tanh(net))
    lie = ca.dot(ca.gradient(V, x), f)
    p = lyapunov_problem(x, V, lie, inner=0.1, outer=1.0)
    on = verify(p, affine=True)
    off = verify(p, affine=False)
    assert on.status == off.status == "verified"
    assert on.boxes < off.boxes
    bad = lyapunov_problem(x, V, lie, inner=0.1, outer=1.0, margin=0.5)
    for aff in (True, False):
        assert verify(bad, affine=aff).status == "counterexample"


def test_closed_loop_problem_unchanged_verdict():
    """The saved-network problem of the benchmark family (2-6-1 V, true f)."""
    from pathlib import Path

    import systems
    from nlyap_opt.kernel.network import Network

    path = Path(__file__).parents[1] / "bench" / "data" / "vdp_V6.json"
    if not path.exists():
        pytest.skip("bench/data/vdp_V6.json not built (python bench/verify.py)")
    s = systems.get("van_der_pol")
    p = closed_loop_problem(s, Network.load(path), inner=0.2, outer=1.2)
    r1, r2 = verify(p, affine=True), verify(p, affine=False)
    assert r1.status == r2.status == "verified"
    assert r1.boxes < r2.boxes


def test_the_checker_sees_missing_rounding_slack(monkeypatch):
    """Without the rounding terms (u = 0), sums and products of forms at small widths
    violate the exact check: the tests resolve rounding errors, not only relaxations."""
    import nlyap_opt.kernel.rounding as rounding
    import verification.affine as affine

    monkeypatch.setattr(affine, "U", 0.0)
    monkeypatch.setattr(rounding, "U", 0.0)      # up_roundings' relative factor
    monkeypatch.setattr(rounding, "_TINY_ROUNDINGS", 0.0)
    rng = np.random.default_rng(100 + ca.OP_ADD)
    a = _forms(rng, ca.OP_TANH, 200)
    b = _forms(rng, ca.OP_TANH, 200)
    z = AA.binary(ca.OP_ADD, a, b)
    bad = 0
    for j in range(200):
        for eps, eta in zip(*_points(rng, 6)):
            bad += _violations(z, _value(a, j, eps, eta[0]) + _value(b, j, eps, eta[1]),
                               eps, j)
    assert bad > 0


def test_split_rule_follows_the_affine_sensitivities(monkeypatch):
    """A 3-D problem whose last input is scaled by 8 (its box side is 8 times shorter, the
    function 8 times steeper along it): splitting where the affine bounds are most
    sensitive needs far fewer boxes than splitting the widest side; same verdict."""
    from scipy.linalg import solve_continuous_lyapunov

    from verification import VerificationProblem

    vv = __import__("sys").modules["verification.verify"]
    rng = np.random.default_rng(3)
    n = 3
    z = ca.SX.sym("z", n)
    scale = np.array([1.0, 1.0, 8.0])
    y = ca.diag(ca.DM(scale)) @ z
    A = np.array([[-1.0, 0.5, 0.2], [-0.5, -1.0, 0.3], [0.1, -0.3, -1.5]])  # Hurwitz
    W = rng.normal(size=(16, n)) * 0.7
    W2 = rng.normal(size=(n, 16)) * 0.1
    fy = (ca.mtimes(ca.DM(A), y) + ca.mtimes(ca.DM(W2), ca.tanh(ca.mtimes(ca.DM(W), y)))
          - ca.mtimes(ca.DM(W2 @ W), y))
    V = ca.bilin(ca.DM(solve_continuous_lyapunov(A.T, -np.eye(n))), y, y)
    lie = ca.dot(ca.gradient(V, z), ca.diag(ca.DM(1 / scale)) @ fy)
    box = np.array([[-1.0, 1.0], [-1.0, 1.0], [-1 / 8, 1 / 8]])
    r2 = ca.sumsqr(y)
    p = VerificationProblem(z, box, [r2 - 1.0, 0.01 - r2], [-V, lie])
    by_sens = verify(p, mean_value=False)  # the affine sensitivities decide the splits
    orig = vv._affine_enclosure

    def no_sensitivities(problem, lo, hi):
        enc, sens, lag = orig(problem, lo, hi)
        return enc, np.zeros_like(sens), lag  # every box "flat": the widest side is split

    monkeypatch.setattr(vv, "_affine_enclosure", no_sensitivities)
    widest = verify(p, mean_value=False)
    assert by_sens.status == widest.status == "verified"
    assert 2 * by_sens.boxes < widest.boxes
    # the default (the mean-value pass on undecided boxes, split by the Jacobian's smear)
    monkeypatch.setattr(vv, "_affine_enclosure", orig)
    default = verify(p)
    assert default.status == "verified" and 2 * default.boxes < widest.boxes


def _strip_problem(shift: float):
    """Region x0 <= 0.3 in [-1, 1]²; property x0 + 0.05 x1² - 0.3 - shift < 0."""
    x = ca.SX.sym("x", 2)
    from verification import VerificationProblem

    return VerificationProblem(x, [[-1.0, 1.0], [-1.0, 1.0]], [x[0] - 0.3],
                               [x[0] + 0.05 * x[1] ** 2 - 0.3 - shift])


def test_constraint_boundary_boxes_are_decided_soundly():
    """A box across the region's boundary is proved by p - λ g < 0 (λ >= 0) only when
    p < 0 on its part inside the region: the property failing in a thin sliver inside the
    region (x0 > 0.295 near |x1| = 1) is found; failing everywhere outside the region
    (x0 > 0.3) is not a violation, and is proved with fewer boxes."""
    bad = verify(_strip_problem(0.045), presearch=0, resolution=1e-3)
    assert bad.status == "counterexample"
    pt = bad.counterexample.point
    assert pt[0] <= 0.3 and pt[0] + 0.05 * pt[1] ** 2 - 0.345 >= 0
    good = verify(_strip_problem(0.055), presearch=0)
    assert good.status == "verified"
    assert good.boxes < verify(_strip_problem(0.055), presearch=0, affine=False).boxes


def test_constant_outputs_folded_by_casadi():
    """A property that CasADi folds to a constant (no batch dimension in the walker's
    output) is decided like any other, with and without affine arithmetic."""
    from verification import VerificationProblem

    x = ca.SX.sym("x", 1)
    holds = VerificationProblem(x, [[-1.0, 1.0]], [], [ca.SX(-1.0) + 0 * x[0]])
    fails = VerificationProblem(x, [[-1.0, 1.0]], [x[0] - 0.5], [ca.SX(1.0) + 0 * x[0]])
    X = ca.MX.sym("x", 2)
    mx = VerificationProblem(X, [[-1.0, 1.0]] * 2, [ca.sumsqr(X) - 1.0], [ca.MX(-2.0)])
    for kw in ({}, {"affine": False}, {"mean_value": False}):
        assert verify(holds, **kw).status == "verified"
        assert verify(fails, **kw).status == "counterexample"
        assert verify(mx, **kw).status == "verified"
