"""Rigorous verification of Lyapunov conditions over CasADi graphs.

Problem / Result / one-shot function::

    problem = lyapunov_problem(x, V, lie, inner=0.1, outer=1.0, margin=beta)
    result = verify(problem)              # interval backend (default), or backend="dreal"
    result.status                          # "verified" | "counterexample" | "unknown"
"""

from __future__ import annotations

from .backends import BACKENDS, Backend, get_backend
from .formula import Formula, build_formula
from .interval import Interval, IntervalArithmetic
from .problem import (
    Counterexample,
    QueryStatus,
    VerificationProblem,
    VerificationResult,
    closed_loop_problem,
    lyapunov_problem,
)
from .smtlib import evaluate_smtlib, to_smtlib, write_smtlib

__all__ = [
    "verify", "QueryStatus", "VerificationProblem", "VerificationResult", "Counterexample",
    "lyapunov_problem", "closed_loop_problem", "Interval", "IntervalArithmetic", "BACKENDS",
    "Backend",
    "get_backend", "to_smtlib", "write_smtlib", "evaluate_smtlib", "Formula", "build_formula",
]


def verify(problem: VerificationProblem, *, backend: str = "interval",
           **options) -> VerificationResult:
    """Decide whether the properties of ``problem`` hold on its region.

    Parameters
    ----------
    problem : VerificationProblem
    backend : {"interval", "dreal"}
        ``"interval"`` (default): sound branch-and-prune with outward rounding.
        ``"dreal"``: optional; δ-SAT boxes are confirmed by interval evaluation.
    **options
        Backend options. Interval: ``resolution`` (smallest box width; below it a box is
        ``unknown``), ``max_boxes``, ``batch``, ``mean_value``, ``affine``, ``backward``
        (backward linear bound propagation, off by default), ``slope_steps`` (with
        ``backward``: optimised slopes, 0 by default), ``second_order``, ``presearch``,
        ``stop_at_first``, ``keep_leaves``, ``executor`` (any
        ``concurrent.futures.Executor``: a process pool or a Dask client's executor),
        ``n_tasks``. dReal: ``precision``.

    Returns
    -------
    VerificationResult
        ``status`` is ``"verified"``, ``"counterexample"`` (a confirmed point) or
        ``"unknown"``.
    """
    return get_backend(backend).verify(problem, **options)
