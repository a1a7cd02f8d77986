"""Run one command and write its wall time, CPU time and peak resident memory to a JSON file (the benchmark's meter).

Usage: ``python -I peak.py RESULT.json COMMAND...``; exits with the command's exit code.

Why a separate small process: Linux counts in a child's peak RSS (``ru_maxrss``)
the memory it had before ``exec``, and a child forked (or vforked) from the
benchmark starts with the benchmark's memory: a ``python -c 'import numpy'``
child of a process holding 400 MiB read as 427 MiB. This meter imports only the
standard library (about 10 MiB), so the command it starts is measured from a
small start. It must stay standard-library only and be run by its path, not
through the ``condtrack_cli`` package.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time


def main() -> int:
    """Run ``sys.argv[2:]``, write {"seconds": wall s, "cpu_seconds": user + system CPU s of the command and its
    threads, "peak_mib": peak RSS MiB} to ``sys.argv[1]``."""
    result, command = sys.argv[1], sys.argv[2:]
    started = time.perf_counter()
    process = subprocess.Popen(command)
    _, status, usage = os.wait4(process.pid, 0)
    seconds = time.perf_counter() - started
    with open(result, "w") as out:
        json.dump({"seconds": seconds, "cpu_seconds": usage.ru_utime + usage.ru_stime,
                   "peak_mib": usage.ru_maxrss / 1024.0}, out)
    return os.waitstatus_to_exitcode(status)


if __name__ == "__main__":
    sys.exit(main())
