"""TokTalk speed: per-chunk streaming latency, FLOPs and achieved FLOP/s; latency vs utterance length.

Cases (10 Euler steps on the cosine grid, CFG = conditional + unconditional as one batch of 2):
* ``small`` preset, 0.4 s chunk (10 frames) with its 20-frame left context: real-time factor
  (latency / chunk duration), target <= 0.25.
* ``paper`` preset (about 82M decoder parameters): a 10-frame window (chunk only) and a 50-frame
  window (chunk + 40 context frames); the PyTorch reference takes 1.11 s and 1.73 s on this CPU,
  target <= 0.45 s and <= 1.1 s. FLOPs from XLA's cost analysis of one CFG velocity evaluation
  times the number of steps (XLA counts a scan body once).
* Latency of chunk 2 vs chunk 50 of one stream (the fixed window keeps them equal; the reference
  recomputes the whole prefix).

Weights are random (speed does not depend on them): drawn on the host from the parameter shapes, so
the benchmark does not spend minutes compiling the initialiser of the 82M model.

Usage: ``python experiments/bench_toktalk.py [--skip-paper] [--out experiments/results/bench_toktalk.json]``
"""

from __future__ import annotations

import argparse
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.benchmarking import machine_info, measure_matmul_peak, print_table, write_json, xla_flops
from jaxtalk.models import toktalk as tt
import importlib

stream_mod = importlib.import_module("jaxtalk.models.toktalk.stream")  # the package re-exports stream()
from jaxtalk.models.toktalk.model import Condition, velocity
from jaxtalk.models.toktalk.sample import default_grid


def random_params(config: tt.TokTalkConfig, seed: int = 0) -> dict:
    """Parameters with the model's shapes filled on the host (scaled normal; LayerNorm/GroupNorm scale 1)."""
    shapes = jax.eval_shape(lambda k: tt.init_params(config, k), jax.random.key(0))
    rng = np.random.default_rng(seed)

    def fill(path, s):
        name = jax.tree_util.keystr(path)
        if name.endswith("['scale']"):
            return jnp.ones(s.shape, s.dtype)
        if name.endswith("['bias']"):
            return jnp.zeros(s.shape, s.dtype)
        fan_in = int(np.prod(s.shape[:-1])) or 1
        return jnp.asarray(rng.normal(size=s.shape) / np.sqrt(fan_in), s.dtype)

    return jax.tree_util.tree_map_with_path(fill, shapes)


def _median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def stream_case(config: tt.TokTalkConfig, name: str, repeats: int) -> dict:
    """Latency of one streaming chunk (compile excluded) plus XLA FLOPs of the whole chunk."""
    params = random_params(config)
    rng = np.random.default_rng(0)
    ct = tt.tokens_per_chunk(config)
    style = jnp.asarray(rng.normal(size=(1, config.style_dim)), jnp.float32)
    state = tt.init_stream(config, jax.random.key(0), batch=1, buffer_frames=2000)
    chunk = jnp.asarray(rng.normal(size=(1, ct, config.token_dim)), jnp.float32)
    ts = jnp.asarray(default_grid(config), jnp.float32)
    w = jnp.asarray(config.cfg_scale, jnp.float32)
    t0 = time.perf_counter()
    state, out = tt.stream_step(params, config, state, chunk, style)
    jax.block_until_ready(out)
    compile_s = time.perf_counter() - t0
    step = functools.partial(stream_mod._stream_step, config=config)
    # Warm state (window full) for the timed runs.
    for _ in range(config.window_frames // config.chunk_frames):
        state, out = step(params, state, chunk, style, w, ts)
    latency = _median_time(lambda: step(params, state, chunk, style, w, ts)[1], repeats)
    # FLOPs: one guided velocity evaluation (batch 2) times the number of Euler steps.
    wf = config.window_frames
    cond = Condition(
        tokens=jnp.zeros((2, wf, config.token_dim)), style=jnp.zeros((2, config.style_dim)),
        known=jnp.zeros((2, wf, config.param_dim)), known_mask=jnp.zeros((2, wf), bool),
        keep=jnp.ones((2,)), mask=jnp.ones((2, wf), bool), chunked=jnp.ones((2,), bool),
    )
    x = jnp.zeros((2, wf, config.param_dim))
    flops_eval = xla_flops(lambda p, x, c: velocity(p, config, x, jnp.full((2,), 0.5), c), params, x, cond)
    flops = None if flops_eval is None else flops_eval * config.num_steps
    duration = config.chunk_frames / config.fps
    return {
        "case": name,
        "window_frames": wf,
        "chunk_s": duration,
        "compile_s": compile_s,
        "latency_s": latency,
        "rtf": latency / duration,
        "gflops_per_chunk": None if flops is None else flops / 1e9,
        "achieved_gflop_s": None if flops is None else flops / latency / 1e9,
    }


def growth_case(config: tt.TokTalkConfig, chunks: int, repeats: int) -> dict:
    """Per-chunk latency at chunk 2 and at chunk ``chunks`` of one stream."""
    params = random_params(config)
    rng = np.random.default_rng(1)
    ct = tt.tokens_per_chunk(config)
    style = jnp.asarray(rng.normal(size=(1, config.style_dim)), jnp.float32)
    state = tt.init_stream(config, jax.random.key(0), batch=1, buffer_frames=4000)
    ts = jnp.asarray(default_grid(config), jnp.float32)
    w = jnp.asarray(config.cfg_scale, jnp.float32)
    step = functools.partial(stream_mod._stream_step, config=config)
    times = {}
    for i in range(1, chunks + 1):
        chunk = jnp.asarray(rng.normal(size=(1, ct, config.token_dim)), jnp.float32)
        if i in (2, chunks):
            times[i] = _median_time(lambda: step(params, state, chunk, style, w, ts)[1], repeats)
        state, out = step(params, state, chunk, style, w, ts)
        jax.block_until_ready(out)
    return {"chunk_2_s": times[2], f"chunk_{chunks}_s": times[chunks], "ratio": times[chunks] / times[2]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--skip-paper", action="store_true")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--out", default="experiments/results/bench_toktalk.json")
    args = parser.parse_args()
    rows = [stream_case(tt.TokTalkConfig.small(), "small, chunk 0.4 s", args.repeats)]
    if not args.skip_paper:
        rows.append(stream_case(tt.TokTalkConfig.paper(context_frames=0, overlap_frames=0), "paper, 10 frames",
                                max(3, args.repeats // 3)))
        rows.append(stream_case(tt.TokTalkConfig.paper(context_frames=40), "paper, 50 frames",
                                max(3, args.repeats // 3)))
    peak = measure_matmul_peak() / 1e9
    for r in rows:
        r["fraction_of_matmul_peak"] = None if r["achieved_gflop_s"] is None else r["achieved_gflop_s"] / peak
    print_table(rows, f"TokTalk per-chunk latency (10 Euler steps, CFG); matmul peak {peak:.0f} GFLOP/s")
    growth = growth_case(tt.TokTalkConfig.small(), 50, args.repeats)
    print_table([growth], "small preset: per-chunk latency at chunk 2 vs chunk 50 (target ratio <= 1.10)")
    write_json(args.out, {"machine": machine_info(), "matmul_peak_gflop_s": peak, "latency": rows,
                          "growth": growth})


if __name__ == "__main__":
    main()
