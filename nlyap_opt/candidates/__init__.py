"""Candidate Lyapunov functions and controllers: the neural learner, the CEGIS loop, and
the quadratic and sum-of-squares candidates, each re-certified by the certificate
kernel.
"""
