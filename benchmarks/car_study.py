"""Car study: the built-ins with cars flown by the centralised NLP and by consensus ADMM, side by side.

Each case (``intersection``, ``mixed``, ``parking``) runs as built in (centralised), with
``solver.method: admm`` (IPOPT local steps, serial) and with ``admm-qp`` (ADMM with the QP local
step, ``solver.local: qp``), everything else equal. Collisions and the
smallest distance between footprints are recomputed from the saved poses by the exact rectangle
distance; the closed-loop cost of the ADMM run is compared with the centralised run's. Rows of a
run replace the rows of the same case and method already in the file. Writes
``benchmarks/results/car_runs.json``.

    nice -n 10 .venv/bin/python benchmarks/car_study.py --jobs 2       # the rows
    .venv/bin/python benchmarks/car_study.py --methods admm admm-qp    # the two local steps, case by case
    .venv/bin/python benchmarks/car_study.py --record NOTE             # the experiment in cars.json
    .venv/bin/python benchmarks/lab_tables.py --write                  # docs/lab/cars.md
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
RESULTS = ROOT / "benchmarks" / "results" / "car_runs.json"
RECORD = ROOT / "benchmarks" / "results" / "cars.json"
CASES = ("intersection", "mixed", "parking")
METHODS = ("centralized", "admm", "admm-qp")
SETTINGS = {"centralized": {"solver.method": "centralized"}, "admm": {"solver.method": "admm", "solver.local": "ipopt"},
            "admm-qp": {"solver.method": "admm", "solver.local": "qp"}}
"""The scenario keys of each method of the study."""


def footprint_gap(poses: np.ndarray, sizes: np.ndarray) -> float:
    """Smallest signed distance between two footprints over the flown poses (T+1, M, 3) [m]
    (negative: they overlap), recomputed with the exact rectangle distance."""
    from swarmpc.model.footprint import rectangle_distance

    agents = poses.shape[1]
    return min(float(rectangle_distance(poses[:, i], sizes[i], poses[:, j], sizes[j], signed=True).min())
               for i in range(agents) for j in range(i + 1, agents))


def measure(task: tuple[str, str]) -> dict[str, Any]:
    from swarmpc.scenarios import builtin_scenario
    from swarmpc.simulation.loop import simulate
    from swarmpc.simulation.results import agent_footprints, agent_poses

    case, method = task
    scn = builtin_scenario(case).with_updates(**SETTINGS[method])
    start = time.perf_counter()
    result = simulate(scn)
    wall = time.perf_counter() - start
    s, models = result.summary, scn.agent_models()
    gap = footprint_gap(agent_poses(models, result.states), agent_footprints(models, scn.bodies))
    iterations = s.get("admm_iterations") or {}
    return {
        "case": case, "method": method, "all_reached": s["all_reached"], "steps": s["steps"],
        "makespan_s": s.get("makespan_s"), "min_footprint_distance": gap, "d_min": scn.d_min, "cost": s["cost"],
        "step_ms_median": s["step_time_ms"]["median"], "step_ms_p95": s["step_time_ms"]["p95"],
        "critical_ms_median": (s.get("critical_path_ms") or {}).get("median"),
        "admm_iterations_mean": iterations.get("mean"), "failures": s.get("solver_failures"), "wall_s": wall,
        "agent_ms_median": (s.get("agent_step_time_ms") or {}).get("median"),
        "agent_ms_p95": (s.get("agent_step_time_ms") or {}).get("p95"), "local_fallbacks": s.get("local_fallbacks"),
    }


def _cells(r: dict[str, Any], central: dict[str, Any] | None) -> list[str]:
    def f(x: Any, fmt: str) -> str:
        return "–" if x is None else fmt.format(x)

    versus = None if central is None or r["method"] == "centralized" else 100 * (r["cost"] / central["cost"] - 1)
    return [r["case"], r["method"], "yes" if r["all_reached"] else "no", str(r["steps"]),
            f(r["min_footprint_distance"], "{:.3f}"), f(r["d_min"], "{:g}"), f(r["cost"], "{:.1f}"),
            f(versus, "{:+.2f}%"), f(r["step_ms_median"], "{:.0f}"), f(r["step_ms_p95"], "{:.0f}"),
            f(r["critical_ms_median"], "{:.0f}"), f(r.get("agent_ms_median"), "{:.0f}"),
            f(r.get("agent_ms_p95"), "{:.0f}"), f(r["admm_iterations_mean"], "{:.1f}"),
            f(r.get("local_fallbacks"), "{:d}"), f(r["wall_s"], "{:.0f}")]


WHAT = (
    "The built-ins with cars (`intersection`: 8 cars, `mixed`: 2 cars and 2 point robots, `parking`), each flown "
    "as built in by the centralised NLP, with `solver.method: admm` (consensus ADMM agreeing on footprint "
    "poses, IPOPT local steps, serial, rho 10, owner weight 5, tol 1e-3) and with admm-qp (the same ADMM with "
    "the QP local step, `solver.local: qp`), everything else equal, all in one sitting, two runs at a time. "
    "min gap: the smallest distance between two footprints over the run, recomputed from the saved poses by "
    "the exact rectangle distance "
    "(negative: overlap). cost vs central: the closed-loop cost against the centralised run of the same case. "
    "critical ms: per step, the compute with one core per agent (per iteration the slowest local solve). "
    "agent ms: one agent's compute in one MPC step (its local solves summed). hand-overs: local calls the QP "
    "step left to IPOPT."
)


def lab_record(rows: list[dict[str, Any]], note: str) -> dict[str, Any]:
    """The car experiment of the lab record (docs/lab/cars.md, via benchmarks/lab_tables.py)."""
    order = {(case, method): n for n, (case, method) in enumerate((c, m) for c in CASES for m in METHODS)}
    rows = sorted(rows, key=lambda r: order.get((r["case"], r["method"]), len(order)))
    central = {r["case"]: r for r in rows if r["method"] == "centralized"}
    columns = ["case", "method", "all reached", "steps", "min gap m", "d_min m", "cost", "cost vs central",
               "step ms median", "p95", "critical ms median", "agent ms median", "agent ms p95", "ADMM it. mean",
               "hand-overs", "wall s"]
    return {
        "id": "admm-vs-centralised", "title": "Cars: consensus ADMM against the centralised NLP",
        "status": "shipped", "date": "2026-12-06", "commit": None,
        "commands": ["cd benchmarks && ../.venv/bin/python car_study.py --jobs 2 --methods centralized admm admm-qp",
                     "cd benchmarks && ../.venv/bin/python car_study.py --record NOTE"],
        "what": WHAT, "tables": [{"caption": None, "columns": columns,
                                  "rows": [_cells(r, central.get(r["case"])) for r in rows]}],
        "note": note,
    }


def empty_record() -> dict[str, Any]:
    return {"schema": "swarmpc-lab/1", "record": "cars", "title": "Car agents",
            "summary": "Measurements of swarms with car agents (rotating rectangular footprints, full OBCA).",
            "experiments": []}


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--cases", nargs="*", default=list(CASES))
    parser.add_argument("--methods", nargs="*", default=list(METHODS))
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--record", default=None, metavar="NOTE",
                        help="write the experiment (with this conclusion) into cars.json from the rows file")
    args = parser.parse_args(argv)
    if args.record is not None:
        experiment = lab_record(json.loads(args.out.read_text())["rows"], args.record)
        write_experiment(RECORD, experiment, empty_record())
        return 0
    tasks = [(case, method) for case in args.cases for method in args.methods]
    measure_rows(args.out, tasks, measure, lambda r: (r["case"], r["method"]), args.jobs)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
