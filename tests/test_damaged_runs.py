"""Damaged run folders and benchmark reports: every reader answers with one line naming the file.

One real run folder is written once (a few ADMM steps of ``paper-2d``); each case copies it and
damages one file the way a disk, a copy or a hand edit can (truncated or corrupt archives, an
``.npy`` header that claims a huge array, wrong shapes, NaN, broken YAML or JSON, a directory or
a symlink where a file belongs). The Python reader must raise :class:`RunDataError` with one line
naming the file; ``swarmpc plot``, ``animate`` and ``view`` (and ``bench --merge`` for a damaged
``bench.json``) must exit with status 2 and print exactly one ``swarmpc: error:`` line.
"""

from __future__ import annotations

import io
import json
import os
import shutil
import struct
import subprocess
import sys
import time
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from swarmpc import plots, viewer
from swarmpc.bench import BenchCase, CaseOutcome, merge_reports, write_report
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.loop import StopFlag, simulate
from swarmpc.simulation.results import write_run
from swarmpc.simulation.rundata import MissingRunFileError, RunDataError, load_run

SWARMPC = Path(sys.executable).with_name("swarmpc")
OUTPUTS = {"plot": "trajectory.png", "animate": "animation.gif", "view": "view.html"}


# ------------------------------------------------------------------------------------ run folders
def _scenario():
    return builtin_scenario("paper-2d").with_updates(**{"stop.max_steps": 5})


@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    """A real run folder: 5 ADMM steps of paper-2d (4 agents), as ``write_run`` writes it."""
    return write_run(simulate(_scenario()), tmp_path_factory.mktemp("runs") / "pristine")


@pytest.fixture(scope="module")
def zero_steps(tmp_path_factory) -> Path:
    """A real run stopped before its first step: one state, no inputs, empty records."""
    stop = StopFlag()
    stop.requested = True
    return write_run(simulate(_scenario(), stop_flag=stop), tmp_path_factory.mktemp("runs") / "zero")


def _edit_npz(folder: Path, name: str, edit: Callable[[dict[str, np.ndarray]], None]) -> str:
    """Rewrite archive ``name`` of ``folder`` with ``edit`` applied to its arrays."""
    with np.load(folder / name) as data:
        arrays = {key: data[key] for key in data.files}
    edit(arrays)
    np.savez_compressed(folder / name, **arrays)
    return name


def _set(**changes: np.ndarray | Callable[[np.ndarray], np.ndarray]) -> Callable[[dict[str, np.ndarray]], None]:
    """An edit that replaces arrays (by value, or by a function of the old one)."""
    def edit(arrays: dict[str, np.ndarray]) -> None:
        for key, change in changes.items():
            arrays[key] = change(arrays[key]) if callable(change) else change
    return edit


def _with_nan(index: tuple[int, ...], value: float = np.nan) -> Callable[[np.ndarray], np.ndarray]:
    def change(array: np.ndarray) -> np.ndarray:
        array = array.astype(float)
        array[index] = value
        return array
    return change


def _npy_bytes(shape: tuple[int, ...], payload: bytes) -> bytes:
    """A hand-written ``.npy`` member: a float64 header claiming ``shape``, then ``payload``."""
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": "<f8", "fortran_order": False, "shape": shape})
    return buffer.getvalue() + payload


def _replace_member(folder: Path, name: str, member: str, data: bytes) -> str:
    """Rewrite archive ``name`` with member ``member`` replaced by raw ``data``."""
    path = folder / name
    with zipfile.ZipFile(path) as archive:
        members = {info.filename: archive.read(info) for info in archive.infolist()}
    members[member] = data
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as archive:
        for filename, raw in members.items():
            archive.writestr(filename, raw)
    return name


def _flip_compressed_bytes(folder: Path) -> str:
    """Invert 8 bytes inside the deflate stream of ``states.npy`` in ``trajectory.npz``."""
    path = folder / "trajectory.npz"
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo("states.npy")
    raw = bytearray(path.read_bytes())
    name_len, extra_len = struct.unpack("<HH", raw[info.header_offset + 26 : info.header_offset + 30])
    start = info.header_offset + 30 + name_len + extra_len + info.compress_size // 3
    for i in range(start, start + 8):
        raw[i] ^= 0xFF
    path.write_bytes(bytes(raw))
    return "trajectory.npz"


def _truncate(folder: Path, name: str) -> str:
    path = folder / name
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    return name


def _write(folder: Path, name: str, content: str | bytes) -> str:
    path = folder / name
    path.write_bytes(content.encode() if isinstance(content, str) else content)
    return name


def _directory(folder: Path, name: str) -> str:
    (folder / name).unlink()
    (folder / name).mkdir()
    return name


def _symlink(folder: Path, name: str, target: str) -> str:
    (folder / name).unlink()
    (folder / name).symlink_to(target)
    return name


def _remove(folder: Path, name: str) -> str:
    (folder / name).unlink()
    return name


def _fifo(folder: Path, name: str) -> str:
    (folder / name).unlink()
    os.mkfifo(folder / name)  # reading it would block forever
    return name


def _edit_text(folder: Path, name: str, old: str, new: str) -> str:
    path = folder / name
    text = path.read_text()
    assert old in text
    path.write_text(text.replace(old, new, 1))
    return name


_LAUGHS = "a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1]\n" + "".join(
    f"{chr(98 + n)}: &{chr(98 + n)} [{', '.join(['*' + chr(97 + n)] * 9)}]\n" for n in range(8)
)

T = "trajectory.npz"
DAMAGES: dict[str, Callable[[Path], str]] = {
    # the file system
    "missing trajectory": lambda f: _remove(f, T),
    "missing scenario": lambda f: _remove(f, "scenario.yaml"),
    "trajectory is a directory": lambda f: _directory(f, T),
    "summary is a directory": lambda f: _directory(f, "summary.json"),
    "dangling symlink": lambda f: _symlink(f, T, "nowhere.npz"),
    "symlink to /dev/zero": lambda f: _symlink(f, "admm.npz", "/dev/zero"),
    "scenario is a fifo": lambda f: _fifo(f, "scenario.yaml"),
    # the archive
    "not a zip": lambda f: _write(f, T, b"this is not an npz archive\n"),
    "truncated archive": lambda f: _truncate(f, T),
    "flipped compressed bytes": _flip_compressed_bytes,
    "header claims 8 TB": lambda f: _replace_member(f, T, "states.npy", _npy_bytes((10**12,), b"\0" * 16)),
    "header claims more than the member": lambda f: _replace_member(
        f, T, "states.npy", _npy_bytes((6, 4, 4 * 1000), b"\0" * 16)),
    "object array": lambda f: _replace_member(
        f, T, "states.npy", _pickled_npy()),
    "truncated steps archive": lambda f: _truncate(f, "steps.npz"),
    "garbage admm archive": lambda f: _write(f, "admm.npz", b"PK\x03\x04" + b"\0" * 40),
    # shapes
    "no states array": lambda f: _edit_npz(f, T, lambda a: a.pop("states")),
    "states 2-D": lambda f: _edit_npz(f, T, _set(states=lambda s: s[:, :, 0])),
    "states of 3-D agents": lambda f: _edit_npz(f, T, _set(states=lambda s: np.zeros((6, 4, 6)))),
    "states of 3 agents": lambda f: _edit_npz(f, T, _set(states=lambda s: s[:, :3])),
    "no states at all": lambda f: _edit_npz(f, T, _set(states=lambda s: s[:0])),
    "inputs too short": lambda f: _edit_npz(f, T, _set(inputs=lambda u: u[:-1])),
    "t too long": lambda f: _edit_npz(f, T, _set(t=lambda t: np.append(t, 9.0))),
    "goals of 2 agents": lambda f: _edit_npz(f, T, _set(goals=lambda g: g[:2])),
    "delta of 5 values": lambda f: _edit_npz(f, T, _set(delta=np.ones(5))),
    "steps with a row too many": lambda f: _edit_npz(
        f, "steps.npz", _set(step_time_s=lambda s: np.append(s, 1.0))),
    "admm with rows missing": lambda f: _edit_npz(f, "admm.npz", _set(primal=lambda p: p[:2], dual=lambda d: d[:2])),
    # values
    "NaN state": lambda f: _edit_npz(f, T, _set(states=_with_nan((3, 1, 0)))),
    "infinite input": lambda f: _edit_npz(f, T, _set(inputs=_with_nan((2, 0, 1), np.inf))),
    "NaN time": lambda f: _edit_npz(f, T, _set(t=_with_nan((4,)))),
    "dt of zero": lambda f: _edit_npz(f, T, _set(dt=np.float64(0.0))),
    "negative delta": lambda f: _edit_npz(f, T, _set(delta=np.float64(-0.3))),
    # scenario.yaml
    "scenario malformed YAML": lambda f: _write(f, "scenario.yaml", "name: [unclosed\n"),
    "scenario invalid field": lambda f: _edit_text(f, "scenario.yaml", "dt: 0.1", "dt: -1.0"),
    "scenario not a mapping": lambda f: _write(f, "scenario.yaml", "- 1\n- 2\n"),
    "scenario alias bomb": lambda f: _write(f, "scenario.yaml", _LAUGHS + "name: *i\n"),
    "scenario not UTF-8": lambda f: _write(f, "scenario.yaml", b"name: \xff\xfe\n"),
    # summary.json
    "summary not JSON": lambda f: _write(f, "summary.json", "{'scenario': oops"),
    "summary not an object": lambda f: _write(f, "summary.json", "[1, 2, 3]"),
    "summary bad tolerance": lambda f: _write(f, "summary.json", '{"admm_tol": "tight"}'),
}


def _pickled_npy() -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, np.array([{"payload": 1}], dtype=object), allow_pickle=True)
    return buffer.getvalue()


@pytest.fixture
def damage(pristine: Path, tmp_path: Path) -> Callable[[str], tuple[Path, str]]:
    """Copy the pristine run and apply a named damage; return (folder, damaged file name)."""
    def apply(kind: str) -> tuple[Path, str]:
        folder = shutil.copytree(pristine, tmp_path / "run")
        return folder, DAMAGES[kind](folder)
    return apply


def _assert_one_line_naming(message: str, name: str) -> None:
    assert "\n" not in message and message.strip() == message, message
    assert name in message, message


# ------------------------------------------------------------------------------------ the reader
def test_the_pristine_run_reads_back(pristine: Path) -> None:
    run = load_run(pristine)
    assert run.num_steps == 5 and run.num_agents == 4 and run.dim == 2 and run.name == "paper-2d"
    assert run.admm is not None and run.admm.primal.shape[0] == 5 and run.admm.copies.shape == (5, 4)
    assert run.steps["fallback"].shape == (5, 4) and run.steps["fallback"].dtype == bool
    for array in (run.states, run.t, run.admm.primal, run.steps["step_time_s"]):
        assert not array.flags.writeable
    assert plots.load_run is load_run and plots.RunDataError is RunDataError  # one reader


@pytest.mark.parametrize("kind", list(DAMAGES))
def test_a_damaged_run_is_one_line_naming_the_file(kind: str, damage) -> None:
    folder, name = damage(kind)
    started = time.perf_counter()
    with pytest.raises(RunDataError) as info:
        load_run(folder)
    assert time.perf_counter() - started < 5.0  # refused, not read or allocated
    _assert_one_line_naming(str(info.value), name)
    assert str(folder) in str(info.value)
    if kind.startswith("missing") or kind == "dangling symlink":
        assert isinstance(info.value, MissingRunFileError) and isinstance(info.value, FileNotFoundError)
    if kind == "missing scenario":  # the viewer draws a folder without its scenario
        assert viewer.load_run(folder).scenario is None
    else:
        with pytest.raises(RunDataError) as seen_by_viewer:
            viewer.load_run(folder)
        assert str(seen_by_viewer.value) == str(info.value)


@pytest.mark.parametrize(("kind", "words"), [
    ("header claims 8 TB", "more than the 1 GiB"),
    ("header claims more than the member", "holds 16 bytes"),
    ("object array", "pickles are never loaded"),
    ("scenario invalid field", "dt"),
    ("NaN state", "'states' holds NaN"),
    ("trajectory is a directory", "is a directory"),
])
def test_the_line_says_what_is_wrong(kind: str, words: str, damage) -> None:
    folder, _name = damage(kind)
    with pytest.raises(RunDataError, match=words):
        load_run(folder)


def test_a_symlinked_file_is_followed(pristine: Path, tmp_path: Path) -> None:
    folder = shutil.copytree(pristine, tmp_path / "run")
    (folder / "trajectory.npz").rename(tmp_path / "elsewhere.npz")
    (folder / "trajectory.npz").symlink_to(tmp_path / "elsewhere.npz")
    assert load_run(folder).num_steps == 5


def test_zero_steps_read_as_the_initial_state(zero_steps: Path) -> None:
    run = load_run(zero_steps)
    assert run.num_steps == 0 and run.states.shape == (1, 4, 4) and run.inputs.shape == (0, 4, 2)
    assert run.admm is not None and run.admm.primal.shape[0] == 0 and run.steps["fallback"].shape == (0, 4)


def test_a_bare_folder_needs_what_the_scenario_would_give(pristine: Path, tmp_path: Path) -> None:
    folder = tmp_path / "bare"
    folder.mkdir()
    with np.load(pristine / "trajectory.npz") as data:
        np.savez(folder / "trajectory.npz", states=data["states"], dt=data["dt"])
    with pytest.raises(RunDataError, match="missing array 'goals'"):
        viewer.load_run(folder)


# ------------------------------------------------------------------------------------ the commands
def _swarmpc(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(SWARMPC), *args], capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize(("command", "kind"), [
    ("plot", "missing trajectory"),
    ("plot", "trajectory is a directory"),
    ("plot", "truncated archive"),
    ("plot", "header claims 8 TB"),
    ("plot", "states of 3 agents"),
    ("plot", "NaN state"),
    ("plot", "scenario invalid field"),
    ("plot", "summary not JSON"),
    ("animate", "flipped compressed bytes"),
    ("animate", "inputs too short"),
    ("animate", "scenario alias bomb"),
    ("view", "object array"),
    ("view", "admm with rows missing"),
    ("view", "infinite input"),
    ("view", "scenario malformed YAML"),
    ("view", "summary not an object"),
])
def test_the_commands_print_one_line_and_exit_2(command: str, kind: str, damage) -> None:
    folder, name = damage(kind)
    done = _swarmpc(command, str(folder))
    assert done.returncode == 2, done.stderr[-2000:]
    assert "Traceback" not in done.stderr and done.stdout == ""
    (line,) = done.stderr.strip().splitlines()
    assert line.startswith("swarmpc: error: ") and name in line, line
    assert not (folder / OUTPUTS[command]).exists()


@pytest.mark.parametrize("command", list(OUTPUTS))
def test_the_commands_draw_a_run_of_zero_steps(command: str, zero_steps: Path, tmp_path: Path) -> None:
    folder = shutil.copytree(zero_steps, tmp_path / "zero")
    done = _swarmpc(command, str(folder))
    assert done.returncode == 0, done.stderr[-2000:]
    assert (folder / OUTPUTS[command]).is_file()


# ------------------------------------------------------------------------------------ bench.json
def _report(folder: Path) -> Path:
    outcome = CaseOutcome(
        case=BenchCase("random", 4, 0, "admm"), steps=2, timed_out=False, all_reached=True, collisions=0,
        min_separation_ratio=1.5, time_to_goal_s=0.2, cost=3.0, step_ms=[10.0, 12.0], agent_step_ms=[2.0] * 8,
        iterations=[3, 4], solver_failures=0, wall_time_s=1.0,
    )
    _markdown, path = write_report(folder, [outcome], "test machine", 1.0)
    return path


def _edit_report(path: Path, edit: Callable[[dict], None]) -> None:
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))  # NaN is written as the bare token NaN, as json.dumps does


REPORT_DAMAGES: dict[str, Callable[[Path], None]] = {
    "not JSON": lambda p: p.write_text('{"runs": [}'),
    "not an object": lambda p: p.write_text("[]"),
    "runs not a list": lambda p: _edit_report(p, lambda d: d.update(runs={"a": 1})),
    "a run without its cost": lambda p: _edit_report(p, lambda d: d["runs"][0].pop("cost")),
    "NaN step time": lambda p: _edit_report(p, lambda d: d["runs"][0]["step_ms"].append(float("nan"))),
    "unknown family": lambda p: _edit_report(p, lambda d: d["runs"][0]["case"].update(family="blob")),
    "unhashable case": lambda p: _edit_report(p, lambda d: d["runs"][0]["case"].update(workers=[1])),
    "elapsed as a list": lambda p: _edit_report(p, lambda d: d.update(elapsed_s=[1])),
    "a directory": lambda p: (p.unlink(), p.mkdir()),
}


@pytest.mark.parametrize("kind", list(REPORT_DAMAGES))
def test_merging_a_damaged_report_is_one_line_naming_it(kind: str, tmp_path: Path) -> None:
    path = _report(tmp_path / "a")
    REPORT_DAMAGES[kind](path)
    with pytest.raises(ValueError) as info:
        merge_reports([tmp_path / "a" if kind != "a directory" else path], tmp_path / "merged")
    _assert_one_line_naming(str(info.value), "bench.json")
    assert not (tmp_path / "merged").exists()


@pytest.mark.parametrize("kind", ["NaN step time", "runs not a list"])
def test_bench_merge_command_on_a_damaged_report(kind: str, tmp_path: Path) -> None:
    path = _report(tmp_path / "a")
    REPORT_DAMAGES[kind](path)
    done = _swarmpc("bench", "--merge", str(path), "--out", str(tmp_path / "merged"))
    assert done.returncode == 2 and "Traceback" not in done.stderr
    (line,) = done.stderr.strip().splitlines()
    assert line.startswith("swarmpc: error: --merge: ") and str(path) in line, line
    assert not (tmp_path / "merged").exists()
