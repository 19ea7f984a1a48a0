"""The OBCA certificate law, checked against independent geometry.

For a point p and a bounded polytope {x : G x <= g}:
* max over lambda >= 0, ||G^T lambda|| <= 1 of (G p - g)^T lambda = Euclidean distance (p outside);
* max over lambda >= 0, ||G^T lambda|| = 1  of (G p - g)^T lambda = -penetration depth (p inside).
The maxima are computed with the formulation's own certificate expressions and IPOPT; the
references come from a projection QP (SLSQP) and from the facet distances of a convex hull.
"""

import casadi as ca
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize
from scipy.spatial import ConvexHull

from swarmpc.formulation.ocp import certificate_terms, polytope_certificate_terms
from swarmpc.model.geometry import box_certificate, box_certificates, box_exterior_distance, point_box_distance


def best_certificate(point, G, g, soft):
    lam = ca.SX.sym("lam", G.shape[0])
    margin, norm_sq = polytope_certificate_terms(ca.DM(point), lam, G, g)
    solver = ca.nlpsol("cert", "ipopt", {"x": lam, "f": -margin, "g": norm_sq},
                       {"print_time": False, "ipopt.print_level": 0, "ipopt.sb": "yes", "ipopt.tol": 1e-10})
    best = -np.inf
    for start in np.eye(G.shape[0]) / np.linalg.norm(G, axis=1)[:, None]:
        out = solver(x0=start, lbx=0, ubx=np.inf, lbg=1.0 if soft else -np.inf, ubg=1.0)
        if solver.stats()["success"]:
            best = max(best, -float(out["f"]))
    return best


def projection_distance(point, vertices):
    """Distance to the convex hull of ``vertices`` by a QP over convex weights."""
    n = len(vertices)
    result = minimize(
        lambda w: np.sum((w @ vertices - point) ** 2),
        np.full(n, 1.0 / n),
        jac=lambda w: 2 * vertices @ (w @ vertices - point),
        constraints=[{"type": "eq", "fun": lambda w: np.sum(w) - 1, "jac": lambda w: np.ones(n)}],
        bounds=[(0, 1)] * n,
        method="SLSQP",
        options={"ftol": 1e-14, "maxiter": 500},
    )
    return float(np.sqrt(result.fun))


def polytope(seed, dim):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(8 + 2 * dim, dim))
    hull = ConvexHull(points)
    G, g = hull.equations[:, :dim], -hull.equations[:, dim]
    return G, g, points[hull.vertices]


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 10_000), st.sampled_from([2, 3]), st.floats(0.2, 3.0))
def test_hard_certificate_equals_distance_outside(seed, dim, scale):
    G, g, vertices = polytope(seed, dim)
    direction = np.random.default_rng(seed + 1).normal(size=dim)
    centre = vertices.mean(axis=0)
    # beyond the ball round the vertices' mean that holds every vertex: outside the polytope
    reach = np.linalg.norm(vertices - centre, axis=1).max()
    point = centre + direction / np.linalg.norm(direction) * (reach + scale)
    assert np.any(G @ point > g)
    reference = projection_distance(point, vertices)
    assert best_certificate(point, G, g, soft=False) == pytest.approx(reference, abs=1e-5)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 10_000), st.sampled_from([2, 3]), st.floats(0.0, 0.9))
def test_soft_certificate_equals_penetration_inside(seed, dim, blend):
    G, g, vertices = polytope(seed, dim)
    centre = vertices.mean(axis=0)
    point = centre + blend * (vertices[0] - centre)
    assert np.all(G @ point < g)
    depth = float(np.min(g - G @ point))  # hull facets are unit normals: the exit distance
    assert best_certificate(point, G, g, soft=True) == pytest.approx(-depth, abs=1e-5)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=3, max_size=3), st.lists(st.floats(0.05, 1.0), min_size=3, max_size=3))
def test_box_certificate_is_feasible_and_tight(offset, half):
    offset, half = np.array(offset), np.array(half)
    lam = box_certificate(offset, half)
    margin, norm_sq = certificate_terms(ca.DM(offset), ca.DM(lam), ca.DM(half))
    assert float(norm_sq) == pytest.approx(1.0)
    assert float(margin) == pytest.approx(point_box_distance(offset, half), abs=1e-9)


def test_zero_dmin_hard_form_excludes_nothing():
    """The trap of design.md section 9: with d_min = 0, lambda = 0 certifies a point inside."""
    margin, norm_sq = certificate_terms(ca.DM([0.0, 0.0]), ca.DM.zeros(4), ca.DM([0.3, 0.3]))
    assert float(margin) >= 0.0 and float(norm_sq) <= 1.0


@given(
    st.lists(st.lists(st.floats(-2, 2), min_size=3, max_size=3), min_size=1, max_size=6),
    st.lists(st.floats(0.05, 1.0), min_size=3, max_size=3),
)
def test_batched_exterior_distance_is_the_pointwise_distance_outside(offsets, half):
    """The batched separation used by the ADMM checks agrees, offset by offset, with the
    positive part of the signed point-to-box distance."""
    offsets, half = np.array(offsets), np.array(half)
    batched = box_exterior_distance(offsets.T, half.reshape(-1, 1), axis=0)
    expected = [max(point_box_distance(q, half), 0.0) for q in offsets]
    np.testing.assert_allclose(batched, expected, atol=1e-12)


def _box_certificate_reference(offset: np.ndarray, half: np.ndarray) -> np.ndarray:
    """The certificate of one offset as first written: the normalised outside part of the offset,
    or the shallowest exit axis inside."""
    excess = np.abs(offset) - half
    direction = np.zeros(offset.size)
    if np.any(excess > 0):
        direction = np.sign(offset) * np.maximum(excess, 0.0)
        direction /= np.linalg.norm(direction)
    else:
        axis = int(np.argmax(excess))
        direction[axis] = 1.0 if offset[axis] >= 0 else -1.0
    return np.concatenate([np.maximum(direction, 0.0), np.maximum(-direction, 0.0)])


@settings(max_examples=200, deadline=None)
@given(dim=st.sampled_from([2, 3]), data=st.data())
def test_batched_box_certificates_equal_the_rows_one_by_one_bit_for_bit(dim: int, data: st.DataObject) -> None:
    rows = data.draw(st.integers(1, 12))
    flat = data.draw(st.lists(st.floats(-3.0, 3.0, allow_nan=False), min_size=rows * dim, max_size=rows * dim))
    offsets = np.array(flat).reshape(rows, dim)
    half = np.array(data.draw(st.lists(st.floats(0.05, 1.0), min_size=dim, max_size=dim)))
    batch = box_certificates(offsets, half)
    expected = np.array([_box_certificate_reference(q, half) for q in offsets])
    assert np.array_equal(batch, expected)
    assert np.array_equal(box_certificate(offsets[0], half), expected[0])


@settings(max_examples=150, deadline=None)
@given(st.integers(0, 10_000), st.integers(2, 3), st.integers(1, 9))
def test_polytope_vertices_tells_bounded_from_unbounded_as_linear_programs_do(seed, dim, rows):
    """A polytope around the origin is bounded iff no extent along an axis is infinite (2d linear
    programs, the reference); bounded ones get vertices that meet every row."""
    from scipy.optimize import linprog

    from swarmpc.model.geometry import polytope_vertices

    rng = np.random.default_rng(seed)
    G = rng.normal(size=(rows, dim))
    if rng.random() < 0.5:  # half of them open to one side
        G[:, 0] = np.abs(G[:, 0])
    g = rng.uniform(0.5, 2.0, rows)
    extents = [linprog(-e, A_ub=G, b_ub=g, bounds=[(None, None)] * dim, method="highs").status
               for e in np.vstack([np.eye(dim), -np.eye(dim)])]
    if 3 in extents:
        with pytest.raises(ValueError, match="unbounded"):
            polytope_vertices(G, g)
    else:
        vertices = polytope_vertices(G, g)
        assert len(vertices) >= dim + 1 and np.all(vertices @ G.T <= g + 1e-9)
