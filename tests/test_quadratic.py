"""The cheap quadratic certificates before the neural stage, the best certificate wins, and the
level search that follows a decrease counterexample down (issue 15, item 5)."""

import json

import casadi as ca
import numpy as np
import pytest

import systems
from baselines.compare import RowStatus, quadratic_row
from nlyap_opt.candidates.quadratic import (
    LEARNED_SEARCH_STATES,
    certify_quadratics,
    closed_loop_matrix,
    decided_on_sets,
    quadratic_policy,
)
from nlyap_opt.certification.certificate import LevelPolicy, RoaProblem, recheck_certificate
from nlyap_opt.certification.roa import certify_level, least_violation
from nlyap_opt.design.control import lqr, quadratic_lyapunov, saturated_controller
from nlyap_opt.kernel.domain import Ball
from nlyap_opt.kernel.errors import ConfigError
from nlyap_opt.kernel.network import Network
from nlyap_opt.workflow.configs import get_config, make_config
from nlyap_opt.workflow.pipeline import run


# --------------------------------------------------------------------------- level search
def _shell():
    """``V = ‖x‖²`` under ``f = x(‖x‖² − 1/4)``: ``V̇ = 2‖x‖²(‖x‖² − 1/4)`` is negative
    exactly for ``‖x‖ < 1/2``, so the largest certifiable level is ``V = 1/4``."""
    x = ca.MX.sym("x", 2)
    V = ca.sumsqr(x)
    lie = 2 * V * (V - 0.25)
    return x, V, lie


def test_least_violation_finds_the_edge_of_the_violation_set():
    x, V, lie = _shell()
    found = least_violation(x, V, lie, [[0.6, 0.5], [-0.1, 0.9]], inner=0.05,
                            domain=Ball(1.0, 2), tol=1e-7)
    assert found is not None
    assert found[0] == pytest.approx(0.25, abs=1e-6)
    assert np.linalg.norm(found[1]) == pytest.approx(0.5, abs=1e-6)
    # strict tolerance: IPOPT ends just inside the constraint, which tol = 0 refuses
    pts = np.array([[0.9, 0.0]])
    strict = least_violation(x, V, lie, pts, inner=0.05, domain=Ball(1.0, 2), tol=0.0)
    assert strict is None or 2 * strict[0] * (strict[0] - 0.25) >= 0


def test_a_decrease_counterexample_drops_the_level_to_the_violation_edge():
    x, V, lie = _shell()
    lc = certify_level(x, V, lie, level=0.8, inner=0.05, outer=1.0, margin=0.0,
                       max_tries=3, log=lambda m: None, follow_violations=True)
    assert lc.status == "certified", lc.history
    assert 0.24 < lc.level < 0.25
    assert lc.history[0]["decrease"] == "counterexample"
    assert len(lc.history) <= 3
    # the refuted levels were real: V̇ ≥ 0 somewhere below each of them (the tries after the
    # certified one bisect back up towards the refuted level)
    failed = [h for h in lc.history if h.get("contains_inner_ball") != "verified"]
    assert failed and all(h["level"] > 0.25 for h in failed)
    assert [h["level"] for h in lc.history if h not in failed] == [lc.level]


# --------------------------------------------------------------------------- candidates
def _pendulum_problem(controller_scale=20.0):
    s = systems.get("inverted_pendulum")
    cfg = get_config("inverted_pendulum", "fast")
    res = lqr(s, cfg["lqr"]["Q"], cfg["lqr"]["R"])
    ctrl = saturated_controller(s, res.K, controller_scale)
    from nlyap_opt.design.control import quadratic_lyapunov

    return s, cfg, res, RoaProblem(s, quadratic_lyapunov(np.eye(2)), ctrl, None, inner=0.4,
                                   outer=4.0)


def test_quadratic_candidates_solve_their_matrix_equations_and_certify():
    s, cfg, res, problem = _pendulum_problem()
    A_cl = closed_loop_matrix(problem)
    np.testing.assert_allclose(A_cl, res.A - res.B @ res.K, atol=1e-9)
    box = np.asarray(cfg["eval_box"], dtype=float)
    found = certify_quadratics(problem, ["lyapunov", "round"], box=box, n=101,
                               log=lambda m: None)
    assert [c.name for c in found] == ["lyapunov", "round"]
    lyap, rnd = found
    np.testing.assert_allclose(A_cl.T @ lyap.P + lyap.P @ A_cl, -np.eye(2), atol=1e-8)
    assert np.linalg.eigvalsh(rnd.P)[0] >= 1 - 1e-6
    assert np.linalg.cond(rnd.P) <= np.linalg.cond(lyap.P) + 1e-6
    for c in found:
        assert c.certified, c.certificate.reason
        assert c.certificate.inner == pytest.approx(0.1)   # ε/4 of the problem's 0.4
        assert c.volume > 0
        # the certified sublevel set really has V̇ < 0 (sampled, true f, saturated κ)
        rng = np.random.default_rng(0)
        pts = rng.uniform(-4, 4, (20000, 2))
        q = np.einsum("ij,jk,ik->i", pts, c.P, pts)
        r = np.linalg.norm(pts, axis=1)
        inside = (q <= c.certificate.level) & (r >= c.certificate.inner) & (r <= 4)
        f = s.evaluate(pts[inside], problem.controller.numpy(pts[inside]))
        assert np.all(np.einsum("ij,jk,ik->i", pts[inside], c.P, f) < 0)


def test_unknown_or_repeated_quadratic_names_are_config_errors():
    with pytest.raises(ConfigError, match=r"quadratic.*'rond'.*did you mean 'round'"):
        make_config("inverted_pendulum", "fast", overrides={"quadratic": ["rond"]})
    with pytest.raises(ConfigError, match="twice"):
        make_config("inverted_pendulum", "fast", overrides={"quadratic": ["round", "round"]})
    with pytest.raises(ConfigError, match="quadratic"):
        make_config("inverted_pendulum", "fast", overrides={"quadratic": "round"})


# --------------------------------------------------------------------------- pipeline
@pytest.fixture(scope="module")
def quad_run(tmp_path_factory):
    """Inverted pendulum, true f, with the quadratic candidates and a neural stage cut to
    one step (so that the quadratic must win)."""
    d = tmp_path_factory.mktemp("quad")
    cfg = make_config("inverted_pendulum", "fast", overrides={
        "quadratic": ["lyapunov", "round"], "train": {"steps": 1},
        "cegis": {"iterations": 1, "steps": 1}})
    logs = []
    res = run("inverted_pendulum", cfg, d, known_dynamics=True, log=logs.append)
    return d, cfg, res, logs


def test_the_larger_certified_volume_wins_and_is_saved_with_its_artifacts(quad_run):
    d, cfg, res, logs = quad_run
    summary = json.loads((d / "certificate.json").read_text())
    cands = summary["candidates"]
    assert [c["winner"] for c in cands].count(True) == 1
    win = next(c for c in cands if c["winner"])
    lose = next(c for c in cands if not c["winner"])
    assert win["certified_volume"] >= lose["certified_volume"]
    assert res.certified and summary["status"] == "certified"
    assert win["V"].startswith("quadratic")     # the one-step neural V loses
    assert summary["artifacts"]["V"]["file"] == "V_quadratic.json"
    assert summary["artifacts"]["controller"]["file"] == "controller_init.json"
    assert summary["certified_area"] == pytest.approx(win["certified_volume"])
    assert any("quadratic" in a for a in summary["assumptions"])
    # the saved quadratic is the matrix of quadratic.json's best candidate
    best = json.loads((d / "quadratic.json").read_text())["best"]
    V = Network.load(d / "V_quadratic.json")
    P = np.asarray(best["P"])
    z = np.random.default_rng(1).normal(size=(50, 2))
    np.testing.assert_allclose(V.numpy(z)[:, 0], np.einsum("ij,jk,ik->i", z, P, z),
                               rtol=1e-12, atol=1e-12)
    assert "certificate to beat" in "\n".join(logs)
    report = (d / "report.md").read_text()
    assert "## Best certificate" in report and "V_quadratic.json" in report
    # and the report says so plainly, before the details
    assert report.index("**The neural V did not beat the cheap candidate**") < \
        report.index("## Parameters")


def test_the_winning_quadratic_rechecks_and_a_tampered_one_does_not(quad_run, tmp_path):
    import shutil

    d, cfg, _, _ = quad_run
    assert recheck_certificate(d, log=lambda m: None).certified
    e = tmp_path / "copy"
    shutil.copytree(d, e)
    V = Network.load(e / "V_quadratic.json")
    V.layers[0].weight = V.layers[0].weight * 0.5      # a flatter V: a larger set
    V.save(e / "V_quadratic.json")
    again = recheck_certificate(e, log=lambda m: None)
    assert not again.certified and "changed" in again.reason
    # the verifier options the certificate was proved with are saved and checked on re-check
    cert = json.loads((d / "certificate.json").read_text())
    assert cert["problem"]["verify_options"] == cfg.get("cegis", {}).get("verify_options", {})
    f = tmp_path / "bad_opts"
    shutil.copytree(d, f)
    cert["problem"]["verify_options"] = {"rm": True}
    (f / "certificate.json").write_text(json.dumps(cert))
    with pytest.raises(ConfigError, match="unknown verifier option 'rm'"):
        recheck_certificate(f, log=lambda m: None)
    cert["problem"]["verify_options"] = {"batch": 0}     # would crash the verifier
    (f / "certificate.json").write_text(json.dumps(cert))
    with pytest.raises(ConfigError, match=r"'batch' must be an integer >= 1, got 0; rerun"):
        recheck_certificate(f, log=lambda m: None)
    from nlyap_opt.interface.cli import main

    assert main(["verify", "--certificate", str(f / "certificate.json")]) == 3
    # a resumed run recomputes the quadratic stage instead of trusting the file
    logs = []
    res = run("inverted_pendulum", cfg, e, known_dynamics=True, log=logs.append)
    assert "[quadratic] V_quadratic.json changed" in "\n".join(logs)
    assert res.certified
    assert recheck_certificate(e, log=lambda m: None).certified



def test_compare_rows_and_the_pipeline_certify_the_same_p_at_the_same_level(quad_run):
    """One certification policy: ``nlyap compare``'s quadratic row, given the matrix ``P``
    the pipeline's quadratic stage certified (and compare's saturated LQR controller, the
    pipeline's initial one), proves exactly the pipeline's level and inner radius."""
    d, cfg, _, _ = quad_run
    s = systems.get("inverted_pendulum")
    ctrl = saturated_controller(s, lqr(s, cfg["lqr"]["Q"], cfg["lqr"]["R"]).K,
                                cfg["controller_scale"])
    z = np.random.default_rng(2).normal(size=(40, 2))
    np.testing.assert_array_equal(ctrl.numpy(z),
                                  Network.load(d / "controller_init.json").numpy(z))
    cands = json.loads((d / "quadratic.json").read_text())["candidates"]
    assert [c["name"] for c in cands] == ["lyapunov", "round"]
    for c in cands:
        assert c["certified"], c
        row = quadratic_row(s, cfg, quadratic_lyapunov(np.asarray(c["P"])), ctrl,
                            method=f"lqr ({c['name']} P)", log=lambda m: None)
        assert row.status is RowStatus.CERTIFIED, row.status_text
        assert row.level == c["level"] > 0                 # the same level, bit for bit
        assert row.certificate.inner == c["inner"] == pytest.approx(0.25 * cfg["inner"])
        assert row.to_json()["level"] == c["level"]


def test_level_policies():
    """The quadratic policy searches radii from ε/4 with the true f and from ε upwards with
    learned dynamics; a policy without a positive fraction or radius is refused."""
    known, learned = quadratic_policy(True), quadratic_policy(False)
    assert known.inner_fraction == 0.25 and 1.0 in known.factors and min(known.factors) < 1
    assert learned.inner_fraction == 1.0 and min(learned.factors) == 1.0
    assert learned.smallest_level and not known.smallest_level
    # learned dynamics whose closed loop is smooth: whole sets first, at ε
    whole = quadratic_policy(False, whole_set=True)
    assert whole.whole_sets and not learned.whole_sets and whole.smallest_level
    assert whole.factors == learned.factors
    assert whole.inner_fraction == learned.inner_fraction
    # at most LEARNED_SEARCH_STATES states: searched down from the candidate level, at ε
    small = quadratic_policy(False, nx=LEARNED_SEARCH_STATES)
    assert not small.smallest_level and not small.whole_sets
    assert small.factors == learned.factors and small.inner_fraction == 1.0
    assert quadratic_policy(False, nx=LEARNED_SEARCH_STATES + 1) == learned
    for bad in ({"inner_fraction": 0.0}, {"inner_fraction": float("nan")}, {"factors": ()},
                {"factors": (1.0, -2.0)}):
        with pytest.raises(ValueError):
            LevelPolicy(**bad)
    with pytest.raises(AttributeError):
        known.inner_fraction = 1.0         # frozen: one policy object, shared


# ------------------------------------------------------------- V warm-started (train.init)
def test_quadratic_start_is_the_quadratic_over_its_level_near_the_origin():
    """V = ‖N(x) − N(0)‖² + ε‖x‖² with a·Lx in its first neurons equals xᵀPx/level up to
    the tanh's cubic term: |V − q| ≤ a²‖Lx‖⁴/level-scale (checked at 2000 points of
    growing radius); V(0) = 0 exactly; the architecture is the configured one."""
    from nlyap_opt.candidates.learning import QUADRATIC_START_SLOPE, TrainConfig, quadratic_start

    P = np.array([[2.0, 0.3, 0.0], [0.3, 1.0, 0.1], [0.0, 0.1, 0.5]])
    cfg = TrainConfig(hidden=[8], features=4, eps=1e-3, seed=3)
    V = quadratic_start(P, 0.5, cfg)
    assert [w.weight.shape for w in V.layers] == [(8, 3), (4, 8)]
    assert V.numpy(np.zeros((1, 3)))[0, 0] == 0.0
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2000, 3)) * rng.uniform(0, 1, (2000, 1))
    q = np.einsum("ij,jk,ik->i", x, P / 0.5, x)
    v = V.numpy(x)[:, 0]
    a = QUADRATIC_START_SLOPE
    # tanh(t)/a = Lx − a²(Lx)³/3 + ...: the squares differ by at most (2/3)a²‖Lx‖₄⁴ plus
    # the random neurons' 1e-3 read-out, both small against q near the origin
    assert np.all(np.abs(v - q) <= 0.7 * a**2 * q**2 + 1e-2 * np.maximum(q, 1e-6) + 1e-12)
    small = np.linalg.norm(x, axis=1) < 0.1
    np.testing.assert_allclose(v[small], q[small], rtol=0.02)


@pytest.mark.parametrize("train, match", [
    ({"init": "warm"}, r"train\.init.*'random', 'quadratic'|must be one of"),
    ({"init": "quadratic", "activation": "square"}, "one tanh hidden layer"),
    ({"init": "quadratic", "hidden": [6, 6]}, "one tanh hidden layer"),
    ({"init": "quadratic", "features": 1}, "features >= 2"),
])
def test_bad_warm_start_settings_are_config_errors(train, match):
    with pytest.raises(ConfigError, match=match):
        make_config("inverted_pendulum", "fast",
                    overrides={"quadratic": ["lyapunov"], "train": train})
    with pytest.raises(ConfigError, match="no quadratic candidates are listed"):
        make_config("inverted_pendulum", "fast", overrides={"train": {"init": "quadratic"}})


@pytest.mark.slow  # a whole run (6 s); quadratic_start itself is tested above
def test_a_run_with_init_quadratic_starts_cegis_at_the_certified_quadratic(tmp_path,
                                                                            log_until):
    """The pendulum with ``train.init: quadratic``: CEGIS starts from the quadratic stage's
    winner (logged), its stage depends on the quadratic stage's files, and the run is
    certified; a changed V_quadratic.json reruns the quadratic stage, which writes the same
    bytes again (stage files hold no timings), so CEGIS is kept."""
    cfg = make_config("inverted_pendulum", "fast", overrides={
        "quadratic": ["lyapunov"], "train": {"init": "quadratic"}})
    logs = []
    res = run("inverted_pendulum", cfg, tmp_path, known_dynamics=True, log=logs.append)
    text = "\n".join(logs)
    assert res.certified
    assert "[cegis] V starts at the quadratic lyapunov" in text
    stages = json.loads((tmp_path / "stages.json").read_text())
    f = tmp_path / "V_quadratic.json"
    saved = f.read_bytes()
    f.write_text(f.read_text().replace("1", "2", 1))   # tampered: the stage recomputes
    log = log_until("[cegis] ")               # the rerun, until CEGIS loads or recomputes
    with pytest.raises(KeyboardInterrupt):
        run("inverted_pendulum", cfg, tmp_path, known_dynamics=True, log=log)
    text = "\n".join(log.lines)
    assert "[quadratic] certifying" in text and f.read_bytes() == saved
    assert "[cegis] loaded from" in text
    assert "quadratic" in stages and "cegis" in stages


@pytest.mark.parametrize("name", ["van_der_pol", "inverted_pendulum"])
def test_closed_loop_matrix_without_a_controller(name):
    """An autonomous system (no input) and a controlled one at u_eq: the SX closed loop of
    the quadratic candidates (an MX input beside an SX state used to fail) gives the
    Jacobian of f(x, u_eq) at 0 (central differences of the system's own evaluator)."""
    from nlyap_opt.design.control import quadratic_lyapunov
    from nlyap_opt.kernel.symbolic import closed_loop

    s = systems.get(name)
    p = RoaProblem(s, quadratic_lyapunov(np.eye(s.nx)), None, inner=0.1, outer=1.0)
    A = closed_loop_matrix(p)
    h = 1e-6
    u = None if not s.nu else np.tile(np.asarray(s.u_eq, dtype=float), (1, 1))
    fd = np.stack([(s.evaluate(h * e[None], u) - s.evaluate(-h * e[None], u))[0] / (2 * h)
                   for e in np.eye(s.nx)], axis=1)
    np.testing.assert_allclose(A, fd, atol=1e-6)
    cl = closed_loop(s, None, x=ca.SX.sym("x", s.nx))
    assert isinstance(cl.u, ca.SX) and isinstance(cl.rhs, ca.SX)


# --------------------------------------------------------------------- the volume candidate
def _lmi_ok(A, P, alpha, tol=1e-6):
    S = A.T @ P + P @ A + 2 * alpha * P
    return np.linalg.eigvalsh(0.5 * (S + S.T))[-1] <= tol * np.linalg.eigvalsh(P)[-1]


def test_volume_matrix_of_a_symmetric_loop_is_the_ball():
    """``A_cl = −diag(1, 2, 3)``: every ``P ⪰ I`` with ``P = I`` satisfies the decay LMI, and
    ``det P ≥ 1`` on ``P ⪰ I`` with equality only at ``I``: the optimum is the unit ball."""
    from nlyap_opt.design.control import volume_lyapunov_matrix

    P = volume_lyapunov_matrix(-np.diag([1.0, 2.0, 3.0]))
    np.testing.assert_allclose(P, np.eye(3), atol=1e-5)
    assert volume_lyapunov_matrix(np.diag([-1.0, 0.5])) is None      # not Hurwitz


@pytest.mark.parametrize("seed", [1, 4, 10])   # non-normal: the round P is not I
def test_volume_matrix_is_feasible_larger_than_round_and_locally_optimal(seed):
    """On random Hurwitz matrices: ``P ⪰ I`` and the decay LMI hold, the ellipsoid
    ``{xᵀPx ≤ 1}`` is at least as large as the round matrix's (scaled into the unit ball),
    and no feasible perturbation of ``P`` found by sampling has a smaller ``log det``."""
    from nlyap_opt.design.control import round_lyapunov_matrix, volume_lyapunov_matrix

    rng = np.random.default_rng(seed)
    n = 3
    A = rng.normal(size=(n, n))
    A -= (np.max(np.linalg.eigvals(A).real) + 0.5) * np.eye(n)
    alpha = 0.1 * -np.max(np.linalg.eigvals(A).real)
    P = volume_lyapunov_matrix(A)
    assert np.linalg.eigvalsh(P)[0] >= 1 - 1e-6
    assert _lmi_ok(A, P, alpha)
    R = round_lyapunov_matrix(A)
    R = R / np.linalg.eigvalsh(R)[0]
    ld = np.linalg.slogdet(P)[1]
    assert ld < np.linalg.slogdet(R)[1] - 0.02      # the descent moved (R is a start)
    better = 0
    for _ in range(3000):
        D = rng.normal(size=(n, n))
        Q = P + 1e-3 * (D + D.T)
        if np.linalg.eigvalsh(Q)[0] >= 1 and _lmi_ok(A, Q, alpha, tol=0.0):
            better += np.linalg.slogdet(Q)[1] < ld - 1e-6
    assert better == 0


def test_volume_candidate_certifies_the_pendulum_with_sampled_decrease():
    """Through the quadratic stage (``quadratic: ["volume"]``): certified, and the certified
    sublevel set really has ``V̇ < 0`` (sampled, true f, saturated κ)."""
    s, cfg, res, problem = _pendulum_problem()
    box = np.asarray(cfg["eval_box"], dtype=float)
    (c,) = certify_quadratics(problem, ["volume"], box=box, n=101, log=lambda m: None)
    assert c.name == "volume" and c.certified, c.certificate.reason
    A_cl = closed_loop_matrix(problem)
    S = A_cl.T @ c.P + c.P @ A_cl
    assert np.linalg.eigvalsh(S)[-1] < 0                    # a Lyapunov matrix of A_cl
    rng = np.random.default_rng(0)                          # uniform in the ellipse
    z = rng.normal(size=(5000, 2))
    z *= np.sqrt(rng.random((5000, 1))) / np.linalg.norm(z, axis=1, keepdims=True)
    pts = np.linalg.solve(np.linalg.cholesky(c.P).T, z.T).T * np.sqrt(c.certificate.level)
    r = np.linalg.norm(pts, axis=1)
    inside = (r >= c.certificate.inner) & (r <= 4)
    assert inside.sum() > 1000
    f = s.evaluate(pts[inside], problem.controller.numpy(pts[inside]))
    assert np.all(np.einsum("ij,jk,ik->i", pts[inside], c.P, f) < 0)


def test_sets_are_decided_whole_only_for_a_smooth_closed_loop():
    """The pendulum under the smooth controller C·tanh(K'x + b): TaylorDecrease applies; a
    closed loop with a kink (|x₂|) it does not, and the learned policy stays at the
    smallest level there."""
    assert decided_on_sets(_pendulum_problem()[3])
    x = ca.SX.sym("x", 2)
    kink = systems.System("kink", x, None, ca.vertcat(-x[0] + 0.1 * ca.fabs(x[1]), -x[1]),
                          state_box=[[-1, 1]] * 2)
    assert not decided_on_sets(RoaProblem(kink, quadratic_lyapunov(np.eye(2)), None, None,
                                          inner=0.1, outer=1.0))
