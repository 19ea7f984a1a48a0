"""Export a run folder for tools outside swarmpc: CSV for spreadsheets and scripts, MCAP for Foxglove.

* CSV (:func:`write_csv`): one row per state and agent, the columns of :data:`CSV_COLUMNS`
  (``step,t,agent,x,y[,z],vx,vy[,vz],ux,uy[,uz],nearest_m``); numbers are written with full
  precision (Python's ``repr``), so reading the file back gives the run's arrays exactly.
* MCAP (:func:`write_mcap`): the topics of :data:`MCAP_TOPICS`, scenes as Foxglove's
  ``foxglove.SceneUpdate`` (protobuf, the official ``foxglove-schemas-protobuf`` messages, with
  their descriptors embedded so any MCAP reader can decode them) and per-state metrics as JSON on
  ``/metrics`` (fields :data:`METRICS`, plottable in Foxglove's Plot panel). Time stamps are the
  run's ``t`` in nanoseconds; everything is in the frame :data:`FRAME_ID`, in metres.

Agents are drawn as their bodies (:func:`body_half_sizes`): boxes of half-size b_i per axis, Δ/2
by default. Δ is the clearance between two default bodies' centres (a collision is
‖p_i − p_j‖_∞ < Δ, in general |p_i,a − p_j,a| < b_i,a + b_j,a on every axis), so two bodies
overlap exactly when the pair counts as a collision. The files are written beside their target
under a temporary name and renamed into place when complete (:func:`export_run`), so a reader
never sees half a file.

The tables (:data:`CSV_COLUMNS`, :data:`MCAP_TOPICS`, :data:`METRICS`) both drive the writers and
generate their documentation (``docs/run-folder-reference.md``).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import secrets
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from itertools import product
from pathlib import Path
from typing import IO, Any

import numpy as np
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.CubePrimitive_pb2 import CubePrimitive
from foxglove_schemas_protobuf.KeyValuePair_pb2 import KeyValuePair
from foxglove_schemas_protobuf.LinePrimitive_pb2 import LinePrimitive
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.SceneEntity_pb2 import SceneEntity
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
from foxglove_schemas_protobuf.SpherePrimitive_pb2 import SpherePrimitive
from foxglove_schemas_protobuf.TextPrimitive_pb2 import TextPrimitive
from foxglove_schemas_protobuf.TriangleListPrimitive_pb2 import TriangleListPrimitive
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.descriptor_pb2 import FileDescriptorSet
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.writer import CompressionType, Writer

from swarmpc.config import Obstacle
from swarmpc.model.geometry import inf_separation_ratio, polytope_vertices
from swarmpc.palette import agent_colors
from swarmpc.simulation.outdir import OutputError, refuse_existing_file
from swarmpc.simulation.rundata import TRAJECTORY_FILE, RunData, RunDataError, load_run

__all__ = [
    "CSV_COLUMNS",
    "FORMATS",
    "FRAME_ID",
    "MCAP_TOPICS",
    "METRICS",
    "ColumnDoc",
    "MetricDoc",
    "TopicDoc",
    "body_half_sizes",
    "csv_header",
    "export_run",
    "metrics_json_schema",
    "metrics_record",
    "nearest_distances",
    "timestamps_ns",
    "write_csv",
    "write_mcap",
]

FORMATS = ("csv", "mcap")
FRAME_ID = "world"
"""The frame of every scene entity (positions are the run's, in metres)."""
TRAIL_SECONDS = 1.5
"""Length of the ``/trails`` lines: the last 1.5 s of each agent's path (as in the animation)."""
FLAT_HEIGHT_M = 0.05
"""Height of the slabs that stand for bodies and box obstacles of a 2D run (drawn at z = 0)."""
METRICS_SCHEMA = "swarmpc.Metrics"
AXES = "xyz"


# ------------------------------------------------------------------------------------ tables
@dataclass(frozen=True)
class ColumnDoc:
    """A CSV column; ``{axis}`` in the name stands for one column per axis (x, y and, in 3D, z)."""

    name: str
    units: str
    meaning: str


@dataclass(frozen=True)
class TopicDoc:
    """An MCAP topic: its schema, whether it has one message per state (else one at ``t[0]``)."""

    topic: str
    schema: str
    per_state: bool
    meaning: str

    @property
    def messages(self) -> str:
        """How many messages the topic has, in the terms of the run-folder reference."""
        return "T+1" if self.per_state else "1"


@dataclass(frozen=True)
class MetricDoc:
    """A field of the ``/metrics`` JSON messages (``type`` is its JSON-schema type)."""

    name: str
    type: str
    units: str
    meaning: str


CSV_COLUMNS: tuple[ColumnDoc, ...] = (
    ColumnDoc("step", "–", "Index k of the state, 0 … T."),
    ColumnDoc("t", "s", "Time of the state (`trajectory.npz` `t[k]`)."),
    ColumnDoc("agent", "–", "Agent index i, 0-based, in the scenario's order."),
    ColumnDoc("{axis}", "m", "Position of the agent's centre; `z` only in 3D runs."),
    ColumnDoc("v{axis}", "m/s", "Velocity."),
    ColumnDoc(
        "u{axis}", "m/s²",
        "Input (acceleration) applied from this state to the next, `inputs[k]`; empty on the last state "
        "of the run (no input follows it) and where the run recorded none.",
    ),
    ColumnDoc(
        "nearest_m", "m",
        "Euclidean distance between this agent's centre and the nearest other agent's at this state; "
        "empty with one agent. (Collisions are judged per axis between the bodies, see `summary.json` "
        "`collisions`.)",
    ),
)

MCAP_TOPICS: tuple[TopicDoc, ...] = (
    TopicDoc(
        "/world", "foxglove.SceneUpdate", False,
        "Obstacles (`obstacle/<n>`: boxes as cubes, polytopes as triangle lists, in 2D with an outline), the "
        "workspace outline (`workspace`) and each agent's goal (`goal/<i>`: a sphere of radius "
        "`stop.goal_tolerance` inside the outline of the agent's body).",
    ),
    TopicDoc(
        "/paths", "foxglove.SceneUpdate", False,
        "Each agent's whole closed-loop path (`path/<i>`), a line strip.",
    ),
    TopicDoc(
        "/agents", "foxglove.SceneUpdate", True,
        "Each agent's body at `t[k]` (`agent/<i>`): a box of the body's half-size per axis (Δ/2 unless "
        "`agents[].body` sets it), labelled with the index. Δ is the clearance between two default bodies' "
        "centres, so two bodies overlap exactly when the pair counts as a collision "
        f"(a 2D body is a slab of height {FLAT_HEIGHT_M:g} m at z = 0).",
    ),
    TopicDoc(
        "/trails", "foxglove.SceneUpdate", True,
        f"Each agent's path over the last {TRAIL_SECONDS:g} s up to `t[k]` (`trail/<i>`).",
    ),
    TopicDoc(
        "/metrics", METRICS_SCHEMA, True,
        "JSON, one message per state with the fields below (plot e.g. `/metrics.min_distance_m`).",
    ),
)

METRICS: tuple[MetricDoc, ...] = (
    MetricDoc("step", "integer", "–", "Index k of the state."),
    MetricDoc("t_s", "number", "s", "Time `t[k]`."),
    MetricDoc(
        "min_distance_m", "number", "m",
        "Smallest Euclidean distance between two agents' centres at `t[k]` (the smallest CSV `nearest_m`); "
        "absent with one agent.",
    ),
    MetricDoc("min_separation_inf_m", "number", "m", "Smallest ‖p_i − p_j‖_∞ at `t[k]`; absent with one agent."),
    MetricDoc(
        "min_separation_ratio", "number", "–",
        "Smallest max_a |p_i,a − p_j,a| / (b_i,a + b_j,a) at `t[k]` (/ Δ_a with default bodies); < 1 is a "
        "collision; absent with one agent.",
    ),
    MetricDoc(
        "step_time_ms", "number", "ms",
        "Wall time of the solve at `t[k]` that chose `inputs[k]` (`steps.npz`); absent on the last state.",
    ),
    MetricDoc("solver_failures", "integer", "–", "Failed solve calls of that solve; absent on the last state."),
    MetricDoc("max_slack", "number", "m", "Largest soft-constraint slack of that solve; absent on the last state."),
    MetricDoc(
        "admm_iterations", "integer", "–",
        "ADMM iterations of that solve (`admm.npz`); ADMM runs only, absent on the last state.",
    ),
)


def csv_header(dim: int) -> list[str]:
    """The CSV column names of a run in ``dim`` dimensions (``{axis}`` expanded)."""
    names: list[str] = []
    for column in CSV_COLUMNS:
        if "{axis}" in column.name:
            names.extend(column.name.format(axis=axis) for axis in AXES[:dim])
        else:
            names.append(column.name)
    return names


def metrics_json_schema() -> dict[str, Any]:
    """The JSON schema of the ``/metrics`` messages (embedded in the MCAP file, read by Foxglove)."""
    return {
        "title": METRICS_SCHEMA,
        "description": "swarmpc per-state metrics of a run",
        "type": "object",
        "properties": {m.name: {"type": m.type, "description": f"{m.meaning} [{m.units}]"} for m in METRICS},
        "required": ["step", "t_s"],
    }


# ------------------------------------------------------------------------------------ the entry
def export_run(run_dir: str | Path, fmt: str, out: str | Path | None = None, overwrite: bool = False) -> Path:
    """Export the run folder ``run_dir`` as ``fmt`` (``csv`` or ``mcap``); return the written file.

    ``out`` defaults to ``RUN_DIR/run.<fmt>`` (replaced when present); an explicit ``out`` that
    exists is replaced only with ``overwrite``. The file is written beside its target under a
    temporary name and renamed into place when complete.

    Raises
    ------
    ValueError
        ``fmt`` is not one of :data:`FORMATS`.
    OutputError
        ``out`` exists and may not be replaced, or the file cannot be written.
    RunDataError
        The run folder is missing or damaged (one line naming the file).
    """
    if fmt not in FORMATS:
        raise ValueError(f"format: must be {' or '.join(FORMATS)}, got {fmt!r}")
    target = Path(out) if out is not None else Path(run_dir) / f"run.{fmt}"
    if out is not None:
        refuse_existing_file(target, overwrite)
    # the CSV needs only the trajectory; the scene needs the scenario's obstacles and goal tolerance
    run = load_run(run_dir, require_scenario=fmt == "mcap")
    if fmt == "csv":
        _write_beside(target, _as_text(lambda stream: write_csv(run, stream)))
    else:
        _write_beside(target, lambda stream: write_mcap(run, stream))
    return target


def _write_beside(target: Path, write: Callable[[IO[bytes]], None]) -> None:
    """Write ``target`` through a temporary file in its folder, renamed over it when complete.

    ``open(..., "xb")`` rather than :mod:`tempfile`: the file gets the user's usual permissions.
    """
    temporary = target.with_name(f".{target.name}.{secrets.token_hex(4)}.tmp")
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        with open(temporary, "xb") as stream:
            write(stream)
        os.replace(temporary, target)
    except OSError as err:
        temporary.unlink(missing_ok=True)
        raise OutputError(f"{target}: cannot write ({err.strerror or err})") from None
    except BaseException:
        temporary.unlink(missing_ok=True)
        raise


def _as_text(write_text: Callable[[IO[str]], None]) -> Callable[[IO[bytes]], None]:
    """A binary-stream writer that runs ``write_text`` on a UTF-8 view of the stream."""

    def write(stream: IO[bytes]) -> None:
        text = io.TextIOWrapper(stream, encoding="utf-8", newline="")
        try:
            write_text(text)
            text.flush()
        finally:
            text.detach()  # leave the binary stream to its owner

    return write


# ------------------------------------------------------------------------------------ geometry
def nearest_distances(positions: np.ndarray) -> np.ndarray:
    """(M,) Euclidean distance from each centre in ``positions`` (M, d) to the nearest other one
    (inf with one agent)."""
    gaps = positions[:, None, :] - positions[None, :, :]
    distances = np.sqrt(np.sum(gaps * gaps, axis=-1))
    np.fill_diagonal(distances, np.inf)
    return distances.min(axis=1)


def body_half_sizes(run: RunData) -> np.ndarray:
    """(M, d) half-size of each agent's body per axis, as the run recorded them (Δ/2 for a run
    written before bodies were recorded): two bodies overlap exactly when a collision is counted."""
    return np.asarray(run.body_half_sizes, float)


def timestamps_ns(run: RunData) -> np.ndarray:
    """(T+1,) MCAP time stamps [ns] of the states: the run's ``t``, which must be non-negative,
    non-decreasing and below 2⁶³ ns (:class:`RunDataError` otherwise)."""
    t = np.asarray(run.t, float)
    if np.any(t < 0) or np.any(np.diff(t) < 0) or np.any(t * 1e9 >= 2.0**63):
        raise RunDataError(
            f"{run.run_dir / TRAJECTORY_FILE}: 't' must be non-negative, non-decreasing and below 9.2e9 s "
            "to serve as time stamps"
        )
    return np.round(t * 1e9).astype(np.int64)


# ------------------------------------------------------------------------------------ CSV
def write_csv(run: RunData, stream: IO[str]) -> None:
    """One header row (:func:`csv_header`), then one row per state k and agent i."""
    writer = csv.writer(stream, lineterminator="\n")
    writer.writerow(csv_header(run.dim))
    steps, dim = run.num_steps, run.dim
    no_input = [""] * dim
    for k in range(steps + 1):
        nearest = nearest_distances(run.positions[k])
        for i in range(run.num_agents):
            inputs = [_number(u) for u in run.inputs[k, i]] if k < steps else no_input
            writer.writerow([
                k, _number(run.t[k]), i,
                *(_number(v) for v in run.states[k, i]),
                *inputs,
                _number(nearest[i]),
            ])  # fmt: skip


def _number(value: float) -> str:
    """A float with full precision (it reads back exactly); empty when not finite."""
    value = float(value)
    return repr(value) if math.isfinite(value) else ""


# ------------------------------------------------------------------------------------ metrics
def metrics_record(run: RunData, k: int) -> dict[str, Any]:
    """The ``/metrics`` fields of state ``k``: the :data:`METRICS` that are defined (and finite)
    there, integers as JSON integers."""
    record: dict[str, float] = {"step": k, "t_s": float(run.t[k])}
    positions = run.positions[k]
    if run.num_agents > 1:
        record["min_distance_m"] = float(nearest_distances(positions).min())
        record["min_separation_inf_m"] = float(inf_separation_ratio(positions, np.ones(run.dim)).min())
        bodies = body_half_sizes(run)
        pair_clearance = bodies[:, None, :] + bodies[None, :, :]  # Δ_ij = b_i + b_j per axis
        record["min_separation_ratio"] = float(inf_separation_ratio(positions, pair_clearance).min())
    if k < run.num_steps:
        record.update(_solve_record(run, k))
    integers = {metric.name for metric in METRICS if metric.type == "integer"}
    return {
        name: int(value) if name in integers else float(value)
        for name, value in record.items()
        if math.isfinite(value)  # a damaged steps.npz may hold NaN: the field is left out
    }


def _solve_record(run: RunData, k: int) -> dict[str, float]:
    """The fields of the solve at step ``k`` that ``steps.npz`` and ``admm.npz`` hold."""
    record = {}
    for name, key, scale in (("step_time_ms", "step_time_s", 1000.0), ("solver_failures", "failures", 1.0),
                             ("max_slack", "max_slack", 1.0)):
        if key in run.steps:
            record[name] = scale * float(run.steps[key][k])
    if run.admm is not None:
        record["admm_iterations"] = float(run.admm.iterations[k])
    return record


# ------------------------------------------------------------------------------------ MCAP
def write_mcap(run: RunData, stream: IO[bytes]) -> None:
    """The MCAP file of a run: the :data:`MCAP_TOPICS`, static topics at ``t[0]``, then every
    per-state topic at each ``t[k]``, in time order. ``run.scenario`` must be set."""
    from swarmpc import __version__

    if run.scenario is None:
        raise RunDataError(f"{run.run_dir}: an MCAP export needs the run's scenario.yaml")
    times = timestamps_ns(run)
    writer = Writer(stream, compression=CompressionType.ZSTD)
    writer.start(profile="", library=f"swarmpc {__version__}")
    channels = _register_channels(writer)
    builders = _message_builders(run, times)
    sequence = dict.fromkeys(channels, 0)
    for k, doc in _message_order(run.num_steps):
        writer.add_message(
            channels[doc.topic], log_time=int(times[k]), data=builders[doc.topic](k),
            publish_time=int(times[k]), sequence=sequence[doc.topic],
        )
        sequence[doc.topic] += 1
    writer.finish()


def _message_order(steps: int) -> Iterator[tuple[int, TopicDoc]]:
    """(state index, topic) of every message in time order: the static topics first."""
    for doc in MCAP_TOPICS:
        if not doc.per_state:
            yield 0, doc
    for k in range(steps + 1):
        for doc in MCAP_TOPICS:
            if doc.per_state:
                yield k, doc


def _register_channels(writer: Writer) -> dict[str, int]:
    """Register each schema once and a channel per topic; topic -> channel id."""
    schemas: dict[str, tuple[int, str]] = {}
    channels = {}
    for doc in MCAP_TOPICS:
        if doc.schema not in schemas:
            encoding, data, message_encoding = _schema(doc.schema)
            schemas[doc.schema] = (writer.register_schema(doc.schema, encoding, data), message_encoding)
        schema_id, message_encoding = schemas[doc.schema]
        channels[doc.topic] = writer.register_channel(doc.topic, message_encoding, schema_id)
    return channels


def _schema(name: str) -> tuple[str, bytes, str]:
    """(schema encoding, schema data, message encoding) of the schema ``name``."""
    if name == METRICS_SCHEMA:
        return "jsonschema", json.dumps(metrics_json_schema()).encode(), "json"
    if name == SceneUpdate.DESCRIPTOR.full_name:
        return "protobuf", _descriptor_set(SceneUpdate), "protobuf"
    raise ValueError(f"no schema named {name!r}")


def _descriptor_set(message_class: Any) -> bytes:
    """The serialised ``FileDescriptorSet`` of a protobuf message: its file and every file it
    imports, dependencies first (what MCAP's protobuf encoding asks for, so a reader such as
    Foxglove decodes the messages without knowing them beforehand)."""
    files = FileDescriptorSet()
    seen: set[str] = set()

    def add(file: Any) -> None:
        if file.name in seen:
            return
        seen.add(file.name)
        for dependency in file.dependencies:
            add(dependency)
        file.CopyToProto(files.file.add())

    add(message_class.DESCRIPTOR.file)
    return files.SerializeToString()


def _message_builders(run: RunData, times: np.ndarray) -> dict[str, Callable[[int], bytes]]:
    """Per topic of :data:`MCAP_TOPICS`: the serialised message of state ``k``."""
    scene = _Scene(run, times)

    def scene_update(entities: Callable[[int], list[SceneEntity]]) -> Callable[[int], bytes]:
        return lambda k: SceneUpdate(entities=entities(k)).SerializeToString()

    return {
        "/world": scene_update(scene.world),
        "/paths": scene_update(scene.paths),
        "/agents": scene_update(scene.agents),
        "/trails": scene_update(scene.trails),
        "/metrics": lambda k: json.dumps(metrics_record(run, k), allow_nan=False).encode(),
    }


GREY = (0.55, 0.55, 0.55)
LABEL_COLOR = (0.1, 0.1, 0.1)


class _Scene:
    """The Foxglove scene entities of one run, per state ``k`` (time stamped ``times[k]``)."""

    def __init__(self, run: RunData, times: np.ndarray) -> None:
        self.run = run
        self.times = times
        self.colors = agent_colors(run.num_agents)
        self.trail_steps = max(1, round(TRAIL_SECONDS / run.dt))
        self.bodies = body_half_sizes(run)

    def world(self, k: int) -> list[SceneEntity]:
        """Obstacles, the workspace outline and the goals."""
        run, scenario = self.run, self.run.scenario
        assert scenario is not None
        entities = [self._obstacle(n, obstacle, k) for n, obstacle in enumerate(scenario.obstacles)]
        if scenario.workspace is not None:
            lower = np.asarray(scenario.workspace.lower, float)
            upper = np.asarray(scenario.workspace.upper, float)
            outline = _box_outline((lower + upper) / 2, (upper - lower) / 2, _color(GREY), 0.02)
            entities.append(self._entity("workspace", k, lines=[outline]))
        diameter = 2 * scenario.stop.goal_tolerance
        for i, goal in enumerate(run.goal_positions):
            sphere = SpherePrimitive(pose=_pose(goal), size=_vector([diameter] * 3), color=_color(self.colors[i], 0.8))
            outline = _box_outline(goal, self.bodies[i], _color(self.colors[i]), 0.015)
            entities.append(self._entity(f"goal/{i}", k, spheres=[sphere], lines=[outline]))
        return entities

    def paths(self, k: int) -> list[SceneEntity]:
        """Each agent's whole path."""
        return [
            self._entity(f"path/{i}", k, lines=[_line(self.run.positions[:, i], _color(self.colors[i], 0.35), 0.015)])
            for i in range(self.run.num_agents)
        ]

    def agents(self, k: int) -> list[SceneEntity]:
        """Each agent's body at state ``k``, labelled with its index."""
        entities = []
        for i, position in enumerate(self.run.positions[k]):
            size = _slab_or_cube(2 * self.bodies[i])
            cube = CubePrimitive(pose=_pose(position), size=size, color=_color(self.colors[i], 0.7))
            above = _xyz(position) + np.array([0.0, 0.0, size.z / 2 + 0.05])
            label = TextPrimitive(pose=_pose(above), billboard=True, font_size=14.0, scale_invariant=True,
                                  color=_color(LABEL_COLOR), text=str(i))
            entities.append(self._entity(f"agent/{i}", k, self._body_note(i), cubes=[cube], texts=[label]))
        return entities

    def _body_note(self, i: int) -> dict[str, str]:
        """The metadata of agent ``i``'s entity: what its box stands for."""
        half = ", ".join(f"{h:g}" for h in self.bodies[i])
        return {
            "agent": str(i),
            "body": f"box of half-size ({half}) m per axis (Δ/2 by default): two bodies overlap exactly when the "
                    "pair counts as a collision",
        }

    def trails(self, k: int) -> list[SceneEntity]:
        """Each agent's last :data:`TRAIL_SECONDS` of path up to state ``k``."""
        recent = self.run.positions[max(0, k - self.trail_steps) : k + 1]
        return [
            self._entity(f"trail/{i}", k, lines=[_line(recent[:, i], _color(self.colors[i]), 0.03)])
            for i in range(self.run.num_agents)
        ]

    def _obstacle(self, n: int, obstacle: Obstacle, k: int) -> SceneEntity:
        """A box as a cube; a polytope as triangles (with its outline in 2D), clipped to the scene."""
        if obstacle.box is not None:
            size = _slab_or_cube(2 * np.asarray(obstacle.box.half_size, float))
            cube = CubePrimitive(pose=_pose(obstacle.box.center), size=size, color=_color(GREY, 0.8))
            return self._entity(f"obstacle/{n}", k, cubes=[cube])
        polytope = obstacle.polytope
        assert polytope is not None
        vertices = self._polytope_vertices(np.asarray(polytope.G, float), np.asarray(polytope.g, float))
        if len(vertices) <= self.run.dim:
            return self._entity(f"obstacle/{n}", k)  # empty or flat within the scene: nothing to draw
        mesh = TriangleListPrimitive(pose=_pose(np.zeros(3)), points=[_point(p) for p in _triangles(vertices)],
                                     color=_color(GREY, 0.6))
        lines = [_line(np.vstack([vertices, vertices[:1]]), _color(GREY), 0.02)] if self.run.dim == 2 else []
        return self._entity(f"obstacle/{n}", k, triangles=[mesh], lines=lines)

    def _polytope_vertices(self, G: np.ndarray, g: np.ndarray) -> np.ndarray:
        """Vertices of {p : G p <= g}, clipped 1 m beyond the workspace and the run's positions."""
        run, scenario = self.run, self.run.scenario
        assert scenario is not None
        lower, upper = scenario.bounds()
        points = np.vstack([run.positions.reshape(-1, run.dim), run.goal_positions])
        lower = np.minimum(lower, points.min(axis=0)) - 1.0
        upper = np.maximum(upper, points.max(axis=0)) + 1.0
        return polytope_vertices(G, g, (lower, upper))

    def _entity(
        self, entity_id: str, k: int, metadata: dict[str, str] | None = None, **primitives: Any
    ) -> SceneEntity:
        """An entity in :data:`FRAME_ID` stamped ``times[k]``; it replaces the entity of the same
        id from an earlier message (no lifetime: it stays until then)."""
        ns = int(self.times[k])
        return SceneEntity(
            timestamp=Timestamp(seconds=ns // 1_000_000_000, nanos=ns % 1_000_000_000),
            frame_id=FRAME_ID,
            id=entity_id,
            metadata=[KeyValuePair(key=key, value=value) for key, value in (metadata or {}).items()],
            **primitives,
        )


def _triangles(vertices: np.ndarray) -> np.ndarray:
    """(3n, d) corners of triangles that cover a convex polygon (a fan over its counter-clockwise
    vertices, d = 2) or the surface of a convex polyhedron (its hull's facets, d = 3)."""
    if vertices.shape[1] == 2:
        return np.array([vertices[j] for i in range(1, len(vertices) - 1) for j in (0, i, i + 1)])
    from scipy.spatial import ConvexHull

    hull = ConvexHull(vertices)
    return hull.points[hull.simplices.reshape(-1)]


def _line(points: np.ndarray, color: Color, thickness: float) -> LinePrimitive:
    """A line strip through ``points`` (n, d); ``thickness`` in metres."""
    return LinePrimitive(type=LinePrimitive.LINE_STRIP, pose=_pose(np.zeros(3)), thickness=thickness,
                         points=[_point(p) for p in points], color=color)


def _box_outline(center: Any, half: Any, color: Color, thickness: float) -> LinePrimitive:
    """The edges of an axis-aligned box: a rectangle at z = 0 in 2D, twelve segments in 3D."""
    center, half = np.asarray(center, float), np.asarray(half, float)
    if center.size == 2:
        corners = center + half * np.array([(-1, -1), (1, -1), (1, 1), (-1, 1)])
        kind, points = LinePrimitive.LINE_LOOP, list(corners)
    else:
        signs = np.array(list(product((-1, 1), repeat=3)))
        edges = [(a, b) for a in range(8) for b in range(a + 1, 8) if np.sum(signs[a] != signs[b]) == 1]
        kind, points = LinePrimitive.LINE_LIST, [center + half * signs[j] for edge in edges for j in edge]
    return LinePrimitive(type=kind, pose=_pose(np.zeros(3)), thickness=thickness,
                         points=[_point(p) for p in points], color=color)


def _slab_or_cube(edges: np.ndarray) -> Vector3:
    """Edge lengths of a box with ``edges`` per axis: in 2D a slab :data:`FLAT_HEIGHT_M` high."""
    edges = np.asarray(edges, float)
    return _vector(edges if edges.size == 3 else [*edges, FLAT_HEIGHT_M])


def _xyz(position: Any) -> np.ndarray:
    """A position as three coordinates (z = 0 in 2D)."""
    values = np.asarray(position, float).reshape(-1)
    return np.concatenate([values, np.zeros(3 - values.size)])


def _pose(position: Any) -> Pose:
    """A pose at ``position``, not rotated (the identity quaternion: protobuf's default is all zeros)."""
    return Pose(position=_vector(_xyz(position)), orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0))


def _vector(values: Any) -> Vector3:
    x, y, z = (float(v) for v in values)
    return Vector3(x=x, y=y, z=z)


def _point(position: Any) -> Point3:
    x, y, z = (float(v) for v in _xyz(position))
    return Point3(x=x, y=y, z=z)


def _color(rgb: str | tuple[float, float, float], alpha: float = 1.0) -> Color:
    """A Foxglove colour from ``rgb`` (a ``#rrggbb`` string of :mod:`swarmpc.palette`, or three
    channels in [0, 1]) and ``alpha``."""
    if isinstance(rgb, str):
        rgb = tuple(int(rgb[i : i + 2], 16) / 255 for i in (1, 3, 5))  # type: ignore[assignment]
    r, g, b = (float(c) for c in rgb)
    return Color(r=r, g=g, b=b, a=float(alpha))
