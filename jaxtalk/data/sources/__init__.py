"""Dataset sources: a folder of clips (DualTalk, VOCASET or the generic layout) or SynthTalk, listed
as :class:`ClipEntry` s that read into :class:`RawClip` s and pass :func:`check_clip`.

``open_source("path/to/folder")`` detects the layout; ``open_source("synthtalk:small")`` (optionally
``synthtalk:small:SEED``) lists the built-in corpus from memory.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from pathlib import Path
from typing import Any

from jaxtalk.data.sources.clip import MAX_SKEW_SECONDS, BadClip, ClipEntry, RawClip, check_clip
from jaxtalk.data.sources.dualtalk import dualtalk_entries, is_dualtalk, is_flat_dualtalk
from jaxtalk.data.sources.generic import TOKENIZER_FILE, generic_entries, is_generic
from jaxtalk.data.sources.synthtalk import export_dualtalk, export_generic, generic_export_names, synthtalk_entries
from jaxtalk.data.sources.vocaset import is_vocaset, vocaset_entries

__all__ = [
    "LAYOUTS",
    "Source",
    "open_source",
    "layout_hint",
    "BadClip",
    "ClipEntry",
    "RawClip",
    "check_clip",
    "export_generic",
    "generic_export_names",
    "export_dualtalk",
    "synthtalk_entries",
    "synthtalk_source",
    "MAX_SKEW_SECONDS",
]

LAYOUTS = ("dualtalk", "vocaset", "generic", "synthtalk")


@dataclasses.dataclass(frozen=True)
class Source:
    """A listed dataset.

    Attributes:
        spec: what the user named (a folder path or ``synthtalk:SIZE[:SEED]``).
        layout: one of :data:`LAYOUTS`.
        entries: every clip, in a deterministic order.
        tokenizer: ``() -> VQTokenizer`` of the clips' own token files, when the source has it (so
            that new audio can be turned into the same tokens), else None.
    """

    spec: str
    layout: str
    entries: tuple[ClipEntry, ...]
    tokenizer: Callable[[], Any] | None = None


def _synthtalk(spec: str, cache_dir: str | Path | None) -> Source:
    from jaxtalk.data import synthtalk

    parts = spec.split(":")
    if len(parts) not in (2, 3) or not parts[1]:
        raise ValueError(f"expected synthtalk:SIZE or synthtalk:SIZE:SEED, got {spec!r}")
    seed = 0
    if len(parts) == 3:
        try:
            seed = int(parts[2])
        except ValueError:
            raise ValueError(f"{spec!r}: the seed must be an integer, got {parts[2]!r}") from None
    return synthtalk_source(synthtalk.generate(parts[1], seed=seed, cache_dir=cache_dir))


def synthtalk_source(corpus: Any, spec: str | None = None) -> Source:
    """A generated SynthTalk corpus as a :class:`Source` (its clips from memory, its base token stream's
    tokenizer), ready for :func:`jaxtalk.data.prepare.prepare`: also a custom-size control corpus, which
    ``synthtalk:SIZE`` cannot name.

    Args:
        corpus: a :class:`~jaxtalk.data.synthtalk.SynthTalkCorpus`.
        spec: what the prepared manifest records as the source (default ``synthtalk:SIZE:SEED``; a
            control corpus may say what it changed, e.g. ``synthtalk:full:0 effects=...``).
    """
    return Source(spec=spec or f"synthtalk:{corpus.size}:{corpus.seed}", layout="synthtalk",
                  entries=tuple(synthtalk_entries(corpus)), tokenizer=lambda: corpus.tokenizer("A"))


def layout_hint(spec: str | Path) -> str | None:
    """What to change when a folder's clips were all rejected and the folder looks like a known
    layout laid out differently (None: nothing recognisable)."""
    root = Path(spec)
    if root.is_dir() and is_flat_dualtalk(root):
        return (f"{str(root)!r} holds DualTalk files (*_speaker1.wav, *_speaker2.npz...) without split folders: put "
                "them under train/ and test/ in it, as DualTalk's release does, and run jaxtalk prepare again")
    return None


def open_source(spec: str | Path, *, layout: str | None = None, cache_dir: str | Path | None = None) -> Source:
    """List a dataset's clips without reading them.

    Args:
        spec: a folder, or ``synthtalk:SIZE[:SEED]`` for the built-in corpus.
        layout: force a layout (default: detected: DualTalk split folders, VOCASET's
            ``vertices_npy``/``wav``, else the generic layout).
        cache_dir: SynthTalk's generation cache.

    Returns:
        :class:`Source`.

    Raises:
        FileNotFoundError: the folder does not exist.
        ValueError: an unknown layout, a folder with no recognisable clips, or duplicate clip names.
    """
    text = str(spec)
    if text.startswith("synthtalk:") or layout == "synthtalk":
        return _synthtalk(text if text.startswith("synthtalk:") else f"synthtalk:{text}", cache_dir)
    root = Path(spec)
    if not root.is_dir():
        raise FileNotFoundError(f"dataset folder not found: {str(root)!r}")
    if layout is not None and layout not in LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}; expected one of {', '.join(LAYOUTS)}")
    if layout is None:
        layout = ("dualtalk" if is_dualtalk(root) else "vocaset" if is_vocaset(root)
                  else "generic" if is_generic(root) else None)
        if layout is None:
            raise ValueError(
                f"{str(root)!r} holds no clips in a known layout: expected DualTalk split folders "
                "(train/, test/, ood/ with *_speaker1.wav), VOCASET (vertices_npy/ + wav/) or generic "
                "<clip>.npz + <clip>.wav files"
            )
    lister = {"dualtalk": dualtalk_entries, "vocaset": vocaset_entries, "generic": generic_entries}[layout]
    entries = lister(root)
    if not entries:
        raise ValueError(f"{str(root)!r} has no clips in the {layout} layout")
    seen: set[str] = set()
    for e in entries:
        if e.name in seen:
            raise ValueError(f"{str(root)!r}: two clips are named {e.name!r} (clip names must be unique)")
        seen.add(e.name)
    tokenizer = None
    if layout == "generic" and (root / TOKENIZER_FILE).is_file():
        from jaxtalk.audio import VQTokenizer

        tokenizer = functools.partial(VQTokenizer.load, root / TOKENIZER_FILE)
    return Source(spec=str(root.absolute()), layout=layout, entries=tuple(entries), tokenizer=tokenizer)
