"""The last safety pass (:class:`swarmpc.solvers.admm.settle.Settle`): fallback agents still
in conflict choose, among plans that need no solve, the combination whose first conflict comes
latest; agents whose solves succeeded keep their plans."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from swarmpc.config import scenario_from_dict
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.solvers.admm import ADMMConfig
from swarmpc.solvers.admm.messages import LocalResult, StepRequests
from swarmpc.solvers.admm.repair import Repair
from swarmpc.solvers.admm.safety import SafetyChecks
from swarmpc.solvers.admm.settle import Settle
from swarmpc.solvers.base import braking_plan

SCN = scenario_from_dict({
    "name": "settle", "dim": 2, "delta": 0.25, "limits": {"accel": 2.0},
    "agents": [{"start": [-3.0, 0.0], "goal": [3.0, 0.0]}, {"start": [3.0, 0.0], "goal": [-3.0, 0.0]},
               {"start": [0.0, 3.0], "goal": [0.0, -3.0]}],
})
S = OCPSettings.from_scenario(SCN)
BODIES = np.asarray(SCN.bodies, float)
M = len(BODIES)


def coasting(state: np.ndarray, agent: int, fallback: bool) -> LocalResult:
    """Agent ``agent``'s plan that holds its velocity from ``state``."""
    x = S.model.rollout(state, np.zeros((S.horizon, S.dim)))
    own = S.model.position(x[S.first_constrained_step:]).T.copy()
    return LocalResult(agent=agent, own=own, copies=np.zeros((0, S.dim, S.num_constrained)), states=x,
                       inputs=np.zeros((S.horizon, S.dim)), success=not fallback, fallback=fallback,
                       solve_time=0.0, max_slack=0.0, cost=0.0)


def settle(states: np.ndarray, plans: list[LocalResult]) -> tuple[SafetyChecks, list[LocalResult]]:
    safety = SafetyChecks(S, BODIES)
    requests = StepRequests(S, ADMMConfig(), BODIES, states, states, np.zeros((M, S.horizon + 1, 2 * S.dim)))
    return safety, Settle(requests, safety)(plans)


def test_two_failed_agents_head_on_both_brake_and_stay_apart():
    """Coasting, they meet mid-horizon; braking at 2 m/s^2 from 1 m/s each stops 0.25 m on: apart.
    One braking alone is not enough, so both switch."""
    states = np.array([[-0.6, 0.0, 1.0, 0.0], [0.6, 0.0, -1.0, 0.0], [0.0, 3.0, 0.0, 0.0]])
    plans = [coasting(states[k], k, fallback=k < 2) for k in range(M)]
    safety, settled = settle(states, plans)
    assert safety.first_close_steps(plans, [0, 1])[0] < S.num_constrained
    for k in (0, 1):
        assert np.allclose(settled[k].states, braking_plan(states[k], S)[0]) and settled[k].fallback
    assert settled[2] is plans[2]
    assert safety.first_close_steps(settled, [0, 1]) == (S.num_constrained, 0.0)


def test_an_agent_whose_solve_succeeded_keeps_its_plan():
    """Agent 1 (a success) coasts into agent 0 (a fallback): only agent 0 may change, and it brakes."""
    states = np.array([[-0.6, 0.0, 1.0, 0.0], [0.6, 0.0, -1.0, 0.0], [0.0, 3.0, 0.0, 0.0]])
    plans = [coasting(states[k], k, fallback=k == 0) for k in range(M)]
    _, settled = settle(states, plans)
    assert settled[1] is plans[1] and settled[2] is plans[2]
    assert np.allclose(settled[0].states, braking_plan(states[0], S)[0])


@settings(max_examples=60, deadline=None)
@given(
    positions=st.lists(st.floats(-1.0, 1.0), min_size=2 * M, max_size=2 * M),
    velocities=st.lists(st.floats(-1.5, 1.5), min_size=2 * M, max_size=2 * M),
    fallback=st.lists(st.booleans(), min_size=M, max_size=M),
)
def test_settling_never_brings_the_first_conflict_closer_and_moves_only_fallbacks(positions, velocities, fallback):
    states = np.hstack([np.reshape(positions, (M, 2)), np.reshape(velocities, (M, 2))])
    plans = [coasting(states[k], k, fallback[k]) for k in range(M)]
    safety, settled = settle(states, plans)
    fell = [k for k in range(M) if fallback[k]]
    for k in range(M):
        if not fallback[k]:
            assert settled[k] is plans[k]
        assert np.allclose(S.model.rollout(states[k], settled[k].inputs), settled[k].states)
        assert np.allclose(settled[k].own, S.model.position(settled[k].states[S.first_constrained_step:]).T)
    if fell:
        assert safety.first_close_steps(settled, fell)[0] >= safety.first_close_steps(plans, fell)[0]


def test_the_safety_passes_end_by_settling_agents_whose_every_re_plan_fails():
    """Through ``Repair.make_safe``: agents 0 and 1, coupled and head on, answer every re-plan with
    a fallback that coasts into the other; the passes still end with both braking, apart."""
    from types import MappingProxyType

    from swarmpc.solvers.admm.graph import CouplingGraph

    states = np.array([[-0.6, 0.0, 1.0, 0.0], [0.6, 0.0, -1.0, 0.0], [0.0, 3.0, 0.0, 0.0]])
    safety = SafetyChecks(S, BODIES)
    requests = StepRequests(S, ADMMConfig(), BODIES, states, states, np.zeros((M, S.horizon + 1, 2 * S.dim)))
    asked: list[int] = []

    def solve(batch):  # type: ignore[no-untyped-def]
        asked.extend(r.agent for r in batch)
        return [coasting(states[r.agent], r.agent, fallback=True) for r in batch]

    graph = CouplingGraph(~np.eye(M, dtype=bool), ((1,), (0,), ()), tuple(MappingProxyType({}) for _ in range(M)))
    plans = [coasting(states[k], k, fallback=False) for k in range(M)]
    z = np.array([p.own for p in plans])
    safe = Repair(requests, safety, solve).make_safe(graph, z, 10.0, plans, repair_all=True, stranded_check=True)
    assert {0, 1} <= set(asked)  # the passes did ask them
    for k in (0, 1):
        assert np.allclose(safe.results[k].states, braking_plan(states[k], S)[0])
    assert safety.first_close_steps(safe.results, [0, 1]) == (S.num_constrained, 0.0)
