"""``tools/relayout.py``, the move of ``nlyap_opt``'s modules into layer folders: its
rewrites on small texts (names, paths, imports, contracts, long rows), independent of the
layout of the checkout it runs in (this file is one the script leaves as it is)."""

from __future__ import annotations

import ast
import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def relayout():
    spec = importlib.util.spec_from_file_location("relayout", ROOT / "tools" / "relayout.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["relayout"] = mod
    try:
        spec.loader.exec_module(mod)
    finally:
        del sys.modules["relayout"]
    return mod


@pytest.fixture(scope="module")
def where(relayout):
    return relayout.folder_of()


def test_every_module_has_one_folder_and_folders_are_not_modules(relayout, where):
    assert where["cli"] == "interface" and where["errors"] == "kernel"
    assert len(where) == sum(len(ms) for _, ms in relayout.FOLDERS.values())
    assert not set(relayout.FOLDERS) & set(where)


def test_names_paths_and_globs_are_rewritten_once(relayout, where):
    text = ('import nlyap_opt.cli_args\nx = "nlyap_opt.cli:main"  # nlyap_opt.rounding.U\n'
            'p = "nlyap_opt/rounding.py"; g = "!nlyap_opt/{cli,pipeline}.py"\n'
            "v = nlyap_opt.__version__; q = 'nlyap_opt/__init__.py'; mynlyap_opt.cli = 1\n"
            "    from nlyap_opt import cli, run as r, deps  # lazy: heavy\n")
    once = relayout.rewrite_references(text, where)
    assert once == (
        'import nlyap_opt.interface.cli_args\n'
        'x = "nlyap_opt.interface.cli:main"  # nlyap_opt.kernel.rounding.U\n'
        'p = "nlyap_opt/kernel/rounding.py"; '
        'g = "!nlyap_opt/{interface/cli,workflow/pipeline}.py"\n'
        "v = nlyap_opt.__version__; q = 'nlyap_opt/__init__.py'; mynlyap_opt.cli = 1\n"
        "    from nlyap_opt.interface import cli  # lazy: heavy\n"
        "    from nlyap_opt import run as r  # lazy: heavy\n"
        "    from nlyap_opt.kernel import deps  # lazy: heavy\n")
    assert relayout.rewrite_references(once, where) == once


def test_relative_imports_follow_the_folders(relayout, where):
    text = ("from . import deps\nfrom .errors import ConfigError\nfrom .bounds import M\n"
            "def f():\n    from . import parallel, roa  # lazy: heavy\n")
    moved = relayout.rewrite_relative_imports(text, "learned", where, "x.py")
    assert moved == ("from ..kernel import deps\nfrom ..kernel.errors import ConfigError\n"
                     "from .bounds import M\ndef f():\n"
                     "    from ..distributed import parallel  # lazy: heavy\n"
                     "    from ..certification import roa  # lazy: heavy\n")
    root = relayout.rewrite_relative_imports("from .errors import E\n", None, where, "i.py")
    assert root == "from .kernel.errors import E\n"
    assert relayout.rewrite_relative_imports(root, None, where, "i.py") == root


def test_folder_contracts_keep_every_rule_or_refuse(relayout, where):
    layers = [["nlyap_opt.cli"], ["nlyap_opt.cli_args"], ["baselines"],
              ["nlyap_opt.errors", "nlyap_opt.rounding"]]
    order, extra = relayout.new_contracts(layers, where)
    assert order == ["nlyap_opt.interface", "baselines", "nlyap_opt.kernel"]
    assert "containers =\n    nlyap_opt.interface\nexhaustive = true\nlayers =\n" \
           "    cli\n    cli_args\n" in extra
    assert "nlyap_opt.kernel\n" not in extra         # one layer in kernel: no contract
    with pytest.raises(relayout.RelayoutError, match="interleave"):
        relayout.new_contracts([["nlyap_opt.cli"], ["baselines"], ["nlyap_opt.cli_args"]],
                               where)


def test_long_rows_are_wrapped_without_changing_the_program(relayout):
    long_word = "nlyap_opt.certification.certificate.certify_roa"
    text = (f'def f(a, b):\n    """Call {long_word} and {long_word} on the\n'
            '    closed loop.\n    """\n'
            f'    return g(a, b, "{long_word}", "{long_word}", c=1)\n'
            f'# a comment naming {long_word} and {long_word}\n'
            f'x = """{"w " * 60}"""\n')
    before = f'x = """{"w " * 60}"""\n'
    out, stuck = relayout.wrap_long_lines(text, "m.py", 100, before)
    assert stuck == []
    assert max(len(r) for r in out.splitlines() if not r.startswith("x =")) <= 100
    assert relayout._shape(out) == relayout._shape(text)
    assert ast.get_docstring(ast.parse(out).body[0]).split() == \
        ast.get_docstring(ast.parse(text).body[0]).split()
    assert out.endswith(before)                      # long before the rewrite: kept
    code = 'x = f("""\n' + "word " * 30 + '\n""")\n'  # inside a string: cannot wrap
    assert relayout.wrap_long_lines(code, "n.py", 100)[1] == ["n.py:2"]
