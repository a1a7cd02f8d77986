"""Plan: a batch's inputs -> its jobs, one output each in OUT_DIR; refusals before any work (no click here).

- Names: ``output_names`` gives each input a readable, deterministic name: the
  input's own name (a file without its extension), or, when inputs share it,
  the shortest tail of their paths that tells them apart, joined with ``_``
  (``data/clip001/frames`` -> ``clip001_frames``). Names are computed on the
  whole input list, before ``--shard``, so every shard names alike.
- Resume: an input is skipped when its output exists and was made from the same
  input (``hashes.input_fingerprint``: resolved path, frames' names, sizes and
  mtimes), config hash (``hashes.config_hash``), condtrack version, seed and
  queries file (``hashes.queries_hash``): read from the HDF5 root attributes,
  or for a CSV from the manifest's last ``ok`` record of that output; the input's
  fingerprint always from that record (an output without one is redone).
  Outputs are written atomically, so an output that exists is whole.
- Shards: ``shard(items, i, n)`` keeps items i, i + n, i + 2n, ... of the list.
"""

from __future__ import annotations

import os
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

from condtrack_cli import __version__
from condtrack_cli.batch.job import BatchJob, job_record
from condtrack_cli.batch.manifest import ClipRecord, open_manifest, read_manifest
from condtrack_cli.config import Config
from condtrack_cli.errors import CondtrackError
from condtrack_cli.hashes import config_hash, input_fingerprint, queries_hash
from condtrack_cli.io.atomic import refuse_overwriting_inputs


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
    if not (sep and index.strip().isdecimal() and count.strip().isdecimal()) or not 0 <= int(index) < int(count):
        raise ValueError(f"expected I/N with 0 <= I < N (e.g. 0/4), got {text!r}")
    return int(index), int(count)


def shard(items: list, index: int, count: int) -> list:
    """Items index, index + count, index + 2 count, ...: ``count`` shards cover the list once, in balanced parts."""
    return items[index::count]


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
        except (OSError, KeyError, TypeError, ValueError):  # ValueError, TypeError: an attribute int() cannot read
            return None  # not a readable track file: redo it
    return last or None


def skipped_record(job: BatchJob, manifest: list[dict]) -> ClipRecord | None:
    """A ``skipped`` record when ``job.output`` exists and was made from this input by this version with these
    settings, else None."""
    stored = _stored_run(Path(job.output), manifest)
    wanted = {"config_hash": config_hash(job.config), "version": __version__, "seed": job.seed,
              "queries_hash": job.queries_hash, "input_fingerprint": job.input_fingerprint}
    if stored is None or any(stored.get(key) != value for key, value in wanted.items()):
        return None
    return job_record(job, "skipped", error=None, seconds=0.0, frames=stored.get("frames"),
                      points=stored.get("points"))


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
    """Name every input's output, refuse one that is the queries file or a folder, create ``out_dir``, keep this
    shard, and find what ``skip_existing`` skips."""
    names = output_names(inputs)
    outputs = {f"the output of '{i}',": out_dir / f"{n}{suffix}" for i, n in zip(inputs, names)}
    refuse_overwriting_inputs(outputs, {"-p": queries_path})
    for option, output in outputs.items():  # else found after the input's tracking, when the output is moved in place
        if output.is_dir():
            raise CondtrackError(f"{option} {output}: a folder, which an output file cannot replace")
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise CondtrackError(f"--out-dir '{out_dir}': cannot create the folder ({error.strerror})") from None
    if not os.access(out_dir, os.W_OK | os.X_OK):
        raise CondtrackError(f"--out-dir '{out_dir}' is not writable")
    os.close(open_manifest(out_dir))  # a manifest that cannot take the records is refused before any work
    cwd, digest = os.getcwd(), queries_hash(queries_path)
    jobs = [BatchJob(i, str(out_dir / f"{n}{suffix}"), config, queries_path, seed, threads, input_fingerprint(i), cwd,
                     queries_hash=digest) for i, n in zip(inputs, names)]
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
