"""What a run shows on stderr besides its result: ``warning: ...`` lines and a tracking run's progress bar.

Imports neither numpy nor rich at module level: ``condtrack --help`` imports this module.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import sys
import time
import warnings
from typing import Iterator

import click

from condtrack_cli.errors import CondtrackWarning, names_input

_shown = True  #: the last ``show_warnings`` choice, handed to a batch's worker processes
#: the batch input the warnings printed now are about (``warnings_about``); "" outside a batch's job. A context
#: variable: a Dask worker may run several jobs at once in its threads, each about its own input
_about: contextvars.ContextVar[str] = contextvars.ContextVar("condtrack_warnings_about", default="")


def show_warnings(shown: bool) -> None:
    """Print every :class:`CondtrackWarning` on stderr as a ``warning: ...`` line (``shown``), or none (-q); any
    other warning shown is a ``warning: <category>: ...`` line too (no source line)."""
    global _shown
    _shown = shown
    warnings.simplefilter("always" if shown else "ignore", CondtrackWarning)
    warnings.showwarning = _print_warning


def warnings_shown() -> bool:
    """Whether ``show_warnings`` last chose to print the warnings."""
    return _shown


@contextlib.contextmanager
def warnings_about(name: str) -> Iterator[None]:
    """Inside, the warnings printed begin with ``name: `` (a batch's input, as its ``Error:`` line) unless they
    already name it: a batch's ``warning: 1 of 16 queries are untrackable ...`` did not say of which input."""
    token = _about.set(name)
    try:
        yield
    finally:
        _about.reset(token)


def _print_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """``warnings.showwarning`` as one line on stderr: a CondtrackWarning's message, or any other's category and
    message; within ``warnings_about(name)``, after ``name: ``."""
    named = "" if issubclass(category, CondtrackWarning) else f"{category.__name__}: "
    name = _about.get()
    about = f"{name}: " if name and not names_input(str(message), name) else ""
    click.echo(f"warning: {about}{named}{message}", err=True)


def _may_be_terminal() -> bool:
    """False where rich's ``Console.is_terminal`` is surely false for stderr (so rich, tens of milliseconds of
    import, is not loaded to draw nothing): ``TTY_COMPATIBLE=0``, or neither ``TTY_COMPATIBLE=1`` nor a non-empty
    ``FORCE_COLOR`` and stderr not a terminal. True: ask rich."""
    forced = os.environ.get("TTY_COMPATIBLE", "")
    if forced in ("0", "1"):
        return forced == "1"
    if os.environ.get("FORCE_COLOR") is not None:
        return os.environ["FORCE_COLOR"] != ""
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):  # no stream, or a closed one
        return False


def _terminal_bar():
    """rich's progress bar on stderr when rich takes stderr for a terminal, else None."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress as Bar, TextColumn, TimeRemainingColumn

    console = Console(stderr=True)
    return Bar(
        TextColumn("tracking"), BarColumn(), MofNCompleteColumn(), TextColumn("frames"),
        TextColumn("{task.fields[fps]:.1f} fps"), TimeRemainingColumn(), console=console, transient=True,
    ) if console.is_terminal else None


class Progress:
    """A tracking run's progress bar on stderr: frames done of all, frames per second, time left.

    Drawn only when stderr is a terminal (rich's test, so ``TTY_COMPATIBLE=1`` forces
    it); otherwise nothing. Call it as ``progress(done, total)`` after each frame;
    use it as a context manager, which removes the bar at the end.
    """

    def __init__(self) -> None:
        self.started = time.perf_counter()
        self.bar = _terminal_bar() if _may_be_terminal() else None
        self.task = None
        self.drawn = False  #: the bar started (an interrupt may arrive inside rich's start)

    def __call__(self, done: int, total: int) -> None:
        if self.bar is None:
            return
        fps = done / max(time.perf_counter() - self.started, 1e-9)
        if self.task is None:
            self.task = self.bar.add_task("tracking", total=total, fps=fps)
            self.bar.start()
            self.drawn = True
        self.bar.update(self.task, completed=done, fps=fps)

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc) -> None:
        if self.drawn:
            self.bar.stop()
        elif self.task is not None:  # interrupted while starting: at least give the cursor back
            self.bar.console.show_cursor(True)
