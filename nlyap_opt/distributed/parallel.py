"""Dask distributed for the whole tool: one client helper and load-balanced verification.

One helper, :func:`dask_client`, gives every parallel job of nlyap_opt (the multi-seed
portfolio, :mod:`nlyap_opt.workflow.portfolio`, and distributed verification,
:func:`verify_distributed`) its Dask client:

- by default a ``LocalCluster`` that the tool starts and stops itself (worker processes,
  one thread each, no dashboard, bound to 127.0.0.1, quiet logs);
- with ``scheduler="tcp://HOST:PORT"`` an existing cluster (``dask scheduler`` on one
  machine, ``dask worker tcp://HOST:PORT --nthreads 1`` on each of the others), which is
  only connected to and never closed.

Dask is imported when a client is asked for, so the rest of the package imports without it.

Examples
--------
>>> from nlyap_opt.distributed.parallel import dask_client, verify_distributed
>>> with dask_client(workers=2) as client:                      # doctest: +SKIP
...     result = verify_distributed(problem, client)
>>> result.status                                                # doctest: +SKIP
'verified'

Several machines (the same nlyap_opt and Dask versions installed on each)::

    # on the scheduler machine (its address: tcp://HOST:8786)
    dask scheduler --host HOST --port 8786 --no-dashboard
    # on every worker machine: one single-threaded worker per core
    export MALLOC_TRIM_THRESHOLD_=1073741824 MALLOC_MMAP_THRESHOLD_=33554432
    dask worker tcp://HOST:8786 --nthreads 1 --nworkers N --no-dashboard
    # anywhere
    nlyap verify ... --scheduler tcp://HOST:8786
    nlyap run NAME --seeds 8 --scheduler tcp://HOST:8786 --out /shared/runs/pf

The two ``export`` lines matter: Dask's nanny sets ``MALLOC_TRIM_THRESHOLD_=65536`` for
its workers, which turns glibc's adaptive allocator off and makes the interval verifier
about 4x slower (measured); a value set in the environment wins over Dask's, and the local
cluster of :func:`dask_client` leaves it unset. A portfolio's ``--out`` must be a
directory that every worker and the calling process see (a shared filesystem). The
scheduler only listens where ``--host`` says; keep it on a private network.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import copy
import hashlib
import heapq
import inspect
import io
import logging
import math
import os
import re
import socket
import threading
import time
import zipfile
from collections.abc import Iterator

import casadi as ca
import numpy as np

import verification
from verification.precondition import hessian_coordinates, solve_preconditioned
from verification.problem import VerificationResult
from verification.verify import (
    MAX_PARTITION_ENTRIES,
    confirm_points,
    partition_leaves,
    split_box,
    verify_interval,
)

from ..kernel import deps
from ..kernel.errors import BackendUnavailableError, ConfigError
from ..kernel.jsonio import read_npz
from ..kernel.walker import NUMPY, Program, compile_function, evaluate

__all__ = ["dask_client", "verify_distributed", "verifying_on", "check", "ahead", "Ahead",
           "Proofs", "proving", "proving_active", "from_proof",
           "SimulatedCluster", "model_speedups", "task_defaults", "pass_boxes",
           "parse_scheduler", "client_workers", "cpu_cores", "check_connect_timeout",
           "MAX_LOCAL_WORKERS", "DEFAULT_CONNECT_TIMEOUT"]

#: ``tcp://HOST:PORT`` (also ``tls://``); a bare ``HOST:PORT`` means ``tcp://``
_ADDRESS = re.compile(r"^(?:(tcp|tls)://)?(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.\-]+):(\d{1,5})$")
_INSTALL = "Dask is not installed; run: pip install 'dask[distributed]'"


def _distributed():
    """The ``distributed`` module, or a one-line install hint."""
    try:
        distributed = deps.distributed()
    except ImportError:
        raise BackendUnavailableError(_INSTALL) from None
    return distributed


def parse_scheduler(address: str) -> str:
    """Check a scheduler address and return it as ``tcp://HOST:PORT``.

    Parameters
    ----------
    address : str
        ``tcp://HOST:PORT``, ``tls://HOST:PORT`` or ``HOST:PORT``.

    Returns
    -------
    str
        The address with its protocol.

    Raises
    ------
    ConfigError
        The address is not of that form or the port is out of 1..65535.

    Examples
    --------
    >>> parse_scheduler("127.0.0.1:8786")
    'tcp://127.0.0.1:8786'
    """
    if not isinstance(address, str):
        raise ConfigError(f"scheduler address must be a string like tcp://HOST:PORT, got "
                          f"{address!r}")
    m = _ADDRESS.match(address.strip())
    if m is None:
        raise ConfigError(f"scheduler address must look like tcp://HOST:PORT, got {address!r}; "
                          "pass the address that `dask scheduler` prints")
    proto, host, port = m.group(1) or "tcp", m.group(2), int(m.group(3))
    if not 1 <= port <= 65535:
        raise ConfigError(f"scheduler port must be in 1..65535, got {port} in {address!r}")
    return f"{proto}://{host}:{port}"


#: the most worker processes of a local cluster (a cluster of more machines: a scheduler)
MAX_LOCAL_WORKERS = 256
#: seconds a connection to a scheduler may take, its first answer included
DEFAULT_CONNECT_TIMEOUT = 10.0


def _check_workers(workers, local: bool = True) -> int | None:
    if workers is None:
        return None
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise ConfigError(f"workers must be an integer >= 1, got {workers!r}; "
                          "pass e.g. workers=2 (or leave it out: one per CPU core)")
    if local and workers > MAX_LOCAL_WORKERS:
        raise ConfigError(f"workers = {workers} local worker processes; at most "
                          f"{MAX_LOCAL_WORKERS} are started on this machine: pass fewer, or "
                          "start a cluster and give its scheduler address")
    return int(workers)


def check_connect_timeout(seconds) -> float:
    """``seconds`` as a finite positive number (:class:`ConfigError` otherwise)."""
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float, np.floating)) \
            or not math.isfinite(seconds) or not 0 < seconds <= 3600:
        raise ConfigError(f"connect timeout must be a number of seconds in (0, 3600], got "
                          f"{seconds!r}; pass e.g. 10")
    return float(seconds)


def _probe_scheduler(address: str, timeout: float) -> None:
    """Reach the scheduler at ``address`` and have it answer, all within ``timeout``.

    A plain TCP connection first (a closed port is refused at once), then Dask's handshake
    and one ``identity`` call on an event loop of its own in a helper thread, abandoned at
    the deadline: a listener that accepts and never answers ends here, not in a hang.
    :class:`ConfigError` with the address when either fails.
    """

    get_address_host_port = _distributed().comm.get_address_host_port
    deadline = time.monotonic() + timeout

    def fail(why: str):
        return ConfigError(f"no Dask scheduler answered at {address} within {timeout:g} s "
                           f"({why}); start `dask scheduler` there, fix the address, or "
                           "raise the connect timeout")

    try:
        host, port = get_address_host_port(address)
        with socket.create_connection((host, port), timeout=timeout):
            pass
    except (OSError, ValueError) as err:
        raise fail(type(err).__name__) from None
    if address.startswith("tls://"):   # the TLS handshake needs the security settings
        return
    outcome: list = []

    def ask():
        rpc = _distributed().core.rpc
        async def identity():
            async with rpc(address) as r:
                return await r.identity()

        async def bounded():
            return await asyncio.wait_for(identity(), max(deadline - time.monotonic(), 0.01))

        try:
            outcome.append(asyncio.run(bounded()))
        except BaseException as err:  # noqa: BLE001 - reported to the caller as a refusal
            outcome.append(err)

    t = threading.Thread(target=ask, name="nlyap-scheduler-probe", daemon=True)
    t.start()
    t.join(max(deadline - time.monotonic(), 0.0) + 1.0)
    if t.is_alive() or not outcome:
        raise fail("no answer")
    if isinstance(outcome[0], BaseException):
        raise fail(type(outcome[0]).__name__)
    if not isinstance(outcome[0], dict) or outcome[0].get("type") != "Scheduler":
        raise fail("not a scheduler")


def cpu_cores() -> int:
    """CPU cores this process may run on (the default number of local workers)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


@contextlib.contextmanager
def dask_client(workers: int | None = None, scheduler: str | None = None, *,
                timeout: float = 60.0,
                connect_timeout: float = DEFAULT_CONNECT_TIMEOUT) -> Iterator:
    """A Dask client: on a local cluster started here, or on an existing cluster.

    Parameters
    ----------
    workers : int, optional
        Without ``scheduler``: the number of worker processes of the ``LocalCluster``
        (default: the number of CPU cores this process may use). With ``scheduler``: wait
        (up to ``timeout``) until at least this many workers are connected. At most
        :data:`MAX_LOCAL_WORKERS` for a local cluster.
    scheduler : str, optional
        Address ``tcp://HOST:PORT`` of a running Dask scheduler. The cluster is connected
        to, never closed; without it a ``LocalCluster`` is started and closed on exit
        (processes, one thread per worker, ``dashboard_address=None``, host 127.0.0.1,
        logs at error level only).
    timeout : float
        Seconds to wait for the workers (and a local cluster to start).
    connect_timeout : float
        Seconds to reach the scheduler at ``scheduler`` and have it answer (default
        :data:`DEFAULT_CONNECT_TIMEOUT`); a closed port fails at once, a listener that
        never answers after this time.

    Yields
    ------
    distributed.Client

    Raises
    ------
    ConfigError
        ``workers`` < 1, a malformed address, or no scheduler / not enough workers at the
        address within ``timeout``.
    BackendUnavailableError
        Dask is not installed (with the install command).

    Examples
    --------
    >>> with dask_client(workers=2) as client:                      # doctest: +SKIP
    ...     client.submit(sum, [1, 2]).result()
    3
    """
    workers = _check_workers(workers, local=scheduler is None)
    address = None if scheduler is None else parse_scheduler(scheduler)
    if not (isinstance(timeout, (int, float)) and timeout > 0):
        raise ConfigError(f"timeout must be a positive number of seconds, got {timeout!r}")
    connect_timeout = check_connect_timeout(connect_timeout)
    distributed = _distributed()

    if address is not None:
        _probe_scheduler(address, connect_timeout)
        try:
            client = distributed.Client(address, timeout=connect_timeout,
                                        set_as_default=False)
        except (OSError, TimeoutError) as err:
            raise ConfigError(f"no Dask scheduler answered at {address} within "
                              f"{connect_timeout:g} s ({type(err).__name__}); start `dask "
                              "scheduler` there or fix the address") from None
        try:
            if workers:
                try:
                    client.wait_for_workers(workers, timeout=timeout)
                except (TimeoutError, OSError):
                    have = len(client.scheduler_info().get("workers", {}))
                    raise ConfigError(
                        f"the scheduler at {address} has {have} worker(s) after {timeout:g} s, "
                        f"{workers} asked for; start more `dask worker {address}` or lower "
                        "workers") from None
            yield client
        finally:
            client.close()
        return

    dask = deps.dask()
    n = workers or cpu_cores()
    # Dask's nannies export MALLOC_TRIM_THRESHOLD_=65536 to their workers; an explicit
    # threshold turns off glibc's adaptive mmap threshold, and the verifier's many large
    # temporaries then run 4x slower (measured). Workers started here keep glibc's default.
    with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None,
                          "distributed.worker.profile.enabled": False}):
        cluster = distributed.LocalCluster(
            n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
            dashboard_address=None, worker_dashboard_address=None,
            silence_logs=logging.ERROR, scheduler_port=0,
            # the scheduler always serves its small HTTP API (health, metrics; no dashboard
            # without bokeh, and none asked for): on a free loopback port, not *:8787
            scheduler_kwargs={"dashboard": False, "dashboard_address": "127.0.0.1:0"})
    try:
        client = distributed.Client(cluster, timeout=timeout, set_as_default=False)
        try:
            yield client
        finally:
            client.close()
    finally:
        cluster.close(timeout=timeout)


def client_workers(client) -> int:
    """Number of workers (threads in all) currently connected to ``client``'s scheduler."""
    info = client.scheduler_info().get("workers", {})
    return max(1, sum(int(w.get("nthreads", 1)) for w in info.values()))


# ---------------------------------------------------------------------------- verification
def _starts_from_boxes() -> bool:
    """Whether ``verify_interval`` accepts ``boxes=`` (start from given sub-boxes, batched)."""

    return "boxes" in inspect.signature(verify_interval).parameters


def _split(out_boxes: np.ndarray, resolution: float, n: int
           ) -> tuple[np.ndarray, np.ndarray]:
    """``(unknown, open)``: boxes at the resolution, and boxes still to bisect."""
    if not len(out_boxes):
        return np.zeros((0, n, 2)), np.zeros((0, n, 2))
    wide = np.max(out_boxes[:, :, 1] - out_boxes[:, :, 0], axis=1) > resolution
    return out_boxes[~wide], out_boxes[wide]


def _pack(r, resolution: float, n: int) -> dict:
    unknown, open_ = _split(r.undecided, resolution, n)
    if r.open is not None and len(r.open):  # hand_back: halves not evaluated yet
        open_ = np.concatenate([open_, r.open])
    return {"found": r.counterexamples, "unknown": unknown, "open": open_, "boxes": r.boxes,
            "depth": r.depth, "leaves": r.leaves or []}


def _box_task(problem, boxes: np.ndarray, budget: int, options: dict, batched: bool,
              tail: int = 0) -> dict:
    """Worker side: bisect ``boxes`` ``(k, n, 2)`` by the serial verifier's rules until
    ``budget`` boxes are spent; what it would still bisect comes back *open*.

    ``batched``: all boxes start in one batch (``verify_interval(boxes=...)``). Otherwise
    each box is a serial run of its own (a restricted copy of the problem, sharing its
    compiled CasADi Functions), run to the end (``budget`` is then the global cap).
    ``tail`` (batched): a queue that shrinks below this many boxes comes back open too.
    """
    t, w = time.thread_time(), time.time()
    out = _decide_boxes(problem, boxes, budget, options, batched, tail)
    return dict(out, cpu=time.thread_time() - t, pid=os.getpid(), span=(w, time.time()))


def _decide_boxes(problem, boxes, budget, options, batched, tail: int = 0) -> dict:
    res = options["resolution"]
    if batched:
        r = verify_interval(problem, boxes=boxes, max_boxes=budget, presearch=0,
                            hand_back=True, hand_back_below=tail, **options)
        return _pack(r, res, problem.n)
    found, unknown, open_, leaves = [], [], [], []
    used, depth = 0, 0
    for i, box in enumerate(boxes):
        if used >= budget:
            open_.append(boxes[i:])
            break
        sub = copy.copy(problem)
        sub.box = np.asarray(box, dtype=float)
        r = verify_interval(sub, max_boxes=max(1, budget - used), presearch=0, **options)
        part = _pack(r, res, problem.n)
        used += r.boxes
        depth = max(depth, r.depth)
        found += part["found"]
        leaves += part["leaves"]
        unknown.append(part["unknown"])
        open_.append(part["open"])
        if found and options["stop_at_first"]:
            break
    empty = np.zeros((0, problem.n, 2))
    return {"found": found, "unknown": np.concatenate([empty] + unknown),
            "open": np.concatenate([empty] + open_), "boxes": used, "depth": depth,
            "leaves": leaves}


def _root_task(problem, options: dict, presearch: int, initial_boxes: int,
               budget: int) -> dict:
    """Worker side: the pre-search and the serial verifier on the root box until ``budget``
    boxes are spent (``budget = 0``: only the root box itself is evaluated)."""

    t, w = time.thread_time(), time.time()
    more = {"hand_back": True} if budget else {}  # batched: the halves go on unevaluated
    r = verify_interval(problem, max_boxes=budget, presearch=presearch,
                        initial_boxes=initial_boxes, **more, **options)
    return dict(_pack(r, options["resolution"], problem.n), cpu=time.thread_time() - t,
                pid=os.getpid(), span=(w, time.time()))


class _CountingArithmetic:
    """Float arithmetic (numpy) that counts its calls and the scalar results they make."""

    name = "numpy"

    def __init__(self):
        self._np = NUMPY
        self.calls = 0
        self.elements = 0

    def _tally(self, y, per: int = 1):
        self.calls += 1
        self.elements += int(np.size(y)) * per
        return y

    def constant(self, value):
        return self._np.constant(value)

    def unary(self, op, a):
        return self._tally(self._np.unary(op, a))

    def binary(self, op, a, b):
        return self._tally(self._np.binary(op, a, b))

    def matmul(self, a, b):
        return self._tally(self._np.matmul(a, b), per=int(np.shape(a)[-1]))

    def sum(self, a, axis):
        self._tally(a)
        return self._np.sum(a, axis)

    def structural(self, fn, *args):
        return self._np.structural(fn, *args)


#: boxes per unit of (arithmetic calls / scalar results) of a pass: an interval operation
#: costs about this many times more as a call than per box it encloses (measured on 2
#: cores for the cartpole certificate's checks, query (A) and Van der Pol 2-6, all within
#: a factor of 2 of it)
_BOXES_PER_CALL_RATIO = 2000


def pass_boxes(problem, second_order: bool = False) -> int:
    """Boxes at which a walker pass over ``problem``'s graphs costs as much per box as it
    costs fixed: the least start of a task that is not mostly fixed cost.

    A pass costs a fixed time per arithmetic call (one per graph instruction, the
    instructions of called Functions included) and a time per scalar result per box. Both
    are counted, deterministically, by one float walk of the fused ``(F, J)`` graph at one
    point (with ``second_order``, the verifier's option, also of the properties' gradient
    and Hessian graphs, which its rounds walk too); the estimate is
    :data:`_BOXES_PER_CALL_RATIO` times calls per scalar result, rounded up to a power of
    two (in ``[1, 8192]``). Scalar graphs (a system's ``f`` as SX, called from the
    networks' MX graph: every operation one call per box batch) give about 1024; networks
    of matrix products about 128.

    Examples
    --------
    >>> import numpy as np, systems
    >>> from baselines.lqr import quadratic_lyapunov
    >>> from verification import closed_loop_problem
    >>> V = quadratic_lyapunov(np.eye(2))
    >>> pass_boxes(closed_loop_problem(systems.get("van_der_pol"), V, inner=0.1, outer=1.0))
    2048
    """
    fun = problem.function_jacobian_checked if problem.checked else problem.function_jacobian
    ar = _CountingArithmetic()
    point = np.mean(np.asarray(problem.box, dtype=float), axis=1)[None, :]
    funs = [fun, *(problem.second_order_functions if second_order else ())]
    with np.errstate(all="ignore"):
        for f in funs:
            evaluate(f, [point], ar)
    ratio = ar.calls / max(1, ar.elements)
    boxes = max(1.0, min(8192.0, _BOXES_PER_CALL_RATIO * ratio))
    return 1 << int(math.ceil(math.log2(boxes)))


def task_defaults(workers: int, batch: int = 8192, pass_size: int | None = None) -> dict:
    """The task sizes :func:`verify_distributed` uses on ``workers`` workers by default.

    The work is over-decomposed in proportion to the workers: the root task stops sooner,
    tasks start from fewer open boxes and spend fewer boxes before they hand the rest back,
    so that on many workers none waits for a long task while the others idle. On one or two
    workers the grains stay coarse (each walker pass costs a fixed time per instruction of
    the graphs besides its time per box): two workers get the grains of one, measured best
    on two cores (the cartpole certificate's decrease check, 2 workers).

    Parameters
    ----------
    workers : int
        Worker threads of the cluster.
    batch : int
        The verifier's boxes per walker pass (the grain everything is measured in).
    pass_size : int, optional
        The problem's :func:`pass_boxes` (boxes at which a pass costs as much per box as
        fixed). On more than two workers no task starts from fewer (up to ``batch``; a
        quarter during the ramp-up, see :func:`verify_distributed`), and a task's
        budget is at least four times its least start: a task whose passes are
        thinner than that spends most of its time on the passes' fixed cost (on the
        cartpole certificate's decrease check, tasks started from a median of 458 boxes
        cost 3.2 times the serial CPU seconds in all).

    Returns
    -------
    dict
        ``task_boxes``, ``tasks_per_worker``, ``root_boxes``, ``min_task_boxes``.

    Examples
    --------
    >>> task_defaults(1)
    {'task_boxes': 16384, 'tasks_per_worker': 1, 'root_boxes': 2048, 'min_task_boxes': 1024}
    >>> task_defaults(16)
    {'task_boxes': 2048, 'tasks_per_worker': 2, 'root_boxes': 128, 'min_task_boxes': 128}
    >>> task_defaults(16, pass_size=1024)
    {'task_boxes': 4096, 'tasks_per_worker': 2, 'root_boxes': 128, 'min_task_boxes': 1024}
    """
    w = max(1, int(workers))
    w = 1 if w <= 2 else w  # up to two workers: the grains measured best on two cores
    grain = max(1, int(batch))
    out = {"task_boxes": min(grain, 2048) if grain < 2048 else max(2048, 2 * grain // w),
           "tasks_per_worker": 1 if w <= 2 else 2,
           "root_boxes": max(1, grain // (4 * w)),
           "min_task_boxes": max(min(128, grain // 8), grain // (8 * w), 1)}
    if w > 2 and pass_size is not None:
        out["min_task_boxes"] = max(out["min_task_boxes"], min(int(pass_size), grain))
        out["task_boxes"] = max(out["task_boxes"], 4 * out["min_task_boxes"])
    return out


def _deal_boxes(boxes: np.ndarray, parts: int) -> list[np.ndarray]:
    """``boxes`` dealt into ``parts`` strided shares: share ``i`` holds boxes ``i``,
    ``i + parts``, ``i + 2·parts``, ...

    The verifier's queue lists neighbouring boxes next to each other, and the hard boxes
    (near a level set, near the inner ball) come in clusters: contiguous chunks would give
    one task a whole cluster, strided shares give every task a part of each. Sizes differ by
    one at most; every box is in exactly one share, in its queue order.

    Examples
    --------
    >>> [s[:, 0, 0].tolist() for s in _deal_boxes(np.arange(5.0).reshape(5, 1, 1), 2)]
    [[0.0, 2.0, 4.0], [1.0, 3.0]]
    """
    parts = max(1, min(int(parts), len(boxes)))
    return [boxes[i::parts] for i in range(parts)]


class _DaskRunner:
    """The tasks of one :func:`verify_distributed` call on a Dask client."""

    def __init__(self, client, problem):
        self.client = client
        self.workers = client_workers(client)
        [self.pf] = client.scatter([problem], broadcast=True, hash=False)
        self.ac = _distributed().as_completed([], loop=client.loop)
        self.submitted: list = []

    def submit(self, fn, *args):
        fut = self.client.submit(fn, self.pf, *args, pure=False)
        self.submitted.append(fut)
        self.ac.add(fut)
        return fut.key

    def next(self):
        """``(key, output)`` of the next task to finish, ``None`` when none is left."""
        with _waiting():  # another check may take its turn meanwhile (ahead())
            fut = next(self.ac, None)
        if fut is None:
            return None
        out = fut.result()
        fut.release()
        return fut.key, out

    def close(self):
        self.client.cancel([f for f in self.submitted if not f.done()])
        self.pf.release()


class SimulatedCluster:
    """A stand-in for a Dask client that models ``workers`` workers: the speed-up model.

    Pass it to :func:`verify_distributed` (or to :func:`verifying_on`) in place of a client:
    every task runs here, in this process, when it is submitted, and is scheduled on
    ``workers`` virtual workers by list scheduling (a task starts on the first worker to
    be free, in the order of submission, as Dask's scheduler hands out queued tasks), its
    duration its *cost*. Completions are absorbed in the order of their virtual finishing
    times, so the task graph is the one :func:`verify_distributed` builds on a real cluster
    of that size; only the clock is modelled. ``cost="boxes"``: the boxes a task processed
    (deterministic: the same run gives the same model on any machine and load);
    ``cost="cpu"``: its CPU seconds here (which include each walker pass's fixed cost).

    Other jobs (the seeds of :func:`nlyap_opt.workflow.portfolio.run_portfolio`) submit
    plain tasks: :meth:`submit` runs ``fn`` at once and returns a finished future; its cost
    is its CPU seconds here (``cost="cpu"``), and each virtual worker pays ``startup``
    seconds before its first such task (a worker process's start: imports, first use of
    torch), which the caller measures in a fresh process. Waiting for a future
    (``result()``, ``done()``) moves the modelled clock to its finish, so that tasks
    submitted after it start no sooner.

    Attributes
    ----------
    workers : int
    cost : str
    startup : float
    calls : list of dict
        Per :func:`verify_distributed` call, in the order they end (and one for all plain
        tasks): ``makespan`` (modelled time from the call's start to its last completion),
        ``work`` (the sum of the task costs, one ``startup`` included, which is the time on
        one worker), ``tasks`` (count) and, for a verification, ``start`` (the modelled time
        it started at) and ``boxes`` (processed). Calls made side by side (:class:`Ahead`
        threads, as :func:`nlyap_opt.certification.certificate.certify_roa` runs condition
        (c) on a cluster) share the virtual workers, in modelled time, as their tasks share
        a cluster's. By CPU seconds, a virtual worker's first task of a call also pays
        compiling the problem's graphs (timed afresh here), as a worker process does.
    modelling_seconds : float
        CPU seconds this process spent on the model itself (timing each problem's
        compilation, which the workers' first tasks are charged), not part of the run.
    compile_seconds : float
        The compilations charged to the virtual workers' first tasks (part of
        :meth:`work`).

    Examples
    --------
    >>> sim = SimulatedCluster(4)                                 # doctest: +SKIP
    >>> verify_distributed(problem, sim).status                   # doctest: +SKIP
    'verified'
    >>> sim.speedup()                                             # doctest: +SKIP
    3.6
    """

    simulated = True

    def __init__(self, workers: int, cost: str = "boxes", startup: float = 0.0):
        self.workers = _check_workers(workers, local=False)
        if cost not in ("boxes", "cpu"):
            raise ConfigError(f"cost must be 'boxes' or 'cpu', got {cost!r}")
        if isinstance(startup, bool) or not isinstance(startup, (int, float)) or \
                not math.isfinite(startup) or startup < 0:
            raise ConfigError(f"startup must be a finite number of seconds >= 0, got "
                              f"{startup!r}")
        self.cost = cost
        self.startup = float(startup)
        self.calls: list[dict] = []
        self.modelling_seconds = 0.0  # CPU this process spent on the model itself
        self.compile_seconds = 0.0    # compiling charged to the virtual workers
        self._plain: dict | None = None  # the schedule of plain tasks (submit)
        # the verification tasks of every call share the virtual workers and one clock:
        # checks that run side by side (:class:`Ahead` threads) are list-scheduled together
        # (time, worker) at which each virtual worker is free (a heap)
        self._free = [(0.0, w) for w in range(self.workers)]
        self._now = 0.0                     # the modelled time of the last completion
        self._end = 0.0                     # the last completion absorbed by any call
        self._seq = 0
        self._runs: list[_SimRun] = []      # calls in progress
        self._cv = threading.Condition()
        self._runnable = 1                  # threads of this model not waiting for it

    def _block(self) -> None:
        """A thread stops running (it waits for a task or for another thread): when none
        runs any more, the earliest completion of all calls goes to its call's thread."""
        with self._cv:
            self._runnable -= 1
            self._deliver()

    def _unblock(self) -> None:
        with self._cv:
            self._runnable += 1

    def _deliver(self) -> None:
        """With the condition held: if no thread runs, hand the earliest pending completion
        (modelled finish time, then submission order) to the call it belongs to."""
        if self._runnable > 0:
            return
        heads = [(run.pending[0][:2], run) for run in self._runs
                 if run.pending and run.delivered is None]
        if not heads:
            return
        (finish, _), run = min(heads, key=lambda h: h[0])
        finish, key, out = heapq.heappop(run.pending)
        self._now = max(self._now, finish)
        self._end = max(self._end, finish)
        run.last = finish
        run.delivered = (key, out)
        self._runnable += 1
        self._cv.notify_all()

    def _runner(self, problem) -> _SimRun:
        return _SimRun(self, problem)

    def submit(self, fn, *args, pure: bool | None = None, **kwargs) -> _SimFuture:
        """Run ``fn(*args, **kwargs)`` now; schedule it on the first free virtual worker.

        Its cost is its CPU seconds (thread time) here; a worker's first task also pays
        :attr:`startup`. ``pure`` is accepted for Dask's signature and ignored.
        """
        if self.cost != "cpu":
            raise ConfigError("plain tasks are modelled by their CPU seconds: use "
                              "SimulatedCluster(workers, cost='cpu')")
        st = self._plain
        if st is None:
            st = self._plain = {"free": [(0.0, w) for w in range(self.workers)],
                                "started": set(), "now": 0.0, "after": -1, "log": [],
                                "call": {"makespan": 0.0, "work": self.startup, "tasks": 0}}
            heapq.heapify(st["free"])
            self.calls.append(st["call"])
        free_at, w = heapq.heappop(st["free"])
        start = max(st["now"], free_at)
        if w not in st["started"]:
            st["started"].add(w)
            start += self.startup
        t = time.thread_time()
        try:
            value, error = fn(*args, **kwargs), None
        except Exception as err:  # noqa: BLE001 - handed to the caller by result()
            value, error = None, err
        cost = time.thread_time() - t
        finish = start + cost
        heapq.heappush(st["free"], (finish, w))
        st["log"].append((st["after"], cost))
        call = st["call"]
        call["work"] += cost
        call["tasks"] += 1
        call["makespan"] = max(call["makespan"], finish)
        return _SimFuture(self, len(st["log"]) - 1, finish, value, error)

    def _waited(self, index: int, finish: float) -> None:
        """The caller waited for plain task ``index`` (finishing at ``finish``)."""
        if finish > self._plain["now"]:
            self._plain["now"], self._plain["after"] = finish, index

    def replay(self, workers: int) -> dict:
        """The plain tasks run so far, list-scheduled again on ``workers`` workers.

        Each task keeps its measured cost and its order, and starts no sooner than the
        finish of the task the caller had waited for when it was submitted (on that
        schedule); each worker pays :attr:`startup` before its first task. One run of the
        tasks thus models every worker count.

        Returns
        -------
        dict
            ``makespan``, ``work`` (the sum of the costs and one ``startup``), ``tasks``.
        """
        workers = _check_workers(workers, local=False)
        log = self._plain["log"] if self._plain else []
        free = [(0.0, w) for w in range(workers)]
        started: set = set()
        finish: list[float] = []
        for after, cost in log:
            free_at, w = heapq.heappop(free)
            start = max(free_at, finish[after] if after >= 0 else 0.0)
            if w not in started:
                started.add(w)
                start += self.startup
            finish.append(start + cost)
            heapq.heappush(free, (finish[-1], w))
        return {"makespan": max(finish, default=0.0),
                "work": self.startup + sum(c for _, c in log), "tasks": len(log)}

    def cancel(self, futures) -> None:
        """Nothing to cancel: every task ran when it was submitted."""

    def work(self) -> float:
        """Sum of all task costs over every call (the modelled time on one worker)."""
        return float(sum(c["work"] for c in self.calls))

    def makespan(self) -> float:
        """Modelled time on :attr:`workers` workers: from the first verification task's
        start to the last completion (calls in turn add up, calls side by side overlap),
        plus that of the plain tasks."""
        plain = self._plain["call"]["makespan"] if self._plain else 0.0
        return float(self._end + plain)

    def speedup(self) -> float:
        """Modelled speed-up over one worker: :meth:`work` / :meth:`makespan`."""
        span = self.makespan()
        return self.work() / span if span > 0 else 1.0


class _SimFuture:
    """A plain task of a :class:`SimulatedCluster`: finished when submitted."""

    __slots__ = ("_sim", "_index", "_finish", "_value", "_error")

    def __init__(self, sim: SimulatedCluster, index: int, finish: float, value, error):
        self._sim, self._index, self._finish = sim, index, finish
        self._value, self._error = value, error

    def done(self) -> bool:
        """True (the caller has waited for it: the modelled clock moves to its finish)."""
        self._sim._waited(self._index, self._finish)
        return True

    def result(self):
        """The task's value (its exception is raised here)."""
        self._sim._waited(self._index, self._finish)
        if self._error is not None:
            raise self._error
        return self._value


def _compile_seconds(problem) -> float:
    """CPU seconds to compile ``problem``'s graphs for the walker afresh: what each worker
    process pays before its first task of the problem (the median of three timings: one
    can hold a full garbage collection of this process's heap, about 0.1 s beside 0.03 s
    of compiling for the cartpole certificate, which a worker's small heap does not cost).
    They are then compiled (cached) in this process, so that no task's CPU seconds here
    include them."""
    names = ("function", "jacobian", "function_jacobian", "function_checked",
             "function_jacobian_checked")
    funs = [getattr(problem, n, None) for n in names]
    funs = [f for f in funs + list(getattr(problem, "_second_order", None) or ())
            if isinstance(f, ca.Function)]
    times = []
    for _ in range(3):
        t = time.thread_time()
        for f in funs:
            Program(f)
        times.append(time.thread_time() - t)
    seconds = sorted(times)[1]
    for f in funs:
        compile_function(f)
    return seconds


class _SimRun:
    """The tasks of one :func:`verify_distributed` call on a :class:`SimulatedCluster`.

    Tasks run when submitted and are placed on the model's shared virtual workers at its
    current time; :meth:`next` waits until no thread of the model runs and this call holds
    the earliest completion of all calls (so calls in threads side by side interleave as
    on a cluster, in modelled time).
    """

    def __init__(self, sim: SimulatedCluster, problem):
        self.sim, self.problem, self.workers = sim, problem, sim.workers
        self.pending: list = []              # (finish, seq, out) of tasks not absorbed
        self.delivered: tuple | None = None  # (key, out) handed to this call by the model
        self.start = self.last = sim._now
        self.work = 0.0
        self.tasks = self.boxes = 0
        self.seen: set = set()  # virtual workers that ran a task of this call
        # by CPU seconds: what a worker process pays before its first task of this problem
        # (its graphs compiled for the walker; here they are compiled once for all)
        t = time.thread_time()
        self.setup = _compile_seconds(problem) if sim.cost == "cpu" else 0.0
        sim.modelling_seconds += time.thread_time() - t
        with sim._cv:
            sim._runs.append(self)

    @property
    def now(self) -> float:
        """The model's time: the finish of the last completion absorbed."""
        return self.sim._now

    def submit(self, fn, *args):
        sim = self.sim
        t = time.thread_time()
        out = fn(self.problem, *args)
        cost = float(out["boxes"]) if sim.cost == "boxes" else time.thread_time() - t
        with sim._cv:
            free_at, w = heapq.heappop(sim._free)
            start = max(sim._now, free_at)
            if w not in self.seen:  # a worker process compiles the problem's graphs once
                self.seen.add(w)
                cost += self.setup
                sim.compile_seconds += self.setup
            finish = start + cost
            heapq.heappush(sim._free, (finish, w))
            sim._seq += 1
            heapq.heappush(self.pending, (finish, sim._seq, out))
            self.work += cost
            self.tasks += 1
            self.boxes += int(out["boxes"])
            return sim._seq

    def next(self):
        sim = self.sim
        if not self.pending:
            return None
        with _waiting():  # another check may take its turn meanwhile (ahead())
            sim._block()
            with sim._cv:
                while self.delivered is None:
                    sim._cv.wait()
                done, self.delivered = self.delivered, None
        return done

    def close(self):
        # with stop_at_first, tasks not absorbed are cancelled: the call ends at its last
        # absorbed completion (their workers stay busy until they finish, as on Dask)
        sim = self.sim
        with sim._cv:
            sim._runs.remove(self)
            sim.calls.append({"makespan": self.last - self.start, "work": self.work,
                              "tasks": self.tasks, "start": self.start,
                              "boxes": self.boxes})


def model_speedups(run, workers=(1, 2, 4, 8, 16), cost: str = "boxes") -> dict[int, dict]:
    """Modelled speed-ups of ``run(client)`` on each worker count (:class:`SimulatedCluster`).

    Parameters
    ----------
    run : callable
        ``run(client)`` makes its :func:`verify_distributed` calls (or :func:`check` calls,
        inside :func:`verifying_on`) on the client it is given; it is run once per worker
        count, serially in this process.
    workers : sequence of int
    cost : {"boxes", "cpu"}

    Returns
    -------
    dict
        Worker count (1 always among them) to ``{"work", "makespan", "speedup",
        "efficiency", "tasks"}``: ``work`` the sum of the task costs, ``makespan`` the
        modelled time, ``speedup`` the makespan on one worker over this one (with
        ``cost="cpu"`` the extra cost of smaller tasks on more workers counts against it),
        ``efficiency`` the speed-up per worker.
    """
    counts = sorted({1, *(int(_check_workers(w, local=False)) for w in workers)})
    out = {}
    for w in counts:
        sim = SimulatedCluster(w, cost)
        run(sim)
        out[w] = {"work": sim.work(), "makespan": sim.makespan(),
                  "tasks": sum(c["tasks"] for c in sim.calls)}
    one = out[1]["makespan"]
    for w, row in out.items():
        row["speedup"] = one / row["makespan"] if row["makespan"] > 0 else 1.0
        row["efficiency"] = row["speedup"] / w
    return out


def verify_distributed(problem, client, *, resolution: float | None = None,
                       max_boxes: int = 2_000_000, presearch: int = 500,
                       stop_at_first: bool = True, keep_leaves: bool = False,
                       initial_boxes: int = 256, task_boxes: int | None = None,
                       tasks_per_worker: int | None = None, root_boxes: int | None = None,
                       min_task_boxes: int | None = None, stats: dict | None = None,
                       start: np.ndarray | None = None, **options):
    """Decide ``problem`` with the interval verifier on a Dask cluster, load-balanced.

    The hard boxes of a Lyapunov problem are few (near the level set, near the inner
    sphere), so a fixed split of the root box leaves workers idle. Work is handed out by
    *box budget* instead:

    1. one task runs the pre-search and evaluates the root box's initial grid
       (``initial_boxes``), bisecting on until ``root_boxes`` boxes are processed (a check
       that needs fewer is decided there, as serially); the boxes it would still bisect are
       bisected once more and their halves come back *open*, unevaluated
       (``verify_interval(hand_back=True)``: no box is evaluated twice, which cost the
       cartpole certificate's decrease check 54 % more boxes);
    2. open boxes are dealt (in strided shares) into enough tasks to
       keep ``tasks_per_worker`` per worker busy, but none gets fewer than
       ``min_task_boxes`` to start from; each task bisects its
       boxes (all in one batch) by the serial verifier's rules until it has spent
       ``task_boxes`` boxes, and returns what is still open;
    3. each finished task's open boxes are dealt out again at once (a few are held back
       while every worker is busy, to start the next task with others'), until none is
       left. :class:`SimulatedCluster` models the schedule of this graph on any number of
       workers.

    Each walker pass costs a fixed time per instruction of the graphs besides its time per
    box (about 0.12 s against 70 µs per box for the cartpole's Frobenius form of condition
    (c)): a task that starts from a few boxes spends passes on them while its queue grows.
    Dealt into four tasks of 112 boxes each, that check took 1.5 times the serial CPU
    seconds and 4.0 s on 2 workers; with the root's first 2048 boxes and tasks of at least
    1024, 2.8 s (serial 4.2 s).

    Step 2 needs ``verification.verify.verify_interval(boxes=...)``; where the verifier
    lacks it, the root box is instead split (:func:`verification.verify.split_box`) into
    ``4·tasks_per_worker·workers`` sub-boxes, each a serial run to the end, scheduled as
    workers free up.

    Every box is decided by the serial verifier's rules, so the verdict is the serial one:
    ``verified`` when every leaf is decided, a *confirmed* counterexample (with
    ``stop_at_first`` the first one found ends the run and pending tasks are cancelled),
    otherwise ``unknown`` with the boxes left at the resolution (or beyond ``max_boxes``).
    The problem travels to each worker once (``client.scatter``; it pickles through
    ``VerificationProblem.__getstate__``).

    Parameters
    ----------
    problem : verification.VerificationProblem
    client : distributed.Client or SimulatedCluster
        From :func:`dask_client`; a :class:`SimulatedCluster` runs the same task graph in
        this process and models its schedule on that many workers.
    resolution, max_boxes, presearch, stop_at_first, keep_leaves, initial_boxes
        As in :func:`verification.verify` (interval backend); ``resolution`` is the root
        problem's; ``max_boxes`` bounds the boxes of all tasks together (each new task gets
        a share of what is left; a first grid is always evaluated whole, as serially).
    task_boxes, tasks_per_worker, root_boxes, min_task_boxes : int, optional
        The grains; by default :func:`task_defaults` for the cluster's worker count and
        ``batch`` (finer on more workers; a ``task_boxes`` below ``batch`` takes its place
        as the grain the other defaults follow) and, on more than two workers without a
        ``task_boxes``, the problem's :func:`pass_boxes` (no task starts from passes
        thinner than that).
    task_boxes : int
        Boxes one task processes before it hands its open boxes back (the load-balancing
        grain; one walker pass evaluates up to ``batch`` boxes), or, once more boxes are
        done, the boxes done so far over twice the tasks in flight (guided
        self-scheduling: a large check pays fewer fixed costs per pass). While workers
        would idle, a new task gets at most four times the boxes it starts from (ramp-up).
    tasks_per_worker : int
        Tasks kept in flight per worker (one up to two workers: each finished task's open
        boxes go whole to the next task; on the cartpole certificate's decrease check two
        per worker spent 19.5 CPU seconds on 2 workers against 16.5 with one). A large open
        set is dealt into more tasks than that, none starting from more than a quarter of
        ``task_boxes``; the extra ones wait in the scheduler's queue.
    root_boxes : int, optional
        Boxes of step 1 (1: only the initial grid, then the work is dealt out).
    min_task_boxes : int, optional
        Least number of open boxes a new task starts from. A task whose queue thins below
        half of it hands the queue back; while every worker is busy, open sets smaller than
        this wait to be merged with the next ones (a walker pass costs a fixed time per
        instruction of the graphs: thin passes are mostly that). On more than two workers,
        until every worker has been busy once (the ramp-up), a quarter of it: workers
        that would otherwise wait pay the thinner passes, and the open set widens sooner.
    start : (k, n, 2) ndarray, optional
        The leaf boxes of a partition of the root box that a serial run decided
        (:class:`Proofs`): they are dealt at once, in strided shares, into four tasks per
        worker, and no root task runs (no pre-search, no first grid). A leaf that is not
        decided is bisected on as usual. The verdict is about the leaves' union: they must
        cover the box (:func:`verification.verify.partition_leaves` gives such leaves).
    stats : dict, optional
        Filled with ``tasks`` (count), ``root_cpu`` (CPU seconds of step 1),
        ``cpu_by_worker`` (CPU seconds of the other tasks per worker process: the load
        balance, independent of other load on the machines), ``starts`` (the number of
        open boxes each task after the root started from), ``task_boxes`` (the boxes each
        task processed, in the order they were absorbed), ``grains`` (the grains used) and
        ``timeline`` (per task, root first: worker process id, wall-clock start and end on
        the worker, wall-clock time this process absorbed it, boxes: the schedule as it
        ran, for diagnosis; nothing depends on it).
    **options
        Any other option of the interval verifier (``batch``, ``mean_value``, ``affine``,
        ``seed``, ...), passed to every task.

    Returns
    -------
    verification.VerificationResult
        ``depth``: the deepest bisection level below the root box, counting a first grid
        of ``k`` cells per side as ``log2 k`` levels (an upper bound: each task's deepest
        level plus that of its deepest starting box).

    Raises
    ------
    ConfigError
        A count is not a positive integer.
    TypeError
        An option the interval verifier does not have.
    """

    known = set(inspect.signature(verify_interval).parameters) - {
        "problem", "executor", "n_tasks", "progress", "boxes", "hand_back", "hand_back_below",
        "precondition", "partition"}  # tasks start from boxes; coordinates change before
    for name in options:
        if name not in known:
            raise TypeError(f"verify_distributed() got an unknown option {name!r}; options: "
                            f"{', '.join(sorted(known))}")
    batch = options.get("batch", inspect.signature(verify_interval).parameters["batch"].default)
    for name, v in (("task_boxes", task_boxes), ("tasks_per_worker", tasks_per_worker),
                    ("root_boxes", root_boxes), ("min_task_boxes", min_task_boxes),
                    ("max_boxes", max_boxes), ("initial_boxes", initial_boxes)):
        if v is not None and (isinstance(v, bool) or not isinstance(v, (int, np.integer))
                              or v < 1):
            raise ConfigError(f"{name} must be an integer >= 1, got {v!r}")
    t0 = time.perf_counter()
    box = np.asarray(problem.box, dtype=float)
    root_w = box[:, 1] - box[:, 0]
    if resolution is None:
        resolution = 1e-4 * float(np.max(root_w))
    batched = _starts_from_boxes()
    options = dict(options, resolution=float(resolution), stop_at_first=bool(stop_at_first),
                   keep_leaves=bool(keep_leaves))
    if not batched:  # each fixed sub-box starts from its own grid
        options["initial_boxes"] = int(initial_boxes)
    if options.get("second_order"):
        problem.second_order_functions  # built before pickling: workers get them
    runner = client._runner(problem) if getattr(client, "simulated", False) else \
        _DaskRunner(client, problem)
    n_workers = runner.workers
    ok_batch = isinstance(batch, (int, np.integer)) and not isinstance(batch, bool) and batch >= 1
    grain = int(batch) if ok_batch else 1
    if task_boxes is not None:  # a finer task grain given: the other grains follow it
        grain = min(grain, int(task_boxes))
    # a task grain given: the grains follow it; else no task starts from thin passes
    size = pass_boxes(problem, bool(options.get("second_order"))) \
        if n_workers > 2 and batched and task_boxes is None else None
    grains = task_defaults(n_workers, grain, size)
    given = {"task_boxes": task_boxes, "tasks_per_worker": tasks_per_worker,
             "root_boxes": root_boxes, "min_task_boxes": min_task_boxes}
    grains.update({k: int(v) for k, v in given.items() if v is not None})
    task_boxes = grains["task_boxes"]
    target = grains["tasks_per_worker"] * n_workers
    min_task = grains["min_task_boxes"]
    root_boxes = grains["root_boxes"]

    found, unknown, leaves = [], [], []
    state = {"boxes": 0, "depth": 0, "running": 0, "ramped": False}
    tally = {"tasks": 0, "root_cpu": None, "cpu_by_worker": {}, "starts": [],
             "task_boxes": [], "grains": dict(grains), "timeline": []}

    offsets: dict = {}  # task key -> bisection depth of its deepest starting box

    def absorb(out, offset: int = 0) -> np.ndarray:
        tally["tasks"] += 1
        tally["task_boxes"].append(int(out["boxes"]))
        if "span" in out:
            tally["timeline"].append((out["pid"], *out["span"], time.time(),
                                      int(out["boxes"])))
        if tally["root_cpu"] is None:
            tally["root_cpu"] = out["cpu"]
        else:
            by = tally["cpu_by_worker"]
            by[out["pid"]] = by.get(out["pid"], 0.0) + out["cpu"]
        found.extend(out["found"])
        if len(out["unknown"]):
            unknown.append(out["unknown"])
        leaves.extend(out["leaves"])
        state["boxes"] += out["boxes"]
        state["depth"] = max(state["depth"], offset + out["depth"],
                             _depth(out["open"], root_w))
        return out["open"]

    def deal(open_boxes: np.ndarray, parts: int) -> None:
        k = len(open_boxes)
        if not k:
            return
        left = max_boxes - state["boxes"]
        if left <= 0:  # the global budget is spent: these stay undecided
            unknown.append(open_boxes)
            return
        # guided self-scheduling: a budget grows with the work done so far (a large check
        # pays fewer fixed costs per pass; the last tasks stay a small part of the whole)
        grain = max(task_boxes, state["boxes"] // (2 * target))
        # enough parts for the free task slots, and for a large open set enough that no
        # task starts from more than a quarter of its budget (it would run long while the
        # others run dry): extra tasks wait in the scheduler's queue
        parts = max(1, parts, -(-k // max(1, grain // 4)))
        parts = min(parts, k)
        if batched:  # no task starts from fewer than min_task boxes (but one from all)
            least = min_task
            if n_workers > 2 and not state["ramped"] and \
                    state["running"] + k // min_task < n_workers:
                # ramp-up on many workers (until every one has been busy once): workers
                # would idle even so; thinner starts (a quarter) widen the open set sooner,
                # their extra fixed costs paid by workers that would wait
                least = max(1, min_task // 4)
            parts = max(1, min(parts, k // least))
        share = max(1, left // parts)  # of the global budget, per new task
        budget = min(grain, share) if batched else share
        if batched and state["running"] + parts < n_workers:
            # workers would idle: a short task, so that its open boxes (about twice its
            # undecided ones) come back soon to be dealt wider (ramp-up)
            budget = min(budget, max(min_task, 4 * -(-k // parts)))
        # a task's thin tail (its queue below half a start) comes back to be merged with
        # others' (unless this is all the work there is: then it finishes it)
        tail = min_task // 2 if batched and (state["running"] or parts > 1) else 0
        for chunk in _deal_boxes(open_boxes, parts):  # sizes differ by one at most
            tally["starts"].append(len(chunk))
            key = runner.submit(_box_task, chunk, budget, options, batched, tail)
            offsets[key] = _depth(chunk, root_w)
            state["running"] += 1
        state["ramped"] = state["ramped"] or state["running"] >= n_workers

    pool: list = []  # open boxes held back until there are enough to start a task

    def offer(open_boxes: np.ndarray) -> None:
        """Deal open boxes out, or hold a few back while every worker is busy (they
        join the next task's start instead of making a thin task of their own)."""
        if len(open_boxes):
            pool.append(open_boxes)
        k = sum(len(b) for b in pool)
        if not k or (k < min_task and state["running"] >= n_workers):
            return
        merged = pool[0] if len(pool) == 1 else np.concatenate(pool)
        pool.clear()
        deal(merged, target - state["running"])

    try:
        if start is not None and batched:  # a recorded partition: its leaves, dealt at once
            tally["root_cpu"] = 0.0
            for chunk in _deal_boxes(np.asarray(start, dtype=float), 4 * n_workers):
                tally["starts"].append(len(chunk))
                key = runner.submit(_box_task, chunk, len(chunk) + task_boxes, options, True)
                offsets[key] = _depth(chunk, root_w)
                state["running"] += 1
            state["ramped"] = True
            opened = np.zeros((0, problem.n, 2))
        else:
            root = {k: v for k, v in options.items() if k != "initial_boxes"}
            runner.submit(_root_task, root, presearch, initial_boxes if batched else 1,
                          min(root_boxes, max_boxes) if batched else 0)
            _, out = runner.next()
            opened = absorb(out)
        if not (found and stop_at_first):
            if not batched and len(opened):  # fixed split, scheduled as workers free up
                parts = 1 << max(0, math.ceil(math.log2(4 * target)))
                opened = np.stack([b for ob in opened for b in split_box(ob, parts)])
                # the sub-boxes' first grids together about as fine as the serial one
                options["initial_boxes"] = max(1, int(initial_boxes) // parts)
                deal(opened, len(opened))
            else:
                offer(opened)
            while True:
                done = runner.next()
                if done is None:
                    break
                key, out = done
                state["running"] -= 1
                opened = absorb(out, offsets.pop(key, 0))
                if found and stop_at_first:
                    break
                offer(opened)
    finally:
        runner.close()

    if stats is not None:
        stats.update(tally)
    und = np.concatenate(unknown) if unknown else np.zeros((0, problem.n, 2))
    seconds = time.perf_counter() - t0
    leaves_out = leaves if keep_leaves else None
    if found:
        found.sort(key=lambda c: -c.value_lower)
        return VerificationResult("counterexample", found[0], found, und, state["boxes"],
                                  state["depth"], seconds, leaves_out)
    return VerificationResult("unknown" if len(und) else "verified", None, [], und,
                              state["boxes"], state["depth"], seconds, leaves_out)


#: the Dask client that :func:`check` sends its problems to (set by :func:`verifying_on`)
_CLUSTER: contextvars.ContextVar = contextvars.ContextVar("nlyap_verify_cluster", default=None)


@contextlib.contextmanager
def verifying_on(client) -> Iterator:
    """Within this block, :func:`check` decides its problems on ``client``'s cluster.

    The certificate's checks (:func:`nlyap_opt.certification.roa.certify_level`, the inner ellipse,
    the initial set) call :func:`check`; the pipeline's certificate stage runs them inside this
    block when ``nlyap run --workers/--scheduler`` is given. ``client=None`` runs them
    serially.

    Examples
    --------
    >>> with dask_client(workers=2) as client, verifying_on(client):   # doctest: +SKIP
    ...     cert = certify_roa(problem, level)
    """
    token = _CLUSTER.set(client)
    try:
        yield client
    finally:
        _CLUSTER.reset(token)


def _preconditioned_options(options: dict) -> dict:
    """The options of a check in changed coordinates: without ``precondition``, and with the
    second-order form's affine Hessian pass (``second_order="affine"``) if it is on."""
    out = {k: v for k, v in options.items() if k != "precondition"}
    if out.get("second_order"):
        out["second_order"] = "affine"
    return out


def check(problem, **options):
    """:func:`verification.verify` (interval backend), on the cluster of :func:`verifying_on`.

    On a cluster, a ``verified`` verdict is taken from :func:`verify_distributed` (every box
    decided by the serial rules), and so is a counterexample that its root task found alone
    (pre-search or first grid: the serial run's own first steps, which end with the same
    counterexample). Any other verdict is decided again by the serial verifier, so that
    the counterexample, and every level a search derives from it, are the serial ones:
    verdicts, levels and saved artifacts are those of a serial run, and the cluster only
    speeds up the checks that hold (in a certificate stage, almost all of them). A verified
    check processes exactly the serial run's boxes (each box is decided on its own, and
    ``hand_back`` evaluates none twice); only seconds differ. A verdict at the edge of the
    box budget may differ too: a cluster run may prove within ``max_boxes`` what a serial
    run leaves ``unknown`` there (never the reverse for a property that fails: that is
    decided serially).

    Under :func:`proving`, a check first tries the leaves of its recorded tree
    (:func:`from_proof`), serially or on the cluster; a serial check under recording
    proofs records its tree. Either way a preconditioned check goes through its changed
    coordinates as on a cluster, so that the tree is the one of the problem bisected.
    """

    client = _CLUSTER.get()
    proofs = _PROOFS.get()
    if client is None and (proofs is None or options.get("backend", "interval") != "interval"):
        return verification.verify(problem, **options)
    if options.get("precondition"):  # coordinates z = Mx first, then the cluster on them
        return solve_preconditioned(problem, hessian_coordinates(problem),
                                    lambda p: check(p, **_preconditioned_options(options)),
                                    confirm_points)
    opts = {k: v for k, v in options.items() if k not in _LOCAL_OPTIONS}
    res = from_proof(problem, **options)
    if res is not None:
        return res
    if client is None:  # serially, recording a tree or without one
        if proofs.record:
            res = verification.verify(problem, **options, partition=True)
            if res.partition is not None:
                proofs.add(problem, res.partition)
            return res
        return verification.verify(problem, **options)
    st: dict = {}
    res = verify_distributed(problem, client, stats=st, **opts)
    if res.status == "verified":
        return res
    if res.status == "counterexample" and st.get("tasks") == 1 and \
            opts.get("stop_at_first", True) and _starts_from_boxes():
        # found by the root task alone: its pre-search and first grid are the serial run's
        # first steps (same seed, grid and batch), which stops there with this very result
        return res
    return verification.verify(problem, **options)


#: options of :func:`check` for a serial verification only, not handed to cluster tasks
_LOCAL_OPTIONS = ("n_tasks", "executor", "progress", "backend")

#: the :class:`Proofs` that :func:`check` records into or starts from (:func:`proving`)
_PROOFS: contextvars.ContextVar = contextvars.ContextVar("nlyap_proofs", default=None)


class Proofs:
    """The bisection trees of verified checks, by problem: a re-check's *proof* file.

    A serial check records the tree it decided (``verify_interval(partition=True)``); a
    later check of the same problem (the same graphs, box and number of conditions,
    :meth:`key`) starts from that tree's leaves instead of searching for them again: about
    half the boxes, and all of them known at once, so a cluster deals them out evenly from
    the start. Nothing in a proof is trusted: the leaves are rebuilt by bisecting the
    problem's own box as the verifier does (:func:`verification.verify.partition_leaves`),
    so they cover it whatever the file says, and every leaf is decided again by the
    verifier's rules. A leaf that is not decided is bisected on; a check whose leaves do
    not all hold is decided again from the root box, as without a proof. A proof can make a
    re-check faster or slower, never make a false condition verified. A tree of more nodes
    than the check's box budget is not used. A decrease check with a recorded tree was
    bisected when it was recorded, so its leaves come before the closed-form attempt that
    precedes bisection (:func:`from_proof`); if they do not all hold, both follow as
    without a proof.

    Parameters
    ----------
    record : bool
        Record the trees of the checks run serially under :func:`proving`.
    """

    FORMAT = "nlyap-proof-1"  # breadth-first codes, left halves before right halves

    def __init__(self, record: bool = False):
        self.record = bool(record)
        self.trees: dict[str, tuple[int, np.ndarray]] = {}
        self.looked: set[str] = set()  # keys of the checks that looked for a tree
        self.failed: set[str] = set()  # keys whose leaves did not all hold
        self.decided: set[str] = set()  # keys of the checks decided from their tree

    @property
    def asked(self) -> int:
        """The number of checks (distinct problems) that looked for a tree."""
        return len(self.looked)

    @property
    def used(self) -> int:
        """The number of checks (distinct problems) decided from their tree."""
        return len(self.decided)

    @staticmethod
    def key(problem) -> str:
        """The problem's identity: a hash of its box, its counts of states, constraints and
        properties, and its conditions' values (7 significant digits) at 8 seeded points of
        the box. The values do not depend on how CasADi stores the graphs (another version
        or machine finds the same key unless a value rounds the other way there); a key
        shared by two problems can only cost time (see the class)."""
        box = np.ascontiguousarray(problem.box, dtype=np.float64)
        lo, hi = box[:, 0], box[:, 1]
        points = lo + (hi - lo) * np.random.default_rng(20261128).random((8, problem.n))
        with np.errstate(all="ignore"):
            values = np.asarray(evaluate(problem.function, [points])[0], dtype=float)
        h = hashlib.sha256()
        h.update(box.tobytes())
        h.update(f"{problem.n},{problem.n_constraints},{problem.n_properties};".encode())
        h.update(",".join(f"{v:.6e}" for v in values.ravel()).encode())
        return h.hexdigest()

    def add(self, problem, partition: dict) -> None:
        """Keep ``result.partition`` of a verified check of ``problem``."""
        self.trees[self.key(problem)] = (int(partition["initial_boxes"]),
                                         np.asarray(partition["codes"], dtype=np.int8))

    def leaves(self, problem, max_boxes: int | None = None, *,
               key: str | None = None) -> np.ndarray | None:
        """The leaf boxes of ``problem``'s recorded tree: ``None`` if there is none, if its
        leaves did not all hold before (:attr:`failed`: the same leaves would be decided
        the same way), or if it has more than ``max_boxes`` nodes (``key``: its
        :meth:`key`, if known)."""
        key = self.key(problem) if key is None else key
        self.looked.add(key)
        tree = self.trees.get(key)
        if tree is None or key in self.failed or \
                (max_boxes is not None and len(tree[1]) > max_boxes):
            return None
        try:
            return partition_leaves(problem.box, *tree)
        except ValueError:  # not a tree of this box: the check searches as without it
            return None

    def save(self, path) -> None:
        """Write the trees to ``path`` (a ``.npz`` file of integer arrays)."""
        keys = sorted(self.trees)
        arrays = {"format": np.frombuffer(self.FORMAT.encode(), dtype=np.uint8)}
        for i, k in enumerate(keys):
            initial, codes = self.trees[k]
            arrays[f"key{i}"] = np.frombuffer(k.encode(), dtype=np.uint8)
            arrays[f"initial{i}"] = np.asarray([initial], dtype=np.int64)
            arrays[f"codes{i}"] = codes
        # the bytes depend on the trees only (np.savez stamps each entry with the clock)
        with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
            for name, arr in arrays.items():
                buf = io.BytesIO()
                np.lib.format.write_array(buf, np.ascontiguousarray(arr), allow_pickle=False)
                info = zipfile.ZipInfo(name + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
                info.compress_type = zipfile.ZIP_DEFLATED
                zf.writestr(info, buf.getvalue())

    @classmethod
    def load(cls, path) -> Proofs:
        """Read a proof file written by :meth:`save`.

        Raises
        ------
        ConfigError
            The file is not a readable proof file (one line naming the problem).
        """
        fix = "write it again with 'nlyap verify --certificate DIR --save-proof FILE'"
        try:
            z = read_npz(path, "proof file", fix, limit=4 * MAX_PARTITION_ENTRIES)
        except OSError as err:
            raise ConfigError(f"cannot read the proof file {path}: {err.strerror or err} "
                              f"({fix})") from None

        def text(name: str) -> str | None:
            a = z.get(name)
            if a is None or a.dtype != np.uint8 or a.ndim != 1 or a.size > 64:
                return None
            return bytes(a).decode("latin-1")

        if text("format") != cls.FORMAT:
            raise ConfigError(f"{path} is not a proof file of this tool ({fix})")
        n = (len(z) - 1) // 3
        if set(z) != {"format"} | {f"{w}{i}" for i in range(n)
                                   for w in ("key", "initial", "codes")}:
            raise ConfigError(f"{path}: its arrays are not those of a proof file ({fix})")
        out = cls()
        for i in range(n):
            key, initial, codes = text(f"key{i}"), z[f"initial{i}"], z[f"codes{i}"]
            if key is None or not re.fullmatch(r"[0-9a-f]{64}", key) or \
                    initial.shape != (1,) or initial.dtype != np.int64 or \
                    not 1 <= int(initial[0]) <= 2**20 or codes.dtype != np.int8 or \
                    codes.ndim != 1 or len(codes) > MAX_PARTITION_ENTRIES:
                raise ConfigError(f"{path}: entry {i} is not a bisection tree ({fix})")
            out.trees[key] = (int(initial[0]), codes)
        return out


def from_proof(problem, **options) -> VerificationResult | None:
    """``problem`` decided from the leaves of its tree in the :class:`Proofs` of
    :func:`proving` (on the cluster of :func:`verifying_on`, if any): the verified result,
    or ``None`` when there is no tree, it was tried before, or its leaves do not all hold
    (the caller then decides the check as without a proof). A tree of more nodes than
    ``max_boxes`` is not used (the search it stands for would have stopped there)."""
    proofs = _PROOFS.get()
    if proofs is None or proofs.record or options.get("precondition") or \
            options.get("backend", "interval") != "interval":
        return None
    opts = {k: v for k, v in options.items() if k not in _LOCAL_OPTIONS}
    max_boxes = opts.get("max_boxes", inspect.signature(verify_interval)
                         .parameters["max_boxes"].default)
    key = proofs.key(problem)
    start = proofs.leaves(problem, max_boxes, key=key)
    if start is None:
        return None
    client = _CLUSTER.get()
    if client is None:
        res = verify_interval(problem, **dict(opts, boxes=start, presearch=0))
    else:
        res = verify_distributed(problem, client, start=start, **opts)
    if res.status != "verified":
        proofs.failed.add(key)
        return None
    proofs.decided.add(key)
    return res


def proving_active() -> bool:
    """Whether :func:`check` runs under :func:`proving` with proofs to start from."""
    proofs = _PROOFS.get()
    return proofs is not None and not proofs.record


@contextlib.contextmanager
def proving(proofs: Proofs | None) -> Iterator:
    """Within this block, :func:`check` starts from the trees of ``proofs`` (and, with
    ``record``, records the trees of the checks it runs serially); ``None``: no proofs."""
    token = _PROOFS.set(proofs)
    try:
        yield proofs
    finally:
        _PROOFS.reset(token)


# ------------------------------------------------------------ a check ahead of its turn
#: One thread at a time runs the tool's own code (CasADi releases the GIL and is not safe
#: for building expressions in two threads at once). A thread gives its turn away only while
#: it waits for cluster tasks (:func:`_waiting` in :func:`verify_distributed`).
_TURN = threading.Lock()
_LOCAL = threading.local()  # holds: this thread has the turn; job: its Ahead, if any


class _Cancelled(BaseException):
    """An :class:`Ahead` job was closed before it finished: its thread stops at its next
    wait for cluster tasks (pending tasks are cancelled by :func:`verify_distributed`)."""


@contextlib.contextmanager
def _waiting():
    """Around a blocking wait for cluster tasks: the turn goes to a check running ahead."""
    holds = getattr(_LOCAL, "holds", False)
    if holds:
        _TURN.release()
    try:
        yield
    finally:
        if holds:
            _TURN.acquire()
    job = getattr(_LOCAL, "job", None)
    if job is not None and job._cancel.is_set():
        raise _Cancelled


class Ahead:
    """``fn(*args, **kwargs)``, computed ahead of the point where its result is needed.

    Inside :func:`verifying_on` (a cluster) it starts at once in a thread of its own, whose
    checks go to the same cluster: their tasks run beside the caller's, and a narrow check
    (few boxes, one worker busy) no longer leaves the other workers idle. The two threads
    take turns (a module lock): each runs only while the other waits for its cluster tasks,
    so CasADi never runs in two threads at once, and every verdict is the one a serial run
    gives (:func:`check`). An ``Ahead`` may start another (a check beside a check). On a
    :class:`SimulatedCluster` the threads run as on a cluster, their tasks list-scheduled
    together on the model's workers in modelled time. Without a cluster nothing starts:
    ``fn`` runs when :meth:`result` is first called, exactly where a serial program would
    run it, and not at all if the result is never asked for.

    Use it as a context manager: leaving the block without asking for the result (an early
    return) stops the thread at its next wait for the cluster and waits for it; leaving on
    an exception stops it without waiting.

    Examples
    --------
    >>> with ahead(sum, [1, 2]) as job:
    ...     job.result()
    3
    """

    def __init__(self, fn, *args, _defer: bool = False, **kwargs):
        self._fn = lambda: fn(*args, **kwargs)
        self._cancel = threading.Event()
        self._thread = None
        self._took = False          # the caller took the turn to start the thread
        self._out: tuple | None = None
        # on a model (SimulatedCluster): the thread counts among its runnable threads until
        # it ends; a caller that joins it is handed that count back (no other thread runs)
        self._sim = None
        self._left = self._joined = False
        cluster = _CLUSTER.get()
        if _defer or cluster is None:
            return
        if not getattr(_LOCAL, "holds", False):
            _TURN.acquire()
            _LOCAL.holds = self._took = True
        if getattr(cluster, "simulated", False):
            self._sim = cluster
            cluster._unblock()
        ctx = contextvars.copy_context()
        self._thread = threading.Thread(target=self._body, args=(ctx,), daemon=True,
                                        name="nlyap-ahead")
        self._thread.start()

    def _body(self, ctx):
        _TURN.acquire()
        _LOCAL.holds, _LOCAL.job = True, self
        try:
            self._out = (True, ctx.run(self._fn))
        except BaseException as err:  # handed to the caller by result()
            self._out = (False, err)
        finally:
            _LOCAL.holds, _LOCAL.job = False, None
            if self._sim is not None:
                with self._sim._cv:
                    self._left = True
                    if not self._joined:
                        self._sim._runnable -= 1
                        self._sim._deliver()
            _TURN.release()

    def _join(self):
        sim = self._sim
        if sim is not None:
            with sim._cv:  # the caller waits: it stops running until this thread ends
                if not self._left and not self._joined:
                    self._joined = True
                    sim._runnable -= 1
                    sim._deliver()
        with _waiting():
            self._thread.join()
        if self._took:
            _LOCAL.holds = self._took = False
            _TURN.release()

    def result(self):
        """The value of ``fn(*args, **kwargs)`` (its exception is raised here)."""
        if self._out is None:
            if self._thread is None:
                try:
                    self._out = (True, self._fn())
                except BaseException as err:
                    self._out = (False, err)
            else:
                self._join()
        ok, value = self._out
        if not ok:
            raise value
        return value

    def __enter__(self):
        return self

    def __exit__(self, kind, err, tb):
        if self._thread is None or not self._thread.is_alive() and not self._took:
            return False
        self._cancel.set()
        if kind is None:
            self._join()
        elif self._took:  # unwinding: give the turn back, do not wait
            _LOCAL.holds = self._took = False
            _TURN.release()
        return False


def ahead(fn, *args, when: bool = True, **kwargs) -> Ahead:
    """``Ahead(fn, *args, **kwargs)``: start ``fn`` now on the cluster of
    :func:`verifying_on`, or run it when its result is asked for (see :class:`Ahead`).

    ``when=False``: never start early (the serial behaviour on a cluster too), for work
    that is likely to be thrown away, e.g. condition (c) during a level search that may
    end without a level."""
    return Ahead(fn, *args, **kwargs, _defer=not when)


def _depth(boxes: np.ndarray, root_w: np.ndarray) -> int:
    """Deepest bisection level of ``boxes`` below a root box of widths ``root_w``."""
    if not len(boxes):
        return 0
    w = boxes[:, :, 1] - boxes[:, :, 0]
    ratio = np.where(w > 0, root_w / np.maximum(w, 1e-300), 1.0)
    return int(np.ceil(np.max(np.log2(np.maximum(ratio, 1.0)).sum(axis=1)) - 1e-9))
