"""Queries CSV parsing: BOM, integer ids and frames read exactly (issue 16 items 5, 6)."""

from __future__ import annotations

import numpy as np
import pytest

from condtrack_cli.errors import CondtrackError, InvalidArgument
from condtrack_cli.queries import queries_from_rows, read_queries
from condtrack_cli.types import SequenceInfo

INFO = SequenceInfo("clip", 64, 48, 10, 0.0)


def _read(tmp_path, text: str, encoding: str = "utf-8"):
    path = tmp_path / "q.csv"
    path.write_bytes(text.encode(encoding))
    return read_queries(path, INFO)


@pytest.mark.parametrize("text", ["point_id,frame,x,y\n7,1,2,3\n5,0,4,5\n", "frame,x,y,point_id\n1,2,3,7\n0,4,5,5\n"])
def test_a_byte_order_mark_is_ignored(tmp_path, text):
    queries = _read(tmp_path, text, "utf-8-sig")
    assert queries.point_id.tolist() == [5, 7] and queries.frame.tolist() == [0, 1]


@pytest.mark.parametrize("big", [2**53 + 1, 2**63 - 1, -(2**63)])
def test_point_ids_are_read_exactly(tmp_path, big):
    queries = _read(tmp_path, f"point_id,frame,x,y\n{big},0,2,3\n1,0,4,5\n")
    assert big in queries.point_id.tolist()


@pytest.mark.parametrize(
    "cell, message",
    [
        ("1e20", "outside the 64-bit integer range"),
        ("9223372036854775808", "outside the 64-bit integer range"),
        ("2.5", "not a whole number"),
        ("nan", "not a whole number"),
        ("seven", "not a number"),
    ],
)
def test_bad_point_ids_are_refused_naming_file_and_row(tmp_path, cell, message):
    with pytest.raises(CondtrackError) as error:
        _read(tmp_path, f"point_id,frame,x,y\n1,0,2,3\n{cell},0,4,5\n")
    text = str(error.value)
    assert "q.csv" in text and "row 3, column 'point_id'" in text and message in text and "\n" not in text


def test_whole_numbers_written_as_decimals_are_accepted(tmp_path):
    queries = _read(tmp_path, "point_id,frame,x,y\n3.0,2.0,2,3\n1e3,0,4,5\n")
    assert queries.point_id.tolist() == [3, 1000] and queries.frame.tolist() == [2, 0]
    assert queries.point_id.dtype == np.int64


def test_a_value_beyond_the_header_s_columns_is_refused_an_empty_trailing_cell_is_not(tmp_path):
    """``frame,x,y`` then ``0,10,3,7``: the 7 (meant as a point_id?) had no column and was dropped, the point
    numbered 0; a spreadsheet's trailing empty cell (``0,10,3,``) is no value."""
    with pytest.raises(CondtrackError, match=r"q.csv: row 3 has 4 fields, the header 3$"):
        _read(tmp_path, "frame,x,y\n0,4,5\n0,10,3,7\n")
    queries = _read(tmp_path, "frame,x,y\n0,4,5,\n1,10,3, \n")
    assert queries.point_id.tolist() == [0, 1] and queries.xy.tolist() == [[4.0, 5.0], [10.0, 3.0]]


@pytest.mark.parametrize("frame, shown", [(1e30, "1000000000000000019884624838656"), (2.0**63, "9223372036854775808"),
                                          (10.0, "10"), (-1.0, "-1")])
def test_an_array_s_frame_beyond_int64_is_refused_with_its_own_value(frame, shown):
    """A frame of 1e30 in an (N, 3) array was cast to int64 first (numpy's 'invalid value encountered in cast', an
    error under -W error) and reported as frame -9223372036854775808; now the frame given, before any cast."""
    with pytest.raises(CondtrackError, match=rf"^queries: row 1: frame {shown} is outside the sequence \(0\.\.9\)$"):
        queries_from_rows(np.array([[0, 1.0, 2.0], [frame, 1.0, 2.0]]), INFO)
    assert queries_from_rows(np.array([[9, 1.0, 2.0]], dtype=np.float32), INFO).frame.dtype == np.int64


def test_query_rows_of_different_lengths_are_an_invalid_argument():
    """A list of rows of 3 and 2 values reached the caller as numpy's bare ValueError ("inhomogeneous shape")."""
    with pytest.raises(InvalidArgument, match=r"^queries: expected a non-empty \(N, 3\) array of frame, x, y; got rows "
                                              r"of different lengths$"):
        queries_from_rows([[0, 1.0, 2.0], [0, 1.0]], INFO)


@pytest.mark.parametrize("dtype, frame", [(np.int64, 2**53 + 1), (np.int64, 2**63 - 1), (np.uint64, 2**64 - 1)])
def test_an_integer_array_s_frame_outside_the_sequence_is_named_as_given(dtype, frame):
    """An integer array's frame was named after its cast to float64: 2^63 - 1 as 9223372036854775808, 2^53 + 1 as
    9007199254740992, a frame the array does not hold; now its own value."""
    rows = np.array([[0, 1, 2], [frame, 1, 2]], dtype=dtype)
    with pytest.raises(CondtrackError, match=rf"^queries: row 1: frame {frame} is outside the sequence \(0\.\.9\)$"):
        queries_from_rows(rows, INFO)
    assert queries_from_rows(np.array([[9, 1, 2]], dtype=dtype), INFO).frame.tolist() == [9]


@pytest.mark.parametrize("cell", ["nan", "inf", "-inf"])
def test_a_query_that_is_not_finite_is_said_so(tmp_path, cell):
    """A NaN or infinite coordinate was refused as 'outside the 64x48 frame', which sends the user looking at the
    frame size; it is named for what it is."""
    with pytest.raises(CondtrackError, match=rf"/q\.csv: row 3: point \(4, {cell}\) is not finite$"):
        _read(tmp_path, f"frame,x,y\n0,4,5\n0,4,{cell}\n")


@pytest.mark.parametrize("text, message", [
    ("frame,x,y\n\n\n0,4,abc\n", r"row 4, column 'y': 'abc' is not a number"),
    ("frame,x,y\n0,4,5\n\n0,4,5,7\n", r"row 4 has 4 fields, the header 3"),
    ("frame,x,y\n0,4,5\n\n\n10,4,5\n", r"row 5: frame 10 is outside the sequence \(0\.\.9\)"),
    ("frame,x,y\n\n0,4,5\n\n0,400,5\n", r"row 5: point \(400, 5\) is outside the 64x48 frame"),
])
def test_a_bad_row_after_blank_lines_is_named_by_its_line(tmp_path, text, message):
    """Blank lines (skipped) shifted the row an error named: a bad value on line 4 after two blank lines was
    reported as 'row 2'; rows are now named by their line in the file, the header being row 1."""
    with pytest.raises(CondtrackError, match=rf"/q\.csv: {message}$"):
        _read(tmp_path, text)
