"""Retargeting: jaxtalk motion (56-d parameters, or vertices on a mesh) -> a blendshape rig's weights.

Once, on the host (:class:`Retargeter`):

1. the rig's neutral is registered to the template face exactly as FreeTalk aligns a mesh it animates
   (:func:`jaxtalk.geometry.canonical.align_to_face`: units, similarity transform through MediaPipe's
   canonical face or the template, separate eyes and teeth left out, any pose, or the rig's 68 landmarks
   when given; a refusal for a mesh that is not a face); a rig on the motion's own mesh needs none;
2. every rig vertex finds its closest point on the motion's mesh (in the template's frame); vertices
   farther than ``max_distance`` or beyond the mesh's rim (the back of a head, the neck, the inside of the
   mouth of a face mask) are left out of the fit;
3. the rig's shapes, in the template's frame and metres, become the fit's basis ``B``, its Gram matrix
   and ``B^T`` carried back onto the motion's mesh, so that a frame's right-hand side is one product
   with that frame's displacements.

Per frame (jitted): the head's rigid rotation is taken out (the neck rotation of the parameters; Procrustes
on the upper face of a vertex sequence), the rest of the displacement is fitted by
:func:`jaxtalk.export.solver.solve_weights` (weights in ``[0, 1]``, temporal smoothness towards the previous
frame's weights, left/right symmetry of the pairs found by name, L1/L2). For head parameters the whole map
from a frame's parameters to the fit's right-hand side ``B^T d`` is precomputed once (:func:`_param_projection`:
the face model's skinning is linear in each joint's transform, so ``B^T d`` is one product of the frame's
joint transforms and expression with a fixed matrix) and evaluated inside the solver's frame loop: no
vertex is posed to solve a frame. The head's rotation is reported as yaw, pitch and roll in radians, in
the template's frame (x: the subject's left, y: up, z: out of the face):

* yaw about +y, positive when the face turns towards the subject's left;
* pitch about +x, positive when the head nods down (the face tips forward);
* roll about +z, positive when the head tilts towards the subject's right (the left ear rises),

composed as ``R = R_y(yaw) R_x(pitch) R_z(roll)``. The jaw stays in the fitted motion: ARKit's ``jawOpen``,
``jawLeft``, ``jawRight`` and ``jawForward`` are shapes.

Penalties are relative to the fit term, which is divided by the rig's mean squared shape norm over the
fitted vertices: a residual as large as one average shape at full weight costs 1/2, as does a weight jump
of ``1 / sqrt(smoothness)`` from the previous frame.

A frame's weights depend only on its own motion and the frames before it (the smoothness term looks back),
so a clip is the same solved whole, in windows, or streamed chunk by chunk (:meth:`Retargeter.stream_step`,
which ``jaxtalk serve``'s ``arkit`` output runs): each piece is tied to the last weights of the one before.
A clip of any length runs in bounded memory: it is solved in windows of :data:`DEFAULT_WINDOW` frames, and
per-vertex arrays (a vertex sequence's displacements, the fit's residual) exist for a few hundred frames at
a time. What a clip keeps is its weights, ``frames x shapes``, and the head's rotations.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.export.rig import Rig
from jaxtalk.export.solver import (
    DEFAULT_MAX_ITER,
    DEFAULT_TOL,
    Penalties,
    SolveInfo,
    bucket,
    solve_frames,
    solve_weights,
    symmetry_matrix,
)
from jaxtalk.face.model import LinearFaceModel, _pose_feature, _restrict, _skeleton, _world_transforms, rodrigues
from jaxtalk.types import EXP_DIM, PARAM_DIM, Array, Float, Int

__all__ = ["Retargeter", "RetargetResult", "Registration", "StreamState", "retarget", "head_angles",
           "DEFAULT_PENALTIES", "DEFAULT_MAX_DISTANCE", "DEFAULT_WINDOW"]

# What `jaxtalk retarget` uses unless told otherwise: a little smoothing and ridge, no sparsity or symmetry.
DEFAULT_PENALTIES = Penalties(smoothness=0.01, l1=0.0, l2=1e-4, symmetry=0.0)
# Rig vertices farther than this (template metres) from the motion's mesh after registration are not fitted.
DEFAULT_MAX_DISTANCE = 0.01
# The fraction of the fitted rig vertices, those the rig's shapes move least, that Procrustes on a vertex
# sequence takes for the head's rigid part.
_RIGID_FRACTION = 0.1
# Frames a clip is solved in at once (40 s at 25 fps): the weights, frames x shapes, are all a clip of any
# length keeps.
DEFAULT_WINDOW = 1000
# Frames whose per-vertex arrays (displacements, the fit's residual) exist at once: what bounds memory.
_PIECE = 250


@dataclasses.dataclass(frozen=True)
class Registration:
    """How the rig was put on the motion's mesh.

    Attributes:
        method: ``"same mesh"`` (the rig is the motion's mesh), ``"icp"`` or ``"landmarks"``.
        reference: the face fitted to the rig (``"mediapipe"``, ``"template"``, ``"landmarks"``), or
            ``""`` for the same mesh.
        ignored: the vertex counts of the rig's separate inner parts (eyes, teeth, a tongue) left out of
            the alignment (:attr:`jaxtalk.geometry.canonical.Canonicalization.ignored`).
        residual: mean distance (metres, template frame) from the fitted rig vertices to the motion's mesh.
        fitted: rig vertices used in the fit (the rest are beyond the motion's mesh).
        total: the rig's vertices.
        scale, rotation, translation: ``x_template = scale * rotation @ x_rig + translation``.
        units: the rig's unit.
    """

    method: str
    residual: float
    fitted: int
    total: int
    scale: float
    rotation: np.ndarray
    translation: np.ndarray
    units: str
    reference: str = ""
    ignored: tuple[int, ...] = ()

    def describe(self) -> str:
        """One line: how the rig was registered and how many of its vertices the fit uses."""
        from jaxtalk.geometry.canonical import describe_parts

        via = " via MediaPipe's canonical face" if self.reference == "mediapipe" else ""
        line = (f"registered ({self.method}{via}, units {self.units}): {self.fitted} of {self.total} rig vertices on "
                f"the motion's mesh, mean distance {self.residual * 1e3:.2f} mm")
        if self.ignored:
            line += f"; left out of the alignment: {describe_parts(self.ignored)}"
        return line


class RetargetResult(NamedTuple):
    """Retargeted motion.

    Attributes:
        weights: ``(T, K)`` in ``[0, 1]``, the rig's shape order.
        head_rotation: ``(T, 3, 3)`` the head's rotation in the template's frame.
        head_angles: ``(T, 3)`` yaw, pitch, roll in radians (module docstring).
        rms_error: metres, root-mean-square distance of the fitted rig vertices from the motion, over every
            frame (what the weights cannot reproduce); NaN when the call was asked not to measure it.
        iterations: solver steps (of the frame that took the most).
        seconds: wall time of the solves.
        windows: how many windows the clip was solved in (1: one solve of the whole clip).
    """

    weights: Float[np.ndarray, "frames k"]
    head_rotation: Float[np.ndarray, "frames 3 3"]
    head_angles: Float[np.ndarray, "frames 3"]
    rms_error: float
    iterations: int
    seconds: float
    windows: int = 1


class StreamState(NamedTuple):
    """What a stream carries between chunks: the last frame's weights (None before the first chunk)."""

    previous: Float[np.ndarray, " k"] | None


def head_angles(rotations: Float[np.ndarray, "*frames 3 3"]) -> Float[np.ndarray, "*frames 3"]:
    """Yaw, pitch, roll (radians) of rotation matrices in the template's frame (module docstring).

    In closed form (a stream asks every chunk, where a general Euler-angle conversion costs more than the
    chunk's solve): ``R = R_y(yaw) R_x(pitch) R_z(roll)`` has ``R[1, 2] = -sin(pitch)``, ``R[0, 2] / R[2, 2]
    = tan(yaw)`` and ``R[1, 0] / R[1, 1] = tan(roll)``, with pitch in ``[-pi/2, pi/2]`` (a head never nods
    through a right angle, where yaw and roll would be one turn).
    """
    r = np.asarray(rotations, np.float64)
    pitch = np.arcsin(np.clip(-r[..., 1, 2], -1.0, 1.0))
    yaw = np.arctan2(r[..., 0, 2], r[..., 2, 2])
    roll = np.arctan2(r[..., 1, 0], r[..., 1, 1])
    return np.stack([yaw, pitch, roll], axis=-1)


def _boundary_vertices(faces: np.ndarray, num_vertices: int) -> np.ndarray:
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    mask = np.zeros(num_vertices, bool)
    mask[unique[counts == 1].reshape(-1)] = True
    return mask


@jax.jit
def _rhs(bs, disp):
    return jnp.einsum("vck,tvc->tk", bs, disp)


@jax.jit
def _squared_residuals(basis, corners, bary, disp, weights):
    """Per frame, the summed squared distance of the fitted points from the motion: ``(T,)``."""
    # One corner at a time: a (T, n, 3) gather each, never the (T, n, 3, 3) of all three at once.
    target = sum(bary[None, :, j, None] * disp[:, corners[:, j]] for j in range(3))
    return jnp.sum((target - jnp.einsum("tk,knc->tnc", weights, basis)) ** 2, axis=(1, 2))


@jax.jit
def _params_displacements(face: LinearFaceModel, params):
    # The head's rotation is reported, not fitted: the neck is posed at rest.
    still = params.at[:, PARAM_DIM - 3:].set(0.0)
    return face.vertices_seq(still) - jnp.asarray(face.template, still.dtype)[None]


def _skeleton_model(face: LinearFaceModel, dtype: Any) -> LinearFaceModel:
    """``face`` without its mesh, on the device: the joints and their expression regression, all that a
    frame's right-hand side poses (:func:`_param_features`), small enough to pass to every chunk's solve."""
    children, aux = _restrict(face, jnp.zeros((0,), jnp.int32)).tree_flatten()
    children = [{} if name == "regions" else None if c is None else
                jnp.asarray(c, dtype if np.issubdtype(np.asarray(c).dtype, np.floating) else None)
                for name, c in zip(LinearFaceModel._LEAVES, children)]
    return LinearFaceModel.tree_unflatten(aux, children)


def _param_features(skeleton: LinearFaceModel, params: Float[Array, "56"]) -> Float[Array, " features"]:
    """One frame's features ``[u, (R_j - I) (x) u, t_j]`` (:func:`_param_projection`), the neck at rest."""
    still = params.at[PARAM_DIM - 3:].set(0.0)  # the head's rotation is reported, not fitted
    rotations, joints = _skeleton(skeleton, still)
    transforms = _world_transforms(rotations, joints, skeleton.parents)  # (J, 12): [R row-major | t]
    u = [jnp.ones((1,), still.dtype), still[:EXP_DIM]]
    if skeleton.pose_basis is not None:
        u.append(_pose_feature(rotations))
    u = jnp.concatenate(u)
    bend = transforms[:, :9] - jnp.eye(3, dtype=still.dtype).reshape(1, 9)
    return jnp.concatenate([u, (bend[:, :, None] * u[None, None, :]).reshape(-1), transforms[:, 9:].reshape(-1)])


def _param_projection(face: LinearFaceModel, bs: Float[np.ndarray, "verts 3 k"]) -> Float[np.ndarray, "features k"]:
    """The fixed matrix ``P`` with ``B^T d = phi P`` for a frame's features ``phi`` (:func:`_param_features`).

    The face poses a vertex as ``x_v = sum_j w_vj (R_j r_v + t_j)``, its rest position
    ``r_v = sum_m u_m r^m_v`` linear in ``u = [1, expression, pose features]`` (``r^0`` the template, then
    the expression and pose-corrective bases). With ``s_v = sum_j w_vj`` (1 on a proper skinning),

        d_v = x_v - r^0_v = sum_j w_vj ((R_j - I) r_v + t_j) + (r_v - r^0_v) + (s_v - 1) r_v,

    each term a product of a frame's ``u``, ``R_j - I`` or ``t_j`` with per-vertex constants: summed against
    ``B^T`` (``bs``, per vertex) once, here, they leave ``phi P`` per frame. ``R_j - I`` rather than ``R_j``
    keeps the rest pose out of the sums, whose float32 rounding would otherwise swamp small expressions.
    """
    used = np.flatnonzero(np.any(bs != 0, axis=(1, 2)))  # the vertices the fit sees
    b = np.asarray(bs, np.float64)[used]
    skin = np.asarray(face.weights, np.float64)[used]
    parts = [np.asarray(face.template, np.float64)[used, :, None], np.asarray(face.exp_basis, np.float64)[used]]
    if face.pose_basis is not None:
        parts.append(np.asarray(face.pose_basis, np.float64)[used])
    r = np.concatenate(parts, axis=-1)  # (n, 3, M)
    n, _, m = r.shape
    k = b.shape[-1]
    # sum_v w_vj b_vak r_vbm, one (3K x n) @ (n x 3M) product per joint, rows ordered (j, a, b, m)
    bend = np.stack([(b * skin[:, j, None, None]).reshape(n, 3 * k).T @ r.reshape(n, 3 * m)
                     for j in range(skin.shape[1])])
    bend = bend.reshape(-1, 3, k, 3, m).transpose(0, 1, 3, 4, 2).reshape(-1, k)
    shift = np.einsum("nj,nak->jak", skin, b).reshape(-1, k)
    offsets = r.copy()
    offsets[..., 0] = 0.0  # r_v - r^0_v
    linear = np.einsum("nak,nam->mk", b, offsets + (skin.sum(axis=1) - 1.0)[:, None, None] * r)
    return np.concatenate([linear, bend, shift])


@jax.jit
def _param_rhs(skeleton: LinearFaceModel, projection, params):
    return jax.vmap(lambda p: _param_features(skeleton, p) @ projection)(params)


@jax.jit
def _solve_params(skeleton: LinearFaceModel, projection, params, count, gram, sym, previous, anchored, lam, lower,
                  upper, tol, max_iter):
    """Weights and head rotations of a window of parameters (frames from ``count`` on are padding): each
    frame's right-hand side is made inside the solver's frame loop, so a frame's arithmetic is the same
    whatever window or chunk it is solved in."""
    weights, info = solve_frames(lambda p: _param_features(skeleton, p) @ projection, params, gram, sym, previous,
                                 anchored, lam, lower, upper, tol, max_iter, count=count)
    return weights, info, rodrigues(params[:, PARAM_DIM - 3:])


class Retargeter:
    """The precomputed retargeting of one kind of motion onto one rig (module docstring).

    Build with :meth:`for_face` (56-d parameters on a face model) or :meth:`for_mesh` (vertex sequences
    on a mesh); then :meth:`__call__` a whole clip, or :meth:`init_stream` / :meth:`stream_step` chunk by
    chunk (the smoothness term carries across chunks; the weights are the whole clip's). Penalties and
    solver settings are traced: a new :class:`Penalties` never recompiles; chunk lengths share one program
    per power of two.
    """

    def __init__(self, rig: Rig, *, neutral: np.ndarray, faces: np.ndarray, template: LinearFaceModel,
                 registration: Registration, corners: np.ndarray, bary: np.ndarray, fitted: np.ndarray,
                 rigid: np.ndarray, face: LinearFaceModel | None, to_template: Any,
                 penalties: Penalties = DEFAULT_PENALTIES) -> None:
        self.rig = rig
        self.neutral = neutral  # the motion's mesh, template frame, metres
        self.faces = faces
        self.template = template
        self.registration = registration
        self.face = face
        self._to_template = to_template  # the motion mesh's canonicalisation (None: already template frame)
        self.penalties = penalties
        # rigid: indices into the fitted rig vertices (their correspondences) that move with the head only
        self.corners, self.bary, self.fitted, self.rigid = corners, bary, fitted, rigid
        s, r = registration.scale, registration.rotation
        basis = np.einsum("kvc,dc->kvd", rig.deltas[:, fitted], r) * s  # (K, n, 3) template metres
        self._basis = basis
        gram = np.einsum("kvc,jvc->kj", basis, basis)
        self._scale = float(np.mean(np.diag(gram)))
        if not self._scale > 0:
            raise ValueError("none of the rig's shapes moves a vertex that lies on the motion's mesh: "
                             "nothing to fit")
        bs = np.zeros((neutral.shape[0], 3, rig.num_shapes))
        np.add.at(bs, corners.reshape(-1), (bary[:, :, None, None] * np.moveaxis(basis, 0, -1)[:, None]).reshape(
            -1, 3, rig.num_shapes))
        dtype = jnp.result_type(float)
        self._gram = jnp.asarray(gram / self._scale, dtype)
        self._residual_args = (jnp.asarray(basis, dtype), jnp.asarray(corners), jnp.asarray(bary, dtype))
        self._bs = jnp.asarray(bs / self._scale, dtype)
        self._symmetry = jnp.asarray(symmetry_matrix(rig.pairs(), rig.num_shapes), dtype)
        self._box = (jnp.zeros((rig.num_shapes,), dtype), jnp.ones((rig.num_shapes,), dtype))
        if face is not None:  # parameters: the map from a frame's parameters to B^T d / scale, made once
            self._projection = jnp.asarray(_param_projection(face, bs / self._scale), dtype)
            self._skeleton = _skeleton_model(face, dtype)

    # ---- construction ------------------------------------------------------------------------------
    @classmethod
    def for_face(cls, rig: Rig, face: LinearFaceModel, penalties: Penalties = DEFAULT_PENALTIES, *,
                 max_distance: float = DEFAULT_MAX_DISTANCE,
                 landmarks: Float[np.ndarray, "68 3"] | None = None) -> Retargeter:
        """Retarget 56-d parameters posed on ``face`` (the built-in face or FLAME) onto ``rig``.

        Args:
            rig: the blendshape rig.
            face: the face model the parameters are posed on.
            penalties: the solver's penalties.
            max_distance: rig vertices farther than this (template metres) from the face are not fitted.
            landmarks: optional ``(68, 3)`` positions of the 68 standard landmarks on the rig's neutral (its
                units and frame), which then register it (as FreeTalk's ``--landmarks`` align a mesh).

        Raises:
            ValueError: a rig that does not register to the face (see
                :func:`~jaxtalk.geometry.canonical.align_to_face`).
        """
        neutral = np.asarray(face.template, np.float64)
        faces = np.asarray(face.faces, np.int64)
        return cls._build(rig, neutral, faces, face, face, None, penalties, max_distance, landmarks=landmarks)

    @classmethod
    def for_mesh(cls, rig: Rig, neutral: Float[np.ndarray, "verts 3"], faces: Int[np.ndarray, "tris 3"], *,
                 template: LinearFaceModel | None = None, units: str | None = None,
                 penalties: Penalties = DEFAULT_PENALTIES, max_distance: float = DEFAULT_MAX_DISTANCE,
                 landmarks: Float[np.ndarray, "68 3"] | None = None) -> Retargeter:
        """Retarget vertex sequences on the mesh ``(neutral, faces)`` (FreeTalk's output on a user's mesh, or
        any animation of the rig's own mesh) onto ``rig``.

        Args:
            rig: the blendshape rig.
            neutral: ``(V, 3)`` the mesh at rest, in its own units and frame (the motion's).
            faces: ``(F, 3)`` its triangles.
            template: the face both meshes are registered to (default: the built-in face).
            units: the mesh's unit (None: detected from its size).
            penalties, max_distance: as for :meth:`for_face`.
            landmarks: the rig's 68 landmarks, as for :meth:`for_face` (they also align the mesh when it is
                the rig's own).

        Raises:
            ValueError: a mesh or rig that does not register to the face.
        """
        from jaxtalk.geometry.canonical import align_to_face

        if template is None:
            from jaxtalk.face import builtin_face

            template = builtin_face(0)
        neutral = np.asarray(neutral, np.float64)
        faces = np.asarray(faces, np.int64)
        if neutral.ndim != 2 or neutral.shape[1] != 3 or faces.ndim != 2 or faces.shape[1] != 3:
            raise ValueError(f"the motion's mesh must be (V, 3) vertices and (F, 3) faces, got {neutral.shape} and "
                             f"{faces.shape}")
        t_verts = np.asarray(template.template, np.float64)
        if neutral.shape == t_verts.shape and np.allclose(neutral, t_verts, atol=1e-6):
            to_template = None  # the template itself
        else:
            own = _same(neutral, rig.neutral)  # the rig's own mesh: its units and landmarks are the mesh's
            to_template = align_to_face(neutral, faces, template, units=units or (rig.units if own else None),
                                        landmarks=landmarks if own else None)
        in_template = neutral if to_template is None else to_template.to_template(neutral)
        return cls._build(rig, in_template, faces, template, None, to_template, penalties, max_distance,
                          original=neutral, landmarks=landmarks)

    @classmethod
    def _build(cls, rig: Rig, neutral: np.ndarray, faces: np.ndarray, template: LinearFaceModel,
               face: LinearFaceModel | None, to_template: Any, penalties: Penalties, max_distance: float,
               original: np.ndarray | None = None, landmarks: np.ndarray | None = None) -> Retargeter:
        from jaxtalk.geometry.canonical import align_to_face

        if not (np.isfinite(max_distance) and max_distance > 0):
            raise ValueError(f"max_distance must be a positive distance in metres, got {max_distance}")
        motion_frame = neutral if original is None else original
        if _same(motion_frame, rig.neutral):
            # The rig is the motion's own mesh: every vertex corresponds to itself.
            if to_template is None:
                scale, rot, trans, units = 1.0, np.eye(3), np.zeros(3), rig.units or "m"
            else:
                scale, rot, trans, units = (to_template.scale, to_template.rotation, to_template.translation,
                                            to_template.units)
            n = rig.num_vertices
            corners = np.repeat(np.arange(n)[:, None], 3, axis=1)
            bary = np.tile([1.0, 0.0, 0.0], (n, 1))
            fitted = np.arange(n)
            registration = Registration("same mesh", 0.0, n, n, scale, rot, trans, units)
        else:
            # The alignment FreeTalk gives a mesh it animates (one code path): with the template's landmarks,
            # a real face is fitted through MediaPipe's canonical face, not the built-in face's features.
            canon = align_to_face(rig.neutral, rig.faces, template, units=rig.units, landmarks=landmarks)
            rig_t = canon.to_template(rig.neutral)
            corners, bary, distance = _closest_points(neutral, faces, rig_t)
            rim = _boundary_vertices(faces, neutral.shape[0])
            keep = (distance <= max_distance) & ~rim[corners].any(axis=1)
            fitted = np.flatnonzero(keep)
            if fitted.size < 3:
                raise ValueError(f"after registration only {fitted.size} of the rig's {rig.num_vertices} vertices lie "
                                 f"within {max_distance * 1e3:.0f} mm of the motion's face: the rig's mesh does not "
                                 "register to it")
            corners, bary = corners[fitted], bary[fitted]
            registration = Registration(canon.method, float(distance[fitted].mean()), int(fitted.size),
                                        rig.num_vertices, canon.scale, canon.rotation, canon.translation, canon.units,
                                        canon.reference, canon.ignored)
        # The head's rigid part, for Procrustes on vertex sequences: the fitted rig vertices that the rig's
        # shapes move least (a rig's shapes say where its face moves; the forehead and temples do not).
        mobility = np.linalg.norm(rig.deltas[:, fitted], axis=-1).max(axis=0)
        count = min(fitted.size, max(10, int(_RIGID_FRACTION * fitted.size)))
        rigid = np.argsort(mobility, kind="stable")[:count]
        return cls(rig, neutral=neutral, faces=faces, template=template, registration=registration, corners=corners,
                   bary=bary, fitted=fitted, rigid=rigid, face=face, to_template=to_template, penalties=penalties)

    # ---- per frame ---------------------------------------------------------------------------------
    @property
    def kind(self) -> str:
        """``"params"`` or ``"vertices"``: what :meth:`__call__` takes."""
        return "params" if self.face is not None else "vertices"

    @property
    def head_pivot(self) -> Float[np.ndarray, "3"]:
        """Where the head turns, in the rig's frame: its head bone, else the template's neck joint."""
        if self.rig.head_pivot is not None:
            return self.rig.head_pivot
        neck = np.asarray(self.template.joints, np.float64)[self.template.neck_joint]
        reg = self.registration
        return (neck - reg.translation) @ reg.rotation / reg.scale

    def rig_rotation(self, head_rotation: Float[np.ndarray, "frames 3 3"]) -> Float[np.ndarray, "frames 3 3"]:
        """Template-frame head rotations as rotations in the rig's frame."""
        r = self.registration.rotation
        return np.einsum("ji,tjk,kl->til", r, np.asarray(head_rotation, np.float64), r)

    def displacements(self, motion: Any) -> tuple[Any, Float[np.ndarray, "frames 3 3"]]:
        """``(displacements (T, Vs, 3) template metres with the head's rotation removed (a JAX array for
        parameters, NumPy for vertices), rotations (T, 3, 3))``.

        Raises:
            ValueError: a wrong shape, NaN or inf.
        """
        x = np.asarray(motion)
        if self.face is not None:
            if x.ndim != 2 or x.shape[1] != PARAM_DIM or x.shape[0] < 1:
                raise ValueError(f"motion must be (frames, {PARAM_DIM}) head parameters, got shape {x.shape}")
            if not np.all(np.isfinite(x)):
                raise ValueError("motion holds NaN or inf")
            params = jnp.asarray(x, jnp.result_type(float))
            disp = _params_displacements(self.face, params)
            return disp, np.asarray(rodrigues(params[:, PARAM_DIM - 3:]), np.float64)
        v = self.neutral.shape[0]
        if x.ndim == 2 and x.shape[1] == 3 * v:
            x = x.reshape(x.shape[0], v, 3)
        if x.ndim != 3 or x.shape[1:] != (v, 3) or x.shape[0] < 1:
            raise ValueError(f"motion must be (frames, {v}, 3) vertices of the retargeter's mesh, got shape {x.shape}")
        if not np.all(np.isfinite(x)):
            raise ValueError("motion holds NaN or inf")
        x = np.asarray(x, np.float64)
        if self._to_template is not None:
            x = self._to_template.to_template(x)
        from jaxtalk.geometry.canonical import umeyama

        corners, bary = self.corners[self.rigid], self.bary[self.rigid]
        rest = np.einsum("nj,njc->nc", bary, self.neutral[corners])
        _, rot, shift = umeyama(rest, np.einsum("nj,tnjc->tnc", bary, x[:, corners]))
        still = np.einsum("tji,tvj->tvi", rot, x - shift[:, None])  # R^T (x - t)
        return still - self.neutral, rot

    def solve(self, rhs: Float[Any, "frames k"], previous: np.ndarray | None = None, *,
              penalties: Penalties | None = None, tol: float = DEFAULT_TOL,
              max_iter: int = DEFAULT_MAX_ITER) -> tuple[Any, Any]:
        """The weights of right-hand sides ``B^T d / scale`` (as :meth:`rhs` makes them)."""
        return solve_weights(self._gram, rhs, penalties or self.penalties, symmetry=self._symmetry,
                             previous=previous, tol=tol, max_iter=max_iter)

    def rhs(self, displacements: Any) -> Any:
        """``B^T d / scale`` per frame, jitted."""
        return _rhs(self._bs, jnp.asarray(displacements, self._bs.dtype))

    def param_rhs(self, params: Float[np.ndarray, "frames 56"]) -> Float[Array, "frames k"]:
        """``B^T d / scale`` of head parameters (a :meth:`for_face` retargeter) through the precomputed
        projection, as the solver evaluates it frame by frame; what :meth:`rhs` of their
        :meth:`displacements` gives, to rounding.

        Raises:
            ValueError: a retargeter of vertex sequences.
        """
        if self.face is None:
            raise ValueError("param_rhs is for a retargeter of head parameters (Retargeter.for_face)")
        return _param_rhs(self._skeleton, self._projection, jnp.asarray(params, self._projection.dtype))

    def __call__(self, motion: Any, *, previous: np.ndarray | None = None, penalties: Penalties | None = None,
                 tol: float = DEFAULT_TOL, max_iter: int = DEFAULT_MAX_ITER,
                 window: int | None = DEFAULT_WINDOW, fit_error: bool = True) -> RetargetResult:
        """Retarget a clip: ``(T, 56)`` parameters (:meth:`for_face`) or ``(T, V, 3)`` vertices (:meth:`for_mesh`).

        A clip longer than ``window`` is solved a window at a time, each window tied by the smoothness term
        to the last weights already kept: a frame's weights depend only on the frames up to it, so the
        windows give the whole clip's weights. Only the frames of the window being solved have per-vertex
        arrays (and those :data:`_PIECE` frames at a time), so memory does not grow with the clip: a
        memory-mapped ``.npy`` is read a window at a time.

        Args:
            motion: the clip (any array-like that slices by frame: a NumPy array, a memory map).
            previous: the weights of the frame before it (a stream's last frame), or None.
            penalties: instead of the retargeter's own.
            tol, max_iter: the solver's stopping rule.
            window: frames per window; None solves the whole clip at once (memory grows with it).
            fit_error: measure ``rms_error`` (posing the motion's vertices for parameters; a live stream
                that does not report it leaves it out, and ``rms_error`` is NaN).

        Raises:
            ValueError: a wrong shape, NaN or inf, a window below one frame.
        """
        penalties = penalties or self.penalties
        frames = self._frames(motion)
        if window is not None and (isinstance(window, bool) or int(window) != window or window < 1):
            raise ValueError(f"window must be a whole number of frames >= 1 (or None), got {window!r}")
        span = frames if window is None else min(int(window), frames)
        weights = np.empty((frames, self.rig.num_shapes))
        rotations = np.empty((frames, 3, 3))
        squared, iterations, seconds, windows, done = 0.0, 0, 0.0, 0, 0
        while done < frames:
            # Every window is `span` frames, so one compiled solve serves them all: the last one ends at the
            # clip's end and starts earlier, solving again frames already kept (to the same weights: each
            # depends only on the frames before it) from the weights kept before it.
            start = min(done, frames - span)
            anchor = previous if start == 0 else weights[start - 1]
            w, rot, sq, info, spent = self._window(motion, start, start + span, done - start, anchor, penalties, tol,
                                                   max_iter, fit_error)
            weights[done:start + span], rotations[done:start + span] = w, rot
            squared += sq
            iterations, seconds, windows = max(iterations, int(info.iterations)), seconds + spent, windows + 1
            done = start + span
        rms = float(np.sqrt(squared / (frames * self.corners.shape[0]))) if fit_error else float("nan")
        return RetargetResult(weights, rotations, head_angles(rotations), rms, iterations, seconds, windows)

    def _frames(self, motion: Any) -> int:
        """The clip's frame count, its shape checked (values are checked a piece at a time)."""
        shape = np.shape(motion)
        if self.face is not None:
            if len(shape) != 2 or shape[1] != PARAM_DIM or shape[0] < 1:
                raise ValueError(f"motion must be (frames, {PARAM_DIM}) head parameters, got shape {shape}")
        else:
            v = self.neutral.shape[0]
            if not (len(shape) == 2 and shape[1] == 3 * v or len(shape) == 3 and shape[1:] == (v, 3)) or shape[0] < 1:
                raise ValueError(f"motion must be (frames, {v}, 3) vertices of the retargeter's mesh, got shape "
                                 f"{shape}")
        return int(shape[0])

    def _window(self, motion: Any, start: int, stop: int, first: int, anchor: np.ndarray | None,
                penalties: Penalties, tol: float, max_iter: int, fit_error: bool
                ) -> tuple[np.ndarray, np.ndarray, float, SolveInfo, float]:
        """Solve frames ``[start, stop)``, tied to ``anchor``; keep those from ``first`` on (window positions).

        Returns the kept weights and rotations, their summed squared residual (0 without ``fit_error``), the
        solver's info and its time.
        """
        if self.face is not None:
            dtype = np.dtype(self._gram.dtype)
            params = np.asarray(motion[start:stop], dtype)
            if not np.all(np.isfinite(params)):
                raise ValueError("motion holds NaN or inf")
            count = stop - start
            # Frames past the clip's end round the count up to a power of two; the solver skips them.
            padded = np.concatenate([params, np.repeat(params[-1:], bucket(count) - count, axis=0)])
            prev = np.zeros(self.rig.num_shapes, dtype) if anchor is None else np.asarray(anchor, dtype)
            clock = time.perf_counter()
            # NumPy arguments: a jitted call takes them as they are, where jnp.asarray would dispatch a
            # conversion each (a stream's chunk is short enough for that to show).
            weights, info, rot = _solve_params(
                self._skeleton, self._projection, padded, np.int32(count), self._gram, self._symmetry, prev,
                np.bool_(anchor is not None), penalties.as_array().astype(dtype), *self._box, dtype.type(tol),
                np.int32(max_iter))
            weights, rot = np.asarray(weights, np.float64)[:count], np.asarray(rot, np.float64)[:count]
            spent = time.perf_counter() - clock
            squared = 0.0
            if fit_error:
                for a in range(first, count, _PIECE):
                    b = min(a + _PIECE, count)
                    disp, _ = self.displacements(params[a:b])
                    squared += float(np.sum(self._squared_residuals(disp, weights[a:b]), dtype=np.float64))
            return weights[first:], rot[first:], squared, info, spent
        rhs, kept = [], []
        rotations = np.empty((stop - start - first, 3, 3))
        for a in range(0, stop - start, _PIECE):
            b = min(a + _PIECE, stop - start)
            disp, rot = self.displacements(motion[start + a:start + b])
            rhs.append(self.rhs(disp))
            if b > first:  # a piece with kept frames: its displacements wait for the weights' residual
                lo = max(a, first)
                kept.append((a, lo, disp))
                rotations[lo - first:b - first] = rot[lo - a:]
        clock = time.perf_counter()
        weights, info = self.solve(jnp.concatenate(rhs), anchor, penalties=penalties, tol=tol, max_iter=max_iter)
        weights = jax.block_until_ready(weights)
        spent = time.perf_counter() - clock
        squared = 0.0
        if fit_error:
            for a, lo, disp in kept:
                per_frame = self._squared_residuals(disp, weights[a:a + disp.shape[0]])
                squared += float(np.sum(per_frame[lo - a:], dtype=np.float64))
        return np.asarray(weights[first:], np.float64), rotations, squared, info, spent

    def _squared_residuals(self, displacements: Any, weights: Any) -> np.ndarray:
        dtype = self._bs.dtype
        return np.asarray(_squared_residuals(*self._residual_args, jnp.asarray(displacements, dtype),
                                             jnp.asarray(weights, dtype)), np.float64)

    def rms_error(self, displacements: Any, weights: np.ndarray) -> float:
        """Root-mean-square distance (metres) of the fitted rig vertices from the motion (displacements as
        :meth:`displacements` gives them), :data:`_PIECE` frames at a time."""
        frames = len(weights)
        squared = sum(float(np.sum(self._squared_residuals(displacements[a:a + _PIECE], weights[a:a + _PIECE]),
                                   dtype=np.float64)) for a in range(0, frames, _PIECE))
        return float(np.sqrt(squared / (frames * self.corners.shape[0])))

    @property
    def face_radius(self) -> float:
        """Metres: the root-mean-square distance of the fitted points (the rig's vertices on the motion's
        mesh, template frame) from their centroid; the face's size :meth:`check_fit` holds a fit error to."""
        points = np.einsum("nj,njc->nc", self.bary, self.neutral[self.corners])
        return float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=-1))))

    def check_fit(self, rms_error: float, frame: Float[np.ndarray, "..."] | None = None) -> None:
        """Refuse a fit error larger than the face itself: the mark of a unit or scale mistake, not a poor fit.

        The threshold is :attr:`face_radius` (73 mm on the built-in face): a fit error that large means the
        motion's points lie, on average, as far from where the rig can put them as the face's own points lie
        from its centre. No expression comes near it (the built-in rig's widest-open jaw moves the face's
        points by 14 mm RMS, and a fit error is at most the motion's own displacement), while a unit mistake
        does whatever the face's size: vertices 10, 100 or 1000 times too large, or too small by as much,
        miss by a whole face or more, as do parameters scaled by 100.

        Args:
            rms_error: metres, :attr:`RetargetResult.rms_error`.
            frame: one frame of a vertex sequence as given (its size against its mesh's names the unit
                mistake); None for parameters.

        Raises:
            ValueError: a fit error at or above :attr:`face_radius`, with the likely mistake.
        """
        radius = self.face_radius
        if not rms_error >= radius:
            return
        head = (f"fit error {rms_error * 1e3:.0f} mm RMS is larger than the face itself (its points lie "
                f"{radius * 1e3:.0f} mm from its centre, RMS)")
        if frame is None:
            raise ValueError(f"{head}: these parameters move the face farther than any expression does; are they "
                             "scaled (by 100 or 1000?), or another face model's (FLAME's: pass --flame)?")
        import math

        from jaxtalk.geometry.canonical import UNITS

        x = np.asarray(frame, np.float64).reshape(-1, 3)
        if self._to_template is not None:
            x = self._to_template.to_template(x)

        def spread(points: np.ndarray) -> float:
            return float(np.sqrt(np.mean(np.sum((points - points.mean(axis=0)) ** 2, axis=-1))))

        ratio = spread(x) / spread(self.neutral)
        power = round(math.log10(ratio)) if ratio > 0 else 0
        unit = self._to_template.units if self._to_template is not None else "m"
        given = [name for name, metres in UNITS.items() if math.isclose(metres, UNITS[unit] / 10.0**power)]
        if power == 0 or abs(math.log10(ratio) - power) > 0.1:
            raise ValueError(f"{head}: the vertices do not move like the mesh they were matched to; were they "
                             "animated on another mesh of as many vertices (pass --mesh, that mesh's file)?")
        size = f"{10.0**power:g} times the size" if power > 0 else f"1/{10.0**-power:g} of the size"
        units = f"are they in {given[0]} and the mesh in {unit}? " if given else ""
        raise ValueError(f"{head}: the vertices are {size} of the mesh they animate; {units}save them in the "
                         f"mesh's units ({unit})")

    def init_stream(self) -> StreamState:
        """The state before a stream's first chunk."""
        return StreamState(None)

    def stream_step(self, state: StreamState, chunk: np.ndarray, **kw: Any) -> tuple[StreamState, RetargetResult]:
        """Retarget one chunk of a stream; its first frame is tied to the previous chunk's last by the
        smoothness term, so the chunks' weights are those of their frames retargeted as one clip. ``kw``
        goes to :meth:`__call__` (``fit_error=False`` skips the fit error, which poses the face's vertices).
        Returns the new state and the chunk's result."""
        result = self(chunk, previous=state.previous, **kw)
        return StreamState(result.weights[-1].copy()), result


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape:
        return False
    extent = float(np.ptp(b, axis=0).max()) or 1.0
    return bool(np.allclose(a, b, rtol=0.0, atol=1e-6 * extent))


def _closest_points(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per point, the triangle corners and barycentric coordinates of its closest point on the mesh, and the
    distance."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    closest, distance, tri = trimesh.proximity.closest_point(mesh, points)
    corners = faces[tri]
    bary = trimesh.triangles.points_to_barycentric(vertices[corners], closest)
    bary = np.clip(bary, 0.0, 1.0)
    bary /= bary.sum(axis=1, keepdims=True)
    return corners.astype(np.int64), bary, np.asarray(distance, np.float64)


def retarget(motion: np.ndarray, rig: Rig, *, face: LinearFaceModel | None = None,
             mesh: tuple[np.ndarray, np.ndarray] | None = None, smoothness: float = DEFAULT_PENALTIES.smoothness,
             l1: float = DEFAULT_PENALTIES.l1, l2: float = DEFAULT_PENALTIES.l2,
             symmetry: float = DEFAULT_PENALTIES.symmetry, landmarks: np.ndarray | None = None) -> RetargetResult:
    """Retarget a clip onto ``rig`` in one call (builds a :class:`Retargeter`; keep one to retarget many).

    Args:
        motion: ``(T, 56)`` head parameters, or ``(T, V, 3)`` vertices.
        rig: the blendshape rig.
        face: the face model parameters are posed on (default: the built-in face).
        mesh: ``(neutral, faces)`` the vertices were animated on (default: the rig's own mesh when ``V``
            matches it, else the built-in face of that vertex count).
        smoothness, l1, l2, symmetry: :class:`Penalties`.
        landmarks: optional ``(68, 3)`` landmarks on the rig's neutral (its units) to register it by.

    Raises:
        ValueError: bad shapes or values, a mesh that matches nothing, a rig that does not register.
    """
    from jaxtalk.face import builtin_face

    penalties = Penalties(smoothness=smoothness, l1=l1, l2=l2, symmetry=symmetry)
    x = np.asarray(motion)
    if x.ndim == 2 and x.shape[1] == PARAM_DIM:
        return Retargeter.for_face(rig, face if face is not None else builtin_face(0), penalties, landmarks=landmarks)(x)
    if x.ndim != 3 or x.shape[2] != 3:
        raise ValueError(f"motion must be (frames, {PARAM_DIM}) parameters or (frames, verts, 3) vertices, "
                         f"got shape {x.shape}")
    if mesh is None:
        if x.shape[1] == rig.num_vertices:
            mesh = (rig.neutral, rig.faces)
        else:
            for resolution in ("low", "default", "high"):
                candidate = builtin_face(0, resolution=resolution)
                if candidate.num_vertices == x.shape[1]:
                    return Retargeter.for_mesh(rig, np.asarray(candidate.template), np.asarray(candidate.faces),
                                               template=candidate, penalties=penalties, landmarks=landmarks)(x)
            else:
                raise ValueError(f"motion animates {x.shape[1]} vertices, neither the rig's {rig.num_vertices} nor a "
                                 "built-in face's: give the mesh it was animated on")
    return Retargeter.for_mesh(rig, *mesh, penalties=penalties, landmarks=landmarks)(x)
