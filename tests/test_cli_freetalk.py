"""``jaxtalk sample RUN_ATS AUDIO --stm RUN_STM --mesh FACE``: FreeTalk from the command line onto a mesh
file a user brings, ``jaxtalk render`` of the result with the mesh file's triangles, user errors, and
the ATS ``paper`` preset on 768-d HuBERT features from a checkpoint on disk.

The ATS run is the session's, trained two steps through the CLI on SynthTalk tiny (``trained_ats`` in
conftest); the STM run is at its initial parameters (``stm_run``). The checks are on the wiring:
shapes, units, file order, finite values and the one-line errors.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import soundfile as sf
from scipy.spatial.transform import Rotation

from helpers import TINY_TRAIN_ARGS, cli_ok as _ok, cli_error as _user_error

ATS_SMALL = [*TINY_TRAIN_ARGS["ats"], "--set", "batch_size=2"]


@pytest.fixture(scope="module")
def ats_run(trained_ats):
    return trained_ats.dir


@pytest.fixture(scope="module")
def files(tmp_path_factory, synthtalk_tiny):
    """A 1.2-s 44.1 kHz speech WAV and a face in millimetres, rotated and shifted, as PLY and OBJ."""
    import trimesh

    from jaxtalk.face import builtin_face

    root = tmp_path_factory.mktemp("freetalk_files")
    clip = synthtalk_tiny.split("test")[0]
    audio = synthtalk_tiny.audio(clip)[: int(16000 * 1.2)]
    from jaxtalk.audio import resample_audio

    sf.write(root / "speech.wav", resample_audio(audio, 16000, 44100), 44100)
    face = builtin_face(3, resolution="low")
    rotation = Rotation.from_euler("xyz", [20, -70, 10], degrees=True).as_matrix()
    vertices = 1000.0 * (np.asarray(face.template, np.float64) @ rotation.T + [0.3, -1.2, 0.5])
    mesh = trimesh.Trimesh(vertices, np.asarray(face.faces), process=False)
    mesh.export(root / "face.ply")
    mesh.export(root / "face.obj")
    trimesh.PointCloud(vertices).export(root / "cloud.ply")
    return {"wav": root / "speech.wav", "ply": root / "face.ply", "obj": root / "face.obj",
            "cloud": root / "cloud.ply", "vertices": vertices, "faces": np.asarray(face.faces), "root": root}


@pytest.mark.slow
def test_sample_animates_a_mesh_file_in_its_own_units_and_renders_it(ats_run, stm_run, files):
    out = files["root"] / "anim.npy"
    output = _ok(["sample", ats_run, files["wav"], "--stm", stm_run, "--mesh", files["ply"], "--emotion", "happy",
                  "--intensity", "2.5", "--out", out])
    assert "units mm" in output and "aligned to the template by icp" in output
    verts = np.load(out)
    assert verts.shape == (30, files["vertices"].shape[0], 3) and np.isfinite(verts).all()
    # In the file's own frame and units: every frame stays within a few cm (tens of mm) of the input.
    assert np.abs(verts - files["vertices"]).max() < 50.0
    assert f"jaxtalk render {out} --faces {files['ply']}" in output
    gif = files["root"] / "anim.gif"
    _ok(["render", out, "--faces", files["obj"], "--out", gif, "--size", "96"])
    assert gif.stat().st_size > 0


@pytest.mark.slow
def test_sample_onto_an_obj_kit_keeps_its_vertices(ats_run, stm_run, files):
    """An OBJ as face kits ship it (materials, groups, a UV and a normal per corner, quads): the animation
    has the file's ``v`` records, in count and order, and renders with the file as --faces."""
    from jaxtalk.testing.faces import write_face_kit_obj

    kit = files["root"] / "kit.obj"
    write_face_kit_obj(kit, files["vertices"], files["faces"])
    out = files["root"] / "kit.npy"
    output = _ok(["sample", ats_run, files["wav"], "--stm", stm_run, "--mesh", kit, "--out", out])
    assert f"{files['vertices'].shape[0]} vertices" in output
    verts = np.load(out)
    assert verts.shape == (30, files["vertices"].shape[0], 3) and np.isfinite(verts).all()
    # In the file's order: every vertex stays within a few cm (tens of mm) of its own `v` record.
    assert np.abs(verts - files["vertices"]).max() < 50.0
    _ok(["render", out, "--faces", kit, "--out", files["root"] / "kit.gif", "--size", "64"])


@pytest.mark.slow
def test_sample_animates_mediapipes_canonical_face_in_centimetres(ats_run, stm_run, files):
    """A new user's command on MediaPipe's canonical face (468 vertices, cm, a real face mask): it
    aligns (through MediaPipe's own face, at about the template's size) and animates in centimetres."""
    from jaxtalk.geometry.canonical import MEDIAPIPE_FACE_FILE, load_mesh

    out = files["root"] / "mediapipe.npy"
    output = _ok(["sample", ats_run, files["wav"], "--stm", stm_run, "--mesh", MEDIAPIPE_FACE_FILE, "--emotion",
                  "happy", "--intensity", "2", "--out", out])
    assert "468 vertices" in output and "units cm" in output
    assert "aligned to the template by icp via MediaPipe's canonical face (scale 0.9" in output
    vertices, _ = load_mesh(MEDIAPIPE_FACE_FILE)
    verts = np.load(out)
    assert verts.shape == (30, 468, 3) and np.isfinite(verts).all()
    assert 0 < np.abs(verts - vertices).max() < 5.0  # centimetres: the face moves, by less than 5 cm


@pytest.mark.slow
def test_sample_onto_a_mesh_user_errors_are_one_line(ats_run, stm_run, files, tmp_path):
    base = ["sample", ats_run, files["wav"], "--stm", stm_run, "--mesh"]
    _user_error([*base, files["ply"], "--emotion", "elated"], "--emotion elated: not an emotion of this run")
    _user_error([*base, files["ply"], "--intensity", "4"], "intensity must lie in [1, 3]")
    _user_error([*base, files["cloud"]], "is a point cloud")
    _user_error([*base, tmp_path / "missing.obj"], "mesh file not found")
    _user_error([*base, files["ply"], "--units", "inch"], "--units must be one of m, dm, cm, mm, um, got 'inch'")
    _user_error([*base, files["ply"], "--units", "m"], "check the units")
    _user_error([*base, files["ply"], "--out", tmp_path / "x.npz"], "must end in .npy")
    _user_error([*base, files["ply"], "--cfg-scale", "2"], "--cfg-scale: not an option of a FreeTalk run")
    _user_error([*base, files["ply"], "--temperature", "0.5"], "--temperature: not an option of a FreeTalk run")
    _user_error(["sample", ats_run, files["wav"], "--stm", stm_run], "needs both --stm RUN_STM and --mesh FILE")
    _user_error(["sample", ats_run, files["wav"]], "sample it onto a mesh with --stm RUN_STM --mesh FILE")
    _user_error(["sample", stm_run, files["wav"], "--stm", stm_run, "--mesh", files["ply"]], "is a stm run")
    _user_error(["render", files["root"] / "none.npy", "--faces", files["ply"]], "not found")


def test_render_refuses_a_mesh_file_of_another_vertex_count(files, tmp_path):
    np.save(tmp_path / "v.npy", np.zeros((2, 10, 3), np.float32))
    _user_error(["render", tmp_path / "v.npy", "--faces", files["ply"], "--out", tmp_path / "x.gif"],
                "not the mesh these vertices belong to")


@pytest.mark.slow
def test_paper_ats_trains_on_768_d_hubert_features_and_animates_a_mesh(tmp_path, stm_run, files, synthtalk_tiny):
    """``prepare --features hubert:PATH`` -> ``train ats --preset paper`` (768-d input, displacement
    scale 1 as the preset says) -> ``sample`` onto a mesh through the run's own front end. The HuBERT
    port is randomly initialised with the real base model's 768-d hidden states and one layer; ATS keeps
    the paper's widths with one decoder layer so that a step runs on a CPU."""
    pytest.importorskip("safetensors")
    import jax
    import jax.numpy as jnp

    from jaxtalk.audio.encoders import EncoderConfig, Wav2Vec2Model, save_checkpoint
    from jaxtalk.runs import RunRecord

    enc = EncoderConfig.small("hubert", "base", hidden_size=768, num_hidden_layers=1, num_attention_heads=12,
                              intermediate_size=256, conv_dim=(16,) * 7, conv_kernel=(10, 3, 3, 3, 3, 2, 2),
                              conv_stride=(5, 2, 2, 2, 2, 2, 2), num_conv_pos_embedding_groups=16)
    params = jax.jit(Wav2Vec2Model(enc).init)(jax.random.key(0), jnp.zeros((1, enc.receptive_field)))["params"]
    ckpt = save_checkpoint(tmp_path / "hubert-base", enc, params, normalize=False)
    clips = tmp_path / "clips"
    _ok(["data", "--size", "tiny", "--cache-dir", synthtalk_tiny._cache_dir, "--out", clips])  # the session's corpus
    for extra in sorted(clips.glob("*.wav"))[12:]:  # a dozen clips are plenty for one step
        for path in clips.glob(f"{extra.stem}.*"):
            path.unlink()
    _ok(["prepare", clips, "--out", tmp_path / "prepared", "--features", f"hubert:{ckpt}", "--no-progress"])
    run = tmp_path / "run"
    _ok(["train", "ats", "--data", tmp_path / "prepared", "--preset", "paper", "--set", "num_layers=1",
         "--set", "max_frames=25", "--set", "window_frames=25", "--set", "batch_size=2", "--steps", "1",
         "--no-progress", "--out", run])
    record = RunRecord.load(run)
    assert record.preset == "paper" and record.config["speech_dim"] == 768 and record.config["width"] == 512
    assert record.config["displacement_scale"] == 1.0
    out = tmp_path / "anim.npy"
    _ok(["sample", run, files["wav"], "--stm", stm_run, "--mesh", files["obj"], "--sample-steps", "2", "--out", out])
    verts = np.load(out)
    assert verts.shape == (30, files["vertices"].shape[0], 3) and np.isfinite(verts).all()
    assert Path(record.data["path"]).is_dir()


def test_training_ats_on_labels_outside_its_vocabulary_is_a_user_error(prepared_tiny, tmp_path):
    _user_error(["train", "ats", "--data", "synthtalk:tiny", "--cache-dir", prepared_tiny.root.parent, "--steps", "1",
                 *ATS_SMALL, "--set", "emotions=mead", "--no-progress", "--out", tmp_path / "run"],
                "outside the model's vocabulary (neutral, angry, contempt")
