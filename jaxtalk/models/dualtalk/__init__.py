"""A DualTalk-style baseline (Peng et al., CVPR 2025): the non-causal model TIMAR's Table 1 compares to.

It reads a whole window at once, both speakers' speech and the user's (partner's) head motion, and
regresses the agent's 56-d head motion for every frame of it. Nothing is sampled and nothing streams:
every output frame reads every input frame, the future included.

Kept from DualTalk (its paper and released code):

* the dual-speaker joint encoder: each speaker's speech through its own encoder, the partner's motion
  through a 2-layer ReLU MLP (hidden half the stream width) to the same width;
* the cross-modal temporal enhancer on the partner: the partner's speech features attend to the
  partner's motion features, then a 2-layer bidirectional LSTM;
* the dual-speaker interaction module: the agent's speech features concatenated with the partner
  branch (twice the stream width), a transformer encoder with full bidirectional self-attention over
  time, and dropout on its output;
* the expressive synthesis module's decoder layer attending to the interaction features, then a
  per-frame linear map to the 56 FLAME parameters;
* the loss: the MSE of exp, of jaw and of neck, plus the MSE of the frame-to-frame velocity, summed
  with equal weights; no agent motion is an input;
* the sizes (``paper`` preset): 256-wide streams, a 512-wide encoder of 3 layers x 4 heads with a
  2048-wide ReLU feed-forward, one decoder layer, dropout 0.1 in the layers and 0.5 on the encoder
  output; 8-s (200-frame) training windows.

Changed:

* the two wav2vec 2.0 encoders (fine-tuned inside DualTalk) become any per-frame speech feature
  (``speech_dim``: jaxtalk's 80-band log-mel by default, 1024 for precomputed wav2vec 2.0 large)
  through one learnable projection per speaker, which also stands in for DualTalk's shared projection
  after the encoders;
* those features carry no position of their own (wav2vec 2.0's convolutional position code gave
  DualTalk's speech features one), so fixed sinusoidal frame positions are added to the encoder input;
* the transformer layers are jaxtalk's pre-LayerNorm blocks (DualTalk's PyTorch layers are post-LN),
  with a final LayerNorm after the encoder and after the decoder; the feed-forward keeps ReLU;
* data: TIMAR's recipe (the same windows and per-channel normaliser, so both models see identical
  data); the regression is on standardised parameters, so the loss weights channels by their spread;
  the training settings are TIMAR's (the protocol of its Table 1), not DualTalk's Adam 1e-4 with a
  step decay;
* ``small`` preset: 128 wide, 4 layers, 4 heads, no dropout, in the budget of TIMAR's ``small``.

Dropped:

* the extra self-attention after the interaction encoder (one more attention without residual or
  feed-forward; the depth is ``num_layers``);
* the "adaptive expression modulation" ``x + 0.1 Linear(x)`` before the output layer: an affine map
  followed by the affine output layer is the same function class as the output layer alone;
* the frozen convolutional feature extractor of wav2vec 2.0 (no audio encoder inside the model).

Modules: ``config`` (presets), ``model`` (network, ``init_params``, ``apply``), ``predict``
(``predict_window``; ``predict_turns``, Table 1's progressive context), ``loss``, ``recipe``.
"""

from jaxtalk.models.dualtalk.config import DualTalkConfig
from jaxtalk.models.dualtalk.loss import loss, make_loss_fn
from jaxtalk.models.dualtalk.model import apply, init_params
from jaxtalk.models.dualtalk.predict import predict_turns, predict_window

__all__ = ["DualTalkConfig", "apply", "loss", "init_params", "make_loss_fn", "predict_turns", "predict_window"]
