"""How much of a `paper` train step is the optimizer's memory-bound pass, and why small batches cannot
reach the matmul peak.

A train step is the forward and backward (matmuls: FLOPs grow with the batch) plus one update of
every parameter (gradient clipping, AdamW, the EMA where the recipe keeps one). The update reads
and writes several arrays the size of the parameters whatever the batch, so it is bound by memory
bandwidth, not by the matmul units; at a small batch it is a large share of the step and the step's
FLOP/s cannot approach the matmul peak.

For each model (``paper`` config, the recipe's own optimiser settings for that preset): the number of
parameters, the update alone (jitted exactly as the train step applies it: ``make_optimizer`` of the
recipe's :class:`~jaxtalk.train.OptimConfig`, then ``ema_update`` where the recipe has ``ema_decay``),
median of timed runs, the bytes it must move at least (4 bytes x parameters x arrays read and
written), and the machine's streaming bandwidth measured in the same run (``x * c`` over 256 MiB).
With ``--bench FILE`` (a ``jaxtalk bench --train --paper`` JSON) the update's share of each measured
paper step is added.

Usage: python experiments/optimizer_share.py [--models toktalk,ats,timar] [--bench B.json ...] [--out PATH]
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxtalk.benchmarking import machine_info, measure_matmul_peak, measure_memory_bandwidth, print_table, write_json


def paper_params(model: str) -> tuple[object, object]:
    """``(parameter shapes, TrainSettings)`` of the model's ``paper`` preset."""
    key = jax.random.PRNGKey(0)
    if model == "toktalk":
        from jaxtalk.models.toktalk import TokTalkConfig
        from jaxtalk.models.toktalk.model import init_params
        from jaxtalk.models.toktalk.recipe import DEFAULTS as settings

        return jax.eval_shape(lambda k: init_params(TokTalkConfig.paper(), k), key), settings
    if model == "ats":
        from jaxtalk.models.freetalk.ats import init_params
        from jaxtalk.models.freetalk.config import ATSConfig
        from jaxtalk.models.freetalk.recipe import ATS_PRESET_DEFAULTS

        return jax.eval_shape(lambda k: init_params(ATSConfig.paper(), k), key), ATS_PRESET_DEFAULTS["paper"]
    if model == "timar":
        from jaxtalk.models.timar import TimarConfig
        from jaxtalk.models.timar.model import init_params
        from jaxtalk.models.timar.recipe import PRESET_DEFAULTS

        return jax.eval_shape(lambda k: init_params(TimarConfig.paper(), k), key), PRESET_DEFAULTS["paper"]
    raise ValueError(f"unknown model {model!r}")


def _median_time(fn, args, repeats: int) -> tuple[float, object]:
    out = fn(*args)
    jax.block_until_ready(out)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn(*out[:-1], args[-1])
        jax.block_until_ready(out)
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def update_row(model: str, repeats: int) -> dict:
    from jaxtalk.train.ema import ema_update
    from jaxtalk.train.optim import make_optimizer

    shapes, settings = paper_params(model)
    optim = settings.optim(100_000)
    tx = make_optimizer(optim)
    params = jax.tree.map(lambda s: jnp.ones(s.shape, s.dtype), shapes)
    grads = jax.tree.map(lambda p: p * 1e-3, params)
    ema = jax.tree.map(lambda p: p.copy(), params) if optim.ema_decay is not None else None

    @jax.jit
    def update(params, opt_state, ema, grads):
        updates, opt_state = tx.update(grads, opt_state, params)
        params = optax.apply_updates(params, updates)
        if ema is not None:
            ema = ema_update(ema, params, optim.ema_decay, None, step=jnp.int32(10))
        return params, opt_state, ema, grads

    seconds, _ = _median_time(update, (params, tx.init(params), ema, grads), repeats)
    n = sum(int(np.prod(s.shape)) for s in jax.tree.leaves(shapes))
    # clip: read g; AdamW: read g, m, v, p and write m, v, p; EMA: read p, e and write e.
    arrays = (1 if optim.clip_norm is not None else 0) + 7 + (3 if ema is not None else 0)
    return {"model": model, "params_m": n / 1e6, "clip": optim.clip_norm is not None, "ema": ema is not None,
            "update_ms": seconds * 1e3, "min_bytes_gb": 4 * n * arrays / 1e9,
            "achieved_gb_s": 4 * n * arrays / seconds / 1e9}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="toktalk,ats,timar")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--bench", nargs="*", default=[], help="jaxtalk bench --train JSON files with paper rows")
    ap.add_argument("--out", default="experiments/results/optimizer_share.json")
    args = ap.parse_args()
    peak = measure_matmul_peak() / 1e9
    bandwidth = measure_memory_bandwidth(repeats=args.repeats) / 1e9
    rows = [update_row(m, args.repeats) for m in args.models.split(",")]
    steps = []
    for path in args.bench:
        for table in json.loads(open(path).read())["tables"]:
            steps += [r for r in table["rows"] if r.get("preset") == "paper" and "step_s" in r]
    shares = []
    for r in rows:
        for s in (s for s in steps if s["model"] == r["model"]):
            shares.append({"model": r["model"], "batch": s["batch"], "step_s": s["step_s"], "of_peak": s["of_peak"],
                           "update_share": r["update_ms"] / 1e3 / s["step_s"],
                           # the rest of the step's rate, against the bench run's own peak
                           "of_peak_without_update": s["of_peak"] / (1 - r["update_ms"] / 1e3 / s["step_s"])
                           if s.get("of_peak") else None})
    print_table(rows, f"The parameter update alone (paper presets); streaming bandwidth {bandwidth:.1f} GB/s, "
                      f"matmul peak {peak:.0f} GFLOP/s")
    if shares:
        print_table(shares, "Its share of measured paper train steps")
    write_json(args.out, {"machine": machine_info(), "matmul_peak_gflop_s": peak, "stream_gb_s": bandwidth,
                          "args": vars(args), "rows": rows, "shares": shares})


if __name__ == "__main__":
    main()
