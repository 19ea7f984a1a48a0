"""The car QP local step's two QP solvers side by side: OSQP and PIQP on the same local problems.

A car (0.7 x 0.45 m, N = 15 steps of 0.2 s, the geometry of tests/test_footprint_qp.py) drives
past a neighbour's copy parked beside its way (the copy's lateral offset and heading
varied over a grid); each problem is asked with free copies (an ADMM iteration's call) and with the
copy pinned (a repair's call), by each QP solver in turn, repetition after repetition (interleaved,
so machine load falls on both alike): a cold call (a new local step, from the straight guess) and a
warm one (the same local step asked again from its answer, with the consensus target moved by 1 cm,
as at the next ADMM iteration). Times are wall-clock times of the whole call (rounds, exact checks
and Python included). IPOPT answers each problem once, as the reference optimum.

    .venv/bin/python benchmarks/car_qp_solvers.py --reps 10 --out rows.json
    .venv/bin/python benchmarks/car_qp_solvers.py --summarise rows.json
    .venv/bin/python benchmarks/car_qp_solvers.py --summarise rows.json --record NOTE \
        --closed-loop LABEL=RUN_DIR ...   # write the lab record (docs/lab/cars.md#car-qp-solvers)

``--closed-loop`` adds a table of whole runs (``swarmpc run ... --local qp``) from their
summary.json and steps.npz, one row per run folder.
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

RECORD = Path(__file__).parent / "results" / "cars.json"
HORIZON = 15
OFFSETS = (0.55, 0.6, 0.7)
"""[m] lateral offsets of the parked copy from the car's way (footprints 0.7 x 0.45 m, d_min 0.05):
clear of the straight guess at every heading below, within d_min of it at the nearest."""
HEADINGS = (-0.3, 0.0, 0.2)
"""[rad] headings of the parked copy."""


def _problems() -> list[dict[str, Any]]:
    """Every local problem of the grid: the agent, its neighbour, the guess, the parameters, the copy."""
    from swarmpc.formulation.footprint_local import NeighbourKind, consensus_block, slot_size
    from swarmpc.formulation.footprint_ocp import FootprintAgent
    from swarmpc.formulation.ocp import OCPSettings
    from swarmpc.solvers.footprint_central import straight_guess

    Q = np.diag([1.0, 1.0, 0.5, 0.1])
    settings = OCPSettings(dim=2, horizon=HORIZON, dt=0.2, discretization="rk4", Q=Q, R=0.1 * np.eye(2),
                           Qf=20.0 * Q, collision="hard", d_min=0.05, kappa=100.0, lower=np.array([-3.0, -2.0]),
                           upper=np.array([3.0, 2.0]), accel=np.array([1.0, 1.0]), speed=1.0, obstacles=(),
                           model_name="car")
    own = other = FootprintAgent(settings)
    start, goal = np.array([-2.0, 0.0, 0.0, 0.0]), np.array([2.0, 0.0, 0.0, 0.0])
    guess = straight_guess(own, start, goal)
    out = []
    for offset, heading in itertools.product(OFFSETS, HEADINGS):
        copy = np.tile(np.array([[0.0], [offset], [heading]]), (1, HORIZON))
        params = {"x0": guess[0], "goal": goal, "rho": np.array([[1.0]]), "Z": consensus_block(own, guess),
                  "Y": np.zeros((3, HORIZON)), "Z0": copy, "Y0": np.zeros_like(copy), "S0": slot_size(own, other)}
        out.append({"own": own, "other": other, "kinds": (NeighbourKind.of(other),), "guess": guess,
                    "params": params, "copy": copy, "label": f"offset {offset}, heading {heading}"})
    return out


def _reference(problem: dict[str, Any], pinned: bool) -> float:
    """IPOPT's optimal cost of one local problem."""
    from swarmpc.formulation.footprint_local import build_footprint_local
    from swarmpc.solvers.footprint_admm import footprint_local_guess

    own, other = problem["own"], problem["other"]
    fixed = {"C0": problem["copy"]} if pinned else None
    start = footprint_local_guess(own, problem["guess"], [other], [problem["copy"]])
    answer = build_footprint_local(own, problem["kinds"]).solve(problem["params"], start, fixed=fixed)
    return float(answer.cost) if answer.success else float("nan")


def measure(reps: int) -> list[dict[str, Any]]:
    """One row per problem, kind of call, solver and repetition (module docstring)."""
    from swarmpc.solvers.footprint_qp import FootprintLocalQP
    from swarmpc.solvers.qp_local import QPLocalOptions

    rows = []
    problems = _problems()
    reference = {(k, pinned): _reference(p, pinned) for k, p in enumerate(problems) for pinned in (False, True)}
    for rep in range(reps):
        for (k, problem), pinned, solver in itertools.product(enumerate(problems), (False, True), ("osqp", "piqp")):
            options = QPLocalOptions(solver=solver, repair_solver=solver)
            step = FootprintLocalQP(problem["own"], problem["kinds"], options)
            params = dict(problem["params"])
            started = time.perf_counter()
            cold = step.solve(params, problem["guess"], None, [problem["copy"]], pinned)
            cold_s = time.perf_counter() - started
            params["Z"] = params["Z"] + 0.01
            plan, inputs = np.asarray(cold.x["X"]).T, np.asarray(cold.x["U"]).T
            started = time.perf_counter()
            warm = step.solve(params, plan, inputs, [np.asarray(cold.x["C0"])], pinned)
            warm_s = time.perf_counter() - started
            rows.append({"rep": rep, "problem": k, "label": problem["label"], "pinned": pinned, "solver": solver,
                         "cold_ms": 1e3 * cold_s, "warm_ms": 1e3 * warm_s, "cold_ok": bool(cold.success),
                         "warm_ok": bool(warm.success), "cost": float(cold.cost),
                         "ipopt_cost": reference[(k, pinned)]})
    return rows


def summarise(rows: list[dict[str, Any]]) -> list[list[str]]:
    """Per kind of call and solver: cold and warm call times (median / p95), answers, and the
    largest gap of a cold answer's cost to IPOPT's optimum."""
    table = []
    for pinned, solver in itertools.product((False, True), ("osqp", "piqp")):
        mine = [r for r in rows if r["pinned"] == pinned and r["solver"] == solver]
        if not mine:
            continue
        cold = np.array([r["cold_ms"] for r in mine])
        warm = np.array([r["warm_ms"] for r in mine])
        gap = max(abs(r["cost"] - r["ipopt_cost"]) / abs(r["ipopt_cost"]) for r in mine if r["cold_ok"])
        solved = sum(r["cold_ok"] for r in mine) + sum(r["warm_ok"] for r in mine)
        osqp = {(r["rep"], r["problem"]): r["cost"] for r in rows if r["pinned"] == pinned and r["solver"] == "osqp"}
        apart = max(abs(r["cost"] - osqp[(r["rep"], r["problem"])]) / abs(r["cost"]) for r in mine)
        table.append(["repair (copy pinned)" if pinned else "ADMM iteration (copy free)", solver, str(len(mine)),
                      f"{np.median(cold):.1f} / {np.percentile(cold, 95):.1f}",
                      f"{np.median(warm):.1f} / {np.percentile(warm, 95):.1f}",
                      f"{solved} of {2 * len(mine)}", f"{100 * gap:.3f} %", f"{100 * apart:.4f} %"])
    return table


COLUMNS = ["call", "QP solver", "calls", "cold call ms median / p95", "warm call ms median / p95", "answered",
           "largest cost gap to IPOPT (cold answers)",
           "largest cost gap to OSQP's answer"]


RUN_COLUMNS = ["code", "all reached", "steps", "min gap m", "cost", "step ms median / p95",
               "agent ms median / p95", "hand-overs", "repaired steps", "wall s"]


def run_row(label: str, folder: Path) -> list[str]:
    """One closed-loop run's row from its folder (summary.json; per-agent times from steps.npz)."""
    summary = json.loads((folder / "summary.json").read_text())
    steps = np.load(folder / "steps.npz")
    agent_ms = 1e3 * np.asarray(steps["agent_time_s"]).ravel()
    step = summary["step_time_ms"]
    return [label, "yes" if summary["all_reached"] else "no", str(summary["steps"]),
            f"{summary['min_footprint_distance']:.3f}", f"{summary['cost']:.1f}",
            f"{step['median']:.0f} / {step['p95']:.0f}",
            f"{np.median(agent_ms):.0f} / {np.percentile(agent_ms, 95):.0f}", str(summary["local_fallbacks"]),
            str(summary["admm_repairs"]), f"{summary['wall_time_s']:.0f}"]


def record(rows: list[dict[str, Any]], note: str, runs: list[str]) -> None:
    """Write the experiment into the lab record (``benchmarks/results/cars.json``)."""
    from study import write_experiment

    tables = [{"caption": "Each local problem's calls, both solvers interleaved.", "columns": COLUMNS,
               "rows": summarise(rows)}]
    if runs:
        closed = [run_row(label, Path(folder)) for label, folder in (spec.split("=", 1) for spec in runs)]
        tables.append({"caption": "`mixed` by ADMM with the QP local step; each pair of rows flown at the same time.",
                       "columns": RUN_COLUMNS, "rows": closed})
    write_experiment(RECORD, {
        "id": "car-qp-solvers", "title": "The car QP local step on OSQP and on PIQP",
        "status": "shipped", "date": time.strftime("%Y-%m-%d"), "commit": None,
        "commands": [".venv/bin/python benchmarks/car_qp_solvers.py --reps 10 --out rows.json",
                     "swarmpc run mixed --method admm --local qp  # with the code before, and after, at the same time",
                     "swarmpc run MIXED.yaml  # mixed with solver.method admm, solver.local qp, solver.qp.solver piqp, "
                     "at the same time as the code before"],
        "what": __doc__.split("\n\n")[1].replace("\n", " "), "tables": tables, "note": note,
    })


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, default=10)
    parser.add_argument("--out", type=Path, default=None, help="write the rows to this JSON file")
    parser.add_argument("--summarise", type=Path, default=None, help="print the table of a rows file")
    parser.add_argument("--record", default=None, metavar="NOTE", help="write the lab record with this note")
    parser.add_argument("--closed-loop", nargs="*", default=[], metavar="LABEL=RUN_DIR",
                        help="run folders for the record's closed-loop table")
    args = parser.parse_args(argv)
    rows = json.loads(args.summarise.read_text()) if args.summarise else measure(args.reps)
    if args.record is not None:
        record(rows, args.record, args.closed_loop)
    if args.out is not None:
        args.out.write_text(json.dumps(rows) + "\n")
    print("| " + " | ".join(COLUMNS) + " |")
    for row in summarise(rows):
        print("| " + " | ".join(row) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
