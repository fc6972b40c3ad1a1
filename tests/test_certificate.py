"""The one certificate core: conditions (a), (b), (c), typed results, honest status, JSON."""

import json

import casadi as ca
import numpy as np
import pytest

import systems
from nlyap_opt.certification.certificate import (
    CertStatus,
    RoaCertificate,
    RoaProblem,
    certify_roa,
    recheck_certificate,
    save_certificate,
)
from nlyap_opt.design.control import lqr, lyapunov_matrix, quadratic_lyapunov
from nlyap_opt.kernel.errors import ConfigError
from nlyap_opt.kernel.network import Layer, Network

QUIET = {"log": lambda m: None}


def _vdp_quadratic():
    s = systems.get("van_der_pol")
    res = lqr(s)
    return s, quadratic_lyapunov(res.P), res.P


def _min_V_where_decrease_fails(P, s, r, n=801):
    """Independent grid estimate: min V over {ε ≤ ‖x‖ ≤ r, V̇ ≥ 0} ∪ {‖x‖ = r}."""
    g = np.linspace(-r, r, n)
    X = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    X = X[np.linalg.norm(X, axis=1) <= r]
    v = np.einsum("ij,jk,ik->i", X, P, X)
    F = s.evaluate(X, None)
    vdot = 2 * np.einsum("ij,jk,ik->i", X, P, F)
    th = np.linspace(0, 2 * np.pi, 4000)
    S = r * np.stack([np.cos(th), np.sin(th)], 1)
    bad = (vdot >= 0) & (np.linalg.norm(X, axis=1) >= 0.05)
    return min(v[bad].min() if bad.any() else np.inf, np.einsum("ij,jk,ik->i", S, P, S).min())


def test_known_f_quadratic_certificate_and_mutations():
    s, V, P = _vdp_quadratic()
    prob = RoaProblem(s, V, inner=0.05, outer=2.0)
    c_max = _min_V_where_decrease_fails(P, s, 2.0)
    cert = certify_roa(prob, 0.9 * c_max, **QUIET)
    assert cert.status is CertStatus.CERTIFIED, cert.reason
    assert cert.inner_ellipse is not None and cert.inner_ellipse.proved
    assert all(v in ("verified", "certified") for v in cert.checks.values()), cert.checks
    # the certified set: Ω_c ∪ E, and nothing where V > level outside E
    pts = np.random.default_rng(0).uniform(-2, 2, (4000, 2))
    inside = cert.contains(pts)
    v = np.einsum("ij,jk,ik->i", pts, P, pts)
    assert np.all(v[inside & ~cert.inner_ellipse.contains(pts)] <= cert.level)
    # a level above the grid's minimum of V on the failure set cannot be certified
    bad = certify_roa(prob, 1.05 * c_max, **QUIET)
    assert bad.status in (CertStatus.COUNTEREXAMPLE, CertStatus.NOT_CERTIFIED)
    assert not bad.contains(pts).any()
    # with search, the level comes down to a certified one below c_max
    found = certify_roa(prob, 1.05 * c_max, search=True, **QUIET)
    assert found.certified and found.level < c_max


def test_flipped_gain_is_refused():
    s = systems.get("inverted_pendulum")
    res = lqr(s)
    from nlyap_opt.design.control import linear_controller

    bad_ctrl = linear_controller(s, -res.K)  # wrong sign: the closed loop is unstable
    prob = RoaProblem(s, quadratic_lyapunov(res.P), bad_ctrl, inner=0.1, outer=1.0)
    cert = certify_roa(prob, 0.01, **QUIET)
    assert not cert.certified


def test_problem_input_validation():
    s, V, _ = _vdp_quadratic()
    for kw in ({"inner": 2.0, "outer": 1.0}, {"inner": -0.1, "outer": 1.0},
               {"inner": 0.1, "outer": float("nan")}, {"inner": 0.1, "outer": 1.0, "eta": 0.1},
               {"inner": 0.1, "outer": 1.0, "margin_mode": "foo"}):
        with pytest.raises(ConfigError):
            RoaProblem(s, V, **kw)
    with pytest.raises(ConfigError):
        certify_roa(RoaProblem(s, V, inner=0.1, outer=1.0), -1.0, **QUIET)
    with pytest.raises(ConfigError):
        certify_roa(RoaProblem(s, V, inner=0.1, outer=1.0), float("inf"), **QUIET)


def _unstable_truth_with_stable_model():
    """True f = +x (unstable); learned φ = −x (a model the samples would never give)."""
    x = ca.SX.sym("x", 2)
    s = systems.System("unstable_truth", x, None, x, state_box=[[-2, 2], [-2, 2]])
    phi = Network([Layer(-np.eye(2), np.zeros(2), "linear")],
                  meta={"kind": "dynamics", "model": "full"})
    V = quadratic_lyapunov(np.eye(2))
    return s, phi, V


def test_learned_certificate_refused_when_its_assumption_is_refuted():
    """(c) is assumed for learned φ; the tool's own true-f check refutes it: not certified."""
    s, phi, V = _unstable_truth_with_stable_model()
    prob = RoaProblem(s, V, None, phi, inner=0.1, outer=1.0, eta=0.01,
                      dynamics_box=[[-2, 2], [-2, 2]])
    cert = certify_roa(prob, 0.5, **QUIET)
    assert cert.checks["(a) decrease"] == "verified"          # on φ, the decrease holds
    assert cert.status is CertStatus.ASSUMPTION_REFUTED, cert.reason
    assert "Assumption 3" in " ".join(cert.assumptions)
    assert not cert.contains(np.zeros((1, 2))).any()


def test_learned_eta_too_large_is_not_certified():
    s, phi, V = _unstable_truth_with_stable_model()
    # ∇V·φ + η‖∇V‖ = −2‖x‖² + 2η‖x‖ ≥ 0 for ‖x‖ ≤ η: with η = 0.5 the ring 0.1..0.5 fails
    prob = RoaProblem(s, V, None, phi, inner=0.1, outer=1.0, eta=0.5,
                      dynamics_box=[[-2, 2], [-2, 2]])
    cert = certify_roa(prob, 0.5, **QUIET)
    assert cert.status in (CertStatus.COUNTEREXAMPLE, CertStatus.NOT_CERTIFIED)
    assert cert.checks["(a) decrease"] in ("counterexample", "unknown")


def test_ball_outside_the_dynamics_box_is_refused():
    s, phi, V = _unstable_truth_with_stable_model()
    prob = RoaProblem(s, V, None, phi, inner=0.1, outer=1.0, eta=0.01,
                      dynamics_box=[[-0.5, 0.5], [-0.5, 0.5]])
    cert = certify_roa(prob, 0.5, **QUIET)
    assert not cert.certified and "does not apply" in cert.reason


def test_json_round_trip_and_recheck(tmp_path):
    s, V, P = _vdp_quadratic()
    prob = RoaProblem(s, V, inner=0.05, outer=2.0)
    cert = certify_roa(prob, 0.5 * _min_V_where_decrease_fails(P, s, 2.0), **QUIET)
    assert cert.certified
    path = save_certificate(cert, prob, tmp_path)
    back = RoaCertificate.from_dict(__import__("json").loads(path.read_text()))
    assert back.status is cert.status and back.level == cert.level
    assert np.array_equal(back.inner_ellipse.P, cert.inner_ellipse.P)
    again = recheck_certificate(path, **QUIET)
    assert again.certified and again.level == cert.level
    # tampering with the saved V is detected by its hash
    V2 = quadratic_lyapunov(0.5 * P)
    V2.save(tmp_path / "V.json")
    refused = recheck_certificate(path, **QUIET)
    assert not refused.certified and "changed" in refused.reason


def test_recheck_checks_the_saved_inner_ellipse_without_a_search(tmp_path, monkeypatch):
    """Condition (c) is re-checked for the saved P in its saved form, not searched again: a
    certificate.json whose P was replaced by one that fails (P A + AᵀP not negative
    definite at 0) or by an indefinite matrix is not certified any more."""
    import json

    import nlyap_opt.certification.roa as roa

    s, V, P = _vdp_quadratic()
    prob = RoaProblem(s, V, inner=0.05, outer=2.0)
    cert = certify_roa(prob, 0.5 * _min_V_where_decrease_fails(P, s, 2.0), **QUIET)
    assert cert.certified and cert.inner_ellipse.form in ("minors", "frobenius")
    path = save_certificate(cert, prob, tmp_path)
    calls = []
    real = roa._inner_ellipse
    monkeypatch.setattr(roa, "_inner_ellipse", lambda *a, **k: calls.append(a[2]) or real(*a, **k))
    again = recheck_certificate(path, **QUIET)
    assert again.certified and len(calls) == 1
    np.testing.assert_array_equal(calls[0], cert.inner_ellipse.P)
    A = np.array(ca.Function("J", [s.x], [ca.jacobian(s.f, s.x)])(np.zeros(2)), dtype=float)
    bad = np.diag([1.0, 100.0])
    assert np.linalg.eigvalsh(bad @ A + A.T @ bad)[-1] > 0     # fails at the origin itself
    d = json.loads(path.read_text())
    for P_bad, words in ((bad, "counterexample"), (np.diag([1.0, -1.0]), "positive definite")):
        d["inner_ellipse"]["P"] = P_bad.tolist()
        path.write_text(json.dumps(d))
        refused = recheck_certificate(path, **QUIET)
        assert not refused.certified and "(c)" in refused.reason and words in refused.reason


def test_recheck_rejects_non_certificates(tmp_path):
    (tmp_path / "c.json").write_text('{"a": 1}')
    with pytest.raises(ConfigError):
        recheck_certificate(tmp_path / "c.json", **QUIET)
    (tmp_path / "d.json").write_text('{"a": ')
    with pytest.raises(ConfigError):
        recheck_certificate(tmp_path / "d.json", **QUIET)
    with pytest.raises(ConfigError):
        recheck_certificate(tmp_path / "missing.json", **QUIET)


def test_non_network_V_is_saved_as_data_and_rechecked_and_no_casadi_binary_is_loaded(
        tmp_path):
    """A V that is only a CasADi expression (SOS polynomial) is saved as the data of its
    scalar graph (``V.sx.json``) and re-checked from it. A certificate naming a CasADi
    serialised Function (``kind: casadi``, which can open a shared library or start a
    compiler when loaded) is refused without loading it, and so is an ``sx`` file with an
    operation outside the op table."""
    from nlyap_opt.certification.certificate import sha256_file

    s, V, P = _vdp_quadratic()

    class Poly:
        def casadi(self, x):
            return ca.mtimes([x.T, ca.DM(P), x])

    prob = RoaProblem(s, Poly(), inner=0.05, outer=2.0)
    cert = certify_roa(prob, 0.5 * _min_V_where_decrease_fails(P, s, 2.0), **QUIET)
    assert cert.certified
    path = save_certificate(cert, prob, tmp_path)
    d = json.loads(path.read_text())
    assert d["artifacts"]["V"]["kind"] == "sx" and not (tmp_path / "V.casadi").exists()
    again = recheck_certificate(path, **QUIET)
    assert again.certified and again.level == cert.level
    # a CasADi binary, hashed and named in the certificate: never loaded
    x = ca.SX.sym("x", 2)
    ca.Function("V", [x], [ca.mtimes([x.T, ca.DM(P), x])]).save(str(tmp_path / "V.casadi"))
    loads = []
    real = ca.Function.load
    try:
        ca.Function.load = staticmethod(lambda *a: loads.append(a) or real(*a))
        d["artifacts"]["V"] = {"file": "V.casadi", "sha256": sha256_file(tmp_path / "V.casadi"),
                               "kind": "casadi"}
        path.write_text(json.dumps(d))
        refused = recheck_certificate(path, **QUIET)
    finally:
        ca.Function.load = real
    assert not refused.certified and "not loaded" in refused.reason and not loads
    # an sx file with an operation that is not arithmetic
    data = json.loads((tmp_path / "V.sx.json").read_text())
    data["instructions"][1][0] = "OP_CALL"
    (tmp_path / "V.sx.json").write_text(json.dumps(data))
    d["artifacts"]["V"] = {"file": "V.sx.json", "sha256": sha256_file(tmp_path / "V.sx.json"),
                           "kind": "sx"}
    path.write_text(json.dumps(d))
    bad = recheck_certificate(path, **QUIET)
    assert not bad.certified and "unknown operation 'OP_CALL'" in bad.reason


def test_artifacts_outside_the_directory_pipes_and_edited_number_types_are_refused(tmp_path):
    """An artifact name with a directory part (absolute, ``../``), a named pipe in place of
    an artifact (refused without waiting on it), a level written as a string or a boolean
    and an assumption list without one the proof rests on never re-check as certified."""
    import os

    from nlyap_opt.certification.certificate import sha256_file

    s, V, P = _vdp_quadratic()
    prob = RoaProblem(s, V, inner=0.05, outer=2.0)
    cert = certify_roa(prob, 0.5 * _min_V_where_decrease_fails(P, s, 2.0), **QUIET)
    path = save_certificate(cert, prob, tmp_path / "run")
    good = json.loads(path.read_text())
    assert recheck_certificate(path, **QUIET).certified
    vfile = good["artifacts"]["V"]["file"]
    outside = tmp_path / "elsewhere.json"
    outside.write_bytes((tmp_path / "run" / vfile).read_bytes())
    for name in (str(outside), "../elsewhere.json"):
        d = json.loads(json.dumps(good))
        d["artifacts"]["V"]["file"] = name
        path.write_text(json.dumps(d))
        r = recheck_certificate(path, **QUIET)
        assert not r.certified and "no directory part" in r.reason
    os.mkfifo(tmp_path / "run" / "pipe.json")
    d = json.loads(json.dumps(good))
    d["artifacts"]["V"]["file"] = "pipe.json"
    path.write_text(json.dumps(d))
    r = recheck_certificate(path, **QUIET)            # returns: nothing waits on the pipe
    assert not r.certified and "not a regular file" in r.reason
    for level in (str(good["level"]), True):
        d = json.loads(json.dumps(good))
        d["level"] = level
        path.write_text(json.dumps(d))
        with pytest.raises(ConfigError, match="level must be a number"):
            recheck_certificate(path, **QUIET)
    assert sha256_file(tmp_path / "run" / vfile) == good["artifacts"]["V"]["sha256"]
    # an assumption the proof rests on, removed from the list: refused; one added: kept
    assert good["assumptions"]
    d = json.loads(json.dumps(good))
    d["assumptions"] = d["assumptions"][1:]
    path.write_text(json.dumps(d))
    r = recheck_certificate(path, **QUIET)
    assert not r.certified and "assumptions" in r.reason
    d["assumptions"] = good["assumptions"] + ["the run also assumed nothing else"]
    path.write_text(json.dumps(d))
    assert recheck_certificate(path, **QUIET).certified


def test_lyapunov_matrix_is_the_lyapunov_solution():
    A = np.array([[0.0, 1.0], [-2.0, -3.0]])
    P = lyapunov_matrix(A)
    assert np.allclose(A.T @ P + P @ A, -np.eye(2), atol=1e-12)


def test_inner_radius_is_chosen_by_the_tool_without_retraining():
    """ε = 1.2 is refused for the Van der Pol LQR quadratic at level 2 (Ω_2 does not hold
    B_1.2, and condition (c) fails on so large an ellipse: every candidate quadratic
    increases somewhere on it, sampled V̇_q up to 0.28); the same V certifies with a
    smaller ε, and the certificate says which and why."""
    from nlyap_opt.certification.certificate import certify_with_inner_search
    from nlyap_opt.certification.roa import certify_inner_ellipse

    s, V, P = _vdp_quadratic()
    prob = RoaProblem(s, V, inner=1.2, outer=2.0)
    refused = certify_roa(prob, 2.0, **QUIET)
    assert not refused.certified and "inner ball" in refused.reason
    assert certify_inner_ellipse(s, None, 1.2)["status"] == "inner ellipse counterexample"
    cert = certify_with_inner_search(prob, 2.0, **QUIET)
    assert cert.certified and cert.inner < 1.2
    assert any("chosen by the tool" in a for a in cert.assumptions)
    tried = cert.history[-1]["inner_radius_search"]
    assert tried[0]["inner"] == 1.2 and tried[-1]["inner"] == cert.inner
    # and it is a real certificate: re-check it at its own radius
    again = certify_roa(RoaProblem(s, V, inner=cert.inner, outer=2.0), cert.level, **QUIET)
    assert again.certified


def test_a_radius_refuted_by_an_earlier_counterexample_is_not_searched():
    """V = ‖x‖²: a counterexample x with ‖x‖ = 0.5 (V = 0.25) refutes every level ≥ 0.25 at
    every radius ε ≤ 0.5; a radius needs a level above its inner ball's (ε²), so ε = 0.5
    cannot certify, while ε = 0.1 (levels in (0.01, 0.25) remain) and ε = 0.6 (the point is
    inside the ball) may."""
    from nlyap_opt.certification.certificate import _refuted_radius
    from nlyap_opt.design.control import quadratic_lyapunov
    x = ca.SX.sym("x", 2)
    s = systems.System("lin2", x, None, -x, state_box=[[-1, 1]] * 2)
    prob = RoaProblem(s, quadratic_lyapunov(np.eye(2)), None, None, inner=0.1, outer=1.0)
    dec = prob.decrease()
    cex = [np.array([[0.3, 0.4]])]
    assert _refuted_radius(prob, dec, 0.1, cex) == ("", pytest.approx(0.25))   # start below
    why, below = _refuted_radius(prob, dec, 0.5, cex)
    assert "refutes every level" in why and below == pytest.approx(0.25)
    assert _refuted_radius(prob, dec, 0.6, cex) == ("", np.inf)
    assert _refuted_radius(prob, dec, 0.5, []) == ("", np.inf)


def test_sx_files_rebuild_exactly_or_are_refused_and_huge_numbers_are_one_line_errors(
        tmp_path):
    """An sx file is taken only if its instructions rebuild to themselves: ``x/x`` (which
    CasADi would fold to 1) and an extra argument are refused, as is a constant of 400
    digits; a certificate holding an integer of thousands of digits is a ConfigError."""
    from nlyap_opt.kernel import sxjson

    x = ca.SX.sym("x", 2)
    good = sxjson.to_json(ca.Function("V", [x], [x[0] * x[1] + 2.5 * x[0] ** 2]))
    assert sxjson.to_json(sxjson.from_json(json.loads(json.dumps(good)))) == good
    folded = dict(good, registers=2, instructions=[["OP_INPUT", [0], [0, 0]],
                                                   ["OP_DIV", [1], [0, 0]],
                                                   ["OP_OUTPUT", [0, 0], [1]]])
    with pytest.raises(ConfigError, match="rebuild to themselves"):
        sxjson.from_json(folded)
    extra = json.loads(json.dumps(good))
    k = next(j for j, r in enumerate(extra["instructions"]) if r[0] == "OP_MUL")
    extra["instructions"][k][2].append(0)
    with pytest.raises(ConfigError, match="two arguments"):
        sxjson.from_json(extra)
    big = json.loads(json.dumps(good))
    big["instructions"].insert(0, ["OP_CONST", [0], [], 10**400])
    with pytest.raises(ConfigError, match="finite number"):
        sxjson.from_json(big)
    (tmp_path / "certificate.json").write_text('{"level": ' + "9" * 5000 + "}")
    with pytest.raises(ConfigError, match="cannot be read"):
        recheck_certificate(tmp_path, **QUIET)


def test_an_atomic_write_onto_a_directory_names_the_file(tmp_path):
    """A directory where a run's JSON file goes: one error naming that file (not the
    temporary one the write goes through), and no temporary file left behind."""
    from nlyap_opt.certification.certificate import write_json_atomic
    from nlyap_opt.kernel.errors import ConfigError

    (tmp_path / "certificate.json").mkdir()
    with pytest.raises(ConfigError, match=r"certificate\.json is a directory; give the path"):
        write_json_atomic(tmp_path / "certificate.json", {"a": 1})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["certificate.json"]
    write_json_atomic(tmp_path / "other.json", {"a": 1})
    assert (tmp_path / "other.json").read_text().startswith("{")
