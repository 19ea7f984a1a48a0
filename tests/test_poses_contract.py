"""``poses`` and ``footprints`` in every run's ``trajectory.npz``: where each agent's footprint is
in the plane and how large it is.

Real runs (2D and 3D, unequal bodies) must save poses equal to the saved positions' first two
coordinates with heading 0 and footprints equal to twice the saved body half-sizes on x and y; the
expected values are recomputed here from the other saved arrays, never from the code that wrote
them. A folder written before the arrays existed reads with the same values derived, and a
damaged pair of arrays is refused with one line naming the file. A model that knows its own pose
and footprint (a car) is asked for them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from swarmpc.config import scenario_from_dict
from swarmpc.simulation.loop import simulate
from swarmpc.simulation.results import agent_footprints, agent_poses, write_run
from swarmpc.simulation.rundata import RunDataError, load_run

PLANE = {
    "name": "poses-2d", "dim": 2, "delta": 0.3,
    "workspace": {"lower": [-3, -3], "upper": [3, 3]},
    "agents": [{"start": [-1.5, 0.4], "goal": [1.5, 0.4], "body": [0.12, 0.3]},
               {"start": [1.5, -0.4], "goal": [-1.5, -0.4]},
               {"start": [0.2, -2.0], "goal": [0.2, 2.0], "body": 0.1}],
    "solver": {"method": "centralized"},
    "stop": {"max_steps": 4},
}
SPACE = {
    "name": "poses-3d", "dim": 3, "delta": [0.3, 0.2, 0.4],
    "workspace": {"lower": [-3, -3, -3], "upper": [3, 3, 3]},
    "agents": [{"start": [-1.5, 0.3, 1.0], "goal": [1.5, 0.3, -1.0], "body": [0.1, 0.25, 0.4]},
               {"start": [1.5, -0.3, -1.0], "goal": [-1.5, -0.3, 1.0]}],
    "solver": {"method": "centralized"},
    "stop": {"max_steps": 4},
}


@pytest.fixture(scope="module", params=["2d", "3d"])
def run_folder(request, tmp_path_factory) -> Path:
    """A short real run written by ``write_run``: three agents in the plane or two in space."""
    scn = scenario_from_dict(PLANE if request.param == "2d" else SPACE)
    return write_run(simulate(scn), tmp_path_factory.mktemp("poses") / request.param)


def _saved(folder: Path) -> dict[str, np.ndarray]:
    with np.load(folder / "trajectory.npz") as data:
        return {name: data[name] for name in data.files}


def _expected(arrays: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(poses, footprints) of point agents, from the saved states and bodies alone."""
    states, bodies = arrays["states"], arrays["bodies"]
    dim = states.shape[2] // 2
    poses = np.concatenate([states[:, :, :2], np.zeros((*states.shape[:2], 1))], axis=2)
    assert dim in (2, 3) and bodies.shape == (states.shape[1], dim)
    return poses, 2.0 * bodies[:, :2]


def test_a_run_saves_the_point_agents_poses_and_footprints(run_folder):
    arrays = _saved(run_folder)
    poses, footprints = _expected(arrays)
    steps, agents = arrays["states"].shape[:2]
    assert steps > 1
    assert arrays["poses"].shape == (steps, agents, 3) and arrays["poses"].dtype == np.float64
    assert arrays["footprints"].shape == (agents, 2) and arrays["footprints"].dtype == np.float64
    assert np.array_equal(arrays["poses"], poses)
    assert np.array_equal(arrays["footprints"], footprints)
    assert not np.allclose(footprints[:, 0], footprints[0, 0])  # unequal bodies: each agent its own


def test_the_footprints_follow_the_scenarios_bodies(run_folder):
    arrays = _saved(run_folder)
    if arrays["states"].shape[2] == 4:
        expected = [[0.24, 0.6], [0.3, 0.3], [0.2, 0.2]]  # bodies [0.12, 0.3], Δ/2 = 0.15 and 0.1
    else:
        expected = [[0.2, 0.5], [0.3, 0.2]]  # bodies [0.1, 0.25, 0.4] and Δ/2 = [0.15, 0.1, 0.2]
    np.testing.assert_allclose(arrays["footprints"], expected, rtol=0, atol=1e-15)


def test_the_reader_returns_the_saved_arrays(run_folder):
    arrays, run = _saved(run_folder), load_run(run_folder)
    assert np.array_equal(run.poses, arrays["poses"])
    assert np.array_equal(run.footprints, arrays["footprints"])
    assert not run.poses.flags.writeable and not run.footprints.flags.writeable


def _rewrite(folder: Path, arrays: dict[str, np.ndarray], scenario_from: Path | None) -> Path:
    folder.mkdir()
    np.savez_compressed(folder / "trajectory.npz", **arrays)
    if scenario_from is not None:
        (folder / "scenario.yaml").write_text((scenario_from / "scenario.yaml").read_text())
    return folder


def test_an_old_folder_reads_with_derived_poses_and_footprints(run_folder, tmp_path):
    """A folder written before the arrays existed (every agent then a point agent) reads with the
    values a new run would have saved."""
    arrays = _saved(run_folder)
    poses, footprints = _expected(arrays)
    old = {name: array for name, array in arrays.items() if name not in ("poses", "footprints")}
    run = load_run(_rewrite(tmp_path / "old", old, run_folder))
    assert np.array_equal(run.poses, poses)
    assert np.array_equal(run.footprints, footprints)


def test_an_older_folder_without_bodies_or_scenario_takes_delta(run_folder, tmp_path):
    """Before bodies existed every body was Δ/2 per axis, so the footprint is Δ on x and y."""
    arrays = _saved(run_folder)
    old = {name: array for name, array in arrays.items() if name not in ("poses", "footprints", "bodies")}
    run = load_run(_rewrite(tmp_path / "older", old, None), require_scenario=False)
    delta = np.broadcast_to(arrays["delta"], (arrays["states"].shape[2] // 2,))
    assert np.array_equal(run.footprints, np.tile(delta[:2], (arrays["states"].shape[1], 1)))
    assert np.array_equal(run.poses, _expected(arrays)[0])


@pytest.mark.parametrize(
    ("name", "damage", "words"),
    [
        ("poses", lambda a: a[:, :, :2], "'poses' must have shape"),
        ("poses", lambda a: a[:-1], "'poses' must have shape"),
        ("poses", lambda a: np.where(np.arange(a.size).reshape(a.shape) == 5, np.nan, a), "'poses' holds NaN"),
        ("footprints", lambda a: a[:-1], "'footprints' must have shape"),
        ("footprints", lambda a: np.hstack([a, a]), "'footprints' must have shape"),
        ("footprints", lambda a: -a, "'footprints' must be finite and > 0"),
        ("footprints", lambda a: np.full_like(a, np.inf), "'footprints' must be finite and > 0"),
    ],
)
def test_damaged_arrays_are_refused_in_one_line(run_folder, tmp_path, name, damage, words):
    arrays = _saved(run_folder)
    arrays[name] = damage(arrays[name])
    folder = _rewrite(tmp_path / "damaged", arrays, run_folder)
    with pytest.raises(RunDataError, match=words) as caught:
        load_run(folder)
    message = str(caught.value)
    assert "\n" not in message and str(folder / "trajectory.npz") in message


# ------------------------------------------------------------------------------ models with a pose
class _Point:
    """A point agent's model as far as the poses need it: state [p, v] in the plane."""

    def position(self, states: np.ndarray) -> np.ndarray:
        return states[..., :2]


class _Cart(_Point):
    """A model that knows its footprint: centre 0.5 ahead of its reference point along a heading
    kept in the state's third entry (not a real car; the writer only asks it)."""

    footprint = (1.2, 0.6)

    def pose(self, states: np.ndarray) -> np.ndarray:
        theta = states[..., 2]
        return np.stack([states[..., 0] + 0.5 * np.cos(theta), states[..., 1] + 0.5 * np.sin(theta), theta], -1)


def test_a_model_with_a_pose_and_footprint_gives_its_own():
    rng = np.random.default_rng(0)
    states = rng.normal(size=(6, 3, 4))
    bodies = np.array([[0.1, 0.2], [0.3, 0.4], [0.5, 0.6]])
    models = (_Point(), _Cart(), _Point())
    poses = agent_poses(models, states)  # type: ignore[arg-type]
    assert poses.shape == (6, 3, 3)
    np.testing.assert_array_equal(poses[:, 0], np.column_stack([states[:, 0, :2], np.zeros(6)]))
    np.testing.assert_allclose(poses[:, 1, 0], states[:, 1, 0] + 0.5 * np.cos(states[:, 1, 2]))
    np.testing.assert_allclose(poses[:, 1, 1], states[:, 1, 1] + 0.5 * np.sin(states[:, 1, 2]))
    np.testing.assert_array_equal(poses[:, 1, 2], states[:, 1, 2])
    np.testing.assert_array_equal(poses[:, 2, 2], 0.0)
    footprints = agent_footprints(models, bodies)  # type: ignore[arg-type]
    np.testing.assert_array_equal(footprints, [[0.2, 0.4], [1.2, 0.6], [1.0, 1.2]])


def test_one_model_serves_every_agent_and_a_wrong_count_is_refused():
    states = np.arange(2 * 3 * 4, dtype=float).reshape(2, 3, 4)
    np.testing.assert_array_equal(agent_poses(_Cart(), states)[..., 2], states[..., 2])  # type: ignore[arg-type]
    np.testing.assert_array_equal(agent_footprints(_Cart(), np.ones((3, 2))), np.tile([1.2, 0.6], (3, 1)))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="expected 3 agent models, got 2"):
        agent_poses((_Point(), _Point()), states)  # type: ignore[arg-type]
