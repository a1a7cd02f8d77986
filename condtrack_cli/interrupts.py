"""Stop signals: SIGTERM ends a run as Ctrl-C does, and a file write is never cut in half.

- :func:`raise_on_sigterm` makes SIGTERM raise :class:`Terminated` (a
  ``KeyboardInterrupt``), so the same cleanups run for both signals and the
  command line exits 130 (SIGINT) or 143 (SIGTERM).
- :func:`held_signals` holds SIGINT and SIGTERM while a file is written: a
  signal arriving then is recorded and acted on when the block ends. Libraries
  written in C are not interrupted halfway (h5py runs Python callbacks inside
  its calls, and an exception raised there is printed and swallowed, so the
  file was published and the run exited 0); the caller reads
  ``held.received`` to discard what it built before the signal is delivered.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from dataclasses import dataclass, field
from typing import Iterator

#: The signals that stop a run, with their exit codes (128 + signal number, the shell's convention).
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


class Terminated(KeyboardInterrupt):
    """SIGTERM arrived: handled wherever Ctrl-C is, exit code 143."""

    exit_code = 128 + signal.SIGTERM


def _raise_terminated(signum: int, frame) -> None:
    raise Terminated()


def raise_on_sigterm() -> None:
    """From now on SIGTERM raises :class:`Terminated` in the main thread (instead of killing the process)."""
    signal.signal(signal.SIGTERM, _raise_terminated)


def exit_code(interrupt: KeyboardInterrupt) -> int:
    """130 for Ctrl-C, 143 for SIGTERM."""
    return getattr(interrupt, "exit_code", 128 + signal.SIGINT)


@dataclass
class Held:
    """The stop signals received while held, in arrival order."""

    received: list[int] = field(default_factory=list)


@contextlib.contextmanager
def held_signals() -> Iterator[Held]:
    """Record SIGINT and SIGTERM during the block instead of acting on them; deliver the first one after it.

    A signal whose handler is ``SIG_IGN`` (or not set from Python) is left
    alone. Outside the main thread, where handlers cannot be set, nothing is
    held.
    """
    held = Held()
    if threading.current_thread() is not threading.main_thread():
        yield held
        return
    previous = {s: signal.getsignal(s) for s in STOP_SIGNALS}
    previous = {s: handler for s, handler in previous.items() if handler not in (signal.SIG_IGN, None)}
    for signum in previous:
        signal.signal(signum, lambda signum, frame: held.received.append(signum))
    try:
        yield held
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        if held.received:
            signal.raise_signal(held.received[0])
