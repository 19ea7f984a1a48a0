"""Bodies drawn as oriented footprints: the figures, the animation and the HTML viewer of a 2D run
draw each agent's rectangle ``footprints`` at ``poses`` (and a heading tick for an agent that
turns), and a point run's drawing stays the axis-aligned box of its body.

The run folders are real (written by ``write_run`` from a short 2-agent run); the turned one has
its ``poses`` and ``footprints`` in ``trajectory.npz`` replaced by turned ones of the same shapes.
Every expected corner is recomputed here from the saved arrays with ``footprint_vertices``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from swarmpc import plots, viewer
from swarmpc.config import scenario_from_dict
from swarmpc.model.footprint import footprint_vertices
from swarmpc.simulation.loop import simulate
from swarmpc.simulation.results import write_run

SCENARIO = {
    "name": "oriented", "dim": 2, "delta": 0.3,
    "workspace": {"lower": [-3, -3], "upper": [3, 3]},
    "agents": [{"start": [-1.5, 0.4], "goal": [1.5, 0.4], "body": [0.12, 0.2]},
               {"start": [1.5, -0.4], "goal": [-1.5, -0.4]}],
    "solver": {"method": "centralized"},
    "stop": {"max_steps": 5},
}
FOOTPRINTS = np.array([[0.5, 0.2], [0.4, 0.25]])
OUTLINE = [2, 3, 0, 1]  # footprint_vertices' corners from the rear right one, as a unit square's path runs


def _saved(folder: Path) -> dict[str, np.ndarray]:
    with np.load(folder / "trajectory.npz") as data:
        return {name: data[name] for name in data.files}


def _turn(folder: Path) -> None:
    """Replace the saved poses and footprints by turned ones: agent 0 turns from pi/4 on, agent 1
    keeps pi/4; each centre sits a little ahead of its position along its heading."""
    arrays = _saved(folder)
    poses = arrays["poses"].copy()
    steps = poses.shape[0]
    poses[:, 0, 2] = np.pi / 4 + 0.3 * np.arange(steps)
    poses[:, 1, 2] = np.pi / 4
    poses[:, :, :2] += 0.05 * np.stack([np.cos(poses[:, :, 2]), np.sin(poses[:, :, 2])], axis=-1)
    arrays.update(poses=poses, footprints=FOOTPRINTS.copy())
    np.savez(folder / "trajectory.npz", **arrays)


@pytest.fixture(scope="module")
def folders(tmp_path_factory) -> dict[str, Path]:
    """The same short run twice: as written (point agents) and with turned footprints."""
    result = simulate(scenario_from_dict(SCENARIO))
    root = tmp_path_factory.mktemp("oriented")
    turned = write_run(result, root / "turned")
    _turn(turned)
    return {"point": write_run(result, root / "point"), "turned": turned}


def _corners(patch) -> np.ndarray:
    """(4, 2) corners of a body patch in data coordinates, as the figure draws its path."""
    return patch.get_patch_transform().transform(patch.get_path().vertices)[:4]


def _body_patches(ax) -> dict[tuple[int, ...], object]:
    return {tuple(int(n) for n in p.get_gid().split(":")[1:]): p for p in ax.patches
            if (p.get_gid() or "").startswith(f"{plots.GID_BODY}:")}


def _ticks(ax) -> dict[int, np.ndarray]:
    """Heading lines by agent: (n, 2, 2) segments (centre, front middle)."""
    out = {}
    for line in ax.lines:
        gid = line.get_gid() or ""
        if gid.startswith(f"{plots.GID_HEADING}:"):
            xy = np.asarray(line.get_xydata(), float)
            out[int(gid.split(":")[1])] = xy[np.isfinite(xy).all(axis=1)].reshape(-1, 2, 2)
    return out


def _expected_tick(pose: np.ndarray, size: np.ndarray) -> np.ndarray:
    front = pose[..., :2] + size[0] / 2 * np.stack([np.cos(pose[..., 2]), np.sin(pose[..., 2])], axis=-1)
    return np.stack([pose[..., :2], front], axis=-2)


# ------------------------------------------------------------------------------------ figures
def test_the_trajectory_figure_draws_the_saved_footprints_turned(folders):
    arrays = _saved(folders["turned"])
    run = plots.load_run(folders["turned"])
    steps = run.num_steps + 1
    ax = plots.make_trajectory_figure(run, snapshots=steps).axes[0]
    bodies = _body_patches(ax)
    assert sorted(bodies) == [(i, k) for i in range(2) for k in range(steps)]
    for (i, k), patch in bodies.items():
        expected = footprint_vertices(arrays["poses"][k, i], arrays["footprints"][i])[OUTLINE]
        np.testing.assert_allclose(_corners(patch), expected, atol=1e-12)
    ticks = _ticks(ax)
    assert sorted(ticks) == [0, 1]  # both headings leave 0
    for i, segments in ticks.items():
        np.testing.assert_allclose(segments, _expected_tick(arrays["poses"][:, i], arrays["footprints"][i]),
                                   atol=1e-12)
    corners = footprint_vertices(arrays["poses"], arrays["footprints"]).reshape(-1, 2)
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    assert np.all((corners[:, 0] > x0) & (corners[:, 0] < x1) & (corners[:, 1] > y0) & (corners[:, 1] < y1))


def test_plot_run_writes_the_turned_figure(folders, tmp_path):
    written = plots.plot_run(folders["turned"], tmp_path)
    assert [p.name for p in written] == ["trajectory.png"]
    assert written[0].stat().st_size > 0


def test_the_animation_moves_and_turns_the_footprints(folders, tmp_path):
    arrays = _saved(folders["turned"])
    run = plots.load_run(folders["turned"])
    ax = plots._new_figure(6.0, 5.0).add_subplot()
    update = plots._planar_movers(ax, run, (0, 1), plots.agent_colors(run.num_agents))
    bodies = _body_patches(ax)
    assert sorted(bodies) == [(0,), (1,)]
    for k in range(run.num_steps + 1):
        update(k, 0)
        ticks = _ticks(ax)
        for i in range(2):
            expected = footprint_vertices(arrays["poses"][k, i], arrays["footprints"][i])[OUTLINE]
            np.testing.assert_allclose(_corners(bodies[(i,)]), expected, atol=1e-12)
            np.testing.assert_allclose(ticks[i][0], _expected_tick(arrays["poses"][k, i], arrays["footprints"][i]),
                                       atol=1e-12)
    assert plots.animate(run, tmp_path / "turned.gif", max_frames=3).stat().st_size > 0


def test_a_point_run_draws_axis_aligned_boxes_of_the_saved_size(folders):
    arrays = _saved(folders["point"])
    positions, bodies = arrays["states"][:, :, :2], arrays["bodies"]
    assert np.array_equal(arrays["footprints"], 2 * bodies) and not np.any(arrays["poses"][:, :, 2])
    run = plots.load_run(folders["point"])
    ax = plots.make_trajectory_figure(run, snapshots=run.num_steps + 1).axes[0]
    for (i, k), patch in _body_patches(ax).items():
        assert patch.get_angle() == 0
        assert (patch.get_width(), patch.get_height()) == tuple(arrays["footprints"][i])
        lower, upper = positions[k, i] - bodies[i], positions[k, i] + bodies[i]
        square = np.array([lower, [upper[0], lower[1]], upper, [lower[0], upper[1]]])
        np.testing.assert_allclose(_corners(patch), square, atol=1e-12)
    assert _ticks(ax) == {}


# ------------------------------------------------------------------------------------ viewer
def _box_traces(fig: dict) -> list[tuple[int, dict, dict]]:
    """(time index, agent, trace) of every body trace: the initial data and each frame's."""
    roles = {n: tr.get("meta") or {} for n, tr in enumerate(fig["data"])}
    boxes = {n: meta["agent"] for n, meta in roles.items() if meta.get("role") == "box"}
    out = [(0, boxes[n], fig["data"][n]) for n in boxes]
    for frame in fig["frames"]:
        out += [(int(frame["name"]), boxes[n], tr) for n, tr in zip(frame["traces"], frame["data"], strict=True)
                if n in boxes]
    return out


def test_the_viewer_draws_the_saved_footprints_turned_with_heading_ticks(folders):
    arrays = _saved(folders["turned"])
    fig = viewer.figure_dict(folders["turned"])
    traces = _box_traces(fig)
    assert len(traces) == 2 * (1 + len(fig["frames"]))
    for k, i, trace in traces:
        pose, size = arrays["poses"][k, i], arrays["footprints"][i]
        assert trace["x"][5] is None and trace["y"][5] is None and len(trace["x"]) == 8
        outline = np.array([trace["x"][:5], trace["y"][:5]], float).T
        np.testing.assert_allclose(outline, footprint_vertices(pose, size)[OUTLINE + [2]], atol=6e-4)
        tick = np.array([trace["x"][6:], trace["y"][6:]], float).T
        np.testing.assert_allclose(tick, _expected_tick(pose, size), atol=6e-4)
    lo = [fig["layout"]["xaxis"]["range"][0], fig["layout"]["yaxis"]["range"][0]]
    hi = [fig["layout"]["xaxis"]["range"][1], fig["layout"]["yaxis"]["range"][1]]
    corners = footprint_vertices(arrays["poses"], arrays["footprints"]).reshape(-1, 2)
    assert np.all((corners > lo) & (corners < hi))


def test_the_viewer_draws_a_point_runs_boxes_as_before(folders):
    arrays = _saved(folders["point"])
    positions, bodies = arrays["states"][:, :, :2], arrays["bodies"]
    fig = viewer.figure_dict(folders["point"])
    for k, i, trace in _box_traces(fig):
        lower, upper = positions[k, i] - bodies[i], positions[k, i] + bodies[i]
        assert (trace["x"], trace["y"]) == tuple(viewer._box_lines(lower, upper, 3))  # no tick, same loop
        np.testing.assert_allclose(np.ptp(trace["x"]), arrays["footprints"][i, 0], atol=1e-3)
        np.testing.assert_allclose(np.ptp(trace["y"]), arrays["footprints"][i, 1], atol=1e-3)
