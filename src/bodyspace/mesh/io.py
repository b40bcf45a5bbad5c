"""Read and write triangle meshes as plain arrays, keeping the vertex order exactly.

Registered meshes share one topology *by vertex index*: vertex 1234 is the same point of the
body in every scan. So a reader must never merge, split or reorder vertices.

- OBJ is parsed here (numpy, no trimesh): trimesh splits OBJ files with several ``o``/``g``
  groups or materials into separate geometries and duplicates/reorders vertices when it joins
  them again, which silently breaks the shared topology. Our parser keeps every ``v`` line, in
  file order, and fan-triangulates polygons in face order (quads become (0,1,2),(0,2,3), as
  trimesh does).
- PLY, GLB/GLTF and STL go through trimesh with ``process=False, maintain_order=True``.
  STL stores three fresh vertices per triangle, so an STL file has no shared vertices and
  cannot carry a registered topology; use it for export only.

Arrays: ``vertices`` (V, 3) float64, ``faces`` (F, 3) int64, in the file's units (the caller
converts to metres).
"""

from __future__ import annotations

import os
import re
import warnings
from pathlib import Path

import numpy as np

from bodyspace.atomic import atomic_path
from bodyspace.errors import MeshError

READ_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".stl")
WRITE_SUFFIXES = (".obj", ".ply", ".glb", ".stl")

# Nine significant digits reproduce any float32 exactly (the on-disk precision of the scan
# database) and are 1 nm at 1 m, far below any scanner's noise.
OBJ_FLOAT_FORMAT = "%.9g"

# In a face corner "v/vt/vn" only the position index matters to us.
_OBJ_CORNER_TAIL = re.compile(r"/[^\s]*")


def load_mesh(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh, keeping the file's vertex order and count.

    Returns ``vertices`` (V, 3) float64 and ``faces`` (F, 3) int64. Raises MeshError naming the
    file if it is missing, unreadable, has no faces, indexes missing vertices or holds NaN/inf.
    """
    path = mesh_path(path)
    suffix = path.suffix.lower()
    if suffix not in READ_SUFFIXES:
        raise MeshError(f"{path}: unsupported mesh format '{suffix}', expected one of {', '.join(READ_SUFFIXES)}")
    if not path.is_file():
        raise MeshError(f"{path}: mesh file not found")
    if suffix == ".obj":
        vertices, faces = _read_obj(path)
    else:
        vertices, faces = _read_with_trimesh(path, suffix[1:])
    _check_loaded(path, vertices, faces)
    return vertices, faces


def save_mesh(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Write ``vertices`` (V, 3) and ``faces`` (F, 3) to ``path``; the format follows the suffix.

    The file appears complete or not at all (written to a temporary name, then renamed).
    trimesh (for PLY/STL/glTF) is imported here, not at the top: it takes 0.5-3 s to import and
    OBJ, the format of every bodyspace command, does not need it.
    """
    path = mesh_path(path)
    suffix = path.suffix.lower()
    if suffix not in WRITE_SUFFIXES:
        raise MeshError(f"{path}: cannot write mesh format '{suffix}', expected one of {', '.join(WRITE_SUFFIXES)}")
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise MeshError(f"{path}: vertices have shape {vertices.shape}, expected (V, 3)")
    if faces.ndim != 2 or faces.shape[1] != 3 or (faces.size and faces.dtype.kind not in "iu"):
        raise MeshError(f"{path}: faces have shape {faces.shape} and dtype {faces.dtype}, expected (F, 3) integers")
    _check_loaded(path, vertices, faces.astype(np.int64))
    with atomic_path(path) as tmp:
        if suffix == ".obj":
            _write_obj(tmp, vertices, faces)
        else:
            import trimesh

            mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
            # The temporary file ends in ".part", so the format must be named explicitly.
            mesh.export(file_obj=str(tmp), file_type=suffix[1:])


def mesh_path(path) -> Path:
    """``path`` (str or os.PathLike) as a Path; MeshError for anything else (None, a number, bytes)."""
    if isinstance(path, Path):
        return path
    if not isinstance(path, (str, os.PathLike)) or isinstance(os.fspath(path), bytes):
        raise MeshError(f"mesh path {path!r} is a {type(path).__name__}, expected a file name (str or pathlib.Path)")
    if not os.fspath(path):
        raise MeshError("mesh path is empty, expected a file name such as body.obj")
    return Path(path)


def _check_loaded(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Raise MeshError unless ``faces`` (F, 3) is non-empty and indexes finite ``vertices`` (V, 3)."""
    if len(vertices) == 0 and len(faces) == 0:
        raise MeshError(f"{path}: found no vertices and no faces; the file is empty, cut short, binary or of "
                        f"another format than its suffix says (expected {_EXPECTED[path.suffix.lower()[1:]]})")
    if len(faces) == 0:
        raise MeshError(f"{path}: found {len(vertices)} vertices and no faces, expected a triangle mesh")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise MeshError(f"{path}: faces index vertices {faces.min()}..{faces.max()}, "
                        f"but the file has {len(vertices)} vertices")
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise MeshError(f"{path}: {int(bad.sum())} vertices contain NaN or infinity "
                        f"(first: vertex {int(np.argmax(bad))}), expected finite coordinates")


# What each format must hold, for the messages about a file that does not read.
_EXPECTED = {
    "obj": "text lines 'v x y z' and 'f i j k'",
    "ply": "a PLY file (binary or ASCII) with a 'vertex' and a 'face' element",
    "stl": "an STL file of triangles (binary: 80-byte header, triangle count, 50 bytes per triangle; or ASCII)",
    "glb": "a binary glTF 2.0 file holding a triangle mesh",
    "gltf": "a glTF 2.0 JSON file holding a triangle mesh, with its buffer files beside it",
}
_TRUNCATED_HINT = "it may be truncated (an interrupted copy or download) or of another format than its suffix says"


def _read_with_trimesh(path: Path, file_type: str) -> tuple[np.ndarray, np.ndarray]:
    """PLY / glTF / STL through trimesh without any merging or reordering (trimesh is imported
    here, only when such a file is read: see ``save_mesh``)."""
    import trimesh

    try:
        loaded = trimesh.load(str(path), file_type=file_type, process=False, maintain_order=True)
    except Exception as exc:  # trimesh raises many types for a damaged file
        raise MeshError(f"{path}: could not read as {file_type.upper()} ({str(exc)[:120]}); expected "
                        f"{_EXPECTED[file_type]}; {_TRUNCATED_HINT}") from exc
    if isinstance(loaded, trimesh.Scene):
        meshes = [g for g in loaded.dump() if isinstance(g, trimesh.Trimesh)] if loaded.geometry else []
        if not meshes:
            raise MeshError(f"{path}: found no triangle mesh ({path.stat().st_size} bytes); expected "
                            f"{_EXPECTED[file_type]}; {_TRUNCATED_HINT}")
        loaded = meshes[0] if len(meshes) == 1 else trimesh.util.concatenate(meshes)
    if not isinstance(loaded, trimesh.Trimesh):
        n_points = len(getattr(loaded, "vertices", []))
        raise MeshError(f"{path}: found {type(loaded).__name__} with {n_points} vertices and no faces, "
                        f"expected a triangle mesh")
    return (np.asarray(loaded.vertices, dtype=np.float64).reshape(-1, 3),
            np.asarray(loaded.faces, dtype=np.int64).reshape(-1, 3))


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Wavefront OBJ: every ``v`` line in file order; polygons triangulated as trimesh does."""
    try:
        text = path.read_text(encoding="utf-8-sig", errors="replace")
    except OSError as exc:
        raise MeshError(f"{path}: could not read: {exc}") from exc
    vertices = _parse_obj_vertices(path, _obj_statements(text, "v"), text)
    face_lines = _obj_statements(text, "f")
    faces = _parse_obj_faces(path, face_lines, text) if face_lines else np.zeros((0, 3), dtype=np.int64)
    _check_declared_counts(path, text, len(vertices), len(faces))
    return vertices, faces


# The first line _write_obj writes: a file cut short (a killed copy, a full disk) still parses
# when it ends at a line break, so the counts it declares are how such a cut is caught.
_OBJ_COUNTS_HEADER = re.compile(r"# bodyspace mesh: (\d+) vertices, (\d+) faces")


def _check_declared_counts(path: Path, text: str, n_vertices: int, n_faces: int) -> None:
    """MeshError if a file written by bodyspace holds fewer or more vertices/faces than its header says."""
    declared = _OBJ_COUNTS_HEADER.match(text[:100])
    if declared is None:
        return  # written by another program: nothing to compare with
    want_v, want_f = int(declared[1]), int(declared[2])
    if (want_v, want_f) != (n_vertices, n_faces):
        raise MeshError(f"{path}: holds {n_vertices} vertices and {n_faces} triangles, but its first line says "
                        f"{want_v} vertices and {want_f} faces: the file is truncated or was edited; "
                        f"copy or write it again")


# Registered meshes repeat the same face lines file after file; remembering the last parse
# skips about a third of the reading time of each further file.
_last_obj_faces: tuple[str, np.ndarray] = ("", np.zeros((0, 3), dtype=np.int64))


def _parse_obj_faces(path: Path, face_lines: list[str], text: str) -> np.ndarray:
    """``f`` lines (with their keyword) -> triangles (F, 3) int64, 0-based."""
    global _last_obj_faces
    joined = "\n".join(face_lines)
    if joined == _last_obj_faces[0]:
        return _last_obj_faces[1].copy()
    # Each line is "f" plus one token per corner.
    corner_counts = np.fromiter(map(len, map(str.split, face_lines)), dtype=np.int64, count=len(face_lines)) - 1
    if corner_counts.min() < 3:
        bad = int(np.argmax(corner_counts < 3))
        cut = bad == len(face_lines) - 1 and not text.endswith("\n")
        raise MeshError(f"{path}: face {bad} ('{face_lines[bad].strip()}') has {corner_counts[bad]} corners, "
                        f"expected at least 3" + ("; the file ends inside this line: it is truncated" if cut else ""))
    indices = None
    if joined.count("f") == len(face_lines):  # the keywords are the only letters
        indices = _parse_numbers(_OBJ_CORNER_TAIL.sub("", joined.replace("f", " ")), np.int64,
                                 int(corner_counts.sum()))
    if indices is None:
        raise MeshError(f"{path}: a face line holds a non-integer vertex index, expected 'f i j k' with i >= 1")
    if (indices == 0).any():
        raise MeshError(f"{path}: a face uses vertex index 0, but OBJ indices start at 1")
    if (indices < 0).any():
        # Negative indices count back from the last vertex defined *before* that face line, so
        # the result depends on more than the face lines: not remembered.
        defined = np.repeat(_vertices_defined_before_each_face(text), corner_counts)
        return triangulate_polygons(np.where(indices < 0, defined + indices, indices - 1), corner_counts)
    faces = triangulate_polygons(indices - 1, corner_counts)
    _last_obj_faces = (joined, faces.copy())
    return faces


def _obj_statements(text: str, keyword: str) -> list[str]:
    """The lines ``keyword <values>`` of an OBJ text, in file order, starting at the keyword."""
    head = keyword + " "
    tabbed = f"\n{keyword}\t" in text or text.startswith(keyword + "\t")
    indented = "\n " in text or "\n\t" in text or text[:1] in (" ", "\t")
    if tabbed or indented:
        # Rare layouts: a regular expression handles them, at a few times the cost.
        pattern = re.compile(rf"^[ \t]*({keyword}[ \t]+[^\r\n]*)", re.MULTILINE)
        return pattern.findall(text)
    if text.startswith(head):
        start = 0
    else:
        start = text.find("\n" + head) + 1
        if start == 0:
            return []
    end = text.find("\n", text.rfind("\n" + head) + 1)
    block = text[start:] if end < 0 else text[start:end]
    # Exporters write each kind of statement as one contiguous run; then one split suffices.
    if block.count("\n") == block.count("\n" + head):
        return block.split("\n")
    return [line for line in text.split("\n") if line.startswith(head)]


def _parse_numbers(text: str, dtype, expected: int) -> np.ndarray | None:
    """Whitespace-separated numbers -> (expected,) array, or None if any token is not a number."""
    with warnings.catch_warnings():
        # numpy warns (rather than raises) when it stops at a bad token; the count tells us.
        warnings.simplefilter("ignore", DeprecationWarning)
        try:
            values = np.fromstring(text, dtype=dtype, sep=" ")
        except ValueError:
            return None
    return values if values.size == expected else None


def _parse_obj_vertices(path: Path, vertex_lines: list[str], text: str = "\n") -> np.ndarray:
    """``v x y z [w | r g b]`` lines -> (V, 3) float64 (extra values are dropped).

    ``text`` (the whole file) tells whether a bad last line is where the file was cut off.
    """
    joined = " ".join(vertex_lines)
    if joined.count("v") == len(vertex_lines):  # the keywords are the only 'v's: blank them out
        values = _parse_numbers(joined.replace("v", " "), np.float64, 3 * len(vertex_lines))
        if values is not None:
            return values.reshape(-1, 3)
    # Some lines carry a w or colours (or garbage): take the first three values of each line.
    rows = [line.split()[1:4] for line in vertex_lines]
    for i, row in enumerate(rows):
        if len(row) < 3:
            cut = i == len(rows) - 1 and text.rstrip("\n").endswith(vertex_lines[i].rstrip("\n"))
            raise MeshError(f"{path}: vertex {i} ('{vertex_lines[i].strip()[:60]}') has fewer than 3 coordinates"
                            + ("; the file ends inside this line: it is truncated" if cut else ""))
    try:
        return np.array(rows, dtype=np.float64).reshape(-1, 3)
    except ValueError as exc:
        raise MeshError(f"{path}: a 'v' line holds a non-numeric coordinate ({str(exc)[:80]!r}); "
                        "expected 'v x y z' with decimal numbers") from exc


def _vertices_defined_before_each_face(text: str) -> np.ndarray:
    """(P,) number of ``v`` lines preceding each of the P ``f`` lines."""
    counts, n_vertices = [], 0
    for line in text.splitlines():
        head = line.lstrip()[:2]
        if head in ("v ", "v\t"):
            n_vertices += 1
        elif head in ("f ", "f\t"):
            counts.append(n_vertices)
    return np.asarray(counts, dtype=np.int64)


def triangulate_polygons(indices: np.ndarray, corner_counts: np.ndarray) -> np.ndarray:
    """Polygons as flat vertex ``indices`` (sum(corner_counts),) -> triangles (F, 3).

    Same triangles in the same order as trimesh's OBJ reader, so faces agree with meshes loaded
    through it: a quad (a,b,c,d) gives (a,b,c),(c,d,a), a larger polygon the fan (a,b,c),(a,c,d)...
    A file of only quads lists every quad's first triangle, then every quad's second; otherwise
    the triangles follow the polygons in file order.
    """
    indices = np.asarray(indices, dtype=np.int64)
    corner_counts = np.asarray(corner_counts, dtype=np.int64)
    if (corner_counts == 3).all():
        return indices.reshape(-1, 3)
    if (corner_counts == 4).all():
        quads = indices.reshape(-1, 4)
        return np.concatenate([quads[:, [0, 1, 2]], quads[:, [2, 3, 0]]])
    starts = np.cumsum(corner_counts) - corner_counts
    triangles_per_polygon = corner_counts - 2
    polygon = np.repeat(np.arange(len(corner_counts)), triangles_per_polygon)
    k = np.arange(len(polygon)) - (np.cumsum(triangles_per_polygon) - triangles_per_polygon)[polygon]
    local = np.stack([np.zeros_like(k), k + 1, k + 2], axis=1)
    # A quad's second triangle starts at its third corner: (2, 3, 0) rather than (0, 2, 3).
    local[(corner_counts[polygon] == 4) & (k == 1)] = (2, 3, 0)
    return indices[starts[polygon][:, None] + local]


def _write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Positions and 1-based triangles only: no normals or UVs, so nothing can split vertices."""
    with open(path, "w", encoding="utf-8") as handle:
        handle.write(f"# bodyspace mesh: {len(vertices)} vertices, {len(faces)} faces\n")
        np.savetxt(handle, vertices, fmt=f"v {OBJ_FLOAT_FORMAT} {OBJ_FLOAT_FORMAT} {OBJ_FLOAT_FORMAT}")
        np.savetxt(handle, np.asarray(faces, dtype=np.int64) + 1, fmt="f %d %d %d")
