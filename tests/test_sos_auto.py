"""The SOS candidate by default where it applies: ``sos.degree = "auto"`` (the degree chosen
from the size of the SDPs, off where SOS does not apply), the competition with the neural V
and the determinism of the SDPs."""

import json
import os
import subprocess
import sys
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from forge import forge_stage_file

import systems
from nlyap_opt.candidates.sos import (
    AUTO,
    AUTO_DEGREES,
    AUTO_GRAM_LIMIT,
    SOSConfig,
    choose_degree,
    sos_roa,
)
from nlyap_opt.design import sos_sdp
from nlyap_opt.design.control import lqr, saturated_controller
from nlyap_opt.design.polynomial import polynomial_closed_loop
from nlyap_opt.kernel.errors import ConfigError
from nlyap_opt.workflow import pipeline
from nlyap_opt.workflow.configs import domain_of, make_config
from nlyap_opt.workflow.pipeline import run

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _poly_system(nx: int, cubic: bool = True, name: str = "auto_poly") -> systems.System:
    """x_i' = -x_i + x_{i+1} (+ x_i² x_{i+1}): a polynomial system without inputs in nx
    states (degree 3, or 1 without the cubic terms)."""
    x = ca.SX.sym("x", nx)
    f = ca.vertcat(*[-x[i] + 0.5 * x[(i + 1) % nx]
                     + (x[i] ** 2 * x[(i + 1) % nx] if cubic else 0) for i in range(nx)])
    return systems.System(name, x, None, f, state_box=[[-1.0, 1.0]] * nx)


# --------------------------------------------------------------------------- the SDP size
def test_gram_size_is_the_largest_gram_matrix_the_programs_set_up(monkeypatch):
    """gram_size, known before any SDP, equals the order of the largest PSD variable that
    sos_roa's programs actually create (recorded while they run)."""
    orders = []
    real = sos_sdp._Space.gram_variable

    def record(self, degree):
        G, M = real(self, degree)
        orders.append(G.shape[0])
        return G, M

    monkeypatch.setattr(sos_sdp._Space, "gram_variable", record)
    vdp = systems.get("van_der_pol")
    for degree in (2, 4):
        orders.clear()
        sos_roa(vdp, degree=degree, iterations=1, certify=False, log=None)
        assert orders and max(orders) == sos_sdp.gram_size(2, degree, 3)


def test_gram_size_counts_monomials():
    # the decrease constraint of degree D has binom(nx + D/2, nx) - 1 monomials of degree
    # 1..D/2; V of degree 6, f cubic, s of degree 4: D = 10
    assert sos_sdp.gram_size(2, 6, 3) == len(sos_sdp.monomials(2, 1, 5)) == 20
    assert sos_sdp.gram_size(3, 4, 4) == len(sos_sdp.monomials(3, 1, 5)) == 55
    sizes = [sos_sdp.gram_size(n, d, 3) for n in (2, 3, 4) for d in (2, 4, 6)]
    assert all(a < b for a, b in zip(sizes[:3], sizes[1:3]))          # grows with degree
    assert sos_sdp.gram_size(3, 4, 3) < sos_sdp.gram_size(4, 4, 3)     # and with n
    with pytest.raises(ValueError, match="even degree"):
        sos_sdp.gram_size(2, 3, 3)


# --------------------------------------------------------------------------- the choice
@pytest.mark.parametrize("system, degree", [
    (lambda: systems.get("van_der_pol"), 6),
    (lambda: _poly_system(2, cubic=False, name="auto_lin2"), 6),
    (lambda: systems.load_spec(EXAMPLES / "fossil_nonpoly2.toml"), 4),
    (lambda: _poly_system(3), 4),
    (lambda: systems.load_spec(EXAMPLES / "fossil_nonpoly3.toml"), 0),   # quartic f in 3-D
    (lambda: systems.load_spec(EXAMPLES / "centre_4d.toml"), 0),
    (lambda: _poly_system(5), 0),
])
def test_auto_picks_the_largest_degree_whose_sdps_fit_the_budget(system, degree):
    s = system()
    choice = choose_degree(s, AUTO, known=True)
    assert choice.degree == degree and choice.automatic
    deg_f = max(p.degree for p in polynomial_closed_loop(s))
    fits = [d for d in AUTO_DEGREES if sos_sdp.gram_size(s.nx, d, deg_f) <= AUTO_GRAM_LIMIT]
    assert degree == (max(fits) if fits else 0)
    if degree:
        assert choice.gram == sos_sdp.gram_size(s.nx, degree, deg_f) <= AUTO_GRAM_LIMIT
        assert f"n = {s.nx}, deg f = {deg_f}" in choice.describe()
    else:
        assert f"> {AUTO_GRAM_LIMIT}" in choice.reason and "sos.degree 4" in choice.reason


def test_auto_is_off_where_sos_does_not_apply():
    vdp = systems.get("van_der_pol")
    learned = choose_degree(vdp, AUTO, known=False)
    assert learned.degree == 0 and "learned dynamics" in learned.reason
    # with a polynomial model of φ its degree sizes the programs, as f's does
    from nlyap_opt.design.polynomial import PolynomialFit
    model = PolynomialFit(polynomial_closed_loop(vdp), 3, 1e-4)
    fitted = choose_degree(vdp, AUTO, known=False, model=model)
    assert fitted.degree == 6 and "a degree-3 model of φ" in fitted.reason
    # learned dynamics with an input: the controller's tanh is named, not a missing model
    pend = systems.get("inverted_pendulum")
    assert "C·tanh(Kx + b)" in choose_degree(pend, AUTO, known=False).reason
    pend = systems.get("inverted_pendulum")
    assert choose_degree(pend, AUTO).degree == 0                       # inputs: κ unknown
    tanh = choose_degree(pend, AUTO, controller=saturated_controller(pend, lqr(pend).K, 20.0))
    assert tanh.degree == 0 and "not polynomial: it applies" in tanh.reason
    assert "tanh" in tanh.reason
    power = choose_degree(systems.load_spec(EXAMPLES / "two_machine_power.toml"), AUTO)
    assert power.degree == 0 and "sin" in power.reason
    lorenz = choose_degree(systems.load_spec(EXAMPLES / "lorenz_controlled.toml"), AUTO)
    assert lorenz.degree == 0 and "C·tanh(Kx + b)" in lorenz.reason
    for text in (learned, tanh, power, lorenz):
        assert "\n" not in text.describe() and text.describe().startswith(
            "sos.degree 'auto' -> off: ")


def test_an_explicit_degree_keeps_its_meaning():
    vdp = systems.get("van_der_pol")
    assert choose_degree(vdp, 0).degree == 0 and not choose_degree(vdp, 0).automatic
    assert choose_degree(vdp, 4).degree == 4
    # explicit: no automatic rule, also where auto would be off (certify_sos says why)
    assert choose_degree(vdp, 2, known=False).degree == 2
    assert choose_degree(systems.load_spec(EXAMPLES / "centre_4d.toml"), 4).degree == 4


# --------------------------------------------------------------------------- configuration
def test_the_default_method_runs_sos_automatically_the_presets_do_not():
    assert make_config("van_der_pol", None).sos.degree == AUTO
    for preset in ("fast", "paper", "large"):
        assert make_config("van_der_pol", preset).sos.degree == 0
    assert SOSConfig().degree == 0


@pytest.mark.parametrize("degree", ["Auto", "6", True, 6.0, None, [6]])
def test_bad_degrees_are_one_line_config_errors(degree):
    with pytest.raises(ConfigError) as err:
        make_config("van_der_pol", None, overrides={"sos": {"degree": degree}})
    msg = str(err.value)
    assert "sos.degree must be one of 'auto', 0, 2, 4, 6" in msg and "\n" not in msg


def test_init_sos_with_auto_resolves_the_degree_before_any_stage():
    train = {"init": "sos", "activation": "square", "hidden": [6], "features": 5}
    with pytest.raises(ConfigError, match=r"\(degree 6\) needs|degree 2 or 4 .*got degree 6"):
        make_config("van_der_pol", None, overrides={"train": train})      # auto -> 6 in 2-D
    s = systems.load_spec(EXAMPLES / "fossil_nonpoly3.toml")
    if s.name not in systems.names():
        systems.register(s.name, lambda: s)
    with pytest.raises(ConfigError, match=r"SOS stage is off \(sos.degree 'auto' -> off: n = "
                                          r"3, deg f = 4"):
        make_config(s.name, None, overrides={"train": train})


def test_nlyap_config_says_what_auto_resolves_to(capsys):
    from nlyap_opt.interface.cli import main

    assert main(["config", "van_der_pol", "--preset", "default"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["sos"]["degree"] == "auto"        # stdout stays the JSON config
    assert err.strip() == ("with --known-dynamics, sos.degree 'auto' -> degree 6: n = 2, "
                           "deg f = 3: Gram matrices of order 20 <= 40; with learned "
                           "dynamics, chosen once φ is learned, from the degree of a "
                           "polynomial model of φ")
    assert main(["config", "inverted_pendulum", "--preset", "default"]) == 0
    assert capsys.readouterr().err.strip().endswith("with learned dynamics, off (an input)")
    assert main(["config", "van_der_pol", "--preset", "fast"]) == 0
    assert capsys.readouterr().err == ""


# --------------------------------------------------------------------------- the stage
def _context(tmp_path, known: bool, logs: list):
    vdp = systems.get("van_der_pol")
    cfg = make_config("van_der_pol", None)
    region = cfg.view(pipeline._REGION)
    D, XI = domain_of(region, 2)
    stages = pipeline._Stages(tmp_path, "van_der_pol", known, cfg, logs.append)
    return pipeline._Context(vdp, tmp_path, stages, logs.append, D, XI, D.max_norm(),
                             float(region.inner))


def test_with_learned_dynamics_the_auto_stage_is_one_line_and_writes_nothing(tmp_path):
    logs = []
    assert pipeline._sos_stage(_context(tmp_path, False, logs)) is None
    assert logs == ["[sos] sos.degree 'auto' -> off: learned dynamics: the SOS programs need "
                    "the polynomial model of f"]
    assert not (tmp_path / "sos.json").exists() and not (tmp_path / "V_sos.json").exists()


@pytest.fixture(scope="module")
def auto_run(tmp_path_factory):
    """Van der Pol, true f, the default method's sos.degree 'auto' (-> 6, one V-s round per
    degree) beside a neural stage cut to one step: the SOS V must win."""
    d = tmp_path_factory.mktemp("sos_auto")
    cfg = make_config("van_der_pol", "fast", overrides={
        "sos": {"degree": "auto", "iterations": 1}, "train": {"steps": 1},
        "cegis": {"iterations": 1, "steps": 1}})
    logs = []
    res = run("van_der_pol", cfg, d, known_dynamics=True, log=logs.append)
    return d, cfg, res, logs


def test_an_automatic_sos_winner_is_the_certificate_and_the_report_says_so(auto_run):
    d, _, res, logs = auto_run
    text = "\n".join(logs)
    assert "[sos] sos.degree 'auto' -> degree 6: n = 2, deg f = 3" in text
    rec = json.loads((d / "sos.json").read_text())
    assert rec["degree"] == 6 and rec["status"] == "certified"
    summary = json.loads((d / "certificate.json").read_text())
    win = [c for c in summary["candidates"] if c["winner"]]
    assert len(win) == 1 and win[0]["V"].startswith("SOS degree")
    vols = {c["V"]: c["certified_volume"] for c in summary["candidates"]}
    assert win[0]["certified_volume"] == max(vols.values()) > vols["neural (V.json)"]
    assert res.certified and summary["certified_area"] == pytest.approx(
        win[0]["certified_volume"])
    assert "[cegis] the certificate to beat: SOS degree" in text
    assert "The neural V did not beat the cheap candidate" in (d / "report.md").read_text()


@pytest.mark.slow  # 10 s idle, 30 s on the shared machine: two more runs of the pipeline
def test_a_finished_auto_stage_is_loaded_and_a_changed_degree_recomputes_it(auto_run,
                                                                              tmp_path):
    import shutil

    d, cfg, _, _ = auto_run
    e = tmp_path / "again"
    shutil.copytree(d, e)
    logs = []
    run("van_der_pol", cfg, e, known_dynamics=True, log=logs.append)
    assert "[sos] loaded from" in "\n".join(logs)
    # a stage record of another degree (an older rule) is not reused

    rec = json.loads((e / "sos.json").read_text())
    rec["degree"] = 4
    (e / "sos.json").write_text(json.dumps(rec))
    forge_stage_file(e, "sos", "sos.json")
    logs.clear()
    run("van_der_pol", cfg, e, known_dynamics=True, log=logs.append)
    assert "sos.json holds degree 4, the run's degree is 6: the SOS stage is recomputed" in \
        "\n".join(logs)
    assert json.loads((e / "V_sos.json").read_text()) == \
        json.loads((d / "V_sos.json").read_text())


# --------------------------------------------------------------------------- the domain
@pytest.mark.slow  # 4 s idle, 11 s shared; tests/test_domain.py's Khalil box runs this search
def test_a_set_across_the_domain_boundary_is_searched_again_inside_it():
    """Van der Pol's SOS set grows across the box [-1.5, 1.5]² (its ROA does not fit in
    it): the iteration runs again with its sets kept inside, and the V kept has the larger
    set inside the box (star areas of {V <= min(level, least V on the boundary)})."""
    from nlyap_opt.design.sos_sdp import star_area
    from nlyap_opt.kernel.domain import parse_set

    vdp = systems.get("van_der_pol")
    box = parse_set({"type": "box", "box": [[-1.5, 1.5], [-1.5, 1.5]]}, 2)
    edge = box.sample_boundary(2000, np.random.default_rng(1))

    def inside(r):
        return star_area(r.V, min(r.sdp_level, float(r.V(edge).min())))

    plain = sos_roa(vdp, degree=4, iterations=2, certify=False)
    kept = sos_roa(vdp, degree=4, iterations=2, certify=False, keep_in=box)
    assert float(plain.V(edge).min()) < plain.sdp_level           # crosses ∂D
    assert any("repeated inside the domain" in n for n in kept.notes)
    assert inside(kept) > 1.2 * inside(plain)
    assert kept.V.degree == 4 and float(kept.V(edge).min()) >= 0.99 * kept.sdp_level


def test_the_search_inside_the_domain_keeps_to_half_the_budget():
    """Larger programs (a cubic in 3-D at degree 4: order 34 > 20) are not searched again
    inside the domain: the set is kept as it is (certification cuts it down) and a note says
    why, before any SDP."""
    from nlyap_opt.candidates import sos as sos_mod
    from nlyap_opt.design.polynomial import Polynomial
    from nlyap_opt.kernel.domain import parse_set

    s = _poly_system(3)
    f = polynomial_closed_loop(s)
    V = Polynomial.quadratic(np.eye(3))
    ball = parse_set({"type": "ball", "radius": 1.0}, 3)
    notes = []
    edge = ball.sample_boundary(600, np.random.default_rng(0))
    out = sos_mod._keep_inside(V, 4.0, V, 4.0, f, 4, [], notes, 3.0,
                               {"say": lambda m: None, "edge": edge})
    assert out == (V, 4.0)
    assert notes == ["the set crosses the domain's boundary; not searched again inside it "
                     "(Gram matrices of order 34 > 20)"]


# --------------------------------------------------------------------------- determinism
_DET = ("import json, systems; from nlyap_opt.candidates.sos import sos_roa; "
        "r = sos_roa(systems.get('van_der_pol'), degree=4, iterations=1, certify=False); "
        "print(json.dumps([r.V.as_json(), r.sdp_level, r.history]))")


@pytest.mark.slow  # the default tier stays within 5 min on 2 cores
def test_the_sos_programs_give_the_same_v_in_one_process_and_across_processes():
    """Same input, same SOS V bit for bit: twice here and once in a process with another
    hash seed."""
    vdp = systems.get("van_der_pol")
    a, b = (sos_roa(vdp, degree=4, iterations=1, certify=False) for _ in range(2))
    here = [json.dumps([r.V.as_json(), r.sdp_level]) for r in (a, b)]
    assert here[0] == here[1]
    env = dict(os.environ, PYTHONHASHSEED="12345",
               PYTHONPATH=os.pathsep.join([str(EXAMPLES.parent), os.environ.get("PYTHONPATH",
                                                                                "")]))
    out = subprocess.run([sys.executable, "-c", _DET], capture_output=True, text=True,
                         env=env, check=True, timeout=120).stdout
    V, level, history = json.loads(out.strip().splitlines()[-1])
    assert json.dumps([V, level]) == here[0]
    assert [h["area"] for h in history] == [h["area"] for h in a.history]
    assert np.isfinite(level) and level > 0


# --------------------------------------------------------------------------- strictness
def test_the_vs_iteration_keeps_a_decrease_rate_relative_to_the_start():
    """The V-s iteration asks -V̇ >= ε_vs ‖x‖² on its set, with ε_vs = strictness times the
    start quadratic's least rate λ_min(-(AᵀP + PA)) at its level: on samples of
    {V <= 1 - backoff} the SOS V's decrease rate stays above (most of) ε_vs, where without
    the strictness it drops below it; the note says which ε_vs was used."""
    from nlyap_opt.candidates import sos as sos_mod
    from nlyap_opt.design.polynomial import Polynomial

    vdp = systems.get("van_der_pol")
    f = polynomial_closed_loop(vdp)
    P = lqr(vdp).P
    A = np.array([[0.0, -1.0], [1.0, -1.0]])   # x1' = -x2, x2' = x1 - x2 + x1² x2
    assert sos_mod._start_rate(P, f) == pytest.approx(
        np.linalg.eigvalsh(-(A.T @ P + P @ A))[0], rel=1e-12)
    level_q = sos_sdp.sos_level(Polynomial.quadratic(P), f, radius=6.0).level

    def least_rate(strictness):
        res = sos_roa(vdp, degree=4, iterations=2, strictness=strictness, certify=False,
                      log=None)
        eps_vs = strictness * sos_mod._start_rate(P, f) / level_q
        assert res.V.degree == 4
        assert [n for n in res.notes if "strictness" in n] == [
            f"V-s iteration with strictness {eps_vs:.3g} (a fraction {strictness:g} of "
            "the starting V's decrease rate)"]
        X = np.random.default_rng(0).uniform(-4, 4, size=(200000, 2))
        X = X[(res.V(X) <= 0.99 * res.sdp_level) & (np.linalg.norm(X, axis=1) > 1e-2)]
        h = 1e-6
        grad = np.stack([(res.V(X + h * e) - res.V(X - h * e)) / (2 * h)
                         for e in np.eye(2)], 1)
        fx = np.stack([p(X) for p in f], axis=1)
        assert len(X) > 1000
        return float((-np.einsum("ij,ij->i", grad, fx) / np.sum(X**2, axis=1)).min()), eps_vs

    least_rate(sos_mod.STRICTNESS)               # the default: its note
    rate, eps_vs = least_rate(0.05)
    assert rate >= 0.5 * eps_vs
    plain = sos_roa(vdp, degree=4, iterations=2, strictness=0.0, certify=False, log=None)
    X = np.random.default_rng(0).uniform(-4, 4, size=(200000, 2))
    X = X[(plain.V(X) <= 0.99 * plain.sdp_level) & (np.linalg.norm(X, axis=1) > 1e-2)]
    h = 1e-6
    grad = np.stack([(plain.V(X + h * e) - plain.V(X - h * e)) / (2 * h) for e in np.eye(2)], 1)
    fx = np.stack([p(X) for p in f], axis=1)
    assert (-np.einsum("ij,ij->i", grad, fx) / np.sum(X**2, axis=1)).min() < 0.5 * eps_vs


def test_a_zero_strictness_and_a_start_without_decrease_add_no_margin():
    """strictness = 0 keeps the plain epsilon (no note); a start matrix whose quadratic does
    not decrease at the origin has rate 0."""
    from nlyap_opt.candidates import sos as sos_mod
    from nlyap_opt.design.polynomial import Polynomial

    res = sos_roa(systems.get("van_der_pol"), degree=4, iterations=1, strictness=0.0,
                  certify=False, log=None)
    assert not any("strictness" in n for n in res.notes)
    unstable = [Polynomial.from_dict({(1, 0): 1.0}, 2), Polynomial.from_dict({(0, 1): 1.0}, 2)]
    assert sos_mod._start_rate(np.eye(2), unstable) == 0.0


def test_only_the_v_step_accepts_an_inaccurate_solution(monkeypatch):
    """An ``optimal_inaccurate`` SDP counts as solved for the V step (a search direction)
    and as failed for a level (what the verifier starts from)."""
    import cvxpy as cp

    class Prob:
        status = cp.OPTIMAL_INACCURATE

        def solve(self, solver):
            pass

    assert sos_sdp._solve(Prob(), "CLARABEL", inaccurate=True)
    assert not sos_sdp._solve(Prob(), "CLARABEL")


@pytest.mark.slow  # ~60-110 s on 2 cores (20 rounds of degree-4 SDPs in 3-D, the verifier)
def test_a_lightly_damped_3d_loop_gets_a_verifiable_sos_v():
    """The Genesio-Tesi system (slowest mode decays at 0.022 per s): the degree-4 V of the
    V-s iteration is certified on its box by the interval verifier, with a set of volume
    above 3 (the simulated true ROA in the box: 5.26; without the relative strictness the
    decrease stayed 'unknown' at every level and only an early iterate, volume 1.03, was
    certified)."""
    from nlyap_opt.kernel.domain import parse_set

    s = systems.load_spec(EXAMPLES / "genesio_tesi_3d.toml")
    box = parse_set({"type": "box", "box": [[-2.0, 2.0]] * 3}, 3)
    res = sos_roa(s, degree=4, inner=0.05, certify=True, domain=box, keep_in=box, log=None)
    assert res.certified and res.V.degree == 4
    X = np.random.default_rng(0).uniform(-2, 2, size=(200000, 3))
    assert 64 * np.mean(res.mask(X)) > 3.0


def test_with_a_domain_the_iteration_measures_only_the_set_inside_it():
    """With keep_in, each round's area is that of {V <= min(1, least V on ∂D)}, whose
    star-shaped part lies in D: on the unit disc no round's area exceeds the disc's (π, up
    to the sampling of ∂D), where the sets themselves grow to several times that."""
    from nlyap_opt.kernel.domain import parse_set

    vdp = systems.get("van_der_pol")
    disc = parse_set({"type": "ball", "radius": 1.0}, 2)
    free = sos_roa(vdp, degree=4, iterations=3, certify=False, log=None)
    inside = sos_roa(vdp, degree=4, iterations=3, certify=False, keep_in=disc, log=None)
    assert max(h["area"] for h in free.history if h["degree"] == 4) > 2 * np.pi
    rounds = [h["area"] for h in inside.history if h["degree"] == 4]
    assert rounds and max(rounds) <= 1.02 * np.pi


def test_a_fast_loop_keeps_its_v_steps_feasible():
    """The strictness also asks V - ε‖x‖² ∈ Σ, so it is capped at half the start's
    λ_min(P) at its level: a loop with modes near -1000 per s still gets a degree-4 V."""
    from nlyap_opt.design.control import lyapunov_matrix
    from nlyap_opt.design.polynomial import Polynomial

    A = np.array([[-1000.0, 500.0], [-500.0, -1000.0]])
    f = [Polynomial.from_dict({(1, 0): -1000.0, (0, 1): 500.0, (3, 0): 1.0}, 2),
         Polynomial.from_dict({(1, 0): -500.0, (0, 1): -1000.0}, 2)]
    res = sos_roa(systems.get("van_der_pol"), degree=4, iterations=2, f=f,
                  V0=lyapunov_matrix(A), certify=False, log=None)
    assert res.V.degree == 4
