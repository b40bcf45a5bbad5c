"""``bodyspace motion info CLIP.bvh`` and ``bodyspace motion match CLIP.bvh --rig NAME`` (or
``--target OTHER.bvh``): what a motion capture clip holds, and which of its joints drives which
bone of a rig (Rupprecht §3.3.2), with ``--map`` overrides and a JSON report."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from bodyspace.atomic import WRITTEN_BY, write_json
from bodyspace.cli.common import ForceOption, check_file_output, console, guarded, out_console
from bodyspace.data.template import RIG_NAMES
from bodyspace.errors import MotionError
from bodyspace.motion.bvh import UNITS, read_bvh
from bodyspace.motion.matching import graph_from_motion, load_joint_map, match_skeletons, rig_graph

BvhUnitOption = typer.Option("auto", "--bvh-unit", help="Length unit of the BVH file (it has no unit field): auto "
                                                      "(from the skeleton's size), " + ", ".join(UNITS)
                                                      + " (cmu = 1/0.45 inch), or metres per file unit.")


def motion_info(clip: Path = typer.Argument(..., help="A BVH motion capture file."),
                bvh_unit: str = BvhUnitOption) -> None:
    """What a BVH clip holds: joints, channels and their orders, frames, rate, unit, size."""
    motion = read_bvh(clip, unit=bvh_unit)
    sk = motion.skeleton
    orders = Counter(sk.rotation_order(j) or "none" for j in range(sk.n_joints))
    moving = [n for n, ch in zip(sk.names, sk.channels) if any(c.endswith("position") for c in ch)]
    rest = np.vstack([motion.rest_positions(), sk.rest_end_sites() * motion.unit])
    root = motion.local_translations()[:, 0]
    path = float(np.linalg.norm(np.diff(root, axis=0), axis=1).sum()) if motion.n_frames > 1 else 0.0
    more = ", ..." if sk.n_joints > 6 else ""
    rows = [("file", str(clip)), ("joints", f"{sk.n_joints} ({', '.join(sk.names[:6])}{more})"),
            ("end sites", str(len(sk.end_sites))), ("channels", f"{sk.n_channels} per frame"),
            ("rotation orders", ", ".join(f"{o} x{c}" for o, c in orders.most_common())),
            ("translation channels", f"{', '.join(moving) or 'none'} ({motion.translation} the offset)"),
            ("frames", f"{motion.n_frames} at {motion.fps:.6g} per second ({motion.frame_time:.6g} s), "
                       f"{motion.duration:.2f} s"),
            ("unit", f"{motion.unit:.6g} m per file unit ({motion.unit_note})"),
            ("rest skeleton extent", f"{(rest.max(0) - rest.min(0)).max() * 100:.1f} cm"),
            ("root travels", f"{path * 100:.1f} cm")]
    for key, value in rows:
        out_console.print(f"{key + ':':<22}{value}", highlight=False, soft_wrap=True)


def motion_match(clip: Path = typer.Argument(..., help="The source BVH clip."),
                 rig: Optional[str] = typer.Option(None, "--rig", help="Target: a CC0 rig, one of "
                                                   + ", ".join(RIG_NAMES) + "."),
                 target: Optional[Path] = typer.Option(None, "--target", help="Target: another BVH file."),
                 joint_map: Optional[Path] = typer.Option(None, "--map", help="JSON object {\"source joint\": "
                                                          "\"target bone\" or null} overriding the structural match."),
                 json_out: Optional[Path] = typer.Option(None, "--json", help="Also write the match as JSON "
                                                         "(pairs, unmatched with reasons, segments, landmarks, axes)."),
                 bvh_unit: str = BvhUnitOption, force: bool = ForceOption) -> None:
    """Match a clip's skeleton to a rig or another clip by structure; print what matched what,
    what was left unmatched and why."""
    if (rig is None) == (target is None):
        raise MotionError("give one target: --rig NAME (" + ", ".join(RIG_NAMES) + ") or --target OTHER.bvh")
    if rig is not None and rig not in RIG_NAMES:
        raise MotionError(f"--rig {rig!r}: not a CC0 rig; expected one of {', '.join(RIG_NAMES)}")
    if json_out is not None:
        check_file_output(json_out, "--json", force, (".json",), example="match.json")
    source = graph_from_motion(read_bvh(clip, unit=bvh_unit))
    goal = rig_graph(rig) if rig is not None else graph_from_motion(read_bvh(target, unit=bvh_unit))
    overrides = load_joint_map(joint_map, source, goal) if joint_map is not None else None
    result = match_skeletons(source, goal, overrides)
    out_console.print(result.report(), highlight=False, soft_wrap=True, markup=False)
    if json_out is not None:
        write_json(json_out, {"written_by": WRITTEN_BY, **result.to_dict()})
        console.print(f"wrote {json_out}", highlight=False)


# The ``bodyspace motion`` group; the dispatcher (bodyspace.cli) loads it when ``motion`` is run.
app = typer.Typer(name="motion", add_completion=False, no_args_is_help=True,
                  help="Motion capture (BVH): inspect a clip, match its skeleton to a rig.")
for _name, _command in (("info", motion_info), ("match", motion_match)):
    app.command(_name)(guarded(_command))
