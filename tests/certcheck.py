"""One certificate-checking helper reused by the verifier tests."""

import numpy as np

from nlyap_opt.kernel.walker import evaluate


def dense_region_samples(problem, n: int, seed: int = 0, chunk: int = 250_000):
    """Yield (points, F) for ``n`` uniform samples of the root box that lie in the region."""
    rng = np.random.default_rng(seed)
    lo, hi = problem.box[:, 0], problem.box[:, 1]
    m = problem.n_constraints
    done = 0
    while done < n:
        k = min(chunk, n - done)
        pts = lo + (hi - lo) * rng.random((k, problem.n))
        F = evaluate(problem.function, [pts])[0]
        inside = np.all(F[:, :m] <= 0, axis=1) if m else np.ones(k, bool)
        done += k
        yield pts[inside], F[inside]


def assert_no_sample_contradicts(problem, n: int = 1_000_000, seed: int = 0):
    """Every sampled region point satisfies every property (p < 0) in float64."""
    m = problem.n_constraints
    count = 0
    for pts, F in dense_region_samples(problem, n, seed):
        worst = np.max(F[:, m:], axis=1) if len(F) else np.zeros(0)
        bad = ~(worst < 0)  # NaN: a property undefined at a region point contradicts too
        assert not bad.any(), f"sample {pts[bad][0]} contradicts a verified verdict"
        count += len(pts)
    assert count > 0.05 * n, "the region is (almost) empty: the check would be vacuous"
    return count


def assert_confirmed(problem, cex):
    """A counterexample lies in the region and violates a property in float64 too."""
    F = evaluate(problem.function, [cex.point[None, :]])[0][0]
    m = problem.n_constraints
    assert np.all(F[:m] <= 1e-12), "counterexample outside the region"
    if cex.property.startswith("domain of"):
        assert not np.all(np.isfinite(F[m:]))
    else:
        assert cex.value_lower >= 0 and np.max(F[m:]) >= -1e-12


#: the artifacts whose sha256 a same-fingerprint reference records (bit for bit)
REFERENCE_FILES = ("V.json", "controller.json", "dynamics.json")

_REFERENCE_FILE = __import__("pathlib").Path(__file__).parent / "data" / "fast_certificates.json"


def fast_references() -> dict:
    """``tests/data/fast_certificates.json``: ``floors`` (what every machine must reach) and
    ``fingerprints`` (bit-for-bit values recorded per numeric-environment fingerprint)."""
    import json

    return json.loads(_REFERENCE_FILE.read_text())


def fast_reference() -> tuple[str, dict | None]:
    """``(fingerprint_id, values)``: the fast certificates recorded on this process's
    numeric environment (:func:`nlyap_opt.kernel.provenance.fingerprint_id`), or ``None``."""
    from nlyap_opt.kernel.provenance import fingerprint_id

    fid = fingerprint_id()
    rec = fast_references()["fingerprints"].get(fid)
    return fid, None if rec is None else rec["values"]


def fast_summary(cert: dict, run_dir=None) -> dict:
    """What a fast reference records of a run: level, certified area, η and the sha256 of
    its saved networks (``run_dir`` given)."""
    import hashlib
    from pathlib import Path

    got = {"status": cert["status"], "level": cert["level"],
           "certified_area": cert["certified_area"], "eta": cert.get("eta", 0.0)}
    if run_dir is not None:
        got["sha256"] = {f: hashlib.sha256((Path(run_dir) / f).read_bytes()).hexdigest()
                         for f in REFERENCE_FILES if (Path(run_dir) / f).exists()}
    return got


def assert_fast_certificate(key: str, cert: dict, run_dir=None) -> bool:
    """A fast-preset certificate (``key`` = ``"NAME/known"`` or ``"NAME/learned"``).

    On every machine: certified, the certified area at least the floor and η at most the
    bound of ``floors`` (properties with stated margins, which hold on any x86-64 CPU and
    BLAS kernel). On a machine whose numeric-environment fingerprint has a recorded
    reference: the same level, area, η and network files bit for bit. Returns whether the
    bit-for-bit comparison ran.
    """
    floor = fast_references()["floors"][key]
    got = fast_summary(cert, run_dir)
    assert got["status"] == "certified", (key, got)
    assert got["certified_area"] >= floor["certified_area_min"], (key, got, floor)
    assert got["eta"] <= floor["eta_max"], (key, got, floor)
    fid, ref = fast_reference()
    if ref is None or key not in ref:
        return False
    want = ref[key]
    for k in ("level", "certified_area", "eta"):
        assert got[k] == want[k], (key, fid, k, got[k], want[k])
    if run_dir is not None:
        assert got["sha256"] == want["sha256"], (key, fid, got["sha256"], want["sha256"])
    return True


def assert_reverifies(system, V, level: float, inner: float, outer: float, half: float):
    """``V`` (a network of the true closed loop of ``system``, no controller) re-verifies
    at ``level`` on ``inner ≤ ‖x‖ ≤ outer`` in the box ``[-half, half]^n``, independently
    of the run that produced it."""
    from nlyap_opt.kernel.symbolic import closed_loop, lie_derivative
    from verification import lyapunov_problem, verify

    cl = closed_loop(system, None, None, strict=True)
    Vx = V.casadi(cl.x)
    prob = lyapunov_problem(cl.x, Vx, lie_derivative(Vx, cl.x, cl.rhs), inner=inner,
                            outer=outer, level=level, margin=0.0,
                            box=np.tile([-half, half], (system.nx, 1)), check_positive=False)
    assert verify(prob).status == "verified"

