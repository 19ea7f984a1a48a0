"""Regenerate tests/data/elastic-repair-call.npz: ``python tests/data/make_elastic_case.py OUT.npz``.

Flies the first 15 steps of the bench's random 3D case (M = 64, seed 0, QP local step) and keeps
the smallest repair call (neighbours' plans held fixed) whose hard certificate loops failed and
that the elastic phase answered: its parameters (``p:`` keys), the pinned copies (``f:`` keys) and
the failed loop's last plan (``failed_X``), from which the hard loop fails again.
tests/test_elastic_repair.py poses that call to the QP local step.
"""

import sys
from typing import Any

import numpy as np

from swarmpc.bench import BenchCase
from swarmpc.simulation.loop import simulate
from swarmpc.solvers.admm import ladders


def main(out: str) -> None:
    found: list[dict[str, Any]] = []
    elastic = ladders.QPLocalSolverLadder._elastic

    def recorded(self: Any, params: Any, failed: Any, fixed: Any, copies: int, planes: int) -> Any:
        answer = elastic(self, params, failed, fixed, copies, planes)
        if answer[0] is not None and planes == 0:
            found.append({"copies": copies, **{f"p:{k}": np.asarray(v, float) for k, v in params.items()},
                          **{f"f:{k}": np.asarray(v, float) for k, v in fixed.items()},
                          "failed_X": np.asarray(failed.x["X"], float)})
        return answer

    ladders.QPLocalSolverLadder._elastic = recorded  # type: ignore[method-assign]
    simulate(BenchCase(family="random", agents=64, seed=0, local="qp", max_steps=15).scenario())
    smallest = min(found, key=lambda case: case["copies"])
    np.savez_compressed(out, **smallest)


if __name__ == "__main__":
    main(sys.argv[1])
