"""Streaming speed of the published TIMAR size: jaxtalk against the public reference code, on this CPU.

Both run the released model's shapes with random weights (32 timm blocks of width 1024, 16 heads,
1024-d tokens and speech, head 3 x 1024, 8-turn tables) and stream the same number of 1-s turns with
5 ancestral diffusion steps and CFG (scale 2, so both branches run), one conversation:

* reference: ``TIMAR.sample(..., history, num_iter=1, cfg=2.0, mask_history_agent=True)`` (the public
  evaluation's call; the random small wav2vec 2.0 replaced by precomputed speech, so only TIMAR is
  timed), under torch's CPU threads;
* jaxtalk: :func:`jaxtalk.models.timar.stream_step` on ``TimarConfig.reference()`` (compiled
  once before timing).

It prints the seconds per turn of each (median over the timed turns, turn 1 excluded from the
median for jaxtalk's compile), their ratio, and jaxtalk's achieved FLOP/s as a fraction of a measured
float32 matmul peak (a 2048^3 ``jnp.dot``) on the same machine. The FLOPs of a turn are counted
analytically (every matmul of the encoder over the turn's 110 tokens against its window, of the
head over 25 frames x 5 steps, both CFG branches).

Set-up as for ``experiments/timar_reference_parity.py`` (the reference half runs under
``--torch-python``, with the timm ``Block`` stand-in when timm does not import)::

    python experiments/timar_reference_speed.py --reference-repo /work/timar-ref \\
        --torch-python /work/torchenv/bin/python --turns 4

It writes ``results/timar_reference_speed.json`` (``--out``): both sides' seconds per turn, their
medians and ratio, the FLOPs per turn and the measured peak.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
STANDINS = HERE / "timar_reference_standins"
WIDTH, DEPTH, HEADS, SPEECH, HEAD_W, STEPS, CFG, FPS = 1024, 32, 16, 1024, 1024, 5, 2.0, 25


def _reference(args: argparse.Namespace) -> dict:
    import importlib

    try:
        importlib.import_module("timm.models.vision_transformer")
    except Exception:  # noqa: BLE001
        for name in [m for m in sys.modules if m == "timm" or m.startswith(("timm.", "torchvision"))]:
            del sys.modules[name]
        sys.path.insert(0, str(STANDINS))
    sys.path.insert(0, str(args.reference_repo.resolve()))
    from functools import partial

    import torch
    import transformers

    transformers.Wav2Vec2Model.from_pretrained = classmethod(lambda cls, *a, **k: torch.nn.Identity())
    import model.timar as ref_timar

    torch.manual_seed(0)
    m = ref_timar.TIMAR(speech_snippet_embed_dim=SPEECH, token_embed_dim=WIDTH, encoder_embed_dim=WIDTH,
                        decoder_embed_dim=WIDTH, encoder_depth=DEPTH // 2, decoder_depth=DEPTH // 2,
                        encoder_num_heads=HEADS, decoder_num_heads=HEADS, norm_layer=partial(torch.nn.LayerNorm, eps=1e-6),
                        use_causal_attn=True, diffloss_d=3, diffloss_w=HEAD_W, num_sampling_steps=str(STEPS),
                        use_encoder_only=True).eval()
    speech = torch.randn(1, FPS, SPEECH)
    # Only TIMAR is timed: the speech encoder returns precomputed features of the turn.
    type(m.speech_encoder).__call__ = lambda self, chunk, num_frames: speech
    torch.Tensor.cuda = lambda self, *a, **k: self
    audio = torch.zeros(1, 16000)
    motion = torch.randn(1, FPS, 56)
    history, times = None, []
    with torch.no_grad():
        for _ in range(args.turns):
            t0 = time.perf_counter()
            _, history = m.sample(audio, motion, audio, history, num_iter=1, cfg=CFG, mask_history_agent=True)
            times.append(time.perf_counter() - t0)
    return {"times": times, "threads": torch.get_num_threads()}


def _turn_flops(turn: int) -> float:
    """FLOPs of jaxtalk's streamed turn ``turn`` (0-based; window still filling): both CFG branches."""
    tpt = 4 * FPS + 10
    keys = (turn + 1) * tpt
    d = WIDTH
    per_token = DEPTH * (2 * 12 * d * d + 4 * d * keys)  # qkv + proj + mlp (12 d^2 MACs) + scores/values
    embed = 2 * (3 * FPS * SPEECH * d + 3 * FPS * (56 * d // 2 + d * d // 2) + tpt * d * d)  # projections
    encoder = tpt * per_token + embed
    h = HEAD_W
    head_cond = FPS * 2 * (d * h)  # Dense(z)
    per_step = FPS * 2 * (56 * h + 3 * (2 * h * h + 3 * h * h) + 2 * h * h + h * 112 + 2 * h * h)
    return 2 * (encoder + head_cond + STEPS * per_step)


def _jaxtalk(args: argparse.Namespace) -> dict:
    import jax
    import jax.numpy as jnp

    from jaxtalk.models.timar.config import TimarConfig
    from jaxtalk.models.timar.model import init_params
    from jaxtalk.models.timar.streaming import init_stream, stream_step

    config = TimarConfig.reference(dropout=0.0)
    params = init_params(config, jax.random.key(0))
    jax.block_until_ready(params)
    rng = np.random.default_rng(0)
    speech = jnp.asarray(rng.standard_normal((1, FPS, SPEECH)), jnp.float32)
    motion = jnp.asarray(rng.standard_normal((1, FPS, 56)), jnp.float32)
    state = init_stream(config, jax.random.key(1), batch=1, context=config.max_turns - 1)
    times = []
    for _ in range(args.turns):
        t0 = time.perf_counter()
        state, y = stream_step(params, config, state, speech, motion, speech, cfg_scale=CFG - 1.0, sample_steps=STEPS)
        jax.block_until_ready(y)
        times.append(time.perf_counter() - t0)
    a = jnp.ones((2048, 2048), jnp.float32)
    dot = jax.jit(lambda x: x @ x)
    jax.block_until_ready(dot(a))
    best = min(_timed(lambda: jax.block_until_ready(dot(a))) for _ in range(5))
    return {"times": times, "peak": 2 * 2048**3 / best}


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--reference-repo", type=Path, required=True)
    p.add_argument("--torch-python", default=sys.executable)
    p.add_argument("--turns", type=int, default=4)
    p.add_argument("--out", type=Path, default=HERE / "results" / "timar_reference_speed.json")
    p.add_argument("--reference-side", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.reference_side:
        print(json.dumps(_reference(args)))
        return 0
    cmd = [args.torch_python, str(Path(__file__).resolve()), "--reference-repo", str(args.reference_repo),
           "--turns", str(args.turns), "--reference-side"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode:
        sys.stderr.write(proc.stderr[-3000:])
        return 2
    ref = json.loads(proc.stdout.strip().splitlines()[-1])
    ours = _jaxtalk(args)
    r_med = float(np.median(ref["times"][1:] if len(ref["times"]) > 1 else ref["times"]))
    j_med = float(np.median(ours["times"][1:]))
    flops = np.mean([_turn_flops(t) for t in range(1, args.turns)])
    print(f"TIMAR reference size (32 x 1024, head 3 x 1024), {args.turns} streamed turns, {STEPS} steps, CFG {CFG:g}")
    print("reference (torch, %d threads): %s s per turn" % (ref["threads"], ", ".join(f"{t:.2f}" for t in ref["times"])))
    print("jaxtalk: %s s per turn (turn 1 includes compiling)" % ", ".join(f"{t:.2f}" for t in ours["times"]))
    print(f"median after turn 1: reference {r_med:.2f} s, jaxtalk {j_med:.2f} s: jaxtalk {r_med / j_med:.1f}x faster")
    print(f"jaxtalk: {flops / 1e9:.1f} GFLOP per turn, {flops / j_med / 1e9:.1f} GFLOP/s = "
          f"{flops / j_med / ours['peak']:.0%} of the measured matmul peak ({ours['peak'] / 1e9:.1f} GFLOP/s)")
    from jaxtalk.benchmarking import machine_info, write_json

    write_json(args.out, {"machine": machine_info(), "turns": args.turns, "steps": STEPS, "cfg": CFG,
                          "reference_threads": ref["threads"], "reference_s": ref["times"], "jaxtalk_s": ours["times"],
                          "reference_median_s": r_med, "jaxtalk_median_s": j_med, "reference_over_jaxtalk": r_med / j_med,
                          "gflop_per_turn": flops / 1e9, "matmul_peak_gflop_s": ours["peak"] / 1e9,
                          "of_peak": flops / j_med / ours["peak"]})
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
