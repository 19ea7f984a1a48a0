"""The lab record's pages, generated from its data.

Every measurement behind a design choice is kept as data in ``benchmarks/results/<record>.json``
(one file per subject: what was measured, the commands, the date or commit where stated, the
table rows and a note on what the measurement showed). This script renders each record as a page
under ``docs/lab/`` and writes the lab's index; ``tests/test_docs.py`` fails when a committed page
differs from what this script generates.

    python benchmarks/lab_tables.py            # check: exit 1 and name the stale pages
    python benchmarks/lab_tables.py --write    # regenerate docs/lab/*.md

A record is a JSON object with ``"schema": "swarmpc-lab/1"`` (files without it, such as the raw
output of a benchmark script, are not records)::

    {
      "schema": "swarmpc-lab/1",
      "record": "admm",                 # the page: docs/lab/admm.md
      "title": "...", "summary": "...", # markdown
      "moved_from": {"page": "docs/admm.md", "commit": "..."},   # optional
      "experiments": [
        {
          "id": "coupling-margin",      # the page anchor: docs/lab/admm.md#coupling-margin
          "title": "...",
          "status": "shipped",          # see STATUSES
          "date": null, "commit": null, # as stated by the measurement, else null
          "logged": {"commit": "...", "date": "..."},   # wrote most of its rows into the old log (git blame)
          "commands": ["swarmpc bench ..."],
          "what": "...",                # markdown: what was measured, and how
          "figures": [{"path": "../img/x.png", "caption": "..."}],   # optional
          "tables": [{"caption": null, "columns": ["M", "steps"], "rows": [["4", "150"]]}],
          "note": "..."                 # markdown: what it showed
        }
      ]
    }

Table cells are strings, exactly as printed (``"1.10"``, ``"+2.0%"``, ``"**8.7**"``), so the
precision a measurement was reported with is kept.

A few benchmark scripts write their raw output (not a record) in a form this script can read;
``GENERATED`` names each such file, the record whose page shows it and the experiment it follows
there, and the function that turns it into an experiment (its table rendered from the rows, its
note from the numbers and from the file's optional ``"note"``, which a rerun of the script drops).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
LAB = ROOT / "docs" / "lab"
SCHEMA = "swarmpc-lab/1"
STATUSES = {
    "shipped": "the measurement behind the shipped default",
    "measured, not the default": "a variant that was measured and not adopted",
    "superseded by a later measurement": "an earlier state of the solver, kept for the history",
    "analysis": "a profile or an analysis, no setting at stake",
}
EXPERIMENT_KEYS = {"id", "title", "status", "date", "commit", "logged", "commands", "what", "figures", "tables", "note"}
ID = re.compile(r"^[a-z0-9]+(?:-[a-z0-9]+)*$")


class RecordError(ValueError):
    """A lab record that does not follow the schema; the message names the file and the field."""


def load_records(folder: Path = RESULTS) -> list[tuple[Path, dict[str, Any]]]:
    """Every lab record in ``folder`` (sorted by file name), validated."""
    records = []
    for path in sorted(folder.glob("*.json")):
        data = json.loads(path.read_text())
        if isinstance(data, dict) and data.get("schema") == SCHEMA:
            validate(data, path.name)
            records.append((path, data))
    return records


def validate(record: dict[str, Any], name: str) -> None:
    """Raise :class:`RecordError` unless ``record`` follows the schema above."""
    for key in ("record", "title", "summary", "experiments"):
        if key not in record:
            raise RecordError(f"{name}: missing {key!r}")
    if not ID.match(record["record"]):
        raise RecordError(f"{name}: record {record['record']!r} is not a lower-case-with-hyphens name")
    seen: set[str] = set()
    for index, exp in enumerate(record["experiments"]):
        where = f"{name}: experiments[{index}]"
        unknown = set(exp) - EXPERIMENT_KEYS
        if unknown:
            raise RecordError(f"{where}: unknown keys {sorted(unknown)}")
        for key in ("id", "title", "status", "date", "commit", "commands", "what", "tables", "note"):
            if key not in exp:
                raise RecordError(f"{where}: missing {key!r}")
        if not ID.match(exp["id"]) or exp["id"] in seen:
            raise RecordError(f"{where}: id {exp['id']!r} is not a new lower-case-with-hyphens name")
        seen.add(exp["id"])
        if exp["status"] not in STATUSES:
            raise RecordError(f"{where}: status {exp['status']!r} is not one of {sorted(STATUSES)}")
        for t, table in enumerate(exp["tables"]):
            columns = table["columns"]
            for r, row in enumerate(table["rows"]):
                if len(row) != len(columns) or not all(isinstance(cell, str) for cell in row):
                    raise RecordError(f"{where}.tables[{t}].rows[{r}]: {len(columns)} string cells expected")
                if any("|" in cell or "\n" in cell for cell in row):
                    raise RecordError(f"{where}.tables[{t}].rows[{r}]: a cell holds '|' or a line break")


def markdown_table(columns: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def _stated(exp: dict[str, Any]) -> str:
    parts = [f"*{exp['status']}*"]
    if exp.get("date"):
        parts.append(f"measured {exp['date']}")
    if exp.get("commit"):
        parts.append(f"commit `{exp['commit']}`")
    logged = exp.get("logged")
    if logged:
        parts.append(f"logged {logged['date']} (commit `{logged['commit']}`)")
    return " · ".join(parts)


def render_record(record: dict[str, Any], source: str) -> str:
    """The lab page of one record."""
    out = [
        (
            f"<!-- Generated by benchmarks/lab_tables.py from {source}: edit the JSON, then run "
            "`python benchmarks/lab_tables.py --write`. -->"
        ),
        "",
        f"# {record['title']}",
        "",
        record["summary"].strip(),
        "",
    ]
    moved = record.get("moved_from")
    if moved:
        out += [
            (
                f"The data is `{source}`. It was moved there from the measurement log of `{moved['page']}` "
                f"(as of commit `{moved['commit']}`); every table row and every number of that log is kept."
            ),
            "",
        ]
    else:
        out += [f"The data is `{source}`.", ""]
    out += ["| experiment | status | tables |", "|---|---|---|"]
    for exp in record["experiments"]:
        rows = sum(len(table["rows"]) for table in exp["tables"])
        tables = f"{len(exp['tables'])} ({rows} row{'s' if rows != 1 else ''})" if exp["tables"] else "–"
        out.append(f"| [{exp['title']}](#{exp['id']}) | {exp['status']} | {tables} |")
    out.append("")
    for exp in record["experiments"]:
        out += [f'<a id="{exp["id"]}"></a>', "", f"## {exp['title']}", "", _stated(exp), ""]
        if exp["commands"]:
            out += ["```bash", *exp["commands"], "```", ""]
        if exp["what"].strip():
            out += ["**What was measured**", "", exp["what"].strip(), ""]
        for figure in exp.get("figures", []):
            out += [f"![{figure['caption']}]({figure['path']})", ""]
        for table in exp["tables"]:
            if table.get("caption"):
                out += [table["caption"].strip(), ""]
            out += [markdown_table(table["columns"], table["rows"]), ""]
        if exp["note"].strip():
            out += ["**What it showed**", "", exp["note"].strip(), ""]
    return "\n".join(out).rstrip("\n") + "\n"


def render_index(records: list[tuple[Path, dict[str, Any]]]) -> str:
    """The lab's index page: one line per record, and the statuses."""
    out = [
        (
            "<!-- Generated by benchmarks/lab_tables.py from benchmarks/results/*.json: edit the JSON, then run "
            "`python benchmarks/lab_tables.py --write`. -->"
        ),
        "",
        "# Lab record",
        "",
        (
            "The measurements behind swarmpc's design choices, kept as data in `benchmarks/results/*.json` "
            "and rendered here by `benchmarks/lab_tables.py`. The [design notes](../design/admm.md) say "
            "why each choice was made and link to the experiment that settled it; the user guide starts "
            "at [the documentation index](../index.md)."
        ),
        "",
        (
            "Read the times with care: most runs shared a 2-core machine with other runs (each experiment "
            "says how), so counts (steps, iterations, repairs, collisions) and costs are the robust "
            "numbers; milliseconds compare only within one table."
        ),
        "",
        "| record | experiments | tables | rows | data |",
        "|---|---|---|---|---|",
    ]
    for path, record in records:
        exps = record["experiments"]
        tables = sum(len(exp["tables"]) for exp in exps)
        rows = sum(len(table["rows"]) for exp in exps for table in exp["tables"])
        out.append(
            f"| [{record['title']}]({record['record']}.md) | {len(exps)} | {tables} | {rows} | "
            f"`benchmarks/results/{path.name}` |"
        )
    out += ["", "Each experiment carries one status:", ""]
    out += [f"* *{status}*: {meaning}." for status, meaning in STATUSES.items()]
    return "\n".join(out) + "\n"


def _cell(value: float, digits: int = 3) -> str:
    return f"{value:.{digits}f}"


def _variant(row: dict[str, Any]) -> str:
    return row["variant"] + (f" ({row['threads']} threads)" if row["threads"] > 1 else "")


def batched_qp_experiment(data: dict[str, Any]) -> dict[str, Any]:
    """The experiment of ``benchmarks/batched_qp.py``'s output: one row per batch size and variant."""
    shape, rows = data["shape"], data["rows"]
    table = [
        [
            str(r["batch"]), r["variant"], "loop" if r["threads"] == 0 else str(r["threads"]),
            _cell(r["median_ms"]), _cell(r["p95_ms"]), _cell(r["per_agent_median_ms"]),
            f"{r['speedup_vs_one_by_one']:.2f}×", f"{r['max_distance_from_one_by_one']:.1e}",
        ]
        for r in rows
    ]
    largest = max(r["batch"] for r in rows)
    at_largest = [r for r in rows if r["batch"] == largest]
    per_agent = "; ".join(
        f"{_variant(r)} {_cell(r['per_agent_median_ms'])} ms ({r['speedup_vs_one_by_one']:.2f}×)" for r in at_largest
    )
    load = ", ".join(f"{sample[0]:.2f}" for sample in data["load_average"])
    what = (
        f"`benchmarks/batched_qp.py` (data: `benchmarks/results/batched_qp.json`): the local QPs of "
        f"{data['recorded_agents']} agents of one MPC step of {data['scenario']} that share a shape "
        f"({shape['copies']} copies: {shape['variables']} variables, {shape['rows']} rows), at ADMM iteration "
        f"{data['iteration']}, each with its converged certificates; larger batches are made of these with "
        "targets moved by ~1 mm and certificate normals turned by ~1e-3. Per batch size B, each variant is set "
        "up once, then updates and solves the whole batch once per round, warm-started, after every problem's "
        f"consensus targets moved by ~1 mm; {data['repeats']} rounds, the variants taking turns within each. "
        "Times are wall times around the whole update + solve of the batch, from Python. "
        "*OSQP one by one* is the shipped way (one OSQP solver per agent); *block-diagonal* is one OSQP "
        "problem holding the B problems; ProxQP dense runs over proxsuite's `BatchQP`, by "
        "`solve_in_parallel` or by each QP's own `solve` in a Python loop; CasADi's `conic` (osqp plugin) is "
        f"mapped over the batch by `Function.map`. Idle OpenMP threads: `OMP_WAIT_POLICY={data['omp_wait_policy']}`. "
        f"Machine: {data['machine']}, {data['cores']} cores, 1-minute load average {load} (before, after): "
        "the threaded variants shared the cores with other work."
    )
    note = f"Per agent at B = {largest}: {per_agent}."
    if data.get("note"):
        note += "\n\n" + data["note"].strip()
    columns = [
        "B", "variant", "threads", "median ms", "p95 ms", "per agent ms (median)", "vs one by one",
        "max abs x difference from one by one",
    ]
    return {
        "id": "batched-local-qps", "title": "Batched solving of same-shape local QPs",
        "status": "measured, not the default", "date": data.get("date"), "commit": None,
        "commands": [f"nice -n 10 {data['command']}"], "what": what,
        "tables": [{"caption": None, "columns": columns, "rows": table}], "note": note,
    }


BENCH_COLUMNS = (
    ("family", "family", "{}"), ("M", "agents", "{}"), ("local", "local", "{}"), ("runs", "runs", "{}"),
    ("all reached", "all_reached_rate", "{:.0%}"), ("collision-free", "collision_free_rate", "{:.0%}"),
    ("makespan s (median)", "makespan_s_median", "{:.1f}"), ("vs lone", "interaction_ratio_median", "{:.2f}"),
    ("per-agent ms median", "agent_ms_median", "{:.2f}"), ("p99", "agent_ms_p99", "{:.1f}"),
    ("critical path ms median", "critical_path_ms_median", "{:.1f}"), ("p99", "critical_path_ms_p99", "{:.0f}"),
    ("deadline misses", "deadline_misses", "{}"), ("wall s per run", "wall_s_per_run_median", "{:.0f}"),
    ("local fallbacks", "local_fallbacks", "{}"),
)
"""The columns of a ``swarmpc bench`` report shown in the lab record: (header, row key, format)."""


def bench_experiment(data: dict[str, Any]) -> dict[str, Any]:
    """The lab experiment of a ``swarmpc bench`` report (its ``bench.json``, copied into
    benchmarks/results/ with the keys ``id``, ``title``, ``status``, ``date``, ``command``, ``what``
    and ``note`` added): the report's rows in the columns of ``BENCH_COLUMNS``."""
    table = [[_bench_cell(row.get(key), fmt) for _, key, fmt in BENCH_COLUMNS] for row in data["rows"]]
    what = f"{data['what'].strip()} Machine: {data['machine']}; {data['elapsed_s'] / 60:.0f} min in all."
    return {
        "id": data["id"], "title": data["title"], "status": data["status"], "date": data["date"], "commit": None,
        "commands": [data["command"]], "what": what,
        "tables": [{"caption": None, "columns": [c[0] for c in BENCH_COLUMNS], "rows": table}],
        "note": data["note"].strip(),
    }


def _bench_cell(value: Any, fmt: str) -> str:
    return "–" if value is None else fmt.format(value)


GENERATED = {
    "batched_qp.json": ("admm", "local-solver-candidates", batched_qp_experiment),
    "bench-random-fast-qp.json": ("controller", "knot-rule", bench_experiment),
    "bench-random-fast-ipopt.json": ("controller", "random-fast-tuning", bench_experiment),
    "bench-random-fast-qp-knots.json": ("controller", "random-fast-tuning-ipopt", bench_experiment),
    "bench-random-stiff-qp.json": ("controller", "random-fast-tuning-knots", bench_experiment),
    "bench-random-stiff-speed-qp.json": ("controller", "random-stiff-tuning", bench_experiment),
}
"""Raw benchmark output file -> (record, the experiment it follows on that record's page, builder)."""


def with_generated(records: list[tuple[Path, dict[str, Any]]], folder: Path) -> list[tuple[Path, dict[str, Any]]]:
    """``records`` with the experiments of the ``GENERATED`` files present in ``folder`` inserted."""
    out = []
    for path, record in records:
        experiments = list(record["experiments"])
        for name, (target, after, build) in GENERATED.items():
            if target != record["record"] or not (folder / name).exists():
                continue
            ids = [exp["id"] for exp in experiments]
            at = ids.index(after) + 1 if after in ids else len(experiments)
            experiments.insert(at, build(json.loads((folder / name).read_text())))
        record = {**record, "experiments": experiments}
        validate(record, path.name)
        out.append((path, record))
    return out


def generate(folder: Path = RESULTS) -> dict[Path, str]:
    """Every lab page by its path: one per record, and the index."""
    records = with_generated(load_records(folder), folder)
    pages = {LAB / "index.md": render_index(records)}
    for path, record in records:
        pages[LAB / f"{record['record']}.md"] = render_record(record, f"benchmarks/results/{path.name}")
    return pages


def stale(pages: dict[Path, str]) -> list[Path]:
    """Pages whose committed text differs from ``pages``, and generated-looking pages with no record."""
    out = [path for path, text in pages.items() if not path.exists() or path.read_text() != text]
    out += [path for path in sorted(LAB.glob("*.md")) if path not in pages]
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--write", action="store_true", help="regenerate docs/lab/*.md")
    args = parser.parse_args(argv)
    pages = generate()
    if args.write:
        LAB.mkdir(parents=True, exist_ok=True)
        for path in sorted(LAB.glob("*.md")):
            if path not in pages:
                path.unlink()
        for path, text in pages.items():
            path.write_text(text)
        print(f"wrote {len(pages)} pages to {LAB.relative_to(ROOT)}/")
        return 0
    out_of_date = stale(pages)
    for path in out_of_date:
        print(f"{path.relative_to(ROOT)} is out of date: run `python benchmarks/lab_tables.py --write`")
    return 1 if out_of_date else 0


if __name__ == "__main__":
    sys.exit(main())
