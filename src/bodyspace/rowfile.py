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

import fcntl
import json
import os
from pathlib import Path

import numpy as np

from bodyspace.errors import DatabaseError, OutputError


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


def read_rows(path: str | os.PathLike, start: int, stop: int, layout=None, out: np.ndarray | None = None) -> np.ndarray:
    """Rows ``start`` .. ``stop`` of the .npy file ``path`` as a new array (its dtype), read with
    ``pread`` (nothing stays mapped). ``layout``: ``npy_layout(path)`` if already known. ``out``:
    a C-contiguous array of those rows' shape and the file's dtype to read into instead (a caller
    reading chunk after chunk keeps one: fresh pages cost more than the copy)."""
    shape, dtype, offset = layout or npy_layout(path)
    stop = min(stop, shape[0])
    row_bytes = int(np.prod(shape[1:], dtype=np.int64)) * dtype.itemsize
    want = (max(0, stop - start),) + tuple(shape[1:])
    if out is None:
        out = np.empty(want, dtype=dtype)
    elif out.shape != want or out.dtype != dtype or not out.flags.c_contiguous:
        raise DatabaseError(f"{path}: rows {start}..{stop} are {want} {dtype}; the array to read them into is "
                            f"{out.shape} {out.dtype}{'' if out.flags.c_contiguous else ' (not contiguous)'}")
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


class CheckpointedRows:
    """A ``RowFile`` filled in row order, chunk by chunk, that a killed run continues.

    ``FOLDER/.NAME-KEY.npy`` holds the rows, ``FOLDER/.NAME-KEY.json`` how many are complete
    (written after the rows are synced, atomically) and what the caller keeps beside them; KEY
    names what the rows are computed from, so a run of other inputs never continues them. While a
    run works, it holds an ``flock`` on ``.NAME-KEY.lock``: a second run of the same work is
    refused, and files of this NAME whose lock is free (an earlier, interrupted run of other
    inputs) are removed when a run starts, so one folder keeps at most one interrupted run a NAME.
    """

    def __init__(self, folder: str | os.PathLike, name: str, key: str, shape: tuple[int, ...], dtype=np.float32):
        self.folder, self.name, self.key = Path(folder), name, key
        self.shape, self.dtype = tuple(int(s) for s in shape), np.dtype(dtype)
        stem = self.folder / f".{name}-{key[:16]}"
        self.path, self.state_path, self.lock_path = (stem.with_suffix(".npy"), stem.with_suffix(".json"),
                                                      stem.with_suffix(".lock"))
        self.rows: RowFile | None = None
        self._lock = None

    def open(self) -> tuple[int, dict, str]:
        """Take the lock and open the rows: ``(rows complete, what the caller stored, a sentence
        for the user: resumed or started cleanly)``."""
        self.folder.mkdir(parents=True, exist_ok=True)
        self._lock = open(self.lock_path, "w")
        try:
            fcntl.flock(self._lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self._lock.close()
            self._lock = None
            raise OutputError(f"{self.path}: another bodyspace run is computing these rows now; wait for it to "
                              "finish") from None
        removed = self._remove_interrupted_others()
        state = None
        try:
            state = json.loads(self.state_path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            pass
        if (state is not None and state.get("key") == self.key and self.path.is_file()
                and npy_layout(self.path)[:2] == (self.shape, self.dtype) and 0 < int(state.get("done", 0))):
            self.rows = RowFile(self.path)
            done = min(int(state["done"]), self.shape[0])
            return done, state.get("extra", {}), (f"resumed an interrupted run from its last complete chunk: {done} "
                                                  f"of {self.shape[0]} rows were already computed ({self.path})")
        self.rows = RowFile.create(self.path, self.shape, self.dtype)
        self.state_path.unlink(missing_ok=True)
        return 0, {}, "started cleanly" + (f" (removed an interrupted run of other inputs: {removed[0]})"
                                           if removed else "")

    def commit(self, done: int, extra: dict | None = None) -> None:
        """Rows ``0..done`` are complete: sync them, then record it (atomically)."""
        fd = os.open(self.path, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        tmp = self.state_path.with_name(self.state_path.name + f".{os.getpid()}.tmp")
        tmp.write_text(json.dumps({"key": self.key, "done": int(done), "extra": extra or {}}), encoding="utf-8")
        os.replace(tmp, self.state_path)

    def close(self, remove: bool) -> None:
        """Release the lock; ``remove`` the files (the work is done) or keep them to resume."""
        if remove:
            for path in (self.path, self.state_path):
                path.unlink(missing_ok=True)
        if self._lock is not None:
            if remove:
                self.lock_path.unlink(missing_ok=True)
            fcntl.flock(self._lock, fcntl.LOCK_UN)
            self._lock.close()
            self._lock = None

    def _remove_interrupted_others(self) -> list[Path]:
        """Files of this NAME with another KEY whose lock nobody holds; returns the rows removed."""
        removed = []
        for lock_path in self.folder.glob(f".{self.name}-*.lock"):
            if lock_path == self.lock_path:
                continue
            try:
                handle = open(lock_path, "r+")
            except OSError:
                continue
            with handle:
                try:
                    fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except OSError:
                    continue  # a run is working on it
                for path in (lock_path.with_suffix(".npy"), lock_path.with_suffix(".json")):
                    if path.exists():
                        path.unlink()
                        if path.suffix == ".npy":
                            removed.append(path)
                lock_path.unlink(missing_ok=True)
        return removed
