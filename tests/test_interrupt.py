"""Ctrl-C mid-run leaves either nothing or a complete run folder marked as interrupted."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import numpy as np


def test_sigint_gives_a_complete_interrupted_folder(tmp_path):
    out = tmp_path / "run"
    process = subprocess.Popen(
        [sys.executable, "-m", "swarmpc", "run", "paper-2d",
         "--max-steps", "100000", "--out", str(out), "--quiet"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    time.sleep(6.0)  # imports, solver build and some steps
    assert process.poll() is None, process.communicate()
    process.send_signal(signal.SIGINT)
    _stdout, stderr = process.communicate(timeout=120)
    assert process.returncode == 0, stderr
    assert "Traceback" not in stderr
    leftovers = [p.name for p in tmp_path.iterdir() if p.name != "run"]
    assert leftovers == []  # no half-written staging folder
    summary = json.loads((out / "summary.json").read_text())
    assert summary["interrupted"] is True
    with np.load(out / "trajectory.npz") as data:
        states, inputs = data["states"], data["inputs"]
    assert summary["steps"] == inputs.shape[0] == states.shape[0] - 1 >= 1
