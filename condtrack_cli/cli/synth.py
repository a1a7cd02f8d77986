"""``condtrack synth OUT``: write a synthetic scene (or the shipped samples) with exact ground truth."""

from __future__ import annotations

from pathlib import Path

import click
from click.core import ParameterSource

from condtrack_cli import MAX_SEED
from condtrack_cli.cli.options import FiniteFloatRange
from condtrack_cli.errors import CondtrackError

#: Options of ``synth`` that --samples ignores (the samples are fixed scenes and seeds at their defaults).
SCENE_ONLY = ("scene", "seed", "size", "n_frames", "noise")


class _Size(click.ParamType):
    """``WIDTHxHEIGHT`` -> (width, height) in pixels; anything else is a usage error."""

    name = "WIDTHxHEIGHT"

    def convert(self, value, param, ctx) -> tuple[int, int]:
        width, sep, height = value.partition("x")
        if not (sep and width.isdecimal() and height.isdecimal()):
            self.fail(f"expected WIDTHxHEIGHT, got {value!r}", param, ctx)
        return int(width), int(height)


@click.command("synth")
@click.argument("out", type=click.Path(file_okay=False))
@click.option("--scene", help="Scene to write into OUT: camera_motion, occlusion, ring, illumination, fast, jumps, card, nonrigid.")
@click.option("--samples", is_flag=True,
              help="Write the shipped sample sequences under OUT instead (make samples); takes --force only.")
@click.option("--seed", type=click.IntRange(min=0, max=MAX_SEED), default=0, show_default=True)
@click.option("--size", type=_Size(), default="320x240", show_default=True, help="WIDTHxHEIGHT in pixels, 64 to 4096 each way.")
@click.option("--frames", "n_frames", type=click.IntRange(min=2), help="Number of frames (the scene's default otherwise).")
@click.option("--noise", type=FiniteFloatRange(min=0), help="Noise standard deviation (grey levels).")
@click.option("--force", is_flag=True,
              help="Replace OUT (with --samples: its sample folders) when it exists; a folder holding other files than "
                   "a scene's is never replaced.")
def synth(out, scene, samples, seed, size, n_frames, noise, force) -> None:
    """Write a synthetic scene with exact ground truth: frames, queries.csv, tracks.csv, labels.csv.

    An existing, non-empty OUT is refused unless --force is given.
    """
    from condtrack_cli.frames.synthetic import SAMPLE_SEEDS, SCENES, make_scene, write_samples, write_scene

    usage = click.get_current_context()
    if samples:
        given = [param.opts[0] for param in usage.command.params
                 if param.name in SCENE_ONLY and usage.get_parameter_source(param.name) is ParameterSource.COMMANDLINE]
        if given:
            usage.fail(f"{', '.join(given)}: a single-scene option (not with --samples)")
        _refuse_replacing([Path(out) / name for name in SAMPLE_SEEDS], force)
        try:
            written = write_samples(out)
        except ValueError as error:  # a sample folder holding other files, checked before any is written
            raise CondtrackError(str(error)) from None
        except OSError as error:
            raise CondtrackError(f"{out}: cannot write the samples ({error.strerror}: {error.filename})") from None
        for name, folder in written.items():
            click.echo(f"{name}: {folder}")
        return
    if not scene:
        usage.fail("synth needs --scene NAME or --samples")
    if scene not in SCENES:
        raise click.BadParameter(f"unknown scene {scene!r}; valid: {', '.join(SCENES)}", usage, param_hint="'--scene'")
    _refuse_replacing([Path(out)], force)
    try:
        made = make_scene(scene, seed, size, n_frames, noise)
    except ValueError as error:  # --size, --frames or --noise out of the scene's range, checked before allocating
        usage.fail(str(error))
    try:
        written = write_scene(made, out)
    except ValueError as error:
        raise CondtrackError(str(error)) from None
    except OSError as error:
        raise CondtrackError(f"{out}: cannot write the scene ({error.strerror}: {error.filename})") from None
    click.echo(f"{scene}: {written}")


def _refuse_replacing(folders: list[Path], force: bool) -> None:
    """Without ``force``, a usage error naming the first of ``folders`` that exists and holds anything (one that
    cannot be listed is left to the writer, whose error names it)."""
    for folder in folders:
        try:
            replaced = folder.is_dir() and any(folder.iterdir())
        except OSError:
            replaced = False
        if replaced and not force:
            click.get_current_context().fail(f"{folder}: the folder exists (--force replaces a scene folder)")
