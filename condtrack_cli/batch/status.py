"""Read the record back (``condtrack status``): each input's latest manifest record, the counts, the redo command.

``OUT_DIR/manifest.jsonl`` gains a line per attempt (``manifest.ClipRecord``); a
resumed or retried batch leaves several per input, and the last one counts.
An input is one input however its path was typed: records that name the same
file, read from their batch's working directory (``cwd``, absent from older
manifests, whose paths are taken as written), are one input's. Outputs are
looked for in OUT_DIR, where a batch writes them, whatever folder the batch or
``status`` runs in; an input whose last record is ``ok`` or ``skipped`` but
whose output file is gone, or was replaced since by another input's of the same name, is
``missing``. A batch's ``planned`` record of an input is dropped once a later
record of that input and output ends it; one that nothing ends (the batch was
killed, or is still running) is an attempt that never ended: ``interrupted``.
"""

from __future__ import annotations

import os
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
STATUSES = ("ok", "failed", "interrupted", "skipped", "missing")

#: The statuses whose inputs the redo commands run again.
REDONE = ("failed", "interrupted", "missing")

#: The fields ``status`` reads from every record, with their JSON types (``manifest.JSON_TYPES``).
STATUS_FIELDS = {"input": "string", "output": "string", "status": "string", "seconds": "number",
                 "method": "string", "seed": "integer", "config_hash": "string"}

#: The ``error`` of an input whose latest record is its batch's plan: it is ``interrupted``, with no record of why.
NEVER_ENDED = "never ended (the batch was killed, or is still running)"


@dataclass(frozen=True)
class InputStatus:
    """One input's latest record: ``status`` one of ``STATUSES``, ``error`` the failure's one-line reason (a missing
    output's when another input's replaced it), ``output`` None for an interrupted input (it has none)."""

    input: str
    status: str
    output: str | None
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
    redo: list[str]  #: commands that redo the failed, interrupted and missing inputs (one per method, seed and format)
    notes: list[str]  #: what the redo commands cannot know and the user must add

    @property
    def counts(self) -> dict[str, int]:
        found = Counter(item.status for item in self.inputs)
        return {status: found[status] for status in STATUSES}

    def to_json(self) -> dict:
        return {**asdict(self), "counts": self.counts}


def batch_path(record: dict, path: str) -> str:
    """``path`` as written in ``record``, made absolute from the record's batch folder (as written without one)."""
    return os.path.abspath(os.path.join(record["cwd"], path)) if record.get("cwd") else path


def input_identity(record: dict) -> str:
    """What tells ``record``'s input apart: its resolved absolute path (as written when it cannot be made absolute)."""
    shown = batch_path(record, record["input"])
    return os.path.realpath(shown) if os.path.isabs(shown) else shown


def batch_status(out_dir: str | Path) -> BatchStatus:
    """Read ``out_dir``'s manifest into a :class:`BatchStatus`; CondtrackError without one or with a broken line
    (MissingInput without the folder or a record)."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise MissingInput(f"{out_dir}: no such folder")
    records = read_manifest(out_dir, STATUS_FIELDS)
    if not records:
        raise MissingInput(f"{out_dir / MANIFEST}: no manifest records (not a batch's --out-dir?)")
    every_identity = [input_identity(record) for record in records]
    records, identities = _without_ended_plans(records, every_identity)
    attempts = Counter(identities)
    latest = dict.fromkeys(every_identity)  # in first-run order (an ended plan's too); each input's last record wins
    latest.update(zip(identities, records))
    written_by = {Path(record["output"]).name: identity  # each output name's last writer
                  for identity, record in zip(identities, records) if record["status"] == "ok"}
    inputs = []
    for identity, record in latest.items():
        name = Path(record["output"]).name
        status, output, error = record["status"], str(out_dir / name), record.get("error")
        if status == "planned":
            status, error = "interrupted", NEVER_ENDED
        writer = written_by.get(name, identity)
        if status in ("ok", "skipped") and not Path(output).exists():
            status = "missing"
        elif status in ("ok", "skipped") and writer != identity:  # a batch of another input wrote that name since
            other = latest[writer]
            status, error = "missing", f"{output} was replaced by the output of {batch_path(other, other['input'])}"
        inputs.append(InputStatus(batch_path(record, record["input"]), status,
                                  None if status == "interrupted" else output, error,
                                  float(record["seconds"]), attempts[identity], record["method"], int(record["seed"])))
    redo, notes = _redo(inputs, list(latest.values()), records, out_dir)
    return BatchStatus(str(out_dir), inputs, sum(item.seconds for item in inputs),
                       sum(float(record["seconds"]) for record in records), redo, notes)


def _without_ended_plans(records: list[dict], identities: list[str]) -> tuple[list[dict], list[str]]:
    """``records`` and their inputs' ``identities`` without the ``planned`` records that the next record of the same
    input and output name ends (one that is not ``planned``)."""
    kept, next_status = [], {}
    for record, identity in reversed(list(zip(records, identities))):
        key = (identity, Path(record["output"]).name)
        if record["status"] != "planned" or next_status.get(key, "planned") == "planned":
            kept.append((record, identity))
        next_status[key] = record["status"]
    kept.reverse()
    return [record for record, _ in kept], [identity for _, identity in kept]


def _redo(inputs: list[InputStatus], latest: list[dict], records: list[dict],
          out_dir: Path) -> tuple[list[str], list[str]]:
    """``condtrack track`` commands for the failed, interrupted and missing inputs, and notes on the options they lack.

    ``latest``: each input's latest record, in the order of ``inputs``. The
    inputs to redo alone when their output names come out as before; otherwise
    every input of the manifest with --skip-existing (output names depend on the
    whole list). The inputs' paths are absolute when the manifest has the batch's folder; the outputs go to
    ``out_dir``, whose manifest this is, made absolute (not the folder the records name: the batch's, before a move).
    """
    groups: dict[tuple[str, int, str], list[tuple[InputStatus, dict]]] = {}
    for item, record in zip(inputs, latest):
        if item.status in REDONE:
            groups.setdefault((item.method, item.seed, Path(record["output"]).suffix), []).append((item, record))
    commands, notes = [], []
    for (method, seed, suffix), todo in groups.items():
        names, stems = [item.input for item, _ in todo], [Path(record["output"]).stem for _, record in todo]
        skip = []
        if output_names(names) != stems:
            names, skip = [item.input for item in inputs], ["--skip-existing"]
            if [output_names(names)[names.index(item.input)] for item, _ in todo] != stems:
                notes.append(f"-m {method}: the outputs were named from a longer input list than the manifest holds "
                             "(another shard's, or inputs not run yet); redo with that list and --skip-existing")
        first = todo[0][1]
        options = ["--out-dir", os.path.abspath(out_dir), "-m", method, "--seed", str(seed)]
        options += ["--format", "csv"] if suffix == ".csv" else []
        commands.append(shlex.join(["condtrack", "track", *names, *options, *skip]))
        if not all(os.path.isabs(path) for path in names):
            notes.append(f"-m {method}: the manifest does not say which folder the batch ran in; run the command "
                         "from there")
        if not _default_config(method, first["config_hash"]):
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
