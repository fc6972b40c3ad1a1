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
    artifacts)."""
    from nlyap_opt.workflow.configs import get_config
    from nlyap_opt.workflow.pipeline import run

    runs = {}

    def get(name, known=False):
        if (name, known) not in runs:
            d = tmp_path_factory.mktemp(name + ("_known" if known else "_learned"))
            runs[name, known] = d, run(name, get_config(name, "fast"), d, known_dynamics=known,
                                       log=lambda m: None).summary
        return runs[name, known]

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
