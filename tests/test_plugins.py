"""Stages from other packages, and every registered stage of every kind, run end to end."""

from __future__ import annotations

import dataclasses
import errno
import functools
import os
import subprocess
import sys
import textwrap

import cv2
import numpy as np
import pytest

import condtrack_cli as ct
from condtrack_cli import registry
from condtrack_cli.settings import StageSettings
from condtrack_cli.evaluate.groundtruth import load_gt_csv
from condtrack_cli.io.formats import FORMATS

from conftest import SAMPLES

SAMPLE = SAMPLES / "ring"

#: A filter package that condtrack does not know: every point stays at its query position.
HOLD_PACKAGE = '''
    import numpy as np
    from condtrack_cli.settings import StageSettings
    from condtrack_cli.filters.base import Tracker
    from condtrack_cli.registry import register

    class HoldSettings(StageSettings):
        variance: float = 4.0

    class HoldTracker(Tracker):
        method = "hold"

        def __init__(self, settings, queries, info):
            super().__init__(queries, info)
            self.variance = settings.variance

        def _start(self, index, frame):
            self.cov[index] = self.variance * np.eye(2)

        def _advance(self, index, prev, frame, motion):
            """Positions, covariances and visibility stay as they are."""

    @register("filter", "hold", HoldSettings, "every point stays at its query position")
    def make_hold(settings, queries, info, **_context):
        return HoldTracker(settings, queries, info)
'''


def installed(site, module, source, entry):
    """``site``, a folder holding the package ``module`` (its ``source``) and its dist-info with the
    ``condtrack.stages`` entry point ``entry = module``."""
    site.mkdir(exist_ok=True)
    (site / f"{module}.py").write_text(textwrap.dedent(source))
    info = site / f"{module}-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {module.replace('_', '-')}\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text(f"[condtrack.stages]\n{entry} = {module}\n")
    return site


@pytest.fixture
def hold_package(tmp_path):
    """A folder holding the package ``thirdparty_hold`` and its dist-info with a ``condtrack.stages`` entry point."""
    return installed(tmp_path / "site", "thirdparty_hold", HOLD_PACKAGE, "hold")


def run_with(site, *args):
    """``python -m condtrack_cli ARGS`` (or ``python -c`` code) with ``site`` on the path, as an installed package."""
    env = {**os.environ, "PYTHONPATH": str(site)}
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, env=env)


def test_entry_point_filter_tracks_renders_and_benchmarks(tmp_path, hold_package):
    queries = SAMPLE / "queries.csv"
    for suffix in (".h5", ".csv"):
        done = run_with(hold_package, "-m", "condtrack_cli", "track", str(SAMPLE), "-p", str(queries), "-m", "hold",
                        "-o", str(tmp_path / f"hold{suffix}"), "-q")
        assert done.returncode == 0, done.stderr
    rows = (tmp_path / "hold.csv").read_text().splitlines()[1:]
    assert rows and {row.rsplit(",", 1)[1] for row in rows} == {"hold"}
    sheet = tmp_path / "sheet.png"
    done = run_with(hold_package, "-m", "condtrack_cli", "render", str(tmp_path / "hold.h5"), str(SAMPLE),
                    "-o", str(tmp_path / "hold.mp4"), "--contact-sheet", str(sheet))
    assert done.returncode == 0, done.stderr
    from condtrack_cli.render import OTHER_COLOUR

    assert (cv2.imread(str(sheet)) == OTHER_COLOUR).all(axis=-1).sum() > 100  # the points, in the default colour
    listed = run_with(hold_package, "-c", "from condtrack_cli import registry; print(*registry.tracking_methods())")
    assert listed.stdout.split() == ["stk", "mdr", "clf", "cnlf", "auto", "hold"]  # what make bench runs
    helped = run_with(hold_package, "-m", "condtrack_cli", "track", "--help")
    assert "auto|hold]" in helped.stdout

    # read back in this process, with the package registered the same way
    sys.path.insert(0, str(hold_package))
    registry.reload_entry_points()
    try:
        back = ct.read_tracks(tmp_path / "hold.h5")
        assert set(back.method) == {"hold"}
        assert registry.method_code("hold") == 4
        held = np.broadcast_to(back.queries.xy[:, None], back.xy.shape)
        assert np.array_equal(back.xy, held)  # hold keeps each point at its query, on every frame
        assert np.array_equal(ct.read_tracks(tmp_path / "hold.csv").xy, np.round(held, 6))
    finally:
        sys.path.remove(str(hold_package))
        registry._STAGES["filter"].pop("hold", None)
        registry.reload_entry_points()
        sys.modules.pop("thirdparty_hold", None)


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    """A 160x120, 5-frame synthetic camera-motion scene with exact ground truth."""
    from condtrack_cli.frames.synthetic import make_scene, write_scene

    return write_scene(make_scene("camera_motion", seed=0, size=(160, 120), n_frames=5),
                       tmp_path_factory.mktemp("tiny") / "scene")


def every_stage() -> list[tuple[str, str]]:
    return [(kind, name) for kind in registry.KINDS for name in registry.names(kind)]


@pytest.mark.parametrize("kind, name", every_stage())
def test_every_registered_stage_runs_on_a_tiny_scene(tmp_path, tiny_scene, kind, name):
    """Each stage, chosen by name in the config, tracks the tiny scene to within 0.5 px (median) of the truth."""
    config = {"filter": {"method": name}} if kind == "filter" else (
        {} if kind == "output" else {kind: {"name": name}})
    queries = None if kind == "detect" else tiny_scene / "queries.csv"
    t = ct.track(str(tiny_scene), queries=queries, config=config)
    if kind == "detect":
        assert len(t.queries) > 0 and np.isfinite(t.xy).all()
        return
    truth = load_gt_csv(tiny_scene / "tracks.csv")
    error = np.linalg.norm(t.xy - truth.gt_xy, axis=-1)[truth.known]
    assert np.median(error) < 0.5
    if kind == "output":
        suffix = next(s for s, format_name in FORMATS.items() if format_name == name)
        (t.to_csv if name == "csv" else t.to_hdf5)(tmp_path / f"out{suffix}")
        assert np.allclose(ct.read_tracks(tmp_path / f"out{suffix}").xy, t.xy, atol=1e-6, equal_nan=True)


@pytest.mark.parametrize("returned, message", [
    (np.zeros((3, 3)), r"detect stage 'bad' returned shape \(3, 3\), dtype float64; expected an \(M, 2\)"),
    (np.zeros(3), r"detect stage 'bad' returned shape \(3,\)"),
    (np.full((3, 2), "1"), r"detect stage 'bad' returned shape \(3, 2\), dtype <U1"),
    (None, r"detect stage 'bad' returned a NoneType"),
    (np.array([[20.0, 20.0], [np.nan, 5.0]]), r"detect stage 'bad': point 1 is not finite"),
    (np.array([[20.0, 20.0], [-50.0, 5.0]]), r"detect stage 'bad': row 1: point \(-50, 5\) is outside the 320x240"),
])
def test_a_detect_stage_returning_what_its_contract_does_not_allow_is_refused(returned, message):
    """A detector's output is checked against detect/interface.py: a one-line error naming the stage, not a numpy
    traceback deep in the filter (or a point outside the frame tracked)."""

    class BadSettings(StageSettings):
        pass

    registry.register("detect", "bad", BadSettings)(lambda settings, gray: returned)
    try:
        with pytest.raises(ct.CondtrackError, match=message):
            ct.track(str(SAMPLE), config={"detect": {"name": "bad"}, "filter": {"method": "mdr"}})
    finally:
        registry._STAGES["detect"].pop("bad", None)


def test_a_filter_stage_writing_what_the_readers_refuse_is_not_written(tmp_path):
    """A filter stage's negative variance was written to a track file that condtrack itself then refused to read;
    now the write is refused, naming the value and the filter, and no file is left."""
    from condtrack_cli.filters.base import Tracker

    class NegativeSettings(StageSettings):
        pass

    class NegativeTracker(Tracker):
        method = "negative"

        def _start(self, index, frame):
            self.cov[index] = np.eye(2)

        def _advance(self, index, prev, frame, motion):
            self.cov[index] = -np.eye(2)

    registry.register("filter", "negative", NegativeSettings)(
        lambda settings, queries, info, **_context: NegativeTracker(queries, info))
    try:
        tracks = ct.track(str(SAMPLE), queries=SAMPLE / "queries.csv", method="negative")
        for name in ("out.csv", "out.h5"):
            with pytest.raises(ct.CondtrackError, match=rf"{name}: not written: cov at point_id 0, frame 1 is "
                                                        r"\[\[-1.0, -0.0\], \[-0.0, -1.0\]\]: a variance is never "
                                                        r"negative \(filter 'negative'\)"):
                tracks.to_csv(tmp_path / name) if name.endswith(".csv") else tracks.to_hdf5(tmp_path / name)
        assert not list(tmp_path.iterdir())
    finally:
        registry._STAGES["filter"].pop("negative", None)


def test_a_stage_whose_settings_lack_a_default_is_not_registered():
    """A filter whose settings model had a field without a default broke every run (any -m: 'config key
    filter.req.gain: Field required') and `stages --default-config` (a yaml traceback); now register refuses it,
    which an entry point's loading reports as a warning, leaving its stages out."""
    from pydantic import Field

    from condtrack_cli.config import default_yaml, load_config

    class RequiredSettings(StageSettings):
        gain: float = Field(description="no default")

    try:
        with pytest.raises(ValueError, match="filter stage 'req': setting gain has no default"):
            registry.register("filter", "req", RequiredSettings)(lambda settings, queries, info, **_context: None)
        assert "req" not in registry.names("filter")
        assert load_config(None).method == "auto" and "req:" not in default_yaml()
    finally:
        registry._STAGES["filter"].pop("req", None)


@pytest.mark.parametrize("change, message", [
    (None, None),
    (lambda m: dataclasses.replace(m, z=m.z[:-1]), r"measure stage 'odd' returned z of shape \((\d+), 2\); "
                                                   r"expected \((\d+), 2\) numbers"),
    (lambda m: dataclasses.replace(m, R=m.R[:, 0]), r"returned R of shape \((\d+), 2\); expected \(\1, 2, 2\)"),
    (lambda m: dataclasses.replace(m, R=-m.R), r"measure stage 'odd' returned an R with a NaN or a negative variance"),
])
def test_a_measure_stage_returning_what_its_contract_does_not_allow_is_refused(change, message):
    """A measure stage from outside condtrack (the built-in SSD, its measurements altered) whose arrays break
    measure/interface.py made a numpy traceback deep in the filter; now a one-line error names the stage. Unaltered,
    it tracks as the built-in stage does (its optional methods, as resized for the drift check, still used)."""
    from condtrack_cli.measure.response import SSDSettings
    from condtrack_cli.measure.ssd import SSDMeasure

    class Altered(SSDMeasure):
        def measure(self, *args):
            found = super().measure(*args)
            return found if change is None else change(found)

    registry.register("measure", "odd", SSDSettings)(lambda settings, **_context: Altered(settings))
    track = functools.partial(ct.track, str(SAMPLE), queries=SAMPLE / "queries.csv", method="clf")
    config = {"filter": {"clf": {"drift_check_template": 15}}}
    try:
        if message is None:
            ours = track(config={**config, "measure": {"name": "odd"}})
            assert np.array_equal(ours.xy, track(config=config).xy, equal_nan=True)
        else:
            with pytest.raises(ct.CondtrackError, match=message):
                track(config={"measure": {"name": "odd"}})
    finally:
        registry._STAGES["measure"].pop("odd", None)


def test_a_stage_whose_settings_are_not_stage_settings_is_not_registered():
    """Settings as a plain pydantic model took a misspelt key ('stpe') and a string for an int silently; register
    now refuses a model that is not a StageSettings, as README asks of it."""
    from pydantic import BaseModel

    class PlainSettings(BaseModel):
        step: int = 3

    try:
        with pytest.raises(ValueError, match="detect stage 'plain': settings .* is not a subclass of "
                                             "condtrack_cli.settings.StageSettings"):
            registry.register("detect", "plain", PlainSettings)(lambda settings, gray: np.zeros((0, 2)))
        assert "plain" not in registry.names("detect")
    finally:
        registry._STAGES["detect"].pop("plain", None)


#: A filter package whose tracker fails on frame 1 with an exception of its own.
BROKEN_PACKAGE = '''
    import numpy as np
    from condtrack_cli.settings import StageSettings
    from condtrack_cli.filters.base import Tracker
    from condtrack_cli.registry import register

    class BrokenSettings(StageSettings):
        pass

    class BrokenTracker(Tracker):
        method = "broken"

        def _start(self, index, frame):
            self.cov[index] = np.eye(2)

        def _advance(self, index, prev, frame, motion):
            raise RuntimeError("out of cheese")

    @register("filter", "broken", BrokenSettings)
    def make_broken(settings, queries, info, **_context):
        return BrokenTracker(queries, info)
'''


@pytest.mark.parametrize("suffix", [".h5", ".csv"])
def test_a_plugin_stage_raising_is_one_error_line_and_no_output(tmp_path, suffix):
    """A plugin's filter raising a RuntimeError of its own ended `condtrack track` in a traceback; now one `Error:`
    line names the stage, the plugin and the exception, the exit code is 1 and no output file is left."""
    site = installed(tmp_path / "site", "thirdparty_broken", BROKEN_PACKAGE, "broken")
    output = tmp_path / f"out{suffix}"
    done = run_with(site, "-m", "condtrack_cli", "track", str(SAMPLE), "-p", str(SAMPLE / "queries.csv"),
                    "-m", "broken", "-o", str(output), "-q")
    assert done.returncode == 1
    assert done.stderr == ("Error: filter stage 'broken' (plugin thirdparty_broken) raised RuntimeError: "
                           "out of cheese\n")
    assert not output.exists() and sorted(path.name for path in tmp_path.iterdir()) == ["site"]


class RaisingSettings(StageSettings):
    pass


def raising(*_args, **_kwargs):
    raise RuntimeError("out of cheese")


def raising_stage(kind: str):
    """A factory of ``kind`` whose stage raises RuntimeError in the method the pipeline calls (the factory itself
    for detect), the rest of its work the built-in stage's."""
    from condtrack_cli.filters.base import Tracker
    from condtrack_cli.frames.readers import FrameSettings, open_frames
    from condtrack_cli.measure.ssd import SSDMeasure
    from condtrack_cli.motion.local import make_robust_motion
    from condtrack_cli.motion.robust import RobustMotionSettings

    class Frames:
        def __init__(self, path):
            self.source = open_frames(FrameSettings(), path)
            self.info = self.source.info

        def __iter__(self):
            yield next(iter(self.source))
            raising()

    class Measure(SSDMeasure):
        measure = raising

    def motion(settings):
        built = make_robust_motion(RobustMotionSettings())
        return dataclasses.replace(built, global_motion=type("Fit", (), {"fit": raising})())

    class Raising(Tracker):
        method = "raising"

        def _start(self, index, frame):
            self.cov[index] = np.eye(2)

        _advance = raising

    return {"frames": lambda settings, path: Frames(path), "detect": raising, "motion": motion,
            "measure": lambda settings: Measure(settings),
            "filter": lambda settings, queries, info, **_context: Raising(queries, info)}[kind]


@pytest.mark.parametrize("kind", ["frames", "detect", "motion", "measure", "filter"])
def test_a_plugin_stage_raising_is_a_condtrack_error_chained_to_its_exception(kind):
    """In Python, what a plugin's stage raises is a CondtrackError naming the stage, its ``__cause__`` the plugin's
    own exception (its traceback), wherever the pipeline calls the stage (the motion on its own thread too)."""
    from condtrack_cli.measure.response import SSDSettings

    settings = SSDSettings if kind == "measure" else RaisingSettings
    registry.register(kind, "raising", settings)(raising_stage(kind))
    config = {"filter": {"method": "raising"}} if kind == "filter" else {kind: {"name": "raising"}, "filter": {
        "method": "clf"}}
    queries = None if kind == "detect" else SAMPLE / "queries.csv"
    try:
        with pytest.raises(ct.CondtrackError, match=rf"^{kind} stage 'raising' \(plugin [\w.]*test_plugins\) raised "
                                                    r"RuntimeError: out of cheese$") as raised:
            ct.track(str(SAMPLE), queries=queries, config=config)
        assert isinstance(raised.value.__cause__, RuntimeError)
    finally:
        registry._STAGES[kind].pop("raising", None)


def test_a_plugin_motion_stage_s_field_source_raising_is_a_condtrack_error():
    """A motion plugin's ``field_source`` (motion/interface.py), which the pipeline runs in a thread of its own with
    more than one OpenCV thread, is guarded as its estimators are: what it raises is one CondtrackError naming the
    stage, chained to the plugin's exception."""
    import cv2

    from condtrack_cli.motion.dense import DisMotionSettings, make_dis_motion

    class Field:
        compute = staticmethod(raising)

        @staticmethod
        def prime(prev, cur, field):
            raise AssertionError("never reached")

    def motion(settings):
        return dataclasses.replace(make_dis_motion(DisMotionSettings()), field_source=Field())

    registry.register("motion", "raising_field", RaisingSettings)(motion)
    before = cv2.getNumThreads()
    cv2.setNumThreads(2)
    try:
        with pytest.raises(ct.CondtrackError, match=r"^motion stage 'raising_field' \(plugin [\w.]*test_plugins\) "
                                                    r"raised RuntimeError: out of cheese$") as raised:
            ct.track(str(SAMPLE), queries=SAMPLE / "queries.csv", config={"motion": {"name": "raising_field"}},
                     method="clf")
        assert isinstance(raised.value.__cause__, RuntimeError)
    finally:
        cv2.setNumThreads(before)
        registry._STAGES["motion"].pop("raising_field", None)


def test_a_plugin_stage_s_property_raising_is_a_condtrack_error():
    """A frame source whose ``info`` is a property (the input opened lazily) raising ended `condtrack track` in a
    traceback: only the stage's methods were called through StageSpec.call. Reading an attribute is too now, and
    ``hasattr`` still answers False for one the stage lacks."""
    from condtrack_cli.frames.readers import FrameSettings, open_frames

    class Lazy:
        def __init__(self, path):
            self.source = open_frames(FrameSettings(), path)

        @property
        def info(self):
            raising()

        def __iter__(self):
            return iter(self.source)

    registry.register("frames", "lazy", RaisingSettings)(lambda settings, path: Lazy(path))
    try:
        assert not hasattr(registry.get("frames", "lazy").build(RaisingSettings(), str(SAMPLE)), "read")
        with pytest.raises(ct.CondtrackError, match=r"^frames stage 'lazy' \(plugin [\w.]*test_plugins\) raised "
                                                    r"RuntimeError: out of cheese$") as raised:
            ct.track(str(SAMPLE), queries=SAMPLE / "queries.csv", config={"frames": {"name": "lazy"}}, method="clf")
        assert isinstance(raised.value.__cause__, RuntimeError)
    finally:
        registry._STAGES["frames"].pop("lazy", None)


def test_only_a_plugin_stage_is_wrapped_a_built_in_bug_keeps_its_exception(monkeypatch):
    """The same failing measurement: from a plugin, a CondtrackError; in the built-in SSD stage, the RuntimeError
    itself and its traceback (a bug report)."""
    from condtrack_cli.measure.response import SSDSettings
    from condtrack_cli.measure.ssd import SSDMeasure

    track = functools.partial(ct.track, str(SAMPLE), queries=SAMPLE / "queries.csv", method="clf")
    registry.register("measure", "raising", SSDSettings)(raising_stage("measure"))
    try:
        with pytest.raises(ct.CondtrackError, match="measure stage 'raising'"):
            track(config={"measure": {"name": "raising"}})
    finally:
        registry._STAGES["measure"].pop("raising", None)
    monkeypatch.setattr(SSDMeasure, "measure", raising)
    with pytest.raises(RuntimeError, match="out of cheese") as raised:
        track()
    assert not isinstance(raised.value, ct.CondtrackError)


@pytest.mark.parametrize("raised, message", [
    (OSError(errno.ENOSPC, "No space left on device"), "{out}: no space left on device, in {stage}"),
    (PermissionError(errno.EACCES, "Permission denied"), "{out}: cannot write (Permission denied), in {stage}"),
    (RuntimeError("out of cheese"), "{out}: not written: {stage} raised RuntimeError: out of cheese"),
])
def test_a_plugin_writer_raising_names_the_file_and_the_stage(tmp_path, monkeypatch, capsys, raised, message):
    """A plugin's output writer raising OSError said neither the file nor the usual write error's words (the stage's
    message alone); now one `Error:` line names the file as every other write error does, then the stage, exit 1 and
    no file (nor its temporary) left."""
    from condtrack_cli.cli import main
    from condtrack_cli.io.interface import OutputSettings

    def failing_writer(tracks, path, info, meta, settings):
        path.write_text("point_id,frame\n0,")  # a partial file, then the failure
        raise raised

    monkeypatch.setitem(registry._STAGES["output"], "csv", registry._STAGES["output"]["csv"])
    registry.register("output", "csv", OutputSettings)(failing_writer)
    out = tmp_path / "out.csv"
    monkeypatch.setattr(sys, "argv", ["condtrack", "track", str(SAMPLE), "-p", str(SAMPLE / "queries.csv"), "-m", "stk",
                                      "-o", str(out), "-q"])
    with pytest.raises(SystemExit) as stop:
        main()
    stage = f"output stage 'csv' (plugin {__name__})"
    assert (stop.value.code, capsys.readouterr().err) == (1, f"Error: {message.format(out=out, stage=stage)}\n")
    assert list(tmp_path.iterdir()) == []
