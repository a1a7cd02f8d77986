"""How many threads one clip uses: OpenCV's pool and the BLAS pools.

One clip alone uses every core this process may run on (:func:`cores`, its CPU
affinity) unless ``--threads`` says otherwise. A batch of ``-j N`` gives each
job ``threads_per_job`` threads, the cores shared out, so that N jobs never ask
for more threads than the machine has cores.

The BLAS and OpenMP pools read their size once, when numpy is imported: a
process started for a batch job gets :func:`blas_environment` in its
environment before it imports anything; OpenCV's pool is set at run time by
:func:`use_threads`.
"""

from __future__ import annotations

import os

from condtrack_cli.errors import CondtrackError

#: Environment variable giving the default of ``--threads``.
THREADS_ENV = "CONDTRACK_THREADS"

#: Variables read by the BLAS / OpenMP libraries numpy and scipy may load, at import time.
BLAS_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS")


def cores() -> int:
    """Cores this process may run on (its CPU affinity, not the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def threads_from_environment() -> int | None:
    """``CONDTRACK_THREADS`` as a positive int, None when unset; ValueError when it is not one."""
    text = os.environ.get(THREADS_ENV, "").strip()
    if not text:
        return None
    if not text.isdecimal() or int(text) < 1:
        raise ValueError(f"{THREADS_ENV}={text!r}: expected a positive integer")
    return int(text)


def requested_threads(threads: int | None) -> int | None:
    """--threads, else $CONDTRACK_THREADS, else None."""
    if threads is not None:
        return threads
    try:
        return threads_from_environment()
    except ValueError as error:
        raise CondtrackError(str(error)) from None


def threads_per_job(requested: int | None, jobs: int, available: int | None = None) -> tuple[int, str | None]:
    """(threads for each of ``jobs`` parallel jobs, a warning or None).

    ``requested`` None: the ``available`` cores shared out, ``available // jobs``
    each (at least 1). A request is capped at that share so the jobs never
    oversubscribe the ``available`` cores (``--threads 100000`` started a
    thread storm); the warning says so.
    """
    available = available or cores()
    fair = max(1, available // jobs)
    if requested is None:
        return fair, None
    if requested > fair:
        times, each = (f" x {jobs} jobs", " per job") if jobs > 1 else ("", "")
        return fair, (f"{requested} threads{times} exceeds the {available} core{'s' if available > 1 else ''}: "
                      f"using {fair} thread{'s' if fair > 1 else ''}{each}")
    return requested, None


def blas_environment(threads: int | None) -> dict[str, str]:
    """Environment entries that size the BLAS / OpenMP pools of a process started next (empty for None)."""
    return {} if threads is None else {name: str(threads) for name in BLAS_VARIABLES}


def use_threads(threads: int | None) -> None:
    """Size OpenCV's thread pool for this process (None or more than its cores: every core it may use)."""
    import cv2

    cv2.setNumThreads(cores() if threads is None else min(threads, cores()))


def threads_in_use() -> dict[str, int | str]:
    """What this process uses now: OpenCV's thread count and OMP_NUM_THREADS (reported per clip)."""
    import cv2

    return {"opencv": cv2.getNumThreads(), "omp": os.environ.get("OMP_NUM_THREADS", "")}
