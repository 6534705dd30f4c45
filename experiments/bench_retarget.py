"""Benchmark blendshape retargeting: the jitted projected-Newton solve of a clip onto the built-in ARKit rig.

A clip of ``--frames`` frames of the rig's own random animation (each of the 52 weights on in 30 % of
frames) is retargeted through :class:`jaxtalk.export.Retargeter` on the rig's own mesh. Reported: the
first call (tracing + compile + solve), then over ``--repeats`` calls the median and minimum of the
solve alone (``RetargetResult.seconds``, which ends with ``block_until_ready``) and of the whole call
(registration-free host work, right-hand sides and the solve), the most Newton steps a frame took and the
fit's RMS error. The solve is a loop over frames of small (52 x 52) factorisations and products,
latency-bound rather than FLOP-bound, so it is reported as frames per second of solve time, not against
the matmul peak.

Usage: python experiments/bench_retarget.py [--frames 250 1000] [--repeats 10] [--resolution low]
    [--out experiments/results/bench_retarget.json]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from jaxtalk import benchmarking as bm
from jaxtalk.export import Retargeter, arkit_rig
from jaxtalk.face import builtin_face


def rig_animation(frames: int, seed: int) -> np.ndarray:
    """Random weights in [0, 1], each shape on in about 30 % of frames."""
    rng = np.random.default_rng(seed)
    return rng.uniform(0.0, 1.0, size=(frames, 52)) * (rng.uniform(size=(frames, 52)) < 0.3)


def bench(frames: int, repeats: int, resolution: str, seed: int) -> dict:
    rig = arkit_rig(resolution)
    retargeter = Retargeter.for_mesh(rig, rig.neutral, rig.faces, template=builtin_face(0, resolution=resolution))
    verts = rig.vertices(rig_animation(frames, seed))
    start = time.perf_counter()
    first = retargeter(verts)
    first_call = time.perf_counter() - start
    solves, calls = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        result = retargeter(verts)
        calls.append(time.perf_counter() - start)
        solves.append(result.seconds)
    solve = statistics.median(solves)
    return {"frames": frames, "vertices": int(rig.neutral.shape[0]), "first_call_s": first_call,
            "solve_median_s": solve, "solve_min_s": min(solves), "call_median_s": statistics.median(calls),
            "solve_frames_per_s": frames / solve, "iterations": result.iterations,
            "rms_error_m": result.rms_error, "first_call_iterations": first.iterations}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[250, 1000])
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--resolution", default="low")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--out", default="experiments/results/bench_retarget.json")
    args = parser.parse_args()
    rows = [bench(n, args.repeats, args.resolution, args.seed) for n in args.frames]
    bm.print_table(rows, "Retargeting onto the built-in ARKit rig (seconds)")
    bm.write_json(args.out, {"rows": rows, "repeats": args.repeats, "seed": args.seed,
                             "resolution": args.resolution})


if __name__ == "__main__":
    main()
