"""Move the modules of ``nlyap_opt/`` into one folder per import layer; rewrite every reference.

Run from the repository root of a git checkout::

    python tools/relayout.py            # move and rewrite (a second run changes nothing)
    python tools/relayout.py --dry-run  # print the plan, change nothing

What it does, in this order (nothing is changed before every check has passed):

1. finds the modules ``nlyap_opt/*.py`` and the folder of each (:data:`FOLDERS`); a module
   without a folder, a folder module that also lies at the top level, or an untracked module
   stops the script before any change, naming them;
2. rewrites the import layers of ``setup.cfg``: the main contract lists the folders (with
   ``baselines``, ``verification`` and ``systems`` where they were); a folder whose modules
   were in more than one layer gets a contract of its own (``containers``, ``exhaustive``)
   that keeps their order, so that no dependency rule is lost. The folder order must agree
   with the old layer order (checked: the script stops otherwise);
3. rewrites the relative imports of the moved modules and of ``nlyap_opt/__init__.py``
   (``from .x import`` and ``from . import x`` to the new relative form);
4. rewrites every dotted name ``nlyap_opt.<module>``, every path ``nlyap_opt/<module>``
   (also inside a glob ``nlyap_opt/{a,b}.py``) and every ``from nlyap_opt import <module>``
   in the tracked text files (``.py .md .cfg .toml .txt .ini .json .rst`` and ``Makefile``;
   ``docs/changelog.md`` is history and keeps the names of its time);
5. ``git mv`` each module into its folder and writes each folder's ``__init__.py`` (its
   docstring describes the layer; no re-exports);
6. wraps the rows that the longer names push over ruff's ``line-length`` (docstrings and
   comments are reflowed into their paragraph, code is split inside brackets; the program
   is checked to be the same) and sorts the imports of the rewritten Python files
   (``ruff check --select I --fix``), since the new dotted names sort differently.

Saved artifacts (certificate.json and the other run files) name no module, so the move
changes no file format. Exit status: 0 done (or nothing to do), 3 a check failed (the
message says what to fix).
"""

from __future__ import annotations

import argparse
import ast
import configparser
import io
import re
import shutil
import subprocess
import sys
import tokenize
from pathlib import Path

__all__ = ["FOLDERS", "main"]

PACKAGE = "nlyap_opt"

#: the folders of ``nlyap_opt/``, top layer first: folder -> (docstring, modules)
FOLDERS: dict[str, tuple[str, tuple[str, ...]]] = {
    "interface": (
        "The ``nlyap`` command line: the commands, their argument types and exit codes (the "
        "top layer; it may import every other layer).",
        ("cli", "cli_args", "cli_dynamics", "cli_deploy")),
    "workflow": (
        "Whole runs: the validated run configuration and its presets, the resumable "
        "pipeline of stages, the run report, and the multi-seed portfolio.",
        ("portfolio", "pipeline", "report", "configs")),
    "candidates": (
        "Candidate Lyapunov functions and controllers: the neural learner, the CEGIS loop, "
        "and the quadratic and sum-of-squares candidates, each re-certified by the "
        "certificate kernel.",
        ("cegis", "learning", "quadratic", "sos")),
    "deployment": (
        "A certificate put to use: re-verified runs and closed-loop simulation, C99 and "
        "ONNX export, and the CLF-QP safety filter.",
        ("deploy", "export", "filter")),
    "certification": (
        "The certificate kernel: the one definition of conditions (a), (b), (c) of a "
        "region of attraction, the level search, and compositional certificates of "
        "interconnected systems.",
        ("certificate", "compositional", "roa")),
    "learned": (
        "Learned dynamics of an unknown system: the network φ and its training, the "
        "configuration and the stage with its η gate, the error models and their sound "
        "bounds (Lipschitz constants, interval suprema), and the inner set proved from data.",
        ("dynamics", "bounds", "lipschitz", "dynamics_config", "dynamics_stage",
         "error_models", "interval_sup", "phi_training", "inner_from_data")),
    "design": (
        "Controller design and exact polynomials: the LQR start, quadratic Lyapunov "
        "matrices, and the semidefinite programs of the sum-of-squares candidates.",
        ("control", "sos_sdp", "polynomial")),
    "distributed": (
        "Parallel and distributed work: the Dask client helper and load-balanced "
        "verification.",
        ("parallel",)),
    "kernel": (
        "The core: networks and their CasADi graphs, closed loops and Lie derivatives, "
        "the graph walker, simulation, the rounding model, domains, grids and samples, "
        "JSON input, provenance, determinism, the errors and the optional dependencies "
        "(the bottom layer; it imports no other layer of the project).",
        ("symbolic", "network", "walker", "simulate", "determinism", "provenance",
         "sampling", "jsonio", "grid", "domain", "errors", "rounding", "deps")),
}

#: files of the package root that stay where they are
ROOT_FILES = ("__init__.py", "__main__.py")

#: suffixes (and names) of the tracked text files whose references are rewritten
TEXT_SUFFIXES = (".py", ".md", ".cfg", ".toml", ".txt", ".ini", ".json", ".rst", ".in")
TEXT_NAMES = ("Makefile",)

#: tracked files left as they are: the changelog is history; the script and its test name
#: the old modules on purpose
KEEP = ("docs/changelog.md", "tools/relayout.py", "tests/test_relayout.py")

LAYERS_SECTION = "importlinter:contract:layers"


class RelayoutError(Exception):
    """A check failed; the message names the problem and the fix."""


# --------------------------------------------------------------------------- the plan
def folder_of() -> dict[str, str]:
    """Module base name -> folder, from :data:`FOLDERS` (checked: names distinct)."""
    out: dict[str, str] = {}
    for folder, (_, modules) in FOLDERS.items():
        if folder in {m for _, ms in FOLDERS.values() for m in ms}:
            raise RelayoutError(f"folder {folder!r} is also a module name; rename the folder "
                                "in FOLDERS (tools/relayout.py)")
        for m in modules:
            if m in out:
                raise RelayoutError(f"module {m!r} is in two folders of FOLDERS")
            out[m] = folder
    return out


def _git(*args: str, check: bool = True) -> str:
    res = subprocess.run(["git", *args], capture_output=True, text=True)
    if check and res.returncode != 0:
        raise RelayoutError(f"git {' '.join(args)} failed: {res.stderr.strip()}")
    return res.stdout


def plan(root: Path) -> tuple[dict[str, str], list[str]]:
    """``(module -> folder for every module present, modules still to move)``."""
    where = folder_of()
    pkg = root / PACKAGE
    top = sorted(p.stem for p in pkg.glob("*.py") if p.name not in ROOT_FILES)
    unknown = [m for m in top if m not in where]
    if unknown:
        raise RelayoutError(
            "modules with no folder: " + ", ".join(f"{PACKAGE}/{m}.py" for m in unknown)
            + "; add each to a folder of FOLDERS in tools/relayout.py (the folder of its "
            "import layer) and run again")
    twice = [m for m in top if (pkg / where[m] / f"{m}.py").exists()]
    if twice:
        raise RelayoutError("modules both at the top level and in their folder: "
                            + ", ".join(twice) + "; keep one copy and run again")
    present = {m: f for m, f in where.items()
               if m in top or (pkg / f / f"{m}.py").exists()}
    tracked = set(_git("ls-files", "--", PACKAGE).split())
    untracked = [f"{PACKAGE}/{m}.py" for m in top if f"{PACKAGE}/{m}.py" not in tracked]
    if untracked:
        raise RelayoutError("untracked modules: " + ", ".join(untracked)
                            + "; git add (or remove) them and run again")
    return present, top


# --------------------------------------------------------------------------- setup.cfg
def _parse_layers(raw: str) -> list[list[str]]:
    return [[m.strip() for m in line.split(":") if m.strip()]
            for line in raw.strip().splitlines() if line.strip()]


def _unit(name: str, where: dict[str, str]) -> str:
    """The new top-level layer of a module of the old contract."""
    prefix = PACKAGE + "."
    if name.startswith(prefix) and name[len(prefix):] in where:
        return f"{prefix}{where[name[len(prefix):]]}"
    return name


def new_contracts(layers: list[list[str]], where: dict[str, str]) -> tuple[list[str], str]:
    """The folder layers of the main contract and the text of the folder contracts.

    Raises :class:`RelayoutError` where a folder order would drop a rule of ``layers``:
    every module of an upper unit must have been in a layer above or beside every module of
    a lower unit.
    """
    order: list[str] = []
    span: dict[str, list[int]] = {}
    for i, layer in enumerate(layers):
        for name in layer:
            u = _unit(name, where)
            if u not in span:
                order.append(u)
                span[u] = [i, i]
            span[u][1] = i
    order.sort(key=lambda u: (span[u][0], span[u][1]))
    for upper, lower in zip(order, order[1:]):
        if span[upper][1] > span[lower][0]:
            raise RelayoutError(
                f"{upper} (layers {span[upper][0]}-{span[upper][1]}) and {lower} (layers "
                f"{span[lower][0]}-{span[lower][1]}) interleave in [{LAYERS_SECTION}]; move "
                "modules between folders in FOLDERS so that each folder is a block of "
                "consecutive layers")
    extra = []
    for folder in FOLDERS:
        inner = []
        for layer in layers:
            mods = [n[len(PACKAGE) + 1:] for n in layer
                    if n.startswith(PACKAGE + ".") and where.get(n[len(PACKAGE) + 1:]) == folder]
            if mods:
                inner.append(" : ".join(mods))
        if len(inner) > 1:
            body = "\n".join(f"    {line}" for line in inner)
            extra.append(f"[importlinter:contract:{folder}]\n"
                         f"name = {folder}: " + " > ".join(
                             line.replace(" : ", ", ") for line in inner) + "\n"
                         f"type = layers\ncontainers =\n    {PACKAGE}.{folder}\n"
                         f"exhaustive = true\nlayers =\n{body}\n")
    return order, "\n".join(extra)


def rewrite_setup_cfg(text: str, where: dict[str, str]) -> str:
    """``setup.cfg`` with the main contract over folders and one contract per ordered
    folder (unchanged if its contract names no module of a folder)."""
    cfg = configparser.ConfigParser()
    cfg.read_string(text)
    if LAYERS_SECTION not in cfg:
        raise RelayoutError(f"setup.cfg has no [{LAYERS_SECTION}]; nothing to map the "
                            "folders onto")
    layers = _parse_layers(cfg[LAYERS_SECTION]["layers"])
    if not any(_unit(n, where) != n for layer in layers for n in layer):
        return text                                  # already folders
    named = {n[len(PACKAGE) + 1:] for layer in layers for n in layer
             if n.startswith(PACKAGE + ".")}
    unlayered = sorted(set(where) - named)
    if unlayered:
        raise RelayoutError("modules in no layer of setup.cfg: " + ", ".join(unlayered)
                            + f"; add each to [{LAYERS_SECTION}] and run again")
    order, extra = new_contracts(layers, where)
    lines = text.splitlines(keepends=True)
    start = next(i for i, ln in enumerate(lines) if ln.strip() == f"[{LAYERS_SECTION}]")
    i = start + 1
    out = lines[:start + 1]
    while i < len(lines) and not lines[i].startswith("["):
        ln = lines[i]
        if ln.startswith("name ="):
            short = [u.split(".")[-1] for u in order]
            out.append("name = Layers: " + " > ".join(short) + "\n")
        elif ln.startswith("layers ="):
            out.append(ln)
            i += 1
            while i < len(lines) and lines[i][:1] in (" ", "\t") and lines[i].strip():
                i += 1
            out += [f"    {u}\n" for u in order]
            continue
        else:
            out.append(ln)
        i += 1
    while out and not out[-1].strip():
        out.pop()
    note = ("# Each folder of nlyap_opt/ is one layer above; a folder whose modules are "
            "ordered\n# among themselves has a contract of its own below (exhaustive: a new "
            "module of\n# that folder must be placed in one of its layers).\n")
    tail = "".join(lines[i:])
    return "".join(out) + "\n" + note + extra + ("\n" + tail if tail.strip() else "")


# --------------------------------------------------------------------------- imports
def _relative(src: str | None, folder: str) -> str:
    """The relative package of ``folder`` seen from a module of folder ``src`` (None: the
    package root)."""
    if src is None:
        return "." + folder
    return "." if src == folder else ".." + folder


def _names(stmt: ast.ImportFrom) -> list[str]:
    return [a.name + (f" as {a.asname}" if a.asname else "") for a in stmt.names]


def _grouped(indent: str, base: str, names: list[tuple[str, str | None]],
             comment: str) -> str:
    """One ``from PKG import ...`` line per package: ``names`` is ``(name, package)``, a
    package of None meaning ``base``."""
    groups: dict[str, list[str]] = {}
    for name, pkg in names:
        groups.setdefault(pkg or base, []).append(name)
    return "\n".join(f"{indent}from {pkg} import {', '.join(ns)}{comment}"
                     for pkg, ns in groups.items())


def rewrite_relative_imports(text: str, src: str | None, where: dict[str, str],
                             rel: str) -> str:
    """Rewrite the level-1 imports of a module that moves to folder ``src`` (None: stays at
    the package root)."""
    tree = ast.parse(text, filename=rel)
    lines = text.splitlines(keepends=True)
    for stmt in sorted((n for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)
                        and n.level == 1), key=lambda n: -n.lineno):
        first = lines[stmt.lineno - 1]
        head = first[stmt.col_offset:]
        if stmt.module:
            base = stmt.module.split(".")[0]
            if base not in where:
                continue                              # already a folder path
            pkg = _relative(src, where[base])
            new = ("" if pkg == "." else pkg) + "." + stmt.module
            m = re.match(r"from\s+\.\s*" + re.escape(stmt.module) + r"\b", head)
            if not m:
                raise RelayoutError(f"{rel}:{stmt.lineno}: cannot parse {head.strip()!r}")
            lines[stmt.lineno - 1] = (first[:stmt.col_offset] + f"from {new}"
                                      + head[m.end():])
            continue
        mods = [a.name for a in stmt.names]
        if not all(a in where for a in mods):
            if any(a in where for a in mods):
                raise RelayoutError(f"{rel}:{stmt.lineno}: `from . import` mixes modules "
                                    "and names; split it and run again")
            continue
        targets = {_relative(src, where[a]) for a in mods}
        m = re.match(r"from\s+\.\s+import\s+", head)
        if not m:
            raise RelayoutError(f"{rel}:{stmt.lineno}: cannot parse {head.strip()!r}")
        if len(targets) == 1:
            lines[stmt.lineno - 1] = (first[:stmt.col_offset]
                                      + f"from {targets.pop()} import " + head[m.end():])
            continue
        if stmt.end_lineno != stmt.lineno or "(" in head:
            raise RelayoutError(f"{rel}:{stmt.lineno}: a multi-line `from . import` of "
                                "modules of several folders; split it and run again")
        comment = head[head.index("#"):].rstrip("\n") if "#" in head else ""
        comment = ("  " + comment) if comment else ""
        names = [(n, _relative(src, where[a.name])) for n, a in zip(_names(stmt), stmt.names)]
        lines[stmt.lineno - 1] = (_grouped(first[:stmt.col_offset], ".", names, comment)
                                  + "\n")
    return "".join(lines)


# --------------------------------------------------------------------------- names, paths
def _alternation(where: dict[str, str]) -> str:
    return "|".join(sorted(map(re.escape, where), key=lambda m: (-len(m), m)))


def rewrite_references(text: str, where: dict[str, str]) -> str:
    """Dotted names, paths, globs and ``from nlyap_opt import <module>`` lines."""
    alt = _alternation(where)
    text = re.sub(rf"(?<![\w.]){PACKAGE}\.({alt})(?!\w)",
                  lambda m: f"{PACKAGE}.{where[m.group(1)]}.{m.group(1)}", text)
    text = re.sub(rf"(?<![\w.]){PACKAGE}/({alt})(?![\w{{}}])",
                  lambda m: f"{PACKAGE}/{where[m.group(1)]}/{m.group(1)}", text)

    def glob(m: re.Match) -> str:
        items = [f"{where[i]}/{i}" if i in where else i for i in m.group(1).split(",")]
        return f"{PACKAGE}/{{{','.join(items)}}}"

    text = re.sub(rf"(?<![\w.]){PACKAGE}/\{{([\w,/]*)\}}", glob, text)

    def from_import(m: re.Match) -> str:
        indent, body, comment = m.group(1), m.group(2), m.group(3) or ""
        names = []
        for item in (s.strip() for s in body.split(",")):
            if not item:
                continue
            base = item.split()[0]
            names.append((item, f"{PACKAGE}.{where[base]}" if base in where else None))
        if all(p is None for _, p in names):
            return m.group(0)
        return _grouped(indent, PACKAGE, names, comment)

    return re.sub(rf"(?m)^([ \t]*)from {PACKAGE} import ([\w ,]+?)([ \t]*#[^\n]*)?$",
                  from_import, text)


def text_files(root: Path) -> list[Path]:
    """The tracked text files whose references are rewritten."""
    out = []
    for rel in sorted(_git("ls-files").splitlines()):
        path = root / rel
        if rel in KEEP or not path.is_file() or path.is_symlink():
            continue
        if path.suffix in TEXT_SUFFIXES or path.name in TEXT_NAMES:
            out.append(path)
    return out


# --------------------------------------------------------------------------- long lines
_MARKER = re.compile(r"(- |\* |\d+\. )")


def line_limit(root: Path) -> int:
    """``line-length`` of ruff in ``pyproject.toml`` (100 without one)."""
    path = root / "pyproject.toml"
    m = re.search(r"(?m)^line-length\s*=\s*(\d+)", path.read_text()) if path.exists() else None
    return int(m.group(1)) if m else 100


def _docstring_rows(tree: ast.Module) -> dict[int, tuple[int, int]]:
    """Row -> (first row, last row) of the docstring-like string statement holding it."""
    out = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant) \
                and isinstance(node.value.value, str):
            for row in range(node.lineno, node.end_lineno + 1):
                out[row] = (node.lineno, node.end_lineno)
    return out


def _split_at(line: str, start: int, limit: int) -> int | None:
    """The column of the last space in ``line[start:limit + 1]`` with text before it."""
    p = line.rfind(" ", start, limit + 1)
    return p if p > start and line[start:p].strip() else None


def _reflow(lines: list[str], i: int, indent: str, start: int, limit: int,
            joinable) -> bool:
    """Move the words of row ``i`` beyond ``limit`` to the next row if ``joinable(i + 1)``,
    else onto a new row starting with ``indent``."""
    line = lines[i].rstrip("\n")
    p = _split_at(line, start, limit)
    if p is None:
        return False
    head, tail = line[:p].rstrip(), line[p + 1:].strip()
    lines[i] = head + "\n"
    if i + 1 < len(lines) and joinable(i + 1):
        lines[i + 1] = indent + tail + " " + lines[i + 1][len(indent):]
    else:
        lines.insert(i + 1, indent + tail + "\n")
    return True


def _wrap_docstring(lines: list[str], i: int, span: tuple[int, int], limit: int) -> bool:
    first, last = span[0] - 1, span[1] - 1
    block = i
    while block > first and lines[block - 1].strip():
        block -= 1
    if any(ln.lstrip().startswith(">>>") for ln in lines[block:i + 1]):
        return False                                  # a doctest: exact text
    line = lines[i]
    indent = line[:len(line) - len(line.lstrip())]
    start = len(indent)
    if i == first:
        quotes = re.match(r"[rRuU]?(\"\"\"|''')", line.lstrip())
        if not quotes:
            return False
        start += len(quotes.group(0))
    else:
        m = _MARKER.match(line[start:])
        if m:
            indent, start = indent + " " * len(m.group(0)), start + len(m.group(0))

    def joinable(j: int) -> bool:
        nxt = lines[j]
        text = nxt[len(indent):]
        return (i < last and j < last and nxt.startswith(indent) and text.strip() != ""
                and not text[:1].isspace() and not _MARKER.match(text)
                and not text.startswith((">>>", ":", "..", '"""', "'''"))
                and set(text.strip()) - set("-=~^") != set()
                and not (j + 1 <= last and set(lines[j + 1].strip()) <= set("-=~^")
                         and lines[j + 1].strip()))

    return _reflow(lines, i, indent, start, limit, joinable)


def _wrap_comment(lines: list[str], i: int, col: int, limit: int) -> bool:
    line = lines[i]
    prefix = re.match(r"#:?\s?", line[col:]).group(0)
    whole = not line[:col].strip()
    indent = " " * col + prefix

    def joinable(j: int) -> bool:
        return whole and lines[j].startswith(indent) and bool(lines[j][len(indent):].strip()) \
            and not lines[j][len(indent):][:1].isspace()

    return _reflow(lines, i, indent, col + len(prefix), limit, joinable)


def _wrap_code(lines: list[str], i: int, toks: list, limit: int) -> bool:
    """Split row ``i`` after a comma inside brackets, else between two literals of a
    string inside brackets, else with a backslash."""
    line = lines[i].rstrip("\n")
    row = i + 1
    stack: list[tokenize.TokenInfo] = []
    commas, strings, gaps = [], [], []
    prev = None
    for tok in toks:
        if tok.start[0] > row:
            break
        if tok.type == tokenize.OP and tok.string in "([{":
            stack.append(tok)
        elif tok.type == tokenize.OP and tok.string in ")]}":
            stack.pop()
        if tok.start[0] != row or tok.type in (tokenize.NL, tokenize.NEWLINE,
                                                tokenize.COMMENT):
            prev = tok
            continue
        if stack:
            opener = stack[-1]
            hanging = all(t.start[0] != opener.start[0] or t.start <= opener.start
                          or t.type in (tokenize.NL, tokenize.COMMENT) for t in toks)
            lead = len(line) - len(line.lstrip())
            cont = " " * (opener.start[1] + 1 if not hanging
                          else lead + 4 if opener.start[0] == row else lead)
            if tok.string == "," and tok.end[1] <= limit:
                commas.append((tok.end[1], cont))
            elif tok.type == tokenize.STRING and tok.start[0] == tok.end[0]:
                m = re.match(r"([rRbBuU]*)('|\")", tok.string)
                if m and tok.string[len(m.group(0)):][:2] != m.group(2) * 2:
                    strings.append((tok, m.group(1), m.group(2), cont))
        elif prev is not None and prev.end[0] == row and prev.end[1] < tok.start[1] \
                and tok.start[1] <= limit - 2:
            gaps.append(prev.end[1])
        prev = tok
    rest_after = {c for c, _ in commas if line[c:].strip() and not line[c:].lstrip()
                  .startswith("#")}
    commas = [(c, cont) for c, cont in commas if c in rest_after]
    if commas:
        c, cont = max(commas)
        lines[i:i + 1] = [line[:c].rstrip() + "\n", cont + line[c:].lstrip() + "\n"]
        return True
    for tok, pre, q, cont in sorted(strings, key=lambda s: -s[0].start[1]):
        if "f" in pre.lower():
            continue
        body_start = tok.start[1] + len(pre) + 1
        p = line.rfind(" ", body_start, min(limit - 1, tok.end[1] - 2))
        if p > body_start:
            lines[i:i + 1] = [line[:p + 1] + q + "\n", cont + pre + q + line[p + 1:] + "\n"]
            return True
    if gaps:
        c = max(gaps)
        lead = len(line) - len(line.lstrip())
        lines[i:i + 1] = [line[:c] + " \\\n", " " * (lead + 4) + line[c:].lstrip() + "\n"]
        return True
    return False


def _shape(text: str) -> str:
    """The AST of ``text`` with the whitespace of every string normalised."""
    tree = ast.parse(text)
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            node.value = " ".join(node.value.split())
    return ast.dump(tree)


def wrap_long_lines(text: str, rel: str, limit: int, before: str = "") -> tuple[str, list[str]]:
    """``text`` with its rows above ``limit`` characters wrapped, and ``file:row`` of the
    rows it could not wrap; rows already as long in ``before`` (the text before the rewrite)
    stay as they are. Docstrings and comments are reflowed into the next row of the
    same paragraph; code is split inside brackets or with a backslash. The program is the
    same before and after (checked: the ASTs agree up to whitespace inside strings)."""
    stuck: set[int] = set()
    shape = _shape(text)
    pragma = re.compile(r"\s+#\s*(noqa|type:\s*ignore|pyright:\s*ignore)\b.*$")
    kept = {ln for ln in before.splitlines() if len(ln) > limit}   # ruff allows them

    def too_long(ln: str) -> bool:
        ln = ln.rstrip("\n")
        return len(pragma.sub("", ln)) > limit and ln not in kept

    for _ in range(10_000):
        lines = text.splitlines(keepends=True)
        long = [i for i, ln in enumerate(lines) if too_long(ln) and i not in stuck]
        if not long:
            break
        i = long[0]
        tree = ast.parse(text)
        docs = _docstring_rows(tree)
        toks = list(tokenize.generate_tokens(io.StringIO(text).readline))
        comment = next((t for t in toks if t.type == tokenize.COMMENT
                        and t.start[0] == i + 1), None)
        code_end = len(lines[i][:comment.start[1]].rstrip()) if comment else 0
        if i + 1 in docs and not comment:
            ok = _wrap_docstring(lines, i, docs[i + 1], limit)
        elif comment and code_end <= limit:
            ok = _wrap_comment(lines, i, comment.start[1], limit)
        else:
            ok = _wrap_code(lines, i, toks, limit)
        if not ok:
            stuck.add(i)
            continue
        text = "".join(lines)
    if _shape(text) != shape:
        raise RelayoutError(f"{rel}: wrapping its long lines would change the program; "
                            "wrap them by hand")
    rows = text.splitlines()
    return text, [f"{rel}:{i + 1}" for i in sorted(stuck) if too_long(rows[i])]


# --------------------------------------------------------------------------- main
def _init_text(folder: str) -> str:
    doc, _ = FOLDERS[folder]
    words, lines, line = doc.split(), [], ""
    for w in words:
        if len(line) + len(w) + 1 > 88:
            lines.append(line)
            line = w
        else:
            line = f"{line} {w}" if line else w
    lines.append(line)
    body = "\n".join(lines)
    return f'"""{body}\n"""\n'


def run(root: Path, dry_run: bool = False) -> list[str]:
    """Move and rewrite; returns what was done, one line each."""
    where, top = plan(root)
    done: list[str] = []
    cfg_path = root / "setup.cfg"
    cfg_old = cfg_path.read_text(encoding="utf-8")
    cfg_new = rewrite_setup_cfg(cfg_old, where)
    changed: dict[Path, str] = {}
    if cfg_new != cfg_old:
        changed[cfg_path] = cfg_new
    pkg = root / PACKAGE
    for name in [*ROOT_FILES, *(f"{m}.py" for m in top)]:
        path = pkg / name
        if not path.exists():
            continue
        src = None if name in ROOT_FILES else where[path.stem]
        text = changed.get(path, path.read_text(encoding="utf-8"))
        new = rewrite_relative_imports(text, src, where, f"{PACKAGE}/{name}")
        if new != text:
            changed[path] = new
    for path in text_files(root):
        try:
            text = changed.get(path) or path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue                                  # not text
        new = rewrite_references(text, where)
        if new != text:
            changed[path] = new
    limit, stuck = line_limit(root), []
    for path in [p for p in changed if p.suffix == ".py"]:
        changed[path], rows = wrap_long_lines(changed[path], str(path.relative_to(root)),
                                              limit, path.read_text(encoding="utf-8"))
        stuck += rows
    if stuck:
        raise RelayoutError(f"rows above {limit} characters that the script cannot wrap: "
                            + ", ".join(stuck) + "; shorten them before the move")
    inits = [f for f in FOLDERS if any(where.get(m) == f for m in where)
             and not (pkg / f / "__init__.py").exists()]
    for path in sorted(changed):
        done.append(f"rewrite {path.relative_to(root)}")
    for m in top:
        done.append(f"git mv {PACKAGE}/{m}.py {PACKAGE}/{where[m]}/{m}.py")
    for f in inits:
        done.append(f"write {PACKAGE}/{f}/__init__.py")
    if dry_run or not done:
        return done
    for path, text in changed.items():
        path.write_text(text, encoding="utf-8")
    for f in inits:
        (pkg / f).mkdir(exist_ok=True)
        (pkg / f / "__init__.py").write_text(_init_text(f), encoding="utf-8")
        _git("add", "--", f"{PACKAGE}/{f}/__init__.py")
    for m in top:
        _git("mv", "--", f"{PACKAGE}/{m}.py", f"{PACKAGE}/{where[m]}/{m}.py")
    py = [str(p.relative_to(root)) for p in changed if p.suffix == ".py"]
    py = [where_now(root, p, where) for p in py]
    _sort_imports(root, py)
    return done


def where_now(root: Path, rel: str, where: dict[str, str]) -> str:
    """The path of a rewritten file after the move."""
    parts = Path(rel).parts
    if len(parts) == 2 and parts[0] == PACKAGE and Path(rel).stem in where:
        return f"{PACKAGE}/{where[Path(rel).stem]}/{parts[1]}"
    return rel


def _sort_imports(root: Path, files: list[str]) -> None:
    if not files:
        return
    ruff = shutil.which("ruff") or str(Path(sys.executable).with_name("ruff"))
    cmd = ([ruff] if Path(ruff).exists() else [sys.executable, "-m", "ruff"])
    res = subprocess.run([*cmd, "check", "--select", "I", "--fix", "--quiet", *files],
                         cwd=root, capture_output=True, text=True)
    if res.returncode != 0:
        raise RelayoutError("ruff could not sort the imports of the rewritten files "
                            f"({res.stdout.strip() or res.stderr.strip()}); install ruff "
                            "(pip install -e .[dev]) and run `ruff check --select I --fix .`")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dry-run", action="store_true", help="print the plan only")
    args = parser.parse_args(argv)
    root = Path.cwd()
    if not (root / "setup.cfg").is_file() or not (root / PACKAGE).is_dir():
        print(f"relayout: run from the repository root (with setup.cfg and {PACKAGE}/)",
              file=sys.stderr)
        return 3
    try:
        done = run(root, args.dry_run)
    except RelayoutError as err:
        print(f"relayout: {err}", file=sys.stderr)
        return 3
    for line in done:
        print(line)
    print("relayout: " + ("nothing to do" if not done else
                          "planned (dry run)" if args.dry_run else f"{len(done)} changes"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
