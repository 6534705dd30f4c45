"""The DualTalk baseline's evaluation protocol (``jaxtalk eval`` on a ``dualtalk`` run;
:attr:`jaxtalk.runs.ModelSpec.evaluate`): the same sides, normaliser, context and tables as TIMAR's
(:func:`jaxtalk.models.turns.training.evaluate_sides`), each turn predicted from the window of its past turns and
the whole current turn."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from jaxtalk.metrics.evaluation import EvalSettings, EvalTable
from jaxtalk.models.dualtalk.predict import predict_turns
from jaxtalk.models.turns.training import evaluate_sides

__all__ = ["evaluate"]


def evaluate(run: Any, data: Any, split: str, opts: EvalSettings, echo: Callable[[str], None]
             ) -> tuple[int, list[EvalTable]]:
    """The DualTalk baseline on a split of prepared data (:func:`jaxtalk.models.dualtalk.predict_turns`;
    deterministic: the key is unused).

    Raises:
        ValueError: a split without a conversation side of a whole turn.
    """
    def predict(streams, key, context):
        return predict_turns(run.params, run.config, *streams, context=context)

    return evaluate_sides(run, data, split, opts, echo, predict=predict, title="DualTalk baseline",
                          label="dualtalk (turn windows)", verb="predicting")
