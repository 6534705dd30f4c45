"""glTF export: the .glb read back by glTF's own rules (``GlbAnimation``) rebuilds the face model's vertices
(built-in face and a FLAME-like model with regressed joints, five joints and pose correctives), the
vertex basis meets its bound with the fewest components, and bad input is refused clearly."""

from __future__ import annotations

import numpy as np
import pygltflib
import pytest
import soundfile
from typer.testing import CliRunner

from jaxtalk.cli import app
from jaxtalk.data.formats import MotionClip, save_npz
from jaxtalk.export import GlbAnimation, export_face_model, export_vertex_sequence, one_sided_targets, vertex_basis
from jaxtalk.face import LinearFaceModel, builtin_face

runner = CliRunner()


def head_motion(frames: int, seed: int = 0) -> np.ndarray:
    """Expression, an opening jaw and a turning head: every part of the 56-d vector moves."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / 25.0
    params = np.zeros((frames, 56), np.float32)
    params[:, :50] = 0.8 * rng.normal(size=(frames, 50))
    params[:, 50] = 0.15 * (1 + np.sin(2 * np.pi * t))
    params[:, 51:53] = 0.02 * rng.normal(size=(frames, 2))
    params[:, 53:] = 0.3 * np.sin(2 * np.pi * 0.5 * t)[:, None] * np.array([0.5, 1.0, -0.3])
    return params


def flame_like_model(seed: int = 0) -> LinearFaceModel:
    """Five joints as FLAME's (global, neck, jaw, eyes), joints regressed from the expression, pose
    correctives, and skinning weights on all five joints of every vertex (two JOINTS sets)."""
    rng = np.random.default_rng(seed)
    verts = 80
    template = rng.normal(scale=0.05, size=(verts, 3))
    weights = rng.random((verts, 5)) ** 2
    return LinearFaceModel(
        template=template, faces=rng.integers(0, verts, size=(120, 3)).astype(np.int32),
        exp_basis=0.002 * rng.normal(size=(verts, 3, 50)), joints=rng.normal(scale=0.05, size=(5, 3)),
        joint_exp_basis=0.002 * rng.normal(size=(5, 3, 50)), weights=weights / weights.sum(1, keepdims=True),
        pose_basis=0.01 * rng.normal(size=(verts, 3, 36)), landmark_vertices=np.zeros((68, 3), np.int32),
        landmark_bary=np.full((68, 3), 1 / 3), regions={}, parents=(-1, 0, 1, 1, 1), neck_joint=1, jaw_joint=2,
        name="flame-like")


def relative_error(got: np.ndarray, want: np.ndarray) -> float:
    return float(np.abs(got - want).max() / np.abs(want).max())


@pytest.mark.parametrize("model", ["builtin", "flame-like"])
def test_glb_rebuilds_the_face_models_vertices_at_first_middle_and_last_frame(tmp_path, model):
    face = builtin_face(0) if model == "builtin" else flame_like_model()
    params = head_motion(60)
    summary = export_face_model(face, params, tmp_path / "a.glb")
    glb = GlbAnimation(tmp_path / "a.glb")
    want = np.asarray(face.vertices_seq(params), np.float64)
    assert glb.num_frames == 60 and np.allclose(glb.times, np.arange(60) / 25.0)
    for frame in (0, 30, 59):
        assert relative_error(glb.vertices(frame), want[frame]) < 1e-5, frame
    # One-sided morph weights in [0, 1], from which the expression coefficients come back.
    weights = glb.morph_weights()
    assert weights.min() >= 0 and weights.max() == 1
    np.testing.assert_allclose(glb.component_weights()[:, :50], params[:, :50], atol=1e-6)
    assert glb.target_names[:3] == ["exp_00+", "exp_00-", "exp_01+"]
    assert summary.morph_targets == 2 * (50 if model == "builtin" else 50 + 36)
    assert summary.joints == face.num_joints and summary.nodes == face.num_joints + 1


def test_builtin_face_export_animates_morph_weights_and_the_two_joint_rotations_only(tmp_path):
    summary = export_face_model(builtin_face(0), head_motion(10), tmp_path / "a.glb")
    gltf = pygltflib.GLTF2().load_binary(str(tmp_path / "a.glb"))
    paths = sorted((gltf.nodes[c.target.node].name, c.target.path) for c in gltf.animations[0].channels)
    assert paths == [("face", "weights"), ("jaw", "rotation"), ("neck", "rotation")]
    assert summary.channels == 3
    assert [n.name for n in gltf.nodes] == ["face", "neck", "jaw"]
    assert gltf.skins[0].joints == [1, 2] and gltf.nodes[1].children == [2]


def test_a_still_rest_pose_exports_the_neutral_mesh(tmp_path):
    face = builtin_face(0)
    export_face_model(face, np.zeros((3, 56), np.float32), tmp_path / "rest.glb")
    glb = GlbAnimation(tmp_path / "rest.glb")
    np.testing.assert_allclose(glb.vertices(1), np.asarray(face.template), atol=1e-7)


def test_one_sided_targets_are_exact_at_keyframes_and_along_linear_interpolation():
    rng = np.random.default_rng(0)
    targets, weights = rng.normal(size=(3, 7, 3)), rng.normal(size=(5, 3))
    weights[:, 2] = np.abs(weights[:, 2])  # a component that is never negative
    sided_targets, sided, scales = one_sided_targets(targets, weights)
    assert sided.min() >= 0 and sided.max(axis=0).tolist() == [1.0, 1.0, 1.0, 1.0, 1.0, 0.0]
    for a in (0.0, 0.3, 1.0):  # between keyframes 1 and 2 (where signs change)
        w = (1 - a) * weights[1] + a * weights[2]
        s = (1 - a) * sided[1] + a * sided[2]
        np.testing.assert_allclose(np.einsum("k,kvc->vc", s, sided_targets), np.einsum("k,kvc->vc", w, targets),
                                   atol=1e-12)
    np.testing.assert_allclose((sided * scales).reshape(5, 3, 2).sum(-1),
                               weights, atol=1e-12)


def test_vertex_basis_meets_its_bound_with_the_fewest_components():
    rng = np.random.default_rng(0)
    frames, verts = 40, 300
    # Rank 6 motion plus 0.02 mm noise: 6 components leave only the noise, 5 leave far more than 0.1 mm.
    basis = rng.normal(size=(6, verts, 3)) * 1e-3
    x = rng.normal(scale=0.05, size=(verts, 3)) + np.einsum("tk,kvc->tvc", rng.normal(size=(frames, 6)), basis)
    x = x + rng.normal(scale=2e-5 / np.sqrt(3), size=x.shape)
    mean, targets, weights, error = vertex_basis(x, 1e-4)
    # Measured as a .glb stores it: one-sided targets and weights in float32.
    sided_targets, sided_weights, _ = one_sided_targets(targets, weights)
    rebuilt = mean + np.einsum("tk,kvc->tvc", sided_weights.astype(np.float32).astype(np.float64),
                               sided_targets.astype(np.float32))
    measured = np.sqrt(((rebuilt - x) ** 2).sum(-1)).max()
    assert targets.shape[0] == 6 and measured <= 1e-4 and error == pytest.approx(measured)
    # The stored weights are one-sided, each target's reaching 1 (PCA coefficients are centred, so every
    # component has both signs; its scales carry the rest).
    assert sided_weights.min() >= 0 and np.all(sided_weights.max(axis=0) == pytest.approx(1.0))
    _, fewer, _, _ = vertex_basis(x, 1e-2)
    assert fewer.shape[0] < 6


def test_vertex_sequence_glb_holds_every_frame_within_the_bound(tmp_path):
    face = builtin_face(0, resolution="low")
    verts = np.asarray(face.vertices_seq(head_motion(50)), np.float32)
    summary = export_vertex_sequence(verts, np.asarray(face.faces), tmp_path / "v.glb", max_error=5e-5)
    glb = GlbAnimation(tmp_path / "v.glb")
    worst = max(np.linalg.norm(glb.vertices(f) - verts[f], axis=1).max() for f in range(50))
    assert worst <= 5e-5 and summary.max_error == pytest.approx(worst, rel=1e-3)
    assert summary.morph_targets < 2 * 50 and summary.joints == 0


@pytest.mark.parametrize("params, message", [
    (np.zeros((5, 55), np.float32), "shape"),
    (np.full((5, 56), np.nan, np.float32), "NaN"),
    (np.zeros((0, 56), np.float32), "zero frames"),
])
def test_bad_parameters_are_refused(tmp_path, params, message):
    with pytest.raises(ValueError, match=message):
        export_face_model(builtin_face(0), params, tmp_path / "a.glb")
    assert not (tmp_path / "a.glb").exists()


def test_bad_vertex_sequences_are_refused(tmp_path):
    face = builtin_face(0, resolution="low")
    verts = np.asarray(face.vertices_seq(head_motion(4)), np.float32)
    tri = np.asarray(face.faces)
    with pytest.raises(ValueError, match="not the mesh"):
        export_vertex_sequence(verts[:, :500], tri, tmp_path / "v.glb")
    with pytest.raises(ValueError, match="NaN"):
        export_vertex_sequence(np.where(np.arange(verts.shape[1])[None, :, None] == 7, np.nan, verts), tri,
                               tmp_path / "v.glb")
    with pytest.raises(ValueError, match="frames >= 1"):
        export_vertex_sequence(verts[:0], tri, tmp_path / "v.glb")
    with pytest.raises(ValueError, match="must end in"):
        export_vertex_sequence(verts, tri, tmp_path / "v.gltf")
    with pytest.raises(ValueError, match="positive distance"):
        export_vertex_sequence(verts, tri, tmp_path / "v.glb", max_error=0.0)


def test_cli_exports_params_with_their_audio_beside_and_refuses_bad_files(tmp_path):
    params = head_motion(50)
    audio = (0.1 * np.sin(np.arange(2 * 16000) / 7)).astype(np.float32)
    save_npz(tmp_path / "clip.npz", MotionClip(name="clip", fps=25, params=params, audio=audio))
    # A missing folder is created, as every command that writes does.
    result = runner.invoke(app, ["export", str(tmp_path / "clip.npz"), "--out", str(tmp_path / "out" / "clip.glb")])
    assert result.exit_code == 0, result.output
    assert "100 morph targets, 2 joints, 3 nodes, 50 frames at 25 fps" in result.output
    wav, rate = soundfile.read(tmp_path / "out" / "clip.glb.wav", dtype="float32")
    assert rate == 16000 and wav.shape == audio.shape and np.abs(wav - audio).max() < 1e-4

    np.savez(tmp_path / "wide.npz", params=np.zeros((5, 57), np.float32), fps=25)
    np.savez(tmp_path / "nan.npz", params=np.full((5, 56), np.nan, np.float32), fps=25)
    np.save(tmp_path / "verts.npy", np.zeros((5, 1234, 3), np.float32))
    for bad, message in (("wide.npz", "(frames, 56)"), ("nan.npz", "NaN"), ("verts.npy", "not a built-in face mesh"),
                         ("missing.npz", "file not found")):
        result = runner.invoke(app, ["export", str(tmp_path / bad), "--out", str(tmp_path / "out" / "bad.glb")])
        assert result.exit_code == 2 and message in result.output, (bad, result.output)
    assert not (tmp_path / "out" / "bad.glb").exists()


def test_cli_exports_a_vertex_sequence_on_the_mesh_file_it_was_animated_on(tmp_path):
    import trimesh

    face = builtin_face(0, resolution="low")
    verts = np.asarray(face.vertices_seq(head_motion(20)), np.float32)
    trimesh.Trimesh(np.asarray(face.template), np.asarray(face.faces), process=False).export(tmp_path / "mesh.ply")
    np.save(tmp_path / "verts.npy", verts + 0.5)  # not a built-in face any more: needs its mesh
    result = runner.invoke(app, ["export", str(tmp_path / "verts.npy"), "--faces", str(tmp_path / "mesh.ply"),
                                 "--out", str(tmp_path / "v.glb"), "--max-error-mm", "0.05"])
    assert result.exit_code == 0, result.output
    assert "vertex basis" in result.output and "no audio" in result.output
    glb = GlbAnimation(tmp_path / "v.glb")
    assert np.linalg.norm(glb.vertices(19) - (verts[19] + 0.5), axis=1).max() <= 5e-5
    np.save(tmp_path / "short.npy", verts[:, :100])
    result = runner.invoke(app, ["export", str(tmp_path / "short.npy"), "--faces", str(tmp_path / "mesh.ply"),
                                 "--out", str(tmp_path / "s.glb")])
    assert result.exit_code == 2 and "not the mesh these vertices belong to" in result.output
