"""The template body: the body-only part of MakeHuman's hm08 base mesh, compiled once.

What we take from the CC0 assets and how (see docs/template.md):

- vertices: the ``body`` group, hm08 vertices 0..13379 (helper geometry, eyes, teeth, tongue
  and joint cubes dropped), scaled from MakeHuman decimetres to metres. +Y up, +Z front (the
  body faces +Z), the person's left at +X. The origin is MakeHuman's (near the pelvis).
- faces: each hm08 quad (a, b, c, d) becomes triangles (a, b, c) and (a, c, d), in file order,
  so triangle ``2k`` and ``2k+1`` come from quad ``k``.
- left/right/mid vertex groups and the mirror map (``mirror[i]`` is the vertex mirrored
  through x = 0).
- anchor points: everything the rigs and joints refer to that is not a body vertex (joint-cube
  centres, helper-geometry vertices, means of vertices) becomes a sparse row of a *regressor*
  over body vertices, fitted so that it reproduces the point under every MakeHuman target
  (joint positions as vertex averages, valid on any body of this topology).
- the CC0 rigs of ``rigs/standard`` with skin weights restricted to body vertices and
  renormalized.
- the macro targets as a dense (T, V, 3) float32 array of displacements (metres), each averaged
  with its mirror image (the files' 4-decimal rounding breaks symmetry by up to 3e-5 m); the
  rules that weigh them live in ``phenotype.py``.

Compiling takes a few seconds; the result is cached as ``.npz`` (no pickle) beside the assets.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import os
import warnings
import zipfile
import zlib
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
import scipy.optimize
import scipy.sparse as sp
from scipy.spatial import cKDTree

from bodyspace.atomic import atomic_path
from bodyspace.data import assets
from bodyspace.errors import AssetError, ParameterError

TEMPLATE_ID = "makehuman-hm08-body-v1"
N_BODY_VERTICES = 13380
DECIMETRE = 0.1  # MakeHuman's unit; we work in metres
COMPILED_VERSION = 5
RIG_NAMES = ("default", "default_no_toes", "game_engine", "cmu_mb", "mixamo", "game_engine_with_breast")
# Rigs MPFB2 ships without a weights file, and the rig whose weights theirs are derived from
# (``derive_weights``): default_no_toes is default with the 26 toe bones folded into one toe bone
# per foot (toe1-1, whose head moves back to the ball of the foot).
DERIVED_WEIGHTS = {"default_no_toes": "default"}
TARGET_FOLDERS = ("targets/macrodetails", "targets/breast")
# Regressor candidates: the nearest body vertices to an anchor, plus a few in each direction.
REGRESSOR_NEIGHBOURS = 32
REGRESSOR_PER_DIRECTION = 3


@dataclass(frozen=True)
class Rig:
    """A CC0 MakeHuman skeleton on the body-only template.

    Bone ``b``'s head and tail on a body with vertices (V, 3) are
    ``head_regressor[b] @ vertices`` and ``tail_regressor[b] @ vertices``.
    ``roll`` is Blender's bone roll (radians) as stored by MPFB2; ``weights`` is the (V, B)
    sparse skinning matrix whose rows sum to one.
    """

    name: str
    bone_names: tuple[str, ...]
    parents: np.ndarray  # (B,) int, -1 for a root
    head_regressor: sp.csr_matrix  # (B, V)
    tail_regressor: sp.csr_matrix  # (B, V)
    roll: np.ndarray  # (B,)
    weights: sp.csr_matrix  # (V, B)

    @property
    def n_bones(self) -> int:
        return len(self.bone_names)

    def bone_index(self, name: str) -> int:
        try:
            return self.bone_names.index(name)
        except ValueError:
            raise ParameterError(f"bone {name!r}: not a bone of rig {self.name!r}; expected one of "
                                 f"{', '.join(self.bone_names)}") from None

    def heads(self, vertices: np.ndarray) -> np.ndarray:
        """Bone heads (..., B, 3) of bodies (..., V, 3)."""
        return _apply_regressor(self.head_regressor, vertices)

    def tails(self, vertices: np.ndarray) -> np.ndarray:
        """Bone tails (..., B, 3) of bodies (..., V, 3)."""
        return _apply_regressor(self.tail_regressor, vertices)


@dataclass(frozen=True)
class Template:
    """The body-only hm08 template and everything later layers need from the assets."""

    vertices: np.ndarray  # (V, 3) float64, metres
    faces: np.ndarray  # (F, 3) int64
    left: np.ndarray  # vertex indices with x > 0 side (the person's left)
    right: np.ndarray
    mid: np.ndarray  # vertices on the symmetry plane
    mirror: np.ndarray  # (V,) int: mirror[i] is i reflected through x = 0
    joint_names: tuple[str, ...]  # hm08 joint cubes, e.g. "joint-l-knee"
    joint_regressor: sp.csr_matrix  # (J, V): joint-cube centres from body vertices
    target_names: tuple[str, ...]  # e.g. "macrodetails/universal-female-young-averagemuscle-averageweight"
    target_deltas: np.ndarray  # (T, V, 3) float32 displacements in metres
    rigs: dict[str, Rig] = field(default_factory=dict)
    vertex_groups: dict[str, np.ndarray] = field(default_factory=dict)  # hm08 named groups restricted to body
    template_id: str = TEMPLATE_ID

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)

    def joints(self, vertices: np.ndarray) -> np.ndarray:
        """Joint-cube centres (..., J, 3) of bodies (..., V, 3)."""
        return _apply_regressor(self.joint_regressor, vertices)

    def joint(self, vertices: np.ndarray, name: str) -> np.ndarray:
        """One joint-cube centre (..., 3) by hm08 name, e.g. ``"joint-l-knee"``."""
        try:
            j = self.joint_names.index(name)
        except ValueError:
            raise ParameterError(f"joint {name!r}: not a joint of the template; expected one of "
                                 f"{', '.join(self.joint_names)}") from None
        return self.joints(vertices)[..., j, :]


def _apply_regressor(reg: sp.csr_matrix, vertices: np.ndarray) -> np.ndarray:
    v = np.asarray(vertices, dtype=float)
    if v.ndim == 2:
        return reg @ v
    flat = v.transpose(1, 0, 2).reshape(v.shape[-2], -1)  # (V, N*3)
    return (reg @ flat).reshape(reg.shape[0], v.shape[0], 3).transpose(1, 0, 2)


# ----------------------------------------------------------------------------------------------
# Parsing the CC0 files


def parse_obj(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """hm08 ``base.obj``: vertices (19158, 3) in decimetres and quad faces per group."""
    verts, groups, current = [], {}, None
    with open(path) as f:
        for line in f:
            if line.startswith("v "):
                verts.append(line.split()[1:4])
            elif line.startswith("g "):
                current = line.split()[1]
                groups.setdefault(current, [])
            elif line.startswith("f "):
                groups[current].append([int(t.split("/")[0]) - 1 for t in line.split()[1:]])
    return np.array(verts, dtype=float), {g: np.array(f, dtype=np.int64) for g, f in groups.items() if f}


# How to mend a damaged asset file, in the words of every interface.
_REFETCH = ("; fetch the verified assets again (`bodyspace assets --fetch`) or point --assets (BODYSPACE_ASSETS) "
            "at a complete MakeHuman/MPFB2 folder")


def load_target(path: Path, n_vertices: int) -> np.ndarray:
    """A MakeHuman ``.target.gz``: rows ``index dx dy dz`` (decimetres) → dense (n_vertices, 3) metres.

    The numbers are parsed in one pass of numpy's C text reader (the 576 targets of the template
    are 5.4 million lines: a split per line in Python took 15 s of the template's compilation);
    a row that is not four numbers is refused (AssetError), never read as a shifted one.
    """
    with gzip.open(path, "rb") as f:
        text = f.read().decode("utf-8")
    rows = [line for line in text.splitlines() if line.strip() and not line.startswith("#")]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", DeprecationWarning)   # older numpy warns where 2.x raises
            values = np.fromstring("\n".join(rows), sep=" ") if rows else np.zeros(0)
    except (ValueError, DeprecationWarning) as exc:
        raise AssetError(f"{path}: a row is not numbers ({exc}); expected rows 'index dx dy dz' of a MakeHuman "
                         f"target{_REFETCH}") from None
    if values.size != 4 * len(rows):
        raise AssetError(f"{path}: {values.size} numbers on {len(rows)} rows; expected 4 a row (index dx dy dz) "
                         f"of a MakeHuman target{_REFETCH}")
    data = values.reshape(-1, 4)
    out = np.zeros((n_vertices, 3))
    idx = data[:, 0].astype(np.int64)
    keep = idx < n_vertices
    out[idx[keep]] = data[keep, 1:] * DECIMETRE
    return out


def _ranges_to_indices(ranges) -> np.ndarray:
    if not ranges:
        return np.zeros(0, dtype=np.int64)
    return np.concatenate([np.arange(a, b + 1) for a, b in ranges]).astype(np.int64)


def triangulate_quads(quads: np.ndarray) -> np.ndarray:
    """Quads (Q, 4) → triangles (2Q, 3): (a, b, c) then (a, c, d) for each quad, in order."""
    tris = np.empty((2 * len(quads), 3), dtype=np.int64)
    tris[0::2] = quads[:, [0, 1, 2]]
    tris[1::2] = quads[:, [0, 2, 3]]
    return tris


def _surrounding_vertices(point: np.ndarray, vertices: np.ndarray, tree: cKDTree) -> np.ndarray:
    """Candidate body vertices around ``point``: its nearest ones plus the nearest few in each
    of 26 directions, so a point deep inside the body (a spine joint) is bracketed from all
    sides instead of regressed from the one patch of skin that happens to be closest."""
    _, near = tree.query(point, k=REGRESSOR_NEIGHBOURS)
    d = vertices - point
    dist = np.linalg.norm(d, axis=1)
    unit = d / np.maximum(dist, 1e-12)[:, None]
    dirs = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) != (0, 0, 0)], float)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    cone = unit @ dirs.T > 0.85  # (V, 26)
    picks = [near]
    for c in cone.T:
        idx = np.flatnonzero(c)
        picks.append(idx[np.argsort(dist[idx])[:REGRESSOR_PER_DIRECTION]])
    return np.unique(np.concatenate(picks))


def fit_point_regressor(points: np.ndarray, body: np.ndarray) -> sp.csr_matrix:
    """Sparse convex weights over body vertices that reproduce anchor points on every sample.

    points: (S, P, 3) anchor points on S deformed meshes (the base mesh and base + each target).
    body: (S, V, 3) body vertices of the same meshes.
    Returns (P, V) with non-negative rows summing to one (so the regressor commutes with
    translation), fitted by NNLS on candidate vertices that surround each point.
    """
    S, P, _ = points.shape
    tree = cKDTree(body[0])
    rows, cols, vals = [], [], []
    for p in range(P):
        cand = _surrounding_vertices(points[0, p], body[0], tree)
        # Offsets from the anchor on each sample: sum_k w_k (x_k - p) = 0 with sum_k w_k = 1.
        A = (body[:, cand, :] - points[:, p, None, :]).transpose(0, 2, 1).reshape(S * 3, len(cand))
        A = np.vstack([A, np.ones((1, len(cand)))])
        b = np.zeros(S * 3 + 1)
        b[-1] = 1.0
        w, _ = scipy.optimize.nnls(A, b, maxiter=50 * len(cand))
        keep = w > 1e-6 * w.max()
        rows.extend([p] * int(keep.sum()))
        cols.extend(cand[keep])
        vals.extend(w[keep] / w[keep].sum())
    return sp.csr_matrix((vals, (rows, cols)), shape=(P, body.shape[1]))


def _bone_stem(name: str) -> tuple[str, str]:
    """A bone name's family and side: ``"toe2-3.L"`` -> ``("toe", ".L")``, ``"spine03"`` -> ``("spine", "")``."""
    side = name[-2:] if name[-2:] in (".L", ".R") else ""
    base = name[: len(name) - len(side)]
    return base.rstrip("0123456789-_"), side


def derive_weights(source_bones: list[str], source_weights: sp.spmatrix, target_bones: list[str]) -> sp.csr_matrix:
    """Skin weights (V, B_target) of a rig whose bones are a subset of another rig's.

    A bone of the target keeps its weights; a bone the target lacks hands its weights to the
    target bone of the same family and side (``toe2-3.L`` -> ``toe1-1.L``, the one toe bone of
    ``default_no_toes``: the toes bend together), the first such bone in the target's order.
    Rows still sum to one (weights are moved, never dropped). Raises AssetError when a dropped
    bone has no family member in the target.
    """
    index = {b: i for i, b in enumerate(target_bones)}
    family: dict[tuple[str, str], int] = {}
    for i, b in enumerate(target_bones):
        family.setdefault(_bone_stem(b), i)
    to = np.empty(len(source_bones), dtype=np.int64)
    for j, b in enumerate(source_bones):
        if b in index:
            to[j] = index[b]
        elif _bone_stem(b) in family:
            to[j] = family[_bone_stem(b)]
        else:
            raise AssetError(f"deriving weights: bone {b!r} of the source rig has no counterpart among the target's "
                             f"{len(target_bones)} bones; expected the target to keep a bone of its family")
    W = sp.coo_matrix(source_weights)
    out = sp.csr_matrix((W.data, (W.row, to[W.col])), shape=(W.shape[0], len(target_bones)))
    out.sum_duplicates()
    return out


def _compile(root: Path) -> dict[str, np.ndarray]:
    """Read the CC0 files under ``root`` and build every array the Template needs."""
    full, groups = parse_obj(root / "3dobjs/base.obj")
    n_full = len(full)
    if "body" not in groups:
        raise AssetError(f"{root / '3dobjs/base.obj'}: no 'body' group; expected the hm08 base mesh")
    body_quads = groups["body"]
    if body_quads.max() >= N_BODY_VERTICES or body_quads.shape[1] != 4:
        raise AssetError(f"{root / '3dobjs/base.obj'}: body group is not quads on vertices "
                         f"0..{N_BODY_VERTICES - 1}; expected hm08")
    faces = triangulate_quads(body_quads)

    # Targets over the full hm08 vertex set (anchors live on helper geometry too).
    target_paths = []
    for folder in TARGET_FOLDERS:
        target_paths += sorted((root / folder).rglob("*.target.gz"))
    names = [str(p.relative_to(root / "targets")).removesuffix(".target.gz") for p in target_paths]
    deltas_full = np.stack([load_target(p, n_full) for p in target_paths])  # (T, Vfull, 3) metres
    base_full = full * DECIMETRE

    vgroups = json.loads((root / "mesh_metadata/basemesh_vertex_groups.json").read_text())
    named = {g: _ranges_to_indices(r) for g, r in vgroups.items()}
    joint_names = sorted(g for g in named if g.startswith("joint-"))

    # Anchor points: joint-cube centres, then every rig head/tail as a list of full-mesh vertices.
    anchors: list[np.ndarray] = [named[j] for j in joint_names]
    rig_specs = {}
    for rig in RIG_NAMES:
        rig_path = root / f"rigs/standard/rig.{rig}.json"
        w_path = root / f"rigs/standard/weights.{rig}.json"
        if not (rig_path.is_file() and (w_path.is_file() or rig in DERIVED_WEIGHTS)):
            continue
        bones = json.loads(rig_path.read_text())
        bones = bones.get("bones", bones)
        spec = {"bones": list(bones), "parents": [], "head": [], "tail": [], "roll": []}
        for b, info in bones.items():
            spec["parents"].append(list(bones).index(info["parent"]) if info.get("parent") else -1)
            spec["roll"].append(float(info.get("roll", 0.0)))
            for end in ("head", "tail"):
                s = info[end]
                if s["strategy"] == "CUBE":
                    idx = named[s["cube_name"]]
                elif s["strategy"] == "VERTEX":
                    idx = np.array([s["vertex_index"]])
                elif s["strategy"] == "MEAN":
                    idx = np.array(s["vertex_indices"])
                else:
                    raise AssetError(f"{rig_path}: bone {b} {end} has strategy {s['strategy']!r}; "
                                     "expected CUBE, VERTEX or MEAN")
                spec[end].append(len(anchors))
                anchors.append(np.asarray(idx, dtype=np.int64))
        source = DERIVED_WEIGHTS.get(rig)
        if not w_path.is_file() and source is not None:
            if source not in rig_specs:
                continue
            spec["weights"] = derive_weights(rig_specs[source]["bones"], rig_specs[source]["weights"],
                                             spec["bones"])
            rig_specs[rig] = spec
            continue
        weights = json.loads(w_path.read_text())["weights"]
        r, c, v = [], [], []
        for bi, b in enumerate(spec["bones"]):
            pairs = np.asarray(weights.get(b, []), dtype=float).reshape(-1, 2)
            keep = pairs[:, 0] < N_BODY_VERTICES
            r.append(pairs[keep, 0].astype(np.int64))
            c.append(np.full(int(keep.sum()), bi))
            v.append(pairs[keep, 1])
        W = sp.csr_matrix((np.concatenate(v), (np.concatenate(r), np.concatenate(c))),
                          shape=(N_BODY_VERTICES, len(spec["bones"])))
        total = np.asarray(W.sum(axis=1)).ravel()
        if (total <= 0).any():
            raise AssetError(f"{w_path}: {int((total <= 0).sum())} body vertices have no skin weight")
        spec["weights"] = sp.diags(1.0 / total) @ W
        rig_specs[rig] = spec

    # Anchor positions on the base mesh and on base + each target, then one regressor for all.
    # Unique anchors are fitted once (the rigs share many cube centres).
    keys = [tuple(a.tolist()) for a in anchors]
    unique = {k: i for i, k in enumerate(dict.fromkeys(keys))}
    uniq_idx = list(unique)

    def anchor_positions(mesh_full: np.ndarray) -> np.ndarray:
        return np.stack([mesh_full[..., list(k), :].mean(axis=-2) for k in uniq_idx], axis=-2)

    samples_full = np.concatenate([base_full[None], base_full[None] + deltas_full])  # (S, Vfull, 3)
    reg_unique = fit_point_regressor(anchor_positions(samples_full), samples_full[:, :N_BODY_VERTICES])
    rows = np.array([unique[k] for k in keys])
    reg_all = reg_unique[rows]

    mirror = np.arange(N_BODY_VERTICES)
    for line in (root / "mesh_metadata/hm08.mirror").read_text().split("\n"):
        parts = line.split()
        if len(parts) >= 2 and int(parts[0]) < N_BODY_VERTICES and int(parts[1]) < N_BODY_VERTICES:
            mirror[int(parts[0])] = int(parts[1])

    # MakeHuman's macro targets are symmetric by design but stored with 4 decimals, which leaves
    # left/right differences up to ~3e-5 m. Averaging each target with its mirror image makes a
    # symmetric phenotype exactly symmetric (the base mesh already is).
    body_deltas = deltas_full[:, :N_BODY_VERTICES]
    body_deltas = 0.5 * (body_deltas + body_deltas[:, mirror] * np.array([-1.0, 1.0, 1.0]))

    body_groups = {g: idx[idx < N_BODY_VERTICES] for g, idx in named.items()}
    out: dict[str, np.ndarray] = {
        "version": np.array(COMPILED_VERSION),
        "vertices": base_full[:N_BODY_VERTICES],
        "faces": faces,
        "mirror": mirror,
        "joint_names": np.array(joint_names),
        "target_names": np.array(names),
        "target_deltas": body_deltas.astype(np.float32),
        "group_names": np.array(list(body_groups)),
        "rig_names": np.array(list(rig_specs)),
    }
    for g, idx in body_groups.items():
        out[f"group/{g}"] = idx
    _put_sparse(out, "joint_regressor", reg_all[: len(joint_names)])
    for rig, spec in rig_specs.items():
        out[f"rig/{rig}/bones"] = np.array(spec["bones"])
        out[f"rig/{rig}/parents"] = np.array(spec["parents"])
        out[f"rig/{rig}/roll"] = np.array(spec["roll"])
        _put_sparse(out, f"rig/{rig}/head", reg_all[spec["head"]])
        _put_sparse(out, f"rig/{rig}/tail", reg_all[spec["tail"]])
        _put_sparse(out, f"rig/{rig}/weights", spec["weights"])
    return out


def _put_sparse(out: dict, key: str, m: sp.spmatrix) -> None:
    m = sp.csr_matrix(m)
    out[f"{key}/data"], out[f"{key}/indices"], out[f"{key}/indptr"] = m.data, m.indices, m.indptr
    out[f"{key}/shape"] = np.array(m.shape)


def _get_sparse(z, key: str) -> sp.csr_matrix:
    return sp.csr_matrix((z[f"{key}/data"], z[f"{key}/indices"], z[f"{key}/indptr"]),
                         shape=tuple(z[f"{key}/shape"]))


def _compiled_path(root: Path) -> Path:
    """Where the compiled template for an asset folder is cached (keyed by folder and content)."""
    manifest = root / "MANIFEST.json"
    stamp = manifest.read_text() if manifest.is_file() else str(
        [(p, (root / p).stat().st_mtime_ns) for p in assets.REQUIRED_FILES])
    key = hashlib.sha256(f"{root.resolve()}|{stamp}|{COMPILED_VERSION}".encode()).hexdigest()[:16]
    return assets.cache_dir() / "compiled" / f"template-{key}.npz"


# What a damaged cache file raises when it is opened or an array of it is read: a truncated
# zip (BadZipFile, EOFError, OSError), a garbled member (ValueError from numpy's header parser,
# zlib.error from a bad deflate stream), a missing array (KeyError).
_DAMAGED_CACHE_ERRORS = (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile, zlib.error)


@lru_cache(maxsize=4)
def _load_compiled(root: Path) -> Template:
    """The compiled template of ``root``: read from the cache, compiled (again) when the cache
    file is missing, damaged (a run killed while copying it, a full disk) or of another version.

    The cache is ours and derived only from the assets, so a bad one is rebuilt rather than
    reported: it would otherwise fail on every later run.
    """
    path = _compiled_path(root)
    if path.is_file():
        try:
            return read_compiled(path)
        except (AssetError, *_DAMAGED_CACHE_ERRORS):
            pass  # rebuilt below, written over the damaged file
    try:
        arrays = _compile(root)
    except AssetError:
        raise
    except (OSError, EOFError, ValueError, KeyError, IndexError, TypeError, AttributeError) as exc:
        # A user's MPFB2-style folder holds every required file, but one of them is not what
        # MakeHuman writes (a truncated target, a JSON file of another layout...).
        raise AssetError(f"{root}: the MakeHuman files do not compile into the template ({type(exc).__name__}: "
                         f"{exc}); expected the hm08 files of MakeHuman/MPFB2. Point --assets (or "
                         "BODYSPACE_ASSETS) at a complete folder, or unset it to use the verified cache "
                         "(`bodyspace assets --fetch`)") from exc
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
    try:
        return read_compiled(path)
    except _DAMAGED_CACHE_ERRORS as exc:
        raise AssetError(f"{path}: the compiled template just written cannot be read back ({exc}); "
                         f"check the free space and permissions of {path.parent}") from exc


def read_compiled(path: Path) -> Template:
    """A compiled template ``.npz`` (written by ``_compile``) -> Template.

    Raises AssetError for another ``COMPILED_VERSION``; a truncated or garbled file raises one of
    ``_DAMAGED_CACHE_ERRORS`` (the caller rebuilds it).
    """
    with np.load(path, allow_pickle=False) as z:
        version = z["version"]
        if version.shape != () or version.dtype.kind not in "iu" or int(version) != COMPILED_VERSION:
            raise AssetError(f"{path}: compiled template version {version!r}, expected {COMPILED_VERSION}")
        groups = {str(g): z[f"group/{g}"] for g in z["group_names"]}
        rigs = {}
        for rig in map(str, z["rig_names"]):
            rigs[rig] = Rig(rig, tuple(map(str, z[f"rig/{rig}/bones"])), z[f"rig/{rig}/parents"],
                            _get_sparse(z, f"rig/{rig}/head"), _get_sparse(z, f"rig/{rig}/tail"),
                            z[f"rig/{rig}/roll"], _get_sparse(z, f"rig/{rig}/weights"))
        template = Template(
            vertices=z["vertices"], faces=z["faces"], left=groups["Left"], right=groups["Right"],
            mid=groups["Mid"], mirror=z["mirror"], joint_names=tuple(map(str, z["joint_names"])),
            joint_regressor=_get_sparse(z, "joint_regressor"),
            target_names=tuple(map(str, z["target_names"])), target_deltas=z["target_deltas"],
            rigs=rigs, vertex_groups=groups)
    if template.vertices.shape != (N_BODY_VERTICES, 3) or template.target_deltas.shape[1:] != (N_BODY_VERTICES, 3):
        raise AssetError(f"{path}: compiled template holds vertices {template.vertices.shape} and targets "
                         f"{template.target_deltas.shape}, expected ({N_BODY_VERTICES}, 3) and (T, {N_BODY_VERTICES}, 3)")
    return template


def load_template(assets_root: str | os.PathLike | None = None) -> Template:
    """The compiled template for the asset folder (fetched and compiled on first use)."""
    root = assets.asset_root(assets_root).resolve()
    return _load_compiled(root)
