"""Run results: a frozen result object and its run folder, written atomically.

A run folder holds ``summary.json``, ``trajectory.npz`` and ``scenario.yaml`` (the contract of
:mod:`swarmpc.simulation.contract`, published as ``docs/run-folder-reference.md``;
``trajectory.npz`` adds ``disturbances`` when the run injected process noise; its ``poses`` and
``footprints`` place each agent's footprint in the plane, :func:`agent_poses`),
``steps.npz`` (per-step solver records: ``failures`` = failed solve calls, ``fallback`` = which
agents applied a safe fallback plan, ``repaired`` = ADMM repair pass, ``critical_path_s`` = the
step's compute with one core per agent, ``deadline_stop`` = ADMM cut short by ``solver.deadline``,
``local_fallbacks`` = local solves the QP local step handed to IPOPT)
and, for ADMM, ``admm.npz`` (residual histories, ``copies``: how many neighbours each agent held
per step, and ``planes``: how many separating planes it kept to). It is written under a
temporary name beside the target and renamed into place when complete, so a reader never
sees a half-written folder; a complete folder carries a marker file, and only such folders are
ever replaced (:mod:`swarmpc.simulation.outdir`).
"""

from __future__ import annotations

import json
import math
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from swarmpc.config import Scenario, scenario_to_yaml
from swarmpc.model.agent_model import AgentModel
from swarmpc.simulation.metrics import summarize
from swarmpc.simulation.outdir import OutputError, RunFolderTarget, write_marker
from swarmpc.simulation.quality import quality_summary
from swarmpc.simulation.rundata import point_footprints, point_poses
from swarmpc.solvers.base import PlanStep


@dataclass(frozen=True)
class StepRecord:
    """What one MPC step's solve reported."""

    wall_time: float
    agent_times: np.ndarray
    failures: int
    fallback: np.ndarray
    max_slack: float
    admm_iterations: int | None
    repaired: bool
    primal_residuals: tuple[float, ...]
    dual_residuals: tuple[float, ...]
    rho: tuple[float, ...]
    copies: np.ndarray | None = None
    """(M,) neighbours' copies each agent held (ADMM), None for a centralised solve."""
    planes: np.ndarray | None = None
    """(M,) separating planes each agent kept to (ADMM), None for a centralised solve."""
    critical_path: float | None = None
    """Seconds of compute on the step's critical path (:attr:`PlanStep.critical_path`); None: not
    measured, read as ``wall_time`` (see :attr:`critical_path_s`)."""
    deadline_stop: bool = False
    """ADMM stopped iterating for ``solver.deadline`` (:attr:`PlanStep.deadline_stop`)."""
    local_fallbacks: int = 0
    """Local solves the QP local step failed and IPOPT answered (:attr:`PlanStep.local_fallbacks`)."""

    @property
    def critical_path_s(self) -> float:
        """The critical path [s]; a solver that does not measure it is taken to be all on it."""
        return self.wall_time if self.critical_path is None else self.critical_path

    @classmethod
    def from_plan(cls, plan: PlanStep) -> StepRecord:
        return cls(
            wall_time=plan.wall_time,
            agent_times=np.asarray(plan.agent_times, float),
            failures=plan.failures,
            fallback=np.asarray(plan.fallback, bool),
            max_slack=plan.max_slack,
            admm_iterations=plan.admm_iterations,
            repaired=plan.repaired,
            primal_residuals=tuple(plan.primal_residuals),
            dual_residuals=tuple(plan.dual_residuals),
            rho=tuple(plan.rho_history),
            copies=None if plan.copies is None else np.asarray(plan.copies, int),
            planes=None if plan.planes is None else np.asarray(plan.planes, int),
            critical_path=plan.critical_path,
            deadline_stop=plan.deadline_stop,
            local_fallbacks=int(plan.local_fallbacks),
        )


@dataclass(frozen=True)
class RunResult:
    """A finished (or interrupted) closed-loop run: arrays, per-step records and the summary."""

    scenario: Scenario
    t: np.ndarray
    states: np.ndarray
    inputs: np.ndarray
    records: tuple[StepRecord, ...]
    summary: dict[str, Any]
    deadlock_events: tuple[tuple[int, int], ...] = ()
    extras: dict[str, Any] = field(default_factory=dict)
    disturbances: np.ndarray | None = None

    @classmethod
    def create(
        cls,
        scenario: Scenario,
        states: np.ndarray,
        inputs: np.ndarray,
        records: Sequence[StepRecord],
        deadlock_events: Sequence[tuple[int, int]],
        interrupted: bool,
        wall_time: float,
        rrt_stats: dict[str, int] | None = None,
        disturbances: np.ndarray | None = None,
    ) -> RunResult:
        """Summarise a run; ``disturbances`` (T, M, 2d) is the process noise it injected, if any."""
        is_admm = scenario.solver.method == "admm"
        iterations = np.array([r.admm_iterations or 0 for r in records]) if is_admm else None
        summary = summarize(
            scenario,
            scenario.solver.method,
            states,
            inputs,
            step_times=np.array([r.wall_time for r in records]),
            admm_iterations=iterations,
            solver_failures=sum(r.failures for r in records),
            max_slack=max((r.max_slack for r in records), default=0.0),
            deadlock_events=len(deadlock_events),
            interrupted=interrupted,
            wall_time=wall_time,
        )
        summary["fallback_steps"] = int(sum(r.fallback.any() for r in records))
        summary["fallback_agent_steps"] = int(sum(int(r.fallback.sum()) for r in records))
        summary["local_fallbacks"] = int(sum(r.local_fallbacks for r in records))
        summary["disturbance"] = (
            scenario.disturbance.model_dump() if scenario.disturbance != type(scenario.disturbance)() else None
        )
        summary["admm_repairs"] = int(sum(r.repaired for r in records)) if is_admm else None
        if is_admm:
            summary["admm_tol"] = scenario.solver.tol
            summary["rho"] = scenario.solver.rho
            after_first = iterations[1:] if iterations is not None and len(iterations) > 1 else iterations
            summary["admm_iterations_after_first"] = (
                float(np.median(after_first)) if after_first is not None and len(after_first) else None
            )
        if rrt_stats is not None:
            summary["rrt"] = rrt_stats
        summary["agent_step_time_ms"] = _agent_time_stats(records)
        summary.update(deadline_summary(records, scenario))
        summary.update(quality_summary(states, scenario.goal_states(), scenario.dt, scenario.stop.goal_tolerance))
        return cls(
            scenario=scenario,
            t=np.arange(states.shape[0]) * scenario.dt,
            states=states,
            inputs=inputs,
            records=tuple(records),
            summary=summary,
            deadlock_events=tuple(deadlock_events),
            disturbances=None if disturbances is None else np.asarray(disturbances, float),
        )

    @property
    def positions(self) -> np.ndarray:
        return self.states[:, :, : self.scenario.dim]

    def residual_histories(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(primal, dual, rho), each (steps, longest) padded with NaN."""
        longest = max((len(r.primal_residuals) for r in self.records), default=0)
        shape = (len(self.records), longest)
        primal, dual, rho = np.full(shape, np.nan), np.full(shape, np.nan), np.full(shape, np.nan)
        for k, record in enumerate(self.records):
            n = len(record.primal_residuals)
            primal[k, :n] = record.primal_residuals
            dual[k, :n] = record.dual_residuals
            rho[k, :n] = record.rho
        return primal, dual, rho


def _agent_time_stats(records: Sequence[StepRecord]) -> dict[str, float | None]:
    if not records:
        return {"median": None, "p95": None}
    times = np.concatenate([r.agent_times for r in records]) * 1000.0
    return {"median": float(np.median(times)), "p95": float(np.percentile(times, 95))}


def deadline_budget(scenario: Scenario) -> float:
    """The critical-path budget a step is counted against [s]: ``solver.deadline``, or the sample
    period dt when the scenario sets none (a step slower than dt is late whether or not ADMM was
    told to stop for it)."""
    return scenario.dt if scenario.solver.deadline is None else scenario.solver.deadline


def deadline_summary(records: Sequence[StepRecord], scenario: Scenario) -> dict[str, Any]:
    """``critical_path_ms`` (median, p95, p99, max over the steps; None when there are none),
    ``deadline_s`` (:func:`deadline_budget`), ``deadline_misses`` (steps whose critical path
    exceeded it) and ``deadline_stops`` (steps ADMM ended early for ``solver.deadline``)."""
    path = np.array([r.critical_path_s for r in records]) * 1000.0
    budget = deadline_budget(scenario)
    stats: dict[str, float | None] = dict.fromkeys(("median", "p95", "p99", "max"))
    if path.size:
        stats = {"median": float(np.median(path)), "p95": float(np.percentile(path, 95)),
                 "p99": float(np.percentile(path, 99)), "max": float(path.max())}
    return {
        "critical_path_ms": stats,
        "deadline_s": budget,
        "deadline_misses": int(np.sum(path > 1000.0 * budget)),
        "deadline_stops": int(sum(r.deadline_stop for r in records)),
    }


Writer = Callable[[RunResult, Path], None]


def write_run(
    result: RunResult,
    out_dir: str | Path | RunFolderTarget,
    extra_writers: Sequence[Writer] = (),
    overwrite: bool = False,
) -> Path:
    """Write the run folder under a temporary name and move it into place when complete.

    ``out_dir`` is a path or a :class:`~swarmpc.simulation.outdir.RunFolderTarget` reserved before
    the run. An existing path there is replaced only when it is a swarmpc run folder and
    ``overwrite`` is set (:class:`OutputError` otherwise). ``extra_writers`` add files (figures)
    before the move. When the folder cannot be written, the run is written to the system's
    temporary folder instead and the error says where.
    """
    target = out_dir if isinstance(out_dir, RunFolderTarget) else RunFolderTarget(out_dir, overwrite)
    try:
        _write_contents(result, target.staging)
        for writer in extra_writers:
            writer(result, target.staging)
        write_marker(target.staging)
    except OSError as err:
        target.discard()
        raise OutputError(
            f"{target.target}: cannot write the run folder ({err.strerror or err}); {_rescue(result)}"
        ) from None
    except BaseException:
        target.discard()
        raise
    return target.commit()


def expected_run_bytes(scn: Scenario) -> int:
    """An upper estimate of a run folder's size before compression: the arrays of a run that
    lasts ``stop.max_steps`` (trajectory, inputs, per-step and per-agent records)."""
    m, d, steps = scn.num_agents, scn.dim, scn.stop.max_steps
    per_step = m * (2 * d + d + 2 * d + 3) + 4 * m + 8
    return 8 * (steps + 1) * per_step


def _rescue(result: RunResult) -> str:
    """Write the run to a new folder in the system's temporary folder; say where (or that not)."""
    try:
        folder = Path(tempfile.mkdtemp(prefix=f"swarmpc-{result.scenario.name}-"))
        _write_contents(result, folder)
        write_marker(folder)
    except OSError as err:
        return f"no copy could be kept either ({err.strerror or err})"
    return f"the run is kept in {folder}"


def json_safe(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None, so the JSON is strictly valid."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _per_agent(models: AgentModel | Sequence[AgentModel], agents: int) -> Sequence[AgentModel]:
    """One model per agent: ``models`` itself when it is a sequence of ``agents`` models, else
    the one model repeated."""
    if isinstance(models, Sequence):
        if len(models) != agents:
            raise ValueError(f"expected {agents} agent models, got {len(models)}")
        return models
    return (models,) * agents


def agent_poses(models: AgentModel | Sequence[AgentModel], states: np.ndarray) -> np.ndarray:
    """(..., M, 3) pose [x, y, theta] of each agent's footprint centre in the plane.

    ``states`` is (..., M, n); ``models`` is one model for every agent or one per agent. A model
    with a ``pose(states) -> (..., 3)`` method (a car, whose footprint centre is not its
    reference point) gives its own; any other agent is a point agent: its position's first two
    coordinates with heading 0 (:func:`~swarmpc.simulation.rundata.point_poses`), in 3D too.
    """
    states = np.asarray(states, float)
    per_agent = _per_agent(models, states.shape[-2])
    poses = np.empty((*states.shape[:-1], 3))
    for i, model in enumerate(per_agent):
        own = getattr(model, "pose", None)
        agent_states = states[..., i, :]
        poses[..., i, :] = own(agent_states) if callable(own) else point_poses(model.position(agent_states))
    return poses


def agent_footprints(models: AgentModel | Sequence[AgentModel], bodies: np.ndarray) -> np.ndarray:
    """(M, 2) footprint [length, width] of each agent in the plane.

    ``bodies`` (M, d) are the body half-sizes per axis; ``models`` is one model for every agent or
    one per agent. A model with a ``footprint`` (length, width) gives its rectangle; a point
    agent's footprint is the box its body keeps clear on the x and y axes, 2 x its half-sizes
    there (:func:`~swarmpc.simulation.rundata.point_footprints`).
    """
    bodies = np.asarray(bodies, float)
    footprints = point_footprints(bodies)
    for i, model in enumerate(_per_agent(models, bodies.shape[0])):
        own = getattr(model, "footprint", None)
        if own is not None:
            footprints[i] = np.asarray(own, float).reshape(2)
    return footprints


def _write_contents(result: RunResult, folder: Path) -> None:
    scn = result.scenario
    (folder / "scenario.yaml").write_text(scenario_to_yaml(scn))
    summary = json.dumps(json_safe(result.summary), indent=2, allow_nan=False)
    (folder / "summary.json").write_text(summary + "\n")
    delta = np.asarray(scn.delta, float)
    arrays: dict[str, np.ndarray] = {
        "t": result.t,
        "states": result.states,
        "inputs": result.inputs,
        "goals": scn.goal_states(),
        "delta": delta,
        "dt": np.asarray(scn.dt),
        "bodies": scn.bodies,
        "poses": agent_poses(scn.agent_models(), result.states),
        "footprints": agent_footprints(scn.agent_models(), scn.bodies),
    }
    if result.disturbances is not None:
        # states[k+1] = f(states[k], inputs[k]) + disturbances[k]
        arrays["disturbances"] = result.disturbances
    # The stubs cannot tell that no array is named like the keyword allow_pickle (numpy >= 2.1).
    np.savez_compressed(folder / "trajectory.npz", **arrays)  # type: ignore[arg-type]
    records = result.records
    m = scn.num_agents
    np.savez_compressed(
        folder / "steps.npz",
        step_time_s=np.array([r.wall_time for r in records]),
        agent_time_s=np.array([r.agent_times for r in records]).reshape(len(records), m),
        failures=np.array([r.failures for r in records], int),
        fallback=np.array([r.fallback for r in records], bool).reshape(len(records), m),
        max_slack=np.array([r.max_slack for r in records]),
        repaired=np.array([r.repaired for r in records], bool),
        critical_path_s=np.array([r.critical_path_s for r in records], float),
        deadline_stop=np.array([r.deadline_stop for r in records], bool),
        local_fallbacks=np.array([r.local_fallbacks for r in records], int),
    )
    if scn.solver.method == "admm":
        primal, dual, rho = result.residual_histories()
        np.savez_compressed(
            folder / "admm.npz",
            primal=primal,
            dual=dual,
            rho=rho,
            iterations=np.array([r.admm_iterations or 0 for r in records], int),
            copies=np.array([r.copies if r.copies is not None else np.zeros(m, int) for r in records],
                            int).reshape(len(records), m),
            planes=np.array([r.planes if r.planes is not None else np.zeros(m, int) for r in records],
                            int).reshape(len(records), m),
        )
