"""`nlyap run` on fast configurations: certified, re-verifiable, resumable, sound in simulation."""

import json

import numpy as np
import pytest
from certcheck import assert_fast_certificate
from forge import forge_stage_file

import systems
from nlyap_opt.certification.roa import grid_points
from nlyap_opt.interface.cli import main
from nlyap_opt.kernel.network import Network
from nlyap_opt.kernel.provenance import fingerprint, fingerprint_id
from nlyap_opt.kernel.simulate import simulate_converges
from nlyap_opt.workflow.configs import get_config, make_config
from nlyap_opt.workflow.pipeline import run

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
def known_runs(fast_run):
    return {name: fast_run(name, known=True) for name in systems.SEED_SYSTEMS}


@pytest.mark.parametrize("name", systems.SEED_SYSTEMS)
def test_fast_known_dynamics_run_is_certified(known_runs, name):
    d, cert = known_runs[name]
    assert cert["status"] == "certified", cert["status"]
    assert CERT_KEYS <= set(cert)
    saved = json.loads((d / "certificate.json").read_text())
    assert saved["status"] == "certified" and saved["level"] == cert["level"]
    assert saved["provenance"] == fingerprint()        # what determined these numbers
    report = (d / "report.md").read_text()
    assert f"fingerprint: {fingerprint_id()}" in report
    # with an input, the true ROA is said to be that of the certificate's closed loop
    assert ("under the certificate's controller κ" in report) == bool(systems.get(name).nu)
    for f in ("V.json", "report.md", "roa.png", "cegis.json"):
        assert (d / f).exists(), f
    assert 0 < cert["certified_area"] <= cert["true_roa_area"] * 1.02
    assert cert["inner_ellipse"]["status"] == "certified"


@pytest.mark.parametrize("name", systems.SEED_SYSTEMS)
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


@pytest.mark.parametrize("name", systems.SEED_SYSTEMS)
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
                log=logs.append).summary
    assert any("[cegis] loaded" in m for m in logs)
    assert again["level"] == cert["level"]


def test_changed_training_settings_rerun_the_cegis_stage(known_runs, tmp_path, log_until):
    import shutil

    d, _ = known_runs["van_der_pol"]
    shutil.copytree(d, tmp_path / "run")
    steps = get_config("van_der_pol", "fast").train.steps
    cfg = make_config("van_der_pol", "fast", overrides={"train": {"steps": steps + 1}})
    log = log_until("cegis iteration 0")     # CEGIS trains again: stop there
    with pytest.raises(KeyboardInterrupt):
        run("van_der_pol", cfg, tmp_path / "run", known_dynamics=True, log=log)
    assert not any("[cegis] loaded" in m for m in log.lines)
    assert any("cegis iteration 0" in m for m in log.lines)


@pytest.fixture(scope="module")
def learned_runs(fast_run):
    return fast_run.many(systems.SEED_SYSTEMS)    # two at a time


@pytest.mark.parametrize("name", systems.SEED_SYSTEMS)
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


# ------------------------------------------------------------------ trust boundary (issue 12)
def _copy_run(known_runs, tmp_path, name="van_der_pol"):
    import shutil

    d, cert = known_runs[name]
    shutil.copytree(d, tmp_path / "run")
    return tmp_path / "run", cert


def test_certificate_rechecks_from_its_artifacts(known_runs):
    from nlyap_opt.certification.certificate import recheck_certificate

    for name, (d, cert) in known_runs.items():
        again = recheck_certificate(d / "certificate.json", log=lambda m: None)
        assert again.certified, (name, again.reason)
        assert again.level == cert["level"]


def test_tampered_V_is_never_certified_on_resume(known_runs, tmp_path):
    """Replace V.json in a finished run: the rerun recomputes CEGIS (saying so) and the
    final certificate is that of the V on disk, re-verified."""
    from nlyap_opt.certification.certificate import recheck_certificate

    d, cert = _copy_run(known_runs, tmp_path)
    V = Network.load(d / "V.json")
    V.layers[0].weight[...] *= 1.5           # a different V (V(0) = 0 still by construction)
    V.save(d / "V.json")
    logs = []
    res = run("van_der_pol", get_config("van_der_pol", "fast"), d, known_dynamics=True,
              log=logs.append)
    assert any("V.json changed" in m for m in logs), logs[:5]
    assert not any("[cegis] loaded" in m for m in logs)
    assert res.certified and recheck_certificate(d, log=lambda m: None).certified


@pytest.mark.slow  # ~50 s idle: a second learned run; the default tier stays under 5 min on 2 cores
def test_tampered_V_with_forged_stage_record_is_not_certified(known_runs, tmp_path):
    """Even with stages.json forged to match a false V, the certificate stage re-verifies."""

    d, cert = _copy_run(known_runs, tmp_path)
    V = Network.load(d / "V.json")
    for layer in V.layers:
        layer.weight[...] *= -0.05           # flat V: containment fails at the saved level
    V.save(d / "V.json")
    forge_stage_file(d, "cegis", "V.json")
    res = run("van_der_pol", get_config("van_der_pol", "fast"), d, known_dynamics=True,
              log=lambda m: None)
    if res.certified:  # only if the forged V happens to satisfy every condition itself
        from nlyap_opt.certification.certificate import recheck_certificate

        assert recheck_certificate(d, log=lambda m: None).certified
    else:
        saved = json.loads((d / "certificate.json").read_text())
        assert saved["status"] != "certified"


def test_corrupt_stage_files_are_recomputed(known_runs, tmp_path):
    d, cert = _copy_run(known_runs, tmp_path)
    (d / "stages.json").write_text('{"cegis": ')
    (d / "true_roa.npz").write_bytes(b"garbage")
    logs = []
    res = run("van_der_pol", get_config("van_der_pol", "fast"), d, known_dynamics=True,
              log=logs.append)
    assert any("unreadable" in m for m in logs)
    assert res.certified and res.summary["level"] == cert["level"]   # deterministic rerun


def test_a_true_roa_cache_with_the_right_key_but_wrong_arrays_is_simulated_again(
        known_runs, tmp_path):
    """true_roa.npz is checked, not trusted: its key alone does not make arrays of another
    shape (or type) the true ROA; the run simulates again and reports the same figures."""
    import numpy as np

    d, cert = _copy_run(known_runs, tmp_path)
    with np.load(d / "true_roa.npz") as z:
        key, mask = str(z["key"]), z["mask"]
    bad = np.ones((3, 3), bool)
    np.savez_compressed(d / "true_roa.npz", mask=bad, undecided=bad, elsewhere=bad, stays=bad,
                        key=key)
    logs = []
    res = run("van_der_pol", get_config("van_der_pol", "fast"), d, known_dynamics=True,
              log=logs.append)
    assert any("true ROA by simulation" in m for m in logs)
    assert res.summary["true_roa_area"] == cert["true_roa_area"]
    with np.load(d / "true_roa.npz") as z:
        assert np.array_equal(z["mask"], mask)


def test_second_run_into_a_locked_directory_is_refused(known_runs, tmp_path):
    import subprocess
    import sys

    from nlyap_opt.workflow.pipeline import RunLockedError

    d, _ = _copy_run(known_runs, tmp_path)
    holder = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (d / ".nlyap.lock").write_text(str(holder.pid))
        with pytest.raises(RunLockedError, match="another nlyap run"):
            run("van_der_pol", get_config("van_der_pol", "fast"), d, known_dynamics=True,
                log=lambda m: None)
    finally:
        holder.kill()
        holder.wait()
    # a stale lock (its process is gone) is taken over
    logs = []
    assert run("van_der_pol", get_config("van_der_pol", "fast"), d, known_dynamics=True,
               log=logs.append).certified
    assert any("stale lock" in m for m in logs)
    assert not (d / ".nlyap.lock").exists()


def test_out_that_is_a_file_is_an_input_error(tmp_path):
    from nlyap_opt.kernel.errors import ConfigError

    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(ConfigError, match="is a file"):
        run("van_der_pol", get_config("van_der_pol", "fast"), f, known_dynamics=True,
            log=lambda m: None)


_INTERRUPT_AT = {"controller": "saturated_controller", "cegis": "cegis",
                 "certificate": "_areas_and_checks"}   # the names the pipeline calls


def test_a_run_interrupted_in_each_stage_in_turn_resumes_to_a_certificate_that_reverifies(
        tmp_path, monkeypatch):
    """SIGINT (KeyboardInterrupt) in the controller stage, then in the CEGIS stage of the
    rerun, then in the certificate stage of the next: each rerun gets past the stage the
    last one was stopped in, no lock is left behind, and the final rerun's certificate
    re-verifies. (One fresh run per stage: the slow test below.)"""
    import nlyap_opt.workflow.pipeline as pl
    from nlyap_opt.certification.certificate import recheck_certificate

    name = "inverted_pendulum"
    cfg = get_config(name, "fast")
    for target in _INTERRUPT_AT.values():
        reached = []

        def boom(*a, target=target, **k):
            reached.append(target)
            raise KeyboardInterrupt

        with monkeypatch.context() as m:
            m.setattr(pl, target, boom)
            with pytest.raises(KeyboardInterrupt):
                run(name, cfg, tmp_path, known_dynamics=True, log=lambda m: None)
        assert reached == [target]
        assert not (tmp_path / ".nlyap.lock").exists()
    res = run(name, cfg, tmp_path, known_dynamics=True, log=lambda m: None)
    assert res.certified
    assert recheck_certificate(tmp_path, log=lambda m: None).certified


@pytest.mark.slow  # three runs: the default tier interrupts the stages of one run in turn (above)
@pytest.mark.parametrize("stage", ["controller", "cegis", "certificate"])
def test_interrupted_run_resumes_to_a_certificate_that_reverifies(stage, tmp_path,
                                                                  monkeypatch):
    """SIGINT in a stage (KeyboardInterrupt): the rerun's certificate re-verifies."""
    import nlyap_opt.workflow.pipeline as pl
    from nlyap_opt.certification.certificate import recheck_certificate

    name = "inverted_pendulum"
    cfg = get_config(name, "fast")
    target = _INTERRUPT_AT[stage]

    def boom(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(pl, target, boom)
    with pytest.raises(KeyboardInterrupt):
        run(name, cfg, tmp_path, known_dynamics=True, log=lambda m: None)
    monkeypatch.undo()
    assert not (tmp_path / ".nlyap.lock").exists()
    res = run(name, cfg, tmp_path, known_dynamics=True, log=lambda m: None)
    assert res.certified
    assert recheck_certificate(tmp_path, log=lambda m: None).certified


# ------------------------------------------------------------------ regression (issue 11)
@pytest.mark.parametrize("name", systems.SEED_SYSTEMS)
def test_fast_certificates_reach_their_floors_and_match_this_fingerprint(
        known_runs, learned_runs, name):
    """Refactors must not move a certificate. On any machine the fast presets' certificates
    reach the floors of tests/data/fast_certificates.json (certified area, η: properties
    with stated margins); on a machine whose numeric-environment fingerprint has a recorded
    reference they are the recorded ones bit for bit, networks included
    (``certcheck.assert_fast_certificate``). Another CPU, BLAS kernel or package version
    trains another φ in its last bits, so no value recorded elsewhere is compared exactly."""
    for setting, runs in (("known", known_runs), ("learned", learned_runs)):
        d, cert = runs[name]
        assert_fast_certificate(f"{name}/{setting}", cert, d)


@pytest.mark.slow  # the default tier stays within 5 min on 2 cores
def test_interrupt_after_the_dynamics_files_are_written(tmp_path, monkeypatch):
    """SIGINT right after φ's files are written but before the stage is recorded: the rerun
    learns φ again (deterministically: the same φ) and its certificate re-verifies."""
    import hashlib

    from nlyap_opt.certification.certificate import recheck_certificate
    from nlyap_opt.learned.dynamics_stage import DynamicsStage

    cfg = get_config("van_der_pol", "fast")
    save = DynamicsStage.save

    def save_then_interrupt(self, out):
        save(self, out)
        raise KeyboardInterrupt

    monkeypatch.setattr(DynamicsStage, "save", save_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        run("van_der_pol", cfg, tmp_path, log=lambda m: None)
    first = hashlib.sha256((tmp_path / "dynamics.json").read_bytes()).hexdigest()
    monkeypatch.undo()
    logs = []
    res = run("van_der_pol", cfg, tmp_path, log=logs.append)
    assert not any("[dynamics] loaded" in m for m in logs)
    assert hashlib.sha256((tmp_path / "dynamics.json").read_bytes()).hexdigest() == first
    assert res.certified and recheck_certificate(tmp_path, log=lambda m: None).certified


def test_recheck_refuses_a_certificate_whose_eta_was_lowered(learned_runs, tmp_path):
    """η is the bound the certificate rests on: a certificate.json edited to a smaller η is
    refused against the hashed bounds.json of the run, not re-verified with the lower η."""
    import shutil

    from nlyap_opt.certification.certificate import recheck_certificate

    d, cert = learned_runs["van_der_pol"]
    shutil.copytree(d, tmp_path / "run")
    assert recheck_certificate(tmp_path / "run", log=lambda m: None).certified
    c = json.loads((tmp_path / "run" / "certificate.json").read_text())
    c["eta"] = c["eta"] / 10
    (tmp_path / "run" / "certificate.json").write_text(json.dumps(c))
    again = recheck_certificate(tmp_path / "run", log=lambda m: None)
    assert not again.certified and "η" in again.reason


@pytest.mark.parametrize("edit,words", [
    (lambda b: b.update(eta=10 ** 400), "eta"),
    (lambda b: b.update(eta="0.01"), "eta must be a number"),
    (lambda b: b.update(grid=5), "'grid'"),
    (lambda b: b["grid"].update(box=[[-1, 1], [0]]), "grid.box"),
    (lambda b: b["grid"].update(box=[[-1, 10 ** 400], [-1, 1]]), "grid.box"),
], ids=["huge-eta", "text-eta", "grid-number", "ragged-box", "huge-box"])
def test_recheck_refuses_an_edited_bounds_file_whose_hash_was_updated(learned_runs, tmp_path,
                                                                      edit, words):
    """A bounds file edited together with its hash in certificate.json is refused with a
    reason (the certificate is not certified), never an internal error."""
    import hashlib
    import shutil

    from nlyap_opt.certification.certificate import recheck_certificate

    d, cert = learned_runs["van_der_pol"]
    shutil.copytree(d, tmp_path / "run")
    c = json.loads((tmp_path / "run" / "certificate.json").read_text())
    bf = tmp_path / "run" / c["artifacts"]["bounds"]["file"]
    b = json.loads(bf.read_text())
    edit(b)
    bf.write_text(json.dumps(b))
    c["artifacts"]["bounds"]["sha256"] = hashlib.sha256(bf.read_bytes()).hexdigest()
    (tmp_path / "run" / "certificate.json").write_text(json.dumps(c))
    again = recheck_certificate(tmp_path / "run", log=lambda m: None)
    assert not again.certified and "cannot be read" in again.reason, again.reason
    assert words in again.reason, again.reason


def test_recheck_refutes_a_bound_that_f_and_phi_contradict(learned_runs, tmp_path):
    """bounds.json and certificate.json edited together (hashes updated) to η smaller than
    ‖f − φ‖ somewhere: the certificate then proved decrease for φ only. The re-check compares
    f and φ at seeded points of the bound's box and withdraws it (simulate/export too)."""
    import hashlib
    import shutil

    from nlyap_opt.certification.certificate import bound_refutation, recheck_run

    d, cert = learned_runs["van_der_pol"]
    _, problem = recheck_run(d, log=lambda m: None)
    assert bound_refutation(problem) == ""          # the run's own η holds at every point
    shutil.copytree(d, tmp_path / "run")
    c = json.loads((tmp_path / "run" / "certificate.json").read_text())
    bf = tmp_path / "run" / c["artifacts"]["bounds"]["file"]
    b = json.loads(bf.read_text())
    b["eta"] = c["eta"] = 1e-12
    bf.write_text(json.dumps(b))
    c["artifacts"]["bounds"]["sha256"] = hashlib.sha256(bf.read_bytes()).hexdigest()
    (tmp_path / "run" / "certificate.json").write_text(json.dumps(c))
    again, prob = recheck_run(tmp_path / "run", log=lambda m: None)
    assert prob is None and not again.certified
    assert "‖f − φ‖ ≤ η = 1e-12" in again.reason and "does not hold" in again.reason


def _edit_run(src, dst, edit):
    """Copy a run, apply ``edit(dir, certificate dict)``, write the certificate back."""
    import shutil

    shutil.copytree(src, dst)
    c = json.loads((dst / "certificate.json").read_text())
    edit(dst, c)
    (dst / "certificate.json").write_text(json.dumps(c))
    return dst


def _shift_phi(d, c, by=0.1):
    """φ's first output moved by ``by`` (far beyond η), its hash in the certificate updated."""
    import hashlib

    f = d / c["artifacts"]["dynamics"]["file"]
    phi = json.loads(f.read_text())
    phi["layers"][-1]["bias"][0] += by
    f.write_text(json.dumps(phi))
    c["artifacts"]["dynamics"]["sha256"] = hashlib.sha256(f.read_bytes()).hexdigest()


def _drop_bound(d, c):
    c["artifacts"].pop("bounds")
    c["eta"] = 0.0
    _shift_phi(d, c)


@pytest.mark.parametrize("edit,words", [
    (_drop_bound, "lists no bound on ‖f − φ‖"),
    (_shift_phi, "is not the network that bounds.json bounds"),
], ids=["bound-removed-eta-0", "phi-changed"])
def test_recheck_refuses_learned_dynamics_without_the_bound_of_this_phi(learned_runs, tmp_path,
                                                                        edit, words):
    """η rests on bounds.json, computed for one φ: a certificate whose bound was removed (and
    η set to 0), or whose φ was replaced with its hash updated, is refused, not re-verified
    with a φ no bound covers."""
    from nlyap_opt.certification.certificate import recheck_certificate
    from nlyap_opt.interface.cli import main

    d, _ = learned_runs["van_der_pol"]
    run = _edit_run(d, tmp_path / "run", edit)
    again = recheck_certificate(run, log=lambda m: None)
    assert not again.certified and words in again.reason, again.reason
    assert main(["verify", "--certificate", str(run)]) == 2


def test_a_reversed_controller_is_a_counterexample_with_the_point_named(learned_runs,
                                                                        tmp_path, capsys):
    """κ with its sign flipped (hash updated) is re-verified and refuted: exit 1, and the
    line names a state that violates the certificate's condition."""
    import hashlib

    from nlyap_opt.interface.cli import main

    def flip(d, c):
        f = d / c["artifacts"]["controller"]["file"]
        k = json.loads(f.read_text())
        scale = k["output_scale"]
        k["output_scale"] = [-v for v in scale] if isinstance(scale, list) else -scale
        f.write_text(json.dumps(k))
        c["artifacts"]["controller"]["sha256"] = hashlib.sha256(f.read_bytes()).hexdigest()

    run = _edit_run(learned_runs["inverted_pendulum"][0], tmp_path / "run", flip)
    assert main(["verify", "--certificate", str(run)]) == 1
    out = capsys.readouterr().out.strip().splitlines()[-1]
    assert out.startswith("counterexample:") and "violates it" in out and "x = [" in out


@pytest.mark.parametrize("edit,words", [
    (lambda d, c: c["checks"].update({"(a) decrease": "failed"}), "checks['(a) decrease']"),
    (lambda d, c: c["checks"].update({"(z) extra": "failed"}), "checks['(z) extra']"),
    (lambda d, c: c.update(reason="PROVEN BY ME"), "reason"),
], ids=["failed-check", "extra-failed-check", "reason"])
def test_recheck_refuses_stored_checks_that_contradict_the_proof(learned_runs, tmp_path,
                                                                 edit, words):
    """The stored checks and reason describe the proof: a certificate that states a check
    failed (or another reason) beside its certified status is refused as edited."""
    from nlyap_opt.certification.certificate import recheck_certificate

    run = _edit_run(learned_runs["van_der_pol"][0], tmp_path / "run", edit)
    again = recheck_certificate(run, log=lambda m: None)
    assert not again.certified and words in again.reason, again.reason


def test_recheck_refuses_a_controlled_system_without_its_controller(learned_runs, tmp_path,
                                                                    capsys):
    """A certificate of a system with inputs whose κ artifact was removed is refused (exit 2),
    not verified for the open loop (whose counterexample would be exit 1)."""
    from nlyap_opt.interface.cli import main

    d, _ = learned_runs["inverted_pendulum"]
    run = _edit_run(d, tmp_path / "run", lambda d, c: c["artifacts"].pop("controller"))
    assert main(["verify", "--certificate", str(run)]) == 2
    assert "lists no controller" in capsys.readouterr().out


def test_recheck_refuses_a_certificate_whose_input_box_was_widened(learned_runs, tmp_path):
    """U is part of where ‖f − φ‖ ≤ η holds: a certificate.json whose input box no longer
    is the one of its hashed bounds file is refused, not re-verified on the wider box."""
    import shutil

    from nlyap_opt.certification.certificate import recheck_certificate

    d, cert = learned_runs["inverted_pendulum"]
    shutil.copytree(d, tmp_path / "run")
    c = json.loads((tmp_path / "run" / "certificate.json").read_text())
    assert c["problem"]["input_box"] is not None
    c["problem"]["input_box"] = [[lo - 1.0, hi + 1.0] for lo, hi in c["problem"]["input_box"]]
    (tmp_path / "run" / "certificate.json").write_text(json.dumps(c))
    again = recheck_certificate(tmp_path / "run", log=lambda m: None)
    assert not again.certified and "input box" in again.reason


def test_certificate_stage_verifies_with_the_cegis_verifier_options(tmp_path):
    """cegis.verify_options hold for the certificate stage too: the saved problem carries
    them, so the run's own re-verification and `nlyap verify --certificate` use them."""
    from nlyap_opt.workflow.configs import make_config

    opts = {"second_order": True, "max_boxes": 300000}
    cfg = make_config("van_der_pol", "fast", overrides={"cegis": {"verify_options": opts}})
    res = run("van_der_pol", cfg, tmp_path / "r", known_dynamics=True, log=lambda m: None)
    saved = json.loads((tmp_path / "r" / "certificate.json").read_text())
    assert saved["problem"]["verify_options"] == opts
    assert res.status.value == "certified"
