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
def fast_learned_run(tmp_path_factory):
    """``fast_learned_run(name)``: the directory and summary of ``nlyap run NAME --preset
    fast`` with learned f (run from Python, no log), once per session for every module that
    needs it. Tests read the directory; a test that changes files copies it first."""
    from nlyap_opt.workflow.configs import get_config
    from nlyap_opt.workflow.pipeline import run

    runs = {}

    def get(name):
        if name not in runs:
            d = tmp_path_factory.mktemp(name + "_learned")
            runs[name] = d, run(name, get_config(name, "fast"), d, known_dynamics=False,
                                log=lambda m: None).summary
        return runs[name]

    return get
