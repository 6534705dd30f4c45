"""Pretrained speech encoders in JAX: wav2vec 2.0 and HuBERT loaded from Hugging Face checkpoints.

* ``SpeechEncoder.from_pretrained(path)``: a checkpoint directory (``config.json`` +
  ``model.safetensors``, or ``pytorch_model.bin`` when PyTorch is installed) as an audio front end:
  ``.features(audio_16k, layer=None) -> (frames, dim)`` at ``.rate`` (50 Hz), ``.features_at(audio,
  25)`` (resampled to the motion rate), ``.interpolated_features(audio, 25)`` (TIMAR/DualTalk: conv
  features interpolated before the transformer), ``.encode(audio) -> TokenStream``.
* ``encoder_features(params, waveform, lengths, config=..., layer=..., frozen=...)``: the pure,
  jit-able function to call inside a model's program (frozen or fine-tuned).
* ``Wav2Vec2Model``: the Flax modules (HF names), ``EncoderConfig``: the architecture from
  ``config.json``, ``load_checkpoint``: tensors mapped by name with clear errors.

PyTorch is never needed at run time; ``transformers`` only serves the equivalence tests.
"""

from jaxtalk.audio.encoders.config import EncoderConfig
from jaxtalk.audio.encoders.frontend import (
    SpeechEncoder,
    encoder_features,
    interpolate_align_corners,
    normalize_waveform,
    resolve_layer,
)
from jaxtalk.audio.encoders.loader import (
    Checkpoint,
    checkpoint_fingerprint,
    expected_param_shapes,
    hf_tensor_names,
    load_checkpoint,
    params_from_state_dict,
    params_to_state_dict,
    read_state_dict,
    save_checkpoint,
    weight_files,
)
from jaxtalk.audio.encoders.wav2vec2 import EncoderOutput, Wav2Vec2Model, conv_output_lengths

__all__ = [
    "SpeechEncoder",
    "encoder_features",
    "interpolate_align_corners",
    "normalize_waveform",
    "resolve_layer",
    "EncoderConfig",
    "Checkpoint",
    "load_checkpoint",
    "read_state_dict",
    "weight_files",
    "checkpoint_fingerprint",
    "params_from_state_dict",
    "params_to_state_dict",
    "save_checkpoint",
    "expected_param_shapes",
    "hf_tensor_names",
    "Wav2Vec2Model",
    "EncoderOutput",
    "conv_output_lengths",
]
