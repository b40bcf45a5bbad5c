"""Mesh sequences: an animation as posed vertices per frame, one ``.npz`` file.

``write_mesh_sequence(path, vertices, faces, frame_time)`` writes ``vertices`` (F, V, 3) float32
metres (+Y up, +Z front), ``faces`` (F', 3) int64, ``frame_time`` (seconds) and a ``header``
(UTF-8 JSON as uint8: format ``bodyspace.mesh_sequence``, version, counts, units and any extras
such as the clip and the body) with ``allow_pickle=False``, atomically. ``read_mesh_sequence``
reads it back: ``np.load(path)["vertices"]`` is all another program needs.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from bodyspace.atomic import atomic_path
from bodyspace.errors import MeshError, ParameterError

__all__ = ["FORMAT", "read_mesh_sequence", "write_mesh_sequence"]

FORMAT = "bodyspace.mesh_sequence"
VERSION = 1


def write_mesh_sequence(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray, frame_time: float,
                        extras: dict | None = None) -> Path:
    """Write posed vertices (F, V, 3) metres, faces (F', 3) and the frame time (s) as an ``.npz``."""
    path = Path(path)
    if path.suffix.lower() != ".npz":
        raise ParameterError(f"{path}: a mesh sequence is written as .npz; expected a name ending in .npz")
    v = np.asarray(vertices)
    f = np.asarray(faces, dtype=np.int64)
    if v.ndim != 3 or v.shape[2] != 3 or len(v) == 0:
        raise MeshError(f"vertices: shape {v.shape}, expected (frames, V, 3) with at least one frame")
    if f.ndim != 2 or f.shape[1] != 3 or (len(f) and (f.min() < 0 or f.max() >= v.shape[1])):
        raise MeshError(f"faces: shape {f.shape}, expected (F, 3) indices of the {v.shape[1]} vertices")
    if not (np.isfinite(frame_time) and frame_time > 0):
        raise ParameterError(f"frame_time: {frame_time!r}, expected a positive number of seconds")
    header = {"format": FORMAT, "format_version": VERSION, "frames": int(v.shape[0]), "vertices": int(v.shape[1]),
              "faces": int(len(f)), "units": "metre", "up": "+Y", "front": "+Z", "frame_time_s": float(frame_time),
              **(extras or {})}
    arrays = {"header": np.frombuffer(json.dumps(header).encode("utf-8"), dtype=np.uint8),
              "vertices": v.astype(np.float32), "faces": f, "frame_time": np.array(float(frame_time))}
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as out:
            np.savez(out, **arrays)
    return path


def read_mesh_sequence(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, float, dict]:
    """Vertices (F, V, 3) float32, faces (F', 3), frame time (s) and the header of a sequence file."""
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            header = json.loads(bytes(z["header"]).decode("utf-8"))
            if header.get("format") != FORMAT:
                raise MeshError(f"{path}: format {header.get('format')!r}, expected {FORMAT!r}")
            return z["vertices"], z["faces"], float(z["frame_time"]), header
    except (OSError, KeyError, ValueError) as exc:
        raise MeshError(f"{path}: not a bodyspace mesh sequence ({exc}); expected an .npz written by "
                        "bodyspace animate --out NAME.npz") from None
