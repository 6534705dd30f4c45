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
from jaxtalk.export.solver import DEFAULT_MAX_ITER, DEFAULT_TOL, symmetry_matrix
from jaxtalk.face import builtin_face

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


def causal_reference(a, b, *, smoothness=0.0, l1=0.0, l2=0.0, symmetry=0.0, pairs=(), previous=None,
                     lower=0.0, upper=1.0):
    """The same problem solved frame after frame by scipy's BVLS, each frame one bounded least squares tied to
    the previous frame's solution.

    The L1 term on [0, 1] is linear, ``l1 sum(w)``; it enters as a shifted target ``b - a (a^T a)^+ l1 1``
    (same gradient), the other penalties as extra rows.
    """
    k = a.shape[1]
    shift = a @ np.linalg.lstsq(a.T @ a, np.full(k, l1), rcond=None)[0]
    out = []
    for row in b:
        blocks, rhs = [a], [row - shift]
        if l2:
            blocks.append(np.sqrt(l2) * np.eye(k))
            rhs.append(np.zeros(k))
        for left, right in pairs:
            tie = np.zeros((1, k))
            tie[0, left], tie[0, right] = 1.0, -1.0
            blocks.append(np.sqrt(symmetry) * tie)
            rhs.append(np.zeros(1))
        if smoothness and previous is not None:
            blocks.append(np.sqrt(smoothness) * np.eye(k))
            rhs.append(np.sqrt(smoothness) * previous)
        previous = lsq_linear(np.concatenate(blocks), np.concatenate(rhs), bounds=(lower, upper), method="bvls",
                              tol=1e-14).x
        out.append(previous)
    return np.stack(out)


# ---- the solver -----------------------------------------------------------------------------------------
@pytest.mark.parametrize("seed", range(4))
def test_solver_matches_scipy_bvls_per_frame_in_float32(seed):
    a, b = random_problem(seed)
    ref = np.stack([lsq_linear(a, row, bounds=(0.0, 1.0), method="bvls", tol=1e-14).x for row in b])
    weights, info = solve_weights(a.T @ a, b @ a)
    assert np.asarray(weights).dtype == np.float32 and bool(info.converged)
    # float32 rounding of the normal equations is the floor (a few units in the last place of a weight)
    assert np.abs(np.asarray(weights) - ref).max() < 1e-6, info
    assert 0.05 < (ref == 0).mean() + (ref == 1).mean() < 0.95  # both free and bound weights are tested


def test_solver_matches_scipy_bvls_within_its_tolerance_on_random_problems_in_float64(float64):
    """Sizes, conditioning, penalties and boxes drawn at random (many weights on their bounds): the solve is
    scipy's frame after frame within the solver's tolerance, in a few Newton steps per frame."""
    errors, steps = [], []
    for seed in range(20):
        rng = np.random.default_rng(100 + seed)
        k = (3, 11, 29)[seed % 3]  # three programs
        a, b = random_problem(100 + seed, frames=15, rows=k + int(rng.integers(0, 40)), k=k)
        b = b * rng.uniform(0.5, 4.0)  # far outside the box too
        penalties = dict(smoothness=float(rng.choice([0.0, 0.1, 3.0])), l2=float(rng.choice([0.0, 1e-3])))
        lower = rng.choice([0.0, -0.5], size=k)
        upper = lower + rng.uniform(0.2, 2.0, size=k)
        ref = causal_reference(a, b, lower=lower, upper=upper, **penalties)
        weights, info = solve_weights(a.T @ a, b @ a, Penalties(**penalties), lower=lower, upper=upper)
        assert np.asarray(weights).dtype == np.float64 and bool(info.converged)
        errors.append(np.abs(np.asarray(weights) - ref).max())
        steps.append(int(info.iterations))
        held = np.isclose(ref, lower) | np.isclose(ref, upper)
        assert 0.05 < held.mean() < 0.95, held.mean()
    print(f"largest error {max(errors):.1e}, at most {max(steps)} Newton steps a frame")
    assert max(errors) < DEFAULT_TOL and max(steps) < 10


def test_a_rank_deficient_fit_still_reaches_the_least_squares_optimum():
    a, b = random_problem(5, k=8)
    a[:, 3] = a[:, 2]  # two shapes the fit cannot tell apart
    a[:, 5] = 0.0  # a shape that moves nothing
    weights, info = solve_weights(a.T @ a, b @ a)
    weights = np.asarray(weights, np.float64)
    ref = causal_reference(a, b)
    assert np.all(np.isfinite(weights)) and bool(info.converged)
    assert 0.5 * np.sum((weights @ a.T - b) ** 2) <= 0.5 * np.sum((ref @ a.T - b) ** 2) * (1 + 1e-6)


@pytest.mark.parametrize("penalties", [dict(smoothness=2.0), dict(l1=3.0), dict(l2=5.0),
                                       dict(symmetry=4.0), dict(smoothness=0.5, l1=1.0, l2=0.1, symmetry=1.0)])
def test_each_penalty_matches_the_stacked_least_squares_reference(float64, penalties):
    a, b = random_problem(3, frames=12, k=6)
    pairs = [(0, 1), (2, 4)]
    ref = causal_reference(a, b, pairs=pairs, **penalties)
    weights, _ = solve_weights(a.T @ a, b @ a, Penalties(**penalties), symmetry=symmetry_matrix(pairs, 6))
    assert np.abs(np.asarray(weights) - ref).max() < 1e-10


def test_a_streamed_chunk_is_tied_to_the_previous_frame(float64):
    a, b = random_problem(5, frames=10, k=6)
    previous = np.linspace(0.0, 1.0, 6)
    ref = causal_reference(a, b, smoothness=3.0, previous=previous)
    weights, _ = solve_weights(a.T @ a, b @ a, Penalties(smoothness=3.0), previous=previous)
    assert np.abs(np.asarray(weights) - ref).max() < 1e-10
    free, _ = solve_weights(a.T @ a, b @ a, Penalties(smoothness=3.0))
    assert np.abs(np.asarray(free)[0] - previous).sum() > np.abs(np.asarray(weights)[0] - previous).sum()


def test_a_clip_cut_anywhere_solves_to_the_whole_clips_weights():
    """The smoothness term looks back only: chunks tied to the last weights of the chunk before give the
    whole clip's weights, wherever the cuts fall."""
    a, b = random_problem(8, frames=40, k=8)
    penalties = Penalties(smoothness=0.5, l2=1e-3)
    whole, _ = solve_weights(a.T @ a, b @ a, penalties)
    for cuts in ([1, 2, 3, 20], [13, 14, 39], list(range(1, 40, 7))):
        pieces, previous = [], None
        for start, stop in zip([0, *cuts], [*cuts, 40]):
            w, _ = solve_weights(a.T @ a, b[start:stop] @ a, penalties, previous=previous)
            pieces.append(np.asarray(w))
            previous = pieces[-1][-1]
        assert np.abs(np.concatenate(pieces) - np.asarray(whole)).max() <= DEFAULT_TOL, cuts


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


def test_an_obj_folder_rig_finds_its_neutral_by_a_word_of_its_name(tmp_path):
    rig = low_rig()
    folder = tmp_path / "kit"
    folder.mkdir()
    _write_obj(folder / "generic_neutral_mesh.obj", rig.neutral, rig.faces)  # as ICT-FaceKit names it
    _write_obj(folder / "jawOpen.obj", rig.neutral + rig.deltas[17], rig.faces)
    _write_obj(folder / "mouthSmile_L.obj", rig.neutral + rig.deltas[23], rig.faces)
    objs = load_rig(folder)
    assert objs.names == ("jawOpen", "mouthSmile_L")
    np.testing.assert_allclose(objs.neutral, rig.neutral, atol=1e-6)
    _write_obj(folder / "neutral.obj", rig.neutral, rig.faces)
    with pytest.raises(ValueError, match="several neutral shapes"):
        load_rig(folder)


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
    from jaxtalk.testing import faces as fs
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


def test_streamed_chunks_of_any_length_give_the_whole_clips_weights(speech_clip):
    """A stream cut anywhere (chunks of 1 to 24 frames) is the whole clip retargeted at once: the live
    server's arkit output is what ``jaxtalk retarget`` writes for the same motion."""
    motion, _ = speech_clip
    retargeter = Retargeter.for_face(low_rig(), low_face())
    whole = retargeter(motion)
    rng = np.random.default_rng(0)
    state, chunks, angles, start = retargeter.init_stream(), [], [], 0
    while start < len(motion):
        stop = start + int(rng.integers(1, 25))
        state, result = retargeter.stream_step(state, motion[start:stop], fit_error=False)
        chunks.append(result.weights)
        angles.append(result.head_angles)
        assert np.isnan(result.rms_error)
        start = stop
    assert len(chunks) > 10
    assert np.abs(np.concatenate(chunks) - whole.weights).max() <= DEFAULT_TOL
    np.testing.assert_allclose(np.concatenate(angles), whole.head_angles, atol=1e-12)


def test_the_parameters_right_hand_side_is_the_posed_vertices_projected(float64):
    """The precomputed map from a frame's parameters to ``B^T d`` is the face posed and projected, for the
    built-in face and for a FLAME-like one (five joints, joints regressed from the expression, pose
    correctives)."""
    import jax.numpy as jnp

    from jaxtalk.export.retarget import _param_projection, _param_rhs, _skeleton_model
    from test_export_gltf import flame_like_model, head_motion

    params = head_motion(30).astype(np.float64)
    still = params.copy()
    still[:, 53:] = 0.0  # the head's rotation is reported, not fitted
    for face in (low_face(), flame_like_model()):
        rng = np.random.default_rng(1)
        bs = rng.normal(size=(face.num_vertices, 3, 7)) * (rng.uniform(size=(face.num_vertices, 1, 1)) < 0.7)
        got = _param_rhs(_skeleton_model(face, np.float64), _param_projection(face, bs), params)
        exact = face.astype(jnp.float64)
        displacements = np.asarray(exact.vertices_seq(still)) - np.asarray(exact.template)
        want = np.einsum("vck,tvc->tk", bs, displacements)
        assert np.abs(np.asarray(got) - want).max() < 1e-12 * np.abs(want).max(), face.name


def test_the_rigs_solve_is_scipys_frame_after_frame(speech_clip, float64):
    """On the built-in rig and speech motion (an ill-conditioned fit: shapes 50 times apart in size), the
    retargeter's weights are scipy's BVLS solution of each frame's problem, tied to the previous frame."""
    motion, _ = speech_clip
    retargeter = Retargeter.for_face(low_rig(), low_face())
    motion = motion[:60]
    result = retargeter(motion)
    p = retargeter.penalties
    hessian = np.asarray(retargeter._gram) + p.l2 * np.eye(52)
    rhs = np.asarray(retargeter.param_rhs(motion))
    # 1/2 w^T H w - c^T w + s/2 |w - w_prev|^2 is 1/2 |R w - R^-T c|^2 + s/2 |w - w_prev|^2 (+ const), H = R^T R
    root = np.linalg.cholesky(hessian).T
    target = np.linalg.solve(root.T, rhs.T).T
    ref = causal_reference(root, target, smoothness=p.smoothness)
    error = np.abs(result.weights - ref).max()
    print(f"largest difference from scipy: {error:.1e} ({result.iterations} Newton steps at most)")
    assert error < DEFAULT_TOL and result.iterations < 20


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


def test_a_clip_solved_in_windows_is_the_whole_clip_solved_at_once():
    """Windows tied to the weights kept before them give the whole clip's weights, fit error and head
    angles, every frame kept once (the last window starts early, to the same weights)."""
    rig, face = low_rig(), low_face()
    params, window = _talking(400), 60
    retargeter = Retargeter.for_face(rig, face)
    whole, windowed = retargeter(params, window=None), retargeter(params, window=window)
    assert whole.windows == 1 and windowed.windows == 7
    assert np.abs(windowed.weights - whole.weights).max() <= DEFAULT_TOL
    np.testing.assert_allclose(windowed.head_angles, whole.head_angles, atol=1e-12)
    assert abs(windowed.rms_error - whole.rms_error) < 1e-6 * whole.rms_error


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
