"""``jaxtalk convert timar``: a checkpoint of the public TIMAR code -> a jaxtalk run folder.

The checkpoint (``torch.save`` of ``model``, ``model_ema`` and ``args``, e.g. the released
``TIMAR.pth``) is read with torch, an optional extra (``pip install "jaxtalk[torch]"``), converted
by :mod:`jaxtalk.models.timar.convert` and written as a run that ``jaxtalk sample``, ``stream`` and
``eval`` open like a trained one. Every input is checked before anything is written.
"""

from __future__ import annotations

import dataclasses
import warnings
from pathlib import Path

__all__ = ["ConvertOptions", "ConvertReport", "convert_timar_run"]


@dataclasses.dataclass(frozen=True)
class ConvertOptions:
    """Settings of :func:`convert_timar_run`.

    Attributes:
        checkpoint: the public code's ``.pth``.
        out: the run folder to write.
        features: the speech front end, as ``jaxtalk prepare --features`` takes it (``wav2vec2:PATH``).
        stats: the public code's ``stat_flame.json`` (the motion normaliser), or None.
        ema: convert the EMA weights (default) rather than the raw ones.
        overwrite: replace an existing run folder.
    """

    checkpoint: Path
    out: Path
    features: str
    stats: Path | None = None
    ema: bool = True
    overwrite: bool = False


@dataclasses.dataclass(frozen=True)
class ConvertReport:
    """What was converted.

    Attributes:
        lines: the summary lines to print.
        warnings: warnings raised while converting (e.g. an identity normaliser).
    """

    lines: tuple[str, ...]
    warnings: tuple[str, ...]


def convert_timar_run(opts: ConvertOptions) -> ConvertReport:
    """Convert ``opts.checkpoint`` into a run folder at ``opts.out``.

    Returns:
        :class:`ConvertReport`.

    Raises:
        FileNotFoundError: a missing checkpoint, statistics file or feature folder.
        ValueError: torch missing, a bad checkpoint (naming the key), a bad statistics file, or an
            existing ``out`` without ``overwrite``.
    """
    from jaxtalk.models.timar.convert import convert_checkpoint

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = convert_checkpoint(opts.checkpoint, opts.out, features=opts.features, stats=opts.stats, ema=opts.ema,
                                    overwrite=opts.overwrite)
    c = result.config
    kind = "encoder-only" if c.architecture == "encoder" else f"encoder-decoder ({c.decoder_layers} decoder blocks)"
    lines = (
        f"converted {opts.checkpoint} ({result.weights} weights, {result.num_params / 1e6:.1f} M parameters)",
        (f"  TIMAR {kind}: {c.num_layers} blocks x {c.width} wide, {c.num_heads} heads, "
         f"{c.attention.replace('_', '-')} attention, head {c.head_blocks} x {c.head_width}, speech {c.speech_dim}-d"),
        f"  motion normaliser: {result.normalizer}; sampling: {c.sample_steps} ancestral steps, guidance weight {c.cfg_scale:g}"
         f"{' (none)' if c.cfg_scale == 0 else ''}",
        f"written {result.run_dir}",
    )
    return ConvertReport(lines=lines, warnings=tuple(str(w.message) for w in caught))
