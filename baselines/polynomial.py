"""Exact polynomials of the SOS baseline: :mod:`nlyap_opt.design.polynomial` (re-exported)."""

from nlyap_opt.design.polynomial import *  # noqa: F403
from nlyap_opt.design.polynomial import __all__  # noqa: F401
