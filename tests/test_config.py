"""The run configuration: one schema derived from the dataclasses, validated up front."""

import dataclasses
import json

import pytest

from nlyap_opt.candidates.cegis import CegisConfig
from nlyap_opt.candidates.learning import TrainConfig
from nlyap_opt.kernel.errors import ConfigError, UnknownNameError
from nlyap_opt.workflow import configs
from nlyap_opt.workflow.configs import (
    PRESETS,
    check_dynamics_box,
    check_lqr_weights,
    get_config,
    make_config,
    schema,
)

ALL_PRESETS = [(s, p) for s in PRESETS for p in PRESETS[s]]


@pytest.mark.parametrize("system,preset", ALL_PRESETS)
def test_every_preset_validates_and_builds_the_dataclasses(system, preset):
    cfg = get_config(system, preset)
    assert cfg["system"] == system and cfg["preset"] == preset
    train = TrainConfig(**cfg.get("train", {}))
    ccfg = CegisConfig(inner=cfg["inner"], outer=cfg["outer"], train=train,
                       **cfg.get("cegis", {}))
    assert ccfg.inner < ccfg.outer
    check_dynamics_box(cfg)  # every preset's ball fits its dynamics box


@pytest.mark.parametrize("system,preset", ALL_PRESETS)
def test_no_wall_clock_budget_in_any_preset(system, preset):
    text = json.dumps(PRESETS[system][preset])
    assert "time_budget" not in text


def test_schema_is_derived_from_the_dataclasses():
    sch = schema()
    train_fields = {f.name for f in dataclasses.fields(TrainConfig)} - {"time_budget"}
    # inner, outer, domain and initial_set are top-level keys; train is its own section
    cegis_fields = {f.name for f in dataclasses.fields(CegisConfig)} - {
        "inner", "outer", "train", "time_budget", "domain", "initial_set"}
    assert set(sch["train"]) == train_fields
    assert set(sch["cegis"]) == cegis_fields
    # defaults and types come from the dataclasses
    assert sch["train"]["lr"].default == TrainConfig().lr and sch["train"]["lr"].kind == "float"
    assert sch["cegis"]["first_steps"].optional and sch["cegis"]["first_steps"].kind == "int"
    assert sch["train"]["hidden"].kind == "int_list"
    # no key escapes a type check
    for section in ("", "lqr", "train", "cegis", "cegis.verify_options"):
        assert all(k.kind != "any" for k in sch[section].values()), section


def test_range_rules_name_existing_fields_only():
    sch = schema()
    for section, rules in configs._RULES.items():
        unknown = set(rules) - set(sch[section])
        assert not unknown, (section, unknown)


def test_dynamics_section_follows_the_dynamics_dataclass():
    dc = pytest.importorskip("nlyap_opt.learned.dynamics_config")
    names = {f.name for f in dataclasses.fields(dc.DynamicsConfig)}
    assert set(schema()["dynamics"]) == names


def test_overrides_and_file_merge_in_order(tmp_path):
    f = tmp_path / "c.json"
    f.write_text(json.dumps({"train": {"steps": 7, "lr": 0.5}, "cegis": {"iterations": 3}}))
    cfg = make_config("van_der_pol", "fast", overrides={"train": {"steps": 9}}, file=f)
    assert cfg["train"]["steps"] == 9            # overrides last
    assert cfg["train"]["lr"] == 0.5             # file over preset
    assert cfg["train"]["hidden"] == [6]         # preset kept
    assert cfg["cegis"]["iterations"] == 3
    assert PRESETS["van_der_pol"]["fast"]["train"]["steps"] == 300  # preset untouched


def test_dynamics_grid_given_one_way_replaces_the_other():
    cfg = make_config("van_der_pol", "large", overrides={"dynamics": {"grid_spacing": 0.01}})
    assert "grid_counts" not in cfg["dynamics"] and cfg["dynamics"]["grid_spacing"] == 0.01


def test_make_config_without_a_preset():
    cfg = make_config("van_der_pol", preset=None, overrides={"outer": 1.0, "inner": 0.2})
    assert cfg["eval_box"] == [[-1.5, 1.5], [-1.5, 1.5]] and cfg["preset"] is None
    # without a preset the settings come from the system's boxes: the state box is the
    # domain, ε = a tenth of the largest ball inside it, C = the largest symmetric range
    # inside U
    auto = make_config("van_der_pol", preset=None)
    assert auto["outer"] is None and auto["inner"] == 0.15
    assert auto["domain"] == {"type": "box", "box": [[-1.5, 1.5], [-1.5, 1.5]]}
    pend = make_config("inverted_pendulum", preset=None)
    s = __import__("systems").get("inverted_pendulum")
    assert pend["domain"]["box"] == s.state_box.tolist()
    assert pend["inner"] == 0.1 * float(min(-s.state_box[:, 0].max(),
                                            s.state_box[:, 1].min()))
    assert pend["controller_scale"] == float(min(-s.input_box[:, 0].max(),
                                                 s.input_box[:, 1].min()))
    with pytest.raises(ConfigError, match="controller_scale"):
        make_config("inverted_pendulum", preset=None, overrides={"controller_scale": None})


def test_default_controller_scale_is_per_input_and_a_shifted_box_is_named():
    """C_i = the largest [−C_i, C_i] inside input i's box (one number when all agree); an
    input whose box holds no such range around its u_eq is named with the shifted box."""
    import casadi as ca

    import systems
    from systems.spec import default_run_settings

    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 2)
    f = ca.vertcat(x[0] + u[0], x[1] + u[1] - 1.0)    # u_eq = (0, 1)

    def sys_(ub, ueq=(0.0, 1.0)):
        return systems.System("two", x, u, f, state_box=[[-1, 1], [-1, 1]], input_box=ub,
                              u_eq=list(ueq))

    assert default_run_settings(sys_([[-2, 2], [-8, 9]]))["controller_scale"] == [2.0, 8.0]
    assert default_run_settings(sys_([[-3, 2], [-2, 5]]))["controller_scale"] == 2.0
    with pytest.raises(ConfigError, match=r"input 'u2'.*box \[-2, 2\], u_eq = 0"):
        default_run_settings(sys_([[-2, 2], [-1, 3]]))
    with pytest.raises(ConfigError, match=r"input 'u2'.*u_eq = 1 is not inside its box"):
        default_run_settings(sys_([[-2, 2], [1, 3]]))              # u_eq on the edge


def test_system_without_a_preset_says_what_is_possible():
    import casadi as ca

    import systems

    name = "test_config_no_preset"
    if name not in systems.names():
        x = ca.SX.sym("x", 2)
        systems.register(name, lambda: systems.System(
            name, x, None, ca.vertcat(-x[0], -x[1]), state_box=[[-1, 1], [-1, 1]]))
    with pytest.raises(UnknownNameError, match="preset=None") as err:
        get_config(name, "large")
    assert "full --config" not in str(err.value)
    cfg = make_config(name, None, overrides={"outer": 0.9, "inner": 0.1})
    assert cfg["system"] == name


@pytest.mark.parametrize("over,words", [
    ({"train": {"stpes": 1}}, ["train.stpes", "did you mean 'train.steps'"]),
    ({"cegis": {"margin_mode": "global "}}, ["margin_mode", "'pointwise', 'global'"]),
    ({"train": {"lr": float("nan")}}, ["train.lr", "NaN"]),
    ({"train": {"lr": float("inf")}}, ["train.lr", "Infinity"]),
    ({"inner": 1.0}, ["0 < inner < outer"]),
    ({"outer": 1e200}, ["outer = 1e+200 is beyond 1e+100", "rescale"]),
    ({"train": {"time_budget": 60.0}}, ["time_budget", "wall-clock budgets were removed"]),
    ({"cegis": {"verify_options": {"max_boxes": 0}}}, ["max_boxes", ">= 1"]),
    ({"train": {"threads": 1.0}}, ["train.threads", "integer"]),
    ({"eval_points": 10**11}, ["eval_points", "state coordinates", "1e+08"]),
    ({"train": {"hidden": [10**9]}}, ["train.hidden", "weights of V's network"]),
    ({"train": {"hidden": [50000]}}, ["cegis.samples", "narrow train.hidden"]),
    ({"dynamics": {"hidden": 10**8}}, ["'hidden'", "hidden activations"]),
    ({"dynamics": {"grid_counts": [10**5, 10**5]}}, ["'grid_counts'", "grid coordinates"]),
])
def test_bad_overrides_are_refused_before_anything_runs(over, words):
    with pytest.raises(ConfigError) as err:
        make_config("van_der_pol", "fast", overrides=over)
    for w in words:
        assert w in str(err.value), (w, str(err.value))
    assert "\n" not in str(err.value)


def test_numpy_numbers_are_accepted():
    np = pytest.importorskip("numpy")
    cfg = make_config("inverted_pendulum", "fast",
                      overrides={"train": {"steps": np.int64(5), "lr": np.float64(0.1)},
                                 "lqr": {"Q": np.eye(2).tolist(), "R": 2.0}})
    assert cfg["train"]["steps"] == 5


def test_unknown_system_and_preset():
    with pytest.raises(UnknownNameError, match="registered systems"):
        make_config("cartpoll")
    with pytest.raises(UnknownNameError, match="did you mean 'fast'"):
        make_config("van_der_pol", "fats")


def test_lqr_weights_checked_against_the_system():
    import systems

    s = systems.get("inverted_pendulum")
    Q, R = check_lqr_weights(s, 2.0, [[3.0]])
    assert Q.shape == (2, 2) and Q[1, 1] == 2.0 and R[0, 0] == 3.0
    with pytest.raises(ConfigError, match="positive definite"):
        check_lqr_weights(s, None, 0.0)
    with pytest.raises(ConfigError, match="symmetric"):
        check_lqr_weights(s, [[1.0, 1.0], [0.0, 1.0]])


def test_config_reference_lists_every_key():
    ref = configs.config_reference()
    for section in ("train", "cegis"):
        for name in schema()[section]:
            assert f"`{section}.{name}`" in ref
    assert "time_budget" not in ref
