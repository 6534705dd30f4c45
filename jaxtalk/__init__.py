"""jaxtalk: speech-driven 3D face animation in JAX.

Three systems as pure functions with jitted samplers:

* **TokTalk** (``jaxtalk.models.toktalk``): audio-LLM token embeddings -> FLAME parameters with a
  chunk-wise conditional flow-matching decoder and a streaming engine.
* **FreeTalk** (``jaxtalk.models.freetalk``): audio + emotion -> 68 landmark displacements (ATS),
  then DiffusionNet Sparse-To-Mesh on any face topology (STM).
* **TIMAR** (``jaxtalk.models.timar``): dyadic conversation -> the agent's head motion, turn by turn.

Importing ``jaxtalk`` is cheap: subpackages are imported on first attribute access.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_SUBMODULES = (
    "masks",
    "types",
    "nn",
    "samplers",
    "train",
    "audio",
    "face",
    "geometry",
    "data",
    "metrics",
    "models",
    "render",
    "fit",
    "runs",
)

__all__ = ["__version__", *_SUBMODULES]


def __getattr__(name: str) -> Any:
    # Lazy subpackage import keeps `import jaxtalk` (and the CLI's --help) fast.
    if name in _SUBMODULES:
        return importlib.import_module(f"jaxtalk.{name}")
    raise AttributeError(f"module 'jaxtalk' has no attribute {name!r}")
