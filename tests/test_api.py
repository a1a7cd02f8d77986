"""The Python API: the README example runs, ct.track equals condtrack track bit for bit, read_tracks round-trips."""

from __future__ import annotations

import copy
import json
import re
import subprocess
import sys
from pathlib import PurePosixPath

import h5py
import numpy as np
import pytest

import condtrack_cli as ct
from condtrack_cli.config import load_config
from condtrack_cli.errors import CondtrackError, InvalidArgument
from condtrack_cli.io.read import read_tracks as read_result

from conftest import REPO, SAMPLES

SAMPLE = SAMPLES / "occlusion"
DATASETS = ("tracks/xy", "tracks/cov", "tracks/visible", "tracks/method_code", "tracks/point_id", "queries",
            "measurements/z", "measurements/R")


def readme_example() -> str:
    """The first ```python block of the README's "Python API" section."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    section = text[text.index("## Python API"):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_readme_example_runs(tmp_path, monkeypatch):
    (tmp_path / "sample_sequences").symlink_to(SAMPLES)
    monkeypatch.chdir(tmp_path)
    exec(compile(readme_example(), "README.md", "exec"), {})
    assert (tmp_path / "occlusion.h5").is_file() and (tmp_path / "occlusion.csv").is_file()


@pytest.fixture(scope="module")
def cnlf_tracks():
    """The CNLF (random draws: the strictest case for bit-identity) on the occlusion sample, seed 3."""
    return ct.track(str(SAMPLE), queries=str(SAMPLE / "queries.csv"), method="cnlf", seed=3)


def test_api_and_command_give_identical_arrays(tmp_path, cnlf_tracks):
    queries = SAMPLE / "queries.csv"
    args = [str(SAMPLE), "-p", str(queries), "-m", "cnlf", "--seed", "3", "-q"]
    for suffix in (".h5", ".csv"):
        cli_out = tmp_path / f"cli{suffix}"
        done = subprocess.run([sys.executable, "-m", "condtrack_cli", "track", *args, "-o", str(cli_out)],
                              capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
    t = cnlf_tracks
    t.to_hdf5(tmp_path / "api.h5")
    t.to_csv(tmp_path / "api.csv")
    assert (tmp_path / "api.csv").read_bytes() == (tmp_path / "cli.csv").read_bytes()
    with h5py.File(tmp_path / "api.h5") as a, h5py.File(tmp_path / "cli.h5") as b:
        for name in DATASETS:
            assert a[name][()].tobytes() == b[name][()].tobytes(), name
        assert dict(a.attrs) == dict(b.attrs)
    cli_tracks = ct.read_tracks(tmp_path / "cli.h5")
    assert cli_tracks.xy.tobytes() == t.xy.tobytes() and (cli_tracks.method == t.method).all()


def test_queries_as_an_array_track_like_the_csv():
    from_csv = ct.track(str(SAMPLE), queries=str(SAMPLE / "queries.csv"), method="clf")
    rows = np.column_stack([from_csv.queries.frame, from_csv.queries.xy])
    from_rows = ct.track(str(SAMPLE), queries=rows, method="clf")
    assert from_rows.xy.tobytes() == from_csv.xy.tobytes()
    assert from_rows.cov.tobytes() == from_csv.cov.tobytes()
    with pytest.raises(CondtrackError, match=r"queries: row 1: frame 99 is outside the sequence"):
        ct.track(str(SAMPLE), queries=[[0, 10, 10], [99, 10, 10]], method="clf")


@pytest.mark.parametrize("suffix", [".h5", ".csv"])
def test_read_tracks_round_trips(tmp_path, suffix, cnlf_tracks):
    t = cnlf_tracks
    first, second = tmp_path / f"a{suffix}", tmp_path / f"b{suffix}"
    (t.to_csv if suffix == ".csv" else t.to_hdf5)(first)
    back = ct.read_tracks(first)
    assert isinstance(back, ct.Tracks)
    (back.to_csv if suffix == ".csv" else back.to_hdf5)(second)
    assert first.read_bytes() == second.read_bytes()
    assert np.array_equal(back.xy, np.round(t.xy, 6) if suffix == ".csv" else t.xy, equal_nan=True)
    assert (back.visible == t.visible).all() and (back.method == t.method).all()
    if suffix == ".h5":
        assert back.config == t.config and back.info == t.info
        assert back.result.z.tobytes() == read_result(first)[0].z.tobytes()
    else:
        assert back.config is None


def test_config_mapping_is_validated_like_the_yaml(tmp_path):
    with pytest.raises(CondtrackError, match=r"config key 'motion.levelz': unknown key"):
        ct.track(str(SAMPLE), config={"motion": {"levelz": 3}})
    with pytest.raises(CondtrackError, match=r"config key 'filter.method': unknown method 'nope'"):
        ct.track(str(SAMPLE), method="nope")
    with pytest.raises(CondtrackError, match=r"config key 'filter.method': unknown method 'foo'"):
        load_config({"filter": {"method": "foo"}}, method="clf")  # a bad value written stays bad under -m
    assert load_config({"filter": {"method": "cnlf"}}, method="clf").method == "clf"
    with pytest.raises(CondtrackError, match=r"a csv file needs a \.csv name"):
        ct.track(str(SAMPLE), queries=str(SAMPLE / "queries.csv"), config={"filter": {"method": "mdr"}}).to_csv(
            tmp_path / "x.h5")
    (tmp_path / "file.h5").write_bytes(b"")  # a file named as the output's folder
    with pytest.raises(CondtrackError, match=r"the output folder '.*file\.h5' is not a folder"):
        ct.track(str(SAMPLE), queries=str(SAMPLE / "queries.csv"), config={"filter": {"method": "mdr"}}).to_csv(
            tmp_path / "file.h5" / "x.csv")
    (tmp_path / "c.yaml").write_text("filter: {method: mdr}\n")
    from_yaml = ct.track(str(SAMPLE), queries=str(SAMPLE / "queries.csv"), config=tmp_path / "c.yaml")
    from_dict = ct.track(str(SAMPLE), queries=str(SAMPLE / "queries.csv"), config={"filter": {"method": "mdr"}})
    assert from_yaml.config == from_dict.config and from_yaml.xy.tobytes() == from_dict.xy.tobytes()


def test_progress_callback_gets_every_frame_of_both_passes():
    calls = []
    ct.track(str(SAMPLE), queries=str(SAMPLE / "queries.csv"), method="stk", progress=lambda *a: calls.append(a))
    assert calls == [(done, 38) for done in range(1, 39)]  # 30 forward frames, then frames 7..0 backward
    with pytest.raises(CondtrackError, match="progress: expected True, False or a callable"):
        ct.track(str(SAMPLE), progress="yes")


def test_warnings_are_python_warnings_that_tests_can_make_errors(tmp_path):
    """What the command line prints as ``warning:`` lines (here a skipped file) is a CondtrackWarning."""
    folder = tmp_path / "clip"
    folder.mkdir()
    for frame in sorted(SAMPLE.glob("*.png"))[:3]:
        (folder / frame.name).symlink_to(frame)
    (folder / "notes.txt").write_text("hello")
    with pytest.warns(ct.CondtrackWarning, match=r"clip: skipping 1 non-image file\(s\), e.g. 'notes.txt'"):
        ct.track(str(folder), method="stk")
    with pytest.raises(ct.CondtrackWarning):  # this suite makes every warning an error (pyproject.toml)
        ct.track(str(folder), method="stk")
@pytest.mark.parametrize("keywords, kind, option", [
    ({"seed": -1}, ValueError, ["--seed", "-1"]),
    ({"seed": 2**64}, ValueError, ["--seed", str(2**64)]),
    ({"seed": 1.5}, TypeError, ["--seed", "1.5"]),
    ({"queries": np.array([["0", "10", "10"]])}, TypeError, None),
    ({"queries": np.array([[0.0, "a", 1.0]], dtype=object)}, TypeError, None),
])
def test_bad_arguments_raise_condtrack_errors_worded_as_the_command_line(keywords, kind, option):
    """Issue 28.12: ct.track raised numpy's bare ValueError or TypeError; now a ct.CondtrackError (still a ValueError
    or TypeError), before any work, saying what ``condtrack track`` says of the same value."""
    with pytest.raises(ct.CondtrackError) as raised:
        ct.track(str(SAMPLE), method="stk", **keywords)
    assert isinstance(raised.value, kind) and ct.CondtrackError is CondtrackError
    if option is not None:
        done = subprocess.run([sys.executable, "-c", "from condtrack_cli.cli import main; main()", "track", str(SAMPLE),
                               *option], capture_output=True, text=True, timeout=60)
        assert done.returncode == 2
        message = str(raised.value).removeprefix("seed: ")
        assert message.replace("'", "") in done.stderr.replace("'", ""), (message, done.stderr)


def test_a_method_that_is_not_a_name_is_an_invalid_argument_type():
    """ct.track(src, method=3) raised a plain CondtrackError ("unknown method 3") where every other argument of another
    type raises InvalidArgumentType (a TypeError); an unknown name is still refused naming the methods."""
    with pytest.raises(ct.CondtrackError, match="^method: expected a method name") as raised:
        ct.track(str(SAMPLE), method=3)
    assert isinstance(raised.value, TypeError)
    with pytest.raises(ct.CondtrackError, match="unknown method 'kalman'"):
        ct.track(str(SAMPLE), method="kalman")


def test_a_path_argument_of_another_type_or_a_folder_is_a_condtrack_error(tmp_path):
    """ct.read_tracks(5) and t.to_csv(None) raised pathlib's bare TypeError, ct.track(None) said 'None: no such file
    or folder', ct.read_tracks(folder) 'no such file'; now InvalidArgumentType naming the argument, and 'not a regular
    file' for a folder."""
    t = ct.track(str(SAMPLE), queries=np.array([[0, 120.0, 80.0]]), method="stk")
    for call, name in ((lambda: ct.track(None), "source"), (lambda: ct.read_tracks(5), "path"),
                       (lambda: t.to_csv(5), "path"), (lambda: t.to_hdf5(None), "path")):
        with pytest.raises(ct.CondtrackError, match=rf"^{name}: expected a file or folder path, got ") as raised:
            call()
        assert isinstance(raised.value, TypeError)
    with pytest.raises(CondtrackError, match=r": not a regular file \(a folder\?\)$"):
        ct.read_tracks(tmp_path)


def test_numpy_scalars_in_a_config_mapping_are_read_as_the_values_they_hold():
    """config={"filter": {"cnlf": {"particles": np.int64(50)}}} was refused with "Input should be a valid integer (got
    50)", np.bool_(True) for filter.smooth with "expected true or false, got True"; now they are 50 and True."""
    mapping = {"filter": {"smooth": np.bool_(True), "cnlf": {"particles": np.int64(50)}},
               "detect": {"max_points": np.array([7])[0]}}
    config = load_config(mapping, method="cnlf")
    assert config == load_config({"filter": {"smooth": True, "cnlf": {"particles": 50}}, "detect": {"max_points": 7}},
                                 method="cnlf")
    assert config.filters["cnlf"].particles == 50 and config.smooth is True


def test_numpy_booleans_are_taken_for_forward_only_and_progress():
    """forward_only=np.bool_(True) was refused with "expected True or False, got bool"; now it is True."""
    source = str(SAMPLES / "ring")
    expected = ct.track(source, method="stk", forward_only=True, progress=False)
    given = ct.track(source, method="stk", forward_only=np.bool_(True), progress=np.bool_(False))
    assert np.array_equal(given.xy, expected.xy, equal_nan=True)
    assert given.config == expected.config


def test_a_method_read_from_tracks_is_taken_as_its_name():
    """method=t.method[0], a numpy string (np.str_('stk')), ended in yaml's bare RepresenterError "cannot represent an
    object" when the config was resolved; now it is the method 'stk'."""
    source, queries = str(SAMPLES / "ring"), np.array([[0, 40.0, 40.0]])
    first = ct.track(source, queries=queries, method="stk")
    again = ct.track(source, queries=queries, method=first.method[0])
    assert type(first.method[0]) is np.str_ and again.config == first.config
    assert np.array_equal(again.xy, first.xy, equal_nan=True)


def test_a_numpy_integer_seed_writes_the_file_a_plain_seed_writes(tmp_path):
    """seed=np.int32(3) or np.uint8(3) wrote the HDF5 root attribute ``seed`` as int32 or uint8 (docs/schema.md: int64),
    so the file differed byte for byte from ``--seed 3``'s; now the seed is the int it holds, the file the same."""
    source, queries = str(SAMPLES / "ring"), np.array([[0, 40.0, 40.0]])
    ct.track(source, queries=queries, method="mdr", seed=3).to_hdf5(tmp_path / "plain.h5")
    for seed in (np.int32(3), np.uint8(3), np.int64(3)):
        t = ct.track(source, queries=queries, method="mdr", seed=seed)
        assert type(t.attributes["seed"]) is int
        t.to_hdf5(tmp_path / "numpy.h5")
        assert (tmp_path / "numpy.h5").read_bytes() == (tmp_path / "plain.h5").read_bytes(), type(seed)


def test_the_lazy_api_names_are_listed_by_dir_and_star_import():
    """dir(ct) (a notebook's tab completion, help(ct)) and ``from condtrack_cli import *`` left out track, read_tracks
    and Tracks, which are imported on first use; now both list them, and the star import binds them."""
    code = ("import json, condtrack_cli as ct\nnames = dir(ct)\nfrom condtrack_cli import *\n"
            "print(json.dumps([names, track is ct.track, read_tracks is ct.read_tracks, Tracks is ct.Tracks]))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    names, *bound = json.loads(done.stdout)
    assert {"track", "read_tracks", "Tracks", "CondtrackError"} <= set(names) and bound == [True, True, True]


def test_the_repr_is_one_line_of_shapes_methods_input_and_seed(tmp_path, cnlf_tracks):
    """repr(t) (a notebook cell ending with ``t``) was the dataclass's: every array, the whole config and the hashes,
    15 kB on 449 lines for the occlusion sample; now one line."""
    assert repr(cnlf_tracks) == ("Tracks(64 points x 30 frames, cnlf 64, input "
                                 f"{str(SAMPLE)!r} 320x240 px, seed 3)")
    cnlf_tracks.to_csv(tmp_path / "t.csv")
    assert repr(ct.read_tracks(tmp_path / "t.csv")) == "Tracks(64 points x 30 frames, cnlf 64)"  # a CSV: no input


def test_tracks_compare_by_value_with_equals(tmp_path, cnlf_tracks):
    """back == t raised numpy's "The truth value of an array with more than one element is ambiguous" (the dataclass's
    == compared tuples of arrays); now two Tracks are equal when their arrays are bit for bit (NaN equal to NaN), and
    the sequence, config and run attributes equal."""
    cnlf_tracks.to_hdf5(tmp_path / "t.h5")
    back = ct.read_tracks(tmp_path / "t.h5")
    assert back == cnlf_tracks and not back != cnlf_tracks and back == copy.deepcopy(back)
    moved = copy.deepcopy(back)
    moved.xy[3, 7, 0] = np.nextafter(moved.xy[3, 7, 0], np.inf)  # one bit of one position
    assert moved != back and moved.result != back.result
    cnlf_tracks.to_csv(tmp_path / "t.csv")
    assert ct.read_tracks(tmp_path / "t.csv") != cnlf_tracks and back != "t.h5"
    with pytest.raises(TypeError, match="unhashable"):
        hash(back)


def test_read_tracks_gives_back_the_particles_and_the_segmentation(tmp_path):
    """ct.read_tracks dropped /particles/xy and /segmentation (output.store_particles, store_segmentation), so
    read_tracks(a).to_hdf5(b) wrote a b without them; now they are in t.result.extras and b is a, byte for byte."""
    config = {"output": {"store_particles": True, "store_segmentation": True}, "filter": {"cnlf": {"particles": 8}}}
    t = ct.track(str(SAMPLES / "ring"), queries=np.array([[0, 40.0, 40.0], [2, 60.0, 50.0]]), method="auto",
                 config=config)
    t.to_hdf5(tmp_path / "a.h5")
    back = ct.read_tracks(tmp_path / "a.h5")
    assert back.result.extras.keys() == {"particles/xy", "segmentation"} and back == t
    back.to_hdf5(tmp_path / "b.h5")
    assert (tmp_path / "b.h5").read_bytes() == (tmp_path / "a.h5").read_bytes()


@pytest.mark.parametrize("value, said", [(float("inf"), "finite number (got inf)"), (np.nan, "finite number (got nan)"),
                                         ("3", "valid number (got '3')")])
def test_max_std_is_refused_in_words_about_the_value_given(value, said):
    """ct.track(max_std=float('inf')) was refused with "Input should be a valid number (got 'inf')": the float became
    the text inf of an override, which YAML reads as a string; the value is now written as YAML reads it back."""
    with pytest.raises(CondtrackError, match=re.escape(f"config key 'output.max_std': Input should be a {said}")):
        ct.track(str(SAMPLE), method="clf", max_std=value)


def test_read_back_attributes_are_the_python_values_a_run_has(tmp_path):
    """ct.read_tracks gave the attributes as h5py reads them, np.int64 seed, np.bool_ smoothed, np.float64 max_std,
    so json.dumps(back.attributes) raised "Object of type int64 is not JSON serializable" where json.dumps(t.attributes)
    of the run worked; now they are int, bool and float, as the run's."""
    t = ct.track(str(SAMPLES / "ring"), queries=np.array([[0, 40.0, 40.0]]), method="mdr", seed=5, max_std=2.5)
    t.to_hdf5(tmp_path / "t.h5")
    back = ct.read_tracks(tmp_path / "t.h5").attributes
    assert {key: type(value) for key, value in back.items()} == {key: type(value) for key, value in t.attributes.items()}
    assert json.loads(json.dumps(back)) == t.attributes and back["seed"] == 5 and back["max_std"] == 2.5


@pytest.mark.filterwarnings("ignore:.*queries are untrackable:condtrack_cli.errors.CondtrackWarning")  # incidental queries (issue 29)
def test_masked_query_rows_are_refused_not_tracked():
    """A masked array of queries lost its mask: the values under it were tracked as queries. A masked row is now
    refused, naming it; a masked array with nothing masked is read as its values."""
    rows = np.ma.array([[0, 120.0, 100.0], [0, 40.0, 50.0]], mask=[[False] * 3, [False, True, False]])
    with pytest.raises(InvalidArgument, match=r"^queries: row 1 is masked; give the rows to track"):
        ct.track(str(SAMPLE), queries=rows, method="stk")
    assert ct.track(str(SAMPLE), queries=np.ma.array(rows.data), method="stk") == ct.track(str(SAMPLE), queries=rows.data, method="stk")


def test_queries_and_config_may_be_any_path_like():
    """queries=PurePosixPath(...) (or any os.PathLike but Path) was refused with "queries: expected an (N, 3) array of
    numbers frame, x, y; got dtype object", config=PurePosixPath(...) with "config: expected a YAML path or a nested
    mapping, got PurePosixPath", though source takes any path; now both are read as the file they name."""
    queries, config = SAMPLE / "queries.csv", REPO / "configs" / "default.yaml"
    expected = ct.track(str(SAMPLE), queries=str(queries), method="mdr", config=str(config))
    given = ct.track(str(SAMPLE), queries=PurePosixPath(queries), method="mdr", config=PurePosixPath(config))
    assert given == expected


def test_a_csv_read_back_and_written_as_hdf5_can_be_drawn_on_its_frames(tmp_path, cnlf_tracks):
    """read_tracks('t.csv').to_hdf5('t.h5') recorded a frame size of 0 x 0 px (a CSV holds none), so `render t.h5`
    refused the very sequence it came from ('tracked on 0x0 px'); an unknown frame size is now not recorded. Nor are
    an unknown input ("", which `info` printed as a blank) and its fps (0, which `info` read as "a folder of frames")."""
    cnlf_tracks.to_csv(tmp_path / "t.csv")
    ct.read_tracks(tmp_path / "t.csv").to_hdf5(tmp_path / "t.h5")
    with h5py.File(tmp_path / "t.h5") as f:
        assert not {"width", "height", "input", "fps"} & set(f.attrs) and f.attrs["n_frames"] == 30
    shown = subprocess.run([sys.executable, "-m", "condtrack_cli", "info", str(tmp_path / "t.h5")], capture_output=True,
                           text=True, cwd=tmp_path).stdout
    assert "input:             n/a\n" in shown and "fps:               n/a\n" in shown
    done = subprocess.run([sys.executable, "-m", "condtrack_cli", "render", str(tmp_path / "t.h5"), str(SAMPLE),
                           "-o", str(tmp_path / "o.mp4"), "--contact-sheet", str(tmp_path / "sheet.png")], capture_output=True, text=True, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "sheet.png").stat().st_size > 0


def test_writing_tracks_onto_a_folder_is_refused_naming_it(tmp_path):
    """t.to_csv("out.csv") with out.csv a folder wrote the whole file, then ended in the rename's IsADirectoryError
    traceback; now a CondtrackError names the folder before anything is written, and nothing is left beside it."""
    t = ct.track(str(SAMPLE), queries=np.array([[0, 120.0, 80.0]]), method="stk")
    for name, write in (("out.csv", t.to_csv), ("out.h5", t.to_hdf5)):
        (tmp_path / name).mkdir()
        with pytest.raises(CondtrackError, match=rf"^{re.escape(str(tmp_path / name))}: is a folder; an output file "
                                                 "cannot replace it$"):
            write(tmp_path / name)
        assert (tmp_path / name).is_dir() and not any((tmp_path / name).iterdir())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.csv", "out.h5"]
