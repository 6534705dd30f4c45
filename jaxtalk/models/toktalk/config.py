"""TokTalk configuration: one frozen dataclass, with ``paper``, ``small`` and ``tiny`` presets.

Everything here is static (it sets shapes, loop lengths or the compiled program); numeric knobs a user
sweeps at fixed shapes (CFG weight, the time grid values, the style vector) are traced arguments of
the sampling functions instead. Defaults not given in the paper come from ``papers/NOTES.md``
(chunk 10 frames, overlap 5, 10 Euler steps on the cosine grid, w = 0.7, sigma_min 1e-6, condition
dropout 0.2) and the CosyVoice decoder's sizes from ``design/REFERENCE_NOTES.md``.
"""

from __future__ import annotations

import dataclasses
import math

from jaxtalk.types import MOTION_FPS, PARAM_DIM, check_compute_dtype

__all__ = ["TokTalkConfig"]


def _check(name: str, ok: bool, value: object) -> None:
    if not ok:
        raise ValueError(f"TokTalkConfig.{name} is invalid: {value!r}")


@dataclasses.dataclass(frozen=True)
class TokTalkConfig:
    """Static settings of the TokTalk model, its training and its samplers.

    Attributes:
        param_dim: motion width (56: ``[exp 50 | jaw 3 | neck 3]``).
        fps: motion frame rate.
        token_rate: base token stream rate in Hz (Mimi / SynthTalk stream "A": 12.5).
        speech_dim: base token embedding width (SynthTalk stream "A": 64).
        width: width of every U-Net stage (the reference decoder: 256). Keep it well above
            ``param_dim``: the velocity's noise part is a near-identity map of the input.
        num_mid_blocks: middle stages (reference: 12).
        transformer_blocks: transformer blocks per stage (reference: 4).
        num_heads, head_dim: attention heads and their width (reference: 8 x 64).
        mlp_ratio: feed-forward width / width (4).
        time_frequency_dim: sinusoidal time features (320) fed to the time MLP.
        time_embed_dim: time embedding width (1024).
        num_groups: group-norm groups in the ResNet blocks (8).
        causal: the streaming model (default). The decoder has causal convolutions, causal stride-2
            down/upsampling and a per-frame LayerNorm (CosyVoice2's streaming decoder), so under the
            chunk mask a frame's receptive field ends at the last frame of its own chunk; tokens are
            aligned to frames without looking ahead (frame ``f`` takes the latest token that starts
            at or before it); the adaptation layer has a causal convolution and attends only to the
            last ``adapter_context`` tokens. False is the OFFLINE model: centred convolutions,
            masked GroupNorm over time (CosyVoice's offline decoder), linear token interpolation
            (odd frames blend the next token) and a bidirectional adapter. It sees the future even
            with the chunk mask, so it is for whole-utterance sampling only; streaming it is refused.
        style_dim: width of the style encoder's latent (MSMD: 256).
        style_anchor: append the reference clip's mean pose (standardised) to the style vector and run
            the flow in coordinates centred on it, so the decoder generates motion RELATIVE to the
            speaker's resting pose seen in the reference clip. The style vector is then
            ``style_dim + param_dim`` wide (:attr:`style_vector_dim`). Default on: a speaker's resting
            pose is most of a clip's motion; see docs/design-decisions.md.
        anchor_input: with ``style_anchor``, also show the anchor pose to the decoder as part of the style
            condition (True), or only centre the flow on it (False: the decoder sees the style latent
            alone). The ``small`` preset turns it off: a decoder that reads the training speakers'
            anchors extrapolates badly to new ones (see ``style_source``).
        latent_input: show the style encoder's latent to the decoder (True), or not (False: the decoder
            sees no style at all unless ``anchor_input``; with ``style_anchor`` the anchor still centres
            the flow). The ``small`` preset turns it off: a decoder can memorise few training speakers'
            latents and misplace the rest pose of speakers it never saw (see ``style_source``).
        style_source: where a training example's reference clip comes from: ``"target"``, a crop of
            the target clip itself (the paper's objective), or ``"other_clip"``, a crop of ANOTHER clip
            of the same speaker (a departure: the style vector cannot copy the target, so training
            measures real style transfer; a speaker with one clip falls back to the target). With
            another clip the target's offset from the anchor is the difference of two clips' emotion
            offsets, which a decoder can only learn per training speaker (from the voice); with the
            target's own crop it is the window's motion about the clip's mean, the same for every
            speaker. The ``small`` preset trains on the target's crop and shows the decoder neither the
            anchor nor the latent; the anchor pose still centres the flow, so a new speaker's rest pose
            comes from its reference clip. The ``paper`` preset is the paper's (target crop, learned
            latent, no anchor). Why ``small`` does so: it stays under the mean pose on held-out
            speakers however long it trains; see docs/design-decisions.md.
        style_hidden: style encoder width (MSMD: 512).
        style_heads: style encoder attention heads (8).
        style_frames: length of the reference clip used in training (frames).
        style_min_frames: shortest accepted reference clip (frames).
        kl_weight: weight of the style encoder's KL term (MSMD: 1e-7).
        adapter_width, adapter_layers, adapter_heads: adaptation layer transformer sizes.
        adapter_kernel: taps of the adapter's input convolution.
        adapter_context: with ``causal``, the tokens each adapter attention query sees (itself and the
            ``adapter_context - 1`` before it, at the base rate): a bounded past, so the streaming
            adapter carries a fixed-size state.
        adapter_max_position: the adaptation layer's positions are counted from the start of the
            utterance, so a stream reaches positions far past a training window; stage-2 training
            places each batch's window at a random start in ``[0, adapter_max_position - window)`` so
            that every position up to this one (15,000 tokens: 10 min at 25 Hz) is one it was trained at.
        chunk_frames: streaming chunk (even: one stride-2 down/up pair halves it).
        overlap_frames: frames of previous output re-used as known frames for the next chunk (the
            paper's overlap inpainting; 5 from its notes). With the causal decoder the left context
            is regenerated from the same noise anyway, and feeding emitted frames back drifts, so 0
            streams with a lower error; see docs/design-decisions.md.
        context_frames: bounded left context of the streaming window (a multiple of chunk_frames).
        sample_steps: Euler steps at inference.
        cfg_scale: default classifier-free guidance weight w (traced at sampling time).
        temperature: default scale of the starting noise at inference (traced at sampling time; 1: the
            trained prior). Below 1 the sampler starts nearer the flow's mean and trades diversity for
            accuracy, as flow-matching TTS samplers do (Matcha-TTS samples at 0.667); 0 integrates the
            flow from the mean of the prior. The ``small`` preset samples at 0.25 (its 10-step samples
            beat the mean pose and keep the data's smoothness there; see docs/design-decisions.md), the
            ``paper`` preset at the paper's 1 (``tiny``, for unit tests, at 1); ``--temperature`` of
            ``sample``, ``stream``, ``serve`` and ``eval`` overrides it.
        sigma_min: minimum noise of the CFM path.
        cfg_dropout: probability of dropping audio, style and known frames together (CFG training).
        known_prob: probability that a training example gets a known-frames segment.
        known_max_fraction: longest known segment as a fraction of the example's length.
        chunk_mask_prob: probability that a training batch uses the chunk mask (else the full mask).
        dropout: dropout rate in the transformer blocks (training only).
        precondition: wrap the decoder in the Gaussian-optimal skip/scale of the flow path (see
            :func:`jaxtalk.models.toktalk.model.velocity`); False = the raw decoder output, as in CosyVoice.
        noise_frames: temporal correlation of the flow's starting noise, as the standard deviation in
            frames of a Gaussian smoothing of white noise (rescaled to unit variance per frame); 0 =
            white noise (the paper's). See :mod:`jaxtalk.models.toktalk.noise`. Default 2 frames: the
            noise the decoder leaves becomes smooth motion instead of jitter; see docs/design-decisions.md.
        time_sampling: training flow times: "cosine" (``t = 1 - cos(u pi / 2)``, ``u ~ U(0, 1)``:
            more weight near the noise end, where the conditional mean is learned; CosyVoice's
            ``t_scheduler: cosine``) or "uniform" (``t ~ U(0, 1)``). Default cosine: a lower one-step
            mouth error; see docs/design-decisions.md.
    """

    param_dim: int = PARAM_DIM
    fps: int = MOTION_FPS
    token_rate: float = 12.5
    speech_dim: int = 64
    width: int = 256
    num_mid_blocks: int = 12
    transformer_blocks: int = 4
    num_heads: int = 8
    head_dim: int = 64
    mlp_ratio: float = 4.0
    time_frequency_dim: int = 320
    time_embed_dim: int = 1024
    num_groups: int = 8
    causal: bool = True
    style_dim: int = 256
    style_anchor: bool = True
    anchor_input: bool = True
    latent_input: bool = True
    style_source: str = "other_clip"
    style_hidden: int = 512
    style_heads: int = 8
    style_frames: int = 50
    style_min_frames: int = 10
    kl_weight: float = 1e-7
    adapter_width: int = 256
    adapter_layers: int = 2
    adapter_heads: int = 4
    adapter_kernel: int = 3
    adapter_context: int = 16
    adapter_max_position: int = 15000
    chunk_frames: int = 10
    overlap_frames: int = 5
    context_frames: int = 40
    sample_steps: int = 10
    cfg_scale: float = 0.7
    temperature: float = 1.0
    sigma_min: float = 1e-6
    cfg_dropout: float = 0.2
    known_prob: float = 0.5
    known_max_fraction: float = 0.3
    chunk_mask_prob: float = 0.5
    dropout: float = 0.0
    precondition: bool = True
    noise_frames: float = 2.0
    time_sampling: str = "cosine"
    compute_dtype: str = "float32"

    def __post_init__(self) -> None:
        check_compute_dtype(self.compute_dtype, "TokTalkConfig")
        positive = (
            "param_dim", "fps", "speech_dim", "width", "transformer_blocks", "num_heads", "head_dim",
            "time_frequency_dim", "time_embed_dim", "num_groups", "style_dim", "style_hidden",
            "style_heads", "style_frames", "style_min_frames", "adapter_width", "adapter_layers",
            "adapter_heads", "adapter_kernel", "adapter_context", "adapter_max_position", "chunk_frames", "sample_steps",
        )
        for name in positive:
            value = getattr(self, name)
            _check(name, isinstance(value, int) and not isinstance(value, bool) and value > 0, value)
        _check("num_mid_blocks", isinstance(self.num_mid_blocks, int) and self.num_mid_blocks >= 0,
               self.num_mid_blocks)
        _check("token_rate", math.isfinite(self.token_rate) and self.token_rate > 0, self.token_rate)
        _check("width", self.width % self.num_groups == 0, (self.width, self.num_groups))
        _check("style_hidden", self.style_hidden % self.style_heads == 0, (self.style_hidden, self.style_heads))
        _check("adapter_width", self.adapter_width % self.adapter_heads == 0,
               (self.adapter_width, self.adapter_heads))
        if self.chunk_frames % 2:
            raise ValueError(
                f"chunk_frames={self.chunk_frames} must be even: the decoder's stride-2 downsampling "
                "needs whole chunks of chunk_frames / 2 at the half rate"
            )
        _check("overlap_frames", 0 <= self.overlap_frames <= self.context_frames, self.overlap_frames)
        if self.context_frames < 0 or self.context_frames % self.chunk_frames:
            raise ValueError(
                f"context_frames={self.context_frames} must be a non-negative multiple of "
                f"chunk_frames={self.chunk_frames} (the streaming window is whole chunks)"
            )
        _check("style_min_frames", self.style_min_frames <= self.style_frames, self.style_min_frames)
        for name in ("cfg_dropout", "known_prob", "known_max_fraction", "chunk_mask_prob", "dropout"):
            value = getattr(self, name)
            _check(name, 0.0 <= value <= 1.0, value)
        _check("sigma_min", 0.0 <= self.sigma_min < 1.0, self.sigma_min)
        _check("kl_weight", self.kl_weight >= 0.0, self.kl_weight)
        _check("noise_frames", math.isfinite(self.noise_frames) and 0.0 <= self.noise_frames <= 50.0, self.noise_frames)
        _check("temperature", math.isfinite(self.temperature) and self.temperature >= 0.0, self.temperature)
        _check("time_sampling", self.time_sampling in ("uniform", "cosine"), self.time_sampling)
        _check("style_source", self.style_source in ("target", "other_clip"), self.style_source)

    # ------------------------------------------------------------------------------- presets
    @classmethod
    def paper(cls, **overrides: object) -> TokTalkConfig:
        """The reference decoder's sizes (about 82M parameters with a 56-d target) and the paper's
        objective: white starting noise (``noise_frames=0``), the style clip cropped from the target
        (``style_source="target"``) and no anchor pose (``style_anchor=False``).

        The other presets keep jaxtalk's departures on (time-correlated noise, another clip's style,
        the anchor pose; each documented on its field, its measurement in docs/design-decisions.md):
        pass them here as overrides to train the paper-size model with them.
        """
        return dataclasses.replace(cls(noise_frames=0.0, style_anchor=False, style_source="target"), **overrides)

    @classmethod
    def small(cls, **overrides: object) -> TokTalkConfig:
        """Learns SynthTalk in minutes on 2 CPU cores and streams in real time there; trains on the
        target clip's own crop as the style and shows the decoder neither the anchor nor the style
        latent (so held-out speakers stay under the mean pose as it trains; see ``style_source``);
        samples at temperature 0.25 (see ``temperature``)."""
        # Width 64 is enough once the decoder is preconditioned (``precondition``): the skip carries
        # the near-identity noise part of the velocity that a 64-wide U-Net alone learns far more slowly.
        base = cls(
            width=64,
            num_mid_blocks=2,
            transformer_blocks=1,
            num_heads=4,
            head_dim=32,
            time_frequency_dim=64,
            time_embed_dim=128,
            style_dim=32,
            style_hidden=64,
            style_heads=4,
            adapter_width=64,
            adapter_layers=1,
            adapter_heads=4,
            context_frames=20,
            style_source="target",
            anchor_input=False,
            latent_input=False,
            temperature=0.25,
        )
        return dataclasses.replace(base, **overrides)

    @classmethod
    def tiny(cls, **overrides: object) -> TokTalkConfig:
        """Smallest sensible sizes, for fast unit tests (compile time dominates)."""
        base = cls(
            width=16,
            num_mid_blocks=1,
            transformer_blocks=1,
            num_heads=2,
            head_dim=8,
            mlp_ratio=2.0,
            time_frequency_dim=16,
            time_embed_dim=16,
            num_groups=4,
            style_dim=8,
            style_hidden=16,
            style_heads=2,
            style_frames=20,
            style_min_frames=8,
            adapter_width=16,
            adapter_layers=1,
            adapter_heads=2,
            chunk_frames=4,
            overlap_frames=2,
            context_frames=8,
            sample_steps=3,
        )
        return dataclasses.replace(base, **overrides)

    # ------------------------------------------------------------------------------- derived
    @property
    def frames_per_token(self) -> float:
        """Motion frames per base token (2 for 12.5 Hz tokens at 25 fps)."""
        return self.fps / self.token_rate

    @property
    def token_alignment(self) -> str:
        """How base tokens map onto motion frames: ``"previous"`` (causal) or ``"linear"`` (offline)."""
        return "previous" if self.causal else "linear"

    @property
    def style_vector_dim(self) -> int:
        """Width of a style vector: the encoder latent, plus the anchor pose with ``style_anchor``."""
        return self.style_dim + (self.param_dim if self.style_anchor else 0)

    @property
    def window_frames(self) -> int:
        """Frames the streaming engine feeds the decoder per chunk: left context + chunk."""
        return self.context_frames + self.chunk_frames
