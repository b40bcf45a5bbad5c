"""Skin weights compared over the whole pose library: MakeHuman's CC0 weights as shipped, the
smoothed ones (``weights="smoothed"``) and bone heat (``weights="bone_heat"``, Baran & Popović
2007, with the template's rules ``posing.template_heat_rules``), and the plain bone heat any mesh
gets (no rules) with its cut to four bones smoothed within each bone's support (the default) and
with the cut alone (``smoothing=0``), all with linear blend (or ``--skinning dqs`` dual-quaternion)
skinning of the default rig on the template topology.

Per pose, summed or worst over a few bodies: folded triangles added to the rest mesh
(``count_folded_triangles``), the change of the enclosed volume (``capped_volume``), and the
chest girth change in ``arms_overhead`` (the hm08 measurement set). Prints markdown tables.
``--volume`` adds, for every weight set, the same skinning followed by the volume-preserving
correction (``rig.volume.preserve_volume``, ``pose_bodies(..., preserve_volume=True)``), and the
time of the correction against the skinning alone in the same run.

Run: python benchmarks/compare_skin_weights.py [--influences 4] [--heat 1.0] [--smoothing 0.03] [--skinning lbs]
[--bodies paper|train|other|heldout] [--volume]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bodyspace.data.template import load_template
from bodyspace.measure.definitions import load_measurement_set
from bodyspace.measure.evaluate import measure
from bodyspace.mesh.geometry import capped_volume
from bodyspace.rig.kinematics import forward_kinematics
from bodyspace.rig.posing import count_folded_triangles, smoothed_weights, template_heat_rules
from bodyspace.rig.skinning import dual_quaternion_skinning, linear_blend_skinning
from bodyspace.rig.volume import preserve_volume, volume_rig
from bodyspace.rig.weights import DEFAULT_SMOOTHING, bone_heat_weights
from bodyspace.synth.phenotype import PhenotypeModel
from bodyspace.synth.poses import load_pose_library

# The three bodies of tests/test_rig.py and docs/poses.md: male average, female average,
# heavy male with no muscle.
BODIES = {"gender": [1.0, 0.0, 1.0], "weight": [0.5, 0.5, 1.0], "muscle": [0.5, 0.5, 0.0],
          "height": [0.6, 0.4, 0.5]}
# Three more training bodies (muscular heavy short woman, slight short man, a muscular middle
# body): with BODIES, the six bodies the template's rules are chosen on (``--bodies train``).
TRAIN_EXTRA = {"gender": [0.0, 1.0, 0.3], "weight": [0.8, 0.3, 0.4], "muscle": [0.8, 0.3, 0.9],
               "height": [0.2, 0.2, 0.7]}
# Four other bodies (heavy short woman, muscular tall lean man, lean tall woman, a middle body),
# not used to choose the template's bone-heat rules: a held-out check of them (``--bodies other``).
OTHER_BODIES = {"gender": [0.0, 1.0, 0.0, 0.5], "weight": [1.0, 0.2, 0.2, 0.7], "muscle": [0.2, 1.0, 0.5, 0.5],
                "height": [0.3, 0.9, 0.8, 0.5]}
# Eight more held-out bodies: the half fraction 2^(4-1) of sex x weight x muscle x height at 0.1 / 0.9
# (height = sex XOR weight XOR muscle), so every pair of the four spans its four corners.
_SEX, _WEIGHT, _MUSCLE = (np.array(c, dtype=float) for c in np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"))
_HEIGHT = (_SEX + _WEIGHT + _MUSCLE) % 2
HELD_OUT_EXTRA = {k: list(0.1 + 0.8 * a.ravel()) for k, a in
                  (("gender", _SEX), ("weight", _WEIGHT), ("muscle", _MUSCLE), ("height", _HEIGHT))}


def body_set(name: str) -> dict:
    """Phenotypes of a named set: "paper" (BODIES), "train" (BODIES + TRAIN_EXTRA, the six the rules
    are chosen on), "other" (OTHER_BODIES), "heldout" (OTHER_BODIES + HELD_OUT_EXTRA, twelve)."""
    join = lambda a, b: {k: list(a[k]) + list(b[k]) for k in a}           # noqa: E731
    return {"paper": BODIES, "train": join(BODIES, TRAIN_EXTRA), "other": OTHER_BODIES,
            "heldout": join(OTHER_BODIES, HELD_OUT_EXTRA)}[name]

def weight_sets(template, rig, influences: int, heat: float, smoothing: float) -> dict:
    """name → (V, B) weights; bone heat on the template's mean body: plain (MakeHuman's deforming
    bones, no mask: what any mesh gets), and with the template's rules (``template_heat_rules``:
    hip helper bones out, jaw on the chin, no upper arm on the torso farther than 10 cm from the
    armpit loop (and the earlier 6 cm height line, ``armpit="height"``), arm twist bones heated
    with the bone they twist, the rib cage's bones one group through the cut to four bones (and
    the rules without it, ``chest_group=False``); what
    ``pose_bodies(weights="bone_heat")`` uses)."""
    v = template.vertices
    deform = np.asarray(abs(rig.weights).sum(axis=0)).ravel() > 0
    args = (v, template.faces, rig.heads(v), rig.tails(v), influences)
    cut = bone_heat_weights(*args, deform=deform, heat=heat, smoothing=0.0)
    plain = bone_heat_weights(*args, deform=deform, heat=heat, smoothing=smoothing)
    height_line = bone_heat_weights(*args, **template_heat_rules(rig, v, template.faces, armpit="height",
                                                                 chest_group=False), heat=heat, smoothing=smoothing)
    no_group = bone_heat_weights(*args, **template_heat_rules(rig, v, template.faces, chest_group=False),
                                 heat=heat, smoothing=smoothing)
    rules = template_heat_rules(rig, v, template.faces)
    t = time.perf_counter()
    heat_w = bone_heat_weights(*args, **rules, heat=heat, smoothing=smoothing)
    print(f"bone heat with the template's rules: {time.perf_counter() - t:.2f} s, {heat_w.nnz:,} weights "
          f"(MakeHuman's {rig.weights.nnz:,}, smoothed {smoothed_weights(rig).nnz:,})")
    return {"MakeHuman": rig.weights, "smoothed": smoothed_weights(rig), "bone heat, cut only": cut,
            "bone heat, no rules": plain, "bone heat, armpit height line": height_line,
            "bone heat, no chest group": no_group, "bone heat": heat_w}


def evaluate(template, rig, library, bodies, weights, skinning: str = "lbs", volume: bool = False) -> dict:
    """Per weight set: folds added (P, N), volume change (P, N) and chest change in arms_overhead (N,);
    with ``volume`` also each set with the volume correction ("name + volume"), and the seconds
    spent skinning and correcting."""
    faces = template.faces
    R = library.stack(library.names, rig)
    mset = load_measurement_set()
    k = library.names.index("arms_overhead")
    skin = dual_quaternion_skinning if skinning == "dqs" else linear_blend_skinning
    out = {}
    timing = {"skinning": 0.0, "volume": 0.0}
    for name, W in weights.items():
        for corrected in ((False, True) if volume else (False,)):
            out[name + (" + volume" if corrected else "")] = _evaluate_set(
                template, rig, library, bodies, W, R, mset, k, skin, corrected, timing)
    if volume:
        print(f"skinning {timing['skinning']:.2f} s, volume correction {timing['volume']:.2f} s "
              f"(x{timing['volume'] / max(timing['skinning'], 1e-9):.1f} the skinning's time)")
    return out


def _evaluate_set(template, rig, library, bodies, W, R, mset, k, skin, corrected, timing):
    """(folds (P, N), volume change (P, N), chest change (N,)) of one weight set W over the bodies."""
    faces = template.faces
    folds, volume, chest = [], [], []
    vrig = volume_rig(W, rig.parents, faces) if corrected else None
    for body in bodies:
        G = forward_kinematics(R, rig.heads(body), rig.parents)
        t = time.perf_counter()
        posed = skin(body, W, G)
        timing["skinning"] += time.perf_counter() - t
        if corrected:
            t = time.perf_counter()
            preserve_volume(posed, body[None], G, rig.heads(body)[None], rig.tails(body)[None], vrig)
            timing["volume"] += time.perf_counter() - t
        folds.append(count_folded_triangles(posed, faces) - count_folded_triangles(body, faces))
        volume.append(capped_volume(posed, faces) / capped_volume(body, faces) - 1.0)
        girth = measure(mset, np.stack([body, posed[k]]), faces)["chest_girth"]
        chest.append(girth[1] - girth[0])
    return np.array(folds).T, np.array(volume).T, np.array(chest)


def print_tables(names, results) -> None:
    sets = list(results)
    print("\n| pose | " + " | ".join(f"folds {s}" for s in sets) + " | " +
          " | ".join(f"volume {s}" for s in sets) + " |")
    print("|---" * (1 + 2 * len(sets)) + "|")
    for p, pose in enumerate(names):
        folds = [f"{int(np.clip(results[s][0][p], 0, None).sum())}" for s in sets]
        vols = []
        for s in sets:
            v = results[s][1][p]
            vols.append(f"{100 * v[np.argmax(np.abs(v))]:+.1f} %")
        print(f"| `{pose}` | " + " | ".join(folds) + " | " + " | ".join(vols) + " |")
    print("\n| weights | folds added (all poses, all bodies) | fold-free poses | worst volume change | "
          "poses within 2 % volume | chest girth change in arms_overhead (per body) |")
    print("|---|---|---|---|---|---|")
    for s in sets:
        folds, vol, chest = results[s]
        worst = np.abs(vol).max(axis=1)
        print(f"| {s} | {int(np.clip(folds, 0, None).sum())} | {int((folds.max(axis=1) <= 0).sum())} / {len(names)} | "
              f"{100 * vol.flat[np.argmax(np.abs(vol))]:+.1f} % ({names[int(np.argmax(worst))]}) | "
              f"{int((worst <= 0.02).sum())} / {len(names)} | "
              + ", ".join(f"{100 * c:+.1f} cm" for c in chest) + " |")


def main(influences: int = 4, heat: float = 1.0, smoothing: float = DEFAULT_SMOOTHING, skinning: str = "lbs",
         bodies: str = "paper", volume: bool = False) -> None:
    template = load_template()
    rig = template.rigs["default"]
    library = load_pose_library()
    bodies_name, phenotypes = bodies, body_set(bodies)
    bodies = PhenotypeModel(template).vertices(phenotypes)
    print(f"{len(bodies)} bodies ({bodies_name}) x {len(library.names)} poses, {skinning.upper()}, default rig; "
          f"bone heat with at most {influences} influences, c = {heat}, smoothing {smoothing}")
    results = evaluate(template, rig, library, bodies, weight_sets(template, rig, influences, heat, smoothing),
                       skinning, volume)
    print_tables(library.names, results)
    print(f"\nmeasured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--influences", type=int, default=4)
    parser.add_argument("--heat", type=float, default=1.0)
    parser.add_argument("--smoothing", type=float, default=DEFAULT_SMOOTHING)
    parser.add_argument("--skinning", choices=("lbs", "dqs"), default="lbs")
    parser.add_argument("--bodies", choices=("paper", "train", "other", "heldout"), default="paper",
                        help="paper: the three of docs/poses.md; train: those and three more (the rules are chosen "
                             "on these six); other: four held-out bodies; heldout: those and eight more (twelve)")
    parser.add_argument("--other-bodies", action="store_true", help="the same as --bodies other")
    parser.add_argument("--volume", action="store_true", help="also each weight set with the volume correction")
    a = parser.parse_args()
    main(a.influences, a.heat, a.smoothing, a.skinning, "other" if a.other_bodies else a.bodies, a.volume)
