r"""The Jacobian of an unknown ``f`` at the equilibrium, from data, with a rigorous error bound.

For condition (c) of a learned-``f`` certificate (docs/method.md, "Condition (c) for unknown f,
from samples"): with the declared second-derivative bound
:math:`|\partial^2 f_k / \partial z_i \partial z_j| \le H` on :math:`X \times U`, a central
difference around the equilibrium :math:`z_0 = (0, u_{eq})` over the nodes
:math:`z_0 - b\,e_i` and :math:`z_0 + a\,e_i`,

.. math:: \hat J_{ki} = \frac{f_k(z_0 + a e_i) - f_k(z_0 - b e_i)}{a + b}
          = \partial_i f_k(z_0) + \frac{a^2 \partial_{ii} f_k(\xi_+)
            - b^2 \partial_{ii} f_k(\xi_-)}{2 (a + b)},

(Taylor with the Lagrange remainder on each side) is within
:math:`H (a^2 + b^2) / (2 (a + b))` (:math:`= H h / 2` for :math:`a = b = h`) of the true
derivative. :func:`jacobian_from_data` adds every other error it can name, entry by entry
and rounded up: data noise (a declared ``sample_error`` ε: :math:`2ε/(a + b)`), the float64
subtraction and division (4 units in the last place of :math:`|\hat J|`), and — where the
nearest node is not exactly :math:`z_0` — :math:`H \|z_{node} - z_0\|_1` (the mean value
theorem on :math:`\partial_i f_k`). Every ``f`` that agrees with the data and the
declaration then has :math:`|J_{ki} - \hat J_{ki}| \le \text{error}_{ki}`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nlyap_opt.kernel.errors import ConfigError
from nlyap_opt.kernel.rounding import U, up_rel

from .base import System

__all__ = ["JacobianBound", "jacobian_from_data"]


@dataclass
class JacobianBound:
    r"""Central-difference Jacobian :math:`[\hat A\ \hat B]` at the equilibrium and its bound.

    Attributes
    ----------
    J : (nx, nx + nu) ndarray
        :math:`\hat J = [\hat A\ \hat B]` (columns: states, then inputs).
    error : (nx, nx + nu) ndarray
        Entrywise bound :math:`|J_{true} - \hat J| \le` ``error`` (rounded up).
    steps : (nx + nu, 2) ndarray
        ``(b, a)`` per axis: the distances of the nodes used below and above.
    point : (nx + nu,) ndarray
        The node used as :math:`z_0`.
    hessian : float
        The declared :math:`H` the bound rests on.
    source : str
        ``"samples"``, ``"callable"`` or ``"model"`` (a model evaluated like a black box).
    """

    J: np.ndarray
    error: np.ndarray
    steps: np.ndarray
    point: np.ndarray
    hessian: float
    source: str

    @property
    def A(self) -> np.ndarray:
        """:math:`\\hat A = \\partial f / \\partial x` estimate, ``(nx, nx)``."""
        return self.J[:, :self.J.shape[0]]

    @property
    def B(self) -> np.ndarray:
        """:math:`\\hat B = \\partial f / \\partial u` estimate, ``(nx, nu)``."""
        return self.J[:, self.J.shape[0]:]

    def to_dict(self) -> dict:
        return {"J": self.J.tolist(), "error": self.error.tolist(), "steps": self.steps.tolist(),
                "point": self.point.tolist(), "hessian": self.hessian, "source": self.source}


def jacobian_from_data(system: System, *, step=None) -> JacobianBound:
    r"""Bound the Jacobian of ``f`` at ``(0, u_eq)`` from the data and the declared ``H``.

    Parameters
    ----------
    system : System
        With ``declarations.hessian`` declared. A ``"samples"`` system uses the grid
        neighbours of the equilibrium node (a single input level: the declared ``B``, exact
        under that declaration); a ``"callable"`` (or ``"model"``) is evaluated at
        ``z0 ± step`` along each axis.
    step : float or (nx + nu,) array_like, optional
        Half-width of the differences for a callable (default per axis:
        ``max(sqrt(2ε/H), 1e-6·width)`` with ε the declared ``sample_error`` or 0). Ignored
        for samples (the grid's spacing).

    Returns
    -------
    JacobianBound

    Raises
    ------
    ConfigError
        No ``hessian`` declared; the equilibrium node lacks a neighbour on some axis (it is
        on the box boundary); a step leaves the box.

    Examples
    --------
    >>> import numpy as np, systems
    >>> s = systems.System.from_callable(
    ...     "p", lambda X, U: np.stack([X[:, 1], 9.81 * np.sin(X[:, 0]) + U[:, 0]], 1),
    ...     nx=2, nu=1, state_box=[[-1, 1], [-1, 1]], input_box=[[-1, 1]], u_eq=[0.0],
    ...     declarations=systems.Declarations(hessian=9.81))
    >>> jb = jacobian_from_data(s)
    >>> np.round(jb.J, 6).tolist(), bool(jb.error.max() < 1e-4)
    ([[0.0, 1.0, 0.0], [9.81, 0.0, 1.0]], True)
    """
    decl = system.declarations
    if decl is None or decl.hessian is None:
        raise ConfigError(
            f"the Jacobian of {system.name!r} from data needs a declared second-derivative "
            "bound; declare hessian (H) to bound the finite-difference error"
        )
    H = decl.hessian_max()   # one bound for every row (per-state bounds: the largest)
    eps = decl.sample_error or 0.0
    nx, nu = system.nx, system.nu
    d = nx + nu
    zeq = np.concatenate([np.zeros(nx), system.u_eq])
    J = np.zeros((nx, d))
    err = np.zeros((nx, d))
    steps = np.zeros((d, 2))
    if system.kind == "samples":
        smp = system.samples
        k0, _ = smp.nearest_node(np.where(smp.counts == 1, smp.box[:, 0], zeq))
        idx0 = np.array(np.unravel_index(k0, tuple(smp.counts)))
        z0 = smp.points([k0])[0]
        f_at = lambda idx: smp.values[np.ravel_multi_index(tuple(idx), tuple(smp.counts))]  # noqa: E731
        for i in range(d):
            if smp.counts[i] == 1:  # one input level: B is declared (control-affine)
                J[:, i] = decl.B[:, i - nx]
                continue
            lo_i, hi_i = idx0.copy(), idx0.copy()
            lo_i[i] -= 1
            hi_i[i] += 1
            if lo_i[i] < 0 or hi_i[i] >= smp.counts[i]:
                raise ConfigError(
                    f"the equilibrium node of {system.name!r} is on the boundary of the sample "
                    f"grid along {smp.names[i]!r}; sample a grid with nodes on both sides of it"
                )
            zm, zp = smp.axes[i][lo_i[i]], smp.axes[i][hi_i[i]]
            J[:, i], err[:, i], steps[i] = _central(f_at(hi_i), f_at(lo_i), zp, zm, z0[i], H, eps)
        z0 = np.where(smp.counts == 1, zeq, z0)  # a declared-B column is exact at any u
        source = "samples"
    else:
        box = system.sampling_box
        width = box[:, 1] - box[:, 0]
        if step is None:
            h = np.maximum(np.sqrt(2 * eps / H), 1e-6 * width)
        else:
            h = np.broadcast_to(np.asarray(step, dtype=float), (d,)).copy()
            if not np.all(np.isfinite(h)) or np.any(h <= 0):
                raise ConfigError(f"step must be positive numbers, got {step!r}")
        z0 = zeq.copy()
        Z = np.repeat(z0[None, :], 2 * d, axis=0)
        for i in range(d):
            Z[2 * i, i] = z0[i] + h[i]
            Z[2 * i + 1, i] = z0[i] - h[i]
        if np.any(Z < box[:, 0]) or np.any(Z > box[:, 1]):
            raise ConfigError(f"step {h.tolist()} leaves the box {box.tolist()} of "
                              f"{system.name!r}; use a smaller step")
        with np.errstate(all="ignore"):
            F = system.evaluate(Z[:, :nx], Z[:, nx:])
        if not np.all(np.isfinite(F)):
            raise ConfigError(f"f of {system.name!r} is not finite next to the equilibrium")
        for i in range(d):
            J[:, i], err[:, i], steps[i] = _central(F[2 * i], F[2 * i + 1], Z[2 * i, i],
                                                    Z[2 * i + 1, i], z0[i], H, eps)
        source = system.kind
    # the node is not (0, u_eq): |∂_i f_k(z0) − ∂_i f_k(zeq)| ≤ H ‖z0 − zeq‖₁
    shift = float(np.sum(np.abs(z0 - zeq)))
    if shift > 0:
        err = up_rel(err + H * shift, 4)
    return JacobianBound(J, err, steps, z0, H, source)


def _central(fp, fm, zp: float, zm: float, z0: float, H: float, eps: float):
    """One column: the difference quotient and its error bound (see the module docstring)."""
    a = float(np.nextafter(zp - z0, np.inf))   # distances, rounded up
    b = float(np.nextafter(z0 - zm, np.inf))
    a_lo = float(np.nextafter(zp - z0, -np.inf))
    b_lo = float(np.nextafter(z0 - zm, -np.inf))
    if not (a_lo > 0 and b_lo > 0):
        raise ConfigError("the difference nodes must lie on both sides of the equilibrium")
    q = (np.asarray(fp, dtype=float) - np.asarray(fm, dtype=float)) / (zp - zm)
    taylor = H * (a * a + b * b) / (2.0 * (a_lo + b_lo))
    noise = 2.0 * eps / (a_lo + b_lo)
    rounding = 4.0 * U * np.abs(q) * 2
    return q, up_rel(taylor + noise + rounding, 4), np.array([b, a])
