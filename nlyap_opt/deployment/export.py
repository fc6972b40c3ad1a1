r"""Deployment code of a certified run: dependency-free C99 (CasADi code generation) or ONNX.

:func:`export_c` writes ``nlyap.c`` and ``nlyap.h`` (C99, ``math.h`` only)::

    int nlyap_kappa(const double *x, double *u);       /* κ(x), NLYAP_NU entries     */
    int nlyap_V(const double *x, double *v);           /* V(x), one entry             */
    int nlyap_grad_V(const double *x, double *g);      /* ∇V(x), NLYAP_NX entries     */
    int nlyap_in_certified_set(const double *x);       /* 1: x ∈ Ω_c ∪ E, else 0      */

(the first three return 0), from the same float64 networks the certificate was proved for,
with the level, the domain, the inner ellipse and the sha256 of ``certificate.json`` in the
header. The membership test is the certificate's (:meth:`RoaCertificate.contains`):
``x ∈ D and V(x) ≤ c``, or ``xᵀPx ≤ c_E``; at points where ``V(x)`` lies within rounding of
``c`` the C and Python answers may differ (the C code evaluates ``V`` with another
summation order).

:func:`export_onnx` writes ``V.onnx`` and ``kappa.onnx`` (float64, batch axis) with
torch's exporter; it needs the ``onnx`` package (the ``onnx`` extra).
"""

from __future__ import annotations

import importlib.util
import json
import warnings
from pathlib import Path

import casadi as ca

from ..kernel import deps
from ..kernel.errors import ConfigError
from ..kernel.jsonio import write_files_atomic
from ..kernel.network import Network

__all__ = ["export_c", "export_onnx", "C_FUNCTIONS"]

#: the C API (name -> (what, output size attribute))
C_FUNCTIONS = ("nlyap_kappa", "nlyap_V", "nlyap_grad_V", "nlyap_in_certified_set")


def _c_double(v: float) -> str:
    """A C99 hexadecimal floating literal: the exact float64."""
    return float(v).hex()


def _comment(text: str) -> str:
    """``text`` safe inside a C comment (ASCII, no comment delimiters)."""
    return text.encode("ascii", "replace").decode().replace("*/", "* /").replace("/*", "/ *")


def _functions(run) -> dict[str, ca.Function]:
    """``kappa``, ``V``, ``grad_V``, ``member`` as SX Functions of ``x``."""
    problem, sysm = run.problem, run.system
    x = ca.SX.sym("x", sysm.nx)
    V = problem.V_expr(x)
    kappa = problem.controller.casadi(x) if problem.controller is not None \
        else ca.SX(ca.DM(sysm.u_eq)) if sysm.nu else ca.SX(0, 1)
    cert = run.certificate
    in_D = ca.SX(1)
    for g, _ in problem.domain.inequalities(x):
        in_D = ca.logic_and(in_D, g <= 0)
    member = ca.logic_and(in_D, V <= cert.level)
    E = cert.inner_ellipse
    if E is not None:
        member = ca.logic_or(member, ca.bilin(ca.DM(E.P), x, x) <= E.level)
    return {"kappa": ca.Function("nlyap_cg_kappa", [x], [kappa]),
            "V": ca.Function("nlyap_cg_V", [x], [V]),
            "grad_V": ca.Function("nlyap_cg_grad_V", [x], [ca.gradient(V, x)]),
            "member": ca.Function("nlyap_cg_member", [x], [ca.if_else(member, 1.0, 0.0)])}


def _wrapper(fn: ca.Function, name: str, out: str, ret: str = "") -> str:
    n_arg, n_res = max(fn.sz_arg(), 1), max(fn.sz_res(), 1)
    n_iw, n_w = max(fn.sz_iw(), 1), max(fn.sz_w(), 1)
    head = f"int {name}(const double *x)" if ret else f"int {name}(const double *x, double *{out})"
    call_out = "&m" if ret else out
    body = [head + " {",
            f"  const casadi_real *arg[{n_arg}];",
            f"  casadi_real *res[{n_res}];",
            f"  casadi_int iw[{n_iw}];",
            f"  casadi_real w[{n_w}];"]
    if ret:
        body.append("  double m = 0.0;")
    body += ["  arg[0] = x;",
             f"  res[0] = {call_out};",
             f"  if ({fn.name()}(arg, res, iw, w, 0)) return {'0' if ret else '1'};",
             f"  return {ret or '0'};",
             "}"]
    return "\n".join(body) + "\n"


def export_c(run, out: str | Path) -> tuple[Path, Path]:
    """Write ``nlyap.c`` and ``nlyap.h`` for ``run`` (a
    :class:`~nlyap_opt.deployment.deploy.CertifiedRun`)
    into directory ``out``; returns their paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sysm, cert = run.system, run.certificate
    fns = _functions(run)
    cg = ca.CodeGenerator("nlyap_impl.c", {"with_header": False, "casadi_real": "double",
                                           "casadi_int": "long long int", "prefix": "nlyap_cg_",
                                           "verbose": False})
    for f in fns.values():
        cg.add(f)
    impl = cg.dump()
    E = cert.inner_ellipse
    box = run.problem.domain.bounding_box()
    dom = json.dumps(run.problem.domain.to_dict())
    lines = [
        "/* nlyap: a certified controller, Lyapunov function and region of attraction.",
        f" * run {_comment(run.directory.name)}: system {_comment(sysm.name)}, "
        f"{cert.setting} dynamics,",
        f" * certificate.json sha256 {run.sha256}.",
        " * Certified set: Omega_c u E, Omega_c = {x in D : V(x) <= NLYAP_LEVEL} (the component",
        " * holding 0; the only one, as the certificate proves), E = {x'Px <= NLYAP_E_LEVEL}.",
        " * Generated by `nlyap export --format c`; C99, needs only <math.h> (link with -lm). */",
        "#ifndef NLYAP_H", "#define NLYAP_H", "",
        f"#define NLYAP_NX {sysm.nx}", f"#define NLYAP_NU {sysm.nu}",
        f"#define NLYAP_SYSTEM {_c_string(sysm.name)}",
        f'#define NLYAP_CERTIFICATE_SHA256 "{run.sha256}"',
        "/* nlyap.c compiles only beside the header of its own export */",
        f"#define NLYAP_EXPORT_{run.sha256[:16]} 1",
        f"#define NLYAP_LEVEL {_c_double(cert.level)}  /* {cert.level!r} */",
        f"#define NLYAP_INNER_RADIUS {_c_double(cert.inner)}  /* {cert.inner!r} */",
        f"#define NLYAP_DOMAIN_JSON {_c_string(dom)}",
        "/* bounding box of D, rows (lower, upper) */",
        "#define NLYAP_DOMAIN_BOX { " + ", ".join(
            f"{{{_c_double(lo)}, {_c_double(hi)}}}" for lo, hi in box) + " }",
    ]
    if E is not None:
        lines += [f"#define NLYAP_E_LEVEL {_c_double(E.level)}  /* {E.level!r} */",
                  "#define NLYAP_E_P { " + ", ".join(
                      "{" + ", ".join(_c_double(v) for v in row) + "}" for row in E.P) + " }"]
    lines += ["",
              "/* u = kappa(x): NLYAP_NU entries; returns 0 */",
              "int nlyap_kappa(const double *x, double *u);",
              "/* v[0] = V(x); returns 0 */",
              "int nlyap_V(const double *x, double *v);",
              "/* g = grad V(x): NLYAP_NX entries; returns 0 */",
              "int nlyap_grad_V(const double *x, double *g);",
              "/* 1 if x lies in the certified set Omega_c u E, else 0 */",
              "int nlyap_in_certified_set(const double *x);",
              "", "#endif /* NLYAP_H */", ""]
    h = out / "nlyap.h"
    wrappers = "\n".join([
        _wrapper(fns["kappa"], "nlyap_kappa", "u"),
        _wrapper(fns["V"], "nlyap_V", "v"),
        _wrapper(fns["grad_V"], "nlyap_grad_V", "g"),
        _wrapper(fns["member"], "nlyap_in_certified_set", "", ret="m > 0.5"),
    ])
    c = out / "nlyap.c"
    # both or neither: a failed write (a full disk) leaves the old pair as it was
    write_files_atomic({h: "\n".join(lines),
                        c: f"/* certificate.json sha256 {run.sha256}; see nlyap.h */\n"
                           '#include "nlyap.h"\n'
                           f"#ifndef NLYAP_EXPORT_{run.sha256[:16]}\n"
                           '#error "nlyap.h is not the header of this nlyap.c (another '
                           'export): export both again"\n#endif\n' + impl
                           + "\n/* the API of nlyap.h */\n" + wrappers})
    return c, h


def _c_string(text: str) -> str:
    """``text`` as a C99 string literal of its UTF-8 bytes: printable ASCII as is (``"`` and
    ``\\`` escaped), every other byte as a three-digit octal escape (JSON's ``\\ud83d``
    escapes are not C: a non-BMP system name broke the header)."""
    out = []
    for b in text.encode("utf-8"):
        c = chr(b)
        out.append("\\" + c if c in '"\\' else c if 32 <= b < 127 and c != "?" else f"\\{b:03o}")
    return '"' + "".join(out) + '"'


def export_onnx(run, out: str | Path) -> list[Path]:
    """Write ``V.onnx`` (``(N, nx) -> (N, 1)``) and, with inputs, ``kappa.onnx``
    (``(N, nx) -> (N, nu)``), float64, into ``out``."""
    if importlib.util.find_spec("onnx") is None:
        raise ConfigError("ONNX export needs the onnx package, which is not installed; "
                          "pip install 'nlyap_opt[onnx]' (or pip install onnx)")
    torch = deps.torch()


    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    problem = run.problem
    written = []
    for name, net in (("V", problem.V), ("kappa", problem.controller)):
        if net is None:
            continue
        if not isinstance(net, Network):
            raise ConfigError(f"the {name} of {run.directory} is not a network (a CasADi "
                              "function); export it with --format c")
        mod = net.torch_module().eval()
        path = out / f"{name}.onnx"
        with torch.no_grad(), warnings.catch_warnings():
            # the TorchScript exporter: the torch.export one needs onnxscript as well
            warnings.simplefilter("ignore", DeprecationWarning)
            torch.onnx.export(mod, (torch.zeros(1, net.n_in, dtype=torch.float64),),
                              str(path), input_names=["x"], output_names=[name],
                              dynamic_axes={"x": {0: "batch"}, name: {0: "batch"}},
                              dynamo=False)
        written.append(path)
    return written
