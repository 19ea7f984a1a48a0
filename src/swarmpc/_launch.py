"""The ``swarmpc`` command's entry point: Ctrl-C while the command line is still being imported
(numpy, CasADi, the CLI library: a few tenths of a second) ends with one line and status 130, not
a traceback, like Ctrl-C at any later moment."""

from __future__ import annotations

import sys

INTERRUPTED = 130


def caused_by_interrupt(error: BaseException) -> bool:
    """Whether ``error`` is a Ctrl-C or was raised while handling one.

    A Ctrl-C that lands inside a compiled extension's initialisation comes out as that module's
    import error, with the ``KeyboardInterrupt`` as its cause or context.
    """
    seen: set[int] = set()
    current: BaseException | None = error
    while current is not None and id(current) not in seen:
        if isinstance(current, KeyboardInterrupt):
            return True
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return False


def main() -> None:
    try:
        from swarmpc.cli import main as cli_main
    except BaseException as error:  # noqa: BLE001 - only interrupts are swallowed, see below
        if not caused_by_interrupt(error):
            raise
        sys.stderr.write("swarmpc: interrupted\n")
        sys.exit(INTERRUPTED)
    cli_main()
