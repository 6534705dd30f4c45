"""Imports run only downwards (docs/architecture.md, Layers), through ranked layers:

0. core: ``types``, ``layout``, ``checks``, ``files``, ``masks``, ``benchmarking``;
1. building blocks: ``nn``, ``samplers``, ``audio``, ``face``, ``geometry``, ``metrics``, ``render``, ``viewer``;
2. on those: ``export``, ``fit``;
3. ``data``;
4. ``train``: the loop, checkpoints and the recipes' training on windows (it knows no run format);
5. ``runs``: the run folder and the registry; it trains a recipe's windows and records the run, and
   restores a run's checkpoints (both through ``train``);
6. ``models``: no model package imports another; what two models share moves down a layer, or into a
   family package of the models layer (:data:`FAMILIES`) that the models import and that imports no model;
7. applications: ``commands``, ``cli``, ``demo``, ``serve``, ``bench``, and ``testing`` (the tools the
   test suite and the experiments share).

The experiments (``experiments/*.py``) use the package as a user would: they import ``jaxtalk`` and
each other, never the test suite.

A module imports only from its own rank or below; packages of one rank import each other without a
circle (:data:`KNOWN_CIRCLES` names any still to be cut: none). The checker walks the AST of every module,
imports inside functions included and relative imports resolved, so a lazy import cannot hide a
dependency. The registry's spec paths (imported by name, so invisible to the AST) are checked to name
``spec`` modules of the models layer.
"""

from __future__ import annotations

import ast
import itertools
import re
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "jaxtalk"

RANKS: dict[str, int] = {
    **dict.fromkeys(("types", "layout", "checks", "files", "masks", "benchmarking"), 0),
    **dict.fromkeys(("nn", "samplers", "audio", "face", "geometry", "metrics", "render", "viewer"), 1),
    **dict.fromkeys(("export", "fit"), 2),
    "data": 3,
    "train": 4,
    "runs": 5,
    "models": 6,
    **dict.fromkeys(("commands", "cli", "demo", "serve", "bench", "testing"), 7),
}
# Packages of the models layer that hold what a family of models shares (TIMAR and the DualTalk
# baseline's turn windows, training and protocol): models may import them; they import no model.
FAMILIES = frozenset({"turns"})
# The package's own entry points sit above every layer.
TOP = frozenset({"__init__", "__main__"})
# Circles between packages of one rank that are still to be cut (a new one must be cut, not listed).
KNOWN_CIRCLES: frozenset[frozenset[str]] = frozenset()


def _module_name(path: Path, root: Path) -> str:
    parts = path.relative_to(root.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, module: str) -> list[tuple[str, ...]]:
    """Every import in ``path``, anywhere in its body: ``(module,)`` for ``import module``, ``(source,
    source.name)`` for ``from source import name`` (``name`` may be a submodule), relative sources
    resolved against the module's package."""
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out: list[tuple[str, ...]] = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out += [(alias.name,) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                source = ".".join(parts[: len(parts) - (node.level - 1)] + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            out += [(source, f"{source}.{alias.name}") for alias in node.names]
    return out


def _forbidden(importer: str, target: str) -> bool:
    """Whether module ``importer`` may not import ``target`` (both dotted, under ``jaxtalk``)."""
    src, dst = importer.split("."), target.split(".")
    if dst[0] != "jaxtalk" or len(src) < 2 or len(dst) < 2 or src[1] in TOP or dst[1] not in RANKS:
        return False
    if (src[1] == "models" and len(src) > 2 and dst[1] == "models" and len(dst) > 2 and dst[2] != src[2]
            and dst[2] not in FAMILIES):
        # ``jaxtalk.models`` alone is the (empty) namespace package: ``from jaxtalk.models import x``
        # is judged by ``x``.
        return True
    return src[1] in RANKS and RANKS[dst[1]] > RANKS[src[1]]


def package_graph(root: Path) -> dict[str, set[str]]:
    """Top-level package -> the other top-level packages it imports (anywhere in its modules)."""
    graph: dict[str, set[str]] = {}
    for path in sorted(root.rglob("*.py")):
        top = path.relative_to(root).parts[0].removesuffix(".py")
        for candidates in _imports(path, _module_name(path, root)):
            parts = candidates[0].split(".")
            if parts[0] == "jaxtalk" and len(parts) > 1 and parts[1] != top and parts[1] in RANKS:
                graph.setdefault(top, set()).add(parts[1])
    return graph


def circles(graph: dict[str, set[str]]) -> set[frozenset[str]]:
    """The pairs of packages that reach each other (through any path)."""
    reach = {node: set(edges) for node, edges in graph.items()}
    changed = True
    while changed:
        changed = False
        for node, seen in reach.items():
            more = set().union(*(reach.get(n, set()) for n in seen)) - seen
            if more:
                seen |= more
                changed = True
    return {frozenset((a, b)) for a, b in itertools.combinations(sorted(reach), 2)
            if b in reach[a] and a in reach.get(b, set())}


def layer_violations(root: Path) -> list[str]:
    """``"file -> module"`` for every import under ``root`` (a ``jaxtalk`` package folder) that runs
    upwards or sideways between models, and ``"file -> unclassified"`` for a top-level module that
    belongs to no layer (so a new one gets placed)."""
    found = []
    for path in sorted(root.rglob("*.py")):
        module = _module_name(path, root)
        rel = path.relative_to(root.parent).as_posix()
        top = path.relative_to(root).parts[0].removesuffix(".py")
        if top not in set(RANKS) | TOP:
            found.append(f"{rel} -> unclassified")
        for candidates in _imports(path, module):
            # ``from jaxtalk.models.x import Name``: the module is reported, not the name imported from it;
            # ``from jaxtalk import models``: the name is the module.
            bad = next((c for c in candidates if _forbidden(module, c)), None)
            if bad is not None:
                found.append(f"{rel} -> {bad}")
    return sorted(set(found))


def test_jaxtalk_imports_run_only_downwards():
    assert layer_violations(PACKAGE) == []


def test_no_two_packages_import_each_other():
    assert circles(package_graph(PACKAGE)) <= KNOWN_CIRCLES


def test_experiments_import_the_package_not_the_test_suite():
    experiments = PACKAGE.parent / "experiments"
    test_modules = {path.stem for path in (PACKAGE.parent / "tests").glob("*.py")}
    found = []
    for path in sorted(experiments.glob("*.py")):
        text = path.read_text()
        imported = {c[0].split(".")[0] for c in _imports(path, path.stem)}
        found += [f"{path.name} -> tests.{name}" for name in sorted(imported & test_modules) if name != "conftest"
                  and not (experiments / f"{name}.py").exists()]
        if re.search(r"sys\.path\.(insert|append)\(.*tests", text):
            found.append(f"{path.name} -> the tests folder on sys.path")
    assert found == []


def test_circle_finder_sees_a_circle_through_a_third_package():
    assert circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == {
        frozenset("ab"), frozenset("ac"), frozenset("bc")}
    assert circles({"a": {"b"}, "b": {"c"}}) == set()


def test_registry_spec_paths_name_spec_modules_of_the_models_layer():
    from jaxtalk.runs import SPEC_PATHS

    for model, path in SPEC_PATHS.items():
        module, _, attr = path.partition(":")
        parts = module.split(".")
        assert parts[:2] == ["jaxtalk", "models"] and parts[-1] == "spec" and attr, (model, path)
        assert (PACKAGE.parent / Path(*parts)).with_suffix(".py").is_file(), path


def _plant(root: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        path = root / "jaxtalk" / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root / "jaxtalk"


def test_checker_reports_exactly_the_planted_upward_and_sideways_imports(tmp_path):
    package = _plant(tmp_path, {
        "__init__.py": "from jaxtalk import models\n",  # the package root may import anything
        "types.py": "import numpy\n",
        "data/__init__.py": "",
        # upward, hidden inside a function: still found
        "data/features.py": "def f():\n    from jaxtalk.models.toktalk.sampling import sample\n    return sample\n",
        "data/ok.py": "from jaxtalk.types import Float\nfrom . import features\n",
        "train/__init__.py": "import jaxtalk.commands.training\n",  # a foundation importing an application
        "models/__init__.py": "",
        "models/timar/__init__.py": "",
        "models/timar/loss.py": "from ..toktalk import loss\n",  # sideways, relative
        "models/timar/model.py": "from .loss import f\nfrom jaxtalk.data.ok import g\nfrom jaxtalk.models.timar import loss\n",
        "models/toktalk/__init__.py": "",
        "models/toktalk/loss.py": "from jaxtalk import cli\n",  # a model importing an application
        "scratch.py": "",
    })
    assert layer_violations(package) == [
        "jaxtalk/data/features.py -> jaxtalk.models.toktalk.sampling",
        "jaxtalk/models/timar/loss.py -> jaxtalk.models.toktalk",
        "jaxtalk/models/toktalk/loss.py -> jaxtalk.cli",
        "jaxtalk/scratch.py -> unclassified",
        "jaxtalk/train/__init__.py -> jaxtalk.commands.training",
    ]


@pytest.mark.parametrize("importer, target, forbidden", [
    ("jaxtalk.runs", "jaxtalk.models.toktalk", True),
    ("jaxtalk.runs", "jaxtalk.train.recipes", False),
    ("jaxtalk.train.recipes", "jaxtalk.runs", True),
    ("jaxtalk.train.loop", "jaxtalk.runs", True),
    ("jaxtalk.models.timar.recipe", "jaxtalk.runs", False),
    ("jaxtalk.runs", "jaxtalk.commands.training", True),
    ("jaxtalk.fit.inversion", "jaxtalk.models", True),
    ("jaxtalk.models.dualtalk.loss", "jaxtalk.models.timar.loss", True),
    ("jaxtalk.models.dualtalk.recipe", "jaxtalk.models.turns.training", False),
    ("jaxtalk.models.turns.training", "jaxtalk.models.timar.loss", True),
    ("jaxtalk.models.dualtalk.loss", "jaxtalk.models.dualtalk.model", False),
    ("jaxtalk.models.dualtalk.loss", "jaxtalk.metrics.params", False),
    ("jaxtalk.models.toktalk.inversion", "jaxtalk.models", False),
    ("jaxtalk.models.freetalk.fit", "jaxtalk.commands.runs", True),
    ("jaxtalk.commands.training", "jaxtalk.models.timar", False),
    ("jaxtalk.data.prepare", "numpy", False),
    ("jaxtalk.audio.tokenizer", "jaxtalk.data.formats", True),
    ("jaxtalk.geometry.mesh_io", "jaxtalk.export.playback", True),
    ("jaxtalk.export.playback", "jaxtalk.geometry.mesh_io", False),
    ("jaxtalk.data.formats", "jaxtalk.train.loop", True),
    ("jaxtalk.files", "jaxtalk.types", False),
])
def test_forbidden_rule_per_layer(importer, target, forbidden):
    assert _forbidden(importer, target) is forbidden
