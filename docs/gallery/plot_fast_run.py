"""
A whole run: Van der Pol with the fast preset
=============================================

``nlyap run van_der_pol --preset fast --known-dynamics`` from Python: train V, certify
its level with the interval verifier, and compare the certified set with the true region
of attraction estimated by simulation (the inside of the limit cycle).
"""

import tempfile

import matplotlib.pyplot as plt
import numpy as np

import systems
from nlyap_opt import load_network
from nlyap_opt.workflow.configs import make_config
from nlyap_opt.workflow.pipeline import run

out = tempfile.mkdtemp()
cfg = make_config("van_der_pol", "fast")
result = run("van_der_pol", cfg, out, known_dynamics=True, log=lambda m: None)
assert result.certified, result.reason
print(result.status.value, "level", result.summary["level"])

# %%
# The certified set ``Ω_c ∪ E`` (blue) inside the simulated true ROA (grey).
V = load_network(f"{out}/V.json")
g = np.linspace(-3, 3, 241)
X = np.stack(np.meshgrid(g, g, indexing="xy"), -1).reshape(-1, 2)
inside = result.certificate.contains(X).reshape(len(g), len(g))
true_roa = np.load(f"{out}/true_roa.npz")["mask"]
tg = -3 + 6 * (np.arange(true_roa.shape[0]) + 0.5) / true_roa.shape[0]   # cell centres

fig, ax = plt.subplots(figsize=(5, 5))
ax.contourf(tg, tg, true_roa.T.astype(float), levels=[0.5, 1.5], colors=["#d9d9d9"])
ax.contourf(g, g, inside, levels=[0.5, 1.5], colors=["#6baed6"])
ax.contour(g, g, V.numpy(X).reshape(len(g), len(g)), levels=[result.summary["level"]],
           colors="k", linewidths=0.8)
ax.set(xlabel="x₁", ylabel="x₂", aspect="equal",
       title=f"{systems.get('van_der_pol').name}: certified vs true ROA")
plt.show()
