"""TIMAR animating speech for ``jaxtalk sample`` and ``jaxtalk stream`` (the spec's
:class:`~jaxtalk.runs.SpeechAnimator`).

The agent's audio becomes per-turn speech features with the front end the run's data was prepared
with (its ``features.json``), standardised with the run's normaliser; the partner is ``--partner``'s
audio or silence, and still at the training mean pose. Only whole turns are animated: the audio is cut
to them. Offline and streamed are the same computation, turn by turn with the run's context
(:func:`~jaxtalk.models.timar.streaming.stream`); streamed, each turn is timed.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from jaxtalk.models.timar.config import TimarConfig
from jaxtalk.runs import SpeechConditions
from jaxtalk.types import AUDIO_SAMPLE_RATE, MOTION_FPS

__all__ = ["read_speech", "sample_speech", "stream_speech", "step_frames"]


def step_frames(config: TimarConfig) -> int:
    """Frames TIMAR animates at a time: a turn."""
    return config.frames_per_turn


def _turn_samples(config: TimarConfig) -> int:
    """16-kHz audio samples a turn spans."""
    return AUDIO_SAMPLE_RATE * config.frames_per_turn // MOTION_FPS


def _whole_turns(config: TimarConfig, audio: np.ndarray, name: str) -> int:
    """The whole turns in 16-kHz ``audio`` (``name`` in the message when there is none)."""
    samples = _turn_samples(config)
    turns = audio.shape[0] // samples
    if turns < 1:
        raise ValueError(f"{name} is {audio.shape[0] / AUDIO_SAMPLE_RATE:.2f} s long; TIMAR needs at "
                         f"least one {samples / AUDIO_SAMPLE_RATE:g}-s turn")
    return turns


def read_speech(run: Any, path: str | Path) -> np.ndarray:
    """An audio file's 16-kHz waveform, refused when it is shorter than one turn."""
    from jaxtalk.audio import load_audio

    audio = load_audio(path)
    _whole_turns(run.config, audio, repr(str(path)))
    return audio


def _context(run: Any) -> int:
    """The past turns a stream attends to: as many as the run's training windows held, less one."""
    return max(run.record.extra.get("num_turns", run.config.max_turns) - 1, 0)


def _streams(run: Any, audio: np.ndarray, partner: np.ndarray | None) -> tuple[dict[str, np.ndarray], np.ndarray, int]:
    """Normalised ``(1, T, .)`` streams from the agent's 16-kHz ``audio`` and the partner's (None:
    silence), that audio cut to whole turns, and the turns."""
    from jaxtalk.data.features import parse_audio_features
    from jaxtalk.models.timar.data import Normalizer
    from jaxtalk.types import PARAM_DIM

    config = run.config
    norm = Normalizer.from_dict(run.record.extra["normalizer"])
    turns = _whole_turns(config, audio, "the audio")
    samples = turns * _turn_samples(config)
    if partner is not None:
        partner = np.pad(partner, (0, max(samples - partner.shape[0], 0)))
    else:
        partner = np.zeros(samples, np.float32)
    frames = turns * config.frames_per_turn
    features = parse_audio_features(run.features()["audio"])
    streams = {
        "user_speech": norm.speech(features.turn_speech(partner, turns)),
        "agent_speech": norm.speech(features.turn_speech(audio, turns)),
        # A still partner at the training mean pose is zero in the normalised space.
        "user_motion": np.zeros((frames, PARAM_DIM), np.float32),
    }
    return {k: v[None] for k, v in streams.items()}, audio[:samples], turns


def sample_speech(run: Any, speech: np.ndarray, conditions: SpeechConditions) -> tuple[np.ndarray, np.ndarray]:
    """``(params (T, 56), the audio animated)``: the whole turns of the agent's 16-kHz ``speech`` streamed in one
    call."""
    import jax

    from jaxtalk.models.timar.data import Normalizer
    from jaxtalk.models.timar.streaming import stream

    key = jax.random.key(conditions.seed)
    streams, audio, _ = _streams(run, speech, conditions.partner)
    motion = stream(run.params, run.config, streams["user_speech"], streams["user_motion"], streams["agent_speech"],
                    key, context=_context(run), cfg_scale=conditions.cfg_scale, sample_steps=conditions.sample_steps,
                    temperature=conditions.temperature)
    motion = Normalizer.from_dict(run.record.extra["normalizer"]).unmotion(motion)
    return np.asarray(motion, np.float32)[0], audio


def stream_speech(run: Any, speech: np.ndarray, conditions: SpeechConditions, on_chunk: Callable[..., None],
                  echo: Callable[[str], None]) -> tuple[np.ndarray, np.ndarray, float]:
    """``(params (T, 56), the audio animated, seconds per turn)``: the whole turns of the agent's 16-kHz
    ``speech`` streamed turn by turn, each timed."""
    import jax

    from jaxtalk.models.timar.data import Normalizer
    from jaxtalk.models.timar.streaming import init_stream, stream_step

    key = jax.random.key(conditions.seed)
    config = run.config
    streams, audio, turns = _streams(run, speech, conditions.partner)
    f = config.frames_per_turn
    state = jax.device_put(init_stream(config, key, context=_context(run)), jax.local_devices()[0])
    outs = []
    for i in range(turns):
        sl = slice(i * f, (i + 1) * f)
        t0 = time.perf_counter()
        state, out = stream_step(run.params, config, state, streams["user_speech"][:, sl],
                                 streams["user_motion"][:, sl], streams["agent_speech"][:, sl],
                                 cfg_scale=conditions.cfg_scale, sample_steps=conditions.sample_steps,
                                 temperature=conditions.temperature)
        outs.append(np.asarray(jax.block_until_ready(out))[0])
        on_chunk(turns, time.perf_counter() - t0, f / MOTION_FPS)
    params = Normalizer.from_dict(run.record.extra["normalizer"]).unmotion(np.concatenate(outs))
    return np.asarray(params, np.float32), audio, f / MOTION_FPS
