"""System catalogue: CasADi dynamics with a registry.

Examples
--------
>>> import systems
>>> sorted(systems.names())
['inverted_pendulum', 'unicycle_path_following', 'van_der_pol']
>>> systems.get("van_der_pol").nx
2
"""

from __future__ import annotations

from collections.abc import Callable

from nlyap_opt.errors import UnknownNameError

from .base import System
from .catalogue import inverted_pendulum, unicycle_path_following, van_der_pol

__all__ = ["System", "get", "names", "register", "REGISTRY"]

REGISTRY: dict[str, Callable[..., System]] = {
    "van_der_pol": van_der_pol,
    "unicycle_path_following": unicycle_path_following,
    "inverted_pendulum": inverted_pendulum,
}


def register(name: str, factory: Callable[..., System]) -> None:
    """Add a system factory (a callable returning a :class:`System`) to the registry."""
    if name in REGISTRY:
        raise ValueError(f"a system named {name!r} is registered already")
    REGISTRY[name] = factory


def names() -> list[str]:
    """Names of the registered systems."""
    return list(REGISTRY)


def get(name: str, **params) -> System:
    """Build the registered system ``name`` with optional parameter overrides."""
    try:
        factory = REGISTRY[name]
    except KeyError:
        raise UnknownNameError(
            f"unknown system {name!r}; registered systems: {', '.join(REGISTRY)} "
            "(add one with systems.register)"
        ) from None
    return factory(**params)
