"""``swarmpc run --executor/--workers/--address``: where the ADMM local solves run never changes
the run (same states as serial, bit for bit, as tests/test_executors.py asserts per plan), and a
bad choice is one line naming the option, exit status 2, no output folder."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import load_folder, run_cli

STEPS = 12


def run_folder(tmp_path: Path, name: str, *args: str) -> tuple[dict, dict]:
    out = tmp_path / name
    done = run_cli("run", "paper-2d", "--out", str(out), "--quiet", *args, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "Traceback" not in done.stderr, done.stderr[-3000:]
    return load_folder(out)


@pytest.fixture(scope="module")
def serial_run(tmp_path_factory):
    return run_folder(tmp_path_factory.mktemp("serial"), "serial", "--max-steps", str(STEPS), "--executor", "serial")


@pytest.mark.loop
def test_process_executor_matches_serial(serial_run, tmp_path):
    summary, arrays = run_folder(tmp_path, "process", "--max-steps", str(STEPS), "--executor", "process",
                                 "--workers", "2")
    reference_summary, reference = serial_run
    assert reference["states"].shape[0] == STEPS + 1  # the scenario does not finish early here
    assert np.array_equal(arrays["states"], reference["states"])
    assert np.array_equal(arrays["inputs"], reference["inputs"])
    assert summary["executor"] == "process" and reference_summary["executor"] == "serial"


@pytest.mark.skipif(importlib.util.find_spec("ray") is None,
                    reason="Ray is not installed (pip install 'swarmpc[ray]')")
@pytest.mark.loop
def test_ray_executor_matches_serial(serial_run, tmp_path):
    summary, arrays = run_folder(tmp_path, "ray", "--max-steps", "6", "--executor", "ray", "--workers", "2")
    # --max-steps only ends the loop: a 6-step run is the first 7 states of the 12-step one
    _, reference = serial_run
    assert np.array_equal(arrays["states"], reference["states"][:7])
    assert summary["executor"] == "ray"


BAD = {
    "unknown executor": (["--executor", "foo"], "--executor"),
    "zero workers": (["--executor", "process", "--workers", "0"], "--workers"),
    "workers without a parallel executor": (["--workers", "2"], "--workers"),
    "address without ray": (["--address", "auto"], "--address"),
    "address with process": (["--executor", "process", "--address", "auto"], "--address"),
    "executor with the centralised solver": (["--method", "centralized", "--executor", "process"], "--executor"),
}


def assert_rejected(done: subprocess.CompletedProcess, option: str, tmp_path: Path) -> str:
    assert done.returncode == 2, done.stderr[-3000:]
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr[-3000:]
    assert lines[0].startswith("swarmpc: error: ") and option in lines[0], lines[0]
    assert not (tmp_path / "out").exists() and not (tmp_path / "results").exists()
    return lines[0]


@pytest.mark.parametrize("case", list(BAD))
def test_bad_executor_options(case, tmp_path):
    args, option = BAD[case]
    done = run_cli("run", "paper-2d", "--max-steps", "2", "--out", str(tmp_path / "out"), "--quiet", *args,
                   cwd=tmp_path)
    assert_rejected(done, option, tmp_path)


def test_ray_missing_says_how_to_install(tmp_path):
    stub = tmp_path / "stub" / "ray"
    stub.mkdir(parents=True)
    (stub / "__init__.py").write_text('raise ImportError("No module named \'ray\' (test stub)")\n')
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(stub.parent), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run(
        [sys.executable, "-m", "swarmpc", "run", "paper-2d", "--max-steps", "2", "--out", str(tmp_path / "out"),
         "--quiet", "--executor", "ray"],
        capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300,
    )
    line = assert_rejected(done, "--executor", tmp_path)
    assert "pip install 'swarmpc[ray]'" in line
