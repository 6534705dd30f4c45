"""Numbers in the documentation and the committed result files they come from.

A page cites its source with an HTML comment (invisible once rendered):

* ``0.990<!-- from: experiments/results/retarget/public_rig.json#/jaw_open/r -->``: a keyed citation.
  The number right before the comment equals the value at that JSON path at the precision printed:
  ``/``-separated keys (spaces allowed; ``~1`` stands for a ``/`` inside a key, ``~0`` for ``~``, as in
  a JSON pointer), list indices as integers.
* ``... 180/180 aligned, 7.6 mm<!-- from: experiments/results/alignment/any_pose.json -->``: an inline
  citation without a key. Every number on the line before the comment (after any earlier comment of
  the line) is a value of the file at the precision printed.
* A comment alone on its line cites the block that follows it (the lines up to the next blank line):
  every number of the block is a value of the file, except a table's header row and its first column
  (the labels of the rows). ``<!-- from: FILE; columns 4-5 -->`` checks only those columns (1-based) of
  the table, where other columns hold settings rather than results; ``columns 3, 5-6`` skips column 4
  (a column derived from the others, which no file holds).

Several files may be named, separated by commas; a folder names every result file under it. A printed
number (``282k`` and ``225M`` read as thousands and millions) matches a value ``v`` when ``v``,
``100 v`` (a percentage), ``1000 v`` (a file in base units, the page in milli-units: seconds printed
as ms) or ``v / 1000`` (a file in milli-units, the page in base units: ms printed as seconds) rounds to
it. Numbers inside code spans, fenced blocks, link targets and words (``wav2vec2``, ``v1``) are not
figures and are not checked.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from collections.abc import Iterator
from pathlib import Path

MARKER = re.compile(r"<!--\s*from:\s*(?P<files>[^#;>]+?)\s*(?:#(?P<key>[^;>]*?))?\s*"
                    r"(?:;\s*columns\s+(?P<columns>\d+(?:-\d+)?(?:\s*,\s*\d+(?:-\d+)?)*)\s*)?-->")
NUMBER = re.compile(r"(?<![\w.^])(?P<int>\d{1,3}(?:,\d{3})+(?!\d)|\d+)(?P<frac>\.\d+)?(?:e(?P<exp>[-+\u2212]?\d+))?"
                    r"(?P<suffix>[kM](?!\w))?(?![\w.]\w)")
# A minus sign: a hyphen or U+2212 right before the digits, not after a word or number (``53-98`` is a range).
MINUS = re.compile(r"(?<![\w.)])[-\u2212]$")
FENCE = re.compile(r"^(```|~~~).*?^\1[^\n]*$", flags=re.S | re.M)
INLINE_CODE = re.compile(r"`[^`\n]*`")
LINK_TARGET = re.compile(r"\]\([^)]*\)")
RESULT_SUFFIXES = (".json", ".jsonl", ".csv", ".txt", ".md")
# The scales a value may be printed at: as is, as a percentage, in milli-units, from milli-units.
SCALES = (1.0, 100.0, 1000.0, 0.001)


@dataclasses.dataclass(frozen=True)
class Figure:
    """A number as a page prints it: its value and the half-width of its last printed digit."""

    text: str
    value: float
    tolerance: float

    def matches(self, value: float) -> bool:
        return any(abs(value * s - self.value) <= self.tolerance for s in SCALES)


def figures(text: str) -> list[Figure]:
    """The numbers of ``text`` (prose: code spans and link targets already removed by the caller)."""
    out = []
    for m in NUMBER.finditer(text):
        digits = m.group("int").replace(",", "")
        frac = m.group("frac") or ""
        exp = int((m.group("exp") or "0").replace("\u2212", "-")) + {"k": 3, "M": 6}.get(m.group("suffix") or "", 0)
        value = float(digits + frac) * 10.0 ** exp
        if MINUS.search(text[max(m.start() - 2, 0):m.start()]):
            value = -value
        decimals = len(frac) - 1 if frac else 0
        # Half a unit of the last digit printed, with room for the float error of the scaled value.
        tolerance = 0.5 * 10.0 ** (exp - decimals) * (1 + 1e-9) + 1e-12
        out.append(Figure(("-" if value < 0 else "") + m.group(0), value, tolerance))
    return out


def _walk(value: object) -> Iterator[float]:
    if isinstance(value, bool):
        return
    if isinstance(value, (int, float)):
        if math.isfinite(value):
            yield float(value)
    elif isinstance(value, dict):
        for item in value.values():
            yield from _walk(item)
    elif isinstance(value, (list, tuple)):
        for item in value:
            yield from _walk(item)
    elif isinstance(value, str):
        yield from (f.value for f in figures(value))


def _files(root: Path, names: str) -> list[Path]:
    paths = []
    for name in (n.strip() for n in names.split(",")):
        path = root / name
        if not path.exists():
            raise FileNotFoundError(f"{name}: no such result file")
        paths += sorted(p for p in path.rglob("*") if p.suffix in RESULT_SUFFIXES) if path.is_dir() else [path]
    return paths


def _load(path: Path) -> object:
    text = path.read_text()
    if path.suffix == ".json":
        return json.loads(text)
    if path.suffix == ".jsonl":
        return [json.loads(line) for line in text.splitlines() if line.strip()]
    return text


def file_values(paths: list[Path]) -> list[float]:
    """Every number the files hold (JSON values, and numbers written in their strings or text)."""
    return [v for p in paths for v in _walk(_load(p))]


def lookup(data: object, key: str) -> object:
    """The value at a ``/``-separated key path of parsed JSON."""
    for part in (p.replace("~1", "/").replace("~0", "~") for p in key.split("/") if p):
        if isinstance(data, list):
            data = data[int(part)]
        elif isinstance(data, dict) and part in data:
            data = data[part]
        else:
            raise KeyError(f"no key {part!r} on the path {key!r}")
    return data


def _prose(line: str) -> str:
    return LINK_TARGET.sub("]", INLINE_CODE.sub(" ", line))


def _table_cells(line: str) -> list[str]:
    return [c for c in line.strip().strip("|").split("|")]


def _columns(spec: str | None) -> list[tuple[int, int]]:
    """The 1-based, inclusive column ranges of a ``columns`` spec (``4``, ``4-5``, ``3, 5-6``); all but the
    first column (the row labels) when there is none."""
    if spec is None:
        return [(2, 10**6)]
    ranges = []
    for part in spec.split(","):
        first, _, last = part.strip().partition("-")
        ranges.append((int(first), int(last or first)))
    return ranges


def check_page(page: Path, root: Path) -> list[str]:
    """The citations of ``page`` that do not hold, one line each (empty when all hold)."""
    problems: list[str] = []
    text = FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), page.read_text())
    lines = text.splitlines()
    for n, line in enumerate(lines):
        start = 0
        # A marker quoted in a code span is an example, not a citation (same length: positions hold).
        for marker in MARKER.finditer(INLINE_CODE.sub(lambda m: " " * len(m.group(0)), line)):
            where = f"{page.name}:{n + 1}"
            try:
                paths = _files(root, marker.group("files"))
            except FileNotFoundError as e:
                problems.append(f"{where}: {e}")
                start = marker.end()
                continue
            key = marker.group("key")
            alone = not line[:marker.start()].strip() and not line[marker.end():].strip()
            if key is not None:
                before = figures(_prose(MARKER.sub(" ", line[start:marker.start()])))
                if not before:
                    problems.append(f"{where}: no number before the citation of {key}")
                else:
                    try:
                        value = lookup(_load(paths[0]), key)
                    except (KeyError, IndexError, ValueError) as e:
                        problems.append(f"{where}: {marker.group('files')}: {e}")
                    else:
                        values = list(_walk(value))
                        if not any(before[-1].matches(v) for v in values):
                            problems.append(f"{where}: {before[-1].text} is not {key} = {value!r} of "
                                            f"{marker.group('files')}")
            else:
                if alone:
                    block = []
                    for following in lines[n + 1:]:
                        if not following.strip():
                            break
                        block.append(following)
                    if block and block[0].lstrip().startswith("|"):
                        rows = [r for r in block[1:] if not re.fullmatch(r"\s*\|?[\s:|-]+\|?\s*", r)]
                        ranges = _columns(marker.group("columns"))
                        cited = [" ".join(c for first, last in ranges for c in _table_cells(r)[first - 1:last])
                                 for r in rows]
                    else:
                        cited = block
                else:
                    cited = [line[start:marker.start()]]
                values = file_values(paths)
                for piece in cited:
                    for figure in figures(_prose(MARKER.sub(" ", piece))):
                        if not any(figure.matches(v) for v in values):
                            problems.append(f"{where}: {figure.text} is in no value of {marker.group('files')}")
            start = marker.end()
    return problems
