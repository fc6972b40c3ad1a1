"""The true ROA the reports compare against, checked against an independent computation.

Reversed Van der Pol (μ = 1): its ROA is the inside of the unstable limit cycle. The toolbox
estimates it by simulating a grid of initial states with its own fixed-step RK4
(``nlyap_opt.certification.roa.true_roa_mask``); ``vdp_reference.vdp_limit_cycle`` computes the
cycle with SciPy's adaptive DOP853 on the forward-time system and the area with the shoelace
formula.
"""

import numpy as np
from vdp_reference import vdp_limit_cycle, vdp_true_roa_area

import systems
from nlyap_opt.certification.roa import true_roa_mask


def test_the_limit_cycle_is_closed_and_has_the_known_amplitude():
    c = vdp_limit_cycle(1.0)
    assert np.linalg.norm(c[0] - c[-1]) < 1e-8          # one whole period
    # the classical amplitude of the μ = 1 cycle: max x₁ = 2.00862 (e.g. Strogatz, §7.5)
    assert abs(c[:, 0].max() - 2.00862) < 1e-5
    area = vdp_true_roa_area(1.0)
    # between the largest disc inside the cycle and the smallest around it
    r = np.linalg.norm(c, axis=1)
    assert np.pi * r.min() ** 2 < area < np.pi * r.max() ** 2


def test_the_grid_estimate_of_the_true_roa_matches_the_limit_cycle():
    """Cells whose centre converges, times the cell area, against the cycle's area: they
    can differ only by the cells the cycle crosses (at most perimeter·√2·h in area)."""
    box = np.array([[-3.0, 3.0], [-3.0, 3.0]])
    n = 120
    mask = true_roa_mask(systems.get("van_der_pol"), None, box, n=n)
    h = 6.0 / n
    estimate = mask.mean() * 36.0
    c = vdp_limit_cycle(1.0)
    perimeter = float(np.sum(np.linalg.norm(np.diff(c, axis=0), axis=1)))
    exact = vdp_true_roa_area(1.0)
    assert abs(estimate - exact) <= perimeter * np.sqrt(2) * h, (estimate, exact)
    # and much closer in practice: boundary cells are split about evenly
    assert abs(estimate - exact) < 0.05 * exact
