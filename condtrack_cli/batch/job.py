"""One job of a batch: ``BatchJob`` (input -> output, picklable), ``run_job``, its run in whichever process, and
``job_record``, the manifest record it ends with (``planned_record``: the one the batch starts with).

``run_local`` and ``run_dask`` both run ``run_job``, so the outputs are the same
bytes; on Dask the job also looks at its batch's stop Event while it runs. The
job writes its output into the batch's staging folder; the batch moves it in
place when it records the job's end (``run_batch``), so an interrupt never
leaves an output without its manifest line.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

from condtrack_cli import __version__
from condtrack_cli.batch.manifest import ClipRecord
from condtrack_cli.config import Config
from condtrack_cli.errors import CondtrackError
from condtrack_cli.hashes import config_hash, queries_hash
from condtrack_cli.progress import warnings_about
from condtrack_cli.run import track_input
from condtrack_cli.threads import threads_in_use, use_threads

#: Seconds between two looks of a running Dask task at its batch's stop Event.
STOP_CHECK_SECONDS = 0.2


@dataclass(frozen=True)
class BatchJob:
    """One input of a batch: what ``run_job`` needs (picklable, sent to a worker process or a Dask task)."""

    input: str
    output: str
    config: Config
    queries_path: str | None
    seed: int
    threads: int | None  #: threads of this job (None: every core the process may use)
    input_fingerprint: str = ""  #: ``hashes.input_fingerprint`` of the input when the batch was planned
    cwd: str = ""  #: the batch's working directory (absolute): what a relative ``input`` or ``output`` is read from
    staging: str = ""  #: the batch's staging folder, where ``run_job`` writes the output (set by ``run_batch``)
    stop_event: str | None = None  #: on Dask: the name of the batch's stop Event, checked while the job runs
    queries_hash: str = ""  #: ``hashes.queries_hash`` of the queries file when the batch was planned


def staged_output(staging: str | Path, output: str) -> Path:
    """Where a job writes ``output`` before the batch moves it in place: the same name in the staging folder."""
    return Path(staging) / Path(output).name


def job_record(job: BatchJob, status: str, **values) -> ClipRecord:
    """The manifest record of ``job`` with ``status``; ``values`` give the other fields (``queries_hash``: the job's,
    from the planned queries file, unless given), so a failed or interrupted input's record says the batch had queries
    (``condtrack status``'s redo note) as an ``ok`` one does."""
    return ClipRecord(
        input=job.input, output=job.output, status=status, method=job.config.method,
        config_hash=config_hash(job.config), version=__version__, seed=job.seed,
        input_fingerprint=job.input_fingerprint, cwd=job.cwd, **{"queries_hash": job.queries_hash, **values},
    )


def planned_record(job: BatchJob) -> ClipRecord:
    """The manifest record of a job the batch will run, written as it starts (its end is a later record)."""
    return job_record(job, "planned", error=None, seconds=0.0, frames=None, points=None)


def interrupted_record(job: BatchJob) -> ClipRecord:
    """The manifest record of a job that the batch's interrupt stopped (or never started)."""
    return replace(planned_record(job), status="interrupted", error="interrupted")


class Cancelled(CondtrackError):
    """The batch that sent this Dask task was interrupted: the task stops without publishing its output."""


class _StopCheck:
    """A Dask task's ``progress(done, total)`` callback for ``track_input``: raises :class:`Cancelled` once the
    batch's stop Event is set, asked at most every ``STOP_CHECK_SECONDS`` and after the last frame, before the output
    is written."""

    def __init__(self, event_name: str):
        from distributed import Event

        self.event, self.next_check = Event(event_name), 0.0

    def __call__(self, done: int, total: int) -> None:
        if done < total and time.monotonic() < self.next_check:
            return
        self.next_check = time.monotonic() + STOP_CHECK_SECONDS
        if self.event.is_set():
            raise Cancelled("cancelled: the batch was interrupted")


def run_job(job: BatchJob) -> ClipRecord:
    """Track one input into its staged output (in whichever process runs it); a bad input gives a ``failed`` record."""
    use_threads(job.threads)
    started = time.perf_counter()
    stop_check = _StopCheck(job.stop_event) if job.stop_event else None
    try:
        with warnings_about(job.input):
            summary = track_input(job.input, job.config, job.queries_path, job.output, job.seed, stop_check,
                                  staged_path=str(staged_output(job.staging, job.output)))
        digest = queries_hash(job.queries_path)
    except CondtrackError as error:
        return job_record(job, "failed", error=str(error), seconds=round(time.perf_counter() - started, 3),
                          frames=None, points=None, threads=threads_in_use())
    return job_record(
        job, "ok", error=None, seconds=round(time.perf_counter() - started, 3), frames=summary.n_frames,
        points=summary.n_points, visible=round(summary.visible_share, 4), queries_hash=digest,
        threads=threads_in_use(),
    )
