"""Shared helpers: run folders produced through the real command line, and independent checks."""

from __future__ import annotations

import contextlib
import io
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np


def run_cli(*args: str, cwd: Path | None = None, timeout: float = 900) -> subprocess.CompletedProcess:
    """``python -m swarmpc ARGS`` in a subprocess, as a user would run it."""
    return subprocess.run(
        [sys.executable, "-m", "swarmpc", *args], capture_output=True, text=True, cwd=cwd, timeout=timeout
    )


def load_folder(folder: Path) -> tuple[dict, dict]:
    summary = json.loads((folder / "summary.json").read_text())
    with np.load(folder / "trajectory.npz") as data:
        arrays = {key: data[key] for key in data.files}
    return summary, arrays


def recount_collisions(states: np.ndarray, delta: np.ndarray) -> tuple[int, float]:
    """Collisions and the min separation ratio, by brute force over every pair and instant."""
    d = states.shape[2] // 2
    delta = np.broadcast_to(np.asarray(delta, float), (d,))
    count, worst = 0, np.inf
    for i in range(states.shape[1]):
        for j in range(i + 1, states.shape[1]):
            ratio = np.max(np.abs(states[:, i, :d] - states[:, j, :d]) / delta, axis=1)
            count += int(np.sum(ratio < 1 - 1e-9))
            worst = min(worst, float(ratio.min()))
    return count, worst


def dynamics_error(states: np.ndarray, inputs: np.ndarray, dt: float, method: str = "euler") -> float:
    """Largest deviation of the saved states from the double integrator, written out by hand.

    ``euler``: p' = p + dt v (the paper); ``zoh``: p' = p + dt v + dt^2/2 u (exact for an input
    held over the step). Both: v' = v + dt u.
    """
    d = inputs.shape[2]
    p, v = states[:-1, :, :d], states[:-1, :, d:]
    if method == "euler":
        position = p + dt * v
    elif method == "zoh":
        position = p + dt * v + 0.5 * dt * dt * inputs
    else:
        raise ValueError(f"unknown discretisation {method!r}")
    predicted = np.concatenate([position, v + dt * inputs], axis=2)
    return float(np.max(np.abs(predicted - states[1:])))


class ScriptedExecutor:
    """Stands in for the agents: ``respond(request)`` returns each LocalResult."""

    def __init__(self, respond):
        self.respond = respond
        self.requests = []

    def start(self, factory, agent_ids):
        pass

    def solve(self, requests):
        self.requests.extend(requests)
        return [self.respond(r) for r in requests]

    def close(self):
        pass


def cli_in_process(*args: str) -> tuple[object, str]:
    """``swarmpc ARGS`` through the console entry point, in this process: the imports (and CasADi's
    compiled functions) are shared between calls, so a short run costs a fraction of a second
    instead of a fresh interpreter. Returns (exit status, stderr); an exception escaping the entry
    point (what a user would see as a traceback) fails the test."""
    from swarmpc.cli import main

    stderr = io.StringIO()
    argv = sys.argv
    sys.argv = ["swarmpc", *args]
    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(stderr):
            try:
                main()
            except SystemExit as done:
                code = done.code
            else:  # pragma: no cover - main() always exits
                code = 0
    finally:
        sys.argv = argv
    return code, stderr.getvalue()


def one_car_scenario(obstacles: list[dict[str, Any]], horizon: int, start: list[float] | None = None,
                     goal: list[float] | None = None, **changes: Any) -> Any:
    """One car, by default from [-2, 0] heading +x to [2, 0] heading +x, among ``obstacles``, with
    RRT guesses, accel and speed limits of 1 and a horizon of ``horizon`` steps of 0.1 s;
    ``changes``: top-level keys to replace."""
    from swarmpc.config import scenario_from_dict

    data: dict[str, Any] = {
        "name": "one-car", "dim": 2, "dt": 0.1, "horizon": horizon, "seed": 3,
        "weights": {"Q": 1.0, "R": 1.0, "Qf": 20.0},
        "solver": {"method": "centralized", "initial_guess": "rrt"},
        "limits": {"accel": 1.0, "speed": 1.0},
        "workspace": {"lower": [-3.0, -2.5], "upper": [3.0, 2.5]},
        "obstacles": obstacles,
        "agents": [{"model": "car", "start": start or [-2.0, 0.0, 0.0], "goal": goal or [2.0, 0.0, 0.0]}],
    }
    data.update(changes)
    return scenario_from_dict(data)
