r"""Independent reference: the largest level of the LQR quadratic for reversed Van der Pol.

Reversed Van der Pol (no input): :math:`\dot x_1 = -x_2`,
:math:`\dot x_2 = x_1 - \mu x_2 + \mu x_1^2 x_2`, i.e. :math:`\dot x = A x + g(x)` with
:math:`A = [[0, -1], [1, -\mu]]` and the cubic :math:`g(x) = (0, \mu x_1^2 x_2)`. The baselines'
quadratic is :math:`V = x^\top P x` with :math:`A^\top P + P A = -I` (Q = I, no input).

On the ray :math:`x = r u`, :math:`\|u\| = 1`: :math:`V = r^2 q(u)` with :math:`q = u^\top P u`,
and :math:`\dot V = r^2 \alpha(u) + r^4 \beta(u)` with :math:`\alpha = u^\top (A^\top P + P A) u
= -1` and :math:`\beta = 2 u^\top P g(u)` (``g`` is homogeneous of degree 3). So
:math:`\dot V \ge 0` at :math:`x \ne 0` exactly when :math:`\beta(u) > 0` and
:math:`r^2 \ge -\alpha/\beta`, and the least ``V`` there is

.. math:: c^* = \min_{\theta:\ \beta > 0} \; q(\theta)\,\frac{-\alpha(\theta)}{\beta(\theta)}.

Every level ``c < c*`` has :math:`\dot V < 0` on :math:`\{V \le c\} \setminus \{0\}`, and no
level above it does: ``c*`` is the supremum of the levels any sound verifier may certify for
this ``V`` (decrease on the whole sublevel set). It is computed here by a dense grid in
``θ`` refined by a bounded scalar minimisation, with nothing from the toolbox. For μ = 1,
``c* = 2.30454...`` (the figure 2.3045 used by older tests).
"""

import numpy as np
from scipy.linalg import solve_continuous_lyapunov
from scipy.optimize import minimize_scalar

__all__ = ["vdp_limit_cycle", "vdp_lyapunov_matrix", "vdp_quadratic_level", "vdp_sampled_level",
           "vdp_true_roa_area"]


def vdp_lyapunov_matrix(mu: float = 1.0) -> np.ndarray:
    """``P`` with ``AᵀP + PA = -I`` for the linearisation of reversed Van der Pol."""
    A = np.array([[0.0, -1.0], [1.0, -mu]])
    return solve_continuous_lyapunov(A.T, -np.eye(2))


def _ratio(theta, P, mu):
    """``q(θ)·(-α(θ))/β(θ)`` where ``β > 0``, ``inf`` elsewhere (vectorised in ``θ``)."""
    A = np.array([[0.0, -1.0], [1.0, -mu]])
    u = np.stack([np.cos(theta), np.sin(theta)], axis=-1)
    q = np.einsum("...i,ij,...j->...", u, P, u)
    alpha = np.einsum("...i,ij,...j->...", u, A.T @ P + P @ A, u)
    g = np.stack([np.zeros_like(theta), mu * u[..., 0] ** 2 * u[..., 1]], axis=-1)
    beta = 2.0 * np.einsum("...i,ij,...j->...", u, P, g)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(beta > 0, q * (-alpha) / beta, np.inf)


def vdp_quadratic_level(P, mu: float = 1.0, n: int = 200_001) -> float:
    """``c*`` of the module docstring for ``V = xᵀPx`` (``P`` a Lyapunov matrix of ``A``)."""
    P = np.asarray(P, dtype=float)
    th = np.linspace(0.0, 2.0 * np.pi, n)
    vals = _ratio(th, P, mu)
    k = int(np.argmin(vals))
    h = th[1] - th[0]
    res = minimize_scalar(lambda t: float(_ratio(np.asarray(t), P, mu)),
                          bounds=(th[k] - h, th[k] + h), method="bounded",
                          options={"xatol": 1e-12})
    return float(min(res.fun, vals[k]))


def vdp_sampled_level(P, mu: float = 1.0, radius: float = 3.0, n: int = 1201) -> float:
    """Least ``V`` over a dense planar grid where ``V̇ ≥ 0`` (``x ≠ 0``): an upper bound of
    ``c*`` that a grid of spacing ``2·radius/(n-1)`` approaches from above."""
    P = np.asarray(P, dtype=float)
    g = np.linspace(-radius, radius, n)
    X1, X2 = np.meshgrid(g, g, indexing="ij")
    f1, f2 = -X2, X1 - mu * X2 + mu * X1**2 * X2
    V = P[0, 0] * X1**2 + 2 * P[0, 1] * X1 * X2 + P[1, 1] * X2**2
    Vdot = 2 * ((P[0, 0] * X1 + P[0, 1] * X2) * f1 + (P[0, 1] * X1 + P[1, 1] * X2) * f2)
    bad = (Vdot >= 0) & (X1**2 + X2**2 > 1e-6)
    return float(V[bad].min())


def vdp_limit_cycle(mu: float = 1.0, rtol: float = 1e-12) -> np.ndarray:
    r"""The limit cycle bounding reversed Van der Pol's ROA, by an integrator the toolbox
    does not use (SciPy's adaptive DOP853 on the forward-time system, whose cycle attracts).

    Forward Van der Pol :math:`\dot x_1 = x_2,\ \dot x_2 = -x_1 + \mu(1 - x_1^2)x_2` is the
    reversed system in reversed time, so its stable limit cycle is the boundary of the
    reversed system's ROA. From (2, 0), 60 time units settle onto the cycle (its Floquet
    multiplier at μ = 1 is about e^{-1.06 T}); one period is then cut between two upward
    crossings of x₂ = 0 with x₁ > 0, located by dense output to ``rtol``.

    Returns
    -------
    (N, 2) ndarray
        Points of one period of the cycle (closed: the last equals the first to ``rtol``).
    """
    from scipy.integrate import solve_ivp

    def forward(t, x):
        return [x[1], -x[0] + mu * (1.0 - x[0] ** 2) * x[1]]

    settle = solve_ivp(forward, (0.0, 60.0), [2.0, 0.0], method="DOP853", rtol=rtol,
                       atol=rtol)

    def crossing(t, x):
        return x[1]

    crossing.direction = -1.0   # x₂ falls through 0 at the cycle's rightmost point
    cyc = solve_ivp(forward, (0.0, 30.0), settle.y[:, -1], method="DOP853", rtol=rtol,
                    atol=rtol, events=crossing, dense_output=True)
    t0, t1 = cyc.t_events[0][1], cyc.t_events[0][2]
    ts = np.linspace(t0, t1, 20001)
    return cyc.sol(ts).T


def vdp_true_roa_area(mu: float = 1.0) -> float:
    """Area inside :func:`vdp_limit_cycle` (the shoelace formula on 20 001 points; the
    polygon's error is O(1/N²), far below 1e-6 here)."""
    x, y = vdp_limit_cycle(mu).T
    return 0.5 * abs(float(np.dot(x[:-1], y[1:]) - np.dot(x[1:], y[:-1])))
