"""Decode the next frame while the current one is tracked: a reader thread one frame ahead of the pipeline.

OpenCV's decoders (``cv2.imread``, ``VideoCapture.read``) release the GIL, so a
thread reading frame k+1 runs beside the tracking of frame k. The queue holds
at most ``depth`` decoded frames: memory stays flat in the clip's length. An
error raised while reading is raised again, the same exception, in the
consumer when it reaches that frame. Leaving the ``with`` block, at the end or
early (an exception, Ctrl-C), stops the thread and waits for it; the frames'
iterator is closed in the thread (a video capture is released there).
"""

from __future__ import annotations

import queue
import threading
from typing import Generic, Iterable, Iterator, TypeVar

T = TypeVar("T")

_FRAME, _END, _ERROR = "frame", "end", "error"

#: Seconds between two checks of a stop request while the queue is full.
_POLL = 0.05


class Prefetched(Generic[T]):
    """Iterate ``frames`` with a reader thread up to ``depth`` items ahead; a context manager that joins it."""

    def __init__(self, frames: Iterable[T], depth: int = 1):
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._stop = threading.Event()
        self._finished = False
        # a daemon: a Prefetched never closed cannot keep the interpreter from exiting
        self._thread = threading.Thread(target=self._read, args=(frames,), name="condtrack-frame-reader", daemon=True)
        self._thread.start()

    def _read(self, frames: Iterable[T]) -> None:
        """The reader thread: each item, then the end or the error, into the queue (until a stop request)."""
        iterator = None
        try:
            iterator = iter(frames)
            for item in iterator:
                if not self._put((_FRAME, item)):
                    return
            self._put((_END, None))
        except BaseException as error:  # handed to the consumer, which raises it
            self._put((_ERROR, error))
        finally:
            close = getattr(iterator, "close", None)
            if close is not None:
                close()

    def _put(self, entry: tuple) -> bool:
        """Queue ``entry``, waiting while the queue is full; False when the consumer stopped first."""
        while not self._stop.is_set():
            try:
                self._queue.put(entry, timeout=_POLL)
                return True
            except queue.Full:
                continue
        return False

    def __iter__(self) -> Iterator[T]:
        return self

    def __next__(self) -> T:
        if self._finished:
            raise StopIteration
        kind, value = self._queue.get()
        if kind == _FRAME:
            return value
        self._finished = True
        self._thread.join()
        if kind == _ERROR:
            raise value
        raise StopIteration

    def close(self) -> None:
        """Stop the reader thread and wait for it (it ends within one item's decoding)."""
        self._finished = True
        self._stop.set()
        self._thread.join()

    def __enter__(self) -> Prefetched[T]:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
