"""Report: a batch's progress on stderr, one line per finished input, then its final table and failures."""

from __future__ import annotations

import time
from pathlib import Path

import click

from condtrack_cli.batch.manifest import MANIFEST, ClipRecord
from condtrack_cli.errors import names_input


class ClipProgress:
    """One stderr line per finished input: counts, failures so far, ETA from the mean time of the inputs run."""

    def __init__(self, total: int, quiet: bool):
        self.total, self.quiet = total, quiet
        self.done = self.ran = self.failed = 0
        self.started = time.perf_counter()

    def __call__(self, record: ClipRecord) -> None:
        self.done += 1
        self.ran += record.status != "skipped"
        self.failed += record.status == "failed"
        if self.quiet:
            return
        elapsed = time.perf_counter() - self.started
        left = self.total - self.done
        eta = f"ETA {_clock(elapsed / self.ran * left)}" if self.ran and left else ("done" if not left else "ETA ?")
        click.echo(f"[{self.done}/{self.total}] {record.status} {record.input} ({record.seconds:.1f} s); "
                   f"{self.failed} failed so far; {eta}", err=True)


def _clock(seconds: float) -> str:
    minutes, seconds = divmod(int(round(seconds)), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{seconds:02d}"


def report_end(records: list[ClipRecord], method: str, out_dir: Path, quiet: bool) -> int:
    """The final table (not with -q), then the failures on stderr; the number of failed inputs."""
    failed = sum(r.status == "failed" for r in records)
    if not quiet:
        _print_table(records, method)
    if failed:
        if quiet:  # -q silences progress and the table, not the errors
            for r in records:
                if r.status == "failed":  # named once: most messages start with the input already
                    named = names_input(r.error, r.input)
                    click.echo(f"Error: {r.error}" if named else f"Error: {r.input}: {r.error}", err=True)
        click.echo(f"Error: {failed} of {len(records)} inputs failed (see {out_dir / MANIFEST})", err=True)
    return failed


def _print_table(records: list[ClipRecord], method: str) -> None:
    """The batch's final table, on stderr (stdout stays clean)."""
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"condtrack batch ({method})")
    for column in ("input", "status", "points", "visible", "s/frame", "output or error"):
        table.add_column(column)
    for r in records:
        visible = "" if r.visible is None else f"{r.visible:.1%}"
        per_frame = f"{r.seconds / r.frames:.3f}" if r.status == "ok" and r.frames else ""
        table.add_row(r.input, r.status, "" if r.points is None else str(r.points), visible, per_frame,
                      r.error if r.status == "failed" else r.output)
    Console(stderr=True, width=160).print(table)
