"""Pretrained speech encoders as a jaxtalk audio front end.

:class:`SpeechEncoder` turns a loaded checkpoint into per-frame features at the encoder's own rate
(50 Hz for the standard conv stack at 16 kHz) and converts them to the motion rate (25 fps), the
same interface as the built-in log-mel front end and the VQ token streams (:meth:`SpeechEncoder.encode`
returns a :class:`~jaxtalk.audio.TokenStream`, ``ids=None``).

Inside a model's own jitted program use the pure function :func:`encoder_features` (or
``SpeechEncoder.apply``) with the params as an ordinary argument: ``frozen=True`` stops gradients
into them (the papers' frozen encoders), ``frozen=False`` fine-tunes them (``dropout_key`` turns on
the checkpoint's dropout rates).

Two ways to reach the motion rate (both documented by the papers' code):

* ``features_at`` (FreeTalk): run the encoder at 50 Hz, then resample its output with
  :func:`jaxtalk.audio.resample_features` (frame ``i`` at time ``i / 50`` s).
* ``interpolated_features`` (TIMAR / DualTalk, after FaceFormer's ``wav2vec.py``): linearly
  interpolate the CONV features along time to the number of motion frames BEFORE the feature
  projection and transformer, with PyTorch's ``F.interpolate(mode="linear", align_corners=True)``
  convention: output frame ``j`` of ``m`` samples input position ``j (n - 1) / (m - 1)`` of ``n``, so
  the first and last frames coincide. The transformer then runs at 25 fps.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Bool, Float, Int

from jaxtalk.audio.encoders.config import EncoderConfig
from jaxtalk.audio.encoders.loader import load_checkpoint
from jaxtalk.audio.encoders.wav2vec2 import Wav2Vec2Model, lengths_to_mask
from jaxtalk.types import MOTION_FPS, Array, PRNGKeyArray

__all__ = [
    "SpeechEncoder",
    "encoder_features",
    "normalize_waveform",
    "interpolate_align_corners",
    "resolve_layer",
]

# HF zero_mean_unit_var_norm adds this to the variance.
_NORMALIZE_EPS = 1e-7


def normalize_waveform(
    waveform: Float[Array, "batch samples"], sample_lengths: Int[Array, " batch"]
) -> Float[Array, "batch samples"]:
    """Zero mean / unit variance per row over its real samples; padding set to 0 (HF processors).

    Args:
        waveform: ``(batch, samples)`` right-padded audio.
        sample_lengths: ``(batch,)`` real samples per row (>= 1).

    Returns:
        ``(x - mean) / sqrt(var + 1e-7)`` on real samples, 0 on padding.
    """
    mask = lengths_to_mask(sample_lengths, waveform.shape[1])
    count = jnp.maximum(sample_lengths, 1).astype(waveform.dtype)[:, None]
    mean = jnp.sum(jnp.where(mask, waveform, 0.0), axis=1, keepdims=True) / count
    var = jnp.sum(jnp.where(mask, jnp.square(waveform - mean), 0.0), axis=1, keepdims=True) / count
    return jnp.where(mask, (waveform - mean) * jax.lax.rsqrt(var + _NORMALIZE_EPS), 0.0)


def interpolate_align_corners(
    x: Float[Array, "batch frames channels"],
    in_lengths: Int[Array, " batch"],
    out_lengths: Int[Array, " batch"],
    num_out: int,
) -> Float[Array, "batch num_out channels"]:
    """Per-row linear interpolation in time, ``align_corners=True`` (PyTorch ``F.interpolate``).

    Row ``b`` maps its first ``in_lengths[b]`` frames to ``out_lengths[b]`` frames: output ``j`` sits
    at input position ``j (in - 1) / (out - 1)`` (position 0 when ``out == 1``). Outputs past
    ``out_lengths[b]`` are 0. Lengths are traced, ``num_out`` (the padded size) is static.

    Args:
        x: ``(batch, frames, channels)`` right-padded features.
        in_lengths: ``(batch,)`` real input frames (>= 1).
        out_lengths: ``(batch,)`` wanted output frames (<= ``num_out``).
        num_out: padded output length.

    Returns:
        ``(batch, num_out, channels)``.
    """
    j = jnp.arange(num_out, dtype=jnp.int32)[None, :]
    span_in = (in_lengths - 1)[:, None]
    span_out = jnp.maximum(out_lengths - 1, 1)[:, None]
    # Integer numerator, one float division: the exact position rounded once.
    pos = (j * span_in).astype(x.dtype) / span_out.astype(x.dtype)
    lo = jnp.clip(jnp.floor(pos).astype(jnp.int32), 0, span_in)
    hi = jnp.minimum(lo + 1, span_in)
    w = (pos - lo.astype(x.dtype))[:, :, None]
    take = lambda idx: jnp.take_along_axis(x, idx[:, :, None], axis=1)  # noqa: E731
    out = take(lo) * (1 - w) + take(hi) * w
    return jnp.where((j < out_lengths[:, None])[:, :, None], out, 0.0)


def resolve_layer(config: EncoderConfig, layer: int | None) -> int | None:
    """Validate ``layer`` and make it non-negative: None (final output) or an index in [0, layers].

    Index ``k`` is HF's ``hidden_states[k]``: 0 = input of the first transformer layer, ``k`` = output
    of layer ``k``; negative indices count from the end (``-1`` = output of the last layer, which
    for stable-layer-norm models is BEFORE the final LayerNorm; None gives the normalised output).

    Raises:
        ValueError: out of range or not an integer.
    """
    if layer is None:
        return None
    total = config.num_hidden_layers + 1
    if isinstance(layer, bool) or not isinstance(layer, (int, np.integer)) or not -total <= layer < total:
        raise ValueError(
            f"layer must be None or an integer in [{-total}, {total - 1}] for a "
            f"{config.num_hidden_layers}-layer encoder, got {layer!r}"
        )
    return int(layer) % total


def _slice_layers(params: dict[str, Any], config: EncoderConfig, num_layers: int) -> dict[str, Any]:
    """Params of the first ``num_layers`` transformer layers (stacked on axis 0)."""
    if num_layers == config.num_hidden_layers:
        return params
    encoder = dict(params["encoder"])
    layers = encoder.pop("layers")
    if num_layers > 0:
        encoder["layers"] = jax.tree.map(lambda a: a[:num_layers], layers)
    return {**params, "encoder": encoder}


def encoder_features(
    params: dict[str, Any],
    waveform: Float[Array, "batch samples"],
    sample_lengths: Int[Array, " batch"] | None = None,
    *,
    config: EncoderConfig,
    layer: int | None = None,
    normalize: bool = False,
    frozen: bool = True,
    mask_group_norm: bool = True,
    interpolate_frames: int | None = None,
    interpolate_lengths: Int[Array, " batch"] | None = None,
    dropout_key: PRNGKeyArray | None = None,
) -> tuple[Float[Array, "batch frames hidden"], Bool[Array, "batch frames"]]:
    """Pure, jit-able encoder: waveform -> features of one layer, with the frame mask.

    Only the layers up to ``layer`` run (a middle layer costs less than the full model).

    Args:
        params: Flax params of :class:`Wav2Vec2Model` (``Checkpoint.params``).
        waveform: ``(batch, samples)`` right-padded audio at the model's rate (16 kHz).
        sample_lengths: ``(batch,)`` real samples per row; None = all.
        config: architecture (static).
        layer: None = HF ``last_hidden_state``; an int = HF ``hidden_states[layer]`` (static).
        normalize: zero-mean / unit-variance each row first (the checkpoint's ``do_normalize``).
        frozen: stop gradients into ``params``.
        mask_group_norm: group-norm statistics over real frames only (padding-invariant).
        interpolate_frames: TIMAR/DualTalk variant: interpolate the conv features to this many
            (padded) frames before the transformer (static); None = native 50 Hz.
        interpolate_lengths: ``(batch,)`` real output frames per row for the interpolation;
            None = ``interpolate_frames`` for every row.
        dropout_key: PRNG key turning dropout on (fine-tuning); None = deterministic.

    Returns:
        ``(features (batch, frames, hidden_size), frame_mask (batch, frames))``.

    Raises:
        ValueError: a bad ``layer`` or ``interpolate_frames``, or a non-2-D waveform.
    """
    if waveform.ndim != 2:
        raise ValueError(f"waveform must be (batch, samples), got shape {waveform.shape}")
    layer = resolve_layer(config, layer)
    run_layers = config.num_hidden_layers if layer is None else layer
    if frozen:
        params = jax.lax.stop_gradient(params)
    batch, samples = waveform.shape
    if sample_lengths is None:
        sample_lengths = jnp.full((batch,), samples, jnp.int32)
    sample_lengths = jnp.asarray(sample_lengths, jnp.int32)
    if normalize:
        waveform = normalize_waveform(waveform, sample_lengths)
    model = Wav2Vec2Model(config.truncated(run_layers), deterministic=dropout_key is None)
    variables = {"params": _slice_layers(params, config, run_layers)}
    rngs = None if dropout_key is None else {"dropout": dropout_key}
    conv, frame_lengths = model.apply(
        variables, waveform, sample_lengths, mask_group_norm, method=Wav2Vec2Model.extract
    )
    if interpolate_frames is not None:
        if isinstance(interpolate_frames, bool) or not isinstance(interpolate_frames, int) or interpolate_frames < 1:
            raise ValueError(f"interpolate_frames must be a positive integer, got {interpolate_frames!r}")
        out_lengths = (
            jnp.full((batch,), interpolate_frames, jnp.int32)
            if interpolate_lengths is None
            else jnp.minimum(jnp.asarray(interpolate_lengths, jnp.int32), interpolate_frames)
        )
        conv = interpolate_align_corners(conv, jnp.maximum(frame_lengths, 1), out_lengths, interpolate_frames)
        frame_lengths = out_lengths
    out = model.apply(
        variables, conv, frame_lengths, False, method=Wav2Vec2Model.transform, rngs=rngs
    )
    features = out.last_hidden_state if layer is None else out.layer_output
    return features, out.frame_mask


_jitted_features = jax.jit(
    encoder_features,
    static_argnames=("config", "layer", "normalize", "frozen", "mask_group_norm", "interpolate_frames"),
)


@dataclasses.dataclass(frozen=True, eq=False)
class SpeechEncoder:
    """A pretrained wav2vec 2.0 / HuBERT encoder as an audio front end.

    Attributes:
        config: the architecture.
        params: Flax params (NumPy or JAX arrays).
        normalize: normalise each waveform to zero mean / unit variance first.
        sample_rate: the rate the encoder expects (16 kHz).
        pad_multiple: host-side inputs are zero-padded (with a length mask) to a multiple of this
            many samples so that clips of similar length share one compiled program; padding does
            not change the features (see ``mask_group_norm``).
    """

    config: EncoderConfig
    params: dict[str, Any]
    normalize: bool = True
    sample_rate: int = 16_000
    pad_multiple: int = 16_000

    def __post_init__(self):
        if not isinstance(self.pad_multiple, int) or self.pad_multiple < 1:
            raise ValueError(f"pad_multiple must be a positive integer, got {self.pad_multiple!r}")

    @classmethod
    def from_pretrained(
        cls,
        path: str | os.PathLike[str],
        *,
        dtype: Any = np.float32,
        normalize: bool | None = None,
        pad_multiple: int = 16_000,
    ) -> SpeechEncoder:
        """Load a Hugging Face checkpoint directory (``config.json`` + ``model.safetensors``).

        Args:
            path: checkpoint directory.
            dtype: params dtype.
            normalize: override the checkpoint's ``do_normalize``.
            pad_multiple: see the class attributes.

        Raises:
            FileNotFoundError, ImportError, ValueError: see :func:`load_checkpoint`.
        """
        ckpt = load_checkpoint(path, dtype=dtype)
        params = jax.tree.map(jnp.asarray, ckpt.params)
        return cls(
            ckpt.config,
            params,
            ckpt.normalize if normalize is None else bool(normalize),
            ckpt.sample_rate,
            pad_multiple,
        )

    @property
    def rate(self) -> float:
        """Feature frames per second (50.0 for the standard conv stack at 16 kHz)."""
        return self.config.frame_rate(self.sample_rate)

    @property
    def dim(self) -> int:
        """Feature width (``hidden_size``: 768 base, 1024 large)."""
        return self.config.hidden_size

    @property
    def num_layers(self) -> int:
        """Transformer layers; valid ``layer`` indices are ``-(num_layers + 1) .. num_layers``."""
        return self.config.num_hidden_layers

    def apply(
        self,
        params: dict[str, Any],
        waveform: Float[Array, "batch samples"],
        sample_lengths: Int[Array, " batch"] | None = None,
        **kwargs: Any,
    ) -> tuple[Float[Array, "batch frames hidden"], Bool[Array, "batch frames"]]:
        """:func:`encoder_features` with this encoder's config and normalisation bound (pure)."""
        kwargs.setdefault("normalize", self.normalize)
        return encoder_features(params, waveform, sample_lengths, config=self.config, **kwargs)

    # -- host-side helpers -------------------------------------------------------------------

    def _prepare(self, audio: Any, sample_rate: int | None, name: str = "audio") -> np.ndarray:
        from jaxtalk.audio import resample_audio

        if isinstance(audio, jax.core.Tracer):
            raise ValueError(f"{name}: host-side features() got a traced array; use SpeechEncoder.apply inside jit")
        audio = np.asarray(audio)
        if audio.ndim != 1:
            raise ValueError(f"{name}: expected mono audio of shape (samples,), got shape {audio.shape}")
        if not np.issubdtype(audio.dtype, np.floating):
            raise ValueError(f"{name}: expected a float waveform in [-1, 1], got dtype {audio.dtype}")
        if not np.all(np.isfinite(audio)):
            raise ValueError(f"{name}: audio contains {int(np.sum(~np.isfinite(audio)))} NaN/inf samples")
        if sample_rate is not None:
            if isinstance(sample_rate, bool) or not isinstance(sample_rate, (int, np.integer)) or sample_rate <= 0:
                raise ValueError(f"sample_rate must be a positive integer of Hz, got {sample_rate!r}")
            if sample_rate != self.sample_rate:
                audio = resample_audio(audio, sample_rate, self.sample_rate)
        minimum = self.config.receptive_field
        if audio.shape[0] < minimum:
            raise ValueError(
                f"{name}: {audio.shape[0]} samples is too short for the encoder: it needs at least "
                f"{minimum} samples ({1e3 * minimum / self.sample_rate:.1f} ms) at {self.sample_rate} Hz"
            )
        return audio.astype(np.float32)

    def _padded(self, audios: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        longest = max(a.shape[0] for a in audios)
        size = -(-longest // self.pad_multiple) * self.pad_multiple
        batch = np.zeros((len(audios), size), np.float32)
        for row, audio in enumerate(audios):
            batch[row, : audio.shape[0]] = audio
        return batch, np.array([a.shape[0] for a in audios], np.int32)

    def features_batch(
        self,
        audios: list[Any],
        layer: int | None = None,
        *,
        sample_rate: int | None = None,
    ) -> tuple[Float[Array, "batch frames hidden"], Bool[Array, "batch frames"]]:
        """Features of several clips of different lengths in one padded, jitted call.

        Args:
            audios: list of ``(samples,)`` float waveforms.
            layer: see :func:`resolve_layer`.
            sample_rate: the clips' rate; resampled when it differs from ``self.sample_rate``
                (None = already at ``self.sample_rate``).

        Returns:
            ``(features (batch, frames, dim), frame_mask (batch, frames))``; row ``b`` has
            ``config.num_frames(len(audios[b]))`` real frames, equal to ``features(audios[b])``.

        Raises:
            ValueError: an empty list, or a bad clip (see :meth:`features`).
        """
        if not isinstance(audios, (list, tuple)) or not audios:
            raise ValueError("audios must be a non-empty list of waveforms")
        clips = [self._prepare(a, sample_rate, name=f"audios[{i}]") for i, a in enumerate(audios)]
        batch, lengths = self._padded(clips)
        frames = max(self.config.num_frames(c.shape[0]) for c in clips)
        features, mask = _jitted_features(
            self.params, batch, lengths, config=self.config, layer=layer, normalize=self.normalize
        )
        return features[:, :frames], mask[:, :frames]

    def features(
        self, audio: Any, layer: int | None = None, *, sample_rate: int | None = None
    ) -> Float[Array, "frames hidden"]:
        """Per-frame features of one clip at :attr:`rate` (50 Hz).

        Args:
            audio: ``(samples,)`` float waveform.
            layer: None = the model output (HF ``last_hidden_state``); an int = HF
                ``hidden_states[layer]`` (0 = transformer input, -1 = last layer's output).
            sample_rate: the clip's rate; resampled when it differs from ``self.sample_rate``
                (None = already at ``self.sample_rate``, which cannot be checked: pass it when
                unsure).

        Returns:
            ``(config.num_frames(samples), dim)`` features.

        Raises:
            ValueError: not 1-D, not float, NaN/inf, shorter than the receptive field (400
                samples), a bad ``sample_rate`` or ``layer``.
        """
        features, _ = self.features_batch([audio], layer, sample_rate=sample_rate)
        return features[0]

    def features_at(
        self,
        audio: Any,
        fps: float | int = MOTION_FPS,
        *,
        layer: int | None = None,
        num_frames: int | None = None,
        mode: str = "linear",
        sample_rate: int | None = None,
    ) -> Float[Array, "frames hidden"]:
        """Features at the motion rate: 50 Hz features resampled with ``resample_features``.

        Args:
            audio, layer, sample_rate: see :meth:`features`.
            fps: target frame rate (25 by default).
            num_frames: output frames; default ``round(duration * fps)``.
            mode: ``"linear"`` or ``"previous"`` (causal), see ``resample_features``.

        Returns:
            ``(num_frames, dim)``.
        """
        from jaxtalk.audio import resample_features

        clip = self._prepare(audio, sample_rate)
        if num_frames is None:
            num_frames = self._motion_frames(clip.shape[0], fps)
        return resample_features(self.features(clip, layer), self.rate, fps, num_frames=num_frames, mode=mode)

    def interpolated_features(
        self,
        audio: Any,
        fps: float | int = MOTION_FPS,
        *,
        layer: int | None = None,
        num_frames: int | None = None,
        sample_rate: int | None = None,
    ) -> Float[Array, "frames hidden"]:
        """TIMAR/DualTalk variant: conv features interpolated to the motion rate before the transformer.

        Args:
            audio, layer, sample_rate: see :meth:`features`.
            fps: motion frame rate used for the default length.
            num_frames: motion frames (the length of the motion clip); default
                ``round(duration * fps)``.

        Returns:
            ``(num_frames, dim)``.
        """
        clip = self._prepare(audio, sample_rate)
        if num_frames is None:
            num_frames = self._motion_frames(clip.shape[0], fps)
        if isinstance(num_frames, bool) or not isinstance(num_frames, (int, np.integer)) or num_frames < 1:
            raise ValueError(f"num_frames must be a positive integer, got {num_frames!r}")
        batch, lengths = self._padded([clip])
        features, _ = _jitted_features(
            self.params,
            batch,
            lengths,
            config=self.config,
            layer=layer,
            normalize=self.normalize,
            interpolate_frames=int(num_frames),
        )
        return features[0]

    def encode(
        self, audio: Any, layer: int | None = None, *, sample_rate: int | None = None
    ) -> Any:
        """Features as a :class:`~jaxtalk.audio.TokenStream` (``ids=None``, ``rate=self.rate``).

        The same object the VQ tokenizers return, so models consume either front end;
        ``stream.to_frame_rate(25)`` converts it to the motion rate.
        """
        from jaxtalk.audio import TokenStream

        features = self.features(audio, layer, sample_rate=sample_rate)
        return TokenStream(ids=None, embeddings=np.asarray(features, np.float32), rate=self.rate)

    def _motion_frames(self, samples: int, fps: float | int) -> int:
        from jaxtalk.audio import default_num_frames

        return default_num_frames(samples, self.sample_rate, fps)

