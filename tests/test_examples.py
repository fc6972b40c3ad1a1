"""The examples of ``examples/`` end to end, each through the one command the README gives,
with a fast variant of its run settings (``--config`` merged over the file's ``[run]``)."""

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from nlyap_opt.certification.certificate import recheck_certificate, spec_factory
from nlyap_opt.interface.cli import main

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

# sos.degree 0: the automatic SOS candidate (degree 4 for the 3-D cubics, ~15 s idle) is
# tested in tests/test_sos_auto.py; here the example's own workflow, fast
FAST_KNOWN = {"train": {"hidden": [8], "features": 3, "steps": 400, "lr": 0.02},
              "cegis": {"iterations": 2, "steps": 100, "samples": 4000},
              "eval_points": 10000, "sos": {"degree": 0}}

# the pendulum examples learn φ: a coarse φ (η ≈ 0.04, the full run's is 7e-3) on a smaller
# disc; it runs the whole workflow in ~30 s but is too coarse to certify near B_ε
FAST_PENDULUM = {
    "outer": 2.0, "inner": 0.2, "eval_box": [[-2.0, 2.0], [-2.0, 2.0]], "eval_points": 10000,
    "train": {"hidden": [16], "features": 4, "steps": 800, "lr": 0.01},
    "cegis": {"iterations": 1, "steps": 200, "samples": 4000, "sim_points": 0,
              "min_iterations": 1},
    "dynamics": {"preset": "fast", "hidden": 40, "grid_counts": [201, 201],
                 "train_points": 3000, "steps": 600, "lm_iterations": 40,
                 "minimax_rounds": 2, "minimax_iterations": 5, "interval_boxes": 4096,
                 "eta_target": None}}


def _config(tmp_path, cfg: dict) -> Path:
    p = tmp_path / "fast.json"
    p.write_text(json.dumps(cfg))
    return p


_SLOW = pytest.mark.slow  # 5-10 s idle each; one example stays in the default tier


@pytest.mark.parametrize("name", [pytest.param("two_machine_power", marks=_SLOW),
                                  pytest.param("lorenz_controlled", marks=_SLOW), "fossil_nonpoly2",
                                  pytest.param("fossil_nonpoly3", marks=_SLOW),
                                  pytest.param("fossil_poly1", marks=_SLOW)])
def test_model_examples_certify_and_recheck(name, tmp_path, capsys):
    out = tmp_path / name
    code = main(["run", str(EXAMPLES / f"{name}.toml"), "--known-dynamics", "--config",
                 str(_config(tmp_path, FAST_KNOWN)), "--out", str(out)])
    assert code == 0
    cert = json.loads((out / "certificate.json").read_text())
    assert cert["status"] == "certified" and cert["system"] == name
    assert all(v in ("verified", "certified") for v in cert["checks"].values())
    assert cert["certified_points_converge_in_simulation"]
    assert 0 < cert["fraction_of_true_roa"] <= 1.0 + 1e-9
    # no certified set (in D, forward invariant) holds more than the states that stay in D
    # (up to one grid cell: a point at ∂D may leave D in the integration's rounding)
    box = np.asarray(cert["eval_box"])
    cell = np.prod(np.ptp(box, axis=1)) / cert["eval_grid"] ** len(box)
    assert cert["fraction_of_true_roa"] <= cert["true_roa_stays_in_domain"] \
        + cell / cert["true_roa_area"] + 1e-9
    assert cert["true_roa_undecided"] >= 0 and cert["true_roa_elsewhere"] >= 0
    assert (out / "roa.png").stat().st_size > 10_000          # 3-D: the slice x3 = 0
    assert recheck_certificate(out, log=lambda m: None).certified


def _check_unknown_f_run(out: Path, code: int, *, simulated: bool):
    """What a run without a model of f must say: certified (exit 0), under the declared
    assumptions, and the certificate re-checks."""
    cert = json.loads((out / "certificate.json").read_text())
    assert code == 0 and cert["status"] == "certified", (code, cert["status"], cert["reason"])
    assert cert["setting"] == "learned"
    declared = cert["assumptions_declared_by_user"]
    assert any("K_f = 34.5" in a for a in declared) and any("H = 26" in a for a in declared)
    assert any("check of the same V and κ against the true f" in a
               for a in cert["not_available"])
    assert (cert["true_roa_area"] is not None) == simulated
    report = (out / "report.md").read_text()
    assert "Assumptions (declared by the user)" in report and "Not available" in report
    b = json.loads((out / "bounds.json").read_text())
    assert b["eta"] > 0 and b["delta"] > 0
    assert cert["certified_area"] > 0
    # a factory spec is run on re-check only when given with allow_factory
    src = cert.get("system_source")
    given = {"system": src, "allow_factory": True} if src and spec_factory(src) else {}
    assert recheck_certificate(out, log=lambda m: None, **given).certified
    return cert, b


@pytest.mark.slow  # ~35 s idle (a learned run of a black-box callable)
def test_blackbox_pendulum_runs_end_to_end(tmp_path, capsys):
    out = tmp_path / "bb"
    code = main(["run", str(EXAMPLES / "blackbox_pendulum.toml"), "--config",
                 str(_config(tmp_path, FAST_PENDULUM)), "--out", str(out)])
    _check_unknown_f_run(out, code, simulated=True)      # the callable is simulated


@pytest.mark.slow  # 20-40 s: the default tier stays near 5 min on 2 cores
def test_pendulum_csv_runs_end_to_end_from_the_written_samples(tmp_path, capsys):
    # the README's two commands: write the samples, then run the spec that reads them
    data = tmp_path / "data"
    subprocess.run([sys.executable, str(EXAMPLES / "write_pendulum_csv.py"), "--out",
                    str(data / "pendulum.csv"), "--counts", "201", "201"], check=True,
                   capture_output=True)
    spec = tmp_path / "pendulum_csv.toml"
    shutil.copy(EXAMPLES / "pendulum_csv.toml", spec)     # data/pendulum.csv beside it
    out = tmp_path / "csv"
    fast = {k: v for k, v in FAST_PENDULUM.items()}
    fast["dynamics"] = {k: v for k, v in FAST_PENDULUM["dynamics"].items()
                        if k != "grid_counts"}            # the file's grid, not a choice
    code = main(["run", str(spec), "--config", str(_config(tmp_path, fast)), "--out", str(out)])
    cert, b = _check_unknown_f_run(out, code, simulated=False)   # samples only
    assert any(a.startswith("true ROA") for a in cert["not_available"])
    # δ is the covering radius of the file's grid: half the cell diagonal (2-norm)
    h = 8.0 / 200
    assert b["delta"] == pytest.approx(0.5 * (2 * h * h) ** 0.5, rel=1e-12)


def test_a_one_state_system_certifies_and_gets_its_picture(tmp_path, capsys):
    """x' = −x + x³ on [−2, 2] (ROA (−1, 1)): a one-state spec runs end to end; the
    certified interval lies in the true ROA; roa.png shows V and x' along the interval
    (the 2-D phase portrait has no second axis)."""
    spec = tmp_path / "cubic_1d.toml"
    spec.write_text('name = "cubic_1d"\nstates = ["x"]\nstate_box = [[-2.0, 2.0]]\n\n'
                    '[rhs]\nx = "-x + x^3"\n')
    out = tmp_path / "out"
    assert main(["run", str(spec), "--known-dynamics", "--config",
                 str(_config(tmp_path, FAST_KNOWN)), "--out", str(out)]) == 0
    cert = json.loads((out / "certificate.json").read_text())
    assert cert["status"] == "certified" and cert["certified_points_converge_in_simulation"]
    assert 1.0 < cert["certified_area"] < 2.0 and cert["true_roa_area"] == pytest.approx(2.0,
                                                                                         abs=0.01)
    assert "roa.png not written" not in capsys.readouterr().out
    assert (out / "roa.png").stat().st_size > 10_000
