"""Read a frame folder, a multi-page TIFF or a video as a stream of 8-bit grey frames.

Conversion to 8-bit grey, the same for every input:
- colour (BGR or BGRA) -> grey with OpenCV's weights 0.299 R + 0.587 G + 0.114 B;
- 16-bit -> 8-bit by value 255 / (2^``bit_depth`` - 1), rounded, at most 255 (``bit_depth`` 16, the default:
  value / 257, full range 0..65535 -> 0..255; 12 for a 12-bit camera's frames, 0..4095 -> 0..255); a folder whose
  first frame is 16-bit with every value below 4096 read at 16 bits gets a warning (at most 16 grey levels), as
  does one with values above 2^``bit_depth`` - 1 (read as white);
- 8-bit grey is kept as it is; any other pixel type is refused.

A multi-page TIFF given as the input (a microscope's stack, ``STACK_EXTENSIONS``) is a sequence of its pages,
read a few pages at a time; one cut short (its chain of page directories going on past its end) is refused.
A folder is read in natural sort order (``frame2`` before ``frame10``). Files
whose extension is not an image extension are skipped with one warning line on
stderr (``frames.non_image_files: refuse`` makes them an error instead), but for
the known sidecar files (``SIDECAR_FILES``: a sample's queries, ground truth,
labels and scene description, a README), skipped silently.
"""

from __future__ import annotations

import contextlib
import re
import struct
from pathlib import Path
from typing import Iterator, Literal

import cv2
import numpy as np
from pydantic import Field

from condtrack_cli.errors import CondtrackError, MissingInput, warn
from condtrack_cli.settings import StageSettings
from condtrack_cli.types import SequenceInfo

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm", ".ppm")
#: Suffixes of an input file read as a stack of frames, one per page (a multi-page TIFF), not as a video.
STACK_EXTENSIONS = (".tif", ".tiff")

#: Files a frame folder may hold beside its frames, skipped without a word (``condtrack synth`` writes the first four).
SIDECAR_FILES = ("queries.csv", "tracks.csv", "labels.csv", "scene.json", "README.md")


class FrameSettings(StageSettings):
    non_image_files: Literal["skip", "refuse"] = Field(
        "skip", description="files in a frame folder that are not images: skip (warn once) or refuse"
    )
    bit_depth: int = Field(
        16, ge=8, le=16,
        description="significant bits of 16-bit frames (12 for a 12-bit camera's): a value v is read as the grey level "
                    "round(255 v / (2^bit_depth - 1)), at most 255; 8-bit frames are read as they are",
    )


#: A 16-bit first frame whose values all stay below this, read at 16 bits, gets a warning (``FolderSource``).
NARROW_16BIT = 4096


def natural_key(name: str) -> list:
    """Sort key putting ``frame2`` before ``frame10``."""
    return [int(part) if part.isdecimal() else part.lower() for part in re.split(r"(\d+)", name)]


def to_gray8(image: np.ndarray, where: str, bit_depth: int = 16) -> np.ndarray:
    """(H, W[, C]) uint8/uint16 -> (H, W) uint8 grey, as documented above (``bit_depth``: of 16-bit images)."""
    if image.dtype == np.uint16:
        top = (1 << bit_depth) - 1  # round(255 v / top) in integers (at 16 bits: round(v / 257), 510 v + top < 2^32)
        image = np.minimum((image.astype(np.uint32) * 510 + top) // (2 * top), 255).astype(np.uint8)
    elif image.dtype != np.uint8:
        raise CondtrackError(f"{where}: unsupported pixel type {image.dtype} (8- or 16-bit images only)")
    if image.ndim == 3:
        code = {3: cv2.COLOR_BGR2GRAY, 4: cv2.COLOR_BGRA2GRAY}.get(image.shape[2])
        if code is None:
            raise CondtrackError(f"{where}: unsupported number of channels {image.shape[2]}")
        image = cv2.cvtColor(image, code)
    if image.ndim != 2:
        raise CondtrackError(f"{where}: unsupported image shape {image.shape}")
    return np.ascontiguousarray(image)


#: Suffixes of the JPEG files whose end :func:`cut_short` checks.
JPEG_EXTENSIONS = (".jpg", ".jpeg")
#: Bytes at the end of a JPEG file in which :func:`cut_short` looks for the end-of-image marker (a camera may append
#: its own data after it).
JPEG_TAIL = 65536


def cut_short(path: Path) -> bool:
    """Whether ``path`` is a JPEG file (it starts with the start-of-image marker FF D8) with no end-of-image marker
    (FF D9) in its last ``JPEG_TAIL`` bytes: a copy or a download cut short, which libjpeg decodes anyway, the
    missing rows grey (with only a line on stderr). A file that cannot be read is left to the decoder."""
    try:
        with path.open("rb") as handle:
            if handle.read(2) != b"\xff\xd8":
                return False
            handle.seek(max(handle.seek(0, 2) - JPEG_TAIL, 0))
            return b"\xff\xd9" not in handle.read()
    except OSError:
        return False


@contextlib.contextmanager
def opencv_log(level: int) -> Iterator[None]:
    """OpenCV's log at ``level`` (``cv2.utils.logging.LOG_LEVEL_*``) during the block, its former level after."""
    former = cv2.utils.logging.getLogLevel()
    cv2.utils.logging.setLogLevel(level)
    try:
        yield
    finally:
        cv2.utils.logging.setLogLevel(former)


def warn_if_narrow(raw: np.ndarray, where: Path, bit_depth: int) -> None:
    """A warning when the first frame ``raw`` of ``where`` is 16-bit with every value below ``NARROW_16BIT`` and read
    at 16 bits, or with values above ``bit_depth``'s largest, which are read as white (module docstring)."""
    if raw.dtype != np.uint16:
        return
    top = (1 << bit_depth) - 1
    if bit_depth == 16 and raw.max() < NARROW_16BIT:
        warn(f"{where}: 16-bit frames whose values stay below {NARROW_16BIT} (frame 0: at most {raw.max()}) are "
             f"read as value / 257, at most {round(raw.max() / 257) + 1} grey levels; frames of a camera with "
             "fewer bits want frames.bit_depth (12 for a 12-bit one)")
    elif raw.max() > top:
        warn(f"{where}: frames.bit_depth is {bit_depth}, but frame 0 has values up to {raw.max()}, above "
             f"{top}: {(raw > top).mean():.0%} of its pixels are read as white (255); frames.bit_depth "
             f"{int(raw.max()).bit_length()} reads them")


def of_first_size(image: np.ndarray, info: SequenceInfo, where: str, first: str) -> np.ndarray:
    """``image`` (H, W) when it has the sequence's size (``info``, the first frame's), else a CondtrackError naming
    ``where`` and ``first`` (how the first frame is called there)."""
    if image.shape != (info.height, info.width):
        raise CondtrackError(f"{where}: size {image.shape[1]}x{image.shape[0]} differs from {first} "
                             f"{info.width}x{info.height}")
    return image


class FolderSource:
    """A folder of image files, one frame per file."""

    def __init__(self, folder: Path, settings: FrameSettings):
        entries = [p for p in folder.iterdir() if not p.name.startswith(".")]
        broken = [p for p in entries if p.is_symlink() and not p.exists()]
        if broken:  # skipping it would shift every later frame number
            raise CondtrackError(f"{broken[0]}: a broken symbolic link (its target '{broken[0].readlink()}' does not exist)")
        # the name itself breaks a tie (frame1 and frame01, F1 and f1), else their order would be the folder listing's
        names = sorted((p.name for p in entries if p.is_file()), key=lambda name: (natural_key(name), name))
        images = [n for n in names if Path(n).suffix.lower() in IMAGE_EXTENSIONS]
        others = [n for n in names if Path(n).suffix.lower() not in IMAGE_EXTENSIONS and n not in SIDECAR_FILES]
        if others and settings.non_image_files == "refuse":
            raise CondtrackError(f"{folder}: '{others[0]}' is not an image file (frames.non_image_files: refuse)")
        if not images:
            raise CondtrackError(f"{folder}: no image files ({', '.join(IMAGE_EXTENSIONS)}) in the folder")
        if others:
            warn(f"{folder}: skipping {len(others)} non-image file(s), e.g. '{others[0]}'")
        self.paths, self.bit_depth = [folder / n for n in images], settings.bit_depth
        raw = self._decoded(0)
        warn_if_narrow(raw, folder, self.bit_depth)
        if self.paths[0].suffix.lower() in STACK_EXTENSIONS and (pages := cv2.imcount(str(self.paths[0]))) > 1:
            warn(f"{folder}: frame 0 ({self.paths[0].name}) is a TIFF of {pages} pages, of which a frame folder reads "
                 "the first; a stack is read page by page when it is the input itself")
        first = to_gray8(raw, f"frame 0 ({self.paths[0]})", self.bit_depth)
        self.info = SequenceInfo(str(folder), first.shape[1], first.shape[0], len(self.paths), 0.0)

    def _decoded(self, index: int) -> np.ndarray:
        """The file of frame ``index`` as decoded (any depth and channels); CondtrackError naming it when unreadable."""
        path = self.paths[index]
        if path.suffix.lower() in JPEG_EXTENSIONS and cut_short(path):  # before libjpeg decodes it anyway
            raise CondtrackError(f"frame {index} ({path}): the JPEG file is cut short (no end-of-image marker in its "
                                 f"last {JPEG_TAIL // 1024} KiB); its decoder would fill the missing part with grey")
        with opencv_log(cv2.utils.logging.LOG_LEVEL_SILENT):  # a damaged file's decoder lines: the error names it
            raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise CondtrackError(f"frame {index} ({path}): not a readable image")
        return raw

    def read(self, index: int) -> np.ndarray:
        """Frame ``index`` as (H, W) uint8."""
        image = to_gray8(self._decoded(index), f"frame {index} ({self.paths[index]})", self.bit_depth)
        return of_first_size(image, self.info, f"frame {index} ({self.paths[index]})", "the first frame's")

    def __iter__(self) -> Iterator[np.ndarray]:
        for index in range(len(self.paths)):
            yield self.read(index)


def tiff_directories(path: Path) -> tuple[int, bool]:
    """(pages, cut): the number of whole page directories of the TIFF (or BigTIFF) file ``path``, found by walking
    their chain from the header, and whether the chain goes on past the end of the file (a copy or a download cut
    short, whose decoder reads the pages before the cut as if they were all). (0, False) for a file that is no TIFF
    or cannot be read, and at a directory met twice (a loop): left to the decoder."""
    try:
        with path.open("rb") as handle:
            head = handle.read(16)
            size = handle.seek(0, 2)
            order = {b"II": "<", b"MM": ">"}.get(head[:2])
            if order is None or len(head) < 8:
                return 0, False
            version = struct.unpack(order + "H", head[2:4])[0]
            if version == 42:
                count, entry, link = "H", 12, "I"  # classic TIFF: 2-byte entry count, 12-byte entries, 4-byte links
                offset = struct.unpack(order + "I", head[4:8])[0]
            elif version == 43 and len(head) == 16:
                count, entry, link = "Q", 20, "Q"  # BigTIFF
                offset = struct.unpack(order + "Q", head[8:16])[0]
            else:
                return 0, False
            count, link = struct.Struct(order + count), struct.Struct(order + link)  # the formats above, this file's order
            pages, seen = 0, set()
            while offset and offset not in seen:
                seen.add(offset)
                handle.seek(offset)
                raw = handle.read(count.size)
                if len(raw) < count.size:
                    return pages, True
                end = offset + count.size + count.unpack(raw)[0] * entry + link.size  # past the next directory's link
                if end > size:
                    return pages, True
                handle.seek(end - link.size)
                pages, offset = pages + 1, link.unpack(handle.read(link.size))[0]
            return (0, False) if offset else (pages, False)
    except OSError:
        return 0, False


#: Pages a stack's iteration decodes at a time, at least: each decode walks the file's page directory from its start,
#: so one page at a time takes time quadratic in the page count.
STACK_CHUNK = 16
#: Bytes of decoded pages a stack's iteration holds at a time, at most (beyond ``STACK_CHUNK`` pages): the walk costs
#: as much for a small page as for a large one, so a stack of small pages is decoded in larger chunks.
STACK_CHUNK_BYTES = 32 << 20


class StackSource:
    """A multi-page TIFF, one frame per page, decoded ``STACK_CHUNK`` pages at a time, or as many as make
    ``STACK_CHUNK_BYTES`` when more (pages of the first page's size)."""

    def __init__(self, path: Path, settings: FrameSettings):
        self.path, self.bit_depth = path, settings.bit_depth
        with opencv_log(cv2.utils.logging.LOG_LEVEL_SILENT):  # a damaged file's decoder lines: the error names it
            count = cv2.imcount(str(path))
        if count < 1:
            raise CondtrackError(f"{path}: not a readable TIFF (OpenCV found no page in it)")
        pages, cut = tiff_directories(path)
        if cut:  # its decoder stops at the cut without a word: the stack would end early
            raise CondtrackError(f"{path}: the TIFF file is cut short: its chain of page directories goes on past "
                                 f"the end of the file after page {pages - 1} (a copy or a download cut short?)")
        (raw,) = self._decoded(0, 1)
        warn_if_narrow(raw, path, self.bit_depth)
        first = to_gray8(raw, f"page 0 of {path}", self.bit_depth)
        self.info = SequenceInfo(str(path), first.shape[1], first.shape[0], count, 0.0)
        self.chunk = max(STACK_CHUNK, STACK_CHUNK_BYTES // raw.nbytes)

    def _decoded(self, start: int, count: int) -> list[np.ndarray]:
        """Pages ``start`` .. ``start + count - 1`` as decoded (any depth and channels); CondtrackError naming the
        first when they are unreadable."""
        with opencv_log(cv2.utils.logging.LOG_LEVEL_SILENT):
            ok, pages = cv2.imreadmulti(str(self.path), start, count, flags=cv2.IMREAD_UNCHANGED)
        if not ok or len(pages) != count:
            raise CondtrackError(f"page {start + len(pages) if ok else start} of {self.path}: not a readable image")
        return list(pages)

    def _gray(self, index: int, raw: np.ndarray) -> np.ndarray:
        """Page ``index``, decoded as ``raw``, as (H, W) uint8 (the first page's size)."""
        where = f"page {index} of {self.path}"
        return of_first_size(to_gray8(raw, where, self.bit_depth), self.info, where, "the first page's")

    def read(self, index: int) -> np.ndarray:
        """Frame ``index`` (page ``index``) as (H, W) uint8."""
        return self._gray(index, self._decoded(index, 1)[0])

    def __iter__(self) -> Iterator[np.ndarray]:
        for start in range(0, self.info.n_frames, self.chunk):
            pages = self._decoded(start, min(self.chunk, self.info.n_frames - start))
            for index, raw in enumerate(pages, start):
                yield self._gray(index, raw)


class VideoSource:
    """A video file read through OpenCV, decoded one frame at a time."""

    def __init__(self, path: Path):
        self.path = path
        capture = self._open()
        count = 0
        while capture.grab():
            count += 1
        fps = float(capture.get(cv2.CAP_PROP_FPS) or 0.0)
        listed = float(capture.get(cv2.CAP_PROP_FRAME_COUNT) or 0.0)  # the container's count (0: none)
        capture.release()
        if count == 0:
            raise CondtrackError(f"{path}: not a readable video (OpenCV decoded no frame)")
        if np.isfinite(listed) and listed > count:  # a decode error mid-stream looks like the end of the clip
            warn(f"{path}: decoding stopped after {count} of the {int(listed)} frames its container lists (a "
                 f"truncated or damaged file?); the {count} decoded are read")
        first = next(iter(self))
        self.info = SequenceInfo(str(path), first.shape[1], first.shape[0], count, fps if np.isfinite(fps) else 0.0)

    def _open(self) -> cv2.VideoCapture:
        capture = cv2.VideoCapture(str(self.path))
        if not capture.isOpened():
            raise CondtrackError(f"{self.path}: not a readable video (OpenCV could not open it)")
        return capture

    def __iter__(self) -> Iterator[np.ndarray]:
        capture = self._open()
        try:
            index = 0
            while True:
                ok, raw = capture.read()
                if not ok:
                    break
                yield to_gray8(raw, f"frame {index} of {self.path}")
                index += 1
        finally:
            capture.release()

    def read(self, index: int) -> np.ndarray:
        """Frame ``index`` (decodes from the start: videos are read sequentially)."""
        for position, image in enumerate(self):
            if position == index:
                return image
        raise CondtrackError(f"{self.path}: frame {index} is past the end")


def open_frames(settings: FrameSettings, path: str | Path) -> FolderSource | StackSource | VideoSource:
    """Open ``path`` as a frame source; CondtrackError naming the path otherwise."""
    path = Path(path)
    if not path.exists():
        raise MissingInput(f"{path}: no such file or folder")
    if path.is_dir():
        return FolderSource(path, settings)
    if path.is_fifo() or path.is_socket():  # OpenCV's open would block in C, deaf to Ctrl-C and SIGTERM
        raise CondtrackError(f"{path}: not a regular file (a {'named pipe' if path.is_fifo() else 'socket'}); "
                             "give a video file or a folder of frames")
    if path.suffix.lower() in STACK_EXTENSIONS:
        return StackSource(path, settings)
    return VideoSource(path)
