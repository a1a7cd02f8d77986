"""Options that several commands share: the overlay's (``track --overlay`` and ``render``). Imports click only."""

from __future__ import annotations

import click

from condtrack_cli.errors import CondtrackError


def overlay_options(command):
    """Decorate ``command`` with --overlay-points, --ellipses and --ellipse-cap (see ``render.OverlayStyle``)."""
    options = [
        click.option("--overlay-points", type=click.IntRange(min=1), metavar="N",
                     help="Overlay: draw only the N points that move most (longest path over the clip)."),
        click.option("--ellipses", type=click.Choice(["all", "visible", "none"]),
                     help="Overlay: covariance ellipses on every point (all, the default), on visible points, or none."),
        click.option("--ellipse-cap", type=click.FloatRange(min=0, min_open=True), metavar="PX",
                     help="Overlay: largest semi-major axis drawn (px); a larger ellipse is a diamond mark "
                          "(default: half the frame's diagonal)."),
    ]
    for option in reversed(options):
        command = option(command)
    return command


def overlay_style(overlay_points: int | None, ellipses: str | None, ellipse_cap: float | None, overlay: object = True):
    """The ``render.OverlayStyle`` of the options; None without ``overlay`` (the video), CondtrackError when one is given then."""
    if not overlay:
        given = [f"--{name}" for name, value in (("overlay-points", overlay_points), ("ellipses", ellipses),
                                                 ("ellipse-cap", ellipse_cap)) if value is not None]
        if given:
            raise CondtrackError(f"{', '.join(given)}: an overlay option (give --overlay OUT.mp4)")
        return None
    from condtrack_cli.render import OverlayStyle

    return OverlayStyle(overlay_points, ellipses or "all", ellipse_cap)
