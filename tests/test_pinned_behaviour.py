"""Closed-loop behaviour pinned: four whole runs must give the trajectories recorded in
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
CASES = {"paper-2d": ("paper-2d", {}), "paper-3d": ("paper-3d", {}), "wall-door": ("wall-door", {}),
         "random-16": ("random", {"agents": 16, "dim": 3, "seed": 0})}
TOLERANCE = 1e-9
"""Bit for bit on the machine that recorded them; a hair of slack for another CPU's rounding in
the linear algebra underneath IPOPT."""


@pytest.mark.parametrize("case", list(CASES))
def test_trajectories_are_unchanged(case):
    name, params = CASES[case]
    result = simulate(builtin_scenario(name, **params))
    with np.load(PINNED) as pinned:
        states = pinned[f"{case}/states"]
    assert result.states.shape == states.shape, "the run took a different number of steps"
    assert np.max(np.abs(result.states - states)) <= TOLERANCE
