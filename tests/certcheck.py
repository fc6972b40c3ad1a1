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
