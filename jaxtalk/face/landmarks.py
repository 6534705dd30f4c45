"""The 68 semantic face landmarks (iBUG-300W order) and their standard graph.

Index ranges: jaw line 0-16 (subject's right ear to left ear through the chin), right brow 17-21 and
left brow 22-26 (outer to inner, then inner to outer), nose bridge 27-30 and nostril base 31-35, right
eye 36-41 and left eye 42-47 (corner, two upper-lid points, corner, two lower-lid points), outer lips
48-59 and inner lips 60-67 (from the right mouth corner over the upper lip, back under the lower lip).
"Right" is the subject's right, which is ``x < 0`` in FLAME's frame (x to the subject's left, y up,
z out of the face).

``LANDMARK_EDGES`` is the usual 68-point drawing graph (FreeTalk's GCN runs on it): open polylines for
the jaw, brows, nose bridge and nostril base (joined to the bridge tip), closed loops for the eyes and
the outer and inner lips.
"""

from __future__ import annotations

import numpy as np

__all__ = ["LANDMARK_EDGES", "LANDMARK_PARTS", "landmark_edges"]

# name -> (first index, last index inclusive, closed loop?)
LANDMARK_PARTS: dict[str, tuple[int, int, bool]] = {
    "jaw": (0, 16, False),
    "brow_r": (17, 21, False),
    "brow_l": (22, 26, False),
    "nose_bridge": (27, 30, False),
    "nostrils": (31, 35, False),
    "eye_r": (36, 41, True),
    "eye_l": (42, 47, True),
    "lips_outer": (48, 59, True),
    "lips_inner": (60, 67, True),
}


def landmark_edges() -> np.ndarray:
    """Build the 68-point graph: each part's polyline (closed for eyes and lips) plus the nose joint.

    Returns:
        Undirected edges as index pairs ``(i, j)`` with ``i < j``, shape ``(E, 2)`` int32 (E = 64).
    """
    edges: list[tuple[int, int]] = []
    for first, last, closed in LANDMARK_PARTS.values():
        idx = list(range(first, last + 1))
        edges.extend(zip(idx[:-1], idx[1:]))
        if closed:
            edges.append((last, first))
    # The nostril base hangs from the nose tip (30) at its middle point (33).
    edges.append((30, 33))
    out = np.sort(np.asarray(edges, dtype=np.int32), axis=1)
    return out[np.lexsort((out[:, 1], out[:, 0]))]


LANDMARK_EDGES: np.ndarray = landmark_edges()
LANDMARK_EDGES.setflags(write=False)
