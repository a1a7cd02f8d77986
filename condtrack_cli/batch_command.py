"""The batch side of ``condtrack track``: its options, progress over clips, the final table, signals."""

from __future__ import annotations

import contextlib
import signal
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import click

from condtrack_cli.errors import CondtrackError
from condtrack_cli.threads import THREADS_ENV, threads_from_environment, threads_per_job

if TYPE_CHECKING:
    from condtrack_cli.batch import ClipRecord
    from condtrack_cli.config import Config

#: Options of ``track`` that only a batch (--out-dir) takes.
BATCH_ONLY = ("skip_existing", "shard", "scheduler", "scheduler_file", "jobs")


class _Shard(click.ParamType):
    """``--shard I/N`` -> (I, N) with 0 <= I < N; anything else is a usage error."""

    name = "I/N"

    def convert(self, value, param, ctx) -> tuple[int, int]:
        from condtrack_cli.batch import parse_shard

        try:
            return parse_shard(value)
        except ValueError as error:
            self.fail(str(error), param, ctx)


def batch_options(command):
    """Decorate ``track`` with the batch options (resume, shards, Dask) and --threads."""
    options = [
        click.option("--skip-existing", is_flag=True,
                     help="Batch: skip inputs whose output exists from the same config, seed, queries and version."),
        click.option("--shard", type=_Shard(), metavar="I/N", help="Batch: only the I-th of N parts of the inputs (I = 0..N-1)."),
        click.option("--scheduler", metavar="ADDRESS", help="Batch: run one task per input on this dask.distributed scheduler."),
        click.option("--scheduler-file", type=click.Path(dir_okay=False, exists=True), help="Batch: as --scheduler, from a Dask scheduler file."),
        click.option("--threads", type=click.IntRange(min=1),
                     help=f"Threads per input (default ${THREADS_ENV}, else every core for one input, cores / N per job with -j N)."),
    ]
    for option in reversed(options):
        command = option(command)
    return command


def requested_threads(threads: int | None) -> int | None:
    """--threads, else $CONDTRACK_THREADS, else None."""
    if threads is not None:
        return threads
    try:
        return threads_from_environment()
    except ValueError as error:
        raise CondtrackError(str(error)) from None


def refuse_batch_options(batch_values: dict) -> None:
    """A usage error naming the batch-only options given (a single run without --out-dir would ignore them)."""
    given = [f"--{name.replace('_', '-')}" for name in BATCH_ONLY if batch_values.get(name) not in (None, False)]
    if given:
        click.get_current_context().fail(f"{', '.join(given)}: a batch option (give --out-dir)")


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


@contextlib.contextmanager
def sigterm_exits():
    """While open, SIGTERM raises SystemExit(143) here, so the batch unwinds (workers stopped, temporaries removed)."""
    from condtrack_cli.batch import SIGTERM_EXIT, stop_on_sigterm

    previous = signal.signal(signal.SIGTERM, stop_on_sigterm)
    try:
        yield
    except SystemExit as exit_:
        if exit_.code == SIGTERM_EXIT:
            click.echo("Error: terminated", err=True)
        raise
    finally:
        signal.signal(signal.SIGTERM, previous)


def run_batch(
    inputs: list[str], config: Config, queries_path: str | None, out_dir: str, batch_format: str, seed: int,
    jobs: int | None, quiet: bool, skip_existing: bool, shard: tuple[int, int] | None, scheduler: str | None,
    scheduler_file: str | None, threads: int | None,
) -> None:
    """Plan, run and report a batch; exit 1 when an input failed. ``jobs`` None: -j not given (one job at a time)."""
    from condtrack_cli.batch import append_record, connect_dask, interrupted_record, plan_batch, run_dask, run_local

    usage = click.get_current_context()
    if scheduler and scheduler_file:
        usage.fail("--scheduler and --scheduler-file: give one")
    on_dask = bool(scheduler or scheduler_file)
    if on_dask and jobs is not None:
        usage.fail("-j/--jobs: not with --scheduler (the Dask workers run the inputs: dask worker --nworkers)")
    jobs = jobs or 1
    requested = requested_threads(threads)
    if on_dask:
        per_job, warning = requested or 1, None  # a Dask worker runs several tasks at once: one thread each by default
    else:
        per_job, warning = threads_per_job(requested, min(jobs, len(inputs)))
    if warning and not quiet:
        click.echo(f"warning: {warning}", err=True)
    # The scheduler is reached before the out-dir is made: one that does not answer leaves nothing behind.
    connection = connect_dask(scheduler, scheduler_file) if on_dask else contextlib.nullcontext()
    with connection as client:
        plan = plan_batch(inputs, config, queries_path, Path(out_dir), f".{batch_format}", seed, per_job, shard,
                          skip_existing)
        progress = ClipProgress(len(plan.jobs), quiet)
        records: dict[str, ClipRecord] = {}

        def finished(record: ClipRecord) -> None:
            append_record(Path(out_dir), record)
            records[record.input] = record
            progress(record)

        with sigterm_exits():
            for record in plan.skipped:
                finished(record)
            try:
                if on_dask:
                    run_dask(plan.todo, client, finished)
                else:
                    run_local(plan.todo, jobs, finished)
            except (KeyboardInterrupt, SystemExit):  # the manifest says what did not end
                for job in plan.todo:
                    if job.input not in records:
                        append_record(Path(out_dir), interrupted_record(job))
                raise
    ordered = [records[job.input] for job in plan.jobs]
    failed = sum(r.status == "failed" for r in ordered)
    if not quiet:
        _print_table(ordered, config.method)
    if failed:
        if quiet:  # -q silences progress and the table, not the errors
            for r in ordered:
                if r.status == "failed":  # named once: most messages start with the input already
                    named = r.error.startswith(f"{r.input}:")
                    click.echo(f"Error: {r.error}" if named else f"Error: {r.input}: {r.error}", err=True)
        click.echo(f"Error: {failed} of {len(ordered)} inputs failed (see {Path(out_dir) / 'manifest.jsonl'})", err=True)
        sys.exit(1)


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
