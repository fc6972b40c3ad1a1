r"""A multi-seed portfolio: K seeded candidates trained in parallel on Dask, the best one kept.

:func:`run_portfolio` runs :func:`nlyap_opt.workflow.pipeline.run` once per seed ``k`` into
``OUT/seed_k`` (the seed replaces ``train.seed`` and ``cegis.seed``: the initial V and κ,
the samples and the counterexample search), each as one task on a Dask cluster
(:func:`nlyap_opt.distributed.parallel.dask_client`: a local cluster started and stopped here, or an
existing one by its address). Every candidate is certified by the pipeline's own
certificate stage; the portfolio keeps the certified candidate with the largest certified
area (ties: the lowest seed). Training is deterministic (step budgets, fixed torch threads),
so the same seeds give the same candidates, and the same choice, on any number of workers.

The learned dynamics do not depend on the seed: the first seed's run learns φ, and as soon
as its ``dynamics`` stage is recorded, its files and their ``stages.json`` entry are copied
into the other seed directories, whose runs then load that stage (the pipeline accepts it
because the file hashes match) instead of learning φ again.

Written into ``OUT``: ``portfolio.json`` and ``portfolio.md`` (every seed: status, level,
certified area, share of the true ROA, seconds) and ``best``, a link to the chosen seed's
directory (its ``certificate.json`` re-checks with ``nlyap verify --certificate``).

With an existing cluster, ``OUT`` must be a directory that the workers and this process
share (the runs write there) and the workers must have this package installed.
"""

from __future__ import annotations

import contextlib
import copy
import json
import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from threadpoolctl import threadpool_limits

import systems as _systems

from ..certification.certificate import sha256_file, write_json_atomic
from ..distributed.parallel import DEFAULT_CONNECT_TIMEOUT, client_workers, cpu_cores, dask_client
from ..kernel import deps
from ..kernel.errors import ConfigError
from ..kernel.jsonio import write_atomic
from .configs import RunConfig, Section, check_dynamics_box, validate_config
from .pipeline import run

__all__ = ["run_portfolio", "PortfolioResult", "SeedRun", "seed_config", "warm_up", "warm_workers"]

_POLL = 0.5  # seconds between looks for the first seed's finished dynamics stage


@dataclass
class SeedRun:
    """One candidate of a portfolio.

    Attributes
    ----------
    seed : int
    status : str
        The pipeline's status (``"certified"``, ``"not certified"``, ...) or ``"skipped"``.
    certified : bool
    level : float or None
        The certified sublevel value.
    certified_area : float
        Certified area on the evaluation grid (0 when not certified).
    share : float or None
        Certified area as a share of the simulated true ROA.
    seconds : float
        Wall-clock seconds of this seed's run (on its worker).
    dir : str
        The run's directory, relative to the portfolio's.
    reason : str
    cpu_seconds : float
        CPU seconds (user + system, every thread) of its worker process during the run:
        above ``seconds`` when the run used several threads, well below when its worker
        waited for a CPU.
    """

    seed: int
    status: str
    certified: bool
    level: float | None
    certified_area: float
    share: float | None
    seconds: float
    dir: str
    reason: str = ""
    cpu_seconds: float = 0.0


@dataclass
class PortfolioResult:
    """Result of :func:`run_portfolio`.

    Attributes
    ----------
    runs : list of SeedRun
        Every seed, in the order given.
    best : SeedRun or None
        The certified run with the largest certified area (ties: lowest seed); ``None`` if
        no seed certified.
    out : Path
    workers : int
        Workers of the cluster that ran it.
    seconds : float
        Wall-clock seconds of the whole portfolio.
    """

    runs: list[SeedRun]
    best: SeedRun | None
    out: Path
    workers: int
    seconds: float
    system: str = ""
    known_dynamics: bool = False
    shared_dynamics: str | None = field(default=None)

    @property
    def certified(self) -> bool:
        return self.best is not None

    def to_json(self) -> dict:
        """The content of ``portfolio.json``."""
        return {
            "format": "nlyap-portfolio", "version": 1, "system": self.system,
            "setting": "known" if self.known_dynamics else "learned",
            "seeds": [r.seed for r in self.runs],
            "best": None if self.best is None else {
                "seed": self.best.seed, "dir": self.best.dir,
                "certificate": f"{self.best.dir}/certificate.json",
                "report": f"{self.best.dir}/report.md"},
            "rule": "largest certified area among certified seeds; ties: lowest seed",
            "shared_dynamics": self.shared_dynamics,
            "workers": self.workers, "seconds": self.seconds,
            "runs": [asdict(r) for r in self.runs],
        }


def seed_config(cfg, seed: int) -> RunConfig:
    """The run configuration ``cfg`` (a ``RunConfig`` or its JSON) with
    ``train.seed = cegis.seed = seed`` (``cfg`` is left as it is)."""
    out = cfg.to_json() if isinstance(cfg, Section) else copy.deepcopy(cfg)
    for section in ("train", "cegis"):
        sec = out.get(section)
        out[section] = dict(sec) if isinstance(sec, dict) else {}
        out[section]["seed"] = int(seed)
    return RunConfig.from_json(out)


def _check_seeds(seeds) -> list[int]:
    if isinstance(seeds, bool):
        seeds = None
    if isinstance(seeds, int):
        if seeds < 1:
            raise ConfigError(f"seeds must be >= 1 (the number of candidates), got {seeds}; "
                              "pass e.g. seeds=4 or a list of seeds")
        return list(range(seeds))
    try:
        out = list(seeds)
    except TypeError:
        out = None
    if (not out or any(isinstance(s, bool) or not isinstance(s, int) or s < 0 for s in out)):
        raise ConfigError(f"seeds must be a count >= 1 or a list of integers >= 0, got "
                          f"{seeds!r}; pass e.g. seeds=4 or seeds=[0, 3, 7]")
    if len(set(out)) != len(out):
        raise ConfigError(f"seeds must be distinct, got {out}; drop the repeated ones")
    return out


def warm_up() -> float:
    """Pay a fresh process's one-time costs of a run now: the imports of the pipeline,
    torch's first optimiser step (its set-up loads modules lazily) and matplotlib's Agg
    backend (the run's figures).

    Run on every worker of a cluster that is kept for many runs (:func:`warm_workers`),
    so that the first seed a worker runs costs what the later ones do. It changes no
    result: it trains nothing that a run reads, and a run sets its own seeds and threads.

    Returns
    -------
    float
        The CPU seconds this process spent on it.
    """
    t = time.process_time()
    p = torch.zeros(2, requires_grad=True)
    opt = torch.optim.Adam([p], lr=1e-3)
    (p * p).sum().backward()
    opt.step()
    deps.pyplot()
    return time.process_time() - t


def warm_workers(client) -> list[float]:
    """:func:`warm_up` on every worker of ``client`` (a ``distributed.Client``); returns
    each worker's CPU seconds for it, in the order of the workers' addresses.

    Examples
    --------
    >>> with dask_client(workers=16) as client:                   # doctest: +SKIP
    ...     warm_workers(client)
    ...     run_portfolio("van_der_pol", cfg, "runs/pf", seeds=16, client=client)
    """
    done = client.run(warm_up)
    return [float(done[a]) for a in sorted(done)]


def _run_seed(system: str, cfg: RunConfig, out: str, known_dynamics: bool,
              spec: str | None, seed: int) -> SeedRun:
    """Worker side: one pipeline run, its log in ``out/run.log``; its summary back.

    ``spec``: the system comes from this TOML spec file (loaded here, in the worker).
    One BLAS/OpenMP thread (a worker is one of as many as there are cores; Dask's nanny
    sets the same through the environment, a worker started without one does not).
    """

    if spec is not None:
        system = _systems.load_spec(spec)
    t, cpu = time.perf_counter(), time.process_time()
    Path(out).mkdir(parents=True, exist_ok=True)
    with open(Path(out) / "run.log", "a", encoding="utf-8") as fh:
        def log(msg):
            fh.write(f"{msg}\n")
            fh.flush()

        with threadpool_limits(limits=1):
            res = run(system, cfg, out, known_dynamics=known_dynamics, log=log)
    s = res.summary or {}
    share = s.get("fraction_of_true_roa")
    return SeedRun(seed, str(getattr(res.status, "value", res.status)), bool(res.certified),
                   float(s["level"]) if res.certified and s.get("level") is not None
                   else None,
                   float(s.get("certified_area") or 0.0) if res.certified else 0.0,
                   None if share is None or not res.certified else float(share),
                   time.perf_counter() - t, Path(out).name, str(res.reason or ""),
                   time.process_time() - cpu)


@dataclass(frozen=True)
class _DynamicsStage:
    """A finished dynamics stage of a run directory: its ``stages.json`` entry, whose files
    (name -> sha256) were checked against the files on disk."""

    entry: dict

    @property
    def names(self) -> list[str]:
        """The stage's files."""
        return list(self.entry["files"])


def _dynamics_record(run_dir: Path) -> _DynamicsStage | None:
    """The finished ``dynamics`` entry of ``run_dir/stages.json`` whose files match it."""
    try:
        rec = json.loads((run_dir / "stages.json").read_text()).get("dynamics")
        if not rec or not rec.get("files"):
            return None
        for name, digest in rec["files"].items():
            if sha256_file(run_dir / name) != digest:
                return None
    except (OSError, ValueError, AttributeError):
        return None
    return _DynamicsStage(rec)


def _share_dynamics(src: Path, dst: Path, rec: _DynamicsStage) -> None:
    """Copy the dynamics stage (files and ``stages.json`` entry) from ``src`` to ``dst``."""
    dst.mkdir(parents=True, exist_ok=True)
    for name in rec.names:
        tmp = dst / f".{name}.copy"
        shutil.copyfile(src / name, tmp)
        tmp.replace(dst / name)
    stages = {}
    try:
        stages = json.loads((dst / "stages.json").read_text())
        stages = stages if isinstance(stages, dict) else {}
    except (OSError, ValueError):
        pass
    stages["dynamics"] = rec.entry
    write_json_atomic(dst / "stages.json", stages)


def _best(runs: list[SeedRun]) -> SeedRun | None:
    ok = [r for r in runs if r.certified]
    return min(ok, key=lambda r: (-r.certified_area, r.seed)) if ok else None


def run_portfolio(system, cfg: dict, out: str | Path, *, seeds: int | list[int],
                  workers: int | None = None, scheduler: str | None = None,
                  known_dynamics: bool = False, log=print,
                  connect_timeout: float | None = None, client=None) -> PortfolioResult:
    """Train and certify one candidate per seed in parallel; keep the best certified one.

    Parameters
    ----------
    system : str, path or systems.System
        A catalogue name, or a system spec file (TOML; each worker loads it). A ``System``
        object is sent by its name: it must be registered in the worker processes too.
    cfg : RunConfig or dict
        A validated run configuration (:func:`nlyap_opt.workflow.configs.get_config`).
    out : path
        Portfolio directory; seed ``k`` runs in ``out/seed_k`` (an earlier portfolio's
        directories are resumed stage by stage).
    seeds : int or list of int
        ``K`` (seeds ``0 … K−1``) or the seeds themselves (distinct, ≥ 0).
    workers : int, optional
        Worker processes of the local cluster (default: ``min(K, CPU cores)``); with
        ``scheduler``, the workers to wait for.
    scheduler : str, optional
        ``tcp://HOST:PORT`` of an existing Dask cluster (never closed here).
    connect_timeout : float, optional
        Seconds to reach the scheduler (default
        :data:`nlyap_opt.distributed.parallel.DEFAULT_CONNECT_TIMEOUT`).
    known_dynamics : bool
        Use the true f instead of learned φ (then there is no dynamics stage to share).
    log : callable
        Progress lines of the portfolio (each run's own log goes to ``seed_k/run.log``).
    client : distributed.Client or SimulatedCluster, optional
        Run the seeds on this client (kept open) instead of a cluster started here; not
        with ``workers`` or ``scheduler``. A
        :class:`nlyap_opt.distributed.parallel.SimulatedCluster` (``cost="cpu"``) runs the
        seeds one after another in this process and models their schedule on its workers
        (the portfolio's speed-up model, ``bench/portfolio.py``).

    Returns
    -------
    PortfolioResult

    Raises
    ------
    ConfigError
        Bad ``seeds``, ``workers`` or ``scheduler``.

    Examples
    --------
    >>> from nlyap_opt.workflow.configs import get_config
    >>> res = run_portfolio("van_der_pol", get_config("van_der_pol", "fast"),  # doctest: +SKIP
    ...                     "runs/pf", seeds=4, workers=2, known_dynamics=True)
    >>> res.best.seed, res.best.certified_area                               # doctest: +SKIP
    """
    seed_list = _check_seeds(seeds)
    if isinstance(cfg, RunConfig):
        cfg = cfg.to_json()
    if not isinstance(cfg, dict):
        raise ConfigError(f"cfg must be a run configuration, got {type(cfg).__name__}; "
                          "use nlyap_opt.workflow.configs.get_config(system, preset)")
    name, spec = _resolve_system(system)
    if name in _systems.names():  # the checks pipeline.run makes, once for all seeds
        for s in seed_list:
            validate_config(seed_config(cfg, s), name)
        if not known_dynamics:
            check_dynamics_box(cfg)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"out {out} is a file; pass a directory (new or of a portfolio)")
    out.mkdir(parents=True, exist_ok=True)
    if client is not None and (workers is not None or scheduler is not None):
        raise ConfigError("give a client, or workers/scheduler for a cluster started here, "
                          "not both")
    if workers is None and scheduler is None:
        workers = max(1, min(len(seed_list), cpu_cores()))
    dirs = {s: out / f"seed_{s}" for s in seed_list}
    t0 = time.perf_counter()
    given = contextlib.nullcontext(client) if client is not None else dask_client(
        workers=workers, scheduler=scheduler,
        connect_timeout=connect_timeout or DEFAULT_CONNECT_TIMEOUT)
    with given as client:
        n_workers = client.workers if getattr(client, "simulated", False) else \
            client_workers(client)
        log(f"[portfolio] {name}: seeds {seed_list} on {n_workers} worker(s)")
        runs, shared = _run_seeds(client, name, spec, cfg, dirs, known_dynamics, log)
    res = PortfolioResult(runs, _best(runs), out, n_workers, time.perf_counter() - t0,
                          system=name, known_dynamics=known_dynamics, shared_dynamics=shared)
    _write(res)
    if res.best is None:
        log(f"[portfolio] no seed certified; see {out / 'portfolio.md'}")
    else:
        log(f"[portfolio] best: seed {res.best.seed} (certified area "
            f"{res.best.certified_area:.4g}); see {out / 'portfolio.md'}")
    return res


def _resolve_system(system) -> tuple[str, str | None]:
    """``(name, spec file or None)`` of a catalogue name, a spec file or a System (an
    unknown name fails here, before a cluster starts)."""
    spec = None
    if isinstance(system, (str, os.PathLike)) and (
            str(system).endswith(".toml") or Path(system).is_file()):
        spec = str(Path(system).resolve())  # a system spec file: each worker loads it
        system = _systems.load_spec(spec)
    elif Path(str(getattr(system, "source", "") or "")).is_file():
        spec = str(Path(system.source).resolve())  # a System loaded from a spec file
    name = system if isinstance(system, str) else getattr(system, "name", None)
    if not isinstance(name, str):
        raise ConfigError(f"system must be a catalogue name, a spec file or a systems.System, "
                          f"got {system!r}")
    if spec is None:
        _systems.get(name)
    return name, spec


def _run_seeds(client, name: str, spec: str | None, cfg: dict, dirs: dict, known_dynamics: bool,
               log) -> tuple[list[SeedRun], str | None]:
    """Every seed's run on ``client`` (with learned dynamics the first seed's dynamics stage
    shared with the others); ``(the runs in the order of dirs, the seed directory φ came
    from)``."""
    seed_list = list(dirs)
    results: dict[int, SeedRun] = {}
    shared = None

    def submit(s):
        return client.submit(_run_seed, name, seed_config(cfg, s), str(dirs[s].resolve()),
                             known_dynamics, spec, s, pure=False)

    first, rest = seed_list[0], seed_list[1:]
    futures = {first: submit(first)}
    if known_dynamics:
        futures.update({s: submit(s) for s in rest})
    else:  # learn φ once: wait for the first seed's dynamics stage, then share it
        rec = None
        while rec is None and not futures[first].done():
            rec = _dynamics_record(dirs[first])
            if rec is None:
                time.sleep(_POLL)
        rec = rec or _dynamics_record(dirs[first])
        if rec is not None:
            shared = f"seed_{first}"
            for s in rest:
                _share_dynamics(dirs[first], dirs[s], rec)
            log(f"[portfolio] dynamics learned once (seed {first}), shared with "
                f"{len(rest)} other seed(s)")
            futures.update({s: submit(s) for s in rest})
        else:
            r0 = futures[first].result()  # raises the first seed's error, if any
            reason = (f"not run: seed {first} stopped in the shared dynamics stage "
                      f"({r0.status}: {r0.reason})")
            for s in rest:
                results[s] = SeedRun(s, "skipped", False, None, 0.0, None, 0.0, dirs[s].name,
                                     reason)
    try:
        for s, fut in futures.items():
            results[s] = r = fut.result()
            log(f"[portfolio] seed {s}: {r.status}"
                + (f", level {r.level:.6g}, area {r.certified_area:.4g}"
                   if r.certified else f" ({r.reason})")
                + f", {r.seconds:.1f} s")
    finally:
        client.cancel([f for f in futures.values() if not f.done()])
    return [results[s] for s in seed_list], shared


def _write(res: PortfolioResult) -> None:
    """``portfolio.json``, ``portfolio.md`` and the ``best`` link in ``res.out``."""
    out = res.out
    write_json_atomic(out / "portfolio.json", res.to_json())

    def num(v, fmt):
        return "–" if v is None else format(v, fmt)

    lines = [f"# Portfolio: {res.system} ({'true f' if res.known_dynamics else 'learned φ'})",
             "",
             f"{len(res.runs)} seeds on {res.workers} Dask worker(s), {res.seconds:.1f} s "
             "wall-clock. Kept: the certified seed with the largest certified area "
             "(ties: the lowest seed)."
             + (f" The learned dynamics were computed once ({res.shared_dynamics}) and "
                "shared." if res.shared_dynamics else ""),
             "",
             "| seed | status | level | certified area | share of true ROA | seconds | run |",
             "|---|---|---|---|---|---|---|"]
    for r in res.runs:
        mark = " **(best)**" if res.best is not None and r.seed == res.best.seed else ""
        status = r.status + ("" if r.certified or not r.reason else f" ({r.reason})")
        lines.append(f"| {r.seed}{mark} | {status} | {num(r.level, '.6g')} | "
                     f"{num(r.certified_area if r.certified else None, '.4g')} | "
                     f"{num(None if r.share is None else 100 * r.share, '.1f')}"
                     f"{'' if r.share is None else ' %'} | {r.seconds:.1f} | [{r.dir}]({r.dir}/) |")
    lines.append("")
    linked = _link_best(res)
    if res.best is None:
        lines.append("No seed certified.")
    else:
        lines.append(f"Best certificate: [{res.best.dir}/certificate.json]"
                     f"({res.best.dir}/certificate.json)"
                     + (" (also `best/`)" if linked else
                        " (`best/` is not a link to it: a directory of that name, not "
                        "written by this portfolio, is in the way)"
                        if (out / "best").exists() else "")
                     + f", report [{res.best.dir}/report.md]({res.best.dir}/report.md).")
    write_atomic(out / "portfolio.md", "\n".join(lines) + "\n")


def _link_best(res: PortfolioResult) -> bool:
    """``OUT/best``, a link to the best seed's directory; whether it is one now. A real
    directory named best (not this tool's) is left alone: it is not the best seed."""
    link = res.out / "best"
    if link.is_symlink() or link.exists():
        if link.is_symlink() or link.is_file():
            link.unlink()
        else:
            return False
    if res.best is None:
        return False
    try:
        os.symlink(res.best.dir, link, target_is_directory=True)
    except OSError:  # no symlinks here (some filesystems): portfolio.json points to it
        return False
    return True
