"""What a glTF player shows: the vertices of a ``.glb``'s animated mesh at its keyframes.

An independent reading of the file, by glTF 2.0's rules, not by jaxtalk's face model: morph targets
``base + sum_k w_k target_k``; node transforms ``T * R * S`` composed from the root; skinning
``sum_i w_i (global_{j_i} * inverseBind_{j_i}) v`` over every ``JOINTS_n``/``WEIGHTS_n`` set. It is how
the round-trip tests check an export against :class:`~jaxtalk.face.LinearFaceModel`, and how a user can
check a file without a 3D tool.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pygltflib
from scipy.spatial.transform import Rotation

from jaxtalk.geometry.mesh_io import read_accessor
from jaxtalk.types import Float, Int

__all__ = ["GlbAnimation"]

class GlbAnimation:
    """A ``.glb`` with one mesh and one animation, read back (``GlbAnimation(path)``).

    Attributes:
        gltf: the parsed file (pygltflib).
        times: ``(T,)`` keyframe times in seconds.
        faces: ``(F, 3)`` triangles.
        target_names: the morph targets' names.
    """

    def __init__(self, path: str | Path) -> None:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"file not found: {str(path)!r}")
        try:
            self.gltf = pygltflib.GLTF2().load_binary(str(path))
        except Exception as err:  # pygltflib raises whatever its parser meets
            raise ValueError(f"{str(path)!r} is not a readable binary glTF file ({err})") from None
        self._blob = self.gltf.binary_blob()
        if len(self.gltf.meshes) != 1 or len(self.gltf.animations) != 1:
            raise ValueError(f"{str(path)!r}: expected one mesh and one animation, found "
                             f"{len(self.gltf.meshes)} and {len(self.gltf.animations)}")
        self._primitive = self.gltf.meshes[0].primitives[0]
        self._mesh_node = next(i for i, n in enumerate(self.gltf.nodes) if n.mesh == 0)
        self.faces: Int[np.ndarray, "tris 3"] = self.accessor(self._primitive.indices).reshape(-1, 3).astype(np.int64)
        self.target_names: list[str] = list((self.gltf.meshes[0].extras or {}).get("targetNames", []))
        animation = self.gltf.animations[0]
        self._channels = {(c.target.node, c.target.path): self.accessor(animation.samplers[c.sampler].output)
                          for c in animation.channels}
        self.times: Float[np.ndarray, " frames"] = self.accessor(animation.samplers[0].input).reshape(-1)

    def accessor(self, index: int) -> np.ndarray:
        """Accessor ``index`` as an ``(count, width)`` array (``(count,)`` for scalars)."""
        return read_accessor(self.gltf, self._blob, index)

    @property
    def num_frames(self) -> int:
        """Number of keyframes."""
        return int(self.times.shape[0])

    def morph_weights(self) -> Float[np.ndarray, "frames targets"]:
        """The animated morph weights, ``(T, K)``."""
        return self._channels[(self._mesh_node, "weights")].reshape(self.num_frames, -1).astype(np.float64)

    def component_weights(self) -> Float[np.ndarray, "frames components"]:
        """The components' own weights (expression coefficients, pose-corrective entries, principal
        component coefficients), ``(T, C)``, rebuilt from a jaxtalk export's one-sided targets."""
        info = (self.gltf.meshes[0].extras or {}).get("jaxtalk")
        if info is None:
            raise ValueError("this .glb was not written by jaxtalk export: it records no components")
        out = np.zeros((self.num_frames, len(info["components"])))
        np.add.at(out.T, np.asarray(info["targetComponent"]),
                  (self.morph_weights() * np.asarray(info["targetScale"])).T)
        return out

    def _node_matrix(self, node: int, frame: int) -> np.ndarray:
        n = self.gltf.nodes[node]
        if n.matrix:
            return np.asarray(n.matrix, np.float64).reshape(4, 4).T  # stored column-major
        t = self._channels.get((node, "translation"))
        r = self._channels.get((node, "rotation"))
        s = self._channels.get((node, "scale"))
        m = np.eye(4)
        quat = r[frame] if r is not None else (n.rotation or [0.0, 0.0, 0.0, 1.0])
        m[:3, :3] = Rotation.from_quat(np.asarray(quat, np.float64)).as_matrix() @ np.diag(
            s[frame] if s is not None else (n.scale or [1.0, 1.0, 1.0]))
        m[:3, 3] = t[frame] if t is not None else (n.translation or [0.0, 0.0, 0.0])
        return m

    def _global_matrices(self, frame: int) -> dict[int, np.ndarray]:
        out: dict[int, np.ndarray] = {}

        def visit(node: int, parent: np.ndarray) -> None:
            out[node] = parent @ self._node_matrix(node, frame)
            for child in self.gltf.nodes[node].children or []:
                visit(child, out[node])

        for root in self.gltf.scenes[self.gltf.scene or 0].nodes:
            visit(root, np.eye(4))
        return out

    def vertices(self, frame: int) -> Float[np.ndarray, "verts 3"]:
        """The mesh's vertices at keyframe ``frame`` (float64), as a glTF player poses them."""
        if not 0 <= frame < self.num_frames:
            raise ValueError(f"frame {frame} is outside the animation's {self.num_frames} frames")
        attrs = self._primitive.attributes
        v = self.accessor(attrs.POSITION).astype(np.float64)
        weights = self.morph_weights()[frame]
        for w, target in zip(weights, self._primitive.targets, strict=True):
            position = target["POSITION"] if isinstance(target, dict) else target.POSITION  # as pygltflib reads it
            v = v + w * self.accessor(position).astype(np.float64)
        node = self.gltf.nodes[self._mesh_node]
        matrices = self._global_matrices(frame)
        if node.skin is None:
            m = matrices[self._mesh_node]
            return v @ m[:3, :3].T + m[:3, 3]
        skin = self.gltf.skins[node.skin]
        inverse_bind = self.accessor(skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
        joint_matrices = np.stack([matrices[j] for j in skin.joints]) @ inverse_bind  # (J, 4, 4)
        blended = np.zeros((v.shape[0], 4, 4))
        s = 0
        while getattr(attrs, f"JOINTS_{s}", None) is not None:
            joints = self.accessor(getattr(attrs, f"JOINTS_{s}")).astype(np.int64)
            w = self.accessor(getattr(attrs, f"WEIGHTS_{s}")).astype(np.float64)
            blended += np.einsum("vi,viab->vab", w, joint_matrices[joints])
            s += 1
        return np.einsum("vab,vb->va", blended[:, :3, :3], v) + blended[:, :3, 3]
