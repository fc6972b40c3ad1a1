"""The LQR baseline uses the method's own LQR start: :mod:`nlyap_opt.design.control`
(re-exported)."""

from nlyap_opt.design.control import (
    LQRResult,
    linear_controller,
    lqr,
    lyapunov_matrix,
    quadratic_lyapunov,
    saturated_controller,
)

__all__ = [
    "LQRResult", "lqr", "lyapunov_matrix", "saturated_controller", "linear_controller",
    "quadratic_lyapunov",
]
