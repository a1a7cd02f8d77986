"""Produce the next item while the current one is used: a thread one item ahead of its consumer.

It decodes the next frame while the current one is tracked (the reader thread),
and the pipeline runs the motion stage one frame pair ahead of the filter with
it (``pipeline.py``). OpenCV's decoders (``cv2.imread``, ``VideoCapture.read``)
and its image functions release the GIL, so the thread's work runs beside the
consumer's. The thread starts on an item only while fewer than ``depth`` items
are made and not yet taken: memory stays flat in the clip's length. An error
raised while producing is raised again, the same exception, in the consumer when
it reaches that item. Leaving the ``with`` block, at the end or early (an
exception, Ctrl-C), stops the thread and waits for it (it ends within one item's
production); the items' iterator is closed in the thread (a video capture is
released there).
"""

from __future__ import annotations

import queue
import threading
from typing import Generic, Iterable, Iterator, TypeVar

T = TypeVar("T")

_ITEM, _END, _ERROR = "item", "end", "error"

#: The thread's default name (the frame reader's).
READER = "condtrack-frame-reader"

#: Seconds between two checks of a stop request while the thread waits for the consumer.
_POLL = 0.05

#: ``next``'s default when the items are exhausted.
_EXHAUSTED = object()


class Prefetched(Generic[T]):
    """Iterate ``items`` with a thread up to ``depth`` items ahead; a context manager that joins it."""

    def __init__(self, items: Iterable[T], depth: int = 1, name: str = READER):
        self._queue: queue.Queue = queue.Queue()  # at most ``depth`` items and the end or the error (the slots)
        self._slots = threading.Semaphore(depth)  # items the thread may still make before the consumer takes one
        self._stop = threading.Event()
        self._finished = False
        # a daemon: a Prefetched never closed cannot keep the interpreter from exiting
        self._thread = threading.Thread(target=self._produce, args=(items,), name=name, daemon=True)
        self._thread.start()

    def _produce(self, items: Iterable[T]) -> None:
        """The thread: each item, then the end or the error, into the queue (until a stop request)."""
        iterator = None
        try:
            iterator = iter(items)
            while self._slot():
                item = next(iterator, _EXHAUSTED)
                if item is _EXHAUSTED:
                    self._queue.put((_END, None))
                    return
                self._queue.put((_ITEM, item))
        except BaseException as error:  # handed to the consumer, which raises it
            self._queue.put((_ERROR, error))
        finally:
            close = getattr(iterator, "close", None)
            if close is not None:
                close()

    def _slot(self) -> bool:
        """Wait until fewer than ``depth`` items are made and not yet taken; False when the consumer stopped first."""
        while not self._stop.is_set():
            if self._slots.acquire(timeout=_POLL):
                return True
        return False

    def __iter__(self) -> Iterator[T]:
        return self

    def __next__(self) -> T:
        if self._finished:
            raise StopIteration
        kind, value = self._queue.get()
        if kind == _ITEM:
            self._slots.release()
            return value
        self._finished = True
        self._thread.join()
        if kind == _ERROR:
            raise value
        raise StopIteration

    def close(self) -> None:
        """Stop the thread and wait for it (it ends within one item's production)."""
        self._finished = True
        self._stop.set()
        self._thread.join()

    def __enter__(self) -> Prefetched[T]:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
