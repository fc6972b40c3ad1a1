"""Controller design and exact polynomials: the LQR start, quadratic Lyapunov matrices, and
the semidefinite programs of the sum-of-squares candidates.
"""
