"""Per-frame progress of a tracking run on stderr (``condtrack track`` without -q, ``ct.track(progress=True)``)."""

from __future__ import annotations

import logging
import sys

import click


def show_warnings(shown: bool) -> None:
    """The library's warnings (logger ``condtrack``) go to stderr as ``warning: ...`` lines, or nowhere (-q)."""
    logger = logging.getLogger("condtrack")
    if not logger.handlers:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("warning: %(message)s"))
        logger.addHandler(handler)
        logger.propagate = False
    logger.setLevel(logging.WARNING if shown else logging.ERROR)


class Progress:
    """Per-frame progress on stderr, per pass: a rich bar on a terminal, a plain line every tenth of a pass otherwise.

    The forward pass reads the ``n_frames`` frames; the backward pass (queries
    after frame 0) reads ``n_backward`` frames, k_max .. 0.
    """

    def __init__(self, n_frames: int, n_backward: int = 0):
        self.passes = [("forward pass", n_frames)] + ([("backward pass", n_backward)] if n_backward else [])
        self.done = 0
        self.bar = None
        if sys.stderr.isatty():
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            self.bar = Progress(
                TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                TextColumn("{task.fields[active]} active"), TimeRemainingColumn(),
                console=Console(stderr=True), transient=True,
            )
            self.task = self.bar.add_task(self.passes[0][0], total=n_frames, active=0)
            self.bar.start()

    def __call__(self, index: int, estimate) -> None:
        self.done += 1
        (name, total), frame = self.passes[0], self.done
        if frame > total:
            (name, total), frame = self.passes[1], frame - total
        import numpy as np  # here, not at the top: condtrack --help imports this module and no numpy

        active = int(np.isfinite(estimate.xy[:, 0]).sum())
        if self.bar is not None:
            self.bar.update(self.task, description=name, total=total, completed=frame, active=active)
        elif frame % max(1, total // 10) == 0 or frame == total:
            click.echo(f"{name}: frame {frame}/{total}: {active} active points", err=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()
