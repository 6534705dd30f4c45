"""Positive control for "silence is silence": does the tokenizer's causal noise-floor normaliser keep a
trained TokTalk's mouth at its style's rest in background noise, where the same model without it does not?

Two corpora that differ only in the normaliser: SynthTalk ``tiny+mic`` (every clip through its own
recording chain, tokens read through the 2-s normaliser) and the same with ``noise_floor_seconds=0``.
On each, the ``small`` TokTalk trains ``--steps`` steps (seeds as given) exactly as the learning test
trains it; then, in the style of a neutral training clip, it streams 8 s of steady white noise at
-70 to -20 dBFS, a -90 dBFS dither and digital zero. Reported per level: the jaw's mean after the
first second minus the style clip's rest (``style_rest_jaw``); and, as the check that the model
opens the mouth at all, its jaw in speech and silence on the held-out monologues (each in the style of
another clip of its speaker) and their LVE against the mean pose's.

    python experiments/silence_normaliser.py --steps 300 --seeds 0 1 --out experiments/results/real_voice/silence_normaliser.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
from pathlib import Path

import jax
import numpy as np

from jaxtalk.audio import VQTokenizer
from jaxtalk.data import synthtalk
from jaxtalk.data.loader import PreparedData
from jaxtalk.data.prepare import prepare
from jaxtalk.data.sources import synthtalk_source
from jaxtalk.face import builtin_face
from jaxtalk.layout import JAW_OPEN_INDEX
from jaxtalk.metrics import lve
from jaxtalk.metrics.speech_sync import style_rest_jaw
from jaxtalk.models import toktalk as tt
from jaxtalk.models.toktalk import recipe
from jaxtalk.models.toktalk.sampling import default_grid
from jaxtalk.runs import RunSettings
from jaxtalk.train import LoopSettings, OptimConfig

SR = 16000
LEVELS_DB = (-70, -60, -50, -40, -30, -20)


def _corpus(normaliser: bool, cache: Path) -> PreparedData:
    base = synthtalk.SIZES["tiny+mic"]
    spec = base if normaliser else dataclasses.replace(base, noise_floor_seconds=0.0)
    corpus = synthtalk.generate(spec, 0, cache_dir=cache / "synthtalk")
    out = cache / ("prepared-normaliser" if normaliser else "prepared-none")
    prepare(synthtalk_source(corpus, spec=f"synthtalk:tiny+mic:0 normaliser={normaliser}"), out, progress=False)
    return PreparedData(out)


def _inputs() -> dict[str, np.ndarray]:
    n = 8 * SR
    rng = np.random.default_rng(0)
    out = {f"noise {db} dBFS": (10 ** (db / 20) * rng.standard_normal(n)).astype(np.float32) for db in LEVELS_DB}
    out["dither -90 dBFS"] = (10 ** (-90 / 20) * rng.standard_normal(n)).astype(np.float32)
    out["digital zero"] = np.zeros(n, np.float32)
    return out


def _run(data: PreparedData, steps: int, seed: int) -> dict:
    cfg = tt.TokTalkConfig.small()
    t0 = time.perf_counter()
    result = recipe.train(cfg, data, OptimConfig(lr=recipe.DEFAULTS.lr, warmup_steps=50, total_steps=steps,
                                                 ema_decay=recipe.DEFAULTS.ema_decay),
                          key=jax.random.key(seed), run=RunSettings(batch_size=16, loop=LoopSettings(progress=False)),
                          val_clips=0)
    train_s = time.perf_counter() - t0
    params = result.state.eval_params
    tokenizer = VQTokenizer.load(data.root / data.manifest["tokenizer"])
    ts = default_grid(cfg, 1)

    def stream(tokens: np.ndarray, style, key: int) -> np.ndarray:
        return np.asarray(tt.stream(params, cfg, np.asarray(tokens, np.float32)[None], style,
                                    jax.random.key(key), ts=ts))[0]

    # The style: the longest neutral training monologue.
    neutral = [i for i in data.split("train") if data.clips[i]["emotion"] == "neutral" and data.clips[i]["tokens"]]
    ref_clip = max(neutral, key=lambda i: data.clips[i]["frames"])
    ref = data.record(ref_clip, ("motion",))["motion"][: 4 * cfg.style_frames]
    style = tt.encode_style(params, cfg, ref[None])
    rest = style_rest_jaw(ref[:, JAW_OPEN_INDEX])
    silence = {}
    for name, audio in _inputs().items():
        jaw = stream(tokenizer.encode(audio).embeddings, style, 0)[25:200, JAW_OPEN_INDEX]
        silence[name] = float(jaw.mean() - rest)

    face = builtin_face(0)
    lips = np.asarray(face.regions["lips"])
    mean_pose = np.asarray(params["norm"]["mean"], np.float32)
    test = [i for i in data.split("test") if data.clips[i]["tokens"] and not data.clips[i]["partner"]]
    by_speaker: dict[str, list[int]] = {}
    for i in test:
        by_speaker.setdefault(data.clips[i]["speaker"], []).append(i)
    errors, base, jaw_speech, jaw_silent = [], [], [], []
    for n, i in enumerate(test):
        rec = data.record(i, ("motion", "tokens"))
        gt = np.asarray(rec["motion"], np.float32)
        # Held-out speakers are animated in their own style: another clip of theirs, as the learning test does.
        other = next((j for j in by_speaker[data.clips[i]["speaker"]] if j != i), i)
        own = tt.encode_style(params, cfg, data.record(other, ("motion",))["motion"][None, : 4 * cfg.style_frames])
        out = stream(rec["tokens"], own, n + 1)[: gt.shape[0]]
        v_gt = np.asarray(face.vertices_seq(gt))
        errors.append(float(lve(np.asarray(face.vertices_seq(out)), v_gt[: out.shape[0]], lips)) * 1e6)
        base.append(float(lve(np.asarray(face.vertices_seq(np.broadcast_to(mean_pose, gt.shape))), v_gt, lips)) * 1e6)
        # Speech vs silence from the ground truth's own jaw: open beyond its rest by 0.03 rad.
        gt_rest = style_rest_jaw(gt[:, JAW_OPEN_INDEX])
        talking = gt[: out.shape[0], JAW_OPEN_INDEX] > gt_rest + 0.03
        jaw_speech.append(float((out[talking, JAW_OPEN_INDEX] - gt_rest).mean()))
        jaw_silent.append(float((out[~talking, JAW_OPEN_INDEX] - gt_rest).mean()))
    return {"seed": seed, "steps": steps, "train_s": train_s, "style_clip": int(ref_clip), "style_rest_jaw": rest,
            "jaw_minus_style_rest": silence,
            "heldout_monologues": {"clips": len(test), "LVE_mm2": float(np.mean(errors)),
                                   "mean_pose_LVE_mm2": float(np.mean(base)),
                                   "jaw_minus_rest_where_gt_talks": float(np.mean(jaw_speech)),
                                   "jaw_minus_rest_where_gt_rests": float(np.mean(jaw_silent))}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--cache", type=Path, default=None, help="corpus and prepared-data folder (default: a temporary one)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    results: dict = {"steps": args.steps, "levels_db": list(LEVELS_DB), "runs": {}}
    with tempfile.TemporaryDirectory() as tmp:
        cache = args.cache or Path(tmp)
        for normaliser in (True, False):
            data = _corpus(normaliser, cache)
            name = "normaliser" if normaliser else "no normaliser"
            results["runs"][name] = [_run(data, args.steps, seed) for seed in args.seeds]
            print(json.dumps({name: results["runs"][name]}, indent=1), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
