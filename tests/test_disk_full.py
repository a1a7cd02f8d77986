"""Issue 28.10: a full disk while writing the HDF5, the CSV, stdout or the overlay video gives one line
``Error: <file>: no space left on device``, exit 1, and no partial file."""

from __future__ import annotations

import contextlib
import errno
import pathlib
import subprocess
import sys

import pytest

from condtrack_cli.cli import main
from conftest import SAMPLES

SAMPLE = SAMPLES / "occlusion"
TRACK = ["track", str(SAMPLE), "-p", str(SAMPLE / "queries.csv"), "-m", "stk", "-q"]


def _no_space(*_args, **_kwargs):
    raise OSError(errno.ENOSPC, "No space left on device")


def _main(args: list[str], monkeypatch, capsys) -> tuple[int, str]:
    monkeypatch.setattr(sys, "argv", ["condtrack", *args])
    with pytest.raises(SystemExit) as stop:
        main()
    return stop.value.code, capsys.readouterr().err


@pytest.mark.parametrize("suffix, target", [(".h5", "condtrack_cli.io.write._dataset"),
                                            (".csv", "pathlib.Path.write_bytes")])
def test_a_full_disk_while_writing_the_tracks(tmp_path, monkeypatch, capsys, suffix, target):
    out = tmp_path / f"out{suffix}"
    monkeypatch.setattr(target, _no_space)
    assert _main([*TRACK, "-o", str(out)], monkeypatch, capsys) == (1, f"Error: {out}: no space left on device\n")
    assert not list(tmp_path.iterdir())


def test_a_full_disk_behind_stdout():
    with open("/dev/full", "w") as full:  # every write fails with ENOSPC
        result = subprocess.run([sys.executable, "-c", "from condtrack_cli.cli import main; main()", *TRACK],
                                stdout=full, stderr=subprocess.PIPE, text=True, timeout=120)
    assert (result.returncode, result.stderr) == (1, "Error: stdout: no space left on device\n")


@contextlib.contextmanager
def _small_file_system(folder: pathlib.Path, size: str):
    """A tmpfs of ``size`` mounted on ``folder`` (root only: skip otherwise), unmounted after."""
    folder.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(folder)],
                      capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs (not root)")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], check=True)


@pytest.mark.parametrize("filled", [False, True], ids=["fills-while-writing", "full-before"])
def test_a_full_disk_while_writing_the_overlay(tmp_path, filled):
    """On a real full file system OpenCV's writer either fails to open (it was blamed on the codec) or drops frames
    silently (a cut video was published)."""
    with _small_file_system(tmp_path / "small", "96k") as small:
        if filled:
            with pytest.raises(OSError), open(small / "filler", "wb") as filler:
                filler.write(bytes(200_000))
        out = small / "out.mp4"
        result = subprocess.run([sys.executable, "-c", "from condtrack_cli.cli import main; main()", *TRACK,
                                 "--overlay", str(out)], capture_output=True, text=True, timeout=120)
        assert (result.returncode, result.stderr) == (1, f"Error: {out}: no space left on device\n")
        assert sorted(p.name for p in small.iterdir()) == (["filler"] if filled else [])
