"""Proofs of a re-check: the bisection tree a verified check decided, replayed later.

The mathematics checked: the leaves rebuilt from any codes cover the box (their volumes add
up to the box's and seeded points of the box lie in one of them); the leaves of a recorded
tree are the boxes the serial run decided; a proof never turns a failing check into a
verified one; a proof file is read without trusting it.
"""

import zipfile

import numpy as np
import pytest

import systems
from nlyap_opt.design.control import quadratic_lyapunov
from nlyap_opt.distributed.parallel import Proofs, check, proving, recorded
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
        assert recorded(prob)
        again = check(prob)
    assert again.status == "verified" and use.used == 1 and use.asked == 1
    assert again.boxes < first.boxes  # the leaves only
    other = _problem(outer=0.9)  # another problem: no tree of it, searched as without
    with proving(use):
        assert not recorded(other)
        assert check(other).status == "verified"
    assert use.used == 1 and use.asked == 2


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
    with pytest.raises(ConfigError, match="cannot read the proof file"):
        Proofs.load(junk)
    other = tmp_path / "other.npz"
    np.savez(other, codes=np.zeros(3, np.int8))
    with pytest.raises(ConfigError, match="not a proof file"):
        Proofs.load(other)
    wrong = tmp_path / "wrong.npz"
    np.savez(wrong, format=np.frombuffer(Proofs.FORMAT.encode(), np.uint8),
             key0=np.frombuffer(b"x" * 64, np.uint8), initial0=np.array([4]),
             codes0=np.zeros(3, np.int8))
    with pytest.raises(ConfigError, match="entry 0 is not a bisection tree"):
        Proofs.load(wrong)
    big = tmp_path / "big.npz"  # declares more than a proof holds: refused before inflating
    with zipfile.ZipFile(big, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("codes0.npy", b"\0" * (2 * MAX_PARTITION_ENTRIES + 1))
    with pytest.raises(ConfigError, match="holds more than"):
        Proofs.load(big)


def test_cli_saves_and_uses_a_proof(fast_run, tmp_path, capsys):
    d, _ = fast_run("van_der_pol", known=True)
    proof = tmp_path / "proof.npz"
    assert main(["verify", "--certificate", str(d), "--save-proof", str(proof)]) == 0
    out = capsys.readouterr().out
    assert "written to" in out and proof.exists()
    assert main(["verify", "--certificate", str(d), "--proof", str(proof)]) == 0
    out = capsys.readouterr().out
    n = len(Proofs.load(proof).trees)
    assert n >= 1  # the decrease check, at least, is bisected
    assert f"proof: {n} of {n} bisected checks started" in out
    for argv in (["verify", "--certificate", str(d), "--proof", str(proof), "--save-proof",
                  str(proof)],
                 ["verify", "--certificate", str(d), "--save-proof", str(proof), "--workers",
                  "2"],
                 ["verify", "--system", "van_der_pol", "--proof", str(proof)],
                 ["verify", "--certificate", str(d), "--proof", str(tmp_path / "none.npz")]):
        assert main(argv) == 3
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "Traceback" not in err
