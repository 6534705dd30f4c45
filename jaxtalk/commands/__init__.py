"""The logic behind each ``jaxtalk`` command; :mod:`jaxtalk.cli` is only the typer layer over it.

* :mod:`~jaxtalk.commands.runs`: model registry, ``--set key=value`` overrides, the ``run.json``
  record of a training run, and loading a run's trained parameters from its checkpoint.
* :mod:`~jaxtalk.commands.training`: ``jaxtalk train {toktalk,ats,stm,timar}``.
* :mod:`~jaxtalk.commands.inference`: ``jaxtalk sample`` and ``jaxtalk stream``.
* :mod:`~jaxtalk.commands.evaluation`: ``jaxtalk eval``.
* :mod:`~jaxtalk.commands.rendering`: ``jaxtalk render``.

Every module imports JAX and the models lazily, so ``jaxtalk --help`` stays instant.
"""
