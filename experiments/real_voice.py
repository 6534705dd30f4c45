"""Does a trained TokTalk run move the mouth with a real person's speech, on time, and close it in silence?

For each run given, streamed exactly as ``jaxtalk stream RUN FILE --best`` streams:

* every recording of a folder of real speech (``*.wav``; DualTalk's ``X_speakerN.wav`` with
  ``X_speakerN.npz`` tracked FLAME beside it where there is one): ``jaxtalk.metrics.speech_sync`` (the
  jaw's correlation with the tracked jaw at lag 0, its best lag, the loudness follower beside it, the jaw
  in silence vs speech; with tracked motion also a 0/1 speech indicator's correlation with the tracked
  jaw and the tracked jaw in silence vs speech);
* silence: 8 s of a -90 dBFS dither (digital zero is refused as no speech) and 8 s of steady white noise
  at -40 and -30 dBFS: the jaw's mean after the first second, and its distance from the rest of the
  run's default style clip (``jaxtalk.metrics.speech_sync.style_rest_jaw``), the opening a mouth in
  that style should hold in silence;
* SynthTalk ``small`` seed 0's held-out demo clip (the clip ``jaxtalk demo`` reports, streamed with its
  speaker's style clip): the lip error LVE (mm^2) and the mean-pose baseline's.

    python experiments/real_voice.py --real ../shared/data/dualtalk_demo --out experiments/results/real_voice.json RUN [RUN ...]
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np
import soundfile as sf

from jaxtalk.audio import load_audio
from jaxtalk.commands.inference import SampleOptions, stream_run
from jaxtalk.layout import JAW_OPEN_INDEX
from jaxtalk.metrics.speech_sync import frame_loudness, speech_sync, style_rest_jaw, voice_activity
from jaxtalk.files import load_npy
from jaxtalk.runs import STYLE_FILE

SR = 16000


def _stream(run: Path, audio: np.ndarray, tmp: Path, style: Path | None = None) -> np.ndarray:
    wav = tmp / "input.wav"
    sf.write(wav, audio, SR, subtype="FLOAT")
    out = tmp / "out.npz"
    out.unlink(missing_ok=True)
    return stream_run(SampleOptions(run, wav, out=out, best=True, style=style), echo=lambda s: None).params


def _tracked_jaw(wav: Path) -> np.ndarray | None:
    npz = wav.with_suffix(".npz")
    if not npz.is_file():
        return None
    with np.load(npz) as z:
        return np.asarray(z["pose"][:, 3] if "pose" in z else z["params"][:, JAW_OPEN_INDEX], np.float64)


def _real(run: Path, folder: Path, tmp: Path) -> list[dict]:
    rows = []
    for wav in sorted(folder.glob("*.wav")):
        audio = load_audio(wav)
        jaw = _stream(run, audio, tmp)[:, JAW_OPEN_INDEX]
        tracked = _tracked_jaw(wav)
        n = jaw.shape[0] if tracked is None else min(jaw.shape[0], tracked.shape[0])
        m = speech_sync(jaw[:n], audio, SR, tracked_jaw=None if tracked is None else tracked[:n])
        row = {"recording": wav.name, "tracked": tracked is not None, **m.to_dict()}
        if tracked is not None:
            # What a pure speech detector scores, and how far the tracked jaw itself moves between
            # silence and speech: the scale of what `corr` can see on this clip.
            speech = voice_activity(frame_loudness(audio, SR, n))
            row["speech_indicator_corr"] = float(np.corrcoef(speech.astype(np.float64), tracked[:n])[0, 1])
            row["tracked_jaw_silence"] = float(tracked[:n][~speech].mean())
            row["tracked_jaw_speech"] = float(tracked[:n][speech].mean())
        rows.append(row)
    return rows


def _silence(run: Path, tmp: Path) -> dict:
    n = 8 * SR
    # jaxtalk refuses digital zero as "no speech": the quietest input is a -90 dBFS dither.
    dither = (10 ** (-90 / 20) * np.random.default_rng(1).standard_normal(n)).astype(np.float32)
    rest = _stream(run, dither, tmp)[25:, JAW_OPEN_INDEX]
    style_rest = style_rest_jaw(np.asarray(load_npy(run / STYLE_FILE))[:, JAW_OPEN_INDEX])
    out = {"style_rest_jaw": style_rest, "rest_jaw": float(rest.mean()),
           "dither_jaw_minus_style_rest": float(rest.mean() - style_rest)}
    for db in (-40, -30):
        noise = (10 ** (db / 20) * np.random.default_rng(0).standard_normal(n)).astype(np.float32)
        jaw = _stream(run, noise, tmp)[25:, JAW_OPEN_INDEX]
        out[f"noise_{-db}dBFS_jaw_minus_rest"] = float(np.mean(jaw - rest))
        out[f"noise_{-db}dBFS_jaw_minus_style_rest"] = float(np.mean(jaw) - style_rest)
    return out


def _synthtalk(run: Path, tmp: Path) -> dict:
    from jaxtalk.data import synthtalk
    from jaxtalk.demo import _pick_clips
    from jaxtalk.face import builtin_face
    from jaxtalk.metrics import lve

    corpus = synthtalk.generate("small", 0, cache_dir=".cache/synthtalk")
    clip, style_clip = _pick_clips(corpus)
    style = tmp / "style.npz"
    np.savez(style, params=np.asarray(corpus.motion(style_clip), np.float32), fps=np.float32(25))
    gt = np.asarray(corpus.motion(clip), np.float32)
    pred = _stream(run, corpus.audio(clip), tmp, style=style)[:gt.shape[0]]
    face = builtin_face(0)
    lips = face.regions["lips"]
    vg = np.asarray(face.vertices_seq(gt))
    train = np.concatenate([corpus.motion(i) for i in corpus.split("train")])
    mean_pose = np.broadcast_to(train.mean(0), gt.shape)
    return {"clip": clip, "LVE_mm2": float(lve(np.asarray(face.vertices_seq(pred)), vg, lips)) * 1e6,
            "mean_pose_LVE_mm2": float(lve(np.asarray(face.vertices_seq(np.asarray(mean_pose, np.float32))), vg, lips)) * 1e6}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path)
    parser.add_argument("--real", type=Path, required=True, help="folder of real recordings (*.wav, tracked *.npz)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for run in args.runs:
            record = json.loads((run / "run.json").read_text())
            results[str(run)] = {"data": record.get("data", {}).get("spec"), "items": record.get("items"),
                                 "real": _real(run, args.real, Path(tmp)), "silence": _silence(run, Path(tmp)),
                                 "synthtalk_small_heldout": _synthtalk(run, Path(tmp))}
            print(json.dumps({str(run): results[str(run)]}, indent=1))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
