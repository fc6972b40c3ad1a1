"""Systems: CasADi models, black-box callables and sample files, a registry, spec files.

A :class:`System` is a CasADi model (``kind == "model"``), a black-box batched callable
(:meth:`System.from_callable`) or samples on a regular grid (:meth:`System.from_samples`,
:func:`load_samples`); :func:`load_spec` reads a TOML spec file. Assumptions about an
unknown ``f`` are :class:`Declarations`, checked against data by :func:`check_declarations`.

Examples
--------
>>> import systems
>>> sorted(systems.names())  # doctest: +NORMALIZE_WHITESPACE
['cartpole', 'inverted_pendulum', 'lyznet_10d', 'lyznet_chain', 'planar_quadrotor',
 'unicycle_path_following', 'van_der_pol']
>>> systems.get("van_der_pol").nx
2
"""

from __future__ import annotations

import inspect
import os
from collections.abc import Callable

from nlyap_opt.kernel.errors import (
    ArgumentTypeError,
    ConfigError,
    NlyapError,
    UnknownNameError,
)

from .base import ModelUnavailableError, System
from .catalogue import (
    cartpole,
    inverted_pendulum,
    lyznet_10d,
    lyznet_chain,
    planar_quadrotor,
    unicycle_path_following,
    van_der_pol,
)
from .declarations import Declarations, check_declarations
from .jacobian import JacobianBound, jacobian_from_data
from .samples import SampleSet, load_samples, sample_function, save_samples
from .spec import check_spec
from .spec import default_run_settings as _default
from .spec import load_spec as _load_spec

__all__ = ["System", "SEED_SYSTEMS", "get", "names", "register", "REGISTRY", "CATALOGUE",
           "ModelUnavailableError",
           "Declarations", "check_declarations", "SampleSet", "load_samples", "save_samples",
           "sample_function", "load_spec", "check_spec", "default_run_settings", "JacobianBound",
           "jacobian_from_data"]

REGISTRY: dict[str, Callable[..., System]] = {
    "van_der_pol": van_der_pol,
    "unicycle_path_following": unicycle_path_following,
    "inverted_pendulum": inverted_pendulum,
    "cartpole": cartpole,
    "planar_quadrotor": planar_quadrotor,
    "lyznet_10d": lyznet_10d,
    "lyznet_chain": lyznet_chain,
}
#: the built-in catalogue's names (a spec file may not reuse them)
CATALOGUE = tuple(REGISTRY)

#: the paper's 2-D seed systems: what the default test suite and benchmarks iterate over
#: (the 4-D / 6-D catalogue systems have their own tests, ``tests/test_highdim.py``)
SEED_SYSTEMS = ("van_der_pol", "unicycle_path_following", "inverted_pendulum")


def register(name: str, factory: Callable[..., System]) -> None:
    """Add a system factory (a callable returning a :class:`System`) to the registry."""
    if name in REGISTRY:
        raise ValueError(f"a system named {name!r} is registered already")
    if not callable(factory):
        raise ConfigError(f"register({name!r}, factory): factory must be a callable "
                          f"returning a System, got {type(factory).__name__} (for a System s, "
                          "pass lambda: s)")
    REGISTRY[name] = factory


def names() -> list[str]:
    """Names of the registered systems."""
    return list(REGISTRY)


def get(name: str, **params) -> System:
    """Build the registered system ``name`` with optional parameter overrides."""
    try:
        factory = REGISTRY[name]
    except (KeyError, TypeError):   # TypeError: an unhashable name
        raise UnknownNameError(
            f"unknown system {name!r}; registered systems: {', '.join(REGISTRY)} "
            "(add one with systems.register)"
        ) from None
    if not params:
        return factory()
    try:
        sig = inspect.signature(factory)
        sig.bind(**params)
    except TypeError as err:   # a parameter the factory does not take
        raise ConfigError(f"system {name!r} takes the parameters "
                          f"{', '.join(sig.parameters) or 'none'}; {err}") from None
    except ValueError:         # no signature to read: the call says
        pass
    try:
        return factory(**params)
    except (TypeError, ValueError) as err:   # e.g. a text where a number belongs
        if isinstance(err, NlyapError):
            raise
        raise ConfigError(f"system {name!r} cannot be built with {params}: "
                          f"{' '.join(str(err).split())}; pass numbers for its "
                          "parameters") from None


def load_spec(path, *, allow_factory: bool = True) -> System:
    """Build a :class:`System` from a TOML spec file (:func:`systems.spec.load_spec`;
    ``allow_factory=False`` refuses a spec whose system is Python code).

    Imports SymPy (the expression parser) only when called.
    """
    if isinstance(path, bytes) or not isinstance(path, (str, os.PathLike)):
        raise ArgumentTypeError(f"load_spec needs the path of a spec file (a str or "
                                f"pathlib.Path), got {path!r}")

    return _load_spec(path, allow_factory=allow_factory)


def default_run_settings(system: System) -> dict:
    """Proposed run settings from a system's box (:func:`systems.spec.default_run_settings`)."""

    return _default(system)
