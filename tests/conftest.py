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
