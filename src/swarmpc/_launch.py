"""The ``swarmpc`` command's entry point: Ctrl-C while the command line is still being imported
(numpy, CasADi, the CLI library: a few tenths of a second) ends with one line and status 130, not
a traceback, like Ctrl-C at any later moment."""

from __future__ import annotations

import signal
import sys

from swarmpc._interrupts import INTERRUPTED, caused_by_interrupt


def main() -> None:
    interrupted: list[BaseException] = []
    received: list[int] = []

    def on_sigint(signum: int, frame: object) -> None:
        # Python's own reaction (KeyboardInterrupt), remembered: a compiled extension whose
        # initialisation it interrupts may report a plain import error that does not chain it
        received.append(signum)
        raise KeyboardInterrupt

    def note_interrupts(unraisable: sys.UnraisableHookArgs) -> None:
        # a Ctrl-C that lands in a callback the import machinery runs (a module lock's weakref
        # callback) is "ignored" with a printed traceback and the import goes on: act on it below
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            interrupted.append(unraisable.exc_value)
        else:
            sys.__unraisablehook__(unraisable)

    previous = signal.getsignal(signal.SIGINT)
    try:
        # inside the try: ``signal.signal`` first runs the handler of a Ctrl-C already pending
        sys.unraisablehook = note_interrupts
        signal.signal(signal.SIGINT, on_sigint)
        from swarmpc.cli import main as cli_main
    except BaseException as error:  # noqa: BLE001 - only interrupts are swallowed, see below
        if not (caused_by_interrupt(error) or received):
            raise
        interrupted.append(error)
    finally:
        sys.unraisablehook = sys.__unraisablehook__
        signal.signal(signal.SIGINT, previous)
    if interrupted or received:
        sys.stderr.write("swarmpc: interrupted\n")
        sys.exit(INTERRUPTED)
    cli_main()
