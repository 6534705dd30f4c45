"""Landmark-free alignment of the face meshes people bring, measured: shape x units -> success, the
units found, the reference face used, the fitted scale, the residual and how far the mesh's nose tip,
mouth corners and eye corners land from the template's (mm).

Shapes (``jaxtalk/testing/faces.py``): MediaPipe's canonical face, a built-in head with skull, neck and
ears, a BFM-style mask cut from it, the head as a noisy scan with holes, and, where they are on disk,
menpo3d's head scan (``bash experiments/fetch_real_scan.sh``), FLAME's template (the user's own file,
see ``jaxtalk/testing/faces.py``) and masks cut from both. Each in a random pose. Then shapes that are no
face, whose best fit must stay above the limit (``_MAX_FIT_M``).

Also the floor of the semantic error: the similarity fitted to the seven semantic points themselves
(the faces differ there, so no alignment of the whole face gets below it).

Prints both tables and writes them to ``--out`` (default
``experiments/results/alignment/canonical.json``).

Usage: python experiments/canonical_alignment.py [--units mm cm m] [--seed 0] [--out PATH]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from jaxtalk.geometry import canonical as cn
from jaxtalk.testing import faces as fs


def _shapes() -> list[fs.Shape]:
    shapes = [fs.mediapipe_face(), fs.procedural_head(), fs.bfm_mask(), fs.head_scan()]
    for extra in (fs.real_scan(), fs.flame_template()):
        if extra is not None:
            shapes += [extra, fs.cut_mask(extra)]
    return shapes


def _no_faces() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    import trimesh

    def arrays(mesh):
        return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)

    ellipsoid = trimesh.creation.icosphere(4)
    ellipsoid.apply_scale([0.075, 0.11, 0.095])
    mask = trimesh.creation.icosphere(4)
    mask.apply_scale([0.075, 0.1, 0.06])
    mask.update_faces(mask.vertices[mask.faces].mean(axis=1)[:, 2] > 0)
    return {"sphere (r 10 cm)": arrays(trimesh.creation.icosphere(4, radius=0.1)),
            "ellipsoid (15 x 22 x 19 cm)": arrays(ellipsoid),
            "box (15 x 20 x 12 cm)": arrays(trimesh.creation.box([0.15, 0.2, 0.12])),
            "cylinder (r 8 cm, 22 cm)": arrays(trimesh.creation.cylinder(0.08, 0.22, sections=64)),
            "smooth mask (half ellipsoid)": arrays(mask),
            "torus (7 + 3 cm)": arrays(trimesh.creation.torus(0.07, 0.03))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--units", nargs="+", default=["mm", "cm", "m"], choices=list(cn.UNITS))
    parser.add_argument("--seed", type=int, default=0, help="seed of the random poses")
    parser.add_argument("--out", type=Path, default=Path("experiments/results/alignment/canonical.json"))
    args = parser.parse_args()
    from jaxtalk.benchmarking import write_json
    from jaxtalk.face import builtin_face
    from jaxtalk.models.freetalk.data import neutral_landmarks

    tv, tf, points = fs.template()
    landmarks = neutral_landmarks(builtin_face(0, resolution="low")).astype(np.float64)
    print("| shape | vertices | units | aligned | units found | reference | scale | residual (mm) | max / mean error (mm) "
          "| floor max / mean (mm) | seconds |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    faces, no_faces = [], []
    for k, shape in enumerate(_shapes()):
        s, rot, t = cn.umeyama(shape.points, points, scale=True)
        floor = np.linalg.norm(s * shape.points @ rot.T + t - points, axis=1) * 1000
        for unit in args.units:
            vertices, semantic = fs.posed(args.seed * 100 + k, shape.vertices, shape.points)
            t0 = time.perf_counter()
            try:
                c = cn.canonicalize(vertices / cn.UNITS[unit], shape.faces, tv, tf, template_landmarks=landmarks)
            except ValueError as err:
                print(f"| {shape.name} | {len(shape.vertices)} | {unit} | no: {err} | | | | | | | |")
                faces.append({"shape": shape.name, "vertices": len(shape.vertices), "units": unit, "aligned": False,
                              "error": str(err)})
                continue
            seconds = time.perf_counter() - t0
            error = np.linalg.norm(c.to_template(semantic / cn.UNITS[unit]) - points, axis=1) * 1000
            print(f"| {shape.name} | {len(shape.vertices)} | {unit} | yes | {c.units} | {c.reference} | {c.fitted_scale:.3f} "
                  f"| {c.residual * 1000:.1f} | {error.max():.1f} / {error.mean():.1f} | {floor.max():.1f} / {floor.mean():.1f} "
                  f"| {seconds:.1f} |", flush=True)
            faces.append({"shape": shape.name, "vertices": len(shape.vertices), "units": unit, "aligned": True,
                          "units_found": c.units, "reference": c.reference, "scale": float(c.fitted_scale),
                          "residual_mm": float(c.residual * 1000), "max_error_mm": float(error.max()),
                          "mean_error_mm": float(error.mean()), "floor_max_mm": float(floor.max()),
                          "floor_mean_mm": float(floor.mean()), "seconds": seconds})
    print("\n| no face | best fit (mm; limit %.0f) | refused |" % (cn._MAX_FIT_M * 1000))
    print("|---|---|---|")
    references = [cn._face(tv, tf), cn._face(*cn.reference_face())]
    for name, (vertices, faces) in _no_faces().items():
        user = cn._surface(vertices, faces)
        fits = [float(cn._fit_score(cn._distances(face.core, user, cn._fit(face, user)), face.weights)) for face in references]
        try:
            cn.canonicalize(vertices * 1000, faces, tv, tf, template_landmarks=landmarks)
            refused = "no"
        except ValueError as err:
            refused = "yes: " + str(err).split(":")[0]
        print(f"| {name} | {min(fits) * 1000:.1f} | {refused} |", flush=True)
        no_faces.append({"shape": name, "best_fit_mm": min(fits) * 1000, "refused": refused != "no",
                         "message": refused})
    write_json(args.out, {"seed": args.seed, "limit_mm": cn._MAX_FIT_M * 1000, "faces": faces, "no_faces": no_faces})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
