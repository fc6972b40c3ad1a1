"""Tests of nlyap_opt.learned.lipschitz: LipSDP bounds are rigorous, tight-ish and re-certified."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import minimize

from nlyap_opt.kernel.errors import DimensionError
from nlyap_opt.learned.lipschitz import (
    LipschitzResult,
    _build_lmi,
    _certify,
    _lambda_max_upper,
    _recertify,
    _rho_estimate,
    _solve_sdp,
    lipschitz_lipsdp,
    lipschitz_naive,
    lipschitz_sampled,
)

REL = 1e-9  # float slack when comparing a computed lower bound with a rigorous upper bound


def _net(rng, n, h, m, w0_scale=1.5, b0_scale=1.0):
    """Random net with weight scales like a trained one (W1 ~ 1/sqrt(h))."""
    W0 = rng.normal(size=(h, n)) * w0_scale
    b0 = rng.normal(size=h) * b0_scale
    W1 = rng.normal(size=(m, h)) / math.sqrt(h)
    return W0, b0, W1


def _jac_norm(W0, b0, W1, z, dsig=lambda s: 1.0 - np.tanh(s) ** 2):
    J = (W1 * dsig(W0 @ z + b0)) @ W0
    return float(np.linalg.norm(J, 2))


def _sampled_lower(rng, W0, b0, W1, n_points=20_000, box=3.0, refine=5, activation="tanh"):
    """Sampled Jacobian norm plus Nelder-Mead refinement of the best points (a lower bound)."""
    n = W0.shape[1]
    pts = rng.uniform(-box, box, size=(n_points, n))
    best = lipschitz_sampled(W0, b0, W1, pts, activation=activation)
    if refine:
        dsig = {
            "tanh": lambda s: 1.0 - np.tanh(s) ** 2,
            "sigmoid": lambda s: (e := 1.0 / (1.0 + np.exp(-s))) * (1.0 - e),
        }.get(activation, activation)
        d = dsig(pts @ W0.T + b0)
        J = np.einsum("oh,bh,hi->boi", W1, d, W0)
        norms = np.linalg.norm(J, 2, axis=(1, 2))
        for k in np.argsort(norms)[-refine:]:
            res = minimize(
                lambda z: -_jac_norm(W0, b0, W1, z, dsig),
                pts[k],
                method="Nelder-Mead",
                options={"maxiter": 400, "xatol": 1e-8, "fatol": 1e-12},
            )
            best = max(best, -float(res.fun))
    return best


# --------------------------------------------------------------------------- LipSDP bounds


@pytest.mark.parametrize(
    "seed, shape, w0_scale",
    [(0, (2, 16, 2), 1.0), (1, (3, 50, 2), 1.5), (2, (3, 50, 2), 3.0), (3, (3, 200, 2), 2.0)],
)
def test_sampled_le_lipsdp_le_naive(seed, shape, w0_scale):
    rng = np.random.default_rng(seed)
    W0, b0, W1 = _net(rng, *shape, w0_scale=w0_scale)
    res = lipschitz_lipsdp(W0, b0, W1)
    low = _sampled_lower(rng, W0, b0, W1)
    naive = lipschitz_naive(W0, W1)
    print(
        f"\n{shape} scale={w0_scale}: LipSDP {res.value:.6f} (sdp {res.sdp_value:.6f}), "
        f"naive {naive:.6f}, sampled {low:.6f}, {res.seconds:.2f} s, {res.note}"
    )
    assert isinstance(res, LipschitzResult)
    assert res.certified, res.note
    assert res.naive == naive
    assert low <= res.value * (1 + REL)
    assert res.value <= naive
    assert res.value < 0.9 * naive  # LipSDP beats the product bound on these nets
    # the certified value is close to the solver's value (re-certification costs little)
    assert res.value <= res.sdp_value * (1 + 1e-5)


def test_one_neuron_exact():
    # phi(z) = 2 tanh(z): L = 2 exactly; LipSDP is tight (t = 4, rho = 4)
    res = lipschitz_lipsdp([[1.0]], [0.0], [[2.0]])
    assert res.value >= 2.0
    assert res.value <= 2.0 * (1 + 1e-6)
    assert abs(res.sdp_value - 2.0) <= 1e-6
    # the naive bound is exact here too, rounded up by at most a few ulps
    assert 2.0 <= lipschitz_naive([[1.0]], [[2.0]]) <= 2.0 * (1 + 1e-14)


def test_linear_slope_exact():
    # slope (1, 1) makes the activation the identity: phi(z) = W1 W0 z, L = ||W1 W0||_2
    rng = np.random.default_rng(3)
    W0 = rng.normal(size=(6, 3))
    W1 = rng.normal(size=(2, 6))
    exact = np.linalg.norm(W1 @ W0, 2)
    res = lipschitz_lipsdp(W0, None, W1, slope=(1.0, 1.0))
    assert res.certified, res.note
    # the LMI is exact only in the limit t -> inf, so allow a small gap
    assert exact * (1 - 1e-12) <= res.value <= exact * (1 + 1e-3)
    assert res.value < res.naive


def test_sigmoid_slope():
    rng = np.random.default_rng(4)
    W0, b0, W1 = _net(rng, 2, 30, 2, w0_scale=3.0)
    res = lipschitz_lipsdp(W0, b0, W1, slope=(0.0, 0.25))
    low = _sampled_lower(rng, W0, b0, W1, n_points=5000, box=4.0, activation="sigmoid")
    assert res.certified, res.note
    assert low <= res.value * (1 + REL)
    assert res.value <= lipschitz_naive(W0, W1, slope=(0.0, 0.25))
    assert res.naive == lipschitz_naive(W0, W1, slope=(0.0, 0.25))


def test_general_slope_nonzero_lower():
    # sigma(s) = 0.1 s + 0.9 tanh(s) is slope-restricted in [0.1, 1] (a*b != 0 branch)
    rng = np.random.default_rng(5)
    W0, b0, W1 = _net(rng, 3, 40, 2)

    def dsig(s):
        return 0.1 + 0.9 * (1.0 - np.tanh(s) ** 2)

    res = lipschitz_lipsdp(W0, b0, W1, slope=(0.1, 1.0))
    low = _sampled_lower(rng, W0, b0, W1, n_points=5000, activation=dsig)
    assert res.certified, res.note
    assert low <= res.value * (1 + REL)
    assert res.value <= res.naive


def test_scs_solver():
    rng = np.random.default_rng(6)
    W0, b0, W1 = _net(rng, 2, 16, 2)
    res = lipschitz_lipsdp(W0, b0, W1, solver="SCS")
    ref = lipschitz_lipsdp(W0, b0, W1)
    assert res.solver == "SCS"
    assert res.certified, res.note
    assert res.value <= res.naive
    assert res.value >= _sampled_lower(rng, W0, b0, W1, refine=0) * (1 - REL)
    assert abs(res.value - ref.value) <= 1e-3 * ref.value


def test_solver_failure_falls_back_to_naive():
    rng = np.random.default_rng(7)
    W0, b0, W1 = _net(rng, 2, 8, 2)
    res = lipschitz_lipsdp(W0, b0, W1, solver="NO_SUCH_SOLVER")
    assert not res.certified
    assert res.solver == "none"
    assert res.value == res.naive == lipschitz_naive(W0, W1)
    assert math.isnan(res.sdp_value)
    assert "naive" in res.note


def test_inactive_neurons_and_constant_net():
    rng = np.random.default_rng(8)
    W0, b0, W1 = _net(rng, 2, 10, 2)
    W1[:, 3] = 0.0  # output ignores neuron 3
    W0[5] = 0.0  # neuron 5 is constant
    res = lipschitz_lipsdp(W0, b0, W1)
    assert res.certified
    assert "pruned" in res.note
    keep = [i for i in range(10) if i not in (3, 5)]
    ref = lipschitz_lipsdp(W0[keep], b0[keep], W1[:, keep])
    assert abs(res.value - ref.value) <= 1e-6 * ref.value
    zero = lipschitz_lipsdp(W0, b0, np.zeros_like(W1))
    assert zero.value == 0.0 and zero.certified


def test_bad_input():
    with pytest.raises(DimensionError):
        lipschitz_lipsdp(np.ones((4, 2)), np.zeros(4), np.ones((2, 3)))
    with pytest.raises(DimensionError):
        lipschitz_lipsdp(np.ones((4, 2)), np.zeros(3), np.ones((2, 4)))
    with pytest.raises(ValueError):
        lipschitz_lipsdp(np.full((4, 2), np.nan), np.zeros(4), np.ones((2, 4)))
    with pytest.raises(ValueError):
        lipschitz_lipsdp(np.ones((4, 2)), np.zeros(4), np.ones((2, 4)), slope=(1.0, 0.0))
    with pytest.raises(DimensionError):
        lipschitz_sampled(np.ones((4, 2)), np.zeros(4), np.ones((2, 4)), np.ones((5, 3)))


def test_sampled_matches_single_point_jacobian():
    rng = np.random.default_rng(9)
    W0, b0, W1 = _net(rng, 3, 20, 2)
    pts = rng.normal(size=(50, 3))
    ref = max(_jac_norm(W0, b0, W1, z) for z in pts)
    assert lipschitz_sampled(W0, b0, W1, pts, batch_size=7) == pytest.approx(ref, rel=1e-12)
    assert lipschitz_sampled(W0, b0, W1, pts[0]) == pytest.approx(
        _jac_norm(W0, b0, W1, pts[0]), rel=1e-12
    )


# --------------------------------------------------------------------------- re-certification


def _solved(rng, n=3, h=50, m=2):
    W0, b0, W1 = _net(rng, n, h, m)
    s0, s1 = np.linalg.norm(W0, 2), np.linalg.norm(W1, 2)
    tn, rn = _solve_sdp(W0 / s0, W1 / s1, 0.0, 1.0, "CLARABEL", False)
    return W0, b0, W1, tn * s1**2, rn * (s0 * s1) ** 2


def test_recertify_raises_too_small_rho():
    rng = np.random.default_rng(10)
    W0, b0, W1, t, rho = _solved(rng)
    low = _sampled_lower(rng, W0, b0, W1, refine=2)
    for use_estimate in (False, True):
        rc = _recertify(W0, W1, t, 0.5 * rho, use_estimate=use_estimate)
        assert rc.rho is not None, rc.note
        # the certified rho is at least the (float) optimum for the multipliers it used
        assert rc.rho >= _rho_estimate(W0, W1, rc.t, 0.0, 1.0) * (1 - 1e-9)
        assert rc.rho >= 0.5 * rho * (1 + 1e-3)  # it really had to go up
        assert rc.value >= low * (1 - REL)
        assert rc.value**2 >= rc.rho


def test_recertify_corrupted_multipliers_never_unsound():
    rng = np.random.default_rng(11)
    W0, b0, W1, t, rho = _solved(rng)
    low = _sampled_lower(rng, W0, b0, W1, refine=2)
    corruptions = [
        t * 0.3,  # too small: lower-right block indefinite
        t * rng.uniform(0.0, 2.0, size=t.shape),  # noisy
        -t,  # negative (clipped to 0, then floored)
        np.where(rng.random(t.shape) < 0.2, 0.0, t),  # some multipliers zeroed
        t * 1.5,  # feasible but suboptimal
        t * rng.uniform(0.97, 1.03, size=t.shape),  # slightly noisy
    ]
    n_cert = 0
    for tc in corruptions:
        for r in (0.5 * rho, rho, 2 * rho):
            rc = _recertify(W0, W1, tc, r, max_tries=30)
            assert rc.tries <= 30
            if rc.rho is not None:
                n_cert += 1
                assert np.all(rc.t >= 0)
                assert rc.value >= low * (1 - REL)
                assert rc.rho >= _rho_estimate(W0, W1, rc.t, 0.0, 1.0) * (1 - 1e-9)
    assert n_cert >= 6  # the repairs (scaling t, flooring t) do find certificates
    # without the repairs, multipliers with 2T - W1^T W1 indefinite admit no rho at all
    tc = 0.3 * t
    floor = 0.5 * np.sum(W1 * W1, axis=0) * (1 + 1e-9)
    negD = 2 * np.diag(np.maximum(tc, floor)) - W1.T @ W1
    assert np.linalg.eigvalsh(negD)[0] < -1e-6
    rc = _recertify(W0, W1, tc, 100 * rho, use_estimate=False)
    assert rc.rho is None and rc.tries == 29


def test_failed_recertification_returns_naive(monkeypatch):
    import nlyap_opt.learned.lipschitz as lip

    rng = np.random.default_rng(17)
    W0, b0, W1 = _net(rng, 2, 12, 2)
    monkeypatch.setattr(lip, "_recertify", lambda *a, **k: lip._Recert(None, None, 30, "forced"))
    res = lipschitz_lipsdp(W0, b0, W1)
    assert not res.certified
    assert res.value == res.naive == lipschitz_naive(W0, W1)
    assert "re-certification failed" in res.note
    assert res.sdp_value < res.naive


def test_certify_rejects_infeasible_rho():
    rng = np.random.default_rng(12)
    W0, b0, W1, t, rho = _solved(rng)
    t = np.maximum(t, 0.0)
    r_min = _rho_estimate(W0, W1, t, 0.0, 1.0)
    assert math.isfinite(r_min)
    for f in (0.999, 1 - 1e-6):
        assert not _certify(W0, W1, t, r_min * f, 0.0, 1.0)
    assert _certify(W0, W1, t, r_min * (1 + 1e-6), 0.0, 1.0)
    assert not _certify(W0, W1, -t, r_min * 2, 0.0, 1.0)  # negative multipliers


def test_lambda_max_upper_against_mpmath():
    mpmath = pytest.importorskip("mpmath")
    rng = np.random.default_rng(13)
    mpmath.mp.dps = 60
    for trial in range(6):
        n = 6
        Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
        lam = -rng.uniform(0.1, 10.0, size=n)
        lam[0] = [-1e-13, 1e-13, -1e-15, 0.0, -1e-9, 1e-10][trial]  # near-singular
        M = (Q * lam) @ Q.T
        M = np.triu(M) + np.triu(M, 1).T  # exactly symmetric float matrix = exact data
        exact = max(mpmath.eigsy(mpmath.matrix(M.tolist()), eigvals_only=True))
        ub = _lambda_max_upper(M, np.zeros_like(M))
        assert ub >= float(exact)
        assert ub <= float(exact) + 1e-12 * 10.0
        # an entrywise perturbation bound is honoured
        Epert = np.full_like(M, 1e-8)
        assert _lambda_max_upper(M, Epert) >= float(exact) + 1e-8 * 0.99


def test_build_lmi_error_bound_against_mpmath():
    mpmath = pytest.importorskip("mpmath")
    mpmath.mp.dps = 50
    rng = np.random.default_rng(14)
    W0, W1 = rng.normal(size=(5, 2)), rng.normal(size=(2, 5))
    t = rng.uniform(0.5, 3.0, size=5)
    a, b, rho = 0.1, 0.9, 7.3
    Mt, E = _build_lmi(W0, W1, t, rho, a, b)
    mp = mpmath.mpf
    A0 = mpmath.matrix(W0.tolist())
    A1 = mpmath.matrix(W1.tolist())
    T = mpmath.diag([mp(x) for x in t])
    B11 = -mp(rho) * mpmath.eye(2) - 2 * mp(a) * mp(b) * A0.T * T * A0
    B21 = (mp(a) + mp(b)) * T * A0
    B22 = -2 * T + A1.T * A1
    for i in range(7):
        for j in range(7):
            if i < 2 and j < 2:
                ex = B11[i, j]
            elif i >= 2 and j < 2:
                ex = B21[i - 2, j]
            elif i < 2:
                ex = B21[j - 2, i]
            else:
                ex = B22[i - 2, j - 2]
            assert abs(ex - mp(Mt[i, j])) <= mp(E[i, j])


def test_naive_is_upper_bound_against_mpmath():
    mpmath = pytest.importorskip("mpmath")
    mpmath.mp.dps = 50
    rng = np.random.default_rng(15)
    W0, W1 = rng.normal(size=(7, 3)), rng.normal(size=(2, 7))

    def norm2(W):
        A = mpmath.matrix(W.tolist())
        return mpmath.sqrt(max(mpmath.eigsy(A.T * A, eigvals_only=True)))

    exact = norm2(W0) * norm2(W1)
    naive = lipschitz_naive(W0, W1)
    assert mpmath.mpf(naive) >= exact
    assert naive <= float(exact) * (1 + 1e-12)


def test_3_200_2_bounds_sandwich_the_jacobian_norms():
    """A trained-size 3-200-2 net: every sampled ‖J_φ(z)‖₂ ≤ K_φ ≤ ‖W1‖₂‖W0‖₂ (timing: bench)."""
    rng = np.random.default_rng(16)
    W0, b0, W1 = _net(rng, 3, 200, 2)
    res = lipschitz_lipsdp(W0, b0, W1)
    assert res.certified
    # Jacobian norms at random points and at Nelder–Mead-refined maximisers, computed here
    # independently of the module (J = W1 diag(tanh'(W0 z + b0)) W0)
    pts = rng.uniform(-3.0, 3.0, size=(2000, 3))
    norms = [_jac_norm(W0, b0, W1, z) for z in pts]
    low = max(max(norms), _sampled_lower(rng, W0, b0, W1, n_points=5000, refine=3))
    product = float(np.linalg.norm(W1, 2) * np.linalg.norm(W0, 2))
    assert low <= res.value * (1 + REL)
    assert res.value <= res.naive <= product * (1 + 1e-12)
    # LipSDP is informative: strictly below the product of the norms for this net
    assert res.value < 0.99 * product
