"""The DualTalk release layout: ``train/``, ``test/``, ``ood/`` (and optionally ``val/``), each flat::

    <name>_speaker1.npz  <name>_speaker1.wav  <name>_speaker2.npz  <name>_speaker2.wav

npz: FLAME ``exp (T, 50)``, ``pose (T, 6)`` = neck | jaw (other keys ignored), 25 fps; wav at any
rate. The two sides of a name are one conversation. A side with a wav but no npz is audio-only: a
partner without tracked motion (as in DualTalk's own demo clips). A side with motion whose partner
has no wav is reported as a broken clip (missing partner).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from jaxtalk.data.sources.clip import ClipEntry, RawClip

__all__ = ["SPLIT_FOLDERS", "is_dualtalk", "dualtalk_entries"]

SPLIT_FOLDERS = ("train", "val", "test", "ood")
_SIDE = re.compile(r"^(?P<conv>.+)_speaker(?P<side>[12])$")
# DualTalk names are "<youtube id>_sub_video_<n>[_<k>]": sub-clips of one video share its people.
_VIDEO = re.compile(r"^(?P<video>.+?)_sub_video")


def is_dualtalk(root: Path) -> bool:
    """A folder with at least one split folder holding ``*_speaker[12].wav`` files."""
    return any((root / s).is_dir() and any((root / s).glob("*_speaker[12].wav")) for s in SPLIT_FOLDERS)


def is_flat_dualtalk(root: Path) -> bool:
    """DualTalk's ``*_speaker1.wav`` / ``*_speaker2.wav`` files lying in ``root`` itself, without the
    split folders (``train/``, ``test/``) that :func:`is_dualtalk` looks for."""
    return not is_dualtalk(root) and any(root.glob("*_speaker[12].wav"))


def _read(npz: Path | None, wav: Path) -> RawClip:
    from jaxtalk.audio.io import load_audio
    from jaxtalk.data.formats import dualtalk_to_params56
    from jaxtalk.files import load_npz

    params = None
    if npz is not None:
        data = load_npz(npz, what="motion file")
        missing = [k for k in ("exp", "pose") if k not in data]
        if missing:
            raise ValueError(f"missing keys {missing} (found {sorted(data)})")
        exp, pose = np.asarray(data["exp"], np.float32), np.asarray(data["pose"], np.float32)
        if exp.ndim != 2 or pose.ndim != 2 or exp.shape[1] != 50 or pose.shape[1] != 6:
            raise ValueError(f"expected exp (T, 50) and pose (T, 6), got {exp.shape} and {pose.shape}")
        if exp.shape[0] != pose.shape[0]:
            raise ValueError(f"exp has {exp.shape[0]} frames but pose has {pose.shape[0]}")
        params = dualtalk_to_params56(exp, pose)
    audio = load_audio(wav, allow_silence=True)
    return RawClip(fps=25.0, params=params, audio=audio)


def dualtalk_entries(root: Path) -> list[ClipEntry]:
    """Every side of every conversation under ``root``'s split folders, sorted by split and name."""
    entries: list[ClipEntry] = []
    for split in SPLIT_FOLDERS:
        folder = root / split
        if not folder.is_dir():
            continue
        stems = sorted({p.stem for p in folder.iterdir() if p.suffix in (".npz", ".wav") and _SIDE.match(p.stem)})
        for stem in stems:
            m = _SIDE.match(stem)
            conv, side = m["conv"], m["side"]
            partner = f"{conv}_speaker{'2' if side == '1' else '1'}"
            npz, wav = folder / f"{stem}.npz", folder / f"{stem}.wav"
            vm = _VIDEO.match(conv)
            motion = npz if npz.is_file() else None
            entries.append(ClipEntry(
                name=stem,
                speaker=f"{conv}_speaker{side}",
                files=(npz, wav) if motion is not None else (wav,),
                read=lambda motion=motion, wav=wav: _read(motion, wav),
                split=split,
                partner=partner,
                requires_partner=True,
                group=vm["video"] if vm else conv,
            ))
    return entries
