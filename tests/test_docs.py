"""The documentation runs: README.md's and docs/'s Python blocks, the spec-file blocks and
the gallery examples execute; every config key and CLI argument has a description; the
README stays short; no page reads as a history log or cites a document outside the
repository. ``make docs`` (CI) builds the site with warnings as errors; the slow test here
does the same without the make target.

A Python block preceded by the line ``<!-- docs-test: skip -->`` is not executed (for
blocks that need a long run or a cluster); every other block must run in seconds.
"""

from __future__ import annotations

import re
import runpy
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
SKIP_MARK = "<!-- docs-test: skip -->"
_GENERATED = ("_build", "_generated", "auto_examples")


def _pages() -> list[Path]:
    pages = [ROOT / "README.md"]
    pages += sorted(p for p in DOCS.rglob("*.md")
                    if not any(part in _GENERATED for part in p.relative_to(DOCS).parts))
    return pages


def _blocks(lang: str) -> list:
    """``(page, line, code)`` of every fenced ``lang`` block not marked to skip."""
    out = []
    fence = re.compile(r"^```" + lang + r"\s*$")
    for page in _pages():
        lines = page.read_text().splitlines()
        i = 0
        while i < len(lines):
            if fence.match(lines[i]):
                j = i + 1
                while j < len(lines) and lines[j].strip() != "```":
                    j += 1
                skip = i > 0 and lines[i - 1].strip() == SKIP_MARK
                if not skip:
                    code = "\n".join(lines[i + 1:j])
                    # a whole pipeline run (seconds) stays in the default tier on the README
                    # only; the pages' runs go to the slow tier
                    slow = page.name != "README.md" and "run(" in code and "tempfile" in code
                    out.append(pytest.param(page, i + 1, code,
                                            marks=[pytest.mark.slow] if slow else [],
                                            id=f"{page.relative_to(ROOT)}:{i + 1}"))
                i = j
            i += 1
    return out


@pytest.mark.parametrize(("page", "line", "code"), _blocks("python"))
def test_python_blocks_run(page, line, code, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    monkeypatch.chdir(ROOT)    # blocks read examples/ by their repository paths
    exec(compile(code, f"{page.name}:{line}", "exec"), {"__name__": "__docs__"})


@pytest.mark.parametrize(("page", "line", "code"), _blocks("toml"))
def test_spec_file_blocks_load(page, line, code, tmp_path):
    import tomllib

    import systems

    data = tomllib.loads(code)          # every TOML block parses
    if "name" not in data:              # a [run] table on its own: check its keys
        assert set(data) <= {"run"}, f"{page.name}:{line}: a partial spec with {set(data)}"
        return
    path = tmp_path / "spec.toml"
    path.write_text(code)
    s = systems.load_spec(path)
    assert s.name == data["name"] and s.nx == len(data["states"])
    assert s.has_model


@pytest.mark.slow  # `make docs` (CI's second step) runs every gallery example too
@pytest.mark.parametrize("example", sorted((DOCS / "gallery").glob("plot_*.py")),
                         ids=lambda p: p.name)
def test_gallery_examples_run(example, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    monkeypatch.chdir(example.parent)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*non-interactive.*")
        runpy.run_path(str(example), run_name="__main__")
    assert plt.get_fignums(), f"{example.name} draws no figure"
    plt.close("all")


def test_every_config_key_has_a_description():
    from nlyap_opt.workflow.configs import config_reference, schema

    missing = [k.name for sec in schema().values() for k in sec.values() if not k.doc.strip()]
    assert not missing, f"config keys without a description: {missing}"
    ref = config_reference()
    for sec in schema().values():
        for key in sec.values():
            row = next(r for r in ref.splitlines() if r.startswith(f"| `{key.name}` |"))
            assert row.rstrip(" |").endswith(key.doc.replace("|", "\\|").strip())


def test_every_cli_argument_has_help():
    sys.path.insert(0, str(DOCS / "_ext"))
    try:
        from nlyap_docs import cli_reference
    finally:
        sys.path.remove(str(DOCS / "_ext"))
    text = cli_reference()      # raises on an argument without help
    for cmd in ("run", "verify", "config", "compare", "learn-dynamics", "systems", "lqr"):
        assert f"## nlyap {cmd}" in text
    for code in (0, 1, 2, 3, 4, 5, 130):
        assert f"| {code} |" in text


def test_readme_is_short_and_pages_cite_nothing_outside():
    assert len((ROOT / "README.md").read_text().splitlines()) <= 150
    history = re.compile(r"previous round|the former |used to (cost|take)|before this",
                         re.IGNORECASE)
    outside = re.compile(r"PITFALLS|METHOD §|\bissue \d+", re.IGNORECASE)
    for page in _pages():
        text = page.read_text()
        assert not outside.search(text), f"{page}: {outside.search(text).group(0)!r}"
        if page.name != "changelog.md":
            assert not history.search(text), f"{page}: {history.search(text).group(0)!r}"


@pytest.mark.slow
def test_docs_build_without_warnings(tmp_path):
    pytest.importorskip("sphinx")
    pytest.importorskip("myst_parser")
    pytest.importorskip("numpydoc")
    pytest.importorskip("sphinx_gallery")
    proc = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b",
                           "html", str(DOCS), str(tmp_path / "html")],
                          capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert proc.returncode == 0, proc.stderr[-4000:]
