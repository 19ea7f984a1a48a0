"""The scaling benchmark behind ``swarmpc bench``: swarms of growing size, one table.

Families (all with Δ = 0.3 and the paper's weights): ``circle`` (2D antipodal swap), ``sphere``
(3D antipodal swap), ``random`` (3D, seeded starts and goals in a 3 x 3 x 2 m box, >= 0.5 m
apart and >= 0.1 m from each other's delta box, acceleration <= 1 m/s² per axis, goal tolerance
0.1 m) and ``spread`` (``random`` at constant density: the box grows as (M / 8)^(1/3) per side, so
neighbourhoods stay the size they have at M = 8 and the work per agent can be read against M
alone). Each case is one closed-loop run; cases run side by side in worker processes
(:mod:`swarmpc.batch`), or one after another in this process with one job. Collisions and
separations come from the run's trajectory, never from a flag. An ADMM case can run once per
local step (``solver.local``: ``ipopt``, ``qp``), the runs of one case planned one after the
other, so that the two local steps are measured on the machine in the same state; the table
then has a row per local step, with the local solves the QP local step handed to IPOPT.
Numbers are wall-clock measurements on whatever machine runs it: read them as such.

Car family, never run by default: ``crossing`` (the built-in of that name with its own weights,
limits and tolerances: M cars, M / 4 queued on each arm of a four-way crossing, all going straight
across). Its sizes are multiples of 4; another size is refused before anything runs. It runs with
the same methods as the others (ADMM per local step, centralised up to ``central_max_agents``); a
case the scenario validation refuses fails like any failing case, with its one-line reason. Its
collisions and its smallest gap between two cars come from the exact distance between the rotated
footprints (:func:`swarmpc.simulation.metrics.car_safety`), so its rows give that gap [m] in a
column of its own (shown when a row has one) instead of ``min sep/Δ``. A size run centralised only
(no ADMM run measured, e.g. every ADMM case failed) has one row of its centralised runs, local step
``centralized``, with the same compute columns (a centralised step's per-agent compute is its
solve split evenly over the agents, its critical path the whole solve).

Closed-loop quality (:mod:`swarmpc.simulation.quality`): each run's makespan and largest overshoot,
and for an ADMM run that brought every agent to its goal, the interaction ratio, its makespan over
the latest of its agents' lone-agent times (each agent simulated alone, same scenario and
controller). The lone runs are made here and not by every ``swarmpc run``: they are M extra closed
loops, a cost only a benchmark should pay.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from contextlib import closing
from dataclasses import MISSING, asdict, dataclass, fields, replace
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np

from swarmpc.batch import Finished, QuietStart, Task, run_batch
from swarmpc.config import Scenario, SolverConfig, default_local, scenario_from_dict
from swarmpc.model.geometry import body_separation_ratio, count_body_collisions
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.loop import StopFlag, simulate
from swarmpc.simulation.metrics import car_safety, final_goal_distance
from swarmpc.simulation.quality import interaction_ratio, time_to_goal
from swarmpc.simulation.results import write_run
from swarmpc.solvers.executors import Executor, available_cores, make_executor

FAMILIES = ("circle", "sphere", "random", "spread", "crossing")
SEEDED_FAMILIES = ("random", "spread")
DEFAULT_FAMILIES = ("circle", "sphere", "random")
CAR_FAMILIES = ("crossing",)
"""The families of cars: each is the built-in scenario of its name, with its own settings."""
SIZE_MULTIPLES: Mapping[str, int] = MappingProxyType({"crossing": 4})
"""Families whose swarm sizes must be multiples of a number (``crossing``: M / 4 cars per arm)."""
FULL_SIZES = (4, 8, 16, 32, 64)
QUICK_SIZES = (4, 8)
METHODS = ("admm", "centralized")
"""The methods a case runs (``solver.method``): ADMM, and the centralised reference."""
LOCAL_STEPS = ("ipopt", "qp")
"""The ADMM agents' local steps a case can use (``solver.local``)."""
CENTRAL_ROW = "centralized"
EXCURSION_SHOWN = 1e-3
"""[m] how far outside the workspace box a row's runs must have got for the table to show the
column (below it: the solvers' tolerances)."""
"""The local step (``local``) of a report row of centralised runs only: a size at which no ADMM
run was measured (:func:`aggregate`)."""
DEFAULT_LOCAL: str = SolverConfig.model_fields["local"].default
"""The local step of the benchmark's ADMM cases (a scenario's ``solver.local`` unless it sets one)."""
REPORTED_BEFORE_LOCAL = "ipopt"
"""The local step of a ``bench.json`` run written before cases recorded theirs (then the only one)."""
CENTRAL_LOCAL = "ipopt"
"""The ``local`` of a centralised case: its one NLP is solved by IPOPT, whatever the ADMM default."""


@dataclass(frozen=True)
class BenchCase:
    """One run of the benchmark: a family, a swarm size, a seed and the solver to use."""

    family: str
    agents: int
    seed: int
    method: str = "admm"
    executor: str = "serial"
    workers: int | None = None
    budget_s: float = 600.0
    max_steps: int | None = None
    plane_margin: float | None = None
    """``solver.plane_margin`` of an ADMM case (None: the scenario's own)."""
    local: str = ""
    """``solver.local`` of an ADMM case: the agents' local step, ``ipopt`` or ``qp``; empty: the
    family's own (:func:`family_local`). A centralised case has none: :data:`CENTRAL_LOCAL`
    whatever is given."""
    settings: tuple[tuple[str, Any], ...] = ()
    """Scenario keys (dotted, ``weights.Q``) and values set on the case's scenario before the
    benchmark's own (``--set``): a tuning compared on the same families."""

    def __post_init__(self) -> None:
        if self.method == "centralized":  # one reference per seed, whichever local steps ADMM ran
            object.__setattr__(self, "local", CENTRAL_LOCAL)
        elif not self.local:
            object.__setattr__(self, "local", family_local(self.family))

    def scenario(self) -> Scenario:
        """The case's scenario (built-in generators; see the module docstring)."""
        if self.family in SEEDED_FAMILIES:
            scn = builtin_scenario(self.family, agents=self.agents, dim=3, seed=self.seed)
        elif self.family in CAR_FAMILIES:
            scn = builtin_scenario(self.family, agents=self.agents, seed=self.seed)
        else:
            scn = builtin_scenario("circle", agents=self.agents, dim=2 if self.family == "circle" else 3)
            scn = scn.with_updates(**{"limits.accel": 1.0, "stop.goal_tolerance": 0.1, "seed": self.seed})
        scn = scn.with_settings(dict(self.settings))  # a user's KEY=null sets null
        updates: dict[str, Any] = {"solver.method": self.method}
        if self.max_steps is not None:
            updates["stop.max_steps"] = self.max_steps
        if self.plane_margin is not None and self.method == "admm":
            updates["solver.plane_margin"] = self.plane_margin
        if self.method == "admm":
            updates["solver.local"] = self.local
        return scn.with_updates(**updates)

    @property
    def label(self) -> str:
        """A name for the case's run folder: ``random-M64-seed1-admm``, with the local step appended
        when it is not the family's own (``random-M64-seed1-admm-ipopt``)."""
        local = f"-{self.local}" if self.method == "admm" and self.local != family_local(self.family) else ""
        return f"{self.family}-M{self.agents}-seed{self.seed}-{self.method}{local}"

    @property
    def name(self) -> str:
        """The case in words, for progress lines and messages: ``random M=64 seed=1 admm qp``."""
        local = f" {self.local}" if self.method == "admm" else ""
        return f"{self.family} M={self.agents} seed={self.seed} {self.method}{local}"


@dataclass(frozen=True)
class CaseOutcome:
    """What one case measured (a row of the JSON file)."""

    case: BenchCase
    steps: int
    timed_out: bool
    all_reached: bool
    collisions: int
    min_separation_ratio: float
    time_to_goal_s: float | None
    cost: float
    step_ms: list[float]
    agent_step_ms: list[float]
    iterations: list[int]
    solver_failures: int
    wall_time_s: float
    unreached: tuple[int, ...] = ()
    """Agents not within the goal tolerance at the end of the run."""
    worst_goal_distance: float = 0.0
    """Largest final distance of an agent from its goal [m]."""
    copies_mean: float | None = None
    """Neighbours' copies an agent held, averaged over agents and steps (ADMM; None: centralised
    or a report written before it was recorded)."""
    planes_mean: float | None = None
    """Separating planes an agent kept to, averaged over agents and steps (ADMM with
    ``solver.plane_margin``; None: centralised or a report written before it was recorded)."""
    makespan_s: float | None = None
    """Latest time to goal over the agents (``summary.json`` ``makespan_s``); None unless every
    agent reached, or in a report written before it was recorded."""
    overshoot_max_m: float | None = None
    """Largest overshoot past the goal of any agent [m] (``summary.json`` ``overshoot_m``)."""
    lone_makespan_s: float | None = None
    """Latest of the agents' lone-agent times to goal (ADMM runs that reached every goal only)."""
    interaction_ratio: float | None = None
    """``makespan_s`` over ``lone_makespan_s``: 1 when the agents did not slow each other down."""
    critical_path_ms: list[float] | None = None
    """Per step, the compute on its critical path [ms] (``steps.npz`` ``critical_path_s``: what the
    step would take with one core per agent); None in a report written before it was recorded."""
    deadline_misses: int | None = None
    """Steps whose critical path exceeded the run's budget (``summary.json`` ``deadline_misses``:
    ``solver.deadline``, else dt); None in a report written before it was recorded."""
    local_fallbacks: int | None = None
    """Local solves the QP local step failed and IPOPT answered instead (``summary.json``
    ``local_fallbacks``; 0 on the IPOPT local step); None in a report written before it was recorded."""
    workspace_excursion_m: float | None = None
    """Farthest an agent got outside the workspace box [m] (``summary.json``
    ``max_workspace_excursion``); None without a workspace or in a report written before it was
    recorded."""
    min_footprint_distance: float | None = None
    """Smallest exact distance between two agents' footprints over the run [m] (a swarm with cars;
    None otherwise). ``min_separation_ratio`` of such a run is that of ``summary.json``, between
    the body boxes around the agents' reference points, and the table does not show it."""



def run_case(case: BenchCase, runs_dir: Path | None = None) -> CaseOutcome:
    """Run one case in closed loop, stopping cleanly when its wall-time budget is spent; with
    ``runs_dir``, keep its run folder (``summary.json``, ``trajectory.npz``) there too."""
    scn = case.scenario()
    executor = _case_executor(case)
    stop = StopFlag()
    timer = threading.Timer(case.budget_s, lambda: setattr(stop, "requested", True))
    timer.start()
    started = time.perf_counter()
    try:
        result = simulate(scn, stop_flag=stop, executor=executor)
    finally:
        timer.cancel()
        if executor is not None:  # this function made it, this function closes it (interrupted too)
            executor.close()
    wall = time.perf_counter() - started
    summary = result.summary
    lone = lone_agent_times(scn) if case.method == "admm" and summary["makespan_s"] is not None else None
    if runs_dir is not None:
        write_run(result, runs_dir / case.label, overwrite=True)
    d = scn.dim
    positions = result.states[:, :, :d]
    collisions = count_body_collisions(positions, scn.bodies)
    separation = float(body_separation_ratio(positions, scn.bodies).min()) if scn.num_agents > 1 else float("inf")
    footprint_gap = None
    if scn.has_cars:  # the exact distance between the rotated footprints, not boxes around the reference points
        safety = car_safety(scn, result.states)
        collisions, footprint_gap = safety["collisions"], safety["min_footprint_distance"]
    records = result.records
    return CaseOutcome(
        case=case,
        steps=len(records),
        timed_out=bool(summary["interrupted"]),
        all_reached=bool(summary["all_reached"]),
        collisions=int(collisions),
        min_separation_ratio=float(separation),
        time_to_goal_s=float(summary["sim_time_s"]) if summary["all_reached"] else None,
        cost=float(summary["cost"]),
        step_ms=[1000.0 * r.wall_time for r in records],
        agent_step_ms=[1000.0 * t for r in records for t in r.agent_times],
        critical_path_ms=[1000.0 * r.critical_path_s for r in records],
        deadline_misses=int(summary["deadline_misses"]),
        local_fallbacks=int(summary["local_fallbacks"]),
        iterations=[int(r.admm_iterations) for r in records if r.admm_iterations is not None],
        solver_failures=int(summary["solver_failures"]),
        wall_time_s=wall,
        unreached=tuple(i for i, done in enumerate(summary["reached"]) if not done),
        worst_goal_distance=float(final_goal_distance(result.states, scn).max()),
        copies_mean=_mean([r.copies for r in records if r.copies is not None]),
        planes_mean=_mean([r.planes for r in records if r.planes is not None]),
        makespan_s=summary["makespan_s"],
        overshoot_max_m=max(summary["overshoot_m"], default=None),
        lone_makespan_s=None if lone is None or np.isnan(lone).any() else float(lone.max()),
        interaction_ratio=None if lone is None else interaction_ratio(summary["makespan_s"], lone),
        workspace_excursion_m=summary["max_workspace_excursion"],
        min_footprint_distance=footprint_gap,
    )


def _case_executor(case: BenchCase) -> Executor | QuietStart | None:
    """Where an ADMM case's local solves run (None for a centralised case). Worker processes are
    started with SIGINT and SIGTERM held (:class:`swarmpc.batch.QuietStart`): a Ctrl-C meant for
    the benchmark must not kill a worker that is still starting, with a traceback, before it can
    ignore the signal."""
    if case.method != "admm":
        return None
    options: dict[str, Any] = {}
    if case.workers and case.executor in ("process", "ray"):
        options = {"workers" if case.executor == "process" else "actors": case.workers}
    executor = make_executor(case.executor, **options)
    return QuietStart(executor) if case.executor == "process" else executor


def lone_agent_times(scn: Scenario) -> np.ndarray:
    """Each agent's time to goal when it is alone: the same scenario (weights, limits, obstacles,
    solver) with only that agent, in closed loop; (M,), NaN for an agent that never reached."""
    data = scn.model_dump()
    times = np.full(scn.num_agents, np.nan)
    for i, agent in enumerate(data["agents"]):
        alone = scenario_from_dict({**data, "agents": [agent]})
        result = simulate(alone)
        times[i] = time_to_goal(result.states, alone.goal_states(), alone.dt, alone.stop.goal_tolerance)[0]
    return times


def _mean(values: Sequence[Any]) -> float | None:
    """Mean over every number in ``values`` (scalars or equal-length arrays); None when empty."""
    return float(np.mean(values)) if len(values) else None


def plan_cases(
    families: Iterable[str], sizes: Iterable[int], seeds: int, executor: str, workers: int | None,
    budget_s: float, central_max_agents: int, max_steps: int | None = None, first_seed: int = 0,
    plane_margin: float | None = None, locals_: Sequence[str] | None = None,
    settings: tuple[tuple[str, Any], ...] = (), methods: Sequence[str] = METHODS,
) -> list[BenchCase]:
    """Every case of the benchmark; the circle, sphere and crossing families are deterministic
    (one seed). The random and spread families run seeds ``first_seed`` … ``first_seed + seeds - 1``,
    so a long study can be split over machines or separate invocations without repeating a seed.
    Each ADMM case runs once per local step of ``locals_``, one right after the other (so that they
    meet the machine in the same state); the centralised reference runs once. ``locals_`` None:
    each family's own (:func:`family_local`). ``settings`` are set
    on every case's scenario. ``methods`` leaves out ADMM or the centralised runs (a study of one
    method). ValueError (one line) for a size a family does not take (:data:`SIZE_MULTIPLES`)."""
    families, sizes = tuple(families), tuple(sizes)
    if locals_ is not None:
        _check_locals(locals_)
    _check_sizes(families, sizes)
    unknown = sorted(set(methods) - set(METHODS))
    if unknown or not methods:
        raise ValueError(f"methods: {'unknown ' + ', '.join(unknown) if unknown else 'none given'} "
                         f"(choose from {', '.join(METHODS)})")
    cases: list[BenchCase] = []
    for family in families:
        for m in sizes:
            for seed in (range(first_seed, first_seed + seeds) if family in SEEDED_FAMILIES else range(1)):
                if "admm" in methods:
                    cases.extend(BenchCase(family, m, seed, "admm", executor, workers, budget_s, max_steps,
                                           plane_margin, local, settings)
                                 for local in locals_ or ("",))
                if m <= central_max_agents and "centralized" in methods:
                    cases.append(BenchCase(family, m, seed, "centralized", "serial", None, budget_s, max_steps,
                                           settings=settings))
    return cases


def _check_sizes(families: Iterable[str], sizes: Iterable[int]) -> None:
    """ValueError (``sizes: ...``, one line) when a family does not take one of the sizes."""
    for family in families:
        multiple = SIZE_MULTIPLES.get(family)
        wrong = [m for m in sizes if multiple and m % multiple]
        if wrong:
            raise ValueError(f"sizes: family {family} takes multiples of {multiple}, got {wrong[0]}")


def family_local(family: str) -> str:
    """The local step of a family's ADMM cases when none is asked for: that its scenarios take
    (:func:`swarmpc.config.default_local`: ipopt for the car families, else qp)."""
    return default_local(has_cars=family in CAR_FAMILIES)


def _check_locals(locals_: Sequence[str]) -> None:
    """ValueError (``local: ...``) unless ``locals_`` names local steps, each once."""
    unknown = sorted(set(locals_) - set(LOCAL_STEPS))
    if unknown or not locals_ or len(set(locals_)) != len(locals_):
        problem = f"unknown {', '.join(unknown)}" if unknown else "none given" if not locals_ else "repeated"
        raise ValueError(f"local: {problem} (choose from {', '.join(LOCAL_STEPS)}, each once)")


def _row_order(key: tuple[str, int, str]) -> tuple[int, int, int]:
    family, m, local = key
    return FAMILIES.index(family), m, LOCAL_STEPS.index(local) if local in LOCAL_STEPS else len(LOCAL_STEPS)


def _percentile(values: Sequence[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if len(values) else None


def aggregate(outcomes: Sequence[CaseOutcome]) -> list[dict[str, Any]]:
    """One row per (family, size, ADMM local step): rates over seeds, pooled step statistics, cost
    gap vs centralised (the one centralised run of a seed is every local step's reference).

    A size with centralised runs only has one row of those, local step :data:`CENTRAL_ROW`. A row
    of runs with cars gives ``min_footprint_distance_m`` and no ``min_separation_ratio``
    (:attr:`CaseOutcome.min_footprint_distance`)."""
    rows = []
    keys = {(o.case.family, o.case.agents, o.case.local) for o in outcomes if o.case.method == "admm"}
    admm_sizes = {key[:2] for key in keys}
    keys |= {(o.case.family, o.case.agents, CENTRAL_ROW) for o in outcomes
             if (o.case.family, o.case.agents) not in admm_sizes}  # centralised only: one row of them
    for family, m, local in sorted(keys, key=_row_order):
        central = {o.case.seed: o for o in outcomes
                   if (o.case.family, o.case.agents, o.case.method) == (family, m, "centralized")}
        runs = list(central.values()) if local == CENTRAL_ROW else [
            o for o in outcomes
            if (o.case.family, o.case.agents, o.case.method, o.case.local) == (family, m, "admm", local)]
        gaps = [100.0 * (o.cost / central[o.case.seed].cost - 1.0) for o in runs
                if o.case.method == "admm" and o.case.seed in central and o.all_reached
                and central[o.case.seed].all_reached]
        steps = [t for o in runs for t in o.step_ms]
        agent = [t for o in runs for t in o.agent_step_ms]
        iterations = [k for o in runs for k in o.iterations]
        reached_times = [o.time_to_goal_s for o in runs if o.time_to_goal_s is not None]
        makespans = [o.makespan_s for o in runs if o.makespan_s is not None]
        ratios = [o.interaction_ratio for o in runs if o.interaction_ratio is not None]
        critical = [t for o in runs for t in o.critical_path_ms or ()]
        misses = [o.deadline_misses for o in runs if o.deadline_misses is not None]
        handed = [o.local_fallbacks for o in runs if o.local_fallbacks is not None]
        rows.append({
            "family": family, "agents": m, "local": local, "runs": len(runs),
            "all_reached_rate": float(np.mean([o.all_reached for o in runs])) if runs else None,
            "collision_free_rate": float(np.mean([o.collisions == 0 for o in runs])) if runs else None,
            "timed_out": sum(o.timed_out for o in runs),
            "min_separation_ratio": min((o.min_separation_ratio for o in runs if o.min_footprint_distance is None),
                                        default=None),
            "time_to_goal_s_median": _percentile(reached_times, 50),
            "makespan_s_median": _percentile(makespans, 50),
            "overshoot_m_max": max((o.overshoot_max_m for o in runs if o.overshoot_max_m is not None), default=None),
            "workspace_excursion_m_max": max(
                (o.workspace_excursion_m for o in runs if o.workspace_excursion_m is not None), default=None),
            "interaction_ratio_median": _percentile(ratios, 50),
            "step_ms_median": _percentile(steps, 50), "step_ms_p95": _percentile(steps, 95),
            "critical_path_ms_median": _percentile(critical, 50), "critical_path_ms_p99": _percentile(critical, 99),
            "deadline_misses": sum(misses) if misses else None,
            "agent_ms_median": _percentile(agent, 50), "agent_ms_p95": _percentile(agent, 95),
            "agent_ms_p99": _percentile(agent, 99),
            "wall_s_per_run_median": _percentile([o.wall_time_s for o in runs], 50),
            "iterations_mean": float(np.mean(iterations)) if iterations else None,
            "iterations_max": max(iterations, default=None),
            "solver_failures": sum(o.solver_failures for o in runs),
            "local_fallbacks": sum(handed) if handed else None,
            "cost_gap_pct_median": _percentile(gaps, 50),
            "central_step_ms_median": _percentile([t for o in central.values() for t in o.step_ms], 50),
            "copies_mean": _mean([o.copies_mean for o in runs if o.copies_mean is not None]),
            "planes_mean": _mean([o.planes_mean for o in runs if o.planes_mean is not None]),
            "min_footprint_distance_m": min(
                (o.min_footprint_distance for o in runs if o.min_footprint_distance is not None), default=None),
        })
    return rows


def growth_exponents(rows: Sequence[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per family with two sizes or more: k in time ~ M^k, the least-squares slope of
    log(median) against log(M), for the per-step wall time and the per-agent compute.

    k <= 1 for the step time is "no worse than linear in M"; the per-agent k says how the work of
    one agent grows with the swarm (0 when neighbourhoods do not grow). Rows of another local step
    than the family's own are fitted apart, under ``family/local`` (``circle/ipopt``), and each fit
    names its ``local``.
    """
    out: dict[str, dict[str, Any]] = {}
    for family, local in dict.fromkeys((r["family"], r.get("local") or family_local(r["family"])) for r in rows):
        exponents: dict[str, Any] = {}
        for key, name in (("step_ms_median", "step"), ("agent_ms_median", "agent")):
            points = [(r["agents"], r[key]) for r in rows
                      if (r["family"], r.get("local") or family_local(r["family"])) == (family, local)
                      and r[key] is not None and r[key] > 0]
            if len({m for m, _ in points}) >= 2:
                log_m, log_t = np.log([m for m, _ in points]), np.log([t for _, t in points])
                exponents[name] = float(np.polyfit(log_m, log_t, 1)[0])
                exponents["sizes"] = sorted(m for m, _ in points)
        if exponents:
            out[family if local == family_local(family) else f"{family}/{local}"] = {**exponents, "local": local}
    return out


def step_growth_interval(
    outcomes: Sequence[CaseOutcome], family: str, level: float = 0.9, repeats: int = 1000, seed: int = 0,
    local: str = DEFAULT_LOCAL,
) -> tuple[float, float] | None:
    """How far the per-step exponent could move with other seeds: a percentile bootstrap over runs.

    Each repeat draws, at every size, as many ADMM runs (of local step ``local``) as there are,
    with replacement, pools their step times and fits the exponent of the medians as
    :func:`growth_exponents` does. The ``level`` interval of those fits is returned, or None when
    a size has fewer than two runs or there are fewer than two sizes (nothing to resample, or
    nothing to fit).
    """
    by_size: dict[int, list[np.ndarray]] = {}
    for o in outcomes:
        if o.case.family == family and o.case.method == "admm" and o.case.local == local and o.step_ms:
            by_size.setdefault(o.case.agents, []).append(np.asarray(o.step_ms, dtype=float))
    if len(by_size) < 2 or min(len(runs) for runs in by_size.values()) < 2:
        return None
    rng = np.random.default_rng(seed)
    sizes = sorted(by_size)
    log_m = np.log(sizes)
    slopes = np.empty(repeats)
    for r in range(repeats):
        medians = []
        for m in sizes:
            runs = by_size[m]
            drawn = rng.integers(len(runs), size=len(runs))
            medians.append(np.median(np.concatenate([runs[i] for i in drawn])))
        slopes[r] = np.polyfit(log_m, np.log(medians), 1)[0]
    tail = 50.0 * (1.0 - level)
    low, high = np.percentile(slopes, [tail, 100.0 - tail])
    return float(low), float(high)


def growth_lines(growth: dict[str, dict[str, Any]]) -> str:
    """One sentence per family for the markdown report."""
    lines = []
    for family, g in growth.items():
        sizes = g["sizes"]
        interval = (f" (90 % interval over resampled runs {g['step_interval'][0]:.2f}–{g['step_interval'][1]:.2f})"
                    if g.get("step_interval") else "")
        parts = [f"per-step wall time ~ M^{g['step']:.2f}{interval}" if "step" in g else None,
                 f"per-agent compute ~ M^{g['agent']:.2f}" if "agent" in g else None]
        lines.append(f"* {family} (M = {sizes[0]}…{sizes[-1]}, medians): "
                     + ", ".join(p for p in parts if p))
    return "\n".join(lines) + "\n" if lines else ""


def _cell(value: Any, fmt: str = "{:.1f}") -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return fmt.format(value)
    return str(value)


def markdown_table(rows: Sequence[dict[str, Any]]) -> str:
    """The benchmark table (one line per family, swarm size and ADMM local step). ``local
    fallbacks``: the local solves the QP local step handed to IPOPT, over the row's runs. A last
    column ``min footprint gap m`` (the exact distance between cars' footprints) is there when a
    row has one: a table of point swarms only stays as it was. So is a column ``outside workspace
    max m`` (how far an agent got outside the workspace box), when a row's runs left it by more
    than :data:`EXCURSION_SHOWN`."""
    footprints = any(r.get("min_footprint_distance_m") is not None for r in rows)
    excursions = any((r.get("workspace_excursion_m_max") or 0.0) > EXCURSION_SHOWN for r in rows)
    header = ("| family | M | local | runs | all reached | collision-free | timed out | min sep/Δ | time to goal s "
              "| makespan s | overshoot max m | makespan vs lone "
              "| step ms median | p95 | critical path ms median | p99 | deadline misses "
              "| per-agent ms median | p95 | p99 | wall s per run | ADMM it. mean | max | failures "
              "| local fallbacks | cost vs central | central step ms | copies per agent | planes per agent |"
              + (" min footprint gap m |" if footprints else "")
              + (" outside workspace max m |" if excursions else ""))
    lines = [header, "|" + "---|" * (header.count("|") - 1)]
    for r in rows:
        lines.append("| " + " | ".join([
            r["family"], str(r["agents"]), str(r.get("local") or family_local(r["family"])), str(r["runs"]),
            _cell(None if r["all_reached_rate"] is None else 100 * r["all_reached_rate"], "{:.0f}%"),
            _cell(None if r["collision_free_rate"] is None else 100 * r["collision_free_rate"], "{:.0f}%"),
            str(r["timed_out"]), _cell(r["min_separation_ratio"], "{:.2f}"),
            _cell(r["time_to_goal_s_median"]), _cell(r.get("makespan_s_median")),
            _cell(r.get("overshoot_m_max"), "{:.2f}"), _cell(r.get("interaction_ratio_median"), "{:.2f}"),
            _cell(r["step_ms_median"]), _cell(r["step_ms_p95"]),
            _cell(r.get("critical_path_ms_median")), _cell(r.get("critical_path_ms_p99")),
            _cell(r.get("deadline_misses")),
            _cell(r["agent_ms_median"]), _cell(r["agent_ms_p95"]), _cell(r.get("agent_ms_p99")),
            _cell(r.get("wall_s_per_run_median")), _cell(r["iterations_mean"]),
            _cell(r["iterations_max"]), str(r["solver_failures"]), _cell(r.get("local_fallbacks")),
            _cell(r["cost_gap_pct_median"], "{:+.1f}%"), _cell(r["central_step_ms_median"]),
            _cell(r.get("copies_mean"), "{:.2f}"), _cell(r.get("planes_mean"), "{:.2f}"),
            *([_cell(r.get("min_footprint_distance_m"), "{:.3f}")] if footprints else []),
            *([_cell(r.get("workspace_excursion_m_max"), "{:.3f}")] if excursions else []),
        ]) + " |")
    return "\n".join(lines) + "\n"


def run_bench(
    out: Path,
    quick: bool = False,
    families: Sequence[str] = DEFAULT_FAMILIES,
    sizes: Sequence[int] | None = None,
    seeds: int | None = None,
    jobs: int | None = None,
    executor: str = "serial",
    workers: int | None = None,
    budget_s: float = 600.0,
    central_max_agents: int = 16,
    max_steps: int | None = None,
    log: Callable[[str], None] = lambda _line: None,
    first_seed: int = 0,
    save_runs: bool = False,
    plane_margin: float | None = None,
    case_runner: Callable[[BenchCase, Path | None], CaseOutcome] = run_case,
    locals_: Sequence[str] | None = None,
    settings: Mapping[str, Any] | None = None,
    methods: Sequence[str] = METHODS,
) -> tuple[Path, Path]:
    """Run the benchmark, write ``bench.md`` and ``bench.json`` into ``out``; return their paths.

    Cases run ``jobs`` at a time in worker processes (one job: in this process), each with
    ``executor`` for its own local solves; per-step times are therefore measured with ``jobs`` runs
    sharing the machine. The report is rewritten after every finished case, so an interrupted
    study (``KeyboardInterrupt``, raised once the workers are down) keeps what it measured. A case
    that fails (a scenario its validation refuses too) is logged and left out of the table, its
    one-line reason listed under it; the others still run, and a ``RuntimeError`` naming the
    failures follows the last report. ``save_runs`` keeps every run's folder under ``out/runs``;
    ``plane_margin`` sets ``solver.plane_margin`` of every ADMM case. ``locals_`` are the ADMM
    agents' local steps (``solver.local``) to compare: every ADMM case runs once with each, the
    runs of a case one after the other, and the table has a row per local step (None: each
    family's own, :func:`family_local`). ``case_runner``
    runs one case (a module-level function when ``jobs`` > 1, so that worker processes can load it).
    ``settings`` (dotted scenario keys to values, ``{"weights.Q": 1.0}``) are set on every case's
    scenario; ValueError (``set: ...``) before anything runs when a case's scenario rejects them.
    ``methods`` leaves out ADMM or the centralised runs (:func:`plan_cases`); a size a family does
    not take is a ValueError (``sizes: ...``) before anything runs.
    """
    unknown = sorted(set(families) - set(FAMILIES))
    if unknown:
        raise ValueError(f"families: unknown {', '.join(unknown)} (choose from {', '.join(FAMILIES)})")
    sizes = tuple(sizes or (QUICK_SIZES if quick else FULL_SIZES))
    seeds = seeds or (1 if quick else 5)
    cases = plan_cases(families, sizes, seeds, executor, workers, budget_s,
                       min(central_max_agents, 4) if quick else central_max_agents, max_steps, first_seed,
                       plane_margin, None if locals_ is None else tuple(locals_), tuple((settings or {}).items()),
                       tuple(methods))
    _check_settings(cases)
    jobs = jobs or (1 if executor != "serial" else available_cores())
    machine = f"{os.cpu_count()} cores, {jobs} case(s) at a time, executor {executor}"
    if settings:
        machine += "; every scenario with " + ", ".join(f"{key}: {value}" for key, value in settings.items())
    outcomes: list[CaseOutcome] = []
    failures: list[str] = []
    started = time.perf_counter()
    paths = (out / "bench.md", out / "bench.json")
    tasks = [Task(case_runner, (case, out / "runs" if save_runs else None)) for case in cases]
    with closing(run_batch(tasks, jobs)) as finished:
        for done, result in enumerate(finished, 1):
            log(f"[{done}/{len(cases)}] {_progress(cases[result.index], result)}")
            if result.ok:
                outcomes.append(result.value)
            else:
                failures.append(f"{cases[result.index].label}: {result.error}")
            paths = write_report(out, outcomes, machine, time.perf_counter() - started, planned=len(cases),
                                 failed=failures)
    if not outcomes and not failures:
        paths = write_report(out, outcomes, machine, time.perf_counter() - started, planned=len(cases))
    if failures:
        raise RuntimeError(f"{len(failures)} of {len(cases)} bench cases failed (the report holds the others), "
                           f"first {failures[0]}")
    return paths


def _check_settings(cases: Sequence[BenchCase]) -> None:
    """ValueError (``set: ...``, one line) when a case's scenario rejects the benchmark's settings.
    A case whose scenario is refused without them too is left to fail when it runs, with its own
    reason (a method the family's scenario does not take is no fault of the settings)."""
    for case in {(c.family, c.method): c for c in cases if c.settings}.values():
        try:
            case.scenario()
        except (ValueError, KeyError, TypeError) as err:
            try:
                replace(case, settings=()).scenario()
            except (ValueError, KeyError, TypeError):
                continue
            raise ValueError(f"set: {str(err).splitlines()[0] if str(err) else type(err).__name__}") from None


def _progress(case: BenchCase, result: Finished) -> str:
    """The progress line of a finished case (without its ``[k/n]``)."""
    name = case.name
    if not result.ok:
        return f"{name}: FAILED ({result.error})"
    outcome: CaseOutcome = result.value
    return (f"{name}: {outcome.steps} steps, reached={outcome.all_reached}, collisions={outcome.collisions}, "
            f"{outcome.wall_time_s:.0f} s")


def _write_atomically(path: Path, text: str) -> None:
    partial = path.with_name(path.name + ".partial")
    partial.write_text(text)
    partial.replace(path)


def write_report(
    out: Path, outcomes: Sequence[CaseOutcome], machine: str, elapsed_s: float, planned: int | None = None,
    failed: Sequence[str] = (),
) -> tuple[Path, Path]:
    """Write ``bench.md`` and ``bench.json`` for the runs so far (each file replaced whole).

    The JSON keeps every run's per-step times, so reports of separate invocations can be merged
    (:func:`merge_reports`). ``failed`` are the cases that failed so far, each ``label: one-line
    reason``: listed under the table (when there are any) and in the JSON's ``failed``."""
    out.mkdir(parents=True, exist_ok=True)
    rows = aggregate(outcomes)
    planned = len(outcomes) if planned is None else planned
    progress = f"{len(outcomes)} runs" if len(outcomes) == planned else f"{len(outcomes)} of {planned} runs"
    markdown, json_path = out / "bench.md", out / "bench.json"
    growth = growth_exponents(rows)
    for key, g in growth.items():
        interval = step_growth_interval(outcomes, key.split("/")[0], local=g["local"])
        if interval is not None and "step" in g:
            g["step_interval"] = list(interval)
    fits = f"\nGrowth with the swarm size (least-squares fit on log-log):\n\n{growth_lines(growth)}" if growth else ""
    failures = "".join(f"* {line}\n" for line in failed)
    failures = f"\nFailed, left out of the table ({len(failed)}):\n\n{failures}" if failed else ""
    _write_atomically(markdown, f"# swarmpc bench\n\n{progress} in {elapsed_s:.0f} s ({machine}).\n\n"
                      + markdown_table(rows) + failures + fits)
    data = {"machine": machine, "elapsed_s": elapsed_s, "planned_runs": planned, "rows": rows, "growth": growth,
            "failed": list(failed),
            "runs": [{**asdict(o), "step_ms_median": _percentile(o.step_ms, 50),
                      "agent_ms_median": _percentile(o.agent_step_ms, 50),
                      "critical_path_ms_median": _percentile(o.critical_path_ms or [], 50)} for o in outcomes]}
    _write_atomically(json_path, json.dumps(data, indent=2))
    return markdown, json_path


def _is_count(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= 0


def _is_finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _is_finite_or_none(value: Any) -> bool:
    return value is None or _is_finite(value)


def _is_ratio(value: Any) -> bool:  # inf: a single agent has no neighbour
    return isinstance(value, (int, float)) and not isinstance(value, bool) and value >= 0


def _is_finite_list(value: Any) -> bool:
    return isinstance(value, list) and all(_is_finite(v) for v in value)


def _is_count_list(value: Any) -> bool:
    return isinstance(value, list) and all(_is_count(v) for v in value)


_OUTCOME_CHECKS: Mapping[str, tuple[Callable[[Any], bool], str]] = MappingProxyType({
    "steps": (_is_count, "a count"), "timed_out": (lambda v: isinstance(v, bool), "true or false"),
    "all_reached": (lambda v: isinstance(v, bool), "true or false"), "collisions": (_is_count, "a count"),
    "min_separation_ratio": (_is_ratio, "a number >= 0"), "time_to_goal_s": (_is_finite_or_none, "a number or null"),
    "cost": (_is_finite, "a finite number"), "step_ms": (_is_finite_list, "a list of finite numbers"),
    "agent_step_ms": (_is_finite_list, "a list of finite numbers"), "iterations": (_is_count_list, "a list of counts"),
    "solver_failures": (_is_count, "a count"), "wall_time_s": (_is_finite, "a finite number"),
    "unreached": (_is_count_list, "a list of agent indices"), "worst_goal_distance": (_is_finite, "a finite number"),
    "copies_mean": (_is_finite_or_none, "a number or null"), "planes_mean": (_is_finite_or_none, "a number or null"),
    "makespan_s": (_is_finite_or_none, "a number or null"),
    "overshoot_max_m": (_is_finite_or_none, "a number or null"),
    "lone_makespan_s": (_is_finite_or_none, "a number or null"),
    "interaction_ratio": (_is_finite_or_none, "a number or null"),
    "critical_path_ms": (lambda v: v is None or _is_finite_list(v), "a list of finite numbers or null"),
    "deadline_misses": (lambda v: v is None or _is_count(v), "a count or null"),
    "local_fallbacks": (lambda v: v is None or _is_count(v), "a count or null"),
    "workspace_excursion_m": (_is_finite_or_none, "a number or null"),
    "min_footprint_distance": (_is_finite_or_none, "a number or null"),
})  # fmt: skip
"""What each field of a ``bench.json`` run must hold (what :func:`write_report` writes)."""

_CASE_CHECKS: Mapping[str, tuple[Callable[[Any], bool], str]] = MappingProxyType({
    "family": (lambda v: v in FAMILIES, f"one of {', '.join(FAMILIES)}"),
    "agents": (lambda v: _is_count(v) and v >= 1, "a count >= 1"), "seed": (_is_count, "a count"),
    "method": (lambda v: v in ("admm", "centralized"), "admm or centralized"),
    "executor": (lambda v: isinstance(v, str), "a name"),
    "workers": (lambda v: v is None or _is_count(v), "a count or null"),
    "budget_s": (_is_finite, "a finite number"), "max_steps": (lambda v: v is None or _is_count(v), "a count or null"),
    "plane_margin": (_is_finite_or_none, "a number or null"),
    "local": (lambda v: v in LOCAL_STEPS, f"one of {', '.join(LOCAL_STEPS)}"),
    "settings": (lambda v: isinstance(v, list) and all(
        isinstance(p, list) and len(p) == 2 and isinstance(p[0], str) for p in v), "a list of [key, value] pairs"),
})  # fmt: skip


def _checked_fields(data: Any, checks: Mapping[str, tuple[Callable[[Any], bool], str]], required: Iterable[str],
                    where: str) -> dict[str, Any]:
    """The fields of the JSON object ``data`` that ``checks`` knows, each checked; ValueError
    (one line, ``where`` first) on a missing required field or a wrong value."""
    if not isinstance(data, dict):
        raise ValueError(f"{where or 'the file'}: expected an object, got {type(data).__name__}")
    missing = [key for key in required if key not in data]
    if missing:
        raise ValueError(f"{where + ': ' if where else ''}missing '{missing[0]}'")
    for key, (check, expected) in checks.items():
        if key in data and not check(data[key]):
            raise ValueError(f"{where + '.' if where else ''}{key}: expected {expected}, got {_shown(data[key])}")
    return {key: value for key, value in data.items() if key in checks}


def _shown(value: Any) -> str:
    """A JSON value, briefly: a container by its kind, anything else as JSON (cut at 60 characters)."""
    if isinstance(value, (dict, list)):
        return "an object" if isinstance(value, dict) else f"a list of {len(value)}"
    return json.dumps(value)[:60]


def _required_fields(cls: type) -> list[str]:
    return [f.name for f in fields(cls) if f.default is MISSING and f.default_factory is MISSING]


def _outcome_from_json(run: Any, where: str) -> CaseOutcome:
    """One run of a ``bench.json`` as a :class:`CaseOutcome`; ValueError when it is not one."""
    if isinstance(run, dict) and "step_ms" in run and run["step_ms"] is None:
        raise ValueError(f"{where}: holds no per-step times (written by an older swarmpc)")
    values = _checked_fields(run, _OUTCOME_CHECKS, _required_fields(CaseOutcome), where)
    case = _checked_fields(run["case"], _CASE_CHECKS, _required_fields(BenchCase), f"{where}.case")
    values["unreached"] = tuple(values.get("unreached", ()))
    case["settings"] = tuple((key, value) for key, value in case.get("settings", ()))
    case.setdefault("local", REPORTED_BEFORE_LOCAL)
    return CaseOutcome(case=BenchCase(**case), **values)


def read_report(path: Path) -> tuple[list[CaseOutcome], str, float]:
    """The runs, machine and elapsed seconds of a ``bench.json`` (or of the one in folder ``path``).

    The file may come from another machine or a damaged copy: anything that is not what
    :func:`write_report` writes (not JSON, a wrong structure, a missing key, NaN where a number
    belongs) is a ValueError whose message is one line naming the file.
    """
    path = path / "bench.json" if path.is_dir() else path
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"{path}: cannot read ({type(err).__name__})") from None
    except (json.JSONDecodeError, RecursionError) as err:
        detail = f" ({err.msg} at line {err.lineno})" if isinstance(err, json.JSONDecodeError) else ""
        raise ValueError(f"{path}: not a swarmpc bench.json: not valid JSON{detail}") from None
    try:
        _checked_fields(data, {"runs": (lambda v: isinstance(v, list), "a list"),
                               "machine": (lambda v: isinstance(v, str), "text"),
                               "elapsed_s": (_is_finite, "a finite number")}, ["runs"], "")
        outcomes = [_outcome_from_json(run, f"runs[{n}]") for n, run in enumerate(data["runs"])]
    except ValueError as err:
        raise ValueError(f"{path}: not a swarmpc bench.json: {err}") from None
    return outcomes, str(data.get("machine", "?")), float(data.get("elapsed_s", 0.0))


def load_outcomes(path: Path) -> list[CaseOutcome]:
    """The runs of a ``bench.json`` (or of the one in folder ``path``); see :func:`read_report`."""
    return read_report(path)[0]


def merge_reports(sources: Sequence[Path], out: Path) -> tuple[Path, Path]:
    """One report from the runs of several ``bench.json`` files (e.g. seeds split over invocations
    with ``--first-seed``); the same case in two sources is an error, not a silent pick. Every
    source is read and checked before anything is written."""
    outcomes: list[CaseOutcome] = []
    seen: dict[BenchCase, Path] = {}
    machines: list[str] = []
    elapsed = 0.0
    for source in sources:
        runs, machine, seconds = read_report(source)
        for outcome in runs:
            if outcome.case in seen:
                raise ValueError(f"case {outcome.case.name} is in both {seen[outcome.case]} and {source}")
            seen[outcome.case] = source
            outcomes.append(outcome)
        machines.append(machine)
        elapsed += seconds
    machine = "; ".join(sorted(set(machines))) + f"; merged from {len(sources)} reports"
    return write_report(out, outcomes, machine, elapsed)
