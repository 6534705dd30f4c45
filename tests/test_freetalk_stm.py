"""FreeTalk STM: vertex-permutation equivariance, any topology, per-frame decoding, padding, errors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.face import builtin_face
from jaxtalk.geometry.topology import make_variant
from jaxtalk.models.freetalk import stm
from jaxtalk.models.freetalk.config import FUSIONS, STMConfig
from helpers import assert_recipe_resumes_exactly

K = 12



def _config(**kw) -> STMConfig:
    base = dict(mesh_feature_dim=16, encoder_width=16, encoder_blocks=1, decoder_width=16, decoder_blocks=1,
                gcn_hidden=16, index_encoding_dim=8, attention_dim=16, attention_heads=4, num_eigenpairs=K)
    return STMConfig(**{**base, **kw})


@pytest.fixture(scope="module")
def face():
    f = builtin_face(0, resolution="low")
    return np.asarray(f.template, np.float64), np.asarray(f.faces)


@pytest.fixture(scope="module")
def model(face):
    cfg = _config()
    mesh = stm.prepare_mesh(*face, cfg)
    return cfg, mesh, stm.init_params(cfg, jax.random.key(0), mesh)


def _motion(frames=3, seed=0):
    return (0.004 * np.random.default_rng(seed).normal(size=(frames, 68, 3))).astype(np.float32)


def test_presets_and_fused_width():
    paper = STMConfig.paper()
    assert (paper.mesh_feature_dim, paper.gcn_layers, paper.gcn_hidden) == (128, 3, 128)
    assert (paper.attention_heads, paper.attention_dim) == (4, 128)
    assert (paper.velocity_weight, paper.acceleration_weight) == (0.5, 0.2)
    assert paper.fused_dim == 128 + 204 + 128  # [f_i | g_t | c_t,i]
    assert STMConfig(fusion="concat").fused_dim == 128 + 204
    assert STMConfig(fusion="ca").fused_dim == 128 + 128
    with pytest.raises(ValueError, match="fusion"):
        STMConfig(fusion="sum")
    with pytest.raises(ValueError, match="divisible"):
        STMConfig(attention_dim=30, attention_heads=4)


def test_outputs_permute_with_the_mesh_vertices(model, face):
    cfg, mesh, params = model
    vertices, faces = face
    perm = np.random.default_rng(1).permutation(len(vertices))
    inverse = np.argsort(perm)
    permuted = stm.prepare_mesh(vertices[perm], inverse[faces], cfg)  # vertex i of the new mesh = perm[i]
    motion = _motion()
    out = stm.apply(params, cfg, mesh, motion)
    out_p = stm.apply(params, cfg, permuted, motion)
    # Operators are recomputed on the permuted mesh (its own eigensolve), so equality is up to the
    # solver's tolerance; the outputs are displacements of a few millimetres.
    scale = float(jnp.abs(out).max())
    assert scale > 1e-5
    np.testing.assert_allclose(out_p, out[:, perm], atol=2e-3 * scale)


def test_runs_on_topologies_it_was_not_initialised_on(model, face):
    cfg, mesh, params = model
    motion = _motion(2)
    for kind in ("subdivided", "decimated"):
        variant = make_variant(*face, kind, seed=0)
        other = stm.prepare_mesh(variant.vertices, variant.faces, cfg)
        assert other.num_vertices != mesh.num_vertices
        out = stm.apply(params, cfg, other, motion)
        assert out.shape == (2, other.num_vertices, 3) and bool(jnp.all(jnp.isfinite(out)))


def test_frames_are_decoded_independently_from_shared_features(model):
    cfg, mesh, params = model
    motion = _motion(3, seed=2)
    features = stm.stm_mesh_features(params, cfg, mesh)
    assert features.shape == (mesh.num_vertices, cfg.mesh_feature_dim)
    together = stm.stm_decode(params, cfg, features, motion, mesh)
    np.testing.assert_allclose(together, stm.apply(params, cfg, mesh, motion), rtol=1e-5, atol=1e-8)
    # Frame 1 alone (as a 1-frame sequence padded with itself) gives the same field.
    alone = stm.stm_decode(params, cfg, features, np.repeat(motion[1:2], 3, axis=0), mesh)
    np.testing.assert_allclose(alone[0], together[1], rtol=1e-4, atol=1e-7)
    # The decoder's stacked-frames layout (V, T, C) equals the one-frame (V, C) module path.
    decode_one = jax.jit(lambda p, f, d, o: stm.SparseToMesh(cfg).apply(
        p, f, d * cfg.displacement_scale, o, method=stm.SparseToMesh.decode_frame))
    single = decode_one(params, features, motion[1], mesh.ops)
    np.testing.assert_allclose(single / cfg.displacement_scale, together[1], rtol=1e-4, atol=1e-7)
    # Landmark motion drives the output: different displacements, different fields.
    assert float(jnp.abs(together[0] - together[1]).max()) > 1e-5
    # The flat ATS layout (T, 204) is accepted.
    flat = stm.stm_decode(params, cfg, features, motion.reshape(3, -1), mesh)
    np.testing.assert_allclose(flat, together, rtol=1e-6, atol=1e-9)


def test_fusion_matches_a_brute_force_reference(model):
    # W [f_i | g_t | c_t,i] with c_t,i the softmax attention of vertex i's query over all 68 landmark
    # keys, written out in float64 NumPy from the parameters (the per-mesh/per-frame split and the
    # merged output projection must not change the function).
    cfg, mesh, params = model
    p = jax.tree.map(lambda a: np.asarray(a, np.float64), params["params"])
    model_ = stm.SparseToMesh(cfg)
    features = np.asarray(stm.stm_mesh_features(params, cfg, mesh), np.float64)
    disp = _motion(1, seed=9)[0] * cfg.displacement_scale
    context = model_.apply(params, jnp.asarray(features, jnp.float32), method=stm.SparseToMesh.mesh_context)
    fused = np.asarray(model_.apply(params, context, jnp.asarray(disp), method=stm.SparseToMesh.fuse_frame))
    lms = np.asarray(model_.apply(params, jnp.asarray(disp), method=lambda m, d: m.landmarks(d)), np.float64)

    def dense(x, layer):
        return np.tensordot(x, layer["kernel"], axes=1) + layer.get("bias", 0.0)

    ca = p["cross_attention"]
    q, k, v = dense(features, ca["query"]), dense(lms, ca["key"]), dense(lms, ca["value"])
    heads, head_dim = q.shape[1:]
    expected = dense(features, p["fuse_features"]) + disp.reshape(-1) @ p["fuse_global"]["kernel"]
    for i in range(0, mesh.num_vertices, 97):
        c = np.zeros((heads, head_dim))
        for h in range(heads):
            logits = k[:, h] @ q[i, h] / np.sqrt(head_dim)
            w = np.exp(logits - logits.max())
            c[h] = (w / w.sum()) @ v[:, h]
        np.testing.assert_allclose(fused[i], expected[i] + np.einsum("hd,hdo->o", c, ca["out"]["kernel"]),
                                   rtol=2e-4, atol=2e-5)


def test_padding_vertices_do_not_change_real_vertices(model, face):
    cfg, mesh, params = model
    padded = stm.prepare_mesh(*face, cfg, num_vertices=mesh.num_vertices + 37)
    assert not bool(padded.valid[-1]) and bool(padded.valid[mesh.num_vertices - 1])
    motion = _motion(2, seed=3)
    out = stm.apply(params, cfg, mesh, motion)
    out_pad = stm.apply(params, cfg, padded, motion)
    np.testing.assert_allclose(out_pad[:, : mesh.num_vertices], out, rtol=1e-4, atol=1e-7)


@pytest.mark.slow
def test_loss_ignores_padding_rows_and_trains_all_parts(model, face):
    cfg, mesh, params = model
    n = mesh.num_vertices
    variant = make_variant(*face, "decimated", seed=0)
    total = n + 5
    meshes = stm.stack_meshes([
        stm.prepare_mesh(*face, cfg, num_vertices=total, degree=12),
        stm.prepare_mesh(variant.vertices, variant.faces, cfg, num_vertices=total, degree=12),
    ])
    rng = np.random.default_rng(4)
    batch = {
        "mesh": np.array([0, 1]),
        "landmarks": np.stack([_motion(4, 5), _motion(4, 6)]),
        "vertices": (0.003 * rng.normal(size=(2, 4, total, 3))).astype(np.float32),
    }
    value_and_grad = jax.jit(jax.value_and_grad(stm.make_loss_fn(cfg, meshes), has_aux=True))
    (loss, parts), grads = value_and_grad(params, batch, jax.random.key(0))
    assert np.isfinite(float(loss))
    for name in ("encoder", "decoder", "landmarks", "cross_attention"):
        assert max(float(jnp.abs(g).max()) for g in jax.tree.leaves(grads["params"][name])) > 0, name
    junk = dict(batch, vertices=batch["vertices"].copy())
    junk["vertices"][0, :, n:] = 7.0  # padding rows of the base mesh
    junk["vertices"][1, :, len(variant.vertices):] = -7.0
    np.testing.assert_allclose(value_and_grad(params, junk, jax.random.key(0))[0][0], loss, rtol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("fusion", FUSIONS[:-1])
def test_ablation_fusions_run(face, fusion):
    cfg = _config(fusion=fusion, num_eigenpairs=8)
    mesh = stm.prepare_mesh(*face, cfg)
    params = stm.init_params(cfg, jax.random.key(1), mesh)
    assert ("cross_attention" in params["params"]) == (fusion != "concat")
    assert ("gcn_0" in params["params"].get("landmarks", {})) is False
    out = stm.apply(params, cfg, mesh, _motion(1))
    assert out.shape == (1, mesh.num_vertices, 3)


def test_bad_inputs_raise_clear_errors(model, face):
    cfg, mesh, params = model
    with pytest.raises(ValueError, match=r"shape \(frames, 68, 3\)"):
        stm.apply(params, cfg, mesh, np.zeros((3, 67, 3), np.float32))
    with pytest.raises(ValueError, match=r"shape \(frames, 68, 3\)"):
        stm.apply(params, cfg, mesh, np.zeros((3, 68), np.float32))
    bad = _motion(2)
    bad[1, 4, 0] = np.inf
    with pytest.raises(ValueError, match="NaN/inf"):
        stm.apply(params, cfg, mesh, bad)
    with pytest.raises(ValueError, match="no frames"):
        stm.apply(params, cfg, mesh, np.zeros((0, 68, 3), np.float32))
    with pytest.raises(ValueError, match="features must have shape"):
        stm.stm_decode(params, cfg, jnp.zeros((10, cfg.mesh_feature_dim)), _motion(1), mesh)
    with pytest.raises(ValueError, match="num_eigenpairs"):
        stm.prepare_mesh(face[0][:10], face[1][:2], cfg)
    with pytest.raises(ValueError, match="single mesh"):
        stm.stm_mesh_features(params, cfg, stm.stack_meshes([mesh, mesh]))


def test_prepare_meshes_pads_to_common_shapes(face):
    cfg = _config(num_eigenpairs=8)
    variant = make_variant(*face, "subdivided", seed=0)
    meshes = stm.prepare_meshes([face, (variant.vertices, variant.faces)], cfg)
    shapes = [tuple(a.shape for a in jax.tree.leaves(m)) for m in meshes]
    assert shapes[0] == shapes[1] and meshes[0].num_vertices == len(variant.vertices)
    assert [int(m.valid.sum()) for m in meshes] == [len(face[0]), len(variant.vertices)]
    single = stm.prepare_mesh(*face, cfg)
    # Same operators on the real vertices (eigenvectors up to sign), zeros on the padding.
    np.testing.assert_allclose(np.abs(meshes[0].ops.evecs[: len(face[0])]), np.abs(single.ops.evecs), atol=1e-4)
    assert float(jnp.abs(meshes[0].ops.evecs[len(face[0]):]).max()) == 0.0
    assert stm.stack_meshes(meshes).vertices.shape == (2, len(variant.vertices), 3)
    with pytest.raises(ValueError, match="at least one"):
        stm.prepare_meshes([], cfg)


@pytest.mark.slow
def test_recipe_resumes_exactly_from_its_checkpoint(model, prepared_tiny, tmp_path):
    # STM's one training path, the recipe (one small mesh, 3-frame windows), resumed from its step-2
    # checkpoint (tests/helpers.py).
    from jaxtalk.models.freetalk.recipe import train_stm

    assert_recipe_resumes_exactly(train_stm, model[0], prepared_tiny, tmp_path, window_frames=3,
                                  meshes=((1, "decimated"),), held_out=((3, "retriangulated"),), val_clips=1)
