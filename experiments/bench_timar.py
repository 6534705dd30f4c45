"""TIMAR speed: streaming per-turn latency (small preset), the diffusion head alone, the paper preset.

* ``small`` preset, 1-s turns, context n = 7, 5 DDIM steps with CFG: latency of every streamed turn
  (turns 0..7 use the key/value cache, later turns slide the window and rebuild it). Target: at
  most 250 ms per turn, and a per-turn cost that does not grow with the turn index while cached.
* Diffusion head alone at the reference size (width 1024, 3 blocks, 56 in, learned variance), one
  turn (25 frames) with CFG, 5 and 100 DDIM steps. The public PyTorch sampler: 0.135 s and 2.7 s on
  this CPU; targets 0.07 s and 1.4 s.
* ``paper`` preset: per-turn latency, XLA FLOPs and achieved FLOP/s against the measured matmul peak
  (``--skip-paper`` to leave it out).

Compile and run time are reported separately; every run is ``block_until_ready``-ed; medians.

Usage: ``python experiments/bench_timar.py [--repeats 5] [--skip-paper] [--out results/bench_timar.json]``
"""

from __future__ import annotations

import argparse
import statistics

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.bench import timar_stream
from jaxtalk.benchmarking import machine_info, measure_matmul_peak, print_table, time_jitted, write_json, xla_flops
from jaxtalk.models.timar import TimarConfig, init_params
from jaxtalk.models.timar.head import apply_head_modulated, head_condition, head_modulations, time_embedding
from jaxtalk.models.timar.sampling import respaced_schedule, sample_frames
from jaxtalk.models.timar.streaming import _condition, init_stream


def _turn_inputs(config: TimarConfig, batch: int, turns: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    t = turns * config.frames_per_turn
    return (jnp.asarray(rng.normal(size=(batch, t, config.speech_dim)), jnp.float32),
            jnp.asarray(rng.normal(size=(batch, t, 56)), jnp.float32),
            jnp.asarray(rng.normal(size=(batch, t, config.speech_dim)), jnp.float32))


def head_latency(steps: int, repeats: int, precompute: bool | None = None):
    """The diffusion head alone at the reference size: one 25-frame turn with CFG.

    Returns the timing and the FLOPs of the whole sampler. XLA's cost analysis counts a scanned
    loop body once, so the FLOPs are counted in parts: before the loop, ``Dense(z)`` of both CFG
    branches and the adaLN modulations of every (step, frame) pair; per step, one CFG-batched head
    call on 2 x 25 frames with those modulations (the same total as computing them in the loop).
    """
    cfg = TimarConfig.paper(num_layers=1)  # only the head is used
    params = init_params(cfg, jax.random.key(0))
    z = jax.random.normal(jax.random.key(1), (1, 25, cfg.width))
    fn = lambda p, zc, zu, k: sample_frames(p, cfg, zc, zu, k, cfg_scale=0.5, sample_steps=steps,  # noqa: E731
                                            precompute=precompute)
    timing = time_jitted(fn, params, z, z * 0.5, jax.random.key(2), repeats=repeats, warmup=1)
    zz = jnp.concatenate([z, z * 0.5])
    times = jnp.asarray(respaced_schedule(cfg.schedule, cfg.num_timesteps, steps).timesteps, jnp.float32)

    def before_loop(p, zz):
        cz = head_condition(p["head"], cfg, zz)
        c = cz[None] + time_embedding(p["head"], cfg, times)[:, None, None]
        return head_modulations(p["head"], cfg, c)

    mods = tuple(m[0] for m in before_loop(params, zz))
    x = jnp.zeros((2, 25, cfg.param_dim))
    step = lambda p, x, m: apply_head_modulated(p["head"], cfg, x, m)  # noqa: E731
    f_step, f_pre = xla_flops(step, params, x, mods), xla_flops(before_loop, params, zz)
    flops = None if f_step is None or f_pre is None else steps * f_step + f_pre
    return timing, flops


def paper_turn(repeats: int, peak: float):
    """One cached streaming turn and one full 8-turn window of the paper preset: latency, FLOPs."""
    cfg = TimarConfig.paper()
    params = init_params(cfg, jax.random.key(0))
    us, um, as_ = _turn_inputs(cfg, 1, 1)
    rows = []
    for label, turn, mode in (("paper turn 0 (cached, n=7)", 0, "cached"),
                              ("paper turn 8 (sliding window, n=7)", 8, "sliding")):
        state = init_stream(cfg, jax.random.key(0), context=7)._replace(turn=jnp.asarray(turn, jnp.int32))

        def step(p, s, a, b, c, k, mode=mode):
            s2, z = _condition(p, cfg, s, a, b, c, True, mode)
            return sample_frames(p, cfg, z[:1], z[1:], k, cfg_scale=0.5, sample_steps=5)

        args = (params, state, us, um, as_, jax.random.key(0))
        timing = time_jitted(step, *args, repeats=repeats, warmup=1)
        flops = xla_flops(step, *args)
        rows.append({
            "what": label, "compile_s": timing.compile_s, "run_s": timing.run_median_s,
            "GFLOP": None if flops is None else flops / 1e9,
            "GFLOP/s": None if flops is None else flops / timing.run_median_s / 1e9,
            "of peak": None if flops is None else flops / timing.run_median_s / peak,
        })
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--turns", type=int, default=12)
    ap.add_argument("--skip-paper", action="store_true")
    ap.add_argument("--out", default="experiments/results/bench_timar.json")
    args = ap.parse_args()

    small = TimarConfig.small()
    # The streaming measurement lives in the library (also behind `jaxtalk bench`).
    compile_s, per_turn = timar_stream(small, context=7, turns=args.turns, repeats=args.repeats)
    rows = [{"turn": i, "cached": i <= 7, "latency_ms": 1e3 * t} for i, t in enumerate(per_turn)]
    print_table(rows, f"TIMAR small, n=7, 5 DDIM steps + CFG: per-turn latency (first call incl. compile {compile_s:.1f} s)")

    peak = measure_matmul_peak()
    head_rows = []
    for steps, ref, target in ((5, 0.135, 0.07), (100, 2.7, 1.4)):
        t, flops = head_latency(steps, args.repeats)
        head_rows.append({"steps": steps, "compile_s": t.compile_s, "run_s": t.run_median_s,
                          "pytorch_ref_s": ref, "target_s": target, "meets_target": t.run_median_s <= target,
                          "GFLOP": None if flops is None else flops / 1e9,
                          "of_peak": None if flops is None else flops / t.run_median_s / peak})
    print_table(head_rows, f"Diffusion head alone (1024 wide, K=3, learned variance), one turn of 25 frames + CFG "
                           f"(matmul peak {peak / 1e9:.1f} GFLOP/s)")

    paper_rows = []
    if not args.skip_paper:
        paper_rows = paper_turn(max(1, args.repeats // 2), peak)
        print_table(paper_rows, f"TIMAR paper preset (matmul peak {peak / 1e9:.1f} GFLOP/s)")

    cached = [r["latency_ms"] for r in rows if r["cached"]]
    sliding = [r["latency_ms"] for r in rows if not r["cached"]]
    summary = {
        "small_cached_median_ms": statistics.median(cached),
        "small_sliding_median_ms": statistics.median(sliding) if sliding else None,
        "small_max_ms": max(r["latency_ms"] for r in rows),
        "meets_250ms": max(r["latency_ms"] for r in rows) <= 250.0,
    }
    print(summary)
    write_json(args.out, {"machine": machine_info(), "small_stream": rows, "small_compile_s": compile_s,
                          "head": head_rows, "paper": paper_rows, "matmul_peak_flops": peak, "summary": summary})


if __name__ == "__main__":
    main()
