"""``condtrack synth OUT``: write a synthetic scene (or the shipped samples) with exact ground truth."""

from __future__ import annotations

import click

from condtrack_cli.errors import CondtrackError


class _Size(click.ParamType):
    """``WIDTHxHEIGHT`` -> (width, height) in pixels; anything else is a usage error."""

    name = "WIDTHxHEIGHT"

    def convert(self, value, param, ctx) -> tuple[int, int]:
        width, sep, height = value.partition("x")
        if not (sep and width.isdigit() and height.isdigit()):
            self.fail(f"expected WIDTHxHEIGHT, got {value!r}", param, ctx)
        return int(width), int(height)


@click.command("synth")
@click.argument("out", type=click.Path(file_okay=False))
@click.option("--scene", help="Scene to write into OUT: camera_motion, occlusion, ring, illumination, fast, jumps, card, nonrigid.")
@click.option("--samples", is_flag=True, help="Write the shipped sample sequences under OUT instead (make samples).")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option("--size", type=_Size(), default="320x240", show_default=True, help="WIDTHxHEIGHT in pixels.")
@click.option("--frames", "n_frames", type=click.IntRange(min=2), help="Number of frames (the scene's default otherwise).")
@click.option("--noise", type=click.FloatRange(min=0), help="Noise standard deviation (grey levels).")
def synth(out, scene, samples, seed, size, n_frames, noise) -> None:
    """Write a synthetic scene with exact ground truth: frames, queries.csv, tracks.csv, labels.csv."""
    from condtrack_cli.frames.synthetic import SCENES, make_scene, write_samples, write_scene

    usage = click.get_current_context()
    if samples:
        try:
            written = write_samples(out)
        except OSError as error:
            raise CondtrackError(f"{out}: cannot write the samples ({error.strerror}: {error.filename})") from None
        for name, folder in written.items():
            click.echo(f"{name}: {folder}")
        return
    if not scene:
        usage.fail("synth needs --scene NAME or --samples")
    if scene not in SCENES:
        raise click.BadParameter(f"unknown scene {scene!r}; valid: {', '.join(SCENES)}", usage, param_hint="'--scene'")
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
