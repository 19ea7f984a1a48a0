"""ADMM vs centralised MPC on the paper's scenarios (issue: distributed MPC by consensus ADMM).

Runs paper-2d and paper-3d for delta in {0.1, 0.3, 0.5}, hard and soft, with both methods, and
writes a markdown table (and the raw rows as JSON) to ``benchmarks/out/``. Per-step times are the
wall time of the whole swarm's solve with the agents solved one after another.

    python benchmarks/admm_vs_centralized.py [--quick] [--jobs 2]
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path
from typing import Any

from swarmpc.batch import Task, run_batch

OUT = Path(__file__).parent / "out"


def run_case(case: tuple[str, float, str, str]) -> dict[str, Any]:
    from swarmpc.scenarios import builtin_scenario
    from swarmpc.simulation.loop import simulate

    name, delta, collision, method = case
    scn = builtin_scenario(name, delta=delta).with_updates(collision=collision, **{"solver.method": method})
    summary = simulate(scn).summary
    iterations = summary["admm_iterations"]
    return {
        "scenario": name, "delta": delta, "collision": collision, "method": method,
        "step_ms_median": summary["step_time_ms"]["median"], "step_ms_p95": summary["step_time_ms"]["p95"],
        "iter_median": iterations["median"] if iterations else None,
        "iter_median_after_first": summary.get("admm_iterations_after_first"),
        "iter_max": iterations["max"] if iterations else None,
        "cost": summary["cost"], "steps": summary["steps"], "all_reached": summary["all_reached"],
        "collisions": summary["collisions"], "min_sep_ratio": summary["min_separation_ratio"],
        "max_slack": summary["max_slack"], "failures": summary["solver_failures"],
        "repairs": summary.get("admm_repairs"), "deadlocks": summary["deadlocks"],
    }


def fmt(value: object, digits: int = 1) -> str:
    if value is None:
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def table(rows: list[dict[str, Any]]) -> str:
    head = ("| scenario | Δ | form | method | step ms median | p95 | ADMM it. median (after 1st) | max | "
            "closed-loop cost | cost vs central | steps | all reached | collisions | min sep/Δ | repairs |")
    lines = [head, "|" + "---|" * 15]
    central = {(r["scenario"], r["delta"], r["collision"]): r["cost"] for r in rows if r["method"] == "centralized"}
    for r in rows:
        ref = central.get((r["scenario"], r["delta"], r["collision"]))
        gap = "-" if r["method"] == "centralized" or not ref else f"{100 * (r['cost'] - ref) / ref:+.1f}%"
        lines.append(
            f"| {r['scenario']} | {r['delta']} | {r['collision']} | {r['method']} | {fmt(r['step_ms_median'])} | "
            f"{fmt(r['step_ms_p95'])} | {fmt(r['iter_median'], 0)} ({fmt(r['iter_median_after_first'], 0)}) | "
            f"{fmt(r['iter_max'])} | {fmt(r['cost'])} | {gap} | {r['steps']} | {fmt(r['all_reached'])} | "
            f"{r['collisions']} | {fmt(r['min_sep_ratio'], 2)} | {fmt(r['repairs'])} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="delta 0.3 only")
    parser.add_argument("--jobs", type=int, default=1, help="cases run side by side (1 for clean timings)")
    args = parser.parse_args()
    deltas = [0.3] if args.quick else [0.1, 0.3, 0.5]
    cases = list(itertools.product(["paper-2d", "paper-3d"], deltas, ["hard", "soft"], ["centralized", "admm"]))
    finished = sorted(run_batch([Task(run_case, (case,)) for case in cases], args.jobs), key=lambda f: f.index)
    rows = [f.value for f in finished if f.ok]
    failed = [f"{cases[f.index]}: {f.error}" for f in finished if not f.ok]
    OUT.mkdir(exist_ok=True)
    (OUT / "admm_vs_centralized.json").write_text(json.dumps(rows, indent=2))
    text = table(rows)
    (OUT / "admm_vs_centralized.md").write_text(text + "\n")
    print(text)
    if failed:
        sys.exit(f"{len(failed)} case(s) failed and are not in the table:\n" + "\n".join(failed))


if __name__ == "__main__":
    main()
