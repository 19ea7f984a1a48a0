"""A small setup-once / solve-many wrapper around CasADi's ``nlpsol``.

Variables, parameters and constraints are declared as named 2-D blocks whose last axis is time,
so a solution (primal and dual) can be unpacked by name and shifted one MPC step forward to
warm-start the next solve. The solver is built once; every later call only changes numbers.
"""

from __future__ import annotations

import functools
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ParamSpec, TypeVar

import casadi as ca
import numpy as np

Arrays = dict[str, np.ndarray]

_P = ParamSpec("_P")
_R = TypeVar("_R")

CASADI_CONSTRUCTION = threading.RLock()
"""Held while CasADi expressions and functions are built (:func:`builds_casadi`).

CasADi's symbolic layer is not thread-safe: its expression nodes are reference-counted without
atomics, and two threads building problems at once can abort the process (seen with the thread
executor, whose agents build their local problems on first use, two at a time). It is the one
piece of process-wide state here because the library's is: any thread of the process may build.
Evaluating built functions needs no lock."""


def builds_casadi(build: Callable[_P, _R]) -> Callable[_P, _R]:
    """``build`` run under :data:`CASADI_CONSTRUCTION` (one thread of the process at a time)."""

    @functools.wraps(build)
    def serialised(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        with CASADI_CONSTRUCTION:
            return build(*args, **kwargs)

    return serialised


@dataclass(frozen=True)
class _Block:
    name: str
    shape: tuple[int, int]
    start: int

    @property
    def size(self) -> int:
        return self.shape[0] * self.shape[1]

    @property
    def stop(self) -> int:
        return self.start + self.size


class _Layout:
    """Named blocks laid end to end in one column vector (column-major, like CasADi)."""

    def __init__(self) -> None:
        self.blocks: dict[str, _Block] = {}
        self.size = 0

    def add(self, name: str, shape: tuple[int, int]) -> _Block:
        if name in self.blocks:
            raise ValueError(f"duplicate block {name!r}")
        block = _Block(name, shape, self.size)
        self.blocks[name] = block
        self.size += block.size
        return block

    def pack(self, values: dict[str, Any], default: np.ndarray | float = 0.0) -> np.ndarray:
        out = (np.full(self.size, default, dtype=float) if np.ndim(default) == 0
               else np.array(np.broadcast_to(default, (self.size,)), dtype=float))
        for name, value in values.items():
            block = self.blocks[name]
            array = np.asarray(value, float)
            if array.ndim <= 1 and array.size in (1, block.size):
                out[block.start : block.stop] = array  # a vector already in CasADi's order, or a scalar
            elif array.shape == block.shape:
                out[block.start : block.stop] = array.ravel(order="F")
            elif array.ndim == 1 and array.size == block.shape[0]:  # one column for every column
                out[block.start : block.stop] = np.broadcast_to(array[:, None], block.shape).ravel(order="F")
            else:
                out[block.start : block.stop] = np.broadcast_to(array, block.shape).ravel(order="F")
        return out

    def unpack(self, vector: np.ndarray) -> Arrays:
        vector = np.asarray(vector, float).ravel()
        return {
            name: vector[b.start : b.stop].reshape(b.shape, order="F") for name, b in self.blocks.items()
        }


def shift_blocks(values: Arrays) -> Arrays:
    """Every block moved one step back in time along its last axis, the last column repeated."""
    shifted = {}
    for name, value in values.items():
        if value.shape[1] > 1:
            value = np.concatenate([value[:, 1:], value[:, -1:]], axis=1)
        shifted[name] = value
    return shifted


@dataclass(frozen=True)
class NLPSolution:
    """Result of one NLP solve, with everything needed to warm-start the next."""

    x: Arrays
    x_vec: np.ndarray
    lam_x: np.ndarray
    lam_g: np.ndarray
    cost: float
    success: bool
    status: str
    iterations: int
    solve_time: float


class ProblemBuilder:
    """Collects named variables, parameters, constraints and a cost, then builds one solver."""

    def __init__(self) -> None:
        self._x = _Layout()
        self._p = _Layout()
        self._g = _Layout()
        self._x_syms: list[ca.SX] = []
        self._p_syms: list[ca.SX] = []
        self._g_exprs: list[ca.SX] = []
        self._lbx: dict[str, np.ndarray] = {}
        self._ubx: dict[str, np.ndarray] = {}
        self._lbg: dict[str, np.ndarray] = {}
        self._ubg: dict[str, np.ndarray] = {}
        self.cost: ca.SX = ca.SX(0)

    def variable(self, name: str, rows: int, cols: int = 1, lb: Any = -np.inf, ub: Any = np.inf) -> ca.SX:
        sym = ca.SX.sym(name, rows, cols)
        self._x.add(name, (rows, cols))
        self._x_syms.append(sym)
        self._lbx[name] = np.broadcast_to(np.asarray(lb, float), (rows, cols))
        self._ubx[name] = np.broadcast_to(np.asarray(ub, float), (rows, cols))
        return sym

    def parameter(self, name: str, rows: int, cols: int = 1) -> ca.SX:
        sym = ca.SX.sym(name, rows, cols)
        self._p.add(name, (rows, cols))
        self._p_syms.append(sym)
        return sym

    def constrain(self, name: str, expr: ca.SX, lb: Any, ub: Any) -> None:
        shape = (expr.shape[0], expr.shape[1])
        self._g.add(name, shape)
        self._g_exprs.append(expr)
        self._lbg[name] = np.broadcast_to(np.asarray(lb, float), shape)
        self._ubg[name] = np.broadcast_to(np.asarray(ub, float), shape)

    def build(
        self, label: str, plugin: str = "ipopt", options: dict[str, Any] | None = None,
        warm_options: dict[str, Any] | None = None,
    ) -> CompiledNLP:
        """Build the solver; with ``warm_options`` also a second one (same problem, those
        options on top) used for calls that pass the previous solve's multipliers."""
        x = ca.vertcat(*[ca.vec(s) for s in self._x_syms])
        p = ca.vertcat(*[ca.vec(s) for s in self._p_syms]) if self._p_syms else ca.SX(0, 1)
        g = ca.vertcat(*[ca.vec(e) for e in self._g_exprs]) if self._g_exprs else ca.SX(0, 1)
        problem = {"x": x, "p": p, "f": self.cost, "g": g}
        solver = ca.nlpsol(label, plugin, problem, options or {})
        warm_solver = None
        if warm_options is not None:
            warm_solver = ca.nlpsol(f"{label}_warm", plugin, problem, {**(options or {}), **warm_options})
        return CompiledNLP(
            solver=solver,
            warm_solver=warm_solver,
            constraint_function=ca.Function(f"{label}_g", [x, p], [g]),
            x_layout=self._x,
            p_layout=self._p,
            g_layout=self._g,
            lbx=self._x.pack(self._lbx),
            ubx=self._x.pack(self._ubx),
            lbg=self._g.pack(self._lbg),
            ubg=self._g.pack(self._ubg),
        )


@dataclass(frozen=True)
class CompiledNLP:
    """A built solver plus the layouts that map names to vector slices."""

    solver: ca.Function
    constraint_function: ca.Function
    x_layout: _Layout
    p_layout: _Layout
    g_layout: _Layout
    lbx: np.ndarray
    ubx: np.ndarray
    lbg: np.ndarray
    ubg: np.ndarray
    warm_solver: ca.Function | None = None

    def solve(
        self,
        params: dict[str, Any],
        guess: dict[str, Any] | np.ndarray,
        lam_x: np.ndarray | None = None,
        lam_g: np.ndarray | None = None,
        fixed: dict[str, Any] | None = None,
    ) -> NLPSolution:
        """Solve for parameter values ``params`` from a primal guess (and optional duals).

        ``fixed`` pins named variable blocks to given values for this call only.
        """
        x0 = guess if isinstance(guess, np.ndarray) else self.x_layout.pack(guess)
        lbx, ubx = self.lbx, self.ubx
        if fixed:
            pinned = self.x_layout.pack(fixed, default=np.nan)
            mask = ~np.isnan(pinned)
            lbx, ubx = np.where(mask, pinned, lbx), np.where(mask, pinned, ubx)
        args: dict[str, Any] = {
            "x0": np.clip(x0, lbx, ubx),
            "p": self.p_layout.pack(params),
            "lbx": lbx,
            "ubx": ubx,
            "lbg": self.lbg,
            "ubg": self.ubg,
        }
        solver = self.solver
        if lam_x is not None:
            args["lam_x0"] = lam_x
        if lam_g is not None:
            args["lam_g0"] = lam_g
            if self.warm_solver is not None:
                solver = self.warm_solver
        started = time.perf_counter()
        out = solver(**args)
        elapsed = time.perf_counter() - started
        stats = solver.stats()
        x_vec = np.asarray(out["x"]).ravel()
        lam_g_vec = np.asarray(out["lam_g"]).ravel()
        finite = bool(np.all(np.isfinite(x_vec)))
        return NLPSolution(
            x=self.x_layout.unpack(x_vec),
            x_vec=x_vec,
            lam_x=np.asarray(out["lam_x"]).ravel(),
            lam_g=lam_g_vec,
            cost=float(out["f"]),
            success=bool(stats.get("success", False)) and finite,
            status=str(stats.get("return_status", "unknown")),
            iterations=int(stats.get("iter_count", -1)),
            solve_time=elapsed,
        )

    def constraint_violation(self, x_vec: np.ndarray, params: dict[str, Any]) -> float:
        """Largest bound or constraint violation of a primal point (for checks and tests)."""
        g = np.asarray(self.constraint_function(x_vec, self.p_layout.pack(params))).ravel()
        gaps = [self.lbg - g, g - self.ubg, self.lbx - x_vec, x_vec - self.ubx]
        return float(max(0.0, *(np.max(gap) if gap.size else 0.0 for gap in gaps)))
