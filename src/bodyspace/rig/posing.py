"""Posing of template bodies: linear-blend (or dual-quaternion) skinning of a rig, ground
placement, smoothed skin weights and the fold counter. The pose library, which says *which*
rotations, is ``bodyspace.synth.poses``.
"""

from __future__ import annotations

import hashlib
from functools import lru_cache

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from bodyspace.atomic import atomic_path
from bodyspace.data.assets import cache_dir
from bodyspace.data.template import Rig, load_template
from bodyspace.errors import MeshError, ParameterError
from bodyspace.measure.parts import PART_INDEX, part_of_bone, parts_from_weights
from bodyspace.mesh.topology import face_adjacency_matrix
from bodyspace.rig.kinematics import (
    dual_quaternion_skinning,
    forward_kinematics,
    linear_blend_skinning,
)
from bodyspace.rig.volume import VolumeRig, volume_rig
from bodyspace.rig.volume import preserve_volume as correct_volume
from bodyspace.rig.weights import bone_heat_weights

# ------------------------------------------------------------------------------------ posing

def root_bone(rig: Rig) -> int:
    """Index of the rig's root bone (the first bone without a parent): the pelvis anchor."""
    roots = np.flatnonzero(np.asarray(rig.parents) < 0)
    if len(roots) == 0:
        raise ParameterError(f"rig {rig.name!r} has no root bone (every parent is set)")
    return int(roots[0])


def ground_offset(posed: np.ndarray, posed_pelvis: np.ndarray, rest_pelvis: np.ndarray) -> np.ndarray:
    """Translations (N, 3) that put posed bodies on the floor y = 0 with the pelvis over its rest x/z.

    posed: (N, V, 3) posed vertices; posed_pelvis, rest_pelvis: (N, 3) pelvis points.
    The y offset brings the lowest vertex to 0; the x/z offset moves the posed pelvis back over
    the rest pelvis (a root rotation otherwise swings the whole body about the root head).
    """
    posed = np.asarray(posed, dtype=float)
    off = np.zeros((posed.shape[0], 3))
    off[:, [0, 2]] = np.asarray(rest_pelvis, float)[:, [0, 2]] - np.asarray(posed_pelvis, float)[:, [0, 2]]
    off[:, 1] = -posed[..., 1].min(axis=1)
    return off


def place_on_ground(posed: np.ndarray, posed_pelvis: np.ndarray, rest_pelvis: np.ndarray) -> np.ndarray:
    """Posed bodies (N, V, 3) translated by ``ground_offset``: lowest vertex at y = 0, pelvis x/z kept."""
    return np.asarray(posed, dtype=float) + ground_offset(posed, posed_pelvis, rest_pelvis)[:, None, :]


# Weight smoothing (measured on 4 bodies x 39 poses, docs/poses.md): explicit diffusion steps
# W <- (1 - a) W + a P W (P: mean over the 1-ring) on the vertices with two or more influences
# above 1 % plus a few rings around them; then weights below the prune level are dropped.
SMOOTH_STEPS = 150
SMOOTH_RATE = 0.5
SMOOTH_MIN_INFLUENCE = 0.01
SMOOTH_DILATE_RINGS = 6
SMOOTH_PRUNE = 2e-3
_SMOOTHED: dict[tuple[int, bytes], tuple[object, sp.csr_matrix]] = {}


def vertex_adjacency(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """Symmetric (V, V) 0/1 matrix of vertices joined by a mesh edge."""
    f = np.asarray(faces, dtype=np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    A = sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_vertices, n_vertices))
    return ((A + A.T) > 0).astype(float).tocsr()


def smooth_skin_weights(weights: sp.spmatrix, faces: np.ndarray, steps: int = SMOOTH_STEPS,
                        rate: float = SMOOTH_RATE, min_influence: float = SMOOTH_MIN_INFLUENCE,
                        dilate: int = SMOOTH_DILATE_RINGS, prune: float = SMOOTH_PRUNE) -> sp.csr_matrix:
    """Skin weights (V, B) diffused over the mesh where bones blend, rows renormalized to one.

    Vertices with two or more influences above ``min_influence``, grown by ``dilate`` edge
    rings, take ``steps`` explicit Laplacian steps ``w <- (1 - rate) w + rate mean(w of the
    1-ring)``; the others keep their weights. Weights under ``prune`` are dropped. Widening the
    blend band spreads a joint's bend over more skin, so far fewer triangles fold over.
    """
    W = sp.csr_matrix(weights, dtype=float)
    V = W.shape[0]
    A = vertex_adjacency(faces, V)
    P = sp.diags(1.0 / np.maximum(np.asarray(A.sum(1)).ravel(), 1.0)) @ A
    mask = np.asarray((W > min_influence).sum(1)).ravel() >= 2
    for _ in range(dilate):
        mask = mask | (A @ mask.astype(float) > 0)
    M = sp.diags(mask.astype(float))
    S = (sp.identity(V) - rate * M + rate * (M @ P)).tocsr()
    for _ in range(steps):
        W = S @ W
    W = W.multiply(W > prune).tocsr()
    W = (sp.diags(1.0 / np.asarray(W.sum(1)).ravel()) @ W).tocsr()
    W.sort_indices()
    return W


def mirror_bones(rig: Rig) -> np.ndarray:
    """(B,) index of each bone's left/right mirror (``.L`` <-> ``.R``; itself otherwise)."""
    idx = {b: i for i, b in enumerate(rig.bone_names)}
    swap = {".L": ".R", ".R": ".L"}
    return np.array([idx.get(b[:-2] + swap[b[-2:]], i) if b[-2:] in swap else i for i, b in enumerate(rig.bone_names)])


def smoothed_weights(rig: Rig, faces: np.ndarray | None = None, mirror: np.ndarray | None = None) -> sp.csr_matrix:
    """``smooth_skin_weights`` of ``rig.weights``, made left/right symmetric, cached per rig.

    faces: the template's (F, 3) faces; mirror: (V,) the template's vertex mirror map
    (``Template.mirror``); by default both from the shipped template. The uniform Laplacian
    follows the triangulation, which is not exactly mirror-symmetric, so the result is
    averaged with its mirror image (vertex i <-> mirror[i], bone .L <-> .R): mirror poses stay
    mirror-image meshes.
    """
    if faces is None or mirror is None:
        t = load_template()
        faces = t.faces if faces is None else faces
        mirror = t.mirror if mirror is None else mirror
    f = np.ascontiguousarray(faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3 or f.max() >= rig.weights.shape[0]:
        raise MeshError(f"faces: shape {f.shape}, expected (F, 3) indices of the rig's {rig.weights.shape[0]} vertices")
    mirror = np.asarray(mirror, dtype=np.int64)
    key = (id(rig), f.tobytes() + mirror.tobytes())
    hit = _SMOOTHED.get(key)
    if hit is None or hit[0] is not rig:
        hit = (rig, _smoothed_from_disk_or_compute(rig, f, mirror))
        _SMOOTHED[key] = hit
    return hit[1]


def _smoothed_from_disk_or_compute(rig: Rig, faces: np.ndarray, mirror: np.ndarray) -> sp.csr_matrix:
    """The smoothed weights, cached on disk beside the compiled template (they take ~6 s)."""
    W0 = rig.weights.tocsr(copy=True)
    W0.sum_duplicates()  # canonical form, so the key does not depend on index order
    digest = hashlib.sha256(b"".join([np.ascontiguousarray(a).tobytes() for a in
                                      (W0.data, W0.indices, W0.indptr, faces, mirror)])).hexdigest()[:16]
    path = cache_dir() / "compiled" / f"smoothed-weights-{rig.name}-{digest}.npz"
    if path.is_file():
        with np.load(path, allow_pickle=False) as z:
            return sp.csr_matrix((z["data"], z["indices"], z["indptr"]), shape=tuple(z["shape"]))
    W = smooth_skin_weights(rig.weights, faces)
    mb = mirror_bones(rig)
    W = (0.5 * (W + W[mirror][:, mb])).tocsr()
    W.sort_indices()
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as out:
            np.savez(out, data=W.data, indices=W.indices, indptr=W.indptr, shape=np.array(W.shape))
    return W


_BONE_HEAT: dict[tuple[int, bytes], tuple[object, sp.csr_matrix]] = {}

# The template's bone-heat rules (``template_heat_rules``), measured on 3 bodies x 39 library
# poses (docs/skinning.md): MakeHuman's hip helper bones (root to hip joint, rotated by no pose)
# as heat sources split the groin between a still bone and the thigh (42 folds added);
HIP_HELPER_BONES = ("pelvis.L", "pelvis.R")
# the jaw is the nearest visible bone of the throat, which then turns with the head (26 folds in
# head_turn_*): it may weigh only where MakeHuman's jaw weight is above this (the chin and lower
# lip, so the mouth still opens);
JAW_BONE, JAW_REGION = "jaw", 0.8
# the upper arm (and shoulder) bones pull the chest ring up with a raised arm (chest girth -3.8 cm
# in arms_overhead): no torso vertex farther than ARMPIT_DISTANCE from the armpit loop (the torso
# vertices bordering the upper arm), measured along the torso's surface of the rest body, is
# weighted by them. Chosen on six training bodies x 39 poses (docs/skinning.md "Held-out
# bodies"): 6 / 8 / 9 / 10 / 12 cm gave 344 / 267 / 242 / 238 / 250 folds and a worst chest of
# 0.6 / 1.2 / 1.9 / 2.3 / 3.6 cm; 10 cm has the fewest folds with the chest within 2.5 cm.
# A surface distance follows the loop round the front and back of the armpit, where a height
# below its lowest vertex (the earlier rule, ``armpit="height"``: ARMPIT_DROP = 6 cm, 255 folds
# there) cuts the back and front at the side's level.
ARMPIT_DISTANCE = 0.10
ARMPIT_DROP = 0.06
# MakeHuman's arm twist bones, heated as one bone with the bone they twist and then split along
# it (``bone_heat_weights(twist_of=...)``): at the shoulder a twist bone otherwise takes one of
# the four places (upper arm, its twist bone, shoulder, breast), leaving the torso one bone.
# Measured: 176 -> 152 folds. The leg twist bones are not merged: that measured worse (182 and
# 180 folds for upperleg02 and lowerleg02 left out of the heat).
TWIST_BONES = {"upperarm02.L": "upperarm01.L", "upperarm02.R": "upperarm01.R",
               "lowerarm02.L": "lowerarm01.L", "lowerarm02.R": "lowerarm01.R"}
# The rib cage's bones, one group through the cut to four bones (``bone_heat_weights(groups=...)``):
# beside the armpit five of them share the four places with the upper arm, and the plain cut
# hands their dropped weight to the arm (0.51 -> 0.70), which folds the torso side of the armpit
# when the arm swings forward. Chosen on the six training bodies x 39 poses (docs/skinning.md):
# 238 -> 197 folds added (LBS), 168 -> 142 with the volume correction; spine01-03 and the
# breasts alone 214; the whole torso 246 (the groin folds in sitting).
CHEST_GROUP = ("spine01", "spine02", "spine03", "breast.L", "breast.R", "clavicle.L", "clavicle.R",
               "shoulder01.L", "shoulder01.R")


def template_heat_rules(rig: Rig, vertices: np.ndarray, faces: np.ndarray, armpit: str = "surface",
                        chest_group: bool = True) -> dict:
    """The deforming bones, the part-aware mask and the twist pairs for bone heat on a template body.

    rig: a template ``Rig``; vertices (V, 3) a body of the template topology in metres, +Y up;
    faces (F, 3). armpit: where the upper-arm bones stop on the torso: ``"surface"`` (default)
    farther than ``ARMPIT_DISTANCE`` from the armpit loop along the torso's surface; ``"height"``
    (the earlier rule) more than ``ARMPIT_DROP`` below the loop's lowest vertex. chest_group:
    the rib cage's bones (``CHEST_GROUP``) keep their share through the cut to four bones
    (False: the rules before, for comparison). Returns the keyword arguments of
    ``bone_heat_weights``: ``deform`` (B,) bool (the bones MakeHuman's weights use, less the hip
    helper bones), ``allowed`` (V, B) bool (the jaw only on its chin region, the upper-arm bones
    off the torso away from the armpit), ``twist_of`` (B,) int (the arm twist bones) and
    ``groups`` (B,) int (0 for the chest group, else -1). Rules whose bones a rig does not have
    are skipped (they are named for MakeHuman's default rigs).
    """
    V, B = vertices.shape[0], rig.n_bones
    mh = rig.weights.tocsc()
    deform = np.asarray(abs(mh).sum(axis=0)).ravel() > 0
    names = list(rig.bone_names)
    for name in HIP_HELPER_BONES:
        if name in names:
            deform[names.index(name)] = False
    allowed = np.ones((V, B), dtype=bool)
    if JAW_BONE in names:
        j = names.index(JAW_BONE)
        allowed[:, j] = np.asarray(mh[:, j].toarray()).ravel() > JAW_REGION
    parts = parts_from_weights(rig.weights, rig.bone_names)              # (V,) part per vertex
    bone_part = np.array([part_of_bone(b) for b in rig.bone_names])      # (B,)
    if armpit not in ("surface", "height"):
        raise ParameterError(f"armpit={armpit!r}; expected 'surface' or 'height'")
    y = vertices[:, 1]
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    torso = PART_INDEX["torso"]
    on_torso = parts == torso
    inner = edges[on_torso[edges[:, 0]] & on_torso[edges[:, 1]]]
    # The torso's own edge graph, so the distance does not short-cut through the arm.
    graph = sp.csr_matrix((np.linalg.norm(vertices[inner[:, 0]] - vertices[inner[:, 1]], axis=1),
                           (inner[:, 0], inner[:, 1])), shape=(V, V))
    for side in ("l", "r"):
        arm = PART_INDEX["upper_arm_" + side]
        crossing = edges[(parts[edges[:, 0]] == arm) & (parts[edges[:, 1]] == torso)]   # (E', 2) arm, torso
        if not len(crossing) or not (bone_part == arm).any():
            continue
        if armpit == "height":
            far = on_torso & (y < y[crossing[:, 0]].min() - ARMPIT_DROP)
        else:
            loop = np.unique(crossing[:, 1])
            far = on_torso & (dijkstra(graph, directed=False, indices=loop, min_only=True,
                                       limit=2 * ARMPIT_DISTANCE) > ARMPIT_DISTANCE)
        allowed[np.ix_(far, bone_part == arm)] = False
    twist_of = np.full(B, -1, dtype=np.int64)
    for child, parent in TWIST_BONES.items():
        if child in names and parent in names and deform[names.index(child)] and deform[names.index(parent)]:
            twist_of[names.index(child)] = names.index(parent)
    groups = np.full(B, -1, dtype=np.int64)
    if chest_group:
        groups[[names.index(n) for n in CHEST_GROUP if n in names]] = 0
    return {"deform": deform, "allowed": allowed, "twist_of": twist_of, "groups": groups}


def bone_heat_rig_weights(rig: Rig, vertices: np.ndarray | None = None, faces: np.ndarray | None = None,
                          max_influences: int = 4) -> sp.csr_matrix:
    """Bone-heat weights (``rig.weights.bone_heat_weights``) of a template rig, cached per rig.

    vertices: (V, 3) the rest body the heat is computed on, faces (F, 3); by default the shipped
    template's mean body. The bones are the rig's bones at that body (its regressors); the
    bones MakeHuman's weights use deform (39 of the default rig's 163, the face-control, tongue
    and root bones, get none), less the hip helper bones, with the part-aware mask and the arm
    twist pairs of ``template_heat_rules`` (jaw on the chin only, no upper arm on the torso
    farther than ``ARMPIT_DISTANCE`` from the armpit loop along the surface, each arm twist bone
    heated with the bone it twists, the rib cage's bones one group through the cut).
    """
    if vertices is None or faces is None:
        t = load_template()
        vertices = t.vertices if vertices is None else vertices
        faces = t.faces if faces is None else faces
    v = np.ascontiguousarray(vertices, dtype=float)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    if v.shape != (rig.weights.shape[0], 3):
        raise MeshError(f"vertices: shape {v.shape}, expected ({rig.weights.shape[0]}, 3) a body of the template topology")
    key = (id(rig), v.tobytes() + f.tobytes() + bytes([max_influences]))
    hit = _BONE_HEAT.get(key)
    if hit is None or hit[0] is not rig:
        hit = (rig, bone_heat_weights(v, f, rig.heads(v), rig.tails(v), max_influences,
                                      **template_heat_rules(rig, v, f)))
        _BONE_HEAT.clear()                      # one entry: a (V, B) matrix per body is large
        _BONE_HEAT[key] = hit
    return hit[1]


_VOLUME_RIGS: dict[tuple[int, int, bytes], tuple[object, object, VolumeRig]] = {}


def rig_volume_data(rig: Rig, weights: sp.spmatrix, faces: np.ndarray | None = None) -> VolumeRig:
    """``volume.volume_rig`` of a template rig with ``weights`` (V, B) and faces (F, 3) (default:
    the shipped template's), cached per rig and weight matrix (a few of them: one per weight set)."""
    if faces is None:
        faces = load_template().faces
    f = np.ascontiguousarray(faces, dtype=np.int64)
    key = (id(rig), id(weights), f.tobytes())
    hit = _VOLUME_RIGS.get(key)
    if hit is None or hit[0] is not rig or hit[1] is not weights:
        if len(_VOLUME_RIGS) >= 4:
            _VOLUME_RIGS.pop(next(iter(_VOLUME_RIGS)))
        hit = (rig, weights, volume_rig(weights, rig.parents, f))
        _VOLUME_RIGS[key] = hit
    return hit[2]


def pose_bodies(vertices: np.ndarray, rig: Rig, rotations: np.ndarray, *, on_ground: bool = False,
                return_joints: bool = False, skinning: str = "lbs", weights: str = "original",
                faces: np.ndarray | None = None, dtype=np.float64, preserve_volume: bool = False):
    """Pose bodies of the template topology: joints from the rig regressors, FK, then LBS.

    vertices: (N, V, 3) rest-pose bodies, or (V, 3) for one body (posed once, or once per
        frame when ``rotations`` holds several frames: one body over an animation).
    rig: a ``Rig`` of the template (its regressors give each body's own joints).
    rotations: (N, B, 3, 3) per-bone rotations (rest-pose world axes, about the bone heads),
        or (B, 3, 3) applied to every body; e.g. ``load_pose_library().rotations("squat", rig)``.
    on_ground: translate each posed body so its lowest vertex is at y = 0 and its pelvis (root
        bone head) keeps its rest x/z (``place_on_ground``).
    skinning: ``"lbs"`` (linear blend skinning, the default) or ``"dqs"`` (dual-quaternion
        skinning, ``kinematics.dual_quaternion_skinning``).
    weights: ``"original"`` (default): MakeHuman's weights as shipped; ``"smoothed"``: the
        rig's weights diffused over the mesh where bones blend (``smoothed_weights``), which
        removes about 80 % of the folded triangles LBS makes at armpit, groin and knee, but
        drags the chest skin with a raised arm (chest girth +4.9 cm in arms_overhead against
        < 2.5 cm), so the measurement landmarks, fitted on the original weights, are not
        validated for it. Not yet the default for that reason. ``"bone_heat"``: bone-heat
        weights computed on the template's mean body (``bone_heat_rig_weights``, Baran &
        Popović 2007; docs/skinning.md compares the three).
    faces: (F, 3) template faces for the smoothing and the volume correction; by default the
        shipped template's.
    preserve_volume: after skinning, displace each posed body along its normals around the bent
        joints so its enclosed volume equals its rest volume (to rounding; ``rig.volume``,
        docs/skinning.md "Volume-preserving skinning"). LBS alone loses up to 17 % (squat).
        A glTF file cannot carry this correction (viewers skin with plain LBS).
    dtype: float64 (default) or float32 posed vertices; float32 skins in float32 arithmetic
        (``skinning.linear_blend_skinning``: within 0.001 mm, about 1.5x as fast).
    FK and skinning are the compiled kernels of ``kinematics`` / ``skinning`` (two lanes for
    large batches).
    Returns posed vertices (N, V, 3) (or (V, 3) for a single (V, 3) input and one pose); with
    ``return_joints`` also the posed bone heads (N, B, 3) (or (B, 3)), translated alike.
    """
    v = np.asarray(vertices, dtype=float)
    R = np.asarray(rotations, dtype=float)
    frames = R.shape[0] if R.ndim == 4 else 1
    # One rest body for every frame: (V, 3) with several rotation sets, or a (N, V, 3) broadcast
    # of one body (stride 0). Its joints are regressed once and the skinning reads it once.
    shared = (v.ndim == 2 and frames > 1) or (v.ndim == 3 and v.shape[0] > 1 and v.strides[0] == 0)
    single = v.ndim == 2 and not shared
    if shared:
        v = v if v.ndim == 2 else v[0]
        if v.shape != (rig.weights.shape[0], 3):
            raise MeshError(f"vertices: shape {np.shape(vertices)}, expected ({rig.weights.shape[0]}, 3) "
                            f"a body of the template topology")
        v = v[None]
    elif single:
        v = v[None]
    if v.ndim != 3 or v.shape[2] != 3 or v.shape[1] != rig.weights.shape[0]:
        raise MeshError(f"vertices: shape {np.shape(vertices)}, expected (N, {rig.weights.shape[0]}, 3) "
                        f"bodies of the template topology")
    n = frames if shared else v.shape[0]
    if R.ndim == 3:
        R = np.broadcast_to(R, (n,) + R.shape)
    if R.shape != (n, rig.n_bones, 3, 3):
        raise ParameterError(f"rotations: shape {np.shape(rotations)}, expected ({n}, {rig.n_bones}, 3, 3) "
                             f"or ({rig.n_bones}, 3, 3) for rig {rig.name!r}")
    heads = rig.heads(v)                                           # (N, B, 3), or (1, B, 3) shared
    G = forward_kinematics(R, heads, rig.parents)                  # (N, B, 4, 4)
    if weights == "smoothed":
        W = smoothed_weights(rig, faces)
    elif weights == "original":
        W = rig.weights
    elif weights == "bone_heat":
        W = bone_heat_rig_weights(rig, faces=faces)
    else:
        raise ParameterError(f"weights={weights!r}; expected 'original', 'smoothed' or 'bone_heat'")
    if skinning == "lbs":
        posed = linear_blend_skinning(v, W, G, dtype=dtype)        # (N, V, 3)
    elif skinning == "dqs":
        posed = dual_quaternion_skinning(v, W, G, dtype=dtype)
    else:
        raise ParameterError(f"skinning={skinning!r}; expected 'lbs' or 'dqs'")
    if preserve_volume:
        correct_volume(posed, v, G, heads, rig.tails(v), rig_volume_data(rig, W, faces))
    joints = np.einsum("nbij,nbj->nbi", G[..., :3, :3], np.broadcast_to(heads, (n,) + heads.shape[1:])) + G[..., :3, 3]
    if on_ground:
        r = root_bone(rig)
        off = ground_offset(posed, joints[:, r], np.broadcast_to(heads[:, r], (n, 3)))
        posed += off[:, None, :]                                   # in place: posed is ours
        joints += off[:, None, :]
    if single:
        posed, joints = posed[0], joints[0]
    return (posed, joints) if return_joints else posed


# ------------------------------------------------------------------------------ mesh quality

@lru_cache(maxsize=4)
def _face_adjacency(faces_bytes: bytes, n_faces: int) -> sp.csr_matrix:
    """``face_adjacency_matrix`` of the faces in ``faces_bytes`` (int64, (n_faces, 3)), cached:
    every call of ``count_folded_triangles`` on one mesh needs the same matrix."""
    return face_adjacency_matrix(np.frombuffer(faces_bytes, dtype=np.int64).reshape(n_faces, 3))


def folded_triangles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Which triangles are folded: (N, V, 3) or (V, 3) vertices, (F, 3) faces → (N, F) or (F,) bool.

    A face is *folded* when its normal has a negative dot product with the area-weighted
    mean normal of its edge neighbours (the sum of their unnormalized cross products): the
    skin has flipped over onto itself there, as in the LBS collapse at armpit and groin. The
    one definition of a fold: ``count_folded_triangles`` counts these, the NICP's local
    stiffening and ``register.nicp.unfold`` act on them.
    """
    v = np.asarray(vertices, dtype=float)
    single = v.ndim == 2
    if single:
        v = v[None]
    if v.ndim != 3 or v.shape[2] != 3:
        raise MeshError(f"vertices: shape {np.shape(vertices)}, expected (N, V, 3) or (V, 3)")
    f = np.ascontiguousarray(faces, dtype=np.int64)
    A = _face_adjacency(f.tobytes(), len(f))
    n = np.cross(v[:, f[:, 1]] - v[:, f[:, 0]], v[:, f[:, 2]] - v[:, f[:, 0]])   # (N, F, 3), |n| = 2 area
    N, F = n.shape[:2]
    acc = np.asarray(A @ n.transpose(1, 0, 2).reshape(F, 3 * N)).reshape(F, N, 3).transpose(1, 0, 2)
    folded = np.einsum("nfc,nfc->nf", n, acc) < 0
    return folded[0] if single else folded


def count_folded_triangles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Folded triangles per body (``folded_triangles``): (N, V, 3) or (V, 3) vertices, (F, 3)
    faces → (N,) int (or int)."""
    folded = folded_triangles(vertices, faces).sum(axis=-1)
    return int(folded) if np.ndim(folded) == 0 else folded
