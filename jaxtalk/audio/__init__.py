"""Audio front end: file I/O and resampling, log-mel features in JAX, frame-rate conversion, and
vector-quantised tokenizers.

* ``load_audio(path, target_rate=16000)``: WAV/FLAC -> mono float32 at 16 kHz (polyphase resampling).
* ``log_mel(audio, sample_rate=16000, n_mels=80, n_fft=400, hop_length=160)``: Slaney mel, natural log
  with a 1e-10 floor, centred frames at 100 frames/s; jit-able, batched over leading axes.
* ``resample_features(x, src_rate, dst_rate, num_frames=None, mode="linear"|"previous")``: any stream to
  the motion rate; ``"previous"`` is causal.
* ``VQTokenizer`` / ``TokenStream``: k-means token ids + embedding tables at a chosen rate and width;
  ``TokenStream.from_npy`` brings in user-supplied per-frame embeddings (e.g. an audio LLM's);
  ``VQTokenizer.stream()`` tokenizes live audio piece by piece (``TokenizerStream``), equal to ``encode``.
* ``kmeans``: jitted k-means++ / Lloyd used to fit the codebooks.
* ``espeak.speak(text, voice="en-us", rate_wpm=175, pitch=50, pitch_range=50)``: eSpeak NG speech
  (22050 Hz) with its phoneme events (mnemonic, start time), reproducible byte for byte.
"""

from jaxtalk.audio.framerate import (
    default_num_frames,
    interpolation_plan,
    resample_features,
)
from jaxtalk.audio.io import (
    check_audio,
    load_audio,
    rational_ratio,
    resample_audio,
    save_audio,
)
from jaxtalk.audio.kmeans import KMeansResult, kmeans, nearest_centroid
from jaxtalk.audio.melspec import (
    hz_to_mel,
    log_mel,
    mel_filterbank,
    mel_to_hz,
    num_frames,
)
from jaxtalk.audio.tokenizer import TokenizerStream, TokenStream, VQTokenizer

__all__ = [
    "load_audio",
    "save_audio",
    "resample_audio",
    "rational_ratio",
    "check_audio",
    "log_mel",
    "mel_filterbank",
    "hz_to_mel",
    "mel_to_hz",
    "num_frames",
    "resample_features",
    "default_num_frames",
    "interpolation_plan",
    "kmeans",
    "KMeansResult",
    "nearest_centroid",
    "VQTokenizer",
    "TokenStream",
    "TokenizerStream",
]
