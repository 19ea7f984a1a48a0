"""Symmetric swaps: agents that stall far from their goal are detected (``deadlocks`` in the
summary) and detoured until every agent reaches its goal without a collision."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import load_folder, recount_collisions
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.deadlock import DeadlockPolicy, DeadlockResolver
from swarmpc.simulation.loop import simulate
from swarmpc.simulation.results import write_run


def _check_swap(folder) -> dict:
    summary, arrays = load_folder(folder)
    states, goals = arrays["states"], arrays["goals"]
    final = np.linalg.norm(states[-1, :, :2] - goals[:, :2], axis=1)
    assert np.all(final <= 0.05 + 1e-9), final.max()
    collisions, ratio = recount_collisions(states, arrays["delta"])
    assert collisions == 0 and ratio >= 1.0
    assert summary["all_reached"] and summary["collisions"] == 0
    return summary


@pytest.mark.parametrize("agents", [2, 4, pytest.param(8, marks=pytest.mark.loop)])
def test_circle_swap_unjams(agents, tmp_path):
    # the paper's weights and the reactive rule alone: the agents meet head-on fast enough to jam
    # (with Qf: lqr they arrive slower and circle-4 does not jam at all; keeping right, nobody jams)
    scn = builtin_scenario("circle", agents=agents).with_updates(
        **{"solver.method": "centralized", "weights.Q": 0.1, "weights.Qf": 1.0, "deadlock.keep_right_deg": 0.0})
    summary = _check_swap(write_run(simulate(scn), tmp_path / f"circle-{agents}"))
    # the head-on meeting does jam, and the summary says so
    assert summary["deadlocks"] >= 1
    assert summary["steps"] < scn.stop.max_steps


@pytest.mark.slow
@pytest.mark.parametrize("agents", [12, 16])
def test_large_circle_swap_unjams(agents, tmp_path):
    # circle-16 needs ~750 steps, more than the built-in 600
    scn = builtin_scenario("circle", agents=agents).with_updates(
        **{"solver.method": "centralized", "stop.max_steps": 1200}
    )
    _check_swap(write_run(simulate(scn), tmp_path / f"circle-{agents}"))


@pytest.mark.slow
def test_circle_swap_unjams_with_admm(tmp_path):
    _check_swap(write_run(simulate(builtin_scenario("circle", agents=4)), tmp_path / "circle-4-admm"))


def test_detector_needs_slow_far_and_crowded_for_patience_steps():
    resolver = DeadlockResolver(2, 2, DeadlockPolicy(keep_right_deg=0.0))
    goals = np.array([[2.0, 0.0, 0, 0], [-2.0, 0.0, 0, 0]])
    jammed = np.array([[-0.2, 0.0, 0.0, 0.0], [0.2, 0.0, 0.0, 0.0]])
    moving = jammed + np.array([0, 0, 0.5, 0])
    for step in range(10):
        assert np.array_equal(resolver.goals(step, moving, goals), goals)
    assert resolver.events == []
    patience = resolver.policy.patience
    for step in range(10, 10 + patience - 1):
        assert np.array_equal(resolver.goals(step, jammed, goals), goals)
    detoured = resolver.goals(10 + patience - 1, jammed, goals)
    assert len(resolver.events) == 2
    # both turn right of their goal direction: agent 0 heads +x, so it steps to -y; agent 1 to +y
    assert detoured[0, 1] < 0 < detoured[1, 1]
    # an agent stuck alone far from its goal (a static trap) waits longer before it detours
    lonely = DeadlockResolver(2, 2)
    apart = np.array([[-1.9, 0.0, 0, 0], [1.9, 0.0, 0, 0]])
    for step in range(lonely.policy.lonely_patience - 1):
        lonely.goals(step, apart, goals)
    assert lonely.events == []
    lonely.goals(lonely.policy.lonely_patience - 1, apart, goals)
    assert len(lonely.events) == 2


def test_repeated_jams_get_desynchronised_detours():
    policy = DeadlockResolver(2, 2).policy
    goals = np.array([[2.0, 0.0, 0, 0], [-2.0, 0.0, 0, 0]])
    jammed = np.array([[-0.2, 0.0, 0.0, 0.0], [0.2, 0.0, 0.0, 0.0]])
    runs = []
    for seed in (0, 1):
        resolver = DeadlockResolver(2, 2, seed=seed)
        holds = []
        step = 0
        while len(resolver.events) < 2 * (policy.escalate_after + 1):
            before = len(resolver.events)
            resolver.goals(step, jammed, goals)
            if len(resolver.events) > before:
                holds.append(resolver._detour_left.copy() + 1)  # one hold step is used at once
            step += 1
        runs.append(holds)
        # the first detours are the plain rule, identical for both agents
        for hold in holds[: policy.escalate_after]:
            assert np.all(hold == policy.hold)
        # from the escalation on, the two agents' holds differ and are longer
        last = holds[-1]
        assert last[0] != last[1] and np.all(last >= policy.hold)
    assert not np.array_equal(runs[0][-1], runs[1][-1])  # seeded: another seed, other draws


def test_slow_approach_next_to_a_parked_agent_is_not_a_jam():
    resolver = DeadlockResolver(2, 2)
    goals = np.array([[0.0, 0.0, 0, 0], [0.4, 0.0, 0, 0]])
    for step in range(30):
        # agent 0 crawls towards its goal at 0.03 m/s (3 mm per step); agent 1 is parked at its goal
        x = -0.5 + 0.003 * step
        states = np.array([[x, 0.0, 0.03, 0.0], [0.4, 0.0, 0.0, 0.0]])
        assert np.array_equal(resolver.goals(step, states, goals), goals)
    assert resolver.events == []
    assert resolver._stalled.max() == 0
    # the same crawl away from a goal another agent sits on (no progress) is a jam
    stuck = DeadlockResolver(2, 2)
    for step in range(30):
        states = np.array([[-0.3 - 0.003 * step, 0.0, -0.03, 0.0], [0.2, 0.0, 0.0, 0.0]])
        stuck.goals(step, states, goals)
    assert stuck.events and stuck.events[0] == (stuck.policy.patience - 1, 0)


def test_overshot_free_goal_among_parked_neighbours_is_not_a_jam():
    # agent 0 drifted 0.2-0.3 m past its goal and brakes slowly; parked agents sit 0.55 m from it,
    # none of them in the corridor back to its goal: nothing to unjam (it used to circle its goal)
    resolver = DeadlockResolver(3, 2, clearance=0.35)
    goals = np.array([[0.0, 0.0, 0, 0], [0.55, 0.35, 0, 0], [-0.35, 0.55, 0, 0]])
    for step in range(40):
        x = 0.2 + 0.002 * step
        states = np.array([[x, 0.0, 0.02, 0.0], [0.55, 0.35, 0, 0], [-0.35, 0.55, 0, 0]])
        assert np.array_equal(resolver.goals(step, states, goals), goals)
    assert resolver.events == []
    # the same drift with a parked agent between it and its goal is a jam
    blocked = DeadlockResolver(3, 2, clearance=0.35)
    goals[1] = [-0.45, 0.0, 0, 0]
    for step in range(40):
        x = 0.2 + 0.002 * step
        states = np.array([[x, 0.0, 0.02, 0.0], [0.1, 0.05, 0, 0], [-0.35, 0.55, 0, 0]])
        blocked.goals(step, states, goals)
    assert blocked.events and blocked.events[0] == (blocked.policy.patience, 0)  # 0.2 m: not yet "far"


def test_blocking_follows_the_clearance_per_axis():
    # a neighbour 0.3 m above the corridor blocks when the vertical clearance is large (downwash)
    positions = np.array([[0.0, 0.0, 1.0], [0.5, 0.0, 1.3]])
    goals = np.array([[1.0, 0.0, 1.0], [0.5, 0.0, 1.3]])
    assert not DeadlockResolver(2, 3, clearance=0.2).blocked(positions, goals)[0]
    assert DeadlockResolver(2, 3, clearance=np.array([0.2, 0.2, 0.35])).blocked(positions, goals)[0]


def _sliding_pair(step: int) -> np.ndarray:
    """Two agents in contact turning round their common centre at 0.1 m/s, neither closer to
    its goal from one second to the next (what held two agents of random M = 64 for 25 s)."""
    angle = 0.02 * np.sin(0.3 * step)
    offset = 0.18 * np.array([np.cos(angle), np.sin(angle)])
    velocity = np.array([0.0, 0.1 * np.sign(np.cos(0.3 * step))])
    return np.array([[*-offset, *-velocity], [*offset, *velocity]])


def test_a_pair_sliding_round_each_other_is_a_jam_once_progress_is_watched():
    from swarmpc.simulation.deadlock import DeadlockPolicy

    goals = np.array([[1.0, 0.0, 0, 0], [-1.0, 0.0, 0, 0]])  # each behind the other
    speed_only = DeadlockResolver(2, 2)
    window = 20
    watched = DeadlockResolver(2, 2, DeadlockPolicy(progress_window=window))
    for step in range(60):
        speed_only.goals(step, _sliding_pair(step), goals)
        watched.goals(step, _sliding_pair(step), goals)
    assert speed_only.events == []  # never slower than the speed threshold
    first = watched.policy.progress_window + watched.policy.patience - 1
    assert sorted(watched.events)[:2] == [(first, 0), (first, 1)]


def test_watching_progress_leaves_a_blocked_agent_that_gets_closer_alone():
    from swarmpc.simulation.deadlock import DeadlockPolicy

    resolver = DeadlockResolver(2, 2, DeadlockPolicy(progress_window=20))
    goals = np.array([[1.0, 0.0, 0, 0], [-1.0, 0.0, 0, 0]])
    for step in range(80):
        # agent 0 edges round agent 1 at 0.1 m/s, 0.04 m/s of it towards its goal: slow progress
        states = np.array([[-1.5 + 0.004 * step, 0.0, 0.1, 0.0], [-1.0, 0.0, 0.0, 0.0]])
        resolver.goals(step, states, goals)
    assert resolver.events == []


def test_an_agent_near_a_free_goal_is_never_detoured_but_one_near_an_occupied_goal_is():
    # agent 0 crawls 0.25 m from its goal past agent 1, parked 0.43 m (inf-norm) from that goal
    goals = np.array([[0.25, 0.0, 0, 0], [0.25, 0.43, 0, 0]])
    states = np.array([[0.0, 0.0, 0.01, 0.0], [0.25, 0.43, 0.0, 0.0]])
    resolver = DeadlockResolver(2, 2, clearance=0.35)
    assert resolver.blocked(states[:, :2], goals[:, :2])[0]  # near its corridor, within the margin
    assert resolver.goal_free(states[:, :2], goals[:, :2])[0]
    for step in range(30):
        resolver.goals(step, states, goals)
    assert resolver.events == []
    # the same agent with agent 1 sitting 0.3 m from its goal: the goal cannot be held, detour
    occupied = states.copy()
    occupied[1, 1] = 0.3
    crowded = DeadlockResolver(2, 2, clearance=0.35)
    assert not crowded.goal_free(occupied[:, :2], goals[:, :2])[0]
    for step in range(30):
        crowded.goals(step, occupied, goals)
    assert (crowded.policy.patience - 1, 0) in crowded.events


def test_a_head_on_pair_at_rest_short_of_free_goals_is_detoured_once_patience_runs_out():
    # spread 3D, M = 128, seed 0: two agents 0.85 m short of their goals, each in the other's
    # corridor, both goals free, at rest for good (spared by the free-goal rule)
    states = np.array([[-3.59, 0.73, 1.17, 0, 0, 0], [-3.49, 0.37, 1.37, 0, 0, 0]])
    goals = np.array([[-3.59, -0.13, 1.18, 0, 0, 0], [-3.48, 1.22, 1.37, 0, 0, 0]])
    resolver = DeadlockResolver(2, 3, clearance=0.35)
    assert resolver.blocked(states[:, :3], goals[:, :3]).all()
    assert resolver.goal_free(states[:, :3], goals[:, :3]).all()
    patience = resolver.policy.free_goal_patience
    for step in range(patience + resolver.policy.patience + 1):
        detoured = resolver.goals(step, states, goals)
        if step < patience:
            assert np.array_equal(detoured, goals), step  # spared while it may still get going
    assert {agent for _, agent in resolver.events} == {0, 1}
    # steps 0 … patience - 1 are spared, the next is the first of ``policy.patience`` stalled steps
    assert min(step for step, _ in resolver.events) == patience + resolver.policy.patience - 1
    assert not np.allclose(detoured[:, :3], goals[:, :3])
    # without the patience the exemption holds for ever; a pair that moves again resets it
    forever = DeadlockResolver(2, 3, clearance=0.35, policy=DeadlockPolicy(free_goal_patience=None))
    restarted = DeadlockResolver(2, 3, clearance=0.35)
    moving = states.copy()
    moving[:, 3] = 0.1
    for step in range(3 * patience):
        forever.goals(step, states, goals)
        restarted.goals(step, moving if step % patience == patience - 1 else states, goals)
    assert forever.events == [] and restarted.events == []


def _knotted_pair() -> tuple[np.ndarray, np.ndarray]:
    """Two agents in 3D, each sitting 0.25 m from the other's goal, side by side near the floor."""
    states = np.array([[0.0, 0.0, 0.4, 0.01, 0, 0], [0.0, 0.36, 0.4, -0.01, 0, 0]])
    goals = np.array([[0.0, 0.6, 0.4, 0, 0, 0], [0.0, -0.25, 0.4, 0, 0, 0]])
    return states, goals


def test_a_knot_lifts_one_member_out_of_its_layer_while_the_other_waits():
    states, goals = _knotted_pair()
    bounds = (np.array([-1.5, -1.5, 0.2]), np.array([1.5, 1.5, 2.2]))
    resolver = DeadlockResolver(2, 3, clearance=0.35, bounds=bounds)
    assert resolver.knots(states[:, :3], goals[:, :3], np.ones(2, bool), np.ones(2, bool))
    patience = resolver.policy.patience
    for step in range(patience):
        out = resolver.goals(step, states, goals)
    assert resolver.events == [(patience - 1, 0)]  # one member only, the lowest index
    # agent 0 rises (the floor is 0.2 m below it) and heads over its own goal
    assert out[0, 2] == pytest.approx(0.4 + resolver.policy.lift)
    assert np.allclose(out[0, :2], goals[0, :2]) and np.array_equal(out[1], goals[1])
    for step in range(patience, resolver.policy.lift_hold - 1):
        resolver.goals(step, states, goals)
    assert len(resolver.events) == 1  # agent 1 waits for its goal to clear, no detour of its own
    # the right-hand rule (2D, or no workspace given) turns both members instead
    plain = DeadlockResolver(2, 3, clearance=0.35)
    for step in range(patience):
        plain.goals(step, states, goals)
    assert sorted(plain.events) == [(patience - 1, 0), (patience - 1, 1)]


def test_a_knot_near_the_ceiling_lifts_downwards_and_a_second_knot_lifts_the_other_member():
    states, goals = _knotted_pair()
    states[:, 2] = goals[:, 2] = 2.0
    bounds = (np.array([-1.5, -1.5, 0.2]), np.array([1.5, 1.5, 2.2]))
    resolver = DeadlockResolver(2, 3, clearance=0.35, bounds=bounds)
    lift_hold = resolver.policy.lift_hold
    for step in range(lift_hold + 2 * resolver.policy.patience):
        out = resolver.goals(step, states, goals)
        if step == resolver.policy.patience - 1:
            assert out[0, 2] == pytest.approx(2.0 - resolver.policy.lift)
    assert [agent for _, agent in resolver.events] == [0, 1]


def test_a_lift_ends_as_soon_as_the_lifted_members_goal_is_free_and_its_way_clear():
    states, goals = _knotted_pair()
    bounds = (np.array([-1.5, -1.5, 0.2]), np.array([1.5, 1.5, 2.2]))
    early = DeadlockResolver(2, 3, clearance=0.35, bounds=bounds)
    held = DeadlockResolver(2, 3, clearance=0.35, bounds=bounds, policy=DeadlockPolicy(release_lifts=False))
    patience = early.policy.patience
    for step in range(patience):
        early.goals(step, states, goals)
        held.goals(step, states, goals)
    assert early.events == held.events == [(patience - 1, 0)]
    # agent 0 is over its goal, but agent 1 still sits under it: the lift goes on
    risen = states.copy()
    risen[0, :3] = [0.0, 0.5, 0.9]
    assert early.goals(patience, risen, goals)[0, 2] == pytest.approx(0.9)
    # agent 1 has slid into its own slot: agent 0's goal is free and the way down clear
    parted = risen.copy()
    parted[1, :3] = goals[1, :3]
    assert np.array_equal(early.goals(patience + 1, parted, goals), goals)
    assert held.goals(patience + 1, parted, goals)[0, 2] == pytest.approx(0.9)


def test_a_knot_whose_members_slide_without_getting_closer_is_untied_after_knot_patience():
    states, goals = _knotted_pair()
    states[:, 3] = [0.2, -0.2]  # moving, never slow: the stall rule alone never fires
    bounds = (np.array([-1.5, -1.5, 0.2]), np.array([1.5, 1.5, 2.2]))
    knot_patience = 4
    resolver = DeadlockResolver(2, 3, clearance=0.35, bounds=bounds, policy=DeadlockPolicy(knot_patience=knot_patience))
    waiting = DeadlockResolver(2, 3, clearance=0.35, bounds=bounds, policy=DeadlockPolicy(knot_patience=None))
    for step in range(3 * knot_patience):
        resolver.goals(step, states, goals)
        waiting.goals(step, states, goals)
    assert resolver.events == [(knot_patience, 0)] and waiting.events == []


def test_a_knot_whose_members_flow_past_each_other_is_left_alone_though_one_is_pushed_back():
    states, goals = _knotted_pair()
    states[:, 3] = [0.2, -0.2]
    bounds = (np.array([-1.5, -1.5, 0.2]), np.array([1.5, 1.5, 2.2]))
    resolver = DeadlockResolver(2, 3, clearance=0.35, bounds=bounds)
    knot_patience = resolver.policy.knot_patience
    assert knot_patience is not None
    for step in range(knot_patience + 5):
        assert resolver.knots(states[:, :3], goals[:, :3], np.ones(2, bool), np.ones(2, bool))
        resolver.goals(step, states, goals)
        states[0, 1] += 0.012  # agent 0 gets on towards its goal
        states[1, 1] += 0.001  # and pushes agent 1 back from its own
    assert resolver.events == []


def test_the_member_of_a_knot_that_made_no_progress_longest_is_the_one_lifted():
    states, goals = _knotted_pair()
    states[:, 3] = [0.2, -0.2]
    bounds = (np.array([-1.5, -1.5, 0.2]), np.array([1.5, 1.5, 2.2]))
    resolver = DeadlockResolver(2, 3, clearance=0.35, bounds=bounds, policy=DeadlockPolicy(knot_patience=4))
    for step in range(8):
        resolver.goals(step, states, goals)
        if step >= 2:  # agent 0 creeps towards its goal, still on agent 1's; agent 1 stays put
            states[0, 1] += 0.003
    assert resolver.events == [(4, 1)]


def test_a_neighbour_parked_beside_a_knots_goal_does_not_hide_the_knot():
    states, goals = _knotted_pair()
    # a third agent settled in its own slot, nearer agent 0's goal than agent 1 is
    parked = np.array([[0.0, 0.75, 0.6, 0, 0, 0]])
    states, goals = np.vstack([states, parked]), np.vstack([goals, parked])
    bounds = (np.array([-1.5, -1.5, 0.2]), np.array([1.5, 1.5, 2.2]))
    resolver = DeadlockResolver(3, 3, clearance=0.35, bounds=bounds)
    gaps = resolver._goal_gaps(states[:, :3], goals[:, :3], resolver.clearance + resolver.policy.corridor_margin)
    assert gaps[0].argmin() == 2  # the parked agent is the one nearest agent 0's goal
    unsettled = np.array([True, True, False])
    [cycle] = resolver.knots(states[:, :3], goals[:, :3], unsettled, np.array([True, False, False]))
    assert sorted(cycle.tolist()) == [0, 1]


def test_a_knot_boxed_in_from_above_steps_out_sideways():
    states, goals = _knotted_pair()
    # agents parked 0.45 m over the pair's layer (the floor 0.2 m under it): no way over or under
    parked = np.array([[0.0, y, 0.85, 0, 0, 0] for y in (-0.3, 0.0, 0.3, 0.6)])
    states, goals = np.vstack([states, parked]), np.vstack([goals, parked])
    bounds = (np.array([-1.5, -1.5, 0.2]), np.array([1.5, 1.5, 2.2]))
    resolver = DeadlockResolver(len(states), 3, clearance=0.35, bounds=bounds)
    for step in range(resolver.policy.patience):
        out = resolver.goals(step, states, goals)
    assert resolver.events == [(resolver.policy.patience - 1, 0)]
    # beside its goal, across the swap's axis, in the layer
    assert abs(out[0, 0]) == pytest.approx(resolver.policy.lift)
    assert out[0, 1] == pytest.approx(goals[0, 1]) and out[0, 2] == pytest.approx(0.4)
    # without side steps the member climbs into the parked agents' layer as before
    upward = DeadlockResolver(len(states), 3, clearance=0.35, bounds=bounds,
                              policy=DeadlockPolicy(side_steps=False))
    for step in range(upward.policy.patience):
        out = upward.goals(step, states, goals)
    assert out[0, 2] == pytest.approx(0.4 + upward.policy.lift)


def test_path_room_measures_the_gap_to_the_nearest_agent_in_clearances():
    resolver = DeadlockResolver(2, 3, clearance=np.array([0.3, 0.3, 0.6]))
    start, end = np.zeros(3), np.array([1.0, 0.0, 0.0])
    others = np.array([[0.5, 0.6, 0.0], [2.0, 0.0, 0.0]])
    assert resolver._path_room(start, end, others) == pytest.approx(2.0)  # 0.6 m across in y, 0.3 per clearance
    assert resolver._path_room(start, end, np.array([[0.5, 0.0, 0.3]])) == pytest.approx(0.5)


def _swap(name: str, lower: list[float], upper: list[float], first: list[float], second: list[float],
          max_steps: int):
    """Two drones swap places (each starts on the other's goal) in a box workspace."""
    from swarmpc.config import scenario_from_dict

    return scenario_from_dict({
        "name": name, "dim": 3, "dt": 0.1, "horizon": 10, "delta": 0.3,
        "weights": {"Q": 0.1, "R": 1.0, "Qf": 1.0}, "limits": {"accel": 1.0},
        "solver": {"method": "centralized"},
        "workspace": {"lower": lower, "upper": upper},
        "agents": [{"start": first, "goal": second}, {"start": second, "goal": first}],
        "stop": {"goal_tolerance": 0.1, "max_steps": max_steps},
    })


def _corridor_swap(max_steps: int):
    """A swap in a 0.2 m wide corridor: the drones can pass only over or under each other."""
    return _swap("corridor-swap", [-0.1, -1.0, 0.2], [0.1, 1.0, 1.6], [0.0, -0.2, 0.4], [0.0, 0.2, 0.4],
                 max_steps)


@pytest.mark.loop
def test_a_swap_in_a_corridor_is_untied_by_a_lift_and_not_by_turning_right(tmp_path):
    scn = _corridor_swap(300)
    summary, arrays = load_folder(write_run(simulate(scn), tmp_path / "lift"))
    states = arrays["states"]
    assert summary["all_reached"] and summary["steps"] < 200
    collisions, ratio = recount_collisions(states, arrays["delta"])
    assert collisions == 0 and ratio >= 1.0
    assert states[:, :, 2].max() > 0.4 + 0.3  # one of them went over the other
    # the right-hand rule alone turns both in the corridor's plane, and they never pass
    turning = scn.with_updates(**{"deadlock.untie_knots": False})
    summary = load_folder(write_run(simulate(turning), tmp_path / "turn"))[0]
    assert not summary["all_reached"] and summary["deadlocks"] >= 10


@pytest.mark.loop
def test_a_swap_under_a_low_ceiling_is_untied_by_a_side_step(tmp_path):
    # 0.4 m between floor and ceiling: no room to pass over or under, only beside
    scn = _swap("low-ceiling-swap", [-1.0, -1.0, 0.2], [1.0, 1.0, 0.6], [-0.2, 0.0, 0.4], [0.2, 0.0, 0.4], 300)
    summary, arrays = load_folder(write_run(simulate(scn), tmp_path / "side"))
    states = arrays["states"]
    assert summary["all_reached"] and summary["steps"] < 250
    collisions, ratio = recount_collisions(states, arrays["delta"])
    assert collisions == 0 and ratio >= 1.0
    assert np.abs(states[:, :, 1]).max() > 0.3  # one of them went round the other in the layer
    # lifting only: the 0.2 m to the ceiling is not enough to pass, and the swap is never made
    lifting = scn.with_updates(**{"deadlock.side_steps": False})
    summary = load_folder(write_run(simulate(lifting), tmp_path / "lift"))[0]
    assert not summary["all_reached"] and summary["deadlocks"] >= 4


def test_keep_right_turns_blocked_goals_right_from_the_first_step_and_spares_agents_near_their_goal():
    goals = np.array([[3.0, 0.0, 0, 0], [-3.0, 0.0, 0, 0], [0.5, 5.0, 0, 0]])
    # agents 0 and 1 head at each other, moving (not stalled); agent 2 is 0.5 m from its goal
    states = np.array([[-0.4, 0.0, 0.5, 0.0], [0.4, 0.0, -0.5, 0.0], [0.0, 5.0, 0.0, 0.0]])
    policy = DeadlockPolicy(keep_right_deg=30.0)
    out = DeadlockResolver(3, 2, policy).goals(0, states, goals)
    for i in (0, 1):
        offset, true = out[i, :2] - states[i, :2], goals[i, :2] - states[i, :2]
        assert np.linalg.norm(offset) == pytest.approx(np.linalg.norm(true))
        # turned clockwise by 30 degrees: the cross product true x offset is negative
        cross = true[0] * offset[1] - true[1] * offset[0]
        cos = offset @ true / np.linalg.norm(true) ** 2
        assert cross < 0 and cos == pytest.approx(np.cos(np.radians(30.0)))
        assert np.all(out[i, 2:] == 0.0)
    assert np.array_equal(out[2], goals[2])
    # off and the same states: the true goals, and nobody detoured
    plain = DeadlockResolver(3, 2, DeadlockPolicy(keep_right_deg=0.0)).goals(0, states, goals)
    assert np.array_equal(plain, goals)
    # the default: on at 20 degrees in the plane, off in 3D
    assert DeadlockResolver(3, 2).keep_right_deg == 20.0 and DeadlockResolver(3, 3).keep_right_deg == 0.0
    turned = DeadlockResolver(3, 2).goals(0, states, goals)
    offset, true = turned[0, :2] - states[0, :2], goals[0, :2] - states[0, :2]
    assert offset @ true / np.linalg.norm(true) ** 2 == pytest.approx(np.cos(np.radians(20.0)))
    # agent 1 settled at its goal in agent 0's way: agent 0 keeps its goal (and agent 1 its own)
    settled = goals.copy()
    settled[1, :2] = [0.4, 0.0]
    out = DeadlockResolver(3, 2, policy).goals(0, states, settled)
    assert np.array_equal(out[0], settled[0]) and np.array_equal(out[1], settled[1])
    # the same pair far apart is not blocked: true goals even with the rule on
    apart = states.copy()
    apart[:2, 0] = [-2.5, 2.5]
    assert np.array_equal(DeadlockResolver(3, 2, policy).goals(0, apart, goals), goals)
