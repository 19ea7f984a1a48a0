"""One options seam: solvers come from a registry and are used through the MPCSolver protocol;
the ADMM, IPOPT, QP and executor settings are scenario sections whose values reach the objects
that use them; the closed loop takes its guess provider and deadlock resolver as parameters; and
whoever creates an executor closes it."""

from __future__ import annotations

import ast
import dataclasses
import json
import multiprocessing
import typing
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from conftest import cli_in_process
from swarmpc.config import (
    ADMMOptions,
    ExecutorConfig,
    IpoptOptions,
    QPOptions,
    ScenarioError,
    SolverConfig,
    default_local,
    load_scenario,
    scenario_from_dict,
    scenario_to_yaml,
)
from swarmpc.docgen import schema_fields
from swarmpc.formulation.ocp import IPOPT_OPTIONS, LOCAL_IPOPT_OPTIONS, OCPSettings, ipopt_options
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation import controller as controller_module
from swarmpc.simulation.controller import Controller
from swarmpc.simulation.deadlock import DeadlockResolver
from swarmpc.simulation.guessing import GuessProvider
from swarmpc.simulation.loop import simulate
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver
from swarmpc.solvers.centralized import CentralizedSolver
from swarmpc.solvers.executors import ProcessExecutor, SerialExecutor, ThreadExecutor
from swarmpc.solvers.footprint_admm import FootprintADMMOptions
from swarmpc.solvers.qp_local import QPLocalOptions
from swarmpc.solvers.registry import SOLVERS, SolverRegistry, build_solver

AGENTS = [{"start": [-1.0, 0.0], "goal": [1.0, 0.1]}, {"start": [1.0, 0.0], "goal": [-1.0, -0.1]}]
BASE = {"name": "seam", "dim": 2, "workspace": {"lower": [-3, -3], "upper": [3, 3]}, "agents": AGENTS}


def scenario(**sections: Any) -> Any:
    return scenario_from_dict({**BASE, **sections})


def from_yaml(tmp_path: Path, text: str) -> Any:
    """The scenario of ``BASE`` plus the YAML ``text``, read from a file as a user's would be."""
    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump(BASE, sort_keys=False) + text)
    return load_scenario(path)


# ------------------------------------------------------------------------------ the registry
def test_the_registry_has_exactly_the_methods_a_scenario_can_name():
    assert set(SOLVERS.methods) == set(typing.get_args(SolverConfig.model_fields["method"].annotation))


def test_the_registry_builds_each_method_and_refuses_an_unknown_one():
    scn = scenario()
    settings, bodies = OCPSettings.from_scenario(scn), scn.bodies
    assert isinstance(build_solver("admm", scn.solver, settings, bodies), ADMMSolver)
    assert isinstance(build_solver("centralized", scn.solver, settings, bodies), CentralizedSolver)
    with pytest.raises(ValueError, match=r"solver.method: unknown method 'gpu' \(registered: admm, centralized\)"):
        build_solver("gpu", scn.solver, settings, bodies)
    with pytest.raises(ValueError, match="bodies: expected"):
        build_solver("admm", scn.solver, settings, bodies[0])


def test_registering_returns_a_new_registry_and_the_controller_uses_the_one_it_is_given():
    seen: list[tuple[Any, ...]] = []

    class Recorder:
        def __init__(self, *args: Any) -> None:
            seen.append(args)
            self.inner = CentralizedSolver(args[1], len(args[2]), args[2])

        def plan(self, states: np.ndarray, goals: np.ndarray, guess: np.ndarray) -> Any:
            return self.inner.plan(states, goals, guess)

    mine = SOLVERS.register("centralized", Recorder)
    assert SOLVERS.builders["centralized"] is not Recorder and mine.builders["centralized"] is Recorder
    assert mine.methods == SOLVERS.methods
    scn = scenario(solver={"method": "centralized"})
    with Controller(scn, solvers=mine) as mpc:
        assert isinstance(mpc.solver, Recorder)
        mpc.step(scn.start_states())
    options, settings, bodies, executor = seen[0]
    assert options == scn.solver and settings.horizon == scn.horizon and executor is None
    assert np.array_equal(bodies, scn.bodies)
    with pytest.raises(ValueError, match="unknown method 'admm'"):
        Controller(scenario(), solvers=SolverRegistry())


def test_the_simulation_layer_imports_no_concrete_solver():
    for module in ("controller", "loop"):
        source = Path(controller_module.__file__).with_name(f"{module}.py").read_text()
        imported = {node.module for node in ast.walk(ast.parse(source)) if isinstance(node, ast.ImportFrom)}
        assert not {name for name in imported if name and (".admm" in name or "centralized" in name)}, module
        assert "a test may swap" not in source


# ------------------------------------------------------------------------------ solver.admm
def test_the_admm_section_defaults_are_the_admm_config_defaults():
    # every default but the local step's and the probe's: a scenario's is the QP step with the probe of
    # the agents' own optima, the solver object's the paper's algorithm (the reference NLP, no probe)
    assert ADMMConfig.from_options(SolverConfig(), "soft") == ADMMConfig(local="qp", independent_first=True)
    hard = ADMMConfig.from_options(SolverConfig(), "hard")
    assert (hard.coupling_margin, hard.closing_time) == (0.2, 0.1)


ADMM_SECTION = """\
solver:
  admm:
    stall_window: 7
    stall_rho_factor: 3.0
    rho_min: 0.5
    rho_max: 50.0
    carry_multipliers: never
    warm_start: false
    repair: false
    owner_weight: 2.5
    repair_rounds: 5
    dynamic_copies: true
    closing_time: 0.25
    deadline_repair: select
    repair_order: colour
    dual_tol: 0.02
    independent_first: false
"""


def test_every_admm_key_in_a_file_reaches_the_solver(tmp_path):
    scn = from_yaml(tmp_path, ADMM_SECTION)
    with Controller(scn) as mpc:
        config = mpc.solver.config
    assert (config.stall_window, config.stall_rho_factor, config.rho_bounds) == (7, 3.0, (0.5, 50.0))
    assert (config.carry_multipliers, config.warm_start, config.repair) == ("never", False, False)
    assert (config.owner_weight, config.dynamic_copies, config.closing_time) == (2.5, True, 0.25)
    assert (config.repair_rounds, config.deadline_repair, config.repair_order) == (5, "select", "colour")
    assert config.dual_tol == 0.02 and config.local == "ipopt"  # dynamic copies: the NLP, unless asked
    assert config.independent_first is False
    car_only = {"pair_copies"}  # the ADMM of a swarm with cars: test_pair_copies_in_a_file_reach_the_car_solver
    assert set(ADMMOptions.model_fields) - car_only == set(yaml.safe_load(ADMM_SECTION)["solver"]["admm"])


def test_the_local_step_left_out_is_the_qp_step_for_point_agents_and_the_nlp_with_cars(tmp_path):
    assert scenario().solver.local == "qp" == SolverConfig().local
    car = {"start": [0.0, 0.0, 0.0], "goal": [2.0, 0.0, 0.0], "model": "car"}
    mixed = {**BASE, "agents": [*AGENTS[:1], car], "weights": {"Qf": 10.0}}
    assert scenario_from_dict(mixed).solver.local == "ipopt"  # a car's QP step is slower than its NLP
    assert scenario_from_dict({**mixed, "solver": {"local": "qp"}}).solver.local == "qp"  # asked for: kept
    assert scenario_from_dict({**mixed, "solver": SolverConfig()}).solver.local == "ipopt"
    assert scenario_from_dict({**mixed, "solver": SolverConfig(local="qp")}).solver.local == "qp"
    assert scenario(solver={"admm": {"dynamic_copies": True}}).solver.local == "ipopt"  # the step that takes them
    cars_and_copies = {**mixed, "solver": {"admm": {"dynamic_copies": True}}}
    assert scenario_from_dict(cars_and_copies).solver.local == "ipopt"
    # one rule: ipopt when either needs it
    assert [default_local(cars, copies) for cars in (False, True) for copies in (False, True)] == \
        ["qp", "ipopt", "ipopt", "ipopt"]
    with pytest.raises(ScenarioError, match="dynamic_copies"):
        scenario(solver={"local": "qp", "admm": {"dynamic_copies": True}})
    written = from_yaml(tmp_path, "")  # a written scenario records the local step it resolved to
    assert "local: qp" in scenario_to_yaml(written)
    assert scenario_from_dict(yaml.safe_load(scenario_to_yaml(scenario_from_dict(mixed)))).solver.local == "ipopt"


def test_pair_copies_in_a_file_reach_the_car_solver():
    scn = builtin_scenario("parking").with_updates(**{"solver.method": "admm"})
    assert FootprintADMMOptions.from_options(scn.solver).pair_copies == "later"
    both = scn.with_updates(**{"solver.admm.pair_copies": "both"})
    assert FootprintADMMOptions.from_options(both.solver).pair_copies == "both"


def test_closing_time_follows_the_coupling_margin_unless_set():
    margin = scenario(solver={"coupling_margin": 0.3})
    assert ADMMConfig.from_options(margin.solver, "hard").closing_time == 0.0
    both = scenario(solver={"coupling_margin": 0.3, "admm": {"closing_time": 0.4}})
    config = ADMMConfig.from_options(both.solver, "hard")
    assert (config.coupling_margin, config.closing_time) == (0.3, 0.4)


# ------------------------------------------------------------------------------ solver.ipopt / solver.qp
def test_the_ipopt_defaults_are_the_shipped_option_dicts():
    assert IPOPT_OPTIONS == {"expand": True, "print_time": False, "ipopt.print_level": 0, "ipopt.sb": "yes",
                             "ipopt.max_iter": 300, "ipopt.tol": 1e-6, "ipopt.acceptable_tol": 1e-4,
                             "ipopt.mu_strategy": "adaptive"}
    assert LOCAL_IPOPT_OPTIONS == {**IPOPT_OPTIONS, "ipopt.mumps_scaling": 0, "ipopt.mumps_permuting_scaling": 0,
                                   "calc_lam_p": False}
    assert OCPSettings.from_scenario(scenario()).ipopt == IpoptOptions()


def test_the_ipopt_section_reaches_the_settings_and_the_options(tmp_path):
    scn = from_yaml(tmp_path, "solver:\n  ipopt: {max_iter: 40, tol: 1.0e-7, acceptable_tol: 1.0e-3, "
                              "mu_strategy: monotone, local_scaling: true}\n")
    with Controller(scn) as mpc:
        section = mpc.settings.ipopt
    central, local = ipopt_options(section), ipopt_options(section, local=True)
    assert (central["ipopt.max_iter"], central["ipopt.tol"], central["ipopt.acceptable_tol"]) == (40, 1e-7, 1e-3)
    assert central["ipopt.mu_strategy"] == "monotone"
    assert "ipopt.mumps_scaling" not in local and local["calc_lam_p"] is False


@pytest.mark.parametrize("method", ["centralized", "admm"])
def test_an_ipopt_iteration_cap_of_one_makes_the_solves_fail(method):
    """The cap reaches IPOPT itself: one iteration cannot solve a swap from a straight guess."""
    capped = scenario(solver={"method": method, "local": "ipopt", "initial_guess": "straight",
                              "ipopt": {"max_iter": 1}})
    free = scenario(solver={"method": method, "local": "ipopt", "initial_guess": "straight"})
    with Controller(capped) as mpc:
        mpc.step(capped.start_states())
        assert mpc.last_record.failures > 0
    with Controller(free) as mpc:
        mpc.step(free.start_states())
        assert mpc.last_record.failures == 0


def test_the_qp_section_mirrors_the_qp_options():
    assert set(QPOptions.model_fields) == {f.name for f in dataclasses.fields(QPLocalOptions)}
    assert QPLocalOptions.from_config(QPOptions()) == QPLocalOptions()


def test_the_qp_section_reaches_the_agents_qp_steps(tmp_path):
    scn = from_yaml(tmp_path, "solver:\n  local: qp\n  qp: {max_rounds: 2, margin: 2.0e-5, eps_abs: 1.0e-5, "
                              "speed_facets: 8, polish: false, repair_solver: piqp}\n")
    with Controller(scn) as mpc:
        agent = mpc.solver.executor._agents[0]
        options = agent.nlp.qp.options
    assert options == QPLocalOptions(max_rounds=2, margin=2e-5, eps_abs=1e-5, speed_facets=8, polish=False,
                                     repair_solver="piqp")


# ------------------------------------------------------------------------------ executor
def test_the_controller_makes_the_scenarios_executor_and_closes_it():
    scn = scenario(executor={"type": "process", "workers": 1})
    with Controller(scn) as mpc:
        assert isinstance(mpc.solver.executor, ProcessExecutor)
        workers = list(mpc.solver.executor._processes)
        assert len(workers) == 1 and workers[0].is_alive()
        mpc.step(scn.start_states())
    assert not workers[0].is_alive()
    assert not set(workers) & set(multiprocessing.active_children())


def test_an_executor_given_wins_over_the_section_and_stays_open():
    scn = scenario(executor={"type": "process", "workers": 1})
    given = ThreadExecutor(workers=3)
    with Controller(scn, executor=given) as mpc:
        assert mpc.solver.executor is given
        mpc.step(scn.start_states())
    assert given._agents, "the caller's executor was closed"
    given.close()


def test_a_serial_section_leaves_the_solver_its_own_executor():
    with Controller(scenario(executor={"type": "serial"})) as mpc:
        assert type(mpc.solver.executor) is SerialExecutor and mpc._made_executor is None
    with Controller(scenario(executor={"type": "thread", "workers": 3})) as mpc:
        assert isinstance(mpc.solver.executor, ThreadExecutor) and mpc.solver.executor._workers == 3


# ------------------------------------------------------------------------------ loop parameters
def test_simulate_takes_the_guess_provider_and_the_deadlock_resolver_class():
    made: list[str] = []

    class Guesser(GuessProvider):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            made.append("guesser")
            super().__init__(*args, **kwargs)

    class Resolver(DeadlockResolver):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            made.append("resolver")
            super().__init__(*args, **kwargs)

    scn = scenario(solver={"method": "centralized"}, stop={"max_steps": 2})
    simulate(scn, guess_provider=Guesser, deadlock_factory=Resolver)
    assert made == ["guesser", "resolver"]


# ------------------------------------------------------------------------------ the reference
def test_every_new_key_is_in_the_generated_reference():
    paths = {row.path for row in schema_fields()}
    for prefix, model in (("solver.admm.", ADMMOptions), ("solver.ipopt.", IpoptOptions),
                          ("solver.qp.", QPOptions), ("executor.", ExecutorConfig)):
        assert {prefix + name for name in model.model_fields} <= paths, prefix
    page = (Path(__file__).parents[1] / "docs" / "scenario-reference.md").read_text()
    assert "`solver.admm.stall_window`" in page and "`executor.workers`" in page


# ------------------------------------------------------------------------------ refusals
def run_in_process(*args: str) -> tuple[int, str]:
    """``swarmpc ARGS`` in this process: (exit status, stderr)."""
    code, stderr = cli_in_process(*args)
    return int(code or 0), stderr


BAD = {
    "solver.admm.rho_max": {"solver": {"admm": {"rho_min": 5.0, "rho_max": 1.0}}},
    "solver.admm.stall_rho_factor": {"solver": {"admm": {"stall_rho_factor": 1.0}}},
    "solver.admm.carry_multipliers": {"solver": {"admm": {"carry_multipliers": "sometimes"}}},
    "solver.admm.dynamic_copies": {"solver": {"local": "qp", "admm": {"dynamic_copies": True}}},
    "solver.admm.bogus": {"solver": {"admm": {"bogus": 1}}},
    "solver.ipopt.max_iter": {"solver": {"ipopt": {"max_iter": 0}}},
    "solver.ipopt.tol": {"solver": {"ipopt": {"tol": True}}},
    "solver.ipopt.mu_strategy": {"solver": {"ipopt": {"mu_strategy": "probing"}}},
    "solver.qp.eps_abs": {"solver": {"qp": {"eps_abs": 0}}},
    "solver.qp.speed_facets": {"solver": {"qp": {"speed_facets": 3}}},
    "solver.qp.repair_solver": {"solver": {"qp": {"repair_solver": "qpoases"}}},
    "executor.type": {"executor": {"type": "gpu"}},
    "executor.workers": {"executor": {"workers": 2}},
    "executor.address": {"executor": {"type": "process", "address": "auto"}},
}


@pytest.mark.parametrize("field", list(BAD))
def test_a_bad_value_is_one_line_naming_the_field_and_status_2(field, tmp_path):
    with pytest.raises(ScenarioError, match=rf"^{field}: "):
        scenario(**BAD[field])
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({**BASE, **BAD[field]}))
    out = tmp_path / "out"
    code, stderr = run_in_process("run", str(path), "--out", str(out), "--quiet", "--max-steps", "1")
    assert code == 2 and stderr.startswith(f"swarmpc: error: {field}: ") and stderr.count("\n") == 1, stderr
    assert not out.exists()


def test_a_parallel_executor_needs_admm():
    with pytest.raises(ScenarioError, match="^executor.type: process only applies to solver.method admm"):
        scenario(executor={"type": "process"}, solver={"method": "centralized"})


# ------------------------------------------------------------------------------ the command line wins
def run_folder(tmp_path: Path, executor: dict[str, Any], *args: str) -> tuple[int, str, dict[str, Any]]:
    tmp_path.mkdir(parents=True, exist_ok=True)
    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump({**BASE, "executor": executor}))
    out = tmp_path / "out"
    code, stderr = run_in_process("run", str(path), "--out", str(out), "--quiet", "--max-steps", "1", *args)
    summary = json.loads((out / "summary.json").read_text()) if code == 0 else {}
    saved = yaml.safe_load((out / "scenario.yaml").read_text()) if code == 0 else {}
    return code, stderr, {"summary": summary, "scenario": saved}


@pytest.mark.loop
def test_the_scenarios_executor_runs_unless_the_command_line_says_otherwise(tmp_path):
    code, stderr, run = run_folder(tmp_path / "a", {"type": "thread", "workers": 2})
    assert code == 0, stderr
    assert run["summary"]["executor"] == "thread" and run["scenario"]["executor"]["workers"] == 2
    code, stderr, run = run_folder(tmp_path / "b", {"type": "thread", "workers": 2}, "--executor", "serial")
    assert code == 0, stderr
    assert run["summary"]["executor"] == "serial" and run["scenario"]["executor"]["type"] == "serial"


@pytest.mark.parametrize(("executor", "args", "message"), [
    ({"type": "serial"}, ["--workers", "2"], "--workers: only with --executor process or ray"),
    ({"type": "thread"}, ["--address", "auto"], "--address: only with --executor ray"),
    ({"type": "process"}, ["--method", "centralized"], "executor.type: process only applies to solver.method admm"),
    ({"type": "serial"}, ["--method", "centralized", "--executor", "process"],
     "--executor: process only applies to solver.method admm"),
])
def test_command_line_executor_options_are_checked_against_the_section(executor, args, message, tmp_path):
    code, stderr, _ = run_folder(tmp_path, executor, *args)
    assert code == 2 and stderr.startswith(f"swarmpc: error: {message}") and stderr.count("\n") == 1, stderr
    assert not (tmp_path / "out").exists()


def test_a_ladder_type_handed_to_the_agents_factory_solves_every_local_problem():
    """Library-only knob: benchmarks record the local problems through a ladder subclass."""
    from swarmpc.scenarios import builtin_scenario
    from swarmpc.simulation.disturbance import planner_bodies
    from swarmpc.simulation.loop import simulate
    from swarmpc.solvers.admm import ADMMConfig, ADMMSolver, LocalAgentFactory, LocalSolverLadder

    calls: list[int] = []

    class Counting(LocalSolverLadder):
        def solve(self, *args: Any, **kwargs: Any) -> Any:
            calls.append(kwargs["copies"])
            return super().solve(*args, **kwargs)

    scn = builtin_scenario("paper-2d").with_updates(**{"stop.max_steps": 3, "solver.local": "ipopt"})
    settings = OCPSettings.from_scenario(scn)
    config = ADMMConfig.from_options(scn.solver, settings.collision)
    bodies = planner_bodies(scn)
    agents = LocalAgentFactory.for_config(settings, bodies, config, ladder_type=Counting)
    solver = ADMMSolver(settings, scn.num_agents, bodies, config, agents=agents)
    try:
        result = simulate(scn, solver=solver)
    finally:
        solver.close()
    assert len(calls) >= scn.num_agents * result.summary["steps"]  # every agent, every step at least once
