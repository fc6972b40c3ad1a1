"""Reading configuration files: a JSON object, or a :class:`ConfigError` saying why not.

A core module (it imports only :mod:`nlyap_opt.errors`), so that every layer that reads a
configuration file (the run configuration, the dynamics configuration) shares one reader.
"""

from __future__ import annotations

import json
from pathlib import Path

from .errors import ConfigError

__all__ = ["read_json_object"]


def read_json_object(path: str | Path) -> dict:
    """A configuration file: a JSON object (else :class:`ConfigError` saying why).

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    dict

    Raises
    ------
    ConfigError
        The file is missing, a directory, unreadable, not text, not valid JSON, or not an
        object.
    """
    p = Path(path)
    if p.is_dir():
        raise ConfigError(f"config {path} is a directory; pass the JSON file inside it")
    try:
        obj = json.loads(p.read_text())
    except OSError as err:
        raise ConfigError(f"cannot read config {path}: {err.strerror or err}; "
                          "check the path") from None
    except UnicodeDecodeError:
        raise ConfigError(f"config {path} is not a text file; pass a JSON file") from None
    except json.JSONDecodeError as err:
        raise ConfigError(f"config {path} is not valid JSON ({err}); fix the file") from None
    if not isinstance(obj, dict):
        raise ConfigError(f"config {path} must hold a JSON object {{...}}, "
                          f"got a {type(obj).__name__}")
    return obj
