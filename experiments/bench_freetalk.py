"""Benchmark FreeTalk: STM frames per second on a ~5k-vertex face and ATS DDIM time for a 4-s clip.

STM: the built-in face at "high" resolution (~5.9k vertices; FLAME has 5,023), ``small`` and
``paper`` configurations, 25 landmark frames decoded per call with the mesh features precomputed.
The per-mesh precompute (operators: Laplacian, eigenbasis, gradients; then the DiffusionNet encoder
features) is timed separately. Target: STM ``small`` at least 25 frames/s on this CPU.

ATS: a 4-s clip (100 frames at 25 fps), DDIM with 100 and 10 steps, ``small`` and ``paper``
configurations (random weights: speed does not depend on them).

Compile and run times are reported separately (median of repeats, ``block_until_ready``). The CPU
is shared with other jobs, so absolute numbers are inflated: compare rows of one run.

Usage: python experiments/bench_freetalk.py [--out PATH] [--repeats N] [--skip-paper]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxtalk import benchmarking as bm
from jaxtalk.bench import ats_clip, stm_frames
from jaxtalk.models.freetalk.config import ATSConfig, STMConfig

FRAMES = 25
CLIP_FRAMES = 100


def bench_stm(name: str, cfg: STMConfig, repeats: int) -> dict:
    row = stm_frames(cfg, name, resolution="high", frames=FRAMES, repeats=repeats)
    per_frame = row["latency_s"] / FRAMES
    return {
        "model": f"STM {name}",
        "vertices": row["vertices"],
        "k": cfg.num_eigenpairs,
        "operators_s": row["operators_s"],
        "mesh_features_s": row["mesh_features_s"],
        "compile_s": row["compile_s"],
        "s_per_frame": per_frame,
        "frames_per_s": 1.0 / per_frame,
        "real_time_25fps": 1.0 / per_frame >= 25.0,
        "gflop_per_frame": None if row["gflops"] is None else row["gflops"] / FRAMES,
        "gflop_s": row["gflop_s"],
    }


def bench_ats(name: str, cfg: ATSConfig, steps: int, repeats: int) -> dict:
    row = ats_clip(cfg, name, steps=steps, frames=CLIP_FRAMES, repeats=repeats)
    return {
        "model": f"ATS {name}",
        "clip_s": row["clip_s"],
        "ddim_steps": steps,
        "compile_s": row["compile_s"],
        "run_s": row["latency_s"],
        "real_time_factor": row["rtf"],
        "gflops": row["gflops"],
        "gflop_s": row["gflop_s"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("experiments/results/bench_freetalk.json"))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--skip-paper", action="store_true", help="only the small configurations")
    args = parser.parse_args()

    configs = [("small", STMConfig.small())] + ([] if args.skip_paper else [("paper", STMConfig.paper())])
    stm_rows = [bench_stm(n, c, args.repeats) for n, c in configs]
    bm.print_table(stm_rows, f"STM: {FRAMES} frames per call, mesh features precomputed")

    ats_configs = [("small", ATSConfig.small())] + ([] if args.skip_paper else [("paper", ATSConfig.paper())])
    ats_rows = [bench_ats(n, c, s, max(1, args.repeats // 2)) for n, c in ats_configs for s in (100, 10)]
    bm.print_table(ats_rows, f"ATS DDIM on a {CLIP_FRAMES / 25:.0f}-s clip")
    path = bm.write_json(args.out, {"stm": stm_rows, "ats": ats_rows})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
