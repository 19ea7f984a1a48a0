"""Consensus ADMM: one step against the centralised optimum, the executor contract, closed loops."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from conftest import dynamics_error, load_folder, recount_collisions, run_cli
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.geometry import point_box_distance
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.guessing import GuessProvider
from swarmpc.simulation.loop import simulate
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver
from swarmpc.solvers.centralized import CentralizedSolver
from swarmpc.solvers.executors import SerialExecutor, ThreadExecutor


def plan_cost(plan, goals, s: OCPSettings) -> float:
    total = 0.0
    for states, inputs, goal in zip(plan.states, plan.inputs, goals, strict=True):
        err = states - goal
        total += np.einsum("ki,ij,kj->", err[:-1], s.Q, err[:-1]) + np.einsum("ki,ij,kj->", inputs, s.R, inputs)
        total += err[-1] @ s.Qf @ err[-1]
    return float(total)


def approach_state(name: str, steps: int = 20):
    """Agents on their way to the centre, where the collision constraints become active."""
    scn = builtin_scenario(name).with_updates(**{"solver.method": "centralized", "stop.max_steps": steps})
    return scn, simulate(scn).states[-1]


@pytest.mark.parametrize("relaxation", [1.0, 1.6])
@pytest.mark.parametrize("name", ["paper-2d", "paper-3d"])
def test_one_step_matches_centralised(name, relaxation):
    scn, states = approach_state(name)
    s = OCPSettings.from_scenario(scn)
    goals = scn.goal_states()
    guess = GuessProvider(scn, s, "straight").guesses(states, goals, None)
    central = CentralizedSolver(s, scn.num_agents, scn.delta_vector).plan(states, goals, guess)
    # the paper's stopping rule (every block, both residuals; the default): consensus on the
    # global optimum
    config = ADMMConfig(max_iter=200, relaxation=relaxation)
    admm = ADMMSolver(s, scn.num_agents, scn.delta_vector, config).plan(states, goals, guess)
    assert central.failures == 0 and admm.failures == 0 and not admm.repaired
    assert admm.primal_residuals[-1] <= 1e-3 and admm.dual_residuals[-1] <= 1e-3
    # every constraint, recomputed from the agents' own plans
    d, first = s.dim, s.first_constrained_step
    for i in range(scn.num_agents):
        rollout = admm.states[i, 0]
        for k in range(s.horizon):
            rollout = np.concatenate([rollout[:d] + s.dt * rollout[d:], rollout[d:] + s.dt * admm.inputs[i, k]])
            assert np.allclose(rollout, admm.states[i, k + 1], atol=1e-8)
        for j in range(i + 1, scn.num_agents):
            for k in range(first, s.horizon + 1):
                gap = point_box_distance(admm.states[i, k, :d] - admm.states[j, k, :d], scn.delta_vector)
                assert gap >= s.d_min - 5e-3
    central_cost = plan_cost(central, goals, s)
    assert plan_cost(admm, goals, s) == pytest.approx(central_cost, rel=0.01)
    assert admm.max_slack == 0.0


@pytest.mark.parametrize("mode", ["never", "always", "stable"])
def test_new_step_carries_only_consistent_multipliers(mode):
    """A new MPC step starts from zero multipliers ("never"), the shifted ones (the paper's
    "always"), or ("stable", the default) those of blocks whose coupling is unchanged, decided
    alike by every holder of a block so that each block's multipliers still sum to zero."""
    scn, states = approach_state("paper-2d")
    s = OCPSettings.from_scenario(scn)
    goals = scn.goal_states()
    guess = GuessProvider(scn, s, "straight").guesses(states, goals, None)
    executor = SerialExecutor()
    solver = ADMMSolver(s, scn.num_agents, scn.delta_vector, ADMMConfig(max_iter=5, carry_multipliers=mode),
                        executor)
    solver.plan(states, goals, guess)
    agents = executor._agents

    def own_multiplier(i: int) -> float:
        gamma = agents[i].multipliers.own
        return 0.0 if gamma is None else float(np.abs(gamma).max())

    coupled = [i for i in agents if own_multiplier(i) > 0.0]
    assert coupled  # iterations after the first updated the multipliers
    solver.config = ADMMConfig(max_iter=1, carry_multipliers=mode)  # only the step's first iteration
    if mode == "stable":
        # agent 0 decoupled from everyone: its block restarts for every holder; the others keep theirs
        carried = solver.carryover
        solver.carryover = replace(carried, neighbours=((9,), *carried.neighbours[1:]))
    solver.plan(states, goals, guess)
    for i in coupled:
        carried = own_multiplier(i) > 0.0
        assert carried == (mode == "always" or (mode == "stable" and i != 0))
        if mode == "stable":
            assert 0 not in agents[i].multipliers.copies


@pytest.mark.parametrize("relaxation", [1.0, 1.6])
def test_each_blocks_multipliers_sum_to_zero_within_a_step(relaxation):
    """The z-update is the weighted average of the (relaxed) answers, so the multiplier updates
    of every block, the owner's (weighted) and its holders', cancel: ADMM's consensus invariant."""
    scn, states = approach_state("paper-2d")
    s = OCPSettings.from_scenario(scn)
    guess = GuessProvider(scn, s, "straight").guesses(states, scn.goal_states(), None)
    executor = SerialExecutor()
    config = ADMMConfig(max_iter=6, relaxation=relaxation, carry_multipliers="never", repair=False)
    ADMMSolver(s, scn.num_agents, scn.delta_vector, config, executor).plan(states, scn.goal_states(), guess)
    agents = executor._agents
    checked = 0
    for j, owner in agents.items():
        if owner.multipliers.own is None:
            continue
        held = [agent.multipliers.copies[j] for agent in agents.values() if j in agent.multipliers.copies]
        assert held and np.abs(owner.multipliers.own).max() > 1e-6
        assert np.allclose(owner.multipliers.own + sum(held), 0.0, atol=1e-9)
        checked += 1
    assert checked >= 2


def test_executors_give_identical_plans():
    scn, states = approach_state("paper-2d", steps=15)
    s = OCPSettings.from_scenario(scn)
    goals = scn.goal_states()
    guess = GuessProvider(scn, s, "straight").guesses(states, goals, None)
    plans = []
    for executor in (SerialExecutor(), ThreadExecutor(workers=2)):
        solver = ADMMSolver(s, scn.num_agents, scn.delta_vector, ADMMConfig(), executor)
        first = solver.plan(states, goals, guess)
        second = solver.plan(first.states[:, 1], goals, guess)  # warm-started step
        plans.append((first, second))
        solver.close()
    for a, b in zip(plans[0], plans[1], strict=True):
        assert a.admm_iterations == b.admm_iterations
        assert np.array_equal(a.states, b.states) and np.array_equal(a.inputs, b.inputs)
        assert a.primal_residuals == b.primal_residuals


@pytest.fixture(scope="module", params=[("paper-2d", "hard"), ("paper-3d", "hard"), ("paper-2d", "soft"),
                                        ("paper-3d", "soft")], ids=lambda p: "-".join(p))
def admm_run(request, tmp_path_factory):
    name, collision = request.param
    out = tmp_path_factory.mktemp("admm") / f"{name}-{collision}"
    done = run_cli("run", name, "--collision", collision, "--out", str(out), "--quiet")
    assert done.returncode == 0, done.stderr
    return collision, out


@pytest.mark.loop
def test_admm_closed_loop(admm_run):
    collision, out = admm_run
    summary, arrays = load_folder(out)
    states, goals = arrays["states"], arrays["goals"]
    d = states.shape[2] // 2
    assert summary["method"] == "admm"
    assert np.all(np.linalg.norm(states[-1, :, :d] - goals[:, :d], axis=1) <= 0.05 + 1e-9)
    assert dynamics_error(states, arrays["inputs"], float(arrays["dt"])) < 1e-9
    collisions, _ = recount_collisions(states, arrays["delta"])
    assert summary["collisions"] == collisions
    if collision == "hard":
        assert collisions == 0
    else:
        assert summary["max_slack"] >= 0.0 and "max_slack" in summary
    iterations = summary["admm_iterations"]
    assert iterations["median"] >= 1 and iterations["max"] <= 100
    with np.load(out / "admm.npz") as admm:
        assert admm["primal"].shape[0] == summary["steps"]
        assert np.all(admm["iterations"] >= 1)
        copies = admm["copies"]
        m = summary["num_agents"]
        assert copies.shape == (summary["steps"], m) and copies.min() >= 0 and copies.max() <= m - 1
        assert np.all(copies.sum(axis=1) % 2 == 0)  # coupling is symmetric: a copy held each way
        assert copies.max() >= 1  # the swap meets in the middle, where the agents couple


def test_components_label_connected_agents_alike():
    from swarmpc.solvers.admm import components

    labels = components([(1,), (0, 2), (1,), (), (5,), (4,)])
    assert labels[0] == labels[1] == labels[2] and labels[4] == labels[5]
    assert len({labels[0], labels[3], labels[4]}) == 3


class FailingRepairExecutor(SerialExecutor):
    """Agent ``failing`` fails every repair solve and flies a fallback nobody planned against:
    coasting straight on (a replayed previous plan can go anywhere the others no longer expect)."""

    def __init__(self, failing: int, settings: OCPSettings) -> None:
        super().__init__()
        self.failing = failing
        self.settings = settings

    def solve(self, requests):
        from swarmpc.model.dynamics import DoubleIntegrator
        from swarmpc.solvers.admm import LocalResult

        out = []
        for r in requests:
            if r.agent == self.failing and r.neighbour_plans is not None:
                s = self.settings
                inputs = np.zeros((s.horizon, s.dim))
                states = DoubleIntegrator(s.dim, s.dt, s.discretization).rollout(r.state, inputs)
                own = states[self.settings.first_constrained_step:, : self.settings.dim].T.copy()
                out.append(LocalResult(agent=r.agent, own=own, copies=r.z_neighbours.copy(), states=states,
                                       inputs=inputs, success=False, fallback=True, solve_time=0.0,
                                       max_slack=0.0, cost=0.0))
            else:
                out.extend(super().solve([r]))
        return out


def test_neighbours_replan_around_a_fallback_they_did_not_see():
    """Two agents head-on at speed, ADMM cut short so the repair runs; agent 0 fails in the repair
    (after agent 1 was repaired against its plan) and coasts straight on. Agent 1 must end up clear
    of that fallback, not of the plan agent 0 no longer flies."""
    # the paper's weights: one ADMM iteration leaves this meeting without consensus
    scn = builtin_scenario("circle", agents=2, radius=2.0).with_updates(
        **{"limits.accel": 1.0, "weights.Q": 0.1, "weights.Qf": 1.0})
    s = OCPSettings.from_scenario(scn)
    states = np.array([[-0.6, 0.02, 0.6, 0.0], [0.6, -0.02, -0.6, 0.0]])
    goals = scn.goal_states()
    guess = GuessProvider(scn, s, "straight").guesses(states, goals, None)
    executor = FailingRepairExecutor(0, s)
    solver = ADMMSolver(s, 2, scn.delta_vector, ADMMConfig(max_iter=1), executor)
    plan = solver.plan(states, goals, guess)
    assert plan.repaired and plan.fallback[0] and not plan.fallback[1]
    k = s.first_constrained_step
    gaps = np.max(np.abs(plan.states[0, k:, :2] - plan.states[1, k:, :2]), axis=1)
    assert gaps.min() >= scn.delta_vector[0] + s.d_min - 1e-3


@pytest.mark.parametrize("name", ["paper-2d", "paper-3d"])
def test_a_loose_tolerance_still_stops_only_on_plans_kept_apart(name):
    """Consensus within tol (an RMS) bounds how far copies sit from the flown plans on average,
    not at every step: at tol = 10 cm the residual test alone stops on own plans that overlap
    (by 9 cm and more; at 5 cm the overlap depends on the last bits of the machine's arithmetic).
    The stop's check on the coupled pairs' own plans iterates on (or repairs) until they keep
    d_min / 2, recomputed here from the plans."""
    scn, states = approach_state(name, 26)
    s = OCPSettings.from_scenario(scn)
    goals = scn.goal_states()
    guess = GuessProvider(scn, s, "straight").guesses(states, goals, None)

    class ResidualsOnly(ADMMSolver):
        """The stop on the residual test alone."""

        def coupled_plans_clear(self, results, neighbours) -> bool:
            return True

    def closest(check: bool) -> float:
        solver = (ADMMSolver if check else ResidualsOnly)(s, 4, scn.delta_vector, ADMMConfig(tol=0.1))
        plan = solver.plan(states, goals, guess)
        positions = plan.states[:, s.first_constrained_step:, : s.dim]
        return min(point_box_distance(p - q, scn.delta_vector)
                   for i in range(4) for j in range(i + 1, 4) for p, q in zip(positions[i], positions[j], strict=True))

    assert closest(check=False) < 0.0  # inside each other's delta box
    assert closest(check=True) >= 0.5 * s.d_min - 1e-6


def test_the_dual_tolerance_is_its_own_and_defaults_to_the_primal_one():
    from swarmpc.solvers.admm.consensus import consensus_met

    paper, loose = ADMMConfig(tol=1e-3), ADMMConfig(tol=1e-3, dual_tol=1e-2)
    assert paper.dual_tol is None
    assert not consensus_met(5e-4, 5e-3, paper.rho, paper)  # the dual residual holds the paper's stop
    assert consensus_met(5e-4, 5e-3, loose.rho, loose)
    assert consensus_met(5e-4, 5e-4, paper.rho, paper)
    assert not consensus_met(2e-3, 1e-6, loose.rho, loose)  # never without the primal
    assert consensus_met(5e-4, 4e-2, 4 * loose.rho, loose)  # compared at the step's starting rho
    with pytest.raises(ValueError, match="dual_tol"):
        ADMMConfig(dual_tol=0.0)


def test_a_looser_dual_tolerance_stops_a_crossing_step_sooner_on_plans_kept_apart():
    """paper-2d about to cross: the step stops in fewer iterations when z may still move by tol per
    iteration, and the coupled agents' plans keep d_min / 2, recomputed here."""
    scn, states = approach_state("paper-2d", 22)
    s = OCPSettings.from_scenario(scn)
    goals = scn.goal_states()
    guess = GuessProvider(scn, s, "straight").guesses(states, goals, None)

    def step(config: ADMMConfig):
        return ADMMSolver(s, 4, scn.delta_vector, config).plan(states, goals, guess)

    paper, loose = step(ADMMConfig()), step(ADMMConfig(dual_tol=ADMMConfig().rho * ADMMConfig().tol))
    assert loose.admm_iterations < paper.admm_iterations
    positions = loose.states[:, s.first_constrained_step:, : s.dim]
    closest = min(point_box_distance(p - q, scn.delta_vector)
                  for i in range(4) for j in range(i + 1, 4) for p, q in zip(positions[i], positions[j], strict=True))
    assert closest >= 0.5 * s.d_min - 1e-6
