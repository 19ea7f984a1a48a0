"""The stage-wise local problem of benchmarks/structured_solvers.py is the package's local problem
reordered: solved with IPOPT, both reach the same optimum, so the benchmark compares solvers on
the problem the agents actually solve."""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from swarmpc.formulation.ocp import IPOPT_OPTIONS, OCPSettings, build_local
from swarmpc.scenarios import builtin_scenario

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _module():
    if str(BENCHMARKS) not in sys.path:
        sys.path.insert(0, str(BENCHMARKS))
    return importlib.import_module("structured_solvers")


@pytest.mark.parametrize("copies", [0, 2])
def test_stagewise_problem_has_the_local_problems_optimum(copies):
    bench = _module()
    settings = OCPSettings.from_scenario(builtin_scenario("random", agents=8, dim=3, seed=0))
    d, N, first = settings.dim, settings.horizon, settings.first_constrained_step
    problem, data = bench.stagewise_local_problem(settings, copies)
    state, params = bench.problem_values(settings, copies, np.random.default_rng(1))
    lbx, ubx = data["lbx"].copy(), data["ubx"].copy()
    lbx[: state.size] = ubx[: state.size] = state
    start = bench.held_start(settings, data["structure"]["nu"], state, params, copies)
    stagewise = ca.nlpsol("stagewise", "ipopt", problem, dict(IPOPT_OPTIONS))(
        x0=np.clip(start, lbx, ubx), p=params, lbx=lbx, ubx=ubx, lbg=data["lbg"], ubg=data["ubg"])

    goal = params[: 2 * d]
    targets = params[3 * d:].reshape(copies + 1, N + 1, d).transpose(0, 2, 1)[:, :, first:]
    local = build_local(settings, copies)
    values = {"x0": state, "goal": goal, "delta": params[2 * d: 3 * d], "rho": bench.RHO,
              "owner_weight": bench.OWNER_WEIGHT, "Z": targets[0], "Y": np.zeros_like(targets[0])}
    guess = {"X": np.tile(state[:, None], (1, N + 1))}
    for c in range(copies):
        values.update({f"Z{c}": targets[c + 1], f"Y{c}": np.zeros_like(targets[0])})
        guess[f"C{c}"] = targets[c + 1]
    solution = local.solve(values, guess)

    assert solution.success
    assert float(stagewise["f"]) == pytest.approx(solution.cost, rel=1e-5)
    x = np.asarray(stagewise["x"]).ravel()
    offsets = np.cumsum([0] + [2 * d + n for n in data["structure"]["nu"]])[:-1]
    states = np.array([x[o: o + 2 * d] for o in offsets]).T
    first_input = x[2 * d: 3 * d]
    assert np.allclose(states, solution.x["X"], atol=1e-5)
    assert np.allclose(first_input, solution.x["U"][:, 0], atol=1e-5)
    assert np.abs(first_input).max() > 1e-3  # the agent does move towards its goal
