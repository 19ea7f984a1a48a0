"""``swarmpc reproduce --quick``: every figure and table is produced, and every number in the report
matches the ``summary.json`` of the run folder its row links (parsed back independently here).

The quick plan runs once per module (about a minute on two cores); the plot and animate commands
are then checked on its real 2D and 3D run folders.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
FIGURES = ("fig-trajectories-2d.png", "fig-trajectories-3d.png", "fig-convergence.png", "fig-delta.png",
           "fig-guesses.png")
SECTIONS = ("## Trajectories (paper Fig. 3)", "## ADMM convergence (paper Fig. 4)",
            "## Variation with Δ (paper Fig. 5)", "## Hard vs soft constraints", "## Initial guess",
            "## The paper's claims against these runs")
LINK = re.compile(r"\[([^\]]+)\]\(([^)]+)/summary\.json\)")


def cli(*args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "swarmpc", *args], capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture(scope="module")
def quick(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("reproduce") / "out"
    done = cli("reproduce", "--quick", "--out", str(out), "--jobs", "2")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().endswith("report.md")
    return out


def tables(text: str) -> list[tuple[list[str], list[list[str]]]]:
    """Every markdown table of a page: (headers, rows of cells)."""
    found, lines = [], text.splitlines()
    k = 0
    while k < len(lines):
        if lines[k].startswith("|") and k + 1 < len(lines) and lines[k + 1].startswith("|---"):
            headers = [c.strip() for c in lines[k].strip("|").split("|")]
            rows, k = [], k + 2
            while k < len(lines) and lines[k].startswith("|"):
                rows.append([c.strip() for c in lines[k].strip("|").split("|")])
                k += 1
            found.append((headers, rows))
        else:
            k += 1
    return found


def _admm(key: str) -> Callable[[dict[str, Any], dict[str, Any]], Any]:
    return lambda s, _scn: (s.get("admm_iterations") or {}).get(key)


EXPECTED: dict[str, Callable[[dict[str, Any], dict[str, Any]], Any]] = {
    "scenario": lambda s, _scn: s["scenario"],
    "Δ": lambda s, _scn: float(s["delta"]),
    "form": lambda s, _scn: s["collision"],
    "method": lambda s, _scn: s["method"],
    "guess": lambda _s, scn: scn["solver"]["initial_guess"],
    "reached": lambda s, _scn: f"{sum(s['reached'])}/{s['num_agents']}",
    "steps": lambda s, _scn: s["steps"],
    "cost": lambda s, _scn: s["cost"],
    "step ms median": lambda s, _scn: s["step_time_ms"]["median"],
    "step ms p95": lambda s, _scn: s["step_time_ms"]["p95"],
    "agent ms median": lambda s, _scn: s["agent_step_time_ms"]["median"],
    "ADMM it. median": _admm("median"),
    "ADMM it. mean": _admm("mean"),
    "ADMM it. max": _admm("max"),
    "failures": lambda s, _scn: s["solver_failures"],
    "fallbacks": lambda s, _scn: s.get("fallback_steps"),
    "repairs": lambda s, _scn: s.get("admm_repairs"),
    "collisions": lambda s, _scn: s["collisions"],
    "min sep/Δ": lambda s, _scn: s["min_separation_ratio"],
    "max slack": lambda s, _scn: s["max_slack"],
}
# derived columns: the run the percentage is relative to, from the row's run name
REFERENCE = {"vs centralised": ("_admm_", "_centralized_"), "vs hard": ("_soft_", "_hard_")}


def assert_cell(cell: str, expected: Any, where: str) -> None:
    if expected is None:
        assert cell == "-", where
    elif isinstance(expected, str):
        assert cell == expected, where
    else:
        value = float(cell)
        decimals = len(cell.split(".")[1]) if "." in cell else 0
        assert abs(value - float(expected)) <= 0.5 * 10.0**-decimals + 1e-9, f"{where}: {cell} vs {expected}"


@pytest.mark.loop
def test_every_figure_and_animation_is_written(quick: Path) -> None:
    for name in FIGURES:
        data = (quick / name).read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 10_000, name
    for name in ("anim-paper-2d.gif", "anim-paper-3d.gif"):
        assert (quick / name).read_bytes()[:6] in (b"GIF89a", b"GIF87a"), name
    report = (quick / "report.md").read_text()
    for target in re.findall(r"!?\[[^\]]*\]\(([^)\s]+)\)", report):
        if not target.startswith(("http", "../")):
            assert (quick / target).exists(), f"report.md links a missing file: {target}"


@pytest.mark.loop
def test_every_run_folder_is_complete_and_in_the_report(quick: Path) -> None:
    manifest = json.loads((quick / "reproduce.json").read_text())
    report = (quick / "report.md").read_text()
    assert manifest["quick"] is True and manifest["runs"]
    assert not [run["name"] for run in manifest["runs"] if run["error"]]
    linked = {folder for _name, folder in LINK.findall(report)}
    for run in manifest["runs"]:
        folder = quick / run["folder"]
        for name in ("summary.json", "trajectory.npz", "scenario.yaml", "steps.npz"):
            assert (folder / name).is_file(), f"{run['folder']}/{name}"
        assert run["folder"] in linked, f"{run['folder']} is in no table of report.md"
    methods = {json.loads((quick / run["folder"] / "summary.json").read_text())["method"] for run in manifest["runs"]}
    assert methods == {"admm", "centralized"}


@pytest.mark.loop
def test_report_has_every_section_and_table(quick: Path) -> None:
    report = (quick / "report.md").read_text()
    for section in SECTIONS:
        assert section in report, section
    found = tables(report)
    headers = [h for h, _rows in found]
    assert len(found) == 3, headers
    assert {"vs centralised", "min sep/Δ"} <= set(headers[0])  # the variation-with-Δ table
    assert {"form", "cost", "step ms median", "failures", "max slack"} <= set(headers[1])  # hard vs soft
    assert {"guess", "step ms median", "step ms p95", "ADMM it. mean", "cost", "reached"} <= set(headers[2])
    assert {row[headers[2].index("guess")] for row in found[2][1]} == {"straight", "rrt", "auto"}
    for verdict in ("*Performance degrades as Δ grows*", "*Soft is slightly sub-optimal*", "*Soft is slower*",
                    "*The RRT guess lowers compute time*", "*The RRT guess avoids local minima*"):
        assert verdict in report


@pytest.mark.loop
def test_every_number_in_the_report_matches_its_run_folder(quick: Path) -> None:
    checked = 0
    for headers, rows in tables((quick / "report.md").read_text()):
        assert headers[-1] == "run"
        for row in rows:
            name, folder = LINK.fullmatch(row[-1]).groups()  # type: ignore[union-attr]
            summary = json.loads((quick / folder / "summary.json").read_text())
            scenario = yaml.safe_load((quick / folder / "scenario.yaml").read_text())
            for header, cell in zip(headers[:-1], row[:-1], strict=True):
                where = f"{name} / {header}"
                if header in REFERENCE:
                    old, new = REFERENCE[header]
                    if old not in name:
                        assert cell == "-", where
                        continue
                    base = json.loads((quick / folder.replace(old, new) / "summary.json").read_text())["cost"]
                    assert_cell(cell.rstrip("%"), 100 * (summary["cost"] - base) / base, where)
                else:
                    assert header in EXPECTED, f"unchecked column {header!r}"
                    expected = EXPECTED[header](summary, scenario)
                    if header == "Δ":
                        assert float(cell) == expected, where
                    else:
                        assert_cell(cell, expected, where)
                checked += 1
    assert checked > 300


@pytest.mark.loop
def test_plot_and_animate_work_on_real_2d_and_3d_run_folders(quick: Path, tmp_path: Path) -> None:
    for dim in ("2d", "3d"):
        run = tmp_path / dim
        shutil.copytree(quick / "runs" / f"paper-{dim}_d0.3_hard_admm_auto", run)
        done = cli("plot", str(run))
        assert done.returncode == 0, done.stderr
        assert (run / "trajectory.png").read_bytes().startswith(PNG_MAGIC)
        assert (run / "convergence.png").read_bytes().startswith(PNG_MAGIC)
        done = cli("animate", str(run))
        assert done.returncode == 0, done.stderr
        assert (run / "animation.gif").read_bytes()[:3] == b"GIF"
    done = cli("animate", str(tmp_path / "3d"), "--format", "mp4")  # ffmpeg from imageio-ffmpeg
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "3d" / "animation.mp4").read_bytes()[4:8] == b"ftyp"


def test_bad_reproduce_options_are_one_line_errors(tmp_path: Path) -> None:
    done = cli("reproduce", "--jobs", "0", "--out", str(tmp_path / "x"))
    assert done.returncode == 2
    assert done.stderr.count("\n") == 1 and "jobs" in done.stderr
    assert not (tmp_path / "x").exists()
