"""Evaluation metrics of the three papers.

* Vertex metrics (``vertex``): ``lve``, ``mve``, ``fdd``/``fdd_batch``, ``mod``, ``dtw``, ``dfd``,
  ``delta_m``, ``delta_cd`` (FreeTalk, TokTalk tables) and ``jitter`` (TokTalk Table 5).
* Landmark metrics (``landmarks``): ``landmark_metrics`` (FreeTalk ATS's columns on 68 landmarks).
* Trajectory alignment (``alignment``): ``trajectory_dtw``, ``trajectory_dfd`` on any point sequences.
* Conversation metrics (``conversation``): ``conversation_metrics`` (FD, P-FD, MSE, SID, rPCC of the
  DualTalk benchmark used by TIMAR) and its parts.
"""

from __future__ import annotations

from jaxtalk.metrics.alignment import trajectory_dfd, trajectory_dtw
from jaxtalk.metrics.conversation import (
    CONVERSATION_GROUPS,
    PUBLISHED_SCALE,
    SID_CLUSTERS,
    conversation_metrics,
    frechet_distance,
    gaussian_frechet_distance,
    gaussian_statistics,
    rpcc,
    sid,
)
from jaxtalk.metrics.landmarks import MOUTH_LANDMARKS, landmark_metrics
from jaxtalk.metrics.vertex import delta_cd, delta_m, dfd, dtw, fdd, fdd_batch, jitter, lve, mod, mve

__all__ = [
    "lve",
    "mve",
    "fdd",
    "fdd_batch",
    "mod",
    "dtw",
    "dfd",
    "delta_m",
    "delta_cd",
    "jitter",
    "MOUTH_LANDMARKS",
    "landmark_metrics",
    "trajectory_dtw",
    "trajectory_dfd",
    "CONVERSATION_GROUPS",
    "SID_CLUSTERS",
    "PUBLISHED_SCALE",
    "gaussian_statistics",
    "gaussian_frechet_distance",
    "frechet_distance",
    "sid",
    "rpcc",
    "conversation_metrics",
]
