"""Built-in scenarios, selectable by name (``swarmpc scenarios`` lists them).

* ``paper-2d`` / ``paper-3d``: the paper's setting (M = 4, N = 10, dt = 0.1, Q = 0.1 I, R = I,
  Qf = I). The paper gives no positions; here four agents start at the corners of a 3 m square
  (2D) or at alternate corners of a 3 m cube around z = 1.5 (3D) and swap diagonally, so all
  four paths cross at the centre, the hardest case for a 4-agent swap.
* ``circle``: M agents on a circle (2D) or a sphere (3D, Fibonacci points) swapping antipodally.
* ``random``: seeded random starts and goals in a box, at least 0.5 m apart.
* ``wall-door``: a wall with a door between two groups that swap sides.
* ``pillars``: agents crossing a field of pillars.
* ``u-trap``: a U-shaped trap in front of a goal; the straight line leads into it.
* ``intersection``: eight cars through a four-way crossing, two per arm, going straight or turning.
* ``mixed``: cars and point robots crossing in the plane.
* ``parking``: cars leaving and entering bays between short dividers along an aisle.
* ``crossing``: M cars queued on the four arms of a crossing go straight across (the car family of
  ``swarmpc bench``).

Every generator declares its arguments in its signature (all take ``seed``, the scenario's seed,
which ``random`` and ``spread`` also draw their points from); :func:`builtin_scenario` refuses
any other argument and any value out of range before the generator runs.
"""

from __future__ import annotations

import inspect
import numbers
from collections.abc import Callable
from types import MappingProxyType
from typing import Any

import numpy as np

from swarmpc.config import (
    MAX_AGENTS,
    MAX_MAGNITUDE,
    MAX_SEED,
    Scenario,
    ScenarioError,
    scenario_from_dict,
    short_repr,
)
from swarmpc.model.geometry import box_signed_distance

PAPER = {"dt": 0.1, "horizon": 10, "weights": {"Q": 0.1, "R": 1.0, "Qf": 1.0}, "stop": {"max_steps": 600},
         "deadlock": {"keep_right_deg": 0.0}}
"""The paper's setting, weights included: paper-2d and paper-3d reproduce it as published (and
swap-2d, paper-2d with the Riccati terminal weight, keeps its crossing as well: four agents
keeping right at the crossing took longer than without, docs/lab/controller.md)."""
CONTROL = {"dt": 0.1, "horizon": 10, "stop": {"max_steps": 600}}
"""Every other built-in: the paper's sample period and horizon with the default weights
(``Qf: lqr``, :class:`swarmpc.config.Weights`)."""


def paper_2d(delta: float = 0.3, seed: int = 0) -> dict[str, Any]:
    corners = [[-1.5, -1.5], [1.5, -1.5], [1.5, 1.5], [-1.5, 1.5]]
    agents = [{"start": corners[i], "goal": corners[(i + 2) % 4]} for i in range(4)]
    return {"name": "paper-2d", "dim": 2, **PAPER, "delta": delta, "seed": seed,
            "workspace": {"lower": [-3.0, -3.0], "upper": [3.0, 3.0]}, "agents": agents}


TUNED_WEIGHTS = {"Q": 0.1, "R": 1.0, "Qf": "lqr"}
"""The paper's stage weights with the terminal weight from the Riccati equation (docs/tuning.md):
the MPC is then the LQR wherever no constraint binds, so agents stop at their goals instead of
sailing past them, at the paper's control effort and with fewer ADMM iterations on this swap
than the default Q = 0.2."""


def swap_2d(delta: float = 0.3, seed: int = 0) -> dict[str, Any]:
    """The paper's 2D swap flown with the Riccati terminal weight instead of the paper's Qf = I."""
    return {**paper_2d(delta, seed), "name": "swap-2d", "weights": TUNED_WEIGHTS}


def paper_3d(delta: float = 0.3, seed: int = 0) -> dict[str, Any]:
    corners = [[-1.5, -1.5, 0.5], [1.5, -1.5, 2.5], [1.5, 1.5, 0.5], [-1.5, 1.5, 2.5]]
    agents = [
        {"start": corners[i], "goal": [-corners[i][0], -corners[i][1], 3.0 - corners[i][2]]}
        for i in range(4)
    ]
    return {"name": "paper-3d", "dim": 3, **PAPER, "delta": delta, "seed": seed,
            "workspace": {"lower": [-3.0, -3.0, 0.0], "upper": [3.0, 3.0, 3.0]}, "agents": agents}


def circle(agents: int = 8, dim: int = 2, radius: float | None = None, delta: float = 0.3,
           seed: int = 0) -> dict[str, Any]:
    m = int(agents)
    if dim == 2:
        r = radius or max(2.0, 1.2 * m * delta / np.pi + 0.5)
        angles = 2 * np.pi * np.arange(m) / m
        points = np.stack([r * np.cos(angles), r * np.sin(angles)], axis=1)
        center = np.zeros(2)
    else:
        r = radius or max(2.0, np.sqrt(m) * delta + 0.5)
        k = np.arange(m) + 0.5
        polar = np.arccos(1 - 2 * k / m)
        azimuth = np.pi * (1 + 5**0.5) * k
        points = r * np.stack(
            [np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], axis=1
        )
        center = np.array([0.0, 0.0, r + 0.5])
    starts = points + center
    goals = -points + center
    bound = r + 1.0
    lower = (center - bound).tolist()
    upper = (center + bound).tolist()
    return {"name": f"circle-{m}" if dim == 2 else f"sphere-{m}", "dim": dim, **CONTROL,
            "delta": delta, "seed": seed, "workspace": {"lower": lower, "upper": upper},
            "agents": [{"start": s.round(6).tolist(), "goal": g.round(6).tolist()}
                       for s, g in zip(starts, goals, strict=True)],
            "stop": {"max_steps": 600}}


SWARM_SOLVER = {"tol": 5e-3}
"""ADMM settings of the swarm families (``random``, ``spread``): a consensus tolerance of 5 mm
instead of 1 mm. In a dense swarm the stop waits for the slowest group of coupled agents, so a
looser tolerance saves the iterations spent polishing its consensus, which barely move the agents.
Safety does not rest on the tolerance: the stop also requires the flown plans of coupled agents to
keep d_min / 2 apart. The paper's scenarios keep 1 mm, so the paper reproduction is unchanged.
Evidence: docs/lab/admm.md, "Consensus tolerance and the stop's check on the flown plans"."""


def random_swarm(agents: int = 8, dim: int = 3, seed: int = 0, delta: float = 0.3,
                 min_gap: float = 0.5, clearance: float = 0.1, box_scale: float = 1.0) -> dict[str, Any]:
    """Seeded random starts and goals in a 3 x 3 (x 2) m box, pairwise >= ``min_gap`` apart.

    ``box_scale`` stretches every side of the box (the floor stays at z = 0.2) and the step cap
    with it, since the paths grow as long.

    Every pair also leaves ``clearance`` (Euclidean) between one point and the other's delta box:
    two goals closer than the OBCA separation d_min (0.05 m by default) can never both be held, and
    Euclidean spacing alone allows that (offset (0.31, 0.31, 0.26) is 0.51 m long but 0.014 m from
    the box).

    More agents than :func:`packing_bound` allows are refused at once; below it, the sampler gives
    up after 200 000 draws.
    """
    rng = np.random.default_rng(seed)
    lower = np.array([-1.5 * box_scale, -1.5 * box_scale, 0.2][:dim])
    upper = np.array([1.5 * box_scale, 1.5 * box_scale, 0.2 + 2.0 * box_scale][:dim])
    half = np.full(dim, delta)

    def spaced(p: np.ndarray, others: np.ndarray) -> bool:  # from every point drawn so far at once
        offsets = p - others
        return bool(np.all(np.linalg.norm(offsets, axis=1) >= min_gap)
                    and np.all(box_signed_distance(offsets, half) >= clearance))

    apart = max(delta + (clearance / np.sqrt(dim) if clearance > 0 else clearance), min_gap / np.sqrt(dim))
    if agents > packing_bound(upper - lower - 0.2, apart):  # at once, not after 200 000 draws
        raise ScenarioError(f"agents: {agents} agents do not fit {min_gap} m apart in the random box")

    def sample() -> np.ndarray:
        points, count = np.empty((agents, dim)), 0
        for _attempt in range(200000):
            p = rng.uniform(lower + 0.1, upper - 0.1)
            if spaced(p, points[:count]):
                points[count], count = p, count + 1
                if count == agents:
                    return points
        raise ScenarioError(f"agents: {agents} agents do not fit {min_gap} m apart in the random box")

    starts, goals = sample(), sample()
    return {"name": f"random-{dim}d-{agents}-s{seed}", "dim": dim, **CONTROL, "delta": delta,
            "seed": seed, "limits": {"accel": 1.0}, "solver": dict(SWARM_SOLVER),
            "workspace": {"lower": lower.round(4).tolist(), "upper": upper.round(4).tolist()},
            "agents": [{"start": s.round(4).tolist(), "goal": g.round(4).tolist()}
                       for s, g in zip(starts, goals, strict=True)],
            "stop": {"goal_tolerance": 0.1, "max_steps": int(np.ceil(600 * max(box_scale, 1.0)))}}


def packing_bound(sides: np.ndarray, spacing: float) -> int:
    """At most how many points fit in a box with these ``sides`` when every pair differs by at
    least ``spacing`` along some axis (infinity-norm distance): cells of side ``spacing`` tile the
    box, floor(side / spacing) + 1 along each axis, and two points in one half-open cell are closer
    than ``spacing``.

    A pair of ``random_swarm``'s points is ``min_gap`` apart (Euclidean), so at least
    min_gap / sqrt(d) along some axis, and a point is ``clearance`` from the other's delta box,
    so at least delta + clearance / sqrt(d) along some axis (delta + clearance for a clearance <= 0).
    """
    if spacing <= 0:
        return np.iinfo(np.int64).max
    return int(np.prod(np.floor(np.asarray(sides, float) / spacing) + 1))


SPREAD_DENSITY_AGENTS = 8
"""The ``spread`` family keeps the density of ``random`` with this many agents."""


def spread_swarm(agents: int = 16, dim: int = 3, seed: int = 0, delta: float = 0.3) -> dict[str, Any]:
    """``random`` at a constant density: the box grows with the swarm so that every agent has the
    room it has in the 3 x 3 x 2 m box with 8 agents (side x (M / 8)^(1/d)).

    A fixed box gets denser as M grows, and every agent's neighbourhood with it; this family holds
    the neighbourhoods steady, so it shows how the solver's work grows with M alone.
    """
    scale = (agents / SPREAD_DENSITY_AGENTS) ** (1.0 / dim)
    spec = random_swarm(agents=agents, dim=dim, seed=seed, delta=delta, box_scale=scale)
    return {**spec, "name": f"spread-{dim}d-{agents}-s{seed}"}


def wall_door(delta: float = 0.2, seed: int = 0) -> dict[str, Any]:
    """A wall across x = 0 with a 1.2 m door at y in [-0.6, 0.6]; two agents swap sides."""
    return {"name": "wall-door", "dim": 2, **CONTROL, "delta": delta, "seed": seed,
            "workspace": {"lower": [-3.0, -3.0], "upper": [3.0, 3.0]},
            "obstacles": [{"box": {"center": [0.0, 1.8], "half_size": [0.15, 1.2]}},
                          {"box": {"center": [0.0, -1.8], "half_size": [0.15, 1.2]}}],
            "agents": [{"start": [-2.0, 1.5], "goal": [2.0, 1.5]},
                       {"start": [2.0, -1.5], "goal": [-2.0, -1.5]}],
            "stop": {"max_steps": 600}}


def pillars(delta: float = 0.2, seed: int = 0) -> dict[str, Any]:
    """Four agents crossing a 3 x 3 grid of square pillars."""
    obstacles = [{"box": {"center": [x, y], "half_size": [0.2, 0.2]}}
                 for x in (-1.0, 0.0, 1.0) for y in (-1.0, 0.0, 1.0)]
    agents = [{"start": [-2.5, -0.5], "goal": [2.5, 0.5]}, {"start": [2.5, -0.5], "goal": [-2.5, 0.5]},
              {"start": [-0.5, -2.5], "goal": [0.5, 2.5]}, {"start": [0.5, 2.5], "goal": [-0.5, -2.5]}]
    return {"name": "pillars", "dim": 2, **CONTROL, "delta": delta, "seed": seed,
            "workspace": {"lower": [-3.0, -3.0], "upper": [3.0, 3.0]},
            "obstacles": obstacles, "agents": agents, "stop": {"max_steps": 600}}


def u_trap(delta: float = 0.2, seed: int = 0) -> dict[str, Any]:
    """A U open towards the start sits between the agent and its goal: straight guesses stall."""
    obstacles = [{"box": {"center": [0.5, 0.0], "half_size": [0.1, 1.0]}},
                 {"box": {"center": [-0.1, 0.9], "half_size": [0.5, 0.1]}},
                 {"box": {"center": [-0.1, -0.9], "half_size": [0.5, 0.1]}}]
    return {"name": "u-trap", "dim": 2, **CONTROL, "delta": delta, "seed": seed,
            "workspace": {"lower": [-3.0, -3.0], "upper": [3.0, 3.0]},
            "obstacles": obstacles,
            "agents": [{"start": [-2.0, 0.0], "goal": [2.0, 0.0]}],
            "stop": {"max_steps": 600}}


CARS: dict[str, Any] = {
    "dt": 0.1, "horizon": 20, "solver": {"method": "centralized"},
    "weights": {"Q": [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.05, 0.0], [0.0, 0.0, 0.0, 0.1]],
                "R": 1.0, "Qf": 20.0},
    "limits": {"accel": 1.0, "speed": 1.0},
    "stop": {"goal_tolerance": 0.1, "heading_tolerance_deg": 10.0, "max_steps": 400},
}
"""The built-ins with cars: a 2 s horizon (a car needs room to turn), stage weights light on the
heading and the speed (a car corrects a sideways offset only by turning away from its goal
heading for a while), a numeric terminal weight
(the car has no linearisation for ``Qf: lqr``), the centralised solver (``solver.method: admm``
flies them by consensus ADMM), 1 m/s and 1 m/s^2, and goals held to 10 cm and 10 degrees."""


def _car(start: list[float], goal: list[float]) -> dict[str, Any]:
    return {"model": "car", "start": start, "goal": goal}


def _rotated(pose: tuple[float, float, float], quarter: int) -> list[float]:
    """``pose`` [x, y, heading_deg] turned by ``quarter`` right angles about the origin."""
    x, y, heading = pose
    for _ in range(quarter):
        x, y = -y, x
    return [round(x, 6), round(y, 6), float((heading + 90 * quarter + 180) % 360 - 180)]


def intersection(delta: float = 0.3, seed: int = 0) -> dict[str, Any]:
    """Eight cars through a four-way crossing of two 3 m roads, right-hand traffic (lanes 0.75 m
    right of the centre lines): on every arm the front car turns right and the one behind goes
    straight across; the four arms are the same, turned by right angles. A straight car ends in
    the lane a turning car entered before it, so it stops short of that car's goal."""
    arm = [((-3.0, -0.75, 0.0), (-0.75, -4.5, -90.0)), ((-4.5, -0.75, 0.0), (3.0, -0.75, 0.0))]
    agents = [_car(_rotated(start, q), _rotated(goal, q)) for q in range(4) for start, goal in arm]
    return {"name": "intersection", "dim": 2, **CARS, "horizon": 15, "delta": delta, "seed": seed,
            "workspace": {"lower": [-6.0, -6.0], "upper": [6.0, 6.0]}, "agents": agents}


def mixed(delta: float = 0.3, seed: int = 0) -> dict[str, Any]:
    """Two cars and two point robots cross in the plane: the cars swap ends of an east-west
    road, the robots cross it north-south between them."""
    agents = [
        _car([-3.0, -0.4, 0.0], [3.0, -0.4, 0.0]),
        _car([3.0, 0.4, 180.0], [-3.0, 0.4, 180.0]),
        {"start": [-0.5, -2.5], "goal": [0.5, 2.5]},
        {"start": [0.5, 2.5], "goal": [-0.5, -2.5]},
    ]
    return {"name": "mixed", "dim": 2, **CARS, "delta": delta, "seed": seed,
            "workspace": {"lower": [-4.0, -4.0], "upper": [4.0, 4.0]}, "agents": agents}


def parking(delta: float = 0.3, seed: int = 0) -> dict[str, Any]:
    """A row of four bays 0.8 m wide (a car is 0.45 m wide and 0.7 m long) between 0.7 m dividers
    along the bottom edge of a car park, opening on a one-way aisle to the east. Two cars drive in
    along the aisle and turn nose-first into the two western bays, the second passing behind the
    first as it turns in; two cars parked facing the aisle drive out of the two eastern bays and
    leave eastwards.

    The straight line out of a bay runs into the divider beside it, so every car starts from its
    SE(2) path (``initial_guess: rrt``) and is steered along it while its straight way is blocked
    (:meth:`~swarmpc.simulation.guessing.CarRoutes.waypoint`). The steering weight is a tenth of the other car
    built-ins' (a car squares up in a bay only by steering hard over a short distance), and the
    keep-right rule is off (one-way traffic; a turned goal points into the dividers). Flown by
    ADMM (``solver.method: admm``), of each coupled pair only the later car holds a copy of the
    other (``solver.admm.pair_copies: later``), the earlier car yielding only through the
    consensus. By ADMM every car parks, with either setting, at the centralised run's cost; without
    the steering along the paths the two cars entering the western bays ended up in each other's
    way (docs/lab/cars.md#parking-car-waypoints, #parking-admm-probe)."""
    bays = [-1.2, -0.4, 0.4, 1.2]
    dividers = [{"box": {"center": [x, 0.35], "half_size": [0.05, 0.35]}} for x in (-1.6, -0.8, 0.0, 0.8, 1.6)]
    agents = [
        _car([-2.2, 2.2, 0.0], [bays[0], 0.75, -90.0]),
        _car([-3.2, 2.2, 0.0], [bays[1], 0.75, -90.0]),
        _car([bays[2], 0.25, 90.0], [3.8, 3.0, 0.0]),
        _car([bays[3], 0.25, 90.0], [3.8, 2.2, 0.0]),
    ]
    weights = {**CARS["weights"], "R": [[1.0, 0.0], [0.0, 0.1]]}
    return {"name": "parking", "dim": 2, **CARS, "weights": weights, "delta": delta, "seed": seed,
            "solver": {**CARS["solver"], "initial_guess": "rrt", "admm": {"pair_copies": "later"}},
            "deadlock": {"keep_right_deg": 0.0},
            "workspace": {"lower": [-3.5, 0.0], "upper": [4.5, 3.8]}, "obstacles": dividers, "agents": agents}


CROSSING_LEAD = 3.0
"""Distance [m] from the centre of the crossing to the rear axle of the first car of an arm (and to
the nearest goal beyond it); the roads are 3 m wide, so it leaves 1.5 m before the crossing."""
CROSSING_GAP = 1.5
"""Spacing [m] of the cars queued on an arm and of the goals on an outbound lane (a car is 0.7 m
long, so 0.8 m lies between two queued cars)."""


def crossing(agents: int = 8, delta: float = 0.3, seed: int = 0) -> dict[str, Any]:
    """``agents`` cars through a four-way crossing of two 3 m roads, every car going straight
    across, right-hand traffic (lanes 0.75 m right of the centre lines).

    The cars are dealt to the four arms in turn (M/4 per arm when M is a multiple of 4), queued one
    behind the other, ``CROSSING_GAP`` apart, the first ``CROSSING_LEAD`` from the centre. An arm's
    cars leave in the order they queue on the outbound lane across the crossing: the first car
    takes the farthest goal, so no car has to pass another. The four arms are the same, turned by
    right angles, and every car crosses the paths of two others' arms. Straight traffic only, unlike
    ``intersection``: the conflicts (and the work of the solver) then grow with M alone, which
    makes it the car family of ``swarmpc bench``. The step cap grows with the queues.
    """
    m = int(agents)
    per_arm = [m // 4 + (q < m % 4) for q in range(4)]
    longest = max(per_arm)
    agent_list = []
    for q, n in enumerate(per_arm):
        for k in range(n):
            start = (-(CROSSING_LEAD + CROSSING_GAP * k), -0.75, 0.0)
            goal = (CROSSING_LEAD + CROSSING_GAP * (n - 1 - k), -0.75, 0.0)
            agent_list.append(_car(_rotated(start, q), _rotated(goal, q)))
    bound = CROSSING_LEAD + CROSSING_GAP * (longest - 1) + 1.5
    return {"name": f"crossing-{m}", "dim": 2, **CARS, "horizon": 15, "delta": delta, "seed": seed,
            "workspace": {"lower": [-bound, -bound], "upper": [bound, bound]}, "agents": agent_list,
            "stop": {**CARS["stop"], "max_steps": 400 + 50 * (longest - 1)}}


BUILTINS: dict[str, tuple[Callable[..., dict[str, Any]], str]] = {
    "paper-2d": (paper_2d, "the paper's 2D experiment: 4 agents swap diagonal corners of a 3 m square"),
    "paper-3d": (paper_3d, "the paper's 3D experiment: 4 drones swap diagonal corners of a 3 m cube"),
    "swap-2d": (swap_2d, "paper-2d with the terminal weight from the Riccati equation: no overshoot"),
    "circle": (circle, "M agents on a circle swap antipodally (--agents M; dim 3: a sphere)"),
    "random": (random_swarm, "seeded random starts and goals in a 3 x 3 x 2 m box (--agents, --seed)"),
    "spread": (spread_swarm, "random at constant density: the box grows with --agents (8 agents per 3 x 3 x 2 m)"),
    "wall-door": (wall_door, "two agents swap sides through the door of a wall"),
    "pillars": (pillars, "four agents cross a 3 x 3 field of pillars"),
    "u-trap": (u_trap, "a U-shaped trap in front of the goal; the straight line leads into it"),
    "intersection": (intersection, "eight cars through a four-way crossing, two per arm, straight or turning right"),
    "mixed": (mixed, "two cars and two point robots cross in the plane"),
    "parking": (parking, "two cars drive into bays between dividers while two leave the bays beside them"),
    "crossing": (crossing, "M cars queued on the four arms of a crossing go straight across (--agents M, default 8)"),
}


MAX_BOX_SCALE = 100.0
"""Largest ``box_scale`` of the random family (its step cap grows with it)."""

_INTEGER_RANGES = MappingProxyType({"agents": (1, MAX_AGENTS), "dim": (2, 3), "seed": (0, MAX_SEED)})
"""Per integer argument of the generators: (smallest, largest)."""
_REAL_RANGES = MappingProxyType({
    "delta": (False, MAX_MAGNITUDE), "radius": (False, MAX_MAGNITUDE), "min_gap": (False, MAX_MAGNITUDE),
    "clearance": (True, MAX_MAGNITUDE), "box_scale": (False, MAX_BOX_SCALE),
})
"""Per real argument of the generators: (whether 0 is allowed, the largest value)."""


def builtin_parameters(name: str) -> tuple[str, ...]:
    """The arguments the built-in ``name``'s generator takes (its signature is the declaration)."""
    return tuple(inspect.signature(BUILTINS[name][0]).parameters)


def _argument_problem(key: str, value: Any) -> str | None:
    """What is wrong with the value of a generator argument, if anything: integers are integers
    (not booleans) in range, reals are finite numbers in range."""
    if key in _INTEGER_RANGES:
        low, high = _INTEGER_RANGES[key]
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            return f"expected an integer, got {short_repr(value)}"
        if low <= int(value) <= high:
            return None
        allowed = f"{low} or {high}" if high == low + 1 else f"between {low} and {high}"
        return f"must be {allowed}, got {short_repr(value)}"
    zero_allowed, largest = _REAL_RANGES[key]
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        return f"expected a number, got {short_repr(value)}"
    number = int(value) if isinstance(value, numbers.Integral) else float(value)
    if not ((number >= 0 if zero_allowed else number > 0) and number <= largest):  # NaN fails too
        return f"must be {'>=' if zero_allowed else '>'} 0 and <= {largest:g}, got {short_repr(value)}"
    return None


def _checked_arguments(name: str, params: dict[str, Any]) -> dict[str, Any]:
    """The given arguments (None: not given) of built-in ``name``, each known to its generator and
    in range, integers as plain ``int``; raises :class:`ScenarioError` naming the argument."""
    accepted = builtin_parameters(name)
    given = {key: value for key, value in params.items() if value is not None}
    for key, value in given.items():
        label = key if key.isidentifier() else short_repr(key)
        if key not in accepted:
            raise ScenarioError(f"{label}: not an argument of built-in {name!r} (accepts: {', '.join(accepted)})")
        problem = _argument_problem(key, value)
        if problem is not None:
            raise ScenarioError(f"{label}: {problem}")
    return {key: int(value) if key in _INTEGER_RANGES else value for key, value in given.items()}


def builtin_scenario(name: str, **params: Any) -> Scenario:
    """A built-in scenario by name; ``params`` shape its generator (:func:`builtin_parameters`).

    A None value means "not given" (the command line passes agents, dim and seed to every
    built-in); an argument the generator does not take, or a value out of range, is a
    :class:`ScenarioError` naming it, raised before the generator runs.
    """
    if name not in BUILTINS:
        raise ScenarioError(f"scenario: unknown built-in {short_repr(name)} (see 'swarmpc scenarios')")
    factory = BUILTINS[name][0]
    return scenario_from_dict(factory(**_checked_arguments(name, params)), source=name)
