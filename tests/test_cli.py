"""The command line end to end: outputs per contract, errors as one line with no partial file."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from condtrack_cli import registry
from condtrack_cli.cli import cli
from condtrack_cli.io.read import read_tracks
from condtrack_cli.io.write import CSV_COLUMNS


def run_cli(*args: str) -> subprocess.CompletedProcess:
    """Run the real console entry point (so the ``Error:`` handling is exercised)."""
    return subprocess.run(
        [sys.executable, "-c", "from condtrack_cli.cli import main; main()", *args],
        capture_output=True, text=True, timeout=300,
    )


def test_track_writes_every_contract_field(shifted_folder, tmp_path):
    folder, shifts = shifted_folder
    h5 = tmp_path / "out.h5"
    csv = tmp_path / "out.csv"
    assert run_cli("track", str(folder), "-m", "stk", "-o", str(h5), "-q").returncode == 0
    result = run_cli("track", str(folder), "-m", "stk", "-o", str(csv), "-q")
    assert result.returncode == 0 and result.stdout == "" and result.stderr == ""
    with h5py.File(h5) as f:
        for key in ("schema_version", "condtrack_version", "config", "input", "width", "height", "n_frames", "fps", "coordinates"):
            assert key in f.attrs, key
        assert (f.attrs["width"], f.attrs["height"], f.attrs["n_frames"]) == (320, 256, 6)
        p = f["tracks/xy"].shape[0]
        assert f["tracks/xy"].shape == (p, 6, 2) and f["tracks/cov"].shape == (p, 6, 2, 2)
        assert f["tracks/visible"].dtype == bool and f["tracks/visible"].shape == (p, 6)
        assert f["tracks/method"].shape == (p,) and f["queries"].shape == (p, 3)
        assert "measurements/z" in f and "measurements/R" in f
        assert "motion:" in f.attrs["config"] and "method: stk" in f.attrs["config"]
        assert np.isfinite(f["tracks/xy"][()]).all()  # every point queried on frame 0
    lines = csv.read_text().splitlines()
    assert lines[0] == ",".join(CSV_COLUMNS)
    assert len(lines) == 1 + p * 6
    first = lines[1].split(",")
    assert first[4:7] == ["nan", "nan", "nan"] and first[7:] == ["inf", "1", "stk"]  # stk: no covariance, Gaussian
    tracks, _ = read_tracks(csv)
    from_h5, _ = read_tracks(h5)
    np.testing.assert_allclose(tracks.xy, from_h5.xy, atol=1e-6)
    errors = np.linalg.norm(tracks.xy - (tracks.queries.xy[:, None] + shifts[None]), axis=-1)
    assert np.median(errors) < 0.1


def test_csv_on_stdout_without_output(shifted_folder):
    folder, _ = shifted_folder
    result = CliRunner().invoke(cli, ["track", str(folder), "-q"])
    assert result.exit_code == 0
    assert result.output.splitlines()[0] == ",".join(CSV_COLUMNS)


def test_output_dash_is_stdout(shifted_folder, tmp_path):
    """``-o -`` (the usual name of stdout) was refused as "unknown output format ''"; it writes the CSV on stdout, the
    same bytes as no -o, and is still refused in a batch, which writes into --out-dir."""
    folder, _ = shifted_folder
    dashed = CliRunner().invoke(cli, ["track", str(folder), "-m", "stk", "-o", "-", "-q"])
    assert dashed.exit_code == 0, dashed.output
    assert dashed.output == CliRunner().invoke(cli, ["track", str(folder), "-m", "stk", "-q"]).output
    batch = run_cli("track", str(folder), str(folder), "-o", "-", "--out-dir", str(tmp_path / "out"))
    assert batch.returncode == 2 and batch.stderr.endswith("Error: -o and --overlay take one input; a batch writes "
                                                           "into --out-dir\n")
    assert not (tmp_path / "out").exists()


def test_queries_are_tracked_forward_and_backward_from_their_frame(shifted_folder, tmp_path):
    folder, shifts = shifted_folder
    queries = tmp_path / "q.csv"
    start = np.array([[100.0, 80.0], [200.0, 150.0]])
    queries.write_text(f"point_id,frame,x,y\n7,2,{start[0,0] + shifts[2,0]},{start[0,1] + shifts[2,1]}\n3,0,{start[1,0]},{start[1,1]}\n")
    out = tmp_path / "t.csv"
    assert run_cli("track", str(folder), "-p", str(queries), "-o", str(out), "-q").returncode == 0
    assert run_cli("track", str(folder), "-p", str(queries), "-o", str(tmp_path / "t.h5"), "-q").returncode == 0
    tracks, _ = read_tracks(tmp_path / "t.h5")
    np.testing.assert_array_equal(tracks.queries.point_id, [3, 7])
    np.testing.assert_array_equal(tracks.queries.frame, [0, 2])
    assert np.isfinite(tracks.xy).all()  # tracked backward from frame 2 to 0 as well
    truth = start[::-1][:, None] + shifts[None]  # point 3 starts at start[1], point 7 at start[0]
    # 0.35 px: the default `auto` starts points on the particle filter, whose path mean carries Monte Carlo spread
    # here (largest error 0.13-0.31 px over seeds 0-7 with the default DIS motion stage)
    np.testing.assert_array_less(np.linalg.norm(tracks.xy - truth, axis=-1), 0.35)
    lines = out.read_text().splitlines()
    assert len(lines) == 1 + 2 * 6 and lines[1].startswith("3,0,") and lines[7].startswith("7,0,")


def test_forward_only_writes_rows_from_each_query_frame_on(shifted_folder, tmp_path):
    folder, shifts = shifted_folder
    queries = tmp_path / "q.csv"
    queries.write_text(f"point_id,frame,x,y\n7,2,{100 + shifts[2, 0]},{80 + shifts[2, 1]}\n3,0,200,150\n")
    out = tmp_path / "t.csv"
    assert run_cli("track", str(folder), "-p", str(queries), "-m", "clf", "--forward-only", "-o", str(out), "-q").returncode == 0
    frames = {point: [int(line.split(",")[1]) for line in out.read_text().splitlines()[1:] if line.startswith(f"{point},")]
              for point in (3, 7)}
    assert frames == {3: [0, 1, 2, 3, 4, 5], 7: [2, 3, 4, 5]}  # point 7 has no row before its query frame 2


@pytest.mark.parametrize(
    "content, message",
    [
        ("frame,x\n0,1\n", "missing column 'y'"),
        ("frame,x,y\n0,abc,3\n", "row 2, column 'x': 'abc' is not a number"),
        ("frame,x,y\n0,1000,3\n", "row 2: point (1000, 3) is outside"),
        ("frame,x,y\n99,10,3\n", "row 2: frame 99 is outside the sequence"),
        # issue 28.3: a misspelt point_id would renumber the points; a repeated column is ambiguous
        ("frame,x,y,pointid\n0,10,3,5\n", "q.csv: unknown column 'pointid'"),
        ("frame,x,y,x\n0,10,3,12\n", "q.csv: column 'x' appears twice in the header"),
        ("point_id,frame,x,y,point_id\n1,0,10,3,2\n", "column 'point_id' appears twice"),
    ],
)
def test_bad_queries_are_refused_without_output(shifted_folder, tmp_path, content, message):
    folder, _ = shifted_folder
    queries = tmp_path / "q.csv"
    queries.write_text(content)
    out = tmp_path / "t.h5"
    result = run_cli("track", str(folder), "-p", str(queries), "-o", str(out))
    assert result.returncode != 0
    assert result.stderr.startswith("Error: ") and message in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    assert not out.exists() and not list(tmp_path.glob(".t.h5*"))


def test_bad_config_and_output_are_refused_before_work(shifted_folder, tmp_path):
    folder, _ = shifted_folder
    result = run_cli("track", str(folder), "--set", "filter.stk.levels=0", "-o", str(tmp_path / "a.csv"))
    assert result.returncode != 0 and "Error: config key 'filter.stk.levels'" in result.stderr
    result = run_cli("track", str(folder), "-o", str(tmp_path / "missing" / "a.csv"))
    assert result.returncode != 0 and "does not exist" in result.stderr
    result = run_cli("track", str(folder), "-o", str(tmp_path / "a.txt"))
    assert result.returncode != 0 and "unknown output format" in result.stderr
    result = run_cli("track", str(folder), "-m", "kalman")
    assert result.returncode == 2 and "is not one of" in result.stderr
    assert not list(tmp_path.glob("a.*"))


@pytest.mark.parametrize("option, named", [("-o", "'-o' / '--output'"), ("--overlay", "'--overlay'")])
def test_an_empty_output_path_is_refused_as_empty(shifted_folder, option, named):
    """-o "" (an unset shell variable) was refused as ".: unknown output format ''", naming a folder nobody gave."""
    folder, _ = shifted_folder
    result = run_cli("track", str(folder), option, "")
    assert result.returncode == 2
    assert result.stderr.splitlines()[-1] == f"Error: Invalid value for {named}: an empty path; name a file"


def _installed_plugin(tmp_path, monkeypatch, name: str, entry: str) -> None:
    """A distribution ``name`` 1.0 installed on sys.path (tmp_path) whose ``condtrack.stages`` entry point is
    ``entry`` (``"key = module"``), and the registry's entry points read again."""
    info = tmp_path / f"{name.replace('-', '_')}-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[condtrack.stages]\n{entry}\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    registry.reload_entry_points()


def test_third_party_stage_registers_through_entry_points(tmp_path, monkeypatch):
    package = tmp_path / "thirdparty_detect.py"
    package.write_text(textwrap.dedent('''
        import numpy as np
        from condtrack_cli.settings import StageSettings
        from condtrack_cli.registry import register

        class GridSettings(StageSettings):
            step: int = 32

        @register("detect", "grid", GridSettings, "a regular grid of points")
        def grid(settings, gray):
            ys, xs = np.mgrid[settings.step:gray.shape[0] - settings.step:settings.step,
                              settings.step:gray.shape[1] - settings.step:settings.step]
            return np.column_stack([xs.ravel(), ys.ravel()]).astype(float)
    '''))
    _installed_plugin(tmp_path, monkeypatch, "thirdparty-detect", "grid = thirdparty_detect")
    try:
        assert "grid" in registry.names("detect")
        result = CliRunner().invoke(cli, ["stages"])
        assert "grid" in result.output and "a regular grid of points" in result.output
    finally:
        registry._STAGES["detect"].pop("grid", None)
        registry.reload_entry_points()


def test_a_broken_entry_point_is_warned_and_the_other_stages_work(tmp_path, monkeypatch):
    """An entry point naming a module that is not installed ended every command (stages, info, track) in a
    ModuleNotFoundError traceback."""
    _installed_plugin(tmp_path, monkeypatch, "broken-plugin", "broken = no_such_condtrack_plugin")
    try:
        result = CliRunner().invoke(cli, ["stages"])
        assert result.exit_code == 0 and "  clf " in result.output, result.output
        assert result.stderr == ("warning: condtrack.stages entry point 'broken = no_such_condtrack_plugin' not "
                                 "loaded, its stages left out (ModuleNotFoundError: No module named "
                                 "'no_such_condtrack_plugin')\n")
    finally:
        registry.reload_entry_points()


@pytest.mark.parametrize("sample, floor", [("camera_motion", 0.90), ("occlusion", 0.75)])
def test_stk_accuracy_on_the_samples(tmp_path, sample, floor):
    """STK's <delta_avg on the shipped samples' exact ground truth stays above a floor (measured 0.958 / 0.807)."""
    from condtrack_cli.evaluate.groundtruth import load_gt_csv
    from condtrack_cli.evaluate.score import score_tracks

    from conftest import SAMPLES

    folder = SAMPLES / sample
    out = tmp_path / "stk.h5"
    assert run_cli("track", str(folder), "-p", str(folder / "queries.csv"), "-m", "stk", "-o", str(out), "-q").returncode == 0
    result, _ = score_tracks(read_tracks(out)[0], load_gt_csv(folder / "tracks.csv"))
    assert result["delta_avg"] >= floor


def _track_csv(path, rows):
    """A condtrack track CSV with ``rows`` of (point_id, frame, x, y), covariances I, visible, clf."""
    path.write_text(",".join(CSV_COLUMNS) + "\n" + "".join(f"{p},{f},{x},{y},1,0,1,inf,1,clf\n" for p, f, x, y in rows))
    return path


@pytest.mark.parametrize("command", ["eval", "render", "info", "compare"])
def test_a_track_csv_with_a_repeated_point_and_frame_is_refused(shifted_folder, tmp_path, command):
    """Issue 28.4: every command that reads a track CSV refuses a second row for one (point_id, frame)."""
    folder, _ = shifted_folder
    rows = [(p, f, 100.0 + f, 50.0 + 10 * p) for p in (0, 1) for f in range(6)]
    good = _track_csv(tmp_path / "good.csv", rows)
    bad = _track_csv(tmp_path / "bad.csv", rows[:9] + [(1, 1, 140.0, 60.0)] + rows[9:])
    truth = tmp_path / "gt.csv"
    truth.write_text("point_id,frame,x,y,visible\n" + "".join(f"{p},{f},{x},{y},1\n" for p, f, x, y in rows))
    args = {"eval": [str(bad), str(truth)], "render": [str(bad), str(folder), "-o", str(tmp_path / "out.mp4")],
            "info": [str(bad)], "compare": [str(bad), str(good)]}[command]
    result = run_cli(command, *args)
    assert result.returncode == (2 if command == "compare" else 1)  # compare: 1 means "differ"
    assert result.stderr == f"Error: {bad}: line 11 (point_id 1, frame 1): a second row for the same point_id and frame\n"
    assert not (tmp_path / "out.mp4").exists()
    assert run_cli(command, *[str(good) if a == str(bad) else a for a in args]).returncode == 0


def test_an_image_output_inside_the_input_frame_folder_is_refused(shifted_folder, tmp_path):
    """``render --contact-sheet`` on one of INPUT's frames overwrote it (the -o check compared the folder itself);
    a new PNG there would add a frame to the sequence. Both are refused before any work, the frames as they were."""
    folder, _ = shifted_folder
    tracks = tmp_path / "t.h5"
    assert run_cli("track", str(folder), "-m", "stk", "-o", str(tracks), "-q").returncode == 0
    frames = sorted(folder.glob("*.png"))
    before = {frame: frame.read_bytes() for frame in frames}
    for sheet in (frames[1], folder / "sheet.png"):
        result = run_cli("render", str(tracks), str(folder), "-o", str(tmp_path / "v.mp4"), "--contact-sheet", str(sheet))
        assert result.returncode == 1 and result.stderr == (
            f"Error: --contact-sheet {sheet}: an image in the frame folder INPUT {folder}; writing it would replace or "
            "add a frame of the input\n")
        assert not (tmp_path / "v.mp4").exists()
    assert sorted(folder.glob("*.png")) == frames and {f: f.read_bytes() for f in frames} == before


def test_output_on_an_input_is_refused_and_a_symlinked_output_is_written_through(shifted_folder, tmp_path):
    """Issue 28.5: -o naming the queries file (or a link to it) is refused; -o on a link replaces its target."""
    folder, _ = shifted_folder
    queries = tmp_path / "q.csv"
    queries.write_text("frame,x,y\n0,120,100\n")
    before = queries.read_bytes()
    alias = tmp_path / "alias.csv"
    alias.symlink_to(queries)
    for out in (queries, alias):
        result = run_cli("track", str(folder), "-p", str(queries), "-m", "stk", "-o", str(out))
        assert result.returncode == 1 and result.stderr == (
            f"Error: -o {out}: the same file as the input -p {queries}; writing it would destroy the input\n")
        assert queries.read_bytes() == before
    target = tmp_path / "kept" / "tracks.csv"
    target.parent.mkdir()
    target.write_text("old\n")
    link = tmp_path / "latest.csv"
    link.symlink_to(target)
    assert run_cli("track", str(folder), "-p", str(queries), "-m", "stk", "-o", str(link), "-q").returncode == 0
    assert link.is_symlink() and link.readlink() == target
    assert target.read_text().splitlines()[0] == ",".join(CSV_COLUMNS)
    assert not [p for p in tmp_path.rglob(".*.part")]
