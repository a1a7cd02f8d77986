"""Batches: output names, manifest, resume, shards, Dask, interrupts and threads per job.

The clips are small synthetic scenes laid out as a dataset is (``clipNNN/frames``),
tracked with ``stk`` (the fastest method) unless a test needs slower clips.
"""

from __future__ import annotations

import json
import os
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import default_sigint

from condtrack_cli.batch.manifest import MANIFEST
from condtrack_cli.batch.plan import _stored_run, output_names, parse_shard, shard
from condtrack_cli.errors import CondtrackError
from condtrack_cli.frames.synthetic import make_scene, write_scene

MANIFEST_FIELDS = {"input", "output", "status", "error", "seconds", "frames", "points", "method", "config_hash",
                   "version", "seed"}


def run_cli(*args: str, env: dict | None = None, affinity: set[int] | None = None) -> subprocess.CompletedProcess:
    """Run the real console entry point in a child process (on the CPUs ``affinity`` when given)."""
    return subprocess.run(
        [sys.executable, "-c", "from condtrack_cli.cli import main; main()", *args],
        capture_output=True, text=True, timeout=300, env=env,
        preexec_fn=None if affinity is None else lambda: os.sched_setaffinity(0, affinity),
    )


def make_clips(root: Path, count: int, n_frames: int | list[int] = 5) -> list[str]:
    """``count`` folders root/clipNNN/frames of the 160 x 120 camera_motion scene (seed NNN); their paths."""
    clips = []
    for index in range(count):
        folder = root / f"clip{index:03d}" / "frames"
        length = n_frames[index] if isinstance(n_frames, list) else n_frames
        write_scene(make_scene("camera_motion", seed=index, size=(160, 120), n_frames=length), folder)
        clips.append(str(folder))
    return clips


def manifest(out_dir: Path, planned: bool = False) -> list[dict]:
    """The manifest's records: the inputs' ends, and with ``planned`` the batches' plans too."""
    records = [json.loads(line) for line in (out_dir / MANIFEST).read_text().splitlines()]
    return [record for record in records if planned or record["status"] != "planned"]


def outputs(out_dir: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(out_dir.glob("*.h5"))}


@pytest.fixture(scope="module")
def clips(tmp_path_factory) -> list[str]:
    return make_clips(tmp_path_factory.mktemp("data"), 4)


def test_same_named_inputs_get_the_shortest_distinguishing_tail():
    assert output_names(["/d/clip001/frames", "/d/clip002/frames", "/e/other.mp4"]) == [
        "clip001_frames", "clip002_frames", "other"]
    # only the inputs that share a name grow; a deeper clash grows further
    assert output_names(["/a/x/frames", "/b/x/frames", "/c/y/frames", "/c/solo"]) == [
        "a_x_frames", "b_x_frames", "y_frames", "solo"]
    assert output_names(["/v/clip.mp4", "/w/clip.avi"]) == ["v_clip", "w_clip"]
    with pytest.raises(CondtrackError, match="given twice"):
        output_names(["/d/a/frames", "/d/a/./frames"])
    with pytest.raises(CondtrackError, match="would both write 'v_clip'"):
        output_names(["/v/clip.mp4", "/v/clip.avi"])


def test_shards_cover_every_input_once():
    items = list(range(11))
    parts = [shard(items, i, 3) for i in range(3)]
    assert sorted(sum(parts, [])) == items and [len(p) for p in parts] == [4, 4, 3]
    assert parse_shard("2/3") == (2, 3)
    for bad in ("3/3", "-1/3", "1", "a/b", "0/0", "\u00b2/3"):  # "²" is a digit to str.isdigit, not to int()
        with pytest.raises(ValueError, match="expected I/N"):
            parse_shard(bad)


def test_batch_creates_out_dir_names_same_named_inputs_and_writes_the_manifest(clips, tmp_path):
    out_dir = tmp_path / "new" / "tracks"
    broken = tmp_path / "broken" / "frames"
    broken.mkdir(parents=True)
    (broken / "0.png").write_bytes(b"not a png")
    result = run_cli("track", *clips[:2], str(broken), "-m", "stk", "--seed", "3", "--out-dir", str(out_dir), "-j", "2")
    assert result.returncode == 1, result.stderr
    assert sorted(p.name for p in out_dir.iterdir()) == ["clip000_frames.h5", "clip001_frames.h5", MANIFEST]
    records = manifest(out_dir)
    assert sorted(r["input"] for r in records) == sorted([*clips[:2], str(broken)])
    plan = manifest(out_dir, planned=True)[:3]  # written as the batch starts, before any end
    names = ["clip000_frames.h5", "clip001_frames.h5", "broken_frames.h5"]
    assert [(r["input"], r["output"], r["status"]) for r in plan] == [
        (clip, str(out_dir / name), "planned") for clip, name in zip([*clips[:2], str(broken)], names)]
    for record in records:
        assert MANIFEST_FIELDS <= set(record), record
        assert (record["method"], record["seed"], record["version"]) == ("stk", 3, "0.1.0")
        assert len(record["config_hash"]) == 64
    by_input = {r["input"]: r for r in records}
    assert by_input[str(broken)]["status"] == "failed" and "not a readable image" in by_input[str(broken)]["error"]
    ok = by_input[clips[0]]
    assert ok["status"] == "ok" and ok["error"] is None and ok["frames"] == 5 and ok["points"] > 0
    assert ok["output"] == str(out_dir / "clip000_frames.h5") and ok["seconds"] > 0
    # progress over clips, then the table
    assert "[3/3]" in result.stderr and "1 failed so far" in result.stderr and "condtrack batch" in result.stderr
    import h5py

    with h5py.File(out_dir / "clip000_frames.h5") as f:
        assert f.attrs["config_hash"] == ok["config_hash"] and f.attrs["queries_hash"] == ""
    # resume: the HDF5 outputs made with these settings are skipped, the failed input is tried again
    again = run_cli("track", *clips[:2], str(broken), "-m", "stk", "--seed", "3", "--out-dir", str(out_dir),
                    "--skip-existing", "-q")
    assert again.returncode == 1 and again.stderr.count(f"Error: {broken}: ") == 1
    status = {r["input"]: r["status"] for r in manifest(out_dir)[3:]}
    assert status == {clips[0]: "skipped", clips[1]: "skipped", str(broken): "failed"}
    assert [(r["input"], r["status"]) for r in manifest(out_dir, planned=True)[6:7]] == [(str(broken), "planned")]


def test_config_hash_follows_the_resolved_config():
    from condtrack_cli.config import load_config
    from condtrack_cli.hashes import config_hash

    same = config_hash(load_config(None, [], "stk")) == config_hash(load_config(None, ["filter.method=stk"], None))
    assert same
    assert config_hash(load_config(None, [], "stk")) != config_hash(load_config(None, ["filter.stk.win_size=31"], "stk"))


def test_killed_batch_resumes_with_skip_existing_and_does_each_input_once(tmp_path):
    clips = make_clips(tmp_path / "data", 4, n_frames=8)
    out_dir = tmp_path / "tracks"
    args = ["track", *clips, "-m", "cnlf", "--out-dir", str(out_dir), "--format", "csv", "--skip-existing"]
    process = subprocess.Popen([sys.executable, "-c", "from condtrack_cli.cli import main; main()", *args],
                               preexec_fn=default_sigint, stderr=subprocess.PIPE, text=True)
    for line in process.stderr:  # until the first input is done
        if "[1/4]" in line:
            break
    else:
        pytest.fail(f"the batch ended before its first input was done (exit {process.wait()})")
    process.send_signal(signal.SIGTERM)
    _, stderr = process.communicate(timeout=120)
    assert process.returncode == 143, stderr
    first = manifest(out_dir)
    done = {r["input"] for r in first if r["status"] == "ok"}
    assert 1 <= len(done) < 4 and not list(out_dir.glob("*.part")) and not list(out_dir.glob(".*"))
    result = run_cli(*args, "-q")
    assert result.returncode == 0, result.stderr
    second = manifest(out_dir)[len(first):]
    assert {r["input"] for r in second if r["status"] == "skipped"} == done
    ok = [r["input"] for r in first + second if r["status"] == "ok"]
    assert sorted(ok) == sorted(clips)  # every input done exactly once over both runs
    assert len(list(out_dir.glob("*.csv"))) == 4
    # another seed is another result: not skipped
    result = run_cli(*args, "--seed", "1", "--shard", "0/4", "-q")
    assert result.returncode == 0
    assert [r["status"] for r in manifest(out_dir)[len(first) + len(second):]] == ["ok"]


def test_a_batch_removes_the_staging_folder_of_a_batch_killed_with_sigkill(clips, tmp_path):
    """A batch killed with SIGKILL (the OOM killer, a cluster's time limit) runs no clean-up: its staging folder in
    OUT_DIR, with the outputs it had not moved in place, stayed there for good, one more at each kill. The next batch
    into OUT_DIR removes it; a running batch's (this process stands for one) and another host's stay."""
    import socket

    dead = subprocess.Popen(["true"])
    dead.wait()
    out_dir, host = tmp_path / "tracks", socket.gethostname()
    stale, running, other_host = (out_dir / f".outputs-{host}-{dead.pid}-.x1.part",
                                  out_dir / f".outputs-{host}-{os.getpid()}-.x2.part",
                                  out_dir / f".outputs-{host}x-{dead.pid}-.x3.part")
    for folder in (stale, running, other_host):
        folder.mkdir(parents=True)
        (folder / "clip000_frames.h5").write_bytes(b"an output not moved in place")
    result = run_cli("track", clips[0], "-m", "stk", "--out-dir", str(out_dir), "-q")
    assert result.returncode == 0, result.stderr
    assert sorted(p.name for p in out_dir.iterdir()) == sorted([MANIFEST, "frames.h5", running.name, other_host.name])


def _running(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie, dead but not yet reaped by its new parent, does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the parent-death signal is Linux's prctl")
def test_workers_end_when_the_batch_process_is_killed(tmp_path):
    """A batch process SIGKILLed (the OOM killer: no clean-up runs) left its -j workers tracking on for nobody, then
    writing tracebacks into a closed pipe; each worker now gets SIGTERM when the batch's process dies."""
    script = tmp_path / "parent.py"
    script.write_text(  # each worker busy with a job (an idle one ends on its closed task pipe anyway)
        "import multiprocessing, os, pathlib, time\n"
        "from condtrack_cli.batch import local\n"
        "def job(k):\n"
        "    pathlib.Path(f'pid{k}').write_text(str(os.getpid()))\n"
        "    time.sleep(60)\n"
        "if __name__ == '__main__':\n"
        "    pool = multiprocessing.get_context('spawn').Pool(2, initializer=local._start_worker,\n"
        "                                                    initargs=(False, os.getpid()))\n"
        "    pool.map_async(job, range(2), chunksize=1)\n"
        "    while not all(pathlib.Path(f'pid{k}').exists() for k in range(2)):\n"
        "        time.sleep(0.05)\n"
        "    time.sleep(0.1)\n"
        "    print(*(pathlib.Path(f'pid{k}').read_text() for k in range(2)), flush=True)\n"
        "    time.sleep(60)\n"
    )
    parent = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, text=True, cwd=tmp_path,
                              stderr=subprocess.DEVNULL,  # its resource tracker's note on the semaphores it cleans up
                              env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])})
    try:
        assert select.select([parent.stdout], [], [], 60)[0], "the pool's workers did not start"
        workers = [int(pid) for pid in parent.stdout.readline().split()]
        assert workers and all(_running(pid) for pid in workers)
    finally:
        parent.kill()
        parent.wait(timeout=30)
        parent.stdout.close()
    deadline = time.monotonic() + 20
    while any(_running(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(_running(pid) for pid in workers)


def test_two_shards_cover_the_inputs_once_with_the_names_of_the_whole_list(clips, tmp_path):
    out_dir = tmp_path / "tracks"
    for index in range(2):
        result = run_cli("track", *clips, "-m", "stk", "--out-dir", str(out_dir), "--shard", f"{index}/2", "-q")
        assert result.returncode == 0, result.stderr
    records = manifest(out_dir)
    assert sorted(r["input"] for r in records) == sorted(clips)
    assert sorted(outputs(out_dir)) == [f"clip{i:03d}_frames.h5" for i in range(4)]


def test_a_shard_with_no_input_says_so_and_succeeds(clips, tmp_path):
    """More shards than inputs (a CI matrix wider than today's clip list): the empty shard tracks nothing, exits 0 and
    says why on stderr (not under -q)."""
    out_dir = tmp_path / "tracks"
    result = run_cli("track", clips[0], "-m", "stk", "--out-dir", str(out_dir), "--shard", "1/2")
    assert result.returncode == 0, result.stderr
    assert "warning: --shard 1/2: none of the 1 input(s) is in this shard (it takes inputs 1, 3, ..." in result.stderr
    assert not outputs(out_dir)
    quiet = run_cli("track", clips[0], "-m", "stk", "--out-dir", str(out_dir), "--shard", "1/2", "-q")
    assert quiet.returncode == 0 and quiet.stderr == ""


def _batch_signal_run(clips: list[str], out_dir: Path, sig: int) -> tuple[int, str, set, set, list[int]]:
    """Run a -j 2 batch, send ``sig`` once the first input is done; (exit code, stderr, outputs at the signal, after, worker pids)."""
    process = subprocess.Popen(
        [sys.executable, "-c", "from condtrack_cli.cli import main; main()", "track", *clips, "-m", "cnlf",
         "--out-dir", str(out_dir), "-j", "2"],
        preexec_fn=default_sigint, stderr=subprocess.PIPE, text=True,
    )
    for line in process.stderr:  # until the first input is reported done
        if "[1/" in line:
            break
    else:
        pytest.fail(f"the batch ended before its first input was done (exit {process.wait()})")
    workers = children(process.pid)
    at_signal = {p.name for p in out_dir.glob("*.h5")}
    process.send_signal(sig)
    _, stderr = process.communicate(timeout=120)
    time.sleep(1.0)  # a worker left running would publish its output meanwhile
    return process.returncode, stderr, at_signal, {p.name for p in out_dir.glob("*.h5")}, workers


def children(pid: int) -> list[int]:
    """Pids of the live processes whose parent is ``pid`` (read from /proc)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if int(fields[1]) == pid:
                found.append(int(entry.name))
    return found


def alive(pid: int) -> bool:
    """True while ``pid`` runs (a zombie, dead but not yet reaped, is not alive)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_interrupted_batch_stops_its_workers_and_publishes_nothing_after(tmp_path, sig, code):
    clips = make_clips(tmp_path / "data", 6, n_frames=[3] + [25] * 5)  # the first ends long before the second
    out_dir = tmp_path / "tracks"
    returncode, stderr, at_signal, after, workers = _batch_signal_run(clips, out_dir, sig)
    assert returncode == code, stderr
    assert after == at_signal and len(after) < 6  # queued inputs were cancelled, running ones not published
    assert not list(out_dir.glob("*.part")) and not list(out_dir.glob(".*"))
    assert len(workers) >= 2
    deadline = time.monotonic() + 10
    while any(alive(pid) for pid in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [pid for pid in workers if alive(pid)]
    assert "Traceback" not in stderr
    assert stderr.splitlines()[-1] == "Error: interrupted"  # SIGTERM said 'Error: terminated' (README: interrupted)


def test_a_batch_of_two_jobs_shares_the_cores_out(clips, tmp_path):
    cores = len(os.sched_getaffinity(0))
    env = {k: v for k, v in os.environ.items() if k not in ("CONDTRACK_THREADS", "OMP_NUM_THREADS")}
    out_dir = tmp_path / "tracks"
    result = run_cli("track", *clips[:2], "-m", "clf", "--out-dir", str(out_dir), "-j", "2", "-q", env=env)
    assert result.returncode == 0, result.stderr
    half = max(1, cores // 2)
    for record in manifest(out_dir):
        assert record["threads"] == {"opencv": half, "omp": str(half)}, record
    # one input alone uses every core it may run on, here with one core fewer
    run_on = sorted(os.sched_getaffinity(0))[: max(1, cores - 1)]
    result = run_cli("track", clips[0], "-m", "clf", "--out-dir", str(tmp_path / "one"), "-q", env=env,
                     affinity=set(run_on))
    assert result.returncode == 0, result.stderr
    (record,) = manifest(tmp_path / "one")
    assert record["threads"] == {"opencv": len(run_on), "omp": ""}, record
    # the environment default, capped so the jobs do not oversubscribe the cores
    result = run_cli("track", *clips[:2], "-m", "stk", "--out-dir", str(tmp_path / "env"), "-j", "2",
                     env={**env, "CONDTRACK_THREADS": str(cores)})
    assert result.returncode == 0, result.stderr
    for record in manifest(tmp_path / "env"):
        assert record["threads"]["opencv"] == half and record["threads"]["omp"] == str(half)
    assert (f"using {half} thread" in result.stderr) == (cores > half)


def test_dask_run_writes_the_same_bytes_as_the_local_run(clips, tmp_path):
    distributed = pytest.importorskip("distributed")
    local, remote = tmp_path / "local", tmp_path / "dask"
    assert run_cli("track", *clips, "-m", "clf", "--out-dir", str(local), "-j", "2", "-q").returncode == 0
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, protocol="tcp",
                                  dashboard_address=None) as cluster:
        result = run_cli("track", *clips, "-m", "clf", "--out-dir", str(remote), "--scheduler", cluster.scheduler_address)
    assert result.returncode == 0, result.stderr
    assert "[4/4]" in result.stderr
    assert outputs(local) == outputs(remote) and len(outputs(local)) == 4
    assert sorted(r["input"] for r in manifest(remote)) == sorted(clips)


def test_skip_existing_redoes_another_input_with_the_same_output_name(tmp_path):
    """Issue 28.1: the resume check compares the input's identity (path, frames' names, sizes, mtimes), not the name."""
    import h5py

    first, second = make_clips(tmp_path / "a", 1)[0], make_clips(tmp_path / "b", 2)[1]
    out_dir = tmp_path / "tracks"
    args = ["-m", "stk", "--out-dir", str(out_dir), "--skip-existing", "-q"]
    assert run_cli("track", first, *args).returncode == 0
    assert run_cli("track", first, *args).returncode == 0  # the same input: skipped
    assert run_cli("track", second, *args).returncode == 0  # clip001/frames, also written as frames.h5
    assert [(r["input"], r["status"]) for r in manifest(out_dir)] == [
        (first, "ok"), (first, "skipped"), (second, "ok")]
    with h5py.File(out_dir / "frames.h5") as f:
        assert f.attrs["input"] == second
    frame = Path(second) / "00001.png"
    frame.write_bytes((Path(second) / "00002.png").read_bytes())  # a frame changed: its size or mtime differs
    assert run_cli("track", second, *args).returncode == 0
    assert manifest(out_dir)[-1]["status"] == "ok"


def test_batch_only_options_are_refused_where_they_would_be_ignored(clips, tmp_path):
    """Issue 28.9: -j with one input and no --out-dir, and -j with --scheduler, did nothing and said nothing; usage
    errors (28.18)."""
    usage = "Usage: condtrack track [OPTIONS] INPUT...\n"
    result = run_cli("track", clips[0], "-m", "stk", "-j", "2", "-o", str(tmp_path / "out.csv"))
    assert result.returncode == 2 and result.stderr == usage + "Error: --jobs: a batch option (give --out-dir)\n"
    result = run_cli("track", *clips[:2], "-m", "stk", "--out-dir", str(tmp_path / "d"), "-j", "2",
                     "--scheduler", "tcp://127.0.0.1:9")
    assert result.returncode == 2 and result.stderr.startswith(usage + "Error: -j/--jobs: not with --scheduler")
    assert not (tmp_path / "out.csv").exists() and not (tmp_path / "d").exists()


def test_from_list_paths_are_relative_to_the_list_and_names_do_not_depend_on_the_working_directory(tmp_path):
    """Issue 28.21: a list's relative paths are read from the list's folder, so the batch (inputs and output names)
    is the same from any working directory."""
    make_clips(tmp_path / "data", 2)
    listing = tmp_path / "lists" / "clips.txt"
    listing.parent.mkdir()
    listing.write_text("# two clips\n../data/clip000/frames\n\n../data/clip001/frames\n")
    names = []
    for cwd in (tmp_path, tmp_path / "lists"):
        out_dir = tmp_path / f"out_{cwd.name}"
        result = subprocess.run(
            [sys.executable, "-c", "from condtrack_cli.cli import main; main()", "track", "--from-list",
             os.path.relpath(listing, cwd), "-m", "stk", "--out-dir", str(out_dir), "-q"],
            capture_output=True, text=True, timeout=300, cwd=cwd)
        assert result.returncode == 0, result.stderr
        assert [r["status"] for r in manifest(out_dir)] == ["ok", "ok"]
        names.append(sorted(p.name for p in out_dir.glob("*.h5")))
    assert names == [["clip000_frames.h5", "clip001_frames.h5"]] * 2


def test_a_list_s_byte_order_mark_is_skipped_and_a_list_not_utf8_or_with_no_input_is_one_error_line(clips, tmp_path):
    """A list saved with a byte-order mark failed its first input ('\ufeffclip: no such file or folder'), a Latin-1
    list was a UnicodeDecodeError traceback, an empty list said 'no INPUT given (..., or --from-list FILE)'."""
    listing, out_dir = tmp_path / "clips.txt", tmp_path / "out"
    listing.write_text(f"{clips[0]}\n", encoding="utf-8-sig")
    assert run_cli("track", "--from-list", str(listing), "--out-dir", str(out_dir), "-m", "stk", "-q").returncode == 0
    assert [r["status"] for r in manifest(out_dir)] == ["ok"]
    for text, code, message in ((b"clip\xe9\n", 1, "the input list is not UTF-8 text (byte 0xe9 at offset 4)"),
                                (b"# none yet\n\n", 2, "no input listed (only blank lines and # comments)")):
        listing.write_bytes(text)
        result = run_cli("track", "--from-list", str(listing), "--out-dir", str(tmp_path / "other"))
        assert result.returncode == code and result.stderr.splitlines()[-1] == f"Error: {listing}: {message}", result.stderr
        assert "Traceback" not in result.stderr and not (tmp_path / "other").exists()


def test_a_manifest_that_cannot_be_written_is_refused_before_any_work(clips, tmp_path):
    """A manifest.jsonl that is a folder (or a read-only file) ended the batch in an IsADirectoryError traceback after
    its first output was published without a record; now one Error line naming it, before any input is tracked."""
    out_dir = tmp_path / "out"
    (out_dir / MANIFEST).mkdir(parents=True)
    result = run_cli("track", *clips[:2], "--out-dir", str(out_dir), "-m", "stk", "-q")
    assert result.returncode == 1 and result.stderr == f"Error: {out_dir / MANIFEST}: cannot write (Is a directory)\n"
    assert [p.name for p in out_dir.iterdir()] == [MANIFEST]


def test_a_scheduler_that_is_not_one_or_does_not_answer_fails_fast_and_leaves_nothing(clips, tmp_path):
    """Issues 28.11 and 28.16: a scheduler file that is not one was an AssertionError; an unreachable scheduler took
    60 s and left an empty out-dir."""
    pytest.importorskip("distributed")
    not_json, no_address = tmp_path / "notes.txt", tmp_path / "other.json"
    not_json.write_text("hello\n")
    no_address.write_text('{"a": 1}\n')
    out_dir = tmp_path / "out"
    for path in (not_json, no_address):
        result = run_cli("track", *clips[:2], "--out-dir", str(out_dir), "--scheduler-file", str(path))
        assert result.returncode == 1 and result.stderr == (
            f"Error: --scheduler-file {path}: not a Dask scheduler file (a JSON object with the scheduler's 'address')\n")
    started = time.monotonic()
    result = run_cli("track", *clips[:2], "--out-dir", str(out_dir), "--scheduler", "tcp://127.0.0.1:9")
    assert time.monotonic() - started < 45  # the old wait was 60 s; start-up alone took 14 s on a loaded 2-core machine
    assert result.returncode == 1 and result.stderr.startswith("Error: cannot reach the Dask scheduler tcp://127.0.0.1:9")
    assert result.stderr.count("\n") == 1 and not out_dir.exists()


def test_a_dask_batch_stops_promptly_on_sigterm_and_writes_its_manifest(tmp_path):
    """Issue 28.16: the cluster's running tasks went on writing outputs seconds after the batch exited, and the
    inputs that had not ended were not in the manifest."""
    distributed = pytest.importorskip("distributed")
    clips = make_clips(tmp_path / "data", 4, n_frames=[3] + [60] * 3)
    out_dir = tmp_path / "tracks"
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, protocol="tcp",
                                  dashboard_address=":0") as cluster:
        process = subprocess.Popen(
            [sys.executable, "-c", "from condtrack_cli.cli import main; main()", "track", *clips, "-m", "cnlf",
             "--out-dir", str(out_dir), "--scheduler", cluster.scheduler_address],
            preexec_fn=default_sigint, stderr=subprocess.PIPE, text=True)
        for line in process.stderr:  # until the first input is reported done
            if "[1/" in line:
                break
        process.send_signal(signal.SIGTERM)
        signalled = time.monotonic()
        _, stderr = process.communicate(timeout=60)
        assert time.monotonic() - signalled < 5 and process.returncode == 143, stderr
        time.sleep(2.0)  # a task left running would publish its output meanwhile
    assert [p.name for p in out_dir.glob("*.h5")] == ["clip000_frames.h5"]
    assert [(r["input"], r["status"]) for r in manifest(out_dir)] == [
        (clips[0], "ok"), *[(clip, "interrupted") for clip in clips[1:]]]
    assert "Traceback" not in stderr


def test_a_list_from_a_pipe_is_read_from_the_working_directory(tmp_path):
    """--from-list <(ls -d clips/*) read its relative paths from the pipe's folder, /dev/fd: every input
    '/dev/fd/clips/...: no such file or folder'."""
    import threading

    from condtrack_cli.cli.track import _read_list

    pipe = tmp_path / "list"
    os.mkfifo(pipe)
    writer = threading.Thread(target=pipe.write_text, args=("clips/a\n# b\n\n",))
    writer.start()
    assert _read_list(str(pipe)) == ["clips/a"]
    writer.join()
    listing = tmp_path / "list.txt"
    listing.write_text("clips/a\n")
    assert _read_list(str(listing)) == [str(tmp_path / "clips" / "a")]


def test_each_warning_of_a_batch_names_its_input(clips, tmp_path):
    """A batch with one queries file printed 'warning: 1 of 1 queries are untrackable ...' per clip, naming none:
    which clip's query was meant was not said (its Error: lines name their input); each warning now begins with it."""
    queries = tmp_path / "q.csv"
    queries.write_text("frame,x,y\n0,10,10\n")  # flat on clip000 (score 0.6)
    (Path(clips[1]) / "notes.txt").write_text("")  # its reader's warning names it already, as x/f for ./x/f
    typed = [clips[0], f"{clips[1]}/."]
    result = run_cli("track", *typed, "-m", "stk", "-p", str(queries), "--out-dir", str(tmp_path / "o"), "-j", "2")
    (Path(clips[1]) / "notes.txt").unlink()
    assert result.returncode == 0, result.stderr
    warned = [line for line in result.stderr.splitlines() if line.startswith("warning:")]
    assert f"warning: {clips[1]}: skipping 1 non-image file(s), e.g. 'notes.txt'" in warned
    assert f"warning: {clips[0]}: 1 of 1 queries are untrackable" in result.stderr
    assert all(line.startswith((f"warning: {clips[0]}: ", f"warning: {typed[1]}: ", f"warning: {clips[1]}: skipping"))
               for line in warned)


def test_a_failed_input_typed_otherwise_than_its_reader_names_it_is_named_once(clips, tmp_path):
    """-q's Error: line for ./nothere was 'Error: ./nothere: nothere: no such file or folder'."""
    typed = f"{tmp_path}/nothere/."
    result = run_cli("track", typed, clips[0], "-m", "stk", "--out-dir", str(tmp_path / "o"), "-q")
    assert result.returncode == 1
    assert result.stderr.splitlines()[0] == f"Error: {tmp_path}/nothere: no such file or folder"


def test_more_threads_than_cores_are_capped_with_a_warning(clips, tmp_path):
    """Issue 28.14: --threads 100000 (or CONDTRACK_THREADS) was taken as asked, a thread storm."""
    result = run_cli("track", clips[0], "-m", "stk", "--threads", "100000", "-o", str(tmp_path / "o.csv"), affinity={0})
    assert result.returncode == 0 and "warning: 100000 threads exceeds the 1 core: using 1 thread\n" in result.stderr
    result = run_cli("track", clips[0], "-m", "stk", "--out-dir", str(tmp_path / "d"), affinity={0},
                     env={**{k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}, "CONDTRACK_THREADS": "100000"})
    assert result.returncode == 0 and "warning: 100000 threads exceeds the 1 core: using 1 thread\n" in result.stderr
    assert manifest(tmp_path / "d")[0]["threads"] == {"opencv": 1, "omp": ""}


def test_a_threads_variable_of_a_non_decimal_digit_is_refused_naming_it(monkeypatch):
    """CONDTRACK_THREADS="²" passed str.isdigit and failed int(): "Error: invalid literal for int()", not naming it."""
    from condtrack_cli.threads import threads_from_environment
    monkeypatch.setenv("CONDTRACK_THREADS", "\u00b2")
    with pytest.raises(ValueError, match="CONDTRACK_THREADS='\u00b2': expected a positive integer"):
        threads_from_environment()


def test_a_batch_output_that_is_the_queries_file_is_refused_before_work(clips, tmp_path):
    """Issue 28.5's batch side: an input named 'queries' wrote OUT_DIR/queries.csv over the -p file."""
    import shutil

    clip = tmp_path / "queries"
    shutil.copytree(clips[0], clip)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    queries = out_dir / "queries.csv"
    queries.write_text("frame,x,y\n0,40,30\n")
    result = run_cli("track", str(clip), clips[1], "-p", str(queries), "-m", "stk", "--out-dir", str(out_dir),
                     "--format", "csv")
    assert result.returncode == 1 and result.stderr == (
        f"Error: the output of '{clip}', {queries}: the same file as the input -p {queries}; "
        "writing it would destroy the input\n")
    assert queries.read_text() == "frame,x,y\n0,40,30\n" and [p.name for p in out_dir.iterdir()] == ["queries.csv"]


def _sleep_through_sigterm() -> None:
    """A stand-in for a pool worker that does not exit on SIGTERM."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    time.sleep(60)


def test_a_pool_whose_shutdown_hangs_has_its_workers_killed(monkeypatch):
    """The fall-back of an interrupted batch (stop_pool): when the pool's terminate does not return, the workers
    still alive after STOP_WAIT are killed, so the batch exits instead of waiting for ever."""
    import multiprocessing
    import threading

    from condtrack_cli.batch import local

    worker = multiprocessing.get_context("spawn").Process(target=_sleep_through_sigterm, daemon=True)
    worker.start()
    stuck = threading.Event()

    class HangingPool:
        def terminate(self):
            stuck.wait()

    monkeypatch.setattr(local, "STOP_WAIT", 0.5)
    started = time.monotonic()
    local.stop_pool(HangingPool())
    worker.join(5)
    assert worker.exitcode == -signal.SIGKILL and time.monotonic() - started < 5
    stuck.set()


def _batch_modules() -> dict[str, set[str]]:
    """Each module of condtrack_cli.batch -> the modules of the package it imports (TYPE_CHECKING imports included)."""
    import ast

    import condtrack_cli.batch

    package = Path(condtrack_cli.batch.__file__).parent
    graph = {}
    for path in package.glob("*.py"):
        if path.stem == "__init__":
            continue
        imported = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("condtrack_cli.batch."):
                imported.add(node.module.rsplit(".", 1)[1])
            elif isinstance(node, ast.Import):
                imported |= {a.name.rsplit(".", 1)[1] for a in node.names if a.name.startswith("condtrack_cli.batch.")}
        graph[path.stem] = imported
    return graph


def test_the_batch_modules_import_each_other_in_one_direction():
    """Issue 47.23: job and manifest imported each other. The package's import graph has no cycle, and the manifest
    (what a record is, how it is read and written) needs none of the other modules."""
    graph = _batch_modules()
    assert graph["manifest"] == set() and {"job", "manifest", "plan", "local", "dask", "report", "status"} <= set(graph)
    done: set[str] = set()

    def visit(module: str, path: tuple[str, ...]) -> None:
        assert module not in path, f"import cycle: {' -> '.join([*path, module])}"
        if module not in done:
            for imported in graph[module]:
                visit(imported, (*path, module))
            done.add(module)

    for module in graph:
        visit(module, ())


@pytest.fixture
def sigterm_restored():
    """main() installs its own SIGTERM handler in this process: put the previous one back after the test."""
    previous = signal.getsignal(signal.SIGTERM)
    yield
    signal.signal(signal.SIGTERM, previous)


@pytest.mark.parametrize("moment", ["condtrack_cli.batch.job.track_input", "condtrack_cli.batch.publish"])
def test_sigterm_between_an_output_and_its_record_leaves_them_agreeing(clips, tmp_path, monkeypatch, sigterm_restored,
                                                                       moment):
    """Issue 47.4: a SIGTERM just after a job published its output (before the batch wrote its record) left the output
    in place and 'interrupted' in the manifest. The signal is raised here at that moment: right after the output is
    written, and right after the batch moves it in place; either way an output is there if and only if its input's
    manifest record says ok."""
    from condtrack_cli.cli import main

    target, name = moment.rsplit(".", 1)
    real = getattr(__import__(target, fromlist=[name]), name)

    def then_sigterm(*args, **kwargs):
        result = real(*args, **kwargs)
        signal.raise_signal(signal.SIGTERM)
        return result

    monkeypatch.setattr(moment, then_sigterm)
    out_dir = tmp_path / "tracks"
    monkeypatch.setattr(sys, "argv", ["condtrack", "track", *clips[:2], "-m", "stk", "--out-dir", str(out_dir), "-q"])
    with pytest.raises(SystemExit) as stop:
        main()
    assert stop.value.code == 143
    records = manifest(out_dir)
    assert [r["input"] for r in records] == clips[:2]
    assert {Path(r["output"]).name for r in records if r["status"] == "ok"} == set(outputs(out_dir))
    assert [r["status"] for r in records] == (["interrupted"] * 2 if moment.endswith("track_input")
                                              else ["ok", "interrupted"])
    assert sorted(p.name for p in out_dir.iterdir()) == sorted([MANIFEST, *outputs(out_dir)])  # no staging left


def test_a_batch_output_that_is_an_existing_folder_is_refused_before_work(clips, tmp_path):
    """OUT_DIR/clip000_frames.h5 being a folder was found only once that input was tracked: its record said 'failed:
    ... cannot put the output in place (Is a directory)'; now one Error line before any input is tracked."""
    out_dir = tmp_path / "out"
    (out_dir / "clip000_frames.h5").mkdir(parents=True)
    result = run_cli("track", *clips[:2], "--out-dir", str(out_dir), "-m", "stk", "-q")
    assert result.returncode == 1 and result.stderr == (
        f"Error: the output of '{clips[0]}', {out_dir / 'clip000_frames.h5'}: a folder, which an output file cannot "
        "replace\n")
    assert [p.name for p in out_dir.iterdir()] == ["clip000_frames.h5"]


@pytest.mark.parametrize("key, value", [("seed", "x"), ("n_frames", "abc"), ("seed", np.array([1, 2]))])
def test_skip_existing_redoes_an_output_whose_attributes_cannot_be_read(tmp_path, key, value):
    """--skip-existing over an output whose seed or n_frames attribute was no number (a hand-edited file, another
    tool's) ended the batch in int()'s ValueError or TypeError traceback before any work; such an output is now one
    it cannot trust, redone like a file that is no HDF5."""
    import h5py

    output = tmp_path / "c1.h5"
    with h5py.File(output, "w") as f:
        f.attrs.update({"config_hash": "0" * 64, "condtrack_version": "0.1.0", "seed": 0, "n_frames": 5})
        f["tracks/point_id"] = np.arange(3)
    assert _stored_run(output, [])["seed"] == 0
    with h5py.File(output, "r+") as f:
        f.attrs[key] = value
    assert _stored_run(output, []) is None


def test_a_failed_write_names_the_output_not_the_staging_folder(clips, tmp_path, monkeypatch, sigterm_restored):
    """A job writes into the batch's hidden staging folder; a write that failed (a full disk) was recorded, shown and
    kept in the manifest as ``OUT/.outputs-<host>-<pid>-*.part/frames.h5: no space left on device``, a folder
    gone once the batch ends. The error names the output, OUT/frames.h5."""
    import errno

    from condtrack_cli.cli import main

    def full_disk(*_args, **_kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("condtrack_cli.io.write.write_hdf5", full_disk)
    out_dir = tmp_path / "tracks"
    monkeypatch.setattr(sys, "argv", ["condtrack", "track", clips[0], "-m", "stk", "--out-dir", str(out_dir), "-q"])
    with pytest.raises(SystemExit) as stop:
        main()
    assert stop.value.code == 1
    assert [record["error"] for record in manifest(out_dir)] == [
        f"{out_dir / 'frames.h5'}: no space left on device"]
    assert [p.name for p in out_dir.iterdir()] == [MANIFEST]
