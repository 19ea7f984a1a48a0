"""Regenerate tests/data/pinned-trajectories.npz: ``python tests/data/make_pinned.py OUT.npz``.

Run it only on a commit whose behaviour is meant to change; tests/test_pinned_behaviour.py then
pins the new trajectories."""

import sys

import numpy as np

from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.loop import simulate

CASES = {"paper-2d": ("paper-2d", {}), "paper-3d": ("paper-3d", {}), "wall-door": ("wall-door", {}),
         "random-16": ("random", {"agents": 16, "dim": 3, "seed": 0})}

if __name__ == "__main__":
    arrays = {}
    for key, (name, params) in CASES.items():
        result = simulate(builtin_scenario(name, **params))
        arrays[f"{key}/states"] = result.states
    np.savez_compressed(sys.argv[1], **arrays)
