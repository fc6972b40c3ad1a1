"""The quadratic stage skips a candidate that cannot win: its volume bound really bounds what
it certifies, a skipped candidate's bound is at most the winner's volume, and the winner is
the one found without skipping. Condition (c) is computed once per radius and shared."""

from dataclasses import replace

import numpy as np
import pytest
from scipy.linalg import solve_continuous_lyapunov

import systems
from nlyap_opt.candidates import quadratic
from nlyap_opt.candidates.quadratic import (
    certify_quadratics,
    closed_loop_matrix,
    quadratic_policy,
    volume_bound,
)
from nlyap_opt.certification.certificate import (
    NOT_CHECKED,
    InnerEllipseCache,
    LevelPolicy,
    RoaProblem,
)
from nlyap_opt.design.control import lqr, lyapunov_matrix, quadratic_lyapunov, saturated_controller
from nlyap_opt.kernel.domain import Ball, as_domain
from nlyap_opt.workflow.configs import get_config


def _pendulum(controller_scale=20.0):
    s = systems.get("inverted_pendulum")
    cfg = get_config("inverted_pendulum", "fast")
    res = lqr(s, cfg["lqr"]["Q"], cfg["lqr"]["R"])
    ctrl = saturated_controller(s, res.K, controller_scale)
    problem = RoaProblem(s, quadratic_lyapunov(np.eye(2)), ctrl, None, inner=0.4, outer=4.0)
    return problem, np.asarray(cfg["eval_box"], dtype=float)


def _wide(A_cl, known=True, domain=None):
    """The Lyapunov matrix of ``A_clᵀP + PA_cl = −diag(1, 30)``: on the pendulum its
    certified set is about three times that of the ``"lyapunov"`` candidate."""
    return solve_continuous_lyapunov(A_cl.T, -np.diag([1.0, 30.0]))


def test_the_boundary_level_bounds_the_least_v_on_the_boundary_from_above():
    rng = np.random.default_rng(3)
    box = {"type": "box", "box": [[-1.0, 2.0], [-0.5, 0.5], [-3.0, 1.0]]}
    for D in (Ball(2.0, 3), as_domain(box, 3)):
        A = rng.standard_normal((3, 3))
        P = A @ A.T + 0.1 * np.eye(3)
        c = quadratic._boundary_level(P, D)
        # never below the true minimum on ∂D, and close to the least of dense samples of ∂D
        assert c >= _min_on_boundary_from_below(P, D) * (1 - 1e-9)
        b = D.sample_boundary(200000, rng)
        assert c <= float(np.einsum("ij,jk,ik->i", b, P, b).min()) * 1.05


def _min_on_boundary_from_below(P, D):
    """A lower bound of ``min xᵀPx`` on ``∂D``: ``λ_min r²`` on the ball (exact); on a box the
    least minimum over the hyperplanes of its faces."""
    if isinstance(D, Ball):
        return float(np.linalg.eigvalsh(P)[0]) * D.radius**2
    box = D.bounding_box()
    best = np.inf
    for i in range(len(box)):
        for b in box[i]:
            keep = [j for j in range(len(box)) if j != i]
            Pkk = P[np.ix_(keep, keep)]
            Pki = P[keep, i]
            plane = b * b * (P[i, i] - Pki @ np.linalg.solve(Pkk, Pki))
            best = min(best, plane)
    return best


def test_a_candidate_that_cannot_win_is_skipped_and_the_winner_is_unchanged(monkeypatch):
    problem, box = _pendulum()
    monkeypatch.setitem(quadratic.QUADRATIC_CANDIDATES, "wide", _wide)
    names = ["lyapunov", "wide"]
    full = certify_quadratics(problem, names, box=box, n=101, prune=False, log=lambda m: None)
    pruned = certify_quadratics(problem, names, box=box, n=101, prune=True, log=lambda m: None)
    assert [c.name for c in full] == [c.name for c in pruned] == names
    assert all(c.certified for c in full)
    assert full[0].volume < full[1].volume
    # the bound bounds: each candidate's certified volume is at most its volume bound
    policy = quadratic_policy(True)
    for c in full:
        b = volume_bound(problem, c.P, policy, box=box, n=101, ellipses=InnerEllipseCache())
        assert c.volume <= b
    # "wide" goes first (the larger estimate); "lyapunov" is skipped: its bound is below the
    # winner's certified volume, and the winner is the one found without skipping
    lyap, wide = pruned
    assert lyap.skipped and not lyap.certified and lyap.volume == 0.0
    assert full[0].volume <= lyap.bound < wide.volume
    assert wide.certified and wide.volume == full[1].volume
    assert wide.certificate.level == full[1].certificate.level
    rec = lyap.to_json()
    assert rec["status"] == "skipped" and rec["volume_bound"] == lyap.bound
    assert "cannot beat quadratic wide" in rec["reason"]


def test_a_tie_keeps_the_earlier_name(monkeypatch):
    """The same matrix twice: the second one's bound equals the first one's volume (the
    level reaches the domain), and the earlier name wins a tie, so it is skipped."""
    problem, box = _pendulum()
    monkeypatch.setitem(quadratic.QUADRATIC_CANDIDATES, "again",
                        quadratic.QUADRATIC_CANDIDATES["lyapunov"])
    first, again = certify_quadratics(problem, ["lyapunov", "again"], box=box, n=101,
                                      prune=True, log=lambda m: None)
    assert first.certified and again.skipped
    assert again.bound >= first.volume


def test_the_level_bound_follows_the_policy():
    """With ``smallest_level`` the level is at most ``(1 + margin)·λ_max ε²``; a radius whose
    ball needs a level above the boundary's is dropped."""
    problem, box = _pendulum()
    P = lyapunov_matrix(closed_loop_matrix(problem))
    lam_min, lam_max = np.linalg.eigvalsh(P)[[0, -1]]
    smallest = LevelPolicy(1.0, (1.0, 2.0, 100.0), smallest_level=True)
    levels = quadratic._radius_levels(problem, P, smallest)
    edge = lam_min * 16.0       # the least V on ‖x‖ = 4
    assert [e for e, _ in levels] == [e for e in (0.4, 0.8) if lam_max * e * e < edge]
    for eps, c in levels:
        assert c == pytest.approx(min(edge, 1.02 * lam_max * eps * eps), rel=1e-6)
    plain = quadratic._radius_levels(problem, P, LevelPolicy(1.0, (1.0,)))
    assert plain == [] or plain[0][1] == pytest.approx(edge, rel=1e-6)


def test_the_ellipse_cache_serves_one_closed_loop_only():
    problem, _ = _pendulum()
    cache = InnerEllipseCache()
    first = cache.get(problem)
    assert cache.get(problem) is first                         # computed once
    other, _ = _pendulum(controller_scale=10.0)
    with pytest.raises(ValueError, match="one closed loop"):
        cache.get(other)


def _learned_toy():
    """A 2-D loop with learned dynamics: φ its linearisation, η = 0.01 (the policy with the
    smallest level at ε, 2ε, 3ε), condition (c) checked on the true f."""
    import casadi as ca

    from nlyap_opt.kernel.network import Layer, Network

    A = np.array([[-1.0, 3.0], [0.0, -2.0]])
    x = ca.SX.sym("x", 2)
    f = ca.mtimes(ca.DM(A), x) + ca.vertcat(0.5 * x[0] ** 2 * x[1], -0.5 * x[0] ** 3)
    s = systems.System("learned_toy", x, None, f, state_box=[[-2, 2], [-2, 2]])
    phi = Network([Layer(A.copy(), np.zeros(2), "linear")],
                  meta={"kind": "dynamics", "model": "full"})
    problem = RoaProblem(s, quadratic_lyapunov(np.eye(2)), None, phi, inner=0.1, outer=1.5,
                         eta=0.01, dynamics_box=[[-2, 2], [-2, 2]])
    return problem, np.array([[-1.5, 1.5], [-1.5, 1.5]])


@pytest.mark.slow  # a learned-dynamics loop, six radii (about 3 s)
def test_learned_dynamics_prune_by_default_and_the_bound_bounds_every_radius():
    problem, box = _learned_toy()
    names = ["lyapunov", "round", "volume"]
    full = certify_quadratics(problem, names, box=box, n=61, prune=False, log=lambda m: None)
    pruned = certify_quadratics(problem, names, box=box, n=61, log=lambda m: None)
    assert [c.name for c in pruned] == names
    assert all(c.certified for c in full)
    # two states: each level is searched down from the candidate level (the bound then
    # counts the set at the level of ∂D); the bound covers every radius's level and ellipse
    policy = quadratic_policy(False, nx=problem.system.nx)
    assert not policy.smallest_level and policy.inner_fraction == 1.0
    for c in full:
        b = volume_bound(problem, c.P, policy, box=box, n=61, ellipses=InnerEllipseCache())
        assert c.volume <= b
    # the same winner, at the same level and volume, with or without skipping
    win = max(full, key=lambda c: c.volume)
    same = [c for c in pruned if c.name == win.name][0]
    assert same.certified and same.volume == win.volume
    assert same.certificate.level == win.certificate.level
    assert max(c.volume for c in pruned) == win.volume


def test_few_states_with_learned_dynamics_try_the_true_f_decay_rate_first(monkeypatch):
    """Learned dynamics in 2 states: the "volume" candidate is the true f's matrix (decay
    rate VOLUME_DECAY_FRACTION); where it certifies nothing, the learned-dynamics rate's
    matrix is verified and kept."""
    problem, box = _learned_toy()
    A = quadratic.closed_loop_matrix(problem)
    P_known = quadratic.QUADRATIC_CANDIDATES["volume"](A, True, problem.domain)
    P_learned = quadratic.QUADRATIC_CANDIDATES["volume"](A, False, problem.domain)
    assert not np.allclose(P_known, P_learned)
    found = certify_quadratics(problem, ["volume"], box=box, n=31, log=lambda m: None)[0]
    assert found.certified and np.array_equal(found.P, P_known)
    real = quadratic.certify_candidate

    def refuse_known(prob, policy, **kw):       # as if the true f's rate were refuted
        cert = real(prob, policy, **kw)
        P = quadratic.quadratic_form(prob.V)
        if np.allclose(np.array(P, dtype=float), P_known):
            cert.status = type(cert.status)("not certified")
        return cert
    monkeypatch.setattr(quadratic, "certify_candidate", refuse_known)
    logs = []
    again = certify_quadratics(problem, ["volume"], box=box, n=31, log=logs.append)[0]
    assert again.certified and np.array_equal(again.P, P_learned)
    assert any("the learned-dynamics rate" in m for m in logs)


def test_a_radius_whose_own_level_cannot_win_is_not_checked(monkeypatch):
    """Once a candidate is certified, the next one is also skipped radius by radius where
    the level it would check cannot beat it (here with the stage's own bound made useless),
    and the winner is the one found without skipping."""
    problem, box = _pendulum()
    monkeypatch.setitem(quadratic.QUADRATIC_CANDIDATES, "wide", _wide)
    names = ["wide", "lyapunov"]
    full = certify_quadratics(problem, names, box=box, n=101, prune=False, log=lambda m: None)
    monkeypatch.setattr(quadratic, "volume_bound", lambda *a, **k: np.inf)
    pruned = certify_quadratics(problem, names, box=box, n=101, prune=True, log=lambda m: None)
    wide, lyap = pruned
    assert wide.certified and wide.volume == full[0].volume > full[1].volume
    assert not lyap.skipped and not lyap.certified
    assert lyap.certificate.reason.startswith(NOT_CHECKED)      # nothing was found false
    assert "no certificate of it can beat the quadratic wide" in lyap.certificate.reason
    tried = lyap.certificate.history[-1]["inner_radius_search"]
    assert tried and all(t["status"] == "skipped" for t in tried)
    assert all(t["reason"].startswith("cannot beat the quadratic wide") for t in tried)


def _wide_problem():
    problem, box = _pendulum()
    P = _wide(closed_loop_matrix(problem))
    return RoaProblem(problem.system, quadratic_lyapunov(P), problem.controller, None,
                      inner=0.4, outer=4.0), box


def test_no_level_below_the_least_level_can_beat_and_the_next_grid_point_can():
    """``VolumeToBeat.least_level``: the bound is below the volume at the returned level (so
    at every lower one, the bound being monotone in the level), and reaches it one or two
    grid points higher: the floor is tight, not merely safe."""
    from nlyap_opt.certification.certificate import VolumeToBeat
    from nlyap_opt.certification.roa import grid_points

    problem, box = _wide_problem()
    pts, _ = grid_points(box, 61)
    v = np.sort(problem.V_numpy(pts[problem.domain.contains(pts)]))
    for volume in (10.0, 20.0, 40.0):     # (c)'s ellipse alone: 6.3; the disc: 50.4
        beat = VolumeToBeat(volume, box, 61, "test", ellipses=InnerEllipseCache())
        least = beat.least_level(problem)
        assert 0 < least < np.inf
        assert beat.bound(problem, least) < volume
        above = v[np.searchsorted(v, least * (1 + 1e-9), side="right") + 2]
        assert beat.bound(problem, above) >= volume
    assert VolumeToBeat(1e-9, box, 61, "test", ellipses=InnerEllipseCache()
                        ).least_level(problem) == 0.0
    assert VolumeToBeat(1e9, box, 61, "test", ellipses=InnerEllipseCache()
                        ).least_level(problem) == np.inf


def test_a_level_search_stops_above_the_least_level_that_can_beat():
    """A search that would step below ``least`` ends there with the reason, having checked
    no level below it; without ``least`` the same search goes on down and certifies."""
    from nlyap_opt.certification.certificate import certify_roa

    problem, _ = _wide_problem()
    free = certify_roa(problem, 200.0, search=True, log=lambda m: None)
    assert free.certified and free.level < 200.0
    tried = [h["level"] for h in free.history if "level" in h]
    floor = 0.5 * (tried[0] + free.level)       # above the certified level
    logs = []
    stopped = certify_roa(problem, 200.0, search=True, least=(floor, "quadratic test"),
                          log=logs.append)
    assert not stopped.certified
    assert "could beat the quadratic test" in stopped.reason
    assert all(h["level"] >= floor for h in stopped.history if "level" in h)
    assert any("the search ends" in m for m in logs)


def test_a_radius_whose_search_ends_at_the_least_level_ends_the_radius_search(monkeypatch):
    """When no level that could beat the certificate to beat holds at the first radius, the
    other radii are not tried (as when a level that cannot win is certified there); without
    a certificate to beat, the same candidate goes through every radius."""
    from types import SimpleNamespace

    from nlyap_opt.certification import certificate as cert_mod
    from nlyap_opt.certification.certificate import VolumeToBeat, certify_candidate

    problem, box = _pendulum()
    problem = RoaProblem(problem.system, quadratic_lyapunov(np.eye(2)), problem.controller,
                         None, inner=0.4, outer=4.0)     # V = |x|²: no level certifies
    monkeypatch.setattr(cert_mod, "candidate_level",
                        lambda *a, **k: SimpleNamespace(level=15.0))
    policy = quadratic_policy(True)
    cache = InnerEllipseCache()
    free = certify_candidate(problem, policy, ellipses=cache, log=lambda m: None)
    assert not free.certified
    assert len(free.history[-1]["inner_radius_search"]) == len(policy.factors)
    beat = VolumeToBeat(20.0, box, 61, "quadratic test", cache)
    least = beat.least_level(replace(problem, inner=problem.inner * policy.inner_fraction))
    assert 0 < least < 15.0
    logs = []
    cut = certify_candidate(problem, policy, ellipses=cache, beat=beat, log=logs.append)
    tried = cut.history[-1]["inner_radius_search"]
    assert not cut.certified and len(tried) == 1
    assert "could beat the quadratic test" in tried[0]["reason"]
    assert any("the other radii are not tried" in m for m in logs)
