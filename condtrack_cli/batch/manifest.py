"""Record: what became of each input, one ``ClipRecord`` a line in ``OUT_DIR/manifest.jsonl``.

A line is appended when its input ends, so a killed batch leaves a true
manifest; ``read_manifest`` gives the records back (for --skip-existing and
``condtrack status``).
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from condtrack_cli import __version__
from condtrack_cli.errors import CondtrackError
from condtrack_cli.hashes import config_hash

if TYPE_CHECKING:
    from condtrack_cli.batch.job import BatchJob

MANIFEST = "manifest.jsonl"


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
    threads: dict = field(default_factory=dict)  #: what the job's process used: opencv, omp

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=False)


def job_record(job: BatchJob, status: str, **values) -> ClipRecord:
    """The manifest record of ``job`` with ``status``; ``values`` give the other fields (queries_hash included)."""
    return ClipRecord(
        input=job.input, output=job.output, status=status, method=job.config.method,
        config_hash=config_hash(job.config), version=__version__, seed=job.seed,
        input_fingerprint=job.input_fingerprint, **values,
    )


def interrupted_record(job: BatchJob) -> ClipRecord:
    """The manifest record of a job that the batch's interrupt stopped (or never started)."""
    return job_record(job, "interrupted", error="interrupted", seconds=0.0, frames=None, points=None, queries_hash="")


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
