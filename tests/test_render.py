"""Overlay rendering (video, PNG fallback, contact sheet) and the render / info commands, on a tiny sequence."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from condtrack_cli import SCHEMA_VERSION
from condtrack_cli import render
from condtrack_cli.cli import cli
from condtrack_cli.cli.info import _distribution, info_command
from condtrack_cli.cli.render import render_command
from condtrack_cli.errors import CondtrackError, CondtrackWarning
from condtrack_cli.config import load_config
from condtrack_cli.frames.readers import FrameSettings, open_frames
from condtrack_cli.io.interface import OutputSettings
from condtrack_cli.io.write import write_tracks
from condtrack_cli.render import ellipse_axes, render_contact_sheet, render_overlay, sheet_frames
from condtrack_cli.types import Queries, SequenceInfo, Tracks
from conftest import SAMPLES

WIDTH, HEIGHT, N_FRAMES = 96, 64, 8
CONFIG = load_config({}).to_yaml()  # a track file's config attribute: the resolved defaults


@pytest.fixture
def frames_folder(tmp_path):
    """8 frames of a smooth random texture, 96 x 64 px."""
    folder = tmp_path / "frames"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for k in range(N_FRAMES):
        noise = rng.uniform(60, 200, (HEIGHT, WIDTH)).astype(np.float32)
        cv2.imwrite(str(folder / f"f{k}.png"), cv2.GaussianBlur(noise, (0, 0), 2).astype(np.uint8))
    return folder


def make_tracks(f: int = N_FRAMES) -> Tracks:
    """4 points over ``f`` (8) frames: finite, NaN and infinite covariances, hidden frames, methods clf and stk.

    Point 0 (clf) moves right from (20, 20), visible, finite cov; point 1 (clf) at (70, 40),
    not visible on frames 3-5 where its cov is infinite; point 2 (stk) at (40, 50), NaN cov;
    point 3 (stk) starts on frame 2 at (80, 15).
    """
    p = 4
    k = np.arange(f)
    xy = np.full((p, f, 2), np.nan)
    xy[0] = np.column_stack([20 + 1.5 * k, np.full(f, 20.0)])
    xy[1] = [70.0, 40.0]
    xy[2] = np.column_stack([40.0 - 0.5 * k, np.full(f, 50.0)])
    xy[3, 2:] = [80.25, 15.5]
    cov = np.full((p, f, 2, 2), np.nan)
    cov[0] = [[4.0, 1.0], [1.0, 2.0]]
    cov[1] = [[1.0, 0.0], [0.0, 1.0]]
    cov[1, 3:6] = [[np.inf, 0.0], [0.0, np.inf]]
    cov[3, 2:] = [[9.0, 0.0], [0.0, 1.0]]
    has = np.isfinite(xy).all(axis=-1)
    visible = has.copy()
    visible[1, 3:6] = False
    method = np.where(has, np.array([2, 2, 0, 0])[:, None], -1).astype(np.int8)
    queries = Queries(np.arange(p, dtype=np.int64), np.array([0, 0, 0, 2]), xy[np.arange(p), [0, 0, 0, 2]])
    dof = np.where(has, np.array([4.0, 6.0, np.inf, np.inf])[:, None], np.nan)  # stk rows: Gaussian
    return Tracks(queries, xy, cov, dof, visible, method, np.full_like(xy, np.nan), np.full_like(cov, np.nan))


def write_h5(path, width=WIDTH, height=HEIGHT, n_frames=N_FRAMES):
    info = SequenceInfo("frames", width, height, n_frames, 0.0)
    meta = {"config": CONFIG, "method": "clf", "seed": 0}
    write_tracks(make_tracks(n_frames), path, info, meta=meta, settings=OutputSettings())
    return path


def raw_frames(folder) -> list[np.ndarray]:
    return list(open_frames(FrameSettings(), folder))


def test_ellipse_axes_are_the_95_percent_semi_axes():
    cov = np.array([[[4.0, 0.0], [0.0, 1.0]], [[1.0, 0.0], [0.0, 9.0]], [[2.0, 1.0], [1.0, 2.0]]])
    axes, angle = ellipse_axes(cov)
    np.testing.assert_allclose(axes, np.sqrt(5.991465 * np.array([[4, 1], [9, 1], [3, 1]])), rtol=1e-6)
    np.testing.assert_allclose(angle, [0.0, np.pi / 2, np.pi / 4], atol=1e-12)
    # issue 27: a Student-t row's ellipse, nu = 3: (nu - 2)((1 - 0.95)^(-2/nu) - 1) = 20^(2/3) - 1 = 6.368
    axes, _ = ellipse_axes(cov, np.array([3.0, np.inf, np.nan]))
    np.testing.assert_allclose(axes[0], np.sqrt((20 ** (2 / 3) - 1) * np.array([4, 1])), rtol=1e-12)
    np.testing.assert_allclose(axes[1:], np.sqrt(5.991465 * np.array([[9, 1], [3, 1]])), rtol=1e-6)


def test_overlay_video_has_the_input_length_and_size_and_marks_the_points(frames_folder, tmp_path):
    tracks, raw = make_tracks(), raw_frames(frames_folder)
    out = render_overlay(tracks, open_frames(FrameSettings(), frames_folder), tmp_path / "overlay.mp4", 0.0)
    assert out == tmp_path / "overlay.mp4"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames", "overlay.mp4"]  # no staging left behind
    capture = cv2.VideoCapture(str(out))
    decoded = []
    while True:
        ok, image = capture.read()
        if not ok:
            break
        decoded.append(image)
    capture.release()
    assert len(decoded) == N_FRAMES and decoded[0].shape == (HEIGHT, WIDTH, 3)
    for k in (0, 4, 7):
        x, y = np.rint(tracks.xy[0, k]).astype(int)
        near = decoded[k][y - 1:y + 2, x - 1:x + 2].astype(int)
        assert np.abs(near - raw[k][y - 1:y + 2, x - 1:x + 2, None]).max() > 60  # the green dot


def test_drawing_follows_the_states(frames_folder):
    """Lossless check of the frame drawing: dot, X, ellipses, nothing where no state; grey untouched far away."""
    tracks, raw = make_tracks(), raw_frames(frames_folder)
    overlay = render.Overlay(tracks, trail=3)
    grey = lambda image: cv2.cvtColor(image, cv2.COLOR_GRAY2BGR).astype(int)  # noqa: E731
    drawn = overlay.draw(4, raw[4]).astype(int)
    changed = np.abs(drawn - grey(raw[4])).max(axis=-1) > 0
    assert changed[20, 26] and changed[40, 70]  # point 0's dot, point 1's X centre (cov infinite, hidden)
    assert not changed[40, 74]  # no ellipse around point 1 while its cov is infinite
    assert changed[15, 80 + 7]  # point 3's ellipse: semi-axis sqrt(5.991 * 9) = 7.3 px along x
    assert not changed[55:, 60:].any()  # nothing drawn far from every point (legend is top-left)
    assert (drawn[20, 26] == render.PALETTE["clf"]).all()
    before = overlay.draw(1, raw[1]).astype(int)
    assert not (np.abs(before - grey(raw[1])).max(axis=-1) > 0)[15, 80]  # point 3 has no state before frame 2


def test_particles_are_drawn_as_pixels(frames_folder):
    tracks, raw = make_tracks(), raw_frames(frames_folder)
    particles = np.full((4, N_FRAMES, 5, 2), np.nan)
    particles[1, :, :, 0] = [60, 61, 62, 63, 200]  # the last one outside the image
    particles[1, :, :, 1] = 58
    drawn = render.Overlay(tracks, particles=particles).draw(2, raw[2])
    tint = (render.PALETTE["cnlf"] + 255) // 2
    assert (drawn[58, 60:64] == tint).all()
    with pytest.raises(ValueError, match="particles"):
        render.Overlay(tracks, particles=particles[:, :3])


def test_png_folder_when_no_codec_opens(frames_folder, tmp_path, monkeypatch):
    class ClosedWriter:
        def __init__(self, *args):
            pass

        def isOpened(self):
            return False

        def release(self):
            pass

    ClosedWriter.fourcc = staticmethod(cv2.VideoWriter.fourcc)
    monkeypatch.setattr(render.cv2, "VideoWriter", ClosedWriter)
    with pytest.warns(CondtrackWarning, match="no video codec opened.*PNG") as seen:
        out = render_overlay(make_tracks(), raw_frames(frames_folder), tmp_path / "overlay.mp4", 25.0)
    assert out == tmp_path / "overlay" and len(seen) == 1
    names = sorted(p.name for p in out.iterdir())
    assert names == [f"{k:05d}.png" for k in range(N_FRAMES)]
    assert cv2.imread(str(out / "00003.png")).shape == (HEIGHT, WIDTH, 3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames", "overlay"]
    with pytest.raises(CondtrackError, match="already exists"):  # never writes into an existing folder
        render_overlay(make_tracks(), raw_frames(frames_folder), tmp_path / "overlay.mp4", 25.0)


def test_contact_sheet_layout(frames_folder, tmp_path):
    assert sheet_frames(8, 6).tolist() == [0, 1, 3, 4, 6, 7]
    assert sheet_frames(3, 6).tolist() == [0, 1, 2]
    assert sheet_frames(30, 1).tolist() == [0] and sheet_frames(30, 2).tolist() == [0, 29]  # as render --help says
    out = render_contact_sheet(make_tracks(), raw_frames(frames_folder), tmp_path / "sheet.png", n=5, columns=3)
    assert cv2.imread(str(out)).shape == (2 * HEIGHT, 3 * WIDTH, 3)
    small = render_contact_sheet(make_tracks(), raw_frames(frames_folder), tmp_path / "two.png", n=2, columns=3)
    assert cv2.imread(str(small)).shape == (HEIGHT, 2 * WIDTH, 3)


def test_render_command_writes_video_and_sheet(frames_folder, tmp_path):
    h5 = write_h5(tmp_path / "t.h5")
    result = CliRunner().invoke(render_command, [
        str(h5), str(frames_folder), "-o", str(tmp_path / "o.mp4"), "--contact-sheet", str(tmp_path / "s.png"),
        "--sheet-frames", "4", "--trail", "3",
    ])
    assert result.exit_code == 0, result.output
    capture = cv2.VideoCapture(str(tmp_path / "o.mp4"))
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == N_FRAMES
    capture.release()
    assert cv2.imread(str(tmp_path / "s.png")).shape == (2 * HEIGHT, 3 * WIDTH, 3)


def test_render_command_reads_stored_particles(frames_folder, tmp_path):
    import h5py

    h5 = write_h5(tmp_path / "t.h5")
    with h5py.File(h5, "a") as f:
        f["particles/xy"] = np.zeros((4, N_FRAMES, 3))  # not (P, F, N, 2)
    result = CliRunner().invoke(render_command, [str(h5), str(frames_folder), "-o", str(tmp_path / "o.mp4")])
    assert isinstance(result.exception, CondtrackError) and "t.h5" in str(result.exception)
    assert "/particles/xy" in str(result.exception)
    assert not (tmp_path / "o.mp4").exists()


@pytest.mark.parametrize("size", [(WIDTH + 1, HEIGHT, N_FRAMES), (WIDTH, HEIGHT, N_FRAMES - 1)])
def test_render_refuses_a_mismatched_input_without_output(frames_folder, tmp_path, size):
    h5 = write_h5(tmp_path / "t.h5", *size)
    result = CliRunner().invoke(render_command, [
        str(h5), str(frames_folder), "-o", str(tmp_path / "o.mp4"), "--contact-sheet", str(tmp_path / "s.png"),
    ])
    assert isinstance(result.exception, CondtrackError)
    message = str(result.exception)
    assert "t.h5" in message and str(frames_folder) in message and f"{size[0]}x{size[1]}" in message
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames", "t.h5"]


def test_render_leaves_nothing_when_the_frames_fail(frames_folder, tmp_path):
    (frames_folder / "f5.png").write_bytes(b"not a png")
    with pytest.raises(CondtrackError, match="frame 5"):
        render_overlay(make_tracks(), open_frames(FrameSettings(), frames_folder), tmp_path / "o.mp4", 0.0)
    with pytest.raises(CondtrackError, match="frame 5"):
        render_contact_sheet(make_tracks(), open_frames(FrameSettings(), frames_folder), tmp_path / "s.png")
    with pytest.raises(CondtrackError, match="7 frames, the tracks 8"):
        render_overlay(make_tracks(), [np.zeros((HEIGHT, WIDTH), np.uint8)] * 7, tmp_path / "o.mp4", 0.0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames"]


def test_render_from_csv_pads_to_the_input(frames_folder, tmp_path):
    from condtrack_cli.io.write import csv_text

    tracks = make_tracks()
    csv = tmp_path / "t.csv"
    short = Tracks(tracks.queries, tracks.xy[:, :5], tracks.cov[:, :5], tracks.dof[:, :5], tracks.visible[:, :5],
                   tracks.method[:, :5], tracks.z[:, :5], tracks.R[:, :5])
    csv.write_text(csv_text(short))
    result = CliRunner().invoke(cli, ["render", str(csv), str(frames_folder), "-o", str(tmp_path / "o.mp4")])
    assert result.exit_code == 0, result.output
    capture = cv2.VideoCapture(str(tmp_path / "o.mp4"))
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == N_FRAMES
    capture.release()
    # issue 28.9: a CSV shorter than the input (every frame has a row since the backward pass) is another input's
    assert f"{csv} has rows up to frame 4, but {frames_folder} has 96x64 px, 8 frames: was it tracked on another" \
        in result.stderr


def test_render_of_a_header_only_csv_says_it_holds_no_row(frames_folder, tmp_path):
    """It said 'rows up to frame -1 ... was it tracked on another input?'; the overlay is the bare input."""
    from condtrack_cli.io.write import csv_text

    csv = tmp_path / "t.csv"
    csv.write_text(csv_text(make_tracks()).splitlines()[0] + "\n")
    result = CliRunner().invoke(cli, ["render", str(csv), str(frames_folder), "-o", str(tmp_path / "o.mp4")])
    assert result.exit_code == 0, result.output
    assert f"{csv} holds no track row (a header only): no point to show on {frames_folder}" in result.stderr
    assert "frame -1" not in result.stderr and (tmp_path / "o.mp4").exists()



def test_render_says_an_empty_hdf5_holds_no_track_and_counts_one_frame_in_the_singular(frames_folder, tmp_path):
    """An HDF5 file of no track (a header-only CSV written back) was said to be 'a header only', CSV wording, and a
    one-frame input 'has 96x64 px, 1 frames'."""
    import condtrack_cli as ct
    from condtrack_cli.io.write import csv_text

    csv, h5, out = tmp_path / "t.csv", tmp_path / "t.h5", tmp_path / "o.mp4"
    csv.write_text(csv_text(make_tracks()).splitlines()[0] + "\n")
    ct.read_tracks(csv).to_hdf5(h5)
    result = CliRunner().invoke(cli, ["render", str(h5), str(frames_folder), "-o", str(out)])
    assert result.exit_code == 0, result.output
    assert f"warning: {h5} holds no track (0 frames): no point to show on {frames_folder}" in result.stderr
    for path in sorted(frames_folder.iterdir())[1:]:
        path.unlink()
    result = CliRunner().invoke(cli, ["render", str(write_h5(h5)), str(frames_folder), "-o", str(out)])
    assert str(result.exception).endswith(f"but {frames_folder} has 96x64 px, 1 frame")
    with pytest.raises(CondtrackError, match="the input has 1 frame, the tracks 8$"):
        render_overlay(make_tracks(), [np.zeros((HEIGHT, WIDTH), np.uint8)], out, 0.0)


def test_render_warns_about_a_csv_with_visible_positions_outside_the_frame(frames_folder, tmp_path):
    """Issue 28.9: a CSV holds no frame size; visible positions outside the input's frame say it is another input's."""
    from condtrack_cli.io.write import csv_text

    tracks = make_tracks()
    xy = tracks.xy.copy()
    xy[0, 6:, 0] = [WIDTH - 0.75, WIDTH + 10.0]  # inside the last pixel, then 10 px out
    for name, positions, warned in (("out.csv", xy, True), ("in.csv", tracks.xy, False)):
        csv = tmp_path / name
        csv.write_text(csv_text(Tracks(tracks.queries, positions, tracks.cov, tracks.dof, tracks.visible, tracks.method,
                                       tracks.z, tracks.R)))
        result = CliRunner().invoke(cli, ["render", str(csv), str(frames_folder), "-o", str(tmp_path / "o.mp4")])
        assert result.exit_code == 0, result.output
        message = f"{csv} has 1 visible position(s) outside the 96x64 frame of {frames_folder}: was it tracked on"
        assert (message in result.stderr) == warned, result.stderr


def test_info_prints_what_the_file_holds(tmp_path):
    h5 = write_h5(tmp_path / "t.h5")
    result = CliRunner().invoke(info_command, [str(h5)])
    assert result.exit_code == 0, result.output
    out = result.output
    assert f"schema version:    {SCHEMA_VERSION}" in out
    assert "frame size:        96 x 64 px" in out and "frames:            8" in out
    assert "points:            4 (stk 2, clf 2)" in out
    visible_rows = 8 + 8 + 8 + 6
    assert f"{(visible_rows - 3) / visible_rows:.1%} of {visible_rows} rows" in out
    assert "query frames:      0 .. 2" in out
    assert "distribution:      Student-t per row, dof 4 .. 6 (median 5) on 53.3% of rows, Gaussian elsewhere" in out
    assert "measurements:      stored" in out and "particles:         not stored" in out
    assert "method:            clf" in out and "seed:              0" in out
    assert out.endswith("config (resolved):\n" + "".join(f"  {line}\n" for line in CONFIG.splitlines()))


def test_info_never_prints_a_dof_of_two():
    """The schema's nu is above 2: a smallest or median dof of 2.0022 reads '2.002', not '2' (issue 45's probe)."""
    line = _distribution(np.array([2.0022, 2.0022, 2.0022, 5.0, 2000.0, np.inf]))
    assert line == "Student-t per row, dof 2.002 .. 2e+03 (median 2.002) on 83.3% of rows, Gaussian elsewhere"
    assert _distribution(np.array([2.0 + 1e-9, 3.0])).startswith("Student-t per row, dof 2.000000001 .. 3 (median 2.5)")


def test_info_refuses_a_bad_file_naming_it(tmp_path):
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"nope")
    result = CliRunner().invoke(info_command, [str(bad)])
    assert isinstance(result.exception, CondtrackError) and "bad.h5" in str(result.exception)


@pytest.mark.parametrize("name", ["o.png", "o.h5", "o"])
def test_render_refuses_an_output_name_that_is_not_a_video(frames_folder, tmp_path, name):
    """The video is MPEG-4 in the container its extension names: -o x.png is refused, not an MPEG-4 named .png."""
    h5 = write_h5(tmp_path / "t.h5")
    result = CliRunner().invoke(render_command, [str(h5), str(frames_folder), "-o", str(tmp_path / name)])
    assert result.exit_code == 2 and f"Invalid value for '-o' / '--output': {tmp_path / name}:" in result.stderr
    assert ".mp4" in result.stderr  # issue 47.7: a bad value of -o, a usage error
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames", "t.h5"]


def test_render_checks_every_output_folder_before_work(frames_folder, tmp_path):
    """/proc is a folder that even root cannot create files in: refused before the video is written."""
    h5 = write_h5(tmp_path / "t.h5")
    result = CliRunner().invoke(render_command, [
        str(h5), str(frames_folder), "-o", str(tmp_path / "o.mp4"), "--contact-sheet", "/proc/s.png",
    ])
    assert isinstance(result.exception, CondtrackError) and "/proc/s.png" in str(result.exception)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames", "t.h5"]


def _changed(overlay, k, frame) -> np.ndarray:
    """(H, W) bool: pixels the overlay changed on frame ``k``."""
    return np.abs(overlay.draw(k, frame).astype(int) - cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR).astype(int)).max(-1) > 0


def _legend_bottom(changed: np.ndarray) -> int:
    """The last row of the legend (its darkened boxes start at column 2)."""
    return int(np.flatnonzero(changed[:, 2]).max())


def test_overlay_points_keeps_the_points_that_move_most(frames_folder):
    """Point 0 moves 10.5 px over the clip, point 2 3.5 px, points 1 and 3 not at all."""
    tracks, raw = make_tracks(), raw_frames(frames_folder)
    assert render.most_moving(tracks.xy, 2).tolist() == [True, False, True, False]
    one = render.Overlay(tracks, trail=1, style=render.OverlayStyle(points=1))
    changed = _changed(one, 4, raw[4])
    assert changed[20, 26] and not changed[50, 38] and not changed[40, 70]  # point 0's dot; not 2's, not 1's X
    assert one.methods == [2]  # the legend names clf alone: one row less than with every point
    assert _legend_bottom(changed) < _legend_bottom(_changed(render.Overlay(tracks, trail=1), 4, raw[4]))


def test_ellipses_all_visible_or_none(frames_folder):
    tracks, raw = make_tracks(), raw_frames(frames_folder)
    tracks.visible[3, 4] = False  # point 3 hidden on frame 4 with a finite covariance
    ring = (15, 80 + 7)  # on point 3's ellipse, 7.3 px right of it
    drawn = {mode: _changed(render.Overlay(tracks, style=render.OverlayStyle(ellipses=mode)), k, raw[k])
             for mode in ("all", "visible", "none") for k in (2,)}
    assert drawn["all"][ring] and drawn["visible"][ring] and not drawn["none"][ring]  # visible on frame 2
    hidden = {mode: _changed(render.Overlay(tracks, style=render.OverlayStyle(ellipses=mode)), 4, raw[4])
              for mode in ("all", "visible")}
    assert hidden["all"][ring] and not hidden["visible"][ring] and hidden["visible"][15, 80]  # the X stays
    with pytest.raises(ValueError, match="ellipses must be"):
        render.Overlay(tracks, style=render.OverlayStyle(ellipses="some"))


def test_an_ellipse_over_the_cap_is_a_diamond_named_in_the_legend(frames_folder):
    tracks, raw = make_tracks(), raw_frames(frames_folder)
    """Point 3's ellipse is 7.3 x 2.4 px (semi-axes) around (80.25, 15.5); the diamond reaches 6 px each way."""
    drawn = _changed(render.Overlay(tracks), 2, raw[2])
    capped = _changed(render.Overlay(tracks, style=render.OverlayStyle(ellipse_cap=5.0)), 2, raw[2])
    assert drawn[15, 72] and not drawn[10, 80]  # the ellipse's left end; nothing 5.5 px above the point
    assert capped[10, 80] and not capped[15, 72]  # the diamond's top corner; no ellipse
    assert _legend_bottom(capped) > _legend_bottom(drawn)  # the legend says what the diamond means
    tracks.cov[0] = [[1e4, 0.0], [0.0, 1e4]]  # point 0: a 245 px ellipse, over half the frame's diagonal
    huge = _changed(render.Overlay(tracks), 2, np.full((200, 300), 128, np.uint8))  # cap: 180 px
    assert huge[14, 23] and not huge[80:].any()  # its diamond; no outline, no legend below row 80


def test_overlay_options_on_track_and_render(frames_folder, tmp_path):
    h5 = write_h5(tmp_path / "t.h5")
    result = CliRunner().invoke(render_command, [
        str(h5), str(frames_folder), "-o", str(tmp_path / "o.mp4"), "--overlay-points", "2", "--ellipses", "visible",
        "--ellipse-cap", "20"])
    assert result.exit_code == 0, result.output
    capture = cv2.VideoCapture(str(tmp_path / "o.mp4"))
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == N_FRAMES
    capture.release()
    overlay, sample = tmp_path / "t.mp4", SAMPLES / "occlusion"
    result = CliRunner().invoke(cli, ["track", str(sample), "-p", str(sample / "queries.csv"), "-m", "stk", "-o",
                                      str(tmp_path / "t.csv"), "--overlay", str(overlay), "--overlay-points", "3",
                                      "--ellipses", "none", "-q"])
    assert result.exit_code == 0, result.output
    capture = cv2.VideoCapture(str(overlay))
    assert int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) == 30
    capture.release()
    refused = CliRunner().invoke(cli, ["track", str(frames_folder), "-o", str(tmp_path / "r.csv"), "--ellipses", "none"])
    assert refused.exit_code == 2 and "--ellipses: an overlay option (give --overlay OUT.mp4)" in refused.stderr
    assert not (tmp_path / "r.csv").exists()
    bad = CliRunner().invoke(render_command, [str(h5), str(frames_folder), "-o", str(tmp_path / "b.mp4"),
                                              "--overlay-points", "0"])
    assert bad.exit_code == 2 and "--overlay-points" in bad.output and not (tmp_path / "b.mp4").exists()


def test_a_position_far_off_the_frame_is_left_out_of_the_drawing(frames_folder):
    """A row at x = 1e12 (a hand-edited file, a point extrapolated far away) overflowed cv2's int32 fixed point:
    numpy's 'invalid value encountered in cast' warning and a wrapped-around mark or trail; the marks and segments
    reaching beyond FARTHEST_PX are now not drawn: frame 4 is drawn as if point 2 had no state there."""
    tracks, raw = make_tracks(), raw_frames(frames_folder)
    particles = np.full((4, N_FRAMES, 2, 2), np.nan)
    particles[1, 4] = [[60.0, 58.0], [1e30, 58.0]]
    far, gone = make_tracks(), make_tracks()
    far.xy[2, 4] = [1e12, 50.0]
    gone.xy[2, 4] = np.nan
    for k in (4, 5):  # the point's mark on frame 4, the trail segments from it on frames 4 and 5
        drawn = render.Overlay(far, trail=3, particles=particles).draw(k, raw[k])
        np.testing.assert_array_equal(drawn, render.Overlay(gone, trail=3, particles=particles).draw(k, raw[k]))
    assert (render.Overlay(tracks, particles=particles).draw(4, raw[4])[58, 60] == (render.PALETTE["cnlf"] + 255) // 2).all()
