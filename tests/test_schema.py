"""The writers' output is exactly what docs/schema.md documents, and readers refuse other schemas."""

from __future__ import annotations

import dataclasses
import re
import subprocess
import sys

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from condtrack_cli import COORDINATES, SCHEMA_VERSION
from condtrack_cli.cli import cli
from condtrack_cli.errors import CondtrackError, CondtrackWarning
from condtrack_cli.io.interface import OutputSettings
from condtrack_cli.io.read import matched_to_input, read_tracks
from condtrack_cli.io.compare import compare_tracks
from condtrack_cli.io.write import CSV_COLUMNS, FLOAT_FORMATS, csv_text, write_tracks
from condtrack_cli.registry import BUILTIN_METHOD_CODES
from condtrack_cli.types import Queries, SequenceInfo, Tracks

from conftest import REPO

SCHEMA = (REPO / "docs" / "schema.md").read_text(encoding="utf-8")
P, F = 3, 4
#: The metadata ``condtrack track`` passes to the writer.
TRACK_META = {"config": "filter:\n  method: clf\n", "method": "clf", "seed": 0, "config_hash": "0" * 64, "queries_hash": "", "smoothed": False,
              "max_std": float("inf")}


def doc_table(heading: str) -> list[dict[str, str]]:
    """The first markdown table after ``heading`` in docs/schema.md, as rows of {column: cell} (backticks removed)."""
    section = SCHEMA.split(f"\n{heading}\n", 1)[1]
    lines = [line.strip() for line in section.splitlines()]
    start = next(i for i, line in enumerate(lines) if line.startswith("|"))
    table = []
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        table.append([cell.strip().replace("`", "") for cell in line.strip("|").split("|")])
    header, rows = table[0], table[2:]
    return [dict(zip(header, row)) for row in rows]


def doc_code_block(after: str) -> str:
    """The first fenced code block after the text ``after`` in docs/schema.md."""
    return re.search(r"```text\n(.*?)\n```", SCHEMA.split(after, 1)[1], re.S).group(1)


def doc_shape(cell: str) -> tuple[int, ...]:
    """'(P, F, 2)' -> (P, F, 2) with this module's P and F."""
    sizes = {"P": P, "F": F}
    parts = [part.strip() for part in cell.strip("()").split(",") if part.strip()]
    return tuple(sizes[part] if part in sizes else int(part) for part in parts)


def small_tracks() -> Tracks:
    """P=3 points over F=4 frames: one from frame 1 (no state before), inf and nan covariances, every method."""
    rng = np.random.default_rng(1)
    queries = Queries(np.array([4, 9, 2]), np.array([0, 1, 0]), rng.uniform(0, 50, (P, 2)))
    xy = rng.uniform(0, 50, (P, F, 2))
    xy[1, 0] = np.nan
    cov = np.tile(np.diag([0.5, 2.0]), (P, F, 1, 1))
    cov[0, 2] = np.inf
    cov[2, :] = np.nan
    method = np.array([[2, 2, 3, 3], [-1, 1, 1, 1], [0, 0, 0, 0]], np.int8)
    visible = np.array([[1, 1, 0, 1], [0, 1, 1, 1], [1, 0, 1, 1]], bool)
    dof = np.where(np.isfinite(xy).all(axis=-1), np.array([3.5, 12.25, np.inf])[:, None], np.nan)
    return Tracks(queries, xy, cov, dof, visible, method, xy + 0.1, cov.copy())


def write_small(path, settings: OutputSettings | None = None) -> None:
    info = SequenceInfo("frames/", 64, 48, F, 0.0)
    write_tracks(small_tracks(), path, info, TRACK_META, settings or OutputSettings())


def h5_layout(path) -> dict[str, tuple[tuple[int, ...], np.dtype, dict]]:
    """Every dataset of the file by absolute name: (shape, dtype, attributes)."""
    layout = {}

    def visit(name: str, obj) -> None:
        if isinstance(obj, h5py.Dataset):
            layout["/" + name] = (obj.shape, obj.dtype, dict(obj.attrs))

    with h5py.File(path, "r") as f:
        f.visititems(visit)
    return layout


def doc_dtype_matches(doc: str, dtype: np.dtype) -> bool:
    if doc == "string":
        info = h5py.check_string_dtype(dtype)
        return info is not None and info.encoding == "utf-8" and info.length is None
    return dtype == np.dtype(doc)


def test_schema_version_and_pixel_convention_are_documented():
    assert f"Schema version: `{SCHEMA_VERSION}`" in SCHEMA
    assert doc_code_block("## Pixel convention") == COORDINATES


def test_csv_columns_formats_and_header_match_the_doc(tmp_path):
    columns = doc_table("## CSV")
    assert tuple(row["column"] for row in columns) == CSV_COLUMNS
    for row in columns:
        expected = FLOAT_FORMATS.get(row["column"])
        assert row["format"] == (expected or row["format"]), row["column"]
        assert (row["type"] == "float") == (expected is not None), row["column"]
    header = doc_code_block("The first line is the header:")
    assert header == ",".join(CSV_COLUMNS)
    path = tmp_path / "t.csv"
    write_small(path)
    lines = path.read_bytes().decode("ascii").split("\n")
    assert lines[0] == header and lines[-1] == ""
    rows = [line.split(",") for line in lines[1:-1]]
    assert all(len(row) == len(CSV_COLUMNS) for row in rows)
    assert len(rows) == P * F - 1  # point 9 has no state on frame 0
    assert {row[9] for row in rows} <= set(BUILTIN_METHOD_CODES)
    assert rows[2][4:7] == ["inf", "inf", "inf"] and rows[-1][4:7] == ["nan", "nan", "nan"]
    assert rows[0][7] == "3.5" and rows[4][7] == "12.25" and rows[-1][7] == "inf"


def test_method_codes_match_the_doc(tmp_path):
    table = doc_table("## Methods")
    assert [(int(row["code"]), row["name"]) for row in table] == [(-1, "")] + list(enumerate(BUILTIN_METHOD_CODES))
    path = tmp_path / "t.h5"
    write_small(path)
    with h5py.File(path) as f:
        assert f["tracks/method_code"].attrs["names"] == ",".join(BUILTIN_METHOD_CODES)
        assert [m.decode() for m in f["tracks/method"][()]] == ["clf", "mdr", "stk"]


@pytest.mark.parametrize("store_measurements", [True, False])
@pytest.mark.parametrize("compression", [4, 0])
def test_hdf5_datasets_match_the_doc(tmp_path, store_measurements, compression):
    path = tmp_path / "t.h5"
    write_small(path, OutputSettings(hdf5_compression=compression, store_measurements=store_measurements))
    documented = {
        row["dataset"]: row for row in doc_table("### Datasets")
        if row["written"] == "always" or (row["written"] == "store_measurements" and store_measurements)
    }
    layout = h5_layout(path)
    assert set(layout) == set(documented)
    for name, row in documented.items():
        shape, dtype, attributes = layout[name]
        assert shape == doc_shape(row["shape"]), name
        assert doc_dtype_matches(row["dtype"], dtype), (name, dtype)
        assert set(attributes) == {a.strip() for a in row["attributes"].split(",") if a.strip()}, name
        assert all(isinstance(value, str) for value in attributes.values()), name
    assert layout["/queries"][2]["columns"] == "frame,x,y"


def test_hdf5_root_attributes_match_the_doc(tmp_path):
    path = tmp_path / "t.h5"
    write_small(path)
    documented = {row["attribute"]: row["type"] for row in doc_table("### Root attributes")}
    with h5py.File(path) as f:
        assert set(f.attrs) == set(documented)
        for name, kind in documented.items():
            value = f.attrs[name]
            assert isinstance(value, str) if kind == "string" else np.asarray(value).dtype == np.dtype(kind), name
        assert f.attrs["schema_version"] == SCHEMA_VERSION and f.attrs["coordinates"] == COORDINATES


def test_track_command_writes_the_documented_root_attributes(shifted_folder, tmp_path):
    folder, _ = shifted_folder
    queries = tmp_path / "q.csv"
    queries.write_text("frame,x,y\n0,120,100\n0,200,150\n")
    path = tmp_path / "t.h5"
    result = CliRunner().invoke(cli, ["track", str(folder), "-p", str(queries), "-m", "stk", "-o", str(path), "-q"])
    assert result.exit_code == 0, result.output
    documented = {row["attribute"] for row in doc_table("### Root attributes")}
    with h5py.File(path) as f:
        assert set(f.attrs) == documented



def test_points_are_written_by_increasing_point_id_whatever_the_queries_file_s_order(shifted_folder, tmp_path):
    """The doc said the points come "in query order"; the queries are sorted by point_id, and so are both files."""
    folder, _ = shifted_folder
    queries = tmp_path / "q.csv"
    queries.write_text("point_id,frame,x,y\n50,0,120,100\n7,0,200,150\n300,0,150,60\n")
    for name in ("t.h5", "t.csv"):
        result = CliRunner().invoke(cli, ["track", str(folder), "-p", str(queries), "-m", "stk", "-o",
                                          str(tmp_path / name), "-q"])
        assert result.exit_code == 0, result.output
    with h5py.File(tmp_path / "t.h5") as f:
        np.testing.assert_array_equal(f["tracks/point_id"][()], [7, 50, 300])
        np.testing.assert_array_equal(f["queries"][:, 1], [200, 120, 150])
    rows = (tmp_path / "t.csv").read_text().splitlines()[1:]
    assert list(dict.fromkeys(int(row.split(",")[0]) for row in rows)) == [7, 50, 300]
    assert "point (by increasing `point_id`" in (REPO / "docs" / "schema.md").read_text()

def test_a_csv_with_another_header_is_refused_naming_the_expected_one(tmp_path):
    path = tmp_path / "old.csv"
    path.write_text("point_id,frame,x,y,visible\n0,0,1.0,2.0,1\n")
    with pytest.raises(CondtrackError, match=re.escape(f"expected the header {','.join(CSV_COLUMNS)}")):
        read_tracks(path)
    path.write_text("# schema 1.0\n" + ",".join(CSV_COLUMNS) + "\n")
    with pytest.raises(CondtrackError, match="not a condtrack CSV"):
        read_tracks(path)


def test_an_hdf5_of_another_schema_version_is_refused_naming_both(tmp_path):
    path = tmp_path / "t.h5"
    write_small(path)
    with h5py.File(path, "r+") as f:
        f.attrs["schema_version"] = "0.9"
    message = "schema_version '0.9' is not supported (this condtrack reads '1.0' and '2.0')"
    with pytest.raises(CondtrackError, match=re.escape(message)):
        read_tracks(path)


def test_a_csv_saved_with_a_byte_order_mark_or_windows_line_ends_reads_the_same(tmp_path):
    """A golden CSV that an editor or a spreadsheet saved with a UTF-8 byte-order mark was refused with Python's
    "'ascii' codec can't decode byte 0xef" (the queries and truth readers take it); it reads as the file it was, as
    with CRLF line ends, and a byte that is not ASCII is named with its offset."""
    path = tmp_path / "t.csv"
    write_small(path)
    expected, _ = read_tracks(path)
    text = path.read_bytes()
    for name, content in (("bom.csv", b"\xef\xbb\xbf" + text), ("crlf.csv", text.replace(b"\n", b"\r\n"))):
        (tmp_path / name).write_bytes(content)
        assert read_tracks(tmp_path / name)[0] == expected, name
    (tmp_path / "latin.csv").write_bytes(text.replace(b"point_id", b"point_\xe9d", 1))
    with pytest.raises(CondtrackError, match=r"latin.csv: not a condtrack CSV \(byte 0xe9 at offset 6 is not ASCII\)$"):
        read_tracks(tmp_path / "latin.csv")


def test_an_hdf5_file_of_another_program_is_said_to_be_no_track_file(tmp_path):
    """An HDF5 file without condtrack's root attributes was refused as "schema_version None is not supported", as if
    it were a track file of an unknown schema."""
    path = tmp_path / "other.h5"
    with h5py.File(path, "w") as f:
        f["x"] = np.arange(3)
    message = f"{path}: not a condtrack track file (an HDF5 file without the root attribute 'schema_version')"
    with pytest.raises(CondtrackError, match=f"^{re.escape(message)}$"):
        read_tracks(path)


def test_files_of_schema_1_0_are_read_as_gaussian(tmp_path):
    """Issue 27: a schema 1.0 file (no dof) is read with dof inf where a row exists, NaN elsewhere, and compares
    equal to a 2.0 file of the same tracks written Gaussian."""
    tracks = small_tracks()
    gaussian = dataclasses.replace(tracks, dof=np.where(np.isfinite(tracks.xy).all(axis=-1), np.inf, np.nan))
    old_h5, new_h5, old_csv = tmp_path / "old.h5", tmp_path / "new.h5", tmp_path / "old.csv"
    write_small(old_h5)
    with h5py.File(old_h5, "r+") as f:
        f.attrs["schema_version"] = "1.0"
        del f["tracks/dof"]
    write_tracks(gaussian, new_h5, SequenceInfo("frames/", 64, 48, F, 0.0), TRACK_META, OutputSettings())
    lines = csv_text(tracks).splitlines()
    column = CSV_COLUMNS.index("dof")
    old_csv.write_text("\n".join(",".join(c for i, c in enumerate(line.split(",")) if i != column) for line in lines) + "\n")
    assert old_csv.read_text().splitlines()[0] == "point_id,frame,x,y,cov_xx,cov_xy,cov_yy,visible,method"
    for old in (old_h5, old_csv):
        read, _ = read_tracks(old)  # a CSV lists its points by id
        order = [list(tracks.queries.point_id).index(i) for i in read.queries.point_id]
        assert np.array_equal(read.dof, gaussian.dof[order], equal_nan=True), old
    assert compare_tracks(read_tracks(old_h5)[0], read_tracks(new_h5)[0]).agree


@pytest.mark.parametrize("dataset", ["dof", "trackability"])
def test_a_schema_2_0_hdf5_without_a_dataset_2_0_added_is_refused(tmp_path, dataset):
    """Schema 2.0 added /tracks/dof and /tracks/trackability; a 2.0 file without one was read as a 1.0 file (Gaussian
    rows, unknown scores) without a word."""
    path = tmp_path / "t.h5"
    write_small(path)
    with h5py.File(path, "r+") as f:
        del f[f"tracks/{dataset}"]
    with pytest.raises(CondtrackError, match=rf"t.h5: damaged or incomplete condtrack HDF5 file .*{dataset}"):
        read_tracks(path)


def test_an_hdf5_whose_shapes_depart_from_the_schema_is_refused(tmp_path):
    path = tmp_path / "t.h5"
    write_small(path)
    with h5py.File(path, "r+") as f:
        del f["tracks/visible"]
        f["tracks/visible"] = np.ones((P, F + 1), bool)
    with pytest.raises(CondtrackError, match=r"damaged or incomplete .*visible has shape \(3, 5\), expected \(3, 4\)"):
        read_tracks(path)


def test_an_hdf5_whose_positions_are_integers_is_refused(tmp_path):
    """A file of whole-pixel positions (another tracker's, written in this layout) stored as integers was read, and
    eval ended in numpy's 'cannot convert float NaN to integer' traceback; /tracks/xy is float64 (NaN: no state), so
    such a file is now refused naming the dataset, as one of another shape is."""
    path = tmp_path / "t.h5"
    write_small(path)
    with h5py.File(path, "r+") as f:
        xy = np.nan_to_num(f["tracks/xy"][()])
        del f["tracks/xy"]
        f["tracks/xy"] = np.rint(xy).astype(np.int64)
    with pytest.raises(CondtrackError, match=r"t.h5: damaged or incomplete .*\(xy holds int64 values, not floats\)$"):
        read_tracks(path)


def _negated_variance(cov):
    cov[0, 1, 0, 0] = -0.5
    return cov


def _asymmetric(cov):
    cov[0, 1, 0, 1] = 0.3
    return cov


def _nan_frame(queries):
    queries[1, 0] = np.nan
    return queries


@pytest.mark.parametrize("dataset, change, said", [
    ("tracks/point_id", lambda ids: ids.astype(float), "point_id holds float64 values of shape (3,), expected (P,) "
                                                       "whole numbers"),
    ("tracks/point_id", lambda ids: np.array([4, 9, 4]), "point_id 4 is repeated"),
    ("queries", _nan_frame, "queries row 1 (point_id 9) is [nan, "),
    ("queries", lambda q: q + [[100, 0, 0]], "queries row 0 (point_id 4) has frame 100, past the 4 frames of xy"),
    ("tracks/xy", lambda xy: np.where(xy == xy[0, 1, 0], np.inf, xy), "xy at point_id 4, frame 1 is [inf, "),
    ("tracks/cov", _negated_variance, "cov at point_id 4, frame 1 is [[-0.5, 0.0], [0.0, 2.0]]: a variance is never "
                                      "negative"),
    ("tracks/cov", _asymmetric, "cov at point_id 4, frame 1 is [[0.5, 0.3], [0.0, 2.0]]: its two off-diagonal "
                                "entries differ"),
    ("tracks/dof", lambda dof: np.where(dof == 3.5, 1.0, dof), "dof at point_id 4, frame 0 is 1.0: expected a number "
                                                               "above 2 or inf"),
])
def test_an_hdf5_whose_values_a_csv_could_not_hold_is_refused(tmp_path, dataset, change, said):
    """Values a CSV row is refused for (a negative variance, a dof of 1, a position partly infinite), and ids or
    queries no condtrack file holds, were read from an HDF5 file: render ended in numpy's 'invalid value encountered
    in sqrt' (dof 1), a query frame NaN in 'invalid value encountered in cast', eval in int()'s ValueError (string
    ids); each is now refused naming the dataset, the point_id and the frame."""
    path = tmp_path / "t.h5"
    write_small(path)
    read_tracks(path)  # the file as written is read
    with h5py.File(path, "r+") as f:
        value = change(f[dataset][()])
        del f[dataset]
        f[dataset] = value
    with pytest.raises(CondtrackError, match=r"t.h5: damaged or incomplete condtrack HDF5 file \(" + re.escape(said)):
        read_tracks(path)


def test_a_covariance_symmetric_to_rounding_is_read(tmp_path):
    """Files written before 9c8e680 held covariances whose off-diagonal entries differed in their last bits (the Kalman
    update's rounding): the check of 9b96ecd refused every such file, golden files of yesterday's version included.
    A difference within the rounding (1e-9 of the diagonal) is read as it is; a larger one is refused (above)."""
    path = tmp_path / "t.h5"
    write_small(path)
    with h5py.File(path, "r+") as f:
        cov = f["tracks/cov"][()]
        cov[0, 1, 0, 1] = np.nextafter(cov[0, 1, 1, 0] + 0.1, 1.0)  # 0.1 + 1 ulp against 0.1
        cov[0, 1, 1, 0] += 0.1
        del f["tracks/cov"]
        f["tracks/cov"] = cov
    back = read_tracks(path)[0]
    assert back.cov[0, 1, 0, 1] != back.cov[0, 1, 1, 0] and np.isclose(back.cov[0, 1, 0, 1], back.cov[0, 1, 1, 0])


@pytest.mark.parametrize("key, value, said", [
    ("n_frames", "abc", "root attribute 'n_frames' is 'abc', not a whole number of frames"),
    ("n_frames", -1, "root attribute 'n_frames' is -1, not a whole number of frames"),
    ("n_frames", F + 1, f"root attribute 'n_frames' is {F + 1}, but /tracks/xy has {F} frames"),
    ("width", -5, "root attribute 'width' is -5, not a whole number of pixels above 0"),
    ("height", None, "root attribute 'height' is missing beside the other"),
    ("fps", float("nan"), "root attribute 'fps' is nan, not a finite number >= 0"),
    ("config", 5, "root attribute 'config' is 5, not a string"),
])
def test_an_hdf5_whose_root_attributes_depart_from_the_schema_is_refused(tmp_path, key, value, said):
    """A file whose n_frames was a string ended render and ct.read_tracks in int()'s ValueError, a config that was no
    string ended info in an AttributeError; each is now refused naming the attribute, as every other damaged file is
    (None: the attribute deleted). A file whose n_frames disagreed with /tracks/xy was read: compare reported it
    agreeing with the file it came from, render blamed the input for having another frame count."""
    import condtrack_cli as ct

    path = tmp_path / "t.h5"
    write_small(path)
    with h5py.File(path, "r+") as f:
        if value is None:
            del f.attrs[key]
        else:
            f.attrs[key] = value
    message = rf"^{re.escape(str(path))}: damaged or incomplete condtrack HDF5 file \({re.escape(said)}\)$"
    with pytest.raises(CondtrackError, match=message):  # what info, compare, eval and render read it with
        read_tracks(path)
    with pytest.raises(CondtrackError, match=message):
        ct.read_tracks(path)


@pytest.mark.parametrize("name", ["t.h5", "t.csv"])
def test_tracks_of_another_frame_count_than_their_input_are_not_written(tmp_path, name):
    """write_tracks wrote an HDF5 file whose n_frames (the input's) disagreed with its /tracks/xy, which the readers
    refuse as damaged; tracks and input that disagree are now an error naming both counts, and nothing is written."""
    path = tmp_path / name
    with pytest.raises(CondtrackError, match=rf"^{re.escape(str(path))}: not written: the tracks have {F} frames, but "
                                             rf"frames/ has {F + 1} frames$"):
        write_tracks(small_tracks(), path, SequenceInfo("frames/", 64, 48, F + 1, 0.0), TRACK_META, OutputSettings())
    assert list(tmp_path.iterdir()) == []


def test_an_hdf5_without_n_frames_has_the_frames_of_its_tracks(tmp_path):
    """ct.read_tracks and render of a file written without the n_frames attribute (by hand, as eval reads one) ended in
    a KeyError traceback; its frame count is now that of /tracks/xy."""
    import condtrack_cli as ct

    path = tmp_path / "t.h5"
    write_small(path)
    with h5py.File(path, "r+") as f:
        del f.attrs["n_frames"]
    assert ct.read_tracks(path).info.n_frames == F
    _, meta = read_tracks(path)
    assert matched_to_input(small_tracks(), meta, path, SequenceInfo("frames/", 64, 48, F, 0.0)) == small_tracks()
    with pytest.raises(CondtrackError, match=r"t.h5 was tracked on 64x48 px, 4 frames, but frames/ has 64x48 px, 5 "):
        matched_to_input(small_tracks(), meta, path, SequenceInfo("frames/", 64, 48, F + 1, 0.0))


def test_a_config_attribute_that_is_no_config_is_refused_naming_the_file(tmp_path):
    """ct.read_tracks of a file whose config attribute was not YAML ended in PyYAML's ParserError traceback; it now
    names the file. One whose config this version does not take (another version's: a key since renamed or removed)
    said "config key ..." without naming the file and read nothing, where the commands read its tracks; it is now read
    without its config, with a warning naming the file and the key."""
    import condtrack_cli as ct

    path = tmp_path / "t.h5"
    damaged = "damaged or incomplete condtrack HDF5 file (root attribute 'config' is"
    for config, said in (("a: [1", f"{damaged} not valid YAML)"), ("", f"{damaged} not a mapping of sections)")):
        write_tracks(small_tracks(), path, SequenceInfo("frames/", 64, 48, F, 0.0), {**TRACK_META, "config": config},
                     OutputSettings())
        with pytest.raises(CondtrackError, match=rf"^{re.escape(str(path))}: {re.escape(said)}"):
            ct.read_tracks(path)
    write_tracks(small_tracks(), path, SequenceInfo("frames/", 64, 48, F, 0.0),
                 {**TRACK_META, "config": "measure:\n  templat: 11\n"}, OutputSettings())
    with pytest.warns(CondtrackWarning, match=rf"^{re.escape(str(path))}: root attribute 'config' is not a config of "
                                              r"this version \(config key 'measure.templat': unknown key"):
        back = ct.read_tracks(path)
    assert back.config is None and np.array_equal(back.xy, small_tracks().xy, equal_nan=True)


def test_optional_datasets_of_auto_match_the_doc(tmp_path):
    """``auto`` with particles and segmentation stored writes exactly the documented optional datasets."""
    from conftest import SAMPLES

    folder, out = SAMPLES / "ring", tmp_path / "auto.h5"
    result = subprocess.run(
        [sys.executable, "-m", "condtrack_cli", "track", str(folder), "-p", str(folder / "queries.csv"), "-m", "auto",
         "--set", "output.store_particles=true", "--set", "output.store_segmentation=true", "-o", str(out), "-q"],
        capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr
    layout = h5_layout(out)
    with h5py.File(out) as f:
        p, n_frames = f["tracks/xy"].shape[:2]
        height, width = int(f.attrs["height"]), int(f.attrs["width"])
    sizes = {"P": p, "F": n_frames, "F-1": n_frames - 1, "N": 100, "H": height, "W": width}
    for row in doc_table("### Datasets"):
        if row["written"] in ("store_particles", "store_segmentation"):
            shape, dtype, attributes = layout[row["dataset"]]
            parts = [part.strip() for part in row["shape"].strip("()").split(",")]
            assert shape == tuple(sizes[part] if part in sizes else int(part) for part in parts), row["dataset"]
            assert doc_dtype_matches(row["dtype"], dtype), row["dataset"]
            assert set(attributes) == {a.strip() for a in row["attributes"].split(",") if a.strip()}


@pytest.mark.parametrize("method, smooth", [("clf", True), ("cnlf", False), ("auto", False)])
def test_every_reported_covariance_is_exactly_symmetric(method, smooth):
    """cov_xy and cov_yx of /tracks/cov differed in the last bit (up to 1.8e-15 px^2 on the occlusion sample: sums of
    products in another order), so a reader taking one or the other got two covariances; they are now equal."""
    import condtrack_cli as ct
    from conftest import SAMPLES

    queries = np.array([[0, 40.0, 40.0], [0, 120.0, 60.0], [3, 60.0, 50.0], [5, 90.0, 90.0]])  # a backward pass too
    t = ct.track(str(SAMPLES / "ring"), queries=queries, method=method, config={"filter": {"smooth": smooth}})
    finite = np.isfinite(t.cov[..., 0, 1])
    assert finite.mean() > 0.9
    np.testing.assert_array_equal(t.cov[..., 0, 1], t.cov[..., 1, 0])


@pytest.mark.parametrize("method", ["clf", "cnlf", "auto", "stk"])
def test_no_row_outside_the_frame_is_reported_visible(method):
    """The occlusion sample's point 42 left the 320 px frame at x = 320.8 on frame 29 and was written visible there
    (clf), so `condtrack render` warned that its own input might be another; such rows are now not visible."""
    import condtrack_cli as ct
    from conftest import SAMPLES

    sample = SAMPLES / "occlusion"
    t = ct.track(str(sample), queries=str(sample / "queries.csv"), method=method)
    x, y = t.xy[..., 0], t.xy[..., 1]
    with np.errstate(invalid="ignore"):
        outside = (x < -0.5) | (x > t.info.width - 0.5) | (y < -0.5) | (y > t.info.height - 0.5)
    assert not (t.visible & outside).any()
    assert t.visible.mean() > 0.7


def test_measurements_are_nan_and_inf_where_the_doc_says(tmp_path):
    """/measurements/z is NaN on the query's frame, where no measurement is made (R NaN), and where no candidate lay in
    the gate, R then +inf on its diagonal and 0 off it (19 rows of clf on the occlusion sample); the doc said only the
    first."""
    import condtrack_cli as ct
    from conftest import SAMPLES

    sample = SAMPLES / "occlusion"
    ct.track(str(sample), queries=str(sample / "queries.csv"), method="clf").to_hdf5(tmp_path / "clf.h5")
    with h5py.File(tmp_path / "clf.h5") as f:
        z, R, query_frame = f["measurements/z"][()], f["measurements/R"][()], f["queries"][:, 0].astype(int)
    no_z, no_r = np.isnan(z).all(axis=-1), np.isnan(R).all(axis=(-2, -1))
    query = np.zeros_like(no_r)
    query[np.arange(len(query)), query_frame] = True
    np.testing.assert_array_equal(no_r, query)
    gate_empty = no_z & ~no_r
    assert gate_empty.any() and (np.isnan(z).any(axis=-1) == no_z).all()
    assert np.isinf(R[gate_empty][:, [0, 1], [0, 1]]).all() and (R[gate_empty][:, [0, 1], [1, 0]] == 0).all()
