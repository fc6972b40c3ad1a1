"""
A quadratic certificate for the inverted pendulum
=================================================

The cheapest certificate: the LQR Lyapunov matrix ``P`` of the pendulum's closed loop under
a saturated LQR controller ``u = 20·tanh(Kx + b)``, certified by the interval verifier on
the disc ``‖x‖ ≤ 4`` with the level search. The figure shows the certified set against
closed-loop trajectories.
"""

import matplotlib.pyplot as plt
import numpy as np
from scipy.integrate import solve_ivp

import systems
from nlyap_opt.certification.certificate import RoaProblem, certify_roa
from nlyap_opt.design.control import lqr, quadratic_lyapunov, saturated_controller

s = systems.get("inverted_pendulum")
gain = lqr(s, Q=np.diag([1.0, 20.0]), R=1.0)
kappa = saturated_controller(s, gain.K, 20.0)
problem = RoaProblem(s, quadratic_lyapunov(gain.P), kappa, inner=0.1, outer=4.0)
# start the search at the largest level whose ellipse fits in the disc
start = 0.99 * np.linalg.eigvalsh(gain.P)[0] * 4.0**2
cert = certify_roa(problem, start, search=True, log=lambda m: None)
assert cert.certified, cert.reason
print(cert.status.value, "at level", cert.level)

# %%
# The certified set and a few trajectories of the true closed loop.
g = np.linspace(-4.2, 4.2, 421)
X = np.stack(np.meshgrid(g, g, indexing="xy"), -1).reshape(-1, 2)
inside = cert.contains(X).reshape(len(g), len(g))


def rhs(_t, x):
    u = kappa.numpy(x[None, :])
    return s.evaluate(x[None, :], u)[0]


fig, ax = plt.subplots(figsize=(5, 5))
ax.contourf(g, g, inside, levels=[0.5, 1.5], colors=["#9ecae1"])
for a in np.linspace(0, 2 * np.pi, 12, endpoint=False):
    sol = solve_ivp(rhs, (0, 6), 3.8 * np.array([np.cos(a), np.sin(a)]), max_step=0.05)
    ax.plot(sol.y[0], sol.y[1], lw=0.8, color="k")
ax.add_patch(plt.Circle((0, 0), 4.0, fill=False, ls="--"))
ax.set(xlabel="θ", ylabel="ω", aspect="equal", title=f"certified set (level {cert.level:.3g})")
plt.show()
