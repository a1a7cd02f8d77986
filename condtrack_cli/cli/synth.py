"""``condtrack synth OUT``: write a synthetic scene (or the shipped samples) with exact ground truth."""

from __future__ import annotations

import click

from condtrack_cli.errors import CondtrackError


@click.command("synth")
@click.argument("out", type=click.Path(file_okay=False))
@click.option("--scene", help="Scene to write into OUT: camera_motion, occlusion, ring, illumination, fast.")
@click.option("--samples", is_flag=True, help="Write the shipped sample sequences under OUT instead (make samples).")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True)
@click.option("--size", default="320x240", show_default=True, help="WIDTHxHEIGHT in pixels.")
@click.option("--frames", "n_frames", type=click.IntRange(min=2), help="Number of frames (the scene's default otherwise).")
@click.option("--noise", type=click.FloatRange(min=0), help="Noise standard deviation (grey levels).")
def synth(out, scene, samples, seed, size, n_frames, noise) -> None:
    """Write a synthetic scene with exact ground truth: frames, queries.csv, tracks.csv, labels.csv."""
    from condtrack_cli.frames.synthetic import make_scene, write_samples, write_scene

    if samples:
        try:
            written = write_samples(out)
        except OSError as error:
            raise CondtrackError(f"{out}: cannot write the samples ({error.strerror}: {error.filename})") from None
        for name, folder in written.items():
            click.echo(f"{name}: {folder}")
        return
    if not scene:
        raise CondtrackError("synth needs --scene NAME or --samples")
    width, sep, height = size.partition("x")
    if not (sep and width.isdigit() and height.isdigit()):
        raise CondtrackError(f"--size: expected WIDTHxHEIGHT, got {size!r}")
    try:
        written = write_scene(make_scene(scene, seed, (int(width), int(height)), n_frames, noise), out)
    except ValueError as error:
        raise CondtrackError(str(error)) from None
    except OSError as error:
        raise CondtrackError(f"{out}: cannot write the scene ({error.strerror}: {error.filename})") from None
    click.echo(f"{scene}: {written}")
