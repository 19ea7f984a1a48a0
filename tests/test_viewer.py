"""Tests of the HTML run viewer (swarmpc.viewer): the figure, the page, and the page in Chromium.

The run folders are synthetic: a scenario built with ``scenario_from_dict`` and trajectories of
the Euler double integrator s_{k+1} = [p + dt v, v + dt u] driven by a PD law towards each goal.
The browser tests (marked ``browser``) drive headless Debian Chromium through selenium with the
system chromedriver; they skip only when /usr/bin/chromium, /usr/bin/chromedriver or selenium is
missing (``scripts/install-browser.sh`` installs the first two).
"""

from __future__ import annotations

import json
import math
import os
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import plotly  # the viewer's dependency (the "view" and "test" extras): no skip without it
import plotly.io
import plotly.offline
import pytest

from conftest import load_folder, run_cli
from swarmpc import viewer
from swarmpc.config import scenario_from_dict, scenario_to_yaml

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")


# ------------------------------------------------------------------------------ run folders
def _simulate(scn, steps: int, gains: list[float], rng: np.random.Generator, accel: float = 2.0):
    """Euler double integrator under a saturated PD law; returns t, states, inputs."""
    d, dt = scn.dim, scn.dt
    start, goal = scn.start_states(), scn.goal_states()
    m = len(start)
    states = np.zeros((steps + 1, m, 2 * d))
    inputs = np.zeros((steps, m, d))
    states[0] = start
    for k in range(steps):
        p, v = states[k, :, :d], states[k, :, d:]
        kp = np.asarray(gains)[:, None]
        u = kp * (goal[:, :d] - p) - 2.0 * np.sqrt(kp) * v + 0.3 * rng.standard_normal((m, d))
        u = np.clip(u, -accel, accel)
        inputs[k] = u
        states[k + 1, :, :d] = p + dt * v
        states[k + 1, :, d:] = v + dt * u
    return dt * np.arange(steps + 1), states, inputs


def _write_run(folder: Path, spec: dict, steps: int, gains: list[float], seed: int = 0) -> Path:
    scn = scenario_from_dict(spec)
    t, states, inputs = _simulate(scn, steps, gains, np.random.default_rng(seed))
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "scenario.yaml").write_text(scenario_to_yaml(scn))
    np.savez(
        folder / "trajectory.npz",
        t=t,
        states=states,
        inputs=inputs,
        goals=scn.goal_states(),
        delta=np.asarray(scn.delta, float),
        dt=scn.dt,
    )
    d = scn.dim
    positions = states[:, :, :d]
    gaps = np.abs(positions[:, :, None, :] - positions[:, None, :, :]) / scn.delta_vector
    ratio = gaps.max(axis=3)
    iu = np.triu_indices(scn.num_agents, 1)
    summary = {
        "scenario": scn.name,
        "method": scn.solver.method,
        "collision": scn.collision,
        "num_agents": scn.num_agents,
        "dim": d,
        "delta": scn.delta,
        "steps": steps,
        "all_reached": bool(np.all(np.linalg.norm(positions[-1] - scn.goal_states()[:, :d], axis=1) < 0.05)),
        "collisions": int(np.sum(ratio[:, iu[0], iu[1]] < 1)),
        "min_separation_inf": float(_min_inf_separation(positions)[0]),
        "cost": 12.5,
    }
    (folder / "summary.json").write_text(json.dumps(summary))
    return folder


SPEC_2D = {
    "name": "cross-2d",
    "dim": 2,
    "dt": 0.1,
    "delta": 0.3,
    "workspace": {"lower": [0.0, 0.0], "upper": [6.0, 6.0]},
    "obstacles": [{"box": {"center": [3.0, 1.2], "half_size": [0.6, 0.35]}}],
    "agents": [
        {"start": [0.5, 0.5], "goal": [5.5, 5.5]},
        {"start": [5.5, 0.5], "goal": [0.5, 5.5]},
        {"start": [0.5, 3.0], "goal": [5.5, 3.4]},
    ],
    "solver": {"method": "admm"},
}

SPEC_3D = {
    "name": "swap-3d",
    "dim": 3,
    "dt": 0.1,
    "delta": [0.25, 0.25, 0.35],
    "collision": "soft",
    "workspace": {"lower": [0.0, 0.0, 0.0], "upper": [4.0, 4.0, 3.0]},
    "obstacles": [
        {
            "polytope": {  # a tetrahedron hanging off-centre
                "G": [[-1, 0, 0], [0, -1, 0], [0, 0, -1], [1, 1, 1]],
                "g": [-2.6, -0.3, -0.2, 4.5],
            }
        }
    ],
    "agents": [
        {"start": [0.5, 0.5, 0.5], "goal": [3.5, 3.5, 2.5]},
        {"start": [3.5, 3.5, 2.5], "goal": [0.5, 0.5, 0.5]},
        {"start": [0.5, 3.5, 1.5], "goal": [3.5, 0.5, 1.5]},
        {"start": [3.5, 0.5, 1.0], "goal": [0.5, 3.5, 2.0]},
    ],
    "solver": {"method": "centralized"},
}


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> dict[str, Path]:
    base = tmp_path_factory.mktemp("runs")
    return {
        "2d": _write_run(base / "run2d", SPEC_2D, steps=60, gains=[1.2, 1.0, 0.8], seed=1),
        "3d": _write_run(base / "run3d", SPEC_3D, steps=50, gains=[1.0, 1.1, 0.9, 1.3], seed=2),
        "long": _write_run(base / "long2d", SPEC_2D, steps=450, gains=[0.05, 0.06, 0.04], seed=3),
    }


@pytest.fixture(scope="module")
def pages(runs) -> dict[str, Path]:
    return {key: viewer.write_view(folder) for key, folder in runs.items() if key != "long"}


def _arrays(folder: Path) -> dict[str, np.ndarray]:
    with np.load(folder / "trajectory.npz") as data:
        return {key: np.asarray(data[key]) for key in data.files}


def _min_inf_separation(positions: np.ndarray) -> tuple[float, int]:
    """Independent brute force: min over t, i < j of ||p_i - p_j||_inf, and where."""
    best, where = math.inf, -1
    m = positions.shape[1]
    for k in range(positions.shape[0]):
        for i in range(m):
            for j in range(i + 1, m):
                gap = float(np.max(np.abs(positions[k, i] - positions[k, j])))
                if gap < best:
                    best, where = gap, k
    return best, where


def _role(fig, role: str) -> list:
    return [tr for tr in fig.data if isinstance(tr.meta, dict) and tr.meta.get("role") == role]


def _frame_traces(fig, frame) -> list[tuple[dict, object]]:
    """(meta of the figure trace it updates, frame trace) for every trace of a frame."""
    return [(fig.data[idx].meta, tr) for idx, tr in zip(frame.traces, frame.data, strict=True)]


def _annotations(fig, dim: int) -> list:
    return list(fig.layout.scene.annotations if dim == 3 else fig.layout.annotations)


# ------------------------------------------------------------------------------ page tests
@pytest.mark.parametrize("key", ["2d", "3d"])
def test_page_is_one_self_contained_file(pages, runs, key):
    page = pages[key]
    assert page == runs[key] / "view.html"
    text = page.read_text(encoding="utf-8")
    bundle = plotly.offline.get_plotlyjs()
    assert bundle[:5000] in text and bundle[-5000:] in text, "plotly.js is not embedded"
    assert not re.search(r"<script[^>]*\bsrc\s*=", text, re.I), "an external <script src=...>"
    assert '<script src="http' not in text
    assert not re.search(r"<link[^>]*href\s*=\s*[\"']https?:", text, re.I)
    assert "<title>swarmpc view" in text
    assert page.stat().st_size > 3_000_000  # the plotly.js bundle itself is ~4.5 MB
    assert list(page.parent.glob(".*.tmp")) == []  # the temporary file was renamed away
    umask = os.umask(0)
    os.umask(umask)
    assert page.stat().st_mode & 0o777 == 0o666 & ~umask  # a normal file, not tempfile's 0600


def test_write_view_custom_out(runs, tmp_path):
    out = viewer.write_view(runs["2d"], tmp_path / "sub" / "page.html")
    assert out == tmp_path / "sub" / "page.html" and out.is_file()


@pytest.mark.parametrize("key,dim,agents", [("2d", 2, 3), ("3d", 3, 4)])
def test_traces_per_agent(runs, key, dim, agents):
    fig = viewer.build_figure(runs[key])
    markers = _role(fig, "agent")
    assert [tr.name for tr in markers] == [f"agent {i}" for i in range(agents)]
    assert [tr.meta["agent"] for tr in markers] == list(range(agents))
    for role in ("box", "trail", "start", "goal", "path"):
        assert sorted(tr.meta["agent"] for tr in _role(fig, role)) == list(range(agents)), role
    kind = "scatter3d" if dim == 3 else "scatter"
    assert {tr.type for tr in markers} == {kind}
    assert len(_role(fig, "workspace")) == 1
    obstacles = _role(fig, "obstacle")
    assert len(obstacles) == 1
    if dim == 2:
        assert obstacles[0].type == "scatter" and obstacles[0].fill == "toself"
        xs, ys = np.array(obstacles[0].x), np.array(obstacles[0].y)
        assert xs.min() == pytest.approx(2.4) and xs.max() == pytest.approx(3.6)
        assert ys.min() == pytest.approx(0.85) and ys.max() == pytest.approx(1.55)
        assert {tr.marker.symbol for tr in _role(fig, "goal")} == {"star"}
    else:
        mesh = obstacles[0]
        assert mesh.type == "mesh3d" and 0 < mesh.opacity < 1
        assert len(mesh.x) == 4 and len(mesh.i) == 4  # a tetrahedron: 4 vertices, 4 faces
        edges = _role(fig, "obstacle-edges")[0]
        assert sum(v is None for v in edges.x) == 6  # 6 edges, no triangulation diagonals
        assert {tr.marker.symbol for tr in _role(fig, "goal")} == {"diamond"}
        box = _role(fig, "box")[0]
        assert sum(v is None for v in box.x) == 3  # one path through the cube's 12 edges


@pytest.mark.parametrize("key", ["2d", "3d"])
def test_frames_follow_the_trajectory(runs, key):
    fig = viewer.build_figure(runs[key])
    arrays = _arrays(runs[key])
    states, t = arrays["states"], arrays["t"]
    d = states.shape[2] // 2
    delta = np.broadcast_to(arrays["delta"], (d,))
    m = states.shape[1]
    assert len(fig.frames) == len(t)  # short runs: one frame per step
    marker_ids = [n for n, tr in enumerate(fig.data) if tr.meta and tr.meta.get("role") == "agent"]
    slider = fig.layout.sliders[0]
    assert len(slider.steps) == len(fig.frames)
    assert slider.currentvalue.suffix.strip() == "s"
    for k in (0, len(t) // 2, len(t) - 1):
        frame = fig.frames[k]
        assert frame.name == str(k)
        assert slider.steps[k].label == f"{t[k]:.2f}"
        assert list(slider.steps[k].args[0]) == [frame.name]
        assert set(marker_ids) <= set(frame.traces)
        assert len(frame.traces) == 3 * m
        for meta, tr in _frame_traces(fig, frame):
            i = meta["agent"]
            if meta["role"] == "agent":
                coords = [tr.x[0], tr.y[0]] + ([tr.z[0]] if d == 3 else [])
                np.testing.assert_allclose(coords, states[k, i, :d], atol=1e-4)
            if meta["role"] == "box":  # the body: half-size delta / 2 (the default body) around the agent
                for a, values in enumerate([tr.x, tr.y] + ([tr.z] if d == 3 else [])):
                    vals = [v for v in values if v is not None]
                    np.testing.assert_allclose(min(vals), states[k, i, a] - delta[a] / 2, atol=1e-3)
                    np.testing.assert_allclose(max(vals), states[k, i, a] + delta[a] / 2, atol=1e-3)
            if meta["role"] == "trail":
                assert len(tr.x) == k + 1
                np.testing.assert_allclose([tr.x[-1], tr.y[-1]], states[k, i, :2], atol=1e-3)
    buttons = fig.layout.updatemenus[0].buttons
    assert [b.method for b in buttons] == ["animate", "animate"]
    assert "Play" in buttons[0].label and "Pause" in buttons[1].label


def test_long_run_is_subsampled(runs):
    fig = viewer.build_figure(runs["long"])
    positions = _arrays(runs["long"])["states"][:, :, :2]
    assert positions.shape[0] == 451
    names = [int(f.name) for f in fig.frames]
    assert 150 <= len(names) <= viewer.MAX_FRAMES + 1
    assert names == sorted(set(names)) and names[0] == 0 and names[-1] == 450
    _, closest_step = _min_inf_separation(positions)
    assert closest_step in names  # the closest approach is one of the frames
    assert fig.layout.meta["frames"] == len(names)
    last = fig.frames[-1]
    for meta, tr in _frame_traces(fig, last):
        if meta["role"] == "trail":  # thinned to a bounded size, still ending at the agent
            assert 0.5 * viewer.TRAIL_POINTS <= len(tr.x) <= viewer.TRAIL_POINTS
            np.testing.assert_allclose([tr.x[-1], tr.y[-1]], positions[-1, meta["agent"]], atol=1e-3)
            np.testing.assert_allclose([tr.x[0], tr.y[0]], positions[0, meta["agent"]], atol=1e-3)


@pytest.mark.parametrize("key", ["2d", "3d", "long"])
def test_closest_approach_matches_brute_force(runs, key):
    arrays = _arrays(runs[key])
    d = arrays["states"].shape[2] // 2
    positions = arrays["states"][:, :, :d]
    expected, step = _min_inf_separation(positions)
    fig = viewer.build_figure(runs[key])
    notes = [a for a in _annotations(fig, d) if "closest approach" in a.text]
    assert len(notes) == 1
    match = re.fullmatch(r"closest approach: ([0-9.e+-]+) m \(inf-norm\), t = ([0-9.]+) s", notes[0].text)
    assert match, notes[0].text
    assert float(match.group(1)) == pytest.approx(expected, rel=1e-3)
    assert float(match.group(2)) == pytest.approx(arrays["t"][step], abs=0.006)
    marker = _role(fig, "closest")[0]
    assert marker.meta["distance"] == pytest.approx(expected, rel=1e-12)
    i, j = marker.meta["pair"]
    mid = 0.5 * (positions[step, i] + positions[step, j])
    np.testing.assert_allclose([notes[0].x, notes[0].y] + ([notes[0].z] if d == 3 else []), mid, atol=1e-9)
    if key != "long":
        page = viewer.write_view(runs[key], runs[key] / "check.html").read_text()
        assert notes[0].text in page


@pytest.mark.parametrize("key", ["2d", "3d"])
def test_hover_reports_speed_goal_and_neighbours(runs, key):
    arrays = _arrays(runs[key])
    d = arrays["states"].shape[2] // 2
    positions, velocities = arrays["states"][:, :, :d], arrays["states"][:, :, d:]
    goals = arrays["goals"][:, :d]
    fig = viewer.build_figure(runs[key])
    for k in (0, 17, len(arrays["t"]) - 1):
        markers = {tr.meta["agent"]: tr for tr in _role(fig, "agent")}
        for meta, tr in _frame_traces(fig, fig.frames[k]):
            if meta["role"] != "agent":
                continue
            i = meta["agent"]
            agent, speed, to_goal, n_inf, id_inf, n_two, id_two, _ratio, tk = tr.customdata[0]
            others = [j for j in range(positions.shape[1]) if j != i]
            infs = [np.max(np.abs(positions[k, i] - positions[k, j])) for j in others]
            twos = [np.linalg.norm(positions[k, i] - positions[k, j]) for j in others]
            assert agent == i
            assert speed == pytest.approx(np.linalg.norm(velocities[k, i]), abs=1e-4)
            assert to_goal == pytest.approx(np.linalg.norm(positions[k, i] - goals[i]), abs=1e-4)
            assert n_inf == pytest.approx(min(infs), abs=1e-4) and id_inf == others[int(np.argmin(infs))]
            assert n_two == pytest.approx(min(twos), abs=1e-4) and id_two == others[int(np.argmin(twos))]
            assert tk == pytest.approx(arrays["t"][k])
            for field in ("speed |v|", "to goal", "inf-norm", "Euclidean", "customdata[0]"):
                assert field in markers[i].hovertemplate


def test_layout_fixed_ranges_and_title(runs):
    fig2 = viewer.build_figure(runs["2d"])
    x, y = fig2.layout.xaxis, fig2.layout.yaxis
    assert x.autorange is False and y.autorange is False
    assert x.range[0] <= 0 and x.range[1] >= 6 and y.range[0] <= 0 and y.range[1] >= 6
    assert y.scaleanchor == "x" and y.scaleratio == 1
    title = fig2.layout.title.text
    summary = json.loads((runs["2d"] / "summary.json").read_text())
    assert "cross-2d" in title and "admm" in title and f"collisions: {summary['collisions']}" in title
    assert "δ" in title and "min separation" in title

    fig3 = viewer.build_figure(runs["3d"])
    scene = fig3.layout.scene
    for axis, top in ((scene.xaxis, 4), (scene.yaxis, 4), (scene.zaxis, 3)):
        assert axis.autorange is False and axis.range[0] <= 0 and axis.range[1] >= top
    assert scene.aspectmode in ("manual", "data", "cube")
    # equal scale on every axis: the aspect ratio follows the ranges
    spans = [ax.range[1] - ax.range[0] for ax in (scene.xaxis, scene.yaxis, scene.zaxis)]
    ratios = [scene.aspectratio.x, scene.aspectratio.y, scene.aspectratio.z]
    np.testing.assert_allclose(np.array(ratios) / max(ratios), np.array(spans) / max(spans), rtol=1e-9)
    assert "swap-3d" in fig3.layout.title.text and "centralized" in fig3.layout.title.text


@pytest.mark.parametrize("key", ["2d", "3d"])
def test_page_dict_needs_no_validation(runs, key):
    """write_view skips plotly's validation: its dictionary must already be in canonical form
    (e.g. no shorthand ``title="x"``, which plotly.js 3 ignores and only validation rewrites)."""
    raw = json.loads(plotly.io.to_json(viewer.figure_dict(runs[key]), validate=False))
    validated = json.loads(plotly.io.to_json(viewer.build_figure(runs[key])))
    assert raw == validated


def test_polytope_vertices():
    lower, upper = np.array([-10.0, -10.0]), np.array([10.0, 10.0])
    triangle = viewer.polytope_vertices(
        np.array([[-1.0, 0.0], [0.0, -1.0], [1.0, 1.0]]), np.array([0.0, 0.0, 1.0]), (lower, upper)
    )
    assert len(triangle) == 3
    assert {tuple(np.round(v, 9)) for v in triangle} == {(0.0, 0.0), (1.0, 0.0), (0.0, 1.0)}
    # a half-plane is clipped to the box
    half = viewer.polytope_vertices(np.array([[1.0, 0.0]]), np.array([0.0]), (lower, upper))
    assert half[:, 0].min() == pytest.approx(-10) and half[:, 0].max() == pytest.approx(0)
    # an empty polytope has no vertices
    G, g = np.array([[1.0, 0.0], [-1.0, 0.0]]), np.array([-1.0, -1.0])  # x <= -1 and x >= 1
    assert viewer.polytope_vertices(G, g, (lower, upper)).shape == (0, 2)


def test_single_agent_and_missing_scenario(tmp_path, runs):
    """A bare run folder (no scenario.yaml, no summary.json) with one agent still renders."""
    arrays = _arrays(runs["2d"])
    folder = tmp_path / "bare"
    folder.mkdir()
    np.savez(
        folder / "trajectory.npz",
        t=arrays["t"],
        states=arrays["states"][:, :1],
        inputs=arrays["inputs"][:, :1],
        goals=arrays["goals"][:1],
        delta=0.3,
        dt=0.1,
    )
    fig = viewer.build_figure(folder)
    assert [tr.name for tr in _role(fig, "agent")] == ["agent 0"]
    assert _role(fig, "closest") == [] and not fig.layout.annotations
    assert viewer.write_view(folder).is_file()


# ------------------------------------------------------------------------------ the view command
_SCRIPT_SRC = re.compile(r"<script[^>]*\bsrc\s*=", re.I)


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory) -> Path:
    """A real run folder, written by ``swarmpc run`` (15 ADMM steps of paper-2d)."""
    folder = tmp_path_factory.mktemp("cli") / "paper"
    done = run_cli("run", "paper-2d", "--max-steps", "15", "--out", str(folder), "--quiet")
    assert done.returncode == 0, done.stderr
    return folder


def _assert_page_of_run(page: Path, folder: Path) -> None:
    text = page.read_text(encoding="utf-8")
    assert not _SCRIPT_SRC.search(text), "an external <script src=...>"
    bundle = plotly.offline.get_plotlyjs()
    assert bundle[:5000] in text and bundle[-5000:] in text, "plotly.js is not embedded"
    assert "<title>swarmpc view · paper-2d</title>" in text
    summary, arrays = load_folder(folder)
    assert summary["steps"] == 15 and arrays["states"].shape[:2] == (16, 4)
    for i in range(4):
        assert f'"agent {i}"' in text
    assert '"agent 4"' not in text


def test_view_command_on_a_real_run(cli_run, tmp_path):
    out = tmp_path / "pages" / "y.html"  # a parent that does not exist yet
    done = run_cli("view", str(cli_run), "--out", str(out))
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines() == [str(out)]
    assert out.is_file() and out.stat().st_size > 3_000_000
    _assert_page_of_run(out, cli_run)
    assert not (cli_run / "view.html").exists()  # --out replaces the default, it does not add to it
    assert list(out.parent.glob(".*.tmp")) == []

    done = run_cli("view", str(cli_run))  # default: RUN_DIR/view.html
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip().splitlines() == [str(cli_run / "view.html")]
    _assert_page_of_run(cli_run / "view.html", cli_run)


@pytest.mark.parametrize("kind", ["empty folder", "missing folder", "a file", "summary only"])
def test_view_command_rejects_a_non_run_folder(kind, cli_run, tmp_path):
    target = tmp_path / "notarun"
    if kind == "empty folder":
        target.mkdir()
    elif kind == "a file":
        target = cli_run / "summary.json"
    elif kind == "summary only":  # looks like a run folder but has no trajectory
        target.mkdir()
        shutil.copy(cli_run / "summary.json", target / "summary.json")
        shutil.copy(cli_run / "scenario.yaml", target / "scenario.yaml")
    out = tmp_path / "page.html"
    done = run_cli("view", str(target), "--out", str(out))
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    assert lines[0].startswith("swarmpc: error: ") and str(target) in lines[0]
    assert "not a run folder" in lines[0]
    assert done.stdout == "" and not out.exists()


@pytest.mark.parametrize(
    "kind",
    [
        pytest.param("garbage bytes", id="garbage"),
        pytest.param("no states key", id="no-states"),
        pytest.param("truncated zip", id="truncated-zip"),
    ],
)
def test_view_command_on_a_broken_trajectory(kind, tmp_path):
    """A trajectory.npz that is there but unusable is still one line and exit status 2."""
    folder = tmp_path / "broken"
    folder.mkdir()
    traj = folder / "trajectory.npz"
    if kind == "garbage bytes":
        traj.write_bytes(b"not an npz file\n")
    elif kind == "no states key":
        np.savez(traj, t=np.arange(3.0))
    else:
        traj.write_bytes(b"PK\x03\x04" + b"\0" * 10)
    done = run_cli("view", str(folder))
    assert done.returncode == 2, done.stderr[-400:]
    assert len(done.stderr.strip().splitlines()) == 1 and "Traceback" not in done.stderr
    assert not (folder / "view.html").exists()


def _main_in_process(monkeypatch, *args: str) -> int:
    """``swarmpc ARGS`` through the console entry point, in this process."""
    from swarmpc import cli

    monkeypatch.setattr(sys, "argv", ["swarmpc", *args])
    with pytest.raises(SystemExit) as stop:
        cli.main()
    return stop.value.code


def test_view_command_open_in_process(cli_run, tmp_path, monkeypatch, capsys):
    opened: list[tuple[str, bool]] = []

    def fake_open(url, *args, **kwargs):
        opened.append((url, page.is_file()))  # the page must be complete before it is opened
        return True

    monkeypatch.setattr(viewer.webbrowser, "open", fake_open)
    page = tmp_path / "no-open.html"
    assert _main_in_process(monkeypatch, "view", str(cli_run), "--out", str(page)) == 0
    assert opened == [] and page.is_file()  # without --open no browser is started
    assert capsys.readouterr().out.strip() == str(page)

    page = tmp_path / "open.html"
    assert _main_in_process(monkeypatch, "view", str(cli_run), "--out", str(page), "--open") == 0
    assert opened == [(page.resolve().as_uri(), True)]
    captured = capsys.readouterr()
    assert captured.out.strip() == str(page) and captured.err == ""
    assert not _SCRIPT_SRC.search(page.read_text(encoding="utf-8"))

    # a bad folder with --open: exit status 2 and no browser
    assert _main_in_process(monkeypatch, "view", str(tmp_path / "nothing"), "--open") == 2
    assert len(opened) == 1
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


# ------------------------------------------------------------------------------ browser tests
def _browser_or_skip():
    missing = [str(p) for p in (CHROMIUM, CHROMEDRIVER) if not p.exists()]
    if missing:
        pytest.skip(f"browser test needs {' and '.join(missing)} (run scripts/install-browser.sh)")
    try:
        from selenium import webdriver  # noqa: F401
    except ImportError:
        pytest.skip("browser test needs selenium (pip install selenium)")


@pytest.fixture(scope="module")
def driver():
    _browser_or_skip()
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    profile = tempfile.mkdtemp(prefix="swarmpc-chromium-")
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)  # explicit paths: selenium-manager never runs
    for flag in (
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--disable-dev-shm-usage",
        "--enable-unsafe-swiftshader",  # software WebGL for the 3D (scatter3d/mesh3d) view
        "--window-size=1280,900",
        f"--user-data-dir={profile}",
    ):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    service = Service(executable_path=str(CHROMEDRIVER))
    drv = webdriver.Chrome(service=service, options=options)
    drv.set_page_load_timeout(60)
    try:
        yield drv
    finally:
        drv.quit()
        shutil.rmtree(profile, ignore_errors=True)


_STATE_JS = """
const gd = document.querySelector('.js-plotly-plot');
if (!gd || !gd._fullLayout || !gd._fullData) return null;
const agents = gd.data.filter(t => t.meta && t.meta.role === 'agent');
const full = gd._fullData.filter(t => t.meta && t.meta.role === 'agent');
const slider = gd._fullLayout.sliders && gd._fullLayout.sliders[0];
return {
  names: agents.map(t => t.name),
  count: gd.data.length,
  frames: (gd._transitionData && gd._transitionData._frames || []).length,
  active: slider ? slider.active : null,
  xs: full.map(t => Array.from(t.x)),
  ys: full.map(t => Array.from(t.y)),
  webgl: !!document.querySelector('canvas'),
  title: gd._fullLayout.title.text,
};
"""


# offset from the plot div's centre to agent 0's marker (2D), for a real mouse hover
_AGENT0_OFFSET_JS = """
const gd = document.querySelector('.js-plotly-plot');
const fl = gd._fullLayout;
const t = gd._fullData.find(t => t.meta && t.meta.role === 'agent' && t.meta.agent === 0);
const r = gd.getBoundingClientRect();
return [fl.xaxis._offset + fl.xaxis.l2p(t.x[0]) - r.width / 2,
        fl.yaxis._offset + fl.yaxis.l2p(t.y[0]) - r.height / 2];
"""


@pytest.mark.browser
@pytest.mark.parametrize("key,agents", [("2d", 3), pytest.param("3d", 4, marks=pytest.mark.loop)])
def test_page_in_chromium(driver, pages, key, agents, tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    page = pages[key]
    driver.get_log("browser")  # drop what an earlier page logged
    driver.get(page.resolve().as_uri())
    state = WebDriverWait(driver, 30).until(lambda drv: drv.execute_script(_STATE_JS))
    assert state["names"] == [f"agent {i}" for i in range(agents)]
    assert state["active"] == 0
    assert state["frames"] == len(viewer.build_figure(page.parent).frames)
    assert "closest approach" in driver.execute_script(
        "return Array.from(document.querySelectorAll('.annotation-text, .annotation'))"
        ".map(e => e.textContent).join(' ')"
    )
    time.sleep(0.5)  # let WebGL draw before the first screenshot
    before = tmp_path / f"view-{key}-start.png"
    driver.save_screenshot(str(before))

    # really click the Play button of the updatemenu
    buttons = driver.find_elements(By.CSS_SELECTOR, ".updatemenu-container .updatemenu-button")
    labels = [b.text for b in buttons]
    play = next(b for b in buttons if "Play" in b.text)
    ActionChains(driver).move_to_element(play).click().perform()
    deadline = time.time() + 10
    advanced = None
    while time.time() < deadline:
        time.sleep(0.25)
        advanced = driver.execute_script(_STATE_JS)
        if advanced["active"] and advanced["active"] >= 3:
            break
    assert advanced["active"] >= 3, f"slider did not advance after clicking Play ({labels})"
    assert advanced["xs"] != state["xs"] or advanced["ys"] != state["ys"], "markers did not move"

    pause = next(b for b in buttons if "Pause" in b.text)
    ActionChains(driver).move_to_element(pause).click().perform()
    time.sleep(1.0)  # a frame already being drawn may still land
    paused = driver.execute_script(_STATE_JS)["active"]
    time.sleep(1.0)  # playing, that would be about 10 more frames
    assert driver.execute_script(_STATE_JS)["active"] == paused, "Pause did not stop the animation"

    if key == "2d":  # a real mouse hover on agent 0 shows its card
        plot = driver.find_element(By.CSS_SELECTOR, ".js-plotly-plot")
        dx, dy = driver.execute_script(_AGENT0_OFFSET_JS)
        ActionChains(driver).move_to_element_with_offset(plot, int(dx), int(dy)).perform()
        card = WebDriverWait(driver, 5).until(
            lambda drv: drv.execute_script("return document.querySelector('.hoverlayer').textContent")
        )
        for text in ("agent 0", "speed |v|", "to goal", "inf-norm", "Euclidean"):
            assert text in card, card
    else:
        assert driver.execute_script("return !!document.querySelector('.gl-container canvas')")
    assert "WebGL is not supported" not in driver.find_element(By.TAG_NAME, "body").text
    fetched = driver.execute_script(
        "return performance.getEntriesByType('resource').map(e => e.name)"
        ".filter(n => !n.startsWith('file:') && !n.startsWith('data:') && !n.startsWith('blob:'))"
    )
    assert fetched == [], f"the page fetched from a network: {fetched}"

    shot = tmp_path / f"view-{key}.png"
    assert driver.save_screenshot(str(shot))
    assert shot.stat().st_size > 10_000 and before.stat().st_size > 10_000
    severe = [e for e in driver.get_log("browser") if e.get("level") == "SEVERE"]
    assert severe == [], severe
