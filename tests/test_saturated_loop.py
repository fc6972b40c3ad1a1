"""The whole-set decrease test of a quadratic ``V`` under a saturated controller
(:class:`nlyap_opt.certification.roa.SaturatedLoop`, the row-wise remainder of
:class:`~nlyap_opt.certification.roa.TaylorDecrease`) and the ``"sector"`` candidate designed
for it (:func:`nlyap_opt.design.control.polytopic_lyapunov_matrix`): the enclosure holds every
mean-value Jacobian, proofs only where sampling finds the decrease, and a design that the
exact test proves."""

from fractions import Fraction

import casadi as ca
import numpy as np
import pytest

import systems
from nlyap_opt.candidates.quadratic import QUADRATIC_CANDIDATES, certify_quadratics
from nlyap_opt.certification.certificate import RoaProblem
from nlyap_opt.certification.roa import (
    SaturatedLoop,
    TaylorDecrease,
    mean_value_form,
    quadratic_form,
    split_boxes,
)
from nlyap_opt.design.control import (
    lqr,
    lyapunov_matrix,
    polytopic_lyapunov_matrix,
    quadratic_lyapunov,
    saturated_controller,
)
from nlyap_opt.kernel.domain import Ball
from nlyap_opt.kernel.symbolic import closed_loop


def _loop(scale=3.0):
    """``x₁' = x₂, x₂' = sin x₁ − ½x₂ + u − 1`` (hover input ``u_eq = 1``) under the
    saturated LQR controller ``c·tanh(Wx + b)`` with ``c = scale`` (``b = atanh(1/c) ≠ 0``)."""
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    s = systems.System("sat2", x, u, ca.vertcat(x[1], ca.sin(x[0]) - 0.5 * x[1] + u[0] - 1),
                       state_box=[[-2.0, 2.0]] * 2, input_box=[[-scale, scale]], u_eq=[1.0])
    res = lqr(s, np.eye(2), [[1.0]])
    ctrl = saturated_controller(s, res.K, scale)
    cl = closed_loop(s, ctrl, x=ca.SX.sym("y", 2))
    return s, ctrl, cl, res.A - res.B @ res.K


def _in_ellipsoid(P, level, m, rng):
    z = rng.normal(size=(m, P.shape[0]))
    z *= rng.random((m, 1)) ** (1 / P.shape[0]) / np.linalg.norm(z, axis=1, keepdims=True)
    return np.linalg.solve(np.linalg.cholesky(P).T, z.T).T * np.sqrt(level)


def test_pieces_cover_each_box():
    """Each box is cut into k^len(axes) pieces along the axes; the pieces tile it exactly
    (shared float edges, the outer edges the box's own)."""
    lo = np.array([[-1.0, 0.1, -0.3], [-2.0, -0.7, 0.2]])
    hi = np.array([[0.5, 0.3, 0.9], [1.0, 0.1, 0.25]])
    plo, phi, pieces = split_boxes(lo, hi, [0, 2], 3)
    assert pieces == 9 and plo.shape == (18, 3)
    rng = np.random.default_rng(0)
    for i in range(2):
        blo, bhi = plo[9 * i:9 * i + 9], phi[9 * i:9 * i + 9]
        np.testing.assert_array_equal(blo[:, 1], lo[i, 1])      # the axis not cut
        assert blo[:, [0, 2]].min(axis=0).tolist() == lo[i, [0, 2]].tolist()
        assert bhi[:, [0, 2]].max(axis=0).tolist() == hi[i, [0, 2]].tolist()
        pts = lo[i] + (hi[i] - lo[i]) * rng.random((2000, 3))
        inside = np.all((pts[:, None, :] >= blo) & (pts[:, None, :] <= bhi), axis=2)
        assert inside.any(axis=1).all()
        assert np.isclose(np.prod(bhi - blo, axis=1).sum(), np.prod(hi[i] - lo[i]))


@pytest.mark.parametrize("weighted", [False, True])
def test_mean_value_form_bounds_every_matrix_in_the_interval(weighted):
    """``2yᵀP(C + Δ)y ≤ yᵀNy`` for every ``|Δ| ≤ R`` (entrywise), with or without weights."""
    rng = np.random.default_rng(1)
    n = 4
    A = rng.normal(size=(n, n))
    P = A @ A.T + n * np.eye(n)
    C, R = rng.normal(size=(n, n)), np.abs(rng.normal(size=(n, n)))
    d = [Fraction(v) for v in rng.uniform(0.1, 3.0, n)] if weighted else None
    fr = [[Fraction(v) for v in row] for row in P]
    N = np.array(mean_value_form(fr, [[Fraction(v) for v in r] for r in C],
                                 [[Fraction(v) for v in r] for r in R], d), dtype=float)
    for _ in range(2000):
        D = R * rng.uniform(-1, 1, (n, n))
        y = rng.normal(size=n)
        assert 2 * y @ P @ (C + D) @ y <= y @ N @ y + 1e-9 * abs(y @ N @ y)


def test_the_enclosure_holds_every_mean_value_jacobian_on_the_ellipsoid():
    """For ``y`` in ``{yᵀPy ≤ c}`` the mean-value Jacobian ``J̄(y) = ∫J(sy)ds`` (Gauss–Legendre,
    64 nodes) satisfies ``yᵀ(PJ̄ + J̄ᵀP)y ≤ max_v yᵀN_v y`` with ``N_v`` the corners' forms
    plus the remainder: the bound the test relies on."""
    s, ctrl, cl, A = _loop()
    sat = SaturatedLoop(cl.x, s.f_fun, ctrl)
    assert sat.why == ""
    P = lyapunov_matrix(A)
    Pq = quadratic_form(quadratic_lyapunov(P))
    Pf = np.array(Pq, dtype=float)
    level = 0.6 * np.linalg.eigvalsh(Pf)[0] * 4.0
    h = np.sqrt(level * np.diag(np.linalg.inv(Pf)))
    corners, R = sat.enclose(np.column_stack([-h, h]), sat.radii(Pq, level))
    assert len(corners) == 2 ** (1 + len(sat.affine))
    Ns = [np.array(mean_value_form(Pq, J, R), dtype=float) for J in corners]
    J = ca.Function("J", [cl.x], [ca.jacobian(cl.rhs, cl.x)])
    nodes, weights = np.polynomial.legendre.leggauss(64)
    s_nodes, w = 0.5 * (nodes + 1), 0.5 * weights
    rng = np.random.default_rng(2)
    for y in _in_ellipsoid(Pf, level, 300, rng):
        Jbar = sum(wk * np.array(J(sk * y)) for sk, wk in zip(s_nodes, w))
        lhs = y @ (Pf @ Jbar + Jbar.T @ Pf) @ y
        assert lhs <= max(y @ N @ y for N in Ns) + 1e-9


def test_the_saturated_test_proves_only_where_sampling_finds_the_decrease():
    """``V = xᵀPx`` (the LQR loop's Lyapunov matrix) under the saturated controller with a small
    authority (1.5 against the hover input 1): proved on a small sublevel set, where 10⁵
    samples agree and the entrywise enclosure alone proves nothing, and never where a
    sample shows ``V̇ ≥ 0``."""
    s, ctrl, cl, A = _loop(scale=1.5)
    P = lyapunov_matrix(A)
    Pq = quadratic_form(quadratic_lyapunov(P))
    sat = SaturatedLoop(cl.x, s.f_fun, ctrl)
    test = TaylorDecrease(cl.x, cl.rhs, Pq, saturated=sat)
    V = ca.bilin(ca.DM(np.array(Pq, dtype=float)), cl.x, cl.x)
    Vdot = ca.Function("vd", [cl.x], [ca.jacobian(V, cl.x) @ cl.rhs])
    Pf = np.array(Pq, dtype=float)
    box = np.array([[-2.0, 2.0]] * 2)
    rng = np.random.default_rng(3)
    verdicts = {}
    for level in (0.01, 0.05, 0.5, 2.0, 8.0):
        pts = _in_ellipsoid(Pf, level, 100000, rng)
        pts = pts[np.all(np.abs(pts) <= 2.0, axis=1) & (np.linalg.norm(pts, axis=1) > 0.02)]
        worst = float(np.max(np.asarray(Vdot(pts.T)).ravel()))
        res = test.check(level, box, 0.02)   # g(0) = c·tanh(b) − 1 is 0 only in floats
        verdicts[level] = res is not None
        if res is not None:
            assert res.status == "verified" and worst < 0, level
    assert verdicts[0.01]
    assert TaylorDecrease(cl.x, cl.rhs, Pq).check(0.01, box, 0.02) is None
    assert not all(verdicts.values())     # the large sets lose the decrease


def test_the_design_meets_its_constraints_and_the_exact_test_proves_it():
    """A linear loop (one corner, no remainder): the designed ``P`` holds ``B_ε`` at level 1,
    its ellipsoid lies in the box, ``−(PA + AᵀP)`` pays the robust margin, and the exact
    test proves the robust decrease on the whole ellipsoid."""
    A = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-6.0, -11.0, -6.0]])
    h, eps, eta = np.array([0.8, 1.2, 2.5]), 0.1, 0.002
    P = polytopic_lyapunov_matrix([A], np.zeros((3, 3)), half_widths=h, inner=eps, eta=eta,
                                  components=[2])
    assert P is not None
    assert np.array_equal(P, P.T)        # exactly: a saved P must be symmetric
    assert np.linalg.eigvalsh(P)[-1] * eps ** 2 < 1
    assert np.all(np.diag(np.linalg.inv(P)) <= h ** 2 * (1 + 1e-6))
    x = ca.SX.sym("x", 3)
    Pq = quadratic_form(quadratic_lyapunov(P))
    test = TaylorDecrease(x, ca.mtimes(ca.DM(A), x), Pq, eta=eta, components=[2])
    assert test.check(1.0, np.column_stack([-h, h]), eps).status == "verified"


def test_the_sector_candidate_is_certified_with_a_sampled_decrease():
    """Through the quadratic stage (true f): ``"sector"`` gives a ``P``, certified, and the
    certified sublevel set has ``V̇ < 0`` on 20 000 samples."""
    s, ctrl, cl, A = _loop(scale=2.0)
    problem = RoaProblem(s, quadratic_lyapunov(np.eye(2)), ctrl, None, inner=0.2,
                         outer=2.0, domain=Ball(2.0, 2))
    assert QUADRATIC_CANDIDATES["sector"](A, True, problem.domain) is None   # needs problem
    (c,) = certify_quadratics(problem, ["sector"], box=np.array([[-2.0, 2.0]] * 2), n=61,
                              log=lambda m: None)
    assert c.P is not None and c.certified, c.certificate.reason
    rng = np.random.default_rng(4)
    pts = _in_ellipsoid(c.P, c.certificate.level, 20000, rng)
    pts = pts[np.linalg.norm(pts, axis=1) >= c.certificate.inner]
    f = s.evaluate(pts, ctrl.numpy(pts))
    assert np.all(np.einsum("ij,jk,ik->i", pts, c.P, f) < 0)


def test_a_controller_that_is_not_one_tanh_layer_is_not_split():
    s, ctrl, cl, _ = _loop()
    from nlyap_opt.kernel.network import Layer, Network
    two = Network([Layer(np.ones((3, 2)), np.zeros(3), "tanh"),
                   Layer(np.ones((1, 3)), np.zeros(1), "tanh")])
    assert "one tanh layer" in SaturatedLoop(cl.x, s.f_fun, two).why


def test_the_jacobian_form_on_the_whole_set_holds_where_sampling_agrees():
    """``contracts``: ``PJ(y) + J(y)ᵀP ≺ 0`` at every point of the sublevel set, proved with
    the split only where the largest sampled eigenvalue is negative, and refused on a set
    large enough for the saturation to break it."""
    s, ctrl, cl, A = _loop(scale=1.5)
    P = lyapunov_matrix(A)
    Pq = quadratic_form(quadratic_lyapunov(P))
    Pf = np.array(Pq, dtype=float)
    test = TaylorDecrease(cl.x, cl.rhs, Pq, saturated=SaturatedLoop(cl.x, s.f_fun, ctrl))
    J = ca.Function("J", [cl.x], [ca.jacobian(cl.rhs, cl.x)])
    box = np.array([[-2.0, 2.0]] * 2)
    rng = np.random.default_rng(5)
    verdicts = []
    for level in (0.0005, 0.005, 2.0):
        pts = _in_ellipsoid(Pf, level, 4000, rng)
        worst = max(np.linalg.eigvalsh(Pf @ np.array(J(y)) + np.array(J(y)).T @ Pf)[-1]
                    for y in pts)
        ok = test.contracts(level, box, 0.0)
        verdicts.append(ok)
        if ok:
            assert worst < 0, level
    assert verdicts[0] and not verdicts[-1]


def test_condition_c_with_the_split_is_certified_and_rechecked():
    """Condition (c) of the saturated loop at ε = 0.2: certified (by the candidates in turn, the
    ``sector`` matrix last in two states), and the saved ``P`` and form check again."""
    from nlyap_opt.certification.roa import certify_inner_ellipse
    from nlyap_opt.design.control import InnerStatus
    s, ctrl, cl, A = _loop(scale=2.0)
    out = certify_inner_ellipse(s, ctrl, 0.2)
    assert out["verdict"] is InnerStatus.CERTIFIED, out["status"]
    again = certify_inner_ellipse(s, ctrl, 0.2, P=out["P"], form=out["form"])
    assert again["verdict"] is InnerStatus.CERTIFIED


def test_numbers_beyond_floats_leave_the_test_undecided_without_an_error():
    """A loop whose enclosure is finite but beyond float range in the weights' search: the
    test returns ``None`` (undecided), as the exact test alone did."""
    x = ca.SX.sym("x", 2)
    g = ca.vertcat(-x[0] + 1e307 * x[0] ** 3, -x[1])
    Pq = quadratic_form(quadratic_lyapunov(10 * np.eye(2)))
    assert TaylorDecrease(x, g, Pq).check(10.0, np.array([[-1.0, 1.0]] * 2), 0.0) is None


def test_a_saved_sector_certificate_rechecks_and_a_tampered_one_does_not(tmp_path):
    """The catalogue pendulum under a saturated controller: the ``sector`` quadratic is
    certified, saved, and re-checked from its files (the split rebuilt from the saved
    controller); a flatter ``V`` (a larger set) is refused."""
    from nlyap_opt.certification.certificate import recheck_certificate, save_certificate
    from nlyap_opt.kernel.network import Network
    s = systems.get("inverted_pendulum")
    res = lqr(s, np.eye(2), [[1.0]])
    ctrl = saturated_controller(s, res.K, 4.0)
    problem = RoaProblem(s, quadratic_lyapunov(np.eye(2)), ctrl, None, inner=0.4, outer=4.0)
    (c,) = certify_quadratics(problem, ["sector"], box=np.array([[-4.0, 4.0]] * 2), n=41,
                              log=lambda m: None)
    assert c.certified, c.certificate.reason
    from dataclasses import replace
    d = tmp_path / "sector"
    save_certificate(c.certificate, replace(problem, V=quadratic_lyapunov(c.P),
                                            inner=c.certificate.inner), d)
    assert recheck_certificate(d, log=lambda m: None).certified
    V = Network.load(d / "V.json")
    V.layers[0].weight = V.layers[0].weight * 0.5
    V.save(d / "V.json")
    assert not recheck_certificate(d, log=lambda m: None).certified


def test_the_volume_bound_holds_the_sector_candidates_ellipse():
    """:func:`inner_ellipse_bound` (which skips candidates that cannot win) holds every
    ellipse condition (c) may prove, the ``sector`` matrix's included."""
    from nlyap_opt.certification.roa import (
        _sector_candidate,
        ellipse_around_ball,
        grid_points,
        inner_ellipse_bound,
    )
    s, ctrl, cl, A = _loop(scale=2.0)
    sat = SaturatedLoop(cl.x, s.f_fun, ctrl)
    P = _sector_candidate(sat, cl, A, s, 0.2)
    assert P is not None
    c_q, _ = ellipse_around_ball(P, 0.2)
    pts, _ = grid_points(np.array([[-2.0, 2.0]] * 2), 121)
    inside = np.einsum("ij,jk,ik->i", pts, P, pts) <= c_q
    mask = inner_ellipse_bound(s, ctrl, 0.2, pts)
    assert inside.sum() > 10 and mask is not None and np.all(mask[inside])
