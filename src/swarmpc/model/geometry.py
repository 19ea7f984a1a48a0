"""Geometry of agents and obstacles: polytopes, boxes, distances and separations.

Agents are axis-aligned boxes of half-size delta (one value per axis) around their positions;
static obstacles are convex polytopes {p : G p <= g}.
"""

from __future__ import annotations

import numpy as np


def box_halfspaces(center: np.ndarray, half_size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(G, g) of the axis-aligned box ``center +- half_size``, rows ordered [I; -I]."""
    center = np.asarray(center, float)
    half = np.broadcast_to(np.asarray(half_size, float), center.shape)
    eye = np.eye(center.size)
    return np.vstack([eye, -eye]), np.concatenate([center + half, half - center])


def box_exterior_distance(offsets: np.ndarray, half_size: np.ndarray, axis: int = -1) -> np.ndarray:
    """Euclidean distance of each offset (coordinates along ``axis``) to the box [-half, half],
    0 inside: the separation the OBCA certificate bounds, for many offsets at once."""
    excess = np.abs(np.asarray(offsets, float)) - np.asarray(half_size, float)
    return np.linalg.norm(np.maximum(excess, 0.0), axis=axis)


def box_signed_distance(offsets: np.ndarray, half_size: np.ndarray, axis: int = -1) -> np.ndarray:
    """Signed Euclidean distance of each offset to the box [-half, half] (negative inside, where
    its magnitude is the penetration depth): :func:`point_box_distance` for many offsets at once."""
    excess = np.abs(np.asarray(offsets, float)) - np.asarray(half_size, float)
    outside = np.linalg.norm(np.maximum(excess, 0.0), axis=axis)
    return np.where(outside > 0, outside, np.max(excess, axis=axis))


def point_box_distance(offset: np.ndarray, half_size: np.ndarray) -> float:
    """Signed Euclidean distance of ``offset`` to the box [-half, half] (negative inside).

    Inside, the magnitude is the penetration depth: the smallest move that leaves the box.
    """
    offset = np.asarray(offset, float)
    half = np.broadcast_to(np.asarray(half_size, float), offset.shape)
    outside = float(box_exterior_distance(offset, half))
    if outside > 0:
        return outside
    return float(np.max(np.abs(offset) - half))


def box_certificate(offset: np.ndarray, half_size: np.ndarray) -> np.ndarray:
    """The optimal OBCA dual certificate lambda (2d,) of a point against a box.

    Maximises (G q - g)^T lambda over lambda >= 0 with ||G^T lambda||_2 = 1, G = [I; -I]: the
    unit direction from the box to the point outside, or the shallowest exit axis inside. It
    warm-starts the solver's certificates from a guessed trajectory.
    """
    offset = np.asarray(offset, float)
    dim = offset.size
    half = np.broadcast_to(np.asarray(half_size, float), offset.shape)
    excess = np.abs(offset) - half
    direction = np.zeros(dim)
    if np.any(excess > 0):
        direction = np.sign(offset) * np.maximum(excess, 0.0)
        direction /= np.linalg.norm(direction)
    else:
        axis = int(np.argmax(excess))
        direction[axis] = 1.0 if offset[axis] >= 0 else -1.0
    return np.concatenate([np.maximum(direction, 0.0), np.maximum(-direction, 0.0)])


def polytope_certificate(point: np.ndarray, G: np.ndarray, g: np.ndarray) -> np.ndarray:
    """A feasible, near-optimal certificate of a point against {p : G p <= g}.

    Uses the most violated normalised face: exact for a box and for any point whose nearest
    feature is a face, and always feasible (||G^T lambda|| = 1), which is what a warm start needs.
    """
    norms = np.linalg.norm(G, axis=1)
    margins = (G @ point - g) / norms
    face = int(np.argmax(margins))
    certificate = np.zeros(len(g))
    certificate[face] = 1.0 / norms[face]
    return certificate


def inf_separation_ratio(positions: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Pairwise max_a |p_i,a - p_j,a| / delta_a for positions (..., M, d); < 1 is a collision.

    Returns (..., M, M) with +inf on the diagonal.
    """
    positions = np.asarray(positions, float)
    delta = np.asarray(delta, float)
    gaps = np.abs(positions[..., :, None, :] - positions[..., None, :, :]) / delta
    ratio = gaps.max(axis=-1)
    m = positions.shape[-2]
    ratio[..., np.arange(m), np.arange(m)] = np.inf
    return ratio


def count_collisions(positions: np.ndarray, delta: np.ndarray, tol: float = 1e-9) -> int:
    """Number of (k, i < j) with agents i and j inside each other's box at step k.

    ``positions`` is (T, M, d); the test is ||p_i - p_j||_inf < delta (per axis: outside on no
    axis), with a small tolerance so touching boxes do not count.
    """
    ratio = inf_separation_ratio(positions, delta)
    m = ratio.shape[-1]
    upper = np.triu(np.ones((m, m), bool), k=1)
    scale = np.asarray(delta, float).max()
    return int(np.sum((ratio < 1 - tol / scale) & upper))


def obstacle_penetration(positions: np.ndarray, G: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Depth by which each position (..., d) lies inside {G p <= g}; <= 0 means outside."""
    norms = np.linalg.norm(G, axis=1)
    return np.min((g - np.asarray(positions) @ G.T) / norms, axis=-1)
