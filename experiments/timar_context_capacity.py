"""Can TIMAR's encoder learn the mimicry context when that is all it is trained for?

``timar_context_probe.py`` finds that a trained TIMAR's head conditions carry no more of the context
than a freshly initialised encoder's. This separates the two explanations left: the ARCHITECTURE (the
encoder cannot turn the window into the lagged partner motion a linear probe reads) or TIMAR's
TRAINING (the diffusion objective over all 56 channels, at this budget, does not make it). The same
encoder, config and optimiser as the TIMAR model given with ``--like``, on the same windows (every
agent frame masked, as at inference), is trained with one linear readout of the neck and the squared
error of the neck alone, each window's prediction and target centred on their own means (the probe's
within-side target: a speaker's rest pose is not context). Its head conditions then go through
``timar_context_probe.py`` like TIMAR's.

Usage: python experiments/timar_context_capacity.py --like MODEL.pkl --size full --effects mimicry_1.2
       --cache-dir DIR --steps 1500 --seed 1 --out MODEL_OUT.pkl
"""

from __future__ import annotations

import argparse
import functools
import time

import jax
import jax.numpy as jnp

from jaxtalk.models.turns.streams import to_turns
from jaxtalk.layout import NECK_SLICE
from jaxtalk.models.timar.data import Normalizer
from jaxtalk.models.timar.encoder import init_encoder
from jaxtalk.models.timar.loss import STREAMS
from jaxtalk.models.timar.model import encode_window
from jaxtalk.runs import RunSettings
from jaxtalk.train.recipes import TrainSettings
from jaxtalk.models.turns.training import train_on_turn_windows

from timar_common import EFFECTS, load_model, open_prepared, save_model  # noqa: E402


def init_params(config, key) -> dict:
    """TIMAR's encoder and a zero linear readout of the 3 neck channels from each frame's condition."""
    return {"encoder": init_encoder(config, key),
            "readout": {"w": jnp.zeros((config.width, 3), jnp.float32), "b": jnp.zeros((3,), jnp.float32)}}


def neck_loss(config, params, batch, key):
    """Squared error of the centred neck (per window), every agent frame masked."""
    f = config.frames_per_turn
    us, um, as_, am = (to_turns(jnp.asarray(batch[k], jnp.float32), f) for k in STREAMS)
    z = encode_window(params, config, us, um, as_, None, None, None)  # (B, N, F, width)
    pred = z @ params["readout"]["w"] + params["readout"]["b"]
    target = am[..., NECK_SLICE]
    centre = lambda x: x - x.mean(axis=(1, 2), keepdims=True)  # noqa: E731
    loss = jnp.mean((centre(pred) - centre(target)) ** 2)
    return loss, {"loss_neck": loss}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--like", required=True, help="the TIMAR model whose config to use (timar_common.save_model)")
    ap.add_argument("--size", default="full")
    ap.add_argument("--effects", default="mimicry_1.2", choices=sorted(EFFECTS))
    ap.add_argument("--cache-dir", default=".cache/prepared")
    ap.add_argument("--steps", type=int, default=1500)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    config, _, _ = load_model(args.like)
    optim = TrainSettings(lr=args.lr, warmup_steps=args.warmup, final_lr_ratio=0.1).optim(args.steps)
    t0 = time.perf_counter()
    result = train_on_turn_windows(
        "timar-neck-readout", config, open_prepared(args), optim, init_params,
        lambda c: functools.partial(neck_loss, c), key=jax.random.key(args.seed),
        run=RunSettings(steps=args.steps, batch_size=args.batch, seed=args.seed), predict=None, val_clips=0)
    losses = [float(h["loss"]) for h in result.history if "loss" in h]
    print(f"{args.steps} steps in {time.perf_counter() - t0:.0f} s; loss {losses[0]:.4f} -> "
          f"{sum(losses[-50:]) / len(losses[-50:]):.4f} (last 50)")
    save_model(args.out, config, result.state.eval_params, Normalizer.from_dict(result.extra["normalizer"]))
    print(f"saved {args.out}")


if __name__ == "__main__":
    main()
