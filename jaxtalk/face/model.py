"""``LinearFaceModel``: FLAME-style linear face model (expression blendshapes + jaw/neck skinning).

A frame's 56-d head vector ``[exp 50 | jaw 3 | neck 3]`` becomes vertices in four steps, as in FLAME:

1. expression offsets are added to the template in the rest pose: ``v = T + E @ exp``;
2. the joints are regressed from that rest shape (``J = J0 + JE @ exp``: FLAME regresses its joints from
   the expression-shaped mesh, the built-in face has ``JE = 0``);
3. optional pose-corrective offsets (FLAME's ``posedirs``) from the joint rotation matrices;
4. linear blend skinning down a small kinematic tree: the neck rotation turns the whole head about the
   neck joint, the jaw rotation (about the jaw joint, a child of the neck) opens the mouth.

One implementation serves a frame ``(56,)`` and a sequence ``(T, 56)`` (any leading batch axes, so it
also vmaps); it is written so XLA fuses the skinning into a single pass over the vertices.

Rotations are axis-angle vectors turned into matrices by a Rodrigues formula that is exact and has
finite gradients at angle 0 (the rest pose, where every motion sequence starts).

The model is a pytree (arrays are leaves; the kinematic tree and joint roles are static metadata), so
it crosses ``jit``/``vmap``/``grad`` as an argument and one compiled program serves every identity of
the same topology.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.types import EXP_DIM, PARAM_DIM, Array, Float, Int

__all__ = ["LinearFaceModel", "rodrigues"]

ArrayLike = Array | np.ndarray

# Below this squared angle the sin/cos ratios are replaced by their Taylor series: exact to float64
# precision there, and their derivatives stay finite at 0 (sqrt(theta^2) has an infinite one).
_SMALL_ANGLE_SQ = 1e-6


@jax.jit
def rodrigues(axis_angle: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Rotation matrices from axis-angle vectors (Rodrigues' formula), safe and smooth at angle 0.

    ``R = I + A(theta) K + B(theta) K^2`` with ``K`` the cross-product matrix of the (unnormalised)
    axis-angle vector, ``A = sin(theta)/theta`` and ``B = (1 - cos(theta))/theta^2``.

    Args:
        axis_angle: rotation vectors (direction = axis, norm = angle in radians), shape ``(..., 3)``.

    Returns:
        Rotation matrices, shape ``(..., 3, 3)``.
    """
    aa = jnp.asarray(axis_angle)
    theta_sq = jnp.sum(aa * aa, axis=-1)
    small = theta_sq < _SMALL_ANGLE_SQ
    # Double-where: the unused branch must not see theta = 0 either, or its NaN gradient leaks through.
    safe_sq = jnp.where(small, jnp.ones_like(theta_sq), theta_sq)
    theta = jnp.sqrt(safe_sq)
    a = jnp.where(small, 1.0 - theta_sq / 6.0 + theta_sq**2 / 120.0, jnp.sin(theta) / theta)
    b = jnp.where(small, 0.5 - theta_sq / 24.0 + theta_sq**2 / 720.0, (1.0 - jnp.cos(theta)) / safe_sq)
    x, y, z = aa[..., 0], aa[..., 1], aa[..., 2]
    zero = jnp.zeros_like(x)
    k = jnp.stack(
        [
            jnp.stack([zero, -z, y], axis=-1),
            jnp.stack([z, zero, -x], axis=-1),
            jnp.stack([-y, x, zero], axis=-1),
        ],
        axis=-2,
    )
    eye = jnp.broadcast_to(jnp.eye(3, dtype=k.dtype), k.shape)
    return eye + a[..., None, None] * k + b[..., None, None] * (k @ k)


@jax.tree_util.register_pytree_node_class
@dataclasses.dataclass(frozen=True, eq=False)
class LinearFaceModel:
    """A FLAME-like linear face model: template, expression basis, joints and skinning weights.

    Attributes:
        template: rest-pose vertices in metres, ``(V, 3)``.
        faces: triangles, ``(F, 3)`` int32, counter-clockwise seen from outside.
        exp_basis: expression offsets per unit coefficient, ``(V, 3, 50)``.
        joints: rest joint positions for zero expression, ``(J, 3)``.
        joint_exp_basis: how the regressed joints move with expression, ``(J, 3, 50)``.
        weights: skinning weights, ``(V, J)``, rows sum to 1.
        pose_basis: pose-corrective offsets (FLAME's ``posedirs``) per entry of the flattened
            ``(R_j - I)`` of the non-root joints, ``(V, 3, 9 (J-1))``, or ``None`` (not applied).
        landmark_vertices: the three mesh vertices of the triangle holding each of the 68
            landmarks, ``(68, 3)`` int32.
        landmark_bary: barycentric coordinates of each landmark in that triangle, ``(68, 3)``.
        regions: named vertex-index sets (``"lips"``, ``"upper_face"``, ``"mouth_upper"``,
            ``"mouth_lower"``, ``"eyes"``, ``"jaw"``, ...), int arrays.
        parents: static kinematic tree, ``parents[j]`` is the parent of joint ``j`` (-1: root).
        neck_joint: static index of the joint the 56-d vector's neck rotation drives.
        jaw_joint: static index of the joint the 56-d vector's jaw rotation drives.
        name: static label ("builtin", "flame", ...).
    """

    template: Float[ArrayLike, "verts 3"]
    faces: Int[ArrayLike, "tris 3"]
    exp_basis: Float[ArrayLike, "verts 3 50"]
    joints: Float[ArrayLike, "joints 3"]
    joint_exp_basis: Float[ArrayLike, "joints 3 50"]
    weights: Float[ArrayLike, "verts joints"]
    pose_basis: Float[ArrayLike, "verts 3 pose"] | None
    landmark_vertices: Int[ArrayLike, "68 3"]
    landmark_bary: Float[ArrayLike, "68 3"]
    regions: dict[str, Any]
    parents: tuple[int, ...]
    neck_joint: int
    jaw_joint: int
    name: str = "face"

    def __post_init__(self) -> None:
        num_joints = len(self.parents)
        if any(p >= j for j, p in enumerate(self.parents)):
            raise ValueError(f"parents must list each joint after its parent, got {self.parents}")
        if not (0 <= self.neck_joint < num_joints and 0 <= self.jaw_joint < num_joints):
            raise ValueError(
                f"neck_joint={self.neck_joint} and jaw_joint={self.jaw_joint} must index one of the "
                f"{num_joints} joints"
            )
        if self.neck_joint == self.jaw_joint:
            raise ValueError(f"neck_joint and jaw_joint must differ, both are {self.neck_joint}")
        num_verts = np.shape(self.template)[0]
        expected = {
            "template": (num_verts, 3),
            "exp_basis": (num_verts, 3, EXP_DIM),
            "weights": (num_verts, num_joints),
            "joint_exp_basis": (num_joints, 3, EXP_DIM),
            "landmark_vertices": (68, 3),
            "landmark_bary": (68, 3),
        }
        for field, shape in expected.items():
            if tuple(np.shape(getattr(self, field))) != shape:
                raise ValueError(f"{field} must have shape {shape}, got {np.shape(getattr(self, field))}")
        if np.ndim(self.faces) != 2 or np.shape(self.faces)[1] != 3:
            raise ValueError(f"faces must have shape (F, 3), got {np.shape(self.faces)}")
        if tuple(np.shape(self.joints)) != (num_joints, 3):
            raise ValueError(f"joints must have shape ({num_joints}, 3), got {np.shape(self.joints)}")
        if np.shape(self.exp_basis)[-1] != EXP_DIM:
            raise ValueError(f"exp_basis must have {EXP_DIM} components, got {np.shape(self.exp_basis)}")
        if self.pose_basis is not None and np.shape(self.pose_basis)[-1] != 9 * (num_joints - 1):
            raise ValueError(
                f"pose_basis must have 9*(J-1) = {9 * (num_joints - 1)} columns, "
                f"got {np.shape(self.pose_basis)}"
            )

    # ---- pytree protocol -------------------------------------------------------------------------
    _LEAVES = (
        "template",
        "faces",
        "exp_basis",
        "joints",
        "joint_exp_basis",
        "weights",
        "pose_basis",
        "landmark_vertices",
        "landmark_bary",
        "regions",
    )

    def tree_flatten(self):
        children = tuple(getattr(self, f) for f in self._LEAVES)
        return children, (self.parents, self.neck_joint, self.jaw_joint, self.name)

    @classmethod
    def tree_unflatten(cls, aux, children):
        # Bypass __init__: JAX unflattens with tracers or placeholder objects that would fail the
        # shape checks in __post_init__ and the runtime type checker.
        obj = object.__new__(cls)
        for f, value in zip(cls._LEAVES, children):
            object.__setattr__(obj, f, value)
        for f, value in zip(("parents", "neck_joint", "jaw_joint", "name"), aux):
            object.__setattr__(obj, f, value)
        return obj

    # ---- sizes -----------------------------------------------------------------------------------
    @property
    def num_vertices(self) -> int:
        """Number of mesh vertices ``V``."""
        return int(np.shape(self.template)[0])

    @property
    def num_joints(self) -> int:
        """Number of skinning joints ``J``."""
        return len(self.parents)

    # ---- evaluation ------------------------------------------------------------------------------
    # Inputs are annotated loosely ("...") so that a wrong shape reaches the explicit ValueError below,
    # which names the expected layout; outputs carry the exact shapes.
    def vertices(self, params: Float[ArrayLike, "..."]) -> Float[Array, "verts 3"]:
        """Posed vertices of one frame.

        Args:
            params: the head vector ``[exp 50 | jaw 3 | neck 3]`` (axis-angle rotations in radians).

        Returns:
            Vertices in metres, shape ``(V, 3)``.

        Raises:
            ValueError: if ``params`` is not shape ``(56,)`` or (outside jit) holds NaN/inf.
        """
        _check_params(params, batched=False)
        return _vertices_jit(self, params)

    def vertices_seq(self, params: Float[ArrayLike, "..."]) -> Float[Array, "frames verts 3"]:
        """Posed vertices of a sequence of frames (``vertices`` vmapped over frames).

        Args:
            params: head vectors, shape ``(T, 56)``.

        Returns:
            Vertices, shape ``(T, V, 3)``.

        Raises:
            ValueError: if ``params`` is not shape ``(T, 56)`` or (outside jit) holds NaN/inf.
        """
        _check_params(params, batched=True)
        return _vertices_seq_jit(self, params)

    def landmarks(self, params: Float[ArrayLike, "..."]) -> Float[Array, "68 3"]:
        """The 68 semantic landmarks (iBUG order) of one posed frame.

        Args:
            params: the head vector, shape ``(56,)``.

        Returns:
            Landmark positions in metres, shape ``(68, 3)``.

        Raises:
            ValueError: as ``vertices``.
        """
        _check_params(params, batched=False)
        return _landmarks_jit(self, params)

    def landmarks_seq(self, params: Float[ArrayLike, "..."]) -> Float[Array, "frames 68 3"]:
        """The 68 landmarks of a sequence of frames.

        Args:
            params: head vectors, shape ``(T, 56)``.

        Returns:
            Landmarks, shape ``(T, 68, 3)``.

        Raises:
            ValueError: as ``vertices_seq``.
        """
        _check_params(params, batched=True)
        return _landmarks_seq_jit(self, params)

    def landmarks_from_vertices(self, vertices: Float[ArrayLike, "..."]) -> Float[Array, "*batch 68 3"]:
        """Landmarks read off already-posed vertices (barycentric interpolation).

        Args:
            vertices: vertices of this mesh, shape ``(..., V, 3)``.

        Returns:
            Landmarks, shape ``(..., 68, 3)``.
        """
        v = jnp.asarray(vertices)
        if v.shape[-2:] != (self.num_vertices, 3):
            raise ValueError(f"vertices must end in ({self.num_vertices}, 3), got {v.shape}")
        corners = jnp.take(v, jnp.asarray(self.landmark_vertices), axis=-2)  # (..., 68, 3, 3)
        return jnp.einsum("...lkc,lk->...lc", corners, jnp.asarray(self.landmark_bary, v.dtype))

    def joint_transforms(self, params: Float[ArrayLike, "..."]) -> Float[Array, "frames joints 12"]:
        """Each joint's rigid map from the rest pose to the posed frame, as the skinning applies it.

        Vertex ``v`` (expression- and pose-corrected, in the rest pose) weighted fully on joint ``j``
        goes to ``R v + t`` with ``[R (row-major 9) | t (3)]`` the joint's entry; what an exporter
        writes into a skeleton (:mod:`jaxtalk.export`).

        Args:
            params: head vectors, shape ``(T, 56)``.

        Returns:
            ``(T, J, 12)``.

        Raises:
            ValueError: as ``vertices_seq``.
        """
        _check_params(params, batched=True)
        return _joint_transforms_jit(self, params)

    def pose_features(self, params: Float[ArrayLike, "..."]) -> Float[Array, "frames pose"]:
        """The pose-corrective coefficients ``(R_j - I)`` of the non-root joints, flattened row-major,
        that multiply ``pose_basis`` (FLAME's ``posedirs``).

        Args:
            params: head vectors, shape ``(T, 56)``.

        Returns:
            ``(T, 9 (J - 1))``.

        Raises:
            ValueError: as ``vertices_seq``.
        """
        _check_params(params, batched=True)
        return _pose_features_jit(self, params)

    def astype(self, dtype: Any) -> LinearFaceModel:
        """A copy with every floating-point array cast to ``dtype`` (e.g. ``jnp.float64`` for tests)."""
        def cast(x):
            return jnp.asarray(x, dtype) if jnp.issubdtype(jnp.asarray(x).dtype, jnp.floating) else x

        changes = {
            f: cast(getattr(self, f))
            for f in ("template", "exp_basis", "joints", "joint_exp_basis", "weights", "landmark_bary")
        }
        if self.pose_basis is not None:
            changes["pose_basis"] = cast(self.pose_basis)
        return dataclasses.replace(self, **changes)


def _check_params(params: Any, *, batched: bool) -> None:
    shape = np.shape(params)
    want = "(T, 56)" if batched else "(56,)"
    if len(shape) != (2 if batched else 1) or shape[-1] != PARAM_DIM:
        raise ValueError(f"params must have shape {want} = [exp 50 | jaw 3 | neck 3], got {shape}")
    if batched and shape[0] == 0:
        raise ValueError("params has zero frames")
    if not isinstance(params, jax.core.Tracer) and not bool(np.all(np.isfinite(np.asarray(params)))):
        bad = np.argwhere(~np.isfinite(np.asarray(params)))[0].tolist()
        raise ValueError(f"params holds NaN or inf (first at index {bad})")


def _add(a: Array, b: Array) -> Array:
    """a + b with b broadcast explicitly to a's (batched) shape (rank promotion is an error here)."""
    return a + jnp.broadcast_to(b, a.shape)


def _world_transforms(
    rotations: Float[Array, "*batch joints 3 3"], joints: Float[Array, "*batch joints 3"], parents: tuple[int, ...]
) -> Float[Array, "*batch joints 12"]:
    """Per-joint rigid maps ``x -> R x + t`` from rest to posed, composed down the kinematic tree.

    Returns ``[R (row-major 9) | t (3)]`` per joint.
    """
    world_r: list[Array] = []
    world_t: list[Array] = []
    # A Python loop over the (static, <= 5) joints of the tree, not over frames.
    for j, parent in enumerate(parents):
        r_j, joint = rotations[..., j, :, :], joints[..., j, :]
        local_t = joint - jnp.einsum("...ab,...b->...a", r_j, joint)  # rotation about joint j
        if parent < 0:
            world_r.append(r_j)
            world_t.append(local_t)
        else:
            world_r.append(world_r[parent] @ r_j)
            world_t.append(jnp.einsum("...ab,...b->...a", world_r[parent], local_t) + world_t[parent])
    batch = rotations.shape[:-3]
    r = jnp.stack(world_r, axis=-3).reshape(*batch, len(parents), 9)
    return jnp.concatenate([r, jnp.stack(world_t, axis=-2)], axis=-1)


def _skeleton(
    model: LinearFaceModel, params: Float[Array, "*batch 56"]
) -> tuple[Float[Array, "*batch joints 3 3"], Float[Array, "*batch joints 3"]]:
    """Each joint's local rotation and its position regressed from the expression."""
    dtype = jnp.result_type(model.template, params)
    params = jnp.asarray(params, dtype)
    exp = params[..., :EXP_DIM]
    jaw = params[..., EXP_DIM : EXP_DIM + 3]
    neck = params[..., EXP_DIM + 3 : EXP_DIM + 6]
    joints = _add(
        jnp.einsum("...k,jck->...jc", exp, jnp.asarray(model.joint_exp_basis, dtype)),
        jnp.asarray(model.joints, dtype),
    )
    axis_angles = jnp.zeros((*params.shape[:-1], model.num_joints, 3), dtype)
    axis_angles = axis_angles.at[..., model.neck_joint, :].set(neck).at[..., model.jaw_joint, :].set(jaw)
    return rodrigues(axis_angles), joints


def _pose_feature(rotations: Float[Array, "*batch joints 3 3"]) -> Float[Array, "*batch pose"]:
    eye = jnp.broadcast_to(jnp.eye(3, dtype=rotations.dtype), rotations[..., 1:, :, :].shape)
    return (rotations[..., 1:, :, :] - eye).reshape(*rotations.shape[:-3], -1)


def _pose(model: LinearFaceModel, params: Float[Array, "*batch 56"]) -> Float[Array, "*batch verts 3"]:
    """Vertices for any leading batch of frames (one frame: no batch axes)."""
    dtype = jnp.result_type(model.template, params)
    params = jnp.asarray(params, dtype)
    batch = params.shape[:-1]
    rest = _add(
        jnp.einsum("...k,vck->...vc", params[..., :EXP_DIM], jnp.asarray(model.exp_basis, dtype)),
        jnp.asarray(model.template, dtype),
    )
    rotations, joints = _skeleton(model, params)
    if model.pose_basis is not None:
        rest = rest + jnp.einsum("...p,vcp->...vc", _pose_feature(rotations), jnp.asarray(model.pose_basis, dtype))

    transforms = _world_transforms(rotations, joints, model.parents)  # (..., J, 12)
    # Skinning written as scalar-weighted sums over joints (not an einsum to a (..., V, 12) array
    # and a 3x3 product per vertex): XLA fuses it into one pass over the vertices, which is what
    # bounds the speed on CPU.
    weights = jnp.asarray(model.weights, dtype)
    shape = (*batch, weights.shape[0])
    w = [jnp.broadcast_to(weights[:, j], shape) for j in range(model.num_joints)]

    def blend(m: int) -> Array:
        # Entry m of the blended [R | t] per vertex: sum_j w_vj G_jm.
        return sum(
            w[j] * jnp.broadcast_to(transforms[..., j, m].reshape(*batch, 1), shape)
            for j in range(model.num_joints)
        )

    x, y, z = rest[..., 0], rest[..., 1], rest[..., 2]
    out = [blend(3 * a) * x + blend(3 * a + 1) * y + blend(3 * a + 2) * z + blend(9 + a) for a in range(3)]
    return jnp.stack(out, axis=-1)


def _pose_landmarks(model: LinearFaceModel, params: Float[Array, "*batch 56"]) -> Float[Array, "*batch 68 3"]:
    # Pose only the (at most 204) vertices the landmarks sit on, not the whole mesh.
    corners = jnp.asarray(model.landmark_vertices).reshape(-1)
    verts = _pose(_restrict(model, corners), params)
    verts = verts.reshape(*verts.shape[:-2], -1, 3, 3)
    return jnp.einsum("...lkc,lk->...lc", verts, jnp.asarray(model.landmark_bary, verts.dtype))


def _restrict(model: LinearFaceModel, index: Int[Array, "n"]) -> LinearFaceModel:
    """The model restricted to a subset of vertices (rows of every per-vertex array)."""
    per_vertex = ("template", "exp_basis", "weights", "pose_basis")
    children, aux = model.tree_flatten()
    # Rebuilt through tree_unflatten: a vertex subset is not a valid standalone model (the faces
    # and landmarks still index the full mesh), so it must skip the constructor's checks.
    children = [
        jnp.take(jnp.asarray(c), index, axis=0) if name in per_vertex and c is not None else c
        for name, c in zip(LinearFaceModel._LEAVES, children)
    ]
    return LinearFaceModel.tree_unflatten(aux, children)


# One program per input rank: (56,) for a frame, (T, 56) for a sequence.
_vertices_jit = _vertices_seq_jit = jax.jit(_pose)
_landmarks_jit = _landmarks_seq_jit = jax.jit(_pose_landmarks)
_joint_transforms_jit = jax.jit(lambda model, params: _world_transforms(*_skeleton(model, params), model.parents))
_pose_features_jit = jax.jit(lambda model, params: _pose_feature(_skeleton(model, params)[0]))
