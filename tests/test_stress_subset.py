"""A 20-scenario subset of the stress suite (benchmarks/stress.py --small): small seeded random
swarms, 2D mostly, hard and soft, with and without obstacles; each checked from its saved
trajectory: no collision in the hard form, every goal reached, no obstacle entered."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import load_folder, recount_collisions
from swarmpc.config import load_scenario
from swarmpc.model.geometry import obstacle_penetration

pytestmark = pytest.mark.loop  # twenty whole runs

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _stress_module():
    # on sys.path so that the spawned worker processes can import it too
    if str(BENCHMARKS) not in sys.path:
        sys.path.insert(0, str(BENCHMARKS))
    return importlib.import_module("stress")


def test_twenty_small_random_scenarios(tmp_path):
    stress = _stress_module()
    rows = stress.run_suite(20, seed=0, jobs=2, small=True, runs_dir=str(tmp_path), progress=False)
    assert len(rows) == 20
    assert {r["collision"] for r in rows} == {"hard", "soft"}
    assert any(r["obstacles"] for r in rows) and any(not r["obstacles"] for r in rows)
    for row in rows:
        folder = tmp_path / row["name"]
        summary, arrays = load_folder(folder)
        scn = load_scenario(folder / "scenario.yaml")
        states = arrays["states"]
        collisions, _ratio = recount_collisions(states, arrays["delta"])
        if scn.collision == "hard":
            assert collisions == 0, row["name"]
        assert summary["collisions"] == collisions
        d = scn.dim
        final = np.linalg.norm(states[-1, :, :d] - arrays["goals"][:, :d], axis=1)
        assert np.all(final <= scn.stop.goal_tolerance + 1e-9), (row["name"], final.max())
        for G, g in scn.obstacle_halfspaces():
            assert obstacle_penetration(states[:, :, :d], G, g).max() <= 1e-9, row["name"]
