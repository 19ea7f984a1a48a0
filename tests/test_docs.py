"""The documentation stays true: generated references match the code, links resolve, recipes run."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from pydantic import BaseModel

from swarmpc.docgen import MissingDocError, cli_reference, run_folder_reference, scenario_reference, schema_fields
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.contract import ARRAYS, FILES, SUMMARY_KEYS, conditions_of, expected_shapes
from swarmpc.simulation.loop import simulate
from swarmpc.simulation.results import write_run

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
REGENERATE = (
    "run `python -m swarmpc.docgen --write` (or `python -m swarmpc.docgen > docs/scenario-reference.md`, "
    "`python -m swarmpc.docgen --cli > docs/cli-reference.md` and "
    "`python -m swarmpc.docgen --run-folder > docs/run-folder-reference.md`)"
)


@pytest.mark.parametrize(
    ("filename", "generate"),
    [
        ("scenario-reference.md", scenario_reference),
        ("cli-reference.md", cli_reference),
        ("run-folder-reference.md", run_folder_reference),
    ],
)
def test_generated_reference_is_current(filename, generate):
    committed = (DOCS / filename).read_text()
    assert committed == generate(), f"docs/{filename} is out of date with the code: {REGENERATE}"


def test_every_schema_field_is_documented():
    text = (DOCS / "scenario-reference.md").read_text()
    rows = schema_fields()
    assert len(rows) > 30
    missing = [row.path for row in rows if f"| `{row.path}` |" not in text]
    assert not missing, f"fields missing from docs/scenario-reference.md: {missing}; {REGENERATE}"


def test_undocumented_field_fails_the_generator():
    class Undocumented(BaseModel):
        mystery: int = 1

    with pytest.raises(MissingDocError, match="mystery"):
        schema_fields(Undocumented, prefix="extra.")


# ----------------------------------------------------------------------------------- run folders
CONTRACT = "swarmpc/simulation/contract.py"
CONTRACT_RUNS = {
    # ADMM with an obstacle: admm.npz, the ADMM keys and the RRT planner's counts
    "admm-rrt": {"obstacles": [{"box": {"center": [0.0, 2.5], "half_size": [0.3, 0.2]}}]},
    # centralised with process noise: no admm.npz, trajectory.npz holds the disturbances
    "centralized-noise": {"solver.method": "centralized", "disturbance.process_position_std": 0.01},
}


@pytest.fixture(scope="module", params=sorted(CONTRACT_RUNS))
def contract_run(request, tmp_path_factory):
    """A real run folder (3 steps of paper-2d as ``write_run`` writes it) and its conditions."""
    scn = builtin_scenario("paper-2d").with_updates(**{"stop.max_steps": 3, **CONTRACT_RUNS[request.param]})
    folder = write_run(simulate(scn), tmp_path_factory.mktemp("contract") / request.param)
    return folder, conditions_of(scn)


def _dotted_keys(mapping: dict, documented: set[str], prefix: str = "") -> list[str]:
    """The keys of a summary, nested ones dotted where the contract documents children."""
    keys = []
    for key, value in mapping.items():
        path = f"{prefix}{key}"
        keys.append(path)
        if isinstance(value, dict) and any(name.startswith(f"{path}.") for name in documented):
            keys.extend(_dotted_keys(value, documented, f"{path}."))
    return keys


def test_run_folder_holds_exactly_the_documented_files(contract_run):
    folder, held = contract_run
    expected = {name for doc in FILES if doc.when in held for name in doc.name.split(", ")}
    written = {path.name for path in folder.iterdir()}
    assert written == expected, (
        f"undocumented files {sorted(written - expected)}, documented but missing {sorted(expected - written)}: "
        f"update FILES in {CONTRACT}, then {REGENERATE}"
    )


def test_summary_holds_exactly_the_documented_keys(contract_run):
    folder, held = contract_run
    summary = json.loads((folder / "summary.json").read_text())
    documented = {doc.key for doc in SUMMARY_KEYS}
    expected = {doc.key for doc in SUMMARY_KEYS if doc.when in held}
    written = set(_dotted_keys(summary, documented))
    assert written == expected, (
        f"summary.json keys undocumented {sorted(written - expected)}, documented but not written "
        f"{sorted(expected - written)}: update SUMMARY_KEYS in {CONTRACT}, then {REGENERATE}"
    )


def test_archives_hold_exactly_the_documented_arrays(contract_run):
    folder, held = contract_run
    summary = json.loads((folder / "summary.json").read_text())
    sizes = {"T": summary["steps"], "M": summary["num_agents"], "d": summary["dim"], "I": 0}
    if (folder / "admm.npz").exists():
        with np.load(folder / "admm.npz") as admm:
            sizes["I"] = int(admm["iterations"].max(initial=0))
    for archive in dict.fromkeys(doc.file for doc in ARRAYS):
        docs = {doc.name: doc for doc in ARRAYS if doc.file == archive and doc.when in held}
        if not docs:
            assert not (folder / archive).exists()
            continue
        with np.load(folder / archive) as data:
            arrays = {name: data[name] for name in data.files}
        assert set(arrays) == set(docs), (
            f"{archive}: undocumented arrays {sorted(set(arrays) - set(docs))}, documented but not written "
            f"{sorted(set(docs) - set(arrays))}: update ARRAYS in {CONTRACT}, then {REGENERATE}"
        )
        for name, array in arrays.items():
            doc = docs[name]
            assert array.shape in expected_shapes(doc.shape, sizes), f"{archive} {name}: {array.shape} vs {doc.shape}"
            assert array.dtype.name == doc.dtype, f"{archive} {name}: {array.dtype} vs {doc.dtype}"


def test_the_reader_reads_every_documented_array():
    """A documented array that ``load_run`` ignores is a gap (the reader may also accept more)."""
    from swarmpc.simulation import rundata

    def documented(archive: str) -> set[str]:
        return {doc.name for doc in ARRAYS if doc.file == archive}

    assert documented("trajectory.npz") <= set(rundata._TRAJECTORY_KEYS)
    assert documented("steps.npz") <= set(rundata._STEP_KEYS)
    assert documented("admm.npz") <= set(rundata._ADMM_KEYS)


def test_every_export_is_documented():
    text = (DOCS / "run-folder-reference.md").read_text()
    from swarmpc.export import MCAP_TOPICS, METRICS

    assert all(f"| `{doc.topic}` |" in text for doc in MCAP_TOPICS)
    assert all(f"| `{doc.name}` |" in text for doc in METRICS)
    assert all(f"| `{doc.key}` |" in text for doc in SUMMARY_KEYS)


def _without_code(text: str) -> str:
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def _anchors(page: Path) -> set[str]:
    """GitHub-style heading anchors of a markdown page, and its explicit ``<a id="...">`` anchors."""
    text = re.sub(r"^```.*?^```", "", page.read_text(), flags=re.S | re.M)
    headings = re.findall(r"^#+\s+(.*?)\s*$", text, flags=re.M)
    explicit = set(re.findall(r'<a id="([^"]+)"></a>', text))
    return {re.sub(r"[^\w\- ]", "", h.lower()).replace(" ", "-") for h in headings} | explicit


LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
PAGES = sorted([*DOCS.rglob("*.md"), ROOT / "README.md"])


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page):
    broken = []
    for target in LINK.findall(_without_code(page.read_text())):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):
            continue  # http(s), mailto
        path, _, anchor = target.partition("#")
        file = page.parent / path if path else page
        if not file.exists():
            broken.append(target)
        elif anchor and file.suffix == ".md" and anchor not in _anchors(file):
            broken.append(target)
    assert not broken, f"{page.relative_to(ROOT)}: broken relative links {broken}"


def _recipes() -> list[str]:
    text = (DOCS / "recipes.md").read_text()
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def test_recipes_exist():
    assert len(_recipes()) == 7


@pytest.mark.parametrize("index", range(7), ids=lambda i: f"recipe-{i + 1}")
def test_recipe_runs(index, tmp_path):
    code = _recipes()[index]
    env = {**os.environ, "MPLBACKEND": "Agg"}
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env
    )
    assert done.returncode == 0, f"recipe {index + 1} of docs/recipes.md failed:\n{done.stderr[-3000:]}"
    assert done.stdout.strip(), f"recipe {index + 1} printed nothing"


# ------------------------------------------------------------------------- lab record and site
def _lab_tables():
    """``benchmarks/lab_tables.py`` (a script, not part of the package), imported by path."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("lab_tables", ROOT / "benchmarks" / "lab_tables.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_lab_pages_are_generated_from_the_json():
    lab = _lab_tables()
    pages = lab.generate()
    assert len(pages) >= 5  # the index and at least admm, initial-guesses, paper-reproduction, troubleshooting
    stale = [str(path.relative_to(ROOT)) for path in lab.stale(pages)]
    assert not stale, (
        f"{stale} out of date with benchmarks/results/*.json: run `python benchmarks/lab_tables.py --write`"
    )


def test_lab_records_follow_the_schema():
    lab = _lab_tables()
    records = lab.load_records()  # validates every record
    names = {record["record"] for _, record in records}
    assert {"admm", "initial-guesses", "paper-reproduction", "troubleshooting"} <= names
    rows = sum(len(t["rows"]) for _, record in records for e in record["experiments"] for t in e["tables"])
    assert rows >= 262  # the rows moved out of the old measurement logs: none may be lost
    broken = {"schema": lab.SCHEMA, "record": "x", "title": "x", "summary": "x", "experiments": [{"id": "a"}]}
    with pytest.raises(lab.RecordError, match="missing"):
        lab.validate(broken, "broken.json")


def test_design_notes_cite_the_lab_record():
    """Every row of a design note's "option | default | why | evidence" table links its evidence."""
    for page in sorted((DOCS / "design").glob("*.md")):
        rows = [line for line in page.read_text().splitlines()
                if line.startswith("| ") and not line.startswith("| option")]
        assert rows, f"{page.name}: no choices table"
        for row in rows:
            evidence = row.rstrip(" |").rsplit("|", 1)[-1].strip()
            assert evidence == "–" or "](" in evidence, f"design/{page.name}: no evidence link in {row[:60]}"


def test_the_site_builds_without_warnings(tmp_path):
    """``mkdocs build --strict``: every page, link, anchor and API docstring renders without a warning."""
    pytest.importorskip("mkdocs")
    pytest.importorskip("mkdocstrings_handlers.python")
    done = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(ROOT / "mkdocs.yml"),
         "-d", str(tmp_path / "site")],
        check=False,
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    warnings = [line for line in done.stderr.splitlines() if "WARNING" in line or "ERROR" in line]
    assert done.returncode == 0 and not warnings, (
        "mkdocs build --strict failed:\n" + "\n".join(warnings or [done.stderr[-3000:]])
    )
    api = (tmp_path / "site" / "api" / "simulation" / "index.html").read_text()
    assert "swarmpc.simulation.loop.simulate" in api and "RunData" in api

