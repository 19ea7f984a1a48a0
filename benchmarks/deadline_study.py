"""Deadline study: the critical path and the deadline misses of random 3D swarms, one checkout
against another, run by run.

Each call flies one random 3D case (the bench family: ``random``, accel <= 1, 5 mm consensus
tolerance) with the shipped fast tuning (Q = 10, R = 0.1, ``Qf: lqr``, ``limits.speed`` 1, QP local
step) and an optional ``solver.deadline``, and appends one row to a JSON-lines file: the outcome
(steps, every agent at its goal, collisions recomputed from the states, makespan, cost), the
critical path of every step, which steps went through the repair pass, the deadline misses and
the calls handed to IPOPT. To compare two versions of swarmpc, call it alternately under each
checkout (``PYTHONPATH=<checkout>/src``) with a ``--tag`` each, seed by seed, so that both share
the machine's load; or compare two settings of one checkout (``--set KEY=VALUE``, a tag each);
``--summarise`` pools the rows by size, deadline and tag.

    for s in 0 1 2 3 4; do for t in old new; do
      PYTHONPATH=$CHECKOUT_$t/src .venv/bin/python benchmarks/deadline_study.py --tag $t --agents 16 \\
          --seed $s --deadline 0.1 --out rows.jsonl; done; done
    .venv/bin/python benchmarks/deadline_study.py --summarise rows.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

TUNING = {"weights.Q": 10.0, "weights.R": 0.1, "limits.speed": 1.0, "solver.local": "qp"}
"""The tuning to start from (docs/tuning.md), on the QP local step."""


def fly(
    tag: str, agents: int, seed: int, deadline: float | None, extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """One run's row; ``extra``: further scenario settings (dotted keys) of the variant."""
    from swarmpc.scenarios import builtin_scenario
    from swarmpc.simulation.loop import simulate

    settings: dict[str, Any] = {**TUNING, "solver.deadline": deadline, **(extra or {})}
    scn = builtin_scenario("random", agents=agents, dim=3, seed=seed).with_updates(**settings)
    began = time.perf_counter()
    result = simulate(scn)
    wall = time.perf_counter() - began
    s = result.summary
    return {
        "tag": tag, "agents": agents, "seed": seed, "deadline": deadline, "wall_s": round(wall, 2),
        "steps": s["steps"], "all_reached": s["all_reached"], "collisions": s["collisions"],
        "makespan_s": s["makespan_s"], "cost": s["cost"], "local_fallbacks": s["local_fallbacks"],
        "deadline_misses": s["deadline_misses"], "repairs": s["admm_repairs"],
        "critical_ms": [round(r.critical_path_s * 1e3, 3) for r in result.records],
        "repaired": [bool(r.repaired) for r in result.records],
    }


def summarise(rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (agents, deadline, tag): runs, outcomes and the critical path pooled over all steps and
    over the repaired steps."""
    groups: dict[tuple[int, float, str], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["agents"], r["deadline"] or 0.0, r["tag"]), []).append(r)
    table = []
    for (agents, deadline, tag), runs in sorted(groups.items()):
        critical = np.concatenate([r["critical_ms"] for r in runs])
        repaired = np.concatenate([np.asarray(r["critical_ms"])[np.asarray(r["repaired"], bool)] for r in runs])
        makespans = [np.inf if r["makespan_s"] is None else r["makespan_s"] for r in runs]
        table.append({
            "agents": agents, "deadline": deadline or None, "tag": tag, "runs": len(runs),
            "all_reached": sum(r["all_reached"] for r in runs), "collisions": sum(r["collisions"] for r in runs),
            "makespan_median_s": float(np.median(makespans)), "steps": int(critical.size),
            "critical_ms": [float(np.percentile(critical, q)) for q in (50, 95, 99)],
            "repaired_steps": int(repaired.size),
            "repaired_critical_ms": [float(np.percentile(repaired, q)) for q in (50, 99)] if repaired.size else None,
            "deadline_misses": sum(r["deadline_misses"] for r in runs),
            "local_fallbacks": sum(r["local_fallbacks"] for r in runs),
            "wall_median_s": float(np.median([r["wall_s"] for r in runs])),
        })
    return table


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tag", default="run")
    parser.add_argument("--agents", type=int, default=16)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--deadline", type=float, default=None)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a scenario setting of the variant (value as JSON), repeatable")
    parser.add_argument("--out", type=Path, default=None, help="append the row to this JSON-lines file")
    parser.add_argument("--summarise", type=Path, nargs="+", default=None, metavar="ROWS")
    args = parser.parse_args(argv)
    if args.summarise:
        rows = [json.loads(line) for path in args.summarise for line in path.read_text().splitlines() if line]
        json.dump(summarise(rows), sys.stdout, indent=1)
        print()
        return 0
    extra = {key: json.loads(value) for key, _, value in (item.partition("=") for item in args.set)}
    row = json.dumps(fly(args.tag, args.agents, args.seed, args.deadline, extra))
    print(row, flush=True)
    if args.out is not None:
        with args.out.open("a") as f:
            f.write(row + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
