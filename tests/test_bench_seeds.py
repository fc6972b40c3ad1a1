"""The seed lists and the spread over seeds of the default-method benchmark
(bench/default_training.py, bench/seeds.py)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.fixture(scope="module")
def bench():
    """bench/default_training.py as a module (it imports bench/seeds.py as a script does)."""
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location("bench_default_training",
                                                      BENCH / "default_training.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
        yield mod
    finally:
        sys.path.remove(str(BENCH))


def test_seed_lists(bench):
    parse = bench.parse_seeds
    assert parse("0-4") == [0, 1, 2, 3, 4]
    assert parse("0,3") == [0, 3]
    assert parse("2") == [2]
    for bad in ("", "x", "1-x", "4-2", "-1", "1,,2", "0-1-2"):
        with pytest.raises(ValueError, match="seed"):
            parse(bad)
    with pytest.raises(ValueError, match="twice"):
        parse("1,2,1")


def test_spread_counts_an_uncertified_seed_as_zero(bench):
    # median, smallest, largest (in %) and how many seeds certified
    assert bench.spread([0.929, 0.957, 0.963, 0.918, 0.928]) == "92.9 | 91.8 | 96.3 | 5/5"
    assert bench.spread([0.9, None, 0.8]) == "80.0 | 0.0 | 90.0 | 2/3"


def test_every_seed_runs_each_case_and_setting_with_its_own_sets(bench):
    runs = bench._runs(["inverted_pendulum@large", "vdp3"], ["known", "learned"], [0, 3])
    assert [(r[0], r[1], r[2]) for r in runs] == [
        (c, s, k) for c in ("inverted_pendulum@large", "vdp3") for s in ("known", "learned")
        for k in (0, 3)]
    pend = runs[0][5]
    # the seed joins the case's overrides (NAME@large: the large preset's sets)
    assert pend["train"] == {"seed": 0} and pend["domain"]["radius"] == 4.0
    assert runs[-1][5] == {"train": {"seed": 3}}
    # no seed given: the configuration's own
    assert bench._runs(["vdp3"], ["known"], [None])[0][5] == {}
