"""A candidate whose certificate cannot beat the best certified volume is not verified: the
volume bound bounds every certificate it stands for, and skipping changes only what is
attempted (the same candidate levels, no claim without a verification)."""

import numpy as np
import pytest

import systems
from nlyap_opt.candidates.cegis import CegisConfig, cegis
from nlyap_opt.candidates.learning import TrainConfig
from nlyap_opt.certification.certificate import (
    NOT_CHECKED,
    LevelPolicy,
    RoaProblem,
    VolumeToBeat,
    certify_candidate,
)
from nlyap_opt.certification.roa import (
    certify_inner_ellipse,
    grid_points,
    inner_ellipse_bound,
)
from nlyap_opt.design.control import lyapunov_matrix, quadratic_lyapunov

BOX = np.array([[-2.5, 2.5], [-2.5, 2.5]])
N = 61


@pytest.fixture(scope="module")
def vdp():
    s = systems.get("van_der_pol")
    P = lyapunov_matrix(np.asarray(s.A, dtype=float))
    return s, RoaProblem(s, quadratic_lyapunov(P), None, None, inner=0.1, outer=2.0)


def test_the_ellipse_bound_holds_the_proved_inner_ellipse(vdp):
    s, _ = vdp
    pts, _ = grid_points(BOX, N)
    for eps in (0.1, 0.4):
        res = certify_inner_ellipse(s, None, eps)
        assert res["verdict"].value == "certified"
        P, c = np.asarray(res["P"]), float(res["level"])
        inside = np.einsum("ij,jk,ik->i", pts, P, pts) <= c
        assert inside.sum() > 0
        mask = inner_ellipse_bound(s, None, eps, pts)
        assert mask is not None and np.all(mask[inside])


def test_the_volume_bound_bounds_the_certified_volume(vdp):
    s, problem = vdp
    cert = certify_candidate(problem, LevelPolicy(1.0, (1.0,)), log=lambda m: None)
    assert cert.certified
    vol = cert.area(BOX, N)
    b = VolumeToBeat(0.0, BOX, N, "nothing").bound(problem, cert.level)
    assert vol <= b
    # the bound grows with the level and stays below the whole domain's grid volume
    assert b <= VolumeToBeat(0.0, BOX, N, "x").bound(problem, 10 * cert.level) <= 25.0


def test_radii_that_cannot_beat_are_skipped_and_the_rest_is_unchanged(vdp):
    s, problem = vdp
    policy = LevelPolicy(1.0, (1.0, 2.0))
    quiet = {"log": lambda m: None}
    plain = certify_candidate(problem, policy, **quiet)
    low = certify_candidate(problem, policy, beat=VolumeToBeat(0.0, BOX, N, "zero"), **quiet)
    assert plain.certified and low.certified and low.level == plain.level
    high = certify_candidate(problem, policy, beat=VolumeToBeat(1e3, BOX, N, "quadratic x"),
                             **quiet)
    assert not high.certified and "can beat the quadratic x" in high.reason
    # said as what it is: not verified because it could not win, nothing found false
    assert high.reason.startswith(NOT_CHECKED + ": at each inner radius tried (ε = 0.1, 0.2)")
    tried = high.history[-1]["inner_radius_search"]
    assert [t["status"] for t in tried] == ["skipped", "skipped"]
    assert [t["inner"] for t in tried] == [0.1, 0.2]


def test_only_radii_skipped_for_the_volume_are_called_unchecked():
    """A candidate is 'not checked' only when every radius was skipped because it could not
    win; a radius refuted by counterexamples (or without a level) keeps the plain reason."""
    from nlyap_opt.certification import certificate

    beat = VolumeToBeat(5.0, BOX, N, "quadratic x")
    lost = {"inner": 0.1, "status": "skipped",
            "reason": "cannot beat the quadratic x: volume bound 4 below its certified 5"}
    refuted = {"inner": 0.2, "status": "skipped",
               "reason": "counterexamples refute every level above 0.3"}
    empty = {"inner": 0.4, "status": "no positive candidate level"}
    why = certificate._unchecked_reason([lost, {**lost, "inner": 0.05}], beat)
    assert why == (NOT_CHECKED + ": at each inner radius tried (ε = 0.1, 0.05) no certificate "
                   "of it can beat the quadratic x (at ε = 0.1: volume bound 4 below its "
                   "certified 5)")
    for tried in ([lost, refuted], [lost, empty], [refuted]):
        why = certificate._unchecked_reason(tried, beat)
        assert why.startswith("no inner radius left to check: ε = "), why
    assert certificate._unchecked_reason([lost], None).startswith("no inner radius left")
    # the one predicate the report and the log read it by
    assert certificate.unchecked("not certified", certificate._unchecked_reason([lost], beat))
    assert not certificate.unchecked("not certified", certificate._unchecked_reason(
        [lost, refuted], beat))
    assert not certificate.unchecked("certified", NOT_CHECKED + ": stale")
    assert not certificate.unchecked("not certified", None)


def test_cegis_does_not_verify_an_iterate_that_cannot_beat():
    s = systems.get("van_der_pol")
    train = TrainConfig(hidden=[8], features=3, steps=100, lr=0.02, w_local=10.0,
                        level_slack=0.5, relative_decrease=True)
    cfg = CegisConfig(inner=0.3, outer=1.5, iterations=2, steps=30, samples=1000,
                      sphere_samples=200, train=train, area_points=6400)
    box = np.array([[-1.5, 1.5], [-1.5, 1.5]])
    skipped = cegis(s, None, None, cfg, log=lambda m: None,
                    beat=VolumeToBeat(1e3, box, 41, "quadratic x"))
    assert not skipped.certified and skipped.level == 0.0
    for h in skipped.history:
        assert h["boxes"] == 0 and h["status"] == "not certified"
        assert h["skipped"].startswith("cannot beat the quadratic x"), h
        assert h["reason"].startswith("not verified (cannot beat"), h
    # without the bound the same first iterate (same training, same candidate level) is
    # verified
    plain = cegis(s, None, None, CegisConfig(**{**cfg.__dict__, "iterations": 1}),
                  log=lambda m: None)
    assert plain.history[0]["candidate_level"] == skipped.history[0]["candidate_level"]
    assert plain.history[0]["boxes"] > 0 and plain.history[0]["skipped"] == ""


def test_the_bound_applies_to_learned_dynamics_where_c_is_proved_on_the_model(vdp):
    """With learned dynamics of a system that has a model, condition (c) is proved on the
    true closed loop, so the bound is the true f's (it reads no φ); without a model (c)
    comes from the samples or is assumed, and there is no bound."""
    import dataclasses
    import math

    s, problem = vdp
    phi = quadratic_lyapunov(np.eye(2))        # any network: the bound does not read φ
    phi.meta = {}                              # (not one saved as a V)
    learned = dataclasses.replace(problem, dynamics=phi, eta=0.01, dynamics_box=BOX)
    assert not learned.known and s.has_model
    beat = VolumeToBeat(0.0, BOX, N, "x")
    assert beat.bound(learned, 1.0) == beat.bound(problem, 1.0) < math.inf

    class NoModel:                              # the system as a sample file would give it
        has_model = False

        def __getattr__(self, name):
            return getattr(s, name)

    sampled = dataclasses.replace(learned, system=NoModel())
    assert beat.bound(sampled, 1.0) == math.inf


def test_a_radius_below_the_inner_balls_level_is_skipped_before_the_bound(vdp):
    """A radius whose candidate level holds no inner ball is skipped at once: the volume
    bound (which may compute condition (c) at that radius) is not asked for it."""
    s, problem = vdp

    class NoBound(VolumeToBeat):
        def bound(self, problem, level):
            raise AssertionError(f"bound asked at ε = {problem.inner}")

    policy = LevelPolicy(1.0, (15.0,), smallest_level=True, whole_sets=True)
    cert = certify_candidate(problem, policy, beat=NoBound(1e3, BOX, N, "x"),
                             log=lambda m: None)
    assert not cert.certified
    assert "ε = 1.5: candidate level" in cert.reason and "inner ball's level" in cert.reason


def test_the_inner_ellipse_bound_is_computed_once_per_closed_loop(vdp, monkeypatch):
    """``cannot_beat`` then ``least_level`` on the same problem (a CEGIS iterate) reuse one
    :func:`inner_ellipse_bound`; another radius computes its own, with the same answers as a
    fresh ``VolumeToBeat``."""
    from dataclasses import replace

    import nlyap_opt.certification.certificate as certificate
    s, problem = vdp
    calls = []
    real = certificate.inner_ellipse_bound
    monkeypatch.setattr(certificate, "inner_ellipse_bound",
                        lambda *a, **k: calls.append(a[2]) or real(*a, **k))
    beat = VolumeToBeat(1.0, BOX, N, "x")
    why = beat.cannot_beat(problem, 0.5)
    least = beat.least_level(problem)
    assert len(calls) == 1
    other = replace(problem, inner=problem.inner / 2)
    assert beat.least_level(other) == VolumeToBeat(1.0, BOX, N, "x").least_level(other)
    assert len(calls) == 3
    assert (why, least) == (VolumeToBeat(1.0, BOX, N, "x").cannot_beat(problem, 0.5),
                            VolumeToBeat(1.0, BOX, N, "x").least_level(problem))
