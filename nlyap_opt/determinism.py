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
    torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(old_det, warn_only=old_warn)
        torch.set_num_threads(old_threads)
