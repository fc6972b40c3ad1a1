"""RunConfig: the typed, frozen configuration tree the pipeline reads, its JSON round trip,
the stage views and the stage keys derived from the keys each stage declares."""

import copy
import dataclasses
import json
import pickle
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from nlyap_opt.candidates.learning import TrainConfig
from nlyap_opt.kernel.errors import ConfigError
from nlyap_opt.workflow import pipeline
from nlyap_opt.workflow.configs import (
    PRESETS,
    RunConfig,
    Section,
    UndeclaredKeyError,
    config_reference,
    make_config,
    schema,
)

ROOT = Path(__file__).resolve().parents[1]
ALL_PRESETS = [(s, p) for s in PRESETS for p in PRESETS[s]]


def test_every_key_is_described():
    """Each key of the schema has a description, and ``nlyap config --keys`` shows it."""
    keys = [k for section in schema().values() for k in section.values()]
    undescribed = [k.name for k in keys if not k.doc.strip()]
    assert len(keys) > 100 and undescribed == []
    rows = [r for r in config_reference().splitlines() if r.startswith("| `")]
    assert len(rows) == len(keys)
    assert all(r.rstrip(" |").rsplit("|", 1)[1].strip() for r in rows)


@pytest.mark.parametrize("system,preset", ALL_PRESETS)
def test_json_round_trip_keeps_keys_order_and_values(system, preset):
    cfg = make_config(system, preset)
    data = cfg.to_json()
    # the preset's own keys first, in its order, then the two informational keys
    assert list(data) == [k for k in PRESETS[system][preset] if k not in ("system", "preset")] \
        + ["system", "preset"]
    assert json.dumps(data) == json.dumps(RunConfig.from_json(data).to_json())
    for name, value in PRESETS[system][preset].items():
        assert data[name] == value
    assert RunConfig.from_json(data) == cfg and copy.deepcopy(cfg) == cfg
    assert pickle.loads(pickle.dumps(cfg)) == cfg


def test_attributes_give_the_value_or_the_schema_default():
    cfg = make_config("inverted_pendulum", "fast", overrides={"cegis": {"margin_mode": "global"}})
    sch = schema()
    for section in ("train", "cegis", "sos"):
        given = cfg.to_json().get(section, {})
        for name, key in sch[section].items():
            got = getattr(getattr(cfg, section), name)
            if isinstance(got, Section):
                got = got.to_json()
            assert got == given.get(name, key.default), key.name
    assert cfg.cegis.margin_mode == "global" and cfg.train.steps == 300
    assert cfg.auto_inner is False and cfg.domain is None and cfg.quadratic == []
    assert cfg.lqr.Q == [[1.0, 0.0], [0.0, 20.0]] and cfg.cegis.verify_options.to_json() == {}
    # the typed values are what the dataclasses would take as defaults
    assert TrainConfig(**cfg.train.to_json()) == TrainConfig(**cfg["train"])
    with pytest.raises(AttributeError, match="did you mean 'steps'"):
        cfg.train.stpes


def test_the_config_cannot_be_changed_through_what_it_returns():
    cfg = make_config("van_der_pol", "fast")
    before = json.dumps(cfg.to_json())
    cfg.train.hidden.append(99)
    cfg["train"]["hidden"].append(99)
    cfg.eval_box[0][0] = -100.0
    cfg.to_json()["train"]["steps"] = 1
    assert json.dumps(cfg.to_json()) == before
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.inner = 0.5
    with pytest.raises(TypeError):
        cfg["inner"] = 0.5


def test_a_view_refuses_keys_its_stage_does_not_declare():
    cfg = make_config("van_der_pol", "fast")
    view = cfg.view(("inner", "cegis.margin_mode"))
    assert view.inner == 0.3 and view.cegis.margin_mode == "pointwise"
    assert view.declared() == {"inner": 0.3, "cegis.margin_mode": None}
    assert list(view) == ["inner", "cegis"] and view["cegis"] == {}
    # every way of reading an undeclared key fails loudly (none answers "absent")
    for read in (lambda: view.train, lambda: view.cegis.steps, lambda: view["outer"],
                 lambda: view.get("train", {}), lambda: view.cegis["steps"]):
        with pytest.raises(UndeclaredKeyError):
            read()


def test_from_json_refuses_unknown_keys_with_a_suggestion():
    with pytest.raises(ConfigError, match="did you mean 'train.steps'"):
        RunConfig.from_json({"train": {"stpes": 3}})
    with pytest.raises(ConfigError, match="must be a JSON object"):
        RunConfig.from_json({"train": 3})


def _probe(data: dict, dotted: str, value) -> dict:
    out = copy.deepcopy(data)
    node = out
    *heads, last = dotted.split(".")
    for h in heads:
        node = node.setdefault(h, {})
    node[last] = value
    return out


def _all_dotted() -> list[str]:
    sch = schema()
    return [k.name for section in sch.values() for k in section.values()]


@pytest.mark.parametrize("stage", sorted(pipeline._STAGE_FIELDS))
def test_a_stage_key_changes_with_exactly_the_keys_the_stage_declares(stage, tmp_path):
    data = make_config("inverted_pendulum", "fast").to_json()
    fields = pipeline._STAGE_FIELDS[stage]

    def key(d):
        return pipeline._Stages(tmp_path, "inverted_pendulum", False, RunConfig.from_json(d),
                                lambda m: None).key(stage)

    base = key(data)
    sch = schema()
    for dotted in _all_dotted():
        head, _, rest = dotted.partition(".")
        if not rest and sch[""][head].kind == "section":
            continue   # a section is probed through its keys
        declared = any(dotted == f or dotted.startswith(f + ".") for f in fields)
        changed = key(_probe(data, dotted, "probe")) != base
        assert changed == declared, f"{stage}: {dotted} (declared {declared})"
    # the setting and the system are part of every key
    other = pipeline._Stages(tmp_path, "inverted_pendulum", True, RunConfig.from_json(data),
                             lambda m: None).key(stage)
    assert other != base


def test_a_stage_that_reads_an_undeclared_key_fails(monkeypatch, tmp_path):
    """The controller stage reads controller_scale: without it declared, it cannot run
    (a stale stage is impossible, not merely unlikely)."""
    import systems
    from nlyap_opt.workflow.configs import domain_of

    cfg = make_config("inverted_pendulum", "fast")
    s = systems.get("inverted_pendulum")
    D, XI = domain_of(cfg, s.nx)
    stages = pipeline._Stages(tmp_path, s.name, True, cfg, lambda m: None)
    ctx = pipeline._Context(s, tmp_path, stages, lambda m: None, D, XI, D.max_norm(),
                            cfg.inner)
    monkeypatch.setitem(pipeline._STAGE_FIELDS, "controller", ("lqr",))
    with pytest.raises(UndeclaredKeyError, match="controller_scale"):
        pipeline._controller_stage(ctx)
    monkeypatch.undo()
    assert pipeline._controller_stage(ctx) is not None
    assert json.loads((tmp_path / "stages.json").read_text())["controller"]["files"]


def test_orchestration_functions_stay_small():
    """No function of the orchestration layer exceeds 60 statements or a complexity of 15
    (ruff's PLR0915 and C901 with the limits of pyproject.toml, whose per-file rule must
    cover the same modules)."""
    from test_structure import ORCHESTRATION

    ruff = shutil.which("ruff") or str(Path(sys.executable).with_name("ruff"))
    if not Path(ruff).exists():
        pytest.skip("ruff is not installed (pip install -e .[dev])")
    res = subprocess.run([ruff, "check", "--select", "C901,PLR0915", *ORCHESTRATION],
                         cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 0, res.stdout + res.stderr
    text = (ROOT / "pyproject.toml").read_text()
    held = text.split('"!nlyap_opt/{', 1)[1].split("}", 1)[0].split(",")
    assert sorted(f"nlyap_opt/{m}.py" for m in held) == sorted(ORCHESTRATION)


def test_an_undeclared_read_is_an_internal_error_not_an_input_error(monkeypatch, tmp_path,
                                                                     capsys):
    """A stage that reads an undeclared key is a bug of the program: exit 4, not 3."""
    from nlyap_opt.interface.cli import main

    monkeypatch.setitem(pipeline._STAGE_FIELDS, "controller", ("lqr",))
    code = main(["run", "inverted_pendulum", "--preset", "fast", "--known-dynamics",
                 "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert code == 4 and "UndeclaredKeyError" in err and "controller_scale" in err


def test_schema_and_declared_keys_are_read_only():
    """The schema is computed once and shared, a view's declared keys feed its stage key:
    neither can be changed by a caller."""
    sch = schema()
    with pytest.raises(TypeError):
        sch["train"] = {}
    with pytest.raises(TypeError):
        sch["train"]["steps"] = None
    declared = make_config("van_der_pol", "fast").view(("inner",)).declared()
    with pytest.raises(TypeError):
        declared["inner"] = 1.0
    assert dict(declared) == {"inner": 0.3}


def test_stage_records_round_trip_and_refuse_bad_content(tmp_path):
    """The CEGIS record writes the JSON it loads back (status as its enum's value); a
    record with an unknown status or a missing key is an input error naming the file."""
    from nlyap_opt.certification.certificate import CertStatus

    rec = pipeline._CegisRecord(CertStatus.CERTIFIED, "", 0.5, 0.01, 2.0, 0.1, 0.3,
                                [{"it": 0}], 1.5)
    path = tmp_path / "cegis.json"
    pipeline._write_stage_json(path, rec.to_json())
    assert json.loads(path.read_text())["status"] == "certified"
    assert "seconds" not in json.loads(path.read_text())   # timings beside it
    assert pipeline._CegisRecord.load(path) == rec
    data = json.loads(path.read_text())
    for bad in (dict(data, status="certfied"), {k: v for k, v in data.items() if k != "M"}):
        path.write_text(json.dumps(bad))
        with pytest.raises(ConfigError, match="cegis.json cannot be read"):
            pipeline._CegisRecord.load(path)
    sos = pipeline._CheapRecord("sos", "SOS degree 2", "V_sos.json", 0.7, 0.1, 2.5, {})
    assert pipeline._CheapRecord.of_stage("sos", sos.to_json(), path) == sos
    quad = pipeline._CheapRecord.of_stage(
        "quadratic", {"name": "round", "P": [[1.0]], "level": 0.2, "inner": 0.1,
                      "volume": 1.0}, path)
    assert (quad.label, quad.file, quad.P) == ("quadratic round", "V_quadratic.json", [[1.0]])
    with pytest.raises(ConfigError, match="cannot be read"):
        pipeline._CheapRecord.of_stage("sos", {"kind": "sos"}, path)


def test_a_stages_file_that_is_a_directory_is_refused_before_any_stage(tmp_path):
    """``stages.json`` replaced by a directory: refused when the run starts (it was found
    only when the first stage was recorded, after that stage's work), naming the file."""
    from nlyap_opt.kernel.errors import ConfigError

    (tmp_path / "stages.json").mkdir()
    with pytest.raises(ConfigError, match=r"stages\.json is not a regular file.*--out"):
        pipeline._Stages(tmp_path, "inverted_pendulum", True,
                         make_config("inverted_pendulum", "fast"), lambda m: None)
