r"""Samples of an unknown ``f`` on a complete regular grid: files in, a grid with exact δ out.

A sample file holds rows ``(x, u, ẋ)``. :func:`load_samples` accepts it only if the
``(x, u)`` rows form a **complete regular grid** over a box: on every axis the coordinates
are ``lo + k h`` (``k = 0 … n−1``) within a relative ``1e-9`` of ``h``, every node appears
exactly once, and nothing is NaN or inf. The result, a :class:`SampleSet`, has the same nodes
as ``nlyap_opt.learned.dynamics.Grid(box, counts)`` (same ``np.linspace`` construction, both box
ends exact) and the same covering radius :math:`\delta = \tfrac12\|h\|_2` (rounded up the
same way), plus the values in the grid's C order. Where the file's coordinates are not
bitwise the nodes (a csv printed with fewer digits), the largest distance ``offset`` between
a row and its node is added to δ: the value of a row is attributed to its node, and every
point of the box is within :math:`\delta + \text{offset}` of the row whose value it gets.

File formats
------------
``.csv``
    One row per sample; columns ``<state>`` for ``x``, ``<input>`` for ``u`` and
    ``<state>_dot`` for ``ẋ``, in any order, named by a header line (or, for a file
    without a header, by the ``columns`` argument). Every row has the same number of
    fields.
``.npz``
    Arrays ``x`` ``(N, nx)``, ``u`` ``(N, nu)`` (absent or empty without inputs) and
    ``xdot`` ``(N, nx)``; loaded without pickle.

An input may have a single level ``u0`` in the whole file (a slice ``f(x, u0)``, e.g.
``u0 = 0`` for a control-affine system with a declared ``B``): that axis is then not part
of the grid (δ is over the state axes only, equal to ``Grid(box_x, counts_x).delta``).
"""

from __future__ import annotations

import csv
import difflib
import io
import unicodedata
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from nlyap_opt.kernel.errors import ConfigError, DimensionError
from nlyap_opt.kernel.grid import GridNodes
from nlyap_opt.kernel.grid import norm2_up as _norm2_up
from nlyap_opt.kernel.jsonio import read_file_bytes, read_npz

__all__ = ["SampleSet", "load_samples", "save_samples", "sample_function", "RTOL_GRID"]

#: relative tolerance (of the spacing h) for a coordinate to count as a grid node
RTOL_GRID = 1e-9


def _nodes(lo: float, hi: float, n: int) -> np.ndarray:
    """Axis nodes exactly as ``nlyap_opt.learned.dynamics.Grid`` builds them."""
    ax = np.linspace(lo, hi, n)
    ax[0], ax[-1] = lo, hi
    return ax


class SampleSet(GridNodes):
    r"""Values of ``f`` at every node of a regular grid over :math:`X \times U`.

    Build it with :func:`load_samples` (from a file) or :func:`sample_function` (from a
    callable); the constructor takes rows in any order and checks that they form a
    complete regular grid.

    Parameters
    ----------
    points : (N, nx + nu) array_like
        The ``(x, u)`` of each sample.
    values : (N, nx) array_like
        ``ẋ = f(x, u)`` of each sample.
    nx, nu : int
    names : sequence of str, optional
        The ``nx + nu`` axis names (states then inputs), for messages.
    source : str, optional
        Where the samples come from (file name), for messages.

    Attributes
    ----------
    box : (d, 2) ndarray
        Rows ``(lo, hi)``, ``d = nx + nu``: the smallest and largest coordinate per axis.
    counts : (d,) ndarray of int
        Nodes per axis.
    axes : list of (n_i,) ndarray
        Node coordinates, bitwise equal to ``Grid(box, counts).axes``.
    spacing, gaps : (d,) ndarray
        Nominal spacing ``h`` and the largest float64 gap per axis, rounded up (as ``Grid``).
    offset : float
        Largest ``‖row − node‖₂`` (rounded up; 0 when the file holds the nodes exactly).
    delta : float
        Covering radius of the samples: ``½‖gaps‖₂`` rounded up (equal to
        ``Grid(box, counts).delta``) plus ``offset``.
    values : (N, nx) ndarray
        ``f`` at the nodes, in C order of the grid (``values[k]`` belongs to ``points(k)``).

    Examples
    --------
    >>> import numpy as np
    >>> z = np.array([[a, b] for a in (-1.0, 0.0, 1.0) for b in (0.0, 1.0)])
    >>> s = SampleSet(z[::-1], -z[::-1, :1], nx=1, nu=1)
    >>> s.counts.tolist(), round(s.delta, 12), s.values[:2].ravel().tolist()
    ([3, 2], 0.707106781187, [1.0, 1.0])
    """

    def __init__(self, points, values, *, nx: int, nu: int = 0,
                 names: Sequence[str] | None = None, source: str = ""):
        pts = np.asarray(points, dtype=float)
        val = np.asarray(values, dtype=float)
        self.nx, self.nu = int(nx), int(nu)
        d = self.nx + self.nu
        self.source = str(source)
        pre = f"{self.source}: " if self.source else ""
        self.names = list(names) if names is not None and len(names) == d else (
            [f"x{i + 1}" for i in range(self.nx)] + [f"u{i + 1}" for i in range(self.nu)])
        if pts.ndim != 2 or pts.shape[1] != d:
            raise DimensionError(f"{pre}points must have shape (N, {d}), got {pts.shape}")
        if val.shape != (pts.shape[0], self.nx):
            raise DimensionError(
                f"{pre}values must have shape ({pts.shape[0]}, {self.nx}), got {val.shape}"
            )
        for what, arr, cols in (("coordinate", pts, self.names),
                                ("value", val, [f"{n}_dot" for n in self.names[:self.nx]])):
            bad = ~np.isfinite(arr)
            if bad.any():
                r, c = np.argwhere(bad)[0]
                raise ConfigError(
                    f"{pre}{what} {cols[c]!r} of sample row {r + 1} is {arr[r, c]}; every "
                    "sample needs finite numbers (drop or recompute the row)"
                )
        idx = np.empty(pts.shape, dtype=np.int64)
        box, counts, axes = [], [], []
        for i in range(d):
            ax, k = self._axis(pts[:, i], self.names[i], pre, single_ok=i >= self.nx)
            box.append((ax[0], ax[-1]))
            counts.append(ax.size)
            axes.append(ax)
            idx[:, i] = k
        self.box = np.array(box, dtype=float).reshape(d, 2)
        self.counts = np.array(counts, dtype=np.int64)
        self.axes = axes
        flat = np.ravel_multi_index(tuple(idx.T), tuple(self.counts))
        size = int(np.prod(self.counts))
        order = np.argsort(flat, kind="stable")
        sf = flat[order]
        dup = np.flatnonzero(sf[1:] == sf[:-1])
        if dup.size:
            r1, r2 = sorted((int(order[dup[0]]), int(order[dup[0] + 1])))
            raise ConfigError(
                f"{pre}grid node {self._fmt_node(sf[dup[0]])} appears twice (rows {r1 + 1} "
                f"and {r2 + 1}); every node must be sampled exactly once (remove the duplicate)"
            )
        if sf.size != size:
            have = np.zeros(size, dtype=bool)
            have[sf] = True
            miss = int(np.flatnonzero(~have)[0])
            raise ConfigError(
                f"{pre}the grid is incomplete: node {self._fmt_node(miss)} is missing "
                f"({sf.size} rows for {' x '.join(map(str, counts))} = {size} nodes); sample "
                "every node of the regular grid"
            )
        self.values = np.ascontiguousarray(val[order])
        nodes = np.stack([ax[k] for ax, k in zip(axes, idx.T)], axis=-1)
        self.offset = float(np.max(_norm2_up(pts - nodes, axis=1), initial=0.0)) if size else 0.0
        if np.all(pts == nodes):
            self.offset = 0.0
        full = self.counts > 1
        self.spacing = np.where(full, self.box[:, 1] - self.box[:, 0], 0.0) / np.maximum(
            self.counts - 1, 1)
        self.gaps = np.array([np.nextafter(np.max(np.diff(ax)), np.inf) if ax.size > 1 else 0.0
                              for ax in self.axes])
        # δ over the axes with ≥ 2 nodes (a single input level is a slice, not an axis)
        delta = _norm2_up(0.5 * self.gaps[full])
        if self.offset > 0:
            delta = float(np.nextafter(delta + self.offset, np.inf))
        self.delta = delta

    # ------------------------------------------------------------------ construction
    def _axis(self, c: np.ndarray, name: str, pre: str,
              single_ok: bool = False) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = float(np.min(c)), float(np.max(c))
        if lo == hi and single_ok:  # one input level: a slice u = u0 (control-affine data)
            return np.array([lo]), np.zeros(c.size, dtype=np.int64)
        if not lo < hi:
            raise ConfigError(
                f"{pre}axis {name!r} has the single coordinate {lo}; a grid needs at least 2 "
                "nodes per axis"
            )
        u = np.unique(c)
        # coordinates closer than the tolerance are one node (a csv's last digits)
        tol = RTOL_GRID * (hi - lo)
        n = int(np.sum(np.diff(u) > tol)) + 1
        if n < 2:
            raise ConfigError(f"{pre}axis {name!r} needs at least 2 distinct coordinates")
        ax = _nodes(lo, hi, n)
        h = (hi - lo) / (n - 1)
        k = np.clip(np.rint((c - lo) / h), 0, n - 1).astype(np.int64)
        dev = np.abs(c - ax[k])
        j = int(np.argmax(dev))
        if dev[j] > RTOL_GRID * h:
            raise ConfigError(
                f"{pre}axis {name!r} is not equally spaced: coordinate {float(c[j])!r} is "
                f"{dev[j]:.3g} from the nearest node {float(ax[k[j]])!r} of {n} equally spaced "
                f"nodes on [{lo!r}, {hi!r}] (spacing {h:.6g}, tolerance relative {RTOL_GRID:g}); "
                "sample on a regular grid"
            )
        return ax, k

    def _fmt_node(self, flat) -> str:
        idx = np.unravel_index(int(flat), tuple(self.counts))
        return "(" + ", ".join(f"{n}={ax[i]:.6g}" for n, ax, i in
                               zip(self.names, self.axes, idx)) + ")"

    # ------------------------------------------------------------------ Grid interface
    @property
    def input_slice(self) -> bool:
        """True when some input has a single level (samples of ``f(x, u0)`` only)."""
        return bool(np.any(self.counts[self.nx:] == 1))

    def index_of(self, z) -> np.ndarray:
        """Flat indices of the nodes ``z`` ``(N, d)``; a point that is not a node is an error.

        A coordinate matches a node only if it equals it exactly (float64): values of a
        sample set exist at its nodes and nowhere else.
        """
        z = np.asarray(z, dtype=float)
        if z.ndim != 2 or z.shape[1] != self.dim:
            raise DimensionError(f"points must have shape (N, {self.dim}), got {z.shape}")
        idx = np.empty(z.shape, dtype=np.int64)
        for i, (ax, (lo, _), h) in enumerate(zip(self.axes, self.box, self.spacing)):
            with np.errstate(all="ignore"):
                k = np.clip(np.rint((z[:, i] - lo) / h), 0, ax.size - 1) if h > 0 else \
                    np.zeros(z.shape[0])
            k = np.where(np.isfinite(k), k, 0).astype(np.int64)
            bad = ax[k] != z[:, i]
            if bad.any():
                r = int(np.flatnonzero(bad)[0])
                raise ConfigError(
                    f"point {z[r].tolist()} is not a node of the sample grid"
                    f"{' of ' + self.source if self.source else ''} ({self.names[i]!r} = "
                    f"{z[r, i]!r}); samples give f only at their nodes (learn φ to go between)"
                )
            idx[:, i] = k
        return np.ravel_multi_index(tuple(idx.T), tuple(self.counts))

    def lookup(self, x, u=None) -> np.ndarray:
        """``f`` at the nodes ``(x, u)`` (``(N, nx)``, ``(N, nu)``), from the samples."""
        x = np.asarray(x, dtype=float)
        z = x if self.nu == 0 else np.hstack([x, np.asarray(u, dtype=float)])
        return self.values[self.index_of(z)]

    def nearest_node(self, z) -> tuple[int, float]:
        """Flat index of the node nearest to one point ``z`` and its distance."""
        z = np.asarray(z, dtype=float).reshape(self.dim)
        k = [int(np.clip(np.rint((c - lo) / h), 0, ax.size - 1)) if h > 0 else 0
             for c, ax, (lo, _), h in zip(z, self.axes, self.box, self.spacing)]
        node = np.array([ax[i] for ax, i in zip(self.axes, k)])
        return int(np.ravel_multi_index(tuple(k), tuple(self.counts))), float(
            np.linalg.norm(node - z))

    def to_dict(self) -> dict:
        """Summary for reports (no values)."""
        return {"source": self.source, "box": self.box.tolist(), "counts": self.counts.tolist(),
                "spacing": self.spacing.tolist(), "size": self.size, "delta": self.delta,
                "offset": self.offset, "names": self.names}

    def __repr__(self) -> str:
        return (f"SampleSet(counts={self.counts.tolist()}, spacing={self.spacing.tolist()}, "
                f"delta={self.delta:.6g})")


# ============================================================================ files
def _did_you_mean(name: str, options: Sequence[str]) -> str:
    m = difflib.get_close_matches(name, list(options), n=1, cutoff=0.6)
    return f"; did you mean {m[0]!r}?" if m else ""


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def _read_csv(path: Path, columns: Sequence[str] | None) -> tuple[list[str], np.ndarray]:
    try:  # utf-8-sig: a spreadsheet's BOM
        text = read_file_bytes(path, "sample file").decode("utf-8-sig")
        rows = [r for r in csv.reader(io.StringIO(text, newline=""))
                if r and any(c.strip() for c in r)]
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text (byte {exc.object[exc.start]:#04x} at "
                          f"offset {exc.start}); save the csv as UTF-8") from None
    except csv.Error as exc:
        raise ConfigError(f"{path}: not a readable csv ({exc}); fix the file") from None
    if not rows:
        raise ConfigError(f"{path}: the sample file is empty; write one row per sample")
    first = [unicodedata.normalize("NFKC", c.strip()) for c in rows[0]]
    header = None if all(_is_number(c) for c in first) else first
    data = rows[1:] if header is not None else rows
    width = len(rows[0])
    for r, row in enumerate(data):
        if len(row) != width:
            line = r + (2 if header is not None else 1)
            raise ConfigError(
                f"{path}: line {line} has {len(row)} fields, the first line has {width}; every "
                "row needs the same columns (a ragged csv)"
            )
    if columns is not None:
        columns = [unicodedata.normalize("NFKC", str(c)) for c in columns]
        if header is not None and header != columns:
            raise ConfigError(
                f"{path}: header {header} differs from the declared columns {columns}; "
                "remove one of them or make them agree"
            )
        names = columns
    elif header is not None:
        names = header
    else:
        raise ConfigError(
            f"{path}: the csv has no header; add one (names of states, inputs and "
            "<state>_dot) or declare 'columns'"
        )
    if len(names) != width:
        raise ConfigError(f"{path}: {len(names)} column names for rows of {width} fields")
    if not data:
        raise ConfigError(f"{path}: the csv has a header but no data rows; write one row per "
                          "sample below it")
    odd = next(((r, c) for r, row in enumerate(data) for c in row
                if "_" in c or not c.isascii()), None)
    if odd is not None:  # float() reads 1_0 as 10, and digits of other scripts: not data
        raise ConfigError(f"{path}: sample row {odd[0] + 1} holds {odd[1].strip()!r}, not a "
                          "plain number (ASCII digits, no '_' between them); fix the data")
    try:
        arr = np.array([[float(c) for c in row] for row in data], dtype=float)
    except ValueError as exc:
        raise ConfigError(f"{path}: a field is not a number ({exc}); fix the data") from None
    return names, _magnitudes(path, "a field", arr.reshape(len(data), width))


def _real_array(path: Path, name: str, a: np.ndarray) -> np.ndarray:
    """``a`` as float64 if it holds real numbers (a complex, boolean, text or structured
    array is refused: casting would drop an imaginary part or invent values)."""
    if a.dtype.kind not in "iuf":
        what = {"c": "complex", "b": "boolean", "U": "text", "S": "bytes", "V": "structured",
                "O": "object"}.get(a.dtype.kind, str(a.dtype))
        fix = "x.real, if the imaginary part is 0" if what == "complex" else "float64 arrays"
        raise ConfigError(f"{path}: array {name!r} is {what} ({a.dtype}); an npz sample file "
                          f"holds real numbers only (save {fix})")
    return _magnitudes(path, name, np.asarray(a, dtype=float))


#: the largest magnitude of a sample value (its square is finite; 1e308's is not)
SAMPLE_LIMIT = 1e100


def _magnitudes(path: Path, name: str, a: np.ndarray) -> np.ndarray:
    """``a``, unless a finite value exceeds :data:`SAMPLE_LIMIT` in magnitude (the first one
    named, with its sample row counted from 1)."""
    with np.errstate(invalid="ignore"):
        big = np.isfinite(a) & (np.abs(a) > SAMPLE_LIMIT)
    if np.any(big):
        at = tuple(np.argwhere(big)[0])
        raise ConfigError(f"{path}: {name} holds {a[at]:g} (sample row {at[0] + 1}), beyond "
                          f"±{SAMPLE_LIMIT:g}; rescale the samples")
    return a


def _read_npz(path: Path, nx: int, nu: int):
    """Arrays ``x``, ``u``, ``xdot`` of an npz file, read without pickle and checked."""
    npz = read_npz(path, "npz sample file",
                   "write it again with numpy.savez(path, x=..., u=..., xdot=...)",
                   not_npz_fix="write it with numpy.savez(path, x=..., u=..., xdot=...), or "
                               "give a csv file the suffix .csv")
    keys = set(npz)
    need = {"x", "xdot"} | ({"u"} if nu else set())
    extra = keys - need - {"u"}
    if need - keys or extra:
        raise ConfigError(
            f"{path}: an npz sample file holds arrays 'x' (N, {nx}), 'u' (N, {nu}) "
            f"and 'xdot' (N, {nx}); got {sorted(keys)}"
        )
    x = _real_array(path, "x", npz["x"])
    xdot = _real_array(path, "xdot", npz["xdot"])
    u = _real_array(path, "u", npz["u"]) if "u" in keys else np.zeros((len(x), 0))
    return x, u, xdot


def load_samples(path, *, states: Sequence[str], inputs: Sequence[str] = (),
                 columns: Sequence[str] | None = None) -> SampleSet:
    """Load a ``.csv`` or ``.npz`` sample file and check it is a complete regular grid.

    Parameters
    ----------
    path : str or Path
    states, inputs : sequence of str
        Names of the states and inputs; the csv needs the columns ``states``, ``inputs``
        and ``<state>_dot``.
    columns : sequence of str, optional
        Column names of a csv without a header (or to check the header against).

    Returns
    -------
    SampleSet

    Raises
    ------
    ConfigError
        Unreadable, ragged, missing or extra columns, NaN, an irregular or incomplete grid,
        duplicate nodes (one line naming the problem and the fix).
    """
    path = Path(path)
    states = [unicodedata.normalize("NFKC", str(s)) for s in states]
    inputs = [unicodedata.normalize("NFKC", str(s)) for s in inputs]
    nx, nu = len(states), len(inputs)
    if not path.is_file():
        raise ConfigError(f"sample file {str(path)!r} " + (
            "is not a regular file (a directory, pipe or device); give the csv or npz file"
            if path.exists() else "not found; check the path"))
    if path.suffix.lower() == ".npz":
        x, u, xdot = _read_npz(path, nx, nu)
        x = x.reshape(len(x), -1) if x.ndim == 1 and nx == 1 else x
        xdot = xdot.reshape(len(xdot), -1) if xdot.ndim == 1 and nx == 1 else xdot
        u = u.reshape(len(u), -1) if u.ndim == 1 and nu == 1 else u
        for nm, a, w in (("x", x, nx), ("u", u, nu), ("xdot", xdot, nx)):
            if a.ndim != 2 or a.shape[1] != w or a.shape[0] != x.shape[0]:
                raise ConfigError(
                    f"{path}: array {nm!r} has shape {a.shape}; expected ({x.shape[0]}, {w})"
                )
        pts, val = np.hstack([x, u.reshape(len(x), nu)]), xdot
        if not len(pts):
            raise ConfigError(f"{path}: the npz sample file holds no samples (its arrays have "
                              "0 rows); write one row per sample")
    elif path.suffix.lower() == ".csv":
        names, arr = _read_csv(path, columns)
        want = states + inputs + [f"{s}_dot" for s in states]
        if len(set(names)) != len(names):
            dup = next(n for n in names if names.count(n) > 1)
            raise ConfigError(f"{path}: column {dup!r} appears twice; name every column once")
        for n in names:
            if n not in want:
                raise ConfigError(
                    f"{path}: unknown column {n!r}{_did_you_mean(n, want)} (columns: states "
                    f"{states}, inputs {inputs}, derivatives {[s + '_dot' for s in states]})"
                )
        for n in want:
            if n not in names:
                raise ConfigError(f"{path}: column {n!r} is missing; the csv needs {want}")
        col = {n: i for i, n in enumerate(names)}
        pts = arr[:, [col[n] for n in states + inputs]]
        val = arr[:, [col[f"{s}_dot"] for s in states]]
    else:
        raise ConfigError(f"sample file {str(path)!r}: use a .csv or .npz file")
    return SampleSet(pts, val, nx=nx, nu=nu, names=states + inputs, source=str(path))


def save_samples(path, points, values, *, states: Sequence[str],
                 inputs: Sequence[str] = ()) -> Path:
    """Write samples as ``.csv`` (header, every float with 17 significant digits) or ``.npz``.

    The csv round-trips float64 exactly, so the loaded grid has ``offset == 0``.
    """
    path = Path(path)
    pts, val = np.asarray(points, dtype=float), np.asarray(values, dtype=float)
    nx, nu = len(states), len(inputs)
    if pts.shape[1:] != (nx + nu,) or val.shape != (pts.shape[0], nx):
        raise DimensionError(
            f"points (N, {nx + nu}) and values (N, {nx}) expected, got {pts.shape}, {val.shape}"
        )
    if path.suffix.lower() == ".npz":
        np.savez(path, x=pts[:, :nx], u=pts[:, nx:], xdot=val)
    elif path.suffix.lower() == ".csv":
        header = list(states) + list(inputs) + [f"{s}_dot" for s in states]
        with open(path, "w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(header)
            for row in np.hstack([pts, val]):
                w.writerow([repr(float(v)) for v in row])
    else:
        raise ConfigError(f"sample file {str(path)!r}: use a .csv or .npz file")
    return path


def sample_function(f: Callable[[np.ndarray, np.ndarray], np.ndarray], box, counts,
                    *, nx: int, names: Sequence[str] | None = None,
                    batch_size: int = 1 << 16) -> SampleSet:
    """Sample a batched ``f(X, U) -> Xdot`` at every node of ``Grid(box, counts)``.

    Parameters
    ----------
    f : callable
        ``(N, nx), (N, nu) -> (N, nx)`` float64 (e.g. ``System.evaluate``).
    box : (nx + nu, 2) array_like
    counts : sequence of int
    nx : int
        Number of states (the first ``nx`` axes).
    """
    box = np.array(box, dtype=float, ndmin=2)
    counts = [int(c) for c in counts]
    if box.shape != (len(counts), 2) or min(counts) < 2:
        raise ConfigError(f"box {box.shape} and counts {counts} do not describe a grid")
    axes = [_nodes(lo, hi, n) for (lo, hi), n in zip(box, counts)]
    size = int(np.prod(counts))
    pts = np.empty((size, len(counts)))
    vals = np.empty((size, nx))
    for start in range(0, size, batch_size):
        k = np.arange(start, min(start + batch_size, size))
        idx = np.unravel_index(k, counts)
        z = np.stack([ax[i] for ax, i in zip(axes, idx)], axis=-1)
        pts[k] = z
        vals[k] = np.asarray(f(z[:, :nx], z[:, nx:]), dtype=float)
    return SampleSet(pts, vals, nx=nx, nu=len(counts) - nx, names=names)
