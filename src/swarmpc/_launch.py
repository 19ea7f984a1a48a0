"""The ``swarmpc`` command's entry point: Ctrl-C while the command line is still being imported
(numpy, CasADi, the CLI library: a few tenths of a second) ends with one line and status 130, not
a traceback, like Ctrl-C at any later moment."""

from __future__ import annotations

import sys

INTERRUPTED = 130


def main() -> None:
    try:
        from swarmpc.cli import main as cli_main
    except KeyboardInterrupt:
        sys.stderr.write("swarmpc: interrupted\n")
        sys.exit(INTERRUPTED)
    cli_main()
