"""Start-up: ``condtrack --help`` loads no numerics library, and each command loads only what it runs."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import click
import pytest
from click.testing import CliRunner

from condtrack_cli.cli import COMMANDS, LazyGroup, cli
from conftest import FORCED_TERMINAL

#: Libraries ``condtrack --help`` must not import (each costs tens of milliseconds).
HEAVY = ("numpy", "cv2", "scipy", "h5py", "pydantic")

#: Runs the console entry point with the given arguments, then prints on stderr the modules it imported.
_PROBE = """
import json, sys
from condtrack_cli.cli import main
sys.argv = ["condtrack", *sys.argv[1:]]
try:
    main()
except SystemExit as exit_:
    code = exit_.code
print(json.dumps({"code": code, "modules": sorted(sys.modules)}), file=sys.stderr)
"""


def imported_by(*args: str, env: dict[str, str] | None = None) -> set[str]:
    """The modules a fresh ``condtrack ARGS`` process imported (it must exit 0); ``env``: its environment."""
    done = subprocess.run([sys.executable, "-c", _PROBE, *args], capture_output=True, text=True, timeout=300, env=env)
    report = json.loads(done.stderr.splitlines()[-1])
    assert report["code"] == 0, done.stderr
    return set(report["modules"])


@pytest.mark.parametrize("args", [["--help"], ["--version"], ["info", "--help"], ["render", "--help"],
                                  ["synth", "--help"], ["stages", "--help"], ["status", "--help"]])
def test_help_and_version_import_no_numerics(args):
    loaded = imported_by(*args)
    assert not [name for name in HEAVY if name in loaded]
    commands = {f"condtrack_cli.cli.{spec.partition(':')[0]}" for spec, _ in COMMANDS.values()}
    wanted = {f"condtrack_cli.cli.{args[0]}"} if len(args) == 2 else set()
    assert commands & loaded == wanted  # a command's help imports its own module, no other


def test_a_csv_run_imports_neither_hdf5_nor_the_other_commands(tmp_path):
    from condtrack_cli.frames.synthetic import make_scene, write_scene

    folder = write_scene(make_scene("camera_motion", seed=0, size=(96, 72), n_frames=3), tmp_path / "clip")
    loaded = imported_by("track", str(folder), "-m", "stk", "-o", str(tmp_path / "out.csv"), "-q")
    assert {"numpy", "cv2"} <= loaded  # it did track
    assert not {"h5py", "rich", "matplotlib", "dask"} & loaded
    commands = {f"condtrack_cli.cli.{spec.partition(':')[0]}" for spec, _ in COMMANDS.values()}
    assert commands & loaded == {"condtrack_cli.cli.track"}


def test_a_run_whose_stderr_is_no_terminal_does_not_load_rich(tmp_path, tiny_clip):
    """No bar is drawn on a pipe, so rich (tens of ms of import) is not loaded, -q or not; forced, it is."""
    plain = {k: v for k, v in os.environ.items() if k not in ("TTY_COMPATIBLE", "FORCE_COLOR")}
    track = ("track", str(tiny_clip), "-p", str(tiny_clip / "queries.csv"), "-m", "stk")
    assert "rich" not in imported_by(*track, "-o", str(tmp_path / "a.csv"), env=plain)
    assert "rich" in imported_by(*track, "-o", str(tmp_path / "b.csv"), env={**plain, **FORCED_TERMINAL})


@pytest.fixture(scope="module")
def tiny_clip(tmp_path_factory):
    """A 96x72, 3-frame synthetic scene with its queries."""
    from condtrack_cli.frames.synthetic import make_scene, write_scene

    return write_scene(make_scene("camera_motion", seed=0, size=(96, 72), n_frames=3),
                       tmp_path_factory.mktemp("startup") / "clip")


#: What no single-input run imports: the robust local field and the paper's regression (the default motion is
#: ``dis``) and the batch machinery.
NEVER_FOR_ONE_INPUT = {"condtrack_cli.motion.local", "condtrack_cli.motion.regression", "condtrack_cli.batch",
                       "condtrack_cli.batch.dask"}


@pytest.mark.parametrize("method, others", [("stk", ("clf", "cnlf", "auto")), ("clf", ("cnlf", "auto", "stk")),
                                            ("auto", ("stk",))])
def test_a_run_imports_only_the_stages_it_uses(tmp_path, tiny_clip, method, others):
    loaded = imported_by("track", str(tiny_clip), "-p", str(tiny_clip / "queries.csv"), "-m", method,
                         "-o", str(tmp_path / "out.h5"), "-q")
    assert f"condtrack_cli.filters.{method}" in loaded
    assert not {f"condtrack_cli.filters.{other}" for other in others} & loaded
    assert not NEVER_FOR_ONE_INPUT & loaded


#: The packages of the stages' implementations (and their interfaces).
STAGE_PACKAGES = tuple(f"condtrack_cli.{package}." for package in ("frames", "detect", "motion", "measure", "filters"))


def test_listing_the_stages_imports_none_of_them():
    loaded = imported_by("stages")
    assert not [name for name in HEAVY if name in loaded]
    assert not [name for name in loaded if name.startswith(STAGE_PACKAGES + ("condtrack_cli.io.",))]


def test_reading_a_track_file_imports_no_stage(tmp_path, tiny_clip):
    imported_by("track", str(tiny_clip), "-p", str(tiny_clip / "queries.csv"), "-o", str(tmp_path / "out.h5"), "-q")
    loaded = imported_by("info", str(tmp_path / "out.h5"))
    assert "h5py" in loaded and "cv2" not in loaded
    assert not [name for name in loaded if name.startswith(STAGE_PACKAGES)]


def test_the_lazy_help_lists_what_the_commands_say():
    eager = click.Group(cli.name, help=cli.help, params=cli.params, context_settings=cli.context_settings)
    for name in COMMANDS:
        command = LazyGroup.get_command(cli, None, name)
        assert command.name == name
        eager.add_command(command)
    assert CliRunner().invoke(cli, ["--help"]).output == CliRunner().invoke(eager, ["--help"]).output


def test_an_unknown_command_is_refused():
    result = CliRunner().invoke(cli, ["trak"])
    assert result.exit_code == 2 and "No such command 'trak'" in result.output


def test_no_command_shows_the_help_on_stderr():
    """``condtrack`` alone printed a usage line, then ``Error: Usage: ...`` holding the whole help (Click 8.2's
    NoArgsIsHelpError read as an error message); now the help alone, on stderr, exit 2, as Click shows it."""
    done = subprocess.run([sys.executable, "-c", "from condtrack_cli.cli import main; main()"], capture_output=True,
                          text=True, timeout=300)
    assert (done.returncode, done.stdout) == (2, "")
    assert done.stderr.startswith("Usage: condtrack [OPTIONS] COMMAND [ARGS]...\n\n  Batch point tracking")
    assert "\nCommands:\n" in done.stderr and "Error" not in done.stderr
