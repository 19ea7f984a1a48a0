"""Figures and animations of a finished run folder.

Reads what a run writes (``trajectory.npz``, ``summary.json``, ``scenario.yaml`` and, for ADMM
runs, ``admm.npz``) through the package's one reader, :func:`swarmpc.simulation.rundata.load_run`
(re-exported here with :class:`RunData` and :class:`RunDataError`), and draws the paper's
figures: the trajectories with the agents' bodies and the obstacles (Fig. 3), the ADMM residuals
per iteration (Fig. 4) and an animation.

Each agent is drawn as its body. In a 2D run that is its footprint, the rectangle
``RunData.footprints`` at ``RunData.poses`` (centre and heading): a point agent's is the box of
half-size b_i around its position (``RunData.bodies``) at heading 0, a car's turns with it and also
carries a heading tick, a segment from its centre to the middle of its front side, so that its
front is visible. A 3D run draws the boxes of half-size b_i, projected. Two drawn point-agent
bodies overlap exactly when the run counts the pair as a collision (|p_i - p_j| < b_i + b_j on
every axis), so a picture never shows an overlap the summary does not count, nor hides one.

Only the object-oriented matplotlib API is used (:class:`~matplotlib.figure.Figure` with an Agg
canvas), never :mod:`matplotlib.pyplot`: no window opens, no backend is switched and no figure
lingers in a global registry after it is saved.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import matplotlib
import numpy as np
from matplotlib import animation, colormaps
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch, Polygon, Rectangle
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection
from scipy.spatial import ConvexHull, QhullError

from swarmpc import palette
from swarmpc.config import Scenario
from swarmpc.frames import even_indices, frame_indices
from swarmpc.model.footprint import footprint_vertices
from swarmpc.model.geometry import body_separation_ratio, count_body_collisions, polytope_vertices
from swarmpc.simulation.rundata import AdmmResiduals as AdmmResiduals
from swarmpc.simulation.rundata import MissingRunFileError as MissingRunFileError
from swarmpc.simulation.rundata import RunData as RunData
from swarmpc.simulation.rundata import RunDataError as RunDataError
from swarmpc.simulation.rundata import load_run as load_run

if TYPE_CHECKING:
    from matplotlib.typing import RcKeyType

PathLike = str | os.PathLike[str]

DPI = 120
"""Resolution of the saved PNG figures."""
ANIMATION_DPI = 80
TRAIL_SECONDS = 1.5
MAX_FPS = 20.0
OBSTACLE_COLOR = "0.55"
AXIS_NAMES = ("x", "y", "z")
GID_OBSTACLE = "obstacle"
GID_TOLERANCE = "tolerance"
GID_BODY = "body"
"""Body patches carry the gid ``body:<agent>:<step>`` (snapshots) or ``body:<agent>`` (animation)."""
GID_HEADING = "heading"
"""Heading ticks (lines, one per turning agent) carry the gid ``heading:<agent>``."""
BODY_LABEL = "bodies (half-size b)"


class AnimationWriterError(RuntimeError):
    """The requested animation format needs a tool that is not installed."""


# --------------------------------------------------------------------------------- geometry
def agent_colors(m: int) -> list[tuple[float, float, float, float]]:
    """One RGBA colour per agent, from :func:`swarmpc.palette.agent_colors` (the viewer's too)."""
    return [to_rgba(color) for color in palette.agent_colors(m)]


def polygon_vertices_2d(
    G: np.ndarray, g: np.ndarray, bounds: tuple[np.ndarray, np.ndarray] | None = None
) -> np.ndarray:
    """Vertices of the 2D polygon {p : G p <= g} in counter-clockwise order.

    Parameters
    ----------
    G : np.ndarray
        (k, 2) face normals.
    g : np.ndarray
        (k,) offsets.
    bounds : (lower, upper), optional
        Clip to this rectangle; needed when the set is unbounded.

    Returns
    -------
    np.ndarray
        (n, 2) vertices, counter-clockwise; (0, 2) when the set is empty or flat.
    """
    G = np.atleast_2d(np.asarray(G, float))
    if G.shape[1] != 2:
        raise ValueError(f"G must have 2 columns, got {G.shape[1]}")
    return polytope_vertices(G, g, bounds)  # scipy's 2D hull lists vertices counter-clockwise


def _project_outline(vertices: np.ndarray, axes: tuple[int, int]) -> np.ndarray:
    """Counter-clockwise outline of the projection of a convex point set onto two axes."""
    points = vertices[:, list(axes)]
    if len(points) < 3:
        return np.empty((0, 2))
    try:
        hull = ConvexHull(points)
    except QhullError:
        return np.empty((0, 2))
    return points[hull.vertices]


def _hull_faces(vertices: np.ndarray) -> list[np.ndarray]:
    """The planar faces of a 3D convex hull, each an ordered (k, 3) vertex loop."""
    try:
        hull = ConvexHull(vertices)
    except QhullError:
        return []
    groups: dict[tuple[float, ...], set[int]] = {}
    for simplex, equation in zip(hull.simplices, hull.equations, strict=True):
        key = tuple(np.round(equation, 6) + 0.0)
        groups.setdefault(key, set()).update(int(i) for i in simplex)
    faces = []
    for key, indices in groups.items():
        normal = np.asarray(key[:3])
        loop = hull.points[sorted(indices)]
        centre = loop.mean(axis=0)
        u = loop[0] - centre
        u /= np.linalg.norm(u)
        v = np.cross(normal, u)
        rel = loop - centre
        faces.append(loop[np.argsort(np.arctan2(rel @ v, rel @ u))])
    return faces


# --------------------------------------------------------------------------------- helpers
def _view_limits(run: RunData) -> tuple[np.ndarray, np.ndarray]:
    """Axis limits covering the workspace (or scenario bounds), the paths and the goals."""
    lower, upper = _scenario(run).bounds()
    pos = run.positions.reshape(-1, run.dim)
    goals = run.goals[:, : run.dim]
    reach = run.body_half_sizes.max(axis=0)
    lower = np.minimum(lower, np.minimum(pos.min(axis=0), goals.min(axis=0)) - reach)
    upper = np.maximum(upper, np.maximum(pos.max(axis=0), goals.max(axis=0)) + reach)
    turning = _turning(run.poses[:, :, 2]) if run.dim == 2 else np.zeros(run.num_agents, bool)
    if turning.any():  # a turned footprint reaches past its body's box
        corners = footprint_vertices(run.poses[:, turning], run.footprints[turning]).reshape(-1, 2)
        lower, upper = np.minimum(lower, corners.min(axis=0)), np.maximum(upper, corners.max(axis=0))
    pad = 0.04 * (upper - lower).max()
    return lower - pad, upper + pad


def _obstacle_vertices(run: RunData) -> list[np.ndarray]:
    """Vertices of each obstacle, clipped well outside the view so cut edges stay hidden."""
    lower, upper = _view_limits(run)
    margin = 0.5 * (upper - lower).max()
    out = []
    for G, g in _scenario(run).obstacle_halfspaces():
        vertices = polytope_vertices(G, g, (lower - margin, upper + margin))
        if len(vertices):
            out.append(vertices)
    return out


def _headline(run: RunData) -> str:
    """Title: scenario, method and the safety numbers of the run."""
    s = run.summary
    method = s.get("method", _scenario(run).solver.method)
    collision = s.get("collision", _scenario(run).collision)
    first = (f"{_plain(run.name)}  ({_plain(method)}, {_plain(collision)} constraints, "
             f"{run.num_agents} agents, {run.dim}D)")
    bodies = run.body_half_sizes
    ratio = body_separation_ratio(run.positions, bodies).min() if run.num_agents > 1 else np.inf
    collisions = s.get("collisions")
    if collisions is None:
        collisions = count_body_collisions(run.positions, bodies)
    sep = f"{ratio:.2f}" if np.isfinite(ratio) else "n/a"
    parts = [f"collisions: {_plain(collisions)}", rf"min $|p_i - p_j| / (b_i + b_j)$ = {sep}"]
    reached = s.get("reached")
    if isinstance(reached, list):
        parts.append(f"reached: {sum(bool(r) for r in reached)}/{run.num_agents}")
    elif isinstance(reached, (int, float)) and not isinstance(reached, bool) and math.isfinite(reached):
        parts.append(f"reached: {int(reached)}/{run.num_agents}")
    elif "all_reached" in s:
        parts.append("all reached" if s["all_reached"] else "not all reached")
    parts.append(f"T = {run.t[-1] - run.t[0]:.1f} s")
    return first + "\n" + "   ·   ".join(parts)


def _scenario(run: RunData) -> Scenario:
    """The run's scenario, which every figure needs (obstacles, workspace, method)."""
    if run.scenario is None:
        raise RunDataError(f"{run.run_dir}: no scenario.yaml; figures need the run's scenario")
    return run.scenario


def _plain(value: Any) -> str:
    """``value`` as text that matplotlib shows as it is (a ``$`` would start mathtext)."""
    return str(value).replace("$", r"\$")


def _new_figure(
    width: float, height: float, layout: Literal["constrained", "compressed", "tight"] | None = "constrained"
) -> Figure:
    fig = Figure(figsize=(width, height), layout=layout)
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path: PathLike, dpi: int = DPI) -> Path:
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi, format="png")
    fig.clear()
    return out


def _draw_static_planar(ax: Axes, run: RunData, axes: tuple[int, int], obstacles: list[np.ndarray]) -> None:
    """Obstacles, workspace rectangle, limits, aspect and labels of a 2D (projected) view."""
    for vertices in obstacles:
        outline = _project_outline(vertices, axes)
        if len(outline):
            ax.add_patch(
                Polygon(outline, closed=True, facecolor=OBSTACLE_COLOR, edgecolor="0.3",
                        linewidth=0.8, alpha=0.85, zorder=1, gid=GID_OBSTACLE)
            )
    workspace = _scenario(run).workspace
    if workspace is not None:
        lo = np.asarray(workspace.lower)[list(axes)]
        hi = np.asarray(workspace.upper)[list(axes)]
        ax.add_patch(
            Rectangle(tuple(lo), *(hi - lo), fill=False, edgecolor="0.2", linestyle="--",
                      linewidth=1.0, zorder=0, gid="workspace")
        )
    lower, upper = _view_limits(run)
    ax.set_xlim(lower[axes[0]], upper[axes[0]])
    ax.set_ylim(lower[axes[1]], upper[axes[1]])
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel(f"{AXIS_NAMES[axes[0]]} [m]")
    ax.set_ylabel(f"{AXIS_NAMES[axes[1]]} [m]")
    ax.grid(True, linewidth=0.4, alpha=0.4)


def _planar_bodies(run: RunData, axes: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre (T+1, M, 2), size (M, 2) and heading (T+1, M) [rad] of the bodies drawn on ``axes``.

    A 2D run draws the footprints (``RunData.poses``, ``RunData.footprints``); a point agent's is
    its body box at heading 0, so its drawing is the box of half-size b_i around its position. A 3D
    view draws the bodies' boxes projected on ``axes``, never turned.
    """
    if run.dim == 2:
        return run.poses[:, :, :2], run.footprints, run.poses[:, :, 2]
    centers = run.positions[:, :, list(axes)]
    return centers, 2.0 * run.body_half_sizes[:, list(axes)], np.zeros(centers.shape[:2])


def _turning(headings: np.ndarray) -> np.ndarray:
    """(M,) True for the agents whose heading (T+1, M) ever leaves 0: they get a heading tick
    (a point agent never turns; a car that does shows which side is its front)."""
    return np.any(headings != 0.0, axis=0)


def _heading_tick(center: np.ndarray, size: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """(..., 2, 2) segments from the centres (..., 2) to the middles of the front sides of footprints
    of sizes (..., 2) at headings (...)."""
    front = center + (size[..., 0] / 2.0)[..., None] * np.stack([np.cos(heading), np.sin(heading)], axis=-1)
    return np.stack([center, front], axis=-2)


def _body_patch(
    center: np.ndarray, size: np.ndarray, heading: float, color: Any, alpha: float, **kwargs: Any
) -> Rectangle:
    """The rectangle of ``size`` (length along the heading, width) centred at ``center`` and
    turned by ``heading`` [rad] about its centre (at heading 0, the plain axis-aligned box)."""
    return Rectangle(tuple(center - size / 2.0), size[0], size[1], angle=math.degrees(heading),
                     rotation_point="center", facecolor=color, edgecolor=color, alpha=alpha,
                     linewidth=0.8, **kwargs)


def _place_body(patch: Rectangle, center: np.ndarray, size: np.ndarray, heading: float) -> None:
    """Move ``patch`` (of :func:`_body_patch`) to ``center`` and ``heading``."""
    patch.set_xy(tuple(center - size / 2.0))
    patch.set_angle(math.degrees(heading))


def _draw_paths_planar(
    ax: Axes, run: RunData, axes: tuple[int, int], colors: list[Any], snapshots: int
) -> None:
    """Paths, start circles, goal stars and snapshot bodies (with the heading ticks of turning
    agents) of every agent, projected on ``axes``."""
    pos = run.positions[:, :, list(axes)]
    goals = run.goals[:, list(axes)]
    centers, sizes, headings = _planar_bodies(run, axes)
    turning = _turning(headings)
    instants = even_indices(run.num_steps + 1, snapshots)
    alphas = np.linspace(0.10, 0.28, len(instants))
    for i, color in enumerate(colors):
        for k, alpha in zip(instants, alphas, strict=True):
            ax.add_patch(_body_patch(centers[k, i], sizes[i], float(headings[k, i]), color, float(alpha),
                                     zorder=2, gid=f"{GID_BODY}:{i}:{int(k)}"))
        if turning[i]:
            ticks = _heading_tick(centers[instants, i], sizes[i], headings[instants, i])
            gaps = np.full((len(instants), 1, 2), np.nan)  # one line, a gap between the ticks
            xy = np.concatenate([ticks, gaps], axis=1).reshape(-1, 2)
            ax.plot(xy[:, 0], xy[:, 1], color=color, linewidth=1.2, zorder=3, gid=f"{GID_HEADING}:{i}")
        ax.plot(pos[:, i, 0], pos[:, i, 1], color=color, linewidth=1.6, zorder=3, label=f"agent {i}")
        ax.plot(*pos[0, i], "o", color=color, markeredgecolor="k", markersize=7, zorder=4)
        ax.plot(*goals[i], "*", color=color, markeredgecolor="k", markersize=13, zorder=4)


def _legend_handles(run: RunData, colors: list[Any], obstacles: bool) -> list[Any]:
    handles: list[Any] = []
    if len(colors) <= 10:
        handles += [Line2D([], [], color=c, linewidth=1.6, label=f"agent {i}") for i, c in enumerate(colors)]
    handles += [
        Line2D([], [], marker="o", linestyle="", color="0.8", markeredgecolor="k", label="start"),
        Line2D([], [], marker="*", linestyle="", color="0.8", markeredgecolor="k", markersize=12, label="goal"),
        Patch(facecolor="0.6", edgecolor="0.6", alpha=0.3, label=f"{BODY_LABEL}, snapshots"),
    ]
    if run.dim == 2 and _turning(run.poses[:, :, 2]).any():
        handles.append(Line2D([], [], color="0.3", linewidth=1.2, label="heading (to the front)"))
    if obstacles:
        handles.append(Patch(facecolor=OBSTACLE_COLOR, edgecolor="0.3", label="obstacle"))
    if _scenario(run).workspace is not None:
        handles.append(Line2D([], [], color="0.2", linestyle="--", label="workspace"))
    return handles


def _set_3d_view(ax: Any, run: RunData) -> None:
    lower, upper = _view_limits(run)
    ax.set_xlim(lower[0], upper[0])
    ax.set_ylim(lower[1], upper[1])
    ax.set_zlim(lower[2], upper[2])
    span = upper - lower
    ax.set_box_aspect(np.maximum(span, 0.3 * span.max()), zoom=1.05)  # equal scale unless very flat
    ax.set_xlabel("x [m]", labelpad=-2)
    ax.set_ylabel("y [m]", labelpad=-2)
    ax.set_zlabel("z [m]", labelpad=-2)
    ax.tick_params(labelsize=7, pad=0)
    ax.view_init(elev=24, azim=-58)


def _draw_obstacles_3d(ax: Any, obstacles: list[np.ndarray]) -> None:
    for vertices in obstacles:
        faces = _hull_faces(vertices)
        if faces:
            ax.add_collection3d(
                Poly3DCollection(faces, facecolor=OBSTACLE_COLOR, edgecolor="0.3", linewidth=0.6,
                                 alpha=0.3, gid=GID_OBSTACLE)
            )


# --------------------------------------------------------------------------------- figures
def make_trajectory_figure(run: RunData, snapshots: int = 4) -> Figure:
    """The trajectory figure (paper Fig. 3) without saving it.

    Parameters
    ----------
    run : RunData
        A loaded run.
    snapshots : int
        Number of evenly spaced instants (first and last included) at which the agents' bodies
        are drawn.

    Returns
    -------
    Figure
        2D: one axes. 3D: a 3D axes, a top view (x-y) and a side view (x-z).
    """
    colors = agent_colors(run.num_agents)
    obstacles = _obstacle_vertices(run)
    handles = _legend_handles(run, colors, bool(obstacles))
    if run.dim == 2:
        fig = _new_figure(8.0, 6.0)
        ax = fig.add_subplot()
        _draw_static_planar(ax, run, (0, 1), obstacles)
        _draw_paths_planar(ax, run, (0, 1), colors, snapshots)
        ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)
        ax.set_title(_headline(run), fontsize=9)
        return fig
    # A fixed layout: constrained layout lets a 3D axes' labels spill over its neighbours.
    fig = _new_figure(14.0, 5.2, layout=None)
    ax3 = fig.add_axes((0.0, 0.10, 0.36, 0.78), projection="3d")
    _set_3d_view(ax3, run)
    _draw_obstacles_3d(ax3, obstacles)
    pos, goals = run.positions, run.goals[:, :3]
    for i, color in enumerate(colors):
        ax3.plot(pos[:, i, 0], pos[:, i, 1], pos[:, i, 2], color=color, linewidth=1.5)
        ax3.plot(*pos[0, i, :, None], "o", color=color, markeredgecolor="k", markersize=6)
        ax3.plot(*goals[i, :, None], "*", color=color, markeredgecolor="k", markersize=11)
    ax3.set_title("3D view", fontsize=9)
    for axes, left, title in (((0, 1), 0.41, "top view (x-y)"), ((0, 2), 0.72, "side view (x-z)")):
        ax = fig.add_axes((left, 0.17, 0.26, 0.66))
        _draw_static_planar(ax, run, axes, obstacles)
        _draw_paths_planar(ax, run, axes, colors, snapshots)
        ax.set_title(title, fontsize=9)
    fig.legend(handles=handles, loc="lower center", bbox_to_anchor=(0.5, 0.0), ncol=len(handles),
               fontsize=8, frameon=False)
    fig.suptitle(_headline(run), fontsize=10, y=0.985)
    return fig


def plot_trajectories(run: RunData, path: PathLike, snapshots: int = 4) -> Path:
    """Save the trajectory figure (paper Fig. 3) as a PNG.

    Parameters
    ----------
    run : RunData
        A loaded run.
    path : str or PathLike
        Output PNG file.
    snapshots : int
        Number of instants at which the agents' bodies are drawn.

    Returns
    -------
    Path
        The written file.
    """
    return _save(make_trajectory_figure(run, snapshots), path)


def _default_steps(admm: AdmmResiduals) -> list[int]:
    """First, middle and slowest MPC step, without repeats, in order."""
    steps = admm.primal.shape[0]
    iterations = np.nan_to_num(admm.iterations, nan=-1.0)
    return sorted({0, steps // 2, int(np.argmax(iterations))})


def make_convergence_figure(run: RunData, steps: Sequence[int] | None = None) -> Figure:
    """The ADMM convergence figure (paper Fig. 4) without saving it.

    Parameters
    ----------
    run : RunData
        A loaded run with ADMM residuals.
    steps : sequence of int, optional
        MPC steps to show; default: the first, the middle and the slowest step.

    Returns
    -------
    Figure
        Primal and dual residuals vs iteration (log scale) and the iterations per MPC step.

    Raises
    ------
    ValueError
        When the run has no ADMM residuals or a step is out of range.
    """
    admm = run.admm
    if admm is None:
        raise RunDataError(f"{run.run_dir}: no ADMM residuals (admm.npz) in this run; nothing to plot")
    total = admm.primal.shape[0]
    if total == 0:
        raise RunDataError(f"{run.run_dir}: admm.npz holds no MPC steps")
    chosen = _default_steps(admm) if steps is None else [int(s) for s in steps]
    bad = [s for s in chosen if not 0 <= s < total]
    if bad or not chosen:
        raise ValueError(f"steps: expected MPC steps in [0, {total - 1}], got {list(steps or [])}")
    fig = _new_figure(12.0, 4.0)
    grid = fig.add_gridspec(1, 3, width_ratios=[1.0, 1.0, 0.9])
    ax_p = fig.add_subplot(grid[0])
    ax_d = fig.add_subplot(grid[1], sharey=ax_p)
    ax_it = fig.add_subplot(grid[2])
    shades = colormaps["viridis"](np.linspace(0.0, 0.8, len(chosen)))
    tol = run.summary.get("admm_tol")
    for ax, values, label in ((ax_p, admm.primal, "primal"), (ax_d, admm.dual, "dual")):
        for step, color in zip(chosen, shades, strict=True):
            row = np.where(values[step] > 0, values[step], np.nan)
            iters = np.arange(1, row.size + 1)
            keep = np.isfinite(row)
            ax.plot(iters[keep], row[keep], "-", marker=".", markersize=3, color=color,
                    label=f"step {step} ({int(admm.iterations[step])} it.)")
        if tol is not None:
            ax.axhline(float(tol), color="k", linestyle="--", linewidth=1.0,
                       label=f"tolerance {float(tol):g}", gid=GID_TOLERANCE)
        ax.set_yscale("log", nonpositive="mask")
        ax.set_xlabel("ADMM iteration")
        ax.set_ylabel(f"{label} residual")
        ax.set_title(f"{label} residual", fontsize=9)
        ax.grid(True, which="both", linewidth=0.4, alpha=0.4)
    ax_p.legend(fontsize=8)
    mpc_steps = np.arange(total)
    ax_it.bar(mpc_steps, admm.iterations, width=1.0, color="0.7")
    for step, color in zip(chosen, shades, strict=True):
        ax_it.bar([step], [admm.iterations[step]], width=1.0, color=color)
    ax_it.set_xlabel("MPC step")
    ax_it.set_ylabel("ADMM iterations")
    ax_it.set_title("iterations per MPC step", fontsize=9)
    ax_it.grid(True, axis="y", linewidth=0.4, alpha=0.4)
    fig.suptitle(f"{_plain(run.name)}: ADMM convergence ({total} MPC steps)", fontsize=10)
    return fig


def plot_convergence(run: RunData, path: PathLike, steps: Sequence[int] | None = None) -> Path:
    """Save the ADMM convergence figure (paper Fig. 4) as a PNG.

    Parameters
    ----------
    run : RunData
        A loaded run with ADMM residuals.
    path : str or PathLike
        Output PNG file.
    steps : sequence of int, optional
        MPC steps to show; default: the first, the middle and the slowest step.

    Returns
    -------
    Path
        The written file.

    Raises
    ------
    ValueError
        When the run has no ADMM residuals.
    """
    return _save(make_convergence_figure(run, steps), path)


# --------------------------------------------------------------------------------- animation
def _planar_movers(
    ax: Axes, run: RunData, axes: tuple[int, int], colors: list[Any]
) -> Callable[[int, int], None]:
    """Create the moving artists of a 2D view; return ``update(k, first)`` (trail from ``first``)."""
    pos = run.positions[:, :, list(axes)]
    centers, sizes, headings = _planar_bodies(run, axes)
    for i, color in enumerate(colors):
        ax.plot(*run.goals[i, list(axes)], "*", color=color, markeredgecolor="k", markersize=11, zorder=4)
    boxes = [_body_patch(centers[0, i], sizes[i], float(headings[0, i]), c, 0.3, zorder=2, gid=f"{GID_BODY}:{i}")
             for i, c in enumerate(colors)]
    for box in boxes:
        ax.add_patch(box)
    ticks = {i: ax.plot([], [], color=colors[i], linewidth=1.2, zorder=3, gid=f"{GID_HEADING}:{i}")[0]
             for i in map(int, np.flatnonzero(_turning(headings)))}
    trails = [ax.plot([], [], color=c, linewidth=1.5, zorder=3)[0] for c in colors]
    dots = [ax.plot([], [], "o", color=c, markeredgecolor="k", markersize=5, zorder=5)[0] for c in colors]
    numbers = [ax.text(pos[0, i, 0], pos[0, i, 1], f" {i}", color=c, fontsize=8, fontweight="bold", zorder=6)
               for i, c in enumerate(colors)]

    def update(k: int, first: int) -> None:
        for i in range(len(colors)):
            _place_body(boxes[i], centers[k, i], sizes[i], float(headings[k, i]))
            if i in ticks:
                ticks[i].set_data(*_heading_tick(centers[k, i], sizes[i], headings[k, i]).T)
            trails[i].set_data(pos[first : k + 1, i, 0], pos[first : k + 1, i, 1])
            dots[i].set_data([pos[k, i, 0]], [pos[k, i, 1]])
            numbers[i].set_position(tuple(pos[k, i]))

    return update


def _cube_edges(center: np.ndarray, half: np.ndarray) -> np.ndarray:
    """(12, 2, 3) edge segments of the box ``center +- half``."""
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    points = center + corners * half
    pairs = [(a, b) for a in range(8) for b in range(a + 1, 8) if np.sum(corners[a] != corners[b]) == 1]
    return np.array([[points[a], points[b]] for a, b in pairs])


def _spatial_movers(ax: Any, run: RunData, colors: list[Any]) -> Callable[[int, int], None]:
    """Moving artists of the 3D axes: dots, trails and wireframe bodies."""
    pos = run.positions
    bodies = run.body_half_sizes
    for i, color in enumerate(colors):
        ax.plot(*run.goals[i, :3, None], "*", color=color, markeredgecolor="k", markersize=10)
    trails = [ax.plot([], [], [], color=c, linewidth=1.4)[0] for c in colors]
    dots = [ax.plot([], [], [], "o", color=c, markeredgecolor="k", markersize=5)[0] for c in colors]
    cubes = Line3DCollection(
        np.concatenate([_cube_edges(pos[0, i], bodies[i]) for i in range(len(colors))]),
        colors=np.repeat(np.asarray(colors), 12, axis=0), linewidths=0.7, alpha=0.6,
    )
    ax.add_collection3d(cubes)
    numbers = [ax.text(*pos[0, i], f" {i}", color=c, fontsize=8, fontweight="bold") for i, c in enumerate(colors)]

    def update(k: int, first: int) -> None:
        for i in range(len(colors)):
            trails[i].set_data_3d(pos[first : k + 1, i, 0], pos[first : k + 1, i, 1], pos[first : k + 1, i, 2])
            dots[i].set_data_3d([pos[k, i, 0]], [pos[k, i, 1]], [pos[k, i, 2]])
            numbers[i].set_position_3d(tuple(pos[k, i]))
        cubes.set_segments(np.concatenate([_cube_edges(pos[k, i], bodies[i]) for i in range(len(colors))]))

    return update


def _time_format(times: np.ndarray) -> str:
    """A format with enough decimals that consecutive frame times print differently."""
    gaps = np.diff(times)
    smallest = float(gaps.min()) if gaps.size and np.all(gaps > 0) else 0.1
    decimals = max(1, math.ceil(-math.log10(smallest) - 1e-9))
    return f"t = {{:.{min(decimals, 4)}f}} s"


def find_ffmpeg() -> str | None:
    """The ffmpeg executable for MP4 output: matplotlib's configured one when it runs, else the
    binary shipped by the ``imageio-ffmpeg`` wheel (a dependency, so a fresh install has one)."""
    if animation.writers.is_available("ffmpeg"):
        return str(matplotlib.rcParams["animation.ffmpeg_path"])
    try:
        import imageio_ffmpeg
    except ImportError:
        return None
    try:
        return str(imageio_ffmpeg.get_ffmpeg_exe())
    except RuntimeError:  # the wheel has no binary for this platform
        return None


def animate(
    run: RunData,
    path: PathLike,
    fmt: Literal["gif", "mp4"] = "gif",
    fps: float | None = None,
    max_frames: int = 200,
) -> Path:
    """Write an animation of the run: agents with their bodies, short trails, goals and obstacles.

    Parameters
    ----------
    run : RunData
        A loaded run.
    path : str or PathLike
        Output file; its suffix must match ``fmt`` (added when missing).
    fmt : {"gif", "mp4"}
        GIF through Pillow, MP4 through ffmpeg.
    fps : float, optional
        Frames per second; default real time, capped to 20.
    max_frames : int
        The states are subsampled evenly to at most this many frames (see :func:`frame_indices`).

    Returns
    -------
    Path
        The written file.

    Raises
    ------
    AnimationWriterError
        ``fmt="mp4"`` without ffmpeg installed.
    ValueError
        Unknown ``fmt``, mismatched suffix, ``max_frames < 1`` or ``fps <= 0``.
    """
    if fmt not in ("gif", "mp4"):
        raise ValueError(f"fmt: expected 'gif' or 'mp4', got {fmt!r}")
    if max_frames < 1:
        raise ValueError(f"max_frames: must be >= 1, got {max_frames}")
    if fps is not None and fps <= 0:
        raise ValueError(f"fps: must be > 0, got {fps}")
    out = Path(path)
    if out.suffix == "":
        out = out.with_suffix(f".{fmt}")
    elif out.suffix.lower() != f".{fmt}":
        raise ValueError(f"{out}: suffix does not match fmt={fmt!r}")
    ffmpeg_path = find_ffmpeg() if fmt == "mp4" else None
    if fmt == "mp4" and ffmpeg_path is None:
        raise AnimationWriterError(
            "mp4 animations need ffmpeg, which was not found: install ffmpeg "
            "(e.g. `pip install imageio-ffmpeg` or `apt-get install ffmpeg`) "
            "or write a GIF instead (--format gif, fmt='gif')"
        )
    frames = frame_indices(run.num_steps + 1, max_frames)
    times = run.t[frames]
    if fps is None:
        duration = float(times[-1] - times[0])
        fps = min(MAX_FPS, (len(frames) - 1) / duration) if duration > 0 and len(frames) > 1 else 10.0
    trail = max(1, round(TRAIL_SECONDS / run.dt)) if run.dt > 0 else 15
    colors = agent_colors(run.num_agents)
    obstacles = _obstacle_vertices(run)
    if run.dim == 2:
        fig = _new_figure(6.4, 5.4)
        ax = fig.add_subplot()
        _draw_static_planar(ax, run, (0, 1), obstacles)
        updates = [_planar_movers(ax, run, (0, 1), colors)]
    else:
        fig = _new_figure(10.0, 5.0)
        ax3 = fig.add_subplot(1, 2, 1, projection="3d")
        _set_3d_view(ax3, run)
        _draw_obstacles_3d(ax3, obstacles)
        ax = fig.add_subplot(1, 2, 2)
        _draw_static_planar(ax, run, (0, 1), obstacles)
        ax.set_title("top view (x-y)", fontsize=9)
        updates = [_spatial_movers(ax3, run, colors), _planar_movers(ax, run, (0, 1), colors)]
    method = run.summary.get("method", _scenario(run).solver.method)
    fig.suptitle(f"{_plain(run.name)} ({_plain(method)}); boxes: {BODY_LABEL}", fontsize=10)
    clock = ax.text(0.02, 0.98, "", transform=ax.transAxes, fontsize=9, va="top", ha="left", zorder=10,
                    bbox={"boxstyle": "round,pad=0.3", "facecolor": "white", "edgecolor": "0.6", "alpha": 0.85})
    label = _time_format(times)
    fig.canvas.draw()
    fig.set_layout_engine("none")  # freeze the layout: every frame has the same geometry
    writer: animation.AbstractMovieWriter
    if fmt == "gif":
        # The writers take any positive frame rate (frame duration 1000 / fps, ffmpeg's -r); the stubs say int.
        writer = animation.PillowWriter(fps=fps)  # type: ignore[arg-type]
    else:
        writer = animation.FFMpegWriter(
            fps=fps, codec="h264", extra_args=["-pix_fmt", "yuv420p"]  # type: ignore[arg-type]
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    rc: dict[RcKeyType, Any] = {"animation.ffmpeg_path": ffmpeg_path} if ffmpeg_path else {}
    with matplotlib.rc_context(rc), writer.saving(fig, str(out), dpi=ANIMATION_DPI):
        for k, stamp in zip(frames, times, strict=True):
            first = max(0, int(k) - trail)
            for update in updates:
                update(int(k), first)
            clock.set_text(label.format(stamp))
            writer.grab_frame()
    fig.clear()
    return out


# --------------------------------------------------------------------------------- entry point
def plot_run(run_dir: PathLike | RunData, out: PathLike | None = None) -> list[Path]:
    """Load a run folder and write its figures (what ``swarmpc plot RUN_DIR`` calls).

    Parameters
    ----------
    run_dir : str, PathLike or RunData
        The run folder, or one already loaded (:func:`load_run`).
    out : str or PathLike, optional
        Output folder (created if needed); default the run folder.

    Returns
    -------
    list of Path
        ``trajectory.png`` and, when the run has ADMM residuals, ``convergence.png``.
    """
    run = run_dir if isinstance(run_dir, RunData) else load_run(Path(run_dir))
    folder = Path(out) if out is not None else run.run_dir
    written = [plot_trajectories(run, folder / "trajectory.png")]
    if run.admm is not None and run.admm.primal.shape[0] > 0:
        written.append(plot_convergence(run, folder / "convergence.png"))
    return written
