"""The one reader of a run folder: :func:`load_run` turns a folder into a :class:`RunData`.

A run folder (``trajectory.npz``, ``scenario.yaml``, ``summary.json``, ``steps.npz``,
``admm.npz``; see :mod:`swarmpc.simulation.results`) is read back by the figures, the animation,
the HTML viewer and the experiments. The folder may have been copied, truncated, edited by hand or
come from someone else, so it is read as untrusted input: every way it can be damaged (a missing
or misplaced file, a corrupt or truncated archive, an ``.npy`` header that claims a huge array,
object arrays, wrong or inconsistent shapes, NaN, malformed JSON or YAML, an invalid scenario)
ends in a :class:`RunDataError` whose message is one line naming the file, never a traceback and
never an unbounded allocation. Nothing is unpickled.
"""

from __future__ import annotations

import json
import math
import stat
import zipfile
import zlib
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import IO, Any

import numpy as np

from swarmpc.config import Scenario, ScenarioError, parse_yaml_text, scenario_from_dict

__all__ = [
    "ADMM_FILE",
    "MAX_ARCHIVE_BYTES",
    "SCENARIO_FILE",
    "STEPS_FILE",
    "SUMMARY_FILE",
    "TRAJECTORY_FILE",
    "AdmmResiduals",
    "MissingRunFileError",
    "RunData",
    "RunDataError",
    "load_run",
    "point_footprints",
    "point_poses",
    "read_npz",
    "read_summary",
]

TRAJECTORY_FILE = "trajectory.npz"
SCENARIO_FILE = "scenario.yaml"
SUMMARY_FILE = "summary.json"
STEPS_FILE = "steps.npz"
ADMM_FILE = "admm.npz"

MAX_ARCHIVE_BYTES = 1 << 30
"""Most array data one ``.npz`` file of a run may hold once loaded (1 GiB): a header that claims
more is refused before anything is allocated. A run of 1000 agents over 10 000 steps in 3D needs
about 0.5 GiB of states."""
MAX_TEXT_BYTES = 64 << 20
"""Largest ``summary.json`` or ``scenario.yaml`` that is read (64 MiB)."""
_MAX_MEMBERS = 256
_MAX_HEADER_BYTES = 10_000
_NUMERIC_KINDS = "biuf"  # bool, signed and unsigned integers, floats

_TRAJECTORY_KEYS = ("t", "states", "inputs", "goals", "delta", "dt", "disturbances", "bodies", "poses", "footprints")
_STEP_KEYS: Mapping[str, bool] = MappingProxyType({  # name -> True when it has one column per agent
    "step_time_s": False, "agent_time_s": True, "failures": False, "fallback": True,
    "max_slack": False, "repaired": False, "critical_path_s": False, "deadline_stop": False,
    "local_fallbacks": False,
})  # fmt: skip
_ADMM_KEYS = ("primal", "dual", "rho", "iterations", "copies", "planes")


class RunDataError(ValueError):
    """A run folder that cannot be read; the message is one line naming the file."""

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(str(message).split()))


class MissingRunFileError(RunDataError, FileNotFoundError):
    """A run folder, or a file it needs (``trajectory.npz``, ``scenario.yaml``), does not exist."""


# ------------------------------------------------------------------------------------ the data
@dataclass(frozen=True, eq=False)
class AdmmResiduals:
    """ADMM records of a run (``admm.npz``).

    Attributes
    ----------
    primal, dual : np.ndarray
        (T, max_iter) residual per MPC step and ADMM iteration, NaN after convergence.
    iterations : np.ndarray
        (T,) number of ADMM iterations of each MPC step.
    rho : np.ndarray or None
        (T, max_iter) penalty per iteration, when recorded.
    copies, planes : np.ndarray or None
        (T, M) neighbours' copies held and separating planes kept per agent, when recorded.
    """

    primal: np.ndarray
    dual: np.ndarray
    iterations: np.ndarray
    rho: np.ndarray | None = None
    copies: np.ndarray | None = None
    planes: np.ndarray | None = None


@dataclass(frozen=True, eq=False)
class RunData:
    """Everything a run folder holds, as read-only arrays.

    Attributes
    ----------
    run_dir : Path
        The folder the run was loaded from.
    t : np.ndarray
        (T+1,) time stamps [s].
    states : np.ndarray
        (T+1, M, 2d) states [position, velocity]; T = 0 for a run stopped before its first step.
    inputs : np.ndarray
        (T, M, d) accelerations (NaN when the trajectory did not record them).
    goals : np.ndarray
        (M, 2d) goal states.
    delta : np.ndarray
        (d,) Δ per axis (> 0): the separation of two default bodies' centres.
    dt : float
        Sampling time [s] (> 0).
    scenario : Scenario or None
        The fully resolved scenario of the run; None only when loaded with
        ``require_scenario=False`` from a folder without ``scenario.yaml``.
    summary : dict
        ``summary.json`` (empty when the file is absent).
    poses : np.ndarray
        (T+1, M, 3) pose [x, y, theta] of each agent's footprint centre in the plane:
        ``trajectory.npz``'s ``poses``, else (a folder written before they existed, when every
        agent was a point agent) :func:`point_poses` of the positions.
    footprints : np.ndarray
        (M, 2) footprint [length, width] of each agent in the plane (> 0): ``trajectory.npz``'s
        ``footprints``, else :func:`point_footprints` of :attr:`bodies`.
    admm : AdmmResiduals or None
        Records from ``admm.npz``; None when the run has none.
    disturbances : np.ndarray or None
        (T, M, 2d) additive disturbances when the run recorded them.
    steps : Mapping[str, np.ndarray]
        Per-step solver records of ``steps.npz`` (``step_time_s``, ``agent_time_s``,
        ``failures``, ``fallback``, ``max_slack``, ``repaired``, ``critical_path_s``,
        ``deadline_stop``, ``local_fallbacks``; older runs may lack the last three), each with T
        rows; empty when the file is absent.
    bodies : np.ndarray or None
        (M, d) half-size of each agent's body per axis (> 0): ``trajectory.npz``'s ``bodies``,
        else the scenario's, else delta / 2 (the default body). Two agents collide when their
        bodies overlap; see :attr:`body_half_sizes`.
    """

    run_dir: Path
    t: np.ndarray
    states: np.ndarray
    inputs: np.ndarray
    goals: np.ndarray
    delta: np.ndarray
    dt: float
    scenario: Scenario | None
    summary: dict[str, Any]
    poses: np.ndarray
    footprints: np.ndarray
    admm: AdmmResiduals | None = None
    disturbances: np.ndarray | None = None
    steps: Mapping[str, np.ndarray] = field(default_factory=lambda: MappingProxyType({}))
    bodies: np.ndarray | None = None

    @property
    def body_half_sizes(self) -> np.ndarray:
        """(M, d) half-size of each agent's body: :attr:`bodies`, or delta / 2 when not given."""
        if self.bodies is not None:
            return self.bodies
        return np.tile(self.delta / 2.0, (self.num_agents, 1))

    @property
    def dim(self) -> int:
        """Spatial dimension d (2 or 3)."""
        return int(self.states.shape[2]) // 2

    @property
    def num_agents(self) -> int:
        """Number of agents M."""
        return int(self.states.shape[1])

    @property
    def num_steps(self) -> int:
        """Number of closed-loop steps T (the run has T+1 states)."""
        return int(self.states.shape[0]) - 1

    @property
    def positions(self) -> np.ndarray:
        """(T+1, M, d) positions."""
        return self.states[:, :, : self.dim]

    @property
    def velocities(self) -> np.ndarray:
        """(T+1, M, d) velocities."""
        return self.states[:, :, self.dim :]

    @property
    def goal_positions(self) -> np.ndarray:
        """(M, d) goal positions."""
        return self.goals[:, : self.dim]

    @property
    def name(self) -> str:
        """Scenario name: the summary's, else the scenario's, else the folder's."""
        named = self.summary.get("scenario")
        if isinstance(named, str) and named:
            return named
        return self.scenario.name if self.scenario is not None else self.run_dir.name


def point_poses(positions: np.ndarray) -> np.ndarray:
    """(..., 3) poses [x, y, 0] of point agents at ``positions`` (..., d): a point agent's
    footprint is centred on its position and never turns (in 3D, its shadow on the x-y plane)."""
    positions = np.asarray(positions, float)
    poses = np.zeros((*positions.shape[:-1], 3))
    poses[..., :2] = positions[..., :2]
    return poses


def point_footprints(bodies: np.ndarray) -> np.ndarray:
    """(M, 2) footprints [length, width] of point agents with body half-sizes ``bodies`` (M, d):
    the box each body keeps clear on the x and y axes, twice its half-sizes there."""
    return 2.0 * np.asarray(bodies, float)[:, :2]


# ------------------------------------------------------------------------------------ reading
def load_run(run_dir: str | Path, *, require_scenario: bool = True) -> RunData:
    """Read and check a run folder.

    Parameters
    ----------
    run_dir : str or PathLike
        Folder with ``trajectory.npz`` and ``scenario.yaml`` (required), ``summary.json``,
        ``steps.npz`` and ``admm.npz`` (optional).
    require_scenario : bool
        False lets a folder without ``scenario.yaml`` load (``RunData.scenario`` is then None and
        ``trajectory.npz`` must hold ``dt``, ``goals`` and ``delta`` itself).

    Returns
    -------
    RunData

    Raises
    ------
    MissingRunFileError
        The folder or a required file does not exist (a ``ValueError`` and a ``FileNotFoundError``).
    RunDataError
        Any file is unreadable, corrupt, too large, inconsistent or holds NaN where values are
        needed; the message is one line naming the file.
    """
    folder = _run_folder(Path(run_dir))
    trajectory_path = folder / TRAJECTORY_FILE
    _is_regular_file(trajectory_path, required=True)
    scenario = _read_scenario(folder / SCENARIO_FILE, required=require_scenario)
    arrays = read_npz(trajectory_path, _TRAJECTORY_KEYS)
    trajectory = _check_trajectory(arrays, trajectory_path, scenario)
    steps, agents = trajectory["states"].shape[0] - 1, trajectory["states"].shape[1]
    summary_path = folder / SUMMARY_FILE
    steps_path, admm_path = folder / STEPS_FILE, folder / ADMM_FILE
    return RunData(
        run_dir=folder,
        scenario=scenario,
        summary=read_summary(summary_path) if _is_regular_file(summary_path) else {},
        admm=_read_admm(admm_path, steps, agents) if _is_regular_file(admm_path) else None,
        steps=_read_steps(steps_path, steps, agents) if _is_regular_file(steps_path) else MappingProxyType({}),
        **trajectory,
    )


def read_summary(path: str | Path) -> dict[str, Any]:
    """A run's ``summary.json`` as a dict; :class:`RunDataError` (one line naming it) otherwise."""
    path = Path(path)
    _is_regular_file(path, required=True)
    text = _read_text(path)
    try:
        summary = json.loads(text)
    except json.JSONDecodeError as err:
        raise RunDataError(f"{path}: not valid JSON ({err.msg} at line {err.lineno})") from None
    except RecursionError:
        raise RunDataError(f"{path}: not valid JSON (nested too deeply)") from None
    if not isinstance(summary, dict):
        raise RunDataError(f"{path}: expected a JSON object, got {type(summary).__name__}")
    tol = summary.get("admm_tol")
    if tol is not None and not (_is_number(tol) and math.isfinite(tol) and tol > 0):
        raise RunDataError(f"{path}: 'admm_tol' must be a positive number, got {_short(repr(tol))}")
    return summary


def read_npz(path: str | Path, keys: Collection[str]) -> dict[str, np.ndarray]:
    """The arrays ``keys`` of an ``.npz`` archive that holds them (absent keys are left out).

    Each member's ``.npy`` header is read and checked before its data: only bool, integer and
    float arrays, at most :data:`MAX_ARCHIVE_BYTES` in all, and exactly as many bytes as the
    member holds. Pickles are never loaded. Members that are not asked for are not read.
    """
    path = Path(path)
    try:
        handle = path.open("rb")
    except OSError as err:
        raise RunDataError(f"{path}: cannot read ({_reason(err)})") from None
    try:
        with handle, zipfile.ZipFile(handle) as archive:
            members = _npy_members(archive, path)
            budget = MAX_ARCHIVE_BYTES
            arrays: dict[str, np.ndarray] = {}
            for key in keys:
                if key in members:
                    arrays[key] = _read_member(archive, members[key], path, budget)
                    budget -= arrays[key].nbytes
            return arrays
    except RunDataError:
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, zlib.error, EOFError, OSError, ValueError,
            NotImplementedError, RuntimeError) as err:  # RuntimeError: an encrypted member
        raise RunDataError(f"{path}: corrupt or truncated archive ({_reason(err)})") from None


# ------------------------------------------------------------------------------------ files
def _run_folder(folder: Path) -> Path:
    """``folder`` when it is a directory; a one-line error otherwise."""
    try:
        mode = folder.stat().st_mode
    except FileNotFoundError:
        raise MissingRunFileError(f"{folder}: no such run folder") from None
    except OSError as err:
        raise RunDataError(f"{folder}: cannot open the run folder ({_reason(err)})") from None
    if not stat.S_ISDIR(mode):
        raise MissingRunFileError(f"{folder}: no such run folder (it is a file)")
    return folder


def _is_regular_file(path: Path, required: bool = False) -> bool:
    """Whether ``path`` is a regular file (symlinks followed); False when absent and optional.

    Something else in its place (a directory, a FIFO, a dangling or looping symlink) is an
    error even for an optional file: a damaged folder is never read as a folder without it.
    """
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        if path.is_symlink():
            raise MissingRunFileError(f"{path}: dangling symlink (its target does not exist)") from None
        if required:
            raise MissingRunFileError(f"{path.parent}: missing {path.name} (is this a run folder?)") from None
        return False
    except OSError as err:  # a symlink loop, no permission, a path through a file
        raise RunDataError(f"{path}: cannot open ({_reason(err)})") from None
    if stat.S_ISDIR(mode):
        raise RunDataError(f"{path}: is a directory, not a file")
    if not stat.S_ISREG(mode):
        raise RunDataError(f"{path}: not a regular file")
    return True


def _read_text(path: Path) -> str:
    """The UTF-8 text of a small file, refusing one larger than :data:`MAX_TEXT_BYTES`."""
    try:
        with path.open("rb") as stream:
            raw = stream.read(MAX_TEXT_BYTES + 1)
    except OSError as err:
        raise RunDataError(f"{path}: cannot read ({_reason(err)})") from None
    if len(raw) > MAX_TEXT_BYTES:
        raise RunDataError(f"{path}: larger than {_size(MAX_TEXT_BYTES)}; not a run file")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as err:
        raise RunDataError(f"{path}: not UTF-8 text (byte {err.start})") from None


def _read_scenario(path: Path, required: bool) -> Scenario | None:
    """The validated scenario of ``scenario.yaml``; None when absent and not required."""
    if not _is_regular_file(path, required):
        return None
    try:
        data = parse_yaml_text(_read_text(path), str(path))  # the scenario loader's own bounds
    except ScenarioError as err:
        raise RunDataError(str(err)) from None
    try:
        return scenario_from_dict(data, source=str(path))
    except ScenarioError as err:
        message = str(err)
        raise RunDataError(message if message.startswith(str(path)) else f"{path}: {message}") from None
    except RecursionError:
        raise RunDataError(f"{path}: invalid scenario (nested too deeply)") from None


# ------------------------------------------------------------------------------------ archives
def _npy_members(archive: zipfile.ZipFile, path: Path) -> dict[str, zipfile.ZipInfo]:
    """The ``.npy`` members of an archive by array name."""
    infos = archive.infolist()
    if len(infos) > _MAX_MEMBERS:
        raise RunDataError(f"{path}: {len(infos)} archive members; a run file holds a few")
    return {info.filename[: -len(".npy")]: info for info in infos if info.filename.endswith(".npy")}


def _read_member(archive: zipfile.ZipFile, info: zipfile.ZipInfo, path: Path, budget: int) -> np.ndarray:
    """One array of an archive, its header checked before any data is read or allocated."""
    key = info.filename[: -len(".npy")]
    try:
        with archive.open(info) as stream:
            shape, fortran, dtype = _npy_header(stream, path, key)
            claimed = math.prod(shape) * dtype.itemsize
            if claimed > budget:
                raise RunDataError(f"{path}: '{key}' claims shape {shape} ({_size(claimed)}), more than "
                                   f"the {_size(MAX_ARCHIVE_BYTES)} a run file may hold")
            held = info.file_size - stream.tell()
            if claimed != held:
                raise RunDataError(f"{path}: '{key}' claims shape {shape} ({claimed} bytes) but its member "
                                   f"holds {held} bytes")
            raw = _read_exactly(stream, claimed)
            if len(raw) != claimed or stream.read(1):  # read to the end: the CRC is checked there
                raise RunDataError(f"{path}: '{key}' is truncated")
    except RunDataError:
        raise
    except (zipfile.BadZipFile, zlib.error, EOFError, OSError, ValueError, NotImplementedError,
            RuntimeError) as err:
        raise RunDataError(f"{path}: corrupt archive member '{key}' ({_reason(err)})") from None
    return np.frombuffer(raw, dtype=dtype).reshape(shape, order="F" if fortran else "C")


def _npy_header(stream: IO[bytes], path: Path, key: str) -> tuple[tuple[int, ...], bool, np.dtype]:
    """(shape, fortran order, dtype) of an ``.npy`` stream; refuses anything but plain numbers."""
    version = np.lib.format.read_magic(stream)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(stream, max_header_size=_MAX_HEADER_BYTES)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(stream, max_header_size=_MAX_HEADER_BYTES)
    else:
        raise RunDataError(f"{path}: '{key}' has unsupported .npy format version {version}")
    if dtype.hasobject:
        raise RunDataError(f"{path}: '{key}' holds Python objects; pickles are never loaded")
    if dtype.kind not in _NUMERIC_KINDS:
        raise RunDataError(f"{path}: '{key}' has dtype {dtype}, not numbers")
    if any(n < 0 for n in shape):
        raise RunDataError(f"{path}: '{key}' claims the negative shape {shape}")
    return tuple(int(n) for n in shape), bool(fortran), dtype


def _read_exactly(stream: IO[bytes], count: int) -> bytes:
    """``count`` bytes of ``stream`` or fewer at its end (a zip member returns them in pieces)."""
    pieces, left = [], count
    while left > 0:
        piece = stream.read(min(left, 1 << 24))
        if not piece:
            break
        pieces.append(piece)
        left -= len(piece)
    return b"".join(pieces)


# ------------------------------------------------------------------------------------ checks
def _check_trajectory(arrays: dict[str, np.ndarray], path: Path, scenario: Scenario | None) -> dict[str, Any]:
    """The checked, read-only trajectory fields of :class:`RunData` from ``trajectory.npz``."""
    states = _states(arrays, path, scenario)
    steps, agents, dim = states.shape[0] - 1, states.shape[1], states.shape[2] // 2
    dt = _dt(arrays, path, scenario)
    t = _optional(arrays, "t", path, (steps + 1,))
    inputs = _optional(arrays, "inputs", path, (steps, agents, dim))
    disturbances = _optional(arrays, "disturbances", path, (steps, agents, 2 * dim))
    goals = _goals(arrays, path, scenario, agents, dim)
    delta = _delta(arrays, path, scenario, dim)
    bodies = _bodies(arrays, path, scenario, delta, agents)
    poses = _optional(arrays, "poses", path, (steps + 1, agents, 3))
    return {
        "states": _frozen(states),
        "dt": dt,
        "t": _frozen(dt * np.arange(steps + 1) if t is None else t),
        "inputs": _frozen(np.full((steps, agents, dim), np.nan) if inputs is None else inputs),
        "goals": _frozen(goals),
        "delta": _frozen(delta),
        "disturbances": None if disturbances is None else _frozen(disturbances),
        "bodies": _frozen(bodies),
        "poses": _frozen(point_poses(states[:, :, :dim]) if poses is None else poses),
        "footprints": _frozen(_footprints(arrays, path, bodies)),
    }


def _states(arrays: dict[str, np.ndarray], path: Path, scenario: Scenario | None) -> np.ndarray:
    """(T+1, M, 2d) states: present, finite, d in {2, 3}, matching the scenario."""
    if "states" not in arrays:
        raise RunDataError(f"{path}: missing array 'states' (not a swarmpc trajectory)")
    states = np.asarray(arrays["states"], float)
    if states.ndim != 3 or states.shape[2] not in (4, 6):
        raise RunDataError(f"{path}: 'states' must be (T+1, M, 2d) with d = 2 or 3, got shape {states.shape}")
    if states.shape[0] == 0:
        raise RunDataError(f"{path}: 'states' holds no states (not even the initial one)")
    if states.shape[1] == 0:
        raise RunDataError(f"{path}: 'states' holds no agents")
    if scenario is not None and (scenario.dim, scenario.num_agents) != (states.shape[2] // 2, states.shape[1]):
        raise RunDataError(
            f"{path}: 'states' {states.shape} is not (T+1, {scenario.num_agents}, {2 * scenario.dim}) "
            f"as scenario.yaml has {scenario.num_agents} agents in dim {scenario.dim}"
        )
    _require_finite(states, "states", path)
    return states


def _optional(arrays: dict[str, np.ndarray], key: str, path: Path, shape: tuple[int, ...]) -> np.ndarray | None:
    """Array ``key`` as floats when present, checked to have ``shape`` and finite values."""
    if key not in arrays:
        return None
    array = np.asarray(arrays[key], float)
    if array.shape != shape:
        raise RunDataError(f"{path}: '{key}' must have shape {shape}, got {array.shape}")
    _require_finite(array, key, path)
    return array


def _dt(arrays: dict[str, np.ndarray], path: Path, scenario: Scenario | None) -> float:
    """The sampling time: the trajectory's ``dt``, else the scenario's; finite and > 0."""
    if "dt" not in arrays:
        if scenario is None:
            raise RunDataError(f"{path}: missing array 'dt' (and no scenario.yaml to take it from)")
        return float(scenario.dt)
    dt = np.asarray(arrays["dt"], float).reshape(-1)
    if dt.size != 1 or not math.isfinite(dt[0]) or dt[0] <= 0:
        raise RunDataError(f"{path}: 'dt' must be one finite number > 0, got {_short(str(dt.tolist()))}")
    return float(dt[0])


def _goals(arrays: dict[str, np.ndarray], path: Path, scenario: Scenario | None, agents: int, dim: int) -> np.ndarray:
    """(M, 2d) goal states: the trajectory's (positions alone get zero velocities) or the scenario's."""
    if "goals" not in arrays:
        if scenario is None:
            raise RunDataError(f"{path}: missing array 'goals' (and no scenario.yaml to take them from)")
        return scenario.goal_states()
    goals = np.asarray(arrays["goals"], float)
    if goals.shape == (agents, dim):
        goals = np.hstack([goals, np.zeros((agents, dim))])
    if goals.shape != (agents, 2 * dim):
        raise RunDataError(f"{path}: 'goals' must have shape {(agents, 2 * dim)}, got {goals.shape}")
    _require_finite(goals, "goals", path)
    return goals


def _delta(arrays: dict[str, np.ndarray], path: Path, scenario: Scenario | None, dim: int) -> np.ndarray:
    """(d,) box half-sizes from a scalar or d values, finite and > 0."""
    if "delta" not in arrays:
        if scenario is None:
            raise RunDataError(f"{path}: missing array 'delta' (and no scenario.yaml to take it from)")
        return np.asarray(scenario.delta_vector, float)
    delta = np.asarray(arrays["delta"], float)
    if delta.ndim > 1 or delta.size not in (1, dim):
        raise RunDataError(f"{path}: 'delta' must be a scalar or {dim} values, got shape {delta.shape}")
    if not np.all(np.isfinite(delta) & (delta > 0)):
        raise RunDataError(f"{path}: 'delta' must be finite and > 0, got {_short(str(delta.tolist()))}")
    return np.broadcast_to(delta.reshape(-1), (dim,)).copy()


def _bodies(
    arrays: dict[str, np.ndarray], path: Path, scenario: Scenario | None, delta: np.ndarray, agents: int
) -> np.ndarray:
    """(M, d) body half-sizes: the trajectory's ``bodies`` (finite, > 0), else the scenario's, else
    delta / 2 for every agent (the default body of a folder written before bodies existed)."""
    dim = delta.size
    if "bodies" not in arrays:
        if scenario is not None:
            return scenario.bodies
        return np.tile(delta / 2.0, (agents, 1))
    bodies = np.asarray(arrays["bodies"], float)
    if bodies.shape != (agents, dim):
        raise RunDataError(f"{path}: 'bodies' must have shape {(agents, dim)}, got {bodies.shape}")
    if not np.all(np.isfinite(bodies) & (bodies > 0)):
        raise RunDataError(f"{path}: 'bodies' must be finite and > 0")
    return bodies


def _footprints(arrays: dict[str, np.ndarray], path: Path, bodies: np.ndarray) -> np.ndarray:
    """(M, 2) footprints: the trajectory's ``footprints`` (finite, > 0), else the point agents'
    of ``bodies`` (a folder written before footprints existed)."""
    if "footprints" not in arrays:
        return point_footprints(bodies)
    footprints = np.asarray(arrays["footprints"], float)
    if footprints.shape != (bodies.shape[0], 2):
        raise RunDataError(f"{path}: 'footprints' must have shape {(bodies.shape[0], 2)}, got {footprints.shape}")
    if not np.all(np.isfinite(footprints) & (footprints > 0)):
        raise RunDataError(f"{path}: 'footprints' must be finite and > 0")
    return footprints


def _read_steps(path: Path, steps: int, agents: int) -> Mapping[str, np.ndarray]:
    """The per-step records of ``steps.npz``: T rows each, M columns where per agent."""
    arrays = read_npz(path, tuple(_STEP_KEYS))
    for key, array in arrays.items():
        shape = (steps, agents) if _STEP_KEYS[key] else (steps,)
        if array.shape != shape:
            raise RunDataError(f"{path}: '{key}' must have shape {shape} for {steps} steps, got {array.shape}")
    return MappingProxyType({key: _frozen(array, array.dtype) for key, array in arrays.items()})


def _read_admm(path: Path, steps: int, agents: int) -> AdmmResiduals:
    """The ADMM records of ``admm.npz``: residual histories with T rows (NaN pads them)."""
    arrays = read_npz(path, _ADMM_KEYS)
    for key in ("primal", "dual"):
        if key not in arrays:
            raise RunDataError(f"{path}: missing array '{key}'")
    primal = np.asarray(arrays["primal"], float)
    if primal.ndim != 2 or primal.shape[0] != steps:
        raise RunDataError(f"{path}: 'primal' must be ({steps}, iterations) for {steps} steps, got {primal.shape}")
    dual = _admm_array(arrays, "dual", path, primal.shape, nan_ok=True)
    assert dual is not None  # present: checked above
    rho = _admm_array(arrays, "rho", path, primal.shape, nan_ok=True)
    iterations = _admm_array(arrays, "iterations", path, (steps,), nan_ok=False)
    if iterations is None:
        iterations = np.sum(np.isfinite(primal), axis=1).astype(float)
    if np.any(iterations < 0):
        raise RunDataError(f"{path}: 'iterations' holds negative counts")
    return AdmmResiduals(
        primal=_frozen(primal),
        dual=_frozen(dual),
        iterations=_frozen(iterations),
        rho=None if rho is None else _frozen(rho),
        copies=_frozen_or_none(_admm_array(arrays, "copies", path, (steps, agents), nan_ok=False)),
        planes=_frozen_or_none(_admm_array(arrays, "planes", path, (steps, agents), nan_ok=False)),
    )


def _admm_array(
    arrays: dict[str, np.ndarray], key: str, path: Path, shape: tuple[int, ...], nan_ok: bool
) -> np.ndarray | None:
    """Array ``key`` of ``admm.npz`` as floats with ``shape``; NaN and inf only where ``nan_ok``."""
    if key not in arrays:
        return None
    array = np.asarray(arrays[key], float)
    if array.shape != shape:
        raise RunDataError(f"{path}: '{key}' must have shape {shape}, got {array.shape}")
    if not nan_ok:
        _require_finite(array, key, path)
    return array


# ------------------------------------------------------------------------------------ helpers
def _require_finite(array: np.ndarray, key: str, path: Path) -> None:
    bad = ~np.isfinite(array)
    if bad.any():
        where = tuple(int(i) for i in np.argwhere(bad)[0])
        raise RunDataError(f"{path}: '{key}' holds NaN or infinite values (first at index {where})")


def _frozen(array: np.ndarray, dtype: Any = float) -> np.ndarray:
    """A read-only copy of ``array``."""
    frozen = np.array(array, dtype=dtype)
    frozen.setflags(write=False)
    return frozen


def _frozen_or_none(array: np.ndarray | None) -> np.ndarray | None:
    return None if array is None else _frozen(array)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _reason(err: BaseException) -> str:
    """``ErrorClass: what it says``, short and on one line."""
    text = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
    text = _short(" ".join(str(text).split()))
    kind = "zlib.error" if isinstance(err, zlib.error) else type(err).__name__
    return f"{kind}: {text}" if text else kind


def _short(text: str, limit: int = 120) -> str:
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _size(count: int) -> str:
    """A byte count for people: 1 GiB, 7.3 TiB."""
    value = float(count)
    for unit in ("bytes", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if value < 1024 or unit == "PiB":
            return f"{value:.0f} {unit}" if unit == "bytes" or value == int(value) else f"{value:.1f} {unit}"
        value /= 1024
    return f"{count} bytes"
