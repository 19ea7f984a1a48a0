"""Which initial guess helps: straight, shifted, RRT, auto (and lambda seeding on/off).

Closed loop (ADMM, the default solver) over seeded random variants of the three obstacle
scenarios (wall-door, pillars, u-trap; a few 3D ones) and the paper's swaps (paper-2d, paper-3d),
once per guess configuration. Success is recomputed from the trajectories, not taken from the
summary: every agent at its goal, no pair with ||p_i - p_j||_inf < delta at any instant, and no
position inside an obstacle. Writes ``benchmarks/out/guess_study.md`` and ``guess_study.json``
(one row per run) and the trajectories in ``benchmarks/out/guess_study_runs/``.

    nice -n 10 python benchmarks/guess_study.py --jobs 2        # the full study
    python benchmarks/guess_study.py --quick                    # a smoke run (few scenarios)

Configurations:

* ``straight`` / ``shifted`` / ``rrt`` / ``auto``: ``solver.initial_guess`` (lambda seeded);
* ``auto, lambda=0``: the default with ``solver.seed_duals: false``;
* ``rrt, no waypoints`` (obstacle scenarios only): the RRT state guess WITHOUT the RRT waypoint
  that ``rrt``/``auto`` also use as the MPC's goal while the straight line is blocked, to
  separate what the guess itself does from what the sub-goal does.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from swarmpc.batch import Task, run_batch

OUT = Path(__file__).parent / "out"
DELTA = 0.2
TRAPPED = 0.5  # a run that ends farther than this from a goal is caught, not just slow
SCALE = 0.7  # layouts are drawn in a 6 m box, then shrunk to 4.2 m (run time)
PAPER_SCENARIOS = ("paper-2d", "paper-3d")
CONFIGS: dict[str, dict[str, Any]] = {
    "straight": {"solver.initial_guess": "straight"},
    "shifted": {"solver.initial_guess": "shifted"},
    "rrt": {"solver.initial_guess": "rrt"},
    "auto": {"solver.initial_guess": "auto"},
    "auto, lambda=0": {"solver.initial_guess": "auto", "solver.seed_duals": False},
    "rrt, no waypoints": {"solver.initial_guess": "rrt"},
}
NO_STEER = "rrt, no waypoints"
BASE = {"dt": 0.1, "horizon": 10, "weights": {"Q": 0.1, "R": 1.0, "Qf": 1.0}, "delta": DELTA}


# ----------------------------------------------------------------------------- scenario families


def _box(center: list[float], half: list[float]) -> dict[str, Any]:
    return {"box": {"center": [round(c, 4) for c in center], "half_size": [round(h, 4) for h in half]}}


def _spread(rng: np.random.Generator, low: np.ndarray, high: np.ndarray, count: int,
            gap: float, taken: list[np.ndarray] | None = None) -> np.ndarray:
    """``count`` points uniform in [low, high], pairwise (and from ``taken``) >= gap apart (inf-norm)."""
    points: list[np.ndarray] = []
    others = list(taken or [])
    for _ in range(10000):
        p = rng.uniform(low, high)
        if all(np.max(np.abs(p - q)) >= gap for q in points + others):
            points.append(p)
            if len(points) == count:
                return np.array(points)
    raise RuntimeError("could not place the agents")


def wall_door_variant(seed: int) -> dict[str, Any]:
    """A wall across the workspace at a random x with a random door; agents swap sides."""
    rng = np.random.default_rng(seed)
    wx, door, half_door = rng.uniform(-0.4, 0.4), rng.uniform(-1.2, 1.2), rng.uniform(0.45, 0.7)
    t = 0.15
    top, bottom = door + half_door, door - half_door
    obstacles = [_box([wx, (top + 3.0) / 2], [t, (3.0 - top) / 2]),
                 _box([wx, (bottom - 3.0) / 2], [t, (bottom + 3.0) / 2])]
    m = 2 + int(rng.random() < 0.25)  # mostly one agent per side, sometimes three
    left = m // 2 + m % 2
    lo_l, hi_l = np.array([-2.7, -2.6]), np.array([wx - 1.2, 2.6])
    lo_r, hi_r = np.array([wx + 1.2, -2.6]), np.array([2.7, 2.6])
    starts_l, starts_r = _spread(rng, lo_l, hi_l, left, 0.6), _spread(rng, lo_r, hi_r, m - left, 0.6)
    goals_r = _spread(rng, lo_r, hi_r, left, 0.6, list(starts_r))
    goals_l = _spread(rng, lo_l, hi_l, m - left, 0.6, list(starts_l))
    starts, goals = np.vstack([starts_l, starts_r]), np.vstack([goals_r, goals_l])
    return {"name": f"wall-door-v{seed}", "dim": 2, **BASE,
            "workspace": {"lower": [-3.0, -3.0], "upper": [3.0, 3.0]}, "obstacles": obstacles,
            "agents": _agents(starts, goals)}


def pillars_variant(seed: int) -> dict[str, Any]:
    """5-8 random square pillars (>= 0.7 m apart) in the middle; agents cross the field."""
    rng = np.random.default_rng(seed)
    count = int(rng.integers(5, 9))
    centers: list[np.ndarray] = []
    halves: list[float] = []
    for _ in range(5000):
        c, h = rng.uniform(-1.4, 1.4, size=2), float(rng.uniform(0.15, 0.3))
        if all(np.max(np.abs(c - q)) - h - hq >= 0.7 for q, hq in zip(centers, halves, strict=True)):
            centers.append(c)
            halves.append(h)
            if len(centers) == count:
                break
    obstacles = [_box(c.tolist(), [h, h]) for c, h in zip(centers, halves, strict=True)]
    m = int(rng.integers(2, 4))
    starts, goals = [], []
    for i in range(m):
        side = i % 4  # left -> right, right -> left, bottom -> top, top -> bottom
        a, b = rng.uniform(-2.2, 2.2, size=2)
        pairs = [([-2.6, a], [2.6, b]), ([2.6, a], [-2.6, b]), ([a, -2.6], [b, 2.6]), ([a, 2.6], [b, -2.6])]
        starts.append(pairs[side][0])
        goals.append(pairs[side][1])
    starts_a, goals_a = _separate(rng, np.array(starts)), _separate(rng, np.array(goals))
    return {"name": f"pillars-v{seed}", "dim": 2, **BASE,
            "workspace": {"lower": [-3.0, -3.0], "upper": [3.0, 3.0]}, "obstacles": obstacles,
            "agents": _agents(starts_a, goals_a)}


def _separate(rng: np.random.Generator, points: np.ndarray, gap: float = 0.6) -> np.ndarray:
    """Nudge points along the edge they sit on until pairwise >= gap apart (inf-norm)."""
    points = points.copy()
    for _ in range(1000):
        clash = [(i, j) for i in range(len(points)) for j in range(i) if np.max(np.abs(points[i] - points[j])) < gap]
        if not clash:
            return points
        i, _j = clash[0]
        free = 1 if abs(points[i, 0]) > 2.5 else 0  # move along the edge
        points[i, free] = rng.uniform(-2.2, 2.2)
    raise RuntimeError("could not separate the agents")


def u_trap_variant(seed: int) -> dict[str, Any]:
    """A U open towards the agents (random size, position and one of four orientations)."""
    rng = np.random.default_rng(seed)
    depth, half_width, t = rng.uniform(0.8, 1.3), rng.uniform(0.7, 1.1), 0.1
    cx, cy = rng.uniform(-0.3, 0.3, size=2)
    # local frame: opening towards -x, back wall at x = cx + depth / 2
    local = [([cx + depth / 2, cy], [t, half_width + t]),
             ([cx, cy + half_width], [depth / 2, t]),
             ([cx, cy - half_width], [depth / 2, t])]
    m = int(rng.integers(1, 3))
    starts = _spread(rng, np.array([-2.6, cy - 0.8]), np.array([-1.9, cy + 0.8]), m, 0.5)
    goals = _spread(rng, np.array([1.9, -1.5]), np.array([2.6, 1.5]), m, 0.5)
    turn = int(rng.integers(0, 4))
    rot = np.linalg.matrix_power(np.array([[0.0, -1.0], [1.0, 0.0]]), turn)
    obstacles = [_box((rot @ np.array(c)).tolist(), np.abs(rot @ np.array(h)).tolist()) for c, h in local]
    return {"name": f"u-trap-v{seed}", "dim": 2, **BASE,
            "workspace": {"lower": [-3.0, -3.0], "upper": [3.0, 3.0]}, "obstacles": obstacles,
            "agents": _agents(starts @ rot.T, goals @ rot.T)}


def window_3d_variant(seed: int) -> dict[str, Any]:
    """3D: a wall at x ~ 0 with a square window; two drones swap sides through it."""
    rng = np.random.default_rng(seed)
    wy, wz, h = rng.uniform(-0.8, 0.8), rng.uniform(1.0, 2.0), rng.uniform(0.45, 0.6)
    t = 0.15
    obstacles = [_box([0.0, (wy + h + 3.0) / 2, 1.5], [t, (3.0 - wy - h) / 2, 1.5]),
                 _box([0.0, (wy - h - 3.0) / 2, 1.5], [t, (wy - h + 3.0) / 2, 1.5]),
                 _box([0.0, wy, (wz + h + 3.0) / 2], [t, h, (3.0 - wz - h) / 2]),
                 _box([0.0, wy, (wz - h) / 2], [t, h, (wz - h) / 2])]
    starts = np.array([[-2.2, *rng.uniform([-2.0, 0.5], [2.0, 2.5])], [2.2, *rng.uniform([-2.0, 0.5], [2.0, 2.5])]])
    goals = np.array([[2.2, *rng.uniform([-2.0, 0.5], [2.0, 2.5])], [-2.2, *rng.uniform([-2.0, 0.5], [2.0, 2.5])]])
    return {"name": f"window-3d-v{seed}", "dim": 3, **BASE,
            "workspace": {"lower": [-3.0, -3.0, 0.0], "upper": [3.0, 3.0, 3.0]}, "obstacles": obstacles,
            "agents": _agents(starts, goals)}


def _agents(starts: np.ndarray, goals: np.ndarray) -> list[dict[str, list[float]]]:
    return [{"start": s.round(4).tolist(), "goal": g.round(4).tolist()} for s, g in zip(starts, goals, strict=True)]


FAMILIES = {"wall-door": wall_door_variant, "pillars": pillars_variant, "u-trap": u_trap_variant,
            "window-3d": window_3d_variant}


def _scaled(data: dict[str, Any], factor: float) -> dict[str, Any]:
    """The layout shrunk about the origin (z kept for 3D): shorter runs, same topology."""
    dim = data["dim"]
    scale = np.array([factor] * 2 + [1.0] * (dim - 2))
    data["workspace"] = {k: (np.array(v) * scale).round(4).tolist() for k, v in data["workspace"].items()}
    data["obstacles"] = [_box((np.array(o["box"]["center"]) * scale).tolist(),
                              (np.array(o["box"]["half_size"]) * scale).tolist()) for o in data["obstacles"]]
    data["agents"] = [{k: (np.array(v) * scale).round(4).tolist() for k, v in a.items()} for a in data["agents"]]
    return data


def generate(counts: dict[str, int], max_steps: int, scale: float = SCALE) -> list[dict[str, Any]]:
    """Valid scenario dicts: ``counts[family]`` per family, seeds 1, 2, ... (invalid draws skipped),
    every layout shrunk by ``scale`` so that a run takes ~200 steps."""
    from swarmpc.config import ScenarioError, scenario_from_dict

    out = []
    for family, count in counts.items():
        seed = 0
        made = 0
        while made < count:
            seed += 1
            try:
                data = _scaled(FAMILIES[family](seed), scale)
                data["stop"] = {"max_steps": max_steps}
                data["seed"] = seed
                scenario_from_dict(data)
            except (ScenarioError, RuntimeError):
                continue
            out.append(data)
            made += 1
    return out


# ----------------------------------------------------------------------------- one run


def run_one(task: tuple[dict[str, Any] | str, str, int | None]) -> dict[str, Any]:
    """Run one (scenario, configuration) pair in closed loop; success recomputed from the states."""
    spec, config, max_steps = task
    from swarmpc.config import scenario_from_dict
    from swarmpc.model.geometry import count_collisions, obstacle_penetration
    from swarmpc.scenarios import builtin_scenario
    from swarmpc.simulation import loop
    from swarmpc.simulation.guessing import GuessProvider

    scn = builtin_scenario(spec) if isinstance(spec, str) else scenario_from_dict(spec)
    updates = dict(CONFIGS[config])
    if max_steps is not None:
        updates["stop.max_steps"] = max_steps
    scn = scn.with_updates(**updates)
    provider: type[GuessProvider] = GuessProvider
    if config == NO_STEER:
        class NoWaypoints(GuessProvider):
            """The RRT state guess only: the MPC always aims at the real goal."""

            def goals(self, states: np.ndarray, goals: np.ndarray) -> np.ndarray:
                return goals

        provider = NoWaypoints  # the ablation: the controller builds this provider instead
    started, cpu = time.perf_counter(), time.process_time()
    result = loop.simulate(scn, guess_provider=provider)
    wall, cpu = time.perf_counter() - started, time.process_time() - cpu
    d = scn.dim
    states = result.states
    positions = states[:, :, :d]
    goals = scn.goal_states()
    final_gap = np.linalg.norm(states[-1, :, :d] - goals[:, :d], axis=1)
    collisions = count_collisions(positions, scn.delta_vector)
    penetration = max((float(obstacle_penetration(positions, G, g).max()) for G, g in scn.obstacle_halfspaces()),
                      default=-np.inf)
    reached = bool(result.summary["all_reached"])
    step_ms = np.array([r.wall_time for r in result.records]) * 1000.0
    iterations = np.array([r.admm_iterations or 0 for r in result.records], float)
    s = result.summary
    name = scn.name
    folder = OUT / os.environ.get("GUESS_STUDY_RUNS", "guess_study_runs")  # set by main() from --name
    folder.mkdir(parents=True, exist_ok=True)
    tag = f"{name}__{config.replace(', ', '_').replace('=', '').replace(' ', '-')}"
    np.savez_compressed(folder / f"{tag}.npz", states=states, goals=goals, delta=scn.delta_vector, dt=scn.dt,
                        step_ms=step_ms, iterations=iterations)
    return {
        "scenario": name,
        "family": _family(name),
        "dim": d,
        "agents": scn.num_agents,
        "obstacles": len(scn.obstacles),
        "config": config,
        "reached": reached,
        "collisions": collisions,
        "max_penetration": penetration if np.isfinite(penetration) else None,
        "success": bool(reached and collisions == 0 and penetration <= 1e-9),
        "steps": int(s["steps"]),
        "max_final_gap": float(final_gap.max()),
        "cost": float(s["cost"]),
        "step_ms": step_ms.tolist(),
        "step_ms_median": float(np.median(step_ms)) if step_ms.size else None,
        "step_ms_p95": float(np.percentile(step_ms, 95)) if step_ms.size else None,
        "iterations_mean": float(iterations.mean()) if iterations.size else None,
        "iterations_median": float(np.median(iterations)) if iterations.size else None,
        "solver_failures": int(s["solver_failures"]),
        "repairs": int(s.get("admm_repairs", 0) or 0),
        "rrt": s.get("rrt"),
        "wall_s": wall,
        "cpu_ms_per_step": 1000.0 * cpu / max(int(s["steps"]), 1),
    }


def _family(name: str) -> str:
    for family in (*FAMILIES, *PAPER_SCENARIOS):
        if name.startswith(family):
            return family
    return name


# ----------------------------------------------------------------------------- report


def _fmt(value: float | None, digits: int = 1) -> str:
    return "n/a" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def aggregate(rows: list[dict[str, Any]], configs: list[str]) -> list[str]:
    """Markdown tables: all runs per configuration, then paired on the runs every config solved."""
    lines: list[str] = []
    for title, subset in (("Obstacle scenarios", [r for r in rows if r["obstacles"]]),
                          ("Paper swaps (no obstacles)", [r for r in rows if not r["obstacles"]])):
        if not subset:
            continue
        scenarios = sorted({r["scenario"] for r in subset})
        present = [c for c in configs if any(r["config"] == c for r in subset)]
        by = {(r["scenario"], r["config"]): r for r in subset}
        common = [s for s in scenarios if all(by.get((s, c), {}).get("success") for c in present)]
        lines += [f"### {title}: {len(scenarios)} scenarios", "",
                  "| guess | success | reached | trapped (> 0.5 m from goal at the cap) | runs with collisions | "
                  "obstacle hits | step ms median | p95 | CPU ms/step | ADMM it. mean | solver failures | "
                  "RRT plans / reuses / failed plans |",
                  "|" + "---|" * 12]
        for c in present:
            runs = [by[(s, c)] for s in scenarios if (s, c) in by]
            steps = np.concatenate([r["step_ms"] for r in runs]) if runs else np.array([])
            its = np.concatenate([[r["iterations_mean"]] * r["steps"] for r in runs]) if runs else np.array([])
            rrt = [r["rrt"] for r in runs if r["rrt"]]
            plans = sum(x["fresh"] for x in rrt)
            reuses = sum(x["reused"] for x in rrt)
            failed = sum(x["failed"] for x in rrt)
            cpu_ms = sum(r["cpu_ms_per_step"] * r["steps"] for r in runs) / max(sum(r["steps"] for r in runs), 1)
            lines.append(
                f"| {c} | {sum(r['success'] for r in runs)}/{len(runs)} | "
                f"{sum(r['reached'] for r in runs)}/{len(runs)} | "
                f"{sum(r['max_final_gap'] > TRAPPED for r in runs)} | {sum(r['collisions'] > 0 for r in runs)} | "
                f"{sum((r['max_penetration'] or -1) > 1e-9 for r in runs)} | "
                f"{_fmt(np.median(steps) if steps.size else None)} | "
                f"{_fmt(np.percentile(steps, 95) if steps.size else None)} | "
                f"{_fmt(cpu_ms)} | "
                f"{_fmt(its.mean() if its.size else None, 2)} | {sum(r['solver_failures'] for r in runs)} | "
                + (f"{plans} / {reuses} / {failed} |" if rrt else "- |")
            )
        lines += ["", f"Paired on the {len(common)} scenarios that every configuration above solved "
                  "(per-run medians, then the median over scenarios; cost relative to `auto`):", "",
                  "| guess | step ms (median of run medians) | run p95 (median) | CPU ms/step (median) | "
                  "ADMM it. mean | steps | cost vs auto (median) | cost vs auto (worst) |", "|" + "---|" * 8]
        for c in present:
            runs = [by[(s, c)] for s in common]
            if not runs:
                continue
            ratio = [100 * (by[(s, c)]["cost"] / by[(s, "auto")]["cost"] - 1) for s in common if (s, "auto") in by]
            lines.append(
                f"| {c} | {_fmt(np.median([r['step_ms_median'] for r in runs]))} | "
                f"{_fmt(np.median([r['step_ms_p95'] for r in runs]))} | "
                f"{_fmt(np.median([r['cpu_ms_per_step'] for r in runs]))} | "
                f"{_fmt(np.mean([r['iterations_mean'] for r in runs]), 2)} | "
                f"{_fmt(np.median([r['steps'] for r in runs]), 0)} | "
                f"{_fmt(np.median(ratio) if ratio else None, 1)}% | "
                f"{_fmt(max(ratio, key=abs) if ratio else None, 1)}% |"
            )
        lines.append("")
    return lines


def per_scenario(rows: list[dict[str, Any]], configs: list[str]) -> list[str]:
    """One line per scenario: outcome per configuration (ok / stuck / collision) and median step ms."""
    scenarios = sorted({r["scenario"] for r in rows}, key=lambda s: (_family(s), s))
    present = [c for c in configs if any(r["config"] == c for r in rows)]
    by = {(r["scenario"], r["config"]): r for r in rows}
    lines = ["| scenario | M | " + " | ".join(present) + " |", "|" + "---|" * (len(present) + 2)]
    for s in scenarios:
        cells = []
        for c in present:
            r = by.get((s, c))
            if r is None:
                cells.append("-")
                continue
            verdict = "ok" if r["success"] else ("collision" if r["collisions"] or (r["max_penetration"] or -1) > 1e-9
                                                 else f"{'trapped' if r['max_final_gap'] > TRAPPED else 'slow'} "
                                                 f"{r['max_final_gap']:.2f} m")
            cells.append(f"{verdict}, {r['steps']} st, {_fmt(r['step_ms_median'])} ms")
        agents = next(r["agents"] for r in rows if r["scenario"] == s)
        lines.append(f"| {s} | {agents} | " + " | ".join(cells) + " |")
    return lines


def write_report(rows: list[dict[str, Any]], configs: list[str], header: list[str], name: str = "guess_study") -> None:
    OUT.mkdir(exist_ok=True)
    slim = [{k: v for k, v in r.items() if k != "step_ms"} for r in rows]
    (OUT / f"{name}.json").write_text(json.dumps(slim, indent=1))
    text = header + [""] + aggregate(rows, configs) + ["### Per scenario", ""] + per_scenario(rows, configs)
    (OUT / f"{name}.md").write_text("\n".join(text) + "\n")
    print("\n".join(text))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--jobs", type=int, default=2, help="parallel worker processes")
    parser.add_argument("--quick", action="store_true", help="smoke run: two small scenarios, 120 steps")
    parser.add_argument("--max-steps", type=int, default=300, help="step cap of the generated scenarios")
    parser.add_argument("--report", action="store_true",
                        help="only rebuild the report from the rows of the last (possibly partial) run")
    parser.add_argument("--configs", default=";".join(CONFIGS),
                        help="semicolon-separated subset of the configurations (default: all)")
    parser.add_argument("--no-paper", action="store_true", help="skip the paper swaps")
    parser.add_argument("--name", default="guess_study", help="basename of the outputs in benchmarks/out")
    args = parser.parse_args()
    chosen = [c.strip() for c in args.configs.split(";") if c.strip()]
    unknown = [c for c in chosen if c not in CONFIGS]
    if unknown:
        parser.error(f"unknown configuration(s) {unknown}; choose from {list(CONFIGS)}")
    rows_file = OUT / f"{args.name}_rows.jsonl"
    os.environ["GUESS_STUDY_RUNS"] = f"{args.name}_runs"  # inherited by the worker processes
    if args.report:
        saved: list[dict[str, Any]] = [json.loads(line) for line in rows_file.read_text().splitlines() if line.strip()]
        header = ["## Initial-guess study (generated by benchmarks/guess_study.py, rebuilt with --report)", "",
                  f"{len(saved)} runs; see the JSON for the settings."]
        write_report(sorted(saved, key=lambda r: (r["scenario"], r["config"])), list(CONFIGS), header, args.name)
        return
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    paper: tuple[str, ...]
    if args.quick:
        counts, max_steps, paper = {"wall-door": 1, "u-trap": 1}, 120, ()
        paper_steps: int | None = None
    else:
        counts = {"wall-door": 7, "pillars": 7, "u-trap": 6, "window-3d": 1}
        max_steps, paper = args.max_steps, PAPER_SCENARIOS
        paper_steps = None
    scenarios = generate(counts, max_steps)
    tasks: list[tuple[dict[str, Any] | str, str, int | None]] = []
    if args.no_paper:
        paper = ()
    spec: dict[str, Any] | str
    for spec in [*scenarios, *paper]:  # the paper swaps are the longest runs: last, so a cut-off
        for config in chosen:            # study still holds every obstacle scenario
            if config == NO_STEER and (isinstance(spec, str) or spec["name"].startswith("pillars")):
                continue  # no obstacles: nothing to steer around; pillars: lines of sight everywhere
            tasks.append((spec, config, paper_steps if isinstance(spec, str) else None))
    print(f"{len(scenarios)} generated scenarios + {len(paper)} paper swaps, {len(tasks)} runs, {args.jobs} jobs",
          flush=True)
    started = time.perf_counter()
    rows: list[dict[str, Any]] = []
    failed: list[str] = []
    OUT.mkdir(exist_ok=True)
    rows_file.write_text("")
    # a worker is renewed after 4 runs (with one job, every run is in this process)
    for done, finished in enumerate(run_batch([Task(run_one, (t,)) for t in tasks], args.jobs,
                                              max_tasks_per_worker=4), 1):
        progress = f"[{done}/{len(tasks)} {time.perf_counter() - started:6.0f}s]"
        if not finished.ok:
            spec, config, _ = tasks[finished.index]
            failed.append(f"{spec if isinstance(spec, str) else spec['name']} / {config}: {finished.error}")
            print(f"{progress} FAILED {failed[-1]}", flush=True)
            continue
        row = finished.value
        rows.append(row)
        with rows_file.open("a") as handle:
            handle.write(json.dumps(row) + "\n")
        print(f"{progress} {row['scenario']:>16} "
              f"{row['config']:>18}: success={row['success']} steps={row['steps']} "
              f"median={_fmt(row['step_ms_median'])} ms fails={row['solver_failures']} ({row['wall_s']:.0f}s)",
              flush=True)
    header = [
        "## Initial-guess study (generated by benchmarks/guess_study.py)", "",
        f"{len(scenarios)} generated obstacle scenarios ({', '.join(f'{k} x{v}' for k, v in counts.items())}; "
        f"delta {DELTA}, hard OBCA, ADMM defaults, max {max_steps} steps) and the paper swaps "
        f"({', '.join(paper)}). {len(tasks)} runs in {time.perf_counter() - started:.0f} s wall with {args.jobs} "
        "jobs on a shared 2-core machine (timings are noisy; compare within a table). Success = every agent "
        "at its goal, no inf-norm collision, no obstacle penetration, recomputed from the states.",
    ]
    write_report(sorted(rows, key=lambda r: (r["scenario"], r["config"])), list(CONFIGS), header, args.name)
    if failed:
        sys.exit(f"{len(failed)} run(s) failed and are not in the report:\n" + "\n".join(failed))


if __name__ == "__main__":
    main()
