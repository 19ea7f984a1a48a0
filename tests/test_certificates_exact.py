"""The closed-form best certificates of swarmpc.formulation.certificates, against exact geometry.

(a) dual feasibility: lambda >= 0 and ||G^T lambda||_2 = 1 (feasible for the hard and soft forms);
(b) tightness: the certified value equals the exact signed distance (Euclidean distance outside,
    minus the penetration depth inside) within 1e-9; boxes against the project's
    ``box_signed_distance``, polytopes against an exact point-to-hull distance over the simplices
    of a scipy ConvexHull (independent of the facet form the certifier uses);
(c) weak duality: ANY point meeting the linear constraint (G q - g)^T lambda >= d with the fixed
    certificate (including points exactly on it) keeps an exact distance >= d.
"""

from __future__ import annotations

import itertools

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull

from swarmpc.formulation.certificates import (
    PolytopeCertifier,
    box_certificates,
    certificate_values,
    pair_rows,
    polytope_certificates,
)
from swarmpc.model.geometry import box_halfspaces, box_signed_distance

TOL = 1e-9

coordinate = st.floats(-3.0, 3.0, allow_nan=False)
half_sizes = st.floats(0.05, 1.0)


def simplex_distance(point: np.ndarray, simplex: np.ndarray) -> float:
    """Exact Euclidean distance of ``point`` to the simplex spanned by the rows of ``simplex``:
    the nearest point is the projection onto the affine hull of some face whose barycentric
    coordinates are all >= 0, so the minimum over those projections is exact."""
    best = np.inf
    for size in range(1, len(simplex) + 1):
        for face in itertools.combinations(range(len(simplex)), size):
            base, rest = simplex[face[0]], simplex[list(face[1:])] - simplex[face[0]]
            if size == 1:
                best = min(best, float(np.linalg.norm(point - base)))
                continue
            coef = np.linalg.lstsq(rest.T, point - base, rcond=None)[0]
            if np.all(coef >= 0) and coef.sum() <= 1:
                best = min(best, float(np.linalg.norm(point - base - rest.T @ coef)))
    return best


def hull_signed_distance(point: np.ndarray, hull: ConvexHull) -> float:
    """Signed Euclidean distance to a convex hull: to its boundary simplices outside, minus the
    distance to the nearest facet plane inside (qhull's facet normals are unit)."""
    normals, offsets = hull.equations[:, :-1], hull.equations[:, -1]
    residual = normals @ point + offsets
    if np.max(residual) <= 0:
        return float(np.max(residual))
    return min(simplex_distance(point, hull.points[s]) for s in hull.simplices)


def random_polytope(seed: int, dim: int) -> tuple[np.ndarray, np.ndarray, ConvexHull]:
    """A random full-dimensional polytope as (G, g) with rows scaled arbitrarily, and its hull."""
    rng = np.random.default_rng(seed)
    hull = ConvexHull(rng.normal(size=(6 + 3 * dim, dim)))
    scale = rng.uniform(0.3, 3.0, size=len(hull.equations))
    return hull.equations[:, :-1] * scale[:, None], -hull.equations[:, -1] * scale, hull


def assert_dual_feasible(G: np.ndarray, lam: np.ndarray) -> None:
    assert np.all(lam >= 0)
    np.testing.assert_allclose(np.linalg.norm(G.T @ lam, axis=0), 1.0, atol=1e-12)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.lists(coordinate, min_size=3, max_size=3), min_size=1, max_size=8),
       st.lists(half_sizes, min_size=3, max_size=3))
def test_box_certificate_is_feasible_and_exact(offsets, half):
    offsets, half = np.array(offsets).T, np.array(half)
    cert = box_certificates(offsets, half)
    G, g = box_halfspaces(np.zeros(3), half)
    assert_dual_feasible(G, cert.lam)
    exact = box_signed_distance(offsets, half[:, None], axis=0)
    np.testing.assert_allclose(cert.value, exact, atol=TOL, rtol=0)
    np.testing.assert_allclose(certificate_values(offsets, G, g, cert.lam), exact, atol=TOL, rtol=0)


@settings(max_examples=200, deadline=None)
@given(st.sampled_from([2, 3]), st.lists(coordinate, min_size=3, max_size=3),
       st.lists(half_sizes, min_size=3, max_size=3))
def test_box_certificate_agrees_with_the_polytope_certifier(dim, offset, half):
    offset, half = np.array(offset[:dim]), np.array(half[:dim])
    G, g = box_halfspaces(np.zeros(dim), half)
    np.testing.assert_allclose(polytope_certificates(offset, G, g).value, box_certificates(offset, half).value,
                               atol=TOL, rtol=0)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 100_000), st.sampled_from([2, 3]), st.floats(0.0, 2.5))
def test_polytope_certificate_is_feasible_and_exact(seed, dim, spread):
    G, g, hull = random_polytope(seed, dim)
    rng = np.random.default_rng(seed + 7)
    points = hull.points[hull.vertices].mean(axis=0)[:, None] + spread * rng.normal(size=(dim, 12))
    cert = PolytopeCertifier(G, g)(points)
    assert_dual_feasible(G, cert.lam)
    exact = np.array([hull_signed_distance(p, hull) for p in points.T])
    np.testing.assert_allclose(cert.value, exact, atol=TOL, rtol=0)
    np.testing.assert_allclose(certificate_values(points, G, g, cert.lam), cert.value, atol=TOL, rtol=0)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 100_000), st.sampled_from([2, 3]))
def test_polytope_certificate_is_exact_near_vertices_and_edges(seed, dim):
    """Points just outside vertices and edges, where the optimal certificate mixes facets."""
    G, g, hull = random_polytope(seed, dim)
    rng = np.random.default_rng(seed + 11)
    corners = hull.points[hull.vertices]
    centre = corners.mean(axis=0)
    pairs = rng.integers(0, len(corners), size=(10, 2))
    anchors = 0.5 * (corners[pairs[:, 0]] + corners[pairs[:, 1]])
    points = (anchors + rng.uniform(0.01, 0.5, (10, 1)) * (anchors - centre)
              + 0.05 * rng.normal(size=(10, dim))).T
    cert = PolytopeCertifier(G, g)(points)
    assert_dual_feasible(G, cert.lam)
    exact = np.array([hull_signed_distance(p, hull) for p in points.T])
    np.testing.assert_allclose(cert.value, exact, atol=TOL, rtol=0)


def shift_onto_constraint(points: np.ndarray, normal: np.ndarray, value: np.ndarray, margin: float) -> np.ndarray:
    """Move each point along the certificate's unit normal until its value reaches ``margin``
    (points already beyond stay): the points ON the linear constraint are the critical ones."""
    return points + np.maximum(margin - value, 0.0) * normal


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 100_000), st.lists(coordinate, min_size=3, max_size=3),
       st.lists(half_sizes, min_size=3, max_size=3), st.floats(0.01, 1.0))
def test_box_pair_weak_duality(seed, offset, half, margin):
    """With a fixed certificate, every pair (p_i, p_j) meeting n'(p_i - p_j) >= d_min + delta'|n|
    keeps the delta boxes at least d_min apart, wherever the certificate came from."""
    half = np.array(half)
    lam = box_certificates(np.array(offset), half).lam
    n, constant = pair_rows(lam[:, None], half)
    rng = np.random.default_rng(seed)
    p_i, p_j = rng.uniform(-3, 3, (3, 50)), rng.uniform(-3, 3, (3, 50))
    deficit = np.maximum(margin + constant - n[:, 0] @ (p_i - p_j), 0.0)
    p_i, p_j = p_i + 0.5 * deficit * n, p_j - 0.5 * deficit * n
    assert np.all(n[:, 0] @ (p_i - p_j) - constant >= margin - 1e-12)
    assert np.all(box_signed_distance(p_i - p_j, half[:, None], axis=0) >= margin - TOL)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 100_000), st.sampled_from([2, 3]), st.floats(0.01, 1.0))
def test_polytope_weak_duality(seed, dim, margin):
    G, g, hull = random_polytope(seed, dim)
    rng = np.random.default_rng(seed + 3)
    anchor = hull.points[hull.vertices].mean(axis=0) + 2.0 * rng.normal(size=dim)
    lam = polytope_certificates(anchor, G, g).lam
    normal = (G.T @ lam)[:, None]
    points = anchor[:, None] + 1.5 * rng.normal(size=(dim, 30))
    points = shift_onto_constraint(points, normal, certificate_values(points, G, g, lam[:, None]), margin)
    assert np.all(certificate_values(points, G, g, lam[:, None]) >= margin - 1e-12)
    exact = np.array([hull_signed_distance(p, hull) for p in points.T])
    assert np.all(exact >= margin - TOL)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(dim=st.sampled_from([2, 3]), copies=st.integers(1, 5), steps=st.integers(2, 12), data=st.data())
def test_one_box_per_column_equals_each_box_on_its_own(dim: int, copies: int, steps: int, data: st.DataObject) -> None:
    """A (d, K) half-size (one box per column: the pairs of several bodies in one call) gives
    each column the certificate of its own box called alone, to rounding."""
    points = data.draw(st.lists(coordinate, min_size=dim * copies * steps, max_size=dim * copies * steps))
    halves = data.draw(st.lists(half_sizes, min_size=dim * copies, max_size=dim * copies))
    offsets = np.reshape(points, (dim, copies * steps))
    half = np.reshape(halves, (dim, copies))
    together = box_certificates(offsets, np.repeat(half, steps, axis=1))
    for c in range(copies):
        alone = box_certificates(offsets[:, c * steps:(c + 1) * steps], half[:, c])
        np.testing.assert_allclose(together.lam[:, c * steps:(c + 1) * steps], alone.lam, rtol=0, atol=1e-15)
        np.testing.assert_allclose(together.value[c * steps:(c + 1) * steps], alone.value, rtol=0, atol=1e-15)
        exact = [box_signed_distance(offsets[:, c * steps + k], half[:, c]) for k in range(steps)]
        np.testing.assert_allclose(together.value[c * steps:(c + 1) * steps], exact, atol=TOL)
