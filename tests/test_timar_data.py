"""TIMAR data pipeline on hand-built inputs: per-turn speech features, role swap, normalisation, windows."""

from __future__ import annotations

import types

import numpy as np
import pytest

from jaxtalk.audio import log_mel, resample_features
from jaxtalk.models.timar.data import (
    SPEECH_DIM,
    Conversation,
    Normalizer,
    conversations,
    fit_normalizer,
    monologues,
    turn_speech_features,
    windows,
)

SR = 16000


def _tone(seconds: float, freq: float, seed: int = 0) -> np.ndarray:
    t = np.arange(int(seconds * SR)) / SR
    noise = np.random.default_rng(seed).normal(0, 1e-3, t.shape)
    return (0.3 * np.sin(2 * np.pi * freq * t) + noise).astype(np.float32)


def test_turn_features_are_each_turns_own_log_mel_resampled_to_25_fps():
    audio = _tone(3.0, 220.0)
    feats = turn_speech_features(audio, 3)
    assert feats.shape == (75, SPEECH_DIM) and feats.dtype == np.float32
    # Turn k is the log-mel of its own 1-s chunk, linearly resampled from 100 to 25 frames/s.
    for k in range(3):
        mel = log_mel(audio[k * SR : (k + 1) * SR], SR, n_mels=SPEECH_DIM)
        ref = np.asarray(resample_features(mel, 100, 25, num_frames=25))
        np.testing.assert_allclose(feats[k * 25 : (k + 1) * 25], ref, rtol=1e-4, atol=1e-4)


def test_turn_features_expose_no_future_audio():
    # Per-chunk tokenisation: changing turn 2's audio leaves turns 0 and 1 bit-identical.
    audio = _tone(3.0, 220.0)
    other = audio.copy()
    other[2 * SR :] = _tone(1.0, 880.0, seed=1)
    a, b = turn_speech_features(audio, 3), turn_speech_features(other, 3)
    np.testing.assert_array_equal(a[:50], b[:50])
    assert np.abs(a[50:] - b[50:]).max() > 1.0
    # Audio beyond the requested turns is ignored.
    np.testing.assert_array_equal(turn_speech_features(audio[: 2 * SR + 100], 2), a[:50])


def test_turn_features_reject_bad_audio():
    with pytest.raises(ValueError, match="1-D"):
        turn_speech_features(np.zeros((2, SR), np.float32), 1)
    with pytest.raises(ValueError, match="fewer than 2 turns"):
        turn_speech_features(np.zeros(SR + 5, np.float32), 2)
    with pytest.raises(ValueError, match="num_turns"):
        turn_speech_features(np.zeros(SR, np.float32), 0)
    bad = np.zeros(SR, np.float32)
    bad[7] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        turn_speech_features(bad, 1)


def _fake_corpus(frames=(60, 53), seconds=3.0):
    """Two clips forming one conversation: motion[i, d] = 1000 * clip + i + d / 100 (hand-checkable)."""
    clips = [types.SimpleNamespace(num_frames=n) for n in frames]
    motion = [1000.0 * c + np.arange(n)[:, None] + np.arange(56)[None] / 100.0 for c, n in enumerate(frames)]
    audio = [_tone(seconds, 200.0 + 300.0 * c, seed=c) for c in range(len(frames))]
    return types.SimpleNamespace(
        clips=clips,
        conversations=lambda split: [(0, 1)] if split == "train" else [],
        audio=lambda c: audio[c],
        motion=lambda c: motion[c].astype(np.float32),
        oracle=lambda c: (motion[c] + 0.5).astype(np.float32),
    )


def test_conversations_give_both_roles_cut_to_whole_common_turns():
    corpus = _fake_corpus()
    convs = conversations(corpus, "train")
    assert len(convs) == 2
    a, b = convs
    # min(60, 53) = 53 frames -> 2 whole turns of 25 = 50 frames for both sides.
    assert a.num_frames == b.num_frames == 50
    assert (a.agent_clip, a.user_clip, b.agent_clip, b.user_clip) == (0, 1, 1, 0)
    np.testing.assert_array_equal(a.agent_motion, corpus.motion(0)[:50])
    np.testing.assert_array_equal(a.user_motion, corpus.motion(1)[:50])
    np.testing.assert_array_equal(a.agent_oracle, corpus.oracle(0)[:50])
    assert not np.array_equal(a.agent_oracle, a.agent_motion)
    # The swapped role is the same data with agent and user exchanged.
    np.testing.assert_array_equal(b.agent_motion, a.user_motion)
    np.testing.assert_array_equal(b.user_speech, a.agent_speech)
    np.testing.assert_array_equal(a.agent_speech, turn_speech_features(corpus.audio(0), 2))
    with pytest.raises(ValueError, match="no conversations"):
        conversations(corpus, "test")


def _conv(motion: np.ndarray, speech: np.ndarray, user_shift: float = 100.0) -> Conversation:
    return Conversation(
        agent_speech=speech, agent_motion=motion, user_speech=speech + user_shift, user_motion=motion + user_shift,
        agent_oracle=motion, agent_clip=0, user_clip=1,
    )


def test_fit_normalizer_matches_hand_statistics_and_floors_constant_channels():
    m1 = np.zeros((4, 56), np.float32)
    m1[:, 0] = [1, 2, 3, 4]
    m2 = np.zeros((2, 56), np.float32)
    m2[:, 0] = [5, 6]
    s1 = np.full((4, SPEECH_DIM), 2.0, np.float32)
    s2 = np.full((2, SPEECH_DIM), 8.0, np.float32)
    norm = fit_normalizer([_conv(m1, s1), _conv(m2, s2)])
    # Agent streams only (the user side of a conversation is the agent of its swapped copy).
    assert norm.motion_mean[0] == pytest.approx(3.5)
    assert norm.motion_std[0] == pytest.approx(np.std([1, 2, 3, 4, 5, 6]))
    # A constant channel gets the floor: 1e-3 x the mean raw std over channels (the shared
    # fit_standardizer's relative floor), not 0.
    assert norm.motion_std[1] == pytest.approx(1e-3 * np.std([1, 2, 3, 4, 5, 6]) / 56, rel=1e-5)
    np.testing.assert_allclose(norm.motion(m1)[:, 1], 0.0)  # finite, no division by zero
    assert norm.speech_mean[0] == pytest.approx(4.0)  # (4 * 2 + 2 * 8) / 6
    assert norm.speech_std[0] == pytest.approx(np.std([2, 2, 2, 2, 8, 8]))
    with pytest.raises(ValueError, match="at least one"):
        fit_normalizer([])


def test_normalizer_round_trips_and_serialises():
    rng = np.random.default_rng(0)
    norm = Normalizer(
        rng.normal(size=SPEECH_DIM).astype(np.float32), rng.uniform(0.5, 2, SPEECH_DIM).astype(np.float32),
        rng.normal(size=56).astype(np.float32), rng.uniform(0.1, 2, 56).astype(np.float32),
    )
    x = rng.normal(size=(3, 7, 56)).astype(np.float32)
    z = norm.motion(x)
    np.testing.assert_allclose(z, (x - norm.motion_mean) / norm.motion_std, rtol=1e-6)
    np.testing.assert_allclose(norm.unmotion(z), x, rtol=1e-5, atol=1e-5)
    s = rng.normal(size=(5, SPEECH_DIM))
    np.testing.assert_allclose(norm.speech(s), (s - norm.speech_mean) / norm.speech_std, rtol=1e-5)
    back = Normalizer.from_dict(norm.to_dict())
    for name in ("speech_mean", "speech_std", "motion_mean", "motion_std"):
        np.testing.assert_array_equal(getattr(back, name), getattr(norm, name))


def test_windows_cut_whole_turns_with_the_stride_and_normalise():
    f = 5
    t = 4 * f  # 4 turns
    motion = np.tile(np.arange(t, dtype=np.float32)[:, None], (1, 56))
    speech = np.tile(np.arange(t, dtype=np.float32)[:, None], (1, SPEECH_DIM))
    conv = _conv(motion, speech)
    norm = Normalizer(np.zeros(SPEECH_DIM, np.float32), np.ones(SPEECH_DIM, np.float32),
                      np.full(56, 1.0, np.float32), np.full(56, 2.0, np.float32))
    w = windows([conv], norm, num_turns=2, stride_turns=1, frames_per_turn=f)
    assert sorted(w) == ["agent_motion", "agent_speech", "user_motion", "user_speech"]
    # Starts at turns 0, 1, 2: (4 - 2) / 1 + 1 = 3 windows of 10 frames.
    assert w["agent_motion"].shape == (3, 10, 56) and w["user_speech"].shape == (3, 10, SPEECH_DIM)
    for i in range(3):
        frames = np.arange(i * f, i * f + 2 * f, dtype=np.float32)
        np.testing.assert_array_equal(w["agent_motion"][i, :, 3], (frames - 1.0) / 2.0)
        np.testing.assert_array_equal(w["user_motion"][i, :, 3], (frames + 100.0 - 1.0) / 2.0)
        np.testing.assert_array_equal(w["agent_speech"][i, :, 0], frames)
    w2 = windows([conv], norm, num_turns=2, stride_turns=2, frames_per_turn=f)
    assert w2["agent_motion"].shape[0] == 2  # starts at turns 0 and 2
    np.testing.assert_array_equal(w2["agent_motion"][1], w["agent_motion"][2])
    with pytest.raises(ValueError, match="no conversation has 5 whole turns"):
        windows([conv], norm, num_turns=5, frames_per_turn=f)
    with pytest.raises(ValueError, match=">= 1"):
        windows([conv], norm, num_turns=0, frames_per_turn=f)


def test_monologues_get_a_silent_still_user_and_whole_turns():
    frames = (55, 30, 20)  # clip 2 is shorter than a turn: skipped
    clips = [types.SimpleNamespace(num_frames=n, is_conversation=False) for n in frames]
    clips.append(types.SimpleNamespace(num_frames=50, is_conversation=True))  # not a monologue
    motion = [np.full((n, 56), float(c + 1), np.float32) for c, n in enumerate(frames)] + [np.zeros((50, 56), np.float32)]
    audio = [_tone(n / 25.0, 300.0, seed=c) for c, n in enumerate(frames)] + [np.zeros(32000, np.float32)]
    corpus = types.SimpleNamespace(
        clips=clips, split=lambda name: [0, 1, 2, 3] if name == "train" else [3],
        audio=lambda c: audio[c], motion=lambda c: motion[c], oracle=lambda c: motion[c] * 2.0,
    )
    convs = monologues(corpus, "train")
    assert [c.agent_clip for c in convs] == [0, 1] and all(c.user_clip == -1 for c in convs)
    assert [c.num_frames for c in convs] == [50, 25]
    # The user's pose is one constant for the split: the frame-weighted mean of its monologues.
    still = (55 * 1.0 + 30 * 2.0 + 20 * 3.0) / 105
    for c in convs:
        np.testing.assert_allclose(c.user_motion, still, rtol=1e-6)
        np.testing.assert_array_equal(c.user_speech,
                                      turn_speech_features(np.zeros(c.num_frames * 640, np.float32), c.num_frames // 25))
    np.testing.assert_array_equal(convs[0].agent_speech, turn_speech_features(audio[0], 2))
    np.testing.assert_array_equal(convs[1].agent_oracle, motion[1][:25] * 2.0)
    with pytest.raises(ValueError, match="no monologue clips"):
        monologues(corpus, "test")
