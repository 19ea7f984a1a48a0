"""The local solves the QP local step hands to IPOPT, counted per step and per run.

``steps.npz`` ``local_fallbacks`` (one count per step) and ``summary.json`` ``local_fallbacks``
(their sum) record how often the QP path (``solver.local: qp``) failed a call that IPOPT then
answered; the IPOPT local step and centralised runs record 0. A QP backend that refuses every
solve makes the count visible, and it matches what the agents reported through the executor.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from swarmpc.config import Scenario
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.disturbance import planner_bodies
from swarmpc.simulation.loop import simulate
from swarmpc.simulation.results import write_run
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver, LocalAgentFactory
from swarmpc.solvers.executors import SerialExecutor
from swarmpc.solvers.qp_local import OSQPBackend, QPAnswer


def circle(local: str, method: str = "admm", steps: int = 6) -> Scenario:
    """The 2D antipodal swap of four agents, a few steps, with the given local step and method."""
    return builtin_scenario("circle", agents=4, dim=2).with_updates(
        **{"solver.method": method, "solver.local": local, "stop.max_steps": steps})


class RefusingBackend(OSQPBackend):
    """OSQP that reports every solve failed: every call of the QP path falls back to IPOPT."""

    def solve(self, x: np.ndarray, y: np.ndarray | None) -> QPAnswer:
        answer = super().solve(x, y)
        return QPAnswer(answer.x, answer.y, False, "refused", answer.iterations, answer.solver_time)


class TallyExecutor(SerialExecutor):
    """The serial executor, adding up the fallbacks the agents report in their answers."""

    def __init__(self) -> None:
        super().__init__()
        self.fallbacks = 0

    def solve(self, requests):  # type: ignore[no-untyped-def]
        results = super().solve(requests)
        self.fallbacks += sum(r.local_fallbacks for r in results)
        return results


def written(scn: Scenario, folder, **kwargs) -> tuple[dict, np.ndarray]:  # type: ignore[no-untyped-def]
    """Run ``scn``, write its folder; (summary.json, steps.npz ``local_fallbacks``)."""
    write_run(simulate(scn, **kwargs), folder)
    with np.load(folder / "steps.npz") as steps:
        counts = steps["local_fallbacks"]
    return json.loads((folder / "summary.json").read_text()), counts


def refused_run(scn: Scenario, folder) -> tuple[dict, np.ndarray, int]:  # type: ignore[no-untyped-def]
    """Run ``scn`` by ADMM whose QP path refuses every solve, write its folder; (summary.json,
    steps.npz ``local_fallbacks``, the hand-overs the agents reported through the executor)."""
    s, bodies = OCPSettings.from_scenario(scn), planner_bodies(scn)
    config = ADMMConfig.from_options(scn.solver, scn.collision)
    tally = TallyExecutor()
    agents = LocalAgentFactory.for_config(s, bodies, config, qp_backend=RefusingBackend)
    solver = ADMMSolver(s, scn.num_agents, bodies, config, tally, agents=agents)
    try:
        summary, counts = written(scn, folder, solver=solver)
    finally:
        solver.close()
        tally.close()
    return summary, counts, tally.fallbacks


@pytest.mark.parametrize(("local", "method"), [("qp", "admm"), ("ipopt", "admm"), ("ipopt", "centralized")])
def test_the_run_folder_holds_the_count_per_step_and_its_sum(tmp_path, local, method):
    summary, counts = written(circle(local, method), tmp_path / "run")
    assert counts.shape == (summary["steps"],) and counts.dtype.kind == "i"
    assert summary["local_fallbacks"] == int(counts.sum())
    if (local, method) != ("qp", "admm"):  # nothing to fall back from
        assert summary["local_fallbacks"] == 0 and not counts.any()


def test_a_refusing_qp_path_is_counted_in_every_step(tmp_path):
    scn = circle("qp")
    summary, counts, handed = refused_run(scn, tmp_path / "run")
    assert counts.shape == (6,) and np.all(counts > 0)  # every step solved something, on IPOPT
    assert summary["local_fallbacks"] == int(counts.sum()) == handed
    assert summary["solver_failures"] == 0  # IPOPT answered every call


def test_under_a_deadline_a_refusing_qp_path_hands_nothing_to_ipopt(tmp_path):
    """An IPOPT call does not fit a step's budget: with ``solver.deadline`` a failed QP call is a
    failed local step (the agent's fallback rules answer it), never an IPOPT solve."""
    scn = circle("qp").with_updates(**{"solver.deadline": 0.1})
    summary, counts, handed = refused_run(scn, tmp_path / "run")
    assert summary["local_fallbacks"] == 0 == handed and not counts.any()
    assert summary["solver_failures"] > 0  # the refused calls failed, and nothing else answered them
    assert summary["collisions"] == 0
