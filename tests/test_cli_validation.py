"""Every bad input: one line on stderr naming the field, exit status 2, no output folder."""

from __future__ import annotations

import pytest
import yaml

from conftest import run_cli

BASE = {"agents": [{"start": [-1, -1], "goal": [1, 1]}, {"start": [1, -1], "goal": [-1, 1]}]}


def with_(**changes):
    return {**BASE, **changes}


CASES = {
    "unknown key": (with_(colour="red"), "colour"),
    "wrong vector length": ({"agents": [{"start": [0, 0, 0], "goal": [1, 1]}]}, "agents[0].start"),
    "dim not 2/3": (with_(dim=4), "dim"),
    "dt <= 0": (with_(dt=-0.1), "dt"),
    "horizon <= 0": (with_(horizon=0), "horizon"),
    "delta <= 0": (with_(delta=0.0), "delta"),
    "NaN": (with_(kappa=float("nan")), "kappa"),
    "inf in a vector": ({"agents": [{"start": [float("inf"), 0], "goal": [1, 1]}]}, "agents[0].start"),
    "agents closer than delta at start": (
        {"agents": [{"start": [0, 0], "goal": [1, 1]}, {"start": [0.1, 0.1], "goal": [-1, 1]}]}, "agents[1].start"),
    "agents closer than delta at goal": (
        {"agents": [{"start": [0, 0], "goal": [1, 1]}, {"start": [2, 2], "goal": [1.1, 1]}]}, "agents[1].goal"),
    "start inside an obstacle": (
        with_(obstacles=[{"box": {"center": [-1, -1], "half_size": [0.2, 0.2]}}]), "agents[0].start"),
    "goal outside the workspace": (
        {"workspace": {"lower": [-3, -3], "upper": [3, 3]}, "agents": [{"start": [0, 0], "goal": [3.5, 0]}]},
        "agents[0].goal"),
    "empty agent list": ({"agents": []}, "agents"),
    "malformed polytope": (with_(obstacles=[{"polytope": {"G": [[1, 0], [0, 1]], "g": [1]}}]), "obstacles[0]"),
    "hard with d_min 0": (with_(d_min=0), "d_min"),
    "over-relaxation of 2": (with_(solver={"relaxation": 2.0}), "solver.relaxation"),
    "negative reuse tolerance": (with_(solver={"reuse_tol": -1e-4}), "solver.reuse_tol"),
    # (data, field, reason): the reason is a further substring the line must contain
    "goal inside an obstacle": (
        with_(obstacles=[{"box": {"center": [1, 1], "half_size": [0.2, 0.2]}}]), "agents[0].goal",
        "inside obstacles[0]"),
    "goal inside a polytope obstacle": (
        with_(obstacles=[{"box": {"center": [0, 2.5], "half_size": [0.2, 0.2]}},
                         {"polytope": {"G": [[1, 0], [0, 1], [-1, -1]], "g": [1.5, 1.5, -1.5]}}]),
        "agents[0].goal", "inside obstacles[1]"),
    "start outside the workspace": (
        {"workspace": {"lower": [-3, -3], "upper": [3, 3]},
         "agents": [{"start": [0, 0], "goal": [1, 1]}, {"start": [2, -3.5], "goal": [-1, 1]}]},
        "agents[1].start", "outside the workspace"),
    "NaN in a vector": (
        {"agents": [{"start": [-1, -1], "goal": [1, 1]}, {"start": [1, float("nan")], "goal": [-1, 1]}]},
        "agents[1].start", "finite"),
    "NaN in a full state": (
        {"agents": [{"start": [0, 0], "goal": [1, 1, 0, float("nan")]}]}, "agents[0].goal", "finite"),
    "NaN in a weight matrix": (
        with_(weights={"Q": [[0.1, 0, 0, 0], [0, float("nan"), 0, 0], [0, 0, 0.1, 0], [0, 0, 0, 0.1]]}),
        "weights.Q", "finite"),
    "NaN in a polytope G": (
        with_(obstacles=[{"polytope": {"G": [[1, 0], [0, float("nan")]], "g": [3, 3]}}]),
        "obstacles[0].polytope.G", "finite"),
    "a removed solver key": (
        with_(solver={"component_stop": False}), "solver.component_stop", "removed",
        "docs/lab/admm.md#component-stop"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_rejected_with_one_line(case, tmp_path):
    data, field, *reason = CASES[case]
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    out = tmp_path / "out"
    done = run_cli("run", str(path), "--out", str(out), "--quiet", cwd=tmp_path)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr
    assert lines[0].startswith(f"swarmpc: error: {field}"), lines[0]
    for text in reason:
        assert text in lines[0], lines[0]
    assert not out.exists() and not (tmp_path / "results").exists()


@pytest.mark.parametrize(
    "content,needle",
    [("agents: [\n  {start: [0, 0]", "malformed YAML"), (None, "cannot read")],
)
def test_unreadable_files(content, needle, tmp_path):
    path = tmp_path / "s.yaml"
    if content is not None:
        path.write_text(content)
    done = run_cli("run", str(path), "--out", str(tmp_path / "out"), "--quiet")
    assert done.returncode == 2 and needle in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("kind,error", [
    ("invalid UTF-8", "UnicodeDecodeError"),
    ("directory.yaml", "a directory, not a regular file"),  # refused before it is opened
    ("directory", "a directory, not a regular file"),  # no suffix: found because it exists
])
def test_existing_but_unreadable(kind, error, tmp_path):
    """Files that exist but cannot be read (root ignores chmod 000, so bytes and folders instead)."""
    if kind == "invalid UTF-8":
        path = tmp_path / "latin1.yaml"
        path.write_bytes(yaml.safe_dump(BASE).encode() + b"name: caf\xe9 \xff\xfe\n")
    else:
        path = tmp_path / kind
        path.mkdir()
        (path / "scenario.yaml").write_text(yaml.safe_dump(BASE))  # a valid scenario inside
    out = tmp_path / "out"
    done = run_cli("run", str(path), "--out", str(out), "--quiet", cwd=tmp_path)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    assert lines[0] == f"swarmpc: error: {path}: cannot read scenario file ({error})"
    assert not out.exists() and not (tmp_path / "results").exists()


def test_bad_cli_option_value(tmp_path):
    done = run_cli("run", "paper-2d", "--delta", "-1", "--out", str(tmp_path / "o"), "--quiet")
    assert done.returncode == 2 and "delta" in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "o").exists()
