"""Initial guesses for the MPC solvers: states, inputs and OBCA certificates.

A guess is an (N+1, 2d) state trajectory per agent whose first row is the measured state. From it
the inputs follow (velocity differences) and the certificates lambda follow from geometry, so a
solver is seeded with a primal point that is consistent in every block.
"""

from __future__ import annotations

import numpy as np

from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.geometry import box_certificate, polytope_certificate


def inputs_from_states(states: np.ndarray, settings: OCPSettings) -> np.ndarray:
    """Accelerations (N, d) that reproduce the guessed velocities, clipped to the limits."""
    d = settings.dim
    accel = np.diff(states[:, d:], axis=0) / settings.dt
    if settings.accel is not None:
        accel = np.clip(accel, -settings.accel, settings.accel)
    return accel


def pair_certificates(offsets: np.ndarray, half_size: np.ndarray) -> np.ndarray:
    """Box certificates (2d, K) for offsets (K, d) between two agents."""
    return np.array([box_certificate(q, half_size) for q in offsets]).T


def obstacle_certificates(positions: np.ndarray, G: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Polytope certificates (rows of G, K) for positions (K, d)."""
    return np.array([polytope_certificate(p, G, g) for p in positions]).T


def nominal_speed(settings: OCPSettings) -> float:
    """The speed a guess travels at: 80% of the speed limit, else 1 m/s."""
    return 0.8 * settings.speed if settings.speed is not None else 1.0


def agent_guess_blocks(tag: str, states: np.ndarray, settings: OCPSettings) -> dict[str, np.ndarray]:
    """Primal guess of one agent's own blocks: X, U and its static-obstacle certificates."""
    first = settings.first_constrained_step
    blocks = {f"X{tag}": states.T, f"U{tag}": inputs_from_states(states, settings).T}
    for n, (G, g) in enumerate(settings.obstacles):
        blocks[f"L{tag}_o{n}"] = obstacle_certificates(states[first:, : settings.dim], G, g)
    return blocks
