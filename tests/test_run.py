"""`nlyap run` on fast configurations: certified, re-verifiable, resumable, sound in simulation."""

import json

import numpy as np
import pytest

import systems
from nlyap_opt.cli import main
from nlyap_opt.configs import get_config
from nlyap_opt.network import Network
from nlyap_opt.pipeline import run
from nlyap_opt.roa import grid_points
from nlyap_opt.simulate import simulate_converges

CERT_KEYS = {"status", "level", "inner_radius", "outer_radius", "margin", "M",
             "certified_area", "true_roa_area", "assumptions", "true_dynamics_check",
             "seconds"}


def _certified_points(out, cert, n=60):
    V = Network.load(out / "V.json")
    box = np.asarray(cert["eval_box"])
    pts, _ = grid_points(box, n)
    inside = (np.linalg.norm(pts, axis=1) <= cert["outer_radius"]) & \
        (V.numpy(pts)[:, 0] <= cert["level"])
    ie = cert["inner_ellipse"]
    inside |= np.einsum("ij,jk,ik->i", pts, np.asarray(ie["P"]), pts) <= ie["level"]
    return pts[inside]


@pytest.fixture(scope="module")
def known_runs(tmp_path_factory):
    out = {}
    for name in systems.names():
        d = tmp_path_factory.mktemp(name)
        cert = run(name, get_config(name, "fast"), d, known_dynamics=True, log=lambda m: None)
        out[name] = (d, cert)
    return out


@pytest.mark.parametrize("name", systems.names())
def test_fast_known_dynamics_run_is_certified(known_runs, name):
    d, cert = known_runs[name]
    assert cert["status"] == "certified", cert["status"]
    assert CERT_KEYS <= set(cert)
    saved = json.loads((d / "certificate.json").read_text())
    assert saved["status"] == "certified" and saved["level"] == cert["level"]
    for f in ("V.json", "report.md", "roa.png", "cegis.json"):
        assert (d / f).exists(), f
    assert 0 < cert["certified_area"] <= cert["true_roa_area"] * 1.02
    assert cert["inner_ellipse"]["status"] == "certified"


@pytest.mark.parametrize("name", systems.names())
def test_certified_points_converge_in_simulation(known_runs, name):
    """No certified point may diverge (simulated with the true f and the saved controller)."""
    d, cert = known_runs[name]
    s = systems.get(name)
    ctrl = Network.load(d / "controller.json") if (d / "controller.json").exists() else None
    pts = _certified_points(d, cert)
    assert len(pts) > 50

    def rhs(z):
        return s.evaluate(z, None if ctrl is None else ctrl.numpy(z))

    ok = simulate_converges(rhs, pts, t_final=80.0, dt=0.02, tol=1e-3)
    assert ok.all(), pts[~ok][:5]


@pytest.mark.parametrize("name", systems.names())
def test_saved_certificate_reverifies_with_cli(known_runs, name, tmp_path):
    d, cert = known_runs[name]
    args = ["verify", "--system", name, "--lyapunov", str(d / "V.json"),
            "--inner", str(cert["inner_radius"]), "--outer", str(cert["outer_radius"]),
            "--level", repr(cert["level"]), "--json", str(tmp_path / "v.json")]
    if (d / "controller.json").exists():
        args += ["--controller", str(d / "controller.json")]
    assert main(args) == 0
    res = json.loads((tmp_path / "v.json").read_text())
    assert res["status"] == "verified" and res["counterexample"] is None
    # and a level far above the certified one is refuted (exit code 1) or undecided (2)
    args[args.index("--level") + 1] = repr(cert["level"] * 50)
    assert main(args[:-2]) in (1, 2)


def test_run_resumes_from_saved_stages(known_runs):
    d, cert = known_runs["van_der_pol"]
    logs = []
    again = run("van_der_pol", get_config("van_der_pol", "fast"), d, known_dynamics=True,
                log=logs.append)
    assert any("[cegis] loaded" in m for m in logs)
    assert again["level"] == cert["level"]


def test_changed_training_settings_rerun_the_cegis_stage(known_runs, tmp_path):
    import shutil

    d, _ = known_runs["van_der_pol"]
    shutil.copytree(d, tmp_path / "run")
    cfg = get_config("van_der_pol", "fast")
    cfg["train"]["steps"] += 1
    logs = []
    run("van_der_pol", cfg, tmp_path / "run", known_dynamics=True, log=logs.append)
    assert not any("[cegis] loaded" in m for m in logs)
    assert any("cegis iteration 0" in m for m in logs)


@pytest.fixture(scope="module")
def learned_runs(tmp_path_factory):
    out = {}
    for name in systems.names():
        d = tmp_path_factory.mktemp(name + "_learned")
        cert = run(name, get_config(name, "fast"), d, known_dynamics=False, log=lambda m: None)
        out[name] = (d, cert)
    return out


@pytest.mark.parametrize("name", systems.names())
def test_fast_learned_dynamics_run_is_certified(learned_runs, name, tmp_path):
    d, cert = learned_runs[name]
    assert cert["status"] == "certified", cert["status"]
    bounds = json.loads((d / "bounds.json").read_text())
    assert cert["eta"] == bounds["eta"] > 0
    assert any("Assumption 3" in a for a in cert["assumptions"])
    assert cert["true_dynamics_check"] is not None
    # re-verify the learned-dynamics certificate from the saved files
    args = ["verify", "--system", name, "--lyapunov", str(d / "V.json"),
            "--dynamics", str(d / "dynamics.json"), "--eta", repr(cert["eta"]),
            "--smoothing", repr(cert["norm_smoothing"]),
            "--inner", str(cert["inner_radius"]), "--outer", str(cert["outer_radius"]),
            "--level", repr(cert["level"])]
    if (d / "controller.json").exists():
        args += ["--controller", str(d / "controller.json")]
    assert main(args) == 0
    # the same networks with a much larger η are not certified at that level
    args[args.index("--eta") + 1] = repr(cert["eta"] * 1000 + 1.0)
    assert main(args) in (1, 2)
