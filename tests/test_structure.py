"""Structure counts of the code base, and the package's public face.

Run as a script (``python tests/test_structure.py``) to print the counts:

- definitions of the unit roundoff ``u`` (a constant ``2**-53`` or ``2**-52``, or numpy's
  ``finfo(...).eps``) and of every rounding helper: one each, in ``nlyap_opt/kernel/rounding.py``;
- private names (``_x``) imported from another module of the project: may not grow above
  :data:`PRIVATE_IMPORTS_MAX`;
- string comparisons of statuses in the orchestration layer (``x.status == "..."``,
  ``d["status"] != "..."``, ``status.startswith("...")``): none (statuses are enums);
- functions of the orchestration layer annotated ``-> dict`` (a typed result instead; a
  ``to_json`` method, the saved form of one, is not counted): none;
- function-level imports package-wide: at most :data:`LAZY_IMPORTS_MAX`, each of an optional
  or heavy dependency and saying so (``# lazy: <reason>`` on its line);
- statements per function in the orchestration layer: at most :data:`STATEMENTS_MAX`.
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("nlyap_opt", "systems", "verification", "baselines")
ROUNDING = "nlyap_opt/kernel/rounding.py"

#: private names imported across modules (35 when the rounding model was unified, 11 before
#: the argument types moved to nlyap_opt.interface.cli_args): verification.affine uses 7 kernels of
#: verification.interval
PRIVATE_IMPORTS_MAX = 7

#: names that a rounding helper had or has; each may be defined once, in rounding.py
LEGACY_HELPERS = ("_up", "_dn", "_up_s", "_dn_s", "_up_w", "_dn_w", "_down", "_upper",
                  "_gamma", "_upnn", "_fac", "_add_up", "_mul_up", "_next_up")

#: the orchestration layer (above the certificate kernel): no string status comparison, no
#: ``-> dict`` return, no function above :data:`STATEMENTS_MAX` statements (ruff's C901 and
#: PLR0915 hold for the same modules, pyproject.toml)
ORCHESTRATION = ("nlyap_opt/workflow/pipeline.py", "nlyap_opt/candidates/cegis.py",
                 "nlyap_opt/candidates/learning.py",
                 "nlyap_opt/workflow/configs.py", "nlyap_opt/workflow/report.py",
                 "nlyap_opt/workflow/portfolio.py",
                 "nlyap_opt/candidates/quadratic.py", "nlyap_opt/candidates/sos.py",
                 "nlyap_opt/interface/cli.py",
                 "nlyap_opt/interface/cli_dynamics.py", "nlyap_opt/interface/cli_deploy.py")

#: function-level imports package-wide
LAZY_IMPORTS_MAX = 20

#: statements in one function of the orchestration layer
STATEMENTS_MAX = 60


def _sources() -> dict[str, ast.Module]:
    out = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = path.relative_to(ROOT).as_posix()
            out[rel] = ast.parse(path.read_text(encoding="utf-8"), filename=rel)
    return out


def _constant(node: ast.AST) -> float | None:
    """The value of a constant arithmetic expression (``2.0**-53``, ``1 / 2**53``), else None."""
    if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) \
            and not isinstance(node.value, bool):
        return float(node.value)
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
        v = _constant(node.operand)
        return None if v is None else -v
    if isinstance(node, ast.BinOp):
        a, b = _constant(node.left), _constant(node.right)
        if a is None or b is None:
            return None
        ops = {ast.Pow: lambda: a**b, ast.Mult: lambda: a * b, ast.Div: lambda: a / b,
               ast.Add: lambda: a + b, ast.Sub: lambda: a - b}
        f = ops.get(type(node.op))
        try:
            return None if f is None else float(f())
        except (OverflowError, ZeroDivisionError):
            return None
    return None


def u_definitions(sources: dict[str, ast.Module]) -> list[str]:
    """``file:line`` of every definition of ``u`` (or ``2u``) and every ``finfo(..).eps``."""
    hits = []
    for rel, tree in sources.items():
        for node in ast.walk(tree):
            if isinstance(node, (ast.Assign, ast.AnnAssign)) and node.value is not None:
                if _constant(node.value) in (2.0**-53, 2.0**-52):
                    hits.append(f"{rel}:{node.lineno}")
            elif isinstance(node, ast.Attribute) and node.attr == "eps" \
                    and isinstance(node.value, ast.Call) \
                    and getattr(node.value.func, "attr", getattr(node.value.func, "id", "")) \
                    == "finfo":
                hits.append(f"{rel}:{node.lineno}")
    return hits


def helper_definitions(sources: dict[str, ast.Module], names) -> dict[str, list[str]]:
    """``file:line`` of every function definition named one of ``names``."""
    out: dict[str, list[str]] = {n: [] for n in names}
    for rel, tree in sources.items():
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.name in out:
                out[node.name].append(f"{rel}:{node.lineno}")
    return out


def private_imports(sources: dict[str, ast.Module]) -> list[str]:
    """``file: module._name`` for each private name imported from another project module."""
    hits = []
    for rel, tree in sources.items():
        for node in ast.walk(tree):
            if not isinstance(node, ast.ImportFrom):
                continue
            mod = node.module or ""
            if node.level == 0 and mod.split(".")[0] not in PACKAGES:
                continue        # third-party or standard library
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    hits.append(f"{rel}: {'.' * node.level}{mod}.{alias.name}")
    return hits


def _is_status(node: ast.AST) -> bool:
    if isinstance(node, ast.Name):
        return "status" in node.id
    if isinstance(node, ast.Attribute):
        return "status" in node.attr
    if isinstance(node, ast.Subscript):
        key = node.slice
        return isinstance(key, ast.Constant) and isinstance(key.value, str) \
            and "status" in key.value
    if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "get" and node.args:
        key = node.args[0]
        return isinstance(key, ast.Constant) and isinstance(key.value, str) \
            and "status" in key.value
    return False


def status_string_comparisons(tree: ast.Module) -> int:
    """Comparisons of a status with a string literal, and ``status.startswith("...")``."""
    n = 0
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            sides = [node.left, *node.comparators]
            strs = [s for s in sides if isinstance(s, ast.Constant) and isinstance(s.value, str)
                    or isinstance(s, (ast.Tuple, ast.List, ast.Set)) and s.elts
                    and all(isinstance(e, ast.Constant) and isinstance(e.value, str)
                            for e in s.elts)]
            if strs and any(_is_status(s) for s in sides):
                n += 1
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                and node.func.attr in ("startswith", "endswith") \
                and _is_status(node.func.value):
            n += 1
    return n


def rounding_shadows(sources: dict[str, ast.Module]) -> list[str]:
    """Functions that bind a name the module imports from the rounding model (a parameter
    ``U`` would silently replace the unit roundoff ``U`` in that function)."""
    hits = []
    for rel, tree in sources.items():
        imported = {a.asname or a.name for n in tree.body if isinstance(n, ast.ImportFrom)
                    and (n.module or "").endswith("rounding") for a in n.names}
        for f in ast.walk(tree):
            if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                args = f.args
                bound = {a.arg for a in args.posonlyargs + args.args + args.kwonlyargs}
                bound |= {n.id for n in ast.walk(f)
                          if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store)}
                for name in sorted(bound & imported):
                    hits.append(f"{rel}:{f.lineno} {getattr(f, 'name', 'lambda')} binds {name}")
    return hits


def dict_returns(tree: ast.Module) -> list[str]:
    """``name:line`` of each function annotated to return a ``dict`` (``dict``,
    ``dict[...]``, ``dict | None``, ``Dict``), ``to_json`` methods excepted."""
    hits = []
    for f in ast.walk(tree):
        if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef)) and f.returns is not None \
                and f.name != "to_json":
            names = {n.id for n in ast.walk(f.returns) if isinstance(n, ast.Name)}
            if isinstance(f.returns, ast.Constant) and isinstance(f.returns.value, str):
                names = set(re.findall(r"\w+", f.returns.value))
            if names & {"dict", "Dict"}:
                hits.append(f"{f.name}:{f.lineno}")
    return hits


def lazy_imports(rel: str, tree: ast.Module, text: str) -> list[tuple[str, str]]:
    """``(file:line, reason)`` of each import inside a function; the reason is the
    ``# lazy: ...`` comment on the import's line ("" without one)."""
    lines = text.splitlines()
    hits = []
    for f in ast.walk(tree):
        if not isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(f):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                m = re.search(r"#\s*lazy:\s*(\S.*)$", lines[node.lineno - 1])
                hits.append((f"{rel}:{node.lineno}", m.group(1).strip() if m else ""))
    return sorted(set(hits))


def _own_statements(f: ast.AST) -> int:
    """Statements in a function's body, those of nested functions and classes excepted."""
    n = 0
    stack = list(f.body)
    while stack:
        node = stack.pop()
        n += 1
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            continue
        for name in ("body", "orelse", "finalbody", "handlers", "cases"):
            for child in getattr(node, name, ()) or ():
                if isinstance(child, ast.stmt):
                    stack.append(child)
                elif isinstance(child, (ast.excepthandler, ast.match_case)):
                    stack.extend(child.body)
    return n


def long_functions(tree: ast.Module, limit: int) -> list[str]:
    """``name:line (statements)`` of each function with more than ``limit`` statements."""
    return [f"{f.name}:{f.lineno} ({_own_statements(f)})" for f in ast.walk(tree)
            if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
            and _own_statements(f) > limit]


def report() -> dict:
    import nlyap_opt.kernel.rounding as rounding

    sources = _sources()
    helpers = [n for n in rounding.__all__ if callable(getattr(rounding, n))]
    status = {rel: status_string_comparisons(sources[rel]) for rel in ORCHESTRATION
              if rel in sources}
    lazy = [h for rel, tree in sources.items()
            for h in lazy_imports(rel, tree, (ROOT / rel).read_text(encoding="utf-8"))]
    return {"u": u_definitions(sources),
            "dict_returns": {rel: dict_returns(sources[rel]) for rel in ORCHESTRATION},
            "lazy": lazy,
            "long": {rel: long_functions(sources[rel], STATEMENTS_MAX) for rel in ORCHESTRATION},
            "helpers": helper_definitions(sources, helpers),
            "legacy": helper_definitions(sources, LEGACY_HELPERS),
            "private_imports": private_imports(sources),
            "shadows": rounding_shadows(sources),
            "status_comparisons": status}


@pytest.fixture(scope="module")
def counts():
    return report()


def test_u_is_defined_once(counts):
    """The unit roundoff has one definition, in the rounding module."""
    assert len(counts["u"]) == 1 and counts["u"][0].startswith(ROUNDING + ":"), counts["u"]


def test_each_rounding_helper_is_defined_once(counts):
    assert len(counts["helpers"]) >= 10
    for name, where in counts["helpers"].items():
        assert len(where) == 1 and where[0].startswith(ROUNDING + ":"), (name, where)
    stale = {n: w for n, w in counts["legacy"].items() if w}
    assert not stale, f"local rounding helpers: {stale} (import nlyap_opt.kernel.rounding instead)"


def test_no_function_shadows_the_rounding_names(counts):
    assert not counts["shadows"], counts["shadows"]


def test_private_imports_do_not_grow(counts):
    hits = counts["private_imports"]
    print(f"private names imported across modules: {len(hits)}")
    assert len(hits) <= PRIVATE_IMPORTS_MAX, "\n".join(hits)


def test_the_counters_see_what_they_count():
    """The counters find a planted case of each (so that a zero means none, not blindness)."""
    tree = ast.parse("_U = 2.0 ** -53\nE = np.finfo(float).eps\nfrom .x import _y\n"
                     "from numpy import _z\n"
                     "if r.status == 'ok' or d['status'] != 'x' or s.status in ('a', 'b'):\n"
                     "    status.startswith('inner')\nif n == 'status': pass\n")
    src = {"nlyap_opt/planted.py": tree}
    assert len(u_definitions(src)) == 2
    assert private_imports(src) == ["nlyap_opt/planted.py: .x._y"]
    assert status_string_comparisons(tree) == 4
    assert helper_definitions({"a.py": ast.parse("def up(y):\n    pass\n")}, ["up"]) == \
        {"up": ["a.py:1"]}
    shadow = ast.parse("from nlyap_opt.kernel.rounding import U\ndef f(L, U):\n    return U\n")
    assert rounding_shadows({"b.py": shadow}) == ["b.py:2 f binds U"]
    code = ("def a() -> dict:\n    import torch  # lazy: torch, heavy\n    return {}\n"
            "def b() -> dict[str, int] | None:\n    from . import x\n    return None\n"
            "class R:\n    def to_json(self) -> dict:\n        return {}\n"
            "def c(n) -> 'dict | None':\n" + "    n += 1\n" * 3
            + "    if n:\n        def inner():\n            pass\n    else:\n"
            "        pass\n    return None\n")
    tree = ast.parse(code)
    assert dict_returns(tree) == ["a:1", "b:4", "c:10"]
    assert lazy_imports("m.py", tree, code) == [("m.py:2", "torch, heavy"), ("m.py:5", "")]
    assert long_functions(tree, 5) == ["c:10 (7)"] and not long_functions(tree, 7)


def _checked(per_file: dict) -> dict:
    """The modules of the orchestration layer with a nonzero count."""
    assert set(per_file) == set(ORCHESTRATION)
    return {rel: v for rel, v in per_file.items() if v}


def test_no_status_is_compared_as_a_string(counts):
    """Statuses are enums (CertStatus, SOSStatus, QueryStatus, RowStatus, ...): a typo in
    a string comparison would silently be false."""
    assert not _checked(counts["status_comparisons"])


def test_no_orchestration_function_returns_a_dict(counts):
    """Results are typed (dataclasses; ``to_json`` gives the saved form)."""
    assert not _checked(counts["dict_returns"])


def test_no_orchestration_function_is_long(counts):
    assert not _checked(counts["long"]), f"split functions above {STATEMENTS_MAX} statements"


def test_lazy_imports_are_few_and_say_why(counts):
    """Imports inside functions only for optional or heavy dependencies, each saying which
    (``# lazy: torch, heavy``); the others belong at module level."""
    hits = counts["lazy"]
    print(f"function-level imports: {len(hits)}")
    unexplained = [w for w, r in hits if not r]
    assert not unexplained, f"imports inside functions without '# lazy: <reason>': {unexplained}"
    assert len(hits) <= LAZY_IMPORTS_MAX, hits


# --------------------------------------------------------------------------- public face
PUBLIC = {"run": "nlyap_opt.workflow.pipeline", "make_config": "nlyap_opt.workflow.configs",
          "RoaProblem": "nlyap_opt.certification.certificate",
          "certify_roa": "nlyap_opt.certification.certificate",
          "recheck_certificate": "nlyap_opt.certification.certificate",
          "CertStatus": "nlyap_opt.certification.certificate",
          "ConfigError": "nlyap_opt.kernel.errors", "NlyapError": "nlyap_opt.kernel.errors",
          "Network": "nlyap_opt.kernel.network", "evaluate": "nlyap_opt.kernel.walker"}


@pytest.mark.parametrize("name", sorted(PUBLIC))
def test_public_names_are_the_defining_modules_objects(name):
    import importlib

    import nlyap_opt

    assert name in nlyap_opt.__all__ and name in dir(nlyap_opt)
    obj = getattr(nlyap_opt, name)
    assert obj is getattr(importlib.import_module(PUBLIC[name]), name)
    assert getattr(obj, "__module__", PUBLIC[name]) == PUBLIC[name]


def test_unknown_attribute_is_an_attribute_error():
    import nlyap_opt

    with pytest.raises(AttributeError, match="no attribute 'no_such_name'"):
        nlyap_opt.no_such_name  # noqa: B018


def test_import_stays_light():
    """``import nlyap_opt`` loads neither the pipeline, the certificate kernel nor torch."""
    light = ("import sys, nlyap_opt; heavy = ['nlyap_opt.workflow.pipeline', "
             "'nlyap_opt.certification.certificate', "
             "'nlyap_opt.workflow.configs', 'torch', 'cvxpy', 'dask']; "
             "print([m for m in heavy if m in sys.modules])")
    lazy = "from nlyap_opt import run, CertStatus; import sys; print('torch' in sys.modules)"
    procs = [subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, cwd=ROOT)
             for code in (light, lazy)]                   # the two processes at once
    (out, err), (out2, err2) = (p.communicate(timeout=120) for p in procs)
    assert procs[0].returncode == 0, err
    assert out.strip() == "[]", out
    assert procs[1].returncode == 0 and out2.strip() == "True", err2


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    r = report()
    print(f"definitions of u: {len(r['u'])}  {r['u']}")
    for name, where in r["helpers"].items():
        print(f"  {name}: {len(where)}  {where}")
    print(f"legacy helper definitions: {sum(map(len, r['legacy'].values()))}")
    print(f"private names imported across modules: {len(r['private_imports'])}")
    for h in r["private_imports"]:
        print("  " + h)
    print(f"string status comparisons (orchestration): {sum(r['status_comparisons'].values())}")
    for rel, n in r["status_comparisons"].items():
        print(f"  {rel}: {n}")
    print(f"-> dict returns (orchestration): {sum(map(len, r['dict_returns'].values()))}")
    for rel, names in r["dict_returns"].items():
        if names:
            print(f"  {rel}: {names}")
    print(f"functions above {STATEMENTS_MAX} statements (orchestration):")
    for rel, names in r["long"].items():
        if names:
            print(f"  {rel}: {names}")
    print(f"function-level imports: {len(r['lazy'])}, without a reason: "
          f"{sum(1 for _, why in r['lazy'] if not why)}")
    for where, why in r["lazy"]:
        print(f"  {where}  {why or '(no reason)'}")


def test_project_text_cites_nothing_outside_the_repository():
    """Docstrings, comments and messages of the packages, benchmarks and examples stand
    alone: no internal pitfall numbers, method-document sections or issue numbers."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    outside = re.compile(r"PITFALLS|METHOD(\.md| §)|\bissue \d+|\(issue|\bP(9|1[0-9])\b")
    found = [f"{p.relative_to(root)}:{i}" for d in ("nlyap_opt", "systems", "verification",
                                                     "baselines", "bench", "examples")
             for p in sorted((root / d).rglob("*.py"))
             for i, line in enumerate(p.read_text().splitlines(), 1) if outside.search(line)]
    assert not found, found
