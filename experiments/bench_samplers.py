"""Benchmark the Euler (flow matching) and DDIM samplers with a realistic-size stub model and CFG.

Stub velocity/x0 model: a per-frame 3-layer MLP 56 -> 512 -> 512 -> 56 (plus a 128-d per-frame
condition and a time input) over 100 frames x batch 1, evaluated with classifier-free guidance (one
batched call of batch 2 per step). For steps {1, 5, 10, 20} it reports compile time, median run time
(compiled executable, block_until_ready), XLA FLOPs per call (one step's cost analysis x steps, since
XLA counts a scan body once), achieved FLOP/s, and the fraction of this machine's float32 matmul peak
measured in the same run (best of repeated 2048^3, 1024^3 and 512^3 matmuls), from the median run and from the
fastest run.

Usage: python experiments/bench_samplers.py [--out PATH] [--repeats N]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk import benchmarking as bm
from jaxtalk.samplers import diffusion, flow
from jaxtalk.samplers.schedules import cosine_grid, make_schedule, respace

FRAMES, BATCH, DIM, COND, HIDDEN = 100, 1, 56, 128, 512
STEPS = (1, 5, 10, 20)


def init_params(seed: int = 0) -> dict[str, jax.Array]:
    rng = np.random.default_rng(seed)

    def dense(n_in: int, n_out: int) -> jax.Array:
        return jnp.asarray(rng.normal(size=(n_in, n_out)) / np.sqrt(n_in), jnp.float32)

    return {
        "w_x": dense(DIM, HIDDEN),
        "w_c": dense(COND, HIDDEN),
        "w_t": dense(1, HIDDEN),
        "w_2": dense(HIDDEN, HIDDEN),
        "w_3": dense(HIDDEN, DIM),
    }


def mlp(params: dict[str, jax.Array], x: jax.Array, t: jax.Array, cond: dict[str, jax.Array]) -> jax.Array:
    """Per-frame MLP; x (B, F, 56), t (B,), cond["audio"] (B, F, 128) -> (B, F, 56)."""
    h = x @ params["w_x"] + cond["audio"] @ params["w_c"] + t[:, None, None] * params["w_t"][None]
    h = jax.nn.gelu(h)
    h = jax.nn.gelu(h @ params["w_2"])
    return h @ params["w_3"]


def euler(params, noise, cond, uncond, ts, w):
    return flow.sample_euler(jax.tree_util.Partial(mlp, params), noise, cond, ts, uncond=uncond, cfg_scale=w)


def ddim(params, noise, cond, uncond, sched, key, w):
    return diffusion.sample_ddim(
        jax.tree_util.Partial(mlp, params), noise, cond, sched, key, uncond=uncond, cfg_scale=w, eta=0.0
    )


def one_guided_step(params, x, cond, uncond, w):
    t = jnp.full((x.shape[0],), 0.5, x.dtype)
    return flow.guided_apply(jax.tree_util.Partial(mlp, params), x, t, cond, uncond, w)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--out", type=Path, default=Path("experiments/results/bench_samplers.json"))
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    if args.repeats <= 0:
        parser.error(f"--repeats must be positive, got {args.repeats}")

    params = init_params()
    key = jax.random.key(0)
    k_noise, k_cond, k_sample = jax.random.split(key, 3)
    noise = jax.random.normal(k_noise, (BATCH, FRAMES, DIM))
    cond = {"audio": jax.random.normal(k_cond, (BATCH, FRAMES, COND))}
    uncond = {"audio": jnp.zeros((BATCH, FRAMES, COND))}
    w = jnp.asarray(0.7, jnp.float32)

    # Best over sizes and many repeats: on a shared CPU a long 2048^3 run is rarely left uninterrupted,
    # while a few-millisecond 512^3 run often is (the sampler calls being timed are that short too).
    peak = max(
        bm.measure_matmul_peak(jnp.float32, n=2048, repeats=5),
        bm.measure_matmul_peak(jnp.float32, n=1024, repeats=30),
        bm.measure_matmul_peak(jnp.float32, n=512, repeats=100),
    )
    step_flops = bm.xla_flops(one_guided_step, params, noise, cond, uncond, w)
    base = make_schedule("linear")

    rows = []
    for sampler in ("euler", "ddim"):
        for n in STEPS:
            if sampler == "euler":
                fn, call_args = (
                    euler,
                    (params, noise, cond, uncond, jnp.asarray(cosine_grid(n), jnp.float32), w),
                )
            else:
                fn, call_args = (
                    ddim,
                    (params, noise, cond, uncond, respace(base, n).astype(jnp.float32), k_sample, w),
                )
            timing = bm.time_jitted(fn, *call_args, repeats=args.repeats, warmup=2)
            flops = None if step_flops is None else step_flops * n
            achieved = None if flops is None else flops / timing.run_median_s
            best = None if flops is None else flops / timing.run_min_s
            rows.append(
                {
                    "sampler": sampler,
                    "steps": n,
                    "compile_s": timing.compile_s,
                    "run_median_ms": 1e3 * timing.run_median_s,
                    "run_min_ms": 1e3 * timing.run_min_s,
                    "ms_per_step": 1e3 * timing.run_median_s / n,
                    "gflop_per_call": None if flops is None else flops / 1e9,
                    "gflop_s": None if achieved is None else achieved / 1e9,
                    "peak_fraction": None if achieved is None else achieved / peak,
                    "peak_fraction_best": None if best is None else best / peak,
                }
            )

    title = (
        f"Samplers, MLP {DIM}->{HIDDEN}->{HIDDEN}->{DIM} x {FRAMES} frames x batch {BATCH}, "
        "CFG (batch 2/step); "
        f"float32 matmul peak {peak / 1e9:.1f} GFLOP/s; backend {jax.default_backend()}"
    )
    bm.print_table(rows, title)
    out = bm.write_json(
        args.out,
        {
            "benchmark": "samplers",
            "config": {
                "frames": FRAMES,
                "batch": BATCH,
                "dim": DIM,
                "cond": COND,
                "hidden": HIDDEN,
                "cfg": True,
            },
            "matmul_peak_flops": peak,
            "xla_flops_per_guided_step": step_flops,
            "repeats": args.repeats,
            "rows": rows,
        },
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
