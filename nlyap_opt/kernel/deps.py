"""The heavy and optional dependencies, imported on first use.

``import nlyap_opt`` and the certificate kernel load neither torch nor the packages that take
a second or more to import and serve one feature (cvxpy for SOS and LipSDP, python-control,
Dask, matplotlib, osqp) nor the optional dreal backend; every module that needs one asks this
module for it, so these are the only imports of the package inside functions. A missing
package raises the :class:`ImportError` of its import (callers that can do without it catch
that).
"""

from __future__ import annotations

from types import ModuleType

__all__ = ["control", "cvxpy", "dask", "distributed", "dreal", "osqp", "pyplot", "torch",
           "tqdm"]


def torch() -> ModuleType:
    """``torch`` (training, tensors, ONNX export)."""
    import torch  # lazy: torch, heavy (seconds to import)

    return torch


def cvxpy() -> ModuleType:
    """``cvxpy`` (SOS programs, LipSDP, the round Lyapunov matrix)."""
    import cvxpy  # lazy: cvxpy, heavy and only for SDPs

    return cvxpy


def control() -> ModuleType:
    """python-control (LQR and Lyapunov equations)."""
    import control  # lazy: python-control, heavy (loads scipy.signal)

    return control


def pyplot() -> ModuleType:
    """``matplotlib.pyplot`` on the non-interactive Agg backend (figures written to files)."""
    import matplotlib  # lazy: matplotlib, heavy and only for figures

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: matplotlib, heavy and only for figures

    return plt


def dask() -> ModuleType:
    """``dask`` (its configuration for the local cluster)."""
    import dask  # lazy: dask, heavy and only for clusters

    return dask


def distributed() -> ModuleType:
    """``distributed`` (Dask clusters, scheduler handshake, rpc)."""
    import distributed  # lazy: distributed, heavy and only for clusters

    return distributed


def osqp() -> ModuleType:
    """``osqp`` (the CLF-QP safety filter)."""
    import osqp  # lazy: osqp, heavy and only for deploy's filter

    return osqp


def dreal() -> ModuleType:
    """``dreal`` (the optional delta-complete backend)."""
    import dreal  # lazy: dreal, optional backend

    return dreal


def tqdm():
    """``tqdm.auto.tqdm`` (progress bars)."""
    from tqdm.auto import tqdm  # lazy: tqdm.auto, probes for notebooks; progress bars only

    return tqdm

