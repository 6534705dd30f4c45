"""LinearFaceModel: Rodrigues, skinning against a brute-force reference, gradients, jit/vmap, errors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxtalk.face import builtin_face, rodrigues
from jaxtalk.face.model import _vertices_seq_jit


@pytest.fixture(scope="module")
def face():
    return builtin_face(resolution="low")


def reference_vertices(model, params: np.ndarray) -> np.ndarray:
    """FLAME-style LBS written out directly in NumPy/SciPy: one joint at a time, vertex by vertex."""
    params = np.asarray(params, np.float64)
    exp, jaw, neck = params[:50], params[50:53], params[53:56]
    rest = np.asarray(model.template, np.float64) + np.asarray(model.exp_basis, np.float64) @ exp
    joints = np.asarray(model.joints, np.float64) + np.asarray(model.joint_exp_basis, np.float64) @ exp
    aa = np.zeros((model.num_joints, 3))
    aa[model.neck_joint], aa[model.jaw_joint] = neck, jaw
    local = Rotation.from_rotvec(aa).as_matrix()
    if model.pose_basis is not None:
        rest = rest + np.asarray(model.pose_basis, np.float64) @ (local[1:] - np.eye(3)).reshape(-1)
    # 4x4 homogeneous chain: G_j = G_parent @ [R_j | J_j - R_j J_j].
    chain = []
    for j, parent in enumerate(model.parents):
        g = np.eye(4)
        g[:3, :3] = local[j]
        g[:3, 3] = joints[j] - local[j] @ joints[j]
        chain.append(g if parent < 0 else chain[parent] @ g)
    weights = np.asarray(model.weights, np.float64)
    out = np.zeros_like(rest)
    for i in range(len(rest)):
        blend = sum(weights[i, j] * chain[j] for j in range(model.num_joints))
        out[i] = blend[:3, :3] @ rest[i] + blend[:3, 3]
    return out


def test_rodrigues_matches_scipy_including_tiny_angles(float64):
    rng = np.random.default_rng(0)
    aa = np.concatenate([rng.normal(size=(20, 3)), 1e-5 * rng.normal(size=(5, 3)), np.zeros((1, 3))])
    got = np.asarray(rodrigues(jnp.asarray(aa)))
    np.testing.assert_allclose(got, Rotation.from_rotvec(aa).as_matrix(), atol=1e-12)


def test_rodrigues_gradient_at_zero_is_the_cross_product_generator(float64):
    # d(R x)/d(aa) at aa = 0 is -[x]_x (since R x ~ x + aa x x): finite, no NaN.
    x = jnp.array([0.3, -0.2, 0.5])
    jac = jax.jit(jax.jacfwd(lambda a: rodrigues(a) @ x))(jnp.zeros(3))
    expected = -np.array([[0, -x[2], x[1]], [x[2], 0, -x[0]], [-x[1], x[0], 0]])
    np.testing.assert_allclose(np.asarray(jac), expected, atol=1e-12)
    grad = jax.jit(jax.grad(lambda a: jnp.sum(rodrigues(a) ** 3)))(jnp.zeros(3))
    assert np.all(np.isfinite(np.asarray(grad)))


def test_zero_params_give_the_template(face):
    np.testing.assert_array_equal(np.asarray(face.vertices(jnp.zeros(56))), np.asarray(face.template))


def test_vertices_match_bruteforce_lbs(face):
    rng = np.random.default_rng(1)
    params = np.zeros(56)
    params[:50] = 0.8 * rng.normal(size=50)
    params[50:53] = [0.3, 0.05, -0.04]
    params[53:56] = [0.1, -0.25, 0.07]
    got = np.asarray(face.vertices(jnp.asarray(params, jnp.float32)))
    np.testing.assert_allclose(got, reference_vertices(face, params), atol=2e-6)


def test_neck_rotation_is_rigid_about_the_neck_joint(face):
    aa = np.array([0.2, -0.3, 0.1])
    params = np.zeros(56, np.float32)
    params[53:56] = aa
    got = np.asarray(face.vertices(params))
    r = Rotation.from_rotvec(aa).as_matrix()
    joint = np.asarray(face.joints)[face.neck_joint]
    expected = (np.asarray(face.template) - joint) @ r.T + joint
    np.testing.assert_allclose(got, expected, atol=2e-6)


def test_jaw_moves_only_jaw_weighted_vertices(face):
    params = np.zeros(56, np.float32)
    params[50] = 0.3
    moved = np.linalg.norm(np.asarray(face.vertices(params)) - np.asarray(face.template), axis=1)
    jaw_w = np.asarray(face.weights)[:, face.jaw_joint]
    assert moved[jaw_w < 1e-6].max() < 1e-6
    assert moved[jaw_w > 0.99].min() > 0.005  # everything on the jaw moves by at least 5 mm


def test_gradient_matches_finite_differences(face, float64):
    model = face.astype(jnp.float64)
    rng = np.random.default_rng(2)
    probe = jnp.asarray(rng.normal(size=(model.num_vertices, 3)))

    def loss(p):
        # Quadratic in the vertices so the second-order terms of the rotations are exercised too.
        v = model.vertices(p)
        return jnp.sum(v * probe) + jnp.sum(v**2)

    # One compiled program gives both the gradient and the values for the finite differences.
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    random_point = np.concatenate([0.5 * rng.normal(size=50), [0.2, 0.03, -0.02], [0.05, 0.1, -0.03]])
    for point in (np.zeros(56), random_point):  # zero: the Rodrigues singular point
        g = np.asarray(value_and_grad(jnp.asarray(point))[1])
        assert np.all(np.isfinite(g))
        for i in (0, 18, 40, 50, 51, 52, 53, 54, 55):
            e = np.zeros(56)
            e[i] = 1e-6
            hi, lo = value_and_grad(jnp.asarray(point + e))[0], value_and_grad(jnp.asarray(point - e))[0]
            np.testing.assert_allclose(g[i], float(hi - lo) / 2e-6, rtol=1e-6, atol=1e-8)


def test_sequence_api_is_the_per_frame_api_vmapped(face):
    rng = np.random.default_rng(3)
    params = jnp.asarray(0.3 * rng.normal(size=(4, 56)), jnp.float32)
    seq = np.asarray(face.vertices_seq(params))
    lms = np.asarray(face.landmarks_seq(params))
    assert seq.shape == (4, face.num_vertices, 3) and lms.shape == (4, 68, 3)
    for t in range(4):
        np.testing.assert_allclose(seq[t], np.asarray(face.vertices(params[t])), atol=1e-6)
        np.testing.assert_allclose(lms[t], np.asarray(face.landmarks(params[t])), atol=1e-6)
    # The landmark path poses only the landmark triangles: same as reading them off all vertices.
    np.testing.assert_allclose(lms, np.asarray(face.landmarks_from_vertices(seq)), atol=1e-6)
    np.testing.assert_allclose(np.asarray(jax.vmap(face.vertices)(params)), seq, atol=1e-6)


def test_model_crosses_jit_and_identities_share_one_compilation(face):
    other = builtin_face(7, resolution="low")

    @jax.jit
    def mouth_y(model, p):
        return model.vertices_seq(p)[:, :, 1].mean()

    p = jnp.zeros((3, 56))
    assert float(mouth_y(face, p)) != float(mouth_y(other, p))
    assert mouth_y._cache_size() == 1
    face.vertices_seq(p)
    before = _vertices_seq_jit._cache_size()
    other.vertices_seq(p)
    assert _vertices_seq_jit._cache_size() == before


@pytest.mark.parametrize(
    "params, match",
    [
        (np.zeros(55), r"shape \(56,\)"),
        (np.zeros((2, 56)), r"shape \(56,\)"),
        (np.full(56, np.nan), "NaN"),
    ],
)
def test_bad_frame_params_raise(face, params, match):
    with pytest.raises(ValueError, match=match):
        face.vertices(jnp.asarray(params, jnp.float32))


@pytest.mark.parametrize(
    "params, match",
    [(np.zeros((3, 50)), r"\(T, 56\)"), (np.zeros((0, 56)), "zero frames"), (np.zeros(56), r"\(T, 56\)")],
)
def test_bad_sequence_params_raise(face, params, match):
    with pytest.raises(ValueError, match=match):
        face.landmarks_seq(jnp.asarray(params, jnp.float32))


def test_nan_inside_a_sequence_is_reported(face):
    p = np.zeros((5, 56), np.float32)
    p[3, 51] = np.inf
    with pytest.raises(ValueError, match=r"index \[3, 51\]"):
        face.vertices_seq(p)


@pytest.mark.parametrize(
    "changes, match",
    [
        ({"parents": (0, 0)}, "parents must list each joint after its parent"),
        ({"jaw_joint": 0}, "neck_joint and jaw_joint must differ"),
        ({"neck_joint": 5}, "must index one of the 2 joints"),
    ],
)
def test_inconsistent_models_are_rejected(face, changes, match):
    import dataclasses

    with pytest.raises(ValueError, match=match):
        dataclasses.replace(face, **changes)
