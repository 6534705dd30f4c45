"""Motion to binary glTF 2.0 (``.glb``): morph targets, a skin and one animation, written by pygltflib.

Two layouts, both exact to float32 storage:

* **Face model** (:func:`export_face_model`): the neutral mesh; the 50 expression components as morph
  targets; when the model has FLAME's pose correctives, one more component per entry of ``(R_j - I)``
  of the non-root joints (their weights are those entries, linear in the targets, so the correctives
  stay exact); jaw and neck as joints of a skin with the model's skinning weights. The joints are real
  skin joints rather than baked into the morph sequence: Blender, three.js, Unity and Unreal all play
  skinned morph-target meshes, and a user can retarget or edit a jaw joint, not a baked vertex stream.
  Each joint node's rotation is animated, and its translation too when the model regresses its joints
  from the expression (FLAME), so that the node's global transform times its inverse bind matrix is
  exactly the model's rigid map of that joint.
* **Vertex basis** (:func:`export_vertex_sequence`): any vertex sequence (FreeTalk on a user's mesh) as
  its mean frame plus the fewest principal components whose reconstruction stays within a stated
  distance of every vertex of every frame.

In both, every signed component is stored as two one-sided morph targets (``exp_07+``, ``exp_07-``)
whose weights lie in ``[0, 1]`` (:func:`one_sided_targets`: Blender's importer clamps other weights);
the mesh's ``extras.jaxtalk`` records each target's component and scale, from which
:meth:`~jaxtalk.export.GlbAnimation.component_weights` gives the coefficients back.

A face model's file can also be posed live, frame by frame, rather than by its animation:
:func:`face_model_weights` and :func:`face_model_rotations` give the morph weights of its targets
(:func:`face_model_targets`) and its joints' rotations for any parameters (what ``jaxtalk serve``'s
``morph`` output sends for a file of still frames, whose targets have unit scales).

The animation samples every frame at ``frame / fps`` seconds with LINEAR interpolation. glTF has no
audio: the command line (:mod:`jaxtalk.commands.exporting`) writes the audio beside the ``.glb``.
"""

from __future__ import annotations

import dataclasses
import struct
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pygltflib

from jaxtalk.checks import check_finite
from jaxtalk.face.model import LinearFaceModel
from jaxtalk.files import atomic_output, check_output_path
from jaxtalk.types import MOTION_FPS, Array, Float, Int

# Inputs are annotated loosely ("..."), as in LinearFaceModel, so that a wrong shape reaches the explicit
# ValueError that names the expected layout; outputs carry their exact shapes.

__all__ = ["ExportSummary", "export_face_model", "export_rig_animation", "export_vertex_sequence", "face_model_rotations",
           "face_model_targets", "face_model_weights", "one_sided_targets", "vertex_basis", "write_audio_beside",
           "audio_path_for"]

# Default bound of the vertex-basis layout: 0.1 mm, far below what a renderer shows at face scale.
DEFAULT_MAX_ERROR = 1e-4
_SKIN_RGBA = [0.80, 0.62, 0.52, 1.0]


@dataclasses.dataclass(frozen=True)
class ExportSummary:
    """What an export wrote.

    Attributes:
        path: the ``.glb``.
        layout: ``"face model"`` or ``"vertex basis"``.
        frames, fps: the animation's length and rate.
        vertices, triangles: the mesh's size.
        morph_targets: number of morph targets.
        joints: number of skin joints (0 for the vertex basis).
        nodes: number of scene nodes (the mesh and the joints).
        channels: number of animation channels (morph weights, joint rotations and translations).
        max_error: metres, the vertex basis's largest vertex distance from the input after float32
            storage (``None`` for the face model, which is exact by construction).
    """

    path: Path
    layout: str
    frames: int
    fps: float
    vertices: int
    triangles: int
    morph_targets: int
    joints: int
    nodes: int
    channels: int
    max_error: float | None = None

    def describe(self) -> str:
        """One line for a user."""
        error = "" if self.max_error is None else f", max vertex error {self.max_error * 1e3:.3f} mm"
        return (f"{self.path}: {self.layout}, {self.vertices} vertices, {self.triangles} triangles, "
                f"{self.morph_targets} morph targets, {self.joints} joints, {self.nodes} nodes, "
                f"{self.frames} frames at {self.fps:g} fps in {self.channels} animation channels{error}")


# Frames an animation's keys are made and written at a time: a long clip's keys never exist all at once.
_KEY_ROWS = 4096


class _GlbWriter:
    """Accessors over one binary buffer, then the file.

    The buffer is a list of pieces, written when the file is saved: an array's bytes (the mesh), or rows
    made on demand (an animation's keys, :meth:`streamed`), so that a long animation is written a chunk
    at a time. The file is what pygltflib's ``save_binary`` writes for the same document and buffer, byte
    for byte (the JSON chunk space-padded, every view 4-byte aligned, the buffer zero-padded to 4).
    """

    _TYPES = {1: pygltflib.SCALAR, 2: pygltflib.VEC2, 3: pygltflib.VEC3, 4: pygltflib.VEC4, 16: pygltflib.MAT4}
    _COMPONENTS = {np.dtype(np.float32): pygltflib.FLOAT, np.dtype(np.uint8): pygltflib.UNSIGNED_BYTE,
                   np.dtype(np.uint16): pygltflib.UNSIGNED_SHORT, np.dtype(np.uint32): pygltflib.UNSIGNED_INT}

    def __init__(self, audio_file: str | None = None) -> None:
        extras = {"audio": audio_file} if audio_file else {}
        self.gltf = pygltflib.GLTF2(asset=pygltflib.Asset(version="2.0", generator="jaxtalk", extras=extras))
        self._pieces: list[tuple[int, int, bytes | Callable[[], Iterator[np.ndarray]]]] = []
        self._length = 0

    def _view(self, nbytes: int, target: int | None, data: bytes | Callable[[], Iterator[np.ndarray]]) -> int:
        offset = self._length + (-self._length % 4)  # every view starts 4-byte aligned
        self.gltf.bufferViews.append(pygltflib.BufferView(buffer=0, byteOffset=offset, byteLength=nbytes,
                                                          target=target))
        self._pieces.append((offset, nbytes, data))
        self._length = offset + nbytes
        return len(self.gltf.bufferViews) - 1

    def _accessor(self, view: int, dtype: np.dtype, count: int, width: int, low: list | None,
                  high: list | None) -> int:
        self.gltf.accessors.append(pygltflib.Accessor(bufferView=view, componentType=self._COMPONENTS[np.dtype(dtype)],
                                                      count=int(count), type=self._TYPES[width], min=low, max=high))
        return len(self.gltf.accessors) - 1

    def accessor(self, array: np.ndarray, *, target: int | None = None, bounds: bool = False) -> int:
        """Append ``array`` (rows = elements) as an accessor; ``bounds`` writes its min/max."""
        array = np.ascontiguousarray(array)
        width = 1 if array.ndim == 1 else int(np.prod(array.shape[1:]))
        rows = array.reshape(array.shape[0], width)
        view = self._view(array.nbytes, target, array.tobytes())
        return self._accessor(view, array.dtype, array.shape[0], width, rows.min(axis=0).tolist() if bounds else None,
                              rows.max(axis=0).tolist() if bounds else None)

    def streamed(self, count: int, width: int, rows: Callable[[], Iterator[np.ndarray]], *,
                 bounds: tuple[list[float], list[float]] | None = None) -> int:
        """An accessor of ``count`` float32 elements of ``width`` components whose bytes ``rows()`` yields,
        in order and in chunks, when the file is saved; ``bounds`` its min/max, known beforehand."""
        view = self._view(4 * count * width, None, rows)
        return self._accessor(view, np.dtype(np.float32), count, width, *(bounds if bounds is not None else (None, None)))

    def save(self, path: Path) -> None:
        padded = self._length + (-self._length % 4)
        self.gltf.buffers = [pygltflib.Buffer(byteLength=padded)]
        document = self.gltf.gltf_to_json(separators=(",", ":"), indent=None).encode("utf-8")
        document += b" " * (-len(document) % 4)
        with atomic_output(path) as tmp, open(tmp, "wb") as handle:
            handle.write(b"glTF" + struct.pack("<II", 2, 12 + 8 + len(document) + 8 + padded))
            handle.write(struct.pack("<I", len(document)) + b"JSON" + document)
            handle.write(struct.pack("<I", padded) + b"BIN\0")
            position = 0
            for offset, nbytes, data in self._pieces:
                handle.write(b"\0" * (offset - position))
                if isinstance(data, bytes):
                    handle.write(data)
                else:
                    written = 0
                    for chunk in data():
                        chunk = np.ascontiguousarray(chunk, np.float32)
                        handle.write(chunk.tobytes())
                        written += chunk.nbytes
                    if written != nbytes:  # a maker of rows out of step with its accessor: a bug, not a file
                        raise AssertionError(f"streamed {written} bytes into a view of {nbytes}")
                position = offset + nbytes
            handle.write(b"\0" * (padded - position))


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    import trimesh

    normals = np.asarray(trimesh.Trimesh(vertices, faces, process=False).vertex_normals, np.float64)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    # A vertex on no triangle has no normal; glTF requires unit normals, so give it any.
    normals = np.where(length > 1e-12, normals / np.maximum(length, 1e-12), [0.0, 0.0, 1.0])
    return normals.astype(np.float32)


def one_sided_targets(
    targets: Float[np.ndarray, "k verts 3"], weights: Float[np.ndarray, "frames k"],
) -> tuple[Float[np.ndarray, "k2 verts 3"], Float[np.ndarray, "frames k2"], Float[np.ndarray, " k2"]]:
    """Each signed component as two morph targets whose weights lie in ``[0, 1]``.

    Component ``k`` with weights ``w`` becomes targets ``+s_k target_k`` and ``-r_k target_k`` weighted
    by ``max(w, 0) / s_k`` and ``max(-w, 0) / r_k`` (``s_k``, ``r_k``: the largest positive and negative
    excursion, 1 when there is none). The sum is exact at every keyframe and, the weights being linear
    in the original ones, along every LINEAR interpolation between keyframes too. Why: Blender's glTF
    importer (3.4 to 4.x) widens a shape key's [0, 1] slider range to fit only the FIRST keyframe's
    weight, so it clamps every other weight outside [0, 1]; an expression coefficient of -1.2 would play
    as 0 there.

    Returns:
        ``(targets (2K, V, 3), weights (T, 2K), signed scales (2K,))``: target ``2k`` is the positive
        side of component ``k``, ``2k + 1`` the negative; ``component weight = sum scale x weight``.
    """
    up = np.maximum(weights, 0.0).max(axis=0, initial=0.0)
    down = np.maximum(-weights, 0.0).max(axis=0, initial=0.0)
    up, down = np.where(up > 0, up, 1.0), np.where(down > 0, down, 1.0)
    scales = np.stack([up, -down], axis=1).reshape(-1)
    return np.repeat(targets, 2, axis=0) * scales[:, None, None], _sided(weights, scales), scales


def _sided(weights: Float[np.ndarray | Array, "frames k"], scales: Float[np.ndarray, " k2"], xp=np
           ) -> Float[np.ndarray | Array, "frames k2"]:
    """``(T, K)`` signed component weights -> ``(T, 2K)`` weights of targets with signed ``scales``
    (positive side first): ``max(w, 0) / s+`` and ``max(-w, 0) / -s-``. ``xp``: NumPy, or ``jax.numpy``
    (traced, in the weights' dtype: :func:`face_model_morph`)."""
    pairs = np.asarray(scales, np.float64 if xp is np else np.float32).reshape(-1, 2)
    return xp.stack([xp.maximum(weights, 0.0) / pairs[:, 0], xp.maximum(-weights, 0.0) / -pairs[:, 1]],
                    axis=2).reshape(weights.shape[0], -1)


def _mesh(writer: _GlbWriter, base: np.ndarray, faces: np.ndarray, targets: np.ndarray, weights: np.ndarray,
          names: list[str], skin_attributes: dict[str, int] | None = None) -> np.ndarray:
    """The one mesh (index 0): base positions, normals, triangles, and the signed components
    ``targets (K, V, 3)`` with ``weights (T, K)`` as one-sided morph targets (:func:`one_sided_targets`).

    Returns:
        The morph weights to animate, ``(T, 2K)`` in ``[0, 1]``.
    """
    sided_targets, sided_weights, scales = one_sided_targets(targets, weights)
    # Blender, three.js and Babylon read morph target names from the mesh's extras.targetNames; the
    # jaxtalk entry says how to turn the one-sided weights back into the components' own.
    _write_mesh(writer, base, faces, sided_targets, [f"{n}{side}" for n in names for side in "+-"],
                {"components": names, "targetComponent": np.repeat(np.arange(len(names)), 2).tolist(),
                 "targetScale": scales.tolist()}, skin_attributes)
    return sided_weights


def _write_mesh(writer: _GlbWriter, base: np.ndarray, faces: np.ndarray, targets: np.ndarray, target_names: list[str],
                jaxtalk_extras: dict | None, skin_attributes: dict[str, int] | None = None) -> None:
    """The one mesh (index 0) and its material: base positions, normals, triangles, morph targets
    ``(K, V, 3)`` named in ``extras.targetNames``."""
    index_type = np.uint16 if base.shape[0] <= np.iinfo(np.uint16).max else np.uint32
    attributes = pygltflib.Attributes(
        POSITION=writer.accessor(base.astype(np.float32), target=pygltflib.ARRAY_BUFFER, bounds=True),
        NORMAL=writer.accessor(_vertex_normals(base, faces), target=pygltflib.ARRAY_BUFFER),
        **(skin_attributes or {}))
    primitive = pygltflib.Primitive(
        attributes=attributes,
        indices=writer.accessor(faces.reshape(-1).astype(index_type), target=pygltflib.ELEMENT_ARRAY_BUFFER),
        material=0,
        targets=[pygltflib.Attributes(POSITION=writer.accessor(t.astype(np.float32), target=pygltflib.ARRAY_BUFFER,
                                                               bounds=True)) for t in targets])
    extras: dict = {"targetNames": list(target_names)}
    if jaxtalk_extras is not None:
        extras["jaxtalk"] = jaxtalk_extras
    writer.gltf.meshes.append(pygltflib.Mesh(name="face", primitives=[primitive], weights=[0.0] * len(targets),
                                             extras=extras))
    writer.gltf.materials.append(pygltflib.Material(
        name="skin", pbrMetallicRoughness=pygltflib.PbrMetallicRoughness(baseColorFactor=_SKIN_RGBA, metallicFactor=0.0,
                                                                        roughnessFactor=0.7)))


def _channel(writer: _GlbWriter, animation: pygltflib.Animation, times: int, node: int, path: str,
             values: np.ndarray | int) -> None:
    """An animated property: ``values`` an array of keys, or the accessor that holds them."""
    output = values if isinstance(values, int) else writer.accessor(values.astype(np.float32))
    animation.samplers.append(pygltflib.AnimationSampler(input=times, output=output,
                                                         interpolation=pygltflib.ANIM_LINEAR))
    animation.channels.append(pygltflib.AnimationChannel(
        sampler=len(animation.samplers) - 1, target=pygltflib.AnimationChannelTarget(node=node, path=path)))


def _check_fps(fps: float | int) -> float:
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f"fps must be a positive number, got {fps}")
    return float(fps)


def _times(writer: _GlbWriter, frames: int, fps: float | int) -> int:
    """The key times ``frame / fps`` (float32), made a chunk at a time when the file is written."""
    rate = np.float32(fps)

    def rows() -> Iterator[np.ndarray]:
        for a in range(0, frames, _KEY_ROWS):
            yield np.arange(a, min(a + _KEY_ROWS, frames), dtype=np.float32) / rate

    # float32 division, as the keys' own: the last key is the largest
    return writer.streamed(frames, 1, rows, bounds=([0.0], [float(np.float32(frames - 1) / rate)]))


def _quaternions(rotations: Float[np.ndarray | Array, "frames 3 3"], xp=np) -> Float[np.ndarray | Array, "frames 4"]:
    """``(T, 3, 3)`` rotation matrices -> ``(T, 4)`` unit quaternions ``(x, y, z, w)``, glTF's order.

    Shepperd's method, as scipy's ``Rotation.from_matrix`` (the same quaternions, with the same sign: the
    largest component positive) without its checks of each matrix, which cost a live stream's morph output
    more than the rest of its chunk: each row of ``4 q_i q`` comes from the matrix's diagonal and
    off-diagonal sums, and the one of the largest ``q_i`` is normalised. ``xp``: NumPy (float64) or
    ``jax.numpy`` (traced, in the input's dtype: :func:`face_model_morph`).
    """
    m = np.asarray(rotations, np.float64) if xp is np else rotations
    a, b, c = m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]
    squares = xp.stack([1 + a - b - c, 1 - a + b - c, 1 - a - b + c, 1 + a + b + c], axis=1)  # 4 q_i^2
    xy, xz, yz = m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1]
    wx, wy, wz = m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]
    rows = xp.stack([xp.stack([squares[:, 0], xy, xz, wx], axis=1), xp.stack([xy, squares[:, 1], yz, wy], axis=1),
                     xp.stack([xz, yz, squares[:, 2], wz], axis=1), xp.stack([wx, wy, wz, squares[:, 3]], axis=1)],
                    axis=1)  # (T, 4, 4): row i is 4 q_i q
    q = xp.take_along_axis(rows, xp.argmax(squares, axis=1)[:, None, None], axis=1)[:, 0]
    return q / xp.linalg.norm(q, axis=1, keepdims=True)


def _continuous(quaternions: np.ndarray) -> np.ndarray:
    """q and -q are one rotation: flip signs so consecutive keys are on the same side (no spin)."""
    q = quaternions.copy()
    for t in range(1, q.shape[0]):
        if np.dot(q[t], q[t - 1]) < 0:
            q[t] = -q[t]
    return q


def _skin_attributes(writer: _GlbWriter, weights: np.ndarray) -> dict[str, int]:
    """JOINTS_n / WEIGHTS_n sets of four holding every non-zero skinning weight of each vertex."""
    order = np.argsort(-weights, axis=1, kind="stable")
    nonzero = int(max(1, (weights > 0).sum(axis=1).max()))
    sets = -(-nonzero // 4)
    joints = np.zeros((weights.shape[0], 4 * sets), np.int64)
    values = np.zeros((weights.shape[0], 4 * sets), np.float64)
    keep = order[:, :nonzero]
    joints[:, :nonzero] = keep
    values[:, :nonzero] = np.take_along_axis(weights, keep, axis=1)
    values = values / values.sum(axis=1, keepdims=True)
    joints[values == 0] = 0  # an unused slot: joint 0 at weight 0
    joint_type = np.uint8 if weights.shape[1] <= 256 else np.uint16
    out = {}
    for s in range(sets):
        cols = slice(4 * s, 4 * s + 4)
        out[f"JOINTS_{s}"] = writer.accessor(joints[:, cols].astype(joint_type), target=pygltflib.ARRAY_BUFFER)
        out[f"WEIGHTS_{s}"] = writer.accessor(values[:, cols].astype(np.float32), target=pygltflib.ARRAY_BUFFER)
    return out


def _joint_names(face: LinearFaceModel) -> list[str]:
    return ["neck" if j == face.neck_joint else "jaw" if j == face.jaw_joint else f"joint_{j}"
            for j in range(face.num_joints)]


def _local_joint_motion(face: LinearFaceModel, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per frame and joint, the node's local rotation ``(T, J, 3, 3)`` and translation ``(T, J, 3)``
    such that its global transform times ``T(-rest joint)`` is the model's map of that joint."""
    world = np.asarray(face.joint_transforms(params), np.float64)
    rot, shift = world[..., :9].reshape(*world.shape[:2], 3, 3), world[..., 9:]
    rest = np.asarray(face.joints, np.float64)
    # Global node translation: the model's map applied to the rest joint.
    origin = shift + np.einsum("tjab,jb->tja", rot, rest)
    local_r, local_t = rot.copy(), origin.copy()
    for j, parent in enumerate(face.parents):
        if parent >= 0:
            inv = np.swapaxes(rot[:, parent], -1, -2)
            local_r[:, j] = inv @ rot[:, j]
            local_t[:, j] = np.einsum("tab,tb->ta", inv, origin[:, j] - origin[:, parent])
    return local_r, local_t


def _component_names(face: LinearFaceModel) -> list[str]:
    """The signed components :func:`export_face_model` stores, in order: the expression components, then
    (FLAME) the pose-corrective entries of the non-root joints."""
    names = [f"exp_{k:02d}" for k in range(int(np.shape(face.exp_basis)[-1]))]
    if face.pose_basis is not None:
        joint_names = _joint_names(face)
        names += [f"pose_{joint_names[j]}_r{a}{b}" for j in range(1, face.num_joints) for a in range(3) for b in range(3)]
    return names


def _component_weights(face: LinearFaceModel, params: np.ndarray) -> np.ndarray:
    """``(T, K)`` weights of :func:`_component_names` (``params`` already checked)."""
    weights = [params[:, : int(np.shape(face.exp_basis)[-1])].astype(np.float64)]
    if face.pose_basis is not None:
        weights.append(np.asarray(face.pose_features(params), np.float64))
    return np.concatenate(weights, axis=1)


def _rotation_channels(face: LinearFaceModel, local_r: np.ndarray,
                       previous: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """The animated joints' local rotations as ``(T, 4)`` quaternions ``(x, y, z, w)``, signs continuous
    across frames (and with ``previous``, the last quaternion of each joint before these frames)."""
    names = _joint_names(face)
    out = {}
    for j in (face.neck_joint, face.jaw_joint):
        quats = _quaternions(local_r[:, j])
        last = None if previous is None else previous.get(names[j])
        if last is not None and np.dot(quats[0], last) < 0:
            quats[0] = -quats[0]
        out[names[j]] = _continuous(quats)
    return out


def face_model_targets(face: LinearFaceModel) -> list[str]:
    """The morph target names :func:`export_face_model` writes for ``face`` (its mesh's
    ``extras.targetNames``), in order: ``exp_00+``, ``exp_00-``, ``exp_01+``..."""
    return [f"{n}{side}" for n in _component_names(face) for side in "+-"]


def face_model_weights(
    face: LinearFaceModel, params: Float[np.ndarray, "..."], scales: Float[np.ndarray, " k2"] | None = None,
) -> Float[np.ndarray, "frames k2"]:
    """Morph weights that pose a ``.glb`` of ``face`` (written by :func:`export_face_model`) as ``params``.

    A file's targets are the components times its own scales (``extras.jaxtalk.targetScale``, the largest
    excursion of the clip it was written for); a file of still frames, e.g.
    ``export_face_model(face, np.zeros((1, 56)), ...)``, has unit scales, and its weights are simply
    ``max(w, 0)`` and ``max(-w, 0)`` per component: what a live stream drives.

    Args:
        face: the face model of the file.
        params: ``(T, 56)`` head vectors.
        scales: the file's ``(2K,)`` signed target scales (None: unit, ``+1, -1`` per component).

    Returns:
        ``(T, 2K)`` weights of :func:`face_model_targets`, in order (not clamped to ``[0, 1]``).

    Raises:
        ValueError: wrong shape or NaN/inf in ``params``; scales of the wrong length or with a zero.
    """
    params = np.asarray(params, np.float32)
    if params.ndim != 2 or params.shape[1] != 56:
        raise ValueError(f"params must have shape (T, 56) = [exp 50 | jaw 3 | neck 3], got {params.shape}")
    check_finite(params, "params")
    weights = _component_weights(face, params)
    k2 = 2 * weights.shape[1]
    scales = np.tile([1.0, -1.0], k2 // 2) if scales is None else np.asarray(scales, np.float64)
    if scales.shape != (k2,) or not np.all(np.isfinite(scales)) or np.any(scales == 0):
        raise ValueError(f"scales must be {k2} finite non-zero signed target scales, got shape {scales.shape}")
    return _sided(weights, scales)


def face_model_rotations(
    face: LinearFaceModel, params: Float[np.ndarray, "..."], previous: dict[str, np.ndarray] | None = None,
) -> dict[str, Float[np.ndarray, "frames 4"]]:
    """The rotations :func:`export_face_model` animates: each of the neck and jaw nodes' local rotation as
    ``(T, 4)`` quaternions ``(x, y, z, w)`` (glTF's order), keyed by node name (``"neck"``, ``"jaw"``).

    Consecutive quaternions keep one sign (``q`` and ``-q`` are one rotation; interpolating across a sign
    flip spins the joint); ``previous`` (each node's last quaternion before these frames) carries that
    across the chunks of a stream.

    Raises:
        ValueError: wrong shape or NaN/inf in ``params``.
    """
    local_r, _ = _local_joint_motion(face, np.asarray(params, np.float32))
    return _rotation_channels(face, local_r, previous)


def face_model_morph(face: LinearFaceModel, params: Float[Array, "frames 56"]) -> Float[Array, "frames channels"]:
    """The values that pose a ``.glb`` of ``face`` written from still frames (unit target scales), traced
    (JAX, no checks): :func:`face_model_weights` followed by the jaw's, then the neck's local rotation as
    ``(x, y, z, w)``: the channels of ``jaxtalk serve``'s ``morph`` output, for a graph that runs without
    Python (an exported stream). The quaternions carry Shepperd's sign (largest component positive); keeping
    consecutive ones on one side (:func:`face_model_rotations`' ``previous``) is the caller's.

    Raises:
        ValueError: a face with pose correctives (FLAME), whose file has more targets than the expression's.
    """
    import jax.numpy as jnp

    if face.pose_basis is not None:
        raise ValueError("face_model_morph poses faces without pose correctives (the built-in face), not FLAME")
    k = int(np.shape(face.exp_basis)[-1])
    sided = _sided(params[:, :k], np.tile([1.0, -1.0], k), jnp)  # a still frame's file: unit scales
    rot = face.joint_transforms(params)[..., :9].reshape(params.shape[0], -1, 3, 3)
    quats = []
    for j in (face.jaw_joint, face.neck_joint):
        parent = face.parents[j]
        local = rot[:, j] if parent < 0 else jnp.swapaxes(rot[:, parent], -1, -2) @ rot[:, j]
        quats.append(_quaternions(local, jnp))
    return jnp.concatenate([sided, *quats], axis=1)


def export_face_model(
    face: LinearFaceModel, params: Float[np.ndarray, "..."], out: str | Path, *, fps: float | int = MOTION_FPS,
    name: str = "motion", audio_file: str | None = None,
) -> ExportSummary:
    """Write head parameters on ``face`` as a skinned morph-target ``.glb`` (module docstring).

    Args:
        face: the linear face model the parameters belong to (built-in or FLAME).
        params: ``(T, 56)`` head vectors ``[exp 50 | jaw 3 | neck 3]``.
        out: the ``.glb`` to write (atomically).
        fps: frames per second of ``params``.
        name: the animation's name.
        audio_file: the name of the audio written beside the file (:func:`audio_path_for`), recorded in
            the asset's ``extras.audio`` (glTF itself has no audio).

    Returns:
        :class:`ExportSummary`.

    Raises:
        ValueError: wrong shape, no frames, NaN or inf in ``params``; a bad ``fps`` or output path.
    """
    out = check_output_path(out, (".glb",))
    fps = _check_fps(fps)
    params = np.asarray(params, np.float32)
    local_r, local_t = _local_joint_motion(face, params)  # also checks the shape and finiteness
    frames, num_joints = params.shape[0], face.num_joints

    writer = _GlbWriter(audio_file)
    targets = [np.moveaxis(np.asarray(face.exp_basis, np.float64), -1, 0)]
    if face.pose_basis is not None:
        targets.append(np.moveaxis(np.asarray(face.pose_basis, np.float64), -1, 0))
    morph_weights = _mesh(writer, np.asarray(face.template, np.float64), np.asarray(face.faces),
                          np.concatenate(targets), _component_weights(face, params), _component_names(face),
                          _skin_attributes(writer, np.asarray(face.weights, np.float64)))

    gltf = writer.gltf
    rest = np.asarray(face.joints, np.float64)
    gltf.nodes.append(pygltflib.Node(name="face", mesh=0, skin=0))
    joint_nodes = list(range(1, num_joints + 1))
    for j, joint_name in enumerate(_joint_names(face)):
        parent = face.parents[j]
        offset = rest[j] - (rest[parent] if parent >= 0 else 0.0)
        children = [joint_nodes[c] for c, p in enumerate(face.parents) if p == j]
        gltf.nodes.append(pygltflib.Node(name=joint_name, translation=offset.tolist(), children=children))
    inverse_bind = np.tile(np.eye(4), (num_joints, 1, 1))
    inverse_bind[:, :3, 3] = -rest
    gltf.skins.append(pygltflib.Skin(
        name="head", joints=joint_nodes, skeleton=joint_nodes[0],
        inverseBindMatrices=writer.accessor(np.swapaxes(inverse_bind, 1, 2).reshape(num_joints, 16).astype(np.float32))))
    roots = [joint_nodes[j] for j, p in enumerate(face.parents) if p < 0]
    gltf.scenes.append(pygltflib.Scene(name="jaxtalk", nodes=[0, *roots]))
    gltf.scene = 0

    animation = pygltflib.Animation(name=name)
    times = _times(writer, frames, fps)
    _channel(writer, animation, times, 0, "weights", morph_weights.reshape(-1))
    # The joints move with the expression only where the model regresses them from it (FLAME); for
    # the built-in face the node offsets are exact and no translation is animated.
    moving_joints = np.abs(np.asarray(face.joint_exp_basis)).max() > 0
    rotations = _rotation_channels(face, local_r)
    for j, joint_name in enumerate(_joint_names(face)):
        if joint_name in rotations:
            _channel(writer, animation, times, joint_nodes[j], "rotation", rotations[joint_name])
        if moving_joints:
            _channel(writer, animation, times, joint_nodes[j], "translation", local_t[:, j])
    gltf.animations.append(animation)
    writer.save(out)
    return ExportSummary(out, "face model", frames, fps, face.num_vertices, int(np.shape(face.faces)[0]),
                         morph_weights.shape[1], num_joints, len(gltf.nodes), len(animation.channels))


def export_rig_animation(
    rig, weights: Float[np.ndarray, "..."], out: str | Path, *, fps: float | int = MOTION_FPS,
    head_rotation: Float[np.ndarray, "..."] | None = None, pivot: Float[np.ndarray, "..."] | None = None,
    name: str = "motion", audio_file: str | None = None,
) -> ExportSummary:
    """Write a blendshape rig animated by its weights as a ``.glb``: the rig's mesh, its morph targets under
    their own names (weights in ``[0, 1]``, as engines and Blender's shape keys take them) and one animation.

    With ``head_rotation``, the mesh hangs under a ``head`` node placed at ``pivot`` whose rotation is
    animated: the head turns about that point (the rig's neck or head bone) while the face's shapes play.

    Args:
        rig: a :class:`jaxtalk.export.rig.Rig`.
        weights: ``(T, K)`` in the rig's shape order.
        out: the ``.glb`` to write (atomically).
        fps: frames per second.
        head_rotation: ``(T, 3, 3)`` rotations in the rig's frame, or None (no head node).
        pivot: ``(3,)`` the point the head turns about, in the rig's frame (default: the origin).
        name: the animation's name.
        audio_file: the name of the audio beside the file, recorded in the asset's ``extras.audio``.

    Raises:
        ValueError: wrong shapes, NaN or inf, a bad fps or output path.
    """
    out = check_output_path(out, (".glb",))
    fps = _check_fps(fps)
    w = np.asarray(weights, np.float64)
    if w.ndim != 2 or w.shape[0] < 1 or w.shape[1] != rig.num_shapes:
        raise ValueError(f"weights must have shape (frames >= 1, {rig.num_shapes}), got {w.shape}")
    if not np.all(np.isfinite(w)):
        raise ValueError("weights contain NaN or inf")
    frames = w.shape[0]
    writer = _GlbWriter(audio_file)
    _write_mesh(writer, rig.neutral, rig.faces, rig.deltas, list(rig.names), None)
    gltf = writer.gltf
    animation = pygltflib.Animation(name=name)
    times = _times(writer, frames, fps)
    # The keys are made from the weights and rotations a chunk of frames at a time as the file is
    # written: a clip of any length holds no copy of them.
    if head_rotation is None:
        gltf.nodes.append(pygltflib.Node(name="face", mesh=0))
        roots = [0]
    else:
        rot = np.asarray(head_rotation, np.float64)
        if rot.shape != (frames, 3, 3) or not np.all(np.isfinite(rot)):
            raise ValueError(f"head_rotation must be finite (frames, 3, 3) = {(frames, 3, 3)}, got {rot.shape}")
        p = np.zeros(3) if pivot is None else np.asarray(pivot, np.float64).reshape(3)
        # head (at the pivot, rotating) -> face (shifted back by the pivot): x -> p + R (x - p).
        gltf.nodes.append(pygltflib.Node(name="face", mesh=0, translation=(-p).tolist()))
        gltf.nodes.append(pygltflib.Node(name=rig.head_bone or "head", translation=p.tolist(), children=[0]))
        roots = [1]

        def quaternions() -> Iterator[np.ndarray]:
            last = None
            for a in range(0, frames, _KEY_ROWS):
                q = _quaternions(rot[a:a + _KEY_ROWS])
                if last is not None and np.dot(q[0], last) < 0:  # one sign across chunks too (_continuous)
                    q[0] = -q[0]
                q = _continuous(q)
                last = q[-1]
                yield q

        _channel(writer, animation, times, 1, "rotation", writer.streamed(frames, 4, quaternions))
    gltf.scenes.append(pygltflib.Scene(name="jaxtalk", nodes=roots))
    gltf.scene = 0

    def weight_keys() -> Iterator[np.ndarray]:
        for a in range(0, frames, _KEY_ROWS):
            yield w[a:a + _KEY_ROWS].reshape(-1)

    _channel(writer, animation, times, 0, "weights", writer.streamed(frames * w.shape[1], 1, weight_keys))
    gltf.animations.append(animation)
    writer.save(out)
    return ExportSummary(out, "blendshape rig", w.shape[0], fps, rig.num_vertices, int(rig.faces.shape[0]),
                         rig.num_shapes, 0, len(gltf.nodes), len(animation.channels))


def vertex_basis(
    vertices: Float[np.ndarray, "frames verts 3"], max_error: float | int = DEFAULT_MAX_ERROR,
) -> tuple[Float[np.ndarray, "verts 3"], Float[np.ndarray, "k verts 3"], Float[np.ndarray, "frames k"], float]:
    """The fewest principal components of a vertex sequence that keep every vertex within ``max_error``.

    ``vertices[t] ~ mean + sum_k weights[t, k] targets[k]``. The error is the largest Euclidean distance
    of any vertex in any frame, measured on what a ``.glb`` stores: the float32 mean and the float32
    one-sided targets and weights of :func:`one_sided_targets`.

    Args:
        vertices: ``(T, V, 3)`` in metres.
        max_error: metres.

    Returns:
        ``(mean (float32), targets, weights, error)``: the components as unit-norm directions and their
        coefficients (float64), which :func:`one_sided_targets` turns into what is stored.

    Raises:
        ValueError: a non-positive bound, or one float32 storage cannot meet.
    """
    if not (np.isfinite(max_error) and max_error > 0):
        raise ValueError(f"max_error must be a positive distance in metres, got {max_error}")
    x = np.asarray(vertices, np.float64)
    frames, verts = x.shape[:2]
    mean = x.mean(axis=0)
    centred = (x - mean).reshape(frames, 3 * verts)
    u, s, vt = np.linalg.svd(centred, full_matrices=False)
    mean32 = mean.astype(np.float32)

    def stored(k: int) -> tuple[np.ndarray, np.ndarray, float]:
        targets, weights = vt[:k].reshape(k, verts, 3), u[:, :k] * s[:k]
        sided_targets, sided_weights, _ = one_sided_targets(targets, weights)
        rebuilt = mean32 + np.einsum("tk,kvc->tvc", sided_weights.astype(np.float32).astype(np.float64),
                                     sided_targets.astype(np.float32).astype(np.float64))
        return targets, weights, float(np.sqrt(((rebuilt - x) ** 2).sum(-1)).max())

    residual = centred.copy()
    for k in range(1, len(s) + 1):  # an animation needs a channel: even a still sequence gets one component
        residual -= np.outer(u[:, k - 1] * s[k - 1], vt[k - 1])
        if np.sqrt((residual.reshape(frames, verts, 3) ** 2).sum(-1).max()) <= max_error:
            targets, weights, error = stored(k)  # the float32 rounding may still need one more
            if error <= max_error:
                return mean32, targets, weights, error
    targets, weights, error = stored(max(1, len(s)))
    if error > max_error:
        raise ValueError(f"a {max_error * 1e3:g} mm bound is below what float32 storage holds for this sequence "
                         f"(best {error * 1e3:.4f} mm): choose a larger max_error")
    return mean32, targets, weights, error


def export_vertex_sequence(
    vertices: Float[np.ndarray, "..."], faces: Int[np.ndarray, "..."], out: str | Path, *,
    fps: float | int = MOTION_FPS, max_error: float | int = DEFAULT_MAX_ERROR, name: str = "motion",
    audio_file: str | None = None,
) -> ExportSummary:
    """Write a vertex sequence as a morph-target ``.glb`` on its principal components (module docstring).

    Args:
        vertices: ``(T, V, 3)`` in metres.
        faces: ``(F, 3)`` triangles of the mesh the vertices belong to.
        out: the ``.glb`` to write (atomically).
        fps: frames per second.
        max_error: metres, the largest vertex distance allowed (default 0.1 mm).
        name: the animation's name.
        audio_file: the name of the audio beside the file, recorded in the asset's ``extras.audio``.

    Returns:
        :class:`ExportSummary` (``max_error`` = the measured one).

    Raises:
        ValueError: bad shapes, no frames, NaN or inf, triangles indexing past the vertices, a bad bound,
            fps or output path.
    """
    out = check_output_path(out, (".glb",))
    fps = _check_fps(fps)
    x = np.asarray(vertices)
    if x.ndim != 3 or x.shape[2] != 3 or x.shape[0] < 1 or x.shape[1] < 3:
        raise ValueError(f"vertices must have shape (frames >= 1, verts >= 3, 3), got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("vertices contain NaN or inf")
    tri = np.asarray(faces)
    if tri.ndim != 2 or tri.shape[1] != 3 or tri.shape[0] < 1 or not np.issubdtype(tri.dtype, np.integer):
        raise ValueError(f"faces must be integer triangles of shape (F, 3), got {tri.dtype} {tri.shape}")
    if tri.min() < 0 or tri.max() >= x.shape[1]:
        raise ValueError(f"faces index vertices 0..{tri.max()} but the sequence has {x.shape[1]} vertices: "
                         "not the mesh these vertices belong to")
    # The bound is met by what is stored (vertex_basis measures the one-sided float32 form _mesh writes).
    mean, targets, weights, error = vertex_basis(x, max_error)
    writer = _GlbWriter(audio_file)
    morph_weights = _mesh(writer, mean, tri, targets, weights, [f"pc_{k:03d}" for k in range(targets.shape[0])])
    writer.gltf.nodes.append(pygltflib.Node(name="face", mesh=0))
    writer.gltf.scenes.append(pygltflib.Scene(name="jaxtalk", nodes=[0]))
    writer.gltf.scene = 0
    animation = pygltflib.Animation(name=name)
    _channel(writer, animation, _times(writer, x.shape[0], fps), 0, "weights", morph_weights.reshape(-1))
    writer.gltf.animations.append(animation)
    writer.save(out)
    return ExportSummary(out, "vertex basis", x.shape[0], fps, x.shape[1], tri.shape[0], morph_weights.shape[1], 0, 1,
                         1, max_error=error)


def audio_path_for(glb: str | Path) -> Path:
    """Where the audio of ``glb`` goes: its full name plus ``.wav`` (``talk.glb`` -> ``talk.glb.wav``).

    Not ``talk.wav``: that is the natural name of the recording the animation was made from, and an
    export must never write over its own input.
    """
    glb = Path(glb)
    return glb.with_name(glb.name + ".wav")


def write_audio_beside(glb: str | Path, audio: Float[np.ndarray, " samples"], sample_rate: int = 16_000) -> Path:
    """Write ``audio`` next to ``glb`` as :func:`audio_path_for` names it (16-bit PCM, atomically):
    glTF has no audio, and ``jaxtalk view`` pairs a clip with its sound by this name.

    Returns:
        The ``.wav`` written.

    Raises:
        ValueError: empty audio, or NaN / inf in it.
    """
    import soundfile

    audio = np.asarray(audio, np.float32)
    if audio.ndim != 1 or audio.shape[0] == 0:
        raise ValueError(f"audio must be a non-empty mono signal, got shape {audio.shape}")
    if not np.all(np.isfinite(audio)):
        raise ValueError("audio contains NaN or inf")
    wav = audio_path_for(glb)
    with atomic_output(wav) as tmp:
        soundfile.write(tmp, audio, sample_rate, subtype="PCM_16", format="WAV")
    return wav
