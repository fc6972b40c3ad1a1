"""Bad input: each a specific exception with a message that says what fixes it."""

import json
import warnings

import casadi as ca
import numpy as np
import pytest
import torch

import systems
from baselines.lqr import lqr, saturated_controller
from nlyap_opt.kernel.errors import (
    DimensionError,
    EquilibriumError,
    EquilibriumWarning,
    NetworkFileError,
    NotStabilizableError,
    UnknownNameError,
    UnsupportedLayerError,
)
from nlyap_opt.kernel.network import Layer, Network, from_torch
from nlyap_opt.kernel.symbolic import closed_loop


def _shifted_system():
    x = ca.SX.sym("x", 2)
    return systems.System("shifted", x, None, ca.vertcat(x[1], -x[0] + 1.0),
                          state_box=[[-1, 1], [-1, 1]])


def _unstabilisable():
    x = ca.SX.sym("x", 2)
    u = ca.SX.sym("u", 1)
    return systems.System("unstab", x, u, ca.vertcat(x[0], -x[1] + u),
                          state_box=[[-1, 1], [-1, 1]], input_box=[[-1, 1]])


def _nan_file(tmp_path):
    p = tmp_path / "nan.json"
    p.write_text('{"layers": [{"weight": [[NaN, 1.0]], "bias": [0.0], "activation": "tanh"}]}')
    return Network.load(p)


def _inf_file(tmp_path):
    p = tmp_path / "inf.json"
    p.write_text('{"layers": [{"weight": [[Infinity, 1.0]], "bias": [0.0]}]}')
    return Network.load(p)


def _bad_controller_bias():
    s = systems.get("unicycle_path_following")
    K = lqr(s).K
    ctrl = saturated_controller(s, K, 5.0)
    ctrl.layers[0].bias[:] = 0.1974  # the seed code's hand-typed bias, not the solved one
    return closed_loop(s, ctrl)


CASES = [
    ("origin not an equilibrium (system)", _shifted_system, EquilibriumError,
     "not an equilibrium"),
    ("origin not an equilibrium (closed loop, training)", _bad_controller_bias,
     EquilibriumError, "solve the controller bias"),
    ("non-stabilisable (A, B)", lambda: lqr(_unstabilisable()), NotStabilizableError,
     "not stabilisable"),
    ("unknown system", lambda: systems.get("cartpoll"), UnknownNameError,
     "registered systems"),
    ("unsupported layer", lambda: from_torch(torch.nn.Sequential(torch.nn.Linear(2, 3),
                                                                 torch.nn.GELU())),
     UnsupportedLayerError, "supported layers"),
    ("unsupported activation", lambda: Layer([[1.0]], [0.0], "swish"), UnsupportedLayerError,
     "use one of"),
    ("layer dimensions", lambda: Network([Layer(np.ones((3, 2)), np.zeros(3)),
                                          Layer(np.ones((1, 4)), np.zeros(1))]),
     DimensionError, "expects 4 inputs"),
    ("bias dimension", lambda: Layer(np.ones((3, 2)), np.zeros(2)), DimensionError, "bias"),
    ("f shape", lambda: systems.System("bad", ca.SX.sym("x", 2), None, ca.SX.sym("x", 2)[0],
                                       state_box=[[-1, 1], [-1, 1]]),
     DimensionError, "shape (2, 1)"),
    ("state box shape", lambda: systems.System("bad", ca.SX.sym("x", 2), None,
                                               ca.SX.zeros(2, 1), state_box=[[-1, 1]]),
     DimensionError, "state_box"),
    ("evaluate dims", lambda: systems.get("van_der_pol").evaluate(np.zeros((4, 3))),
     DimensionError, "(N, 2)"),
    ("controller dims", lambda: closed_loop(systems.get("inverted_pendulum"),
                                            Network([Layer(np.ones((1, 3)), [0.0])])),
     DimensionError, "needs R^2 -> R^1"),
]


@pytest.mark.parametrize("label,call,exc,msg", CASES, ids=[c[0] for c in CASES])
def test_bad_input(label, call, exc, msg):
    with pytest.raises(exc, match=msg.replace("(", r"\(").replace(")", r"\)")
                       .replace("^", r"\^")):
        call()


@pytest.mark.parametrize("maker", [_nan_file, _inf_file])
def test_nan_inf_network_files_refused(maker, tmp_path):
    with pytest.raises(NetworkFileError, match="(NaN|Infinity|finite)"):
        maker(tmp_path)


def test_malformed_network_file(tmp_path):
    p = tmp_path / "m.json"
    p.write_text(json.dumps({"layers": [{"bias": [0.0]}]}))
    with pytest.raises(NetworkFileError, match="malformed"):
        Network.load(p)
    p.write_text("{not json")
    with pytest.raises(NetworkFileError, match="not valid JSON"):
        Network.load(p)


def test_non_equilibrium_is_only_a_warning_in_verification():
    s = systems.get("unicycle_path_following")
    ctrl = saturated_controller(s, lqr(s).K, 5.0)
    ctrl.layers[0].bias[:] = 0.1974
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        closed_loop(s, ctrl, strict=False)
    assert any(issubclass(x.category, EquilibriumWarning) for x in w)


def test_errors_subclass_builtins():
    assert issubclass(UnknownNameError, KeyError)
    assert issubclass(NetworkFileError, ValueError)
    assert issubclass(UnsupportedLayerError, TypeError)


# ============================================================================ the CLI table
# Every case: argv (placeholders filled from the ``files`` fixture, ``{cfg}`` a config file
# holding ``config``), the exit code, and words the one-line message must contain. All fail
# before any training: the training entry points are replaced by a tripwire.

_NET_FILES = {
    "ragged": '{"layers": [{"weight": [[1.0, 2.0], [3.0]], "bias": [0.0, 0.0], '
              '"activation": "tanh"}]}',
    "strings": '{"layers": [{"weight": [["a", "b"]], "bias": [0.0], "activation": "tanh"}]}',
    "nanw": '{"layers": [{"weight": [[NaN, 2.0]], "bias": [0.0], "activation": "linear"}]}',
    "infw": '{"layers": [{"weight": [[Infinity, 2.0]], "bias": [0.0], "activation": "linear"}]}',
    "truncated": '{"layers": [{"weight": [[1.0, 2.0]], "bias": [0.0], "activ',
    "malformed": "{not json",
    "empty": "",
    "jlist": "[1, 2]",
    "nolayers": '{"layers": []}',
    "swish": '{"layers": [{"weight": [[1.0, 2.0]], "bias": [0.0], "activation": "swish"}]}',
    "badbias": '{"layers": [{"weight": [[1.0, 2.0]], "bias": [0.0, 1.0], '
               '"activation": "linear"}]}',
}


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    from nlyap_opt.design.control import lyapunov_matrix, quadratic_lyapunov

    d = tmp_path_factory.mktemp("bad")
    paths = {"tmp": str(d)}
    V = quadratic_lyapunov(lyapunov_matrix(systems.get("van_der_pol").A))
    paths["V"] = str(V.save(d / "V.json"))
    paths["V3"] = str(Network([Layer(np.ones((1, 3)), [0.0])]).save(d / "V3.json"))
    for name, text in _NET_FILES.items():
        (d / f"{name}.json").write_text(text)
        paths[name] = str(d / f"{name}.json")
    (d / "adir").mkdir()
    paths["dir"] = str(d / "adir")
    (d / "afile").write_text("x")
    paths["file"] = str(d / "afile")
    paths["missing"] = str(d / "nothing_here.json")
    (d / "portfolio").mkdir()
    (d / "portfolio" / "portfolio.json").write_text("{}")
    paths["portfolio"] = str(d / "portfolio")
    for name, file in (("otherrun", "certificate.json"), ("otherportfolio", "portfolio.json")):
        (d / name).mkdir()
        (d / name / file).write_text(json.dumps({"system": "inverted_pendulum"}))
        paths[name] = str(d / name)
    (d / "otherstages").mkdir()    # a run interrupted before its certificate was written
    (d / "otherstages" / "stages.json").write_text(json.dumps(
        {"quadratic": {"key": "0", "files": {}, "seal": "0", "system": "inverted_pendulum"}}))
    paths["otherstages"] = str(d / "otherstages")
    (d / "nanrun.toml").write_text('name = "n"\nstates = ["x"]\nstate_box = [[-1.0, 1.0]]\n'
                                   '[rhs]\nx = "-x"\n[run]\nouter = nan\n')
    paths["nanrun"] = str(d / "nanrun.toml")
    paths["cert_noproblem"] = str(d / "cert_noproblem.json")
    (d / "cert_noproblem.json").write_text(json.dumps({"status": "certified"}))
    return paths


@pytest.fixture(autouse=True)
def _tripwire(monkeypatch):
    """A bad input that reaches training fails the test at once (code 4), never trains."""
    import nlyap_opt.workflow.pipeline

    def boom(*a, **k):
        raise RuntimeError("TRIPWIRE: reached training")

    monkeypatch.setattr(nlyap_opt.workflow.pipeline, "run", boom)
    import baselines.compare

    monkeypatch.setattr(baselines.compare, "compare", boom)
    import nlyap_opt.interface.cli_dynamics
    import nlyap_opt.learned.dynamics_stage

    # every module that binds the φ stage by name (bound at import, so each is patched)
    for mod in (nlyap_opt.learned.dynamics_stage, nlyap_opt.workflow.pipeline,
                nlyap_opt.interface.cli_dynamics):
        if callable(getattr(mod, "dynamics_stage", None)):
            monkeypatch.setattr(mod, "dynamics_stage", boom)


VERIFY = ["verify", "--system", "van_der_pol", "--lyapunov", "{V}"]
RADII = ["--inner", "0.1", "--outer", "1"]
PEND_VERIFY = ["verify", "--system", "inverted_pendulum", "--lyapunov", "{V}", *RADII]
RUN = ["run", "van_der_pol", "--preset", "fast", "--config", "{cfg}", "--out", "{tmp}/r"]
PEND_RUN = ["run", "inverted_pendulum", "--preset", "fast", "--config", "{cfg}", "--out",
            "{tmp}/r"]
COMPARE = ["compare", "van_der_pol", "--preset", "fast", "--config", "{cfg}",
           "--out", "{tmp}/c"]
LEARN = ["learn-dynamics", "van_der_pol", "--fast", "--config", "{cfg}", "--out", "{tmp}/l"]


def _c(label, argv, words, config=None, code=3):
    return pytest.param(argv, code, words, config, id=label)


CLI_CASES = [
    # ---------------------------------------------------------------- usage, systems
    _c("no command", [], ["required"]),
    _c("unknown command", ["rn", "van_der_pol"], ["invalid choice", "run"]),
    _c("unknown top-level option", ["--verbose", "systems"], ["unrecognized", "--verbose"]),
    _c("systems extra argument", ["systems", "van_der_pol"], ["unrecognized"]),
    _c("systems unknown option", ["systems", "--all"], ["unrecognized", "--all"]),
    # ---------------------------------------------------------------- lqr
    _c("lqr no system", ["lqr"], ["required", "system"]),
    _c("lqr unknown system", ["lqr", "cartpoll"], ["unknown system", "inverted_pendulum"]),
    _c("lqr misspelt system", ["lqr", "inverted_pendlum"], ["did you mean", "inverted_pendulum"]),
    _c("lqr Q text", ["lqr", "inverted_pendulum", "--Q", "abc"], ["--Q", "abc"]),
    _c("lqr R beyond the solver", ["lqr", "inverted_pendulum", "--R", "1e20"],
       ["does not stabilise", "lost accuracy", "moderate weights"]),
    _c("lqr Q ragged", ["lqr", "inverted_pendulum", "--Q", "1,2;3"], ["--Q", "rows"]),
    _c("lqr Q with an underscore", ["lqr", "inverted_pendulum", "--Q", "1_0"], ["--Q", "1_0"]),
    _c("lqr Q in another script's digits", ["lqr", "inverted_pendulum", "--Q", "\u0967"],
       ["--Q"]),
    _c("run seeds in another script's digits", ["run", "van_der_pol", "--seeds", "\u0661"],
       ["--seeds"]),
    _c("verify radius with an underscore", ["verify", "--system", "van_der_pol", "--lyapunov",
                                            "{V}", "--inner", "1_0", "--outer", "2"],
       ["--inner"]),
    _c("lqr Q nan", ["lqr", "inverted_pendulum", "--Q", "nan"], ["--Q", "finite"]),
    _c("lqr Q inf", ["lqr", "inverted_pendulum", "--Q", "1,0;0,inf"], ["--Q", "finite"]),
    _c("lqr Q wrong size", ["lqr", "inverted_pendulum", "--Q", "1,0,0;0,1,0;0,0,1"],
       ["--Q", "2x2", "3x3"]),
    _c("lqr Q not symmetric", ["lqr", "inverted_pendulum", "--Q", "1,2;3,4"],
       ["--Q", "symmetric"]),
    _c("lqr Q negative", ["lqr", "inverted_pendulum", "--Q", "-1"], ["--Q", "semidefinite"]),
    _c("lqr Q empty", ["lqr", "inverted_pendulum", "--Q", ""], ["--Q"]),
    _c("lqr R zero", ["lqr", "inverted_pendulum", "--R", "0"], ["--R", "positive definite"]),
    _c("lqr R negative", ["lqr", "inverted_pendulum", "--R", "-2"],
       ["--R", "positive definite"]),
    _c("lqr R text", ["lqr", "inverted_pendulum", "--R", "one"], ["--R", "one"]),
    _c("lqr R wrong size", ["lqr", "inverted_pendulum", "--R", "1,0;0,1"], ["--R", "1x1"]),
    _c("lqr R nan", ["lqr", "unicycle_path_following", "--R", "nan"], ["--R", "finite"]),
    _c("lqr Q huge", ["lqr", "inverted_pendulum", "--Q", "1e308"], ["riccati", "weights"]),
    _c("lqr R tiny", ["lqr", "inverted_pendulum", "--R", "1e-308"], ["riccati", "weights"]),
    _c("lqr R without inputs", ["lqr", "van_der_pol", "--R", "1"], ["no inputs", "--R"]),
    _c("lqr json is a directory", ["lqr", "van_der_pol", "--json", "{dir}"],
       ["--json", "directory"]),
    _c("lqr json under a file", ["lqr", "van_der_pol", "--json", "{file}/k.json"],
       ["--json", "file"]),
    # ---------------------------------------------------------------- verify: arguments
    _c("verify nothing", ["verify"], ["--system", "--lyapunov", "--inner", "--outer"]),
    _c("run into another system's run", ["run", "van_der_pol", "--out", "{otherrun}"],
       ["holds a run of system 'inverted_pendulum'", "another --out"]),
    _c("run into another system's portfolio", ["run", "van_der_pol", "--seeds", "2",
                                               "--out", "{otherportfolio}"],
       ["portfolio.json", "'inverted_pendulum'"]),
    _c("run into another system's interrupted run", ["run", "van_der_pol", "--out",
                                                     "{otherstages}"],
       ["stages of a run of system 'inverted_pendulum'", "another --out"]),
    _c("compare into another system's run", ["compare", "van_der_pol", "--preset", "fast",
                                             "--out", "{otherrun}"],
       ["holds a run of system 'inverted_pendulum'"]),
    _c("simulate decay 0", ["simulate", "{dir}", "--filter", "clf-qp", "--nominal", "{V}",
                            "--decay", "0", "--out", "{tmp}/s"], ["--decay", "(0, 1]"]),
    _c("simulate decay negative", ["simulate", "{dir}", "--filter", "clf-qp", "--nominal",
                                   "{V}", "--decay", "-1", "--out", "{tmp}/s"],
       ["--decay", "(0, 1]"]),
    _c("simulate a portfolio", ["simulate", "{portfolio}", "--out", "{tmp}/s"],
       ["portfolio", "best"]),
    _c("verify V as controller", PEND_VERIFY + ["--controller", "{V}"],
       ["--controller", "kind 'lyapunov'", "controller.json"]),
    _c("verify V as dynamics", VERIFY + RADII + ["--dynamics", "{V}"],
       ["--dynamics", "kind 'lyapunov'", "dynamics.json"]),
    # a network without a kind, of the wrong shape: the learned-φ note printed before the error
    _c("verify dynamics of the wrong shape", VERIFY + RADII + ["--dynamics", "{V3}"],
       ["dynamics"]),
    _c("verify no radii", VERIFY, ["--inner", "--outer"]),
    _c("verify inner > outer", [*VERIFY, "--inner", "2", "--outer", "1"],
       ["--inner", "--outer"]),
    _c("verify inner = outer", [*VERIFY, "--inner", "1", "--outer", "1"], ["--inner"]),
    _c("verify inner negative", [*VERIFY, "--inner", "-0.1", "--outer", "1"],
       ["--inner", ">= 0"]),
    _c("verify inner nan", [*VERIFY, "--inner", "nan", "--outer", "1"], ["--inner", "finite"]),
    _c("verify inner text", [*VERIFY, "--inner", "abc", "--outer", "1"], ["--inner", "abc"]),
    _c("verify outer zero", [*VERIFY, "--inner", "0", "--outer", "0"], ["--outer", "> 0"]),
    _c("verify outer nan", [*VERIFY, "--inner", "0.1", "--outer", "nan"], ["--outer", "finite"]),
    _c("verify outer inf", [*VERIFY, "--inner", "0.1", "--outer", "inf"],
       ["--outer", "finite"]),
    _c("verify outer -inf", [*VERIFY, "--inner", "0.1", "--outer=-inf"], ["--outer"]),
    _c("verify level -1", [*VERIFY, *RADII, "--level", "-1"], ["--level", "> 0"]),
    _c("verify level 0", [*VERIFY, *RADII, "--level", "0"], ["--level", "> 0"]),
    _c("verify level nan", [*VERIFY, *RADII, "--level", "nan"], ["--level", "finite"]),
    _c("verify level inf", [*VERIFY, *RADII, "--level", "inf"], ["--level", "finite"]),
    _c("verify eta -5", [*VERIFY, *RADII, "--eta", "-5"], ["--eta", ">= 0"]),
    _c("verify eta nan", [*VERIFY, *RADII, "--eta", "nan"], ["--eta", "finite"]),
    _c("verify eta inf", [*VERIFY, *RADII, "--eta", "inf"], ["--eta", "finite"]),
    _c("verify margin negative", [*VERIFY, *RADII, "--margin", "-1"], ["--margin", ">= 0"]),
    _c("verify margin inf", [*VERIFY, *RADII, "--margin", "inf"], ["--margin", "finite"]),
    _c("verify smoothing negative", [*VERIFY, *RADII, "--eta", "0.1", "--smoothing", "-1"],
       ["--smoothing", ">= 0"]),
    _c("verify smoothing nan", [*VERIFY, *RADII, "--smoothing", "nan"], ["--smoothing"]),
    _c("verify smoothing without eta", [*VERIFY, *RADII, "--smoothing", "0.01"],
       ["--smoothing", "--eta"]),
    _c("verify resolution zero", [*VERIFY, *RADII, "--resolution", "0"], ["--resolution"]),
    _c("verify resolution negative", [*VERIFY, *RADII, "--resolution", "-1"],
       ["--resolution"]),
    _c("verify resolution text", [*VERIFY, *RADII, "--resolution", "fine"], ["--resolution"]),
    _c("verify precision with interval", [*VERIFY, *RADII, "--precision", "0.01"],
       ["--precision", "dreal"]),
    _c("verify resolution with dreal", [*VERIFY, *RADII, "--backend", "dreal",
                                        "--resolution", "0.01"], ["--resolution"]),
    _c("verify unknown backend", [*VERIFY, *RADII, "--backend", "z3"],
       ["--backend", "invalid choice"]),
    _c("verify unknown system", ["verify", "--system", "cartpoll", "--lyapunov", "{V}", *RADII],
       ["unknown system", "van_der_pol"]),
    # ---------------------------------------------------------------- verify: files
    _c("verify lyapunov missing", ["verify", "--system", "van_der_pol", "--lyapunov",
                                   "{missing}", *RADII], ["--lyapunov", "no such file"]),
    _c("verify lyapunov directory", ["verify", "--system", "van_der_pol", "--lyapunov",
                                     "{dir}", *RADII], ["--lyapunov", "directory"]),
    *[_c(f"verify lyapunov {name}", ["verify", "--system", "van_der_pol", "--lyapunov",
                                     "{" + name + "}", *RADII], words)
      for name, words in [("ragged", ["ragged"]), ("strings", ["string"]),
                          ("nanw", ["nan"]), ("infw", ["infinity"]),
                          ("truncated", ["json"]), ("malformed", ["json"]),
                          ("empty", ["json"]), ("jlist", ["layers"]),
                          ("nolayers", ["layer"]), ("swish", ["swish"]),
                          ("badbias", ["bias"]), ("V3", ["3"])]],
    _c("verify controller missing", [*PEND_VERIFY, "--controller", "{missing}"],
       ["--controller", "no such file"]),
    _c("verify controller ragged", [*PEND_VERIFY, "--controller", "{ragged}"], ["ragged"]),
    _c("verify controller wrong dims", [*PEND_VERIFY, "--controller", "{V3}"], ["3"]),
    _c("verify dynamics missing", [*VERIFY, *RADII, "--dynamics", "{missing}"],
       ["--dynamics", "no such file"]),
    _c("verify dynamics malformed", [*VERIFY, *RADII, "--dynamics", "{malformed}"], ["json"]),
    _c("verify dynamics directory", [*VERIFY, *RADII, "--dynamics", "{dir}"],
       ["--dynamics", "directory"]),
    _c("verify json is a directory", [*VERIFY, *RADII, "--json", "{dir}"],
       ["--json", "directory"]),
    _c("verify json under a file", [*VERIFY, *RADII, "--json", "{file}/v.json"],
       ["--json", "file"]),
    _c("verify certificate missing", ["verify", "--certificate", "{missing}"],
       ["--certificate", "no such file"]),
    _c("verify certificate dir without one", ["verify", "--certificate", "{dir}"],
       ["certificate.json", "no such file"]),
    _c("verify certificate with lyapunov", ["verify", "--certificate", "{file}",
                                            "--lyapunov", "{V}"], ["--certificate", "drop"]),
    _c("verify certificate with dreal", ["verify", "--certificate", "{file}", "--backend",
                                         "dreal"], ["--certificate", "drop --backend"]),
    _c("verify certificate with resolution", ["verify", "--certificate", "{file}",
                                              "--resolution", "0.01"],
       ["--certificate", "drop --resolution"]),
    _c("verify certificate malformed", ["verify", "--certificate", "{malformed}"], ["json"]),
    _c("verify certificate truncated", ["verify", "--certificate", "{truncated}"], ["json"]),
    _c("verify certificate without problem", ["verify", "--certificate", "{cert_noproblem}"],
       ["certificate"]),
    # ---------------------------------------------------------------- run: arguments, files
    _c("run no system", ["run"], ["required"]),
    _c("run unknown system", ["run", "cartpoll", "--out", "{tmp}/r"],
       ["unknown system", "van_der_pol"]),
    _c("run bad preset", ["run", "van_der_pol", "--preset", "huge"], ["--preset", "fast"]),
    _c("run config missing", ["run", "van_der_pol", "--config", "{missing}"],
       ["--config", "no such file"]),
    _c("run config directory", ["run", "van_der_pol", "--config", "{dir}"],
       ["--config", "directory"]),
    _c("run config malformed", ["run", "van_der_pol", "--config", "{malformed}"],
       ["not valid json"]),
    _c("run config truncated", ["run", "van_der_pol", "--config", "{truncated}"],
       ["not valid json"]),
    _c("run config empty", ["run", "van_der_pol", "--config", "{empty}"], ["not valid json"]),
    _c("run config a list", ["run", "van_der_pol", "--config", "{jlist}"], ["json object"]),
    _c("run out is a file", ["run", "van_der_pol", "--preset", "fast", "--out", "{file}"],
       ["--out", "is a file"]),
    _c("run out under a file", ["run", "van_der_pol", "--preset", "fast", "--out",
                                "{file}/sub"], ["--out", "file"]),
    # ---------------------------------------------------------------- run: config contents
    _c("cfg domain not a set", RUN, ["domain", "must be"], {"domain": [[-1, 1], [-1, 1]]}),
    _c("cfg domain unknown type", RUN, ["domain", "must be one of"], {"domain": {"type": "cube"}}),
    _c("cfg domain box rows", RUN, ["domain.box", "2 rows"],
       {"domain": {"type": "box", "box": [[-1, 1]]}}),
    _c("cfg domain box nan", RUN, ["domain.box", "finite"],
       {"domain": {"type": "box", "box": [[-1, 1], [-1, float("nan")]]}}),
    _c("cfg domain misses origin", RUN, ["domain", "origin"],
       {"domain": {"type": "box", "box": [[0.5, 1], [-1, 1]]}}),
    _c("cfg domain ellipsoid both", RUN, ["ellipsoid", "exactly one"],
       {"domain": {"type": "ellipsoid", "semi_axes": [1, 1], "matrix": [[1, 0], [0, 1]]}}),
    _c("cfg domain ellipsoid indefinite", RUN, ["domain.matrix", "positive definite"],
       {"domain": {"type": "ellipsoid", "matrix": [[1, 2], [2, 1]]}}),
    _c("cfg domain and outer", RUN, ["both 'outer'", "domain"],
       {"domain": {"type": "ball", "radius": 1.0}, "outer": 1.0}),
    _c("cfg inner ball leaves domain", RUN, ["inner ball", "domain"],
       {"domain": {"type": "box", "box": [[-0.2, 1], [-1, 1]]}}),
    _c("cfg initial set too large", RUN, ["initial set", "domain"],
       {"domain": {"type": "box", "box": [[-1, 1], [-1, 1]]},
        "initial_set": {"type": "ball", "radius": 2.0}}),
    _c("cfg initial set unknown key", RUN, ["initial_set", "unknown key"],
       {"initial_set": {"type": "ball", "radius": 0.2, "center": [0, 0]}}),
    _c("cfg unknown top key", RUN, ["unknown key 'outre'", "did you mean 'outer'"],
       {"outre": 1.0}),
    _c("cfg unknown train key", RUN, ["train.stpes", "train.steps"], {"train": {"stpes": 5}}),
    _c("cfg unknown cegis key", RUN, ["cegis.iteratons", "cegis.iterations"],
       {"cegis": {"iteratons": 2}}),
    _c("cfg unknown dynamics key", RUN, ["dynamics.hiden", "dynamics.hidden"],
       {"dynamics": {"hiden": 5}}),
    _c("cfg unknown lqr key", RUN, ["lqr.q", "lqr.Q"], {"lqr": {"q": 1}}),
    _c("cfg unknown section", RUN, ["trian", "did you mean 'train'"], {"trian": {}}),
    _c("cfg unknown verify option", RUN, ["verify_options.resolutoin", "resolution"],
       {"cegis": {"verify_options": {"resolutoin": 0.1}}}),
    _c("cfg section key at top", RUN, ["train.steps", "cegis.steps"], {"steps": 5}),
    _c("cfg train time_budget", RUN, ["time_budget", "steps"], {"train": {"time_budget": 9}}),
    _c("cfg cegis time_budget", RUN, ["time_budget", "steps"], {"cegis": {"time_budget": 9}}),
    _c("cfg dynamics time_budget", RUN, ["time_budget", "steps"],
       {"dynamics": {"time_budget": 9}}),
    _c("cfg lr string", RUN, ["train.lr", "finite number"], {"train": {"lr": "0.1"}}),
    _c("cfg lr NaN", RUN, ["train.lr", "nan"], '{"train": {"lr": NaN}}'),
    _c("cfg lr Infinity", RUN, ["train.lr", "infinity"], '{"train": {"lr": Infinity}}'),
    _c("cfg lr negative", RUN, ["train.lr", "> 0"], {"train": {"lr": -0.1}}),
    _c("cfg steps zero", RUN, ["train.steps", ">= 1"], {"train": {"steps": 0}}),
    _c("cfg steps float", RUN, ["train.steps", "integer"], {"train": {"steps": 2.5}}),
    _c("cfg steps bool", RUN, ["train.steps", "integer"], {"train": {"steps": True}}),
    _c("cfg hidden empty", RUN, ["train.hidden", "non-empty"], {"train": {"hidden": []}}),
    _c("cfg hidden string", RUN, ["train.hidden"], {"train": {"hidden": [4, "a"]}}),
    _c("cfg hidden scalar", RUN, ["train.hidden", "list"], {"train": {"hidden": 6}}),
    _c("cfg hidden zero", RUN, ["train.hidden", ">= 1"], {"train": {"hidden": [0]}}),
    _c("cfg lr_schedule", RUN, ["lr_schedule", "cosine"], {"train": {"lr_schedule": "linear"}}),
    _c("cfg fit_transform", RUN, ["fit_transform", "log"], {"train": {"fit_transform": "exp"}}),
    _c("cfg fit_quantile", RUN, ["fit_quantile", "<= 1"], {"train": {"fit_quantile": 1.5}}),
    _c("cfg train_controller", RUN, ["train_controller", "true or false"],
       {"train": {"train_controller": "yes"}}),
    _c("cfg seed negative", RUN, ["train.seed", ">= 0"], {"train": {"seed": -1}}),
    _c("cfg margin_mode", RUN, ["margin_mode", "did you mean 'pointwise'"],
       {"cegis": {"margin_mode": "pointwize"}}),
    _c("cfg iterations zero", RUN, ["cegis.iterations", ">= 1"], {"cegis": {"iterations": 0}}),
    _c("cfg min_iterations", RUN, ["min_iterations", "iterations"],
       {"cegis": {"min_iterations": 5}}),
    _c("cfg norm_smoothing", RUN, ["norm_smoothing", ">= 0"],
       {"cegis": {"norm_smoothing": -1e-3}}),
    _c("cfg sim_dt", RUN, ["sim_dt", "> 0"], {"cegis": {"sim_dt": 0}}),
    _c("cfg first_steps", RUN, ["first_steps"], {"cegis": {"first_steps": 0}}),
    _c("cfg verify resolution", RUN, ["resolution", "> 0"],
       {"cegis": {"verify_options": {"resolution": -1}}}),
    _c("cfg verify_options list", RUN, ["verify_options", "json object"],
       {"cegis": {"verify_options": [1]}}),
    _c("cfg inner >= outer", RUN, ["inner", "outer"], {"inner": 2.0}),
    _c("cfg inner zero", RUN, ["inner", "> 0"], {"inner": 0}),
    _c("cfg outer NaN", RUN, ["outer", "nan"], '{"outer": NaN}'),
    _c("cfg outer string", RUN, ["outer", "finite number"], {"outer": "3"}),
    _c("cfg outer negative", RUN, ["outer", "> 0"], {"outer": -1}),
    _c("cfg eval_points", RUN, ["eval_points", ">= 4"], {"eval_points": 1}),
    _c("cfg eval_grid (renamed)", RUN, ["eval_grid", "eval_points"], {"eval_grid": 200}),
    _c("cfg eval_box rows", RUN, ["eval_box", "2 states"], {"eval_box": [[0, 1]]}),
    _c("cfg eval_box order", RUN, ["eval_box", "lo < hi"], {"eval_box": [[1, 0], [0, 1]]}),
    _c("cfg controller_scale null", PEND_RUN, ["controller_scale", "input"],
       {"controller_scale": None}),
    _c("cfg controller_scale zero", PEND_RUN, ["controller_scale", "> 0"],
       {"controller_scale": 0}),
    _c("cfg controller_scale list length", PEND_RUN, ["controller_scale", "1 input"],
       {"controller_scale": [1.0, 2.0]}),
    _c("cfg controller_scale list NaN", PEND_RUN, ["controller_scale", "NaN"],
       '{"controller_scale": [NaN]}'),
    _c("cfg controller_scale no inputs", RUN, ["controller_scale", "no inputs"],
       {"controller_scale": 5}),
    _c("cfg lqr Q string", PEND_RUN, ["lqr.Q"], {"lqr": {"Q": "abc"}}),
    _c("cfg lqr Q ragged", PEND_RUN, ["lqr.Q"], {"lqr": {"Q": [[1, 0], [0]]}}),
    _c("cfg lqr Q size", PEND_RUN, ["lqr.Q", "2x2"], {"lqr": {"Q": [[1, 0, 0]] * 3}}),
    _c("cfg lqr Q NaN", PEND_RUN, ["lqr.Q", "finite"], '{"lqr": {"Q": [[NaN, 0], [0, 1]]}}'),
    _c("cfg lqr R tiny", PEND_RUN, ["lqr", "weights"], {"lqr": {"R": 1e-308}}),
    _c("cfg lqr R zero", PEND_RUN, ["lqr.R", "positive definite"], {"lqr": {"R": 0}}),
    _c("cfg dynamics preset", RUN, ["preset", "slow"], {"dynamics": {"preset": "slow"}}),
    _c("cfg dynamics model", RUN, ["model", "quadratic"], {"dynamics": {"model": "quadratic"}}),
    _c("cfg dynamics steps", RUN, ["steps", "-1"], {"dynamics": {"steps": -1}}),
    _c("cfg dynamics inputs", RUN, ["inputs", "'model' or 'all'"],
       {"dynamics": {"inputs": "some"}}),
    _c("cfg dynamics box too small", RUN, ["state_box", "outer"],
       {"dynamics": {"state_box": [[-0.5, 0.5], [-0.5, 0.5]]}}),
    _c("cfg section not an object", RUN, ["train", "json object"], {"train": 5}),
    _c("cfg dynamics not an object", RUN, ["dynamics"], {"dynamics": [1]}),
    _c("cfg other system", RUN, ["inverted_pendulum", "van_der_pol"],
       {"system": "inverted_pendulum"}),
    _c("cfg other preset", RUN, ["preset", "large"], {"preset": "large"}),
    # ---------------------------------------------------------------- compare
    _c("compare unknown system", ["compare", "cartpoll"], ["unknown system"]),
    _c("compare bad preset", ["compare", "van_der_pol", "--preset", "big"], ["--preset"]),
    _c("compare unknown key", COMPARE, ["train.stpes"], {"train": {"stpes": 1}}),
    _c("compare NaN", COMPARE, ["outer", "nan"], '{"outer": NaN}'),
    _c("compare out is a file", ["compare", "van_der_pol", "--preset", "fast", "--out",
                                 "{file}"], ["--out", "is a file"]),
    _c("compare config missing", ["compare", "van_der_pol", "--config", "{missing}"],
       ["no such file"]),
    # ---------------------------------------------------------------- learn-dynamics
    _c("learn unknown system", ["learn-dynamics", "cartpoll", "--out", "{tmp}/l"],
       ["unknown system"]),
    _c("learn no out", ["learn-dynamics", "van_der_pol"], ["--out"]),
    _c("learn out is a file", ["learn-dynamics", "van_der_pol", "--fast", "--out", "{file}"],
       ["--out", "is a file"]),
    _c("learn config missing", ["learn-dynamics", "van_der_pol", "--config", "{missing}",
                                "--out", "{tmp}/l"], ["no such file"]),
    _c("learn config malformed", ["learn-dynamics", "van_der_pol", "--config", "{malformed}",
                                  "--out", "{tmp}/l"], ["json"]),
    _c("learn unknown key", LEARN, ["grid_count", "grid_counts"], {"grid_count": [3, 3]}),
    _c("learn time_budget", LEARN, ["time_budget", "steps"], {"time_budget": 5}),
    _c("learn NaN", LEARN, ["lr"], '{"lr": NaN}'),
    _c("learn bad model", ["learn-dynamics", "van_der_pol", "--model", "quadratic",
                           "--out", "{tmp}/l"], ["--model", "invalid choice"]),
    # a seed beyond what torch seeds with was exit 4; an empty --bound was ignored
    _c("learn huge seed", ["learn-dynamics", "van_der_pol", "--seed", "9" * 23, "--out",
                           "{tmp}/l"], ["--seed", "at most"]),
    _c("learn huge config seed", LEARN, ["seed", "2^53"], {"seed": 10**23}),
    _c("learn empty bound", ["learn-dynamics", "van_der_pol", "--bound", "", "--out",
                             "{tmp}/l"], ["bound_model", "'best'"]),
    # ---------------------------------------------------------------- config
    _c("config unknown system", ["config", "cartpoll"], ["unknown system"]),
    _c("config no system", ["config"], ["system", "--keys"]),
    _c("config unknown key", ["config", "van_der_pol", "--config", "{cfg}"], ["train.stpes"],
       {"train": {"stpes": 1}}),
    # ---------------------------------------------------------------- files that are not files
    _c("config is a device", ["config", "van_der_pol", "--config", "/dev/zero"],
       ["/dev/zero", "not a regular file"]),
    _c("spec is a device", ["systems", "--check", "/dev/zero"], ["not a regular file"]),
    _c("certificate is a device", ["verify", "--certificate", "/dev/zero"],
       ["not a regular file"]),
    _c("spec run table nan", ["systems", "--check", "{nanrun}"], ["finite", "nan"]),
    # the value came from the spec's [run] table: named so (it said "run config")
    _c("spec run table nan in run", ["run", "{nanrun}", "--out", "{tmp}/nr"],
       ["nanrun.toml [run]", "outer"]),
    _c("cfg duplicate key", RUN, ["outer", "appears twice"], '{"outer": 1.0, "outer": 2.0}'),
    _c("cfg count beyond 2^53", RUN, ["train.steps", "2^53"], {"train": {"steps": 10**30}}),
    _c("run seeds huge", ["run", "van_der_pol", "--seeds", "99999999999999999999"],
       ["--seeds", "10000"]),
]


def _fill(argv, files, config, label):
    values = dict(files)
    if config is not None:
        p = f"{files['tmp']}/{label.replace(' ', '_')}.json"
        with open(p, "w") as fh:
            fh.write(config if isinstance(config, str) else json.dumps(config))
        values["cfg"] = p
    return [a.format(**values) for a in argv]


def test_systems_check_reads_a_factory_spec_without_running_it_and_any_name_loads(
        tmp_path, capsys):
    """``systems --check`` reads files and runs nothing: a spec whose system is built by
    Python code (here ``os:abort``, which would end the process) is described, not
    imported. A system name CasADi would not accept as a Function name (``my-system``)
    loads too."""
    from nlyap_opt.interface.cli import main

    f = tmp_path / "factory.toml"
    f.write_text('name = "t"\nfactory = "os:abort"\n')
    assert main(["systems", "--check", str(f)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["factory"] == "os:abort" and "does not run" in out["note"]
    g = tmp_path / "named.toml"
    g.write_text('name = "my-system"\nstates = ["x"]\nstate_box = [[-1.0, 1.0]]\n'
                 '[rhs]\nx = "-x"\n')
    assert main(["systems", "--check", str(g)]) == 0
    assert json.loads(capsys.readouterr().out)["name"] == "my-system"
    assert systems.load_spec(g).A.tolist() == [[-1.0]]


def test_systems_check_refuses_what_run_refuses_and_runs_nothing(tmp_path, capsys):
    """``systems --check`` checks what ``config``/``run`` check before anything runs: a
    factory spec that also defines the system (refused without importing the factory,
    ``os:abort`` here) and a ``[run]`` table with a value out of range."""
    from nlyap_opt.interface.cli import main

    f = tmp_path / "both.toml"
    f.write_text('name = "t"\nfactory = "os:abort"\nstates = ["x"]\n'
                 'state_box = [[-1.0, 1.0]]\n[rhs]\nx = "-x"\n')
    g = tmp_path / "neg.toml"
    g.write_text('name = "t_neg"\nstates = ["x"]\nstate_box = [[-1.0, 1.0]]\n'
                 '[rhs]\nx = "-x"\n[run]\nouter = -1.0\n')
    for path, words in ((f, ["factory defines the system", "remove"]),
                        (g, ["outer must be a finite number > 0", "correct"])):
        for command in (["systems", "--check"], ["config"]):
            assert main(command + [str(path)]) == 3
            err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
            assert len(err) == 1 and all(w in err[0] for w in words), (command, err)


def test_cli_table_has_over_100_cases():
    assert len(CLI_CASES) >= 100
    commands = {c.values[0][0] for c in CLI_CASES if c.values[0]}
    assert {"systems", "lqr", "verify", "run", "compare", "learn-dynamics"} <= commands | \
        {"systems"}


@pytest.mark.parametrize("argv,code,words,config", CLI_CASES)
def test_cli_bad_input(argv, code, words, config, files, capsys, request):
    from nlyap_opt.interface.cli import main

    label = request.node.callspec.id
    with warnings.catch_warnings(record=True) as caught:  # a warning prints more lines
        warnings.simplefilter("always")
        got = main(_fill(argv, files, config, label))
    out = capsys.readouterr()
    shown = [str(w.message) for w in caught
             if not issubclass(w.category, (DeprecationWarning, PendingDeprecationWarning))]
    assert not shown, shown
    assert "Traceback" not in out.err and "TRIPWIRE" not in out.err, out.err
    lines = [ln for ln in out.err.splitlines() if ln.strip()]
    assert got == code, out.err
    assert len(lines) == 1 and lines[0].startswith("nlyap: error: "), out.err
    assert ";" in lines[0], lines[0]  # the problem; the fix
    for w in words:
        assert w.lower() in lines[0].lower(), (w, lines[0])


@pytest.mark.parametrize("argv", [
    ["verify", "--system", "van_der_pol", "--lyapunov", "{V}", "--inner", "2", "--outer", "1"],
    ["run", "van_der_pol", "--config", "{cfg}"],
])
def test_cli_bad_input_in_a_real_process(argv, files, tmp_path):
    import subprocess
    import sys

    cfg = tmp_path / "c.json"
    cfg.write_text('{"train": {"stpes": 1}}')
    argv = [a.format(**files, cfg=str(cfg)) for a in argv]
    res = subprocess.run([sys.executable, "-m", "nlyap_opt.interface.cli", *argv],
                         capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 3, res.stderr
    assert "Traceback" not in res.stderr
    assert res.stderr.strip().count("\n") == 0 and res.stderr.startswith("nlyap: error:")


def test_load_spec_without_factories_decides_on_the_bytes_it_parses(tmp_path):
    """``load_spec(allow_factory=False)`` refuses a factory spec itself (the callers' own
    look at the file is not what keeps the code from running); a TOML integer of thousands
    of digits is a one-line error."""
    from nlyap_opt.kernel.errors import ConfigError

    f = tmp_path / "factory.toml"
    f.write_text('name = "t"\nfactory = "os:abort"\n')
    with pytest.raises(ConfigError, match="factory"):
        systems.load_spec(f, allow_factory=False)
    g = tmp_path / "big.toml"
    g.write_text('name = "t"\nstates = ["x"]\nstate_box = [[-1.0, 1.0]]\n[rhs]\nx = "-x"\n'
                 "[parameters]\nk = " + "9" * 5000 + "\n")
    with pytest.raises(ConfigError, match="cannot be read"):
        systems.load_spec(g)


def test_run_into_a_directory_whose_certificate_is_a_pipe_does_not_wait(tmp_path, capsys):
    """The check for another system's run reads certificate.json as every input is read:
    a pipe there is not waited on (the run went on and was stopped by the tripwire)."""
    import os

    from nlyap_opt.interface.cli import main

    os.mkfifo(tmp_path / "certificate.json")
    assert main(["run", "van_der_pol", "--preset", "fast", "--out", str(tmp_path)]) == 4
    assert "TRIPWIRE" in capsys.readouterr().err
