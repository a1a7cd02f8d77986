"""Per-frame progress of a tracking run on stderr (``condtrack track`` without -q, ``ct.track(progress=True)``)."""

from __future__ import annotations

import sys

import click
import numpy as np


class Progress:
    """Per-frame progress on stderr: a rich bar on a terminal, a plain line every tenth otherwise."""

    def __init__(self, n_frames: int):
        self.n_frames, self.done = n_frames, 0
        self.step = max(1, n_frames // 10)
        self.bar = None
        if sys.stderr.isatty():
            from rich.console import Console
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

            self.bar = Progress(
                TextColumn("tracking"), BarColumn(), MofNCompleteColumn(), TextColumn("{task.fields[active]} active"),
                TimeRemainingColumn(), console=Console(stderr=True), transient=True,
            )
            self.task = self.bar.add_task("track", total=n_frames, active=0)
            self.bar.start()

    def __call__(self, index: int, estimate) -> None:
        self.done += 1
        active = int(np.isfinite(estimate.xy[:, 0]).sum())
        if self.bar is not None:
            self.bar.update(self.task, completed=self.done, active=active)
        elif self.done % self.step == 0 or self.done == self.n_frames:
            click.echo(f"frame {self.done}/{self.n_frames}: {active} active points", err=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()
