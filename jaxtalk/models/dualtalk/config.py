"""DualTalk baseline configuration: a frozen (hashable, jit-static) dataclass with ``paper`` and ``small``
presets.

Sizes of the published model (DualTalk's released code): 256-wide features per stream, so a 512-wide
interaction encoder of 3 layers x 4 heads with a 2048-wide ReLU feed-forward, one synthesis decoder
layer, a 2-layer bidirectional LSTM of 128 units per direction, dropout 0.1 inside the transformer
layers and 0.5 on the interaction features, 1024-d wav2vec 2.0 large speech features, 200-frame
(8-s) training clips.
"""

from __future__ import annotations

import dataclasses
import math

from jaxtalk.types import MOTION_FPS, PARAM_DIM, check_compute_dtype

__all__ = ["DualTalkConfig"]


@dataclasses.dataclass(frozen=True)
class DualTalkConfig:
    """Static settings of the DualTalk baseline (any change recompiles).

    Attributes:
        width: interaction-encoder width; each input stream is projected to ``width // 2`` (DualTalk's
            ``feature_dim``) and the agent's speech and the partner branch are concatenated.
        num_layers: interaction-encoder blocks (full bidirectional self-attention over the window).
        num_heads: attention heads of every attention layer (``width // 2`` must be divisible by it).
        mlp_ratio: feed-forward width / block width.
        decoder_layers: synthesis decoder blocks (self-attention + attention to the encoder output).
        lstm_layers: bidirectional LSTM layers of the partner branch (``width // 4`` units per
            direction).
        speech_dim: width of the per-frame speech feature fed to each speaker's learnable projection
            (80 for jaxtalk's log-mel front end, 1024 for wav2vec 2.0 large).
        param_dim: head-motion vector width (56 = exp 50 | jaw 3 | neck 3).
        frames_per_turn: motion frames per turn (1 s at 25 fps): windows are whole turns, as TIMAR's.
        max_turns: the longest window in turns: the training window (8 turns = DualTalk's 200-frame
            clips); longer windows are refused, the model never saw them.
        dropout: dropout inside the transformer blocks (residual branches, feed-forward).
        feature_dropout: dropout on the interaction encoder's output, before the synthesis decoder.
        velocity_weight: weight of the frame-to-frame velocity MSE next to the per-group MSE.
    """

    width: int = 128
    num_layers: int = 4
    num_heads: int = 4
    mlp_ratio: float = 4.0
    decoder_layers: int = 1
    lstm_layers: int = 2
    speech_dim: int = 80
    param_dim: int = PARAM_DIM
    frames_per_turn: int = MOTION_FPS
    max_turns: int = 8
    dropout: float = 0.0
    feature_dropout: float = 0.0
    velocity_weight: float = 1.0
    compute_dtype: str = "float32"

    def __post_init__(self) -> None:
        check_compute_dtype(self.compute_dtype, "DualTalkConfig")
        positive = ("width", "num_layers", "num_heads", "decoder_layers", "lstm_layers", "speech_dim", "param_dim",
                    "frames_per_turn", "max_turns")
        for name in positive:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"DualTalkConfig.{name} must be a positive integer, got {value!r}")
        if self.width % 4:
            raise ValueError(f"DualTalkConfig.width must be a multiple of 4 (two streams of width // 2, LSTM "
                             f"directions of width // 4), got {self.width}")
        if self.feature_width % self.num_heads:
            raise ValueError(f"DualTalkConfig.width // 2 = {self.feature_width} (the per-stream width) is not "
                             f"divisible by num_heads {self.num_heads}")
        if self.param_dim != PARAM_DIM:
            raise ValueError(f"DualTalkConfig.param_dim must be {PARAM_DIM} (exp 50 | jaw 3 | neck 3), got {self.param_dim}")
        if not (self.mlp_ratio > 0 and math.isfinite(self.mlp_ratio)):
            raise ValueError(f"DualTalkConfig.mlp_ratio must be positive, got {self.mlp_ratio}")
        for name in ("dropout", "feature_dropout"):
            if not 0.0 <= getattr(self, name) < 1.0:
                raise ValueError(f"DualTalkConfig.{name} must lie in [0, 1), got {getattr(self, name)}")
        if not (self.velocity_weight >= 0 and math.isfinite(self.velocity_weight)):
            raise ValueError(f"DualTalkConfig.velocity_weight must be >= 0, got {self.velocity_weight}")

    @property
    def feature_width(self) -> int:
        """Width of each projected input stream (DualTalk's ``feature_dim``)."""
        return self.width // 2

    @classmethod
    def paper(cls, **overrides) -> DualTalkConfig:
        """The published sizes: 512-wide interaction encoder (2 x 256-wide streams) of 3 layers x 4 heads,
        2048-wide feed-forward, one decoder layer, a 2-layer BiLSTM, dropout 0.1 / 0.5, on 1024-d
        wav2vec 2.0 large features. Its optimiser is TIMAR's paper setting (TIMAR retrains DualTalk
        under its own training configuration): :data:`jaxtalk.models.dualtalk.recipe.PRESET_DEFAULTS`.

        Args:
            **overrides: any field to change.

        Returns:
            The config.
        """
        base = dict(width=512, num_layers=3, num_heads=4, mlp_ratio=4.0, decoder_layers=1, lstm_layers=2,
                    speech_dim=1024, dropout=0.1, feature_dropout=0.5)
        return cls(**(base | overrides))

    @classmethod
    def small(cls, **overrides) -> DualTalkConfig:
        """A CPU-sized model on jaxtalk's 80-band log-mel features, in the budget of
        :meth:`jaxtalk.models.timar.TimarConfig.small`: 128 wide (2 x 64-wide streams), 4 layers x 4
        heads, one decoder layer, a 2-layer BiLSTM, and, as TIMAR's small preset, no dropout.

        Args:
            **overrides: any field to change.

        Returns:
            The config.
        """
        base = dict(width=128, num_layers=4, num_heads=4, decoder_layers=1, lstm_layers=2, speech_dim=80,
                    dropout=0.0, feature_dropout=0.0)
        return cls(**(base | overrides))
