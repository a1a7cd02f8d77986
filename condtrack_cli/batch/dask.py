"""Execute on Dask: connect to a running dask.distributed scheduler, one task per job, and stop them on an interrupt."""

from __future__ import annotations

import json
import uuid
from dataclasses import replace
from pathlib import Path
from typing import Callable

from condtrack_cli.batch.job import BatchJob, job_record, run_job
from condtrack_cli.batch.manifest import ClipRecord
from condtrack_cli.errors import CondtrackError, read_error
from condtrack_cli.interrupts import held_signals

#: Seconds to wait for a Dask scheduler to answer.
CONNECT_SECONDS = 3


def scheduler_address(scheduler_file: str) -> str:
    """The address in a Dask scheduler file (the JSON ``dask scheduler --scheduler-file`` writes); CondtrackError
    naming the file when it is not one."""
    try:
        text = Path(scheduler_file).read_text(encoding="utf-8")
    except OSError as error:
        raise read_error(error, f"--scheduler-file {scheduler_file}: cannot read ({error.strerror})") from None
    try:
        data = json.loads(text)
    except (UnicodeDecodeError, json.JSONDecodeError):
        data = None
    if not (isinstance(data, dict) and isinstance(data.get("address"), str)):
        raise CondtrackError(f"--scheduler-file {scheduler_file}: not a Dask scheduler file "
                             "(a JSON object with the scheduler's 'address')")
    return data["address"]


def connect_dask(address: str | None, scheduler_file: str | None):
    """A dask.distributed Client of the scheduler at ``address`` (or named by ``scheduler_file``), connected within
    ``CONNECT_SECONDS``; CondtrackError when Dask is not installed or the scheduler does not answer."""
    try:
        from distributed import Client
    except ImportError:
        raise CondtrackError("--scheduler needs the Dask extra: pip install 'condtrack[dask]'") from None
    where = address or scheduler_address(scheduler_file)
    try:
        return Client(where, timeout=CONNECT_SECONDS)
    except (OSError, ValueError, TypeError) as error:  # unreachable (a TimeoutError), refused, or no address
        raise CondtrackError(f"cannot reach the Dask scheduler {where}: {error}") from None


def run_dask(jobs: list[BatchJob], client, on_record: Callable[[ClipRecord], None]) -> None:
    """One task per job on ``client``'s cluster; ``on_record`` as each ends.

    The tasks write the outputs (the cluster must see the same file system) and
    are retried once when they raise; a task whose worker is lost is run again
    elsewhere by the scheduler (``distributed.scheduler.allowed-failures``
    times). An interrupt cancels the tasks not yet started and sets the batch's
    stop Event, on which the running ones stop within ``STOP_CHECK_SECONDS`` and
    a frame, before writing their output.
    """
    from distributed import Event, as_completed

    stop = Event(f"condtrack-stop-{uuid.uuid4().hex}", client=client)
    futures = {client.submit(run_job, replace(job, stop_event=stop.name), pure=False, retries=1): job
               for job in jobs}
    try:
        for future in as_completed(futures):
            try:
                record = future.result()
            except Exception as error:  # the task itself failed twice (not a bad input: those give records)
                record = job_record(futures[future], "failed", error=f"Dask task failed: {error}", seconds=0.0,
                                    frames=None, points=None)
            on_record(record)
    except BaseException:
        with held_signals():  # a second Ctrl-C does not stop the workers' stop halfway
            stop.set()
            client.cancel(list(futures))
        raise
