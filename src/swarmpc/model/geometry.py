"""Geometry of agents and obstacles: polytopes, boxes, distances and separations.

Every agent has a body: an axis-aligned box of half-size b_i (one value per axis) around its
position. Two agents collide when their bodies overlap, i.e. when |p_i - p_j| < Delta_ij on every
axis with Delta_ij = b_i + b_j; the scenario's delta is the Delta of two default bodies (b = delta / 2).
Static obstacles are convex polytopes {p : G p <= g}; a body stays out of one when its centre
stays out of the polytope grown by the body (:func:`inflate_polytope`).

Functions that take a ``delta`` accept either form the solvers use: a 1-D Delta (d,) shared by
every pair, or per-agent body half-sizes (M, d) (:func:`as_bodies`).
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
    return box_certificates(offset.reshape(1, -1), half_size)[0]


def box_certificates(offsets: np.ndarray, half_size: np.ndarray) -> np.ndarray:
    """:func:`box_certificate` of every row of ``offsets`` (K, d) at once: (K, 2d).

    A row outside the box gets the unit direction from the box to it, its length the row's dot
    product with itself (:func:`numpy.vecdot`, the product :func:`numpy.linalg.norm` takes of one
    vector, so a batch and its rows one by one agree bit for bit); a row inside gets the
    shallowest exit axis."""
    offsets = np.asarray(offsets, float)
    if offsets.ndim != 2:
        raise ValueError(f"box_certificates: offsets must be (K, d), got shape {offsets.shape}")
    half = np.broadcast_to(np.asarray(half_size, float), offsets.shape)
    excess = np.abs(offsets) - half
    outside = np.any(excess > 0, axis=1)
    direction = np.zeros_like(offsets)
    out = np.sign(offsets[outside]) * np.maximum(excess[outside], 0.0)
    direction[outside] = out / np.sqrt(np.vecdot(out, out))[:, None]
    inside = np.flatnonzero(~outside)
    axis = np.argmax(excess[inside], axis=1)
    direction[inside, axis] = np.where(offsets[inside, axis] >= 0, 1.0, -1.0)
    return np.concatenate([np.maximum(direction, 0.0), np.maximum(-direction, 0.0)], axis=1)


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


def as_bodies(delta: np.ndarray, num_agents: int) -> np.ndarray:
    """Per-agent body half-sizes (M, d) from a solver's ``delta``.

    A 1-D ``delta`` (d,) is one Delta for every pair, which is every body of half-size delta / 2:
    halving and doubling are exact in binary floating point, so b_i + b_j reproduces delta bit
    for bit. A 2-D ``delta`` (M, d) is the bodies themselves.
    """
    delta = np.asarray(delta, float)
    if delta.ndim == 2:
        if delta.shape[0] != num_agents:
            raise ValueError(f"bodies: expected {num_agents} rows, got {delta.shape[0]}")
        return delta.copy()
    return np.tile(delta.reshape(-1) / 2.0, (num_agents, 1))


def pair_deltas(bodies: np.ndarray) -> np.ndarray:
    """(M, M, d) Delta_ij = b_i + b_j of every pair of bodies (M, d): how far apart, per axis, two
    agents' centres must stay for their bodies not to overlap."""
    bodies = np.asarray(bodies, float)
    return bodies[:, None, :] + bodies[None, :, :]


def largest_pair_delta(bodies: np.ndarray) -> np.ndarray:
    """(M, M) largest axis of each pair's Delta_ij: an inf-norm gap at least this large keeps the
    two bodies apart on some axis."""
    return pair_deltas(bodies).max(axis=2)


def inflate_polytope(G: np.ndarray, g: np.ndarray, half_size: np.ndarray) -> np.ndarray:
    """Offsets g' of the polytope {p : G p <= g} grown by a box body of ``half_size`` per axis.

    Facet k moves out by the box's support function in its normal direction, sum_a |G_ka| b_a.
    The body at p meets the obstacle only if p lies in {G p <= g'}: that set contains the
    Minkowski sum of obstacle and box (it is exactly that sum when the obstacle is an axis-aligned
    box; at a sharp vertex of another polytope it also takes in a sliver the body does not reach,
    which errs on the safe side). The OBCA point-in-polytope certificate against {G p <= g'}
    therefore keeps the whole body out.
    """
    return np.asarray(g, float) + np.abs(np.asarray(G, float)) @ np.asarray(half_size, float)


def inf_separation_ratio(positions: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Pairwise max_a |p_i,a - p_j,a| / delta_a for positions (..., M, d); < 1 is a collision.

    ``delta`` is one Delta (d,) for every pair or each pair's Delta_ij (M, M, d)
    (:func:`pair_deltas`). Returns (..., M, M) with +inf on the diagonal.
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

    ``positions`` is (T, M, d) and ``delta`` one Delta (d,) or every pair's Delta_ij (M, M, d);
    the test is ||p_i - p_j||_inf < delta (per axis: outside on no axis), with a small tolerance
    (``tol`` metres on the pair's largest axis) so touching boxes do not count.
    """
    ratio = inf_separation_ratio(positions, delta)
    m = ratio.shape[-1]
    upper = np.triu(np.ones((m, m), bool), k=1)
    scale = np.atleast_1d(np.asarray(delta, float)).max(axis=-1)
    return int(np.sum((ratio < 1 - tol / scale) & upper))


def count_body_collisions(positions: np.ndarray, bodies: np.ndarray, tol: float = 1e-9) -> int:
    """Number of (k, i < j) whose bodies overlap at step k: |p_i - p_j| < b_i + b_j on every axis.

    ``positions`` (T, M, d), ``bodies`` (M, d). With every body delta / 2 this is exactly
    :func:`count_collisions` with ``delta``.
    """
    return count_collisions(positions, pair_deltas(bodies), tol)


def body_separation_ratio(positions: np.ndarray, bodies: np.ndarray) -> np.ndarray:
    """Pairwise max_a |p_i,a - p_j,a| / (b_i,a + b_j,a) for positions (..., M, d) and bodies (M, d):
    < 1 where two bodies overlap; (..., M, M) with +inf on the diagonal."""
    return inf_separation_ratio(positions, pair_deltas(bodies))


def obstacle_penetration(positions: np.ndarray, G: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Depth by which each position (..., d) lies inside {G p <= g}; <= 0 means outside."""
    norms = np.linalg.norm(G, axis=1)
    return np.min((g - np.asarray(positions) @ G.T) / norms, axis=-1)


def body_obstacle_penetration(
    positions: np.ndarray, bodies: np.ndarray, G: np.ndarray, g: np.ndarray
) -> np.ndarray:
    """Depth by which each agent's body reaches into {G p <= g}: :func:`obstacle_penetration` of
    its centre against the obstacle grown by its body (:func:`inflate_polytope`).

    ``positions`` (..., M, d), ``bodies`` (M, d); returns (..., M), <= 0 where the body stays out.
    For a box obstacle, > 0 exactly when the body's box overlaps the obstacle.
    """
    grown = np.asarray(g, float)[None, :] + np.asarray(bodies, float) @ np.abs(np.asarray(G, float)).T  # (M, f)
    norms = np.linalg.norm(G, axis=1)
    inside = (grown - np.asarray(positions, float) @ np.asarray(G, float).T) / norms
    return np.min(inside, axis=-1)


def _positively_spanning(A: np.ndarray) -> bool:
    """Whether the rows of ``A`` (unit norm) positively span R^d, i.e. a nonempty {p : A p <= b}
    is bounded: the recession cone {y : A y <= 0} is {0} exactly when the origin lies inside the
    convex hull of the rows, which one hull computation decides (cheaper than 2d linear programs)."""
    from scipy.spatial import ConvexHull, QhullError

    if A.shape[1] == 1:
        return bool(A.min() < 0 < A.max())
    try:
        hull = ConvexHull(A)
    except QhullError:  # fewer than d + 1 affinely independent rows: a flat hull
        return False
    return bool(np.all(hull.equations[:, -1] < -1e-9))


def polytope_vertices(
    G: np.ndarray, g: np.ndarray, bounds: tuple[np.ndarray, np.ndarray] | None = None
) -> np.ndarray:
    """Vertices of the polytope {p : G p <= g}, optionally clipped to an axis-aligned box.

    Parameters
    ----------
    G : np.ndarray
        (k, d) face normals.
    g : np.ndarray
        (k,) offsets.
    bounds : (lower, upper), optional
        Clip to this box; needed when the set is unbounded.

    Returns
    -------
    np.ndarray
        (n, d) vertices of the convex hull, (0, d) when the set is empty or flat.

    Raises
    ------
    ValueError
        When the set is unbounded and no ``bounds`` are given, or the shapes disagree.
    """
    # scipy here, not at the top: the command line starts without it (about 0.4 s)
    from scipy.optimize import linprog
    from scipy.spatial import ConvexHull, HalfspaceIntersection, QhullError

    G = np.atleast_2d(np.asarray(G, float))
    g = np.asarray(g, float).reshape(-1)
    d = G.shape[1]
    if G.shape[0] != g.size:
        raise ValueError(f"G has {G.shape[0]} rows but g has {g.size} entries")
    if bounds is not None:
        lower = np.broadcast_to(np.asarray(bounds[0], float), (d,))
        upper = np.broadcast_to(np.asarray(bounds[1], float), (d,))
        eye = np.eye(d)
        G = np.vstack([G, eye, -eye])
        g = np.concatenate([g, upper, -lower])
    norms = np.linalg.norm(G, axis=1)
    if np.any(norms == 0):
        raise ValueError("G has a zero row")
    A, b = G / norms[:, None], g / norms
    # Chebyshev centre: max r  s.t.  a_i^T x + r <= b_i  (rows of A have unit norm).
    cost = np.zeros(d + 1)
    cost[-1] = -1.0
    lp = linprog(
        cost,
        A_ub=np.hstack([A, np.ones((len(b), 1))]),
        b_ub=b,
        bounds=[(None, None)] * d + [(0, None)],
        method="highs",
    )
    if lp.status == 3:
        raise ValueError("the polytope is unbounded: pass bounds to clip it")
    centre = lp.x  # None only when the solve failed (status != 0)
    if lp.status != 0 or centre is None or centre[-1] <= 1e-9:
        return np.empty((0, d))
    if bounds is None and not _positively_spanning(A):
        raise ValueError("the polytope is unbounded: pass bounds to clip it")
    try:
        points = HalfspaceIntersection(np.hstack([A, -b[:, None]]), centre[:d]).intersections
        hull = ConvexHull(points)
    except QhullError:
        return np.empty((0, d))
    return hull.points[hull.vertices]
