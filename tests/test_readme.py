"""The README's promises: its two commands are the install + demo and the test command, and its
Python example runs as written."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _blocks(language: str) -> list[str]:
    return re.findall(rf"```{language}\n(.*?)```", README.read_text(), flags=re.S)


def test_readme_opens_with_the_two_commands():
    bash = _blocks("bash")
    assert 'pip install -e ".[test]"' in bash[0] and "jaxtalk demo" in bash[0]
    assert bash[1].strip() == "pytest"


@pytest.mark.slow
def test_python_example_runs(synthtalk_tiny, monkeypatch):
    (example,) = _blocks("python")
    from jaxtalk.data import synthtalk

    # The example generates the tiny corpus itself; reuse the session's copy of the same corpus.
    monkeypatch.setattr(synthtalk, "generate", lambda *args, **kwargs: synthtalk_tiny)
    namespace: dict = {}
    exec(compile(example, str(README), "exec"), namespace)
    motion, vertices = namespace["motion"], namespace["vertices"]
    assert motion.ndim == 3 and motion.shape[0] == 1 and motion.shape[2] == 56
    assert vertices.shape == (motion.shape[1], synthtalk_tiny.face(0).num_vertices, 3)
    assert np.isfinite(np.asarray(vertices)).all()
