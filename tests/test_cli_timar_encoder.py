"""TIMAR's ``paper`` preset end to end on wav2vec 2.0 features from a checkpoint on disk: ``jaxtalk
prepare --features wav2vec2:PATH`` -> ``jaxtalk train timar --preset paper`` (1024-d speech input) ->
``jaxtalk sample`` on a WAV, which computes the same per-turn features from the run's front end.

The checkpoint is a randomly initialised wav2vec 2.0 "large"-style port with the real model's 1024-d
hidden states (2 layers, so it builds in seconds); the TIMAR model keeps the paper's widths with one
encoder layer and one head block, so a step runs on a CPU.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from helpers import cli_ok as _ok

pytest.importorskip("safetensors")
# wav2vec 2.0's conv stack (hop 320 samples: 50 frames/s), narrow: long clips stay cheap to encode.
REAL_HOP = dict(conv_dim=(16,) * 7, conv_kernel=(10, 3, 3, 3, 3, 2, 2), conv_stride=(5, 2, 2, 2, 2, 2, 2))


def _keep_conversations(folder, splits):
    """Prune a generic-layout export to its first two-sided conversation in each split (fewer clips
    to encode; TIMAR trains on conversations)."""
    import csv

    with open(folder / "metadata.csv", newline="") as handle:
        rows = list(csv.DictReader(handle))
    keep = set()
    for split in splits:
        first = next(r for r in rows if r["split"] == split and r["partner"])
        keep |= {first["clip"], first["partner"]}
    for row in rows:
        if row["clip"] not in keep:
            for path in folder.glob(f"{row['clip']}.*"):
                path.unlink()
    with open(folder / "metadata.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(r for r in rows if r["clip"] in keep)


@pytest.mark.slow
def test_paper_timar_trains_and_samples_on_1024_d_wav2vec2_features(tmp_path, synthtalk_tiny):
    from jaxtalk.audio.encoders import EncoderConfig, Wav2Vec2Model, save_checkpoint
    from jaxtalk.runs import RunRecord
    from jaxtalk.data.formats import read_npz

    enc = EncoderConfig.small("wav2vec2", "large", hidden_size=1024, num_hidden_layers=1, num_attention_heads=8,
                              num_conv_pos_embedding_groups=8, **REAL_HOP)
    params = jax.jit(Wav2Vec2Model(enc).init)(jax.random.key(0), jnp.zeros((1, enc.receptive_field)))["params"]
    ckpt = save_checkpoint(tmp_path / "wav2vec2-large", enc, params, normalize=True)

    clips = tmp_path / "clips"
    _ok(["data", "--size", "tiny", "--cache-dir", synthtalk_tiny._cache_dir, "--out", str(clips)])  # the session's corpus
    _keep_conversations(clips, ("train", "val", "test"))
    _ok(["prepare", str(tmp_path / "clips"), "--out", str(tmp_path / "prepared"), "--features", f"wav2vec2:{ckpt}",
         "--no-progress"])
    run = tmp_path / "run"
    _ok(["train", "timar", "--data", str(tmp_path / "prepared"), "--preset", "paper", "--set", "num_layers=1",
         "--set", "head_blocks=1", "--set", "max_turns=2", "--set", "batch_size=2", "--steps", "1", "--no-progress",
         "--out", str(run)])
    record = RunRecord.load(run)
    assert record.preset == "paper" and record.config["speech_dim"] == 1024 and record.config["width"] == 1024

    wav = next((tmp_path / "clips").rglob("*.wav"))
    out = tmp_path / "agent.npz"
    _ok(["sample", str(run), str(wav), "--out", str(out)])
    motion = read_npz(out, load_audio=False).params
    assert motion.shape[1] == 56 and motion.shape[0] >= 25 and np.isfinite(motion).all()
