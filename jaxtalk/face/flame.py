"""Load a FLAME 2020 model file (``generic_model.pkl``) into ``LinearFaceModel`` without chumpy.

The official file is a Python-2 pickle of a dict: ``v_template (5023, 3)``, ``f (9976, 3)``,
``shapedirs (5023, 3, 400)`` (300 shape then 100 expression components), ``posedirs (5023, 3, 36)``,
``J_regressor`` (scipy sparse ``(5, 5023)``), ``weights (5023, 5)``, ``kintree_table (2, 5)``; several
entries are ``chumpy.ch.Ch`` objects. A custom ``pickle.Unpickler`` maps every chumpy class to a
small stand-in that keeps the object's state, from which the array is extracted, so chumpy (which
does not install on modern Python/NumPy) is never imported.

Mapping into the 56-d vector:
* the first 50 of FLAME's 100 expression components are the expression basis;
* ``jaw`` drives FLAME's jaw joint (index 2);
* ``neck`` drives FLAME's global joint (index 0) by default, like DECA/EMOCA trackers, whose
  ``pose[:, :3]`` is the global head rotation (DualTalk's "neck"); ``head_joint="neck"`` drives
  FLAME's neck joint (index 1) instead, which leaves the lowest neck ring in place;
* eye joints stay at rest; identity shape coefficients (up to 300) can be baked into the template;
* joints are regressed exactly as in FLAME, from the shaped and expression-offset rest mesh;
* ``posedirs`` (pose-corrective offsets) are applied by default (``use_posedirs=False`` drops them).

FLAME does not ship its 68 landmarks in ``generic_model.pkl``; pass a landmark embedding (DECA's
``landmark_embedding.npy`` with ``full_lmk_faces_idx``/``full_lmk_bary_coords``, or explicit face
indices and barycentric coordinates). Without one the model's landmarks are NaN (loudly absent).
FLAME's vertex masks (``FLAME_masks.pkl``) are a separate download too: pass them as ``regions``.
"""

from __future__ import annotations

import os
import pickle
from typing import Any

import jax.numpy as jnp
import numpy as np
import scipy.sparse

from jaxtalk.face.model import LinearFaceModel
from jaxtalk.types import EXP_DIM

__all__ = ["load_flame", "read_flame_pickle", "FLAME_NUM_SHAPE"]

FLAME_NUM_SHAPE = 300
_REQUIRED = ("v_template", "f", "shapedirs", "J_regressor", "weights", "kintree_table")


class _ChumpyStandIn:
    """Receives a chumpy object's pickled state; ``array`` extracts the value it wrapped."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._args = args
        self._state: Any = None

    def __setstate__(self, state: Any) -> None:
        self._state = state

    def array(self) -> np.ndarray:
        state = self._state
        if isinstance(state, tuple) and len(state) == 2 and isinstance(state[0], dict):
            state = state[0]  # (dict, slots) form
        if isinstance(state, dict):
            # chumpy's Ch keeps its value in "x"; other chumpy nodes cache it in "_cache"/"r".
            for key in ("x", "r", "a"):
                if key in state:
                    return _to_numpy(state[key])
            arrays = [v for v in state.values() if isinstance(v, np.ndarray)]
            if len(arrays) == 1:
                return arrays[0]
        if isinstance(state, np.ndarray):
            return state
        raise ValueError(f"cannot extract an array from a pickled chumpy object with state {type(state).__name__}")


# Modules a model pickle may reference. Anything else is refused: unpickling can call any importable
# callable, and a model file is data.
_ALLOWED_MODULES = ("numpy", "scipy.sparse", "copyreg", "builtins", "_codecs", "collections")
_ALLOWED_BUILTINS = {"object", "set", "frozenset", "dict", "list", "tuple", "slice", "bytearray", "complex"}


class _NoChumpyUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        if module == "chumpy" or module.startswith("chumpy."):
            return _ChumpyStandIn
        if module.startswith("scipy.sparse"):
            # Old pickles name private modules (scipy.sparse.csc, ...); the classes live at the top.
            return getattr(scipy.sparse, name)
        if module.startswith("numpy.core"):
            module = "numpy._core" + module[len("numpy.core") :]
        module = {"__builtin__": "builtins", "copy_reg": "copyreg"}.get(module, module)  # Python 2 names
        allowed = any(module == m or module.startswith(m + ".") for m in _ALLOWED_MODULES)
        if not allowed or (module == "builtins" and name not in _ALLOWED_BUILTINS):
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} from a model file")
        return super().find_class(module, name)


def _to_numpy(value: Any) -> Any:
    return value.array() if isinstance(value, _ChumpyStandIn) else value


def read_flame_pickle(path: str | os.PathLike) -> dict[str, Any]:
    """Read a FLAME ``.pkl`` into a dict of NumPy arrays (chumpy objects become arrays).

    Args:
        path: the model file.

    Returns:
        The pickled dict with chumpy values replaced by ``np.ndarray`` (sparse matrices kept).

    Raises:
        FileNotFoundError: if the file does not exist.
        ValueError: if the file is not a pickled dict or lacks a FLAME key.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"FLAME model file not found: {path}")
    with open(path, "rb") as fh:
        try:
            data = _NoChumpyUnpickler(fh, encoding="latin1").load()
        except (pickle.UnpicklingError, EOFError) as err:
            raise ValueError(f"{path} is not a readable pickle: {err}") from err
    if not isinstance(data, dict):
        raise ValueError(f"{path} holds a {type(data).__name__}, expected the FLAME dict")
    missing = [k for k in _REQUIRED if k not in data]
    if missing:
        raise ValueError(f"{path} is missing FLAME entries {missing}; found {sorted(data)}")
    return {k: _to_numpy(v) for k, v in data.items()}


def _landmark_embedding(landmarks: Any, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    if landmarks is None:
        return None
    if isinstance(landmarks, (str, os.PathLike)):
        path = os.fspath(landmarks)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"landmark embedding file not found: {path}")
        loaded = np.load(path, allow_pickle=True)
        if isinstance(loaded, np.ndarray) and loaded.dtype == object:
            loaded = loaded.item()
        try:
            face_idx, bary = loaded["full_lmk_faces_idx"], loaded["full_lmk_bary_coords"]
        except (KeyError, ValueError, TypeError):
            raise ValueError(
                f"{path} lacks 'full_lmk_faces_idx'/'full_lmk_bary_coords' (DECA's landmark_embedding)"
            ) from None
    else:
        face_idx, bary = landmarks
    face_idx = np.asarray(face_idx).reshape(-1).astype(np.int64)
    bary = np.asarray(bary, np.float64).reshape(-1, 3)
    if face_idx.shape != (68,) or bary.shape != (68, 3):
        raise ValueError(f"landmark embedding must give 68 faces and (68, 3) barycentrics, got {face_idx.shape}, {bary.shape}")
    if face_idx.min() < 0 or face_idx.max() >= len(faces):
        raise ValueError(f"landmark face indices must lie in [0, {len(faces)}), got range [{face_idx.min()}, {face_idx.max()}]")
    return faces[face_idx].astype(np.int32), bary


def _check_regions(regions: dict[str, np.ndarray] | None, num_verts: int) -> dict[str, np.ndarray]:
    out = {"all": np.arange(num_verts, dtype=np.int32)}
    for name, idx in (regions or {}).items():
        idx = np.asarray(idx).reshape(-1).astype(np.int32)
        if idx.size == 0 or idx.min() < 0 or idx.max() >= num_verts:
            raise ValueError(f"region {name!r} must hold vertex indices in [0, {num_verts}), got {idx[:5]}...")
        out[name] = idx
    return out


def load_flame(
    path: str | os.PathLike,
    *,
    shape_params: np.ndarray | None = None,
    landmarks: str | os.PathLike | tuple[np.ndarray, np.ndarray] | None = None,
    head_joint: str = "global",
    use_posedirs: bool = True,
    regions: dict[str, np.ndarray] | None = None,
) -> LinearFaceModel:
    """Load FLAME 2020 (``generic_model.pkl``) as a ``LinearFaceModel`` (no chumpy needed).

    Args:
        path: the FLAME model pickle.
        shape_params: optional identity coefficients (up to 300) baked into the template.
        landmarks: DECA-style ``landmark_embedding.npy`` path, or ``(face_idx (68,), bary (68, 3))``.
            Without it the model's landmarks are NaN.
        head_joint: which FLAME joint the 56-d vector's neck rotation drives ("global" = DECA/DualTalk).
        use_posedirs: apply FLAME's pose-corrective blendshapes.
        regions: named vertex-index sets (e.g. from ``FLAME_masks.pkl``); "all" is always added.

    Returns:
        The model (float32 arrays unless 64-bit mode is on).

    Raises:
        FileNotFoundError: if a file is missing.
        ValueError: for a malformed file, too many shape coefficients, bad landmarks or head_joint.
    """
    data = read_flame_pickle(path)
    template = np.asarray(data["v_template"], np.float64)
    faces = np.asarray(data["f"]).astype(np.int32)
    shapedirs = np.asarray(data["shapedirs"], np.float64)
    weights = np.asarray(data["weights"], np.float64)
    kintree = np.asarray(data["kintree_table"]).astype(np.int64)
    regressor = data["J_regressor"]
    regressor = regressor.toarray() if scipy.sparse.issparse(regressor) else np.asarray(regressor)
    num_verts = template.shape[0]
    if template.ndim != 2 or template.shape[1] != 3:
        raise ValueError(f"v_template must be (V, 3), got {template.shape}")
    if shapedirs.shape[:2] != (num_verts, 3) or shapedirs.shape[2] < FLAME_NUM_SHAPE + EXP_DIM:
        raise ValueError(
            f"shapedirs must be ({num_verts}, 3, >= {FLAME_NUM_SHAPE + EXP_DIM}) "
            f"(300 shape + expression), got {shapedirs.shape}"
        )
    num_joints = kintree.shape[1]
    if weights.shape != (num_verts, num_joints) or regressor.shape != (num_joints, num_verts):
        raise ValueError(
            f"weights {weights.shape} / J_regressor {regressor.shape} disagree with "
            f"{num_verts} vertices and {num_joints} joints"
        )
    if num_joints < 3:
        raise ValueError(f"FLAME needs at least the global, neck and jaw joints, got {num_joints}")
    if head_joint not in ("global", "neck"):
        raise ValueError(f"head_joint must be 'global' or 'neck', got {head_joint!r}")

    # kintree_table[0] holds parent ids (the root's is a sentinel such as 2**32 - 1), [1] joint ids.
    order = kintree[1]
    id_to_index = {int(j): i for i, j in enumerate(order)}
    parents = tuple(id_to_index.get(int(p), -1) for p in kintree[0])

    if shape_params is not None:
        betas = np.asarray(shape_params, np.float64).reshape(-1)
        if betas.size > FLAME_NUM_SHAPE or not np.all(np.isfinite(betas)):
            raise ValueError(f"shape_params must be <= {FLAME_NUM_SHAPE} finite values, got {betas.size}")
        template = template + shapedirs[:, :, : betas.size] @ betas
    exp_basis = shapedirs[:, :, FLAME_NUM_SHAPE : FLAME_NUM_SHAPE + EXP_DIM]
    joints = regressor @ template
    joint_exp_basis = np.einsum("jv,vck->jck", regressor, exp_basis)

    pose_basis = None
    if use_posedirs and "posedirs" in data:
        pose_basis = np.asarray(data["posedirs"], np.float64)
        if pose_basis.shape != (num_verts, 3, 9 * (num_joints - 1)):
            raise ValueError(f"posedirs must be ({num_verts}, 3, {9 * (num_joints - 1)}), got {pose_basis.shape}")

    embedding = _landmark_embedding(landmarks, faces)
    if embedding is None:
        lm_vertices = np.zeros((68, 3), np.int32)
        lm_bary = np.full((68, 3), np.nan)  # NaN landmarks say "no embedding" loudly
    else:
        lm_vertices, lm_bary = embedding

    return LinearFaceModel(
        template=jnp.asarray(template),
        faces=faces,
        exp_basis=jnp.asarray(exp_basis),
        joints=jnp.asarray(joints),
        joint_exp_basis=jnp.asarray(joint_exp_basis),
        weights=jnp.asarray(weights),
        pose_basis=None if pose_basis is None else jnp.asarray(pose_basis),
        landmark_vertices=lm_vertices,
        landmark_bary=jnp.asarray(lm_bary),
        regions=_check_regions(regions, num_verts),
        parents=parents,
        neck_joint=0 if head_joint == "global" else 1,
        jaw_joint=2,
        name="flame",
    )
