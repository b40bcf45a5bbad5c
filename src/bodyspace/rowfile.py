"""Rows of a .npy file written and read in chunks with plain file I/O, so memory stays bounded.

A memory map (``np.load(mmap_mode="r")``) is the simplest lazy array, but every page it touches
stays mapped into the process: reading all 20,000 scans of a database through one (3.2 GB of
float32 vertices) makes the process's resident size grow by the whole file, and the peak memory
the operating system reports with it. ``write_rows`` and ``read_rows`` go through ``pwrite`` /
``pread`` instead: the page cache still holds the file (the kernel frees it under pressure), but
the process only ever holds the chunk it asked for.

The file is an ordinary .npy file (``numpy.lib.format`` version 1 header, C order): anything
that reads .npy reads it, memory-mapped or not.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from bodyspace.errors import DatabaseError


def create_rows(path: str | os.PathLike, shape: tuple[int, ...], dtype=np.float32) -> int:
    """Create the .npy file ``path`` of ``shape`` (N, ...) and ``dtype``, its data unwritten
    (a sparse file of zeros); returns the byte offset of row 0."""
    dtype = np.dtype(dtype).newbyteorder("<")
    header = {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False, "shape": tuple(shape)}
    with open(path, "wb") as handle:
        np.lib.format.write_array_header_1_0(handle, header)
        offset = handle.tell()
        handle.truncate(offset + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize)
    return offset


def npy_layout(path: str | os.PathLike) -> tuple[tuple[int, ...], np.dtype, int]:
    """(shape, dtype, offset of row 0) of a C-order .npy file, read from its header."""
    with open(path, "rb") as handle:
        version = np.lib.format.read_magic(handle)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(handle)
        else:
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(handle)
        offset = handle.tell()
    if fortran or dtype.hasobject:
        raise DatabaseError(f"{path}: a Fortran-order or object array; expected a C-order numeric .npy file")
    return tuple(shape), dtype, offset


def write_rows(path: str | os.PathLike, start: int, rows: np.ndarray, sync: bool = False) -> None:
    """Write ``rows`` (n, ...) as rows ``start`` .. ``start + n`` of the .npy file ``path``
    (made by ``create_rows``), converted to its dtype. ``sync``: fsync before returning, so a
    chunk recorded as done afterwards is on disk even if the machine stops."""
    shape, dtype, offset = npy_layout(path)
    rows = np.ascontiguousarray(rows, dtype=dtype)
    if rows.shape[1:] != shape[1:] or start < 0 or start + len(rows) > shape[0]:
        raise DatabaseError(f"{path}: rows {start}..{start + len(rows)} of shape {rows.shape[1:]}, but the file "
                            f"holds {shape[0]} rows of shape {shape[1:]}")
    row_bytes = int(np.prod(shape[1:], dtype=np.int64)) * dtype.itemsize
    fd = os.open(path, os.O_WRONLY)
    try:
        view, at = memoryview(rows.reshape(-1).view(np.uint8)), offset + start * row_bytes
        while len(view):
            written = os.pwrite(fd, view, at)
            view, at = view[written:], at + written
        if sync:
            os.fsync(fd)
    finally:
        os.close(fd)


def read_rows(path: str | os.PathLike, start: int, stop: int, layout=None) -> np.ndarray:
    """Rows ``start`` .. ``stop`` of the .npy file ``path`` as a new array (its dtype), read with
    ``pread`` (nothing stays mapped). ``layout``: ``npy_layout(path)`` if already known."""
    shape, dtype, offset = layout or npy_layout(path)
    stop = min(stop, shape[0])
    row_bytes = int(np.prod(shape[1:], dtype=np.int64)) * dtype.itemsize
    out = np.empty((max(0, stop - start),) + tuple(shape[1:]), dtype=dtype)
    buffer = memoryview(out.reshape(-1).view(np.uint8))
    fd = os.open(path, os.O_RDONLY)
    try:
        at = offset + start * row_bytes
        while len(buffer):
            got = os.preadv(fd, [buffer], at)
            if got == 0:
                raise DatabaseError(f"{path}: ends before row {stop}; the file is truncated")
            buffer, at = buffer[got:], at + got
    finally:
        os.close(fd)
    return out


class RowFile:
    """An (N, ...) .npy file on disk read in row blocks: what out-of-core code passes around
    instead of an array (``shape.solvers`` accept it wherever they take codes).

    ``RowFile.create(path, shape, dtype)`` makes the file; ``write(start, rows)`` fills it;
    ``read(start, stop)`` and ``blocks(size)`` read it back without mapping it.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.layout = npy_layout(self.path)
        self.shape, self.dtype = self.layout[0], self.layout[1]
        self.ndim = len(self.shape)

    @classmethod
    def create(cls, path: str | os.PathLike, shape: tuple[int, ...], dtype=np.float32) -> "RowFile":
        create_rows(path, shape, dtype)
        return cls(path)

    def __len__(self) -> int:
        return int(self.shape[0])

    @property
    def nbytes(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64)) * self.dtype.itemsize

    def write(self, start: int, rows: np.ndarray) -> None:
        write_rows(self.path, start, rows)

    def read(self, start: int, stop: int) -> np.ndarray:
        return read_rows(self.path, start, stop, self.layout)

    def blocks(self, size: int):
        """``(start, rows (n, ...))`` over the file in blocks of ``size`` rows."""
        for start in range(0, len(self), size):
            yield start, self.read(start, start + size)

    def __repr__(self) -> str:
        return f"RowFile({str(self.path)!r}, shape={self.shape}, dtype={self.dtype})"
