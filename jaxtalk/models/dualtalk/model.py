"""The DualTalk baseline's network (Flax Linen) and its pure ``init_params`` / ``apply``.

One pass over a whole window of ``T`` frames, every layer reading every frame:

1. joint encoder: the agent's and the user's per-frame speech features each through their own
   ``Dense(speech_dim -> width / 2)``; the user's head motion through a 2-layer ReLU MLP
   ``56 -> width / 4 -> width / 2``;
2. temporal enhancer (the user branch): the user's speech features attend to the user's motion
   features (cross-attention, no residual: the branch carries motion selected by speech), then a
   bidirectional LSTM stack (``width / 4`` units per direction);
3. interaction encoder: ``[agent speech | user branch]`` (``width``) plus fixed sinusoidal frame
   positions, pre-LN transformer blocks with full bidirectional self-attention, a final LayerNorm and
   ``feature_dropout``;
4. synthesis: decoder blocks (self-attention, attention to the interaction features, feed-forward),
   a LayerNorm and a per-frame ``Dense(width -> 56)``.

The backward LSTM and the attention layers read the future, so the output at frame ``t`` depends on
every input frame of the window: this is an offline model (tests check that it reads the future).
"""

from __future__ import annotations

import functools
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp

from jaxtalk.models.turns.streams import check_streams
from jaxtalk.models.dualtalk.config import DualTalkConfig
from jaxtalk.nn import MLP, DecoderBlock, MultiHeadAttention, TransformerBlock
from jaxtalk.nn.embeddings import sinusoidal_embedding
from jaxtalk.nn.precision import compute_in
from jaxtalk.types import Array, Float, PRNGKeyArray, StreamLike

__all__ = ["DualTalkNet", "apply", "check_inputs", "init_params"]

# Longest period of the frame-position sinusoids, in frames: well beyond an 8-turn (200-frame) window,
# so no two frames of a window share a code.
_POSITION_PERIOD = 1000.0


class DualTalkNet(nn.Module):
    """Both speakers' speech and the user's motion over a window -> the agent's 56-d motion.

    Attributes:
        config: the model config.
    """

    config: DualTalkConfig

    def _block_kwargs(self) -> dict[str, Any]:
        c = self.config
        # ReLU feed-forward as DualTalk's PyTorch transformer layers.
        return dict(num_heads=c.num_heads, head_dim=c.width // c.num_heads, mlp_ratio=c.mlp_ratio,
                    dropout_rate=c.dropout, activation=nn.relu)

    @nn.compact
    def __call__(
        self,
        user_speech: Float[Array, "batch frames speech_dim"],
        user_motion: Float[Array, "batch frames param_dim"],
        agent_speech: Float[Array, "batch frames speech_dim"],
        *,
        deterministic: bool = True,
    ) -> Float[Array, "batch frames param_dim"]:
        c = self.config
        d = c.feature_width
        agent = nn.Dense(d, name="agent_speech_proj")(agent_speech)
        user = nn.Dense(d, name="user_speech_proj")(user_speech)
        motion = MLP((d // 2, d), activation=nn.relu, activate_final=True, name="user_motion_mlp")(user_motion)
        branch = MultiHeadAttention(num_heads=c.num_heads, head_dim=d // c.num_heads, name="user_cross_attention")(
            user, motion)
        for i in range(c.lstm_layers):
            # The cell's parameter dtype sets its carry's dtype, which must match the input's under scan
            # (float64 in the gradient checks). parent=None: each layer owns its RNNs and their cells (their
            # parameters nest under user_lstm_i), not this module.
            fwd, bwd = (nn.RNN(nn.OptimizedLSTMCell(d // 2, param_dtype=branch.dtype, parent=None), parent=None)
                        for _ in range(2))
            branch = nn.Bidirectional(fwd, bwd, name=f"user_lstm_{i}")(branch)
        h = jnp.concatenate([agent, branch], axis=-1)
        # Per-frame features carry no position (wav2vec 2.0's convolutional position code did in DualTalk).
        frames = jnp.arange(h.shape[-2], dtype=h.dtype)
        h = h + sinusoidal_embedding(frames, c.width, max_period=_POSITION_PERIOD).astype(h.dtype)[None]
        for i in range(c.num_layers):
            h = TransformerBlock(**self._block_kwargs(), name=f"encoder_{i}")(h, deterministic=deterministic)
        h = nn.LayerNorm(name="encoder_norm")(h)
        memory = nn.Dropout(c.feature_dropout)(h, deterministic=deterministic)
        h = memory
        for i in range(c.decoder_layers):
            h = DecoderBlock(**self._block_kwargs(), name=f"decoder_{i}")(h, memory, deterministic=deterministic)
        h = nn.LayerNorm(name="decoder_norm")(h)
        return nn.Dense(c.param_dim, name="out")(h)


@functools.partial(jax.jit, static_argnums=0)
def init_params(config: DualTalkConfig, key: PRNGKeyArray) -> dict[str, Any]:
    """Initial parameters (a plain pytree; every size is independent of the window length).

    Args:
        config: model config.
        key: PRNG key.

    Returns:
        Parameter pytree.
    """
    f = config.frames_per_turn
    speech = jnp.zeros((1, f, config.speech_dim), jnp.float32)
    motion = jnp.zeros((1, f, config.param_dim), jnp.float32)
    return DualTalkNet(config).init(key, speech, motion, speech)["params"]


def check_inputs(
    config: DualTalkConfig, user_speech: StreamLike, user_motion: StreamLike, agent_speech: StreamLike
) -> int:
    """Validate a window's streams (TIMAR's checks) and return its number of turns.

    Raises:
        ValueError: a stream that is not ``(B, T, D)`` floating, wrong widths, misaligned streams,
            ``T`` not a positive multiple of ``frames_per_turn``, more than ``max_turns`` turns,
            or NaN/inf values (checked on concrete arrays only).
    """
    return check_streams(config, {"user_speech": user_speech, "user_motion": user_motion,
                                  "agent_speech": agent_speech}, max_turns=config.max_turns)


def apply(
    params: dict[str, Any],
    config: DualTalkConfig,
    user_speech: StreamLike,
    user_motion: StreamLike,
    agent_speech: StreamLike,
    *,
    dropout_key: PRNGKeyArray | None = None,
) -> Float[Array, "batch frames param_dim"]:
    """The agent's head motion over a whole window, every output frame reading every input frame.

    There is no agent-motion input: the model regresses the agent's motion from both speakers'
    speech and the user's motion alone. Composable (not jitted); :func:`predict_window` is the
    jitted inference entry point.

    Args:
        params: :func:`init_params` output.
        config: model config.
        user_speech, agent_speech: ``(B, T, speech_dim)`` per-frame speech features (normalised).
        user_motion: ``(B, T, 56)`` the user's (normalised) head motion.
        dropout_key: enables dropout (training) when given.

    Returns:
        ``(B, T, 56)`` agent motion (in the training normalisation).

    Raises:
        ValueError: bad streams (see :func:`check_inputs`).
    """
    check_inputs(config, user_speech, user_motion, agent_speech)
    rngs = None if dropout_key is None else {"dropout": dropout_key}
    us, um, as_ = (jnp.asarray(x) for x in (user_speech, user_motion, agent_speech))
    apply = compute_in(config.compute_dtype, DualTalkNet(config).apply)
    return apply({"params": params}, us, um, as_, deterministic=dropout_key is None, rngs=rngs)
