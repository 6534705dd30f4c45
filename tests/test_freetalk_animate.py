"""FreeTalk end to end on meshes a user brings: units, alignment, the way back into the user's frame,
broken meshes, bad input, the emotion vocabulary, and the windowed ATS track.

Models are at their initial parameters (small configs): these tests check the chain's geometry and
error handling, which do not depend on training. A real, independently made face scan (menpo3d's
``james.obj``, fetched by ``experiments/fetch_real_scan.sh``, which ``.ci/run`` runs) goes through the
chain when it is present.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxtalk.data.batching import window_starts
from jaxtalk.face import builtin_face
from jaxtalk.geometry.canonical import canonicalize, detect_units, load_mesh
from jaxtalk.models.freetalk import animate as ft
from jaxtalk.models.freetalk import ats, stm
from jaxtalk.models.freetalk.config import ATSConfig, STMConfig
from jaxtalk.models.freetalk.data import DisplacementStats, neutral_landmarks
from jaxtalk.models.freetalk.emotions import MEAD_EMOTIONS, emotion_ids, parse_vocabulary
from jaxtalk.models.freetalk.fit import FittedATS, FittedSTM

REAL_SCAN = Path(__file__).resolve().parents[1] / ".cache" / "assets" / "james.obj"


@pytest.fixture(scope="module")
def models():
    """ATS and STM (small, initial parameters): ATS's statistics give centimetre-scale landmark motion."""
    acfg = ATSConfig.small(width=32, num_layers=1, num_heads=2, ff_dim=32, max_frames=20, sample_steps=2)
    scfg = STMConfig.small(encoder_blocks=1, decoder_blocks=1, num_eigenpairs=16)
    face = builtin_face(0, resolution="low")
    tmpl = stm.prepare_mesh(np.asarray(face.template), np.asarray(face.faces), scfg)
    stats = DisplacementStats(mean=np.zeros((68, 3), np.float32), std=np.full((68, 3), 0.004, np.float32))
    fitted_ats = FittedATS(acfg, ats.init_params(acfg, jax.random.key(0)), stats, [], window=20)
    return fitted_ats, FittedSTM(scfg, stm.init_params(scfg, jax.random.key(1), tmpl))


def _face(identity: int = 0):
    f = builtin_face(identity, resolution="low")
    return np.asarray(f.template, np.float64), np.asarray(f.faces, np.int64)


def _pose(vertices: np.ndarray, seed: int, scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    rotation = Rotation.random(random_state=seed).as_matrix()
    shift = rng.normal(size=3) * 0.5
    return scale * (vertices @ rotation.T + shift), rotation, shift


def _speech(seconds: float, seed: int = 0) -> np.ndarray:
    t = np.arange(int(16000 * seconds)) / 16000
    rng = np.random.default_rng(seed)
    return (0.3 * np.sin(2 * np.pi * 180 * t) * (1 + np.sin(2 * np.pi * 3 * t))
            + 0.01 * rng.normal(size=t.size)).astype(np.float32)


# -------------------------------------------------------------------------------------- units, pose


@pytest.mark.parametrize(("extent", "unit"), [(0.2, "m"), (0.09, "m"), (2.0, "dm"), (20.0, "cm"), (200.0, "mm"), (2.0e5, "um")])
def test_detect_units_from_the_size_of_a_face(extent, unit):
    v = np.array([[0, 0, 0], [extent, extent / 2, extent / 3]], float)
    assert detect_units(v) == unit


@pytest.mark.parametrize("extent", [0.6, 1000.0, 0.001, 6.0])
def test_detect_units_rejects_a_size_no_face_has(extent):
    v = np.array([[0, 0, 0], [extent, 0, 0]], float)
    with pytest.raises(ValueError, match="not the size of a face"):
        detect_units(v)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_canonicalize_recovers_a_rotated_shifted_face_in_millimetres(seed):
    v, f = _face(0)
    user, rotation, shift = _pose(v, seed, 1000.0)
    c = canonicalize(user, f, v, f)
    assert (c.units, c.method) == ("mm", "icp")
    back = c.to_template(user)
    assert np.abs(back - v).mean() < 5e-4  # 0.5 mm on a face 14 cm wide
    assert abs(c.fitted_scale - 1.0) < 0.01
    np.testing.assert_allclose(c.to_user(back), user, atol=1e-6)
    # A displacement rotates and scales into the user's frame but does not translate.
    d = np.random.default_rng(seed).normal(size=(5, 3)) * 0.01
    np.testing.assert_allclose(c.displacements_to_user(d), c.to_user(back[:5] + d) - c.to_user(back[:5]), atol=1e-9)


def test_canonicalize_with_landmarks_is_the_similarity_that_fits_them():
    v, f = _face(0)
    lms = neutral_landmarks(builtin_face(0, resolution="low")).astype(np.float64)
    user, rotation, shift = _pose(v, 5, 100.0)  # centimetres
    user_lms = 100.0 * (lms @ rotation.T + shift)
    c = canonicalize(user, f, v, f, units="cm", landmarks=user_lms, template_landmarks=lms)
    assert c.method == "landmarks" and c.units == "cm"
    assert np.abs(c.to_template(user) - v).mean() < 5e-4
    with pytest.raises(ValueError, match="landmarks must have shape"):
        canonicalize(user, f, v, f, landmarks=user_lms[:10], template_landmarks=lms)
    with pytest.raises(ValueError, match="NaN"):
        canonicalize(user, f, v, f, landmarks=np.full((68, 3), np.nan), template_landmarks=lms)


def test_canonicalize_rejects_a_sphere_the_size_of_a_head():
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    v, f = _face(0)
    with pytest.raises(ValueError, match="does not look like a face"):
        canonicalize(np.asarray(sphere.vertices), np.asarray(sphere.faces), v, f)


def test_canonicalize_rejects_units_that_make_the_mesh_too_large():
    v, f = _face(0)
    with pytest.raises(ValueError, match="check the units"):
        canonicalize(v * 1000.0, f, v, f, units="cm")  # a 14-m face
    with pytest.raises(ValueError, match="unknown units"):
        canonicalize(v, f, v, f, units="inch")


# ------------------------------------------------------------------------------- the whole chain


def test_animation_in_the_users_frame_is_the_template_animation_moved_there(models):
    """The same face in metres at the template pose, and rotated, shifted and in millimetres: the
    outputs differ exactly by that similarity (so the way back into the user's frame is right)."""
    fitted_ats, fitted_stm = models
    v, f = _face(0)
    user, rotation, shift = _pose(v, 3, 1000.0)
    lm = ft.landmark_track(fitted_ats, _speech(0.6), "happy", 2.0, jax.random.key(0))
    base = ft.displace(fitted_stm, ft.prepare_user_mesh(fitted_stm, (v, f)), lm)
    moved_mesh = ft.prepare_user_mesh(fitted_stm, (user, f))
    moved = ft.displace(fitted_stm, moved_mesh, lm)
    assert moved_mesh.canonical.units == "mm" and moved.shape == base.shape == (15, v.shape[0], 3)
    expected = 1000.0 * (base.astype(np.float64) @ rotation.T + shift)
    motion = np.abs(base - v).max()
    assert motion > 1e-4  # the untrained model still moves the mesh (about a millimetre)
    # Vertices agree to a small fraction of the motion (the alignment is exact to ~0.1 mm).
    assert np.abs(moved - expected).max() < 0.2 * 1000.0 * motion + 0.2
    np.testing.assert_allclose(moved[0] - moved[0].mean(0), expected[0] - expected[0].mean(0), atol=0.5)


def test_a_mesh_file_animates_in_file_order_with_duplicates_and_isolated_vertices(models, tmp_path):
    """OBJ in centimetres with duplicated vertices (as UV seams make) and one isolated vertex: the
    output has the file's vertex count and order; duplicates move together; the isolated one stays."""
    import trimesh

    fitted_ats, fitted_stm = models
    v, f = _face(2)
    v_cm = 100.0 * v
    dup = np.concatenate([v_cm, v_cm[:50], [[500.0, 0.0, 0.0]]])  # 50 duplicates + 1 isolated far point
    faces = f.copy()
    faces[:40] = np.where(faces[:40] < 50, faces[:40] + v.shape[0], faces[:40])  # some faces use the copies
    path = tmp_path / "face.obj"
    trimesh.Trimesh(dup, faces, process=False).export(path)
    out = ft.animate(fitted_ats, fitted_stm, _speech(0.4), "neutral", 1.0, path, key=jax.random.key(1))
    assert out.shape == (10, dup.shape[0], 3) and np.all(np.isfinite(out))
    np.testing.assert_allclose(out[:, v.shape[0]:v.shape[0] + 50], out[:, :50], atol=1e-4)
    np.testing.assert_allclose(out[:, -1], np.broadcast_to(dup[-1], (10, 3)), atol=1e-4)


def test_a_face_cut_into_forty_components_with_holes_animates_without_nan(models):
    fitted_ats, fitted_stm = models
    v, f = _face(0)
    rng = np.random.default_rng(0)
    label = rng.integers(0, 40, size=f.shape[0])  # each face joins one of 40 pieces
    pieces_v, pieces_f, offset = [], [], 0
    for k in range(40):
        ff = f[label == k]
        used = np.unique(ff)
        remap = np.full(v.shape[0], -1)
        remap[used] = np.arange(used.size) + offset
        pieces_v.append(v[used])
        pieces_f.append(remap[ff])
        offset += used.size
    from jaxtalk.geometry.mesh_checks import inspect_mesh

    keep = np.concatenate(pieces_f)[rng.random(f.shape[0]) > 0.05]  # and 5% of the faces gone (holes)
    verts = np.concatenate(pieces_v)
    assert inspect_mesh(verts, keep).components >= 40
    mesh = ft.prepare_user_mesh(fitted_stm, (verts, keep))
    out = ft.displace(fitted_stm, mesh, np.zeros((3, 68, 3), np.float32) + 0.002)
    assert out.shape == (3, verts.shape[0], 3) and np.all(np.isfinite(out))


def test_parts_of_a_mesh_far_beyond_the_template_face_stay_still(models):
    """A face with a second, disconnected copy 4 cm below it (like a neck or shoulders far outside
    what STM was trained on): the face moves, the copy's vertices do not move at all."""
    fitted_ats, fitted_stm = models
    v, f = _face(0)
    below = v + [0.0, -0.24, 0.0]  # 24 cm down: its top 4 cm below the chin, beyond FADE_END_M
    _, _, landmarks = fitted_stm.template()  # the alignment is guided: this test is about the fade
    mesh = ft.prepare_user_mesh(fitted_stm, (np.concatenate([v, below]), np.concatenate([f, f + v.shape[0]])),
                                landmarks=landmarks)
    assert np.all(mesh.weights[mesh.cleaned.vertex_map[: v.shape[0]]] == 1.0)
    assert np.all(mesh.weights[mesh.cleaned.vertex_map[v.shape[0]:]] == 0.0)
    out = ft.displace(fitted_stm, mesh, np.full((2, 68, 3), 0.003, np.float32))
    np.testing.assert_array_equal(out[:, v.shape[0]:], np.broadcast_to(below.astype(np.float32), (2, *below.shape)))
    assert np.abs(out[:, : v.shape[0]] - v).max() > 1e-4


def test_non_manifold_edges_and_degenerate_faces_animate_on_the_robust_laplacian(models):
    from jaxtalk.geometry.mesh_checks import inspect_mesh
    from jaxtalk.geometry.operators import resolve_method

    fitted_ats, fitted_stm = models
    v, f = _face(1)
    # Three fins on existing edges (each edge then has three faces), and zero-area faces: one with a
    # repeated index and one with collinear corners.
    und = np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, counts = np.unique(und, axis=0, return_counts=True)
    edges = unique[counts == 2][[0, 100, 200]]  # interior edges: two faces each, three with the fin
    fins = np.column_stack([edges, np.arange(3) + v.shape[0]])
    tips = v[edges].mean(axis=1) + [0.0, 0.0, 0.01]
    mid = (v[f[10, 0]] + v[f[10, 1]]) / 2
    verts = np.concatenate([v, tips, [mid]])
    faces = np.concatenate([f, fins, [[f[5, 0], f[5, 0], f[5, 1]], [f[10, 0], f[10, 1], verts.shape[0] - 1]]])
    report = inspect_mesh(verts, faces)
    # The collinear face lies on an interior edge too: four edges with three faces.
    assert report.nonmanifold_edges == 4 and report.degenerate_faces == 2
    mesh = ft.prepare_user_mesh(fitted_stm, (verts, faces))
    # Cleaning drops the zero-area faces; the fins stay, so the operators use the robust Laplacian.
    assert mesh.cleaned.faces.shape[0] == faces.shape[0] - 2
    assert resolve_method(mesh.cleaned.vertices, mesh.cleaned.faces, "auto") == "robust"
    out = ft.displace(fitted_stm, mesh, np.full((4, 68, 3), 0.002, np.float32))
    assert out.shape == (4, verts.shape[0], 3) and np.all(np.isfinite(out))


# ----------------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("vertices", "faces", "message"),
    [
        (np.zeros((0, 3)), np.zeros((0, 3), int), "no vertices"),
        (np.full((200, 3), np.nan), np.array([[0, 1, 2]]), "non-finite"),
        (np.random.default_rng(0).normal(size=(500, 3)) * 0.05, np.zeros((0, 3), int), "point cloud"),
        (np.array([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]], float), np.array([[0, 1, 2]]), "3 usable vertices"),
        (np.eye(3), np.array([[0, 1, 5]]), "face indices"),
    ],
)
def test_prepare_user_mesh_rejects_what_cannot_be_a_face_mesh(models, vertices, faces, message):
    with pytest.raises(ValueError, match=message):
        ft.prepare_user_mesh(models[1], (vertices, faces))


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".glb", ".gltf", ".off"])
def test_load_mesh_keeps_the_files_vertex_order(tmp_path, suffix):
    import trimesh

    v, f = _face(4)
    path = tmp_path / f"face{suffix}"
    trimesh.Trimesh(100.0 * v, f, process=False).export(path)
    vertices, faces = load_mesh(path)
    np.testing.assert_allclose(vertices, 100.0 * v, atol=1e-5)  # glTF stores float32
    np.testing.assert_array_equal(faces, f)


def test_load_mesh_errors_name_the_file_and_the_problem(tmp_path):
    import trimesh

    with pytest.raises(FileNotFoundError, match="mesh file not found"):
        load_mesh(tmp_path / "missing.obj")
    (tmp_path / "face.txt").write_text("v 0 0 0\n")
    with pytest.raises(ValueError, match="expected a mesh file"):
        load_mesh(tmp_path / "face.txt")
    trimesh.PointCloud(np.random.default_rng(0).normal(size=(100, 3))).export(tmp_path / "cloud.ply")
    with pytest.raises(ValueError, match="point cloud"):
        load_mesh(tmp_path / "cloud.ply")


def test_chain_rejects_bad_audio_emotion_and_intensity(models):
    fitted_ats, _ = models
    key = jax.random.key(0)
    with pytest.raises(ValueError, match="empty"):
        ft.landmark_track(fitted_ats, np.zeros(0, np.float32), "happy", 1.0, key)
    bad = _speech(0.4)
    bad[100] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        ft.landmark_track(fitted_ats, bad, "happy", 1.0, key)
    with pytest.raises(ValueError, match="silent"):
        ft.landmark_track(fitted_ats, np.zeros(8000, np.float32), "happy", 1.0, key)
    with pytest.raises(ValueError, match="unknown emotion name.*'elated'"):
        ft.landmark_track(fitted_ats, _speech(0.4), "elated", 1.0, key)
    with pytest.raises(ValueError, match=r"intensity must lie in \[1, 3\]"):
        ft.landmark_track(fitted_ats, _speech(0.4), "happy", 3.5, key)


# ------------------------------------------------------------------------------ ATS windowing


def test_landmark_track_of_a_short_clip_is_one_ats_sample(models):
    from jaxtalk.models.freetalk.fit import sample_displacements

    fitted_ats, _ = models
    audio = _speech(0.5)
    track = ft.landmark_track(fitted_ats, audio, "sad", 1.5, jax.random.key(3))
    feats = fitted_ats.audio_features(audio, 12)[None]
    direct = sample_displacements(fitted_ats, feats, "sad", 1.5, jax.random.key(3))[0]
    np.testing.assert_allclose(track, direct, atol=1e-6)


def test_crossfade_weights_sum_to_one_and_ramp_over_the_overlaps():
    starts = window_starts(50, 20, 15)  # animate's windows: a quarter overlap
    assert starts == [0, 15, 30]
    w = ft._crossfade(50, 20, starts)
    np.testing.assert_allclose(w.sum(axis=0), 1.0)
    assert np.all(w[0, :15] == 1.0) and np.all(w[0, 20:] == 0.0)
    assert np.all(np.diff(w[1, 15:20]) > 0)  # window 1 fades in where window 0 fades out
    np.testing.assert_allclose(w[0, 15:20] + w[1, 15:20], 1.0)


def test_landmark_track_of_a_long_clip_has_one_frame_per_40_ms(models):
    fitted_ats, _ = models
    track = ft.landmark_track(fitted_ats, _speech(2.2), "angry", 3.0, jax.random.key(0))
    assert track.shape == (55, 68, 3) and np.all(np.isfinite(track))


def test_landmark_track_is_the_same_whatever_number_of_windows_each_call_samples(models):
    # 6 s = 150 frames = 9 windows of 20: one call of all 9 (the unbounded batch), groups of 2, one by one.
    fitted_ats, _ = models
    audio, key = _speech(6.0), jax.random.key(4)
    whole = ft.landmark_track(fitted_ats, audio, "happy", 2.0, key, windows_per_call=16)
    for per_call in (1, 2):
        np.testing.assert_allclose(ft.landmark_track(fitted_ats, audio, "happy", 2.0, key, windows_per_call=per_call),
                                   whole, atol=1e-5)


def test_landmark_track_cross_fades_each_window_by_its_normalised_ramp(models):
    # The track equals the old construction: every window sampled (own noise), weighted by _crossfade.
    from jaxtalk.models.freetalk.fit import sample_displacements

    fitted_ats, _ = models
    audio, key = _speech(2.2), jax.random.key(5)
    track = ft.landmark_track(fitted_ats, audio, "sad", 1.0, key)
    starts = window_starts(55, 20, 15)  # a quarter overlap, as landmark_track cuts them
    feats = fitted_ats.audio_features(audio, 55)
    weights = ft._crossfade(55, 20, starts)
    want = np.zeros_like(track, dtype=np.float64)
    for w, s in enumerate(starts):
        noise = ft._window_noise(key, w, 20, fitted_ats.config.motion_dim)[None]
        d = sample_displacements(fitted_ats, feats[None, s:s + 20], "sad", 1.0, key, noise=noise)[0]
        want[s:s + 20] += weights[w, s:s + 20, None, None] * d
    np.testing.assert_allclose(track, want, atol=1e-5)


# ------------------------------------------------------------------------------ vocabularies


def test_emotion_vocabulary_is_a_config_setting():
    mead = ATSConfig.small(emotions="mead")
    assert mead.emotions == MEAD_EMOTIONS and mead.num_emotions == 8
    assert ATSConfig.small(emotions=["neutral", "happy"]).num_emotions == 2
    assert ATSConfig.small(emotions="neutral,joy,rage").emotions == ("neutral", "joy", "rage")
    assert emotion_ids(["contempt", "surprised"], MEAD_EMOTIONS).tolist() == [2, 7]
    with pytest.raises(ValueError, match="this model knows: neutral, angry, contempt"):
        emotion_ids("afraid", MEAD_EMOTIONS)
    with pytest.raises(ValueError, match="starts with 'neutral'"):
        parse_vocabulary("happy,neutral")
    with pytest.raises(ValueError, match="repeated"):
        parse_vocabulary("neutral,happy,happy")
    params = ats.init_params(ATSConfig.small(emotions="mead", width=32, num_layers=1, num_heads=2, ff_dim=32,
                                          max_frames=8), jax.random.key(0))
    assert params["params"]["affect"]["emotion"].shape[0] == 8


def test_presets_use_the_displacement_scale_training_accepts():
    assert ATSConfig.paper().displacement_scale == ATSConfig.small().displacement_scale == 1.0
    assert ATSConfig.paper().speech_dim == 768 and ATSConfig.small().speech_dim == 320


# ------------------------------------------------------------------------------ a real scan


@pytest.mark.skipif(not REAL_SCAN.is_file(), reason="no real face scan: run bash experiments/fetch_real_scan.sh (.ci/run does)")
def test_a_real_face_scan_in_millimetres_animates_in_its_own_frame(models):
    """menpo3d's james.obj: a textured head scan in mm, its own pose, 28 components, UV-seam
    duplicates. It is found to be in millimetres, aligns to within millimetres of the template, and
    animates without NaN with the output in its own frame (displacements of millimetres, not metres)."""
    fitted_ats, fitted_stm = models
    vertices, faces = load_mesh(REAL_SCAN)
    mesh = ft.prepare_user_mesh(fitted_stm, (vertices, faces))
    assert mesh.canonical.units == "mm" and 0.8 < mesh.canonical.fitted_scale < 1.2
    assert mesh.canonical.residual < 0.006
    out = ft.displace(fitted_stm, mesh, ft.landmark_track(fitted_ats, _speech(0.4), "happy", 2.0, jax.random.key(0)))
    assert out.shape == (10, vertices.shape[0], 3) and np.all(np.isfinite(out))
    step = np.linalg.norm(out - vertices, axis=-1).max()
    assert 0 < step < 50.0  # millimetres: a face moves by less than 5 cm
    landmarks = REAL_SCAN.with_suffix(".ljson")
    if landmarks.is_file():  # its 68 landmarks, grouped by region in menpo's file; iBUG order here
        points = np.asarray(json.loads(landmarks.read_text())["groups"]["LJSON"]["landmarks"]["points"])
        points = points[np.r_[0:17, 29:34, 43:48, 34:43, 17:23, 23:29, 48:68]]
        guided = ft.prepare_user_mesh(fitted_stm, (vertices, faces), landmarks=points)
        _, _, tl = fitted_stm.template()
        err = np.linalg.norm(guided.canonical.to_template(points) - tl, axis=1)
        assert guided.canonical.method == "landmarks" and err[48:].mean() < 0.01  # mouth within 1 cm


def test_an_ats_run_recorded_before_the_vocabulary_setting_loads_as_emovoca(tmp_path):
    import dataclasses

    from jaxtalk.runs import RunRecord
    from jaxtalk.models.freetalk.emotions import EMOTIONS

    old = dataclasses.asdict(ATSConfig.small())
    old.pop("emotions")
    record = RunRecord(model="ats", preset="small", items=[], config={**old, "num_emotions": 12}, train={}, optim={},
                       data={}, seed=0)
    record.save(tmp_path / "emovoca")
    assert RunRecord.load(tmp_path / "emovoca").model_config().emotions == EMOTIONS
    dataclasses.replace(record, config={**old, "num_emotions": 8}).save(tmp_path / "eight")
    with pytest.raises(ValueError, match="no vocabulary on record"):
        RunRecord.load(tmp_path / "eight")


def test_fitted_models_open_from_a_loaded_run_and_say_so_when_given_a_path():
    for cls in (FittedATS, FittedSTM):
        with pytest.raises(ValueError, match=r"from_run takes a loaded run: from_run\(jaxtalk.runs.load_run\('runs/x'\)\)"):
            cls.from_run("runs/x")
