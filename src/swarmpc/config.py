"""Scenario configuration: immutable, validated pydantic models and YAML loading.

Everything that runs is described by a :class:`Scenario`. It is validated as a whole before
anything is built, so a bad file fails early with one line that names the field
(:class:`ScenarioError`), never with a traceback from deep inside a solver.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

Number = float
Matrix = list[list[float]]
ScalarOrMatrix = float | Matrix
ScalarOrVector = float | list[float]


class ScenarioError(ValueError):
    """A scenario that cannot run; the message is one line naming the offending field."""


def _check_finite(value: Any, path: str = "") -> None:
    """Raise ValueError when any number nested in ``value`` is NaN or infinite."""
    if isinstance(value, bool) or value is None:
        return
    if isinstance(value, (int, float)):
        if not math.isfinite(value):
            raise ValueError(f"must be finite, got {value}")
        return
    if isinstance(value, (list, tuple)):
        for item in value:
            _check_finite(item, path)


class _Frozen(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    @model_validator(mode="before")
    @classmethod
    def _reject_non_finite(cls, data: Any) -> Any:
        if isinstance(data, dict):
            for key, value in data.items():
                try:
                    _check_finite(value)
                except ValueError as err:
                    raise ValueError(f"{key}: {err}") from None
        return data


class Weights(_Frozen):
    """Quadratic cost weights: scalars (times identity) or full matrices."""

    Q: ScalarOrMatrix = 0.1
    R: ScalarOrMatrix = 1.0
    Qf: ScalarOrMatrix = 1.0


class Workspace(_Frozen):
    """Axis-aligned bounds on every agent's position."""

    lower: list[float]
    upper: list[float]

    @model_validator(mode="after")
    def _ordered(self) -> Workspace:
        if len(self.lower) != len(self.upper):
            raise ValueError("lower and upper differ in length")
        if any(lo >= hi for lo, hi in zip(self.lower, self.upper)):
            raise ValueError("lower must be below upper on every axis")
        return self


class Limits(_Frozen):
    """Optional actuator and speed limits (None: unbounded)."""

    accel: ScalarOrVector | None = Field(default=None, description="per-axis |a| bound [m/s^2]")
    speed: float | None = Field(default=None, description="bound on the speed norm [m/s]")

    @field_validator("accel")
    @classmethod
    def _positive_accel(cls, value: ScalarOrVector | None) -> ScalarOrVector | None:
        values = [value] if isinstance(value, (int, float)) else (value or [])
        if any(v <= 0 for v in values):
            raise ValueError("must be > 0")
        return value

    @field_validator("speed")
    @classmethod
    def _positive_speed(cls, value: float | None) -> float | None:
        if value is not None and value <= 0:
            raise ValueError("must be > 0")
        return value


class BoxSpec(_Frozen):
    center: list[float]
    half_size: list[float]

    @field_validator("half_size")
    @classmethod
    def _positive(cls, value: list[float]) -> list[float]:
        if any(v <= 0 for v in value):
            raise ValueError("every half-size must be > 0")
        return value


class PolytopeSpec(_Frozen):
    G: Matrix
    g: list[float]

    @model_validator(mode="after")
    def _shapes(self) -> PolytopeSpec:
        if len(self.G) == 0:
            raise ValueError("G has no rows")
        if len(self.G) != len(self.g):
            raise ValueError(f"G has {len(self.G)} rows but g has {len(self.g)} entries")
        widths = {len(row) for row in self.G}
        if len(widths) != 1:
            raise ValueError("rows of G differ in length")
        if any(np.linalg.norm(row) == 0 for row in self.G):
            raise ValueError("G has a zero row")
        return self


class Obstacle(_Frozen):
    """A static convex obstacle: an axis-aligned box or a polytope {p : G p <= g}."""

    box: BoxSpec | None = None
    polytope: PolytopeSpec | None = None

    @model_validator(mode="after")
    def _exactly_one(self) -> Obstacle:
        if (self.box is None) == (self.polytope is None):
            raise ValueError("give exactly one of 'box' or 'polytope'")
        return self

    def halfspaces(self, dim: int) -> tuple[np.ndarray, np.ndarray]:
        """The obstacle as (G, g) with {p : G p <= g}."""
        if self.box is not None:
            center = np.asarray(self.box.center, float)
            half = np.asarray(self.box.half_size, float)
            eye = np.eye(dim)
            return np.vstack([eye, -eye]), np.concatenate([center + half, half - center])
        assert self.polytope is not None
        return np.asarray(self.polytope.G, float), np.asarray(self.polytope.g, float)


class Agent(_Frozen):
    """An agent's start and goal: a position, or a full state [position, velocity]."""

    start: list[float]
    goal: list[float]


class SolverConfig(_Frozen):
    """How each MPC step is solved."""

    method: Literal["admm", "centralized"] = "admm"
    rho: float = Field(default=10.0, gt=0, description="ADMM penalty parameter")
    max_iter: int = Field(default=100, ge=1, description="ADMM iteration cap per MPC step")
    tol: float = Field(default=1e-3, gt=0, description="ADMM primal/dual residual tolerance [m] (the random and spread built-ins use 0.005)")
    adaptive_rho: bool = Field(default=False, description="residual balancing of rho")
    coupling_margin: float | None = Field(
        default=None, ge=0,
        description="ADMM couples pairs whose guesses come within delta + d_min + this [m]; "
        "others are coupled on demand (smaller: less work in dense swarms); "
        "null: 0.2 plus 0.1 s times the pair's closing speed with hard constraints, 0.5 with soft ones",
    )
    relaxation: float = Field(
        default=1.0, gt=0, lt=2,
        description="ADMM over-relaxation alpha: the consensus averages alpha * answer + (1 - alpha) * "
        "previous consensus (1: plain ADMM, as in the paper)",
    )
    component_stop: bool = Field(
        default=False,
        description="ADMM also stops each connected group of coupled agents once its own residuals meet tol "
        "(its agents are not solved again in the step while other groups iterate); false: only the "
        "residuals over all blocks decide",
    )
    plane_margin: float | None = Field(
        default=None, ge=0,
        description="ADMM keeps a coupled pair apart by fixed separating planes instead of copies when its "
        "guesses clear the delta box by d_min + this [m] on some axis at every constrained step "
        "(no consensus for that pair); null: every coupled pair holds copies",
    )
    reuse_tol: float = Field(
        default=1e-4, ge=0,
        description="within an MPC step, an ADMM agent whose consensus targets moved less than this [m] "
        "since its last solve sends its last answer again instead of solving (0: always solve)",
    )
    initial_guess: Literal["auto", "rrt", "straight", "shifted"] = "auto"
    rrt_time_budget: float = Field(default=0.05, gt=0, description="seconds per RRT plan")
    seed_duals: bool = Field(
        default=True, description="seed the OBCA certificates from the guess's geometry (else 0)"
    )


class StopConfig(_Frozen):
    """When the closed loop ends."""

    goal_tolerance: float = Field(default=0.05, gt=0, description="position tolerance [m]")
    speed_tolerance: float = Field(default=0.1, gt=0, description="speed tolerance at the goal")
    max_steps: int = Field(default=400, ge=1)


class Disturbance(_Frozen):
    """Uncertainty injected into the closed loop (all zero: off, the nominal simulation).

    Process noise is added to the true state after every step, measurement noise to the state the
    planner sees; both are Gaussian, independent per component, drawn from a generator seeded by
    the scenario's ``seed``. ``tightening`` is a safety margin added to delta in the planner only
    (collisions are still counted against the true delta).
    """

    process_position_std: float = Field(
        default=0.0, ge=0, description="process noise std per position component, added each step [m]"
    )
    process_velocity_std: float = Field(
        default=0.0, ge=0, description="process noise std per velocity component, added each step [m/s]"
    )
    measurement_position_std: float = Field(
        default=0.0, ge=0, description="measurement noise std per position component the planner sees [m]"
    )
    measurement_velocity_std: float = Field(
        default=0.0, ge=0, description="measurement noise std per velocity component the planner sees [m/s]"
    )
    tightening: float = Field(
        default=0.0, ge=0, description="safety margin added to delta in the planner only [m]"
    )

    @property
    def has_process_noise(self) -> bool:
        return self.process_position_std > 0 or self.process_velocity_std > 0

    @property
    def has_measurement_noise(self) -> bool:
        return self.measurement_position_std > 0 or self.measurement_velocity_std > 0


class Scenario(_Frozen):
    """A complete, validated multi-agent scenario (design.md section 8)."""

    name: str = "unnamed"
    dim: int = 2
    dt: float = 0.1
    horizon: int = 10
    delta: ScalarOrVector = 0.3
    collision: Literal["hard", "soft"] = "hard"
    d_min: float = 0.05
    kappa: float = 1000.0
    discretization: Literal["euler", "zoh"] = "euler"
    seed: int = Field(default=0, ge=0)
    weights: Weights = Weights()
    workspace: Workspace | None = None
    limits: Limits = Limits()
    obstacles: list[Obstacle] = []
    agents: list[Agent]
    solver: SolverConfig = SolverConfig()
    stop: StopConfig = StopConfig()
    disturbance: Disturbance = Field(
        default=Disturbance(),
        description="process/measurement noise (seeded by `seed`) and planner tightening; default off",
    )

    @field_validator("dim")
    @classmethod
    def _dim(cls, value: int) -> int:
        if value not in (2, 3):
            raise ValueError(f"must be 2 or 3, got {value}")
        return value

    @field_validator("dt", "kappa")
    @classmethod
    def _positive(cls, value: float) -> float:
        if value <= 0:
            raise ValueError(f"must be > 0, got {value}")
        return value

    @field_validator("horizon")
    @classmethod
    def _horizon(cls, value: int) -> int:
        if value < 2:
            raise ValueError(f"must be >= 2, got {value}")
        return value

    @field_validator("delta")
    @classmethod
    def _delta(cls, value: ScalarOrVector) -> ScalarOrVector:
        values = [value] if isinstance(value, (int, float)) else value
        if any(v <= 0 for v in values):
            raise ValueError(f"must be > 0, got {value}")
        return value

    @field_validator("agents")
    @classmethod
    def _agents(cls, value: list[Agent]) -> list[Agent]:
        if not value:
            raise ValueError("needs at least one agent")
        return value

    @model_validator(mode="after")
    def _consistent(self) -> Scenario:
        for error in _consistency_errors(self):
            raise ValueError(error)
        return self

    # ----------------------------------------------------------------- derived views
    @property
    def num_agents(self) -> int:
        return len(self.agents)

    @property
    def state_dim(self) -> int:
        return 2 * self.dim

    @property
    def delta_vector(self) -> np.ndarray:
        """Half-size of the box around each agent, one entry per axis."""
        return np.broadcast_to(np.asarray(self.delta, float), (self.dim,)).copy()

    def start_states(self) -> np.ndarray:
        """(M, 2d) start states (zero velocity where only a position is given)."""
        return np.array([_full_state(a.start, self.dim) for a in self.agents])

    def goal_states(self) -> np.ndarray:
        """(M, 2d) goal states (zero velocity where only a position is given)."""
        return np.array([_full_state(a.goal, self.dim) for a in self.agents])

    def obstacle_halfspaces(self) -> list[tuple[np.ndarray, np.ndarray]]:
        return [ob.halfspaces(self.dim) for ob in self.obstacles]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Workspace box; without one, the starts' and goals' bounding box padded by 1 m."""
        if self.workspace is not None:
            return np.asarray(self.workspace.lower, float), np.asarray(self.workspace.upper, float)
        points = np.vstack([self.start_states()[:, : self.dim], self.goal_states()[:, : self.dim]])
        return points.min(axis=0) - 1.0, points.max(axis=0) + 1.0

    def matrix(self, which: Literal["Q", "R", "Qf"]) -> np.ndarray:
        size = self.dim if which == "R" else self.state_dim
        value = getattr(self.weights, which)
        if isinstance(value, (int, float)):
            return float(value) * np.eye(size)
        return np.asarray(value, float)

    def with_updates(self, **changes: Any) -> Scenario:
        """A validated copy with top-level fields (or dotted ``solver.rho`` style keys) changed."""
        data = self.model_dump()
        for key, value in changes.items():
            if value is None:
                continue
            target = data
            parts = key.split(".")
            for part in parts[:-1]:
                target = target[part]
            target[parts[-1]] = value
        return scenario_from_dict(data)


def _full_state(vector: list[float], dim: int) -> np.ndarray:
    values = np.asarray(vector, float)
    if values.size == dim:
        return np.concatenate([values, np.zeros(dim)])
    return values


def _consistency_errors(scn: Scenario) -> list[str]:
    """Cross-field checks, each a message that starts with the field path."""
    d = scn.dim
    errors: list[str] = []
    if not isinstance(scn.delta, (int, float)) and len(scn.delta) != d:
        errors.append(f"delta: expected a scalar or {d} values for dim {d}, got {len(scn.delta)}")
    if scn.collision == "hard" and scn.d_min <= 0:
        errors.append(
            "d_min: must be > 0 with collision: hard (d_min = 0 lets lambda = 0 satisfy the "
            "certificate, which excludes nothing)"
        )
    if scn.d_min < 0:
        errors.append("d_min: must be >= 0")
    for which in ("Q", "R", "Qf"):
        value = getattr(scn.weights, which)
        size = d if which == "R" else 2 * d
        if isinstance(value, list):
            matrix = np.asarray(value, float) if all(isinstance(r, list) for r in value) else None
            if matrix is None or matrix.shape != (size, size):
                errors.append(f"weights.{which}: expected a scalar or a {size}x{size} matrix")
            elif not np.allclose(matrix, matrix.T) or np.min(np.linalg.eigvalsh(matrix)) < 0:
                errors.append(f"weights.{which}: must be symmetric positive semidefinite")
        elif value < 0:
            errors.append(f"weights.{which}: must be >= 0")
    if isinstance(scn.weights.R, (int, float)) and scn.weights.R <= 0:
        errors.append("weights.R: must be > 0")
    if scn.workspace is not None and len(scn.workspace.lower) != d:
        errors.append(f"workspace.lower: expected {d} values for dim {d}, got {len(scn.workspace.lower)}")
    if scn.limits.accel is not None and isinstance(scn.limits.accel, list) and len(scn.limits.accel) != d:
        errors.append(f"limits.accel: expected a scalar or {d} values, got {len(scn.limits.accel)}")
    for n, ob in enumerate(scn.obstacles):
        if ob.box is not None:
            for field in ("center", "half_size"):
                if len(getattr(ob.box, field)) != d:
                    errors.append(f"obstacles[{n}].box.{field}: expected {d} values for dim {d}")
        elif ob.polytope is not None and len(ob.polytope.G[0]) != d:
            errors.append(f"obstacles[{n}].polytope.G: rows must have {d} columns for dim {d}")
    for n, agent in enumerate(scn.agents):
        for field in ("start", "goal"):
            size = len(getattr(agent, field))
            if size not in (d, 2 * d):
                errors.append(
                    f"agents[{n}].{field}: expected {d} (position) or {2 * d} (state) values "
                    f"for dim {d}, got {size}"
                )
    if errors:
        return errors[:1]
    delta = scn.delta_vector
    for field in ("start", "goal"):
        positions = np.array([_full_state(getattr(a, field), d)[:d] for a in scn.agents])
        for i in range(len(positions) - 1):  # one row of pairs at a time: O(M) numpy calls
            gaps = np.abs(positions[i + 1 :] - positions[i])
            inside = np.flatnonzero(np.all(gaps < delta, axis=1))
            if inside.size:
                j = i + 1 + int(inside[0])
                return [
                    f"agents[{j}].{field}: within delta of agents[{i}].{field} "
                    f"(inf-norm gap {np.max(gaps[inside[0]]):.3g} < delta {scn.delta})"
                ]
        for n, position in enumerate(positions):
            if scn.workspace is not None:
                lo = np.asarray(scn.workspace.lower)
                hi = np.asarray(scn.workspace.upper)
                if np.any(position < lo) or np.any(position > hi):
                    return [f"agents[{n}].{field}: {position.tolist()} is outside the workspace"]
            for k, ob in enumerate(scn.obstacles):
                G, g = ob.halfspaces(d)
                if np.all(G @ position <= g):
                    return [f"agents[{n}].{field}: {position.tolist()} is inside obstacles[{k}]"]
    return []


_FIELD_PREFIX = re.compile(r"^[A-Za-z_][\w\[\].]*: ")
_TYPE_TAGS = {"float", "int", "list[float]", "list[list[float]]", "function-after", "function-before"}


def _format_validation_error(err: ValidationError) -> str:
    """One line: the dotted path of the first offending field, then what is wrong with it."""
    first = err.errors()[0]
    location = ""
    for part in first["loc"]:
        if isinstance(part, int):
            location += f"[{part}]"
        elif str(part) not in _TYPE_TAGS:
            location += ("." if location else "") + str(part)
    message = {"extra_forbidden": "unknown key", "missing": "is required"}.get(
        first["type"], first["msg"].removeprefix("Value error, ")
    )
    if not location:
        return message
    if _FIELD_PREFIX.match(message):
        return f"{location}.{message}"
    return f"{location}: {message}"


def scenario_from_dict(data: Any, source: str = "scenario") -> Scenario:
    """Validate a plain mapping into a :class:`Scenario`; raise :class:`ScenarioError`."""
    if not isinstance(data, dict):
        raise ScenarioError(f"{source}: expected a mapping of scenario fields at the top level")
    try:
        return Scenario.model_validate(data)
    except ValidationError as err:
        raise ScenarioError(_format_validation_error(err)) from None


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario YAML file."""
    file = Path(path)
    try:
        text = file.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise ScenarioError(f"{file}: cannot read scenario file ({err.__class__.__name__})") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise ScenarioError(f"{file}: malformed YAML{where}") from None
    return scenario_from_dict(data, source=str(file))


def scenario_to_yaml(scn: Scenario) -> str:
    """The scenario with every default filled in, as YAML that loads back to an equal scenario."""
    return yaml.safe_dump(scn.model_dump(), sort_keys=False)
