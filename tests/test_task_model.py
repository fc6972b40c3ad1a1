"""How verification work is cut into tasks, and the task-level speed-up model (no Dask).

:class:`~nlyap_opt.distributed.parallel.SimulatedCluster` runs
:func:`~nlyap_opt.distributed.parallel.verify_distributed`'s task graph in this process and
schedules it on virtual workers: the verdicts and box counts are those of a real cluster run, so
they are checked against the serial verifier here.
"""

import numpy as np
import pytest

import systems
from baselines.lqr import quadratic_lyapunov
from nlyap_opt.distributed.parallel import (
    SimulatedCluster,
    _deal_boxes,
    model_speedups,
    pass_boxes,
    task_defaults,
    verify_distributed,
)
from nlyap_opt.kernel.errors import ConfigError
from verification import VerificationProblem, closed_loop_problem, verify
from verification.verify import verify_interval

P_VDP = np.array([[1.5, -0.5], [-0.5, 1.0]])


def _vdp_problem(outer: float):
    return closed_loop_problem(systems.get("van_der_pol"), quadratic_lyapunov(P_VDP),
                               inner=0.1, outer=outer)


# ------------------------------------------------------------------------- dealing boxes
@pytest.mark.parametrize("k, parts", [(10, 3), (7, 7), (5, 9), (1, 4), (64, 8)])
def test_deal_boxes_is_a_partition_in_queue_order(k, parts):
    boxes = np.arange(float(k)).reshape(k, 1, 1) * np.ones((1, 1, 2))
    shares = _deal_boxes(boxes, parts)
    assert len(shares) == min(parts, k)
    sizes = [len(s) for s in shares]
    assert max(sizes) - min(sizes) <= 1 and sum(sizes) == k
    ids = np.concatenate([s[:, 0, 0] for s in shares])
    assert sorted(ids.tolist()) == list(range(k))      # every box once
    for s in shares:                                    # queue order kept inside a share
        assert np.all(np.diff(s[:, 0, 0]) > 0)


def test_deal_boxes_spreads_a_cluster_of_hard_boxes():
    """Neighbouring queue entries (a cluster) go to different shares, not to one chunk."""
    shares = _deal_boxes(np.zeros((40, 2, 2)) + np.arange(40.0)[:, None, None], 4)
    cluster = set(range(8, 16))
    per_share = [len(cluster & set(s[:, 0, 0].astype(int).tolist())) for s in shares]
    assert per_share == [2, 2, 2, 2]


def test_task_grains_get_finer_with_more_workers():
    rows = [task_defaults(w) for w in (1, 2, 4, 8, 16, 64)]
    for key in ("task_boxes", "root_boxes", "min_task_boxes"):
        vals = [r[key] for r in rows]
        assert all(a >= b for a, b in zip(vals, vals[1:])), (key, vals)
        assert min(vals) >= 1
    # a task still starts from enough boxes to amortise a walker pass, and the root task
    # of 16 workers does no more than the first grid's pass
    assert task_defaults(16)["min_task_boxes"] >= 128 and task_defaults(16)["root_boxes"] <= 256
    small = task_defaults(16, batch=8)
    assert small["task_boxes"] <= 8 and all(v >= 1 for v in small.values())


# ---------------------------------------------------------------------- the schedule model
def test_simulated_cluster_is_list_scheduling():
    """Tasks start on the first free virtual worker in submission order: costs 3, 3, 2 on
    two workers end at 3, 3 and 5."""
    sim = SimulatedCluster(2)
    run = sim._runner(None)
    for c in (3, 3, 2):
        run.submit(lambda _p, c: {"boxes": c}, c)
    finished = []
    while (nxt := run.next()) is not None:
        finished.append((run.now, nxt[1]["boxes"]))
    run.close()
    assert finished == [(3.0, 3), (3.0, 3), (5.0, 2)]
    assert sim.calls == [{"makespan": 5.0, "work": 8.0, "tasks": 3, "start": 0.0,
                          "boxes": 8}]
    assert sim.speedup() == pytest.approx(8 / 5)


def test_simulated_cluster_rejects_bad_arguments():
    with pytest.raises(ConfigError, match="workers must be an integer"):
        SimulatedCluster(0)
    with pytest.raises(ConfigError, match="cost must be"):
        SimulatedCluster(2, cost="seconds")


@pytest.mark.parametrize("workers", [1, 2, 16])
@pytest.mark.parametrize("outer, expected", [(1.0, "verified"), (1.2, "counterexample")])
def test_simulated_runs_decide_as_the_serial_verifier(workers, outer, expected):
    problem = _vdp_problem(outer)
    serial = verify(problem, presearch=0)
    sim = SimulatedCluster(workers)
    st: dict = {}
    res = verify_distributed(problem, sim, presearch=0, task_boxes=64, stats=st)
    assert res.status == serial.status == expected
    if expected == "verified":
        # every box decided once, by the serial rules: the serial run's boxes exactly
        assert res.boxes == serial.boxes == sim.work() == sum(st["task_boxes"])
        assert st["tasks"] >= 2  # really cut into tasks
        assert 1.0 <= sim.speedup() <= workers + 1e-9


def test_each_virtual_worker_compiles_a_problem_once(monkeypatch):
    """By CPU seconds, a virtual worker pays compiling a problem's graphs before its first
    task of it (as each worker process does), once whatever its number of tasks; the
    verdict and boxes stay the serial ones."""
    from nlyap_opt.distributed import parallel

    problem = _vdp_problem(1.0)
    assert parallel._compile_seconds(problem) > 0
    monkeypatch.setattr(parallel, "_compile_seconds", lambda p: 100.0)
    serial = verify(problem, presearch=0)
    for workers in (1, 2):
        sim, st = SimulatedCluster(workers, "cpu"), {}
        res = verify_distributed(problem, sim, presearch=0, task_boxes=32, root_boxes=1,
                                 min_task_boxes=8, stats=st)
        assert (res.status, res.boxes) == (serial.status, serial.boxes)
        assert st["tasks"] >= workers + 1  # the root task, then tasks on every worker
        # the tasks' own CPU seconds are far below 100: one compile per worker used
        assert 100 * workers <= sim.work() < 100 * workers + 50
        # the second worker's first task follows the root task's open boxes: it compiles then
        assert 100 * workers <= sim.makespan() < 100 * workers + 50


def test_compile_seconds_is_the_median_of_three_timings(monkeypatch):
    """The compile charged to each virtual worker is the median of three timings: one
    timing that holds a pause (a full garbage collection of this process's heap, which a
    worker's small heap does not pay) does not move it."""
    import gc
    import time

    from nlyap_opt.distributed import parallel

    problem = _vdp_problem(1.0)
    n_funs = []
    real = parallel.Program

    def program(f):
        if not n_funs:   # the first compile of the first timing: a 0.2 s pause
            t = time.thread_time()
            while time.thread_time() - t < 0.2:
                pass
        n_funs.append(f)
        return real(f)

    monkeypatch.setattr(parallel, "Program", program)
    # no real collection in the other two timings (after thousands of tests the heap's can
    # take longer than the planted pause, which would then be the median)
    was = gc.isenabled()
    gc.disable()
    try:
        seconds = parallel._compile_seconds(problem)
    finally:
        if was:
            gc.enable()
    assert len(n_funs) % 3 == 0 and len(n_funs) >= 3   # three timings of the same graphs
    assert 0 < seconds < 0.2


def test_unknown_stays_unknown_in_the_model():
    import casadi as ca

    x = ca.MX.sym("x", 1)
    problem = VerificationProblem(x, [[-1, 1]], [], [(x - 0.3) * (0.3 - x) - 1e-12])
    res = verify_distributed(problem, SimulatedCluster(4), resolution=0.1, presearch=0,
                             task_boxes=4)
    assert res.status == verify(problem, resolution=0.1, presearch=0).status == "unknown"


def test_model_speedups_are_deterministic_and_bounded():
    problem = _vdp_problem(1.0)

    def run(client):
        return verify_distributed(problem, client, presearch=0, task_boxes=32)

    a = model_speedups(run, workers=(2, 4))
    b = model_speedups(run, workers=(4, 2))
    assert a == b and sorted(a) == [1, 2, 4]
    assert a[1]["speedup"] == 1.0
    for w, row in a.items():
        assert row["work"] == a[1]["work"]        # same boxes on every worker count
        assert 1.0 <= row["speedup"] <= w + 1e-9
        assert row["efficiency"] == pytest.approx(row["speedup"] / w)
    assert a[4]["speedup"] >= a[2]["speedup"] - 1e-9 and a[4]["speedup"] > 1.0


# ------------------------------------------------------------------ tails handed back
def test_hand_back_below_evaluates_no_box_twice():
    """A queue that thins below ``hand_back_below`` comes back open, unevaluated: carrying
    on from the open boxes processes exactly the serial run's boxes."""
    problem = _vdp_problem(1.0)
    serial = verify_interval(problem, presearch=0)
    total, passes = 0, 0
    r = verify_interval(problem, presearch=0, hand_back=True, hand_back_below=64)
    while True:
        total += r.boxes
        passes += 1
        assert r.status in ("verified", "unknown") and not len(r.undecided)
        if r.open is None or not len(r.open):
            break
        r = verify_interval(problem, boxes=r.open, presearch=0, hand_back=True,
                            hand_back_below=64)
    assert passes > 1 and total == serial.boxes and serial.status == "verified"


def _overlap(a: dict, b: dict) -> bool:
    """Whether two modelled calls ran side by side (their modelled spans overlap)."""
    return a["start"] < b["start"] + b["makespan"] and b["start"] < a["start"] + a["makespan"]


def test_a_certificate_modelled_on_a_simulated_cluster_is_the_serial_one(monkeypatch):
    """``verifying_on(SimulatedCluster(W))``: every check of the certificate goes through
    the model, condition (c) beside (a) and (b) as on a cluster (its thread ends with the
    call), the model is deterministic, and the certificate is the serial one. (c)'s
    whole-set Jacobian test is switched off: it would decide this small ellipse at once."""
    import threading

    from nlyap_opt.certification.certificate import RoaProblem, certify_roa
    from nlyap_opt.certification.roa import TaylorDecrease
    from nlyap_opt.distributed.parallel import verifying_on

    monkeypatch.setattr(TaylorDecrease, "contracts", lambda self, *a, **k: False)

    prob = RoaProblem(systems.get("van_der_pol"), quadratic_lyapunov(P_VDP), inner=0.3,
                      outer=1.5)
    serial = certify_roa(prob, 1.0, log=lambda m: None)
    before = threading.active_count()
    calls = []
    for _ in range(2):
        sim = SimulatedCluster(4)
        with verifying_on(sim):
            modelled = certify_roa(prob, 1.0, log=lambda m: None)
            assert threading.active_count() == before
        assert serial.status.value == modelled.status.value == "certified"
        assert (modelled.level, modelled.checks) == (serial.level, serial.checks)
        np.testing.assert_array_equal(modelled.inner_ellipse.P, serial.inner_ellipse.P)
        assert modelled.inner_ellipse.form == serial.inner_ellipse.form
        assert len(sim.calls) >= 2 and sim.work() > 0 and 1.0 <= sim.speedup() <= 4
        calls.append(sim.calls)
    assert calls[0] == calls[1]  # boxes as cost: the same schedule every time
    # (c) started with (a): some call overlaps another in modelled time, and the whole
    # takes less than its calls one after another
    assert any(_overlap(a, b) for i, a in enumerate(calls[0]) for b in calls[0][i + 1:])
    assert sim.makespan() < sum(c["makespan"] for c in sim.calls)


@pytest.mark.parametrize("inner, verdict", [(0.3, "certified"), (2.5, "counterexample")])
def test_a_saved_shell_form_checks_its_core_beside_the_shell_as_serially(inner, verdict,
                                                                          monkeypatch):
    """Re-checking a saved ``shell`` form on a cluster runs the core ellipse's check beside
    the shell's (both start at once); the result is the serial one, and a shell that fails
    decides it as serially (the core's result is not used). The shell goes to bisection
    here (the whole-set tests are switched off: they would decide Van der Pol's shell and
    core at once)."""
    from nlyap_opt.certification.roa import TaylorDecrease, certify_inner_ellipse
    from nlyap_opt.distributed.parallel import verifying_on

    monkeypatch.setattr(TaylorDecrease, "check", lambda self, *a, **k: None)
    monkeypatch.setattr(TaylorDecrease, "contracts", lambda self, *a, **k: False)

    form = "shell r=0.075 + minors"
    system = systems.get("van_der_pol")
    serial = certify_inner_ellipse(system, None, inner, P=P_VDP, form=form)
    sim = SimulatedCluster(4)
    with verifying_on(sim):
        modelled = certify_inner_ellipse(system, None, inner, P=P_VDP, form=form)
    assert serial["verdict"].value == modelled["verdict"].value
    assert serial["status"] == modelled["status"]
    assert verdict in serial["status"]
    assert (serial["form"], serial["level"]) == (modelled["form"], modelled["level"])
    np.testing.assert_array_equal(serial["box"], modelled["box"])
    if verdict == "certified":
        assert len(sim.calls) == 2 and _overlap(*sim.calls)
        assert [c["start"] for c in sim.calls] == [0.0, 0.0]
        assert sim.makespan() < sim.work()


# ------------------------------------------------------------- the fixed cost of a pass
def test_pass_boxes_is_deterministic_and_follows_calls_per_scalar():
    """Scalar graphs (every operation a call per batch) need fuller passes than graphs of
    matrix products, whose calls each do many scalars' work."""
    import casadi as ca

    x = ca.MX.sym("x", 2)
    scalar = VerificationProblem(x, [[-1, 1], [-1, 1]], [],
                                 [ca.sin(x[0]) * ca.cos(x[1]) + x[0] * x[1] - 5])
    W = np.random.default_rng(0).normal(size=(64, 2))
    wide = VerificationProblem(x, [[-1, 1], [-1, 1]], [],
                               [ca.sumsqr(ca.tanh(ca.mtimes(ca.DM(W), x))) - 100])
    a, b = pass_boxes(scalar), pass_boxes(wide)
    assert a == pass_boxes(scalar) and b == pass_boxes(wide)    # no timing involved
    c = pass_boxes(scalar, second_order=True)   # the gradient and Hessian graphs counted too
    for v in (a, b, c):
        assert 1 <= v <= 8192 and v & (v - 1) == 0               # a power of two
    assert a >= 4 * b


def test_pass_size_coarsens_the_grains_of_many_workers_only():
    assert task_defaults(2, pass_size=4096) == task_defaults(2)      # measured on 2 cores
    fine, coarse = task_defaults(16), task_defaults(16, pass_size=1024)
    assert coarse["min_task_boxes"] == 1024 and coarse["task_boxes"] >= 4 * 1024
    assert coarse["root_boxes"] == fine["root_boxes"]
    assert task_defaults(16, pass_size=16) == fine                   # never finer
    assert task_defaults(16, batch=64, pass_size=1024)["min_task_boxes"] <= 64


# ------------------------------------------------------------- plain tasks (portfolio)
@pytest.fixture
def cpu_clock(monkeypatch):
    """A thread-CPU clock that advances only by what a task declares it spent."""
    import nlyap_opt.distributed.parallel as par

    clock = [0.0]
    monkeypatch.setattr(par.time, "thread_time", lambda: clock[0])

    def spend(seconds, value=None):
        clock[0] += seconds
        return value
    return spend


def test_plain_tasks_are_list_scheduled_with_a_start_per_worker(cpu_clock):
    """Costs 3, 3, 2 on two workers with a start of 1 each: 4, 4, then 6; one worker
    pays the start once: 9."""
    sim = SimulatedCluster(2, cost="cpu", startup=1.0)
    futs = [sim.submit(cpu_clock, c, value=c) for c in (3.0, 3.0, 2.0)]
    assert [f.result() for f in futs] == [3.0, 3.0, 2.0]
    assert sim.replay(2) == {"makespan": 6.0, "work": 9.0, "tasks": 3}
    assert sim.replay(1)["makespan"] == 9.0 == sim.work()
    assert sim.replay(3)["makespan"] == 4.0
    assert sim.calls[-1]["makespan"] == 6.0          # the schedule as it ran (2 workers)


def test_a_task_submitted_after_a_wait_starts_after_that_task(cpu_clock):
    """The portfolio with learned φ waits for the first seed before it submits the rest:
    on any number of workers they start after it, never beside it."""
    sim = SimulatedCluster(4, cost="cpu")
    first = sim.submit(cpu_clock, 5.0)
    assert first.done()
    rest = [sim.submit(cpu_clock, 1.0) for _ in range(3)]
    assert all(f.done() for f in rest)
    assert sim.replay(4)["makespan"] == 6.0 and sim.replay(1)["makespan"] == 8.0


def test_a_plain_task_error_is_raised_by_result(cpu_clock):
    sim = SimulatedCluster(2, cost="cpu")

    def boom():
        raise RuntimeError("seed failed")
    fut = sim.submit(boom)
    with pytest.raises(RuntimeError, match="seed failed"):
        fut.result()


def test_plain_tasks_need_cpu_cost_and_a_valid_start():
    with pytest.raises(ConfigError, match="CPU seconds"):
        SimulatedCluster(2).submit(sum, [1])
    for bad in (-1.0, float("nan"), True, "1"):
        with pytest.raises(ConfigError, match="startup must be"):
            SimulatedCluster(2, cost="cpu", startup=bad)


def test_portfolio_runs_its_seeds_on_a_given_client(tmp_path, monkeypatch, cpu_clock):
    """``run_portfolio(client=...)``: every seed one task on that client, the best kept as
    on a cluster; a client and workers together are refused."""
    import nlyap_opt.workflow.portfolio as pf
    from nlyap_opt.workflow.configs import get_config

    def fake(system, cfg, out, known, spec, seed):
        area = {0: 1.0, 1: 3.0, 2: 2.0}[seed]
        return cpu_clock(1.0 + seed, pf.SeedRun(seed, "certified", True, 0.5, area, 0.9,
                                                 1.0, f"seed_{seed}"))
    monkeypatch.setattr(pf, "_run_seed", fake)
    cfg = get_config("van_der_pol", "fast")
    sim = SimulatedCluster(3, cost="cpu", startup=0.5)
    res = pf.run_portfolio("van_der_pol", cfg, tmp_path / "p", seeds=3, client=sim,
                           known_dynamics=True, log=lambda m: None)
    assert res.best.seed == 1 and res.workers == 3
    assert sim.replay(3)["makespan"] == 3.5 and sim.replay(1)["makespan"] == 6.5
    with pytest.raises(ConfigError, match="not both"):
        pf.run_portfolio("van_der_pol", cfg, tmp_path / "q", seeds=2, client=sim, workers=2,
                         known_dynamics=True, log=lambda m: None)


@pytest.mark.parametrize("workers", [4, 16])
def test_default_grains_of_many_workers_decide_as_serially(workers):
    """With the counted pass size and the ramp-up (more than two workers, no grain given),
    every box is still decided once by the serial rules: the serial verdict and boxes."""
    problem = closed_loop_problem(systems.get("van_der_pol"), quadratic_lyapunov(P_VDP),
                                  inner=0.05, outer=1.1)
    serial = verify(problem, presearch=0)
    st: dict = {}
    res = verify_distributed(problem, SimulatedCluster(workers), presearch=0, batch=32,
                             stats=st)
    assert res.status == serial.status == "verified" and res.boxes == serial.boxes
    assert st["tasks"] >= 4
    # the pass size (2048 for this scalar graph) coarsens the least start up to the grain
    assert pass_boxes(problem) >= 1024
    assert st["grains"]["min_task_boxes"] == 32 > task_defaults(workers, 32)["min_task_boxes"]
