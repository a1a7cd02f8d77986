"""Bad input through the real command line: one ``Error:`` line naming the problem, non-zero exit, no file."""

from __future__ import annotations

import hashlib
import os
import signal
import subprocess
import sys

import cv2
import h5py
import numpy as np
import pytest

from click.testing import CliRunner

from condtrack_cli.cli import cli
from condtrack_cli.errors import CondtrackError
from conftest import FORCED_TERMINAL, SAMPLES, default_sigint
from test_cli import run_cli

SAMPLE = SAMPLES / "occlusion"


def _assert_clean_failure(result, message: str, folder) -> None:
    assert result.returncode not in (0, None)
    lines = result.stderr.strip().splitlines()
    errors = [line for line in lines if line.startswith("Error: ")]
    assert errors == [lines[-1]], result.stderr  # progress or warning lines may come before it
    assert message in errors[0], result.stderr
    assert "Traceback" not in result.stderr
    assert not [p for p in folder.iterdir() if p.name.startswith(("out", ".out"))]


def _frames_folder(tmp_path, sizes=((48, 64),) * 4):
    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for k, shape in enumerate(sizes):
        cv2.imwrite(str(folder / f"{k:03d}.png"), rng.integers(0, 256, shape, dtype=np.uint8))
    return folder


def test_input_failures(tmp_path):
    out = tmp_path / "out.h5"
    _assert_clean_failure(run_cli("track", str(tmp_path / "nowhere"), "-o", str(out)), "no such file or folder", tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    _assert_clean_failure(run_cli("track", str(empty), "-o", str(out)), "no image files", tmp_path)
    mixed = _frames_folder(tmp_path, ((48, 64), (48, 64), (40, 64)))
    _assert_clean_failure(run_cli("track", str(mixed), "-o", str(out)), "frame 2 (", tmp_path)
    (mixed / "002.png").write_bytes((mixed / "001.png").read_bytes()[:60])  # truncated PNG
    _assert_clean_failure(run_cli("track", str(mixed), "-o", str(out)), "frame 2 (", tmp_path)
    jpegs = tmp_path / "jpegs"
    jpegs.mkdir()
    for k, frame in enumerate(sorted(mixed.iterdir())[:2]):
        cv2.imwrite(str(jpegs / f"{k:03d}.jpg"), cv2.imread(str(frame), cv2.IMREAD_GRAYSCALE)[:, :48])
    full = (jpegs / "001.jpg").read_bytes()
    (jpegs / "001.jpg").write_bytes(full[: len(full) // 2])  # cut short: libjpeg would decode it, half grey
    result = run_cli("track", str(jpegs), "-o", str(out))
    _assert_clean_failure(result, "frame 1 (", tmp_path)
    assert "the JPEG file is cut short" in result.stderr and len(result.stderr.strip().splitlines()) == 1
    video = tmp_path / "clip.avi"
    video.write_bytes(b"RIFF....AVI garbage")
    _assert_clean_failure(run_cli("track", str(video), "-o", str(out)), "clip.avi: not a readable video", tmp_path)


@pytest.mark.parametrize(
    "yaml_text, extra, message",
    [
        ("motion: {levels: [\n", [], "not valid YAML"),
        # a second YAML document: PyYAML's words say what is wrong, not only where
        ("measure: {template: 11}\n---\nmotion: {levels: 3}\n", [],
         "not valid YAML at line 2: expected a single document in the stream, but found another document"),
        ("motion: {levelz: 3}\n", [], "'motion.levelz': unknown key"),
        ("filter: {stk: {win_size: big}}\n", [], "'filter.stk.win_size'"),
        ("filter: {stk: {fb_threshold: -1}}\n", [], "'filter.stk.fb_threshold'"),
        ("", ["--set", "filter.stk.levels=0"], "'filter.stk.levels'"),
        ("", ["-m", "stk", "--set", "filter.stk.win_size=500"], "does not fit in the 320x240 frame"),
        # issue 28.6: PyYAML keeps the last of two equal keys silently
        ("motion:\n  levels: 3\n  levels: 2\n", [], "c.yaml', line 3: key 'levels' given twice"),
        ("filter: {stk: {win_size: 31, win_size: 15}}\n", [], "line 1: key 'win_size' given twice"),
        ("", ["--set", "motion={levels: 3, levels: 2}"], "key 'levels' given twice"),
        # issue 28.8: a non-finite number is no setting
        ("measure: {gamma: .inf}\n", ["-m", "stk"], "'measure.gamma': Input should be a finite number (got inf)"),
        ("", ["-m", "stk", "--set", "filter.stk.epsilon=.nan"], "'filter.stk.epsilon': Input should be a finite number"),
    ],
)
def test_config_failures(tmp_path, yaml_text, extra, message):
    config = tmp_path / "c.yaml"
    config.write_text(yaml_text)
    result = run_cli("track", str(SAMPLE), "-c", str(config), *extra, "-o", str(tmp_path / "out.csv"))
    _assert_clean_failure(result, message, tmp_path)


def test_output_folder_failures(tmp_path, monkeypatch):
    result = run_cli("track", str(SAMPLE), "-o", str(tmp_path / "missing" / "out.csv"))
    _assert_clean_failure(result, "does not exist", tmp_path)
    (tmp_path / "a.h5").write_bytes(b"")  # a file named as the output's folder
    result = run_cli("track", str(SAMPLE), "-o", str(tmp_path / "a.h5" / "out.csv"))
    _assert_clean_failure(result, f"the output folder '{tmp_path / 'a.h5'}' is not a folder", tmp_path)
    (tmp_path / "a.h5").unlink()
    # Tests run as root, who may write anywhere: simulate a read-only folder in process.
    import condtrack_cli.run

    monkeypatch.setattr(condtrack_cli.run.os, "access", lambda path, mode: False)
    result = CliRunner().invoke(cli, ["track", str(SAMPLE), "-o", str(tmp_path / "out.csv"), "-q"])
    assert result.exit_code != 0 and "is not writable" in str(result.exception)
    assert not list(tmp_path.iterdir())


def test_interrupt_exits_130_and_leaves_nothing(tmp_path):
    out = tmp_path / "out.h5"
    process = subprocess.Popen(
        [sys.executable, "-c", "from condtrack_cli.cli import main; main()", "track", str(SAMPLE), "-o", str(out)],
        preexec_fn=default_sigint, stderr=subprocess.PIPE, text=True, env={**os.environ, **FORCED_TERMINAL},
    )
    process.stderr.read(1)  # the progress bar's first drawing: tracking has started
    process.send_signal(signal.SIGINT)
    _, stderr = process.communicate(timeout=120)
    if process.returncode == 0:
        pytest.skip("the run finished before the interrupt arrived")
    assert process.returncode == 130 and "Error: interrupted" in stderr
    assert list(tmp_path.iterdir()) == []


def test_batch_with_one_broken_input(tmp_path):
    good = _frames_folder(tmp_path)
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "0.png").write_bytes(b"not a png")
    listing = tmp_path / "inputs.txt"
    listing.write_text(f"{broken}\n{SAMPLE}\n")
    out_dir = tmp_path / "outs"
    out_dir.mkdir()
    result = run_cli("track", str(good), "--from-list", str(listing), "--out-dir", str(out_dir), "-j", "2", "-q")
    assert result.returncode == 1
    assert sorted(p.name for p in out_dir.glob("*.h5")) == ["frames.h5", "occlusion.h5"]
    assert result.stderr.splitlines() == [line for line in result.stderr.splitlines() if line.startswith("Error: ")]
    assert f"Error: {broken}: " in result.stderr and "not a readable image" in result.stderr


def test_same_seed_same_bytes(tmp_path):
    outputs = []
    for run in range(2):
        csv, h5 = tmp_path / f"run{run}.csv", tmp_path / f"run{run}.h5"
        for path in (csv, h5):
            args = ("track", str(SAMPLE), "-p", str(SAMPLE / "queries.csv"), "--seed", "5", "-o", str(path), "-q")
            assert run_cli(*args).returncode == 0
        outputs.append((csv, h5))
    (csv_a, h5_a), (csv_b, h5_b) = outputs
    assert hashlib.sha256(csv_a.read_bytes()).digest() == hashlib.sha256(csv_b.read_bytes()).digest()
    with h5py.File(h5_a) as a, h5py.File(h5_b) as b:
        names = []
        a.visit(names.append)
        for name in names:
            if isinstance(a[name], h5py.Dataset):
                left, right = a[name][()], b[name][()]
                same = left.tolist() == right.tolist() if left.dtype == object else left.tobytes() == right.tobytes()
                assert same, name
        assert dict(a.attrs) == dict(b.attrs)


def _one_error_line(result, code: int, message: str) -> None:
    """Exit ``code``, stderr exactly one ``Error:`` line holding ``message`` (after warnings and, for a usage error,
    Click's usage line), no traceback."""
    assert result.returncode == code, result.stderr
    lines = [line for line in result.stderr.strip().splitlines() if not line.startswith(("warning: ", "Usage: "))]
    assert len(lines) == 1 and lines[0].startswith("Error: ") and message in lines[0], result.stderr


def test_negative_seed_is_a_usage_error(tmp_path):
    _one_error_line(run_cli("track", str(SAMPLE), "--seed", "-1", "-o", str(tmp_path / "out.csv")), 2, "--seed")
    _one_error_line(run_cli("synth", str(tmp_path / "s"), "--scene", "ring", "--seed", "-1"), 2, "--seed")
    assert not list(tmp_path.iterdir())


def test_synth_into_a_folder_that_cannot_be_written(tmp_path):
    (tmp_path / "afile").write_text("a file, not a folder")
    _one_error_line(run_cli("synth", str(tmp_path / "afile" / "scene"), "--scene", "ring", "--frames", "2",
                            "--size", "64x64"), 1, "afile")
    assert [p.name for p in tmp_path.iterdir()] == ["afile"]


def test_synth_samples_refuse_a_foreign_file_before_writing_any_sample(tmp_path):
    """``--samples --force`` with a file of the user's in the last sample folder: a traceback after the first
    folders were rewritten. Now the single-scene message, exit 1, and every file keeps its bytes and mtime."""
    from condtrack_cli.frames.synthetic import write_samples

    root = tmp_path / "samples"
    write_samples(root)
    (root / "ring" / "mine.txt").write_text("mine")
    before = {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in root.rglob("*") if p.is_file()}
    message = f"{root / 'ring'}: holds 'mine.txt', not a synthetic scene folder; not overwriting"
    _one_error_line(run_cli("synth", str(root), "--samples", "--force"), 1, message)
    assert {p: (p.read_bytes(), p.stat().st_mtime_ns) for p in root.rglob("*") if p.is_file()} == before
    assert sorted(p.name for p in root.iterdir()) == sorted(["camera_motion", "occlusion", "ring"])
    _one_error_line(run_cli("synth", str(root / "ring"), "--scene", "ring", "--force", "--frames", "2",
                            "--size", "64x64"), 1, message)



@pytest.mark.parametrize("size", [(1, 1), (2, 2), (2, 40)])
@pytest.mark.parametrize("method", ["stk", "clf"])
def test_a_frame_smaller_than_every_window_is_refused_as_too_small(tmp_path, size, method):
    """Issue 28.11: a 1x1 frame was blamed on detect.block (or motion.local_window), which no value could fix."""
    folder = _frames_folder(tmp_path, (size,) * 3)
    queries = tmp_path / "q.csv"
    queries.write_text("frame,x,y\n0,0,0\n")
    for extra in ([], ["-p", str(queries)]):
        result = run_cli("track", str(folder), *extra, "-m", method, "-o", str(tmp_path / "out.csv"))
        _one_error_line(result, 1, f"{folder}: the {size[1]}x{size[0]} frame is too small for tracking (at least 3x3 px)")
        assert "config key" not in result.stderr
    (tmp_path / "five").mkdir()
    result = run_cli("track", str(_frames_folder(tmp_path / "five", ((5, 5),) * 3)), "-m", method)
    if method == "clf":  # no window would make OpenCV's DIS run on it: the frame is named, not a key
        _one_error_line(result, 1, "the 5x5 frame is too small for motion 'dis' (at least 12 px on one side)")
        return
    _one_error_line(result, 1, "config key 'detect.block': a window of 7 px does not fit in the 5x5 frame (at most 5)")
    # every window that does not fit is named in that one line, not one per run; STK reads no motion or measure stage
    assert "; nor do filter.stk.win_size (21 px)" in result.stderr and "motion." not in result.stderr


def test_a_window_of_a_filter_the_method_does_not_use_does_not_refuse_the_frame(tmp_path):
    """An 18 x 18 frame: STK's 21 px window does not fit it, but ``clf`` does not use STK (it did refuse it, naming
    filter.stk.win_size); ``-m stk`` still refuses it, naming the key."""
    folder = _frames_folder(tmp_path, ((18, 18),) * 3)
    queries = tmp_path / "q.csv"
    queries.write_text("frame,x,y\n0,9,9\n")
    out = tmp_path / "out.csv"
    result = run_cli("track", str(folder), "-p", str(queries), "-m", "clf", "-o", str(out))
    assert result.returncode == 0, result.stderr
    assert out.exists()
    result = run_cli("track", str(folder), "-p", str(queries), "-m", "stk", "-o", str(tmp_path / "stk.csv"))
    _one_error_line(result, 1, "config key 'filter.stk.win_size': a window of 21 px does not fit in the 18x18 frame")


def test_stk_tracks_a_frame_too_small_for_the_motion_and_measure_windows_it_does_not_use(tmp_path):
    """An 8 x 8 frame with ``filter.stk.win_size=5``: ``-m stk`` was refused for motion.local_window (9 px) and
    measure.template (11 px), windows of stages STK never runs; it now tracks (STK's settings' ``stage_kinds``)."""
    rng = np.random.default_rng(0)
    scene = cv2.GaussianBlur((rng.random((16, 16)) * 255).astype(np.uint8), (3, 3), 0)
    folder = tmp_path / "tiny"
    folder.mkdir()
    for k in range(3):
        cv2.imwrite(str(folder / f"{k:03d}.png"), scene[k : k + 8, k : k + 8])  # the view moves 1 px a frame
    queries = tmp_path / "q.csv"
    queries.write_text("frame,x,y\n0,4,4\n")
    out = tmp_path / "out.csv"
    result = run_cli("track", str(folder), "-p", str(queries), "-m", "stk", "--set", "filter.stk.win_size=5",
                     "-o", str(out))
    assert result.returncode == 0, result.stderr
    rows = np.loadtxt(out, delimiter=",", skiprows=1, usecols=(2, 3))
    np.testing.assert_allclose(rows[-1], [2.0, 2.0], atol=0.5)  # the scene point at (4, 4) of frame 0, 2 px up-left
    result = run_cli("track", str(folder), "-p", str(queries), "-m", "clf", "-o", str(tmp_path / "clf.csv"))
    _one_error_line(result, 1, "the 8x8 frame is too small for motion 'dis' (at least 12 px on one side)")


@pytest.mark.parametrize("side, select", [(10, False), (11, False), (23, True)])
def test_a_frame_too_small_for_opencvs_dis_is_refused_in_one_line(tmp_path, side, select):
    """With windows small enough to fit, a 10 x 10 frame reached cv2.DISOpticalFlow, which ended the run in OpenCV's
    traceback ('The input image must have either width or height >= 12'); ``select``'s raw field does so under 24 px
    (it runs on half-size frames). Such a frame is now refused naming the stage; ``-m stk`` runs no DIS and tracks."""
    folder = _frames_folder(tmp_path, ((side, side),) * 3)
    queries = tmp_path / "q.csv"
    queries.write_text(f"frame,x,y\n0,{side // 2},{side // 2}\n")
    small = ["--set", "motion.local_window=3", "--set", "motion.misfit_window=3", "--set", "measure.template=3"]
    if select:
        small += ["--set", "motion.mean_normalization=select"]
    out = tmp_path / "out.h5"
    result = run_cli("track", str(folder), "-p", str(queries), "-m", "clf", *small, "-o", str(out))
    least = 24 if select else 12
    _one_error_line(result, 1, f"the {side}x{side} frame is too small for motion 'dis' (at least {least} px on one side)")
    assert not out.exists()
    result = run_cli("track", str(folder), "-p", str(queries), "-m", "stk", "--set", "filter.stk.win_size=3", "-o", str(out))
    assert result.returncode == 0, result.stderr


@pytest.mark.parametrize("option, value", [("--atol-px", "nan"), ("--atol-px", "inf"), ("--rtol-cov", "inf"),
                                           ("--rtol-cov", "nan")])
def test_compare_refuses_tolerances_that_are_not_finite(tmp_path, option, value):
    tracks = SAMPLE / "tracks.csv"
    _one_error_line(run_cli("compare", str(tracks), str(tracks), option, value), 2, option)


def test_quiet_batch_prints_nothing(tmp_path):
    good = _frames_folder(tmp_path)
    out_dir = tmp_path / "outs"
    out_dir.mkdir()
    result = run_cli("track", str(good), str(SAMPLE), "--out-dir", str(out_dir), "-m", "stk", "-q")
    assert result.returncode == 0 and result.stderr == "" and result.stdout == ""


@pytest.mark.parametrize("args", [
    ["track", "{missing}"],
    ["track", str(SAMPLE), "-p", "{missing}"],
    ["track", str(SAMPLE), "-c", "{missing}"],
    ["track", "--from-list", "{missing}", "--out-dir", "{tmp}"],
    ["eval", "{missing}", str(SAMPLE / "tracks.csv")],
    ["eval", str(SAMPLE / "tracks.csv"), "{missing}"],
    ["info", "{missing}"],
    ["render", "{missing}", str(SAMPLE), "-o", "{tmp}/o.mp4"],
    ["compare", "{missing}", str(SAMPLE / "tracks.csv")],
])
def test_a_missing_input_file_exits_2_in_every_command(tmp_path, args):
    """One convention (README, "Exit codes"): 2 for a wrong command line, a missing input included; 1 for a failed run."""
    missing = tmp_path / "missing.file"
    args = [a.format(missing=missing, tmp=tmp_path) for a in args]
    _one_error_line(run_cli(*args), 2, "missing.file")
    assert not list(tmp_path.iterdir())


def test_a_set_on_a_filter_the_method_does_not_use_is_warned(tmp_path):
    """Issue 28.7: --set filter.stk.* under -m auto changes nothing; say so and name the method that would use it."""
    out = tmp_path / "out.csv"
    result = run_cli("track", str(SAMPLE), "-m", "mdr", "--set", "filter.stk.win_size=31", "--set", "filter.cnlf.particles=50",
                     "--set", "filter.mdr.initial_std=1", "-o", str(out))
    assert result.returncode == 0, result.stderr
    warnings = [line for line in result.stderr.splitlines() if "has no effect" in line]
    assert warnings == [
        "warning: --set filter.stk.win_size=31 has no effect: method 'mdr' does not use filter.stk (-m stk would)",
        "warning: --set filter.cnlf.particles=50 has no effect: method 'mdr' does not use filter.cnlf "
        "(-m auto or -m cnlf would)",
    ]
    result = run_cli("track", str(SAMPLE), "-m", "stk", "--set", "filter.stk.win_size=31", "-o", str(out))
    assert result.returncode == 0 and "has no effect" not in result.stderr
    # STK runs neither the motion nor the measurement stage: their keys change nothing either
    result = run_cli("track", str(SAMPLE), "-m", "stk", "--set", "measure.template=7", "--set", "motion.name=robust",
                     "--set", "detect.block=5", "-o", str(out))
    assert result.returncode == 0, result.stderr
    assert [line for line in result.stderr.splitlines() if "has no effect" in line] == [
        "warning: --set measure.template=7 has no effect: method 'stk' runs no measure stage",
        "warning: --set motion.name=robust has no effect: method 'stk' runs no motion stage",
    ]


def test_a_stored_dataset_the_run_cannot_write_is_warned(tmp_path):
    """output.store_particles under clf (no particles), output.store_segmentation under cnlf (only auto segments) and
    either into a CSV (no room for them) did nothing without a word (probe round 15); each now says so."""
    def effects(method, out):
        result = run_cli("track", str(SAMPLE), "-m", method, "--set", "output.store_particles=true",
                         "--set", "output.store_segmentation=true", "-o", str(tmp_path / out))
        assert result.returncode == 0, result.stderr
        return [line for line in result.stderr.splitlines() if "has no effect" in line]

    assert effects("clf", "clf.h5") == [
        "warning: output.store_particles has no effect: method 'clf' writes no particles (-m auto or -m cnlf would)",
        "warning: output.store_segmentation has no effect: method 'clf' writes no segmentation (-m auto would)",
    ]
    assert effects("cnlf", "cnlf.csv") == [
        "warning: output.store_segmentation has no effect: method 'cnlf' writes no segmentation (-m auto would)",
        "warning: output.store_particles has no effect: a CSV holds no particles (write an .h5 file for them)",
    ]
    assert effects("auto", "auto.h5") == []


def test_a_stored_dataset_into_csv_is_warned_once_on_stdout_and_in_a_batch(tmp_path):
    """CSV on stdout wrote no particles without a word, and a --format csv batch repeated the warning for each input
    (the same for all: the config's); now each run says it once, as it reads the config."""
    particles = ["--set", "output.store_particles=true", "-m", "cnlf"]
    warning = "warning: output.store_particles has no effect: a CSV holds no particles (write an .h5 file for them)"
    batch = [str(SAMPLE), str(SAMPLES / "ring"), "--format", "csv", "--out-dir", str(tmp_path / "out"), "-j", "2"]
    for args in ([str(SAMPLE)], batch):
        result = run_cli("track", *args, *particles, "--set", "detect.max_points=4")
        assert result.returncode == 0, result.stderr
        assert [line for line in result.stderr.splitlines() if "has no effect" in line] == [warning]


def test_messages_show_values_plainly_and_name_an_input_once(tmp_path):
    """Issue 28.20: no ``np.str_('abc')`` in a message, and a quiet batch does not print "Error: empty: empty: ..."."""
    tracks = tmp_path / "t.csv"
    tracks.write_text("point_id,frame,x,y,cov_xx,cov_xy,cov_yy,visible,method\n0,0,1.0,2.0,1,0,1,1,abc\n")
    result = run_cli("info", str(tracks))
    assert result.returncode == 1 and result.stderr == (
        f"Error: {tracks}: unknown method 'abc'; valid: stk, mdr, clf, cnlf\n")
    h5 = tmp_path / "t.h5"
    with h5py.File(h5, "w") as f:
        f.attrs["schema_version"] = np.int64(3)
    result = run_cli("info", str(h5))
    assert result.stderr == f"Error: {h5}: schema_version 3 is not supported (this condtrack reads '1.0' and '2.0')\n"
    empty = tmp_path / "empty"
    empty.write_bytes(b"")
    result = run_cli("track", str(empty), str(SAMPLE), "-m", "stk", "--out-dir", str(tmp_path / "out"), "-q")
    errors = [line for line in result.stderr.splitlines() if line.startswith("Error: ")]
    assert result.returncode == 1 and errors[0] == f"Error: {empty}: not a readable video (OpenCV could not open it)"
    from condtrack_cli.config import load_config
    from condtrack_cli.errors import CondtrackError

    with pytest.raises(CondtrackError, match=r"^config key 'measure.gamma': Input should be greater than 0 \(got -1.0\)$"):
        load_config({"measure": {"gamma": np.float64(-1)}})
    tracks.write_text("point_id,frame,x,y,cov_xx,cov_xy,cov_yy,visible,method\n0,0,1.0,2.0,1,0,1,1,stk\n0,1,abc,2,1,0,1,1,stk\n")
    result = run_cli("info", str(tracks))
    assert result.stderr == f"Error: {tracks}: line 3, column 'x': 'abc' is not a number\n"


@pytest.mark.parametrize("args, message", [
    (["track"], "no INPUT given"),
    (["track", "{clip}", "{clip2}", "--out-dir", "{tmp}/d", "--shard", "3/2"], "Invalid value for '--shard'"),
    (["track", "{clip}", "{clip2}", "--out-dir", "{tmp}/d", "--shard", "0/0"], "Invalid value for '--shard'"),
    (["track", "{clip}", "{clip2}", "--out-dir", "{tmp}/d", "--shard", "abc"], "Invalid value for '--shard'"),
    (["track", "{clip}", "-m", "foo"], "Invalid value for '-m' / '--method': 'foo' is not one of"),
    (["track", "{clip}", "--skip-existing"], "--skip-existing: a batch option (give --out-dir)"),
    (["track", "{clip}", "--shard", "0/2"], "--shard: a batch option (give --out-dir)"),
    (["track", "{clip}", "-o", "{tmp}/o.h5", "--format", "csv"], "--format: a batch option (give --out-dir)"),
    (["track", "{clip}", "{clip2}"], "several inputs need --out-dir"),
    (["track", "{clip}", "{clip2}", "-o", "{tmp}/o.csv"], "-o and --overlay take one input"),
    (["track", "{clip}", "--out-dir", "{tmp}/d", "-o", "{tmp}/o.csv"], "-o and --overlay take one input"),
    (["synth", "{tmp}/s", "--scene", "ring", "--size", "abc"], "Invalid value for '--size': expected WIDTHxHEIGHT"),
    (["synth", "{tmp}/s", "--scene", "nosuch"], "Invalid value for '--scene': unknown scene 'nosuch'"),
    (["synth", "{tmp}/s", "--scene", "ring", "--size", "100000x100000"], "too large (at most 4096 px each way)"),
    (["synth", "{tmp}/s", "--scene", "ring", "--samples"], "--scene: a single-scene option (not with --samples)"),
    (["synth", "{tmp}/s", "--samples", "--force", "--size", "64x64", "--seed", "0", "--frames", "3", "--noise", "9"],
     "--seed, --size, --frames, --noise: a single-scene option (not with --samples)"),
])
def test_command_line_mistakes_are_usage_errors(tmp_path, args, message):
    """Issue 28.18 (and the synth size bound of 28.11): exit 2 after Click's usage line, the filter.method key unnamed
    (the user typed -m), nothing created."""
    args = [a.format(clip=SAMPLE, clip2=SAMPLES / "ring", tmp=tmp_path) for a in args]
    result = run_cli(*args)
    _one_error_line(result, 2, message)
    assert result.stderr.startswith(f"Usage: condtrack {args[0]} [OPTIONS]") and "filter.method" not in result.stderr
    assert not list(tmp_path.iterdir())


def test_a_config_not_in_utf8_and_a_seed_beyond_64_bits_are_refused_before_work(tmp_path):
    """Issue 28.11: a Latin-1 config was a UnicodeDecodeError traceback; --seed 2^64 failed only after the whole run,
    when the HDF5 attribute was written."""
    config = tmp_path / "c.yaml"
    config.write_bytes("# réglages\nmotion: {levels: 3}\n".encode("latin-1"))
    result = run_cli("track", str(SAMPLE), "-c", str(config), "-o", str(tmp_path / "out.h5"))
    _one_error_line(result, 1, f"config file '{config}' is not UTF-8 text (byte 0xe9 at offset 3)")
    config.unlink()
    result = run_cli("track", str(SAMPLE), "-m", "stk", "--seed", str(2**64), "-o", str(tmp_path / "out.h5"))
    _one_error_line(result, 2, f"Invalid value for '--seed': {2**64} is not in the range 0<=x<=9223372036854775807")
    assert "frame" not in result.stderr  # refused before tracking: no progress line
    assert not list(tmp_path.iterdir())
    result = run_cli("track", str(SAMPLE), "-m", "stk", "--seed", str(2**63 - 1), "-o", str(tmp_path / "out.h5"))
    assert result.returncode == 0, result.stderr


def test_a_track_csv_with_a_huge_frame_number_is_refused_within_a_small_memory(tmp_path):
    """Issue 28.13: two rows, one on frame 100000000, made info allocate 9.5 GiB (dense (P, F) arrays)."""
    import tracemalloc

    from condtrack_cli.errors import CondtrackError
    from condtrack_cli.evaluate.groundtruth import load_gt_csv
    from condtrack_cli.io.read import read_tracks

    tracks, truth = tmp_path / "t.csv", tmp_path / "gt.csv"
    tracks.write_text("point_id,frame,x,y,cov_xx,cov_xy,cov_yy,visible,method\n"
                      "0,0,1.0,2.0,1,0,1,1,clf\n0,100000000,1.0,2.0,1,0,1,1,clf\n")
    truth.write_text("point_id,frame,x,y,visible\n0,0,1,2,1\n1,100000000,1,2,1\n")
    for read, path in ((read_tracks, tracks), (load_gt_csv, truth)):
        tracemalloc.start()
        try:
            with pytest.raises(CondtrackError, match=r"line 3 has frame 100000000, but the file has 2 rows for "):
                read(path)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 2**25, peak  # 32 MiB; the dense arrays took 9.5 GiB
    result = run_cli("info", str(tracks))
    _one_error_line(result, 1, f"{tracks}: line 3 has frame 100000000, but the file has 2 rows for 1 points")
    result = run_cli("eval", str(SAMPLE / "tracks.csv"), str(truth))
    _one_error_line(result, 1, f"{truth}: line 3 has frame 100000000")


def test_a_named_pipe_input_is_refused_at_once(tmp_path):
    """Issue 28.15: OpenCV's open blocked on a FIFO, deaf to Ctrl-C and SIGTERM; the run must end by itself."""
    fifo = tmp_path / "clip.mp4"
    os.mkfifo(fifo)
    process = subprocess.Popen([sys.executable, "-c", "from condtrack_cli.cli import main; main()", "track", str(fifo),
                                "-o", str(tmp_path / "out.csv")], stderr=subprocess.PIPE, text=True)
    try:
        _, stderr = process.communicate(timeout=30)
    except subprocess.TimeoutExpired:
        process.kill()
        process.communicate()
        pytest.fail("the run hung on the named pipe")
    assert process.returncode == 1 and stderr == (
        f"Error: {fifo}: not a regular file (a named pipe); give a video file or a folder of frames\n")
    assert [p.name for p in tmp_path.iterdir()] == ["clip.mp4"]


def _with_a_closed_pipe(stream: str, *args: str) -> subprocess.CompletedProcess:
    """Run the command line with its ``stream`` ("stdout" or "stderr") a pipe whose reader has already gone."""
    reader, writer = os.pipe()
    os.close(reader)
    try:
        return subprocess.run([sys.executable, "-c", "from condtrack_cli.cli import main; main()", *args],
                              capture_output=False, text=True, timeout=300,
                              **{stream: writer, ("stderr" if stream == "stdout" else "stdout"): subprocess.PIPE})
    finally:
        os.close(writer)


def test_a_reader_closing_the_pipe_early_is_not_an_error(tmp_path):
    folder = _frames_folder(tmp_path)
    csv, other = tmp_path / "a.csv", tmp_path / "b.csv"
    assert run_cli("track", str(folder), "-m", "stk", "-o", str(csv), "-q").returncode == 0
    header, first, *rest = csv.read_text().splitlines(keepends=True)
    fields = first.split(",")
    fields[2] = f"{float(fields[2]) + 10:f}"  # the first row's x 10 px off: compare says they differ (exit 1)
    other.write_text("".join([header, ",".join(fields), *rest]))
    for args, code in [(("--help",), 0), (("info", str(csv)), 0), (("compare", "--strict", str(csv), str(other)), 1),
                       (("track", str(folder), "-m", "stk", "-q", "--overlay", str(tmp_path / "o.mp4")), 0)]:
        result = _with_a_closed_pipe("stdout", *args)
        assert (result.returncode, result.stderr) == (code, ""), args  # the command's own code, nothing said
    assert (tmp_path / "o.mp4").stat().st_size > 0 and not list(tmp_path.glob("*.part"))
    result = _with_a_closed_pipe("stderr", "track", str(tmp_path / "nowhere"))
    assert (result.returncode, result.stdout) == (2, "")


def _main(args: list[str], monkeypatch, capsys) -> tuple[int, str, str]:
    """``condtrack ARGS`` in this process (its monkeypatches apply): exit code, stdout, stderr."""
    from condtrack_cli.cli import main

    monkeypatch.setattr(sys, "argv", ["condtrack", *args])
    with pytest.raises(SystemExit) as stop:
        main()
    captured = capsys.readouterr()
    return stop.value.code, captured.out, captured.err


@pytest.mark.parametrize("output", ["out.h5", "out.csv", None])
@pytest.mark.parametrize("failure", ["frame gone", "frames dropped"])
def test_an_overlay_failing_in_its_second_pass_leaves_no_track_file(tmp_path, monkeypatch, capsys, output, failure):
    """The track file was published before the overlay's second pass over the frames, so a failure there (a frame
    removed since the first pass, a video writer that dropped frames) exited 1 with the -o file written (and the CSV
    already on stdout). Now both are published once the overlay is: nothing is left, an earlier file at the -o path
    stays as it was, stdout gets nothing."""
    import condtrack_cli.render
    import condtrack_cli.run

    (tmp_path / "in").mkdir()
    folder = _frames_folder(tmp_path / "in")
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    earlier = out_dir / "out.h5"
    earlier.write_bytes(b"an earlier run's file")
    if failure == "frame gone":
        tracked = condtrack_cli.run.track_sequence

        def track_then_lose_a_frame(*args, **kwargs):
            done = tracked(*args, **kwargs)
            (folder / "003.png").unlink()
            return done

        monkeypatch.setattr(condtrack_cli.run, "track_sequence", track_then_lose_a_frame)
        message = f"Error: frame 3 ({folder / '003.png'}): not a readable image\n"
    else:
        def dropped(video, count, named):
            raise CondtrackError(f"{named}: the video writer stored 2 of {count} frames (is the disk full?)")

        monkeypatch.setattr(condtrack_cli.render, "_check_video", dropped)
        message = f"Error: {out_dir / 'overlay.mp4'}: the video writer stored 2 of 4 frames (is the disk full?)\n"
    overlay = out_dir / "overlay.mp4"
    args = ["track", str(folder), "-m", "stk", "-q", "--overlay", str(overlay)]
    code, stdout, stderr = _main(args + (["-o", str(out_dir / output)] if output else []), monkeypatch, capsys)
    assert (code, stdout, stderr) == (1, "", message)
    assert sorted(p.name for p in out_dir.iterdir()) == ["out.h5"]
    assert earlier.read_bytes() == b"an earlier run's file"
