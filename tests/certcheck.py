"""One certificate-checking helper reused by the verifier tests."""

import numpy as np

from nlyap_opt.walker import evaluate


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


#: how far a fast reference certificate's level and η may move with the order of floating
#: sums: the known-f values differ by 1.8e-10 relative between OpenBLAS's SkylakeX and Haswell
#: kernels (inverted pendulum: the IPOPT candidate level). A real change of the training or
#: the verifier moves a level by far more (1e-3 and up in every recorded re-recording).
REFERENCE_RTOL = 1e-8


def blas_kernel() -> str | None:
    """The kernel numpy's OpenBLAS runs on this machine (``"Haswell"``, ``"SkylakeX"``, ...;
    it follows the CPU, or ``OPENBLAS_CORETYPE``), or ``None`` where it cannot be asked."""
    import ctypes
    from pathlib import Path

    libs = sorted((Path(np.__file__).parent.parent / "numpy.libs").glob("*openblas*"))
    for lib in libs:
        try:
            handle = ctypes.CDLL(str(lib))
        except OSError:
            continue
        for sym in ("scipy_openblas_get_corename64_", "openblas_get_corename64_",
                    "openblas_get_corename"):
            fn = getattr(handle, sym, None)
            if fn is not None:
                fn.restype = ctypes.c_char_p
                return fn().decode().strip() or None
    return None


def fast_reference() -> tuple[str | None, dict, bool]:
    """``(kernel, values, recorded)``: the fast certificates recorded under this machine's
    OpenBLAS kernel (``recorded``), else those of the first kernel recorded (its known-f
    values hold to :data:`REFERENCE_RTOL` on any kernel; its learned-f ones need not)."""
    import json
    from pathlib import Path

    ref = json.loads((Path(__file__).parent / "data" / "fast_certificates.json").read_text())
    kernels = ref["kernels"]
    k = blas_kernel()
    if k in kernels:
        return k, kernels[k], True
    return k, next(iter(kernels.values())), False


def assert_matches_reference(got: dict, want: dict, what: str = ""):
    """A fast-preset certificate against ``tests/data/fast_certificates.json``: the
    certified area (a grid count) exactly, level and η to :data:`REFERENCE_RTOL`."""
    assert set(got) == set(want), (what, sorted(got), sorted(want))
    assert got["certified_area"] == want["certified_area"], (what, got, want)
    for key in ("level", "eta"):
        g, w = float(got[key]), float(want[key])
        assert abs(g - w) <= REFERENCE_RTOL * abs(w), (what, key, g, w)
