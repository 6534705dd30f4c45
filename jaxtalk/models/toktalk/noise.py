"""The flow's starting noise: white, or correlated over time (``TokTalkConfig.noise_frames``).

Flow matching transports ANY source distribution to the data; the paper's is white Gaussian noise. A
decoder that does not fully remove the noise passes what it leaves straight into the samples, and
white noise left over is all high frequency: on SynthTalk the ``small`` model's denoised estimate at
mid flow times carried 3-6x the data's acceleration energy and its 10-step samples 13x the data's jitter.
With ``noise_frames = s > 0`` the noise is white noise smoothed over time by a Gaussian kernel of
standard deviation ``s`` frames and rescaled to unit variance per frame, so every frame is still
``N(0, 1)`` (the preconditioning's assumption) but neighbouring frames are correlated
(``corr(lag) = exp(-lag^2 / (4 s^2))``) and leftover noise is smooth motion rather than jitter.

Offline noise is drawn with ``3 s`` extra frames of white noise on each side, so it is stationary up to
the edges; the streaming engine's fixed buffer is smoothed cyclically, so that frame ``f``'s noise is
``buffer[f mod N]`` with the same statistics everywhere.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.types import Array, Float, PRNGKeyArray

__all__ = ["noise_kernel", "prior_noise", "cyclic_prior_noise"]


def noise_kernel(frames: float) -> Float[np.ndarray, " taps"]:
    """Gaussian taps of standard deviation ``frames`` (truncated at 3 sd), scaled to unit energy so
    that smoothing white noise keeps its variance at 1."""
    if frames <= 0:
        return np.ones(1)
    r = max(1, math.ceil(3 * frames))
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / frames) ** 2)
    return k / np.sqrt(np.sum(k * k))


def _smooth(white: Array, kernel: np.ndarray) -> Array:
    """Valid convolution over axis 1 of ``(B, T + 2r, D)`` -> ``(B, T, D)``."""
    r = (kernel.shape[0] - 1) // 2
    t = white.shape[1] - 2 * r
    k = jnp.asarray(kernel, white.dtype)
    return sum(k[i] * white[:, i : i + t] for i in range(kernel.shape[0]))


def prior_noise(
    key: PRNGKeyArray, shape: tuple[int, int, int], frames: float, dtype=jnp.float32
) -> Float[Array, "batch time dim"]:
    """``(B, T, D)`` starting noise: white for ``frames == 0``, else smoothed over time (see the module)."""
    kernel = noise_kernel(frames)
    if kernel.shape[0] == 1:
        return jax.random.normal(key, shape, dtype)
    r = (kernel.shape[0] - 1) // 2
    b, t, d = shape
    return _smooth(jax.random.normal(key, (b, t + 2 * r, d), dtype), kernel)


def cyclic_prior_noise(
    key: PRNGKeyArray, shape: tuple[int, int, int], frames: float, dtype=jnp.float32
) -> Float[Array, "batch time dim"]:
    """Like :func:`prior_noise` but smoothed circularly: row ``T - 1`` is followed by row 0 with the
    same correlation, for a buffer read at ``f mod T``."""
    kernel = noise_kernel(frames)
    white = jax.random.normal(key, shape, dtype)
    if kernel.shape[0] == 1:
        return white
    r = (kernel.shape[0] - 1) // 2
    if r > shape[1]:
        raise ValueError(f"a noise buffer of {shape[1]} frames is shorter than the noise kernel's reach ({r})")
    wrapped = jnp.concatenate([white[:, -r:], white, white[:, :r]], axis=1)
    return _smooth(wrapped, kernel)
