"""Initial guesses for cars: an OMPL path in SE(2) within the car's turning limit, then a speed profile.

A point agent's guess (:mod:`swarmpc.solvers.rrt`) is a polyline of positions; a car cannot follow
one, since it cannot turn on the spot nor move sideways. :func:`car_path` therefore plans in SE(2),
the poses ``(x, y, theta)`` of the car's reference point (the centre of the rear axle, whose path
has curvature ``tan(delta) / wheelbase``), in OMPL's Reeds-Shepp state space: every motion between
two poses is a shortest path made of arcs of the car's minimum turning radius
``1 / KinematicCar.max_curvature`` and straight lines, forwards or in reverse. By default it first
tries the Dubins space (the same curves, forwards only), since the Reeds-Shepp paths reverse
freely and a car reverses slowly; a car that may not reverse (``max_reverse_speed == 0``) is only
ever planned in the Dubins space.
:func:`car_guess` then drives along that path: it accelerates, cruises and brakes along the arc
length within the car's speed and acceleration limits, stopping at every cusp (a change between
forwards and reverse), and derives the inputs with :meth:`KinematicCar.guess_inputs`.
:func:`car_straight_guess` is the obstacle-blind fallback along the straight line to the goal.

Validity model
--------------
A pose is valid when the car's rectangular footprint at that pose (:meth:`KinematicCar.pose`)
lies inside the workspace box and keeps an exact Euclidean distance ``>= d_min`` to every obstacle
``{y : G y <= g}`` (:func:`swarmpc.model.footprint.polygon_distance`, signed, so that with
``d_min = 0`` an overlap is invalid and touching is not). Obstacles far from the footprint are
skipped by a cheap lower bound: the largest normalised face residual of the footprint's centre,
less the footprint's half diagonal.

Motions are checked at the poses OMPL's motion validator visits, spaced at most ``h`` apart along
the reference point's path, ``h = min(d_min / 2, 0.01 * extent) / (1 + r kappa)`` (``extent`` the
workspace diagonal, ``r`` :attr:`KinematicCar.body_radius`, ``kappa`` the maximum curvature;
``0.01 * extent / (1 + r kappa)`` when ``d_min == 0``). Over an arc of length ``s`` of the
reference point no point of the footprint moves further than ``(1 + r kappa) s``, and every pose
between two checked ones is within ``h / 2`` of one of them, so between checks the clearance can
drop by at most ``d_min / 4``. The returned path is made of exactly the checked poses, plus the
cusps that fall between them, which are checked afterwards.

Planner
-------
RRT-Connect. It returns its first solution, so for a given seed the path does not depend on how
many iterations fit into the time limit, whereas RRT* and BIT* are anytime planners that keep
improving until the limit and would return a different path on a more or less loaded machine
(a guess that changes from run to run breaks reproducible closed-loop runs). The Reeds-Shepp
steering is symmetric, which the bidirectional search suits; OMPL's RRT-Connect checks the goal
tree's motions in the direction they are driven, so it is correct in the asymmetric Dubins space
as well. Optimality is not the point: the guess only has to put the car in the right homotopy
class, and the MPC optimises the trajectory; the path simplifier removes the detours. A goal
reachable only along a short arc (a pose close to the workspace edge or an obstacle, facing it)
is a narrow target for the forwards-only search, which then spends its iterations in vain
before the Reeds-Shepp attempt finds the manoeuvre with reversing.

Reproducibility
---------------
As in :mod:`swarmpc.solvers.rrt`: every attempt reseeds OMPL's process-wide generator and builds
fresh OMPL objects, and the simplifier runs a bounded number of deterministic passes. An attempt
ends after a number of planner iterations; the time limit is only a guard, since which attempt
finds the path must not depend on the machine's load. OMPL's log level is lowered for the
duration of a call. The seed and the log level are global to the process, so concurrent planning
from several threads is not reproducible.

Failure
-------
:func:`car_path` returns ``None`` (it never raises for the geometry) when no attempt found a path
within its iterations or the time limit, which includes a goal that no path reaches (a closed
wall: a sampling planner cannot tell it from an unlucky search), or when the start or goal pose
is itself invalid. The
caller falls back to :func:`car_straight_guess` (:func:`car_guess` does so itself when handed
``None``). Malformed arguments (shapes, non-finite numbers, a non-planar model) raise ValueError.
"""

from __future__ import annotations

import math
import operator
import time
from collections.abc import Callable, Sequence

import numpy as np
from ompl import base as ob
from ompl import geometric as og
from ompl import util as ou

from swarmpc.model.car import KinematicCar
from swarmpc.model.footprint import polygon_distance, polygon_vertices, rotation
from swarmpc.solvers.rrt import ompl_seed, simplify_path

__all__ = ["PLANNER_ITERATIONS", "car_guess", "car_path", "car_straight_guess"]

PLANNER_ITERATIONS = 400
"""Default RRT-Connect iterations per planning attempt of :func:`car_path`: the guesses of the
built-ins and the tests' scenes are found within 150 when a path exists (the forwards-only
attempt round the parking bays finds none, and the Reeds-Shepp attempt finds one within 50)."""

Obstacles = Sequence[tuple[np.ndarray, np.ndarray]]

_SAME_POSE = 1e-12  # poses whose reference points are closer than this [m] are the same point
_DIRECTION_PROBE = 1e-7  # length [m] of the step that reads the direction of motion along a curve
_BISECTIONS = 60  # bisection steps locating a cusp between two checked poses
_STOP_TOL = 1e-9  # arc length [m] within which the guess counts as arrived at a stop
_START_TOL = 1e-6  # largest mismatch between a path's first pose and the car's pose [m, rad]


def _vector(x: np.ndarray, size: int, name: str) -> np.ndarray:
    """``x`` as a finite float vector of length ``size``, else ValueError."""
    v = np.asarray(x, dtype=float).reshape(-1)
    if v.size != size or not np.all(np.isfinite(v)):
        raise ValueError(f"{name} must be a finite vector of length {size}")
    return v


def _check_car(model: KinematicCar) -> None:
    if not isinstance(model, KinematicCar):
        raise ValueError(f"model must be a KinematicCar, got {type(model).__name__}")


class _FootprintValidity:
    """Whether the car's footprint at a pose of its reference point is inside the box and clear.

    Obstacle vertices are computed once and padded to a common count by repeating the last
    vertex (a zero-length edge has a zero normal, which :func:`polygon_distance` ignores), so the
    footprint is measured against all nearby obstacles in one broadcast call.
    """

    def __init__(
        self, model: KinematicCar, bounds: tuple[np.ndarray, np.ndarray], obstacles: Obstacles, d_min: float
    ) -> None:
        _check_car(model)
        lower, upper = bounds
        self.lower, self.upper = _vector(lower, 2, "bounds[0]"), _vector(upper, 2, "bounds[1]")
        if np.any(self.upper <= self.lower):
            raise ValueError("the upper bound must be strictly greater than the lower one")
        d_min = float(d_min)
        if not math.isfinite(d_min) or d_min < 0:
            raise ValueError("d_min must be a finite number >= 0")
        self.model, self.d_min = model, d_min
        self.offset = model.centre_offset
        half = 0.5 * np.array(model.footprint)
        self.reach = float(np.hypot(*half))  # half diagonal: centre to corner
        # Corners relative to the reference point in the body frame (x along the heading).
        self._body = np.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]]) * half + [self.offset, 0.0]
        extent = float(np.linalg.norm(self.upper - self.lower))
        spacing = min(0.5 * d_min, 0.01 * extent) if d_min > 0 else 0.01 * extent
        self.step = spacing / (1.0 + model.body_radius * model.max_curvature)

        normals, offsets, vertices = [], [], []
        for G, g in obstacles:
            G = np.atleast_2d(np.asarray(G, dtype=float))
            g = np.asarray(g, dtype=float).reshape(-1)
            if G.ndim != 2 or G.shape[1] != 2 or g.size != G.shape[0]:
                raise ValueError("obstacle (G, g) must have shapes (m, 2) and (m,)")
            norms = np.linalg.norm(G, axis=1)
            normals.append(G / norms[:, None])
            offsets.append(g / norms)
            vertices.append(polygon_vertices(G, g))
        count = len(normals)
        faces = max((G.shape[0] for G in normals), default=1)
        corners = max((V.shape[0] for V in vertices), default=1)
        self._normals = np.zeros((count, faces, 2))
        self._offsets = np.full((count, faces), np.inf)  # padding rows: residual -inf, never the max
        self._vertices = np.zeros((count, corners, 2))
        for k in range(count):
            self._normals[k, : normals[k].shape[0]] = normals[k]
            self._offsets[k, : offsets[k].size] = offsets[k]
            self._vertices[k] = np.vstack([vertices[k]] + [vertices[k][-1:]] * (corners - vertices[k].shape[0]))

    def corners(self, poses: np.ndarray) -> np.ndarray:
        """Counter-clockwise footprint corners (n, 4, 2) of reference poses (n, 3)."""
        return np.einsum("kb,nab->nka", self._body, rotation(poses[:, 2])) + poses[:, None, :2]

    def poses_valid(self, poses: np.ndarray) -> np.ndarray:
        """Validity (n,) of the reference poses (n, 3), measured exactly against every obstacle."""
        corners = self.corners(np.atleast_2d(np.asarray(poses, dtype=float)))
        ok = np.all((corners >= self.lower) & (corners <= self.upper), axis=(1, 2))
        if self._vertices.shape[0]:
            gaps = polygon_distance(corners[:, None], self._vertices[None], signed=True)
            ok &= np.all(gaps >= self.d_min, axis=1)
        return ok

    def pose_valid(self, x: float, y: float, theta: float) -> bool:
        """Validity of one pose (the planner's hot path): exact distances to nearby obstacles only."""
        cos, sin = math.cos(theta), math.sin(theta)
        corners = self._body @ np.array([[cos, sin], [-sin, cos]]) + (x, y)
        if (corners < self.lower).any() or (corners > self.upper).any():
            return False
        if not self._vertices.shape[0]:
            return True
        centre = np.array([x + self.offset * cos, y + self.offset * sin])
        near = np.max(self._normals @ centre - self._offsets, axis=1) - self.reach < self.d_min
        if not near.any():
            return True
        gaps = polygon_distance(corners, self._vertices[near], signed=True)
        return bool(np.all(gaps >= self.d_min))

    def ompl_checker(self) -> Callable[[ob.State], bool]:
        """A plain callable for ``SpaceInformation.setStateValidityChecker``."""
        valid = self.pose_valid

        def check(state: ob.State) -> bool:
            return valid(state.getX(), state.getY(), state.getYaw())

        return check


def _space_information(validity: _FootprintValidity, reverse: bool) -> ob.SpaceInformation:
    """Reeds-Shepp (``reverse``) or Dubins space with the car's turning radius, the workspace box
    as the reference point's bounds and motion checks every ``validity.step``."""
    radius = 1.0 / validity.model.max_curvature
    space = ob.ReedsSheppStateSpace(radius) if reverse else ob.DubinsStateSpace(radius)
    bounds = ob.RealVectorBounds(2)
    for i in range(2):
        bounds.setLow(i, float(validity.lower[i]))
        bounds.setHigh(i, float(validity.upper[i]))
    space.setBounds(bounds)
    space.setLongestValidSegmentFraction(validity.step / space.getMaximumExtent())
    si = ob.SpaceInformation(space)
    si.setStateValidityChecker(validity.ompl_checker())
    si.setup()
    return si


def _termination(iterations: int, deadline: float) -> ob.PlannerTerminationCondition:
    """Ends a search after ``iterations`` evaluations (one per planner iteration) or at
    ``deadline`` (``time.perf_counter()``), whichever comes first."""
    count = [0]

    def spent() -> bool:
        count[0] += 1
        return count[0] > iterations or time.perf_counter() >= deadline

    return ob.PlannerTerminationCondition(spent)


def _solve(
    si: ob.SpaceInformation, start: np.ndarray, goal: np.ndarray, iterations: int, deadline: float,
) -> list[og.PathGeometric]:
    """RRT-Connect from ``start`` to ``goal`` within ``iterations`` planner iterations and before
    ``deadline``: [simplified path, raw path], or [] without an exact solution."""
    setup = og.SimpleSetup(si)
    # si.allocState() states are owned by Python; space.allocState() ones leak.
    s_start, s_goal = si.allocState(), si.allocState()
    for state, pose in ((s_start, start), (s_goal, goal)):
        state.setXY(float(pose[0]), float(pose[1]))
        state.setYaw((float(pose[2]) + math.pi) % (2.0 * math.pi) - math.pi)  # SO(2) bounds: [-pi, pi)
    setup.setStartAndGoalStates(s_start, s_goal)
    setup.setPlanner(og.RRTConnect(si))
    setup.solve(_termination(iterations, deadline))
    if not setup.haveExactSolutionPath():
        return []
    path = og.PathGeometric(setup.getSolutionPath())
    raw = og.PathGeometric(path)
    simplify_path(si, path)
    return [path, raw]


def _sample(si: ob.SpaceInformation, path: og.PathGeometric) -> np.ndarray:
    """Poses (n, 3) along ``path``: the poses its motion checks visit, plus the cusp between two of
    them (located by bisection on the direction of motion), with wrapped headings.

    The direction is read at both ends of each step, so a step holding two cusps (a piece of the
    Reeds-Shepp curve shorter than the step between them) keeps neither: the path then turns at
    most by the curvature bound times the piece's length more than the step's chord suggests.
    """
    space = si.getStateSpace()
    scratch = si.allocState()
    waypoints = path.getStates()
    rows = [_pose_of(waypoints[0])]
    for a, b in zip(waypoints[:-1], waypoints[1:], strict=True):
        length = space.distance(a, b)
        if length <= _SAME_POSE:
            continue

        def at(t: float, a: ob.State = a, b: ob.State = b) -> np.ndarray:
            space.interpolate(a, b, min(max(t, 0.0), 1.0), scratch)
            return _pose_of(scratch)

        probe = _DIRECTION_PROBE / length
        count = space.validSegmentCount(a, b)
        for j in range(count):
            lo, hi = j / count, (j + 1) / count
            heading = _direction(at(lo), at(lo + probe))
            if heading != _direction(at(hi - probe), at(hi)):
                for _ in range(_BISECTIONS):
                    if hi - lo <= probe:
                        break
                    mid = 0.5 * (lo + hi)
                    lo, hi = (mid, hi) if _direction(at(mid), at(mid + probe)) == heading else (lo, mid)
                rows.append(at(0.5 * (lo + hi)))
            rows.append(_pose_of(b) if j + 1 == count else at((j + 1) / count))
    return np.array(rows)


def _pose_of(state: ob.State) -> np.ndarray:
    return np.array([state.getX(), state.getY(), state.getYaw()])


def _direction(before: np.ndarray, after: np.ndarray) -> int:
    """+1 when the move from pose ``before`` to ``after`` goes along the heading, -1 against it."""
    move = after[:2] - before[:2]
    return 1 if move[0] * math.cos(before[2]) + move[1] * math.sin(before[2]) >= 0 else -1


def _with_headings(poses: np.ndarray, start: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """``poses`` with continuous headings from ``start``'s, first row ``start`` and last ``goal``
    (its heading shifted by the multiple of 2 pi nearest to the path's)."""
    poses = poses.copy()
    poses[:, 2] = np.unwrap(poses[:, 2])
    poses[:, 2] += start[2] - poses[0, 2]
    poses[0] = start
    turns = np.round((poses[-1, 2] - goal[2]) / (2.0 * math.pi))
    poses[-1] = [goal[0], goal[1], goal[2] + 2.0 * math.pi * turns]
    return poses


def car_path(
    model: KinematicCar,
    start_pose: np.ndarray,
    goal_pose: np.ndarray,
    obstacles: Obstacles,
    bounds: tuple[np.ndarray, np.ndarray],
    d_min: float,
    seed: int,
    time_limit: float = 1.0,
    prefer_forward: bool = True,
    iterations: int = PLANNER_ITERATIONS,
) -> np.ndarray | None:
    """Plan a collision-free path of the car's reference pose with OMPL, within its turning limit.

    Parameters
    ----------
    model : KinematicCar
        The car: its turning radius ``1 / max_curvature``, its footprint (``length``, ``width``,
        ``centre_offset``) and whether it may reverse (``max_reverse_speed > 0``: Reeds-Shepp
        curves, else Dubins curves).
    start_pose, goal_pose : (3,) array
        ``(x, y, theta)`` of the reference point (the rear axle's centre), as in the car's state.
    obstacles : sequence of (G, g)
        Bounded convex polygons ``{y : G y <= g}``.
    bounds : (lower, upper)
        The workspace box (2,) each; the whole footprint must stay inside it.
    d_min : float
        Required clearance (>= 0) of the footprint to every obstacle.
    seed : int
        Seed of OMPL's generators: the same seed gives the same path.
    time_limit : float
        Planner time limit in seconds (> 0; setup, simplification and sampling come on top) for
        all attempts together (see ``prefer_forward``): a guard for a slow or loaded machine.
    iterations : int
        Planner iterations per attempt (> 0). An attempt ends after them or at the time limit,
        whichever comes first; only a search that the iterations end is reproducible, so the time
        limit should leave them ample room.
    prefer_forward : bool
        For a car that may reverse, first plan forwards only (Dubins curves), and only when no
        such path is found plan with reversing (Reeds-Shepp curves). A Reeds-Shepp connection
        between two samples reverses as readily as it drives forwards, so Reeds-Shepp paths tend
        to have long reverse stretches, driven at the car's lower reverse speed limit.

    Returns
    -------
    (n, 3) array or None
        Poses along the path, at most the motion-check step apart along the reference point's
        path (see the module docstring), every one of them valid, the cusps among them (a car
        comes to rest there, so :func:`car_guess` needs them). The headings are continuous (not
        wrapped): the first row is exactly ``start_pose``, the last is ``goal_pose`` up to a
        multiple of 2 pi in the heading. Between consecutive rows the reference point follows
        arcs of curvature at most ``model.max_curvature`` and straight lines. None when no path
        was found within ``iterations`` and ``time_limit`` (a closed wall included) or when
        ``start_pose`` or ``goal_pose`` is invalid; nothing raises then.
    """
    validity = _FootprintValidity(model, bounds, obstacles, d_min)
    start = _vector(start_pose, 3, "start_pose")
    goal = _vector(goal_pose, 3, "goal_pose")
    time_limit = float(time_limit)
    if not time_limit > 0:
        raise ValueError("time_limit must be > 0")
    if not (isinstance(iterations, int) and iterations > 0):
        raise ValueError("iterations must be an int > 0")
    if not (validity.pose_valid(*start) and validity.pose_valid(*goal)):
        return None
    if np.linalg.norm(goal[:2] - start[:2]) <= _SAME_POSE and math.remainder(goal[2] - start[2], 2 * math.pi) == 0:
        return _with_headings(np.vstack([start, goal]), start, goal)

    attempts = [False, True] if prefer_forward and model.max_reverse_speed > 0 else [model.max_reverse_speed > 0]
    previous_level = ou.getLogLevel()
    ou.setLogLevel(ou.LOG_NONE)
    deadline = time.perf_counter() + time_limit
    try:
        for reverse in attempts:
            path = _plan(validity, start, goal, seed, iterations, deadline, reverse)
            if path is not None:
                return path
    finally:
        ou.setLogLevel(previous_level)
    return None


def _plan(
    validity: _FootprintValidity, start: np.ndarray, goal: np.ndarray, seed: int, iterations: int, deadline: float,
    reverse: bool,
) -> np.ndarray | None:
    """One planning attempt of :func:`car_path`, in the Reeds-Shepp (``reverse``) or Dubins space."""
    # Reseeding after OMPL has created generators reseeds the seed generator (OMPL logs an
    # error saying it is not deterministic, but the generators created after it are).
    ou.RNG.setSeed(ompl_seed(seed))
    si = _space_information(validity, reverse)
    # The simplifier's B-spline smoothing repairs states, not motions, and the cusps between
    # checked poses were never checked: hand out the first candidate whose every pose is valid.
    for path in _solve(si, start, goal, iterations, deadline):
        poses = _with_headings(_sample(si, path), start, goal)
        if np.all(validity.poses_valid(poses)):
            return poses
    return None


def _limits(model: KinematicCar, speed: float | None, accel: float | None) -> tuple[float, float, float]:
    """(forward speed cap, reverse speed cap, acceleration limit) of a guess."""
    cap = math.inf if speed is None else float(speed)
    a_max = model.default_accel if accel is None else float(accel)
    if not cap >= 0 or not (math.isfinite(a_max) and a_max > 0):
        raise ValueError("need speed >= 0 (or None) and a finite accel > 0 (or None)")
    return min(model.max_speed, cap), min(model.max_reverse_speed, cap), a_max


def _braking_distance(speed: float, a_max: float, dt: float) -> float:
    """Distance covered while braking from ``speed`` to rest at ``a_max`` in steps of ``dt``
    (the speed is linear within a step, so each step covers its mean speed times dt)."""
    distance = 0.0
    while speed > 0:
        following = max(0.0, speed - a_max * dt)
        distance += 0.5 * (speed + following) * dt
        speed = following
    return distance


def _runs(poses: np.ndarray, speed: float, a_max: float, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cumulative arc length (m,) of the chords of ``poses`` kept, their poses (m, 3), and the runs:
    (r, 2) rows [end arc length, direction +-1] of the stretches driven in one direction.

    A car moving against the first run's direction (or with nowhere to go) first brakes straight
    along its heading and comes back: a stub out and back is put in front of the path.
    """
    heading = poses[0, 2]
    chords = np.diff(poses[:, :2], axis=0)
    mean = 0.5 * (poses[:-1, 2] + poses[1:, 2])
    signs = np.where(chords[:, 0] * np.cos(mean) + chords[:, 1] * np.sin(mean) >= 0, 1.0, -1.0)
    lengths = np.linalg.norm(chords, axis=1)
    keep = lengths > _SAME_POSE
    moving = float(np.sign(speed))
    if moving and (not keep.any() or signs[keep][0] != moving):
        reach = _braking_distance(abs(speed), a_max, dt)
        if reach > _SAME_POSE:
            stub = poses[0] + moving * reach * np.array([math.cos(heading), math.sin(heading), 0.0])
            poses = np.vstack([poses[:1], stub, poses])
        return _runs(poses, 0.0, a_max, dt)  # speed 0: no second stub
    points = np.vstack([poses[:1], poses[1:][keep]])
    arc = np.concatenate([[0.0], np.cumsum(lengths[keep])])
    signs = signs[keep]
    ends = np.flatnonzero(np.append(signs[1:] != signs[:-1], True)) if signs.size else np.zeros(0, int)
    runs = np.column_stack([arc[ends + 1], signs[ends]]) if signs.size else np.array([[0.0, 1.0]])
    return arc, points, runs


def _profile(
    runs: np.ndarray, caps: tuple[float, float], speed: float, a_max: float, dt: float, horizon: int
) -> tuple[np.ndarray, np.ndarray]:
    """Arc length travelled (N+1,) and signed speed (N+1,) at each step along the runs.

    Each step the speed magnitude w rises by at most ``a_max dt`` up to the run's cap, and is the
    largest from which the car can still stop at the run's end: after the step the remaining
    distance r must be at least w^2 / (2 a_max), the distance braking at ``a_max`` in steps of
    ``dt`` covers from a multiple of ``a_max dt``. The step covers (w_k + w_k+1) dt / 2, the
    exact travel of a linear speed. The car comes to rest at each run's end (a cusp or the goal),
    overshooting it by at most ``a_max dt^2 / 8`` (clamped), then starts the next run.
    """
    arc = np.zeros(horizon + 1)
    signed = np.zeros(horizon + 1)
    s, w, run = 0.0, abs(speed), 0
    signed[0] = speed
    for k in range(horizon):
        while run + 1 < runs.shape[0] and w == 0.0 and s >= runs[run, 0] - _STOP_TOL:
            run += 1
        end, direction = runs[run]
        cap = caps[0] if direction > 0 else caps[1]
        room = end - s - 0.5 * w * dt
        half = 0.5 * a_max * dt
        stoppable = -half + math.sqrt(half * half + 2.0 * a_max * room) if room > 0 else 0.0
        following = max(min(cap, w + a_max * dt, stoppable), w - a_max * dt, 0.0)
        s = min(s + 0.5 * (w + following) * dt, end)
        w = following
        arc[k + 1], signed[k + 1] = s, direction * w
    return arc, signed


def _follow(
    model: KinematicCar,
    state: np.ndarray,
    poses: np.ndarray,
    horizon: int,
    dt: float,
    speed: float | None,
    accel: float | None,
) -> tuple[np.ndarray, np.ndarray]:
    """States (N+1, 4) driving along ``poses`` from ``state`` (row 0) and their inputs (N, 2)."""
    forward, reverse, a_max = _limits(model, speed, accel)
    arc, points, runs = _runs(poses, float(state[3]), a_max, dt)
    travelled, signed = _profile(runs, (forward, reverse), float(state[3]), a_max, dt, horizon)
    states = np.empty((horizon + 1, 4))
    if arc.size > 1:
        for i in range(3):
            states[:, i] = np.interp(travelled, arc, points[:, i])
    else:
        states[:, :3] = points[0]
    states[:, 3] = signed
    states[0] = state
    inputs = model.guess_inputs(states)
    inputs[:, 0] = np.clip(inputs[:, 0], -a_max, a_max)
    return states, inputs


def _guess_args(model: KinematicCar, state: np.ndarray, horizon: int, dt: float) -> tuple[np.ndarray, int]:
    _check_car(model)
    state = _vector(state, 4, "state")
    horizon = operator.index(horizon)
    if horizon < 0:
        raise ValueError("horizon must be >= 0")
    if not math.isclose(float(dt), model.dt, rel_tol=1e-12):
        raise ValueError(f"dt must be the model's sampling time {model.dt}, got {dt}")
    return state, horizon


def car_straight_guess(
    model: KinematicCar,
    state: np.ndarray,
    goal: np.ndarray,
    horizon: int,
    dt: float,
    speed: float | None = None,
    accel: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Guess driving forwards along the straight line to the goal, ignoring obstacles.

    The heading of rows 1..N is the line's direction (the multiple of 2 pi nearest to the car's
    heading), or the car's own heading when it is already at the goal; like the point agents'
    straight line, the guess ignores what the car cannot do at the first step (turn on the spot),
    and the inputs of that step are clipped to the steering limit. The speed profile is
    :func:`car_guess`'s.

    Parameters
    ----------
    model, state, horizon, dt, speed, accel
        As in :func:`car_guess`.
    goal : (2,) or (3,) array
        The goal position; a pose's heading is not used.

    Returns
    -------
    states (N+1, 4), inputs (N, 2)
        As in :func:`car_guess`.
    """
    state, horizon = _guess_args(model, state, horizon, dt)
    target = np.asarray(goal, dtype=float).reshape(-1)
    target = _vector(target[:2] if target.size == 3 else target, 2, "goal")
    line = target - state[:2]
    if np.linalg.norm(line) <= _SAME_POSE:
        return _follow(model, state, state[None, :3], horizon, dt, speed, accel)
    direction = math.atan2(line[1], line[0])
    direction += 2.0 * math.pi * round((state[2] - direction) / (2.0 * math.pi))
    poses = np.array([[state[0], state[1], direction], [target[0], target[1], direction]])
    return _follow(model, state, poses, horizon, dt, speed, accel)


def car_guess(
    model: KinematicCar,
    state: np.ndarray,
    goal_pose: np.ndarray,
    path: np.ndarray | None,
    horizon: int,
    dt: float,
    speed: float | None = None,
    accel: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """States and inputs of an OCP guess driving the car along a path of poses (:func:`car_path`).

    The car accelerates at ``accel``, cruises at the speed cap and brakes at ``accel`` to come to
    rest at every cusp of the path and at its end, where it stays; it drives forwards at most at
    ``min(model.max_speed, speed)`` and in reverse (negative v) at most at
    ``min(model.max_reverse_speed, speed)``. A car moving against the path's first direction
    brakes straight ahead first and comes back. Positions and headings are interpolated along the
    path at the travelled arc length, so the guess is as clear of obstacles as the path; the
    inputs are :meth:`KinematicCar.guess_inputs` of the states (acceleration clipped to
    ``accel``), which reproduce them up to the path's curvature changes within a step.

    Parameters
    ----------
    model : KinematicCar
        The car.
    state : (4,) array
        Current state [x, y, theta, v]; row 0 of the guess, unchanged.
    goal_pose : (3,) array
        Where the straight-line fallback heads when ``path`` is None.
    path : (n, 3) array or None
        Poses of the reference point from the car's own pose (position within 1e-6 m, heading
        within 1e-6 rad up to a multiple of 2 pi), as :func:`car_path` returns them; None (a
        failed plan): :func:`car_straight_guess` to ``goal_pose``.
    horizon : int
        Number of steps N (>= 0).
    dt : float
        Sampling time, the model's ``dt``.
    speed : float, optional
        Speed cap (>= 0) below the car's own limits, e.g. the scenario's speed limit.
    accel : float, optional
        Acceleration limit (> 0); None: ``model.default_accel``.

    Returns
    -------
    states (N+1, 4), inputs (N, 2)
        |v_k| within its cap for k >= 1 (unless the car starts faster and slows down at
        ``accel``), |v_k+1 - v_k| <= accel dt, steering within ``model.max_steer``.

    Raises
    ------
    ValueError
        When the path does not start at the car's pose, or on malformed arguments.
    """
    state, horizon = _guess_args(model, state, horizon, dt)
    if path is None:
        return car_straight_guess(model, state, goal_pose, horizon, dt, speed, accel)
    poses = np.atleast_2d(np.asarray(path, dtype=float))
    if poses.ndim != 2 or poses.shape[1] != 3 or poses.shape[0] == 0 or not np.all(np.isfinite(poses)):
        raise ValueError("path must be a finite (n, 3) array of poses")
    poses = poses.copy()
    poses[:, 2] = np.unwrap(poses[:, 2])
    poses[:, 2] += 2.0 * math.pi * round((state[2] - poses[0, 2]) / (2.0 * math.pi))
    if np.linalg.norm(poses[0, :2] - state[:2]) > _START_TOL or abs(poses[0, 2] - state[2]) > _START_TOL:
        raise ValueError("path must start at the car's pose (state[:3])")
    return _follow(model, state, poses, horizon, dt, speed, accel)
