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
    interrupted: list[BaseException] = []

    def note_interrupts(unraisable: "sys.UnraisableHookArgs") -> None:
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
