"""The documentation stays true: generated references match the code, links resolve, recipes run."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from pydantic import BaseModel

from swarmpc.docgen import MissingDocError, cli_reference, scenario_reference, schema_fields

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
REGENERATE = (
    "run `python -m swarmpc.docgen --write` (or `python -m swarmpc.docgen > docs/scenario-reference.md` "
    "and `python -m swarmpc.docgen --cli > docs/cli-reference.md`)"
)


@pytest.mark.parametrize(
    ("filename", "generate"),
    [("scenario-reference.md", scenario_reference), ("cli-reference.md", cli_reference)],
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


def _without_code(text: str) -> str:
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def _anchors(page: Path) -> set[str]:
    """GitHub-style heading anchors of a markdown page."""
    text = re.sub(r"^```.*?^```", "", page.read_text(), flags=re.S | re.M)
    headings = re.findall(r"^#+\s+(.*?)\s*$", text, flags=re.M)
    return {re.sub(r"[^\w\- ]", "", h.lower()).replace(" ", "-") for h in headings}


LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
PAGES = sorted([*DOCS.glob("*.md"), ROOT / "README.md"])


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
    assert len(_recipes()) == 6


@pytest.mark.parametrize("index", range(6), ids=lambda i: f"recipe-{i + 1}")
def test_recipe_runs(index, tmp_path):
    code = _recipes()[index]
    env = {**os.environ, "MPLBACKEND": "Agg"}
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300, env=env
    )
    assert done.returncode == 0, f"recipe {index + 1} of docs/recipes.md failed:\n{done.stderr[-3000:]}"
    assert done.stdout.strip(), f"recipe {index + 1} printed nothing"
