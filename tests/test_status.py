"""``condtrack status OUT_DIR`` (issue 30.2): the latest manifest record per input, counts, time, the redo command."""

from __future__ import annotations

import json
import os
import shlex
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner

from condtrack_cli import __version__
from condtrack_cli.batch.manifest import ClipRecord, append_records
from condtrack_cli.cli import cli, main
from condtrack_cli.config import load_config
from condtrack_cli.errors import MissingInput
from condtrack_cli.frames.synthetic import make_scene, write_scene
from condtrack_cli.hashes import config_hash

STK = config_hash(load_config(None, [], "stk"))


def record(out_dir, name: str, status: str, seconds: float, error: str | None = None, suffix=".h5", config=STK,
           cwd=""):
    """Append a manifest line for data/<name>/frames, written to OUT_DIR/<name>_frames<suffix>; ``cwd``: the batch's
    folder ("": not recorded, as in older manifests)."""
    append_records(out_dir, ClipRecord(
        input=f"data/{name}/frames", output=str(out_dir / f"{name}_frames{suffix}"), status=status, error=error,
        seconds=seconds, frames=None if error else 5, points=None if error else 12, method="stk",
        config_hash=config, version=__version__, seed=0, queries_hash="", cwd=cwd))


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
        "redo the failed, interrupted and missing inputs:",
        f"  condtrack track data/clip001/frames data/clip003/frames --out-dir {out} -m stk --seed 0",
        "  # -m stk: the manifest does not say which folder the batch ran in; run the command from there",
    ]
    report = json.loads(status(str(out), "--json").stdout)
    assert report["counts"] == {"ok": 1, "failed": 1, "interrupted": 0, "skipped": 1, "missing": 1}
    assert [(i["input"], i["status"], i["attempts"]) for i in report["inputs"]] == [
        ("data/clip000/frames", "ok", 2), ("data/clip001/frames", "failed", 2), ("data/clip002/frames", "skipped", 2),
        ("data/clip003/frames", "missing", 1)]
    assert report["inputs"][1]["error"].endswith("not a readable image") and report["seconds"] == 2.75
    assert report["seconds_all_attempts"] == 8.25 and report["notes"] == [
        "-m stk: the manifest does not say which folder the batch ran in; run the command from there"]


def test_the_redo_keeps_the_output_names_and_says_what_it_cannot_know(tmp_path):
    """Redone alone, x/frames would be named frames.csv: the redo then lists every input with --skip-existing."""
    out = tmp_path / "o"
    out.mkdir()
    record(out, "x", "failed", 1.0, "data/x/frames: no image files", suffix=".csv", config="another")
    record(out, "y", "ok", 1.0, suffix=".csv", config="another")
    (out / "y_frames.csv").write_text("")
    result = status(str(out))
    assert result.exit_code == 1
    assert result.stdout.splitlines()[-3:] == [
        f"  condtrack track data/x/frames data/y/frames --out-dir {out} -m stk --seed 0 --format csv --skip-existing",
        "  # -m stk: the manifest does not say which folder the batch ran in; run the command from there",
        "  # -m stk: the batch's config is not that method's defaults; add its -c/--set options"]
    assert shlex.split(result.stdout.splitlines()[-3])[2:4] == ["data/x/frames", "data/y/frames"]


def test_a_redo_that_cannot_give_the_batch_s_output_name_says_so(tmp_path):
    """A shard's failed input named x_frames.h5 from the whole list (x/frames beside y/frames of another shard): the
    redo, knowing x alone, would write frames.h5, and nothing said so."""
    record(tmp_path, "x", "failed", 1.0, "data/x/frames: no image files", cwd=str(tmp_path))
    assert status(str(tmp_path)).stdout.splitlines()[-2:] == [
        f"  condtrack track {tmp_path}/data/x/frames --out-dir {tmp_path} -m stk --seed 0 --skip-existing",
        "  # -m stk: the outputs were named from a longer input list than the manifest holds (another shard's, or "
        "inputs not run yet); redo with that list and --skip-existing"]


def test_an_output_replaced_by_another_input_s_of_the_same_name_is_missing(tmp_path):
    """x/frames then y/frames, each batched alone into one OUT_DIR, both write frames.h5: status said both were ok,
    though the file on disk was y's; x's is missing, named as replaced, and redone."""
    for name in ("x", "y"):
        append_records(tmp_path, ClipRecord(
            input=f"{name}/frames", output=str(tmp_path / "frames.h5"), status="ok", error=None, seconds=1.0, frames=5,
            points=12, method="stk", config_hash=STK, version=__version__, seed=0, queries_hash="", cwd=str(tmp_path)))
    (tmp_path / "frames.h5").write_bytes(b"")
    result = status(str(tmp_path))
    assert result.exit_code == 0
    assert result.stdout.splitlines()[:4] == [
        f"missing  {tmp_path}/x/frames  {tmp_path}/frames.h5 was replaced by the output of {tmp_path}/y/frames",
        f"ok       {tmp_path}/y/frames  {tmp_path}/frames.h5",
        "2 inputs: 1 ok, 1 missing; 2.0 s in their latest runs, 2.0 s in all",
        "redo the failed, interrupted and missing inputs:"]


def test_the_redo_writes_into_the_out_dir_read_even_when_moved(tmp_path, monkeypatch):
    """A batch's OUT_DIR renamed (tracks -> tracks_v1): status read tracks_v1's manifest and outputs, but its redo
    wrote into tracks, the folder the records name, away from the others (a new folder, with --skip-existing every
    input again)."""
    (tmp_path / "tracks").mkdir()
    record(tmp_path / "tracks", "a", "failed", 1.0, "data/a/frames: no such file or folder", cwd=str(tmp_path))
    (tmp_path / "tracks").rename(tmp_path / "tracks_v1")
    monkeypatch.chdir(tmp_path)
    assert status("tracks_v1").stdout.splitlines()[-2] == (
        f"  condtrack track {tmp_path}/data/a/frames --out-dir {tmp_path}/tracks_v1 -m stk --seed 0 --skip-existing")


def test_all_done_exits_0_and_a_folder_without_manifest_is_an_error(tmp_path, monkeypatch, capsys):
    """A missing OUT_DIR gave Click's usage line and 'Directory ... does not exist', where every other command names a
    missing input in one Error: line (README, Exit codes); it is now that line."""
    record(tmp_path, "a", "ok", 1.0)
    (tmp_path / "a_frames.h5").write_bytes(b"")
    done = status(str(tmp_path))
    assert done.exit_code == 0 and "redo" not in done.stdout
    empty = tmp_path / "empty"
    empty.mkdir()
    result = status(str(empty))  # main() prints it as one Error: line, exit 2 (README, Exit codes)
    assert isinstance(result.exception, MissingInput) and "manifest.jsonl: no manifest records" in str(result.exception)
    assert _main(["status", str(tmp_path / "nowhere")], monkeypatch, capsys) == (
        2, "", f"Error: {tmp_path / 'nowhere'}: no such folder\n")


def _main(args: list[str], monkeypatch, capsys) -> tuple[int, str, str]:
    """Run the console entry point here; (exit code, stdout, stderr)."""
    monkeypatch.setattr(sys, "argv", ["condtrack", *args])
    previous = signal.getsignal(signal.SIGTERM)  # main() installs its own
    try:
        with pytest.raises(SystemExit) as stop:
            main()
    finally:
        signal.signal(signal.SIGTERM, previous)
    captured = capsys.readouterr()
    return stop.value.code, captured.out, captured.err


def test_a_batch_run_elsewhere_and_resumed_with_other_paths_is_two_inputs_found_in_place(tmp_path, monkeypatch, capsys):
    """Issue 47.1 and 47.2: a batch run in work/ with relative paths, resumed from the parent folder with paths typed
    otherwise, read by status from the parent folder: its outputs were 'missing' (looked for from the current
    folder) and each input counted twice."""
    work = tmp_path / "work"
    for seed, name in enumerate(("c1", "c2")):
        write_scene(make_scene("camera_motion", seed=seed, size=(160, 120), n_frames=3), work / "data" / name)
    monkeypatch.chdir(work)
    assert _main(["track", "data/c1", "./data/c2", "-m", "stk", "--out-dir", "out", "-q"], monkeypatch, capsys)[:2] == (
        0, "")
    monkeypatch.chdir(tmp_path)
    code, _, err = _main(["track", "work/data/c1", "work/data//c2", "-m", "stk", "--out-dir", "work/out", "-q",
                          "--skip-existing"], monkeypatch, capsys)
    assert (code, err) == (0, "")
    code, out, _ = _main(["status", "work/out"], monkeypatch, capsys)
    assert code == 0
    assert out.splitlines()[:3] == [f"skipped  {work}/data/c1  work/out/c1.h5 (2 attempts)",
                                    f"skipped  {work}/data/c2  work/out/c2.h5 (2 attempts)",
                                    "2 inputs: 2 skipped" + out.splitlines()[2][len("2 inputs: 2 skipped"):]]
    (work / "out" / "c2.h5").unlink()
    monkeypatch.chdir(work / "data")  # the redo names absolute paths: it runs from any folder
    code, out, _ = _main(["status", "../out"], monkeypatch, capsys)
    assert code == 0 and out.splitlines()[1] == f"missing  {work}/data/c2  ../out/c2.h5 is gone (2 attempts)"
    assert out.splitlines()[-1] == f"  condtrack track {work}/data/c2 --out-dir {work}/out -m stk --seed 0"


def test_interrupted_inputs_are_counted_and_redone_without_an_output(tmp_path):
    """Issue 47.3: interrupted inputs were not counted, were shown with an output they do not have, were not in the
    redo command, and status exited 0."""
    out = tmp_path / "o"
    out.mkdir()
    folder = str(tmp_path)
    record(out, "a", "ok", 2.0, cwd=folder)
    (out / "a_frames.h5").write_bytes(b"")
    record(out, "b", "interrupted", 0.0, "interrupted", cwd=folder)
    record(out, "c", "interrupted", 0.0, "interrupted", cwd=folder)
    result = status(str(out))
    assert result.exit_code == 1  # as for a failed input: the batch's own record says the input did not end
    assert result.stdout.splitlines() == [
        f"ok           {folder}/data/a/frames  {out}/a_frames.h5",
        f"interrupted  {folder}/data/b/frames  stopped before it ended: no output",
        f"interrupted  {folder}/data/c/frames  stopped before it ended: no output",
        "3 inputs: 1 ok, 2 interrupted; 2.0 s in their latest runs, 2.0 s in all",
        "redo the failed, interrupted and missing inputs:",
        f"  condtrack track {folder}/data/b/frames {folder}/data/c/frames --out-dir {out} -m stk --seed 0",
    ]
    report = json.loads(status(str(out), "--json").stdout)
    assert report["counts"] == {"ok": 1, "failed": 0, "interrupted": 2, "skipped": 0, "missing": 0}
    assert [item["output"] for item in report["inputs"]] == [str(out / "a_frames.h5"), None, None]
    assert report["redo"] == [result.stdout.splitlines()[-1].strip()] and report["notes"] == []


#: A batch whose process SIGKILLs itself (as the OOM killer would) as its input ``data/c2`` starts.
KILLED_AT_C2 = """
import os, signal
from condtrack_cli.batch import local
from condtrack_cli.cli import main
run_job = local.run_job
local.run_job = lambda job: os.kill(os.getpid(), signal.SIGKILL) if job.input == "data/c2" else run_job(job)
main()
"""


def test_inputs_of_a_batch_killed_with_sigkill_are_interrupted_and_redone(tmp_path, monkeypatch, capsys):
    """A batch killed by SIGKILL (the OOM killer, a power loss) records nothing for the inputs it had not ended, so
    status listed only the ended ones and printed no redo: the others were forgotten. The batch now records its plan
    as it starts, and an input planned but never ended is interrupted, counted and redone."""
    for seed, name in enumerate(("c1", "c2", "c3")):
        write_scene(make_scene("camera_motion", seed=seed, size=(160, 120), n_frames=5), tmp_path / "data" / name)
    killed = subprocess.run(
        [sys.executable, "-c", KILLED_AT_C2, "track", "data/c1", "data/c2", "data/c3", "-m", "stk", "--out-dir", "out",
         "-q"], cwd=tmp_path, capture_output=True, text=True, timeout=120,
        env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    monkeypatch.chdir(tmp_path)
    code, out, _ = _main(["status", "out"], monkeypatch, capsys)
    never = "never ended (the batch was killed, or is still running): no output"
    assert code == 1 and out.splitlines() == [
        f"ok           {tmp_path}/data/c1  out/c1.h5",
        f"interrupted  {tmp_path}/data/c2  {never}",
        f"interrupted  {tmp_path}/data/c3  {never}",
        out.splitlines()[3],  # the time taken varies
        "redo the failed, interrupted and missing inputs:",
        f"  condtrack track {tmp_path}/data/c2 {tmp_path}/data/c3 --out-dir {tmp_path}/out -m stk --seed 0",
    ]
    assert out.splitlines()[3].startswith("3 inputs: 1 ok, 2 interrupted; ")
    redo = shlex.split(out.splitlines()[-1])[1:]
    assert _main([*redo, "-q"], monkeypatch, capsys) == (0, "", "")
    code, out, _ = _main(["status", "out"], monkeypatch, capsys)
    assert code == 0 and out.splitlines()[:3] == [  # the killed attempt counts; the plans that ended do not
        f"ok       {tmp_path}/data/c1  out/c1.h5", f"ok       {tmp_path}/data/c2  out/c2.h5 (2 attempts)",
        f"ok       {tmp_path}/data/c3  out/c3.h5 (2 attempts)"]


def test_a_plan_is_ended_by_the_next_record_of_its_input_and_output(tmp_path):
    """A ``planned`` record followed by its input's end is no attempt of its own; one followed by nothing, or by a
    plan of another batch, is an attempt that never ended; one followed by the end of another output of its input
    (another --format) is that other output's run, not this one's end."""
    out = tmp_path / "o"
    out.mkdir()
    folder = str(tmp_path)
    for name, status_, seconds, error, suffix in [
            ("a", "planned", 0.0, None, ".h5"), ("b", "planned", 0.0, None, ".h5"), ("a", "ok", 2.0, None, ".h5"),
            ("c", "planned", 0.0, None, ".h5"), ("c", "interrupted", 0.0, "interrupted", ".h5"),  # Ctrl-C
            ("d", "planned", 0.0, None, ".h5"), ("d", "planned", 0.0, None, ".h5"), ("d", "ok", 1.0, None, ".h5"),
            ("e", "planned", 0.0, None, ".csv"), ("e", "planned", 0.0, None, ".h5"), ("e", "ok", 1.0, None, ".csv")]:
        record(out, name, status_, seconds, error, suffix=suffix, cwd=folder)
    for name in ("a_frames.h5", "d_frames.h5", "e_frames.csv"):
        (out / name).write_bytes(b"")
    report = json.loads(status(str(out), "--json").stdout)
    assert [(i["input"][len(folder):], i["status"], i["error"], i["attempts"]) for i in report["inputs"]] == [
        ("/data/a/frames", "ok", None, 1),
        ("/data/b/frames", "interrupted", "never ended (the batch was killed, or is still running)", 1),
        ("/data/c/frames", "interrupted", "interrupted", 1),
        ("/data/d/frames", "ok", None, 2),
        ("/data/e/frames", "ok", None, 2)]
    assert report["counts"]["interrupted"] == 2 and report["seconds_all_attempts"] == 4.0
    assert status(str(out)).stdout.splitlines()[2].endswith("  stopped before it ended: no output")


def test_a_batch_with_queries_whose_inputs_all_failed_says_to_add_p(tmp_path, monkeypatch, capsys):
    """A failed (or interrupted) input's record had an empty queries_hash, so when no input of a batch run with -p
    ended ok the redo command lacked -p and no note said to add it: the redo would detect points instead. Every
    record now holds the planned queries file's hash."""
    from condtrack_cli.batch.job import interrupted_record
    from condtrack_cli.batch.plan import plan_batch
    from condtrack_cli.hashes import queries_hash

    queries = tmp_path / "q.csv"
    queries.write_text("frame,x,y\n0,10,10\n")
    monkeypatch.chdir(tmp_path)
    code, _, _ = _main(["track", "gone1", "gone2", "-p", "q.csv", "-m", "stk", "--out-dir", "o", "-q"], monkeypatch,
                       capsys)
    assert code == 1
    code, out, _ = _main(["status", "o"], monkeypatch, capsys)
    assert code == 1 and out.splitlines()[-1] == "  # -m stk: the batch had a queries file; add its -p option"
    plan = plan_batch(["gone1"], load_config(None, [], "stk"), "q.csv", tmp_path / "o", ".h5", 0, None)
    assert interrupted_record(plan.todo[0]).queries_hash == queries_hash(queries) != ""


@pytest.mark.parametrize("line, problem", [
    ('{"input": "a", "output": "a.h5", "seconds": 1, "method": "stk", "seed": 0, "config_hash": ""}',
     "the record has no 'status'"),
    ('{"input": "a", "status": "ok", "seconds": 1, "method": "stk", "seed": 0, "config_hash": ""}',
     "the record has no 'output'"),
    ('{"input": "a", "output": "a.h5", "status": "ok", "method": "stk", "seed": 0, "config_hash": ""}',
     "the record has no 'seconds'"),
    ('{"input": "a", "output": "a.h5", "status": "ok", "seconds": "1", "method": "stk", "seed": 0, '
     '"config_hash": ""}', "'seconds' is \"1\", not a number"),
    ('{"input": "a", "output": "a.h5", "status": "ok", "seconds": NaN, "method": "stk", "seed": 0, "config_hash": ""}',
     "'seconds' is NaN, not a number"),
    ('{"input": "a", "output": "a.h5", "status": "ok", "seconds": -Infinity, "method": "stk", "seed": 0, '
     '"config_hash": ""}', "'seconds' is -Infinity, not a number"),
    ('{"input": "a", "output": "a.h5", "status": "ok", "seconds": 1, "method": "stk", "seed": "0", "config_hash": ""}',
     "'seed' is \"0\", not an integer"),
    ('{"input": "a", "output": "a.h5", "status": "done", "seconds": 1, "method": "stk", "seed": 0, '
     '"config_hash": ""}', 'unknown status "done" (not one of ok, failed, skipped, interrupted, planned)'),
    ('{"input": "a", "output": "a.h', "not a JSON record"),
    ("[1, 2]", "not a JSON object"),
], ids=["no status", "no output", "no seconds", "seconds a string", "seconds NaN", "seconds -inf", "seed a string",
        "unknown status", "broken JSON", "a list"])
def test_a_broken_manifest_line_is_named(tmp_path, monkeypatch, capsys, line, problem):
    """Issue 47.9: a record without 'status' was a KeyError traceback; a broken line was silently skipped. Seconds of
    NaN (which Python's json reads) were taken and printed by status --json as NaN, which is not JSON."""
    record(tmp_path, "a", "ok", 1.0)
    with open(tmp_path / "manifest.jsonl", "a") as manifest:
        manifest.write(line + "\n")
    record(tmp_path, "b", "ok", 1.0)
    assert _main(["status", str(tmp_path)], monkeypatch, capsys) == (
        1, "", f"Error: {tmp_path / 'manifest.jsonl'}, line 2: {problem}\n")


def test_blank_lines_in_the_manifest_are_skipped(tmp_path):
    """Two manifests joined with a blank line between (or a hand edit) were refused: 'line 2: not a JSON record'."""
    record(tmp_path, "a", "ok", 1.0)
    with open(tmp_path / "manifest.jsonl", "a") as manifest:
        manifest.write("\n  \n")
    record(tmp_path, "b", "ok", 1.0)
    for name in ("a", "b"):
        (tmp_path / f"{name}_frames.h5").write_bytes(b"")
    result = status(str(tmp_path))
    assert result.exit_code == 0, result.stderr
    assert "2 inputs: 2 ok" in result.stdout


def test_a_last_line_cut_short_by_a_kill_is_ignored(tmp_path):
    record(tmp_path, "a", "ok", 1.0)
    (tmp_path / "a_frames.h5").write_bytes(b"")
    with open(tmp_path / "manifest.jsonl", "a") as manifest:
        manifest.write('{"input": "data/b/frames", "outp')
    result = status(str(tmp_path))
    assert result.exit_code == 0 and result.stdout.startswith("1 inputs: 1 ok", len(result.stdout.splitlines()[0]) + 1)


@pytest.mark.parametrize("tail", ['{"input": "data/b/frames", "outp', "whole"])
def test_a_record_appended_after_a_line_cut_short_stays_a_record(tmp_path, tail):
    """A batch killed (or out of disk) in the middle of a manifest line left it without a newline, and the next
    batch's record was appended to it: one broken line of both, which status refused for good ('line 2: not a JSON
    record') and --skip-existing skipped, the new record with it. The cut line is now ended first, marked as cut
    short (status skips it), or by a newline alone when it is a whole record."""
    record(tmp_path, "a", "ok", 1.0)
    whole = (tmp_path / "manifest.jsonl").read_text().splitlines()[0]
    with open(tmp_path / "manifest.jsonl", "a") as manifest:
        manifest.write(whole.replace("/a_frames.h5", "/c_frames.h5").replace('"data/a/frames"', '"data/c/frames"')
                       if tail == "whole" else tail)
    record(tmp_path, "b", "ok", 2.0)
    for name in ("a", "b", "c"):
        (tmp_path / f"{name}_frames.h5").write_bytes(b"")
    result = status(str(tmp_path))
    assert result.exit_code == 0, result.stderr
    counted = "3 inputs: 3 ok" if tail == "whole" else "2 inputs: 2 ok"
    assert "data/b/frames" in result.stdout and counted in result.stdout
