"""The wiring of issue 15: only the pipeline's layer reads the config, and a filter gets the motion it asks for, once per pair."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

import condtrack_cli as ct
from condtrack_cli.motion.dense import DisGlobalMotion, DisLocalMotion
from condtrack_cli.motion.local import LocalMotion
from condtrack_cli.motion.robust import GlobalMotion

PACKAGE = Path(ct.__file__).parent

#: Modules that may read the Config: the commands, the API and drivers, the pipeline, the hashes, the evaluation.
CONFIG_READERS = ("config.py", "cli/", "api.py", "run.py", "batch/", "pipeline.py",
                  "hashes.py",
                  "evaluate/")


def imports_config(path: Path) -> bool:
    """Whether the module at ``path`` imports ``condtrack_cli.config`` (or ``config`` from ``condtrack_cli``)."""
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import) and any(alias.name == "condtrack_cli.config" for alias in node.names):
            return True
        if isinstance(node, ast.ImportFrom) and (node.module == "condtrack_cli.config" or (
                node.module == "condtrack_cli" and any(alias.name == "config" for alias in node.names))):
            return True
    return False


def test_no_stage_imports_the_config():
    modules = [path.relative_to(PACKAGE).as_posix() for path in PACKAGE.rglob("*.py")]
    readers = [name for name in modules if imports_config(PACKAGE / name)]
    assert "pipeline.py" in readers  # the scan finds what it looks for
    assert [name for name in readers if not name.startswith(CONFIG_READERS)] == []


@pytest.fixture(scope="module")
def tiny_scene(tmp_path_factory):
    """A 160x120, 5-frame synthetic camera-motion scene and 6 query points on frame 0."""
    from condtrack_cli.frames.synthetic import make_scene, write_scene

    folder = write_scene(make_scene("camera_motion", seed=0, size=(160, 120), n_frames=5),
                         tmp_path_factory.mktemp("wiring") / "scene")
    xy = np.column_stack((np.linspace(40, 120, 6), np.linspace(30, 90, 6)))
    return folder, np.column_stack((np.zeros(6), xy))


@pytest.mark.filterwarnings("ignore:.*queries are untrackable:condtrack_cli.errors.CondtrackWarning")  # incidental queries (issue 29)
@pytest.mark.parametrize("stage, estimators", [
    ("dis", (DisGlobalMotion, DisLocalMotion)),
    ("robust", (GlobalMotion, LocalMotion)),
])
@pytest.mark.parametrize("method, dynamics, expected", [
    ("stk", "select", (0, 0)),  # STK estimates its own motion (OpenCV LK)
    ("mdr", "select", (4, 0)),
    ("clf", "global", (4, 0)),  # the paper's CLF: the global fit alone
    ("clf", "select", (4, 4)),
    ("cnlf", "select", (4, 4)),
    ("auto", "select", (4, 4)),  # its CLF and CNLF share each pair's fit and field
])
def test_each_frame_pair_gets_the_motion_the_filter_needs_once(monkeypatch, tiny_scene, method, dynamics, expected,
                                                              stage, estimators):
    """Global fits and local fields estimated over the 4 frame pairs of one forward pass, per method and motion stage."""
    calls = {"global": 0, "local": 0}
    global_motion, local_motion = estimators
    fit, field = global_motion.fit, local_motion.field

    def counted_fit(self, prev, cur):
        calls["global"] += 1
        return fit(self, prev, cur)

    def counted_field(self, prev, cur, global_fit):
        calls["local"] += 1
        return field(self, prev, cur, global_fit)

    monkeypatch.setattr(global_motion, "fit", counted_fit)
    monkeypatch.setattr(local_motion, "field", counted_field)
    folder, queries = tiny_scene
    t = ct.track(str(folder), queries=queries, config={"motion": {"name": stage},
                                                       "filter": {"method": method, "clf": {"dynamics": dynamics}}})
    assert np.isfinite(t.xy).all()
    assert (calls["global"], calls["local"]) == expected
