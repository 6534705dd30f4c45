"""``prepare``'s per-turn speech features use no future audio (TIMAR's streaming path reads them)."""

from __future__ import annotations

import numpy as np

from jaxtalk.data.features import SAMPLES_PER_FRAME, TURN_BLOCK, TURN_FRAMES, AudioFeatures


def test_turn_speech_of_past_turns_is_bitwise_unchanged_when_later_audio_changes():
    rng = np.random.default_rng(0)
    turns = TURN_BLOCK + 3  # crosses a block boundary: blocks must not leak either
    spt = TURN_FRAMES * SAMPLES_PER_FRAME
    audio = (0.1 * rng.standard_normal(turns * spt)).astype(np.float32)
    t = TURN_BLOCK - 1  # change everything after turn t
    future = audio.copy()
    future[(t + 1) * spt:] = (0.1 * rng.standard_normal(future.size - (t + 1) * spt)).astype(np.float32)
    features = AudioFeatures()
    a, b = features.turn_speech(audio, turns), features.turn_speech(future, turns)
    assert a.shape == (turns * TURN_FRAMES, 80)
    past = slice(0, (t + 1) * TURN_FRAMES)
    np.testing.assert_array_equal(a[past], b[past])
    # The test is not vacuous: every later turn changes, on both sides of the block boundary.
    for k in range(t + 1, turns):
        assert not np.array_equal(a[k * TURN_FRAMES:(k + 1) * TURN_FRAMES], b[k * TURN_FRAMES:(k + 1) * TURN_FRAMES])
