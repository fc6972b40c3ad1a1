"""SOS as a cheap certificate of the pipeline (issue 15, item 5): the ``sos`` section, the
``sos`` stage, the best certificate among neural, quadratic and SOS, and what is refused."""

import json
import os
import shutil

import numpy as np
import pytest
from forge import forge_stage_file

import systems
from nlyap_opt.candidates.sos import SOSConfig, certify_sos
from nlyap_opt.certification.certificate import RoaProblem, recheck_certificate
from nlyap_opt.design.control import lqr, quadratic_lyapunov, saturated_controller
from nlyap_opt.design.polynomial import Polynomial
from nlyap_opt.kernel.errors import ConfigError
from nlyap_opt.kernel.network import Layer, Network
from nlyap_opt.workflow.configs import make_config
from nlyap_opt.workflow.pipeline import run


# --------------------------------------------------------------------------- configuration
@pytest.mark.parametrize("sos, msg", [
    ({"degree": 3}, r"sos\.degree must be one of 'auto', 0, 2, 4, 6, got 3"),
    ({"degree": 2.0}, r"sos\.degree must be one of"),
    ({"degre": 2}, r"unknown key 'sos\.degre'; did you mean 'sos\.degree'"),
    ({"iterations": 0}, r"sos\.iterations must be an integer >= 1, got 0"),
    (4, r"sos must be a JSON object"),
])
def test_bad_sos_sections_are_config_errors(sos, msg):
    with pytest.raises(ConfigError, match=msg):
        make_config("van_der_pol", "fast", overrides={"sos": sos})


def test_a_misplaced_degree_names_its_section():
    with pytest.raises(ConfigError, match=r"it belongs in a section: sos\.degree"):
        make_config("van_der_pol", "fast", overrides={"degree": 4})


# --------------------------------------------------------------------------- not applicable
def test_a_saturated_controller_makes_sos_not_applicable():
    """tanh in the closed loop: no SDP is set up and the reason names the operation."""
    s = systems.get("inverted_pendulum")
    ctrl = saturated_controller(s, lqr(s).K, 20.0)
    p = RoaProblem(s, quadratic_lyapunov(np.eye(2)), ctrl, inner=0.1, outer=1.0)
    res = certify_sos(p, SOSConfig(degree=2), log=lambda m: None)
    assert not res.applicable and not res.certified
    assert res.text.startswith("not applicable") and res.certificate is None
    assert "tanh" in res.non_polynomial


def test_learned_dynamics_with_inputs_make_sos_not_applicable():
    """With φ and an input the closed loop under C·tanh(Kx + b) is not polynomial: refused
    before any SDP or fit."""
    s = systems.get("inverted_pendulum")
    phi = Network([Layer(np.full((3, 3), 0.1), np.zeros(3), "tanh"),
                   Layer(-np.eye(2, 3), np.zeros(2), "linear")])
    ctrl = saturated_controller(s, lqr(s).K, 20.0)
    p = RoaProblem(s, quadratic_lyapunov(np.eye(2)), ctrl, phi, inner=0.1, outer=1.0,
                   eta=0.01, dynamics_box=[[-2, 2], [-2, 2]], input_box=[[-20, 20]])
    res = certify_sos(p, SOSConfig(degree=4), log=lambda m: None)
    assert res.text.startswith("not applicable: learned dynamics with inputs")
    assert res.V is None and res.history == [] and res.certificate is None


def test_learned_dynamics_run_sos_on_a_model_of_phi_and_certify_on_phi(trained, monkeypatch):
    """Learned Van der Pol: the SOS programs run on a polynomial fitted to φ, never on the
    model of f (reading it fails the test), and the V they give is certified on φ with the
    robust margin; the property holds at sampled points of the certified set."""
    import casadi as ca

    import nlyap_opt.candidates.sos as sos_mod
    from nlyap_opt.kernel.symbolic import closed_loop

    def model_read(*a, **k):
        raise AssertionError("the model of f was read")
    monkeypatch.setattr(sos_mod, "polynomial_closed_loop", model_read)
    monkeypatch.setattr(sos_mod, "lqr", model_read)
    res_phi = trained["van_der_pol"]
    s, eta = systems.get("van_der_pol"), 2e-3
    p = RoaProblem(s, quadratic_lyapunov(np.eye(2)), None, res_phi.network, inner=0.1,
                   outer=1.5, eta=eta, dynamics_box=[[-2, 2], [-2, 2]])
    logs = []
    res = certify_sos(p, SOSConfig(degree=4, iterations=3), log=logs.append)
    assert res.certified, res.text
    assert res.V.degree == 4 and res.inner == p.inner          # the run's ε (robust margin)
    assert not res.problem.known and res.problem.eta == eta
    assert any("least-squares model of φ" in m for m in logs)
    # ∇V·φ + η‖∇V‖ < 0 on sampled points of {V ≤ c} ∩ D outside B_ε
    x = ca.SX.sym("x", 2)
    V = res.V.casadi(x)
    g = closed_loop(s, None, res_phi.network, x=x, strict=False).rhs
    F = ca.Function("F", [x], [V, ca.dot(ca.gradient(V, x), g)
                               + eta * ca.norm_2(ca.gradient(V, x)[1])])
    pts = np.random.default_rng(0).uniform(-1.5, 1.5, (4000, 2))
    v, prop = (np.asarray(a).ravel() for a in F.map(len(pts))(pts.T))
    keep = (v <= res.certified_level) & (np.linalg.norm(pts, axis=1) >= p.inner) \
        & (np.linalg.norm(pts, axis=1) <= 1.5)
    assert keep.sum() > 500 and np.all(prop[keep] < 0)


@pytest.mark.slow
def test_a_learned_dynamics_run_keeps_an_sos_winner_that_rechecks(tmp_path):
    """Van der Pol with learned dynamics, the neural stage cut to one step: the SOS V of
    the model of φ wins, its certificate names φ and the bound, and `nlyap verify
    --certificate` re-checks it from the hashed files."""
    cfg = make_config("van_der_pol", "fast", overrides={
        "sos": {"degree": 4, "iterations": 2}, "train": {"steps": 1},
        "cegis": {"iterations": 1, "steps": 1}})
    res = run("van_der_pol", cfg, tmp_path, known_dynamics=False, log=lambda m: None)
    summary = json.loads((tmp_path / "certificate.json").read_text())
    assert res.certified and summary["artifacts"]["V"]["kind"] == "sx"
    assert {"dynamics", "bounds"} <= set(summary["artifacts"])
    assert any("SOS degree 4 polynomial" in a for a in summary["assumptions"])
    again = recheck_certificate(tmp_path, log=lambda m: None)
    assert again.certified and again.level == summary["level"]


def test_the_polynomial_model_is_the_least_degree_that_fits():
    """A quadratic field is fitted at degree 2 (exactly), a cubic at 3; a field no cubic
    fits returns degree 3 with its residual; the model vanishes at 0; same bits twice."""
    import casadi as ca

    from nlyap_opt.design.polynomial import FIT_TOLERANCE, fit_polynomial_model

    x = ca.SX.sym("x", 2)
    box = [[-2.0, 2.0], [-1.0, 3.0]]
    quad = fit_polynomial_model(ca.Function("q", [x], [ca.vertcat(-x[0] + x[1] ** 2,
                                                                  -2 * x[1] + x[0] * x[1])]), box)
    assert quad.degree == 2 and quad.residual < 1e-12
    assert abs(quad.polynomials[0].to_dict()[(0, 2)] - 1.0) < 1e-10
    np.testing.assert_allclose(quad.linear_part, [[-1, 0], [0, -2]], atol=1e-10)
    fsin = ca.Function("s", [x], [ca.vertcat(ca.sin(3 * x[0]) - x[1], -x[1])])
    a, b = fit_polynomial_model(fsin, box), fit_polynomial_model(fsin, box)
    assert a.degree == 3 and a.residual > FIT_TOLERANCE
    assert all((pa.coefficients == pb.coefficients).all()
               for pa, pb in zip(a.polynomials, b.polynomials))
    assert all(p(np.zeros((1, 2)))[0] == 0 for p in a.polynomials)


def test_degree_zero_is_off():
    s = systems.get("van_der_pol")
    p = RoaProblem(s, quadratic_lyapunov(np.eye(2)), None, inner=0.1, outer=1.0)
    with pytest.raises(ValueError, match="off"):
        certify_sos(p, SOSConfig())


# --------------------------------------------------------------------------- pipeline
@pytest.fixture(scope="module")
def sos_run(tmp_path_factory):
    """Van der Pol, true f, an SOS V of degree 2 and a neural stage cut to one step (so
    that SOS must win)."""
    d = tmp_path_factory.mktemp("sos")
    cfg = make_config("van_der_pol", "fast", overrides={
        "sos": {"degree": 2}, "train": {"steps": 1}, "cegis": {"iterations": 1, "steps": 1}})
    logs = []
    res = run("van_der_pol", cfg, d, known_dynamics=True, log=logs.append)
    return d, cfg, res, logs


def test_the_sos_certificate_wins_and_is_saved_with_its_artifacts(sos_run):
    d, cfg, res, logs = sos_run
    summary = json.loads((d / "certificate.json").read_text())
    assert res.certified and summary["status"] == "certified"
    cands = summary["candidates"]
    assert [c["V"] for c in cands] == ["neural (V.json)", "SOS degree 2 (V_sos.json)"]
    assert [c["winner"] for c in cands] == [False, True]
    assert summary["artifacts"]["V"] == {**summary["artifacts"]["V"], "file": "V.sx.json",
                                         "kind": "sx"}
    assert summary["certified_area"] == pytest.approx(cands[1]["certified_volume"])
    assert any("SOS degree 2 polynomial" in a for a in summary["assumptions"])
    rec = json.loads((d / "sos.json").read_text())
    assert rec["status"] == "certified" and rec["best"]["level"] == summary["level"]
    assert summary["inner_radius"] == pytest.approx(0.25 * cfg["inner"])
    text = "\n".join(logs)
    assert "[cegis] the certificate to beat: SOS degree 2" in text
    assert "[certificate] verifying the saved SOS degree 2 (V_sos.json)" in text
    report = (d / "report.md").read_text()
    assert "## Best certificate" in report and "V_sos.json" in report
    assert (d / "roa.png").stat().st_size > 10_000


def test_the_saved_sos_v_really_decreases_on_its_certified_set(sos_run):
    """The claim, checked by sampling: V̇ = ∇V·f < 0 on {ε ≤ ‖x‖ ≤ r, V ≤ c} for the saved
    polynomial and the true f, and V(0) = 0 < V elsewhere (central differences)."""
    d, cfg, _, _ = sos_run
    s = systems.get("van_der_pol")
    summary = json.loads((d / "certificate.json").read_text())
    V = Polynomial.from_json(json.loads((d / "V_sos.json").read_text()))
    c, eps, r = summary["level"], summary["inner_radius"], cfg["outer"]
    rng = np.random.default_rng(0)
    x = rng.uniform(-r, r, (40000, 2))
    n = np.linalg.norm(x, axis=1)
    x = x[(n >= eps) & (n <= r) & (V(x) <= c)]
    assert len(x) > 5000
    h = 1e-6
    grad = np.stack([(V(x + h * e) - V(x - h * e)) / (2 * h) for e in np.eye(2)], axis=1)
    assert np.all(np.einsum("ij,ij->i", grad, s.evaluate(x)) < 0)
    assert V(np.zeros((1, 2)))[0] == 0.0 and np.all(V(x) > 0)


def test_the_sos_certificate_rechecks_and_a_tampered_one_does_not(sos_run, tmp_path):
    d, cfg, _, _ = sos_run
    assert recheck_certificate(d, log=lambda m: None).certified
    e = tmp_path / "copy"
    shutil.copytree(d, e)
    # a flatter V would claim a larger set: the saved polynomial is hashed
    V = Polynomial.from_json(json.loads((e / "V_sos.json").read_text()))
    (e / "V_sos.json").write_text(json.dumps(V.scaled(0.5).as_json()))
    logs = []
    res = run("van_der_pol", cfg, e, known_dynamics=True, log=logs.append)
    text = "\n".join(logs)
    assert "[sos] V_sos.json changed since this stage wrote it" in text
    assert "[sos] SOS V of degree 2" in text               # recomputed, not trusted
    assert res.certified
    assert json.loads((e / "V_sos.json").read_text()) == \
        json.loads((d / "V_sos.json").read_text())
    # and the certificate's own V artifact is hashed too
    f = e / "V.sx.json"
    f.write_bytes(f.read_bytes() + b"\n")
    again = recheck_certificate(e, log=lambda m: None)
    assert not again.certified and "changed" in again.reason


def test_a_malformed_sos_file_with_a_matching_hash_is_a_one_line_error(sos_run, tmp_path):
    """A V_sos.json whose content was replaced together with the stage record (hash
    matching) is still parsed, not trusted: a ConfigError naming the file and the fix."""

    d, cfg, _, _ = sos_run
    e = tmp_path / "copy2"
    shutil.copytree(d, e)
    (e / "V_sos.json").write_text(json.dumps({"exponents": [[1.5, 0]], "coefficients": [1]}))
    forge_stage_file(e, "sos", "V_sos.json")
    with pytest.raises(ConfigError, match=r"V_sos\.json cannot be read .*delete it and rerun"):
        run("van_der_pol", cfg, e, known_dynamics=True, log=lambda m: None)


def test_polynomial_json_round_trip_and_refusals():
    p = Polynomial.quadratic([[2.0, 0.3], [0.3, 1.0]])
    q = Polynomial.from_json(json.loads(json.dumps(p.as_json())))
    z = np.random.default_rng(0).normal(size=(20, 2))
    np.testing.assert_array_equal(p(z), q(z))
    for bad in ({}, {"exponents": [[1, 0]]}, {"exponents": [[1, 0]], "coefficients": [1, 2]},
                {"exponents": [[-1, 0]], "coefficients": [1]},
                {"exponents": [[1, 0]], "coefficients": [float("nan")]}, [1, 2]):
        with pytest.raises(ValueError, match="polynomial needs"):
            Polynomial.from_json(bad)


# --------------------------------------------------------------------------- solver noise
def test_a_solver_panic_message_is_held_back_other_output_is_not(capfd):
    """Clarabel's Rust panics print to file descriptor 2 (with a backtrace under
    RUST_BACKTRACE) although the failure is handled; what the solver writes otherwise
    passes through unchanged."""
    from nlyap_opt.design.sos_sdp import _stderr_held

    with _stderr_held() as drop:             # native code writes to fd 2, whatever
        os.write(2, b"thread '<unnamed>' panicked at solver.rs\n")   # sys.stderr is
        drop[0] = True
    with _stderr_held():
        os.write(2, b"solver warning kept\n")
    with pytest.raises(KeyboardInterrupt), _stderr_held():
        os.write(2, b"written before an interrupt\n")
        raise KeyboardInterrupt
    err = capfd.readouterr().err
    assert "panicked" not in err and "solver warning kept" in err
    assert "written before an interrupt" in err
    n_fds = len(os.listdir("/proc/self/fd"))
    for _ in range(50):
        with _stderr_held():
            pass
    assert len(os.listdir("/proc/self/fd")) == n_fds


# --------------------------------------------------------------------------- V starts at SOS
def _random_sos(nx: int, degree: int, seed: int = 0) -> Polynomial:
    """V = Σ_k (a_k · z(x))², z the monomials of degree 1..degree/2 (expanded exactly)."""
    import casadi as ca

    from nlyap_opt.design.polynomial import expand_polynomials, monomials

    z_exp = monomials(nx, 1, degree // 2)
    x = ca.SX.sym("x", nx)
    z = ca.vertcat(*[ca.mtimes([x[i] ** int(e[i]) for i in range(nx)] + [1]) for e in z_exp])
    A = np.random.default_rng(seed).normal(size=(len(z_exp), len(z_exp)))
    V = ca.sumsqr(ca.mtimes(ca.DM(A), z))
    return expand_polynomials(ca.Function("V", [x], [V]))[0]


@pytest.mark.parametrize("nx, degree, hidden, features", [(2, 4, 7, 6), (3, 4, 9, 9),
                                                          (3, 2, 6, 3)])
def test_sos_start_is_the_sos_polynomial_over_its_level(nx, degree, hidden, features):
    """V_net = V/level + ε‖x‖² at 2000 points (relative 1e-6: the Gram factor's rounding and
    the random neurons' 1e-3 read-out), V_net(0) = 0, the configured architecture."""
    from nlyap_opt.candidates.learning import TrainConfig, sos_start

    V = _random_sos(nx, degree)
    assert V.degree == degree
    cfg = TrainConfig(hidden=[hidden], features=features, activation="square", eps=1e-3,
                      seed=2)
    net = sos_start(V, 0.4, cfg)
    assert [ly.weight.shape for ly in net.layers] == [(hidden, nx), (features, hidden)]
    assert [ly.activation for ly in net.layers] == ["square", "linear"]
    x = np.random.default_rng(1).normal(size=(2000, nx))
    ref = V(x) / 0.4 + 1e-3 * np.sum(x * x, axis=1)
    np.testing.assert_allclose(net.numpy(x)[:, 0], ref, rtol=1e-6, atol=1e-9)
    assert net.numpy(np.zeros((1, nx)))[0, 0] == 0.0


@pytest.mark.parametrize("train, sos, msg", [
    ({"init": "sos", "activation": "square", "hidden": [6], "features": 5}, {},
     r"train.init 'sos' .* the SOS stage is off"),
    ({"init": "sos", "hidden": [6], "features": 5}, {"degree": 4},
     r"train.init 'sos' \(degree 4\) needs one square hidden layer of at least 5 neurons and "
     r"features >= 5, got activation 'tanh'"),
    ({"init": "sos", "activation": "square", "hidden": [4], "features": 5}, {"degree": 4},
     r"at least 5 neurons"),
    ({"init": "sos", "activation": "square", "hidden": [6], "features": 4}, {"degree": 4},
     r"features >= 5"),
    ({"init": "sos", "activation": "square", "hidden": [6, 6], "features": 5}, {"degree": 4},
     r"one square hidden layer"),
    ({"init": "sos", "activation": "square", "hidden": [6], "features": 5}, {"degree": 6},
     r"SOS V of degree 2 or 4 .* got degree 6"),
    ({"init": "quadratic", "activation": "square"}, {},
     r"no quadratic candidates are listed"),
])
def test_sos_start_config_errors_before_any_stage(train, sos, msg):
    with pytest.raises(ConfigError, match=msg):
        make_config("van_der_pol", "fast", overrides={"train": train, "sos": sos})


def test_a_run_starts_v_at_the_sos_certificate_and_builds_on_its_stage(tmp_path, log_until):
    """train.init 'sos': CEGIS starts from the saved SOS V (logged); a changed V_sos.json
    reruns the SOS stage, which writes the same bytes again (stage files hold no timings),
    so the CEGIS stage built on them is kept."""
    cfg = make_config("van_der_pol", "fast", overrides={
        "sos": {"degree": 4, "iterations": 2},
        "train": {"init": "sos", "activation": "square", "hidden": [6], "features": 5,
                  "steps": 50},
        "cegis": {"iterations": 1, "steps": 20}})
    logs = []
    res = run("van_der_pol", cfg, tmp_path, known_dynamics=True, log=logs.append)
    text = "\n".join(logs)
    assert "[cegis] V starts at the SOS degree" in text
    assert res.certified
    saved = (tmp_path / "V_sos.json").read_bytes()
    V = Polynomial.from_json(json.loads(saved))
    (tmp_path / "V_sos.json").write_text(json.dumps(V.scaled(2.0).as_json()))
    log = log_until("[cegis] ")               # the rerun, until CEGIS loads or recomputes
    with pytest.raises(KeyboardInterrupt):
        run("van_der_pol", cfg, tmp_path, known_dynamics=True, log=log)
    text = "\n".join(log.lines)
    assert "[sos] V_sos.json changed" in text
    assert (tmp_path / "V_sos.json").read_bytes() == saved
    assert "[cegis] loaded from" in text


def test_a_linearisation_without_a_quadratic_lyapunov_function_gives_no_sos_level():
    """Fossil's Poly1 (linearisation diag(0, −1, −4)): no quadratic start for the V-s
    iteration; a status saying so, not an exception (the run goes on to the neural V)."""
    from pathlib import Path

    s = systems.load_spec(Path(__file__).resolve().parents[1] / "examples" / "fossil_poly1.toml")
    p = RoaProblem(s, quadratic_lyapunov(np.eye(3)), None, inner=0.1, outer=1.0)
    res = certify_sos(p, SOSConfig(degree=4), log=lambda m: None)
    assert res.text.startswith("no SOS level") and "not Hurwitz" in res.text
    assert not res.certified and res.certificate is None and res.applicable


@pytest.mark.slow  # 20-40 s: the default tier stays near 5 min on 2 cores
def test_a_badly_scaled_v_s_iteration_is_repeated_in_scaled_units():
    """Fossil's NonPoly2: the quadratic's SOS set reaches |x| ≈ 8, where the degree-4 V step
    fails in x; repeated with x = R·y it succeeds, and the V mapped back is the scaled
    one's (V(x) = V_y(x/R)). Its decrease on the SDP level set is checked by sampling."""
    from pathlib import Path

    from nlyap_opt.candidates.sos import sos_roa

    s = systems.load_spec(Path(__file__).resolve().parents[1] / "examples" /
                          "fossil_nonpoly2.toml")
    res = sos_roa(s, degree=4, iterations=1, certify=False, log=lambda m: None)
    assert res.V.degree == 4
    assert any("repeated in units" in n for n in res.notes)
    assert [h["degree"] for h in res.history] == [2, 4]
    # sampled: V̇ < 0 on {V ≤ 0.9·level} \ B_0.1 (the SDP's claim, away from its tolerance)
    rng = np.random.default_rng(0)
    x = rng.uniform(-6, 6, (200000, 3))
    x = x[(res.V(x) <= 0.9 * res.sdp_level) & (np.linalg.norm(x, axis=1) >= 0.1)]
    assert len(x) > 1000
    h = 1e-6
    grad = np.stack([(res.V(x + h * e) - res.V(x - h * e)) / (2 * h) for e in np.eye(3)],
                    axis=1)
    assert np.all(np.einsum("ij,ij->i", grad, s.evaluate(x)) < 0)


def test_substituted_is_composition_with_a_scaling():
    p = Polynomial.from_dict({(4, 0): 2.0, (1, 1): -1.0, (0, 2): 0.5, (3, 1): 0.25})
    x = np.random.default_rng(0).normal(size=(50, 2))
    np.testing.assert_allclose(p.substituted(3.0)(x), p(3.0 * x), rtol=1e-12)
    np.testing.assert_allclose(p.substituted(3.0).substituted(1 / 3.0)(x), p(x), rtol=1e-12)


def test_a_recheck_always_proves_condition_c(sos_run, tmp_path):
    """A certificate.json whose inner ellipse was removed is not re-checked as (a) and (b)
    alone: (c) is proved again, and since the file does not state the ellipse the re-check
    proves, the edited certificate is refused as written, naming the field."""
    d, _, _, _ = sos_run
    e = tmp_path / "no_ellipse"
    shutil.copytree(d, e)
    cert = json.loads((e / "certificate.json").read_text())
    assert cert["inner_ellipse"] is not None
    cert["inner_ellipse"] = None
    (e / "certificate.json").write_text(json.dumps(cert))
    again = recheck_certificate(e, log=lambda m: None)
    assert not again.certified and "not checked" not in again.reason
    assert "inner_ellipse = None" in again.reason
    assert again.inner_ellipse is not None and again.inner_ellipse.status == "certified"
    assert any(k.startswith("(c)") for k in again.checks)


def test_an_unknown_artifact_kind_is_refused_not_an_internal_error(sos_run, tmp_path):
    from nlyap_opt.interface.cli import main

    d, _, _, _ = sos_run
    e = tmp_path / "bogus_kind"
    shutil.copytree(d, e)
    cert = json.loads((e / "certificate.json").read_text())
    cert["artifacts"]["V"]["kind"] = "bogus"
    (e / "certificate.json").write_text(json.dumps(cert))
    again = recheck_certificate(e, log=lambda m: None)
    assert not again.certified and "cannot be read" in again.reason and "bogus" in again.reason
    assert main(["verify", "--certificate", str(e / "certificate.json")]) not in (0, 4)


@pytest.mark.parametrize("name, known", [("van_der_pol", False), ("inverted_pendulum", True)])
def test_init_sos_where_sos_cannot_apply_is_refused_before_any_stage(name, known, tmp_path):
    """Learned f, or a system with inputs (κ = C·tanh(Kx + b) is not polynomial): the SOS
    start can never exist, so the run stops before any work, naming the fix."""
    cfg = make_config(name, "fast", overrides={
        "sos": {"degree": 2},
        "train": {"init": "sos", "activation": "square", "hidden": [6], "features": 5}})
    with pytest.raises(ConfigError, match=r"train.init 'sos' .*--known-dynamics.*without "
                                          r"inputs.*init 'random' or 'quadratic'"):
        run(name, cfg, tmp_path, known_dynamics=known, log=lambda m: None)
    assert not (tmp_path / "stages.json").exists()


def test_cegis_settings_do_not_recompute_the_cheap_stages(sos_run, tmp_path, log_until):
    """The SOS stage reads cegis.verify_options and cegis.margin_mode only. (Each rerun
    stops once the stage in question has said whether it loads or recomputes.)"""
    d, cfg, _, _ = sos_run
    e = tmp_path / "steps"
    shutil.copytree(d, e)
    cfg2 = make_config("van_der_pol", "fast", overrides={
        "sos": {"degree": 2}, "train": {"steps": 1}, "cegis": {"iterations": 1, "steps": 2}})
    log = log_until("[cegis] ")
    with pytest.raises(KeyboardInterrupt):
        run("van_der_pol", cfg2, e, known_dynamics=True, log=log)
    text = "\n".join(log.lines)
    assert "[sos] loaded from" in text
    assert "[cegis] configuration, system or earlier stage changed" in text
    cfg3 = make_config("van_der_pol", "fast", overrides={
        "sos": {"degree": 2}, "train": {"steps": 1},
        "cegis": {"iterations": 1, "steps": 2, "verify_options": {"batch": 512}}})
    log = log_until("[sos] ")
    with pytest.raises(KeyboardInterrupt):
        run("van_der_pol", cfg3, e, known_dynamics=True, log=log)
    assert "[sos] configuration, system or earlier stage changed: recomputing" in \
        "\n".join(log.lines)


def test_no_gram_matrix_starts_v_at_random(monkeypatch, tmp_path, log_until):
    import nlyap_opt.design.sos_sdp as sdp

    def fail(V, **kw):
        raise ValueError("no Gram matrix of V was found (solver status infeasible)")

    monkeypatch.setattr(sdp, "gram_factor", fail)
    cfg = make_config("van_der_pol", "fast", overrides={
        "sos": {"degree": 2},
        "train": {"init": "sos", "activation": "square", "hidden": [6], "features": 5,
                  "steps": 20},
        "cegis": {"iterations": 1, "steps": 5}})
    log = log_until("cegis iteration 0")     # CEGIS went on from a random V: stop there
    with pytest.raises(KeyboardInterrupt):
        run("van_der_pol", cfg, tmp_path, known_dynamics=True, log=log)
    text = "\n".join(log.lines)
    assert "[cegis] V cannot start at the SOS degree 2 (no Gram matrix" in text
    assert "V starts at the SOS" not in text


def test_no_model_of_phi_is_fitted_where_auto_cannot_pick_a_degree_and_starts_are_checked():
    """Four or more states: "auto" cannot pick a degree whatever f, so no fit is made (a
    3ⁿ grid of 20 states would not fit in memory); a fit in many states uses seeded points;
    a linear part stable only up to rounding gives no start matrix."""
    import casadi as ca

    from nlyap_opt.candidates.sos import _start_matrix, sos_may_fit
    from nlyap_opt.design.polynomial import fit_polynomial_model

    assert sos_may_fit(2) and sos_may_fit(3) and not sos_may_fit(4)
    x = ca.SX.sym("x", 8)
    fit = fit_polynomial_model(ca.Function("f", [x], [-x + 0.5 * x ** 3]),
                               np.tile([-1.0, 1.0], (8, 1)), points=2000)
    assert fit.degree == 3 and fit.residual < 1e-10
    np.testing.assert_allclose(fit.linear_part, -np.eye(8), atol=1e-9)
    rng = np.random.default_rng(4)
    for _ in range(300):        # near-marginal: never a start matrix that is not PD
        M = rng.normal(size=(3, 3))
        A = M - (np.max(np.linalg.eigvals(M).real) + 1e-13) * np.eye(3)
        P = _start_matrix(A)
        assert P is None or np.linalg.eigvalsh(0.5 * (P + P.T))[0] > 0
    P = _start_matrix(np.array([[-1.0, 2.0], [0.0, -3.0]]))
    assert P is not None and np.linalg.eigvalsh(P)[0] > 0
    assert _start_matrix(np.array([[0.0, 1.0], [-1.0, 0.0]])) is None
