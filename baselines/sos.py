"""The SOS baseline is the method's own SOS certificate: :mod:`nlyap_opt.candidates.sos`
(re-exported).

The SOS programs, the polynomial expansion and the re-certification live in
:mod:`nlyap_opt.candidates.sos`, :mod:`nlyap_opt.design.sos_sdp` and
:mod:`nlyap_opt.design.polynomial`, below the pipeline, which runs them as a cheap certificate
before the neural stage (the ``sos`` key of the run configuration); ``nlyap compare`` lists the same
result as its SOS row.
"""

from nlyap_opt.candidates.sos import (
    NotPolynomialError,
    Polynomial,
    SOSLevel,
    SOSResult,
    polynomial_closed_loop,
    sos_level,
    sos_roa,
)

__all__ = [
    "NotPolynomialError", "Polynomial", "SOSLevel", "SOSResult", "polynomial_closed_loop",
    "sos_level", "sos_roa",
]
