"""Read the record back (``condtrack status``): each input's latest manifest record, the counts, the redo command.

``OUT_DIR/manifest.jsonl`` gains a line per attempt (``manifest.ClipRecord``); a
resumed or retried batch leaves several per input, and the last one counts.
An input whose last record is ``ok`` or ``skipped`` but whose output file is
gone is ``missing``.
"""

from __future__ import annotations

import shlex
from collections import Counter
from dataclasses import asdict, dataclass
from pathlib import Path

from condtrack_cli.batch.manifest import MANIFEST, read_manifest
from condtrack_cli.batch.plan import output_names
from condtrack_cli.config import load_config
from condtrack_cli.errors import CondtrackError, MissingInput
from condtrack_cli.hashes import config_hash

#: The statuses in the order they are counted.
STATUSES = ("ok", "failed", "skipped", "missing")


@dataclass(frozen=True)
class InputStatus:
    """One input's latest record: ``status`` one of ``STATUSES``, ``error`` the failure's one-line reason."""

    input: str
    status: str
    output: str
    error: str | None
    seconds: float
    attempts: int
    method: str
    seed: int


@dataclass(frozen=True)
class BatchStatus:
    """Every input of the manifest (first-run order), the time of their latest runs and of every attempt, the redo."""

    out_dir: str
    inputs: list[InputStatus]
    seconds: float
    seconds_all_attempts: float
    redo: list[str]  #: commands that redo the failed and missing inputs (one per method, seed and format)
    notes: list[str]  #: what the redo commands cannot know and the user must add

    @property
    def counts(self) -> dict[str, int]:
        found = Counter(item.status for item in self.inputs)
        return {status: found[status] for status in STATUSES}

    def to_json(self) -> dict:
        return {**asdict(self), "counts": self.counts}


def batch_status(out_dir: str | Path) -> BatchStatus:
    """Read ``out_dir``'s manifest into a :class:`BatchStatus`; CondtrackError without one."""
    out_dir = Path(out_dir)
    records = read_manifest(out_dir)
    if not records:
        raise MissingInput(f"{out_dir / MANIFEST}: no manifest records (not a batch's --out-dir?)")
    latest: dict[str, dict] = {}
    attempts = Counter(record["input"] for record in records)
    for record in records:
        latest[record["input"]] = record
    inputs = []
    for name, record in latest.items():
        status = record["status"]
        if status in ("ok", "skipped") and not Path(record["output"]).exists():
            status = "missing"
        inputs.append(InputStatus(name, status, record["output"], record.get("error"), float(record["seconds"]),
                                  attempts[name], record["method"], int(record["seed"])))
    redo, notes = _redo(out_dir, inputs, latest, records)
    return BatchStatus(str(out_dir), inputs, sum(item.seconds for item in inputs),
                       sum(float(record["seconds"]) for record in records), redo, notes)


def _redo(out_dir: Path, inputs: list[InputStatus], latest: dict[str, dict],
          records: list[dict]) -> tuple[list[str], list[str]]:
    """``condtrack track`` commands for the failed and missing inputs, and notes on the options they lack.

    The failed ones alone when their output names come out as before; otherwise every input of the
    manifest with --skip-existing (output names depend on the whole list).
    """
    groups: dict[tuple[str, int, str], list[InputStatus]] = {}
    for item in inputs:
        if item.status in ("failed", "missing"):
            groups.setdefault((item.method, item.seed, Path(item.output).suffix), []).append(item)
    commands, notes = [], []
    for (method, seed, suffix), todo in groups.items():
        names = [item.input for item in todo]
        skip = []
        if output_names(names) != [Path(item.output).stem for item in todo]:
            names, skip = list(latest), ["--skip-existing"]
        options = ["--out-dir", str(out_dir), "-m", method, "--seed", str(seed)]
        options += ["--format", "csv"] if suffix == ".csv" else []
        commands.append(shlex.join(["condtrack", "track", *names, *options, *skip]))
        if not _default_config(method, latest[todo[0].input]["config_hash"]):
            notes.append(f"-m {method}: the batch's config is not that method's defaults; add its -c/--set options")
        if any(record.get("queries_hash") for record in records if record["method"] == method):
            notes.append(f"-m {method}: the batch had a queries file; add its -p option")
    return commands, notes


def _default_config(method: str, digest: str) -> bool:
    """Whether ``digest`` is the config hash of the default config with ``-m method``."""
    try:
        return config_hash(load_config(None, [], method)) == digest
    except CondtrackError:  # a method no longer registered
        return False
