"""TIMAR: turn-level interleaved masked autoregression with a per-frame diffusion head.

Modules: ``config`` (presets), ``tokens`` (turn layout, separators, interleave), ``encoder``
(embedding + turn-causal fusion, and the MAE-style encoder-decoder variant), ``head`` (per-frame adaLN
diffusion head, vmapped), ``model`` (parameters, window pass), ``loss`` (masking, CFG dropout, grouped x0
diffusion loss), ``sampling``
(respaced DDIM/DDPM with traced CFG: :func:`sample`), ``streaming`` (turn-by-turn engine with a KV cache:
:func:`init_stream`, :func:`stream_step`, :func:`stream`), ``data``
(SynthTalk conversations -> turn windows, normalisation), ``convert`` (the public code's checkpoints ->
parameters and a run folder; torch only there, ``pip install "jaxtalk[torch]"``).
"""

from jaxtalk.models.timar.config import TimarConfig
from jaxtalk.models.timar.loss import loss, make_loss_fn
from jaxtalk.models.timar.model import encode_window, init_params
from jaxtalk.models.timar.sampling import posterior_mean, sample
from jaxtalk.models.timar.streaming import init_stream, stream, stream_step

__all__ = ["TimarConfig", "init_params", "encode_window", "loss", "make_loss_fn", "sample", "posterior_mean",
           "init_stream", "stream_step", "stream"]
