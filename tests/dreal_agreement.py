"""The dReal agreement check, shared by the real-dReal test and the tests that show it can fail.

δ-SAT is not a proof (a δ-weakened formula may hold where the exact one does not): the
refuted case must come back ``counterexample`` with a point that rigorous evaluation
confirms; ``unknown`` is a wrong answer there.
"""

import numpy as np
from certcheck import assert_confirmed

import systems
from baselines.lqr import quadratic_lyapunov
from verification import closed_loop_problem
from verification.verify import confirm_points

P_VDP = np.array([[1.5, -0.5], [-0.5, 1.0]])


def agreement_problems():
    """(verified case, refuted case) of the Van der Pol quadratic V (see test_verify.py)."""
    s = systems.get("van_der_pol")
    V = quadratic_lyapunov(P_VDP)
    return (closed_loop_problem(s, V, inner=0.1, outer=1.0),
            closed_loop_problem(s, V, inner=0.1, outer=1.2))


def check_dreal_agreement(run) -> None:
    """``run(problem, precision=...)`` -> VerificationResult must give the right verdicts."""
    ok_problem, bad_problem = agreement_problems()
    ok = run(ok_problem, precision=1e-4)
    assert ok.status == "verified", ok.status
    bad = run(bad_problem, precision=1e-3)
    assert bad.status == "counterexample", (
        f"refuted case answered {bad.status!r}: the maximum of the Lie derivative on "
        "|x| = 1.2 is about +0.165, so dReal's δ-SAT box must hold a confirmable point")
    assert bad.counterexample.property == "decrease"
    assert_confirmed(bad_problem, bad.counterexample)
    for c in bad.counterexamples:
        assert_confirmed(bad_problem, c)  # float64
        assert confirm_points(bad_problem, c.point[None, :]), "not confirmed rigorously"
