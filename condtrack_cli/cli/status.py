"""``condtrack status OUT_DIR``: each input's latest record in a batch's manifest, the counts, and the redo command."""

from __future__ import annotations

import json
import sys

import click


@click.command("status")
@click.argument("out_dir", metavar="OUT_DIR", type=click.Path(file_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print the status as JSON (for scripts).")
def status_command(out_dir: str, as_json: bool) -> None:
    """Show what became of each input of the batch written into OUT_DIR (its manifest.jsonl).

    Per input its latest record: ok, failed (with the reason), interrupted
    (the batch was stopped or killed before the input ended, or is still
    running it: no output), skipped, or missing
    (recorded as done but its output is gone, or replaced by another input's
    of the same name); then the counts, the time taken
    and the command that redoes the failed, interrupted and missing inputs.
    A batch still running into OUT_DIR shows the inputs it has not ended yet
    as interrupted. The exit code is 1 when an input's latest record is failed
    or interrupted.
    """
    from condtrack_cli.batch.status import batch_status

    status = batch_status(out_dir)
    if as_json:
        click.echo(json.dumps(status.to_json(), indent=2))
    else:
        _print(status)
    if status.counts["failed"] or status.counts["interrupted"]:
        sys.exit(1)


#: What ``status`` shows for an interrupted input in place of an output.
NOT_ENDED = "stopped before it ended: no output"


def _print(status) -> None:
    from condtrack_cli.batch.status import NEVER_ENDED

    width = max(len(item.input) for item in status.inputs)
    status_width = max(8, 1 + max(len(item.status) for item in status.inputs))
    for item in status.inputs:
        never_ended = f"{NEVER_ENDED}: no output" if item.error == NEVER_ENDED else NOT_ENDED
        detail = {"failed": item.error, "interrupted": never_ended}.get(item.status, item.output)
        if item.status == "missing":
            detail = item.error or f"{detail} is gone"
        tries = f" ({item.attempts} attempts)" if item.attempts > 1 else ""
        click.echo(f"{item.status:{status_width}s} {item.input:{width}s}  {detail}{tries}")
    counts = ", ".join(f"{count} {name}" for name, count in status.counts.items() if count)
    click.echo(f"{len(status.inputs)} inputs: {counts}; {status.seconds:.1f} s in their latest runs, "
               f"{status.seconds_all_attempts:.1f} s in all")
    if status.redo:
        click.echo("redo the failed, interrupted and missing inputs:")
        for line in status.redo + [f"# {note}" for note in status.notes]:
            click.echo(f"  {line}")
