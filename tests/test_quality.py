"""Closed-loop quality metrics: hand-made trajectories with known answers, properties, the run
folder and the bench columns."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swarmpc.bench import BenchCase, CaseOutcome, aggregate, lone_agent_times, markdown_table, read_report, write_report
from swarmpc.config import scenario_from_dict
from swarmpc.simulation.loop import simulate
from swarmpc.simulation.quality import (
    control_effort,
    interaction_ratio,
    makespan,
    overshoot,
    quality_summary,
    run_folder_quality,
    time_to_goal,
)
from swarmpc.simulation.results import write_run

DT = 0.1
TOL = 0.05


def states_of(positions: np.ndarray) -> np.ndarray:
    """(T+1, M, 2d) states with zero velocities from (T+1, M, d) positions (only positions count)."""
    positions = np.asarray(positions, float)
    return np.concatenate([positions, np.zeros_like(positions)], axis=-1)


def goals_of(points: list[list[float]]) -> np.ndarray:
    points = np.asarray(points, float)
    return np.concatenate([points, np.zeros_like(points)], axis=-1)


# ------------------------------------------------------------------------ known answers
def test_an_agent_that_reaches_leaves_and_comes_back_counts_from_its_return():
    x = np.linspace(-2.0, 0.0, 21)  # at the goal (0, 0) at k = 20, t = 2.0 s
    away = [0.2, 0.3, 0.2, 0.1, 0.06]  # out of the tolerance at k = 21 ... 25 ...
    back = [0.04, 0.01, 0.0, 0.0]  # ... and within it for good from k = 26, t = 2.6 s
    path = np.concatenate([x, away, back])
    positions = np.stack([path, np.zeros_like(path)], axis=-1)[:, None, :]
    goal = goals_of([[0.0, 0.0]])
    assert time_to_goal(states_of(positions[:21]), goal, DT, TOL)[0] == pytest.approx(2.0)
    assert time_to_goal(states_of(positions), goal, DT, TOL)[0] == pytest.approx(2.6)
    assert overshoot(states_of(positions), goal)[0] == pytest.approx(0.3)


def test_overshoot_along_a_diagonal_ignores_the_sideways_part():
    goal = goals_of([[1.0, 1.0]])
    path = [[0.0, 0.0], [0.5, 0.5], [1.3, 1.3], [1.0, 1.0]]
    assert overshoot(states_of(np.array(path)[:, None]), goal)[0] == pytest.approx(0.3 * 2**0.5)
    sideways = [[0.0, 0.0], [1.2, 1.0], [1.0, 1.0]]  # 0.2 m in x: 0.2 / sqrt(2) along the move
    assert overshoot(states_of(np.array(sideways)[:, None]), goal)[0] == pytest.approx(0.2 / 2**0.5)
    across = [[0.0, 0.0], [1.5, 0.5], [1.0, 1.0]]  # off the line, not past the goal
    assert overshoot(states_of(np.array(across)[:, None]), goal)[0] == pytest.approx(0.0)


def test_an_agent_that_never_reaches_has_no_time_and_no_makespan():
    path = np.array([[[0.0, 0.0], [3.0, 0.0]], [[0.5, 0.0], [3.0, 1.0]], [[0.9, 0.0], [3.0, 2.0]]])
    goals = goals_of([[1.0, 0.0], [3.0, 2.0]])
    times = time_to_goal(states_of(path), goals, DT, TOL)
    assert np.isnan(times[0]) and times[1] == pytest.approx(0.2)
    assert np.isnan(makespan(times))
    summary = quality_summary(states_of(path), goals, DT, TOL)
    assert summary == {"time_to_goal_s": [None, pytest.approx(0.2)], "makespan_s": None,
                       "overshoot_m": [0.0, 0.0]}
    assert makespan(np.array([0.2, 1.5, 0.7])) == pytest.approx(1.5)


def test_an_agent_starting_at_its_goal_takes_no_time_and_cannot_overshoot():
    path = np.array([[[1.0, 1.0]], [[1.02, 1.0]], [[1.0, 1.0]]])
    goal = goals_of([[1.0, 1.0]])
    assert time_to_goal(states_of(path), goal, DT, TOL)[0] == 0.0
    assert overshoot(states_of(path), goal)[0] == 0.0


def test_the_tolerance_boundary_counts_as_reached():
    path = np.array([[[0.0, 0.0]], [[0.95, 0.0]]])
    assert time_to_goal(states_of(path), goals_of([[1.0, 0.0]]), DT, 0.05)[0] == pytest.approx(0.1)


def test_control_effort_and_interaction_ratio():
    inputs = np.array([[[1.0, 0.0], [0.0, 0.0]], [[3.0, 4.0], [1.0, 1.0]]])  # (T=2, M=2, d=2)
    assert control_effort(inputs, 0.5) == pytest.approx([0.5 * (1 + 25), 0.5 * 2])
    assert interaction_ratio(6.0, [2.0, 3.0]) == pytest.approx(2.0)
    assert interaction_ratio(None, [2.0]) is None
    assert interaction_ratio(6.0, [2.0, None]) is None
    assert interaction_ratio(6.0, [float("nan")]) is None
    assert interaction_ratio(0.0, [0.0, 0.0]) is None  # every agent at its goal from the start


# ------------------------------------------------------------------------ properties
paths = st.integers(2, 30).flatmap(
    lambda n: st.lists(st.lists(st.floats(-3, 3), min_size=2, max_size=2), min_size=n, max_size=n)
)


@given(path=paths, goal=st.lists(st.floats(-3, 3), min_size=2, max_size=2), extra=st.integers(1, 20),
       offset=st.floats(0.0, 0.99))
@settings(max_examples=60, deadline=None)
def test_time_to_goal_is_unchanged_by_appending_states_at_the_goal(path, goal, extra, offset):
    positions = np.array(path, float)
    positions[-1] = np.array(goal) + [offset * TOL, 0.0]  # the run ends within the tolerance
    goals = goals_of([goal])
    before = time_to_goal(states_of(positions[:, None]), goals, DT, TOL)[0]
    longer = np.vstack([positions, np.tile(goal, (extra, 1))])
    assert time_to_goal(states_of(longer[:, None]), goals, DT, TOL)[0] == pytest.approx(before)
    assert 0.0 <= before <= (len(positions) - 1) * DT + 1e-12


@given(progress=st.lists(st.floats(0.0, 1.0), min_size=2, max_size=40),
       lateral=st.lists(st.floats(-2.0, 2.0), min_size=40, max_size=40),
       start=st.lists(st.floats(-3, 3), min_size=2, max_size=2), angle=st.floats(0.0, 2 * np.pi),
       length=st.floats(0.1, 5.0))
@settings(max_examples=60, deadline=None)
def test_a_monotone_approach_has_no_overshoot(progress, lateral, start, angle, length):
    alpha = np.sort(progress)  # never goes back nor past the goal along the move
    direction = np.array([np.cos(angle), np.sin(angle)])
    normal = np.array([-direction[1], direction[0]])
    start = np.array(start)
    goal = start + length * direction
    positions = start + np.outer(alpha * length, direction) + np.outer(lateral[: len(alpha)], normal)
    positions[0] = start
    assert overshoot(states_of(positions[:, None]), goals_of([goal.tolist()]))[0] == pytest.approx(0.0, abs=1e-9)


# ------------------------------------------------------------------------ a real run
def lone_scenario(**weights) -> dict:
    return {"name": "lone", "dim": 2, "weights": {"Q": 0.1, "R": 1.0, "Qf": "lqr", **weights},
            "agents": [{"start": [-1.5, -1.5], "goal": [1.5, 1.5]}], "stop": {"max_steps": 400}}


def test_the_summary_holds_the_quality_keys_and_the_folder_recomputes_them(tmp_path):
    scn = scenario_from_dict({**lone_scenario(), "agents": [{"start": [-1.5, -1.5], "goal": [1.5, 1.5]},
                                                          {"start": [1.5, -1.5], "goal": [-1.5, 1.5]}],
                              "stop": {"max_steps": 20}})
    result = simulate(scn)
    summary = result.summary
    assert [t is not None for t in summary["time_to_goal_s"]] == summary["reached"]
    assert summary["makespan_s"] is None if not summary["all_reached"] else summary["makespan_s"] > 0
    assert len(summary["overshoot_m"]) == 2 and min(summary["overshoot_m"]) >= 0.0
    folder = write_run(result, tmp_path / "run")
    written = json.loads((folder / "summary.json").read_text())
    recomputed = run_folder_quality(folder)
    for key in ("time_to_goal_s", "makespan_s", "overshoot_m"):
        assert written[key] == pytest.approx(recomputed[key]) if written[key] is not None else recomputed[key] is None


# ------------------------------------------------------------------------ bench columns
def bench_outcome(seed: int, makespan_s: float | None, overshoot_m: float, ratio: float | None) -> CaseOutcome:
    return CaseOutcome(
        case=BenchCase("random", 4, seed, "admm"), steps=10, timed_out=False, all_reached=makespan_s is not None,
        collisions=0, min_separation_ratio=1.2, time_to_goal_s=makespan_s, cost=1.0, step_ms=[10.0],
        agent_step_ms=[2.0], iterations=[1], solver_failures=0, wall_time_s=1.0, makespan_s=makespan_s,
        overshoot_max_m=overshoot_m, lone_makespan_s=None if ratio is None else makespan_s / ratio,
        interaction_ratio=ratio,
    )


def test_bench_rows_report_makespan_overshoot_and_interaction(tmp_path):
    outcomes = [bench_outcome(0, 4.0, 0.1, 2.0), bench_outcome(1, 6.0, 0.3, 1.0), bench_outcome(2, None, 0.2, None)]
    (row,) = aggregate(outcomes)
    assert row["makespan_s_median"] == pytest.approx(5.0)
    assert row["overshoot_m_max"] == pytest.approx(0.3)
    assert row["interaction_ratio_median"] == pytest.approx(1.5)
    table = markdown_table([row])
    assert "| makespan s | overshoot max m | makespan vs lone |" in table
    assert "| 5.0 | 0.30 | 1.50 |" in table
    _markdown, path = write_report(tmp_path, outcomes, "test", 1.0)
    again, _machine, _elapsed = read_report(path)
    assert [o.interaction_ratio for o in again] == [2.0, 1.0, None]


def test_lone_agent_times_run_each_agent_alone():
    scn = scenario_from_dict({**lone_scenario(Q=1.0), "agents": [
        {"start": [-1.0, 0.0], "goal": [1.0, 0.0]}, {"start": [1.0, 0.5], "goal": [-1.0, 0.5]},
        {"start": [0.0, -1.0], "goal": [0.0, -0.5]}]})
    times = lone_agent_times(scn)
    assert times[0] == pytest.approx(times[1])  # mirror images of each other
    assert 0.0 < times[2] < times[0]  # a shorter move


# ------------------------------------------------------------------------ the tuning guide
def tuning_study():
    """benchmarks/tuning_study.py as a module (benchmarks/ is not a package)."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "tuning_study.py"
    spec = importlib.util.spec_from_file_location("tuning_study", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_tuning_guide_shows_the_table_generated_from_the_committed_results():
    study = tuning_study()
    data = json.loads(study.RESULTS.read_text())
    assert study.generated_block() == study.tables(data), "regenerate: benchmarks/tuning_study.py --doc"
    measured = {(r["case"], r["Q"], r["R"], r["Qf"], r["N"]) for r in data["rows"]}
    planned = {(case, c["Q"], c["R"], c["Qf"], c["N"]) for case in study.CASES for c in study.grid()}
    assert measured == planned


def test_the_tuning_results_agree_with_the_lqr_theory():
    """Where no constraint binds, `Qf: lqr` makes the horizon irrelevant and only Q / R matter."""
    rows = json.loads(tuning_study().RESULTS.read_text())["rows"]
    lone = {(r["Q"], r["R"], r["Qf"], r["N"]): r for r in rows if r["case"] == "lone"}
    for q, r in ((0.1, 1.0), (1.0, 0.1), (1.0, 1.0)):
        assert lone[(q, r, "lqr", 10)]["makespan_s"] == lone[(q, r, "lqr", 20)]["makespan_s"]
    overshoot = lone[(1.0, 1.0, "lqr", 10)]["overshoot_max_m"]
    assert lone[(0.1, 0.1, "lqr", 10)]["overshoot_max_m"] == pytest.approx(overshoot)
