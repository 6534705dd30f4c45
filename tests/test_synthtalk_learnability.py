"""SynthTalk is learnable where it should be and unpredictable where it should be: a closed-form
ridge regression from a +-5-frame window of log-mel features predicts the mouth on unseen speakers
(R^2 > 0.5) and fails on blinks (R^2 < 0.2)."""

from __future__ import annotations

import numpy as np
import pytest

from jaxtalk.data import synthtalk
from jaxtalk.layout import GROUPS

HALF_WINDOW = 5
N_MELS = 16
LAMBDAS = (1.0, 10.0, 100.0, 1000.0, 10000.0)


def window_features(corpus, clips: list[int]) -> np.ndarray:
    """Log-mel (100 fps) box-averaged to 25 fps, stacked over a +-5-frame window, per clip."""
    from jaxtalk.audio import log_mel

    # One log-mel pass over the split: every clip is a whole number of 640-sample motion frames,
    # so mel frames stay aligned with motion frames across clip boundaries.
    audio = np.concatenate([corpus.audio(i) for i in clips])
    frames = audio.size // 640
    mel = np.asarray(log_mel(audio, n_mels=N_MELS))[: 4 * frames]
    per_frame = mel.reshape(frames, 4, N_MELS).mean(1)  # average the 4 mel frames of a motion frame
    out, start = [], 0
    for i in clips:
        n = corpus.clips[i].num_frames
        f = per_frame[start:start + n]
        start += n
        idx = np.clip(np.arange(n)[:, None] + np.arange(-HALF_WINDOW, HALF_WINDOW + 1)[None, :], 0, n - 1)
        out.append(f[idx].reshape(n, -1))
    return np.concatenate(out)


def pooled_r2(y: np.ndarray, pred: np.ndarray) -> float:
    """1 - SSE / SST summed over dims (variance-weighted R^2 of a parameter group)."""
    return float(1.0 - ((y - pred) ** 2).sum() / ((y - y.mean(0)) ** 2).sum())


def ridge(x: np.ndarray, y: np.ndarray, lam: float) -> np.ndarray:
    return np.linalg.solve(x.T @ x + lam * np.eye(x.shape[1]), x.T @ y)


@pytest.fixture(scope="module")
def data():
    corpus = synthtalk.generate("tiny", seed=0)
    feats, motion = {}, {}
    for split in ("train", "val", "test"):
        clips = corpus.split(split)
        feats[split] = window_features(corpus, clips)
        motion[split] = np.concatenate([corpus.motion(i) for i in clips])
    mu, sd = feats["train"].mean(0), feats["train"].std(0) + 1e-6
    feats = {k: np.c_[(v - mu) / sd, np.ones(len(v))] for k, v in feats.items()}
    return feats, motion


def fit_and_score(data, group: str) -> float:
    """Ridge chosen on val (lambda), refitted on train+val, R^2 on the test speakers."""
    feats, motion = data
    idx = GROUPS[group]
    best = max(LAMBDAS, key=lambda lam: pooled_r2(
        motion["val"][:, idx], feats["val"] @ ridge(feats["train"], motion["train"][:, idx], lam)))
    x = np.concatenate([feats["train"], feats["val"]])
    y = np.concatenate([motion["train"][:, idx], motion["val"][:, idx]])
    return pooled_r2(motion["test"][:, idx], feats["test"] @ ridge(x, y, best))


def test_mouth_is_predictable_from_audio(data):
    # A probe that ignores the audio scores <= 0; the generator's own oracle scores about 0.9.
    assert fit_and_score(data, "mouth") > 0.5


def test_blinks_are_not_predictable_from_audio(data):
    assert fit_and_score(data, "blink") < 0.2


def test_ridge_and_r2_helpers_are_right():
    rng = np.random.default_rng(0)
    x = rng.normal(size=(200, 3))
    w = np.array([[1.0], [-2.0], [0.5]])
    y = x @ w
    np.testing.assert_allclose(ridge(x, y, 1e-9), w, atol=1e-6)
    assert pooled_r2(y, y) == 1.0
    assert abs(pooled_r2(y, np.repeat(y.mean(0, keepdims=True), 200, 0))) < 1e-12
