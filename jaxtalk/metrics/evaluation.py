"""What every model's evaluation protocol shares (``jaxtalk eval`` calls the protocol its spec names).

* :class:`EvalSettings`: the knobs a protocol reads (clips, seed, FLAME, step counts, temperature).
* :class:`EvalTable`: one printed table.
* :func:`vertex_metrics`: TokTalk's columns for one parameter track posed on a face (MSE, LVE, MVE,
  FDD, MOD, jitter).
* :func:`average_metrics` and :func:`method_rows`: per-clip metrics averaged over clips weighted by
  their frames (FDD: the plain mean over clips), one row per method.
* :func:`flame_face`: FLAME posed for the metrics, with the regions of ``FLAME_masks.pkl`` beside it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["EvalSettings", "EvalTable", "EvalProtocol", "vertex_metrics", "average_metrics", "method_rows",
           "flame_face", "SCORINGS"]


# How a turn model's conversation sides are scored (:attr:`EvalSettings.scoring`), with the words the
# tables' titles use for each.
SCORINGS: dict[str, str] = {
    "jaxtalk": "whole sides, the tail after the last whole turn repeating it",
    "public": "as the public calc_metric.py: whole seconds, cut to the shortest",
}


@dataclasses.dataclass(frozen=True)
class EvalSettings:
    """What an evaluation protocol reads.

    Attributes:
        max_clips: at most this many clips (TokTalk, ATS, STM) or conversation sides (TIMAR, DualTalk).
        seed: noise seed.
        flame: TokTalk: a FLAME 2020 model file to pose the parameters on instead of the built-in face.
        sample_steps: TokTalk: Euler step counts, one streamed row each (empty: the config's).
        offline: TokTalk: also sample each clip offline in one pass (full attention), per step count.
        temperature: scale of the sampler's noise (TokTalk: the starting noise, None: the config's;
            TIMAR: MAR's temperature, None: 1).
        scoring: TIMAR and the DualTalk baseline: how each conversation side is scored, one set of
            tables per entry of :data:`SCORINGS`: ``"jaxtalk"`` scores the agent's whole side (the
            frames after the last whole turn repeat its prediction); ``"public"`` as the public TIMAR
            code's ``calc_metric.py``: the prediction's whole seconds only, prediction, truth and
            partner cut to the shortest.
    """

    max_clips: int = 8
    seed: int = 0
    flame: Path | None = None
    sample_steps: tuple[int, ...] = ()
    offline: bool = False
    temperature: float | None = None
    scoring: tuple[str, ...] = ("jaxtalk",)

    def __post_init__(self) -> None:
        unknown = [s for s in self.scoring if s not in SCORINGS]
        if unknown or not self.scoring:
            raise ValueError(f"scoring must name one or more of {', '.join(SCORINGS)}, got {self.scoring!r}")


@dataclasses.dataclass
class EvalTable:
    """One printed table: a title and its rows (dicts with the same keys; None prints as ``-``)."""

    title: str
    rows: list[dict[str, Any]]


# ``protocol(run, data, split, settings, echo) -> (items scored, tables)``: a loaded run, its prepared data.
EvalProtocol = Callable[[Any, Any, str, EvalSettings, Callable[[str], None]], tuple[int, list[EvalTable]]]


def vertex_metrics(pred: np.ndarray, gt: np.ndarray, face: Any, *, gt_vertices: np.ndarray | None = None,
                   template: np.ndarray | None = None) -> dict[str, float | None]:
    """TokTalk's columns for one ``(T, 56)`` track posed on ``face``.

    Args:
        pred: ``(T, 56)`` prediction.
        gt: ``(T, 56)`` ground truth.
        face: the face model; a metric whose region (``lips``; ``upper_face``; ``mouth_upper`` and
            ``mouth_lower``) it lacks is None.
        gt_vertices: ``face.vertices_seq(gt)`` when already computed.
        template: the neutral face ``(V, 3)`` (default: ``face`` at zero parameters).

    Returns:
        ``{"MSE", "LVE_mm2", "MVE_mm", "FDD_mm2", "MOD_mm", "jitter_mm"}``: MSE of the parameters; LVE (mm^2,
        per frame the max over the lip vertices of the squared error, averaged); MVE (mm, mean vertex error);
        FDD (mm^2, signed upper-face dynamics deviation: positive when the prediction moves the upper face
        less than the truth); MOD (mm, mouth-opening distance); jitter (mm per frame^2, mean vertex
        acceleration).

    Raises:
        ValueError: shapes differ.
    """
    from jaxtalk.metrics import fdd, jitter, lve, mod, mve

    if pred.shape != gt.shape:
        raise ValueError(f"prediction {pred.shape} and ground truth {gt.shape} differ in shape")
    regions = face.regions
    vp = np.asarray(face.vertices_seq(pred))
    vg = np.asarray(face.vertices_seq(gt)) if gt_vertices is None else gt_vertices
    if template is None:
        template = np.asarray(face.vertices(np.zeros(pred.shape[1], np.float32)))
    has_mouth = "mouth_upper" in regions and "mouth_lower" in regions
    return {
        "MSE": float(np.mean((pred - gt) ** 2)),
        "LVE_mm2": float(lve(vp, vg, regions["lips"])) * 1e6 if "lips" in regions else None,
        "MVE_mm": float(mve(vp, vg)) * 1e3,
        "FDD_mm2": float(fdd(vp, vg, template, regions["upper_face"])) * 1e6 if "upper_face" in regions else None,
        "MOD_mm": float(mod(vp, vg, regions["mouth_upper"], regions["mouth_lower"])) * 1e3 if has_mouth else None,
        "jitter_mm": float(jitter(vp)) * 1e3,
    }


def average_metrics(per_item: Sequence[dict[str, float | None]], frames: Sequence[int],
                    plain: tuple[str, ...] = ("FDD_mm2",)) -> dict[str, float | None]:
    """Frame-weighted means of per-clip metrics (keys in ``plain``: unweighted); None stays None."""
    weights = np.asarray(frames, np.float64)
    out: dict[str, float | None] = {}
    for key in per_item[0]:
        values = [m[key] for m in per_item]
        if any(v is None for v in values):
            out[key] = None
        elif key in plain:
            out[key] = float(np.mean(values))
        else:
            out[key] = float(np.sum(weights * np.asarray(values)) / weights.sum())
    return out


def method_rows(per: dict[str, list[dict[str, float | None]]], frames: list[int], *, lead: dict[str, Any] | None = None,
                count: str = "clips") -> list[dict[str, Any]]:
    """One row per method with items: ``lead`` columns, method, item count, frames, the averages."""
    return [{**(lead or {}), "method": name, count: len(items), "frames": int(sum(frames)),
             **average_metrics(items, frames)} for name, items in per.items() if items]


def flame_face(path: Path) -> tuple[Any, list[str]]:
    """FLAME posed for the metrics, with regions from ``FLAME_masks.pkl`` beside it; notes to print.

    Raises:
        ValueError: an unreadable mask pickle.
    """
    import pickle

    from jaxtalk.face import load_flame
    from jaxtalk.face.flame import _NoChumpyUnpickler

    masks_path = Path(path).with_name("FLAME_masks.pkl")
    regions: dict[str, np.ndarray] = {}
    if masks_path.is_file():
        with open(masks_path, "rb") as fh:
            try:
                masks = _NoChumpyUnpickler(fh, encoding="latin1").load()
            except (pickle.UnpicklingError, EOFError) as err:
                raise ValueError(f"{masks_path} is not a readable FLAME mask pickle: {err}") from None
        if "lips" in masks:
            regions["lips"] = np.asarray(masks["lips"])
        upper = [np.asarray(masks[k]).reshape(-1) for k in ("forehead", "eye_region") if k in masks]
        if upper:
            regions["upper_face"] = np.unique(np.concatenate(upper))
    face = load_flame(path, regions=regions)
    notes = ["FLAME has no mouth-opening vertex pairs: MOD left out"]
    if not regions:
        notes.append(f"no FLAME_masks.pkl beside {path}: LVE and FDD (lip and upper-face regions) left out")
    return face, notes
