"""Option types, checks and options that several commands share: the overlay's (``track --overlay`` and ``render``).

Imports click only; a check imports what it needs when it runs.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Callable

import click

from condtrack_cli.errors import CondtrackError


class FiniteFloatRange(click.FloatRange):
    """A ``click.FloatRange`` that also refuses ``nan``, ``inf`` and what overflows to it (``1e999``): a bad option value."""

    def convert(self, value, param, ctx) -> float:
        number = super().convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        return number


def json_value(value: Any) -> Any:
    """A value for strict JSON, lists and dicts throughout: a non-finite float as the string "inf", "-inf" or "nan"."""
    if isinstance(value, dict):
        return {key: json_value(v) for key, v in value.items()}
    if isinstance(value, list):
        return [json_value(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    return value


def checked(check: Callable[[Path], None], stdout: str | None = None):
    """A click callback running ``check(path)`` on the option's value when given: a CondtrackError it raises is a bad
    value of that option (a usage error, exit 2, naming the option), as is an empty value. ``stdout``: a value that
    names standard output (``-``), passed on unchecked."""

    def callback(ctx: click.Context, param: click.Parameter, value: str | None) -> str | None:
        if value == "":  # Path("") is ".", which the checks would name instead
            raise click.BadParameter("an empty path; name a file", ctx, param)
        if value is not None and value != stdout:
            try:
                check(Path(value))
            except CondtrackError as error:
                raise click.BadParameter(str(error), ctx, param) from None
        return value

    return callback


def track_file_suffix(path: Path) -> None:
    """Refuse an output track file whose suffix is not one of ``io.formats.FORMATS``."""
    from condtrack_cli.io.formats import track_format

    track_format(path, "output")


def video_suffix(path: Path) -> None:
    """Refuse an overlay video whose suffix is not one of ``render.VIDEO_SUFFIXES``."""
    from condtrack_cli.render import check_video_suffix

    check_video_suffix(path)


def png_suffix(path: Path) -> None:
    """Refuse a picture (``render --contact-sheet``, ``eval --plot``) not named .png: PNG is what they write."""
    if path.suffix.lower() != ".png":
        raise CondtrackError(f"{path}: the picture is a PNG (use a .png name)")


def overlay_options(command):
    """Decorate ``command`` with --overlay-points, --ellipses and --ellipse-cap (see ``render.OverlayStyle``)."""
    options = [
        click.option("--overlay-points", type=click.IntRange(min=1), metavar="N",
                     help="Overlay: draw only the N points that move most (longest path over the clip)."),
        click.option("--ellipses", type=click.Choice(["all", "visible", "none"]),
                     help="Overlay: covariance ellipses on every point (all, the default), on visible points, or none."),
        click.option("--ellipse-cap", type=FiniteFloatRange(min=0, min_open=True), metavar="PX",
                     help="Overlay: largest semi-major axis drawn (px); a larger ellipse is a diamond mark "
                          "(default: half the frame's diagonal)."),
    ]
    for option in reversed(options):
        command = option(command)
    return command


def overlay_style(overlay_points: int | None, ellipses: str | None, ellipse_cap: float | None, overlay: object = True):
    """The ``render.OverlayStyle`` of the options; None without ``overlay`` (the video), a usage error when one is given then."""
    if not overlay:
        given = [f"--{name}" for name, value in (("overlay-points", overlay_points), ("ellipses", ellipses),
                                                 ("ellipse-cap", ellipse_cap)) if value is not None]
        if given:
            click.get_current_context().fail(f"{', '.join(given)}: an overlay option (give --overlay OUT.mp4)")
        return None
    from condtrack_cli.render import OverlayStyle

    return OverlayStyle(overlay_points, ellipses or "all", ellipse_cap)
