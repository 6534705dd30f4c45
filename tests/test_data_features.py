"""``prepare``'s per-turn speech features use no future audio (TIMAR's streaming path reads them), and
the recording-level waveform normalisation of offline evaluation is the public loader's."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from jaxtalk.data.features import (SAMPLES_PER_FRAME, TURN_BLOCK, TURN_FRAMES, AudioFeatures, normalize_recording,
                                   parse_audio_features)


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


# ------------------------------------------------------------------- recording-level normalisation

# DualTalk's demo clips (real conversations) live outside the repository; the test skips without them.
DEMO_CLIPS = Path(__file__).resolve().parents[2] / "shared" / "data" / "dualtalk_demo"
REAL_RECORDING = DEMO_CLIPS / "UbjUDM1MiGE_sub_video_72_speaker1.wav"


def _hf_zero_mean_unit_var_norm(x: np.ndarray) -> np.ndarray:
    # Hugging Face's Wav2Vec2FeatureExtractor.zero_mean_unit_var_norm for one unpadded row, as written
    # there: float32 input, numpy mean and variance, 1e-7 added to the variance.
    x = np.asarray(x, np.float32)
    return (x - x.mean()) / np.sqrt(x.var() + 1e-7)


def _recordings() -> list[tuple[str, np.ndarray]]:
    rng = np.random.default_rng(3)
    t = np.arange(3 * 16_000) / 16_000
    made = (0.3 * np.sin(2 * np.pi * 180 * t) * (t > 1) + 0.02 * rng.standard_normal(t.size) + 0.05).astype(np.float32)
    out = [("tone with an offset", made)]
    if REAL_RECORDING.exists():
        from jaxtalk.audio import load_audio

        out.append(("real DualTalk recording", np.asarray(load_audio(REAL_RECORDING, 16_000), np.float32)))
    return out


@pytest.mark.parametrize("name, audio", _recordings(), ids=lambda v: v if isinstance(v, str) else "")
def test_recording_normaliser_equals_the_reference_processor(name, audio):
    ours = normalize_recording(audio)
    np.testing.assert_allclose(ours, _hf_zero_mean_unit_var_norm(audio), atol=1e-6, rtol=0)
    if importlib.util.find_spec("transformers") is not None:
        from transformers import Wav2Vec2FeatureExtractor

        extractor = Wav2Vec2FeatureExtractor(do_normalize=True, return_attention_mask=False)
        ref = extractor(audio, sampling_rate=16_000, return_tensors="np").input_values[0]
        np.testing.assert_allclose(ours, ref, atol=1e-6, rtol=0)
    assert abs(float(ours.mean())) < 1e-4 and abs(float(ours.std()) - 1) < 1e-3


def test_recording_level_turn_features_encode_each_turn_of_the_normalised_recording(tmp_path):
    pytest.importorskip("safetensors")
    import dataclasses

    import jax
    import jax.numpy as jnp

    from jaxtalk.audio.encoders import EncoderConfig, Wav2Vec2Model, save_checkpoint

    enc = EncoderConfig.small("wav2vec2", "large")
    enc_params = jax.jit(Wav2Vec2Model(enc).init)(jax.random.key(0), jnp.zeros((1, enc.receptive_field)))["params"]
    path = str(save_checkpoint(tmp_path / "w2v", enc, enc_params, normalize=True))
    audio = _recordings()[0][1]
    turns = 3
    spt = TURN_FRAMES * SAMPLES_PER_FRAME
    whole = parse_audio_features(f"wav2vec2+recording:{path}")
    assert whole.waveform_norm == "recording" and whole.spec == f"wav2vec2+recording:{path}"
    assert whole.encoder == parse_audio_features(f"wav2vec2:{path}").encoder
    got = whole.turn_speech(audio, turns)
    # By hand: the public loader's order, the recording normalised once, each turn then encoded raw.
    raw = dataclasses.replace(whole._encoder, normalize=False)
    normed = _hf_zero_mean_unit_var_norm(audio)
    want = np.concatenate([np.asarray(raw.interpolated_features(normed[k * spt:(k + 1) * spt], num_frames=TURN_FRAMES))
                           for k in range(turns)])
    np.testing.assert_allclose(got, want, atol=1e-6)
    # Per turn, the first turn (silence plus an offset) is normalised on its own: other features.
    per_turn = AudioFeatures("wav2vec2", path).turn_speech(audio, turns)
    assert np.abs(per_turn[:TURN_FRAMES] - got[:TURN_FRAMES]).max() > 1e-3


@pytest.mark.parametrize("spec, message", [
    ("wav2vec2+global:{path}", "unknown waveform normalisation 'global'"),
    ("logmel+recording:{path}", "log-mel features have no waveform normalisation"),
])
def test_a_bad_waveform_normalisation_is_refused(tmp_path, spec, message):
    from helpers import encoder_folder

    folder = encoder_folder(tmp_path / "w2v", "wav2vec2")
    with pytest.raises(ValueError, match=message):
        parse_audio_features(spec.format(path=folder))
