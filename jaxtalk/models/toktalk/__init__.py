"""TokTalk: chunk-wise conditional flow matching from audio-LLM token embeddings to FLAME parameters.

* :class:`TokTalkConfig` (``paper``, ``small``, ``tiny`` presets) and :func:`init_params`.
* Model pieces: :class:`Decoder` (1-D U-Net transformer), :class:`StyleEncoder`, :class:`Adapter`.
* Losses: :func:`loss` (stage 1) and :func:`adapter_loss` (stage 2).
* Inference: :func:`sample` (offline), :func:`sample_long` (offline, any length in bounded memory),
  :func:`init_stream` / :func:`stream_step` / :func:`stream` (streaming engine with an explicit carried
  state), :func:`encode_style`, :func:`adapt_tokens`.
* Training: :mod:`jaxtalk.models.toktalk.recipe` (:func:`~jaxtalk.models.toktalk.recipe.train`, stage 1, and
  :func:`~jaxtalk.models.toktalk.recipe.train_adapter`, stage 2, on a prepared dataset with the shared loop).
"""

from jaxtalk.models.toktalk.adapter import Adapter
from jaxtalk.models.toktalk.config import TokTalkConfig
from jaxtalk.models.toktalk.decoder import Decoder, attention_bias
from jaxtalk.models.toktalk.loss import adapter_loss, flow_matching_terms, loss, make_loss_fn, random_known_mask
from jaxtalk.models.toktalk.model import (
    Condition,
    adapt_tokens,
    adapter_apply,
    encode_style,
    from_flow_space,
    init_adapter,
    init_params,
    interpolate_tokens,
    source_to_base_rate,
    to_flow_space,
    velocity,
)
from jaxtalk.models.toktalk.sampling import sample, sample_long
from jaxtalk.models.toktalk.streaming import (
    AdapterState,
    StreamState,
    init_stream,
    source_tokens_per_chunk,
    stream,
    stream_noise,
    stream_step,
    tokens_per_chunk,
)
from jaxtalk.models.toktalk.style import StyleEncoder, kl_divergence

__all__ = [
    "TokTalkConfig",
    "Decoder",
    "StyleEncoder",
    "Adapter",
    "Condition",
    "attention_bias",
    "init_params",
    "init_adapter",
    "velocity",
    "interpolate_tokens",
    "encode_style",
    "to_flow_space",
    "from_flow_space",
    "adapt_tokens",
    "adapter_apply",
    "source_to_base_rate",
    "kl_divergence",
    "flow_matching_terms",
    "random_known_mask",
    "loss",
    "make_loss_fn",
    "adapter_loss",
    "sample",
    "sample_long",
    "StreamState",
    "init_stream",
    "AdapterState",
    "source_tokens_per_chunk",
    "stream_step",
    "stream",
    "tokens_per_chunk",
    "stream_noise",
]
