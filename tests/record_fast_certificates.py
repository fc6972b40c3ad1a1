"""Print the fast presets' certificates (level, certified area, η) as JSON, for
``tests/data/fast_certificates.json`` under the OpenBLAS kernel this machine uses.

    python tests/record_fast_certificates.py      # about two minutes on 2 cores

Record only for a new kernel or a deliberate change of the training, saying so in the commit.
"""

from __future__ import annotations

import json
import tempfile

from certcheck import blas_kernel

import systems
from nlyap_opt.configs import get_config
from nlyap_opt.pipeline import run


def record() -> dict:
    out = {}
    for name in systems.SEED_SYSTEMS:
        for setting in ("known", "learned"):
            with tempfile.TemporaryDirectory() as d:
                c = run(name, get_config(name, "fast"), d, known_dynamics=setting == "known",
                        log=lambda m: None).summary
            out[f"{name}/{setting}"] = {"level": c["level"],
                                        "certified_area": c["certified_area"],
                                        "eta": c.get("eta", 0.0)}
    return out


if __name__ == "__main__":
    print(json.dumps({blas_kernel() or "unknown": record()}, indent=1))
