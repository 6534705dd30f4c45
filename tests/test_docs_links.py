"""The documentation holds together: the README stays a short manual, every relative link of the README,
the docs pages and the experiments index points at a file of the repository, and the experiments index
names every experiment script."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path
from urllib.parse import unquote

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
EXPERIMENTS_README = ROOT / "experiments" / "README.md"
PAGES = [README, *sorted((ROOT / "docs").glob("*.md")), EXPERIMENTS_README]

LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")  # [text](target) and ![alt](target)
FENCE = re.compile(r"^(```|~~~).*?^\1", flags=re.S | re.M)
INLINE_CODE = re.compile(r"`[^`\n]*`")


def _relative_links(page: Path) -> list[str]:
    """The link targets of ``page`` outside code, less web addresses and pure ``#anchor`` links."""
    text = INLINE_CODE.sub("", FENCE.sub("", page.read_text()))
    targets = [m.group(1) for m in LINK.finditer(text)]
    return [t for t in targets if not re.match(r"^[a-z][a-z0-9+.-]*:", t, flags=re.I) and not t.startswith("#")]


def _ignored_by_git(path: Path) -> bool:
    """Whether git ignores ``path`` and does not track it: a file that a fresh clone would not have."""
    try:
        tracked = subprocess.run(["git", "-C", str(ROOT), "ls-files", "--error-unmatch", str(path)],
                                 capture_output=True, check=False)
        if tracked.returncode == 0:
            return False
        ignored = subprocess.run(["git", "-C", str(ROOT), "check-ignore", "-q", str(path)],
                                 capture_output=True, check=False)
    except OSError:  # no git: existence is all that can be checked
        return False
    return ignored.returncode == 0


def test_readme_has_fewer_than_300_lines():
    lines = README.read_text().splitlines()
    assert len(lines) < 300, f"README.md has {len(lines)} lines; move detail into a docs/ page"


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_relative_links_point_at_files_of_the_repository(page: Path):
    assert page.exists(), f"{page.relative_to(ROOT)} is missing"
    broken = []
    for target in _relative_links(page):
        path = (page.parent / unquote(target.split("#", 1)[0])).resolve()
        if not path.exists():
            broken.append(f"{target} (no such file)")
        elif ROOT not in path.parents and path != ROOT:
            broken.append(f"{target} (outside the repository)")
        elif path.is_file() and _ignored_by_git(path):
            broken.append(f"{target} (ignored by git and not committed: `git add -f` it)")
    assert not broken, f"{page.relative_to(ROOT)}: broken links:\n  " + "\n  ".join(broken)


def test_experiments_readme_names_every_experiment_script():
    text = EXPERIMENTS_README.read_text()
    scripts = sorted(p.name for p in (ROOT / "experiments").glob("*.py"))
    missing = [name for name in scripts if not re.search(rf"(?<![\w.-]){re.escape(name)}(?![\w.-])", text)]
    assert not missing, f"experiments/README.md does not name: {', '.join(missing)}"
