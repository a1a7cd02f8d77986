"""Record: what became of each input, one ``ClipRecord`` a line in ``OUT_DIR/manifest.jsonl``.

As a batch starts it appends a ``planned`` line per input it will run (its
plan); a line is appended when an input ends, so a killed batch leaves a true
manifest: a ``planned`` line with no later line of its input is an input that
never ended. ``read_manifest`` gives the records back (for --skip-existing and
``condtrack status``).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path

from condtrack_cli.errors import CondtrackError, write_error

MANIFEST = "manifest.jsonl"

#: A record's statuses: "interrupted" when the batch was stopped before the input ended; "planned" when the batch
#: started, before the input ran (the input's end is a later record).
RECORD_STATUSES = ("ok", "failed", "skipped", "interrupted", "planned")

#: How ``append_records`` ends a line cut short (a kill or a full disk during its write) before the next record.
CUT_SHORT = " <- cut short: the rest of this line was never written"

#: The Python types of the JSON values a record's fields are checked against (``read_manifest``).
JSON_TYPES = {"string": str, "integer": int, "number": (int, float)}


@dataclass(frozen=True)
class ClipRecord:
    """One manifest line: what became of one input (``seconds`` is the job's wall time, start to written output)."""

    input: str
    output: str
    status: str  #: one of ``RECORD_STATUSES``
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
    cwd: str = ""  #: the batch's working directory, against which a relative ``input`` or ``output`` is read

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=False)


def read_manifest(out_dir: Path, fields: dict[str, str] | None = None) -> list[dict]:
    """The manifest's records, oldest first; [] without a manifest.

    Blank lines are skipped, and so is a line cut short by a kill or a full disk: the last line when it has no
    newline, or one that ``append_records`` ended with ``CUT_SHORT`` before its record. Other broken lines
    are skipped, unless ``fields`` (name -> a ``JSON_TYPES`` name) is given: then a line that
    is not a JSON object with those fields, or whose status is not one of
    ``RECORD_STATUSES``, is a CondtrackError naming the file and the line.
    """
    path = out_dir / MANIFEST
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return []
    except OSError as error:
        raise CondtrackError(f"{path}: cannot read ({error.strerror})") from None
    except UnicodeDecodeError:
        raise CondtrackError(f"{path}: not UTF-8 text") from None
    lines = text.splitlines()
    records = []
    for number, line in enumerate(lines, 1):
        if not line.strip():  # a blank line (manifests joined or hand-edited) holds no record: not an error
            continue
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            if fields is None or (number == len(lines) and not text.endswith("\n")) or line.endswith(CUT_SHORT):
                continue
            raise CondtrackError(f"{path}, line {number}: not a JSON record") from None
        if fields is not None:
            problem = _record_problem(record, fields)
            if problem:
                raise CondtrackError(f"{path}, line {number}: {problem}")
        records.append(record)
    return records


def _record_problem(record, fields: dict[str, str]) -> str | None:
    """What makes ``record`` not a manifest record with ``fields`` (name -> a ``JSON_TYPES`` name); None if it is one."""
    if not isinstance(record, dict):
        return "not a JSON object"
    for name, kind in fields.items():
        if name not in record:
            return f"the record has no '{name}'"
        value = record[name]
        if (not isinstance(value, JSON_TYPES[kind]) or isinstance(value, bool)
                or (kind == "number" and not math.isfinite(value))):  # Python's json reads NaN and Infinity
            return f"'{name}' is {json.dumps(value)}, not {'an' if kind == 'integer' else 'a'} {kind}"
    if "status" in fields and record["status"] not in RECORD_STATUSES:
        return f"unknown status {json.dumps(record['status'])} (not one of {', '.join(RECORD_STATUSES)})"
    return None


def open_manifest(out_dir: Path) -> int:
    """A descriptor appending to the manifest, created when missing; CondtrackError naming it when it cannot be
    written (a folder of that name, a read-only file)."""
    try:  # read too: append_records reads the last byte
        return os.open(out_dir / MANIFEST, os.O_RDWR | os.O_APPEND | os.O_CREAT, 0o666)
    except OSError as error:
        raise write_error(out_dir / MANIFEST, error) from None


def _ending(descriptor: int) -> str:
    """What ends the manifest's last line before a record is appended (``append_records``): "" when it ends already."""
    size = os.fstat(descriptor).st_size
    tail = os.pread(descriptor, min(size, 1 << 16), max(size - (1 << 16), 0))
    if not tail or tail.endswith(b"\n"):
        return ""
    try:
        json.loads(tail.rsplit(b"\n", 1)[-1])
    except ValueError:  # (UnicodeDecodeError too: cut inside a character)
        return CUT_SHORT + "\n"
    return "\n"


def append_records(out_dir: Path, *records: ClipRecord) -> None:
    """Append one line per record to the manifest with a single write (O_APPEND: shards sharing OUT_DIR do not
    interleave).

    After a last line without a newline (a kill or a full disk during its write), which the records would extend
    into a broken line of both, that line is first ended: with ``CUT_SHORT`` (``read_manifest`` skips it) when it
    is cut short, with a newline alone when it is a whole record."""
    if not records:
        return
    descriptor = open_manifest(out_dir)
    try:
        lines = "".join(record.to_json() + "\n" for record in records)
        os.write(descriptor, (_ending(descriptor) + lines).encode("utf-8"))
    except OSError as error:
        raise write_error(out_dir / MANIFEST, error) from None
    finally:
        os.close(descriptor)
