"""The scaling benchmark: a real small case end to end, and the aggregation it reports."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swarmpc.bench import (
    BenchCase,
    CaseOutcome,
    aggregate,
    growth_exponents,
    load_outcomes,
    markdown_table,
    merge_reports,
    plan_cases,
    run_bench,
    run_case,
    step_growth_interval,
    write_report,
)
from swarmpc.config import ScenarioError
from swarmpc.scenarios import builtin_scenario


def outcome(family: str, agents: int, seed: int, method: str, cost: float, reached: bool = True,
            collisions: int = 0) -> CaseOutcome:
    return CaseOutcome(
        case=BenchCase(family, agents, seed, method), steps=10, timed_out=False, all_reached=reached,
        collisions=collisions, min_separation_ratio=1.2, time_to_goal_s=1.0 if reached else None, cost=cost,
        step_ms=[10.0, 20.0], agent_step_ms=[2.0, 4.0, 6.0], iterations=[1, 3], solver_failures=0,
        wall_time_s=1.0,
    )


def test_case_scenarios_follow_the_benchmark_definition():
    random = BenchCase("random", 6, 2).scenario()
    assert random.dim == 3 and random.num_agents == 6 and random.seed == 2
    lower, upper = random.bounds()
    assert np.allclose(upper - lower, [3.0, 3.0, 2.0]) and lower[2] == pytest.approx(0.2)
    sphere = BenchCase("sphere", 8, 0, method="centralized").scenario()
    assert sphere.dim == 3 and sphere.solver.method == "centralized"
    assert sphere.limits.accel is not None and sphere.stop.goal_tolerance == pytest.approx(0.1)
    spread = BenchCase("spread", 64, 2).scenario()
    lower, upper = spread.bounds()
    assert spread.num_agents == 64 and spread.seed == 2 and spread.limits.accel is not None
    assert np.allclose(upper - lower, [6.0, 6.0, 4.0], atol=1e-3)  # 8 agents per 3 x 3 x 2 m


def test_plan_runs_centralised_only_up_to_its_size_limit():
    cases = plan_cases(["random", "circle"], [4, 32], seeds=3, executor="serial", workers=None,
                       budget_s=60.0, central_max_agents=16)
    central = [c for c in cases if c.method == "centralized"]
    assert {c.agents for c in central} == {4}
    assert sum(c.family == "random" and c.method == "admm" for c in cases) == 6
    assert sum(c.family == "circle" and c.method == "admm" for c in cases) == 2  # deterministic: one run


def test_first_seed_shifts_the_random_seeds_only():
    cases = plan_cases(["random", "circle", "spread"], [8], seeds=2, executor="serial", workers=None,
                       budget_s=60.0, central_max_agents=0, first_seed=3)
    assert sorted(c.seed for c in cases if c.family == "random") == [3, 4]
    assert sorted(c.seed for c in cases if c.family == "spread") == [3, 4]
    assert [c.seed for c in cases if c.family == "circle"] == [0]


def test_aggregate_rates_and_cost_gap():
    rows = aggregate([
        outcome("random", 4, 0, "admm", 110.0), outcome("random", 4, 1, "admm", 90.0, reached=False, collisions=2),
        outcome("random", 4, 0, "centralized", 100.0), outcome("random", 4, 1, "centralized", 100.0),
    ])
    (row,) = rows
    assert row["runs"] == 2 and row["all_reached_rate"] == 0.5 and row["collision_free_rate"] == 0.5
    assert row["cost_gap_pct_median"] == pytest.approx(10.0)  # only seeds where both reached
    assert row["agent_ms_median"] == pytest.approx(4.0) and row["iterations_max"] == 3
    assert row["copies_mean"] is None  # none recorded
    table = markdown_table(rows)
    assert "| random | 4 | qp | 2 | 50% | 50% |" in table and "+10.0%" in table
    with_copies = [CaseOutcome(**{**outcome("random", 8, seed, "admm", 1.0).__dict__, "copies_mean": held,
                                  "planes_mean": planes})
                   for seed, held, planes in ((0, 1.0, 0.5), (1, 2.0, 1.0))]
    (row,) = aggregate(with_copies + [outcome("random", 8, 2, "admm", 1.0)])
    assert row["copies_mean"] == pytest.approx(1.5)  # runs that recorded none do not count
    assert row["planes_mean"] == pytest.approx(0.75)
    assert markdown_table([row]).rstrip().endswith("| 1.50 | 0.75 |")


def test_the_table_shows_how_far_runs_left_the_workspace_only_when_one_did():
    inside = [CaseOutcome(**{**outcome("random", 8, seed, "admm", 1.0).__dict__, "workspace_excursion_m": 0.0})
              for seed in (0, 1)]
    (row,) = aggregate(inside)
    assert row["workspace_excursion_m_max"] == 0.0
    assert "outside workspace" not in markdown_table([row])
    out = [CaseOutcome(**{**outcome("random", 8, 2, "admm", 1.0).__dict__, "workspace_excursion_m": 0.063})]
    (row,) = aggregate(inside + out + [outcome("random", 8, 3, "admm", 1.0)])  # one run recorded none
    assert row["workspace_excursion_m_max"] == pytest.approx(0.063)
    table = markdown_table([row])
    assert "outside workspace max m |" in table and table.rstrip().endswith("| 0.063 |")


@given(k_step=st.floats(0.0, 3.0), k_agent=st.floats(-1.0, 2.0), scale=st.floats(0.1, 100.0))
@settings(max_examples=25, deadline=None)
def test_growth_exponent_recovers_a_power_law(k_step, k_agent, scale):
    rows = [{"family": "spread", "agents": m, "step_ms_median": scale * m**k_step,
             "agent_ms_median": scale * m**k_agent} for m in (4, 8, 16, 32, 64)]
    rows.append({"family": "circle", "agents": 4, "step_ms_median": 1.0, "agent_ms_median": None})
    growth = growth_exponents(rows)
    assert set(growth) == {"spread"}  # one size is no fit
    assert growth["spread"]["step"] == pytest.approx(k_step, abs=1e-6)
    assert growth["spread"]["agent"] == pytest.approx(k_agent, abs=1e-6)
    assert growth["spread"]["sizes"] == [4, 8, 16, 32, 64]


def test_report_states_the_growth(tmp_path):
    runs = [CaseOutcome(**{**outcome("random", m, 0, "admm", 1.0).__dict__, "step_ms": [float(m * m)],
                           "agent_step_ms": [float(m)]}) for m in (4, 8, 16)]
    markdown, data = write_report(tmp_path, runs, "test", 1.0)
    assert "random (M = 4…16, medians): per-step wall time ~ M^2.00, per-agent compute ~ M^1.00" in markdown.read_text()
    assert json.loads(data.read_text())["growth"]["random"]["step"] == pytest.approx(2.0)


def timed(family: str, agents: int, seed: int, step_ms: list[float]) -> CaseOutcome:
    return CaseOutcome(**{**outcome(family, agents, seed, "admm", 1.0).__dict__, "step_ms": step_ms})


@given(k=st.floats(0.0, 2.5), spread=st.floats(0.0, 0.5), runs=st.integers(2, 4))
@settings(max_examples=20, deadline=None)
def test_growth_interval_brackets_the_fit_and_widens_with_disagreeing_runs(k, spread, runs):
    sizes = (4, 8, 16, 32)
    outcomes = [timed("spread", m, s, [m**k * (1.0 + spread * s)] * 3) for m in sizes for s in range(runs)]
    low, high = step_growth_interval(outcomes, "spread", repeats=200)
    fitted = growth_exponents(aggregate(outcomes))["spread"]["step"]
    assert low - 1e-9 <= fitted <= high + 1e-9
    if spread == 0.0:  # identical runs: every resample is the same fit
        assert high - low == pytest.approx(0.0, abs=1e-9) and fitted == pytest.approx(k, abs=1e-9)


def test_growth_interval_needs_two_runs_per_size_and_reaches_the_report(tmp_path):
    one_each = [timed("random", m, 0, [float(m)]) for m in (4, 8)]
    assert step_growth_interval(one_each, "random") is None
    assert step_growth_interval(one_each + [timed("random", 4, 1, [4.0])], "random") is None  # M = 8: one run
    # runs that disagree by 2x at M = 8: the exponent is 0.5, 1.0 or 1.5 depending on the draw
    runs = [timed("random", 4, s, [4.0]) for s in (0, 1)] + [timed("random", 8, 0, [8.0 / 2**0.5]),
                                                               timed("random", 8, 1, [8.0 * 2**0.5])]
    low, high = step_growth_interval(runs, "random")
    assert low == pytest.approx(0.5) and high == pytest.approx(1.5)
    markdown, data = write_report(tmp_path, runs, "test", 1.0)
    assert "(90 % interval over resampled runs 0.50–1.50)" in markdown.read_text()
    assert json.loads(data.read_text())["growth"]["random"]["step_interval"] == pytest.approx([0.5, 1.5])


def test_real_case_recomputes_safety_from_the_trajectory():
    result = run_case(BenchCase("random", 3, 0, max_steps=40))
    assert result.steps == 40 and not result.timed_out
    assert result.copies_mean is not None and 0.0 <= result.copies_mean <= 2.0  # at most the 2 others
    assert len(result.agent_step_ms) == 3 * result.steps and result.iterations
    assert result.collisions == 0 and result.min_separation_ratio >= 1.0
    assert result.workspace_excursion_m is not None and 0.0 <= result.workspace_excursion_m < 1e-3
    tolerance = BenchCase("random", 3, 0).scenario().stop.goal_tolerance
    assert (not result.unreached) == result.all_reached == (result.worst_goal_distance <= tolerance + 1e-9)


def test_run_bench_writes_table_and_json(tmp_path):
    def stand_in(case: BenchCase, runs_dir: object) -> CaseOutcome:
        return outcome(case.family, case.agents, case.seed, case.method, 100.0)

    markdown, data = run_bench(tmp_path, quick=True, families=["circle", "random"], jobs=1, case_runner=stand_in)
    text = markdown.read_text()
    assert text.count("| circle |") == 2 and text.count("| random |") == 2
    assert len(json.loads(data.read_text())["rows"]) == 4
    with pytest.raises(ValueError, match="families: unknown blob"):
        run_bench(tmp_path, families=["blob"])


def test_bench_command_writes_its_table(tmp_path):
    from conftest import run_cli

    out = tmp_path / "bench"
    done = run_cli("bench", "--families", "circle", "--sizes", "2", "--max-steps", "5", "--jobs", "1",
                   "--out", str(out), "--save-runs")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == str(out / "bench.md")
    table = (out / "bench.md").read_text()
    assert "| circle | 2 | qp | 1 |" in table  # the point families' own local step
    data = json.loads((out / "bench.json").read_text())
    assert {r["case"]["method"] for r in data["runs"]} == {"admm", "centralized"}
    assert all(r["steps"] == 5 and r["collisions"] == 0 for r in data["runs"])
    saved = np.load(out / "runs" / "circle-M2-seed0-admm" / "trajectory.npz")
    assert saved["states"].shape[:2] == (6, 2)  # the saved run is the measured one: 5 steps, 2 agents
    assert (out / "runs" / "circle-M2-seed0-centralized" / "summary.json").exists()


@pytest.mark.parametrize(("args", "field"), [
    (["--families", "blob"], "--families"),
    (["--sizes", "4,x"], "--sizes"),
    (["--sizes", "0"], "--sizes"),
    (["--seeds", "0"], "--seeds"),
    (["--set", "weights"], "--set"),
    (["--set", "weights.Qq=1"], "--set"),
    (["--set", "weights.Q=-1"], "--set"),
    (["--set", "nosuch.key=1"], "--set"),
])
def test_bench_command_rejects_bad_options(tmp_path, args, field):
    from conftest import run_cli

    done = run_cli("bench", *args, "--out", str(tmp_path / "b"))
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and field in lines[0] and "Traceback" not in done.stderr
    assert not (tmp_path / "b").exists()


def test_reports_of_split_studies_merge_into_the_table_of_all_their_runs(tmp_path):
    first = [outcome("random", 64, 0, "admm", 100.0), outcome("random", 64, 1, "admm", 90.0, reached=False)]
    second = [CaseOutcome(**{**outcome("random", 64, 2, "admm", 80.0).__dict__, "step_ms": [30.0, 70.0],
                             "unreached": (3, 5), "worst_goal_distance": 0.4})]
    write_report(tmp_path / "a", first, "machine a", 10.0)
    write_report(tmp_path / "b", second, "machine b", 20.0)
    assert load_outcomes(tmp_path / "b") == second  # every field survives the JSON, per-step times too
    markdown, data = merge_reports([tmp_path / "a", tmp_path / "b" / "bench.json"], tmp_path / "all")
    (row,) = json.loads(data.read_text())["rows"]
    assert row == aggregate(first + second)[0]
    assert row["runs"] == 3 and row["all_reached_rate"] == pytest.approx(2 / 3)
    assert row["step_ms_median"] == pytest.approx(20.0)  # pooled over all steps: 10, 20, 10, 20, 30, 70
    assert "3 runs in 30 s" in markdown.read_text()


def test_merging_the_same_case_twice_or_an_old_report_is_refused(tmp_path):
    write_report(tmp_path / "a", [outcome("random", 8, 0, "admm", 1.0)], "m", 1.0)
    with pytest.raises(ValueError, match="random M=8 seed=0 admm qp is in both"):
        merge_reports([tmp_path / "a", tmp_path / "a"], tmp_path / "all")
    old = tmp_path / "old.json"
    old.write_text(json.dumps({"runs": [{"case": {"family": "random", "agents": 8, "seed": 1}, "step_ms": None}]}))
    with pytest.raises(ValueError, match="no per-step times"):
        merge_reports([old], tmp_path / "all")
    assert not (tmp_path / "all").exists()


def test_a_bench_cut_short_keeps_the_runs_it_finished(tmp_path):
    def run_or_fail(case: BenchCase, runs_dir: object) -> CaseOutcome:
        if case.seed == 1:
            raise RuntimeError("machine lost")
        return outcome(case.family, case.agents, case.seed, case.method, 100.0)

    with pytest.raises(RuntimeError):  # one job: in this process, finishing in the order submitted
        run_bench(tmp_path, families=["random"], sizes=[4], seeds=2, central_max_agents=0, jobs=1,
                  case_runner=run_or_fail)
    data = json.loads((tmp_path / "bench.json").read_text())
    assert [r["case"]["seed"] for r in data["runs"]] == [0] and data["planned_runs"] == 2
    assert "1 of 2 runs" in (tmp_path / "bench.md").read_text()
    assert not list(tmp_path.glob("*.partial"))


def test_bench_merge_command_reports_a_bad_source_in_one_line(tmp_path):
    from conftest import run_cli

    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    done = run_cli("bench", "--merge", str(broken), "--out", str(tmp_path / "m"))
    assert done.returncode == 2 and "Traceback" not in done.stderr
    (line,) = done.stderr.strip().splitlines()
    assert "--merge" in line and "broken.json" in line
    assert not (tmp_path / "m").exists()


def test_a_plane_margin_reaches_the_admm_cases_only():
    cases = plan_cases(["random"], [4], 1, "serial", None, 60.0, 4, plane_margin=0.05)
    by_method = {c.method: c.scenario().solver.plane_margin for c in cases}
    assert by_method == {"admm": 0.05, "centralized": None}
    unset = plan_cases(["random"], [4], 1, "serial", None, 60.0, 0)
    assert all(c.scenario().solver.plane_margin is None for c in unset)


# --- both local steps side by side ----------------------------------------------------------------
def test_each_admm_case_runs_once_per_local_step_one_after_the_other():
    cases = plan_cases(["random"], [4], 2, "serial", None, 60.0, 4, locals_=("qp", "ipopt"))
    assert [(c.seed, c.method, c.local) for c in cases] == [
        (0, "admm", "qp"), (0, "admm", "ipopt"), (0, "centralized", "ipopt"),
        (1, "admm", "qp"), (1, "admm", "ipopt"), (1, "centralized", "ipopt")]  # the reference runs once
    assert [c.scenario().solver.local for c in cases[:2]] == ["qp", "ipopt"]
    assert [c.label for c in cases[:3]] == ["random-M4-seed0-admm", "random-M4-seed0-admm-ipopt",
                                            "random-M4-seed0-centralized"]
    assert plan_cases(["random"], [4], 1, "serial", None, 60.0, 0) == [BenchCase("random", 4, 0, budget_s=60.0)]
    for wrong in (("blob",), (), ("qp", "qp")):
        with pytest.raises(ValueError, match="local: "):
            plan_cases(["random"], [4], 1, "serial", None, 60.0, 0, locals_=wrong)


def test_run_bench_with_two_local_steps_writes_a_row_for_each(tmp_path):
    def stand_in(case: BenchCase, runs_dir: object) -> CaseOutcome:
        made = outcome(case.family, case.agents, case.seed, case.method, 110.0 if case.local == "qp" else 100.0)
        fallbacks = 3 if case.local == "qp" and case.method == "admm" else 0
        return CaseOutcome(**{**made.__dict__, "case": case, "local_fallbacks": fallbacks})

    markdown, data = run_bench(tmp_path, families=["random"], sizes=[4, 8], seeds=2, jobs=1, central_max_agents=4,
                               case_runner=stand_in, locals_=("qp", "ipopt"))
    report = json.loads(data.read_text())
    assert [(r["agents"], r["local"], r["runs"], r["local_fallbacks"]) for r in report["rows"]] == [
        (4, "ipopt", 2, 0), (4, "qp", 2, 6), (8, "ipopt", 2, 0), (8, "qp", 2, 6)]
    gaps = {(r["agents"], r["local"]): r["cost_gap_pct_median"] for r in report["rows"]}
    assert gaps[4, "qp"] == pytest.approx(10.0) and gaps[4, "ipopt"] == pytest.approx(0.0)  # one reference
    assert sum(r["case"]["method"] == "centralized" for r in report["runs"]) == 2
    assert set(report["growth"]) == {"random", "random/ipopt"}
    table = markdown.read_text()
    assert "| random | 4 | ipopt | 2 |" in table and "| random | 4 | qp | 2 |" in table
    assert "| local fallbacks |" in table


def test_bench_command_compares_both_local_steps_in_one_run(tmp_path):
    from conftest import run_cli

    out = tmp_path / "bench"
    done = run_cli("bench", "--families", "circle", "--sizes", "2", "--max-steps", "5", "--jobs", "1",
                   "--central-max-agents", "0", "--local", "qp,ipopt", "--out", str(out))
    assert done.returncode == 0, done.stderr
    data = json.loads((out / "bench.json").read_text())
    assert [(r["case"]["method"], r["case"]["local"]) for r in data["runs"]] == [("admm", "qp"), ("admm", "ipopt")]
    assert all(r["steps"] == 5 and r["local_fallbacks"] >= 0 for r in data["runs"])
    assert data["runs"][1]["local_fallbacks"] == 0  # the IPOPT local step has nothing to fall back from
    table = (out / "bench.md").read_text()
    assert "| circle | 2 | ipopt | 1 |" in table and "| circle | 2 | qp | 1 |" in table
    refused = run_cli("bench", "--local", "qp,blob", "--out", str(tmp_path / "b"))
    assert refused.returncode == 2 and "--local" in refused.stderr and not (tmp_path / "b").exists()


def test_a_report_from_before_local_steps_merges_as_ipopt(tmp_path):
    write_report(tmp_path / "old", [outcome("random", 8, 0, "admm", 1.0)], "m", 1.0)
    data = json.loads((tmp_path / "old" / "bench.json").read_text())
    for run in data["runs"]:
        del run["case"]["local"], run["local_fallbacks"]
    (tmp_path / "old" / "bench.json").write_text(json.dumps(data))
    (old,) = load_outcomes(tmp_path / "old")
    assert old.case.local == "ipopt" and old.local_fallbacks is None
    qp = CaseOutcome(**{**outcome("random", 8, 0, "admm", 1.0).__dict__,
                        "case": BenchCase("random", 8, 0, local="qp"), "local_fallbacks": 2})
    write_report(tmp_path / "new", [qp], "m", 1.0)
    _, merged = merge_reports([tmp_path / "old", tmp_path / "new"], tmp_path / "all")  # not the same case
    rows = json.loads(merged.read_text())["rows"]
    assert [(r["local"], r["local_fallbacks"]) for r in rows] == [("ipopt", None), ("qp", 2)]


# --- scenario settings on every case (--set) -------------------------------------------------------
def test_settings_reach_every_case_and_survive_the_report(tmp_path):
    settings = (("weights.Q", 1.0), ("weights.R", 0.1), ("deadlock.keep_right_deg", 15.0))
    cases = plan_cases(["random", "circle"], [4], 1, "serial", None, 60.0, 4, locals_=("qp", "ipopt"),
                       settings=settings)
    assert {c.method for c in cases} == {"admm", "centralized"}
    for case in cases:
        scn = case.scenario()
        assert np.allclose(scn.matrix("Q", scn.agent_model()), np.eye(2 * scn.dim))
        assert np.allclose(scn.matrix("R", scn.agent_model()), 0.1 * np.eye(scn.dim))
        assert scn.deadlock.keep_right_deg == 15.0
        assert scn.solver.method == case.method  # the benchmark's own keys still win
    made = outcome("random", 4, 0, "admm", 1.0)
    written = CaseOutcome(**{**made.__dict__, "case": cases[0]})
    write_report(tmp_path / "r", [written], "m", 1.0)
    (loaded,) = load_outcomes(tmp_path / "r")
    assert loaded.case.settings == settings and loaded == written


def test_a_null_setting_sets_null():
    """``--set KEY=null`` is a value: it sets the field to null instead of being dropped as an
    option not given (the scenario's non-null value would otherwise fly unnoticed)."""
    paper = builtin_scenario("paper-2d")
    assert paper.deadlock.keep_right_deg == 0.0
    assert paper.with_settings({"deadlock.keep_right_deg": None}).deadlock.keep_right_deg is None
    assert paper.with_updates(**{"deadlock.keep_right_deg": None}).deadlock.keep_right_deg == 0.0  # not given
    (case,) = plan_cases(["random"], [4], 1, "serial", None, 60.0, 0, locals_=("qp",),
                         settings=(("solver.qp.handover_slack", 1e-4), ("solver.qp.handover_slack", None)))
    assert case.scenario().solver.qp.handover_slack is None  # the last value, null, as given


def test_run_bench_states_its_settings_and_refuses_bad_ones_before_running(tmp_path):
    ran: list[BenchCase] = []

    def stand_in(case: BenchCase, runs_dir: object) -> CaseOutcome:
        ran.append(case)
        return CaseOutcome(**{**outcome(case.family, case.agents, case.seed, case.method, 1.0).__dict__, "case": case})

    markdown, _ = run_bench(tmp_path / "ok", families=["random"], sizes=[4], seeds=1, jobs=1, central_max_agents=0,
                            case_runner=stand_in, settings={"weights.Q": 1.0})
    assert "every scenario with weights.Q: 1.0" in markdown.read_text()
    assert [c.settings for c in ran] == [(("weights.Q", 1.0),)]
    with pytest.raises(ValueError, match=r"^set: .*weights"):
        run_bench(tmp_path / "bad", families=["random"], sizes=[4], seeds=1, jobs=1, central_max_agents=0,
                  case_runner=stand_in, settings={"weights.Q": "heavy"})
    assert len(ran) == 1 and not (tmp_path / "bad").exists()


# --- the car family ---------------------------------------------------------------------------------
def car_outcome(case: BenchCase, gap: float = 0.3) -> CaseOutcome:
    made = outcome(case.family, case.agents, case.seed, case.method, 100.0)
    return CaseOutcome(**{**made.__dict__, "case": case, "min_footprint_distance": gap,
                          "critical_path_ms": [10.0, 20.0], "makespan_s": 8.0})


def test_crossing_cases_are_the_builtin_run_by_the_benchmark_method():
    cases = plan_cases(["crossing"], [4, 8], seeds=3, executor="serial", workers=None, budget_s=60.0,
                       central_max_agents=16)
    assert [(c.agents, c.seed, c.method) for c in cases] == [
        (4, 0, "admm"), (4, 0, "centralized"), (8, 0, "admm"), (8, 0, "centralized")]  # deterministic: one seed
    central = cases[3].scenario()
    builtin = builtin_scenario("crossing", agents=8)
    assert central.has_cars and central.num_agents == 8 and central.solver.method == "centralized"
    assert central.start_states().tolist() == builtin.start_states().tolist()
    assert central.stop == builtin.stop and central.weights == builtin.weights  # the built-in's own settings
    assert cases[2].scenario().solver.method == "admm"
    assert [c.method for c in plan_cases(["crossing"], [4], 1, "serial", None, 60.0, 16,
                                         methods=("centralized",))] == ["centralized"]
    with pytest.raises(ValueError, match="^methods: unknown blob"):
        plan_cases(["crossing"], [4], 1, "serial", None, 60.0, 16, methods=("blob",))


def test_sizes_the_crossing_does_not_take_are_refused_before_anything_runs(tmp_path):
    with pytest.raises(ValueError, match="^sizes: family crossing takes multiples of 4, got 6$"):
        plan_cases(["circle", "crossing"], [4, 6], 1, "serial", None, 60.0, 16)
    assert len(plan_cases(["circle"], [6], 1, "serial", None, 60.0, 16)) == 2  # the point families take any M

    def never(case: BenchCase, runs_dir: object) -> CaseOutcome:
        raise AssertionError("nothing may run")

    with pytest.raises(ValueError, match="^sizes: "):
        run_bench(tmp_path / "b", families=["crossing"], sizes=[2], jobs=1, case_runner=never)
    assert not (tmp_path / "b").exists()
    from conftest import run_cli

    done = run_cli("bench", "--families", "circle,crossing", "--sizes", "4,10", "--out", str(tmp_path / "c"))
    (line,) = done.stderr.strip().splitlines()
    assert done.returncode == 2 and line.endswith("--sizes: family crossing takes multiples of 4, got 10")
    assert not (tmp_path / "c").exists()


def test_a_centralised_crossing_bench_reports_per_agent_compute(tmp_path):
    markdown, data = run_bench(tmp_path, families=["crossing"], sizes=[4], seeds=1, jobs=1, max_steps=5,
                               methods=("centralized",))
    report = json.loads(data.read_text())
    (row,) = report["rows"]
    assert (row["family"], row["agents"], row["local"], row["runs"]) == ("crossing", 4, "centralized", 1)
    for key in ("agent_ms_median", "agent_ms_p95", "agent_ms_p99", "critical_path_ms_median", "critical_path_ms_p99",
                "step_ms_median", "step_ms_p95", "central_step_ms_median", "wall_s_per_run_median",
                "min_footprint_distance_m"):
        assert isinstance(row[key], float) and np.isfinite(row[key]) and row[key] > 0, key
    assert row["collision_free_rate"] == 1.0 and row["min_separation_ratio"] is None  # footprints, not boxes
    (run,) = report["runs"]
    assert run["steps"] == 5 and run["collisions"] == 0 and len(run["agent_step_ms"]) == 4 * 5
    assert run["min_footprint_distance"] == pytest.approx(row["min_footprint_distance_m"])
    assert report["failed"] == []
    table = markdown.read_text()
    assert "| crossing | 4 | centralized | 1 | 0% | 100% |" in table
    assert table.splitlines()[4].endswith("| planes per agent | min footprint gap m |")


@pytest.mark.loop
def test_a_whole_centralised_crossing_run_reports_its_makespan(tmp_path):
    _, data = run_bench(tmp_path, families=["crossing"], sizes=[4], seeds=1, jobs=1, methods=("centralized",))
    (row,) = json.loads(data.read_text())["rows"]
    assert row["all_reached_rate"] == 1.0 and row["collision_free_rate"] == 1.0
    assert row["makespan_s_median"] > 0 and row["agent_ms_p99"] > 0 and row["critical_path_ms_p99"] > 0


def test_a_refused_admm_case_is_listed_with_its_reason_and_the_centralised_row_stays(tmp_path):
    def refusing(case: BenchCase, runs_dir: object) -> CaseOutcome:
        if case.method == "admm":
            raise ScenarioError("solver.method: admm does not take car agents yet; use centralized")
        return car_outcome(case)

    with pytest.raises(RuntimeError) as failed:
        run_bench(tmp_path, families=["crossing"], sizes=[4, 8], seeds=1, jobs=1, case_runner=refusing)
    message = str(failed.value)
    assert "\n" not in message and message.startswith("2 of 4 bench cases failed")
    assert "crossing-M4-seed0-admm: ScenarioError: solver.method: admm does not take car agents yet" in message
    report = json.loads((tmp_path / "bench.json").read_text())
    assert report["failed"] == [
        f"crossing-M{m}-seed0-admm: ScenarioError: solver.method: admm does not take car agents yet; use centralized"
        for m in (4, 8)]
    assert [(r["agents"], r["local"], r["runs"]) for r in report["rows"]] == [(4, "centralized", 1),
                                                                              (8, "centralized", 1)]
    assert all(r["agent_ms_p99"] is not None and r["critical_path_ms_p99"] is not None for r in report["rows"])
    assert all(r["makespan_s_median"] == 8.0 and r["cost_gap_pct_median"] is None for r in report["rows"])
    table = (tmp_path / "bench.md").read_text()
    assert "2 of 4 runs" in table and "Failed, left out of the table (2):" in table
    assert "* crossing-M8-seed0-admm: ScenarioError: solver.method: admm" in table
    assert load_outcomes(tmp_path) == [car_outcome(BenchCase("crossing", m, 0, "centralized", budget_s=600.0))
                                       for m in (4, 8)]  # the footprint gap survives the JSON


def test_point_swarm_tables_have_no_footprint_column_and_car_rows_sort_last():
    point = outcome("circle", 4, 0, "admm", 1.0)
    assert "footprint" not in markdown_table(aggregate([point]))
    cars = [car_outcome(BenchCase("crossing", 4, 0, method)) for method in ("admm", "centralized")]
    rows = aggregate([cars[0], point, cars[1]])
    assert [(r["family"], r["local"]) for r in rows] == [("circle", "qp"), ("crossing", "ipopt")]  # cars: IPOPT
    assert rows[1]["min_footprint_distance_m"] == pytest.approx(0.3) and rows[1]["min_separation_ratio"] is None
    assert rows[1]["cost_gap_pct_median"] == pytest.approx(0.0)  # ADMM against the centralised run, as for points
    lines = markdown_table(rows).splitlines()
    assert lines[2].endswith("| - |") and lines[3].endswith("| 0.300 |")


def test_a_case_its_validation_refuses_fails_with_its_reason_and_the_others_run(tmp_path):
    """A plane margin the scenario refuses (it applies to the ADMM case only): the real case fails
    in one line, settings are not blamed for it, and the centralised run still reports."""
    with pytest.raises(RuntimeError, match=r"^1 of 2 bench cases failed .* crossing-M4-seed0-admm: "):
        run_bench(tmp_path, families=["crossing"], sizes=[4], seeds=1, jobs=1, max_steps=2, plane_margin=-1.0,
                  settings={"weights.R": 0.5})
    report = json.loads((tmp_path / "bench.json").read_text())
    (failure,) = report["failed"]
    assert failure.startswith("crossing-M4-seed0-admm: ScenarioError: solver.plane_margin") and "\n" not in failure
    (row,) = report["rows"]
    assert (row["local"], row["runs"]) == ("centralized", 1) and row["agent_ms_median"] > 0
    assert report["runs"][0]["case"]["settings"] == [["weights.R", 0.5]]
    with pytest.raises(ValueError, match="^set: "):  # a bad setting is still refused before anything runs
        run_bench(tmp_path / "bad", families=["crossing"], sizes=[4], seeds=1, jobs=1, settings={"weights.R": -1})
    assert not (tmp_path / "bad").exists()


def test_each_family_runs_its_own_local_step_unless_asked():
    assert BenchCase("random", 4, 0).local == "qp" and BenchCase("crossing", 4, 0).local == "ipopt"  # cars: NLP
    assert BenchCase("crossing", 4, 0).scenario().solver.local == "ipopt"
    assert BenchCase("crossing", 4, 0, local="qp").scenario().solver.local == "qp"  # asked for: kept
    assert BenchCase("random", 4, 0, "centralized", local="qp").local == "ipopt"  # the reference's one NLP
    cases = plan_cases(["random", "crossing"], [4], 1, "serial", None, 60.0, 0)
    assert [(c.family, c.local) for c in cases] == [("random", "qp"), ("crossing", "ipopt")]
