"""Proofs of a re-check: the bisection tree a verified check decided, replayed later.

The mathematics checked: the leaves rebuilt from any codes cover the box (their volumes add
up to the box's and seeded points of the box lie in one of them); the leaves of a recorded
tree are the boxes the serial run decided; a proof never turns a failing check into a
verified one; a proof file is read without trusting it.
"""

import io
import json
import os
import zipfile

import numpy as np
import pytest

import systems
from nlyap_opt.design.control import quadratic_lyapunov
from nlyap_opt.distributed.parallel import Proofs, check, proving
from nlyap_opt.interface.cli import main
from nlyap_opt.kernel.errors import ConfigError
from verification import closed_loop_problem
from verification.verify import (
    MAX_PARTITION_ENTRIES,
    MAX_PARTITION_LEVELS,
    partition_leaves,
    verify_interval,
)

P = np.array([[1.5, -0.5], [-0.5, 1.0]])


def _problem(level=None, outer=1.0):
    V = quadratic_lyapunov(P)
    return closed_loop_problem(systems.get("van_der_pol"), V, inner=0.1, outer=outer,
                               level=level)


def _covers(box, leaves, rng):
    vol = np.prod(leaves[:, :, 1] - leaves[:, :, 0], axis=1).sum()
    assert vol == pytest.approx(np.prod(box[:, 1] - box[:, 0]), rel=1e-12)
    pts = box[:, 0] + (box[:, 1] - box[:, 0]) * rng.random((2000, len(box)))
    inside = np.all((leaves[None, :, :, 0] <= pts[:, None, :]) &
                    (pts[:, None, :] <= leaves[None, :, :, 1]), axis=2)
    assert inside.any(axis=1).all()


def test_a_recorded_tree_gives_back_the_boxes_the_run_decided(rng):
    prob = _problem()
    r = verify_interval(prob, partition=True, initial_boxes=16)
    assert r.status == "verified" and r.partition is not None
    codes = r.partition["codes"]
    assert len(codes) == r.boxes  # one code per box the run evaluated
    leaves = partition_leaves(prob.box, r.partition["initial_boxes"], codes)
    splits = int(np.sum(codes >= 0))
    assert len(leaves) == len(codes) - splits == r.boxes - splits
    _covers(prob.box, leaves, rng)
    again = verify_interval(prob, boxes=leaves, presearch=0)
    assert again.status == "verified" and again.boxes == len(leaves)  # none bisected again


def test_any_codes_cover_the_box_or_are_refused(rng):
    box = np.array([[-1.0, 2.0], [0.5, 3.0], [-4.0, -1.0]])
    for _ in range(40):
        codes = rng.integers(-1, 3, size=int(rng.integers(1, 400))).astype(np.int8)
        try:
            leaves = partition_leaves(box, 8, codes)
        except ValueError:
            continue
        _covers(box, leaves, rng)
    with pytest.raises(ValueError, match="lie in -1 .. 2"):
        partition_leaves(box, 1, np.array([3], np.int8))
    with pytest.raises(ValueError, match="end after"):
        partition_leaves(box, 1, np.array([0, 1], np.int8))  # the root's halves' codes missing
    with pytest.raises(ValueError, match="after its tree ends"):
        partition_leaves(box, 1, np.array([-1, -1], np.int8))
    chain = np.array([0, -1] * (MAX_PARTITION_LEVELS * 3 + 2) + [-1], np.int8)
    with pytest.raises(ValueError, match="deeper than"):
        partition_leaves(box, 1, chain)  # one split per level: refused, not looped on
    with pytest.raises(ValueError, match="more than"):
        partition_leaves(box, 1, np.zeros(MAX_PARTITION_ENTRIES // 3 + 1, np.int8))


def test_check_records_then_starts_from_the_tree():
    prob = _problem()
    rec = Proofs(record=True)
    with proving(rec):
        first = check(prob)
    assert first.status == "verified" and len(rec.trees) == 1
    use = Proofs()
    use.trees = rec.trees
    with proving(use):
        assert Proofs.key(prob) in use.trees
        again = check(prob)
    assert again.status == "verified" and use.used == 1 and use.asked == 1
    assert again.boxes < first.boxes  # the leaves only
    other = _problem(outer=0.9)  # another problem: no tree of it, searched as without
    with proving(use):
        assert Proofs.key(other) not in use.trees
        assert check(other).status == "verified"
    assert use.used == 1 and use.asked == 2


def test_on_a_cluster_the_leaves_are_dealt_at_once():
    from nlyap_opt.distributed.parallel import SimulatedCluster, verify_distributed, verifying_on

    prob = _problem()
    r = verify_interval(prob, partition=True)
    leaves = partition_leaves(prob.box, r.partition["initial_boxes"], r.partition["codes"])
    sim = SimulatedCluster(4)
    st: dict = {}
    res = verify_distributed(prob, sim, start=leaves, stats=st)
    assert res.status == "verified" and res.boxes == len(leaves)  # each leaf once, no more
    assert st["tasks"] == 16 and sum(st["starts"]) == len(leaves)  # four tasks per worker
    use = Proofs()
    use.add(prob, r.partition)
    bad = _problem(outer=3.0)
    use.add(bad, r.partition)  # a forged tree for a false check
    with verifying_on(SimulatedCluster(4)), proving(use):
        assert check(prob).status == "verified"
        assert check(bad).status == "counterexample"
    assert use.used == 1 and use.asked == 2 and len(use.failed) == 1


def test_a_proof_never_verifies_a_failing_check():
    good = _problem(outer=0.8)
    r = verify_interval(good, partition=True)
    assert r.status == "verified"
    bad = _problem(outer=3.0)  # Van der Pol's ROA is smaller: the decrease fails there
    assert verify_interval(bad).status == "counterexample"
    for initial, codes in ((r.partition["initial_boxes"], r.partition["codes"]),
                           (1, np.array([-1], np.int8))):  # a tree of another box, a root
        forged = Proofs()
        forged.trees[Proofs.key(bad)] = (initial, codes)
        with proving(forged):
            assert check(bad).status == "counterexample"


def test_a_tree_past_the_box_budget_is_not_used():
    prob = _problem()
    rec = Proofs(record=True)
    with proving(rec):
        check(prob)
    [(_, codes)] = rec.trees.values()
    use = Proofs()
    use.trees = rec.trees
    budget = len(codes) // 2  # the search the tree stands for needs twice as many boxes
    plain = check(prob, max_boxes=budget)
    with proving(use):
        res = check(prob, max_boxes=budget, backend="interval")
    assert plain.status == res.status == "unknown" and use.used == 0
    with proving(use):
        assert check(prob, backend="interval").status == "verified" and use.used == 1


def test_a_forged_tree_cannot_cost_a_certificate_the_closed_form_proves():
    import casadi as ca

    from nlyap_opt.certification.roa import certify_level, quadratic_form

    class Forged(Proofs):  # a tree for every check: the whole box as its one leaf
        def leaves(self, problem, max_boxes=None, *, key=None):
            self.looked.add(self.key(problem))
            return None if self.key(problem) in self.failed else problem.box[None].copy()

    x = ca.SX.sym("x", 2)
    Vnet = quadratic_lyapunov(np.array([[1.5, 0.5], [0.5, 1.0]]))
    V = Vnet.casadi(x)
    rhs = ca.mtimes(ca.DM(np.array([[0.0, 1.0], [-1.0, -1.0]])), x)
    lie = ca.mtimes(ca.jacobian(V, x), rhs)
    kw = dict(level=1.0, inner=0.01, outer=2.0, margin=0.0, quadratic=quadratic_form(Vnet),
              rhs=rhs, verify_options={"max_boxes": 300}, log=lambda m: None, max_tries=1)
    plain = certify_level(x, V, lie, **kw)
    forged = Forged()
    with proving(forged):
        again = certify_level(x, V, lie, **kw)
    assert plain.status == again.status == "certified" and again.level == plain.level
    assert forged.asked >= 1 and forged.used == 0  # tried, failed, then the closed form


def test_proof_files_round_trip_and_hostile_files_are_refused(tmp_path):
    prob = _problem()
    rec = Proofs(record=True)
    with proving(rec):
        check(prob)
    path = tmp_path / "p.npz"
    rec.save(path)
    with zipfile.ZipFile(path) as zf:  # no clock in the bytes: the same trees, the same file
        assert {i.date_time for i in zf.infolist()} == {(1980, 1, 1, 0, 0, 0)}
    back = Proofs.load(path)
    assert list(back.trees) == list(rec.trees)
    (i0, c0), (i1, c1) = rec.trees[Proofs.key(prob)], back.trees[Proofs.key(prob)]
    assert i0 == i1 and np.array_equal(c0, c1) and c1.dtype == np.int8
    junk = tmp_path / "junk.npz"
    junk.write_text("not a zip")
    with pytest.raises(ConfigError, match="is not an npz file"):
        Proofs.load(junk)
    with pytest.raises(ConfigError, match="cannot read the proof file"):
        Proofs.load(tmp_path / "missing.npz")
    fifo = tmp_path / "fifo.npz"  # a pipe: refused without waiting on it
    os.mkfifo(fifo)
    with pytest.raises(ConfigError, match="not a regular file"):
        Proofs.load(fifo)
    other = tmp_path / "other.npz"
    np.savez(other, codes=np.zeros(3, np.int8))
    with pytest.raises(ConfigError, match="not a proof file"):
        Proofs.load(other)
    fmt = np.frombuffer(Proofs.FORMAT.encode(), np.uint8)
    for bad in ({"key0": np.frombuffer(b"x" * 64, np.uint8), "initial0": np.array([4]),
                 "codes0": np.zeros(3, np.int8)},
                {"key0": np.frombuffer(b"a" * 64, np.uint8), "initial0": np.array([4.0]),
                 "codes0": np.zeros(3, np.int8)},
                {"key0": np.frombuffer(b"a" * 64, np.uint8).reshape(8, 8),
                 "initial0": np.array([4]), "codes0": np.zeros(3, np.int8)}):
        wrong = tmp_path / "wrong.npz"
        np.savez(wrong, format=fmt, **bad)
        with pytest.raises(ConfigError, match="entry 0 is not a bisection tree"):
            Proofs.load(wrong)
    lying = tmp_path / "lying.npz"  # a header that declares 10**12 codes in a few bytes
    head = io.BytesIO()
    np.lib.format.write_array_header_1_0(head, {"descr": "|i1", "fortran_order": False,
                                               "shape": (10**12,)})
    with zipfile.ZipFile(lying, "w") as zf:
        zf.writestr("format.npy", _npy(fmt))
        zf.writestr("codes0.npy", head.getvalue() + b"\0" * 8)
    with pytest.raises(ConfigError, match="declares more data than it holds"):
        Proofs.load(lying)
    odd = tmp_path / "odd.npz"  # compressed as numpy never writes
    with zipfile.ZipFile(odd, "w", zipfile.ZIP_BZIP2) as zf:
        zf.writestr("format.npy", _npy(fmt))
    with pytest.raises(ConfigError, match="not an array as numpy.savez writes one"):
        Proofs.load(odd)


def _npy(a) -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array(buf, a)
    return buf.getvalue()


def test_cli_saves_and_uses_a_proof(fast_run, tmp_path, capsys):
    d, _ = fast_run("van_der_pol", known=True)
    proof = tmp_path / "proof.npz"
    assert main(["verify", "--certificate", str(d), "--save-proof", str(proof)]) == 0
    out = capsys.readouterr().out
    assert "written to" in out and proof.exists()
    js = tmp_path / "out.json"
    assert main(["verify", "--certificate", str(d), "--proof", str(proof), "--json",
                 str(js)]) == 0
    out = capsys.readouterr().out
    n = len(Proofs.load(proof).trees)
    assert n >= 1  # the decrease check, at least, is bisected
    assert f"proof: {n} of {n} bisected checks started" in out
    said = json.loads(js.read_text())["proof"]
    assert said["checks"] == said["started_from_proof"] == n and said["file"] == str(proof)
    for argv in (["verify", "--certificate", str(d), "--proof", str(proof), "--save-proof",
                  str(proof)],
                 ["verify", "--certificate", str(d), "--save-proof", str(proof), "--workers",
                  "2"],
                 ["verify", "--system", "van_der_pol", "--proof", str(proof)],
                 ["verify", "--certificate", str(d), "--save-proof", str(d / "certificate.json")],
                 ["verify", "--certificate", str(d), "--save-proof",
                  str(proof / "p.npz")],  # under a file, not a directory
                 ["verify", "--certificate", str(d), "--save-proof", ""],
                 ["verify", "--certificate", str(d), "--proof", str(tmp_path / "none.npz")]):
        assert main(argv) == 3
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "Traceback" not in err
