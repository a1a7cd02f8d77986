"""The command line's stdout and stderr: a reader that closes the pipe early (``condtrack eval A GT | head -1``)
is not an error. What is left to print is dropped, the command runs to its end, and its exit code is its own.

Imports no numpy: ``condtrack --help`` loads this module.
"""

from __future__ import annotations

import os
from typing import TextIO


def drop(stream: TextIO) -> None:
    """Send the rest of ``stream`` to the null device: nothing more is written there, and nothing fails at exit."""
    os.dup2(os.open(os.devnull, os.O_WRONLY), stream.fileno())


class QuietPipe:
    """``stream``, whose text is dropped once its reader has closed the pipe (instead of a BrokenPipeError)."""

    def __init__(self, stream: TextIO) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except BrokenPipeError:
            drop(self._stream)
            return len(text)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            drop(self._stream)

    def __getattr__(self, name: str):
        return getattr(self._stream, name)
