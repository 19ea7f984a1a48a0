"""Per-step initial-guess strategies for the closed loop (straight, shifted, RRT, auto)."""

from __future__ import annotations

import numpy as np

from swarmpc.config import Scenario
from swarmpc.formulation.footprint_ocp import FootprintAgent, OrientedBody
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.geometry import inflate_polytope
from swarmpc.simulation.disturbance import planner_bodies
from swarmpc.solvers.base import SHIFT_TOLERANCE, PlanStep
from swarmpc.solvers.footprint_central import straight_guess
from swarmpc.solvers.guesses import nominal_speed
from swarmpc.solvers.registry import agent_settings
from swarmpc.solvers.rrt import RRTGuess, straight_line_guess


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

    A car (``agents[].model: car``) is guessed with its own model: shifted as above, otherwise
    along the straight line heading where it goes
    (:func:`~swarmpc.solvers.footprint_central.straight_guess`); the RRT plans points, so it
    guesses and steers the point agents only.
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
        self.lookahead = 1.5 * self.speed * settings.horizon * settings.dt
        self._route: np.ndarray | None = None  # the goals given to the last goals() call
        self._cars: list[FootprintAgent | None] = [None] * scn.num_agents  # per agent: a car's own settings
        if scn.has_cars:
            self._cars = [FootprintAgent(s) if isinstance(s.model, OrientedBody) else None
                          for s in agent_settings(scn)]

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
        """The RRT planners' counts (fresh, reused, failed), summed over the body sizes."""
        if not self._planners:
            return None
        stats = [planner.stats for planner in self._planners]
        return {key: sum(s[key] for s in stats) for key in stats[0]}

    def _fresh(self, agent: int, state: np.ndarray, goal: np.ndarray) -> np.ndarray:
        s, model = self.settings, self.settings.model
        car = self._cars[agent]
        if car is not None:
            return straight_guess(car, state, goal)
        if self._rrt_of:
            if self._route is not None and agent < len(self._route):
                goal = self._route[agent]  # plan (and reuse) towards the route goal, not the waypoint
            guess = self._rrt_of[agent].guess(agent, state, model.position(goal), s.dt, s.horizon, self.speed, model)
            if guess is not None:
                return guess
        return straight_line_guess(state, model.position(goal), s.dt, s.horizon, self.speed, model)

    def goals(self, states: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """This step's MPC goals: an RRT waypoint for agents whose straight line is blocked."""
        if not self._rrt_of:
            return goals
        model = self.settings.model
        self._route = goals.copy()
        out = goals.copy()
        for i, (state, goal) in enumerate(zip(states, goals, strict=True)):
            here, there = model.position(state), model.position(goal)
            if self._cars[i] is not None or self._rrt_of[i].line_of_sight(here, there):
                continue
            waypoint = self._rrt_of[i].waypoint(i, here, there, self.lookahead)
            if waypoint is not None:
                out[i] = model.state_at(waypoint)  # at rest there
        return out

    def guesses(self, states: np.ndarray, goals: np.ndarray, previous: PlanStep | None) -> np.ndarray:
        """(M, N+1, n) guesses for measured ``states`` (M, n)."""
        out = []
        for i, (state, goal) in enumerate(zip(states, goals, strict=True)):
            if (
                self.strategy in ("shifted", "auto")
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
