"""FLAME loader: a synthetic generic_model.pkl with chumpy objects, loaded without chumpy, checked
against a direct NumPy implementation of FLAME's forward pass."""

from __future__ import annotations

import pickle
import sys
import types

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse
from scipy.spatial.transform import Rotation

from jaxtalk.face import load_flame
from jaxtalk.face.flame import read_flame_pickle

NUM_VERTS, NUM_FACES = 60, 80


def _fake_chumpy_class():
    """A class that pickles as chumpy.ch.Ch (value kept in the instance's "x" attribute)."""

    class Ch:
        def __init__(self, x):
            self.x = x
            self._dirty_vars = set()
            self.label = "chumpy"

    Ch.__module__ = "chumpy.ch"
    Ch.__qualname__ = Ch.__name__ = "Ch"
    return Ch


def make_flame_dict(rng: np.random.Generator) -> dict:
    template = rng.normal(scale=0.05, size=(NUM_VERTS, 3))
    regressor = np.abs(rng.normal(size=(5, NUM_VERTS))) * (rng.random((5, NUM_VERTS)) < 0.2)
    regressor[:, 0] += 1e-3
    regressor /= regressor.sum(axis=1, keepdims=True)
    weights = rng.random((NUM_VERTS, 5)) ** 3
    weights /= weights.sum(axis=1, keepdims=True)
    return {
        "v_template": template,
        "f": rng.integers(0, NUM_VERTS, size=(NUM_FACES, 3)).astype(np.uint32),
        "shapedirs": 0.01 * rng.normal(size=(NUM_VERTS, 3, 400)),
        "posedirs": 0.01 * rng.normal(size=(NUM_VERTS, 3, 36)),
        "J_regressor": scipy.sparse.csc_matrix(regressor),
        "weights": weights,
        "kintree_table": np.array([[4294967295, 0, 1, 1, 1], [0, 1, 2, 3, 4]], np.int64),
        "bs_style": "lbs",
        "bs_type": "lrotmin",
    }


@pytest.fixture(scope="module")
def flame_file(tmp_path_factory):
    """Write the synthetic model with chumpy arrays, then make chumpy unimportable again."""
    rng = np.random.default_rng(0)
    data = make_flame_dict(rng)
    ch_cls = _fake_chumpy_class()
    chumpy = types.ModuleType("chumpy")
    chumpy_ch = types.ModuleType("chumpy.ch")
    chumpy_ch.Ch = ch_cls
    chumpy.ch = chumpy_ch
    stored = dict(data)
    stored["shapedirs"] = ch_cls(data["shapedirs"])
    stored["v_template"] = ch_cls(data["v_template"])
    stored["J"] = ch_cls(data["J_regressor"] @ data["v_template"])
    path = tmp_path_factory.mktemp("flame") / "generic_model.pkl"
    sys.modules["chumpy"], sys.modules["chumpy.ch"] = chumpy, chumpy_ch
    try:
        with open(path, "wb") as fh:
            pickle.dump(stored, fh, protocol=2)
    finally:
        del sys.modules["chumpy"], sys.modules["chumpy.ch"]
    return path, data


def flame_reference(data, shape, exp, jaw, global_rot, neck_rot=np.zeros(3), posedirs=True):
    """FLAME's forward pass (lbs with shape+expression blendshapes, regressed joints, posedirs)."""
    betas = np.concatenate([np.pad(shape, (0, 300 - len(shape))), exp, np.zeros(50)])
    v_shaped = data["v_template"] + data["shapedirs"] @ betas
    joints = data["J_regressor"].toarray() @ v_shaped
    rots = Rotation.from_rotvec(np.stack([global_rot, neck_rot, jaw, np.zeros(3), np.zeros(3)])).as_matrix()
    v_posed = v_shaped + (data["posedirs"] @ (rots[1:] - np.eye(3)).reshape(-1) if posedirs else 0.0)
    parents = [-1, 0, 1, 1, 1]
    transforms = []
    for j in range(5):
        rel = joints[j] - (joints[parents[j]] if parents[j] >= 0 else 0.0)
        local = np.eye(4)
        local[:3, :3], local[:3, 3] = rots[j], rel
        transforms.append(local if parents[j] < 0 else transforms[parents[j]] @ local)
    # Remove the rest-pose joint location (the "A" matrices of SMPL/FLAME's lbs).
    a = np.stack(transforms)
    a[:, :3, 3] -= np.einsum("jab,jb->ja", a[:, :3, :3], joints)
    blended = np.einsum("vj,jab->vab", data["weights"], a)
    return np.einsum("vab,vb->va", blended[:, :3, :3], v_posed) + blended[:, :3, 3]


def test_pickle_reads_without_chumpy(flame_file):
    path, data = flame_file
    assert "chumpy" not in sys.modules
    loaded = read_flame_pickle(path)
    assert "chumpy" not in sys.modules
    np.testing.assert_array_equal(loaded["shapedirs"], data["shapedirs"])
    np.testing.assert_array_equal(loaded["v_template"], data["v_template"])
    assert scipy.sparse.issparse(loaded["J_regressor"])


@pytest.mark.parametrize("head_joint", ["global", "neck"])
def test_loaded_model_reproduces_flame(flame_file, head_joint, float64):
    path, data = flame_file
    rng = np.random.default_rng(1)
    shape = rng.normal(size=20)
    model = load_flame(path, shape_params=shape, head_joint=head_joint)
    assert model.parents == (-1, 0, 1, 1, 1)
    exp = rng.normal(size=50)
    jaw, head = np.array([0.25, 0.02, -0.03]), np.array([0.1, -0.3, 0.05])
    params = jnp.asarray(np.concatenate([exp, jaw, head]))
    got = np.asarray(model.vertices(params))
    if head_joint == "global":
        expected = flame_reference(data, shape, exp, jaw, global_rot=head)
    else:
        expected = flame_reference(data, shape, exp, jaw, global_rot=np.zeros(3), neck_rot=head)
    np.testing.assert_allclose(got, expected, atol=1e-10)


def test_posedirs_can_be_dropped(flame_file, float64):
    path, data = flame_file
    model = load_flame(path, use_posedirs=False)
    assert model.pose_basis is None
    exp, jaw = np.zeros(50), np.array([0.3, 0.0, 0.0])
    got = np.asarray(model.vertices(jnp.asarray(np.concatenate([exp, jaw, np.zeros(3)]))))
    expected = flame_reference(data, np.zeros(0), exp, jaw, np.zeros(3), posedirs=False)
    np.testing.assert_allclose(got, expected, atol=1e-10)
    with_posedirs = flame_reference(data, np.zeros(0), exp, jaw, np.zeros(3))
    assert np.abs(with_posedirs - expected).max() > 1e-4  # the option really changes something


def test_landmark_embedding_file(flame_file, tmp_path):
    path, data = flame_file
    rng = np.random.default_rng(2)
    faces_idx = rng.integers(0, NUM_FACES, 68)
    bary = rng.dirichlet(np.ones(3), 68)
    emb = tmp_path / "landmark_embedding.npy"
    np.save(emb, {"full_lmk_faces_idx": faces_idx[None], "full_lmk_bary_coords": bary[None]}, allow_pickle=True)
    model = load_flame(path, landmarks=emb)
    params = jnp.asarray(np.concatenate([0.5 * rng.normal(size=50), [0.2, 0, 0], [0, 0.1, 0]]), jnp.float32)
    verts = np.asarray(model.vertices(params))
    tri = data["f"][faces_idx].astype(np.int64)
    expected = np.einsum("lkc,lk->lc", verts[tri], bary)
    np.testing.assert_allclose(np.asarray(model.landmarks(params)), expected, atol=1e-6)
    no_lmk = load_flame(path)
    assert np.all(np.isnan(np.asarray(no_lmk.landmarks(params))))


def test_errors(flame_file, tmp_path):
    path, data = flame_file
    with pytest.raises(FileNotFoundError, match="nope.pkl"):
        load_flame(tmp_path / "nope.pkl")
    broken = tmp_path / "broken.pkl"
    partial = {k: v for k, v in data.items() if k != "weights"}
    broken.write_bytes(pickle.dumps(partial))
    with pytest.raises(ValueError, match=r"missing FLAME entries \['weights'\]"):
        load_flame(broken)
    garbage = tmp_path / "garbage.pkl"
    garbage.write_bytes(b"not a pickle at all")
    with pytest.raises(ValueError, match="not a readable pickle"):
        load_flame(garbage)
    hostile = tmp_path / "hostile.pkl"
    hostile.write_bytes(pickle.dumps({"v_template": np.zeros(3), "evil": print}))
    with pytest.raises(ValueError, match="refusing to load builtins.print"):
        load_flame(hostile)
    with pytest.raises(ValueError, match="shape_params must be <= 300"):
        load_flame(path, shape_params=np.zeros(301))
    with pytest.raises(ValueError, match="68 faces"):
        load_flame(path, landmarks=(np.zeros(10, int), np.zeros((10, 3))))
    with pytest.raises(ValueError, match="head_joint"):
        load_flame(path, head_joint="eyes")
    with pytest.raises(FileNotFoundError, match="landmark embedding"):
        load_flame(path, landmarks=tmp_path / "missing.npy")
