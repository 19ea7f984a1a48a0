"""Pairs whose plans overlap after a step's safety passes, in one random 3D case of the bench family.

Flies the case (default weights, QP local step, optionally under a deadline) with the ADMM
solver's safety passes (``Repair.make_safe``) wrapped: after each pass, every pair of agents whose
bodies overlap (|p_i - p_j| < b_i + b_j on every axis) at some constrained step of their plans is
printed with the step of the horizon, whether the pair is coupled, and each agent's success and
fallback flags. A collision in the closed loop starts as such a pair; the passes' guarantee says
there is none whenever the solves succeed.

    .venv/bin/python benchmarks/plan_overlap_probe.py --agents 64 --seed 9 --deadline 0.1
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np


def overlapping_pairs(
    bodies: np.ndarray, results: list[Any], neighbours: tuple[tuple[int, ...], ...],
) -> list[dict[str, Any]]:
    """Every pair (i < j) whose own plans' bodies overlap at a constrained step: its first such step
    and the pair's coupling, success and fallback flags."""
    own = np.array([r.own for r in results])  # (M, d, K)
    half = bodies[:, None] + bodies[None]  # (M, M, d)
    gap = np.abs(own[:, None] - own[None])  # (M, M, d, K)
    hit = np.all(gap < half[..., None], axis=2)  # (M, M, K)
    rows = []
    for i, j in zip(*np.nonzero(np.triu(hit.any(axis=2), 1)), strict=True):
        i, j = int(i), int(j)
        rows.append({"pair": (i, j), "step": int(np.argmax(hit[i, j])), "coupled": j in neighbours[i],
                     "success": (results[i].success, results[j].success),
                     "fallback": (results[i].fallback, results[j].fallback)})
    return rows


SUMMARY_KEYS = ("collisions", "min_separation_ratio", "all_reached", "cost", "deadline_misses", "makespan_s")
"""The run's ``summary.json`` entries the ``--json`` line carries."""


def probe(agents: int, seed: int, deadline: float | None, as_json: bool = False) -> int:
    """Fly the case, printing the overlapping pairs step by step (``as_json``: then one JSON line
    with the pairs' steps of the horizon, the first constrained step among them, and the run's
    :data:`SUMMARY_KEYS`); returns how many were found."""
    from swarmpc.bench import BenchCase
    from swarmpc.simulation.loop import simulate
    from swarmpc.solvers.admm import repair

    found: list[dict[str, Any]] = []
    steps = [0]
    original = repair.Repair.make_safe

    def make_safe(self: Any, *args: Any, **kwargs: Any) -> Any:
        safe = original(self, *args, **kwargs)
        for row in overlapping_pairs(np.asarray(self.safety.bodies), safe.results, safe.graph.neighbours):
            found.append(row)
            print(f"step {steps[0]}: {row}", flush=True)
        steps[0] += 1
        return safe

    settings = (("solver.deadline", deadline),) if deadline is not None else ()
    repair.Repair.make_safe = make_safe  # type: ignore[method-assign]
    try:
        case = BenchCase(family="random", agents=agents, seed=seed, local="qp", settings=settings)
        result = simulate(case.scenario())
    finally:
        repair.Repair.make_safe = original  # type: ignore[method-assign]
    print(f"{len(result.records)} steps, {len(found)} overlapping pairs after the safety passes")
    if as_json:
        line = {"seed": seed, "agents": agents, "deadline": deadline, "steps": len(result.records),
                "overlaps": len(found), "overlap_steps": [row["step"] for row in found],
                "pairs": sorted({row["pair"] for row in found}),
                **{key: result.summary.get(key) for key in SUMMARY_KEYS}}
        print(json.dumps(line), flush=True)
    return len(found)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--deadline", type=float, default=None, help="solver.deadline [s]; none by default")
    parser.add_argument("--json", action="store_true", help="end with a JSON line: overlaps and summary")
    args = parser.parse_args()
    probe(args.agents, args.seed, args.deadline, args.json)


if __name__ == "__main__":
    main()
