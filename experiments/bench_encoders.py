"""Speed of the JAX wav2vec 2.0 / HuBERT port vs transformers (PyTorch), side by side in one run.

A base-size encoder (random weights, built offline by transformers and saved as safetensors) runs
on the same clip of 16 kHz audio in both frameworks. JAX: jitted ``encoder_features`` with compile
time reported separately (``jaxtalk.benchmarking.time_jitted``). PyTorch: ``model(x)`` under
``torch.inference_mode()`` with ``torch.set_num_threads`` set to the cores this process may use.
Run time is the median of repeats after warm-up; the table also shows the max abs difference of
the outputs (same weights, so it checks the two did the same work).

    python experiments/bench_encoders.py [--seconds 10] [--repeats 7] [--model-type hubert]
        [--size base|large] [--out experiments/results/bench_encoders.json]
"""

from __future__ import annotations

import argparse
import functools
import os
import statistics
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.audio.encoders import SpeechEncoder, encoder_features
from jaxtalk.benchmarking import machine_info, print_table, time_jitted, write_json


def _cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


def _hf_model(model_type: str, size: str):
    import transformers

    config_cls = {"hubert": transformers.HubertConfig, "wav2vec2": transformers.Wav2Vec2Config}[model_type]
    model_cls = {"hubert": transformers.HubertModel, "wav2vec2": transformers.Wav2Vec2Model}[model_type]
    kwargs = {}
    if size == "large":
        kwargs = dict(
            hidden_size=1024,
            num_hidden_layers=24,
            num_attention_heads=16,
            intermediate_size=4096,
            feat_extract_norm="layer",
            conv_bias=True,
            do_stable_layer_norm=True,
        )
    return model_cls(config_cls(**kwargs)).eval()


def _time_torch(model, audio, repeats: int, warmup: int = 2) -> tuple[list[float], np.ndarray]:
    import torch

    x = torch.from_numpy(audio[None])
    with torch.inference_mode():
        for _ in range(warmup):
            out = model(x).last_hidden_state
        runs = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            out = model(x).last_hidden_state
            runs.append(time.perf_counter() - t0)
    return runs, out[0].numpy()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--model-type", choices=("hubert", "wav2vec2"), default="hubert")
    parser.add_argument("--size", choices=("base", "large"), default="base")
    parser.add_argument("--out", default="experiments/results/bench_encoders.json")
    args = parser.parse_args(argv)

    try:
        import torch
    except ImportError:
        print("bench_encoders needs torch and transformers (the [encoders] extra)", file=sys.stderr)
        return 1
    threads = _cores()
    torch.set_num_threads(threads)
    torch.manual_seed(0)
    hf = _hf_model(args.model_type, args.size)
    with tempfile.TemporaryDirectory() as tmp:
        hf.save_pretrained(tmp)
        encoder = SpeechEncoder.from_pretrained(tmp, normalize=False)

    samples = int(round(args.seconds * 16_000))
    audio = (0.1 * np.random.default_rng(0).standard_normal(samples)).astype(np.float32)

    fn = functools.partial(encoder_features, config=encoder.config, normalize=False)
    timing = time_jitted(fn, encoder.params, jnp.asarray(audio[None]), repeats=args.repeats)
    jax_out = np.asarray(jax.jit(fn)(encoder.params, jnp.asarray(audio[None]))[0][0])

    torch_runs, torch_out = _time_torch(hf, audio, args.repeats)
    diff = float(np.max(np.abs(jax_out - torch_out)))

    rows = [
        {
            "impl": "jaxtalk (jit)",
            "compile_s": timing.compile_s,
            "run_median_s": timing.run_median_s,
            "run_min_s": timing.run_min_s,
            "x_realtime": args.seconds / timing.run_median_s,
        },
        {
            "impl": f"transformers (torch {torch.__version__}, {threads} threads)",
            "compile_s": None,
            "run_median_s": statistics.median(torch_runs),
            "run_min_s": min(torch_runs),
            "x_realtime": args.seconds / statistics.median(torch_runs),
        },
    ]
    speedup = rows[1]["run_median_s"] / rows[0]["run_median_s"]
    title = (
        f"{args.model_type}-{args.size} on {args.seconds:g} s of 16 kHz audio "
        f"({jax_out.shape[0]} frames x {jax_out.shape[1]}), median of {args.repeats}; "
        f"jaxtalk/torch speed-up {speedup:.2f}x; max |jax - torch| = {diff:.2e}"
    )
    print_table(rows, title)
    path = write_json(
        args.out,
        {
            "benchmark": "bench_encoders",
            "model_type": args.model_type,
            "size": args.size,
            "seconds": args.seconds,
            "repeats": args.repeats,
            "torch_threads": threads,
            "rows": rows,
            "speedup_torch_over_jax": speedup,
            "max_abs_diff": diff,
            "jax_timing": timing,
            "torch_runs": torch_runs,
            "machine": machine_info(),
        },
    )
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
