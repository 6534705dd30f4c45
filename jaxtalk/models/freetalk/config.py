"""FreeTalk configurations: frozen dataclasses for ATS (landmark diffusion) and STM (sparse-to-mesh).

Everything here is static: it sets shapes, loop lengths or the compiled program. Numeric knobs swept
at fixed shapes (DDIM eta, emotion intensity) are traced arguments of the sampling functions.
Sizes of the ``paper`` presets come from the FreeTalk supplement (``papers/NOTES.md``); the band
radius, which the paper does not give, defaults to 2 frames there.
"""

from __future__ import annotations

import dataclasses
import math

from jaxtalk.geometry.diffusionnet import DiffusionNetConfig
from jaxtalk.models.freetalk.emotions import EMOTIONS, parse_vocabulary
from jaxtalk.types import NUM_LANDMARKS, check_compute_dtype

__all__ = ["ATSConfig", "STMConfig", "FUSIONS", "DECODERS"]

# STM feature-combination variants of the supplement's ablation (Table 2), full model last.
FUSIONS: tuple[str, ...] = ("concat", "ca", "ca_concat", "gcn_ca_concat")
# STM decoders: the paper's DiffusionNet, and the supplement's substitution, a per-vertex MLP that
# sees no mesh operator (each vertex decoded from its own fused features alone).
DECODERS: tuple[str, ...] = ("diffusionnet", "mlp")


def _positive_ints(owner: object, names: tuple[str, ...]) -> None:
    for name in names:
        value = getattr(owner, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{type(owner).__name__}.{name} must be a positive integer, got {value!r}")


def _positive_float(owner: object, name: str) -> None:
    value = getattr(owner, name)
    if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
        raise ValueError(f"{type(owner).__name__}.{name} must be a finite positive number, got {value!r}")


@dataclasses.dataclass(frozen=True)
class ATSConfig:
    """Static settings of the Audio-To-Sparse landmark diffusion transformer.

    Attributes:
        num_landmarks: N (68); the motion width is ``3 N``.
        speech_dim: width of the per-frame audio features (HuBERT-base 768 in the paper preset;
            jaxtalk's log-mel stack 320 in the small one).
        audio_frames_per_frame: audio feature frames per motion frame (1.0 once resampled to the
            motion rate, as in the paper; 2.0 for raw 50 Hz HuBERT against 25 fps).
        width: model width d (paper 512).
        num_layers: decoder layers (paper 6).
        num_heads: attention heads (paper 8); ``width`` must be divisible by it.
        ff_dim: feed-forward width (paper 2048).
        max_frames: longest motion sequence (size of the learned target positional table).
        band_radius: cross-attention band half-width r in motion frames (paper: not given; 2).
        num_intensities: intensity levels (MEAD 3); intensity is accepted in ``[1, num_intensities]``.
        emotions: the emotion vocabulary, neutral first (default EmoVOCA's 11 + neutral; MEAD's 8 is
            ``emotions.MEAD_EMOTIONS``, ``--set emotions=mead``); row e of the emotion table.
        time_frequency_dim: sinusoidal features of the diffusion step.
        num_timesteps: DDPM training steps (1000, linear betas 1e-4 .. 0.02).
        sample_steps: default DDIM steps at inference (100).
        displacement_scale: the model sees ``scale * displacement``. The training recipe feeds
            standardised displacements (unit variance per coordinate, what the unit-variance noise
            schedule assumes), so every preset uses 1; 100 (metres -> centimetres) suits raw
            displacements in metres.
        velocity_weight, acceleration_weight: loss weights (0.3, 0.1).
        dropout: dropout in the decoder blocks (training only).
    """

    num_landmarks: int = NUM_LANDMARKS
    speech_dim: int = 320
    audio_frames_per_frame: float = 1.0
    width: int = 512
    num_layers: int = 6
    num_heads: int = 8
    ff_dim: int = 2048
    max_frames: int = 600
    band_radius: int = 2
    num_intensities: int = 3
    # Given as a tuple, a list (run.json) or a name / comma-separated string (--set); stored as a tuple.
    emotions: tuple[str, ...] | list[str] | str = EMOTIONS
    time_frequency_dim: int = 256
    num_timesteps: int = 1000
    sample_steps: int = 100
    displacement_scale: float = 1.0
    velocity_weight: float = 0.3
    acceleration_weight: float = 0.1
    dropout: float = 0.0
    compute_dtype: str = "float32"

    def __post_init__(self) -> None:
        check_compute_dtype(self.compute_dtype, "ATSConfig")
        _positive_ints(self, ("num_landmarks", "speech_dim", "width", "num_layers", "num_heads", "ff_dim",
                              "max_frames", "num_intensities", "time_frequency_dim",
                              "num_timesteps", "sample_steps"))
        _positive_float(self, "audio_frames_per_frame")
        _positive_float(self, "displacement_scale")
        # A list (from run.json) or a name / comma-separated string (from --set) becomes the tuple.
        object.__setattr__(self, "emotions", parse_vocabulary(self.emotions))
        if self.width % self.num_heads:
            raise ValueError(f"ATSConfig.width={self.width} must be divisible by num_heads={self.num_heads}")
        if isinstance(self.band_radius, bool) or not isinstance(self.band_radius, int) or self.band_radius < 0:
            raise ValueError(f"ATSConfig.band_radius must be an integer >= 0, got {self.band_radius!r}")
        if self.sample_steps > self.num_timesteps:
            raise ValueError(
                f"ATSConfig.sample_steps={self.sample_steps} exceeds num_timesteps={self.num_timesteps}"
            )
        for name in ("velocity_weight", "acceleration_weight", "dropout"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"ATSConfig.{name} must be finite and >= 0, got {value!r}")

    @property
    def num_emotions(self) -> int:
        """Rows of the emotion table (the vocabulary's size)."""
        return len(self.emotions)

    @property
    def motion_dim(self) -> int:
        """D = 3 N, the per-frame width of the landmark displacement sequence."""
        return 3 * self.num_landmarks

    @property
    def head_dim(self) -> int:
        return self.width // self.num_heads

    @property
    def max_audio_frames(self) -> int:
        """Size of the learned memory positional table."""
        return int(math.ceil(self.max_frames * self.audio_frames_per_frame))

    @classmethod
    def paper(cls, **overrides) -> ATSConfig:
        """The supplement's sizes: d 512, 6 layers, 8 heads, FF 2048, 1000 steps, 100 DDIM steps, on
        768-d HuBERT-base features at the motion rate (``prepare --features hubert:PATH``)."""
        return cls(**{"speech_dim": 768, **overrides})

    @classmethod
    def small(cls, **overrides) -> ATSConfig:
        """CPU-sized model (trains in minutes on 2 cores): d 128, 3 layers, 4 heads, FF 256, on the
        320-d log-mel stack."""
        kwargs = dict(width=128, num_layers=3, num_heads=4, ff_dim=256, max_frames=300)
        return cls(**{**kwargs, **overrides})


@dataclasses.dataclass(frozen=True)
class STMConfig:
    """Static settings of the Sparse-To-Mesh module.

    Attributes:
        num_landmarks: N (68).
        mesh_feature_dim: d, width of the static mesh features f_i (paper latent 128).
        encoder_width, encoder_blocks: DiffusionNet encoder size (paper width 128; 4 blocks as the
            reference).
        decoder_width, decoder_blocks: DiffusionNet decoder size.
        gcn_layers, gcn_hidden: landmark GCN (paper 3 x 128).
        index_encoding_dim: width of the sinusoidal landmark-index encoding p_j.
        attention_dim: d_c, cross-attention model width (paper 128).
        attention_heads: cross-attention heads (paper 4).
        fusion: feature combination (one of :data:`FUSIONS`; the paper's is ``"gcn_ca_concat"``).
        decoder: ``"diffusionnet"`` (the paper's) or ``"mlp"``: the supplement's substitution, a
            per-vertex MLP of the same width and depth (``decoder_blocks`` x 2 hidden layers) that
            decodes every vertex from its own fused features, with no spatial diffusion.
        position_scale: mesh coordinates are multiplied by this before the operators and the encoder
            (metres -> decimetres puts a face in about [-1, 1]).
        displacement_scale: landmark and vertex displacements are multiplied by this inside the model
            (metres -> centimetres).
        num_eigenpairs: k of the Laplacian eigenbasis used by both DiffusionNets.
        velocity_weight, acceleration_weight: loss weights (0.5, 0.2).
    """

    num_landmarks: int = NUM_LANDMARKS
    mesh_feature_dim: int = 128
    encoder_width: int = 128
    encoder_blocks: int = 4
    decoder_width: int = 128
    decoder_blocks: int = 4
    gcn_layers: int = 3
    gcn_hidden: int = 128
    index_encoding_dim: int = 32
    attention_dim: int = 128
    attention_heads: int = 4
    fusion: str = "gcn_ca_concat"
    decoder: str = "diffusionnet"
    position_scale: float = 10.0
    displacement_scale: float = 100.0
    num_eigenpairs: int = 128
    velocity_weight: float = 0.5
    acceleration_weight: float = 0.2
    compute_dtype: str = "float32"

    def __post_init__(self) -> None:
        check_compute_dtype(self.compute_dtype, "STMConfig")
        _positive_ints(self, ("num_landmarks", "mesh_feature_dim", "encoder_width", "encoder_blocks",
                              "decoder_width", "decoder_blocks", "gcn_layers", "gcn_hidden",
                              "attention_dim", "attention_heads", "num_eigenpairs"))
        if isinstance(self.index_encoding_dim, bool) or not isinstance(self.index_encoding_dim, int) \
                or self.index_encoding_dim < 2:
            raise ValueError(f"STMConfig.index_encoding_dim must be an integer >= 2, got {self.index_encoding_dim!r}")
        if self.attention_dim % self.attention_heads:
            raise ValueError(
                f"STMConfig.attention_dim={self.attention_dim} must be divisible by "
                f"attention_heads={self.attention_heads}"
            )
        if self.fusion not in FUSIONS:
            raise ValueError(f"STMConfig.fusion must be one of {FUSIONS}, got {self.fusion!r}")
        if self.decoder not in DECODERS:
            raise ValueError(f"STMConfig.decoder must be one of {DECODERS}, got {self.decoder!r}")
        _positive_float(self, "position_scale")
        _positive_float(self, "displacement_scale")
        for name in ("velocity_weight", "acceleration_weight"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"STMConfig.{name} must be finite and >= 0, got {value!r}")

    @property
    def motion_dim(self) -> int:
        return 3 * self.num_landmarks

    @property
    def uses_global(self) -> bool:
        """Whether the global displacement vector g_t is concatenated to every vertex."""
        return self.fusion in ("concat", "ca_concat", "gcn_ca_concat")

    @property
    def uses_attention(self) -> bool:
        return self.fusion != "concat"

    @property
    def uses_gcn(self) -> bool:
        return self.fusion == "gcn_ca_concat"

    @property
    def fused_dim(self) -> int:
        """Width of ``[f_i | g_t | c_t,i]`` (without the parts the fusion variant drops)."""
        return (self.mesh_feature_dim + (self.motion_dim if self.uses_global else 0)
                + (self.attention_dim if self.uses_attention else 0))

    def encoder_config(self) -> DiffusionNetConfig:
        """DiffusionNet encoder: [xyz | normal] (6) -> f_i (mesh_feature_dim)."""
        w = self.encoder_width
        return DiffusionNetConfig(6, self.mesh_feature_dim, width=w, num_blocks=self.encoder_blocks,
                                  mlp_hidden=(w, w))

    def decoder_config(self) -> DiffusionNetConfig:
        """DiffusionNet decoder: the linearly fused ``[f_i | g_t | c_t,i]`` (decoder_width) -> 3."""
        w = self.decoder_width
        return DiffusionNetConfig(w, 3, width=w, num_blocks=self.decoder_blocks, mlp_hidden=(w, w))

    @classmethod
    def paper(cls, **overrides) -> STMConfig:
        """The supplement's sizes: DiffusionNet width/latent 128, GCN 3 x 128, attention 4 x 128."""
        return cls(**overrides)

    @classmethod
    def small(cls, **overrides) -> STMConfig:
        """CPU-sized model: width 32, 2 blocks each side, GCN 3 x 32, attention 4 heads x 32, k 32."""
        kwargs = dict(mesh_feature_dim=32, encoder_width=32, encoder_blocks=2, decoder_width=32,
                      decoder_blocks=2, gcn_hidden=32, index_encoding_dim=16, attention_dim=32,
                      num_eigenpairs=32)
        return cls(**{**kwargs, **overrides})
