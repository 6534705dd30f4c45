"""Does a trained TokTalk take a speaker's rest pose from the voice (tokens) or from the style clip?

For pairs of speakers (A, B) of a split, stream A's clip with A's style (own) and B's clip with A's
style (voice swapped), and print the lip distance (mm^2, built-in face) of each output's time-mean pose
to A's and B's rest pose (the mean of their clips). Output that follows A's rest under B's voice takes
the rest pose from the style; output far from A's rest on held-out speakers misses it.

    python experiments/toktalk_rest_pose.py RUN_DIR STEP SPLIT   # a run of the small preset on synthtalk:small
"""
import sys

import jax
import numpy as np

from jaxtalk.data.loader import PreparedData
from jaxtalk.runs import _restore_state, build_config, checkpoint_dir, model_spec
from jaxtalk.models.toktalk.model import encode_style, frames_for_tokens
from jaxtalk.models.toktalk.streaming import stream
from jaxtalk.face import builtin_face
run, step, split = sys.argv[1], int(sys.argv[2]), sys.argv[3]
data = PreparedData(".cache/prepared/synthtalk-small-seed0")
fields = [f"{f}={data.manifest[k]}" for f, k in model_spec("toktalk").data_fields]
config = build_config("toktalk", "small", fields)
state, _ = _restore_state(checkpoint_dir(run), step)
params = state["ema_params"]
by = {}
for i in data.split(split):
    by.setdefault(data.clips[i]["speaker"], []).append(i)
speakers = [s for s in by if len(by[s]) >= 2][:6]
face = builtin_face(0)
lips = face.regions["lips"]
rest = {s: np.mean([np.asarray(data.record(i, ("motion",))["motion"]).mean(0) for i in by[s]], 0) for s in speakers}
def run_clip(tok_clip, style_clip):
    rec = data.record(tok_clip, ("motion", "tokens"))
    tokens = np.asarray(rec["tokens"], np.float32)[None]
    t = min(frames_for_tokens(tokens.shape[1], config.token_rate, config.fps), rec["motion"].shape[0])
    style = np.asarray(data.record(style_clip, ("motion",))["motion"], np.float32)[:200][None]
    sv = encode_style(params, config, style)
    out = np.asarray(stream(params, config, tokens, sv, jax.random.key(0)))[0][:t]
    return out.mean(0)
def lipdist(a, b):
    va, vb = np.asarray(face.vertices_seq(a[None])), np.asarray(face.vertices_seq(b[None]))
    return float(((va[:, lips] - vb[:, lips]) ** 2).sum(-1).mean() * 1e6)
rows = []
for a, b in zip(speakers, speakers[1:] + speakers[:1]):
    own = run_clip(by[a][0], by[a][1])          # A's voice, A's style
    swapped = run_clip(by[b][0], by[a][1])      # B's voice, A's style
    rows.append((lipdist(own, rest[a]), lipdist(swapped, rest[a]), lipdist(swapped, rest[b]), lipdist(rest[a], rest[b])))
    print(f"{a}<-{b}: own-voice mean vs A rest {rows[-1][0]:.1f}; B-voice mean vs A rest {rows[-1][1]:.1f}, "
          f"vs B rest {rows[-1][2]:.1f}; A rest vs B rest {rows[-1][3]:.1f} mm^2", flush=True)
r = np.array(rows).mean(0)
print(f"{split} mean: own {r[0]:.1f}, swapped->A {r[1]:.1f}, swapped->B {r[2]:.1f}, A vs B {r[3]:.1f}")
