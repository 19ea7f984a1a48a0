"""Closed-loop behaviour pinned: four whole runs, each with either local step, must give the trajectories recorded in
tests/data/pinned-trajectories.npz (made by tests/data/make_pinned.py). A refactor that changes a
single state of these runs fails here (the inputs follow from the states through the dynamics); a
change meant to alter behaviour regenerates the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.loop import simulate

pytestmark = pytest.mark.loop  # four whole runs

PINNED = Path(__file__).parent / "data" / "pinned-trajectories.npz"
RUNS = {"paper-2d": ("paper-2d", {}), "paper-3d": ("paper-3d", {}), "wall-door": ("wall-door", {}),
        "random-16": ("random", {"agents": 16, "dim": 3, "seed": 0})}
PAPER = {"solver.local": "ipopt", "solver.admm.independent_first": False}
CASES = {**{key: (name, params, PAPER) for key, (name, params) in RUNS.items()},
         **{f"{key}-qp": (name, params, {}) for key, (name, params) in RUNS.items()}}
"""Each run with the paper's algorithm (the IPOPT local step, every step iterated) and with the
defaults (the QP local step, the probe of the agents' own optima)."""
TOLERANCE = 1e-9
"""Bit for bit on the machine that recorded them; a hair of slack for another CPU's rounding in
the linear algebra underneath IPOPT."""


@pytest.mark.parametrize("case", list(CASES))
def test_trajectories_are_unchanged(case):
    """The run matches one of the case's stored trajectories: the recorded one, or a variant
    recorded on a CPU whose kernels round differently (``make_pinned.py --add-variant``), since
    the closed loop feeds a last-bit difference back until the runs part."""
    name, params, updates = CASES[case]
    result = simulate(builtin_scenario(name, **params).with_updates(**updates))
    with np.load(PINNED) as pinned:
        stored = [pinned[key] for key in pinned.files if key.split("~")[0] == f"{case}/states"]
    assert stored and any(s.shape == result.states.shape for s in stored), "the run took a different number of steps"
    gaps = [np.max(np.abs(result.states - s)) for s in stored if s.shape == result.states.shape]
    assert min(gaps) <= TOLERANCE, f"largest state difference {min(gaps):.3g} from the closest stored run"
