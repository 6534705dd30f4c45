"""TIMAR's evaluation protocol (``jaxtalk eval`` on a TIMAR run; :attr:`jaxtalk.runs.ModelSpec.evaluate`):
every conversation side streamed turn by turn, as users run it, and scored as every turn model is
(:func:`jaxtalk.models.turns.training.evaluate_sides`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from jaxtalk.metrics.evaluation import EvalSettings, EvalTable
from jaxtalk.models.timar.streaming import stream
from jaxtalk.models.turns.training import evaluate_sides

__all__ = ["evaluate"]


def evaluate(run: Any, data: Any, split: str, opts: EvalSettings, echo: Callable[[str], None]
             ) -> tuple[int, list[EvalTable]]:
    """TIMAR on a split of prepared data: each side streamed (:func:`jaxtalk.models.timar.stream`) with the
    run's context and ``opts.temperature`` (None: MAR's 1).

    Raises:
        ValueError: a split without a conversation side of a whole turn.
    """
    def predict(streams, key, context):
        return stream(run.params, run.config, *streams, key, context=context, temperature=opts.temperature)

    return evaluate_sides(run, data, split, opts, echo, predict=predict, title="TIMAR", label="timar (streamed)",
                          verb="streaming")
