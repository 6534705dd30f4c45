"""The generic layout: one flat folder of clips, with optional metadata::

    <clip>.wav                 audio, any rate, mono or stereo
    <clip>.npz                 fps (required) and one motion stream:
                                 params56 (T, 56) [exp 50 | jaw 3 | neck 3], or
                                 exp (T, 50) + pose (T, 6) (DualTalk's neck | jaw), or
                                 vertices (T, V, 3) (+ template (V, 3));
                               optional oracle (T, 56): a known best prediction (SynthTalk)
    <clip>.tokens.npy          optional (Tt, D) audio-LLM token embeddings, rate in tokens.json
    tokens.json                {"rate": 12.5}: the token rate in Hz
    tokenizer.npz              optional: the jaxtalk VQ tokenizer that made the token files (then a
                               trained model turns new audio into the same tokens)
    metadata.csv               optional columns: clip, speaker, emotion, intensity, split, partner

Without ``metadata.csv`` every clip is its own speaker and splits are drawn at random (seeded,
speaker-disjoint). A clip listed in ``metadata.csv`` whose files are missing is reported, not skipped
silently.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from jaxtalk.data.sources.clip import ClipEntry, RawClip

__all__ = ["METADATA_FILE", "TOKENS_FILE", "TOKENIZER_FILE", "is_generic", "generic_entries", "read_metadata"]

METADATA_FILE = "metadata.csv"
TOKENS_FILE = "tokens.json"
TOKENIZER_FILE = "tokenizer.npz"
_COLUMNS = ("clip", "speaker", "emotion", "intensity", "split", "partner")


def _clip_stems(root: Path) -> set[str]:
    """Stems of the clip ``.npz`` files: not ``tokenizer.npz``, nor hidden (temporary) files."""
    return {p.stem for p in root.glob("*.npz") if p.name != TOKENIZER_FILE and not p.name.startswith(".")}


def is_generic(root: Path) -> bool:
    """A folder with ``<clip>.npz`` files (and no DualTalk/VOCASET structure)."""
    return bool(_clip_stems(root)) or (root / METADATA_FILE).is_file()


def read_metadata(root: Path) -> dict[str, dict[str, str]]:
    """``metadata.csv`` as ``{clip: {column: value}}`` (empty cells dropped); {} when absent.

    Raises:
        ValueError: no ``clip`` column, an unknown column, or a clip listed twice.
    """
    path = root / METADATA_FILE
    if not path.is_file():
        return {}
    with open(path, newline="") as handle:
        reader = csv.DictReader(handle)
        fields = reader.fieldnames or []
        if "clip" not in fields:
            raise ValueError(f"{path}: needs a 'clip' column (found {fields})")
        unknown = [f for f in fields if f not in _COLUMNS]
        if unknown:
            raise ValueError(f"{path}: unknown columns {unknown}; known: {', '.join(_COLUMNS)}")
        rows: dict[str, dict[str, str]] = {}
        for line, row in enumerate(reader, start=2):
            name = (row.get("clip") or "").strip()
            if not name:
                raise ValueError(f"{path}:{line}: empty clip name")
            if name in rows:
                raise ValueError(f"{path}:{line}: clip {name!r} is listed twice")
            rows[name] = {k: v.strip() for k, v in row.items() if k != "clip" and v is not None and v.strip()}
    return rows


def _token_rate(root: Path) -> float | None:
    path = root / TOKENS_FILE
    if not path.is_file():
        return None
    try:
        rate = float(json.loads(path.read_text())["rate"])
    except (ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{path}: expected {{\"rate\": <Hz>}} ({err})") from None
    return rate


def _read(npz: Path, wav: Path, tokens: Path | None, token_rate: float | None) -> RawClip:
    from jaxtalk.audio.io import load_audio
    from jaxtalk.data.formats import dualtalk_to_params56
    from jaxtalk.files import load_npy, load_npz

    data = load_npz(npz, what="motion file")
    keys = set(data)
    if "fps" not in keys:
        raise ValueError(f"no 'fps' in the npz (found {sorted(keys)})")
    fps = np.asarray(data["fps"])
    if fps.shape != () or not np.issubdtype(fps.dtype, np.number):
        raise ValueError(f"'fps' must be a numeric scalar, got {fps.dtype} {fps.shape}")
    params = vertices = template = oracle = None
    if "params56" in keys:
        params = np.asarray(data["params56"], np.float32)
    elif {"exp", "pose"} <= keys:
        exp, pose = np.asarray(data["exp"], np.float32), np.asarray(data["pose"], np.float32)
        if exp.ndim != 2 or pose.ndim != 2 or exp.shape[1] != 50 or pose.shape[1] != 6 or len(exp) != len(pose):
            raise ValueError(f"expected exp (T, 50) and pose (T, 6), got {exp.shape} and {pose.shape}")
        params = dualtalk_to_params56(exp, pose)
    elif "vertices" in keys:
        vertices = np.asarray(data["vertices"], np.float32)
        template = np.asarray(data["template"], np.float32) if "template" in keys else None
    else:
        raise ValueError(f"no motion: needs 'params56', 'exp' + 'pose', or 'vertices' (found {sorted(keys)})")
    if "oracle" in keys:
        oracle = np.asarray(data["oracle"], np.float32)
    audio = load_audio(wav, allow_silence=True)
    emb = None
    if tokens is not None:
        if token_rate is None:
            raise ValueError(f"{tokens.name} has no rate: write {TOKENS_FILE} with {{\"rate\": <Hz>}}")
        emb = np.asarray(load_npy(tokens, what="token file"), np.float32)
    return RawClip(fps=float(fps), params=params, vertices=vertices, template=template, audio=audio,
                   tokens=emb, token_rate=token_rate if emb is not None else None, oracle=oracle)


def generic_entries(root: Path) -> list[ClipEntry]:
    """One entry per ``<clip>.npz`` (and per clip named in ``metadata.csv``), sorted by name."""
    meta = read_metadata(root)
    token_rate = _token_rate(root)
    names = sorted(_clip_stems(root) | set(meta))
    entries = []
    for name in names:
        row = meta.get(name, {})
        npz, wav, tok = root / f"{name}.npz", root / f"{name}.wav", root / f"{name}.tokens.npy"
        tokens = tok if tok.is_file() else None
        files = (npz, wav) + ((tok,) if tokens is not None else ())
        intensity = row.get("intensity")
        entries.append(ClipEntry(
            name=name,
            speaker=row.get("speaker", name),
            files=files,
            read=lambda npz=npz, wav=wav, tokens=tokens: _read(npz, wav, tokens, token_rate),
            split=row.get("split"),
            emotion=row.get("emotion"),
            intensity=float(intensity) if intensity is not None else None,
            partner=row.get("partner"),
            requires_partner="partner" in row,
        ))
    return entries
