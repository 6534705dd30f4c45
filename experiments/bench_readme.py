"""The performance tables of docs/performance.md from ``jaxtalk bench`` JSON files (``--train`` adds the training table).

    jaxtalk bench --train --paper --out experiments/results/bench_all.json
    python experiments/bench_readme.py experiments/results/bench_all.json > /tmp/performance.md

Prints Markdown per file: the machine and the limits the run measured, then one table per benchmark
table of the run (every row, the columns that matter to a reader), so every table docs/performance.md
quotes names its run. The machine line and each table cite the file they come from
(``<!-- from: FILE -->``, checked by ``tests/test_docs_numbers.py``), named as given on the command line:
run it from the repository's root.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

# Columns shown per table kind (the JSON keeps every field); a table's title picks its kind.
TRAIN_COLUMNS = (("model", "model"), ("preset", "preset"), ("batch", "batch"), ("params_m", "params (M)"),
                 ("step_s", "step (s)"), ("gflops", "GFLOP / step"), ("gflop_s", "GFLOP/s"),
                 ("of_peak", "of peak"), ("compile_s", "compile (s)"), ("memory_gb", "memory (GiB)"),
                 ("host_share", "host share"), ("loader_x", "loader / step rate"))
SAMPLE_COLUMNS = (("model", "model"), ("case", "case"), ("steps", "steps"), ("compile_s", "compile (s)"),
                  ("latency_s", "latency (s)"), ("rtf", "real-time factor"), ("frames_per_s", "frames/s"),
                  ("gflops", "GFLOP"), ("gflop_s", "GFLOP/s"), ("of_peak", "of peak"), ("weight_gb", "weights read (GB)"),
                  ("of_bandwidth", "of bandwidth"), ("of_roofline", "of roofline"))


def cell(value: Any) -> str:
    """A Markdown cell: floats to 3 significant digits, missing values as ``-``."""
    if value is None:
        return "-"
    if isinstance(value, float):
        return str(value) if not math.isfinite(value) else f"{value:.3g}"
    return str(value)


def markdown_table(rows: list[dict[str, Any]], columns: tuple[tuple[str, str], ...]) -> str:
    """``rows`` as a Markdown table of the ``(key, header)`` columns any row has."""
    present = [(k, h) for k, h in columns if any(k in r for r in rows)]
    lines = ["| " + " | ".join(h for _, h in present) + " |", "|" + "---|" * len(present)]
    lines += ["| " + " | ".join(cell(r.get(k)) for k, _ in present) + " |" for r in rows]
    return "\n".join(lines)


def performance_section(payload: dict[str, Any], titles: tuple[str, ...] = (), source: str | None = None) -> str:
    """The Markdown of a bench JSON: machine line, then every table (only those whose title starts
    with one of ``titles`` when given). With ``source`` (the JSON file's path from the repository's
    root) the machine line ends with, and each table follows, a citation of that file."""
    cite = f"<!-- from: {source} -->" if source else ""
    m = payload["machine_info"]
    recorded = payload.get("recorded", {})
    head = (f"Measured by `{recorded.get('command', 'jaxtalk bench')}` on {recorded.get('date_utc', '?')}: "
            f"{m['cpu_model']}, {m['cpu_cores']} cores, backend {m['backend']} ({m['device_kind']}), "
            f"jax {m['jax']}, 1-minute load average {m['load_avg_1m']}; float32 matmul peak measured in the same "
            f"run: {payload['matmul_peak_gflop_s']:.0f} GFLOP/s"
            + (f", memory bandwidth {payload['memory_bandwidth_gb_s']:.1f} GB/s."
               if payload.get("memory_bandwidth_gb_s") else ".") + cite)
    parts = [head]
    for table in payload["tables"]:
        if titles and not table["title"].startswith(titles):
            continue
        columns = TRAIN_COLUMNS if table["title"].startswith("Training") else SAMPLE_COLUMNS
        parts += [f"**{table['title']}**", (cite + "\n" if cite else "") + markdown_table(table["rows"], columns)]
    return "\n\n".join(parts) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("json", type=Path, nargs="+", help="`jaxtalk bench` JSON files (one section each)")
    parser.add_argument("--titles", nargs="*", default=(), help="only the tables whose titles start with these")
    args = parser.parse_args()
    titles = tuple(args.titles)
    print("\n".join(performance_section(json.loads(path.read_text()), titles, source=path.as_posix())
                    for path in args.json), end="")


if __name__ == "__main__":
    main()
