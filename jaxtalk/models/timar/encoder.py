"""TIMAR's token embedding and turn-level causal fusion encoder (Flax Linen).

Tokens: per-frame speech features go through one learnable projection ``P_speech`` (shared by user
and agent), head-motion frames through a 2-layer ReLU MLP ``F_head`` (hidden ``d_t / 2``), both to the
shared width ``d_t``; agent-motion tokens may be replaced by the learned mask token, all user tokens
of an example by the learned fake token (CFG); the four spans are interleaved with ten learned
separators (:mod:`~jaxtalk.models.timar.tokens`). Fusion: ``LayerNorm``, a learned positional
embedding ``P1`` over the whole window, pre-LN transformer blocks with the turn-causal mask as an
additive bias, a final ``LayerNorm``. The diffusion head's positional embedding ``P2`` (per agent
frame of the window) lives here too.

``architecture="encoder_decoder"`` (Table 2's MAE-style variant, MAR's default layout) adds a
decoder: the encoder attends to the VISIBLE tokens only (masked agent-motion tokens are no keys in any
of its layers: with static shapes this is exactly MAE's dropping of the masked tokens, since a token
that is no key cannot influence any other token, and the masked tokens' own outputs are discarded);
the decoder takes ``Dense(encoder output)`` at the visible positions and the learned mask token at
every masked agent frame, adds its own positional table, runs ``decoder_layers`` blocks under the same
turn-causal (or bidirectional) mask, and its agent-motion outputs plus ``P2`` condition the head.
The variant's parameters live in the same module (the ``"encoder"`` subtree, prefixed ``decoder_``).

:meth:`~TimarEncoder.encode` and :meth:`~TimarEncoder.head_condition` take their tokens' first turn
slot (``first_turn``, may be traced), so a streaming step can encode the current turn alone at its
slot of the window, continuing the keys/values of the past turns (:mod:`~jaxtalk.models.timar.streaming`);
the whole-window methods (:meth:`~TimarEncoder.fuse`, and the variant's ``encode_visible`` and
``decode``) place the window at slots ``0..N-1``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.masks import mask_to_bias
from jaxtalk.models.timar.config import NUM_SEPARATORS, TimarConfig
from jaxtalk.models.timar.tokens import agent_token_mask, interleave, turn_layout
from jaxtalk.nn import MLP, TransformerBlock
from jaxtalk.nn.embeddings import sinusoidal_embedding
from jaxtalk.types import Array, Bool, Float, Int

__all__ = ["TimarEncoder", "KVCache", "init_encoder", "aligned_position_init"]

# Per encoder layer: (keys, values), each (batch, length, heads, head_dim); the length differs between
# the cache passed in and the one returned, hence the loose annotation.
KVCache = tuple[tuple[Float[Array, "..."], Float[Array, "..."]], ...]


def aligned_position_init(config: TimarConfig) -> Callable[..., Float[Array, "positions width"]]:
    """Initialiser of the learned positional table ``P1``: frame-aligned sinusoids (still trained).

    Why: an agent-motion (mask) token must read the speech of ITS frame, 2F + 4 tokens away. With a
    small random table the identical mask tokens cannot tell their frames apart, and on a CPU-sized
    budget the encoder only learns turn-level averages (the mouth is never predicted). Here every
    span token starts with a sinusoidal code of its frame inside the turn (the same code in all four
    spans, so "same frame" is one dot product for the attention to find), separators with codes
    after the frames, and the last quarter of the channels codes the turn slot.

    Args:
        config: model config (frames per turn, turns, width).

    Returns:
        A Flax initialiser ``(key, shape, dtype) -> (max_turns (4F + 10), width)``.
    """

    def init(key: Any, shape: tuple[int, ...], dtype: Any = jnp.float32) -> Array:
        del key  # deterministic
        layout = turn_layout(config.frames_per_turn)
        code = np.where(layout.span >= 0, layout.frame, config.frames_per_turn + layout.separator)
        turn = np.repeat(np.arange(config.max_turns), layout.tokens)
        w = shape[-1]
        w_turn = max(w // 4, 2) if w >= 8 else 0
        parts = [sinusoidal_embedding(jnp.asarray(np.tile(code, config.max_turns)), w - w_turn, max_period=100.0)]
        if w_turn:
            parts.append(sinusoidal_embedding(jnp.asarray(turn), w_turn, max_period=100.0))
        return jnp.concatenate(parts, axis=-1).astype(dtype)

    return init


class TimarEncoder(nn.Module):
    """Token embedding + turn-causal transformer encoder + the diffusion head's positional table.

    Attributes:
        config: the model config.
    """

    config: TimarConfig

    def setup(self) -> None:
        c = self.config
        w = c.width
        ew = c.embed_width  # token width before the optional input projection (= w without it)
        small = nn.initializers.normal(stddev=0.02)
        self.speech_proj = nn.Dense(ew, name="speech_proj")
        self.motion_encoder = MLP((max(ew // 2, 1), ew), activation=jax.nn.relu,
                                  activate_final=c.motion_encoder_final_relu, name="motion_encoder")
        self.separators = self.param("separators", small, (NUM_SEPARATORS, ew))
        self.mask_token = self.param("mask_token", small, (w,))
        self.fake_token = self.param("fake_token", small, (ew,))
        if c.input_projection:
            self.input_proj = nn.Dense(w, name="input_proj")
        self.pos_embed = self.param("pos_embed", aligned_position_init(c), (c.max_turns * c.tokens_per_turn, w))
        self.head_pos_embed = self.param("head_pos_embed", small, (c.max_turns * c.frames_per_turn, w))
        self.in_norm = nn.LayerNorm(name="in_norm")
        self.blocks = self._stack("block", c.num_layers)
        self.out_norm = nn.LayerNorm(name="out_norm")
        if c.architecture == "encoder_decoder":
            # MAR's decoder: decoder_embed, decoder_pos_embed_learned, decoder blocks, decoder_norm; its
            # mask token is the model's one ``mask_token``. The positional table starts frame-aligned
            # for the encoder's reason: the decoder's identical mask tokens must find their own
            # frame's speech among the encoder outputs.
            self.decoder_embed = nn.Dense(w, name="decoder_embed")
            self.decoder_pos_embed = self.param(
                "decoder_pos_embed", aligned_position_init(c), (c.max_turns * c.tokens_per_turn, w)
            )
            self.decoder_blocks = self._stack("decoder_block", c.decoder_layers)
            self.decoder_norm = nn.LayerNorm(name="decoder_norm")

    def _stack(self, prefix: str, depth: int) -> list[TransformerBlock]:
        """``depth`` transformer blocks of the config's width, heads and dropout, named ``prefix_i``."""
        c = self.config
        return [
            TransformerBlock(num_heads=c.num_heads, head_dim=c.width // c.num_heads, mlp_ratio=c.mlp_ratio,
                             dropout_rate=c.dropout, attention_dropout_rate=c.dropout,
                             layer_norm_epsilon=c.block_norm_epsilon, name=f"{prefix}_{i}")
            for i in range(depth)
        ]

    def embed(
        self,
        user_speech: Float[Array, "batch turns frames speech_dim"],
        user_motion: Float[Array, "batch turns frames param_dim"],
        agent_speech: Float[Array, "batch turns frames speech_dim"],
        agent_motion: Float[Array, "batch turns frames param_dim"] | None,
        agent_mask: Bool[Array, "batch turns frames"] | None,
        user_drop: Bool[Array, " batch"] | Bool[Array, "batch turns"] | None,
    ) -> Float[Array, "batch turns tokens width"]:
        """Interleaved token embeddings of whole turns (no positional embedding yet).

        Args:
            user_speech, agent_speech: ``(B, N, F, speech_dim)`` per-frame speech features.
            user_motion: ``(B, N, F, 56)`` the user's head motion.
            agent_motion: ``(B, N, F, 56)`` the agent's head motion, or None when every agent
                frame is masked (sampling).
            agent_mask: ``(B, N, F)`` True where the agent frame is replaced by the mask token
                (ignored when ``agent_motion`` is None).
            user_drop: ``(B,)`` True where every user token of the example is replaced by the fake
                token, or ``(B, N)`` True where the user tokens of that turn are.

        Returns:
            ``(B, N, 4F + 10, width)`` tokens (after the input projection when the config has one:
            the fake token replaces user tokens BEFORE it, the mask token agent tokens AFTER it,
            as in the public code; the projection is per token, so projecting each span and the
            separators before interleaving equals projecting the interleaved sequence).
        """
        us = self.speech_proj(user_speech)
        as_ = self.speech_proj(agent_speech)
        um = self.motion_encoder(user_motion)
        am = None if agent_motion is None else self.motion_encoder(agent_motion)
        if user_drop is not None:
            drop = user_drop[:, None, None, None] if user_drop.ndim == 1 else user_drop[:, :, None, None]
            us = jnp.where(drop, self.fake_token.astype(us.dtype), us)
            um = jnp.where(drop, self.fake_token.astype(um.dtype), um)
        seps = self.separators
        if self.config.input_projection:
            us, um, as_, seps = self.input_proj(us), self.input_proj(um), self.input_proj(as_), self.input_proj(seps)
            am = None if am is None else self.input_proj(am)
        if am is None:
            am = jnp.broadcast_to(self.mask_token.astype(us.dtype), us.shape)
        elif agent_mask is not None:
            am = jnp.where(agent_mask[..., None], self.mask_token.astype(am.dtype), am)
        return interleave(us, um, as_, am, seps)

    def encode(
        self,
        tokens: Float[Array, "batch turns tokens width"],
        first_turn: Int[Array, ""] | int,
        bias: Float[Array, "*bias_dims"],
        kv_cache: KVCache | None = None,
        return_kv: bool = False,
        deterministic: bool = True,
    ) -> Float[Array, "batch turns tokens width"] | tuple[Float[Array, "batch turns tokens width"], KVCache]:
        """Fuse tokens of consecutive turns placed at window slots ``first_turn, first_turn + 1, ...``.

        Args:
            tokens: ``(B, Nq, 4F + 10, width)`` from :meth:`embed`.
            first_turn: window slot of the first turn (positional table offset; may be traced).
            bias: additive attention bias broadcastable to ``(B, heads, Nq (4F+10), keys)`` where
                ``keys`` is the cache length plus ``Nq (4F + 10)``.
            kv_cache: per layer, keys/values of earlier tokens (prepended to the new ones).
            return_kv: also return per-layer keys/values (cache + new).
            deterministic: disables dropout (training passes False with a ``"dropout"`` RNG).

        Returns:
            ``(B, Nq, 4F + 10, width)`` fused features (and the keys/values with ``return_kv``).
        """
        b, nq, tpt, w = tokens.shape
        x = tokens.reshape(b, nq * tpt, w)
        start = jnp.asarray(first_turn, jnp.int32) * tpt
        pos = jax.lax.dynamic_slice_in_dim(self.pos_embed, start, nq * tpt, axis=0)
        if self.config.norm_after_position:
            x = self.in_norm(x + pos[None].astype(x.dtype))  # the public code's z_proj_ln(z_proj(x) + P1)
        else:
            x = self.in_norm(x) + pos[None].astype(x.dtype)
        caches = []
        for i, block in enumerate(self.blocks):
            cache = None if kv_cache is None else kv_cache[i]
            out = block(x, bias=bias, kv_cache=cache, return_kv=return_kv, deterministic=deterministic)
            if return_kv:
                x, kv = out
                caches.append(kv)
            else:
                x = out
        x = self.out_norm(x).reshape(b, nq, tpt, w)
        return (x, tuple(caches)) if return_kv else x

    def encode_visible(
        self,
        tokens: Float[Array, "batch turns tokens width"],
        agent_mask: Bool[Array, "batch turns frames"],
        visibility: Bool[Array, "*vis_batch seq seq"],
        deterministic: bool = True,
    ) -> Float[Array, "batch turns tokens width"]:
        """The MAE-style variant's encoder: a window at slots ``0..N-1`` seen through its visible tokens.

        Masked agent-motion tokens are excluded as keys in every layer, on top of ``visibility``: the
        outputs at the other positions are those of the encoder run on the visible tokens alone
        (tested), whatever the masked tokens hold. The outputs AT the masked positions are
        meaningless and are replaced by the mask token in :meth:`decode`.

        Args:
            tokens: ``(B, N, 4F + 10, width)`` from :meth:`embed`.
            agent_mask: ``(B, N, F)`` True where the agent frame is masked.
            visibility: ``[query, key]`` mask, ``(S, S)`` or ``(B, S, S)`` with ``S = N (4F + 10)``
                (turn-causal or bidirectional, and any unfilled slots of a stream hidden).
            deterministic: disables dropout.

        Returns:
            ``(B, N, 4F + 10, width)``.
        """
        b, n, tpt, _ = tokens.shape
        hidden = agent_token_mask(agent_mask).reshape(b, n * tpt)
        vis = visibility if visibility.ndim == 3 else visibility[None]
        keys = vis & ~hidden[:, None, :]  # (B, S, S)
        return self.encode(tokens, 0, mask_to_bias(keys)[:, None], deterministic=deterministic)

    def decode(
        self,
        features: Float[Array, "batch turns tokens width"],
        agent_mask: Bool[Array, "batch turns frames"],
        visibility: Bool[Array, "*vis_batch seq seq"],
        deterministic: bool = True,
    ) -> Float[Array, "batch turns tokens width"]:
        """The MAE-style variant's decoder over a window at slots ``0..N-1``.

        Args:
            features: ``(B, N, 4F + 10, width)`` from :meth:`encode_visible`.
            agent_mask: ``(B, N, F)`` True where the agent frame is masked: its feature is replaced
                by the mask token.
            visibility: ``[query, key]`` mask as in :meth:`encode_visible` (no masked-token
                exclusion here: the decoder reads the mask tokens).
            deterministic: disables dropout.

        Returns:
            ``(B, N, 4F + 10, width)`` decoded features (agent-motion positions feed the head).
        """
        if self.config.architecture != "encoder_decoder":
            raise ValueError(f"decode needs architecture='encoder_decoder', got {self.config.architecture!r}")
        b, n, tpt, w = features.shape
        x = self.decoder_embed(features)
        masked = agent_token_mask(agent_mask)[..., None]
        x = jnp.where(masked, self.mask_token.astype(x.dtype), x).reshape(b, n * tpt, w)
        x = x + self.decoder_pos_embed[None, : n * tpt].astype(x.dtype)
        bias = mask_to_bias(visibility)
        if bias.ndim == 3:
            bias = bias[:, None]
        for block in self.decoder_blocks:
            x = block(x, bias=bias, deterministic=deterministic)
        return self.decoder_norm(x).reshape(b, n, tpt, w)

    def fuse(
        self,
        tokens: Float[Array, "batch turns tokens width"],
        agent_mask: Bool[Array, "batch turns frames"],
        visibility: Bool[Array, "*vis_batch seq seq"],
        deterministic: bool = True,
    ) -> Float[Array, "batch turns frames width"]:
        """Head conditions of a whole window at slots ``0..N-1``, for either architecture.

        Args:
            tokens: ``(B, N, 4F + 10, width)`` from :meth:`embed` (masked agent frames already hold
                the mask token).
            agent_mask: ``(B, N, F)`` True where the agent frame is masked (read by the
                encoder-decoder variant only).
            visibility: ``[query, key]`` mask, ``(S, S)`` or ``(B, S, S)``.
            deterministic: disables dropout.

        Returns:
            ``(B, N, F, width)``.
        """
        if self.config.architecture == "encoder":
            bias = mask_to_bias(visibility)
            if bias.ndim == 3:
                bias = bias[:, None]
            features = self.encode(tokens, 0, bias, deterministic=deterministic)
        else:
            features = self.encode_visible(tokens, agent_mask, visibility, deterministic)
            features = self.decode(features, agent_mask, visibility, deterministic)
        return self.head_condition(features, 0)

    def head_condition(
        self, features: Float[Array, "batch turns tokens width"], first_turn: Int[Array, ""] | int
    ) -> Float[Array, "batch turns frames width"]:
        """The diffusion head's condition: agent-motion features plus ``P2`` of their frames.

        Args:
            features: ``(B, Nq, 4F + 10, width)`` output of :meth:`encode`.
            first_turn: window slot of the first turn.

        Returns:
            ``(B, Nq, F, width)``.
        """
        b, nq, _, w = features.shape
        f = self.config.frames_per_turn
        am = turn_layout(f).agent_motion
        # The agent-motion span is contiguous: a static slice (its gradient is a pad, not a scatter).
        z = features[:, :, int(am[0]) : int(am[0]) + f]
        start = jnp.asarray(first_turn, jnp.int32) * f
        pos = jax.lax.dynamic_slice_in_dim(self.head_pos_embed, start, nq * f, axis=0)
        return z + pos.reshape(1, nq, f, w).astype(z.dtype)

    def __call__(
        self,
        user_speech: Float[Array, "batch turns frames speech_dim"],
        user_motion: Float[Array, "batch turns frames param_dim"],
        agent_speech: Float[Array, "batch turns frames speech_dim"],
        agent_motion: Float[Array, "batch turns frames param_dim"] | None = None,
        agent_mask: Bool[Array, "batch turns frames"] | None = None,
        user_drop: Bool[Array, " batch"] | Bool[Array, "batch turns"] | None = None,
        deterministic: bool = True,
    ) -> Float[Array, "batch turns frames width"]:
        """Whole-window pass: embed, fuse with the config's mask, return the head conditions.

        Args:
            user_speech, user_motion, agent_speech, agent_motion, agent_mask, user_drop: see
                :meth:`embed`.
            deterministic: disables dropout.

        Returns:
            ``(B, N, F, width)`` head conditions of every agent frame.
        """
        tokens = self.embed(user_speech, user_motion, agent_speech, agent_motion, agent_mask, user_drop)
        b, n = tokens.shape[:2]
        frames = (b, n, self.config.frames_per_turn)
        if agent_motion is None:
            masked = jnp.ones(frames, bool)
        elif agent_mask is None:
            masked = jnp.zeros(frames, bool)
        else:
            masked = jnp.asarray(agent_mask, bool)
        mask = turn_layout(self.config.frames_per_turn).attention_mask(
            n, causal=self.config.attention == "turn_causal"
        )
        return self.fuse(tokens, masked, jnp.asarray(mask), deterministic)


def init_encoder(config: TimarConfig, key: Any) -> dict[str, Any]:
    """Initialise the encoder's parameters on a one-turn dummy window.

    Args:
        config: model config.
        key: PRNG key.

    Returns:
        The encoder's parameter pytree.
    """
    f = config.frames_per_turn
    speech = jnp.zeros((1, 1, f, config.speech_dim), jnp.float32)
    motion = jnp.zeros((1, 1, f, config.param_dim), jnp.float32)
    return TimarEncoder(config).init(key, speech, motion, speech, motion)["params"]
