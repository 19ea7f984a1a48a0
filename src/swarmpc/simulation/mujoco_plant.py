"""A physics plant: every agent a rigid body in MuJoCo, driven by force actuators.

The planner's double integrator is an idealisation: inputs act instantly, nothing resists motion,
and an Euler step stands for continuous motion. :class:`MuJoCoPlant` drops those idealisations so a
controller can be tried against a plant it does not model exactly, and so that whether two robots
touched is decided by a physics engine's own contact detection rather than by our own geometry.

The model (MJCF, built in code; :func:`build_mjcf`):

* each agent is a body with one slide joint per axis (x, y in 2D: the body stays in the plane;
  x, y, z in 3D) and a box geom of the agent's body (``agents[].body``, default Δ/2 per axis),
  so two default bodies touch exactly when one centre enters the other's Δ box;
* gravity is off, in 3D too: the commanded acceleration is taken as the net acceleration beyond
  hover, as a drone's thrust controller compensates its weight;
* one force actuator per joint applies ``mass`` × the commanded acceleration, through a
  first-order lag of time constant ``lag_s`` when it is > 0; a joint damping of
  ``mass`` × ``drag`` gives the linear drag;
* box obstacles are box geoms; polytope obstacles are convex meshes of their exact vertices (an
  unbounded polytope is cut far outside where the agents go: the workspace, or the starts' and
  goals' box, grown by its own size plus 1 m on every side; in 2D the shapes are prisms 2 m high);
* agent bodies collide with each other and with obstacles (contype = conaffinity = 1), and the
  physics runs at ``physics_dt`` (dt split into equal substeps).

The bodies' joints realise the double integrator (the scenario's agent model): an agent's state
is its model state at position qpos moving with velocity qvel. MuJoCo is imported only when this
plant is built, so ``import swarmpc`` and double-integrator runs never load it.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Callable
from typing import Any

import numpy as np

from swarmpc.config import PlantConfig, Scenario
from swarmpc.model.geometry import polytope_vertices
from swarmpc.simulation.disturbance import DisturbanceModel
from swarmpc.simulation.plant import checked_inputs

PhysicsHook = Callable[[Any, Any], None]
"""Called as ``hook(model, data)`` after every physics step (MuJoCo's ``MjModel``, ``MjData``)."""

_AXES = ("x", "y", "z")
_FLAT_HALF_HEIGHT = 1.0  # m: half-height of the 2D obstacles' prisms
_BOUNDS_PAD = 1.0  # m: added to how far beyond the workspace an unbounded polytope is cut


def load_mujoco() -> Any:
    """The ``mujoco`` module; ImportError with the install command when it is missing."""
    try:
        import mujoco
    except ImportError:
        raise ImportError("plant.type: mujoco needs the mujoco package (pip install mujoco)") from None
    return mujoco


def physics_substeps(dt: float, physics_dt: float) -> int:
    """Equal physics steps per sampling period, each no longer than ``physics_dt``."""
    return max(1, math.ceil(dt / physics_dt - 1e-9))


def _physics_value(value: float | None, name: str) -> float:
    """A physics field of a ``mujoco`` plant section: its validator fills every one of them, so
    None means a section of another plant type was passed."""
    if value is None:
        raise ValueError(f"plant.{name}: unset (a plant.type: mujoco section fills it from its defaults)")
    return float(value)


def _numbers(values: Any) -> str:
    return " ".join(repr(float(v)) for v in np.ravel(values))


def _lifted(vector: np.ndarray, fill: float) -> np.ndarray:
    """A position or size as three values (2D: ``fill`` for z)."""
    return np.append(vector, fill) if vector.size == 2 else vector


def _add_agent(world: ET.Element, actuators: ET.Element, index: int, position: np.ndarray,
               half: np.ndarray, config: PlantConfig) -> None:
    """Agent ``index``: a body at its start ``position``, a slide joint and a force actuator per
    axis, a box geom."""
    dim = position.size
    name = f"agent{index}"
    body = ET.SubElement(world, "body", name=name, pos=_numbers(_lifted(position, 0.0)))
    mass = _physics_value(config.mass, "mass")
    drag = _physics_value(config.drag, "drag")
    lag = _physics_value(config.lag_s, "lag_s")
    actuator = {"gainprm": repr(mass), "ctrllimited": "false"}
    if lag > 0:
        actuator.update(dyntype="filterexact", dynprm=repr(lag))
    for axis in range(dim):
        joint = f"{name}_{_AXES[axis]}"
        direction = np.eye(3)[axis]
        # ref = the start coordinate: qpos is the world coordinate, and qpos0 puts the agent at its start
        ET.SubElement(body, "joint", name=joint, type="slide", axis=_numbers(direction),
                      ref=repr(float(position[axis])), damping=repr(mass * drag), limited="false")
        ET.SubElement(actuators, "general", attrib={"name": joint, "joint": joint, **actuator})
    size = _lifted(half, float(np.max(half)))
    ET.SubElement(body, "geom", name=name, type="box", size=_numbers(size), mass=repr(mass),
                  contype="1", conaffinity="1")


def _add_obstacles(scn: Scenario, world: ET.Element, asset: ET.Element) -> None:
    """Box obstacles as boxes, polytopes as convex meshes (prisms in 2D); empty polytopes are left out."""
    lower, upper = scn.bounds()
    pad = np.max(upper - lower) + _BOUNDS_PAD
    for n, obstacle in enumerate(scn.obstacles):
        name = f"obstacle{n}"
        if obstacle.box is not None:
            centre = _lifted(np.asarray(obstacle.box.center, float), 0.0)
            half = _lifted(np.asarray(obstacle.box.half_size, float), _FLAT_HALF_HEIGHT)
            ET.SubElement(world, "geom", name=name, type="box", pos=_numbers(centre), size=_numbers(half),
                          contype="1", conaffinity="1")
            continue
        G, g = obstacle.halfspaces(scn.dim)
        vertices = polytope_vertices(G, g, (lower - pad, upper + pad))
        if len(vertices) == 0:
            continue
        if scn.dim == 2:
            vertices = np.vstack([np.c_[vertices, np.full(len(vertices), z)]
                                  for z in (-_FLAT_HALF_HEIGHT, _FLAT_HALF_HEIGHT)])
        ET.SubElement(asset, "mesh", name=name, vertex=_numbers(vertices))
        ET.SubElement(world, "geom", name=name, type="mesh", mesh=name, contype="1", conaffinity="1")


def build_mjcf(scn: Scenario, config: PlantConfig, substeps: int) -> str:
    """The MJCF text of the scenario's agents and obstacles (see the module docstring)."""
    root = ET.Element("mujoco", model=scn.name)
    ET.SubElement(root, "option", timestep=repr(scn.dt / substeps), gravity="0 0 0", integrator="implicitfast")
    asset = ET.SubElement(root, "asset")
    world = ET.SubElement(root, "worldbody")
    actuators = ET.SubElement(root, "actuator")
    model = scn.agent_model()
    for i, (start, half) in enumerate(zip(model.position(scn.start_states(model)), scn.bodies, strict=True)):
        _add_agent(world, actuators, i, start, half, config)
    _add_obstacles(scn, world, asset)
    if not len(asset):
        root.remove(asset)
    return ET.tostring(root, encoding="unicode")


class ContactCounter:
    """Counts, from MuJoCo's own contact list, which bodies touch at each physics step.

    ``agent_contacts`` sums over the physics steps the pairs of agents in contact (several contact
    points of one pair count once); ``obstacle_contacts`` the (agent, obstacle) pairs likewise.
    ``first_agent_contact`` is (physics step, i, j) of the first pair of agents that touched.
    """

    def __init__(self, model: Any, num_agents: int) -> None:
        self.agent_of_geom = np.full(model.ngeom, -1)
        for i in range(num_agents):
            self.agent_of_geom[model.geom(f"agent{i}").id] = i
        self.agent_contacts = 0
        self.obstacle_contacts = 0
        self.first_agent_contact: tuple[int, int, int] | None = None

    def record(self, data: Any, physics_step: int) -> None:
        """Count the contacts MuJoCo found at this physics step (``data.contact[:data.ncon]``)."""
        n = data.ncon
        if n == 0:
            return
        geom1, geom2 = data.contact.geom1[:n], data.contact.geom2[:n]
        a, b = self.agent_of_geom[geom1], self.agent_of_geom[geom2]
        low, high = np.minimum(a, b), np.maximum(a, b)
        both = low >= 0
        pairs = set(zip(low[both].tolist(), high[both].tolist(), strict=True))
        if pairs and self.first_agent_contact is None:
            self.first_agent_contact = (physics_step, *min(pairs))
        self.agent_contacts += len(pairs)
        one = (low < 0) & (high >= 0)
        other = np.where(a >= 0, geom2, geom1)
        self.obstacle_contacts += len(set(zip(high[one].tolist(), other[one].tolist(), strict=True)))


class MuJoCoPlant:
    """The scenario's agents as rigid bodies in MuJoCo (``plant: {type: mujoco}``).

    ``on_physics_step(model, data)`` is called after every physics step (e.g. to read
    ``data.contact``); :attr:`contacts` counts the contacts between bodies as they happen. The
    scenario's ``disturbance`` block applies here too: measurement noise on :meth:`measure`,
    process noise added to the bodies' states after each sampling period.
    """

    nominal = False

    def __init__(self, scn: Scenario, on_physics_step: PhysicsHook | None = None) -> None:
        self.mujoco = load_mujoco()
        self.scenario = scn
        self.config = scn.plant if scn.plant.type == "mujoco" else PlantConfig(type="mujoco")
        self.substeps = physics_substeps(scn.dt, _physics_value(self.config.physics_dt, "physics_dt"))
        self.mjcf = build_mjcf(scn, self.config, self.substeps)
        self.model = self.mujoco.MjModel.from_xml_string(self.mjcf)
        self.data = self.mujoco.MjData(self.model)
        self.on_physics_step = on_physics_step
        self.nominal_model = scn.agent_model()
        self.reset()

    def reset(self) -> np.ndarray:
        """Every body at its start (with the start's velocity), actuators at rest, counters at zero."""
        scn = self.scenario
        self.mujoco.mj_resetData(self.model, self.data)
        model = self.nominal_model
        starts = scn.start_states(model)
        self.data.qpos[:] = model.position(starts).reshape(-1)
        self.data.qvel[:] = model.velocity(starts).reshape(-1)
        self.mujoco.mj_forward(self.model, self.data)
        self.noise = DisturbanceModel.from_scenario(scn)
        self.contacts = ContactCounter(self.model, scn.num_agents)
        self.physics_steps = 0
        states = self.true_states()
        self.last_disturbance = np.zeros_like(states)
        return states

    def true_states(self) -> np.ndarray:
        """(M, n) every agent's state at its joints' qpos moving with their qvel ([p, v])."""
        m, d = self.scenario.num_agents, self.scenario.dim
        return self.nominal_model.state_at(self.data.qpos.reshape(m, d), self.data.qvel.reshape(m, d))

    def measure(self) -> np.ndarray:
        return self.true_states() + self.noise.measurement()

    def step(self, inputs: np.ndarray) -> np.ndarray:
        """Hold ``inputs`` (M, d) for dt over the physics substeps; return the true states."""
        scn = self.scenario
        control = checked_inputs(inputs, scn.num_agents, scn.dim)
        before = self.true_states()
        self.data.ctrl[:] = control.reshape(-1)
        for _ in range(self.substeps):
            self.mujoco.mj_step(self.model, self.data)  # collisions of the step's starting configuration
            self.contacts.record(self.data, self.physics_steps)
            self.physics_steps += 1
            if self.on_physics_step is not None:
                self.on_physics_step(self.model, self.data)
        self._add_process_noise()
        after = self.true_states()
        self.last_disturbance = after - self.nominal_model.step(before, control)
        return after

    def _add_process_noise(self) -> None:
        if not self.scenario.disturbance.has_process_noise:
            return
        model = self.nominal_model
        noise = self.noise.process()
        self.data.qpos[:] += model.position(noise).reshape(-1)
        self.data.qvel[:] += model.velocity(noise).reshape(-1)
        self.mujoco.mj_forward(self.model, self.data)

    def describe(self) -> dict[str, Any]:
        """The plant block, the physics step actually used, and the contacts MuJoCo reported."""
        return {
            **self.config.model_dump(),
            "substeps": self.substeps,
            "mujoco_version": self.mujoco.__version__,
            "agent_contacts": self.contacts.agent_contacts,
            "obstacle_contacts": self.contacts.obstacle_contacts,
        }
