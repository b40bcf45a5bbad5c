"""The pose library and posing of template bodies.

A *pose* is a set of per-bone rotations of the ``default`` rig (MakeHuman's 163-bone CC0 rig)
stored as data in ``bodyspace/synth/pose_library.json``: for each named bone an axis-angle
rotation vector in **degrees**, expressed in the **rest-pose world axes** (+X the person's
left, +Y up, +Z front) and applied about the bone's rest head; the parent's rotation applies
on top (``kinematics.forward_kinematics``). Bones a pose does not name keep the identity, so
an empty pose is the template's rest pose (MakeHuman's A-pose: arms about 40 degrees from the
body, elbows slightly bent forward). Sign guide for the common motions:

=====================  ======================================================================
rotation about         moves
=====================  ======================================================================
+X                     up-vectors toward the front, down-vectors toward the back: spine or neck
                       flexion (bend forward), knee flexion (foot back), toes down; -X is hip
                       flexion (thigh forward) and shoulder flexion (arm forward)
+Y                     the front toward the person's left: twist / head turn to the left
+Z                     up-vectors toward the person's right (side bend right), down-vectors
                       toward the left: left arm / left leg abduction; the right side uses -Z
=====================  ======================================================================

A left/right mirror image of a rotation vector (x, y, z) is (x, -y, -z) on the mirrored bone
(``.L`` ↔ ``.R``). The poses follow the spirit of the 34 poses of Hasler et al. 2009 (arm
raises, squats, one-leg stands, twists, bends); docs/poses.md lists them.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Iterator, Mapping

import numpy as np

from bodyspace.data.template import Rig
from bodyspace.errors import ParameterError
from bodyspace.rig.kinematics import rotvec_to_matrix

LIBRARY_PATH = Path(__file__).resolve().parent / "pose_library.json"
LIBRARY_FORMAT = "bodyspace-pose-library"


@dataclass(frozen=True)
class Pose:
    """One named pose: per-bone rotation vectors in degrees (rest-pose world axes)."""

    name: str
    description: str
    rotvecs_deg: Mapping[str, tuple[float, float, float]]
    mirror: str | None = None  # the left/right mirror-image pose (itself if symmetric), if any


class PoseLibrary:
    """Named poses of one rig (by default the shipped library of the ``default`` rig).

    ``rotations(name, rig)`` gives the (B, 3, 3) matrices for ``forward_kinematics`` /
    ``pose_bodies``; ``rotvecs`` the (B, 3) rotation vectors in radians.
    """

    def __init__(self, poses: list[Pose], rig_name: str = "default", source: str = "<memory>"):
        names = [p.name for p in poses]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ParameterError(f"{source}: pose names {dupes} appear more than once; expected unique names")
        self._poses = {p.name: p for p in poses}
        self.rig_name = rig_name
        self.source = source

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self._poses)

    def __len__(self) -> int:
        return len(self._poses)

    def __iter__(self) -> Iterator[str]:
        return iter(self._poses)

    def __contains__(self, name: object) -> bool:
        return name in self._poses

    def pose(self, name: str) -> Pose:
        try:
            return self._poses[name]
        except (KeyError, TypeError):
            raise ParameterError(f"pose {name!r} is not in {self.source}; known poses: "
                                 f"{', '.join(self._poses)}") from None

    def description(self, name: str) -> str:
        return self.pose(name).description

    def mirror(self, name: str) -> str | None:
        """Name of the left/right mirror image of pose ``name`` (itself if symmetric), or None."""
        return self.pose(name).mirror

    def rotvecs(self, name: str, rig: Rig) -> np.ndarray:
        """Rotation vectors (B, 3) in radians for ``rig``'s bones; bones not named are zero."""
        pose = self.pose(name)
        out = np.zeros((rig.n_bones, 3))
        index = {b: i for i, b in enumerate(rig.bone_names)}
        for bone, rv in pose.rotvecs_deg.items():
            if bone not in index:
                raise ParameterError(f"pose {name!r} in {self.source} names bone {bone!r}, which rig "
                                     f"{rig.name!r} does not have (the library is written for rig "
                                     f"{self.rig_name!r})")
            out[index[bone]] = np.deg2rad(rv)
        return out

    def rotations(self, name: str, rig: Rig) -> np.ndarray:
        """Rotation matrices (B, 3, 3) for ``rig``'s bones; bones not named are the identity."""
        return rotvec_to_matrix(self.rotvecs(name, rig))

    def stack(self, names: list[str] | tuple[str, ...], rig: Rig) -> np.ndarray:
        """Rotation matrices (P, B, 3, 3) of several poses, ready for ``pose_bodies``."""
        return np.stack([self.rotations(n, rig) for n in names]) if len(names) else np.zeros((0, rig.n_bones, 3, 3))


def _parse_library(data: object, source: str) -> PoseLibrary:
    if not isinstance(data, dict) or data.get("format") != LIBRARY_FORMAT:
        raise ParameterError(f"{source}: expected a JSON object with \"format\": \"{LIBRARY_FORMAT}\"")
    if data.get("units") != "degrees":
        raise ParameterError(f"{source}: \"units\" is {data.get('units')!r}; expected \"degrees\"")
    raw = data.get("poses")
    if not isinstance(raw, list):
        raise ParameterError(f"{source}: \"poses\" is {type(raw).__name__}; expected a list of pose objects")
    poses = []
    for k, p in enumerate(raw):
        if not isinstance(p, dict) or not isinstance(p.get("name"), str) or not p["name"]:
            raise ParameterError(f"{source}: pose #{k} has no \"name\" string")
        name = p["name"]
        rot = p.get("rotations", {})
        if not isinstance(rot, dict):
            raise ParameterError(f"{source}: pose {name!r} \"rotations\" is {type(rot).__name__}; "
                                 "expected an object mapping bone names to [x, y, z] degrees")
        rv = {}
        for bone, v in rot.items():
            arr = np.asarray(v, dtype=float) if isinstance(v, list) else np.zeros(0)
            if arr.shape != (3,) or not np.isfinite(arr).all():
                raise ParameterError(f"{source}: pose {name!r} bone {bone!r} rotation is {v!r}; "
                                     "expected [x, y, z], a finite rotation vector in degrees")
            rv[bone] = tuple(float(a) for a in arr)
        mirror = p.get("mirror")
        if mirror is not None and not isinstance(mirror, str):
            raise ParameterError(f"{source}: pose {name!r} \"mirror\" is {mirror!r}; expected a pose name or null")
        poses.append(Pose(name, str(p.get("description", "")), rv, mirror))
    names = {p.name for p in poses}
    for p in poses:
        if p.mirror is not None and p.mirror not in names:
            raise ParameterError(f"{source}: pose {p.name!r} names mirror pose {p.mirror!r}, which is not in the library")
    return PoseLibrary(poses, rig_name=str(data.get("rig", "default")), source=source)


@lru_cache(maxsize=8)
def _load_cached(path: str, mtime_ns: int) -> PoseLibrary:
    try:
        data = json.loads(Path(path).read_text())
    except json.JSONDecodeError as e:
        raise ParameterError(f"{path}: not valid JSON ({e}); expected a pose library") from None
    return _parse_library(data, path)


def load_pose_library(path: str | os.PathLike | None = None) -> PoseLibrary:
    """The shipped pose library, or the one at ``path`` (same JSON format)."""
    p = Path(path) if path is not None else LIBRARY_PATH
    if not p.is_file():
        raise ParameterError(f"{p}: pose library file not found")
    return _load_cached(str(p.resolve()), p.stat().st_mtime_ns)


