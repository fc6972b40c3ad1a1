r"""The floating-point rounding model (the core layer): every rigorous bound rests on it.

Model
-----
All arithmetic is IEEE 754 binary64 (numpy ``float64``) in round-to-nearest. For a real
value :math:`w` within the normal range the stored result :math:`\hat w = fl(w)` satisfies

.. math:: \hat w = w (1 + \delta), \quad |\delta| \le u = 2^{-53},

and in the subnormal range :math:`|\hat w - w| \le \eta / 2` with :math:`\eta = 2^{-1074}`
(the smallest positive float). One rounding therefore moves a result by at most half an
ulp, and one ulp (:func:`next_up`) or a relative :math:`2^{-52}` (:func:`up`) past the
stored float always reaches the exact value. ``+ - * /`` and ``sqrt`` are *correctly
rounded* (one rounding of the exact real result); a sum or difference of two floats that
is zero or subnormal is exact (both operands are multiples of :math:`\eta`). numpy's
elementary functions (``exp``, ``log``, ``tanh``, ...) are not correctly rounded: numpy
documents and tests them to under 4 ulps, and they are widened here by at least 16.

A sequence of :math:`k` roundings (a dot product or sum of :math:`k` terms in any order,
FMA or not) is bounded by Higham's constant

.. math:: \gamma_k = \frac{k u}{1 - k u}, \qquad
          |fl(x^\top y) - x^\top y| \le \gamma_k\, |x|^\top |y| \; (+\text{underflow}).

Helpers and what each guarantees
--------------------------------
Each helper keeps one rule; they differ on purpose (cost, and whether the input came
from one correctly rounded operation, from a libm function or from a longer
computation), so use the one whose premise matches how the value was produced.

- :func:`up`, :func:`dn`: ``y`` is the result of one correctly rounded operation
  (``+ - * /``, ``sqrt``, any sign, subnormals included): ``dn(y) <= exact <= up(y)``.
  Rule: ``y·(1 ± 2**-52)`` then ``± 2**-1074``; the relative step covers the half ulp of a
  normal result and the absolute step the half ulp of a subnormal one. A bound that
  overflowed is clipped to ``±float_max`` on the safe side (a lower bound never becomes
  ``+inf``, an upper bound never ``-inf``). Arrays or scalars; cheap (no ``nextafter``).
- :func:`up_sum`, :func:`dn_sum`: ``y`` is the rounded sum or difference of two floats.
  As :func:`up`/:func:`dn` without the absolute step (zero and subnormal sums are exact),
  so ``0 + 0`` stays ``[0, 0]``.
- :func:`up_fn`, :func:`dn_fn`: ``y`` is a numpy/scipy elementary-function value
  (error below 16 ulps): relative ``2**-48`` plus absolute ``2**-1060``.
- :func:`next_up`, :func:`next_down`: ``steps`` floats past ``x`` (``np.nextafter``).
  One step bounds every real that rounds to nearest as ``x`` (one correctly rounded
  operation); two steps also cover the rounding of an operation applied to an already
  rounded bound (e.g. ``sqrt`` of an upper bound). Exact, tightest, scalar-friendly.
- :func:`up_rel`, :func:`dn_rel`: a value with a *relative* error budget: ``up_rel(v, k)``
  is at least ``(1 + k u)·v`` for ``v >= 0`` (the product's own rounding covered by two
  ulps), so it bounds every real ``w`` with ``w <= (1 + k u) v``; ``dn_rel(v, k)`` is at
  most ``v - k u |v|`` for any sign. Use them where a short computation (one to three
  roundings, or a few libm ulps) produced ``v``; ``k`` names the budget in units of ``u``.
- :func:`up_roundings`: ``x >= 0`` computed with at most ``m`` roundings:
  ``x·(1 + 2(m + 4)u) + 2**-1000`` (bounds :math:`(1+u)^m/(1-u)` and the underflow of
  the operations, and the rounding of this very line).
- :func:`add_up`, :func:`mul_up`: sums and products of Python floats each rounded up by
  one ulp (:func:`next_up` after every operation); for short scalar bound arithmetic.
- :func:`gamma`: a float :math:`\ge \gamma_k` (rigorous). :func:`gamma_rn`: :math:`\gamma_k`
  rounded to nearest (``1 - k u`` is exact, so this is within half an ulp of
  :math:`\gamma_k`, possibly below it): only for error terms that a caller multiplies by
  a further relative safety factor; prefer :func:`gamma`.

The checks of every helper against exact (mpmath) arithmetic on random and adversarial
values (zero, subnormals, huge, negative, infinite) are in ``tests/test_rounding.py``.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "U", "EPS", "ETA", "FLOAT_MAX", "FOLD", "gamma", "gamma_rn", "up", "dn", "up_sum", "dn_sum",
    "up_fn", "dn_fn", "next_up", "next_down", "up_rel", "dn_rel", "up_roundings", "add_up",
    "mul_up",
]

#: unit roundoff of float64 round-to-nearest
U = 2.0**-53

#: relative allowance added to interval enclosures of derivative graphs: CasADi folds
#: products of constants in float64 when it builds a graph (a relative error of a few units
#: of ``U`` per fold), so an enclosure of the folded graph is widened by this fraction of its
#: magnitude (a power of two: exact in float64 and as a ``Fraction``)
FOLD = 2.0**-30
#: machine epsilon (the spacing of floats at 1), ``2 u``
EPS = 2.0 * U
#: smallest positive (subnormal) float64
ETA = 2.0**-1074
#: largest finite float64
FLOAT_MAX = float(np.finfo(np.float64).max)

_INF = np.inf
_R1_LO, _R1_HI = 1.0 - 2.0**-52, 1.0 + 2.0**-52  # one ulp, correctly rounded operations
_RW_LO, _RW_HI = 1.0 - 2.0**-48, 1.0 + 2.0**-48  # >= 16 ulps, elementary functions
_ETA_W = 2.0**-1060  # absolute slack of elementary functions (subnormal results)
_TINY_ROUNDINGS = 2.0**-1000  # absolute slack of up_roundings (underflow)
_GAMMA_MAX_KU = 0.01  # k u above this: the analysis is refused (k >= 9e13)


# --------------------------------------------------------------------------- gamma_k
def gamma_rn(k: int) -> float:
    r"""Return :math:`\gamma_k = k u / (1 - k u)` rounded to nearest.

    ``k u`` and ``1 - k u`` are exact (``k u <= 0.01``), so the result is the correctly
    rounded :math:`\gamma_k`: within half an ulp, possibly *below* it. Use :func:`gamma`
    for a guaranteed upper bound.

    Raises
    ------
    ValueError
        If ``k u > 0.01`` (more than about ``9e13`` terms): the rounding-error analysis
        does not cover the problem; split it.
    """
    ku = k * U
    if ku >= _GAMMA_MAX_KU:
        raise ValueError(f"the rounding-error analysis supports sums of fewer than 9e13 terms, "
                         f"got k={k}; split the computation")
    return ku / (1.0 - ku)


def gamma(k: int) -> float:
    r"""Return a float :math:`\ge \gamma_k = k u / (1 - k u)` (Higham's constant).

    :func:`gamma_rn` is within a relative :math:`u` of :math:`\gamma_k`; the factor
    ``1 + 1e-10`` (itself rounded, relative error ``u``) lifts it above.

    Raises
    ------
    ValueError
        As :func:`gamma_rn`.
    """
    return gamma_rn(k) * (1.0 + 1e-10)


# --------------------------------------------------------------------------- one operation
def dn(y):
    """Lower bound of the real result of one correctly rounded operation that gave ``y``."""
    t = y * _R1_LO
    r = y * _R1_HI
    if type(t) is np.ndarray:
        np.minimum(t, r, out=t)
        t -= ETA
        return np.minimum(t, FLOAT_MAX, out=t)
    return np.minimum(np.minimum(t, r) - ETA, FLOAT_MAX)


def up(y):
    """Upper bound of the real result of one correctly rounded operation that gave ``y``."""
    t = y * _R1_LO
    r = y * _R1_HI
    if type(t) is np.ndarray:
        np.maximum(t, r, out=t)
        t += ETA
        return np.maximum(t, -FLOAT_MAX, out=t)
    return np.maximum(np.maximum(t, r) + ETA, -FLOAT_MAX)


def dn_fn(y):
    """Lower bound of a real function value that numpy computed as ``y`` (<= 16 ulps)."""
    t = y * _RW_LO
    r = y * _RW_HI
    if type(t) is np.ndarray:
        np.minimum(t, r, out=t)
        t -= _ETA_W
        return np.minimum(t, FLOAT_MAX, out=t)
    return np.minimum(np.minimum(t, r) - _ETA_W, FLOAT_MAX)


def up_fn(y):
    """Upper bound of a real function value that numpy computed as ``y`` (<= 16 ulps)."""
    t = y * _RW_LO
    r = y * _RW_HI
    if type(t) is np.ndarray:
        np.maximum(t, r, out=t)
        t += _ETA_W
        return np.maximum(t, -FLOAT_MAX, out=t)
    return np.maximum(np.maximum(t, r) + _ETA_W, -FLOAT_MAX)


def dn_sum(y):
    """Lower bound of the real sum or difference of two floats that gave ``y``.

    As :func:`dn` without the absolute ``2**-1074``: a sum that is zero or subnormal is
    exact (both operands are multiples of ``2**-1074``), so ``0 + 0`` stays ``[0, 0]``
    (``x² + y²`` keeps a lower bound of 0, as a square root's domain check needs).
    """
    t = y * _R1_LO
    r = y * _R1_HI
    if type(t) is np.ndarray:
        np.minimum(t, r, out=t)
        return np.minimum(t, FLOAT_MAX, out=t)
    return np.minimum(np.minimum(t, r), FLOAT_MAX)


def up_sum(y):
    """Upper bound of the real sum or difference of two floats that gave ``y``."""
    t = y * _R1_LO
    r = y * _R1_HI
    if type(t) is np.ndarray:
        np.maximum(t, r, out=t)
        return np.maximum(t, -FLOAT_MAX, out=t)
    return np.maximum(np.maximum(t, r), -FLOAT_MAX)


# --------------------------------------------------------------------------- ulp steps
def _steps(x, direction: float, steps: int):
    r = np.asarray(x, dtype=float)
    for _ in range(steps):
        r = np.nextafter(r, direction)
    return float(r) if np.ndim(r) == 0 else r


def next_up(x, steps: int = 1):
    """``x`` moved ``steps`` floats towards ``+inf`` (a float for scalar input, else an array).

    One step is an upper bound of every real that rounds to nearest as ``x``.
    """
    return _steps(x, _INF, steps)


def next_down(x, steps: int = 1):
    """``x`` moved ``steps`` floats towards ``-inf`` (a float for scalar input, else an array).

    One step is a lower bound of every real that rounds to nearest as ``x``.
    """
    return _steps(x, -_INF, steps)


# --------------------------------------------------------------------------- relative budgets
def up_rel(v, k: int):
    """An upper bound of ``(1 + k u)·v`` for ``v >= 0`` (a float for scalar input).

    ``v·(1 + k u)`` (``1 + k u`` exact for ``k < 2**52``) rounded, then two ulps up.
    """
    return next_up(np.asarray(v, dtype=float) * (1.0 + k * U), 2)


def dn_rel(v, k: int) -> float:
    """A lower bound of ``v - k u |v|`` for a float ``v`` of any sign."""
    v = float(v)
    return next_down(v - abs(v) * (k * U), 2)


def up_roundings(x, m: int):
    """Upper bound of a nonnegative real computed in round-to-nearest with ``<= m`` roundings.

    ``x·(1 + 2(m + 4)u) + 2**-1000``: the factor (exactly representable) bounds
    ``(1 + u)**m / (1 - u)`` with room for this line's own two roundings; the absolute
    term covers underflow.
    """
    return x * (1.0 + 2.0 * (m + 4) * U) + _TINY_ROUNDINGS


# --------------------------------------------------------------------------- scalar chains
def add_up(*vals) -> float:
    """Upper bound of the exact sum of ``vals`` (each partial sum rounded up one ulp)."""
    s = 0.0
    for v in vals:
        s = next_up(s + float(v))
    return s


def mul_up(a, b) -> float:
    """Upper bound of the exact product ``a·b`` of two floats."""
    return next_up(float(a) * float(b))
