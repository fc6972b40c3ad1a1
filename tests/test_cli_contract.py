"""The exit-code contract of ``nlyap``: 0 success, 1 counterexample (verify only), 2 unknown /
not certified, 3 input or usage error, 4 internal error, 5 stopped by ``--time-limit``, 130
interrupted; one line, no traceback unless ``--debug``."""

import argparse
import json
import os
import signal
import subprocess
import sys
import types

import numpy as np
import pytest
from certcheck import assert_fast_certificate

import systems
from nlyap_opt.design.control import lyapunov_matrix, quadratic_lyapunov
from nlyap_opt.interface import cli
from nlyap_opt.interface.cli import EXIT_CODES, build_parser, main
from nlyap_opt.kernel.errors import ConfigError


def _err_lines(capsys):
    return [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]


def test_every_command_documents_the_exit_codes(capsys):
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    names = list(sub.choices)
    assert {"systems", "lqr", "verify", "run", "compare", "learn-dynamics"} <= set(names)
    for name in names:
        assert main([name, "--help"]) == 0
        text = capsys.readouterr().out
        assert "exit codes:" in text, name
        for code in (0, 3, 4, 130):
            assert f"  {code} " in text, (name, code)
    assert main(["verify", "--help"]) == 0
    text = capsys.readouterr().out
    assert "  1    counterexample" in text and "  2    unknown" in text
    assert set(EXIT_CODES) == {0, 1, 2, 3, 4, 5, 130}
    for name in ("run", "compare", "learn-dynamics"):
        assert main([name, "--help"]) == 0
        text = capsys.readouterr().out
        assert "  5    stopped at --time-limit" in text and "--time-limit SECONDS" in text


@pytest.fixture(scope="module")
def vfiles(tmp_path_factory):
    d = tmp_path_factory.mktemp("v")
    s = systems.get("van_der_pol")
    good = quadratic_lyapunov(lyapunov_matrix(s.A)).save(d / "Vp.json")
    ident = quadratic_lyapunov(np.eye(2)).save(d / "Vi.json")
    return str(good), str(ident), d


@pytest.mark.parametrize("which,radii,extra,code,status", [
    (0, ["0.1", "0.5"], [], 0, "verified"),
    (1, ["0.2", "2.5"], [], 1, "counterexample"),           # dV/dt > 0 at |x1| > 1
    # sup of dV/dt on the annulus is -0.00992259676 (on ‖x‖ = 0.1, by optimisation): with
    # β = 0.0099225 the property holds with a slack of 1e-7, which boxes of width 0.3 cannot show
    (0, ["0.1", "0.5"], ["--margin", "0.0099225", "--resolution", "0.3"], 2, "unknown"),
])
def test_verify_exit_codes_follow_the_verdict(vfiles, which, radii, extra, code, status,
                                              tmp_path, capsys):
    out = tmp_path / "v.json"
    argv = ["verify", "--system", "van_der_pol", "--lyapunov", vfiles[which], "--inner",
            radii[0], "--outer", radii[1], "--json", str(out), *extra]
    assert main(argv) == code
    assert json.loads(out.read_text())["status"] == status
    assert [ln for ln in _err_lines(capsys) if not ln.startswith("note:")] == []


def test_a_counterexample_is_printed_in_the_terms_of_its_condition(vfiles, capsys):
    """V > 0 is checked as -V < 0: the line gave -V's value (positive: it read as if V > 0
    held there). A decrease counterexample gives dV/dt + β, which must be negative."""
    from nlyap_opt.kernel.network import Layer, Network

    d = vfiles[2]
    shifted = Network([Layer(np.eye(2), np.zeros(2), "square"),
                       Layer(np.ones((1, 2)), [-0.5], "linear")]).save(d / "Vshift.json")
    assert main(["verify", "--system", "van_der_pol", "--lyapunov", str(shifted), "--inner",
                 "0.1", "--outer", "0.5"]) == 1
    line = next(ln for ln in capsys.readouterr().out.splitlines() if "counterexample x" in ln)
    assert "violates V > 0: V(x) in [" in line
    lo, hi = (float(v) for v in line.split("V(x) in [")[1].rstrip("]").split(","))
    assert lo <= hi < 0   # V = ‖x‖² - 0.5 < 0 on ‖x‖ <= 0.5
    assert main(["verify", "--system", "van_der_pol", "--lyapunov", vfiles[1], "--inner",
                 "0.2", "--outer", "2.5", "--margin", "0.01"]) == 1
    line = next(ln for ln in capsys.readouterr().out.splitlines() if "counterexample x" in ln)
    assert "violates decrease: dV/dt + 0.01 in [" in line and line.endswith("(must be < 0)")
    lo = float(line.split("in [")[1].split(",")[0])
    assert lo >= 0


def _patch_command(monkeypatch, exc):
    def boom(args):
        raise exc

    monkeypatch.setattr(cli, "cmd_systems", boom)


@pytest.mark.parametrize("exc,code,words", [
    (ZeroDivisionError("division by zero"), 4, ["internal error", "ZeroDivisionError",
                                                "--debug"]),
    (ValueError("a bug deep inside"), 4, ["internal error", "--debug"]),
    (RuntimeError("multi\nline"), 4, ["internal error", "multi line"]),
    (KeyError("k"), 4, ["internal error"]),
    (ConfigError("bad key; fix it"), 3, ["error: bad key; fix it"]),
    (FileNotFoundError(2, "No such file or directory", "/x/y.json"), 3, ["/x/y.json"]),
    (PermissionError(13, "Permission denied", "/root/z"), 3, ["Permission denied"]),
    (json.JSONDecodeError("Expecting value", "{", 1), 3, ["malformed JSON"]),
    (SystemExit(1), 4, ["internal error"]),
    (MemoryError(), 3, ["out of memory in 'nlyap systems'", "smaller ones"]),
    (OSError(28, "No space left on device"), 3, ["No space left", "free space"]),
    (OSError(5, "Input/output error"), 4, ["internal error"]),
])
def test_exceptions_map_to_exit_codes(monkeypatch, capsys, exc, code, words):
    _patch_command(monkeypatch, exc)
    assert main(["systems"]) == code
    lines = _err_lines(capsys)
    assert len(lines) == 1 and lines[0].startswith("nlyap: "), lines
    assert "Traceback" not in lines[0]
    for w in words:
        assert w in lines[0], (w, lines[0])


def test_debug_prints_the_traceback_of_an_internal_error(monkeypatch, capsys):
    _patch_command(monkeypatch, ZeroDivisionError("division by zero"))
    assert main(["--debug", "systems"]) == 4
    err = capsys.readouterr().err
    assert "Traceback" in err and "ZeroDivisionError" in err
    assert err.strip().splitlines()[-1].startswith("nlyap: internal error:")


def test_keyboard_interrupt_exits_130(monkeypatch, capsys):
    _patch_command(monkeypatch, KeyboardInterrupt())
    assert main(["systems"]) == 130
    assert _err_lines(capsys) == ["nlyap: interrupted; rerun the same command to resume"]


_INTERRUPT_IMPORT = """
import sys
class Stop:
    def find_spec(self, name, path=None, target=None):
        if name == "nlyap_opt.interface.cli":
            raise KeyboardInterrupt
sys.meta_path.insert(0, Stop())
from nlyap_opt.interface.entry import main
sys.exit(main(["run", "van_der_pol"]))
"""


def test_ctrl_c_while_the_command_line_is_imported_is_one_line_exit_130():
    """A Ctrl-C during the ~1 s import of the command line (numpy, CasADi, the toolbox)
    ends with one line and exit 130, never a traceback: ``import nlyap_opt`` loads nothing
    heavy, and the console script imports the rest inside a guard."""
    check = subprocess.run([sys.executable, "-c", "import sys, nlyap_opt, "
                            "nlyap_opt.interface.entry; print(sorted({'numpy', 'casadi', "
                            "'torch'} & set(sys.modules)))"],
                           capture_output=True, text=True, timeout=60)
    assert check.stdout.strip() == "[]", check.stdout + check.stderr
    res = subprocess.run([sys.executable, "-c", _INTERRUPT_IMPORT], capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 130
    assert "Traceback" not in res.stderr
    assert res.stderr.strip().splitlines() == ["nlyap: interrupted while starting; nothing "
                                               "was run"]


def test_never_exit_1_for_errors(monkeypatch, capsys):
    for exc in (Exception("x"), AssertionError("y"), OSError("z"), SystemExit(1)):
        _patch_command(monkeypatch, exc)
        assert main(["systems"]) not in (0, 1)
        capsys.readouterr()


@pytest.mark.parametrize("status,code", [("certified", 0), ("counterexample", 1),
                                         ("not certified", 2), ("assumption refuted", 2)])
def test_verify_certificate_exit_codes(monkeypatch, tmp_path, capsys, status, code):
    certificate = pytest.importorskip("nlyap_opt.certification.certificate")
    f = tmp_path / "certificate.json"
    f.write_text("{}")
    fake = types.SimpleNamespace(status=certificate.CertStatus(status),
                                 summary=lambda: f"{status}: because")
    import nlyap_opt.interface.cli

    monkeypatch.setattr(nlyap_opt.interface.cli, "recheck_certificate", lambda path, **k: fake)
    assert main(["verify", "--certificate", str(tmp_path)]) == code
    assert f"{status}: because" in capsys.readouterr().out


@pytest.mark.parametrize("status,code", [("certified", 0), ("not certified", 2)])
def test_run_passes_the_validated_config_and_maps_the_status(monkeypatch, tmp_path, status,
                                                             code):
    import nlyap_opt.workflow.pipeline

    seen = {}

    def fake_run(system, cfg, out, known_dynamics=False, **kw):
        seen.update(system=system, cfg=cfg, out=out, known=known_dynamics)
        return types.SimpleNamespace(status=types.SimpleNamespace(value=status))

    monkeypatch.setattr(nlyap_opt.workflow.pipeline, "run", fake_run)
    c = tmp_path / "c.json"
    c.write_text(json.dumps({"train": {"steps": 11}}))
    argv = ["run", "van_der_pol", "--preset", "fast", "--config", str(c), "--known-dynamics",
            "--out", str(tmp_path / "o")]
    assert main(argv) == code
    assert seen["cfg"]["train"]["steps"] == 11 and seen["known"] is True


def test_config_command_round_trips(tmp_path, capsys):
    assert main(["config", "inverted_pendulum", "--preset", "fast"]) == 0
    printed = capsys.readouterr().out
    cfg = json.loads(printed)
    (tmp_path / "c.json").write_text(printed)
    assert main(["config", "inverted_pendulum", "--preset", "fast", "--config",
                 str(tmp_path / "c.json")]) == 0
    assert json.loads(capsys.readouterr().out) == cfg
    assert main(["config", "--keys"]) == 0
    assert "`cegis.margin_mode`" in capsys.readouterr().out


def _nlyap(*argv, **kw):
    return subprocess.Popen([sys.executable, "-m", "nlyap_opt.interface.cli", *argv], text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, **kw)


def test_help_and_usage_error_in_a_real_process():
    p, h = _nlyap("lqr", "inverted_pendulum", "--R", "0"), _nlyap("run", "--help")  # at once
    out, err = p.communicate(timeout=120)
    assert p.returncode == 3 and "Traceback" not in err
    assert err.strip() == err.strip().splitlines()[0]
    assert "positive definite" in err
    out, err = h.communicate(timeout=120)
    assert h.returncode == 0 and "exit codes:" in out


def test_a_reader_that_leaves_the_pipe_does_not_turn_the_exit_code_into_an_error():
    r, w = os.pipe()
    os.close(r)                                  # `nlyap systems | true`: the reader is gone
    try:
        p = subprocess.run([sys.executable, "-m", "nlyap_opt.interface.cli", "systems"],
                           stdout=w, stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        os.close(w)
    assert p.returncode == 0, p.stderr
    assert p.stderr == ""                        # no BrokenPipeError, not even at exit


def test_sigint_during_a_run_exits_130(tmp_path):
    """A real SIGINT in the CEGIS stage of a fast run: exit 130, one line, no traceback."""
    p = _nlyap("run", "van_der_pol", "--preset", "fast", "--known-dynamics", "--out",
               str(tmp_path / "run"),
               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        for line in p.stdout:
            if line.startswith("[cegis]"):
                break
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130, err
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1] == \
        "nlyap: interrupted; rerun the same command to resume"


@pytest.mark.parametrize("bad", ["0", "-3", "nan", "soon", "1e300"])
def test_time_limit_must_be_a_positive_number_a_timer_holds(bad, capsys):
    """1e300 s ended in an OverflowError (exit 4): no interval timer holds it."""
    assert main(["run", "van_der_pol", "--time-limit", bad]) == 3
    (line,) = _err_lines(capsys)
    assert "--time-limit" in line and "a finite number of seconds in (0, 3.16224e+07]" in line


def test_time_limit_stops_with_exit_5_and_the_rerun_gives_the_reference(tmp_path):
    """--time-limit is a guard, not a budget: it stops a fast learned run part-way (exit 5,
    one line naming the output directory), and the same command without it resumes from the
    kept stages to the fast certificate (its floors; bit for bit where this machine's
    fingerprint is recorded: certcheck.assert_fast_certificate). The limit, 0.3 s, lies far
    below the run's own work (φ's training, CEGIS, the certificate: seconds on any CPU), so
    a fast machine is stopped too."""
    out = tmp_path / "run"
    p = _nlyap("run", "van_der_pol", "--preset", "fast", "--out", str(out),
               "--time-limit", "0.3")
    _, err = p.communicate(timeout=300)
    assert p.returncode == 5, err
    assert "Traceback" not in err
    last = err.strip().splitlines()[-1]
    assert last.startswith("nlyap: stopped at --time-limit 0.3 s;") and str(out) in last
    assert not (out / "certificate.json").exists()
    # the same command again (in this process: its imports are done)
    assert main(["run", "van_der_pol", "--preset", "fast", "--out", str(out)]) == 0
    cert = json.loads((out / "certificate.json").read_text())
    assert_fast_certificate("van_der_pol/learned", cert, out)


def test_time_limit_waits_for_a_running_import(tmp_path, monkeypatch):
    """--time-limit never fires inside an import: a module imported through a C++ extension
    (torch's imports run so) would abort the process with the exception thrown through it
    (seen: `terminate called ... TimeLimitReached` and SIGABRT when a clean clone's first run
    imported torch at the limit). The guard fires once the import is done."""
    (tmp_path / "slow_import_mod.py").write_text("import time\ntime.sleep(0.4)\nDONE = True\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "slow_import_mod", raising=False)
    with pytest.raises(cli.TimeLimitReached):
        with cli._time_guard(0.1):
            import slow_import_mod  # noqa: F401 - the import is what is timed
            sys.modules["slow_import_mod"].AFTER = True
            signal.pause()  # the limit ends the wait
    mod = sys.modules["slow_import_mod"]
    assert mod.DONE and mod.AFTER  # the import ended, then the limit stopped the rest


def test_ctrl_c_waits_for_a_running_import_and_main_restores_the_handler(tmp_path,
                                                                          monkeypatch):
    """Ctrl-C during an import (a clean run's imports of torch take seconds) must not throw
    through it: seen were a torch module left half initialised and the next import failing
    as "internal error" (exit 4) instead of exit 130. The CLI's SIGINT handler waits for
    the import; main() puts the caller's handler back."""
    import os
    import threading

    (tmp_path / "slow_import_int.py").write_text("import time\ntime.sleep(0.4)\nDONE = True\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "slow_import_int", raising=False)
    old = signal.signal(signal.SIGINT, cli._outside_imports(cli._interrupt))
    try:
        threading.Timer(0.1, os.kill, (os.getpid(), signal.SIGINT)).start()
        with pytest.raises(KeyboardInterrupt):
            import slow_import_int  # noqa: F401 - the import is what is interrupted
            signal.pause()  # the deferred Ctrl-C ends the wait
    finally:
        signal.signal(signal.SIGINT, old)
    assert sys.modules["slow_import_int"].DONE
    before = signal.getsignal(signal.SIGINT)
    assert main(["run", "van_der_pol", "--time-limit", "soon"]) == 3
    assert signal.getsignal(signal.SIGINT) is before


def test_an_open_progress_bar_does_not_swallow_the_one_line_message(capsys):
    """A run stopped mid-bar (--time-limit during φ's training) left the bar's line open and
    the message was appended to it; the CLI closes open bars before its message."""
    import sys

    from tqdm import tqdm

    from nlyap_opt.interface.cli import _close_progress_bars

    bar = tqdm(total=10, desc="φ[1] test", leave=False, mininterval=0)
    bar.update(3)
    _close_progress_bars()
    print("nlyap: stopped", file=sys.stderr)
    err = capsys.readouterr().err
    assert "3/10" in err                                      # the bar was drawn
    assert err.strip().splitlines()[-1] == "nlyap: stopped"
    assert bar.disable or bar not in getattr(tqdm, "_instances", set())


def test_a_stop_is_deferred_inside_casadis_wrapper_and_found_behind_a_wrapping_error():
    """A stop (Ctrl-C, --time-limit) is not raised inside CasADi's SWIG wrapper module, whose
    overload dispatch clears exceptions (the stop was lost, the run went on to exit 0) and
    whose C functions wrap them in ``SystemError`` (exit 4): the handler retries later, as
    during an import. A stop wrapped by an extension is still found behind the error."""
    import sys as _sys

    from nlyap_opt.interface.cli import TimeLimitReached, _in_import
    from nlyap_opt.kernel.errors import interruption, raise_if_interrupted

    def frame_in(module_name):
        scope = {"__name__": module_name, "_sys": _sys}
        exec("def here():\n    return _sys._getframe()\n", scope)
        return scope["here"]()

    assert _in_import(frame_in("casadi.casadi"))
    assert not _in_import(frame_in("nlyap_opt.workflow.pipeline"))
    stop = TimeLimitReached(0.3)
    try:
        try:
            raise stop
        except KeyboardInterrupt as inner:
            raise SystemError("returned a result with an exception set") from inner
    except SystemError as wrapped:
        assert interruption(wrapped) is stop
        with pytest.raises(TimeLimitReached):
            raise_if_interrupted(wrapped)
    plain = ValueError("solver failed")
    plain.__context__ = RuntimeError("before")
    assert interruption(plain) is None
    raise_if_interrupted(plain)            # nothing to raise


def test_no_progress_bar_goes_to_a_log_file(monkeypatch):
    """Standard error that is not a terminal (a log file, a pipe) gets no carriage-return
    progress bars; a terminal does."""
    import io
    import sys

    from nlyap_opt.learned.phi_training import progress_bar

    class Tty(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setattr(sys, "stderr", io.StringIO())
    assert progress_bar(10, True, "φ[0]") is None
    monkeypatch.setattr(sys, "stderr", Tty())
    bar = progress_bar(10, True, "φ[0]")
    assert bar is not None
    bar.close()
    assert progress_bar(10, False, "φ[0]") is None


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full on this system")
def test_a_full_device_is_the_users_to_fix(capsys):
    """A write the file system refuses after the file opened (no space left: ``/dev/full``;
    a file of ``/proc`` that takes no text) is exit 3 naming the file, not an internal
    error."""
    for path, why in (("/dev/full", "--json /dev/full is not a regular file"),
                      ("/proc/version", "cannot write --json /proc/version")):
        if not os.path.exists(path):
            continue
        assert main(["lqr", "van_der_pol", "--json", path]) == 3
        lines = _err_lines(capsys)
        assert len(lines) == 1 and why in lines[0], lines


def test_outputs_are_written_whole_or_not_at_all(tmp_path, monkeypatch, capsys):
    """A JSON output goes through a new file and a rename: a pipe there is refused at once
    (it blocked), a symbolic link is replaced (its target, another run's file, was
    overwritten), and a write that fails leaves the old file and no temporary one."""
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    assert main(["lqr", "van_der_pol", "--json", str(fifo)]) == 3
    assert "not a regular file" in _err_lines(capsys)[0]
    victim = tmp_path / "certificate.json"
    victim.write_text("{}")
    link = tmp_path / "link.json"
    link.symlink_to(victim)
    assert main(["lqr", "van_der_pol", "--json", str(link)]) == 0
    assert victim.read_text() == "{}" and not link.is_symlink()
    assert "K" in json.loads(link.read_text())
    capsys.readouterr()

    def full(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", full)
    assert main(["lqr", "van_der_pol", "--json", str(victim)]) == 3
    assert "No space left" in _err_lines(capsys)[0]
    assert victim.read_text() == "{}"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["certificate.json", "fifo",
                                                         "link.json"]


def test_a_warning_is_one_line(tmp_path, capsys):
    """A warning of the tool (a controller whose bias leaves the origin no equilibrium) is
    printed as one 'nlyap: warning:' line, without the source line Python adds."""
    import systems
    from nlyap_opt.design.control import lqr, quadratic_lyapunov, saturated_controller

    s = systems.get("inverted_pendulum")
    res = lqr(s)
    ctrl = saturated_controller(s, res.K, 20.0)
    ctrl.layers[0].bias[:] = 0.3
    V, C = quadratic_lyapunov(res.P).save(tmp_path / "V.json"), ctrl.save(tmp_path / "c.json")
    main(["verify", "--system", "inverted_pendulum", "--lyapunov", str(V), "--controller",
          str(C), "--inner", "0.4", "--outer", "1"])
    err = capsys.readouterr().err.splitlines()
    warned = [ln for ln in err if "not an equilibrium" in ln]
    assert len(warned) == 1 and warned[0].startswith("nlyap: warning: the origin"), err
    assert not any("closed_loop(" in ln or ".py:" in ln for ln in err), err


def test_verify_says_what_an_unknown_needs_and_what_a_dynamics_file_is_about(tmp_path,
                                                                             capsys):
    """With --inner 0 the decrease cannot be decided at the origin: the undecided line
    names what to change (it said 'at resolution None'). With --dynamics the result is about
    the learned φ: a note says so, and how to make it one about f."""
    import numpy as np

    import systems
    from nlyap_opt.design.control import lyapunov_matrix, quadratic_lyapunov
    from nlyap_opt.kernel.network import Layer, Network

    s = systems.get("van_der_pol")
    V = quadratic_lyapunov(lyapunov_matrix(s.A)).save(tmp_path / "V.json")
    base = ["verify", "--system", "van_der_pol", "--lyapunov", str(V), "--outer", "0.5"]
    assert main(base + ["--inner", "0"]) == 2
    out = capsys.readouterr().out
    assert "undecided at the default resolution" in out and "--inner" in out, out
    phi = Network([Layer(np.asarray(s.A, dtype=float), [0.0, 0.0])])
    phi.meta = {"kind": "dynamics"}
    dyn = phi.save(tmp_path / "dynamics.json")
    assert main(base + ["--inner", "0.1", "--dynamics", str(dyn)]) == 0
    err = capsys.readouterr().err
    assert "along the learned φ" in err and "give --eta" in err, err
