"""What the study scripts share: measuring rows in a process pool into a rows file, and writing
one experiment into a lab record (``benchmarks/results/<record>.json``)."""

from __future__ import annotations

import json
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

Row = dict[str, Any]


def measure_rows(out: Path, tasks: Sequence[Any], measure: Callable[[Any], Row], key: Callable[[Row], Any],
                 jobs: int) -> None:
    """Measure ``tasks`` on ``jobs`` processes; each row replaces the row of the same ``key`` in
    ``out`` (kept in ``{"rows": [...]}``), which is rewritten after every row."""
    rows = json.loads(out.read_text())["rows"] if out.exists() else []
    with ProcessPoolExecutor(jobs) as pool:
        for row in pool.map(measure, tasks):
            print(json.dumps(row), flush=True)
            rows = [r for r in rows if key(r) != key(row)]
            rows.append(row)
            out.write_text(json.dumps({"rows": rows}, indent=2) + "\n")


def write_experiment(record_path: Path, experiment: Row, empty: Row | None = None) -> None:
    """Put ``experiment`` into the lab record at ``record_path`` (replacing the one with its id;
    a record that does not exist yet starts as ``empty``)."""
    record = json.loads(record_path.read_text()) if record_path.exists() or empty is None else dict(empty)
    record["experiments"] = [e for e in record["experiments"] if e["id"] != experiment["id"]] + [experiment]
    record_path.write_text(json.dumps(record, indent=1, ensure_ascii=False) + "\n")
