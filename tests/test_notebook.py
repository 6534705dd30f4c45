"""``notebooks/quickstart.ipynb`` runs top to bottom (nbclient), so it never rots.

Besides "no cell raised", the checks read the notebook's own printed numbers: the tiny model's loss
went down, and the gradient through the sampler agrees with a finite difference.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

nbformat = pytest.importorskip("nbformat")
nbclient = pytest.importorskip("nbclient")

pytestmark = [pytest.mark.external, pytest.mark.slow]  # a Jupyter kernel running the whole quickstart

NOTEBOOK = Path(__file__).resolve().parents[1] / "notebooks" / "quickstart.ipynb"


def _text(nb) -> str:
    out = []
    for cell in nb.cells:
        for o in cell.get("outputs", []):
            out.append(o.get("text", ""))
            out.append(str(o.get("data", {}).get("text/plain", "")))
    return "\n".join(out)


def test_quickstart_runs_top_to_bottom(tmp_path, monkeypatch, synthtalk_tiny, prepared_tiny):
    nb = nbformat.read(NOTEBOOK, as_version=4)
    assert all(not c.get("outputs") for c in nb.cells if c.cell_type == "code"), "commit the notebook without outputs"
    # The kernel inherits the environment: reuse the session's tiny corpus instead of regenerating it.
    monkeypatch.setenv("JAXTALK_CACHE", str(synthtalk_tiny._cache_dir))
    # ... and its prepared copy, where open_data("synthtalk:tiny:0") finds it (tests/conftest.py).
    monkeypatch.setenv("JAXTALK_PREPARED", str(prepared_tiny.root.parent))
    client = nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                                     resources={"metadata": {"path": str(tmp_path)}})
    client.execute()
    text = _text(nb)
    first, last = map(float, re.search(r"loss ([\d.]+) -> ([\d.]+)", text).groups())
    assert last < first, text
    auto, fd = map(float, re.search(r"autodiff (-?[\d.]+), finite difference (-?[\d.]+)", text).groups())
    assert auto == pytest.approx(fd, rel=0.05, abs=1e-4), text
    assert "frame" in text and any(o.get("output_type") == "display_data" for c in nb.cells for o in c.get("outputs", []))
