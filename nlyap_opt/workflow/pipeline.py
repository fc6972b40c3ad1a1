"""``nlyap run``: from samples to a certified region of attraction, in resumable stages.

Stages (each saves its artifacts in the output directory; a rerun with the same
configuration loads finished stages instead of recomputing them):

1. ``dynamics`` — learn φ on a grid, compute α, δ, K_f, K_φ, η (skipped with
   ``known_dynamics``);
2. ``controller`` — LQR on the linearisation, saturated controller with solved bias;
   ``local`` — only with learned dynamics whose η on the whole sampling box leaves no room
   for the robust margin: η bounded again on the sub-box of a smaller verification ball
   (:func:`_local_stage`);
3. ``quadratic`` — only when the configuration lists ``quadratic`` candidates: the cheap
   certificates ``V = xᵀPx`` under the initial controller (:mod:`nlyap_opt.candidates.quadratic`);
   the best one is saved as ``V_quadratic.json``;
   ``sos`` — only when ``sos.degree`` > 0, or ``"auto"`` and
   :func:`~nlyap_opt.candidates.sos.choose_degree` picks a degree (a polynomial closed loop:
   the model of f, or with learned dynamics and no input a polynomial fitted to φ; SDPs small
   enough): an SOS ``V`` (:mod:`nlyap_opt.candidates.sos`), saved as
   ``V_sos.json`` when certified;
4. ``cegis`` — learn V and κ, certify conditions (a) and (b) at a level;
5. ``certificate`` — always rerun: the saved V, κ, φ are verified again at the saved level
   with conditions (a), (b), (c) (:func:`nlyap_opt.certification.certificate.certify_roa`) before
   ``certified`` is written, and so are the saved quadratic and SOS V; the largest
   certified volume on the evaluation grid wins (the neural V on a tie) and is written as
   ``certificate.json``, the others listed under ``candidates``; certified and true-ROA
   areas, the check of the *same* V and κ against the true f (a benchmark, reported
   separately); ``report.md`` and ``roa.png``.

Each stage declares the configuration keys it reads (:data:`_STAGE_FIELDS`) and reads the
:class:`~nlyap_opt.workflow.configs.RunConfig` only through the view of those keys, which refuses
any other. Nothing on disk is trusted without a check: ``stages.json`` records, per stage, the
hash of those keys' values and the sha256 of every file it wrote; a stage whose files changed
(or whose record is unreadable) is recomputed, saying so, and so is every stage built on it.
Files are written atomically, so an interrupted run resumes from its finished stages. A lock
file keeps a second concurrent run out of the same directory.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from pathlib import Path
from types import MappingProxyType, SimpleNamespace
from typing import Any

import casadi as ca
import numpy as np

import systems as _systems
from verification import closed_loop_problem

from ..candidates.cegis import CegisConfig, cegis
from ..candidates.learning import TrainConfig, quadratic_start, sos_start
from ..candidates.quadratic import certify_quadratics, closed_loop_matrix
from ..candidates.sos import (
    AUTO,
    SOSConfig,
    certify_sos,
    choose_degree,
    learned_model,
    sos_may_fit,
)
from ..certification.certificate import (
    CertStatus,
    RoaCertificate,
    RoaProblem,
    VolumeToBeat,
    certify_roa,
    certify_with_inner_search,
    parse_bound,
    save_certificate,
    sha256_file,
    system_fingerprint,
    unchecked,
    write_json_atomic,
)
from ..certification.roa import (
    TRUE_ROA_TIME,
    axis_count,
    centre_lyapunov_matrix,
    grid_area,
    grid_points,
    true_roa_horizon,
    true_roa_mask,
    true_roa_stays,
)
from ..design.control import lqr, quadratic_lyapunov, saturated_controller
from ..design.polynomial import Polynomial
from ..distributed.parallel import (
    DEFAULT_CONNECT_TIMEOUT,
    client_workers,
    dask_client,
    verifying_on,
)
from ..distributed.parallel import check as parallel_check
from ..kernel.domain import Ball
from ..kernel.errors import ConfigError, NlyapError
from ..kernel.jsonio import (
    load_with_timings,
    read_npz,
    save_timings,
    split_timings,
    write_atomic,
)
from ..kernel.network import Network
from ..kernel.provenance import fingerprint
from ..kernel.sampling import sample_sphere
from ..kernel.symbolic import closed_loop
from ..learned.dynamics import as_config
from ..learned.dynamics_stage import GateStatus, dynamics_stage, eta_limit_linear
from ..learned.error_models import write_bounds
from ..learned.local_bound import local_bound, local_box
from .configs import RunConfig, check_dynamics_box, domain_of, validate_config
from .report import status_line, write_report

__all__ = ["run", "RunResult", "RunLockedError"]


def _hash(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _seal(key: str, arrays: list) -> str:
    """The sha256 of ``key`` and the arrays' shapes and bytes (a cache's own check)."""
    h = hashlib.sha256(key.encode())
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape};".encode())
        h.update(a.tobytes())
    return h.hexdigest()


class RunLockedError(NlyapError, RuntimeError):
    """Another run holds the output directory."""


@dataclass
class RunResult:
    """Result of :func:`run`.

    Attributes
    ----------
    certificate : RoaCertificate
        The certificate of the saved V, κ (and φ), re-verified in this call.
    status : CertStatus
        ``certificate.status`` (or ``NOT_CERTIFIED`` when a gate stopped the run early).
    summary : dict
        The content of ``certificate.json`` (areas, checks, assumptions, timings).
    out : Path
        The output directory.
    """

    certificate: RoaCertificate | None
    status: CertStatus
    summary: dict
    out: Path
    reason: str = ""

    @property
    def certified(self) -> bool:
        return self.status is CertStatus.CERTIFIED


#: the verification region every stage after the dynamics stage works in (the inner radius
#: with auto_inner too): a stage that uses it declares these keys (:meth:`_Run.region`)
_REGION = ("inner", "outer", "domain", "initial_set", "auto_inner")
#: the evaluation grid of areas and of the simulated true ROA
_EVAL = ("eval_box", "eval_points")
#: the verifier settings every check of the run uses (CEGIS certified with them)
_VERIFY = ("cegis.verify_options", "cegis.margin_mode")

#: the configuration keys each stage reads, declared once: the stage receives the view of
#: these keys only (:meth:`nlyap_opt.workflow.configs.RunConfig.view`; reading another raises
#: UndeclaredKeyError) and its stage key hashes their values. The cheap certificates read
#: only the verifier settings of 'cegis' (a changed cegis.steps does not recompute them).
_STAGE_FIELDS: dict[str, tuple[str, ...]] = {
    "dynamics": ("dynamics",),
    "controller": ("lqr", "controller_scale"),
    "quadratic": _REGION + ("quadratic",) + _VERIFY + _EVAL,
    "sos": _REGION + ("sos",) + _VERIFY + _EVAL,
    # lqr: the gain scan (cegis.gain_scan) runs only where the user left the LQR weights
    "cegis": _REGION + ("train", "cegis", "lqr") + _EVAL,
    "local": _REGION + ("dynamics",),
}
#: the files each stage writes (the sha256 of each is recorded)
_STAGE_FILES = {
    "dynamics": ("dynamics.json", "bounds.json"),
    "controller": ("controller_init.json", "lqr.json"),
    "quadratic": ("quadratic.json", "V_quadratic.json"),
    "sos": ("sos.json", "V_sos.json"),
    "cegis": ("V.json", "controller.json", "cegis.json"),
    "local": ("local.json", "bounds_local.json"),
}


def _write_stage_json(path: Path, data: dict) -> None:
    """A stage file: hashed, so its wall-clock timings go to ``timings.json`` beside it
    (the same input then gives the same bytes)."""
    clean, timings = split_timings(data)
    write_json_atomic(path, clean)
    save_timings(path, timings)


def _record_error(path: Path, err: Exception) -> ConfigError:
    return ConfigError(f"{path} cannot be read ({err}); delete it and rerun (its stage is "
                       "recomputed)")


@dataclass(frozen=True)
class _CegisRecord:
    """The CEGIS stage's record (``cegis.json``; its timings in ``timings.json``).

    Attributes
    ----------
    status : CertStatus
        What CEGIS certified (the certificate stage verifies the saved V again).
    reason : str
    level : float
        The level CEGIS certified (0 when none).
    margin, M, smoothing, area_in_ball
        The margin, the bound M, the smoothing of the pointwise margin and the share of
        the ball inside the level set, as CEGIS reported them.
    history : list
        One entry per CEGIS iteration.
    seconds : float or None
        Wall-clock seconds of the stage (``None`` when its timings file is gone).
    """

    status: CertStatus
    reason: str
    level: float
    margin: Any
    M: Any
    smoothing: Any
    area_in_ball: Any
    history: list
    seconds: float | None = None

    def to_json(self) -> dict:
        """The content of ``cegis.json`` (with its timings)."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["status"] = self.status.value
        return out

    @classmethod
    def load(cls, path: Path) -> _CegisRecord:
        """The record saved at ``path`` (its timings put back), its content checked."""
        data = load_with_timings(path)
        try:
            if not isinstance(data, dict):
                raise ValueError("not a JSON object")
            rec = cls(**{**{f.name: data[f.name] for f in fields(cls) if f.name != "seconds"},
                         "status": CertStatus(data["status"]),
                         "seconds": data.get("seconds")})
            for name in ("level", "smoothing", "margin", "M"):
                v = getattr(rec, name)
                if (v is not None or name in ("level", "smoothing")) and not (
                        isinstance(v, (int, float)) and not isinstance(v, bool)
                        and math.isfinite(v) and v >= 0):
                    raise ValueError(f"{name} is {v!r}, not a finite number >= 0")
            if not isinstance(rec.history, list):
                raise ValueError("history is not a list")
            return rec
        except (KeyError, TypeError, ValueError) as err:
            raise _record_error(path, err) from None


@dataclass(frozen=True)
class _CheapRecord:
    """A certified cheap certificate (quadratic or SOS) as its stage saved it: what CEGIS
    may start at and what the certificate stage verifies again.

    Attributes
    ----------
    kind : str
        ``"quadratic"`` or ``"sos"``.
    label : str
        How messages name it (``"quadratic round"``, ``"SOS degree 4"``).
    file : str
        Its V's file in the output directory.
    level, inner, volume : float
        The certified level, its inner radius ε and the certified volume on the evaluation
        grid.
    verify_options : Mapping
        The verifier options it was proved with.
    name : str
        The quadratic candidate's name (``""`` for SOS).
    P : list or None
        The quadratic candidate's matrix (``None`` for SOS).
    """

    kind: str
    label: str
    file: str
    level: float
    inner: float
    volume: float
    verify_options: Mapping
    name: str = ""
    P: list | None = None

    def to_json(self) -> dict:
        """The SOS stage's ``best`` record in ``sos.json``."""
        return {"kind": self.kind, "label": self.label, "file": self.file,
                "level": self.level, "inner": self.inner, "volume": self.volume,
                "verify_options": dict(self.verify_options)}

    @classmethod
    def of_stage(cls, kind: str, best: Mapping | None, path: Path) -> _CheapRecord | None:
        """The record of a ``kind`` stage's ``best`` (``quadratic.json``: the winning
        candidate's record; ``sos.json``: :meth:`to_json`), ``None`` when none was
        certified; ``path`` names the file in an error."""
        if best is None:
            return None
        try:
            if kind == "quadratic":
                return cls(kind, f"quadratic {best['name']}", "V_quadratic.json",
                           best["level"], best["inner"], best["volume"],
                           best.get("verify_options") or {}, str(best["name"]), best["P"])
            return cls(best["kind"], best["label"], best["file"], best["level"],
                       best["inner"], best["volume"], best.get("verify_options") or {})
        except (KeyError, TypeError, AttributeError) as err:
            raise _record_error(path, err) from None

    @classmethod
    def load(cls, kind: str, path: Path) -> _CheapRecord | None:
        """The ``best`` record of the stage file ``path`` (see :meth:`of_stage`)."""
        try:
            data = json.loads(path.read_text())
            if not isinstance(data, dict):
                raise ValueError("not a JSON object")
        except (OSError, ValueError) as err:
            raise _record_error(path, err) from None
        return cls.of_stage(kind, data.get("best"), path)


class _Stages:
    """Stage bookkeeping in ``DIR/stages.json``: stage -> {key, files: {name: sha256}}.

    A stage's key covers the system, the setting, the values of the configuration keys the
    stage declares (:data:`_STAGE_FIELDS`, the view it reads) and the recorded file hashes
    of the stages it builds on. The numeric environment is not part of it: Dask workers
    start in another one (one BLAS thread) and must find the stages their parent computed;
    every certificate records the environment it was made in.
    """

    def __init__(self, out: Path, system: str, known: bool, cfg: RunConfig, log):
        self.out, self.log, self.system, self.known, self.cfg = out, log, system, known, cfg
        self.file = out / "stages.json"
        self.done: dict = {}
        self.marks = 0          # stages computed (and recorded) by this call
        if self.file.exists() and not self.file.is_file():   # found now, not after a stage
            raise ConfigError(f"{self.file} is not a regular file (a directory?); remove it "
                              "or write to another --out")
        if self.file.exists():
            try:
                done = json.loads(self.file.read_text())
                if not isinstance(done, dict) or not all(
                        isinstance(v, dict) and "key" in v for v in done.values()):
                    raise ValueError("unexpected content")
                self.done = done
            except (ValueError, OSError) as err:
                log(f"warning: {self.file} is unreadable ({err}); recomputing every stage")

    def view(self, stage: str) -> RunConfig:
        """The configuration as ``stage`` may read it: its declared keys only."""
        return self.cfg.view(_STAGE_FIELDS[stage])

    def key(self, stage: str, *deps) -> str:
        return _hash([stage, self.system, self.known, dict(self.view(stage).declared()),
                      [self.done.get(d, {}).get("files") for d in deps]])

    def finished(self, stage: str, *deps) -> bool:
        rec = self.done.get(stage)
        if rec is None:
            return False
        if rec.get("key") != self.key(stage, *deps):
            self.log(f"[{stage}] configuration, system or earlier stage changed: recomputing")
            return False
        files = rec.get("files")
        if not isinstance(files, dict) or not all(
                isinstance(n, str) and isinstance(h, str) for n, h in files.items()) or \
                rec.get("seal") != _hash([rec["key"], files]):
            # the files' hashes are sealed with the key: a record whose list was emptied or
            # edited would otherwise let the stage's files through unchecked
            self.log(f"[{stage}] its record in stages.json was edited: recomputing the stage")
            return False
        for name, digest in files.items():
            f = self.out / name
            if not f.exists():
                self.log(f"[{stage}] {name} is missing: recomputing the stage")
                return False
            if sha256_file(f) != digest:
                self.log(f"[{stage}] {name} changed since this stage wrote it: recomputing "
                         "the stage")
                return False
        self.log(f"[{stage}] loaded from {self.out} (finished earlier, files unchanged)")
        return True

    def mark(self, stage: str, *deps):
        files = {n: sha256_file(self.out / n) for n in _STAGE_FILES[stage]
                 if (self.out / n).exists()}
        key = self.key(stage, *deps)
        # the system named in plain words too: a run of another system into this directory,
        # interrupted before its certificate was written, is recognised (nlyap run --out)
        self.done[stage] = {"key": key, "files": files, "seal": _hash([key, files]),
                            "system": self.system.rsplit(":", 1)[0]}
        write_json_atomic(self.file, self.done)
        self.marks += 1


class _OutLock:
    """``DIR/.nlyap.lock`` holding the pid of the run that writes into ``DIR``."""

    def __init__(self, out: Path, log):
        self.path, self.log = out / ".nlyap.lock", log

    def __enter__(self):
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            except FileExistsError:
                try:
                    pid = int(self.path.read_text().strip() or 0)
                except (OSError, ValueError):
                    pid = 0
                if pid and pid != os.getpid() and _alive(pid):
                    raise RunLockedError(
                        f"another nlyap run (pid {pid}) is writing into {self.path.parent}; "
                        "wait for it to finish or pass another --out") from None
                self.log(f"note: removing a stale lock of pid {pid} in {self.path.parent}")
                self.path.unlink(missing_ok=True)
                continue
            with os.fdopen(fd, "w") as fh:
                fh.write(str(os.getpid()))
            return self
        raise RunLockedError(f"cannot lock {self.path.parent}; remove {self.path} and rerun")

    def __exit__(self, *exc):
        self.path.unlink(missing_ok=True)
        return False


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _out_dir(out) -> Path:
    if isinstance(out, bytes) or not isinstance(out, (str, os.PathLike)) or \
            not str(out).strip():
        raise ConfigError(f"out must be the path of a directory (a str or pathlib.Path, not "
                          f"empty), got {out!r}; pass e.g. 'runs/my_system'")
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise ConfigError(f"--out {out} is a file; pass a directory (new or of an earlier run)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ConfigError(f"cannot create the output directory {out}: "
                          f"{err.strerror or err}; pass a writable --out") from None
    return out


def run(system, cfg: RunConfig | dict, out: str | Path, *, known_dynamics: bool = False,
        log=print, workers: int | None = None, scheduler: str | None = None,
        connect_timeout: float | None = None) -> RunResult:
    """Run the pipeline for ``system`` with the run configuration ``cfg`` into ``out``.

    Parameters
    ----------
    system : str or systems.System
        A catalogue name or a system object.
    cfg : RunConfig or dict
        A validated run configuration (:func:`nlyap_opt.workflow.configs.make_config`), or its JSON
        (checked here for a registered system).
    out : path
        Output directory (created; an earlier run's directory is resumed).
    known_dynamics : bool
        Use the true f (the paper's "actual dynamics" setting) instead of learning φ.
    workers, scheduler : optional
        Run the certificate stage's interval checks on Dask
        (:func:`nlyap_opt.distributed.parallel.dask_client`: a local cluster of ``workers``
        processes, or the existing cluster at ``scheduler``). Status, level, checks and artifacts
        are the serial run's; the verification statistics (boxes, seconds) differ
        (:func:`nlyap_opt.distributed.parallel.check`).
    connect_timeout : float, optional
        Seconds to reach the scheduler (default
        :data:`nlyap_opt.distributed.parallel.DEFAULT_CONNECT_TIMEOUT`).

    Returns
    -------
    RunResult
    """
    system = _systems.get(system) if isinstance(system, str) else system
    if system.name in _systems.names():   # a hand-built dict gets the CLI's checks too
        validate_config(cfg, system.name)
        if not known_dynamics:
            check_dynamics_box(cfg)
    cfg = RunConfig.from_json(cfg)
    out = _out_dir(out)
    with _OutLock(out, log), _client(workers, scheduler, log, connect_timeout) as client:
        return _run(system, cfg, out, known_dynamics, log, client)


@contextlib.contextmanager
def _client(workers, scheduler, log, connect_timeout=None):
    """``None`` (serial), or a Dask client for the certificate stage's checks: connected
    before any stage runs, so that a bad address fails before the training."""
    if workers is None and scheduler is None:
        yield None
        return
    with dask_client(workers, scheduler,
                     connect_timeout=connect_timeout or DEFAULT_CONNECT_TIMEOUT) as client:
        log(f"[dask] certificate checks on {client_workers(client)} workers")
        yield client


def _run(system, cfg: RunConfig, out: Path, known_dynamics: bool, log,
         client=None) -> RunResult:
    """The stages in order (each loads its finished files or computes them), then the
    certificate stage."""
    _check_setting(system, cfg, known_dynamics)
    _log_centre(system, cfg, log)
    region = cfg.view(_REGION)
    D, XI = domain_of(region, system.nx)
    # the stages' keys name the system by its fingerprint (equations, boxes, u_eq, data):
    # a spec edited under the same name recomputes every stage
    ctx = _Context(system, out, _Stages(out, f"{system.name}:{system_fingerprint(system)}",
                                        known_dynamics, cfg, log), log,
                   D, XI, D.max_norm(), float(region.inner))
    seconds: dict[str, float] = {}
    if not known_dynamics:
        stopped = _dynamics_stage(ctx, seconds)
        if stopped is not None:
            return stopped
    ctx.controller = _controller_stage(ctx)
    if ctx.eta > 0:
        _local_stage(ctx)
        ctx.eps = _inner_for_margin(system, ctx.controller, ctx.dynamics, ctx.eta, ctx.eps, D,
                                    region.auto_inner, log)
    quad = _timed(_quadratic_stage, ctx, "quadratic", seconds)
    sos = _timed(_sos_stage, ctx, "sos", seconds)
    cg = _cegis_stage(ctx, {"quadratic": quad, "sos": sos}, seconds)
    return _certificate_stage(ctx, cfg, cg, [c for c in (quad, sos) if c is not None],
                              seconds, client)


def _timed(stage, ctx: _Context, name: str, seconds: dict):
    """``stage(ctx)``, its wall seconds recorded under ``name`` when it computed (a stage
    loaded from its finished files keeps the seconds of the call that computed it)."""
    t = time.perf_counter()
    n_marked = ctx.stages.marks
    res = stage(ctx)
    if ctx.stages.marks != n_marked:
        seconds[name] = time.perf_counter() - t
    return res


def _check_setting(system, cfg: RunConfig, known_dynamics: bool) -> None:
    """Settings the system's kind rules out (an exit-3 error naming the fix)."""
    if known_dynamics and not getattr(system, "has_model", True):
        raise ConfigError(f"system {system.name!r} has no model of f ({system.kind}); it can "
                          "only be run with learned dynamics: drop --known-dynamics")
    unstable = _systems.spec.unstable_origin(system)
    if unstable:
        raise ConfigError(unstable)
    if cfg.train.init == "sos" and (not known_dynamics or system.nu):
        raise ConfigError(
            "train.init 'sos' starts V at the run's SOS certificate; it is supported with the "
            "true f (--known-dynamics) and a closed loop without inputs (the controller "
            "C·tanh(Kx + b) is not polynomial); use init 'random' or 'quadratic'")


def _log_centre(system, cfg: RunConfig, log) -> None:
    """Say so when the linearisation has a centre (:func:`systems.spec.centre_dimension`):
    the defaults of such a system (:func:`systems.default_run_settings`) differ."""
    k = _systems.spec.centre_dimension(system)
    if k:
        log(f"[centre] the linearisation at 0 has {k} eigenvalue(s) on the imaginary axis that "
            "no input moves: the origin is not exponentially stable; condition (c) by the "
            f"weighted blow-up (inner = {float(cfg.inner):.4g}"
            + (f", V: {cfg.train.activation} activation" if cfg.preset is None else "")
            + ")")


@dataclass
class _Context:
    """What the stages share: the system, the output directory, the verification region
    (ε raised by ``auto_inner`` once η is known) and the learned dynamics (φ, η, the boxes
    of the bound and its record) and the initial controller."""

    system: Any
    out: Path
    stages: _Stages
    log: Any
    D: Any
    XI: Any
    r: float
    eps: float
    dynamics: Network | None = None
    eta: float = 0.0
    bounds: dict | None = None
    dyn_box: np.ndarray | None = None
    input_box: np.ndarray | None = None
    controller: Network | None = None
    #: the file of the bound η in use (``bounds_local.json`` when :func:`_local_stage`
    #: replaced the global bound)
    bounds_file: str = "bounds.json"
    #: the stages the bound η comes from (``local`` joins when it replaced the global one)
    eta_stages: tuple = ("dynamics",)

    def region(self, view: RunConfig) -> tuple:
        """``(D, X_I, r, ε)`` for a stage whose view declares the region keys
        (:data:`_REGION`): reading them through the view fails for one that does not, so
        no stage key can miss a key the region comes from."""
        for name in _REGION:
            getattr(view, name)
        return self.D, self.XI, self.r, self.eps

    def problem(self, view: RunConfig, V, ctrl, **kw) -> RoaProblem:
        """The run's :class:`RoaProblem` for ``V`` and ``ctrl`` under the verifier settings
        of ``view`` (``cegis.margin_mode``; ``cegis.verify_options`` unless given: the
        options CEGIS certified with hold for every check of the run)."""
        D, XI, r, eps = self.region(view)
        kw.setdefault("verify_options", view.cegis.verify_options.to_json())
        assumed = [] if self.bounds is None else \
            [f"{self.bounds['bound_model']['name']} bound"] + list(
                self.bounds["bound_model"].get("assumptions", []))
        return RoaProblem(self.system, V, ctrl, self.dynamics, inner=eps, outer=r,
                          eta=self.eta, margin_mode=view.cegis.margin_mode, domain=D,
                          initial_set=XI, dynamics_box=self.dyn_box, input_box=self.input_box,
                          dynamics_assumptions=assumed, **kw)


def _finite_or_inf(bounds, path: Path) -> float:
    """η of a bounds record: a number (``inf``, written as a string, when no bound was
    found: the gate then stops the run), else a one-line error naming the file."""
    eta = bounds.get("eta") if isinstance(bounds, dict) else None
    if eta == "inf" or (isinstance(eta, (int, float)) and not isinstance(eta, bool)
                        and not math.isnan(eta) and eta >= 0):
        return float(eta)
    raise _record_error(path, ValueError(f"eta is {eta!r}, not a number >= 0"))


def _dynamics_stage(ctx: _Context, seconds: dict) -> RunResult | None:
    """Stage 1: φ and η (learned, or loaded); ``None``, or the result of a run the η gate
    stopped."""
    system, out, log = ctx.system, ctx.out, ctx.log
    if not ctx.stages.finished("dynamics"):
        t = time.perf_counter()
        dcfg = ctx.stages.view("dynamics").dynamics.to_json()
        dcfg.setdefault("progress", log is print)   # progress bars on the terminal only
        dynamics_stage(system, dcfg, log=log).save(out)
        seconds["dynamics"] = time.perf_counter() - t
        ctx.stages.mark("dynamics")
    ctx.dynamics = Network.load(out / "dynamics.json")
    # bounds.json is read back even when fresh: error_models.write_bounds writes a
    # normalised record (inf as a string), and the certificate quotes that record
    bounds = ctx.bounds = load_with_timings(out / "bounds.json")
    ctx.eta = eta = _finite_or_inf(bounds, out / "bounds.json")
    gate = bounds.get("gate") or {}
    if _gate_status(gate, out / "bounds.json") is not GateStatus.OK:
        reason = f"η = {eta:.4g} above eta_target {gate.get('eta_target')}: " \
            f"{gate.get('advice', '')}"
        log(f"[done] status: not certified (dynamics stage): {reason}")
        cert = RoaCertificate(CertStatus.NOT_CERTIFIED, reason, system.name, "learned",
                              0.0, ctx.eps, ctx.r, eta=eta, domain=ctx.D, initial_set=ctx.XI)
        summary = dict(cert.to_dict(), problem={}, stage="dynamics", gate=gate,
                       provenance=fingerprint())
        write_json_atomic(out / "certificate.json", summary)
        return RunResult(cert, CertStatus.NOT_CERTIFIED, summary, out, reason)
    try:   # checked as a re-check checks it (a record whose hash was forged too)
        parse_bound(json.dumps(bounds))
    except (ValueError, KeyError, TypeError, RecursionError, OverflowError) as err:
        raise _record_error(out / "bounds.json", err) from None
    grid_box = np.asarray(bounds["grid"]["box"], dtype=float)
    ctx.dyn_box = dyn_box = grid_box[: system.nx]
    # U of the bound: the grid's input rows (full model) or the system's (control-affine:
    # the error does not depend on u)
    ctx.input_box = grid_box[system.nx:] if len(grid_box) > system.nx else system.input_box
    ball_box = ctx.D.bounding_box()
    if np.any(ball_box[:, 0] < dyn_box[:, 0]) or np.any(ball_box[:, 1] > dyn_box[:, 1]):
        raise ConfigError(
            f"the verification domain {ctx.D.describe()} leaves the box {dyn_box.tolist()} "
            "on which ‖f − φ‖ ≤ η was established; enlarge the dynamics box or shrink the "
            "domain ('outer' or 'domain')"
        )
    log(f"[dynamics] η = {eta:.4g} ({bounds['bound_model']['name']} bound)")
    return None


def _gate_status(gate: Mapping, path: Path) -> GateStatus:
    """The η gate's status in the record ``gate`` of ``path`` (passed when not recorded)."""
    try:
        return GateStatus(gate.get("status", GateStatus.OK.value))
    except (AttributeError, ValueError) as err:
        raise _record_error(path, err) from None


def _controller_stage(ctx: _Context) -> Network | None:
    """Stage 2: the saturated LQR controller (``None`` for a system without inputs)."""
    system = ctx.system
    if not system.nu:
        return None
    has_model = getattr(system, "has_model", True)
    # without a model, the LQR start linearises the learned φ (its CasADi graph)
    cdeps = () if has_model else ("dynamics",)
    if not ctx.stages.finished("controller", *cdeps):
        view = ctx.stages.view("controller")
        res = lqr(system, view.lqr.Q, view.lqr.R,
                  dynamics=None if has_model else ctx.dynamics)
        ctrl = saturated_controller(system, res.K, view.controller_scale)
        ctrl.save(ctx.out / "controller_init.json")
        write_json_atomic(ctx.out / "lqr.json", res.to_dict())
        ctx.stages.mark("controller", *cdeps)
    return Network.load(ctx.out / "controller_init.json")


def _cegis_stage(ctx: _Context, starts: Mapping[str, _CheapRecord | None],
                 seconds: dict) -> _CegisRecord:
    """Stage 4: V and κ by CEGIS; returns the ``cegis.json`` record (fresh, or loaded)."""
    view = ctx.stages.view("cegis")
    train = TrainConfig(**view.train.to_json())
    # train.init: V starts at a cheap certificate; with the true f an iterate that cannot
    # beat the best one is not verified: the CEGIS stage builds on the cheap stages
    cheap = [c for c in starts.values() if c is not None]
    deps = (*ctx.eta_stages, "controller") + tuple(
        k for k, c in starts.items() if c is not None or k == train.init)
    out = ctx.out
    if ctx.stages.finished("cegis", *deps):
        return _CegisRecord.load(out / "cegis.json")
    t = time.perf_counter()
    V0 = _start_V(ctx, train, starts.get(train.init))
    D, XI, r, eps = ctx.region(view)
    ccfg = CegisConfig(inner=eps, outer=r, train=train, domain=D, initial_set=XI,
                       **view.cegis.to_json())
    # LQR weights the user chose are kept: the gain scan only replaces the default Q = R = I
    ccfg.gain_scan = ccfg.gain_scan and view.lqr.Q is None and view.lqr.R is None
    where = f"{eps:g} ≤ ‖x‖ ≤ {r:g}" if view.domain is None else \
        f"‖x‖ ≥ {eps:g} in {D.describe()}"
    ctx.log(f"[cegis] learning V{' and κ' if ctx.controller is not None else ''} on {where}"
            + (f", X_I = {XI.describe()}" if XI is not None else "")
            + (f" with η = {ctx.eta:.3g}" if ctx.eta else " (true f)"))
    beat = None
    if cheap:
        best = max(cheap, key=lambda c: c.volume)
        ctx.log(f"[cegis] the certificate to beat: {best.label}, volume "
                f"{best.volume:.4g} on the evaluation grid")
        beat = VolumeToBeat(best.volume, *_eval_grid(ctx.system, view), best.label)
    res = cegis(ctx.system, ctx.controller, ctx.dynamics, ccfg, eta=ctx.eta,
                dynamics_box=ctx.dyn_box, input_box=ctx.input_box, log=ctx.log, V0=V0,
                beat=beat)
    res.V.save(out / "V.json")
    if res.controller is not None:
        res.controller.save(out / "controller.json")
    rec = _CegisRecord(res.status, res.reason, res.level, res.margin, res.M, res.smoothing,
                       res.area, res.history, res.seconds)
    _write_stage_json(out / "cegis.json", rec.to_json())
    seconds["cegis"] = time.perf_counter() - t
    ctx.stages.mark("cegis", *deps)
    return rec


def _start_V(ctx: _Context, train: TrainConfig, start: _CheapRecord | None):
    """The V that CEGIS starts at (``train.init``): the cheap certificate ``start`` as a
    network, or ``None`` (random)."""
    if start is None:
        if train.init != "random":
            ctx.log(f"[cegis] no {train.init} certificate: V starts at random (train.init)")
        return None
    V0 = None
    if train.init == "quadratic":
        V0 = quadratic_start(np.asarray(start.P, dtype=float), float(start.level), train)
    else:
        try:
            V0 = sos_start(_cheap_V(ctx.out, start), float(start.level), train)
        except ConfigError:
            raise
        except ValueError as err:   # no Gram matrix found: a start, not a claim
            ctx.log(f"[cegis] V cannot start at the {start.label} ({err}): V starts "
                    "at random")
    if V0 is not None:
        ctx.log(f"[cegis] V starts at the {start.label}: level 1 of V = its certified "
                f"set (level {float(start.level):.6g})")
    return V0


def _certificate_stage(ctx: _Context, cfg: RunConfig, cg: _CegisRecord,
                       cheap: list[_CheapRecord], seconds: dict, client) -> RunResult:
    """Stage 5 (always run): the saved V, κ (and φ) verified again at the saved level, the
    saved cheap certificates too, the best one written as ``certificate.json``."""
    system, out, log = ctx.system, ctx.out, ctx.log
    t = time.perf_counter()
    V = Network.load(out / "V.json")
    controller = Network.load(out / "controller.json") if ctx.controller is not None else None
    mode = cfg.cegis.margin_mode
    problem = ctx.problem(cfg, V, controller, smoothing=float(cg.smoothing)
                          if mode == "pointwise" else None)
    claimed = cg.status is CertStatus.CERTIFIED and float(cg.level) > 0
    if claimed:
        log(f"[certificate] verifying the saved V{', κ' if controller else ''}"
            f"{', φ' if ctx.dynamics else ''} at the saved level {float(cg.level):.6g}")
    else:
        log(f"[certificate] CEGIS certified no level ({cg.reason or cg.status.value}); "
            "trying the last V with other inner radii")
    # the saved level at the configured ε first (exact re-verification); other radii only
    # if that is refused (the same V and κ; no retraining). The cheap certificates are
    # verified first: with the true f, a radius whose certificate cannot beat the best of
    # them is not searched
    with verifying_on(client):   # client None: serial
        checked = _verify_cheap(system, cfg, out, problem, cheap, log)
        win = max((c for c in checked if c[1].certified), key=lambda c: c[3], default=None)
        beat = None if win is None else VolumeToBeat(win[3], *_eval_grid(system, cfg),
                                                     win[0].label)
        cert = certify_with_inner_search(problem, float(cg.level) if claimed else None,
                                         beat=beat, log=lambda m: log("  " + m))
        cert, problem, files, compared = _best_certificate(
            system, cfg, cert, problem, checked, log)
        extra = _areas_and_checks(system, cfg, cert, problem, out, log).to_json()
        _refute_by_true_f(cert, extra.get("true_dynamics_check"), ctx.eta, log)
        if compared:
            extra["candidates"] = compared
    seconds["certificate"] = time.perf_counter() - t
    extra["seconds"] = dict(_save_seconds(out, seconds))
    if ctx.bounds is not None:
        extra["dynamics_bound"] = {k: ctx.bounds.get(k) for k in
                                   ("eta", "alpha", "delta", "K_f", "K_phi", "bound_model")}
    if ctx.bounds_file != "bounds.json":
        extra["dynamics_bound"]["local"] = {
            "file": ctx.bounds_file, "radius": ctx.r,
            "box": np.asarray(ctx.bounds["grid"]["box"]).tolist(),
            "global_eta": load_with_timings(out / "local.json")["global_eta"]}
        cert.assumptions.append(
            f"η = {ctx.eta:.6g} bounds ‖f − φ‖ on the sub-box {ctx.bounds_file} names only "
            f"(its own grid; the whole sampling box has η = "
            f"{extra['dynamics_bound']['local']['global_eta']:.4g}): the verification ball "
            f"‖x‖ ≤ {ctx.r:.4g} lies in its states and κ of the ball in its inputs (proved)")
    _say_raised_inner(cert, ctx, float(cfg.view(_REGION).inner))
    if ctx.bounds_file != "bounds.json":
        files = dict(files or {}, bounds=ctx.bounds_file)
    path = save_certificate(cert, problem, out, extra, files=files)
    summary = json.loads(path.read_text())
    write_report(out, system, cfg, summary, ctx.bounds, cg.to_json())
    _log_done(log, cert, summary, out)
    return RunResult(cert, cert.status, summary, out, cert.reason)


def _say_raised_inner(cert, ctx: _Context, configured: float) -> None:
    """Where the run's ε differs from the configured one (raised by ``auto_inner`` from η,
    or scaled with a local bound's ball), the certificate lists it as an assumption; a run
    that certified nothing at a radius raised for η also says, in its reason, that a
    smaller η would let a smaller ε work."""
    if ctx.eps == configured:
        return
    from_eta = ctx.bounds_file == "bounds.json"
    cert.assumptions.append(
        f"inner radius ε = {ctx.eps:.6g} chosen by the tool (configured {configured:g}): "
        + (f"with η = {ctx.eta:.3g} the robust margin η‖∇V‖ needs it" if from_eta else
           f"scaled with the verification ball of the local bound (‖x‖ ≤ {ctx.r:.4g})"))
    if from_eta and not cert.certified:
        advice = (f"ε was raised to {ctx.eps:.4g} (configured {configured:g}) for the "
                  f"robust margin of η = {ctx.eta:.3g}: a smaller η lets a smaller ε work "
                  "(dynamics.grid_counts, dynamics.steps)")
        cert.reason = f"{cert.reason}; {advice}" if cert.reason else advice


def _save_seconds(out: Path, seconds: Mapping[str, float]) -> Mapping[str, float]:
    """``seconds.json``: this call's stage timings over those of earlier calls (returned
    read-only)."""
    sec_file = out / "seconds.json"
    prev = {}
    if sec_file.exists():
        try:
            prev = json.loads(sec_file.read_text())
        except ValueError:
            prev = {}
    prev.update(seconds)
    write_json_atomic(sec_file, prev)
    return MappingProxyType(prev)


def _log_done(log, cert: RoaCertificate, summary: dict, out: Path) -> None:
    if cert.certified and summary["true_roa_area"] is None:
        why = [a for a in summary.get("not_available") or [] if a.startswith("true ROA")]
        log(f"[done] status: {status_line(summary)}; certified area "
            f"{summary['certified_area']:.4g}; not available: "
            f"{why[0] if why else 'true ROA'}; see {out / 'report.md'}")
    elif cert.certified:
        log(f"[done] status: {status_line(summary)}; certified area "
            f"{summary['certified_area']:.4g} = "
            f"{100 * summary['fraction_of_true_roa']:.1f}% of the true ROA "
            f"({summary['true_roa_area']:.4g}"
            + ("" if (stays := summary.get("true_roa_stays_in_domain")) is None or stays >= 1
               else f"; no certificate in D can exceed {100 * stays:.1f}%, the share that "
                    "stays in D")
            + f"); see {out / 'report.md'}")
    else:
        log(f"[done] status: {cert.status.value}: {cert.reason}; see {out / 'report.md'}")


#: the simulated true ROA is not available when fewer grid states in D reach the origin
#: within eval_time than this share of those that neither converge nor diverge
TOO_FEW_CONVERGED = 0.1


#: the inner radius that learned dynamics afford is this multiple of the radius at which the
#: linearised quadratic certificate loses its robust decrease (the presets' margin)
INNER_MARGIN_FACTOR = 2.0


def _inner_for_margin(system, controller, dynamics, eta: float, eps: float, D, auto: bool,
                      log) -> float:
    r"""The inner radius for learned dynamics: ``eps``, or with ``auto`` the smallest ε whose
    robust margin the linearisation affords when that is larger.

    With :math:`A_{cl}^\top P + PA_{cl} = -I` (φ's closed loop at 0) the linear decrease
    :math:`\|x\|^2` beats the robust term :math:`\eta\|\nabla V\| \le
    2\eta\lambda_{\max}(P)\|x\|` only for :math:`\|x\| > 2\eta\lambda_{\max}(P)`
    (:func:`nlyap_opt.learned.dynamics_stage.eta_limit_linear`); ε needs
    :data:`INNER_MARGIN_FACTOR` times that. Only the radius changes: every condition is
    verified as configured, at the radius used (and recorded in the certificate).

    Without ``auto`` (the user fixed ε) an ε below ``need`` gets a warning naming the ε
    that would work (the estimate rests on one quadratic; another V may do better). Only
    an ε that provably cannot work stops the run: a point of the sphere ``‖x‖ = ε`` (where
    the decrease must hold) with ``‖φ(x, κ(x))‖ < η`` defeats every V, since there
    :math:`\nabla V\cdot\varphi + \eta\|\nabla V\| \ge \|\nabla V\|(\eta - \|\varphi\|)
    \ge 0` (:func:`_slow_on_sphere`).

    Raises
    ------
    ConfigError
        ``auto`` is off and a sampled point of the sphere ``‖x‖ = ε`` moves slower than η.
    """
    if _systems.spec.centre_dimension(system):
        need = _centre_inner(system, controller, dynamics, eta, eps, D)
        what = "the centre quadratic's decrease (sampled)"
    else:
        need = _linear_need(system, controller, dynamics, eta, eps)
        if need is None:      # not Hurwitz: no linear estimate; the certificate stage says why
            return eps
        what = "the linear decrease"
    if need <= eps:
        return eps
    room = 0.5 * D.inradius()
    if need >= room:
        log(f"[inner] with η = {eta:.3g} the robust margin needs ε ≥ {need:.3g} (from "
            f"{what}), more than half the domain's inradius {D.inradius():.3g}: lower "
            "η (dynamics.grid_counts, dynamics.steps) or enlarge the domain")
        return eps
    if auto:
        log(f"[inner] ε = {need:.4g} chosen by the tool (configured {eps:g}): with η = "
            f"{eta:.3g} the robust margin η‖∇V‖ beats {what} inside "
            f"‖x‖ < {need / INNER_MARGIN_FACTOR:.3g}")
        return need
    slow = _slow_on_sphere(system, controller, dynamics, eta, eps)
    if slow is not None:
        raise ConfigError(
            f"inner = {eps:g} cannot work with η = {eta:.3g}: at x = {np.round(slow, 4)} "
            f"(‖x‖ = ε) the model's closed loop moves slower than η, so no V decreases "
            f"robustly there; set inner to {need:.3g} or more, or auto_inner = true to let "
            "the tool choose")
    log(f"[inner] warning: with η = {eta:.3g} the robust margin η‖∇V‖ beats {what} "
        f"inside ‖x‖ < {need / INNER_MARGIN_FACTOR:.3g}; other V may still certify at "
        f"inner = {eps:g}; if none does, set inner to {need:.3g} or more (or auto_inner = "
        "true)")
    return eps


def _linear_need(system, controller, dynamics, eta: float, eps: float) -> float | None:
    r"""The inner radius the robust margin ``η‖∇V‖`` needs by the linear decrease:
    :data:`INNER_MARGIN_FACTOR` times :math:`2\eta\lambda_{\max}(P)`, or ``None`` when φ's
    closed loop is not Hurwitz at 0 (no estimate)."""
    try:
        A = closed_loop_matrix(SimpleNamespace(system=system, controller=controller,
                                               dynamics=dynamics))
        return INNER_MARGIN_FACTOR * eps * eta / eta_limit_linear(A, eps)
    except ConfigError:
        return None


#: the radii of the smaller verification balls :func:`_local_stage` tries, as fractions of
#: the configured outer radius (largest first)
LOCAL_FRACTIONS = (0.5, 0.25, 0.125)
#: node budget of each local grid (:func:`nlyap_opt.learned.local_bound.local_counts`)
LOCAL_GRID_NODES = 4_000_000


def _local_stage(ctx: _Context) -> None:
    r"""η on the sub-box of a smaller ball, when η on the whole sampling box leaves no room.

    Runs only when the robust margin with the global η needs an inner radius of half the
    domain's inradius or more (:func:`_linear_need`; the run would certify nothing), the
    domain is the ball ``‖x‖ ≤ r`` about the origin, there is no initial set and f can be
    evaluated off the grid. For ``r_k = r·LOCAL_FRACTIONS[k]``, largest first, it bounds
    ``‖f − φ‖`` on ``X_k × U_k`` (``X_k = [−r_k, r_k]^n`` holds the ball; ``U_k`` encloses
    the initial controller on ``X_k`` with slack,
    :func:`nlyap_opt.learned.local_bound.local_box`) on a grid of its own
    (:func:`nlyap_opt.learned.local_bound.local_bound`). The inner radius shrinks with the
    ball (``ε_k = ε·r_k/r``: the configured shape of the ring, so that a quadratic's inner
    ball still fits below its level on the sphere), and the first radius whose margin the
    linear decrease affords at ``ε_k`` (:func:`_linear_need` over
    :data:`INNER_MARGIN_FACTOR` below ``ε_k``) is kept. The run then verifies on the ball of
    that radius with that η and ε, ``X_k`` as the dynamics box and ``U_k`` as the input
    box: every certificate proves ``κ(R) ⊆ U_k`` and its region inside ``X_k`` and states
    that it rests on the local bound (``bounds_local.json``, hashed with the certificate).
    ``local.json`` records every radius tried.
    """
    system, log, eta = ctx.system, ctx.log, ctx.eta
    if _systems.spec.centre_dimension(system):
        return
    need = _linear_need(system, ctx.controller, ctx.dynamics, eta, ctx.eps)
    room = 0.5 * ctx.D.inradius()
    if need is None or need < room:
        return
    head = (f"[local] with η = {eta:.3g} on the whole box the robust margin needs "
            f"ε ≥ {need:.3g}, not below half the domain's inradius {ctx.D.inradius():.3g}")
    why = None
    if not (isinstance(ctx.D, Ball) and ctx.D.plain_ball):
        why = f"the domain {ctx.D.describe()} is not a ball about the origin"
    elif ctx.XI is not None:
        why = "an initial set is given (a smaller domain may not hold it)"
    elif not getattr(system, "can_simulate", True):
        why = "f is known at the sample nodes only (a local grid needs new values)"
    if why is not None:
        log(f"{head}; no local bound: {why}")
        return
    log(f"{head}: bounding ‖f − φ‖ on the sub-boxes of smaller balls")
    out = ctx.out
    deps = ("dynamics", "controller")
    # a bound written before bounds files named the φ they bound cannot back a certificate
    # (a re-check refuses it): computed again
    if not ctx.stages.finished("local", *deps) or _names_no_network(out / "bounds_local.json"):
        _local_search(ctx, ctx.stages.view("local"))
        ctx.stages.mark("local", *deps)
    path = out / "local.json"
    try:
        rec = load_with_timings(path)
        for t in rec["tried"]:
            log(f"[local] ball ‖x‖ ≤ {t['radius']:.4g}, ε = {t['inner']:.4g}: η = "
                f"{t['eta']:.4g} on {t['counts']} nodes; the linear decrease beats the "
                f"margin beyond {t['need'] / INNER_MARGIN_FACTOR:.3g} "
                f"({'fits' if t['fits'] else 'not'} below ε)")
        if rec["radius"] is None:
            log("[local] no smaller ball affords the robust margin: the run goes on with the "
                "global η")
            return
        radius, inner = float(rec["radius"]), float(rec["inner"])
        path = out / "bounds_local.json"
        bounds = load_with_timings(path)
        box = np.asarray(bounds["grid"]["box"], dtype=float).reshape(-1, 2)
        eta = float(bounds["eta"])
    except (KeyError, TypeError, ValueError) as err:
        raise _record_error(path, err) from None
    ctx.bounds, ctx.bounds_file = bounds, "bounds_local.json"
    ctx.eta_stages = ("dynamics", "local")
    ctx.eta = eta
    ctx.dyn_box = box[: system.nx]
    if len(box) > system.nx:
        ctx.input_box = box[system.nx:]
    ctx.D = Ball(radius, system.nx)
    ctx.r = ctx.D.max_norm()
    ctx.eps = inner
    log(f"[local] verifying on {ctx.eps:.4g} ≤ ‖x‖ ≤ {ctx.r:.4g} with η = {ctx.eta:.4g} on "
        f"{np.round(box, 4).tolist()} (bounds_local.json)")


def _names_no_network(path: Path) -> bool:
    """Whether the bounds file ``path`` exists and records no network it bounds."""
    try:
        d = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(d, dict) and "network" not in d


def _local_search(ctx: _Context, view: RunConfig) -> None:
    """The radii of :func:`_local_stage`, largest first, until one fits: writes
    ``local.json`` (every radius tried) and ``bounds_local.json`` (the radius kept)."""
    system, out = ctx.system, ctx.out
    dcfg = as_config(system, view.dynamics.to_json())
    grid_box = np.asarray(ctx.bounds["grid"]["box"], dtype=float)
    r0 = ctx.D.max_norm()
    tried, radius, inner = [], None, None
    t0 = time.perf_counter()
    for frac in LOCAL_FRACTIONS:
        r = r0 * frac
        X = Ball(r, system.nx).bounding_box()
        if np.any(X[:, 0] < grid_box[: system.nx, 0]) or \
                np.any(X[:, 1] > grid_box[: system.nx, 1]):
            continue
        sub = local_box(grid_box, X, ctx.controller if len(grid_box) > system.nx else None)
        res = local_bound(system, ctx.dynamics, grid_box, sub, nodes=LOCAL_GRID_NODES,
                          options=dcfg.bound_options, select=dcfg.bound_model,
                          boxes=dcfg.interval_boxes, check_points=20000, seed=dcfg.seed)
        eps = ctx.eps * frac
        need = _linear_need(system, ctx.controller, ctx.dynamics, res.eta, eps)
        fits = need is not None and need / INNER_MARGIN_FACTOR < eps
        tried.append({"radius": r, "inner": eps, "eta": res.eta, "need": need, "fits": fits,
                      "box": sub.tolist(), "counts": res.grid.counts.tolist(),
                      "alpha": res.alpha.alpha, "selected": res.selected})
        if fits:
            write_bounds(out / "bounds_local.json", res,
                         network_path=str(out / "dynamics.json"))
            radius, inner = r, eps
            break
    if radius is None:
        (out / "bounds_local.json").unlink(missing_ok=True)
    _write_stage_json(out / "local.json", {
        "format": "nlyap-local-bound", "global_eta": ctx.eta, "radius": radius,
        "inner": inner, "tried": tried, "seconds": time.perf_counter() - t0})


def _slow_on_sphere(system, controller, dynamics, eta: float, eps: float,
                    samples: int = 2000) -> np.ndarray | None:
    """A sampled point of the sphere ``‖x‖ = eps`` where the model's closed loop has
    ``‖φ(x, κ(x))‖ < η`` (no V can decrease robustly there), or ``None``."""
    x = ca.SX.sym("x", system.nx)
    rhs = closed_loop(system, controller, dynamics, x=x, strict=False).rhs
    F = ca.Function("g", [x], [ca.norm_2(rhs)])
    pts = sample_sphere(samples, system.nx, eps, np.random.default_rng(0))
    speed = np.array(F(pts.T), dtype=float).ravel()
    k = int(np.argmin(speed))
    return pts[k] if speed[k] < eta else None


#: the radii :func:`_centre_inner` samples, from ε up to half the domain's inradius
CENTRE_RADII = 40


def _centre_inner(system, controller, dynamics, eta: float, eps: float, D) -> float:
    r"""The inner radius learned dynamics afford for a system with a centre
    (:func:`systems.spec.centre_dimension`): :data:`INNER_MARGIN_FACTOR` times the largest
    sampled radius where the robust decrease of the centre quadratic
    (:func:`nlyap_opt.certification.roa.centre_lyapunov_matrix` of the model's ``A``) fails.

    Along a centre (``x' = -x³``) ``V̇_q`` is only :math:`\sim -\|x\|^4` against the robust
    term :math:`\eta\|\nabla V_q\| \sim \eta\|x\|`: ε grows like :math:`\eta^{1/3}`, and the
    linearisation of φ (nearly singular) gives no estimate. On :data:`CENTRE_RADII` spheres
    :math:`\rho_k` (geometric, from ``eps`` to half the inradius; 2000 points each)
    :math:`2x^\top P\varphi(x) + \eta\|2Px\| < 0` is checked; ``need`` is the factor times the
    largest :math:`\rho_k` that fails (0 when none does, ``inf`` when the largest does).
    A choice of radius only: every condition is verified at the radius used.
    """
    P = centre_lyapunov_matrix(np.asarray(system.A, dtype=float))
    if P is None:
        return eps
    x = ca.SX.sym("x", system.nx)
    rhs = closed_loop(system, controller, dynamics, x=x, strict=False).rhs
    F = ca.Function("g", [x], [2 * ca.dot(x, ca.mtimes(ca.DM(P), rhs))])
    d = sample_sphere(2000, system.nx, 1.0, np.random.default_rng(0))
    radii = np.geomspace(eps, max(eps, 0.5 * D.inradius()), CENTRE_RADII)
    good = []
    for rho in radii:
        pts = rho * d
        v = np.array(F(pts.T), dtype=float).ravel()
        good.append(bool(np.all(v + 2 * eta * np.linalg.norm(pts @ P, axis=1) < 0)))
    k = len(good)
    while k and good[k - 1]:
        k -= 1
    if k == len(good):
        return np.inf
    return 0.0 if k == 0 else INNER_MARGIN_FACTOR * float(radii[k - 1])


def _eval_grid(system, cfg: RunConfig) -> tuple[np.ndarray, int]:
    """Box and nodes per axis of the evaluation grid (``cfg`` declares :data:`_EVAL`)."""
    return np.asarray(cfg.eval_box, dtype=float), axis_count(int(cfg.eval_points), system.nx)


def _cheap_stage_problem(ctx: _Context, view: RunConfig) -> RoaProblem:
    """The run's problem for the cheap certificates under the initial controller (its V a
    placeholder that each candidate replaces); its ``verify_options`` (the run's
    ``cegis.verify_options``) are those they are proved with, saved with each record."""
    return ctx.problem(view, quadratic_lyapunov(np.eye(ctx.system.nx)), ctx.controller)


def _quadratic_stage(ctx: _Context) -> _CheapRecord | None:
    """Stage 3: the quadratic candidates of ``quadratic``; returns the best certified
    one's record (``quadratic.json``'s ``best``) or ``None``."""
    view = ctx.stages.view("quadratic")
    names = list(view.quadratic or [])
    if not names:
        return None
    deps = (*ctx.eta_stages, "controller")
    out, log = ctx.out, ctx.log
    if ctx.stages.finished("quadratic", *deps):
        return _CheapRecord.load("quadratic", out / "quadratic.json")
    else:
        t = time.perf_counter()
        log(f"[quadratic] certifying V = xᵀPx under the initial controller: "
            f"{', '.join(names)}")
        box, n = _eval_grid(ctx.system, view)
        problem = _cheap_stage_problem(ctx, view)
        opts = dict(problem.verify_options)
        found = certify_quadratics(problem, names, box=box, n=n, log=log)
        ok = [c for c in found if c.certified]
        win = max(ok, key=lambda c: c.volume) if ok else None
        (out / "V_quadratic.json").unlink(missing_ok=True)
        if win is not None:
            quadratic_lyapunov(win.P).save(out / "V_quadratic.json")
        best = None if win is None else dict(win.to_json(), verify_options=opts)
        _write_stage_json(out / "quadratic.json", {
            "candidates": [c.to_json() for c in found], "best": best,
            "seconds": time.perf_counter() - t})
        ctx.stages.mark("quadratic", *deps)
        log(f"[quadratic] {'best: ' + win.name if win else 'none certified'} "
            f"({time.perf_counter() - t:.1f} s)")
    return _CheapRecord.of_stage("quadratic", best, out / "quadratic.json")


def _sos_stage(ctx: _Context) -> _CheapRecord | None:
    """Stage 3b: the SOS candidate of ``sos`` (:func:`nlyap_opt.candidates.sos.certify_sos`) at
    the degree :func:`~nlyap_opt.candidates.sos.choose_degree` gives (``"auto"``: said in one
    line); returns its record (``sos.json``'s ``best``) when certified, else ``None``."""
    view = ctx.stages.view("sos")
    sc = SOSConfig(**view.sos.to_json())
    model = None
    if not ctx.stages.known and not ctx.system.nu and ctx.dynamics is not None \
            and sc.degree != 0 and (sc.degree != AUTO or sos_may_fit(ctx.system.nx)):
        # the polynomial search model of φ (its degree sizes the SDPs); none where φ is not
        # finite on the fit's points (the choice then says the stage needs a model)
        try:
            model = learned_model(ctx.system, ctx.dynamics, ctx.D.bounding_box())
        except ValueError:
            model = None
    choice = choose_degree(ctx.system, sc.degree, known=ctx.stages.known,
                           controller=ctx.controller, model=model)
    if choice.automatic:
        ctx.log(f"[sos] {choice.describe()}")
    if not choice.degree:
        return None
    sc = replace(sc, degree=choice.degree)
    deps = (*ctx.eta_stages, "controller")
    path = ctx.out / "sos.json"
    if ctx.stages.finished("sos", *deps):
        saved = _saved_sos_degree(path)
        if saved == choice.degree:
            return _CheapRecord.load("sos", path)
        ctx.log(f"[sos] {path.name} holds degree {saved!r}, the run's degree is "
                f"{choice.degree}: the SOS stage is recomputed")
    return _sos_compute(ctx, view, sc, deps, model)


def _saved_sos_degree(path: Path):
    """The degree a finished SOS stage recorded in ``path`` (``None`` when unreadable)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data.get("degree") if isinstance(data, dict) else None


def _sos_compute(ctx: _Context, view: RunConfig, sc, deps: tuple,
                 model=None) -> _CheapRecord | None:
    out, log = ctx.out, ctx.log
    t = time.perf_counter()
    log(f"[sos] SOS V of degree {sc.degree} under the initial controller "
        f"({sc.iterations} V-s rounds per degree at most)")
    problem = _cheap_stage_problem(ctx, view)
    res = certify_sos(problem, sc, model=model, log=log)
    box, n = _eval_grid(ctx.system, view)
    vol = res.area(box, n) if res.certified else 0.0
    (out / "V_sos.json").unlink(missing_ok=True)
    best = None
    if res.certified:
        write_json_atomic(out / "V_sos.json", res.V.as_json())
        best = _CheapRecord("sos", f"SOS degree {res.degree}", "V_sos.json",
                            res.certified_level, res.inner, vol,
                            dict(problem.verify_options))
    _write_stage_json(out / "sos.json", {
        "degree": sc.degree, "V_degree": res.degree, "status": res.text,
        "sdp_level": res.sdp_level,
        "level": res.certified_level, "inner": res.inner, "volume": vol,
        "history": res.history, "notes": res.notes,
        "non_polynomial": dict(res.non_polynomial),
        "best": None if best is None else best.to_json(),
        "seconds": time.perf_counter() - t})
    ctx.stages.mark("sos", *deps)
    for note in res.notes:
        if note not in res.text:
            log(f"[sos] note: {note}")
    log(f"[sos] {res.text}" + (f", volume {vol:.4g}" if res.certified else "")
        + f" ({time.perf_counter() - t:.1f} s)")
    return best


def _cheap_V(out: Path, rec: _CheapRecord):
    """The V of a saved cheap certificate (the file's hash was checked by its stage; its
    content is parsed, not trusted)."""
    if rec.kind == "quadratic":
        V = Network.load(out / rec.file)
    else:
        try:
            V = Polynomial.from_json(json.loads((out / rec.file).read_text()))
        except ValueError as err:
            raise ConfigError(f"{out / rec.file} cannot be read ({err}); delete it and "
                              "rerun (the SOS stage is recomputed)") from None
    return V


def _cheap_problem(system, out: Path, problem: RoaProblem, rec: _CheapRecord) -> RoaProblem:
    """The problem of a saved cheap certificate: its V file, the initial controller, its ε
    and verifier options."""
    V = _cheap_V(out, rec)
    ctrl0 = Network.load(out / "controller_init.json") if system.nu else None
    return replace(problem, V=V, controller=ctrl0, inner=float(rec.inner), smoothing=None,
                   verify_options=dict(rec.verify_options))


def _verify_cheap(system, cfg, out: Path, problem, cheap: list, log) -> list[tuple]:
    """Re-verify each saved cheap certificate (quadratic, SOS) at its saved level and ε:
    ``(record, certificate, problem, certified volume on the evaluation grid)`` each."""
    box, n = _eval_grid(system, cfg)
    checked = []
    for rec in cheap:
        pc = _cheap_problem(system, out, problem, rec)
        log(f"[certificate] verifying the saved {rec.label} ({rec.file}) at its saved "
            f"level {float(rec.level):.6g}, ε = {float(rec.inner):g}")
        c = certify_roa(pc, float(rec.level), log=lambda m: log("  " + m))
        checked.append((rec, c, pc, c.area(box, n) if c.certified else 0.0))
    return checked


def _best_certificate(system, cfg, cert, problem, checked: list, log):
    """The best certificate wins: the largest certified volume on the evaluation grid among
    the neural ``cert`` and the re-verified cheap ones (``checked``, of
    :func:`_verify_cheap`); the neural V on a tie, then the earlier candidate.

    Returns ``(cert, problem, files, compared)``: the winner, its problem, the artifact file
    names of :func:`save_certificate` and the table of every candidate (``[]`` without a
    cheap certificate).
    """
    if not checked:
        return cert, problem, None, []
    box, n = _eval_grid(system, cfg)
    vol_n = cert.area(box, n) if cert.certified else 0.0
    compared = [
        {"V": "neural (V.json)", "controller": "controller.json" if system.nu else None,
         "status": cert.status.value, "reason": cert.reason, "level": cert.level,
         "inner": cert.inner, "certified_volume": vol_n, "winner": False}]
    # (volume, certificate, problem, cheap record or None for the neural V, table row)
    best = (vol_n if cert.certified else -1.0, cert, problem, None, compared[0])
    for rec, c, pc, vol in checked:
        row = {"V": f"{rec.label} ({rec.file})",
               "controller": "controller_init.json" if system.nu else None,
               "status": c.status.value, "reason": c.reason, "level": c.level,
               "inner": c.inner, "certified_volume": vol, "winner": False}
        compared.append(row)
        if c.certified and vol > best[0]:
            best = (vol, c, pc, rec, row)
    _, win, wp, rec, row = best
    row["winner"] = True
    log(f"[certificate] best certificate: {'neural' if rec is None else rec.label} ("
        + "; ".join(f"{r['V']} " + ("not checked (cannot beat)" if unchecked(
            r["status"], r["reason"]) else f"{r['status']} {r['certified_volume']:.4g}")
            for r in compared)
        + ")")
    if rec is None:
        return cert, problem, None, compared
    if rec.kind == "quadratic":
        what = f"the quadratic xᵀPx ({rec.name} candidate, {rec.file})"
        files = {"V": rec.file, "controller": "controller_init.json"}
    else:
        what = f"the {rec.label} polynomial ({rec.file}; saved as V.sx.json)"
        files = {"controller": "controller_init.json"}
    win.assumptions.append(
        f"the certified V is {what} under the initial controller"
        + (" (controller_init.json)" if system.nu else "")
        + ": it covers a larger volume than the neural V")
    return win, wp, files, compared


def _refute_by_true_f(cert: RoaCertificate, check: Mapping | None, eta, log) -> None:
    """A certificate for learned dynamics that the true f contradicts is not certified.

    The certificate proves ``∇V·φ + η‖∇V‖ < 0`` on its set, which implies ``∇V·f < 0``
    wherever ``‖f − φ‖ ≤ η``; a confirmed point of that set where ``∇V·f ≥ 0`` therefore
    shows that the bound η does not hold for this f (a spec edited after the dynamics were
    learned, an edited bounds.json): the claim is withdrawn, saying so."""
    if not cert.certified or not check or check.get("decrease_true_f") != "counterexample":
        return   # (a verifier status is a str: its word compares equal)
    at = check.get("counterexample")
    cert.status = CertStatus.NOT_CERTIFIED
    cert.reason = (f"the true f contradicts the bound η = {float(eta):.6g} the certificate "
                   f"rests on: V and κ fail the decrease with f at x = {at} inside the set "
                   "it covers, so ‖f − φ‖ ≤ η does not hold there (dynamics learned for "
                   "another f, or an edited bounds.json); delete the run's dynamics.json and "
                   "bounds.json and rerun")
    log(f"[certificate] NOT CERTIFIED: {cert.reason}")


@dataclass(frozen=True)
class _Areas:
    """Certified and true-ROA areas on the evaluation grid, and the check of the same V
    and κ against the true f (``certificate.json``'s entries of the same names)."""

    certified_area: float
    true_roa_area: float | None
    true_roa_undecided: float | None
    true_roa_elsewhere: float | None
    true_roa_stays_in_domain: float | None
    true_roa_time: float
    fraction_of_true_roa: float | None
    certified_points_converge_in_simulation: bool | None
    not_available: list[str]
    true_dynamics_check: Mapping | None
    eval_box: list
    eval_grid: int
    eval_points: int

    def to_json(self) -> dict:
        """The entries, in the order ``certificate.json`` writes them."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


def _areas_and_checks(system, cfg, cert: RoaCertificate, problem: RoaProblem, out: Path,
                      log) -> _Areas:
    """Certified and true-ROA areas on the evaluation grid; the same V and κ against the
    true f (a benchmark, not part of a learned-f certificate)."""
    box, n = _eval_grid(system, cfg)   # n: nodes per axis
    pts, shape = grid_points(box, n)
    omega = cert.contains(pts).reshape(shape)
    controller = problem.controller
    cache = out / "true_roa.npz"
    feedback = None if controller is None else (lambda z: controller.numpy(z))
    horizon = float(cfg.eval_time)
    if getattr(system, "can_simulate", True):   # longer for a loop with a slow mode
        horizon = true_roa_horizon(system, feedback, box, horizon)
    ckey = _hash([system.name, system_fingerprint(system), cfg.eval_box, n,
                  None if controller is None
                  else controller.to_dict(), "undecided", "elsewhere",
                  problem.domain.to_dict()]
                 + ([] if horizon == TRUE_ROA_TIME else [horizon]))
    not_available = []
    true_mask = undecided = elsewhere = stays = None
    if not getattr(system, "can_simulate", True):
        not_available.append("true ROA by simulation (no model and no simulator of f)")
        true_mask = np.zeros(shape, dtype=bool)
    elif os.path.lexists(cache):
        try:   # read as every input is: a pipe refused, sizes checked, no pickle
            z = read_npz(cache, "true-ROA cache", "it is simulated again")
            saved = [z[k] for k in ("mask", "undecided", "elsewhere", "stays")] \
                if str(z["key"]) == ckey else []
            if saved and all(a.shape == shape and a.dtype == bool for a in saved) and \
                    str(z["seal"]) == _seal(ckey, saved):
                true_mask, undecided, elsewhere, stays = saved
            elif saved:
                log("[certificate] true_roa.npz was edited: simulating again")
        except (OSError, ValueError, KeyError, ConfigError):
            log("warning: true_roa.npz is unreadable; simulating again")
    if true_mask is None:
        log("[certificate] true ROA by simulation on the evaluation grid"
            + ("" if getattr(system, "has_model", True) else " (simulating the black box)"))
        ie = cert.inner_ellipse
        ell = (ie.P, ie.level) if ie is not None and ie.certified else None
        true_mask, undecided, elsewhere = true_roa_mask(system, feedback, box, n,
                                                        t_final=horizon, ellipse=ell,
                                                        undecided=True)
        # of the true ROA within D, the states that reach the origin without leaving D
        reach = true_mask.ravel() & problem.domain.contains(pts)
        stays = np.zeros(reach.shape, bool)
        stays[reach] = true_roa_stays(system, feedback, pts[reach], problem.domain,
                                      t_final=horizon, ellipse=ell)
        stays = stays.reshape(shape)
        buf = io.BytesIO()
        np.savez_compressed(buf, mask=true_mask, undecided=undecided, elsewhere=elsewhere,
                            stays=stays, key=ckey,
                            seal=_seal(ckey, [true_mask, undecided, elsewhere, stays]))
        write_atomic(cache, buf.getvalue())
    # the true ROA within D, where every certificate lies (areas and shares on one set; a
    # true ROA that reaches past D, e.g. over the corners of a box around a ball D, is
    # not counted)
    in_d = problem.domain.contains(pts).reshape(shape)
    true_mask = true_mask & in_d
    cert_area = grid_area(omega, box)
    true_area = grid_area(true_mask, box)
    open_share, rest_share = (
        0.0 if m is None else
        float(np.count_nonzero(m & in_d)) / max(int(np.count_nonzero(in_d)), 1)
        for m in (undecided, elsewhere))
    open_count = 0 if undecided is None else int(np.count_nonzero(undecided & in_d))
    reached = int(np.count_nonzero(true_mask))
    if undecided is not None and (not reached or reached < TOO_FEW_CONVERGED * open_count):
        # no state, or far fewer states than remain undecided, reached the origin: an area
        # of 0 (or of a sliver of the ROA) would be a wrong figure. (States that go to
        # a periodic orbit also stay undecided, so a ratio closer to 1 would refuse
        # estimates that are right; those at rest at another stable equilibrium are decided.)
        not_available.append(
            f"true ROA by simulation (only {reached} states of the "
            f"evaluation grid in D reached the origin within {horizon:.4g} s of "
            f"simulated time, and {100 * open_share:.1f}% neither converged nor diverged: "
            "the closed loop converges too slowly for this estimate; raise eval_time)")
    elif open_share > 0:
        log(f"[certificate] {100 * open_share:.1f}% of the evaluation grid neither converged "
            f"nor diverged nor came to rest at another equilibrium within {horizon:.4g} s of "
            "simulated time: counted outside the true ROA (the share may be an overestimate; "
            "raise eval_time if they converge slowly)")
    true_check = None
    if not getattr(system, "has_model", True):
        not_available.append("check of the same V and κ against the true f (no model of f)")
    elif cert.certified and not problem.known:
        prob = closed_loop_problem(system, problem.V, controller, None, inner=problem.inner,
                                   domain=problem.domain, level=cert.level, margin=0.0,
                                   strict=False, check_positive=False)
        res = parallel_check(prob)
        true_check = {"decrease_true_f": res.status,
                      "inner_ball_true_f": cert.inner_ellipse.status, "seconds": res.seconds}
        if res.counterexample is not None:
            true_check["counterexample"] = np.asarray(res.counterexample.point).tolist()
        log(f"[certificate] same V, κ against the true f: decrease {res.status}, "
            f"inner ball {cert.inner_ellipse.status}")
    simulated = not any(a.startswith("true ROA") for a in not_available)
    return _Areas(
        certified_area=cert_area,
        true_roa_area=true_area if simulated else None,
        true_roa_undecided=open_share if simulated else None,
        true_roa_elsewhere=rest_share if simulated else None,
        true_roa_stays_in_domain=(float(np.count_nonzero(stays & true_mask)) / reached
                                  if reached else None) if simulated else None,
        true_roa_time=horizon,
        fraction_of_true_roa=(cert_area / true_area if true_area else 0.0) if simulated
        else None,
        certified_points_converge_in_simulation=bool(np.all(true_mask[omega])
                                                     if omega.any() else True)
        if simulated else None,
        not_available=not_available,
        true_dynamics_check=true_check,
        eval_box=box.tolist(),
        eval_grid=n,
        eval_points=int(cfg.eval_points))
