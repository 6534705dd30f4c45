"""Every number a page cites from a result file is in that file (:mod:`cited_numbers` gives the syntax),
and the checker sees a wrong number, a wrong key and a missing file."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from cited_numbers import check_page, figures

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "experiments" / "README.md"]


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_every_cited_number_is_in_its_result_file(page: Path):
    problems = check_page(page, ROOT)
    assert not problems, "\n".join(problems)


def test_the_docs_cite_result_files():
    cited = sum(page.read_text().count("<!-- from:") for page in PAGES)
    assert cited >= 137, f"only {cited} citations in the docs"


@pytest.fixture()
def results(tmp_path: Path) -> Path:
    (tmp_path / "r").mkdir()
    (tmp_path / "r" / "run.json").write_text(json.dumps(
        {"jaw": {"r": 0.98961, "lag": 0}, "rows": [{"LVE": 137.04}, {"LVE": 116.62}], "share": 0.4012,
         "note": "measured 4.68 s", "update_ms": 3423.2}))
    return tmp_path


def _page(root: Path, text: str) -> Path:
    page = root / "page.md"
    page.write_text(text)
    return page


@pytest.mark.parametrize("text", [
    "jawOpen r = 0.990<!-- from: r/run.json#/jaw/r -->.",
    "LVE 116.6<!-- from: r/run.json#/rows/1/LVE -->, lag 0<!-- from: r/run.json#/jaw/lag -->",
    "from 137.0 to 116.6 mm, a 40% share, 4.68 s<!-- from: r/run.json -->",
    "<!-- from: r -->\n| method | LVE |\n|---|---|\n| 2 steps | 137.0 |\n| 10 steps | 116.6 |\n",
    "<!-- from: r; columns 3 -->\n| method | 20 clips | LVE |\n|---|---|---|\n| 2 steps | 20 | 137.0 |\n",
    "a citation quoted as code, `<!-- from: r/missing.json -->`, is an example",
    "`137.5` in code and [a link](x/2.5.md) and wav2vec2 are not figures: 116.6<!-- from: r/run.json -->",
    "<!-- from: r; columns 2, 4 -->\n| method | LVE | clips | share |\n|---|---|---|---|\n| 2 steps | 137.0 | 20 | 40% |\n",
    "the update takes 3,423 ms<!-- from: r/run.json#/update_ms -->, or 3.4 s<!-- from: r/run.json#/update_ms -->",
])
def test_citations_that_hold_pass(results: Path, text: str):
    assert check_page(_page(results, text), results) == []


@pytest.mark.parametrize("text, problem", [
    ("jawOpen r = 0.991<!-- from: r/run.json#/jaw/r -->", "0.991 is not /jaw/r"),
    ("LVE 116.6<!-- from: r/run.json#/rows/0/LVE -->", "116.6 is not /rows/0/LVE"),
    ("r = 0.990<!-- from: r/run.json#/jaw/rho -->", "no key 'rho'"),
    ("from 137.0 to 117.6 mm<!-- from: r/run.json -->", "117.6 is in no value"),
    ("<!-- from: r -->\n| method | LVE |\n|---|---|\n| 2 steps | 137.0 |\n| 10 steps | 116.7 |\n", "116.7 is in no value"),
    ("<!-- from: r; columns 2-3 -->\n| method | 20 clips | LVE |\n|---|---|---|\n| 2 steps | 20 | 137.0 |\n",
     "20 is in no value"),
    ("<!-- from: r; columns 2, 4 -->\n| method | LVE | clips | share |\n|---|---|---|---|\n| 2 steps | 137.0 | 20 | 41% |\n",
     "41 is in no value"),
    ("the update takes 3.5 s<!-- from: r/run.json#/update_ms -->", "3.5 is not /update_ms"),
    ("0.990<!-- from: r/missing.json#/jaw/r -->", "r/missing.json: no such result file"),
    ("-0.40<!-- from: r/run.json#/share -->", "-0.40 is not /share"),
])
def test_a_wrong_number_a_wrong_key_or_a_missing_file_is_reported(results: Path, text: str, problem: str):
    problems = check_page(_page(results, text), results)
    assert len(problems) == 1 and problem in problems[0], problems


def test_printed_precision_and_ranges_are_read_as_written():
    got = [(f.value, f.tolerance) for f in figures("53-98 ms, -0.12, 1,000 steps, 2.4x, v2 wav2vec2")]
    assert [v for v, _ in got] == [53.0, 98.0, -0.12, 1000.0, 2.4]
    assert got[2][1] == pytest.approx(0.005)
