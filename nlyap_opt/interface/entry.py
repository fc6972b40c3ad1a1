"""The ``nlyap`` console script: the command line, imported inside a Ctrl-C guard.

Importing the command line loads numpy, CasADi and the toolbox (about a second); a Ctrl-C
in that second ends here with one line and exit 130, not a traceback. ``import nlyap_opt``
itself stays light (its public names load on first use), so nothing heavy runs before
this guard.
"""

from __future__ import annotations

import sys


def main(argv=None) -> int:
    """Run ``nlyap`` (:func:`nlyap_opt.interface.cli.main`); 130 when interrupted while
    the command line is still being imported."""
    try:
        from .cli import main as cli_main  # lazy: inside the Ctrl-C guard (module docstring)
    except KeyboardInterrupt:
        print("nlyap: interrupted while starting; nothing was run", file=sys.stderr)
        return 130
    return cli_main(argv)


if __name__ == "__main__":
    sys.exit(main())
