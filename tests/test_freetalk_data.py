"""FreeTalk data helpers: audio feature alignment, windows, mesh motion on remeshed faces."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.audio import log_mel
from jaxtalk.face import builtin_face
from jaxtalk.geometry.topology import make_variant
from jaxtalk.models.freetalk import data


def test_audio_features_stack_four_mel_frames_per_motion_frame():
    rng = np.random.default_rng(0)
    audio = rng.normal(size=16000 + 333).astype(np.float32) * 0.1
    feats = data.audio_features(audio, 25)
    assert feats.shape == (25, data.AUDIO_FEATURE_DIM) == (25, 320)
    mel = np.asarray(log_mel(audio))  # unpadded reference, 100 frames/s
    # Motion frame t holds mel frames 4t..4t+3; bucket padding must not change them.
    np.testing.assert_allclose(feats[7].reshape(4, 80), mel[28:32], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(feats[24].reshape(4, 80), mel[96:100], rtol=1e-5, atol=1e-5)
    # Asking for more frames than the audio covers repeats the last mel frame.
    longer = data.audio_features(audio, 27)
    np.testing.assert_allclose(longer[26].reshape(4, 80), np.repeat(mel[-1:], 4, 0), rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="num_frames"):
        data.audio_features(audio, 0)
    with pytest.raises(ValueError, match="non-empty"):
        data.audio_features(np.zeros((0,), np.float32), 3)


def test_displacement_stats_standardise_per_coordinate_with_a_floor():
    rng = np.random.default_rng(1)
    spread = np.ones((68, 3))
    spread[5, 2] = 1e-4  # a nearly static coordinate: floored at 0.2 x the mean std, not blown up
    disp = (0.002 + 0.003 * spread * rng.normal(size=(40, 16, 68, 3))).astype(np.float32)
    stats = data.DisplacementStats.fit(disp)
    flat = disp.reshape(-1, 68, 3).astype(np.float64)
    np.testing.assert_allclose(stats.mean, flat.mean(0), rtol=1e-4, atol=1e-8)
    raw_std = flat.std(0)
    np.testing.assert_allclose(stats.std[0], raw_std[0], rtol=1e-4)
    np.testing.assert_allclose(stats.std[5, 2], 0.2 * raw_std.mean(), rtol=1e-3)
    z = stats.normalize(disp)
    assert isinstance(z, np.ndarray) and z.shape == disp.shape
    np.testing.assert_allclose(z.reshape(-1, 68, 3)[:, 0].std(0), 1.0, rtol=1e-3)
    np.testing.assert_allclose(stats.denormalize(z), disp, rtol=1e-4, atol=1e-7)
    np.testing.assert_allclose(stats.denormalize(jnp.asarray(z)), disp, rtol=1e-4, atol=1e-7)
    assert stats.as_standardizer()["mean"].shape == (204,)
    with pytest.raises(ValueError, match="at least 2"):
        data.DisplacementStats.fit(disp[:1, :1])
    with pytest.raises(ValueError, match="NaN"):
        data.DisplacementStats.fit(np.full((2, 3, 68, 3), np.nan, np.float32))
    with pytest.raises(ValueError, match=r"shape \(\.\.\., frames, N, 3\)"):
        data.DisplacementStats.fit(np.zeros((68, 3), np.float32))


def test_mesh_motion_on_base_and_remeshed_faces():
    face = builtin_face(1, resolution="low")
    rng = np.random.default_rng(1)
    motion = np.zeros((3, 56), np.float32)
    motion[1, :50] = rng.normal(size=50)
    motion[2, 50] = 0.2  # open the jaw
    lms, verts, rest = data.mesh_motion(face, motion)
    np.testing.assert_allclose(rest, np.asarray(face.template), atol=1e-6)
    np.testing.assert_allclose(lms[0], 0.0, atol=1e-7)  # frame 0 is the neutral face
    np.testing.assert_allclose(verts[0], 0.0, atol=1e-7)
    assert np.abs(lms[2]).max() > 1e-3 and np.abs(verts[2]).max() > 1e-3
    np.testing.assert_allclose(lms + data.neutral_landmarks(face), np.asarray(face.landmarks_seq(jnp.asarray(motion))),
                               atol=1e-6)
    variant = make_variant(np.asarray(face.template), np.asarray(face.faces), "shuffled", seed=0)
    lms_s, verts_s, rest_s = data.mesh_motion(face, motion, variant)
    np.testing.assert_allclose(lms_s, lms)  # landmarks do not depend on the mesh
    np.testing.assert_allclose(rest_s, variant.vertices, atol=1e-6)
    np.testing.assert_allclose(variant.transfer(verts + rest[None]) - rest_s[None], verts_s, atol=1e-6)


def test_stm_windows_pad_vertices():
    lm = np.ones((10, 68, 3), np.float32)
    tracks = [(0, lm, np.ones((10, 5, 3), np.float32)), (1, 2 * lm, np.ones((10, 7, 3), np.float32))]
    ds = data.stm_windows(tracks, 8, window=4, hop=4)
    assert ds["vertices"].shape == (6, 4, 8, 3) and ds["landmarks"].shape == (6, 4, 68, 3)
    np.testing.assert_array_equal(ds["mesh"], [0, 0, 0, 1, 1, 1])
    assert np.all(ds["vertices"][0, :, 5:] == 0) and np.all(ds["vertices"][3, :, :7] == 1)
    with pytest.raises(ValueError, match="num_vertices"):
        data.stm_windows(tracks, 6)
    with pytest.raises(ValueError, match="window"):
        data.stm_windows(tracks, 8, window=11)


def test_landmark_motion_and_head_pose_removal():
    face = builtin_face(2, resolution="low")
    motion = np.zeros((4, 56), np.float32)
    motion[:, 53] = 0.1  # neck pitch only: a rigid head rotation
    motion[2, 50] = 0.15
    stripped = data.without_head_pose(motion)
    assert np.all(stripped[:, 53:] == 0) and stripped[2, 50] == np.float32(0.15) and motion[0, 53] != 0
    lms = data.landmark_motion(face, motion)
    assert np.abs(lms[0]).max() > 1e-3  # the rotation moves the landmarks
    lms_face = data.landmark_motion(face, stripped)
    np.testing.assert_allclose(lms_face[0], 0.0, atol=1e-7)  # no deformation without head pose
    np.testing.assert_allclose(lms_face, data.mesh_motion(face, stripped)[0], atol=1e-7)
    with pytest.raises(ValueError, match="motion must have shape"):
        data.landmark_motion(face, np.zeros((3, 55), np.float32))


def test_face_mesh_regions():
    base = data.face_mesh(0, "base")
    np.testing.assert_array_equal(base.region("lips"), np.asarray(base.face.regions["lips"]))
    shuffled = data.face_mesh(0, "shuffled")
    # A shuffled mesh is the same surface: its lip region is the base lip region, relabelled.
    lips_pos = {tuple(np.round(p, 6)) for p in base.vertices[base.region("lips")]}
    assert {tuple(np.round(p, 6)) for p in shuffled.vertices[shuffled.region("lips")]} == lips_pos
    with pytest.raises(ValueError, match="unknown region"):
        base.region("tail")


def test_audio_features_of_a_long_clip_in_pieces_equal_the_one_call_frames(monkeypatch):
    # Pieces of 50 mel frames (0.5 s) stand for the 60-s pieces of a long clip: 3 s cross 6 of them.
    x = (0.1 * np.random.default_rng(0).normal(size=16000 * 3 + 77)).astype(np.float32)
    from jaxtalk.audio import speech

    whole = speech.audio_features(x, 75)
    monkeypatch.setattr(speech, "_CHUNK_MEL_FRAMES", 50)
    np.testing.assert_allclose(speech.audio_features(x, 75), whole, atol=1e-5)
