"""A batch: many inputs, one output each in OUT_DIR, on local processes or a Dask cluster (no click here).

- Names: ``output_names`` gives each input a readable, deterministic name: the
  input's own name (a file without its extension), or, when inputs share it,
  the shortest tail of their paths that tells them apart, joined with ``_``
  (``data/clip001/frames`` -> ``clip001_frames``). Names are computed on the
  whole input list, before ``--shard``, so every shard names alike.
- Manifest: ``OUT_DIR/manifest.jsonl`` gets one JSON line per input when that
  input ends (``ClipRecord``), so a killed batch leaves a true manifest.
- Resume: an input is skipped when its output exists and was made from the same
  input (``hashes.input_fingerprint``: resolved path, frames' names, sizes and
  mtimes), config hash (``hashes.config_hash``), condtrack version, seed and
  queries file (``hashes.queries_hash``): read from the HDF5 root attributes,
  or for a CSV from the manifest's last ``ok`` record of that output; the input's
  fingerprint always from that record (an output without one is redone).
  Outputs are written atomically, so an output that exists is whole.
- Shards: ``shard(items, i, n)`` keeps items i, i + n, i + 2n, ... of the list.
- Where: ``run_local`` (a spawn process pool, or in-process for one job) or
  ``run_dask`` (one task per input on a running dask.distributed cluster); both
  run ``run_job``, so the outputs are the same bytes.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import time
import uuid
from collections import defaultdict
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable

from condtrack_cli import __version__
from condtrack_cli.config import Config
from condtrack_cli.errors import CondtrackError, read_error
from condtrack_cli.hashes import config_hash, input_fingerprint, queries_hash
from condtrack_cli.interrupts import held_signals
from condtrack_cli.io.atomic import refuse_overwriting_inputs
from condtrack_cli.progress import show_warnings, warnings_shown
from condtrack_cli.run import track_input
from condtrack_cli.threads import blas_environment, threads_in_use, use_threads

MANIFEST = "manifest.jsonl"

#: Exit status of a process stopped by SIGTERM (128 + 15), the shells' convention.
SIGTERM_EXIT = 143

#: Seconds to wait for a Dask scheduler to answer.
CONNECT_SECONDS = 3

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
    stop_event: str | None = None  #: on Dask: the name of the batch's stop Event, checked while the job runs


@dataclass(frozen=True)
class ClipRecord:
    """One manifest line: what became of one input (``seconds`` is the job's wall time, start to published output)."""

    input: str
    output: str
    status: str  #: "ok", "failed", "skipped" or "interrupted" (the batch was stopped before the input ended)
    error: str | None
    seconds: float
    frames: int | None
    points: int | None
    method: str
    config_hash: str
    version: str
    seed: int
    queries_hash: str
    input_fingerprint: str = ""  #: ``hashes.input_fingerprint`` of the input
    visible: float | None = None  #: share of the tracked rows that are visible
    threads: dict = field(default_factory=dict)  #: what the job's process used: opencv, fft, omp

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=False)


def _record(job: BatchJob, status: str, **values) -> ClipRecord:
    """The manifest record of ``job`` with ``status``; ``values`` give the other fields (queries_hash included)."""
    return ClipRecord(
        input=job.input, output=job.output, status=status, method=job.config.method,
        config_hash=config_hash(job.config), version=__version__, seed=job.seed,
        input_fingerprint=job.input_fingerprint, **values,
    )


def output_names(inputs: list[str]) -> list[str]:
    """One distinct output name (no extension) per input: its name, or the shortest path tail that is unique.

    A file's name loses its extension (``a/clip.mp4`` -> ``clip``), a folder's
    keeps its whole name. Inputs that share a name grow, each, one more parent
    folder (``x/clip001/frames`` -> ``clip001_frames``) until every name is
    unique; the same list always gives the same names. CondtrackError for an
    input given twice, or two whose whole paths only differ by an extension.
    """
    tails = []
    for text in inputs:
        path = Path(os.path.abspath(text))
        last = path.name if path.is_dir() or not path.suffix else path.stem
        tails.append([*path.parent.parts[1:], last])
    depth = [1] * len(inputs)
    while True:
        names = ["_".join(tail[-d:]) for tail, d in zip(tails, depth)]
        sharing: dict[str, list[int]] = defaultdict(list)
        for index, name in enumerate(names):
            sharing[name].append(index)
        clashes = [group for group in sharing.values() if len(group) > 1]
        if not clashes:
            return names
        grown = False
        for group in clashes:
            for index in group:
                if depth[index] < len(tails[index]):
                    depth[index] += 1
                    grown = True
        if not grown:
            first, second = clashes[0][:2]
            if os.path.abspath(inputs[first]) == os.path.abspath(inputs[second]):
                raise CondtrackError(f"input '{inputs[second]}' is given twice")
            raise CondtrackError(f"inputs '{inputs[first]}' and '{inputs[second]}' would both write '{names[first]}'")


def parse_shard(text: str) -> tuple[int, int]:
    """``"I/N"`` -> (I, N) with 0 <= I < N; ValueError otherwise."""
    index, sep, count = text.partition("/")
    if not (sep and index.strip().isdigit() and count.strip().isdigit()) or not 0 <= int(index) < int(count):
        raise ValueError(f"expected I/N with 0 <= I < N (e.g. 0/4), got {text!r}")
    return int(index), int(count)


def shard(items: list, index: int, count: int) -> list:
    """Items index, index + count, index + 2 count, ...: ``count`` shards cover the list once, in balanced parts."""
    return items[index::count]


def read_manifest(out_dir: Path) -> list[dict]:
    """The manifest's records, oldest first (a line cut short by a kill is ignored); [] without a manifest."""
    try:
        lines = (out_dir / MANIFEST).read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        return []
    except OSError as error:
        raise CondtrackError(f"{out_dir / MANIFEST}: cannot read ({error.strerror})") from None
    records = []
    for line in lines:
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return records


def append_record(out_dir: Path, record: ClipRecord) -> None:
    """Append one line to the manifest with a single write (O_APPEND: shards sharing OUT_DIR do not interleave)."""
    descriptor = os.open(out_dir / MANIFEST, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
    try:
        os.write(descriptor, (record.to_json() + "\n").encode("utf-8"))
    finally:
        os.close(descriptor)


def _stored_run(output: Path, manifest: list[dict]) -> dict | None:
    """What made an existing ``output``: config_hash, version, seed, queries_hash, input_fingerprint, frames, points;
    None if unknown."""
    if not output.is_file():
        return None
    done = [r for r in manifest if r.get("status") == "ok" and Path(str(r.get("output"))).name == output.name]
    last = done[-1] if done else {}
    if output.suffix in (".h5", ".hdf5"):
        import h5py

        try:
            with h5py.File(output, "r") as f:
                attrs = f.attrs
                return {
                    "config_hash": str(attrs.get("config_hash", "")), "version": str(attrs.get("condtrack_version", "")),
                    "seed": int(attrs.get("seed", -1)), "queries_hash": str(attrs.get("queries_hash", "")),
                    "frames": int(attrs.get("n_frames", 0)), "points": int(f["tracks/point_id"].shape[0]),
                    "input_fingerprint": last.get("input_fingerprint"),
                }
        except (OSError, KeyError):
            return None  # not a readable track file: redo it
    return last or None


def skipped_record(job: BatchJob, manifest: list[dict]) -> ClipRecord | None:
    """A ``skipped`` record when ``job.output`` exists and was made from this input by this version with these
    settings, else None."""
    stored = _stored_run(Path(job.output), manifest)
    wanted = {"config_hash": config_hash(job.config), "version": __version__, "seed": job.seed,
              "queries_hash": queries_hash(job.queries_path), "input_fingerprint": job.input_fingerprint}
    if stored is None or any(stored.get(key) != value for key, value in wanted.items()):
        return None
    return _record(job, "skipped", error=None, seconds=0.0, frames=stored.get("frames"), points=stored.get("points"),
                   queries_hash=wanted["queries_hash"])


def interrupted_record(job: BatchJob) -> ClipRecord:
    """The manifest record of a job that the batch's interrupt stopped (or never started)."""
    return _record(job, "interrupted", error="interrupted", seconds=0.0, frames=None, points=None, queries_hash="")


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
    """Track one input into its output (in whichever process runs it); a bad input gives a ``failed`` record."""
    use_threads(job.threads)
    started = time.perf_counter()
    stop_check = _StopCheck(job.stop_event) if job.stop_event else None
    try:
        summary = track_input(job.input, job.config, job.queries_path, job.output, job.seed, stop_check)
        digest = queries_hash(job.queries_path)
    except CondtrackError as error:
        return _record(job, "failed", error=str(error), seconds=round(time.perf_counter() - started, 3), frames=None,
                       points=None, queries_hash="", threads=threads_in_use())
    return _record(
        job, "ok", error=None, seconds=round(time.perf_counter() - started, 3), frames=summary.n_frames,
        points=summary.n_points, visible=round(summary.visible_share, 4), queries_hash=digest,
        threads=threads_in_use(),
    )


def stop_on_sigterm(signum, frame) -> None:
    """SIGTERM handler: raise SystemExit(143), so the process unwinds (finally blocks remove temporary files)."""
    raise SystemExit(SIGTERM_EXIT)


def _start_worker(warnings_shown: bool) -> None:
    """Pool worker set-up: Ctrl-C is the parent's to handle; SIGTERM unwinds (an unfinished output's temporary file
    goes); warnings shown as in the parent (not with -q)."""
    show_warnings(warnings_shown)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, stop_on_sigterm)


class _Environment:
    """Context: extra environment variables while it is open (read by processes started inside it)."""

    def __init__(self, values: dict[str, str]):
        self.values, self.saved = values, {}

    def __enter__(self):
        self.saved = {name: os.environ.get(name) for name in self.values}
        os.environ.update(self.values)

    def __exit__(self, *exc):
        for name, value in self.saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def run_local(jobs: list[BatchJob], processes: int, on_record: Callable[[ClipRecord], None]) -> None:
    """Run ``jobs`` here (``processes`` 1) or in a pool of spawned processes; ``on_record`` as each ends.

    Any exception in this process (Ctrl-C's KeyboardInterrupt, SIGTERM's
    SystemExit) drops the queued jobs and terminates the workers, whose running
    job then removes its unfinished output: nothing is published after it.
    """
    if processes <= 1 or len(jobs) <= 1:
        for job in jobs:
            on_record(run_job(job))
        return
    context = multiprocessing.get_context("spawn")  # OpenCV is not fork-safe
    with _Environment(blas_environment(jobs[0].threads)):  # read by the BLAS libraries when the workers import numpy
        shown = warnings_shown()
        pool = context.Pool(min(processes, len(jobs)), initializer=_start_worker, initargs=(shown,))
    try:
        for record in pool.imap_unordered(run_job, jobs):
            on_record(record)
        pool.close()
    except BaseException:
        pool.terminate()
        raise
    finally:
        pool.join()


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
                record = _record(futures[future], "failed", error=f"Dask task failed: {error}", seconds=0.0,
                                 frames=None, points=None, queries_hash="")
            on_record(record)
    except BaseException:
        with held_signals():  # a second Ctrl-C does not stop the workers' stop halfway
            stop.set()
            client.cancel(list(futures))
        raise


@dataclass(frozen=True)
class BatchPlan:
    """The jobs of this process's shard, in input order, and which of them are already done."""

    jobs: list[BatchJob]
    skipped: list[ClipRecord]
    todo: list[BatchJob]


def plan_batch(
    inputs: list[str], config: Config, queries_path: str | None, out_dir: Path, suffix: str, seed: int,
    threads: int | None, shard_spec: tuple[int, int] | None = None, skip_existing: bool = False,
) -> BatchPlan:
    """Name every input's output, refuse one that is the queries file, create ``out_dir``, keep this shard, and find
    what ``skip_existing`` skips."""
    names = output_names(inputs)
    refuse_overwriting_inputs({f"the output of '{i}',": out_dir / f"{n}{suffix}" for i, n in zip(inputs, names)},
                              {"-p": queries_path})
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise CondtrackError(f"--out-dir '{out_dir}': cannot create the folder ({error.strerror})") from None
    if not os.access(out_dir, os.W_OK | os.X_OK):
        raise CondtrackError(f"--out-dir '{out_dir}' is not writable")
    jobs = [BatchJob(i, str(out_dir / f"{n}{suffix}"), config, queries_path, seed, threads, input_fingerprint(i))
            for i, n in zip(inputs, names)]
    if shard_spec is not None:
        jobs = shard(jobs, *shard_spec)
    skipped, todo = [], []
    manifest = read_manifest(out_dir) if skip_existing else []
    for job in jobs:
        record = skipped_record(job, manifest) if skip_existing else None
        if record is None:
            todo.append(job)
        else:
            skipped.append(record)
    return BatchPlan(jobs, skipped, todo)
