"""Issue 47, items 5-8 and 10-18: numbers as a user types them, option values refused as usage errors, and messages.

Each test failed on 35ed7c7.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import warnings

import numpy as np
import pytest
from click.testing import CliRunner

from condtrack_cli.cli import cli
from condtrack_cli.config import load_config, parse_override
from condtrack_cli.errors import CondtrackError, CondtrackWarning
from condtrack_cli.io.read import read_tracks
from condtrack_cli.progress import show_warnings
from conftest import SAMPLES
from test_failures import _one_error_line
from test_cli import run_cli

SAMPLE = SAMPLES / "occlusion"  # 30 frames, 64 queries on frames 0..7
TRACK_STK = ["track", str(SAMPLE), "-p", str(SAMPLE / "queries.csv"), "-m", "stk"]


def _usage_error(result, message: str) -> None:
    """A CliRunner result that is a usage error (exit 2) whose message holds ``message``."""
    assert result.exit_code == 2, result.output
    assert "Usage: " in result.stderr and message in result.stderr, result.stderr


@pytest.mark.parametrize("text, value", [
    ("1e-3", 1e-3), ("1E16", 1e16), ("2.5e3", 2500.0), ("-1e-05", -1e-5), (".5e-3", 5e-4), ("1_000e3", 1e6),
    ("1.0e+16", 1e16), ("0.00001", 1e-5),  # what YAML 1.1 read as floats already
    ("3", 3), ("1e", "1e"), ("e5", "e5"), ("1e-3x", "1e-3x"), ("nan", "nan"),  # not floats: as before
])
def test_a_float_with_an_exponent_is_a_float_in_set_and_yaml(text, value):
    """Item 5: YAML 1.1 reads ``1e-3`` as a string; the config reads every Python float literal as a float."""
    _, parsed = parse_override(f"measure.r_floor={text}")
    assert parsed == value and type(parsed) is type(value)


def test_a_whole_number_with_an_exponent_is_taken_for_an_integer_key(tmp_path):
    """``1e3`` particles is 1000 particles (it failed as "not a valid integer" at 381a548); ``2.5`` is still refused,
    and so is a float for a boolean key."""
    loaded = load_config(None, ["filter.cnlf.particles=1e3", "motion.finest_scale=1e0"])
    particles, finest = loaded.filters["cnlf"].particles, loaded.stage("motion").settings.finest_scale
    assert (particles, type(particles), finest, type(finest)) == (1000, int, 1, int)
    config = tmp_path / "c.yaml"
    config.write_text("measure:\n  template: 1.5e1\n")
    template = load_config(config).stage("measure").settings.template
    assert (template, type(template)) == (15, int)
    for refused, hint in (("filter.cnlf.particles=2.5", "valid integer"), ("filter.clf.reference_update=1e0", "valid boolean")):
        with pytest.raises(CondtrackError, match=hint):
            load_config(None, [refused])


def test_exponent_floats_reach_the_settings_from_set_a_file_and_max_std(tmp_path, shifted_folder):
    assert load_config(None, ["measure.r_floor=1e-3"]).stage("measure").settings.r_floor == 1e-3
    config = tmp_path / "c.yaml"
    config.write_text("measure:\n  r_floor: 1e-3\noutput:\n  max_std: 2E1\n")
    loaded = load_config(config)
    assert (loaded.stage("measure").settings.r_floor, loaded.output.max_std) == (1e-3, 20.0)
    folder, _ = shifted_folder
    visible = {}
    for typed in ("0.00001", "1e16", None):
        out = tmp_path / f"{typed}.h5"
        given = ["--max-std", typed] if typed else []
        result = CliRunner().invoke(cli, ["track", str(folder), "-m", "mdr", *given, "-o", str(out), "-q"])
        assert result.exit_code == 0, result.output
        tracks, meta = read_tracks(out)
        assert meta["max_std"] == float(typed or "inf")
        visible[typed] = tracks.visible[tracks.has_state]
    assert visible[None].mean() > 0.9
    assert not visible["0.00001"].any() and (visible["1e16"] == visible[None]).all()  # every std is in 1e-5 .. 1e16 px


@pytest.mark.parametrize("args, message", [
    (["track", "{clip}", "--max-std", "nan"], "Invalid value for '--max-std': 'nan' is not a finite number"),
    (["track", "{clip}", "--max-std", "inf"], "Invalid value for '--max-std': 'inf' is not a finite number"),
    (["track", "{clip}", "--max-std", "1e999"], "Invalid value for '--max-std': '1e999' is not a finite number"),
    (["render", "{tracks}", "{clip}", "-o", "{tmp}/r.mp4", "--ellipse-cap", "nan"],
     "Invalid value for '--ellipse-cap': 'nan' is not a finite number"),
    (["render", "{tracks}", "{clip}", "-o", "{tmp}/r.mp4", "--ellipse-cap", "inf"],
     "Invalid value for '--ellipse-cap': 'inf' is not a finite number"),
    (["synth", "{tmp}/s", "--scene", "ring", "--noise", "inf"], "Invalid value for '--noise': 'inf' is not a finite number"),
    (["track", "{clip}", "--overlay-points", "3"], "--overlay-points: an overlay option (give --overlay OUT.mp4)"),
    (["track", "{clip}", "--ellipses", "none", "--ellipse-cap", "5"], "--ellipses, --ellipse-cap: an overlay option"),
    (["track", "{clip}", "-o", "{tmp}/out.txt"],
     "Invalid value for '-o' / '--output': {tmp}/out.txt: unknown output format '.txt' (use .csv, .h5 or .hdf5)"),
    (["track", "{clip}", "--overlay", "{tmp}/k.png"], "Invalid value for '--overlay': {tmp}/k.png: the overlay is an MPEG-4"),
    (["render", "{tracks}", "{clip}", "-o", "{tmp}/r.png"], "Invalid value for '-o' / '--output': {tmp}/r.png: the overlay"),
    (["render", "{tracks}", "{clip}", "-o", "{tmp}/r.mp4", "--contact-sheet", "{tmp}/s.jpg"],
     "Invalid value for '--contact-sheet': {tmp}/s.jpg: the picture is a PNG (use a .png name)"),
    (["eval", "{tracks}", "{tracks}", "--plot", "{tmp}/p.jpg"],
     "Invalid value for '--plot': {tmp}/p.jpg: the picture is a PNG (use a .png name)"),
])
def test_bad_option_values_and_options_that_do_not_go_together_are_usage_errors(tmp_path, args, message):
    """Items 6, 7 and 14: exit 2 after the usage line, naming the option; nothing written."""
    fill = {"clip": SAMPLE, "tracks": SAMPLE / "tracks.csv", "tmp": tmp_path}
    result = run_cli(*[a.format(**fill) for a in args])
    _one_error_line(result, 2, message.format(**fill))
    assert result.stderr.startswith(f"Usage: condtrack {args[0]} [OPTIONS]")
    assert not list(tmp_path.iterdir())


def test_max_std_without_a_covariance_is_warned():
    """Item 8: STK writes no covariance, so --max-std (or --set output.max_std) changes nothing: say so."""
    with pytest.warns(CondtrackWarning, match="^--max-std has no effect: method 'stk' writes no covariance$"):
        load_config(None, [], "stk", {"--max-std": "output.max_std=3.0"})
    with pytest.warns(CondtrackWarning, match="^--set output.max_std=3 has no effect: method 'stk' writes no covariance$"):
        load_config(None, ["output.max_std=3"], "stk")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert load_config(None, [], "mdr", {"--max-std": "output.max_std=3.0"}).output.max_std == 3.0


def test_a_set_that_an_option_overrides_is_warned():
    """``--forward-only --set output.backward=true`` ran forward only, ``-m stk --set filter.method=clf`` ran STK, without
    a word: the option is applied after the --set. The same value twice is no conflict."""
    with pytest.warns(CondtrackWarning, match="^--set output.backward=true has no effect: --forward-only sets "
                                              "output.backward to false$"):
        config = load_config(None, ["output.backward=true"], None, {"--forward-only": "output.backward=false"})
    assert config.output.backward is False
    with pytest.warns(CondtrackWarning, match="^--set filter.method=clf has no effect: -m sets filter.method to stk$"):
        assert load_config(None, ["filter.method=clf"], "stk").method == "stk"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_config(None, ["filter.method=stk", "output.backward=false"], "stk",
                    {"--forward-only": "output.backward=false"})


def test_max_std_without_a_covariance_is_warned_on_the_command_line(tmp_path):
    result = CliRunner().invoke(cli, [*TRACK_STK, "--max-std", "3", "-o", str(tmp_path / "t.csv")])
    assert result.exit_code == 0, result.output
    assert result.stderr.splitlines()[0] == "warning: --max-std has no effect: method 'stk' writes no covariance"


@pytest.mark.parametrize("content", [b"", b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 4])
def test_a_broken_video_gives_condtracks_error_line_only(tmp_path, content):
    """Item 10: FFmpeg printed ``moov atom not found`` before condtrack's line."""
    video, tracks = tmp_path / "clip.mp4", tmp_path / "t.csv"
    video.write_bytes(content)
    _track_csv(tracks, "inf")
    env = {key: value for key, value in os.environ.items() if key != "OPENCV_FFMPEG_LOGLEVEL"}
    for args in (["track", str(video), "-o", str(tmp_path / "out.csv")],
                 ["render", str(tracks), str(video), "-o", str(tmp_path / "out.mp4")]):
        result = subprocess.run([sys.executable, "-m", "condtrack_cli", *args], capture_output=True, text=True,
                                env=env, timeout=120)
        assert result.returncode == 1
        assert result.stderr == f"Error: {video}: not a readable video (OpenCV could not open it)\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.mp4", "t.csv"]


def test_eval_plot_without_covariances_prints_the_metrics_and_warns(tmp_path):
    """Item 11: --plot is "also draw": an STK run has nothing to plot, its metrics are still printed, exit 0."""
    pred = tmp_path / "stk.csv"
    assert CliRunner().invoke(cli, [*TRACK_STK, "-o", str(pred), "-q"]).exit_code == 0
    plot = tmp_path / "p.png"
    result = CliRunner().invoke(cli, ["eval", str(pred), str(SAMPLE / "tracks.csv"), "--json", "--plot", str(plot)])
    assert result.exit_code == 0, result.output
    assert result.stderr == "warning: --plot: the predictions hold no covariance: nothing to plot\n"
    scores = json.loads(result.stdout)
    assert scores["n_points"] == 64 and scores["cov50"] is None and 0.5 < scores["pts_within_2"] <= 1
    assert not plot.exists()


def _track_csv(path, dof: str, first_frame: int = 0) -> None:
    rows = "".join(f"0,{k},10.0,20.0,1,0,1,{dof},1,clf\n" for k in range(first_frame, first_frame + 3))
    path.write_text("point_id,frame,x,y,cov_xx,cov_xy,cov_yy,dof,visible,method\n" + rows)


@pytest.mark.parametrize("dof", ["0", "-3", "2", "1.5", "nan", "-inf"])
def test_a_dof_not_above_2_is_refused_showing_the_value(tmp_path, dof):
    """Item 12: the message shows the value read; nan is refused, as docs/schema.md allows only > 2 or inf."""
    path = tmp_path / "t.csv"
    _track_csv(path, dof)
    with pytest.raises(CondtrackError) as refused:
        read_tracks(path)
    assert str(refused.value) == (f"{path}: line 2 (point_id 0, frame 0): dof is {dof}, "
                                  "expected a number above 2 or inf (Gaussian)")


def _edited_track_csv(path, line: int, old: str, new: str):
    """The three-row track CSV of ``_track_csv`` (dof inf) at ``path`` with ``old`` replaced by ``new`` on file line
    ``line`` (the header is line 1), hand-edited; read_tracks' result."""
    _track_csv(path, "inf")
    lines = path.read_text().splitlines()
    lines[line - 1] = lines[line - 1].replace(old, new)
    path.write_text("\n".join(lines) + "\n")
    return read_tracks(path)


@pytest.mark.parametrize("x, y", [("nan", "20.0"), ("10.0", "inf")])
def test_a_row_without_a_finite_position_is_refused_showing_it(tmp_path, x, y):
    """docs/schema.md: a CSV row exists only where the point has a position, always finite; a hand-edited NaN on a
    visible row was read by info, eval and render without a word."""
    path = tmp_path / "t.csv"
    with pytest.raises(CondtrackError) as refused:
        _edited_track_csv(path, 3, "10.0,20.0", f"{x},{y}")
    assert str(refused.value) == (f"{path}: line 3 (point_id 0, frame 1): x, y is {x}, {y}: a row is a position, "
                                  "always finite")


@pytest.mark.parametrize("cov_xx, cov_yy", [("-1", "1"), ("1", "-inf")])
def test_a_negative_variance_is_refused_showing_it(tmp_path, cov_xx, cov_yy):
    """A hand-edited negative variance was read by info, eval and render, and eval counted the row as having no
    covariance; a variance is never negative (a covariance cov_xy may be, and nan / inf keep their meaning)."""
    path = tmp_path / "t.csv"
    with pytest.raises(CondtrackError) as refused:
        _edited_track_csv(path, 4, "20.0,1,0,1,", f"20.0,{cov_xx},0,{cov_yy},")
    assert str(refused.value) == (f"{path}: line 4 (point_id 0, frame 2): cov_xx, cov_yy is {cov_xx}, {cov_yy}: "
                                  "a variance is never negative")
    _edited_track_csv(path, 4, "20.0,1,0,1,", "20.0,inf,-0.5,inf,")


@pytest.mark.parametrize("cov", ["nan,0,1", "1,nan,1", "inf,0,nan"])
def test_a_covariance_partly_undefined_is_refused_showing_it(tmp_path, cov):
    """docs/schema.md: nan means the row has no covariance, so all three cells are nan or none is; a hand-edited row
    with one nan was read, and eval counted it as having no covariance."""
    path = tmp_path / "t.csv"
    with pytest.raises(CondtrackError) as refused:
        _edited_track_csv(path, 4, "20.0,1,0,1,", f"20.0,{cov},")
    assert str(refused.value) == (f"{path}: line 4 (point_id 0, frame 2): cov_xx, cov_xy, cov_yy is "
                                  f"{cov.replace(',', ', ')}: a covariance is undefined (nan) as a whole or not at all")
    assert np.isnan(_edited_track_csv(path, 4, "20.0,1,0,1,", "20.0,nan,nan,nan,")[0].cov[0, 2]).all()


@pytest.mark.parametrize("dof, value", [("2.5", 2.5), ("1e6", 1e6), ("inf", np.inf)])
def test_a_dof_above_2_or_inf_is_read(tmp_path, dof, value):
    path = tmp_path / "t.csv"
    _track_csv(path, dof)
    assert (read_tracks(path)[0].dof == value).all()


def test_info_on_a_csv_prints_no_query_frames(tmp_path):
    """Item 13: a CSV holds no queries; its first rows (here frame 4) are not the query frames."""
    path = tmp_path / "t.csv"
    _track_csv(path, "inf", first_frame=4)
    result = CliRunner().invoke(cli, ["info", str(path)])
    assert result.exit_code == 0, result.output
    assert "query frames:      n/a\n" in result.stdout


def test_warnings_are_warning_lines_in_the_paper_figures_script(tmp_path):
    """Item 15: ``make paper`` printed CondtrackWarnings as Python does, with the file, line and source line."""
    code = ("import sys, warnings; from condtrack_cli.evaluate import paper_figures; from condtrack_cli.errors import warn; "
            f"paper_figures.main(['--shared-data', {str(tmp_path)!r}]); warn('a'); warnings.warn('b', RuntimeWarning)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stderr.splitlines()[1:] == ["warning: a", "warning: RuntimeWarning: b"]


def test_the_command_lines_warnings_of_any_category_are_one_line(capsys):
    with warnings.catch_warnings():
        show_warnings(True)
        warnings.simplefilter("always")
        warnings.warn("b", RuntimeWarning)
    assert capsys.readouterr().err == "warning: RuntimeWarning: b\n"


def test_synth_refuses_an_existing_folder_without_force(tmp_path):
    """Item 17: synth silently replaced an existing scene folder."""
    scene = tmp_path / "s"
    args = ["synth", str(scene), "--scene", "ring", "--size", "64x64", "--frames", "2"]
    assert CliRunner().invoke(cli, args).exit_code == 0
    (scene / "00000.png").write_bytes(b"kept")
    _usage_error(CliRunner().invoke(cli, [*args, "--seed", "1"]), f"{scene}: the folder exists (--force replaces a scene folder)")
    assert (scene / "00000.png").read_bytes() == b"kept"
    assert CliRunner().invoke(cli, [*args, "--seed", "1", "--force"]).exit_code == 0
    assert (scene / "00000.png").read_bytes()[:4] == b"\x89PNG"
    root = tmp_path / "samples"
    (root / "occlusion").mkdir(parents=True)
    (root / "occlusion" / "scene.json").write_text("{}")
    _usage_error(CliRunner().invoke(cli, ["synth", str(root), "--samples"]), f"{root / 'occlusion'}: the folder exists")
    assert [p.name for p in root.iterdir()] == ["occlusion"]
    assert "--force" in CliRunner().invoke(cli, ["synth", "--help"]).output


def test_synth_takes_the_seeds_track_takes(tmp_path):
    """synth --seed took 99999999999999999999999 while track --seed stops at 2^63 - 1 (ct.MAX_SEED); both now take
    0 .. MAX_SEED."""
    from condtrack_cli import MAX_SEED

    result = CliRunner().invoke(cli, ["synth", str(tmp_path / "s"), "--scene", "ring", "--seed", str(MAX_SEED + 1)])
    assert result.exit_code == 2 and f"0<=x<={MAX_SEED}" in result.output and not (tmp_path / "s").exists()


def test_track_help_says_quiet_still_prints_a_batchs_failed_inputs():
    """Item 18: the README says so; --help said -q removed every warning and summary."""
    text = " ".join(CliRunner().invoke(cli, ["track", "--help"]).output.split())
    assert "-q, --quiet No progress bar, summary or warnings on stderr (a batch still prints its failed inputs)." in text
