"""Prediction with the DualTalk baseline: deterministic regression, no sampling.

:func:`predict_window` is one jitted pass over a window. :func:`predict_turns` is the progressive-context
protocol of TIMAR's Table 1: each turn ``t`` of a conversation is predicted from the window of turns
``[max(0, t - n), t]``, the whole current turn included (its future frames too, as DualTalk reads a
whole clip), and only turn ``t``'s frames are kept.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.models.turns.streams import check_streams
from jaxtalk.models.dualtalk.config import DualTalkConfig
from jaxtalk.models.dualtalk.model import DualTalkNet, check_inputs
from jaxtalk.nn.precision import compute_in
from jaxtalk.types import Array, Float, StreamLike

__all__ = ["WINDOW_BATCH", "predict_turns", "predict_window"]

# Full-context windows per compiled call in predict_turns (the last chunk is padded): one program
# serves every conversation, whatever its length.
WINDOW_BATCH = 8


@functools.partial(jax.jit, static_argnums=1)
def _forward(params: Any, config: DualTalkConfig, us: Array, um: Array, as_: Array) -> Array:
    return compute_in(config.compute_dtype, DualTalkNet(config).apply)({"params": params}, us, um, as_, deterministic=True)


def predict_window(
    params: dict[str, Any],
    config: DualTalkConfig,
    user_speech: StreamLike,
    user_motion: StreamLike,
    agent_speech: StreamLike,
) -> Float[Array, "batch frames param_dim"]:
    """The agent's motion over a whole window of N <= ``max_turns`` turns (jitted, deterministic).

    Args:
        params: model parameters.
        config: model config.
        user_speech, agent_speech: ``(B, N F, speech_dim)`` per-frame speech features (normalised).
        user_motion: ``(B, N F, 56)`` the user's (normalised) head motion.

    Returns:
        ``(B, N F, 56)`` agent motion (in the training normalisation).

    Raises:
        ValueError: bad streams (see :func:`~jaxtalk.models.dualtalk.model.check_inputs`).
    """
    check_inputs(config, user_speech, user_motion, agent_speech)
    return _forward(params, config, *(jnp.asarray(x, jnp.float32) for x in (user_speech, user_motion, agent_speech)))


def predict_turns(
    params: dict[str, Any],
    config: DualTalkConfig,
    user_speech: StreamLike,
    user_motion: StreamLike,
    agent_speech: StreamLike,
    *,
    context: int,
) -> Float[np.ndarray, "batch frames param_dim"]:
    """The agent's motion of a whole conversation, turn by turn with ``context`` turns of history.

    Turn ``t`` comes from the window of turns ``[max(0, t - context), t]``. Windows of the first
    ``context`` turns are shorter (one call each); the others all hold ``context + 1`` turns and run
    in fixed batches of :data:`WINDOW_BATCH`, so a whole evaluation compiles at most ``context + 1``
    programs.

    Args:
        params: model parameters.
        config: model config.
        user_speech, agent_speech: ``(B, N F, speech_dim)`` per-frame speech features of the whole
            conversation (normalised); N may exceed ``max_turns``.
        user_motion: ``(B, N F, 56)`` the user's (normalised) head motion.
        context: history turns n (static), ``0 <= n < max_turns``.

    Returns:
        ``(B, N F, 56)`` float32 agent motion (in the training normalisation).

    Raises:
        ValueError: bad streams, or a context outside ``[0, max_turns - 1]``.
    """
    if isinstance(context, bool) or not isinstance(context, int) or not 0 <= context < config.max_turns:
        raise ValueError(f"context must be an integer in [0, max_turns - 1 = {config.max_turns - 1}] (the window "
                         f"holds context + the current turn), got {context!r}")
    turns = check_streams(config, {"user_speech": user_speech, "user_motion": user_motion,
                                   "agent_speech": agent_speech})
    f = config.frames_per_turn
    streams = [np.asarray(x, np.float32) for x in (user_speech, user_motion, agent_speech)]
    batch = streams[0].shape[0]
    out = np.zeros((batch, turns * f, config.param_dim), np.float32)
    for t in range(min(context, turns)):
        y = _forward(params, config, *(jnp.asarray(x[:, : (t + 1) * f]) for x in streams))
        out[:, t * f:(t + 1) * f] = np.asarray(y[:, -f:])
    n_full = turns - min(context, turns)
    if n_full:
        length = (context + 1) * f
        # Frame indices of window w (predicting turn context + w): turns w .. w + context.
        idx = np.arange(n_full)[:, None] * f + np.arange(length)[None, :]
        windows = [x[:, idx].reshape(batch * n_full, length, x.shape[-1]) for x in streams]
        rows = batch * n_full
        pad = -rows % WINDOW_BATCH
        windows = [np.concatenate([w, np.repeat(w[-1:], pad, axis=0)]) for w in windows]
        kept = []
        for s in range(0, rows + pad, WINDOW_BATCH):
            y = _forward(params, config, *(jnp.asarray(w[s:s + WINDOW_BATCH]) for w in windows))
            kept.append(np.asarray(y[:, -f:]))
        last = np.concatenate(kept)[:rows].reshape(batch, n_full * f, config.param_dim)
        out[:, context * f:] = last
    return out
