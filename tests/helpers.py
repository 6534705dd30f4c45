"""Small helpers several test modules share (import as ``from helpers import ...``)."""

from __future__ import annotations

import functools

import jax


@functools.partial(jax.jit, static_argnames="scale")
def perturbed(params, key, scale: float = 0.05):
    """``params`` plus ``scale`` x standard-normal noise on every leaf.

    Zero-initialised layers (adaLN modulations, output projections) make a fresh model's output exactly
    0 or its input; tests of what a layer computes perturb them first so that comparisons see signal.
    """
    leaves, tree = jax.tree.flatten(params)
    keys = jax.random.split(key, len(leaves))
    return jax.tree.unflatten(tree, [x + scale * jax.random.normal(k, x.shape) for x, k in zip(leaves, keys)])


def timar_streams(batch: int, frames: int, seed: int = 0, speech_dim: int = 8) -> dict:
    """Random float32 TIMAR inputs, ``(batch, frames, .)``: both speakers' speech and motion."""
    import numpy as np

    rng = np.random.default_rng(seed)
    return {
        "user_speech": rng.normal(size=(batch, frames, speech_dim)).astype(np.float32),
        "user_motion": rng.normal(size=(batch, frames, 56)).astype(np.float32),
        "agent_speech": rng.normal(size=(batch, frames, speech_dim)).astype(np.float32),
        "agent_motion": rng.normal(size=(batch, frames, 56)).astype(np.float32),
    }
