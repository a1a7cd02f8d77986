"""The batch-only options of ``condtrack track`` (resume, shards, Dask) and --threads; refusing them without --out-dir."""

from __future__ import annotations

import click

from condtrack_cli.threads import THREADS_ENV

#: Options of ``track`` that only a batch (--out-dir) takes.
BATCH_ONLY = ("skip_existing", "shard", "scheduler", "scheduler_file", "jobs", "format")


class _Shard(click.ParamType):
    """``--shard I/N`` -> (I, N) with 0 <= I < N; anything else is a usage error."""

    name = "I/N"

    def convert(self, value, param, ctx) -> tuple[int, int]:
        from condtrack_cli.batch.plan import parse_shard

        try:
            return parse_shard(value)
        except ValueError as error:
            self.fail(str(error), param, ctx)


def batch_options(command):
    """Decorate ``track`` with the batch options (resume, shards, Dask) and --threads."""
    options = [
        click.option("--skip-existing", is_flag=True,
                     help="Batch: skip inputs whose output exists from the same config, seed, queries and version."),
        click.option("--shard", type=_Shard(), metavar="I/N", help="Batch: only the I-th of N parts of the inputs (I = 0..N-1)."),
        click.option("--scheduler", metavar="ADDRESS", help="Batch: run one task per input on this dask.distributed scheduler."),
        click.option("--scheduler-file", type=click.Path(dir_okay=False, exists=True), help="Batch: as --scheduler, from a Dask scheduler file."),
        click.option("--threads", type=click.IntRange(min=1),
                     help=f"Threads per input (default ${THREADS_ENV}, else every core for one input, cores / N per job with -j N)."),
    ]
    for option in reversed(options):
        command = option(command)
    return command


def refuse_batch_options(batch_values: dict) -> None:
    """A usage error naming the batch-only options given (a single run without --out-dir would ignore them)."""
    given = [f"--{name.replace('_', '-')}" for name in BATCH_ONLY if batch_values.get(name) not in (None, False)]
    if given:
        click.get_current_context().fail(f"{', '.join(given)}: a batch option (give --out-dir)")
