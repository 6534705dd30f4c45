"""Validation of conversation input streams and their split into turns.

TIMAR and the DualTalk baseline take the same streams (both sides' speech and motion), so both check
them here, in their family package.

Every stream is per frame at 25 fps and batched: ``(B, T, D)`` with ``T = N * F`` (N whole turns of F
frames). The checks run on the host on concrete arrays (they are skipped inside someone else's
``jit``), so bad input fails with a ``ValueError`` naming the stream and the offending value instead
of deep inside XLA.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.types import Array, Float, StreamLike

__all__ = ["TurnConfig", "check_streams", "to_turns", "from_turns"]


@runtime_checkable
class TurnConfig(Protocol):
    """What the turn-window code reads from a model config: TIMAR's
    (:class:`~jaxtalk.models.timar.TimarConfig`) and the DualTalk baseline's
    (:class:`~jaxtalk.models.dualtalk.DualTalkConfig`) both have these fields, so both models check
    their streams and cut their training windows with the same code."""

    @property
    def speech_dim(self) -> int: ...

    @property
    def param_dim(self) -> int: ...

    @property
    def frames_per_turn(self) -> int: ...

    @property
    def max_turns(self) -> int: ...


def _concrete(x: Any) -> bool:
    return not isinstance(x, jax.core.Tracer)


def check_streams(
    config: TurnConfig,
    streams: dict[str, StreamLike | None],
    *,
    max_turns: int | None = None,
) -> int:
    """Check the named ``(B, T, D)`` streams and return the number of turns ``N = T / F``.

    ``streams`` maps names to arrays (None entries are skipped): names containing ``"speech"``
    must have ``config.speech_dim`` channels, names containing ``"motion"`` 56.

    Args:
        config: model config.
        streams: name -> array.
        max_turns: the most turns allowed (e.g. the positional table); None = no limit.

    Returns:
        N, the number of whole turns.

    Raises:
        ValueError: a stream that is not 3-D or not floating, wrong channel count, different batch
            sizes or lengths between streams, a length that is not a positive multiple of
            ``frames_per_turn``, more turns than ``max_turns``, or NaN/inf values.
    """
    f = config.frames_per_turn
    ref: tuple[str, tuple[int, int]] | None = None
    for name, x in streams.items():
        if x is None:
            continue
        shape = tuple(np.shape(x))
        if len(shape) != 3:
            raise ValueError(f"{name} must be (batch, frames, dim), got shape {shape}")
        if not jnp.issubdtype(jnp.asarray(x).dtype if not hasattr(x, "dtype") else x.dtype, jnp.floating):
            raise ValueError(f"{name} must be a floating array, got dtype {getattr(x, 'dtype', type(x))}")
        want = config.speech_dim if "speech" in name else config.param_dim
        if shape[2] != want:
            raise ValueError(f"{name} must have {want} channels, got shape {shape}")
        if ref is None:
            ref = (name, shape[:2])
        elif shape[:2] != ref[1]:
            raise ValueError(
                f"{name} has (batch, frames) = {shape[:2]} but {ref[0]} has {ref[1]}: all streams must "
                "be aligned frame by frame"
            )
        if _concrete(x) and not bool(np.all(np.isfinite(np.asarray(x)))):
            raise ValueError(f"{name} contains NaN or inf")
    if ref is None:
        raise ValueError("no input streams given")
    frames = ref[1][1]
    if frames == 0 or frames % f:
        raise ValueError(
            f"streams have {frames} frames, not a positive multiple of frames_per_turn={f}: turns "
            f"must be whole ({f} frames = 1 s each)"
        )
    if ref[1][0] == 0:
        raise ValueError("streams have an empty batch")
    turns = frames // f
    if max_turns is not None and turns > max_turns:
        raise ValueError(
            f"{turns} turns exceed the model's positional table of max_turns={max_turns}; use a shorter "
            "window or the streaming sampler"
        )
    return turns


def to_turns(x: Float[Array, "batch frames dim"], frames_per_turn: int) -> Float[Array, "batch turns f dim"]:
    """``(B, N F, D) -> (B, N, F, D)``."""
    b, t, d = x.shape
    return jnp.reshape(x, (b, t // frames_per_turn, frames_per_turn, d))


def from_turns(x: Float[Array, "batch turns f dim"]) -> Float[Array, "batch frames dim"]:
    """``(B, N, F, D) -> (B, N F, D)``."""
    b, n, f, d = x.shape
    return jnp.reshape(x, (b, n * f, d))
