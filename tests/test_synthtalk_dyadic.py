"""SynthTalk's long-range dyadic effects: delayed mimicry, the shared mood, turn arousal in the voice,
and the context ceiling they create (the past turns explain what the current one cannot)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import signal

from jaxtalk.data import synthtalk
from jaxtalk.data.synthtalk import dyadic, phones, script, speakers
from jaxtalk.data.synthtalk.ceiling import context_ceiling, window_starts
from jaxtalk.data.synthtalk.emotions import voice_change
from jaxtalk.data.synthtalk.speech import f0_contour, synthesize
from jaxtalk.layout import NECK_SLICE

FPS = 25


def _style(seed, **changes):
    return dataclasses.replace(speakers.sample_style(np.random.default_rng(seed)), **changes)


def _timeline(segments, duration, arousal=1.0):
    """Phrases of the open vowel, ``segments = [(start, length), ...]`` in seconds, at one arousal or
    one per phrase."""
    a = phones.PHONE_INDEX["a"]
    arousals = np.broadcast_to(np.asarray(arousal, np.float64), (len(segments),))
    phrases = [script.Phrase(np.array([a], np.int32), np.array([length]), np.array([0.5 * length]), np.array([1.0]),
                             arousal=float(g)) for (_, length), g in zip(segments, arousals)]
    return script.layout_timeline(phrases, [s for s, _ in segments], duration)


def test_mimicry_repeats_the_partners_head_movement_after_the_lag_times_the_gain():
    n = 400
    sa, sb = _style(0, mimic_lag=2.0, mimic_gain=0.6), _style(1, mimic_lag=3.0, mimic_gain=0.7)
    rng = np.random.default_rng(0)
    static_b = rng.normal(size=56)
    real_b = static_b + np.concatenate([np.zeros((n, 53)), rng.normal(size=(n, 3))], axis=1)
    real_a = np.zeros((n, 56))  # A's own head stays at its static pose (zero)
    mim_a, mim_b = dyadic.mimicry((real_a, real_b), (np.zeros(56), static_b), (sa, sb), FPS)
    dev_b = real_b[:, NECK_SLICE] - static_b[NECK_SLICE]
    la, lb = 50, 75
    np.testing.assert_array_equal(mim_a[:la], 0.0)
    np.testing.assert_array_equal(mim_b[: la + lb], 0.0)
    # Before B's echo arrives, A repeats B's own movement; B repeats A's repetition (an echo of an echo).
    np.testing.assert_allclose(mim_a[la: 2 * la + lb, NECK_SLICE], 0.6 * dev_b[: la + lb], rtol=1e-12)
    np.testing.assert_allclose(mim_b[la + lb:, NECK_SLICE], 0.7 * mim_a[la:-lb, NECK_SLICE], rtol=1e-12)
    np.testing.assert_allclose(mim_a[la:, NECK_SLICE], 0.6 * (dev_b + mim_b[:, NECK_SLICE])[:-la], rtol=1e-12)
    assert not mim_a[:, :NECK_SLICE.start].any() and not mim_b[:, :NECK_SLICE.start].any()
    off = dyadic.mimicry((real_a, real_b), (np.zeros(56), static_b), (sa, sb), FPS, dyadic.DyadicEffects(mimicry=0.0))
    assert not off[0].any() and not off[1].any()


def test_mimicry_at_a_frame_is_unchanged_by_the_partners_later_motion():
    n, cut = 500, 230
    sa, sb = _style(0, mimic_lag=2.4, mimic_gain=0.8), _style(1, mimic_lag=3.6, mimic_gain=0.5)
    rng = np.random.default_rng(1)
    real = (rng.normal(size=(n, 56)), rng.normal(size=(n, 56)))
    static = (np.zeros(56), np.zeros(56))
    ref = dyadic.mimicry(real, static, (sa, sb), FPS)
    later = real[1].copy()
    later[cut:] += rng.normal(size=(n - cut, 56))  # the partner's future changes
    alt = dyadic.mimicry((real[0], later), static, (sa, sb), FPS)
    np.testing.assert_array_equal(alt[0][: cut + 60], ref[0][: cut + 60])  # lag 2.4 s = 60 frames
    assert np.abs(alt[0][cut + 60:] - ref[0][cut + 60:]).max() > 0.1
    # B hears about its own change only through A's echo: lag 60 + 90 frames.
    np.testing.assert_array_equal(alt[1][: cut + 150], ref[1][: cut + 150])


def test_shared_mood_is_a_causal_average_of_both_voices_the_partners_one_frame_late():
    own = _timeline([(0.5, 2.0)], 12.0, arousal=1.5)
    other = _timeline([(3.0, 2.0), (8.0, 1.0)], 12.0, arousal=0.7)
    n = 300
    mood = dyadic.shared_mood(own, other, n, FPS, tau=5.0)
    t = np.arange(n) / FPS
    drive = np.where(own.speaking(t), np.log(1.5), 0.0) + np.concatenate(
        [[0.0], np.where(other.speaking(t), np.log(0.7), 0.0)[:-1]])
    pole = np.exp(-1.0 / (5.0 * FPS))
    expected = np.zeros(n)
    acc = 0.0
    for f in range(n):  # y_f = pole y_{f-1} + (1 - pole) x_f
        acc = pole * acc + (1 - pole) * drive[f]
        expected[f] = acc
    np.testing.assert_allclose(mood, expected, rtol=1e-10, atol=1e-15)
    assert mood[int(2.5 * FPS)] > 0.05 and mood[int(5.5 * FPS)] < mood[int(2.5 * FPS)]
    # Nothing of the partner's later speech reaches earlier frames.
    changed = _timeline([(3.0, 2.0), (6.0, 3.0)], 12.0, arousal=[0.7, 1.6])
    alt = dyadic.shared_mood(own, changed, n, FPS, tau=5.0)
    np.testing.assert_array_equal(alt[: 6 * FPS + 1], mood[: 6 * FPS + 1])
    assert not np.allclose(alt, mood)
    # Restricted to a window, the average starts from zero at the window's first frame.
    start = window_starts(n, 2)
    windowed = dyadic.shared_mood(own, other, n, FPS, tau=5.0, start=start)
    for f in (10, 80, 151, 299):
        s = start[f]
        ref = signal.lfilter([1 - pole], [1, -pole], drive[s: f + 1])[-1]
        np.testing.assert_allclose(windowed[f], ref, rtol=1e-10, atol=1e-15)
    with pytest.raises(ValueError, match="after the frame"):
        dyadic.shared_mood(own, other, n, FPS, start=np.full(n, 100))


def test_turn_arousal_scales_loudness_and_pitch_range():
    style = _style(3)
    voice = voice_change("neutral", 1)
    calm, aroused = _timeline([(0.2, 1.0)], 1.6, 1.0), _timeline([(0.2, 1.0)], 1.6, 1.5)
    rms = [np.sqrt(np.mean(synthesize(tl, style, voice, np.random.default_rng(0)).astype(np.float64) ** 2))
           for tl in (calm, aroused)]
    assert 1.4 < rms[1] / rms[0] < 1.6
    t = np.linspace(0.25, 1.15, 200)
    ranges = [np.ptp(f0_contour(tl, style, voice, t)) for tl in (calm, aroused)]
    np.testing.assert_allclose(ranges[1] / ranges[0], 1.5, rtol=1e-6)


@pytest.mark.slow
def test_seven_past_turns_raise_the_true_event_ceiling_on_neck_and_upper_face_by_0p15():
    # Motion only (no audio is synthesised): 40 train and 16 test conversations of 30 s, both roles.
    spec = synthtalk.SizeSpec((24, 0, 8, 0), 1, 5.0, (40, 0, 16, 0), 30.0, 32, 1e9, lazy=True)
    corpus = synthtalk.generate(spec, 0)

    def sides(split):
        return [s for a, b in corpus.conversations(split) for s in ((a, b), (b, a))]

    train, test = sides("train"), sides("test")
    none, seven = context_ceiling(corpus, train, test, 0), context_ceiling(corpus, train, test, 7)
    assert seven["neck"] - none["neck"] >= 0.15, (none, seven)
    assert seven["upper_face"] - none["upper_face"] >= 0.15, (none, seven)
    # Monologues carry neither effect: a monologue's motion is its speech's alone.
    assert not any(corpus.clips[i].is_conversation for i in corpus.split("train")[:1])


def test_a_size_spec_with_other_effects_changes_only_the_conversations_by_exactly_those_effects():
    from jaxtalk.data.synthtalk import corpus as corpus_module
    from jaxtalk.data.synthtalk.conversation import conversation_motion

    base = synthtalk.SizeSpec((2, 0, 0, 0), 1, 3.0, (1, 0, 0, 0), 8.0, 32, 1e9, lazy=True)
    strong = dyadic.DyadicEffects(mimicry=1.2, mood=16.0, mood_tau=10.0)
    plain, control = synthtalk.generate(base, 0), synthtalk.generate(dataclasses.replace(base, effects=strong), 0)
    monologue = next(i for i, c in enumerate(plain.clips) if not c.is_conversation)
    np.testing.assert_array_equal(plain.motion_without_audio(monologue)[0], control.motion_without_audio(monologue)[0])
    a, b = plain.conversations("train")[0]
    assert not np.allclose(plain.motion_without_audio(a)[0], control.motion_without_audio(a)[0])
    # The control corpus's conversation is the generator's motion with exactly those strengths.
    unit = control._units[control.clips[a].unit]
    timelines, styles, emotions, _, motion_rngs = corpus_module._unit_args(0, control.clips[a].unit, unit, control.clips)
    expected = conversation_motion(timelines, styles, emotions, motion_rngs, strong)
    for i in (a, b):
        np.testing.assert_array_equal(control.motion_without_audio(i)[0], expected[unit.clips.index(i)].motion)


def test_emotion_gain_scales_each_monologue_emotion_offset_and_nothing_else():
    from jaxtalk.data.synthtalk.emotions import face_offset
    from jaxtalk.data.synthtalk.motion import JAW_OPEN_INDEX

    base = synthtalk.SizeSpec((6, 0, 0, 0), 1, 3.0, (0, 0, 0, 0), 8.0, 32, 1e9, lazy=True)
    plain, control = synthtalk.generate(base, 0), synthtalk.generate(dataclasses.replace(base, emotion_gain=3.0), 0)
    assert plain.key != control.key  # a custom spec is cached under its own content's name
    emotional = [i for i, c in enumerate(plain.clips) if c.emotion != "neutral"]
    assert emotional, "the test needs a clip with an emotion"
    for i in emotional:
        clip = plain.clips[i]
        offset = face_offset(clip.emotion, clip.intensity)
        other = np.arange(offset.size) != JAW_OPEN_INDEX  # the jaw opening is clipped after the sum
        for a, b in zip(plain.motion_without_audio(i), control.motion_without_audio(i)):
            np.testing.assert_allclose((b - a)[:, other], np.broadcast_to(2.0 * offset[other], a[:, other].shape),
                                       atol=2e-6)


@pytest.mark.parametrize("gain", [-1.0, float("nan"), float("inf")])
def test_a_negative_or_non_finite_emotion_gain_is_refused_naming_the_field(gain):
    base = synthtalk.SizeSpec((2, 0, 0, 0), 1, 3.0, (0, 0, 0, 0), 8.0, 32, 1e9, lazy=True)
    with pytest.raises(ValueError, match="emotion_gain"):
        synthtalk.generate(dataclasses.replace(base, emotion_gain=gain), 0)
