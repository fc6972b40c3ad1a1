"""Same config and seed, same artifacts: whatever the clock says and whatever else runs.

A wall-clock budget once gave a different φ (and no certificate) on a loaded machine.
Every training budget is now a count; these tests run the φ and the V/κ training twice,
once with the clock running 100 times fast and a sleep injected into the training loop
(what a loaded machine looks like to a timed loop), and require the saved network JSON to
be identical, byte for byte.
"""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import torch

import systems
from baselines.lqr import lqr, saturated_controller
from nlyap_opt.candidates.learning import LyapunovLearner, TrainConfig, sample_ball, sample_sphere
from nlyap_opt.kernel.determinism import deterministic_torch
from nlyap_opt.kernel.errors import ConfigError
from nlyap_opt.learned import phi_training
from nlyap_opt.learned.dynamics import learn_dynamics

PHI = {"preset": "fast", "hidden": 8, "steps": 60, "lm_iterations": 8, "minimax_rounds": 1,
       "minimax_iterations": 3, "progress": False}


def _slow_machine(monkeypatch):
    """A clock 100× fast and a sleep in every training step: any time budget would bite."""
    t0 = {"perf_counter": time.perf_counter(), "time": time.time(),
          "monotonic": time.monotonic()}
    real = {k: getattr(time, k) for k in t0}
    for name in t0:
        def fast(name=name):
            return t0[name] + 100.0 * (real[name]() - t0[name])
        monkeypatch.setattr(time, name, fast)
    step = torch.optim.Adam.step

    def slow_step(self, *a, **k):
        time.sleep(0.002)
        return step(self, *a, **k)

    monkeypatch.setattr(torch.optim.Adam, "step", slow_step)
    lm_run = phi_training.LevenbergMarquardt.run

    def slow_run(self, *a, **k):
        time.sleep(0.05)
        return lm_run(self, *a, **k)

    monkeypatch.setattr(phi_training.LevenbergMarquardt, "run", slow_run)
    torch.set_num_threads(2)  # a caller with another thread setting


def _phi_json():
    res = learn_dynamics(systems.get("unicycle_path_following"), PHI)
    return json.dumps(res.network.to_dict(), sort_keys=True)


def test_phi_is_bit_identical_under_a_slow_clock(monkeypatch):
    threads = torch.get_num_threads()
    a = _phi_json()
    assert torch.get_num_threads() == threads  # the thread setting is restored
    with monkeypatch.context() as m:
        _slow_machine(m)
        assert time.perf_counter() - time.perf_counter() < 0  # the patch is live (fast clock)
        b = _phi_json()
        assert torch.get_num_threads() == 2
    torch.set_num_threads(threads)
    assert a == b


def _train_V_kappa():
    s = systems.get("inverted_pendulum")
    ctrl = saturated_controller(s, lqr(s).K, 20.0)
    cfg = TrainConfig(hidden=[6], features=3, steps=40, batch=256, seed=3, w_local=1.0)
    L = LyapunovLearner(s, ctrl, None, cfg)
    rng = np.random.default_rng(0)
    X = sample_ball(2000, 2, 2.0, rng)
    S = sample_sphere(200, 2, 2.0, rng)
    info = L.train(X, S, 0.0)
    assert info.steps == 40  # all steps ran: no clock can stop it early
    V, k = L.export()
    return json.dumps(V.to_dict(), sort_keys=True), json.dumps(k.to_dict(), sort_keys=True)


def test_V_and_kappa_are_bit_identical_under_a_slow_clock(monkeypatch):
    a = _train_V_kappa()
    with monkeypatch.context() as m:
        _slow_machine(m)
        b = _train_V_kappa()
    torch.set_num_threads(1)
    assert a == b


def test_no_time_budget_anywhere():
    assert "time_budget" not in TrainConfig.__dataclass_fields__
    with pytest.raises(TypeError):
        TrainConfig(time_budget=1.0)
    with pytest.raises(ConfigError, match="counted in steps"):
        learn_dynamics(systems.get("van_der_pol"), {"preset": "fast", "time_budget": 1.0})


def test_deterministic_torch_is_scoped_and_checked():
    before = (torch.get_num_threads(), torch.are_deterministic_algorithms_enabled())
    with deterministic_torch(1):
        assert torch.get_num_threads() == 1 and torch.are_deterministic_algorithms_enabled()
    assert (torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()) == before
    with pytest.raises(RuntimeError), deterministic_torch(1):
        raise RuntimeError("boom")
    assert (torch.get_num_threads(), torch.are_deterministic_algorithms_enabled()) == before
    with pytest.raises(ConfigError), deterministic_torch(0):
        pass
    with pytest.raises(ConfigError, match="threads"):
        LyapunovLearner(systems.get("van_der_pol"), None, None, TrainConfig(threads=0))


def test_deterministic_torch_loads_no_compiler_and_enforces_determinism():
    """The eager flag alone (no inductor import: about a CPU second per process), and the
    kernels obey it: deterministic mode fills uninitialised memory (NaN for floats)."""
    import subprocess
    import sys

    code = ("import sys, torch\n"
            "from nlyap_opt.kernel.determinism import deterministic_torch\n"
            "with deterministic_torch(1):\n"
            "    assert torch.are_deterministic_algorithms_enabled()\n"
            "    assert torch.isnan(torch.empty(64, dtype=torch.float64)).all()\n"
            "assert not torch.are_deterministic_algorithms_enabled()\n"
            "print('torch._inductor.config' in sys.modules, 'torch._dynamo' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.split() == ["False", "False"], out.stdout + out.stderr


def _run_files(d):
    """sha256 of every hashed artifact of a run (the stage files and the certificate's
    artifacts) and certificate.json without its timings and numeric environment."""
    import hashlib
    from pathlib import Path

    from nlyap_opt.kernel.jsonio import split_timings

    d = Path(d)
    names = {n for rec in json.loads((d / "stages.json").read_text()).values()
             for n in rec["files"]}
    cert = json.loads((d / "certificate.json").read_text())
    names |= {a["file"] for a in cert["artifacts"].values()}
    digests = {n: hashlib.sha256((d / n).read_bytes()).hexdigest() for n in sorted(names)}
    cert.pop("provenance")
    return digests, split_timings(cert)[0]


def test_the_same_run_twice_under_other_thread_counts_and_load_gives_the_same_bytes(
        tmp_path, fast_run):
    """The fast learned Van der Pol run twice at once, each run the other's load (a busy
    machine): from the command line with one BLAS/OpenMP thread and from Python in this
    process with the session's threads (the shared run, no progress bars). Every hashed
    artifact (φ, bounds, V, CEGIS record) has the same sha256 and the certificates the same
    content; only wall-clock timings (kept in timings.json and seconds.json) differ."""
    import os
    import subprocess
    import sys

    def nlyap(out, threads):
        env = dict(os.environ, OPENBLAS_NUM_THREADS=str(threads), OMP_NUM_THREADS=str(threads),
                   MKL_NUM_THREADS=str(threads))
        log = open(tmp_path / f"{out.name}.log", "w")   # closed below
        return subprocess.Popen([sys.executable, "-m", "nlyap_opt.interface.cli", "run",
                                 "van_der_pol", "--preset", "fast", "--out", str(out)],
                                env=env, text=True, stdout=log, stderr=subprocess.STDOUT), log

    procs = [nlyap(tmp_path / "a", 1)]
    try:
        c, _ = fast_run("van_der_pol")   # meanwhile (or already run)
        codes = [p.wait(timeout=600) for p, _ in procs]
    finally:
        for p, log in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
            log.close()
    assert codes == [0], (tmp_path / "a.log").read_text()[-3000:]
    files_a, cert_a = _run_files(tmp_path / "a")
    files_c, cert_c = _run_files(c)
    assert {"dynamics.json", "bounds.json", "V.json", "cegis.json"} <= set(files_a)
    assert files_a == files_c
    assert cert_a == cert_c
    assert json.loads((tmp_path / "a" / "timings.json").read_text())["cegis.json"]


def test_a_diverged_training_stops_with_what_to_do():
    """States of order 1e100 make the loss NaN at the first step (Adam would carry it into
    every weight): the learner stops with a one-line error naming the fix, not an internal
    error later (the history's JSON refused the NaN)."""
    from nlyap_opt.kernel.errors import ConfigError

    L = LyapunovLearner(systems.get("van_der_pol"), None, None,
                        TrainConfig(hidden=[6], features=3, steps=5, batch=64, seed=0))
    rng = np.random.default_rng(0)
    with pytest.raises(ConfigError, match=r"training diverged at step 1: the loss is nan"):
        L.train(sample_ball(200, 2, 1e100, rng), sample_sphere(50, 2, 1e100, rng), 0.0)
