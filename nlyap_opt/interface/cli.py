"""The ``nlyap`` command line.

Exit codes (every command; see :data:`EXIT_CODES`): 0 success / verified / certified;
1 counterexample (``verify`` only); 2 unknown / not certified; 3 input or usage error (one
line ``nlyap: error: <problem>; <fix>``, no traceback); 4 internal error (one line; the
traceback only with ``nlyap --debug ...``); 5 stopped by ``--time-limit`` (the finished
stages are kept; the same command resumes); 130 interrupted.

No result depends on the wall clock: every budget is a count of steps. ``--time-limit`` is
only a guard that stops a run, with its own exit code, never a shorter training.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import difflib
import errno
import json
import os
import signal
import sys
import threading
import traceback
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import systems
from verification import QueryStatus, closed_loop_problem, verify

from ..candidates.sos import AUTO, choose_degree, sos_may_fit
from ..certification.certificate import (
    CertStatus,
    read_certificate_file,
    recheck_certificate,
    spec_factory,
)
from ..certification.compositional import (
    certify_compositional,
    is_compositional_file,
    recheck_compositional,
    save_compositional,
)
from ..design.control import lqr
from ..distributed.parallel import (
    DEFAULT_CONNECT_TIMEOUT,
    MAX_LOCAL_WORKERS,
    Proofs,
    dask_client,
    proving,
    verify_distributed,
    verifying_on,
)
from ..kernel.errors import ConfigError, NlyapError, UsageError, interruption
from ..kernel.jsonio import read_file_bytes, write_atomic
from ..kernel.network import Network
from ..kernel.provenance import (
    PORTABLE_FLAG,
    differences,
    fingerprint_id,
    portable_env,
    portable_problems,
)
from ..workflow.configs import (
    PRESETS,
    RunConfig,
    check_dynamics_box,
    check_lqr_weights,
    config_reference,
    make_config,
)
from .cli_args import (
    RADIUS_MAX,
    connect_timeout_arg,
    inner_radius,
    nonneg,
    outer_radius,
    plain_float,
    positive,
    recheck_system_args,
    seeds,
    time_limit_arg,
    workers,
)
from .cli_deploy import register_cli as register_deploy
from .cli_dynamics import register_cli as register_learn_dynamics

__all__ = ["EXIT_CODES", "build_parser", "main"]

#: the exit-code contract of every ``nlyap`` command
EXIT_CODES: dict[int, str] = {
    0: "success (verify: verified; run, compare: certified)",
    1: "counterexample: a confirmed point violates a condition (verify; simulate: a "
       "trajectory from the certified set left it)",
    2: "unknown / not certified (learn-dynamics: η above the config's eta_target)",
    3: "input or usage error (one line: the problem and its fix)",
    4: "internal error (one line; rerun with --debug for the traceback)",
    5: "stopped at --time-limit (finished stages kept; rerun the same command to resume)",
    130: "interrupted (Ctrl-C); rerun the same command to resume",
}


def _epilog(codes) -> str:
    return "exit codes:\n" + "\n".join(f"  {c:<4d} {EXIT_CODES[c]}" for c in codes)


_EPILOGS = {
    "verify": _epilog([0, 1, 2, 3, 4, 130]),
    "run": _epilog([0, 2, 3, 4, 5, 130]),
    "compare": _epilog([0, 2, 3, 4, 5, 130]),
    "learn-dynamics": _epilog([0, 2, 3, 4, 5, 130]),
    "simulate": _epilog([0, 1, 2, 3, 4, 130]),
}
_DEFAULT_EPILOG = _epilog([0, 3, 4, 130])


class _Parser(argparse.ArgumentParser):
    """An argument parser whose usage errors raise :class:`UsageError` (exit 3, one line)."""

    def error(self, message: str):
        raise UsageError(f"{message}; see '{self.prog} --help'")


# ============================================================================ argument types
def _dask_args(sp) -> None:
    sp.add_argument("--workers", type=workers,
                    help="Dask worker processes of a local cluster started and stopped by "
                         "nlyap (default: one per CPU core); with --scheduler: workers to "
                         "wait for. run: with --seeds the portfolio's candidates, without "
                         "it the certificate stage's checks run on the cluster")
    sp.add_argument("--scheduler", metavar="ADDRESS",
                    help="tcp://HOST:PORT of an existing Dask cluster (`dask scheduler`); "
                         "it is used, never closed")
    sp.add_argument("--connect-timeout", type=connect_timeout_arg, metavar="SECONDS",
                    dest="connect_timeout",
                    help="with --scheduler: seconds to reach the scheduler and have it "
                         "answer (default 10); a closed port fails at once")


def _check_dask_args(args) -> None:
    """``--workers`` bounded for a local cluster; ``--connect-timeout`` only with a scheduler."""

    workers, scheduler = getattr(args, "workers", None), getattr(args, "scheduler", None)
    if workers is not None and scheduler is None and workers > MAX_LOCAL_WORKERS:
        raise UsageError(f"--workers {workers}: at most {MAX_LOCAL_WORKERS} local worker "
                         "processes are started; pass fewer, or start a Dask cluster and "
                         "give --scheduler ADDRESS")
    if getattr(args, "connect_timeout", None) is not None and scheduler is None:
        raise UsageError("--connect-timeout applies to --scheduler; drop it or give "
                         "--scheduler ADDRESS")


def _connect_timeout(args) -> float:
    """``connect_timeout`` of :func:`nlyap_opt.distributed.parallel.dask_client` from the
    arguments."""
    t = getattr(args, "connect_timeout", None)
    return DEFAULT_CONNECT_TIMEOUT if t is None else t


class TimeLimitReached(KeyboardInterrupt):
    """Raised in the main thread when ``--time-limit`` runs out.

    A subclass of :class:`KeyboardInterrupt`, so that it unwinds exactly like Ctrl-C: no
    stage is saved half-done, and the stages finished before it stay on disk for resume.
    """


#: seconds after which a stop (Ctrl-C, --time-limit) that came during an import, or inside
#: CasADi's wrapper, is tried again
IMPORT_RETRY = 0.05


def _in_import(frame) -> bool:
    """Whether ``frame`` (a signal handler's) runs inside an import, or inside CasADi's SWIG
    wrapper module (``casadi.casadi``): its overload dispatch calls Python code to test
    conversions and clears any exception that comes out (a stop raised there is lost
    without a trace), and its C functions turn one into ``SystemError``."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib") or \
                frame.f_globals.get("__name__") == "casadi.casadi":
            return True
        frame = frame.f_back
    return False


def _outside_imports(stop):
    """A signal handler that calls ``stop()`` (which raises) — never inside an import or
    CasADi's wrapper (:func:`_in_import`).

    A module's import may run inside a C++ extension's call (torch's do): an exception
    thrown through it aborts the process (``terminate called ...``), or leaves a module half
    initialised that a later import then fails on. During an import the handler asks again
    :data:`IMPORT_RETRY` seconds later (the same signal, sent to the main thread, where it
    also ends a blocking wait).
    """
    def handler(signum, frame):
        if _in_import(frame) and hasattr(signal, "pthread_kill"):
            retry = threading.Timer(IMPORT_RETRY, signal.pthread_kill,
                                    (threading.main_thread().ident, signum))
            retry.daemon = True
            retry.start()
            return
        stop()

    return handler


def _interrupt():
    raise KeyboardInterrupt


@contextlib.contextmanager
def _time_guard(seconds: float | None):
    """Raise :class:`TimeLimitReached` after ``seconds`` of wall time (``None``: no guard),
    or as soon after as no import is running."""
    if seconds is None:
        yield
        return

    if not hasattr(signal, "setitimer"):
        raise UsageError("--time-limit needs POSIX interval timers, which this platform "
                         "lacks; drop --time-limit (or stop the run with Ctrl-C)")

    def _stop():
        raise TimeLimitReached(seconds)

    old = signal.signal(signal.SIGALRM, _outside_imports(_stop))
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def _matrix_arg(text: str | None, option: str):
    """Parse ``"1,0;0,1"`` (rows separated by ';') or a scalar into an array."""
    if text is None:
        return None
    try:
        rows = [[plain_float(v) for v in r.split(",")] for r in text.split(";")]
    except ValueError:
        raise UsageError(f"{option} {text!r} is not a finite number or rows of finite "
                         "numbers like '1,0;0,1' (plain decimals); fix the value") from None
    if len({len(r) for r in rows}) != 1:
        raise UsageError(f"{option} {text!r} has rows of different lengths; give a square "
                         "matrix like '1,0;0,1'")
    M = np.array(rows, dtype=float)
    if not np.all(np.isfinite(M)):
        raise UsageError(f"{option} {text!r} must be finite (no nan or inf)")
    return M


# ============================================================================ helpers
@contextlib.contextmanager
def _reading(what: str, fix: str = "check the input"):
    """Errors while reading user input are usage errors (exit 3), not internal ones."""
    try:
        yield
    except NlyapError:
        raise
    except (ValueError, TypeError, KeyError, IndexError) as err:
        msg = str(err.args[0]) if isinstance(err, KeyError) and err.args else str(err)
        raise UsageError(f"{what}: {' '.join(msg.split())}; {fix}") from None


def _catalogue_system(name: str) -> None:
    if name not in systems.names():
        close = difflib.get_close_matches(name, systems.names(), n=1)
        hint = f"did you mean {close[0]!r}? " if close else ""
        raise UsageError(f"unknown system {name!r}; {hint}the catalogue: "
                         f"{', '.join(systems.names())} (see 'nlyap systems')")


def _existing_ancestor(path: Path) -> Path:
    p = path.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def _check_writable(path: Path, option: str, directory: bool) -> None:
    if directory and path.exists() and not path.is_dir():
        raise UsageError(f"{option} {path} is a file; give a directory (created if missing)")
    if not directory and path.is_dir():
        raise UsageError(f"{option} {path} is a directory; give a file name")
    anc = _existing_ancestor(path if directory else path.parent)
    if not anc.is_dir():
        raise UsageError(f"{option} {path}: {anc} is a file, not a directory; choose another "
                         "path")
    if not os.access(anc, os.W_OK):
        raise UsageError(f"{option} {path}: no permission to write in {anc}; choose another "
                         "path")


#: the commands whose --out is required (no default directory)
_OUT_REQUIRED = ("simulate", "export", "learn-dynamics")

#: the commands that re-check saved files (someone else's, maybe): a system spec's factory,
#: Python code, runs there only with --allow-factory
_RECHECKS = ("verify", "simulate", "export")


def _is_spec(name: str) -> bool:
    """Whether ``name`` means a file: a ``.toml`` or a path, a file, or something else on
    disk that is no catalogue name (a directory or a pipe: refused as a spec, by name)."""
    return name.endswith(".toml") or os.sep in name or Path(name).is_file() or \
        (name not in systems.names() and os.path.lexists(name))


def _spec_system(path: str, allow_factory: bool = True) -> str:
    """Load a system spec file (TOML), register it for this process, return its name."""

    p = Path(path)
    if p.is_dir():
        raise UsageError(f"system file {p} is a directory; pass a system spec file (.toml) "
                         "or a catalogue name (a run's directory is re-checked with "
                         "'nlyap verify --certificate DIR')")
    if os.path.exists(p) and not p.is_file():
        raise UsageError(f"system file {p} is not a regular file (a pipe, device or socket); "
                         "pass a system spec file (.toml)")
    if not p.is_file():
        raise UsageError(f"system file {p}: no such file; check the path (or pass a "
                         "catalogue name, see 'nlyap systems')")
    return _register_spec(systems.load_spec(p, allow_factory=allow_factory), p)


def _register_spec(s, p) -> str:
    """Register the system ``s`` of spec file ``p`` for this process; its name."""
    if s.name in systems.CATALOGUE:   # another spec file of this process may be replaced
        raise UsageError(f"system file {p} names its system {s.name!r}, which is a catalogue "
                         "system; choose another name in the file")
    systems.REGISTRY[s.name] = lambda _s=s: _s
    return s.name


def _check_paths(args) -> None:
    """Refuse missing inputs and unusable outputs before any work starts."""
    _check_dask_args(args)
    for attr in ("config", "lyapunov", "controller", "dynamics", "certificate", "out", "json",
                 "proof", "save_proof"):
        value = getattr(args, attr, None)
        if isinstance(value, str) and not value.strip():
            optional = not (attr == "out" and args.command in _OUT_REQUIRED)
            raise UsageError(f"--{attr.replace('_', '-')} is given an empty path; give a path"
                             + (", or leave the option out" if optional else ""))
    if getattr(args, "system", None) is not None:
        rechecks = args.command in _RECHECKS   # runs a factory only with --allow-factory
        if _is_spec(args.system) and rechecks and \
                not args.allow_factory and Path(args.system).is_file():
            factory = spec_factory(args.system)
            if factory is not None:
                raise UsageError(f"--system {args.system} defines its system with factory = "
                                 f"{factory!r}, Python code that {args.command} runs only when "
                                 "asked: read it, then add --allow-factory")
        if _is_spec(args.system):   # --system FILE.toml / run FILE.toml
            args.system_file = str(Path(args.system).resolve())  # Dask workers load it
            args.system = _spec_system(
                args.system, allow_factory=not rechecks or args.allow_factory)
        _catalogue_system(args.system)
    for attr in ("config", "lyapunov", "controller", "dynamics", "certificate"):
        value = getattr(args, attr, None)
        if value is None:
            continue
        p, option = Path(value), f"--{attr}"
        if attr == "certificate" and p.is_dir():
            p = p / "certificate.json"
        if not p.exists():
            raise UsageError(f"{option} {p}: no such file; check the path")
        if p.is_dir():
            raise UsageError(f"{option} {p} is a directory; pass the JSON file")
        if not os.access(p, os.R_OK):
            raise UsageError(f"{option} {p}: no permission to read it")
    if getattr(args, "out", None) is not None:
        _check_writable(Path(args.out), "--out", directory=True)
    if getattr(args, "json", None) is not None:
        _check_writable(Path(args.json), "--json", directory=False)


def _write_json(path: str | None, data: dict) -> None:
    if path:
        text = json.dumps(data, indent=1, allow_nan=False)
        try:
            Path(path).parent.mkdir(parents=True, exist_ok=True)
            write_atomic(path, text)
        except ConfigError as err:  # a directory, pipe or device there
            raise ConfigError(f"--json {err}") from None
        except OSError as err:  # e.g. a full disk, or a directory of /proc
            raise ConfigError(f"cannot write --json {path}: {err.strerror or err}; give a "
                              "writable file") from None
        print(f"wrote {path}")


#: per option that reads a network: the ``meta.kind`` this tool writes into such a file, and
#: the file's name in a run directory
_NETWORK_KINDS = {"--lyapunov": ("lyapunov", "V.json"),
                  "--controller": ("controller", "controller.json"),
                  "--dynamics": ("dynamics", "dynamics.json")}


def _load_network(path: str, option: str):
    with _reading(f"{option} {path}"):
        net = Network.load(path)
    kind = net.meta.get("kind") if isinstance(net.meta, dict) else None
    want, name = _NETWORK_KINDS.get(option, (None, ""))
    if kind is not None and want is not None and kind != want:
        raise UsageError(f"{option} {path} is a network of kind {kind!r} (its meta says so), "
                         f"not a {want} network; pass the {want} file ({name} of a run)")
    return net


# ============================================================================ commands
def cmd_systems(args) -> int:
    if args.check is not None and not args.check.strip():
        raise UsageError("--check is given an empty name; give a system spec file (.toml) or "
                         "a catalogue name")
    if args.check:
        if _is_spec(args.check):
            s = systems.check_spec(args.check)
            if s is None:  # Python code: --check reads files, it runs nothing
                print(json.dumps({"spec": str(args.check), "factory": spec_factory(args.check),
                                  "note": "the system is built by Python code, which --check "
                                          "does not run; `nlyap run FILE` imports it"},
                                 indent=1))
                return 0
            # its [run] table, as `nlyap config FILE` checks it
            make_config(_register_spec(s, args.check), None)
        else:
            s = systems.get(args.check)
        try:
            text = json.dumps(s.summary(), indent=1, allow_nan=False, default=str)
        except ValueError:
            raise ConfigError(f"{args.check}: a number the file declares is not finite (nan "
                              "or inf, e.g. in its [run] table); write a finite number") from None
        print(text)
        return 0

    print(f"{'name':26s} {'nx':>3s} {'nu':>3s}  state box / input box")
    for name in systems.names():
        s = systems.get(name)
        box = " x ".join(f"[{lo:g}, {hi:g}]" for lo, hi in s.state_box)
        ubox = " x ".join(f"[{lo:g}, {hi:g}]" for lo, hi in s.input_box) or "-"
        print(f"{name:26s} {s.nx:3d} {s.nu:3d}  {box} / {ubox}   {s.description}")
    return 0


def cmd_lqr(args) -> int:
    s = systems.get(args.system)
    Q, R = check_lqr_weights(s, _matrix_arg(args.Q, "--Q"), _matrix_arg(args.R, "--R"),
                             where="lqr", names=("--Q", "--R"))
    with _reading("lqr: the Riccati solver failed with these weights",
                  "use moderate weights (say between 1e-6 and 1e6)"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a failure is reported as such
        res = lqr(s, Q, R)
    np.set_printoptions(precision=6, suppress=True)
    print(f"system {s.name}: A =\n{s.A}\nB =\n{s.B}")
    if s.nu:
        print(f"K (u = u_eq - K x) =\n{res.K}\nRiccati residual = {res.riccati_residual():.2e}")
    print(f"P (A_clᵀP + P A_cl = -I) =\n{res.P}")
    print(f"closed-loop eigenvalues = {res.eigenvalues}")
    _write_json(args.json, res.to_dict())
    return 0


_PROBLEM_OPTIONS = ("system", "lyapunov", "controller", "dynamics", "inner", "outer", "level",
                    "eta", "margin", "smoothing")


def _note_other_fingerprint(path: Path) -> None:
    """Say when a certificate was made in another numeric environment (the re-check's
    verdict does not depend on it; a re-run of its training would)."""

    try:
        stored = read_certificate_file(path)[1].get("provenance")
    except (ConfigError, AttributeError):
        return  # the re-check itself reports an unreadable certificate
    diff = differences(stored)
    if diff == ["unknown"]:
        print("note: the certificate does not record the numeric environment it was made in "
              "(written by an older nlyap); the re-check does not depend on it")
    elif diff:
        print(f"note: re-checking on another numeric environment (fingerprint "
              f"{fingerprint_id()}, the certificate's {fingerprint_id(stored)}: "
              f"{', '.join(diff)} differ); the verdict does not depend on it (interval "
              "arithmetic with outward rounding), a re-run of the training may give other "
              "networks (nlyap run --portable pins the numeric kernels)")


def _verify_certificate(args) -> int:
    given = [f"--{o}" for o in _PROBLEM_OPTIONS if o != "system" and getattr(args, o) is not None]
    if given:
        raise UsageError(f"--certificate re-checks a saved run with its own V, κ, φ, radii and "
                         f"level; drop {', '.join(given)}")
    system = None
    if args.system is not None:      # loaded by _check_paths (a factory only when allowed)
        system = systems.get(args.system)
    verifier = [o for o, given in (("--backend", args.backend != "interval"),
                                   ("--precision", args.precision is not None),
                                   ("--resolution", args.resolution is not None)) if given]
    if verifier:
        raise UsageError("--certificate re-checks with the interval verifier and the options "
                         f"saved in the certificate; drop {', '.join(verifier)}")
    path, _ = read_certificate_file(args.certificate)  # a readable JSON file, or one line
    proofs = _proofs(args)

    if is_compositional_file(path):
        if args.workers is not None or args.scheduler is not None:
            raise UsageError("a compositional certificate is re-checked without Dask; drop "
                             "--workers/--scheduler")
        if proofs is not None:
            raise UsageError("a compositional certificate is re-checked without bisection; "
                             "drop --proof/--save-proof")
        cert = recheck_compositional(path, system=system, allow_factory=args.allow_factory)
        print(cert.summary())
        if args.json:
            _write_json(args.json, cert.to_dict())
        return 0 if cert.certified else 2
    _note_other_fingerprint(path)
    if args.workers is not None or args.scheduler is not None:
        # the conditions' checks run on the cluster (nlyap_opt.distributed.parallel.check): a
        # "verified" comes from it, any other verdict is decided again serially

        with dask_client(args.workers, args.scheduler,
                         connect_timeout=_connect_timeout(args)) as client, \
                verifying_on(client), proving(proofs):
            cert = recheck_certificate(path, system=system)
    else:
        with proving(proofs):
            cert = recheck_certificate(path, system=system)
    print(cert.summary())
    said = _proof_outcome(args, proofs, cert.status is CertStatus.CERTIFIED)
    if args.json:
        out = cert.to_dict() if hasattr(cert, "to_dict") else \
            {"status": cert.status.value, "summary": cert.summary()}
        if said is not None:
            out["proof"] = said.to_json()
        _write_json(args.json, out)
    if cert.status is CertStatus.CERTIFIED:
        return 0
    return 1 if cert.status is CertStatus.COUNTEREXAMPLE else 2


@dataclass(frozen=True)
class ProofOutcome:
    """What a re-check did with its proof: the ``proof`` entry of ``nlyap verify --json``.

    Attributes
    ----------
    file : str
        The ``--proof`` or ``--save-proof`` file.
    recorded : int or None
        Trees written (``--save-proof``, when the certificate re-checked), else ``None``.
    checks : int
        Bisected checks that looked for a tree (distinct problems).
    started_from_proof : int
        Those decided from their tree's leaves.
    """

    file: str
    recorded: int | None
    checks: int
    started_from_proof: int

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def _proof_outcome(args, proofs: Proofs | None, certified: bool) -> ProofOutcome | None:
    """After a re-check: the proof written (``--save-proof``, if it re-checked) and what
    was said about it (``None`` without a proof)."""
    if proofs is None:
        return None
    if args.proof:
        print(f"proof: {proofs.used} of {proofs.asked} bisected checks started from the "
              f"trees of {args.proof}" + ("" if proofs.used == proofs.asked else
                                          " (the others were decided as without a proof)"))
    recorded = None
    if args.save_proof:
        if certified:
            try:
                Path(args.save_proof).parent.mkdir(parents=True, exist_ok=True)
                proofs.save(args.save_proof)
            except OSError as err:
                raise ConfigError(f"cannot write the proof file {args.save_proof}: "
                                  f"{err.strerror or err}; give a writable path") from None
            recorded = len(proofs.trees)
            print(f"proof: the trees of {recorded} bisected checks written to "
                  f"{args.save_proof} (re-check with --proof {args.save_proof})")
        else:
            print("proof: not written (the certificate did not re-check)")
    return ProofOutcome(str(args.proof or args.save_proof), recorded, proofs.asked,
                        proofs.used)


def _proofs(args) -> Proofs | None:
    """The :class:`Proofs` of ``--proof FILE`` (read) or ``--save-proof FILE`` (recording)."""
    if args.proof and args.save_proof:
        raise UsageError("give --proof FILE (start from a proof) or --save-proof FILE (record "
                         "one), not both")
    if args.save_proof:
        if args.workers is not None or args.scheduler is not None:
            raise UsageError("--save-proof records the checks' trees in a serial re-check; "
                             "drop --workers/--scheduler (then re-check on them with --proof)")
        out = Path(args.save_proof)
        if out.suffix != ".npz":
            raise UsageError(f"--save-proof {out}: a proof file is an .npz file; give a "
                             "path ending in .npz")
        _check_writable(out, "--save-proof", directory=False)
        return Proofs(record=True)
    if args.proof:
        return Proofs.load(args.proof)
    return None


def _check_verify_args(args) -> None:
    """The options of ``nlyap verify`` without a certificate file, checked together
    (a :class:`UsageError` naming the fix)."""
    missing = [f"--{o}" for o in ("system", "lyapunov", "inner", "outer")
               if getattr(args, o) is None]
    if missing:
        raise UsageError(f"verify needs {', '.join(missing)} (or --certificate FILE); "
                         "see 'nlyap verify --help'")
    if not args.inner < args.outer:
        raise UsageError(f"need 0 <= --inner < --outer, got {args.inner:g} and {args.outer:g}; "
                         "make --inner smaller")
    if args.backend == "interval" and args.precision is not None:
        raise UsageError("--precision is the dReal backend's delta; use it with "
                         "--backend dreal, or drop it")
    if args.backend == "dreal" and args.resolution is not None:
        raise UsageError("--resolution applies to --backend interval; drop it or use "
                         "--precision with dreal")
    if args.smoothing and not args.eta:
        raise UsageError("--smoothing only applies with --eta > 0; drop it or give --eta")


def cmd_verify(args) -> int:
    if args.certificate:
        return _verify_certificate(args)
    if args.proof or args.save_proof:
        raise UsageError("--proof and --save-proof apply to a re-check: give --certificate "
                         "DIR")
    _check_verify_args(args)
    eta, margin, smoothing = args.eta or 0.0, args.margin or 0.0, args.smoothing or 0.0
    s = systems.get(args.system)
    V = _load_network(args.lyapunov, "--lyapunov")
    ctrl = _load_network(args.controller, "--controller") if args.controller else None
    dyn = _load_network(args.dynamics, "--dynamics") if args.dynamics else None
    if dyn is None and not s.has_model:
        raise UsageError(f"system {args.system!r} is given by "
                         f"{'samples' if s.kind == 'samples' else 'a black-box callable'}, "
                         "not a model the verifier can bound; pass --dynamics DYN.json (a "
                         "learned φ, e.g. a run's dynamics.json) with --eta, its error bound")
    with _reading("verify"):
        problem = closed_loop_problem(s, V, ctrl, dyn, inner=args.inner, outer=args.outer,
                                      level=args.level, margin=margin, eta=eta,
                                      smoothing=smoothing, strict=False)
    # the notes once the problem is built: an input error stays the one line printed
    if margin and dyn is None:
        print("note: --margin without --dynamics tightens the true-f condition", file=sys.stderr)
    if dyn is not None:
        print(f"note: dV/dt is along the learned φ of --dynamics {args.dynamics}" + (
            f", with the robust term of ‖f − φ‖ ≤ η = {eta:g}" if eta else
            ": a statement about φ, not the true f (give --eta, a bound of ‖f − φ‖, for "
            "one about f)"), file=sys.stderr)
    opts = {}
    if args.backend == "interval":
        opts = {"resolution": args.resolution, "progress": args.progress}
    elif args.precision is not None:
        opts = {"precision": args.precision}
    if args.workers is not None or args.scheduler is not None:
        if args.backend != "interval":
            raise UsageError("--workers/--scheduler run the interval backend on Dask; drop "
                             "them or use --backend interval")

        with dask_client(args.workers, args.scheduler,
                         connect_timeout=_connect_timeout(args)) as client:
            res = verify_distributed(problem, client, resolution=args.resolution)
    else:
        res = verify(problem, backend=args.backend, **opts)
    region = f"{args.inner:g} <= |x| <= {args.outer:g}" + (
        f" and V <= {args.level:g}" if args.level is not None else "")
    extra = f" + {eta:g}|∇V|" if eta else ""
    if eta and smoothing:
        extra = f" + {eta:g}sqrt(|∇V|² + {smoothing:g}²)"
    print(f"{res.status}: V > 0 and dV/dt{extra} < -{margin:g} on {region} "
          f"({res.boxes} boxes, depth {res.depth}, {res.seconds:.3f} s, {res.backend})")
    if res.counterexample is not None:
        c = res.counterexample
        if c.property.startswith("domain of"):
            print(f"  counterexample x = {c.point.tolist()}: the dynamics or V is undefined "
                  f"there ({c.property})")
        elif c.property == "V>0":  # the property checked is -V < 0
            print(f"  counterexample x = {c.point.tolist()} violates V > 0: V(x) in "
                  f"[{-c.value_upper:.6g}, {-c.value_lower:.6g}]")
        else:
            print(f"  counterexample x = {c.point.tolist()} violates {c.property}: "
                  f"dV/dt{extra} + {margin:g} in [{c.value_lower:.6g}, {c.value_upper:.6g}] "
                  "(must be < 0)")
    if res.status is QueryStatus.UNKNOWN:
        at = "the default resolution" if args.resolution is None else \
            f"resolution {args.resolution:g}"
        print(f"  {len(res.undecided)} boxes undecided at {at} (or when the box budget ran "
              "out); a larger --inner leaves out the origin, where dV/dt tends to 0, and a "
              "finer --resolution bisects further")
    _write_json(args.json, res.to_dict())
    return {QueryStatus.VERIFIED: 0, QueryStatus.COUNTEREXAMPLE: 1}.get(res.status, 2)


def _run_config(args, learned: bool) -> RunConfig:
    preset = args.preset
    if preset is None:  # a catalogue system's default preset; none for a system file
        preset = "large" if args.system in PRESETS else None
    elif preset == "default":  # the default method of every system without a preset
        preset = None
    cfg = make_config(args.system, preset, file=args.config)
    if learned:
        check_dynamics_box(cfg)
    return cfg


def _run_compositional(args, system) -> int:
    """``nlyap run`` of a system that declares its subsystems: the compositional
    certificate (:mod:`nlyap_opt.certification.compositional`), from the model's Jacobian
    (``--known-dynamics``) or from sampled values of f and a second-derivative bound."""
    given = [o for o, v in (("--config", args.config), ("--preset", args.preset),
                            ("--seeds", args.seeds), ("--workers", args.workers),
                            ("--scheduler", args.scheduler)) if v is not None]
    if given:
        raise UsageError(f"the compositional certificate of {system.name} has no training "
                         f"or Dask stage; drop {', '.join(given)}")
    out = args.out or f"runs/{system.name}{'_known' if args.known_dynamics else ''}"
    _check_writable(Path(out), "--out", directory=True)
    cert = certify_compositional(system, setting="known" if args.known_dynamics else "data")
    path = save_compositional(cert, system, out)
    from ..workflow.report import write_compositional_report  # lazy: matplotlib, heavy

    write_compositional_report(Path(out), system, cert,
                               json.loads(path.read_text())["provenance"])
    print(cert.summary())
    print(f"wrote {path}")
    return 0 if cert.certified else 2


def _refuse_other_systems_run(out: Path, name: str) -> None:
    """Refuse an ``--out`` that holds the run (or portfolio) of another system: it would be
    overwritten stage by stage, and its other files left beside the new run's."""
    for file in ("certificate.json", "portfolio.json", "comparison.json"):
        try:   # read as every input is (a pipe is refused, not waited on)
            other = json.loads(read_file_bytes(out / file, "run file")).get("system")
        except (OSError, ValueError, AttributeError, RecursionError):
            continue   # none, or unreadable: the run's own checks decide what to redo
        if isinstance(other, str) and other != name:
            raise UsageError(f"--out {out} holds a run of system {other!r} ({file}), not "
                             f"{name!r}; give another --out, or remove that directory")
    try:   # a run interrupted before its certificate: its stages name the system
        stages = json.loads(read_file_bytes(out / "stages.json", "run file"))
        others = sorted({r.get("system") for r in stages.values()
                         if isinstance(r, dict) and isinstance(r.get("system"), str)} - {name})
    except (OSError, ValueError, AttributeError, RecursionError):
        return
    if others:
        raise UsageError(f"--out {out} holds the stages of a run of system {others[0]!r} "
                         f"(stages.json), not {name!r}; give another --out, or remove that "
                         "directory")


def cmd_run(args) -> int:
    from ..workflow.pipeline import run  # lazy: torch (the pipeline trains), heavy

    system = systems.get(args.system)
    if getattr(system, "subsystems", None) is not None:
        return _run_compositional(args, system)
    cfg = _run_config(args, learned=not args.known_dynamics)
    out = args.out or f"runs/{args.system}{'_known' if args.known_dynamics else ''}"
    _check_writable(Path(out), "--out", directory=True)
    _refuse_other_systems_run(Path(out), system.name)
    if args.seeds is not None:  # a portfolio of seeded candidates on Dask, the best kept
        from ..workflow.portfolio import run_portfolio  # lazy: torch and Dask, heavy

        pres = run_portfolio(getattr(args, "system_file", None) or args.system, cfg, out,
                             seeds=args.seeds, workers=args.workers,
                             scheduler=args.scheduler, known_dynamics=args.known_dynamics,
                             connect_timeout=args.connect_timeout)
        return 0 if pres.certified else 2
    # without --seeds, --workers/--scheduler run the certificate stage's checks on Dask
    res = run(args.system, cfg, out, known_dynamics=args.known_dynamics,
              workers=args.workers, scheduler=args.scheduler,
              connect_timeout=args.connect_timeout)
    return 0 if CertStatus(res.status.value) is CertStatus.CERTIFIED else 2


def cmd_compare(args) -> int:
    from baselines.compare import compare  # lazy: torch (the pipeline) and cvxpy, heavy

    cfg = _run_config(args, learned=not args.no_neural)
    out = args.out or f"runs/compare_{args.system}"
    _check_writable(Path(out), "--out", directory=True)
    _refuse_other_systems_run(Path(out), systems.get(args.system).name)
    rows = compare(args.system, cfg, out, include_neural=not args.no_neural)
    print((Path(out) / "comparison.md").read_text())
    return 0 if all(r.certified for r in rows if r.method.startswith("neural")) else 2


def cmd_config(args) -> int:
    if args.keys:
        print(config_reference())
        return 0
    if args.system is None:
        raise UsageError("config needs a system name (or --keys); see 'nlyap config --help'")
    cfg = _run_config(args, learned=False)
    print(json.dumps(cfg.to_json(), indent=1, allow_nan=False))
    if cfg.sos.degree == AUTO:   # what the automatic SOS degree resolves to (not JSON: stderr)
        system = systems.get(args.system)
        choice = choose_degree(system, AUTO, known=True)
        learned = "off (an input)" if system.nu else \
            f"off (n = {system.nx}: the SDPs are too large whatever f)" \
            if not sos_may_fit(system.nx) else \
            "chosen once φ is learned, from the degree of a polynomial model of φ"
        print(f"with --known-dynamics, {choice.describe()}; with learned dynamics, {learned}",
              file=sys.stderr)
    return 0


# ============================================================================ parser
def _preset_arg(sp) -> None:
    sp.add_argument("--preset", default=None, choices=["paper", "large", "fast", "default"],
                    help="paper | large | fast | default (default large for catalogue "
                         "systems; a system file's settings, and 'default' for any system, "
                         "come from the default method: its boxes and its [run] table)")


def _add_verify(add) -> None:
    """The ``verify`` subcommand (``add``: the subparser factory of :func:`build_parser`)."""
    sp = add("verify", help="verify V > 0 and the decrease condition on an annulus",
             description="Verify V > 0 and dV/dt < 0 on inner <= |x| <= outer (and V <= level), "
                         "or re-check a saved run with --certificate.")
    sp.add_argument("--certificate",
                    help="re-check DIR/certificate.json of a run (artifacts hashed, the system "
                         "bound, conditions verified again at the saved numbers); replaces the "
                         "options below but --system")
    recheck_system_args(sp, "catalogue name or spec file (TOML); with --certificate the "
                            "system to re-check against (default: the catalogue system the "
                            "certificate names, or the factory-free spec file it names)")
    sp.add_argument("--lyapunov", help="V network JSON")
    sp.add_argument("--controller", help="controller network JSON (feeds the inputs)")
    sp.add_argument("--dynamics", help="learned dynamics network JSON (replaces f)")
    sp.add_argument("--margin", type=nonneg, help="beta >= 0: require dV/dt < -beta")
    sp.add_argument("--eta", type=nonneg,
                    help="pointwise robust margin >= 0: require dV/dt + eta*|grad V| < -beta "
                         "(grad V: its entries of the components --dynamics learns)")
    sp.add_argument("--smoothing", type=nonneg,
                    help="s >= 0: with --eta use sqrt(|grad V|^2 + s^2) (certificate.json's "
                         "norm_smoothing)")
    sp.add_argument("--inner", type=inner_radius,
                    help="inner radius epsilon (0 <= inner < outer)")
    sp.add_argument("--outer", type=outer_radius, help=f"outer radius r (<= {RADIUS_MAX:g})")
    sp.add_argument("--level", type=positive, help="restrict to V(x) <= level (> 0)")
    sp.add_argument("--backend", default="interval", choices=["interval", "dreal"],
                    help="interval: the sound verifier; dreal: the optional second opinion")
    sp.add_argument("--resolution", type=positive,
                    help="smallest box width (interval backend)")
    sp.add_argument("--precision", type=positive, help="delta of the dreal backend")
    sp.add_argument("--progress", action="store_true", help="show a progress bar")
    sp.add_argument("--json", help="write status, seconds, boxes, counterexample here")
    sp.add_argument("--save-proof", dest="save_proof", metavar="FILE",
                    help="with --certificate: record the bisection trees of the checks "
                         "(a serial re-check) in FILE (.npz), for faster re-checks")
    sp.add_argument("--proof", metavar="FILE",
                    help="with --certificate: start each check from its tree in FILE (the "
                         "leaves are rebuilt from the certificate's own boxes and all decided "
                         "again: a proof never makes a false condition verified)")
    _dask_args(sp)
    sp.set_defaults(func=cmd_verify)


def build_parser() -> argparse.ArgumentParser:
    """The ``nlyap`` argument parser (usage errors raise :class:`UsageError`)."""
    fmt = argparse.RawDescriptionHelpFormatter
    p = _Parser(prog="nlyap", formatter_class=fmt,
                description="Neural Lyapunov control of unknown systems with certified "
                            "regions of attraction.",
                epilog=_epilog([0, 1, 2, 3, 4, 130]))
    p.add_argument("--debug", action="store_true",
                   help="print the traceback of an internal error (exit code 4)")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    def add(name, **kw):
        return sub.add_parser(name, formatter_class=fmt,
                              epilog=_EPILOGS.get(name, _DEFAULT_EPILOG), **kw)

    sp = add("systems", help="list the system catalogue (or check a system file)")
    sp.add_argument("--check", metavar="FILE",
                    help="load a system spec file (TOML) and print what it declares")
    sp.set_defaults(func=cmd_systems)

    sp = add("lqr", help="LQR gain and Lyapunov matrix of a catalogue system")
    sp.add_argument("system", help="a catalogue system name or a system spec file (.toml)")
    sp.add_argument("--Q", help="state weight: scalar or rows '1,0;0,1' (default I; symmetric "
                                "positive semidefinite)")
    sp.add_argument("--R", help="input weight: scalar or rows (default I; symmetric positive "
                                "definite)")
    sp.add_argument("--json", help="write K, P, eigenvalues to this file")
    sp.set_defaults(func=cmd_lqr)

    _add_verify(add)

    sp = add("run", help="learn f (unless --known-dynamics), V and κ; certify the ROA")
    sp.add_argument("system", help="a catalogue system name or a system spec file (.toml)")
    sp.add_argument("--config", help="JSON file merged over the preset (see 'nlyap config')")
    _preset_arg(sp)
    sp.add_argument("--known-dynamics", action="store_true",
                    help="use the true f (the paper's 'actual dynamics' setting)")
    sp.add_argument("--out", help="output directory (default runs/NAME[_known])")
    sp.add_argument("--seeds", type=seeds,
                    help="K (seeds 0..K-1) or 0,3,7: train one candidate per seed in "
                         "parallel on Dask (OUT/seed_k), keep the largest certified area "
                         "(OUT/portfolio.md)")
    sp.add_argument("--portable", action="store_true",
                    help="pin numpy's, OpenBLAS's and torch's numeric kernels to their AVX2 "
                         "code paths and one BLAS thread (the command restarts itself with "
                         "the pins set), so that x86-64 machines with different CPUs train "
                         "the same networks bit for bit; slower")
    _dask_args(sp)
    time_limit_arg(sp)
    sp.set_defaults(func=cmd_run)

    sp = add("compare", help="LQR, SOS and neural ROAs, all certified, vs true ROA")
    sp.add_argument("system", help="a catalogue system name or a system spec file (.toml)")
    sp.add_argument("--config", help="JSON file merged over the preset")
    _preset_arg(sp)
    sp.add_argument("--out", help="output directory (default runs/compare_NAME)")
    sp.add_argument("--no-neural", action="store_true", help="baselines only")
    time_limit_arg(sp)
    sp.set_defaults(func=cmd_compare)

    sp = add("config", help="print the validated run configuration (or every key)",
             description="Print the run configuration of SYSTEM (preset, then --config FILE "
                         "merged over it) after validating it; --keys lists every key.")
    sp.add_argument("system", nargs="?",
                    help="a catalogue system name or a system spec file (.toml)")
    sp.add_argument("--config", help="JSON file merged over the preset")
    _preset_arg(sp)
    sp.add_argument("--keys", action="store_true", help="list every key, type and default")
    sp.set_defaults(func=cmd_config)

    for register in [register_learn_dynamics, register_deploy, *_EXTRA]:
        register(sub)
    for name, parser in sub.choices.items():
        if not parser.epilog or name in _EPILOGS:
            parser.epilog = _EPILOGS.get(name, _DEFAULT_EPILOG)
            parser.formatter_class = fmt
    return p


#: functions adding further subcommands (verify, learn-dynamics, run, compare)
_EXTRA: list = []


# ============================================================================ main
def _one_line(err: BaseException) -> str:
    msg = str(err.args[0]) if isinstance(err, KeyError) and err.args else str(err)
    return " ".join(msg.split()) or type(err).__name__


def _classify(err: BaseException, command: str | None) -> tuple[int, str]:
    """Exit code and one-line message of an exception that ended a command."""
    see = f"see 'nlyap {command} --help'" if command else "see 'nlyap --help'"
    if isinstance(err, json.JSONDecodeError):
        return 3, f"malformed JSON ({_one_line(err)}); fix or replace the file"
    if isinstance(err, NlyapError):
        msg = _one_line(err)
        return 3, msg if ";" in msg else f"{msg}; {see}"
    if isinstance(err, MemoryError):
        if command in ("run", "compare", "learn-dynamics", None):
            return 3, ("this machine ran out of memory; lower the sizes of the run in "
                       "--config (eval_points, cegis.area_points, cegis.samples, train.hidden, "
                       "the dynamics grid) or use a machine with more memory")
        return 3, (f"this machine ran out of memory in 'nlyap {command}'; the networks or "
                   "the system are too large for it: give smaller ones, or use a machine "
                   "with more memory")
    if isinstance(err, OSError) and err.filename is not None:
        return 3, (f"{err.filename}: {err.strerror or _one_line(err)}; check the path "
                   "(and its permissions)")
    if isinstance(err, OSError) and err.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        # a write that the file system refused (no file name: it failed after the open)
        return 3, (f"writing an output failed: {err.strerror or _one_line(err)}; free space "
                   "(or raise the quota) on that file system, or write to another one")
    return 4, f"{type(err).__name__}: {_one_line(err)}; rerun with --debug for the traceback"


def _one_line_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """A warning as one line on standard error (``nlyap: warning: ...``), without the
    source line Python prints beside it (``--debug`` keeps Python's format)."""
    own = category.__module__.startswith(("nlyap_opt", "systems", "verification"))
    text = " ".join(str(message).split())
    print(f"nlyap: warning: {text if own else f'{category.__name__}: {text}'}",
          file=sys.stderr if file is None else file)


def _close_progress_bars() -> None:
    """Close progress bars an exception left open, so that the one-line message starts its
    own line (a bar stopped mid-line by --time-limit had the message appended to it)."""
    tqdm = sys.modules.get("tqdm")
    for bar in list(getattr(getattr(tqdm, "tqdm", None), "_instances", None) or []):
        try:
            bar.close()
        except Exception:  # noqa: BLE001 - a broken bar must not hide the message
            pass


def _enter_portable_mode(argv: list[str], may_restart: bool) -> None:
    """Restart this command with the portable pins set, or check that they took effect.

    The pins act only in a process that starts with them (numpy, OpenBLAS and torch read
    them when they load), so the command replaces itself by a new process with them set.
    """

    if os.environ.get(PORTABLE_FLAG) != "1":
        if not may_restart:
            raise ConfigError(
                "--portable pins numeric kernels before numpy and torch load, which a call "
                "from Python cannot do: run the nlyap command, or start Python with the "
                "variables of nlyap_opt.kernel.provenance.portable_env() set")
        sys.stdout.flush()
        sys.stderr.flush()
        os.execve(sys.executable, [sys.executable, "-m", "nlyap_opt.interface.cli", *argv],
                  dict(os.environ, **portable_env()))
    problems = portable_problems()
    if problems:
        raise ConfigError(
            f"--portable cannot pin this machine's numeric kernels ({'; '.join(problems)}); "
            "it needs an x86-64 CPU with AVX2 and FMA: run without --portable (then the "
            "networks are bit for bit reproducible on this machine's fingerprint only)")


class _ReaderMayLeave:
    """Standard output that drops what is written after its reader closed the pipe
    (``nlyap systems | head``): the command goes on and ends with its own exit code,
    without a ``BrokenPipeError``. The file descriptor is pointed at ``/dev/null`` so that
    the interpreter's own flush at exit stays silent too."""

    def __init__(self, stream):
        self._stream = stream
        self._gone = False

    def _left(self) -> None:
        self._gone = True
        with contextlib.suppress(Exception):
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, self._stream.fileno())
            os.close(null)

    def write(self, text):
        if not self._gone:
            try:
                return self._stream.write(text)
            except BrokenPipeError:
                self._left()
        return len(text)

    def flush(self):
        if not self._gone:
            try:
                self._stream.flush()
            except BrokenPipeError:
                self._left()

    def __getattr__(self, name):
        return getattr(self._stream, name)


def main(argv: list[str] | None = None) -> int:
    """Run ``nlyap`` with ``argv`` (default ``sys.argv[1:]``); return the exit code.

    Never raises: every outcome is an exit code of :data:`EXIT_CODES`. Ctrl-C stops the
    command (exit 130) but never inside an import (:func:`_outside_imports`); the caller's
    SIGINT handler is restored on return. Output written after a pipe's reader has gone
    is dropped (:class:`_ReaderMayLeave`).
    """
    sigint = signal.getsignal(signal.SIGINT)
    own = sigint is signal.default_int_handler and \
        threading.current_thread() is threading.main_thread()
    if own:
        signal.signal(signal.SIGINT, _outside_imports(_interrupt))
    stdout = sys.stdout
    sys.stdout = _ReaderMayLeave(stdout)
    try:
        return _main(argv)
    finally:
        gone = sys.stdout._gone if isinstance(sys.stdout, _ReaderMayLeave) else False
        sys.stdout = stdout
        if gone:    # the descriptor is /dev/null now; keep the exit flush quiet
            with contextlib.suppress(Exception):
                stdout.flush()
        if own:
            signal.signal(signal.SIGINT, sigint)


def _main(argv: list[str] | None) -> int:
    """:func:`main` with its SIGINT handler in place."""
    may_restart = argv is None   # the nlyap command itself, not a call from Python
    argv = list(sys.argv[1:] if argv is None else argv)
    full_argv = list(argv)
    debug = "--debug" in argv
    argv = [a for a in argv if a != "--debug"]
    command = None
    try:
        try:
            args = build_parser().parse_args(argv)
        except SystemExit as stop:  # --help
            return stop.code if isinstance(stop.code, int) else 0
        command = args.command
        if getattr(args, "portable", False):
            _enter_portable_mode(full_argv, may_restart)
        _check_paths(args)
        with _time_guard(getattr(args, "time_limit", None)), warnings.catch_warnings():
            if not debug:
                warnings.showwarning = _one_line_warning
            try:
                return int(args.func(args) or 0)
            except Exception as exc:    # a stop that a C extension wrapped (SystemError)
                stop = interruption(exc)
                if stop is None:
                    raise
                raise stop from None
    except TimeLimitReached as stop:
        _close_progress_bars()
        where = getattr(args, "out", None) or "the output directory"
        print(f"nlyap: stopped at --time-limit {stop.args[0]:g} s; the stages finished "
              f"before it are kept in {where}; rerun the same command to resume (with a "
              "larger --time-limit, or none, to finish)", file=sys.stderr)
        return 5
    except KeyboardInterrupt:
        _close_progress_bars()
        print("nlyap: interrupted; rerun the same command to resume", file=sys.stderr)
        return 130
    except SystemExit as stop:
        if stop.code in (0, None):
            return 0
        err: BaseException = RuntimeError(f"a component exited with code {stop.code}")
        code, msg = 4, f"{_one_line(err)}; rerun with --debug for the traceback"
    except Exception as exc:  # noqa: BLE001 - the exit-code contract maps every exception
        code, msg = _classify(exc, command)
        err = exc
    _close_progress_bars()
    if debug:
        traceback.print_exception(err)
    print(f"nlyap: {'internal error' if code == 4 else 'error'}: {msg}", file=sys.stderr)
    return code


if __name__ == "__main__":
    sys.exit(main())
