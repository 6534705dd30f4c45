"""Shared pieces of the TokTalk experiments: corpus, trained ``small`` model (cached), evaluation.

The base model is the demo's (:func:`jaxtalk.demo.train_or_load`: TokTalk's recipe through
:func:`jaxtalk.commands.training.train_run`, as ``jaxtalk train toktalk``), trained into a run folder
under ``experiments/results/toktalk_cache/`` keyed by corpus, steps and seed (``jaxtalk sample`` /
``jaxtalk stream`` take it as RUN); the stage-2 adapter is cached beside it, so the sweep and the
quality table reuse one training run. Stage 2 is TokTalk's adapter recipe
(:func:`jaxtalk.models.toktalk.recipe.train_adapter`) on the same prepared corpus, with SynthTalk's
stream B as the source.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.data import synthtalk
from jaxtalk.data.loader import open_data
from jaxtalk.data.sources.synthtalk import clip_name
from jaxtalk.demo import DemoOptions, cache_dir, data_spec, model_config, train_or_load
from jaxtalk.metrics import fdd, jitter, lve, mod
from jaxtalk.models import toktalk as tt
from jaxtalk.models.toktalk.recipe import train_adapter
from jaxtalk.runs import RunSettings
from jaxtalk.train import LoopSettings, OptimConfig

RESULTS = Path(__file__).resolve().parent / "results"
CACHE = RESULTS / "toktalk_cache"
# Prepared SynthTalk (open_data's cache); its "synthtalk/" folder is also the in-memory corpus's cache.
DATA = CACHE / "data"


def load_corpus(size: str, seed: int = 0):
    return synthtalk.generate(size, seed, cache_dir=os.environ.get("JAXTALK_CACHE", DATA / "synthtalk"))


def _save(path: Path, params) -> None:
    flat = {jax.tree_util.keystr(k): np.asarray(v) for k, v in jax.tree_util.tree_flatten_with_path(params)[0]}
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **flat)


def _load(path: Path, like):
    with np.load(path) as z:
        leaves = [jnp.asarray(z[jax.tree_util.keystr(k)]) for k, _ in jax.tree_util.tree_flatten_with_path(like)[0]]
    return jax.tree.unflatten(jax.tree.structure(like), leaves)


def trained_small(corpus, steps: int, adapter_steps: int, seed: int = 0, chunk_frames: int = 10):
    """The demo's base model (same recipe, :func:`jaxtalk.demo.train_or_load`) then stage 2 on stream B,
    trained at a streaming chunk of ``chunk_frames`` (a training setting: the chunk mask and window).

    Both stages are cached under ``toktalk_cache/`` (the base as a resumable run folder, the adapter
    as ``.npz``). Returns ``(config, params, info)``.
    """
    if seed != corpus.seed:
        raise ValueError(f"the demo's run trains on SynthTalk of its own seed: seed={seed} but corpus.seed={corpus.seed}")
    cfg = model_config(chunk_frames)
    # "-causal-": the causal (streaming) model; folders of the older offline model are not reused.
    options = DemoOptions(out_dir=CACHE / (f"{corpus.key}-causal-n{model_config(chunk_frames).noise_frames:g}"
                                           f"-s{steps}-c{chunk_frames}-seed{seed}"),
                          size=corpus.size, seed=seed, train_steps=steps, progress=True, cache_dir=DATA,
                          chunk_frames=chunk_frames)
    t0 = time.perf_counter()
    trained = train_or_load(options)
    base, history = jax.tree.map(jnp.asarray, trained.params), trained.history
    t1 = time.perf_counter()
    path = options.out_dir / f"adapter-a{adapter_steps}.npz"
    like = jax.eval_shape(lambda k: tt.init_params(cfg, k, adapter_src_dim=48), jax.random.key(0))
    info = {"base_run": str(options.out_dir), "stage1_s": t1 - t0,
            "stage1_final_loss": history[-1]["loss"] if history else None}
    if path.is_file():
        return cfg, _load(path, like), {**info, "adapter_cached": str(path)}
    stream_b = {clip_name(i): np.asarray(corpus.tokens(i, "B").embeddings, np.float32) for i in range(len(corpus.clips))}
    adapted = train_adapter(cfg, open_data(data_spec(options), cache_dir=cache_dir(options)),
                            OptimConfig(lr=5e-4, warmup_steps=min(20, adapter_steps // 10), total_steps=adapter_steps,
                                        weight_decay=0.0),
                            base_params=base, src_tokens=stream_b, src_rate=25.0, key=jax.random.key(seed + 1),
                            run=RunSettings(batch_size=16, seed=seed, window_frames=options.window_frames,
                                            loop=LoopSettings(log_every=50)))
    params = adapted.state.params
    _save(path, params)
    return cfg, params, {**info, "stage2_s": time.perf_counter() - t1,
                         "stage2_final_loss": adapted.history[-1]["loss"]}


def style_clip_for(corpus, clip: int, frames: int, rng: np.random.Generator) -> np.ndarray:
    """Up to ``frames`` frames of another clip of the same speaker (the clip itself when the speaker has
    no other), ``(1, S, D)``; a shorter clip is used whole (padding would bias its mean pose)."""
    sp = corpus.clips[clip].speaker
    others = [c.index for c in corpus.clips if c.speaker == sp and c.index != clip] or [clip]
    ref = np.asarray(corpus.motion(others[int(rng.integers(len(others)))]), np.float32)
    r0 = int(rng.integers(max(ref.shape[0] - frames, 0) + 1))
    return ref[r0 : r0 + frames][None]


def evaluate(corpus, pred: np.ndarray, clip: int, chunk: int | None = None) -> dict:
    """MSE (params), LVE (lip vertices, mm^2), FDD (upper face, mm^2), MOD (mm) and jitter (all frames /
    near chunk boundaries)."""
    gt = np.asarray(corpus.motion(clip))
    n = min(len(gt), len(pred))
    gt, pred = gt[:n], pred[:n]
    face = corpus.face(0)
    lips = np.asarray(face.regions["lips"])
    v_gt, v_pred = np.asarray(face.vertices_seq(gt)), np.asarray(face.vertices_seq(pred))
    template = np.asarray(face.vertices(np.zeros(gt.shape[1], np.float32)))
    out = {
        "frames": n,
        "mse": float(np.mean(np.square(pred - gt))),
        "lve_mm2": float(lve(v_pred, v_gt, lips)) * 1e6,
        "fdd_mm2": float(fdd(v_pred, v_gt, template, np.asarray(face.regions["upper_face"]))) * 1e6,
        "mod_mm": float(mod(v_pred, v_gt, np.asarray(face.regions["mouth_upper"]),
                            np.asarray(face.regions["mouth_lower"]))) * 1e3,
        "jitter": float(jitter(pred)),
    }
    if chunk is not None and n > chunk + 1:
        out["jitter_boundary"] = float(jitter(pred, list(range(chunk, n - 1, chunk))))
    return out


def weighted_mean(rows: list[dict], key: str) -> float:
    w = np.array([r["frames"] for r in rows], float)
    return float(np.sum(w * np.array([r[key] for r in rows])) / w.sum())
