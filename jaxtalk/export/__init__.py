"""Motion out of jaxtalk: binary glTF 2.0 files that Blender, game engines and web pages play.

* :func:`export_face_model`: head parameters on a linear face model (built-in or FLAME) as morph
  targets and a jaw/neck skin;
* :func:`export_vertex_sequence`: any vertex sequence as a compact principal-component morph basis
  within a stated error;
* :func:`write_audio_beside`: the audio next to a ``.glb`` (glTF has none);
* :class:`GlbAnimation`: read a ``.glb`` back and pose its mesh as a glTF player does;
* :func:`face_model_weights` / :func:`face_model_rotations`: pose a face model's ``.glb`` live;
* :mod:`jaxtalk.export.arkit`, :mod:`jaxtalk.export.livelink`: ARKit's shape names, Live Link Face's
  curves and its UDP packets;
* blendshape rigs (:mod:`~jaxtalk.export.rig`: :class:`Rig`, :func:`load_rig`, the built-in
  :func:`arkit_rig`), retargeting onto them (:mod:`~jaxtalk.export.retarget`: :class:`Retargeter`,
  :func:`retarget`, over :func:`solve_weights`), and their files: :func:`export_rig_animation` (``.glb``),
  :func:`write_live_link_csv` (a Live Link Face recording), :func:`write_weights_json`.

``jaxtalk export``, ``jaxtalk retarget`` and ``jaxtalk view`` (:mod:`jaxtalk.viewer`) wrap them.
"""

from jaxtalk.export.gltf import (
    DEFAULT_MAX_ERROR,
    ExportSummary,
    export_face_model,
    export_rig_animation,
    export_vertex_sequence,
    face_model_morph,
    face_model_rotations,
    face_model_targets,
    face_model_weights,
    one_sided_targets,
    vertex_basis,
    audio_path_for,
    write_audio_beside,
)
from jaxtalk.export.playback import GlbAnimation
from jaxtalk.export.recording import read_live_link_csv, write_live_link_csv, write_weights_json
from jaxtalk.export.retarget import (
    DEFAULT_PENALTIES,
    DEFAULT_WINDOW,
    Retargeter,
    RetargetResult,
    StreamState,
    retarget,
)
from jaxtalk.export.rig import Rig, arkit_rig, arkit_shape_name, load_rig, symmetric_pairs
from jaxtalk.export.solver import Penalties, solve_weights

__all__ = ["DEFAULT_MAX_ERROR", "ExportSummary", "GlbAnimation", "export_face_model", "export_vertex_sequence",
           "one_sided_targets", "vertex_basis", "write_audio_beside", "audio_path_for", "export_rig_animation",
           "Rig", "arkit_rig", "load_rig", "arkit_shape_name", "symmetric_pairs", "Penalties", "solve_weights",
           "Retargeter", "RetargetResult", "StreamState", "retarget", "DEFAULT_PENALTIES", "DEFAULT_WINDOW",
           "write_live_link_csv",
           "read_live_link_csv", "write_weights_json", "face_model_rotations", "face_model_targets",
           "face_model_weights", "face_model_morph"]
