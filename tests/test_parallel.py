"""Dask distributed: the client helper, verification on a cluster, the seed portfolio.

Clusters bind to 127.0.0.1, have no dashboard and are closed by the test that starts them.
"""

import contextlib
import json
import os
import socket
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path

import casadi as ca
import numpy as np
import pytest
from certcheck import assert_confirmed

import systems
from baselines.lqr import quadratic_lyapunov
from nlyap_opt.distributed import parallel
from nlyap_opt.distributed.parallel import (
    _starts_from_boxes,
    ahead,
    check,
    dask_client,
    parse_scheduler,
    verify_distributed,
    verifying_on,
)
from nlyap_opt.kernel.errors import BackendUnavailableError, ConfigError
from verification import VerificationProblem, closed_loop_problem, verify

pytest.importorskip("distributed")

P_VDP = np.array([[1.5, -0.5], [-0.5, 1.0]])
#: task modes of verify_distributed this checkout supports (batched needs
#: verify_interval(boxes=...))
MODES = [False] + ([True] if _starts_from_boxes() else [])


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _listening_hosts() -> set:
    import psutil

    return {c.laddr.ip for c in psutil.Process().net_connections(kind="tcp")
            if c.status == psutil.CONN_LISTEN}


def _vdp_problem(outer: float):
    return closed_loop_problem(systems.get("van_der_pol"), quadratic_lyapunov(P_VDP),
                               inner=0.1, outer=outer)


@pytest.fixture(scope="module")
def client():
    with dask_client(workers=2) as c:
        yield c


@pytest.fixture(params=MODES, ids=lambda b: "batched" if b else "fixed-split")
def mode(request, monkeypatch):
    monkeypatch.setattr("nlyap_opt.distributed.parallel._starts_from_boxes", lambda: request.param)
    return request.param


# ----------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("kwargs, match", [
    ({"workers": 0}, "workers must be an integer >= 1"),
    ({"workers": -2}, "workers must be an integer >= 1"),
    ({"workers": 1.5}, "workers must be an integer >= 1"),
    ({"workers": True}, "workers must be an integer >= 1"),
    ({"scheduler": "localhost"}, "tcp://HOST:PORT"),
    ({"scheduler": "tcp://127.0.0.1"}, "tcp://HOST:PORT"),
    ({"scheduler": "http://127.0.0.1:8786"}, "tcp://HOST:PORT"),
    ({"scheduler": "tcp://127.0.0.1:99999"}, "port must be in 1..65535"),
    ({"scheduler": 8786}, "must be a string"),
    ({"workers": 2, "timeout": 0}, "timeout must be a positive"),
])
def test_bad_client_options_are_config_errors(kwargs, match):
    with pytest.raises(ConfigError, match=match) as err:
        with dask_client(**kwargs):
            pass
    assert "\n" not in str(err.value)


def test_scheduler_address_forms():
    assert parse_scheduler("127.0.0.1:8786") == "tcp://127.0.0.1:8786"
    assert parse_scheduler(" tcp://node-1.example:1 ") == "tcp://node-1.example:1"
    assert parse_scheduler("tls://[::1]:8786") == "tls://[::1]:8786"


def test_no_scheduler_at_address_is_a_config_error():
    address = f"tcp://127.0.0.1:{_free_port()}"  # nothing listens there
    t = time.monotonic()
    with pytest.raises(ConfigError, match="no Dask scheduler answered") as err:
        with dask_client(scheduler=address, timeout=2):
            pass
    assert "dask scheduler" in str(err.value) and time.monotonic() - t < 60


def test_missing_dask_names_the_install_command(monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import fails
    with pytest.raises(BackendUnavailableError, match=r"pip install 'dask\[distributed\]'"):
        with dask_client(workers=1):
            pass
    assert isinstance(BackendUnavailableError("x"), ImportError)


def test_bad_verify_options(client):
    with pytest.raises(ConfigError, match="task_boxes"):
        verify_distributed(_vdp_problem(1.0), client, task_boxes=0)
    with pytest.raises(TypeError, match="unknown option 'executor'"):
        verify_distributed(_vdp_problem(1.0), client, executor=None)
    with pytest.raises(TypeError, match="unknown option 'resolutoin'"):
        verify_distributed(_vdp_problem(1.0), client, resolutoin=0.1)


# ----------------------------------------------------------------------------- the cluster
def test_local_cluster_is_local_quiet_and_closed():
    with dask_client(workers=2) as c:
        info = c.scheduler_info()
        address = c.scheduler.address
        assert address.startswith("tcp://127.0.0.1:")
        assert len(info["workers"]) == 2
        assert all(w["nthreads"] == 1 for w in info["workers"].values())
        assert all(a.startswith("tcp://127.0.0.1:") for a in info["workers"])
        # every listening socket (scheduler, its HTTP API, nannies here; workers there) is
        # on the loopback interface
        assert _listening_hosts() == {"127.0.0.1"}
        assert set().union(*c.run(_listening_hosts).values()) == {"127.0.0.1"}
        # worker processes, not threads of this one
        pids = c.run(os.getpid)
        assert len(set(pids.values())) == 2 and os.getpid() not in pids.values()
        # workers keep glibc's adaptive malloc (see dask_client)
        env = c.run(lambda: os.environ.get("MALLOC_TRIM_THRESHOLD_"))
        assert set(env.values()) == {os.environ.get("MALLOC_TRIM_THRESHOLD_")}
    assert c.status == "closed"
    host, port = address.removeprefix("tcp://").rsplit(":", 1)
    with pytest.raises(OSError):  # the scheduler is gone
        socket.create_connection((host, int(port)), timeout=2).close()


# ----------------------------------------------------------------------------- verification
@pytest.mark.parametrize("outer, expected", [(1.0, "verified"), (1.2, "counterexample")])
def test_distributed_verdict_equals_serial(client, mode, outer, expected):
    problem = _vdp_problem(outer)
    serial = verify(problem)
    dist = verify_distributed(problem, client, task_boxes=64)  # small: many hand-outs
    assert serial.status == dist.status == expected
    if expected == "counterexample":
        assert_confirmed(problem, dist.counterexample)
    else:
        assert len(dist.undecided) == 0 and dist.boxes >= 0.5 * serial.boxes


def test_one_and_two_workers_decide_as_serially_with_the_same_boxes(client):
    """Default grains and fine ones, on a 1-worker and the 2-worker cluster: the verdict and
    the boxes processed are the serial run's (every box decided once, by the serial rules),
    and the 4-D check is really cut into tasks on both."""
    from verification import lyapunov_problem

    x = ca.MX.sym("x", 4)
    f = ca.vertcat(-x[1], x[0] - (1 - x[0]**2) * x[1], -x[3], x[2] - (1 - x[2]**2) * x[3])
    V = ca.bilin(ca.DM(np.kron(np.eye(2), P_VDP)), x, x)
    four = lyapunov_problem(x, V, ca.dot(ca.gradient(V, x), f), inner=0.1, outer=0.9)
    problems = [(_vdp_problem(1.0), {"task_boxes": 64}), (four, {})]
    with dask_client(workers=1) as one:
        for problem, opts in problems:
            serial = verify(problem)
            runs = []
            for c in (one, client):
                st: dict = {}
                runs.append((verify_distributed(problem, c, stats=st, **opts), st))
            for res, st in runs:
                assert res.status == serial.status == "verified"
                assert res.boxes == serial.boxes and st["tasks"] > 1


def test_no_task_starts_from_fewer_than_min_task_boxes(client):
    """Open boxes are dealt out in chunks of at least ``min_task_boxes`` (a task that starts
    from a few boxes pays the walker's fixed cost per pass for them); the verdict and the
    boxes processed stay the serial ones. Without the floor, tiny starts happen here."""
    problem = _vdp_problem(1.0)
    serial = verify(problem)
    tiny: dict = {}
    # four tasks per worker: open sets are dealt in eight parts (the default, one per
    # worker, deals them whole)
    verify_distributed(problem, client, task_boxes=64, min_task_boxes=1, stats=tiny,
                       tasks_per_worker=4)
    assert min(tiny["starts"]) < 16
    st: dict = {}
    dist = verify_distributed(problem, client, task_boxes=64, min_task_boxes=16, stats=st,
                              tasks_per_worker=4)
    assert dist.status == serial.status == "verified" and dist.boxes == serial.boxes
    assert st["starts"] and min(st["starts"]) >= 16
    # the timeline: one entry per task, the root first, each on one worker's clock
    # (ends after it starts); its boxes are the check's
    tl = st["timeline"]
    assert len(tl) == st["tasks"] == len(st["starts"]) + 1
    assert all(s <= e for _, s, e, _, _ in tl)
    assert sum(b for *_, b in tl) == dist.boxes
    assert {p for p, *_ in tl[1:]} == set(st["cpu_by_worker"])
    # default: the root processes a quarter batch first, so a small check is decided there
    small: dict = {}
    res = verify_distributed(problem, client, stats=small)
    assert res.status == "verified" and (small["tasks"] == 1) is (serial.boxes <= 2048)


def test_counterexample_found_by_branching_not_presearch(client, mode):
    """No pre-search: the counterexample comes from a worker's box, confirmed there."""
    problem = _vdp_problem(1.2)
    dist = verify_distributed(problem, client, presearch=0, task_boxes=16)
    assert dist.status == "counterexample"
    assert_confirmed(problem, dist.counterexample)
    # every confirmed one (coarse resolution: the violating set is not ground down)
    all_found = verify_distributed(problem, client, presearch=0, stop_at_first=False,
                                   resolution=0.05, task_boxes=64)
    serial = verify(problem, presearch=0, stop_at_first=False, resolution=0.05)
    assert all_found.status == "counterexample" and len(all_found.counterexamples) >= 2
    assert abs(len(all_found.counterexamples) - len(serial.counterexamples)) <= \
        0.5 * len(serial.counterexamples)
    for c in all_found.counterexamples[:5]:
        assert_confirmed(problem, c)


def test_unknown_stays_unknown(client, mode):
    x = ca.MX.sym("x", 1)
    problem = VerificationProblem(x, [[-1, 1]], [], [(x - 0.3) * (0.3 - x) - 1e-12])
    serial = verify(problem, resolution=0.1, presearch=0)
    dist = verify_distributed(problem, client, resolution=0.1, presearch=0, task_boxes=4)
    assert serial.status == dist.status == "unknown"
    assert len(dist.undecided) > 0
    assert np.all(dist.undecided[:, :, 1] - dist.undecided[:, :, 0] <= 0.1)


def test_box_budget_gives_unknown_never_verified(client, mode):
    problem = _vdp_problem(1.0)
    serial = verify(problem, max_boxes=40, initial_boxes=4)
    dist = verify_distributed(problem, client, max_boxes=40, initial_boxes=4, task_boxes=16)
    assert serial.status == dist.status == "unknown" and len(dist.undecided) > 0


def test_keep_leaves_cover_the_root_box(client):
    problem = _vdp_problem(1.0)
    dist = verify_distributed(problem, client, keep_leaves=True, task_boxes=64)
    assert dist.status == "verified"
    vol = sum(np.prod(leaf["hi"] - leaf["lo"], axis=1).sum() for leaf in dist.leaves)
    assert vol == pytest.approx(np.prod(np.diff(problem.box, axis=1)), rel=1e-12)


def test_unpickled_copies_of_a_problem_share_their_compiled_graphs():
    """A worker receiving the same problem in many tasks compiles its graphs once: every
    unpickled copy holds the same Function objects (the walker caches per object)."""
    import pickle

    from nlyap_opt.kernel.walker import compile_function

    problem = _vdp_problem(1.0)
    problem.second_order_functions
    a, b = (pickle.loads(pickle.dumps(problem)) for _ in range(2))
    assert a.function_jacobian is b.function_jacobian and a.jacobian is b.jacobian
    assert a.second_order_functions[1] is b.second_order_functions[1]
    assert compile_function(a.function_jacobian) is compile_function(b.function_jacobian)
    assert verify(a).status == verify(problem).status == "verified"


def test_executor_hook_of_verify_runs_on_dask(client):
    for outer, expected in ((1.0, "verified"), (1.2, "counterexample")):
        problem = _vdp_problem(outer)
        res = verify(problem, executor=client.get_executor(), n_tasks=4)
        assert res.status == verify(problem).status == expected


# ------------------------------------------------------- the certificate's checks on Dask
def _counting(monkeypatch):
    calls = []
    real = parallel.verify_distributed

    def counted(problem, client, **options):
        res = real(problem, client, **options)
        calls.append(res.status)
        return res

    monkeypatch.setattr(parallel, "verify_distributed", counted)
    return calls


@pytest.mark.parametrize("outer", [1.0, 1.2, 1.6])
def test_check_on_a_cluster_returns_the_serial_result(client, monkeypatch, outer):
    """``check`` inside ``verifying_on``: the verdict is decided on the cluster, and every
    result (the counterexample and its point too) is the serial one."""
    problem = _vdp_problem(outer)
    serial = verify(problem)
    calls = _counting(monkeypatch)
    with verifying_on(client):
        res = check(problem)
    assert calls, "the cluster was not used"
    assert res.status == serial.status
    if serial.status == "counterexample":
        assert calls == ["counterexample"]  # decided there (and again serially unless the
        # root task found it alone: then it is the serial run's own first steps)
        np.testing.assert_array_equal(res.counterexample.point, serial.counterexample.point)
        assert res.counterexample.property == serial.counterexample.property
        assert [c.point.tolist() for c in res.counterexamples] == \
            [c.point.tolist() for c in serial.counterexamples]
    with verifying_on(None):                         # no cluster: serial
        calls.clear()
        assert check(problem).status == serial.status and not calls


@pytest.mark.parametrize("outer, presearch, batch, alone", [
    (1.6, 500, 8192, True), (1.2, 0, 8192, True), (1.15, 0, 8192, True), (1.15, 0, 64, False)])
def test_root_task_counterexample_is_the_serial_one(client, monkeypatch, outer, presearch,
                                                    batch, alone):
    """A counterexample the root task finds alone (pre-search, its first batch) is the
    serial run's, to the last bit: ``check`` keeps it without deciding again. One found by
    a branch task (the root's batch of 64 boxes is too small to reach it) is decided again
    serially. Either way, the result is the serial one."""
    import verification

    problem = _vdp_problem(outer)
    serial = verify(problem, presearch=presearch, batch=batch)
    st: dict = {}
    dist = verify_distributed(problem, client, stats=st, presearch=presearch, batch=batch)
    assert serial.status == dist.status == "counterexample" and (st["tasks"] == 1) is alone
    if alone:
        np.testing.assert_array_equal(dist.counterexample.point, serial.counterexample.point)
        assert [c.point.tolist() for c in dist.counterexamples] == \
            [c.point.tolist() for c in serial.counterexamples]
    serial_calls = []
    real = verification.verify
    monkeypatch.setattr(verification, "verify",
                        lambda *a, **k: serial_calls.append(1) or real(*a, **k))
    with verifying_on(client):
        res = check(problem, presearch=presearch, batch=batch)
    assert len(serial_calls) == (not alone)
    np.testing.assert_array_equal(res.counterexample.point, serial.counterexample.point)
    assert res.counterexample.property == serial.counterexample.property


def test_hand_back_evaluates_no_box_twice():
    """``hand_back``: a task that spends its budget hands back the halves of the boxes it
    would still bisect, unevaluated, so that the tasks together process exactly the serial
    run's boxes; without it the boxes come back whole (undecided) and are evaluated again."""
    from verification.verify import verify_interval

    problem = _vdp_problem(1.0)
    serial = verify(problem)
    assert serial.status == "verified"
    first = verify_interval(problem, max_boxes=1, hand_back=True)
    total, open_ = first.boxes, first.open
    assert first.status == "unknown" and len(first.undecided) == 0 and len(open_)
    while len(open_):
        r = verify_interval(problem, boxes=open_, presearch=0, max_boxes=500, hand_back=True)
        assert r.status != "counterexample" and len(r.undecided) == 0
        total, open_ = total + r.boxes, r.open
    assert total == serial.boxes
    whole = verify_interval(problem, max_boxes=1)   # the old hand-out: boxes come back whole
    assert whole.open is None and len(whole.undecided) == len(first.open) // 2


# ------------------------------------------------------------------ checks ahead of turn
def _ahead_threads():
    return [t for t in __import__("threading").enumerate() if t.name == "nlyap-ahead"]


def test_ahead_without_a_cluster_runs_where_its_result_is_asked_for():
    """Serially ``ahead`` starts nothing: ``fn`` runs at ``result()`` (once), not at all if
    the result is never asked for, and its exception is raised there."""
    calls = []

    def fn(v):
        calls.append(v)
        if v < 0:
            raise ValueError("negative")
        return 2 * v

    with ahead(fn, 3) as job:
        assert calls == [] and not _ahead_threads()
        assert job.result() == 6 and job.result() == 6 and calls == [3]
    with ahead(fn, 4):
        pass
    assert calls == [3]
    with pytest.raises(ValueError, match="negative"), ahead(fn, -1) as job:
        job.result()


def _record_spans(monkeypatch) -> list:
    """``(thread name, start, end)`` of every distributed check from now on."""
    import threading

    spans = []
    real = parallel.verify_distributed

    def spanned(problem, client, **options):
        t0 = time.perf_counter()
        res = real(problem, client, **options)
        spans.append((threading.current_thread().name, t0, time.perf_counter()))
        return res

    monkeypatch.setattr(parallel, "verify_distributed", spanned)
    return spans


def test_ahead_on_a_cluster_runs_beside_the_caller_with_serial_verdicts(client, monkeypatch):
    """On a cluster the job's checks run while the caller waits for its own: the job's first
    check starts before the caller's first check ends (the caller hands over its turn while
    it waits), and both verdicts, counterexample points included, are the serial ones."""

    spans = _record_spans(monkeypatch)
    pa, pb = _vdp_problem(1.0), _vdp_problem(1.2)
    sa, sb = verify(pa), verify(pb)
    with verifying_on(client), ahead(check, pb) as job:
        ra = check(pa)
        rb = job.result()
    assert (ra.status, rb.status) == (sa.status, sb.status) == ("verified", "counterexample")
    np.testing.assert_array_equal(rb.counterexample.point, sb.counterexample.point)
    main = [s for s in spans if s[0] != "nlyap-ahead"]
    side = [s for s in spans if s[0] == "nlyap-ahead"]
    assert main and side and side[0][1] < main[0][2]
    assert not _ahead_threads() and not parallel._TURN.locked()


def test_ahead_left_early_stops_its_job_at_the_next_wait(client):
    """Leaving the block without the result (an early return: a level that failed) stops
    the job at its next wait for the cluster, before any of its checks completes, and gives
    the turn back; so does leaving it on an exception (without waiting for the job)."""
    done = []

    def many():
        for _ in range(50):
            done.append(check(_vdp_problem(1.0)).status)

    with verifying_on(client):
        with ahead(many):
            pass
        assert done == [] and not _ahead_threads() and not parallel._TURN.locked()
        with pytest.raises(KeyError), ahead(many):
            raise KeyError("unwinding")
    for t in _ahead_threads():
        t.join(60)
    assert done == [] and not parallel._TURN.locked()


def test_certify_roa_on_a_cluster_checks_c_beside_a_and_b(client, monkeypatch):
    """``certify_roa`` inside ``verifying_on``: condition (c) runs ahead, beside (a) and (b),
    and the certificate (status, level, checks, proved ellipse) is the serial one. (c)'s
    whole-set Jacobian test is switched off: it would decide this small ellipse at once."""
    from nlyap_opt.certification.certificate import RoaProblem, certify_roa
    from nlyap_opt.certification.roa import TaylorDecrease

    monkeypatch.setattr(TaylorDecrease, "contracts", lambda self, *a, **k: False)

    s = systems.get("van_der_pol")
    prob = RoaProblem(s, quadratic_lyapunov(P_VDP), inner=0.3, outer=1.5)
    serial = certify_roa(prob, 1.0, log=lambda m: None)
    names = []
    real = parallel.verify_distributed
    monkeypatch.setattr(parallel, "verify_distributed", lambda *a, **k: names.append(
        __import__("threading").current_thread().name) or real(*a, **k))
    with verifying_on(client):
        dist = certify_roa(prob, 1.0, log=lambda m: None)
    assert serial.status.value == dist.status.value == "certified"
    assert (dist.level, dist.checks) == (serial.level, serial.checks)
    np.testing.assert_array_equal(dist.inner_ellipse.P, serial.inner_ellipse.P)
    assert dist.inner_ellipse.form == serial.inner_ellipse.form
    assert "nlyap-ahead" in names and "MainThread" in names
    # a level search may end without a level: there (c) waits for a certified level
    names.clear()
    with verifying_on(client):
        found = certify_roa(prob, 1.0, search=True, log=lambda m: None)
    assert found.status.value == "certified"
    assert names and "nlyap-ahead" not in names


@pytest.mark.parametrize("inner", [0.3, 2.5])
def test_saved_shell_form_on_a_cluster_checks_its_core_beside_the_shell(client, monkeypatch,
                                                                        inner):
    """Re-checking a saved ``shell`` form on a cluster: the core ellipse's check runs in a
    thread of its own while the shell's runs; the result is the serial one, also where the
    shell fails (0.3: certified; 2.5: a counterexample of the shell) and the core's result
    is not used; no thread or turn is left behind. The shell goes to bisection here (the
    whole-set tests are switched off: they would decide Van der Pol's shell and core at once)."""

    from nlyap_opt.certification.roa import TaylorDecrease, certify_inner_ellipse

    monkeypatch.setattr(TaylorDecrease, "check", lambda self, *a, **k: None)
    monkeypatch.setattr(TaylorDecrease, "contracts", lambda self, *a, **k: False)

    form, s = "shell r=0.075 + minors", systems.get("van_der_pol")
    serial = certify_inner_ellipse(s, None, inner, P=P_VDP, form=form)
    spans = _record_spans(monkeypatch)
    with verifying_on(client):
        dist = certify_inner_ellipse(s, None, inner, P=P_VDP, form=form)
    assert (dist["status"], dist["verdict"], dist["form"], dist["level"]) == \
        (serial["status"], serial["verdict"], serial["form"], serial["level"])
    if inner == 0.3:
        assert serial["status"] == "certified"
        main = [sp for sp in spans if sp[0] != "nlyap-ahead"]
        side = [sp for sp in spans if sp[0] == "nlyap-ahead"]
        assert main and side and side[0][1] < main[0][2]  # the core started during the shell
    else:
        assert "counterexample" in serial["status"]
    assert not _ahead_threads() and not parallel._TURN.locked()


def test_ahead_when_false_starts_nothing_on_a_cluster(client):
    calls = []
    with verifying_on(client), ahead(calls.append, 1, when=False) as job:
        assert not _ahead_threads() and calls == []
        assert job.result() is None and calls == [1]


@pytest.mark.slow  # 5 s idle: a run on a 2-worker cluster
def test_run_with_dask_certificate_stage_gives_the_serial_certificate(client, tmp_path,
                                                                      monkeypatch):
    """``nlyap run NAME --scheduler ADDR`` (no ``--seeds``): the certificate stage's checks
    run on the cluster; status, level, area, checks and artifact hashes are the serial run's."""
    from nlyap_opt.interface.cli import main
    from nlyap_opt.workflow.configs import make_config
    from nlyap_opt.workflow.pipeline import run

    cfg = make_config("van_der_pol", "fast")
    serial = run("van_der_pol", cfg, tmp_path / "serial", known_dynamics=True,
                 log=lambda m: None)
    calls = _counting(monkeypatch)
    code = main(["run", "van_der_pol", "--preset", "fast", "--known-dynamics",
                 "--scheduler", client.scheduler.address, "--out", str(tmp_path / "dask")])
    assert calls and all(c == "verified" for c in calls)
    assert serial.certified and code == 0
    a, b = (json.loads((d / "certificate.json").read_text())
            for d in (tmp_path / "serial", tmp_path / "dask"))
    for key in ("status", "level", "certified_area", "checks", "inner_ellipse", "artifacts"):
        assert a.get(key) == b.get(key), key
    # the re-check of the saved certificate runs its checks on the cluster too
    calls.clear()
    code = main(["verify", "--certificate", str(tmp_path / "serial"),
                 "--scheduler", client.scheduler.address])
    assert code == 0 and calls and all(c == "verified" for c in calls)


@pytest.mark.parametrize("kwargs, match", [({"scheduler": "localhost"}, "tcp://HOST:PORT"),
                                           ({"workers": 0}, "workers must be an integer")])
def test_run_with_bad_dask_options_fails_before_any_stage(tmp_path, kwargs, match):
    from nlyap_opt.workflow.configs import make_config
    from nlyap_opt.workflow.pipeline import run

    cfg = make_config("van_der_pol", "fast")
    with pytest.raises(ConfigError, match=match):
        run("van_der_pol", cfg, tmp_path, known_dynamics=True, log=lambda m: None, **kwargs)
    assert not (tmp_path / "V.json").exists() and not (tmp_path / "stages.json").exists()


@pytest.mark.slow  # 8-29 s on the shared 2 cores: three Python processes start
def test_existing_cluster_scheduler_and_two_worker_processes(tmp_path):
    """`dask scheduler` + two `dask worker` processes on 127.0.0.1, used through
    ``scheduler=``; the tool connects and leaves the cluster running."""
    dask_cli = Path(sys.executable).with_name("dask")
    if not dask_cli.exists():
        pytest.skip("the `dask` command is not installed next to this Python")
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = dict(os.environ, MALLOC_TRIM_THRESHOLD_="1073741824",
               MALLOC_MMAP_THRESHOLD_="33554432")
    logs = open(tmp_path / "cluster.log", "w")
    procs = [subprocess.Popen([str(dask_cli), "scheduler", "--host", "127.0.0.1", "--port",
                               str(port), "--no-dashboard"], stdout=logs, stderr=logs,
                              env=env, cwd=tmp_path)]
    try:
        for i in range(2):
            procs.append(subprocess.Popen(
                [str(dask_cli), "worker", address, "--host", "127.0.0.1", "--nthreads", "1",
                 "--no-dashboard", "--no-nanny", "--name", f"w{i}", "--death-timeout", "60",
                 "--local-directory", str(tmp_path / f"w{i}")],
                stdout=logs, stderr=logs, env=env, cwd=tmp_path))
        # a closed port is refused at once: wait until the scheduler listens
        t0 = time.monotonic()
        while time.monotonic() - t0 < 60:
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 1):
                break
            time.sleep(0.2)
        with dask_client(workers=2, scheduler=address, timeout=60) as c:
            assert len(c.scheduler_info()["workers"]) == 2
            for outer, expected in ((1.0, "verified"), (1.2, "counterexample")):
                problem = _vdp_problem(outer)
                res = verify_distributed(problem, c, task_boxes=64)
                assert res.status == verify(problem).status == expected
        assert all(p.poll() is None for p in procs), "the tool must not close the cluster"
        with pytest.raises(ConfigError, match=r"has 2 worker\(s\)"):
            with dask_client(workers=3, scheduler=address, timeout=2):
                pass
        assert all(p.poll() is None for p in procs)
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait(timeout=10)
        logs.close()


# ----------------------------------------------------------------------------- portfolio
def _fast_vdp():
    from nlyap_opt.workflow.configs import get_config

    return get_config("van_der_pol", "fast")


@pytest.mark.parametrize("seeds, match", [
    (0, "seeds must be >= 1"), ([], "seeds must be a count"), ([1, -2], "seeds must be"),
    ([0, 0], "distinct"), (True, "seeds must be"), ("3", "seeds must be"),
])
def test_portfolio_bad_seeds(tmp_path, seeds, match):
    from nlyap_opt.workflow.portfolio import run_portfolio

    with pytest.raises(ConfigError, match=match):
        run_portfolio("van_der_pol", _fast_vdp(), tmp_path, seeds=seeds, workers=1)
    assert not list(tmp_path.iterdir())  # nothing started


def test_portfolio_bad_system_or_config_fails_before_any_work(tmp_path):
    from nlyap_opt.kernel.errors import UnknownNameError
    from nlyap_opt.workflow.portfolio import run_portfolio

    with pytest.raises(UnknownNameError, match="no_such_system"):
        run_portfolio("no_such_system", _fast_vdp(), tmp_path, seeds=2, workers=1)
    bad = _fast_vdp().to_json()
    bad["train"] = dict(bad["train"], steps=-1)
    with pytest.raises(ConfigError, match="steps"):
        run_portfolio("van_der_pol", bad, tmp_path, seeds=2, workers=1)
    assert not list(tmp_path.iterdir())


def test_seed_config_sets_both_training_seeds():
    from nlyap_opt.workflow.portfolio import seed_config

    cfg = _fast_vdp()
    c3 = seed_config(cfg, 3)
    assert c3["train"]["seed"] == c3["cegis"]["seed"] == 3
    assert "seed" not in cfg["train"] or cfg["train"]["seed"] != 3  # the input is untouched
    assert {k: v for k, v in c3.items() if k not in ("train", "cegis")} == \
        {k: v for k, v in cfg.items() if k not in ("train", "cegis")}


@pytest.mark.slow  # 20-40 s: the default tier stays near 5 min on 2 cores
def test_two_seed_portfolio_keeps_the_largest_certified_area(client, tmp_path):
    """2 seeds of the fast Van der Pol preset (true f) on the 2-worker cluster, then the
    same seeds on 1 worker: the same candidates, bit for bit, and the same choice."""
    from nlyap_opt.workflow.portfolio import run_portfolio, warm_workers

    cfg = _fast_vdp()
    lines = []
    warmed = warm_workers(client)  # a kept cluster's warm-up changes no result (below)
    assert len(warmed) == 2 and all(v >= 0.0 for v in warmed)
    res = run_portfolio("van_der_pol", cfg, tmp_path / "w2", seeds=[0, 1],
                        scheduler=client.scheduler.address, known_dynamics=True,
                        log=lines.append)
    assert [r.seed for r in res.runs] == [0, 1] and res.workers == 2
    assert all(r.cpu_seconds > 0.0 for r in res.runs)  # the worker's CPU for the seed
    certified = [r for r in res.runs if r.certified]
    assert certified, res.runs
    top = max(r.certified_area for r in certified)
    assert res.best.certified_area == top
    assert res.best.seed == min(r.seed for r in certified if r.certified_area == top)
    for r in res.runs:  # each seed is a full pipeline run of its own, with its seed
        summary = json.loads((tmp_path / "w2" / r.dir / "certificate.json").read_text())
        assert summary["status"] == r.status
        if r.certified:
            assert summary["level"] == r.level and summary["certified_area"] == r.certified_area
    v = [json.loads((tmp_path / "w2" / r.dir / "V.json").read_text()) for r in res.runs]
    assert v[0] != v[1]  # the seeds train different V
    # the files
    pj = json.loads((tmp_path / "w2" / "portfolio.json").read_text())
    assert pj["best"]["seed"] == res.best.seed and len(pj["runs"]) == 2
    md = (tmp_path / "w2" / "portfolio.md").read_text()
    assert md.count("| 0") + md.count("| 1") >= 2 and "(best)" in md
    best = tmp_path / "w2" / "best"
    assert best.is_symlink() and (best / "certificate.json").exists()
    assert any("best: seed" in m for m in lines)
    # 1 worker (a local cluster started by the call): the same result
    one = run_portfolio("van_der_pol", cfg, tmp_path / "w1", seeds=[0, 1], workers=1,
                        known_dynamics=True, log=lambda m: None)
    assert one.workers == 1 and one.best.seed == res.best.seed
    def strip(runs):
        return [{k: v for k, v in asdict(r).items() if k not in ("seconds", "cpu_seconds")}
                for r in runs]

    assert strip(one.runs) == strip(res.runs)


@pytest.mark.slow  # ~17 s idle on a 2-worker cluster
def test_learned_dynamics_are_learned_once_and_shared(client, tmp_path):
    from nlyap_opt.workflow.portfolio import run_portfolio

    res = run_portfolio("van_der_pol", _fast_vdp(), tmp_path, seeds=[2, 0],
                        scheduler=client.scheduler.address, log=lambda m: None)
    assert res.shared_dynamics == "seed_2"
    first, other = tmp_path / "seed_2", tmp_path / "seed_0"
    assert "[dynamics] learning" in (first / "run.log").read_text()
    log0 = (other / "run.log").read_text()
    assert "[dynamics] loaded from" in log0 and "[dynamics] learning" not in log0
    stages = [json.loads((d / "stages.json").read_text())["dynamics"] for d in (first, other)]
    assert stages[0] == stages[1]
    for name in stages[0]["files"]:
        assert (first / name).read_bytes() == (other / name).read_bytes()
    assert [r.seed for r in res.runs] == [2, 0]
    assert json.loads((tmp_path / "portfolio.json").read_text())["setting"] == "learned"
