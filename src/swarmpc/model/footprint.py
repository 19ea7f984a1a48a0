"""Oriented rectangular footprints in the plane: halfspaces, vertices, overlap and exact distances.

A footprint is a rectangle of length l (along its heading) and width w, centred at c with heading
theta; a pose is (x, y, theta) and a size is (l, w). With R(theta) the rotation by theta and the
box G = [I; -I], g = [l/2, w/2, l/2, w/2] of the body frame, the footprint is

    P = {y : A y <= b},   A = G R(theta)^T,   b = g + G R(theta)^T c,

the form OBCA certifies (:mod:`swarmpc.formulation.footprint_certificates`). Static obstacles are
convex polygons {y : G y <= g} of any number of facets.

Distances are exact, between closed convex polygons given by counter-clockwise vertices:

* overlap by the separating-axis test (SAT): two convex polygons are disjoint iff the projections
  on one of their edge normals are; touching polygons overlap;
* separated: the closest points of two disjoint convex polygons include a vertex of one of them,
  so the distance is the least vertex-to-edge distance, both ways;
* signed (optional): minus the penetration depth when they overlap. The depth is the distance of
  the origin to the boundary of the Minkowski difference Q - P, whose facet normals are the edge
  normals of P and Q; that distance is min_u h_{Q-P}(u) over those unit normals u, which is the
  smallest SAT overlap. So the signed distance costs no more than the SAT test itself.

Every function broadcasts over leading axes (many poses, e.g. steps x pairs, at once).
"""

from __future__ import annotations

import numpy as np

from swarmpc.model.geometry import polytope_vertices

__all__ = [
    "edge_normals",
    "footprint_vertices",
    "polygon_distance",
    "polygon_vertices",
    "polygons_overlap",
    "rectangle_distance",
    "rectangle_halfspaces",
    "rectangle_polytope_distance",
    "rectangle_vertices",
    "rectangles_overlap",
    "rotation",
    "sat_separation",
]

_CORNERS = np.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]])
"""Body-frame corners of the unit half-size box, counter-clockwise."""


def rotation(theta: np.ndarray) -> np.ndarray:
    """R(theta) (..., 2, 2): body-frame coordinates to world coordinates."""
    theta = np.asarray(theta, float)
    cos, sin = np.cos(theta), np.sin(theta)
    return np.stack([np.stack([cos, -sin], axis=-1), np.stack([sin, cos], axis=-1)], axis=-2)


def rectangle_halfspaces(
    center: np.ndarray, theta: np.ndarray, length: np.ndarray, width: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(A, b) of the oriented rectangle, A (..., 4, 2) = G R^T and b (..., 4) = g + G R^T c.

    Rows are ordered as G = [I; -I] in the body frame: front, left, back, right; every row of A
    is a unit vector, so A y - b is the signed distance of y to each side's line.
    """
    center = np.asarray(center, float)
    rot_t = np.swapaxes(rotation(theta), -1, -2)
    A = np.concatenate([rot_t, -rot_t], axis=-2)
    half = np.stack([np.asarray(length, float), np.asarray(width, float)], axis=-1) / 2.0
    g = np.concatenate([half, half], axis=-1)
    return A, g + np.einsum("...kd,...d->...k", A, center)


def rectangle_vertices(
    center: np.ndarray, theta: np.ndarray, length: np.ndarray, width: np.ndarray
) -> np.ndarray:
    """Corners (..., 4, 2) of the oriented rectangle, counter-clockwise from front-left."""
    half = np.stack([np.asarray(length, float), np.asarray(width, float)], axis=-1) / 2.0
    corners = _CORNERS * half[..., None, :]  # (..., 4, 2) in the body frame
    world = np.einsum("...ab,...kb->...ka", rotation(theta), corners)
    return world + np.asarray(center, float)[..., None, :]


def footprint_vertices(pose: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Corners (..., 4, 2) of footprints of poses (..., 3) = (x, y, theta) and sizes (..., 2) = (l, w),
    counter-clockwise (:func:`rectangle_vertices`)."""
    pose = np.asarray(pose, float)
    size = np.asarray(size, float)
    return rectangle_vertices(pose[..., :2], pose[..., 2], size[..., 0], size[..., 1])


def polygon_vertices(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Counter-clockwise vertices (n, 2) of the bounded convex polygon {y : A y <= b}.

    Raises
    ------
    ValueError
        When the polygon is not two-dimensional, is unbounded or has no interior.
    """
    A = np.atleast_2d(np.asarray(A, float))
    if A.shape[1] != 2:
        raise ValueError(f"a polygon needs 2 columns in A, got {A.shape[1]}")
    vertices = polytope_vertices(A, b)
    if len(vertices) < 3:
        raise ValueError("the polygon {A y <= b} is empty or flat")
    offset = vertices - vertices.mean(axis=0)
    return vertices[np.argsort(np.arctan2(offset[:, 1], offset[:, 0]))]


def edge_normals(vertices: np.ndarray) -> np.ndarray:
    """Unit outward normals (..., n, 2) of the edges v_k -> v_k+1 of counter-clockwise polygons
    (..., n, 2); a zero-length edge gets a zero normal."""
    vertices = np.asarray(vertices, float)
    edge = np.roll(vertices, -1, axis=-2) - vertices
    normal = np.stack([edge[..., 1], -edge[..., 0]], axis=-1)
    length = np.linalg.norm(normal, axis=-1, keepdims=True)
    return normal / np.where(length > 0, length, 1.0)


def sat_separation(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Largest gap between the projections of polygons P (..., n, 2) and Q (..., m, 2) on their
    unit edge normals (...): > 0 exactly when they are disjoint (a lower bound on their distance
    then), and minus the penetration depth when they overlap."""
    P, Q = np.asarray(P, float), np.asarray(Q, float)
    lead = np.broadcast_shapes(P.shape[:-2], Q.shape[:-2])
    normals_p = np.broadcast_to(edge_normals(P), (*lead, *P.shape[-2:]))
    normals_q = np.broadcast_to(edge_normals(Q), (*lead, *Q.shape[-2:]))
    axes = np.concatenate([normals_p, normals_q], axis=-2)  # (..., n + m, 2)
    on_p = np.einsum("...kd,...ad->...ka", P, axes)  # (..., n, n + m)
    on_q = np.einsum("...kd,...ad->...ka", Q, axes)
    gap = np.maximum(on_q.min(axis=-2) - on_p.max(axis=-2), on_p.min(axis=-2) - on_q.max(axis=-2))
    valid = np.linalg.norm(axes, axis=-1) > 0  # a zero normal separates nothing
    return np.max(np.where(valid, gap, -np.inf), axis=-1)


def polygons_overlap(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """True (...) where the closed convex polygons P (..., n, 2) and Q (..., m, 2) intersect
    (touching included): no edge normal separates them."""
    return sat_separation(P, Q) <= 0.0


def _vertex_edge_distance(P: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Least distance (...) from a vertex of P (..., n, 2) to an edge of Q (..., m, 2)."""
    start = Q[..., None, :, :]
    edge = np.roll(Q, -1, axis=-2)[..., None, :, :] - start  # (..., 1, m, 2)
    offset = P[..., :, None, :] - start  # (..., n, m, 2)
    length_sq = np.sum(edge * edge, axis=-1)
    t = np.clip(np.sum(offset * edge, axis=-1) / np.where(length_sq > 0, length_sq, 1.0), 0.0, 1.0)
    gap = np.linalg.norm(offset - t[..., None] * edge, axis=-1)
    return gap.min(axis=(-2, -1))


def polygon_distance(P: np.ndarray, Q: np.ndarray, signed: bool = False) -> np.ndarray:
    """Euclidean distance (...) between convex polygons P (..., n, 2) and Q (..., m, 2).

    Parameters
    ----------
    P, Q : array
        Counter-clockwise vertices; leading axes broadcast.
    signed : bool
        Where they overlap, return minus the penetration depth (the shortest translation that
        separates them) instead of 0.

    Returns
    -------
    np.ndarray
        0 (or minus the depth) where the SAT test finds an overlap, else the least
        vertex-to-edge distance both ways, which is exact for disjoint convex polygons.
    """
    P, Q = np.asarray(P, float), np.asarray(Q, float)
    separation = sat_separation(P, Q)
    apart = np.minimum(_vertex_edge_distance(P, Q), _vertex_edge_distance(Q, P))
    inside = separation if signed else np.zeros_like(separation)
    # The SAT gap is a lower bound of the distance: taking the larger keeps "0 iff overlap" under rounding.
    return np.where(separation > 0, np.maximum(apart, separation), inside)


def rectangles_overlap(
    pose_i: np.ndarray, size_i: np.ndarray, pose_j: np.ndarray, size_j: np.ndarray
) -> np.ndarray:
    """True (...) where footprints of poses (..., 3) and sizes (..., 2) intersect (SAT)."""
    return polygons_overlap(footprint_vertices(pose_i, size_i), footprint_vertices(pose_j, size_j))


def rectangle_distance(
    pose_i: np.ndarray, size_i: np.ndarray, pose_j: np.ndarray, size_j: np.ndarray, signed: bool = False
) -> np.ndarray:
    """Exact Euclidean distance (...) between two oriented rectangles.

    Poses (..., 3) = (x, y, theta) and sizes (..., 2) = (length, width) broadcast over leading
    axes. 0 where they overlap, or minus the penetration depth with ``signed``
    (:func:`polygon_distance`).
    """
    return polygon_distance(footprint_vertices(pose_i, size_i), footprint_vertices(pose_j, size_j), signed)


def rectangle_polytope_distance(
    pose: np.ndarray, size: np.ndarray, A: np.ndarray, b: np.ndarray, signed: bool = False
) -> np.ndarray:
    """Exact Euclidean distance (...) between footprints of poses (..., 3), sizes (..., 2) and the
    bounded convex polygon {y : A y <= b} (its vertices computed once,
    :func:`polygon_vertices`); with ``signed``, minus the penetration depth where they overlap."""
    return polygon_distance(footprint_vertices(pose, size), polygon_vertices(A, b), signed)
