"""nlyap_opt: neural Lyapunov control of unknown nonlinear systems, with certified ROAs.

Public API (what users type); the machinery lives in the submodules.
"""

from .errors import (
    BackendUnavailableError,
    DimensionError,
    EquilibriumError,
    InputRangeError,
    NetworkFileError,
    NlyapError,
    NotStabilizableError,
    UnknownNameError,
    UnsupportedLayerError,
    UnsupportedOperationError,
)
from .network import Layer, Network, from_torch, load_network
from .symbolic import closed_loop, lie_derivative
from .walker import evaluate

__version__ = "0.1.0"

__all__ = [
    "Layer", "Network", "from_torch", "load_network", "closed_loop", "lie_derivative",
    "evaluate", "NlyapError", "DimensionError", "EquilibriumError", "InputRangeError",
    "NetworkFileError", "NotStabilizableError", "UnknownNameError", "UnsupportedLayerError",
    "UnsupportedOperationError", "BackendUnavailableError", "__version__",
]
