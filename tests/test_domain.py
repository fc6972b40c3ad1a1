"""Verification domains D (ball, box, ellipsoid) and initial sets X_I (METHOD §General
domains): the sets' geometry against their CasADi constraints, condition (b) on every face
of a box, X_I ⊆ Ω_c, the run configuration, and a box-domain run end to end."""

import json
import shutil
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import systems
from nlyap_opt.certification.certificate import (
    CertStatus,
    RoaProblem,
    certify_roa,
    recheck_certificate,
)
from nlyap_opt.certification.roa import candidate_level, certify_level
from nlyap_opt.design.control import lqr, quadratic_lyapunov
from nlyap_opt.interface.cli import main
from nlyap_opt.kernel.domain import Ball, Box, Ellipsoid, parse_set
from nlyap_opt.kernel.errors import ConfigError
from nlyap_opt.workflow.configs import domain_of, make_config

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"

SETS = [
    Ball(1.5, 2),
    Ball(0.7, 3, centre=[0.2, -0.1, 0.3]),
    Box([[-3.5, 3.5], [-0.5, 0.5]]),
    Box([[-1.0, 2.0], [-0.3, 0.1], [-2.0, 0.5]]),
    Ellipsoid.from_semi_axes([2.0, 0.5]),
    Ellipsoid([[2.0, 0.6, 0.0], [0.6, 1.0, 0.2], [0.0, 0.2, 0.5]], centre=[0.1, 0.0, -0.2]),
]


def _g_values(reg, pts, which="inequalities"):
    x = ca.SX.sym("x", reg.n)
    gs = [g for g, _ in getattr(reg, which)(x)]
    F = ca.Function("g", [x], [ca.vertcat(*gs)])
    return np.array(F(pts.T)).T                     # (N, k)


@pytest.mark.parametrize("reg", SETS, ids=lambda r: r.describe())
def test_membership_agrees_with_the_constraints_the_verifier_gets(reg):
    rng = np.random.default_rng(0)
    bb = reg.bounding_box()
    pts = bb[:, 0] - 0.2 + (bb[:, 1] - bb[:, 0] + 0.4) * rng.random((4000, reg.n))
    g = _g_values(reg, pts)
    inside = reg.contains(pts)
    assert np.array_equal(inside, np.all(g <= 0, axis=1))
    assert inside.any() and (~inside).any()
    # the set lies in its bounding box; the region constraints on that box give the set
    assert np.all((pts[inside] >= bb[:, 0]) & (pts[inside] <= bb[:, 1]))
    in_bb = np.all((pts >= bb[:, 0]) & (pts <= bb[:, 1]), axis=1)
    region = _g_values(reg, pts, "constraints") if reg.constraints(ca.SX.sym("x", reg.n)) \
        else np.zeros((len(pts), 0))
    assert np.array_equal(inside, in_bb & np.all(region <= 0, axis=1))


@pytest.mark.parametrize("reg", SETS, ids=lambda r: r.describe())
def test_samples_lie_in_the_set_outside_the_inner_ball_and_on_the_boundary(reg):
    rng = np.random.default_rng(1)
    inner = 0.05 if reg.inradius() > 0 else 0.0
    pts = reg.sample(3000, rng, inner)
    assert pts.shape == (3000, reg.n)
    assert reg.contains(pts).all()
    assert np.all(np.linalg.norm(pts, axis=1) >= inner)
    # uniform: the sample mean is near the centre of mass (the centre for these symmetric sets)
    centre = reg.bounding_box().mean(axis=1)
    spread = reg.bounding_box()[:, 1] - reg.bounding_box()[:, 0]
    assert np.all(np.abs(pts.mean(axis=0) - centre) < 0.05 * spread)
    bnd = reg.sample_boundary(2000, rng)
    g = _g_values(reg, bnd)
    assert np.all(np.max(g, axis=1) <= 1e-12)           # in the set ...
    assert np.all(np.max(g, axis=1) >= -1e-12)          # ... and on its boundary
    # every boundary piece of the verifier holds every boundary sample of its own kind
    x = ca.SX.sym("x", reg.n)
    for box, cons, _ in reg.boundary_pieces(x):
        on = np.all((bnd >= box[:, 0]) & (bnd <= box[:, 1]), axis=1)
        if cons:
            F = ca.Function("c", [x], [ca.vertcat(*[c for c, _ in cons])])
            on &= np.all(np.array(F(bnd.T)).T <= 1e-12, axis=1)
        assert on.any()


@pytest.mark.parametrize("reg", SETS, ids=lambda r: r.describe())
def test_inradius_ball_is_inside_and_json_round_trips(reg):
    rng = np.random.default_rng(2)
    if reg.inradius() > 0:
        d = rng.standard_normal((2000, reg.n))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        assert reg.contains(d * reg.inradius() * (1 - 1e-9)).all()
        assert not reg.contains(d * reg.max_norm() * 1.0001).any()
    again = parse_set(json.loads(json.dumps(reg.to_dict())), reg.n, domain=False)
    assert again == reg
    assert again.contains(reg.sample(100, rng)).all()


@pytest.mark.parametrize("spec,needle", [
    ({"type": "boxx"}, "must be one of"),
    ("box", "must be one of"),
    ({"type": "box", "box": [[-1, 1]]}, "2 rows"),
    ({"type": "box", "box": [[1, -1], [-1, 1]]}, "lo < hi"),
    ({"type": "box", "box": [[0.5, 1], [-1, 1]]}, "origin"),
    ({"type": "ball", "radius": -1}, "> 0"),
    ({"type": "ball", "radius": float("nan")}, "finite"),
    ({"type": "ball", "radius": 1, "center": [0, 0]}, "unknown key"),
    ({"type": "ellipsoid", "semi_axes": [1, 0]}, "> 0"),
    ({"type": "ellipsoid", "semi_axes": [1, 1], "matrix": [[1, 0], [0, 1]]}, "exactly one"),
    ({"type": "ellipsoid", "matrix": [[1, 2], [2, 1]]}, "positive definite"),
    ({"type": "ellipsoid", "matrix": [[1, 0.1], [0, 1]]}, "symmetric"),
    ({"type": "ball", "radius": 1, "centre": [3, 0]}, "origin"),
])
def test_malformed_sets_are_refused_with_the_fix(spec, needle):
    with pytest.raises(ConfigError, match=needle):
        parse_set(spec, 2)


def _quadratic_problem(level_domain):
    """V = x1² + x2² with a decrease everywhere (lie = −2V): only (b) can fail."""
    x = ca.MX.sym("x", 2)
    V = ca.sumsqr(x)
    return x, V, -2 * V


@pytest.mark.parametrize("domain,edge", [
    (Box([[-1.0, 1.0], [-2.0, 2.0]]), 1.0),               # min of V on the faces: 1
    (Ellipsoid.from_semi_axes([1.0, 2.0]), 1.0),
    (Box([[-3.0, 0.5], [-2.0, 2.0]]), 0.25),              # the near face x1 = 0.5
])
def test_containment_is_checked_on_every_face(domain, edge):
    x, V, lie = _quadratic_problem(domain)
    ok = certify_level(x, V, lie, level=0.9 * edge, inner=0.1, domain=domain, margin=0.0,
                       max_tries=1, shrink=0.0, log=lambda m: None)
    assert ok.status == "certified"
    bad = certify_level(x, V, lie, level=1.1 * edge, inner=0.1, domain=domain, margin=0.0,
                        max_tries=1, shrink=0.0, log=lambda m: None)
    assert bad.status != "certified"
    if isinstance(domain, Box):
        # a face is a box of its own: a confirmed point on it, with V <= level
        assert bad.history[-1]["containment"] == "counterexample"
        p = bad.counterexamples[0]
        assert domain.contains(p, tol=1e-9)[0] and p @ p <= 1.1 * edge
        assert not domain.contains(p * (1 + 1e-6))[0]
    else:
        # a curved surface is an equality: no float point is provably on it, so the
        # verdict is "unknown" (never "verified")
        assert bad.history[-1]["containment"] in ("unknown", "counterexample")
    # the level NLP finds the same edge
    cand = candidate_level(x, V, lie, inner=0.1, domain=domain, n_samples=4000)
    assert cand.source == "sphere" and cand.level == pytest.approx(edge, rel=1e-6)


def _vdp_problem(**kw):
    s = systems.get("van_der_pol")
    V = quadratic_lyapunov(lqr(s).P)
    return RoaProblem(s, V, inner=0.1, **kw)


def test_initial_set_must_lie_in_the_certified_set():
    D = Box([[-1.5, 1.5], [-1.0, 1.0]])
    small = _vdp_problem(domain=D, initial_set={"type": "ball", "radius": 0.4})
    cert = certify_roa(small, 1.0, search=True, log=lambda m: None)
    assert cert.certified and cert.checks["(d) X_I ⊆ Ω_c"] == "verified"
    # the same V and level with an X_I that reaches beyond Ω_c: refused, saying why
    big = _vdp_problem(domain=D, initial_set={"type": "box", "box": [[-1.4, 1.4], [-0.9, 0.9]]})
    ref = certify_roa(big, cert.level, log=lambda m: None)
    assert ref.status in (CertStatus.COUNTEREXAMPLE, CertStatus.NOT_CERTIFIED)
    assert "initial set" in ref.reason and ref.checks["(d) X_I ⊆ Ω_c"] != "verified"
    assert not ref.contains(np.zeros((1, 2))).any()
    # the certified set lies in D ∪ E
    pts = D.sample(5000, np.random.default_rng(0))
    inside = cert.contains(np.vstack([pts, pts * 3]))
    assert np.all(D.contains(np.vstack([pts, pts * 3]))[inside]
                  | cert.inner_ellipse.contains(np.vstack([pts, pts * 3]))[inside])


def test_a_domain_replaces_the_ball_in_the_run_config(tmp_path):
    box = {"type": "box", "box": [[-1.5, 1.5], [-1.0, 1.0]]}
    cfg = make_config("van_der_pol", "fast", overrides={"domain": box})
    assert cfg["outer"] is None and cfg["domain"] == box
    D, XI = domain_of(cfg, 2)
    assert D == Box(box["box"]) and XI is None
    # a radius given later replaces the domain again
    f = tmp_path / "c.json"
    f.write_text(json.dumps({"outer": 0.9}))
    cfg2 = make_config("van_der_pol", "fast", overrides={"outer": 0.9})
    assert cfg2["outer"] == 0.9 and cfg2.get("domain") is None
    with pytest.raises(ConfigError, match="both 'outer'"):
        make_config("van_der_pol", "fast", overrides={"domain": box, "outer": 1.0})
    with pytest.raises(ConfigError, match="inner ball"):
        make_config("van_der_pol", "fast",
                    overrides={"domain": {"type": "box", "box": [[-0.2, 1], [-1, 1]]}})
    with pytest.raises(ConfigError, match="initial set"):
        make_config("van_der_pol", "fast", overrides={
            "domain": box, "initial_set": {"type": "ball", "radius": 1.2}})
    # a later domain replaces an earlier one whole (no merged keys)
    cfg3 = make_config("van_der_pol", "fast", file=None, overrides={
        "domain": {"type": "ellipsoid", "semi_axes": [1.5, 1.0]}})
    assert domain_of(cfg3, 2)[0] == Ellipsoid.from_semi_axes([1.5, 1.0])


def test_bad_domain_on_the_command_line_is_one_line_exit_3(tmp_path, capsys):
    f = tmp_path / "c.json"
    f.write_text(json.dumps({"domain": {"type": "box", "box": [[-1, 1]]}}))
    code = main(["run", "van_der_pol", "--preset", "fast", "--config", str(f),
                 "--out", str(tmp_path / "r")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 3 and len(err) == 1 and "domain.box" in err[0]
    assert not (tmp_path / "r" / "V.json").exists()


@pytest.mark.slow  # the default tier stays within 5 min on 2 cores
def test_box_domain_example_certifies_its_initial_set_and_rechecks(tmp_path, capsys):
    """examples/box_domain.toml (Khalil's x1 x2 < 2): a box domain and an initial set."""
    spec = tmp_path / "box_domain.toml"
    shutil.copy(EXAMPLES / "box_domain.toml", spec)
    out = tmp_path / "run"
    # a fast variant: fewer states, steps and iterations, and no SOS stage (its V-s rounds
    # inside a box domain are tested in test_sos_auto; here the neural V must hold D's faces)
    cfg = tmp_path / "fast.json"
    cfg.write_text(json.dumps({"train": {"steps": 600}, "cegis": {"iterations": 1,
                                                                    "samples": 6000},
                               "eval_points": 10000, "sos": {"degree": 0}}))
    assert main(["run", str(spec), "--known-dynamics", "--config", str(cfg),
                 "--out", str(out)]) == 0
    cert = json.loads((out / "certificate.json").read_text())
    assert cert["status"] == "certified"
    assert cert["domain"] == {"type": "box", "box": [[-3.5, 3.5], [-0.5, 0.5]]}
    assert cert["checks"]["(b) V > level on ∂D"] == "verified"
    assert cert["checks"]["(d) X_I ⊆ Ω_c"] == "verified"
    # the true ROA {x1 x2 < 2} holds D, so the share is of D's area (7 × 1)
    assert cert["true_roa_area"] == pytest.approx(7.0, rel=0.02)
    assert cert["certified_points_converge_in_simulation"]
    report = (out / "report.md").read_text()
    assert "D = box [-3.5, 3.5] × [-0.5, 0.5]" in report and "(d) initial set" in report
    assert recheck_certificate(out, log=lambda m: None).certified
    # a claim on a smaller domain is re-checked, not trusted: Ω_c crosses its faces
    d = json.loads((out / "certificate.json").read_text())
    d["domain"] = {"type": "box", "box": [[-1.0, 1.0], [-0.5, 0.5]]}
    d["initial_set"] = None
    (out / "certificate.json").write_text(json.dumps(d))
    again = recheck_certificate(out, log=lambda m: None)
    assert not again.certified
    assert again.checks["(b) V > level on ∂D"] == "counterexample"


@pytest.mark.slow  # 20-40 s: the default tier stays near 5 min on 2 cores
def test_compare_rows_are_certified_on_the_declared_domain(tmp_path):
    from baselines.compare import compare

    box = {"type": "box", "box": [[-1.5, 1.5], [-1.2, 1.2]]}
    cfg = make_config("van_der_pol", "fast", overrides={"domain": box})
    rows = compare("van_der_pol", cfg, tmp_path, log=lambda m: None, include_neural=False)
    certified = [r for r in rows if r.certified]
    assert any(r.method.startswith("sos") for r in certified)
    D = Box(box["box"])
    pts = D.sample(4000, np.random.default_rng(0))
    for r in certified:   # the LQR and the SOS rows: the same D, re-checkable
        saved = json.loads(Path(r.extra["certificate"]).read_text())
        assert saved["domain"] == box
        cert = recheck_certificate(r.extra["certificate"], log=lambda m: None)
        assert cert.certified
        far = np.vstack([pts, 2 * pts])
        inside = cert.contains(far)
        assert np.all(D.contains(far)[inside] | cert.inner_ellipse.contains(far)[inside])
    md = (tmp_path / "comparison.md").read_text()
    assert "within D = box [-1.5, 1.5] × [-1.2, 1.2]" in md
