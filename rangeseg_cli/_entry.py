"""The ``rangeseg`` command's entry point: Ctrl-C while the modules load exits 130.

:func:`rangeseg_cli.cli.main.main` handles Ctrl-C once it runs; this covers the
import before it (numpy, click), which otherwise ends in a traceback.
"""

from __future__ import annotations

import sys


def main() -> None:
    """Import the command line and run it."""
    try:
        from .cli.main import main as cli
    except KeyboardInterrupt:
        sys.stderr.write("interrupted\n")
        raise SystemExit(130) from None
    cli()
