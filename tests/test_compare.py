"""`nlyap compare`: baselines certified by the same verifier; certified sets converge."""

import json

import numpy as np
import pytest
from vdp_reference import vdp_lyapunov_matrix, vdp_quadratic_level, vdp_true_roa_area

import systems
from baselines.compare import CompareRow, compare
from baselines.lqr import linear_controller, lqr, saturated_controller
from nlyap_opt.candidates.sos import sos_roa
from nlyap_opt.certification.certificate import recheck_certificate
from nlyap_opt.certification.roa import grid_points
from nlyap_opt.kernel.simulate import simulate_converges
from nlyap_opt.workflow.configs import get_config

# The non-polynomial operations of each seed system's SOS closed loop (u = u_eq), read off the
# model equations (systems/catalogue.py):
#   Van der Pol  x2' = x1 + μ(x1² - 1)x2                     -> none: SOS applies
#   pendulum     ω' = (m g l sin θ + u - b ω)/(m l²)          -> sin (divided by a constant only)
#   unicycle     d' = v sin θ,  θ' = ω - v κ cos θ/(1 - d κ)  -> sin, cos, division by 1 - dκ
NON_POLYNOMIAL_OPS = {
    "van_der_pol": [],
    "inverted_pendulum": ["sin (OP_SIN)"],
    "unicycle_path_following": ["sin (OP_SIN)", "cos (OP_COS)", "division (OP_DIV)"],
}

#: three compare runs (20 s idle) behind every test here: the slow tier
pytestmark = pytest.mark.slow


def _rows(rows, prefix):
    return [r for r in rows if r["method"].startswith(prefix)]


@pytest.fixture(scope="module")
def baseline_rows(tmp_path_factory):
    out = {}
    for name in systems.SEED_SYSTEMS:
        d = tmp_path_factory.mktemp("cmp_" + name)
        cfg = get_config(name, "large" if name == "van_der_pol" else "fast")
        rows = compare(name, cfg, d, log=lambda m: None, include_neural=False)
        assert all(isinstance(r, CompareRow) for r in rows)
        out[name] = (d, cfg, [r.to_json() for r in rows])
    return out


def test_van_der_pol_quadratic_levels_below_the_reference(baseline_rows):
    """The LQR quadratic and the degree-2 SOS rows certify V = xᵀPx up to c*, the least V
    where V̇ ≥ 0 (computed independently in vdp_reference.py: c* = 2.30448 for μ = 1):
    strictly below it (a sound certificate cannot reach it) and within 1 % of it (on the
    verification ball r = 3, containment (b) does not bind: V ≥ λ_min(P)·9 > c* there)."""
    d, cfg, rows = baseline_rows["van_der_pol"]
    s = systems.get("van_der_pol")
    mu = s.params["mu"]
    lq = cfg.get("lqr") or {}
    P = lqr(s, lq.get("Q"), lq.get("R")).P
    np.testing.assert_allclose(P, vdp_lyapunov_matrix(mu), rtol=1e-10, atol=1e-12)
    reference = vdp_quadratic_level(P, mu)
    assert float(cfg["outer"]) ** 2 * np.linalg.eigvalsh(P).min() > reference
    (row,) = _rows(rows, "lqr")
    assert row["certified"], row["status"]
    assert 0.99 * reference <= row["level"] < reference
    sos = _rows(rows, "sos")
    assert len(sos) == 3 and all(r["certified"] for r in sos), [r["status"] for r in sos]
    (sos2,) = [r for r in sos if "degree 2" in r["method"]]
    assert 0.99 * reference <= sos2["level"] < reference
    assert sos2["level"] <= sos2["sdp_level"]
    saved = json.loads((d / "comparison.json").read_text())
    # the simulated grid estimate against the limit cycle's area, computed independently
    assert abs(saved["true_roa_area"] - vdp_true_roa_area(1.0)) < 0.1
    for r in saved["rows"]:
        assert {"method", "level", "certified", "area", "fraction_of_true_roa",
                "seconds"} <= set(r)
    assert (d / "comparison.png").exists() and (d / "comparison.md").exists()


@pytest.mark.parametrize("name", sorted(NON_POLYNOMIAL_OPS))
def test_sos_not_applicable_exactly_for_non_polynomial_systems(baseline_rows, name):
    """Non-polynomial closed loops: one SOS row, "not applicable", naming the operations,
    with sos_roa's own explanation. Polynomial ones: every degree run and certified."""
    _, cfg, rows = baseline_rows[name]
    sos = _rows(rows, "sos")
    ops = NON_POLYNOMIAL_OPS[name]
    if ops:
        assert len(sos) == 1, [r["method"] for r in sos]  # the reason holds for every degree
        (row,) = sos
        assert row["status"].startswith("not applicable: ")
        assert "not polynomial" in row["status"]
        for op in ops:
            assert op in row["status"], (op, row["status"])
        assert not row["certified"] and row["level"] == 0.0
        assert row.get("area", 0.0) == 0.0
        assert row["status"] == sos_roa(systems.get(name), inner=cfg["inner"]).text
    else:
        assert len(sos) == 3
        for row in sos:
            assert not row["status"].startswith("not applicable"), row["status"]
            assert row["certified"] and row["level"] > 0, row["status"]
    assert any(r["certified"] for r in _rows(rows, "lqr"))


@pytest.mark.parametrize("name", systems.SEED_SYSTEMS)
def test_every_certified_set_converges_in_simulation(baseline_rows, name):
    _, cfg, rows = baseline_rows[name]
    s = systems.get(name)
    pts, _ = grid_points(np.asarray(cfg["eval_box"]), 50)
    lq = cfg.get("lqr", {})
    K = lqr(s, lq.get("Q"), lq.get("R")).K if s.nu else None
    checked = 0
    for r in rows:
        if not r["certified"]:
            assert r["level"] == 0.0
            continue
        # the row's saved certificate re-verifies (as `nlyap verify --certificate` does) ...
        cert = recheck_certificate(r["certificate"], log=lambda m: None)
        assert cert.certified, (r["method"], cert.reason)
        assert cert.level == pytest.approx(r["level"], rel=1e-12)
        # ... and every grid point of its certified set converges in simulation
        inside = pts[cert.contains(pts)]
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
