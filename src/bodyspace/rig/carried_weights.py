"""The skin weights a landmark file of ``bodyspace landmarks`` carries, read for a rig.

``register.landmarks`` writes them (``skin_weights``: the template's MakeHuman weights carried to
a mesh of another topology); ``bodyspace rig MESH --weights FILE`` skins the mesh with them. The
reader lives here, beside the rigs, so a command that skins does not import the registration.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from bodyspace.data.template import Rig
from bodyspace.errors import RigError

__all__ = ["load_carried_weights"]


def load_carried_weights(path: str | os.PathLike, n_vertices: int, rig: Rig, flag: str = "--weights") -> sp.csr_matrix:
    """The skin weights (V2, B) of ``rig`` a landmark file of ``bodyspace landmarks`` carries
    (its ``skin_weights``), for a mesh of ``n_vertices``; rows renormalised to sum to 1."""
    path = Path(path)
    made = "a landmark file written by bodyspace landmarks MESH (it carries the template's skin weights)"
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise RigError(f"{flag} {path}: could not read it as JSON ({exc}); expected {made}") from None
    sw = d.get("skin_weights") if isinstance(d, dict) else None
    if not isinstance(sw, dict):
        raise RigError(f"{flag} {path}: has no 'skin_weights' field; expected {made}")
    if sw.get("rig") != rig.name:
        raise RigError(f"{flag} {path}: its skin weights are of rig {sw.get('rig')!r}, not {rig.name!r}; pass "
                       f"--rig {sw.get('rig')} or carry the weights again")
    try:
        bones = [str(b) for b in sw["bones"]]
        ids = np.asarray(sw["bone_ids"], dtype=np.int64)
        w = np.asarray(sw["weights"], dtype=float)
    except (KeyError, TypeError, ValueError) as exc:
        raise RigError(f"{flag} {path}: field 'skin_weights' lacks or garbles {exc}; expected {made}") from None
    if ids.ndim != 2 or ids.shape != w.shape or len(ids) != n_vertices:
        raise RigError(f"{flag} {path}: skin weights of shape {ids.shape} / {w.shape}; expected ({n_vertices}, k) "
                       "for this mesh's vertices (the file is for another mesh?)")
    if ids.size and (ids.min() < 0 or ids.max() >= len(bones)) or not np.isfinite(w).all() or (w < 0).any():
        raise RigError(f"{flag} {path}: skin weights with bone ids outside 0..{len(bones) - 1}, or negative or "
                       "non-finite weights; expected " + made)
    index = {b: i for i, b in enumerate(rig.bone_names)}
    unknown = sorted(set(bones) - set(index))
    if unknown:
        raise RigError(f"{flag} {path}: bones {', '.join(unknown[:5])} are not in rig {rig.name}")
    cols = np.array([index[b] for b in bones], dtype=np.int64)[ids]
    total = w.sum(axis=1, keepdims=True)
    if (total <= 0).any():
        raise RigError(f"{flag} {path}: {int((total <= 0).sum())} vertices have no weight; expected every vertex "
                       "weighted (re-run bodyspace landmarks)")
    w = w / total
    rows = np.repeat(np.arange(n_vertices), ids.shape[1])
    m = sp.csr_matrix((w.ravel(), (rows, cols.ravel())), shape=(n_vertices, rig.n_bones))
    m.sum_duplicates()
    return m
