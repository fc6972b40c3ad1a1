"""The public Python functions refuse wrong arguments with the tool's own errors (a
:class:`~nlyap_opt.kernel.errors.NlyapError`, one line naming the argument), not with an
exception raised deep inside numpy or CasADi."""

import casadi as ca
import numpy as np
import pytest

import systems
from nlyap_opt.certification.certificate import RoaProblem, certify_roa, recheck_certificate
from nlyap_opt.design.control import linear_controller, lqr, quadratic_lyapunov
from nlyap_opt.kernel.errors import NlyapError
from nlyap_opt.kernel.network import Layer, Network, load_network
from nlyap_opt.kernel.symbolic import closed_loop, lie_derivative
from nlyap_opt.kernel.walker import evaluate
from nlyap_opt.workflow.configs import make_config
from nlyap_opt.workflow.pipeline import run


@pytest.mark.parametrize("call, words", [
    (lambda: quadratic_lyapunov(np.array([[1.0, 2.0], [0.0, 1.0]])),
     ["P must be positive definite", "(P + Pᵀ)/2"]),
    (lambda: quadratic_lyapunov(-np.eye(2)), ["P must be positive definite", "-1"]),
    (lambda: quadratic_lyapunov(np.ones(2)), ["P must be a square matrix", "(2,)"]),
    (lambda: quadratic_lyapunov("abc"), ["P must be a square matrix"]),
    (lambda: lqr(systems.get("inverted_pendulum"), R=-1), ["R must be positive definite"]),
    (lambda: lqr(systems.get("inverted_pendulum"), Q=np.full((2, 2), np.nan)),
     ["Q has entries that are not finite"]),
    (lambda: lqr(systems.get("inverted_pendulum"), Q="1,0;0,1"),
     ["Q must be a matrix of numbers"]),
    (lambda: lqr("inverted_pendulum"), ["lqr needs a System", "systems.get"]),
    (lambda: RoaProblem([1], quadratic_lyapunov(np.eye(2))), ["system must be a System"]),
    (lambda: RoaProblem(systems.get("inverted_pendulum"), "V.json"),
     ["V must be a Network", "Network.load"]),
    (lambda: recheck_certificate(123), ["certificate.json file or its directory"]),
    (lambda: systems.register("api_errors_zz", systems.get("van_der_pol")),
     ["factory must be a callable", "lambda: s"]),
], ids=["P-asymmetric-indefinite", "P-negative", "P-vector", "P-text", "R-negative", "Q-nan",
        "Q-text",
        "lqr-name", "problem-system", "problem-V", "recheck-int", "register-system"])
def test_wrong_arguments_raise_the_tools_errors(call, words):
    with pytest.raises(NlyapError) as err:
        call()
    msg = str(err.value)
    assert "\n" not in msg and all(w in msg for w in words), msg
    assert "api_errors_zz" not in systems.names()


def test_an_asymmetric_p_is_its_symmetric_part():
    """xᵀPx depends on (P + Pᵀ)/2 only: an asymmetric P with a positive definite symmetric
    part is that V, not an error."""
    P = np.array([[2.0, 1.0], [0.0, 2.0]])
    x = np.array([[0.3, -0.7], [1.0, 2.0]])
    np.testing.assert_allclose(quadratic_lyapunov(P).numpy(x)[:, 0],
                               np.einsum("ni,ij,nj->n", x, P, x), rtol=1e-12)


PEND = systems.get("inverted_pendulum")
V2 = quadratic_lyapunov(np.eye(2))
X2 = ca.MX.sym("x", 2)
F2 = ca.Function("f", [X2], [ca.sumsqr(X2)])


@pytest.mark.parametrize("call, words", [
    (lambda: closed_loop("inverted_pendulum"), ["closed_loop needs a System"]),
    (lambda: closed_loop(PEND, "controller.json"), ["controller must be a Network"]),
    (lambda: closed_loop(PEND, x=np.zeros(2)), ["x must be a CasADi symbol of shape (2, 1)"]),
    (lambda: lie_derivative(V2.casadi(X2), X2, ca.MX.zeros(3)), ["rhs has shape (3, 1)"]),
    (lambda: lie_derivative(V2.casadi(X2), X2, ca.SX.zeros(2)), ["of one kind", "SX"]),
    (lambda: lie_derivative(None, X2, X2), ["of one kind"]),
    (lambda: evaluate(F2, [np.zeros((3, 3))]), ["trailing dimension of 2"]),
    (lambda: evaluate(F2, []), ["takes 1 input(s)", "0 array(s)"]),
    (lambda: evaluate(F2, [[0.0]]), ["trailing dimension of 2"]),
    (lambda: evaluate(F2, [0.0]), ["trailing dimension of 2"]),
    (lambda: evaluate(F2, None), ["takes 1 input(s)", "NoneType"]),
    (lambda: evaluate(F2, [np.zeros(2)], "interval"), ["arith must be an arithmetic"]),
    (lambda: evaluate(lambda x: x, [np.zeros(2)]), ["needs a casadi.Function"]),
    (lambda: evaluate(F2, [["a", "b"]]), ["must be arrays of numbers"]),
    (lambda: Network([1, 2]), ["layer 0 is a int, not a Layer"]),
    (lambda: Network("abc"), ["layers must be a list of Layer"]),
    (lambda: Network([Layer(np.ones((1, 2)), [0.0])], meta=[1]), ["meta must be a dict"]),
    (lambda: V2.numpy("ab"), ["network input must be an array of numbers"]),
    (lambda: load_network(None), ["needs a file path"]),
    (lambda: load_network(5), ["needs a file path"]),
    (lambda: Network([Layer(np.ones((1, 2)), [0.0])], meta={"a": {1, 2}}).save("/tmp/x.json"),
     ["meta holds a value JSON cannot write"]),
    (lambda: certify_roa(None, 0.5), ["problem must be RoaProblem"]),
    (lambda: certify_roa(RoaProblem(systems.get("van_der_pol"), V2), 0.5, inner_ellipse="x"),
     ["inner_ellipse must be"]),
    (lambda: certify_roa(RoaProblem(systems.get("van_der_pol"), V2), 0.5, log=None),
     ["log must be a function"]),
    (lambda: RoaProblem(PEND, V2, controller=V2), ["controller is a network of kind "
                                                   "'lyapunov'"]),
    (lambda: RoaProblem(systems.get("van_der_pol"), V2,
                        controller=linear_controller(PEND, np.ones((1, 2)))),
     ["which has no inputs: pass controller=None"]),
    (lambda: RoaProblem(PEND, V2, verify_options={"foo": 1}), ["unknown verifier option 'foo'"]),
    (lambda: RoaProblem(PEND, V2, verify_options={"resolution": -1}), ["'resolution' must be"]),
    (lambda: RoaProblem(PEND, V2, outer=True), ["outer must be a number"]),
    (lambda: RoaProblem(PEND, V2, dynamics=Network([Layer(np.ones((2, 3)), [0.0, 0.0])]),
                        dynamics_box=[[-3, 3]], input_box=[[-1, 1]]),
     ["dynamics_box must be 2 rows"]),
    (lambda: run("inverted_pendulum", make_config("inverted_pendulum", "fast"), ""),
     ["out must be the path of a directory"]),
    (lambda: make_config("inverted_pendulum", "fast", file=5), ["file must be the path"]),
])
def test_public_functions_name_the_wrong_argument(call, words, tmp_path, monkeypatch):
    """These raised AttributeError, TypeError, IndexError or CasADi's RuntimeError from
    inside (and run(out="") wrote a run into the working directory)."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(NlyapError) as err:
        call()
    msg = str(err.value)
    assert "\n" not in msg and all(w in msg for w in words), msg
    assert not any(tmp_path.iterdir())   # nothing written


def test_numpy_scalars_are_verifier_options_as_pythons_numbers():
    p = RoaProblem(PEND, V2, verify_options={"max_boxes": np.int64(1000),
                                             "resolution": np.float64(1e-3),
                                             "second_order": np.bool_(True)})
    assert p.verify_options == {"max_boxes": 1000, "resolution": 1e-3, "second_order": True}
    assert type(p.verify_options["max_boxes"]) is int


X2S, U1S = ca.SX.sym("x", 2), ca.SX.sym("u", 1)


@pytest.mark.parametrize("call, words", [
    (lambda: systems.System(5, X2S, U1S, ca.vertcat(X2S[1], U1S), state_box=[[-1, 1]] * 2,
                            input_box=[[-1, 1]]), ["name must be a non-empty str"]),
    (lambda: systems.System("a", "x", U1S, ca.vertcat(X2S[1], U1S), state_box=[[-1, 1]] * 2,
                            input_box=[[-1, 1]]), ["x must be a column of casadi.SX"]),
    (lambda: systems.System("a", X2S, U1S, ca.vertcat(X2S[1], U1S), state_box="box",
                            input_box=[[-1, 1]]), ["state_box must be 2 rows"]),
    (lambda: systems.System.from_callable("c", 5, nx=2, state_box=[[-1, 1]] * 2),
     ["fun must be a callable"]),
    (lambda: systems.System.from_callable("c", lambda x, u: -x, nx="2",
                                          state_box=[[-1, 1]] * 2), ["nx must be an int"]),
    (lambda: systems.get("van_der_pol", mu="a"), ["cannot be built with", "numbers"]),
    (lambda: systems.get("van_der_pol", zzz=1), ["takes the parameters mu", "zzz"]),
    (lambda: systems.get(["a"]), ["unknown system"]),
    (lambda: systems.load_spec(None), ["needs the path of a spec file"]),
])
def test_the_systems_package_names_the_wrong_argument(call, words):
    """CasADi's NotImplementedError, numpy's ValueError and Python's TypeError came out."""
    with pytest.raises(NlyapError) as err:
        call()
    msg = str(err.value)
    assert "\n" not in msg and all(w in msg for w in words), msg
