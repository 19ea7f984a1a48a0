"""Which QP solver should the sequential-QP local step (swarmpc.solvers.qp_local) use? Measured.

The local problems are recorded from a real closed loop: a few MPC steps of ADMM on
``builtin_scenario("random", agents=16, dim=3, seed=0)`` (3D, N = 10, hard OBCA, accel limits,
workspace), with the project's IPOPT local step, through a recording subclass of ``LocalSolverLadder`` handed
to the agents' factory. Copy counts the run did not produce (10) are made by adding copies
around a recorded problem's agent. For each size, the QP with the converged certificates of that
problem (``SequentialLocalQP``) is set up once per solver, then re-solved ``--repeats`` times,
each time after a small change, warm-started from the previous answer where the solver can:

* ``q``: the consensus targets moved by ~1 mm (a later ADMM iteration: only vectors change);
* ``q+A``: the certificates' normals also turned by ~1e-3 (a certificate round: matrix values
  change in place, the solver refactors).

Per solver and size: setup time, median / p95 / p99 time of one re-solve measured around the
update and solve calls from Python, the solver's own reported time (the difference is the Python
overhead), iterations, the largest distance of the answer from a reference (a cold DAQP solve
with a 1e-12 feasibility tolerance) and its largest constraint violation. DAQP runs twice: with
the working set the caller brings (what a solver shared by agents must do) and with the working
set the model keeps from its last solve (one solver per agent and shape).

Then every recorded call is replayed through the whole QP local step (``QPLocalLadder``:
certificate loop, rebuild, check), in call order, each agent's later ADMM iterations starting from
its own previous QP answer and multipliers, as ``LocalAgent`` would call it; against IPOPT's
answer to the same call: wall time per call (best of ``--best-of`` identical calls, for IPOPT
too, since other work on this machine adds ~4 ms stalls), rounds, and plan and cost deviation.

    .venv/bin/python benchmarks/qp_solvers.py [--steps 3] [--repeats 300] [--copies 0,2,5,10]

Prints markdown tables; writes benchmarks/results/qp_solvers.json.

The solvers other than OSQP come with the ``bench`` extra: ``pip install -c constraints.txt -e ".[bench]"``.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp

from swarmpc.formulation.ocp import OCPSettings
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.disturbance import planner_bodies
from swarmpc.simulation.loop import simulate
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver, LocalAgentFactory, LocalSolverLadder
from swarmpc.solvers.qp_local import (
    LocalShape,
    OSQPBackend,
    QPAnswer,
    QPLocalLadder,
    QPLocalOptions,
    SequentialLocalQP,
)

OUT = Path(__file__).parent / "results"
INF = 1e20


# --- recording real local problems ------------------------------------------------------------
def record_problems(steps: int, best_of: int = 1) -> tuple[OCPSettings, list[dict[str, Any]]]:
    """Every local problem an ADMM run solved, in call order, with IPOPT's answer; ``key`` (the
    measured state and goal) tells which calls are one agent's ADMM iterations of one MPC step."""
    scn = builtin_scenario("random", agents=16, dim=3, seed=0).with_updates(**{"stop.max_steps": steps})
    recorded: list[dict[str, Any]] = []

    class Recording(LocalSolverLadder):
        def solve(self, params, guess, fixed=None, *, copies, planes=0, duals=None):  # type: ignore[no-untyped-def]
            solution = super().solve(params, guess, fixed, copies=copies, planes=planes, duals=duals)
            for _ in range(best_of - 1):  # the same call again: IPOPT is deterministic, only the clock is not
                again = super().solve(params, guess, fixed, copies=copies, planes=planes, duals=duals)
                solution = replace(solution, solve_time=min(solution.solve_time, again.solve_time))
            if not planes and self.pair_collision is None:  # no rescue problems: soft pairs are their own study
                key = (tuple(np.round(params["x0"], 12)), tuple(np.round(params["goal"], 12)))
                recorded.append({"key": key, "params": dict(params),
                                 "guess": guess if isinstance(guess, dict) else None,
                                 "fixed": dict(fixed) if fixed else None, "copies": copies, "ipopt": solution})
            return solution

    recording_run(scn, Recording)
    return OCPSettings.from_scenario(scn), recorded


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


def with_copies(problem: dict[str, Any], copies: int, s: OCPSettings, rng: np.random.Generator) -> dict[str, Any]:
    """A recorded problem grown to ``copies`` neighbours: the extra copies' targets sit 0.45-0.9 m
    per axis from the agent's guessed positions (some engage, some do not), multipliers zero."""
    params, guess = dict(problem["params"]), dict(problem["guess"])
    own = np.asarray(guess["X"])[: s.dim, s.first_constrained_step:]
    for c in range(problem["copies"], copies):
        offset = rng.uniform(0.45, 0.9, s.dim) * rng.choice([-1.0, 1.0], s.dim)
        params[f"Z{c}"] = own + offset[:, None]
        params[f"Y{c}"] = np.zeros_like(own)
        guess[f"C{c}"] = params[f"Z{c}"]
    if problem["copies"] == 0 and copies:
        params["owner_weight"] = 5.0
    return {"params": params, "guess": guess, "copies": copies, "ipopt": None}


def pick_problems(recorded: list[dict[str, Any]], sizes: list[int], s: OCPSettings) -> dict[int, dict[str, Any]]:
    """One problem per copy count: a recorded one with the most active pair rows, else a grown one."""
    rng = np.random.default_rng(0)
    chosen = {}
    for n in sizes:
        same = [p for p in recorded if p["copies"] == n and p["guess"] is not None and p["fixed"] is None]
        if same:
            chosen[n] = same[len(same) // 2]
        else:
            base = max((p for p in recorded if p["copies"] < n and p["guess"] is not None and p["fixed"] is None),
                       key=lambda p: p["copies"])
            chosen[n] = with_copies(base, n, s, rng)
    return chosen


# --- one QP instance and its perturbations ---------------------------------------------------
@dataclass
class Instance:
    """A local QP with converged certificates: the stepper that built it and its data."""

    stepper: SequentialLocalQP
    params: dict[str, Any]
    lin: Any
    start: np.ndarray

    def data(self, params: dict[str, Any], lin: Any) -> tuple[np.ndarray, ...]:
        pb = self.stepper.problem
        lower, upper = pb.bounds(lin, params)
        return (pb.cost_values(float(params["rho"]), float(params["owner_weight"])), pb.linear_cost(params),
                pb.constraint_values(lin, params), lower, upper)


def make_instance(s: OCPSettings, problem: dict[str, Any]) -> Instance:
    shape = LocalShape(problem["copies"])
    stepper = SequentialLocalQP(s, shape, QPLocalOptions())
    solution = stepper.solve(problem["params"], problem["guess"])
    x = solution.x_vec[: stepper.problem.layout.size]
    own, copies = stepper.positions(x, None)
    lin = stepper.certify(own, copies, np.asarray(problem["params"]["delta"], float))
    return Instance(stepper, problem["params"], lin, x)


def perturbed(instance: Instance, rng: np.random.Generator, turn_normals: bool) -> tuple[dict[str, Any], Any]:
    """Consensus targets moved by ~1 mm; with ``turn_normals`` the certificates turned by ~1e-3."""
    params = dict(instance.params)
    for key in [k for k in params if k.startswith("Z")]:
        params[key] = np.asarray(params[key]) + 1e-3 * rng.standard_normal(np.shape(params[key]))
    lin = instance.lin
    if turn_normals and lin.pair_normal.size:
        normal = lin.pair_normal + 1e-3 * rng.standard_normal(lin.pair_normal.shape)
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        lin = replace(lin, pair_normal=normal)
    return params, lin


# --- candidate solvers (each: setup once, update, warm-started solve) --------------------------
class _Split:
    """Equality rows (l == u at setup: initial state, dynamics) and inequality rows of A, with
    maps from A's CSC data to each part's data so values can be updated in place."""

    def __init__(self, A: sp.csc_matrix, lower: np.ndarray, upper: np.ndarray) -> None:
        self.eq = np.nonzero(lower == upper)[0]
        self.ineq = np.nonzero(lower != upper)[0]
        marker = sp.csc_matrix((np.arange(A.nnz, dtype=float) + 1, A.indices, A.indptr), shape=A.shape)
        self.A_eq, self.A_in = marker[self.eq].tocsc(), marker[self.ineq].tocsc()
        self.eq_map = self.A_eq.data.astype(int) - 1
        self.in_map = self.A_in.data.astype(int) - 1

    def parts(self, data: np.ndarray) -> tuple[sp.csc_matrix, sp.csc_matrix]:
        eq, ineq = self.A_eq.copy(), self.A_in.copy()
        eq.data, ineq.data = data[self.eq_map], data[self.in_map]
        return eq, ineq


def _full(P_triu: sp.csc_matrix) -> sp.csc_matrix:
    return (P_triu + sp.triu(P_triu, 1).T).tocsc()


class PIQPBackend:
    """PIQP (sparse proximal interior point): equality and inequality rows split once."""

    name = "PIQP (sparse)"

    def setup(self, P, q, A, lower, upper) -> None:  # type: ignore[no-untyped-def]
        import piqp

        self.split, self.P = _Split(A, lower, upper), P
        self.solver = piqp.SparseSolver()
        self.solver.settings.eps_abs = self.solver.settings.eps_rel = 1e-7
        self.solver.settings.compute_timings = True
        eq, ineq = self.split.parts(A.data)
        self.solver.setup(P, q, eq, lower[self.split.eq], ineq, lower[self.split.ineq], upper[self.split.ineq])

    def update(self, q, lower, upper, P_data, A_data) -> None:  # type: ignore[no-untyped-def]
        args: dict[str, Any] = {"c": q, "b": lower[self.split.eq], "h_l": lower[self.split.ineq],
                                "h_u": upper[self.split.ineq]}
        if P_data is not None:
            args["P"] = sp.csc_matrix((P_data, self.P.indices, self.P.indptr), shape=self.P.shape)
        if A_data is not None:
            args["A"], args["G"] = self.split.parts(A_data)
        self.solver.update(**args)

    def solve(self, x, y) -> QPAnswer:  # type: ignore[no-untyped-def]
        status = self.solver.solve()
        r = self.solver.result
        return QPAnswer(np.array(r.x), np.zeros(0), "solved" in str(status).lower(), str(status),
                        int(r.info.iter), float(r.info.solve_time + r.info.update_time))


class ProxQPBackend:
    """proxsuite's ProxQP (augmented Lagrangian), sparse or dense backend, warm-started with the
    previous primal and dual answer."""

    def __init__(self, dense: bool) -> None:
        self.dense = dense
        self.name = f"ProxQP ({'dense' if dense else 'sparse'})"

    def _matrix(self, M: sp.csc_matrix) -> Any:
        return M.toarray() if self.dense else M

    def setup(self, P, q, A, lower, upper) -> None:  # type: ignore[no-untyped-def]
        import proxsuite

        self.split, self.P = _Split(A, lower, upper), P
        eq, ineq = self.split.parts(A.data)
        module = proxsuite.proxqp.dense if self.dense else proxsuite.proxqp.sparse
        self.qp = module.QP(P.shape[0], len(self.split.eq), len(self.split.ineq))
        self.qp.settings.eps_abs, self.qp.settings.eps_rel = 1e-7, 0.0
        self.qp.settings.compute_timings = True
        self.qp.settings.initial_guess = proxsuite.proxqp.InitialGuess.WARM_START
        self.qp.init(self._matrix(_full(P)), q, self._matrix(eq), lower[self.split.eq], self._matrix(ineq),
                     np.maximum(lower[self.split.ineq], -INF), np.minimum(upper[self.split.ineq], INF))
        self._last: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def update(self, q, lower, upper, P_data, A_data) -> None:  # type: ignore[no-untyped-def]
        args: dict[str, Any] = {"g": q, "b": lower[self.split.eq], "l": np.maximum(lower[self.split.ineq], -INF),
                                "u": np.minimum(upper[self.split.ineq], INF)}
        if P_data is not None:
            args["H"] = self._matrix(_full(sp.csc_matrix((P_data, self.P.indices, self.P.indptr), shape=self.P.shape)))
        if A_data is not None:
            eq, ineq = self.split.parts(A_data)
            args["A"], args["C"] = self._matrix(eq), self._matrix(ineq)
        self.qp.update(**args)

    def solve(self, x, y) -> QPAnswer:  # type: ignore[no-untyped-def]
        if self._last is None:
            self.qp.solve()
        else:
            self.qp.solve(*self._last)
        r = self.qp.results
        self._last = (np.array(r.x), np.array(r.y), np.array(r.z))
        solved = "SOLVED" in str(r.info.status) and "CLOSEST" not in str(r.info.status)
        return QPAnswer(np.array(r.x), np.zeros(0), solved, str(r.info.status), int(r.info.iter),
                        float(r.info.solve_time) * 1e-6)


class DAQPBackend:
    """DAQP (dual active set on the dense QP) through its ``Model``: H and A held as dense arrays
    whose changing entries are written in place. An active-set answer meets its active rows
    exactly and the others within ``primal_tol``. A caller's multipliers ``y`` set the starting
    working set (the local step shares one solver among agents, so each call must bring its
    own); with ``y`` None the model's own last working set is kept (one caller only)."""

    name = "DAQP (dense)"
    EQUALITY, ACTIVE, LOWER = 5, 1, 2  # DAQP sense flags: active + immutable; active; lower bound

    def __init__(self, options: QPLocalOptions | None = None, own_working_set: bool = False) -> None:
        self.options = options or QPLocalOptions()
        self.own_working_set = own_working_set
        self._pending: dict[str, Any] = {}

    def setup(self, P, q, A, lower, upper) -> None:  # type: ignore[no-untyped-def]
        import daqp

        self._P_index = (P.indices.copy(), np.repeat(np.arange(P.shape[1]), np.diff(P.indptr)))
        self._A_index = (A.indices.copy(), np.repeat(np.arange(A.shape[1]), np.diff(A.indptr)))
        self.H, self.A = np.zeros(P.shape), A.toarray()
        self._set_H(P.data)
        self.equality = lower == upper
        self._cold = np.where(self.equality, self.EQUALITY, 0).astype(np.int32)
        self._model = daqp.Model()
        self._model.setup(self.H, q, self.A, np.minimum(upper, 1e30), np.maximum(lower, -1e30), self._cold.copy())
        self._model.settings = {"primal_tol": 1e-9}

    def _set_H(self, data: np.ndarray) -> None:
        rows, cols = self._P_index
        self.H[rows, cols] = data
        self.H[cols, rows] = data

    def update(self, q, lower, upper, P_data, A_data) -> None:  # type: ignore[no-untyped-def]
        self._pending = {"f": q, "bupper": np.minimum(upper, 1e30), "blower": np.maximum(lower, -1e30)}
        if P_data is not None:
            self._set_H(P_data)
            self._pending["H"] = self.H
        if A_data is not None:
            self.A[self._A_index] = A_data
            self._pending["A"] = self.A

    def solve(self, x, y) -> QPAnswer:  # type: ignore[no-untyped-def]
        args = dict(self._pending)
        if not self.own_working_set:
            sense = self._cold.copy()
            if y is not None and y.size == sense.size:
                active = (y != 0) & ~self.equality
                sense[active] = np.where(y[active] < 0, self.ACTIVE | self.LOWER, self.ACTIVE)
            args["sense"] = sense
        if args:
            self._model.update(**args)
        self._pending = {}
        xs, _, flag, info = self._model.solve()
        return QPAnswer(np.array(xs, float), np.array(info["lam"], float), flag > 0, str(flag),
                        int(info["iterations"]), float(info["solve_time"]), exact=flag > 0)


class ClarabelBackend:
    """Clarabel (conic interior point; no warm start): l <= Ax <= u as Ax + s = b, s in cones."""

    name = "Clarabel"

    def setup(self, P, q, A, lower, upper) -> None:  # type: ignore[no-untyped-def]
        import clarabel

        self.clarabel = clarabel
        eq = lower == upper
        self.up = np.nonzero(~eq & np.isfinite(upper))[0]
        self.low = np.nonzero(~eq & np.isfinite(lower))[0]
        self.eq = np.nonzero(eq)[0]
        self.P, self.A = P, A
        settings = clarabel.DefaultSettings()
        settings.verbose = False
        settings.presolve_enable = False  # keep the row count fixed so data can be updated
        self.settings = settings
        self.solver = clarabel.DefaultSolver(P, q, self._stack(A), self._b(lower, upper), self._cones(), settings)

    def _stack(self, A: sp.csc_matrix) -> sp.csc_matrix:
        return sp.vstack([A[self.eq], A[self.up], -A[self.low]]).tocsc()

    def _b(self, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
        return np.concatenate([lower[self.eq], upper[self.up], -lower[self.low]])

    def _cones(self) -> list[Any]:
        return [self.clarabel.ZeroConeT(len(self.eq)), self.clarabel.NonnegativeConeT(len(self.up) + len(self.low))]

    def update(self, q, lower, upper, P_data, A_data) -> None:  # type: ignore[no-untyped-def]
        args: dict[str, Any] = {"q": q, "b": self._b(lower, upper)}
        if P_data is not None:
            args["P"] = sp.csc_matrix((P_data, self.P.indices, self.P.indptr), shape=self.P.shape)
        if A_data is not None:
            args["A"] = self._stack(sp.csc_matrix((A_data, self.A.indices, self.A.indptr), shape=self.A.shape))
        self.solver.update(**args)

    def solve(self, x, y) -> QPAnswer:  # type: ignore[no-untyped-def]
        r = self.solver.solve()
        return QPAnswer(np.array(r.x), np.zeros(0), str(r.status) == "Solved", str(r.status), int(r.iterations),
                        float(r.solve_time))


class CasadiConicBackend:
    """CasADi's ``conic`` plugin, called like ``nlpsol``: every matrix passed on every call."""

    def __init__(self, plugin: str) -> None:
        self.plugin = plugin
        self.name = f"CasADi conic + {plugin}"

    def setup(self, P, q, A, lower, upper) -> None:  # type: ignore[no-untyped-def]
        import casadi as ca

        self.ca = ca
        H = _full(P).tocoo()
        Acoo = A.tocoo()
        self.H_sp = ca.Sparsity.triplet(P.shape[0], P.shape[1], H.row.tolist(), H.col.tolist())
        self.A_sp = ca.Sparsity.triplet(A.shape[0], A.shape[1], Acoo.row.tolist(), Acoo.col.tolist())
        options: dict[str, Any] = {"error_on_fail": False}
        if self.plugin == "qpoases":
            options.update({"printLevel": "none", "sparse": True})
        elif self.plugin == "osqp":
            options.update({"osqp": {"verbose": False, "eps_abs": 1e-6, "eps_rel": 1e-6, "polish": True},
                            "warm_start_primal": True, "warm_start_dual": True})
        self.solver = ca.conic("qp", self.plugin, {"h": self.H_sp, "a": self.A_sp}, options)
        self.P, self.A = P, A
        self.data = {"h": self._dm(_full(P), self.H_sp), "g": q, "a": self._dm(A, self.A_sp),
                     "lba": lower, "uba": upper}
        self._lam: Any = None

    def _dm(self, M: sp.csc_matrix, sparsity: Any) -> Any:
        return self.ca.DM(sparsity, M.tocsc().sorted_indices().data)  # both column-major

    def update(self, q, lower, upper, P_data, A_data) -> None:  # type: ignore[no-untyped-def]
        self.data.update({"g": q, "lba": lower, "uba": upper})
        if P_data is not None:
            P = sp.csc_matrix((P_data, self.P.indices, self.P.indptr), shape=self.P.shape)
            self.data["h"] = self._dm(_full(P), self.H_sp)
        if A_data is not None:
            self.data["a"] = self._dm(sp.csc_matrix((A_data, self.A.indices, self.A.indptr), shape=self.A.shape),
                                      self.A_sp)

    def solve(self, x, y) -> QPAnswer:  # type: ignore[no-untyped-def]
        args = dict(self.data, x0=x)
        if self._lam is not None:
            args["lam_a0"] = self._lam
        out = self.solver(**args)
        stats = self.solver.stats()
        self._lam = out["lam_a"]
        solver_time = stats.get("t_wall_solver", 0.0) or np.nan  # the osqp plugin records none
        return QPAnswer(np.array(out["x"]).ravel(), np.zeros(0), bool(stats.get("success", False)),
                        str(stats.get("return_status", "")), int(stats.get("iter_count", -1)), float(solver_time))


def candidates() -> dict[str, Callable[[], Any]]:
    """Name -> backend factory, each tried; a solver that is not installed is reported, not fatal."""
    return {
        "OSQP (own API, eps 1e-6, polish, check every 25)": lambda: OSQPBackend(
            QPLocalOptions(check_termination=25)),
        "OSQP (own API, eps 1e-6, polish, check every 5)": lambda: OSQPBackend(QPLocalOptions(check_termination=5)),
        "OSQP (own API, eps 1e-4, polish, check every 5)": lambda: OSQPBackend(
            QPLocalOptions(eps_abs=1e-4, eps_rel=1e-4, check_termination=5)),
        "PIQP (sparse)": PIQPBackend,
        "ProxQP (sparse)": lambda: ProxQPBackend(dense=False),
        "ProxQP (dense)": lambda: ProxQPBackend(dense=True),
        "DAQP (dense, caller's working set)": DAQPBackend,
        "DAQP (dense, model keeps its working set)": lambda: DAQPBackend(own_working_set=True),
        "Clarabel": ClarabelBackend,
        "CasADi conic + osqp": lambda: CasadiConicBackend("osqp"),
        "CasADi conic + qpoases": lambda: CasadiConicBackend("qpoases"),
    }


# --- measurement ---------------------------------------------------------------------------------
def reference(instance: Instance, params: dict[str, Any], lin: Any) -> np.ndarray:
    """The answer of a perturbed QP by a fresh, cold DAQP model with a 1e-12 feasibility
    tolerance (an active-set answer: exact on its active set), to measure the others' accuracy."""
    P_data, q, A_data, lower, upper = instance.data(params, lin)
    pb = instance.stepper.problem
    backend = DAQPBackend()
    backend.setup(sp.csc_matrix((P_data, pb.P.indices, pb.P.indptr), shape=pb.P.shape), q,
                  sp.csc_matrix((A_data, pb.A.indices, pb.A.indptr), shape=pb.A.shape), lower, upper)
    backend._model.settings = {"primal_tol": 1e-12}
    answer = backend.solve(np.zeros(pb.P.shape[0]), None)
    assert answer.solved, answer.status
    return answer.x


def measure(name: str, factory: Callable[[], Any], instance: Instance, repeats: int, mode: str) -> dict[str, Any]:
    """Setup once, then ``repeats`` perturbed re-solves, warm-started from the previous answer."""
    rng = np.random.default_rng(1)
    pb = instance.stepper.problem
    P_data, q, A_data, lower, upper = instance.data(instance.params, instance.lin)
    backend = factory()
    began = time.perf_counter()
    backend.setup(sp.csc_matrix((P_data, pb.P.indices, pb.P.indptr), shape=pb.P.shape), q,
                  sp.csc_matrix((A_data, pb.A.indices, pb.A.indptr), shape=pb.A.shape), lower, upper)
    answer = backend.solve(instance.start, None)
    setup = time.perf_counter() - began
    cases = [perturbed(instance, rng, mode == "q+A") for _ in range(min(repeats, 20))]
    references = [reference(instance, *case) for case in cases]
    wall, own, iterations, error, violation, solved = [], [], [], [], [], []
    for r in range(repeats):
        params, lin = cases[r % len(cases)]
        _, q, A_new, lower, upper = instance.data(params, lin)
        x, y = answer.x, answer.y if answer.y.size else None
        started = time.perf_counter()
        backend.update(q, lower, upper, None, A_new if mode == "q+A" else None)
        answer = backend.solve(x, y)
        wall.append(time.perf_counter() - started)
        own.append(answer.solver_time)
        iterations.append(answer.iterations)
        solved.append(answer.solved)
        if answer.solved:
            Ax = sp.csc_matrix((A_new, pb.A.indices, pb.A.indptr), shape=pb.A.shape) @ answer.x
            violation.append(float(max(np.max(lower - Ax), np.max(Ax - upper), 0.0)))
            error.append(float(np.max(np.abs(answer.x - references[r % len(cases)]))))
    return summarise(name, mode, instance, setup, wall, own, iterations, solved, error, violation)


def summarise(name: str, mode: str, instance: Instance, setup: float, wall: list[float], own: list[float],
              iterations: list[int], solved: list[bool], error: list[float], violation: list[float]) -> dict[str, Any]:
    ms = 1e3 * np.array(wall)
    own_ms = 1e3 * np.array(own)
    pb = instance.stepper.problem
    return {
        "solver": name, "mode": mode, "copies": instance.stepper.shape.copies, "variables": int(pb.P.shape[0]),
        "rows": int(pb.A.shape[0]), "setup_ms": 1e3 * setup,
        "median_ms": float(np.median(ms)), "p95_ms": float(np.percentile(ms, 95)),
        "p99_ms": float(np.percentile(ms, 99)),
        "solver_median_ms": float(np.median(own_ms)),  # nan: the solver reports no time of its own
        "python_overhead_ms": float(np.median(ms - own_ms)),
        "iterations": float(np.median(iterations)), "solved": float(np.mean(solved)),
        "max_error": float(max(error, default=np.nan)), "max_violation": float(max(violation, default=np.nan)),
    }


def replay(s: OCPSettings, recorded: list[dict[str, Any]], options: QPLocalOptions,
           backend: Callable[[QPLocalOptions], Any] = OSQPBackend, best_of: int = 1) -> list[dict[str, Any]]:
    """The recorded calls again, in order, through the QP local step, as ``LocalAgent`` would call
    it: an agent's later ADMM iterations (and repair passes) start from its own previous QP answer
    and duals. Per call: wall time, rounds and the deviation from IPOPT's answer to the same call."""
    ladder = QPLocalLadder(s, options=options, backend=backend)
    last: dict[Any, Any] = {}
    rows = []
    for call in recorded:
        fixed, copies = call["fixed"], call["copies"]
        previous = last.get(call["key"])
        shape = LocalShape(copies, 0, fixed is not None and any(k.startswith("C") for k in fixed), s.collision)
        duals: tuple[np.ndarray, np.ndarray] | None = None
        if call["guess"] is not None:
            guess: Any = call["guess"]
        elif previous is not None and previous[0] == shape:
            guess, duals = previous[1].x_vec, (previous[1].lam_x, previous[1].lam_g)
        elif previous is not None:
            guess = {"X": previous[1].x["X"], "U": previous[1].x["U"],
                     **{f"C{c}": call["params"][f"Z{c}"] for c in range(copies)}}
        else:
            continue
        solution = ladder.solve(call["params"], guess, fixed, copies=copies, duals=duals)
        for _ in range(best_of - 1):  # identical calls: the warm start is explicit, so is the answer
            again = ladder.solve(call["params"], guess, fixed, copies=copies, duals=duals)
            solution = replace(solution, solve_time=min(solution.solve_time, again.solve_time))
        record = ladder.stepper(shape).last_record
        if solution.success:
            last[call["key"]] = (shape, solution)
        ipopt = call["ipopt"]
        row = {"copies": copies, "repair": fixed is not None, "qp_success": solution.success,
               "ipopt_success": ipopt.success, "qp_ms": 1e3 * solution.solve_time, "ipopt_ms": 1e3 * ipopt.solve_time,
               "rounds": record.rounds if record else 0, "exact_rounds": record.exact_rounds if record else 0,
               "qp_solver_ms": 1e3 * record.solver_time if record else np.nan,
               "status": solution.status}
        if solution.success and ipopt.success:
            row["plan_deviation"] = float(np.max(np.abs(solution.x["X"] - ipopt.x["X"])))
            row["cost_gap"] = float(solution.cost - ipopt.cost)
            row["relative_cost_gap"] = row["cost_gap"] / max(abs(ipopt.cost), 1.0)
        rows.append(row)
    return rows


def replay_summary(results: dict[str, list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Per local step and copy-count bucket: time percentiles, rounds, exactness, success, and
    (QP steps) the deviation of plan and cost from IPOPT's answer to the same call."""
    buckets = {"0": (0, 0), "1-2": (1, 2), "3-5": (3, 5), "6+": (6, 10**6)}
    summary = []
    for name, rows in results.items():
        key = "ipopt" if name.startswith("IPOPT") else "qp"
        for label, (low, high) in buckets.items():
            group = [r for r in rows if low <= r["copies"] <= high]
            if not group:
                continue
            ms = np.array([r[f"{key}_ms"] for r in group])
            line: dict[str, Any] = {
                "step": name, "copies": label, "calls": len(group), "median_ms": float(np.median(ms)),
                "p95_ms": float(np.percentile(ms, 95)), "p99_ms": float(np.percentile(ms, 99)),
                "success": float(np.mean([r[f"{key}_success"] for r in group]))}
            both = [r for r in group if "plan_deviation" in r]
            if key == "qp" and both:
                rounds = np.array([r["rounds"] for r in group])
                dev = np.array([r["plan_deviation"] for r in both])
                gap = np.array([r["relative_cost_gap"] for r in both])
                line.update({
                    "solver_median_ms": float(np.median([r["qp_solver_ms"] for r in group])),
                    "rounds_median": float(np.median(rounds)), "rounds_max": int(rounds.max()),
                    "exact_answers": sum(r["exact_rounds"] for r in group) / max(int(rounds.sum()), 1),
                    "deviation_median": float(np.median(dev)), "deviation_p95": float(np.percentile(dev, 95)),
                    "deviation_max": float(dev.max()), "same_plan": float(np.mean(dev <= 1e-4)),
                    "qp_cost_lower": float(np.mean(gap < -1e-4)), "qp_cost_higher": float(np.mean(gap > 1e-4)),
                    "relative_cost_gap_median": float(np.median(gap)),
                    "relative_cost_gap_p95": float(np.percentile(gap, 95))})
            summary.append(line)
    return summary


def replay_table(summary: list[dict[str, Any]]) -> str:
    head = ("| local step | copies | calls | median ms (QP solver's own) | p95 ms | p99 ms | rounds (median/max) "
            "| exact QP answers "
            "| success | plan within 1e-4 m of IPOPT's | plan deviation (median/p95/max) m "
            "| cost more than 0.01% below / above IPOPT's | relative cost gap (median/p95) |\n"
            + "|---" * 13 + "|\n")
    lines = []
    for r in summary:
        own = f" ({r['solver_median_ms']:.3f})" if "solver_median_ms" in r else ""
        text = (f"| {r['step']} | {r['copies']} | {r['calls']} | {r['median_ms']:.3f}{own} | {r['p95_ms']:.3f} "
                f"| {r['p99_ms']:.3f} | ")
        if "rounds_median" in r:
            text += (f"{r['rounds_median']:.0f}/{r['rounds_max']} | {100 * r['exact_answers']:.1f}% "
                     f"| {100 * r['success']:.1f}% | {100 * r['same_plan']:.1f}% "
                     f"| {r['deviation_median']:.0e}/{r['deviation_p95']:.0e}/{r['deviation_max']:.0e} "
                     f"| {100 * r['qp_cost_lower']:.1f}% / {100 * r['qp_cost_higher']:.1f}% "
                     f"| {r['relative_cost_gap_median']:.0e}/{r['relative_cost_gap_p95']:.0e} |")
        else:
            text += f"- | - | {100 * r['success']:.1f}% | - | - | - | - |"
        lines.append(text)
    return head + "\n".join(lines)


def _ms(value: float) -> str:
    """A time cell; "n/a" where the solver reports none or more than the wall time around it."""
    return "n/a" if not np.isfinite(value) or value < 0 else f"{value:.3f}"


def table(rows: list[dict[str, Any]]) -> str:
    head = ("| copies (vars/rows) | solver | mode | setup ms | median ms | p95 ms | p99 ms | solver's own ms "
            "| Python overhead ms | iters | solved | max error | max violation |\n" + "|---" * 13 + "|\n")
    lines = []
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['copies']} | {r['solver']} | {r['mode']} | not usable: {r['error']} |" + " |" * 9)
            continue
        lines.append(
            f"| {r['copies']} ({r['variables']}/{r['rows']}) | {r['solver']} | {r['mode']} | {r['setup_ms']:.2f} "
            f"| {r['median_ms']:.3f} | {r['p95_ms']:.3f} | {r['p99_ms']:.3f} | {_ms(r['solver_median_ms'])} "
            f"| {_ms(r['python_overhead_ms'])} | {r['iterations']:.0f} | {100 * r['solved']:.0f}% "
            f"| {r['max_error']:.1e} | {r['max_violation']:.1e} |")
    return head + "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3, help="MPC steps of the recording run")
    parser.add_argument("--repeats", type=int, default=300, help="re-solves per solver and size")
    parser.add_argument("--copies", default="0,2,5,10")
    parser.add_argument("--only", default="", help="comma-separated substrings of solver names")
    parser.add_argument("--best-of", type=int, default=3, help="identical calls per replayed call (min time)")
    args = parser.parse_args()
    s, recorded = record_problems(args.steps, args.best_of)
    sizes = [int(c) for c in args.copies.split(",")]
    instances = {n: make_instance(s, p) for n, p in pick_problems(recorded, sizes, s).items()}
    wanted = [w.strip() for w in args.only.split(",") if w.strip()]
    rows = []
    for name, factory in candidates().items():
        if wanted and not any(w in name for w in wanted):
            continue
        slow = name.startswith("CasADi") or name.startswith("Clarabel")
        for n, instance in instances.items():
            for mode in ("q", "q+A"):
                try:
                    rows.append(measure(name, factory, instance, max(args.repeats // 10, 20) if slow else args.repeats,
                                        mode))
                except Exception as err:  # noqa: BLE001 - a solver that cannot run is a finding
                    rows.append({"solver": name, "mode": mode, "copies": n,
                                 "error": f"{type(err).__name__}: {err}"[:120]})
    osqp_rows = replay(s, recorded, QPLocalOptions(), best_of=args.best_of)
    replays = {"IPOPT (shipped local NLP, as recorded)": osqp_rows, "QP step + OSQP (shipped)": osqp_rows,
               "QP step + DAQP (caller's working set)": replay(s, recorded, QPLocalOptions(), DAQPBackend,
                                                               best_of=args.best_of)}
    print(f"Local QPs from random 3D M=16 ({args.steps} MPC steps recorded, {len(recorded)} local problems); "
          f"{args.repeats} re-solves per cell (CasADi / Clarabel: fewer).\n")
    print(table(rows))
    print("\nEvery recorded local step replayed through the QP local step (certificate loop), in call order, "
          "against IPOPT's answer to the same call:\n")
    summary = replay_summary(replays)
    print(replay_table(summary))
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "qp_solvers.json").write_text(json.dumps({
        "machine": platform.platform(), "python": platform.python_version(), "steps": args.steps,
        "repeats": args.repeats, "best_of": args.best_of, "rows": rows, "replay": summary}, indent=2))


if __name__ == "__main__":
    main()
