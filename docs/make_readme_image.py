"""Regenerate ``docs/synthtalk_face.png``: three frames of a SynthTalk clip on the built-in face.

Usage: ``python docs/make_readme_image.py [--cache .cache/synthtalk]`` (tiny corpus, seed 0).
The frames are the clip's closed, half-open and most open mouth (by the recorded jaw parameter).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from jaxtalk.data import synthtalk
from jaxtalk.render import render_frames, save_png
from jaxtalk.types import JAW_SLICE


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cache", default=".cache/synthtalk")
    parser.add_argument("--out", type=Path, default=Path(__file__).with_name("synthtalk_face.png"))
    args = parser.parse_args()
    corpus = synthtalk.generate("tiny", seed=0, cache_dir=args.cache)
    clip = next(i for i in corpus.split("test") if not corpus.clips[i].is_conversation)
    motion = np.asarray(corpus.motion(clip))
    jaw = motion[:, JAW_SLICE.start]
    order = np.argsort(jaw)
    picks = [int(order[0]), int(order[len(order) // 2]), int(order[-1])]
    face = corpus.face(0)
    verts = [np.asarray(face.vertices_seq(motion[i : i + 1])) for i in picks]
    image = render_frames(verts, face.faces, captions=[f"t = {i / 25:.2f} s" for i in picks], size=220,
                          rest_vertices=[face.template] * 3)[0]
    print(save_png(args.out, image))


if __name__ == "__main__":
    main()
