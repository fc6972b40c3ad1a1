"""Verification in the coordinates of the decrease's Hessian (option ``precondition``) and the
affine Hessian ranges of the second-order form: soundness, covers, mutations."""

from fractions import Fraction

import casadi as ca
import numpy as np
import pytest
from certcheck import assert_confirmed, assert_no_sample_contradicts

from nlyap_opt.kernel.walker import evaluate
from verification import Interval, IntervalArithmetic, VerificationProblem, lyapunov_problem, verify
from verification.affine import tight_ranges
from verification.precondition import hessian_coordinates, precondition, solve_preconditioned
from verification.verify import confirm_points, verify_interval


def _rotation(n: int, seed: int = 0) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(n, n)))
    return q


def _stiff(n=3, ratio=1000.0, k=0.3, level=None):
    """``x' = Ax + k (x_i sin x_{i+1})_i`` with ``A = R diag(-1 … -ratio) Rᵀ`` (a rotated stiff
    loop) and ``V = |x|²``: the decrease ``2xᵀAx + …`` has a Hessian whose axes are not the
    coordinate axes and whose eigenvalues span ``ratio``."""
    x = ca.SX.sym("x", n)
    R = _rotation(n)
    A = R @ np.diag(-np.geomspace(1.0, ratio, n)) @ R.T
    f = ca.mtimes(ca.DM(A), x) + k * ca.vertcat(*[ca.sin(x[(i + 1) % n]) * x[i]
                                                  for i in range(n)])
    V = ca.sumsqr(x)
    lie = ca.dot(ca.gradient(V, x), f)
    return lyapunov_problem(x, V, lie, inner=0.05, outer=1.0, level=level,
                            check_positive=False), A


def _exact_solve(T: np.ndarray, x: np.ndarray) -> list[Fraction]:
    """``T⁻¹x`` in exact rational arithmetic (Gauss-Jordan on the float entries)."""
    n = len(T)
    a = [[Fraction(float(T[i, j])) for j in range(n)] + [Fraction(float(x[i]))]
         for i in range(n)]
    for c in range(n):
        p = max(range(c, n), key=lambda r: abs(a[r][c]))
        a[c], a[p] = a[p], a[c]
        for r in range(n):
            if r != c and a[r][c]:
                f = a[r][c] / a[c][c]
                a[r] = [u - f * v for u, v in zip(a[r], a[c])]
    return [a[i][n] / a[i][i] for i in range(n)]


def test_preconditioned_verdict_survives_dense_sampling_and_needs_fewer_boxes():
    problem, _ = _stiff()
    plain = verify(problem, second_order=True)
    pre = verify(problem, second_order=True, precondition=True)
    assert plain.status == pre.status == "verified"
    # the boxes follow the Hessian's axes: measured 472 boxes against 4570
    assert pre.boxes * 3 < plain.boxes, (pre.boxes, plain.boxes)
    assert_no_sample_contradicts(problem, 300_000)


def test_mutated_loop_gets_a_confirmed_counterexample_in_x():
    problem, _ = _stiff(ratio=100.0, k=8.0)       # the nonlinear term wins near |x| = 1
    res = verify(problem, second_order=True, precondition=True)
    assert res.status == "counterexample"
    cex = res.counterexample
    assert np.all(cex.point >= problem.box[:, 0]) and np.all(cex.point <= problem.box[:, 1])
    assert_confirmed(problem, cex)                   # a point of x, in the region, p >= 0
    assert confirm_points(problem, cex.point[None])


def test_unconfirmed_z_counterexample_is_unknown_never_a_counterexample():
    problem, _ = _stiff(ratio=100.0, k=8.0)
    M = hessian_coordinates(problem)
    real = verify_interval(precondition(problem, M).problem, second_order=True)
    assert real.status == "counterexample"
    res = solve_preconditioned(problem, M, lambda p: real, lambda p, pts: [])
    assert res.status == "unknown" and res.counterexample is None
    assert len(res.undecided)                         # the point's box stays open


def test_cover_holds_the_exact_preimage_of_the_root_box():
    problem, _ = _stiff()
    rng = np.random.default_rng(3)
    M = _rotation(3, 5) @ np.diag([30.0, 1.0, 0.2]) @ _rotation(3, 6)
    pre = precondition(problem, M)
    box = problem.box
    corners = np.array(np.meshgrid(*box, indexing="ij")).reshape(3, -1).T
    pts = np.vstack([corners, rng.uniform(box[:, 0], box[:, 1], (30, 3))])
    zbox = pre.problem.box
    for x in pts:
        z = _exact_solve(pre.T, x)
        assert all(zbox[i, 0] <= z[i] <= zbox[i, 1] for i in range(3)), (x, z, zbox)
    # and the x boxes given back cover the exact image T z of each z box
    zl = rng.uniform(zbox[:, 0], zbox[:, 1], (20, 3))
    zb = np.stack([zl, zl + rng.uniform(0, 0.1, (20, 3))], axis=-1)
    xb = pre.x_boxes(zb)
    for b, zbx in zip(xb, zb):
        for z in (zbx[:, 0], zbx[:, 1], 0.5 * (zbx[:, 0] + zbx[:, 1])):
            x = [sum(Fraction(float(pre.T[i, j])) * Fraction(float(z[j])) for j in range(3))
                 for i in range(3)]
            assert all(b[i, 0] <= max(x[i], Fraction(box[i, 0])) for i in range(3))
            assert all(min(x[i], Fraction(box[i, 1])) <= b[i, 1] for i in range(3))


def test_hessian_coordinates_whiten_a_definite_hessian_and_decline_others():
    problem, A = _stiff(ratio=100.0)
    M = hessian_coordinates(problem)
    H = 2 * (A + A.T)                      # the decrease's Hessian at 0 (V = |x|²)
    w, U = np.linalg.eigh(H)
    np.testing.assert_allclose(M.T @ M, U @ np.diag(np.abs(w)) @ U.T, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(M, hessian_coordinates(problem))   # same H, same M
    x = ca.SX.sym("x", 2)
    saddle = lyapunov_problem(x, ca.sumsqr(x), x[0] ** 2 - x[1] ** 2 - 1, inner=0.1, outer=1.0,
                              check_positive=False)
    assert hessian_coordinates(saddle) is None
    assert verify(saddle, precondition=True).status == verify(saddle).status


def test_precondition_is_deterministic_and_excludes_given_boxes():
    problem, _ = _stiff(level=0.5)
    a = verify(problem, second_order=True, precondition=True)
    b = verify(problem, second_order=True, precondition=True)
    assert (a.status, a.boxes, a.depth) == (b.status, b.boxes, b.depth)
    with pytest.raises(ValueError, match="precondition excludes"):
        verify_interval(problem, precondition=True, boxes=problem.box[None])
    with pytest.raises(ValueError, match="invertible|ill-conditioned"):
        precondition(problem, np.diag([1.0, 1.0, 0.0]))


def test_tight_ranges_hold_every_sample_and_are_never_looser_than_intervals():
    x = ca.SX.sym("x", 3)
    W = np.random.default_rng(0).normal(size=(8, 3))
    v = ca.sumsqr(ca.tanh(ca.mtimes(ca.DM(W), x)))
    g = ca.gradient(v, x)
    f = ca.dot(g, ca.vertcat(x[1], -ca.sin(x[0]) - x[1], x[0] * x[2]))
    H = ca.Function("H", [x], [ca.hessian(f, x)[0], ca.gradient(f, x)])
    rng = np.random.default_rng(1)
    lo = rng.uniform(-1, 0.8, (40, 3))
    hi = lo + rng.uniform(0.01, 0.3, (40, 3))
    tight = tight_ranges(H, lo, hi)
    nat = evaluate(H, [Interval(lo, hi)], IntervalArithmetic())
    Hf = ca.Function("Hf", [x], [ca.vec(ca.hessian(f, x)[0]), ca.gradient(f, x)])
    wider = 0
    for t, a in zip(tight, nat):
        assert np.all(t.lo >= a.lo) and np.all(t.hi <= a.hi)
        wider += np.sum((t.hi - t.lo) < (a.hi - a.lo))
    assert wider > 0                               # affine forms win somewhere
    for b in range(len(lo)):
        pts = lo[b] + (hi[b] - lo[b]) * rng.random((300, 3))
        vals = [np.array(o) for o in Hf.map(len(pts))(pts.T)]
        for t, val in zip(tight, vals):
            assert np.all(val.T <= t.hi[b]) and np.all(val.T >= t.lo[b])


@pytest.mark.slow  # a Dask cluster start (several seconds)
def test_on_a_cluster_coordinates_change_before_the_tasks():
    from nlyap_opt.distributed.parallel import check, dask_client, verify_distributed, verifying_on
    problem, _ = _stiff(level=0.5)
    serial = verify(problem, second_order=True, precondition=True)
    with dask_client(workers=2) as client:
        with verifying_on(client):
            res = check(problem, second_order=True, precondition=True)
        with pytest.raises(TypeError, match="precondition"):
            verify_distributed(problem, client, precondition=True)
    assert res.status == serial.status == "verified"


@pytest.mark.slow
def test_planar_quadrotor_volume_P_at_ten_times_the_lqr_volume():
    """The ``volume`` P of the quadrotor's large preset at level 0.08 (ellipsoid volume
    2.0e-4, 10.8 times the LQR P's certified 1.85e-5): verified only in the Hessian's
    coordinates (measured: 1.6e5 boxes, 48 s at load 7; axis-aligned boxes: unknown after
    2e5)."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
    from high_dimension import loop

    from nlyap_opt.candidates.quadratic import QUADRATIC_CANDIDATES
    from nlyap_opt.design.control import quadratic_lyapunov
    from verification import closed_loop_problem

    s, ctrl, A, _ = loop("planar_quadrotor")
    P = QUADRATIC_CANDIDATES["volume"](A, True)
    problem = closed_loop_problem(s, quadratic_lyapunov(P), ctrl, inner=0.025, outer=1.0,
                                  level=0.08, check_positive=False)
    res = verify(problem, second_order=True, precondition=True, max_boxes=1_000_000)
    assert res.status == "verified", res
    # dense samples of the ellipsoid V <= 0.08 (the root box is almost all outside it)
    rng = np.random.default_rng(0)
    u = rng.normal(size=(200_000, 6))
    u *= rng.random((len(u), 1)) ** (1 / 6) / np.linalg.norm(u, axis=1, keepdims=True)
    X = np.linalg.solve(np.linalg.cholesky(P).T, u.T).T * np.sqrt(0.08)
    F = np.array(problem.function(X.T)).T
    region = np.all(F[:, :problem.n_constraints] <= 0, axis=1)
    assert region.sum() > 100_000
    assert np.all(F[region, problem.n_constraints:] < 0)
    # the certificate mutated to a level past the least violation (V = 0.287): refuted, in x
    bad = closed_loop_problem(s, quadratic_lyapunov(P), ctrl, inner=0.025, outer=1.0,
                              level=0.3, check_positive=False)
    r = verify(bad, second_order=True, precondition=True, max_boxes=1_000_000)
    assert r.status == "counterexample"
    assert_confirmed(bad, r.counterexample)


def _fold_problem():
    """A problem whose graph constant ``c = fl(1/t)`` meets the entry ``t`` of ``T = M⁻¹``
    (``M = diag(3, 3)``, ``T`` rounded to 24 bits): ``c·t`` rounds to exactly 1 but is not 1.
    Substituting ``x = T z`` folds ``c·(t·z₀)`` into ``z₀`` and drops the constant's widening."""
    t = float(np.ldexp(np.round(np.ldexp(1 / 3, 25)), -25))     # fl(1/3) to 24 bits
    c = 1.0 / t
    assert c * t == 1.0 and Fraction(c) * Fraction(t) != 1    # the premise of the test
    x = ca.SX.sym("x", 2)
    g = c * x[0]                                                 # region: x₀ ≤ 0
    p = c * x[1] - 3 * x[0] ** 2 - 3 * x[1] ** 2 - 1
    problem = VerificationProblem(x, [[-1.0, 1.0], [-1.0, 1.0]], [g], [p])

    def exact(z):  # g, p, their gradients and p's Hessian in z, in rationals
        T = [[Fraction(v) for v in row] for row in pre.T]
        zq = [Fraction(float(v)) for v in z]
        xq = [sum(T[i][j] * zq[j] for j in range(2)) for i in range(2)]
        cq = Fraction(c)
        gx = [cq, Fraction(0)]
        px = [-6 * xq[0], cq - 6 * xq[1]]
        Hx = [[Fraction(-6), Fraction(0)], [Fraction(0), Fraction(-6)]]

        def chain(v):  # vᵀ T
            return [sum(v[i] * T[i][j] for i in range(2)) for j in range(2)]
        Hz = [[sum(T[i][a] * Hx[i][k] * T[k][b] for i in range(2) for k in range(2))
               for b in range(2)] for a in range(2)]
        return (cq * xq[0], cq * xq[1] - 3 * xq[0] ** 2 - 3 * xq[1] ** 2 - 1,
                chain(gx), chain(px), Hz)

    pre = precondition(problem, np.diag([3.0, 3.0]))
    assert pre.T[0, 0] == pre.T[1, 1] == t
    return pre, exact


def _inside(iv, k, value) -> bool:
    return Fraction(float(iv.lo[k])) <= value <= Fraction(float(iv.hi[k]))


def test_z_graphs_enclose_the_exact_values_where_a_fold_with_T_lands_on_an_integer():
    """The graphs in ``z`` are the original ones evaluated at ``x = T z`` in outward-rounded
    arithmetic: at points and on boxes of ``z`` their interval and affine enclosures hold the
    exact rational values of ``g(Tz)``, ``p(Tz)``, ``∇g(Tz)ᵀT``, ``∇p(Tz)ᵀT`` and
    ``Tᵀ∇²p T`` (a substituted graph gives the point enclosure ``[z₀, z₀]`` of ``c·t·z₀``)."""
    from verification.affine import Affine, AffineArithmetic
    pre, exact = _fold_problem()
    zp = pre.problem
    fG, fH = zp.second_order_functions
    rng = np.random.default_rng(0)
    zb = zp.box
    pts = rng.uniform(zb[:, 0], zb[:, 1], (40, 2))
    half = rng.uniform(0, 0.05, (40, 2))
    for lo, hi in ((pts, pts.copy()), (pts - half, pts + half)):
        F, J = evaluate(zp.function_jacobian, [Interval(lo, hi)], IntervalArithmetic())
        G = evaluate(fG, [Interval(lo, hi)], IntervalArithmetic())[0]
        H = evaluate(fH, [Interval(lo, hi)], IntervalArithmetic())[0]
        A = evaluate(zp.function, [Affine.from_box(lo, hi)], AffineArithmetic())[0]
        A = A.to_interval()
        for b in range(len(lo)):
            for z in (lo[b], hi[b], 0.5 * (lo[b] + hi[b])):
                g, p, dg, dp, Hz = exact(z)
                Fb, Jb, Gb, Hb, Ab = (Interval(iv.lo[b].ravel(), iv.hi[b].ravel())
                                      for iv in (F, J, G, H, A))
                # rows: g, the root-box ellipsoid, p; J column-major (3 x 2)
                assert _inside(Fb, 0, g) and _inside(Fb, 2, p), (z, g, Fb)
                assert _inside(Ab, 0, g) and _inside(Ab, 2, p)
                assert all(_inside(Jb, 3 * j, dg[j]) and _inside(Jb, 3 * j + 2, dp[j])
                           for j in range(2)), (z, dg, dp, Jb)
                assert all(_inside(Gb, j, dp[j]) for j in range(2))
                assert all(_inside(Hb, a + 2 * c, Hz[a][c]) for a in range(2) for c in range(2))


def test_coordinates_are_the_same_for_every_eigenbasis_of_a_repeated_eigenvalue():
    """A LAPACK build may return any rotation of the basis of a repeated eigenvalue's
    eigenspace: ``M`` is the same for all of them (the plain scaled eigenvector rows are
    not); ``MᵀM = |H|``; and for simple eigenvalues ``M`` is the sign-fixed scaled rows."""
    from verification.precondition import _coarse, _eigen_rows
    Q = _rotation(4, 7)
    H = Q @ np.diag([-2.0, -2.0, -2.0, -9.0]) @ Q.T
    w, U = np.linalg.eigh(H)                              # ascending: -9, then the -2's
    Ms, rows = [], []
    for seed in range(4):                                 # rotate within the eigenspace
        R = np.eye(4)
        R[1:, 1:] = _rotation(3, 100 + seed)
        V = U @ R
        np.testing.assert_allclose(V @ np.diag(w) @ V.T, H, atol=1e-12)
        Ms.append(_eigen_rows(w, V))
        rows.append(_coarse((V * np.sqrt(np.abs(w))).T))
    for M in Ms[1:]:
        np.testing.assert_array_equal(M, Ms[0])
    assert any(not np.array_equal(r, rows[0]) for r in rows[1:])  # eigenvector rows differ
    np.testing.assert_allclose(Ms[0].T @ Ms[0], -H, rtol=1e-6, atol=1e-6)   # |H| = -H here
    # simple eigenvalues: the rows of the eigenvectors, each with its largest entry positive
    w, U = np.linalg.eigh(Q @ np.diag([-1.0, -2.0, -3.0, -9.0]) @ Q.T)
    sign = np.sign(U[np.argmax(np.abs(U), axis=0), np.arange(4)])
    np.testing.assert_array_equal(_eigen_rows(w, U), _coarse((U * sign * np.sqrt(-w)).T))
    np.testing.assert_array_equal(_eigen_rows(w, -U), _eigen_rows(w, U))


def test_an_unpickled_problem_is_preconditioned_from_its_graphs():
    """A problem restored from a pickle holds graphs, not expressions: ``precondition``
    (and the choice of ``M``) works from the graphs alone, with the original's verdict."""
    import pickle
    problem, _ = _stiff(level=0.5)
    clone = pickle.loads(pickle.dumps(problem))
    assert clone.properties is None
    np.testing.assert_array_equal(hessian_coordinates(clone), hessian_coordinates(problem))
    a = verify(problem, second_order=True, precondition=True)
    b = verify(clone, second_order=True, precondition=True)
    assert a.status == b.status == "verified"
    assert (a.boxes, a.depth) == (b.boxes, b.depth)


def test_checked_problem_keeps_per_output_checks_in_z():
    """With a saturation (``fmin``/``fmax``: checked for kinks per box and output) in the
    decrease only, the ``z`` problem flags kinks for the decrease and never for the
    constraints (the calls attribute each check to the outputs it feeds), and verifies."""
    from verification.interval import CheckedIntervalArithmetic
    x = ca.SX.sym("x", 2)
    A = np.array([[-1.0, 0.4], [0.0, -30.0]])
    u = ca.fmin(ca.fmax(3 * x[0] - x[1], -0.5), 0.5)
    f = ca.mtimes(ca.DM(A), x) + ca.vertcat(0.3 * u * x[1], 0)
    problem = lyapunov_problem(x, ca.sumsqr(x), ca.dot(2 * x, f), inner=0.05, outer=1.0,
                               check_positive=False)
    zp = precondition(problem, hessian_coordinates(problem)).problem
    assert problem.checked and zp.checked
    rng = np.random.default_rng(2)
    lo = rng.uniform(zp.box[:, 0], zp.box[:, 1], (300, 2))
    hi = lo + 0.1
    ar = CheckedIntervalArithmetic(len(lo), zp.n_constraints + zp.n_properties + 1)
    ar.collect(evaluate(zp.function_jacobian_checked, [Interval(lo, hi)], ar))
    assert ar.jump[:, -2].any()                              # the decrease: some boxes
    assert not ar.jump[:, :zp.n_constraints].any()           # the constraints: none
    res = verify(problem, second_order=True, precondition=True)
    assert res.status == verify(problem, second_order=True).status == "verified"
