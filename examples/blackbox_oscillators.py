"""Three coupled oscillators given only as a simulator (a black-box callable).

The tool never sees a formula: ``make()`` wraps a batched numpy function ``f(X)`` (think of
a simulator's right-hand side) into a :class:`systems.System` of kind ``"callable"`` that
declares its subsystems and what the compositional certificate needs::

    a1' = −a1 + 0.5 a2 + 0.1 sin(c1) c2      a2' = −0.5 a1 − a2
    b1' = −b1 + b2                           b2' = −b1 − b2 + 0.1 tanh(a1)²
    c1' = −c1 + 0.5 c2                       c2' = −0.5 c1 − c2 − 0.05 b1 c1

on X = [−1.5, 1.5]⁶, no input. Subsystems (a1, a2), (b1, b2), (c1, c2).

Declared (from the formula above, which the user knows and the tool does not):

- ``depends_on``: which states each derivative reads (the structure of the interconnection);
- H per state derivative, a bound on its second derivatives on X (0 for the linear ones):
  ``a1'``: ``|∂²(0.1 sin(c1) c2)| ≤ 0.1 · max(|sin c1| · 1.5, |cos c1|) ≤ 0.15``;
  ``b2'``: ``d²/da² tanh(a)² = 2(1 − t²)(1 − 3t²)`` (``t = tanh a``) is at most 2 in
  magnitude, so ``|∂²(0.1 tanh(a1)²)| ≤ 0.2``; ``c2'``: ``|∂²(0.05 b1 c1)| ≤ 0.05``.
  (One number, ``hessian = 0.2``, is also valid; it charges the linear derivatives too and
  certifies a smaller set.)

Run it: ``nlyap run examples/blackbox_oscillators.toml --out runs/oscillators``, then
``nlyap verify --certificate runs/oscillators --allow-factory`` (the re-check calls the
simulator again).
"""

from __future__ import annotations

import numpy as np

import systems

NAMES = ["a1", "a2", "b1", "b2", "c1", "c2"]


def oscillators_rhs(X: np.ndarray, U: np.ndarray) -> np.ndarray:
    """The black box: ``(N, 6), (N, 0) -> (N, 6)`` float64."""
    a1, a2, b1, b2, c1, c2 = X.T
    return np.stack([-a1 + 0.5 * a2 + 0.1 * np.sin(c1) * c2,
                     -0.5 * a1 - a2,
                     -b1 + b2,
                     -b1 - b2 + 0.1 * np.tanh(a1) ** 2,
                     -c1 + 0.5 * c2,
                     -0.5 * c1 - c2 - 0.05 * b1 * c1], axis=1)


DECLARED = systems.Declarations(hessian=[0.15, 0.0, 0.0, 0.2, 0.0, 0.05], depends_on={
    "a1": ["a1", "a2", "c1", "c2"], "a2": ["a1", "a2"],
    "b1": ["b1", "b2"], "b2": ["b1", "b2", "a1"],
    "c1": ["c1", "c2"], "c2": ["c1", "c2", "b1"]})


def make() -> systems.System:
    """The three oscillators as a :class:`systems.System` (kind ``"callable"``)."""
    return systems.System.from_callable(
        "blackbox_oscillators", oscillators_rhs, nx=6, state_box=[[-1.5, 1.5]] * 6,
        state_names=NAMES, declarations=DECLARED, subsystems=[(0, 1), (2, 3), (4, 5)],
        description="three coupled oscillators (black box, declared structure)")


if __name__ == "__main__":
    s = make()
    print(s, "has_model:", s.has_model)
    for line in s.describe_assumptions():
        print(" -", line)
