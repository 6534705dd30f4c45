"""DiffusionNet in Flax: diffusion limits, gradient layout, equivariance, padding, frame vmap."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from jaxtalk.geometry import diffusionnet as dn
from jaxtalk.geometry.operators import compute_operators


def bumpy_sphere(subdivisions: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    m = trimesh.creation.icosphere(subdivisions)
    rng = np.random.default_rng(seed)
    return np.asarray(m.vertices) * (1 + 0.1 * rng.random((len(m.vertices), 1))), np.asarray(m.faces)



@pytest.fixture(scope="module")
def mesh_ops():
    v, f = bumpy_sphere(2, 0)
    return v, f, compute_operators(v, f, 24)


CFG = dn.DiffusionNetConfig(in_features=3, out_features=2, width=8, num_blocks=2, mlp_hidden=(8,))



@jax.jit
def apply_one(params, x, ops):
    return dn.DiffusionNet(CFG).apply(params, x, ops)


@pytest.fixture(scope="module")
def params(mesh_ops):
    """One set of weights for every test (they do not depend on the vertex count)."""
    v, _, ops = mesh_ops
    init = jax.jit(dn.DiffusionNet(CFG).init)(jax.random.key(0), jnp.asarray(v, jnp.float32), dn.to_diffusion_operators(ops))
    # Non-zero diffusion times so that the tests exercise the spectral path, not only t = 1e-8.
    return jax.tree_util.tree_map_with_path(
        lambda path, p: p + 0.05 * (1 + jnp.arange(p.shape[0])) if "diffusion_time" in str(path) else p, init
    )


def test_zero_time_diffusion_is_projection_onto_eigenbasis(mesh_ops):
    _, _, ops = mesh_ops
    d = dn.to_diffusion_operators(ops)
    x = jnp.asarray(np.random.default_rng(0).standard_normal((ops.num_vertices, 4)), jnp.float32)
    out = dn.spectral_diffusion(x, d.mass, d.evals, d.evecs, jnp.zeros(4))
    phi = ops.evecs.astype(np.float64)
    proj = phi @ (phi.T @ (ops.mass[:, None] * np.asarray(x, np.float64)))
    np.testing.assert_allclose(out, proj, atol=1e-4)
    # Projection is idempotent, and leaves functions in the span unchanged.
    again = dn.spectral_diffusion(out, d.mass, d.evals, d.evecs, jnp.zeros(4))
    np.testing.assert_allclose(again, out, atol=1e-4)


def test_long_time_diffusion_tends_to_mass_weighted_mean(mesh_ops):
    _, _, ops = mesh_ops
    d = dn.to_diffusion_operators(ops)
    x = jnp.asarray(np.random.default_rng(1).standard_normal((ops.num_vertices, 3)), jnp.float32)
    out = dn.spectral_diffusion(x, d.mass, d.evals, d.evecs, jnp.full(3, 1e3))
    mean = (ops.mass[:, None] * np.asarray(x)).sum(0) / ops.mass.sum()
    np.testing.assert_allclose(out, np.broadcast_to(mean, out.shape), atol=1e-4)
    # Intermediate times interpolate: the deviation from the mean shrinks monotonically.
    dev = [float(jnp.abs(dn.spectral_diffusion(x, d.mass, d.evals, d.evecs, jnp.full(3, t)) - mean[None, :]).max())
           for t in (0.01, 0.1, 1.0)]
    assert dev[0] > dev[1] > dev[2]


def test_gradient_layout_matches_sparse_matvec(mesh_ops):
    _, _, ops = mesh_ops
    d = dn.to_diffusion_operators(ops, num_vertices=ops.num_vertices + 5, degree=20)
    x = np.random.default_rng(2).standard_normal((ops.num_vertices + 5, 3)).astype(np.float32)
    gx = dn.apply_gradient(d.grad_x, d.grad_index, jnp.asarray(x))
    gy = dn.apply_gradient(d.grad_y, d.grad_index, jnp.asarray(x))
    n = ops.num_vertices
    np.testing.assert_allclose(gx[:n], ops.grad_x @ x[:n], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(gy[:n], ops.grad_y @ x[:n], rtol=1e-5, atol=1e-5)
    np.testing.assert_array_equal(gx[n:], 0.0)
    # Frames between vertices and channels (the network's layout): each frame's gradient alone.
    frames = np.random.default_rng(8).standard_normal((ops.num_vertices + 5, 4, 3)).astype(np.float32)
    g_frames = dn.apply_gradient(d.grad_x, d.grad_index, jnp.asarray(frames))
    for t in range(4):
        np.testing.assert_allclose(g_frames[:n, t], ops.grad_x @ frames[:n, t], rtol=1e-5, atol=1e-5)


def test_max_degree_is_widest_one_ring(mesh_ops):
    _, f, ops = mesh_ops
    # Icosphere: valence 5 or 6, and each gradient row also stores its diagonal entry.
    valence = np.bincount(np.unique(np.sort(f[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0).ravel())
    assert dn.max_degree(ops) == valence.max() + 1 == 7
    assert dn.to_diffusion_operators(ops).grad_index.shape == (ops.num_vertices, 7)
    with pytest.raises(ValueError, match="degree=6 is smaller than the mesh's one-ring width 7"):
        dn.to_diffusion_operators(ops, degree=6)


def test_spectral_diffusion_of_stacked_frames_matches_each_frame(mesh_ops):
    _, _, ops = mesh_ops
    d = dn.to_diffusion_operators(ops)
    x = jnp.asarray(np.random.default_rng(10).standard_normal((ops.num_vertices, 3, 2)), jnp.float32)
    time = jnp.array([0.02, 0.5])
    out = dn.spectral_diffusion(x, d.mass, d.evals, d.evecs, time)
    for t in range(3):
        np.testing.assert_allclose(out[:, t], dn.spectral_diffusion(x[:, t], d.mass, d.evals, d.evecs, time), atol=1e-5)


def test_outputs_permute_with_vertices(mesh_ops, params):
    v, f, ops = mesh_ops
    perm = np.random.default_rng(3).permutation(len(v))
    ops_p = compute_operators(v[perm], np.argsort(perm)[f], 24)
    x = jnp.asarray(v, jnp.float32)
    d, d_p = dn.to_diffusion_operators(ops), dn.to_diffusion_operators(ops_p)
    out = apply_one(params, x, d)
    out_p = apply_one(params, x[perm], d_p)
    np.testing.assert_allclose(out_p, out[perm], atol=2e-4, rtol=1e-3)


def test_padding_does_not_change_real_vertices(params):
    meshes = [bumpy_sphere(1, 4), bumpy_sphere(2, 5)]
    ops_list = [compute_operators(v, f, 16) for v, f in meshes]
    stacked = dn.stack_operators(ops_list, num_vertices=180)
    rng = np.random.default_rng(6)
    x = np.zeros((2, 180, 3), np.float32)
    for i, (v, _) in enumerate(meshes):
        x[i, : len(v)] = v
        x[i, len(v) :] = rng.standard_normal((180 - len(v), 3))  # garbage in padding rows
    single = [dn.to_diffusion_operators(o) for o in ops_list]
    batched = dn.apply_meshes(CFG, params, jnp.asarray(x), stacked)
    for i, (v, _) in enumerate(meshes):
        alone = apply_one(params, jnp.asarray(v, jnp.float32), single[i])
        np.testing.assert_allclose(batched[i, : len(v)], alone, atol=1e-5)


def test_apply_frames_matches_per_frame_apply(mesh_ops, params):
    v, _, ops = mesh_ops
    d = dn.to_diffusion_operators(ops)
    frames = jnp.asarray(v[None] * np.linspace(0.5, 1.5, 4)[:, None, None], jnp.float32)
    out = dn.apply_frames(CFG, params, frames, d)
    assert out.shape == (4, len(v), 2)
    for t in range(4):
        np.testing.assert_allclose(out[t], apply_one(params, frames[t], d), atol=1e-5)


def test_diffusion_time_starts_at_zero_and_receives_gradient(mesh_ops, params):
    v, _, ops = mesh_ops
    d = dn.to_diffusion_operators(ops)
    assert float(jnp.abs(params["params"]["block_0"]["diffusion"]["diffusion_time"]).min()) > 0  # fixture moved it
    layer = dn.LearnedTimeDiffusion(3)
    x = jnp.asarray(v, jnp.float32)
    variables = jax.jit(layer.init)(jax.random.key(1), x, d)
    assert float(jnp.abs(variables["params"]["diffusion_time"]).max()) == 0.0
    target = dn.spectral_diffusion(x, d.mass, d.evals, d.evecs, jnp.full(3, 0.3))
    grads = jax.jit(jax.grad(lambda p: jnp.sum((layer.apply(p, x, d) - target) ** 2)))(variables)
    # A plain maximum(t, 1e-8) would give exactly zero here and t could never move; the
    # straight-through clamp passes d loss / d t, which is negative (the target is smoother).
    assert float(grads["params"]["diffusion_time"].max()) < 0
    out = jax.jit(layer.apply)(variables, x, d)  # forward value uses t = 1e-8 ~ projection
    proj = dn.spectral_diffusion(x, d.mass, d.evals, d.evecs, jnp.zeros(3))
    np.testing.assert_allclose(out, proj, atol=1e-5)


def test_time_gradient_matches_finite_differences(mesh_ops, float64):
    _, _, ops = mesh_ops
    d = jax.tree.map(lambda a: a.astype(jnp.float64) if a.dtype == jnp.float32 else a, dn.to_diffusion_operators(ops))
    x = jnp.asarray(np.random.default_rng(7).standard_normal((ops.num_vertices, 2)))

    def f(t):
        return jnp.sum(jnp.sin(dn.spectral_diffusion(x, d.mass, d.evals, d.evecs, t)))

    t0 = jnp.array([0.05, 0.2])
    g = jax.jit(jax.grad(f))(t0)
    eps = 1e-6
    f_jit = jax.jit(f)
    fd = [(f_jit(t0.at[i].add(eps)) - f_jit(t0.at[i].add(-eps))) / (2 * eps) for i in range(2)]
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_shape_errors_are_clear(mesh_ops, key):  # errors are raised at trace time, before compiling
    _, _, ops = mesh_ops
    d = dn.to_diffusion_operators(ops)
    with pytest.raises(ValueError, match=r"features must have shape \(V, 3\)"):
        dn.DiffusionNet(CFG).init(key, jnp.zeros((ops.num_vertices, 4)), d)
    with pytest.raises(ValueError, match="features have 10 vertices"):
        dn.DiffusionNet(CFG).init(key, jnp.zeros((10, 3)), d)
    with pytest.raises(ValueError, match="num_vertices=10 is smaller"):
        dn.to_diffusion_operators(ops, num_vertices=10)
    with pytest.raises(ValueError, match="same number of eigenpairs"):
        dn.stack_operators([ops, ops.truncated(8)])
    with pytest.raises(ValueError, match="width must be >= 1"):
        dn.DiffusionNetConfig(width=0)


def test_gradient_features_ignore_tangent_frame_rotation():
    rng = np.random.default_rng(9)
    gx, gy = (jnp.asarray(rng.standard_normal((50, 6)), jnp.float32) for _ in range(2))
    theta = jnp.asarray(rng.uniform(0, 2 * np.pi, (50, 1)), jnp.float32)  # one angle per vertex
    layer = dn.SpatialGradientFeatures(6)
    variables = jax.jit(layer.init)(jax.random.key(2), gx, gy)
    apply = jax.jit(layer.apply)
    rx = jnp.cos(theta) * gx - jnp.sin(theta) * gy
    ry = jnp.sin(theta) * gx + jnp.cos(theta) * gy
    base = apply(variables, gx, gy)
    np.testing.assert_allclose(apply(variables, rx, ry), base, atol=1e-5)
    # Not trivially constant: a non-rotation (swapping X and Y, a reflection) changes the output.
    assert float(jnp.abs(apply(variables, gy, gx) - base).max()) > 1e-2
    # The three-matmul complex product equals the textbook four-matmul one.
    a_re = variables["params"]["A_re"]["kernel"]
    a_im = variables["params"]["A_im"]["kernel"]
    b_re, b_im = gx @ a_re - gy @ a_im, gy @ a_re + gx @ a_im
    np.testing.assert_allclose(base, jnp.tanh(gx * b_re + gy * b_im), atol=1e-5)
