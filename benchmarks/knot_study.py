"""Knot study: the keep-right rule (``deadlock.keep_right_deg``) against the reactive detours alone.

The paper's four-agent crossing (``swap-2d``), antipodal swaps on a circle (2D) and a sphere
(3D), M = 4, 8, 16, with and without an acceleration limit of 1 m/s², and random 3D swarms
(M = 16, seeds 0-2, default weights and the fast tuning Q = 1, R = 0.1, ``Qf: lqr``), each flown
with the rule off (today's reactive detours only) and with the rule at the angles given. Rows of
a run replace the rows of the same case and angle already in the file. Consensus ADMM with the
QP local step (``solver.local: qp``), serial; the rule only changes the goals the MPC steers to, so
every row stays collision-free by the OBCA constraints, which the collision counts recompute from
the states. Writes ``benchmarks/results/knots.json``.

    nice -n 10 .venv/bin/python benchmarks/knot_study.py --jobs 2             # the rows
    .venv/bin/python benchmarks/knot_study.py --record NOTE   # the experiment, with its conclusion, in controller.json
    .venv/bin/python benchmarks/lab_tables.py --write      # docs/lab/controller.md
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from study import measure_rows, write_experiment

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "knots.json"
RECORD = ROOT / "benchmarks" / "results" / "controller.json"
SWAPS = tuple(f"{family}-{m}{limit}" for family in ("circle", "sphere") for m in (4, 8, 16) for limit in ("", "-a1"))
RANDOM = tuple(f"random-16-s{seed}{tuning}" for tuning in ("", "-fast") for seed in range(3))
CASES = ("swap-2d", *SWAPS, *RANDOM)
FAST = {"weights.Q": 1.0, "weights.R": 0.1, "weights.Qf": "lqr"}
"""The fast tuning (``-fast`` cases): stiff stage weights, cheap inputs, the Riccati terminal weight."""
ANGLES = (0.0, 20.0)


def scenario(case: str, angle: float) -> Any:
    """The scenario of a case name (family-M[-a1] or random-M-sSEED) with the rule at ``angle``."""
    from swarmpc.scenarios import builtin_scenario

    if case == "swap-2d":  # the paper's four-agent crossing (keep_right_deg 0 as built in)
        return builtin_scenario(case).with_updates(
            **{"solver.local": "qp", "stop.max_steps": 400, "deadlock.keep_right_deg": angle})
    parts = case.split("-")
    family, agents = parts[0], int(parts[1])
    if family == "random":
        base = builtin_scenario("random", agents=agents, dim=3, seed=int(parts[2][1:]))
        if parts[-1] == "fast":
            base = base.with_updates(**FAST)
    else:
        base = builtin_scenario("circle", agents=agents, dim=2 if family == "circle" else 3)
        if parts[-1] == "a1":
            base = base.with_updates(**{"limits.accel": 1.0})
    return base.with_updates(**{"solver.local": "qp", "stop.max_steps": 400, "deadlock.keep_right_deg": angle})


def separation(states: np.ndarray, dim: int, delta: float) -> float:
    """Smallest inf-norm gap between two agents over the flown states, in units of Delta (below 1:
    the boxes overlap), recomputed from the positions."""
    positions = states[:, :, :dim]
    gaps = np.max(np.abs(positions[:, :, None] - positions[:, None]), axis=3)
    agents = positions.shape[1]
    gaps[:, np.arange(agents), np.arange(agents)] = np.inf
    return float(gaps.min() / delta)


def measure(task: tuple[str, float]) -> dict[str, Any]:
    from swarmpc.bench import lone_agent_times
    from swarmpc.simulation.loop import simulate
    from swarmpc.simulation.quality import interaction_ratio

    case, angle = task
    scn = scenario(case, angle)
    start = time.perf_counter()
    result = simulate(scn)
    s = result.summary
    return {
        "case": case, "keep_right_deg": angle, "all_reached": s["all_reached"], "steps": s["steps"],
        "makespan_s": s.get("makespan_s"), "separation": separation(result.states, scn.dim, scn.delta),
        "deadlocks": s.get("deadlocks"), "interaction": interaction_ratio(s.get("makespan_s"), lone_agent_times(scn)),
        "step_ms_median": s["step_time_ms"]["median"], "wall_s": time.perf_counter() - start,
    }


def _cells(r: dict[str, Any]) -> list[str]:
    def f(x: Any, fmt: str) -> str:
        return "–" if x is None else fmt.format(x)

    return [r["case"], f(r["keep_right_deg"], "{:g}"), "yes" if r["all_reached"] else "no", str(r["steps"]),
            f(r["makespan_s"], "{:.1f}"), f(r["interaction"], "{:.2f}"), f(r["separation"], "{:.2f}"),
            f(r["deadlocks"], "{}")]


WHAT = (
    "The paper's four-agent crossing (swap-2d), antipodal swaps of the circle (2D) and sphere (3D) families of "
    "`swarmpc bench`, M = 4, 8, 16, without and with `limits.accel: 1` (`-a1`), and random 3D swarms (M = 16, "
    "accel <= 1) with the default weights and with the fast tuning Q = 1, R = 0.1, `Qf: lqr` (`-fast`), each with "
    "the keep-right rule off (0: the reactive detours of stalled agents only) and at 20 degrees. Consensus ADMM "
    "with the QP local step, serial, `stop.max_steps` 400 (a row that does not reach is cut there). Separation: "
    "the smallest inf-norm gap between two agents over the run in units of Δ, recomputed from the states (>= 1: "
    "no overlap). vs lone: makespan over the latest lone-agent time to goal with the same controller."
)


def lab_record(rows: list[dict[str, Any]], note: str) -> dict[str, Any]:
    """The knot experiment of the lab record (docs/lab/controller.md, via benchmarks/lab_tables.py)."""
    order = {case: n for n, case in enumerate(CASES)}
    rows = sorted(rows, key=lambda r: (order.get(r["case"], len(order)), r["keep_right_deg"]))
    columns = ["case", "keep right deg", "all reached", "steps", "makespan s", "vs lone", "min sep/Δ", "deadlocks"]
    return {
        "id": "knot-rule", "title": "Knots and symmetric swaps: the keep-right rule", "status": "shipped",
        "date": "2026-12-05", "commit": None,
        "commands": ["nice -n 10 .venv/bin/python benchmarks/knot_study.py --jobs 2"],
        "what": WHAT, "tables": [{"caption": None, "columns": columns, "rows": [_cells(r) for r in rows]}],
        "note": note,
    }


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--cases", nargs="*", default=list(CASES))
    parser.add_argument("--angles", nargs="*", type=float, default=list(ANGLES))
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--record", default=None, metavar="NOTE",
                        help="write the experiment (with this conclusion) into controller.json from the rows file")
    args = parser.parse_args(argv)
    if args.record is not None:
        experiment = lab_record(json.loads(args.out.read_text())["rows"], args.record)
        write_experiment(RECORD, experiment)
        return 0
    tasks = [(case, angle) for case in args.cases for angle in args.angles]
    measure_rows(args.out, tasks, measure, lambda r: (r["case"], r["keep_right_deg"]), args.jobs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
