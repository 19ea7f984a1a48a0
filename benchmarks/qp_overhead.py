"""How much of a QP local step is the QP solver, and how much the Python around it.

Flies one random 3D case of the bench family (default weights, QP local step; no deadline unless
given, so that the run does not depend on the machine's speed) and times every local step of the ADMM iterations and
repair passes: the whole call (:class:`swarmpc.solvers.qp_local.SequentialLocalQP`), the QP
solver's own time inside it (``LoopRecord.solver_time``: OSQP's or PIQP's reported solve, update
and polish time), and the parts of the call by method. Prints per call the medians and totals, and
a fingerprint of the flown states, so two checkouts can be compared call for call:

    PYTHONPATH=CHECKOUT/src .venv/bin/python benchmarks/qp_overhead.py --agents 16 --seed 0 --steps 40 \\
        [--deadline 0.1]

The parts are timed by wrapping methods, which adds about a microsecond per wrapped call.
"""

from __future__ import annotations

import argparse
import hashlib
import time
from collections import defaultdict
from collections.abc import Callable
from typing import Any

import numpy as np

PARTS = {
    "SequentialLocalQP": ("solve", "_start", "_loop", "_result", "_settled"),
    "LocalQP": ("solve",),
    "OSQPBackend": ("update", "solve"),
    "PIQPBackend": ("update", "solve"),
    "Certifier": ("__call__", "rows", "best", "rows_at"),
    "LocalQPProblem": ("linear_cost", "bounds", "constraint_values"),
    "SeparationProof": ("infeasible",),
}
"""The methods of :mod:`swarmpc.solvers.qp_local` timed as parts of a call (those a checkout does not
have are left out, so that checkouts before and after a change compare)."""

FUNCTIONS = ("box_covered",)
"""Module functions of :mod:`swarmpc.solvers.qp_local` timed as parts of a call."""


def _timed(function: Callable[..., Any], label: str, totals: dict[str, list[float]]) -> Callable[..., Any]:
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        began = time.perf_counter()
        try:
            return function(*args, **kwargs)
        finally:
            totals[label].append(time.perf_counter() - began)
    return wrapper


def measure(agents: int, seed: int, steps: int, deadline: float | None = None) -> dict[str, Any]:
    """Fly the case; per-call wall and solver times, the parts' totals, the states' fingerprint
    (``deadline``: ``solver.deadline``, which makes the run depend on the machine's speed)."""
    from swarmpc.bench import BenchCase
    from swarmpc.simulation.loop import simulate
    from swarmpc.solvers import qp_local

    parts: dict[str, list[float]] = defaultdict(list)
    calls: list[tuple[float, float]] = []  # (wall, solver) per SequentialLocalQP.solve
    originals = [(getattr(qp_local, cls), name, getattr(getattr(qp_local, cls), name))
                 for cls, names in PARTS.items() for name in names if hasattr(getattr(qp_local, cls), name)]
    originals += [(qp_local, name, getattr(qp_local, name)) for name in FUNCTIONS]
    for owner, name, function in originals:
        setattr(owner, name, _timed(function, f"{getattr(owner, '__name__', 'qp_local').split('.')[-1]}.{name}", parts))
    whole = qp_local.SequentialLocalQP.solve

    def solve(self: Any, *args: Any, **kwargs: Any) -> Any:
        answer = whole(self, *args, **kwargs)
        calls.append((self.last_record.wall_time, self.last_record.solver_time))
        return answer

    qp_local.SequentialLocalQP.solve = solve  # type: ignore[method-assign]
    try:
        settings = () if deadline is None else (("solver.deadline", deadline),)
        case = BenchCase(family="random", agents=agents, seed=seed, local="qp", max_steps=steps, settings=settings)
        began = time.perf_counter()
        result = simulate(case.scenario())
        wall = time.perf_counter() - began
    finally:
        for owner, name, function in originals:
            setattr(owner, name, function)
    fingerprint = hashlib.sha1(np.ascontiguousarray(result.states).tobytes()).hexdigest()[:12]
    return {"calls": np.array(calls), "parts": parts, "wall": wall, "steps": len(result.records),
            "fingerprint": fingerprint, "iterations": sum(r.admm_iterations or 0 for r in result.records)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--agents", type=int, default=16)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--deadline", type=float, default=None, help="solver.deadline [s] (default: none)")
    args = parser.parse_args()
    m = measure(args.agents, args.seed, args.steps, args.deadline)
    calls = m["calls"]
    python = calls[:, 0] - calls[:, 1]
    print(f"random 3D M = {args.agents}, seed {args.seed}: {m['steps']} steps, {m['iterations']} ADMM iterations, "
          f"run {m['wall']:.1f} s, states {m['fingerprint']}")
    print(f"{len(calls)} local steps: per call median {1e3 * np.median(calls[:, 0]):.3f} ms, of it the QP solver "
          f"{1e3 * np.median(calls[:, 1]):.3f} ms and the Python around it {1e3 * np.median(python):.3f} ms; "
          f"in all {calls[:, 0].sum():.2f} s = {calls[:, 1].sum():.2f} s solver + {python.sum():.2f} s Python")
    print(f"{'part':34s} {'calls':>7s} {'total s':>8s} {'median us':>10s}")
    for label, times in sorted(m["parts"].items(), key=lambda item: -sum(item[1])):
        print(f"{label:34s} {len(times):7d} {sum(times):8.2f} {1e6 * np.median(times):10.1f}")


if __name__ == "__main__":
    main()
