"""The repair passes' QPs, recorded from a closed loop and re-solved by OSQP and PIQP.

A repair call holds the neighbours' plans fixed (copies pinned): its QP has many rows at their
bounds, and some such QPs are infeasible. One run of random 3D (the bench family, M = 16, the
tuning to start from, QP local step, ``solver.deadline`` 0.1 s, the seed given) is flown with the
QP backends wrapped so that every pinned QP is recorded as it was handed to the solver (P, q, A,
bounds, start); each recorded QP is then solved afresh by every candidate, one after the other,
and timed around the solve call. Per candidate: solved, agreement with the shipped OSQP settings
on solvability, iterations, time of a solved and of a failed call, the sum over all calls, and
the objective's relative deviation from OSQP's where both solved.

    .venv/bin/python benchmarks/repair_qps.py --seed 3 --calls 400
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import scipy.sparse as sp
from batched_qp import QPData as RecordedQP  # (P, q, A, bounds, start): one QP as handed to the solver

from swarmpc.solvers import qp_local
from swarmpc.solvers.qp_local import OSQPBackend, PIQPBackend, QPBackend, QPLocalOptions


class Recording(OSQPBackend):
    """The shipped OSQP backend that keeps the data of each QP it solves."""

    calls: list[RecordedQP] = []

    def setup(self, P: sp.csc_matrix, q: np.ndarray, A: sp.csc_matrix, lower: np.ndarray,
              upper: np.ndarray) -> None:
        self._matrices = (P.copy(), A.copy())
        self._vectors = (q.copy(), lower.copy(), upper.copy())
        super().setup(P, q, A, lower, upper)

    def update(self, q: np.ndarray, lower: np.ndarray, upper: np.ndarray, P_data: np.ndarray | None,
               A_data: np.ndarray | None) -> None:
        P, A = self._matrices
        self._matrices = (_with_values(P, P_data), _with_values(A, A_data))
        self._vectors = (q.copy(), lower.copy(), upper.copy())
        super().update(q, lower, upper, P_data, A_data)

    def solve(self, x: np.ndarray, y: np.ndarray | None) -> qp_local.QPAnswer:
        (P, A), (q, lower, upper) = self._matrices, self._vectors
        Recording.calls.append(RecordedQP(P, q, A, lower, upper, x.copy()))
        return super().solve(x, y)


def _with_values(M: sp.csc_matrix, data: np.ndarray | None) -> sp.csc_matrix:
    return M if data is None else sp.csc_matrix((data.copy(), M.indices, M.indptr), shape=M.shape)


def record(seed: int) -> list[RecordedQP]:
    """The pinned QPs of one deadline run (the agents' repair calls), in call order."""
    sys.path.insert(0, str(Path(__file__).parent))
    import deadline_study

    shipped = qp_local.qp_backend

    def backend(options: QPLocalOptions, pinned: bool = False) -> QPBackend:
        return Recording(options) if pinned else shipped(options, pinned)

    qp_local.qp_backend = backend
    try:
        deadline_study.fly("record", 16, seed, 0.1, {"solver.qp.repair_solver": "osqp"})
    finally:
        qp_local.qp_backend = shipped
    return list(Recording.calls)


CANDIDATES: dict[str, tuple[type, dict[str, Any]]] = {
    "OSQP, eps 1e-6 (the QP local step's settings)": (OSQPBackend, {}),
    "OSQP, eps 1e-4": (OSQPBackend, {"eps_abs": 1e-4, "eps_rel": 1e-4}),
    "PIQP, eps 1e-6": (PIQPBackend, {}),
    "PIQP, eps 1e-4": (PIQPBackend, {"eps_abs": 1e-4, "eps_rel": 1e-4}),
}


def objective(P: sp.csc_matrix, q: np.ndarray, x: np.ndarray) -> float:
    full = P + sp.triu(P, 1).T
    return float(0.5 * x @ (full @ x) + q @ x)


def replay(calls: list[RecordedQP]) -> dict[str, list[tuple[bool, int, float, float]]]:
    """Per candidate and call: (solved, iterations, solve time ms, objective)."""
    out: dict[str, list[tuple[bool, int, float, float]]] = {name: [] for name in CANDIDATES}
    for c in calls:
        for name, (kind, settings) in CANDIDATES.items():
            backend = kind(QPLocalOptions(**settings))
            backend.setup(c.P, c.q, c.A, c.lower, c.upper)
            began = time.perf_counter()
            answer = backend.solve(c.start, None)
            ms = (time.perf_counter() - began) * 1e3
            value = objective(c.P, c.q, answer.x) if answer.solved else np.nan
            out[name].append((answer.solved, answer.iterations, ms, value))
    return out


def table(results: dict[str, list[tuple[bool, int, float, float]]]) -> list[str]:
    reference = results[next(iter(CANDIDATES))]
    lines = ["| QP solver | solved | same verdict as OSQP 1e-6 | iterations (median, solved) | ms per solved call "
             "median / p95 | ms per failed call median | ms all calls | objective vs OSQP 1e-6 (median / max) |",
             "|---|---|---|---|---|---|---|---|"]
    for name, rows in results.items():
        ok = np.array([r[0] for r in rows])
        its, ms = np.array([r[1] for r in rows]), np.array([r[2] for r in rows])
        same = sum(r[0] == s[0] for r, s in zip(rows, reference, strict=True))
        gaps = [abs(r[3] - s[3]) / max(1.0, abs(s[3])) for r, s in zip(rows, reference, strict=True) if r[0] and s[0]]
        failed = f"{np.median(ms[~ok]):.2f}" if (~ok).any() else "–"
        lines.append(f"| {name} | {ok.sum()} of {len(ok)} | {same} | {np.median(its[ok]):.0f} | "
                     f"{np.median(ms[ok]):.2f} / {np.percentile(ms[ok], 95):.2f} | {failed} | {ms.sum():.0f} | "
                     f"{np.median(gaps):.1e} / {max(gaps):.1e} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--calls", type=int, default=400, help="recorded calls replayed (the first ones)")
    args = parser.parse_args()
    calls = record(args.seed)[: args.calls]
    print("\n".join(table(replay(calls))))


if __name__ == "__main__":
    main()
