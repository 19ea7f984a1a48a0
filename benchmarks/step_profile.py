"""Where a step's critical path goes: ADMM iterations, repair batches, the coordinator.

Flies one random 3D case of the bench family (default weights, QP local step) under a deadline
(or none: ``--deadline none``) and splits each step's critical path (``critical_path_s``) into
the slowest call of every batch of local steps the coordinator waited for, ADMM iterations and
repair-pass batches apart, and the rest (the coordinator's own work). Prints the totals over
the steps and the worst steps.

    .venv/bin/python benchmarks/step_profile.py --agents 64 --seed 0 --steps 40 \\
        [--set solver.admm.repair_order=colour]
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np
import yaml


def profile(agents: int, seed: int, steps: int, deadline: float | None,
            settings: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per step: its critical path and its parts [ms], iterations and repair batches."""
    from swarmpc.bench import BenchCase
    from swarmpc.simulation.loop import simulate
    from swarmpc.solvers.admm import clock, solver

    batches: list[tuple[bool, float]] = []  # (repair batch, slowest call [s])
    starts: list[int] = []
    timed, planned = clock.StepClock.solve, solver.ADMMSolver.plan

    def solve(self: Any, executor: Any, requests: Any) -> Any:
        results = timed(self, executor, requests)
        slowest = max((getattr(r, "call_time", r.solve_time) for r in results), default=0.0)
        batches.append((any(q.neighbour_plans is not None for q in requests), slowest))
        return results

    def plan(self: Any, *args: Any, **kwargs: Any) -> Any:
        starts.append(len(batches))
        return planned(self, *args, **kwargs)

    clock.StepClock.solve, solver.ADMMSolver.plan = solve, plan  # type: ignore[method-assign]
    try:
        case = BenchCase(family="random", agents=agents, seed=seed, local="qp", max_steps=steps,
                         settings=(("solver.deadline", deadline), *settings.items()))
        result = simulate(case.scenario())
    finally:
        clock.StepClock.solve, solver.ADMMSolver.plan = timed, planned  # type: ignore[method-assign]
    starts.append(len(batches))
    rows = []
    for t, record in enumerate(result.records):
        own = batches[starts[t]:starts[t + 1]]
        iterations = [s for repair, s in own if not repair]
        repairs = [s for repair, s in own if repair]
        critical = 1e3 * record.critical_path_s
        rows.append({"step": t, "critical_ms": critical, "iterations": len(iterations),
                     "iterations_ms": 1e3 * sum(iterations), "repair_batches": len(repairs),
                     "repair_ms": 1e3 * sum(repairs),
                     "coordinator_ms": critical - 1e3 * (sum(iterations) + sum(repairs))})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agents", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--deadline", type=lambda v: None if v == "none" else float(v), default=0.1,
                        help="solver.deadline [s], or none (the default scenario: no deadline)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a scenario setting (dotted key), the value in YAML")
    parser.add_argument("--worst", type=int, default=10, help="worst steps to list")
    args = parser.parse_args()
    settings = {key: yaml.safe_load(value) for key, value in (item.split("=", 1) for item in args.set)}
    rows = profile(args.agents, args.seed, args.steps, args.deadline, settings)
    keys = ("critical_ms", "iterations_ms", "repair_ms", "coordinator_ms")
    print("totals [ms]: " + ", ".join(f"{k[:-3]} {sum(r[k] for r in rows):.0f}" for k in keys))
    print("step critical iterations (ms) repair-batches (ms) coordinator")
    for r in sorted(rows, key=lambda r: -r["critical_ms"])[: args.worst]:
        print(f"{r['step']:4d} {r['critical_ms']:8.0f} {r['iterations']:3d} ({r['iterations_ms']:4.0f}) "
              f"{r['repair_batches']:3d} ({r['repair_ms']:4.0f}) {r['coordinator_ms']:6.0f}")
    budget = args.deadline or 0.1  # without a deadline, dt
    misses = int(np.sum([r["critical_ms"] > 1e3 * budget for r in rows]))
    print(f"steps over {budget:g} s: {misses} of {len(rows)}")


if __name__ == "__main__":
    main()
