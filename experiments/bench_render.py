"""Benchmark the headless renderer: frames per second on one CPU core, and a 10-s clip to mp4.

Part 1: ``render_frame`` (with the mouth cavity from the rest pose) of the built-in face (low ~1k,
default ~3.7k, high ~5.9k vertices) at 256 and 512 px, with and without 2x supersampling; wall and
process-CPU time per frame (median of
repeats, after a warm-up frame). Process CPU time is reported because the machine is shared: wall
time is inflated by other jobs, CPU time much less. Target: >= 10 frames/s at 256-512 px.
Part 2: a 10-s clip (250 frames, jaw and lips moving, 16 kHz audio) rendered and encoded to mp4
with ``render_clip`` at 256 px: total wall time.

The renderer is single-threaded NumPy; run with OMP/BLAS threads at 1 to measure one core.

Usage: python experiments/bench_render.py [--out PATH] [--repeats N] [--skip-clip]
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

from jaxtalk import benchmarking as bm
from jaxtalk.face import builtin_face
from jaxtalk.layout import JAW_OPEN_INDEX
from jaxtalk.render import RenderStyle, fit_camera, render_clip, render_frame


def _talking_params(num_frames: int) -> np.ndarray:
    t = np.arange(num_frames) / 25.0
    params = np.zeros((num_frames, 56), np.float32)
    params[:, JAW_OPEN_INDEX] = 0.18 * (1 + np.sin(2 * np.pi * 3.1 * t)) / 2
    params[:, 1] = 1.5 * np.sin(2 * np.pi * 1.3 * t)  # lip_round
    params[:, 54] = 0.05 * np.sin(2 * np.pi * 0.4 * t)  # neck yaw
    return params


def bench_frames(repeats: int) -> list[dict]:
    rows = []
    for resolution in ("low", "default", "high"):
        face = builtin_face(resolution=resolution)
        verts = np.asarray(face.vertices_seq(_talking_params(repeats + 1)))
        faces = np.asarray(face.faces)
        for size in (256, 512):
            for supersample in (1, 2):
                style = RenderStyle(supersample=supersample)
                camera = fit_camera(verts, width=size, height=size)
                rest = np.asarray(face.template)
                render_frame(verts[0], faces, camera, style=style, rest_vertices=rest)  # warm-up
                wall, cpu = [], []
                for k in range(1, repeats + 1):
                    w0, c0 = time.perf_counter(), time.process_time()
                    render_frame(verts[k], faces, camera, style=style, rest_vertices=rest)
                    wall.append(time.perf_counter() - w0)
                    cpu.append(time.process_time() - c0)
                w, c = statistics.median(wall), statistics.median(cpu)
                rows.append(
                    {
                        "mesh": resolution,
                        "verts": face.num_vertices,
                        "tris": int(faces.shape[0]),
                        "size": size,
                        "ssaa": supersample,
                        "wall_ms": 1e3 * w,
                        "cpu_ms": 1e3 * c,
                        "fps_wall": 1 / w,
                        "fps_cpu": 1 / c,
                    }
                )
                bm.print_table(rows[-1:], "")
    return rows


def bench_clip() -> dict:
    face = builtin_face()
    params = _talking_params(250)
    verts = np.asarray(face.vertices_seq(params))
    audio = (0.1 * np.sin(2 * np.pi * 180 * np.arange(160_000) / 16_000)).astype(np.float32)
    with tempfile.TemporaryDirectory() as tmp:
        w0, c0 = time.perf_counter(), time.process_time()
        out = render_clip(
            Path(tmp) / "clip.mp4", verts, np.asarray(face.faces), audio=audio, size=256,
            rest_vertices=np.asarray(face.template),
        )  # fmt: skip
        wall, cpu = time.perf_counter() - w0, time.process_time() - c0
        size_kb = out.stat().st_size / 1024
    return {"frames": 250, "size": 256, "verts": face.num_vertices, "wall_s": wall, "cpu_s_python": cpu, "mp4_kb": size_kb}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="experiments/results/bench_render.json")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--skip-clip", action="store_true")
    args = parser.parse_args()
    rows = bench_frames(args.repeats)
    bm.print_table(rows, "render_frame (median per frame)")
    payload = {"frames": rows}
    if not args.skip_clip:
        clip = bench_clip()
        bm.print_table([clip], "10-s clip -> mp4 with audio (render_clip)")
        payload["clip"] = clip
    print("written", bm.write_json(args.out, payload))


if __name__ == "__main__":
    main()
