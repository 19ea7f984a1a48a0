"""Scenario configuration: immutable, validated pydantic models and YAML loading.

Everything that runs is described by a :class:`Scenario`. It is validated as a whole before
anything is built, so a bad file fails early with one line that names the field
(:class:`ScenarioError`), never with a traceback from deep inside a solver.

Input is bounded before any work: a scenario file is a regular file of at most
:data:`MAX_FILE_BYTES`, its YAML at most :data:`MAX_YAML_DEPTH` levels deep and
:data:`MAX_YAML_NODES` values with aliases expanded, without duplicate keys; numbers are numbers
(not booleans, not text), within :data:`MAX_MAGNITUDE`; and the run's size (agents, horizon,
steps, the arrays they need) is capped by the ``MAX_*`` constants below.
"""

from __future__ import annotations

import math
import numbers
import os
import re
import stat
import types
import typing
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_serializer, model_validator
from pydantic_core import PydanticSerializationError

from swarmpc.model.agent_model import AgentModel, make_model
from swarmpc.model.dynamics import lqr_terminal_weight, riccati_weights_problem
from swarmpc.model.footprint import footprint_vertices, polygon_distance, polygon_vertices, rectangle_distance

Number = float
Matrix = list[list[float]]
ScalarOrMatrix = float | Matrix
ScalarOrVector = float | list[float]

MAX_FILE_BYTES = 512 * 1024
"""Largest scenario file read (512 KiB): a 1024-agent 3D scenario written out in full is ~0.2 MiB,
and the cap bounds the time the pure-Python YAML parser can spend on a hostile file before refusing it."""
MAX_YAML_DEPTH = 32
"""Deepest nesting of YAML collections accepted (a scenario needs 5: agents, item, start, ...)."""
MAX_YAML_NODES = 500_000
"""Most YAML values (scalars, lists, mappings) accepted, every alias counted as often as it is
used: an alias bomb expands to billions from a few hundred bytes."""
MAX_MAGNITUDE = 1e6
"""Largest magnitude of any real-valued field (positions, sizes, weights, tolerances, ...), so that
squares and products in the costs and norms cannot overflow."""
MAX_AGENTS = 1024
"""Most agents in a scenario."""
MAX_HORIZON = 200
"""Longest MPC horizon N, in steps."""
MAX_STEPS = 100_000
"""Most MPC steps of a run (``stop.max_steps``)."""
MAX_ADMM_ITERATIONS = 100_000
"""Highest ADMM iteration cap per MPC step (``solver.max_iter``)."""
MAX_LOCAL_ITERATIONS = 100_000
"""Highest iteration cap of one IPOPT or OSQP solve (``solver.ipopt.max_iter``, ``solver.qp.max_iter``)."""
MAX_WORKERS = 1024
"""Most worker processes or Ray actors (``executor.workers``)."""
MAX_ADDRESS_CHARS = 500
"""Longest Ray cluster address (``executor.address``)."""
MAX_OBSTACLES = 256
"""Most obstacles in a scenario."""
MAX_FACETS = 64
"""Most rows (facets) of one polytope obstacle."""
MAX_SEED = 2**64 - 1
"""Largest seed: the random generators draw on 64-bit words of it."""
MAX_RUN_BYTES = 2 * 1024**3
"""Bound on the estimated memory of a run's arrays (2 GiB), see :func:`estimated_run_bytes`."""
MAX_NAME_CHARS = 100
"""Longest scenario name (it names the output folder)."""
MAX_MESSAGE_CHARS = 500
"""Longest error message; a longer one (quoting a huge value) is cut."""

_NAME = re.compile(rf"[A-Za-z0-9_][A-Za-z0-9._+-]{{0,{MAX_NAME_CHARS - 1}}}")
_PLAIN_KEY = re.compile(r"[A-Za-z_][\w-]*")
_LINE_BREAKING = re.compile(r"[\x00-\x1f\x7f-\x9f\u2028\u2029]")
_MATRIX_DEPTH = 2  # lists of lists: the deepest a numeric field nests


def short_repr(value: Any, limit: int = 40) -> str:
    """``repr(value)`` cut to ``limit`` characters, safe for any value (even an int too long to print)."""
    try:
        text = repr(value)
    except ValueError:  # an int beyond Python's digit limit for str()
        return "<a number too long to print>"
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _one_line(message: str) -> str:
    """``message`` with every character that could break or forge a line escaped, cut to
    :data:`MAX_MESSAGE_CHARS`."""
    text = _LINE_BREAKING.sub(lambda m: m.group().encode("unicode_escape").decode("ascii"), message)
    return text if len(text) <= MAX_MESSAGE_CHARS else text[: MAX_MESSAGE_CHARS - 3] + "..."


class ScenarioError(ValueError):
    """A scenario that cannot run; the message is one line naming the offending field.

    Line breaks and control characters in the message (from a key or a path) are escaped, so
    the message is always exactly one line and cannot imitate a second one.
    """

    def __init__(self, message: object = "") -> None:
        super().__init__(_one_line(str(message)))


# ------------------------------------------------------------------ strictly typed numbers
def _annotation_kind(annotation: Any) -> type | None:
    """``float``, ``int`` or ``bool`` when that is the only scalar an annotation admits (alone, in
    lists, or with None); None when it admits anything else (text, choices, sections)."""
    kinds: set[Any] = set()
    pending = [annotation]
    while pending:
        item = pending.pop()
        if typing.get_origin(item) in (list, typing.Union, types.UnionType):
            pending.extend(typing.get_args(item))
        elif item is not type(None):
            kinds.add(item if item in (float, int, bool) else None)
    return kinds.pop() if len(kinds) == 1 else None


def _type_name(value: Any) -> str:
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, str):
        return "text"
    return "a number" if isinstance(value, numbers.Real) else type(value).__name__


def _leaf_problem(value: Any, kind: type) -> str | None:
    """What is wrong with one scalar of a field of ``kind``; None when nothing (or when the type
    is so far off that pydantic's own message says it better)."""
    if kind is bool:
        return None if isinstance(value, bool) else f"expected true or false, got {_type_name(value)}"
    if isinstance(value, (bool, str)):
        return f"expected {'an integer' if kind is int else 'a number'}, got {_type_name(value)}"
    if isinstance(value, numbers.Integral):
        if kind is float and abs(int(value)) > MAX_MAGNITUDE:
            return f"magnitude must be <= {MAX_MAGNITUDE:g}"
        return None
    if not isinstance(value, numbers.Real):
        return None
    number = float(value)
    if not math.isfinite(number):
        return f"must be finite, got {number}"
    if kind is float and abs(number) > MAX_MAGNITUDE:
        return f"magnitude must be <= {MAX_MAGNITUDE:g}, got {number:.3g}"
    return None


def _first_problem(value: Any, kind: type, path: str, depth: int = 0) -> str | None:
    """The first scalar of ``value`` (a scalar, a list or a matrix) that is not a proper ``kind``,
    as ``path[i][j]: problem``; deeper lists are left to the schema, which rejects them."""
    if isinstance(value, (list, tuple)):
        if depth >= _MATRIX_DEPTH:
            return None
        for index, item in enumerate(value):
            problem = _first_problem(item, kind, f"{path}[{index}]", depth + 1)
            if problem is not None:
                return problem
        return None
    if value is None:
        return None
    problem = _leaf_problem(value, kind)
    return None if problem is None else f"{path}: {problem}"


class _Frozen(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    @model_validator(mode="before")
    @classmethod
    def _strict_scalars(cls, data: Any) -> Any:
        """Numbers must be numbers and booleans booleans, before pydantic's lax mode would turn
        ``true`` or ``"1.5"`` into a number: every numeric scalar is finite and, where a real is
        expected, within :data:`MAX_MAGNITUDE` (ints stay welcome where reals are expected)."""
        if isinstance(data, dict):
            for key, value in data.items():
                field = cls.model_fields.get(key) if isinstance(key, str) else None
                kind = None if field is None else _annotation_kind(field.annotation)
                problem = None if kind is None else _first_problem(value, kind, key)
                if problem is not None:
                    raise ValueError(problem)
        return data
DEFAULT_Q = 0.2
"""Default stage weight on the state (times identity), with R = 1 and ``Qf: lqr``."""


class Weights(_Frozen):
    """Quadratic cost weights: scalars (times identity) or full matrices.

    ``Qf`` may also be ``lqr``: the cost-to-go of the infinite-horizon LQR of the agent's own
    discretised dynamics with Q and R (:meth:`Scenario.matrix`), with which the MPC is the LQR
    wherever no constraint binds, whatever the horizon.
    """

    Q: ScalarOrMatrix = Field(
        default=DEFAULT_Q,
        description="Stage state weight: a scalar ≥ 0 (times identity) or a symmetric PSD 2·dim × 2·dim matrix. "
        "The default (0.2 with R = 1 and `Qf: lqr`) brings a lone agent to within 5 cm of a 4.24 m move for good "
        "in 9.5 s with 1.9 % overshoot (docs/tuning.md); the paper's 0.1 is slower (11.5 s).",
    )
    R: ScalarOrMatrix = Field(default=1.0, description="Input weight: a scalar > 0 (times identity) or a symmetric "
                              "positive definite dim × dim matrix.")
    Qf: ScalarOrMatrix | Literal["lqr"] = Field(
        default="lqr",
        description="Terminal state weight: a scalar ≥ 0 (times identity), a symmetric PSD 2·dim × 2·dim matrix, "
        "or `lqr`: the solution P of the discrete algebraic Riccati equation of the agent's own double "
        "integrator (this `dt` and `discretization`) with Q and R, so the MPC is the infinite-horizon LQR "
        "wherever no constraint binds (needs R > 0 and a Q that weighs every position).",
    )

    @model_validator(mode="before")
    @classmethod
    def _qf_number_matrix_or_lqr(cls, data: Any) -> Any:
        """``Qf`` is numbers (checked as strictly as every numeric field) or exactly ``lqr``."""
        value = data.get("Qf") if isinstance(data, dict) else None
        if isinstance(value, str):
            if value != "lqr":
                raise ValueError(f"Qf: expected a number >= 0, a matrix or lqr, got {short_repr(value)}")
        elif value is not None:
            problem = _first_problem(value, float, "Qf")
            if problem is not None:
                raise ValueError(problem)
        return data

    @model_validator(mode="after")
    def _lqr_solvable(self) -> Weights:
        """With ``Qf: lqr``, the Riccati equation must have a stabilising solution for Q and R
        (checked here when Q and R are well formed; their shapes and signs are checked with dim)."""
        if self.Qf != "lqr":
            return self
        # scalar weights act alike on every axis, so one axis (size 2) stands for any dim
        size = len(self.Q) if isinstance(self.Q, list) else 2 * len(self.R) if isinstance(self.R, list) else 2
        Q, R = self._square(self.Q, size), self._square(self.R, size // 2)
        if Q is None or R is None or size == 0 or size % 2:
            return self
        if not (np.allclose(Q, Q.T) and np.allclose(R, R.T) and np.min(np.linalg.eigvalsh(Q)) >= 0):
            return self
        if not isinstance(self.R, list) and self.R <= 0:  # "weights.R: must be > 0" comes with dim
            return self
        problem = riccati_weights_problem(Q, R)
        if problem is not None:
            raise ValueError(f"Qf: lqr has no Riccati solution for these weights: {problem}")
        return self

    @staticmethod
    def _square(value: ScalarOrMatrix, size: int) -> np.ndarray | None:
        """A weight as a ``size`` x ``size`` matrix; None when it is a matrix of another shape."""
        if not isinstance(value, list):
            return float(value) * np.eye(size)
        if len(value) != size or any(not isinstance(row, list) or len(row) != size for row in value):
            return None
        return np.asarray(value, float)


class Workspace(_Frozen):
    """Axis-aligned bounds on every agent's position."""

    lower: list[float]
    upper: list[float]

    @model_validator(mode="after")
    def _ordered(self) -> Workspace:
        if len(self.lower) != len(self.upper):
            raise ValueError("lower and upper differ in length")
        if any(lo >= hi for lo, hi in zip(self.lower, self.upper, strict=True)):
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
    G: Matrix = Field(
        description=f"Facet normals, one row of `dim` values per facet (at most {MAX_FACETS} rows); no zero row."
    )
    g: list[float] = Field(description="Facet offsets, one per row of G.")

    @model_validator(mode="after")
    def _shapes(self) -> PolytopeSpec:
        if len(self.G) == 0:
            raise ValueError("G: has no rows")
        if len(self.G) > MAX_FACETS:
            raise ValueError(f"G: at most {MAX_FACETS} rows, got {len(self.G)}")
        if len(self.G) != len(self.g):
            raise ValueError(f"g: has {len(self.g)} entries but G has {len(self.G)} rows")
        if len({len(row) for row in self.G}) != 1:
            raise ValueError("G: rows differ in length")
        for index, row in enumerate(self.G):
            norm = float(np.linalg.norm(row))
            if not (math.isfinite(norm) and norm > 0):
                raise ValueError(f"G[{index}]: row norm must be finite and > 0, got {norm:.3g}")
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


CAR_DEFAULTS: typing.Mapping[str, float] = types.MappingProxyType({
    "length": 0.7, "width": 0.45, "wheelbase": 0.5, "rear_overhang": 0.1, "max_steer_deg": 35.0,
    "max_speed": 1.5, "max_reverse_speed": 0.5,
})
"""What a ``model: {type: car}`` section (or ``model: car``) takes for the car fields it leaves out."""


class AgentModelSpec(_Frozen):
    """An agent's dynamics model (``agents[].model``): the double integrator or a kinematic car.

    ``model: car`` is short for ``model: {type: car}``. The car fields belong to ``car`` only:
    under ``double_integrator`` they stay null, and a car takes each field it leaves out from
    :data:`CAR_DEFAULTS`. A car's state is [x, y, theta, v] (the rear axle's centre, the heading,
    the signed speed) and its input [a, delta] (:class:`swarmpc.model.car.KinematicCar`).
    """

    type: Literal["double_integrator", "car"] = Field(
        default="double_integrator",
        description="`double_integrator`: a point agent with an axis-aligned box body (`body`); `car`: a kinematic "
        "bicycle with a rectangular footprint that turns with it (2D only; `solver.method` admm, with either "
        "local step, or centralized). A car's `start` and `goal` are poses [x, y, heading_deg] or "
        "[x, y, heading_deg, speed] of the rear axle's centre, the heading in degrees from +x "
        "counter-clockwise; it needs a numeric `weights.Qf` (it has no linearisation for `lqr`).",
    )
    length: float | None = Field(default=None, gt=0, description="car only: footprint length [m] (default 0.7).")
    width: float | None = Field(default=None, gt=0, description="car only: footprint width [m] (default 0.45).")
    wheelbase: float | None = Field(
        default=None, gt=0, description="car only: distance between the rear and the front axle [m] (default 0.5)."
    )
    rear_overhang: float | None = Field(
        default=None, ge=0,
        description="car only: distance from the rear bumper forward to the rear axle's centre, the point the "
        "start, goal and workspace refer to [m], at most `length` (default 0.1).",
    )
    max_steer_deg: float | None = Field(
        default=None, gt=0, lt=90, description="car only: largest steering angle [degrees] (default 35)."
    )
    max_speed: float | None = Field(
        default=None, gt=0,
        description="car only: forward speed the vehicle is built for [m/s] (default 1.5); the plans are held to "
        "`limits.speed`.",
    )
    max_reverse_speed: float | None = Field(
        default=None, ge=0, description="car only: reverse speed the vehicle is built for [m/s] (default 0.5)."
    )

    @model_validator(mode="before")
    @classmethod
    def _shorthand_and_defaults(cls, data: Any) -> Any:
        """``car`` / ``double_integrator`` as a bare name; a car's missing fields from :data:`CAR_DEFAULTS`."""
        if isinstance(data, str):
            data = {"type": data}
        if isinstance(data, dict) and data.get("type") == "car":
            return {**data, **{k: v for k, v in CAR_DEFAULTS.items() if data.get(k) is None}}
        return data

    @model_validator(mode="after")
    def _car_fields_only_with_car(self) -> AgentModelSpec:
        if self.type != "car":
            for name in CAR_DEFAULTS:
                if getattr(self, name) is not None:
                    raise ValueError(f"{name}: only with type: car (got {self.type})")
        elif self.rear_overhang is not None and self.length is not None and self.rear_overhang > self.length:
            raise ValueError(f"rear_overhang: must be <= length ({self.length}), got {self.rear_overhang}")
        return self

    @property
    def is_car(self) -> bool:
        return self.type == "car"

    def car_params(self) -> dict[str, float]:
        """The keyword arguments of :class:`swarmpc.model.car.KinematicCar` (steering in radians)."""
        return {"length": float(self.length or 0), "width": float(self.width or 0),
                "wheelbase": float(self.wheelbase or 0), "rear_overhang": float(self.rear_overhang or 0),
                "max_steer": math.radians(float(self.max_steer_deg or 0)), "max_speed": float(self.max_speed or 0),
                "max_reverse_speed": float(self.max_reverse_speed or 0)}


class Agent(_Frozen):
    """An agent's start and goal and its body: for a point agent a position or a full state
    [position, velocity]; for a car a pose [x, y, heading_deg] or [x, y, heading_deg, speed]."""

    start: list[float]
    goal: list[float]
    model: AgentModelSpec = Field(
        default=AgentModelSpec(),
        description="The agent's dynamics: `double_integrator` (default) or `car`, a name or a section "
        "`{type: car, length, width, wheelbase, rear_overhang, max_steer_deg, max_speed, max_reverse_speed}`. "
        "Left out of the written scenario when it is the default.",
    )
    body: ScalarOrVector | None = Field(
        default=None,
        description="Half-size [m] of the agent's body, an axis-aligned box around its position: a scalar or "
        "`dim` values, each > 0. Two agents keep their bodies apart (centres at least b_i + b_j apart on some "
        "axis) and obstacles keep the whole body out. `null`: Δ/2 on every axis, so two default bodies "
        "keep exactly Δ apart.",
    )

    @field_validator("body")
    @classmethod
    def _positive_body(cls, value: ScalarOrVector | None) -> ScalarOrVector | None:
        values = [value] if isinstance(value, (int, float)) else (value or [])
        if any(v <= 0 for v in values):
            raise ValueError(f"every half-size must be > 0, got {short_repr(value)}")
        return value

    @model_validator(mode="after")
    def _car_has_no_body(self) -> Agent:
        if self.model.is_car and self.body is not None:
            raise ValueError("body: a car's body is its footprint (model.length, model.width); give no body")
        return self

    @model_serializer(mode="wrap")
    def _without_default_model(self, handler: Any) -> Any:
        """The written agent leaves ``model`` out when it is the default double integrator, so a
        point-only scenario is written exactly as before models could be chosen."""
        data = handler(self)
        if isinstance(data, dict) and self.model == AgentModelSpec():
            data.pop("model", None)
        return data


class ADMMOptions(_Frozen):
    """The ADMM knobs beyond the flat ``solver`` keys (``solver.admm``).

    The keys and defaults are those of :class:`swarmpc.solvers.admm.config.ADMMConfig`, which
    :meth:`~swarmpc.solvers.admm.config.ADMMConfig.from_options` builds from the ``solver``
    section; ``rho_min`` and ``rho_max`` are its ``rho_bounds``.
    """

    stall_window: int | None = Field(
        default=5, ge=1, le=MAX_ADMM_ITERATIONS,
        description="Iterations without a 10 % drop of the primal residual after which ADMM counts as stalled: "
        "rho is stiffened by `stall_rho_factor` (or, at `rho_max`, the step ends through the repair pass). "
        "`null`: never stalled.",
    )
    stall_rho_factor: float | None = Field(
        default=2.0, gt=1,
        description="Factor on rho when ADMM stalls (capped at `rho_max`). `null`: a stall ends the iterations.",
    )
    rho_min: float = Field(
        default=0.01, gt=0, description="Smallest rho that `adaptive_rho` may lower the penalty to."
    )
    rho_max: float = Field(
        default=1000.0, gt=0,
        description="Largest rho that `adaptive_rho` and the stall rule may raise the penalty to; >= `rho_min`.",
    )
    carry_multipliers: Literal["stable", "always", "never"] = Field(
        default="stable",
        description="Which consensus multipliers a new MPC step starts from (shifted by one step) rather than "
        "zero: `always` every one (the paper), `never` none, `stable` those of agents whose neighbours are "
        "those of the previous step's end (a multiplier whose counterpart was dropped can hold agents short "
        "of free goals).",
    )
    warm_start: bool = Field(
        default=True,
        description="Start each local IPOPT solve after the first of an MPC step from the previous iterate's "
        "multipliers too, not only its primal point (fewer IPOPT iterations to the same solution).",
    )
    repair: bool = Field(
        default=True,
        description="A step that ends without consensus goes through the repair pass (every coupled agent "
        "re-plans against its neighbours' plans held fixed), and fallbacks that break the separation are "
        "re-planned around. `false`: the last iterate's plans are applied as they are, which may leave pairs "
        "in conflict (a deadline stop is repaired anyway).",
    )
    deadline_repair: Literal["sequential", "select", "budget"] = Field(
        default="sequential",
        description="How a step stopped by `solver.deadline` is made safe: `sequential` every coupled agent "
        "re-plans, one after another, against its neighbours' plans; `select` each agent flies its new plan or its "
        "last step's plan shifted, chosen so every pair that can meet stays clear, and one agent of each pair of "
        "those that conflict re-plans (fewer overruns, a slower swarm: at 64 agents 1.2-2 times the time to the "
        "goals); `budget` the sequential re-plans while the deadline allows, then the selection over what they "
        "left (the selection's own re-plans only where two shifted plans conflict).",
    )
    repair_order: Literal["index", "colour"] = Field(
        default="index",
        description="Order of the repair pass: `index` every coupled agent, highest index first (consecutive "
        "agents that hold no copy of each other re-plan together); `colour` the classes of a greedy colouring of "
        "the coupling graph one after another, each class re-planning together (fewer rounds on the critical path).",
    )
    repair_rounds: int = Field(
        default=3, ge=1, le=100,
        description="Repair passes at most per step: after a pass, candidate pairs whose repaired plans conflict "
        "are coupled and their agents re-plan again.",
    )
    dual_tol: float | None = Field(
        default=None, gt=0,
        description="Tolerance of ADMM's dual residual (the penalty-weighted RMS motion of the consensus in the "
        "last iteration, at the step's starting rho); null: `solver.tol`, as in the paper. `rho * tol` stops a step "
        "once the consensus moves less than `solver.tol` per iteration.",
    )
    independent_first: bool | None = Field(
        default=None,
        description="Ask every agent first for its own optimum with no neighbour in it; when those plans keep every "
        "pair that can meet d_min apart, they are the step's answer (the joint optimum, no consensus to reach) and "
        "the step ends after that one round of local steps; else the ADMM iterations run as without it. Asked after "
        "steps whose plans kept every pair d_min + `solver.tol` apart. `null`: on for a swarm of point agents, off "
        "for a swarm with cars (whose ADMM has no such probe); `false`: the paper's iterations at every step.",
    )
    owner_weight: float = Field(
        default=5.0, gt=0,
        description="Weight of an agent's own block in the consensus: its penalty is rho times this, and the "
        "consensus average weighs its own positions this much against 1 for each neighbour's copy.",
    )
    pair_copies: Literal["both", "later"] = Field(
        default="both",
        description="Which agents of a coupled pair hold a copy of the other and keep the pair's OBCA rows "
        "against it, in a swarm with cars: `both` (the paper's consensus) or `later`, only the agent later in "
        "index order (the earlier one still yields through the consensus of its block, which that copy joins; "
        "a repair re-plans against every neighbour). The `parking` built-in sets `later`.",
    )
    dynamic_copies: bool = Field(
        default=False,
        description="An agent's copies of its neighbours are whole trajectories obeying their dynamics and "
        "limits (larger local problems) instead of free positions; not with `solver.local: qp`.",
    )
    closing_time: float | None = Field(
        default=None, ge=0,
        description="Seconds of closing speed added to the coupling reach: pairs approaching at relative speed "
        "v couple within Δ + d_min + `coupling_margin` + this × v. `null`: 0.1 with hard constraints and no "
        "`solver.coupling_margin`, else 0.",
    )

    @model_validator(mode="after")
    def _ordered_bounds(self) -> ADMMOptions:
        if self.rho_min > self.rho_max:
            raise ValueError(f"rho_max: must be >= rho_min ({self.rho_min}), got {self.rho_max}")
        return self


class IpoptOptions(_Frozen):
    """IPOPT's options for every NLP solve (``solver.ipopt``): the centralised problem and the ADMM
    agents' local problems (and the QP path's fallback). The defaults are
    :data:`swarmpc.formulation.ocp.IPOPT_OPTIONS` and ``LOCAL_IPOPT_OPTIONS``."""

    max_iter: int = Field(
        default=300, ge=1, le=MAX_LOCAL_ITERATIONS, description="IPOPT iterations at most per solve."
    )
    tol: float = Field(default=1e-6, gt=0, description="IPOPT's convergence tolerance (its `tol`).")
    acceptable_tol: float = Field(
        default=1e-4, gt=0,
        description="IPOPT's acceptable tolerance: a solve that stays within it for IPOPT's acceptable "
        "iterations counts as solved.",
    )
    mu_strategy: Literal["adaptive", "monotone"] = Field(
        default="adaptive", description="IPOPT's barrier parameter update (its `mu_strategy`)."
    )
    local_scaling: bool = Field(
        default=False,
        description="Let MUMPS scale the KKT systems of the agents' local problems (the centralised problem "
        "always scales); off by default: a warm-started local solve is mostly the linear solver's fixed "
        "cost, which the scaling adds to without changing the solutions.",
    )


class QPOptions(_Frozen):
    """The QP local step's tolerances (``solver.qp``, used with ``solver.local: qp``): OSQP's, the
    rows' safety margin and the certificate loop's. The keys and defaults are those of
    :class:`swarmpc.solvers.qp_local.QPLocalOptions`."""

    eps_abs: float = Field(default=1e-6, gt=0, description="OSQP's absolute tolerance.")
    eps_rel: float = Field(default=1e-6, ge=0, description="OSQP's relative tolerance.")
    max_iter: int = Field(
        default=4000, ge=1, le=MAX_LOCAL_ITERATIONS, description="OSQP iterations at most per QP."
    )
    polish: bool = Field(
        default=True,
        description="OSQP's polishing: solve the KKT system of the guessed active set, so an answer meets its "
        "active rows to machine precision.",
    )
    check_termination: int = Field(
        default=5, ge=1, le=MAX_LOCAL_ITERATIONS,
        description="OSQP tests for termination every this many iterations.",
    )
    check_dualgap: bool = Field(
        default=True,
        description="OSQP's duality-gap test for termination, on top of its residual tests. Every answer is "
        "rebuilt and checked whatever OSQP's stopping test, so off trades only accuracy of the optimum.",
    )
    margin: float = Field(
        default=1e-5, ge=0,
        description="Tightening [m] of every separation, plane, workspace and speed row against OSQP's primal "
        "tolerance, so that d_min itself is never eaten.",
    )
    max_rounds: int = Field(
        default=5, ge=1, le=MAX_LOCAL_ITERATIONS,
        description="Certificate rounds (QPs) per local step at most (a repair call's; a car's QP step's "
        "trust-region rounds); every round's plan is safe, so a capped loop is an inexact but safe step.",
    )
    iteration_rounds: int = Field(
        default=2, ge=1, le=MAX_LOCAL_ITERATIONS,
        description="Certificate rounds per local step of an ADMM iteration (copies free), at most `max_rounds`: "
        "the next iteration starts from the plan and certificates of this one, so the iterations carry the "
        "loop on; a repair call, whose plan is flown, may take `max_rounds`.",
    )
    plan_tol: float = Field(
        default=1e-6, ge=0, description="The certificate loop stops when the QP's plan moved less than this [m]."
    )
    certificate_tol: float = Field(
        default=1e-6, ge=0,
        description="The certificate loop stops when no certificate of a row within `active_band` of its "
        "bound moved more than this.",
    )
    active_band: float = Field(
        default=1e-3, ge=0,
        description="A row within this [m] of its bound counts as near it for `certificate_tol`.",
    )
    speed_facets: int | None = Field(
        default=None, ge=4, le=MAX_FACETS,
        description="Facets of the inner polytope that stands in for the speed limit. `null`: 16 in 2D, the "
        "26 cube directions in 3D.",
    )
    solver: Literal["osqp", "piqp"] = Field(
        default="osqp",
        description="QP solver of the local steps of the ADMM iterations (copies free): `osqp` (first-order, "
        "warm-started from the last answer) or `piqp` (interior point).",
    )
    repair_solver: Literal["osqp", "piqp"] = Field(
        default="piqp",
        description="QP solver of the repair passes' local steps (neighbours' plans held fixed): `piqp` "
        "(interior point: about ten iterations where OSQP needs hundreds on these tightly constrained QPs, "
        "and a quick verdict on an infeasible one) or `osqp`.",
    )
    elastic: bool = Field(
        default=True,
        description="A repair call (neighbours' plans held fixed) whose certificate loops fail is solved again "
        "with soft pair rows from its last plan; a soft plan that needs no slack starts the hard loop again, "
        "whose answer is taken instead of handing the call to IPOPT. Not under `solver.deadline`, where no "
        "call is handed over: there the phase's answers left a 64-agent swarm short of its goals in one of "
        "two runs.",
    )
    handover_slack: float | None = Field(
        default=None, ge=0,
        description="With `elastic`: a failed repair call goes to IPOPT (when the step allows a hand-over) only "
        "if its soft plan falls short of d_min by at most this [m]. `null`: every call the elastic phase does not "
        "answer is handed over. 1e-4 for the shorter tail: on random swarms of 64 the critical path's p99 fell by "
        "60 % and the IPOPT hand-overs by 83 % at the same cost, but one run of ten left three agents short of "
        "their goals after 60 s.",
    )


REMOVED_SOLVER_KEYS: typing.Mapping[str, str] = types.MappingProxyType({
    "component_stop": "it was slower to the goals; docs/lab/admm.md#component-stop",
})
"""``solver`` keys that were removed, with why and where their measurement is kept."""


def default_local(has_cars: bool = False, dynamic_copies: bool = False) -> Literal["qp", "ipopt"]:
    """``solver.local`` of a scenario that leaves it out, the one rule for it: ``qp`` for a swarm of
    point agents (as good plans as the NLP's, several times faster); ``ipopt`` when some agent is a
    car (a car's QP step, a sequential convex programme, is slower than its NLP: docs/lab/cars.md)
    or the ADMM copies are dynamic (``solver.admm.dynamic_copies``: the QP step takes free copies
    only). :class:`SolverConfig` applies it with what it knows (the copies), :class:`Scenario` with
    the agents too."""
    return "ipopt" if has_cars or dynamic_copies else "qp"


def _dynamic_copies(admm: Any) -> bool:
    """Whether raw ``solver.admm`` data (a dict or an :class:`ADMMOptions`) ask for dynamic copies."""
    dynamic = admm.get("dynamic_copies") if isinstance(admm, dict) else getattr(admm, "dynamic_copies", False)
    return dynamic is True


def _names_a_car(agents: Any) -> bool:
    """Whether raw ``agents`` data (dicts or :class:`Agent` objects, before validation) hold a car."""
    if not isinstance(agents, list):
        return False
    for agent in agents:
        model = agent.get("model") if isinstance(agent, dict) else getattr(agent, "model", None)
        kind = model.get("type") if isinstance(model, dict) else getattr(model, "type", model)
        if kind == "car":
            return True
    return False


class SolverConfig(_Frozen):
    """How each MPC step is solved."""

    method: Literal["admm", "centralized"] = Field(
        default="admm",
        description="`admm`: consensus ADMM over the agents' local problems; `centralized`: one NLP over the "
        "whole swarm. A scenario with car agents (`agents[].model: car`) takes both: its ADMM agrees on footprint "
        "poses (its local steps run on any `executor`; `solver.local: qp` solves each local step as a sequence of "
        "QPs about the plan; of the `admm` subsection only `owner_weight` and `pair_copies` apply), its centralised "
        "NLP ignores `solver.local` and the ADMM keys.",
    )
    rho: float = Field(default=10.0, gt=0, description="ADMM penalty parameter")
    max_iter: int = Field(default=100, ge=1, le=MAX_ADMM_ITERATIONS, description="ADMM iteration cap per MPC step")
    tol: float = Field(
        default=1e-3, gt=0,
        description="ADMM primal/dual residual tolerance [m] (the random and spread built-ins use 0.005)",
    )
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
    local: Literal["qp", "ipopt"] = Field(
        default=default_local(),
        description="ADMM agents' local step: qp (a short sequence of convex QPs (OSQP; PIQP in the repair "
        "passes, `solver.qp`) with the OBCA certificates held fixed, whose plans are collision-free as they stand; "
        "a call the QP path fails is solved by IPOPT instead; the speed limit is an inner polytope of the speed "
        "ball, `solver.qp.speed_facets`) or ipopt (the OBCA NLP by IPOPT: the paper's local step and the "
        "reference, several times slower). Left out: qp, or ipopt when some agent is a car (a car's QP step is "
        "slower than its NLP) or with `admm.dynamic_copies`",
    )
    deadline: float | None = Field(
        default=None, gt=0,
        description="ADMM critical-path budget per MPC step [s] (what the step would take with one core per "
        "agent): an iteration that would overrun it, or leave less room than the last repair pass took (up "
        "to half the budget), is not started, and the step ends through the repair pass; with solver.local "
        "qp a failed QP call is "
        "not handed to IPOPT. A deadline that binds makes the run depend on the machine's speed. null: no "
        "deadline (steps whose critical path exceeds dt still count in summary.json deadline_misses)",
    )
    admm: ADMMOptions = Field(
        default=ADMMOptions(),
        description="ADMM's further knobs: the stall rule, the penalty's bounds, multipliers carried across "
        "steps, warm starts, the repair pass, the owner weight, copy form and closing-speed coupling",
    )
    ipopt: IpoptOptions = Field(
        default=IpoptOptions(),
        description="IPOPT's iteration cap, tolerances and barrier strategy, for every NLP solve",
    )
    qp: QPOptions = Field(
        default=QPOptions(),
        description="the QP local step's tolerances (`local: qp`): OSQP's, the rows' margin, the certificate loop",
    )

    @model_validator(mode="before")
    @classmethod
    def _removed_keys(cls, data: Any) -> Any:
        """A removed key is named as removed, not as unknown: a scenario written for it says why."""
        if isinstance(data, dict):
            for key, why in REMOVED_SOLVER_KEYS.items():
                if key in data:
                    raise ValueError(f"{key}: removed ({why})")
        return data

    @model_validator(mode="before")
    @classmethod
    def _local_left_out(cls, data: Any) -> Any:
        """``local`` left out: :func:`default_local` of the copies (set only where it is not the
        field's default, so that a scenario can still tell it was left out)."""
        if isinstance(data, dict) and "local" not in data:
            local = default_local(dynamic_copies=_dynamic_copies(data.get("admm")))
            if local != default_local():
                return {**data, "local": local}
        return data

    @model_validator(mode="after")
    def _qp_needs_free_copies(self) -> SolverConfig:
        if self.local == "qp" and self.admm.dynamic_copies:
            raise ValueError("admm.dynamic_copies: local: qp needs free copies (dynamic_copies: false)")
        return self


class StopConfig(_Frozen):
    """When the closed loop ends."""

    goal_tolerance: float = Field(default=0.05, gt=0, description="position tolerance [m]")
    speed_tolerance: float = Field(default=0.1, gt=0, description="speed tolerance at the goal")
    heading_tolerance_deg: float = Field(
        default=5.0, gt=0, le=180,
        description="car agents only: a car is at its goal when, besides the position and speed tolerances, its "
        "heading is within this many degrees of the goal heading (taken modulo a full turn)",
    )
    max_steps: int = Field(
        default=400, ge=1, le=MAX_STEPS,
        description="MPC steps at most; the run stops earlier when every agent is at its goal. With the "
        f"agents, also bounded by the memory of the run's arrays (at most {MAX_RUN_BYTES // 1024**3} GiB)",
    )


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


PLANT_DEFAULTS: typing.Mapping[str, float] = types.MappingProxyType(
    {"physics_dt": 0.002, "drag": 0.0, "lag_s": 0.0, "mass": 1.0}
)
"""What a ``plant: {type: mujoco}`` section takes for the physics fields it leaves out."""


class PlantConfig(_Frozen):
    """What the closed loop applies the inputs to: the nominal model itself or a physics engine.

    ``double_integrator`` is the planner's own model (with the ``disturbance`` block's noise);
    ``mujoco`` simulates every agent as a rigid body in MuJoCo, pushed by force actuators, so the
    planner meets a plant it does not model exactly (continuous motion, drag, actuator lag). The
    physics fields belong to ``mujoco`` only: under ``double_integrator`` they stay null, and with
    ``mujoco`` a field left out takes its value from :data:`PLANT_DEFAULTS`.
    """

    type: Literal["double_integrator", "mujoco"] = Field(
        default="double_integrator",
        description="`double_integrator`: the planner's own model, exactly (plus `disturbance` noise); "
        "`mujoco`: each agent a rigid box (its `body`, default half-size Δ/2) in MuJoCo, driven by force "
        "actuators",
    )
    physics_dt: float | None = Field(
        default=None, ge=1e-5,
        description="mujoco only: largest physics step [s] (default 0.002); dt is split into equal "
        "substeps no longer than this",
    )
    drag: float | None = Field(
        default=None, ge=0,
        description="mujoco only: linear drag rate [1/s] (default 0): a force of -mass * drag * velocity",
    )
    lag_s: float | None = Field(
        default=None, ge=0,
        description="mujoco only: time constant [s] of a first-order lag between the commanded and the "
        "applied acceleration (default 0: none)",
    )
    mass: float | None = Field(
        default=None, gt=0,
        description="mujoco only: mass of each agent's body [kg] (default 1); the actuators apply "
        "mass * commanded acceleration",
    )

    @model_validator(mode="before")
    @classmethod
    def _mujoco_defaults(cls, data: Any) -> Any:
        """Fill the physics fields a ``mujoco`` section leaves out (or sets to null)."""
        if isinstance(data, dict) and data.get("type") == "mujoco":
            return {**data, **{k: v for k, v in PLANT_DEFAULTS.items() if data.get(k) is None}}
        return data

    @model_validator(mode="after")
    def _physics_only_with_mujoco(self) -> PlantConfig:
        if self.type != "mujoco":
            for name in PLANT_DEFAULTS:
                if getattr(self, name) is not None:
                    raise ValueError(f"{name}: only with plant.type: mujoco (got {self.type})")
        return self


class DeadlockConfig(_Frozen):
    """The deadlock and detour rules (:mod:`swarmpc.simulation.deadlock`).

    An agent that stays slow, far from its goal and blocked (another agent ahead, in the corridor
    to its goal) for ``patience`` steps steers for ``hold`` steps to a detour point ``angle_deg``
    to the right of its goal direction; every blocked agent turns the same way, so a jam unwinds
    like a roundabout. Agents near a free goal are spared, repeated detours are de-synchronised
    (seeded by the scenario's ``seed``), and in 3D a knot of agents sitting on each other's goals
    is untied by lifting (or side-stepping) one member. The keys and defaults are those of
    :class:`swarmpc.simulation.deadlock.DeadlockPolicy`, which is built from this section.
    """

    enabled: bool = Field(
        default=True,
        description="`false` switches the rules off: no detours and no lifts, every agent steers to its own "
        "goal throughout (a symmetric swap may then stay jammed until `stop.max_steps`).",
    )
    speed_threshold: float = Field(
        default=0.05, gt=0, description="An agent slower than this [m/s] (and far from its goal) counts as stalled."
    )
    distance_threshold: float = Field(
        default=0.2, gt=0, description="Only an agent farther than this [m] from its goal can stall."
    )
    patience: int = Field(
        default=4, ge=1, le=MAX_STEPS,
        description="Consecutive stalled steps, with another agent in its way, before an agent is detoured.",
    )
    neighbour_radius: float = Field(
        default=1.0, gt=0,
        description="Only another agent within this [m] (inf-norm), ahead and in the corridor to the goal, "
        "blocks an agent.",
    )
    hold: int = Field(
        default=15, ge=1, le=MAX_STEPS,
        description="Steps a detour lasts: the agent steers to the detour point instead of its goal.",
    )
    detour: float = Field(
        default=1.0, gt=0,
        description="How far [m] the detour point lies from the agent (scaled by the distance to the goal "
        "when that is below 1 m).",
    )
    angle_deg: float = Field(
        default=75.0, gt=0, le=180,
        description="Angle [degrees] of the detour direction to the right (clockwise about z) of the goal "
        "direction.",
    )
    keep_right_deg: float | None = Field(
        default=None, ge=0, lt=90,
        description="Anticipation: an agent more than `approach_radius` from its goal, in traffic (an agent in its "
        "way, itself farther than `distance_threshold` from its goal), steers to its goal turned this many degrees "
        "to the right about itself from the first such step, without waiting to stall, so agents meeting at a "
        "common point pass like a roundabout. 0: off; null: 20 in 2D, off in 3D (where agents pass over and "
        "under each other and the turn slowed them down).",
    )
    approach_radius: float = Field(
        default=1.0, gt=0,
        description="Within this [m] of its goal an agent still closing in by `min_progress` per step is "
        "approaching, not stalled, and one near a free goal is spared (`spare_free_goals`); beyond it an "
        "agent stalled with nobody in its way is detoured after `lonely_patience` steps.",
    )
    lonely_patience: int = Field(
        default=12, ge=1, le=MAX_STEPS,
        description="Consecutive stalled steps before an agent with nobody in its way (stuck at an obstacle) "
        "is detoured.",
    )
    min_progress: float = Field(
        default=0.002, gt=0,
        description="Progress [m per step] towards the goal that makes an agent within `approach_radius` "
        "count as approaching.",
    )
    escalate_after: int = Field(
        default=2, ge=0, le=MAX_STEPS,
        description="Detours of one agent after which its further detours are de-synchronised: angle "
        "jittered, hold stretched (drawn from `seed`), so a recurring jam comes apart.",
    )
    jitter_deg: float = Field(
        default=30.0, ge=0, le=180, description="Largest jitter [degrees] of an escalated detour's angle."
    )
    stretch: float = Field(
        default=2.0, ge=0,
        description="An escalated detour's hold is stretched by a random factor in [1, 1 + stretch].",
    )
    corridor_margin: float = Field(
        default=0.1, ge=0,
        description="Added to the clearance (Δ + d_min) [m] when testing whether another agent is in an "
        "agent's corridor to its goal, or sits on its goal (knots).",
    )
    progress_window: int | None = Field(
        default=None, ge=1, le=MAX_STEPS,
        description="Steps over which a blocked agent must get `window_progress` closer to its goal, however "
        "fast it moves, or count as stalled; `null`: only slow agents stall.",
    )
    window_progress: float = Field(
        default=0.05, gt=0, description="Progress [m] expected over `progress_window` steps."
    )
    spare_free_goals: bool = Field(
        default=True,
        description="Never detour an agent within `approach_radius` of a goal no other agent occupies "
        "(until `free_goal_patience` steps at rest).",
    )
    free_goal_patience: int | None = Field(
        default=100, ge=0, le=MAX_STEPS,
        description="Steps an agent at rest short of a free goal, with another agent in its corridor, is "
        "spared; then it counts as stalled like any other. `null`: spared for ever (a head-on pair short of "
        "free goals may then wait for ever).",
    )
    untie_knots: bool = Field(
        default=True,
        description="In 3D: untie a cycle of agents each sitting on the next one's goal by "
        "lifting one member out of the layer while the others wait, instead of turning them all right.",
    )
    lift: float = Field(default=0.5, gt=0, description="How far [m] the lifted member of a knot climbs or descends.")
    lift_hold: int = Field(
        default=40, ge=1, le=MAX_STEPS,
        description="Steps a lift lasts at most, and the other members of the knot wait.",
    )
    knot_patience: int | None = Field(
        default=10, ge=1, le=MAX_STEPS,
        description="Steps over which the members of a knot together must get `knot_progress` per member and step "
        "closer to their goals, or the knot is untied without waiting for a member to stall (a pair at rest short "
        "of free goals, or sliding round each other). `null`: a knot waits for a member to stall.",
    )
    knot_progress: float = Field(
        default=0.005, gt=0,
        description="Progress [m per member and step] the members of a knot must make together over "
        "`knot_patience` steps, or the knot is untied.",
    )
    release_lifts: bool = Field(
        default=True,
        description="End a lift early, as soon as the knot has come apart (no member within the clearance plus "
        "`corridor_margin` of another member's goal), the lifted member's goal is free and the straight way to "
        "it clear: waiting longer only delays it.",
    )
    side_steps: bool = Field(
        default=True,
        description="When the way over or under a knot runs into a parked agent, the lifted member steps out "
        "sideways instead (the side that keeps farthest from the others).",
    )


def executor_problem(
    kind: str, workers: int | None, address: str | None, names: typing.Mapping[str, str]
) -> str | None:
    """What is wrong with the executor choice ``kind`` / ``workers`` / ``address``, as one line
    that starts with the offending key; None when it is consistent.

    ``workers`` and ``address`` only mean something with the executors that use them. ``names``
    spells the three keys (``type``, ``workers``, ``address``) the way the caller's user wrote
    them: the scenario's ``executor.*`` keys or the command line's ``--executor`` options, so
    both say the same thing in their own words.
    """
    if workers is not None and kind == "serial":
        return f"{names['workers']}: only with {names['type']} process or ray"
    if address is not None and kind != "ray":
        return f"{names['address']}: only with {names['type']} ray"
    if address is not None and not address.strip():
        return f"{names['address']}: must not be empty (auto, ray://host:port)"
    return None


class ExecutorConfig(_Frozen):
    """Where the ADMM agents' local solves run (the ``executor`` section): the run's controller
    creates this executor and closes it when the run ends. ``swarmpc run --executor``,
    ``--workers`` and ``--address`` override it."""

    type: Literal["serial", "thread", "process", "ray"] = Field(
        default="serial",
        description="`serial`: one after another in the run's process; `thread`: a thread pool; `process`: "
        "worker processes (one core each); `ray`: Ray actors, on this machine or a cluster. The plans are "
        "the same, bit for bit, whichever runs them. Anything but `serial` needs `solver.method: admm`.",
    )
    workers: int | None = Field(
        default=None, ge=1, le=MAX_WORKERS,
        description="Threads, worker processes or Ray actors. `null`: the pool's default (threads: Python's, "
        "processes: the available cores, Ray: the cluster's CPUs). Not with `serial`.",
    )
    address: str | None = Field(
        default=None, max_length=MAX_ADDRESS_CHARS,
        description="The Ray cluster to join (`auto`, `ray://host:port`); only with `ray`. `null`: start a "
        "local Ray.",
    )

    @model_validator(mode="after")
    def _options_used(self) -> ExecutorConfig:
        names = {"type": "executor.type", "workers": "workers", "address": "address"}
        problem = executor_problem(self.type, self.workers, self.address, names)
        if problem is not None:
            raise ValueError(problem)
        return self


class Scenario(_Frozen):
    """A complete, validated multi-agent scenario (every key: docs/scenario-reference.md)."""

    name: str = Field(
        default="unnamed",
        description="Scenario name: the default output folder is `results/<name>`; echoed in `summary.json`. "
        f"1 to {MAX_NAME_CHARS} characters from `A-Z a-z 0-9 . _ + -`, the first a letter, digit or `_`.",
    )
    dim: int = 2
    dt: float = 0.1
    horizon: int = Field(default=10, ge=2, le=MAX_HORIZON, description="MPC horizon N in steps.")
    delta: ScalarOrVector = Field(
        default=0.3,
        description="Δ [m]: how far apart two agents' centres keep per axis with default bodies (each agent's "
        "`body` defaults to Δ/2 per axis), a scalar or one value per axis; > 0. Agents i and j collide when "
        "their bodies overlap: |p_i − p_j| < b_i + b_j on every axis (< Δ with default bodies).",
    )
    collision: Literal["hard", "soft"] = "hard"
    d_min: float = 0.05
    kappa: float = 1000.0
    discretization: Literal["euler", "zoh"] = "euler"
    seed: int = Field(
        default=0, ge=0, le=MAX_SEED,
        description="Seed of the RRT planner, of the disturbance noise and of the `random` built-in scenario.",
    )
    weights: Weights = Weights()
    workspace: Workspace | None = None
    limits: Limits = Limits()
    obstacles: list[Obstacle] = Field(
        default=[],
        description=f"Static convex obstacles (at most {MAX_OBSTACLES}). Each entry has exactly one of `box` or "
        "`polytope`; an agent's whole body keeps d_min from it (the obstacle is grown by the body's box). "
        "Starts and goals must keep the body outside.",
    )
    agents: list[Agent] = Field(
        description=f"The agents (1 to {MAX_AGENTS}). Their bodies must not overlap at the starts (nor at the "
        "goals).",
    )
    solver: SolverConfig = SolverConfig()
    stop: StopConfig = StopConfig()
    disturbance: Disturbance = Field(
        default=Disturbance(),
        description="process/measurement noise (seeded by `seed`) and planner tightening; default off",
    )
    plant: PlantConfig = Field(
        default=PlantConfig(),
        description="what the inputs drive: the ideal double integrator (default) or a MuJoCo physics model",
    )
    deadlock: DeadlockConfig = Field(
        default=DeadlockConfig(),
        description="the deadlock and detour rules: when a stalled agent is detoured, how, and knots untied "
        "in 3D; `enabled: false` switches them off",
    )
    executor: ExecutorConfig = Field(
        default=ExecutorConfig(),
        description="where the ADMM agents' local solves run (default: serially, in the run's process)",
    )

    @field_validator("name")
    @classmethod
    def _safe_name(cls, value: str) -> str:
        if not _NAME.fullmatch(value):
            raise ValueError(
                f"must be 1 to {MAX_NAME_CHARS} of A-Z a-z 0-9 . _ + - (not first . + -; it names the "
                f"output folder), got {short_repr(value)}"
            )
        return value

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

    @field_validator("delta")
    @classmethod
    def _delta(cls, value: ScalarOrVector) -> ScalarOrVector:
        values = [value] if isinstance(value, (int, float)) else value
        if any(v <= 0 for v in values):
            raise ValueError(f"must be > 0, got {short_repr(value)}")
        return value

    @field_validator("agents")
    @classmethod
    def _agents(cls, value: list[Agent]) -> list[Agent]:
        if not value:
            raise ValueError("needs at least one agent")
        if len(value) > MAX_AGENTS:
            raise ValueError(f"at most {MAX_AGENTS} agents, got {len(value)}")
        return value

    @field_validator("obstacles")
    @classmethod
    def _obstacles(cls, value: list[Obstacle]) -> list[Obstacle]:
        if len(value) > MAX_OBSTACLES:
            raise ValueError(f"at most {MAX_OBSTACLES} obstacles, got {len(value)}")
        return value

    @model_validator(mode="before")
    @classmethod
    def _local_step_of_the_agents(cls, data: Any) -> Any:
        """``solver.local`` left out: :func:`default_local` with cars (what it is without them,
        :class:`SolverConfig` resolves from the copies alone)."""
        if not isinstance(data, dict) or not _names_a_car(data.get("agents")):
            return data
        solver, local = data.get("solver"), default_local(has_cars=True)
        if solver is None or (isinstance(solver, dict) and "local" not in solver):
            return {**data, "solver": {**(solver or {}), "local": local}}
        if isinstance(solver, SolverConfig) and "local" not in solver.model_fields_set:
            return {**data, "solver": solver.model_copy(update={"local": local})}
        return data

    @model_validator(mode="after")
    def _consistent(self) -> Scenario:
        for error in [*_size_errors(self), *_consistency_errors(self)]:
            raise ValueError(error)
        return self

    def revalidated(self) -> Scenario:
        """A freshly validated copy of this scenario; raises :class:`ScenarioError` when invalid.

        The model is frozen, but its lists are Python lists that can still be changed in place
        (``scn.agents.append(...)``, ``scn.agents[0].start[0] = 1e9``) without any validator
        seeing it. Code about to run a scenario calls this to work on content that was checked.
        An unchanged scenario gives an equal copy.
        """
        try:
            data = self.model_dump(warnings=False)
        except PydanticSerializationError:
            raise ScenarioError("scenario: holds a value that is not scenario data (changed in place?)") from None
        return scenario_from_dict(data)

    # ----------------------------------------------------------------- derived views
    @property
    def num_agents(self) -> int:
        return len(self.agents)

    def agent_model(self) -> AgentModel:
        """The agents' dynamics: the double integrator of this ``dim``, ``dt`` and
        ``discretization`` (:func:`swarmpc.model.agent_model.make_model`)."""
        return make_model("double_integrator", self.dim, self.dt, self.discretization)

    @property
    def state_dim(self) -> int:
        return self.agent_model().state_dim

    @property
    def has_cars(self) -> bool:
        """True when some agent is a car (``agents[].model: car``)."""
        return any(a.model.is_car for a in self.agents)

    def agent_models(self) -> tuple[AgentModel, ...]:
        """Each agent's own dynamics: :meth:`agent_model` for a point agent, the kinematic car of its
        ``model`` section for a car (this ``dt``; a car's step is RK4 whatever the ``discretization``)."""
        point = self.agent_model()
        cars: dict[AgentModelSpec, AgentModel] = {}
        models = []
        for agent in self.agents:
            if not agent.model.is_car:
                models.append(point)
                continue
            if agent.model not in cars:
                cars[agent.model] = make_model("car", self.dim, self.dt, self.discretization,
                                               **agent.model.car_params())
            models.append(cars[agent.model])
        return tuple(models)

    @property
    def delta_vector(self) -> np.ndarray:
        """Δ per axis: the separation of two default bodies' centres."""
        return np.broadcast_to(np.asarray(self.delta, float), (self.dim,)).copy()

    @property
    def bodies(self) -> np.ndarray:
        """(M, d) half-size of each agent's body per axis: its ``body``, else Δ/2 (halving is exact,
        so two default bodies give b_i + b_j == Δ bit for bit)."""
        default = self.delta_vector / 2.0
        return np.array([_car_half_size(a) if a.model.is_car else default if a.body is None
                         else np.broadcast_to(np.asarray(a.body, float), (self.dim,)) for a in self.agents])

    def start_states(self, model: AgentModel | None = None) -> np.ndarray:
        """(M, n) start states of ``model`` (default: each agent's own, :meth:`agent_models`), at
        rest where only a position is given; a car's [x, y, heading (rad), speed]."""
        if model is None and self.has_cars:
            return np.array([_agent_state(a.start, self.dim, a.model.is_car) for a in self.agents])
        model = model or self.agent_model()
        return np.array([_model_state(a.start, self.dim, model) for a in self.agents])

    def goal_states(self, model: AgentModel | None = None) -> np.ndarray:
        """(M, n) goal states of ``model`` (default: each agent's own, :meth:`agent_models`), at
        rest where only a position is given; a car's [x, y, heading (rad), speed]."""
        if model is None and self.has_cars:
            return np.array([_agent_state(a.goal, self.dim, a.model.is_car) for a in self.agents])
        model = model or self.agent_model()
        return np.array([_model_state(a.goal, self.dim, model) for a in self.agents])

    def obstacle_halfspaces(self) -> list[tuple[np.ndarray, np.ndarray]]:
        return [ob.halfspaces(self.dim) for ob in self.obstacles]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Workspace box; without one, the starts' and goals' bounding box padded by 1 m."""
        if self.workspace is not None:
            return np.asarray(self.workspace.lower, float), np.asarray(self.workspace.upper, float)
        if self.has_cars:
            points = np.vstack([self.start_states()[:, : self.dim], self.goal_states()[:, : self.dim]])
        else:
            model = self.agent_model()
            points = np.vstack([model.position(self.start_states(model)), model.position(self.goal_states(model))])
        return points.min(axis=0) - 1.0, points.max(axis=0) + 1.0

    def matrix(self, which: Literal["Q", "R", "Qf"], model: AgentModel | None = None) -> np.ndarray:
        """The weight ``which`` for ``model``'s states and inputs (default :meth:`agent_model`): a
        scalar times identity, a matrix as given, and ``Qf: lqr`` as the Riccati cost-to-go of
        the model (with this ``dt`` and ``discretization``) and the Q and R above
        (:func:`swarmpc.model.dynamics.lqr_terminal_weight`)."""
        model = model or self.agent_model()
        size = model.input_dim if which == "R" else model.state_dim
        value = getattr(self.weights, which)
        if value == "lqr":
            return lqr_terminal_weight(model, self.matrix("Q", model), self.matrix("R", model))
        if isinstance(value, (int, float)):
            return float(value) * np.eye(size)
        return np.asarray(value, float)

    def with_updates(self, **changes: Any) -> Scenario:
        """A validated copy with top-level fields (or dotted ``solver.rho`` style keys) changed; a
        None value leaves its field as it is (an option not given)."""
        return self.with_settings({key: value for key, value in changes.items() if value is not None})

    def with_settings(self, settings: typing.Mapping[str, Any]) -> Scenario:
        """A validated copy with dotted keys set to ``settings``' values, None included (a
        user's ``KEY=null`` sets the field to null)."""
        data = self.model_dump()
        for key, value in settings.items():
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


def _car_half_size(agent: Agent) -> np.ndarray:
    """A car's half length and half width: the half-sizes of its footprint in its own frame."""
    return 0.5 * np.array([agent.model.length or 0.0, agent.model.width or 0.0])


def _agent_state(vector: list[float], dim: int, car: bool) -> np.ndarray:
    """A start or goal as a state of the agent's own model, in a swarm with cars (2D): a car's
    pose [x, y, heading_deg(, speed)] as [x, y, heading (rad), speed], a point agent's position
    (at rest) or state as it is."""
    values = np.asarray(vector, float)
    if car:
        speed = values[3] if values.size == 4 else 0.0
        return np.array([values[0], values[1], math.radians(values[2]), speed])
    return _full_state(vector, dim)


def _model_state(vector: list[float], dim: int, model: AgentModel) -> np.ndarray:
    """A start or goal as a state of ``model``: a position (d values) at rest, or a position and
    a velocity (2d values)."""
    values = np.asarray(vector, float)
    return model.state_at(values[:dim], values[dim:] if values.size > dim else None)


def estimated_run_bytes(scn: Scenario) -> tuple[int, int]:
    """Rough memory of a run's arrays, in bytes: (what the run records, what the solver holds).

    The record is (max_steps + 1) steps x M agents of the state (2d), input (d) and disturbance
    (2d) plus four per-agent solver figures; the solver, horizon x M agents of a state, an input
    and one dual per obstacle facet. It is a lower bound (CasADi's graphs come on top), so a
    scenario above :data:`MAX_RUN_BYTES` is refused before it exhausts the machine half way.
    """
    m, d = scn.num_agents, scn.dim
    facets = sum(2 * d if ob.polytope is None else len(ob.polytope.G) for ob in scn.obstacles)
    record = (scn.stop.max_steps + 1) * m * (5 * d + 4)
    solver = scn.horizon * m * (3 * d + facets)
    return 8 * record, 8 * solver


def _size_errors(scn: Scenario) -> list[str]:
    """The run's estimated memory above :data:`MAX_RUN_BYTES`, naming its larger contributor."""
    record, solver = estimated_run_bytes(scn)
    if record + solver <= MAX_RUN_BYTES:
        return []
    total = (record + solver) / 1024**3
    bound = f"above the bound of {MAX_RUN_BYTES / 1024**3:g} GiB"
    if record >= solver:
        return [f"stop.max_steps: {scn.stop.max_steps} steps of {scn.num_agents} agents need about "
                f"{total:.1f} GiB of arrays, {bound}; lower stop.max_steps or the number of agents"]
    return [f"horizon: a horizon of {scn.horizon} for {scn.num_agents} agents and {len(scn.obstacles)} "
            f"obstacles needs about {total:.1f} GiB of arrays, {bound}"]


def _weight_error(which: str, value: ScalarOrMatrix, size: int) -> str | None:
    """What is wrong with the weight ``which`` for a ``size`` x ``size`` matrix, if anything."""
    if isinstance(value, str):  # Qf: lqr, checked by Weights itself
        return None
    if not isinstance(value, list):
        if value < 0:
            return f"weights.{which}: must be >= 0"
        return "weights.R: must be > 0" if which == "R" and value <= 0 else None
    if len(value) != size or any(not isinstance(row, list) or len(row) != size for row in value):
        return f"weights.{which}: expected a scalar or a {size}x{size} matrix"
    matrix = np.asarray(value, float)
    if not np.allclose(matrix, matrix.T) or np.min(np.linalg.eigvalsh(matrix)) < 0:
        return f"weights.{which}: must be symmetric positive semidefinite"
    return None


def _agent_model_errors(scn: Scenario, n: int) -> list[str]:
    """What agent ``n``'s model cannot do in this scenario (a car: planar, no ADMM deadline, a
    numeric terminal weight, the nominal plant without noise), each a message naming the field."""
    if not scn.agents[n].model.is_car:
        return []
    problems = {
        f"agents[{n}].model: a car moves in the plane only (dim 2), got dim {scn.dim}": scn.dim != 2,
        "solver.deadline: the ADMM of a swarm with cars has no deadline (it runs each step to its tolerance); "
        "remove the key": scn.solver.method == "admm" and scn.solver.deadline is not None,
        f"weights.Qf: lqr needs a linear model and agents[{n}] is a car; give a number or a matrix "
        "(e.g. Qf: 10)": scn.weights.Qf == "lqr",
        "plant.type: mujoco simulates point agents only, not car agents": scn.plant.type == "mujoco",
        "disturbance: noise and tightening do not apply to car agents yet (keep the section at zero)":
            scn.disturbance != Disturbance(),
    }
    return [message for message, wrong in problems.items() if wrong][:1]


def _shape_errors(scn: Scenario) -> list[str]:
    """Lengths that must match ``dim`` and the scalar rules of single fields, each a message
    that starts with the field path."""
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
        error = _weight_error(which, getattr(scn.weights, which), d if which == "R" else 2 * d)
        if error is not None:
            errors.append(error)
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
    if scn.solver.admm.independent_first is True and scn.has_cars:
        errors.append("solver.admm.independent_first: applies to a swarm of point agents; the ADMM of a swarm with "
                      "cars has no probe of the agents' own optima")
    if scn.solver.admm.pair_copies != "both" and not scn.has_cars:
        errors.append(f"solver.admm.pair_copies: {scn.solver.admm.pair_copies} applies to the ADMM of a swarm with "
                      "cars; a swarm of point agents keeps both")
    for n, agent in enumerate(scn.agents):
        errors.extend(_agent_model_errors(scn, n))
        for field in ("start", "goal"):
            size = len(getattr(agent, field))
            if agent.model.is_car and d == 2:
                if size not in (3, 4):
                    errors.append(f"agents[{n}].{field}: a car takes a pose [x, y, heading_deg] or "
                                  f"[x, y, heading_deg, speed], got {size} values")
            elif size == 3 and d == 2:
                errors.append(f"agents[{n}].{field}: 3 values give a heading, which only a car has (model: car); "
                              "a point agent takes 2 (position) or 4 (position, velocity)")
            elif size not in (d, 2 * d):
                errors.append(
                    f"agents[{n}].{field}: expected {d} (position) or {2 * d} (state) values "
                    f"for dim {d}, got {size}"
                )
        if isinstance(agent.body, list) and len(agent.body) != d:
            errors.append(f"agents[{n}].body: expected a scalar or {d} values for dim {d}, got {len(agent.body)}")
    return errors


def _consistency_errors(scn: Scenario) -> list[str]:
    """Cross-field checks, each a message that starts with the field path (the first only)."""
    errors = _shape_errors(scn)
    if errors:
        return errors[:1]
    if scn.executor.type != "serial" and scn.solver.method != "admm":
        return [f"executor.type: {scn.executor.type} only applies to solver.method admm, "
                f"this scenario uses {scn.solver.method}"]
    bodies = scn.bodies
    for field in ("start", "goal"):
        positions = np.array([_full_state(getattr(a, field), scn.dim)[: scn.dim] for a in scn.agents])
        if scn.has_cars:
            error = _footprint_overlap_error(scn, field) or _footprint_placement_error(scn, positions, field)
        else:
            error = _overlap_error(positions, bodies, field) or _placement_error(scn, positions, bodies, field)
        if error is not None:
            return [error]
    return []


def _footprints_at(scn: Scenario, field: str) -> tuple[np.ndarray, np.ndarray]:
    """(poses (M, 3), sizes (M, 2)) of every agent's footprint at its start or goal: a car's
    rectangle, a point agent's axis-aligned body box."""
    states = scn.start_states() if field == "start" else scn.goal_states()
    poses = np.zeros((scn.num_agents, 3))
    sizes = 2.0 * scn.bodies
    for i, (model, state) in enumerate(zip(scn.agent_models(), states, strict=True)):
        own = getattr(model, "pose", None)
        poses[i] = own(state) if callable(own) else (*state[:2], 0.0)
    return poses, sizes


def _footprint_overlap_error(scn: Scenario, field: str) -> str | None:
    """The first pair of agents (one a car, or both points) whose footprints overlap at ``field``:
    a positive penetration depth by the exact rectangle distance (touching is allowed, as for the
    point agents' boxes); one numpy call per agent."""
    poses, sizes = _footprints_at(scn, field)
    for i in range(len(poses) - 1):
        distance = rectangle_distance(poses[i], sizes[i], poses[i + 1 :], sizes[i + 1 :], signed=True)
        inside = np.flatnonzero(distance < 0)
        if inside.size:
            j = i + 1 + int(inside[0])
            return (f"agents[{j}].{field}: the footprints of agents[{i}] and agents[{j}] overlap there "
                    f"(by {-float(distance[inside[0]]):.3g} m, exact rectangle distance)")
    return None


def _obstacle_polygons(scn: Scenario) -> list[np.ndarray | None]:
    """Each obstacle's vertices (n, 2), clipped to the workspace grown by 100 m so that an
    unbounded polytope has a finite polygon (None: the obstacle is empty or flat there)."""
    lower, upper = scn.bounds()
    lower, upper = lower - 100.0, upper + 100.0
    polygons: list[np.ndarray | None] = []
    for G, g in scn.obstacle_halfspaces():
        try:
            polygons.append(polygon_vertices(np.vstack([G, np.eye(2), -np.eye(2)]), np.concatenate([g, upper, -lower])))
        except ValueError:
            polygons.append(None)
    return polygons


def _footprint_placement_error(scn: Scenario, positions: np.ndarray, field: str) -> str | None:
    """The first agent outside the workspace, or whose footprint reaches into an obstacle: a point
    agent's body box as without cars, a car's rectangle by the exact distance (touching counts)."""
    error = _placement_error(scn, positions, scn.bodies, field, points_only=True)
    if error is not None or not scn.obstacles:
        return error
    poses, sizes = _footprints_at(scn, field)
    for n, polygon in enumerate(_obstacle_polygons(scn)):
        if polygon is None:
            continue
        for i, agent in enumerate(scn.agents):
            if agent.model.is_car and polygon_distance(footprint_vertices(poses[i], sizes[i]), polygon) <= 0:
                return (f"agents[{i}].{field}: the car's footprint at {positions[i].tolist()} reaches inside "
                        f"obstacles[{n}]")
    return None


def _overlap_error(positions: np.ndarray, bodies: np.ndarray, field: str) -> str | None:
    """The first pair of agents whose bodies overlap at ``positions``, if any: centres closer than
    b_i + b_j (Δ with default bodies) on every axis."""
    for i in range(len(positions) - 1):  # one row of pairs at a time: O(M) numpy calls
        gaps = np.abs(positions[i + 1 :] - positions[i])
        reach = bodies[i + 1 :] + bodies[i]
        inside = np.flatnonzero(np.all(gaps < reach, axis=1))
        if inside.size:
            k = int(inside[0])
            j = i + 1 + k
            return (f"agents[{j}].{field}: within delta of agents[{i}].{field}, their bodies overlap "
                    f"(gaps {_rounded(gaps[k])} < b_{i} + b_{j} = {_rounded(reach[k])} on every axis)")
    return None


def _rounded(values: np.ndarray) -> list[float]:
    return [float(f"{v:.3g}") for v in values]


def _placement_error(
    scn: Scenario, positions: np.ndarray, bodies: np.ndarray, field: str, points_only: bool = False
) -> str | None:
    """The first agent whose centre lies outside the workspace or whose body reaches into an
    obstacle (the obstacle grown by that agent's body contains its centre), if any; one numpy
    call per obstacle, not per agent and obstacle. The workspace bounds centres, as in the OCPs
    (a car's reference point). ``points_only``: the obstacles are checked for point agents only."""
    outside = np.zeros(len(positions), bool)
    if scn.workspace is not None:
        lo, hi = np.asarray(scn.workspace.lower), np.asarray(scn.workspace.upper)
        outside = np.any((positions < lo) | (positions > hi), axis=1)
    inside = np.zeros((len(positions), len(scn.obstacles)), bool)
    for k, (G, g) in enumerate(scn.obstacle_halfspaces()):
        inside[:, k] = np.all(positions @ G.T <= g + bodies @ np.abs(G).T, axis=1)
    if points_only:
        inside[[a.model.is_car for a in scn.agents]] = False
    bad = np.flatnonzero(outside | inside.any(axis=1))
    if not bad.size:
        return None
    n = int(bad[0])
    if outside[n]:
        return f"agents[{n}].{field}: {positions[n].tolist()} is outside the workspace"
    return (f"agents[{n}].{field}: the body (half-size {_rounded(bodies[n])}) at {positions[n].tolist()} "
            f"reaches inside obstacles[{int(np.argmax(inside[n]))}]")


_FIELD_PREFIX = re.compile(r"^[A-Za-z_][\w\[\].]*: ")
_TYPE_TAGS = frozenset(
    {"float", "int", "list[float]", "list[list[float]]", "function-after", "function-before", "[key]"}
)


def _location(loc: tuple[Any, ...]) -> str:
    """A pydantic error location as a dotted path; a key that is not a plain name is quoted, so
    that a key holding ': ' or a line break cannot pass for another field or another line."""
    location = ""
    for part in loc:
        if isinstance(part, int):
            location += f"[{part}]"
        elif str(part) not in _TYPE_TAGS:
            text = str(part)
            location += ("." if location else "") + (text if _PLAIN_KEY.fullmatch(text) else short_repr(text))
    return location


def _format_validation_error(err: ValidationError) -> str:
    """One line: the dotted path of the first offending field, then what is wrong with it."""
    first = err.errors()[0]
    location = _location(first["loc"])
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
    odd = next((key for key in data if not isinstance(key, str)), None)
    if odd is not None:
        raise ScenarioError(f"{source}: keys must be text, got {short_repr(odd)}")
    try:
        return Scenario.model_validate(data)
    except ValidationError as err:
        raise ScenarioError(_format_validation_error(err)) from None
    except RecursionError:
        raise ScenarioError(f"{source}: nested too deeply") from None


# ------------------------------------------------------------------ bounded YAML
class _Refused(Exception):
    """YAML that is well formed but beyond a bound (or a duplicate key), with where it is."""

    def __init__(self, problem: str, mark: Any = None) -> None:
        super().__init__(problem)
        self.problem = problem
        self.mark = mark


class _BoundedLoader(yaml.SafeLoader):
    """yaml's SafeLoader (no tag runs code) that refuses nesting deeper than
    :data:`MAX_YAML_DEPTH` while composing (before Python's recursion limit is near), refuses a
    mapping that repeats a key, and turns a value its constructors cannot convert (a 5000-digit
    integer, 31 February) into a refusal at the value's line."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self.depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.depth >= MAX_YAML_DEPTH:
            event = self.peek_event()  # type: ignore[no-untyped-call]  # PyYAML's stubs leave it unannotated
            raise _Refused(f"nested deeper than {MAX_YAML_DEPTH} levels", event.start_mark)
        self.depth += 1
        try:
            return super().compose_node(parent, index)
        finally:
            self.depth -= 1

    def construct_object(self, node: Any, deep: bool = False) -> Any:
        try:
            return super().construct_object(node, deep)
        except (ValueError, OverflowError) as err:
            raise _Refused(f"cannot read a value ({err.__class__.__name__})", node.start_mark) from None

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        if isinstance(node, yaml.MappingNode):
            _refuse_duplicate_keys(self, node)
        return super().construct_mapping(node, deep)


def _refuse_duplicate_keys(loader: _BoundedLoader, node: yaml.MappingNode) -> None:
    """Raise :class:`_Refused` at the second occurrence of a key written twice in one mapping
    (yaml itself keeps the last one silently); merge keys (``<<``) may override, as YAML intends."""
    seen: dict[Any, int] = {}
    for key_node, _value in node.value:
        if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == "tag:yaml.org,2002:merge":
            continue
        key = loader.construct_object(key_node)
        try:
            first = seen.get(key)
        except TypeError:  # unhashable: yaml's own constructor reports it
            continue
        if first is not None:
            raise _Refused(f"duplicate key {short_repr(key)} (first at line {first})", key_node.start_mark)
        seen[key] = key_node.start_mark.line + 1


def _expanded_size(node: yaml.Node, sizes: dict[int, tuple[int, int]], depth: int = 1) -> tuple[int, int]:
    """(values, levels) below and including ``node`` (at nesting ``depth``) with every alias
    expanded, memoised per node so that an alias bomb costs one visit per distinct node; raises
    :class:`_Refused` beyond the bounds or on an alias that contains itself."""
    known = sizes.get(id(node))
    if known is None:
        if depth > MAX_YAML_DEPTH:
            raise _Refused(f"nested deeper than {MAX_YAML_DEPTH} levels (aliases expanded)", node.start_mark)
        sizes[id(node)] = (-1, 0)
        known = _measure_children(node, sizes, depth)
        sizes[id(node)] = known
    elif known[0] < 0:
        raise _Refused("an alias refers to a node that contains it", node.start_mark)
    if depth - 1 + known[1] > MAX_YAML_DEPTH:  # an alias whose content reaches too deep from here
        raise _Refused(f"nested deeper than {MAX_YAML_DEPTH} levels (aliases expanded)", node.start_mark)
    return known


def _measure_children(node: yaml.Node, sizes: dict[int, tuple[int, int]], depth: int) -> tuple[int, int]:
    """(values, levels) of ``node`` from its children's, see :func:`_expanded_size`."""
    children: list[Any] = []
    if isinstance(node, yaml.SequenceNode):
        children = node.value
    elif isinstance(node, yaml.MappingNode):
        children = [item for pair in node.value for item in pair]
    count, levels = 1, 1
    for child in children:
        child_count, child_levels = _expanded_size(child, sizes, depth + 1)
        count += child_count
        levels = max(levels, child_levels + 1)
        if count > MAX_YAML_NODES:
            raise _Refused(f"more than {MAX_YAML_NODES} values with aliases expanded", node.start_mark)
    return count, levels


def _load_bounded(text: str) -> Any:
    """The data of one YAML document, composed and measured before anything is constructed."""
    loader = _BoundedLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _expanded_size(node, {})
        return loader.construct_document(node)
    finally:
        loader.dispose()


def parse_yaml_text(text: str, source: str) -> Any:
    """Parse YAML ``text`` safely and within bounds; ``source`` (a file name) starts every message.

    Refused with a one-line :class:`ScenarioError`: text above :data:`MAX_FILE_BYTES`, nesting
    deeper than :data:`MAX_YAML_DEPTH`, more than :data:`MAX_YAML_NODES` values once aliases are
    expanded (a "billion laughs" bomb is refused after one visit per distinct node), a key
    repeated in one mapping, malformed YAML. Tags beyond yaml's safe set are refused, never run.
    """
    size = len(text.encode("utf-8", errors="surrogatepass"))
    if size > MAX_FILE_BYTES:
        raise ScenarioError(f"{source}: {size} bytes, more than a scenario file may have ({MAX_FILE_BYTES} bytes)")
    try:
        return _load_bounded(text)
    except _Refused as err:
        where = f" at line {err.mark.line + 1}" if err.mark is not None else ""
        raise ScenarioError(f"{source}: {err.problem}{where}") from None
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise ScenarioError(f"{source}: malformed YAML{where}") from None
    except RecursionError:
        raise ScenarioError(f"{source}: malformed YAML (nested too deeply)") from None


_FILE_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
               (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def _not_regular(mode: int) -> str | None:
    """What a file of ``mode`` is when it is not a regular file; None for a regular file."""
    if stat.S_ISREG(mode):
        return None
    return next((name for test, name in _FILE_KINDS if test(mode)), "not a regular file")


def _open_without_blocking(path: str, flags: int) -> int:
    """``open``'s opener: a FIFO swapped in after the check must not block the open."""
    return os.open(path, flags | getattr(os, "O_NONBLOCK", 0))


def _check_regular(file: Path, info: os.stat_result) -> None:
    """Refuse anything but a regular file of at most :data:`MAX_FILE_BYTES` (a FIFO would block
    the read, a device might never end)."""
    kind = _not_regular(info.st_mode)
    if kind is not None:
        raise ScenarioError(f"{file}: cannot read scenario file ({kind}, not a regular file)")
    if info.st_size > MAX_FILE_BYTES:
        raise ScenarioError(
            f"{file}: {info.st_size} bytes, more than a scenario file may have ({MAX_FILE_BYTES} bytes)"
        )


def _read_scenario_text(file: Path) -> str:
    """The UTF-8 text of ``file``, checked with ``os.stat`` before it is opened, and again on the
    open file in case it was replaced in between; at most :data:`MAX_FILE_BYTES` are read."""
    try:
        _check_regular(file, os.stat(file))
        with open(file, "rb", opener=_open_without_blocking) as handle:
            _check_regular(file, os.fstat(handle.fileno()))
            raw = handle.read(MAX_FILE_BYTES + 1)
    except OSError as err:
        raise ScenarioError(f"{file}: cannot read scenario file ({err.__class__.__name__})") from None
    if len(raw) > MAX_FILE_BYTES:  # grew since the check
        raise ScenarioError(f"{file}: more than a scenario file may have ({MAX_FILE_BYTES} bytes)")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        raise ScenarioError(f"{file}: cannot read scenario file (UnicodeDecodeError)") from None


def load_scenario(path: str | Path) -> Scenario:
    """Read and validate a scenario YAML file (bounded: see :func:`parse_yaml_text`)."""
    file = Path(path)
    return scenario_from_dict(parse_yaml_text(_read_scenario_text(file), str(file)), source=str(file))


def scenario_to_yaml(scn: Scenario) -> str:
    """The scenario with every default filled in, as YAML that loads back to an equal scenario."""
    return yaml.safe_dump(scn.model_dump(), sort_keys=False)
