"""From certificate to robot: ``nlyap simulate``, ``nlyap export`` and the CLF-QP filter.

Run directories: the fast Van der Pol run (known f, 2-D, no input) and a cartpole (4-D,
one input) certificate of the LQR quadratic under the linear LQR feedback on a small ball,
proved with the verifier's second-order form and saved like a run's.
"""

from __future__ import annotations

import ctypes
import hashlib
import json
import shutil
import subprocess

import casadi as ca
import numpy as np
import pytest

import systems
from nlyap_opt.certification.certificate import (
    RoaProblem,
    certify_roa,
    save_certificate,
    sha256_file,
)
from nlyap_opt.deployment.deploy import load_run, simulate_run
from nlyap_opt.deployment.filter import (
    ClfQpFilter,
    check_control_affine,
    load_nominal,
    write_linear_nominal,
)
from nlyap_opt.design.control import linear_controller, lqr, quadratic_lyapunov
from nlyap_opt.interface.cli import main
from nlyap_opt.kernel.errors import ConfigError
from nlyap_opt.kernel.walker import evaluate
from nlyap_opt.workflow.configs import get_config
from nlyap_opt.workflow.pipeline import run as run_pipeline

QUIET = dict(log=lambda m: None)


@pytest.fixture(scope="module")
def vdp_run(fast_run):
    d, cert = fast_run("van_der_pol", known=True)   # the session's run (test_run's too)
    assert cert["status"] == "certified"
    return d


@pytest.fixture(scope="module")
def cartpole_run(tmp_path_factory):
    d = tmp_path_factory.mktemp("cartpole")
    s = systems.get("cartpole")
    res = lqr(s)
    ev = np.linalg.eigvalsh(res.P)
    r = 0.05
    level = 0.9 * ev[0] * r**2
    eps = 0.5 * np.sqrt(level / ev[-1])
    problem = RoaProblem(s, quadratic_lyapunov(res.P), linear_controller(s, res.K), inner=eps,
                         outer=r, verify_options={"max_boxes": 100_000, "second_order": True})
    cert = certify_roa(problem, level, **QUIET)
    assert cert.certified, cert.reason
    save_certificate(cert, problem, d)
    return d


def _points(run, n, seed=1):
    return run.sample(n, np.random.default_rng(seed))


# ------------------------------------------------------------------ loading and sampling
def test_load_run_rechecks_and_refuses_a_changed_artifact(vdp_run, tmp_path):
    run = load_run(vdp_run, **QUIET)
    assert run.certificate.certified and run.sha256 == sha256_file(vdp_run / "certificate.json")
    bad = tmp_path / "bad"
    shutil.copytree(vdp_run, bad)
    v = json.loads((bad / "V.json").read_text())
    v["layers"][0]["bias"][0] += 1e-3
    (bad / "V.json").write_text(json.dumps(v))
    with pytest.raises(ConfigError, match="changed since the certificate"):
        load_run(bad, **QUIET)


def test_an_edited_level_is_not_used(vdp_run, tmp_path, capsys):
    """certificate.json itself carries no hash: its level is proved again, not trusted."""
    bad = tmp_path / "bad"
    shutil.copytree(vdp_run, bad)
    d = json.loads((bad / "certificate.json").read_text())
    d["level"] *= 20
    (bad / "certificate.json").write_text(json.dumps(d))
    assert main(["simulate", str(bad), "--points", "5", "--out", str(tmp_path / "s")]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "re-verif" in err[0] and "rerun `nlyap run`" in err[0]


def test_samples_are_seeded_and_inside(vdp_run):
    run = load_run(vdp_run, **QUIET)
    a, b = _points(run, 500, 3), _points(run, 500, 3)
    np.testing.assert_array_equal(a, b)
    assert run.contains(a).all()
    assert not np.array_equal(a, _points(run, 500, 4))
    out = run.sample(200, np.random.default_rng(0), inside=False)
    assert not run.contains(out).any() and run.problem.domain.contains(out).all()


# ------------------------------------------------------------------ simulate
def _check_simulation(out, points):
    z = np.load(out / "trajectories.npz")
    X, V = z["inside"], z["V_inside"]
    assert X.shape[1] == points and z["stayed"].all() and z["converged"].all()
    summary = json.loads((out / "simulate.json").read_text())
    assert summary["stayed"] == summary["converged"] == points and not summary["failures"]
    png = (out / "simulate.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000
    return X, V, summary


def test_simulate_van_der_pol(vdp_run, tmp_path):
    out = tmp_path / "sim"
    assert main(["simulate", str(vdp_run), "--points", "40", "--horizon", "25",
                 "--out", str(out)]) == 0
    X, V, summary = _check_simulation(out, 40)
    run = load_run(vdp_run, **QUIET)
    assert summary["certificate_sha256"] == run.sha256
    assert np.all(V[0] <= run.level) and np.all(V[-1] < 1e-6 * run.level)
    # V decreases along every trajectory (up to the last steps, at machine precision)
    early = V[: len(V) // 2]
    assert np.all(np.diff(early, axis=0) <= 1e-12 * run.level)
    # the same command gives the same trajectories (seeded)
    out2 = tmp_path / "sim2"
    assert main(["simulate", str(vdp_run), "--points", "40", "--horizon", "25",
                 "--out", str(out2)]) == 0
    np.testing.assert_array_equal(np.load(out2 / "trajectories.npz")["inside"], X)


def test_simulate_cartpole_4d(cartpole_run, tmp_path):
    out = tmp_path / "sim"
    assert main(["simulate", str(cartpole_run), "--points", "30", "--horizon", "20",
                 "--out", str(out)]) == 0
    X, _, _ = _check_simulation(out, 30)
    assert X.shape[2] == 4


def test_a_trajectory_that_leaves_is_reported(cartpole_run):
    """The checks can fail: with the input held at zero the pole falls out of the set."""
    run = load_run(cartpole_run, **QUIET)
    res = simulate_run(run, points=20, horizon=5.0, feedback=lambda x: np.zeros((len(x), 1)))
    assert res.violated and not res.stayed.all()
    assert any("left the certified set" in f for f in res.failures)


def test_a_step_too_coarse_is_not_a_contradiction(vdp_run, tmp_path, capsys):
    """RK4 at --dt 5 blows up on Van der Pol's closed loop: the trajectories that seem to
    leave are integrated again in finer steps, where they stay and converge (kept so, and
    counted); with more of them than are integrated again, the step is refused (exit 3,
    lower --dt), never reported as a contradiction of the certificate (exit 1)."""
    from nlyap_opt.deployment.deploy import REFINE_AT_MOST

    run = load_run(vdp_run, **QUIET)
    res = simulate_run(run, points=5, horizon=20.0, dt=5.0)
    assert not res.violated and res.converged.all() and res.refined >= 1
    assert "integrated again" in res.summary()
    fine = simulate_run(run, points=5, horizon=20.0, dt=5.0 / 64)
    np.testing.assert_allclose(res.inside[-1], fine.inside[-1], rtol=0, atol=1e-9)  # at t = 20
    with pytest.raises(ConfigError, match="too coarse"):
        simulate_run(run, points=4 * REFINE_AT_MOST, horizon=20.0, dt=5.0)
    # a run that claims nothing (a safety filter's unfiltered nominal) is not integrated
    # again, and its step is not judged
    raw = simulate_run(run, points=4 * REFINE_AT_MOST, horizon=20.0, dt=5.0, confirm=False)
    assert raw.violated and raw.refined == 0
    assert main(["simulate", str(vdp_run), "--dt", "5", "--horizon", "20", "--points",
                 str(4 * REFINE_AT_MOST), "--out", str(tmp_path / "o")]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--dt 5 is too coarse" in err[0] and "lower --dt" in err[0]


def test_the_default_horizon_follows_a_slow_closed_loop(vdp_run, monkeypatch):
    """Without --horizon a closed loop whose slowest mode at the origin decays slowly is
    simulated long enough to converge (a damped Duffing oscillator with damping 0.5 ended
    'not converged' at 20 s): 1.5·ln(R/tol)/σ, at most ten times 20 s; a fast loop keeps
    20 s."""
    import math

    from nlyap_opt.deployment.deploy import SIM_HORIZON, CertifiedRun, default_horizon

    run = load_run(vdp_run, **QUIET)
    assert default_horizon(run) == SIM_HORIZON        # Van der Pol's loop decays fast enough
    box = run.sample_box()
    R, tol = float(np.linalg.norm(np.max(np.abs(box), axis=1))), 1e-2 * run.certificate.inner
    for sigma in (0.05, 0.001):
        monkeypatch.setattr(CertifiedRun, "vector_field",
                            lambda self, which, feedback=None, s=sigma: (lambda x: -s * x))
        want = min(max(SIM_HORIZON, 1.5 * math.log(R / tol) / sigma), 10 * SIM_HORIZON)
        assert default_horizon(run) == pytest.approx(want, rel=1e-6) and want > SIM_HORIZON


def test_simulate_refuses_bad_input(vdp_run, tmp_path, capsys):
    cases = [
        ["simulate", str(tmp_path / "nope"), "--out", str(tmp_path / "o")],
        ["simulate", str(vdp_run), "--points", "0", "--out", str(tmp_path / "o")],
        ["simulate", str(vdp_run), "--filter", "clf-qp", "--out", str(tmp_path / "o")],
        ["simulate", str(vdp_run), "--learned", "--out", str(tmp_path / "o")],
        ["simulate", str(vdp_run), "--decay", "0.5", "--out", str(tmp_path / "o")],
    ]
    for argv in cases:
        assert main(argv) == 3, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("nlyap: error:"), err


# ------------------------------------------------------------------ export
def _compile(out):
    cc = shutil.which("cc")
    if cc is None:
        pytest.skip("no C compiler (cc) on this machine")
    lib = out / "libnlyap.so"
    subprocess.run([cc, "-std=c99", "-Wall", "-Werror", "-O2", "-shared", "-fPIC",
                    str(out / "nlyap.c"), "-o", str(lib), "-lm"], check=True,
                   capture_output=True)
    return ctypes.CDLL(str(lib))


def _close(c, p, what):
    """Per point, relative in the Euclidean norm (a gradient's component may cancel), with a
    floor of 10⁻³ of the largest norm on the sample: where a sum cancels to almost 0 (κ = −Kx
    next to the plane Kx = 0) its relative error is not fixed by float64 inputs."""
    c, p = c.reshape(len(c), -1), p.reshape(len(p), -1)
    norms = np.linalg.norm(p, axis=1)
    scale = np.maximum(norms, 1e-3 * norms.max())
    rel = np.linalg.norm(c - p, axis=1) / scale
    assert rel.max() <= 1e-12, (what, rel.max())


@pytest.mark.parametrize("which", ["vdp_run", "cartpole_run"])
def test_export_c_compiles_and_matches_python(which, request, tmp_path):
    d = request.getfixturevalue(which)
    out = tmp_path / "c"
    assert main(["export", str(d), "--format", "c", "--out", str(out)]) == 0
    run = load_run(d, **QUIET)
    header = (out / "nlyap.h").read_text()
    assert hashlib.sha256((d / "certificate.json").read_bytes()).hexdigest() in header
    assert float.fromhex(header.split("#define NLYAP_LEVEL ")[1].split()[0]) == run.level
    lib = _compile(out)
    nx, nu = run.system.nx, run.system.nu
    box = run.sample_box()
    rng = np.random.default_rng(7)
    # half in the certified set, half uniform in a box 1.2 times the sampler's
    wide = 0.5 * (box[:, 0] + box[:, 1]) + 1.2 * (box[:, 1] - box[:, 0]) * (
        rng.random((5_000, nx)) - 0.5)
    pts = np.vstack([run.sample(5_000, rng), wide])
    x = ca.MX.sym("x", nx)
    gradV = ca.Function("g", [x], [ca.gradient(run.problem.V_expr(x), x)])
    py_V, py_g = run.V(pts), evaluate(gradV, [pts])[0]
    py_k, py_m = run.kappa(pts), run.contains(pts)
    dbl = ctypes.POINTER(ctypes.c_double)
    c_V, c_g = np.empty(len(pts)), np.empty((len(pts), nx))
    c_k, c_m = np.empty((len(pts), nu)), np.empty(len(pts), bool)
    v, g, k = np.empty(1), np.empty(nx), np.empty(max(nu, 1))
    for i, p in enumerate(pts):
        xp = np.ascontiguousarray(p).ctypes.data_as(dbl)
        assert lib.nlyap_V(xp, v.ctypes.data_as(dbl)) == 0
        assert lib.nlyap_grad_V(xp, g.ctypes.data_as(dbl)) == 0
        assert lib.nlyap_kappa(xp, k.ctypes.data_as(dbl)) == 0
        c_V[i], c_g[i], c_k[i], c_m[i] = v[0], g, k[:nu], lib.nlyap_in_certified_set(xp)
    _close(c_V, py_V, "V")
    _close(c_g, py_g, "grad V")
    if nu:
        _close(c_k, py_k, "kappa")
    # membership: equal except within rounding of the level
    differ = c_m != py_m
    assert not differ[np.abs(py_V - run.level) > 1e-12 * run.level].any()
    assert 0.05 < py_m.mean() < 0.95      # both answers occur on the sample


def test_the_header_strings_are_c_for_any_name(tmp_path):
    """The header's strings (the system's name, the domain's JSON) were written by
    json.dumps, whose \\ud83d escapes are not C: a non-BMP name broke every use of the
    macro. Each literal, compiled and printed, gives the UTF-8 bytes of the text."""
    from nlyap_opt.deployment.export import _c_string

    cc = shutil.which("cc")
    if cc is None:
        pytest.skip("no C compiler (cc) on this machine")
    texts = ["lin_\U0001F600", 'a"b\\c', "x??=y", "é\tz", '{"type": "ball"}']
    src = tmp_path / "s.c"
    src.write_text("#include <stdio.h>\nint main(void) {\n" + "".join(
        f"  fputs({_c_string(t)}, stdout); putchar(0);\n" for t in texts) + "  return 0;\n}\n")
    exe = tmp_path / "s"
    subprocess.run([cc, "-std=c99", "-Wall", "-Werror", "-pedantic", str(src), "-o", str(exe)],
                   check=True, capture_output=True)
    out = subprocess.run([str(exe)], check=True, capture_output=True).stdout
    assert out.split(b"\0")[:-1] == [t.encode("utf-8") for t in texts]


def test_an_exported_source_does_not_compile_beside_another_exports_header(vdp_run,
                                                                           tmp_path):
    cc = shutil.which("cc")
    if cc is None:
        pytest.skip("no C compiler (cc) on this machine")
    out = tmp_path / "c"
    assert main(["export", str(vdp_run), "--format", "c", "--out", str(out)]) == 0
    h = out / "nlyap.h"
    h.write_text(h.read_text().replace("#define NLYAP_EXPORT_", "#define NLYAP_EXPORT_0"))
    r = subprocess.run([cc, "-std=c99", "-c", str(out / "nlyap.c"), "-o",
                        str(tmp_path / "n.o")], capture_output=True, text=True)
    assert r.returncode != 0 and "not the header of this nlyap.c" in r.stderr


def test_a_failed_export_leaves_the_old_pair(vdp_run, tmp_path, monkeypatch, capsys):
    """nlyap.h and nlyap.c are written together: a full disk while writing nlyap.c left a new
    header beside a truncated source; now both stay as they were."""
    import builtins

    out = tmp_path / "c"
    out.mkdir()
    (out / "nlyap.h").write_text("old h")
    (out / "nlyap.c").write_text("old c")
    real_open = builtins.open

    def full_on_c(file, mode="r", *a, **k):
        if "nlyap.c" in str(file) and "x" in mode:
            raise OSError(28, "No space left on device")
        return real_open(file, mode, *a, **k)

    monkeypatch.setattr(builtins, "open", full_on_c)
    assert main(["export", str(vdp_run), "--format", "c", "--out", str(out)]) == 3
    assert "No space left" in capsys.readouterr().err
    assert (out / "nlyap.h").read_text() == "old h" and (out / "nlyap.c").read_text() == "old c"
    assert sorted(p.name for p in out.iterdir()) == ["nlyap.c", "nlyap.h"]


def test_export_onnx_refused_without_the_package(vdp_run, tmp_path, capsys, monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec",
                        lambda name, *a: None if name == "onnx" else real(name, *a))
    assert main(["export", str(vdp_run), "--format", "onnx", "--out", str(tmp_path / "o")]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install 'nlyap_opt[onnx]'" in err[0]
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("which", ["vdp_run", "cartpole_run"])
def test_export_onnx_matches_python(which, request, tmp_path):
    pytest.importorskip("onnx", reason="the onnx extra is not installed "
                                       "(pip install 'nlyap_opt[onnx]')")
    from onnx.reference import ReferenceEvaluator

    d = request.getfixturevalue(which)
    out = tmp_path / "o"
    assert main(["export", str(d), "--format", "onnx", "--out", str(out)]) == 0
    run = load_run(d, **QUIET)
    pts = _points(run, 1000)
    got = ReferenceEvaluator(str(out / "V.onnx")).run(None, {"x": pts})[0]
    _close(got, run.V(pts), "V (onnx)")
    if run.system.nu:
        got = ReferenceEvaluator(str(out / "kappa.onnx")).run(None, {"x": pts})[0]
        _close(got, run.kappa(pts), "kappa (onnx)")
    else:
        assert not (out / "kappa.onnx").exists()


# ------------------------------------------------------------------ the CLF-QP filter
def test_control_affinity_is_checked():
    x, u = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    check_control_affine(ca.vertcat(x[1], ca.sin(x[0]) * u), u, "affine")
    with pytest.raises(ConfigError, match="not control-affine"):
        check_control_affine(ca.vertcat(x[1], u**2), u, "quadratic in u")
    with pytest.raises(ConfigError, match="not control-affine"):
        check_control_affine(ca.vertcat(x[1], ca.tanh(u + x[0])), u, "tanh")
    s = systems.get("cartpole")
    check_control_affine(s.f, s.u, "cartpole")


def test_filter_refuses_a_system_without_inputs(vdp_run):
    with pytest.raises(ConfigError, match="no inputs"):
        ClfQpFilter(load_run(vdp_run, **QUIET), lambda x: np.zeros((len(x), 0)))


@pytest.mark.slow
def test_filter_qp_is_feasible_on_1e5_points_of_the_certified_set(cartpole_run):
    _filter_feasible(cartpole_run, 100_000)


def test_filter_qp_is_feasible_on_5000_points_of_the_certified_set(cartpole_run):
    _filter_feasible(cartpole_run, 5_000)


def _filter_feasible(cartpole_run, n):
    """The theorem: κ is feasible on Ω_c∖B_ε, so OSQP solves every QP there, and the answer
    keeps the demanded decrease (no fallback to κ)."""
    run = load_run(cartpole_run, **QUIET)
    rng = np.random.default_rng(11)
    nominal = lambda x: 30.0 * rng.standard_normal((len(x), 1))   # noqa: E731
    filt = ClfQpFilter(run, nominal, decay=0.5)
    pts = _points(run, n)
    pts = pts[~run.certificate.inner_ellipse.contains(pts)]
    assert len(pts) > n // 2
    a, e, d, k = filt.pieces(pts)
    assert d.min() > 0                       # the certificate's decrease of κ
    one = filt.pieces(pts[7:8])               # the one-state path agrees with the batch
    for b, o in zip((a, e, d, k), one):
        np.testing.assert_allclose(o, b[7:8], rtol=1e-13, atol=1e-300)
    un = nominal(pts)
    statuses, worst = set(), -np.inf
    for i in range(len(pts)):
        us, st = filt.solve(a[i], e[i], d[i], k[i], un[i])
        statuses.add(st)
        worst = max(worst, (e[i] + a[i] @ us) / (0.5 * d[i]))
        assert filt.box[0, 0] <= us[0] <= filt.box[0, 1]
    assert statuses == {"solved"} and filt.stats.fallback == 0
    assert worst <= -1 + 1e-6                  # ∇V·f(x, u*) ≤ −λ d(x)
    # the filter changes the nominal input only where it must (an inactive constraint)
    inactive = e + (a * un).sum(axis=1) <= -0.5 * d - 1e-6
    inb = (un[:, 0] > filt.box[0, 0]) & (un[:, 0] < filt.box[0, 1])
    sel = np.flatnonzero(inactive & inb)[:200]
    for i in sel:
        np.testing.assert_allclose(filt.solve(a[i], e[i], d[i], k[i], un[i])[0], un[i],
                                   rtol=1e-6, atol=1e-6)


def test_a_short_horizon_is_reported_in_a_few_lines_with_the_step_taken(vdp_run, tmp_path,
                                                                       capsys):
    """The first unconverged trajectories were printed as bare 'nlyap: ...' lines;
    simulate.json recorded --dt where the step taken divides the horizon evenly."""
    out = tmp_path / "s"
    assert main(["simulate", str(vdp_run), "--points", "12", "--horizon", "0.015", "--dt",
                 "0.01", "--out", str(out)]) == 2
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert all(ln.startswith("nlyap: not converged: ") for ln in err), err
    assert "12 trajectories have not reached" in err[-1] and "--horizon" in err[-1], err
    summary = json.loads((out / "simulate.json").read_text())
    assert summary["dt"] == pytest.approx(0.0075) and summary["dt_requested"] == 0.01
    assert len(err) == len(summary["failures"]) + 1


def test_nominal_files_are_data_not_code(tmp_path, capsys, cartpole_run):
    py = tmp_path / "nominal.py"
    py.write_text("import os\nos.system('touch HACKED')\n")
    out = tmp_path / "o"
    assert main(["simulate", str(cartpole_run), "--filter", "clf-qp", "--nominal", str(py),
                 "--out", str(out)]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"nominal controller {py} is not valid JSON" in err[0], err
    assert not (tmp_path / "HACKED").exists()
    bad = tmp_path / "bad.json"
    for d, msg in [({"format": "nlyap-nominal-controller", "K": [[1, 2]]}, "K must be 1 x 4"),
                   ({"format": "python", "code": "1"}, "'format' must be"),
                   ({"format": "nlyap-nominal-controller", "K": [["a", 0, 0, 0]]}, "numbers"),
                   # float() takes "2" and true: they were read as 2.0 and 1.0
                   ({"format": "nlyap-nominal-controller", "K": [["2", 0, 0, 0]]}, "strings"),
                   ({"format": "nlyap-nominal-controller", "K": [[True, 0, 0, 0]]},
                    "booleans"),
                   ({"format": "nlyap-nominal-controller", "K": [[0, 0, 0, 0]],
                     "u0": ["1"]}, "numbers only"),
                   ({"format": "nlyap-nominal-controller"}, "needs 'K'"),
                   ({"format": "nlyap-nominal-controller", "K": [[0, 0, 0, 0]], "x": 1},
                    "unknown keys")]:
        bad.write_text(json.dumps(d))
        with pytest.raises(ConfigError, match=msg):
            load_nominal(bad, 4, 1)
    v = json.loads((cartpole_run / "V.json").read_text())       # a V is not a controller
    v["layers"][-1]["weight"] = v["layers"][-1]["weight"][:1]
    v["layers"][-1]["bias"] = v["layers"][-1]["bias"][:1]
    bad.write_text(json.dumps(v))
    with pytest.raises(ConfigError, match="of kind 'lyapunov'"):
        load_nominal(bad, 4, 1)
    f = load_nominal(write_linear_nominal(bad, [[1.0, 2.0, 3.0, 4.0]], [0.5]), 4, 1)
    np.testing.assert_allclose(f(np.ones((2, 4))), [[-9.5], [-9.5]])


def test_filtered_nominal_stays_inside_where_unfiltered_leaves(cartpole_run, tmp_path):
    nom = write_linear_nominal(tmp_path / "zero.json", np.zeros((1, 4)),
                               description="no force: the pole falls")
    out = tmp_path / "sim"
    assert main(["simulate", str(cartpole_run), "--points", "30", "--horizon", "20",
                 "--filter", "clf-qp", "--nominal", str(nom), "--out", str(out)]) == 0
    _check_simulation(out, 30)
    summary = json.loads((out / "simulate.json").read_text())
    assert summary["filter"]["unfiltered_stayed"] < 30
    assert summary["filter"]["fallback_to_kappa"] == 0 and summary["filter"]["qp_solves"] > 0
    z = np.load(out / "trajectories.npz")
    assert not z["nominal_stayed"].all()


@pytest.mark.slow
def test_learned_pendulum_simulate_and_filter_with_the_margin(tmp_path):
    """The learned-f path: the fast pendulum run (φ control-affine, η from its samples, ~2 min):
    φ's closed loop and the filter with the margin η‖∇_L V‖ in its constraint."""
    d = tmp_path / "ip"
    cert = run_pipeline("inverted_pendulum", get_config("inverted_pendulum", "fast"), d,
                        **QUIET).summary
    assert cert["status"] == "certified"
    nom = write_linear_nominal(tmp_path / "zero.json", np.zeros((1, 2)))
    out = tmp_path / "sim"
    assert main(["simulate", str(d), "--learned", "--points", "40", "--filter", "clf-qp",
                 "--nominal", str(nom), "--out", str(out)]) == 0
    _check_simulation(out, 40)
    s = json.loads((out / "simulate.json").read_text())
    assert s["dynamics"] == "learned" and s["filter"]["unfiltered_stayed"] < 40
    run = load_run(d, **QUIET)
    filt = ClfQpFilter(run, lambda x: np.zeros((len(x), 1)), dynamics="learned")
    pts = _points(run, 5000)
    pts = pts[~run.certificate.inner_ellipse.contains(pts)]
    a, e, dd, k = filt.pieces(pts)
    assert dd.min() > 0
    assert run.problem.eta > 0      # the constraint carries the margin η‖∇_L V‖
    for i in range(0, len(pts), 50):
        us, st = filt.solve(a[i], e[i], dd[i], k[i], np.zeros(1))
        assert st == "solved" and e[i] + a[i] @ us <= -filt.decay * dd[i] * (1 - 1e-6)


@pytest.mark.parametrize("lam,kept", [(-300.0, False), (0.5, True)])
def test_a_rise_of_v_counts_only_if_the_refined_step_keeps_it(lam, kept):
    """x' = λx, V = x²: with λ = −300 one RK4 step of 0.01 (hλ = −3, outside RK4's
    stability interval) raises V although the flow lowers it: the refined step drops the
    rise. With λ = 0.5 V truly rises and the rise stays."""
    from types import SimpleNamespace

    from nlyap_opt.deployment.deploy import _confirmed_rises
    from nlyap_opt.kernel.simulate import trajectories

    def f(x):
        return lam * x

    run = SimpleNamespace(V=lambda x: np.sum(x ** 2, axis=1))
    Xi = trajectories(f, np.array([[1.0], [0.5]]), 0.01, 1)       # one coarse step
    rise = run.V(Xi[1]) - run.V(Xi[0])
    if lam < 0:
        assert (rise > 0).all()                                   # the coarse step's artefact
    out = _confirmed_rises(run, f, Xi, rise[None, :], dt=0.01, tol=1e-9)
    assert ((out > 1e-9).all() if kept else (out < 0).all()), out


def test_structural_zeros_keep_their_places_in_f_and_in_the_filter():
    # x_0' = 0 stored as a structural zero, and an input that does not enter f (0·u_1 folds
    # away): evaluations and the CLF-QP filter read by position (found by a review: the
    # zero row vanished, a simulation converged that stays put, the filter crashed)
    import types

    x = ca.SX.sym("x", 2)
    s0 = systems.System("zero_row", x, None, ca.vertcat(ca.SX(1, 1), -x[1]),
                        state_box=[[-1, 1], [-1, 1]])
    assert np.array_equal(s0.evaluate(np.array([[1.0, 1.0]])), [[0.0, -1.0]])
    u = ca.SX.sym("u", 2)
    s = systems.System("unused_input", x, u,
                       ca.vertcat(x[1], -x[0] - x[1] + u[0] + 0 * u[1]),
                       state_box=[[-1, 1], [-1, 1]], input_box=[[-2, 2], [-2, 2]])
    V = quadratic_lyapunov(np.array([[1.5, 0.5], [0.5, 1.0]]))
    problem = types.SimpleNamespace(V_expr=V.casadi, input_box=s.input_box, dynamics=None,
                                    controller=linear_controller(s, np.array([[0.5, 0.5],
                                                                              [0.0, 0.0]])))
    run = types.SimpleNamespace(problem=problem, system=s,
                                certificate=types.SimpleNamespace(inner_ellipse=None))
    flt = ClfQpFilter(run, lambda X: np.zeros((len(X), 2)))
    pts = np.array([[0.5, 0.5], [-0.3, 0.2]])
    a = flt.pieces(pts)[0]
    assert a.shape == (2, 2) and np.all(a[:, 1] == 0.0)
    assert flt(pts).shape == (2, 2)
