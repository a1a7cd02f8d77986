"""CSV and HDF5 writers (docs/schema.md).

CSV: long format, one row per point per frame on which the point has a state,
ordered by point then frame, columns
``point_id,frame,x,y,cov_xx,cov_xy,cov_yy,dof,visible,method``, ``\\n`` line ends.
Floats use fixed formats (``FLOAT_FORMATS``): positions with 6 decimals
(round-trip to 1e-6 px), covariances in ``%.6e``, degrees of freedom in
``%.6g``; an infinite variance or ``dof`` (Gaussian) is written ``inf`` and an
undefined one ``nan``.

HDF5: datasets written without timestamps, with fixed chunking and gzip
compression, so that one input, config and seed give identical datasets.
h5py is imported by the HDF5 writer only: a run writing CSV does not load it
(start-up time, issue 13).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from condtrack_cli import COORDINATES, SCHEMA_VERSION, __version__
from condtrack_cli.errors import CondtrackError, counted, write_error
from condtrack_cli.io.atomic import atomic_path
from condtrack_cli.io.formats import track_format
from condtrack_cli.io.interface import OutputSettings
from condtrack_cli.registry import get, method_codes
from condtrack_cli.types import SequenceInfo, Tracks

if TYPE_CHECKING:
    import h5py

CSV_COLUMNS = ("point_id", "frame", "x", "y", "cov_xx", "cov_xy", "cov_yy", "dof", "visible", "method")
#: The columns of schema 1.0 files (no ``dof``: read as Gaussian).
CSV_COLUMNS_1 = tuple(name for name in CSV_COLUMNS if name != "dof")
FLOAT_FORMATS = {"x": "%.6f", "y": "%.6f", "cov_xx": "%.6e", "cov_xy": "%.6e", "cov_yy": "%.6e", "dof": "%.6g"}


def csv_text(tracks: Tracks) -> str:
    """The long CSV (header included) of ``tracks``: one %-format per row (``FLOAT_FORMATS``) over Python scalars."""
    points, frames = np.nonzero(tracks.has_state)  # row-major: by point then frame
    xy = tracks.xy[points, frames]
    cov = tracks.cov[points, frames]
    codes = method_codes()
    columns = [tracks.queries.point_id[points], frames, xy[:, 0], xy[:, 1], cov[:, 0, 0], cov[:, 0, 1], cov[:, 1, 1],
               tracks.dof[points, frames], tracks.visible[points, frames].astype(int)]
    row = ",".join(["%d", "%d"] + [FLOAT_FORMATS[name] for name in CSV_COLUMNS[2:8]] + ["%d", "%s"])
    methods = [codes[code] for code in tracks.method[points, frames].tolist()]
    lines = map(row.__mod__, zip(*(column.tolist() for column in columns), methods))
    return "\n".join([",".join(CSV_COLUMNS), *lines]) + "\n"


def write_csv(tracks: Tracks, path: Path, info: SequenceInfo, meta: dict[str, Any], settings: OutputSettings) -> None:
    """Write the long CSV; the optional datasets of ``tracks.extras`` are not written (a CSV has no room for them:
    ``condtrack track`` warns as it reads the config, ``Tracks.to_csv`` as it writes)."""
    path.write_bytes(csv_text(tracks).encode("ascii"))


def _dataset(group: h5py.Group, name: str, data: np.ndarray, settings: OutputSettings, **attrs: Any) -> None:
    options: dict[str, Any] = {"track_times": False}
    if data.ndim and data.size and settings.hdf5_compression:
        chunks = (min(data.shape[0], 64),) + data.shape[1:]
        options.update(chunks=chunks, compression="gzip", compression_opts=settings.hdf5_compression, shuffle=True)
    dataset = group.create_dataset(name, data=data, **options)
    for key, value in attrs.items():
        dataset.attrs[key] = value


def write_hdf5(tracks: Tracks, path: Path, info: SequenceInfo, meta: dict[str, Any], settings: OutputSettings) -> None:
    """Write the self-describing HDF5 file (docs/schema.md)."""
    import h5py  # here only: CSV runs do not pay its import

    q = tracks.queries
    # No chunk cache: each chunk is written when its dataset is created, so the layout follows the order
    # below. With the cache, chunks were flushed at close in an order that varied between processes
    # (same datasets, different bytes: a Dask run did not match the local one).
    with h5py.File(path, "w", track_order=False, rdcc_nbytes=0) as f:
        attrs = {
            "schema_version": SCHEMA_VERSION, "condtrack_version": __version__, "input": info.input,
            "n_frames": info.n_frames, "fps": info.fps, "coordinates": COORDINATES,
        }
        if not info.input:  # unknown ("") for tracks read back from a CSV: not recorded, nor its fps (0: a folder)
            del attrs["input"], attrs["fps"]
        if info.width and info.height:  # unknown (0) for tracks read back from a CSV: not recorded as 0 x 0 px
            attrs.update(width=info.width, height=info.height)
        attrs.update(meta)
        for key, value in attrs.items():
            f.attrs[key] = value
        group = f.create_group("tracks")
        _dataset(group, "point_id", q.point_id.astype(np.int64), settings)
        _dataset(group, "xy", tracks.xy, settings, units="px", missing="NaN where the point has no state")
        _dataset(group, "cov", tracks.cov, settings, units="px^2", meaning="posterior covariance; NaN undefined, inf unbounded")
        _dataset(group, "dof", tracks.dof, settings, meaning=DOF_MEANING)
        _dataset(group, "visible", tracks.visible, settings)
        _dataset(group, "method", np.array(tracks.point_methods(), dtype=h5py.string_dtype()), settings)
        group["method"].attrs["meaning"] = "the method that produced most of the point's frames"
        _dataset(group, "method_code", tracks.method, settings, names=",".join(method_codes()),
                 meaning="per frame: index into names; -1 where no state")
        _dataset(f, "queries", np.column_stack([q.frame, q.xy]).astype(np.float64), settings, columns="frame,x,y")
        _dataset(group, "trackability", np.asarray(tracks.trackability, np.float64), settings, units="(grey/px)^2",
                 meaning=TRACKABILITY_MEANING)
        for name, data in tracks.extras.items():
            _dataset(f, name, data, settings, **EXTRA_ATTRIBUTES[name])
        if settings.store_measurements:
            m = f.create_group("measurements")
            _dataset(m, "z", tracks.z, settings, units="px", missing="NaN where no measurement was made")
            _dataset(m, "R", tracks.R, settings, units="px^2", meaning="inf diagonal: no information (uniform surface)")


#: The ``dof`` dataset's ``meaning`` attribute (docs/schema.md).
DOF_MEANING = ("degrees of freedom nu > 2 of the row's bivariate Student-t predictive distribution, whose covariance "
               "is cov (scale matrix cov (nu - 2) / nu); inf: Gaussian; NaN where no state")

#: The ``meaning`` attribute of ``/tracks/trackability``.
TRACKABILITY_MEANING = (
    "Shi-Tomasi score of the query at its query frame: the smaller eigenvalue of the structure tensor over "
    "detect.block; trackable above detect.min_eigenvalue; NaN where unknown"
)

#: Attributes of the optional datasets (``Tracks.extras``).
EXTRA_ATTRIBUTES = {
    "particles/xy": {"units": "px", "missing": "NaN where the point is not on the CNLF"},
    "segmentation": {"meaning": "255 x robust weight of the global fit from frame k to k+1, on frame k's grid"},
}

def write_tracks(tracks: Tracks, path: str | Path, info: SequenceInfo, meta: dict[str, Any], settings: OutputSettings,
                 *, named: str | Path | None = None) -> None:
    """Write ``tracks`` to ``path`` (.csv, .h5 or .hdf5), atomically: the file is whole or absent (a full disk included).

    CondtrackError, nothing written, when the F frames of ``tracks`` are not the ``info.n_frames`` of the input: the
    HDF5 file's ``n_frames`` would disagree with its /tracks/xy, which the readers refuse; and when a value is one the
    readers refuse (``read.check_values``: a negative variance, a position partly NaN, a dof not above 2). Errors name
    ``named``, the output the user gave, when ``path`` is a staged copy of it (default: ``path``); a plugin writer's
    exception is one of them, naming its stage."""
    path = Path(path)
    named = path if named is None else named
    if tracks.xy.shape[1] != info.n_frames:
        raise CondtrackError(f"{named}: not written: the tracks have {counted(tracks.xy.shape[1], 'frame')}, but "
                             f"{info.input or 'their input'} has {counted(info.n_frames, 'frame')}")
    from condtrack_cli.io.read import check_values  # read imports this module

    try:  # what the readers would refuse (a filter stage's negative variance, a half-NaN position) is not written
        check_values(tracks)
    except ValueError as error:
        method = f" (filter '{meta['method']}')" if meta.get("method") else ""
        raise CondtrackError(f"{named}: not written: {error}{method}") from None
    writer = get("output", track_format(path, "output"))
    with atomic_path(path) as temporary:
        try:
            writer.build(tracks, temporary, info, meta, settings)
        except OSError as error:  # h5py reports a full disk as OSError with errno ENOSPC, as Python does
            raise write_error(named, error) from None
        except CondtrackError as error:  # a plugin writer's exception (StageSpec.call's, naming the stage)
            raise _plugin_write_error(named, error, writer.label) from error.__cause__


def _plugin_write_error(path: str | Path, error: CondtrackError, stage: str) -> CondtrackError:
    """What a plugin writer ``stage`` raised, as a message naming the file ``path`` as well: an OSError of its own
    (``error.__cause__``) in the words of every other write error (``write_error``), the stage after them."""
    if isinstance(error.__cause__, OSError):
        return CondtrackError(f"{write_error(path, error.__cause__)}, in {stage}")
    return CondtrackError(f"{path}: not written: {error}")
