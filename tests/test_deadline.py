"""The critical path of an MPC step and anytime ADMM with a deadline (``solver.deadline``).

The critical path is what a step would take with one core per agent: per batch of local steps the
slowest agent's, plus the coordinator's own work (:class:`swarmpc.solvers.admm.StepClock`). A
deadline may only remove ADMM iterations: every plan is still made safe by the repair pass."""

from __future__ import annotations

import json
import time
from types import SimpleNamespace

import numpy as np
import pytest

from swarmpc.bench import BenchCase, CaseOutcome, aggregate, load_outcomes, markdown_table, write_report
from swarmpc.model.dynamics import DoubleIntegrator
from swarmpc.model.geometry import count_body_collisions
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation import contract
from swarmpc.simulation.controller import Controller
from swarmpc.simulation.loop import simulate
from swarmpc.simulation.results import deadline_summary, write_run
from swarmpc.solvers.admm import StepClock
from swarmpc.solvers.admm.clock import BatchBudget
from swarmpc.solvers.executors import SerialExecutor

CROSSING_FROM = 20
"""paper-2d's agents couple from step 23 on: from here on a step iterates."""


@pytest.fixture(scope="module")
def crossing():
    """paper-2d and its states after ``CROSSING_FROM`` steps (centralised, quick): agents about
    to cross at the centre, where ADMM needs tens of iterations per step."""
    scn = builtin_scenario("paper-2d").with_updates(**{"solver.method": "centralized",
                                                       "stop.max_steps": CROSSING_FROM})
    return builtin_scenario("paper-2d"), simulate(scn).states[-1]


def fly(scn, states, steps: int):
    """Step a :class:`Controller` of ``scn`` by hand from ``states``; returns the applied states
    (steps + 1, M, 2d), the plans (steps, M, N + 1, 2d) and the step records."""
    model = DoubleIntegrator(scn.dim, scn.dt, scn.discretization)
    applied, plans, records = [states], [], []
    with Controller(scn) as mpc:
        for _ in range(steps):
            states = model.step(states, mpc.step(states))
            applied.append(states)
            plans.append(mpc.plan.states)
            records.append(mpc.last_record)
    return np.array(applied), np.array(plans), records


def test_the_critical_path_is_recorded_and_bounded(tmp_path):
    """Serial executor: at most the step's wall time, at least any agent's solve time in it."""
    scn = builtin_scenario("paper-2d").with_updates(**{"stop.max_steps": 26})  # the last steps iterate
    result = simulate(scn)
    for k, record in enumerate(result.records):
        assert 0.0 < record.critical_path_s <= record.wall_time, f"step {k}"
        # an agent's solves within a step, summed over its iterations, each lie on the path
        assert record.critical_path_s >= record.agent_times.max(), f"step {k}"
        assert not record.deadline_stop
    assert max(r.admm_iterations for r in result.records) > 1
    folder = write_run(result, tmp_path / "run")
    with np.load(folder / "steps.npz") as steps:
        assert steps["critical_path_s"].shape == (26,) and steps["critical_path_s"].dtype == np.float64
        assert np.array_equal(steps["critical_path_s"], [r.critical_path_s for r in result.records])
        assert not steps["deadline_stop"].any()
    summary = json.loads((folder / "summary.json").read_text())
    path_ms = 1000.0 * np.array([r.critical_path_s for r in result.records])
    assert summary["critical_path_ms"]["p99"] == pytest.approx(np.percentile(path_ms, 99))
    assert summary["critical_path_ms"]["max"] == pytest.approx(path_ms.max())
    assert summary["deadline_s"] == scn.dt  # no deadline set: counted against the sample period
    assert summary["deadline_misses"] == int(np.sum(path_ms > 1000.0 * scn.dt))
    assert summary["deadline_stops"] == 0


def test_an_agents_time_counts_its_whole_local_step_not_only_its_solver(crossing, monkeypatch):
    """Bookkeeping an agent does around its solver calls is compute it spends: an agent that
    dawdles PAUSE seconds per request outside its solver is charged for it in ``agent_times``."""
    from swarmpc.solvers.admm.agent import LocalAgent

    pause, solve = 0.004, LocalAgent.solve

    def dawdling(self, request):
        began = time.perf_counter()
        while time.perf_counter() - began < pause:
            pass
        return solve(self, request)

    monkeypatch.setattr(LocalAgent, "solve", dawdling)
    scn, states = crossing
    _, _, records = fly(scn.with_updates(**{"solver.local": "qp"}), states, 3)
    for k, record in enumerate(records):
        # every agent is asked at least once per ADMM iteration
        assert record.agent_times.min() >= pause * record.admm_iterations, f"step {k}"
        assert record.critical_path_s >= record.agent_times.max(), f"step {k}"


def test_a_centralised_step_is_all_on_the_critical_path():
    scn = builtin_scenario("paper-2d").with_updates(**{"solver.method": "centralized", "stop.max_steps": 2})
    for record in simulate(scn).records:
        assert record.critical_path_s == record.wall_time and not record.deadline_stop


def test_a_tiny_deadline_stops_early_yet_every_plan_stays_safe(crossing):
    """1 ms: no step affords a second iteration. Each step ends through the repair pass, its
    plans keep the bodies apart, the overruns are counted, and the run goes on."""
    scn, states = crossing
    tiny = scn.with_updates(**{"solver.deadline": 1e-3, "solver.admm.deadline_repair": "sequential"})
    applied, plans, records = fly(tiny, states, 30)
    assert len(records) == 30
    stopped = [r.deadline_stop for r in records]
    assert sum(stopped) >= 10  # the crossing would have iterated
    for k, record in enumerate(records):
        assert record.admm_iterations == 1, f"step {k}"
        assert record.repaired or not record.deadline_stop, f"step {k}: stopped early without the repair pass"
    d = scn.dim
    assert count_body_collisions(applied[:, :, :d], scn.bodies) == 0
    for k, plan in enumerate(plans):  # every step's committed plans, with the bodies
        assert count_body_collisions(np.transpose(plan[:, :, :d], (1, 0, 2)), scn.bodies) == 0, f"step {k}"
    summary = deadline_summary(records, tiny)
    assert summary["deadline_s"] == 1e-3 and summary["deadline_stops"] == sum(stopped)
    assert summary["deadline_misses"] == sum(r.critical_path_s > 1e-3 for r in records) > 0


def test_a_deadline_stop_by_selection_keeps_the_swarm_apart(crossing):
    """paper-2d at its crossing under a 1 ms deadline: every step stops after one iteration and
    ends by selection. Each agent flies its last iterate or the plan it flew before, shifted; the
    plans and the flown states keep the bodies apart."""
    scn, states = crossing
    tiny = scn.with_updates(**{"solver.deadline": 1e-3, "solver.admm.deadline_repair": "select"})
    applied, plans, records = fly(tiny, states, 25)
    assert sum(r.deadline_stop for r in records) >= 10
    d = scn.dim
    assert count_body_collisions(applied[:, :, :d], scn.bodies) == 0
    for k, plan in enumerate(plans):
        assert count_body_collisions(np.transpose(plan[:, :, :d], (1, 0, 2)), scn.bodies) == 0, f"step {k}"
    shifted = [np.allclose(plans[k][i][1:-1], plans[k - 1][i][2:], atol=1e-9)
               for k in range(1, len(plans)) for i in range(len(states)) if records[k].deadline_stop]
    assert any(shifted) and not all(shifted)  # some agents fell back to their committed plans, not all
    assert np.linalg.norm(applied[-1, :, :d] - applied[0, :, :d], axis=1).min() > 0.1  # the swarm moved on


@pytest.mark.parametrize("batches", [0, 1, 2])
def test_a_deadline_stop_on_a_budget_repairs_what_fits_and_selects_the_rest(crossing, monkeypatch, batches):
    """paper-2d at its crossing under a 1 ms deadline with ``deadline_repair: budget``, its budget
    made to allow ``batches`` repair batches a step: the repair pass is cut short there, the
    selection pass chooses between what it left and the committed plans, and the plans and the
    flown states keep the bodies apart."""
    cut: list[int] = []

    def allows(self: BatchBudget) -> bool:
        self.asked = getattr(self, "asked", 0) + 1
        if self.asked > batches:
            cut.append(self.asked)
            return False
        return True

    monkeypatch.setattr(BatchBudget, "allows", allows)
    scn, states = crossing
    tiny = scn.with_updates(**{"solver.deadline": 1e-3, "solver.admm.deadline_repair": "budget"})
    applied, plans, records = fly(tiny, states, 20)
    assert sum(r.deadline_stop for r in records) >= 10 and cut  # repair passes were cut short
    d = scn.dim
    assert count_body_collisions(applied[:, :, :d], scn.bodies) == 0
    for k, plan in enumerate(plans):
        assert count_body_collisions(np.transpose(plan[:, :, :d], (1, 0, 2)), scn.bodies) == 0, f"step {k}"
    assert np.linalg.norm(applied[-1, :, :d] - applied[0, :, :d], axis=1).max() > 0.1  # the swarm moved on


def test_a_deadline_that_never_binds_changes_nothing(crossing):
    scn, states = crossing
    scn = scn.with_updates(**{"solver.admm.independent_first": False})  # these steps iterate, none is probed
    plain, _, plain_records = fly(scn, states, 4)
    roomy, _, roomy_records = fly(scn.with_updates(**{"solver.deadline": 1e6}), states, 4)
    assert max(r.admm_iterations for r in plain_records) > 10
    assert np.array_equal(plain, roomy)
    assert [r.admm_iterations for r in plain_records] == [r.admm_iterations for r in roomy_records]
    assert not any(r.deadline_stop for r in roomy_records)


class FakeTime:
    """A clock the test advances by hand."""

    def __init__(self) -> None:
        self.now = 0.0

    def perf_counter(self) -> float:
        return self.now


def test_the_clock_counts_a_batch_as_its_slowest_agent_and_stops_before_an_overrun():
    fake = FakeTime()
    clock = StepClock(deadline=1.0, clock=fake.perf_counter)

    class Batch:
        """An executor whose batch takes ``wall`` seconds, its agents ``calls`` each."""

        def __init__(self, wall: float, calls: list[float]) -> None:
            self.wall, self.calls = wall, calls

        def solve(self, requests):
            fake.now += self.wall
            return [SimpleNamespace(call_time=c, solve_time=0.5 * c) for c in self.calls]

    assert clock.next_iteration()  # the first iteration always runs
    fake.now += 0.05  # the coordinator's own work
    clock.solve(Batch(0.6, [0.1, 0.2, 0.3]), [])  # serial: 0.6 s, one core per agent: 0.3 s
    assert clock.elapsed() == pytest.approx((0.65, 0.35))
    assert clock.next_iteration()  # 0.35 + 0.35 <= 1
    clock.solve(Batch(0.6, [0.1, 0.2, 0.3]), [])
    fake.now += 0.05
    assert clock.elapsed()[1] == pytest.approx(0.7)
    assert not clock.next_iteration() and clock.stopped  # 0.7 + 0.35 > 1
    clock.solve(Batch(0.2, [0.2]), [])  # a repair's re-plan: one agent, all of it on the path
    assert clock.elapsed()[1] == pytest.approx(0.9)
    assert StepClock().next_iteration() and StepClock(None).next_iteration()


def test_a_batch_budget_allows_a_batch_while_the_longest_batch_so_far_still_fits():
    fake = FakeTime()
    clock = StepClock(deadline=1.0, clock=fake.perf_counter)
    assert clock.next_iteration()
    fake.now += 0.2
    assert clock.next_iteration()  # an iteration's share: 0.2
    fake.now += 0.2
    budget = BatchBudget(clock)
    assert budget.longest == pytest.approx(0.2)  # at first a batch is estimated as an iteration
    assert budget.allows()  # 0.4 + 0.2 <= 1
    fake.now += 0.3  # that batch took longer than an iteration
    assert budget.allows()  # 0.7 + 0.3 <= 1
    assert budget.longest == pytest.approx(0.3)
    fake.now += 0.05
    assert not budget.allows()  # 0.75 + 0.3 > 1
    assert list(budget.history) == pytest.approx([0.3, 0.05]) and budget.closed_at == pytest.approx(0.75)
    fresh = StepClock(deadline=1.0, clock=fake.perf_counter)
    assert fresh.next_iteration()
    later = BatchBudget(fresh, budget.history)  # the next step: its batches remembered
    assert later.longest == pytest.approx(0.3)
    assert later.allows()  # 0 + 0.3 <= 1
    assert not BatchBudget(fresh, budget.history, margin=0.75).allows()  # 0 + 0.3 + 0.75 > 1
    roomy = BatchBudget(StepClock(None, clock=fake.perf_counter))
    fake.now += 100.0
    assert roomy.allows() and roomy.allows()


def test_the_run_folder_contract_documents_the_critical_path():
    keys = {doc.key for doc in contract.SUMMARY_KEYS}
    assert {"critical_path_ms.median", "critical_path_ms.p95", "critical_path_ms.p99", "critical_path_ms.max",
            "deadline_misses", "deadline_s", "deadline_stops"} <= keys
    arrays = {(doc.file, doc.name): doc for doc in contract.ARRAYS}
    assert arrays["steps.npz", "critical_path_s"].shape == "(T,)"
    assert arrays["steps.npz", "deadline_stop"].dtype == "bool"


def _outcome(seed: int, critical: list[float] | None, misses: int | None) -> CaseOutcome:
    return CaseOutcome(
        case=BenchCase("random", 8, seed), steps=2, timed_out=False, all_reached=True, collisions=0,
        min_separation_ratio=1.2, time_to_goal_s=1.0, cost=1.0, step_ms=[10.0, 20.0],
        agent_step_ms=[1.0, 2.0, 3.0, 100.0], iterations=[1, 3], solver_failures=0, wall_time_s=4.0 + seed,
        critical_path_ms=critical, deadline_misses=misses,
    )


def test_bench_reports_critical_path_per_agent_p99_and_wall_time_and_reads_older_reports(tmp_path):
    runs = [_outcome(0, [5.0, 50.0], 0), _outcome(1, [7.0, 150.0], 1)]
    (row,) = aggregate(runs)
    assert row["critical_path_ms_median"] == pytest.approx(28.5)
    assert row["critical_path_ms_p99"] == pytest.approx(np.percentile([5.0, 50.0, 7.0, 150.0], 99))
    assert row["agent_ms_p99"] == pytest.approx(np.percentile([1.0, 2.0, 3.0, 100.0] * 2, 99))
    assert row["wall_s_per_run_median"] == pytest.approx(4.5) and row["deadline_misses"] == 1
    table = markdown_table([row])
    assert "critical path ms median | p99 | deadline misses" in table and "wall s per run" in table
    write_report(tmp_path / "new", runs, "m", 1.0)
    assert load_outcomes(tmp_path / "new") == runs
    # a report written before these fields: read, its rows show no critical path
    data = json.loads((tmp_path / "new" / "bench.json").read_text())
    for run in data["runs"]:
        del run["critical_path_ms"], run["deadline_misses"]
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "bench.json").write_text(json.dumps(data))
    (old_row,) = aggregate(load_outcomes(tmp_path / "old"))
    assert old_row["critical_path_ms_median"] is None and old_row["deadline_misses"] is None
    assert old_row["agent_ms_p99"] == row["agent_ms_p99"]


def test_the_clock_keeps_its_reserve_free_of_iterations():
    """An iteration that would fit the deadline alone is refused when the reserve for the safety
    passes would not fit after it."""
    for reserve, expected in ((0.0, True), (0.2, True), (0.31, False)):
        fake = FakeTime()
        clock = StepClock(deadline=1.0, clock=fake.perf_counter, reserve=reserve)
        assert clock.next_iteration()
        fake.now += 0.35
        assert clock.next_iteration() is expected, reserve  # 0.35 + 0.35 + reserve vs 1
        assert clock.stopped is not expected


class BatchLog(SerialExecutor):
    """The serial executor, keeping the agents and neighbours of every batch of repair requests."""

    def __init__(self) -> None:
        super().__init__()
        self.batches: list[list[tuple[int, tuple[int, ...]]]] = []

    def solve(self, requests):  # type: ignore[no-untyped-def]
        if requests and all(r.repair for r in requests):
            self.batches.append([(r.agent, r.neighbours) for r in requests])
        return super().solve(requests)


def test_a_deadline_stop_repairs_uncoupled_agents_in_one_batch():
    """The repair pass asks runs of agents that hold no copy of each other in one batch (their
    answers cannot depend on each other), and the plans stay apart."""
    scn = builtin_scenario("random", agents=16, dim=3, seed=0).with_updates(
        **{"solver.deadline": 1e-3, "solver.local": "qp", "stop.max_steps": 3,
           "solver.admm.deadline_repair": "sequential"})
    log = BatchLog()
    try:
        result = simulate(scn, executor=log)
    finally:
        log.close()
    assert result.summary["collisions"] == 0
    assert log.batches and max(len(batch) for batch in log.batches) > 1
    for batch in log.batches:
        agents = [agent for agent, _ in batch]
        assert len(set(agents)) == len(agents)
        assert not any(other in agents for _, neighbours in batch for other in neighbours)
