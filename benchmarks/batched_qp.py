"""Can agents' local QPs of one shape be solved faster in one batched call? Measured.

The local problems are recorded from a real closed loop by ``qp_solvers.record_problems`` (random 3D,
M = 16, seed 0, IPOPT local step). From the recorded steps the crowded group is taken: the largest
set of agents of one MPC step whose problems share a shape (the same copy count, at least one copy),
each at the same ADMM iteration (``--iteration``), and each turned into the QP with the converged
certificates of its problem (``qp_solvers.make_instance``). A batch of B problems takes the first B
of them; where the step has fewer agents of that shape, the others are made from recorded ones with
targets moved by ~1 mm and certificate normals turned by ~1e-3 (``qp_solvers.perturbed``), so every
block of a batch differs. Each variant is set up once per batch size, then re-solved ``--repeats``
times, each time after the consensus targets of every problem moved by ~1 mm (a later ADMM
iteration: q changes, the matrices do not), warm-started from its previous answer:

* OSQP one by one: B OSQP solvers, one per agent, each updated (q, l, u) and solved in turn (the
  shipped way: ``swarmpc.solvers.qp_local.OSQPBackend`` with the default options);
* OSQP block-diagonal: one OSQP problem holding the B problems as diagonal blocks, its stacked
  vectors updated and solved in one call (same options; its stopping test and step size are shared
  by all blocks);
* ProxQP dense: proxsuite's ``proxqp.dense.BatchQP`` solved by ``proxqp.dense.solve_in_parallel``
  with 1 and 2 threads, and the same QPs solved one by one from Python (the batch API's own gain
  apart from the solver's), with the settings ``qp_solvers.py`` gives ProxQP;
* CasADi conic + osqp mapped: one ``conic`` function evaluated over the batch by
  ``Function.map`` (serial, and 2 threads); every matrix is passed on every call.

Per batch size and variant: the wall time of one whole update + solve of the batch measured from
Python (median and p95; the variants take turns within each repeat, in an order drawn anew each
time, so machine noise hits all alike), the time per agent, and the largest distance of any
answer from the one-by-one OSQP answer of the same repeat (each solver stops at its own tolerance,
so a few 1e-6 is agreement). OpenMP threads are made to sleep when idle (``OMP_WAIT_POLICY=PASSIVE``
unless set otherwise): spinning ones would slow whichever variant runs next.

    nice -n 10 .venv/bin/python benchmarks/batched_qp.py [--steps 3] [--iteration 5] [--repeats 300]
        [--batches 1,2,4,8,16,32]

Prints a markdown table; writes benchmarks/results/batched_qp.json.

The solvers other than OSQP come with the ``bench`` extra: ``pip install -c constraints.txt -e ".[bench]"``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import sys
import time
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import scipy.sparse as sp
from qp_solvers import INF, Instance, _full, _Split, make_instance, perturbed, record_problems

from swarmpc.formulation.ocp import OCPSettings
from swarmpc.solvers.qp_local import OSQPBackend, QPAnswer, QPLocalOptions

OUT = Path(__file__).parent / "results" / "batched_qp.json"
SCENARIO = "random 3D, M = 16, seed 0"
"""The closed loop ``qp_solvers.record_problems`` records (named in the output)."""
CASES = 20
"""Perturbed target sets per problem, taken in turn by the repeats."""
WARM_UP = 5
"""Untimed repeats before the timed ones: the first re-solves after setup are not typical."""

Vectors = tuple[np.ndarray, np.ndarray, np.ndarray]


@dataclass(frozen=True)
class QPData:
    """One local QP as set up: P (upper triangle) and A in the shape's sparsity, the vectors, and
    the answer its certificate loop converged to (the first warm start)."""

    P: sp.csc_matrix
    q: np.ndarray
    A: sp.csc_matrix
    lower: np.ndarray
    upper: np.ndarray
    start: np.ndarray


# --- the problems -------------------------------------------------------------------------------
def crowded_group(recorded: list[dict[str, Any]], steps: int, iteration: int) -> list[dict[str, Any]]:
    """The largest group of one MPC step's agents whose problems share a copy count (>= 1), each
    agent's call of ADMM iteration ``iteration`` (its last one if it stopped earlier), started from
    the guess of its first call (later calls carry a solution vector, not named blocks)."""
    calls: dict[Any, list[dict[str, Any]]] = defaultdict(list)
    for call in recorded:
        if call["fixed"] is None:  # repair passes are pinned problems of another shape
            calls[call["key"]].append(call)
    keys = list(calls)  # in order of first call: MPC step by MPC step
    agents = len(keys) // steps
    groups: dict[tuple[int, int], list[dict[str, Any]]] = defaultdict(list)
    for position, key in enumerate(keys):
        first = calls[key][0]
        if first["copies"] == 0 or first["guess"] is None:
            continue
        call = calls[key][min(iteration, len(calls[key]) - 1)]
        groups[(position // agents, first["copies"])].append({**call, "guess": first["guess"]})
    best = max(groups, key=lambda g: (len(groups[g]), g[1], -g[0]))
    return groups[best]


def build_instances(s: OCPSettings, problems: list[dict[str, Any]], count: int, seed: int = 0) -> list[Instance]:
    """The recorded problems as QP instances, then as many variants of them (targets moved,
    normals turned) as make ``count``; all share one sparsity pattern."""
    rng = np.random.default_rng(seed)
    instances = [make_instance(s, p) for p in problems]
    recorded = len(instances)
    while len(instances) < count:
        base = instances[len(instances) % recorded]
        params, lin = perturbed(base, rng, turn_normals=True)
        instances.append(Instance(base.stepper, params, lin, base.start))
    first = instances[0].stepper.problem
    for inst in instances[1:]:
        pb = inst.stepper.problem
        same = all(np.array_equal(getattr(pb, m).indptr, getattr(first, m).indptr)
                   and np.array_equal(getattr(pb, m).indices, getattr(first, m).indices) for m in ("P", "A"))
        assert same, "problems of one shape must share P's and A's sparsity"
    return instances[:count]


def qp_data(instance: Instance) -> QPData:
    pb = instance.stepper.problem
    P_data, q, A_data, lower, upper = instance.data(instance.params, instance.lin)
    return QPData(sp.csc_matrix((P_data, pb.P.indices, pb.P.indptr), shape=pb.P.shape), q,
                  sp.csc_matrix((A_data, pb.A.indices, pb.A.indptr), shape=pb.A.shape), lower, upper, instance.start)


def vector_cases(instance: Instance, rng: np.random.Generator) -> list[Vectors]:
    """``CASES`` sets of (q, l, u) of the instance with its consensus targets moved by ~1 mm."""
    cases = []
    for _ in range(CASES):
        params, _ = perturbed(instance, rng, turn_normals=False)
        _, q, _, lower, upper = instance.data(params, instance.lin)
        cases.append((q, lower, upper))
    return cases


# --- the variants (each: set up once, then update + solve the whole batch) -----------------------
@dataclass
class Answers:
    """One batch's answers, and whether each was reported solved (None: the solver does not say)."""

    x: list[np.ndarray]
    solved: list[bool] | None


class Variant(Protocol):
    name: str
    threads: int

    def setup(self, problems: list[QPData]) -> None: ...

    def step(self, vectors: list[Vectors]) -> Answers: ...


class OneByOne:
    """B OSQP solvers, one per agent, updated and solved in turn (the shipped backend)."""

    name, threads = "OSQP one by one", 1

    def setup(self, problems: list[QPData]) -> None:
        self.backends = [OSQPBackend(QPLocalOptions()) for _ in problems]
        self.answers: list[QPAnswer] = []
        for backend, p in zip(self.backends, problems, strict=True):
            backend.setup(p.P, p.q, p.A, p.lower, p.upper)
            self.answers.append(backend.solve(p.start, None))

    def step(self, vectors: list[Vectors]) -> Answers:
        for i, (backend, (q, lower, upper)) in enumerate(zip(self.backends, vectors, strict=True)):
            backend.update(q, lower, upper, None, None)
            self.answers[i] = backend.solve(self.answers[i].x, self.answers[i].y)
        return Answers([a.x for a in self.answers], [a.solved for a in self.answers])


class BlockDiagonal:
    """One OSQP problem holding the B problems as diagonal blocks; vectors stacked per call."""

    name, threads = "OSQP block-diagonal", 1

    def setup(self, problems: list[QPData]) -> None:
        self.backend = OSQPBackend(QPLocalOptions())
        self.splits = np.cumsum([p.P.shape[0] for p in problems])[:-1]
        P = sp.csc_matrix(sp.block_diag([p.P for p in problems], format="csc"))
        A = sp.csc_matrix(sp.block_diag([p.A for p in problems], format="csc"))
        self.backend.setup(P, np.concatenate([p.q for p in problems]), A, np.concatenate([p.lower for p in problems]),
                           np.concatenate([p.upper for p in problems]))
        self.answer = self.backend.solve(np.concatenate([p.start for p in problems]), None)

    def step(self, vectors: list[Vectors]) -> Answers:
        q, lower, upper = (np.concatenate(part) for part in zip(*vectors, strict=True))
        self.backend.update(q, lower, upper, None, None)
        self.answer = self.backend.solve(self.answer.x, self.answer.y)
        return Answers(np.split(self.answer.x, self.splits), [self.answer.solved] * (len(self.splits) + 1))


class ProxQPBatch:
    """proxsuite's dense ProxQP over a ``BatchQP``: ``solve_in_parallel`` with ``threads`` threads,
    or (``threads`` 0) each QP's own ``solve`` called from Python in turn."""

    def __init__(self, threads: int) -> None:
        self.threads = threads
        self.name = "ProxQP dense, one by one" if threads == 0 else "ProxQP dense, BatchQP + solve_in_parallel"

    def setup(self, problems: list[QPData]) -> None:
        import proxsuite

        self.proxqp = proxsuite.proxqp
        self.splits = [_Split(p.A, p.lower, p.upper) for p in problems]
        self.batch = proxsuite.proxqp.dense.BatchQP(len(problems))  # reserved: no reallocation moves a QP
        for p, split in zip(problems, self.splits, strict=True):
            qp = self.batch.init_qp_in_place(p.P.shape[0], len(split.eq), len(split.ineq))
            qp.settings.eps_abs, qp.settings.eps_rel = 1e-7, 0.0
            qp.settings.initial_guess = proxsuite.proxqp.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
            eq, ineq = split.parts(p.A.data)
            qp.init(_full(p.P).toarray(), p.q, eq.toarray(), p.lower[split.eq], ineq.toarray(),
                    np.maximum(p.lower[split.ineq], -INF), np.minimum(p.upper[split.ineq], INF))
        self.qps = [self.batch.get(i) for i in range(len(problems))]
        self._solve()

    def _solve(self) -> None:
        if self.threads:
            self.proxqp.dense.solve_in_parallel(self.batch, num_threads=self.threads)
        else:
            for qp in self.qps:
                qp.solve()

    def step(self, vectors: list[Vectors]) -> Answers:
        for qp, split, (q, lower, upper) in zip(self.qps, self.splits, vectors, strict=True):
            qp.update(g=q, b=lower[split.eq], l=np.maximum(lower[split.ineq], -INF),
                      u=np.minimum(upper[split.ineq], INF))
        self._solve()
        status = [str(qp.results.info.status) for qp in self.qps]
        return Answers([np.array(qp.results.x) for qp in self.qps],
                       ["SOLVED" in s and "CLOSEST" not in s for s in status])


class CasadiMap:
    """CasADi's ``conic`` with the osqp plugin (options as ``qp_solvers.CasadiConicBackend``
    gives it) mapped over the batch: one call passes every block's matrices and vectors."""

    def __init__(self, threads: int) -> None:
        self.threads = threads
        self.name = "CasADi conic + osqp, Function.map"

    def setup(self, problems: list[QPData]) -> None:
        import casadi as ca

        self.ca = ca
        ones = _full(sp.csc_matrix((np.ones_like(problems[0].P.data), problems[0].P.indices, problems[0].P.indptr),
                                   shape=problems[0].P.shape)).tocoo()
        H_sp = ca.Sparsity.triplet(*ones.shape, ones.row.tolist(), ones.col.tolist())
        A = problems[0].A.sorted_indices()
        A_sp = ca.Sparsity(A.shape[0], A.shape[1], A.indptr.tolist(), A.indices.tolist())
        options: dict[str, Any] = {
            "error_on_fail": False, "warm_start_primal": True, "warm_start_dual": True,
            "osqp": {"verbose": False, "eps_abs": 1e-6, "eps_rel": 1e-6, "polish": True}}
        solver = ca.conic("qp", "osqp", {"h": H_sp, "a": A_sp}, options)
        B = len(problems)
        self.solver = solver.map(B, "thread", self.threads) if self.threads > 1 else solver.map(B, "serial")
        rows, cols = H_sp.get_triplet()
        self.h = ca.horzcat(*[ca.DM(H_sp, _full(p.P).toarray()[rows, cols]) for p in problems])
        self.a = ca.horzcat(*[ca.DM(A_sp, p.A.sorted_indices().data) for p in problems])
        self.x = np.column_stack([p.start for p in problems])
        self.lam: Any = np.zeros((A.shape[0], B))
        self.step([(p.q, p.lower, p.upper) for p in problems])

    def step(self, vectors: list[Vectors]) -> Answers:
        q, lower, upper = (np.column_stack(part) for part in zip(*vectors, strict=True))
        out = self.solver(h=self.h, a=self.a, g=q, lba=lower, uba=upper, x0=self.x, lam_a0=self.lam)
        self.x, self.lam = np.array(out["x"]), out["lam_a"]
        return Answers(list(self.x.T), None)


def variants() -> list[Variant]:
    return [OneByOne(), BlockDiagonal(), ProxQPBatch(0), ProxQPBatch(1), ProxQPBatch(2), CasadiMap(1),
            CasadiMap(2)]


# --- measurement ---------------------------------------------------------------------------------
def measure(problems: list[QPData], cases: list[list[Vectors]], repeats: int) -> list[dict[str, Any]]:
    """Every variant set up on ``problems``, then ``repeats`` rounds in which each variant updates
    and solves the batch once (in an order drawn anew each round), on the targets of case ``r % CASES``."""
    chosen, setup = [], []
    for variant in variants():
        began = time.perf_counter()
        try:
            variant.setup(problems)
        except ImportError as err:  # an optional solver that is not installed is reported, not fatal
            print(f"{variant.name}: not measured ({err})", file=sys.stderr)
            continue
        setup.append(time.perf_counter() - began)
        chosen.append(variant)
    wall: list[list[float]] = [[] for _ in chosen]
    distance: list[float] = [0.0] * len(chosen)
    solved: list[list[bool]] = [[] for _ in chosen]
    order = np.random.default_rng(2)
    for r in range(-WARM_UP, repeats):
        vectors = [per_problem[r % CASES] for per_problem in cases]
        answers: list[Answers | None] = [None] * len(chosen)
        for v in order.permutation(len(chosen)):  # a new order each round: no variant always follows another
            began = time.perf_counter()
            answers[v] = chosen[v].step(vectors)
            if r >= 0:
                wall[v].append(time.perf_counter() - began)
        if r < 0:
            continue
        reference = answers[0]
        assert reference is not None
        for v, answer in enumerate(answers):
            assert answer is not None
            gap = max(float(np.max(np.abs(x - x0))) for x, x0 in zip(answer.x, reference.x, strict=True))
            distance[v] = max(distance[v], gap)
            solved[v] += answer.solved or []
    return [row(v, len(problems), setup[i], wall[i], distance[i], solved[i], wall[0])
            for i, v in enumerate(chosen)]


def row(variant: Variant, batch: int, setup: float, wall: list[float], distance: float, solved: list[bool],
        reference: list[float]) -> dict[str, Any]:
    ms = 1e3 * np.array(wall)
    return {
        "batch": batch, "variant": variant.name, "threads": variant.threads, "setup_ms": 1e3 * setup,
        "median_ms": float(np.median(ms)), "p95_ms": float(np.percentile(ms, 95)),
        "per_agent_median_ms": float(np.median(ms)) / batch, "per_agent_p95_ms": float(np.percentile(ms, 95)) / batch,
        "speedup_vs_one_by_one": float(np.median(reference) / np.median(wall)),
        "max_distance_from_one_by_one": distance,
        "solved": float(np.mean(solved)) if solved else None,
    }


def table(rows: list[dict[str, Any]]) -> str:
    head = ("| B | variant | threads | setup ms | median ms | p95 ms | per agent ms (median / p95) "
            "| speed-up vs one by one | max abs x difference | solved |\n" + "|---" * 10 + "|\n")
    lines = []
    for r in rows:
        solved = "n/a" if r["solved"] is None else f"{100 * r['solved']:.0f}%"
        threads = "loop" if r["threads"] == 0 else str(r["threads"])
        lines.append(
            f"| {r['batch']} | {r['variant']} | {threads} | {r['setup_ms']:.1f} | {r['median_ms']:.3f} "
            f"| {r['p95_ms']:.3f} | {r['per_agent_median_ms']:.3f} / {r['per_agent_p95_ms']:.3f} "
            f"| {r['speedup_vs_one_by_one']:.2f} | {r['max_distance_from_one_by_one']:.1e} | {solved} |")
    return head + "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=3, help="MPC steps of the recording run")
    parser.add_argument("--iteration", type=int, default=5, help="the ADMM iteration whose problems are batched")
    parser.add_argument("--repeats", type=int, default=300, help="timed update + solve rounds per batch size")
    parser.add_argument("--batches", default="1,2,4,8,16,32", help="batch sizes B")
    args = parser.parse_args()
    batches = [int(b) for b in args.batches.split(",")]
    load = os.getloadavg()  # other work on the machine: the threaded variants feel it most
    # OpenMP threads that spin after a parallel region take a core from whatever runs next; passive
    # threads sleep, so each variant pays for its own threads (set before proxsuite loads libgomp).
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    s, recorded = record_problems(args.steps)
    group = crowded_group(recorded, args.steps, args.iteration)
    instances = build_instances(s, group, max(batches))
    rng = np.random.default_rng(1)
    cases = [vector_cases(inst, rng) for inst in instances]
    problems = [qp_data(inst) for inst in instances]
    rows = []
    for batch in batches:
        rows += measure(problems[:batch], cases[:batch], args.repeats)
        print(f"B = {batch} measured", file=sys.stderr, flush=True)
    pb = instances[0].stepper.problem
    shape = {"copies": group[0]["copies"], "variables": int(pb.P.shape[0]), "rows": int(pb.A.shape[0])}
    print(f"Local QPs of {len(group)} agents of one MPC step sharing a shape ({shape['copies']} copies, "
          f"{shape['variables']} variables, {shape['rows']} rows), ADMM iteration {args.iteration}; "
          f"{args.repeats} update + solve rounds per batch size.\n")
    print(table(rows))
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text(json.dumps({
        "command": " ".join(["python benchmarks/batched_qp.py", *sys.argv[1:]]),
        "date": datetime.date.today().isoformat(), "machine": platform.platform(),
        "python": platform.python_version(), "cores": os.cpu_count(), "load_average": [load, os.getloadavg()],
        "omp_wait_policy": os.environ["OMP_WAIT_POLICY"], "scenario": SCENARIO, "steps": args.steps,
        "iteration": args.iteration,
        "repeats": args.repeats, "recorded_agents": len(group), "shape": shape, "rows": rows,
    }, indent=2) + "\n")


if __name__ == "__main__":
    main()
