"""Vector-quantised audio tokenizers: discrete token ids plus an embedding table, at a chosen rate.

Stand-ins for audio-LLM tokenizers (Mimi at 12.5 Hz, CosyVoice2 at 25 Hz) built from jaxtalk's own
front end, so that token streams of different rates and widths can be made from any audio:

1. Features per token: the log-mel stream (100 frames/s) is cut into token windows
   ``[k / rate, (k + 1) / rate)``; each window is split into ``stack`` equal sub-windows, the log-mel
   frames whose centre falls in a sub-window are averaged, and the ``stack`` averages are
   concatenated (``stack * n_mels`` features). Averaging keeps the spectral envelope; stacking keeps
   coarse order inside the window (onset vs. steady part).
2. Features are standardised per dimension (mean/std of the fitting corpus); a k-means codebook is
   fitted on them (``jaxtalk.audio.kmeans``: k-means++ seeding from ``jax.random.key(seed)``, then
   Lloyd iterations; deterministic).
3. Embedding table ``(num_codes, width)``: the centred centroids times a fixed seeded random
   isometry ``P`` (orthonormal columns if ``width <= features``, orthonormal rows otherwise), scaled to
   unit RMS per entry. It carries the codebook's geometry: for ``width >= features`` embedding
   distances are exactly proportional to centroid distances, for smaller widths a random projection
   preserves them approximately (Johnson-Lindenstrauss). Two tokenizers with different seeds, rates
   and widths thus give genuinely different token spaces over the same audio.

4. Optionally (``floor_window > 0``), a causal noise-floor normaliser before step 2: each token's
   features become their level above the recording's background, ``max(raw, FLOOR_MIN) - floor``,
   where ``floor`` is, per mel channel, the minimum of the raw features over the last ``floor_window``
   tokens (this one included; both sub-windows of each), never below ``FLOOR_MIN``. Everything quieter
   than ``FLOOR_MIN`` reads as exactly zero, so digital silence, a -90 dBFS dither and a quiet room
   read alike. A steady background noise then looks like silence at any level, and a recording's
   gain cancels out wherever it has a noise floor. It reads only the past: the features of token ``k``
   do not change with audio after token ``k``'s window (a live stream carries the last
   ``floor_window - 1`` tokens' raw features).

Token count is ``ceil(samples * rate / sample_rate)``: the last token may cover a partial window,
which is padded with silence (zeros), as Mimi pads its last frame.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from fractions import Fraction
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Float, Int

from jaxtalk.audio.framerate import _as_fraction, resample_features
from jaxtalk.audio.io import check_audio
from jaxtalk.audio.kmeans import kmeans, nearest_centroid
from jaxtalk.audio.melspec import _log_mel, mel_filterbank, num_frames
from jaxtalk.types import AUDIO_SAMPLE_RATE, MOTION_FPS, Array

__all__ = ["TokenStream", "TokenizerStream", "VQTokenizer", "FLOOR_MIN", "noise_floor", "above_floor", "GroupLayout",
           "group_tokens"]

_FORMAT_VERSION = 3
_OLDEST_FORMAT = 1  # version 1 files have no normaliser (floor_window 0)
# Version 2's normaliser subtracted the floor without raising what lies below FLOOR_MIN to it
# (``floor_clip=False``): digital zero and a dither read as different negative levels.
# Lowest noise floor of the normaliser, in the features' units (natural log of mel power): white noise at
# about -74 dBFS. Below it, what is left is the recording chain's own floor, not the room.
FLOOR_MIN = -16.0
# Audio is padded to a whole number of these (in seconds, rounded to whole tokens) before the jitted
# feature kernel, so clips of many lengths share a few compiled programs. Zero padding does not change
# the frames inside the clip (centred frames already see zeros past the end).
_BUCKET_SECONDS = 2.0
_MIN_FEATURE_SCALE = 1e-5
_QUANTIZE_ROWS = 256


@dataclasses.dataclass(frozen=True, eq=False)
class TokenStream:
    """A token stream: per-token ids (None for continuous user embeddings), embeddings, and rate.

    Attributes:
        ids: ``(tokens,)`` int32 code ids, or ``None`` for embeddings that come without a codebook
            (e.g. an external audio LLM's per-frame features loaded with ``from_npy``).
        embeddings: ``(tokens, width)`` float32.
        rate: tokens per second.
    """

    ids: Int[np.ndarray, " tokens"] | None
    embeddings: Float[np.ndarray, "tokens width"]
    rate: float | int

    def __post_init__(self):
        emb = self.embeddings
        if (
            not isinstance(emb, np.ndarray)
            or emb.ndim != 2
            or emb.shape[0] == 0
            or emb.shape[1] == 0
        ):
            raise ValueError(
                f"embeddings must be a non-empty (tokens, width) array, got "
                f"{getattr(emb, 'shape', type(emb))}"
            )
        if not np.all(np.isfinite(emb)):
            raise ValueError("embeddings contain NaN or inf values")
        if self.ids is not None and self.ids.shape != emb.shape[:1]:
            raise ValueError(f"ids shape {self.ids.shape} does not match embeddings {emb.shape}")
        if not np.isfinite(self.rate) or self.rate <= 0:
            raise ValueError(
                f"rate must be a positive number of tokens per second, got {self.rate!r}"
            )

    def __len__(self) -> int:
        return int(self.embeddings.shape[0])

    @property
    def width(self) -> int:
        """Embedding width."""
        return int(self.embeddings.shape[1])

    @property
    def duration(self) -> float:
        """Seconds covered: ``tokens / rate``."""
        return len(self) / self.rate

    @classmethod
    def from_npy(cls, path: str | os.PathLike, rate: float | int) -> TokenStream:
        """Load user-supplied per-frame embeddings (a ``(frames, width)`` ``.npy``) at ``rate``.

        Args:
            path: ``.npy`` file holding a 2-D float array.
            rate: its frame rate in Hz (e.g. 12.5 for Mimi/GLM-4-Voice, 25 for CosyVoice2, 50 for
                HuBERT/wav2vec 2.0).

        Returns:
            ``TokenStream`` with ``ids=None`` and float32 embeddings.

        Raises:
            FileNotFoundError: if ``path`` does not exist.
            ValueError: for a non-numeric, non-2-D, empty or NaN array, or a bad rate.
        """
        from jaxtalk.files import load_npy

        path = Path(path)
        array = load_npy(path, what="embedding file")
        if not np.issubdtype(array.dtype, np.number):
            raise ValueError(f"{str(path)!r}: expected a numeric array, got {array.dtype}")
        if array.ndim != 2:
            raise ValueError(
                f"{str(path)!r}: expected (frames, width) embeddings, got shape {array.shape}"
            )
        try:
            return cls(ids=None, embeddings=array.astype(np.float32), rate=float(rate))
        except ValueError as err:
            raise ValueError(f"{str(path)!r}: {err}") from err

    def to_frame_rate(
        self, fps: float | int = MOTION_FPS, num_frames: int | None = None, mode: str = "linear"
    ) -> Float[Array, "frames width"]:
        """The embeddings resampled to ``fps`` (see ``resample_features``; ``"previous"`` is causal)."""
        return resample_features(self.embeddings, self.rate, fps, num_frames=num_frames, mode=mode)


def _token_layout(samples: int, sample_rate: int, rate: float | int, hop_length: int, stack: int):
    """Static plan: (tokens, bucketed tokens, padded samples, sub-window id of every mel frame)."""
    tokens_per_sample = _as_fraction(rate, "rate") / sample_rate
    tokens = max(1, math.ceil(samples * tokens_per_sample))
    per_bucket = max(1, round(_BUCKET_SECONDS * rate))
    bucket_tokens = -(-tokens // per_bucket) * per_bucket
    padded = math.ceil(bucket_tokens / tokens_per_sample)
    frames = num_frames(padded, hop_length=hop_length, center=True)
    # Frame f is centred at f * hop / sr seconds; its sub-window is floor(time * rate * stack).
    step = Fraction(hop_length) * tokens_per_sample * stack
    segment = (np.arange(frames, dtype=np.int64) * step.numerator) // step.denominator
    return tokens, bucket_tokens, padded, segment.astype(np.int32)


@functools.partial(
    jax.jit,
    static_argnames=("num_tokens", "stack", "sample_rate", "n_mels", "n_fft", "hop_length", "center"),
)
def _pooled_features(audio, segment, *, num_tokens, stack, sample_rate, n_mels, n_fft, hop_length, center=True):
    # center=False: ``audio`` already starts n_fft // 2 samples before its first frame's centre (a live
    # window, see TokenizerStream), which is what centring's zero padding gives a whole clip.
    mel = _log_mel(
        audio,
        sample_rate=sample_rate,
        n_mels=n_mels,
        n_fft=n_fft,
        hop_length=hop_length,
        win_length=n_fft,
        f_min=0.0,
        f_max=None,
        center=center,
        pad_mode="constant",
        log_floor=1e-10,
    )
    num_segments = num_tokens * stack
    # Frames past the last token window carry ids >= num_segments; segment_sum drops them.
    total = jax.ops.segment_sum(mel, segment, num_segments=num_segments)
    count = jax.ops.segment_sum(
        jnp.ones_like(segment, dtype=mel.dtype), segment, num_segments=num_segments
    )
    mean = total / jnp.maximum(count, 1)[:, None]
    return mean.reshape(num_tokens, stack * n_mels)


@jax.jit
def _nearest_code(features, mean, scale, codebook):
    return nearest_centroid((features - mean[None, :]) / scale[None, :], codebook)


def noise_floor(raw: Float[np.ndarray, "tokens features"], window: int, n_mels: int,
                past: Float[np.ndarray, "past features"] | None = None) -> Float[np.ndarray, "tokens features"]:
    """The causal noise floor of pooled token features: per mel channel, the minimum over the last
    ``window`` tokens (this one included, all ``stack`` sub-windows), at least :data:`FLOOR_MIN`.

    Args:
        raw: ``(tokens, stack * n_mels)`` raw pooled features (:meth:`VQTokenizer.features`).
        window: tokens the minimum reaches back, ``>= 1``.
        n_mels: mel channels per sub-window.
        past: raw features of the tokens just before ``raw`` (a live stream's carried history); only
            the last ``window - 1`` rows are read.

    Returns:
        The floor, the shape of ``raw`` (each channel's value repeated over the sub-windows).
    """
    raw = np.asarray(raw, np.float32)
    tokens, features = raw.shape
    stack = features // n_mels
    per_mel = raw.reshape(tokens, stack, n_mels).min(axis=1)  # (tokens, n_mels)
    if past is not None and window > 1 and len(past):
        past = np.asarray(past, np.float32)[-(window - 1):]
        history = past.reshape(len(past), stack, n_mels).min(axis=1)
    else:
        history = np.zeros((0, n_mels), np.float32)
    lead = np.full((window - 1 - len(history), n_mels), np.inf, np.float32)
    padded = np.concatenate([lead, history, per_mel])
    floor = np.lib.stride_tricks.sliding_window_view(padded, window, axis=0).min(axis=-1)
    floor = np.maximum(floor, np.float32(FLOOR_MIN))
    return np.tile(floor, (1, stack))


def above_floor(raw: Float[np.ndarray, "tokens features"], window: int, n_mels: int,
                past: Float[np.ndarray, "past features"] | None = None, *,
                clip: bool = True) -> Float[np.ndarray, "tokens features"]:
    """The normaliser's output: the raw features' level above their causal :func:`noise_floor`.

    Args:
        raw, window, n_mels, past: as for :func:`noise_floor`.
        clip: raise features below :data:`FLOOR_MIN` to it first, so that everything quieter than the
            lowest floor reads as exactly zero (False: version-2 tokenizers' normaliser).
    """
    raw = np.asarray(raw, np.float32)
    floor = noise_floor(raw, window, n_mels, past)
    return (np.maximum(raw, np.float32(FLOOR_MIN)) if clip else raw) - floor


def _random_isometry(features: int, width: int, seed: int) -> np.ndarray:
    # NumPy stream keyed by [seed, 1]: reproducible on any machine, separate from the JAX key
    # that seeds k-means.
    rng = np.random.default_rng([seed, 1])
    if width <= features:
        q, _ = np.linalg.qr(rng.standard_normal((features, width)))
        return q  # orthonormal columns: an orthogonal projection onto a random width-d subspace
    q, _ = np.linalg.qr(rng.standard_normal((width, features)))
    return q.T  # orthonormal rows: an exact isometric embedding R^features -> R^width


@dataclasses.dataclass(frozen=True, eq=False)
class VQTokenizer:
    """A fitted vector-quantising audio tokenizer (see the module docstring for the recipe).

    Build with ``VQTokenizer.fit``; persist with ``save`` / ``load``.

    Attributes:
        codebook: ``(num_codes, features)`` k-means centroids in standardised feature space.
        feature_mean: ``(features,)`` per-dimension mean used for standardising.
        feature_scale: ``(features,)`` per-dimension std (floored) used for standardising.
        embedding: ``(num_codes, width)`` embedding table.
        rate: tokens per second.
        sample_rate: audio rate in Hz the tokenizer reads.
        n_mels, n_fft, hop_length: log-mel settings.
        stack: sub-windows per token (``features = stack * n_mels``).
        seed: the seed it was fitted with.
        floor_window: tokens of the causal noise-floor normaliser (0: none, the raw features are
            quantised). See the module's step 4.
        floor_clip: the normaliser reads everything below ``FLOOR_MIN`` as ``FLOOR_MIN`` (True; False
            only for tokenizers saved by format version 2, which did not).
    """

    codebook: Float[np.ndarray, "codes features"]
    feature_mean: Float[np.ndarray, " features"]
    feature_scale: Float[np.ndarray, " features"]
    embedding: Float[np.ndarray, "codes width"]
    rate: float | int
    sample_rate: int = AUDIO_SAMPLE_RATE
    n_mels: int = 80
    n_fft: int = 400
    hop_length: int = 160
    stack: int = 2
    seed: int = 0
    floor_window: int = 0
    floor_clip: bool = True

    def __post_init__(self):
        codes, features = self.codebook.shape
        if features != self.stack * self.n_mels:
            raise ValueError(
                f"codebook has {features} features, expected stack * n_mels = {self.stack * self.n_mels}"
            )
        if self.feature_mean.shape != (features,) or self.feature_scale.shape != (features,):
            raise ValueError(
                f"feature_mean {self.feature_mean.shape} / feature_scale {self.feature_scale.shape} "
                f"must have shape ({features},)"
            )
        if self.embedding.ndim != 2 or self.embedding.shape[0] != codes:
            raise ValueError(f"embedding {self.embedding.shape} must have shape ({codes}, width)")
        if not np.all(self.feature_scale > 0):
            raise ValueError("feature_scale must be positive")
        if isinstance(self.floor_window, bool) or not isinstance(self.floor_window, (int, np.integer)) \
                or self.floor_window < 0:
            raise ValueError(f"floor_window must be an integer >= 0 (tokens; 0 = no normaliser), got {self.floor_window!r}")
        _check_layout(self.rate, self.sample_rate, self.hop_length, self.stack)

    @property
    def lookahead_s(self) -> float:
        """Audio a token reads past the end of its own window, in seconds (the worst token).

        A token pools the log-mel frames centred inside its window; the last of them is centred up to
        a hop before the window's end, and its centred ``n_fft``-sample STFT reaches ``n_fft / 2``
        samples past its centre (2.5 ms at 25 or 12.5 Hz with the defaults: the last centre sits 160
        samples before the end, the STFT reaches 200 past it). A live stream can emit token ``k`` only
        once that much audio after ``(k + 1) / rate`` has arrived, so it adds to the chunk latency.
        """
        frames_per_token = Fraction(self.sample_rate) / _as_fraction(self.rate, "rate") / self.hop_length
        reach = Fraction(self.n_fft, 2 * self.hop_length)  # frames past the last centre
        worst = max((math.ceil((k + 1) * frames_per_token) - 1) + reach - (k + 1) * frames_per_token
                    for k in range(frames_per_token.denominator))
        return float(max(worst, 0) * self.hop_length / self.sample_rate)

    @property
    def num_codes(self) -> int:
        """Codebook size."""
        return int(self.codebook.shape[0])

    @property
    def width(self) -> int:
        """Embedding width."""
        return int(self.embedding.shape[1])

    @classmethod
    def fit(
        cls,
        audios: list[np.ndarray],
        *,
        sample_rate: int = AUDIO_SAMPLE_RATE,
        rate: float | int,
        num_codes: int,
        width: int,
        seed: int,
        n_mels: int = 80,
        stack: int = 2,
        iterations: int = 25,
        floor_window: int = 0,
    ) -> VQTokenizer:
        """Fit the codebook and embedding table on a list of mono clips.

        Args:
            audios: clips, each ``(samples,)`` float at ``sample_rate``.
            sample_rate: their rate in Hz.
            rate: tokens per second (e.g. 12.5 or 25); the token window ``1 / rate`` must hold at
                least ``stack`` log-mel frames (``rate * stack <= 100`` at the default hop).
            num_codes: codebook size.
            width: embedding width.
            seed: seeds k-means++ and the embedding projection (same inputs + seed -> same tokenizer).
            n_mels: log-mel channels of the features.
            stack: sub-windows per token.
            iterations: k-means iterations.
            floor_window: tokens of the causal noise-floor normaliser (0: none). The codebook is
                fitted on the normalised features, each clip's floor starting afresh.

        Returns:
            The fitted tokenizer.

        Raises:
            ValueError: for an empty list, a bad clip (names its index), bad sizes, or fewer distinct
                token features than ``num_codes``.
        """
        if not isinstance(audios, (list, tuple)) or len(audios) == 0:
            raise ValueError("fit needs a non-empty list of audio clips")
        if num_codes < 1 or width < 1 or iterations < 1:
            raise ValueError(
                f"need num_codes, width, iterations >= 1, got {num_codes}, {width}, {iterations}"
            )
        if (
            isinstance(seed, bool)
            or not isinstance(seed, (int, np.integer))
            or not 0 <= seed < 2**32
        ):
            # jax.random.key silently keeps only the low 32 bits (2**32 would collide with 0).
            raise ValueError(f"seed must be an integer in [0, 2**32), got {seed!r}")
        hop_length, n_fft = (
            round(sample_rate / 100),
            round(sample_rate / 40),
        )  # 10 ms hop, 25 ms window
        _check_layout(rate, sample_rate, hop_length, stack)
        mel_filterbank(sample_rate, n_fft, n_mels)  # validates n_mels early
        feats = [
            _features(
                np.asarray(a), sample_rate, rate, n_mels, n_fft, hop_length, stack, f"audios[{i}]"
            )
            for i, a in enumerate(audios)
        ]
        if floor_window:
            feats = [above_floor(f, floor_window, n_mels) for f in feats]
        data = np.concatenate(feats, axis=0).astype(np.float64)
        distinct = np.unique(data, axis=0).shape[0]
        if distinct < num_codes:
            raise ValueError(
                f"only {distinct} distinct token features in {data.shape[0]} tokens, fewer than "
                f"num_codes={num_codes}; give more (or more varied) audio or fewer codes"
            )
        mean = data.mean(axis=0)
        scale = np.maximum(data.std(axis=0), _MIN_FEATURE_SCALE)
        z = (data - mean) / scale
        fitted = kmeans(
            jnp.asarray(z, dtype=jnp.float32),
            num_codes,
            key=jax.random.key(seed),
            iterations=iterations,
        )
        centroids = np.asarray(fitted.centroids, dtype=np.float64)
        projected = (centroids - centroids.mean(axis=0)) @ _random_isometry(z.shape[1], width, seed)
        rms = np.sqrt(np.mean(projected**2))
        embedding = projected / (rms if rms > 0 else 1.0)
        return cls(
            codebook=centroids.astype(np.float32),
            feature_mean=mean.astype(np.float32),
            feature_scale=scale.astype(np.float32),
            embedding=embedding.astype(np.float32),
            rate=float(rate),
            sample_rate=int(sample_rate),
            n_mels=int(n_mels),
            n_fft=int(n_fft),
            hop_length=int(hop_length),
            stack=int(stack),
            seed=int(seed),
            floor_window=int(floor_window),
        )

    def normalise(self, raw: Float[np.ndarray, "tokens features"],
                  past: Float[np.ndarray, "past features"] | None = None) -> Float[np.ndarray, "tokens features"]:
        """What :meth:`quantize` reads: the raw features' level above their causal noise floor
        (:func:`above_floor`), or the raw features themselves for a tokenizer without normaliser
        (``floor_window == 0``).

        Args:
            raw: raw pooled features of consecutive tokens.
            past: the raw features of the tokens before them in the same recording (a live stream's).
        """
        raw = np.asarray(raw, np.float32)
        if not self.floor_window:
            return raw
        return above_floor(raw, self.floor_window, self.n_mels, past, clip=self.floor_clip)

    def features(
        self, audio: Float[np.ndarray | Array, " samples"]
    ) -> Float[np.ndarray, "tokens features"]:
        """Raw (unstandardised) pooled log-mel features, one row per token window.

        Raises:
            ValueError: for a non 1-D, empty or NaN/inf signal.
        """
        return _features(
            np.asarray(audio),
            self.sample_rate,
            self.rate,
            self.n_mels,
            self.n_fft,
            self.hop_length,
            self.stack,
            "audio",
        )

    def quantize(
        self, features: Float[np.ndarray | Array, "tokens features"]
    ) -> Int[np.ndarray, " tokens"]:
        """Nearest codebook entry (Euclidean, standardised space) of each feature row (normalised
        features, :meth:`normalise`, for a tokenizer with a normaliser).

        Raises:
            ValueError: for features of the wrong width.
        """
        features = np.asarray(features, dtype=np.float32)
        if features.ndim != 2 or features.shape[1] != self.codebook.shape[1]:
            raise ValueError(
                f"features must have shape (tokens, {self.codebook.shape[1]}), got {features.shape}"
            )
        # Pad rows to a multiple of _QUANTIZE_ROWS so clips of many lengths share compiled programs.
        rows = features.shape[0]
        padded = np.zeros(
            (-(-max(rows, 1) // _QUANTIZE_ROWS) * _QUANTIZE_ROWS, features.shape[1]), np.float32
        )
        padded[:rows] = features
        ids = _nearest_code(padded, self.feature_mean, self.feature_scale, self.codebook)
        return np.asarray(ids)[:rows]

    def lookup(self, ids: Int[np.ndarray | Array, " tokens"]) -> Float[np.ndarray, "tokens width"]:
        """Embeddings of token ids.

        Raises:
            ValueError: for ids outside ``[0, num_codes)``.
        """
        ids = np.asarray(ids)
        if ids.size and (ids.min() < 0 or ids.max() >= self.num_codes):
            raise ValueError(
                f"token ids must lie in [0, {self.num_codes}), got [{ids.min()}, {ids.max()}]"
            )
        return self.embedding[ids]

    def encode(self, audio: Float[np.ndarray | Array, " samples"]) -> TokenStream:
        """Tokenize one mono clip at ``self.sample_rate``.

        Args:
            audio: ``(samples,)`` float signal (silence is allowed: a listener's channel).

        Returns:
            ``TokenStream`` with ``ceil(samples * rate / sample_rate)`` tokens.

        Raises:
            ValueError: for a non 1-D, empty or NaN/inf signal.
        """
        ids = self.quantize(self.normalise(self.features(audio)))
        return TokenStream(ids=ids, embeddings=self.lookup(ids), rate=self.rate)

    def stream(self, group: int = 1) -> TokenizerStream:
        """A :class:`TokenizerStream`: tokens of audio pushed piece by piece, ``group`` at a time."""
        return TokenizerStream(self, group)

    def save(self, path: str | os.PathLike) -> Path:
        """Write the tokenizer to an ``.npz`` file (exact round trip through ``load``).

        Returns:
            The path written (``.npz`` appended when missing, as NumPy does).
        """
        from jaxtalk.files import atomic_savez

        path = Path(path)
        if path.suffix != ".npz":
            path = path.with_name(path.name + ".npz")
        atomic_savez(
            path,
            format_version=np.int64(_FORMAT_VERSION),
            codebook=self.codebook,
            feature_mean=self.feature_mean,
            feature_scale=self.feature_scale,
            embedding=self.embedding,
            rate=np.float64(self.rate),
            sample_rate=np.int64(self.sample_rate),
            n_mels=np.int64(self.n_mels),
            n_fft=np.int64(self.n_fft),
            hop_length=np.int64(self.hop_length),
            stack=np.int64(self.stack),
            seed=np.int64(self.seed),
            floor_window=np.int64(self.floor_window),
            floor_clip=np.bool_(self.floor_clip),
        )
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> VQTokenizer:
        """Read a tokenizer written by ``save``.

        Raises:
            FileNotFoundError: if ``path`` does not exist.
            ValueError: if it is not a tokenizer file (lists missing keys) or its arrays disagree.
        """
        from jaxtalk.files import load_npz

        path = Path(path)
        arrays = ("codebook", "feature_mean", "feature_scale", "embedding")
        ints = ("sample_rate", "n_mels", "n_fft", "hop_length", "stack", "seed")
        data = load_npz(path, what="tokenizer file")
        missing = [k for k in ("format_version", "rate", *arrays, *ints) if k not in data]
        if missing:
            raise ValueError(f"{str(path)!r} is not a VQTokenizer file: missing keys {missing}")
        version = int(data["format_version"])
        if not _OLDEST_FORMAT <= version <= _FORMAT_VERSION:
            raise ValueError(f"{str(path)!r}: unsupported tokenizer format version {version}")
        if version >= 2:
            ints = (*ints, "floor_window")
            if "floor_window" not in data:
                raise ValueError(f"{str(path)!r} is not a VQTokenizer file: missing keys ['floor_window']")
        if version >= 3 and "floor_clip" not in data:
            raise ValueError(f"{str(path)!r} is not a VQTokenizer file: missing keys ['floor_clip']")
        kwargs = {k: np.array(data[k], dtype=np.float32) for k in arrays}
        kwargs.update({k: int(data[k]) for k in ints})
        kwargs["floor_clip"] = bool(data["floor_clip"]) if version >= 3 else False
        kwargs["rate"] = float(data["rate"])
        return cls(**kwargs)


class TokenizerStream:
    """Tokens of audio that arrives piece by piece: the tokens :meth:`VQTokenizer.encode` gives for all
    the audio pushed so far, each one as soon as the audio it reads has arrived.

    Token ``k`` pools the log-mel frames centred in its window ``[k / rate, (k + 1) / rate)``; the last of
    them reads ``n_fft / 2`` samples past its centre (:attr:`VQTokenizer.lookahead_s`). :meth:`push` emits
    tokens in groups of ``group`` (a model chunk's worth), each group once those samples are in;
    :meth:`finish` emits the rest, the last window padded with silence as ``encode`` pads a clip's end. Each
    group's frames are computed from a fixed-length window of the audio (one compiled program whatever
    the group's position), and only the audio later tokens still read is kept.

    Attributes:
        tokenizer: the :class:`VQTokenizer`.
        group: tokens per emitted group.
        samples: samples pushed so far.
        tokens: tokens emitted so far.
    """

    def __init__(self, tokenizer: VQTokenizer, group: int = 1):
        if isinstance(group, bool) or not isinstance(group, (int, np.integer)) or group < 1:
            raise ValueError(f"group must be a positive integer, got {group!r}")
        self.tokenizer = tokenizer
        self.group = int(group)
        self.samples = 0
        self.tokens = 0
        t = tokenizer
        # Sub-windows advanced per log-mel frame: frame f belongs to sub-window floor(f * step).
        self._step = Fraction(t.hop_length) * _as_fraction(t.rate, "rate") / t.sample_rate * t.stack
        self._reach = t.n_fft // 2  # samples a centred frame reads before its centre
        # Frames of one group, at its widest (the phase of k * stack / step varies when a token is not a
        # whole number of frames): every group is computed on this many, the extra ones dropped.
        phases = self._step.denominator
        self._frames = max(self._first_frame(k + self.group) - self._first_frame(k) for k in range(phases))
        self._window = (self._frames - 1) * t.hop_length + t.n_fft
        self._buffer = np.zeros(0, np.float32)
        self._buffer_start = 0  # absolute index of self._buffer[0] (may be negative: zeros before the clip)
        self._past = np.zeros((0, tokenizer.codebook.shape[1]), np.float32)  # the normaliser's history

    def _first_frame(self, token: int) -> int:
        """The first log-mel frame that belongs to ``token`` (or to a later one)."""
        return math.ceil(token * self.tokenizer.stack / self._step)

    def _segment(self, k0: int) -> np.ndarray:
        """The sub-window (within the group starting at token ``k0``) of each log-mel frame of its window;
        ``group * stack`` for frames that belong to a later group (dropped)."""
        frames = self._first_frame(k0) + np.arange(self._frames, dtype=np.int64)
        segment = (frames * self._step.numerator) // self._step.denominator - k0 * self.tokenizer.stack
        return np.where(segment < self.group * self.tokenizer.stack, segment, self.group * self.tokenizer.stack)

    def layout(self) -> GroupLayout:
        """The fixed layout of every group's window (:class:`GroupLayout`), for a host that computes the tokens
        itself (:func:`group_tokens`, an exported front end).

        Raises:
            ValueError: when groups start at different phases of the log-mel hop (a group that is not a whole
                number of log-mel frames), so that no one layout serves every group.
        """
        t = self.tokenizer
        hop = self._first_frame(self.group)  # frames a group advances, when the layout is fixed
        if any(self._first_frame((n + 1) * self.group) - self._first_frame(n * self.group) != hop
               or not np.array_equal(self._segment(n * self.group), self._segment(0)) for n in range(self._step.denominator)):
            raise ValueError(f"a group of {self.group} tokens at {t.rate} Hz is not a whole number of {t.hop_length}-sample "
                             f"log-mel hops, so its windows differ from group to group: choose a group (chunk) that is")
        return GroupLayout(group=self.group, window_samples=self._window, hop_samples=hop * t.hop_length,
                           offset_samples=-self._reach, lookahead_samples=self._needed(self.group) - hop * t.hop_length,
                           segment=self._segment(0).astype(np.int32))

    def _needed(self, tokens: int) -> int:
        """Samples that tokens ``0 .. tokens - 1`` read (the last frame's centre plus its reach)."""
        last = self._first_frame(tokens) - 1
        return last * self.tokenizer.hop_length - self._reach + self.tokenizer.n_fft

    @property
    def samples_needed(self) -> int:
        """More samples needed before :meth:`push` emits the next group (0: it would now)."""
        return max(self._needed(self.tokens + self.group) - self.samples, 0)

    def push(
        self, audio: Float[np.ndarray | Array, "..."]
    ) -> tuple[Int[np.ndarray, " tokens"], Float[np.ndarray, "tokens width"]]:
        """Add audio; return the ids and embeddings of every group it completes (possibly none).

        Raises:
            ValueError: a non 1-D or NaN/inf signal (nothing is added).
        """
        audio = np.asarray(audio, np.float32)
        if audio.size:
            check_audio(audio, self.tokenizer.sample_rate, min_duration=0.0, allow_silence=True, name="audio")
            self._buffer = np.concatenate([self._buffer, audio])
            self.samples += int(audio.size)
        ready = self.tokens
        while self._needed(ready + self.group) <= self.samples:
            ready += self.group
        return self._emit(ready - self.tokens)

    def finish(self) -> tuple[Int[np.ndarray, " tokens"], Float[np.ndarray, "tokens width"]]:
        """The tokens not emitted yet, up to ``ceil(samples * rate / sample_rate)`` as ``encode`` counts
        them (silence past the end); afterwards the stream is empty and starts again at sample 0."""
        total = math.ceil(self.samples * _as_fraction(self.tokenizer.rate, "rate") / self.tokenizer.sample_rate)
        out = self._emit(max(total - self.tokens, 0))
        self.samples = self.tokens = self._buffer_start = 0
        self._buffer = np.zeros(0, np.float32)
        self._past = self._past[:0]
        return out

    def _emit(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        t = self.tokenizer
        feats = []
        for k0 in range(self.tokens, self.tokens + count, self.group):
            f0 = self._first_frame(k0)
            start = f0 * t.hop_length - self._reach
            window = np.zeros(self._window, np.float32)
            lo, hi = max(start, self._buffer_start), min(start + self._window, self._buffer_start + self._buffer.size)
            if hi > lo:
                window[lo - start:hi - start] = self._buffer[lo - self._buffer_start:hi - self._buffer_start]
            segment = self._segment(k0)
            feats.append(np.asarray(_pooled_features(
                jnp.asarray(window), jnp.asarray(segment, jnp.int32), num_tokens=self.group, stack=t.stack,
                sample_rate=t.sample_rate, n_mels=t.n_mels, n_fft=t.n_fft, hop_length=t.hop_length, center=False)))
        if not feats:
            return np.zeros(0, np.int32), np.zeros((0, t.width), np.float32)
        features = np.concatenate(feats)[:count]
        self.tokens += count
        keep = self._first_frame(self.tokens) * t.hop_length - self._reach  # what later tokens read
        if keep > self._buffer_start:
            self._buffer = self._buffer[keep - self._buffer_start:]
            self._buffer_start = keep
        normalised = t.normalise(features, self._past)
        if t.floor_window > 1:
            self._past = np.concatenate([self._past, features])[-(t.floor_window - 1):]
        ids = t.quantize(normalised)
        return ids, t.lookup(ids)


@dataclasses.dataclass(frozen=True)
class GroupLayout:
    """Where each group of a :class:`TokenizerStream` reads its audio, when every group reads alike.

    Group ``n`` (tokens ``n * group .. (n + 1) * group - 1``) is computed from the ``window_samples`` samples
    starting at ``n * hop_samples + offset_samples`` of the utterance (zeros before its start and past its
    end), and can be computed once ``(n + 1) * hop_samples + lookahead_samples`` samples have arrived.

    Attributes:
        group: tokens per group.
        window_samples: samples of one group's window.
        hop_samples: samples from one group's window to the next.
        offset_samples: where group 0's window starts (negative: before the utterance).
        lookahead_samples: samples past a group's end that its last token reads.
        segment: ``(frames,)`` the sub-window of each log-mel frame of a window (``group * stack``: dropped).
    """

    group: int
    window_samples: int
    hop_samples: int
    offset_samples: int
    lookahead_samples: int
    segment: np.ndarray


def group_tokens(
    tokenizer: VQTokenizer,
    layout: GroupLayout,
    audio: Float[Array, " window"],
    history: Float[Array, "past mels"] | None,
) -> tuple[Int[Array, " group"], Float[Array, "group width"], Float[Array, "past mels"] | None]:
    """One group of a :class:`TokenizerStream` on fixed shapes (traced, no checks): the token ids and
    embeddings of the group whose window is ``audio`` (:meth:`TokenizerStream.layout`), and the
    normaliser's history after it.

    The normaliser's history is, for each of the last ``floor_window - 1`` tokens, the minimum of its raw
    features over its sub-windows per mel channel (``+inf`` for tokens before the utterance); None for a
    tokenizer without normaliser (or ``floor_window == 1``).
    """
    t, group = tokenizer, layout.group
    raw = _pooled_features(audio, jnp.asarray(layout.segment), num_tokens=group, stack=t.stack, sample_rate=t.sample_rate,
                           n_mels=t.n_mels, n_fft=t.n_fft, hop_length=t.hop_length, center=False)
    features = raw
    if t.floor_window:
        per_mel = raw.reshape(group, t.stack, t.n_mels).min(axis=1)
        padded = per_mel if history is None else jnp.concatenate([history, per_mel], axis=0)
        w = t.floor_window
        floor = jnp.stack([padded[g:g + w].min(axis=0) for g in range(group)])
        floor = jnp.tile(jnp.maximum(floor, FLOOR_MIN), (1, t.stack))
        features = (jnp.maximum(raw, FLOOR_MIN) if t.floor_clip else raw) - floor
        history = None if history is None else padded[group:]
    ids = nearest_centroid((features - t.feature_mean[None, :]) / t.feature_scale[None, :], t.codebook)
    return ids, jnp.take(jnp.asarray(t.embedding), ids, axis=0), history


def _check_layout(rate: float | int, sample_rate: int, hop_length: int, stack: int) -> None:
    if isinstance(stack, bool) or not isinstance(stack, (int, np.integer)) or stack < 1:
        raise ValueError(f"stack must be a positive integer, got {stack!r}")
    if not np.isfinite(rate) or rate <= 0:
        raise ValueError(f"rate must be a positive number of tokens per second, got {rate!r}")
    frame_rate = sample_rate / hop_length
    if rate * stack > frame_rate:
        raise ValueError(
            f"rate={rate} Hz with stack={stack} needs {rate * stack} sub-windows/s, more than the "
            f"{frame_rate} log-mel frames/s; lower the rate or the stack"
        )


def _features(audio, sample_rate, rate, n_mels, n_fft, hop_length, stack, name):
    check_audio(audio, sample_rate, min_duration=0.0, allow_silence=True, name=name)
    tokens, bucket_tokens, padded, segment = _token_layout(
        audio.size, sample_rate, rate, hop_length, stack
    )
    signal = np.zeros(padded, dtype=np.float32)
    signal[: audio.size] = audio
    pooled = _pooled_features(
        jnp.asarray(signal),
        jnp.asarray(segment),
        num_tokens=bucket_tokens,
        stack=stack,
        sample_rate=sample_rate,
        n_mels=n_mels,
        n_fft=n_fft,
        hop_length=hop_length,
    )
    # Sliced on the host: slicing the device array compiles a dynamic_slice for every clip length.
    return np.asarray(pooled)[:tokens]
