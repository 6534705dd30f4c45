"""Landmark-free alignment in any pose and unit: every face of the alignment table
(``experiments/canonical_alignment.py``: MediaPipe's canonical face, a built-in head with skull, neck and
ears, a BFM-style mask, the head as a noisy scan, and menpo3d's head scan and FLAME's template with masks
cut from them where they are on disk), a face kit (MediaPipe's face with its eyes and mouth open and
eyeballs, teeth and lashes of their own) and a captured-style head (deep skull, short tilted neck, so that
its longest axis runs from the chin to the back of the skull; with eyeballs, teeth and lashes) and, where
``experiments/fetch_ict_face_kit.sh`` has fetched it, a public face kit as shipped (the ICT Face Model's
neutral head: centimetres, 12 materials, eyes, lashes, teeth, gums and tongue), each in 20
random poses (scipy's ``Rotation.random`` seeded, and a shift of up to 1.5 m), the poses taking turns in
millimetres, centimetres and metres.

Per pose: the distance of the mesh's nose tip, mouth corners and eye corners from the template's after the
alignment (mm), or the refusal and its reason. Per face: the seven-point floor (the similarity fitted to
those seven points themselves: no alignment of the whole face gets below it), the worst and the median
pose, the parts left out, and the time one alignment takes.

Usage: python experiments/alignment_any_pose.py [--poses 20] [--budget-s 600]
       [--out experiments/results/alignment/any_pose.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import canonical_alignment  # noqa: E402  (the alignment table's faces)

from jaxtalk.geometry import canonical as cn  # noqa: E402
from jaxtalk.testing import faces as fs  # noqa: E402

UNIT_CYCLE = ("mm", "cm", "m")


def _shapes() -> list[fs.Shape]:
    kit = fs.with_inner_parts(fs.mediapipe_face(), holes=True, lashes=True)
    shapes = [*canonical_alignment._shapes(), kit, fs.captured_head()]
    public_kit = fs.ict_face_kit()  # bash experiments/fetch_ict_face_kit.sh
    return shapes if public_kit is None else [*shapes, public_kit]


def _summary(values: list[float]) -> dict[str, float] | None:
    return None if not values else {"max": round(max(values), 2), "median": round(float(np.median(values)), 2)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--poses", type=int, default=20, help="random poses per face")
    parser.add_argument("--budget-s", type=float, default=480.0,
                        help="time for the whole run: each face gets its share, and stops starting poses past it")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "alignment" / "any_pose.json")
    args = parser.parse_args()
    _, _, points = fs.template()
    landmarks = fs.template_landmarks()
    tv, tf, _ = fs.template()
    start, faces, shapes = time.perf_counter(), [], _shapes()
    for k, shape in enumerate(shapes):
        deadline = start + args.budget_s * (k + 1) / len(shapes)
        s, rot, t = cn.umeyama(shape.points, points, scale=True)
        floor = np.linalg.norm(s * shape.points @ rot.T + t - points, axis=1) * 1000
        rows, seconds = [], []
        for pose in range(args.poses):
            if time.perf_counter() > deadline:
                break
            unit = UNIT_CYCLE[pose % len(UNIT_CYCLE)]
            seed = 1000 * k + pose
            vertices, semantic = fs.posed(seed, shape.vertices, shape.points)
            clock = time.perf_counter()
            try:
                canon = cn.canonicalize(vertices / cn.UNITS[unit], shape.faces, tv, tf, template_landmarks=landmarks)
            except ValueError as err:
                rows.append({"seed": seed, "unit": unit, "refused": str(err)})
                continue
            seconds.append(time.perf_counter() - clock)
            error = np.linalg.norm(canon.to_template(semantic / cn.UNITS[unit]) - points, axis=1) * 1000
            rows.append({"seed": seed, "unit": unit, "units_found": canon.units, "reference": canon.reference,
                         "scale": round(canon.fitted_scale, 3), "ignored": list(canon.ignored),
                         "error_max_mm": round(float(error.max()), 2), "error_mean_mm": round(float(error.mean()), 2),
                         "seconds": round(seconds[-1], 2)})
        aligned = [r for r in rows if "refused" not in r]
        entry = {
            "face": shape.name, "vertices": int(len(shape.vertices)),
            "floor_mm": {"max": round(float(floor.max()), 2), "mean": round(float(floor.mean()), 2)},
            "poses": len(rows), "aligned": len(aligned), "refused": len(rows) - len(aligned),
            "units_right": sum(r["units_found"] == r["unit"] for r in aligned),
            "references": sorted({r["reference"] for r in aligned}),
            "ignored_part_vertices": sorted({tuple(r["ignored"]) for r in aligned}),
            "error_max_mm": _summary([r["error_max_mm"] for r in aligned]),
            "error_mean_mm": _summary([r["error_mean_mm"] for r in aligned]),
            "seconds": _summary(seconds), "per_pose": rows,
        }
        faces.append(entry)
        worst = entry["error_max_mm"] or {"max": float("nan"), "median": float("nan")}
        print(f"{shape.name}: {entry['aligned']}/{entry['poses']} aligned (units right {entry['units_right']}), "
              f"largest error worst {worst['max']:.1f} / median {worst['median']:.1f} mm, floor {entry['floor_mm']['max']:.1f} "
              f"mm, parts left out {entry['ignored_part_vertices']}", flush=True)
    result = {
        "what": __doc__.split("\n\n")[0].replace("\n", " "),
        "error": "distance of the nose tip, mouth corners and eye corners from the template's after alignment (mm)",
        "units_cycle": list(UNIT_CYCLE), "poses_per_face": args.poses, "budget_s": args.budget_s,
        "machine": f"{os.cpu_count()} CPU cores ({platform.machine()}), shared with other jobs",
        "wall_s": round(time.perf_counter() - start, 1), "faces": faces,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"written {args.out} in {result['wall_s']:.0f} s")


if __name__ == "__main__":
    main()
