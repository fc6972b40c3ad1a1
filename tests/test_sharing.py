"""Certificates others can trust: a re-check runs no code named in the certificate, is bound
to the system it was made for, checks the stored numbers as written; Dask connections time
out; a certificate resting on declarations says so in its status line."""

import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

import systems
from nlyap_opt.certification.certificate import (
    RoaProblem,
    certify_roa,
    recheck_certificate,
    save_certificate,
    system_fingerprint,
)
from nlyap_opt.design.control import lqr, lyapunov_matrix, quadratic_lyapunov
from nlyap_opt.interface.cli import main
from nlyap_opt.kernel.errors import ConfigError

QUIET = {"log": lambda m: None}

SPEC = '''
name = "{name}"
states = ["x1", "x2"]
state_box = [[-2.0, 2.0], [-2.0, 2.0]]

[rhs]
x1 = "{rhs1}"
x2 = "-x1 - x2 + x1^3/3"
{declared}
'''

FACTORY_SPEC = '''
name = "fac_cubic"
factory = "maker.py:make"
'''

MAKER = '''
import casadi as ca
from pathlib import Path
from systems import System

def make():
    Path(__file__).with_name("factory_ran").write_text("yes")
    {extra}
    x = ca.SX.sym("x", 2)
    f = ca.vertcat(x[1], -x[0] - x[1] + x[0]**3/3)
    return System("fac_cubic", x, None, f, state_box=[[-2, 2], [-2, 2]])
'''


def _certify(system, out: Path, outer: float = 1.0) -> Path:
    """A quadratic-V certificate of ``system`` (known f) saved in ``out``."""
    P = lyapunov_matrix(system.A)
    V = quadratic_lyapunov(P)
    prob = RoaProblem(system, V, inner=0.1, outer=outer)
    lam = float(np.linalg.eigvalsh(P)[0])
    cert = certify_roa(prob, 0.9 * lam * outer**2, search=True, **QUIET)
    assert cert.certified, cert.reason
    return save_certificate(cert, prob, out)


def _spec(d: Path, name="own_cubic", rhs1="x2", declared="", file=None) -> Path:
    p = d / (file or f"{name}.toml")
    p.write_text(SPEC.format(name=name, rhs1=rhs1, declared=declared))
    return p


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


# ============================================================ nothing named inside is executed
@pytest.fixture
def factory_certificate(tmp_path):
    """A certificate of a factory-defined system; the factory leaves a marker when it runs."""
    src = tmp_path / "src"
    src.mkdir()
    (src / "maker.py").write_text(MAKER.format(extra=""))
    spec = src / "fac.toml"
    spec.write_text(FACTORY_SPEC)
    system = systems.load_spec(spec)
    out = tmp_path / "cert"
    _certify(system, out)
    (src / "factory_ran").unlink()
    return src, spec, out


def test_factory_named_in_the_certificate_is_not_run(factory_certificate, capsys):
    src, spec, out = factory_certificate
    # the factory turned hostile after the certificate was written: it would exit 0
    (src / "maker.py").write_text(MAKER.format(extra="import sys; sys.exit(0)"))
    assert main(["verify", "--certificate", str(out)]) == 3
    err = _one_line_error(capsys)
    assert "--allow-factory" in err and "--system" in err, err
    with pytest.raises(ConfigError, match="allow"):
        recheck_certificate(out, **QUIET)
    # the spec given on the command line without the flag is refused too, before any import
    assert main(["verify", "--certificate", str(out), "--system", str(spec)]) == 3
    assert "--allow-factory" in _one_line_error(capsys)
    with pytest.raises(ConfigError, match="allow_factory"):
        recheck_certificate(out, system=spec, **QUIET)
    assert not (src / "factory_ran").exists()


def test_factory_given_with_allow_factory_rechecks(factory_certificate, capsys):
    src, spec, out = factory_certificate
    assert main(["verify", "--certificate", str(out), "--system", str(spec),
                 "--allow-factory"]) == 0, capsys.readouterr().err
    assert (src / "factory_ran").exists()
    assert recheck_certificate(out, system=spec, allow_factory=True, **QUIET).certified


def test_simulate_and_export_take_the_system_as_verify_does(factory_certificate, tmp_path,
                                                           capsys):
    """simulate and export re-check the run first: a factory named in it is not run, and
    the fix the message gives (--system FILE.toml --allow-factory) exists for them too."""
    src, spec, out = factory_certificate
    for extra in ([], ["--system", str(spec)]):
        assert main(["export", str(out), "--format", "c", "--out", str(tmp_path / "e"),
                     *extra]) == 3
        assert "--allow-factory" in _one_line_error(capsys)
        assert not (src / "factory_ran").exists()
    assert main(["export", str(out), "--format", "c", "--out", str(tmp_path / "e"),
                 "--system", str(spec), "--allow-factory"]) == 0, capsys.readouterr().err
    assert (tmp_path / "e" / "nlyap.c").is_file() and (src / "factory_ran").exists()
    assert main(["simulate", str(out), "--points", "4", "--out", str(tmp_path / "s"),
                 "--system", str(spec), "--allow-factory"]) == 0, capsys.readouterr().err


def test_a_spec_file_gone_or_replaced_by_a_directory_is_named_as_such(tmp_path, capsys):
    spec = _spec(tmp_path)
    out = tmp_path / "cert"
    _certify(systems.load_spec(spec), out)
    spec.unlink()
    assert main(["verify", "--certificate", str(out)]) == 3
    assert "which does not exist" in _one_line_error(capsys)
    spec.mkdir()
    assert main(["verify", "--certificate", str(out)]) == 3
    err = _one_line_error(capsys)
    assert "is not a regular file" in err and "--system FILE.toml" in err, err


# ============================================================ a certificate binds its system
def test_recheck_against_an_edited_system_is_refused(tmp_path, capsys):
    spec = _spec(tmp_path)
    out = tmp_path / "cert"
    _certify(systems.load_spec(spec), out)
    d = json.loads((out / "certificate.json").read_text())
    assert len(d["system_binding"]["sha256"]) == 64
    # an edited copy, x1' = −x1 (also stable, and certifiable on a larger domain)
    edited = _spec(tmp_path, rhs1="-x1", file="edited.toml")
    assert main(["verify", "--certificate", str(out), "--system", str(edited)]) == 2
    assert "not the certified system" in capsys.readouterr().out
    again = recheck_certificate(out, system=edited, **QUIET)
    assert not again.certified and "not the certified system" in again.reason
    assert "f" in again.reason.split("not the certified system")[1]
    # the spec file named in the certificate edited in place: refused as well
    _spec(tmp_path, rhs1="-x1")
    assert main(["verify", "--certificate", str(out)]) == 2
    assert "not the certified system" in capsys.readouterr().out
    # restored: certified again, with the system given on the command line or not
    _spec(tmp_path)
    assert main(["verify", "--certificate", str(out)]) == 0
    assert main(["verify", "--certificate", str(out), "--system", str(spec)]) == 0


def test_recheck_against_another_catalogue_system_is_refused(tmp_path, capsys):
    out = tmp_path / "cert"
    _certify(systems.get("van_der_pol"), out, outer=1.0)
    assert main(["verify", "--certificate", str(out), "--system", "van_der_pol"]) == 0
    capsys.readouterr()
    # a spec of the same name and different dynamics (nx = 2 as well)
    other = _spec(tmp_path, name="vdp_other", rhs1="x2")
    again = recheck_certificate(out, system=other, **QUIET)
    assert not again.certified and "not the certified system" in again.reason


def test_certificate_without_binding_is_refused_with_the_fix(tmp_path):
    out = tmp_path / "cert"
    _certify(systems.get("van_der_pol"), out)
    d = json.loads((out / "certificate.json").read_text())
    del d["system_binding"]
    (out / "certificate.json").write_text(json.dumps(d))
    again = recheck_certificate(out, **QUIET)
    assert not again.certified
    assert "does not record the system" in again.reason and "rerun" in again.reason


def test_fingerprint_is_deterministic_across_processes(tmp_path):
    spec = _spec(tmp_path, declared="[declared]\nlipschitz = 20.0\n")
    here = system_fingerprint(systems.load_spec(spec))
    code = ("import systems; from nlyap_opt.certification.certificate import system_fingerprint; "
            f"print(system_fingerprint(systems.load_spec({str(spec)!r})))")
    procs = [subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                              env=dict(os.environ, PYTHONHASHSEED=seed))
             for seed in ("1", "12345")]                  # the two processes at once
    for proc in procs:
        assert proc.communicate(timeout=120)[0].strip() == here
        assert proc.returncode == 0
    # and it sees every part: f, the box, the declarations
    for kw in ({"rhs1": "1.0000001*x2"}, {"declared": "[declared]\nlipschitz = 21.0\n"}):
        kw.setdefault("declared", "[declared]\nlipschitz = 20.0\n")
        other = systems.load_spec(_spec(tmp_path, file="o.toml", **kw))
        assert system_fingerprint(other) != here, kw
    s = systems.load_spec(spec)
    s.state_box = np.array([[-2.0, 2.0], [-2.0, 2.5]])
    assert system_fingerprint(s) != here


# ============================================================ the numbers as written
@pytest.fixture
def vdp_certificate(tmp_path):
    out = tmp_path / "cert"
    path = _certify(systems.get("van_der_pol"), out)
    return path


@pytest.mark.parametrize("edit, field", [
    (lambda d: d["inner_ellipse"].__setitem__("level", d["inner_ellipse"]["level"] * 1e4),
     "inner_ellipse.level"),
    (lambda d: d["inner_ellipse"].__setitem__("level", d["inner_ellipse"]["level"] * 0.5),
     "inner_ellipse.level"),
    (lambda d: d["inner_ellipse"].__setitem__(
        "box_half_widths", [10 * v for v in d["inner_ellipse"]["box_half_widths"]]),
     "inner_ellipse.box_half_widths"),
    (lambda d: d["inner_ellipse"].__setitem__("proved", False), "inner_ellipse.proved"),
    (lambda d: d.__setitem__("assumptions_declared_by_user", []), "assumptions_declared"),
    (lambda d: d.__setitem__("decrease_condition", "nothing"), "decrease_condition"),
])
def test_an_edited_number_is_refused_with_its_field(vdp_certificate, edit, field, capsys):
    d = json.loads(vdp_certificate.read_text())
    if field == "assumptions_declared":      # van der Pol declares nothing: add a claim
        d["assumptions_declared_by_user"] = ["made up"]
    else:
        edit(d)
    vdp_certificate.write_text(json.dumps(d))
    again = recheck_certificate(vdp_certificate, **QUIET)
    assert not again.certified and field in again.reason, again.reason
    assert main(["verify", "--certificate", str(vdp_certificate)]) == 2


@pytest.mark.parametrize("field, value, words", [
    ("level", float("nan"), "its level is nan"),
    ("eta", 0.1, "eta > 0 needs learned dynamics"),
])
def test_an_edit_that_states_no_problem_names_the_certificate(vdp_certificate, field, value,
                                                               words, capsys):
    """These edits ended in the Python API's words ("pass dynamics= or eta=0") or a bare
    "level must be finite", naming neither the file nor a fix."""
    d = json.loads(vdp_certificate.read_text())
    d[field] = value
    vdp_certificate.write_text(json.dumps(d))
    assert main(["verify", "--certificate", str(vdp_certificate)]) == 3
    err = _one_line_error(capsys)
    assert f"certificate {vdp_certificate}" in err and words in err, err
    assert "edited certificate.json" in err and "dynamics=" not in err


def test_an_unedited_certificate_rechecks_with_its_numbers(vdp_certificate):
    d = json.loads(vdp_certificate.read_text())
    again = recheck_certificate(vdp_certificate, **QUIET)
    assert again.certified
    assert again.level == d["level"]
    assert again.inner_ellipse.level == d["inner_ellipse"]["level"]


# ============================================================ verify's input errors
@pytest.mark.parametrize("opt, value", [("--outer", "1e200"), ("--inner", "1e200"),
                                        ("--outer", "nan"), ("--outer", "-1"),
                                        ("--outer", "inf")])
def test_verify_radii_out_of_range_are_input_errors(tmp_path, capsys, opt, value):
    s = systems.get("van_der_pol")
    V = tmp_path / "V.json"
    quadratic_lyapunov(lqr(s).P).save(V)
    args = {"--inner": "0.1", "--outer": "1.0", opt: value}
    argv = ["verify", "--system", "van_der_pol", "--lyapunov", str(V)]
    for k, v in args.items():
        argv += [f"{k}={v}"]
    assert main(argv) == 3
    assert opt in _one_line_error(capsys)


# ============================================================ Dask connections
@pytest.fixture
def silent_listener():
    """A loopback socket that accepts connections and never answers."""
    srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    srv.bind(("127.0.0.1", 0))
    srv.listen(8)
    held, stop = [], threading.Event()

    def accept():
        srv.settimeout(0.2)
        while not stop.is_set():
            try:
                held.append(srv.accept()[0])
            except OSError:
                continue

    t = threading.Thread(target=accept, daemon=True)
    t.start()
    yield srv.getsockname()[1]
    stop.set()
    t.join(2)
    for c in held:
        c.close()
    srv.close()


def _closed_port() -> int:
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return port


def test_silent_scheduler_times_out(silent_listener):
    from nlyap_opt.distributed.parallel import DEFAULT_CONNECT_TIMEOUT, dask_client

    assert DEFAULT_CONNECT_TIMEOUT <= 10
    t0 = time.monotonic()
    with pytest.raises(ConfigError, match="no Dask scheduler answered"):
        with dask_client(scheduler=f"127.0.0.1:{silent_listener}", connect_timeout=0.5):
            pass
    assert time.monotonic() - t0 < 8


def test_silent_scheduler_from_the_cli(silent_listener, tmp_path, capsys):
    t0 = time.monotonic()
    code = main(["verify", "--certificate", str(tmp_path), "--scheduler",
                 f"127.0.0.1:{silent_listener}", "--connect-timeout", "0.5"])
    # no certificate in tmp_path: the paths are checked first (exit 3 either way, fast)
    assert code == 3
    capsys.readouterr()
    out = tmp_path / "cert"
    _certify(systems.get("van_der_pol"), out)
    t0 = time.monotonic()
    code = main(["verify", "--certificate", str(out), "--scheduler",
                 f"127.0.0.1:{silent_listener}", "--connect-timeout", "0.5"])
    assert code == 3 and time.monotonic() - t0 < 10
    assert "no Dask scheduler answered" in _one_line_error(capsys)


def test_closed_port_fails_fast():
    from nlyap_opt.distributed.parallel import dask_client

    t0 = time.monotonic()
    with pytest.raises(ConfigError, match="no Dask scheduler answered"):
        with dask_client(scheduler=f"127.0.0.1:{_closed_port()}"):
            pass
    assert time.monotonic() - t0 < 12


@pytest.mark.parametrize("argv", [
    ["verify", "--certificate", "{dir}", "--workers", "100000"],
    ["run", "van_der_pol", "--workers", "100000", "--out", "{dir}/o"],
    ["verify", "--certificate", "{dir}", "--connect-timeout", "0"],
    ["verify", "--certificate", "{dir}", "--connect-timeout", "nan"],
])
def test_workers_and_timeout_are_bounded(tmp_path, capsys, argv):
    argv = [a.replace("{dir}", str(tmp_path)) for a in argv]
    assert main(argv) == 3
    _one_line_error(capsys)


def test_workers_bound_in_the_api():
    from nlyap_opt.distributed.parallel import MAX_LOCAL_WORKERS, dask_client

    with pytest.raises(ConfigError, match="at most"):
        with dask_client(workers=MAX_LOCAL_WORKERS + 1):
            pass


# ============================================================ the status line names declarations
def test_status_line_names_the_declared_assumptions(tmp_path):
    spec = _spec(tmp_path, declared="[declared]\nlipschitz = 20.0\n")
    out = tmp_path / "cert"
    path = _certify(systems.load_spec(spec), out)
    again = recheck_certificate(out, **QUIET)
    assert again.certified
    line = again.summary()
    assert line.startswith("certified under the declared assumptions: "), line
    assert "Lipschitz" in line
    # without declarations the plain word
    out2 = tmp_path / "cert2"
    _certify(systems.get("van_der_pol"), out2)
    assert recheck_certificate(out2, **QUIET).summary().startswith("certified: ")
    # the report's status line says the same
    from nlyap_opt.workflow.report import status_line

    d = json.loads(path.read_text())
    assert status_line(d).startswith("certified under the declared assumptions")


def test_the_decrease_condition_may_show_the_stored_beta_digits(vdp_certificate):
    """``decrease_condition`` states β to 6 digits: a β re-derived within the tolerance of
    the stored one may round the other way, and the stored words (with the stored β) still
    describe the proof; other words are refused."""
    import dataclasses

    from nlyap_opt.certification.certificate import _not_as_proved

    new = recheck_certificate(vdp_certificate, **QUIET)
    text = "∇V·φ(x, κ(x)) < −β with β = M·η = {} (rounded up)"
    new = dataclasses.replace(new, margin=0.1234565000000001,
                              decrease_condition=text.format("0.123457"))
    saved = dataclasses.replace(new, margin=0.1234564999999999,
                                decrease_condition=text.format("0.123456"))
    assert _not_as_proved(saved, new) == []
    for other in ("0.123458", "nothing"):
        edited = dataclasses.replace(saved, decrease_condition=text.format(other)
                                     if other[0].isdigit() else other)
        assert any(p.startswith("decrease_condition") for p in _not_as_proved(edited, new))
