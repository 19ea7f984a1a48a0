"""Per-step initial-guess strategies for the closed loop (straight, shifted, RRT, auto), the
waypoints that steer agents round static obstacles, and the cars' SE(2) routes behind their RRT
guesses and waypoints."""

from __future__ import annotations

import numpy as np

from swarmpc.config import Scenario
from swarmpc.formulation.footprint_ocp import FootprintAgent, OrientedBody
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.car import KinematicCar
from swarmpc.model.footprint import polygon_distance, polygon_vertices
from swarmpc.model.geometry import inflate_polytope
from swarmpc.simulation.disturbance import planner_bodies
from swarmpc.solvers.base import SHIFT_TOLERANCE, PlanStep
from swarmpc.solvers.car_guess import PLANNER_ITERATIONS, car_guess, car_path
from swarmpc.solvers.footprint_central import straight_guess
from swarmpc.solvers.guesses import nominal_speed
from swarmpc.solvers.registry import agent_settings
from swarmpc.solvers.rrt import RRTGuess, straight_line_guess

CAR_BUDGET_FACTOR = 200.0
"""A car's SE(2) plan may take this many times ``solver.rrt_time_budget`` (a point's budget; 10 s
by default). It is a guard for a stalled machine, not the search's end: the planner's iterations
(:data:`~swarmpc.solvers.car_guess.PLANNER_ITERATIONS`) end a search well within it, so a car's
guess, and the run, do not depend on the machine's load. A search round the ``parking`` bays
takes seconds on a slow machine, simplification included, so a limit near that cut searches
short whenever the machine was busy."""
CAR_RETRY_FACTOR = 4
"""A car plan that found nothing is retried once with this many times its planner iterations and
time limit (a narrow passage a short search misses)."""
CAR_CLEARANCE = 0.9
"""A car's path keeps this fraction of d_min from the obstacles, so that a pose the hard form
keeps exactly d_min away is still a valid start."""
CAR_OFF_PATH = 1.0
"""A car whose reference point is farther than this many footprint lengths from its place on its
stored path is off it (it went round another car, or a detour took it away): its path is planned
afresh from where it is. Closer, the stored path is reused, so that the waypoints along it do not
jump from step to step."""


def waypoint_lookahead(settings: OCPSettings) -> float:
    """How far ahead along its path [m] an agent steered round obstacles is given its waypoint:
    1.5 times what it covers in one horizon at its nominal speed."""
    return 1.5 * nominal_speed(settings) * settings.horizon * settings.dt


class CarRoutes:
    """The cars' SE(2) paths (:func:`~swarmpc.solvers.car_guess.car_path`), planned once per goal
    and followed from where the car is at every later call.

    A path is planned around the scenario's static obstacles with the footprint's exact clearance
    (:data:`CAR_CLEARANCE` d_min), the whole footprint inside the workspace, and stored with its
    goal pose; it is planned again when the car's goal changes, or from where the car is when the
    car is off it (:data:`CAR_OFF_PATH`). A plan that finds nothing is retried once with
    :data:`CAR_RETRY_FACTOR` times the iterations and time limit; when the retry finds nothing
    either (a goal walled in, which a sampling planner cannot tell from an unlucky search, or a
    start or goal pose the check refuses), the failure is stored as well, so the car keeps the
    straight-line guess and its true goal until its goal changes instead of searching in vain at
    every step. The seed of a plan is derived from the scenario's seed, the agent and how many
    plans the agent has had, so identical runs plan identical paths.

    Following a stored path: the car's progress along it only moves forwards (a path that
    reverses out of a bay passes the same places twice). From the pose of the path last reached,
    the nearest pose ahead (position, plus the heading difference times the wheelbase) is the
    car's place on the path; when the car is already past it, the next one. The guess's path
    (:meth:`path`) then runs from the car's own pose straight to that pose and on along the rest;
    that first chord is not checked against the obstacles (the MPC's constraints hold the
    trajectory clear, the guess only gives it a side to pass on). The waypoint (:meth:`waypoint`)
    is the pose a given arc length beyond that place, where the MPC is steered while the car's
    straight way to its goal is blocked (:meth:`blocked`).

    Parameters
    ----------
    scn
        The scenario: workspace, obstacles, d_min, seed and ``solver.rrt_time_budget``.
    """

    def __init__(self, scn: Scenario) -> None:
        self.bounds = scn.bounds()
        self.obstacles = scn.obstacle_halfspaces()
        self.clearance = CAR_CLEARANCE * scn.d_min
        self.seed = scn.seed
        self.time_limit = CAR_BUDGET_FACTOR * scn.solver.rrt_time_budget
        self._vertices = [polygon_vertices(G, g) for G, g in self.obstacles]
        self._routes: dict[int, tuple[np.ndarray, np.ndarray | None]] = {}  # agent: (goal pose, path)
        self._progress: dict[int, int] = {}  # agent: index of the path pose last reached
        self._plans: dict[int, int] = {}  # agent: number of plans made
        self._stats = {"fresh": 0, "reused": 0, "failed": 0}

    @property
    def stats(self) -> dict[str, int]:
        """Counts of fresh plans, reuses of a stored one and failed fresh plans (a subset of the fresh)."""
        return dict(self._stats)

    def _plan(self, agent: int, model: KinematicCar, pose: np.ndarray, goal: np.ndarray) -> np.ndarray | None:
        """A fresh path from ``pose`` to ``goal`` (retried once with a longer search), or None."""
        count = self._plans.get(agent, 0)
        self._plans[agent] = count + 1
        entropy = [self.seed % 2**64, agent, count]
        seed = int(np.random.SeedSequence(entropy).generate_state(1, np.uint32)[0])
        path = None
        for factor in (1, CAR_RETRY_FACTOR):
            path = car_path(model, pose, goal, self.obstacles, self.bounds, self.clearance, seed,
                            factor * self.time_limit, iterations=factor * PLANNER_ITERATIONS)
            if path is not None:
                break
        self._stats["fresh"] += 1
        self._stats["failed"] += path is None
        return path

    def _store(self, agent: int, model: KinematicCar, pose: np.ndarray, target: np.ndarray) -> np.ndarray | None:
        """Plan afresh from ``pose`` to ``target``, store the result (a failure too) and reset the
        car's progress along it."""
        path = self._plan(agent, model, pose, target)
        self._routes[agent], self._progress[agent] = (target, path), 0
        return path

    def _nearest(self, agent: int, model: KinematicCar, pose: np.ndarray, path: np.ndarray) -> int:
        """Index of the car's place on ``path``: from the pose last reached on, the nearest pose
        (position, plus the heading difference times the wheelbase, so that a path passing the
        same spot twice in other directions is told apart), or the next one when the car is
        already past it."""
        start = self._progress[agent]
        ahead = path[start:]
        gaps = np.linalg.norm(ahead[:, :2] - pose[:2], axis=1) + model.wheelbase * np.abs(
            np.remainder(ahead[:, 2] - pose[2] + np.pi, 2 * np.pi) - np.pi)
        k = start + int(np.argmin(gaps))
        if k + 1 < len(path) and np.dot(pose[:2] - path[k, :2], path[k + 1, :2] - path[k, :2]) > 0:
            k += 1
        return k

    def _located(self, agent: int, model: KinematicCar, state: np.ndarray,
                 goal: np.ndarray) -> tuple[np.ndarray, int] | None:
        """The car's path to ``goal[:3]`` and the index of its place on it (:meth:`_nearest`), or
        None when the plan found nothing. The stored path is reused; it is planned afresh from the
        car's pose when its goal changed, or when the car is off it: its reference point farther
        than :data:`CAR_OFF_PATH` footprint lengths from its place on the path."""
        pose, target = np.asarray(state[:3], float), np.asarray(goal[:3], float)
        stored = self._routes.get(agent)
        if stored is None or not np.allclose(stored[0], target, rtol=0.0, atol=1e-9):
            path = self._store(agent, model, pose, target)
        else:
            path = stored[1]
            if path is None:
                self._stats["reused"] += 1
                return None
            k = self._nearest(agent, model, pose, path)
            if np.linalg.norm(path[k, :2] - pose[:2]) <= CAR_OFF_PATH * model.length:
                self._stats["reused"] += 1
                self._progress[agent] = k
                return path, k
            path = self._store(agent, model, pose, target)
        if path is None:
            return None
        return path, 0

    def path(self, agent: int, model: KinematicCar, state: np.ndarray, goal: np.ndarray) -> np.ndarray | None:
        """Poses (n, 3) from the car's pose ``state[:3]`` to its goal pose ``goal[:3]`` along its
        stored path (:meth:`_located`), or None when the plan found nothing."""
        located = self._located(agent, model, state, goal)
        if located is None:
            return None
        path, k = located
        pose = np.asarray(state[:3], float)
        rest = path[k:]
        if np.linalg.norm(rest[0, :2] - pose[:2]) <= 1e-12 and len(rest) > 1:
            rest = rest[1:]
        return np.vstack([pose, rest])

    def _clear(self, model: KinematicCar, pose: np.ndarray, targets: np.ndarray) -> np.ndarray:
        """Whether the straight way from ``pose`` (3,) to each of the poses ``targets`` (n, 3) is
        clear (n,): the segment between the footprint's centres, grown by its half diagonal and
        the paths' clearance, keeps off every obstacle (:meth:`blocked`)."""
        ends = np.vstack([pose[None], targets])
        centres = model.pose(np.column_stack([ends, np.zeros(len(ends))]))[:, :2]
        segments = np.stack([np.broadcast_to(centres[0], centres[1:].shape), centres[1:]], axis=1)
        reach = 0.5 * float(np.hypot(*model.footprint)) + self.clearance
        clear = np.ones(len(targets), bool)
        for vertices in self._vertices:
            clear &= polygon_distance(segments, vertices) >= reach
        return clear

    def blocked(self, model: KinematicCar, state: np.ndarray, goal: np.ndarray) -> bool:
        """Whether a static obstacle blocks the car's straight way to its goal pose: the segment
        from its footprint's centre now to the centre at the goal, grown by the footprint's half
        diagonal and the paths' clearance, meets an obstacle.

        The grown segment holds the whole footprint at every heading while the centre runs along
        the segment, so "clear" is sound: however the car turns on the way, a footprint whose
        centre keeps to the line keeps the clearance. The test is conservative near walls: a goal
        less than a half diagonal from an obstacle (a bay) is always "blocked", and a car bound
        there follows its path to the end, where the path's end is the goal (:meth:`waypoint`)."""
        pose, target = np.asarray(state[:3], float), np.asarray(goal[:3], float)
        return not self._clear(model, pose, target[None])[0]

    def waypoint(self, agent: int, model: KinematicCar, state: np.ndarray, goal: np.ndarray,
                 lookahead: float) -> np.ndarray | None:
        """The car's goal state (4,) for this step along its path to ``goal`` (:meth:`_located`),
        at rest with the path's heading there: the path's pose ``lookahead`` metres of arc length
        beyond the car's place on it, or, when the car's straight way (:meth:`_clear`) to a
        later pose of the path is clear, the last such pose; ``goal`` itself (at rest) when less
        than ``lookahead`` of the path is left; None when the plan found nothing.

        The later visible pose skips the stretches of a sampled path that only wander in the
        open (a Reeds-Shepp path round the parking bays loops and reverses in the aisle): the
        path is needed only where obstacles block the straight way."""
        located = self._located(agent, model, state, goal)
        if located is None:
            return None
        path, k = located
        rest = path[k:]
        lengths = np.linalg.norm(np.diff(rest[:, :2], axis=0), axis=1)
        travelled = np.concatenate([[0.0], np.cumsum(lengths)])
        if travelled[-1] <= lookahead:
            return np.append(np.asarray(goal[:3], float), 0.0)
        j = int(np.searchsorted(travelled, lookahead)) - 1
        visible = np.flatnonzero(self._clear(model, np.asarray(state[:3], float), rest))
        if visible.size and travelled[visible[-1]] > lookahead:
            return np.append(rest[visible[-1]], 0.0)
        fraction = (lookahead - travelled[j]) / max(lengths[j], 1e-12)
        return np.append(rest[j] + fraction * (rest[j + 1] - rest[j]), 0.0)


class GuessProvider:
    """Builds every agent's (N+1, n) state guess (states of the settings' agent model) at each MPC
    step.

    * ``straight``: straight line to the goal at a reachable speed;
    * ``shifted``: the agent's previous plan moved one step forward (straight at the start);
    * ``rrt``: an OMPL RRT-Connect path around the static obstacles grown by the agent's body
      (as the planner holds it) and by 0.9 d_min;
    * ``auto``: shifted while the agent's previous solve succeeded, otherwise RRT when the
      scenario has static obstacles and straight when it has none.

    With ``rrt`` and ``auto`` the RRT path also steers: while static obstacles block the straight
    line to an agent's goal, the MPC tracks a waypoint ``lookahead`` metres along the path
    (:meth:`goals`), so a short horizon is not trapped in front of a wall. The RRT state guess is
    then taken along the path to the agent's route goal (the goal :meth:`goals` was given), not to
    the moving waypoint, so the stored path is reused from step to step instead of re-planned.

    A car (``agents[].model: car``) is guessed with its own model: shifted as above; where the
    point agents get RRT guesses (``rrt``, and ``auto`` with static obstacles), along its SE(2)
    path around the obstacles within its turning limit (:class:`CarRoutes`, driven by
    :func:`~swarmpc.solvers.car_guess.car_guess` at 80% of the speed limit, within the
    acceleration limit); otherwise, and whenever its SE(2) plan found nothing, along the straight
    line heading where it goes (:func:`~swarmpc.solvers.footprint_central.straight_guess`).
    A car with an SE(2) path is steered along it as well: while a static obstacle blocks the
    straight way for its footprint (:meth:`CarRoutes.blocked`), its MPC goal is the path's pose
    ``lookahead`` metres (arc length) beyond its place on the path, with the path's heading there,
    at rest (:meth:`CarRoutes.waypoint`); with the way clear, or without a path, its true goal.
    Its state guess, too, follows the path to its route goal, not to the waypoint.
    """

    def __init__(self, scn: Scenario, settings: OCPSettings, strategy: str | None = None) -> None:
        self.strategy = strategy or scn.solver.initial_guess
        self.settings = settings
        self.speed = nominal_speed(settings)
        self._planners: list[RRTGuess] = []
        self._rrt_of: list[RRTGuess] = []  # per agent: the planner of its body
        uses_rrt = self.strategy == "rrt" or (self.strategy == "auto" and scn.obstacles)
        if uses_rrt:
            self._rrt_of = self._body_planners(scn)
        self.lookahead = waypoint_lookahead(settings)
        self._route: np.ndarray | None = None  # the goals given to the last goals() call
        self._cars: list[FootprintAgent | None] = [None] * scn.num_agents  # per agent: a car's own settings
        self._car_routes: CarRoutes | None = None  # the cars' SE(2) paths, with the RRT guesses only
        if scn.has_cars:
            self._cars = [FootprintAgent(s) if isinstance(s.model, OrientedBody) else None
                          for s in agent_settings(scn)]
            if uses_rrt:
                self._car_routes = CarRoutes(scn)

    def _body_planners(self, scn: Scenario) -> list[RRTGuess]:
        """One RRT planner per body size, around the obstacles grown by that body (the planner's
        bodies, tightening included) so that a path the centre follows keeps the whole body clear;
        0.9 d_min on top: positions the hard form keeps exactly d_min away stay valid starts.
        Returns each agent's planner."""
        lower, upper = scn.bounds()
        obstacles = scn.obstacle_halfspaces()
        planners: dict[bytes, RRTGuess] = {}
        of_agent = []
        for body in planner_bodies(scn):
            key = body.tobytes()
            if key not in planners:
                grown = [(G, inflate_polytope(G, g, body)) for G, g in obstacles]
                planners[key] = RRTGuess(lower, upper, grown, inflate=0.9 * scn.d_min, seed=scn.seed,
                                         time_budget=scn.solver.rrt_time_budget)
            of_agent.append(planners[key])
        self._planners = list(planners.values())
        return of_agent

    @property
    def rrt_stats(self) -> dict[str, int] | None:
        """The RRT planners' counts (fresh, reused, failed), summed over the body sizes and the
        cars' SE(2) plans."""
        if not self._planners:
            return None
        stats = [planner.stats for planner in self._planners]
        if self._car_routes is not None:
            stats.append(self._car_routes.stats)
        return {key: sum(s[key] for s in stats) for key in stats[0]}

    def _car_guess(self, agent: int, car: FootprintAgent, state: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """A car's state guess (N+1, 4): along its SE(2) path (:class:`CarRoutes`); the straight
        guess when it gets no SE(2) planning (no RRT guesses in this scenario, a model other than
        the kinematic car) or when its plan found nothing."""
        s, model = car.settings, car.settings.model
        if self._car_routes is None or not isinstance(model, KinematicCar):
            return straight_guess(car, state, goal)
        if self._route is not None and agent < len(self._route):
            goal = self._route[agent]  # plan (and reuse) towards the route goal, not the waypoint
        path = self._car_routes.path(agent, model, state, goal)
        if path is None:
            return straight_guess(car, state, goal)
        states, _ = car_guess(model, state, goal[:3], path, s.horizon, s.dt, speed=nominal_speed(s),
                              accel=model.accel_limit(s.accel))
        return states

    def _fresh(self, agent: int, state: np.ndarray, goal: np.ndarray) -> np.ndarray:
        s, model = self.settings, self.settings.model
        car = self._cars[agent]
        if car is not None:
            return self._car_guess(agent, car, state, goal)
        if self._rrt_of:
            if self._route is not None and agent < len(self._route):
                goal = self._route[agent]  # plan (and reuse) towards the route goal, not the waypoint
            guess = self._rrt_of[agent].guess(agent, state, model.position(goal), s.dt, s.horizon, self.speed, model)
            if guess is not None:
                return guess
        return straight_line_guess(state, model.position(goal), s.dt, s.horizon, self.speed, model)

    def goals(self, states: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """This step's MPC goals: an RRT waypoint for agents whose straight line is blocked, a
        pose along its SE(2) path for a car whose straight way is blocked (:meth:`_car_goal`)."""
        if not self._rrt_of:
            return goals
        model = self.settings.model
        self._route = goals.copy()
        out = goals.copy()
        for i, (state, goal) in enumerate(zip(states, goals, strict=True)):
            car = self._cars[i]
            if car is not None:
                out[i] = self._car_goal(i, car, state, goal)
                continue
            here, there = model.position(state), model.position(goal)
            if self._rrt_of[i].line_of_sight(here, there):
                continue
            waypoint = self._rrt_of[i].waypoint(i, here, there, self.lookahead)
            if waypoint is not None:
                out[i] = model.state_at(waypoint)  # at rest there
        return out

    def _car_goal(self, agent: int, car: FootprintAgent, state: np.ndarray, goal: np.ndarray) -> np.ndarray:
        """A car's MPC goal this step: while its straight way is blocked for its footprint
        (:meth:`CarRoutes.blocked`), the pose along its SE(2) path ``lookahead`` ahead
        (:meth:`CarRoutes.waypoint`; the car's own horizon and speed set it, as
        :attr:`lookahead` does for the point agents); otherwise, or without a path, ``goal``."""
        s, model = car.settings, car.settings.model
        routes = self._car_routes
        if routes is None or not isinstance(model, KinematicCar) or not routes.blocked(model, state, goal):
            return goal
        waypoint = routes.waypoint(agent, model, state, goal, waypoint_lookahead(s))
        return goal if waypoint is None else waypoint

    def guesses(self, states: np.ndarray, goals: np.ndarray, previous: PlanStep | None) -> np.ndarray:
        """(M, N+1, n) guesses for measured ``states`` (M, n).

        A car with an SE(2) route (:class:`CarRoutes`) is guessed fresh only where ``auto`` would
        guess it fresh (the first step, a failed step, a state off its plan): the solvers that
        take cars start from their own shifted answer while they have one, so a car's fresh guess
        is used only there, and a goal the deadlock rules move at every step is not re-planned at
        every step.
        """
        out = []
        for i, (state, goal) in enumerate(zip(states, goals, strict=True)):
            shifts = self.strategy in ("shifted", "auto") or (
                self._car_routes is not None and self._cars[i] is not None)
            if (
                shifts
                and previous is not None
                and np.allclose(previous.states[i, 1], state, atol=SHIFT_TOLERANCE)
                and not previous.fallback[i]
            ):
                plan = previous.states[i]
                out.append(np.vstack([plan[1:], plan[-1:]]))
            elif self.strategy == "straight" and self._cars[i] is None:
                s = self.settings
                out.append(straight_line_guess(state, s.model.position(goal), s.dt, s.horizon, self.speed, s.model))
            else:
                out.append(self._fresh(i, state, goal))
        return np.array(out)
