"""Oriented rectangular footprints (swarmpc.model.footprint) and their OBCA certificates
(swarmpc.formulation.footprint_certificates), against independent geometry.

Distances: symmetric, 0 exactly when the SAT test finds an overlap (and an LP finds a common
point), invariant under a common rigid motion, within the sampling step of a dense sampling of
both boundaries, equal to the closed form of axis-aligned boxes (and the project's
``box_signed_distance`` for the signed version); the penetration depth is the least support of
the Minkowski difference over densely sampled directions.

Certificates: the best ones are dual feasible and certify the exact (signed) distance; ANY
feasible certificate certifies at most the distance (weak duality); the CasADi rows are the
literal OBCA expressions, hold at the best certificate iff the distance is >= d_min, and
IPOPT's maximum over the hard rows is the distance.
"""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from scipy.optimize import linprog
from scipy.spatial import ConvexHull
from scipy.spatial.distance import cdist

from swarmpc.formulation.footprint_certificates import (
    HalfspacePolygon,
    PolytopeFootprintCertifier,
    best_pair_certificates,
    certificate_value,
    footprint_pair_rows,
    footprint_polytope_rows,
    rectangle_pair_certificates,
    rectangle_polytope_certificates,
)
from swarmpc.model.footprint import (
    footprint_vertices,
    polygon_distance,
    polygon_vertices,
    rectangle_distance,
    rectangle_halfspaces,
    rectangle_polytope_distance,
    rectangle_vertices,
    rectangles_overlap,
    rotation,
)
from swarmpc.model.geometry import box_exterior_distance, box_signed_distance

TOL = 1e-9

coordinate = st.floats(-3.0, 3.0, allow_nan=False)
angle = st.floats(-np.pi, np.pi, allow_nan=False)
side = st.floats(0.1, 2.0)
poses = st.tuples(coordinate, coordinate, angle).map(np.array)
sizes = st.tuples(side, side).map(np.array)
footprints = st.tuples(poses, sizes)


@st.composite
def overlapping(draw):
    """Two footprints, the second centred inside the first's inscribed disc: they overlap."""
    (pose_i, size_i), (_, size_j) = draw(footprints), draw(footprints)
    radius = draw(st.floats(0.0, 0.99)) * size_i.min() / 2
    direction, theta = draw(angle), draw(angle)
    centre = pose_i[:2] + radius * np.array([np.cos(direction), np.sin(direction)])
    return (pose_i, size_i), (np.append(centre, theta), size_j)


SETTINGS = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def halfspaces(pose: np.ndarray, size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return rectangle_halfspaces(pose[:2], pose[2], size[0], size[1])


def random_polygon(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A random convex polygon (G, g) with arbitrarily scaled rows."""
    rng = np.random.default_rng(seed)
    hull = ConvexHull(rng.normal(scale=1.5, size=(8, 2)))
    scale = rng.uniform(0.3, 3.0, size=len(hull.equations))
    return hull.equations[:, :2] * scale[:, None], -hull.equations[:, 2] * scale


def boundary_samples(vertices: np.ndarray, count: int) -> np.ndarray:
    """``count`` evenly spaced points per edge (vertices included)."""
    t = np.linspace(0.0, 1.0, count)[:, None, None]
    return (vertices + t * (np.roll(vertices, -1, axis=0) - vertices)).reshape(-1, 2)


def feasible_rectangle_multipliers(theta: float, normal: np.ndarray, extra: np.ndarray) -> np.ndarray:
    """A feasible l >= 0 with (G R^T)^T l = normal that is not the cheapest one: ``extra`` (2,) >= 0
    is added to both rows of each axis, which leaves G^T l unchanged."""
    body = rotation(theta).T @ normal
    return np.concatenate([np.maximum(body, 0.0) + extra, np.maximum(-body, 0.0) + extra])


def common_point_exists(A_i, b_i, A_j, b_j) -> bool:
    """Whether the two polygons share a point (an LP, independent of the SAT test)."""
    lp = linprog(np.zeros(2), A_ub=np.vstack([A_i, A_j]), b_ub=np.concatenate([b_i, b_j]),
                 bounds=[(None, None)] * 2, method="highs")
    return lp.status == 0


# ----------------------------------------------------------------------------- geometry


@SETTINGS
@given(footprints)
def test_halfspaces_are_the_stated_form_and_bound_the_vertices(footprint):
    pose, size = footprint
    A, b = halfspaces(pose, size)
    R = np.array([[np.cos(pose[2]), -np.sin(pose[2])], [np.sin(pose[2]), np.cos(pose[2])]])
    G = np.vstack([np.eye(2), -np.eye(2)])
    g = np.concatenate([size / 2, size / 2])
    np.testing.assert_allclose(A, G @ R.T, atol=1e-15)
    np.testing.assert_allclose(b, g + G @ R.T @ pose[:2], atol=1e-12)
    V = rectangle_vertices(pose[:2], pose[2], size[0], size[1])
    slack = A @ V.T - b[:, None]  # (4 rows, 4 vertices)
    assert np.all(slack <= 1e-12)
    assert np.all(np.sum(np.abs(slack) <= 1e-12, axis=0) == 2)  # each corner on two sides
    x, y = V[:, 0], V[:, 1]
    area = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
    assert area == pytest.approx(size[0] * size[1], rel=1e-12)  # counter-clockwise
    from_halfspaces = polygon_vertices(A, b)
    assert from_halfspaces.shape == (4, 2) and np.all(cdist(V, from_halfspaces).min(axis=1) < 1e-9)
    x, y = from_halfspaces[:, 0], from_halfspaces[:, 1]
    assert np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) > 0  # counter-clockwise too


@SETTINGS
@given(footprints, footprints)
def test_distance_is_symmetric(first, second):
    for signed in (False, True):
        assert rectangle_distance(*first, *second, signed=signed) == pytest.approx(
            rectangle_distance(*second, *first, signed=signed), abs=1e-12)


@SETTINGS
@given(footprints, footprints)
def test_distance_is_zero_exactly_when_sat_finds_an_overlap(first, second):
    distance = float(rectangle_distance(*first, *second))
    overlap = bool(rectangles_overlap(*first, *second))
    assert (distance == 0.0) == overlap
    assert distance >= 0.0
    signed = float(rectangle_distance(*first, *second, signed=True))
    assert (signed <= 0.0) == overlap
    if abs(signed) > 1e-6:  # away from touching, an LP agrees on whether they share a point
        assert common_point_exists(*halfspaces(*first), *halfspaces(*second)) == overlap


@SETTINGS
@given(footprints, footprints, angle, coordinate, coordinate)
def test_distance_is_invariant_under_a_common_rigid_motion(first, second, phi, tx, ty):
    def moved(pose):
        return np.concatenate([rotation(phi) @ pose[:2] + [tx, ty], [pose[2] + phi]])

    for signed in (False, True):
        before = rectangle_distance(*first, *second, signed=signed)
        after = rectangle_distance(moved(first[0]), first[1], moved(second[0]), second[1], signed=signed)
        assert after == pytest.approx(before, abs=TOL)


@SETTINGS
@given(footprints, footprints)
def test_distance_matches_dense_boundary_sampling(first, second):
    distance = float(rectangle_distance(*first, *second))
    assume(distance > 0)
    count = 400
    V_i, V_j = footprint_vertices(*first), footprint_vertices(*second)
    sampled = cdist(boundary_samples(V_i, count), boundary_samples(V_j, count)).min()
    step = max(first[1].max(), second[1].max()) / (count - 1)
    assert distance - 1e-12 <= sampled <= distance + step  # closest points include a vertex, sampled exactly


@SETTINGS
@given(st.tuples(coordinate, coordinate).map(np.array), st.integers(-2, 2), sizes,
       st.tuples(coordinate, coordinate).map(np.array), st.integers(-2, 2), sizes)
def test_axis_aligned_distance_has_the_box_closed_form(c_i, k_i, size_i, c_j, k_j, size_j):
    def extents(k, size):  # a quarter turn swaps length and width
        return (size[::-1] if k % 2 else size) / 2

    total = extents(k_i, size_i) + extents(k_j, size_j)
    pose_i, pose_j = np.append(c_i, k_i * np.pi / 2), np.append(c_j, k_j * np.pi / 2)
    assert rectangle_distance(pose_i, size_i, pose_j, size_j) == pytest.approx(
        box_exterior_distance(c_j - c_i, total), abs=TOL)
    assert rectangle_distance(pose_i, size_i, pose_j, size_j, signed=True) == pytest.approx(
        box_signed_distance(c_j - c_i, total), abs=TOL)


@settings(max_examples=100, deadline=None)
@given(overlapping())
def test_penetration_depth_is_the_least_support_of_the_minkowski_difference(pair):
    first, second = pair
    signed = float(rectangle_distance(*first, *second, signed=True))
    assert signed < 0
    V_i, V_j = footprint_vertices(*first), footprint_vertices(*second)
    phi = np.linspace(0.0, 2 * np.pi, 20000, endpoint=False)
    u = np.stack([np.cos(phi), np.sin(phi)], axis=1)
    support = (V_j @ u.T).max(axis=0) - (V_i @ u.T).min(axis=0)  # h_{Q - P}(u)
    reach = np.linalg.norm(V_j[:, None] - V_i[None], axis=-1).max()
    assert -signed - 1e-12 <= support.min() <= -signed + reach * (phi[1] - phi[0])


@SETTINGS
@given(st.integers(0, 10_000), footprints)
def test_polytope_distance_matches_sampling_and_rectangles(seed, footprint):
    G, g = random_polygon(seed)
    distance = float(rectangle_polytope_distance(*footprint, G, g))
    V = polygon_vertices(G, g)
    count = 400
    sampled = cdist(boundary_samples(footprint_vertices(*footprint), count), boundary_samples(V, count)).min()
    edge = max(footprint[1].max(), np.linalg.norm(np.roll(V, -1, axis=0) - V, axis=1).max())
    if distance > 0:
        assert distance - 1e-12 <= sampled <= distance + edge / (count - 1)
    other = (np.array([0.3, -0.2, 0.7]), np.array([1.0, 0.4]))
    A, b = halfspaces(*other)
    scale = np.random.default_rng(seed).uniform(0.2, 5.0, 4)  # row scaling changes nothing
    assert rectangle_polytope_distance(*footprint, A * scale[:, None], b * scale, signed=True) == pytest.approx(
        rectangle_distance(*footprint, *other, signed=True), abs=TOL)


def test_distances_broadcast_over_leading_axes():
    rng = np.random.default_rng(3)
    pose_i = np.concatenate([rng.uniform(-2, 2, (5, 6, 2)), rng.uniform(-3, 3, (5, 6, 1))], axis=-1)
    pose_j = np.concatenate([rng.uniform(-2, 2, (5, 6, 2)), rng.uniform(-3, 3, (5, 6, 1))], axis=-1)
    size_i, size_j = rng.uniform(0.2, 1.5, (6, 2)), np.array([1.0, 0.5])
    G, g = random_polygon(5)
    together = rectangle_distance(pose_i, size_i, pose_j, size_j, signed=True)
    to_obstacle = rectangle_polytope_distance(pose_i, size_i, G, g, signed=True)
    certificates = rectangle_pair_certificates(pose_i, size_i, pose_j, size_j)
    assert together.shape == to_obstacle.shape == certificates.value.shape == (5, 6)
    assert certificates.lam_ij.shape == (5, 6, 4)
    for t in range(5):
        for k in range(6):
            assert together[t, k] == rectangle_distance(pose_i[t, k], size_i[k], pose_j[t, k], size_j, signed=True)
            assert to_obstacle[t, k] == pytest.approx(
                float(polygon_distance(footprint_vertices(pose_i[t, k], size_i[k]), polygon_vertices(G, g), True)))
    np.testing.assert_allclose(certificates.value, together, atol=TOL)


# ----------------------------------------------------------------------------- certificates


def assert_dual_feasible(A_i, A_j, lam_ij, lam_ji, unit=True):
    assert np.all(lam_ij >= 0) and np.all(lam_ji >= 0)
    normal = lam_ij @ A_i
    np.testing.assert_allclose(normal + lam_ji @ A_j, 0.0, atol=1e-12)
    if unit:
        assert np.linalg.norm(normal) == pytest.approx(1.0, abs=1e-12)


@SETTINGS
@given(st.one_of(st.tuples(footprints, footprints), overlapping()))
def test_best_certificates_are_feasible_and_certify_the_exact_distance(pair):
    first, second = pair
    (A_i, b_i), (A_j, b_j) = halfspaces(*first), halfspaces(*second)
    best = rectangle_pair_certificates(*first, *second)
    assert_dual_feasible(A_i, A_j, best.lam_ij, best.lam_ji)
    assert best.value == pytest.approx(float(certificate_value(b_i, b_j, best.lam_ij, best.lam_ji)), abs=1e-15)
    distance = float(rectangle_distance(*first, *second))
    if distance > 0:
        assert best.value == pytest.approx(distance, abs=1e-7)
    assert best.value == pytest.approx(float(rectangle_distance(*first, *second, signed=True)), abs=TOL)
    generic = best_pair_certificates(A_i, b_i, A_j, b_j)  # from the halfspaces alone
    assert_dual_feasible(A_i, A_j, generic.lam_ij, generic.lam_ji)
    assert generic.value == pytest.approx(float(best.value), abs=TOL)


@SETTINGS
@given(footprints, footprints, angle, st.floats(0.0, 1.0),
       st.tuples(st.floats(0.0, 2.0), st.floats(0.0, 2.0)).map(np.array),
       st.tuples(st.floats(0.0, 2.0), st.floats(0.0, 2.0)).map(np.array))
def test_any_feasible_certificate_certifies_at_most_the_distance(first, second, phi, radius, extra_i, extra_j):
    (A_i, b_i), (A_j, b_j) = halfspaces(*first), halfspaces(*second)
    normal = radius * np.array([np.cos(phi), np.sin(phi)])
    lam_ij = feasible_rectangle_multipliers(first[0][2], normal, extra_i)
    lam_ji = feasible_rectangle_multipliers(second[0][2], -normal, extra_j)
    assert_dual_feasible(A_i, A_j, lam_ij, lam_ji, unit=False)
    value = float(certificate_value(b_i, b_j, lam_ij, lam_ji))
    distance = float(rectangle_distance(*first, *second))
    assert value <= distance + 1e-12
    if distance > 0 or radius == 1.0:  # apart, or ||n|| = 1: bounded by the best (signed) value too
        assert value <= float(rectangle_pair_certificates(*first, *second).value) + 1e-12


@SETTINGS
@given(st.integers(0, 10_000), footprints, st.integers(0, 2**32 - 1), st.floats(0.0, 1.0))
def test_polytope_certificates_are_tight_and_bound_every_feasible_one(seed, footprint, draw, radius):
    G, g = random_polygon(seed)
    A, b = halfspaces(*footprint)
    best = rectangle_polytope_certificates(*footprint, G, g)
    assert_dual_feasible(A, G, best.lam_ij, best.lam_ji)
    signed = float(rectangle_polytope_distance(*footprint, G, g, signed=True))
    assert best.value == pytest.approx(signed, abs=TOL)
    generic = best_pair_certificates(A, b, G, g)
    assert_dual_feasible(A, G, generic.lam_ij, generic.lam_ji)
    assert generic.value == pytest.approx(signed, abs=TOL)
    rng = np.random.default_rng(draw)  # a random feasible certificate: any lambda_ji >= 0, then lambda_ij
    lam_ji = rng.exponential(size=len(g)) * (rng.random(len(g)) < 0.6)
    normal = -G.T @ lam_ji
    assume(np.linalg.norm(normal) > 1e-9)
    lam_ji *= radius / np.linalg.norm(normal)
    lam_ij = feasible_rectangle_multipliers(footprint[0][2], radius * normal / np.linalg.norm(normal),
                                            rng.exponential(size=2))
    assert_dual_feasible(A, G, lam_ij, lam_ji, unit=False)
    value = float(certificate_value(b, g, lam_ij, lam_ji))
    assert value <= max(signed, 0.0) + 1e-12
    if signed > 0 or radius == 1.0:
        assert value <= float(best.value) + 1e-12


def test_polygon_multipliers_survive_redundant_rows():
    G, g = random_polygon(11)
    redundant = np.vstack([G, [[1.0, 1.0]], G[:1] * 2.0])
    offsets = np.concatenate([g, [100.0], g[:1] * 2.0])
    polygon = HalfspacePolygon(redundant, offsets)
    directions = np.random.default_rng(0).normal(size=(50, 2))
    lam = polygon.multipliers(directions)
    assert np.all(lam >= 0)
    np.testing.assert_allclose(lam @ redundant, directions, atol=1e-12)
    np.testing.assert_allclose(lam @ offsets, polygon.support(directions), atol=1e-12)
    certifier = PolytopeFootprintCertifier(redundant, offsets)
    pose, size = np.array([4.0, -1.0, 0.4]), np.array([1.0, 0.5])
    assert certifier(pose, size).value == pytest.approx(float(rectangle_polytope_distance(pose, size, G, g)), abs=TOL)


# ----------------------------------------------------------------------------- CasADi rows


def evaluate(rows):
    return tuple(np.array(ca.DM(block)) for block in (rows.separation, rows.coupling, rows.norm_sq))


@settings(max_examples=50, deadline=None)
@given(footprints, footprints, st.integers(0, 10_000), st.integers(0, 2**32 - 1))
def test_rows_are_the_literal_obca_expressions(first, second, seed, draw):
    rng = np.random.default_rng(draw)
    lam_ij, lam_ji, slack = rng.exponential(size=4), rng.exponential(size=4), rng.exponential()
    (A_i, b_i), (A_j, b_j) = halfspaces(*first), halfspaces(*second)
    pose_i, pose_j, size_i = ca.SX.sym("pi", 3), ca.SX.sym("pj", 3), ca.SX.sym("si", 2)  # size as a parameter
    L_ij, L_ji, alpha = ca.SX.sym("lij", 4), ca.SX.sym("lji", 4), ca.SX.sym("a")
    rows = footprint_pair_rows(pose_i, size_i, pose_j, second[1], L_ij, L_ji, 0.1, alpha)
    f = ca.Function("rows", [pose_i, size_i, pose_j, L_ij, L_ji, alpha], [rows.separation, rows.coupling, rows.norm_sq])
    sep, couple, norm = (np.array(v).ravel() for v in f(first[0], first[1], second[0], lam_ij, lam_ji, slack))
    assert sep[0] == pytest.approx(-b_i @ lam_ij - b_j @ lam_ji + slack, abs=1e-12)
    np.testing.assert_allclose(couple, A_i.T @ lam_ij + A_j.T @ lam_ji, atol=1e-12)
    assert norm[0] == pytest.approx(np.sum((A_i.T @ lam_ij) ** 2), abs=1e-12)
    G, g = random_polygon(seed)
    lam_obs = rng.exponential(size=len(g))
    obstacle = footprint_polytope_rows(ca.DM(first[0]), first[1], G, g, ca.DM(lam_ij), ca.DM(lam_obs), 0.1)
    sep, couple, norm = (v.ravel() for v in evaluate(obstacle))
    assert sep[0] == pytest.approx(-b_i @ lam_ij - g @ lam_obs, abs=1e-12)
    np.testing.assert_allclose(couple, A_i.T @ lam_ij + G.T @ lam_obs, atol=1e-12)
    assert norm[0] == pytest.approx(np.sum((A_i.T @ lam_ij) ** 2), abs=1e-12)


def satisfied(rows, slack_value=None, tol=1e-9):
    sep, couple, norm = evaluate(rows)
    (s_lo, _), (n_lo, n_hi) = rows.separation_bounds, rows.norm_bounds
    return (sep >= s_lo - tol) & np.all(np.abs(couple) <= tol, axis=0) & (norm >= n_lo - tol) & (norm <= n_hi + tol)


@SETTINGS
@given(st.lists(poses, min_size=1, max_size=6), sizes, st.lists(poses, min_size=6, max_size=6), sizes,
       st.floats(0.01, 1.0))
def test_rows_at_the_best_certificate_hold_iff_the_distance_reaches_d_min(list_i, size_i, list_j, size_j, d_min):
    pose_i, pose_j = np.array(list_i), np.array(list_j[: len(list_i)])
    distance = rectangle_distance(pose_i, size_i, pose_j, size_j)
    assume(np.all(np.abs(distance - d_min) > 1e-6))
    best = rectangle_pair_certificates(pose_i, size_i, pose_j, size_j)
    args = (ca.DM(pose_i.T), size_i, ca.DM(pose_j.T), size_j, ca.DM(best.lam_ij.T), ca.DM(best.lam_ji.T), d_min)
    expected = distance >= d_min
    np.testing.assert_array_equal(satisfied(footprint_pair_rows(*args)).ravel(), expected)
    zero = ca.DM.zeros(1, len(pose_i))
    np.testing.assert_array_equal(satisfied(footprint_pair_rows(*args, slack=zero)).ravel(), expected)
    needed = ca.DM(np.maximum(d_min - best.value, 0.0)[None, :])
    assert np.all(satisfied(footprint_pair_rows(*args, slack=needed)))


@SETTINGS
@given(st.integers(0, 10_000), st.lists(poses, min_size=1, max_size=6), sizes, st.floats(0.01, 1.0))
def test_obstacle_rows_at_the_best_certificate_hold_iff_the_distance_reaches_d_min(seed, pose_list, size, d_min):
    G, g = random_polygon(seed)
    pose = np.array(pose_list)
    distance = rectangle_polytope_distance(pose, size, G, g)
    assume(np.all(np.abs(distance - d_min) > 1e-6))
    best = rectangle_polytope_certificates(pose, size, G, g)
    args = (ca.DM(pose.T), size, G, g, ca.DM(best.lam_ij.T), ca.DM(best.lam_ji.T), d_min)
    np.testing.assert_array_equal(satisfied(footprint_polytope_rows(*args)).ravel(), distance >= d_min)
    needed = ca.DM(np.maximum(d_min - best.value, 0.0)[None, :])
    assert np.all(satisfied(footprint_polytope_rows(*args, slack=needed)))


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(footprints, footprints)
def test_ipopt_maximum_over_the_hard_rows_is_the_distance(first, second):
    distance = float(rectangle_distance(*first, *second))
    L_ij, L_ji = ca.SX.sym("lij", 4), ca.SX.sym("lji", 4)
    rows = footprint_pair_rows(ca.DM(first[0]), first[1], ca.DM(second[0]), second[1], L_ij, L_ji, 0.05)
    expression, lower, upper = rows.stacked()
    problem = {"x": ca.vertcat(L_ij, L_ji), "f": -rows.separation, "g": expression[1:, :]}
    solver = ca.nlpsol("best", "ipopt", problem, {"print_time": False, "ipopt.print_level": 0, "ipopt.sb": "yes",
                                                  "ipopt.tol": 1e-12})
    out = solver(x0=np.full(8, 0.1), lbx=0.0, ubx=np.inf, lbg=lower[1:, 0], ubg=upper[1:, 0])
    assert solver.stats()["success"]
    assert -float(out["f"]) == pytest.approx(distance, abs=1e-6)


def test_hard_rows_need_a_positive_margin_and_stack_with_their_bounds():
    lam = ca.SX.sym("l", 4, 3)
    pose = ca.SX.sym("p", 3, 3)
    with pytest.raises(ValueError, match="d_min > 0"):
        footprint_pair_rows(pose, [1.0, 0.5], pose, [1.0, 0.5], lam, lam, 0.0)
    rows = footprint_pair_rows(pose, [1.0, 0.5], pose, [1.0, 0.5], lam, lam, 0.2, slack=ca.SX.sym("a", 1, 3))
    expression, lower, upper = rows.stacked()
    assert expression.shape == lower.shape == upper.shape == (4, 3)
    np.testing.assert_array_equal(lower[:, 0], [0.2, 0.0, 0.0, 1.0])
    np.testing.assert_array_equal(upper[:, 0], [np.inf, 0.0, 0.0, 1.0])
    assert [name for name, *_ in rows.blocks()] == ["sep", "couple", "norm"]
