"""Baselines: LQR (quadratic V), SOS, the neural method on the true dynamics."""

from .lqr import (
    LQRResult,
    linear_controller,
    lqr,
    lyapunov_matrix,
    quadratic_lyapunov,
    saturated_controller,
)
from .sos import SOSResult, sos_roa

__all__ = ["LQRResult", "lqr", "lyapunov_matrix", "saturated_controller", "linear_controller",
           "quadratic_lyapunov", "SOSResult", "sos_roa"]
