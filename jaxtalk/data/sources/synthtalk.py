"""SynthTalk as a dataset source: exported to the generic layout on disk, or listed in memory.

``export_generic(corpus, out)`` writes every clip as ``<clip>.wav`` (float32, lossless), ``<clip>.npz``
(``params56``, ``oracle``, ``fps``), ``<clip>.tokens.npy`` (the base token stream "A") plus
``tokens.json``, the stream's ``tokenizer.npz`` and ``metadata.csv`` (speaker, emotion, intensity, split, partner): any tool that
reads the generic layout reads SynthTalk like a user's folder. ``synthtalk_entries(corpus)`` lists
the same clips without files, for preparing a corpus straight from memory; both give identical
prepared records (tested).
"""

from __future__ import annotations

import csv
import io
import json
import os
from pathlib import Path
from typing import Any

import numpy as np

from jaxtalk.data.sources.clip import ClipEntry, RawClip
from jaxtalk.data.sources.generic import METADATA_FILE, TOKENIZER_FILE, TOKENS_FILE
from jaxtalk.files import atomic_output, atomic_save_npy, atomic_savez, atomic_write_text
from jaxtalk.types import AUDIO_SAMPLE_RATE, MOTION_FPS

__all__ = ["clip_name", "synthtalk_entries", "export_generic", "export_dualtalk"]

BASE_STREAM = "A"


def clip_name(index: int) -> str:
    """The file stem of SynthTalk clip ``index``."""
    return f"clip{index:05d}"


def _speaker(corpus: Any, i: int) -> str:
    return f"spk{corpus.clips[i].speaker:03d}"


def _raw(corpus: Any, i: int) -> RawClip:
    tokens = corpus.tokens(i, BASE_STREAM)
    return RawClip(fps=float(MOTION_FPS), params=np.asarray(corpus.motion(i), np.float32),
                   audio=np.asarray(corpus.audio(i), np.float32),
                   tokens=np.asarray(tokens.embeddings, np.float32), token_rate=float(tokens.rate),
                   oracle=np.asarray(corpus.oracle(i), np.float32))


def synthtalk_entries(corpus: Any) -> list[ClipEntry]:
    """Every clip of ``corpus`` as an in-memory entry (splits, emotions and partners from the corpus)."""
    entries = []
    for info in corpus.clips:
        i = info.index
        entries.append(ClipEntry(
            name=clip_name(i), speaker=_speaker(corpus, i), files=(), read=lambda i=i: _raw(corpus, i),
            split=info.split, emotion=info.emotion, intensity=float(info.intensity),
            partner=clip_name(info.partner) if info.partner >= 0 else None,
            requires_partner=info.partner >= 0, fingerprint=f"synthtalk:{corpus.key}:{i}",
        ))
    return entries


def generic_export_names(corpus: Any) -> list[str]:
    """The file names :func:`export_generic` writes for ``corpus`` (to check them before writing)."""
    per_clip = [f"{clip_name(info.index)}{suffix}" for info in corpus.clips for suffix in (".wav", ".npz", ".tokens.npy")]
    return [*per_clip, TOKENS_FILE, TOKENIZER_FILE, METADATA_FILE]


def export_generic(corpus: Any, out: str | os.PathLike, *, progress: bool = False) -> Path:
    """Write ``corpus`` to ``out`` in the generic layout (see the module docstring).

    Every file is written to a temporary name and renamed, so an interrupted export leaves only
    whole files; an existing file of the same name is replaced.

    Returns:
        The folder.
    """
    from tqdm.auto import tqdm

    from jaxtalk.audio.io import save_audio

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for entry in tqdm(synthtalk_entries(corpus), desc="export", unit="clip", disable=not progress):
        raw = entry.read()
        stem = out / entry.name
        with atomic_output(stem.with_suffix(".wav")) as tmp:
            save_audio(tmp, raw.audio, AUDIO_SAMPLE_RATE, subtype="FLOAT")
        atomic_savez(stem.with_suffix(".npz"), params56=raw.params, oracle=raw.oracle, fps=np.float64(raw.fps))
        atomic_save_npy(out / f"{entry.name}.tokens.npy", raw.tokens)
        rows.append({"clip": entry.name, "speaker": entry.speaker, "emotion": entry.emotion,
                     "intensity": f"{entry.intensity:g}", "split": entry.split, "partner": entry.partner or ""})
    atomic_write_text(out / TOKENS_FILE, json.dumps({"rate": float(corpus.tokens(0, BASE_STREAM).rate)}))
    corpus.tokenizer(BASE_STREAM).save(out / TOKENIZER_FILE)
    table = io.StringIO()
    writer = csv.DictWriter(table, fieldnames=["clip", "speaker", "emotion", "intensity", "split", "partner"])
    writer.writeheader()
    writer.writerows(rows)
    atomic_write_text(out / METADATA_FILE, table.getvalue())
    return out


def export_dualtalk(corpus: Any, out: str | os.PathLike, *, progress: bool = False) -> Path:
    """Write ``corpus``'s conversations in the DualTalk release layout (``train/``, ``val/``, ``test/``,
    ``ood/``; ``<conv>_speaker1/2.npz`` with FLAME-style ``exp``/``pose`` and a float32 ``.wav`` each).

    Monologues have no place in that layout and are left out. ``pose`` is ``neck | jaw`` as DualTalk
    stores it, so reading the folder back gives the corpus's 56-d motion exactly.

    Returns:
        The folder.
    """
    from tqdm.auto import tqdm

    from jaxtalk.audio.io import save_audio

    out = Path(out)
    for a, b in tqdm(corpus.conversations(), desc="export", unit="conversation", disable=not progress):
        split = corpus.clips[a].split
        folder = out / split
        folder.mkdir(parents=True, exist_ok=True)
        for side, clip in (("1", a), ("2", b)):
            stem = folder / f"{clip_name(a)}_conv_speaker{side}"
            motion = np.asarray(corpus.motion(clip), np.float32)
            with atomic_output(stem.with_suffix(".wav")) as tmp:
                save_audio(tmp, np.asarray(corpus.audio(clip), np.float32), AUDIO_SAMPLE_RATE, subtype="FLOAT")
            atomic_savez(stem.with_suffix(".npz"), exp=motion[:, :50],
                         pose=np.concatenate([motion[:, 53:56], motion[:, 50:53]], axis=1))
    return out
