"""Memory and disk a command would need, checked before it starts: a request that cannot fit is
refused up front, in the command's flags, with the amount it needs and the amount there is
(not a MemoryError half-way, nor a disk filled for hours)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from bodyspace.errors import ParameterError

# Bytes a body mesh of V vertices and F faces takes in each output format, at least (OBJ: about
# 28 bytes a "v x y z" line and 20 an "f a b c" line; PLY: binary float32 xyz, a count byte and
# three int32; glb: float32 xyz and uint32 indices).
MESH_BYTES = {"obj": (28, 20), "ply": (12, 13), "glb": (12, 12)}
# Bytes of memory a body's coefficients take while drawn (truncnorm's temporaries) and named.
COEFFICIENT_TEMPORARIES = 4
NAME_BYTES = 80


def format_bytes(n: float) -> str:
    """``1.5e9`` -> ``'1.4 GiB'``."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if abs(n) < 1024 or unit == "PiB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return f"{n:.1f} PiB"  # pragma: no cover - the loop returns


def available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux MemAvailable), or None if unknown."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def free_disk(path: Path) -> int | None:
    """Free bytes on the file system that would hold ``path`` (its nearest existing parent)."""
    where = Path(path).absolute()
    while not where.exists() and where != where.parent:
        where = where.parent
    try:
        return shutil.disk_usage(where).free
    except OSError:
        return None


def mesh_bytes(fmt: str, n_vertices: int, n_faces: int) -> int:
    """Bytes of one mesh file of format ``fmt`` (a key of ``MESH_BYTES``), at least."""
    per_vertex, per_face = MESH_BYTES[fmt]
    return per_vertex * n_vertices + per_face * n_faces


def check_memory(need: float, request: str, fix: str) -> None:
    """Refuse ``request`` (the flags, e.g. '-n 1000000000000') when it needs more than the
    available memory; ``fix`` says what to ask instead."""
    have = available_memory()
    if have is not None and need > have:
        raise ParameterError(f"{request}: would need about {format_bytes(need)} of memory, {format_bytes(have)} "
                             f"is available; {fix}")


def check_disk(need: float, out: Path, request: str, fix: str) -> None:
    """Refuse ``request`` when its output (under ``out``) needs more than the free disk space."""
    have = free_disk(out)
    if have is not None and need > have:
        raise ParameterError(f"{request}: would write about {format_bytes(need)} to {out}, the disk has "
                             f"{format_bytes(have)} free; {fix}")


def check_bodies_fit(n: int, fmt: str, n_components: int, n_vertices: int, n_faces: int, out: Path) -> None:
    """Refuse ``-n n`` bodies (``sample``, ``crowd``) whose coefficients and names do not fit in
    memory or whose meshes do not fit on the disk, before anything is written."""
    fix = "ask for fewer bodies (a smaller -n)"
    check_memory(n * (n_components * 8 * COEFFICIENT_TEMPORARIES + NAME_BYTES), f"-n {n}", fix)
    smaller = "" if fmt != "obj" else " or a smaller format (--format ply)"
    check_disk(n * mesh_bytes(fmt, n_vertices, n_faces), out, f"-n {n} --format {fmt}", f"{fix}{smaller}")
