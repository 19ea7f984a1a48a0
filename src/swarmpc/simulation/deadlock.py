"""Deadlock detection and resolution for symmetric encounters.

Agents that meet head-on (or four agents crossing a square) can settle into a symmetric
equilibrium of the MPC: every agent far from its goal, none moving. When an agent has stayed
slow and far from its goal, with another agent in its way, for ``patience`` steps, its goal is
temporarily replaced by a detour point to the right of its goal direction (a right-hand rule:
every blocked agent turns the same way, so a jam unwinds like a roundabout) for ``hold`` steps.

"In its way" means ahead of the agent and within reach of the straight corridor to its goal: some
point of the segment from the agent to its goal is, on every axis, closer to the other agent than
the clearance (delta + d_min) plus ``corridor_margin``. A neighbour merely nearby is not a jam: in a
dense swarm every agent has parked neighbours within a metre, and an agent that overshot a free
goal and brakes slowly past it would otherwise be detoured again and again, circling its goal.

An agent within ``approach_radius`` of its goal that still gets closer by ``min_progress`` per
step is approaching, not jammed, however slowly: with weak stage weights the last metre is crawled
at a few cm/s, often between parked neighbours, and a detour there only pushes the agent away
from its slot again.

An agent stuck alone, more than ``approach_radius`` from its goal (against the corner of a
static obstacle, where the straight line and the OBCA certificate form a local minimum), is
detoured the same way after ``lonely_patience`` steps, without a neighbour in sight.

Large symmetric swaps can fall into a cycle: the same groups of agents detour together, come back
together and jam again. Once an agent has detoured ``escalate_after`` times, its further detours
are de-synchronised: the angle is jittered by up to ``jitter_deg`` and the hold stretched by a
random factor in [1, 1 + ``stretch``], drawn from a generator seeded by the scenario seed, so the
agents of a jam return at different times and pass one by one. Runs whose agents detour fewer
times draw nothing and are unchanged.

An agent within ``approach_radius`` of a goal that no other agent occupies (every other agent at
least the clearance away from it) is not detoured: the MPC brings it in, and a detour there only
sends it round its goal, again each time it slows down next to a parked neighbour. Only an agent
held at rest there by another in its corridor for ``free_goal_patience`` steps is detoured after
all: two agents short of their free goals, each in the other's way, never move on their own.

What is left near the goals are knots: two or three agents each sitting on the next one's goal,
sliding to and fro together. Turning them all right only moves the knot round in its layer. In 3D,
with the workspace known, a cycle of unsettled agents each within the clearance plus
``corridor_margin`` of the previous one's goal (agents parked in their own slots beside it do
not count) is untied instead, as soon as one member has stalled or the members together made
next to no progress to their goals over ``knot_patience`` steps (a pair at rest short of free
goals is spared by the free-goal rule, a pair sliding round each other is not slow, only
stuck). The member lifted least so far (then the one that has gone longest without progress)
climbs (or descends, whichever side has more room) by ``lift`` and heads over its own goal for
at most ``lift_hold`` steps, while the others keep their goals and wait; the layer clears and
each slides into its slot. The lift ends early once the knot has come apart, the member's goal
is free and the straight way to it clear (``release_lifts``): holding it out of the layer after
that only delays it. Where the way out runs into agents parked just over and under the knot (or
the ceiling is too close), the member steps out sideways instead, across the line to its goal,
on the side that keeps farthest from the others: a pair swapping in a layer between parked
agents cannot pass over or under each other, only side by side.

Every threshold is a field of :class:`DeadlockPolicy`, set from a scenario's ``deadlock:`` section
(:class:`swarmpc.config.DeadlockConfig`, which documents each key; ``enabled: false`` switches
the rules off). Why each rule exists: docs/design/reliability.md; the runs that showed what each
changed: docs/lab/admm.md.

The resolver reads states through the agents' :class:`~swarmpc.model.agent_model.AgentModel`
(positions, velocities, detour goals as states at rest), so it works for any state layout, one
model per agent in a mixed swarm. A model with a heading (a car, which cannot side-step) gets
every detour and keep-right goal as a pose at rest *facing the way it is sent*
(:func:`rest_state`): the car drives forwards there along an arc and turns back to its goal
afterwards, instead of being asked to slide sideways.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from swarmpc.model.agent_model import AgentModel, make_model

if TYPE_CHECKING:
    from swarmpc.config import DeadlockConfig


KEEP_RIGHT_PLANE_DEG = 20.0
"""The keep-right angle of 2D swarms when a scenario does not set one (``deadlock.keep_right_deg``)."""


@dataclass(frozen=True)
class DeadlockPolicy:
    """Thresholds of the detector and shape of the detour (m, m/s, steps, degrees).

    The fields are the keys of a scenario's ``deadlock:`` section, with the same names and
    defaults; :class:`swarmpc.config.DeadlockConfig` describes each and bounds its values. A
    scenario's policy is :meth:`from_config` of that section; built directly, the dataclass takes
    the same fields unchecked.
    """

    speed_threshold: float = 0.05
    distance_threshold: float = 0.2
    patience: int = 4
    neighbour_radius: float = 1.0
    hold: int = 15
    detour: float = 1.0
    angle_deg: float = 75.0
    approach_radius: float = 1.0
    lonely_patience: int = 12
    min_progress: float = 0.002
    escalate_after: int = 2
    jitter_deg: float = 30.0
    stretch: float = 2.0
    corridor_margin: float = 0.1
    progress_window: int | None = None
    """Steps over which a blocked agent must get ``window_progress`` closer to its goal, however
    fast it moves, or count as stalled (None: only slow agents stall)."""
    window_progress: float = 0.05
    spare_free_goals: bool = True
    """Never detour an agent within ``approach_radius`` of a goal no other agent occupies (for
    ``free_goal_patience`` steps at rest)."""
    free_goal_patience: int | None = 100
    """Steps an agent at rest short of a free goal, with another agent in its corridor, is spared;
    then it counts as stalled like any other (None: spared for ever). Without a limit, a head-on
    pair short of their free goals, each in the other's corridor, waits for ever; agents that get
    going again on their own are spared far fewer steps than this in a row."""
    untie_knots: bool = True
    """In 3D, resolve a cycle of agents not at their goals, each sitting on the next one's goal, by
    lifting one of them out of the layer (the others wait) instead of turning them all right."""
    lift: float = 0.5
    """How far (m) the lifted member of a knot climbs or descends."""
    lift_hold: int = 40
    """Steps the lift lasts at most, and the other members wait."""
    knot_patience: int | None = 10
    """Steps over which the members of a knot together must get ``knot_progress`` per member and
    step closer to their goals, or the knot is untied without waiting for a member to stall: a
    pair held at rest short of free goals is spared by the free-goal rule, and a pair sliding
    round each other is not slow, only stuck. The knot as a whole counts: one member pushed back
    while the others flow past is no reason to lift anyone. None: a knot waits for a stall."""
    knot_progress: float = 0.005
    """Progress [m per member and step] the members of a knot must make together over
    ``knot_patience`` steps (0.005: the stall speed, 0.05 m/s, at dt = 0.1 s)."""
    release_lifts: bool = True
    """End a lift before ``lift_hold`` runs out as soon as the knot has come apart (no member
    within the clearance plus ``corridor_margin`` of another member's goal), the lifted member's
    own goal is free (every other agent at least the clearance away) and the straight way to it
    clear of the others: holding the member out of its layer then only delays it."""
    side_steps: bool = True
    """When the vertical way out of a knot runs into a parked neighbour, step out sideways instead
    (the axis and side that keep farthest from the others)."""
    keep_right_deg: float | None = None
    """Anticipation: an agent farther than ``approach_radius`` from its goal in traffic (another
    agent in its way, itself farther than ``distance_threshold`` from its goal) steers, from the
    first such step and without waiting to stall, to its goal turned this many degrees to the
    right about itself (same distance): agents meeting near a common point all veer the same way
    and pass like a roundabout, while a neighbour settled in its slot changes nothing. 0: off (only
    stalled agents are detoured). None: :data:`KEEP_RIGHT_PLANE_DEG` in 2D, off in 3D, where
    agents pass over and under each other and turning about the vertical slowed them down."""
    enabled: bool = True
    """False: no agent is ever detoured or lifted; every step's goals are the true ones."""

    @classmethod
    def from_config(cls, config: DeadlockConfig) -> DeadlockPolicy:
        """The policy of a scenario's ``deadlock:`` section, field by field (the names are shared)."""
        return cls(**config.model_dump())


def right_turn(direction: np.ndarray, angle: float) -> np.ndarray:
    """``direction`` rotated clockwise by ``angle`` about the vertical (z) axis.

    In 3D a purely vertical direction is turned about the x axis instead.
    """
    c, s = np.cos(angle), np.sin(angle)
    out = direction.copy()
    if np.linalg.norm(direction[:2]) < 1e-9 and direction.size == 3:
        out[1], out[2] = c * direction[1] + s * direction[2], -s * direction[1] + c * direction[2]
        out[1] = out[1] if np.linalg.norm(out) > 1e-9 else 1.0
        return out
    out[0], out[1] = c * direction[0] + s * direction[1], -s * direction[0] + c * direction[1]
    return out


def rest_state(model: AgentModel, position: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """A goal state at rest at ``position``; a model with a heading (``heading_row``) faces
    ``direction`` there, so that it reaches the point driving forwards."""
    state = model.state_at(np.asarray(position, float))
    row = getattr(model, "heading_row", None)
    if row is not None:
        state[..., row] = np.arctan2(direction[..., 1], direction[..., 0])
    return state


class DeadlockResolver:
    """Tracks stalled agents and hands out the goals the MPC should use this step.

    ``model`` is the agents' model, whose states :meth:`goals` reads and writes; None: the double
    integrator of ``dim`` (only its state layout is used, which does not depend on dt).
    ``models``: one model per agent instead (a swarm with cars); their positions share the
    state's first ``dim`` entries.
    """

    def __init__(
        self, num_agents: int, dim: int, policy: DeadlockPolicy = DeadlockPolicy(), seed: int = 0,
        clearance: float | np.ndarray = 0.35, bounds: tuple[np.ndarray, np.ndarray] | None = None,
        model: AgentModel | None = None, models: tuple[AgentModel, ...] | None = None,
    ) -> None:
        self.policy = policy
        self.dim = dim
        self.model = model if model is not None else make_model("double_integrator", dim, 1.0)
        self.models = models if models is not None else (self.model,) * num_agents
        self.bounds = bounds
        self._lifts = np.zeros(num_agents, int)
        self._waiting = np.zeros(num_agents, int)
        self.clearance = np.broadcast_to(np.asarray(clearance, float), (dim,)).copy()
        self._repeats = np.zeros(num_agents, int)
        self._rng = np.random.default_rng([seed, 0xD1])
        self._distance: np.ndarray | None = None
        self._history: list[np.ndarray] = []
        self._stalled = np.zeros(num_agents, int)
        self._spared = np.zeros(num_agents, int)
        self._detour_left = np.zeros(num_agents, int)
        self._detour_goal: dict[int, np.ndarray] = {}
        self._lifted: dict[int, np.ndarray] = {}
        self._idle = np.zeros(num_agents, int)
        self._recent: list[np.ndarray] = []
        self.events: list[tuple[int, int]] = []
        default = KEEP_RIGHT_PLANE_DEG if dim == 2 else 0.0
        self.keep_right_deg = default if policy.keep_right_deg is None else policy.keep_right_deg
        """The keep-right angle in force (the policy's, or the default of the dimension)."""

    @property
    def active(self) -> np.ndarray:
        return self._detour_left > 0

    def blocked(self, positions: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """Per agent: another agent within ``neighbour_radius`` (inf-norm), ahead of it and within
        the clearance plus ``corridor_margin`` of its straight corridor to the goal."""
        return np.any(self.blockers(positions, goals), axis=1)

    def blockers(self, positions: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """[i, j]: agent j is in agent i's way (see :meth:`blocked`)."""
        p = self.policy
        offsets = positions[None, :] - positions[:, None]  # [i, j] = p_j - p_i
        near = np.max(np.abs(offsets), axis=2) < p.neighbour_radius
        np.fill_diagonal(near, False)
        to_goal = goals - positions
        ahead = np.einsum("ijd,id->ij", offsets, to_goal) > 0
        fractions = np.linspace(0.0, 1.0, 11)
        corridor = positions[:, None, :] + fractions[None, :, None] * to_goal[:, None, :]  # (M, S, d)
        reach = self.clearance + p.corridor_margin
        # [i, j, s]: corridor point s of agent i lies inside agent j's clearance box (+ margin)
        inside = np.all(np.abs(corridor[:, None] - positions[None, :, None]) < reach, axis=3)
        return near & ahead & inside.any(axis=2)

    def in_traffic(self, positions: np.ndarray, goals: np.ndarray, distance: np.ndarray) -> np.ndarray:
        """Per agent: an agent in its way (:meth:`blockers`) is itself on the move to a goal farther
        than ``distance_threshold`` away: traffic to pass, not a neighbour settled in its slot."""
        unsettled = distance > self.policy.distance_threshold
        return np.any(self.blockers(positions, goals) & unsettled[None, :], axis=1)

    @staticmethod
    def _goal_gaps(positions: np.ndarray, goals: np.ndarray, reach: np.ndarray) -> np.ndarray:
        """[i, j]: how far agent j is from goal i, in units of ``reach`` per axis (inf-norm; below 1
        means j sits on i's goal); inf for an agent's own goal."""
        gaps = np.max(np.abs(goals[:, None, :] - positions[None, :, :]) / reach, axis=2)
        np.fill_diagonal(gaps, np.inf)
        return gaps

    def goal_free(self, positions: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """Per agent: its goal could be held now (every other agent at least the clearance away)."""
        return self._goal_gaps(positions, goals, self.clearance).min(axis=1) >= 1.0

    def knots(self, positions: np.ndarray, goals: np.ndarray, unsettled: np.ndarray,
              due: np.ndarray) -> list[np.ndarray]:
        """Cycles of unsettled agents, each sitting on (within the clearance plus ``corridor_margin``
        of) the goal of the one before, with at least one member due for a detour. The other
        members need not be slow: a pair swapping places often slides to and fro together.

        Turning every member right moves the whole knot round in the layer it sits in, and near the
        floor or the ceiling of a dense swarm, with neighbours parked around it, it rarely comes apart.
        """
        if not self.policy.untie_knots or self.dim != 3 or self.bounds is None:
            return []
        gaps = self._goal_gaps(positions, goals, self.clearance + self.policy.corridor_margin)
        gaps[:, ~unsettled] = np.inf  # a neighbour parked in its own slot beside a goal is no part of a knot
        occupant = np.where(gaps.min(axis=1) < 1.0, gaps.argmin(axis=1), -1)
        cycles: list[np.ndarray] = []
        seen: set[int] = set()
        for start in np.flatnonzero(due & (self._detour_left == 0)):
            path: list[int] = []
            node = int(start)
            while node >= 0 and unsettled[node] and node not in path and node not in seen:
                path.append(node)
                node = int(occupant[node])
            seen.update(path)
            if node in path:
                cycles.append(np.array(path[path.index(node):]))
        return cycles

    def _path_room(self, start: np.ndarray, end: np.ndarray, others: np.ndarray) -> float:
        """Smallest gap, in units of the clearance per axis (inf-norm), between the straight path
        from ``start`` to ``end`` and the other agents (below 1: the path runs into one of them)."""
        if others.size == 0:
            return np.inf
        path = start + np.linspace(0.0, 1.0, 11)[:, None] * (end - start)
        return float(np.max(np.abs(path[:, None, :] - others[None]) / self.clearance, axis=2).min())

    def _way_out(self, lifter: int, positions: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """Where the lifted member of a knot heads: over (or under, the roomier side) its own goal,
        or, when that path runs into a parked neighbour, beside its goal on the axis and side whose
        path keeps farthest from the others (a pair swapping in a layer with agents parked just
        above and below both can only pass side by side)."""
        p = self.policy
        lower, upper = self.bounds  # type: ignore[misc]
        here, goal = positions[lifter], goals[lifter]
        others = np.delete(positions, lifter, axis=0)

        def target(axis: int, sign: float) -> tuple[np.ndarray, float]:
            """The point ``lift`` (or as far as the workspace allows) off ``here`` on one axis,
            over the goal on the others, and how far off it is."""
            room = (upper[axis] - here[axis]) if sign > 0 else (here[axis] - lower[axis])
            height = min(p.lift, max(room, 0.0))
            out = goal.copy()
            out[axis] = here[axis] + sign * height
            return out, height

        up = upper[2] - here[2] >= here[2] - lower[2]
        vertical, _ = target(2, 1.0 if up else -1.0)
        best, best_room = vertical, self._path_room(here, vertical, others)
        if best_room >= 1.0 or not p.side_steps:
            return vertical
        along = int(np.argmax(np.abs(goal - here)))
        for axis in (a for a in range(self.dim) if a != along):
            for sign in (1.0, -1.0):
                candidate, height = target(axis, sign)
                if height < self.clearance[axis]:
                    continue  # too close to the wall to get past anyone
                room = self._path_room(here, candidate, others)
                if room > best_room:
                    best, best_room = candidate, room
        return best

    def _untie(self, step: int, cycle: np.ndarray, positions: np.ndarray, goals: np.ndarray) -> None:
        """Lift the knot's member lifted least so far (then the one that has gone longest without
        progress) out of the knot's layer (see ``_way_out``) for at most ``lift_hold`` steps; the
        others wait for their goals to clear."""
        p, model = self.policy, self.model
        lifter = int(cycle[np.lexsort((cycle, -self._idle[cycle], self._lifts[cycle]))[0]])
        way_out = self._way_out(lifter, positions, model.position(goals))
        target = model.state_at(way_out, model.velocity(goals[lifter]))
        self._lifts[lifter] += 1
        self._detour_goal[lifter] = target
        self._detour_left[lifter] = p.lift_hold
        self._stalled[cycle] = 0
        self._waiting[cycle[cycle != lifter]] = p.lift_hold
        self._idle[cycle] = 0
        self._lifted[lifter] = cycle
        self.events.append((step, lifter))

    def _untie_knots(self, step: int, positions: np.ndarray, goals: np.ndarray, distance: np.ndarray,
                     due: np.ndarray) -> None:
        """Untie every knot (:meth:`knots`) with a member due for a detour or, with
        ``knot_patience`` set, whose members together got less than ``knot_progress`` per member
        and step closer to their goals over the last ``knot_patience`` steps: a knot held at rest
        short of free goals (spared by the free-goal rule), or sliding round without progress.
        A knot whose members still flow past each other is left alone. The members of an untied
        knot are no longer ``due`` (in place)."""
        p, window = self.policy, self.policy.knot_patience
        unsettled = distance > p.distance_threshold
        starts, before, needed = due.copy(), None, 0.0
        if window is not None:
            self._recent = [*self._recent[-window:], distance]
            if len(self._recent) > window:
                before, needed = self._recent[0], p.knot_progress * window  # per member
                starts |= unsettled & (self._waiting == 0)
        for cycle in self.knots(positions, self.model.position(goals), unsettled, starts):
            stuck = before is not None and before[cycle].sum() - distance[cycle].sum() < needed * len(cycle)
            if due[cycle].any() or stuck:
                self._untie(step, cycle, positions, goals)
                due[cycle] = False

    def _release_lifts(self, positions: np.ndarray, goals: np.ndarray) -> None:
        """End the lifts whose knot has come apart (no member within the clearance plus
        ``corridor_margin`` of another member's goal) and whose member can go home now: its goal
        is free and the straight way to it clear of every other agent (``release_lifts``). The
        knot's other members stop waiting."""
        if not self._lifted:
            return
        free = self.goal_free(positions, goals)
        gaps = self._goal_gaps(positions, goals, self.clearance + self.policy.corridor_margin)
        for lifter, cycle in list(self._lifted.items()):
            if self._detour_left[lifter] == 0:
                del self._lifted[lifter]
                continue
            apart = gaps[np.ix_(cycle, cycle)].min() >= 1.0
            others = np.delete(positions, lifter, axis=0)
            if apart and free[lifter] and self._path_room(positions[lifter], goals[lifter], others) >= 1.0:
                self._detour_left[lifter] = 0
                self._waiting[cycle] = 0
                del self._lifted[lifter]

    def goals(self, step: int, states: np.ndarray, goals: np.ndarray) -> np.ndarray:
        """Goals for this step: the true ones, or a detour for agents found deadlocked (always the
        true ones when the policy is not ``enabled``)."""
        p, model = self.policy, self.model
        if not p.enabled:
            return goals.copy()
        positions, goal_positions = model.position(states), model.position(goals)
        velocities = np.array([m.velocity(x) for m, x in zip(self.models, states, strict=True)])
        speeds = np.linalg.norm(velocities, axis=1)
        to_goal = goal_positions - positions
        distance = np.linalg.norm(to_goal, axis=1)
        blocked = self.blocked(positions, goal_positions)
        progress = self._distance - distance if self._distance is not None else np.zeros_like(distance)
        self._distance = distance
        approaching = (distance < p.approach_radius) & (progress >= p.min_progress)
        slow = speeds < p.speed_threshold
        if p.progress_window is not None:
            self._history = [*self._history[-p.progress_window:], distance]
            if len(self._history) > p.progress_window:
                # two agents sliding round each other in contact, never quite slow
                slow |= blocked & (distance > self._history[0] - p.window_progress)
        stalled = slow & (distance > p.distance_threshold) & ~approaching
        stalled &= blocked | (distance > p.approach_radius)
        if p.spare_free_goals:
            exempt = (distance < p.approach_radius) & self.goal_free(positions, goal_positions)
            self._spared = np.where(stalled & exempt, self._spared + 1, 0)
            if p.free_goal_patience is not None:
                exempt &= self._spared <= p.free_goal_patience
            stalled &= ~exempt
        self._stalled = np.where(stalled, self._stalled + 1, 0)
        due = np.where(blocked, self._stalled >= p.patience, self._stalled >= p.lonely_patience)
        out = goals.copy()
        if p.release_lifts:
            self._release_lifts(positions, goal_positions)
        self._waiting = np.maximum(self._waiting - 1, 0)
        due &= self._waiting == 0  # a knot's members wait while one of them is lifted out
        idle = (progress < p.min_progress) & (distance > p.distance_threshold)
        self._idle = np.where(idle, self._idle + 1, 0)
        self._untie_knots(step, positions, goals, distance, due)
        for i in np.flatnonzero(due & (self._detour_left == 0)):
            angle, hold = p.angle_deg, p.hold
            if self._repeats[i] >= p.escalate_after:
                # the same agent jammed again: break the symmetry that brought it back
                angle += self._rng.uniform(-p.jitter_deg, p.jitter_deg)
                hold = int(round(hold * self._rng.uniform(1.0, 1.0 + p.stretch)))
            self._repeats[i] += 1
            direction = right_turn(to_goal[i] / distance[i], np.radians(angle))
            waypoint = positions[i] + p.detour * min(1.0, distance[i]) * direction
            target = rest_state(self.models[i], waypoint, direction)  # at rest
            self._detour_goal[int(i)] = target
            self._detour_left[i] = hold
            self._stalled[i] = 0
            self.events.append((step, int(i)))
        if self.keep_right_deg > 0:
            traffic = self.in_traffic(positions, goal_positions, distance)
            self._keep_right(out, positions, to_goal, distance, traffic)
        for i in np.flatnonzero(self._detour_left > 0):
            out[i] = self._detour_goal[int(i)]
            self._detour_left[i] -= 1
        return out

    def _keep_right(self, out: np.ndarray, positions: np.ndarray, to_goal: np.ndarray, distance: np.ndarray,
                    traffic: np.ndarray) -> None:
        """Turn the goals of agents far from their goals in traffic (:meth:`in_traffic`)
        ``keep_right_deg`` to the right about the agent (in place; agents on a detour or waiting in
        a knot keep theirs)."""
        p = self.policy
        veer = traffic & (distance > p.approach_radius) & (self._detour_left == 0) & (self._waiting == 0)
        for i in np.flatnonzero(veer):
            turned = right_turn(to_goal[i], np.radians(self.keep_right_deg))
            out[i] = rest_state(self.models[i], positions[i] + turned, turned)
