"""`nlyap compare`: baselines certified by the same verifier; certified sets converge."""

import json

import numpy as np
import pytest

import systems
from baselines.compare import compare
from baselines.lqr import linear_controller, lqr, saturated_controller
from nlyap_opt.configs import get_config
from nlyap_opt.roa import grid_points
from nlyap_opt.simulate import simulate_converges


@pytest.fixture(scope="module")
def baseline_rows(tmp_path_factory):
    out = {}
    for name in systems.names():
        d = tmp_path_factory.mktemp("cmp_" + name)
        cfg = get_config(name, "large" if name == "van_der_pol" else "fast")
        out[name] = (d, cfg, compare(name, cfg, d, log=lambda m: None, include_neural=False))
    return out


def test_van_der_pol_quadratic_level_within_one_percent(baseline_rows):
    d, cfg, rows = baseline_rows["van_der_pol"]
    row = next(r for r in rows if r["method"].startswith("lqr"))
    assert row["certified"]
    assert 0.99 * 2.3045 <= row["level"] < 2.3045
    sos = [r for r in rows if r["method"].startswith("sos")]
    assert sos and all(r["certified"] for r in sos)
    saved = json.loads((d / "comparison.json").read_text())
    assert abs(saved["true_roa_area"] - 13.72) < 0.1
    for r in saved["rows"]:
        assert {"method", "level", "certified", "area", "fraction_of_true_roa",
                "seconds"} <= set(r)
    assert (d / "comparison.png").exists() and (d / "comparison.md").exists()


@pytest.mark.parametrize("name", ["unicycle_path_following", "inverted_pendulum"])
def test_non_polynomial_systems_explain_sos(baseline_rows, name):
    _, _, rows = baseline_rows[name]
    sos = [r for r in rows if r["method"].startswith("sos")]
    assert sos and all(r["certified"] or r["status"].startswith("not applicable")
                       for r in sos)
    assert any(r["certified"] for r in rows if r["method"].startswith("lqr"))


@pytest.mark.parametrize("name", systems.names())
def test_every_certified_set_converges_in_simulation(baseline_rows, name):
    _, cfg, rows = baseline_rows[name]
    s = systems.get(name)
    pts, _ = grid_points(np.asarray(cfg["eval_box"]), 50)
    lq = cfg.get("lqr", {})
    K = lqr(s, lq.get("Q"), lq.get("R")).K if s.nu else None
    checked = 0
    for r in rows:
        if not r["certified"]:
            continue
        inside = pts[r["_maskfn"](pts)]
        ctrl = None
        if s.nu:
            ctrl = (linear_controller(s, K) if "linear" in r["method"]
                    else saturated_controller(s, K, cfg["controller_scale"]))

        def rhs(z, ctrl=ctrl):
            return s.evaluate(z, None if ctrl is None else ctrl.numpy(z))

        ok = simulate_converges(rhs, inside, t_final=80.0, dt=0.02, tol=1e-3)
        assert ok.all(), (r["method"], inside[~ok][:3])
        checked += len(inside)
    assert checked > 100
