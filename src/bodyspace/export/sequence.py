"""Mesh sequences: an animation as posed vertices per frame, one ``.npz`` file.

``write_mesh_sequence(path, vertices, faces, frame_time)`` writes ``vertices`` (F, V, 3) float32
metres (+Y up, +Z front), ``faces`` (F', 3) int64, ``frame_time`` (seconds) and a ``header``
(UTF-8 JSON as uint8: format ``bodyspace.mesh_sequence``, version, counts, units and any extras
such as the clip and the body) with ``allow_pickle=False``, atomically. ``read_mesh_sequence``
reads it back: ``np.load(path)["vertices"]`` is all another program needs.

``numbered_mesh_paths(pattern, frames)`` and ``write_numbered_meshes(paths, vertices, faces)``:
the same sequence as one mesh file a frame (PLY or OBJ, any program opens them), named by a
printf-style frame field in the file name (``walk_%04d.ply``: ``walk_0000.ply``, ...), each
written atomically.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np

from bodyspace.atomic import atomic_path
from bodyspace.errors import MeshError, ParameterError
from bodyspace.mesh.io import save_mesh

__all__ = ["FORMAT", "NUMBERED_SUFFIXES", "numbered_mesh_paths", "read_mesh_sequence", "write_mesh_sequence",
           "write_numbered_meshes"]

FORMAT = "bodyspace.mesh_sequence"
VERSION = 1
# Mesh formats of a numbered sequence (one file a frame).
NUMBERED_SUFFIXES = (".ply", ".obj")
# A printf-style integer field: %d, %4d, %04d.
_FRAME_FIELD = re.compile(r"%(0?)(\d*)d")


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


def numbered_mesh_paths(pattern: str | os.PathLike, frames: int) -> list[Path]:
    """The file of each frame 0..frames-1 for ``pattern``, a path whose file name holds one
    frame field (``%d``, ``%4d`` or ``%04d``) and ends in .ply or .obj: ``walk_%04d.ply`` gives
    ``walk_0000.ply``, ``walk_0001.ply``, ... (in the pattern's folder)."""
    pattern = Path(pattern)
    name = pattern.name
    fields = _FRAME_FIELD.findall(name)
    if len(fields) != 1 or name.replace("%%", "").count("%") != 1:
        raise ParameterError(f"{pattern}: a numbered mesh sequence needs one frame field such as %04d in the file "
                             f"name (found {len(fields)}); e.g. walk_%04d.ply")
    if pattern.suffix.lower() not in NUMBERED_SUFFIXES:
        raise ParameterError(f"{pattern}: a numbered mesh sequence is written as {' or '.join(NUMBERED_SUFFIXES)}; "
                             "expected a name such as walk_%04d.ply")
    if frames < 1:
        raise ParameterError(f"frames: {frames}, expected at least one frame")
    return [pattern.with_name(name % k) for k in range(frames)]


def write_numbered_meshes(paths: list[Path], vertices: np.ndarray, faces: np.ndarray) -> list[Path]:
    """Write frame k of ``vertices`` (frames, V, 3) metres with ``faces`` (F, 3) to ``paths[k]``
    (PLY or OBJ by suffix), each file atomically; return the paths."""
    v = np.asarray(vertices)
    if v.ndim != 3 or v.shape[2] != 3 or len(v) != len(paths):
        raise MeshError(f"vertices: shape {v.shape}, expected ({len(paths)}, V, 3): one mesh a file")
    for path, frame in zip(paths, v):
        save_mesh(path, frame, faces)
    return list(paths)
