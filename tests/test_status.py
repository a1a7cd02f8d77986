"""``condtrack status OUT_DIR`` (issue 30.2): the latest manifest record per input, counts, time, the redo command."""

from __future__ import annotations

import json
import shlex

from click.testing import CliRunner

from condtrack_cli import __version__
from condtrack_cli.batch.manifest import ClipRecord, append_record
from condtrack_cli.cli import cli
from condtrack_cli.config import load_config
from condtrack_cli.errors import MissingInput
from condtrack_cli.hashes import config_hash

STK = config_hash(load_config(None, [], "stk"))


def record(out_dir, name: str, status: str, seconds: float, error: str | None = None, suffix=".h5", config=STK):
    """Append a manifest line for data/<name>/frames, written to OUT_DIR/<name>_frames<suffix>."""
    append_record(out_dir, ClipRecord(
        input=f"data/{name}/frames", output=str(out_dir / f"{name}_frames{suffix}"), status=status, error=error,
        seconds=seconds, frames=None if error else 5, points=None if error else 12, method="stk",
        config_hash=config, version=__version__, seed=0, queries_hash=""))


def status(*args: str):
    return CliRunner().invoke(cli, ["status", *args])


def test_retries_a_failure_a_skip_and_a_lost_output(tmp_path):
    out = tmp_path / "tracks"
    out.mkdir()
    record(out, "clip000", "failed", 0.5, "data/clip000/frames: no such file or folder")
    record(out, "clip001", "ok", 2.0)
    record(out, "clip002", "ok", 3.0)
    record(out, "clip000", "ok", 1.5)  # a retry that worked
    record(out, "clip001", "failed", 0.25, "frame 3 (data/clip001/frames/3.png): not a readable image")
    record(out, "clip002", "skipped", 0.0)
    record(out, "clip003", "ok", 1.0)  # its output is deleted below
    for name in ("clip000", "clip001", "clip002"):
        (out / f"{name}_frames.h5").write_bytes(b"")
    result = status(str(out))
    assert result.exit_code == 1  # an input's latest record is failed
    assert result.stdout.splitlines() == [
        "ok       data/clip000/frames  " + str(out / "clip000_frames.h5") + " (2 attempts)",
        "failed   data/clip001/frames  frame 3 (data/clip001/frames/3.png): not a readable image (2 attempts)",
        "skipped  data/clip002/frames  " + str(out / "clip002_frames.h5") + " (2 attempts)",
        "missing  data/clip003/frames  " + str(out / "clip003_frames.h5") + " is gone",
        "4 inputs: 1 ok, 1 failed, 1 skipped, 1 missing; 2.8 s in their latest runs, 8.2 s in all",
        "redo the failed and missing inputs (from the folder the batch ran in):",
        f"  condtrack track data/clip001/frames data/clip003/frames --out-dir {out} -m stk --seed 0",
    ]
    report = json.loads(status(str(out), "--json").stdout)
    assert report["counts"] == {"ok": 1, "failed": 1, "skipped": 1, "missing": 1}
    assert [(i["input"], i["status"], i["attempts"]) for i in report["inputs"]] == [
        ("data/clip000/frames", "ok", 2), ("data/clip001/frames", "failed", 2), ("data/clip002/frames", "skipped", 2),
        ("data/clip003/frames", "missing", 1)]
    assert report["inputs"][1]["error"].endswith("not a readable image") and report["seconds"] == 2.75
    assert report["seconds_all_attempts"] == 8.25 and report["notes"] == []


def test_the_redo_keeps_the_output_names_and_says_what_it_cannot_know(tmp_path):
    """Redone alone, x/frames would be named frames.csv: the redo then lists every input with --skip-existing."""
    out = tmp_path / "o"
    out.mkdir()
    record(out, "x", "failed", 1.0, "data/x/frames: no image files", suffix=".csv", config="another")
    record(out, "y", "ok", 1.0, suffix=".csv", config="another")
    (out / "y_frames.csv").write_text("")
    result = status(str(out))
    assert result.exit_code == 1
    assert result.stdout.splitlines()[-2:] == [
        f"  condtrack track data/x/frames data/y/frames --out-dir {out} -m stk --seed 0 --format csv --skip-existing",
        "  # -m stk: the batch's config is not that method's defaults; add its -c/--set options"]
    assert shlex.split(result.stdout.splitlines()[-2])[2:4] == ["data/x/frames", "data/y/frames"]


def test_all_done_exits_0_and_a_folder_without_manifest_is_an_error(tmp_path):
    record(tmp_path, "a", "ok", 1.0)
    (tmp_path / "a_frames.h5").write_bytes(b"")
    done = status(str(tmp_path))
    assert done.exit_code == 0 and "redo" not in done.stdout
    empty = tmp_path / "empty"
    empty.mkdir()
    result = status(str(empty))  # main() prints it as one Error: line, exit 2 (README, Exit codes)
    assert isinstance(result.exception, MissingInput) and "manifest.jsonl: no manifest records" in str(result.exception)
    result = status(str(tmp_path / "nowhere"))
    assert result.exit_code == 2 and "does not exist" in result.output
