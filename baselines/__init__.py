"""Baselines: LQR (quadratic V), SOS, the neural method on the true dynamics."""

from .lqr import LQRResult, lqr, lyapunov_matrix, saturated_controller

__all__ = ["LQRResult", "lqr", "lyapunov_matrix", "saturated_controller"]
