"""Turn layout of TIMAR's interleaved token sequence: static NumPy index tables plus the interleave.

One turn of ``F`` frames (25 at 25 fps) is laid out as (public code's order)::

    <turn> <us> user speech x F </us> <um> user motion x F </um>
           <as> agent speech x F </as> <am> agent motion x F </am> </turn>

i.e. ``4 F + 10`` tokens (110). Separator ``k`` (0..9) is the k-th delimiter in that order. The
layout is a permutation of ``[user speech | user motion | agent speech | agent motion | separators]``
(the four spans stacked along the frame axis, then the ten separator embeddings), so interleaving is
one gather with a constant index table.
"""

from __future__ import annotations

import dataclasses
import functools

import jax.numpy as jnp
import numpy as np

from jaxtalk.masks import turn_causal_mask
from jaxtalk.models.timar.config import NUM_SEPARATORS, NUM_SPANS
from jaxtalk.types import Array, Bool, Float, Int

__all__ = ["SPANS", "TurnLayout", "turn_layout", "interleave", "agent_token_mask"]

SPANS: tuple[str, ...] = ("user_speech", "user_motion", "agent_speech", "agent_motion")


@dataclasses.dataclass(frozen=True, eq=False)
class TurnLayout:
    """Static index tables of one turn (all NumPy).

    Attributes:
        frames: frames per turn F.
        order: ``(4F + 10,)`` index into ``[spans stacked (4F) | separators (10)]`` of each position.
        span: ``(4F + 10,)`` span id (0..3, see :data:`SPANS`) of each position, -1 on separators.
        frame: ``(4F + 10,)`` frame index inside the turn, -1 on separators.
        separator: ``(4F + 10,)`` separator id 0..9, -1 on span tokens.
        agent_motion: ``(F,)`` positions of the agent-motion tokens, in frame order.
        user: ``(2F,)`` positions of the user's tokens (speech, then motion).
    """

    frames: int
    order: Int[np.ndarray, " tokens"]
    span: Int[np.ndarray, " tokens"]
    frame: Int[np.ndarray, " tokens"]
    separator: Int[np.ndarray, " tokens"]
    agent_motion: Int[np.ndarray, " frames"]
    user: Int[np.ndarray, " user_tokens"]

    @property
    def tokens(self) -> int:
        return int(self.order.shape[0])

    def turn_ids(self, num_turns: int) -> Int[np.ndarray, " seq"]:
        """Turn index of every token of ``num_turns`` consecutive turns, ``(num_turns * (4F+10),)``."""
        return np.repeat(np.arange(num_turns), self.tokens)

    def attention_mask(self, num_turns: int, causal: bool = True) -> Bool[np.ndarray, "seq seq"]:
        """``[query, key]`` visibility over ``num_turns`` turns: turn-causal, or all-visible.

        Args:
            num_turns: window length in turns (> 0).
            causal: turn-causal (TLCA) if True, bidirectional otherwise.

        Returns:
            ``(S, S)`` bool, ``S = num_turns * (4F + 10)``.

        Raises:
            ValueError: non-positive ``num_turns``.
        """
        if num_turns < 1:
            raise ValueError(f"num_turns must be >= 1, got {num_turns}")
        mask = turn_causal_mask(self.turn_ids(num_turns))
        return mask if causal else np.ones_like(mask)


@functools.lru_cache(maxsize=None)
def turn_layout(frames: int) -> TurnLayout:
    """The layout tables for ``frames`` frames per turn (cached; built once in NumPy).

    Args:
        frames: F > 0.

    Returns:
        :class:`TurnLayout`.

    Raises:
        ValueError: non-positive ``frames``.
    """
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1:
        raise ValueError(f"frames per turn must be a positive integer, got {frames!r}")
    f = int(frames)
    order, span, frame, sep = [], [], [], []

    def separator(k: int) -> None:
        order.append(NUM_SPANS * f + k)
        span.append(-1)
        frame.append(-1)
        sep.append(k)

    separator(0)  # <turn>
    for s in range(NUM_SPANS):
        separator(1 + 2 * s)  # open span s
        for j in range(f):
            order.append(s * f + j)
            span.append(s)
            frame.append(j)
            sep.append(-1)
        separator(2 + 2 * s)  # close span s
    separator(NUM_SEPARATORS - 1)  # </turn>
    order_a, span_a = np.asarray(order, np.int32), np.asarray(span, np.int32)
    frame_a, sep_a = np.asarray(frame, np.int32), np.asarray(sep, np.int32)
    assert order_a.shape[0] == NUM_SPANS * f + NUM_SEPARATORS
    assert np.array_equal(np.sort(order_a), np.arange(order_a.shape[0]))
    agent_motion = np.flatnonzero(span_a == 3).astype(np.int32)
    user = np.concatenate([np.flatnonzero(span_a == 0), np.flatnonzero(span_a == 1)]).astype(np.int32)
    return TurnLayout(f, order_a, span_a, frame_a, sep_a, agent_motion, user)


def interleave(
    user_speech: Float[Array, "*batch turns frames width"],
    # Loose annotations: the shape checks below raise a ValueError that names the problem.
    user_motion: Float[Array, "*um_dims"],
    agent_speech: Float[Array, "*as_dims"],
    agent_motion: Float[Array, "*am_dims"],
    separators: Float[Array, "*sep_dims"],
) -> Float[Array, "*batch turns tokens width"]:
    """Interleave four per-turn token spans with the ten separator embeddings.

    Args:
        user_speech, user_motion, agent_speech, agent_motion: ``(*B, N, F, D)`` token embeddings.
        separators: ``(10, D)`` learned separator embeddings.

    Returns:
        ``(*B, N, 4F + 10, D)`` tokens in the layout of :func:`turn_layout`.

    Raises:
        ValueError: if the spans' shapes differ or the separator table is not ``(10, D)``.
    """
    spans = (user_speech, user_motion, agent_speech, agent_motion)
    if any(s.shape != user_speech.shape for s in spans):
        raise ValueError(f"the four spans must have one shape, got {[s.shape for s in spans]}")
    if separators.shape != (NUM_SEPARATORS, user_speech.shape[-1]):
        raise ValueError(f"separators must be ({NUM_SEPARATORS}, {user_speech.shape[-1]}), got {separators.shape}")
    layout = turn_layout(user_speech.shape[-2])
    seps = jnp.broadcast_to(separators.astype(user_speech.dtype), user_speech.shape[:-2] + separators.shape)
    stacked = jnp.concatenate([*spans, seps], axis=-2)
    return jnp.take(stacked, layout.order, axis=-2)


def agent_token_mask(
    agent_mask: Bool[Array, "*batch turns frames"] | Bool[np.ndarray, "*batch turns frames"],
) -> Bool[Array, "*batch turns tokens"]:
    """Spread a per-frame agent mask onto the turn layout: True at the masked agent-motion tokens.

    Args:
        agent_mask: ``(*B, N, F)`` True where the agent frame is masked.

    Returns:
        ``(*B, N, 4F + 10)`` bool, False at every other token (speech, user motion, separators).
    """
    layout = turn_layout(agent_mask.shape[-1])
    f = layout.frames
    # The agent-motion span is contiguous: pad the frame mask with False on both sides (no scatter).
    lo = int(layout.agent_motion[0])
    pad = [(0, 0)] * (agent_mask.ndim - 1) + [(lo, layout.tokens - lo - f)]
    return jnp.pad(jnp.asarray(agent_mask, bool), pad, constant_values=False)
