"""Slow tier (`make test-slow`): the full presets end to end, learned and known dynamics."""

import pytest

import systems
from nlyap_opt.configs import get_config
from nlyap_opt.pipeline import run

pytestmark = pytest.mark.slow


@pytest.mark.parametrize("known", [False, True], ids=["learned", "known"])
@pytest.mark.parametrize("name", systems.SEED_SYSTEMS)
def test_large_preset_is_certified(name, known, tmp_path):
    cert = run(name, get_config(name, "large"), tmp_path, known_dynamics=known,
               log=lambda m: None).summary
    assert cert["status"] == "certified"
    assert cert["certified_points_converge_in_simulation"]
    print(f"{name} ({'known' if known else 'learned'}): "
          f"{100 * cert['fraction_of_true_roa']:.1f}% of the true ROA")
