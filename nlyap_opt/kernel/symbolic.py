r"""Closed loops and Lie derivatives as CasADi expressions (one graph for every consumer).

For a Lyapunov candidate :math:`V`, feedback :math:`\kappa` and vector field :math:`g`
(the true :math:`f` or a learned :math:`\varphi`), the Lie derivative is

.. math:: \dot V(x) = \nabla V(x) \cdot g(x, \kappa(x)).

Everything is built on one ``MX`` state symbol so that network layers stay matrix nodes;
the system's SX right-hand side enters as a call node.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import casadi as ca
import numpy as np

from .errors import DimensionError, EquilibriumError, EquilibriumWarning, NetworkFileError
from .network import Network

__all__ = ["ClosedLoop", "closed_loop", "learned_components_of", "lie_derivative", "robust_lie"]


@dataclass
class ClosedLoop:
    """Symbolic closed loop ``x' = g(x, κ(x))`` on an MX state ``x``.

    Attributes
    ----------
    x : casadi.MX (nx, 1)
    u : casadi.MX (nu, 1)          the feedback expression κ(x) (``u_eq`` if no controller)
    rhs : casadi.MX (nx, 1)        g(x, κ(x))
    """

    x: ca.MX
    u: ca.MX
    rhs: ca.MX

    def function(self, name: str = "closed_loop") -> ca.Function:
        return ca.Function(name, [self.x], [self.rhs])


def closed_loop(system, controller: Network | None = None, dynamics: Network | None = None,
                *, x: ca.MX | None = None, strict: bool = True) -> ClosedLoop:
    """Compose the closed loop of ``system`` under ``controller``.

    Parameters
    ----------
    system : systems.System
    controller : Network, optional
        ``κ: R^nx -> R^nu``; ``None`` applies the constant equilibrium input.
    dynamics : Network, optional
        Learned ``φ(x, u)`` (input ``nx + nu``, output ``nx``) that replaces ``f``.
        A network with ``meta["learned_components"]`` outputs only those state
        derivatives; the others are taken from ``system`` (known exactly).
    strict : bool
        If the origin is not an equilibrium of the closed loop, raise
        :class:`EquilibriumError` (training) or only warn (verification of user networks).
    """
    _check_closed_loop_args(system, controller, dynamics, x)
    x = ca.MX.sym("x", system.nx) if x is None else x
    sym = ca.SX if isinstance(x, ca.SX) else ca.MX   # u of x's type (an SX x with MX u fails)
    if controller is None:
        u = sym(ca.DM(system.u_eq)) if system.nu else sym(0, 1)
    else:
        if controller.n_in != system.nx or controller.n_out != system.nu:
            raise DimensionError(
                f"controller maps R^{controller.n_in} -> R^{controller.n_out}; system "
                f"{system.name!r} needs R^{system.nx} -> R^{system.nu}"
            )
        u = controller.casadi(x)
    if dynamics is None:
        rhs = system.f_fun(x, u)
    else:
        rhs = learned_rhs(system, dynamics, x, u)
    cl = ClosedLoop(x, u, rhs)
    # the equilibrium condition is about the plant f(0, κ(0)), not a learned φ (φ(0) ≠ 0 in
    # general; the verified annulus excludes B_ε, where that does not matter); without a
    # model, f(0, u_eq) = 0 is declared (and checked on the data), so κ(0) = u_eq is required
    if getattr(system, "has_model", True):
        plant = system.f_fun(x, u)
        what = "rhs(0)"
    else:
        plant = u - ca.DM(system.u_eq) if system.nu else sym(0, 1)
        what = "κ(0) − u_eq"
    at0 = np.array(ca.Function("r", [x], [plant])(np.zeros(system.nx)), dtype=float).ravel()
    if np.max(np.abs(at0), initial=0.0) > 1e-8:
        msg = (f"the origin is not an equilibrium of the closed loop of {system.name!r}: "
               f"{what} = {at0}; solve the controller bias from f(0, κ(0)) = 0 "
               "(nlyap_opt.design.control.saturated_controller does)")
        if strict:
            raise EquilibriumError(msg)
        warnings.warn(msg, EquilibriumWarning, stacklevel=2)
    return cl


def learned_components_of(system, dynamics: Network) -> list[int]:
    """The state indices a learned ``φ`` outputs (``meta["learned_components"]``, default
    all); the others are the system's exactly known state derivatives.

    Raises
    ------
    NetworkFileError
        The list is not one of distinct state indices.
    """
    learned = dynamics.meta.get("learned_components")
    if learned is None:
        return list(range(system.nx))
    if not isinstance(learned, (list, tuple)) or not all(
            isinstance(i, int) and not isinstance(i, bool) for i in learned):
        raise NetworkFileError(f"dynamics network meta.learned_components must be a list "
                               f"of ints (state indices), got {learned!r}; fix the file's meta")
    learned = list(learned)
    if len(set(learned)) != len(learned) or not all(0 <= i < system.nx for i in learned):
        raise NetworkFileError(
            f"dynamics network meta.learned_components {learned} must be distinct state "
            f"indices in 0..{system.nx - 1} of system {system.name!r}; fix the file's meta")
    return learned


def learned_rhs(system, dynamics: Network, x, u):
    """``φ(x, u)``, completed with the exactly known components of ``f`` if needed.

    Two models (``dynamics.meta["model"]``):

    - ``"full"`` (default): ``φ`` takes ``(x, u)`` and outputs the learned components;
    - ``"control_affine"``: ``φ₀`` takes ``x`` only and the learned components are
      ``φ₀(x) + B u`` with the known constant input matrix ``meta["input_matrix"]``.

    ``meta["learned_components"]`` lists the state indices ``φ`` outputs (default: all);
    the other components are taken from ``system`` (known exactly).
    """
    model = dynamics.meta.get("model", "full")
    if model not in ("full", "control_affine"):
        raise NetworkFileError(f"dynamics network meta.model is {model!r}; expected 'full' or "
                               "'control_affine' (fix the file's meta or relearn φ)")
    learned = learned_components_of(system, dynamics)
    n_in = system.nx if model == "control_affine" else system.nx + system.nu
    if dynamics.n_in != n_in or dynamics.n_out != len(learned):
        raise DimensionError(
            f"dynamics network maps R^{dynamics.n_in} -> R^{dynamics.n_out}; system "
            f"{system.name!r} with model {model!r} and learned components {learned} needs "
            f"R^{n_in} -> R^{len(learned)}"
        )
    if model == "control_affine":
        phi = dynamics.casadi(x)
        if system.nu:
            try:
                B = np.array(dynamics.meta.get("input_matrix"), dtype=float).reshape(
                    len(learned), system.nu)
            except (TypeError, ValueError):
                raise NetworkFileError(
                    f"control-affine dynamics network needs meta.input_matrix of shape "
                    f"({len(learned)}, {system.nu}) with numbers, got "
                    f"{dynamics.meta.get('input_matrix')!r}") from None
            if not np.all(np.isfinite(B)):
                raise NetworkFileError("meta.input_matrix holds NaN or inf; fix the file")
            phi = phi + ca.mtimes(ca.DM(B), u)
    else:
        phi = dynamics.casadi(ca.vertcat(x, u))
    if learned == list(range(system.nx)):
        return phi
    known = list(system.known_state_derivatives)
    missing = [i for i in range(system.nx) if i not in learned and i not in known]
    if missing:
        raise NetworkFileError(
            f"dynamics network learns components {learned} of {system.name!r}, and components "
            f"{missing} are neither learned nor known exactly; relearn φ for them")
    kf = system.known_function()(x, u)
    return ca.vertcat(*[phi[learned.index(i)] if i in learned else kf[known.index(i)]
                        for i in range(system.nx)])


def _check_closed_loop_args(system, controller, dynamics, x) -> None:
    """One line naming the argument of :func:`closed_loop` that is not what it takes."""
    if not all(hasattr(system, a) for a in ("nx", "nu", "u_eq")):  # (f_fun: a model only)
        raise DimensionError(f"closed_loop needs a System (systems.get(name) or "
                             f"systems.load_spec(path)), got {type(system).__name__}")
    for name, net in (("controller", controller), ("dynamics", dynamics)):
        if net is not None and not isinstance(net, Network):
            raise DimensionError(f"{name} must be a Network (Network.load(path) reads a saved "
                                 f"one) or None, got {type(net).__name__}")
    if x is not None and not (isinstance(x, (ca.MX, ca.SX)) and x.is_symbolic()
                              and x.shape == (system.nx, 1)):
        raise DimensionError(f"x must be a CasADi symbol of shape ({system.nx}, 1) (e.g. "
                             f"casadi.MX.sym('x', {system.nx})), got "
                             f"{type(x).__name__}{getattr(x, 'shape', '')}")


def lie_derivative(V: ca.MX, x: ca.MX, rhs: ca.MX) -> ca.MX:
    r"""Lie derivative :math:`\nabla V(x) \cdot g(x)` of a scalar expression ``V``.

    ``V``, ``x`` (a column of symbols) and ``rhs`` (a column as long as ``x``) are CasADi
    expressions of one kind (all ``MX`` or all ``SX``).
    """
    kinds = {type(a) for a in (V, x, rhs)}
    if not kinds <= {ca.MX, ca.SX} or len(kinds) != 1:
        raise DimensionError("V, x and rhs must be CasADi expressions of one kind (all MX or "
                             f"all SX), got {', '.join(type(a).__name__ for a in (V, x, rhs))}")
    if V.shape != (1, 1):
        raise DimensionError(f"V must be scalar, got shape {V.shape}")
    if not x.is_symbolic() or x.shape[1] != 1:
        raise DimensionError(f"x must be a column of symbols, got shape {x.shape}")
    if rhs.shape != x.shape:
        raise DimensionError(f"rhs has shape {rhs.shape} but x has {x.shape}; give one "
                             "derivative per state")
    return ca.dot(ca.gradient(V, x), rhs)


def robust_lie(lie: ca.MX, V: ca.MX, x: ca.MX, eta: float, smoothing: float = 0.0,
               components: list[int] | None = None) -> ca.MX:
    r"""``∇V·φ + η·sqrt(‖∇_L V‖₂² + s²)``, ``s = smoothing``, ``L = components``.

    By Cauchy–Schwarz an upper bound of ``∇V·f`` wherever ``‖f − φ‖₂ ≤ η``, for every
    ``s ≥ 0`` (``sqrt(q + s²) ≥ sqrt(q)``); ``s`` costs at most ``η·s`` of slack. ``s > 0``
    keeps the derivative of the square root finite (at most ``1/(2s)``) where an interval
    enclosure of ``‖∇V‖²`` reaches 0 — with ``s = 0`` the verifier's mean-value form is
    lost there and boxes near the inner ball multiply (measured: Van der Pol, a 2-20-20 V,
    1.7 million boxes with ``s = 0`` and 74 thousand with ``s = 10⁻³·sup‖∇V‖``).

    ``components`` (default: all): the state derivatives that are learned. The others are
    known exactly (``f_i − φ_i = 0``), so ``∇V·(f − φ) = ∇_L V·(f_L − φ_L) ≤ η‖∇_L V‖``
    with only the learned components' partial derivatives in the norm (the cartpole's
    velocities, not its positions).
    """
    if not smoothing >= 0:
        raise ValueError(f"smoothing must be >= 0, got {smoothing!r}")
    g = ca.gradient(V, x)
    if components is not None:
        g = ca.vertcat(*[g[i] for i in components])
    q = ca.sumsqr(g)
    return lie + eta * ca.sqrt(q + smoothing**2 if smoothing else q)
