"""Write a scene as a folder (frames, queries.csv, tracks.csv, labels.csv, scene.json); the shipped samples."""

from __future__ import annotations

import json
import re
import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np

from condtrack_cli.frames.synthetic.scenes import SAMPLE_SEEDS, Scene, make_scene

COORDINATES = "pixels; x right, y down; origin (0, 0) at the centre of the top-left pixel (OpenCV)"
_OWN_FILES = re.compile(r"\d{5}\.png|queries\.csv|tracks\.csv|labels\.csv|scene\.json")


def write_scene(scene: Scene, out_dir: str | Path) -> Path:
    """Write ``scene`` into ``out_dir`` (files listed in the module docstring); returns the folder.

    The folder is written whole or not at all: files go to a temporary sibling
    folder that then replaces ``out_dir``. An existing ``out_dir`` holding any file
    this writer does not produce is refused (ValueError) rather than deleted.
    """
    out_dir = Path(out_dir)
    _refuse_foreign(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", dir=out_dir.parent))
    try:
        for k, frame in enumerate(scene.frames):
            _, png = cv2.imencode(".png", frame, [cv2.IMWRITE_PNG_COMPRESSION, 9])
            (staging / f"{k:05d}.png").write_bytes(png.tobytes())
        q = scene.queries
        _write_csv(staging / "queries.csv", "point_id,frame,x,y", [q.point_id, q.frame, q.xy[:, 0], q.xy[:, 1]],
                   "%d,%d,%.4f,%.4f")
        n_points, n_frames = scene.visible.shape
        _write_csv(
            staging / "tracks.csv",
            "point_id,frame,x,y,visible",
            [np.repeat(q.point_id, n_frames), np.tile(np.arange(n_frames), n_points),
             scene.tracks[..., 0].ravel(), scene.tracks[..., 1].ravel(), scene.visible.ravel().astype(int)],
            "%d,%d,%.4f,%.4f,%d",
        )
        _write_csv(staging / "labels.csv", "point_id,layer", [q.point_id, scene.layer], "%d,%d")
        meta = {
            "scene": scene.name,
            "seed": scene.seed,
            "width": scene.frames.shape[2],
            "height": scene.frames.shape[1],
            "n_frames": n_frames,
            "noise": scene.noise,
            "coordinates": COORDINATES,
            "layers": list(scene.layer_names),
            "maps": scene.maps.tolist(),
        }
        text = "{\n" + ",\n".join(f" {json.dumps(key)}: {json.dumps(value)}" for key, value in meta.items()) + "\n}\n"
        (staging / "scene.json").write_text(text, encoding="ascii", newline="\n")
        if out_dir.exists():
            shutil.rmtree(out_dir)
        staging.replace(out_dir)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return out_dir


def _refuse_foreign(out_dir: Path) -> None:
    """ValueError when ``out_dir`` exists and holds a file :func:`write_scene` does not produce."""
    if out_dir.exists():
        foreign = [p.name for p in out_dir.iterdir() if not _OWN_FILES.fullmatch(p.name)]
        if foreign:
            raise ValueError(f"{out_dir}: holds '{foreign[0]}', not a synthetic scene folder; not overwriting")


def _write_csv(path: Path, header: str, columns: list[np.ndarray], fmt: str) -> None:
    """One row per element of the (N,) columns, formatted by ``fmt``."""
    table = np.empty((len(columns[0]), len(columns)), dtype=object)
    for j, column in enumerate(columns):
        table[:, j] = column
    with open(path, "w", encoding="ascii", newline="\n") as handle:
        np.savetxt(handle, table, fmt=fmt, header=header, comments="", newline="\n")


def write_samples(out_root: str | Path) -> dict[str, Path]:
    """Write the shipped samples (SAMPLE_SEEDS, default sizes) as ``out_root/<scene>``; returns name -> folder.

    Every folder is checked as :func:`write_scene` checks it before any is written.
    """
    folders = {name: Path(out_root) / name for name in SAMPLE_SEEDS}
    for folder in folders.values():
        _refuse_foreign(folder)
    return {name: write_scene(make_scene(name, SAMPLE_SEEDS[name]), folder) for name, folder in folders.items()}
