"""TIMAR streamed from raw audio is causal with every speech front end: log-mel and a wav2vec 2.0 port.

Audio -> per-turn features (each 1-s turn from its own audio, as ``jaxtalk prepare`` and
``jaxtalk sample``/``stream`` compute them) -> the turn-by-turn stream. Changing both speakers' audio
after turn t leaves the agent motion of turns <= t bitwise unchanged, and changes every later turn.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import perturbed

from jaxtalk.data.features import AudioFeatures
from jaxtalk.models.timar import TimarConfig, init_params
from jaxtalk.models.timar.streaming import stream
from jaxtalk.types import AUDIO_SAMPLE_RATE, MOTION_FPS


TURNS, CUT = 5, 2  # change the audio of turns 3 and 4




def _audio(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return (0.1 * rng.standard_normal(TURNS * AUDIO_SAMPLE_RATE)).astype(np.float32)


def _agent_motion(features: AudioFeatures, speech_dim: int, user: np.ndarray, agent: np.ndarray) -> np.ndarray:
    config = TimarConfig.small(width=32, num_layers=2, num_heads=2, head_width=32, speech_dim=speech_dim,
                               max_turns=4)
    params = perturbed(init_params(config, jax.random.key(0)), jax.random.key(1))
    us, as_ = features.turn_speech(user, TURNS), features.turn_speech(agent, TURNS)
    assert us.shape == (TURNS * MOTION_FPS, speech_dim)
    um = jnp.zeros((1, TURNS * MOTION_FPS, 56))
    out = stream(params, config, us[None], um, as_[None], jax.random.key(2), context=1, sample_steps=3)
    return np.asarray(out)[0]


def _assert_causal(features: AudioFeatures, speech_dim: int) -> None:
    user, agent = _audio(0), _audio(1)
    start = (CUT + 1) * AUDIO_SAMPLE_RATE
    user2, agent2 = user.copy(), agent.copy()
    user2[start:] = _audio(2)[start:]
    agent2[start:] = _audio(3)[start:]
    a = _agent_motion(features, speech_dim, user, agent)
    b = _agent_motion(features, speech_dim, user2, agent2)
    past = (CUT + 1) * MOTION_FPS
    np.testing.assert_array_equal(a[:past], b[:past])
    for turn in range(CUT + 1, TURNS):
        sl = slice(turn * MOTION_FPS, (turn + 1) * MOTION_FPS)
        assert np.abs(a[sl] - b[sl]).max() > 1e-5, f"turn {turn} did not see its own audio"


@pytest.mark.slow
def test_timar_stream_from_log_mel_audio_is_causal():
    _assert_causal(AudioFeatures(), 80)


def test_timar_stream_from_wav2vec2_features_is_causal(tmp_path):
    pytest.importorskip("safetensors")
    from jaxtalk.audio.encoders import EncoderConfig, Wav2Vec2Model, save_checkpoint

    enc = EncoderConfig.small("wav2vec2", "large")
    enc_params = jax.jit(Wav2Vec2Model(enc).init)(jax.random.key(0), jnp.zeros((1, enc.receptive_field)))["params"]
    path = save_checkpoint(tmp_path / "w2v", enc, enc_params, normalize=True)
    _assert_causal(AudioFeatures("wav2vec2", str(path)), enc.hidden_size)
