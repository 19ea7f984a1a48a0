"""Stress suite: many seeded random scenarios, each run in its own process, checked from the
saved trajectories (issue "Reliability and safety", item 4).

Scenario ``k`` of a suite is drawn from a generator seeded by (suite seed, k): M in 2..16 (small
M more often), 2D or 3D, with or without static boxes, hard or soft collision form, starts and
goals at least ``2 delta`` apart and clear of the obstacles, a workspace whose area (volume)
grows with M. A share of the swarms with M <= 8 is solved by ADMM, the rest centrally
(``ADMM_SHARE``; ADMM run serially costs 10-20x more). Weights are brisker than the paper's
(Q = 1, R = 0.5, Qf = 5) and the acceleration is limited to 2 m/s^2. Every run is scored from its
trajectory alone: collisions recounted with the inf-norm against delta, goal reaching, obstacle
penetration; plus the run's own solver failure and deadlock counts. Writes ``stress.md`` (tables)
and ``stress.json`` (every row) to ``--out``.

    nice -n 10 python benchmarks/stress.py --jobs 2            # the full suite (200 scenarios)
    python benchmarks/stress.py --count 20 --small --jobs 2     # the quick subset the tests run

``--jobs`` defaults to the cores this process may use (its affinity mask).
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from swarmpc.batch import Task, run_batch

OUT = Path(__file__).parent / "out"
AGENT_COUNTS = np.arange(2, 17)
# small swarms more often: the suite's time grows quickly with M
AGENT_WEIGHTS = 1.0 / AGENT_COUNTS
STRESS_WEIGHTS = {"Q": 1.0, "R": 0.5, "Qf": 5.0}
ADMM_MAX_AGENTS = 8
OBSTACLE_GAP = 0.6
ADMM_SHARE = 0.3


def _spread(rng: np.random.Generator, count: int, lower: np.ndarray, upper: np.ndarray, gap: float,
            obstacles: list[tuple[np.ndarray, np.ndarray]], clearance: float) -> np.ndarray | None:
    """``count`` points in the box, pairwise >= ``gap`` apart (inf-norm), ``clearance`` off boxes."""
    points: list[np.ndarray] = []
    for _ in range(20000):
        p = rng.uniform(lower, upper)
        if any(np.all(np.abs(p - c) < h + clearance) for c, h in obstacles):
            continue
        if all(np.max(np.abs(p - q)) >= gap for q in points):
            points.append(p)
            if len(points) == count:
                return np.array(points)
    return None


def stress_scenario(index: int, seed: int = 0, small: bool = False) -> dict[str, Any]:
    """The ``index``-th scenario of the suite as a scenario mapping (validated by the caller).

    ``small`` draws the quick subset: M in 2..4, 2D four times out of five.
    """
    rng = np.random.default_rng([seed, index, int(small)])
    if small:
        m = int(rng.integers(2, 5))
        dim = 3 if rng.random() < 0.2 else 2
    else:
        m = int(rng.choice(AGENT_COUNTS, p=AGENT_WEIGHTS / AGENT_WEIGHTS.sum()))
        dim = 3 if rng.random() < 0.3 else 2
    collision = "soft" if rng.random() < 0.4 else "hard"
    # ADMM (serial) costs 10-20x the centralised solve on one machine: a share of the small swarms
    admm_max = 3 if small else ADMM_MAX_AGENTS
    method = "admm" if m <= admm_max and rng.random() < ADMM_SHARE else "centralized"
    with_obstacles = rng.random() < 0.4
    delta = float(rng.choice([0.15, 0.2, 0.25]))
    gap = max(2.0 * delta + 0.1, 0.5)
    # side of the square (cube) holding the starts and goals: about 1 m^2 (0.7 m^3) per agent
    side = max(2.5, float(np.sqrt(m * 1.0)) + 1.0) if dim == 2 else max(2.0, float((0.7 * m) ** (1 / 3)) + 1.0)
    lower, upper = -side / 2 * np.ones(dim), side / 2 * np.ones(dim)
    obstacles: list[tuple[np.ndarray, np.ndarray]] = []
    if with_obstacles:
        for _ in range(int(rng.integers(1, 4))):
            half = rng.uniform(0.1, 0.3, dim)
            center = rng.uniform(lower + 0.6, upper - 0.6)
            # boxes at least OBSTACLE_GAP apart on some axis: no slits narrower than an agent
            # needs (RRT, which inflates by 0.9 d_min only, would steer into them)
            if all(np.any(np.abs(center - c) - half - h >= OBSTACLE_GAP) for c, h in obstacles):
                obstacles.append((center, half))
    # starts and goals keep 2 delta + 0.2 off the boxes: an agent parked at its goal then never
    # closes the gap between itself and a box to the others (RRT waypoints do not see agents)
    clearance = 2 * delta + 0.2
    starts = _spread(rng, m, lower, upper, gap, obstacles, clearance)
    goals = _spread(rng, m, lower, upper, gap, obstacles, clearance)
    if starts is None or goals is None:  # too crowded: drop the obstacles and try again
        obstacles = []
        starts = _spread(rng, m, lower, upper, gap, obstacles, clearance)
        goals = _spread(rng, m, lower, upper, gap, obstacles, clearance)
    assert starts is not None and goals is not None
    margin = delta + 0.5
    return {
        "name": (f"stress-{'s' if small else ''}{index:03d}-{dim}d-m{m}-{collision}"
                 f"{'-obs' if obstacles else ''}-{method}"),
        "dim": dim,
        "delta": delta,
        "collision": collision,
        "seed": int(seed * 1000 + index),
        "weights": STRESS_WEIGHTS,
        "limits": {"accel": 2.0},
        "workspace": {"lower": (lower - margin).round(4).tolist(), "upper": (upper + margin).round(4).tolist()},
        "obstacles": [{"box": {"center": c.round(4).tolist(), "half_size": h.round(4).tolist()}}
                      for c, h in obstacles],
        "agents": [{"start": s.round(4).tolist(), "goal": g.round(4).tolist()}
                   for s, g in zip(starts, goals, strict=True)],
        "solver": {"method": method},
        "stop": {"goal_tolerance": 0.1, "max_steps": 250},
    }


def recount(states: np.ndarray, delta: np.ndarray) -> tuple[int, float]:
    """Collisions (k, i, j) with |p_i - p_j|_inf < delta and the smallest separation ratio."""
    d = states.shape[2] // 2
    p = states[:, :, :d] / np.asarray(delta, float)
    m = states.shape[1]
    if m < 2:
        return 0, float("inf")
    i, j = np.triu_indices(m, 1)
    ratio = np.max(np.abs(p[:, i] - p[:, j]), axis=2)
    return int(np.sum(ratio < 1 - 1e-9)), float(ratio.min())


def run_one(case: tuple[int, int, bool, str | None]) -> dict[str, Any]:
    """Run scenario ``index`` in this (worker) process and score it from its trajectory."""
    from swarmpc.config import scenario_from_dict
    from swarmpc.model.geometry import obstacle_penetration
    from swarmpc.simulation.loop import simulate
    from swarmpc.simulation.results import write_run

    index, seed, small, runs_dir = case
    scn = scenario_from_dict(stress_scenario(index, seed, small))
    started = time.perf_counter()
    result = simulate(scn)
    if runs_dir is not None:
        write_run(result, Path(runs_dir) / scn.name)
    states = result.states
    collisions, ratio = recount(states, scn.delta_vector)
    d = scn.dim
    final = np.linalg.norm(states[-1, :, :d] - scn.goal_states()[:, :d], axis=1)
    penetration = max((float(obstacle_penetration(states[:, :, :d], G, g).max())
                       for G, g in scn.obstacle_halfspaces()), default=0.0)
    s = result.summary
    return {
        "index": index, "name": scn.name, "dim": d, "agents": scn.num_agents, "collision": scn.collision,
        "method": scn.solver.method,
        "obstacles": len(scn.obstacles), "delta": float(scn.delta_vector[0]), "steps": s["steps"],
        "all_reached": bool(np.all(final <= scn.stop.goal_tolerance + 1e-9)),
        "reached": int(np.sum(final <= scn.stop.goal_tolerance + 1e-9)),
        "max_final_gap": float(final.max()),
        "collisions": collisions, "min_sep_ratio": ratio, "obstacle_penetration": penetration,
        "max_slack": s["max_slack"], "solver_failures": s["solver_failures"],
        "fallback_agent_steps": s["fallback_agent_steps"], "deadlocks": s["deadlocks"],
        "summary_collisions": s["collisions"], "wall_s": time.perf_counter() - started,
    }


def run_suite(count: int, seed: int = 0, jobs: int = 2, small: bool = False,
              runs_dir: str | None = None, progress: bool = True,
              journal: Path | None = None) -> list[dict[str, Any]]:
    """Every scenario in its own worker process (a fresh one per scenario; one job: all in this
    process), ``jobs`` at a time, started in index order (any prefix is a fair sample); each row is
    appended to ``journal`` (JSON lines) as soon as it is known, so an interrupted suite still
    leaves its results. A scenario that raises costs no other: the suite runs to its end, then
    raises RuntimeError naming the failed scenarios."""
    tasks = [Task(run_one, ((k, seed, small, runs_dir),)) for k in range(count)]
    rows: list[dict[str, Any]] = []
    failed: list[str] = []
    for done, finished in enumerate(run_batch(tasks, jobs, max_tasks_per_worker=1), 1):
        if not finished.ok:
            failed.append(f"scenario {finished.index}: {finished.error}")
            if progress:
                print(f"[{done}/{count}] scenario {finished.index}: FAILED ({finished.error})", flush=True)
            continue
        row = finished.value
        rows.append(row)
        if journal is not None:
            with journal.open("a") as handle:
                handle.write(json.dumps(row) + "\n")
        if progress:
            print(f"[{done}/{count}] {row['name']}: steps {row['steps']} reached "
                  f"{row['reached']}/{row['agents']} collisions {row['collisions']} "
                  f"failures {row['solver_failures']} deadlocks {row['deadlocks']} "
                  f"({row['wall_s']:.0f} s)", flush=True)
    if failed:
        raise RuntimeError(f"{len(failed)} of {count} stress scenarios failed: " + "; ".join(failed))
    return sorted(rows, key=lambda r: r["index"])


def _group_rows(rows: list[dict[str, Any]], label: str) -> str:
    n = len(rows)
    hard = [r for r in rows if r["collision"] == "hard"]
    reached = sum(r["all_reached"] for r in rows)
    return (f"| {label} | {n} | {reached / n:.1%} | {sum(r['collisions'] for r in hard)} | "
            f"{sum(r['collisions'] for r in rows if r['collision'] == 'soft')} | "
            f"{min(r['min_sep_ratio'] for r in rows):.3f} | "
            f"{sum(r['solver_failures'] for r in rows)} | {sum(r['fallback_agent_steps'] for r in rows)} | "
            f"{sum(r['deadlocks'] for r in rows)} | {np.median([r['steps'] for r in rows]):.0f} | "
            f"{np.median([r['wall_s'] for r in rows]):.0f} / {max(r['wall_s'] for r in rows):.0f} |")


def markdown(rows: list[dict[str, Any]], command: str, wall: float) -> str:
    """The suite's tables: by group, then every scenario that failed to reach or collided."""
    head = ("| group | runs | all reached | collisions (hard) | collisions (soft) | min sep/Δ | "
            "failed solves | fallback agent-steps | deadlock detours | median steps | wall s median / max |")
    lines = [f"Command: `{command}`; {len(rows)} scenarios, {wall / 60:.1f} min wall.", "", head,
             "|" + "---|" * 11]

    def groups() -> Iterable[tuple[str, list[dict[str, Any]]]]:
        yield "all", rows
        for dim in (2, 3):
            yield f"{dim}D", [r for r in rows if r["dim"] == dim]
        for form in ("hard", "soft"):
            yield form, [r for r in rows if r["collision"] == form]
        for method in ("centralized", "admm"):
            yield method, [r for r in rows if r["method"] == method]
        yield "with obstacles", [r for r in rows if r["obstacles"]]
        yield "no obstacles", [r for r in rows if not r["obstacles"]]
        for lo, hi in ((2, 4), (5, 8), (9, 12), (13, 16)):
            yield f"M {lo}-{hi}", [r for r in rows if lo <= r["agents"] <= hi]

    for label, group in groups():
        if group:
            lines.append(_group_rows(group, label))
    bad = [r for r in rows if not r["all_reached"] or (r["collision"] == "hard" and r["collisions"])
           or r["obstacle_penetration"] > 1e-9]
    lines += ["", f"Scenarios that did not reach every goal, collided in hard mode or entered an obstacle: {len(bad)}",
              ""]
    if bad:
        lines += ["| scenario | steps | reached | max final gap [m] | collisions | min sep/Δ | obstacle pen. | "
                  "failed solves | deadlocks |", "|" + "---|" * 9]
        lines += [f"| {r['name']} | {r['steps']} | {r['reached']}/{r['agents']} | {r['max_final_gap']:.2f} | "
                  f"{r['collisions']} | {r['min_sep_ratio']:.3f} | {r['obstacle_penetration']:.3f} | "
                  f"{r['solver_failures']} | {r['deadlocks']} |" for r in bad]
    return "\n".join(lines) + "\n"


def main() -> None:
    from swarmpc.solvers.executors import available_cores

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=200, help="number of scenarios")
    parser.add_argument("--seed", type=int, default=0, help="suite seed")
    parser.add_argument("--jobs", type=int, default=available_cores(),
                        help="worker processes [the cores this process may use]")
    parser.add_argument("--small", action="store_true", help="the quick subset (M 2-4, mostly 2D)")
    parser.add_argument("--save-runs", action="store_true", help="keep every run folder under --out")
    parser.add_argument("--out", type=Path, default=OUT, help="output folder")
    parser.add_argument("--table-from", type=Path, default=None,
                        help="only write the tables from a JSON-lines journal of an unfinished suite")
    args = parser.parse_args()
    if args.table_from is not None:
        rows = sorted((json.loads(line) for line in args.table_from.read_text().splitlines()),
                      key=lambda r: r["index"])
        print(markdown(rows, f"python benchmarks/stress.py (partial: {len(rows)} scenarios)", float("nan")))
        return
    args.out.mkdir(parents=True, exist_ok=True)
    stem = "stress-small" if args.small else "stress"
    runs_dir = str(args.out / f"{stem}-runs") if args.save_runs else None
    started = time.perf_counter()
    journal = args.out / f"{stem}.jsonl"
    journal.unlink(missing_ok=True)
    rows = run_suite(args.count, args.seed, args.jobs, args.small, runs_dir, journal=journal)
    wall = time.perf_counter() - started
    command = (f"python benchmarks/stress.py --count {args.count} --seed {args.seed} --jobs {args.jobs}"
               + (" --small" if args.small else ""))
    (args.out / f"{stem}.json").write_text(json.dumps({"command": command, "wall_s": wall, "rows": rows}, indent=1))
    text = markdown(rows, command, wall)
    (args.out / f"{stem}.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
