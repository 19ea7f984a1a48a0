"""swarmpc deletes only what it created: run folders carry a marker, and only such folders are
replaced, only with ``overwrite``; everything else at the output path is refused before the run."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import run_cli
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.loop import simulate
from swarmpc.simulation.outdir import MARKER, OutputError, RunFolderTarget, is_run_folder
from swarmpc.simulation.results import RunResult, write_run


@pytest.fixture(scope="module")
def tiny_run() -> RunResult:
    return simulate(builtin_scenario("paper-2d").with_updates(**{"stop.max_steps": 2}))


def snapshot(root: Path) -> dict[str, str]:
    """Every entry under ``root`` (links not followed): a content hash, 'dir' or the link's target."""
    entries: dict[str, str] = {}
    for folder, dirs, files in os.walk(root):
        for name in dirs + files:
            path = Path(folder) / name
            key = str(path.relative_to(root))
            if path.is_symlink():
                entries[key] = "link:" + os.readlink(path)
            elif path.is_dir():
                entries[key] = "dir"
            else:
                entries[key] = hashlib.sha256(path.read_bytes()).hexdigest()
    return entries


def test_a_written_run_folder_carries_the_marker_last(tmp_path, tiny_run):
    folder = write_run(tiny_run, tmp_path / "run")
    assert is_run_folder(folder)
    assert json.loads((folder / MARKER).read_text())["format"] == "swarmpc-run"
    assert [p.name for p in tmp_path.iterdir()] == ["run"]  # no staging folder left


@pytest.mark.parametrize("make", ["file", "folder", "link-to-folder", "link-to-run", "dangling-link"])
def test_anything_but_a_run_folder_is_refused_and_left_alone(tmp_path, tiny_run, make):
    user = tmp_path / "user"
    user.mkdir()
    (user / "notes.txt").write_text("mine")
    run = write_run(tiny_run, tmp_path / "earlier")
    target = tmp_path / "target"
    {"file": lambda: target.write_text("mine"),
     "folder": lambda: (target.mkdir(), (target / "a.txt").write_text("mine")),
     "link-to-folder": lambda: target.symlink_to(user),
     "link-to-run": lambda: target.symlink_to(run),
     "dangling-link": lambda: target.symlink_to(tmp_path / "nowhere")}[make]()
    before = snapshot(tmp_path)
    for overwrite in (False, True):
        with pytest.raises(OutputError, match="target"):
            write_run(tiny_run, target, overwrite=overwrite)
    assert snapshot(tmp_path) == before


def test_an_earlier_run_is_replaced_only_with_overwrite(tmp_path, tiny_run):
    target = write_run(tiny_run, tmp_path / "run")
    (target / "summary.json").write_text("{}")
    with pytest.raises(OutputError, match="--overwrite"):
        write_run(tiny_run, target)
    assert (target / "summary.json").read_text() == "{}"
    write_run(tiny_run, target, overwrite=True)
    assert json.loads((target / "summary.json").read_text())["steps"] == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_an_empty_folder_is_taken(tmp_path, tiny_run):
    (tmp_path / "empty").mkdir()
    assert is_run_folder(write_run(tiny_run, tmp_path / "empty"))


def test_the_check_comes_before_the_run_and_a_refusal_leaves_no_folders(tmp_path):
    (tmp_path / "file").write_text("mine")
    with pytest.raises(OutputError):
        RunFolderTarget(tmp_path / "file")
    with pytest.raises(OutputError, match="not enough free space"):
        RunFolderTarget(tmp_path / "a" / "b" / "run", expected_bytes=2**62)
    assert [p.name for p in tmp_path.iterdir()] == ["file"]  # the parents it made are gone again


def test_a_failed_write_keeps_the_run_elsewhere_and_says_where(tmp_path, tiny_run):
    def full_disk(_run: RunResult, _folder: Path) -> None:
        raise OSError(28, "No space left on device")

    with pytest.raises(OutputError, match="No space left on device") as error:
        write_run(tiny_run, tmp_path / "run", extra_writers=[full_disk])
    message = str(error.value)
    assert "\n" not in message
    kept = Path(message.rsplit("kept in ", 1)[1])
    try:
        assert is_run_folder(kept)
        with np.load(kept / "trajectory.npz") as data:
            assert np.array_equal(data["states"], tiny_run.states)
    finally:
        import shutil
        shutil.rmtree(kept)
    assert list(tmp_path.iterdir()) == []


def test_summary_json_is_strict_json(tmp_path):
    """A lone agent has no pair: its separation is infinite, written as null, not Infinity."""
    scn = builtin_scenario("paper-2d").model_dump()
    scn["agents"] = scn["agents"][:1]
    scn["stop"]["max_steps"] = 2
    from swarmpc.config import scenario_from_dict

    folder = write_run(simulate(scenario_from_dict(scn)), tmp_path / "run")

    def refuse(constant: str) -> None:
        raise AssertionError(f"{constant} in summary.json")

    summary = json.loads((folder / "summary.json").read_text(), parse_constant=refuse)
    assert summary["min_separation_inf"] is None


TREE = ["a.txt", "docs/b.md", "docs/deep/c.bin", "results/old.txt", "empty/"]


def _build_tree(root: Path, tiny_run: RunResult) -> list[Path]:
    for entry in TREE:
        path = root / entry
        if entry.endswith("/"):
            path.mkdir(parents=True, exist_ok=True)
        else:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(entry * 3)
    write_run(tiny_run, root / "results" / "earlier")
    (root / "link").symlink_to(root / "docs")
    (root / "runlink").symlink_to(root / "results" / "earlier")
    return [root / e.rstrip("/") for e in TREE] + [root / "results", root / "results" / "earlier",
                                                    root / "link", root / "runlink", root, root / "docs" / ".."]


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(choice=st.integers(0, 100), fresh=st.text("abc/.", min_size=1, max_size=8), overwrite=st.booleans(),
       use_fresh=st.booleans())
def test_never_destroys(tmp_path_factory, tiny_run, choice, fresh, overwrite, use_fresh):
    """For an existing tree and any output path: no entry that existed before the write is
    removed or changed unless it lay inside a swarmpc run folder at the target and overwrite was
    given."""
    root = tmp_path_factory.mktemp("tree")
    candidates = _build_tree(root, tiny_run)
    inside = [part for part in Path(fresh).parts if part != ".." and "/" not in part] or ["out"]  # stay in the tree
    target = root.joinpath(*inside) if use_fresh else candidates[choice % len(candidates)]
    before = snapshot(root)
    replaced = is_run_folder(target) and overwrite
    prefix = str(target.resolve().relative_to(root.resolve())) + os.sep if replaced else None
    try:
        write_run(tiny_run, target, overwrite=overwrite)
    except (OutputError, OSError):
        pass
    after = snapshot(root)
    for key, value in before.items():
        if prefix is not None and (key + os.sep).startswith(prefix):
            continue
        assert after.get(key) == value, f"{key} changed writing to {target}"
    assert not [k for k in after if ".partial-" in k or ".old-" in k]


def test_cli_refuses_before_running_and_writes_nothing(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    for out in (".", "notes.txt"):
        done = run_cli("run", "paper-2d", "--out", out, "--max-steps", "2", "-q", cwd=tmp_path)
        lines = done.stderr.strip().splitlines()
        assert done.returncode == 2 and len(lines) == 1 and lines[0].startswith("swarmpc: error:"), done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["notes.txt"]
    assert (tmp_path / "notes.txt").read_text() == "mine"


def test_cli_replaces_its_own_run_only_with_overwrite(tmp_path):
    args = ("run", "paper-2d", "--max-steps", "2", "-q")
    assert run_cli(*args, cwd=tmp_path).returncode == 0
    assert is_run_folder(tmp_path / "results" / "paper-2d")
    again = run_cli(*args, cwd=tmp_path)
    assert again.returncode == 2 and "--overwrite" in again.stderr
    assert run_cli(*args, "--overwrite", cwd=tmp_path).returncode == 0
    assert os.listdir(tmp_path / "results") == ["paper-2d"]


def test_report_commands_keep_to_their_own_folders(tmp_path):
    """bench and reproduce write only into new, empty or their own marked folders; a refused or
    failed command leaves no folder behind."""
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "bench.md").write_text("my notes")
    for args in (("bench", "--quick", "--out", "mine"), ("reproduce", "--quick", "--out", "mine"),
                 ("bench", "--merge", "nothing.json", "--out", "fresh")):
        done = run_cli(*args, cwd=tmp_path)
        assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine"]
    assert (tmp_path / "mine" / "bench.md").read_text() == "my notes"


@pytest.mark.parametrize("command", ["animate", "view"])
def test_a_named_output_file_is_replaced_only_with_overwrite(tmp_path, tiny_run, command):
    folder = write_run(tiny_run, tmp_path / "run")
    (tmp_path / "notes.txt").write_text("mine")
    done = run_cli(command, str(folder), "--out", "notes.txt", cwd=tmp_path)
    assert done.returncode == 2 and "--overwrite" in done.stderr
    assert (tmp_path / "notes.txt").read_text() == "mine"
