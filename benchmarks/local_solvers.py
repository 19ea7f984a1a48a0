"""Which NLP solver should the agents' local ADMM steps use? Measured on recorded problems.

Records the local problems (parameters, initial point, pinned blocks) that a closed-loop ADMM
run of a scenario actually solves, then re-solves every recorded problem with each candidate
configuration in the same process, interleaved, so machine noise hits all candidates alike.
Reports per configuration: median / p95 solve time, success rate, and the largest deviation of
the solution from the reference (IPOPT as shipped) on problems both solved.

    python benchmarks/local_solvers.py [--scenario paper-2d] [--steps 120] [--repeats 3]

Writes benchmarks/out/local_solvers.md and .json.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from swarmpc.formulation.nlp import CompiledNLP
from swarmpc.formulation.ocp import LOCAL_IPOPT_OPTIONS, OCPSettings, build_local
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.disturbance import planner_bodies
from swarmpc.simulation.loop import simulate
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver, LocalAgentFactory, LocalSolverLadder

OUT = Path(__file__).parent / "out"
QUIET_SQP = {"print_header": False, "print_iteration": False, "print_status": False, "print_time": False,
             "expand": True, "max_iter": 100}

WARM = "warm"
"""Pseudo-option: build with the shipped warm-start options and pass the recorded multipliers."""

CANDIDATES: dict[str, tuple[str, dict[str, Any]]] = {
    "ipopt (shipped: adaptive mu, expanded SX, multipliers warm-started)": ("ipopt", {WARM: True}),
    "ipopt, primal warm start only (multipliers cold)": ("ipopt", {}),
    "ipopt, multipliers warm-started, MUMPS scaling and parameter multipliers on (the previous default)": (
        "ipopt", {WARM: True, "ipopt.mumps_scaling": 77, "ipopt.mumps_permuting_scaling": 7, "calc_lam_p": True}),
    "ipopt, multipliers warm-started, SPRAL linear solver": (
        "ipopt", {WARM: True, "ipopt.linear_solver": "spral"}),
    "ipopt, multipliers warm-started, no NLP scaling": (
        "ipopt", {WARM: True, "ipopt.nlp_scaling_method": "none"}),
    "ipopt, monotone mu": ("ipopt", {"ipopt.mu_strategy": "monotone"}),
    "ipopt, not expanded (MX)": ("ipopt", {"expand": False}),
    "ipopt, JIT-compiled derivatives (gcc -O2)": (
        "ipopt", {"jit": True, "compiler": "shell", "jit_options": {"flags": ["-O2"], "verbose": False}}),
    "sqpmethod + qrqp (Hessian regularised)": ("sqpmethod", {**QUIET_SQP, "qpsol": "qrqp",
                                                 "convexify_strategy": "regularize",
                                       "qpsol_options": {"print_iter": False, "print_header": False,
                                                         "error_on_fail": False}}),
    "fatrop (structure detection)": ("fatrop", {"expand": True, "structure_detection": "auto",
                                                "fatrop": {"print_level": 0}, "print_time": False}),
}


def record_problems(scenario: str, steps: int, agents: int | None = None) -> tuple[OCPSettings, list[dict[str, Any]]]:
    """Run ADMM in closed loop and keep every local problem it solved."""
    scn = builtin_scenario(scenario, **({"agents": agents} if agents else {})).with_updates(
        **{"stop.max_steps": steps})
    recorded: list[dict[str, Any]] = []

    class Recording(LocalSolverLadder):
        def solve(self, params, guess, fixed=None, *, copies, planes=0, duals=None):  # type: ignore[no-untyped-def]
            if not planes:  # the candidates are built without separating planes
                recorded.append({"slots": self.slots_for(copies), "params": params, "guess": guess, "fixed": fixed,
                                 "duals": duals})
            return super().solve(params, guess, fixed, copies=copies, planes=planes, duals=duals)

    recording_run(scn, Recording)
    return admm_settings(scn), recorded


def recording_run(scn: Any, ladder_type: type[LocalSolverLadder]) -> None:
    """``scn`` in closed loop under the scenario's ADMM, the agents' IPOPT ladders of ``ladder_type``."""
    settings = OCPSettings.from_scenario(scn)
    config = ADMMConfig.from_options(scn.solver, settings.collision)
    bodies = planner_bodies(scn)
    agents = LocalAgentFactory.for_config(settings, bodies, config, ladder_type=ladder_type)
    solver = ADMMSolver(settings, scn.num_agents, bodies, config, agents=agents)
    try:
        simulate(scn, solver=solver)
    finally:
        solver.close()


def admm_settings(scn: Any) -> OCPSettings:
    return OCPSettings.from_scenario(scn)


def build_candidate(settings: OCPSettings, slots: int, plugin: str, options: dict[str, Any]) -> CompiledNLP:
    if plugin == "ipopt":
        warm = bool(options.get(WARM))
        return build_local(settings, slots, False, {k: v for k, v in options.items() if k != WARM}, warm_start=warm)
    return build_local(settings, slots, False, options, plugin)


def solve_recorded(nlp: CompiledNLP, problem: dict[str, Any]) -> Any:
    """One recorded problem; its multipliers are used only by a solver built to warm-start."""
    lam_x = lam_g = None
    if nlp.warm_solver is not None and problem["duals"] is not None:
        lam_x, lam_g = problem["duals"]
    return nlp.solve(problem["params"], problem["guess"], lam_x, lam_g, fixed=problem["fixed"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="paper-2d")
    parser.add_argument("--agents", type=int, default=None, help="swarm size of a generated scenario")
    parser.add_argument("--steps", type=int, default=120)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--max-problems", type=int, default=300)
    parser.add_argument("--only", default="", help="comma-separated substrings: run the matching candidates only")
    args = parser.parse_args()
    wanted = [w.strip() for w in args.only.split(",") if w.strip()]
    candidates = {name: spec for name, spec in CANDIDATES.items()
                  if not wanted or any(w in name for w in wanted)}

    settings, problems = record_problems(args.scenario, args.steps, args.agents)
    rng = np.random.default_rng(0)
    if len(problems) > args.max_problems:
        problems = [problems[i] for i in sorted(rng.choice(len(problems), args.max_problems, replace=False))]
    sizes = sorted({p["slots"] for p in problems})
    built: dict[str, dict[int, CompiledNLP]] = {}
    build_time: dict[str, float] = {}
    errors: dict[str, str] = {}
    for name, (plugin, options) in candidates.items():
        started = time.perf_counter()
        try:
            built[name] = {k: build_candidate(settings, k, plugin, options) for k in sizes}
            probe = problems[0]
            solve_recorded(built[name][probe["slots"]], probe)
        except Exception as err:  # noqa: BLE001 - a candidate that cannot run is a finding, not a crash
            errors[name] = f"{type(err).__name__}: {str(err).splitlines()[0][:120]}"
            built.pop(name, None)
        build_time[name] = time.perf_counter() - started

    times: dict[str, list[float]] = {name: [] for name in built}
    success: dict[str, list[bool]] = {name: [] for name in built}
    deviation: dict[str, list[float]] = {name: [] for name in built}
    iterations: dict[str, list[int]] = {name: [] for name in built}
    reference = next(iter(built))
    for problem in problems:
        solutions = {}
        for _repeat in range(args.repeats):
            for name, solvers in built.items():  # interleaved: noise hits every candidate alike
                started = time.perf_counter()
                try:
                    solution = solve_recorded(solvers[problem["slots"]], problem)
                except RuntimeError:  # a solver that throws on a problem has failed it
                    solution = None
                times[name].append(1000.0 * (time.perf_counter() - started))
                solutions[name] = solution
        for name, solution in solutions.items():
            success[name].append(solution is not None and solution.success)
            if solution is not None:
                iterations[name].append(solution.iterations)
            ref = solutions[reference]
            if solution is not None and solution.success and ref is not None and ref.success:
                own = solution.x["X"] - ref.x["X"]
                deviation[name].append(float(np.max(np.abs(own))))

    rows: list[dict[str, Any]] = []
    for name in candidates:
        if name in errors:
            rows.append({"solver": name, "error": errors[name], "build_s": build_time[name]})
            continue
        rows.append({
            "solver": name, "median_ms": float(np.median(times[name])), "p95_ms": float(np.percentile(times[name], 95)),
            "success_rate": float(np.mean(success[name])),
            "median_iterations": float(np.median(iterations[name])) if iterations[name] else float("nan"),
            "max_plan_deviation": float(max(deviation[name], default=float("nan"))),
            "median_plan_deviation": float(np.median(deviation[name])) if deviation[name] else float("nan"),
            "build_s": build_time[name],
        })
    header = ("| local solver | median ms | p95 ms | solver iterations (median) | success "
              "| plan deviation vs shipped (median / max) | build s |\n|---|---|---|---|---|---|---|\n")
    lines = []
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['solver']} | - | - | - | - | not usable: {r['error']} | {r['build_s']:.1f} |")
        else:
            lines.append(f"| {r['solver']} | {r['median_ms']:.2f} | {r['p95_ms']:.2f} | {r['median_iterations']:.0f} "
                         f"| {100 * r['success_rate']:.0f}% "
                         f"| {r['median_plan_deviation']:.1e} / {r['max_plan_deviation']:.1e} | {r['build_s']:.1f} |")
    counts = {k: sum(p['slots'] == k for p in problems) for k in sizes}
    source = f"{args.scenario}, {args.agents} agents" if args.agents else args.scenario
    intro = (f"{len(problems)} local problems recorded from `{source}` ({args.steps} MPC steps; "
             f"problems by copy slots: {counts}), each solved {args.repeats}x per solver, interleaved.\n\n")
    OUT.mkdir(exist_ok=True)
    (OUT / "local_solvers.md").write_text(intro + header + "\n".join(lines) + "\n")
    (OUT / "local_solvers.json").write_text(json.dumps({"problems": len(problems), "sizes": counts,
                                                        "ipopt_options": LOCAL_IPOPT_OPTIONS, "rows": rows}, indent=2))
    print(intro + header + "\n".join(lines))


if __name__ == "__main__":
    main()
