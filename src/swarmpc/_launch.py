"""The ``swarmpc`` command's entry point: Ctrl-C while the command line is still being imported
(numpy, CasADi, the CLI library: a few tenths of a second) ends with one line and status 130, not
a traceback, like Ctrl-C at any later moment."""

from __future__ import annotations

import sys

from swarmpc._interrupts import INTERRUPTED, caused_by_interrupt


def main() -> None:
    interrupted: list[BaseException] = []

    def note_interrupts(unraisable: sys.UnraisableHookArgs) -> None:
        # a Ctrl-C that lands in a callback the import machinery runs (a module lock's weakref
        # callback) is "ignored" with a printed traceback and the import goes on: act on it below
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            interrupted.append(unraisable.exc_value)
        else:
            sys.__unraisablehook__(unraisable)

    sys.unraisablehook = note_interrupts
    try:
        from swarmpc.cli import main as cli_main
    except BaseException as error:  # noqa: BLE001 - only interrupts are swallowed, see below
        if not caused_by_interrupt(error):
            raise
        interrupted.append(error)
    finally:
        sys.unraisablehook = sys.__unraisablehook__
    if interrupted:
        sys.stderr.write("swarmpc: interrupted\n")
        sys.exit(INTERRUPTED)
    cli_main()
