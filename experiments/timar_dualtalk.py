"""TIMAR on real input: the two DualTalk demo conversations (``../shared/data/dualtalk_demo``).

Each clip has both speakers' audio and ONE speaker's tracked FLAME motion. The model (trained on
SynthTalk by ``timar_context.py``, loaded from its pickle; or trained here briefly with ``--steps``)
streams the conversation with the known speaker as the user and produces the OTHER speaker's head
motion (no ground truth exists for it: reported are its statistics next to the known speaker's).
In the swapped role the known speaker is the agent, the generated motion of the other speaker is
the user's motion, and the prediction is scored against the known speaker's tracked motion with the
DualTalk metrics and the mean-pose baseline (the SynthTalk training mean, i.e. what the model would
output if it ignored the input). Both sides are rendered side by side with the built-in face
(``--render``; note the real FLAME expression basis is not the built-in face's, so only jaw and neck
are geometrically faithful).

Caveat that the numbers carry: SynthTalk's built-in expression basis and motion statistics differ
from real FLAME tracks, so this is a domain-transfer smoke run of the real pipeline, not a benchmark.

Skips cleanly (message, exit 0) when ``../shared`` is absent.

Usage: ``python experiments/timar_dualtalk.py [--model experiments/results/timar_context_model.pkl]
[--context 7] [--render]``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax
import numpy as np

from jaxtalk.audio.io import load_audio
from jaxtalk.benchmarking import print_table, write_json
from jaxtalk.data.formats import read_dualtalk
from jaxtalk.metrics.conversation import conversation_metrics
from jaxtalk.models.timar.data import turn_speech_features
from jaxtalk.models.timar.streaming import stream

from timar_common import load_model  # noqa: E402  (sibling script)

DEMO = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "dualtalk_demo"
KEYS = ("FD_exp", "FD_jaw", "FD_pose", "P-FD_jaw", "MSE_exp", "MSE_jaw", "MSE_pose", "rPCC_jaw")


def _stream(config, params, norm, user_speech, user_motion, agent_speech, context, cfg_scale, seed):
    x = stream(
        params, config, norm.speech(user_speech)[None], norm.motion(user_motion)[None], norm.speech(agent_speech)[None],
        jax.random.key(seed), context=context, cfg_scale=cfg_scale,
    )
    return norm.unmotion(np.asarray(x)[0])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="experiments/results/timar_context_model.pkl")
    ap.add_argument("--context", type=int, default=7)
    ap.add_argument("--cfg-scale", type=float, default=0.5, help="guidance weight w (the paper's omega - 1)")
    ap.add_argument("--render", action="store_true")
    ap.add_argument("--out", default="experiments/results/timar_dualtalk.json")
    args = ap.parse_args()
    if not DEMO.is_dir():
        print(f"skipping: the DualTalk demo clips are not here ({DEMO})")
        return 0
    if not Path(args.model).is_file():
        print(f"skipping: no trained model at {args.model}; run experiments/timar_context.py first")
        return 0
    config, params, norm = load_model(args.model)
    context = min(args.context, config.max_turns - 1)
    f = config.frames_per_turn

    rows, record = [], {}
    for npz in sorted(DEMO.glob("*.npz")):
        known = read_dualtalk(npz)
        other_wav = known.partner_audio_path
        if other_wav is None:
            print(f"{npz.name}: no partner audio, skipped")
            continue
        known_audio = known.audio
        other_audio = load_audio(other_wav)
        turns = min(known.params.shape[0] // f, known_audio.shape[0] // 16000, other_audio.shape[0] // 16000)
        t = turns * f
        known_motion = known.params[:t].astype(np.float32)
        s_known = turn_speech_features(known_audio, turns)
        s_other = turn_speech_features(other_audio, turns)
        # 1) The other speaker (unknown motion) as the agent, the known speaker as the user.
        other_motion = _stream(config, params, norm, s_known, known_motion, s_other, context, args.cfg_scale, 0)
        # 2) Swapped: the known speaker as the agent; the user's motion is the one generated in 1).
        pred_known = _stream(config, params, norm, s_other, other_motion, s_known, context, args.cfg_scale, 1)
        m = conversation_metrics(pred_known, known_motion, other_motion, scaled=True, sid_convention=None)
        base = conversation_metrics(np.broadcast_to(norm.motion_mean, known_motion.shape).copy(), known_motion,
                                    other_motion, scaled=True, sid_convention=None)
        clip = npz.stem
        record[clip] = {
            "turns": turns, "timar_swapped": m, "mean_pose_swapped": base,
            "generated_other_std": {"exp": float(other_motion[:, :50].std(0).mean()),
                                    "jaw": float(other_motion[:, 50:53].std(0).mean()),
                                    "neck": float(other_motion[:, 53:].std(0).mean())},
            "known_std": {"exp": float(known_motion[:, :50].std(0).mean()), "jaw": float(known_motion[:, 50:53].std(0).mean()),
                          "neck": float(known_motion[:, 53:].std(0).mean())},
        }
        rows.append({"clip": clip, "method": "TIMAR (swapped role)", **{k: m[k] for k in KEYS}})
        rows.append({"clip": clip, "method": "mean pose", **{k: base[k] for k in KEYS}})
        if args.render:
            from jaxtalk.face.procedural import builtin_face
            from jaxtalk.render.clip import render_clip

            face = builtin_face(0, resolution="low")
            verts = [np.asarray(face.vertices_seq(known_motion)), np.asarray(face.vertices_seq(other_motion))]
            path = Path(args.out).with_name(f"timar_dualtalk_{clip}.mp4")
            render_clip(path, verts, np.asarray(face.faces), audio=known_audio[: t * 640] + other_audio[: t * 640],
                        captions=["known speaker (tracked)", "other speaker (TIMAR)"], size=192)
            record[clip]["video"] = str(path)
            print("wrote", path)
    print_table(rows, f"TIMAR on the DualTalk demo clips (context n={context}, published scaling)")
    for clip, r in record.items():
        print(clip, "std per group: generated other", r["generated_other_std"], "known", r["known_std"])
    write_json(args.out, {"args": vars(args), "clips": record})
    return 0


if __name__ == "__main__":
    sys.exit(main())
