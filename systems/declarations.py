r"""Assumptions a user declares about an unknown ``f``, and their check against samples.

An unknown system is only sampled, so what the certificate needs beyond the samples is
*declared*: a Lipschitz constant :math:`K_f` (the paper's setting), optionally a bound on the
second derivatives (the second-order error model, condition (c) from samples), and
optionally control-affine structure with a known input matrix ``B``. The certificate lists
each :meth:`Declarations.describe` line verbatim under "Assumptions (declared by the user)".

Declarations are never trusted blindly where data can refute them:
:func:`check_declarations` refuses

- a declared :math:`K_f` below the largest finite-difference slope
  :math:`\|f(z_a) - f(z_b)\|_2 / \|z_a - z_b\|_2` between neighbouring grid nodes (every such
  slope is a lower bound of any Lipschitz constant);
- a declared :math:`H` below the largest second difference
  :math:`|f(z + h e_i) - 2 f(z) + f(z - h e_i)| / h^2` or mixed difference over a grid cell
  (each equals a second derivative of a :math:`C^2` function at some point, or its mean
  over the cell);
- a declared ``B`` with :math:`f(x, u_1) - f(x, u_2) \ne B (u_1 - u_2)` between neighbours
  along an input axis;
- a declared dependency (``depends_on``) where ``f_k`` changes between neighbours along a
  variable it is declared not to depend on.

Each sample value is taken as exact to within an absolute ``value_tolerance`` (default: 8
units in the last place of the largest :math:`|f|`, i.e. float64 rounding of the data); the
estimates are lowered by the error this allows (:math:`2\tau/h` for a slope,
:math:`4\tau/h^2` for a second difference) and a declaration is refused only when the
lowered estimate still exceeds it by more than a relative ``1e-6``. A check can only
refute: passing it does not prove a declaration (a Lipschitz constant is a statement about
every pair of points, the grid sees finitely many).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from nlyap_opt.kernel.errors import ConfigError, DimensionError
from nlyap_opt.kernel.rounding import EPS, next_up

__all__ = ["Declarations", "check_declarations", "probe_declarations", "RTOL"]

#: relative slack before a declaration counts as contradicted by an estimate from the data
RTOL = 1e-6


def _fmt(v) -> str:
    return f"{float(v):.6g}"


def _fmt_vec(v) -> str:
    return "(" + ", ".join(_fmt(a) for a in np.ravel(v)) + ")"


def _numbers_only(name: str, v) -> None:
    """Refuse booleans and text inside a declared value (``float()`` reads ``true`` as 1
    and ``"34.5"`` as 34.5: as for boxes, a declaration is written as numbers)."""
    if isinstance(v, np.ndarray):
        ok = v.dtype.kind in "iuf"
    elif isinstance(v, (list, tuple)):
        for a in v:
            _numbers_only(name, a)
        return
    else:
        ok = isinstance(v, (int, float, np.integer, np.floating)) and \
            not isinstance(v, (bool, np.bool_))
    if not ok:
        raise ConfigError(f"declared {name} must be written as numbers (not strings or "
                          f"booleans), got {v!r}")


def _nonnegative(name: str, v) -> float:
    _numbers_only(name, v)
    try:
        v = float(v)
    except (TypeError, ValueError):
        raise ConfigError(f"declared {name} must be a number, got {v!r}") from None
    if not np.isfinite(v) or v < 0:
        raise ConfigError(f"declared {name} must be a finite number >= 0, got {v}")
    return v


def _positive(name: str, v) -> float:
    _numbers_only(name, v)
    try:
        v = float(v)
    except (TypeError, ValueError):
        raise ConfigError(f"declared {name} must be a number, got {v!r}") from None
    if not np.isfinite(v) or v <= 0:
        raise ConfigError(f"declared {name} must be a finite positive number, got {v}")
    return v


@dataclass(frozen=True)
class Declarations:
    r"""Assumptions about ``f`` declared by the user (none is computed from data).

    Parameters
    ----------
    lipschitz : float or sequence of float, optional
        :math:`K_f`: either one constant with
        :math:`\|f(z_a) - f(z_b)\|_2 \le K_f \|z_a - z_b\|_2`, or one per state derivative
        ``k`` with :math:`|f_k(z_a) - f_k(z_b)| \le K_k \|z_a - z_b\|_2`, for all
        :math:`z = (x, u)` in the sampling box :math:`X \times U`.
    hessian : float or sequence of float, optional
        :math:`H`: ``f`` is :math:`C^2` on :math:`X \times U` with
        :math:`|\partial^2 f_k / \partial z_i \partial z_j| \le H` for all ``k, i, j``; or
        one bound per state derivative ``k`` (``H_k ≥ 0``, 0 for a linear component) with
        :math:`|\partial^2 f_k / \partial z_i \partial z_j| \le H_k`.
    input_matrix : (nx, nu) array_like, optional
        Known ``B`` of a control-affine ``f(x, u) = f_0(x) + B u``.
    sample_error : float, optional
        :math:`\varepsilon`: every sample value (or callable output) ``s`` is within
        :math:`\|s - f(z)\|_2 \le \varepsilon` of the true ``f`` (noise, a simulator's
        tolerance); add it to α. Not declared: the data are taken as exact.
    depends_on : mapping, optional
        ``{state: [variables]}``: the state derivative ``f_k`` (a state name or index) depends
        on the listed variables of ``z = (x, u)`` only (names, or indices with the states
        first), i.e. :math:`\partial f_k / \partial z_i \equiv 0` on :math:`X \times U` for
        every other ``z_i``; states not listed may depend on everything. φ's block for
        ``f_k`` then reads only those variables (dynamics config ``inputs: model``), and
        the second-order error bound drops ``H`` on the other axes, where ``f_k − φ_k`` is
        constant: a 4-D grid needs no fine spacing along a variable ``f_k`` ignores.

    Examples
    --------
    >>> d = Declarations(lipschitz=[1.0, 20.0], hessian=40.0)
    >>> round(d.lipschitz_bound(), 6)
    20.024984
    >>> d.describe(state_names=["theta", "omega"])[0][:30]
    'Lipschitz constant per compone'
    """

    lipschitz: float | tuple[float, ...] | None = None
    hessian: float | tuple[float, ...] | None = None
    input_matrix: tuple[tuple[float, ...], ...] | None = None
    sample_error: float | None = None
    depends_on: tuple[tuple[int | str, tuple[int | str, ...]], ...] | None = None
    source: str = field(default="", compare=False)

    def __post_init__(self):
        lip = self.lipschitz
        if lip is not None:
            if np.ndim(lip) == 0:
                lip = _positive("lipschitz (K_f)", lip)
            else:
                if np.ndim(lip) != 1 or len(lip) == 0:
                    raise ConfigError(
                        "declared lipschitz must be a number or a list with one number per "
                        f"state, got {lip!r}"
                    )
                lip = tuple(_positive("lipschitz (K_f) entry", v) for v in lip)
            object.__setattr__(self, "lipschitz", lip)
        if self.hessian is not None:
            h = self.hessian
            if np.ndim(h) == 0:
                h = _positive("hessian (H)", h)
            else:
                if np.ndim(h) != 1 or len(h) == 0:
                    raise ConfigError("declared hessian must be a number or a list with one "
                                      f"number per state, got {h!r}")
                h = tuple(_nonnegative("hessian (H) entry", v) for v in h)
            object.__setattr__(self, "hessian", h)
        if self.sample_error is not None:
            e = self.sample_error
            if isinstance(e, bool) or not isinstance(e, (int, float)) or not np.isfinite(e) \
                    or e < 0:
                raise ConfigError(f"declared sample_error must be a finite number >= 0, got {e!r}")
            object.__setattr__(self, "sample_error", float(e))
        if self.input_matrix is not None:
            _numbers_only("input_matrix", self.input_matrix)
            try:
                b = np.array(self.input_matrix, dtype=float)
            except (TypeError, ValueError):
                raise ConfigError(
                    f"declared input_matrix must be a list of rows of numbers, got "
                    f"{self.input_matrix!r}"
                ) from None
            if b.ndim != 2 or not np.all(np.isfinite(b)):
                raise ConfigError(
                    f"declared input_matrix must be a finite (nx, nu) matrix, got shape {b.shape}"
                )
            object.__setattr__(self, "input_matrix", tuple(tuple(r) for r in b.tolist()))
        if self.depends_on is not None:
            object.__setattr__(self, "depends_on", _dependency_pairs(self.depends_on))

    # ------------------------------------------------------------------ queries
    @property
    def empty(self) -> bool:
        """True when nothing is declared."""
        return (self.lipschitz is None and self.hessian is None and self.input_matrix is None
                and self.sample_error is None and self.depends_on is None)

    def hessian_of(self, k: int) -> float | None:
        """The declared bound on the second derivatives of ``f_k`` (``None``: not declared)."""
        h = self.hessian
        return h[k] if isinstance(h, tuple) else h

    def hessian_max(self) -> float | None:
        """The declared bound on every second derivative of ``f`` (the largest per-state one)."""
        h = self.hessian
        return max(h) if isinstance(h, tuple) else h

    @property
    def B(self) -> np.ndarray | None:
        """The declared input matrix as an ``(nx, nu)`` array (``None`` if not declared)."""
        return None if self.input_matrix is None else np.array(self.input_matrix, dtype=float)

    def validate(self, nx: int, nu: int) -> Declarations:
        """Check the shapes against a system with ``nx`` states and ``nu`` inputs."""
        if isinstance(self.lipschitz, tuple) and len(self.lipschitz) != nx:
            raise ConfigError(
                f"declared lipschitz has {len(self.lipschitz)} entries; give one number, or one "
                f"per state ({nx})"
            )
        if isinstance(self.hessian, tuple) and len(self.hessian) != nx:
            raise ConfigError(
                f"declared hessian has {len(self.hessian)} entries; give one number, or one "
                f"per state ({nx})"
            )
        if self.depends_on is not None:
            self.dependencies([f"x{i + 1}" for i in range(nx)], [f"u{j + 1}" for j in range(nu)],
                              names_given=False)
        if self.input_matrix is not None:
            shape = self.B.shape
            if nu == 0:
                raise ConfigError("declared input_matrix for a system without inputs; remove it")
            if shape != (nx, nu):
                raise ConfigError(
                    f"declared input_matrix has shape {shape}; the system needs ({nx}, {nu}) "
                    "(one row per state, one column per input)"
                )
        return self

    def dependencies(self, state_names: Sequence[str], input_names: Sequence[str] = (), *,
                     names_given: bool = True) -> dict[int, tuple[int, ...]]:
        """The declared ``depends_on`` as ``{k: columns of z = (x, u)}`` (sorted indices).

        Raises
        ------
        ConfigError
            A state or variable that the system does not have (by name, or an index out of
            range), or a state listed twice.
        """
        if self.depends_on is None:
            return {}
        xs, us = list(state_names), list(input_names)
        zs = xs + us

        def index(v, among, what):
            if isinstance(v, str):
                if v in among:
                    return among.index(v)
                if not names_given:  # names are checked once the system's are known
                    return None
                raise ConfigError(f"declared depends_on names {what} {v!r}; the system has "
                                  f"{', '.join(among) or 'none'}")
            if not 0 <= v < len(among):
                raise ConfigError(f"declared depends_on: {what} index {v} is out of range "
                                  f"0..{len(among) - 1}")
            return v

        out: dict[int, tuple[int, ...]] = {}
        for key, cols in self.depends_on:
            k = index(key, xs, "state")
            if k is None:
                continue
            if k in out:
                raise ConfigError(f"declared depends_on lists state {xs[k]!r} twice; give it "
                                  "once")
            idx = [index(c, zs, "variable") for c in cols]
            out[k] = tuple(sorted({i for i in idx if i is not None}))
        return out

    def lipschitz_bound(self, components: Sequence[int] | None = None) -> float | None:
        r"""A global :math:`K_f` for the components ``components`` (default: all).

        Per-component constants give :math:`\|f(z_a) - f(z_b)\|_2 \le \|(K_k)_k\|_2
        \|z_a - z_b\|_2` (rounded up); a global constant bounds every sub-vector too.
        """
        if self.lipschitz is None:
            return None
        if not isinstance(self.lipschitz, tuple):
            return self.lipschitz
        k = np.array(self.lipschitz, dtype=float)
        if components is not None:
            k = k[list(components)]
        s = float(np.sum(k * k)) * (1.0 + 4.0 * (k.size + 2) * EPS)
        return next_up(np.sqrt(s), 2)

    def describe(self, state_names: Sequence[str] | None = None,
                 input_names: Sequence[str] | None = None) -> list[str]:
        """One sentence per declaration, as the certificate and the report list them."""
        out: list[str] = []
        dom = "for all z = (x, u) in the sampling box X × U"

        def per_state(values) -> str:     # "x1': 1, x2': 2"
            names = list(state_names or [f"x{i + 1}" for i in range(len(values))])
            return ", ".join(f"{n}': {_fmt(v)}" for n, v in zip(names, values))

        if self.lipschitz is not None:
            if isinstance(self.lipschitz, tuple):
                out.append(
                    "Lipschitz constant per component (declared): |f_k(z_a) − f_k(z_b)| ≤ K_k·"
                    f"‖z_a − z_b‖₂ {dom}, with K = {per_state(self.lipschitz)}"
                )
            else:
                out.append(
                    f"Lipschitz constant (declared): ‖f(z_a) − f(z_b)‖₂ ≤ K_f·‖z_a − z_b‖₂ {dom},"
                    f" with K_f = {_fmt(self.lipschitz)}"
                )
        if isinstance(self.hessian, tuple):
            out.append(
                "Second-derivative bound per component (declared): f is twice continuously "
                "differentiable on X × U with |∂²f_k/∂z_i∂z_j| ≤ H_k for all i, j, with H = "
                + per_state(self.hessian)
            )
        elif self.hessian is not None:
            out.append(
                "Second-derivative bound (declared): f is twice continuously differentiable on "
                f"X × U with |∂²f_k/∂z_i∂z_j| ≤ H = {_fmt(self.hessian)} for all k, i, j"
            )
        if self.input_matrix is not None:
            rows = "; ".join(", ".join(_fmt(v) for v in r) for r in self.input_matrix)
            inputs = ", ".join(input_names) if input_names else "u"
            out.append(
                "Control-affine structure (declared): f(x, u) = f₀(x) + B·u on X × U with the "
                f"known input matrix B = [{rows}] (inputs: {inputs})"
            )
        if self.sample_error is not None:
            out.append(
                "Sample error (declared): every sample value s of f at a node z satisfies "
                f"‖s − f(z)‖₂ ≤ ε = {_fmt(self.sample_error)}"
            )
        if self.depends_on is not None:
            xs = list(state_names or [])
            us = list(input_names or [])
            if len(xs) and all(isinstance(k, str) or k < len(xs) for k, _ in self.depends_on):
                deps = self.dependencies(xs, us, names_given=False)
                zs = xs + us
                parts = [f"{xs[k]}' depends on ({', '.join(zs[i] for i in cols)}) only"
                         for k, cols in sorted(deps.items())]
            else:
                parts = [f"f_{k} depends on {list(c)} only" for k, c in self.depends_on]
            out.append("Dependency structure (declared): " + "; ".join(parts) + " on X × U "
                       "(∂f_k/∂z_i ≡ 0 for every other variable z_i)")
        return out

    def to_dict(self) -> dict:
        """Plain-JSON form (``None`` entries kept)."""
        lip = list(self.lipschitz) if isinstance(self.lipschitz, tuple) else self.lipschitz
        hes = list(self.hessian) if isinstance(self.hessian, tuple) else self.hessian
        return {"lipschitz": lip, "hessian": hes,
                "input_matrix": None if self.B is None else self.B.tolist(),
                "sample_error": self.sample_error,
                "depends_on": None if self.depends_on is None
                else {str(k): list(c) for k, c in self.depends_on}}


def _dependency_pairs(dep) -> tuple:
    """``depends_on`` as sorted ``((state, (variables...)), ...)`` of names or indices."""
    if not isinstance(dep, dict) or not dep:
        raise ConfigError("declared depends_on must be a table {state: [variables]} (names or "
                          f"indices), got {dep!r}")

    def key(v, what):
        if isinstance(v, str) and v:
            return v
        if isinstance(v, (int, np.integer)) and not isinstance(v, bool) and v >= 0:
            return int(v)
        raise ConfigError(f"declared depends_on: a {what} must be a name or an index >= 0, "
                          f"got {v!r}")

    out = []
    for k, cols in dep.items():
        if isinstance(cols, (str, bytes)) or not isinstance(cols, (list, tuple)):
            raise ConfigError(f"declared depends_on[{k!r}] must be a list of variables, got "
                              f"{cols!r}")
        out.append((key(k, "state"), tuple(key(c, "variable") for c in cols)))
    return tuple(sorted(out, key=lambda p: (isinstance(p[0], str), str(p[0]))))


# ============================================================================ checks
def _z_names(names, d: int) -> list[str]:
    names = list(names or [])
    return names if len(names) == d else [f"z{i + 1}" for i in range(d)]


def _node(axes, idx) -> str:
    return _fmt_vec([ax[i] for ax, i in zip(axes, idx)])


def check_declarations(
    grid,
    values,
    declarations: Declarations,
    *,
    names: Sequence[str] | None = None,
    value_tolerance: float | None = None,
    source: str = "",
) -> dict:
    r"""Refuse declarations that the samples on a regular grid contradict.

    Parameters
    ----------
    grid : Grid or SampleSet
        Anything with ``axes`` (list of the ``d`` per-axis node coordinates, increasing)
        and ``counts``; the nodes in C order. The axes are ``(x, u)``: ``d = nx + nu``
        (``nu = 0``: a grid over ``x`` only, as for control-affine data, where a declared
        ``B`` is not checked). A :class:`nlyap_opt.learned.dynamics.Grid` and a
        :class:`~systems.samples.SampleSet` qualify.
    values : (N, nx) array_like
        ``f`` at the nodes, in the grid's C order.
    declarations : Declarations
    names : sequence of str, optional
        Names of the ``d`` axes (states then inputs), for the messages.
    value_tolerance : float, optional
        Absolute error allowed in each value (default: 8 ulps of ``max |values|`` plus a
        declared ``sample_error``).
    source : str, optional
        Prefix of the messages (e.g. the spec file).

    Returns
    -------
    dict
        The estimates from the data: ``slope`` (largest neighbour slope, 2-norm over the
        components), ``slope_per_component``, ``second_difference`` (largest, ``None`` on a
        grid with fewer than 3 nodes on every axis), ``input_matrix_error`` (largest
        :math:`|Δf − BΔu|`, if ``B`` was declared).

    Raises
    ------
    ConfigError
        A declaration is below (``K_f``, ``H``) or away from (``B``) what the data show.
    """
    axes = [np.asarray(a, dtype=float) for a in grid.axes]
    counts = tuple(int(c) for c in grid.counts)
    d = len(axes)
    v = np.asarray(values, dtype=float)
    if v.ndim != 2 or v.shape[0] != int(np.prod(counts)):
        raise DimensionError(
            f"values must have shape (N, nx) with N = {int(np.prod(counts))} grid nodes, "
            f"got {v.shape}"
        )
    nx = v.shape[1]
    nu = d - nx
    if nu < 0:
        raise DimensionError(f"the grid has {d} axes but the values have {nx} components")
    if not np.all(np.isfinite(v)):
        raise ConfigError("the sample values contain NaN or inf; fix the data before checking")
    if nu or declarations.input_matrix is None:
        declarations.validate(nx, nu)
    else:  # a grid over x only (control-affine data): B cannot be checked here
        Declarations(declarations.lipschitz).validate(nx, 0)
    znames = _z_names(names, d)
    pre = f"{source}: " if source else ""
    scale = float(np.max(np.abs(v), initial=0.0))
    if value_tolerance is None:  # float64 rounding of the data, plus declared noise
        value_tolerance = 8.0 * EPS * scale + (declarations.sample_error or 0.0)
    tau = float(value_tolerance)
    V = v.reshape(counts + (nx,))
    out: dict = {"slope": 0.0, "slope_per_component": [0.0] * nx, "second_difference": None,
                 "input_matrix_error": None}

    # ---- first differences: Lipschitz lower bounds (slack for the data's rounding)
    best = (0.0, None)
    best_k = np.zeros(nx)
    best_k_at: list = [None] * nx
    for i in range(d):
        if counts[i] < 2:
            continue
        shape = [1] * d
        shape[i] = counts[i] - 1
        gap = np.diff(axes[i]).reshape(shape + [1])
        dv = np.diff(V, axis=i)
        allow = 2.0 * tau  # absolute error of a difference of two values
        slope = np.maximum(np.sqrt(np.sum(dv * dv, axis=-1, keepdims=True)) - np.sqrt(nx) * allow,
                           0.0) / gap
        slope_k = np.maximum(np.abs(dv) - allow, 0.0) / gap
        j = int(np.argmax(slope))
        if slope.flat[j] > best[0]:
            idx = np.unravel_index(j, slope.shape[:-1])
            best = (float(slope.flat[j]), (i, idx))
        flat = slope_k.reshape(-1, nx)
        jk = np.argmax(flat, axis=0)
        for k in range(nx):
            if flat[jk[k], k] > best_k[k]:
                best_k[k] = flat[jk[k], k]
                best_k_at[k] = (i, np.unravel_index(int(jk[k]), slope_k.shape[:-1]))
    out["slope"], out["slope_per_component"] = best[0], best_k.tolist()
    lip = declarations.lipschitz
    if lip is not None and not isinstance(lip, tuple) and best[0] > lip * (1 + RTOL):
        i, idx = best[1]
        raise ConfigError(
            f"{pre}declared K_f = {_fmt(lip)} is below the finite-difference slope "
            f"{_fmt(best[0])} between the neighbouring grid samples at z = {_node(axes, idx)} "
            f"and the next node along {znames[i]!r}; declare K_f ≥ {_fmt(best[0])} (any "
            "Lipschitz constant is at least every slope) or check the data's units"
        )
    if isinstance(lip, tuple):
        for k in range(nx):
            if best_k[k] > lip[k] * (1 + RTOL):
                i, idx = best_k_at[k]
                raise ConfigError(
                    f"{pre}declared K_f for component {k} ({znames[k]}') = {_fmt(lip[k])} is "
                    f"below the finite-difference slope {_fmt(best_k[k])} between the "
                    f"neighbouring grid samples at z = {_node(axes, idx)} and the next node "
                    f"along {znames[i]!r}; declare at least {_fmt(best_k[k])}"
                )

    # ---- second differences: lower bounds of max |∂²f_k/∂z_i∂z_j|
    best2 = (0.0, None)
    any2 = False
    Hd = declarations.hessian
    # the declared bound of each component (the last axis of V), and the worst excess over it
    Hk = None if Hd is None else np.broadcast_to(np.asarray(Hd, dtype=float), V.shape[-1:])
    worst = (0.0, None, 0.0)
    for i in range(d):
        for j in range(i, d):
            if i == j:
                if counts[i] < 3:
                    continue
                sl = [slice(None)] * d
                a, b, c = list(sl), list(sl), list(sl)
                a[i], b[i], c[i] = slice(2, None), slice(1, -1), slice(0, -2)
                h1 = np.diff(axes[i])
                shape = [1] * d
                shape[i] = counts[i] - 2
                hl, hr = h1[:-1].reshape(shape + [1]), h1[1:].reshape(shape + [1])
                # divided difference: f[z-, z, z+] * 2 = f''(ξ) for a C² function
                dd = 2.0 * ((V[tuple(a)] - V[tuple(b)]) / hr - (V[tuple(b)] - V[tuple(c)]) / hl)
                dd = dd / (hl + hr)
                allow = 4.0 * tau / (hl * hr)
            else:
                if counts[i] < 2 or counts[j] < 2:
                    continue
                sl = [slice(None)] * d
                pp, pm, mp, mm = list(sl), list(sl), list(sl), list(sl)
                pp[i], pp[j] = slice(1, None), slice(1, None)
                pm[i], pm[j] = slice(1, None), slice(0, -1)
                mp[i], mp[j] = slice(0, -1), slice(1, None)
                mm[i], mm[j] = slice(0, -1), slice(0, -1)
                si, sj = [1] * d, [1] * d
                si[i], sj[j] = counts[i] - 1, counts[j] - 1
                hi_ = np.diff(axes[i]).reshape(si + [1])
                hj_ = np.diff(axes[j]).reshape(sj + [1])
                # (f(++) − f(+−) − f(−+) + f(−−)) / (h_i h_j): the mean of ∂²f/∂z_i∂z_j on the cell
                dd = (V[tuple(pp)] - V[tuple(pm)] - V[tuple(mp)] + V[tuple(mm)]) / (hi_ * hj_)
                allow = 4.0 * tau / (hi_ * hj_)
            any2 = True
            est = np.maximum(np.abs(dd) - allow, 0.0)
            m = int(np.argmax(est))
            if est.flat[m] > best2[0]:
                idx = np.unravel_index(m, est.shape)
                best2 = (float(est.flat[m]), (i, j, idx[-1], idx[:-1]))
            if Hk is not None:
                exc = est - Hk * (1 + RTOL)
                m = int(np.argmax(exc))
                if exc.flat[m] > worst[0]:
                    idx = np.unravel_index(m, exc.shape)
                    worst = (float(exc.flat[m]), (i, j, idx[-1], idx[:-1]), float(est.flat[m]))
    out["second_difference"] = best2[0] if any2 else None
    if worst[1] is not None:
        i, j, k, idx = worst[1]
        base = [ax[t] for ax, t in zip(axes, idx)]
        raise ConfigError(
            f"{pre}declared H = {_fmt(float(Hk[k]))} is below the second-difference estimate "
            f"{_fmt(worst[2])} of |∂²f_{k}/∂{znames[i]}∂{znames[j]}| near z = {_fmt_vec(base)}; "
            f"declare H ≥ {_fmt(worst[2])} (a second difference equals a second derivative "
            "somewhere in its stencil) or check the data"
        )

    # ---- declared dependency: f_k does not change along a variable it ignores
    names_d = list(names or [])
    if declarations.depends_on is not None and len(names_d) == d:
        # an x-grid of control-affine data has no input axes: inputs are not checked here
        deps = declarations.dependencies(names_d[:nx], names_d[nx:], names_given=nu > 0)
        out["dependency_error"] = 0.0
        for k, cols in deps.items():
            for i in range(d):
                if i in cols or counts[i] < 2:
                    continue
                dv = np.abs(np.diff(V[..., k], axis=i))
                m = int(np.argmax(dv))
                worst = float(dv.flat[m])
                out["dependency_error"] = max(out["dependency_error"], worst)
                if worst > 2.0 * tau:
                    idx = np.unravel_index(m, dv.shape)
                    raise ConfigError(
                        f"{pre}declared depends_on is contradicted by the samples: "
                        f"{znames[k]}' changes by {_fmt(worst)} between z = {_node(axes, idx)} "
                        f"and the next node along {znames[i]!r}, which it is declared not to "
                        f"depend on; add {znames[i]!r} to its variables or drop the entry")

    # ---- declared B: f(x, u + h e_j) − f(x, u) = B[:, j] h between input neighbours
    B = declarations.B
    if B is not None and any(counts[nx + j] > 1 for j in range(nu)):
        worst = (0.0, None)
        for j in range(nu):
            i = nx + j
            if counts[i] < 2:  # a single input level says nothing about B
                continue
            shape = [1] * d
            shape[i] = counts[i] - 1
            gap = np.diff(axes[i]).reshape(shape + [1])
            err = np.abs(np.diff(V, axis=i) - B[:, j] * gap)
            allow = 2.0 * tau + RTOL * (scale + np.abs(B[:, j]) * gap)
            bad = np.maximum(err - allow, 0.0)
            m = int(np.argmax(bad))
            if bad.flat[m] > worst[0]:
                idx = np.unravel_index(m, bad.shape)
                worst = (float(err.flat[m]), (i, j, idx[-1], idx[:-1]))
        out["input_matrix_error"] = worst[0]
        if worst[1] is not None:
            i, j, k, idx = worst[1]
            hgap = axes[i][idx[i] + 1] - axes[i][idx[i]]
            nxt = list(idx)
            nxt[i] += 1
            change = V[tuple(nxt) + (k,)] - V[tuple(idx) + (k,)]
            raise ConfigError(
                f"{pre}declared input matrix B is contradicted by the samples: at z = "
                f"{_node(axes, idx)} a step {_fmt(hgap)} in {znames[i]!r} changes f_{k} by "
                f"{_fmt(change)}, but B[{k}, {j}]·step = {_fmt(B[k, j] * hgap)}; the system is "
                "not control-affine with this B: fix B or drop input_matrix"
            )
    return out


# ============================================================================ off-grid probes
def probe_declarations(
    f,
    box,
    declarations: Declarations,
    *,
    nx: int,
    points: int,
    seed: int = 0,
    spacing=None,
    names: Sequence[str] | None = None,
    source: str = "",
) -> dict:
    r"""Refute declarations with evaluations of a callable ``f`` *between* grid nodes.

    A grid check (:func:`check_declarations`) sees ``f`` at the nodes only: a narrow spike
    between two nodes passes it. A callable can be evaluated anywhere, so this draws
    ``points // 3`` seeded random stencils ``(z - s e_i, z, z + s e_i)`` in ``box`` (a
    random axis ``i`` and a step ``s`` between 5 % and 50 % of the grid spacing along it)
    and checks, per stencil:

    - ``K_f``: :math:`\|f(z_b) - f(z_a)\| / s \le K_f` for both neighbouring pairs (per
      component when ``K_f`` is one number per state);
    - ``H``: :math:`|f_k(z+s e_i) - 2 f_k(z) + f_k(z-s e_i)| / s^2 \le H` (it equals
      :math:`\partial^2 f_k/\partial z_i^2` somewhere in the stencil);
    - ``depends_on``: ``f_k`` does not change along an axis it is declared not to read;
    - ``B`` (an input axis ``i = nx + j``): :math:`f(z + s e_i) - f(z) = B_{:,j} s`.

    The same slack as on the grid (8 ulps of the largest value plus a declared
    ``sample_error`` per value, relative ``RTOL`` on the constants). Deterministic: the
    points depend on ``seed`` and ``points`` only.

    Parameters
    ----------
    f : callable
        Batched ``f(x, u) -> (N, nx)`` with ``x`` ``(N, nx)`` and ``u`` ``(N, nu)``.
    box : (d, 2) array_like
        The box ``X × U`` (``d = nx + nu``) the declarations are made on.
    declarations : Declarations
    nx : int
    points : int
        Evaluation budget (``0``: no probe).
    seed : int
    spacing : (d,) array_like, optional
        Grid spacing per axis (default: a tenth of the box).
    names : sequence of str, optional
        The ``d`` axis names (states then inputs), for messages and ``depends_on``.
    source : str, optional
        Prefix of the messages.

    Returns
    -------
    dict
        ``points`` (evaluations made), ``slope``, ``second_difference`` (largest estimates).

    Raises
    ------
    ConfigError
        A declaration that an off-grid pair or stencil contradicts (both points and the
        declared constant in the message), or a non-finite value of ``f``.
    """
    box = np.asarray(box, dtype=float)
    d = box.shape[0]
    nu = d - nx
    m = int(points) // 3
    out = {"points": 3 * m, "slope": 0.0, "second_difference": 0.0}
    if m == 0 or declarations.empty:
        return out
    width = box[:, 1] - box[:, 0]
    h = width / 10.0 if spacing is None else np.asarray(spacing, dtype=float)
    h = np.where((h > 0) & np.isfinite(h), np.minimum(h, width), width)
    rng = np.random.default_rng([int(seed), 0x9E3779B9])  # no wall clock: seed only
    axis = rng.integers(d, size=m)
    s = h[axis] * rng.uniform(0.05, 0.5, size=m)
    z = box[:, 0] + width * rng.random((m, d))
    rows = np.arange(m)
    lo, hi = box[axis, 0] + s, box[axis, 1] - s
    z[rows, axis] = np.clip(z[rows, axis], np.minimum(lo, hi), np.maximum(lo, hi))
    zm, zp = z.copy(), z.copy()
    zm[rows, axis] -= s
    zp[rows, axis] += s
    Z = np.vstack([zm, z, zp])
    with np.errstate(all="ignore"):
        V = np.asarray(f(Z[:, :nx], Z[:, nx:]), dtype=float).reshape(3 * m, nx)
    znames = _z_names(names, d)
    pre = f"{source}: " if source else ""
    bad = ~np.all(np.isfinite(V), axis=1)
    if bad.any():
        r = int(np.flatnonzero(bad)[0])
        raise ConfigError(f"{pre}the callable returned {V[r].tolist()} at z = {_fmt_vec(Z[r])} "
                          "(an off-grid probe inside the box); f must be finite on the whole box")
    Vm, V0, Vp = V[:m], V[m:2 * m], V[2 * m:]
    scale = float(np.max(np.abs(V), initial=0.0))
    tau = 8.0 * EPS * scale + (declarations.sample_error or 0.0)

    def refute(what: str, value: float, r: int, a, b, fix: str) -> ConfigError:
        return ConfigError(
            f"{pre}{what} is contradicted between grid nodes: {_fmt(value)} from f at z_a = "
            f"{_fmt_vec(a)} and z_b = {_fmt_vec(b)} (a step {_fmt(s[r])} along "
            f"{znames[axis[r]]!r}; off-grid probe {r + 1} of {m}, seed {seed}); {fix}")

    # ---- K_f: difference quotients of both pairs
    lip = declarations.lipschitz
    for a, b, za, zb in ((Vm, V0, zm, z), (V0, Vp, z, zp)):
        dv = b - a
        slope = np.maximum(np.linalg.norm(dv, axis=1) - np.sqrt(nx) * 2 * tau, 0.0) / s
        out["slope"] = max(out["slope"], float(slope.max()))
        if lip is not None and not isinstance(lip, tuple):
            r = int(np.argmax(slope))
            if slope[r] > lip * (1 + RTOL):
                raise refute(f"declared K_f = {_fmt(lip)}", slope[r], r, za[r], zb[r],
                             f"a difference quotient ‖Δf‖/‖Δz‖ = {_fmt(slope[r])} needs K_f ≥ "
                             "it; declare a larger K_f or check the callable")
        if isinstance(lip, tuple):
            sk = np.maximum(np.abs(dv) - 2 * tau, 0.0) / s[:, None]
            for k in range(nx):
                r = int(np.argmax(sk[:, k]))
                if sk[r, k] > lip[k] * (1 + RTOL):
                    raise refute(f"declared K_f for component {k} ({znames[k]}') = "
                                 f"{_fmt(lip[k])}", sk[r, k], r, za[r], zb[r],
                                 f"declare at least {_fmt(sk[r, k])} or check the callable")
    # ---- H: second differences along the stencil's axis
    dd = np.maximum(np.abs(Vp - 2.0 * V0 + Vm) - 4.0 * tau, 0.0) / (s * s)[:, None]
    out["second_difference"] = float(dd.max())
    if declarations.hessian is not None:
        Hk = np.broadcast_to(np.asarray(declarations.hessian, dtype=float), dd.shape[-1:])
        r, k = np.unravel_index(int(np.argmax(dd - Hk * (1 + RTOL))), dd.shape)
        H = float(Hk[k])
        if dd[r, k] > H * (1 + RTOL):
            raise refute(f"declared H = {_fmt(H)}", dd[r, k], int(r), zm[r], zp[r],
                         f"|f_{k}(z+) - 2 f_{k}(z) + f_{k}(z-)| / s² estimates "
                         f"|∂²f_{k}/∂{znames[axis[r]]}²| = {_fmt(dd[r, k])} at the midpoint "
                         f"{_fmt_vec(z[r])}; declare H ≥ it or check the callable")
    # ---- depends_on: no change along an axis f_k is declared not to read
    if declarations.depends_on is not None and names is not None and len(names) == d:
        deps = declarations.dependencies(list(names[:nx]), list(names[nx:]))
        for k, cols in deps.items():
            off = ~np.isin(axis, cols)
            for a, b, za, zb in ((Vm, V0, zm, z), (V0, Vp, z, zp)):
                ch = np.where(off, np.abs(b[:, k] - a[:, k]), 0.0)
                r = int(np.argmax(ch))
                if ch[r] > 2.0 * tau:
                    raise refute(f"declared depends_on for {znames[k]}'", ch[r], r, za[r], zb[r],
                                 f"{znames[k]}' changes along {znames[axis[r]]!r}, which it is "
                                 f"declared not to read; add {znames[axis[r]]!r} to its "
                                 "variables or drop the entry")
    # ---- B: f(z + s e_{nx+j}) - f(z) = B[:, j] s along an input axis
    B = declarations.B
    if B is not None and nu and B.shape == (nx, nu):
        inp = axis >= nx
        for a, b, za, zb in ((Vm, V0, zm, z), (V0, Vp, z, zp)):
            j = np.clip(axis - nx, 0, nu - 1)
            want = B[:, j].T * s[:, None]
            err = np.abs((b - a) - want)
            allow = 2.0 * tau + RTOL * (scale + np.abs(want))
            ex = np.where(inp[:, None], np.maximum(err - allow, 0.0), 0.0)
            r, k = np.unravel_index(int(np.argmax(ex)), ex.shape)
            if ex[r, k] > 0:
                raise refute(f"declared input matrix B[{k}, {j[r]}] = {_fmt(B[k, j[r]])}",
                             float((b - a)[r, k] / s[r]), int(r), za[r], zb[r],
                             f"Δf_{k}/Δu differs from B; the system is not control-affine with "
                             "this B: fix B or drop input_matrix")
    return out
