"""The :class:`System`: dynamics ``x' = f(x, u)`` as a CasADi SX expression, frozen once built."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import casadi as ca
import numpy as np

from nlyap_opt.errors import DimensionError, EquilibriumError
from nlyap_opt.walker import ArrayArithmetic, compile_function, evaluate

__all__ = ["System"]


def _box(box, n: int, what: str) -> np.ndarray:
    b = np.asarray(box, dtype=float)
    if b.shape != (n, 2):
        raise DimensionError(
            f"{what} must be an array of shape ({n}, 2) with rows (lower, upper), got {b.shape}"
        )
    if not np.all(np.isfinite(b)) or np.any(b[:, 0] >= b[:, 1]):
        raise ValueError(f"{what} needs finite bounds with lower < upper on every row, got {b}")
    return b


class System:
    r"""A continuous-time control system :math:`\dot x = f(x, u)` defined with CasADi.

    Parameters
    ----------
    name : str
        Identifier used by the registry and in reports.
    x : casadi.SX, shape (nx, 1)
        State symbols.
    u : casadi.SX, shape (nu, 1), or None
        Input symbols (``None`` or empty for autonomous systems such as Van der Pol).
    f : casadi.SX, shape (nx, 1)
        Right-hand side, an expression of ``x`` and ``u`` only.
    state_box : (nx, 2) array_like
        Working box ``X`` (rows: lower, upper) on which dynamics are sampled.
    input_box : (nu, 2) array_like, optional
        Input bounds ``U``.
    u_eq : (nu,) array_like, optional
        Equilibrium input, ``f(0, u_eq) = 0``. Solved from ``f(0, u) = 0`` when omitted.
    params : dict, optional
        Parameter values (documentation and reports).
    state_names, input_names : sequence of str, optional
    description : str, optional
    known_state_derivatives : sequence of int, optional
        Indices ``i`` of states whose derivative is known exactly (e.g. ``θ' = ω``); learned
        dynamics may model only the other components.

    Notes
    -----
    Derived once at construction: the CasADi Function ``f_fun(x, u)``, the linearisation
    ``A = ∂f/∂x``, ``B = ∂f/∂u`` at ``(0, u_eq)``, and batched evaluators.

    Examples
    --------
    >>> import casadi as ca
    >>> x = ca.SX.sym("x", 2); u = ca.SX.sym("u", 1)
    >>> sys = System("double_integrator", x, u, ca.vertcat(x[1], u),
    ...              state_box=[[-1, 1], [-1, 1]], input_box=[[-1, 1]])
    >>> sys.A.tolist(), sys.B.ravel().tolist()
    ([[0.0, 1.0], [0.0, 0.0]], [0.0, 1.0])
    """

    def __init__(
        self,
        name: str,
        x: ca.SX,
        u: ca.SX | None,
        f: ca.SX,
        *,
        state_box,
        input_box=None,
        u_eq=None,
        params: dict | None = None,
        state_names: Sequence[str] | None = None,
        input_names: Sequence[str] | None = None,
        description: str = "",
        known_state_derivatives: Sequence[int] = (),
    ):
        if not isinstance(x, ca.SX) or not x.is_column() or not x.is_valid_input():
            raise TypeError("x must be a column of casadi.SX symbols, e.g. ca.SX.sym('x', 2)")
        u = ca.SX(0, 1) if u is None else u
        if not isinstance(u, ca.SX) or not (u.is_empty() or u.is_valid_input()):
            raise TypeError("u must be a column of casadi.SX symbols or None")
        f = ca.SX(f)
        if f.shape != (x.numel(), 1):
            raise DimensionError(
                f"f must have shape ({x.numel()}, 1) to match x, got {f.shape}; "
                "build it with ca.vertcat(...)"
            )
        fun = ca.Function(name, [x, u], [f], ["x", "u"], ["f"])
        if fun.has_free():
            raise ValueError(
                f"f depends on symbols other than x and u: {fun.get_free()}; "
                "substitute parameter values before building the System"
            )
        self.name = name
        self.x, self.u, self.f = x, u, f
        self.nx, self.nu = x.numel(), u.numel()
        self.state_box = _box(state_box, self.nx, "state_box")
        self.input_box = _box(input_box, self.nu, "input_box") if self.nu else np.zeros((0, 2))
        if self.nu and input_box is None:
            raise ValueError(f"system {name!r} has inputs: give input_box (nu={self.nu})")
        self.params = dict(params or {})
        self.state_names = list(state_names or [f"x{i + 1}" for i in range(self.nx)])
        self.input_names = list(input_names or [f"u{i + 1}" for i in range(self.nu)])
        if len(self.state_names) != self.nx or len(self.input_names) != self.nu:
            raise DimensionError("state_names/input_names must have nx/nu entries")
        self.description = description
        self.known_state_derivatives = tuple(int(i) for i in known_state_derivatives)
        self.f_fun = fun
        self.u_eq = self._equilibrium_input(u_eq)
        jac = ca.Function("jac_" + name, [x, u], [ca.jacobian(f, x), ca.jacobian(f, u)])
        A, B = jac(np.zeros(self.nx), self.u_eq)
        self.A = np.array(A, dtype=float).reshape(self.nx, self.nx)
        self.B = np.array(B, dtype=float).reshape(self.nx, self.nu)
        self._program = compile_function(fun)
        self._torch = None

    # ------------------------------------------------------------------ derived
    def _equilibrium_input(self, u_eq) -> np.ndarray:
        zero = np.zeros(self.nx)
        if u_eq is None and self.nu:  # solve f(0, u) = 0 in the least-squares sense
            from scipy.optimize import least_squares

            u = ca.SX.sym("u", self.nu)
            r = self.f_fun(zero, u)
            res = ca.Function("r", [u], [r, ca.jacobian(r, u)])
            sol = least_squares(
                lambda v: np.array(res(v)[0], dtype=float).ravel(), np.zeros(self.nu),
                jac=lambda v: np.array(res(v)[1], dtype=float).reshape(self.nx, self.nu),
                xtol=1e-15, ftol=1e-15, gtol=1e-15,
            )
            u_eq = sol.x
        u_eq = np.zeros(0) if not self.nu else np.asarray(u_eq, dtype=float).reshape(self.nu)
        resid = np.array(self.f_fun(zero, u_eq), dtype=float).ravel()
        if np.max(np.abs(resid), initial=0.0) > 1e-9:
            raise EquilibriumError(
                f"the origin is not an equilibrium of {self.name!r}: f(0, u_eq={u_eq}) = {resid}; "
                "shift the state so that the equilibrium is at x = 0"
            )
        return u_eq

    def evaluate(self, x, u=None) -> np.ndarray:
        """Evaluate ``f`` on a batch, float64.

        Parameters
        ----------
        x : (N, nx) array_like
        u : (N, nu) array_like, optional
            Defaults to ``u_eq`` for every sample.

        Returns
        -------
        (N, nx) ndarray
        """
        x = np.asarray(x, dtype=float)
        if x.ndim != 2 or x.shape[1] != self.nx:
            raise DimensionError(f"x must have shape (N, {self.nx}), got {x.shape}")
        if u is None:
            u = np.broadcast_to(self.u_eq, (x.shape[0], self.nu))
        u = np.asarray(u, dtype=float)
        if u.ndim != 2 or u.shape != (x.shape[0], self.nu):
            raise DimensionError(f"u must have shape ({x.shape[0]}, {self.nu}), got {u.shape}")
        return evaluate(self._program, [x, u])[0]

    def evaluate_torch(self, x, u=None):
        """Evaluate ``f`` on torch tensors ``(N, nx)``, ``(N, nu)`` (differentiable)."""
        if self._torch is None:
            self._torch = ArrayArithmetic("torch")
        if u is None:
            import torch

            u = torch.as_tensor(self.u_eq, dtype=x.dtype).expand(x.shape[0], self.nu)
        return evaluate(self._program, [x, u], self._torch)[0]

    def closed_loop(self, feedback: Callable[[ca.SX], ca.SX] | None = None) -> ca.Function:
        """CasADi Function ``x -> f(x, κ(x))`` for a symbolic feedback ``κ`` (SX -> SX)."""
        u = ca.DM(self.u_eq) if feedback is None else feedback(self.x)
        return ca.Function(f"{self.name}_cl", [self.x], [self.f_fun(self.x, u)])

    def simulate(
        self,
        feedback: Callable[[np.ndarray], np.ndarray] | None,
        x0,
        t_final: float,
        *,
        n_steps: int = 2000,
        method: str = "rk4",
    ) -> np.ndarray:
        """Simulate the closed loop from many initial states at once (fixed-step RK4).

        Parameters
        ----------
        feedback : callable or None
            Batched numpy feedback ``(N, nx) -> (N, nu)``; ``None`` applies ``u_eq``.
        x0 : (N, nx) array_like
        t_final : float
        n_steps : int

        Returns
        -------
        (n_steps + 1, N, nx) ndarray
            The trajectories (non-finite once a trajectory blows up).
        """
        if method != "rk4":
            raise ValueError(f"method must be 'rk4', got {method!r}")
        x = np.array(x0, dtype=float, ndmin=2)
        dt = t_final / n_steps

        def rhs(z):
            u = None if feedback is None else np.asarray(feedback(z), dtype=float)
            with np.errstate(all="ignore"):
                return self.evaluate(z, u)

        from nlyap_opt.simulate import rk4_step

        out = np.empty((n_steps + 1,) + x.shape)
        out[0] = x
        with np.errstate(all="ignore"):
            for k in range(n_steps):
                x = rk4_step(rhs, x, dt)
                x[~np.isfinite(x).all(axis=1)] = np.nan
                out[k + 1] = x
        return out

    def __repr__(self) -> str:
        return f"System({self.name!r}, nx={self.nx}, nu={self.nu})"
