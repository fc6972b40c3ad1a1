r"""Feed-forward networks: a JSON format, exact CasADi graphs, numpy and torch forms.

The JSON format (``"format": "nlyap-network"``, ``"version": 1``)::

    {"format": "nlyap-network", "version": 1, "input_dim": 2,
     "layers": [{"weight": [[...], ...], "bias": [...], "activation": "tanh"}, ...],
     "output_scale": 1.0,
     "head": null,
     "meta": {...}}

``weight`` of layer ``k`` has shape ``(out_k, in_k)``; ``activation`` is one of
:data:`ACTIVATIONS`; ``output_scale`` (scalar or one per output) multiplies the last
layer's output (a controller ``u = C·tanh(Kx + b)`` is one tanh layer with scale ``C``).
``head`` is ``null`` or ``{"type": "sum_of_squares", "eps": ε}``, which turns the body
:math:`N` into the Lyapunov candidate

.. math:: V(z) = \|N(z) - N(0)\|^2 + \varepsilon \|z\|^2

(:math:`V(0) = 0` and :math:`V \ge \varepsilon\|z\|^2` by construction). Numbers are
written with Python's shortest round-trip ``repr``, so float64 weights survive save/load
bit for bit. :meth:`Network.load` validates a file completely (types, nesting, shapes,
finiteness, unknown keys) and refuses a bad one with a one-line :class:`NetworkFileError`
naming the file, the layer and the fix.

One forward pass, several arithmetics: the layer loop (:meth:`Network._forward`) and the
sum-of-squares head (:func:`_sum_of_squares`) are written once and run with a CasADi
arithmetic (:meth:`Network.casadi`) or a numpy arithmetic (:meth:`Network.numpy`); each
activation is written once as a function of an operation namespace (:data:`ACTIVATIONS`).
The torch form (:meth:`Network.torch_module`, a ``Sequential`` that training and
:func:`from_torch` rely on) is built from the same table and the same head function;
``tests/test_network.py`` checks all three equal in float64, values and gradients.

The CasADi graph uses the float64 weights as exact constants (dense ``mtimes`` nodes when
called on ``MX``), so every consumer -- the NLP, the interval verifier, dReal, SMT-LIB --
sees the very function that is saved.
"""

from __future__ import annotations

import difflib
import json
import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import casadi as ca
import numpy as np

from . import deps
from .errors import (
    ConfigError,
    DimensionError,
    NetworkFileError,
    NlyapError,
    UnsupportedLayerError,
)
from .jsonio import read_file_bytes, write_atomic

__all__ = [
    "Activation", "Layer", "Network", "ACTIVATIONS", "HEADS", "TORCH_CONVERTERS", "from_torch",
    "load_network", "dense_network",
]

FORMAT = "nlyap-network"
VERSION = 1

#: output heads: ``sum_of_squares`` makes a Lyapunov candidate
#: ``V(z) = ||N(z) - N(0)||² + eps·||z||²`` (V(0) = 0 and V ≥ eps||z||² by construction)
HEADS = ("sum_of_squares",)


# ============================================================================ activations
@dataclass(frozen=True)
class Activation:
    """One activation, written once for every arithmetic.

    Attributes
    ----------
    name : str
        The name used in network files.
    apply : callable ``(z, ops) -> σ(z)``
        The formula, written with the operations of ``ops`` (``ops.tanh``, ``ops.exp``,
        ``ops.fmax``): :data:`CASADI_OPS` builds the CasADi graph, :data:`NUMPY_OPS`
        evaluates in float64 numpy.
    torch : str or None
        Class name of the same function: in ``torch.nn``, or one of this module's own torch
        classes (``Square``); ``None``: identity, no module.
    """

    name: str
    apply: Callable[[Any, SimpleNamespace], Any]
    torch: str | None


#: the operations an activation may use, per arithmetic
CASADI_OPS = SimpleNamespace(tanh=ca.tanh, exp=ca.exp, fmax=ca.fmax)
NUMPY_OPS = SimpleNamespace(tanh=np.tanh, exp=np.exp, fmax=np.maximum)

#: activation name -> :class:`Activation`
ACTIVATIONS: dict[str, Activation] = {a.name: a for a in (
    Activation("tanh", lambda z, ops: ops.tanh(z), "Tanh"),
    Activation("relu", lambda z, ops: ops.fmax(z, 0.0), "ReLU"),
    Activation("sigmoid", lambda z, ops: 1.0 / (1.0 + ops.exp(-z)), "Sigmoid"),
    Activation("linear", lambda z, ops: z, None),
    # z²: with the sum-of-squares head, V is a polynomial (degree 4 with one hidden layer);
    # ``z**2`` is CasADi's OP_SQ, whose interval enclosure is exact
    Activation("square", lambda z, ops: z**2, "Square"),
)}


def _sum_of_squares(body: Callable, z, zero, eps: float, sumsq: Callable):
    """``‖body(z) − body(0)‖² + eps‖z‖²``: the ``sum_of_squares`` head, in any arithmetic.

    ``body(0)`` is evaluated, not folded to a float, so ``V(0) = 0`` holds exactly in real
    arithmetic for the CasADi graph as well.
    """
    y = body(z) - body(zero)
    V = sumsq(y)
    if eps:
        V = V + eps * sumsq(z)
    return V


def _casadi_zero(z):
    n = z.shape[0]
    if isinstance(z, ca.MX):
        return ca.MX(ca.DM.zeros(n, 1))
    if isinstance(z, ca.SX):
        return ca.SX.zeros(n, 1)
    return ca.DM.zeros(n, 1)


#: arithmetic = how an affine map, an output scale, a squared norm and a zero input are
#: written; inputs are columns ``(n_in, 1)`` in CasADi and row batches ``(N, n_in)`` in numpy
_CASADI = SimpleNamespace(
    ops=CASADI_OPS,
    affine=lambda layer, h: ca.mtimes(ca.DM(layer.weight), h) + ca.DM(layer.bias),
    scale=lambda h, s: float(s) * h if s.ndim == 0 else ca.DM(s) * h,
    sumsq=ca.sumsqr,
    zero=_casadi_zero,
)
_NUMPY = SimpleNamespace(
    ops=NUMPY_OPS,
    affine=lambda layer, h: h @ layer.weight.T + layer.bias,
    scale=lambda h, s: h * s,
    sumsq=lambda y: np.sum(y * y, axis=-1, keepdims=True),
    zero=lambda z: np.zeros((1, z.shape[-1])),
)


# ============================================================================ layers, network
@dataclass
class Layer:
    """One dense layer ``activation(W z + b)``.

    Parameters
    ----------
    weight : (n_out, n_in) array_like of float
    bias : (n_out,) array_like of float
    activation : str
        A key of :data:`ACTIVATIONS`.
    """

    weight: np.ndarray
    bias: np.ndarray
    activation: str = "linear"

    def __post_init__(self):
        self.weight = _float_array(self.weight, "weight", ndmin=2)
        self.bias = _float_array(self.bias, "bias").reshape(-1)
        if self.weight.ndim != 2 or 0 in self.weight.shape:
            raise DimensionError(
                f"weight must be a non-empty 2-D (n_out, n_in) array, got shape "
                f"{self.weight.shape}"
            )
        if self.bias.shape[0] != self.weight.shape[0]:
            raise DimensionError(
                f"bias has {self.bias.shape[0]} entries but weight has {self.weight.shape[0]} "
                "rows; they must match"
            )
        if self.activation not in ACTIVATIONS:
            raise UnsupportedLayerError(
                f"activation {self.activation!r} is not supported; use one of "
                f"{', '.join(ACTIVATIONS)}"
            )
        if not (np.all(np.isfinite(self.weight)) and np.all(np.isfinite(self.bias))):
            raise NetworkFileError("layer weights and biases must be finite (no NaN or inf)")


def _float_array(value, what: str, ndmin: int = 0) -> np.ndarray:
    """``value`` as a float64 array; refuses strings, booleans, objects and ragged lists."""
    try:
        arr = np.array(value, ndmin=ndmin)
    except (ValueError, TypeError) as err:  # ragged nesting (numpy >= 1.24)
        raise DimensionError(f"{what} is not a rectangular array of numbers ({err})") from None
    if arr.dtype.kind not in "iuf":
        raise DimensionError(
            f"{what} must hold numbers only (got dtype {arr.dtype}: strings, booleans or "
            "ragged lists are not weights)"
        )
    return arr.astype(float)


@dataclass
class Network:
    r"""A feed-forward network of dense layers, with an optional output scale and head.

    Without a head the network is
    :math:`N(z) = c \odot \sigma_L(W_L \cdots \sigma_1(W_1 z + b_1) \cdots + b_L)`;
    with ``head={"type": "sum_of_squares", "eps": ε}`` it is the scalar
    :math:`V(z) = \|N(z) - N(0)\|^2 + \varepsilon\|z\|^2`.

    Parameters
    ----------
    layers : list of Layer
    output_scale : float or (n_out,) array_like
        :math:`c`, multiplies the last layer's output.
    meta : dict
        Free-form metadata saved with the network (training settings, ...).
    head : dict or None
        ``None`` or ``{"type": "sum_of_squares", "eps": eps}`` (``eps ≥ 0``, default 0).

    Examples
    --------
    >>> import casadi as ca, numpy as np
    >>> net = Network([Layer([[1.0, 2.0]], [0.5], "tanh")], output_scale=5.0)
    >>> x = ca.SX.sym("x", 2)
    >>> round(float(ca.Function("k", [x], [net.casadi(x)])([0, 0])), 12)  # 5 tanh(0.5)
    2.3105857863
    >>> round(float(net.numpy(np.zeros((1, 2)))[0, 0]), 12)
    2.3105857863
    """

    layers: list[Layer]
    output_scale: float | np.ndarray = 1.0
    meta: dict = field(default_factory=dict)
    head: dict | None = None

    def __post_init__(self):
        if self.head is not None:
            if not isinstance(self.head, dict):
                raise UnsupportedLayerError(
                    f"network head must be None or a dict like {{'type': 'sum_of_squares', "
                    f"'eps': 0.001}}, got {type(self.head).__name__}"
                )
            kind = self.head.get("type")
            if kind not in HEADS:
                raise UnsupportedLayerError(
                    f"network head {kind!r} is not supported; use one of {', '.join(HEADS)}"
                )
            eps = self.head.get("eps", 0.0)
            if isinstance(eps, bool) or not isinstance(eps, (int, float, np.floating)) or not (
                    math.isfinite(eps) and eps >= 0):
                raise NetworkFileError(f"head eps must be a finite number >= 0, got {eps!r}")
            self.head = {"type": kind, "eps": float(eps)}
        if isinstance(self.layers, (str, bytes, dict)) or not hasattr(self.layers, "__len__"):
            raise DimensionError(f"layers must be a list of Layer, got "
                                 f"{type(self.layers).__name__}; e.g. "
                                 "Network([Layer(W1, b1, 'tanh'), Layer(W2, b2)])")
        self.layers = list(self.layers)
        if not self.layers:
            raise DimensionError("a network needs at least one layer")
        for k, layer in enumerate(self.layers):
            if not isinstance(layer, Layer):
                raise DimensionError(f"layer {k} is a {type(layer).__name__}, not a Layer; "
                                     "build it with Layer(weight, bias, activation) (or read "
                                     "a saved network with Network.load)")
        if not isinstance(self.meta, dict):
            raise NetworkFileError(f"meta must be a dict (saved with the network), got "
                                   f"{type(self.meta).__name__}; pass e.g. meta={{'kind': "
                                   "'lyapunov'}}")
        for k in range(1, len(self.layers)):
            a, b = self.layers[k - 1], self.layers[k]
            if b.weight.shape[1] != a.weight.shape[0]:
                raise DimensionError(
                    f"layer {k} expects {b.weight.shape[1]} inputs but layer {k - 1} gives "
                    f"{a.weight.shape[0]} outputs"
                )
        scale = _float_array(self.output_scale, "output_scale")
        n_body = self.layers[-1].weight.shape[0]
        if scale.ndim > 1 or (scale.ndim == 1 and scale.shape[0] != n_body):
            raise DimensionError(f"output_scale must be a scalar or have {n_body} entries")
        if not np.all(np.isfinite(scale)):
            raise NetworkFileError("output_scale must be finite")
        self.output_scale = scale

    @property
    def n_in(self) -> int:
        """Input size."""
        return self.layers[0].weight.shape[1]

    @property
    def n_out(self) -> int:
        """Output size (1 with a head)."""
        return 1 if self.head else self.layers[-1].weight.shape[0]

    # ---------------------------------------------------------------- evaluation
    def _forward(self, z, ar):
        """The network in arithmetic ``ar`` (:data:`_CASADI` or :data:`_NUMPY`)."""
        if self.head is None:
            return self._body(z, ar)
        return _sum_of_squares(lambda h: self._body(h, ar), z, ar.zero(z), self.head["eps"],
                               ar.sumsq)

    def _body(self, h, ar):
        """The layer loop ``σ_k(W_k h + b_k)``, then the output scale (skipped when 1)."""
        for layer in self.layers:
            h = ACTIVATIONS[layer.activation].apply(ar.affine(layer, h), ar.ops)
        if self.output_scale.ndim > 0 or float(self.output_scale) != 1.0:
            h = ar.scale(h, self.output_scale)
        return h

    def casadi(self, z):
        """The network as a CasADi expression.

        Parameters
        ----------
        z : (n_in, 1) SX, MX or DM

        Returns
        -------
        (n_out, 1) expression of the same kind
        """
        if not isinstance(z, (ca.SX, ca.MX, ca.DM)):
            z = ca.DM(np.asarray(z, dtype=float).reshape(-1, 1))
        if z.shape != (self.n_in, 1):
            raise DimensionError(f"network input must have shape ({self.n_in}, 1), got {z.shape}")
        return self._forward(z, _CASADI)

    def function(self, name: str = "net", sym=ca.MX) -> ca.Function:
        """CasADi Function ``z -> network(z)`` (MX by default: matrix-level nodes)."""
        z = sym.sym("z", self.n_in)
        return ca.Function(name, [z], [self.casadi(z)])

    def numpy(self, z) -> np.ndarray:
        """Evaluate in float64 numpy.

        Parameters
        ----------
        z : (..., n_in) array_like
            A batch of inputs (any leading shape) or one input ``(n_in,)``.

        Returns
        -------
        (..., n_out) ndarray
        """
        try:
            z = np.asarray(z, dtype=float)
        except (TypeError, ValueError):
            raise DimensionError(f"network input must be an array of numbers of shape (N, "
                                 f"{self.n_in}) or ({self.n_in},), got "
                                 f"{type(z).__name__}") from None
        if z.ndim == 0 or z.shape[-1] != self.n_in:
            raise DimensionError(
                f"network input must have shape (N, {self.n_in}) or ({self.n_in},), got "
                f"{z.shape}"
            )
        out = self._forward(np.atleast_2d(z), _NUMPY)
        return out[0] if z.ndim == 1 else out

    def torch_module(self, dtype=None):
        """A ``torch.nn`` module with these weights (float64 by default).

        Without a head: a ``Sequential`` of ``Linear``, activation modules (from
        :data:`ACTIVATIONS`) and a ``Scale`` module; with a head: a module with attributes
        ``body`` (that ``Sequential``) and ``eps``.
        """
        torch = deps.torch()
        nn = torch.nn

        dtype = dtype or torch.float64
        mods = []
        for layer in self.layers:
            lin = nn.Linear(layer.weight.shape[1], layer.weight.shape[0]).to(dtype)
            with torch.no_grad():
                lin.weight.copy_(torch.as_tensor(layer.weight, dtype=dtype))
                lin.bias.copy_(torch.as_tensor(layer.bias, dtype=dtype))
            mods.append(lin)
            act = ACTIVATIONS[layer.activation].torch
            if act is not None:
                own = {c.__name__: c for c in _torch_classes()}
                mods.append((own[act] if act in own else getattr(nn, act))())
        scale_cls, head_cls, _ = _torch_classes()
        if self.output_scale.ndim > 0 or float(self.output_scale) != 1.0:
            mods.append(scale_cls(torch.as_tensor(self.output_scale, dtype=dtype)))
        body = nn.Sequential(*mods)
        if self.head is None:
            return body
        return head_cls(body, self.head["eps"])

    # ---------------------------------------------------------------- files
    def to_dict(self) -> dict:
        """The JSON form (see the module docstring)."""
        return {
            "format": FORMAT,
            "version": VERSION,
            "input_dim": self.n_in,
            "layers": [
                {"weight": layer.weight.tolist(), "bias": layer.bias.tolist(),
                 "activation": layer.activation}
                for layer in self.layers
            ],
            "output_scale": self.output_scale.tolist(),
            "head": self.head,
            "meta": self.meta,
        }

    def save(self, path: str | Path) -> Path:
        """Write the network as JSON (exact float64 decimals)."""
        path = _network_path(path, "save")
        try:
            text = json.dumps(self.to_dict(), allow_nan=False, indent=1)
        except (TypeError, ValueError) as err:
            raise NetworkFileError(f"cannot save the network: its meta holds a value JSON "
                                   f"cannot write ({_one_line(err)}); keep meta to finite "
                                   "numbers, strings, booleans, lists and dicts") from None
        if path.is_dir():
            raise NetworkFileError(f"cannot save the network to {path}: it is a directory; "
                                   "give a file path (e.g. DIR/V.json)")
        path.parent.mkdir(parents=True, exist_ok=True)
        return write_atomic(path, text)

    @classmethod
    def from_dict(cls, d: dict, source: str = "network") -> Network:
        """Build a network from its JSON form, validating every entry.

        Parameters
        ----------
        d : dict
            As written by :meth:`to_dict`.
        source : str
            Named in error messages (the file path for :meth:`load`).

        Raises
        ------
        NetworkFileError
            One line naming ``source``, the layer and the fix, for: a non-object, missing
            or unknown keys, wrong nesting, ragged arrays, strings or booleans where numbers
            belong, NaN or inf, empty layers, unknown activations or heads, and shapes that
            do not chain.
        """
        return _parse_network(cls, d, source)

    @classmethod
    def load(cls, path: str | Path, data: bytes | None = None) -> Network:
        """Read and validate a network JSON file (see :meth:`from_dict`).

        ``data``, when given, is the file's content already read (and hashed) by the
        caller: it is parsed instead of reading ``path`` again, which is then only named in
        messages."""
        path = _network_path(path, "load")
        try:
            if data is None:
                data = read_file_bytes(path, "network file")
            text = data.decode("utf-8")
        except (OSError, UnicodeDecodeError, ConfigError) as err:
            raise NetworkFileError(
                f"cannot read network file {path}: {_one_line(err)}; pass the path of a JSON "
                "file written by Network.save"
            ) from None
        try:
            d = json.loads(text, parse_constant=_refuse_constant)
        except json.JSONDecodeError as err:
            raise NetworkFileError(
                f"{path} is not valid JSON ({_one_line(err)}); the file may be truncated: "
                "re-save it with Network.save"
            ) from None
        except RecursionError:
            raise NetworkFileError(
                f"{path} is not valid network JSON (nested too deeply); weights are lists of "
                "lists of numbers"
            ) from None
        except NetworkFileError as err:
            raise NetworkFileError(f"{path}: {err}") from None
        except ValueError as err:  # an integer of thousands of digits (Python's own limit)
            raise NetworkFileError(f"{path} cannot be read ({_one_line(err)}); re-save it "
                                   "with Network.save") from None
        return cls.from_dict(d, str(path))


def _network_path(path, what: str) -> Path:
    """``path`` as a :class:`~pathlib.Path`, or one line naming what a path is."""
    if not isinstance(path, (str, os.PathLike)) or isinstance(path, bytes) or path == "":
        raise NetworkFileError(f"Network.{what} needs a file path (a str or pathlib.Path), "
                               f"got {path!r}")
    return Path(path)


def _refuse_constant(name: str):
    raise NetworkFileError(
        f"network files may not contain {name}; weights must be finite numbers (retrain or "
        "fix the weights that overflowed)"
    )


def _one_line(err) -> str:
    return " ".join(str(err).split())


# ============================================================================ validation
_TOP_KEYS = ("format", "version", "input_dim", "layers", "output_scale", "head", "meta")
_LAYER_KEYS = ("weight", "bias", "activation")
_HEAD_KEYS = ("type", "eps")


def _kind(v) -> str:
    """JSON name of a Python value's type (for messages)."""
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "a boolean"
    if isinstance(v, (int, float)):
        return "a number"
    if isinstance(v, str):
        return "a string"
    if isinstance(v, list):
        return "a list"
    if isinstance(v, dict):
        return "an object"
    return type(v).__name__


def _is_number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(
        v, (bool, np.bool_))


def _number(v, where: str, fail: Callable[[str], NlyapError]) -> float:
    if not _is_number(v):
        raise fail(f"{where} is {_kind(v)} ({v!r:.40}), expected a number")
    try:
        x = float(v)
    except OverflowError:
        x = math.inf
    if not math.isfinite(x):
        raise fail(f"{where} is {v!r:.40}, expected a finite number (no NaN or inf)")
    return x


def _vector(v, where: str, fail) -> np.ndarray:
    if isinstance(v, np.ndarray):  # a dict built in memory rather than read from JSON
        v = v.tolist()
    if not isinstance(v, list):
        raise fail(f"{where} is {_kind(v)}, expected a list of numbers")
    if not v:
        raise fail(f"{where} is empty, expected at least one number")
    return np.array([_number(x, f"{where}[{i}]", fail) for i, x in enumerate(v)], dtype=float)


def _matrix(v, where: str, fail) -> np.ndarray:
    if isinstance(v, np.ndarray):
        v = v.tolist()
    if not isinstance(v, list) or not v:
        what = "an empty list" if isinstance(v, list) else _kind(v)
        raise fail(f"{where} is {what}, expected a non-empty list of rows (lists of numbers)")
    rows = []
    for i, row in enumerate(v):
        if not isinstance(row, list):
            raise fail(f"{where}[{i}] is {_kind(row)}, expected a row (a list of numbers); "
                       "weight is a list of lists, one row per output")
        rows.append(_vector(row, f"{where}[{i}]", fail))
        if len(rows[-1]) != len(rows[0]):
            raise fail(f"{where} is ragged: row {i} has {len(rows[-1])} entries, row 0 has "
                       f"{len(rows[0])}; every row needs one entry per input")
    return np.array(rows, dtype=float)


def _unknown_keys(d: dict, known: tuple[str, ...], where: str, fail):
    for key in d:
        if key not in known:
            close = difflib.get_close_matches(str(key), known, n=1)
            hint = f"did you mean {close[0]!r}?" if close else f"known keys: {', '.join(known)}"
            raise fail(f"{where} has unknown key {key!r}; {hint}")


def _parse_network(cls, d, source: str) -> Network:
    """Validate the JSON form ``d`` completely, then build the network."""

    def fail(msg: str) -> NetworkFileError:
        return NetworkFileError(f"{source}: {msg}")

    if not isinstance(d, dict):
        raise fail(f"expected a JSON object with a 'layers' list (format {FORMAT!r}), got "
                   f"{_kind(d)}")
    if "format" in d and d["format"] != FORMAT:
        raise fail(f"format is {d['format']!r}, expected {FORMAT!r}; this is not a network file")
    if "version" in d and (not _is_number(d["version"]) or d["version"] != VERSION):
        raise fail(f"version is {d['version']!r}; this nlyap_opt reads version {VERSION}")
    _unknown_keys(d, _TOP_KEYS, "the network object", fail)
    if "layers" not in d:
        raise fail("malformed: missing key 'layers' (a list of {\"weight\", \"bias\", "
                   "\"activation\"} objects)")
    raw = d["layers"]
    if not isinstance(raw, list):
        raise fail(f"'layers' is {_kind(raw)}, expected a list of layer objects")
    if not raw:
        raise fail("'layers' is empty; a network needs at least one layer")
    layers = []
    for k, ld in enumerate(raw):
        def lfail(msg: str, k=k) -> NetworkFileError:
            return fail(f"layer {k}: {msg}")

        if not isinstance(ld, dict):
            raise lfail(f"is {_kind(ld)}, expected an object with keys 'weight', 'bias', "
                        "'activation'")
        _unknown_keys(ld, _LAYER_KEYS, "the layer", lfail)
        for key in _LAYER_KEYS:
            if key not in ld:
                fix = ('add "activation": "linear" for an affine layer' if key == "activation"
                       else f"add {key!r}")
                raise lfail(f"malformed: missing key {key!r}; {fix}")
        w = _matrix(ld["weight"], "weight", lfail)
        b = _vector(ld["bias"], "bias", lfail)
        act = ld["activation"]
        if not isinstance(act, str) or act not in ACTIVATIONS:
            raise lfail(f"activation {act!r} is not supported; use one of "
                        f"{', '.join(ACTIVATIONS)}")
        if b.shape[0] != w.shape[0]:
            raise lfail(f"bias has {b.shape[0]} entries but weight has {w.shape[0]} rows; "
                        "they must match (one bias per output)")
        if layers and w.shape[1] != layers[-1].weight.shape[0]:
            raise lfail(f"weight has {w.shape[1]} columns but layer {k - 1} gives "
                        f"{layers[-1].weight.shape[0]} outputs; the shapes must chain "
                        "(weight is (outputs, inputs))")
        layers.append(Layer(w, b, act))
    n_body = layers[-1].weight.shape[0]
    scale: float | np.ndarray = 1.0
    if "output_scale" in d:
        s = d["output_scale"]
        if isinstance(s, list):
            scale = _vector(s, "output_scale", fail)
            if scale.shape[0] != n_body:
                raise fail(f"output_scale has {scale.shape[0]} entries but the last layer gives "
                           f"{n_body} outputs; give one number or {n_body}")
        else:
            scale = _number(s, "output_scale", fail)
    head = d.get("head")
    if head is not None:
        if not isinstance(head, dict):
            raise fail(f"head is {_kind(head)}, expected null or "
                       "{\"type\": \"sum_of_squares\", \"eps\": 0.001}")
        _unknown_keys(head, _HEAD_KEYS, "head", fail)
        if head.get("type") not in HEADS:
            raise fail(f"head type {head.get('type')!r} is not supported; use one of "
                       f"{', '.join(HEADS)}")
        eps = _number(head.get("eps", 0.0), "head eps", fail)
        if eps < 0:
            raise fail(f"head eps is {eps}, expected a finite number >= 0")
        head = {"type": head["type"], "eps": eps}
    meta = d.get("meta", {})
    if meta is None:
        meta = {}
    if not isinstance(meta, dict):
        raise fail(f"meta is {_kind(meta)}, expected an object")
    if "input_dim" in d:
        n = d["input_dim"]
        integral = isinstance(n, int) or (isinstance(n, float) and n.is_integer())
        if isinstance(n, bool) or not integral or n != layers[0].weight.shape[1]:
            raise fail(f"input_dim is {n!r} but layer 0's weight has "
                       f"{layers[0].weight.shape[1]} columns; they must match")
    try:
        return cls(layers, scale, dict(meta), head)
    except NlyapError as err:  # pragma: no cover - everything is checked above
        raise fail(_one_line(err)) from None


def load_network(path: str | Path) -> Network:
    """Read a network JSON file; see :meth:`Network.load`."""
    return Network.load(path)


# ============================================================================ torch classes
_TORCH_CLASSES: tuple | None = None


def _torch_classes():
    """``(Scale, CentredSumOfSquares, Square)``, defined on first use (torch is imported
    lazily)."""
    global _TORCH_CLASSES
    if _TORCH_CLASSES is not None:
        return _TORCH_CLASSES
    torch = deps.torch()
    nn = torch.nn

    class Scale(nn.Module):
        """Multiply by a constant (the network's output scale)."""

        def __init__(self, scale):
            super().__init__()
            self.register_buffer("scale", scale)

        def forward(self, h):
            return h * self.scale

    class CentredSumOfSquares(nn.Module):
        """``V(z) = ||body(z) - body(0)||² + eps ||z||²`` (the ``sum_of_squares`` head)."""

        def __init__(self, body, eps):
            super().__init__()
            self.body = body
            self.eps = float(eps)

        def forward(self, z):
            return _sum_of_squares(self.body, z, torch.zeros_like(z[..., :1, :]), self.eps,
                                   lambda y: (y * y).sum(-1, keepdim=True))

        def to_network(self):
            net = from_torch(self.body)
            return Network(net.layers, net.output_scale, {}, {"type": "sum_of_squares",
                                                                 "eps": self.eps})

    class Square(nn.Module):
        """Elementwise ``z²`` (the ``square`` activation)."""

        def forward(self, h):
            return h * h

    _TORCH_CLASSES = (Scale, CentredSumOfSquares, Square)
    return _TORCH_CLASSES


# ============================================================================ torch -> Network
#: torch module class name -> converter(module, pending_layers) -> None (mutates the list)
TORCH_CONVERTERS: dict[str, Callable] = {}


def _register(*names):
    def deco(fn):
        for n in names:
            TORCH_CONVERTERS[n] = fn
        return fn
    return deco


@_register("Linear")
def _conv_linear(mod, layers: list):
    w = mod.weight.detach().double().cpu().numpy()
    b = (mod.bias.detach().double().cpu().numpy() if mod.bias is not None
         else np.zeros(w.shape[0]))
    layers.append(Layer(w, b, "linear"))


def _activation(name):
    def conv(mod, layers: list):
        if not layers or layers[-1].activation != "linear":
            raise UnsupportedLayerError(
                f"activation {type(mod).__name__} must follow a Linear layer"
            )
        layers[-1].activation = name
    return conv


for _act in ACTIVATIONS.values():
    if _act.torch is not None:
        TORCH_CONVERTERS[_act.torch] = _activation(_act.name)
TORCH_CONVERTERS["Identity"] = lambda mod, layers: None


def from_torch(module, meta: dict | None = None) -> Network:
    """Convert a torch module (``Sequential`` of ``Linear`` and activations) to a Network.

    Weights are copied as float64 (bit-exact for float64 modules). Modules that define a
    ``to_network()`` method (the project's own V and controller modules) convert themselves.

    Raises
    ------
    UnsupportedLayerError
        For a layer with no converter; the message names it and lists the supported ones.
    """
    if hasattr(module, "to_network"):
        return module.to_network()
    children = list(module.children()) if type(module).__name__ == "Sequential" else [module]
    layers: list[Layer] = []
    scale: float | np.ndarray = 1.0
    for mod in children:
        name = type(mod).__name__
        if name == "Scale" and hasattr(mod, "scale"):
            scale = mod.scale.detach().double().cpu().numpy()
            continue
        conv = TORCH_CONVERTERS.get(name)
        if conv is None:
            raise UnsupportedLayerError(
                f"no converter for torch layer {name}; supported layers: "
                f"{', '.join(sorted(TORCH_CONVERTERS))} (register one in "
                "nlyap_opt.kernel.network.TORCH_CONVERTERS)"
            )
        conv(mod, layers)
    return Network(layers, scale, dict(meta or {}))


def dense_network(sizes: Sequence[int], activation: str = "tanh", *, seed: int = 0,
                  output_scale=1.0) -> Network:
    """A randomly initialised network (Glorot-uniform), last layer linear.

    Parameters
    ----------
    sizes : sequence of int
        ``[n_in, hidden..., n_out]``.
    activation : str
        Activation of the hidden layers (a key of :data:`ACTIVATIONS`).
    seed : int
    output_scale : float or (n_out,) array_like
    """
    rng = np.random.default_rng(seed)
    layers = []
    for k in range(len(sizes) - 1):
        lim = math.sqrt(6.0 / (sizes[k] + sizes[k + 1]))
        w = rng.uniform(-lim, lim, (sizes[k + 1], sizes[k]))
        b = rng.uniform(-0.5, 0.5, sizes[k + 1])
        act = activation if k < len(sizes) - 2 else "linear"
        layers.append(Layer(w, b, act))
    return Network(layers, output_scale)
