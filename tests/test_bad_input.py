"""Bad input: each a specific exception with a message that says what fixes it."""

import json
import warnings

import casadi as ca
import numpy as np
import pytest
import torch

import systems
from baselines.lqr import lqr, saturated_controller
from nlyap_opt.errors import (
    DimensionError,
    EquilibriumError,
    EquilibriumWarning,
    NetworkFileError,
    NotStabilizableError,
    UnknownNameError,
    UnsupportedLayerError,
)
from nlyap_opt.network import Layer, Network, from_torch
from nlyap_opt.symbolic import closed_loop


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
    ctrl.layers[0].bias[:] = 0.1974  # the seed's hand-typed bias (PITFALLS P4)
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
