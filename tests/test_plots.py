"""Tests of swarmpc.plots on synthetic run folders that follow the run-folder contract."""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import matplotlib
import matplotlib.image
import numpy as np
import pytest
from PIL import Image

from swarmpc import plots
from swarmpc.config import scenario_from_dict, scenario_to_yaml

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
MAX_BYTES = 300_000


def _rollout(starts: np.ndarray, goals: np.ndarray, dt: float, steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Euler double integrator s+ = [p + dt v, v + dt u] under a saturated PD law toward the goals."""
    m, two_d = starts.shape
    d = two_d // 2
    states = np.empty((steps + 1, m, two_d))
    inputs = np.empty((steps, m, d))
    states[0] = starts
    for k in range(steps):
        p, v = states[k, :, :d], states[k, :, d:]
        u = np.clip(1.5 * (goals[:, :d] - p) - 2.0 * v, -2.0, 2.0)
        inputs[k] = u
        states[k + 1] = np.hstack([p + dt * v, v + dt * u])
    return states, inputs


def _write_run(folder: Path, scn_dict: dict, steps: int, admm: bool) -> Path:
    folder.mkdir()
    scn = scenario_from_dict(scn_dict)
    (folder / "scenario.yaml").write_text(scenario_to_yaml(scn))
    starts, goals = scn.start_states(), scn.goal_states()
    states, inputs = _rollout(starts, goals, scn.dt, steps)
    np.savez(
        folder / "trajectory.npz",
        t=scn.dt * np.arange(steps + 1),
        states=states,
        inputs=inputs,
        goals=goals,
        delta=np.float64(scn.delta) if isinstance(scn.delta, float) else np.asarray(scn.delta),
        dt=np.float64(scn.dt),
    )
    summary = {
        "scenario": scn.name, "method": scn.solver.method, "collision": scn.collision,
        "num_agents": scn.num_agents, "dim": scn.dim, "delta": scn.delta, "steps": steps,
        "all_reached": True, "reached": [True] * scn.num_agents, "collisions": 0,
        "min_separation_inf": 1.7, "max_slack": 0.0, "cost": 12.3, "step_time_ms": 4.2,
        "admm_iterations": 17.0, "solver_failures": 0, "wall_time_s": 1.0,
    }
    if admm:
        rng = np.random.default_rng(0)
        max_iter = 30
        iterations = rng.integers(4, max_iter, size=steps)  # below max_iter ...
        iterations[steps // 3] = max_iter  # ... except one unique slowest step
        primal = np.full((steps, max_iter), np.nan)
        dual = np.full((steps, max_iter), np.nan)
        for k, n in enumerate(iterations):
            decay = 10.0 ** (-np.arange(n) / 6.0)
            primal[k, :n] = decay * (1 + rng.random(n))
            dual[k, :n] = 0.3 * decay * (1 + rng.random(n))
        np.savez(folder / "admm.npz", primal=primal, dual=dual, iterations=iterations)
        summary["admm_tol"] = 1e-3
    (folder / "summary.json").write_text(json.dumps(summary))
    return folder


STEPS_2D = 60
STEPS_3D = 30


@pytest.fixture(scope="module")
def run_2d(tmp_path_factory: pytest.TempPathFactory) -> Path:
    scn = {
        "name": "cross-2d",
        "dim": 2,
        "dt": 0.1,
        "delta": 0.3,
        "workspace": {"lower": [-1.0, -1.0], "upper": [6.0, 5.0]},
        "obstacles": [
            {"box": {"center": [2.5, 0.5], "half_size": [0.4, 0.4]}},
            # triangle x >= 2, y >= 3, x + y <= 6.5
            {"polytope": {"G": [[-1.0, 0.0], [0.0, -1.0], [1.0, 1.0]], "g": [-2.0, -3.0, 6.5]}},
        ],
        "agents": [
            {"start": [0.0, 0.0], "goal": [5.0, 4.0]},
            {"start": [0.0, 2.0], "goal": [5.0, 2.0]},
            {"start": [0.0, 4.0], "goal": [5.0, 0.0]},
        ],
    }
    return _write_run(tmp_path_factory.mktemp("runs") / "run2d", scn, STEPS_2D, admm=True)


@pytest.fixture(scope="module")
def run_3d(tmp_path_factory: pytest.TempPathFactory) -> Path:
    scn = {
        "name": "swap-3d",
        "dim": 3,
        "dt": 0.1,
        "delta": [0.3, 0.3, 0.2],
        "workspace": {"lower": [0.0, 0.0, 0.0], "upper": [6.0, 6.0, 3.0]},
        "obstacles": [{"box": {"center": [3.0, 3.0, 1.5], "half_size": [0.5, 0.5, 0.8]}}],
        "agents": [
            {"start": [0.5, 0.5, 1.0], "goal": [5.5, 5.5, 2.0]},
            {"start": [5.5, 0.5, 1.0], "goal": [0.5, 5.5, 1.0]},
            {"start": [0.5, 5.5, 1.5], "goal": [5.5, 0.5, 0.5]},
            {"start": [5.5, 5.5, 2.0], "goal": [0.5, 0.5, 2.5]},
        ],
    }
    return _write_run(tmp_path_factory.mktemp("runs") / "run3d", scn, STEPS_3D, admm=False)


def _assert_png(path: Path, size_px: tuple[int, int]) -> None:
    assert path.is_file()
    assert path.read_bytes()[:8] == PNG_MAGIC
    assert path.stat().st_size < MAX_BYTES, f"{path.name} is {path.stat().st_size} bytes"
    image = matplotlib.image.imread(path)
    height, width = image.shape[:2]
    assert abs(width - size_px[0]) <= 2 and abs(height - size_px[1]) <= 2, image.shape


def _expected_px(fig_size: tuple[float, float]) -> tuple[int, int]:
    return round(fig_size[0] * plots.DPI), round(fig_size[1] * plots.DPI)


# ------------------------------------------------------------------------------- geometry
def test_polygon_vertices_of_box_are_its_corners() -> None:
    G = np.vstack([np.eye(2), -np.eye(2)])
    g = np.array([1.5, 3.5, -0.5, -0.5])  # x in [0.5, 1.5], y in [0.5, 3.5]
    vertices = plots.polygon_vertices_2d(G, g)
    corners = {(0.5, 0.5), (1.5, 0.5), (1.5, 3.5), (0.5, 3.5)}
    assert vertices.shape == (4, 2)
    assert {tuple(np.round(v, 9)) for v in vertices} == corners
    x, y = vertices[:, 0], vertices[:, 1]
    assert 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) == pytest.approx(3.0)  # CCW, area 3


def test_polygon_vertices_of_triangle_with_redundant_face() -> None:
    G = np.array([[-1.0, 0.0], [0.0, -1.0], [1.0, 1.0], [1.0, 0.0]])
    g = np.array([0.0, 0.0, 1.0, 5.0])  # last face is redundant
    vertices = plots.polygon_vertices_2d(G, g)
    assert {tuple(np.round(v, 9) + 0.0) for v in vertices} == {(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)}


def test_unbounded_polygon_needs_bounds_and_is_clipped() -> None:
    G, g = np.array([[1.0, 0.0]]), np.array([0.0])  # half-plane x <= 0
    with pytest.raises(ValueError, match="unbounded"):
        plots.polygon_vertices_2d(G, g)
    strip_G, strip_g = np.array([[0.0, 1.0], [0.0, -1.0], [1.0, 0.0]]), np.array([1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="unbounded"):  # 0 <= y <= 1, x <= 0: finite inradius, unbounded
        plots.polygon_vertices_2d(strip_G, strip_g)
    vertices = plots.polygon_vertices_2d(G, g, bounds=(np.array([-1.0, -1.0]), np.array([1.0, 1.0])))
    assert {tuple(np.round(v, 9) + 0.0) for v in vertices} == {(-1.0, -1.0), (0.0, -1.0), (0.0, 1.0), (-1.0, 1.0)}


def test_empty_polygon_has_no_vertices() -> None:
    G, g = np.array([[1.0, 0.0], [-1.0, 0.0]]), np.array([0.0, -1.0])  # x <= 0 and x >= 1
    assert plots.polygon_vertices_2d(G, g, bounds=(-np.ones(2), np.ones(2))).shape == (0, 2)


def test_hull_faces_of_a_cube_are_six_squares() -> None:
    vertices = plots.polytope_vertices(np.vstack([np.eye(3), -np.eye(3)]), np.ones(6))
    faces = plots._hull_faces(vertices)
    assert len(faces) == 6 and all(face.shape == (4, 3) for face in faces)


def test_agent_colors() -> None:
    few = plots.agent_colors(3)
    assert len(few) == 3 and len(set(few)) == 3
    assert few == plots.agent_colors(10)[:3]  # tab10 order, stable per agent index
    many = plots.agent_colors(25)
    assert len(many) == 25 and len(set(many)) == 25
    assert plots.agent_colors(0) == []


@pytest.mark.parametrize(("num_states", "max_frames"), [(61, 200), (61, 12), (2, 5), (1, 10), (200, 199), (7, 1)])
def test_frame_indices(num_states: int, max_frames: int) -> None:
    idx = plots.frame_indices(num_states, max_frames)
    assert len(idx) == min(num_states, max_frames)
    assert idx[0] == 0 and (len(idx) == 1 or idx[-1] == num_states - 1)
    assert np.all(np.diff(idx) > 0)


# ------------------------------------------------------------------------------- loading
def test_load_run(run_2d: Path, run_3d: Path) -> None:
    run = plots.load_run(run_2d)
    assert run.dim == 2 and run.num_agents == 3 and run.num_steps == STEPS_2D
    assert run.positions.shape == (STEPS_2D + 1, 3, 2)
    assert run.delta.shape == (2,) and np.all(run.delta == 0.3)
    assert run.admm is not None and run.admm.primal.shape == (STEPS_2D, 30)
    assert run.summary["admm_tol"] == 1e-3
    with pytest.raises(dataclasses.FrozenInstanceError):
        run.dt = 1.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        run.states[0, 0, 0] = 1.0  # arrays are read-only
    run3 = plots.load_run(str(run_3d))
    assert run3.dim == 3 and run3.admm is None
    assert np.allclose(run3.delta, [0.3, 0.3, 0.2])


def test_load_run_on_empty_folder_names_the_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="trajectory.npz") as info:
        plots.load_run(tmp_path)
    assert isinstance(info.value, FileNotFoundError)
    assert "\n" not in str(info.value)
    np.savez(tmp_path / "trajectory.npz", t=np.zeros(1), states=np.zeros((1, 1, 4)))
    with pytest.raises(ValueError, match="scenario.yaml"):
        plots.load_run(tmp_path)
    with pytest.raises(FileNotFoundError, match="no such run folder"):
        plots.load_run(tmp_path / "absent")


def test_load_run_rejects_inconsistent_states(run_2d: Path, tmp_path: Path) -> None:
    folder = tmp_path / "bad"
    folder.mkdir()
    (folder / "scenario.yaml").write_text((run_2d / "scenario.yaml").read_text())
    np.savez(folder / "trajectory.npz", t=np.zeros(3), states=np.zeros((3, 3, 6)))  # 3D states, 2D scenario
    with pytest.raises(plots.RunDataError, match="states"):
        plots.load_run(folder)


# ------------------------------------------------------------------------------- figures
def test_plot_trajectories_2d(run_2d: Path, tmp_path: Path) -> None:
    run = plots.load_run(run_2d)
    fig = plots.make_trajectory_figure(run)
    assert len(fig.axes) == 1
    ax = fig.axes[0]
    obstacles = [p for p in ax.patches if p.get_gid() == plots.GID_OBSTACLE]
    assert len(obstacles) == 2
    triangle = {tuple(np.round(v, 6) + 0.0) for v in obstacles[1].get_xy()}
    assert triangle >= {(2.0, 3.0), (3.5, 3.0), (2.0, 4.5)}
    assert "cross-2d" in ax.get_title() and "collisions: 0" in ax.get_title()
    assert ax.get_aspect() == 1.0
    size = tuple(fig.get_size_inches())
    out = plots.plot_trajectories(run, tmp_path / "traj2d.png")
    assert out == tmp_path / "traj2d.png"
    _assert_png(out, _expected_px(size))


def test_plot_trajectories_3d(run_3d: Path, tmp_path: Path) -> None:
    run = plots.load_run(run_3d)
    fig = plots.make_trajectory_figure(run)
    assert len(fig.axes) >= 3
    assert fig.axes[0].name == "3d"
    assert [ax.get_xlabel() + ax.get_ylabel() for ax in fig.axes[1:3]] == ["x [m]y [m]", "x [m]z [m]"]
    assert sum(c.get_gid() == plots.GID_OBSTACLE for c in fig.axes[0].collections) == 1
    # the box obstacle projects to its x-z rectangle in the side view
    side = [p for p in fig.axes[2].patches if p.get_gid() == plots.GID_OBSTACLE]
    assert len(side) == 1
    assert np.allclose(np.sort(side[0].get_xy()[:, 1])[[0, -1]], [0.7, 2.3])
    size = tuple(fig.get_size_inches())
    out = plots.plot_trajectories(run, tmp_path / "traj3d.png")
    _assert_png(out, _expected_px(size))


def test_convergence_without_residuals_raises(run_3d: Path, tmp_path: Path) -> None:
    run = plots.load_run(run_3d)
    with pytest.raises(ValueError, match="ADMM residuals"):
        plots.plot_convergence(run, tmp_path / "conv.png")
    assert not (tmp_path / "conv.png").exists()


def test_convergence_figure(run_2d: Path, tmp_path: Path) -> None:
    run = plots.load_run(run_2d)
    assert run.admm is not None
    fig = plots.make_convergence_figure(run)
    primal_ax, dual_ax = fig.axes[0], fig.axes[1]
    assert primal_ax.get_yscale() == "log" and dual_ax.get_yscale() == "log"
    labels = [line.get_label() for line in primal_ax.get_lines() if line.get_gid() != plots.GID_TOLERANCE]
    slowest = int(np.argmax(run.admm.iterations))
    assert labels == [f"step {s} ({int(run.admm.iterations[s])} it.)" for s in sorted({0, STEPS_2D // 2, slowest})]
    assert any(line.get_gid() == plots.GID_TOLERANCE for line in primal_ax.get_lines())
    with pytest.raises(ValueError, match="steps"):
        plots.make_convergence_figure(run, steps=[STEPS_2D])
    custom = plots.make_convergence_figure(run, steps=[5])
    assert len([ln for ln in custom.axes[0].get_lines() if ln.get_gid() != plots.GID_TOLERANCE]) == 1
    size = tuple(fig.get_size_inches())
    out = plots.plot_convergence(run, tmp_path / "conv.png")
    _assert_png(out, _expected_px(size))


# ------------------------------------------------------------------------------- animation
def _gif_frames(path: Path) -> tuple[int, list[int]]:
    with Image.open(path) as image:
        assert image.format == "GIF"
        durations = []
        for n in range(image.n_frames):
            image.seek(n)
            durations.append(image.info.get("duration", 0))
        return image.n_frames, durations


def test_animate_gif_2d_subsampled(run_2d: Path, tmp_path: Path) -> None:
    run = plots.load_run(run_2d)
    out = plots.animate(run, tmp_path / "anim", max_frames=12)
    assert out == tmp_path / "anim.gif"
    frames, durations = _gif_frames(out)
    assert frames == 12
    # real time: 61 states at dt = 0.1 over 12 frames -> 6 s / 11 gaps ~ 1.83 fps -> ~545 ms/frame
    assert abs(durations[0] - 1000 * 6.0 / 11) <= 10


def test_animate_gif_3d_every_state(run_3d: Path, tmp_path: Path) -> None:
    run = plots.load_run(run_3d)
    out = plots.animate(run, tmp_path / "anim3d.gif", max_frames=500, fps=50)
    frames, durations = _gif_frames(out)
    assert frames == STEPS_3D + 1
    assert durations[0] == 20  # an explicit fps is honoured
    assert out.stat().st_size < 3_000_000


def test_mp4_animation_is_a_real_video(run_2d: Path, tmp_path: Path) -> None:
    """MP4 through the ffmpeg that the imageio-ffmpeg dependency ships: the file is an ISO
    media container with an H.264 track and the expected number of frames."""
    import subprocess

    run = plots.load_run(run_2d)
    out = plots.animate(run, tmp_path / "anim.mp4", fmt="mp4", max_frames=12, fps=10)
    head = out.read_bytes()[:64]
    assert head[4:8] == b"ftyp"
    probe = subprocess.run([plots.find_ffmpeg(), "-hide_banner", "-i", str(out), "-map", "0:v:0",
                            "-c", "copy", "-f", "null", "-"], capture_output=True, text=True)
    assert "h264" in probe.stderr
    frames = [line for line in probe.stderr.replace("\r", "\n").splitlines() if line.startswith("frame=")]
    assert frames and int(frames[-1].split("=")[1].split()[0]) == min(12, run.num_steps + 1)


def test_animate_rejects_bad_arguments(run_2d: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    run = plots.load_run(run_2d)
    # a machine without ffmpeg: matplotlib's configured one is not there, nor the imageio-ffmpeg wheel
    monkeypatch.setitem(matplotlib.rcParams, "animation.ffmpeg_path", str(tmp_path.parent / "no-ffmpeg-here"))
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    assert plots.find_ffmpeg() is None
    with pytest.raises(plots.AnimationWriterError, match="install ffmpeg.*gif"):
        plots.animate(run, tmp_path / "a.mp4", fmt="mp4")
    with pytest.raises(ValueError, match="fmt"):
        plots.animate(run, tmp_path / "a.avi", fmt="avi")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="suffix"):
        plots.animate(run, tmp_path / "a.mp4", fmt="gif")
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------------------------- entry point
def test_plot_run(run_2d: Path, run_3d: Path, tmp_path: Path) -> None:
    written = plots.plot_run(run_2d, out=tmp_path / "figs")
    assert [p.name for p in written] == ["trajectory.png", "convergence.png"]
    assert all(p.parent == tmp_path / "figs" and p.read_bytes()[:8] == PNG_MAGIC for p in written)
    written3 = plots.plot_run(run_3d)
    assert written3 == [run_3d / "trajectory.png"]
    assert written3[0].stat().st_size < MAX_BYTES


def test_importing_plots_does_not_load_pyplot() -> None:
    code = "import sys, swarmpc.plots; print('matplotlib.pyplot' in sys.modules)"
    env = {**os.environ, "PYTHONPATH": str(Path(plots.__file__).parents[1])}
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert result.stdout.strip() == "False"
