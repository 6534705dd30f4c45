"""The VOCASET layout used by FaceFormer and CodeTalker::

    root/vertices_npy/<subject>_<sentence>.npy   (T, V*3) or (T, V, 3) vertices at 60 fps
    root/wav/<subject>_<sentence>.wav
    root/templates.pkl (or templates.npz)        {subject: (V, 3)}

The subject is the stem up to the last ``_``. VOCASET has no head parameters: its clips carry
vertices (resampled to 25 fps when prepared) and train the vertex-level models.
"""

from __future__ import annotations

from pathlib import Path

from jaxtalk.data.sources.clip import ClipEntry, RawClip

__all__ = ["is_vocaset", "vocaset_entries"]


def is_vocaset(root: Path) -> bool:
    """A folder with ``vertices_npy/`` and ``wav/``."""
    return (root / "vertices_npy").is_dir() and (root / "wav").is_dir()


def _templates_file(root: Path) -> Path | None:
    for name in ("templates.npz", "templates.pkl"):
        if (root / name).is_file():
            return root / name
    return None


def _read(npy: Path, wav: Path, templates: Path | None) -> RawClip:
    from jaxtalk.data.formats import VOCASET_FPS, read_vocaset, read_vocaset_templates

    table = read_vocaset_templates(templates) if templates is not None else None
    clip = read_vocaset(npy, templates=table, wav_path=wav, target_fps=None, load_audio=True, require_audio=True)
    return RawClip(fps=float(VOCASET_FPS), vertices=clip.vertices, template=clip.template, audio=clip.audio)


def vocaset_entries(root: Path) -> list[ClipEntry]:
    """One entry per vertex sequence, speaker = subject (no layout splits: they are drawn by speaker)."""
    templates = _templates_file(root)
    entries = []
    for npy in sorted((root / "vertices_npy").glob("*.npy")):
        subject = npy.stem.rsplit("_", 1)[0]
        wav = root / "wav" / f"{npy.stem}.wav"
        files = (npy, wav) + ((templates,) if templates is not None else ())
        entries.append(ClipEntry(name=npy.stem, speaker=subject, files=files,
                                 read=lambda npy=npy, wav=wav: _read(npy, wav, templates)))
    return entries
