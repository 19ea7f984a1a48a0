"""Seeding the OBCA dual certificates (lambda) and soft slacks (alpha) from a state guess.

Every collision constraint carries a certificate lambda >= 0 with ||G^T lambda||_2 <= 1 whose value
(G p - g)^T lambda lower-bounds the distance of p to the polytope {G x <= g} (weak duality); the
best certificate attains the distance. A solver started at lambda = 0 starts with every separation
row violated (value 0 < d_min) and, in the soft form, at a point where the equality
||G^T lambda|| = 1 has a zero gradient. Seeding lambda with the optimal certificate of the GUESSED
positions gives a primal point that is consistent in every block: if the guess keeps its distances,
the seed satisfies every collision row, and a soft slack seeded at max(0, d_min - value) makes the
seed feasible even where the guess cuts through an obstacle.

This module is pure geometry (numpy); the solvers call it where they pack their initial point when
no shifted previous solution exists (first step, after a failure, or when ADMM's neighbour set
changed), controlled by ``solver.seed_duals``.
"""

from __future__ import annotations

import itertools

import numpy as np

from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.geometry import box_certificates

__all__ = [
    "certificate_value",
    "obstacle_seed",
    "pair_seed",
    "polytope_certificate",
]

_TOL = 1e-9


def certificate_value(point: np.ndarray, G: np.ndarray, g: np.ndarray, lam: np.ndarray) -> float:
    """The certified distance (G p - g)^T lambda of a certificate (a lower bound if feasible)."""
    return float((np.asarray(G, float) @ np.asarray(point, float) - np.asarray(g, float)) @ lam)


def polytope_certificate(point: np.ndarray, G: np.ndarray, g: np.ndarray) -> np.ndarray:
    """The optimal OBCA certificate of a point against the polytope {x : G x <= g}.

    Outside the polytope it solves max (G p - g)^T lambda s.t. lambda >= 0, ||G^T lambda|| <= 1
    through the projection x* of p: lambda = nu / ||p - x*|| where p - x* = G_S^T nu, nu >= 0, on
    the active face set S. The most violated face is tried first (exact whenever the nearest
    feature is a face, and for every point of a box it is tried with its neighbours), then face
    subsets of size up to d, so the value equals the Euclidean distance and ||G^T lambda|| = 1.
    Inside (or on) the polytope, where no certificate can be positive, it returns the normalised
    normal of the shallowest exit face: value = minus the depth along it, ||G^T lambda|| = 1.

    Parameters
    ----------
    point : (d,) array
    G : (m, d) array
    g : (m,) array

    Returns
    -------
    (m,) array
        lambda >= 0 with ||G^T lambda||_2 = 1.
    """
    p = np.asarray(point, float).reshape(-1)
    G = np.atleast_2d(np.asarray(G, float))
    g = np.asarray(g, float).reshape(-1)
    norms = np.linalg.norm(G, axis=1)
    margins = (G @ p - g) / norms
    order = np.argsort(-margins)
    best = int(order[0])
    lam = np.zeros(g.size)
    lam[best] = 1.0 / norms[best]
    if margins[best] <= 0:
        return lam  # inside or on the boundary
    candidate = p - margins[best] * G[best] / norms[best]
    if np.all(G @ candidate <= g + _TOL * np.maximum(1.0, np.abs(g))):
        return lam  # the nearest feature is the most violated face
    dim = p.size
    for size in range(2, dim + 1):
        for subset in itertools.combinations(order.tolist(), size):
            rows = G[list(subset)]
            gram = rows @ rows.T
            if abs(np.linalg.det(gram)) < 1e-12:
                continue
            nu = np.linalg.solve(gram, rows @ p - g[list(subset)])
            if np.any(nu < -_TOL):
                continue
            x = p - rows.T @ nu
            if not np.all(G @ x <= g + 1e-7 * np.maximum(1.0, np.abs(g))):
                continue
            gap = float(np.linalg.norm(p - x))
            if gap <= _TOL:
                continue
            out = np.zeros(g.size)
            out[list(subset)] = np.maximum(nu, 0.0) / gap
            return out
    return lam  # degenerate geometry: the face certificate is still feasible, a lower bound


def _slack(values: np.ndarray, settings: OCPSettings) -> np.ndarray:
    """Soft-form slack making each separation row feasible at the seed: max(0, d_min - value)."""
    return np.maximum(0.0, settings.d_min - values)[None, :]


def obstacle_seed(tag: str, positions: np.ndarray, settings: OCPSettings) -> dict[str, np.ndarray]:
    """Certificates ``L{tag}_o{n}`` (rows of G_n, K) of guessed positions (K, d) against every static
    obstacle, plus the soft slacks ``A{tag}_o{n}`` (1, K) in the soft form."""
    blocks: dict[str, np.ndarray] = {}
    for n, (G, g) in enumerate(settings.obstacles):
        lam = np.array([polytope_certificate(p, G, g) for p in positions]).T
        blocks[f"L{tag}_o{n}"] = lam
        if settings.collision == "soft":
            values = np.einsum("mk,mk->k", G @ positions.T - g[:, None], lam)
            blocks[f"A{tag}_o{n}"] = _slack(values, settings)
    return blocks


def pair_seed(
    tag: str, offsets: np.ndarray, half_size: np.ndarray, settings: OCPSettings
) -> dict[str, np.ndarray]:
    """Certificate ``L{tag}`` (2d, K) of guessed offsets p_i - p_j (K, d) against the box of
    half-size delta around the other agent, plus the soft slack ``A{tag}`` (1, K)."""
    half = np.broadcast_to(np.asarray(half_size, float), (offsets.shape[1],))
    lam = box_certificates(offsets, half).T
    blocks = {f"L{tag}": lam}
    if settings.collision == "soft":
        d = offsets.shape[1]
        values = np.einsum("kd,dk->k", offsets, lam[:d] - lam[d:]) - half @ (lam[:d] + lam[d:])
        blocks[f"A{tag}"] = _slack(values, settings)
    return blocks
