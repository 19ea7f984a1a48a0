"""Regenerate tests/data/pinned-trajectories.npz: ``python tests/data/make_pinned.py OUT.npz``.

Run it only on a commit whose behaviour is meant to change; tests/test_pinned_behaviour.py then
pins the new trajectories.

``python tests/data/make_pinned.py --add-variant PINNED.npz`` keeps what PINNED.npz holds and adds,
for every case whose run on this machine matches none of its stored trajectories, this machine's
as one more variant (``CASE/states~N``). Runs of an unchanged commit differ between CPUs whose
linear-algebra kernels round differently (IPOPT's and OSQP's arithmetic feeds back through the
closed loop); use it only on a commit whose pinned test passes on the machine that recorded the
file, so that a variant records rounding, not a change of behaviour."""

import sys

import numpy as np

from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.loop import simulate

RUNS = {"paper-2d": ("paper-2d", {}), "paper-3d": ("paper-3d", {}), "wall-door": ("wall-door", {}),
        "random-16": ("random", {"agents": 16, "dim": 3, "seed": 0})}
PAPER = {"solver.local": "ipopt", "solver.admm.independent_first": False}
CASES = {**{key: (name, params, PAPER) for key, (name, params) in RUNS.items()},
         **{f"{key}-qp": (name, params, {}) for key, (name, params) in RUNS.items()}}
"""Each run with the paper's algorithm (the IPOPT local step, every step iterated) and with the
defaults (the QP local step, the probe of the agents' own optima)."""
TOLERANCE = 1e-9


def variants(pinned: dict[str, np.ndarray], key: str) -> list[np.ndarray]:
    """Every stored trajectory of case ``key``."""
    return [array for name, array in pinned.items() if name.split("~")[0] == f"{key}/states"]


def matches(states: np.ndarray, stored: list[np.ndarray]) -> bool:
    return any(s.shape == states.shape and np.max(np.abs(s - states)) <= TOLERANCE for s in stored)


if __name__ == "__main__":
    add = sys.argv[1] == "--add-variant"
    path = sys.argv[-1]
    arrays: dict[str, np.ndarray] = {}
    if add:
        with np.load(path) as stored:
            arrays = {name: stored[name] for name in stored.files}
    for key, (name, params, updates) in CASES.items():
        states = simulate(builtin_scenario(name, **params).with_updates(**updates)).states
        if not add:
            arrays[f"{key}/states"] = states
        elif not matches(states, variants(arrays, key)):
            arrays[f"{key}/states~{len(variants(arrays, key))}"] = states
            print(f"{key}: added variant {len(variants(arrays, key)) - 1}")
    np.savez_compressed(path, **arrays)
