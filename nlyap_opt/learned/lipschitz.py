r"""Certified Lipschitz constants of one-hidden-layer networks.

The learned dynamics are :math:`\varphi(z) = W_1\,\sigma(W_0 z + b_0) + b_1` with
:math:`z = (x, u)`, one hidden layer and a scalar activation :math:`\sigma` that is
*slope-restricted* in :math:`[a, b]`, i.e.
:math:`a \le (\sigma(s) - \sigma(s')) / (s - s') \le b` for all :math:`s \ne s'`
(``tanh``: :math:`[0, 1]`; logistic sigmoid: :math:`[0, 1/4]`).

Three numbers are provided:

* :func:`lipschitz_lipsdp` -- LipSDP-Neuron (Fazlyab et al., NeurIPS 2019), solved with
  an SDP solver and then **re-certified in floating point** so that the returned
  ``value`` is a rigorous upper bound of the 2-norm Lipschitz constant, whatever the
  accuracy of the solver.
* :func:`lipschitz_naive` -- the rigorous product bound :math:`\|W_1\|_2 \|W_0\|_2`
  (times :math:`\max(|a|, |b|)`, which is 1 for ``tanh``).
* :func:`lipschitz_sampled` -- the largest Jacobian norm over sample points, a *lower*
  bound of the Lipschitz constant (used as a sanity check).

The LMI
-------
With :math:`T = \operatorname{diag}(t)`, :math:`t \ge 0`, define

.. math::

    M(\rho, T) = \begin{bmatrix}
        -\rho I - 2ab\, W_0^\top T W_0 & (a + b)\, W_0^\top T \\
        (a + b)\, T W_0 & -2T + W_1^\top W_1
    \end{bmatrix}.

If :math:`M(\rho, T) \preceq 0` then :math:`\|\varphi(z) - \varphi(z')\|_2 \le
\sqrt{\rho}\, \|z - z'\|_2`.  (Multiply by :math:`(\Delta z, \Delta v)` with
:math:`\Delta v = \sigma(W_0 z + b_0) - \sigma(W_0 z' + b_0)`: the quadratic form equals
:math:`-\rho\|\Delta z\|^2 + \|W_1 \Delta v\|^2 + 2\sum_i t_i (\Delta v_i - a \Delta q_i)
(b \Delta q_i - \Delta v_i)` with :math:`\Delta q = W_0 \Delta z`, and every term of the
sum is non-negative by slope restriction.)  The bias terms do not matter.

For the solver the :math:`W_1^\top W_1` term is Schur-lifted, which keeps the hidden
block diagonal and lets Clarabel's chordal decomposition split the cone into small
cliques:

.. math::

    \begin{bmatrix}
        -\rho I - 2ab\, W_0^\top T W_0 & (a + b)\, W_0^\top T & 0 \\
        (a + b)\, T W_0 & -2T & W_1^\top \\
        0 & W_1 & -I
    \end{bmatrix} \preceq 0 .

The weights are normalised by their spectral norms before solving (the LMI is
homogeneous: :math:`t = s_1^2 t'` and :math:`\rho = (s_0 s_1)^2 \rho'`).

Re-certification
----------------
The solver's multipliers are only approximately feasible.  The multipliers :math:`t` are
therefore taken as exact floating-point numbers (clipped to :math:`t \ge 0` and raised, if
needed, to the necessary floor :math:`t_i > \|W_1 e_i\|^2 / 2`; a few up-scaled copies and
the always-feasible floor :math:`t_i \ge 0.505 \|W_1\|_2^2` are tried too), the best
:math:`\rho` for each such :math:`T` is estimated from the Schur complement, and values of
:math:`\rho` (slightly increased step by step) are *proved* to satisfy
:math:`M(\rho, T) \preceq 0` in exact real arithmetic as follows.

1. :math:`\tilde M = \mathrm{fl}(M)` is formed in float64 together with an entrywise bound
   :math:`|M - \tilde M| \le E` from the standard model
   :math:`\mathrm{fl}(x \circ y) = (x \circ y)(1 + \delta)`, :math:`|\delta| \le u = 2^{-53}`:
   an entry that is a sum of :math:`k` products of at most :math:`p` factors has error at most
   :math:`\gamma_{k+p}\sum|\text{terms}|`, :math:`\gamma_k = ku/(1 - ku)`.
2. An eigen-decomposition :math:`\tilde M \approx V \Lambda V^\top` is computed (any
   accuracy).  Then :math:`M = V \Lambda V^\top + G` with
   :math:`\|G\|_2 \le \|G\|_F \le \|\,(1 + \gamma_1)|\mathrm{fl}(\tilde M - V\Lambda V^\top)|
   + \gamma_{n+1} |V||\Lambda||V|^\top + E\,\|_F`, and, by congruence, for
   :math:`\lambda_{\max}(\Lambda) < 0`,
   :math:`\lambda_{\max}(V \Lambda V^\top) \le \lambda_{\max}(\Lambda)\,\sigma_{\min}(V)^2
   \le \lambda_{\max}(\Lambda)\,(1 - \|V^\top V - I\|_F)` (the orthogonality defect is bounded
   the same way).  By Weyl's inequality :math:`\lambda_{\max}(M)` is below the sum; if that
   sum is negative, :math:`M \preceq 0` holds exactly.  Nothing about the accuracy of the
   eigensolver is assumed: a poor decomposition only makes the bound looser.
3. The certified value is :math:`\sqrt{\rho}` rounded up (``np.nextafter``).

All error bounds are computed in floating point themselves and are then inflated by a
factor :math:`1 + 4\gamma_{n^2 + 4n + 16}` (covering the rounding of the bound computation,
which is a sum of non-negative terms) plus a tiny absolute term (covering underflow).
IEEE-754 double arithmetic with round-to-nearest and conventional (not Strassen-like)
matrix products in BLAS are assumed; the summation order inside BLAS does not matter.
If no candidate is certified, or the certified value is not below the naive bound,
``value`` is the naive bound (itself rigorous, computed with the same machinery) and
``certified`` is False.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ..kernel import deps
from ..kernel.errors import DimensionError, raise_if_interrupted
from ..kernel.rounding import U, gamma, next_up

__all__ = ["LipschitzResult", "lipschitz_lipsdp", "lipschitz_naive", "lipschitz_sampled"]

_TINY = 1e-290  # absolute slack covering underflow in products (subnormals are 2**-1074)

# relative increments of rho tried by the re-certification, in order
_RHO_STEPS = tuple(10.0**e for e in np.arange(-10.0, 4.01, 0.5))
# multiplicative perturbations of the multipliers t tried by the re-certification
# (the last candidate, t_i >= 0.505 ||W1||_2^2 for all i, always makes 2T - W1^T W1 > 0)
_T_SCALES = (1.0, 1.0 + 1e-7, 1.0 + 1e-5, 1.0 + 1e-3, 1.01, 1.1, 1.5, 2.0, 4.0)


@dataclass
class LipschitzResult:
    """Outcome of :func:`lipschitz_lipsdp`.

    Attributes
    ----------
    value : float
        Rigorous upper bound on the 2-norm Lipschitz constant of the network.  Either the
        re-certified LipSDP bound or, when that failed or was not better, the naive bound.
    sdp_value : float
        :math:`\\sqrt{\\rho}` as returned by the solver (not certified; ``nan`` when no
        solver succeeded).
    naive : float
        Rigorous upper bound of :math:`\\max(|a|,|b|)\\,\\|W_1\\|_2 \\|W_0\\|_2`.
    solver : str
        Name of the solver whose multipliers were used (``"none"`` if none succeeded,
        ``"trivial"`` if the network has no active neuron).
    seconds : float
        Wall-clock time of the whole computation.
    certified : bool
        True when ``value`` comes from the re-certified LipSDP multipliers; False when
        ``value`` is the naive bound (``note`` says why).
    note : str
        Human-readable explanation of how ``value`` was obtained.
    """

    value: float
    sdp_value: float
    naive: float
    solver: str
    seconds: float
    certified: bool
    note: str


# --------------------------------------------------------------------------- helpers


def _safety(n: int) -> float:
    """Inflation factor for bounds computed in floating point on ``n``-by-``n`` data."""
    return 1.0 + 4.0 * gamma(n * n + 4 * n + 16)


def _fro_upper(B: np.ndarray) -> float:
    """Upper bound of the Frobenius norm of a non-negative matrix ``B``."""
    if B.size == 0:
        return 0.0
    return next_up(float(np.linalg.norm(B)) * _safety(max(B.shape)) + _TINY)


def _lambda_max_upper(Mt: np.ndarray, E: np.ndarray) -> float:
    """Rigorous upper bound of :math:`\\lambda_{\\max}(M)` for every symmetric ``M``
    with :math:`|M - \\tilde M| \\le E` entrywise.

    Parameters
    ----------
    Mt : ndarray, shape (n, n)
        Exactly symmetric float matrix :math:`\\tilde M`.
    E : ndarray, shape (n, n)
        Non-negative entrywise bound of :math:`|M - \\tilde M|`.

    Notes
    -----
    Uses an eigen-decomposition :math:`\\tilde M \\approx V\\Lambda V^\\top` of any accuracy
    and bounds the residual :math:`G = M - V\\Lambda V^\\top` and the orthogonality
    defect :math:`\\|V^\\top V - I\\|` rigorously (see the module docstring).  Returns
    ``inf`` if something is not finite.
    """
    n = Mt.shape[0]
    if n == 0:
        return -math.inf
    if not (np.all(np.isfinite(Mt)) and np.all(np.isfinite(E))):
        return math.inf
    try:
        lam, V = np.linalg.eigh(Mt)
    except np.linalg.LinAlgError:
        return math.inf
    absV = np.abs(V)
    absL = np.abs(lam)
    g1 = gamma(1)
    # residual G = M - V diag(lam) V^T
    P = (V * lam) @ V.T
    R = Mt - P
    Gb = (1.0 + g1) * np.abs(R) + gamma(n + 1) * ((absV * absL) @ absV.T) + E
    g = _fro_upper(Gb)
    # orthogonality defect F = V^T V - I
    F = V.T @ V - np.eye(n)
    Fb = (1.0 + g1) * np.abs(F) + gamma(n) * (absV.T @ absV)
    f = _fro_upper(Fb)
    lmax = float(lam[-1])
    if not (math.isfinite(g) and math.isfinite(f) and math.isfinite(lmax)):
        return math.inf
    if lmax >= 0.0:
        core = lmax * (1.0 + f)
    else:
        core = lmax * max(0.0, 1.0 - f)
    ub = core + g
    # scalar rounding of the three operations above: relative u each, covered by 8u
    ub = ub + 8.0 * U * (abs(lmax) * (1.0 + f) + g) + _TINY
    return next_up(ub)


def _spectral_norm_upper(W: np.ndarray) -> float:
    """Rigorous upper bound of :math:`\\|W\\|_2` (min of a Gram-matrix and a Frobenius bound)."""
    W = np.asarray(W, dtype=np.float64)
    if W.size == 0 or not np.any(W):
        return 0.0
    # Frobenius bound: sum of W.size squares, each rounded, then a sqrt
    fro = next_up(float(np.linalg.norm(W)) * (1.0 + 2.0 * gamma(W.size + 2)) + _TINY)
    # Gram bound: ||W||_2^2 = lambda_max(G) with G the smaller Gram matrix
    A = W if W.shape[0] <= W.shape[1] else W.T  # k x p with k <= p
    k, p = A.shape
    G = A @ A.T
    G = np.triu(G) + np.triu(G, 1).T  # exactly symmetric (mirror the upper triangle)
    absA = np.abs(A)
    E = 2.0 * gamma(p) * (absA @ absA.T) + _TINY
    lam = _lambda_max_upper(G, E)
    if not math.isfinite(lam):
        return fro
    gram = next_up(math.sqrt(max(lam, 0.0)))
    return min(gram, fro)


def _build_lmi(
    W0: np.ndarray, W1: np.ndarray, t: np.ndarray, rho: float, a: float, b: float
) -> tuple[np.ndarray, np.ndarray]:
    """Float matrix :math:`\\tilde M(\\rho, T)` and entrywise error bound ``E``.

    ``t``, ``rho``, ``a`` and ``b`` are taken as exact floating-point numbers.
    """
    h, n = W0.shape
    m = W1.shape[0]
    N = n + h
    TW0 = t[:, None] * W0  # h x n
    Mt = np.empty((N, N))
    # block 11
    B11 = -rho * np.eye(n)
    if a != 0.0 and b != 0.0:
        S = W0.T @ TW0
        B11 = B11 - (2.0 * a * b) * S
    B11 = np.triu(B11) + np.triu(B11, 1).T
    Mt[:n, :n] = B11
    # blocks 12 / 21 (exact transposes of each other)
    B21 = (a + b) * TW0
    Mt[n:, :n] = B21
    Mt[:n, n:] = B21.T
    # block 22
    B22 = W1.T @ W1
    B22[np.diag_indices(h)] -= 2.0 * t
    B22 = np.triu(B22) + np.triu(B22, 1).T
    Mt[n:, n:] = B22
    # entrywise absolute-value matrix of the terms, times gamma_K
    K = h + m + 10
    absW0 = np.abs(W0)
    absW1 = np.abs(W1)
    tA = t[:, None] * absW0
    A = np.empty((N, N))
    A11 = abs(rho) * np.eye(n)
    if a != 0.0 and b != 0.0:
        A11 = A11 + (2.0 * abs(a) * abs(b)) * (absW0.T @ tA)
    A[:n, :n] = A11
    A21 = (abs(a) + abs(b)) * tA
    A[n:, :n] = A21
    A[:n, n:] = A21.T
    A22 = absW1.T @ absW1
    A22[np.diag_indices(h)] += 2.0 * t
    A[n:, n:] = A22
    E = (2.0 * gamma(K)) * A + _TINY
    E = np.maximum(E, E.T)
    return Mt, E


def _rho_estimate(W0: np.ndarray, W1: np.ndarray, t: np.ndarray, a: float, b: float) -> float:
    """Smallest :math:`\\rho` with :math:`M(\\rho, T) \\preceq 0` (float estimate, not rigorous).

    Schur complement: needs :math:`2T - W_1^\\top W_1 \\succ 0`; returns ``inf`` otherwise.
    """
    negD = 2.0 * np.diag(t) - W1.T @ W1
    negD = 0.5 * (negD + negD.T)
    try:
        C = np.linalg.cholesky(negD)
    except np.linalg.LinAlgError:
        return math.inf
    X = (a + b) * (t[:, None] * W0)  # h x n
    Y = np.linalg.solve(C, X)  # C^{-1} X
    S = Y.T @ Y
    if a != 0.0 and b != 0.0:
        S = S - 2.0 * a * b * (W0.T @ (t[:, None] * W0))
    S = 0.5 * (S + S.T)
    val = float(np.linalg.eigvalsh(S)[-1]) if S.size else 0.0
    return max(val, 0.0) if math.isfinite(val) else math.inf


def _certify(W0: np.ndarray, W1: np.ndarray, t: np.ndarray, rho: float, a: float, b: float) -> bool:
    """True only if :math:`M(\\rho, \\operatorname{diag}(t)) \\preceq 0` holds exactly."""
    if not (math.isfinite(rho) and np.all(np.isfinite(t)) and np.all(t >= 0.0)):
        return False
    Mt, E = _build_lmi(W0, W1, t, rho, a, b)
    return _lambda_max_upper(Mt, E) < 0.0


@dataclass
class _Recert:
    rho: float | None  # certified rho (None if none)
    t: np.ndarray | None  # the multipliers for which it was certified
    tries: int
    note: str

    @property
    def value(self) -> float | None:
        return None if self.rho is None else next_up(math.sqrt(self.rho))


def _recertify(
    W0: np.ndarray,
    W1: np.ndarray,
    t: np.ndarray,
    rho: float,
    slope: tuple[float, float] = (0.0, 1.0),
    *,
    max_tries: int = 30,
    use_estimate: bool = True,
) -> _Recert:
    """Find a :math:`\\rho` that provably satisfies the LipSDP LMI for multipliers near ``t``.

    Parameters
    ----------
    W0, W1 : ndarray
        Weights, shapes ``(h, n)`` and ``(m, h)``.
    t : ndarray, shape (h,)
        Multipliers from a solver (any accuracy; clipped to be non-negative).
    rho : float
        The solver's :math:`\\rho`: the start of the ramp when ``use_estimate`` is False
        (otherwise unused: each candidate starts from its own Schur estimate).
    slope : (float, float)
        Slope bounds ``(a, b)``.
    max_tries : int
        Maximum number of rigorous checks.
    use_estimate : bool
        If True (default), try the clipped multipliers, a few up-scaled copies of them and
        a uniform floor :math:`t_i \\ge 0.505\\|W_1\\|_2^2` (which always makes
        :math:`2T - W_1^\\top W_1 \\succ 0`), skip those with an indefinite lower-right
        block, and ramp :math:`\\rho` up from each candidate's Schur-complement estimate of
        its optimal :math:`\\rho`, best candidate first.  If False, only ramp
        :math:`\\rho` up from the given value with the clipped, floored multipliers.

    Notes
    -----
    Whatever ``t`` and ``rho`` are, a returned ``rho`` satisfies the LMI exactly (it was
    checked by :func:`_certify`), so :math:`\\sqrt{\\rho}` is a true Lipschitz bound.  The
    ramp multiplies the start by :math:`1 + 10^{-10}, 1 + 10^{-9.5}, \\ldots, 1 + 10^{4}`.

    Returns
    -------
    _Recert
        ``rho`` is None when nothing could be certified.
    """
    a, b = float(slope[0]), float(slope[1])
    t = np.maximum(np.nan_to_num(np.asarray(t, dtype=np.float64), nan=0.0), 0.0)
    floor = 0.5 * np.sum(W1 * W1, axis=0) * (1.0 + 1e-9)
    uniform = 0.505 * float(np.linalg.norm(W1, 2)) ** 2
    cands = []
    for s in (*_T_SCALES, None):
        tc = np.maximum(t * s, floor) if s is not None else np.maximum(t, uniform)
        if not use_estimate:
            # plain geometric ramp from the solver's rho with the clipped multipliers
            if math.isfinite(rho) and rho > 0.0:
                cands.append((float(rho), s, tc))
            break
        # M < 0 needs 2T - W1^T W1 > 0: candidates failing that (est = inf) are skipped
        est = _rho_estimate(W0, W1, tc, a, b)
        if math.isfinite(est):
            cands.append((est, s, tc))
    cands.sort(key=lambda c: c[0])
    tries = 0
    for j, (start, _s, tc) in enumerate(cands):
        # a few rho steps per candidate; all remaining tries for the last candidate
        per = len(_RHO_STEPS) if j == len(cands) - 1 else 12
        for step in _RHO_STEPS[:per]:
            if tries >= max_tries:
                break
            r = start * (1.0 + step)
            if r <= 0.0:
                continue
            tries += 1
            if _certify(W0, W1, tc, r, a, b):
                return _Recert(r, tc, tries, f"certified after {tries} check(s)")
    return _Recert(None, None, tries, f"no rho certified in {tries} check(s)")


def _validate(W0, b0, W1) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    W0 = np.asarray(W0, dtype=np.float64)
    W1 = np.asarray(W1, dtype=np.float64)
    if W0.ndim != 2:
        raise DimensionError(f"W0 must be 2-D (hidden, inputs); got shape {W0.shape}")
    if W1.ndim != 2:
        raise DimensionError(f"W1 must be 2-D (outputs, hidden); got shape {W1.shape}")
    if W1.shape[1] != W0.shape[0]:
        raise DimensionError(
            f"W1 has {W1.shape[1]} columns but W0 has {W0.shape[0]} rows (hidden units); "
            "expected W0 (h, n_in) and W1 (n_out, h)"
        )
    if b0 is not None:
        b0 = np.asarray(b0, dtype=np.float64).reshape(-1)
        if b0.shape != (W0.shape[0],):
            raise DimensionError(f"b0 must have {W0.shape[0]} entries; got {b0.size}")
        if not np.all(np.isfinite(b0)):
            raise ValueError("b0 contains NaN or inf")
    if not (np.all(np.isfinite(W0)) and np.all(np.isfinite(W1))):
        raise ValueError("weights contain NaN or inf")
    return W0, b0, W1


def _check_slope(slope) -> tuple[float, float]:
    a, b = (float(s) for s in slope)
    if not (math.isfinite(a) and math.isfinite(b) and a <= b):
        raise ValueError(f"slope must be finite (a, b) with a <= b; got {slope!r}")
    return a, b


# --------------------------------------------------------------------------- public API


def lipschitz_naive(W0, W1, *, slope: tuple[float, float] = (0.0, 1.0)) -> float:
    """Rigorous upper bound of :math:`\\max(|a|, |b|)\\,\\|W_1\\|_2\\,\\|W_0\\|_2`.

    Parameters
    ----------
    W0 : array_like, shape (h, n_in)
        Hidden-layer weights.
    W1 : array_like, shape (n_out, h)
        Output-layer weights.
    slope : (float, float), optional
        Slope bounds of the activation (default ``(0, 1)`` for ``tanh``).

    Returns
    -------
    float
        An upper bound of the Lipschitz constant of
        :math:`z \\mapsto W_1 \\sigma(W_0 z + b_0) + b_1` in the 2-norm.

    Notes
    -----
    Each spectral norm is bounded from above without trusting the SVD: for the smaller
    Gram matrix :math:`G = W W^\\top` (or :math:`W^\\top W`) computed in floating point, the
    rounding error is bounded entrywise by :math:`\\gamma_p |W||W|^\\top`, and
    :math:`\\lambda_{\\max}(G)` is bounded by an a-posteriori eigen-residual argument (see
    the module docstring); the result is the minimum of its square root and the
    Frobenius norm (inflated by its rounding error), each rounded up.  The final product
    is rounded up with ``np.nextafter``.  This is at most a few ulps above
    ``np.linalg.norm(W1, 2) * np.linalg.norm(W0, 2)``.
    """
    W0, _, W1 = _validate(W0, None, W1)
    a, b = _check_slope(slope)
    k = max(abs(a), abs(b))
    return next_up(next_up(_spectral_norm_upper(W1) * _spectral_norm_upper(W0)) * k)


def lipschitz_sampled(
    W0,
    b0,
    W1,
    points,
    *,
    activation: str | Callable[[np.ndarray], np.ndarray] = "tanh",
    batch_size: int = 8192,
) -> float:
    """Largest Jacobian 2-norm over sample points: a **lower** bound of the Lipschitz constant.

    Parameters
    ----------
    W0 : array_like, shape (h, n_in)
    b0 : array_like, shape (h,)
    W1 : array_like, shape (n_out, h)
    points : array_like, shape (N, n_in)
        Sample points :math:`z`.
    activation : {"tanh", "sigmoid"} or callable, optional
        The activation; a callable must return the *derivative* :math:`\\sigma'` elementwise.
    batch_size : int, optional
        Points processed per batch (bounds memory).

    Returns
    -------
    float
        :math:`\\max_k \\|W_1 \\operatorname{diag}(\\sigma'(W_0 z_k + b_0)) W_0\\|_2`
        (0.0 for no points).
    """
    W0, b0, W1 = _validate(W0, b0, W1)
    if b0 is None:
        b0 = np.zeros(W0.shape[0])
    Z = np.asarray(points, dtype=np.float64)
    if Z.ndim == 1:
        Z = Z.reshape(1, -1)
    if Z.ndim != 2 or Z.shape[1] != W0.shape[1]:
        raise DimensionError(f"points must have shape (N, {W0.shape[1]}); got {np.shape(points)}")
    if callable(activation):
        dsig = activation
    elif activation == "tanh":

        def dsig(s):
            return 1.0 - np.tanh(s) ** 2

    elif activation == "sigmoid":

        def dsig(s):
            e = 1.0 / (1.0 + np.exp(-s))
            return e * (1.0 - e)

    else:
        raise ValueError(f"activation must be 'tanh', 'sigmoid' or a callable; got {activation!r}")
    best = 0.0
    for i in range(0, Z.shape[0], max(1, int(batch_size))):
        z = Z[i : i + batch_size]
        d = dsig(z @ W0.T + b0)  # (B, h)
        J = np.einsum("oh,bh,hi->boi", W1, d, W0, optimize=True)
        best = max(best, float(np.max(np.linalg.norm(J, 2, axis=(1, 2)))))
    return best


def _solve_sdp(
    A: np.ndarray, B: np.ndarray, a: float, b: float, solver: str, verbose: bool
) -> tuple[np.ndarray, float]:
    """Solve the Schur-lifted LipSDP on normalised weights; return ``(t, rho)``."""
    cp = deps.cvxpy()

    h, n = A.shape
    m = B.shape[0]
    t = cp.Variable(h, nonneg=True)
    rho = cp.Variable()
    TA = cp.multiply(cp.reshape(t, (h, 1), order="F"), A)  # T W0, h x n
    B11 = -rho * np.eye(n)
    if a != 0.0 and b != 0.0:
        B11 = B11 - 2.0 * a * b * (A.T @ TA)
    M = cp.bmat(
        [
            [B11, (a + b) * TA.T, np.zeros((n, m))],
            [(a + b) * TA, -2.0 * cp.diag(t), B.T],
            [np.zeros((m, n)), B, -np.eye(m)],
        ]
    )
    M = 0.5 * (M + M.T)
    prob = cp.Problem(cp.Minimize(rho), [M << 0])
    if solver == "CLARABEL":
        opts = dict(
            chordal_decomposition_enable=True,
            chordal_decomposition_merge_method="parent_child",
        )
    elif solver == "SCS":
        opts = dict(eps_abs=1e-7, eps_rel=1e-7, max_iters=200_000)
    else:
        opts = {}
    with warnings.catch_warnings():   # an inaccurate solution is re-certified by the caller
        warnings.filterwarnings("ignore", message="Solution may be inaccurate")
        prob.solve(solver=solver, verbose=verbose, **opts)
    if prob.status not in ("optimal", "optimal_inaccurate") or t.value is None:
        raise RuntimeError(f"{solver} returned status {prob.status!r}")
    return np.asarray(t.value, dtype=np.float64).reshape(-1), float(rho.value)


def lipschitz_lipsdp(
    W0,
    b0,
    W1,
    *,
    slope: tuple[float, float] = (0.0, 1.0),
    solver: str | Sequence[str] | None = None,
    verbose: bool = False,
    max_tries: int = 30,
) -> LipschitzResult:
    """Certified LipSDP-Neuron upper bound of the 2-norm Lipschitz constant.

    Bounds the Lipschitz constant of :math:`\\varphi(z) = W_1 \\sigma(W_0 z + b_0) + b_1`
    where :math:`\\sigma` is slope-restricted in ``slope = (a, b)``, by solving

    .. math::

        \\min_{\\rho,\\, t \\ge 0} \\rho \\quad\\text{s.t.}\\quad
        \\begin{bmatrix}
            -\\rho I - 2ab\\, W_0^\\top T W_0 & (a + b)\\, W_0^\\top T \\\\
            (a + b)\\, T W_0 & -2T + W_1^\\top W_1
        \\end{bmatrix} \\preceq 0,

    (in Schur-lifted sparse form) and re-certifying the result in floating point so that
    :math:`L \\le \\sqrt{\\rho}` holds rigorously; see the module docstring.

    Parameters
    ----------
    W0 : array_like, shape (h, n_in)
        Hidden-layer weights.
    b0 : array_like, shape (h,) or None
        Hidden-layer bias (checked, but irrelevant for the Lipschitz constant).
    W1 : array_like, shape (n_out, h)
        Output-layer weights.
    slope : (float, float), optional
        Slope bounds ``(a, b)`` of the activation, taken as exact floats that must
        bracket the activation's difference quotients: ``(0, 1)`` for ``tanh`` (default),
        ``(0, 0.25)`` for the logistic sigmoid.
    solver : str or sequence of str, optional
        cvxpy solver name(s) tried in order.  Default: Clarabel (chordal decomposition,
        parent-child merging), then SCS.
    verbose : bool, optional
        Passed to the solver.
    max_tries : int, optional
        Maximum number of rigorous LMI checks during re-certification.

    Returns
    -------
    LipschitzResult
        ``value`` is always a rigorous upper bound: the re-certified LipSDP bound, or the
        naive bound :math:`\\|W_1\\|_2\\|W_0\\|_2` (``certified=False``) when re-certification
        fails or does not beat it.
    """
    t_start = time.perf_counter()
    W0, b0, W1 = _validate(W0, b0, W1)
    a, b = _check_slope(slope)
    naive = lipschitz_naive(W0, W1, slope=(a, b))

    def done(value, sdp_value, solver_name, certified, note):
        return LipschitzResult(
            value=float(value),
            sdp_value=float(sdp_value),
            naive=naive,
            solver=solver_name,
            seconds=time.perf_counter() - t_start,
            certified=bool(certified),
            note=note,
        )

    # neurons with a zero input row or a zero output column do not affect the map
    keep = np.any(W0 != 0.0, axis=1) & np.any(W1 != 0.0, axis=0)
    W0k, W1k = W0[keep], W1[:, keep]
    if W0k.shape[0] == 0 or W0.shape[1] == 0 or W1.shape[0] == 0:
        return done(0.0, 0.0, "trivial", True, "no active neuron: the network is constant")
    pruned = int(np.sum(~keep))
    prune_note = f"; {pruned} inactive neuron(s) pruned" if pruned else ""

    cp = deps.cvxpy()

    installed = set(cp.installed_solvers())
    if solver is None:
        solvers = [s for s in ("CLARABEL", "SCS") if s in installed]
    elif isinstance(solver, str):
        solvers = [solver.upper()]
    else:
        solvers = [s.upper() for s in solver]
    if not solvers:
        return done(naive, math.nan, "none", False, "no SDP solver installed; naive bound")

    s0 = float(np.linalg.norm(W0k, 2))
    s1 = float(np.linalg.norm(W1k, 2))
    A, B = W0k / s0, W1k / s1
    errors = []
    for name in solvers:
        try:
            tn, rn = _solve_sdp(A, B, a, b, name, verbose)
        except Exception as exc:  # solver failure: try the next one
            raise_if_interrupted(exc)
            errors.append(f"{name}: {type(exc).__name__}: {exc}")
            continue
        t_sol = tn * s1**2
        rho_sol = rn * (s0 * s1) ** 2
        sdp_value = math.sqrt(rho_sol) if rho_sol >= 0 else math.nan
        rc = _recertify(W0k, W1k, t_sol, rho_sol, (a, b), max_tries=max_tries)
        if rc.rho is None:
            return done(
                naive,
                sdp_value,
                name,
                False,
                f"re-certification failed ({rc.note}); naive bound returned{prune_note}",
            )
        value = rc.value
        if value > naive:
            return done(
                naive,
                sdp_value,
                name,
                False,
                f"certified LipSDP bound {value:.17g} is not below the naive bound; "
                f"naive bound returned{prune_note}",
            )
        return done(value, sdp_value, name, True, f"LipSDP {rc.note}{prune_note}")
    return done(
        naive,
        math.nan,
        "none",
        False,
        "all SDP solvers failed (" + "; ".join(errors) + "); naive bound returned",
    )
