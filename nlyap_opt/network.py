"""Feed-forward networks: a JSON format, exact CasADi graphs, torch conversion.

The JSON format (``"format": "nlyap-network"``, ``"version": 1``)::

    {"format": "nlyap-network", "version": 1, "input_dim": 2,
     "layers": [{"weight": [[...], ...], "bias": [...], "activation": "tanh"}, ...],
     "output_scale": 1.0,
     "meta": {...}}

``weight`` of layer ``k`` has shape ``(out_k, in_k)``; ``activation`` is one of
:data:`ACTIVATIONS`; ``output_scale`` (scalar or one per output) multiplies the last
layer's output (a controller ``u = C·tanh(Kx + b)`` is one tanh layer with scale ``C``).
Numbers are written with Python's shortest round-trip ``repr``, so float64 weights
survive save/load bit for bit; NaN and inf are refused.

The CasADi graph built by :meth:`Network.casadi` uses the float64 weights as exact
constants (dense ``mtimes`` nodes when called on ``MX``), so every consumer -- the NLP,
the interval verifier, dReal, SMT-LIB -- sees the very function that is saved.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import numpy as np

from .errors import DimensionError, NetworkFileError, UnsupportedLayerError

__all__ = [
    "Layer", "Network", "ACTIVATIONS", "TORCH_CONVERTERS", "from_torch", "load_network",
    "dense_network",
]

FORMAT = "nlyap-network"

#: output heads: ``sum_of_squares`` makes a Lyapunov candidate
#: ``V(z) = ||N(z) - N(0)||² + eps·||z||²`` (V(0) = 0 and V ≥ eps||z||² by construction)
HEADS = ("sum_of_squares",)


def _sigmoid(z):
    return 1.0 / (1.0 + ca.exp(-z))


#: activation name -> (CasADi function, torch function name)
ACTIVATIONS: dict[str, tuple[Callable, str]] = {
    "tanh": (ca.tanh, "tanh"),
    "relu": (lambda z: ca.fmax(z, 0), "relu"),
    "sigmoid": (_sigmoid, "sigmoid"),
    "linear": (lambda z: z, "identity"),
}


@dataclass
class Layer:
    """One dense layer ``activation(W z + b)``."""

    weight: np.ndarray
    bias: np.ndarray
    activation: str = "linear"

    def __post_init__(self):
        self.weight = np.array(self.weight, dtype=float, ndmin=2)
        self.bias = np.array(self.bias, dtype=float).reshape(-1)
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


@dataclass
class Network:
    """A feed-forward network of dense layers, with an optional output scale.

    Parameters
    ----------
    layers : list of Layer
    output_scale : float or (n_out,) array_like
    meta : dict
        Free-form metadata saved with the network (training settings, ...).

    Examples
    --------
    >>> import casadi as ca, numpy as np
    >>> net = Network([Layer([[1.0, 2.0]], [0.5], "tanh")], output_scale=5.0)
    >>> x = ca.SX.sym("x", 2)
    >>> float(ca.Function("k", [x], [net.casadi(x)])([0, 0]))  # 5 tanh(0.5)
    2.310585786300049
    """

    layers: list[Layer]
    output_scale: float | np.ndarray = 1.0
    meta: dict = field(default_factory=dict)
    head: dict | None = None

    def __post_init__(self):
        if self.head is not None:
            kind = self.head.get("type")
            if kind not in HEADS:
                raise UnsupportedLayerError(
                    f"network head {kind!r} is not supported; use one of {', '.join(HEADS)}"
                )
            eps = float(self.head.get("eps", 0.0))
            if not (math.isfinite(eps) and eps >= 0):
                raise NetworkFileError(f"head eps must be finite and >= 0, got {eps}")
            self.head = {"type": kind, "eps": eps}
        if not self.layers:
            raise DimensionError("a network needs at least one layer")
        for k in range(1, len(self.layers)):
            a, b = self.layers[k - 1], self.layers[k]
            if b.weight.shape[1] != a.weight.shape[0]:
                raise DimensionError(
                    f"layer {k} expects {b.weight.shape[1]} inputs but layer {k - 1} gives "
                    f"{a.weight.shape[0]} outputs"
                )
        scale = np.array(self.output_scale, dtype=float)
        if scale.ndim > 1 or (scale.ndim == 1 and scale.shape[0] != self.n_out):
            raise DimensionError(f"output_scale must be a scalar or have {self.n_out} entries")
        if not np.all(np.isfinite(scale)):
            raise NetworkFileError("output_scale must be finite")
        self.output_scale = scale

    @property
    def n_in(self) -> int:
        return self.layers[0].weight.shape[1]

    @property
    def n_out(self) -> int:
        return 1 if self.head else self.layers[-1].weight.shape[0]

    # ---------------------------------------------------------------- evaluation
    def casadi(self, z):
        """The network as a CasADi expression of ``z`` (SX or MX column of size ``n_in``)."""
        if z.shape != (self.n_in, 1):
            raise DimensionError(f"network input must have shape ({self.n_in}, 1), got {z.shape}")
        h = self._casadi_body(z)
        if self.head is None:
            return h
        # centred sum of squares: V(z) = ||N(z) - N(0)||² + eps ||z||², V(0) = 0 exactly.
        # N(0) is part of the graph (not a folded float), so V(0) = 0 in real arithmetic.
        zero = type(z)(ca.DM.zeros(self.n_in, 1)) if isinstance(z, ca.MX) else ca.SX.zeros(
            self.n_in, 1)
        y = h - self._casadi_body(zero)
        V = ca.sumsqr(y)
        if self.head["eps"]:
            V = V + self.head["eps"] * ca.sumsqr(z)
        return V

    def _casadi_body(self, z):
        h = z
        for layer in self.layers:
            h = ACTIVATIONS[layer.activation][0](ca.mtimes(ca.DM(layer.weight), h)
                                                 + ca.DM(layer.bias))
        if self.output_scale.ndim == 0:
            if float(self.output_scale) != 1.0:
                h = float(self.output_scale) * h
        else:
            h = ca.DM(self.output_scale) * h
        return h

    def function(self, name: str = "net", sym=ca.MX) -> ca.Function:
        """CasADi Function ``z -> network(z)`` (MX by default: matrix-level nodes)."""
        z = sym.sym("z", self.n_in)
        return ca.Function(name, [z], [self.casadi(z)])

    def numpy(self, z) -> np.ndarray:
        """Evaluate on a batch ``(N, n_in)`` in float64 numpy."""
        z = np.asarray(z, dtype=float)
        h = self._numpy_body(z)
        if self.head is None:
            return h
        y = h - self._numpy_body(np.zeros((1, self.n_in)))
        return (np.sum(y * y, axis=-1) + self.head["eps"] * np.sum(z * z, axis=-1))[..., None]

    def _numpy_body(self, h):
        for layer in self.layers:
            h = h @ layer.weight.T + layer.bias
            h = {"tanh": np.tanh, "relu": lambda v: np.maximum(v, 0.0),
                 "sigmoid": lambda v: 1.0 / (1.0 + np.exp(-v)),
                 "linear": lambda v: v}[layer.activation](h)
        return h * self.output_scale

    def torch_module(self, dtype=None):
        """A ``torch.nn.Sequential`` with these weights (float64 by default)."""
        import torch
        from torch import nn

        dtype = dtype or torch.float64
        mods = []
        for layer in self.layers:
            lin = nn.Linear(layer.weight.shape[1], layer.weight.shape[0]).to(dtype)
            with torch.no_grad():
                lin.weight.copy_(torch.as_tensor(layer.weight, dtype=dtype))
                lin.bias.copy_(torch.as_tensor(layer.bias, dtype=dtype))
            mods.append(lin)
            act = {"tanh": nn.Tanh, "relu": nn.ReLU, "sigmoid": nn.Sigmoid,
                   "linear": None}[layer.activation]
            if act is not None:
                mods.append(act())
        if self.output_scale.ndim > 0 or float(self.output_scale) != 1.0:
            mods.append(_Scale(torch.as_tensor(self.output_scale, dtype=dtype)))
        body = nn.Sequential(*mods)
        if self.head is None:
            return body
        return _make_head()(body, self.head["eps"])

    # ---------------------------------------------------------------- files
    def to_dict(self) -> dict:
        return {
            "format": FORMAT,
            "version": 1,
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
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.to_dict(), allow_nan=False, indent=1))
        return path

    @classmethod
    def from_dict(cls, d: dict, source: str = "network") -> Network:
        if not isinstance(d, dict) or "layers" not in d:
            raise NetworkFileError(
                f"{source}: expected a JSON object with a 'layers' list (format {FORMAT!r})"
            )
        if d.get("format", FORMAT) != FORMAT:
            raise NetworkFileError(f"{source}: format is {d.get('format')!r}, expected {FORMAT!r}")
        try:
            layers = []
            for k, ld in enumerate(d["layers"]):
                w = np.array(ld["weight"], dtype=float)
                b = np.array(ld["bias"], dtype=float)
                if w.ndim != 2:
                    raise NetworkFileError(f"{source}: layer {k} weight must be a 2-D list")
                if not (np.all(np.isfinite(w)) and np.all(np.isfinite(b))):
                    raise NetworkFileError(f"{source}: layer {k} has NaN or inf weights")
                layers.append(Layer(w, b, ld.get("activation", "linear")))
            net = cls(layers, d.get("output_scale", 1.0), dict(d.get("meta", {})),
                      d.get("head"))
        except (KeyError, TypeError) as err:
            raise NetworkFileError(f"{source}: malformed layer entry ({err})") from None
        if "input_dim" in d and int(d["input_dim"]) != net.n_in:
            raise NetworkFileError(
                f"{source}: input_dim is {d['input_dim']} but the first layer takes {net.n_in}"
            )
        return net

    @classmethod
    def load(cls, path: str | Path) -> Network:
        """Read a network JSON file (refuses NaN, inf, malformed layers)."""
        path = Path(path)
        try:
            text = path.read_text()
        except OSError as err:
            raise NetworkFileError(f"cannot read network file {path}: {err}") from None
        try:
            d = json.loads(text, parse_constant=_refuse_constant)
        except json.JSONDecodeError as err:
            raise NetworkFileError(f"{path} is not valid JSON: {err}") from None
        return cls.from_dict(d, str(path))


def _refuse_constant(name: str):
    raise NetworkFileError(f"network files may not contain {name}; weights must be finite")


def load_network(path: str | Path) -> Network:
    """Read a network JSON file; see :meth:`Network.load`."""
    return Network.load(path)


def _make_scale():
    from torch import nn

    class Scale(nn.Module):
        """Multiply by a constant (the network's output scale)."""

        def __init__(self, scale):
            super().__init__()
            self.register_buffer("scale", scale)

        def forward(self, h):
            return h * self.scale

    return Scale


def _make_head():
    import torch
    from torch import nn

    class CentredSumOfSquares(nn.Module):
        """``V(z) = ||body(z) - body(0)||² + eps ||z||²`` (the ``sum_of_squares`` head)."""

        def __init__(self, body, eps):
            super().__init__()
            self.body = body
            self.eps = float(eps)

        def forward(self, z):
            y = self.body(z) - self.body(torch.zeros_like(z[..., :1, :]))
            return (y * y).sum(-1, keepdim=True) + self.eps * (z * z).sum(-1, keepdim=True)

        def to_network(self):
            net = from_torch(self.body)
            return Network(net.layers, net.output_scale, {}, {"type": "sum_of_squares",
                                                                 "eps": self.eps})

    return CentredSumOfSquares


def _Scale(scale):  # noqa: N802 - behaves as a class
    global _SCALE_CLS
    if _SCALE_CLS is None:
        _SCALE_CLS = _make_scale()
    return _SCALE_CLS(scale)


_SCALE_CLS = None

# ----------------------------------------------------------------------------- torch -> Network
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


TORCH_CONVERTERS["Tanh"] = _activation("tanh")
TORCH_CONVERTERS["ReLU"] = _activation("relu")
TORCH_CONVERTERS["Sigmoid"] = _activation("sigmoid")
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
                "nlyap_opt.network.TORCH_CONVERTERS)"
            )
        conv(mod, layers)
    return Network(layers, scale, dict(meta or {}))


def dense_network(sizes: Sequence[int], activation: str = "tanh", *, seed: int = 0,
                  output_scale=1.0) -> Network:
    """A randomly initialised network (Glorot-uniform), last layer linear."""
    rng = np.random.default_rng(seed)
    layers = []
    for k in range(len(sizes) - 1):
        lim = math.sqrt(6.0 / (sizes[k] + sizes[k + 1]))
        w = rng.uniform(-lim, lim, (sizes[k + 1], sizes[k]))
        b = rng.uniform(-0.5, 0.5, sizes[k + 1])
        act = activation if k < len(sizes) - 2 else "linear"
        layers.append(Layer(w, b, act))
    return Network(layers, output_scale)
