"""Do the structure-exploiting solvers (fatrop, SQP + HPIPM) beat IPOPT on an agent's local problem?

fatrop exploits the optimal-control structure (a Riccati recursion over the horizon) but needs
the variables and constraints ordered stage by stage: x_k, then everything else of step k (the
input, the copies' positions and the certificates of step k), and per stage the gap-closing
dynamics row first, then the stage's path constraints. The package's builder orders by block,
so this script states the same local problem (own trajectory, ``n`` copies, hard OBCA against
each copy, consensus penalties, the scenario's limits) stage-wise, gives fatrop and HPIPM (the
QP solver of CasADi's sqpmethod) the structure by hand, and solves it with each solver from the
same points (qrqp, the sparse active-set QP shipped with CasADi, as the unstructured SQP):

* cold: from the measured state held still, certificates at zero;
* warm: the next ADMM iteration's problem (consensus targets moved by 1 mm) from the previous
  solution, primal and dual.

    python benchmarks/structured_solvers.py [--copies 0,2,5,10] [--repeats 20]

Writes benchmarks/out/structured_solvers.md and .json.
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from swarmpc.formulation.ocp import LOCAL_IPOPT_OPTIONS, WARM_START_OPTIONS, OCPSettings
from swarmpc.model.dynamics import discrete_matrices
from swarmpc.scenarios import builtin_scenario

OUT = Path(__file__).parent / "out"
OWNER_WEIGHT = 5.0
RHO = 10.0


def stagewise_local_problem(s: OCPSettings, copies: int) -> tuple[dict[str, ca.SX], dict[str, Any]]:
    """The local problem ordered by stage, and its bounds and fatrop structure."""
    d, N, first = s.dim, s.horizon, s.first_constrained_step
    A, B = discrete_matrices(d, s.dt, s.discretization)  # type: ignore[arg-type]
    goal, half = ca.SX.sym("goal", 2 * d), ca.SX.sym("half", d)
    targets = [ca.SX.sym(f"Z{c}", d, N + 1) for c in range(copies + 1)]  # own block first
    X = [ca.SX.sym(f"x{k}", 2 * d) for k in range(N + 1)]
    U = [ca.SX.sym(f"u{k}", d) for k in range(N)]
    amax = s.accel if s.accel is not None else np.full(d, np.inf)
    variables: list[ca.SX] = []
    rows: list[ca.SX] = []
    lbx: list[float] = []
    ubx: list[float] = []
    lbg: list[float] = []
    ubg: list[float] = []
    nu: list[int] = []
    ng: list[int] = []
    cost = ca.SX(0)
    for k in range(N + 1):
        variables.append(X[k])
        lower, upper = np.full(2 * d, -np.inf), np.full(2 * d, np.inf)
        if k >= first and s.lower is not None and s.upper is not None:
            lower[:d], upper[:d] = s.lower, s.upper
        lbx += list(lower)
        ubx += list(upper)
        stage_inputs = stage_rows = 0
        if k < N:
            variables.append(U[k])
            lbx += list(-amax)
            ubx += list(amax)
            stage_inputs += d
            rows.append(X[k + 1] - (ca.mtimes(A, X[k]) + ca.mtimes(B, U[k])))  # the gap row first
            lbg += [0.0] * 2 * d
            ubg += [0.0] * 2 * d
            cost += ca.mtimes([U[k].T, s.R, U[k]])
        err = X[k] - goal
        cost += ca.mtimes([err.T, s.Q if k < N else s.Qf, err])
        if k >= first:
            position = X[k][:d]
            cost += 0.5 * RHO * OWNER_WEIGHT * ca.sumsqr(position - targets[0][:, k])
            for c in range(copies):
                copy, lam = ca.SX.sym(f"c{c}_{k}", d), ca.SX.sym(f"l{c}_{k}", 2 * d)
                variables += [copy, lam]
                lbx += [-np.inf] * d + [0.0] * 2 * d
                ubx += [np.inf] * 3 * d
                stage_inputs += 3 * d
                cost += 0.5 * RHO * ca.sumsqr(copy - targets[c + 1][:, k])
                direction, size = lam[:d] - lam[d:], lam[:d] + lam[d:]
                rows += [ca.dot(position - copy, direction) - ca.dot(size, half), ca.sumsqr(direction)]
                lbg += [s.d_min, -np.inf]
                ubg += [np.inf, 1.0]
                stage_rows += 2
        if k >= 1 and s.speed is not None:
            rows.append(ca.sumsqr(X[k][d:]))
            lbg.append(-np.inf)
            ubg.append(s.speed**2)
            stage_rows += 1
        nu.append(stage_inputs)
        ng.append(stage_rows)
    problem = {"x": ca.vertcat(*variables), "f": cost, "g": ca.vertcat(*rows),
               "p": ca.vertcat(goal, half, *[ca.vec(t) for t in targets])}
    return problem, {"lbx": np.array(lbx), "ubx": np.array(ubx), "lbg": np.array(lbg), "ubg": np.array(ubg),
                     "structure": {"N": N, "nx": [2 * d] * (N + 1), "nu": nu, "ng": ng}}


def problem_values(s: OCPSettings, copies: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Start state and parameters: the agent at rest mid-box heading to a goal 1.2 m away, its
    neighbours' consensus targets held still within 0.45-0.9 m per axis (some couple, some not)."""
    d, N = s.dim, s.horizon
    state = np.r_[1.5, 1.5, 1.2, np.zeros(d)][: 2 * d]
    goal = state.copy()
    goal[:d] += 0.7
    targets = [np.tile(state[:d, None], (1, N + 1))]
    for _ in range(copies):
        offset = rng.uniform(0.45, 0.9, d) * rng.choice([-1.0, 1.0], d)
        targets.append(np.tile((state[:d] + offset)[:, None], (1, N + 1)))
    params = np.concatenate([goal, np.full(d, 0.3), *[t.ravel(order="F") for t in targets]])
    return state, params


def held_start(s: OCPSettings, nu: list[int], state: np.ndarray, params: np.ndarray, copies: int) -> np.ndarray:
    """The measured state held along the horizon, each copy at its target, certificates zero."""
    d, N = s.dim, s.horizon
    targets = params[3 * d:].reshape(copies + 1, N + 1, d)  # column-major (d, N+1) blocks
    start = np.zeros(sum(nu) + 2 * d * (N + 1))
    offset = 0
    for k in range(N + 1):
        start[offset: offset + 2 * d] = state
        cursor = offset + 2 * d + (d if k < N else 0)
        if k >= s.first_constrained_step:
            for c in range(copies):
                start[cursor: cursor + d] = targets[c + 1, k]
                cursor += 3 * d
        offset += 2 * d + nu[k]
    return start


def measure(s: OCPSettings, copies: int, repeats: int, rng: np.random.Generator) -> list[dict[str, Any]]:
    problem, data = stagewise_local_problem(s, copies)
    state, params = problem_values(s, copies, rng)
    lbx, ubx = data["lbx"].copy(), data["ubx"].copy()
    lbx[: state.size] = ubx[: state.size] = state  # the measured state pins x_0
    structure = data["structure"]
    ipopt: dict[str, Any] = dict(LOCAL_IPOPT_OPTIONS)
    ipopt_warm: dict[str, Any] = {**LOCAL_IPOPT_OPTIONS, **WARM_START_OPTIONS}
    sqp: dict[str, Any] = {"print_header": False, "print_iteration": False, "print_status": False,
                           "print_time": False, "expand": True, "max_iter": 50, "convexify_strategy": "regularize"}
    builders: dict[str, Callable[[], ca.Function]] = {
        "ipopt": lambda: ca.nlpsol("ipopt_cold", "ipopt", problem, ipopt),
        "ipopt warm": lambda: ca.nlpsol("ipopt_warm", "ipopt", problem, ipopt_warm),
        "fatrop": lambda: ca.nlpsol("fatrop", "fatrop", problem, {
            "expand": True, "print_time": False, "structure_detection": "manual", **structure,
            "fatrop": {"print_level": 0, "tol": 1e-6}}),
        "sqpmethod + hpipm": lambda: ca.nlpsol("sqp_hpipm", "sqpmethod", problem, {
            **sqp, "qpsol": "hpipm", "qpsol_options": {**structure, "error_on_fail": False}}),
        "sqpmethod + qrqp": lambda: ca.nlpsol("sqp_qrqp", "sqpmethod", problem, {
            **sqp, "qpsol": "qrqp",
            "qpsol_options": {"print_iter": False, "print_header": False, "error_on_fail": False}}),
    }
    solvers: dict[str, Any] = {}
    errors: dict[str, str] = {}
    for name, build in builders.items():
        try:
            solvers[name] = build()
        except RuntimeError as err:  # a solver that rejects the problem is a finding, not a crash
            message = [line for line in str(err).splitlines() if "Assertion" in line or "rror" in line]
            errors[name] = (message[-1] if message else str(err).splitlines()[0]).strip()[:160]
    start = held_start(s, data["structure"]["nu"], state, params, copies)
    bounds = {"lbx": lbx, "ubx": ubx, "lbg": data["lbg"], "ubg": data["ubg"]}
    moved = params.copy()
    moved[2 * s.dim + s.dim:] += 1e-3
    rows = []
    reference = solvers["ipopt"](x0=np.clip(start, lbx, ubx), p=params, **bounds)
    for name in ("ipopt", "fatrop", "sqpmethod + hpipm", "sqpmethod + qrqp"):
        if name in errors:
            rows.append({"solver": name, "copies": copies, "variables": int(problem["x"].shape[0]),
                         "error": errors[name]})
            continue
        solver = solvers[name]
        for mode in ("cold", "warm"):
            times, iterations, success, objective = [], [], [], []
            for _ in range(repeats):
                if mode == "cold":
                    args = {"x0": np.clip(start, lbx, ubx), "p": params}
                    used = solver
                else:
                    args = {"x0": reference["x"], "lam_x0": reference["lam_x"], "lam_g0": reference["lam_g"],
                            "p": moved}
                    used = solvers["ipopt warm"] if name == "ipopt" else solver
                began = time.perf_counter()
                out = used(**args, **bounds)
                times.append(1000.0 * (time.perf_counter() - began))
                stats = used.stats()
                iterations.append(int(stats.get("iter_count", -1)))
                success.append(bool(stats.get("success", False)))
                objective.append(float(out["f"]))
            rows.append({"solver": name, "start": mode, "copies": copies, "variables": int(problem["x"].shape[0]),
                         "median_ms": float(np.median(times)), "iterations": int(np.median(iterations)),
                         "success": float(np.mean(success)), "objective": float(np.median(objective))})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--copies", default="0,2,5,10")
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    scn = builtin_scenario("random", agents=8, dim=3, seed=0)
    settings = OCPSettings.from_scenario(scn)
    rng = np.random.default_rng(0)
    rows = [row for n in (int(c) for c in args.copies.split(",")) for row in measure(settings, n, args.repeats, rng)]
    header = ("| copies | variables | solver | start | median ms | iterations | success | objective |\n"
              "|---|---|---|---|---|---|---|---|\n")
    lines = [f"| {r['copies']} | {r['variables']} | {r['solver']} | - | - | - | - | rejected: {r['error']} |"
             if "error" in r else
             f"| {r['copies']} | {r['variables']} | {r['solver']} | {r['start']} | {r['median_ms']:.2f} | "
             f"{r['iterations']} | {100 * r['success']:.0f}% | {r['objective']:.6f} |" for r in rows]
    intro = (f"Local problem of random 3D (N = {settings.horizon}, dt = {settings.dt}, hard OBCA), ordered by "
             f"stage; median of {args.repeats} solves.\n\n")
    OUT.mkdir(exist_ok=True)
    (OUT / "structured_solvers.md").write_text(intro + header + "\n".join(lines) + "\n")
    (OUT / "structured_solvers.json").write_text(json.dumps(rows, indent=2))
    print(intro + header + "\n".join(lines))


if __name__ == "__main__":
    main()
