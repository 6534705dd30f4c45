"""``jaxtalk demo --audio FILE``: the report's speech-sync row for the user's recording, checked by hand.

The demo trains one step of TokTalk small on the session's SynthTalk tiny (its corpus and prepared copy
linked into the demo's cache, so nothing is generated or prepared again), without the sweep or videos.
"""

from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.slow
def test_demo_report_measures_the_jaw_on_the_users_audio(synthtalk_tiny, prepared_tiny, tmp_path):
    import soundfile as sf

    from jaxtalk.audio import load_audio
    from jaxtalk.demo import DemoOptions, run_demo
    from jaxtalk.metrics.speech_sync import voice_activity

    cache = tmp_path / "cache"
    cache.mkdir()
    (cache / "synthtalk").symlink_to(prepared_tiny.root.parent.parent / "synthtalk_tiny", target_is_directory=True)
    (cache / prepared_tiny.root.name).symlink_to(prepared_tiny.root, target_is_directory=True)
    # A voice-like recording at another rate: syllables of a 220-Hz tone between quiet stretches.
    t = np.arange(int(2.4 * 22050)) / 22050
    env = (np.sin(2 * np.pi * 3 * t) > 0) & (t > 0.4) & (t < 2.0)
    hiss = 1e-3 * np.random.default_rng(0).normal(size=t.shape)
    sf.write(tmp_path / "me.wav", (0.3 * np.sin(2 * np.pi * 220 * t) * env + hiss).astype(np.float32), 22050)

    options = DemoOptions(out_dir=tmp_path / "demo", size="tiny", train_steps=1, sweep=False, render=False,
                          progress=False, audio=tmp_path / "me.wav", cache_dir=cache)
    result = run_demo(options, echo=lambda line: None)
    row = result.user_sync
    assert list(row) == ["audio", "frames", "speech_frames", "jaw_silence", "jaw_speech", "rest_jaw",
                         "style_rest_jaw", "loudness_pred_corr", "loudness_pred_best_lag"]
    # By hand from the written parameters and the audio at 16 kHz: dBFS per 640-sample frame.
    jaw = np.load(tmp_path / "demo" / "me_params.npz")["params56"][:, 50].astype(np.float64)
    audio = load_audio(tmp_path / "me.wav").astype(np.float64)
    db = np.array([10 * np.log10(max(np.mean(audio[640 * k:640 * (k + 1)] ** 2), 1e-10)) for k in range(60)])
    speech = voice_activity(db)
    assert row["audio"] == "me.wav" and row["frames"] == jaw.shape[0] == 60
    assert row["speech_frames"] == speech.sum() and 0 < speech.sum() < 60
    assert row["jaw_silence"] == pytest.approx(jaw[~speech].mean(), abs=1e-6)
    assert row["jaw_speech"] == pytest.approx(jaw[speech].mean(), abs=1e-6)
    assert row["loudness_pred_corr"] == pytest.approx(np.corrcoef(jaw, db)[0, 1], abs=1e-5)
    assert -8 <= row["loudness_pred_best_lag"] <= 8 and np.isfinite(row["rest_jaw"])
    # The style clip's rest: the 5th percentile of the demo's style clip's jaw (its first 4 style windows).
    from jaxtalk.data import synthtalk
    from jaxtalk.demo import _pick_clips, model_config

    corpus = synthtalk.generate("tiny", 0, cache_dir=cache / "synthtalk")
    ref = np.asarray(corpus.motion(_pick_clips(corpus)[1]))[: 4 * model_config().style_frames, 50]
    assert row["style_rest_jaw"] == pytest.approx(np.percentile(ref, 5))
    report = (tmp_path / "demo" / "report.md").read_text()
    lines = report[report.index("## Your audio"):].split("\n")
    start = lines.index("| " + " | ".join(row) + " |")
    cells = lines[start + 2]
    assert cells.split(" | ")[0] == "| me.wav" and f"{row['rest_jaw']:.4g}" in cells
