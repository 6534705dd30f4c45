"""Shared pieces of the TIMAR experiments (``timar_context``, ``timar_ablation``, ``timar_dualtalk``):
command-line training knobs, training on SynthTalk, streaming predictions (and the DualTalk baseline's
turn-window predictions), metrics and the pickled model format.

Training goes through TIMAR's recipe (:func:`jaxtalk.models.timar.recipe.train`, what ``jaxtalk train
timar`` runs) on the prepared corpus (``open_data("synthtalk:SIZE")``): 8-turn windows every turn of
both role assignments of every training conversation, standardised with the recipe's normaliser.
Evaluation streams the in-memory corpus's conversations (the same per-turn speech features, checked by
the data tests) with that normaliser.
"""

from __future__ import annotations

import argparse
import dataclasses
import pickle
from pathlib import Path

from typing import Any

import jax
import numpy as np

from jaxtalk.data.synthtalk import DEFAULT_EFFECTS
from jaxtalk.data.synthtalk.dyadic import DyadicEffects
from jaxtalk.layout import GROUPS
from jaxtalk.metrics.conversation import conversation_metrics
from jaxtalk.models.timar import TimarConfig
from jaxtalk.models.timar.data import Normalizer
from jaxtalk.models.timar.streaming import stream
from jaxtalk.runs import RunSettings
from jaxtalk.train.recipes import TrainSettings


def add_training_args(ap: argparse.ArgumentParser, *, steps: int = 2000) -> None:
    """Corpus, optimiser and CPU-budget model knobs shared by the training experiments.

    Defaults: the ``small`` corpus and the ``small`` preset's sizes.
    """
    ap.add_argument("--size", default="small", help="SynthTalk size (full: 120 train speakers, 12 test conversations)")
    ap.add_argument("--cache-dir", default=".cache/prepared",
                    help="SynthTalk and its prepared copy (the default is jaxtalk train's)")
    ap.add_argument("--steps", type=int, default=steps)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--width", type=int, default=128)
    ap.add_argument("--layers", type=int, default=4)
    ap.add_argument("--head-width", type=int, default=128)
    ap.add_argument("--head", default="diffusion", choices=("diffusion", "mlp"),
                    help="the per-frame head: the paper's diffusion head, or the MLP regression of Table 2's ablation")
    ap.add_argument("--warmup", type=int, default=20, help="learning-rate warm-up steps")
    ap.add_argument("--batch-mul", type=int, default=1, help="diffusion (t, noise) draws per frame (MAR: 4)")
    ap.add_argument("--seed", type=int, default=0, help="training seed (initialisation, batches, diffusion noise)")
    ap.add_argument("--effects", default="default", choices=sorted(EFFECTS),
                    help="the corpus's dyadic effect strengths: default, or a control corpus (see EFFECTS)")


# SynthTalk's dyadic strengths: the built-in ones, none, and control corpora with each raised (mimicry
# stays below 1.25: the per-speaker gains are 0.5-0.8 x mimicry, and an echo of an echo must decay).
EFFECTS: dict[str, DyadicEffects] = {
    "default": DEFAULT_EFFECTS,
    "off": DyadicEffects(mimicry=0.0, mood=0.0),
    "mood_x4": DyadicEffects(mood=4 * DEFAULT_EFFECTS.mood),
    "mood_x4_tau10": DyadicEffects(mood=4 * DEFAULT_EFFECTS.mood, mood_tau=10.0),
    "mimicry_1.2": DyadicEffects(mimicry=1.2),
    "all_raised": DyadicEffects(mimicry=1.2, mood=4 * DEFAULT_EFFECTS.mood, mood_tau=10.0),
}


def _spec(args):
    from jaxtalk.data.synthtalk.corpus import SIZES

    return dataclasses.replace(SIZES[args.size], effects=EFFECTS[getattr(args, "effects", "default")])


def load_corpus(args):
    """The SynthTalk corpus of ``--size`` (with ``--effects``) from the cache the prepared copy is made from
    (one generation)."""
    from jaxtalk.data.synthtalk import generate

    name = getattr(args, "effects", "default")
    return generate(args.size if name == "default" else _spec(args), 0, cache_dir=Path(args.cache_dir) / "synthtalk")


def open_prepared(args):
    """The prepared corpus of ``--size`` and ``--effects`` (a control corpus is prepared once, beside
    ``jaxtalk train``'s ``synthtalk:SIZE``)."""
    from jaxtalk.data.loader import PreparedData, open_data

    name = getattr(args, "effects", "default")
    if name == "default":
        return open_data(f"synthtalk:{args.size}", cache_dir=args.cache_dir)
    out = Path(args.cache_dir) / f"synthtalk-{args.size}-effects-{name}-seed0"
    from jaxtalk.data.prepare import is_current

    if not is_current(out):
        from jaxtalk.data.prepare import prepare
        from jaxtalk.data.sources import synthtalk_source

        prepare(synthtalk_source(load_corpus(args), f"synthtalk:{args.size}:0 effects={EFFECTS[name]}"), out)
    return PreparedData(out)


def model_config(args, **overrides) -> TimarConfig:
    """The ``small`` preset at the command line's sizes, 8-turn windows."""
    return TimarConfig.small(max_turns=8, width=args.width, num_layers=args.layers, head_width=args.head_width,
                             num_heads=max(1, args.width // 32), diffusion_batch_mul=args.batch_mul,
                             **{"head": args.head, **overrides})


def train_model(args, config: TimarConfig, *, ckpt_dir=None, max_steps: int | None = None,
                seed: int = 0) -> tuple[Any, Normalizer, int]:
    """Train ``config`` for ``--steps`` through TIMAR's recipe on the prepared corpus (AdamW ``--lr``,
    ``--warmup`` warm-up, cosine to 0.1 x, batch ``--batch``; stop early at ``max_steps``, checkpointed in
    ``ckpt_dir``).

    Returns:
        ``(loop result, normaliser, training windows)``.
    """
    from jaxtalk.models.timar import recipe

    optim = TrainSettings(lr=args.lr, warmup_steps=args.warmup, final_lr_ratio=0.1).optim(args.steps)
    data = open_prepared(args)
    result = recipe.train(config, data, optim, key=jax.random.key(seed),
                          run=RunSettings(steps=max_steps or args.steps, batch_size=args.batch, seed=seed,
                                          ckpt_dir=ckpt_dir))
    return result, Normalizer.from_dict(result.extra["normalizer"]), result.windows


KEYS = ("FD_exp", "FD_jaw", "FD_pose", "P-FD_exp", "MSE_exp", "MSE_jaw", "MSE_pose", "MSE_mouth_spk", "MSE_jaw_spk",
        "SID_fit_gt_exp", "rPCC_exp")


def padded_streams(convs, normalizer) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(user_speech, user_motion, agent_speech)`` of conversation sides, standardised and stacked
    into one batch, each side padded with zeros at its end to the longest side. Exact for a turn-causal
    stream cropped back to each side's length (padding after a side's last turn cannot reach it)."""
    longest = max(c.num_frames for c in convs)

    def stack(field, scale):
        return np.stack([np.pad(scale(getattr(c, field)), ((0, longest - c.num_frames), (0, 0))) for c in convs])

    return (stack("user_speech", normalizer.speech), stack("user_motion", normalizer.motion),
            stack("agent_speech", normalizer.speech))


def predict(config, params, normalizer, convs, *, context, cfg_scale, temperature=1.0, sampler="ddim", seed=0):
    """Stream every conversation with ``context`` turns of history; raw (denormalised) motion.

    ``temperature`` scales the initial diffusion noise (1: samples of the learned distribution, the
    paper's sampling); ``sampler="mean"`` gives the guided posterior mean instead (see ``sample_frames``).
    """
    out = []
    for i, c in enumerate(convs):
        x = stream(
            params, config, normalizer.speech(c.user_speech)[None], normalizer.motion(c.user_motion)[None],
            normalizer.speech(c.agent_speech)[None], jax.random.key(seed + i), context=context, cfg_scale=cfg_scale,
            temperature=temperature, sampler=sampler,
        )
        out.append(normalizer.unmotion(np.asarray(x)[0]))
    return out


def predict_dualtalk(config, params, normalizer, convs, *, context):
    """The DualTalk baseline on every conversation at ``context`` turns of history; raw (denormalised) motion.

    Turn t of a conversation comes from the window of turns ``[max(0, t - context), t]`` (both
    speakers' speech and the user's motion, standardised with ``normalizer`` as :func:`predict` does),
    the whole current turn included, as DualTalk reads a whole clip: Table 1's progressive-context
    protocol (:func:`jaxtalk.models.dualtalk.predict_turns`). Deterministic: no seed.
    """
    from jaxtalk.models.dualtalk import predict_turns

    out = []
    for c in convs:
        x = predict_turns(params, config, normalizer.speech(c.user_speech)[None], normalizer.motion(c.user_motion)[None],
                          normalizer.speech(c.agent_speech)[None], context=context)
        out.append(normalizer.unmotion(np.asarray(x)[0]))
    return out


def metrics(preds, convs, corpus=None):
    """DualTalk metrics (published scaling) plus MSE of the audio-predictable groups.

    On SynthTalk most of the exp variance is a per-speaker/per-emotion offset no audio reveals, so a
    SAMPLE of a correct model scores about twice the conditional variance on MSE_exp and loses to the
    mean pose there; the mean pose in turn has no motion at all, so FD/P-FD (distribution match)
    is where it is poor. ``MSE_mouth_spk`` / ``MSE_jaw_spk`` (mouth = 12 lip components + jaw, on the
    agent's speaking frames, raw units) measure what the audio does determine.
    """
    out = conversation_metrics(preds, [c.agent_motion for c in convs], [c.user_motion for c in convs], scaled=True)
    if corpus is not None:
        for group in ("mouth", "jaw"):
            idx = GROUPS[group]
            errs = []
            for p, c in zip(preds, convs):
                speaking = corpus.voice_activity(c.agent_clip)[: c.num_frames]
                errs.append(((p - c.agent_motion)[speaking][:, idx] ** 2).mean())
            out[f"MSE_{group}_spk"] = float(np.mean(errs))
    return out


def save_model(path, config, params, norm) -> None:
    """Pickle the trained model (config fields, NumPy parameters, normaliser) for other scripts."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as f:
        pickle.dump({"config": dataclasses.asdict(config), "params": jax.device_get(params),
                     "normalizer": norm.to_dict()}, f)


def load_model(path):
    """``(config, params, normaliser)`` written by :func:`save_model`."""
    with open(path, "rb") as f:
        d = pickle.load(f)
    return TimarConfig(**d["config"]), d["params"], Normalizer.from_dict(d["normalizer"])


def context_sensitivity(config, params, normalizer, convs, *, cfg_scale, windows_per_conv=4, seed=0):
    """How much the last turn of an 8-turn window moves when parts of the input are swapped.

    Posterior means (``sampler="mean"``, so no sampling noise) of the LAST turn of windows of
    ``max_turns`` turns (= streaming with n = max_turns - 1), recomputed with (a) the user's streams
    of the PAST turns, (b) the user's streams of the CURRENT turn, (c) the agent's speech of the past
    turns taken from another conversation (same window position). Returns the RMS change per group
    (exp / jaw / neck) in normalised units, and the RMS of the original output's deviation from 0
    (the training mean) for scale.
    """
    from jaxtalk.models.timar.config import LOSS_GROUPS
    from jaxtalk.models.timar.sampling import sample

    f, n = config.frames_per_turn, config.max_turns
    length = n * f
    win = {"us": [], "um": [], "as": []}
    for c in convs:
        starts = np.linspace(0, c.num_frames - length, windows_per_conv).astype(int) // f * f
        for s in starts:
            sl = slice(s, s + length)
            win["us"].append(normalizer.speech(c.user_speech[sl]))
            win["um"].append(normalizer.motion(c.user_motion[sl]))
            win["as"].append(normalizer.speech(c.agent_speech[sl]))
    win = {k: np.stack(v) for k, v in win.items()}
    other = {k: np.roll(v, windows_per_conv, axis=0) for k, v in win.items()}  # another conversation's window
    past, cur = slice(0, length - f), slice(length - f, length)

    def last_turn(us, um, as_):
        x = sample(params, config, us, um, as_, jax.random.key(seed), cfg_scale=cfg_scale, sampler="mean")
        return np.asarray(x)[:, -f:]

    def swap(name, part):
        x = win[name].copy()
        x[:, part] = other[name][:, part]
        return x

    base = last_turn(win["us"], win["um"], win["as"])
    variants = {
        "user past turns": last_turn(swap("us", past), swap("um", past), win["as"]),
        "user current turn": last_turn(swap("us", cur), swap("um", cur), win["as"]),
        "agent speech past turns": last_turn(win["us"], win["um"], swap("as", past)),
    }
    rms = lambda d, lo, hi: float(np.sqrt(np.mean(d[..., lo:hi] ** 2)))  # noqa: E731
    out = {"output": {g: rms(base, lo, hi) for g, lo, hi in LOSS_GROUPS}}
    for name, x in variants.items():
        out[name] = {g: rms(x - base, lo, hi) for g, lo, hi in LOSS_GROUPS}
    return out
