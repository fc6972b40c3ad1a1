"""The numeric environment a certificate records, and portable mode."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from nlyap_opt.interface.cli import main
from nlyap_opt.kernel.provenance import (
    describe,
    differences,
    fingerprint,
    fingerprint_id,
    portable_env,
    portable_problems,
)


def _nlyap(*argv, env=None):
    return subprocess.run([sys.executable, "-m", "nlyap_opt.interface.cli", *argv], text=True,
                          capture_output=True, env=env, timeout=600)


def test_the_fingerprint_names_what_determines_the_numbers():
    fp = fingerprint()
    assert {"numpy", "torch", "scipy", "casadi", "cvxpy", "clarabel"} <= set(fp["versions"])
    assert fp["versions"]["numpy"] and fp["python"]
    assert fp["blas"] and all({"kernel", "threads", "version"} <= set(b) for b in fp["blas"])
    assert fp["torch"]["cpu_capability"]
    assert fp["cpu"]["machine"]
    json.dumps(fp)                                   # stored in certificate.json as it is
    assert fingerprint_id(fp) == fingerprint_id()


def test_the_fingerprint_is_the_same_in_another_process_and_changes_with_a_kernel_pin():
    code = "from nlyap_opt.kernel.provenance import fingerprint_id; print(fingerprint_id())"
    env = dict(os.environ)
    procs = [subprocess.Popen([sys.executable, "-c", code], text=True, stdout=subprocess.PIPE,
                              env=e) for e in (env, env, dict(env, OPENBLAS_CORETYPE="Prescott"))]
    outs = [p.communicate(timeout=300)[0].strip() for p in procs]   # the three at once
    assert [p.returncode for p in procs] == [0, 0, 0]
    *ids, other = outs
    assert len(set(ids)) == 1 and ids[0]
    assert other != ids[0]


def test_differences_and_description():
    fp = fingerprint()
    assert differences(fp, fp) == []
    assert differences(None, fp) == ["unknown"]
    moved = json.loads(json.dumps(fp))
    moved["cpu"]["model"] = "another CPU"
    moved["versions"]["numpy"] = "0.0"
    assert differences(moved, fp) == ["cpu", "versions"]
    text = "\n".join(describe(fp))
    assert fingerprint_id(fp) in text and str(fp["torch"]["cpu_capability"]) in text


def test_portable_problems_name_each_kernel_that_is_not_pinned():
    fp = fingerprint()
    pinned = json.loads(json.dumps(fp))
    pinned["cpu"].update(machine="x86_64", flags=["avx2", "fma"])
    pinned["numpy_dispatch"] = ["X86_V3"]
    pinned["torch"]["cpu_capability"] = "AVX2"
    for b in pinned["blas"]:
        b.update(library="openblas", kernel="Haswell", threads=1)
    assert portable_problems(pinned) == []
    wide = json.loads(json.dumps(pinned))
    wide["numpy_dispatch"] = ["X86_V3", "X86_V4"]
    wide["torch"]["cpu_capability"] = "AVX512"
    wide["blas"][0]["kernel"] = "SkylakeX"
    problems = portable_problems(wide)
    assert len(problems) == 3 and any("SkylakeX" in p for p in problems)
    arm = json.loads(json.dumps(pinned))
    arm["cpu"]["machine"] = "aarch64"
    assert any("not x86-64" in p for p in portable_problems(arm))


def test_portable_from_python_is_refused_with_one_line(capsys):
    if os.environ.get("NLYAP_PORTABLE") == "1":
        pytest.skip("this process already runs in portable mode")
    assert main(["run", "van_der_pol", "--preset", "fast", "--portable"]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--portable" in err[0] and "portable_env()" in err[0]


@pytest.mark.slow  # ~17 s idle: four learned runs in fresh processes
def test_portable_runs_pin_the_kernels_and_train_the_same_networks_whatever_the_shell_set(
        tmp_path):
    """Two portable runs started from different OpenBLAS kernels and thread counts: the
    pins override both, the certificate records them, and φ and V are the same bytes."""
    probe = portable_problems(dict(fingerprint(), numpy_dispatch=["X86_V3"],
                                   torch={"cpu_capability": "AVX2"}, blas=[]))
    if probe:
        pytest.skip(f"portable mode needs x86-64 with AVX2 and FMA: {probe}")
    files = {}
    for core, threads in (("SkylakeX", "2"), ("Zen", "1")):
        out = tmp_path / core
        env = dict(os.environ, OPENBLAS_CORETYPE=core, OPENBLAS_NUM_THREADS=threads)
        p = _nlyap("run", "van_der_pol", "--preset", "fast", "--portable", "--out", str(out),
                   env=env)
        assert p.returncode == 0, p.stderr
        cert = json.loads((out / "certificate.json").read_text())
        prov = cert["provenance"]
        assert prov["portable"] and portable_problems(prov) == []
        assert {k: prov["environment"].get(k) for k in portable_env()} == portable_env()
        assert "(portable mode)" in (out / "report.md").read_text()
        files[core] = {f: (out / f).read_bytes() for f in ("V.json", "dynamics.json")}
    assert files["SkylakeX"] == files["Zen"]
