r"""What determines the numbers of a run: the numeric environment and its fingerprint.

A run is deterministic: the same input gives the same certificate, bit for bit. "The same
input" is the specification and configuration **and** the numeric environment that executes
them, because floating-point sums come out in a different order on different kernels:

- the versions of Python, CasADi, torch, numpy, SciPy, cvxpy, Clarabel, SCS and OSQP;
- the BLAS libraries numpy and SciPy load (OpenBLAS picks a kernel per CPU, e.g.
  ``Haswell`` or ``SkylakeX``; ``OPENBLAS_CORETYPE`` overrides the choice) and their thread
  counts;
- numpy's SIMD dispatch (``X86_V3`` = AVX2/FMA, ``X86_V4`` = AVX-512, ...) and torch's ATen
  CPU capability (``AVX2``, ``AVX512``), which pick different ``tanh``/``exp`` and reduction
  kernels;
- the CPU model and the instruction-set flags that those choices follow.

:func:`fingerprint` collects all of it (``certificate.json`` stores it under ``provenance``,
``report.md`` prints it) and :func:`fingerprint_id` hashes it. Verification does not depend
on any of it: the verifier's interval arithmetic rounds outward, so a certificate re-checks on
any machine. Training does: a learned φ or V may differ in its last bits between machines,
and a few Levenberg–Marquardt or Adam steps can amplify that into another network.

**Portable mode** (``nlyap run … --portable``) pins every numeric kernel that can be pinned
before numpy and torch load — :func:`portable_env` lists the variables — so that machines
with different x86-64 CPUs (AVX2 and FMA or better) run the same code paths. The CLI
re-executes itself with these variables set; from Python, set them in the environment before
the interpreter starts. The pins cost speed (AVX-512 kernels and BLAS threads are given up);
``bench/portable.py`` measures how much.

Examples
--------
>>> fp = fingerprint()
>>> sorted(fp)[:3]
['blas', 'cpu', 'numpy_dispatch']
>>> len(fingerprint_id(fp))
16
"""

from __future__ import annotations

import hashlib
import importlib
import json
import os
import platform
import sys
from functools import lru_cache
from importlib import metadata

from threadpoolctl import threadpool_info

from . import deps

try:
    from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
except ImportError:  # numpy < 2
    from numpy.core._multiarray_umath import __cpu_dispatch__, __cpu_features__

__all__ = ["PORTABLE_FLAG", "describe", "differences", "fingerprint", "fingerprint_id",
           "portable_env", "portable_problems"]

#: the environment variable that marks a process started in portable mode
PORTABLE_FLAG = "NLYAP_PORTABLE"

#: packages whose versions enter the numbers (missing ones are recorded as ``None``)
_PACKAGES = ("casadi", "torch", "numpy", "scipy", "cvxpy", "clarabel", "scs", "osqp",
             "threadpoolctl")

#: the CPU flags that select numeric kernels (SIMD width, fused multiply-add)
_ISA_FLAGS = ("sse4_2", "avx", "avx2", "fma", "f16c", "avx512f", "avx512dq", "avx512bw",
              "avx512vl", "avx512_vnni", "avx512_bf16", "avx512_fp16", "amx_tile", "amx_bf16")

#: the variables portable mode sets, and every variable that changes a numeric kernel
_PORTABLE = {
    # OpenBLAS (numpy's and SciPy's): the AVX2 kernel, one thread (a split dot product sums
    # in another order)
    "OPENBLAS_CORETYPE": "Haswell",
    "OPENBLAS_NUM_THREADS": "1",
    # numpy: no dispatch above X86_V3 (AVX2 + FMA3); naming a target the CPU lacks is harmless
    "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR",
    # torch: ATen's vectorised kernels, oneDNN and MKL on their AVX2 code paths
    "ATEN_CPU_CAPABILITY": "avx2",
    "DNNL_MAX_CPU_ISA": "AVX2",
    "MKL_CBWR": "AVX2,STRICT",
    "MKL_ENABLE_INSTRUCTIONS": "AVX2",
    PORTABLE_FLAG: "1",
}
_NUMERIC_ENV = tuple(_PORTABLE) + ("OMP_NUM_THREADS", "MKL_NUM_THREADS",
                                   "NPY_ENABLE_CPU_FEATURES")


def portable_env() -> dict[str, str]:
    """The environment variables portable mode sets (a copy).

    They take effect only in a process that starts with them: numpy, SciPy and torch read
    them when they load.

    Returns
    -------
    dict of str to str
        Variable name to value.
    """
    return dict(_PORTABLE)


def _cpu() -> dict:
    """CPU model and the kernel-selecting ISA flags (from ``/proc/cpuinfo`` on Linux)."""
    info = {"machine": platform.machine(), "model": platform.processor() or None,
            "vendor": None, "flags": []}
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as fh:
            text = fh.read()
    except OSError:
        return info
    first = text.split("\n\n", 1)[0]
    fields = {}
    for line in first.splitlines():
        key, sep, value = line.partition(":")
        if sep:
            fields[key.strip()] = value.strip()
    info["model"] = fields.get("model name", info["model"])
    info["vendor"] = fields.get("vendor_id")
    info["family_model"] = f"{fields.get('cpu family', '?')}/{fields.get('model', '?')}"
    flags = set(fields.get("flags", "").split())
    info["flags"] = [f for f in _ISA_FLAGS if f in flags]
    return info


#: modules whose BLAS libraries the pipeline calls: loaded before the libraries are listed,
#: so that the list does not depend on what the process imported first (a re-check that
#: never imports the SDP solvers would otherwise list fewer libraries than the run)
_BLAS_MODULES = ("numpy", "scipy.linalg", "scs")


def _blas() -> list[dict]:
    """The BLAS libraries of numpy, SciPy and the SDP solver SCS: library, version, kernel
    and threads."""
    for name in _BLAS_MODULES:
        try:
            importlib.import_module(name)
        except ImportError:  # an optional solver that is not installed lists nothing
            pass
    out = []
    for lib in threadpool_info():
        if lib.get("user_api") != "blas":
            continue
        out.append({"library": lib.get("internal_api"), "prefix": lib.get("prefix"),
                    "version": lib.get("version"), "kernel": lib.get("architecture"),
                    "threads": lib.get("num_threads")})
    return sorted(out, key=lambda d: json.dumps(d, sort_keys=True))


def _numpy_dispatch() -> list[str]:
    """numpy's SIMD dispatch targets that run on this machine."""
    return [t for t in __cpu_dispatch__ if __cpu_features__.get(t)]


def _torch() -> dict:
    torch = deps.torch()

    return {"cpu_capability": torch.backends.cpu.get_cpu_capability(),
            "mkl": bool(torch.backends.mkl.is_available()),
            "mkldnn": bool(torch.backends.mkldnn.is_available())}


def _version(pkg: str) -> str | None:
    try:
        return metadata.version(pkg)
    except metadata.PackageNotFoundError:
        return None


@lru_cache(maxsize=1)
def _fingerprint_json() -> str:
    fp = {
        "python": platform.python_version(),
        "implementation": sys.implementation.name,
        "versions": {p: _version(p) for p in _PACKAGES},
        "cpu": _cpu(),
        "blas": _blas(),
        "numpy_dispatch": _numpy_dispatch(),
        "torch": _torch(),
        "environment": {k: os.environ[k] for k in _NUMERIC_ENV if k in os.environ},
        "portable": os.environ.get(PORTABLE_FLAG) == "1",
    }
    return json.dumps(fp, sort_keys=True)


def fingerprint() -> dict:
    """The numeric environment of this process (what determines the numbers of a run).

    Returns
    -------
    dict
        ``python``, ``implementation``, ``versions`` (package → version), ``cpu`` (machine,
        model, vendor, family/model, ISA flags), ``blas`` (numpy's and SciPy's BLAS
        libraries: version, kernel, threads), ``numpy_dispatch`` (SIMD targets in use),
        ``torch`` (ATen CPU capability, MKL, oneDNN), ``environment`` (the kernel-selecting
        variables that are set) and ``portable`` (started in portable mode).
    """
    return json.loads(_fingerprint_json())


def fingerprint_id(fp: dict | None = None) -> str:
    """A 16-hex-digit hash of :func:`fingerprint` (or of ``fp``): equal ids, same numbers.

    Thread counts (BLAS threads, ``*_NUM_THREADS``) are recorded but not hashed: a run
    gives the same bytes with one or two BLAS threads (tested), and Dask workers, which
    start with one thread, must find the stages their parent computed.
    """
    fp = json.loads(json.dumps(fingerprint() if fp is None else fp))
    for lib in fp.get("blas", []):
        lib.pop("threads", None)
    fp["environment"] = {k: v for k, v in fp.get("environment", {}).items()
                         if not k.endswith("_NUM_THREADS")}
    return hashlib.sha256(json.dumps(fp, sort_keys=True).encode()).hexdigest()[:16]


def portable_problems(fp: dict | None = None) -> list[str]:
    """Why this process does not run on the portable code paths (empty: it does).

    Portable mode needs an x86-64 CPU with AVX2 and FMA, and the pins must have reached
    numpy, OpenBLAS and torch (they act only in a process that starts with them).
    """
    fp = fingerprint() if fp is None else fp
    problems = []
    cpu = fp["cpu"]
    if cpu.get("machine") not in ("x86_64", "AMD64"):
        problems.append(f"the CPU is {cpu.get('machine')}, not x86-64")
    elif not {"avx2", "fma"} <= set(cpu.get("flags", [])):
        problems.append("the CPU lacks AVX2 or FMA")
    if any(t in fp["numpy_dispatch"] for t in ("X86_V4", "AVX512_ICL", "AVX512_SPR")):
        problems.append(f"numpy dispatches to {fp['numpy_dispatch']}")
    for lib in fp["blas"]:
        if lib["library"] == "openblas" and (lib["kernel"] or "").lower() != "haswell":
            problems.append(f"OpenBLAS ({lib['prefix']}) runs the {lib['kernel']} kernel")
        if lib["library"] == "openblas" and lib["threads"] != 1:
            problems.append(f"OpenBLAS ({lib['prefix']}) runs {lib['threads']} threads")
    if str(fp["torch"]["cpu_capability"]).upper() != "AVX2":
        problems.append(f"torch's CPU capability is {fp['torch']['cpu_capability']}")
    return problems


def differences(stored: dict | None, current: dict | None = None) -> list[str]:
    """The top-level parts of two fingerprints that differ (``["cpu", "versions", ...]``).

    ``stored`` ``None`` (a certificate written before fingerprints were recorded) gives
    ``["unknown"]``.
    """
    current = fingerprint() if current is None else current
    if not isinstance(stored, dict):
        return ["unknown"]
    return sorted(k for k in set(stored) | set(current) if stored.get(k) != current.get(k))


def describe(fp: dict) -> list[str]:
    """Markdown bullet lines of a fingerprint, for ``report.md``."""
    cpu, t = fp.get("cpu", {}), fp.get("torch", {})
    blas = "; ".join(f"{b.get('prefix')} {b.get('version')} kernel {b.get('kernel')}, "
                     f"{b.get('threads')} threads" for b in fp.get("blas", []))
    env = ", ".join(f"{k}={v}" for k, v in sorted(fp.get("environment", {}).items())) or "none"
    vers = ", ".join(f"{k} {v}" for k, v in sorted(fp.get("versions", {}).items()) if v)
    return [
        f"- fingerprint: {fingerprint_id(fp)}" + (" (portable mode)" if fp.get("portable")
                                                   else ""),
        f"- CPU: {cpu.get('model')} ({cpu.get('vendor')}, {cpu.get('machine')}); "
        f"ISA: {' '.join(cpu.get('flags', []))}",
        f"- Python {fp.get('python')}; {vers}",
        f"- BLAS: {blas}",
        f"- numpy SIMD dispatch: {' '.join(fp.get('numpy_dispatch', [])) or 'baseline'}; "
        f"torch CPU capability: {t.get('cpu_capability')}",
        f"- kernel-selecting variables: {env}",
    ]
