"""Skinning throughput in vertex-frames per second: compiled LBS / DQS against the plain numpy path
(the code before issue 13, kept as ``kinematics.*_numpy``), beside this machine's memory-bandwidth
bound measured in the same run.

Cases: one 13,380-vertex body over 1,000 frames of the default rig (163 bones), and a batch of
100 bodies x 10 frames (per-body rest meshes). The bound: a compiled streaming write of an
output-sized array on both cores (GB/s), divided by the bytes a vertex-frame writes (24 for
float64, 12 for float32); beside it the bound of non-temporal stores (no read of a line before
it is written). Each kernel is timed in float64 and float32 output (the arithmetic is done in the
output's dtype), on two lanes (wall clock) and on one lane in CPU seconds of its thread
(``time.thread_time``: less disturbed by other jobs on a shared machine).

Run: python benchmarks/bench_skinning.py [--frames 1000]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numba
import numpy as np
from llvmlite import ir
from numba.core import types
from numba.extending import intrinsic

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import best_time, report  # noqa: E402

from bodyspace.data.template import load_template  # noqa: E402
from bodyspace.parallel import halves, run_both  # noqa: E402
from bodyspace.rig.kinematics import (  # noqa: E402
    dual_quaternion_skinning_numpy,
    forward_kinematics,
    forward_kinematics_numpy,
    linear_blend_skinning_numpy,
    rotvec_to_matrix,
)
from bodyspace.rig.posing import pose_bodies  # noqa: E402
from bodyspace.rig.skinning import dual_quaternion_skinning, linear_blend_skinning  # noqa: E402
from bodyspace.synth.phenotype import PARAMETERS, PhenotypeModel  # noqa: E402
from bodyspace.synth.poses import load_pose_library  # noqa: E402


@numba.njit(nogil=True, cache=True)
def _stream_write(flat, start, stop):
    for i in range(start, stop):
        flat[i] = 1.0


@intrinsic
def _store4_nontemporal(typingctx, array, index, value):
    """``array[index:index+4] = value`` as one non-temporal (streaming) vector store: the line
    goes to memory without being read first. ``&array[index]`` must be 32-byte aligned."""
    sig = types.void(array, index, value)

    def codegen(context, builder, signature, args):
        data = context.make_array(signature.args[0])(context, builder, args[0]).data
        vec = ir.VectorType(ir.DoubleType(), 4)
        v = builder.insert_element(ir.Constant(vec, None), args[2], ir.Constant(ir.IntType(32), 0))
        v = builder.shuffle_vector(v, ir.Constant(vec, None), ir.Constant(ir.VectorType(ir.IntType(32), 4), [0] * 4))
        st = builder.store(v, builder.bitcast(builder.gep(data, [args[1]]), vec.as_pointer()), align=32)
        st.set_metadata("nontemporal", builder.module.add_metadata([ir.Constant(ir.IntType(32), 1)]))
        return context.get_dummy_value()
    return sig, codegen


@numba.njit(nogil=True)
def _stream_write_nontemporal(flat, start, stop):
    for i in range(start, stop, 4):
        _store4_nontemporal(flat, i, 1.0)


def write_bandwidth(nbytes: int, nontemporal: bool = False) -> float:
    """GB/s of a compiled streaming write of ``nbytes`` (already touched) on both cores: plain
    stores (each line read before it is written), or non-temporal vector stores (no read; the
    most this machine's memory takes)."""
    flat = np.zeros(nbytes // 8 + 8)
    off = (-(flat.ctypes.data // 8)) % 4                      # 32-byte aligned start
    n = (nbytes // 8) // 8 * 8
    (a0, a1), (b0, b1) = halves(n // 4)
    kernel = _stream_write_nontemporal if nontemporal else _stream_write
    a0, a1, b0, b1 = off + 4 * a0, off + 4 * a1, off + 4 * b0, off + 4 * b1
    fn = lambda: run_both(lambda: kernel(flat, a0, a1), lambda: kernel(flat, b0, b1))  # noqa: E731
    fn()
    return nbytes / best_time(fn, 5) / 1e9


def frames_of(library, rig, n: int, rng) -> np.ndarray:
    """(n, B, 3, 3) rotations: the library's poses in turn, each bone jittered a little so no
    two frames are equal (an animation, not 25 repeated poses)."""
    base = library.stack([library.names[i % len(library.names)] for i in range(n)], rig)
    return base @ rotvec_to_matrix(rng.normal(scale=0.02, size=base.shape[:2] + (3,)))


def main(frames: int = 1000) -> None:
    rng = np.random.default_rng(0)
    template = load_template()
    rig = template.rigs["default"]
    W = rig.weights
    library = load_pose_library()
    body = PhenotypeModel(template).vertices({"gender": 1.0})[0]
    V = body.shape[0]
    R = frames_of(library, rig, frames, rng)
    heads = rig.heads(body)
    vf = frames * V
    print(f"one body, {V:,} vertices, {frames:,} frames, {rig.n_bones} bones, {W.nnz:,} weights; "
          f"numba threading: bodyspace.parallel (2 lanes)")

    gbps = write_bandwidth(vf * 24)
    nt_gbps = write_bandwidth(vf * 24, nontemporal=True)
    bound = {np.dtype(np.float64): gbps * 1e9 / 24, np.dtype(np.float32): gbps * 1e9 / 12}
    nt_bound = {np.dtype(np.float64): nt_gbps * 1e9 / 24, np.dtype(np.float32): nt_gbps * 1e9 / 12}
    print(f"memory bandwidth (compiled streaming write, 2 cores): {gbps:.1f} GB/s -> bound "
          f"{bound[np.dtype(np.float64)] / 1e6:,.0f} M vertex-frames/s for float64 output, "
          f"{bound[np.dtype(np.float32)] / 1e6:,.0f} M for float32")
    print(f"  with non-temporal stores (no read before write): {nt_gbps:.1f} GB/s -> "
          f"{nt_gbps * 1e9 / 24 / 1e6:,.0f} M (float64), {nt_gbps * 1e9 / 12 / 1e6:,.0f} M (float32)")

    fk = best_time(lambda: forward_kinematics(R, heads, rig.parents), 5)
    fk_np = best_time(lambda: forward_kinematics_numpy(R, heads, rig.parents), 1)
    report(f"forward kinematics, {frames} frames", fk, fk_np, frames, "frames")
    G = forward_kinematics(R, heads, rig.parents)

    out64 = np.zeros((frames, V, 3))
    out32 = np.zeros((frames, V, 3), dtype=np.float32)
    lbs_np = best_time(lambda: linear_blend_skinning_numpy(body, W, G), 1)
    for name, compiled, baseline_s in (("LBS", linear_blend_skinning, lbs_np),
                                       ("DQS", dual_quaternion_skinning, None)):
        if baseline_s is None:
            baseline_s = best_time(lambda: dual_quaternion_skinning_numpy(body, W, G), 1)
        ref = compiled(body, W, G)
        for out in (out64, out32):
            t = best_time(lambda: compiled(body, W, G, out=out), 5)
            report(f"{name} {out.dtype}, out= (written in place)", t, baseline_s, vf, "vertex-frames")
            print(f"  {100 * vf / t / bound[out.dtype]:.0f} % of the plain-store bound, "
                  f"{100 * vf / t / nt_bound[out.dtype]:.0f} % of the non-temporal bound for {out.dtype} output")
            t1 = best_time(lambda: compiled(body, W, G, out=out, lanes=1), 3, clock=time.thread_time)
            print(f"  {name} {out.dtype} one lane: {vf / t1 / 1e6:,.0f} M vertex-frames per CPU second")
        t = best_time(lambda: compiled(body, W, G), 3)
        report(f"{name} float64, new output array each call", t, baseline_s, vf, "vertex-frames")
        del ref

    t_new = best_time(lambda: pose_bodies(body, rig, R), 3)

    def numpy_pipeline():
        Gn = forward_kinematics_numpy(R, heads, rig.parents)
        return linear_blend_skinning_numpy(body, W, Gn)
    t_old = best_time(numpy_pipeline, 1)
    report("pose_bodies one body over the frames (heads + FK + LBS)", t_new, t_old, vf, "vertex-frames")
    t32 = best_time(lambda: pose_bodies(body, rig, R, dtype=np.float32), 3)
    report("pose_bodies, float32 output", t32, t_old, vf, "vertex-frames")

    # a batch of 100 bodies x 10 frames: per-body rest meshes
    n_bodies, per = 100, 10
    bodies = PhenotypeModel(template).vertices(rng.random((n_bodies, len(PARAMETERS))))
    rest = np.repeat(bodies, per, axis=0)
    Rb = frames_of(library, rig, n_bodies * per, rng)
    Gb = forward_kinematics(Rb, rig.heads(rest), rig.parents)
    vfb = n_bodies * per * V
    for name, compiled, reference in (("LBS", linear_blend_skinning, linear_blend_skinning_numpy),
                                      ("DQS", dual_quaternion_skinning, dual_quaternion_skinning_numpy)):
        tn = best_time(lambda: reference(rest, W, Gb), 1)
        for dtype in (np.float64, np.float32):
            outb = np.zeros((n_bodies * per, V, 3), dtype=dtype)
            t = best_time(lambda: compiled(rest, W, Gb, out=outb), 3)
            report(f"{name} {n_bodies} bodies x {per} frames (per-body rest), {outb.dtype} out=", t, tn, vfb,
                   "vertex-frames")
    print(f"measured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, load average "
          f"{', '.join(f'{x:.1f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000)
    main(parser.parse_args().frames)
