"""CEGIS with ``best_iterate``: the verifier proves the most promising iterate of its window,
training resumes from the best certified iterate, and no certified area is ever lost."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from certcheck import assert_reverifies

import systems
from nlyap_opt.candidates import cegis as cegis_module
from nlyap_opt.candidates.cegis import RESUME_BELOW, RESUME_LR, CegisConfig, cegis
from nlyap_opt.candidates.learning import LyapunovLearner, TrainConfig


def _train_config() -> TrainConfig:
    return TrainConfig(hidden=[8], features=3, steps=300, lr=0.02, w_fit=10.0, w_pde=1.0,
                       w_local=10.0, relative_decrease=True, level_slack=0.5, decay=0.05,
                       lr_schedule="cosine")


def _small_config(**kw) -> CegisConfig:
    """A small, fast CEGIS on Van der Pol (inner 0.3, outer 1.5) with ``kw`` on top."""
    return CegisConfig(inner=0.3, outer=1.5, steps=100, samples=3000, sphere_samples=500,
                       inner_samples=300, boundary_samples=1000, sim_dt=0.05,
                       train=_train_config(), area_points=6400, **kw)


def test_learner_state_resumes_training_exactly():
    """Training k steps after load_state(s) gives the same weights as training k steps
    right after s was taken (weights, gain and Adam's moments are all restored)."""
    s = systems.get("van_der_pol")
    learner = LyapunovLearner(s, None, None, _train_config())
    rng = np.random.default_rng(0)
    X, S = rng.uniform(-1.5, 1.5, (500, 2)), rng.uniform(-1.5, 1.5, (100, 2))
    learner.train(X, S, 0.0, steps=20)
    saved = learner.state()
    learner.train(X, S, 0.0, steps=20)
    first = learner.export()[0].numpy(X)
    learner.train(X, S, 0.0, steps=20)          # move away, then come back
    learner.load_state(saved)
    learner.train(X, S, 0.0, steps=20)
    assert np.array_equal(learner.export()[0].numpy(X), first)
    # the saved state is a copy: training after it did not change it
    learner.load_state(saved)
    again = learner.state()
    assert all(torch.equal(a, b) for a, b in zip(saved.V.values(), again.V.values()))


def test_later_rounds_train_at_their_own_learning_rate():
    """``lr`` of a train call replaces train.lr for that call only (0: Adam moves nothing);
    CEGIS's rounds after the first get train.lr · cegis.later_lr."""
    from types import SimpleNamespace

    from nlyap_opt.candidates.cegis import _train_round

    s = systems.get("van_der_pol")
    learner = LyapunovLearner(s, None, None, _train_config())
    rng = np.random.default_rng(0)
    X, S = rng.uniform(-1.5, 1.5, (500, 2)), rng.uniform(-1.5, 1.5, (100, 2))
    before = learner.export()[0].numpy(X)
    learner.train(X, S, 0.0, steps=20, lr=0.0)
    assert np.array_equal(learner.export()[0].numpy(X), before)
    learner.train(X, S, 0.0, steps=20)                 # the configured lr moves V
    assert not np.array_equal(learner.export()[0].numpy(X), before)
    seen = []
    fake = SimpleNamespace(config=SimpleNamespace(lr=0.02),
                           train=lambda *a, **k: seen.append((k["steps"], k["lr"])))
    cfg = CegisConfig(inner=0.1, outer=1.0, steps=7, later_lr=0.25, first_steps=9,
                      train=TrainConfig(w_inward=0.0))
    for it in range(3):
        _train_round(fake, cfg, it, 0.0, 0.0, X, S, np.zeros((0, 2)), None, None, None)
    _train_round(fake, cfg, 3, 0.0, 0.0, X, S, np.zeros((0, 2)), None, None, None,
                 lr_scale=RESUME_LR ** 2)                # after two resumptions
    assert seen == [(9, 0.02), (7, 0.005), (7, 0.005), (7, 0.005 * RESUME_LR ** 2)]


def test_a_budget_that_ends_on_a_growing_certificate_is_extended():
    """cegis.extend: verify_every more iterations at a time, up to iterations + extend, only
    while the last verifier call gained more than plateau (the loop asks only then)."""
    from nlyap_opt.candidates.cegis import _extended

    said = []
    cfg = CegisConfig(inner=0.1, outer=1.0, iterations=8, extend=3, verify_every=3)
    assert _extended(8, cfg, 1.8, 1.4, said.append) == (11, False)
    assert "3 more iteration(s), 11 in all" in said[-1]
    assert _extended(11, cfg, 1.9, 1.8, said.append) == (11, True) and len(said) == 1
    assert _extended(8, CegisConfig(inner=0.1, outer=1.0, iterations=8, extend=4,
                                    verify_every=3), 2.0, 1.0, said.append) == (11, False)
    assert _extended(11, CegisConfig(inner=0.1, outer=1.0, iterations=8, extend=4,
                                     verify_every=3), 2.0, 1.0, said.append) == (12, False)
    assert _extended(5, CegisConfig(inner=0.1, outer=1.0, iterations=5), 2.0, 1.0,
                     said.append) == (5, True)                    # extend 0: as before


@pytest.mark.slow
def test_best_iterate_never_loses_area_and_resumes_after_a_bad_round(monkeypatch):
    """A training round that wrecks V (iteration 3, weights perturbed after training) does
    not lose the certified area: its candidate set collapses below the best certified area,
    so after the verifier call training resumes from the best certified iterate; each
    verifier call proves the iterate with the largest candidate set of its window; a
    certified area never exceeds its iterate's candidate set; the returned V re-verifies at
    the returned level."""
    calls = []
    train = LyapunovLearner.train

    rates = []

    def wrecking_train(self, *args, **kwargs):
        info = train(self, *args, **kwargs)
        calls.append(len(calls))
        rates.append(kwargs["lr"])
        if len(calls) == 4:        # iteration 3, the last of the second window
            gen = torch.Generator().manual_seed(0)
            with torch.no_grad():
                for p in self.V.parameters():
                    p.add_(2.0 * torch.randn(p.shape, generator=gen, dtype=p.dtype))
        return info

    monkeypatch.setattr(LyapunovLearner, "train", wrecking_train)
    s = systems.get("van_der_pol")
    cfg = _small_config(iterations=6, min_iterations=6, verify_every=2, best_iterate=True)
    res = cegis(s, None, None, cfg, log=lambda m: None)
    h = res.history
    assert len(h) == 6 and res.certified
    # windows {0, 1}, {2, 3}, {4, 5}: exactly one verified iterate each, the one with the
    # largest candidate set (the latest among equals)
    for window in (h[0:2], h[2:4], h[4:6]):
        verified = [e for e in window if e["boxes"] > 0]
        assert len(verified) == 1
        top = max(e["candidate_area"] for e in window)
        assert verified[0]["candidate_area"] == top
        assert all(e["candidate_area"] < top for e in window
                   if e["iteration"] > verified[0]["iteration"])
    # the wrecked iterate, after the verifier call of its window, hands training back to
    # the best certified one; the next iterate trains on from there
    best_before = max(range(4), key=lambda i: h[i]["area"])
    assert h[3]["candidate_area"] < RESUME_BELOW * h[best_before]["area"]
    assert h[3]["resumed_from"] == best_before
    assert h[4]["candidate_area"] > h[3]["candidate_area"]
    # the rounds after a resumption train at RESUME_LR times the rate (once per resumption)
    lr, n = _train_config().lr, [sum("resumed_from" in e for e in h[:i]) for i in range(6)]
    assert rates == [lr * RESUME_LR ** k for k in n] and n[4] >= 1
    # bookkeeping: resumed only after a verifier call, where the candidate set collapsed
    # below RESUME_BELOW of the best certified area
    best = 0.0
    for e in h:
        assert e["area"] <= e["candidate_area"]
        best = max(best, e["area"])
        if "resumed_from" in e:
            assert (e["iteration"] + 1) % cfg.verify_every == 0
            assert e["candidate_area"] < RESUME_BELOW * best
            assert best == h[e["resumed_from"]]["area"]
        elif (e["iteration"] + 1) % cfg.verify_every == 0 and e["iteration"] < 5:
            assert e["candidate_area"] >= RESUME_BELOW * best
    assert res.area == best == max(e["area"] for e in h) > 0
    assert_reverifies(s, res.V, res.level, inner=0.3, outer=1.5, half=1.5)


def test_candidate_area_is_the_grid_area_of_the_sublevel_set_in_the_domain():
    """D ∩ {V ≤ c} for V = ‖x‖² on a box: the disc of radius √c, cut by the box."""
    from nlyap_opt.certification.roa import grid_points
    from nlyap_opt.kernel.domain import Box
    from nlyap_opt.kernel.network import Layer, Network

    V = Network([Layer(np.eye(2), np.zeros(2), "linear")], 1.0,
                head={"type": "sum_of_squares", "eps": 0.0})
    D = Box([[-1.0, 1.0], [-0.5, 0.5]])
    box = D.bounding_box()
    grid, shape = grid_points(box, 401)
    in_d = D.contains(grid)
    # the disc of radius 0.4 lies in D; the unit disc is cut by |x2| <= 0.5
    assert abs(cegis_module.candidate_area(V, 0.16, grid, in_d, shape, box)
               - np.pi * 0.16) < 0.02
    cut = 2 * (0.5 * np.sqrt(0.75) + np.arcsin(0.5))      # ∫_{-1/2}^{1/2} 2√(1−t²) dt
    assert abs(cegis_module.candidate_area(V, 1.0, grid, in_d, shape, box) - cut) < 0.02
    assert cegis_module.candidate_area(V, 0.0, grid, in_d, shape, box) == 0.0


@pytest.mark.slow
def test_cegis_runs_the_extended_iterations():
    """With plateau −1 every certified last call counts as growing: iterations 2 + extend 2
    run 4 iterations (the budget grows by verify_every = 1 twice), each verified."""
    s = systems.get("van_der_pol")
    said = []
    cfg = _small_config(iterations=2, extend=2, verify_every=1, plateau=-1.0)
    res = cegis(s, None, None, cfg, log=said.append)
    assert res.certified and [e["iteration"] for e in res.history] == [0, 1, 2, 3]
    assert sum("more iteration(s)" in m for m in said) == 2
    assert all(e["boxes"] > 0 for e in res.history)
    # verify_every 2, 3 iterations: the verifier at 1 and 2 (the first budget's last); the
    # extension's window {3, 4} is verified once, at 4, not at 3 as a count from 0 would
    said.clear()
    res = cegis(s, None, None, replace(cfg, iterations=3, verify_every=2),
                log=said.append)
    verified = [e["iteration"] for e in res.history if e["boxes"] > 0]
    assert len(res.history) == 5 and verified == [1, 2, 4], verified


def test_a_last_iteration_without_a_certificate_still_verifies_its_window(monkeypatch):
    """When the budget's last iterate cannot be checked (its controller leaves the input
    box: InputRangeError), the iterates since the last verifier call are verified after the
    loop instead of being dropped: verify_every 5 and 3 iterations put no verifier call
    before the last, so without that the run would certify nothing."""
    from nlyap_opt.certification.certificate import RoaProblem
    from nlyap_opt.kernel.errors import InputRangeError

    exported, bad = [], set()
    export = LyapunovLearner.export
    decrease = RoaProblem.decrease

    def tracked_export(self):
        V, ctrl = export(self)
        exported.append(V)
        if len(exported) == 3:  # iteration 2, the last
            bad.add(id(V))
        return V, ctrl

    def failing_decrease(self, *args, **kwargs):
        if id(self.V) in bad:
            raise InputRangeError("κ leaves the input box (planted)")
        return decrease(self, *args, **kwargs)

    monkeypatch.setattr(LyapunovLearner, "export", tracked_export)
    monkeypatch.setattr(RoaProblem, "decrease", failing_decrease)
    s = systems.get("van_der_pol")
    cfg = _small_config(iterations=3, verify_every=5, best_iterate=True)
    said = []
    res = cegis(s, None, None, cfg, log=said.append)
    h = res.history
    assert [e["iteration"] for e in h] == [0, 1, 2] and "planted" in h[2]["status"]
    verified = [e for e in h if e.get("boxes", 0) > 0]
    assert len(verified) == 1 and verified[0]["iteration"] in (0, 1)
    assert verified[0]["candidate_area"] == max(e["candidate_area"] for e in h[:2])
    assert res.certified and res.area == verified[0]["area"] > 0
    assert any("is verified now" in m for m in said)
    assert_reverifies(s, res.V, res.level, inner=0.3, outer=1.5, half=1.5)


def test_a_window_whose_first_choice_falls_short_verifies_the_runner_up(monkeypatch):
    """The window's most promising iterate (largest candidate set) is refuted by the
    verifier (planted: its search starts far below its candidate level, below the inner
    ball): the next most promising one, whose candidate set can still beat the best, is
    verified too and wins; both entries record their own verification."""
    from nlyap_opt.certification.certificate import CertStatus

    real = cegis_module.certify_roa
    add = cegis_module._add_counterexamples
    calls, fed = [], []
    planted = np.array([[0.77, -0.77]])

    def first_refuted(problem, level, **kwargs):
        calls.append(level)
        cert = real(problem, level, **kwargs)
        if len(calls) == 1:  # a violation the samples missed, planted
            cert = replace(cert, status=CertStatus.NOT_CERTIFIED, reason="planted",
                           level=0.0, counterexamples=planted)
        return cert

    def spy(cex, new, cfg, scale, rng, extra=None):
        fed.append(np.vstack([np.reshape(new, (-1, 2))] +
                             ([] if extra is None else [np.reshape(extra, (-1, 2))])))
        return add(cex, new, cfg, scale, rng, extra)

    monkeypatch.setattr(cegis_module, "certify_roa", first_refuted)
    monkeypatch.setattr(cegis_module, "_add_counterexamples", spy)
    s = systems.get("van_der_pol")
    cfg = _small_config(iterations=3, min_iterations=3, verify_every=3, best_iterate=True)
    said = []
    res = cegis(s, None, None, cfg, log=said.append)
    h = res.history
    verified = [e for e in h if e.get("boxes", 0) > 0 or "verify_seconds" in e
                and e["reason"] != "not verified (candidate only)"]
    assert len(calls) == 2 and len(verified) == 2, (calls, h)
    first, second = sorted(verified, key=lambda e: -e["candidate_area"])
    assert first["status"] == "not certified" and first["area"] == 0.0
    assert second["status"] == "certified" and res.area == second["area"] > 0
    assert any("is verified too" in m for m in said)
    # the loser's real counterexample is fed back to training with the winner's
    assert any((f == planted).all(axis=1).any() for f in fed)
    assert_reverifies(s, res.V, res.level, inner=0.3, outer=1.5, half=1.5)


def test_a_window_whose_runner_up_gains_nothing_keeps_its_first_choice(monkeypatch):
    """With fake verifications: when neither the first choice nor the runner-up certifies
    more than the best so far, the window's result is the first choice (as without the
    rule: the stop rule and the counterexamples fed back do not change), the runner-up's
    entry records its own verification, and its counterexamples are kept for training; a
    runner-up that beats the best wins; in more than 3 states no runner-up is tried."""
    from types import SimpleNamespace as NS

    from nlyap_opt.certification.certificate import CertStatus

    def fake_cert(it, area):
        return NS(status=CertStatus.CERTIFIED if area else CertStatus.NOT_CERTIFIED,
                  certified=bool(area), reason="fake", level=1.0 if area else 0.0,
                  seconds=0.1, checks={}, history=[{"boxes": 7}],
                  counterexamples=np.full((1, 2), float(it)), area=lambda box, n: area or 0.0)

    def iterate(it, cand_area, certifies, nx=2):
        x = cegis_module._Iterate(
            V=None, ctrl=None, problem=NS(system=NS(nx=nx)), cand=NS(level=1.0),
            entry={"iteration": it, "skipped": "", "candidate_area": cand_area, "loss": 0.0,
                   "candidate_level": 1.0, "candidate_source": "decrease"},
            margins=(0.0, 1.0, 0.0), state=None)
        x.problem.plan = (it, certifies)
        return x

    calls = []

    def fake_certify(problem, level, **kwargs):
        calls.append(problem.plan[0])
        return fake_cert(*problem.plan)

    monkeypatch.setattr(cegis_module, "certify_roa", fake_certify)
    areas = NS(box=None, count=None)
    # first choice (iteration 1) refuted, runner-up (0) certifies 0.8 <= best 1.0
    window = [iterate(0, 3.0, 0.8), iterate(1, 5.0, None)]
    win, cert = cegis_module._verify_window(window, window[1], lambda m: None, None, 1.0,
                                            areas)
    assert calls == [1, 0] and win is window[1] and not cert.certified
    assert window[0].verified and window[0].entry["area"] == 0.8 and not window[1].verified
    assert (win.lost == 0.0).all() and win.lost.shape == (1, 2)
    # the runner-up beats the best: it wins, the refuted first choice keeps its record
    calls.clear()
    window = [iterate(0, 3.0, 2.5), iterate(1, 5.0, None)]
    win, cert = cegis_module._verify_window(window, window[1], lambda m: None, None, 1.0,
                                            areas)
    assert calls == [1, 0] and win is window[0] and cert.certified
    assert window[1].verified and window[1].entry["status"] == "not certified"
    assert (win.lost == 1.0).all()
    # 4 states: the first choice only
    calls.clear()
    window = [iterate(0, 3.0, 2.5, nx=4), iterate(1, 5.0, None, nx=4)]
    win, _ = cegis_module._verify_window(window, window[1], lambda m: None, None, 1.0, areas)
    assert calls == [1] and win is window[1]
