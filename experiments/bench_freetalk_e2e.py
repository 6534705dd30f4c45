"""Benchmark FreeTalk end to end: seconds of compute per second of audio on meshes of ~5k, ~25k and
~100k vertices, the per-mesh precompute reported apart.

Meshes: the built-in face at "high" resolution (5.9k vertices), subdivided once (23.5k) and twice
(94k) with trimesh, and the 94k mesh cut into 40 separate strips (a broken scan), each in
millimetres, rotated and shifted, so the whole user path runs
(:func:`jaxtalk.models.freetalk.animate.prepare_user_mesh`: cleaning, unit detection, PCA + ICP
alignment, Laplacian + eigenbasis + gradients, STM's static features). Models at random weights
(speed does not depend on them), ``small`` presets (``--paper``: STM ``paper`` too).

Per mesh, for a 4-s utterance: ATS (DDIM with ``--ddim-steps``, the whole utterance in cross-faded
windows of ``--window`` frames), STM (all frames, decoded 25 at a time) and their sum, each as compile
time (first call minus a warm call) and run time (median of ``--repeats`` warm calls,
``block_until_ready`` through ``np.asarray``), then seconds per second of audio and the real-time
factor (below 1: faster than real time). STM's FLOPs (XLA's count of one frame times the frames) and
the achieved GFLOP/s are shown next to the float32 matmul peak measured in the same run.

Usage: python experiments/bench_freetalk_e2e.py [--repeats N] [--seconds S] [--paper] [--out PATH]
"""

from __future__ import annotations

import argparse
import functools
import time
from pathlib import Path

import jax
import numpy as np

from jaxtalk import benchmarking as bm
from jaxtalk.bench import _median_time
from jaxtalk.face import builtin_face
from jaxtalk.models.freetalk import animate as ft
from jaxtalk.models.freetalk import ats, stm
from jaxtalk.models.freetalk.config import ATSConfig, STMConfig
from jaxtalk.models.freetalk.data import DisplacementStats
from jaxtalk.models.freetalk.fit import FittedATS, FittedSTM


def meshes() -> list[tuple[str, np.ndarray, np.ndarray]]:
    import trimesh
    from scipy.spatial.transform import Rotation

    face = builtin_face(0, resolution="high")
    v, f = np.asarray(face.template, np.float64), np.asarray(face.faces)
    out = []
    rotation = Rotation.from_euler("xyz", [15, -40, 5], degrees=True).as_matrix()
    for level in range(3):
        if level:
            v, f = trimesh.remesh.subdivide(v, f)
        out.append((f"face x{4 ** level}", 1000.0 * (v @ rotation.T + [0.1, 0.2, -0.3]), f))
    # The ~100k mesh cut into 40 vertical strips, each a separate component (vertices duplicated along
    # the cuts): a broken scan, which must animate like the whole one.
    strip = np.clip((np.argsort(np.argsort(v[f].mean(axis=1)[:, 0])) * 40) // len(f), 0, 39)
    pieces_v, pieces_f, offset = [], [], 0
    for k in range(40):
        ff = f[strip == k]
        used, local = np.unique(ff, return_inverse=True)
        pieces_v.append(v[used])
        pieces_f.append(local.reshape(ff.shape) + offset)
        offset += used.size
    cut = np.concatenate(pieces_v)
    out.append(("face x16, 40 components", 1000.0 * (cut @ rotation.T + [0.1, 0.2, -0.3]), np.concatenate(pieces_f)))
    return out


def timed(fn, repeats: int) -> tuple[float, float]:
    """``(compile_s, run_median_s)``: the first call minus a warm one, and the median of warm calls."""
    t0 = time.perf_counter()
    fn()
    first = time.perf_counter() - t0
    run = _median_time(fn, repeats)
    return max(first - run, 0.0), run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--ddim-steps", type=int, default=20)
    parser.add_argument("--window", type=int, default=50)
    parser.add_argument("--paper", action="store_true", help="also STM paper")
    parser.add_argument("--out", type=Path, default=Path("experiments/results/bench_freetalk_e2e.json"))
    args = parser.parse_args()
    peak = bm.measure_matmul_peak() / 1e9
    print(f"float32 matmul peak {peak:.0f} GFLOP/s", flush=True)
    acfg = ATSConfig.small(max_frames=args.window)
    ats_fit = FittedATS(acfg, ats.init_params(acfg, jax.random.key(0)),
                        DisplacementStats(np.zeros((68, 3), np.float32), np.full((68, 3), 0.003, np.float32)), [],
                        window=args.window)
    t = np.arange(int(16000 * args.seconds)) / 16000
    audio = (0.3 * np.sin(2 * np.pi * 170 * t) * (1 + np.sin(2 * np.pi * 3 * t))).astype(np.float32)
    key = jax.random.key(1)
    ats_compile, ats_run = timed(lambda: ft.landmark_track(ats_fit, audio, "happy", 2.0, key, sample_steps=args.ddim_steps),
                                 args.repeats)
    track = ft.landmark_track(ats_fit, audio, "happy", 2.0, key, sample_steps=args.ddim_steps)
    configs = {"small": STMConfig.small()} | ({"paper": STMConfig.paper()} if args.paper else {})
    rows = []
    face = builtin_face(0, resolution="low")
    for name, cfg in configs.items():
        tmpl = stm.prepare_mesh(np.asarray(face.template), np.asarray(face.faces), cfg)
        stm_fit = FittedSTM(cfg, stm.init_params(cfg, jax.random.key(2), tmpl))
        for label, v, f in meshes():
            t0 = time.perf_counter()
            mesh = ft.prepare_user_mesh(stm_fit, (v, f))
            precompute = time.perf_counter() - t0
            # The static features again, warm: the precompute above includes their compilation.
            feat_compile, feat_run = timed(
                lambda m=mesh: np.asarray(stm.stm_mesh_features(stm_fit.params, cfg, m.stm_mesh)), 1)
            stm_compile, stm_run = timed(lambda m=mesh: ft.displace(stm_fit, m, track), args.repeats)
            decode = functools.partial(stm._decode, config=cfg)
            one = bm.xla_flops(lambda p, feats, d, o: decode(p, features=feats, disp=d, ops=o), stm_fit.params,
                               mesh.features, track[:1], mesh.stm_mesh.ops)
            flops = None if one is None else one * track.shape[0]
            total = ats_run + stm_run
            disp = ft.displace(stm_fit, mesh, track)
            rows.append({
                "finite": bool(np.all(np.isfinite(disp))), "STM": name, "mesh": label, "vertices": mesh.num_vertices,
                "precompute_s": precompute,
                "of_which_features_s": feat_run, "ats_compile_s": ats_compile, "stm_compile_s": stm_compile,
                "ats_s_per_audio_s": ats_run / args.seconds, "stm_s_per_audio_s": stm_run / args.seconds,
                "total_s_per_audio_s": total / args.seconds, "real_time": total < args.seconds,
                "stm_gflop_s": None if flops is None else flops / stm_run / 1e9,
                "stm_of_peak": None if flops is None else flops / stm_run / 1e9 / peak,
            })
            print(rows[-1], flush=True)
    title = (f"FreeTalk end to end, {args.seconds:g}-s utterance, ATS small DDIM {args.ddim_steps} steps "
             f"(float32 matmul peak {peak:.0f} GFLOP/s)")
    bm.print_table(rows, title)
    print(f"wrote {bm.write_json(args.out, {'machine': bm.machine_info(), 'peak_gflop_s': peak, 'rows': rows})}")


if __name__ == "__main__":
    main()
