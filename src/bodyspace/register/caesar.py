"""CAESAR-style ``.lnd`` landmark files, read for ``bodyspace register --landmarks``.

The CAESAR survey (Civilian American and European Surface Anthropometry Resource) ships each
scan with a text file of the 73 anthropometric landmarks placed on the subject before scanning.
The variant read here (the one in circulation with CAESAR's ``.ply`` scans):

```
... header lines ...
AUX =
  1   0   1   43.22   19.77  -38.43  522.00 Sellion
  2   0   1   ...                            Lt. Infraorbitale
...
END =
```

Between the ``AUX =`` and ``END =`` lines (every line when the file has no ``AUX =``), a line
is: numbers (an index, flags, a quality value), then the x, y, z of the landmark (the last three
numbers before the name), then its name. Coordinates are in the scan's own frame and units
(CAESAR: millimetres), so ``--units`` and ``--up`` apply to both. Names are CAESAR's ("Lt."
the subject's left), sometimes cut short in the files ("Lt. Acromio"): a name is taken for the
one CAESAR name it begins (at least 8 characters; hyphens, dots and spacing aside). "AUX LAND"
lines (auxiliary marks) are skipped.

``CAESAR_TO_BODYSPACE`` maps them to the measurement set's landmarks: surface points one to one
(acromion → shoulder, cervicale → neck_back, suprasternale → neck_front, thelion → bust,
substernale → underbust_front, crotch), and the joint centres as the middle of the two bony
points either side of the joint (the epicondyles of the knee and elbow, the malleoli, the
radial and ulnar styloids). CAESAR has no head-top or hip-joint landmark. docs/registration.md.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from bodyspace.errors import RegistrationError

__all__ = ["read_lnd", "caesar_to_bodyspace", "CAESAR_NAMES", "CAESAR_TO_BODYSPACE"]

CAESAR_NAMES = (
    "10th Rib Midspine", "Cervicale", "Crotch", "Nuchale", "Sellion", "Substernale", "Supramenton",
    "Suprasternale", "Waist, Preferred, Post.",
    *(f"{side}. {name}" for side in ("Lt", "Rt") for name in (
        "10th Rib", "ASIS", "Acromion", "Axilla, Ant.", "Axilla, Post.", "Calcaneous, Post.", "Clavicale",
        "Dactylion", "Digit II", "Femoral Lateral Epicn", "Femoral Medial Epicn", "Gonion",
        "Humeral Lateral Epicn", "Humeral Medial Epicn", "Iliocristale", "Infraorbitale", "Knee Crease",
        "Lateral Malleolus", "Medial Malleolus", "Metacarpal-Phal. II", "Metacarpal-Phal. V",
        "Metatarsal-Phal. I", "Metatarsal-Phal. V", "Olecranon", "PSIS", "Radial Styloid", "Radiale", "Sphyrion",
        "Thelion/Bustpoint", "Tragion", "Trochanterion", "Ulnar Styloid")),
)

# bodyspace landmark → the CAESAR landmarks whose mean it is.
CAESAR_TO_BODYSPACE = {
    "crotch": ("Crotch",),
    "neck_front": ("Suprasternale",),
    "neck_back": ("Cervicale",),
    "underbust_front": ("Substernale",),
    **{f"{ours}_{s}": tuple(f"{side}. {n}" for n in names)
       for s, side in (("l", "Lt"), ("r", "Rt"))
       for ours, names in (("shoulder", ("Acromion",)), ("bust", ("Thelion/Bustpoint",)),
                           ("elbow_joint", ("Humeral Lateral Epicn", "Humeral Medial Epicn")),
                           ("wrist_joint", ("Radial Styloid", "Ulnar Styloid")),
                           ("knee_joint", ("Femoral Lateral Epicn", "Femoral Medial Epicn")),
                           ("ankle_joint", ("Lateral Malleolus", "Medial Malleolus")))},
}

_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"
# Leading numbers (any count), x y z, then a name that starts with a letter or digits and a letter
# ("10th Rib Midspine"), so a coordinate is never taken for the start of the name.
_LINE = re.compile(rf"^\s*((?:{_NUMBER}\s+)*?)({_NUMBER})\s+({_NUMBER})\s+({_NUMBER})\s+(?!{_NUMBER}(?:\s|$))(\d*[A-Za-z].*?)\s*$")
MIN_PREFIX = 8


def _key(name: str) -> str:
    """A name compared without case, hyphens, dots, commas or spacing."""
    return re.sub(r"[\s.,\-]+", "", name).lower()


_KEYS = {_key(n): n for n in CAESAR_NAMES}


def _canonical(name: str) -> str | None:
    k = _key(name)
    if k in _KEYS:
        return _KEYS[k]
    if len(k) >= MIN_PREFIX:
        hits = [full for key, full in _KEYS.items() if key.startswith(k)]
        if len(hits) == 1:
            return hits[0]
    return None


def read_lnd(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], list[str]]:
    """The landmarks of a CAESAR ``.lnd`` file (module docstring).

    Returns CAESAR name → (3,) point in the file's units and frame, and notes (names not
    recognised, skipped). Raises ``RegistrationError`` for an unreadable file or one without a
    landmark line.
    """
    path = Path(path)
    expected = ("a CAESAR .lnd file: lines 'index flags quality x y z name' between 'AUX =' and 'END =' "
                "(or a JSON {\"landmarks\": {name: [x, y, z]}})")
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise RegistrationError(f"--landmarks {path}: could not read it ({exc.strerror or exc}); expected "
                                f"{expected}") from None
    heads = [i for i, line in enumerate(lines) if re.match(r"^\s*AUX\s*=", line)]
    start = heads[0] + 1 if heads else 0
    out: dict[str, np.ndarray] = {}
    notes: list[str] = []
    for number, line in enumerate(lines[start:], start=start + 1):
        if re.match(r"^\s*END\s*=", line):
            break
        m = _LINE.match(line)
        if m is None:
            if heads and line.strip():
                notes.append(f"line {number}: {line.strip()[:60]!r} is not 'numbers x y z name': skipped")
            continue
        name = m.group(5)
        if name.upper().startswith("AUX"):
            continue
        point = np.array([float(m.group(k)) for k in (2, 3, 4)])
        full = _canonical(name)
        if full is None:
            notes.append(f"line {number}: {name!r} is no CAESAR landmark name: skipped")
            continue
        if not np.isfinite(point).all():
            raise RegistrationError(f"--landmarks {path} line {number}: {name!r} has coordinates {point.tolist()}; "
                                    "expected three finite numbers in the scan's units")
        out[full] = point
    if not out:
        raise RegistrationError(f"--landmarks {path}: no landmark line found; expected {expected}")
    return out, notes


def caesar_to_bodyspace(caesar: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The measurement set's landmarks (name → (3,)) that CAESAR landmarks give
    (``CAESAR_TO_BODYSPACE``): each the mean of its CAESAR points, when all of them are there."""
    return {ours: np.mean([caesar[n] for n in names], axis=0)
            for ours, names in CAESAR_TO_BODYSPACE.items() if all(n in caesar for n in names)}
