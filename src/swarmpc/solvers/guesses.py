"""Initial guesses for the MPC solvers: states, inputs and OBCA certificates.

A guess is an (N+1, n) state trajectory of the agent model per agent whose first row is the
measured state. From it the inputs follow (the model's
:meth:`~swarmpc.model.agent_model.AgentModel.guess_inputs`: velocity differences for the double
integrator) and the certificates lambda (and soft slacks) follow from geometry
(:mod:`swarmpc.solvers.dual_seed`), so a solver is seeded with a primal point that is
consistent in every block. With ``seed_duals=False`` the certificates are left out and the solver
starts them at 0 (the comparison of both is in docs/lab/initial-guesses.md).
"""

from __future__ import annotations

import numpy as np

from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.geometry import box_certificates
from swarmpc.solvers.dual_seed import obstacle_seed, pair_seed, polytope_certificate


def inputs_from_states(states: np.ndarray, settings: OCPSettings) -> np.ndarray:
    """Inputs (N, m) that reproduce a guessed state trajectory (N+1, n), clipped to the input box
    (for the double integrator: the accelerations of the guessed velocities)."""
    model = settings.model
    lower, upper = model.input_bounds(settings.accel, settings.speed)
    return np.clip(model.guess_inputs(states), lower, upper)


def pair_certificates(offsets: np.ndarray, half_size: np.ndarray) -> np.ndarray:
    """Box certificates (2d, K) for offsets (K, d) between two agents."""
    return box_certificates(offsets, half_size).T


def obstacle_certificates(positions: np.ndarray, G: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Polytope certificates (rows of G, K) for positions (K, d)."""
    return np.array([polytope_certificate(p, G, g) for p in positions]).T


def nominal_speed(settings: OCPSettings) -> float:
    """The speed a guess travels at: 80% of the speed limit, else 1 m/s."""
    return 0.8 * settings.speed if settings.speed is not None else 1.0


def agent_guess_blocks(
    tag: str, states: np.ndarray, settings: OCPSettings, seed_duals: bool = True
) -> dict[str, np.ndarray]:
    """Primal guess of one agent's own blocks: X, U and (``seed_duals``) its static-obstacle
    certificates and soft slacks."""
    first = settings.first_constrained_step
    blocks = {f"X{tag}": states.T, f"U{tag}": inputs_from_states(states, settings).T}
    if seed_duals:
        blocks.update(obstacle_seed(tag, settings.model.position(states[first:]), settings))
    return blocks


def pair_guess_blocks(
    tag: str, offsets: np.ndarray, half_size: np.ndarray, settings: OCPSettings, seed_duals: bool = True
) -> dict[str, np.ndarray]:
    """Certificate (and soft slack) guess of a pair's blocks from guessed offsets (K, d); empty
    without ``seed_duals`` (the solver then starts them at 0)."""
    return pair_seed(tag, offsets, half_size, settings) if seed_duals else {}
