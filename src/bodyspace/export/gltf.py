"""Rigged glTF 2.0 (``.glb``): a skinned body mesh with its skeleton and optional morph targets.

``gltf_bytes(vertices, faces, skeleton, weights, morphs=...)`` takes any body: the template
topology with a CC0 rig (``rig.skeleton.body_skeleton``) or any other mesh with a skeleton and
weights from elsewhere (skeleton embedding, bone heat). What the file holds:

- one mesh, one primitive: POSITION (float32, metres, +Y up, +Z front: glTF's axes are ours),
  NORMAL (area-weighted vertex normals), indices (uint16 below 65,535 vertices, else uint32),
  JOINTS_0 / WEIGHTS_0: the 4 largest influences per vertex, a dropped bone's weight given to
  the kept bone nearest to it in the skeleton (``top_influences``; what dropping costs is
  measured in docs/export.md);
- a skin: the bones as joint nodes under one armature node named after the rig, in the rig's
  bone order, each node's local transform its bone's rest frame relative to its parent's
  (``Skeleton.bind_matrices``: rotation = Blender's bone frame, local +Y from head to tail,
  so Blender's importer rebuilds the bone axes and rolls), inverse bind matrices = the inverses
  of the rest frames: **the bind pose is the rest pose** (every joint at its rest transform
  gives the exported vertices back);
- ``extras`` of every joint node: ``head``, ``tail`` (metres, glTF axes), ``roll`` (Blender
  radians), ``length``; of the mesh: ``targetNames`` (Blender and three.js name shape keys /
  morph targets from it) and what each morph means;
- morph targets (optional): POSITION and NORMAL displacements, all weights 0 by default;
- a plain skin material (PBR, not metallic, rough);
- an animation (optional, ``SkeletonAnimation``): one rotation channel per joint and a
  translation channel per root joint (the root motion), linear interpolation, one shared time
  accessor; quaternions made sign-continuous frame to frame so interpolation takes the short way.

pygltflib (MIT) writes the JSON and the GLB container; the binary buffer is laid out here,
every view 4-byte aligned.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import pygltflib
import scipy.sparse as sp
from scipy.sparse.csgraph import shortest_path

from bodyspace import __version__
from bodyspace.atomic import atomic_path
from bodyspace.errors import MeshError, ParameterError
from bodyspace.mesh.geometry import check_mesh, vertex_normals
from bodyspace.rig.kinematics import matrix_to_quaternion
from bodyspace.rig.skeleton import Skeleton

__all__ = ["MorphTarget", "SkeletonAnimation", "continuous_quaternions", "gltf_bytes", "write_gltf", "top_influences",
           "influences_matrix", "bone_distances", "joint_local_transforms", "unit_vertex_normals", "GENERATOR",
           "SKIN_COLOR", "MAX_INFLUENCES"]

GENERATOR = f"bodyspace {__version__}"
MAX_INFLUENCES = 4          # glTF's JOINTS_0 / WEIGHTS_0 hold four per vertex
SKIN_COLOR = (0.80, 0.62, 0.52, 1.0)  # linear RGBA base colour of the plain skin material
# A body is between these heights in metres: anything else is probably millimetres, centimetres
# or not a body at all, and glTF files are in metres.
_PLAUSIBLE_SIZE_M = (0.3, 3.0)

_FLOAT, _USHORT, _UBYTE, _UINT = 5126, 5123, 5121, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


@dataclass(frozen=True)
class MorphTarget:
    """A shape key: per-vertex displacements (V, 3) in metres added at weight 1.

    name: what an artist sees (Blender's shape key, three.js's ``morphTargetDictionary``), e.g.
    ``"stature +10 cm"``; meaning: JSON-able facts stored in the mesh's extras (the variable,
    its change in SI units, how the displacement was made and how exact it is).
    """

    name: str
    deltas: np.ndarray
    meaning: dict = field(default_factory=dict)


@dataclass(frozen=True)
class SkeletonAnimation:
    """A skeletal animation: ``transforms`` (F, B, 4, 4) posed bone transforms per frame in our
    convention (``rig.kinematics.forward_kinematics``, root motion included), ``frame_time``
    seconds between frames, ``name`` of the glTF animation."""

    transforms: np.ndarray
    frame_time: float
    name: str = "motion"


def continuous_quaternions(q: np.ndarray) -> np.ndarray:
    """Quaternions (F, ..., 4) with each frame's sign flipped to the hemisphere of the previous
    frame's (``q`` and ``-q`` are one rotation; interpolating across a flip turns the long way)."""
    q = np.array(q, dtype=float)
    for f in range(1, len(q)):
        flip = np.einsum("...i,...i->...", q[f], q[f - 1]) < 0
        q[f][flip] *= -1.0
    return q


def unit_vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit vertex normals (V, 3) (``mesh.geometry.vertex_normals``), with +Y for a vertex no
    face uses (or whose faces have zero area), so every normal is unit length, as glTF requires."""
    n = vertex_normals(vertices, faces)
    n[np.linalg.norm(n, axis=1) < 0.5] = (0.0, 1.0, 0.0)
    return n


def bone_distances(parents: np.ndarray) -> np.ndarray:
    """(B, B) number of joints between two bones along the skeleton tree (0 on the diagonal;
    bones of different trees are infinitely far)."""
    parents = np.asarray(parents, dtype=np.int64)
    child = np.flatnonzero(parents >= 0)
    tree = sp.coo_matrix((np.ones(len(child)), (child, parents[child])), shape=(len(parents),) * 2)
    return shortest_path(tree, directed=False, unweighted=True)


def top_influences(weights: sp.spmatrix | np.ndarray, k: int = MAX_INFLUENCES,
                   parents: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` largest skin weights of each vertex: joints (V, k) int64, weights (V, k) summing to 1.

    weights: (V, B) non-negative, each row with a positive sum. Slots a vertex does not need
    hold joint 0 with weight 0. Ties keep the lower bone index.
    parents: (B,) the skeleton's parents. Given, the weight of each dropped bone goes to the kept
    bone nearest to it in the skeleton (``bone_distances``: its parent or child where kept, which
    moves most like it; the heavier one on a tie); otherwise the kept weights are renormalized.
    Measured over the pose library (docs/export.md) moving weights to kin lands closer to
    skinning with every influence (99th percentile 1.4 mm against 2.3 mm; the worst vertex,
    in the armpit with 7 or 8 influences, ~27 mm either way).
    The result as a sparse (V, B) matrix (for skinning with exactly what the file holds) is
    ``influences_matrix``.
    """
    W = sp.csr_matrix(weights, dtype=float)
    W.sum_duplicates()
    W.eliminate_zeros()
    V, B = W.shape
    if W.nnz and (W.data < 0).any():
        raise ParameterError("weights: negative skin weights, expected non-negative weights")
    if W.nnz and not np.isfinite(W.data).all():
        raise ParameterError("weights: NaN or infinite skin weights, expected finite weights")
    counts = np.diff(W.indptr)
    if (counts == 0).any():
        raise ParameterError(f"weights: vertex {int(np.flatnonzero(counts == 0)[0])} has no skin weight; expected "
                             "every vertex bound to at least one bone")
    m = max(int(counts.max()), k)
    pos = np.arange(W.nnz) - np.repeat(W.indptr[:-1], counts)            # slot within the row
    rows = np.repeat(np.arange(V), counts)
    val = np.full((V, m), -1.0)
    col = np.zeros((V, m), dtype=np.int64)
    val[rows, pos], col[rows, pos] = W.data, W.indices
    if parents is not None and m > k:
        if len(parents) != B:
            raise ParameterError(f"parents: {len(parents)} bones, expected {B} (the weights' columns)")
        many = np.flatnonzero(counts > k)
        by_size = np.lexsort((col[many], -val[many]), axis=1)
        v_many = np.take_along_axis(val[many], by_size, 1)
        c_many = np.take_along_axis(col[many], by_size, 1)
        D = bone_distances(parents)
        rows = np.arange(len(many))
        for s in range(k, m):
            dropped = v_many[:, s] > 0
            nearest = np.argmin(D[c_many[:, s][:, None], c_many[:, :k]], axis=1)   # first = heavier on ties
            v_many[rows[dropped], nearest[dropped]] += v_many[dropped, s]
        v_many[:, k:] = -1.0                                   # moved: never picked below
        val[many], col[many] = v_many, c_many
    # Largest first; among equal weights the lower bone (lexsort's last key is the primary one).
    order = np.lexsort((col, -val), axis=1)[:, :k]
    w = np.take_along_axis(val, order, 1)
    j = np.take_along_axis(col, order, 1)
    unused = w <= 0
    w[unused], j[unused] = 0.0, 0
    w /= w.sum(axis=1, keepdims=True)
    return j, w


def influences_matrix(joints: np.ndarray, weights: np.ndarray, n_bones: int) -> sp.csr_matrix:
    """(V, B) sparse skin weights from per-vertex joints and weights (V, k) (zeros dropped)."""
    V, k = joints.shape
    M = sp.csr_matrix((weights.ravel(), (np.repeat(np.arange(V), k), joints.ravel())), shape=(V, n_bones))
    M.sum_duplicates()
    M.eliminate_zeros()
    return M


def _unit_sum_float32(w: np.ndarray) -> np.ndarray:
    """float32 weights whose float32 row sums are 1 to the last bit the largest weight allows
    (the glTF validator checks the sum): the rounding is put on each row's largest weight."""
    w32 = w.astype(np.float32)
    big = np.argmax(w32, axis=1)
    rows = np.arange(len(w32))
    rest = w32.sum(axis=1, dtype=np.float32) - w32[rows, big]
    w32[rows, big] = np.float32(1.0) - rest
    return w32


class _Buffer:
    """The GLB binary chunk under construction: 4-byte aligned views and their accessors."""

    def __init__(self, gltf: pygltflib.GLTF2):
        self.gltf, self.parts, self.size = gltf, [], 0

    def add(self, array: np.ndarray, component: int, kind: str, target: int | None = None,
            minmax: bool = False, normalized: bool = False) -> int:
        data = np.ascontiguousarray(array).tobytes()
        view = pygltflib.BufferView(buffer=0, byteOffset=self.size, byteLength=len(data), target=target)
        self.gltf.bufferViews.append(view)
        self.parts.append(data)
        self.size += len(data)
        pad = -self.size % 4
        if pad:
            self.parts.append(b"\0" * pad)
            self.size += pad
        acc = pygltflib.Accessor(bufferView=len(self.gltf.bufferViews) - 1, byteOffset=0, componentType=component,
                                 count=len(array), type=kind, normalized=normalized or None)
        if minmax:
            a = np.asarray(array).reshape(len(array), -1)
            acc.min, acc.max = a.min(axis=0).tolist(), a.max(axis=0).tolist()
        self.gltf.accessors.append(acc)
        return len(self.gltf.accessors) - 1

    def blob(self) -> bytes:
        return b"".join(self.parts)


def _check_inputs(vertices, faces, skeleton, weights, morphs):
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces)
    if v.ndim != 2:
        raise MeshError(f"vertices: shape {v.shape}, expected (V, 3) for one body")
    check_mesh(v, f, "body")
    if len(f) == 0:
        raise MeshError("faces: none, expected a triangle mesh")
    size = float(np.ptp(v, axis=0).max())
    if not _PLAUSIBLE_SIZE_M[0] <= size <= _PLAUSIBLE_SIZE_M[1]:
        raise MeshError(f"vertices: the body is {size:g} units across, expected a body in metres "
                        f"({_PLAUSIBLE_SIZE_M[0]:g}-{_PLAUSIBLE_SIZE_M[1]:g} m; glTF is in metres): scale it "
                        "(millimetres x 0.001, centimetres x 0.01) and turn it +Y up first")
    if (skeleton is None) != (weights is None):
        raise ParameterError("skeleton and weights: pass both (a rigged body) or neither (a plain mesh)")
    if skeleton is not None:
        try:
            weights = sp.csr_matrix(weights, dtype=float)
        except (TypeError, ValueError) as exc:
            raise ParameterError(f"weights: {exc}; expected a (V, B) array or sparse matrix of skin weights") from None
        if not isinstance(skeleton, Skeleton):
            raise ParameterError(f"skeleton: got {type(skeleton).__name__}, expected a bodyspace.rig.skeleton.Skeleton")
        if weights.shape != (len(v), skeleton.n_bones):
            raise ParameterError(f"weights: shape {weights.shape}, expected ({len(v)}, {skeleton.n_bones}) for "
                                 f"{len(v)} vertices and the {skeleton.n_bones} bones of skeleton {skeleton.name!r}")
    names = set()
    out = []
    for m in morphs:
        if not isinstance(m, MorphTarget):
            raise ParameterError(f"morphs: got {type(m).__name__}, expected MorphTarget(name, deltas)")
        d = np.asarray(m.deltas, dtype=float)
        if d.shape != v.shape or not np.isfinite(d).all():
            raise ParameterError(f"morph {m.name!r}: deltas of shape {d.shape}{'' if np.isfinite(d).all() else ' with NaN'}, "
                                 f"expected finite ({len(v)}, 3) displacements in metres")
        if m.name in names:
            raise ParameterError(f"morph {m.name!r} given twice; expected distinct names")
        names.add(m.name)
        out.append(d)
    return v, f.astype(np.int64), weights, out


def gltf_bytes(vertices: np.ndarray, faces: np.ndarray, skeleton: Skeleton | None = None,
               weights: sp.spmatrix | np.ndarray | None = None, morphs: Sequence[MorphTarget] = (), *,
               name: str = "body", extras: dict | None = None, animation: SkeletonAnimation | None = None) -> bytes:
    """A binary glTF 2.0 file (bytes) of one body, rigged when a skeleton and weights are given.

    vertices: (V, 3) metres, +Y up, +Z front (the rest pose, which becomes the bind pose).
    faces: (F, 3) triangles, counter-clockwise seen from outside.
    skeleton: the body's ``Skeleton`` (B bones), or None for a plain mesh.
    weights: (V, B) skin weights (sparse or dense, rows with a positive sum); the 4 largest per
        vertex are written, the rest moved to skeleton kin (``top_influences``).
    morphs: ``MorphTarget`` shape keys (V, 3) displacements each.
    name: the mesh's and mesh node's name; extras: JSON-able facts for the asset's extras.
    animation: a ``SkeletonAnimation`` of the skeleton's bones (needs a skeleton).
    """
    v, f, weights, deltas = _check_inputs(vertices, faces, skeleton, weights, morphs)
    if animation is not None:
        if skeleton is None:
            raise ParameterError("animation: needs a skeleton and weights (a rigged body) to move")
        G = np.asarray(animation.transforms, dtype=float)
        if G.ndim != 4 or G.shape[1:] != (skeleton.n_bones, 4, 4) or len(G) == 0 or not np.isfinite(G).all():
            raise ParameterError(f"animation: transforms of shape {G.shape}, expected finite (frames, "
                                 f"{skeleton.n_bones}, 4, 4) for the skeleton's bones")
        if not (np.isfinite(animation.frame_time) and animation.frame_time > 0):
            raise ParameterError(f"animation: frame time {animation.frame_time!r}, expected a positive number of "
                                 "seconds")
    gltf = pygltflib.GLTF2(asset=pygltflib.Asset(generator=GENERATOR, version="2.0",
                                                 extras={"units": "metre", "up": "+Y", "front": "+Z",
                                                         **(extras or {})}))
    buf = _Buffer(gltf)
    gltf.materials.append(pygltflib.Material(
        name="skin", pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(
            baseColorFactor=list(SKIN_COLOR), metallicFactor=0.0, roughnessFactor=0.65)))
    normals = unit_vertex_normals(v, f)
    attrs = pygltflib.Attributes(
        POSITION=buf.add(v.astype(np.float32), _FLOAT, "VEC3", _ARRAY_BUFFER, minmax=True),
        NORMAL=buf.add(normals.astype(np.float32), _FLOAT, "VEC3", _ARRAY_BUFFER))
    if skeleton is not None:
        joints, w = top_influences(weights, parents=skeleton.parents)
        jtype, jdtype = (_UBYTE, np.uint8) if skeleton.n_bones <= 256 else (_USHORT, np.uint16)
        attrs.JOINTS_0 = buf.add(joints.astype(jdtype), jtype, "VEC4", _ARRAY_BUFFER)
        attrs.WEIGHTS_0 = buf.add(_unit_sum_float32(w), _FLOAT, "VEC4", _ARRAY_BUFFER)
    small = len(v) <= 65535  # 65535 itself is uint16's primitive-restart value, never an index
    indices = buf.add(f.reshape(-1).astype(np.uint16 if small else np.uint32), _USHORT if small else _UINT,
                      "SCALAR", _ELEMENT_ARRAY_BUFFER, minmax=True)
    targets = []
    for d in deltas:
        targets.append(pygltflib.Attributes(
            POSITION=buf.add(d.astype(np.float32), _FLOAT, "VEC3", _ARRAY_BUFFER, minmax=True),
            NORMAL=buf.add((unit_vertex_normals(v + d, f) - normals).astype(np.float32), _FLOAT, "VEC3", _ARRAY_BUFFER)))
    primitive = pygltflib.Primitive(attributes=attrs, indices=indices, material=0, mode=4, targets=targets or None)
    mesh_extras = {}
    if morphs:
        mesh_extras = {"targetNames": [m.name for m in morphs],
                       "morphs": [{"name": m.name, **m.meaning} for m in morphs]}
    gltf.meshes.append(pygltflib.Mesh(name=name, primitives=[primitive], weights=[0.0] * len(morphs) or None,
                                      extras=mesh_extras))
    gltf.nodes.append(pygltflib.Node(name=name, mesh=0))
    gltf.scenes.append(pygltflib.Scene(name=name, nodes=[0]))
    gltf.scene = 0
    if skeleton is not None:
        _add_skeleton(gltf, buf, skeleton)
    if animation is not None:
        _add_animation(gltf, buf, skeleton, animation)
    gltf.buffers.append(pygltflib.Buffer(byteLength=buf.size))
    gltf.set_binary_blob(buf.blob())
    return b"".join(gltf.save_to_bytes())


def _add_skeleton(gltf: pygltflib.GLTF2, buf: _Buffer, skeleton: Skeleton) -> None:
    """Joint nodes (local = parent frame^-1 · own frame), the armature node and the skin."""
    inv = np.linalg.inv(skeleton.bind_matrices())                  # (B, 4, 4) inverse bind matrices
    parents = skeleton.parents
    has_parent = parents >= 0
    translation, rotation = joint_local_transforms(skeleton)       # rest pose = bind pose
    first = len(gltf.nodes) + 1                                    # the armature node comes first
    armature = pygltflib.Node(name=skeleton.name, children=[first + int(b) for b in np.flatnonzero(~has_parent)],
                              extras={"rig": skeleton.name, "bones": skeleton.n_bones})
    gltf.nodes.append(armature)
    children = [[] for _ in range(skeleton.n_bones)]
    for b, p in enumerate(parents):
        if p >= 0:
            children[p].append(first + b)
    lengths = skeleton.lengths
    for b, bone in enumerate(skeleton.bone_names):
        gltf.nodes.append(pygltflib.Node(
            name=bone, translation=translation[b].tolist(), rotation=rotation[b].tolist(),
            children=children[b],
            extras={"head": skeleton.heads[b].tolist(), "tail": skeleton.tails[b].tolist(),
                    "roll": float(skeleton.roll[b]), "length": float(lengths[b])}))
    # glTF matrices are column-major: the transpose of each row-major 4x4, flattened.
    ibm = buf.add(inv.transpose(0, 2, 1).astype(np.float32).reshape(-1, 16), _FLOAT, "MAT4")
    gltf.skins.append(pygltflib.Skin(name=skeleton.name, inverseBindMatrices=ibm, skeleton=first - 1,
                                     joints=[first + b for b in range(skeleton.n_bones)]))
    gltf.nodes[0].skin = 0
    gltf.scenes[0].nodes.append(first - 1)


def _add_animation(gltf: pygltflib.GLTF2, buf: _Buffer, skeleton: Skeleton, animation: SkeletonAnimation) -> None:
    """Rotation channels of every joint node, translation channels of the root joints."""
    G = np.asarray(animation.transforms, dtype=float)
    translation, rotation = joint_local_transforms(skeleton, G)               # (F, B, 3), (F, B, 4)
    rotation = continuous_quaternions(rotation)
    joints = gltf.skins[0].joints                                              # node of each bone
    times = buf.add((np.arange(len(G)) * float(animation.frame_time)).astype(np.float32), _FLOAT, "SCALAR",
                    minmax=True)
    samplers, channels = [], []
    for b in range(skeleton.n_bones):
        samplers.append(pygltflib.AnimationSampler(input=times, interpolation="LINEAR",
                                                   output=buf.add(rotation[:, b].astype(np.float32), _FLOAT, "VEC4")))
        channels.append(pygltflib.AnimationChannel(sampler=len(samplers) - 1, target=pygltflib.AnimationChannelTarget(
            node=joints[b], path="rotation")))
    for b in np.flatnonzero(skeleton.parents < 0):
        moved = buf.add(translation[:, b].astype(np.float32), _FLOAT, "VEC3")
        samplers.append(pygltflib.AnimationSampler(input=times, interpolation="LINEAR", output=moved))
        channels.append(pygltflib.AnimationChannel(sampler=len(samplers) - 1, target=pygltflib.AnimationChannelTarget(
            node=joints[int(b)], path="translation")))
    gltf.animations.append(pygltflib.Animation(name=animation.name, samplers=samplers, channels=channels,
                                               extras={"frames": len(G), "frame_time_s": float(animation.frame_time)}))


def joint_local_transforms(skeleton: Skeleton, transforms: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Local translations (..., B, 3) and rotations (..., B, 4) (x, y, z, w) of the joint nodes.

    transforms: (..., B, 4, 4) posed bone transforms in our convention (``forward_kinematics``:
    rest points to posed points, no inverse bind matrices), or None for the rest pose. A joint
    node's world matrix is then ``G_b · M_b`` (``M_b`` its rest frame, ``bind_matrices``) and its
    local matrix is the parent's world matrix inverted times its own: what a glTF animation
    channel or a loader's bone (three.js ``bone.position`` / ``bone.quaternion``) takes.
    """
    M = skeleton.bind_matrices()
    world = M if transforms is None else np.asarray(transforms, dtype=float) @ M
    parents = skeleton.parents
    local = world.copy()
    has_parent = parents >= 0
    local[..., has_parent, :, :] = np.linalg.inv(world[..., parents[has_parent], :, :]) @ world[..., has_parent, :, :]
    q = matrix_to_quaternion(local[..., :3, :3])
    return local[..., :3, 3], np.concatenate([q[..., 1:], q[..., :1]], axis=-1)


def write_gltf(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray, skeleton: Skeleton | None = None,
               weights=None, morphs: Sequence[MorphTarget] = (), **kwargs) -> Path:
    """``gltf_bytes`` written to ``path`` (a ``.glb``) under a temporary name, then renamed."""
    path = Path(path)
    if path.suffix.lower() != ".glb":
        raise ParameterError(f"{path}: a rigged body is written as binary glTF; expected a name ending in .glb")
    data = gltf_bytes(vertices, faces, skeleton, weights, morphs, **kwargs)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path
