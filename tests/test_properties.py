"""Property: any queries CSV and config, valid or not, either tracks or fails cleanly (issue 16).

Clean failure: exactly one ``Error:`` line on stderr, exit code 1 or 2, no
output file (nor temporary). The command line runs in process (``main``) on a
4-frame 64 x 48 clip, with a bounded, derandomised set of examples.
"""

from __future__ import annotations

import string
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from condtrack_cli.cli import main

WIDTH, HEIGHT, N_FRAMES = 64, 48, 4

numbers = st.one_of(
    st.integers(-3, 70).map(str), st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["", " 7 ", "1e20", "9223372036854775808", "2.5", "abc", "0x10", "-0"]),
)
columns = st.permutations(["frame", "x", "y", "point_id"]).flatmap(
    lambda names: st.integers(2, 4).map(lambda n: list(names[:n]))
)


@st.composite
def queries_csv(draw) -> str:
    header = draw(columns)
    rows = draw(st.lists(st.lists(numbers, min_size=len(header), max_size=len(header)), min_size=0, max_size=4))
    bom = "\ufeff" if draw(st.booleans()) else ""
    return bom + ",".join(header) + "\n" + "".join(",".join(row) + "\n" for row in rows)


config_values = st.one_of(st.integers(-2, 40), st.floats(allow_nan=True, allow_infinity=True),
                          st.text(string.ascii_letters, max_size=4), st.booleans(), st.none())
config_keys = st.sampled_from([
    "filter.stk.win_size", "filter.stk.levels", "filter.stk.fb_threshold", "motion.levels", "detect.block",
    "detect.max_points", "filter.auto.integration_frames", "filter.auto.evidence_margin", "filter.auto.lost_evidence",
    "output.hdf5_compression",
    "measure.template", "filter.nope", "nowhere.key",
])


@pytest.fixture(scope="module")
def clip():
    with tempfile.TemporaryDirectory() as root:
        folder = Path(root) / "frames"
        folder.mkdir()
        rng = np.random.default_rng(0)
        texture = cv2.GaussianBlur(rng.integers(0, 256, (HEIGHT, WIDTH)).astype(np.uint8), (0, 0), 1.5)
        for k in range(N_FRAMES):
            cv2.imwrite(str(folder / f"{k}.png"), np.roll(texture, k, axis=1))
        yield folder


def _run(args: list[str], capsys) -> tuple[int, str]:
    old = sys.argv
    sys.argv = ["condtrack", *args]
    try:
        with pytest.raises(SystemExit) as stop:
            main()
    finally:
        sys.argv = old
    code = stop.value.code
    return (code if isinstance(code, int) else 0), capsys.readouterr().err


@settings(max_examples=40, derandomize=True, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(text=queries_csv(), sets=st.lists(st.tuples(config_keys, config_values), max_size=2),
       method=st.sampled_from(["stk", "mdr"]), suffix=st.sampled_from([".csv", ".h5"]))
def test_every_run_tracks_or_fails_cleanly(clip, capsys, text, sets, method, suffix):
    with tempfile.TemporaryDirectory() as out_dir:
        queries, out = Path(out_dir) / "q.csv", Path(out_dir) / f"out{suffix}"
        queries.write_text(text, encoding="utf-8")
        overrides = [arg for key, value in sets for arg in ("--set", f"{key}={value}")]
        code, stderr = _run(["track", str(clip), "-p", str(queries), "-m", method, *overrides, "-o", str(out), "-q"],
                            capsys)
        if code == 0:
            assert out.is_file() and stderr == ""
        else:
            assert code in (1, 2), stderr
            lines = stderr.strip().splitlines()
            assert len(lines) == 1 and lines[0].startswith("Error: "), stderr
            assert sorted(p.name for p in Path(out_dir).iterdir()) == ["q.csv"]
