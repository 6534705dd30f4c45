"""TokTalk's paper-size sampler against the public PyTorch code it reimplements, side by side on this
CPU: one streaming chunk's sampling, interleaved run by run.

Both sides sample one window of ``W`` frames (10: the chunk alone; 50: the chunk and 40 frames of
context) with 10 Euler steps and classifier-free guidance, the conditional and unconditional passes
run as one batch of 2 (CosyVoice's ``solve_euler``), random weights (speed does not depend on them):

* reference: CosyVoice's ``ConditionalDecoder`` (``cosyvoice/flow/decoder.py``, built from
  Matcha-TTS's ResNet and transformer blocks) at the published sizes (channels (256, 256), 4
  transformer blocks per stage, 12 middle stages, 8 heads x 64, GELU) with the 56-d motion as its
  output and its four 56-d input tracks (x, mu, the speaker/style vector, cond), under
  ``torch.inference_mode`` with torch's threads set to the CPU count, in a child process run by
  ``--torch-python`` (an environment with torch, diffusers 0.27, einops and conformer; the reference
  needs them, jaxtalk does not), its Euler loop written as ``solve_euler`` does it;
* jaxtalk: :func:`jaxtalk.models.toktalk.sampling.generate_frames` on ``TokTalkConfig.paper()`` with the
  same window, compiled once before timing (the streaming engine's step is this call plus slicing).

Rounds alternate: one jaxtalk run, one reference run, ``--rounds`` times per window, so a slow
spell of the shared machine hits both; the medians and their ratio (reference / jaxtalk: above 1,
jaxtalk is faster) are printed and written with the parameter counts of both decoders (the same
architecture: they agree to a fraction of a percent) and jaxtalk's FLOPs per chunk (XLA's count).

Setup (no internet at run time: the reference trees and the torch environment are made once)::

    git -C CosyVoice archive HEAD cosyvoice | tar -x -C /work/ref/cosyvoice
    git -C Matcha-TTS archive HEAD matcha | tar -x -C /work/ref/matcha
    python -m venv /work/torchenv && /work/torchenv/bin/pip install torch diffusers==0.27.2 einops conformer numpy
    python experiments/toktalk_reference_speed.py --cosyvoice /work/ref/cosyvoice --matcha /work/ref/matcha \\
        --torch-python /work/torchenv/bin/python
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

PARAM_DIM, STEPS, CFG = 56, 10, 0.7


def reference_child(cosyvoice: str, matcha: str) -> None:
    """The reference side: reads ``W`` lines on stdin, answers each with one timed chunk (JSON)."""
    import torch

    sys.path[:0] = [cosyvoice, matcha]
    from cosyvoice.flow.decoder import ConditionalDecoder

    torch.set_num_threads(os.cpu_count() or 1)
    torch.manual_seed(0)
    decoder = ConditionalDecoder(in_channels=4 * PARAM_DIM, out_channels=PARAM_DIM, channels=(256, 256), dropout=0.0,
                                 attention_head_dim=64, n_blocks=4, num_mid_blocks=12, num_heads=8, act_fn="gelu").eval()
    params = sum(p.numel() for p in decoder.parameters())
    print(json.dumps({"params": params}), flush=True)

    def chunk(w: int) -> torch.Tensor:
        # solve_euler: x_{t+dt} = x_t + dt * v, v = (1 + cfg) v_cond - cfg v_uncond, both in one batch of 2.
        x = torch.randn(1, PARAM_DIM, w)
        mu, spks, cond = torch.randn(1, PARAM_DIM, w), torch.randn(1, PARAM_DIM), torch.randn(1, PARAM_DIM, w)
        mask = torch.ones(2, 1, w)
        grid = 1 - torch.cos(torch.linspace(0, 1, STEPS + 1) * 0.5 * torch.pi)
        for k in range(STEPS):
            t, dt = grid[k], grid[k + 1] - grid[k]
            v = decoder(torch.cat([x, x]), mask, torch.cat([mu, torch.zeros_like(mu)]), t.repeat(2),
                        torch.cat([spks, torch.zeros_like(spks)]), torch.cat([cond, torch.zeros_like(cond)]))
            x = x + dt * ((1 + CFG) * v[:1] - CFG * v[1:])
        return x

    with torch.inference_mode():
        for line in sys.stdin:
            w = int(line)
            t0 = time.perf_counter()
            chunk(w)
            print(json.dumps({"seconds": time.perf_counter() - t0}), flush=True)


class Reference:
    """The reference child process (one decoder, kept between runs)."""

    def __init__(self, python: str, cosyvoice: str, matcha: str) -> None:
        self.proc = subprocess.Popen([python, __file__, "--child", "--cosyvoice", cosyvoice, "--matcha", matcha],
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.params = self._answer()["params"]

    def _answer(self) -> dict:
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"the reference process stopped (exit code {self.proc.wait()}); see its error above")
        return json.loads(line)

    def run(self, w: int) -> float:
        self.proc.stdin.write(f"{w}\n")
        self.proc.stdin.flush()
        return self._answer()["seconds"]

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait()


def jaxtalk_chunk(w: int):
    """A jitted chunk of jaxtalk's paper model on a ``w``-frame window, its parameter count and FLOPs."""
    import jax
    import jax.numpy as jnp

    from jaxtalk.bench import random_params
    from jaxtalk.benchmarking import xla_flops
    from jaxtalk.models import toktalk as tt
    from jaxtalk.models.toktalk.model import Condition, velocity
    from jaxtalk.models.toktalk.sampling import default_grid, generate_frames

    config = tt.TokTalkConfig.paper(context_frames=w - 10, overlap_frames=0 if w == 10 else 5)
    params = random_params(lambda k: tt.init_params(config, k))
    rng = np.random.default_rng(0)
    tokens = jnp.asarray(rng.normal(size=(1, tt.tokens_per_chunk(config, w), config.speech_dim)), jnp.float32)
    style = jnp.asarray(rng.normal(size=(1, config.style_vector_dim)), jnp.float32)
    noise = jnp.asarray(rng.normal(size=(1, w, config.param_dim)), jnp.float32)
    run = jax.jit(lambda p, tok, sty, z: generate_frames(
        p, config, tok, sty, z, jnp.asarray(default_grid(config), jnp.float32), jnp.float32(config.cfg_scale),
        known=z, known_mask=jnp.zeros((1, w), bool), mask=jnp.ones((1, w), bool), chunked=jnp.zeros((), bool)))
    jax.block_until_ready(run(params, tokens, style, noise))
    cond = Condition(tokens=jnp.zeros((2, w, config.speech_dim)), style=jnp.zeros((2, config.style_vector_dim)),
                     known=jnp.zeros((2, w, config.param_dim)), known_mask=jnp.zeros((2, w), bool), keep=jnp.ones((2,)),
                     mask=jnp.ones((2, w), bool), chunked=jnp.zeros((2,), bool))
    flops = xla_flops(lambda p, x, c: velocity(p, config, x, jnp.full((2,), 0.5), c), params,
                      jnp.zeros((2, w, config.param_dim)), cond)
    count = sum(int(np.prod(leaf.shape)) for leaf in jax.tree.leaves(params["decoder"]))

    def once() -> float:
        t0 = time.perf_counter()
        jax.block_until_ready(run(params, tokens, style, noise))
        return time.perf_counter() - t0

    return once, count, None if flops is None else flops * config.sample_steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cosyvoice", required=True, help="a folder holding CosyVoice's cosyvoice/ package")
    parser.add_argument("--matcha", required=True, help="a folder holding Matcha-TTS's matcha/ package")
    parser.add_argument("--torch-python", default=sys.executable, help="python of an environment with the reference's packages")
    parser.add_argument("--windows", default="10,50")
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--out", default="experiments/results/toktalk_reference_speed.json")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        reference_child(args.cosyvoice, args.matcha)
        return
    from jaxtalk.benchmarking import machine_info, measure_matmul_peak, print_table, write_json

    reference = Reference(args.torch_python, str(Path(args.cosyvoice).resolve()), str(Path(args.matcha).resolve()))
    peak = measure_matmul_peak() / 1e9
    rows = []
    try:
        for w in (int(v) for v in args.windows.split(",")):
            ours, count, flops = jaxtalk_chunk(w)
            reference.run(w)  # warm-up (torch's first call allocates)
            times: dict[str, list[float]] = {"jaxtalk": [], "reference": []}
            for _ in range(args.rounds):
                times["jaxtalk"].append(ours())
                times["reference"].append(reference.run(w))
            jax_s, ref_s = statistics.median(times["jaxtalk"]), statistics.median(times["reference"])
            rows.append({"window_frames": w, "jaxtalk_s": jax_s, "reference_s": ref_s, "reference_over_jaxtalk": ref_s / jax_s,
                         "jaxtalk_params_m": count / 1e6, "reference_params_m": reference.params / 1e6,
                         "gflops": None if flops is None else flops / 1e9,
                         "jaxtalk_of_peak": None if flops is None else flops / jax_s / 1e9 / peak,
                         "reference_of_peak": None if flops is None else flops / ref_s / 1e9 / peak,
                         "jaxtalk_runs_s": times["jaxtalk"], "reference_runs_s": times["reference"]})
    finally:
        reference.close()
    shown = [{k: v for k, v in r.items() if not k.endswith("runs_s")} for r in rows]
    print_table(shown, f"TokTalk paper chunk, {STEPS} Euler steps + CFG: jaxtalk vs CosyVoice's decoder "
                       f"(float32 peak {peak:.0f} GFLOP/s)")
    write_json(args.out, {"machine": machine_info(), "matmul_peak_gflop_s": peak, "args": vars(args), "rows": rows})


if __name__ == "__main__":
    main()
