"""``condtrack compare`` and stable outputs: what golden-file checks in users' CI rely on."""

from __future__ import annotations

import json
import os
import re
import shutil
import struct
import subprocess
import sys
import time

import numpy as np
import pytest
from click.testing import CliRunner

from condtrack_cli.cli import cli
from condtrack_cli.cli.compare import compare_command
from condtrack_cli.io.compare import CSV_FIELDS, HDF5_FIELDS, STRICT, TOLERANT, compare_tracks, with_options
from condtrack_cli.io.interface import OutputSettings
from condtrack_cli.io.read import read_tracks
from condtrack_cli.io.write import write_tracks
from condtrack_cli.types import Queries, SequenceInfo, Tracks

P, F = 4, 6
META = {"config": "filter:\n  method: clf\n", "method": "clf", "seed": 0}


def make_tracks(n_frames: int = F) -> Tracks:
    """P=4 points (ids 3, 7, 11, 20) over ``n_frames``; point 11 from frame 2 on; inf and nan covariances."""
    rng = np.random.default_rng(7)
    xy = rng.uniform(0, 300, (P, n_frames, 2))
    xy[2, :2] = np.nan
    cov = rng.uniform(0.1, 3.0, (P, n_frames, 1, 1)) * np.array([[1.0, 0.2], [0.2, 0.5]])
    cov[1, 3] = [[np.inf, 0.0], [0.0, np.inf]]
    cov[3] = np.nan
    cov[2, :2] = np.nan
    method = np.full((P, n_frames), 2, np.int8)
    method[3] = 0
    method[2, :2] = -1
    visible = rng.random((P, n_frames)) > 0.2
    visible[2, :2] = False
    z = xy + rng.normal(0, 0.5, xy.shape)
    queries = Queries(np.array([3, 7, 11, 20]), np.array([0, 0, 2, 0]), xy[np.arange(P), [0, 0, 2, 0]])
    dof = np.where(np.isfinite(xy).all(axis=-1), 3.0 + rng.random((P, n_frames)) * 10, np.nan)
    return Tracks(queries, xy, cov, dof, visible, method, z, cov * 2)


def edited(tracks: Tracks, **arrays: np.ndarray) -> Tracks:
    """``tracks`` with some arrays replaced."""
    fields = {name: getattr(tracks, name) for name in ("queries", "xy", "cov", "dof", "visible", "method", "z", "R")}
    return Tracks(**{**fields, **arrays})


def write(path, tracks: Tracks, settings: OutputSettings | None = None):
    info = SequenceInfo("frames/", 320, 240, tracks.xy.shape[1], 0.0)
    write_tracks(tracks, path, info, META, settings or OutputSettings())
    return path


def compare(*args) -> tuple[int, str]:
    """Run the compare command in-process: (exit code, stdout)."""
    result = CliRunner().invoke(compare_command, [str(arg) for arg in args])
    return result.exit_code, result.stdout


def run_cli(*args, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """The real console entry point, as users' CI runs it, in its own process with ``env`` added."""
    return subprocess.run(
        [sys.executable, "-c", "from condtrack_cli.cli import main; main()", *map(str, args)],
        capture_output=True, text=True, timeout=300, env={**os.environ, **(env or {})},
    )


def table_rows(report: str) -> list[list[str]]:
    """The rows (point, frame, field, A, B, |A-B|) of the report's largest-differences table."""
    lines = report.splitlines()
    start = lines.index("largest differences:") + 2
    return [line.split() for line in lines[start:]]


@pytest.fixture
def golden(tmp_path):
    return write(tmp_path / "golden.h5", make_tracks())


def test_identical_files_agree_through_the_entry_point(golden, tmp_path):
    copy = shutil.copy(golden, tmp_path / "copy.h5")
    result = run_cli("compare", golden, copy)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("agree: ") and result.stderr == ""


def test_a_moved_position_differs_and_is_named(golden, tmp_path):
    tracks = make_tracks()
    xy = tracks.xy.copy()
    xy[1, 4, 1] += 0.002
    moved = write(tmp_path / "moved.h5", edited(tracks, xy=xy))
    result = run_cli("compare", golden, moved, "--strict")
    assert result.returncode == 1 and result.stderr == ""
    assert result.stdout.startswith("differ: ")
    assert "differing values: xy 1" in result.stdout
    point, frame, field, a, b, diff = table_rows(result.stdout)[0]
    assert (point, frame, field) == ("7", "4", "xy")
    assert [float(v) for v in a.split(",")] == pytest.approx(tracks.xy[1, 4], rel=1e-6)
    assert float(b.split(",")[1]) == pytest.approx(xy[1, 4, 1], rel=1e-6)
    assert float(diff) == pytest.approx(0.002)
    assert run_cli("compare", golden, moved).returncode == 0  # 0.002 px: the default's rounding noise


def test_a_move_within_the_tolerance_agrees(golden, tmp_path):
    tracks = make_tracks()
    xy = tracks.xy + 5e-5
    assert compare(golden, write(tmp_path / "near.h5", edited(tracks, xy=xy)), "--strict")[0] == 0
    xy[0, 0, 0] += 0.01
    far = write(tmp_path / "far.h5", edited(tracks, xy=xy))
    assert compare(golden, far, "--strict")[0] == 1
    assert compare(golden, far, "--strict", "--atol-px", "0.02")[0] == 0
    assert compare(golden, far)[0] == 0


def test_csv_and_hdf5_of_the_same_tracks_agree(golden, tmp_path):
    csv = write(tmp_path / "golden.csv", make_tracks())
    for a, b in ((golden, csv), (csv, golden), (csv, csv)):
        code, out = compare(a, b, "--strict")
        assert code == 0, out
    code, out = compare(golden, csv, "--json")
    report = json.loads(out)
    assert report["agree"] and report["fields"] == list(CSV_FIELDS) and report["n_points"] == P
    skipped = "not compared (a CSV does not hold them): n_frames, query_frame, query_x, query_y, z, R\n"
    assert skipped in compare(golden, csv)[1]


def test_a_point_without_any_position_is_not_expected_in_a_csv(tmp_path):
    tracks = make_tracks()
    xy = tracks.xy.copy()
    xy[2] = np.nan
    lost = edited(tracks, xy=xy)
    h5, csv = write(tmp_path / "lost.h5", lost), write(tmp_path / "lost.csv", lost)
    assert compare(h5, csv)[0] == 0
    code, out = compare(write(tmp_path / "all.h5", tracks), csv)
    assert code == 1 and "differing values: points 1" in out


def test_csv_and_hdf5_of_a_tracked_sequence_agree_and_rerun_is_identical(shifted_folder, tmp_path):
    folder, _ = shifted_folder
    queries = tmp_path / "q.csv"
    queries.write_text("frame,x,y,point_id\n2,120,100,5\n0,200,150,1\n3,60.5,80.25,9\n")
    outputs = [tmp_path / "run1.h5", tmp_path / "run1.csv", tmp_path / "run2.h5"]
    for output in outputs:
        args = ["track", str(folder), "-p", str(queries), "-m", "clf", "-o", str(output), "-q"]
        result = CliRunner().invoke(cli, args)
        assert result.exit_code == 0, result.output
    assert compare(outputs[0], outputs[1], "--strict")[0] == 0
    assert compare(outputs[1], outputs[0], "--strict")[0] == 0
    assert outputs[0].read_bytes() == outputs[2].read_bytes()


@pytest.mark.parametrize("damage", ["missing", "truncated_h5", "truncated_csv", "not_hdf5", "other_schema"])
def test_unreadable_input_exits_2_with_one_error_line(golden, tmp_path, damage):
    bad = tmp_path / "bad.h5"
    if damage == "truncated_h5":
        bad.write_bytes(golden.read_bytes()[: golden.stat().st_size // 2])
    elif damage == "truncated_csv":
        text = write(tmp_path / "whole.csv", make_tracks()).read_text()
        bad = tmp_path / "bad.csv"
        bad.write_text(text[: len(text) - 20])
    elif damage == "not_hdf5":
        bad.write_text("point_id,frame\n")
    elif damage == "other_schema":
        import h5py

        shutil.copy(golden, bad)
        with h5py.File(bad, "r+") as f:
            f.attrs["schema_version"] = "9.0"
    result = CliRunner().invoke(compare_command, [str(golden), str(bad)])
    assert result.exit_code == 2 and result.stdout == ""
    assert result.stderr.startswith(f"Error: {bad}") and result.stderr.count("\n") == 1


def test_unreadable_input_exits_2_through_the_entry_point(golden, tmp_path):
    bad = tmp_path / "bad.h5"
    bad.write_bytes(golden.read_bytes()[:1000])
    result = run_cli("compare", bad, golden)
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.startswith(f"Error: {bad}: ") and result.stderr.count("\n") == 1


@pytest.mark.parametrize(
    "a, b, agree",
    [
        (np.inf, np.nan, False), (np.nan, np.inf, False), (np.inf, 1e300, False), (np.inf, -np.inf, False),
        (np.nan, 2.0, False), (np.inf, np.inf, True), (np.nan, np.nan, True), (2.0, 2.0 * (1 + 5e-5), True),
        (2.0, 2.0 * (1 + 2e-4), False), (0.0, 1e-13, True),
    ],
)
def test_covariance_kinds_and_relative_tolerance(a, b, agree):
    """--strict: the matrix of cell (3, 1) has a norm in [2, 2.6] with cov_xx = 2: 2e-4 relative on it is over 1e-4."""
    tracks = make_tracks()
    cov = tracks.cov.copy()
    cov[0, 1, 0, 0] = a
    other = tracks.cov.copy()
    other[0, 1, 0, 0] = b
    result = compare_tracks(edited(tracks, cov=cov), edited(tracks, cov=other), STRICT)
    assert result.agree == agree
    assert result.counts["cov"] == (0 if agree else 1)
    assert sum(result.counts.values()) == result.counts["cov"]


def test_covariances_are_compared_as_matrices_not_per_entry():
    """A near-zero off-diagonal entry changed by 100 % is a tiny change of the matrix; a changed shape is not."""
    tracks = make_tracks()
    base = np.array([[4.0, 1e-3], [1e-3, 1.0]])
    cov = np.broadcast_to(base, tracks.cov.shape).copy()
    near_zero = cov.copy()
    near_zero[..., 0, 1] = near_zero[..., 1, 0] = 2e-3  # per entry: 100 % relative
    assert compare_tracks(edited(tracks, cov=cov), edited(tracks, cov=near_zero), STRICT).counts["cov"] > 0
    assert compare_tracks(edited(tracks, cov=cov), edited(tracks, cov=near_zero)).counts["cov"] == 0
    rotated = cov.copy()
    rotated[...] = [[1.0, 1e-3], [1e-3, 4.0]]  # the same ellipse turned by 90 degrees: ||A - B|| / ||A|| = 1.03
    result = compare_tracks(edited(tracks, cov=cov), edited(tracks, cov=rotated))
    assert not result.agree and result.counts["cov"] == result.cells
    assert result.top[0].diff == pytest.approx(np.hypot(3, 3) / np.linalg.norm(base))


def test_inf_against_nan_differs_in_files(golden, tmp_path):
    tracks = make_tracks()
    cov = tracks.cov.copy()
    cov[1, 3] = np.nan  # was [[inf, 0], [0, inf]]: undefined as a whole (a CSV refuses a covariance partly nan)
    other = write(tmp_path / "nan.csv", edited(tracks, cov=cov))
    code, out = compare(golden, other, "--json", "--strict")
    report = json.loads(out)
    assert code == 1 and not report["agree"] and report["counts"]["cov"] == 1
    assert report["top"][0] == {"point_id": 7, "frame": 3, "field": "cov", "a": ["inf", 0.0, 0.0, "inf"],
                                "b": ["nan", "nan", "nan", "nan"], "diff": None}


def test_visibility_flips_are_allowed_up_to_the_given_number(golden, tmp_path):
    tracks = make_tracks()
    visible = tracks.visible.copy()
    visible[0, 1] = ~visible[0, 1]
    visible[3, 5] = ~visible[3, 5]
    flipped = write(tmp_path / "flipped.h5", edited(tracks, visible=visible))
    assert compare(golden, flipped)[0] == 1
    assert compare(golden, flipped, "--ignore-visible-flips", "1")[0] == 1
    code, out = compare(golden, flipped, "--ignore-visible-flips", "2")
    assert code == 0 and "differing values: visible 2\n" in out
    code, out = compare(golden, flipped, "--ignore-visible-flips", "1")
    assert [row[:3] for row in table_rows(out)] == [["3", "1", "visible"], ["20", "5", "visible"]]


def test_a_visibility_flip_where_the_positions_differ_is_a_near_tie(golden, tmp_path):
    """A flip that comes with a moved position is a threshold decision on other numbers: a differing cell."""
    tracks = make_tracks()
    visible, xy = tracks.visible.copy(), tracks.xy.copy()
    visible[0, 1] = ~visible[0, 1]
    xy[0, 1] += 0.01
    tie = write(tmp_path / "tie.h5", edited(tracks, visible=visible, xy=xy))
    code, out = compare(golden, tie)
    assert code == 0 and "differing cells: 1 of 22 (4.55%)" in out and "visible 1 (1 near-tie)" in out
    assert compare(golden, tie, "--max-share", "4")[0] == 1
    assert compare(golden, tie, "--strict", "--max-share", "5", "--atol-px", "0.1")[0] == 1  # strict: no tie


def test_points_frames_queries_and_methods_are_compared(golden, tmp_path):
    tracks = make_tracks()
    fewer = Tracks(Queries(tracks.queries.point_id[:3], tracks.queries.frame[:3], tracks.queries.xy[:3]),
                   *(getattr(tracks, name)[:3] for name in ("xy", "cov", "dof", "visible", "method", "z", "R")))
    result = compare_tracks(tracks, fewer)
    assert not result.agree and result.counts["points"] == 1
    first = result.top[0]
    assert (first.point_id, first.frame, first.field, first.a, first.b) == (20, None, "points", "present", "absent")

    longer = make_tracks(F + 1)
    longer = edited(longer, xy=np.concatenate([tracks.xy, longer.xy[:, -1:]], axis=1))
    result = compare_tracks(tracks, longer, fields=CSV_FIELDS)
    assert result.n_frames == F + 1 and result.counts["state"] == P  # frame F: a position in one file only

    padded = {name: np.concatenate([getattr(tracks, name), np.full_like(getattr(tracks, name)[:, :1], fill)], axis=1)
              for name, fill in (("xy", np.nan), ("cov", np.nan), ("visible", False), ("method", -1),
                                 ("z", np.nan), ("R", np.nan))}
    trailing = edited(tracks, **padded)  # one more frame, with no state on it
    assert compare_tracks(tracks, trailing, fields=CSV_FIELDS).agree
    assert compare_tracks(tracks, trailing).counts["n_frames"] == 1

    moved = Queries(tracks.queries.point_id, tracks.queries.frame + 1, tracks.queries.xy)
    assert compare_tracks(tracks, edited(tracks, queries=moved)).counts["query_frame"] == P
    assert compare_tracks(tracks, edited(tracks, queries=moved), fields=CSV_FIELDS).agree

    method = tracks.method.copy()
    method[0, 2] = 3
    result = compare_tracks(tracks, edited(tracks, method=method))
    assert result.counts["method"] == 1 and (result.top[0].a, result.top[0].b) == ("clf", "cnlf")
    assert result.differing_cells == 1 and result.agree  # auto choosing another filter on one cell of 22
    method[method == 2] = 3  # another method for the whole run
    assert not compare_tracks(tracks, edited(tracks, method=method)).agree


def _subset(tracks: Tracks, rows: slice, frames: slice = slice(None)) -> Tracks:
    """The points ``rows`` of ``tracks`` over ``frames``."""
    q = tracks.queries
    return Tracks(Queries(q.point_id[rows], q.frame[rows], q.xy[rows]),
                  *(getattr(tracks, name)[rows, frames] for name in ("xy", "cov", "dof", "visible", "method", "z", "R")))


def test_results_without_a_common_point_or_a_frame_are_compared(tmp_path):
    """Two runs from different query files share no point (a traceback before), and a header-only CSV has neither a
    point nor a frame: each point in one result only is a difference; two empty results agree."""
    tracks = make_tracks()
    result = compare_tracks(_subset(tracks, slice(0, 2)), _subset(tracks, slice(2, 4)))
    assert not result.agree and result.counts["points"] == 4 and result.cells == 0
    assert sorted(f.point_id for f in result.top) == [3, 7, 11, 20]
    empty = _subset(tracks, slice(0, 0), slice(0, 0))
    assert compare_tracks(empty, empty, fields=CSV_FIELDS).agree
    result = compare_tracks(empty, tracks, fields=CSV_FIELDS)
    assert not result.agree and result.counts["points"] == P
    header_only = tmp_path / "empty.csv"
    header_only.write_text(write(tmp_path / "a.csv", tracks).read_text().splitlines()[0] + "\n")
    assert compare(header_only, header_only)[0] == 0
    assert compare(header_only, tmp_path / "a.csv")[0] == 1


def test_measurements_are_compared_between_hdf5_files_only(golden, tmp_path):
    tracks = make_tracks()
    z = tracks.z.copy()
    z[2, 4, 0] += 1.0
    other = edited(tracks, z=z)
    assert compare(golden, write(tmp_path / "z.h5", other), "--strict")[0] == 1
    assert compare(golden, write(tmp_path / "z.csv", other), "--strict")[0] == 0
    assert compare_tracks(tracks, other).counts["z"] == 1
    assert set(HDF5_FIELDS) - set(CSV_FIELDS) == {"n_frames", "query_frame", "query_x", "query_y", "z", "R"}


def test_top_differences_are_ordered_worst_first(golden, tmp_path):
    tracks = make_tracks()
    xy = tracks.xy.copy()
    xy[0, 0, 0] += 0.5
    xy[1, 1, 0] += 2.0
    xy[3, 2, 1] += 0.001
    result = compare_tracks(tracks, edited(tracks, xy=xy), STRICT, top=2)
    assert result.counts["xy"] == 3
    assert [(d.point_id, d.frame, d.field) for d in result.top] == [(7, 1, "xy"), (3, 0, "xy")]
    assert result.top[0].diff == pytest.approx(2.0)


def test_csv_is_byte_stable_and_round_trips_positions(tmp_path):
    tracks = make_tracks()
    first, second = write(tmp_path / "a.csv", tracks), write(tmp_path / "b.csv", make_tracks())
    assert first.read_bytes() == second.read_bytes()
    back, _ = read_tracks(first)
    has = tracks.has_state
    assert np.array_equal(back.has_state, has)
    assert np.abs(back.xy[has] - tracks.xy[has]).max() <= 5e-7 + 1e-9
    np.testing.assert_allclose(back.cov[has], tracks.cov[has], rtol=1e-6)


@pytest.mark.parametrize("compression", [4, 0])
def test_hdf5_is_byte_stable_and_carries_no_timestamp(tmp_path, compression):
    settings = OutputSettings(hdf5_compression=compression)
    before = int(time.time())
    first = write(tmp_path / "a.h5", make_tracks(), settings)
    second = write(tmp_path / "b.h5", make_tracks(), settings)
    after = int(time.time())
    data = first.read_bytes()
    assert data == second.read_bytes()
    stamps = [struct.pack("<I", t) for t in range(before - 2, after + 3)]  # HDF5 stores seconds as uint32
    assert not any(stamp in data for stamp in stamps)


def masked(line: str) -> str:
    """``line`` with every number replaced by N: the form of a report line, not one machine's digits."""
    return re.sub(r"\d+(\.\d+)?(e[+-]?\d+)?", "N", line)


def test_the_readme_compare_example_is_what_compare_prints(tmp_path):
    """Issues 28.21 and 46: the README's golden-file example (a run with --set measure.search_max=8) shows
    today's output: the same lines up to the table's header, numbers masked (their last digits vary by
    machine), and the fields it names differing."""
    from conftest import REPO, SAMPLES

    text = (REPO / "README.md").read_text(encoding="utf-8")
    block = text[text.index("What a failure looks like"):]
    shown = block[block.index("```\n") + 4:block.index("...\n```")].splitlines()
    sample = SAMPLES / "occlusion"
    for name, extra in (("golden.csv", []), ("today.csv", ["--set", "measure.search_max=8"])):
        assert run_cli("track", sample, "-p", sample / "queries.csv", "-o", tmp_path / name, "-q", *extra).returncode == 0
    result = subprocess.run([sys.executable, "-c", "from condtrack_cli.cli import main; main()", "compare", "golden.csv",
                             "today.csv"], capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert result.returncode == 1
    printed = result.stdout.splitlines()
    header = shown.index("largest differences:") + 2
    values = [k for k, line in enumerate(shown) if line.startswith("differing values: ")]
    assert len(values) == 1 and printed[values[0]].startswith("differing values: ")
    for k in range(header):
        if k != values[0]:
            assert masked(printed[k]).split() == masked(shown[k]).split(), (printed[k], shown[k])

    def names(line: str) -> set[str]:
        return {item.split()[0] for item in line.removeprefix("differing values: ").split(", ")}

    assert names(shown[values[0]]) == names(printed[values[0]])  # the README showed no dof, which differed too


#: OpenCV 5's names of its dispatched levels above the SSE3 baseline (``cv2.getCPUFeaturesLine()``):
#: a CPU without any, as OpenCV's dispatch sees it.
OLDER_CPU = {"OPENCV_CPU_DISABLE": "SSE4.1,SSE4.2,POPCNT,AVX,FP16,AVX2,FMA3,AVX512-SKX", "CONDTRACK_THREADS": "1",
             "NPY_DISABLE_CPU_FEATURES": "X86_V3,X86_V4,AVX512_ICL,AVX512_SPR"}


@pytest.fixture(scope="module")
def short_occlusion(tmp_path_factory):
    """The occlusion sample's first 12 frames (links) and its 64 queries (all on frame 0)."""
    from conftest import SAMPLES

    folder = tmp_path_factory.mktemp("short") / "frames"
    folder.mkdir()
    for frame in sorted((SAMPLES / "occlusion").glob("*.png"))[:12]:
        (folder / frame.name).symlink_to(frame)
    return folder, SAMPLES / "occlusion" / "queries.csv"


def track_as(folder, queries, output, *extra, env: dict[str, str] | None = None) -> None:
    """``condtrack track`` in its own process (OpenCV reads its CPU settings once, at load) with ``env`` added."""
    result = run_cli("track", folder, "-p", queries, "-o", output, "-q", *extra, env=env)
    assert result.returncode == 0, result.stderr


@pytest.mark.parametrize("method", ["auto", "cnlf"])
def test_the_same_run_on_another_cpu_agrees_and_a_real_change_does_not(short_occlusion, tmp_path, method):
    """Issue 46: a run with OpenCV limited to its SSE3 code and one thread (another CPU) passes compare's
    defaults against this machine's run; a changed setting or method is still reported, exit 1."""
    folder, queries = short_occlusion
    here, other = tmp_path / "here.h5", tmp_path / "other.h5"
    track_as(folder, queries, here, "-m", method)
    track_as(folder, queries, other, "-m", method, env=OLDER_CPU)
    code, out = compare(here, other)
    assert code == 0, out
    result = compare_tracks(read_tracks(here)[0], read_tracks(other)[0])
    # measured on an AVX-512 machine: 0.0085 px (auto), 0.0011 px (cnlf); --strict differs (44, 7 of 768 cells)
    assert result.max_px < 0.1 and result.differing_cells == 0
    changed = tmp_path / "changed.h5"
    if method == "auto":
        track_as(folder, queries, changed, "-m", method, "--set", "measure.search_max=8")
    else:
        track_as(folder, queries, changed, "-m", "clf")
    code, out = compare(here, changed)
    assert code == 1 and "differing cells" in out, out


def test_a_share_of_differing_cells_and_the_largest_position_difference_decide():
    """P=4, F=6: 22 cells; the default allows 5 % (1 cell) beyond 0.5 px and none beyond 50 px where both runs see
    the point."""
    tracks = make_tracks()
    xy = tracks.xy.copy()
    xy[0, 1:5, 0] += 0.3  # within 0.5 px: never counted
    xy[1, 2, 1] += 4.0
    one = compare_tracks(tracks, edited(tracks, xy=xy))
    assert one.agree and one.differing_cells == 1 and one.cells == 22 and one.max_px == pytest.approx(4.0)
    xy[3, 3, 0] += 0.6
    two = compare_tracks(tracks, edited(tracks, xy=xy))
    assert not two.agree and two.differing_cells == 2
    assert compare_tracks(tracks, edited(tracks, xy=xy), with_options(TOLERANT, max_share=0.1)).agree
    xy, visible = tracks.xy.copy(), tracks.visible.copy()
    xy[1, 2, 1] += 50.5
    visible[1, 2] = True  # both runs see the point there: the cap holds
    seen = edited(tracks, visible=visible)
    far = compare_tracks(seen, edited(seen, xy=xy))
    assert not far.agree and far.differing_cells == 1
    assert compare_tracks(seen, edited(seen, xy=xy), with_options(TOLERANT, max_px=51.0)).agree


def test_the_largest_position_difference_is_capped_only_where_both_runs_see_the_point():
    """A lost point's prediction may lie far from the other run's: where another CPU's rounding tipped a match one run
    keeps the point and the other coasts (the camel, cnlf, OpenCV without AVX: 76 px apart), and a point that left
    the frame is extrapolated far outside it (KITTI seq009: 62 px apart at 70 000 px). Such a cell counts as one
    differing cell; the 50 px cap is for the rows both runs report visible. It failed at 381a548 (the cap held on
    every cell)."""
    tracks = make_tracks()
    xy, seen, lost = tracks.xy.copy(), tracks.visible.copy(), tracks.visible.copy()
    xy[1, 2, 1] += 60.0
    seen[1, 2], lost[1, 2] = True, False
    for a_sees in (seen, lost):  # a near-tie flip, then a point neither run sees
        one_lost = compare_tracks(edited(tracks, visible=a_sees), edited(tracks, xy=xy, visible=lost))
        assert one_lost.agree and one_lost.differing_cells == 1 and one_lost.max_px == pytest.approx(60.0)
        assert one_lost.max_px_seen < 60.0
    both_see = compare_tracks(edited(tracks, visible=seen), edited(tracks, xy=xy, visible=seen))
    assert not both_see.agree and both_see.differing_cells == 1 and both_see.max_px_seen == pytest.approx(60.0)


def test_a_moved_query_differs_even_in_a_csv(golden, tmp_path):
    """A CSV holds no queries; a point moved by 1 px on every frame is one (a point of 4, 6 cells of 22)."""
    tracks = make_tracks()
    xy = tracks.xy.copy()
    xy[0] += 1.0
    code, out = compare(write(tmp_path / "golden.csv", tracks), write(tmp_path / "moved.csv", edited(tracks, xy=xy)),
                        "--max-share", "50")
    assert code == 1 and "moved 1" in out
    assert table_rows(out)[0][:3] == ["3", "-", "moved"]


@pytest.mark.parametrize("option, value", [("--max-share", "nan"), ("--max-share", "-1"), ("--max-share", "150"),
                                           ("--max-px", "inf")])
def test_the_new_tolerances_refuse_what_is_not_a_finite_number(golden, option, value):
    result = CliRunner().invoke(compare_command, [str(golden), str(golden), option, value])
    assert result.exit_code == 2 and result.stdout == ""
    assert f"'{option}'" in result.stderr and "Error: " in result.stderr


def test_the_json_report_s_non_finite_values_are_strings_as_the_help_says(golden, tmp_path):
    """--json wrote an stk file's nan covariance as the string "nan" (strict JSON), which no doc said; --help says so."""
    cov = make_tracks().cov.copy()
    cov[0] = np.nan
    code, out = compare(golden, write(tmp_path / "other.h5", edited(make_tracks(), cov=cov)), "--json")
    values = [v for row in json.loads(out, parse_constant=lambda c: pytest.fail(c))["top"] for v in (row["a"], row["b"])]
    assert code == 1 and "nan" in sum((v if isinstance(v, list) else [v] for v in values), [])
    assert '"inf", "-inf" or "nan"' in " ".join(CliRunner().invoke(compare_command, ["--help"]).stdout.split())


def test_strict_json_writes_its_infinite_max_px_as_a_string(golden):
    """--strict --json printed its tolerance max_px (no cap: inf) as the bare token Infinity, which is not JSON (a
    strict parser, jq or JSON.parse, refuses the whole report); now the string "inf", as the help says of such values."""
    code, out = compare(golden, golden, "--strict", "--json")
    report = json.loads(out, parse_constant=lambda c: pytest.fail(c))
    assert code == 0 and report["tolerances"]["max_px"] == "inf" and report["tolerances"]["atol_px"] == 1e-4
    assert json.loads(compare(golden, golden, "--json")[1])["tolerances"]["max_px"] == 50.0
