"""Retargeting onto blendshape rigs: the solver against scipy, the built-in ARKit rig, registration of
other meshes, the head's rotation, streaming, and the files (GLB, Live Link Face CSV, JSON)."""

from __future__ import annotations

import functools
import json

import numpy as np
import pytest
from scipy.optimize import lsq_linear
from scipy.spatial.transform import Rotation

from jaxtalk.export import (
    GlbAnimation,
    Penalties,
    Retargeter,
    Rig,
    arkit_rig,
    export_rig_animation,
    load_rig,
    read_live_link_csv,
    retarget,
    solve_weights,
    write_live_link_csv,
)
from jaxtalk.export.arkit import ARKIT_NAMES, LIVE_LINK_CURVES
from jaxtalk.export.recording import live_link_timecode
from jaxtalk.export.rig import arkit_shape_name, symmetric_pairs
from jaxtalk.export.solver import DEFAULT_MAX_ITER, symmetry_matrix
from jaxtalk.face import builtin_face
from helpers import jax_flag

# The shapes speech drives (cheekPuff is left out: SynthTalk's faces puff their cheeks idly, silent or not).
MOUTH = [n for n in ARKIT_NAMES if n.startswith(("jaw", "mouth", "tongue"))]


@functools.lru_cache(maxsize=None)
def low_rig() -> Rig:
    return arkit_rig("low")


@functools.lru_cache(maxsize=None)
def low_face():
    return builtin_face(0, resolution="low")


def random_problem(seed: int, frames: int = 20, rows: int = 40, k: int = 8):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(rows, k)) * rng.uniform(0.5, 2.0, size=k)
    b = rng.normal(size=(frames, rows)) * 1.5
    return a, b


def stacked_reference(a, b, *, smoothness=0.0, l1=0.0, l2=0.0, symmetry=0.0, pairs=(), previous=None):
    """The same problem as one bounded least squares over every frame's weights (scipy's BVLS).

    The L1 term on [0, 1] is linear, ``l1 sum(w)``; it enters as a shifted target ``b - a (a^T a)^-1 l1 1``
    (same gradient), the other penalties as extra rows.
    """
    frames, k = b.shape[0], a.shape[1]
    shift = a @ np.linalg.solve(a.T @ a, np.full(k, l1))
    blocks, rhs = [np.kron(np.eye(frames), a)], [(b - shift).reshape(-1)]
    if l2:
        blocks.append(np.sqrt(l2) * np.eye(frames * k))
        rhs.append(np.zeros(frames * k))
    for left, right in pairs:
        row = np.zeros((frames, frames * k))
        for t in range(frames):
            row[t, t * k + left], row[t, t * k + right] = 1.0, -1.0
        blocks.append(np.sqrt(symmetry) * row)
        rhs.append(np.zeros(frames))
    if smoothness:
        diff = (np.eye(frames, k=1) - np.eye(frames))[:-1]
        blocks.append(np.sqrt(smoothness) * np.kron(diff, np.eye(k)))
        rhs.append(np.zeros((frames - 1) * k))
        if previous is not None:
            first = np.zeros((k, frames * k))
            first[:, :k] = np.eye(k)
            blocks.append(np.sqrt(smoothness) * first)
            rhs.append(np.sqrt(smoothness) * previous)
    result = lsq_linear(np.concatenate(blocks), np.concatenate(rhs), bounds=(0.0, 1.0), method="bvls", tol=1e-13)
    return result.x.reshape(frames, k)


# ---- the solver -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(4))
def test_solver_matches_scipy_bvls_per_frame_in_float32(seed):
    a, b = random_problem(seed)
    ref = np.stack([lsq_linear(a, row, bounds=(0.0, 1.0), method="bvls", tol=1e-14).x for row in b])
    weights, info = solve_weights(a.T @ a, b @ a)
    assert np.asarray(weights).dtype == np.float32
    assert np.abs(np.asarray(weights) - ref).max() < 1e-5, info
    assert 0.05 < (ref == 0).mean() + (ref == 1).mean() < 0.95  # both free and bound weights are tested


def test_solver_matches_scipy_bvls_in_float64(float64):
    a, b = random_problem(7, k=12)
    ref = np.stack([lsq_linear(a, row, bounds=(0.0, 1.0), method="bvls", tol=1e-15).x for row in b])
    weights, _ = solve_weights(a.T @ a, b @ a, tol=1e-12, max_iter=20_000)
    assert np.asarray(weights).dtype == np.float64
    assert np.abs(np.asarray(weights) - ref).max() < 1e-9


@pytest.mark.parametrize("penalties", [dict(smoothness=2.0), dict(l1=3.0), dict(l2=5.0),
                                       dict(symmetry=4.0), dict(smoothness=0.5, l1=1.0, l2=0.1, symmetry=1.0)])
def test_each_penalty_matches_the_stacked_least_squares_reference(float64, penalties):
    a, b = random_problem(3, frames=12, k=6)
    pairs = [(0, 1), (2, 4)]
    ref = stacked_reference(a, b, pairs=pairs, **penalties)
    weights, _ = solve_weights(a.T @ a, b @ a, Penalties(**penalties), symmetry=symmetry_matrix(pairs, 6),
                               tol=1e-12, max_iter=50_000)
    assert np.abs(np.asarray(weights) - ref).max() < 1e-7


def test_a_streamed_chunk_is_tied_to_the_previous_frame(float64):
    a, b = random_problem(5, frames=10, k=6)
    previous = np.linspace(0.0, 1.0, 6)
    ref = stacked_reference(a, b, smoothness=3.0, previous=previous)
    weights, _ = solve_weights(a.T @ a, b @ a, Penalties(smoothness=3.0), previous=previous, tol=1e-12, max_iter=50_000)
    assert np.abs(np.asarray(weights) - ref).max() < 1e-7
    free, _ = solve_weights(a.T @ a, b @ a, Penalties(smoothness=3.0), tol=1e-12, max_iter=50_000)
    assert np.abs(np.asarray(free)[0] - previous).sum() > np.abs(np.asarray(weights)[0] - previous).sum()


def test_bounds_hold_and_l1_makes_the_weights_sparser():
    a, b = random_problem(11, frames=30, k=10)
    b = 4.0 * b  # targets far outside the box
    dense, _ = solve_weights(a.T @ a, b @ a)
    sparse, _ = solve_weights(a.T @ a, b @ a, Penalties(l1=20.0))
    dense, sparse = np.asarray(dense), np.asarray(sparse)
    for w in (dense, sparse):
        assert w.min() >= 0.0 and w.max() <= 1.0
    assert (dense == 1.0).any() and (dense == 0.0).any()
    assert (sparse == 0.0).sum() > (dense == 0.0).sum() + 20


def test_smoothness_reduces_frame_to_frame_jitter():
    a, b = random_problem(2, frames=60, k=8)
    rough, _ = solve_weights(a.T @ a, b @ a)
    smooth, _ = solve_weights(a.T @ a, b @ a, Penalties(smoothness=300.0))
    jitter = [np.abs(np.diff(np.asarray(w), axis=0)).mean() for w in (rough, smooth)]
    assert jitter[1] < 0.3 * jitter[0], jitter


def test_symmetry_ties_left_and_right_pairs():
    a, b = random_problem(4, frames=20, k=6)
    pairs = [(0, 1), (2, 3)]
    free, _ = solve_weights(a.T @ a, b @ a)
    tied, _ = solve_weights(a.T @ a, b @ a, Penalties(symmetry=1e4), symmetry=symmetry_matrix(pairs, 6))
    gap = [np.abs(np.asarray(w)[:, [0, 2]] - np.asarray(w)[:, [1, 3]]).max() for w in (free, tied)]
    assert gap[0] > 0.1 and gap[1] < 2e-3, gap


def test_changing_a_penalty_does_not_recompile():
    from jaxtalk.export import solver

    a, b = random_problem(1)
    solve_weights(a.T @ a, b @ a, Penalties(smoothness=0.1))
    before = solver._solve._cache_size()
    for value in (0.2, 0.3):
        solve_weights(a.T @ a, b @ a, Penalties(smoothness=value, l1=value, symmetry=value), tol=1e-5, max_iter=100)
    assert solver._solve._cache_size() == before


def test_solver_refuses_bad_input():
    a, b = random_problem(0)
    with pytest.raises(ValueError, match="rhs must have shape"):
        solve_weights(a.T @ a, b[0] @ a)
    with pytest.raises(ValueError, match="NaN"):
        solve_weights(a.T @ a, np.full_like(b @ a, np.nan))
    with pytest.raises(ValueError, match=">= 0"):
        Penalties(l1=-1.0)


# ---- names and rigs --------------------------------------------------------------------------------------
def test_shape_names_are_matched_to_arkit_whatever_the_rig_calls_them():
    for name, arkit in [("eyeBlink_L", "eyeBlinkLeft"), ("blendShape1.mouthSmile_R", "mouthSmileRight"),
                        ("EyeBlinkLeft", "eyeBlinkLeft"), ("jawOpen", "jawOpen"), ("head:cheekSquint_r", "cheekSquintRight"),
                        ("browDown.L", "browDownLeft"), ("mouthLeft", "mouthLeft"), ("smirk", None)]:
        assert arkit_shape_name(name) == arkit, name
    assert len(symmetric_pairs(ARKIT_NAMES)) == 20
    assert symmetric_pairs(["brow_L", "x", "brow_R", "lip_L"]) == [(0, 2)]


def test_builtin_rig_has_the_52_arkit_shapes_with_their_meaning():
    rig = low_rig()
    assert rig.names == ARKIT_NAMES and rig.deltas.shape == (52, rig.num_vertices, 3)
    x, y = rig.neutral[:, 0], rig.neutral[:, 1]
    d = {n: rig.deltas[i] for i, n in enumerate(rig.names)}
    face = low_face()
    lips = np.asarray(face.regions["lips"])
    mouth_lower = np.asarray(face.regions["mouth_lower"])
    assert d["jawOpen"][mouth_lower, 1].mean() < -0.01  # the lower lip drops by centimetres
    smile = d["mouthSmileLeft"]
    assert smile[lips][x[lips] > 0, 1].max() > 0.002 and np.abs(smile[x < -0.01]).max() < 1e-5
    assert d["eyeBlinkLeft"][np.asarray(face.regions["eye_l"]), 1].min() < -0.003  # the upper lid comes down
    assert np.abs(d["eyeBlinkLeft"][x < -0.01]).max() < 1e-9
    assert d["browInnerUp"][:, 1].max() > 0.002 and np.abs(d["browInnerUp"][y < 0.0]).max() < 1e-4
    assert d["jawLeft"][mouth_lower, 0].mean() > 0.001 and d["jawRight"][mouth_lower, 0].mean() < -0.001
    # Mirror pairs mirror exactly (x -> -x), and all 52 are distinct and independent.
    from scipy.spatial import cKDTree

    mirror = cKDTree(rig.neutral).query(rig.neutral * [-1.0, 1.0, 1.0])[1]
    for left, right in rig.pairs():
        np.testing.assert_allclose(rig.deltas[left], rig.deltas[right][mirror] * [-1.0, 1.0, 1.0], atol=1e-9)
    flat = rig.deltas.reshape(52, -1)
    flat = flat / np.linalg.norm(flat, axis=1, keepdims=True)
    assert np.linalg.eigvalsh(flat @ flat.T)[0] > 1e-4


def test_rig_refuses_what_is_not_a_blendshape_rig(tmp_path):
    rig = low_rig()
    with pytest.raises(ValueError, match="no morph targets"):
        Rig(names=(), neutral=rig.neutral, deltas=np.zeros((0, rig.num_vertices, 3)), faces=rig.faces)
    with pytest.raises(FileNotFoundError):
        load_rig(tmp_path / "nothing.glb")
    (tmp_path / "plain.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    folder = tmp_path / "shapes"
    folder.mkdir()
    (folder / "smile.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(ValueError, match="no neutral"):
        load_rig(folder)


def _write_obj(path, vertices, faces):
    lines = [f"v {x:.9f} {y:.9f} {z:.9f}" for x, y, z in vertices] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def test_glb_and_obj_folder_rigs_load_back_as_written(tmp_path):
    rig = low_rig()
    export_rig_animation(rig, np.zeros((2, 52)), tmp_path / "rig.glb")
    loaded = load_rig(tmp_path / "rig.glb")
    assert loaded.names == rig.names
    np.testing.assert_allclose(loaded.neutral, rig.neutral, atol=1e-6)
    np.testing.assert_allclose(loaded.deltas, rig.deltas, atol=1e-6)
    folder = tmp_path / "objs"
    folder.mkdir()
    _write_obj(folder / "neutral.obj", rig.neutral, rig.faces)
    for k in (17, 23):
        _write_obj(folder / f"{rig.names[k]}.obj", rig.neutral + rig.deltas[k], rig.faces)
    objs = load_rig(folder)
    assert objs.names == ("jawOpen", "mouthSmileLeft")
    np.testing.assert_allclose(objs.deltas[0], rig.deltas[17], atol=1e-6)


# ---- retargeting -----------------------------------------------------------------------------------------
def rig_animation(frames: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.uniform(0.0, 1.0, size=(frames, 52)) * (rng.uniform(size=(frames, 52)) < 0.3)


def test_retargeting_the_builtin_rigs_own_animation_recovers_its_weights_under_head_motion():
    rig = low_rig()
    weights = rig_animation(60)
    turns = np.c_[np.linspace(0.0, 0.3, 60), np.linspace(-0.15, 0.2, 60), np.linspace(0.1, -0.1, 60)]
    rot = Rotation.from_euler("YXZ", turns).as_matrix()
    moved = np.einsum("tij,tvj->tvi", rot, rig.vertices(weights)) + np.array([0.01, -0.02, 0.005])
    retargeter = Retargeter.for_mesh(rig, rig.neutral, rig.faces, template=low_face(), penalties=Penalties())
    assert retargeter.registration.method == "same mesh"
    result = retargeter(moved)
    error = np.abs(result.weights - weights).max()
    print(f"recovery error {error:.2e}, head angle error {np.abs(result.head_angles - turns).max():.1e} rad")
    assert error < 1e-3
    np.testing.assert_allclose(result.head_angles, turns, atol=1e-4)


def test_parameters_retarget_through_the_face_model_and_report_the_neck_as_head_angles():
    rig, face = low_rig(), low_face()
    frames = 50
    params = np.zeros((frames, 56), np.float32)
    params[:, 50] = 0.12 * (1.0 + np.sin(np.arange(frames) / 3.0))
    params[:, 53:56] = [0.1, -0.2, 0.05]  # a fixed neck: pitch, yaw, roll as axis-angle
    result = retarget(params, rig, face=face)
    jaw = result.weights[:, rig.names.index("jawOpen")]
    assert np.corrcoef(jaw, params[:, 50])[0, 1] > 0.99
    assert np.abs(jaw - params[:, 50] / 0.3).max() < 0.1
    expected = Rotation.from_rotvec([0.1, -0.2, 0.05]).as_euler("YXZ")
    np.testing.assert_allclose(result.head_angles, np.tile(expected, (frames, 1)), atol=1e-5)


def test_a_rig_on_another_mesh_is_registered_and_retargeted(tmp_path):
    """The built-in rig scaled to centimetres, turned and moved: registration (ICP, units detected) finds it on
    the face, and the weights match those of the rig in place."""
    fine = arkit_rig("default")
    turn = Rotation.from_euler("y", 30, degrees=True).as_matrix()
    moved = Rig(names=fine.names, neutral=100.0 * fine.neutral @ turn.T + [3.0, 150.0, -2.0],
                deltas=100.0 * fine.deltas @ turn.T, faces=fine.faces, name="moved")
    face = builtin_face(0)
    frames = 20
    params = np.zeros((frames, 56), np.float32)
    params[:, 50] = np.linspace(0.0, 0.25, frames)
    params[:, 18] = np.linspace(0.0, 1.0, frames)  # blink_l
    retargeter = Retargeter.for_face(moved, face, Penalties(l2=1e-4))
    assert retargeter.registration.method == "icp" and retargeter.registration.units == "cm"
    assert retargeter.registration.residual < 1e-3 and retargeter.registration.fitted > 0.8 * moved.num_vertices
    result = retargeter(params)
    same = Retargeter.for_face(fine, face, Penalties(l2=1e-4))(params)
    for name in ("jawOpen", "eyeBlinkLeft"):
        k = ARKIT_NAMES.index(name)
        assert np.corrcoef(result.weights[:, k], same.weights[:, k])[0, 1] > 0.98, name
        assert np.abs(result.weights[:, k] - same.weights[:, k]).max() < 0.1, name


def mediapipe_rig() -> Rig:
    """MediaPipe's canonical face (a real face, centimetres in its file, metres here) as a 52-shape ARKit rig:
    each of its vertices takes the built-in rig's shapes at the built-in face's closest vertex, once the two
    faces are put together by their semantic points."""
    import face_shapes as fs
    from scipy.spatial import cKDTree

    from jaxtalk.geometry.canonical import umeyama

    shape, rig = fs.mediapipe_face(), arkit_rig("default")
    s, rot, t = umeyama(shape.points, fs.template()[2], scale=True)
    near = cKDTree(rig.neutral).query(s * shape.vertices @ rot.T + t)[1]
    return Rig(names=rig.names, neutral=shape.vertices, deltas=rig.deltas[:, near] @ rot / s, faces=shape.faces,
               name="mediapipe")


def test_a_real_faces_rig_registers_as_freetalk_aligns_a_mesh_whatever_its_scale_and_pose():
    """A rig on a real face (MediaPipe's) is registered through MediaPipe's canonical face, as FreeTalk aligns a
    mesh (the template's landmarks carry it over). Stored in metres, decimetres (as a captured head's glTF file
    may be), centimetres and millimetres (0.1x, 1x, 10x and 100x of decimetres) and turned: each unit is found,
    and the weights are the same within 1e-3. A well-conditioned solve (more L2), so that the weights differ
    only where the registrations do."""
    rig, face = mediapipe_rig(), low_face()
    frames = 30
    rng = np.random.default_rng(0)
    params = np.zeros((frames, 56), np.float32)
    params[:, :50] = rng.normal(0.0, 0.5, (frames, 50)) * (rng.random((frames, 50)) < 0.2)
    params[:, 50] = np.linspace(0.0, 0.3, frames)
    penalties = Penalties(smoothness=0.05, l2=1e-2)
    weights = []
    for k, (factor, unit) in enumerate([(1.0, "dm"), (0.1, "m"), (10.0, "cm"), (100.0, "mm")]):
        turn = np.eye(3) if k == 0 else Rotation.random(random_state=k).as_matrix()
        scale = 10.0 * factor  # file units per metre
        moved = Rig(names=rig.names, neutral=scale * (rig.neutral @ turn.T + [0.3, 1.5, -0.2]),
                    deltas=scale * rig.deltas @ turn.T, faces=rig.faces, name=unit)
        retargeter = Retargeter.for_face(moved, face, penalties)
        registration = retargeter.registration
        assert (registration.units, registration.method, registration.reference) == (unit, "icp", "mediapipe")
        weights.append(retargeter(params).weights)
    difference = max(np.abs(w - weights[0]).max() for w in weights[1:])
    print(f"weights at 0.1x-100x and turned: at most {difference:.1e} apart")
    assert difference < 1e-3
    assert np.corrcoef(weights[0][:, ARKIT_NAMES.index("jawOpen")], params[:, 50])[0, 1] > 0.99


def test_a_mesh_that_is_not_a_face_is_refused():
    import trimesh

    box = trimesh.creation.box((0.15, 0.2, 0.18))
    rig = Rig(names=("a",), neutral=box.vertices, deltas=np.ones((1, len(box.vertices), 3)) * 0.001, faces=box.faces)
    with pytest.raises(ValueError, match="does not look like a face"):
        Retargeter.for_face(rig, low_face())


def test_streamed_chunks_match_the_whole_clip():
    rig, face = low_rig(), low_face()
    rng = np.random.default_rng(0)
    params = np.zeros((40, 56), np.float32)
    params[:, 50] = np.clip(np.cumsum(rng.normal(0, 0.02, 40)), 0.0, 0.3)
    params[:, 18] = (np.arange(40) % 13 < 3).astype(np.float32)
    retargeter = Retargeter.for_face(rig, face, Penalties(smoothness=0.5))
    whole = retargeter(params).weights
    state, chunks = retargeter.init_stream(), []
    for start in range(0, 40, 10):
        state, result = retargeter.stream_step(state, params[start:start + 10])
        chunks.append(result.weights)
    streamed = np.concatenate(chunks)
    # A causal solve cannot see the next chunk, so chunk edges differ a little from the whole-clip solve.
    assert np.abs(streamed - whole).mean() < 0.01
    alone = np.concatenate([retargeter(params[s:s + 10]).weights for s in range(0, 40, 10)])
    edges = [9, 19, 29]
    assert np.abs(np.diff(streamed, axis=0)[edges]).sum() < np.abs(np.diff(alone, axis=0)[edges]).sum()


@pytest.fixture(scope="module")
def speech_clip():
    """A speech-driven SynthTalk clip (its rule-based ground truth: jaw and lips follow the phones)."""
    from jaxtalk.data.synthtalk import SizeSpec, generate

    corpus = generate(SizeSpec((1, 0, 0, 0), 1, 8.0, (0, 0, 0, 0), 8.0, 8, 1e9, identities=(0,), lazy=True), seed=0)
    motion, _ = corpus.motion_without_audio(0)
    return motion, corpus.voice_activity(0)


def test_jaw_open_tracks_the_jaw_of_speech_and_the_mouth_rests_on_a_silent_clip(speech_clip):
    from jaxtalk.layout import EXP_INDEX, GROUPS

    motion, speaking = speech_clip
    rig, face = low_rig(), low_face()
    retargeter = Retargeter.for_face(rig, face)
    result = retargeter(motion)
    jaw = result.weights[:, rig.names.index("jawOpen")]
    corr = np.corrcoef(jaw, motion[:, 50])[0, 1]
    print(f"jawOpen vs jaw opening: correlation {corr:.3f}; {result.weights.shape[0]} frames, "
          f"{speaking.mean():.0%} speaking")
    assert corr > 0.8
    # Silence: the same clip with the mouth at rest (no phones), the rest of the face and head moving.
    silent = motion.copy()
    silent[:, GROUPS["mouth"]] = 0.0
    silent[:, GROUPS["residual"]] = 0.0  # the speaker's resting face is their neutral
    # SynthTalk puffs one cheek at a time, which ARKit's single cheekPuff cannot show without a dimple on the
    # other side: the puffs are mouth motion too.
    silent[:, [EXP_INDEX["cheek_puff_l"], EXP_INDEX["cheek_puff_r"]]] = 0.0
    quiet = retargeter(silent).weights
    mouth = [rig.names.index(n) for n in MOUTH]
    print(f"silent clip: mouth shapes at most {quiet[:, mouth].max():.3f}, blinks up to "
          f"{quiet[:, rig.names.index('eyeBlinkLeft')].max():.2f}")
    assert quiet[:, mouth].max() < 0.05
    assert quiet[:, rig.names.index("eyeBlinkLeft")].max() > 0.5  # the clip is not still: it blinks


def test_a_250_frame_clip_converges_before_the_iteration_limit():
    # how fast it converges is measured in experiments/bench_retarget.py; here only that it stops on the
    # tolerance, not the cap, and fits the clip
    rig = low_rig()
    retargeter = Retargeter.for_mesh(rig, rig.neutral, rig.faces, template=low_face())
    result = retargeter(rig.vertices(rig_animation(250, seed=3)))
    assert result.iterations < DEFAULT_MAX_ITER
    assert result.rms_error < 1e-3


# ---- files -----------------------------------------------------------------------------------------------
def test_rig_glb_plays_the_weights_and_turns_the_head_about_the_pivot(tmp_path):
    rig = low_rig()
    weights = rig_animation(6, seed=1)
    rot = Rotation.from_euler("YXZ", np.c_[np.linspace(0, 0.3, 6), np.zeros(6), np.zeros(6)]).as_matrix()
    pivot = np.array([0.0, -0.17, -0.03])
    summary = export_rig_animation(rig, weights, tmp_path / "a.glb", fps=30, head_rotation=rot, pivot=pivot)
    assert summary.morph_targets == 52 and summary.frames == 6
    glb = GlbAnimation(tmp_path / "a.glb")
    assert glb.target_names == list(ARKIT_NAMES)
    np.testing.assert_allclose(glb.times, np.arange(6) / 30, atol=1e-6)
    np.testing.assert_allclose(glb.morph_weights(), weights, atol=1e-6)
    expected = np.einsum("ij,vj->vi", rot[4], rig.vertices(weights[4:5])[0] - pivot) + pivot
    np.testing.assert_allclose(glb.vertices(4), expected, atol=1e-5)


def test_live_link_csv_has_the_apps_layout(tmp_path):
    names = ("jawOpen", "eyeBlink_L", "smirk")
    weights = np.array([[0.5, 0.25, 0.9], [1.0, 0.0, 0.1]])
    head = np.array([[0.1, -0.2, 0.3], [0.0, 0.0, 0.0]])
    path = write_live_link_csv(tmp_path / "take.csv", names, weights, head, fps=25)
    header = path.read_text().splitlines()[0]
    assert header == "Timecode,BlendShapeCount," + ",".join(LIVE_LINK_CURVES)
    stamps, values = read_live_link_csv(path)
    assert stamps == ["00:00:00:00.000", "00:00:00:01.000"]
    assert path.read_text().splitlines()[1].split(",")[1] == "61"
    col = {n: i for i, n in enumerate(LIVE_LINK_CURVES)}
    assert values[0, col["JawOpen"]] == 0.5 and values[0, col["EyeBlinkLeft"]] == 0.25
    assert values[0, col["HeadYaw"]] == 0.1 and values[0, col["HeadRoll"]] == 0.3
    assert values[:, col["MouthSmileLeft"]].tolist() == [0.0, 0.0]
    assert live_link_timecode(25 * 3661 + 7, 25) == "01:01:01:07.000"
    assert live_link_timecode(31, 29.97) == "00:00:01:01.030"


def test_json_lists_weights_names_and_head(tmp_path):
    from jaxtalk.export import write_weights_json

    path = write_weights_json(tmp_path / "w.json", names=("eyeBlink_L", "x"), weights=np.array([[0.5, 0.0]]),
                              head_angles=np.array([[0.1, 0.2, 0.3]]), fps=25)
    data = json.loads(path.read_text())
    assert data["arkit"] == ["eyeBlinkLeft", None] and data["weights"] == [[0.5, 0.0]]
    assert data["head"]["yaw"] == [0.1] and data["head"]["units"] == "radians" and data["fps"] == 25


def test_a_rig_made_in_code_with_two_shapes_on_one_arkit_name_is_refused():
    rig = low_rig()
    deltas = rig.deltas[[ARKIT_NAMES.index("jawOpen")] * 2]
    with pytest.raises(ValueError, match="'mouthSmile_L' and 'MouthSmileLeft' are both ARKit's 'mouthSmileLeft'"):
        Rig(names=("mouthSmile_L", "MouthSmileLeft"), neutral=rig.neutral, deltas=deltas, faces=rig.faces)


def _talking(frames: int) -> np.ndarray:
    t = np.arange(frames)
    params = np.zeros((frames, 56), np.float32)
    params[:, 50] = 0.1 * (1.0 + np.sin(t / 7.0))  # the jaw
    params[:, 18] = (t % 37 < 4).astype(np.float32)  # blinks
    params[:, 54] = 0.1 * np.sin(t / 50.0)  # the head turning
    return params


@pytest.mark.slow  # about 5 s: the float64 solves
def test_a_clip_solved_in_windows_is_one_whole_clip_solve_where_the_windows_join():
    """Windows tied to the weights kept before them and solved past their end by the look-ahead: where
    they join, the weights are the whole clip's solve's to the solver's own precision (float32: the
    whole solve's own distance from the exact one), and every frame is kept once."""
    rig, face = low_rig(), low_face()
    penalties = Penalties(smoothness=0.05, l2=1e-2)  # a short look-ahead: a small test
    params, window = _talking(400), 50
    retargeter = Retargeter.for_face(rig, face, penalties)
    ahead, bound = retargeter.lookahead()
    assert 10 < ahead < 100 and bound <= 1e-7
    whole32, windowed32 = retargeter(params, window=None), retargeter(params, window=window)
    assert (windowed32.windows, windowed32.lookahead, windowed32.seam_bound) == (8, ahead, bound)
    assert whole32.windows == 1 and windowed32.weights.shape == whole32.weights.shape
    np.testing.assert_allclose(windowed32.head_angles, whole32.head_angles, atol=1e-12)
    assert abs(windowed32.rms_error - whole32.rms_error) < 1e-4 * whole32.rms_error
    with jax_flag("jax_enable_x64", True):  # the exact solve, and the windows solved as exactly
        exact = Retargeter.for_face(rig, face, penalties)
        truth = exact(params, window=None, tol=1e-13, max_iter=100_000).weights
        windowed64 = exact(params, window=window, tol=1e-13, max_iter=100_000)
    seams = np.r_[[s + o for s in range(window, 400, window) for o in (-1, 0)]]
    seam_error = np.abs(windowed64.weights - truth)[seams].max()
    precision32 = np.abs(whole32.weights - truth).max()
    error32 = np.abs(windowed32.weights - truth)[seams].max()
    print(f"look-ahead {ahead} frames; seams: float64 {seam_error:.1e} from the whole solve (bound "
          f"{windowed64.seam_bound:.0e}), float32 {error32:.1e} (the float32 whole solve: {precision32:.1e})")
    assert seam_error < 1e-9
    assert error32 <= 2 * precision32 + 1e-7


def test_the_files_written_a_chunk_of_frames_at_a_time_are_the_same_whatever_the_chunk(tmp_path, monkeypatch):
    from jaxtalk.export import gltf, recording, write_weights_json

    rig = low_rig()
    weights = rig_animation(50, seed=2)
    turns = np.c_[np.linspace(0.0, 6.0, 50), np.linspace(-0.2, 0.2, 50), np.zeros(50)]  # past pi: signs flip
    rot = Rotation.from_euler("YXZ", turns).as_matrix()
    pivot = np.array([0.0, -0.1, 0.0])

    def write(folder):
        folder.mkdir()
        export_rig_animation(rig, weights, folder / "a.glb", fps=29.97, head_rotation=rot, pivot=pivot)
        write_live_link_csv(folder / "a.csv", rig.names, weights, turns, fps=29.97)
        write_weights_json(folder / "a.json", names=rig.names, weights=weights, head_angles=turns, fps=29.97,
                           extra={"note": "x"})

    write(tmp_path / "one")  # every frame in one chunk
    monkeypatch.setattr(gltf, "_KEY_ROWS", 7)
    monkeypatch.setattr(recording, "_ROWS", 5)
    write(tmp_path / "chunks")
    for name in ("a.glb", "a.csv"):
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "chunks" / name).read_bytes(), name
    one, chunks = (json.loads((tmp_path / f / "a.json").read_text()) for f in ("one", "chunks"))
    assert one == chunks and np.allclose(one["weights"], weights, atol=5e-7) and one["note"] == "x"
    q = GlbAnimation(tmp_path / "chunks" / "a.glb")
    np.testing.assert_allclose(q.morph_weights(), weights, atol=1e-6)
    expected = np.einsum("ij,vj->vi", rot[37], rig.vertices(weights[37:38])[0] - pivot) + pivot
    np.testing.assert_allclose(q.vertices(37), expected, atol=1e-5)
