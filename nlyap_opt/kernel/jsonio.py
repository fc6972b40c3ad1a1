"""Reading configuration and data files, and keeping wall-clock timings out of hashed
artifacts.

A core module (it imports only :mod:`nlyap_opt.kernel.errors`), so that every layer that reads a
configuration file (the run configuration, the dynamics configuration) shares one reader.

A run's stage files (``bounds.json``, ``cegis.json``, ...) are hashed: the hashes key the
stages built on them and bind the certificate to its artifacts. Wall-clock timings would make
those hashes differ between two runs of the same input, so :func:`split_timings` takes every
``seconds`` / ``*_seconds`` entry out before such a file is written and
:func:`save_timings` keeps them, for the report, in ``timings.json`` beside it (never
hashed, never trusted for anything but display); :func:`load_with_timings` puts them back.
"""

from __future__ import annotations

import io
import json
import math
import os
import secrets
import stat
import zipfile
from pathlib import Path

import numpy as np

from .errors import ConfigError

__all__ = ["MAX_INPUT_BYTES", "TIMINGS_FILE", "load_with_timings", "read_file_bytes",
           "read_json_object", "read_npz", "save_timings", "split_timings"]

#: the largest file any reader of this package reads (a spec, sample, network, configuration
#: or certificate file): a larger one is refused before it fills the memory
MAX_INPUT_BYTES = 1 << 30


def read_file_bytes(path: str | Path, what: str, limit: int = MAX_INPUT_BYTES) -> bytes:
    """The bytes of the regular file ``path`` (symbolic links followed).

    A pipe, device or socket is refused without waiting on it (it is opened non-blocking
    and checked before any read), and so is a file of more than ``limit`` bytes.

    Raises
    ------
    ConfigError
        Not a regular file, or too large (naming ``what`` and the path).
    OSError
        The file is missing or unreadable (callers say so in their own words).
    """
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise IsADirectoryError(21, "Is a directory", str(path))
        if not stat.S_ISREG(st.st_mode):
            raise ConfigError(f"{what} {path} is not a regular file (a pipe, device or "
                              "socket); pass a file")
        if st.st_size > limit:
            raise ConfigError(f"{what} {path} holds {st.st_size} bytes, more than the "
                              f"{limit} this tool reads; pass the right file")
        chunks, size = [], 0
        while True:
            b = os.read(fd, 1 << 20)
            if not b:
                break
            chunks.append(b)
            size += len(b)
            if size > limit:
                raise ConfigError(f"{what} {path} grows past the {limit} bytes this tool "
                                  "reads; pass a finished file")
        return b"".join(chunks)
    finally:
        os.close(fd)

#: the most arrays :func:`read_npz` reads from one file
MAX_NPZ_ARRAYS = 1 << 14

_NPY_HEADERS = {(1, 0): np.lib.format.read_array_header_1_0,
                (2, 0): np.lib.format.read_array_header_2_0}


def read_npz(path: str | Path, what: str, fix: str, *, limit: int = MAX_INPUT_BYTES,
             not_npz_fix: str | None = None) -> dict[str, np.ndarray]:
    """The arrays of an ``.npz`` file (``numpy.savez``), none of its sizes trusted.

    The file is read by :func:`read_file_bytes` (a regular file of at most ``limit``
    bytes). Every entry must be an unencrypted ``.npy`` file, stored or deflated (what
    numpy writes), of a type without Python objects, whose declared shape fits the bytes
    the zip declares for it; the declared sizes together are at most ``limit``. Only then
    is an array unpacked (``allow_pickle=False``).

    Parameters
    ----------
    path : str or Path
    what : str
        The kind of file, for messages (``"proof file"``).
    fix : str
        What the user can do, appended to every message.
    limit : int, optional
        Bytes, on the file and on its arrays together.
    not_npz_fix : str, optional
        The fix for a file that is no zip archive at all (default ``fix``).

    Returns
    -------
    dict
        Array name (without ``.npy``) to array.

    Raises
    ------
    ConfigError
        Anything above, or an archive that cannot be read (one line each).
    OSError
        The file is missing or unreadable.
    """
    data = read_file_bytes(path, what, limit)
    if not data.startswith((b"PK\x03\x04", b"PK\x05\x06")):  # numpy.savez writes a zip
        kind = "text" if data[:512].isascii() else "binary data"
        raise ConfigError(f"{path}: is not an npz file (an npz is a zip archive; this file "
                          f"holds {kind}); {not_npz_fix or fix}")
    out: dict[str, np.ndarray] = {}
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            infos = zf.infolist()
            if len(infos) > MAX_NPZ_ARRAYS or sum(i.file_size for i in infos) > limit:
                raise ConfigError(f"{path}: holds more arrays or bytes than a {what} of "
                                  f"this tool does; {fix}")
            for info in infos:
                if info.flag_bits & 1 or info.compress_type not in (
                        zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED) or \
                        not info.filename.endswith(".npy"):
                    raise ConfigError(f"{path}: entry {info.filename!r} is not an array as "
                                      f"numpy.savez writes one; {fix}")
                with zf.open(info) as fh:
                    header = _NPY_HEADERS.get(np.lib.format.read_magic(fh))
                    if header is None:
                        raise ConfigError(f"{path}: entry {info.filename!r} has a .npy "
                                          f"format version this tool does not read; {fix}")
                    shape, _, dtype = header(fh)
                    if dtype.hasobject or \
                            math.prod(shape) * dtype.itemsize > info.file_size:
                        raise ConfigError(f"{path}: entry {info.filename!r} declares more "
                                          f"data than it holds, or Python objects; {fix}")
                with zf.open(info) as fh:
                    out[info.filename[:-4]] = np.lib.format.read_array(fh, allow_pickle=False)
    except ConfigError:
        raise
    except Exception as exc:  # noqa: BLE001 - zipfile, zlib and format errors alike
        msg = " ".join(str(exc).split())[:200]
        raise ConfigError(f"{path}: cannot be read as an {what} (truncated or corrupt: "
                          f"{type(exc).__name__}{': ' + msg if msg else ''}); {fix}") from None
    return out


#: the file beside a run's stage files that holds their wall-clock timings
TIMINGS_FILE = "timings.json"


def write_atomic(path: str | Path, data: str | bytes) -> Path:
    """Write ``data`` (text as UTF-8) to ``path`` through a new file beside it and a rename.

    The file at ``path`` is then either the old one or the whole new one, never half written
    (a full disk, an interrupt or a crash leaves the old file: the new one is synced before
    the rename); a symbolic link at ``path`` is replaced, not written through (the file it
    points to is left alone). The new file keeps the old one's permissions, or gets those
    of a plain write (``0o666`` less the umask).

    Raises
    ------
    ConfigError
        ``path`` is a directory, a pipe, a device or a socket, or a symbolic link to one
        (naming it).
    OSError
        The write or the rename failed (the new file is removed); callers name the option
        or the output in their own words.
    """
    return write_files_atomic({path: data})[0]


def _target_mode(path: Path) -> int | None:
    """The permission bits a new file at ``path`` keeps (``None``: a plain write's), after
    refusing what is not a place for a file."""
    try:
        mode = os.lstat(path).st_mode
    except (FileNotFoundError, NotADirectoryError):   # open() says what is wrong
        return None
    if stat.S_ISLNK(mode):
        try:
            mode = os.stat(path).st_mode    # what it points to: replaced only if a file
        except OSError:
            return None                     # a dangling link: replaced
    if not stat.S_ISREG(mode):
        kind = "a directory" if stat.S_ISDIR(mode) else \
            "not a regular file (a pipe, device or socket)"
        raise ConfigError(f"{path} is {kind}; give the path of a file to write")
    return stat.S_IMODE(mode)


def write_files_atomic(files: dict) -> list[Path]:
    """:func:`write_atomic` for files that belong together (``{path: data}``): every new
    file is written before the first rename, so that a failed write (a full disk) leaves
    all the old files; only a rename failing midway could leave some of them new."""
    paths = [Path(p) for p in files]
    modes = [_target_mode(p) for p in paths]
    temps: list[Path] = []
    try:
        for path, mode, data in zip(paths, modes, files.values()):
            # the name stays short: a long output name must not become too long a name here
            tmp = path.with_name(f".{path.name[:100]}.{secrets.token_hex(4)}.tmp")
            with open(tmp, "xb") as fh:
                temps.append(tmp)
                fh.write(data.encode("utf-8") if isinstance(data, str) else bytes(data))
                fh.flush()
                os.fsync(fh.fileno())
            if mode is not None:
                os.chmod(tmp, mode)
        for tmp, path in zip(list(temps), paths):
            os.replace(tmp, path)
            temps.remove(tmp)
    finally:
        for tmp in temps:
            try:
                os.unlink(tmp)
            except OSError:
                pass
    return paths


def write_figure(fig, path: str | Path, dpi: int = 110) -> Path:
    """A Matplotlib figure written to ``path`` by :func:`write_atomic`, in the format of its
    suffix (PNG without one)."""
    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi, format=Path(path).suffix[1:].lower() or "png")
    return write_atomic(path, buf.getvalue())


def _is_timing(key) -> bool:
    return isinstance(key, str) and (key == "seconds" or key.endswith("_seconds"))


def split_timings(obj, _path: tuple = ()) -> tuple[object, list]:
    """``(obj without its timings, [[path, value], ...])``: every dict entry named
    ``seconds`` or ``*_seconds``, at any depth, is taken out with its path (keys and list
    indices) so that :func:`load_with_timings` can put it back.

    Examples
    --------
    >>> split_timings({"level": 1.0, "history": [{"it": 0, "verify_seconds": 0.3}]})
    ({'level': 1.0, 'history': [{'it': 0}]}, [[['history', 0, 'verify_seconds'], 0.3]])
    """
    if isinstance(obj, dict):
        clean, found = {}, []
        for k, v in obj.items():
            if _is_timing(k):
                found.append([[*_path, k], v])
            else:
                clean[k], sub = split_timings(v, (*_path, k))
                found += sub
        return clean, found
    if isinstance(obj, (list, tuple)):
        clean, found = [], []
        for i, v in enumerate(obj):
            c, sub = split_timings(v, (*_path, i))
            clean.append(c)
            found += sub
        return clean, found
    return obj, []


def save_timings(path: str | Path, timings: list) -> None:
    """Keep the timings :func:`split_timings` took out of the file ``path`` in
    ``timings.json`` beside it (written through a temporary file and a rename)."""
    path = Path(path)
    tfile = path.parent / TIMINGS_FILE
    try:
        store = json.loads(tfile.read_text())
        if not isinstance(store, dict):
            store = {}
    except (OSError, ValueError):
        store = {}
    store[path.name] = timings
    write_atomic(tfile, json.dumps(store, indent=1))


def load_with_timings(path: str | Path) -> dict:
    """The JSON file ``path`` with its timings from ``timings.json`` put back where they
    were (timings that are missing or do not fit are left out: they are only displayed)."""
    path = Path(path)
    obj = json.loads(path.read_text())
    try:
        timings = json.loads((path.parent / TIMINGS_FILE).read_text()).get(path.name, [])
    except (OSError, ValueError, AttributeError):
        return obj
    for entry in timings if isinstance(timings, list) else []:
        try:
            keys, value = entry
            node = obj
            for k in keys[:-1]:
                node = node[k]
            if isinstance(node, dict) and isinstance(keys[-1], str):
                node[keys[-1]] = value
        except (KeyError, IndexError, TypeError, ValueError):
            continue
    return obj


def _unique_keys(pairs: list) -> dict:
    """A JSON object whose keys are all different (a key given twice is refused: JSON
    readers disagree on which value wins)."""
    seen: dict = {}
    for k, v in pairs:
        if k in seen:
            raise ConfigError(f"key {k!r} appears twice in one object; keep one")
        seen[k] = v
    return seen


def read_json_object(path: str | Path, what: str = "config") -> dict:
    """A configuration file: a JSON object (else :class:`ConfigError` saying why).

    Parameters
    ----------
    path : str or Path
    what : str
        What the file is, as messages name it (default ``"config"``).

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
        raise ConfigError(f"{what} {path} is a directory; pass the JSON file inside it")
    try:
        data = read_file_bytes(p, what)
    except OSError as err:
        raise ConfigError(f"cannot read {what} {path}: {err.strerror or err}; "
                          "check the path") from None
    try:
        obj = json.loads(data.decode("utf-8"), object_pairs_hook=_unique_keys)
    except RecursionError:
        raise ConfigError(f"{what} {path} is nested too deeply to read; fix the file") \
            from None
    except UnicodeDecodeError:
        raise ConfigError(f"{what} {path} is not a text file; pass a JSON file") from None
    except json.JSONDecodeError as err:
        raise ConfigError(f"{what} {path} is not valid JSON ({err}); fix the file") from None
    except ConfigError as err:
        raise ConfigError(f"{what} {path}: {err}") from None
    except ValueError as err:  # an integer of thousands of digits (Python's own limit)
        raise ConfigError(f"{what} {path} cannot be read ({' '.join(str(err).split())[:120]}); "
                          "fix the file") from None
    if not isinstance(obj, dict):
        raise ConfigError(f"{what} {path} must hold a JSON object {{...}}, "
                          f"got a {type(obj).__name__}")
    return obj
