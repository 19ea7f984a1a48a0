"""Sampling-based initial guesses for the MPC, planned with OMPL (RRT-Connect or RRT).

The nonlinear MPC is only locally convergent: started from a straight line through an obstacle it
can get stuck in front of it. A collision-free geometric path from a sampling-based planner,
time-parametrised along its arc length, gives the solver a guess in the right homotopy class.

Validity model
--------------
A position ``p`` is valid when it lies in the workspace box ``[lower, upper]`` and, for every
obstacle ``{x : G x <= g}``, it is NOT inside the face-offset polytope
``{x : G_i x - g_i < inflate * ||G_i|| for all faces i}``. That offset polytope contains the
Minkowski sum of the obstacle with a ball of radius ``inflate``, so every valid point has a
Euclidean distance ``>= inflate`` to every obstacle (conservative near vertices, exact near
faces), and the test is one matrix product vectorised over all obstacles.

Motions are checked by OMPL's discrete motion validator at the step
``h = min(inflate / 2, 0.01 * extent)`` (``extent = ||upper - lower||``, OMPL's maximum extent of
the box; ``h = 0.01 * extent`` when ``inflate == 0``). Between two checked points the clearance
can drop by at most ``h / 2 <= inflate / 4`` (distance is 1-Lipschitz); for polytopes whose
adjacent faces meet at right angles or sharper (boxes in particular) a chord shorter than
``(2 - sqrt(2)) * inflate`` cannot reach the rounded Minkowski sum at all, so the whole path keeps
a clearance ``>= inflate``.

Reproducibility and logging
---------------------------
OMPL's random generators are seeded through the process-wide seed of ``ompl.util.RNG``; every
planning call reseeds it and builds fresh OMPL objects, so the same seed gives the same path.
The path simplifier is run for a fixed number of deterministic passes (bounded by the path size,
not by a wall clock, which would make the result depend on machine load). OMPL's log level is
lowered to ``LOG_NONE`` for the duration of a call and restored afterwards. Both the seed and
the log level are global to the process, so concurrent planning from several threads is not
reproducible.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable, Sequence

import numpy as np
from ompl import base as ob
from ompl import geometric as og
from ompl import util as ou

from swarmpc.model.agent_model import AgentModel, make_model

__all__ = ["RRTGuess", "plan_path", "straight_line_guess", "time_parametrize"]

_PLANNERS = ("rrtconnect", "rrt")
_SIMPLIFY_PASSES = 3  # deterministic simplifier passes at most (stop early when no gain)
_SIMPLIFY_MIN_GAIN = 1e-3  # relative length gain below which another pass is not worth it
_SAME_POINT = 1e-12  # positions closer than this are the same point
_RETRY_FACTOR = 4.0  # budget multiplier of the one retry after a timed-out plan (RRTGuess)

Obstacles = Sequence[tuple[np.ndarray, np.ndarray]]


class _Validity:
    """The point / segment validity check shared by the planner and the path-reuse test.

    Obstacles are padded to a common face count (padding rows never bind) so a point is tested
    against all of them with one ``(k, f, d) @ (d,)`` product.
    """

    def __init__(
        self,
        lower: np.ndarray,
        upper: np.ndarray,
        obstacles: Obstacles,
        inflate: float,
    ) -> None:
        self.lower = np.asarray(lower, dtype=float).reshape(-1)
        self.upper = np.asarray(upper, dtype=float).reshape(-1)
        self.dim = self.lower.size
        if self.dim not in (2, 3) or self.upper.size != self.dim:
            raise ValueError("lower and upper must both have length 2 or 3")
        if not (np.all(np.isfinite(self.lower)) and np.all(np.isfinite(self.upper))):
            raise ValueError("workspace bounds must be finite")
        if np.any(self.upper <= self.lower):
            raise ValueError("upper must be strictly greater than lower")
        inflate = float(inflate)
        if not math.isfinite(inflate) or inflate < 0:
            raise ValueError("inflate must be a finite number >= 0")
        self.inflate = inflate
        self.extent = float(np.linalg.norm(self.upper - self.lower))
        self.step = min(0.5 * inflate, 0.01 * self.extent) if inflate > 0 else 0.01 * self.extent

        faces = []
        self._G: np.ndarray | None = None  # (obstacles, faces, d) stacked face normals; None: no obstacle
        self._h: np.ndarray | None = None  # (obstacles, faces) inflated offsets, padded with +inf
        for G, g in obstacles:
            G = np.atleast_2d(np.asarray(G, dtype=float))
            g = np.asarray(g, dtype=float).reshape(-1)
            if G.ndim != 2 or G.shape[1] != self.dim or g.size != G.shape[0]:
                raise ValueError(f"obstacle (G, g) must have shapes (m, {self.dim}) and (m,)")
            faces.append((G, g + inflate * np.linalg.norm(G, axis=1)))
        if faces:
            n_faces = max(G.shape[0] for G, _ in faces)
            self._G = np.zeros((len(faces), n_faces, self.dim))
            self._h = np.full((len(faces), n_faces), np.inf)  # padding: 0 < inf always holds
            for k, (G, h) in enumerate(faces):
                self._G[k, : G.shape[0]] = G
                self._h[k, : G.shape[0]] = h

    def points_valid(self, points: np.ndarray) -> np.ndarray:
        """Validity of each row of ``points`` (m, d)."""
        points = np.atleast_2d(np.asarray(points, dtype=float))
        ok = np.all((points >= self.lower) & (points <= self.upper), axis=1)
        if self._G is not None:
            inside = np.all(np.einsum("kfd,md->mkf", self._G, points) < self._h, axis=2)
            ok &= ~np.any(inside, axis=1)
        return ok

    def point_valid(self, p: np.ndarray) -> bool:
        """Validity of one position (the hot path of the planner's state checks)."""
        if (p < self.lower).any() or (p > self.upper).any():
            return False
        if self._G is None:
            return True
        return not (self._G @ p < self._h).all(axis=1).any()

    def path_valid(self, path: np.ndarray) -> bool:
        """Whether a polyline is valid at the motion-check resolution.

        Each segment is split into ``ceil(length / step)`` pieces, exactly the states OMPL's
        discrete motion validator would test, and every vertex is tested as well.
        """
        path = np.atleast_2d(np.asarray(path, dtype=float))
        if path.shape[0] == 1:
            return bool(self.points_valid(path)[0])
        seg = np.diff(path, axis=0)
        counts = np.maximum(1, np.ceil(np.linalg.norm(seg, axis=1) / self.step)).astype(int)
        owner = np.repeat(np.arange(seg.shape[0]), counts)
        first = np.repeat(np.cumsum(counts) - counts, counts)
        frac = (np.arange(owner.size) - first) / counts[owner]
        samples = np.vstack([path[owner] + frac[:, None] * seg[owner], path[-1:]])
        return bool(np.all(self.points_valid(samples)))

    def ompl_checker(self) -> Callable[[ob.State], bool]:
        """A plain callable for ``SpaceInformation.setStateValidityChecker``."""
        dim = self.dim
        valid = self.point_valid

        def check(state: ob.State) -> bool:
            return valid(np.array([state[i] for i in range(dim)]))

        return check


def ompl_seed(seed: int) -> int:
    """Map any integer to OMPL's valid seed range [1, 2**32 - 1] (0 is rejected by OMPL)."""
    return int(seed) % 0xFFFFFFFF + 1


def simplify_path(si: ob.SpaceInformation, path: og.PathGeometric) -> None:
    """Shorten ``path`` in place by OMPL's simplifier, one deterministic pass at a time, at most
    ``_SIMPLIFY_PASSES`` and only while a pass still gains ``_SIMPLIFY_MIN_GAIN`` of the length
    (an unbounded simplification would depend on the machine's speed)."""
    simplifier = og.PathSimplifier(si)
    one_pass = ob.plannerAlwaysTerminatingCondition()  # atLeastOnce=True: exactly one pass
    length = path.length()
    for _ in range(_SIMPLIFY_PASSES):
        simplifier.simplify(path, one_pass, True)
        new_length = path.length()
        if new_length > length * (1.0 - _SIMPLIFY_MIN_GAIN):
            break
        length = new_length


def _derived_seed(seed: int, agent_id: int, counter: int) -> int:
    """A per-(agent, call) seed, a deterministic function of the base seed only."""
    entropy = [int(seed) % 2**64, int(agent_id) % 2**64, int(counter)]
    return ompl_seed(int(np.random.SeedSequence(entropy).generate_state(1, np.uint32)[0]))


def _to_point(x: np.ndarray, dim: int, name: str) -> np.ndarray:
    p = np.asarray(x, dtype=float).reshape(-1)
    if p.size != dim or not np.all(np.isfinite(p)):
        raise ValueError(f"{name} must be a finite vector of length {dim}")
    return p


def _path_array(path: og.PathGeometric, dim: int) -> np.ndarray:
    return np.array([[s[i] for i in range(dim)] for s in path.getStates()], dtype=float)


def _plan(
    validity: _Validity,
    start: np.ndarray,
    goal: np.ndarray,
    seed: int,
    time_budget: float,
    planner: str,
) -> np.ndarray | None:
    """Plan, simplify and interpolate one path; see :func:`plan_path`."""
    dim = validity.dim
    start = _to_point(start, dim, "start")
    goal = _to_point(goal, dim, "goal")
    planner = planner.lower()
    if planner not in _PLANNERS:
        raise ValueError(f"planner must be one of {_PLANNERS}, got {planner!r}")
    time_budget = float(time_budget)
    if not time_budget > 0:
        raise ValueError("time_budget must be > 0")
    # An invalid endpoint has no valid path to it: OMPL would refuse it anyway (INVALID_START /
    # INVALID_GOAL), so answer None right away instead of logging through OMPL.
    if not (validity.point_valid(start) and validity.point_valid(goal)):
        return None
    if np.linalg.norm(goal - start) <= _SAME_POINT:
        return np.vstack([start, goal])

    previous_level = ou.getLogLevel()
    ou.setLogLevel(ou.LOG_NONE)
    try:
        # Reseeding after OMPL has created generators reseeds the seed generator (OMPL logs an
        # error saying it is not deterministic, but the generators created after it are).
        ou.RNG.setSeed(ompl_seed(seed))
        space = ob.RealVectorStateSpace(dim)
        bounds = ob.RealVectorBounds(dim)
        for i in range(dim):
            bounds.setLow(i, float(validity.lower[i]))
            bounds.setHigh(i, float(validity.upper[i]))
        space.setBounds(bounds)
        space.setLongestValidSegmentFraction(validity.step / space.getMaximumExtent())
        si = ob.SpaceInformation(space)
        si.setStateValidityChecker(validity.ompl_checker())
        si.setup()

        setup = og.SimpleSetup(si)
        # si.allocState() states are owned by Python; space.allocState() ones leak.
        s_start, s_goal = si.allocState(), si.allocState()
        for i in range(dim):
            s_start[i] = float(start[i])
            s_goal[i] = float(goal[i])
        setup.setStartAndGoalStates(s_start, s_goal)
        setup.setPlanner(og.RRTConnect(si) if planner == "rrtconnect" else og.RRT(si))
        setup.solve(time_budget)
        if not setup.haveExactSolutionPath():
            return None

        path = og.PathGeometric(setup.getSolutionPath())
        raw_path = og.PathGeometric(path)
        raw_path.interpolate()
        raw = _path_array(raw_path, dim)
        simplify_path(si, path)
        path.interpolate()
        waypoints = _path_array(path, dim)
    finally:
        ou.setLogLevel(previous_level)

    # Never hand out a path that fails the check (the B-spline smoothing step of the simplifier
    # only repairs states, not motions): fall back to the planner's raw, motion-checked path.
    for candidate in (waypoints, raw):
        candidate[0], candidate[-1] = start, goal
        if validity.path_valid(candidate):
            return candidate
    return None


def plan_path(
    start: np.ndarray,
    goal: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    obstacles: Obstacles,
    inflate: float,
    seed: int,
    time_budget: float = 0.05,
    planner: str = "rrtconnect",
) -> np.ndarray | None:
    """Plan a collision-free position path with OMPL, for an initial guess.

    Parameters
    ----------
    start, goal : (d,) array, d = 2 or 3
        End points of the path.
    lower, upper : (d,) array
        Workspace box.
    obstacles : sequence of (G, g)
        Convex polytopes ``{p : G p <= g}``.
    inflate : float
        Required clearance to every obstacle (see the module docstring for the exact check).
    seed : int
        Seed of OMPL's generators: the same seed gives the same path.
    time_budget : float
        Planner time limit in seconds (setup and simplification come on top, both small).
    planner : {"rrtconnect", "rrt"}
        OMPL planner.

    Returns
    -------
    (n, d) array or None
        Simplified and interpolated waypoints (spacing at most the motion-check step), first
        row exactly ``start`` and last row exactly ``goal``; ``None`` if no exact solution was
        found in the budget, or if ``start`` or ``goal`` is itself invalid (outside the workspace
        or within ``inflate`` of an obstacle) -- no planning is attempted then, nothing raises.
    """
    validity = _Validity(lower, upper, obstacles, inflate)
    return _plan(validity, start, goal, seed, time_budget, planner)


def time_parametrize(
    path: np.ndarray,
    start_state: np.ndarray,
    dt: float,
    horizon: int,
    speed: float,
    model: AgentModel | None = None,
) -> np.ndarray:
    """Turn a waypoint path into a state guess moving along it at constant speed.

    Parameters
    ----------
    path : (n, d) array
        Waypoints; if ``path[0]`` is not the current position it is prepended.
    start_state : (s,) array
        Current state of ``model``; it is row 0 of the result, unchanged.
    dt : float
        Sampling time (> 0).
    horizon : int
        Number of steps N (>= 0); the result has N + 1 rows.
    speed : float
        Constant speed along the path (>= 0).
    model : AgentModel, optional
        The agent model whose states the guess is made of (:meth:`AgentModel.state_at` of each
        position and velocity); None: the double integrator, states ``[position, velocity]``.

    Returns
    -------
    (horizon + 1, s) array
        Row k is the state at the position at arc length ``min(speed * k * dt, L)`` with velocity
        ``speed`` times the unit tangent, and zero velocity once the end of the path is
        reached (the position then stays at the last waypoint). Consecutive positions are
        therefore at most ``speed * dt`` apart.
    """
    path = np.atleast_2d(np.asarray(path, dtype=float))
    dim = path.shape[1]
    dt, speed = float(dt), float(speed)
    horizon = operator.index(horizon)
    if not dt > 0 or horizon < 0 or not speed >= 0:
        raise ValueError("need dt > 0, horizon >= 0 and speed >= 0")
    model = _model_or_default(model, dim, dt)
    state = np.asarray(start_state, dtype=float).reshape(-1)
    if state.size != model.state_dim:
        raise ValueError(f"start_state must have length {model.state_dim} for a path of dimension {dim}")
    if path.shape[0] == 0:
        raise ValueError("path must have at least one waypoint")
    positions, velocities = _along_path(np.vstack([model.position(state), path]), dt, horizon, speed)
    out = model.state_at(positions, velocities)
    out[0] = state
    return out


def _model_or_default(model: AgentModel | None, dim: int, dt: float) -> AgentModel:
    """``model``, or the double integrator (states [position, velocity]) when None."""
    return model if model is not None else make_model("double_integrator", dim, dt)


def _along_path(points: np.ndarray, dt: float, horizon: int, speed: float) -> tuple[np.ndarray, np.ndarray]:
    """Positions and velocities (horizon + 1, d) at constant ``speed`` along the polyline ``points``
    from its first point (see :func:`time_parametrize`)."""
    seg = np.diff(points, axis=0)
    lengths = np.linalg.norm(seg, axis=1)
    keep = lengths > _SAME_POINT  # drop repeated points (incl. path[0] == current position)
    seg, lengths = seg[keep], lengths[keep]
    points = np.vstack([points[:1], points[1:][keep]])

    positions = np.zeros((horizon + 1, points.shape[1]))
    velocities = np.zeros_like(positions)
    travelled = speed * dt * np.arange(horizon + 1)
    if seg.shape[0] == 0:
        positions[:] = points[0]
    else:
        cum = np.concatenate([[0.0], np.cumsum(lengths)])
        done = travelled >= cum[-1]
        arc = np.minimum(travelled, cum[-1])
        idx = np.clip(np.searchsorted(cum, arc, side="right") - 1, 0, seg.shape[0] - 1)
        frac = (arc - cum[idx]) / lengths[idx]
        positions[:] = points[idx] + frac[:, None] * seg[idx]
        velocities[:] = speed * seg[idx] / lengths[idx, None]
        positions[done] = points[-1]
        velocities[done] = 0.0
    return positions, velocities


def straight_line_guess(
    start_state: np.ndarray,
    goal_pos: np.ndarray,
    dt: float,
    horizon: int,
    speed: float,
    model: AgentModel | None = None,
) -> np.ndarray:
    """State guess (horizon + 1, s) along the straight line to the goal, ignoring obstacles.

    Same shape and conventions as :func:`time_parametrize` (row 0 is the real state, ``model``
    None the double integrator), so it is a drop-in fallback when planning fails.
    """
    goal = np.asarray(goal_pos, dtype=float).reshape(1, -1)
    return time_parametrize(goal, start_state, dt, horizon, speed, model)  # from the current position


class RRTGuess:
    """Per-agent RRT initial guesses for the MPC loop, reusing paths while they stay valid.

    Built once per scenario (obstacle arrays are preprocessed once), queried at every MPC step.
    An agent's previous path is reused when its goal is unchanged and the path, cut at the
    waypoint nearest to the current position and prefixed by that position, still passes the
    validity check (if the agent is already past that waypoint along the path, the cut is at the
    next one, so the guess never steps back). Otherwise a fresh plan is made, with a seed derived
    from the base seed, the agent id and a per-agent call counter, so identical runs give
    identical guesses.

    Parameters
    ----------
    lower, upper, obstacles, inflate, time_budget, planner
        As in :func:`plan_path`.
    seed : int
        Base seed.
    """

    def __init__(
        self,
        lower: np.ndarray,
        upper: np.ndarray,
        obstacles: Obstacles,
        inflate: float,
        seed: int = 0,
        time_budget: float = 0.05,
        planner: str = "rrtconnect",
    ) -> None:
        self._validity = _Validity(lower, upper, obstacles, inflate)
        self._seed = int(seed)
        self._time_budget = float(time_budget)
        self._planner = planner
        if planner.lower() not in _PLANNERS:
            raise ValueError(f"planner must be one of {_PLANNERS}, got {planner!r}")
        if not self._time_budget > 0:
            raise ValueError("time_budget must be > 0")
        self._paths: dict[int, np.ndarray] = {}
        self._goals: dict[int, np.ndarray] = {}
        self._calls: dict[int, int] = {}
        self._fresh = 0
        self._reused = 0
        self._failed = 0

    @property
    def dim(self) -> int:
        """Position dimension d."""
        return self._validity.dim

    @property
    def stats(self) -> dict[str, int]:
        """Counts of fresh plans, reuses and failed fresh plans (a subset of the fresh ones)."""
        return {"fresh": self._fresh, "reused": self._reused, "failed": self._failed}

    def _reusable(self, agent_id: int, pos: np.ndarray, goal: np.ndarray) -> np.ndarray | None:
        """The remaining part of the agent's stored path from ``pos``, or None if not reusable."""
        path = self._paths.get(agent_id)
        if path is None or not np.allclose(self._goals[agent_id], goal, rtol=0.0, atol=1e-9):
            return None
        k = int(np.argmin(np.linalg.norm(path - pos, axis=1)))
        # Already past the nearest waypoint along the path: head to the next one, not back.
        if k + 1 < path.shape[0] and np.dot(pos - path[k], path[k + 1] - path[k]) > 0:
            k += 1
        rest = path[k:]
        if np.linalg.norm(rest[0] - pos) <= _SAME_POINT and rest.shape[0] > 1:
            rest = rest[1:]
        candidate = np.vstack([pos, rest])
        return candidate if self._validity.path_valid(candidate) else None

    def path_for(
        self, agent_id: int, start_pos: np.ndarray, goal_pos: np.ndarray
    ) -> np.ndarray | None:
        """Waypoints (n, d) from ``start_pos`` to ``goal_pos``, reused or freshly planned.

        Returns None when a fresh plan fails (see :func:`plan_path`; a plan between valid
        endpoints that runs out of time is retried once with 4x the budget, and counts as one
        plan); the stored path of the agent is then dropped, so the next call plans again.
        """
        dim = self._validity.dim
        pos = _to_point(start_pos, dim, "start_pos")
        goal = _to_point(goal_pos, dim, "goal_pos")
        counter = self._calls.get(agent_id, 0)
        self._calls[agent_id] = counter + 1

        reused = self._reusable(agent_id, pos, goal)
        if reused is not None:
            self._reused += 1
            self._paths[agent_id] = reused
            return reused.copy()

        self._fresh += 1
        seed = _derived_seed(self._seed, agent_id, counter)
        path = _plan(self._validity, pos, goal, seed, self._time_budget, self._planner)
        if path is None and self._validity.point_valid(pos) and self._validity.point_valid(goal):
            # Valid endpoints, so the wall-clock budget ran out, which a loaded machine can do to a
            # plan that is quick on an idle core: one retry, same seed, RETRY_FACTOR x budget.
            path = _plan(self._validity, pos, goal, seed, _RETRY_FACTOR * self._time_budget, self._planner)
        if path is None:
            self._failed += 1
            self._paths.pop(agent_id, None)
            self._goals.pop(agent_id, None)
            return None
        self._paths[agent_id] = path
        self._goals[agent_id] = goal
        return path.copy()

    def line_of_sight(self, start_pos: np.ndarray, goal_pos: np.ndarray) -> bool:
        """Whether the straight segment between two points is valid (clear of inflated obstacles)."""
        dim = self._validity.dim
        a = _to_point(start_pos, dim, "start_pos")
        b = _to_point(goal_pos, dim, "goal_pos")
        return bool(self._validity.path_valid(np.vstack([a, b])))

    def waypoint(
        self, agent_id: int, start_pos: np.ndarray, goal_pos: np.ndarray, lookahead: float
    ) -> np.ndarray | None:
        """The point ``lookahead`` metres along the agent's path (the goal if nearer), or None."""
        path = self.path_for(agent_id, start_pos, goal_pos)
        if path is None:
            return None
        lengths = np.linalg.norm(np.diff(path, axis=0), axis=1)
        travelled = np.concatenate([[0.0], np.cumsum(lengths)])
        if travelled[-1] <= lookahead:
            return path[-1].copy()
        k = int(np.searchsorted(travelled, lookahead) - 1)
        fraction = (lookahead - travelled[k]) / max(lengths[k], 1e-12)
        return path[k] + fraction * (path[k + 1] - path[k])

    def guess(
        self,
        agent_id: int,
        start_state: np.ndarray,
        goal_pos: np.ndarray,
        dt: float,
        horizon: int,
        speed: float,
        model: AgentModel | None = None,
    ) -> np.ndarray | None:
        """State guess (horizon + 1, s) of ``model`` (None: the double integrator) along the
        agent's path, or None if planning failed.

        Row 0 is ``start_state``; fall back to :func:`straight_line_guess` on None.
        """
        state = np.asarray(start_state, dtype=float).reshape(-1)
        model = _model_or_default(model, self._validity.dim, dt)
        if state.size != model.state_dim:
            raise ValueError(f"start_state must have length {model.state_dim}")
        path = self.path_for(agent_id, model.position(state), goal_pos)
        if path is None:
            return None
        return time_parametrize(path, state, dt, horizon, speed, model)
