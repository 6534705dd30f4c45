"""The logic behind each ``jaxtalk`` command; :mod:`jaxtalk.cli` is only the typer layer over it.

* :mod:`~jaxtalk.commands.training`: ``jaxtalk train {toktalk,ats,stm,timar}``.
* :mod:`~jaxtalk.commands.inference`: ``jaxtalk sample`` and ``jaxtalk stream``.
* :mod:`~jaxtalk.commands.evaluation`: ``jaxtalk eval``.
* :mod:`~jaxtalk.commands.rendering`: ``jaxtalk render``.

The run folder and the model registry they share are the library's :mod:`jaxtalk.runs`. Every module
imports JAX and the models lazily, so ``jaxtalk --help`` stays instant.
"""
