"""Monologues and two-speaker conversations: who says what when, and each channel's audio + motion.

A conversation alternates turns of 1-3 phrases, each turn spoken with its own arousal (louder and
with a wider pitch range, or quieter and flatter). The next turn starts after a pause or, one time
in four, overlaps the end of the current one; during longer turns the listener often backchannels
("mhm"). Each speaker has their own channel (audio with only their voice, as in DualTalk) and their
own motion, which combines their speech with their causal reactions to the other: nods and mirrored
emotion within a second or two (``motion.listener_reaction``), and delayed mimicry and a shared mood
over several seconds (``dyadic``).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxtalk.data.synthtalk import dyadic, espeak_voice
from jaxtalk.data.synthtalk import motion as motion_lib
from jaxtalk.data.synthtalk.emotions import VoiceChange, face_offset, voice_change
from jaxtalk.data.synthtalk.script import (
    Phrase,
    Timeline,
    layout_timeline,
    make_backchannel,
    make_phrase,
)
from jaxtalk.data.synthtalk.speakers import SpeakerStyle
from jaxtalk.data.synthtalk.speech import synthesize

__all__ = ["AROUSAL_SPREAD", "Channel", "monologue_timeline", "conversation_timelines", "render_channel",
           "monologue_motion", "conversation_motion", "render_conversation"]

_FPS = 25
_LEAD_IN = (0.25, 0.45)   # s of silence before the first phrase
_TAIL = 0.4               # s of silence after the last one
# A turn's arousal is exp(N(0, AROUSAL_SPREAD^2)), clipped to [0.6, 1.6]: its loudness and pitch-range
# factor, and what drives the shared mood (``dyadic``).
AROUSAL_SPREAD = 0.3
_AROUSAL_RANGE = (0.6, 1.6)


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


def _make_phrase(rng: np.random.Generator, style: SpeakerStyle, voice: VoiceChange,
                 arousal: float | None = None) -> Phrase:
    # An eSpeak speaker's phrase is timed by eSpeak, whose pitch range depends on the arousal.
    if style.espeak is not None:
        return espeak_voice.make_phrase(rng, style, voice, 1.0 if arousal is None else arousal)
    p = make_phrase(rng, style, voice)
    return p if arousal is None else dataclasses.replace(p, arousal=arousal)


def _make_backchannel(rng: np.random.Generator, style: SpeakerStyle, voice: VoiceChange) -> Phrase:
    if style.espeak is not None:
        return espeak_voice.make_backchannel(rng, style, voice)
    return make_backchannel(rng, style, voice)


def monologue_timeline(rng: np.random.Generator, style: SpeakerStyle, emotion: str, intensity: int,
                       target_seconds: float) -> Timeline:
    """Phrases separated by 0.25-0.7 s pauses until ``target_seconds`` is reached."""
    voice = voice_change(emotion, intensity)
    phrases: list[Phrase] = []
    starts: list[float] = []
    t = float(rng.uniform(*_LEAD_IN))
    while True:
        p = _make_phrase(rng, style, voice)
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
        arousal = float(np.clip(np.exp(rng.normal(0.0, AROUSAL_SPREAD)), *_AROUSAL_RANGE))
        for k in range(int(rng.integers(1, 4))):
            if k:
                t += float(rng.uniform(0.15, 0.4))
            p = _make_phrase(rng, styles[speaker], voices[speaker], arousal)
            phrases[speaker].append(p)
            starts[speaker].append(t)
            t += p.duration
        last_end[speaker] = t
        if t - turn_start > 1.5 and rng.random() < 0.6:
            bc = _make_backchannel(rng, styles[listener], voices[listener])
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


def monologue_motion(own: Timeline, style: SpeakerStyle, emotion: tuple[str, int],
                     motion_rng: np.random.Generator, emotion_gain: float = 1.0) -> motion_lib.MotionParts:
    """Motion and oracle of a monologue (no audio).

    Args:
        own: the speaker's timeline.
        style: the speaker.
        emotion: ``(emotion, intensity)``.
        motion_rng: generator for blinks, sway and drift (consumed; its use depends only on the
            number of frames).
        emotion_gain: the emotion's face offset is multiplied by this (1: SynthTalk's own; a control
            corpus in which the emotion and its intensity change the face by a known, larger amount
            raises it). The voice is unchanged.
    """
    num_frames = int(round(own.duration * _FPS))
    parts = [
        motion_lib.articulation(own, style, num_frames, _FPS),
        motion_lib.prosody(own, style, num_frames, _FPS),
    ]
    noise, noise_mean = motion_lib.stochastic(motion_rng, style, num_frames, _FPS)
    return motion_lib.compose(style, emotion_gain * face_offset(*emotion), parts, noise, noise_mean)


def render_channel(own: Timeline, style: SpeakerStyle, emotion: tuple[str, int], audio_rng: np.random.Generator,
                   motion_rng: np.random.Generator, sample_rate: int = 16_000, emotion_gain: float = 1.0) -> Channel:
    """Audio and motion of a monologue (conversations: :func:`render_conversation`).

    Args:
        own, style, emotion, motion_rng, emotion_gain: see :func:`monologue_motion`.
        audio_rng: generator for the audio noise (consumed).
        sample_rate: audio rate.

    Returns:
        A ``Channel``.
    """
    audio = synthesize(own, style, voice_change(*emotion), audio_rng, sample_rate)
    m = monologue_motion(own, style, emotion, motion_rng, emotion_gain)
    return Channel(audio, m.motion, m.oracle)


def conversation_motion(
    timelines: tuple[Timeline, Timeline], styles: tuple[SpeakerStyle, SpeakerStyle],
    emotions: tuple[tuple[str, int], tuple[str, int]], motion_rngs: tuple[np.random.Generator, np.random.Generator],
    effects: dyadic.DyadicEffects = dyadic.DEFAULT_EFFECTS, emotion_gain: float = 1.0,
) -> tuple[motion_lib.MotionParts, motion_lib.MotionParts]:
    """Both speakers' motion and oracle in a conversation (no audio).

    Each speaker's motion is their speech's (articulation, prosody), their reaction to the partner
    within a second or two (``motion.listener_reaction``), the shared mood's face and the delayed
    mimicry of the partner's head (``dyadic``), their emotion, rest pose and stochastic parts.

    Args:
        timelines, styles, emotions: both speakers' (``(emotion, intensity)`` each).
        motion_rngs: each speaker's generator for blinks, sway and drift (consumed as in a monologue
            of the same length).
        effects: strengths of the long-range effects.
        emotion_gain: see :func:`monologue_motion`.

    Returns:
        Both speakers' ``MotionParts``.
    """
    num_frames = int(round(timelines[0].duration * _FPS))
    if abs(timelines[1].duration - timelines[0].duration) > 1e-9:
        raise ValueError(f"conversation channels differ in duration: {timelines[0].duration} vs {timelines[1].duration}")
    offsets = [emotion_gain * face_offset(*e) for e in emotions]
    parts, noise, noise_mean, realised = [], [], [], []
    for s in (0, 1):
        o = 1 - s
        mood = dyadic.shared_mood(timelines[s], timelines[o], num_frames, _FPS, tau=effects.mood_tau)
        p = [
            motion_lib.articulation(timelines[s], styles[s], num_frames, _FPS),
            motion_lib.prosody(timelines[s], styles[s], num_frames, _FPS),
            motion_lib.listener_reaction(timelines[o], offsets[o], styles[s], num_frames, _FPS),
            dyadic.mood_offset(mood, effects),
        ]
        z, z_mean = motion_lib.stochastic(motion_rngs[s], styles[s], num_frames, _FPS)
        parts.append(p)
        noise.append(z)
        noise_mean.append(z_mean)
        realised.append(styles[s].rest[None, :] + offsets[s][None, :] + sum(p) + z)
    static = (styles[0].rest + offsets[0], styles[1].rest + offsets[1])
    mimic = dyadic.mimicry((realised[0], realised[1]), static, styles, _FPS, effects)
    return tuple(motion_lib.compose(styles[s], offsets[s], parts[s] + [mimic[s]], noise[s], noise_mean[s])
                 for s in (0, 1))


def render_conversation(
    timelines: tuple[Timeline, Timeline], styles: tuple[SpeakerStyle, SpeakerStyle],
    emotions: tuple[tuple[str, int], tuple[str, int]], audio_rngs: tuple[np.random.Generator, np.random.Generator],
    motion_rngs: tuple[np.random.Generator, np.random.Generator], sample_rate: int = 16_000,
    effects: dyadic.DyadicEffects = dyadic.DEFAULT_EFFECTS, emotion_gain: float = 1.0,
) -> tuple[Channel, Channel]:
    """Both channels of a conversation: each speaker's audio (their voice only) and motion.

    Args:
        timelines, styles, emotions, motion_rngs, effects, emotion_gain: see :func:`conversation_motion`.
        audio_rngs: each speaker's generator for the audio noise (consumed).
        sample_rate: audio rate.
    """
    motions = conversation_motion(timelines, styles, emotions, motion_rngs, effects, emotion_gain)
    return tuple(Channel(synthesize(timelines[s], styles[s], voice_change(*emotions[s]), audio_rngs[s], sample_rate),
                         motions[s].motion, motions[s].oracle) for s in (0, 1))
