"""Monologues and two-speaker conversations: who says what when, and each channel's audio + motion.

A conversation alternates turns of 1-3 phrases. The next turn starts after a pause or, one time in
four, overlaps the end of the current one; during longer turns the listener often backchannels
("mhm"). Each speaker has their own channel (audio with only their voice, as in DualTalk) and their
own motion, which combines their speech with their causal reaction to the other.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxtalk.data.synthtalk import motion as motion_lib
from jaxtalk.data.synthtalk.emotions import face_offset, voice_change
from jaxtalk.data.synthtalk.script import (
    Phrase,
    Timeline,
    layout_timeline,
    make_backchannel,
    make_phrase,
)
from jaxtalk.data.synthtalk.speakers import SpeakerStyle
from jaxtalk.data.synthtalk.speech import synthesize

__all__ = ["Channel", "monologue_timeline", "conversation_timelines", "render_channel"]

_FPS = 25
_LEAD_IN = (0.25, 0.45)   # s of silence before the first phrase
_TAIL = 0.4               # s of silence after the last one


def _frames_ceil(seconds: float) -> float:
    return float(np.ceil(seconds * _FPS)) / _FPS


@dataclasses.dataclass(frozen=True)
class Channel:
    """One speaker's rendered channel.

    Attributes:
        audio: ``(samples,)`` float32, 16 kHz.
        motion: ``(frames, 56)`` float32.
        oracle: ``(frames, 56)`` float32, deterministic part (stochastic parts at their mean).
    """

    audio: np.ndarray
    motion: np.ndarray
    oracle: np.ndarray


def monologue_timeline(rng: np.random.Generator, style: SpeakerStyle, emotion: str, intensity: int,
                       target_seconds: float) -> Timeline:
    """Phrases separated by 0.25-0.7 s pauses until ``target_seconds`` is reached."""
    voice = voice_change(emotion, intensity)
    phrases: list[Phrase] = []
    starts: list[float] = []
    t = float(rng.uniform(*_LEAD_IN))
    while True:
        p = make_phrase(rng, style, voice)
        phrases.append(p)
        starts.append(t)
        t += p.duration
        if t >= target_seconds - _TAIL:
            break
        t += float(rng.uniform(0.25, 0.7))
    return layout_timeline(phrases, starts, _frames_ceil(t + _TAIL))


def conversation_timelines(rng: np.random.Generator, styles: tuple[SpeakerStyle, SpeakerStyle],
                           emotions: tuple[tuple[str, int], tuple[str, int]],
                           target_seconds: float) -> tuple[Timeline, Timeline]:
    """Turn-taking schedule of two speakers with pauses, overlaps and backchannels.

    Args:
        rng: NumPy generator (consumed).
        styles: the two speakers.
        emotions: ``((emotion, intensity), (emotion, intensity))`` of each.
        target_seconds: the conversation runs until the turn that passes this time ends.

    Returns:
        The two speakers' timelines, of equal duration.
    """
    voices = [voice_change(e, i) for e, i in emotions]
    phrases: list[list[Phrase]] = [[], []]
    starts: list[list[float]] = [[], []]
    last_end = [0.0, 0.0]
    speaker = int(rng.integers(2))
    t = float(rng.uniform(*_LEAD_IN))
    while True:
        listener = 1 - speaker
        t = max(t, last_end[speaker] + 0.05)
        turn_start = t
        for k in range(int(rng.integers(1, 4))):
            if k:
                t += float(rng.uniform(0.15, 0.4))
            p = make_phrase(rng, styles[speaker], voices[speaker])
            phrases[speaker].append(p)
            starts[speaker].append(t)
            t += p.duration
        last_end[speaker] = t
        if t - turn_start > 1.5 and rng.random() < 0.6:
            bc = make_backchannel(rng, styles[listener], voices[listener])
            lo = max(turn_start + 0.8, last_end[listener] + 0.1)
            hi = t - 0.3 - bc.duration
            if hi > lo:
                s = float(rng.uniform(lo, hi))
                phrases[listener].append(bc)
                starts[listener].append(s)
                last_end[listener] = s + bc.duration
        if t >= target_seconds - _TAIL:
            break
        gap = float(rng.uniform(0.15, 0.7)) if rng.random() < 0.75 else -float(rng.uniform(0.1, 0.4))
        t += gap
        speaker = listener
    duration = _frames_ceil(max(last_end) + _TAIL)
    return (layout_timeline(phrases[0], starts[0], duration),
            layout_timeline(phrases[1], starts[1], duration))


def render_channel(own: Timeline, other: Timeline | None, style: SpeakerStyle, emotion: tuple[str, int],
                   other_emotion: tuple[str, int] | None, audio_rng: np.random.Generator,
                   motion_rng: np.random.Generator, sample_rate: int = 16_000) -> Channel:
    """Audio and motion of one speaker.

    Args:
        own: this speaker's timeline.
        other: the other speaker's timeline (conversation) or None (monologue).
        style: this speaker.
        emotion: ``(emotion, intensity)`` of this speaker.
        other_emotion: the other's, or None.
        audio_rng: generator for the audio noise (consumed).
        motion_rng: generator for blinks, sway and drift (consumed; its use depends only on the
            number of frames, so the stochastic part is the same whatever ``other`` is).
        sample_rate: audio rate.

    Returns:
        A ``Channel``.
    """
    num_frames = int(round(own.duration * _FPS))
    if other is not None and abs(other.duration - own.duration) > 1e-9:
        raise ValueError(f"conversation channels differ in duration: {own.duration} vs {other.duration}")
    audio = synthesize(own, style, voice_change(*emotion), audio_rng, sample_rate)
    other_offset = face_offset(*other_emotion) if other_emotion is not None else np.zeros(56)
    parts = [
        motion_lib.articulation(own, style, num_frames, _FPS),
        motion_lib.prosody(own, style, num_frames, _FPS),
        motion_lib.listener_reaction(other, other_offset, style, num_frames, _FPS),
    ]
    noise, noise_mean = motion_lib.stochastic(motion_rng, style, num_frames, _FPS)
    m = motion_lib.compose(style, face_offset(*emotion), parts, noise, noise_mean)
    return Channel(audio, m.motion, m.oracle)
