"""Compositional certificates (:mod:`nlyap_opt.certification.compositional`): the mathematics on
examples
with known answers, soundness on samples, the re-check, refusals and the command line."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from fractions import Fraction
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

import systems
from nlyap_opt.certification.certificate import CertStatus
from nlyap_opt.certification.compositional import (
    FORMAT,
    certify_compositional,
    check_compositional,
    recheck_compositional,
    save_compositional,
)
from nlyap_opt.interface.cli import main
from nlyap_opt.kernel.errors import ConfigError
from nlyap_opt.kernel.exact import inverse_diagonal, positive_definite

QUIET = {"log": lambda m: None}


def _pair(k: float, box: float = 1.0) -> systems.System:
    """ẋ₁ = -x₁ + k x₂, ẋ₂ = -x₂ + k x₁: two scalar subsystems, eigenvalues -1 ± k."""
    x = ca.SX.sym("x", 2)
    return systems.System("linear_pair", x, None, ca.vertcat(-x[0] + k * x[1], -x[1] + k * x[0]),
                          state_box=[[-box, box]] * 2, subsystems=[(0,), (1,)])


def _vdot(system, cert, X):
    F = system.evaluate(X)
    out = np.zeros(len(X))
    for w, p in zip(cert.weights, cert.pieces):
        xi, fi = X[:, list(p.states)], F[:, list(p.states)]
        out += 2 * w * np.einsum("ni,ij,nj->n", xi, np.asarray(p.P), fi)
    return out


def _points_in(cert, n, rng):
    """Points of {V ≤ c}: random directions scaled to random fractions of the level set."""
    d = cert.domain_box.shape[0]
    X = rng.normal(size=(n, d))
    X *= np.sqrt(cert.level / cert.V(X))[:, None] * rng.uniform(0, 1, (n, 1)) ** (1 / d)
    return X


# ============================================================================ exact algebra
def test_exact_positive_definiteness_and_inverse_diagonal_agree_with_numpy(rng):
    for _ in range(200):
        n = int(rng.integers(1, 6))
        A = rng.normal(size=(n, n))
        S = A + A.T + rng.uniform(-3, 3) * np.eye(n)
        Q = [[Fraction(v) for v in row] for row in S]
        lam = np.linalg.eigvalsh(S)
        if abs(lam).min() > 1e-9:   # away from the boundary float64 decides the same
            assert positive_definite(Q) == (lam.min() > 0)
        if lam.min() > 1e-6:
            inv = inverse_diagonal(Q)
            np.testing.assert_allclose([float(v) for v in inv], np.diag(np.linalg.inv(S)),
                                       rtol=1e-9)
    # a singular PSD matrix is not positive definite (exact, no tolerance)
    assert not positive_definite([[Fraction(1), Fraction(1)], [Fraction(1), Fraction(1)]])


# ============================================================================ known answers
@pytest.mark.parametrize("k", [0.3, 0.6, 0.9])
def test_linear_pair_certifies_below_the_small_gain_bound(k):
    """Scalar V_i = x_i²/2: the local test gives α ≤ 2, β ≥ k²/(2-α) and the comparison
    matrix [[-α, β], [β, -α]] is Hurwitz iff α(2-α) > k²: feasible exactly for |k| < 1."""
    s = _pair(k)
    cert = certify_compositional(s, **QUIET)
    assert cert.certified, cert.reason
    a, b = cert.pieces
    for p in (a, b):
        assert 0 < p.alpha < 2 and p.beta[0] >= k * k / (2 - p.alpha)  # the local test's limit
    assert a.alpha * b.alpha > a.beta[0] * b.beta[0]     # the 2x2 Metzler matrix is Hurwitz
    # no quadratic V decreases faster than twice the slowest eigenvalue's rate
    assert 0 < cert.decay <= 2 * (1 - k) + 1e-12
    # the region is a sublevel set inside the box, and the decrease holds on it
    X = _points_in(cert, 2000, np.random.default_rng(1))
    assert np.all(np.abs(X) <= 1.0)
    assert np.all(_vdot(s, cert, X) <= -cert.decay * cert.V(X) + 1e-12)


@pytest.mark.parametrize("k", [1.0, 1.2, 3.0])
def test_linear_pair_with_too_strong_coupling_is_not_certified(k):
    """k ≥ 1: the small-gain condition fails (k > 1: the origin is unstable)."""
    cert = certify_compositional(_pair(k), **QUIET)
    assert cert.status is CertStatus.NOT_CERTIFIED
    assert "too strong" in cert.reason or "not proved" in cert.reason
    assert not cert.contains(np.zeros((1, 2))).any()


def test_lyznet_10d_on_its_domain_is_certified_and_decreases_on_samples():
    s = systems.get("lyznet_10d")
    assert s.nx == 10 and np.array_equal(s.state_box, [[-1.0, 1.0]] * 10)
    t0 = time.perf_counter()
    cert = certify_compositional(s, **QUIET)
    assert cert.certified, cert.reason
    assert time.perf_counter() - t0 < 60
    assert set(cert.checks) == {"structure", "equilibrium", "positive definite", "local",
                                "comparison", "level"}
    # the neighbours are the published couplings: x9 → x1, x1 → x3, x7 → x5, x2 → x10
    assert [p.neighbours for p in cert.pieces] == [(4,), (0,), (3,), (), (0,)]
    X = _points_in(cert, 20000, np.random.default_rng(0))
    assert np.all(np.abs(X) <= 1.0)
    assert np.all(_vdot(s, cert, X) <= -cert.decay * cert.V(X))
    # the level is the largest the inclusion in D allows (up to float rounding): touching
    # the box along some state
    ext = [np.sqrt(cert.level / w * np.diag(np.linalg.inv(p.P))).max()
           for w, p in zip(cert.weights, cert.pieces)]
    assert max(ext) == pytest.approx(1.0, rel=1e-9) and max(ext) <= 1.0


def test_lyznet_system_on_a_large_box_is_not_certified():
    """On [-10, 10]^10 the quadratic couplings dominate: nothing is claimed."""
    cert = certify_compositional(systems.get("lyznet_10d", radius=10.0), **QUIET)
    assert cert.status is CertStatus.NOT_CERTIFIED and cert.level == 0.0


def test_lyznet_chain_blocks_are_coupled_and_certified():
    s = systems.get("lyznet_chain")
    assert s.nx == 20 and len(s.subsystems) == 10
    f = ca.Function("f", [s.x], [s.f])
    e = np.zeros(20)
    e[0] = 1.0      # x1 of block 1 drives x7 of block 2 through link · x1²
    assert float(f(e)[16]) == pytest.approx(0.1)
    cert = certify_compositional(s, **QUIET)
    assert cert.certified, cert.reason
    assert cert.pieces[8].neighbours == (0,)
    X = _points_in(cert, 5000, np.random.default_rng(2))
    assert np.all(_vdot(s, cert, X) <= -cert.decay * cert.V(X))


# ============================================================================ refusals
def test_systems_that_do_not_admit_the_method_are_refused():
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    with_input = systems.System("with_u", x, u, ca.vertcat(-x[0] + u, -x[1]),
                                state_box=[[-1, 1]] * 2, input_box=[[-1, 1]],
                                subsystems=[(0,), (1,)])
    with pytest.raises(ConfigError, match="without inputs"):
        certify_compositional(with_input, **QUIET)
    with pytest.raises(ConfigError, match="declares no subsystems"):
        certify_compositional(systems.get("van_der_pol"), **QUIET)
    with pytest.raises(ConfigError, match="does not contain the origin in its interior"):
        systems.System("off", x, None, ca.vertcat(-x[0], -x[1]),
                       state_box=[[0.5, 1], [-1, 1]], subsystems=[(0,), (1,)])
    with pytest.raises(ConfigError, match="each index once"):
        systems.System("bad", x, None, ca.vertcat(-x[0], -x[1]), state_box=[[-1, 1]] * 2,
                       subsystems=[(0,), (0, 1)])


def test_non_smooth_or_shifted_systems_are_not_certified():
    x = ca.SX.sym("x", 2)
    kink = systems.System("kink", x, None, ca.vertcat(-x[0] + 0.1 * ca.fabs(x[1]), -x[1]),
                          state_box=[[-1, 1]] * 2, subsystems=[(0,), (1,)])
    cert = certify_compositional(kink, **QUIET)
    assert not cert.certified and "non-smooth" in cert.reason
    shifted = systems.System("shifted", x, None, ca.vertcat(-x[0] + 1e-12, -x[1]),
                             state_box=[[-1, 1]] * 2, subsystems=[(0,), (1,)])
    cert = certify_compositional(shifted, **QUIET)
    assert not cert.certified and "not an equilibrium" in cert.reason


def test_a_float_fold_that_hides_an_offset_is_not_an_equilibrium():
    """``f₁ = −x₁ + ((x₁² + 10¹⁶) + 1) − 10¹⁶``: substituting 0 folds the extra term to 0
    in floats, its real value is 1 (``f(0) ≠ 0``). The equilibrium is decided in exact
    arithmetic: neither the search nor the re-check of a clean system's numbers accepts it."""
    x = ca.SX.sym("x", 2)
    fold = systems.System("fold", x, None,
                          ca.vertcat(-x[0] + ((x[0] ** 2 + 1e16) + 1) - 1e16, -x[1]),
                          state_box=[[-1, 1]] * 2, subsystems=[(0,), (1,)])
    assert float(ca.substitute(fold.f, x, ca.DM.zeros(2))[0]) == 0.0
    cert = certify_compositional(fold, **QUIET)
    assert not cert.certified and "not an equilibrium" in cert.reason
    clean = certify_compositional(_pair(0.0), **QUIET)
    assert clean.certified
    ok, checks, why = check_compositional(fold, clean.pieces, clean.weights, clean.level,
                                          clean.decay)
    assert not ok and "equilibrium" in checks and "not exactly 0" in why


def test_a_decrease_that_fails_by_a_rounding_of_the_product_is_not_proved():
    """One 2-state subsystem ``ẋ = Ax`` whose exact ``AᵀP + PA`` has a (1, 1) entry ``+ε``
    (``V̇ > 0`` along the x₁ axis) while float products round it to ≤ 0: ``P`` and ``A``
    enter the local test as exact rationals, so it fails there (with ``α = 0`` a passing
    local test would fail only later, at the comparison system)."""
    from nlyap_opt.certification.compositional import Piece
    rng = np.random.default_rng(0)
    for _ in range(300):
        Pf = np.diag(rng.uniform(0.5, 2, 2))
        Pf[0, 1] = Pf[1, 0] = rng.uniform(-0.4, 0.4)
        Pq = [[Fraction(v) for v in row] for row in Pf]
        a21, a22 = rng.uniform(-2, 2), -1.0
        a0 = float(-Pq[0][1] * Fraction(a21) / Pq[0][0])
        for k in range(-2, 3):
            a11 = a0 + k * np.spacing(a0)
            a12 = float(-(Pq[0][1] * Fraction(a22) + Pq[1][0] * Fraction(a11)
                          + Pq[1][1] * Fraction(a21)) / Pq[0][0])
            A = [[Fraction(a11), Fraction(a12)], [Fraction(a21), Fraction(a22)]]
            h11 = 2 * sum(Pq[0][j] * A[j][0] for j in range(2))   # (PA + AᵀP)₁₁
            float_h11 = 2 * (Pf[0, 0] * a11 + Pf[0, 1] * a21)
            if h11 > 0 and float_h11 <= 0:
                x = ca.SX.sym("x", 2)
                s = systems.System("rounded", x, None,
                                   ca.DM(np.array([[a11, a12], [a21, a22]])) @ x,
                                   state_box=[[-1, 1]] * 2, subsystems=[(0, 1)])
                piece = Piece((0, 1), (), Pf, 0.0, ())
                ok, checks, why = check_compositional(s, [piece], [1.0], 0.1, 0.1)
                assert not ok and "local" in checks and "not proved" in checks["local"]
                return
    pytest.fail("no case with a positive exact entry and a non-positive float one was found")


def test_a_derivative_that_casadi_folds_to_a_wrong_sign_is_not_trusted():
    """``ẋ₁ = 2((10¹⁶x₁ + x₁) − 10¹⁶x₁) − x₁ = +x₁`` (unstable) while ``ca.jacobian`` folds
    it to ``−1``: the local test encloses the Jacobian along a symbolic seed and refuses."""
    from nlyap_opt.certification.compositional import Piece
    x = ca.SX.sym("x", 2)
    f = ca.vertcat(2 * ((1e16 * x[0] + x[0]) + (-1e16) * x[0]) - x[0], -x[1])
    assert float(ca.jacobian(f, x)[0, 0]) == -1.0
    s = systems.System("folded", x, None, f, state_box=[[-1, 1]] * 2, subsystems=[(0,), (1,)])
    pieces = [Piece((0,), (), np.eye(1), 0.5, ()), Piece((1,), (), np.eye(1), 0.5, ())]
    ok, checks, why = check_compositional(s, pieces, [1.0, 1.0], 0.25, 0.5)
    assert not ok and "not proved" in checks["local"]
    assert not certify_compositional(s, **QUIET).certified


# ============================================================================ re-check
@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    s = systems.get("lyznet_10d")
    cert = certify_compositional(s, **QUIET)
    out = tmp_path_factory.mktemp("comp")
    save_compositional(cert, s, out)
    return out, cert


def _edited(tmp_path, saved, edit):
    d = json.loads((saved[0] / "certificate.json").read_text())
    edit(d)
    (tmp_path / "certificate.json").write_text(json.dumps(d))
    return tmp_path


def test_recheck_of_a_saved_certificate(saved):
    out, cert = saved
    d = json.loads((out / "certificate.json").read_text())
    assert d["format"] == FORMAT and "seconds" not in d and d["assumptions"]
    again = recheck_compositional(out)
    assert again.certified and again.level == cert.level and again.decay == cert.decay


@pytest.mark.parametrize("edit,words", [
    (lambda d: d.update(level=d["level"] * 1.01), "leaves the box"),
    (lambda d: d.update(decay=d["decay"] * 1.5), "comparison system"),
    (lambda d: d["subsystems"][0]["beta"].__setitem__(0, d["subsystems"][0]["beta"][0] / 2),
     "not proved on its box"),
    (lambda d: d["subsystems"][1].update(alpha=d["subsystems"][1]["alpha"] * 1.2),
     "not proved on its box"),
    (lambda d: d["subsystems"][2].update(P=[[1.0, 2.0], [2.0, 1.0]]), "positive definite"),
    (lambda d: d["subsystems"][3].update(neighbours=[]) or d["subsystems"][0].update(
        neighbours=[], beta=[]), "neighbours"),
    (lambda d: d["weights"].__setitem__(0, -1.0), "positive"),
    (lambda d: d.update(assumptions=d["assumptions"][:1]), "assumptions"),
    (lambda d: d.update(status="not certified"), "does not claim"),
    (lambda d: d["subsystems"][0].update(P=[1.0, 0.0]), "wrong shape"),
    (lambda d: d.update(level=float("inf")), "not finite"),
])
def test_recheck_refuses_an_edited_certificate(tmp_path, saved, edit, words):
    cert = recheck_compositional(_edited(tmp_path, saved, edit))
    assert cert.status is CertStatus.NOT_CERTIFIED
    assert words in cert.reason, cert.reason


@pytest.mark.parametrize("edit,words", [
    (lambda d: d.update(version=99), "version"),
    (lambda d: d.update(extra=1), "does not know"),
    (lambda d: d.pop("weights"), "malformed"),
    (lambda d: d["subsystems"][0].update(P="I"), "malformed"),
    (lambda d: d.update(weights=[d["weights"]]), "malformed"),
    (lambda d: d.update(system=7), "'system' is missing"),
])
def test_recheck_fails_closed_on_unknown_or_malformed_files(tmp_path, saved, edit, words):
    with pytest.raises(ConfigError, match=words):
        recheck_compositional(_edited(tmp_path, saved, edit))


def test_recheck_against_another_system_is_refused(saved):
    other = systems.get("lyznet_10d", radius=0.5)
    cert = recheck_compositional(saved[0], system=other)
    assert not cert.certified and "not the certified system" in cert.reason
    # the numbers alone, for a system whose box is smaller: still exact (the level check
    # is about the certificate's own box)
    ok, checks, why = check_compositional(other, saved[1].pieces, saved[1].weights,
                                          saved[1].level, saved[1].decay, split=saved[1].split)
    assert not ok and "level" in checks and "leaves the box" in why


# ============================================================================ command line
def test_cli_run_and_verify(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "lyznet_10d", "--known-dynamics", "--out", str(out)]) == 0
    assert "certified: level" in capsys.readouterr().out
    assert main(["verify", "--certificate", str(out)]) == 0
    assert capsys.readouterr().out.startswith("certified")
    assert main(["verify", "--certificate", str(out), "--system", "lyznet_10d"]) == 0
    assert main(["verify", "--certificate", str(out), "--system", "lyznet_chain"]) == 2
    # the same input gives the same certificate bit for bit (timings live beside it)
    again = tmp_path / "again"
    assert main(["run", "lyznet_10d", "--known-dynamics", "--out", str(again)]) == 0
    assert (again / "certificate.json").read_bytes() == (out / "certificate.json").read_bytes()
    assert (again / "timings.json").exists()
    d = json.loads((out / "certificate.json").read_text())
    d["level"] *= 2
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "certificate.json").write_text(json.dumps(d))
    assert main(["verify", "--certificate", str(tmp_path / "bad")]) == 2


@pytest.mark.parametrize("argv,words", [
    (["run", "lyznet_10d", "--seeds", "2"], "drop --seeds"),
    (["run", "lyznet_chain", "--known-dynamics", "--seeds", "2"], "drop --seeds"),
    (["run", "lyznet_chain", "--known-dynamics", "--preset", "fast"], "drop --preset"),
])
def test_cli_refusals_are_one_line_exit_3(tmp_path, capsys, argv, words):
    assert main(argv + ["--out", str(tmp_path / "o")]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0] and "Traceback" not in err[0]


def test_neural_tools_refuse_a_compositional_certificate(saved, capsys):
    from nlyap_opt.certification.certificate import recheck_run

    with pytest.raises(ConfigError, match="compositional certificate"):
        recheck_run(saved[0])


SPEC = """
name = "two_oscillators"
states = ["a1", "a2", "b1", "b2"]
state_box = [[-1, 1], [-1, 1], [-1, 1], [-1, 1]]
subsystems = [["a1", "a2"], ["b1", "b2"]]

[rhs]
a1 = "-a1 + 0.5*a2 + 0.2*b1^2"
a2 = "-0.5*a1 - a2"
b1 = "-b1 + b2"
b2 = "-b1 - b2 + 0.3*sin(a2)"
"""


def test_spec_file_with_subsystems_runs_and_rechecks(tmp_path, capsys):
    spec = tmp_path / "osc.toml"
    spec.write_text(SPEC)
    s = systems.load_spec(spec)
    assert s.subsystems == ((0, 1), (2, 3))
    assert s.summary()["subsystems"] == [["a1", "a2"], ["b1", "b2"]]
    out = tmp_path / "out"
    assert main(["run", str(spec), "--known-dynamics", "--out", str(out)]) == 0
    assert main(["verify", "--certificate", str(out)]) == 0     # the spec named inside
    spec.write_text(SPEC.replace("0.3*sin", "0.31*sin"))
    assert main(["verify", "--certificate", str(out)]) == 2     # f changed: refused
    assert "not the certified system" in capsys.readouterr().out


@pytest.mark.parametrize("edit,words", [
    (lambda t: t.replace('["b1", "b2"]]', '["b1"]]'), "missing: ['b2']"),
    (lambda t: t.replace('["b1", "b2"]]', '["b1", "b2", "a1"]]'), "twice: ['a1']"),
    (lambda t: t.replace('["b1", "b2"]]', '["b1", "c2"]]'), "'c2' is not a state"),
    (lambda t: t.replace('subsystems = [["a1", "a2"], ["b1", "b2"]]', 'subsystems = "a1"'),
     "list of lists"),
    (lambda t: t.replace('states = ["a1", "a2", "b1", "b2"]',
                         'states = ["a1", "a2", "b1", "b2"]\ninputs = ["u"]\n'
                         'input_box = [[-1, 1]]'), "without inputs"),
])
def test_spec_file_subsystem_errors_are_one_line(tmp_path, capsys, edit, words):
    spec = tmp_path / "osc.toml"
    spec.write_text(edit(SPEC))
    assert main(["run", str(spec), "--known-dynamics", "--out", str(tmp_path / "o")]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err


@pytest.mark.slow
def test_end_to_end_20d_chain_from_a_fresh_process(tmp_path):
    """`nlyap run lyznet_chain --known-dynamics` then `nlyap verify --certificate`, each in a
    fresh interpreter, within the 10-minute budget of the acceptance test."""
    out = tmp_path / "chain"
    t0 = time.perf_counter()
    run = subprocess.run([sys.executable, "-m", "nlyap_opt.interface.cli", "run", "lyznet_chain",
                          "--known-dynamics", "--out", str(out)], capture_output=True,
                         text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    chk = subprocess.run([sys.executable, "-m", "nlyap_opt.interface.cli", "verify",
                          "--certificate",
                          str(out)], capture_output=True, text=True, timeout=600)
    assert chk.returncode == 0 and chk.stdout.startswith("certified"), chk.stderr
    assert time.perf_counter() - t0 < 600
    d = json.loads((out / "certificate.json").read_text())
    assert len(d["subsystems"]) == 10 and len(d["domain_box"]) == 20


# ============================================================================ data setting
def _coupled() -> systems.System:
    """Two oscillators with non-polynomial couplings (f(0) = 0, smooth everywhere)."""
    x = ca.SX.sym("x", 4)
    f = ca.vertcat(-x[0] + 0.5 * x[1] + 0.2 * ca.sin(x[2]) * x[3],
                   -0.5 * x[0] - x[1] + 0.1 * ca.tanh(x[0]) * x[1],
                   -x[2] + x[3],
                   -x[2] - x[3] + 0.3 * ca.sin(x[1]) ** 2)
    return systems.System("coupled_pair", x, None, f, state_box=[[-1.5, 1.5]] * 4,
                          subsystems=[(0, 1), (2, 3)])


def _mean_jacobian(fun, y):
    """``∫₀¹ J(ty) dt`` by 30-node Gauss–Legendre quadrature (float)."""
    t, w = np.polynomial.legendre.leggauss(30)
    t, w = 0.5 * (t + 1), 0.5 * w
    return sum(wk * np.array(fun(tk * y)) for tk, wk in zip(t, w))


@pytest.mark.parametrize("split", [1, 2])
def test_data_enclosure_holds_the_mean_jacobian_and_needs_the_hessian_bound(split, rng):
    """Every piece's ``[C − R, C + R]`` holds ``J̄(y) = ∫₀¹ J(ty) dt`` at random ``y`` of the
    piece (padded rows 0), from the samples with ``H`` and from the interval Jacobian
    (``H = None``); with ``H = 0`` (the finite differences alone) it does not."""
    from nlyap_opt.certification.compositional import (
        _block_function,
        _piece_enclosures,
        _structure,
        hessian_bound,
    )
    from nlyap_opt.certification.roa import split_boxes
    s = _coupled()
    parts = s.subsystems
    nbrs = _structure(s, parts)
    missed = 0
    for i in range(len(parts)):
        idx, y, fi = _block_function(s, parts, nbrs, i)
        m, ni = len(idx), len(parts[i])
        J = ca.Function("J", [y], [ca.vertcat(ca.jacobian(fi, y), ca.DM.zeros(m - ni, m))])
        H, why = hessian_bound(s, parts, nbrs, i)
        assert H is not None and H.shape == (ni, m, m) and np.all(H >= 0), why
        box = s.state_box[idx]
        lo, hi = box[None, :, 0].copy(), box[None, :, 1].copy()
        if split > 1:
            lo, hi, _ = split_boxes(lo, hi, list(range(m)), split)
        for H_used, must_hold in ((H, True), (None, True), (np.zeros_like(H), False)):
            encl, why = _piece_enclosures(s, parts, nbrs, i, H_used, split)
            assert len(encl) == len(lo), why
            for (C, R), bl, bh in zip(encl, lo, hi):
                C = np.array(C, dtype=float)
                R = np.array(R, dtype=float)
                for yv in rng.uniform(bl, bh, size=(8, m)):
                    Jb = _mean_jacobian(J, yv)
                    inside = np.all(np.abs(Jb - C) <= R + 1e-12 * (1 + np.abs(C)))
                    if must_hold:
                        assert inside, (i, yv, Jb, C, R)
                    else:
                        missed += not inside
                if must_hold:
                    assert R.max() < 1.0           # an enclosure, not everything
    assert missed > 0   # the H terms are what makes it hold


def test_data_setting_certifies_and_v_decreases_on_samples(rng):
    """``nlyap run`` without ``--known-dynamics`` on a system with subsystems: the data
    setting certifies LyZNet's 10-D system with a level near the known setting's, and
    ``dV/dt ≤ −γ V`` holds at random points of the set with the true f."""
    s = systems.get("lyznet_10d")
    known = certify_compositional(s, **QUIET)
    data = certify_compositional(s, setting="data", **QUIET)
    assert data.certified and data.setting == "data" and data.split in (1, 2, 4)
    assert "sampled f" in data.summary()
    assert all(p.hessian is not None for p in data.pieces)
    vol = [sum(0.5 * len(p.states) * np.log(c.level / w) - 0.5 * np.log(np.linalg.det(p.P))
               for w, p in zip(c.weights, c.pieces)) for c in (known, data)]
    assert vol[1] > vol[0] - np.log(2)             # within a factor 2 of the known volume
    X = _points_in(data, 4000, rng)
    assert np.all(_vdot(s, data, X) <= -data.decay * data.V(X) * (1 - 1e-9))


@pytest.fixture(scope="module")
def saved_data(tmp_path_factory):
    s = _coupled()
    cert = certify_compositional(s, setting="data", **QUIET)
    assert cert.certified
    out = tmp_path_factory.mktemp("comp_data")
    save_compositional(cert, s, out)
    return out, cert, s


def test_recheck_of_a_data_certificate(saved_data):
    out, cert, s = saved_data
    d = json.loads((out / "certificate.json").read_text())
    assert d["setting"] == "data" and d["split"] == cert.split
    assert all("hessian_bound" in p for p in d["subsystems"])
    again = recheck_compositional(out, system=s)
    assert again.certified and again.level == cert.level and again.setting == "data"


def _lower_hessian(d):
    H = np.array(d["subsystems"][0]["hessian_bound"])
    k = np.unravel_index(np.argmax(H), H.shape)
    H[k] /= 2
    d["subsystems"][0]["hessian_bound"] = H.tolist()


@pytest.mark.parametrize("edit,words", [
    (_lower_hessian, "below the simulator's"),
    (lambda d: d["subsystems"][1]["hessian_bound"][0][0].__setitem__(0, -1.0), "≥ 0"),
    (lambda d: d["subsystems"][1].pop("hessian_bound"), "≥ 0"),
    (lambda d: d.update(assumptions=d["assumptions"][1:]), "assumptions"),
])
def test_recheck_refuses_an_edited_data_certificate(tmp_path, saved_data, edit, words):
    cert = recheck_compositional(_edited(tmp_path, saved_data, edit), system=saved_data[2])
    assert cert.status is CertStatus.NOT_CERTIFIED
    assert words in cert.reason, cert.reason


@pytest.mark.parametrize("edit,words", [
    (lambda d: d.update(split=3), "'split' must be one of"),
    (lambda d: d.update(split=True), "'split' must be one of"),
    (lambda d: d.update(setting="guessed"), "'setting' must be one of"),
    (lambda d: d.pop("setting"), "'setting' must be one of"),
])
def test_recheck_refuses_a_malformed_data_certificate(tmp_path, saved_data, edit, words):
    with pytest.raises(ConfigError, match=words):
        recheck_compositional(_edited(tmp_path, saved_data, edit), system=saved_data[2])


def test_a_known_certificate_with_data_fields_is_refused(tmp_path, saved):
    def add_h(d):
        d["subsystems"][0]["hessian_bound"] = [[[0.0] * 4] * 4] * 2
    cert = recheck_compositional(_edited(tmp_path, saved, add_h))
    assert not cert.certified and "second-derivative bounds" in cert.reason
    with pytest.raises(ConfigError, match="'split' must be one of"):
        recheck_compositional(_edited(tmp_path, saved, lambda d: d.update(split=3)))


def test_cli_run_without_known_dynamics_certifies_from_samples(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "lyznet_10d", "--out", str(out)]) == 0
    assert "sampled f with a second-derivative bound" in capsys.readouterr().out
    assert json.loads((out / "certificate.json").read_text())["setting"] == "data"
    report = (out / "report.md").read_text()
    assert "**Status: certified" in report and "## Assumptions" in report
    assert all(a in report for a in json.loads((out / "certificate.json").read_text())
               ["assumptions"])
    assert (out / "subsystems.png").stat().st_size > 1000
    assert main(["verify", "--certificate", str(out)]) == 0
    assert capsys.readouterr().out.startswith("certified")


# ============================================================================ a simulator
EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "blackbox_oscillators.toml"


def _simulator(hessian=0.2, shift=0.0, depends=True, lie=0.0, mixed=0.0, noise=None,
               fail=None) -> systems.System:
    """The example's three oscillators as a callable, with other declarations or ``f(0)``;
    ``lie``: a2' also reads c1 (declared: a1, a2 only); ``mixed``: a1' gains
    ``mixed·a1·a2`` (pure second derivatives 0); ``noise``: the declared sample error;
    ``fail``: an exception the simulator raises away from the origin."""
    ex = systems.load_spec(EXAMPLE)
    decl = ex.declarations
    fun = ex._callable

    def f(X, U):
        if fail is not None and np.any(X != 0):
            raise fail
        F = fun(X, U) + shift
        F[:, 1] += lie * X[:, 4]
        F[:, 0] += mixed * X[:, 0] * X[:, 1]
        return F

    return systems.System.from_callable(
        "oscillators", f, nx=6, state_box=ex.state_box,
        state_names=ex.state_names, subsystems=ex.subsystems,
        declarations=None if hessian is None else systems.Declarations(
            hessian=hessian, depends_on=dict(decl.depends_on) if depends else None,
            sample_error=noise))


def test_a_simulator_is_certified_from_its_declarations(rng):
    from nlyap_opt.certification.compositional import ASSUMPTIONS_DECLARED
    s = _simulator()
    cert = certify_compositional(s, setting="data", **QUIET)
    assert cert.certified and cert.assumptions == ASSUMPTIONS_DECLARED
    assert cert.summary().startswith("certified under the declared assumptions: hessian")
    assert cert.checks["structure"].startswith("declared")
    # every stored bound is the declared H, 0 where depends_on rules a variable out
    H0 = cert.pieces[0].hessian          # a1' reads a1, a2, c1, c2; a2' only a1, a2
    assert H0.shape == (2, 4, 4) and H0[0].max() == 0.2 and np.all(H0[1][2:, :] == 0)
    # the example declares one H per state derivative (0 for the linear ones): the linear
    # rows then pay nothing, and the decay rate is far larger than with one H for all
    ex = systems.load_spec(EXAMPLE)
    per = certify_compositional(ex, setting="data", **QUIET)
    assert per.certified and np.all(per.pieces[0].hessian[1] == 0)
    assert per.pieces[0].hessian[0].max() == ex.declarations.hessian_of(0) == 0.15
    assert per.decay > 10 * cert.decay
    X = _points_in(cert, 4000, rng)
    assert np.all(_vdot(s, cert, X) <= -cert.decay * cert.V(X) * (1 - 1e-9))
    # without depends_on every derivative may read every state: one 6-D box per subsystem
    wide = certify_compositional(_simulator(depends=False), setting="data", **QUIET)
    assert all(len(p.neighbours) == 2 for p in wide.pieces)


@pytest.mark.parametrize("kw,setting,words", [
    ({}, "known", "needs the model f"),
    ({"hessian": None}, "data", "declare hessian"),
    ({"hessian": 0.1}, "data", "refutes its declared hessian"),
    ({"lie": 1e-6}, "data", "refutes its declared depends_on: a2'"),
    ({"mixed": 1.0}, "data", "second difference of a1' along a1 and a2"),
    ({"noise": 1e-6}, "data", "cannot show"),
    ({"fail": ZeroDivisionError("boom")}, "data", "failed .ZeroDivisionError: boom."),
])
def test_a_simulator_without_the_declarations_it_needs_is_refused(kw, setting, words):
    with pytest.raises(ConfigError, match=words):
        certify_compositional(_simulator(**kw), setting=setting, **QUIET)


def test_a_simulator_whose_origin_is_not_an_exact_equilibrium_is_not_certified():
    cert = certify_compositional(_simulator(shift=1e-12), setting="data", **QUIET)
    assert not cert.certified and "not an exact equilibrium" in cert.reason


def test_cli_certifies_a_simulator_and_rechecks_it_only_when_allowed(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", str(EXAMPLE), "--out", str(out)]) == 0
    assert "certified under the declared assumptions" in capsys.readouterr().out
    assert main(["verify", "--certificate", str(out)]) == 3          # never runs the factory
    assert "--allow-factory" in capsys.readouterr().err
    assert main(["verify", "--certificate", str(out), "--system", str(EXAMPLE),
                 "--allow-factory"]) == 0
    d = json.loads((out / "certificate.json").read_text())
    d["subsystems"][1]["hessian_bound"][1][0][0] = 0.1              # below the declared H
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "certificate.json").write_text(json.dumps(d))
    assert main(["verify", "--certificate", str(tmp_path / "bad"), "--system", str(EXAMPLE),
                 "--allow-factory"]) == 2


@pytest.mark.parametrize("edit", [
    lambda d: d["subsystems"][0]["hessian_bound"][0][2].__setitem__(2, "0.3"),
    lambda d: d["subsystems"][0]["hessian_bound"][0][2].__setitem__(2, True),
    lambda d: d.update(level=str(d["level"])),
    lambda d: d["subsystems"][0].update(states=["0", "1"]),
    lambda d: d["subsystems"][0].update(alpha=True),
])
def test_recheck_refuses_numbers_that_are_not_json_numbers(tmp_path, edit):
    """Strings and booleans where a certificate writes numbers are edits (exit 3)."""
    s = systems.get("lyznet_10d")
    out = tmp_path / "run"
    save_compositional(certify_compositional(s, setting="data", **QUIET), s, out)
    d = json.loads((out / "certificate.json").read_text())
    edit(d)
    (out / "certificate.json").write_text(json.dumps(d))
    with pytest.raises(ConfigError, match="malformed"):
        recheck_compositional(out)


def test_recheck_refuses_a_split_beyond_the_total_pieces():
    """A split whose pieces over all subsystems pass MAX_TOTAL_PIECES (lyznet_10d at 4 per
    axis: 5 boxes of 4⁴) is refused before any work; the run's own split is proved."""
    from nlyap_opt.certification.compositional import MAX_TOTAL_PIECES
    s = systems.get("lyznet_10d")
    cert = certify_compositional(s, setting="data", **QUIET)
    assert cert.certified and 5 * 4 ** 4 > MAX_TOTAL_PIECES
    args = (s, cert.pieces, cert.weights, cert.level, cert.decay)
    ok, checks, why = check_compositional(*args, setting="data", split=4)
    assert not ok and "pieces in all" in why
    assert check_compositional(*args, setting="data", split=cert.split)[0]


def test_a_large_simulator_is_bound_by_seeded_points_not_a_grid():
    """Past 12 variables a callable's binding evaluates it at CALLABLE_POINTS seeded points
    (2^d grid nodes would be millions): the same binding twice, another f another binding."""
    from nlyap_opt.certification.certificate import CALLABLE_POINTS, system_binding
    rows = []

    def make(scale):
        def f(X, U):
            rows.append(len(X))
            return -scale * X
        return systems.System.from_callable("wide", f, nx=16, state_box=[[-1, 1]] * 16)

    a = system_binding(make(1.0))
    assert rows == [1, CALLABLE_POINTS]        # the equilibrium check, then the binding
    assert system_binding(make(1.0)) == a and system_binding(make(2.0)) != a
