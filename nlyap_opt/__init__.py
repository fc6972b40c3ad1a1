"""nlyap_opt: neural Lyapunov control of unknown nonlinear systems, with certified ROAs.

Public API (what users type); the machinery lives in the submodules.

- a whole run: :func:`run` (the pipeline; ``nlyap run``) with :func:`make_config`;
- a certificate: :class:`RoaProblem`, :func:`certify_roa`, :func:`recheck_certificate`,
  :class:`CertStatus`;
- errors: :class:`NlyapError` and its subclasses, :class:`ConfigError` for bad user input.

Every public name except the errors loads its module on first use (module
``__getattr__``), so that ``import nlyap_opt`` stays light (the ``nlyap`` command guards
the heavy imports against Ctrl-C: :mod:`nlyap_opt.interface.entry`).
"""

import importlib

from .kernel.errors import (
    ArgumentTypeError,
    BackendUnavailableError,
    ConfigError,
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

__version__ = "0.1.0"

__all__ = [
    "Layer", "Network", "from_torch", "load_network", "closed_loop", "lie_derivative",
    "evaluate", "NlyapError", "DimensionError", "EquilibriumError", "InputRangeError",
    "NetworkFileError", "NotStabilizableError", "UnknownNameError", "UnsupportedLayerError",
    "UnsupportedOperationError", "BackendUnavailableError", "ConfigError", "ArgumentTypeError",
    "__version__",
    "run", "make_config", "RoaProblem", "certify_roa", "recheck_certificate", "CertStatus",
]

#: the public names loaded on first use: name -> the module that defines it
_LAZY = {
    "Layer": "nlyap_opt.kernel.network",
    "Network": "nlyap_opt.kernel.network",
    "from_torch": "nlyap_opt.kernel.network",
    "load_network": "nlyap_opt.kernel.network",
    "closed_loop": "nlyap_opt.kernel.symbolic",
    "lie_derivative": "nlyap_opt.kernel.symbolic",
    "evaluate": "nlyap_opt.kernel.walker",
    "run": "nlyap_opt.workflow.pipeline",
    "make_config": "nlyap_opt.workflow.configs",
    "RoaProblem": "nlyap_opt.certification.certificate",
    "certify_roa": "nlyap_opt.certification.certificate",
    "recheck_certificate": "nlyap_opt.certification.certificate",
    "CertStatus": "nlyap_opt.certification.certificate",
}


def __getattr__(name: str):
    """Import the module of a lazy public name on first access (PEP 562)."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'nlyap_opt' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
