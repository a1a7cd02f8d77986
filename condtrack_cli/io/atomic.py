"""Write a file (or a folder) completely or not at all: build it beside its final path, rename it at the end.

Interrupted (Ctrl-C, SIGTERM), nothing is left: a file is written by one call
during which the signal is held (:func:`condtrack_cli.interrupts.held_signals`)
and then discarded; a staging folder is deleted as the interrupt unwinds.

An output path that is a symbolic link is written through: the file it points
to is replaced (built beside it, in its folder) and the link stays.
:func:`refuse_overwriting_inputs` refuses, before any work, an output that is
one of the run's input files.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Iterator

from condtrack_cli.errors import CondtrackError
from condtrack_cli.interrupts import held_signals


def _umask() -> int:
    """The process's file-creation mask (read by setting it and putting it back)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def through_links(path: str | Path) -> Path:
    """``path``, or the path its symbolic link points to (followed to the end): where an output really goes."""
    path = Path(path)
    return Path(os.path.realpath(path)) if path.is_symlink() else path


def refuse_overwriting_inputs(outputs: dict[str, str | Path | None], inputs: dict[str, str | Path | None]) -> None:
    """CondtrackError when an output (option -> path) is the same file as an input (option -> path), or an image
    inside an input frame folder (a frame it would replace, or one it would add to the sequence); None is absent."""
    from condtrack_cli.frames.readers import IMAGE_EXTENSIONS  # here: the readers load OpenCV

    for output_option, output in outputs.items():
        for input_option, given in inputs.items():
            if output is None or given is None or not Path(given).exists():
                continue
            if Path(given).is_dir() and Path(output).suffix.lower() in IMAGE_EXTENSIONS \
                    and through_links(output).resolve().parent == Path(given).resolve():
                raise CondtrackError(f"{output_option} {output}: an image in the frame folder {input_option} {given}; "
                                     "writing it would replace or add a frame of the input")
            if Path(output).exists() and os.path.samefile(output, given):
                raise CondtrackError(f"{output_option} {output}: the same file as the input {input_option} {given}; "
                                     "writing it would destroy the input")


def output_folder(path: str | Path) -> tuple[Path, Path]:
    """``path`` through its links and the folder it goes in; CondtrackError where that folder is missing or is not a
    folder (a file named as one)."""
    path = through_links(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        reason = "is not a folder" if folder.exists() else "does not exist"
        raise CondtrackError(f"{path}: the output folder '{folder}' {reason}")
    return path, folder


def output_file(path: str | Path) -> tuple[Path, Path]:
    """:func:`output_folder` for an output file: also a CondtrackError where ``path`` is a folder, which the file
    could not replace (said before it is written, not by the rename at its end)."""
    path, folder = output_folder(path)
    if path.is_dir():
        raise CondtrackError(f"{path}: is a folder; an output file cannot replace it")
    return path, folder


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path in ``path``'s folder; rename it to ``path`` on success, delete it otherwise."""
    path, folder = output_file(path)
    # Held from before the file exists: a signal between its creation and the clean-up's start left it behind.
    with held_signals() as held:  # a stop signal during the write: the file is discarded, then the signal acts
        try:
            handle, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=folder)
        except OSError as error:
            raise CondtrackError(f"{path}: cannot write in '{folder}' ({error.strerror})") from None
        os.close(handle)
        temporary = Path(temporary)
        try:
            yield temporary
            if not held.received:
                os.chmod(temporary, 0o666 & ~_umask())  # mkstemp makes 0600; an output gets the usual permissions
                os.replace(temporary, path)
        finally:
            temporary.unlink(missing_ok=True)


@contextlib.contextmanager
def staging_folder(path: str | Path) -> Iterator[Path]:
    """Yield a new private folder in ``path``'s folder to build an output in; it is deleted on exit with all it holds.

    Whatever is built there and handed to :func:`publish` before the exit appears
    at its final path by one rename; anything else vanishes. Lets the caller pick
    the built item's name (a video keeps its extension, which OpenCV reads) and
    build a folder as well as a file.
    """
    path, folder = output_folder(path)
    with contextlib.ExitStack() as cleanup:
        with held_signals():  # the folder and its clean-up come into being together, whatever signal arrives
            try:
                staging = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".part", dir=folder))
            except OSError as error:
                raise CondtrackError(f"{path}: cannot write in '{folder}' ({error.strerror})") from None
            cleanup.callback(_remove_folder, staging)
        yield staging


def _remove_folder(folder: Path) -> None:
    """Delete ``folder`` with all it holds; a second Ctrl-C does not stop the clean-up halfway."""
    with held_signals():
        shutil.rmtree(folder, ignore_errors=True)


def publish(built: Path, path: str | Path) -> None:
    """Rename ``built`` (inside a :func:`staging_folder` beside ``path``) to ``path``.

    A file replaces an existing file; a folder is refused when ``path`` exists
    and is not an empty folder (nothing of the user's is ever deleted).
    """
    try:
        os.replace(built, through_links(path))
    except OSError as error:
        raise CondtrackError(f"{path}: cannot put the output in place ({error.strerror})") from None


def check_writable(path: str | Path) -> None:
    """Refuse ``path`` before any work when it is a folder, or its folder is missing or no file can be created in it.

    Tried, not guessed from permissions (root passes every permission check,
    and a read-only file system fails none): a temporary file is created and
    removed.
    """
    path, folder = output_file(path)
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as error:
        raise CondtrackError(f"{path}: cannot write in '{folder}' ({error.strerror})") from None
