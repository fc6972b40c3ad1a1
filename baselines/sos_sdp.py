"""The SDPs of the SOS baseline: :mod:`nlyap_opt.design.sos_sdp` (re-exported)."""

from nlyap_opt.design.sos_sdp import *  # noqa: F403
from nlyap_opt.design.sos_sdp import __all__  # noqa: F401
