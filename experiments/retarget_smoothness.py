"""What the retargeter's look-back smoothness costs in lag and buys in steadiness, on real tracked motion.

The solver ties each frame's weights to the previous frame's (``Penalties.smoothness``); it looks back
only, so a live stream's weights equal ``jaxtalk retarget``'s. A one-sided tie delays the weights, and
this measures by how much. Motion: the FLAME parameters DualTalk tracked on a real 30-s recording
(``--motion``), posed on the built-in face and retargeted onto the built-in ARKit rig at each smoothness.
Against the frames solved independently (smoothness 0), per shape that moves (standard deviation of its
independent weights above 0.02):

* ``lag``: the shift (frames, -5..5) that best correlates the smoothed weights with the independent ones
  (positive: the smoothed weights come later); median and largest over the moving shapes;
* ``mean_abs_diff``: the mean absolute weight difference;
* ``jitter``: the mean absolute frame-to-frame weight change, as a share of the independent weights';
* ``jaw_corr``: ``jawOpen`` against the motion's jaw opening.

Usage: python experiments/retarget_smoothness.py --motion CLIP.npz [--smoothness 0 0.005 0.01 0.02 0.05 0.1]
    [--out experiments/results/retarget/smoothness.json]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from jaxtalk import benchmarking as bm
from jaxtalk.data.formats import dualtalk_to_params56
from jaxtalk.files import load_npz
from jaxtalk.export import Retargeter, arkit_rig
from jaxtalk.export.solver import Penalties
from jaxtalk.face import builtin_face
from jaxtalk.layout import JAW_OPEN_INDEX
from jaxtalk.metrics.speech_sync import lagged_correlation

MAX_LAG = 5
MOVING_STD = 0.02


def best_lag(smoothed: np.ndarray, reference: np.ndarray) -> int:
    """The shift of ``smoothed`` (frames; positive = later) that best correlates it with ``reference``."""
    lags, r = lagged_correlation(smoothed, reference, MAX_LAG)
    return int(lags[np.nanargmax(r)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--motion", required=True, help="a DualTalk .npz (exp, pose) of tracked motion")
    parser.add_argument("--smoothness", type=float, nargs="+", default=[0.0, 0.005, 0.01, 0.02, 0.05, 0.1])
    parser.add_argument("--out", default="experiments/results/retarget/smoothness.json")
    args = parser.parse_args()
    data = load_npz(args.motion, what="motion file")
    params = dualtalk_to_params56(data["exp"], data["pose"])
    rig = arkit_rig("low")
    retargeter = Retargeter.for_face(rig, builtin_face(0, resolution="low"))
    weights = {s: retargeter(params, penalties=Penalties(smoothness=s, l2=1e-4)).weights for s in args.smoothness}
    free = retargeter(params, penalties=Penalties(smoothness=0.0, l2=1e-4)).weights
    moving = np.flatnonzero(free.std(axis=0) > MOVING_STD)
    jitter_free = np.abs(np.diff(free, axis=0)).mean()
    jaw_open = rig.names.index("jawOpen")
    rows = []
    for s, w in weights.items():
        lags = [best_lag(w[:, k], free[:, k]) for k in moving]
        rows.append({"smoothness": s, "lag_median": float(np.median(lags)), "lag_max": int(max(lags)),
                     "mean_abs_diff": float(np.abs(w - free).mean()),
                     "jitter": float(np.abs(np.diff(w, axis=0)).mean() / jitter_free),
                     "jaw_corr": float(np.corrcoef(w[:, jaw_open], params[:, JAW_OPEN_INDEX])[0, 1])})
    bm.print_table(rows, f"Look-back smoothness on {Path(args.motion).name} ({len(params)} frames, "
                         f"{len(moving)} moving shapes)")
    bm.write_json(args.out, {"motion": Path(args.motion).name, "frames": len(params),
                             "moving_shapes": [rig.names[k] for k in moving], "rows": rows})


if __name__ == "__main__":
    main()
