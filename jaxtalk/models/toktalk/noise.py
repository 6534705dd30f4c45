"""The flow's starting noise: white, or correlated over time (``TokTalkConfig.noise_frames``).

Flow matching transports ANY source distribution to the data; the paper's is white Gaussian noise. A
decoder that does not fully remove the noise passes what it leaves straight into the samples, and
white noise left over is all high frequency, so it shows as jitter in the samples (the measurement:
docs/design-decisions.md). With ``noise_frames = s > 0`` the noise is white noise smoothed over time by
a Gaussian kernel of standard deviation ``s`` frames and rescaled to unit variance per frame, so every
frame is still ``N(0, 1)`` (the preconditioning's assumption) but neighbouring frames are correlated
(``corr(lag) = exp(-lag^2 / (4 s^2))``) and leftover noise is smooth motion rather than jitter.

Offline noise is drawn with ``3 s`` extra frames of white noise on each side, so it is stationary up to
the edges. The streaming engine needs the noise of an absolute frame to be the same whenever that frame
is regenerated as left context, for utterances of any length: :func:`frame_noise` draws the white noise
of frame ``f`` from ``fold_in(key, f)`` and smooths it over its neighbours' draws, so the noise is a
fixed function of ``(key, f)`` that never repeats (a buffer read at ``f mod N`` would repeat every
``N`` frames, 40 s for a 1,000-frame buffer).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.types import Array, Float, Int, PRNGKeyArray

__all__ = ["noise_kernel", "prior_noise", "frame_noise", "frame_white_noise", "smooth_noise"]


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


def frame_noise(
    key: PRNGKeyArray,
    first_frame: Int[Array, ""] | int,
    frames: int,
    batch: int,
    dim: int,
    noise_frames: float,
    dtype=jnp.float32,
) -> Float[Array, "batch time dim"]:
    """The starting noise of absolute frames ``first_frame .. first_frame + frames - 1`` of a stream.

    Frame ``f``'s white noise is ``normal(fold_in(key, f), (batch, dim))``; with ``noise_frames > 0``
    it is smoothed over the white noise of frames ``f - r .. f + r`` as :func:`prior_noise` does. The
    result depends only on ``key`` and the absolute frame, never on which window asks for it, so the
    same frame gets the same noise in every window and the sequence never repeats. Frames before the
    utterance (negative indices) get noise too (the stream masks them out).

    Args:
        key: the stream's noise key.
        first_frame: absolute index of the first frame (may be traced).
        frames: number of frames (static).
        batch: parallel streams (each its own noise).
        dim: the motion width.
        noise_frames: the correlation length (``TokTalkConfig.noise_frames``; 0: white).
        dtype: floating dtype.

    Returns:
        ``(batch, frames, dim)`` noise, ``N(0, 1)`` per frame.
    """
    r = (noise_kernel(noise_frames).shape[0] - 1) // 2
    return smooth_noise(frame_white_noise(key, jnp.asarray(first_frame, jnp.int32) - r, frames + 2 * r, batch, dim, dtype),
                        noise_frames)


def frame_white_noise(
    key: PRNGKeyArray, first_frame: Int[Array, ""] | int, frames: int, batch: int, dim: int, dtype=jnp.float32,
) -> Float[Array, "batch time dim"]:
    """The white noise of absolute frames ``first_frame .. first_frame + frames - 1`` of a stream: frame
    ``f``'s is ``normal(fold_in(key, f), (batch, dim))`` (what :func:`frame_noise` smooths)."""
    index = jnp.asarray(first_frame, jnp.int32) + jnp.arange(frames, dtype=jnp.int32)
    # fold_in takes 32-bit data: negative frames map to distinct large values (two's complement).
    draw = lambda f: jax.random.normal(jax.random.fold_in(key, f.astype(jnp.uint32)), (batch, dim), dtype)  # noqa: E731
    return jax.vmap(draw, out_axes=1)(index)


def smooth_noise(white: Float[Array, "batch time dim"], noise_frames: float) -> Float[Array, "batch frames dim"]:
    """White noise of ``T + 2r`` consecutive frames -> the starting noise of the ``T`` middle ones (``r`` the
    half-width of :func:`noise_kernel`; the white noise itself for ``noise_frames == 0``)."""
    kernel = noise_kernel(noise_frames)
    return white if kernel.shape[0] == 1 else _smooth(white, kernel)
