"""What every entry point needs to end a Ctrl-C with one line: the exit status and a test for
errors that a Ctrl-C caused. Imports nothing, so the entry point can load it first."""

from __future__ import annotations

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
