"""Execute here: a batch's jobs in this process or a spawned process pool, and how SIGTERM unwinds the batch."""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing
import os
import signal
import sys
import threading
from typing import Callable

import click

from condtrack_cli.batch.job import BatchJob, run_job
from condtrack_cli.batch.manifest import ClipRecord
from condtrack_cli.interrupts import held_signals
from condtrack_cli.progress import show_warnings, warnings_shown
from condtrack_cli.threads import blas_environment

#: Exit status of a process stopped by SIGTERM (128 + 15), the shells' convention.
SIGTERM_EXIT = 143

#: Seconds between two looks for a held stop signal while the pool's workers run (``run_local``).
SIGNAL_POLL = 0.05

#: Seconds an interrupted pool's shutdown may take before its workers are killed (``stop_pool``).
STOP_WAIT = 10.0


def stop_on_sigterm(signum, frame) -> None:
    """SIGTERM handler: raise SystemExit(143), so the process unwinds (finally blocks remove temporary files)."""
    raise SystemExit(SIGTERM_EXIT)


@contextlib.contextmanager
def sigterm_exits():
    """While open, SIGTERM raises SystemExit(143) here, so the batch unwinds (workers stopped, temporaries removed)."""
    previous = signal.signal(signal.SIGTERM, stop_on_sigterm)
    try:
        yield
    except SystemExit as exit_:
        if exit_.code == SIGTERM_EXIT:
            click.echo("Error: interrupted", err=True)  # as for one input, and the README's batch example
        raise
    finally:
        signal.signal(signal.SIGTERM, previous)


#: Linux's prctl option that sends the calling process a signal when its parent dies (<linux/prctl.h>).
PR_SET_PDEATHSIG = 1


def _end_with_parent(parent: int) -> None:
    """On Linux, this worker gets SIGTERM when the batch's process ``parent`` dies, even by SIGKILL (the OOM killer),
    which runs no clean-up: an orphan went on tracking for nobody, then wrote tracebacks into a closed pipe. The pool
    starts its workers from the batch's main thread, whose end is the process's. Elsewhere nothing is done."""
    if not sys.platform.startswith("linux"):
        return
    ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
    if os.getppid() != parent:  # it died before the call
        os.kill(os.getpid(), signal.SIGTERM)


def _start_worker(warnings_shown: bool, parent: int) -> None:
    """Pool worker set-up: Ctrl-C is the parent's to handle; SIGTERM unwinds (an unfinished output's temporary file
    goes), as does the death of the batch's process ``parent``; warnings shown as in the parent (not with -q)."""
    show_warnings(warnings_shown)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, stop_on_sigterm)
    _end_with_parent(parent)


class _Environment:
    """Context: extra environment variables while it is open (read by processes started inside it)."""

    def __init__(self, values: dict[str, str]):
        self.values, self.saved = values, {}

    def __enter__(self):
        self.saved = {name: os.environ.get(name) for name in self.values}
        os.environ.update(self.values)

    def __exit__(self, *exc):
        for name, value in self.saved.items():
            if value is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = value


def run_local(jobs: list[BatchJob], processes: int, on_record: Callable[[ClipRecord], None]) -> None:
    """Run ``jobs`` here (``processes`` 1) or in a pool of spawned processes; ``on_record`` as each ends.

    Any exception in this process (Ctrl-C's KeyboardInterrupt, SIGTERM's
    SystemExit) drops the queued jobs and terminates the workers, whose running
    job then removes its unfinished output: nothing is published after it
    (``stop_pool``). While the pool runs, a stop signal is held and raised
    between two results (``held_signals``): raised inside the pool's own code,
    between a lock's acquire and its ``with`` block, it can leave that lock
    taken, and ``terminate`` then waits forever on the thread that collects the results.
    """
    if processes <= 1 or len(jobs) <= 1:
        for job in jobs:
            on_record(run_job(job))
        return
    context = multiprocessing.get_context("spawn")  # OpenCV is not fork-safe
    with _Environment(blas_environment(jobs[0].threads)):  # read by the BLAS libraries when the workers import numpy
        shown = warnings_shown()
        pool = context.Pool(min(processes, len(jobs)), initializer=_start_worker, initargs=(shown, os.getpid()))
    try:
        with held_signals() as held:
            results = pool.imap_unordered(run_job, jobs)
            while not held.received:
                try:
                    record = results.next(timeout=SIGNAL_POLL)
                except StopIteration:
                    break
                except multiprocessing.TimeoutError:
                    continue
                on_record(record)
        pool.close()
    except BaseException:
        stop_pool(pool)
        raise
    pool.join()


def stop_pool(pool) -> None:
    """Terminate ``pool`` (its workers get SIGTERM and unwind), killing the workers left after ``STOP_WAIT`` s.

    ``Pool.terminate`` waits on locks its workers share with this process (the task
    queue's, the result queue's) and on each worker's exit; an interrupted ``-j 2``
    batch was seen waiting past the tests' two minutes with signals already held
    (where it waited was not caught). So it runs in a thread of its own (a daemon:
    the process may exit without it), and the workers still alive when its time is
    up are killed.
    """
    stopper = threading.Thread(target=pool.terminate, name="condtrack-pool-stop", daemon=True)
    stopper.start()
    stopper.join(STOP_WAIT)
    if stopper.is_alive():
        for worker in multiprocessing.active_children():
            worker.kill()
        stopper.join(STOP_WAIT)
