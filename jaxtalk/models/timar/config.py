"""TIMAR configuration: a frozen (hashable, jit-static) dataclass with ``paper`` and ``small`` presets.

Numbers from the paper (``shared/papers/timar.txt``, Sec. 4 and Appendix 7): shared token width
``d_t = 1024``, a 16-layer x 16-head encoder, a diffusion head of K = 3 adaLN residual blocks of width
``d_m = 1024``, 1-s turns at 25 fps, 8 turns per training clip, mask ratio r = 0.7 (the public code
draws it from a truncated normal on [0.7, 1.0], mean 1.0, std 0.25, as MAR does), ``p_cfg = 0.1``,
1000 cosine diffusion steps, x0-prediction, 5 sampling steps in the evaluation. The CFG scale of the
evaluation is not given in the text: jaxtalk's default, omega = 1.5 (``cfg_scale = 0.5``: jaxtalk's
guidance weight is omega - 1), is a config field.
"""

from __future__ import annotations

import dataclasses
import math

# The diffusion loss is computed per group of the 56-d head vector and summed (Appendix 7.2); the
# groups are shared with the DualTalk baseline and re-exported as part of TIMAR's config API.
from jaxtalk.metrics.params import LOSS_GROUPS
from jaxtalk.types import MOTION_FPS, PARAM_DIM, check_compute_dtype

__all__ = ["TimarConfig", "NUM_SEPARATORS", "NUM_SPANS", "LOSS_GROUPS", "SAMPLERS", "ARCHITECTURES", "GUIDANCE_DROPS"]

# "ddpm": ancestral steps (MAR's sampler; with a learned variance and the temperature on every step's
# noise); "ddim": deterministic DDIM from x_T; "mean": the guided posterior mean (no denoising loop).
SAMPLERS = ("ddpm", "ddim", "mean")
# "encoder": TIMAR's encoder-only backbone; "encoder_decoder": the MAE-style asymmetric variant of
# Table 2 (MAR's default layout: the encoder sees the visible tokens only, a decoder fills in the masks).
ARCHITECTURES = ("encoder", "encoder_decoder")

# What the unconditional (CFG) branch replaces by the fake token: "window": the user tokens of every
# turn of the window (jaxtalk's default; training drops a whole example's user tokens the same way);
# "current_turn": only the current turn's user tokens, earlier turns keep the real ones (the public
# code's ``TIMAR.sample``).
GUIDANCE_DROPS = ("window", "current_turn")

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
            encoder (the paper's sizes). Default 1: at CPU sizes more draws cost time per step for no
            lower held-out loss; see docs/design-decisions.md.
        mask_ratio_min: lower end of the truncated normal of the mask ratio (upper end 1); 1.0
            masks every agent frame (the ``small`` preset: training then matches inference).
        mask_ratio_std: its standard deviation (mean 1.0).
        cfg_dropout: probability that an example's user tokens are all replaced by the fake token.
        sample_steps: default respaced sampling steps.
        sampler: default sampler, one of :data:`SAMPLERS` (``paper``: ``"ddpm"`` as MAR samples,
            reading the learned variance; ``small``: ``"ddim"``).
        cfg_scale: default guidance weight w of :func:`jaxtalk.samplers.flow.guided_apply` (0 = no
            guidance, -1 = unconditional); the paper's omega is ``1 + w``, so its 1.5 is 0.5.
        dropout: dropout in the encoder (residual branches and attention).
        token_width: width of the token embeddings (speech projection, motion encoder, separators,
            mask-free tokens and the fake token) when ``input_projection`` is set; None = ``width``.
        input_projection: a learned ``Dense(token_width -> width)`` on every token before the
            positional embedding (the public code's ``z_proj``); the mask token then lives in the
            encoder width and replaces the PROJECTED agent-motion tokens, as there. False: tokens are
            embedded directly at ``width`` (jaxtalk's default).
        norm_after_position: ``LayerNorm(x + P1)`` at the encoder input (the public code's
            ``z_proj_ln`` after the positional table) instead of jaxtalk's ``LayerNorm(x) + P1``.
        motion_encoder_final_relu: the motion encoder ends with a ReLU (the public code's
            Linear-ReLU-Linear-ReLU) instead of jaxtalk's Linear-ReLU-Linear.
        block_norm_epsilon: epsilon of the LayerNorms inside the transformer blocks (1e-5,
            PyTorch's default; the public ``timar_*`` models build their timm blocks with 1e-6).
            The encoder's input/output norms always use 1e-6.
        guidance_drop: what the unconditional CFG branch replaces by the fake token, one of
            :data:`GUIDANCE_DROPS`.
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
    cfg_scale: float = 0.5
    dropout: float = 0.0
    token_width: int | None = None
    input_projection: bool = False
    norm_after_position: bool = False
    motion_encoder_final_relu: bool = False
    block_norm_epsilon: float = 1e-5
    guidance_drop: str = "window"
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
        if self.token_width is not None:
            if isinstance(self.token_width, bool) or not isinstance(self.token_width, int) or self.token_width < 1:
                raise ValueError(f"TimarConfig.token_width must be a positive integer or None, got {self.token_width!r}")
            if not self.input_projection and self.token_width != self.width:
                raise ValueError(
                    f"TimarConfig.token_width {self.token_width} differs from width {self.width}: "
                    "that needs input_projection=True"
                )
        if not (self.block_norm_epsilon > 0 and math.isfinite(self.block_norm_epsilon)):
            raise ValueError(f"TimarConfig.block_norm_epsilon must be positive, got {self.block_norm_epsilon}")
        if self.guidance_drop not in GUIDANCE_DROPS:
            raise ValueError(f"TimarConfig.guidance_drop must be one of {GUIDANCE_DROPS}, got {self.guidance_drop!r}")

    @property
    def embed_width(self) -> int:
        """Width of the token embeddings before the optional input projection."""
        return self.width if self.token_width is None else self.token_width

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
        ``diffusion_batch_mul``) and MAR's ancestral DDPM sampler.

        This is the model the paper's TEXT describes (a 16-layer encoder), in jaxtalk's layout. The
        released checkpoint (``timar_large`` with ``--use_encoder_only``) stacks
        ``encoder_depth + decoder_depth`` = 32 blocks and uses the public code's layout: that model
        is :meth:`reference` (``num_layers=32``), which ``jaxtalk convert timar`` builds.

        Its optimiser (AdamW 1e-4, batch 32, 100 warm-up steps) is
        :data:`jaxtalk.models.timar.recipe.PRESET_DEFAULTS` ``["paper"]``.

        Args:
            **overrides: any field to change.

        Returns:
            The config.
        """
        base = dict(width=1024, num_layers=16, num_heads=16, speech_dim=1024, head_width=1024,
                    head_blocks=3, learn_sigma=True, diffusion_batch_mul=4, sampler="ddpm", decoder_layers=8)
        return cls(**(base | overrides))

    @classmethod
    def reference(cls, **overrides) -> TimarConfig:
        """The layout of the public code (``CoderChen01/towards-seamless-interaction``) at the released
        checkpoint's sizes: ``timar_large`` with ``--use_encoder_only --use_causal_attn --diffloss_d 3
        --diffloss_w 1024``, i.e. 32 timm ViT blocks (16 encoder + 16 decoder depth, stacked) of
        width 1024 and 16 heads with LayerNorm eps 1e-6, 1024-wide tokens projected by ``z_proj``
        and normalised after the positional table, a Linear-ReLU-Linear-ReLU motion encoder, a
        K = 3 x 1024 head with a learned variance on the 1000-step cosine schedule, x0-prediction,
        5 ancestral sampling steps, and a CFG branch that drops the current turn's user tokens only.
        The public evaluation samples with ``--cfg 1.0`` (no guidance: ``cfg_scale = 0`` here) and
        temperature 1.

        Args:
            **overrides: any field to change (the converter sets every size from the checkpoint).

        Returns:
            The config.
        """
        base = dict(width=1024, num_layers=32, num_heads=16, speech_dim=1024, head_width=1024, head_blocks=3,
                    learn_sigma=True, diffusion_batch_mul=4, sampler="ddpm", decoder_layers=16, token_width=1024,
                    input_projection=True, norm_after_position=True, motion_encoder_final_relu=True,
                    block_norm_epsilon=1e-6, guidance_drop="current_turn", cfg_scale=0.0, dropout=0.1,
                    schedule="cosine", sample_steps=5)
        return cls(**(base | overrides))

    @classmethod
    def small(cls, **overrides) -> TimarConfig:
        """A CPU-sized model (trains in minutes on 2 cores) on jaxtalk's 80-band log-mel features,
        trained with every agent frame masked.

        How it differs from ``paper`` and why (the measurements: docs/design-decisions.md): 128 wide x
        4 layers and a 128-wide head (minutes per run instead of GPU-days); every agent frame masked
        (below); one diffusion draw per frame (see ``diffusion_batch_mul``); a fixed variance and
        deterministic DDIM, the sampler that needs no learned variance; and AdamW at 1e-3 at batch 16
        with 20 warm-up steps, decaying to a tenth (``PRESET_DEFAULTS["small"]``), for runs of a few
        thousand steps rather than the paper's 400 epochs at 1e-4.

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
