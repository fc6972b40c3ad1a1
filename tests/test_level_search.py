"""The level search never goes below the inner ball's level.

On ``x' = −x(1 − ‖x‖²)`` (region of attraction: the open unit ball) with ``V = ‖x‖²`` and
ε = 0.95, no level at or below ``max_{‖x‖=ε} V = 0.9025`` can hold ``B_ε ⊆ Ω_c``. When large
levels end "unknown" (a spent box budget, simulated here by the first verdicts), the
search's 30 % step lands below that: it must try ``1.02 · 0.9025`` instead, where (a), (b)
and (c) hold, and stop when that fails too.
"""

import casadi as ca
import numpy as np
import pytest

import nlyap_opt.distributed.parallel as par
import systems
from nlyap_opt.certification.certificate import RoaProblem, certify_roa
from nlyap_opt.certification.roa import INNER_LEVEL_MARGIN, inner_ball_level
from nlyap_opt.design.control import quadratic_lyapunov
from verification import VerificationResult

EPS = 0.95


def _ring():
    x = ca.SX.sym("x", 2)
    return systems.System("ring", x, None, -x * (1 - ca.sumsqr(x)), state_box=[[-3.0, 3.0]] * 2)


def _undecided_first(monkeypatch, k: int, always: bool = False):
    """The first ``k`` decrease checks (all of them with ``always``) end "unknown"."""
    real, calls = par.check, []

    def check(problem, **kw):
        if list(problem.property_names) == ["decrease"] and (always or len(calls) < k):
            calls.append(problem.property_names)
            return VerificationResult("unknown", boxes=1)
        return real(problem, **kw)

    monkeypatch.setattr(par, "check", check)
    return calls


def test_inner_ball_level_is_the_maximum_on_the_sphere():
    x = ca.SX.sym("x", 3)
    P = np.array([[2.0, 0.5, 0.0], [0.5, 1.0, 0.2], [0.0, 0.2, 3.0]])
    m = inner_ball_level(x, ca.bilin(ca.DM(P), x, x), 0.3)
    assert m == pytest.approx(np.linalg.eigvalsh(P)[-1] * 0.09, rel=1e-9)
    assert m <= np.linalg.eigvalsh(P)[-1] * 0.09 * (1 + 1e-12)   # values of V on the sphere


def test_search_tries_the_inner_balls_level_instead_of_going_below_it(monkeypatch):
    s = _ring()
    p = RoaProblem(s, quadratic_lyapunov(np.eye(2)), inner=EPS, outer=2.0)
    calls = _undecided_first(monkeypatch, 5)
    logs = []
    cert = certify_roa(p, 1.5, search=True, log=logs.append)
    assert len(calls) == 5
    levels = [h["level"] for h in cert.history]
    m = EPS**2
    assert all(c > m for c in levels), levels                 # never at or below it
    assert cert.certified, cert.reason
    assert cert.level == pytest.approx(m * (1 + INNER_LEVEL_MARGIN), rel=1e-9)
    assert any("would not hold the inner ball" in line for line in logs)
    # the truth: V̇ < 0 on Ω_c minus B_ε, and Ω_c inside the unit ball
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, (20000, 2))
    r2 = np.sum(pts**2, axis=1)
    pts, r2 = pts[(r2 >= EPS**2) & (r2 <= cert.level)], r2[(r2 >= EPS**2) & (r2 <= cert.level)]
    assert len(pts) and np.all(-2 * r2 * (1 - r2) < 0)


def test_search_stops_when_the_inner_balls_level_fails_too(monkeypatch):
    s = _ring()
    p = RoaProblem(s, quadratic_lyapunov(np.eye(2)), inner=EPS, outer=2.0)
    _undecided_first(monkeypatch, 0, always=True)
    cert = certify_roa(p, 1.5, search=True, log=lambda m: None)
    assert not cert.certified
    assert "none above the inner ball's level" in cert.reason
    levels = [h["level"] for h in cert.history]
    assert len(levels) < 8 and levels[-1] == pytest.approx(EPS**2 * (1 + INNER_LEVEL_MARGIN))


def test_smallest_level_start_and_radii_below_their_inner_ball_are_skipped():
    """``f = x(‖x‖² − 1/4)``, ``V = ‖x‖²``: V̇ < 0 exactly for ‖x‖ < 1/2 (candidate level
    1/4). At ε = 0.6 every Ω_c ⊇ B_ε holds violations: the radius is skipped, not searched;
    at ε = 0.3 exactly 1.02·0.09 is checked, the smallest level holding B_0.3."""
    from nlyap_opt.certification.certificate import certify_with_inner_search

    x = ca.SX.sym("x", 2)
    s = systems.System("shell", x, None, x * (ca.sumsqr(x) - 0.25), state_box=[[-3.0, 3.0]] * 2)
    p = RoaProblem(s, quadratic_lyapunov(np.eye(2)), inner=0.6, outer=2.0)
    cert = certify_with_inner_search(p, None, smallest_level=True, log=lambda m: None)
    tried = cert.history[-1]["inner_radius_search"]
    assert tried[0]["inner"] == 0.6 and "below the inner ball's level" in tried[0]["status"]
    assert cert.certified and cert.inner == pytest.approx(0.3)
    assert cert.level == pytest.approx(0.09 * (1 + INNER_LEVEL_MARGIN), rel=1e-9)
    assert cert.level < 0.25                                 # below the violations


def test_every_radius_skipped_is_a_refusal_not_an_error():
    """The learned-f cartpole's LQR matrix: every radius skipped (its candidate level lies
    below each inner ball's); the run must go on to the next candidate, not stop with an
    input error. Same situation here with the radii 0.6 and 1.2."""
    from nlyap_opt.certification.certificate import certify_with_inner_search

    x = ca.SX.sym("x", 2)
    s = systems.System("shell", x, None, x * (ca.sumsqr(x) - 0.25), state_box=[[-3.0, 3.0]] * 2)
    p = RoaProblem(s, quadratic_lyapunov(np.eye(2)), inner=0.6, outer=2.0)
    cert = certify_with_inner_search(p, None, factors=(1.0, 2.0), smallest_level=True,
                                     log=lambda m: None)
    assert not cert.certified and cert.status.value == "not certified"
    assert "ε = 0.6" in cert.reason and "below the inner ball's level" in cert.reason
    assert cert.history[-1]["inner_radius_search"][0]["inner"] == 0.6
