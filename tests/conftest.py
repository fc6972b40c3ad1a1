import numpy as np
import pytest
import torch

import systems
from nlyap_opt.learned.dynamics import default_config, learn_dynamics

SEED_SYSTEMS = ["van_der_pol", "unicycle_path_following", "inverted_pendulum"]


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture(scope="session")
def trained():
    """Fast-config learned dynamics for the three seed systems (seconds each), once per run."""
    torch.set_num_threads(1)
    out = {}
    for name in SEED_SYSTEMS:
        cfg = default_config(name, fast=True) | {"progress": False}
        out[name] = learn_dynamics(systems.get(name), cfg)
    return out


@pytest.fixture(scope="session")
def fast_run(tmp_path_factory):
    """``fast_run(name, known=False)``: the directory and summary of ``nlyap run NAME
    --preset fast`` (``--known-dynamics`` with ``known``), run from Python without a log,
    once per session for every module that needs it. Tests read the directory; a test that
    changes files copies it first (a rerun of the same configuration in place writes the same
    artifacts). ``fast_run.many(names, known)``: several of them, the missing ones but the
    last as ``nlyap run`` processes while the last runs here (the summary is the
    certificate.json the pipeline writes and returns; the same bytes from a process or from
    here: test_determinism)."""
    import json
    import subprocess
    import sys

    from nlyap_opt.workflow.configs import get_config
    from nlyap_opt.workflow.pipeline import run

    runs = {}

    def folder(name, known):
        return tmp_path_factory.mktemp(name + ("_known" if known else "_learned"))

    def get(name, known=False):
        if (name, known) not in runs:
            d = folder(name, known)
            runs[name, known] = d, run(name, get_config(name, "fast"), d, known_dynamics=known,
                                       log=lambda m: None).summary
        return runs[name, known]

    def many(names, known=False):
        missing = [n for n in names if (n, known) not in runs]
        procs = []
        try:
            for name in missing[:-1]:
                d = folder(name, known)
                log = open(d.with_suffix(".log"), "w")   # closed below
                argv = [sys.executable, "-m", "nlyap_opt.interface.cli", "run", name,
                        "--preset", "fast", "--out", str(d)] + ["--known-dynamics"] * known
                procs.append((name, d, log, subprocess.Popen(argv, stdout=log,
                                                             stderr=subprocess.STDOUT)))
            if missing:
                get(missing[-1], known)
            for name, d, log, p in procs:
                code = p.wait(timeout=900)
                log.close()
                tail = d.with_suffix(".log").read_text()[-3000:]
                assert code in (0, 2), f"{name}: exit {code}\n{tail}"
                runs[name, known] = d, json.loads((d / "certificate.json").read_text())
        finally:
            for *_, log, p in procs:
                if p.poll() is None:
                    p.kill()
                    p.wait()
                log.close()
        return {n: runs[n, known] for n in names}

    get.many = many
    return get


@pytest.fixture
def log_until():
    """``log_until(marker)``: a run's ``log`` callback that keeps every message (``.lines``)
    and stops the run right after the first one holding ``marker``, with the pipeline's
    interrupt (KeyboardInterrupt: the lock is released, finished stages stay). For tests of
    what a rerun loads or recomputes, decided and logged as each stage starts."""

    def make(marker):
        def log(message):
            log.lines.append(message)
            if marker in message:
                raise KeyboardInterrupt

        log.lines = []
        return log

    return make


@pytest.fixture
def offset_equilibrium_loop():
    """``(system, κ)`` whose closed loop's equilibrium is off the origin by more than
    rounding: κ = C·tanh(0·x + b), C = 10¹⁰, u_eq = fl(C·tanh b), so the real g₀(0) =
    C·tanh(b) − u_eq ≈ −2.4·10⁻⁷ against a decay of 10⁻⁹ along x₀ (equilibrium near
    x₀ = −238). Expanding the loop to SX folds g₀(0) to exactly 0."""
    import math

    import casadi as ca

    from nlyap_opt.kernel.network import Layer, Network

    b, C = 0.3, 1e10
    u_eq = float(C * math.tanh(b))
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    s = systems.System("slowfold", x, u, ca.vertcat(-1e-9 * x[0] + (u - u_eq), -x[1]),
                       state_box=[[-2, 2], [-2, 2]], input_box=[[-1e11, 1e11]], u_eq=[u_eq])
    return s, Network([Layer([[0.0, 0.0]], [b], "tanh")], output_scale=C)
