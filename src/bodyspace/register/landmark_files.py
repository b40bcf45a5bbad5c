"""Landmark files of a raw scan: ``--landmarks FILE`` of ``bodyspace register`` and the sidecar
files of ``bodyspace import --register``.

Two formats, told by the suffix:

- ``.json``: ``{"landmarks": {name: [x, y, z], ...}}``, names of the measurement set
  (``head_top``, ``crotch``, ``knee_joint_l``, ...);
- ``.lnd``: a CAESAR landmark file (``register.caesar``), its names mapped to the measurement
  set's.

Points are in the scan file's own frame and units (what ``--units`` and ``--up`` say of the
scan applies to them too).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from bodyspace.errors import RegistrationError
from bodyspace.register.caesar import caesar_to_bodyspace, read_lnd

__all__ = ["read_scan_landmarks", "LANDMARK_SUFFIXES", "sidecar_landmarks"]

LANDMARK_SUFFIXES = (".json", ".lnd")
# Sidecar names tried beside a scan ``NAME.ply`` by ``sidecar_landmarks``, in this order.
SIDECARS = ("{stem}.lnd", "{stem}.landmarks.json")


def _read_json(path: Path, flag: str) -> dict[str, np.ndarray]:
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise RegistrationError(f"{flag} {path}: could not read it as JSON ({exc}); expected "
                                "{\"landmarks\": {name: [x, y, z], ...}} in the scan's units") from None
    raw = d.get("landmarks", d) if isinstance(d, dict) else None
    if not isinstance(raw, dict) or not raw:
        raise RegistrationError(f"{flag} {path}: expected {{\"landmarks\": {{name: [x, y, z], ...}}}} in the "
                                "scan's frame and units")
    out = {}
    for name, v in raw.items():
        a = np.asarray(v, dtype=float) if isinstance(v, list) else None
        if a is None or a.shape != (3,) or not np.isfinite(a).all():
            raise RegistrationError(f"{flag} {path}: landmark {name!r} is {v!r}; expected [x, y, z] (three "
                                    "numbers in the scan's units)")
        out[str(name)] = a
    return out


def read_scan_landmarks(path: str | os.PathLike, flag: str = "--landmarks") -> tuple[dict[str, np.ndarray], list[str]]:
    """Landmarks name → (3,) (the measurement set's names) of a ``.json`` or ``.lnd`` file, and
    notes for the user (what a CAESAR file gave). ``flag`` names the option in messages."""
    path = Path(path)
    if path.suffix.lower() != ".lnd":
        return _read_json(path, flag), []
    caesar, notes = read_lnd(path)
    ours = caesar_to_bodyspace(caesar)
    if len(ours) < 3:
        raise RegistrationError(f"{flag} {path}: its {len(caesar)} CAESAR landmark(s) give {len(ours)} of the "
                                "measurement set's; expected at least 3 (Crotch, Cervicale, Suprasternale, "
                                "Lt./Rt. Acromion, the epicondyles, malleoli or styloids: docs/registration.md)")
    notes = [f"{path}: {n}" for n in notes]
    notes.append(f"{path}: {len(caesar)} CAESAR landmarks read, used as {len(ours)}: {', '.join(ours)}")
    return ours, notes


def sidecar_landmarks(scan: str | os.PathLike) -> Path | None:
    """The landmark file beside a scan (``NAME.lnd`` or ``NAME.landmarks.json``), or None."""
    scan = Path(scan)
    for pattern in SIDECARS:
        p = scan.with_name(pattern.format(stem=scan.stem))
        if p.is_file():
            return p
    return None
