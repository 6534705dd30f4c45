"""Retarget real tracked motion onto a public blendshape rig as it is shipped, through ``jaxtalk retarget``.

The rig is a folder of OBJ shapes (``--rig``; the ICT Face Model's neutral head and its 53 expression
shapes under ARKit's names, ``bash experiments/fetch_ict_face_kit.sh --rig``: a captured head in
centimetres with eyes, lashes, teeth, gums and tongue) and the same rig written as a glTF file with its
morph targets, then compressed by ``gltfpack -cc`` (meshopt, quantized positions: how three.js's
``facecap.glb`` is shipped; gltfpack also merges vertices that are equal in every attribute). The motion
is the FLAME parameters DualTalk tracked on a real 30-s recording (``--motion``). Reported per rig file:
the command's lines, its wall time, the shapes matched to ARKit's names (whole, or as left and right
halves), ``jawOpen`` against the motion's jaw opening (Pearson r), the weights' range, the fit's RMS
error, the Khronos validator's errors and warnings on the output (where Node.js and ``tests/js`` are
there), and for the compressed file the largest weight difference from the folder's.

Usage: python experiments/retarget_public_rig.py --rig .cache/assets/ict_face_kit --motion CLIP.npz
    [--work runs/public_rig] [--out experiments/results/retarget/public_rig.json]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from jaxtalk import benchmarking as bm
from jaxtalk.data.formats import dualtalk_to_params56
from jaxtalk.files import load_npz
from jaxtalk.export import export_rig_animation, load_rig
from jaxtalk.export.rig import arkit_halves, arkit_shape_name
from jaxtalk.layout import JAW_OPEN_INDEX

ROOT = Path(__file__).resolve().parents[1]
JS = ROOT / "tests" / "js"


def run_retarget(motion: Path, rig: Path, out: Path) -> tuple[list[str], float]:
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "jaxtalk", "retarget", str(motion), "--rig", str(rig), "--out",
                           str(out), "--overwrite"], capture_output=True, text=True)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise SystemExit(f"jaxtalk retarget failed on {rig}:\n{done.stdout}\n{done.stderr}")
    return done.stdout.strip().splitlines(), seconds


def validate(path: Path) -> dict | None:
    if shutil.which("node") is None or not (JS / "node_modules" / "gltf-validator").is_dir():
        return None
    done = subprocess.run(["node", str(JS / "validate.mjs"), str(path)], capture_output=True, text=True, check=True)
    report = json.loads(done.stdout.splitlines()[0])
    issues = report.get("issues", report)
    return {"errors": issues.get("numErrors"), "warnings": issues.get("numWarnings")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rig", type=Path, required=True, help="the rig as shipped (an OBJ folder or a .glb)")
    parser.add_argument("--motion", type=Path, required=True, help="a DualTalk .npz (exp, pose) of tracked motion")
    parser.add_argument("--work", type=Path, default=Path("runs/public_rig"))
    parser.add_argument("--out", type=Path, default=ROOT / "experiments" / "results" / "retarget" / "public_rig.json")
    args = parser.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    data = load_npz(args.motion, what="motion file")
    params = dualtalk_to_params56(data["exp"], data["pose"])
    motion = args.work / "motion.npz"
    np.savez(motion, params=params, fps=25.0)

    rigs = {"shipped": args.rig}
    if args.rig.is_dir():  # the same rig as a glTF file, meshopt-compressed as tools ship them
        rig = load_rig(args.rig)
        plain = export_rig_animation(rig, np.zeros((1, rig.num_shapes)), args.work / "rig_plain.glb").path
        gltfpack = JS / "node_modules" / ".bin" / "gltfpack"
        if gltfpack.exists():
            packed = args.work / "rig_meshopt.glb"
            subprocess.run([str(gltfpack), "-i", str(plain), "-o", str(packed), "-cc", "-kn", "-km"], check=True,
                           capture_output=True)
            rigs["meshopt"] = packed
    rows, first = [], None
    for label, path in rigs.items():
        out = args.work / f"retargeted_{label}.glb"
        lines, seconds = run_retarget(motion, path, out)
        result = json.loads(out.with_suffix(".json").read_text())
        weights = np.asarray(result["weights"], np.float64)
        names = result["names"]
        arkit = {a for a in result["arkit"] if a is not None} | set(arkit_halves(names))
        jaw = weights[:, [arkit_shape_name(n) for n in names].index("jawOpen")]
        row = {"rig": label, "file": path.name, "seconds": round(seconds, 1), "shapes": len(names),
               "arkit_names": len(arkit), "jawOpen_r": float(np.corrcoef(jaw, params[:, JAW_OPEN_INDEX])[0, 1]),
               "weight_min": float(weights.min()), "weight_max": float(weights.max()), "lines": lines,
               "validator": validate(out)}
        if first is None:
            first = (names, weights)
        else:
            order = [names.index(n) for n in first[0]]
            row["max_weight_diff_from_shipped"] = float(np.abs(weights[:, order] - first[1]).max())
        rows.append(row)
        print(f"{label}: {row['arkit_names']}/52 ARKit names, jawOpen r {row['jawOpen_r']:.4f}, weights "
              f"[{row['weight_min']:.3f}, {row['weight_max']:.3f}], {seconds:.1f} s, validator {row['validator']}")
        print("  " + "\n  ".join(lines))
    bm.write_json(args.out, {"motion": args.motion.name, "frames": len(params), "rig": args.rig.name, "rows": rows})


if __name__ == "__main__":
    main()
