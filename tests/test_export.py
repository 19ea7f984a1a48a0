"""``swarmpc export``: real run folders exported as CSV and MCAP and read back independently.

Two real runs are written once: 5 ADMM steps of ``paper-2d`` and 3 of ``paper-3d``, each with a
box and a polytope obstacle added out of the agents' way (so the scene has both kinds). The CSV
is parsed with :mod:`csv` and compared with ``trajectory.npz`` as ``numpy`` loads it; the MCAP is
read with the ``mcap`` reader and every protobuf message is decoded from the schema embedded in
the file (as Foxglove does), never from swarmpc's own classes. Also: the command line, refusals,
damaged input (one line, exit 2), atomic writing, and ``swarmpc --version``.
"""

from __future__ import annotations

import csv
import json
import shutil
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader

from conftest import run_cli
from swarmpc import export
from swarmpc.export import (
    MCAP_TOPICS,
    METRICS,
    csv_header,
    export_run,
    metrics_json_schema,
)
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.loop import StopFlag, simulate
from swarmpc.simulation.outdir import OutputError
from swarmpc.simulation.results import write_run
from swarmpc.simulation.rundata import RunDataError

OBSTACLES = {
    2: [
        {"box": {"center": [0.0, 2.5], "half_size": [0.3, 0.2]}},
        {"polytope": {"G": [[-1, 0], [0, -1], [1, 1]], "g": [-2.3, 0.3, 2.9]}},
    ],
    3: [
        {"box": {"center": [0.0, 2.6, 1.5], "half_size": [0.3, 0.2, 0.3]}},
        {"polytope": {"G": [[-1, 0, 0], [0, -1, 0], [0, 0, -1], [1, 1, 1]], "g": [-2.3, 0.3, -1.2, 4.2]}},
    ],
}
RUNS = {"2d": ("paper-2d", 5, 2), "3d": ("paper-3d", 3, 3)}


@pytest.fixture(scope="module", params=sorted(RUNS))
def run_dir(request, tmp_path_factory) -> Path:
    """A real run folder (see the module's docstring)."""
    name, steps, dim = RUNS[request.param]
    scn = builtin_scenario(name).with_updates(**{"stop.max_steps": steps, "obstacles": OBSTACLES[dim]})
    return write_run(simulate(scn), tmp_path_factory.mktemp("export") / request.param)


def _arrays(folder: Path, name: str) -> dict[str, np.ndarray]:
    with np.load(folder / name) as data:
        return {key: data[key] for key in data.files}


def _nearest(positions: np.ndarray) -> np.ndarray:
    """(M,) Euclidean distance to the nearest other agent, by brute force."""
    m = len(positions)
    return np.array([min((np.linalg.norm(positions[i] - positions[j]) for j in range(m) if j != i),
                         default=np.inf) for i in range(m)])


# ------------------------------------------------------------------------------------ CSV
def test_csv_reads_back_as_the_run_arrays(run_dir, tmp_path):
    target = export_run(run_dir, "csv", out=tmp_path / "out.csv")
    trajectory = _arrays(run_dir, "trajectory.npz")
    states, inputs, t = trajectory["states"], trajectory["inputs"], trajectory["t"]
    steps, m, dim = inputs.shape
    with target.open(newline="") as stream:
        rows = list(csv.reader(stream))
    axes = "xyz"[:dim]
    assert rows[0] == ["step", "t", "agent", *axes, *(f"v{a}" for a in axes), *(f"u{a}" for a in axes), "nearest_m"]
    assert rows[0] == csv_header(dim)
    body = rows[1:]
    assert len(body) == (steps + 1) * m
    for row, (k, i) in zip(body, [(k, i) for k in range(steps + 1) for i in range(m)], strict=True):
        assert (int(row[0]), int(row[2])) == (k, i)
        assert float(row[1]) == t[k]
        assert [float(v) for v in row[3 : 3 + 2 * dim]] == states[k, i].tolist()  # exact: full precision
        written_inputs = row[3 + 2 * dim : 3 + 3 * dim]
        if k < steps:
            assert [float(v) for v in written_inputs] == inputs[k, i].tolist()
        else:
            assert written_inputs == [""] * dim  # no input follows the last state
        assert float(row[-1]) == pytest.approx(_nearest(states[k, :, :dim])[i], rel=1e-12)


def test_csv_of_one_agent_leaves_nearest_empty(tmp_path):
    scn = builtin_scenario("paper-2d").with_updates(**{"stop.max_steps": 2})
    scn = scn.with_updates(agents=[scn.agents[0].model_dump()])
    folder = write_run(simulate(scn), tmp_path / "one")
    with export_run(folder, "csv").open(newline="") as stream:
        rows = list(csv.DictReader(stream))
    assert len(rows) == 3 and all(row["nearest_m"] == "" for row in rows)


def test_a_run_stopped_before_its_first_step_exports(tmp_path):
    stop = StopFlag()
    stop.requested = True
    folder = write_run(simulate(builtin_scenario("paper-2d"), stop_flag=stop), tmp_path / "zero")
    with export_run(folder, "csv").open(newline="") as stream:
        rows = list(csv.DictReader(stream))
    assert len(rows) == 4 and all(row["ux"] == "" for row in rows)
    messages = _read_mcap(export_run(folder, "mcap"))
    assert {topic: len(found) for topic, found in messages.items()} == dict.fromkeys(
        ["/world", "/paths", "/agents", "/trails", "/metrics"], 1)
    assert "step_time_ms" not in messages["/metrics"][0][1]


# ------------------------------------------------------------------------------------ MCAP
def _decoders(schemas: dict) -> dict[int, object]:
    """Per schema id: a function bytes -> decoded message, from the schema stored in the file."""
    decoders = {}
    for schema_id, schema in schemas.items():
        if schema.encoding == "protobuf":
            files = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
            pool = descriptor_pool.DescriptorPool()
            for file in files.file:  # dependencies first, as a generic reader adds them
                pool.Add(file)
            cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
            decoders[schema_id] = cls.FromString
        else:
            assert schema.encoding == "jsonschema"
            decoders[schema_id] = json.loads
    return decoders


def _read_mcap(path: Path) -> dict[str, list[tuple[int, object]]]:
    """Topic -> [(log time, decoded message)] in log-time order."""
    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        decoders = _decoders(summary.schemas)
        messages: dict[str, list[tuple[int, object]]] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            assert message.publish_time == message.log_time
            messages.setdefault(channel.topic, []).append((message.log_time, decoders[schema.id](message.data)))
    return messages


@pytest.fixture(scope="module")
def mcap_of(run_dir, tmp_path_factory):
    """The run's MCAP export, read back: (topic -> messages, the file)."""
    target = export_run(run_dir, "mcap", out=tmp_path_factory.mktemp("mcap") / "run.mcap")
    return _read_mcap(target), target


def test_mcap_has_the_documented_topics_and_counts(run_dir, mcap_of):
    messages, _ = mcap_of
    steps = _arrays(run_dir, "trajectory.npz")["inputs"].shape[0]
    expected = {doc.topic: steps + 1 if doc.per_state else 1 for doc in MCAP_TOPICS}
    assert {topic: len(found) for topic, found in messages.items()} == expected
    assert set(expected) == {"/world", "/paths", "/agents", "/trails", "/metrics"}


def test_mcap_file_declares_foxglove_schemas(mcap_of):
    _, path = mcap_of
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    schemas = {channel.topic: summary.schemas[channel.schema_id] for channel in summary.channels.values()}
    encodings = {channel.topic: channel.message_encoding for channel in summary.channels.values()}
    for topic in ("/world", "/paths", "/agents", "/trails"):
        assert (schemas[topic].name, schemas[topic].encoding, encodings[topic]) == (
            "foxglove.SceneUpdate", "protobuf", "protobuf")
    assert (schemas["/metrics"].encoding, encodings["/metrics"]) == ("jsonschema", "json")
    assert json.loads(schemas["/metrics"].data) == metrics_json_schema()


def test_mcap_agents_sit_at_the_trajectory_states(run_dir, mcap_of):
    messages, _ = mcap_of
    trajectory = _arrays(run_dir, "trajectory.npz")
    states, t = trajectory["states"], trajectory["t"]
    m, dim = states.shape[1], states.shape[2] // 2
    # the default body: half-size Δ/2 per axis, so a cube's edge is Δ (a run may record its own)
    bodies = trajectory.get("bodies", np.tile(np.broadcast_to(trajectory["delta"], (dim,)) / 2, (m, 1)))
    agents = messages["/agents"]
    for k, (log_time, update) in enumerate(agents):
        assert log_time == round(t[k] * 1e9)
        assert [entity.id for entity in update.entities] == [f"agent/{i}" for i in range(m)]
        for i, entity in enumerate(update.entities):
            assert entity.frame_id == "world"
            assert entity.timestamp.seconds * 10**9 + entity.timestamp.nanos == log_time
            (cube,) = entity.cubes
            position = [cube.pose.position.x, cube.pose.position.y, cube.pose.position.z]
            np.testing.assert_allclose(position[:dim], states[k, i, :dim], rtol=0, atol=1e-12)
            if dim == 2:
                assert position[2] == 0.0
            size = [cube.size.x, cube.size.y, cube.size.z][:dim]
            np.testing.assert_allclose(size, 2 * bodies[i])
            assert cube.pose.orientation.w == 1.0
            assert entity.texts[0].text == str(i)
            assert "Δ/2" in {kv.key: kv.value for kv in entity.metadata}["body"]


def test_mcap_trails_paths_and_world(run_dir, mcap_of):
    messages, _ = mcap_of
    positions = _arrays(run_dir, "trajectory.npz")["states"]
    m, dim = positions.shape[1], positions.shape[2] // 2
    positions = positions[:, :, :dim]

    def points(line):
        return np.array([[p.x, p.y, p.z][:dim] for p in line.points])

    (_, paths), = messages["/paths"]
    for i, entity in enumerate(paths.entities):
        np.testing.assert_allclose(points(entity.lines[0]), positions[:, i], atol=1e-12)
    trail_steps = round(export.TRAIL_SECONDS / float(_arrays(run_dir, "trajectory.npz")["dt"]))
    for k, (_, update) in enumerate(messages["/trails"]):
        first = max(0, k - trail_steps)
        for i, entity in enumerate(update.entities):
            assert entity.id == f"trail/{i}"
            np.testing.assert_allclose(points(entity.lines[0]), positions[first : k + 1, i], atol=1e-12)
    (log_time, world), = messages["/world"]
    assert log_time == 0
    by_id = {entity.id: entity for entity in world.entities}
    assert set(by_id) == {"obstacle/0", "obstacle/1", "workspace", *(f"goal/{i}" for i in range(m))}
    box = OBSTACLES[dim][0]["box"]
    (cube,) = by_id["obstacle/0"].cubes
    np.testing.assert_allclose([cube.pose.position.x, cube.pose.position.y, cube.pose.position.z][:dim], box["center"])
    np.testing.assert_allclose([cube.size.x, cube.size.y, cube.size.z][:dim], 2 * np.array(box["half_size"]))
    (mesh,) = by_id["obstacle/1"].triangles
    corners = np.array([[p.x, p.y, p.z][:dim] for p in mesh.points])
    assert len(corners) >= 3 and len(corners) % 3 == 0
    polytope = OBSTACLES[dim][1]["polytope"]
    slack = np.asarray(polytope["g"]) - corners @ np.asarray(polytope["G"], float).T
    assert slack.min() >= -1e-7  # every triangle corner lies on the polytope


def test_mcap_metrics_are_the_run_records(run_dir, mcap_of):
    messages, _ = mcap_of
    trajectory = _arrays(run_dir, "trajectory.npz")
    step_times = _arrays(run_dir, "steps.npz")["step_time_s"]
    iterations = _arrays(run_dir, "admm.npz")["iterations"]
    states = trajectory["states"]
    steps, dim = len(step_times), states.shape[2] // 2
    names = {metric.name for metric in METRICS}
    for k, (log_time, record) in enumerate(messages["/metrics"]):
        assert set(record) <= names and set(metrics_json_schema()["required"]) <= set(record)
        assert (record["step"], record["t_s"], log_time) == (k, trajectory["t"][k], round(trajectory["t"][k] * 1e9))
        assert record["min_distance_m"] == pytest.approx(_nearest(states[k, :, :dim]).min(), rel=1e-12)
        gaps = np.abs(states[k, :, None, :dim] - states[k, None, :, :dim]).max(axis=-1)
        assert record["min_separation_inf_m"] == pytest.approx(gaps[~np.eye(len(gaps), dtype=bool)].min())
        if k < steps:
            assert record["step_time_ms"] == pytest.approx(1000 * step_times[k])
            assert record["admm_iterations"] == iterations[k]
        else:
            assert "step_time_ms" not in record and "admm_iterations" not in record


# ------------------------------------------------------------------------------------ files and CLI
def test_cli_exports_both_formats_and_refuses_an_existing_out(run_dir, tmp_path):
    folder = Path(shutil.copytree(run_dir, tmp_path / "run"))
    for fmt in ("csv", "mcap"):
        done = run_cli("export", str(folder), "--format", fmt)
        assert done.returncode == 0, done.stderr
        assert done.stdout.strip() == str(folder / f"run.{fmt}")
        assert (folder / f"run.{fmt}").stat().st_size > 0
    taken = tmp_path / "taken.csv"
    taken.write_text("mine\n")
    done = run_cli("export", str(folder), "--format", "csv", "--out", str(taken))
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "--overwrite" in done.stderr
    assert taken.read_text() == "mine\n"
    done = run_cli("export", str(folder), "--format", "csv", "--out", str(taken), "--overwrite")
    assert done.returncode == 0, done.stderr
    assert taken.read_text() == (folder / "run.csv").read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run", "taken.csv"]  # no temporary left


@pytest.mark.parametrize("args", [("--format", "xml"), ()], ids=["unknown-format", "no-format"])
def test_cli_rejects_a_bad_format(run_dir, args):
    done = run_cli("export", str(run_dir), *args)
    assert done.returncode == 2
    assert done.stderr.startswith("swarmpc: error:") and done.stderr.count("\n") == 1


def _damage(folder: Path) -> None:
    (folder / "trajectory.npz").write_bytes(b"PK\x03\x04 not really a zip")


@pytest.mark.parametrize("fmt", ["csv", "mcap"])
def test_damaged_run_folder_is_one_line_exit_2(run_dir, tmp_path, fmt):
    folder = Path(shutil.copytree(run_dir, tmp_path / "damaged"))
    _damage(folder)
    before = sorted(p.name for p in folder.iterdir())
    done = run_cli("export", str(folder), "--format", fmt)
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith("swarmpc: error:") and done.stderr.count("\n") == 1
    assert "trajectory.npz" in done.stderr and "Traceback" not in done.stderr
    assert sorted(p.name for p in folder.iterdir()) == before  # nothing written
    with pytest.raises(RunDataError, match="trajectory.npz"):
        export_run(folder, fmt)
    done = run_cli("export", str(tmp_path / "missing"), "--format", fmt)
    assert done.returncode == 2 and done.stderr.count("\n") == 1


def _rewrite(folder: Path, name: str, **changes: np.ndarray) -> None:
    arrays = _arrays(folder, name)
    arrays.update(changes)
    np.savez(folder / name, **arrays)


def test_mcap_refuses_time_that_runs_backwards(run_dir, tmp_path):
    folder = Path(shutil.copytree(run_dir, tmp_path / "run"))
    _rewrite(folder, "trajectory.npz", t=_arrays(folder, "trajectory.npz")["t"][::-1].copy())
    with pytest.raises(RunDataError, match=r"trajectory\.npz: 't' must be non-negative, non-decreasing"):
        export_run(folder, "mcap")
    done = run_cli("export", str(folder), "--format", "mcap")
    assert done.returncode == 2 and done.stderr.count("\n") == 1
    assert not (folder / "run.mcap").exists()
    assert export_run(folder, "csv").exists()  # the CSV just copies t


def test_mcap_metrics_leave_out_what_a_damaged_steps_file_lacks(run_dir, tmp_path):
    folder = Path(shutil.copytree(run_dir, tmp_path / "run"))
    failures = _arrays(folder, "steps.npz")["failures"].astype(float)
    failures[0] = np.nan
    _rewrite(folder, "steps.npz", failures=failures)
    metrics = [record for _, record in _read_mcap(export_run(folder, "mcap"))["/metrics"]]
    assert "solver_failures" not in metrics[0] and metrics[1]["solver_failures"] == 0
    assert isinstance(metrics[1]["solver_failures"], int)


def test_a_failed_export_leaves_the_old_file_and_no_temporary(run_dir, tmp_path):
    """The file system refuses the export half-way, as a full disk or a quota would: a file-size
    limit (RLIMIT_FSIZE) below the CSV's size, in a fresh interpreter, with SIGXFSZ ignored so
    that the write fails (EFBIG) instead of killing the process."""
    pytest.importorskip("resource")
    target = tmp_path / "out.csv"
    target.write_text("old\n")
    script = (
        "import resource, signal\n"
        "from swarmpc.export import export_run\n"
        "from swarmpc.simulation.outdir import OutputError\n"
        "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
        "resource.setrlimit(resource.RLIMIT_FSIZE, (1024, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))\n"
        "try:\n"
        f"    export_run({str(run_dir)!r}, 'csv', out={str(target)!r}, overwrite=True)\n"
        "except OutputError as err:\n"
        "    print(err)\n"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert done.stdout == f"{target}: cannot write (File too large)\n", done.stderr[-2000:]
    assert target.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["out.csv"]


def test_the_python_api_refuses_like_the_cli(run_dir, tmp_path):
    taken = tmp_path / "x.mcap"
    taken.write_bytes(b"")
    with pytest.raises(OutputError, match="--overwrite"):
        export_run(run_dir, "mcap", out=taken)
    with pytest.raises(OutputError, match="not a regular file"):
        export_run(run_dir, "mcap", out=tmp_path)
    with pytest.raises(ValueError, match="csv or mcap"):
        export_run(run_dir, "xml")


# ------------------------------------------------------------------------------------ version
def test_version_is_the_installed_packages():
    import swarmpc

    assert swarmpc.__version__ == version("swarmpc")
    done = subprocess.run([sys.executable, "-m", "swarmpc", "--version"], capture_output=True, text=True, check=False)
    assert (done.returncode, done.stdout, done.stderr) == (0, f"swarmpc {version('swarmpc')}\n", "")
