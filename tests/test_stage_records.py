"""What a rerun reuses from a run directory: only stages whose record, system and files
all check out (``stages.json``), and no certificate the true f contradicts."""

import json
from types import SimpleNamespace

import pytest

from nlyap_opt.certification.certificate import CertStatus
from nlyap_opt.workflow.configs import make_config
from nlyap_opt.workflow.pipeline import _refute_by_true_f, _Stages, run

SPEC = """name = "edited_spec"
states = ["x1", "x2"]
state_box = [[-1.0, 1.0], [-1.0, 1.0]]
[rhs]
x1 = "{x1}"
x2 = "-x2 - x1^3"
[run]
outer = 0.5
inner = 0.1
"""


def _stages(tmp_path, system="s:abc"):
    cfg = make_config("van_der_pol", "fast")
    return _Stages(tmp_path, system, True, cfg, lambda m: None)


def test_a_stage_record_whose_file_list_was_emptied_is_recomputed(tmp_path):
    """Emptying (or replacing by a list) a stage's 'files' let its files through with no
    hash check: an edited bounds.json (η / 10) was reused and certified."""
    (tmp_path / "lqr.json").write_text("{}")
    st = _stages(tmp_path)
    st.mark("controller")
    assert _stages(tmp_path).finished("controller")
    for files in ({}, [], "abc"):
        rec = json.loads((tmp_path / "stages.json").read_text())
        rec["controller"]["files"] = files
        (tmp_path / "stages.json").write_text(json.dumps(rec))
        assert not _stages(tmp_path).finished("controller"), files
        _stages(tmp_path).mark("controller")
    # another system under the same name (its fingerprint differs) finds no stage
    assert not _stages(tmp_path, "s:def").finished("controller")


def test_a_certificate_the_true_f_contradicts_is_withdrawn():
    """A learned-dynamics certificate implies decrease with f where ‖f − φ‖ ≤ η: a confirmed
    true-f counterexample inside its set shows that η does not hold."""
    cert = SimpleNamespace(certified=True, status=CertStatus.CERTIFIED, reason="")
    logs = []
    _refute_by_true_f(cert, {"decrease_true_f": "verified"}, 0.01, logs.append)
    assert cert.status is CertStatus.CERTIFIED and not logs
    _refute_by_true_f(cert, {"decrease_true_f": "counterexample", "counterexample": [0.4, 0]},
                      0.01, logs.append)
    assert cert.status is CertStatus.NOT_CERTIFIED
    assert "contradicts the bound η = 0.01" in cert.reason and "[0.4, 0]" in cert.reason
    assert logs and "NOT CERTIFIED" in logs[0]


def test_an_edited_spec_under_the_same_name_recomputes_its_stages(tmp_path, log_until):
    """The stages' keys named the system by its name only: a spec edited under the same name
    reused the dynamics (and η) learned for the old f, and certified a false set."""
    spec = tmp_path / "s.toml"
    spec.write_text(SPEC.format(x1="-x1 + x2"))
    import systems

    over = {"train": {"steps": 5}, "cegis": {"iterations": 1, "steps": 5},
            "sos": {"degree": 0}, "eval_points": 400}
    out = tmp_path / "run"
    s = systems.load_spec(spec)
    systems.REGISTRY[s.name] = lambda: s
    try:
        run(s.name, make_config(s.name, None, overrides=over), out, known_dynamics=True,
            log=lambda m: None)
        spec.write_text(SPEC.format(x1="-x1 + x2 + 4*x1^2"))
        s2 = systems.load_spec(spec)
        systems.REGISTRY[s.name] = lambda: s2
        log = log_until("[quadratic]")
        with pytest.raises(KeyboardInterrupt):
            run(s.name, make_config(s.name, None, overrides=over), out, known_dynamics=True,
                log=log)
        assert any("[quadratic] configuration, system or earlier stage changed" in m
                   for m in log.lines), log.lines
    finally:
        systems.REGISTRY.pop(s.name, None)


def test_a_real_directory_named_best_is_left_and_not_called_the_best(tmp_path):
    """portfolio.md said "(also best/)" while best/ was a directory the portfolio did not
    write (another seed's copy)."""
    from nlyap_opt.workflow.portfolio import _link_best

    (tmp_path / "seed_0").mkdir()
    res = SimpleNamespace(out=tmp_path, best=SimpleNamespace(dir="seed_0"))
    assert _link_best(res) and (tmp_path / "best").is_symlink()
    assert _link_best(res)                           # replaced by a new link
    (tmp_path / "best").unlink()
    (tmp_path / "best").mkdir()
    (tmp_path / "best" / "certificate.json").write_text("{}")
    assert not _link_best(res)
    assert (tmp_path / "best" / "certificate.json").read_text() == "{}"
