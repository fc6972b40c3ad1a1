"""The import layers of setup.cfg (``[importlinter]``) hold, and every module has a layer.

Layers, top to bottom: CLI → baselines → pipeline → CEGIS/learning → certificate → ROA level
search → dynamics/bounds → control (LQR start) → verification → systems → core. A module
imports only from layers below it; function-level imports count (``lint-imports`` reads
every import statement), so a lazy import cannot hide a cycle.
"""

from __future__ import annotations

import configparser
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("nlyap_opt", "systems", "verification", "baselines")

pytest.importorskip("importlinter", reason="import-linter is not installed; run "
                    "`pip install -e .[dev]` to check the import layers")


def _lint_imports(cwd: Path, config: Path, env: dict | None = None):
    """Run ``lint-imports`` (the console script of this interpreter's environment)."""
    script = Path(sys.executable).with_name("lint-imports")
    cmd = ([str(script)] if script.exists()
           else [sys.executable, "-c", "import sys; from importlinter.cli import "
                 "lint_imports_command; sys.exit(lint_imports_command())"])
    return subprocess.run([*cmd, "--no-cache", "--config", str(config)], cwd=cwd,
                          capture_output=True, text=True, timeout=300, env=env)


def _layers() -> list[list[str]]:
    cfg = configparser.ConfigParser()
    cfg.read(ROOT / "setup.cfg")
    raw = cfg["importlinter:contract:layers"]["layers"]
    out = []
    for line in raw.strip().splitlines():
        out.append([m.strip() for m in line.replace("|", ":").split(":") if m.strip()])
    return out


def _covered(mod: str, layered) -> bool:
    """Whether module ``mod`` is one of ``layered`` or inside one of them (a layer may be a
    package: a folder of modules)."""
    return any(mod == m or mod.startswith(m + ".") for m in layered)


def test_import_layers_hold():
    """``lint-imports`` passes; on failure the message lists each import that breaks a layer
    (importer -> imported (line))."""
    res = _lint_imports(ROOT, ROOT / "setup.cfg")
    report = res.stdout + res.stderr
    broken = report[report.find("Broken contracts"):] if "Broken contracts" in report else report
    assert res.returncode == 0, f"import layers broken (setup.cfg [importlinter]):\n{broken}"
    assert "KEPT" in report


def test_every_module_has_a_layer():
    """A new module must be placed in a layer, or the contract does not constrain it."""
    layered = [m for layer in _layers() for m in layer]
    missing = []
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            mod = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            if mod == "nlyap_opt":  # the package root re-exports core names; in no layer
                continue
            if not _covered(mod, layered):
                missing.append(mod)
    assert not missing, (f"modules in no import layer: {', '.join(missing)}; add each to a "
                         "layer of [importlinter:contract:layers] in setup.cfg")


def test_package_root_imports_core_only():
    """``nlyap_opt/__init__.py`` is outside the layers: it may re-export the bottom layers
    (core) only, so that importing any module of the package stays cheap and acyclic."""
    import ast

    layers = _layers()
    below_systems = layers[[i for i, layer in enumerate(layers) if "systems" in layer][0] + 1:]
    core = {m for layer in below_systems for m in layer}
    assert _covered("nlyap_opt.kernel.errors", core) and _covered("nlyap_opt.kernel.network", core)
    tree = ast.parse((ROOT / "nlyap_opt" / "__init__.py").read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 1:
            assert _covered(f"nlyap_opt.{node.module}", core), (
                f"nlyap_opt/__init__.py imports nlyap_opt.{node.module}, which is not core "
                f"({', '.join(sorted(core))})")


def test_lint_imports_detects_a_violation(tmp_path):
    """The tool really fails on an upward import, also one hidden inside a function."""
    pkg = tmp_path / "toy"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "low.py").write_text(textwrap.dedent("""
        def f():
            from . import high  # a function-level import hiding a cycle
            return high
    """))
    (pkg / "high.py").write_text("from . import low\n")
    cfg = tmp_path / "toy.ini"
    cfg.write_text(textwrap.dedent("""
        [importlinter]
        root_packages =
            toy

        [importlinter:contract:layers]
        name = toy layers
        type = layers
        layers =
            toy.high
            toy.low
    """))
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    res = _lint_imports(tmp_path, cfg, env)
    assert res.returncode != 0, res.stdout + res.stderr
    assert "toy.low -> toy.high (l.3)" in res.stdout, res.stdout
    # and passes once the upward import is gone
    (pkg / "low.py").write_text("X = 1\n")
    res = _lint_imports(tmp_path, cfg, env)
    assert res.returncode == 0, res.stdout + res.stderr
