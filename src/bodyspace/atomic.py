"""Write files and folders so that an interrupted run leaves nothing half-written, and never
replace what bodyspace did not write.

* Everything goes to a temporary sibling ``.NAME.bodyspace-PID-TOKEN.part`` first and is renamed
  into place when complete (a rename within one file system is atomic on POSIX).
* A temporary sibling whose process ``PID`` is dead is the leftover of a killed run: the next
  write into the same folder removes it. Nothing else is ever removed.
* Files are created ``0o666 & ~umask`` and folders ``0o777 & ~umask``, like any other program's.
* Every folder bodyspace writes holds a marker file ``.bodyspace``:
  ``{"written_by": "bodyspace", "kind": KIND, "entries": [...]}``. An existing folder is replaced
  (``overwrite=True``, CLI ``--force``) only if it holds that marker, of the same kind, and
  nothing beside the entries bodyspace wrote there.
* Files carry their own signature (``is_own_file``): a model ``.npz`` its header with format
  ``bodyspace.*``, a PNG the text chunk ``Software=bodyspace``, an OBJ the first line
  ``# bodyspace ...``, a Markdown file the first line ``<!-- written by bodyspace -->``, a JSON
  file the top-level field ``"written_by": "bodyspace"``, a rigged GLB its asset generator
  ``bodyspace VERSION``, a GIF the comment ``written by bodyspace``.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import secrets
import shutil
import struct
import zipfile
from pathlib import Path
from typing import Iterator

from bodyspace.errors import OutputError

MARKER = ".bodyspace"
WRITTEN_BY = "bodyspace"
# What bodyspace writes into files so that it knows them again (see is_own_file).
PNG_METADATA = {"Software": WRITTEN_BY}
MARKDOWN_SIGNATURE = "<!-- written by bodyspace -->"
_PART = re.compile(r"^\..+\.bodyspace-(\d+)-[0-9a-f]{8}\.part$")
_swept: set[str] = set()


def _umask() -> int:
    """The process umask (read by setting and restoring it: POSIX has no getter)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    except OSError:
        return True
    return True


def temporary_name(path: Path) -> Path:
    """``.NAME.bodyspace-PID-TOKEN.part`` beside ``path``: unique, and known as ours by its pattern."""
    return path.with_name(f".{path.name}.bodyspace-{os.getpid()}-{secrets.token_hex(4)}.part")


def remove_leftovers(folder: str | os.PathLike) -> list[Path]:
    """Remove the temporary files and folders of killed bodyspace runs in ``folder`` (name
    pattern of ``temporary_name`` and a process id that is no longer running); returns them."""
    folder = Path(folder)
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        m = _PART.match(entry.name)
        if not m or _pid_alive(int(m.group(1))):
            continue
        p = Path(entry.path)
        try:
            if entry.is_dir(follow_symlinks=False):
                shutil.rmtree(p)
            else:
                p.unlink()
            removed.append(p)
        except OSError:
            pass
    return removed


def _sweep_once(folder: Path) -> None:
    """remove_leftovers(folder), once per process and folder (a crowd of 1,000 files scans once)."""
    key = str(folder.resolve())
    if key not in _swept:
        _swept.add(key)
        remove_leftovers(folder)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary file path beside ``path`` (created empty, permissions from the umask);
    rename it onto ``path`` on success, remove it on failure."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    _sweep_once(path.parent)
    tmp = temporary_name(path)
    os.close(os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def read_marker(folder: str | os.PathLike) -> dict | None:
    """The ``.bodyspace`` marker of ``folder`` (a dict), or None if it has none or a damaged one."""
    try:
        marker = json.loads((Path(folder) / MARKER).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(marker, dict) or marker.get("written_by") != WRITTEN_BY:
        return None
    return marker


def check_replaceable_folder(path: Path, kind: str, flag: str = "overwrite=True") -> None:
    """Raise OutputError unless the existing folder ``path`` is a bodyspace ``kind`` folder that
    holds nothing but what bodyspace wrote there. ``flag`` names the switch in the caller's words."""
    if not path.is_dir():
        raise OutputError(f"{path}: exists and is a file, expected a folder; {flag} replaces only folders "
                          "bodyspace wrote; choose another path")
    marker = read_marker(path)
    if marker is None:
        raise OutputError(f"{path}: exists and was not written by bodyspace (no {MARKER} marker); {flag} "
                          "never replaces other folders; remove it yourself or choose another path")
    if marker.get("kind") != kind:
        raise OutputError(f"{path}: is a bodyspace {marker.get('kind')!r} folder, not a {kind!r} folder; "
                          f"{flag} replaces only a folder of the same kind; choose another path")
    written = set(marker.get("entries") or [])
    foreign = sorted(e for e in os.listdir(path) if e != MARKER and e not in written)
    if foreign:
        raise OutputError(f"{path}: holds {len(foreign)} entr{'y' if len(foreign) == 1 else 'ies'} bodyspace "
                          f"did not write ({', '.join(foreign[:3])}{' ...' if len(foreign) > 3 else ''}); "
                          f"{flag} would delete them; move them away or choose another path")


@contextlib.contextmanager
def atomic_dir(path: str | os.PathLike, overwrite: bool = False, kind: str = "folder",
               flag: str = "overwrite=True") -> Iterator[Path]:
    """Yield a temporary folder beside ``path``; rename it onto ``path`` when the block ends.

    The folder gets the ``.bodyspace`` marker of ``kind`` listing what was written. An existing
    ``path`` is refused unless ``overwrite=True``, and then replaced (after the new folder is
    complete) only if ``check_replaceable_folder`` accepts it. ``flag`` names the switch in
    messages (the CLI passes ``--force``).
    """
    path = Path(path)
    if path.exists():
        if not overwrite:
            raise OutputError(f"{path}: already exists; pass {flag} to replace it")
        check_replaceable_folder(path, kind, flag)
    path.parent.mkdir(parents=True, exist_ok=True)
    _sweep_once(path.parent)
    tmp = temporary_name(path)
    os.mkdir(tmp, 0o777)
    try:
        yield tmp
        install_folder(tmp, path, kind, flag)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def install_folder(tmp: Path, path: Path, kind: str, flag: str = "overwrite=True") -> None:
    """Mark the complete folder ``tmp`` as a bodyspace ``kind`` folder listing its entries and
    rename it onto ``path``, replacing an existing ``path`` only if ``check_replaceable_folder``
    accepts it (the caller checked ``overwrite`` before the work)."""
    entries = sorted(e for e in os.listdir(tmp) if e != MARKER)
    marker = {"written_by": WRITTEN_BY, "kind": kind, "entries": entries}
    (tmp / MARKER).write_text(json.dumps(marker, indent=2) + "\n", encoding="utf-8")
    if path.exists():
        check_replaceable_folder(path, kind, flag)  # again: it may have changed while we worked
        old = temporary_name(path)
        os.replace(path, old)
        os.replace(tmp, path)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, path)


def write_json(path: str | os.PathLike, obj) -> None:
    """Write ``obj`` as indented JSON, atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=False) + "\n")


# ------------------------------------------------------------------ signatures of files
def _own_npz(path: Path) -> bool:
    try:
        with zipfile.ZipFile(path) as archive:
            head = archive.read("header.npy")
    except (OSError, KeyError, zipfile.BadZipFile, RuntimeError):
        return False
    return b'"format": "bodyspace.' in head


def _own_png(path: Path) -> bool:
    """A tEXt chunk Software=bodyspace before the image data."""
    with open(path, "rb") as fh:
        if fh.read(8) != b"\x89PNG\r\n\x1a\n":
            return False
        while True:
            head = fh.read(8)
            if len(head) < 8:
                return False
            length, ctype = struct.unpack(">I4s", head)
            if ctype in (b"IDAT", b"IEND"):
                return False
            data = fh.read(length)
            fh.read(4)
            if ctype == b"tEXt" and data.split(b"\0", 1) == [b"Software", WRITTEN_BY.encode()]:
                return True


def _first_line(path: Path) -> str:
    with open(path, "rb") as fh:
        return fh.readline(200).decode("utf-8", "replace").strip()


def _own_json(path: Path) -> bool:
    try:
        obj = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return False
    return isinstance(obj, dict) and obj.get("written_by") == WRITTEN_BY


def _own_glb(path: Path) -> bool:
    """A binary glTF whose JSON chunk says ``"asset": {"generator": "bodyspace ..."}`` (the rigged
    files of ``bodyspace.export.gltf``; plain meshes written through trimesh carry trimesh's)."""
    with open(path, "rb") as fh:
        head = fh.read(20)
        if len(head) < 20 or head[:4] != b"glTF":
            return False
        length, ctype = struct.unpack("<I4s", head[12:20])
        if ctype != b"JSON" or length > 1 << 26:
            return False
        try:
            doc = json.loads(fh.read(length).decode("utf-8"))
        except ValueError:
            return False
    generator = doc.get("asset", {}).get("generator", "") if isinstance(doc, dict) else ""
    return isinstance(generator, str) and generator.startswith(WRITTEN_BY + " ")


def _own_gif(path: Path) -> bool:
    """A GIF whose comment extension says ``written by bodyspace`` (before the image data)."""
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    return head[:4] == b"GIF8" and f"written by {WRITTEN_BY}".encode() in head


SIGNATURES = {
    ".npz": _own_npz,
    ".png": _own_png,
    ".obj": lambda p: _first_line(p).startswith("# bodyspace"),
    ".md": lambda p: _first_line(p) == MARKDOWN_SIGNATURE,
    ".json": _own_json,
    ".glb": _own_glb,
    ".gif": _own_gif,
}


def is_own_file(path: str | os.PathLike) -> bool:
    """True if the file ``path`` carries bodyspace's signature for its suffix (``SIGNATURES``);
    formats without one (PLY, CSV, a GLB written through trimesh ...) are never recognised."""
    path = Path(path)
    check = SIGNATURES.get(path.suffix.lower())
    if check is None or not path.is_file():
        return False
    try:
        return bool(check(path))
    except OSError:
        return False
