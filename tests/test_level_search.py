"""The level search never goes below the inner ball's level.

On ``x' = −x(1 − ‖x‖²)`` (region of attraction: the open unit ball) with ``V = ‖x‖²`` and
ε = 0.95, no level at or below ``max_{‖x‖=ε} V = 0.9025`` can hold ``B_ε ⊆ Ω_c``. When large
levels end "unknown" (a spent box budget, simulated here by the first verdicts), the
search's 30 % step lands below that: it must try ``1.02 · 0.9025`` instead, where (a), (b)
and (c) hold, and stop when that fails too.

With ``follow_violations`` the search climbs back from its first proved level by bisection:
on ``V = ‖x‖²``, ``V̇ = 2V(V − T)`` with a band of "unknown" verdicts below ``T``, it ends
within a few percent of the largest level the verifier proves, never above it.
"""

import casadi as ca
import numpy as np
import pytest

import nlyap_opt.certification.roa as roa
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


# ------------------------------------------------------------ the climb after a followed violation
T = 0.25        # V̇ = 2V(V − T) < 0 exactly for V < T: the largest certifiable level


def _shell():
    """``V = ‖x‖²`` under ``f = x(‖x‖² − T)``."""
    x = ca.MX.sym("x", 2)
    V = ca.sumsqr(x)
    return x, V, 2 * V * (V - T)


def _unknown_band(monkeypatch, low: float, high: float):
    """The decrease check at a level in ``(low, high]`` ends "unknown" (a verifier that cannot
    separate those levels from the violation at ``V = T``); every other check is the real
    verifier's. Returns the levels of the decrease checks, in order."""
    real_check, real_problem = par.check, roa.lyapunov_problem
    levels, asked = {}, []   # id -> (the problem, kept alive so that no id is reused; level)

    def problem(*a, level=None, **kw):
        p = real_problem(*a, level=level, **kw)
        levels[id(p)] = (p, level)
        return p

    def check(p, **kw):
        kept = levels.get(id(p))
        c = kept[1] if kept is not None and kept[0] is p else None
        if c is not None:
            asked.append(c)
            if low < c <= high:
                return VerificationResult("unknown", boxes=1)
        return real_check(p, **kw)

    monkeypatch.setattr(roa, "lyapunov_problem", problem)
    monkeypatch.setattr(par, "check", check)
    return asked


@pytest.mark.parametrize("band", [0.03, 0.1, 0.25])
def test_the_search_climbs_back_to_within_a_few_percent_of_the_verifiable_level(monkeypatch,
                                                                               band):
    """Above ``T`` the decrease is refuted (real counterexamples, followed down to ``T`` by
    IPOPT); in ``((1 − band)·T, T]`` the verifier says "unknown"; below, it proves the level.
    The search must end on a proved level, at most ``(1 − band)·T`` and within 3 % of it, in
    at most ``max_tries`` tries, each recorded; the tries after the first proved level climb
    (bisection), and every try above the certified level failed."""
    x, V, lie = _shell()
    top = (1 - band) * T                       # the largest level the verifier proves
    asked = _unknown_band(monkeypatch, top, T)
    lc = roa.certify_level(x, V, lie, level=0.8, inner=0.05, outer=1.0, margin=0.0,
                           max_tries=8, log=lambda m: None, follow_violations=True)
    assert lc.status == "certified", lc.history
    assert 0.97 * top <= lc.level <= top < T
    h = lc.history
    assert 3 <= len(h) <= 8 and [e["level"] for e in h] == asked   # every try recorded
    assert h[0]["decrease"] == "counterexample"
    ok = [e["level"] for e in h if e.get("contains_inner_ball") == "verified"]
    assert ok and max(ok) == lc.level
    assert all(e["decrease"] in ("unknown", "counterexample") for e in h
               if e["level"] > lc.level)
    first = next(i for i, e in enumerate(h) if e.get("contains_inner_ball") == "verified")
    assert len(h) > first + 1                                  # bisection tries were made
    assert all(h[first]["level"] < e["level"] < h[first - 1]["level"] for e in h[first + 1:])
    # the mathematics: V̇ < 0 on the certified annulus
    r2 = np.linspace(0.05**2, lc.level, 1000)
    assert np.all(2 * r2 * (r2 - T) < 0)


def test_without_following_the_search_only_steps_down(monkeypatch):
    """The climb is part of ``follow_violations``: without it the search returns the first
    level it proves, every try below the one before (counterexamples creep down to ``T``,
    then the small steps of the "unknown" schedule). In the same band the search that
    follows and climbs ends higher, in fewer tries."""
    x, V, lie = _shell()
    _unknown_band(monkeypatch, 0.9 * T, T)
    kw = dict(level=0.26, inner=0.05, outer=1.0, margin=0.0, log=lambda m: None)
    lc = roa.certify_level(x, V, lie, max_tries=10, **kw)
    h = lc.history
    assert lc.status == "certified" and lc.level <= 0.9 * T, h
    assert h[-1]["level"] == lc.level and h[-1]["contains_inner_ball"] == "verified"
    assert all(a["level"] > b["level"] for a, b in zip(h, h[1:]))   # only downwards
    assert all(e.get("contains_inner_ball") != "verified" for e in h[:-1])
    climb = roa.certify_level(x, V, lie, max_tries=8, follow_violations=True, **kw)
    assert climb.status == "certified" and lc.level < climb.level <= 0.9 * T
    assert len(climb.history) < len(h)


def test_a_failed_bisection_try_never_replaces_the_proved_level(monkeypatch):
    """On the ring (decrease fails at ``V = 1``) with decrease checks above 0.7 "unknown" the
    search proves a first level ``L`` and climbs; when every check above ``L`` is "unknown",
    the certificate is ``L`` itself, with ``L``'s checks (verified), though every later try
    recorded (the bisection) is "unknown"."""
    s = _ring()
    p = RoaProblem(s, quadratic_lyapunov(np.eye(2)), inner=0.1, outer=2.0)
    with monkeypatch.context() as m:
        _unknown_band(m, 0.7, 1.0)
        cert = certify_roa(p, 1.5, search=True, follow_violations=True, log=lambda m: None)
    assert cert.certified and 0.6 < cert.level <= 0.7, cert.reason
    proved = [h["level"] for h in cert.history if h.get("contains_inner_ball") == "verified"]
    first = proved[0]
    _unknown_band(monkeypatch, first * (1 + 1e-12), 1.0)
    again = certify_roa(p, 1.5, search=True, follow_violations=True, log=lambda m: None)
    assert again.certified and again.level == first < cert.level
    after = again.history[[h["level"] for h in again.history].index(first) + 1:]
    assert after and all(h["decrease"] == "unknown" and h["level"] > first for h in after)
    assert len(after) >= 2                              # the tries were spent climbing
    assert again.checks["(a) decrease"] == again.checks["(b) B_ε ⊆ Ω_c"] == "verified"
    assert again.checks["(b) V > level on ‖x‖ = r"] == "verified"


def test_a_starting_level_below_v_on_the_inner_sphere_is_not_checked(monkeypatch):
    """Ring, ``V = ‖x‖²``, ε = 0.95: V = 0.9025 on the whole inner sphere, so a search that
    starts at 0.8 (or any level up to 0.9025) can never hold B_ε. Nothing is handed to the
    verifier, and the reason says why; a start above it is searched as before."""
    s = _ring()
    p = RoaProblem(s, quadratic_lyapunov(np.eye(2)), inner=EPS, outer=2.0)
    real, calls = par.check, []
    monkeypatch.setattr(par, "check", lambda prob, **kw: calls.append(1) or real(prob, **kw))
    logs = []
    cert = certify_roa(p, 0.8, search=True, log=logs.append)
    assert not cert.certified and not calls and not cert.history
    assert "none was checked" in cert.reason and "0.9025" in cert.reason
    assert any("cannot hold the inner ball" in line for line in logs)
    assert certify_roa(p, 0.95, search=True, log=lambda m: None).certified and calls
