"""Architecture of a wav2vec 2.0 / HuBERT encoder, read from a Hugging Face ``config.json``.

Only the fields that change the inference (and fine-tuning) graph are kept. Missing fields take the
defaults of the ``transformers`` config classes (``Wav2Vec2Config`` / ``HubertConfig``), so that a
``config.json`` written by an old ``transformers`` version, which omits later-added keys, reads the
same way ``transformers`` reads it.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path
from typing import Any

__all__ = ["EncoderConfig", "SUPPORTED_MODEL_TYPES", "ACTIVATIONS"]

SUPPORTED_MODEL_TYPES = ("wav2vec2", "hubert")
# HF activation names (ACT2FN keys) that the port implements; "gelu" is the exact erf form.
ACTIVATIONS = ("gelu", "gelu_new", "gelu_pytorch_tanh", "gelu_fast", "relu", "silu", "swish", "tanh")

# Defaults shared by Wav2Vec2Config and HubertConfig (transformers 4.x and 5.x).
_DEFAULTS: dict[str, Any] = {
    "hidden_size": 768,
    "num_hidden_layers": 12,
    "num_attention_heads": 12,
    "intermediate_size": 3072,
    "hidden_act": "gelu",
    "layer_norm_eps": 1e-5,
    "feat_extract_norm": "group",
    "feat_extract_activation": "gelu",
    "conv_dim": (512, 512, 512, 512, 512, 512, 512),
    "conv_stride": (5, 2, 2, 2, 2, 2, 2),
    "conv_kernel": (10, 3, 3, 3, 3, 2, 2),
    "conv_bias": False,
    "num_conv_pos_embeddings": 128,
    "num_conv_pos_embedding_groups": 16,
    "do_stable_layer_norm": False,
    "hidden_dropout": 0.1,
    "attention_dropout": 0.1,
    "activation_dropout": 0.1,
    "feat_proj_dropout": 0.0,
}


@dataclasses.dataclass(frozen=True)
class EncoderConfig:
    """Static architecture of a wav2vec 2.0 / HuBERT encoder (hashable: usable as a jit static arg).

    Field names and meanings are those of the Hugging Face config classes.

    Attributes:
        model_type: ``"wav2vec2"`` or ``"hubert"``.
        hidden_size: transformer width (768 base, 1024 large).
        num_hidden_layers: transformer layers (12 base, 24 large).
        num_attention_heads: attention heads.
        intermediate_size: feed-forward width.
        hidden_act: feed-forward activation (HF name).
        layer_norm_eps: epsilon of the feature-projection and transformer layer norms.
        feat_extract_norm: ``"group"`` (base: one GroupNorm after the first conv) or ``"layer"``
            (large: a LayerNorm after every conv).
        feat_extract_activation: activation of the conv feature extractor and positional conv.
        conv_dim: output channels of each feature-extractor conv.
        conv_stride: stride of each conv.
        conv_kernel: kernel size of each conv.
        conv_bias: whether the feature-extractor convs have biases.
        num_conv_pos_embeddings: kernel size of the positional conv.
        num_conv_pos_embedding_groups: groups of the positional conv.
        conv_pos_batch_norm: HuBERT variant: BatchNorm before a plain (not weight-normalised)
            positional conv.
        feat_proj_layer_norm: LayerNorm before the feature projection (always on for wav2vec2).
        do_stable_layer_norm: pre-LN transformer with a final LayerNorm (large) instead of post-LN.
        hidden_dropout, attention_dropout, activation_dropout, feat_proj_dropout: dropout rates used
            only when the model runs with ``deterministic=False`` (fine-tuning).
    """

    model_type: str = "wav2vec2"
    hidden_size: int = 768
    num_hidden_layers: int = 12
    num_attention_heads: int = 12
    intermediate_size: int = 3072
    hidden_act: str = "gelu"
    layer_norm_eps: float = 1e-5
    feat_extract_norm: str = "group"
    feat_extract_activation: str = "gelu"
    conv_dim: tuple[int, ...] = (512, 512, 512, 512, 512, 512, 512)
    conv_stride: tuple[int, ...] = (5, 2, 2, 2, 2, 2, 2)
    conv_kernel: tuple[int, ...] = (10, 3, 3, 3, 3, 2, 2)
    conv_bias: bool = False
    num_conv_pos_embeddings: int = 128
    num_conv_pos_embedding_groups: int = 16
    conv_pos_batch_norm: bool = False
    feat_proj_layer_norm: bool = True
    do_stable_layer_norm: bool = False
    hidden_dropout: float = 0.1
    attention_dropout: float = 0.1
    activation_dropout: float = 0.1
    feat_proj_dropout: float = 0.0

    def __post_init__(self):
        if self.model_type not in SUPPORTED_MODEL_TYPES:
            raise ValueError(
                f"unsupported model_type {self.model_type!r}: jaxtalk ports {SUPPORTED_MODEL_TYPES} "
                "(wav2vec2-conformer, wavlm, data2vec-audio, ... have other architectures)"
            )
        for name in ("conv_dim", "conv_stride", "conv_kernel"):
            value = getattr(self, name)
            if not isinstance(value, tuple) or not value or not all(_is_pos_int(v) for v in value):
                raise ValueError(f"{name} must be a non-empty tuple of positive integers, got {value!r}")
        if not len(self.conv_dim) == len(self.conv_stride) == len(self.conv_kernel):
            raise ValueError(
                "conv_dim, conv_stride and conv_kernel must have equal lengths, got "
                f"{len(self.conv_dim)}, {len(self.conv_stride)}, {len(self.conv_kernel)}"
            )
        for name in (
            "hidden_size",
            "num_attention_heads",
            "intermediate_size",
            "num_conv_pos_embeddings",
            "num_conv_pos_embedding_groups",
        ):
            if not _is_pos_int(getattr(self, name)):
                raise ValueError(f"{name} must be a positive integer, got {getattr(self, name)!r}")
        layers = self.num_hidden_layers
        if isinstance(layers, bool) or not isinstance(layers, int) or layers < 0:
            raise ValueError(f"num_hidden_layers must be an integer >= 0, got {layers!r}")
        if self.hidden_size % self.num_attention_heads:
            raise ValueError(
                f"hidden_size {self.hidden_size} is not divisible by num_attention_heads "
                f"{self.num_attention_heads}"
            )
        if self.hidden_size % self.num_conv_pos_embedding_groups:
            raise ValueError(
                f"hidden_size {self.hidden_size} is not divisible by num_conv_pos_embedding_groups "
                f"{self.num_conv_pos_embedding_groups}"
            )
        if self.feat_extract_norm not in ("group", "layer"):
            raise ValueError(f"feat_extract_norm must be 'group' or 'layer', got {self.feat_extract_norm!r}")
        for name in ("hidden_act", "feat_extract_activation"):
            if getattr(self, name) not in ACTIVATIONS:
                raise ValueError(f"{name} {getattr(self, name)!r} is not supported; known: {ACTIVATIONS}")
        for name in ("hidden_dropout", "attention_dropout", "activation_dropout", "feat_proj_dropout"):
            rate = getattr(self, name)
            if not 0.0 <= rate < 1.0:
                raise ValueError(f"{name} must be in [0, 1), got {rate!r}")
        if not (self.layer_norm_eps > 0 and math.isfinite(self.layer_norm_eps)):
            raise ValueError(f"layer_norm_eps must be positive, got {self.layer_norm_eps!r}")

    # -- derived sizes -------------------------------------------------------------------------

    @property
    def hop_length(self) -> int:
        """Samples between consecutive output frames: the product of the conv strides (320)."""
        return math.prod(self.conv_stride)

    @property
    def receptive_field(self) -> int:
        """Samples seen by one output frame (400 for the standard stack); the minimum input length."""
        field = 1
        for kernel, stride in zip(reversed(self.conv_kernel), reversed(self.conv_stride)):
            field = (field - 1) * stride + kernel
        return field

    def num_frames(self, num_samples: int) -> int:
        """Output frames for ``num_samples`` input samples (the conv length formula; 0 when too short)."""
        length = int(num_samples)
        for kernel, stride in zip(self.conv_kernel, self.conv_stride):
            if length < kernel:
                return 0
            length = (length - kernel) // stride + 1
        return length

    def frame_rate(self, sample_rate: int = 16_000) -> float:
        """Output frames per second at ``sample_rate`` (50.0 at 16 kHz)."""
        return sample_rate / self.hop_length

    def truncated(self, num_layers: int) -> EncoderConfig:
        """The same encoder with only its first ``num_layers`` transformer layers (>= 0)."""
        if not isinstance(num_layers, int) or not 0 <= num_layers <= self.num_hidden_layers:
            raise ValueError(f"num_layers must be in [0, {self.num_hidden_layers}], got {num_layers!r}")
        return dataclasses.replace(self, num_hidden_layers=num_layers)

    # -- reading HF configs ----------------------------------------------------------------------

    @classmethod
    def from_hf_dict(cls, hf: dict[str, Any]) -> EncoderConfig:
        """Build from the dict of a Hugging Face ``config.json``.

        Raises:
            ValueError: unknown ``model_type``, features the port does not implement (adapters),
                or inconsistent sizes.
        """
        if not isinstance(hf, dict):
            raise ValueError(f"config must be a JSON object, got {type(hf).__name__}")
        model_type = hf.get("model_type")
        if model_type not in SUPPORTED_MODEL_TYPES:
            raise ValueError(
                f"unsupported model_type {model_type!r} in config (architectures="
                f"{hf.get('architectures')}); jaxtalk ports {SUPPORTED_MODEL_TYPES}"
            )
        if hf.get("add_adapter"):
            raise ValueError("config has add_adapter=True (output adapter); not supported by the port")
        if hf.get("adapter_attn_dim") is not None:
            raise ValueError(
                f"config has adapter_attn_dim={hf['adapter_attn_dim']} (MMS attention adapters); "
                "not supported by the port"
            )
        values = {k: hf.get(k, v) for k, v in _DEFAULTS.items()}
        for name in ("conv_dim", "conv_stride", "conv_kernel"):
            if not isinstance(values[name], (list, tuple)):
                raise ValueError(f"config field {name} must be a list, got {values[name]!r}")
            values[name] = tuple(values[name])
        num_feat = hf.get("num_feat_extract_layers")
        if num_feat is not None and num_feat != len(values["conv_dim"]):
            raise ValueError(
                f"num_feat_extract_layers={num_feat} disagrees with len(conv_dim)={len(values['conv_dim'])}"
            )
        for name in ("hidden_dropout", "attention_dropout", "activation_dropout", "feat_proj_dropout"):
            values[name] = float(values[name])
        values["layer_norm_eps"] = float(values["layer_norm_eps"])
        if model_type == "hubert":
            values["feat_proj_layer_norm"] = bool(hf.get("feat_proj_layer_norm", True))
            values["conv_pos_batch_norm"] = bool(hf.get("conv_pos_batch_norm", False))
        else:  # Wav2Vec2FeatureProjection always normalises; it has no such options
            values["feat_proj_layer_norm"] = True
            values["conv_pos_batch_norm"] = False
        return cls(model_type=model_type, **values)

    @classmethod
    def from_json(cls, path: str | os.PathLike[str]) -> EncoderConfig:
        """Read a Hugging Face ``config.json`` (or the directory holding it).

        Raises:
            FileNotFoundError: no such file.
            ValueError: not valid JSON, or see :meth:`from_hf_dict`.
        """
        path = Path(path)
        if path.is_dir():
            path = path / "config.json"
        if not path.is_file():
            raise FileNotFoundError(f"config file not found: {str(path)!r}")
        try:
            hf = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            raise ValueError(f"{str(path)!r}: not valid JSON ({err})") from err
        try:
            return cls.from_hf_dict(hf)
        except ValueError as err:
            raise ValueError(f"{str(path)!r}: {err}") from err

    def to_hf_dict(self) -> dict[str, Any]:
        """The Hugging Face ``config.json`` dict of this architecture (inverse of ``from_hf_dict``)."""
        out: dict[str, Any] = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        for name in ("conv_dim", "conv_stride", "conv_kernel"):
            out[name] = list(out[name])
        out["num_feat_extract_layers"] = len(self.conv_dim)
        out["architectures"] = ["HubertModel" if self.model_type == "hubert" else "Wav2Vec2Model"]
        if self.model_type == "wav2vec2":  # HuBERT-only options
            del out["feat_proj_layer_norm"], out["conv_pos_batch_norm"]
        return out

    # -- presets ---------------------------------------------------------------------------------

    @classmethod
    def base(cls, model_type: str = "hubert") -> EncoderConfig:
        """Base size (95M): group-norm feature extractor, post-LN, 12 x 768 (FreeTalk's HuBERT-base)."""
        return cls(model_type=model_type)

    @classmethod
    def large(cls, model_type: str = "wav2vec2") -> EncoderConfig:
        """Large size (317M): layer-norm feature extractor, stable layer norm, 24 x 1024 (TIMAR/DualTalk)."""
        return cls(
            model_type=model_type,
            hidden_size=1024,
            num_hidden_layers=24,
            num_attention_heads=16,
            intermediate_size=4096,
            feat_extract_norm="layer",
            conv_bias=True,
            do_stable_layer_norm=True,
        )

    @classmethod
    def small(cls, model_type: str = "hubert", style: str = "base", **overrides: Any) -> EncoderConfig:
        """A tiny encoder for tests and CPU demos: 3 convs (hop 20), 2 layers x 32 wide.

        Args:
            model_type: ``"wav2vec2"`` or ``"hubert"``.
            style: ``"base"`` (group norm, post-LN) or ``"large"`` (layer norm, stable layer norm).
            **overrides: any other field.
        """
        if style not in ("base", "large"):
            raise ValueError(f"style must be 'base' or 'large', got {style!r}")
        fields: dict[str, Any] = dict(
            model_type=model_type,
            hidden_size=32,
            num_hidden_layers=2,
            num_attention_heads=4,
            intermediate_size=64,
            conv_dim=(16, 24, 24),
            conv_stride=(5, 2, 2),
            conv_kernel=(10, 3, 3),
            num_conv_pos_embeddings=8,
            num_conv_pos_embedding_groups=4,
        )
        if style == "large":
            fields.update(feat_extract_norm="layer", conv_bias=True, do_stable_layer_norm=True)
        fields.update(overrides)
        return cls(**fields)


def _is_pos_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value > 0
