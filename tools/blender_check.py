"""Import a rigged bodyspace .glb into Blender and check what arrived (not run in CI: bpy is 519 MB).

Usage (bpy 4.2 from PyPI needs Python 3.11; a separate environment keeps it apart):

    python3.11 -m venv ~/bpyenv && ~/bpyenv/bin/pip install bpy==4.2.0
    ~/bpyenv/bin/python tools/blender_check.py body.glb [--json report.json]

It reads the file's own data independently of bodyspace (the GLB's JSON and binary chunks with
numpy), imports it with Blender's glTF importer (default options) and checks:

1. armature: one armature whose bones are the skin's joints, same names, same parents;
2. bones: every head where the joint node's extras say (``head``), every bone's local +Y
   along head -> tail and its local X as the node's, Blender's roll equal to ``extras.roll``;
   Blender sets bone lengths itself (from the children), so the tails are then rebuilt from
   the extras (``tail``) in edit mode and checked;
3. weights: the mesh's vertex groups hold exactly the file's 4 influences per vertex;
4. shape keys: named as the file's morph targets (``extras.targetNames``), each key minus the
   basis equal to the target's displacements;
5. skinning: a pose (several bones turned, the whole body turned) evaluated by Blender's
   armature modifier equals linear blend skinning of the file's weights and inverse bind
   matrices with Blender's own posed bone matrices, and the rest pose gives the file's vertices.

Prints one line per check and exits 1 if any fails. Blender's axes are (x, -z, y) of glTF's.
"""

from __future__ import annotations

import argparse
import json
import math
import struct
import sys

import bpy
import numpy as np
from mathutils import Matrix

TO_BLENDER = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
COMPONENTS = {5126: np.float32, 5123: np.uint16, 5121: np.uint8, 5125: np.uint32}
WIDTH = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def read_glb(path):
    data = open(path, "rb").read()
    if data[:4] != b"glTF":
        sys.exit(f"{path}: not a binary glTF")
    n_json = struct.unpack("<I", data[12:16])[0]
    doc = json.loads(data[20:20 + n_json])
    blob = data[20 + n_json + 8:]

    def accessor(i):
        a = doc["accessors"][i]
        view = doc["bufferViews"][a["bufferView"]]
        arr = np.frombuffer(blob, COMPONENTS[a["componentType"]], a["count"] * WIDTH[a["type"]],
                            view.get("byteOffset", 0) + a.get("byteOffset", 0))
        return arr.reshape(a["count"], WIDTH[a["type"]]).astype(float)
    return doc, accessor


def angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Degrees between vectors (B, 3) and (B, 3), well conditioned near 0 (atan2 of |a x b|, a.b)."""
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("bi,bi->b", a, b)))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("glb")
    ap.add_argument("--json", help="write the results here as JSON")
    args = ap.parse_args(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:])
    doc, accessor = read_glb(args.glb)
    prim = doc["meshes"][0]["primitives"][0]
    skin = doc["skins"][0]
    joints = skin["joints"]
    names = [doc["nodes"][j]["name"] for j in joints]
    parent_node = {c: i for i, n in enumerate(doc["nodes"]) for c in n.get("children", [])}
    extras = [doc["nodes"][j]["extras"] for j in joints]
    positions = accessor(prim["attributes"]["POSITION"])
    file_joints = accessor(prim["attributes"]["JOINTS_0"]).astype(int)
    file_weights = accessor(prim["attributes"]["WEIGHTS_0"])
    ibm = accessor(skin["inverseBindMatrices"]).reshape(-1, 4, 4).transpose(0, 2, 1)
    target_names = doc["meshes"][0].get("extras", {}).get("targetNames", [])
    targets = [accessor(t["POSITION"]) for t in prim.get("targets", [])]

    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_scene.gltf(filepath=args.glb)
    results = []

    def check(name, ok, detail):
        results.append({"check": name, "ok": bool(ok), "detail": detail})
        print(f"{'ok  ' if ok else 'FAIL'} {name}: {detail}")

    armatures = [o for o in bpy.data.objects if o.type == "ARMATURE"]
    meshes = [o for o in bpy.data.objects if o.type == "MESH" and o.data.vertices and len(o.data.vertices) == len(positions)]
    check("armature", len(armatures) == 1 and len(meshes) == 1,
          f"{len(armatures)} armature(s) '{armatures[0].name if armatures else ''}', body mesh found: {bool(meshes)}")
    arm, body = armatures[0], meshes[0]
    bones = arm.data.bones
    same_names = [b.name for b in bones if b.name in names]
    parents_ok = all((bones[n].parent.name if bones[n].parent else None)
                     == (doc["nodes"][parent_node[joints[i]]]["name"] if parent_node.get(joints[i]) in joints else None)
                     for i, n in enumerate(names) if n in bones)
    check("bone names and parents", len(bones) == len(names) and len(same_names) == len(names) and parents_ok,
          f"{len(bones)} bones in Blender, {len(names)} joints in the file, all names kept: "
          f"{len(same_names) == len(names)}, parents kept: {parents_ok}")

    M = np.array([np.array(arm.matrix_world) @ np.array(bones[n].matrix_local) for n in names])  # Blender axes
    heads = np.array([e["head"] for e in extras]) @ TO_BLENDER.T
    tails = np.array([e["tail"] for e in extras]) @ TO_BLENDER.T
    d = (tails - heads) / np.linalg.norm(tails - heads, axis=1, keepdims=True)
    head_err = np.linalg.norm(M[:, :3, 3] - heads, axis=1).max()
    y_err = angle(M[:, :3, 1], d).max()
    frames = np.linalg.inv(ibm)[:, :3, :3]                       # the file's bind frames, glTF axes
    x_err = angle(M[:, :3, 0], frames[:, :, 0] @ TO_BLENDER.T).max()
    check("bone heads and axes", head_err < 1e-5 and y_err < 0.01 and x_err < 0.01,
          f"heads within {head_err * 1000:.4f} mm of extras.head, local +Y within {y_err:.4f} deg of head->tail, "
          f"local X (roll) within {x_err:.4f} deg of the file's")
    lengths = np.array([bones[n].length for n in names])
    true_lengths = np.linalg.norm(tails - heads, axis=1)
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode="EDIT")
    rolls = np.array([arm.data.edit_bones[n].roll for n in names])
    for i, n in enumerate(names):
        eb = arm.data.edit_bones[n]
        eb.tail = eb.head + (eb.tail - eb.head).normalized() * float(true_lengths[i])
    bpy.ops.object.mode_set(mode="OBJECT")
    roll_err = np.degrees(np.abs(np.angle(np.exp(1j * (rolls - np.array([e["roll"] for e in extras])))))).max()
    check("bone rolls", roll_err < 0.05, f"Blender's edit-bone rolls within {roll_err:.4f} deg of extras.roll")
    tail_err = np.linalg.norm(np.array([np.array(arm.matrix_world) @ np.r_[np.array(bones[n].tail_local), 1.0]
                                        for n in names])[:, :3] - tails, axis=1).max()
    check("bone tails rebuilt from extras", tail_err < 1e-5,
          f"Blender's own lengths differ from the file's by up to {np.abs(lengths - true_lengths).max() * 1000:.1f} mm; "
          f"after setting them from extras.tail the tails are within {tail_err * 1000:.4f} mm")

    groups = {g.index: g.name for g in body.vertex_groups}
    bone_of = {n: i for i, n in enumerate(names)}
    W_blender = np.zeros((len(positions), len(names)))
    for v in body.data.vertices:
        for g in v.groups:
            if g.weight > 0 and groups[g.group] in bone_of:
                W_blender[v.index, bone_of[groups[g.group]]] = g.weight
    W_file = np.zeros_like(W_blender)
    np.add.at(W_file, (np.repeat(np.arange(len(positions)), 4), file_joints.ravel()), file_weights.ravel())
    w_err = np.abs(W_blender - W_file).max()
    check("weights", w_err < 1e-6 and (np.count_nonzero(W_blender, axis=1) <= 4).all(),
          f"{len(body.vertex_groups)} vertex groups, weights within {w_err:.2g} of the file's 4 influences per vertex")

    keys = body.data.shape_keys.key_blocks if body.data.shape_keys else []
    key_names = [k.name for k in keys][1:]
    k_err = 0.0
    for name, delta in zip(target_names, targets):
        if name in keys:
            co = np.array([p.co for p in keys[name].data]) - np.array([p.co for p in keys[0].data])
            k_err = max(k_err, float(np.abs(co - delta @ TO_BLENDER.T).max()))
    check("shape keys", key_names == target_names and k_err < 1e-6,
          f"{key_names} (file: {target_names}), displacements within {k_err:.2g} m")

    # skinning: turn some bones in pose mode, evaluate the armature modifier, compare with LBS
    rng = np.random.default_rng(0)
    bpy.ops.object.mode_set(mode="POSE")
    for n in names:
        pb = arm.pose.bones[n]
        pb.rotation_mode = "XYZ"
        pb.rotation_euler = tuple(rng.normal(0.0, 0.25, 3)) if rng.random() < 0.5 else (0.0, 0.0, 0.0)
    arm.pose.bones[names[0]].rotation_euler = (0.2, 0.5, -0.3)
    bpy.ops.object.mode_set(mode="OBJECT")
    bpy.context.view_layer.update()
    depsgraph = bpy.context.evaluated_depsgraph_get()
    evaluated = body.evaluated_get(depsgraph)
    posed = np.array([np.array(body.matrix_world) @ np.r_[np.array(v.co), 1.0] for v in evaluated.data.vertices])[:, :3]
    P = np.array([np.array(arm.matrix_world) @ np.array(arm.pose.bones[n].matrix) for n in names])  # Blender axes
    T = np.eye(4)
    T[:3, :3] = TO_BLENDER
    # A bone's rest matrix in Blender is T . bind (its columns, the bone's axes, carried to
    # Blender's world axes; bone-local axes stay Blender's), so its skinning matrix is
    # posed . (T . bind)^-1 = posed . inverse bind . T^T.
    S = P @ ibm @ T.T
    rest = np.c_[positions @ TO_BLENDER.T, np.ones(len(positions))]
    expected = np.einsum("vk,vkij,vj->vi", file_weights, S[file_joints], rest)[:, :3]
    p_err = np.linalg.norm(posed - expected, axis=1).max()
    moved = np.linalg.norm(posed - rest[:, :3], axis=1).max()
    check("skinning", p_err < 1e-4 and moved > 0.05,
          f"Blender's armature modifier on a pose of {len(names)} bones (up to {moved:.2f} m moved) equals LBS of the "
          f"file's weights and inverse bind matrices within {p_err * 1000:.4f} mm")
    bpy.ops.object.mode_set(mode="POSE")
    bpy.ops.pose.select_all(action="SELECT")
    bpy.ops.pose.transforms_clear()
    bpy.ops.object.mode_set(mode="OBJECT")
    evaluated = body.evaluated_get(bpy.context.evaluated_depsgraph_get())
    rest_err = np.abs(np.array([np.array(body.matrix_world) @ np.r_[np.array(v.co), 1.0]
                                for v in evaluated.data.vertices])[:, :3] - rest[:, :3]).max()
    check("rest pose", rest_err < 1e-5, f"the rest pose gives the file's vertices within {rest_err * 1000:.4f} mm")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"file": args.glb, "blender": bpy.app.version_string, "checks": results}, fh, indent=1)
    failed = [r["check"] for r in results if not r["ok"]]
    print(f"Blender {bpy.app.version_string}: {len(results) - len(failed)} passed, {len(failed)} failed")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
