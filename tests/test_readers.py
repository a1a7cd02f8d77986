"""Frame readers: folders and videos give the same frames, natural sort, conversions, bad inputs; the reader thread."""

from __future__ import annotations

import threading
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from condtrack_cli.cli import cli
from condtrack_cli.errors import CondtrackError, CondtrackWarning
from condtrack_cli.frames.prefetch import Prefetched
from condtrack_cli.frames.readers import FrameSettings, natural_key, open_frames, to_gray8


def _frames(n=5, shape=(48, 64)):
    rng = np.random.default_rng(7)
    return [rng.integers(0, 256, shape, dtype=np.uint8) for _ in range(n)]


@pytest.fixture
def folder_and_video(tmp_path) -> tuple[list[np.ndarray], Path, Path]:
    """Five random 64 x 48 frames, written as a folder of PNGs and as a lossless (FFV1) video."""
    frames = _frames()
    folder = tmp_path / "seq"
    folder.mkdir()
    for k, image in enumerate(frames):
        cv2.imwrite(str(folder / f"frame{k}.png"), image)
    video = tmp_path / "seq.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"FFV1"), 10, (64, 48), isColor=False)
    for image in frames:
        writer.write(image)
    writer.release()
    return frames, folder, video


def test_folder_and_lossless_video_give_the_same_frames(folder_and_video):
    frames, folder, video = folder_and_video
    from_folder = open_frames(FrameSettings(), folder)
    from_video = open_frames(FrameSettings(), video)
    assert from_folder.info.n_frames == from_video.info.n_frames == 5
    assert (from_video.info.width, from_video.info.height) == (64, 48)
    for a, b, truth in zip(from_folder, from_video, frames):
        np.testing.assert_array_equal(a, truth)
        np.testing.assert_array_equal(b, truth)
    np.testing.assert_array_equal(from_video.read(3), frames[3])


def test_natural_sort(tmp_path):
    names = ["frame10.png", "frame2.png", "frame1.png"]
    assert sorted(names, key=natural_key) == ["frame1.png", "frame2.png", "frame10.png"]
    assert natural_key("1\u00b22.png") == ["", 1, "\u00b2", 2, ".png"]  # "²": str.isdigit's, not int()'s (a traceback)
    for k, name in enumerate(names):
        cv2.imwrite(str(tmp_path / name), np.full((8, 8), 10 * k, np.uint8))
    source = open_frames(FrameSettings(), tmp_path)
    assert [int(f[0, 0]) for f in source] == [20, 10, 0]


def test_names_equal_in_natural_order_are_read_in_one_order_whatever_the_folder_lists(tmp_path, monkeypatch):
    """frame1 and frame01 (or F1 and f1) have the same natural key: they were read in the order the file system
    listed them, so a copy of the folder could give other tracks; now the name breaks the tie."""
    names = ["frame1.png", "frame01.png", "F2.png", "f2.png"]
    for k, name in enumerate(names):
        cv2.imwrite(str(tmp_path / name), np.full((8, 8), 10 * k, np.uint8))
    listed = sorted(tmp_path.iterdir())
    orders = []
    for listing in (listed, listed[::-1]):
        monkeypatch.setattr(Path, "iterdir", lambda self, listing=listing: iter(listing))
        orders.append([p.name for p in open_frames(FrameSettings(), tmp_path).paths])
    assert orders[0] == orders[1] == ["F2.png", "f2.png", "frame01.png", "frame1.png"]


def test_sixteen_bit_and_colour_conversion():
    sixteen = np.array([[0, 257, 65535, 385]], np.uint16)
    np.testing.assert_array_equal(to_gray8(sixteen, "x"), [[0, 1, 255, 1]])
    colour = np.zeros((1, 1, 3), np.uint8)
    colour[0, 0] = (255, 0, 0)  # pure blue in BGR
    assert to_gray8(colour, "x")[0, 0] == round(0.114 * 255)
    with pytest.raises(CondtrackError, match="unsupported pixel type float32"):
        to_gray8(np.zeros((2, 2), np.float32), "frame 0")


@pytest.mark.filterwarnings("ignore:.*queries are untrackable:condtrack_cli.errors.CondtrackWarning")  # incidental queries (issue 29)
def test_frames_of_a_twelve_bit_camera_are_read_at_their_bit_depth(shifted_folder, tmp_path):
    """A 12-bit camera's frames in 16-bit files (values 0..4095) were read as value / 257: 17 grey levels at most,
    without a word. They now get a warning naming frames.bit_depth, and read at 12 bits they are the 8-bit frames they
    were made from, so the same queries give the same tracks."""
    import condtrack_cli as ct

    folder, _ = shifted_folder
    twelve = tmp_path / "twelve"
    twelve.mkdir()
    for path in sorted(folder.iterdir()):
        grey = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        cv2.imwrite(str(twelve / path.name), np.round(grey * (4095 / 255)).astype(np.uint16))
    with pytest.warns(CondtrackWarning, match=r"16-bit frames whose values stay below 4096 \(frame 0: at most \d+\) are "
                                              r"read as value / 257, at most \d+ grey levels; .* want frames.bit_depth"):
        open_frames(FrameSettings(), twelve)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        frames = list(open_frames(FrameSettings(bit_depth=12), twelve))
    assert all(np.array_equal(a, b) for a, b in zip(frames, open_frames(FrameSettings(), folder), strict=True))
    queries = np.array([[0, 120.0, 100.0], [0, 200.0, 150.0]])
    expected = ct.track(folder, queries=queries, method="stk")
    tracked = ct.track(twelve, queries=queries, method="stk", config={"frames": {"bit_depth": 12}})
    assert tracked.xy.tolist() == expected.xy.tolist()
    tracked.to_hdf5(tmp_path / "t.h5")  # render reads the frames as they were tracked: no warning
    drawn = CliRunner().invoke(cli, ["render", str(tmp_path / "t.h5"), str(twelve), "-o", str(tmp_path / "o.mp4")])
    assert drawn.exit_code == 0 and "16-bit" not in drawn.output, drawn.output


def test_sixteen_bit_frames_above_the_bit_depth_get_a_warning(tmp_path):
    """frames.bit_depth below the frames' own (12 on a 16-bit camera's frames) read every value above 4095 as white
    (255) without a word: most of a bright frame saturated and its points lost. The first frame's values above the
    depth now get a warning with their share and the depth that reads them; frames within it get none."""
    image = np.linspace(0, 65535, 48 * 64).reshape(48, 64).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "0.png"), image)
    with pytest.warns(CondtrackWarning, match=rf"^{tmp_path}: frames.bit_depth is 12, but frame 0 has values up to "
                                              r"65535, above 4095: 94% of its pixels are read as white \(255\); "
                                              r"frames.bit_depth 16 reads them$"):
        open_frames(FrameSettings(bit_depth=12), tmp_path)
    cv2.imwrite(str(tmp_path / "0.png"), image >> 4)  # 0..4095
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert open_frames(FrameSettings(bit_depth=12), tmp_path).read(0).max() == 255


@pytest.mark.filterwarnings("ignore:.*queries are untrackable:condtrack_cli.errors.CondtrackWarning")  # incidental queries (issue 29)
def test_a_multi_page_tiff_is_a_sequence_of_its_pages(shifted_folder, tmp_path, monkeypatch):
    """A microscope's stack given as the input was opened as a video: one frame (the first page), and the queries
    after it refused. Its pages are now the frames, decoded a few at a time (here 4, across a chunk's end), the same
    frames and tracks as the folder of its pages; a page of another size is refused naming it."""
    import condtrack_cli as ct
    from condtrack_cli.frames import readers

    folder, _ = shifted_folder
    frames = list(open_frames(FrameSettings(), folder))
    stack = tmp_path / "stack.tif"
    assert cv2.imwritemulti(str(stack), frames)
    monkeypatch.setattr(readers, "STACK_CHUNK", 4)
    monkeypatch.setattr(readers, "STACK_CHUNK_BYTES", 0)  # 4 pages at a time, however small
    source = open_frames(FrameSettings(), stack)
    assert source.info.n_frames == len(frames) == 6 and source.info.input == str(stack)
    assert all(np.array_equal(a, b) for a, b in zip(source, frames, strict=True))
    assert np.array_equal(source.read(5), frames[5])
    queries = np.array([[0, 120.0, 100.0], [4, 200.0, 150.0]])
    expected = ct.track(folder, queries=queries, method="stk")
    assert ct.track(stack, queries=queries, method="stk").xy.tolist() == expected.xy.tolist()
    assert cv2.imwritemulti(str(stack), frames[:2] + [frames[2][:-1]])
    with pytest.raises(CondtrackError, match=rf"page 2 of {stack}: size 320x255 differs from the first page's 320x256"):
        list(open_frames(FrameSettings(), stack))
    with pytest.warns(CondtrackWarning, match=r"frame 0 \(stack.tif\) is a TIFF of 3 pages, of which a frame folder reads "
                                              "the first; a stack is read page by page when it is the input itself"):
        open_frames(FrameSettings(), tmp_path)  # the stack in a folder: a frame


def test_a_stack_of_small_pages_is_decoded_in_few_calls(tmp_path, monkeypatch):
    """Each decode of a stack walks its page directory from the start, small pages as slowly as large ones: 16 pages
    at a time, 3000 pages of 80 x 60 took 64 s to read (1 s at once). A stack's iteration now decodes as many pages
    as make readers.STACK_CHUNK_BYTES (at least STACK_CHUNK): here the 40 pages in one call, the same frames."""
    from condtrack_cli.frames import readers

    frames = _frames(40, (6, 8))
    stack = tmp_path / "stack.tif"
    assert cv2.imwritemulti(str(stack), frames)
    source = open_frames(FrameSettings(), stack)
    calls, decode = [], cv2.imreadmulti
    monkeypatch.setattr(readers.cv2, "imreadmulti", lambda *args, **kwargs: calls.append(args) or decode(*args, **kwargs))
    assert all(np.array_equal(a, b) for a, b in zip(source, frames, strict=True))
    assert [args[1:] for args in calls] == [(0, 40)]


@pytest.mark.parametrize("cut", ["in a page directory", "before the last page's directory"])
def test_a_tiff_stack_cut_short_is_refused(tmp_path, cut):
    """A stack cut short (a copy or download that stopped) was read up to the cut without a word: its decoder stops
    at the first page directory past the end, so half a 6-page stack was tracked as a 3-page clip. It is refused,
    naming the file and the last whole page, before any frame is read; the whole file is read as before."""
    frames = _frames(6)
    whole = tmp_path / "whole.tif"
    assert cv2.imwritemulti(str(whole), frames)
    assert open_frames(FrameSettings(), whole).info.n_frames == 6
    data = whole.read_bytes()
    stack = tmp_path / "stack.tif"
    stack.write_bytes(data[: len(data) // 2] if cut == "in a page directory" else data[:-20])
    assert 0 < cv2.imcount(str(stack)) < 6  # what the decoder alone finds
    last = 4 if cut == "before the last page's directory" else cv2.imcount(str(stack)) - 1
    with pytest.raises(CondtrackError, match=rf"^{stack}: the TIFF file is cut short: its chain of page directories "
                                             rf"goes on past the end of the file after page {last} "):
        open_frames(FrameSettings(), stack)


def test_info_of_a_stack_s_tracks_does_not_call_it_a_folder(shifted_folder, tmp_path):
    """A stack has no frame rate, as a folder has none; info printed 'fps: 0 (none: a folder of frames)' for it."""
    import condtrack_cli as ct

    folder, _ = shifted_folder
    stack = tmp_path / "stack.tif"
    assert cv2.imwritemulti(str(stack), list(open_frames(FrameSettings(), folder)))
    ct.track(stack, method="stk").to_hdf5(tmp_path / "t.h5")
    result = CliRunner().invoke(cli, ["info", str(tmp_path / "t.h5")])
    assert result.exit_code == 0, result.output
    assert "fps:               0 (none: a folder of frames or a multi-page TIFF)\n" in result.output


def test_stages_names_the_multi_page_tiff_among_the_inputs():
    """`condtrack stages` summed the frames stage up as 'a folder of images or a video file', after stacks were read."""
    result = CliRunner().invoke(cli, ["stages"])
    assert result.exit_code == 0
    assert "  auto         a folder of images, a multi-page TIFF or a video file, chosen by the path\n" in result.output


def test_sixteen_bit_colour_file(tmp_path):
    image = np.zeros((4, 4, 3), np.uint16)
    image[..., 1] = 65535  # green
    cv2.imwrite(str(tmp_path / "a.tif"), image)
    (frame,) = list(open_frames(FrameSettings(), tmp_path))
    assert frame.dtype == np.uint8 and frame.shape == (4, 4)
    assert frame[0, 0] == round(0.587 * 255)


def test_bad_folders(tmp_path):
    with pytest.raises(CondtrackError, match="no such file"):
        open_frames(FrameSettings(), tmp_path / "missing")
    with pytest.raises(CondtrackError, match="no image files"):
        open_frames(FrameSettings(), tmp_path)
    cv2.imwrite(str(tmp_path / "0.png"), np.zeros((8, 8), np.uint8))
    cv2.imwrite(str(tmp_path / "1.png"), np.zeros((8, 9), np.uint8))
    (tmp_path / "2.png").write_bytes(b"\x89PNG truncated")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(CondtrackError, match="notes.txt.*not an image"):
        open_frames(FrameSettings(non_image_files="refuse"), tmp_path)
    with pytest.warns(CondtrackWarning, match="skipping 1 non-image file"):
        source = open_frames(FrameSettings(), tmp_path)
    frames = iter(source)
    next(frames)
    with pytest.raises(CondtrackError, match=r"frame 1 .*size 9x8 differs"):
        next(frames)
    with pytest.raises(CondtrackError, match=r"frame 2 .*not a readable image"):
        source.read(2)


def test_a_damaged_png_gives_the_error_alone_without_opencv_s_log_lines(tmp_path, capfd):
    """A frame whose PNG signature is followed by garbage printed OpenCV's '[ WARN:0@0.067] global grfmt_png.cpp:834
    read_chunk ...' and '[ERROR:0@0.068] ... IHDR chunk shall be first' before condtrack's one Error line; the decoder
    is now silent while a frame is read, and OpenCV's log level is as it was after."""
    cv2.imwrite(str(tmp_path / "0.png"), _frames(1)[0])
    (tmp_path / "1.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
    level = cv2.utils.logging.getLogLevel()
    source = open_frames(FrameSettings(), tmp_path)
    with pytest.raises(CondtrackError, match=r"^frame 1 \(.*1.png\): not a readable image$"):
        source.read(1)
    assert capfd.readouterr().err == "" and cv2.utils.logging.getLogLevel() == level


def test_a_truncated_video_warns_that_its_container_lists_more_frames(folder_and_video, tmp_path):
    """Decoding stopped at the cut looked like the clip's end; the complete file gives no warning."""
    frames, _, video = folder_and_video
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert open_frames(FrameSettings(), video).info.n_frames == 5
    cut = tmp_path / "cut.avi"
    cut.write_bytes(video.read_bytes()[: int(video.stat().st_size * 0.6)])
    with pytest.warns(CondtrackWarning, match=r"cut.avi: decoding stopped after [1-4] of the 5 frames its container"):
        source = open_frames(FrameSettings(), cut)
    assert 1 <= source.info.n_frames < 5
    np.testing.assert_array_equal(source.read(0), frames[0])


def test_unreadable_video(tmp_path):
    bogus = tmp_path / "clip.mp4"
    bogus.write_bytes(b"not a video at all")
    with pytest.raises(CondtrackError, match="clip.mp4: not a readable video"):
        open_frames(FrameSettings(), bogus)


def test_a_dangling_symlink_frame_is_an_error_naming_it(tmp_path):
    """Dropping it would shift every later frame number (issue 16 item 7)."""
    image = np.zeros((8, 8), np.uint8)
    for k in (0, 2):
        cv2.imwrite(str(tmp_path / f"f{k}.png"), image)
    (tmp_path / "f1.png").symlink_to(tmp_path / "gone.png")
    with pytest.raises(CondtrackError, match=r"f1\.png: a broken symbolic link"):
        open_frames(FrameSettings(), tmp_path)


def _readers() -> list[threading.Thread]:
    return [thread for thread in threading.enumerate() if thread.name == "condtrack-frame-reader"]


@pytest.mark.parametrize("kind", ["folder", "video"])
def test_the_reader_thread_gives_the_frames_of_the_plain_reader(folder_and_video, kind):
    frames, folder, video = folder_and_video
    source = open_frames(FrameSettings(), folder if kind == "folder" else video)
    expected = list(source)
    with Prefetched(source) as prefetched:
        got = list(prefetched)
    assert len(got) == len(expected) == len(frames)
    for a, b in zip(got, expected):
        np.testing.assert_array_equal(a, b)
    assert not _readers()


def test_a_bad_frame_raises_the_plain_readers_error_in_the_consumer(tmp_path):
    image = np.zeros((8, 8), np.uint8)
    for k in (0, 1, 3):
        cv2.imwrite(str(tmp_path / f"{k}.png"), image)
    (tmp_path / "2.png").write_bytes(b"\x89PNG truncated")
    source = open_frames(FrameSettings(), tmp_path)
    with pytest.raises(CondtrackError) as plain:
        list(source)
    assert "frame 2" in str(plain.value) and "not a readable image" in str(plain.value)
    got = []
    with pytest.raises(CondtrackError) as ahead, Prefetched(source) as prefetched:
        for frame in prefetched:
            got.append(frame)
    assert str(ahead.value) == str(plain.value)
    assert len(got) == 2  # the frames before the bad one arrived first
    assert not _readers()


def test_a_consumer_stopping_early_leaves_no_thread_and_closes_the_frames():
    produced, closed = [], []

    def endless():
        try:
            while True:
                produced.append(len(produced))
                yield produced[-1]
        finally:
            closed.append(threading.current_thread().name)

    before = set(threading.enumerate())
    with Prefetched(endless(), depth=2) as prefetched:
        assert [next(prefetched), next(prefetched)] == [0, 1]
        assert len(_readers()) == 1
    assert set(threading.enumerate()) == before
    assert closed == ["condtrack-frame-reader"]  # the generator was closed in its own thread
    assert len(produced) <= 2 + 2 + 1  # read ahead by at most the queue's depth and the item in hand

    with pytest.raises(ZeroDivisionError), Prefetched(endless()) as prefetched:  # the consumer fails mid-way
        next(prefetched) / 0
    assert set(threading.enumerate()) == before


def test_known_sidecar_files_are_skipped_without_a_warning(tmp_path):
    """Issue 28.21: the shipped samples (frames beside queries.csv, tracks.csv, labels.csv, scene.json) read quietly;
    any other file still gets the warning, and is still refused with non_image_files: refuse."""
    import shutil

    from conftest import SAMPLES

    folder = tmp_path / "ring"
    shutil.copytree(SAMPLES / "ring", folder)
    assert {"queries.csv", "tracks.csv", "labels.csv", "scene.json"} <= {p.name for p in folder.iterdir()}
    assert open_frames(FrameSettings(non_image_files="refuse"), folder).info.n_frames == 30  # warnings are errors
    (folder / "notes.txt").write_text("hello")
    with pytest.warns(CondtrackWarning) as seen:
        open_frames(FrameSettings(), folder)
    assert [str(w.message) for w in seen] == [f"{folder}: skipping 1 non-image file(s), e.g. 'notes.txt'"]
