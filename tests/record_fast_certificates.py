"""Record the fast presets' certificates (level, certified area, η, sha256 of the saved
networks) under this machine's numeric-environment fingerprint.

    python tests/record_fast_certificates.py           # print them (about two minutes)
    python tests/record_fast_certificates.py --write   # add them to the reference file

A recorded fingerprint makes the tests compare these runs bit for bit on machines with the
same fingerprint (CPU model and flags, package versions, BLAS kernel and threads, numpy and
torch dispatch: ``nlyap_opt.kernel.provenance``); elsewhere the tests check only the floors. Record
for a new machine you want bit-for-bit regression checks on, or after a deliberate change of
the training (then drop the old fingerprints, saying so in the commit). The floors are not
written by this script: they are properties every machine must reach, set by hand with a
stated margin.
"""

from __future__ import annotations

import json
import sys
import tempfile

from certcheck import _REFERENCE_FILE, fast_references, fast_summary

import systems
from nlyap_opt.kernel.provenance import fingerprint, fingerprint_id
from nlyap_opt.workflow.configs import get_config
from nlyap_opt.workflow.pipeline import run


def record() -> dict:
    out = {}
    for name in systems.SEED_SYSTEMS:
        for setting in ("known", "learned"):
            with tempfile.TemporaryDirectory() as d:
                c = run(name, get_config(name, "fast"), d, known_dynamics=setting == "known",
                        log=lambda m: None).summary
                got = fast_summary(c, d)
            del got["status"]
            out[f"{name}/{setting}"] = got
    return out


def main() -> None:
    fp = fingerprint()
    kernel = fp["blas"][0]["kernel"] if fp["blas"] else "?"
    machine = (f"{fp['cpu']['model']}; BLAS {kernel}; numpy {' '.join(fp['numpy_dispatch'])}; "
               f"torch {fp['torch']['cpu_capability']}" + ("; portable" if fp["portable"] else ""))
    entry = {"machine": machine, "values": record()}
    if "--write" not in sys.argv[1:]:
        print(json.dumps({fingerprint_id(fp): entry}, indent=1))
        return
    ref = fast_references()
    ref["fingerprints"][fingerprint_id(fp)] = entry
    _REFERENCE_FILE.write_text(json.dumps(ref, indent=1, ensure_ascii=False) + "\n")
    print(f"recorded {fingerprint_id(fp)} ({entry['machine']}) in {_REFERENCE_FILE}")


if __name__ == "__main__":
    main()
