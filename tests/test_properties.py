"""Property: any queries CSV, config or track CSV, valid or not, either works or fails cleanly (issues 16, 28).

Clean failure: exactly one ``Error:`` line on stderr, exit code 1 or 2, no
output file (nor temporary), no traceback (an exception out of ``main`` fails
the test). The command line runs in process (``main``) on a 4-frame 64 x 48
clip, with a bounded, derandomised set of examples.
"""

from __future__ import annotations

import string
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings, strategies as st

from condtrack_cli.cli import main
from condtrack_cli.io.write import CSV_COLUMNS

WIDTH, HEIGHT, N_FRAMES = 64, 48, 4

numbers = st.one_of(
    st.integers(-3, 70).map(str), st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["", " 7 ", "1e20", "9223372036854775808", "2.5", "abc", "0x10", "-0"]),
)
columns = st.one_of(
    st.permutations(["frame", "x", "y", "point_id"]).flatmap(lambda names: st.integers(2, 4).map(lambda n: list(names[:n]))),
    # issue 28.3: a misspelt or repeated column
    st.lists(st.sampled_from(["frame", "x", "y", "point_id", "pointid", "Frame", ""]), min_size=3, max_size=5),
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



def _assert_clean_failure(code: int, stderr: str) -> None:
    assert code in (1, 2), stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), stderr


# ---------------------------------------------------------------- configs (issue 28.6, 28.8)

config_names = st.sampled_from(["levels", "gamma", "name", "win_size", "block", "max_points", "template",
                                "hdf5_compression", "non_image_files", "stk", "smooth", "method"])
config_sections = st.sampled_from(["frames", "detect", "motion", "measure", "filter", "output", "nope"])


@st.composite
def config_yaml(draw) -> str:
    """A YAML config of known and unknown sections and keys; sometimes one line repeated (a key given twice)."""
    raw = draw(st.dictionaries(config_sections, st.one_of(
        st.dictionaries(config_names, st.one_of(config_values, st.dictionaries(config_names, config_values, max_size=2)),
                        max_size=3),
        config_values), max_size=3))
    lines = yaml.safe_dump(raw, sort_keys=False).splitlines()
    if lines and draw(st.booleans()):
        index = draw(st.integers(0, len(lines) - 1))
        lines.insert(index, lines[index])
    return "\n".join(lines) + "\n"


@settings(max_examples=30, derandomize=True, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(text=config_yaml())
def test_every_config_file_tracks_or_fails_cleanly(clip, capsys, text):
    with tempfile.TemporaryDirectory() as out_dir:
        config, out = Path(out_dir) / "c.yaml", Path(out_dir) / "out.csv"
        config.write_text(text, encoding="utf-8")
        code, stderr = _run(["track", str(clip), "-c", str(config), "-m", "stk", "-o", str(out), "-q"], capsys)
        if code == 0:
            assert out.is_file() and stderr == ""
        else:
            _assert_clean_failure(code, stderr)
            assert sorted(p.name for p in Path(out_dir).iterdir()) == ["c.yaml"]


# ---------------------------------------------------------------- track CSVs (issue 28.4, 28.20)

GROUND_TRUTH = "point_id,frame,x,y,visible\n" + "".join(f"{p},{f},{10 + f}.5,{20 + p},1\n" for p in (0, 1) for f in range(4))
cells = st.one_of(numbers, st.sampled_from(["clf", "stk", "abc"]))


@st.composite
def track_csv(draw) -> str:
    """A track CSV: mostly the schema's header and well-typed rows on a few points and frames, some cells replaced
    by anything, some rows repeated or cut short."""
    header = draw(st.one_of(st.just(list(CSV_COLUMNS)), st.permutations(CSV_COLUMNS).map(list)))
    well_typed = st.tuples(
        st.one_of(st.integers(-1, 2).map(str), st.just("9223372036854775808")), st.integers(-1, 5).map(str),
        st.floats(0, 70).map(repr), st.floats(0, 50).map(repr),
        st.sampled_from(["1.0", "nan", "inf"]), st.just("0"), st.sampled_from(["1.0", "nan", "inf"]),
        st.sampled_from(["0", "1", "2"]), st.sampled_from(["clf", "stk", "cnlf", "abc"]),
    ).map(list)
    rows = draw(st.lists(well_typed, max_size=8))
    for row in rows:
        if draw(st.integers(0, 3)) == 0:
            row[draw(st.integers(0, len(row) - 1))] = draw(cells)
        if draw(st.integers(0, 7)) == 0:
            del row[draw(st.integers(0, len(row) - 1)):]
    if rows and draw(st.booleans()):
        rows.append(list(rows[draw(st.integers(0, len(rows) - 1))]))
    return ",".join(header) + "\n" + "".join(",".join(row) + "\n" for row in rows)


@settings(max_examples=40, derandomize=True, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(text=track_csv(), command=st.sampled_from(["info", "eval"]))
def test_every_track_csv_is_read_or_refused_cleanly(capsys, text, command):
    with tempfile.TemporaryDirectory() as folder:
        tracks, truth = Path(folder) / "t.csv", Path(folder) / "gt.csv"
        tracks.write_text(text, encoding="ascii")
        truth.write_text(GROUND_TRUTH, encoding="ascii")
        code, stderr = _run([command, str(tracks), *([str(truth), "--json"] if command == "eval" else [])], capsys)
        if code != 0:
            _assert_clean_failure(code, stderr)
        else:
            assert "Error" not in stderr
        assert sorted(p.name for p in Path(folder).iterdir()) == ["gt.csv", "t.csv"]
