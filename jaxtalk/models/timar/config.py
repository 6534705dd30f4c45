"""TIMAR configuration: a frozen (hashable, jit-static) dataclass with ``paper`` and ``small`` presets.

Numbers from the paper (``shared/papers/timar.txt``, Sec. 4 and Appendix 7): shared token width
``d_t = 1024``, a 16-layer x 16-head encoder, a diffusion head of K = 3 adaLN residual blocks of width
``d_m = 1024``, 1-s turns at 25 fps, 8 turns per training clip, mask ratio r = 0.7 (the public code
draws it from a truncated normal on [0.7, 1.0], mean 1.0, std 0.25, as MAR does), ``p_cfg = 0.1``,
1000 cosine diffusion steps, x0-prediction, 5 sampling steps in the evaluation. The CFG scale of the
evaluation is not given in the text: jaxtalk's default (1.5) is a config field.
"""

from __future__ import annotations

import dataclasses
import math

# The diffusion loss is computed per group of the 56-d head vector and summed (Appendix 7.2); the
# groups are shared with the DualTalk baseline and re-exported as part of TIMAR's config API.
from jaxtalk.metrics.params import LOSS_GROUPS
from jaxtalk.types import MOTION_FPS, PARAM_DIM, check_compute_dtype

__all__ = ["TimarConfig", "NUM_SEPARATORS", "NUM_SPANS", "LOSS_GROUPS", "SAMPLERS", "ARCHITECTURES"]

# "ddpm": ancestral steps (MAR's sampler; with a learned variance and the temperature on every step's
# noise); "ddim": deterministic DDIM from x_T; "mean": the guided posterior mean (no denoising loop).
SAMPLERS = ("ddpm", "ddim", "mean")
# "encoder": TIMAR's encoder-only backbone; "encoder_decoder": the MAE-style asymmetric variant of
# Table 2 (MAR's default layout: the encoder sees the visible tokens only, a decoder fills in the masks).
ARCHITECTURES = ("encoder", "encoder_decoder")

# Turn open/close plus an open/close pair around each of the four modality spans.
NUM_SEPARATORS = 10
NUM_SPANS = 4



@dataclasses.dataclass(frozen=True)
class TimarConfig:
    """Static TIMAR settings (any change recompiles).

    Attributes:
        width: shared token width d_t (= encoder width d_e).
        num_layers: encoder blocks.
        architecture: ``"encoder"`` (TIMAR: one encoder over all tokens, masked agent frames enter
            it as the mask token) or ``"encoder_decoder"`` (Table 2's MAE-style variant, MAR's
            default layout: the encoder attends to the visible tokens only; a decoder of
            ``decoder_layers`` blocks takes the encoder's outputs at the visible positions, a
            learned mask token at every masked agent frame and its own positional table, and its
            outputs condition the diffusion head). One of :data:`ARCHITECTURES`.
        decoder_layers: decoder blocks of the ``"encoder_decoder"`` variant (ignored by
            ``"encoder"``; same width, heads and attention mask as the encoder). Default 2 (``small``)
            and 8 (``paper``): half of the preset's encoder depth, an asymmetric (lighter) decoder
            as MAE's, between MAE's 1/3 and MAR's equal depths.
        num_heads: attention heads (``width`` must be divisible by it).
        mlp_ratio: encoder feed-forward width / ``width``.
        speech_dim: width of the per-frame speech feature fed to the learnable projection (80 for
            jaxtalk's log-mel front end, 1024 for wav2vec 2.0 large).
        param_dim: head-motion vector width (56 = exp 50 | jaw 3 | neck 3).
        frames_per_turn: motion frames per turn (1 s at 25 fps).
        max_turns: turns in the positional table: the longest window (context n + current turn).
        head: ``"diffusion"`` (the paper) or ``"mlp"`` (the Table 2 ablation: direct regression).
        head_width: diffusion-head width d_m.
        head_blocks: adaLN residual blocks K.
        attention: ``"turn_causal"`` (TLCA) or ``"bidirectional"`` (the Table 2 ablation).
        num_timesteps: diffusion training steps.
        schedule: ``"cosine"`` or ``"linear"`` beta table.
        learn_sigma: the head also predicts the variance interpolation (improved diffusion's
            learned range, trained with the variational bound as MAR/TIMAR do).
        vlb_weight: weight of the variational-bound term when ``learn_sigma``.
        diffusion_batch_mul: (timestep, noise) draws per masked frame in the loss, all sharing the
            frame's ONE encoder feature (MAR's public code: 4). The encoder only learns through the
            head's high-noise draws (at low noise the noisy frame alone gives x0 away), so more
            draws give it a less noisy gradient; they are cheap when the head is small next to the
            encoder (the paper's sizes). Default 1: on a 64-wide CPU model 4 draws made a step 1.5x
            slower and reached the same held-out loss at equal steps.
        mask_ratio_min: lower end of the truncated normal of the mask ratio (upper end 1); 1.0
            masks every agent frame (the ``small`` preset: training then matches inference).
        mask_ratio_std: its standard deviation (mean 1.0).
        cfg_dropout: probability that an example's user tokens are all replaced by the fake token.
        sample_steps: default respaced sampling steps.
        sampler: default sampler, one of :data:`SAMPLERS` (``paper``: ``"ddpm"`` as MAR samples,
            reading the learned variance; ``small``: ``"ddim"``).
        cfg_scale: default guidance scale omega (paper's convention: 0 = unconditional,
            1 = conditional, > 1 = guided).
        dropout: dropout in the encoder (residual branches and attention).
    """

    width: int = 128
    num_layers: int = 4
    architecture: str = "encoder"
    decoder_layers: int = 2
    num_heads: int = 4
    mlp_ratio: float = 4.0
    speech_dim: int = 80
    param_dim: int = PARAM_DIM
    frames_per_turn: int = MOTION_FPS
    max_turns: int = 8
    head: str = "diffusion"
    head_width: int = 128
    head_blocks: int = 3
    attention: str = "turn_causal"
    num_timesteps: int = 1000
    schedule: str = "cosine"
    learn_sigma: bool = False
    vlb_weight: float = 1.0
    diffusion_batch_mul: int = 1
    mask_ratio_min: float = 0.7
    mask_ratio_std: float = 0.25
    cfg_dropout: float = 0.1
    sample_steps: int = 5
    sampler: str = "ddim"
    cfg_scale: float = 1.5
    dropout: float = 0.0
    compute_dtype: str = "float32"

    def __post_init__(self) -> None:
        check_compute_dtype(self.compute_dtype, "TimarConfig")
        positive = ("width", "num_layers", "num_heads", "speech_dim", "param_dim", "frames_per_turn",
                    "max_turns", "head_width", "head_blocks", "num_timesteps", "sample_steps", "diffusion_batch_mul",
                    "decoder_layers")
        for name in positive:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"TimarConfig.{name} must be a positive integer, got {value!r}")
        if self.width % self.num_heads:
            raise ValueError(f"TimarConfig.width {self.width} is not divisible by num_heads {self.num_heads}")
        if self.param_dim != PARAM_DIM:
            raise ValueError(f"TimarConfig.param_dim must be {PARAM_DIM} (exp 50 | jaw 3 | neck 3), got {self.param_dim}")
        if self.architecture not in ARCHITECTURES:
            raise ValueError(f"TimarConfig.architecture must be one of {ARCHITECTURES}, got {self.architecture!r}")
        if self.head not in ("diffusion", "mlp"):
            raise ValueError(f"TimarConfig.head must be 'diffusion' or 'mlp', got {self.head!r}")
        if self.attention not in ("turn_causal", "bidirectional"):
            raise ValueError(f"TimarConfig.attention must be 'turn_causal' or 'bidirectional', got {self.attention!r}")
        if self.schedule not in ("cosine", "linear"):
            raise ValueError(f"TimarConfig.schedule must be 'cosine' or 'linear', got {self.schedule!r}")
        if not 0.0 <= self.mask_ratio_min <= 1.0:
            raise ValueError(f"TimarConfig.mask_ratio_min must lie in [0, 1], got {self.mask_ratio_min}")
        if not (self.mask_ratio_std > 0 and math.isfinite(self.mask_ratio_std)):
            raise ValueError(f"TimarConfig.mask_ratio_std must be positive, got {self.mask_ratio_std}")
        if not 0.0 <= self.cfg_dropout < 1.0:
            raise ValueError(f"TimarConfig.cfg_dropout must lie in [0, 1), got {self.cfg_dropout}")
        if self.sample_steps > self.num_timesteps:
            raise ValueError(f"TimarConfig.sample_steps {self.sample_steps} exceeds num_timesteps {self.num_timesteps}")
        if self.sampler not in SAMPLERS:
            raise ValueError(f"TimarConfig.sampler must be one of {SAMPLERS}, got {self.sampler!r}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"TimarConfig.dropout must lie in [0, 1), got {self.dropout}")

    @property
    def tokens_per_turn(self) -> int:
        """4 spans of ``frames_per_turn`` tokens plus the 10 separators (110 at 25 fps)."""
        return NUM_SPANS * self.frames_per_turn + NUM_SEPARATORS

    @property
    def head_out_dim(self) -> int:
        """Diffusion-head output width: the x0 estimate, plus the variance channels if learned."""
        return 2 * self.param_dim if self.learn_sigma else self.param_dim

    @classmethod
    def paper(cls, **overrides) -> TimarConfig:
        """The paper's sizes and training: 1024 wide, 16 layers, 16 heads, head K = 3 x 1024, wav2vec 2.0
        features, mask ratio from TN[0.7, 1], a learned variance, 4 diffusion draws per frame (MAR's
        ``diffusion_batch_mul``) and MAR's ancestral DDPM sampler. Its optimiser (AdamW 1e-4, batch
        32, 100 warm-up steps) is :data:`jaxtalk.models.timar.recipe.PRESET_DEFAULTS` ``["paper"]``.

        Args:
            **overrides: any field to change.

        Returns:
            The config.
        """
        base = dict(width=1024, num_layers=16, num_heads=16, speech_dim=1024, head_width=1024,
                    head_blocks=3, learn_sigma=True, diffusion_batch_mul=4, sampler="ddpm", decoder_layers=8)
        return cls(**(base | overrides))

    @classmethod
    def small(cls, **overrides) -> TimarConfig:
        """A CPU-sized model (trains in minutes on 2 cores) on jaxtalk's 80-band log-mel features,
        trained with every agent frame masked.

        How it differs from ``paper`` and why (each measured at CPU scale): 128 wide x 4 layers and a
        128-wide head (minutes per run instead of GPU-days); every agent frame masked (below); one
        diffusion draw per frame (4 made a step 1.5x slower for the same held-out loss at equal steps,
        see ``diffusion_batch_mul``); a fixed variance and deterministic DDIM, the sampler that
        needs no learned variance; and AdamW at 1e-3 at batch 16 with 20 warm-up steps, decaying to a
        tenth (``PRESET_DEFAULTS["small"]``), for runs of a few thousand steps rather than the
        paper's 400 epochs at 1e-4.

        Args:
            **overrides: any field to change.

        Returns:
            The config.
        """
        # Every agent frame masked in training (mask_ratio_min = 1), as at inference: with the paper's
        # r ~ TN[0.7, 1] a CPU-sized run learns to interpolate the 10-30% visible agent frames, which
        # never exist when streaming, instead of reading the audio.
        base = dict(width=128, num_layers=4, num_heads=4, speech_dim=80, head_width=128, head_blocks=3,
                    mask_ratio_min=1.0)
        return cls(**(base | overrides))
