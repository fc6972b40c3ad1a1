"""Condition (a) of a quadratic ``V = xᵀPx`` decided on the sublevel set's box by the
mean-value form of the closed loop (:class:`nlyap_opt.certification.roa.TaylorDecrease`):
proofs only where the decrease holds (also where CasADi's float constant folding would hide
a violation), refusals where the test does not apply, and the level search using it."""

from fractions import Fraction

import casadi as ca
import numpy as np
import pytest
from scipy.linalg import solve_continuous_lyapunov

from nlyap_opt.certification.roa import TaylorDecrease, certify_level, quadratic_form
from nlyap_opt.design.control import quadratic_lyapunov
from nlyap_opt.kernel.domain import Box
from nlyap_opt.kernel.exact import inverse_diagonal
from nlyap_opt.kernel.symbolic import closed_loop


def _lie(V, x, g):
    return ca.jacobian(V, x) @ g


def _setup(P, g_of_x, n):
    """``(x, V, lie, P exact, g)``."""
    x = ca.SX.sym("x", n)
    V_net = quadratic_lyapunov(P)
    V = V_net.casadi(x)
    g = g_of_x(x)
    return x, V, _lie(V, x, g), quadratic_form(V_net), g


def _sampled_max(x, V, lie, level, box, rng, m=200000):
    """Largest sampled ``dV/dt`` on ``{V ≤ level} ∩ box`` minus a tiny ball."""
    n = box.shape[0]
    pts = box[:, 0] + (box[:, 1] - box[:, 0]) * rng.random((m, n))
    f = ca.Function("f", [x], [V, lie])
    v, d = (np.asarray(a).ravel() for a in f(pts.T))
    keep = (v <= level) & (np.linalg.norm(pts, axis=1) > 1e-3)
    return float(np.max(d[keep]))


def _stiff_chain(n):
    """x0' = x1, ..., x_{n-1}' = -Σ a_k x_k: a stiff linear chain (poles -1, -2, ... scaled)."""
    poles = -np.geomspace(0.5, 60.0, n)
    coef = np.poly(poles)[1:][::-1]              # characteristic polynomial, low order first
    A = np.diag(np.ones(n - 1), 1)
    A[-1, :] = -coef
    return A


@pytest.mark.parametrize("n", [2, 4, 6])
def test_a_linear_loop_is_proved_at_every_level_and_sampling_agrees(n):
    """A linear closed loop has a constant Hessian: the test is exact, so it proves the
    decrease at any level (also past ``D``'s box), and sampling finds no violation."""
    A = _stiff_chain(n)
    P = solve_continuous_lyapunov(A.T, -np.eye(n))
    x, V, lie, Pq, g = _setup(P, lambda z: ca.DM(A) @ z, n)
    t = TaylorDecrease(x, g, Pq)
    assert t.why == ""
    box = np.array([[-1.0, 1.0]] * n)
    rng = np.random.default_rng(n)
    for level in (1e-4, 0.3, 50.0):
        res = t.check(level, box, 1e-3)
        assert res is not None and res.status == "verified" and res.backend == "taylor"
        Y = t.box(level, box)
        assert _sampled_max(x, V, lie, level, Y, rng, 50000) < 0


def test_an_unstable_loop_is_never_proved():
    """One unstable mode: ``A_clᵀP + PA_cl`` is indefinite for the stable block's ``P``, and
    the test proves nothing at any level (sampling finds the increase)."""
    A = np.array([[0.2, 1.0], [0.0, -1.0]])
    P = np.array([[1.0, 0.0], [0.0, 1.0]])
    x, V, lie, Pq, g = _setup(P, lambda z: ca.DM(A) @ z, 2)
    t = TaylorDecrease(x, g, Pq)
    box = np.array([[-1.0, 1.0]] * 2)
    for level in (1e-3, 0.5):
        assert t.check(level, box, 1e-3) is None
        assert _sampled_max(x, V, lie, level, t.box(level, box), np.random.default_rng(0)) > 0


def test_a_nonlinear_loop_is_proved_inside_and_not_at_the_roa_boundary():
    """``x' = -x + x³`` (ROA |x| < 1), ``V = x²``: ``dV/dt = -2x²(1 - x²)``. The mean
    Jacobian on 16 slices is at most ``-1 + 1.096 x²``, so the decrease is proved for
    ``x² ≤ 0.8``; at ``|x| ≤ 1`` it vanishes at ±1 and nothing may be proved, past it the
    decrease fails."""
    x, V, lie, Pq, g = _setup(np.array([[1.0]]), lambda z: -z + z ** 3, 1)
    t = TaylorDecrease(x, g, Pq)
    box = np.array([[-3.0, 3.0]])
    assert t.check(0.25, box, 1e-3).status == "verified"
    assert t.check(0.8, box, 1e-3).status == "verified"      # -1 + 1.096·0.8 < 0
    assert t.check(1.0, box, 1e-3) is None
    assert t.check(1.21, box, 1e-3) is None
    # the box of D cuts the ellipse's: |x| ≤ 0.6 within D = [-0.6, 3]
    assert np.allclose(t.box(4.0, np.array([[-0.6, 3.0]])), [[-0.6, 2.0]])
    assert t.check(4.0, np.array([[-0.6, 0.6]]), 1e-3).status == "verified"


def test_the_box_holds_the_ellipsoid():
    rng = np.random.default_rng(3)
    U = np.linalg.qr(rng.standard_normal((3, 3)))[0]
    P = U @ np.diag([1.0, 10.0, 300.0]) @ U.T
    x, V, lie, Pq, g = _setup(P, lambda z: -z, 3)
    t = TaylorDecrease(x, g, Pq)
    Y = t.box(0.7, np.array([[-10.0, 10.0]] * 3))
    # extreme points of the ellipsoid xᵀPx = c along each axis: ±√(c (P⁻¹)_kk), held
    # exactly (rationals) and with at most a few ulps to spare
    d = inverse_diagonal(Pq)
    assert all(Fraction(hk) ** 2 >= Fraction(0.7) * dk for hk, dk in zip(Y[:, 1], d))
    h = np.sqrt(0.7 * np.array([float(v) for v in d]))
    assert np.all(Y[:, 1] <= h * (1 + 1e-12))
    assert np.array_equal(Y[:, 0], -Y[:, 1])


@pytest.mark.parametrize("case", ["abs", "sqrt", "division"])
def test_the_test_refuses_a_closed_loop_that_is_not_smooth_on_the_box(case):
    """A kink or a partial operation inside the box (``|x₀|`` at 0, ``‖x‖`` at 0): the
    checked walk does not clear it, nothing is proved. A division whose denominator stays
    positive is used, and proves nothing here either: ``V̇ = 0`` on the ``x₁`` axis."""
    x = ca.SX.sym("x", 2)
    V_net = quadratic_lyapunov(np.eye(2))
    g = {"abs": -x + ca.vertcat(0.1 * ca.fabs(x[0]) * x[0], 0),       # not C²... nor C¹-safe
         "sqrt": -x + 0.01 * ca.norm_2(x),
         "division": -x * (x[0] ** 2 / (x[0] ** 2 + x[1] ** 2 + 0.5))}[case]
    t = TaylorDecrease(x, g, quadratic_form(V_net))
    Y = t.box(0.5, np.array([[-1.0, 1.0]] * 2))
    assert t._smooth_on(Y) == (case == "division")
    assert t.check(0.5, np.array([[-1.0, 1.0]] * 2), 0.1) is None


def test_an_offset_equilibrium_is_proved_only_outside_the_ball_it_allows():
    """``g = −x + δe₁`` (``g(0) ≠ 0``), ``V = ‖x‖²``: ``V̇ = −2‖x‖² + 2δx₁ > 0`` at
    ``x = (t, 0)``, ``0 < t < δ``. Proved outside ``ε > δ`` (``−N = 2I``, ``λ = 2δ/ε``);
    never at ``ε ≤ δ``, nor without an inner ball."""
    d = 1e-3
    x, V, lie, Pq, g = _setup(np.eye(2), lambda z: -z + ca.vertcat(d, 0), 2)
    t = TaylorDecrease(x, g, Pq)
    box = np.array([[-1.0, 1.0]] * 2)
    assert t.check(0.5, box, 0.01).status == "verified"
    assert t.check(0.5, box, 0.0) is None
    assert t.check(0.5, box, 0.5 * d) is None
    assert t.check(0.5, box, d) is None


def test_float_folding_that_hides_an_offset_is_not_trusted():
    """``g₁ = −x₁ + ((x₁² + 10¹⁶) + 1) − 10¹⁶``: substituting 0 folds the extra term to 0 in
    floats, its real value is 1, so ``V̇(0.05, 0) = +0.095`` for ``V = ‖x‖²``; the interval
    enclosure of ``g(0)`` sees it, and ε = 0.01 is not proved."""
    x = ca.SX.sym("x", 2)
    g = ca.vertcat(-x[0] + ((x[0] ** 2 + 1e16) + 1) - 1e16, -x[1])
    V_net = quadratic_lyapunov(np.eye(2))
    t = TaylorDecrease(x, g, quadratic_form(V_net))
    assert t.check(0.01, np.array([[-1.0, 1.0]] * 2), 0.01) is None


def test_a_decrease_that_fails_by_a_rounding_of_the_product_is_not_proved():
    """A linear loop whose exact ``AᵀP + PA`` has the (1, 1) entry ``+ε`` (``V̇ > 0`` along
    the x₁ axis) while float products round it negative: ``P`` and ``A`` enter the test as
    exact rationals, so it is refused."""
    from fractions import Fraction as Fr
    rng = np.random.default_rng(0)
    for _ in range(300):
        Pf = np.diag(rng.uniform(0.5, 2, 2))
        Pf[0, 1] = Pf[1, 0] = rng.uniform(-0.4, 0.4)
        net = quadratic_lyapunov(Pf)
        Pq = quadratic_form(net)
        a21, a22 = rng.uniform(-2, 2), -1.0
        a0 = float(-Pq[0][1] * Fr(a21) / Pq[0][0])
        for k in range(-2, 3):
            a11 = a0 + k * np.spacing(a0)
            a12 = float(-(Pq[0][1] * Fr(a22) + Pq[1][0] * Fr(a11) + Pq[1][1] * Fr(a21))
                        / Pq[0][0])
            A = [[Fr(a11), Fr(a12)], [Fr(a21), Fr(a22)]]
            h11 = 2 * sum(Pq[0][k2] * A[k2][0] for k2 in range(2))   # (PA + AᵀP)₁₁
            if h11 > 0:
                x = ca.SX.sym("x", 2)
                g = ca.DM(np.array([[a11, a12], [a21, a22]])) @ x
                t = TaylorDecrease(x, g, Pq)
                assert t.why == ""
                assert t.check(1.0, np.array([[-2.0, 2.0]] * 2), 0.01) is None
                return
    pytest.fail("no case with a positive exact entry was found")


def test_the_level_search_uses_it_and_agrees_with_the_verifier():
    """A 4-D stiff linear loop on the box [-1, 1]⁴: the level search proves the decrease by
    Taylor at the containment level; without the exact matrix (no ``quadratic``) the
    interval verifier must bisect and the certified level is not larger."""
    A = _stiff_chain(4)
    P = solve_continuous_lyapunov(A.T, -np.eye(4))
    P = P / np.max(np.linalg.eigvalsh(P))
    x, V, lie, Pq, g = _setup(P, lambda z: ca.DM(A) @ z, 4)
    D = Box([[-1.0, 1.0]] * 4)
    kw = dict(level=10.0, inner=0.01, margin=0.0, max_tries=4, log=lambda m: None, domain=D)
    res = certify_level(x, V, lie, quadratic=Pq, rhs=g, **kw)
    assert res.status == "certified"
    assert res.history[-1]["decrease_backend"] == "taylor"
    # the certified level is the largest the box allows: min over faces of 1/(P⁻¹)_kk
    c_max = 1.0 / np.max(np.diag(np.linalg.inv(np.array(Pq, dtype=float))))
    assert 0.98 * c_max < res.level < c_max
    # a small global margin (learned dynamics) is proved by Taylor too, at the same level;
    # one larger than the decrease at ‖x‖ = ε is not (the verifier then finds it fails)
    small = certify_level(x, V, lie, quadratic=Pq, rhs=g, **{**kw, "margin": 1e-9})
    assert small.status == "certified" and small.level == res.level
    assert small.history[-1]["decrease_backend"] == "taylor"
    big = certify_level(x, V, lie, quadratic=Pq, rhs=g, **{**kw, "margin": 1.0,
                                                               "max_tries": 1})
    assert big.status != "certified"
    assert all(h.get("decrease_backend") != "taylor" for h in big.history)


def test_the_robust_property_of_learned_dynamics_is_proved_only_outside_its_radius(rng):
    """``g = −y`` (a φ), ``V = ‖y‖²``, ``‖f − φ‖ ≤ η``: the robust property
    ``∇V·g + η‖∇_L V‖ = −2r² + 2η‖y_L‖`` (``r = ‖y‖``) is negative exactly where
    ``‖y_L‖ < r²/η``; with every component learned, where ``r > η``. The matrix form of
    the margin, ``(η/ε)(I/t + t P_LᵀP_L)``, is ``2η/ε`` at its best ``t = 1``, so the test
    proves ``ε > η`` (both components, where the scalar bound with ``‖P_L‖_F = √2`` needed
    ``√2 η``; one learned component: ``ε > η`` as well) and never an ``ε`` at which the
    property fails somewhere; a global margin ``m`` needs ``ε > √(m/2)``. Where it proves,
    sampling agrees."""
    eta = 0.01
    x, V, lie, Pq, g = _setup(np.eye(2), lambda z: -z, 2)
    box = np.array([[-1.0, 1.0]] * 2)
    both = TaylorDecrease(x, g, Pq, eta=eta)
    assert both.check(0.5, box, 0.0) is None
    assert both.check(0.5, box, 0.5 * eta) is None        # fails at ‖y‖ < η: not provable
    assert both.check(0.5, box, 0.98 * eta) is None
    assert both.check(0.5, box, 1.02 * eta).status == "verified"   # the sharp threshold
    one = TaylorDecrease(x, g, Pq, eta=eta, components=[0])
    assert one.check(0.5, box, 0.9 * eta) is None
    assert one.check(0.5, box, 1.1 * eta).status == "verified"
    # smoothing s adds η·s: 2η/ε + ηs/ε² must stay below 2 (ε = 0.02: s < 0.04)
    assert TaylorDecrease(x, g, Pq, eta=eta, smoothing=0.03).check(0.5, box, 0.02).status \
        == "verified"
    assert TaylorDecrease(x, g, Pq, eta=eta, smoothing=0.05).check(0.5, box, 0.02) is None
    m = 2e-4
    glob = TaylorDecrease(x, g, Pq, margin=m)
    assert glob.check(0.5, box, 0.9 * np.sqrt(m / 2)) is None
    assert glob.check(0.5, box, 1.1 * np.sqrt(m / 2)).status == "verified"
    # the proved property holds on samples outside the radius
    eps = 1.5 * eta
    robust = lie + eta * ca.norm_2(ca.gradient(V, x))
    pts = rng.uniform(-0.8, 0.8, (100000, 2))
    pts = pts[np.linalg.norm(pts, axis=1) >= eps]
    vals = np.asarray(ca.Function("p", [x], [robust])(pts.T)).ravel()
    assert np.all(vals < 0)


@pytest.mark.parametrize("inner", [0.0, 0.01])
def test_a_derivative_that_casadi_folds_to_a_wrong_sign_is_not_trusted(inner):
    """``g = 2((10¹⁶x + x) − 10¹⁶x) − x`` is ``+x`` as a real function (unstable), but
    ``ca.jacobian`` folds ``10¹⁶ + 1`` to ``10¹⁶`` and gives the constant ``−1``. The test's
    Jacobian is CasADi's forward mode along a symbolic seed: interval arithmetic rounds
    ``10¹⁶·S + S`` outward and sees the ``+1``, so nothing is proved."""
    from fractions import Fraction as Fr
    x = ca.SX.sym("x", 1)
    g = 2 * ((1e16 * x[0] + x[0]) + (-1e16) * x[0]) - x[0]
    assert float(ca.jacobian(g, x)) == -1.0
    t = TaylorDecrease(x, g, [[Fr(1)]])
    assert t.why == ""
    assert t.check(0.25, np.array([[-1.0, 1.0]]), inner) is None


def test_a_controller_constant_that_expansion_would_fold_is_not_trusted(
        offset_equilibrium_loop):
    """The loop of the ``offset_equilibrium_loop`` fixture: g₀(0) ≈ −2.4·10⁻⁷ against a
    decay of 10⁻⁹·x₀, so V = ‖x‖² does not decrease at (−0.5, 0). Expanding the MX loop to
    SX folds g₀(0) to exactly 0; the test reads the graph as given (intervals of
    C·tanh(b) − u_eq) and proves nothing."""
    s, kappa = offset_equilibrium_loop
    cl = closed_loop(s, kappa, strict=True)
    t = TaylorDecrease(cl.x, cl.rhs, quadratic_form(quadratic_lyapunov(np.eye(2))))
    assert t.why == ""
    for inner in (0.0, 0.1, 0.5):
        assert t.check(1.0, np.array([[-2.0, 2.0]] * 2), inner) is None


def test_a_singular_quadratic_is_refused_with_a_reason():
    """A 'quadratic' V = (x₁ + x₂)² (P = [[1, 1], [1, 1]], singular): no test, no crash."""
    x = ca.SX.sym("x", 2)
    t = TaylorDecrease(x, -x, [[Fraction(1), Fraction(1)], [Fraction(1), Fraction(1)]])
    assert "not positive definite" in t.why
    assert t.check(0.5, np.array([[-1.0, 1.0]] * 2), 0.1) is None


def test_the_jacobian_form_without_a_controller_split_holds_where_sampling_agrees():
    """``contracts`` on a smooth loop without a saturated controller (the Jacobian enclosed
    entrywise on the set's box): ``PJ(y) + J(y)ᵀP ≺ 0`` proved on a small ellipse, refused on
    one large enough for the sampled largest eigenvalue to turn positive, and every proof
    agrees with sampling; ``λ`` beyond the margin is refused."""
    x = ca.SX.sym("x", 2)
    g = ca.vertcat(x[1], -x[0] - x[1] + x[0] ** 3 / 3)      # reversed Van der Pol, damped
    A = np.array([[0.0, 1.0], [-1.0, -1.0]])
    P = solve_continuous_lyapunov(A.T, -np.eye(2))
    Pq = quadratic_form(quadratic_lyapunov(P))
    t = TaylorDecrease(x, g, Pq)
    J = ca.Function("J", [x], [ca.jacobian(g, x)])
    whole = np.array([[-np.inf, np.inf]] * 2)
    rng = np.random.default_rng(3)
    verdicts = {}
    for level in (1e-4, 0.05, 3.0):
        w, U = np.linalg.eigh(P)                  # points of {xᵀPx ≤ level}
        z = rng.normal(size=(3000, 2))
        z *= (rng.random((3000, 1)) ** 0.5) / np.linalg.norm(z, axis=1, keepdims=True)
        pts = (z * np.sqrt(level / w)) @ U.T
        worst = max(np.linalg.eigvalsh(P @ np.array(J(y)) + np.array(J(y)).T @ P)[-1]
                    for y in pts)
        verdicts[level] = t.contracts(level, whole, 0.0)
        if verdicts[level]:
            assert worst < 0, level
        if level == 3.0:
            assert worst > 0                        # the refusal is right there
    assert verdicts[1e-4] and not verdicts[3.0]
    # S(0) = -I: the margin λ = 0.9 holds on a tiny set, λ = 1.1 nowhere
    assert t.contracts(1e-8, whole, 0.9) and not t.contracts(1e-8, whole, 1.1)


def test_partial_and_non_smooth_operations_are_used_where_a_checked_walk_clears_them():
    """A loop with a division and a kink: the whole-set test applies on a box where a
    checked interval walk proves the denominator away from 0 and the kink away from the box
    (sampling agrees), and returns ``None`` where the box reaches the kink."""
    x = ca.SX.sym("x", 2)
    g = ca.vertcat(x[1], -x[0] / (2 + ca.sin(x[0])) - x[1] + 0.1 * (ca.fabs(x[0] + 3) - 3))
    A = np.array([[0.0, 1.0], [-0.5 + 0.1, -1.0]])
    P = solve_continuous_lyapunov(A.T, -np.eye(2))
    V_net = quadratic_lyapunov(P)
    V, Pq = V_net.casadi(x), quadratic_form(V_net)
    t = TaylorDecrease(x, g, Pq)
    assert t.why == "" and t._checked is not None       # the graph has checked operations
    whole = np.array([[-np.inf, np.inf]] * 2)
    Pinv = np.linalg.inv(P)
    small = 0.01 / Pinv[0, 0]                             # |x0| ≤ 0.1 on {V ≤ small}
    big = 16.0 / Pinv[0, 0]                               # |x0| reaches 4: the kink at -3
    res = t.check(small, whole, 0.0)
    assert res is not None and res.status.value == "verified"
    box = np.sqrt(small * np.diag(Pinv))[:, None] * np.array([-1.0, 1.0])
    assert _sampled_max(x, V, _lie(V, x, g), small, box, np.random.default_rng(0)) < 0
    assert t.check(big, whole, 0.0) is None
    assert t.contracts(small / 4, whole, 0.0) in (True, False)   # decided without an error
    assert not t.contracts(big, whole, 0.0)


def test_condition_c_decides_the_whole_set_test_once_and_builds_a_form_only_when_needed(
        monkeypatch):
    """Condition (c) (:func:`certify_inner_ellipse`): the whole-set Jacobian test does not
    depend on the form, so it runs once however many forms are tried; where it proves
    ``S ≺ 0`` on ``E`` no form's interval problem is built (its graphs cost a re-check's
    client about 0.02 s on the cartpole, outside every task); where it does not, each form
    goes to its own check, as before."""
    import systems
    from nlyap_opt.certification import roa
    from nlyap_opt.distributed import parallel
    from verification.problem import VerificationProblem

    P = np.array([[1.5, -0.5], [-0.5, 1.0]])
    s = systems.get("van_der_pol")
    calls, built, checked = [], [], []
    monkeypatch.setattr(roa, "VerificationProblem", lambda *a, **k: built.append(a[4:6])
                        or VerificationProblem(*a, **k))
    real_check = parallel.check
    monkeypatch.setattr(parallel, "check", lambda prob, **k: checked.append(
        list(prob.property_names)) or real_check(prob, **k))

    real = TaylorDecrease.contracts
    monkeypatch.setattr(TaylorDecrease, "contracts", lambda self, *a: calls.append(a)
                        or real(self, *a))
    out = roa.certify_inner_ellipse(s, None, 0.3)
    assert out["status"] == "certified" and out["result"].backend == "taylor"
    assert out["form"] == "minors" and len(calls) == 1 and built == [] and checked == []

    # the test fails: every form (minors, then Frobenius) has its own check; the whole-set
    # test ran once for both
    calls.clear()
    monkeypatch.setattr(TaylorDecrease, "contracts", lambda self, *a: calls.append(a) or False)
    monkeypatch.setattr(parallel, "check", lambda prob, **k: checked.append(
        list(prob.property_names)) or roa.VerificationResult(roa.QueryStatus.UNKNOWN))
    out = roa.certify_inner_ellipse(s, None, 0.3, P=P, form="frobenius")
    assert len(calls) == 1 and checked == [["frobenius1"]] and out["status"] != "certified"
    checked.clear()
    calls.clear()
    roa.certify_inner_ellipse(s, None, 0.3, P=P)
    # E's test once (minors and Frobenius); then the shell form's small ellipse has its own
    assert len(calls) >= 1 and [c[0] for c in calls].count(calls[0][0]) == 1
    assert [c[0][:-1] for c in checked[:2]] == ["minors", "frobenius"]
