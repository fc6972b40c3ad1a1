"""The public Python functions refuse wrong arguments with the tool's own errors (a
:class:`~nlyap_opt.kernel.errors.NlyapError`, one line naming the argument), not with an
exception raised deep inside numpy or CasADi."""

import numpy as np
import pytest

import systems
from nlyap_opt.certification.certificate import RoaProblem, recheck_certificate
from nlyap_opt.design.control import lqr, quadratic_lyapunov
from nlyap_opt.kernel.errors import NlyapError


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
