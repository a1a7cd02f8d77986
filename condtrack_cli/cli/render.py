"""``condtrack render TRACKS INPUT -o OUT.mp4``: draw a track file on the frames it was tracked on."""

from __future__ import annotations

from pathlib import Path

import click

from condtrack_cli.cli.options import checked, overlay_options, overlay_style, png_suffix, video_suffix


@click.command("render")
@click.argument("tracks_path", metavar="TRACKS", type=click.Path(dir_okay=False))
@click.argument("input_path", metavar="INPUT", type=click.Path(readable=False))  # a path, checked by the run
@click.option("-o", "--output", "output_path", required=True, type=click.Path(dir_okay=False),
              callback=checked(video_suffix),
              help="Overlay video: OUT.mp4, .avi, .mov or .mkv (MPEG-4; a folder OUT/ of PNGs when no codec opens).")
@click.option("--contact-sheet", "sheet_path", type=click.Path(dir_okay=False), callback=checked(png_suffix),
              help="Also write a PNG tiling evenly spaced frames with the overlay.")
@click.option("--trail", type=click.IntRange(min=1), default=10, show_default=True,
              help="Positions joined by each point's trail (1: no trail).")
@click.option("--sheet-frames", type=click.IntRange(min=1), default=6, show_default=True,
              help="Frames on the contact sheet, evenly spaced, first and last included (1: the first alone).")
@overlay_options
def render_command(tracks_path: str, input_path: str, output_path: str, sheet_path: str | None,
                   trail: int, sheet_frames: int, overlay_points: int | None, ellipses: str | None,
                   ellipse_cap: float | None) -> None:
    """Draw the tracks of TRACKS (.h5 or .csv) on the frames of INPUT, the sequence they were tracked on.

    \b
    Per point, in the colour of its method (legend top-left):
      trail       its last --trail positions, darker with age
      ellipse     its 95% covariance ellipse (none when the covariance is
                  undefined or infinite; a diamond when over --ellipse-cap)
      dot / X     filled dot when visible; hollow X when not visible or
                  when the covariance is infinite
      particles   CNLF particles as single pixels, when the file stores them
    --overlay-points and --ellipses thin it out on a crowded clip.
    Positions are drawn as they are: x right, y down, origin at the centre of
    the top-left pixel (OpenCV's convention).
    """
    from condtrack_cli.frames.readers import FrameSettings, open_frames
    from condtrack_cli.config import stored_config
    from condtrack_cli.io.read import matched_to_input, read_tracks, stored_particles
    from condtrack_cli.io.atomic import check_writable, refuse_overwriting_inputs
    from condtrack_cli.render import check_video_path, render_contact_sheet, render_overlay

    style = overlay_style(overlay_points, ellipses, ellipse_cap)
    tracks_file, output = Path(tracks_path), Path(output_path)
    sheet = Path(sheet_path) if sheet_path else None
    check_video_path(output)
    if sheet is not None:  # checked now: the sheet is written after the video
        check_writable(sheet)
    refuse_overwriting_inputs({"-o": output, "--contact-sheet": sheet}, {"INPUT": input_path, "TRACKS": tracks_file})
    tracks, meta = read_tracks(tracks_file)
    config = stored_config(tracks_file, meta)  # the frames read as they were tracked (frames.bit_depth)
    stored = config.stage("frames").settings if config is not None else None
    source = open_frames(stored if isinstance(stored, FrameSettings) else FrameSettings(), input_path)
    tracks = matched_to_input(tracks, meta, tracks_file, source.info)
    with stored_particles(tracks_file, tracks) as particles:
        written = render_overlay(tracks, source, output, source.info.fps, trail=trail, particles=particles, style=style)
        if sheet is not None:
            render_contact_sheet(tracks, source, sheet, n=sheet_frames, trail=trail, particles=particles,
                                 style=style)
    click.echo(f"wrote {written}" + (f" and {sheet}" if sheet is not None else ""), err=True)
