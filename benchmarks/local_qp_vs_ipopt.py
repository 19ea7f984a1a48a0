"""The ADMM agents' local step on the QP path (``solver.local: qp``) against IPOPT, in closed loop.

Each scenario is flown with both local steps, interleaved (qp, ipopt, qp, ipopt, ...) in one
process, so that machine noise hits both alike; the trajectories are deterministic, so the repeats
differ only in their times, which are pooled. Per scenario and local step:

* local-step time per agent and MPC step (the sum of an agent's local solves in a step, the
  issue's "per-agent compute"): median, p95, p99 [ms];
* time of one local-step call (one agent, one ADMM iteration or repair re-plan): median, p95, p99;
* MPC step wall time: median, p99 [ms] (serial executor: every agent's solves one after another);
* ADMM iterations per step (mean, max), steps until every agent is at its goal, closed-loop cost,
  collisions, and the calls the QP path failed that IPOPT answered (``local_fallbacks``).

    .venv/bin/python benchmarks/local_qp_vs_ipopt.py [--repeats 2] [--agents 16] [--seeds 3]

Prints a markdown table; writes benchmarks/results/local_qp_vs_ipopt.json.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from swarmpc.config import Scenario
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.loop import simulate
from swarmpc.solvers.executors import SerialExecutor

OUT = Path(__file__).parent / "results" / "local_qp_vs_ipopt.json"
LOCALS = ("qp", "ipopt")


class CallRecorder(SerialExecutor):
    """The serial executor, keeping each local-step call's solver time and the IPOPT fallbacks."""

    def __init__(self) -> None:
        super().__init__()
        self.call_times: list[float] = []
        self.fallbacks = 0

    def solve(self, requests: Any) -> list[Any]:
        results = super().solve(requests)
        self.call_times += [r.solve_time for r in results if r.solve_time > 0]  # 0: an answer sent again
        self.fallbacks += sum(r.local_fallbacks for r in results)
        return results


def scenarios(agents: int, seeds: int) -> dict[str, Scenario]:
    """paper-2d, paper-3d, random 3D swarms of 8 agents (``seeds`` seeds) and of ``agents`` (seed 0)."""
    chosen = {"paper-2d": builtin_scenario("paper-2d"), "paper-3d": builtin_scenario("paper-3d")}
    chosen.update({f"random-3d-8-s{seed}": builtin_scenario("random", agents=8, dim=3, seed=seed)
                   for seed in range(seeds)})
    chosen[f"random-3d-{agents}"] = builtin_scenario("random", agents=agents, dim=3, seed=0)
    return chosen


def fly(scn: Scenario, local: str) -> dict[str, Any]:
    """One closed-loop run: its samples (times) and its outcome."""
    recorder = CallRecorder()
    began = time.perf_counter()
    result = simulate(scn.with_updates(**{"solver.local": local}), executor=recorder)
    wall = time.perf_counter() - began
    summary = result.summary
    return {
        "agent_step_ms": np.concatenate([r.agent_times for r in result.records]) * 1e3,
        "call_ms": np.asarray(recorder.call_times) * 1e3,
        "step_ms": np.array([r.wall_time for r in result.records]) * 1e3,
        "iterations": np.array([r.admm_iterations or 0 for r in result.records]),
        "outcome": {"steps": summary["steps"], "all_reached": summary["all_reached"],
                    "collisions": summary["collisions"], "cost": summary["cost"],
                    "local_fallbacks": recorder.fallbacks, "solver_failures": summary["solver_failures"]},
        "wall_s": wall,
    }


def pooled(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """The repeats of one (scenario, local step) as one row: times pooled, outcome of the first
    (every repeat flies the same trajectory; checked)."""
    outcomes = [r["outcome"] for r in runs]
    assert all(o == outcomes[0] for o in outcomes), outcomes  # deterministic: only the clock differs

    def q(key: str, *levels: float) -> list[float]:
        values = np.concatenate([r[key] for r in runs])
        return [float(np.percentile(values, level)) for level in levels]

    iterations = runs[0]["iterations"]
    return {
        **outcomes[0],
        "agent_step_ms": dict(zip(("median", "p95", "p99"), q("agent_step_ms", 50, 95, 99), strict=True)),
        "call_ms": dict(zip(("median", "p95", "p99"), q("call_ms", 50, 95, 99), strict=True)),
        "step_ms": dict(zip(("median", "p99"), q("step_ms", 50, 99), strict=True)),
        "admm_iterations": {"mean": float(iterations.mean()), "max": int(iterations.max())},
        "wall_s": [round(r["wall_s"], 2) for r in runs],
    }


def table(rows: list[dict[str, Any]]) -> str:
    head = ("| scenario | local | agent-step ms med / p95 / p99 | call ms med / p95 / p99 | step ms med / p99 "
            "| ADMM it. mean / max | steps | reached | collisions | cost | IPOPT fallbacks | wall s |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in rows:
        a, c, s, it = r["agent_step_ms"], r["call_ms"], r["step_ms"], r["admm_iterations"]
        lines.append(
            f"| {r['scenario']} | {r['local']} | {a['median']:.2f} / {a['p95']:.1f} / {a['p99']:.1f} "
            f"| {c['median']:.2f} / {c['p95']:.2f} / {c['p99']:.1f} | {s['median']:.1f} / {s['p99']:.0f} "
            f"| {it['mean']:.1f} / {it['max']} | {r['steps']} | {r['all_reached']} | {r['collisions']} "
            f"| {r['cost']:.2f} | {r['local_fallbacks']} | {' / '.join(map(str, r['wall_s']))} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=2, help="runs of each (scenario, local step)")
    parser.add_argument("--agents", type=int, default=16, help="agents of the larger random 3D scenario")
    parser.add_argument("--seeds", type=int, default=3, help="seeds of the random 3D scenario with 8 agents")
    args = parser.parse_args()
    rows = []
    for name, scn in scenarios(args.agents, args.seeds).items():
        runs: dict[str, list[dict[str, Any]]] = {local: [] for local in LOCALS}
        for _ in range(args.repeats):
            for local in LOCALS:  # interleaved: qp, ipopt, qp, ipopt, ...
                runs[local].append(fly(scn, local))
                print(f"{name} {local}: {runs[local][-1]['wall_s']:.1f} s", file=sys.stderr, flush=True)
        rows += [{"scenario": name, "local": local, **pooled(runs[local])} for local in LOCALS]
    print(table(rows))
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps({
        "command": " ".join(["python benchmarks/local_qp_vs_ipopt.py", *sys.argv[1:]]),
        "machine": platform.platform(), "python": platform.python_version(), "executor": "serial",
        "repeats": args.repeats, "rows": rows,
    }, indent=2) + "\n")


if __name__ == "__main__":
    main()
