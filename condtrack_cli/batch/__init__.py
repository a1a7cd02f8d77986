"""A batch: many inputs, one output each in OUT_DIR, on local processes or a Dask cluster; ``run_batch`` runs one.

The modules follow a batch's flow, each called once from ``run_batch``:

- ``plan``: inputs -> jobs (output names, shard, what --skip-existing skips), refusals before any work;
- ``job``: one job, run in whichever process (the same bytes everywhere), writing into the batch's staging folder;
- ``local`` / ``dask``: execute the jobs in a process pool or on a Dask cluster, and stop them on an interrupt;
- ``manifest``: record the plan, then each input's end, in ``OUT_DIR/manifest.jsonl`` (``status`` reads it for
  ``condtrack status``), with its output moved in place from the staging folder at the same moment (``run_batch``);
- ``report``: a progress line per input, the final table and the failures.
"""

from __future__ import annotations

import contextlib
import sys
from dataclasses import replace
from pathlib import Path

import click

from condtrack_cli.batch.dask import connect_dask, run_dask
from condtrack_cli.batch.job import interrupted_record, planned_record, staged_output
from condtrack_cli.batch.local import run_local, sigterm_exits
from condtrack_cli.batch.manifest import ClipRecord, append_records
from condtrack_cli.batch.plan import plan_batch
from condtrack_cli.batch.report import ClipProgress, report_end
from condtrack_cli.config import Config
from condtrack_cli.errors import CondtrackError
from condtrack_cli.frame_reports import owned_name, remove_dead_folders
from condtrack_cli.interrupts import held_signals
from condtrack_cli.io.atomic import publish, staging_folder
from condtrack_cli.threads import requested_threads, threads_per_job


#: The stem of the staging folder's name in OUT_DIR (``.outputs-<host>-<pid>-*.part``: ``frame_reports.owned_name``).
STAGING_STEM = ".outputs"


def run_batch(
    inputs: list[str], config: Config, queries_path: str | None, out_dir: str, batch_format: str, seed: int,
    jobs: int | None, quiet: bool, skip_existing: bool, shard: tuple[int, int] | None, scheduler: str | None,
    scheduler_file: str | None, threads: int | None,
) -> None:
    """Plan, run and report a batch; exit 1 when an input failed. ``jobs`` None: -j not given (one job at a time)."""
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
        if shard is not None and not plan.jobs and not quiet:  # more shards than inputs: nothing to do, not an error
            index, count = shard
            click.echo(f"warning: --shard {index}/{count}: none of the {len(inputs)} input(s) is in this shard "
                       f"(it takes inputs {index}, {index + count}, ... of the list, counted from 0)", err=True)
        progress = ClipProgress(len(plan.jobs), quiet)
        records: dict[str, ClipRecord] = {}

        def finished(record: ClipRecord) -> None:
            with held_signals():  # no interrupt between moving the output in place and writing its line
                record = _published(record, staging)
                append_records(Path(out_dir), record)
                records[record.input] = record
            progress(record)

        # The jobs write into a staging folder, removed as the batch ends with what was not moved in place; one left
        # by a batch killed with SIGKILL (no clean-up runs), the outputs it had not moved in place, by the next batch.
        remove_dead_folders(out_dir, STAGING_STEM)
        with sigterm_exits(), staging_folder(Path(out_dir) / owned_name(STAGING_STEM[1:])) as staging:
            # The plan first: an input that a kill (SIGKILL, out of memory) stops has a record, with no end after it.
            append_records(Path(out_dir), *map(planned_record, plan.todo))
            for record in plan.skipped:
                finished(record)
            todo = [replace(job, staging=str(staging)) for job in plan.todo]
            try:
                if on_dask:
                    run_dask(todo, client, finished)
                else:
                    run_local(todo, jobs, finished)
            except (KeyboardInterrupt, SystemExit):  # the manifest says what did not end
                append_records(Path(out_dir),
                               *(interrupted_record(job) for job in plan.todo if job.input not in records))
                raise
    if report_end([records[job.input] for job in plan.jobs], config.method, Path(out_dir), quiet):
        sys.exit(1)


def _published(record: ClipRecord, staging: Path) -> ClipRecord:
    """``record`` once its output (an ``ok`` one's) is moved from ``staging`` in place; ``failed`` if it cannot be."""
    if record.status != "ok":
        return record
    try:
        publish(staged_output(staging, record.output), record.output)
    except CondtrackError as error:
        return replace(record, status="failed", error=str(error))
    return record
