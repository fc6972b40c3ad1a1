"""Pages generated from the code at build time: the configuration keys and the CLI.

``docs/_generated/config_keys.md`` is :func:`nlyap_opt.workflow.configs.config_reference` (the
output of ``nlyap config --keys``); ``docs/_generated/cli.md`` walks the argument parser of
:func:`nlyap_opt.interface.cli.build_parser`: every command, every option with its help text, and
the exit codes. The pages ``configuration.md`` and ``cli.md`` include them, so the
reference cannot drift from the code.
"""

from __future__ import annotations

import argparse
from pathlib import Path

__all__ = ["cli_reference", "setup"]


def _cell(text: str) -> str:
    return " ".join(str(text or "").split()).replace("|", "\\|")


def _option_rows(parser: argparse.ArgumentParser) -> list[str]:
    rows = ["| argument | default | description |", "| --- | --- | --- |"]
    for action in parser._actions:
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        if action.option_strings:
            name = ", ".join(action.option_strings)
            if action.nargs != 0:
                name += " " + (action.metavar or action.dest.upper())
        else:
            name = action.metavar or action.dest
        if action.choices and not isinstance(action.choices, dict):
            name += " {" + ",".join(str(c) for c in action.choices) + "}"
        default = action.default
        shown = "" if default in (None, False, argparse.SUPPRESS) else f"`{default}`"
        if not action.help:
            raise ValueError(f"CLI argument {name!r} of {parser.prog!r} has no help text")
        rows.append(f"| `{_cell(name)}` | {shown} | {_cell(action.help)} |")
    return rows


def cli_reference() -> str:
    """Markdown reference of every ``nlyap`` command, option and exit code."""
    from nlyap_opt.interface.cli import EXIT_CODES, build_parser

    parser = build_parser()
    out = ["## Global options", "", f"`{_cell(parser.format_usage().strip())}`", ""]
    out += _option_rows(parser)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    helps = {c.dest: c.help for c in sub._choices_actions}
    for name, sp in sub.choices.items():
        out += ["", f"## nlyap {name}", "", _cell(sp.description or helps.get(name, "")), "",
                "```text", sp.format_usage().strip(), "```", ""]
        out += _option_rows(sp)
        if sp.epilog:
            out += ["", "```text", sp.epilog.strip(), "```"]
    out += ["", "## Exit codes", "", "| code | meaning |", "| --- | --- |"]
    out += [f"| {code} | {_cell(text)} |" for code, text in EXIT_CODES.items()]
    return "\n".join(out) + "\n"


def _write_if_changed(path: Path, text: str) -> None:
    if not path.exists() or path.read_text() != text:
        path.write_text(text)


def _generate(app) -> None:
    from nlyap_opt.workflow.configs import config_reference

    out = Path(app.srcdir) / "_generated"
    out.mkdir(exist_ok=True)
    _write_if_changed(out / "config_keys.md", config_reference() + "\n")
    _write_if_changed(out / "cli.md", cli_reference())


def setup(app):
    app.connect("builder-inited", _generate)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
