"""Face models: ``LinearFaceModel`` (FLAME-like params -> vertices), the built-in procedural face,
a FLAME 2020 file loader, and the 68-landmark set with its graph.

``builtin_face()`` gives a ready model with named expression components (``jaxtalk.layout``);
``load_flame(path)`` maps a user's ``generic_model.pkl`` into the same class.
"""

from __future__ import annotations

from jaxtalk.face.flame import load_flame
from jaxtalk.face.landmarks import LANDMARK_EDGES, LANDMARK_PARTS, landmark_edges
from jaxtalk.face.model import LinearFaceModel, rodrigues
from jaxtalk.face.procedural import RESOLUTIONS, builtin_face

__all__ = [
    "LinearFaceModel",
    "builtin_face",
    "load_flame",
    "rodrigues",
    "LANDMARK_EDGES",
    "LANDMARK_PARTS",
    "landmark_edges",
    "RESOLUTIONS",
]
