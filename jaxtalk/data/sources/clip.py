"""What a dataset source yields: clip entries (cheap metadata) that read into raw clips on demand,
and the one validation every clip passes before it is prepared.

A source lists its clips without reading them (a 50-hour dataset is listed in seconds); ``prepare``
reads and checks one clip at a time, so one broken file costs one clip, never the whole run.
"""

from __future__ import annotations

import dataclasses
import hashlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from jaxtalk.types import AUDIO_SAMPLE_RATE, MOTION_FPS, PARAM_DIM

__all__ = ["BadClip", "ClipEntry", "RawClip", "check_clip", "file_hash", "MAX_SKEW_SECONDS", "FPS_RANGE"]

# Motion and audio may disagree by this much (trackers drop a frame or two at either end); more
# means the pair is not the same recording.
MAX_SKEW_SECONDS = 0.2
# A stated frame rate outside this range is a units mistake (e.g. seconds per frame, or samples).
FPS_RANGE = (10.0, 240.0)


class BadClip(ValueError):
    """A clip that cannot be used; ``str(err)`` is the reason a report shows next to the file."""


@dataclasses.dataclass(frozen=True)
class RawClip:
    """One clip as read from its files, before features: motion at its own rate and 16 kHz audio.

    Attributes:
        fps: the motion's frame rate as stored.
        params: ``(T, 56)`` head parameters ``[exp 50 | jaw 3 | neck 3]``, or None.
        vertices: ``(T, V, 3)`` mesh vertices (vertex-only datasets such as VOCASET), or None.
        template: ``(V, 3)`` the subject's neutral mesh, or None.
        audio: ``(samples,)`` mono float32 at 16 kHz, or None (no audio file).
        tokens: ``(Tt, D)`` audio-LLM token embeddings supplied with the clip, or None.
        token_rate: their rate in Hz (required with ``tokens``).
        oracle: ``(T, 56)`` a known best prediction (SynthTalk's deterministic part), or None.
    """

    fps: float
    params: np.ndarray | None = None
    vertices: np.ndarray | None = None
    template: np.ndarray | None = None
    audio: np.ndarray | None = None
    tokens: np.ndarray | None = None
    token_rate: float | None = None
    oracle: np.ndarray | None = None

    @property
    def num_frames(self) -> int:
        """Motion frames at ``fps`` (0 for an audio-only clip)."""
        for value in (self.params, self.vertices):
            if value is not None:
                return int(value.shape[0])
        return 0


@dataclasses.dataclass(frozen=True)
class ClipEntry:
    """A clip a source lists: identity, grouping and how to read it.

    Attributes:
        name: unique name within the dataset (the file stem for file layouts).
        speaker: speaker identifier (clips of one speaker never straddle splits).
        files: the files the clip is read from; their content hash identifies the clip's version.
        read: ``() -> RawClip``; raises (any exception) on an unreadable clip.
        split: the split the layout assigns (``train``/``val``/``test``/``ood``), or None.
        emotion: emotion label, or None.
        intensity: emotion intensity, or None.
        partner: name of the conversation partner's clip, or None (monologue).
        requires_partner: the layout says this clip is one side of a conversation, so a missing
            partner is an error (DualTalk); False for layouts where partners are optional.
        group: the unit that must stay in one split when splits are drawn (default: the speaker).
        fingerprint: identifies the clip's content when it has no files (a generated corpus).
    """

    name: str
    speaker: str
    files: tuple[Path, ...]
    read: Callable[[], RawClip] = dataclasses.field(repr=False, compare=False)
    split: str | None = None
    emotion: str | None = None
    intensity: float | None = None
    partner: str | None = None
    requires_partner: bool = False
    group: str | None = None
    fingerprint: str | None = None

    @property
    def split_group(self) -> str:
        return self.group if self.group is not None else self.speaker

    def content_hash(self) -> str:
        """SHA-1 over the names and bytes of ``files`` (missing files hash as absent)."""
        if self.fingerprint is not None:
            return self.fingerprint
        h = hashlib.sha1()
        for path in self.files:
            h.update(path.name.encode())
            if path.is_file():
                h.update(file_hash(path).encode())
            else:
                h.update(b"<missing>")
        return h.hexdigest()


def file_hash(path: Path, chunk: int = 1 << 20) -> str:
    """SHA-1 of a file's bytes, read in 1 MiB chunks (constant memory for any size)."""
    h = hashlib.sha1()
    with open(path, "rb") as handle:
        while block := handle.read(chunk):
            h.update(block)
    return h.hexdigest()


def _finite(name: str, value: np.ndarray | None) -> None:
    if value is not None and not np.all(np.isfinite(value)):
        bad = int(np.size(value) - np.count_nonzero(np.isfinite(value)))
        raise BadClip(f"{name} contains {bad} NaN/inf values")


def check_clip(raw: RawClip, *, min_frames: int, motion_required: bool = True) -> None:
    """Reject a clip that would train a model on something wrong.

    Checks, in order: a plausible frame rate; motion present (unless audio-only clips are allowed)
    with the right shape; no NaN/inf anywhere; audio present; motion and audio lengths within
    :data:`MAX_SKEW_SECONDS`; at least ``min_frames`` motion frames (after conversion to 25 fps);
    tokens with a positive rate and a duration matching the audio.

    Args:
        raw: the clip as read.
        min_frames: shortest usable clip in 25-fps frames.
        motion_required: False for an audio-only conversation side (a partner without motion).

    Raises:
        BadClip: the first problem found, as a sentence naming the stream and the numbers.
    """
    if not (np.isfinite(raw.fps) and FPS_RANGE[0] <= raw.fps <= FPS_RANGE[1]):
        raise BadClip(f"motion fps {raw.fps!r} is outside the plausible range {FPS_RANGE[0]:g}-{FPS_RANGE[1]:g}")
    if raw.params is not None and (raw.params.ndim != 2 or raw.params.shape[1] != PARAM_DIM):
        raise BadClip(f"params must be (frames, {PARAM_DIM}), got {raw.params.shape}")
    if raw.vertices is not None and (raw.vertices.ndim != 3 or raw.vertices.shape[2] != 3):
        raise BadClip(f"vertices must be (frames, verts, 3), got {raw.vertices.shape}")
    if motion_required and raw.num_frames == 0:
        raise BadClip("no motion (params or vertices) in the clip")
    for name in ("params", "vertices", "template", "audio", "tokens", "oracle"):
        _finite(name, getattr(raw, name))
    if raw.audio is None or raw.audio.size == 0:
        raise BadClip("no audio (missing or empty audio file)")
    audio_s = raw.audio.size / AUDIO_SAMPLE_RATE
    if raw.num_frames:
        motion_s = raw.num_frames / raw.fps
        if abs(motion_s - audio_s) > MAX_SKEW_SECONDS:
            raise BadClip(
                f"motion lasts {motion_s:.2f} s ({raw.num_frames} frames at {raw.fps:g} fps) but audio "
                f"{audio_s:.2f} s: they differ by more than {MAX_SKEW_SECONDS} s (wrong fps, or not the same take?)"
            )
        frames25 = int(round(motion_s * MOTION_FPS))
        if frames25 < min_frames:
            raise BadClip(f"too short: {frames25} frames at {MOTION_FPS} fps, need at least {min_frames}")
    if raw.tokens is not None:
        if raw.tokens.ndim != 2 or raw.tokens.shape[0] == 0:
            raise BadClip(f"tokens must be a non-empty (tokens, dim) array, got {raw.tokens.shape}")
        if raw.token_rate is None or not raw.token_rate > 0:
            raise BadClip(f"tokens need a positive rate in Hz, got {raw.token_rate!r}")
        tokens_s = raw.tokens.shape[0] / raw.token_rate
        if abs(tokens_s - audio_s) > MAX_SKEW_SECONDS + 1.0 / raw.token_rate:
            raise BadClip(f"tokens last {tokens_s:.2f} s at {raw.token_rate:g} Hz but audio {audio_s:.2f} s")
