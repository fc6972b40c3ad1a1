"""Argument types of the ``nlyap`` commands (argparse ``type=`` callables), shared by
:mod:`nlyap_opt.interface.cli` and the commands it registers: each refuses a bad value with one line
that names what is expected."""

from __future__ import annotations

import argparse
import math
import re

__all__ = ["RADIUS_MAX", "connect_timeout_arg", "inner_radius", "nonneg", "number",
           "outer_radius", "plain_float", "positive", "seed", "seeds", "time_limit_arg",
           "workers"]

_FLOAT = re.compile(r"\s*[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?\s*", re.ASCII)
_INT = re.compile(r"\s*[+-]?\d+\s*", re.ASCII)


def plain_float(text: str) -> float:
    """A number written as plain ASCII decimals (``1``, ``-0.5``, ``2e-3``); ``ValueError``
    for anything else that Python's ``float`` would take (``1_0``, other scripts' digits,
    ``inf``, ``nan``)."""
    if not isinstance(text, str) or not _FLOAT.fullmatch(text):
        raise ValueError(f"not a plain decimal number: {text!r}")
    return float(text)


def number(check, want: str):
    """An argparse type: a finite float for which ``check`` holds, else ``want`` in the
    message."""

    def parse(text: str) -> float:
        try:
            v = plain_float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {want}, got {text!r}") from None
        if not math.isfinite(v) or not check(v):
            raise argparse.ArgumentTypeError(f"must be {want}, got {text}")
        return v

    parse.__name__ = want
    return parse


nonneg = number(lambda v: v >= 0, "a finite number >= 0")
positive = number(lambda v: v > 0, "a finite number > 0")
#: the largest radius ``verify`` takes (its square, summed over the states, stays finite)
RADIUS_MAX = 1e100
inner_radius = number(lambda v: 0 <= v <= RADIUS_MAX,
                      f"a finite number >= 0 and <= {RADIUS_MAX:g}")
outer_radius = number(lambda v: 0 < v <= RADIUS_MAX,
                      f"a finite number > 0 and <= {RADIUS_MAX:g}")
#: the longest --time-limit (a year: the interval timer takes seconds a C time_t holds)
TIME_LIMIT_MAX = 366 * 24 * 3600.0
time_limit_seconds = number(lambda v: 0 < v <= TIME_LIMIT_MAX,
                            f"a finite number of seconds in (0, {TIME_LIMIT_MAX:g}]")
connect_timeout_arg = number(lambda v: 0 < v <= 3600, "a finite number of seconds in (0, 3600]")


def _int_at_least(text: str, low: int) -> int:
    """``text`` as an integer ``>= low``; otherwise the argparse error naming the bound."""
    if not _INT.fullmatch(text):
        raise argparse.ArgumentTypeError(f"expected an integer >= {low}, got {text!r}")
    v = int(text)
    if v < low:
        raise argparse.ArgumentTypeError(f"must be an integer >= {low}, got {v}")
    return v


#: the largest seed (the random generators of numpy and torch take 32-bit seeds alike) and
#: the most seeds of one portfolio
MAX_SEED, MAX_SEEDS = 2**32 - 1, 10_000


def seed(text: str) -> int:
    """An integer in ``[0, MAX_SEED]``."""
    v = _int_at_least(text, 0)
    if v > MAX_SEED:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_SEED}, got {v}")
    return v


def seeds(text: str) -> int | list[int]:
    """``--seeds K`` (seeds 0..K-1) or ``--seeds 0,3,7``."""
    parts = [p.strip() for p in text.split(",")]
    if not all(_INT.fullmatch(p) for p in parts):
        raise argparse.ArgumentTypeError(
            f"expected a count K >= 1 or seeds like 0,3,7, got {text!r}")
    vals = [int(p) for p in parts]
    if len(vals) == 1 and "," not in text:
        if not 1 <= vals[0] <= MAX_SEEDS:
            raise argparse.ArgumentTypeError(f"the number of seeds must be between 1 and "
                                             f"{MAX_SEEDS}, got {vals[0]}")
        return vals[0]
    if any(not 0 <= v <= MAX_SEED for v in vals) or len(set(vals)) != len(vals) or \
            len(vals) > MAX_SEEDS:
        raise argparse.ArgumentTypeError(f"seeds must be at most {MAX_SEEDS} distinct integers "
                                         f"in [0, {MAX_SEED}], got {text!r}")
    return vals


def workers(text: str) -> int:
    """An integer >= 1."""
    return _int_at_least(text, 1)


def time_limit_arg(sp) -> None:
    """Add ``--time-limit SECONDS`` (a guard that stops the command, exit 5) to ``sp``."""
    sp.add_argument("--time-limit", type=time_limit_seconds, metavar="SECONDS",
                    dest="time_limit",
                    help="stop after SECONDS of wall time with exit code 5, keeping the "
                         "finished stages (the same command resumes); results never depend "
                         "on it: every training budget is a count of steps")


def recheck_system_args(sp, system_help: str | None = None) -> None:
    """``--system`` and ``--allow-factory`` of the commands that re-check a saved run
    (``verify --certificate``, ``simulate``, ``export``); ``system_help`` replaces the help
    of ``--system`` (``verify``, where it is also the system to verify)."""
    sp.add_argument("--system",
                    help=system_help or "catalogue name or spec file (TOML): the system to "
                         "re-check the run against (default: the catalogue system its "
                         "certificate names, or the factory-free spec file it names)")
    sp.add_argument("--allow-factory", action="store_true", dest="allow_factory",
                    help="run the Python factory of the --system spec file (never run "
                         "otherwise)")
