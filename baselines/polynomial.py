"""Exact polynomials of the SOS baseline: :mod:`nlyap_opt.polynomial` (re-exported)."""

from nlyap_opt.polynomial import *  # noqa: F403
from nlyap_opt.polynomial import __all__  # noqa: F401
