"""Deterministic torch training: a fixed thread count and deterministic algorithms, scoped.

Wall-clock budgets are gone from every training loop (a timed loop gives another
network on a loaded machine); what remains to make a seeded run bit-identical on any
machine load is the thread count of torch's CPU kernels
(a reduction split over a different number of threads sums in a different order) and
torch's choice among non-deterministic algorithms. :func:`deterministic_torch` fixes both
for the duration of a ``with`` block and restores the caller's settings afterwards.

Examples
--------
>>> import torch
>>> before = torch.get_num_threads()
>>> with deterministic_torch(1):
...     torch.get_num_threads()
1
>>> torch.get_num_threads() == before
True
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from contextlib import contextmanager

from . import deps
from .errors import ConfigError

__all__ = ["deterministic_torch"]


@contextmanager
def deterministic_torch(threads: int = 1) -> Iterator[None]:
    """Run the block with ``threads`` torch threads and deterministic algorithms.

    Parameters
    ----------
    threads : int
        Intra-op threads of torch inside the block (a fixed number: the result depends on
        it, never on the machine's load).

    Raises
    ------
    ConfigError
        ``threads`` is not a positive integer.
    """
    torch = deps.torch()

    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ConfigError(f"torch threads must be a positive integer, got {threads!r}")
    old_threads = torch.get_num_threads()
    old_det = torch.are_deterministic_algorithms_enabled()
    old_warn = torch.is_deterministic_algorithms_warn_only_enabled()
    torch.set_num_threads(threads)
    _set_deterministic(True, False)
    try:
        yield
    finally:
        _set_deterministic(old_det, old_warn)
        torch.set_num_threads(old_threads)


def _set_deterministic(mode: bool, warn_only: bool) -> None:
    """Set torch's deterministic-algorithms flag for its eager kernels.

    ``torch.use_deterministic_algorithms`` also sets the flag of torch's inductor compiler,
    and importing that compiler's configuration loads ``torch._dynamo`` and sympy: about
    1.2 CPU seconds (4-5 s wall on a loaded machine) in every process that trains, the
    first seed on each worker of a portfolio included. Nothing here compiles with
    inductor, so while it is not loaded only the eager flag is set (the same kernels are
    chosen); once something has loaded it, the public call sets both.
    """
    torch = deps.torch()
    setter = getattr(torch._C, "_set_deterministic_algorithms", None)
    if setter is None or "torch._inductor.config" in sys.modules:
        torch.use_deterministic_algorithms(mode, warn_only=warn_only)
    else:
        setter(bool(mode), warn_only=bool(warn_only))
