"""Interactive HTML viewer of a run folder (the backend of ``swarmpc view RUN_DIR``).

:func:`build_figure` turns a run folder (``trajectory.npz``, ``summary.json``,
``scenario.yaml``) into an animated plotly figure; :func:`write_view` writes it as ONE
self-contained HTML file (plotly.js embedded, nothing fetched from a network), so the page
opens offline from a ``file://`` URL and can be attached to a report or an issue.

The page shows, in 2D and in 3D:

* per agent: its moving position marker (trace name ``agent i``), its body (drawn red while it
  overlaps another agent's body, i.e. exactly when the pair is counted as a collision): in 2D its
  footprint, the rectangle ``RunData.footprints`` at ``RunData.poses`` (a point agent's is the box
  of half-size b_i around it at heading 0; a turning agent's, a car's, also holds a heading tick
  from its centre to the middle of its front side), in 3D the box of half-size b_i; its trail
  (the path so far), its whole path (faint), start (circle) and goal (star in 2D, diamond in 3D)
  markers;
* the static obstacles (filled polygons in 2D, translucent hull meshes in 3D) and the
  workspace outline;
* animation frames over time (at most about 200), play/pause buttons and a time slider in
  seconds;
* a hover card on each agent: id, speed |v|, distance to its goal, and the distance to its
  nearest neighbour in the inf-norm and the Euclidean norm at that instant;
* the closest approach of the run (a marker at the midpoint of the closest pair at that
  instant, annotated ``closest approach: X m (inf-norm), t = Y s``) and a title with the
  scenario, method, collisions, the minimum separation over δ_ij = b_i + b_j and the bodies.

Every trace of the figure carries ``meta = {"role": ..., "agent": i}`` (roles: agent, box (the
body), trail, path, start, goal, obstacle, obstacle-edges, workspace, closest, closest-pair,
bodies-legend) so that
tests and scripts find the traces of one kind without relying on their order. A frame holds
only what changes (positions, hover data, collision colours) of the traces it names by index
in ``frame.traces``; plotly.js merges it into those traces.

The ``swarmpc view RUN_DIR [--out FILE.html] [--open]`` command maps onto
``write_view(RUN_DIR, out=FILE, open_browser=OPEN)``.

The run folder is read by the package's one reader, :func:`swarmpc.simulation.rundata.load_run`
(here with ``scenario.yaml`` optional), so a damaged folder is one ``ValueError`` line naming the
file. plotly and scipy are imported lazily, when a figure is built.
"""

from __future__ import annotations

import html
import math
import os
import webbrowser
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, SupportsFloat

import numpy as np

from swarmpc.frames import frame_indices
from swarmpc.model.footprint import footprint_vertices
from swarmpc.model.geometry import as_bodies, pair_deltas, polytope_vertices
from swarmpc.palette import agent_colors
from swarmpc.simulation.rundata import RunData
from swarmpc.simulation.rundata import load_run as load_run_data

if TYPE_CHECKING:
    import plotly.graph_objects as go

__all__ = [
    "MAX_FRAMES",
    "TRAIL_POINTS",
    "ClosestApproach",
    "Run",
    "build_figure",
    "closest_approach",
    "figure_dict",
    "frame_indices",
    "load_run",
    "run_figure_dict",
    "polytope_vertices",
    "write_view",
]

MAX_FRAMES = 200
"""Animation frames are subsampled to at most about this many (plus the closest approach)."""

_DIGITS = 4  # coordinates are rounded to 0.1 mm in the page (trails and boxes to 1 mm)
TRAIL_POINTS = 120
"""At most this many points in an agent's trail in one frame (see _trail_indices)."""
_OBSTACLE_FILL = "rgba(90, 98, 112, 0.45)"
_OBSTACLE_LINE = "rgb(60, 66, 78)"
_WORKSPACE_LINE = "rgb(120, 120, 120)"
_CLOSEST_COLOR = "rgb(214, 39, 40)"


# --------------------------------------------------------------------------------------- data
Run = RunData
"""The viewer's name for a loaded run folder (the shared :class:`~swarmpc.simulation.rundata.RunData`)."""


def load_run(run_dir: str | Path) -> RunData:
    """Read a run folder with the shared reader, ``scenario.yaml`` optional.

    A bare folder (``trajectory.npz`` with ``dt``, ``goals`` and ``delta``, nothing else) still
    renders, without obstacles or workspace; any damaged file is a one-line
    :class:`~swarmpc.simulation.rundata.RunDataError` (a ``ValueError``) naming it.
    """
    return load_run_data(run_dir, require_scenario=False)


@dataclass(frozen=True)
class ClosestApproach:
    """The smallest inf-norm distance between two agents over the whole run."""

    distance: float  # min over k, i < j of ||p_i(k) - p_j(k)||_inf  [m]
    step: int  # the time index k where it happens
    time: float  # t[k] [s]
    pair: tuple[int, int]  # (i, j), i < j
    ratio: float  # min over k, i < j of max_a |p_i,a - p_j,a| / (b_i,a + b_j,a) (< 1: collision)


def closest_approach(positions: np.ndarray, t: np.ndarray, delta: np.ndarray) -> ClosestApproach | None:
    """Closest pair of agents over the run (None with fewer than two agents).

    ``delta``: one Δ (d,) for every pair, or the bodies' half-sizes (M, d) (pair Δ_ij = b_i + b_j).
    """
    positions = np.asarray(positions, float)
    steps, m, _ = positions.shape
    if m < 2:
        return None
    iu, ju = np.triu_indices(m, k=1)
    bodies = as_bodies(delta, m)
    pair_delta = bodies[iu] + bodies[ju]  # (pairs, d)
    best = (math.inf, 0, 0)
    best_ratio = math.inf
    chunk = max(1, 2_000_000 // max(1, len(iu) * positions.shape[2]))
    for start in range(0, steps, chunk):
        block = positions[start : start + chunk]
        gaps = np.abs(block[:, iu, :] - block[:, ju, :])  # (K, pairs, d)
        dist = gaps.max(axis=2)
        flat = int(np.nanargmin(dist)) if np.isfinite(dist).any() else -1
        if flat >= 0:
            k, pair = divmod(flat, len(iu))
            if dist[k, pair] < best[0]:
                best = (float(dist[k, pair]), start + k, pair)
        ratio = (gaps / pair_delta).max(axis=2)
        if np.isfinite(ratio).any():
            best_ratio = min(best_ratio, float(np.nanmin(ratio)))
    if not math.isfinite(best[0]):
        return None
    distance, step, pair = best
    return ClosestApproach(
        distance=distance,
        step=step,
        time=float(t[step]),
        pair=(int(iu[pair]), int(ju[pair])),
        ratio=best_ratio,
    )


# ----------------------------------------------------------------------------------- geometry
def _hull_mesh(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]]]:
    """Triangles (i, j, k rows) of the 3D hull of ``points`` and its true edges (not diagonals)."""
    from scipy.spatial import ConvexHull

    hull = ConvexHull(points)
    faces = hull.simplices
    normals = hull.equations[:, :3]
    by_edge: dict[tuple[int, int], list[int]] = {}
    for f, tri in enumerate(faces):
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            key = (int(min(a, b)), int(max(a, b)))
            by_edge.setdefault(key, []).append(f)
    edges = [
        key
        for key, adjacent in by_edge.items()
        if len(adjacent) != 2 or float(normals[adjacent[0]] @ normals[adjacent[1]]) < 1 - 1e-7
    ]
    return hull.points, faces, edges


def _segments(points: np.ndarray, edges: list[tuple[int, int]]) -> list[list[float | None]]:
    """Coordinates per axis of the line segments ``edges``, separated by None gaps."""
    coords: list[list[float | None]] = [[] for _ in range(points.shape[1])]
    for a, b in edges:
        for axis in range(points.shape[1]):
            coords[axis].extend([_round(points[a, axis]), _round(points[b, axis]), None])
    return coords


_CUBE_EDGES = [
    (0, 1), (1, 3), (3, 2), (2, 0),  # bottom
    (4, 5), (5, 7), (7, 6), (6, 4),  # top
    (0, 4), (1, 5), (2, 6), (3, 7),  # verticals
]  # fmt: skip


def _box_lines(lower: np.ndarray, upper: np.ndarray, digits: int = _DIGITS) -> list[list[float | None]]:
    """Outline of the box [lower, upper]: a closed rectangle in 2D, a wireframe cube in 3D."""
    lo, hi = np.asarray(lower, float), np.asarray(upper, float)
    if lo.size == 2:
        xs = [lo[0], hi[0], hi[0], lo[0], lo[0]]
        ys = [lo[1], lo[1], hi[1], hi[1], lo[1]]
        return [[_round(v, digits) for v in xs], [_round(v, digits) for v in ys]]
    corners = np.array([[(hi if (n >> a) & 1 else lo)[a] for a in range(3)] for n in range(8)])
    # path through all 12 edges: bottom loop, top loop, then the 4 verticals (None-separated)
    order = [0, 1, 3, 2, 0, 4, 5, 7, 6, 4, None, 1, 5, None, 3, 7, None, 2, 6]
    return [
        [None if n is None else _round(corners[n, axis], digits) for n in order] for axis in range(3)
    ]


_OUTLINE = [2, 3, 0, 1, 2]
"""The corners of :func:`~swarmpc.model.footprint.footprint_vertices` as a closed outline from the
rear right one, counter-clockwise: at heading 0 the very loop :func:`_box_lines` draws."""


def _footprint_lines(pose: np.ndarray, size: np.ndarray, tick: bool, digits: int = 3) -> list[list[float | None]]:
    """Outline of the footprint of ``size`` (length, width) at ``pose`` (x, y, theta) and, with
    ``tick``, after a gap, its heading tick: the segment from its centre to the middle of its front."""
    corners = footprint_vertices(pose, size)[_OUTLINE]
    coords: list[list[float | None]] = [_rlist(corners[:, 0], digits), _rlist(corners[:, 1], digits)]
    if tick:
        front = pose[:2] + size[0] / 2.0 * np.array([np.cos(pose[2]), np.sin(pose[2])])
        for axis in range(2):
            coords[axis] += [None, _round(pose[axis], digits), _round(front[axis], digits)]
    return coords


# ------------------------------------------------------------------------------------ helpers
def _round(value: SupportsFloat, digits: int = _DIGITS) -> float | None:
    number = float(value)
    if not math.isfinite(number):
        return None
    return round(number, digits)


def _rlist(values: np.ndarray, digits: int = _DIGITS) -> list[float | None]:
    return [_round(v, digits) for v in np.ravel(values)]


def _trail_indices(frames_k: np.ndarray, k_pos: int, cap: int = TRAIL_POINTS) -> np.ndarray:
    """Time indices of the trail at frame ``k_pos``: every frame so far, or at most ``cap``.

    Past ``cap`` points the older half of the trail is thinned evenly and the recent half kept
    at full frame resolution (the faint whole path underneath stays exact), which keeps the
    page's size linear, not quadratic, in the number of frames.
    """
    so_far = frames_k[: k_pos + 1]
    if len(so_far) <= cap:
        return so_far
    recent = cap // 2
    older = so_far[: len(so_far) - recent]
    pick = np.unique(np.round(np.linspace(0, len(older) - 1, cap - recent)).astype(int))
    return np.concatenate([older[pick], so_far[len(so_far) - recent :]])


def _rgba(color: str, alpha: float) -> str:
    color = color.strip()
    if color.startswith("#") and len(color) == 7:
        r, g, b = (int(color[i : i + 2], 16) for i in (1, 3, 5))
        return f"rgba({r}, {g}, {b}, {alpha})"
    if color.startswith("rgb("):
        return color.replace("rgb(", "rgba(").replace(")", f", {alpha})")
    return color


def _template(name: str) -> dict[str, Any]:
    """A named plotly template as a plain dict (an unvalidated figure cannot resolve names)."""
    import plotly.io as pio

    return pio.templates[name].to_plotly_json()


def _neighbour_table(positions: np.ndarray, bodies: np.ndarray) -> tuple[np.ndarray, ...]:
    """For one instant (M, d) and the bodies (M, d): nearest neighbour of every agent in the inf-
    and the 2-norm.

    Returns (inf distance, inf neighbour, 2-norm distance, 2-norm neighbour, smallest separation
    / (b_i + b_j), colliding), each (M,); distances are inf and neighbours -1 for a lone agent.
    ``colliding`` marks the agents whose body overlaps another's by the rule the run's
    ``collisions`` count uses (:func:`swarmpc.model.geometry.count_collisions`, 1e-9 m tolerance).
    """
    m = positions.shape[0]
    diff = positions[:, None, :] - positions[None, :, :]
    d_inf = np.abs(diff).max(axis=2)
    d_two = np.linalg.norm(diff, axis=2)
    reach = pair_deltas(bodies)
    ratio = (np.abs(diff) / reach).max(axis=2)
    for table in (d_inf, d_two, ratio):
        np.fill_diagonal(table, np.inf)
    if m < 2:
        none = np.full(m, np.inf)
        return none, np.full(m, -1), none, np.full(m, -1), none, np.zeros(m, bool)
    colliding = (ratio < 1 - 1e-9 / reach.max(axis=2)).any(axis=1)
    n_inf = np.argmin(d_inf, axis=1)
    n_two = np.argmin(d_two, axis=1)
    rows = np.arange(m)
    return d_inf[rows, n_inf], n_inf, d_two[rows, n_two], n_two, ratio.min(axis=1), colliding


BODIES_LEGEND = "bodies (half-size b)"
"""Legend entry of the agents' boxes: what they are."""


def _bodies_legend(trace: dict[str, Any], is3d: bool) -> dict[str, Any]:
    """A legend-only entry (no data) saying what the boxes around the agents are."""
    trace.update(mode="lines", line=dict(color="rgb(110, 110, 110)", width=2 if is3d else 1),
                 name=BODIES_LEGEND, hoverinfo="skip", meta={"role": "bodies-legend"})
    if not is3d:
        trace.update(fill="toself", fillcolor="rgba(110, 110, 110, 0.12)")
    return trace


def _length_text(values: np.ndarray) -> str:
    """``0.3 m`` when every axis is the same, else ``(0.3, 0.3, 0.2) m``."""
    if np.allclose(values, values[0]):
        return f"{values[0]:.3g} m"
    return "(" + ", ".join(f"{v:.3g}" for v in values) + ") m"


def _title(run: RunData, closest: ClosestApproach | None) -> str:
    s = run.summary
    method = s.get("method") or (run.scenario.solver.method if run.scenario else "?")
    collision = s.get("collision") or (run.scenario.collision if run.scenario else "?")
    collisions = s.get("collisions", "?")
    if isinstance(collisions, (list, tuple)):
        collisions = len(collisions)
    if closest is not None:
        sep = f"min separation {closest.distance:.3f} m (inf-norm), min separation / δ_ij = {closest.ratio:.2f}"
    elif isinstance(s.get("min_separation_inf"), (int, float)):
        sep = f"min separation {float(s['min_separation_inf']):.3f} m (inf-norm)"
    else:
        sep = "single agent"
    delta_text = _length_text(run.delta)
    bodies = run.body_half_sizes
    if np.allclose(bodies, bodies[0]):
        body_text = f"bodies: half-size b = {_length_text(bodies[0])}, δ_ij = b_i + b_j"
    else:
        body_text = f"bodies: half-size b = {bodies.min():.3g}–{bodies.max():.3g} m, δ_ij = b_i + b_j"
    extra = []
    if "all_reached" in s:
        extra.append("all goals reached" if s["all_reached"] else "goals NOT all reached")
    if isinstance(s.get("cost"), (int, float)) and math.isfinite(s["cost"]):
        extra.append(f"cost {s['cost']:.4g}")
    name, method, collision = (html.escape(str(v)) for v in (run.name, method, collision))
    head = f"<b>{name}</b> · {method} · {collision} collision avoidance"
    line2 = (
        f"collisions: {html.escape(str(collisions))} · {sep} · {body_text} (δ = {delta_text}) · "
        f"{run.num_agents} agents, {len(run.t) - 1} steps"
    )
    if extra:
        line2 += " · " + " · ".join(extra)
    return f"{head}<br><span style='font-size:12px'>{line2}</span>"


# -------------------------------------------------------------------------------------- figure
def build_figure(run_dir: str | Path, max_frames: int = MAX_FRAMES) -> go.Figure:
    """The animated plotly figure of a run folder (2D or 3D after the trajectory's dimension).

    The figure is validated by plotly, which is slow for a large run (it walks every frame);
    :func:`write_view` skips that step (the same dictionary, written without validation).
    """
    import plotly.graph_objects as go

    return go.Figure(figure_dict(run_dir, max_frames))


def figure_dict(run_dir: str | Path, max_frames: int = MAX_FRAMES) -> dict[str, Any]:
    """The figure of :func:`build_figure` as a plain plotly dictionary (data, layout, frames)."""
    return run_figure_dict(load_run(run_dir), max_frames)


def run_figure_dict(run: RunData, max_frames: int = MAX_FRAMES) -> dict[str, Any]:
    """:func:`figure_dict` of a run already loaded (see :func:`load_run`).

    The traces come in a fixed order: workspace, obstacles, each agent's path, start and goal,
    the closest approach, the bodies' legend entry, then the 3M dynamic traces (trail, body,
    marker per agent) that the frames update by index.
    """
    bodies = run.body_half_sizes
    closest = closest_approach(run.positions, run.t, bodies)
    frames_k = frame_indices(run.positions.shape[0], max_frames, keep=closest.step if closest else None)
    turning = np.any(run.poses[:, :, 2] != 0.0, axis=0) if run.dim == 2 else np.zeros(run.num_agents, bool)
    canvas = _Canvas(run, run.positions, run.velocities, bodies, agent_colors(run.num_agents), frames_k, turning)
    obstacles = run.scenario.obstacle_halfspaces() if run.scenario is not None else []
    lo, hi = _view_box(run, bodies.max(axis=0), obstacles, turning)

    traces: list[Any] = []
    workspace = _workspace_trace(canvas)
    if workspace is not None:
        traces.append(workspace)
    traces.extend(_obstacle_traces(canvas, obstacles, lo, hi))
    traces.extend(_agent_static_traces(canvas))
    closest_traces, annotations = _closest_traces(canvas, closest)
    traces.extend(closest_traces)
    traces.append(_bodies_legend(canvas.scatter(**canvas.axes([[None]] * run.dim)), canvas.is3d))
    first_dynamic = len(traces)
    hover = _hover_template(canvas.is3d, run.num_agents)
    traces.extend(_dynamic_traces(canvas, 0, hover, full=True))
    dynamic_ids = list(range(first_dynamic, len(traces)))
    frames = [
        {"name": f"{int(k)}", "data": _dynamic_traces(canvas, pos, hover, full=False), "traces": dynamic_ids}
        for pos, k in enumerate(frames_k)
    ]
    layout = _layout(canvas, closest, annotations, lo, hi)
    return {"data": traces, "layout": layout, "frames": frames}


@dataclass(frozen=True)
class _Canvas:
    """What the trace builders of one figure share: the run, its arrays, colours and frames."""

    run: RunData
    positions: np.ndarray  # (T+1, M, d)
    velocities: np.ndarray  # (T+1, M, d)
    bodies: np.ndarray  # (M, d) half-sizes
    colors: list[str]  # one per agent
    frames_k: np.ndarray  # the time index of each animation frame
    turning: np.ndarray  # (M,) True for a 2D agent whose heading ever leaves 0 (it gets a heading tick)

    @property
    def is3d(self) -> bool:
        """True for a 3D run (scatter3d, mesh3d and a scene instead of x/y axes)."""
        return self.run.dim == 3

    def axes(self, coords: list[list[float | None]]) -> dict[str, Any]:
        """``coords`` (one list per axis) as a trace's ``x``, ``y`` (and ``z``) keys."""
        keys = ("x", "y", "z")[: self.run.dim]
        return dict(zip(keys, coords, strict=True))

    def scatter(self, **kwargs: Any) -> dict[str, Any]:
        """A scatter trace (``scatter3d`` in 3D) with the given keys."""
        return {"type": "scatter3d" if self.is3d else "scatter", **kwargs}


def _view_box(
    run: RunData, reach: np.ndarray, obstacles: list[tuple[np.ndarray, np.ndarray]], turning: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Fixed axis ranges: the workspace (or padded starts and goals), everything that moved (the
    ``turning`` agents' footprints whole) and every bounded obstacle, padded by 3 % of the largest side.

    Fixed ranges keep the view still while the animation plays; unbounded obstacles are clipped
    to the view instead of extending it.
    """
    d, P = run.dim, run.positions
    if run.scenario is not None:
        lo, hi = (np.asarray(b, float) for b in run.scenario.bounds())
    else:
        lo, hi = np.full(d, np.inf), np.full(d, -np.inf)
    finite = P[np.isfinite(P).all(axis=2)]
    if finite.size:
        lo = np.minimum(lo, finite.min(axis=0) - reach)
        hi = np.maximum(hi, finite.max(axis=0) + reach)
    lo = np.minimum(lo, run.goal_positions.min(axis=0) - reach)
    hi = np.maximum(hi, run.goal_positions.max(axis=0) + reach)
    if turning.any():  # a turned footprint reaches past its body's box
        corners = footprint_vertices(run.poses[:, turning], run.footprints[turning]).reshape(-1, 2)
        lo, hi = np.minimum(lo, corners.min(axis=0)), np.maximum(hi, corners.max(axis=0))
    span = np.maximum(hi - lo, 1e-6)
    far_lo, far_hi = lo - 10 * span - 10, hi + 10 * span + 10
    for G, g in obstacles:  # bounded obstacles extend the view; unbounded ones are clipped
        verts = polytope_vertices(G, g, (far_lo, far_hi))
        if len(verts) and np.all(verts > far_lo + 1e-6) and np.all(verts < far_hi - 1e-6):
            lo, hi = np.minimum(lo, verts.min(axis=0)), np.maximum(hi, verts.max(axis=0))
    pad = 0.03 * np.maximum(hi - lo, 1e-6).max()
    return lo - pad, hi + pad


def _workspace_trace(canvas: _Canvas) -> dict[str, Any] | None:
    """The workspace outline (None without a scenario or a workspace)."""
    scenario = canvas.run.scenario
    if scenario is None or scenario.workspace is None:
        return None
    ws_lo = np.asarray(scenario.workspace.lower, float)
    ws_hi = np.asarray(scenario.workspace.upper, float)
    is3d = canvas.is3d
    return canvas.scatter(
        **canvas.axes(_box_lines(ws_lo, ws_hi)),
        mode="lines",
        # dashed in 2D; solid in 3D, where dashes read as the scene's grid lines
        line=dict(color=_WORKSPACE_LINE, width=2 if is3d else 1.5, dash="solid" if is3d else "dash"),
        name="workspace",
        hoverinfo="skip",
        meta={"role": "workspace"},
    )


def _obstacle_traces(
    canvas: _Canvas, obstacles: list[tuple[np.ndarray, np.ndarray]], lo: np.ndarray, hi: np.ndarray
) -> list[dict[str, Any]]:
    """The static obstacles clipped to the view [lo, hi]: one filled polygon each in 2D, a
    translucent hull mesh plus its edges in 3D (one legend entry for all of them)."""
    traces: list[dict[str, Any]] = []
    for n, (G, g) in enumerate(obstacles):
        verts = polytope_vertices(G, g, (lo, hi))
        if len(verts) == 0:
            continue
        common = dict(
            name="obstacles",
            legendgroup="obstacles",
            showlegend=n == 0,
            meta={"role": "obstacle", "index": n},
        )
        if canvas.is3d:
            traces.extend(_obstacle_mesh(canvas, n, verts, common))
        else:
            traces.append(_obstacle_polygon(n, verts, common))
    return traces


def _obstacle_polygon(n: int, verts: np.ndarray, common: dict[str, Any]) -> dict[str, Any]:
    """Obstacle ``n`` in 2D: its polygon ``verts`` (counter-clockwise), filled, hover on the fill."""
    closed = np.vstack([verts, verts[:1]])
    return dict(
        type="scatter",
        x=_rlist(closed[:, 0]),
        y=_rlist(closed[:, 1]),
        mode="lines",
        fill="toself",
        fillcolor=_OBSTACLE_FILL,
        line=dict(color=_OBSTACLE_LINE, width=1.5),
        hoveron="fills",
        text=f"obstacle {n}",
        hoverinfo="text",
        **common,
    )


def _obstacle_mesh(canvas: _Canvas, n: int, verts: np.ndarray, common: dict[str, Any]) -> list[dict[str, Any]]:
    """Obstacle ``n`` in 3D: a translucent mesh of the hull of ``verts`` and, as lines, the hull's
    true edges (not the diagonals of its triangulation)."""
    label = f"obstacle {n}"
    points, faces, edges = _hull_mesh(verts)
    mesh = dict(
        type="mesh3d",
        x=_rlist(points[:, 0]),
        y=_rlist(points[:, 1]),
        z=_rlist(points[:, 2]),
        i=faces[:, 0].tolist(),
        j=faces[:, 1].tolist(),
        k=faces[:, 2].tolist(),
        color="rgb(110, 118, 132)",
        opacity=0.35,
        flatshading=True,
        hovertext=label,
        hoverinfo="text",
        **common,
    )
    outline = dict(
        type="scatter3d",
        **canvas.axes(_segments(points, edges)),
        mode="lines",
        line=dict(color=_OBSTACLE_LINE, width=3),
        name=f"{label} edges",
        legendgroup="obstacles",
        showlegend=False,
        hoverinfo="skip",
        meta={"role": "obstacle-edges", "index": n},
    )
    return [mesh, outline]


def _agent_static_traces(canvas: _Canvas) -> list[dict[str, Any]]:
    """Per agent: its whole path (faint, dotted), its start and its goal marker."""
    run, P, colors, is3d = canvas.run, canvas.positions, canvas.colors, canvas.is3d
    d = run.dim
    goal_symbol = "diamond" if is3d else "star"
    start_symbol = "circle-open" if is3d else "circle"
    traces: list[dict[str, Any]] = []
    for i in range(run.num_agents):
        group = dict(legendgroup=f"agent {i}", showlegend=False)
        traces.append(
            canvas.scatter(
                **canvas.axes([_rlist(P[:, i, a]) for a in range(d)]),
                mode="lines",
                line=dict(color=_rgba(colors[i], 0.35), width=2 if is3d else 1.5, dash="dot"),
                name=f"agent {i} path",
                hoverinfo="skip",
                meta={"role": "path", "agent": i},
                **group,
            )
        )
        start = P[0, i]
        traces.append(
            canvas.scatter(
                **canvas.axes([[_round(start[a])] for a in range(d)]),
                mode="markers",
                marker=dict(
                    symbol=start_symbol,
                    size=6 if is3d else 9,
                    color="white" if not is3d else colors[i],
                    line=dict(color=colors[i], width=2),
                ),
                name=f"agent {i} start",
                hoverinfo="skip",  # the agent marker sits on it at t = 0: its hover card wins
                meta={"role": "start", "agent": i},
                **group,
            )
        )
        goal = run.goal_positions[i]
        traces.append(
            canvas.scatter(
                **canvas.axes([[_round(goal[a])] for a in range(d)]),
                mode="markers",
                marker=dict(
                    symbol=goal_symbol, size=6 if is3d else 14, color=colors[i], line=dict(color="black", width=1)
                ),
                name=f"agent {i} goal",
                hoverinfo="skip",  # the agent marker sits on it at the end: its hover card wins
                meta={"role": "goal", "agent": i},
                **group,
            )
        )
    return traces


def _closest_traces(
    canvas: _Canvas, closest: ClosestApproach | None
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """The closest approach of the run: a dashed line between the pair and a marker at its
    midpoint (with a hover card), and the annotation that labels it; nothing for a lone agent."""
    if closest is None:
        return [], []
    P, bodies, d, is3d = canvas.positions, canvas.bodies, canvas.run.dim, canvas.is3d
    i, j = closest.pair
    pi, pj = P[closest.step, i], P[closest.step, j]
    mid = 0.5 * (pi + pj)
    pair_ratio = float(np.max(np.abs(pi - pj) / (bodies[i] + bodies[j])))  # < 1: a collision
    text = f"closest approach: {closest.distance:.4g} m (inf-norm), t = {closest.time:.2f} s"
    pair_line = canvas.scatter(
        **canvas.axes([[_round(pi[a]), _round(pj[a])] for a in range(d)]),
        mode="lines",
        line=dict(color=_CLOSEST_COLOR, width=2 if is3d else 1.5, dash="dash"),
        name="closest pair",
        legendgroup="closest",
        showlegend=False,
        hoverinfo="skip",
        meta={"role": "closest-pair", "pair": [i, j]},
    )
    marker = canvas.scatter(
        **canvas.axes([[_round(mid[a])] for a in range(d)]),
        mode="markers",
        marker=dict(symbol="x", size=6 if is3d else 11, color=_CLOSEST_COLOR),
        name="closest approach",
        legendgroup="closest",
        hovertemplate=(
            f"{text}<br>agents {i} and {j}, separation / δ_ij = {pair_ratio:.3f}"
            f"<br>Euclidean {float(np.linalg.norm(pi - pj)):.4g} m<extra></extra>"
        ),
        meta={
            "role": "closest",
            "distance": closest.distance,
            "time": closest.time,
            "step": closest.step,
            "pair": [i, j],
            "ratio": closest.ratio,
        },
    )
    note = dict(
        text=text,
        showarrow=True,
        arrowhead=2,
        arrowcolor=_CLOSEST_COLOR,
        ax=40,
        ay=-40,
        font=dict(color=_CLOSEST_COLOR, size=12),
        bgcolor="rgba(255, 255, 255, 0.85)",
        bordercolor=_CLOSEST_COLOR,
        borderwidth=1,
    )
    if is3d:
        annotation = dict(x=float(mid[0]), y=float(mid[1]), z=float(mid[2]), **note)
    else:
        annotation = dict(x=float(mid[0]), y=float(mid[1]), xref="x", yref="y", **note)
    return [pair_line, marker], [annotation]


def _hover_template(is3d: bool, m: int) -> str:
    """The agents' hover card; its ``customdata`` is the list built in :func:`_agent_marker`."""
    hover = (
        "<b>agent %{customdata[0]}</b> · t = %{customdata[8]:.2f} s<br>"
        + ("position (%{x:.2f}, %{y:.2f}, %{z:.2f})<br>" if is3d else "position (%{x:.2f}, %{y:.2f})<br>")
        + "speed |v| = %{customdata[1]:.3f} m/s<br>"
        "to goal: %{customdata[2]:.3f} m<br>"
    )
    if m > 1:
        hover += (
            "nearest, inf-norm: %{customdata[3]:.3f} m (agent %{customdata[4]})<br>"
            "nearest, Euclidean: %{customdata[5]:.3f} m (agent %{customdata[6]})<br>"
            "separation / δ_ij: %{customdata[7]:.2f}"
        )
    return hover + "<extra></extra>"


def _dynamic_traces(canvas: _Canvas, k_pos: int, hover: str, *, full: bool) -> list[dict[str, Any]]:
    """The 3M dynamic traces (trail, body, marker per agent) at frame position ``k_pos``.

    ``full`` gives complete traces (the figure's initial data); otherwise only what changes
    from frame to frame (plotly.js merges a frame's data into the traces it names), which
    keeps the page small.
    """
    k = int(canvas.frames_k[k_pos])
    trail_k = _trail_indices(canvas.frames_k, k_pos)
    neighbours = _neighbour_table(canvas.positions[k], canvas.bodies)
    overlapping = neighbours[5]
    out: list[dict[str, Any]] = []
    for i in range(canvas.run.num_agents):
        colliding = bool(overlapping[i])
        out.append(_agent_trail(canvas, i, trail_k, full))
        out.append(_agent_box(canvas, i, k, colliding, full))
        out.append(_agent_marker(canvas, i, k, neighbours, hover, full))
    return out


def _agent_trail(canvas: _Canvas, i: int, trail_k: np.ndarray, full: bool) -> dict[str, Any]:
    """Agent ``i``'s trail through the time indices ``trail_k`` (its path so far)."""
    P, is3d = canvas.positions, canvas.is3d
    trail = canvas.scatter(**canvas.axes([_rlist(P[trail_k, i, a], 3) for a in range(canvas.run.dim)]))
    if full:
        trail.update(
            mode="lines",
            line=dict(color=canvas.colors[i], width=4 if is3d else 2.5),
            name=f"agent {i} trail",
            legendgroup=f"agent {i}",
            showlegend=False,
            hoverinfo="skip",
            meta={"role": "trail", "agent": i},
        )
    return trail


def _agent_box(canvas: _Canvas, i: int, k: int, colliding: bool, full: bool) -> dict[str, Any]:
    """Agent ``i``'s body at time index ``k``, red and bolder while it overlaps another's: its
    footprint in 2D (with its heading tick when it turns), its box in 3D."""
    p, half, is3d = canvas.positions[k, i], canvas.bodies[i], canvas.is3d
    edge = _CLOSEST_COLOR if colliding else canvas.colors[i]
    if is3d:
        outline = _box_lines(p - half, p + half, 3)
    else:
        outline = _footprint_lines(canvas.run.poses[k, i], canvas.run.footprints[i], bool(canvas.turning[i]))
    box = canvas.scatter(**canvas.axes(outline))
    box["line"] = dict(color=edge, width=(3 if colliding else 2) if is3d else (2 if colliding else 1))
    if not is3d:
        box["fillcolor"] = _rgba(edge, 0.22 if colliding else 0.12)
    if full:
        box.update(
            mode="lines",
            name=f"agent {i} body",
            legendgroup=f"agent {i}",
            showlegend=False,
            hoverinfo="skip",
            meta={"role": "box", "agent": i},
        )
        if not is3d:
            box["fill"] = "toself"
    return box


def _agent_marker(
    canvas: _Canvas, i: int, k: int, neighbours: tuple[np.ndarray, ...], hover: str, full: bool
) -> dict[str, Any]:
    """Agent ``i``'s position marker at time index ``k`` with the data of its hover card.

    ``neighbours`` is :func:`_neighbour_table` at ``k``; the marker's rim turns red while the
    agent's body overlaps another's.
    """
    n_inf, id_inf, n_two, id_two, ratio, overlapping = neighbours
    run, p, color, is3d = canvas.run, canvas.positions[k, i], canvas.colors[i], canvas.is3d
    colliding = bool(overlapping[i])
    custom = [
        i,
        _round(np.linalg.norm(canvas.velocities[k, i])),
        _round(np.linalg.norm(p - run.goal_positions[i])),
        _round(n_inf[i]),
        int(id_inf[i]),
        _round(n_two[i]),
        int(id_two[i]),
        _round(ratio[i]),
        _round(run.t[k]),
    ]
    marker = canvas.scatter(
        **canvas.axes([[_round(p[a])] for a in range(run.dim)]),
        customdata=[custom],
        marker=dict(line=dict(color=_CLOSEST_COLOR if colliding else "white")),
    )
    if full:
        marker.update(
            mode="markers+text",
            marker=dict(
                size=7 if is3d else 11,
                color=color,
                line=dict(color=marker["marker"]["line"]["color"], width=1 if is3d else 2),
            ),
            text=[str(i)],
            textposition="top center",
            textfont=dict(size=11, color=color),
            hovertemplate=hover,
            name=f"agent {i}",
            legendgroup=f"agent {i}",
            showlegend=True,
            meta={"role": "agent", "agent": i},
        )
    return marker


def _layout(
    canvas: _Canvas,
    closest: ClosestApproach | None,
    annotations: list[dict[str, Any]],
    lo: np.ndarray,
    hi: np.ndarray,
) -> dict[str, Any]:
    """The figure's layout: title, play buttons, time slider, the axes fixed to [lo, hi] (a
    scene in 3D) and the closest approach's annotation; ``meta`` says what the page shows."""
    run, frames_k = canvas.run, canvas.frames_k
    redraw = canvas.is3d  # 3D (WebGL) traces need a redraw per frame; 2D animates without one
    jump = {"frame": {"duration": 0, "redraw": redraw}, "mode": "immediate", "transition": {"duration": 0}}
    layout: dict[str, Any] = dict(
        title=dict(text=_title(run, closest), x=0.5, xanchor="center", font=dict(size=16)),
        updatemenus=[_play_buttons(run, frames_k, redraw, jump)],
        sliders=[_time_slider(run.t, frames_k, jump)],
        hovermode="closest",
        template=_template("plotly_white"),
        legend=dict(itemsizing="constant", tracegroupgap=2),
        margin=dict(l=60, r=30, t=80, b=130),
        uirevision="swarmpc-view",
        meta={
            "swarmpc": "view",
            "dim": run.dim,
            "num_agents": run.num_agents,
            "frames": len(frames_k),
            "frame_steps": [int(k) for k in frames_k],
        },
    )
    if canvas.is3d:
        layout["scene"] = _scene(lo, hi, annotations)
    else:
        layout.update(_plane_axes(lo, hi))
        layout["annotations"] = annotations
    return layout


def _play_buttons(run: RunData, frames_k: np.ndarray, redraw: bool, jump: dict[str, Any]) -> dict[str, Any]:
    """The play and pause buttons.

    Play shows each frame for about the time it spans in the run (at least 40 ms, at most 150 ms,
    so a long run still plays in reasonable time); pause jumps to the current frame.
    """
    steps = run.positions.shape[0]
    frame_ms = int(np.clip(1000.0 * run.dt * max(1.0, (steps - 1) / max(1, len(frames_k) - 1)), 40, 150))
    play_args = {
        "frame": {"duration": frame_ms, "redraw": redraw},
        "fromcurrent": True,
        "transition": {"duration": 0},
        "mode": "immediate",
    }
    return dict(
        type="buttons",
        direction="left",
        showactive=False,
        x=0.0,
        y=0.0,
        xanchor="left",
        yanchor="top",
        pad=dict(t=45, r=10),
        buttons=[
            dict(label="▶ Play", method="animate", args=[None, play_args]),
            dict(label="❚❚ Pause", method="animate", args=[[None], jump]),
        ],
    )


def _time_slider(t: np.ndarray, frames_k: np.ndarray, jump: dict[str, Any]) -> dict[str, Any]:
    """The time slider: one step per frame, labelled with its time in seconds."""
    many = len(frames_k) > 25
    return dict(
        active=0,
        x=0.16,
        y=0.0,
        len=0.84,
        xanchor="left",
        yanchor="top",
        pad=dict(t=30, b=10),
        currentvalue=dict(
            prefix="t = ", suffix=" s", visible=True, xanchor="left", font=dict(size=14, color="#2a3f5f")
        ),
        # with many steps the per-step tick labels overlap: hide them, keep the current value
        font=dict(color="rgba(0,0,0,0)" if many else "#444", size=10),
        ticklen=2 if many else 5,
        transition=dict(duration=0),
        steps=[dict(method="animate", label=f"{t[k]:.2f}", args=[[f"{int(k)}"], jump]) for k in frames_k],
    )


def _scene(lo: np.ndarray, hi: np.ndarray, annotations: list[dict[str, Any]]) -> dict[str, Any]:
    """The 3D scene: axes fixed to [lo, hi] at their true proportions, a fixed camera, and the
    annotations (which in 3D belong to the scene)."""
    size = hi - lo
    ratio = size / size.max()
    return dict(
        xaxis=dict(range=[float(lo[0]), float(hi[0])], autorange=False, title=dict(text="x [m]")),
        yaxis=dict(range=[float(lo[1]), float(hi[1])], autorange=False, title=dict(text="y [m]")),
        zaxis=dict(range=[float(lo[2]), float(hi[2])], autorange=False, title=dict(text="z [m]")),
        aspectmode="manual",
        aspectratio=dict(x=float(ratio[0]), y=float(ratio[1]), z=float(ratio[2])),
        camera=dict(eye=dict(x=1.25, y=-1.4, z=0.8)),
        annotations=annotations,
        uirevision="swarmpc-view",
    )


def _plane_axes(lo: np.ndarray, hi: np.ndarray) -> dict[str, Any]:
    """The 2D axes, fixed to [lo, hi] with equal scales (a metre is as long on both axes)."""
    return dict(
        xaxis=dict(
            range=[float(lo[0]), float(hi[0])],
            autorange=False,
            title=dict(text="x [m]"),
            constrain="domain",
            zeroline=False,
        ),
        yaxis=dict(
            range=[float(lo[1]), float(hi[1])],
            autorange=False,
            title=dict(text="y [m]"),
            scaleanchor="x",
            scaleratio=1,
            constrain="domain",
            zeroline=False,
        ),
    )


# Pausing (or scrubbing the slider during play) interrupts the running Plotly.animate call; plotly.js
# then rejects that call's promise with no reason, which its own buttons never catch, so the console
# shows "Uncaught (in promise)". Mark exactly those reason-less rejections handled; every real
# error (which has a reason) is still reported.
_QUIET_INTERRUPTED_ANIMATION = (
    "window.addEventListener('unhandledrejection', function (ev) {"
    " if (ev.reason === undefined) { ev.preventDefault(); } });"
)


def write_view(run_dir: str | Path, out: str | Path | None = None, *, open_browser: bool = False) -> Path:
    """Write the run's viewer as one self-contained HTML file; return its path.

    ``out`` defaults to ``RUN_DIR/view.html``. plotly.js is embedded (no CDN, works offline).
    With ``open_browser`` the page is also opened in the default web browser.
    """
    folder = Path(run_dir)
    target = Path(out) if out is not None else folder / "view.html"
    run = load_run(folder)
    import plotly.io as pio

    page = pio.to_html(
        run_figure_dict(run),
        validate=False,  # build_figure validates the same dictionary (in the tests)
        include_plotlyjs=True,
        include_mathjax=False,
        full_html=True,
        auto_play=False,
        div_id="swarmpc-view",
        default_width="100%",
        default_height="100vh",
        config={"displaylogo": False, "responsive": True, "scrollZoom": True},
        post_script=_QUIET_INTERRUPTED_ANIMATION,
    )
    title = f"swarmpc view · {html.escape(run.name)}"
    # one full-window figure: no body margin (plotly's page sets html, body {height: 100%})
    style = "<style>html, body {margin: 0; padding: 0;}</style>"
    page = page.replace("<head>", f"<head><title>{title}</title>{style}", 1)
    target.parent.mkdir(parents=True, exist_ok=True)
    # write beside the target, then rename: a reader never sees half a page (plain open() so the
    # file gets the usual umask permissions, unlike tempfile's 0600)
    tmp = target.with_name(f".{target.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(page, encoding="utf-8")
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if open_browser:
        webbrowser.open(target.resolve().as_uri())
    return target

