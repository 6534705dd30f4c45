"""The suite's measured durations (``durations.json``), which order and tier the tests (``conftest.py``).

Two uses, both from one run of the whole suite on the 2-core machine:

* **Longest module first.** xdist hands whole modules to the workers (``--dist loadfile``) in collection
  order (``--no-loadscope-reorder``: by default it reorders them by their number of tests, which once
  started the longest module, 3 minutes of a test, 17 minutes into a 20-minute run); a long module that
  starts last keeps one worker busy while the other idles. The modules run in the order of their
  recorded totals (a module not on record, last).
* **The ``slow`` tier by measurement.** The marker means "over ~3 s a test on 2 cores"; besides the
  tests marked by hand, every test recorded at 3 s or more (setup and call together) is marked
  ``slow``, so the quick loop (``-m "not slow and not external and not multiprocess"``) leaves out
  what is measured to be slow, not only what was guessed to be.

Regenerate after adding heavy tests:

    python -m pytest -q -p no:cacheprovider --durations=0 > suite.log
    python -m pytest -q -p no:cacheprovider --durations=0 -m "not slow and not external and not multiprocess" > quick.log
    python tests/durations.py suite.log quick.log > tests/durations.json

(the second run only adds: a module's fixtures fall to the first test the quick loop keeps; further logs,
quick or whole, may follow, and a test slow in any of them is marked).

Stale numbers only change the order and the quick tier; they never change what ``pytest`` runs.
"""

from __future__ import annotations

import json
import re
import sys
from collections import defaultdict

# The slow marker's threshold (pyproject.toml: "over ~3 s a test on 2 CPU cores").
SLOW_S = 3.0
LINE = re.compile(r"^([\d.]+)s (?:call|setup|teardown)\s+(tests/([\w/]+\.py)::.+?)\s*$")


def _parse(log: str) -> tuple[dict[str, float], dict[str, float]]:
    modules: dict[str, float] = defaultdict(float)
    tests: dict[str, float] = defaultdict(float)
    for line in log.splitlines():
        m = LINE.match(line)
        if m:
            modules[m[3]] += float(m[1])
            tests[m[2]] += float(m[1])
    return modules, tests


def summarise(full_log: str, *quick_logs: str) -> dict:
    """``{"modules": {file name: seconds}, "slow_tests": {node id: seconds}}`` from ``--durations=0``
    logs: each module's total in the whole-suite run ``full_log``, and the tests of at least
    :data:`SLOW_S` (setup + call + teardown) in it or in any other run (``quick_logs``: runs of the
    quick loop, where a module's fixtures fall to its first quick test, which then is measured slow
    too, and earlier whole-suite runs, whose slow tests stay marked when a cache makes them faster)."""
    modules, tests = _parse(full_log)
    for log in quick_logs:
        for k, v in _parse(log)[1].items():
            tests[k] = max(tests.get(k, 0.0), v)
    by_time = lambda d: {k: round(v, 1) for k, v in sorted(d.items(), key=lambda kv: (-kv[1], kv[0]))}  # noqa: E731
    return {"modules": by_time(modules), "slow_tests": by_time({k: v for k, v in tests.items() if v >= SLOW_S})}


if __name__ == "__main__":
    logs = []
    for path in sys.argv[1:]:
        with open(path) as handle:
            logs.append(handle.read())
    print(json.dumps(summarise(*logs), indent=1))
