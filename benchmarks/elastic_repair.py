"""Repair calls the QP path fails and hands to IPOPT: what the elastic phase makes of each.

Flies the bench's random 3D case (default weights, QP local step, no deadline) with the elastic
phase off (``solver.qp.elastic: false``, every failed repair call handed to IPOPT, as before the
phase existed) and, for every repair call the QP path fails without proving it infeasible, also
runs the elastic phase (:meth:`~swarmpc.solvers.admm.QPLocalSolverLadder._elastic`) on the same
call (after IPOPT's hand-over; the run follows IPOPT's answers, as without the phase).
Per call: the soft plan's largest slack, whether the hard loop from it answered, the elastic
phase's time, and IPOPT's verdict, time and cost. Prints the calls grouped by slack.

    .venv/bin/python benchmarks/elastic_repair.py --agents 64 --seed 0 --steps 15 [--out calls.json]
"""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import numpy as np


def record(agents: int, seed: int, steps: int) -> list[dict[str, Any]]:
    """One row per repair call handed to IPOPT."""
    from swarmpc.bench import BenchCase
    from swarmpc.simulation.loop import simulate
    from swarmpc.solvers.admm import ladders

    rows: list[dict[str, Any]] = []
    handover = ladders.QPLocalSolverLadder._handover

    def probed(self: Any, params: Any, guess: Any, fixed: Any, failed: Any, copies: int, planes: int) -> Any:
        began = time.perf_counter()
        answer = handover(self, params, guess, fixed, failed, copies, planes)
        spent = time.perf_counter() - began
        if not ladders.pins_copies(fixed):
            return answer
        found, slack, elastic = self._elastic(params, failed, fixed, copies, planes)
        rows.append({"copies": copies, "slack": slack, "elastic_answered": found is not None,
                     "elastic_ms": 1e3 * elastic, "elastic_cost": None if found is None else float(found.cost),
                     "ipopt_answered": bool(answer.success), "handover_ms": 1e3 * spent,
                     "ipopt_cost": float(answer.cost) if answer.success else None})
        return answer

    ladders.QPLocalSolverLadder._handover = probed  # type: ignore[method-assign]
    try:
        case = BenchCase(family="random", agents=agents, seed=seed, local="qp", max_steps=steps,
                         settings=(("solver.qp.elastic", False),))
        simulate(case.scenario())
    finally:
        ladders.QPLocalSolverLadder._handover = handover  # type: ignore[method-assign]
    return rows


def summary(rows: list[dict[str, Any]], near: float) -> None:
    """The calls in three groups: answered by the elastic phase, soft plan within ``near`` of
    d_min, farther."""
    groups = {"elastic phase answered": [r for r in rows if r["elastic_answered"]],
              f"soft plan short by <= {near:g} m": [r for r in rows if not r["elastic_answered"]
                                                     and r["slack"] is not None and r["slack"] <= near],
              f"soft plan short by > {near:g} m (or soft call failed)": [
                  r for r in rows if not r["elastic_answered"] and (r["slack"] is None or r["slack"] > near)]}
    print("group | calls | IPOPT answered | IPOPT costs | hand-over ms sum / median | elastic ms sum / median")
    for name, group in groups.items():
        handover = [r["handover_ms"] for r in group] or [0.0]
        elastic = [r["elastic_ms"] for r in group] or [0.0]
        costs = sorted(round(r["ipopt_cost"], 1) for r in group if r["ipopt_answered"])
        print(f"{name} | {len(group)} | {sum(r['ipopt_answered'] for r in group)} | {costs} | "
              f"{sum(handover):.0f} / {np.median(handover):.0f} | {sum(elastic):.0f} / {np.median(elastic):.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agents", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=15)
    parser.add_argument("--near", type=float, default=1e-4, help="slack [m] that counts as near d_min")
    parser.add_argument("--out", help="write the calls as JSON here")
    args = parser.parse_args()
    rows = record(args.agents, args.seed, args.steps)
    summary(rows, args.near)
    if args.out:
        with open(args.out, "w") as stream:
            json.dump(rows, stream, indent=1)


if __name__ == "__main__":
    main()
