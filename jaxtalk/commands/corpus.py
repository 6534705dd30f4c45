"""``jaxtalk data``: generate (or load from the cache) the built-in SynthTalk corpus, summarise its splits,
and optionally write its metadata and the corpus itself as a dataset folder in the generic layout."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

__all__ = ["CorpusOptions", "CorpusReport", "make_corpus"]


@dataclasses.dataclass(frozen=True)
class CorpusOptions:
    """Settings of :func:`make_corpus`.

    Attributes:
        size: the corpus size (``tiny``, ``small``, ``full``, ``tiny+espeak``, ...).
        seed: the corpus seed (same seed, byte-identical corpus).
        cache_dir: where the corpus and its fitted tokenizers are cached.
        tokens: also fit the token streams A and B.
        metadata: write the corpus metadata (clips, speakers) as JSON here (None: not written).
        out: also write the corpus as a dataset folder in the generic layout (None: not written).
        overwrite: let the export replace files of its own in ``out``.
    """

    size: str = "tiny"
    seed: int = 0
    cache_dir: Path = Path(".cache/synthtalk")
    tokens: bool = True
    metadata: Path | None = None
    out: Path | None = None
    overwrite: bool = False


@dataclasses.dataclass(frozen=True)
class CorpusReport:
    """What :func:`make_corpus` made: one row per split (clips, speakers, minutes, conversational clips),
    the table's title and the seconds it took."""

    rows: list[dict[str, Any]]
    title: str
    seconds: float


def make_corpus(opts: CorpusOptions, *, echo: Callable[[str], None] = print) -> CorpusReport:
    """Generate or load the corpus, print its splits' table, and write what ``opts`` asks for.

    Raises:
        ValueError: an unknown size, or an output that would replace a file (see
            :func:`jaxtalk.files.claim_outputs`).
    """
    from jaxtalk.data import synthtalk
    from jaxtalk.files import Output, atomic_write_json, claim_outputs

    if opts.metadata is not None:
        claim_outputs([Output(opts.metadata, named=True)])
    start = time.perf_counter()
    corpus = synthtalk.generate(size=opts.size, seed=opts.seed, cache_dir=opts.cache_dir)
    if opts.out is not None:
        from jaxtalk.data.sources import generic_export_names

        # Every file name of the export is the command's own choice inside the named folder.
        claim_outputs([Output(opts.out / name) for name in generic_export_names(corpus)], overwrite=opts.overwrite)
    if opts.tokens:
        for stream in synthtalk.TOKEN_STREAMS:
            corpus.tokenizer(stream)
    seconds = time.perf_counter() - start
    rows = []
    for split in synthtalk.SPLITS:
        idx = corpus.split(split)
        rows.append({
            "split": split,
            "clips": len(idx),
            "speakers": len({corpus.clips[i].speaker for i in idx}),
            "minutes": round(sum(corpus.clips[i].seconds for i in idx) / 60.0, 2),
            "conversational": sum(corpus.clips[i].is_conversation for i in idx),
        })
    from jaxtalk.benchmarking import format_table

    report = CorpusReport(rows, f"SynthTalk {opts.size} (seed {opts.seed}) in {opts.cache_dir}", seconds)
    echo(format_table(rows, title=report.title))
    echo(f"ready in {seconds:.1f} s")
    if opts.metadata is not None:
        atomic_write_json(opts.metadata, corpus.metadata())
        echo(f"metadata written to {opts.metadata}")
    if opts.out is not None:
        from jaxtalk.data.sources import export_generic

        export_generic(corpus, opts.out, progress=True)
        echo(f"{len(corpus.clips)} clips written to {opts.out} (generic layout)")
    return report
