"""Flax (Linen) port of the wav2vec 2.0 and HuBERT encoders (inference and fine-tuning).

The two architectures share every module; they differ only in config details (HuBERT may drop the
feature-projection LayerNorm or use a BatchNorm positional conv), which :class:`EncoderConfig`
carries. Submodule and parameter names mirror the Hugging Face ``transformers`` modules so that the
checkpoint loader maps tensor names mechanically (``conv_layers_3`` <-> ``conv_layers.3``).

Pipeline (HF ``Wav2Vec2Model.forward``):

1. conv feature extractor: strided 1-D convs over the raw waveform; ``feat_extract_norm="group"``
   normalises the FIRST conv's output per channel over time (GroupNorm with one channel per group),
   ``"layer"`` puts a LayerNorm over channels after EVERY conv;
2. feature projection: (LayerNorm) + Linear to ``hidden_size``;
3. transformer encoder: zero the padded frames, add a convolutional positional embedding
   (weight-normalised grouped conv + same-padding trim + activation), then post-LN layers with an
   input LayerNorm (base) or pre-LN "stable layer norm" layers with a final LayerNorm (large).

Padding: a batch is right-padded and described by per-row sample lengths. The transformer masks
padded keys, so padded rows match single inputs whenever the features of the real frames do. The
layer-norm extractor (large) normalises each frame on its own and its valid frames never see padding
(no conv padding; valid frames are those of the conv length formula), so padded == single exactly.
The group-norm extractor (base) normalises each channel over TIME: Hugging Face (and fairseq) take
those statistics over the whole padded row, which is why their processors pass no attention mask to
base models. Here ``mask_group_norm=True`` (default) takes them over the real frames only, making
padded batches equal to single inputs; ``mask_group_norm=False`` reproduces HF's padded behaviour.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
from jaxtyping import Bool, Float, Int

from jaxtalk.audio.encoders.config import EncoderConfig
from jaxtalk.types import Array

__all__ = [
    "Wav2Vec2Model",
    "EncoderOutput",
    "activation",
    "conv_output_lengths",
    "lengths_to_mask",
]

# torch.nn.LayerNorm / GroupNorm / BatchNorm1d default epsilon (the conv stack and pos-conv norms use
# it, not config.layer_norm_eps).
_TORCH_NORM_EPS = 1e-5


class EncoderOutput(NamedTuple):
    """What the encoder returns (``batch`` rows, ``frames`` output frames).

    Attributes:
        last_hidden_state: ``(batch, frames, hidden)`` HF ``last_hidden_state`` (after the final
            LayerNorm for stable-layer-norm models).
        hidden_states: ``(layers + 1, batch, frames, hidden)`` as HF (transformers >= 5) returns
            ``hidden_states``: entry 0 is the input of the first transformer layer, entry ``k`` the
            output of layer ``k`` (for stable-layer-norm models the last entry is BEFORE the final
            LayerNorm; transformers 4.x put the normalised one there). ``None`` when not collected.
        layer_output: ``(batch, frames, hidden)`` output of the last layer that ran (=
            ``hidden_states[-1]``), available even when ``hidden_states`` is not collected.
        frame_mask: ``(batch, frames)`` True on real (non-padding) frames.
    """

    last_hidden_state: Float[Array, "batch frames hidden"]
    hidden_states: Float[Array, "layers_plus_one batch frames hidden"] | None
    layer_output: Float[Array, "batch frames hidden"]
    frame_mask: Bool[Array, "batch frames"]


def activation(name: str):
    """The JAX function for an HF activation name (``"gelu"`` is the exact erf GELU).

    Raises:
        ValueError: unknown name.
    """
    table = {
        "gelu": functools.partial(jax.nn.gelu, approximate=False),
        "gelu_new": functools.partial(jax.nn.gelu, approximate=True),
        "gelu_pytorch_tanh": functools.partial(jax.nn.gelu, approximate=True),
        "gelu_fast": functools.partial(jax.nn.gelu, approximate=True),
        "relu": jax.nn.relu,
        "silu": jax.nn.silu,
        "swish": jax.nn.silu,
        "tanh": jnp.tanh,
    }
    if name not in table:
        raise ValueError(f"unknown activation {name!r}; known: {sorted(table)}")
    return table[name]


def conv_output_lengths(
    config: EncoderConfig, sample_lengths: Int[Array, " batch"], num_layers: int | None = None
) -> Int[Array, " batch"]:
    """Valid output frames of the first ``num_layers`` convs (all by default) for each input length.

    The conv length formula ``(n - kernel) // stride + 1`` per layer, clipped at 0 (a row shorter
    than the receptive field has no valid frame).
    """
    lengths = jnp.asarray(sample_lengths).astype(jnp.int32)
    layers = len(config.conv_kernel) if num_layers is None else num_layers
    for kernel, stride in zip(config.conv_kernel[:layers], config.conv_stride[:layers]):
        lengths = jnp.maximum(lengths - kernel, -1) // stride + 1
    return lengths


def lengths_to_mask(lengths: Int[Array, " batch"], size: int) -> Bool[Array, "batch size"]:
    """``mask[b, t] = t < lengths[b]`` (right padding)."""
    return jnp.arange(size)[None, :] < lengths[:, None]


def _channels(vector, dtype=None):
    """A per-channel vector shaped (1, 1, channels) for explicit broadcasting over (batch, time)."""
    vector = vector.reshape(1, 1, -1)
    return vector if dtype is None else vector.astype(dtype)


def _layer_norm(eps: float, name: str) -> nn.LayerNorm:
    # Two-pass variance (use_fast_variance=False) as torch does: the unnormalised conv features of
    # base models are large, and E[x^2] - E[x]^2 would lose float32 digits there.
    return nn.LayerNorm(epsilon=eps, use_fast_variance=False, name=name)


class Conv1d(nn.Module):
    """1-D convolution over ``(batch, time, channels)``, kernel stored as ``(kernel, in/groups, out)``."""

    features: int
    kernel_size: int
    stride: int = 1
    padding: int = 0
    groups: int = 1
    use_bias: bool = True

    @nn.compact
    def __call__(self, x: Float[Array, "batch time cin"]) -> Float[Array, "batch time_out cout"]:
        cin = x.shape[-1]
        kernel = self.param(
            "kernel",
            nn.initializers.lecun_normal(),
            (self.kernel_size, cin // self.groups, self.features),
        )
        y = jax.lax.conv_general_dilated(
            x,
            kernel.astype(x.dtype),
            window_strides=(self.stride,),
            padding=[(self.padding, self.padding)],
            dimension_numbers=("NWC", "WIO", "NWC"),
            feature_group_count=self.groups,
        )
        if self.use_bias:
            y = y + _channels(self.param("bias", nn.initializers.zeros, (self.features,)), x.dtype)
        return y


class WeightNormConv1d(nn.Module):
    """Grouped conv whose kernel is ``weight_g * weight_v / ||weight_v||`` (PyTorch weight norm).

    HF wraps the positional conv in ``weight_norm(conv, dim=2)``: with PyTorch's weight layout
    ``(out, in/groups, kernel)`` the norm is taken over out and in for EACH kernel tap, so
    ``weight_g`` has one entry per tap. Here ``weight_v`` is stored as ``(kernel, in/groups, out)`` and
    the norm runs over its last two axes. The kernel is recomputed inside the module (not folded at
    load time) so that fine-tuning trains ``g`` and ``v`` exactly as HF does.
    """

    features: int
    kernel_size: int
    padding: int
    groups: int

    @nn.compact
    def __call__(self, x: Float[Array, "batch time cin"]) -> Float[Array, "batch time_out cout"]:
        cin = x.shape[-1]
        v = self.param(
            "weight_v",
            nn.initializers.normal(0.02),
            (self.kernel_size, cin // self.groups, self.features),
        )
        g = self.param("weight_g", nn.initializers.ones, (self.kernel_size,))
        norm = jnp.sqrt(jnp.sum(jnp.square(v), axis=(1, 2), keepdims=True))
        kernel = (g[:, None, None] * v / norm).astype(x.dtype)
        y = jax.lax.conv_general_dilated(
            x,
            kernel,
            window_strides=(1,),
            padding=[(self.padding, self.padding)],
            dimension_numbers=("NWC", "WIO", "NWC"),
            feature_group_count=self.groups,
        )
        return y + _channels(self.param("bias", nn.initializers.zeros, (self.features,)), x.dtype)


class ChannelGroupNorm(nn.Module):
    """GroupNorm with one channel per group: each channel normalised over (the real frames of) time."""

    @nn.compact
    def __call__(
        self, x: Float[Array, "batch time channels"], mask: Bool[Array, "batch time"] | None
    ) -> Float[Array, "batch time channels"]:
        channels = x.shape[-1]
        scale = self.param("scale", nn.initializers.ones, (channels,))
        bias = self.param("bias", nn.initializers.zeros, (channels,))
        if mask is None:
            mean = jnp.mean(x, axis=1, keepdims=True)
            var = jnp.mean(jnp.square(x - mean), axis=1, keepdims=True)
        else:
            weight = mask[:, :, None].astype(x.dtype)
            count = jnp.maximum(jnp.sum(weight, axis=1, keepdims=True), 1.0)
            mean = jnp.sum(x * weight, axis=1, keepdims=True) / count
            var = jnp.sum(jnp.square(x - mean) * weight, axis=1, keepdims=True) / count
        return (x - mean) * jax.lax.rsqrt(var + _TORCH_NORM_EPS) * _channels(scale) + _channels(bias)


class FeatureExtractor(nn.Module):
    """The strided conv stack: waveform ``(batch, samples)`` -> ``(batch, frames, conv_dim[-1])``."""

    config: EncoderConfig

    @nn.compact
    def __call__(
        self,
        waveform: Float[Array, "batch samples"],
        sample_lengths: Int[Array, " batch"] | None,
        mask_group_norm: bool,
    ) -> Float[Array, "batch frames channels"]:
        cfg = self.config
        act = activation(cfg.feat_extract_activation)
        x = waveform[:, :, None]
        for i, (dim, kernel, stride) in enumerate(zip(cfg.conv_dim, cfg.conv_kernel, cfg.conv_stride)):
            # Submodule names mirror HF's "conv_layers.{i}.conv" / "conv_layers.{i}.layer_norm".
            x = _ConvBlock(
                features=dim,
                kernel_size=kernel,
                stride=stride,
                use_bias=cfg.conv_bias,
                norm="layer" if cfg.feat_extract_norm == "layer" else ("group" if i == 0 else None),
                name=f"conv_layers_{i}",
            )(x, _group_norm_mask(cfg, sample_lengths, x.shape[1], kernel, stride, mask_group_norm))
            x = act(x)
        return x


def _group_norm_mask(cfg, sample_lengths, time_in, kernel, stride, mask_group_norm):
    # Only the first conv's output is group-normalised; its valid frames follow the length formula.
    if sample_lengths is None or not mask_group_norm or cfg.feat_extract_norm != "group":
        return None
    time_out = (time_in - kernel) // stride + 1
    return lengths_to_mask(conv_output_lengths(cfg, sample_lengths, num_layers=1), time_out)


class _ConvBlock(nn.Module):
    features: int
    kernel_size: int
    stride: int
    use_bias: bool
    norm: str | None

    @nn.compact
    def __call__(self, x, group_mask):
        x = Conv1d(
            self.features, self.kernel_size, stride=self.stride, use_bias=self.use_bias, name="conv"
        )(x)
        if self.norm == "layer":
            x = _layer_norm(_TORCH_NORM_EPS, "layer_norm")(x)
        elif self.norm == "group":
            x = ChannelGroupNorm(name="layer_norm")(x, group_mask)
        return x


class FeatureProjection(nn.Module):
    """(LayerNorm over conv channels) + Linear to ``hidden_size`` + dropout."""

    config: EncoderConfig
    deterministic: bool = True

    @nn.compact
    def __call__(self, x: Float[Array, "batch frames channels"]) -> Float[Array, "batch frames hidden"]:
        cfg = self.config
        if cfg.feat_proj_layer_norm:
            x = _layer_norm(cfg.layer_norm_eps, "layer_norm")(x)
        x = nn.Dense(cfg.hidden_size, name="projection")(x)
        return nn.Dropout(cfg.feat_proj_dropout)(x, deterministic=self.deterministic)


class PositionalConvEmbedding(nn.Module):
    """Convolutional relative position embedding: grouped conv, same-padding trim, activation."""

    config: EncoderConfig

    @nn.compact
    def __call__(self, x: Float[Array, "batch frames hidden"]) -> Float[Array, "batch frames hidden"]:
        cfg = self.config
        k = cfg.num_conv_pos_embeddings
        if cfg.conv_pos_batch_norm:
            x = _FrozenBatchNorm(name="batch_norm")(x)
            y = Conv1d(
                cfg.hidden_size, k, padding=k // 2, groups=cfg.num_conv_pos_embedding_groups, name="conv"
            )(x)
        else:
            y = WeightNormConv1d(
                cfg.hidden_size, k, padding=k // 2, groups=cfg.num_conv_pos_embedding_groups, name="conv"
            )(x)
        # Padding k // 2 on both sides gives frames + 1 outputs for an even kernel: drop the last
        # (HF's SamePadLayer), so output t sees inputs t - k/2 .. t + k/2 - 1.
        y = y[:, : x.shape[1]]
        return activation(cfg.feat_extract_activation)(y)


class _FrozenBatchNorm(nn.Module):
    """Inference BatchNorm with stored running statistics (HuBERT ``conv_pos_batch_norm``).

    The running mean/var live in ``params`` (as ``mean`` / ``var``) for a single-collection params
    pytree; gradients are stopped on them because they are statistics, not weights.
    """

    @nn.compact
    def __call__(self, x):
        c = x.shape[-1]
        mean = _channels(jax.lax.stop_gradient(self.param("mean", nn.initializers.zeros, (c,))))
        var = _channels(jax.lax.stop_gradient(self.param("var", nn.initializers.ones, (c,))))
        scale = _channels(self.param("scale", nn.initializers.ones, (c,)))
        bias = _channels(self.param("bias", nn.initializers.zeros, (c,)))
        return (x - mean) * jax.lax.rsqrt(var + _TORCH_NORM_EPS) * scale + bias


class SelfAttention(nn.Module):
    """Multi-head self-attention with a key padding mask (HF ``Wav2Vec2Attention``)."""

    config: EncoderConfig
    deterministic: bool = True

    @nn.compact
    def __call__(
        self, x: Float[Array, "batch frames hidden"], key_mask: Bool[Array, "batch frames"]
    ) -> Float[Array, "batch frames hidden"]:
        cfg = self.config
        heads = cfg.num_attention_heads
        head_dim = cfg.hidden_size // heads
        split = lambda t: t.reshape(*t.shape[:2], heads, head_dim)  # noqa: E731
        q = split(nn.Dense(cfg.hidden_size, name="q_proj")(x))
        k = split(nn.Dense(cfg.hidden_size, name="k_proj")(x))
        v = split(nn.Dense(cfg.hidden_size, name="v_proj")(x))
        scores = jnp.einsum("bqhd,bkhd->bhqk", q, k) * (head_dim**-0.5)
        # where() rather than adding a large negative bias: no overflow, and masked keys get exactly 0.
        scores = jnp.where(key_mask[:, None, None, :], scores, jnp.finfo(scores.dtype).min)
        probs = jax.nn.softmax(scores, axis=-1)
        probs = nn.Dropout(cfg.attention_dropout)(probs, deterministic=self.deterministic)
        out = jnp.einsum("bhqk,bkhd->bqhd", probs, v).reshape(x.shape)
        return nn.Dense(cfg.hidden_size, name="out_proj")(out)


class FeedForward(nn.Module):
    """Dense -> activation -> dropout -> Dense -> dropout."""

    config: EncoderConfig
    deterministic: bool = True

    @nn.compact
    def __call__(self, x: Float[Array, "batch frames hidden"]) -> Float[Array, "batch frames hidden"]:
        cfg = self.config
        h = activation(cfg.hidden_act)(nn.Dense(cfg.intermediate_size, name="intermediate_dense")(x))
        h = nn.Dropout(cfg.activation_dropout)(h, deterministic=self.deterministic)
        h = nn.Dense(cfg.hidden_size, name="output_dense")(h)
        return nn.Dropout(cfg.hidden_dropout)(h, deterministic=self.deterministic)


class EncoderLayer(nn.Module):
    """One transformer layer, post-LN (base) or pre-LN (``do_stable_layer_norm``), scan-shaped."""

    config: EncoderConfig
    deterministic: bool = True
    collect: bool = True

    @nn.compact
    def __call__(self, x, key_mask):
        cfg = self.config
        attention = SelfAttention(cfg, self.deterministic, name="attention")
        feed_forward = FeedForward(cfg, self.deterministic, name="feed_forward")
        layer_norm = _layer_norm(cfg.layer_norm_eps, "layer_norm")
        final_layer_norm = _layer_norm(cfg.layer_norm_eps, "final_layer_norm")
        dropout = nn.Dropout(cfg.hidden_dropout)
        if cfg.do_stable_layer_norm:
            x = x + dropout(attention(layer_norm(x), key_mask), deterministic=self.deterministic)
            x = x + feed_forward(final_layer_norm(x))
        else:
            x = layer_norm(x + dropout(attention(x, key_mask), deterministic=self.deterministic))
            x = final_layer_norm(x + feed_forward(x))
        return x, (x if self.collect else None)


class TransformerEncoder(nn.Module):
    """Positional conv + the stack of layers (scanned: one compiled layer body, stacked params)."""

    config: EncoderConfig
    deterministic: bool = True

    @nn.compact
    def __call__(
        self,
        x: Float[Array, "batch frames hidden"],
        frame_mask: Bool[Array, "batch frames"],
        collect_hidden_states: bool = True,
    ) -> tuple[Any, Any, Any]:
        cfg = self.config
        # Padded frames are zeroed so that the positional conv sees zeros there, exactly as it sees
        # its own zero padding at the end of an unpadded input.
        x = jnp.where(frame_mask[:, :, None], x, 0.0)
        x = x + PositionalConvEmbedding(cfg, name="pos_conv_embed")(x)
        layer_norm = _layer_norm(cfg.layer_norm_eps, "layer_norm")
        if not cfg.do_stable_layer_norm:
            x = layer_norm(x)
        x = nn.Dropout(cfg.hidden_dropout)(x, deterministic=self.deterministic)
        first = x
        stacked = None
        if cfg.num_hidden_layers > 0:
            layers = nn.scan(
                EncoderLayer,
                variable_axes={"params": 0},
                split_rngs={"params": True, "dropout": True},
                in_axes=nn.broadcast,
                length=cfg.num_hidden_layers,
            )(cfg, self.deterministic, collect_hidden_states, name="layers")
            x, stacked = layers(x, frame_mask)
        last = layer_norm(x) if cfg.do_stable_layer_norm else x
        hidden = None
        if collect_hidden_states:
            hidden = first[None] if stacked is None else jnp.concatenate([first[None], stacked], axis=0)
        return last, hidden, x


class Wav2Vec2Model(nn.Module):
    """wav2vec 2.0 / HuBERT encoder (HF ``Wav2Vec2Model`` / ``HubertModel`` without masking heads).

    Attributes:
        config: the architecture.
        deterministic: False turns dropout on (fine-tuning; needs a ``"dropout"`` rng).

    Methods (use ``model.apply(variables, ..., method=...)``):
        ``__call__(waveform, attention_mask=None, ...)``: the whole encoder -> :class:`EncoderOutput`.
        ``extract(waveform, sample_lengths=None, ...)``: conv features + their valid lengths.
        ``transform(conv_features, frame_lengths=None, ...)``: projection + transformer.
        Splitting the two lets a caller change the frame rate in between (TIMAR/DualTalk).
    """

    config: EncoderConfig
    deterministic: bool = True

    def setup(self):
        self.feature_extractor = FeatureExtractor(self.config)
        self.feature_projection = FeatureProjection(self.config, self.deterministic)
        self.encoder = TransformerEncoder(self.config, self.deterministic)

    def extract(
        self,
        waveform: Float[Array, "batch samples"],
        sample_lengths: Int[Array, " batch"] | None = None,
        mask_group_norm: bool = True,
    ) -> tuple[Float[Array, "batch frames channels"], Int[Array, " batch"]]:
        """Conv feature extractor.

        Args:
            waveform: ``(batch, samples)`` right-padded audio (already normalised if the checkpoint
                expects it).
            sample_lengths: ``(batch,)`` real samples per row; None = all.
            mask_group_norm: group-norm statistics over real frames only (see module docstring).

        Returns:
            ``(conv_features (batch, frames, conv_dim[-1]), frame_lengths (batch,) int32)``.
        """
        features = self.feature_extractor(waveform, sample_lengths, mask_group_norm)
        frames = features.shape[1]
        if sample_lengths is None:
            lengths = jnp.full((waveform.shape[0],), frames, jnp.int32)
        else:
            lengths = jnp.minimum(conv_output_lengths(self.config, sample_lengths), frames)
        return features, lengths

    def transform(
        self,
        conv_features: Float[Array, "batch frames channels"],
        frame_lengths: Int[Array, " batch"] | None = None,
        collect_hidden_states: bool = True,
    ) -> EncoderOutput:
        """Feature projection + transformer encoder on conv features.

        Args:
            conv_features: ``(batch, frames, conv_dim[-1])``.
            frame_lengths: ``(batch,)`` real frames per row; None = all.
            collect_hidden_states: also return every layer's output.

        Returns:
            :class:`EncoderOutput`.
        """
        batch, frames = conv_features.shape[:2]
        if frame_lengths is None:
            frame_lengths = jnp.full((batch,), frames, jnp.int32)
        mask = lengths_to_mask(frame_lengths, frames)
        hidden = self.feature_projection(conv_features)
        last, all_hidden, layer_out = self.encoder(hidden, mask, collect_hidden_states)
        return EncoderOutput(last, all_hidden, layer_out, mask)

    def __call__(
        self,
        waveform: Float[Array, "batch samples"],
        attention_mask: Bool[Array, "batch samples"] | None = None,
        collect_hidden_states: bool = True,
        mask_group_norm: bool = True,
    ) -> EncoderOutput:
        """Run the whole encoder.

        Args:
            waveform: ``(batch, samples)`` right-padded audio.
            attention_mask: ``(batch, samples)`` True on real samples (right padding, as HF); None =
                all real.
            collect_hidden_states: also return every layer's output.
            mask_group_norm: see the module docstring (False reproduces HF on padded batches).

        Returns:
            :class:`EncoderOutput`.
        """
        lengths = None
        if attention_mask is not None:
            lengths = jnp.sum(attention_mask.astype(jnp.int32), axis=-1)
        features, frame_lengths = self.extract(waveform, lengths, mask_group_norm)
        return self.transform(features, frame_lengths, collect_hidden_states)
