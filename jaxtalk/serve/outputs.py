"""What ``jaxtalk serve`` turns the model's frames into: one converter per output name.

An output is a converter object: ``channels`` (the names of the values of one frame, in order),
``start()`` (a fresh state for one client: whatever it carries from chunk to chunk, e.g. a smoother's
memory or the last quaternion of each joint) and ``convert(state, params) -> (state, values)`` from
``(T, 56)`` head parameters to ``(T, len(channels))`` values. :data:`OUTPUTS` maps each name to the
factory that builds its converter once per server (the first time a client asks for it); a factory
that cannot build one raises :class:`OutputUnavailable`, which the client receives in its hello reply.

* ``params``: the 56-d head parameters themselves, ``[exp 50 | jaw 3 | neck 3]`` (axis-angle radians).
* ``morph``: the morph weights of the built-in face's glTF export and its jaw and neck rotations, i.e.
  what poses ``export_face_model(builtin_face(0), ...)``'s file written from still frames (unit target
  scales; the server serves that file at ``/face.glb``).
* ``arkit``: the 52 ARKit shape weights and the head's yaw, pitch and roll, retargeted per chunk onto
  the built-in ARKit rig (:class:`ArkitOutput`).
"""

from __future__ import annotations

import functools
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

__all__ = ["OUTPUTS", "PARAM_CHANNELS", "ArkitOutput", "MorphOutput", "Output", "OutputUnavailable", "ParamsOutput",
           "build_outputs"]

PARAM_CHANNELS: tuple[str, ...] = (tuple(f"exp_{k:02d}" for k in range(50))
                                   + tuple(f"{joint}_{axis}" for joint in ("jaw", "neck") for axis in "xyz"))


class OutputUnavailable(ValueError):
    """An output this build of the server cannot produce (said in the hello reply)."""


@runtime_checkable
class Output(Protocol):
    """A converter from head parameters to one output (module docstring)."""

    name: str
    channels: tuple[str, ...]

    def start(self) -> Any:
        """A fresh per-client state."""
        ...

    def convert(self, state: Any, params: np.ndarray) -> tuple[Any, np.ndarray]:
        """``(T, 56)`` parameters -> ``(new state, (T, len(channels)) float32 values)``."""
        ...

    def describe(self) -> dict[str, Any]:
        """What a client needs to apply the values (sent in the hello reply)."""
        ...


class ParamsOutput:
    """The 56-d head parameters as the model produces them (FLAME units)."""

    name = "params"
    channels = PARAM_CHANNELS

    def start(self) -> None:
        return None

    def convert(self, state: None, params: np.ndarray) -> tuple[None, np.ndarray]:
        return None, np.asarray(params, np.float32)

    def describe(self) -> dict[str, Any]:
        return {"channels": list(self.channels), "layout": "[exp 50 | jaw 3 | neck 3], axis-angle radians"}


class MorphOutput:
    """Morph weights of a face model's ``.glb`` and its jaw and neck rotations (glTF quaternions).

    The channels are the file's target names in order (``exp_00+``, ``exp_00-``...), whose weights are
    those of a file written from still frames (unit scales, :func:`~jaxtalk.export.face_model_weights`),
    then ``jaw.qx .. jaw.qw`` and ``neck.qx .. neck.qw``: the local rotation of the skin's ``jaw`` and
    ``neck`` nodes. The state is each joint's last quaternion, so that signs stay continuous across
    chunks (:func:`~jaxtalk.export.face_model_rotations`).
    """

    name = "morph"

    def __init__(self, face: Any):
        from jaxtalk.export import face_model_targets

        if np.abs(np.asarray(face.joint_exp_basis)).max() > 0:
            raise OutputUnavailable("the morph output poses faces whose joints do not move with the expression "
                                    "(the built-in face); this one regresses them (FLAME)")
        self.face = face
        self.targets = tuple(face_model_targets(face))
        self.joints = ("jaw", "neck")
        self.channels = self.targets + tuple(f"{j}.q{c}" for j in self.joints for c in "xyzw")

    def start(self) -> dict[str, np.ndarray]:
        return {}

    def convert(self, state: dict[str, np.ndarray], params: np.ndarray) -> tuple[dict[str, np.ndarray], np.ndarray]:
        from jaxtalk.export import face_model_rotations, face_model_weights

        params = np.asarray(params, np.float32)
        frames = params.shape[0]
        if frames == 0:
            return state, np.zeros((0, len(self.channels)), np.float32)
        # The joints' transforms are one jitted program per frame count: pad the count to a power of two
        # (repeating the last frame) so that a stream's chunks, whatever their length, reuse a few.
        padded = np.concatenate([params, np.repeat(params[-1:], max(4, 1 << (frames - 1).bit_length()) - frames, 0)])
        rotations = face_model_rotations(self.face, padded, previous=state)
        rotations = {j: rotations[j][:frames] for j in self.joints}
        values = np.concatenate([face_model_weights(self.face, params), *(rotations[j] for j in self.joints)], axis=1)
        return {j: rotations[j][-1] for j in self.joints}, values.astype(np.float32)

    @functools.cached_property
    def glb(self) -> bytes:
        """The face's ``.glb`` whose targets these weights drive: the face at rest, written from one still
        frame (unit target scales)."""
        from jaxtalk.export import export_face_model

        with tempfile.TemporaryDirectory() as folder:
            path = Path(folder) / "face.glb"
            export_face_model(self.face, np.zeros((1, 56), np.float32), path, name="rest")
            return path.read_bytes()

    def describe(self) -> dict[str, Any]:
        return {"channels": list(self.channels), "targets": len(self.targets), "joints": list(self.joints),
                "face": "/face.glb", "quaternion": "x, y, z, w (glTF)"}


def _morph_output() -> MorphOutput:
    from jaxtalk.face import builtin_face

    return MorphOutput(builtin_face(0))


class ArkitOutput:
    """The 52 ARKit shape weights (in Live Link Face's order) and the head's yaw, pitch and roll (radians),
    solved per chunk onto the built-in ARKit rig (:func:`~jaxtalk.export.arkit_rig`) by the retargeting
    solver (:class:`~jaxtalk.export.Retargeter`). The per-client state is the solver's last frame, which
    the smoothness term ties the next chunk's first frame to: a stream's weights are those ``jaxtalk
    retarget`` gives its whole motion (the solver looks back only), with no jumps at chunk seams.
    """

    name = "arkit"
    head_channels = ("HeadYaw", "HeadPitch", "HeadRoll")

    def __init__(self, face: Any):
        from jaxtalk.export import Retargeter, arkit_rig

        rig = arkit_rig()
        self.retargeter = Retargeter.for_face(rig, face)
        self.channels = tuple(rig.names) + self.head_channels

    def start(self) -> Any:
        return self.retargeter.init_stream()

    def convert(self, state: Any, params: np.ndarray) -> tuple[Any, np.ndarray]:
        params = np.asarray(params, np.float32)
        if params.shape[0] == 0:
            return state, np.zeros((0, len(self.channels)), np.float32)
        # The fit error would pose the face's vertices, the one per-vertex cost left: nobody reads it here.
        state, result = self.retargeter.stream_step(state, params, fit_error=False)
        return state, np.concatenate([result.weights, result.head_angles], axis=1).astype(np.float32)

    def describe(self) -> dict[str, Any]:
        return {"channels": list(self.channels), "rig": "built-in ARKit rig (jaxtalk.export.arkit_rig)",
                "weights": "[0, 1]", "head": "yaw, pitch, roll in radians (Live Link Face's HeadYaw/Pitch/Roll)"}


def _arkit_output() -> ArkitOutput:
    from jaxtalk.face import builtin_face

    return ArkitOutput(builtin_face(0))


OUTPUTS: dict[str, Callable[[], Output]] = {
    "params": ParamsOutput,
    "morph": _morph_output,
    "arkit": _arkit_output,
}


def build_outputs(names: tuple[str, ...], cache: dict[str, Output],
                  registry: dict[str, Callable[[], Output]] | None = None) -> dict[str, Output]:
    """The converters of ``names`` (each built once into ``cache``).

    Raises:
        KeyError: a name not in the registry.
        OutputUnavailable: a converter that cannot be built here.
    """
    registry = OUTPUTS if registry is None else registry
    out = {}
    for name in names:
        if name not in cache:
            cache[name] = registry[name]()
        out[name] = cache[name]
    return out
