"""Domain errors and warnings of nlyap_opt.

Every error subclasses a builtin (``ValueError``, ``TypeError``, ``KeyError``,
``ImportError``, ``NotImplementedError``) so that ``except ValueError`` keeps
working, and every message says what was expected, what came, and what fixes it.
"""

from __future__ import annotations

__all__ = [
    "NlyapError",
    "DimensionError",
    "EquilibriumError",
    "EquilibriumWarning",
    "NotStabilizableError",
    "UnsupportedLayerError",
    "UnsupportedOperationError",
    "NetworkFileError",
    "UnknownNameError",
    "BackendUnavailableError",
    "InputRangeError",
    "ConfigError",
    "UsageError",
    "interruption",
    "raise_if_interrupted",
]


class NlyapError(Exception):
    """Base class of every error raised by nlyap_opt."""


class DimensionError(NlyapError, ValueError):
    """An array, expression or network has the wrong shape."""


class EquilibriumError(NlyapError, ValueError):
    """The origin is not an equilibrium where one is required (training, LQR)."""


class EquilibriumWarning(UserWarning):
    """The origin is not an equilibrium of a user's closed loop (verification goes on)."""


class NotStabilizableError(NlyapError, ValueError):
    """The linearisation ``(A, B)`` cannot be stabilised by state feedback."""


class UnsupportedLayerError(NlyapError, TypeError):
    """A torch module or network layer has no converter."""


class UnsupportedOperationError(NlyapError, NotImplementedError):
    """A CasADi operation is not supported by an arithmetic of the instruction walker."""


class NetworkFileError(NlyapError, ValueError):
    """A network JSON file is malformed (missing keys, bad shapes, NaN or inf)."""


class UnknownNameError(NlyapError, KeyError):
    """A name (system, backend, option) is not in its registry."""

    def __str__(self) -> str:  # KeyError would print the message in quotes
        return str(self.args[0]) if self.args else ""


class BackendUnavailableError(NlyapError, ImportError):
    """An optional backend (dReal, Dask) is not installed."""


class InputRangeError(NlyapError, ValueError):
    """The controller leaves the input box U on which the dynamics bound holds."""


class ConfigError(NlyapError, ValueError):
    """A configuration value is missing or out of range."""


class ArgumentTypeError(NlyapError, TypeError):
    """An argument of a public function is of the wrong type (a ``TypeError`` too)."""


class UsageError(NlyapError, ValueError):
    """A command-line argument or an input file is invalid (``nlyap`` exits with code 3)."""


def interruption(exc: BaseException) -> KeyboardInterrupt | None:
    """The :class:`KeyboardInterrupt` (Ctrl-C, or the CLI's ``--time-limit`` stop, a
    subclass) that ``exc`` is or that caused it, else ``None``.

    An interrupt raised while a C extension (CasADi's SWIG layer, a solver) runs can come
    out as another exception, e.g. ``SystemError: ... returned a result with an exception
    set``, with the interrupt as its cause or context: the chain is followed.
    """
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def raise_if_interrupted(exc: BaseException) -> None:
    """Raise the interrupt behind ``exc`` (:func:`interruption`), if any: a handler that
    turns failures into a fallback (``except Exception``: try the next solver) must not
    swallow a stop the user asked for."""
    stop = interruption(exc)
    if stop is not None:
        raise stop
