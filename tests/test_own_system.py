"""Bring your own system through the command line: spec files, run settings from the file,
declared assumptions in the certificate, one-line errors for malformed specs."""

import json

import pytest

from nlyap_opt.certification.certificate import recheck_certificate
from nlyap_opt.interface.cli import main

SPEC = '''
name = "{name}"
description = "a cubic damped system (test)"
states = ["x1", "x2"]
state_box = [[-2.0, 2.0], [-2.0, 2.0]]

[rhs]
x1 = "x2"
x2 = "-x1 - x2 + {rhs_extra}"

[declared]
lipschitz = 20.0

[run]
outer = 1.0
inner = 0.2
eval_points = 3600

[run.train]
hidden = [6]
features = 3
steps = 150

[run.cegis]
iterations = 1
steps = 50
samples = 2000
'''


def _spec(tmp_path, name="own_cubic", rhs_extra="x1**3 / 3"):
    p = tmp_path / f"{name}.toml"
    p.write_text(SPEC.format(name=name, rhs_extra=rhs_extra))
    return p


@pytest.mark.slow  # 10 s idle; examples/fossil_nonpoly2.toml keeps a spec file via the CLI
def test_spec_system_runs_end_to_end_from_the_cli(tmp_path, capsys):
    spec = _spec(tmp_path)
    out = tmp_path / "run"
    assert main(["run", str(spec), "--known-dynamics", "--out", str(out)]) == 0
    cert = json.loads((out / "certificate.json").read_text())
    assert cert["status"] == "certified" and cert["system"] == "own_cubic"
    # from [run]: r = 1 and ε = 0.2 (the winning certificate may use another radius of the
    # inner search, a fixed multiple of the configured one)
    from nlyap_opt.certification.certificate import INNER_FACTORS

    assert cert["outer_radius"] == 1.0
    assert any(abs(cert["inner_radius"] - 0.2 * k) < 1e-12 for k in INNER_FACTORS)
    assert any("K_f = 20" in a for a in cert["assumptions_declared_by_user"])
    report = (out / "report.md").read_text()
    assert "Assumptions (declared by the user)" in report
    # the certificate re-checks from its artifacts, also through the CLI
    assert recheck_certificate(out, log=lambda m: None).certified
    assert main(["verify", "--certificate", str(out)]) == 0


def test_systems_check_and_config_of_a_spec(tmp_path, capsys):
    spec = _spec(tmp_path, name="own_cubic_b")
    assert main(["systems", "--check", str(spec)]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["name"] == "own_cubic_b" and summary["has_model"]
    assert main(["config", str(spec)]) == 0
    cfg = json.loads(capsys.readouterr().out)
    assert cfg["outer"] == 1.0 and cfg["train"]["steps"] == 150
    assert cfg["eval_box"] == [[-2.0, 2.0], [-2.0, 2.0]]


@pytest.mark.parametrize("rhs_extra, words", [
    ("x3**3", ["x3"]),                       # unknown symbol
    ("x1**", ["x2"]),                        # syntax error in the x2 equation
    ("__import__('os')", ["x2"]),            # never evaluated
    ("eval('1')", ["eval"]),                 # function not allowed
])
def test_malformed_expressions_are_one_line_input_errors(tmp_path, capsys, rhs_extra, words):
    spec = _spec(tmp_path, name="own_bad", rhs_extra=rhs_extra)
    code = main(["run", str(spec), "--known-dynamics", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip()
    assert code == 3, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    for w in words:
        assert w in err, err
    assert not (tmp_path / "o" / "V.json").exists()


def test_missing_system_file_is_an_input_error(tmp_path, capsys):
    assert main(["run", str(tmp_path / "nope.toml")]) == 3
    assert "no such file" in capsys.readouterr().err


def test_known_dynamics_needs_a_model(tmp_path, capsys):
    import shutil
    from pathlib import Path

    ex = Path(__file__).resolve().parents[1] / "examples"
    for f in ex.glob("blackbox_pendulum*"):
        shutil.copy(f, tmp_path / f.name)
    code = main(["run", str(tmp_path / "blackbox_pendulum.toml"), "--known-dynamics",
                 "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 3 and "no model" in err, err


@pytest.mark.slow  # 12 s idle: a run and a re-check in fresh processes
def test_spec_system_certificate_rechecks_in_a_new_process(tmp_path):
    """The certificate of a spec-file system names its file, so a fresh process (where the
    system is not registered) re-checks it."""
    import subprocess
    import sys

    spec = _spec(tmp_path, name="own_cubic_c")
    out = tmp_path / "run"
    assert main(["run", str(spec), "--known-dynamics", "--out", str(out)]) == 0
    proc = subprocess.run([sys.executable, "-m", "nlyap_opt.interface.cli", "verify",
                           "--certificate",
                           str(out)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr


def test_spec_file_may_not_take_a_catalogue_name(tmp_path, capsys):
    spec = _spec(tmp_path, name="van_der_pol")
    assert main(["run", str(spec), "--known-dynamics", "--out", str(tmp_path / "o")]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "catalogue system" in err[0] and "another name" in err[0]
    assert not (tmp_path / "o" / "V.json").exists()
