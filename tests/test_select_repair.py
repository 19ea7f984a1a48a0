"""The selection pass after a deadline stop (``solver.admm.deadline_repair: select``): every agent
flies its new plan or its committed plan, and every pair that can meet stays apart."""

from __future__ import annotations

from types import MappingProxyType

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from swarmpc.formulation.ocp import OCPSettings
from swarmpc.scenarios import builtin_scenario
from swarmpc.solvers.admm import ADMMConfig
from swarmpc.solvers.admm.graph import CouplingGraph
from swarmpc.solvers.admm.messages import LocalResult, StepRequests
from swarmpc.solvers.admm.replan import Replanner
from swarmpc.solvers.admm.safety import SafetyChecks
from swarmpc.solvers.admm.selection import Selection

SCN = builtin_scenario("paper-2d")
S = OCPSettings.from_scenario(SCN)
M = 4
BODIES = np.asarray(SCN.bodies, float)[:M]
K = S.num_constrained


def result(agent: int, points: np.ndarray, fallback: bool = False) -> LocalResult:
    """An answer whose own positions stay at ``points`` (K, d) (states only for their shape)."""
    states = np.zeros((S.horizon + 1, 2 * S.dim))
    return LocalResult(agent=agent, own=np.asarray(points, float).T.copy(), copies=np.zeros((0, S.dim, K)),
                       states=states, inputs=np.zeros((S.horizon, S.dim)), success=not fallback,
                       fallback=fallback, solve_time=0.0, max_slack=0.0, cost=0.0)


def selection(new_points: np.ndarray, committed_points: np.ndarray, fallback: list[bool],
              waiting: np.ndarray | None = None):
    safety = SafetyChecks(S, BODIES)
    states = np.zeros((M, 2 * S.dim))
    states[:, : S.dim] = committed_points[:, 0]
    requests = StepRequests(S, ADMMConfig(), BODIES, states, states, np.zeros((M, S.horizon + 1, 2 * S.dim)))
    everyone = ~np.eye(M, dtype=bool)
    graph = CouplingGraph(everyone, tuple(() for _ in range(M)), tuple(MappingProxyType({}) for _ in range(M)))
    new = [result(i, new_points[i], fallback[i]) for i in range(M)]
    committed = [result(i, committed_points[i], True) for i in range(M)]
    selection = Selection(requests, safety, Replanner(requests, lambda requests: []))
    chosen, clashes = selection.select(graph, new, committed, waiting)
    return safety, new, committed, chosen, clashes


def apart(safety: SafetyChecks, plans: list[LocalResult], i: int, j: int) -> bool:
    return bool(safety.pairs_apart(plans, np.array([i]), np.array([j]))[0])


@settings(max_examples=60, deadline=None)
@given(
    offsets=st.lists(st.floats(-1.5, 1.5), min_size=M * K * 2, max_size=M * K * 2),
    fallback=st.lists(st.booleans(), min_size=M, max_size=M),
)
def test_selection_keeps_every_pair_apart_and_reverts_only_agents_in_a_clash(offsets, fallback):
    """Committed plans far apart (corners of a 6 m square), new plans anywhere near the centre:
    every pair of the chosen plans keeps half the OBCA separation; an agent flies its new plan or
    its committed one, a fallback answer its committed one, and an agent goes back to its committed
    plan only if its new plan clashed with another agent's new or committed plan."""
    corners = np.array([[-3.0, -3.0], [3.0, -3.0], [-3.0, 3.0], [3.0, 3.0]])
    committed_points = np.repeat(corners[:, None, :], K, axis=1)
    new_points = np.asarray(offsets).reshape(M, K, 2)
    safety, new, committed, chosen, clashes = selection(new_points, committed_points, fallback)
    assert clashes == []
    for i in range(M):
        assert chosen[i] is new[i] or chosen[i] is committed[i]
        if fallback[i]:
            assert chosen[i] is committed[i]
        for j in range(i + 1, M):
            assert apart(safety, chosen, i, j), (i, j)
        if chosen[i] is committed[i] and not fallback[i]:
            others = [p for j in range(M) if j != i for p in (new[j], committed[j])]
            assert any(not apart(safety, [new[i], other], 0, 1) for other in others), i


def test_committed_plans_in_conflict_are_handed_on():
    """Two committed plans that overlap cannot be chosen apart: the pair is returned."""
    corners = np.array([[-3.0, -3.0], [3.0, -3.0], [0.0, 0.0], [0.0, 0.0]])
    committed_points = np.repeat(corners[:, None, :], K, axis=1)
    _, _, _, _, clashes = selection(committed_points + 10.0, committed_points, [False, False, True, True])
    assert clashes == [(2, 3)]


def test_a_failed_clearing_replan_keeps_the_committed_plan_and_asks_the_partner():
    """Committed plans of agents 2 and 3 overlap. Agent 3 (the higher index) re-plans first, a
    quick call; it fails, so agent 3 keeps its committed plan and agent 2 re-plans against that
    plan, pinned."""
    corners = np.array([[-3.0, -3.0], [3.0, -3.0], [0.0, 0.0], [0.0, 0.0]])
    committed_points = np.repeat(corners[:, None, :], K, axis=1)
    safety, _, committed, chosen, clashes = selection(committed_points + 10.0, committed_points,
                                                      [False, False, True, True])
    asked = []

    def solve(requests):
        answers = []
        for r in requests:
            asked.append((r.agent, r.neighbours, r.z_neighbours.copy()))
            assert r.quick and r.repair  # a clearing call has a cheaper way out than restarts
            away = np.full((K, 2), 5.0 if r.agent == 2 else 0.0)
            answers.append(result(r.agent, away, fallback=r.agent == 3))
        return answers

    graph = CouplingGraph(~np.eye(M, dtype=bool), tuple(() for _ in range(M)),
                          tuple(MappingProxyType({}) for _ in range(M))).coupled(clashes)
    states = np.zeros((M, 2 * S.dim))
    requests = StepRequests(S, ADMMConfig(), BODIES, states, states, np.zeros((M, S.horizon + 1, 2 * S.dim)))
    z = np.zeros((M, S.dim, K))
    cleared = Selection(requests, safety, Replanner(requests, solve)).clear(graph, z, 1.0, chosen, clashes)
    assert [agent for agent, _, _ in asked] == [3, 2]
    assert asked[1][1] == (3,) and np.allclose(asked[1][2][0], committed[3].own)
    assert cleared[3].own is committed[3].own and np.allclose(cleared[2].own, 5.0)
    assert apart(safety, cleared, 2, 3)


def test_the_agent_that_waited_longer_keeps_its_iterate():
    """Iterates of agents 0 and 1 overlap, committed plans far apart: with no waiting the lower
    index goes back; after agent 0 has flown its committed plan for three steps, agent 1 does."""
    corners = np.array([[-3.0, -3.0], [3.0, -3.0], [-3.0, 3.0], [3.0, 3.0]])
    committed_points = np.repeat(corners[:, None, :], K, axis=1)
    new_points = committed_points.copy()
    new_points[0] = new_points[1] = 0.0
    _, new, committed, chosen, _ = selection(new_points, committed_points, [False] * M)
    assert chosen[0] is committed[0] and chosen[1] is new[1]
    _, new, committed, chosen, _ = selection(new_points, committed_points, [False] * M, np.array([3, 0, 0, 0]))
    assert chosen[0] is new[0] and chosen[1] is committed[1]


@pytest.mark.parametrize("lands_at, accepted", [(5.0, True), (3.0, False)])
def test_a_refreshed_plan_replaces_the_committed_one_only_where_it_keeps_every_pair_apart(lands_at, accepted):
    """Agent 0's iterate ran into agent 1's plan, so agent 0 re-plans coupled with agent 1 (a quick
    call against the chosen plans); its answer is flown only if it keeps clear of every other
    chosen plan: at (5, 5) it is, at agent 3's corner (3, 3) it is not."""
    corners = np.array([[-3.0, -3.0], [3.0, -3.0], [-3.0, 3.0], [3.0, 3.0]])
    committed_points = np.repeat(corners[:, None, :], K, axis=1)
    iterate_points = committed_points.copy()
    iterate_points[0] = corners[1]
    safety, iterates, committed, chosen, _ = selection(iterate_points, committed_points, [False] * M)
    assert chosen[0] is committed[0]

    def solve(requests):
        assert all(r.quick and r.repair and r.neighbours == (1,) for r in requests)
        return [result(r.agent, np.full((K, 2), lands_at)) for r in requests]

    graph = CouplingGraph(~np.eye(M, dtype=bool), tuple(() for _ in range(M)),
                          tuple(MappingProxyType({}) for _ in range(M)))
    states = np.zeros((M, 2 * S.dim))
    requests = StepRequests(S, ADMMConfig(), BODIES, states, states, np.zeros((M, S.horizon + 1, 2 * S.dim)))
    repair = Selection(requests, safety, Replanner(requests, solve))
    pairs = repair.pairs_to_check(graph, chosen, committed)
    refreshed, coupled = repair.refresh(graph, np.zeros((M, S.dim, K)), 1.0, chosen, iterates, [0], pairs)
    assert coupled.neighbours[0] == (1,) and coupled.neighbours[1] == (0,)
    assert (refreshed[0] is not committed[0]) is accepted
    assert all(refreshed[i] is chosen[i] for i in range(1, M))


def test_the_replanner_charges_every_replan_to_its_agent():
    """The safety passes' compute is what the agents spent on every re-plan asked (a retry and an
    answer not taken count too), not only on the answers that stand at the end."""
    from swarmpc.solvers.admm.messages import TimedResult

    states = np.zeros((M, 2 * S.dim))
    requests = StepRequests(S, ADMMConfig(), BODIES, states, states, np.zeros((M, S.horizon + 1, 2 * S.dim)))
    no_planes = tuple(MappingProxyType({}) for _ in range(M))
    graph = CouplingGraph(~np.eye(M, dtype=bool), ((1,), (0,), (3,), (2,)), no_planes)
    plans = [result(i, np.zeros((K, S.dim))) for i in range(M)]

    def answers(asked):
        return [TimedResult(**{**vars(result(r.agent, np.zeros((K, S.dim)), fallback=r.agent == 1))},
                            call_time=0.25 + r.agent) for r in asked]

    replan = Replanner(requests, answers)
    z = np.zeros((M, S.dim, K))
    replan([0, 2], graph, z, 10.0, plans, [False, False])
    replan([0, 1], graph, z, 10.0, plans, [False, True])  # agent 0 again, agent 1 fails
    assert replan.spent.tolist() == [0.5, 1.25, 2.25, 0.0]
    assert replan.failed == 1
