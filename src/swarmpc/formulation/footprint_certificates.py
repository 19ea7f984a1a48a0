"""OBCA certificates between oriented rectangular footprints and convex polygons: the best ones in
closed form, and the CasADi rows of the condition.

Two polygons P_i = {y : A_i y <= b_i} and P_j = {y : A_j y <= b_j} (a footprint is
A = G R(theta)^T, b = g + G R(theta)^T c, :func:`swarmpc.model.footprint.rectangle_halfspaces`)
keep Euclidean distance >= d_min iff certificates lambda_ij, lambda_ji >= 0 exist with

* hard:  -b_i^T lambda_ij - b_j^T lambda_ji >= d_min,   A_i^T lambda_ij + A_j^T lambda_ji = 0,
  ||A_i^T lambda_ij||_2 <= 1;
* soft:  the same first row plus a slack alpha >= 0 on its left (kappa alpha in the cost), the
  coupling row unchanged, and ||A_i^T lambda_ij||_2 = 1,

as :mod:`swarmpc.formulation.ocp` states them for a point and a polytope.

What the best certificate is
----------------------------
The condition is the Lagrange dual of min ||y_j - y_i|| over y_i in P_i, y_j in P_j. Write
n = A_i^T lambda_ij, so A_j^T lambda_ji = -n.

* Weak duality: for y_i in P_i and y_j in P_j, -b_i^T lambda_ij <= -n^T y_i and
  -b_j^T lambda_ji <= n^T y_j, so the value is <= n^T (y_j - y_i) <= ||n|| ||y_j - y_i||. Any
  feasible certificate bounds the distance from below (the signed distance when ||n|| = 1).
* For a fixed n the two multipliers decouple, and by LP duality
  min {b^T l : A^T l = n, l >= 0} = max {n^T y : A y <= b} = h_P(n), the support function. The
  best value along n is V(n) = -h_{P_i}(n) - h_{P_j}(-n) = min_{P_j} n^T y - max_{P_i} n^T y, the
  gap between the projections of the two polygons on n.
* Its maximum over ||n|| <= 1 is the distance (strong duality: both polygons have interiors);
  over ||n|| = 1 it is the signed distance, minus the penetration depth inside (the SAT argument
  of :mod:`swarmpc.model.footprint`).
* In the plane the maximiser is one of finitely many directions. Disjoint convex polygons have
  closest points that include a vertex, the other being a vertex (n is the unit difference of the
  two) or an interior point of an edge (n is plus or minus that edge's unit normal); for touching
  or overlapping polygons a SAT axis, plus or minus an edge normal, attains the depth. Every
  candidate is a feasible certificate, hence a lower bound, and the optimum is among them: the
  largest candidate IS the optimum, with no solver and no tolerance on the value.
* The multipliers of the chosen n: for a rectangle, A^T l = R (l_+ - l_-) = n is solved at least
  cost by l = [max(R^T n, 0); max(-R^T n, 0)] (then b^T l = h^T |R^T n| + c^T n = h_P(n), with h
  the half-size). For another polygon the LP min {b^T l : A^T l = n, l >= 0} has two equality
  rows, so an optimal basic solution has at most two nonzero entries: the cheapest nonnegative
  solution over the pairs of facets is exact. A tolerance on "nonnegative" (rounding at the edge
  of a vertex's normal cone) is absorbed by recomputing n from the clamped multiplier, so it can
  cost optimality by a rounding error, never feasibility.

Every value returned is the literal -b_i^T lambda_ij - b_j^T lambda_ji of the returned
multipliers, and ||A_i^T lambda_ij|| = 1, so each certificate suits both forms and the constraint
is tight at the poses it was computed for. Arrays hold the rows on the LAST axis ((..., 4) for a
footprint); transpose to the OCP's (rows, K) blocks.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any, NamedTuple

import casadi as ca
import numpy as np

from swarmpc.model.footprint import (
    edge_normals,
    footprint_vertices,
    polygon_vertices,
    rectangle_halfspaces,
)

__all__ = [
    "CertificateRows",
    "HalfspacePolygon",
    "PairCertificates",
    "PolytopeFootprintCertifier",
    "best_direction",
    "best_pair_certificates",
    "certificate_value",
    "footprint_pair_rows",
    "footprint_polytope_rows",
    "rectangle_pair_certificates",
    "rectangle_polytope_certificates",
]

_PARALLEL = 1e-12
"""Smallest |det| of two unit facet normals for the pair to carry a basic solution."""

_NEGATIVE = 1e-12
"""Relative rounding below zero still accepted as a nonnegative multiplier (then clamped)."""


class PairCertificates(NamedTuple):
    """Certificates lambda_ij (..., rows of P_i), lambda_ji (..., rows of P_j), both >= 0 with
    A_i^T lambda_ij = -A_j^T lambda_ji of unit length, and the value (...) they certify:
    -b_i^T lambda_ij - b_j^T lambda_ji, the signed distance of the two polygons."""

    lam_ij: np.ndarray
    lam_ji: np.ndarray
    value: np.ndarray


def certificate_value(b_i: np.ndarray, b_j: np.ndarray, lam_ij: np.ndarray, lam_ji: np.ndarray) -> np.ndarray:
    """-b_i^T lambda_ij - b_j^T lambda_ji (...): the distance bound of given certificates (rows on
    the last axis, leading axes broadcast)."""
    lam_ij, lam_ji = np.asarray(lam_ij, float), np.asarray(lam_ji, float)
    return -np.sum(np.asarray(b_i, float) * lam_ij, axis=-1) - np.sum(np.asarray(b_j, float) * lam_ji, axis=-1)


def best_direction(V_i: np.ndarray, V_j: np.ndarray) -> np.ndarray:
    """The unit n (..., 2) maximising min_{P_j} n^T y - max_{P_i} n^T y over the candidates of the
    module docstring, for counter-clockwise polygons V_i (..., n, 2) and V_j (..., m, 2)."""
    lead = np.broadcast_shapes(V_i.shape[:-2], V_j.shape[:-2])
    normals = np.concatenate(
        [np.broadcast_to(edge_normals(V_i), (*lead, *V_i.shape[-2:])),
         np.broadcast_to(edge_normals(V_j), (*lead, *V_j.shape[-2:]))], axis=-2)
    diff = (V_j[..., None, :, :] - V_i[..., :, None, :]).reshape(*lead, -1, 2)
    length = np.linalg.norm(diff, axis=-1, keepdims=True)
    candidates = np.concatenate([normals, -normals, diff / np.where(length > 0, length, 1.0)], axis=-2)
    valid = np.linalg.norm(candidates, axis=-1) > 0.5  # unit, or zero for a degenerate edge or pair
    low_j = np.einsum("...kd,...cd->...kc", V_j, candidates).min(axis=-2)
    high_i = np.einsum("...kd,...cd->...kc", V_i, candidates).max(axis=-2)
    pick = np.argmax(np.where(valid, low_j - high_i, -np.inf), axis=-1)
    return np.take_along_axis(candidates, pick[..., None, None], axis=-2)[..., 0, :]


def _rectangle_multipliers(theta: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """The least-cost l (..., 4) >= 0 with (G R(theta)^T)^T l = normal (..., 2)."""
    cos, sin = np.cos(theta), np.sin(theta)
    body = np.stack([cos * normal[..., 0] + sin * normal[..., 1], -sin * normal[..., 0] + cos * normal[..., 1]], -1)
    return np.concatenate([np.maximum(body, 0.0), np.maximum(-body, 0.0)], axis=-1)


class HalfspacePolygon:
    """A bounded convex polygon {y : A y <= b} with what certificates need: its counter-clockwise
    vertices and the support multipliers of any direction (facet pairs and their inverses built once).

    Parameters
    ----------
    A : (m, 2) array
        Facet normals (any positive scaling per row; redundant rows allowed).
    b : (m,) array
        Offsets.
    """

    def __init__(self, A: np.ndarray, b: np.ndarray) -> None:
        self.A = np.atleast_2d(np.asarray(A, float))
        self.b = np.asarray(b, float).reshape(-1)
        self.vertices = polygon_vertices(self.A, self.b)
        unit = self.A / np.linalg.norm(self.A, axis=1)[:, None]
        pairs = [p for p in itertools.combinations(range(len(self.b)), 2)
                 if abs(np.linalg.det(unit[list(p)])) > _PARALLEL]
        self.pairs = np.array(pairs, dtype=int).reshape(-1, 2)
        self.inverses = np.linalg.inv(np.swapaxes(self.A[self.pairs], 1, 2))  # (P, 2, 2): mu = inv @ n

    def support(self, directions: np.ndarray) -> np.ndarray:
        """h(n) = max_y n^T y over the polygon, for directions (..., 2)."""
        return np.max(np.asarray(directions, float) @ self.vertices.T, axis=-1)

    def multipliers(self, directions: np.ndarray) -> np.ndarray:
        """l (..., m) >= 0 with A^T l = n and b^T l = h(n), for directions n (..., 2)."""
        n = np.asarray(directions, float)
        flat = n.reshape(-1, 2)
        mu = np.einsum("pab,kb->kpa", self.inverses, flat)  # (K, P, 2)
        scale = np.maximum(1.0, np.max(np.abs(mu), axis=-1))
        feasible = np.all(mu >= -_NEGATIVE * scale[..., None], axis=-1)
        mu = np.maximum(mu, 0.0)
        cost = np.where(feasible, np.einsum("kpa,pa->kp", mu, self.b[self.pairs]), np.inf)
        pick = np.argmin(cost, axis=-1)
        rows = np.arange(len(flat))
        lam = np.zeros((len(flat), len(self.b)))
        for slot in range(2):
            lam[rows, self.pairs[pick, slot]] = mu[rows, pick, slot]
        return lam.reshape(*n.shape[:-1], len(self.b))


def _unit_normal(lam: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lam, A^T lam) rescaled so that ||A^T lam|| = 1 (zero stays zero)."""
    normal = lam @ A
    length = np.linalg.norm(normal, axis=-1, keepdims=True)
    length = np.where(length > 0, length, 1.0)
    return lam / length, normal / length


def rectangle_pair_certificates(
    pose_i: np.ndarray, size_i: np.ndarray, pose_j: np.ndarray, size_j: np.ndarray
) -> PairCertificates:
    """The best certificates of two footprints, in closed form and for many pairs at once.

    Parameters
    ----------
    pose_i, pose_j : (..., 3) array
        (x, y, theta) of each footprint; leading axes broadcast (e.g. steps x pairs).
    size_i, size_j : (..., 2) array
        (length, width).

    Returns
    -------
    PairCertificates
        ``lam_ij`` (..., 4) and ``lam_ji`` (..., 4) in the row order of
        :func:`~swarmpc.model.footprint.rectangle_halfspaces`, and ``value`` (...): the exact
        distance when the footprints are apart, minus the penetration depth when they overlap.
    """
    pose_i, pose_j = np.asarray(pose_i, float), np.asarray(pose_j, float)
    size_i, size_j = np.asarray(size_i, float), np.asarray(size_j, float)
    normal = best_direction(footprint_vertices(pose_i, size_i), footprint_vertices(pose_j, size_j))
    lam_ij = _rectangle_multipliers(pose_i[..., 2], normal)
    lam_ji = _rectangle_multipliers(pose_j[..., 2], -normal)
    _, b_i = rectangle_halfspaces(pose_i[..., :2], pose_i[..., 2], size_i[..., 0], size_i[..., 1])
    _, b_j = rectangle_halfspaces(pose_j[..., :2], pose_j[..., 2], size_j[..., 0], size_j[..., 1])
    return PairCertificates(lam_ij, lam_ji, certificate_value(b_i, b_j, lam_ij, lam_ji))


def best_pair_certificates(A_i: np.ndarray, b_i: np.ndarray, A_j: np.ndarray, b_j: np.ndarray) -> PairCertificates:
    """The best certificates of two bounded convex polygons {A_i y <= b_i} and {A_j y <= b_j}
    (one pair; footprints or obstacles alike): ``lam_ij`` (rows of A_i,), ``lam_ji`` (rows of
    A_j,) and their value, the signed distance of the two polygons."""
    P_i, P_j = HalfspacePolygon(A_i, b_i), HalfspacePolygon(A_j, b_j)
    normal = best_direction(P_i.vertices, P_j.vertices)
    lam_ij, normal = _unit_normal(P_i.multipliers(normal), P_i.A)
    lam_ji = P_j.multipliers(-normal)
    return PairCertificates(lam_ij, lam_ji, certificate_value(P_i.b, P_j.b, lam_ij, lam_ji))


class PolytopeFootprintCertifier:
    """Best certificates of footprints against one static convex polygon {y : G y <= g}: the
    polygon's vertices and facet pairs are built once, then any number of poses are evaluated.

    Parameters
    ----------
    G : (m, 2) array
        Facet normals of the obstacle (any positive scaling per row).
    g : (m,) array
        Offsets.
    """

    def __init__(self, G: np.ndarray, g: np.ndarray) -> None:
        self.polygon = HalfspacePolygon(G, g)

    def __call__(self, pose: np.ndarray, size: np.ndarray) -> PairCertificates:
        """Certificates of footprints of poses (..., 3) and sizes (..., 2): ``lam_ij`` (..., 4) of
        the footprint, ``lam_ji`` (..., m) of the obstacle and the signed distance ``value`` (...)."""
        pose, size = np.asarray(pose, float), np.asarray(size, float)
        normal = best_direction(footprint_vertices(pose, size), self.polygon.vertices)
        lam_ji, minus_normal = _unit_normal(self.polygon.multipliers(-normal), self.polygon.A)
        lam_ij = _rectangle_multipliers(pose[..., 2], -minus_normal)
        _, b_i = rectangle_halfspaces(pose[..., :2], pose[..., 2], size[..., 0], size[..., 1])
        return PairCertificates(lam_ij, lam_ji, certificate_value(b_i, self.polygon.b, lam_ij, lam_ji))


def rectangle_polytope_certificates(
    pose: np.ndarray, size: np.ndarray, G: np.ndarray, g: np.ndarray
) -> PairCertificates:
    """Best certificates of footprints (poses (..., 3), sizes (..., 2)) against {y : G y <= g}
    (one-off convenience; build a :class:`PolytopeFootprintCertifier` to reuse the polygon)."""
    return PolytopeFootprintCertifier(G, g)(pose, size)


@dataclass(frozen=True)
class CertificateRows:
    """The rows of one footprint OBCA condition per column k (symbolic, K columns).

    ``separation`` (1, K) is -b_i^T lambda_ij - b_j^T lambda_ji (+ alpha in the soft form),
    ``coupling`` (2, K) is A_i^T lambda_ij + A_j^T lambda_ji and ``norm_sq`` (1, K) is
    ||A_i^T lambda_ij||^2; each with its (lower, upper) bounds.
    """

    separation: Any
    coupling: Any
    norm_sq: Any
    separation_bounds: tuple[float, float]
    norm_bounds: tuple[float, float]
    coupling_bounds: tuple[float, float] = (0.0, 0.0)

    def blocks(self) -> list[tuple[str, Any, float, float]]:
        """(name, expression, lower, upper) per block, ready for ``ProblemBuilder.constrain``
        (prefix the names with the pair's tag)."""
        return [
            ("sep", self.separation, *self.separation_bounds),
            ("couple", self.coupling, *self.coupling_bounds),
            ("norm", self.norm_sq, *self.norm_bounds),
        ]

    def stacked(self) -> tuple[Any, np.ndarray, np.ndarray]:
        """All four rows as one (4, K) expression with (4, K) lower and upper bounds."""
        expression = ca.vertcat(self.separation, self.coupling, self.norm_sq)
        shape = (4, int(expression.shape[1]))
        bounds = [self.separation_bounds, self.coupling_bounds, self.coupling_bounds, self.norm_bounds]
        lower = np.broadcast_to(np.array([b[0] for b in bounds])[:, None], shape)
        upper = np.broadcast_to(np.array([b[1] for b in bounds])[:, None], shape)
        return expression, lower, upper


def _as_column(value: Any, rows: int) -> Any:
    """A CasADi column for a numeric or symbolic vector of ``rows`` entries."""
    if isinstance(value, ca.SX | ca.MX | ca.DM):
        return value
    return ca.DM(np.asarray(value, float).reshape(rows, 1))


def _footprint_terms(pose: Any, size: Any, lam: Any) -> tuple[Any, Any, Any]:
    """A^T lambda (2, K), b^T lambda (1, K) and ||A^T lambda||^2 (1, K) of footprints of poses
    (3, K) and one size (2,) for multipliers lambda (4, K) in the row order G = [I; -I].

    With m = lambda_+ - lambda_- and s = lambda_+ + lambda_- (body frame), A^T lambda = R m and
    b^T lambda = (l/2, w/2)^T s + c^T R m; the norm is taken as ||m||^2, equal to ||R m||^2.
    """
    half = 0.5 * _as_column(size, 2)
    cos, sin = ca.cos(pose[2, :]), ca.sin(pose[2, :])
    m0, m1 = lam[0, :] - lam[2, :], lam[1, :] - lam[3, :]
    normal = ca.vertcat(cos * m0 - sin * m1, sin * m0 + cos * m1)
    offset = half[0] * (lam[0, :] + lam[2, :]) + half[1] * (lam[1, :] + lam[3, :]) + ca.sum1(pose[:2, :] * normal)
    return normal, offset, m0**2 + m1**2


def _rows(margin: Any, coupling: Any, norm_sq: Any, d_min: float, slack: Any | None) -> CertificateRows:
    """The hard form without ``slack``, the soft form with it (ocp.add_certificate's bounds)."""
    if slack is None:
        if d_min <= 0:
            raise ValueError(f"the hard form needs d_min > 0 (lambda = 0 satisfies it otherwise), got {d_min}")
        return CertificateRows(margin, coupling, norm_sq, (d_min, np.inf), (-np.inf, 1.0))
    return CertificateRows(margin + slack, coupling, norm_sq, (d_min, np.inf), (1.0, 1.0))


def footprint_pair_rows(
    pose_i: Any, size_i: Any, pose_j: Any, size_j: Any, lam_ij: Any, lam_ji: Any, d_min: float,
    slack: Any | None = None,
) -> CertificateRows:
    """OBCA rows keeping two footprints d_min apart, for K columns (steps) at once.

    Parameters
    ----------
    pose_i, pose_j : (3, K) CasADi
        (x, y, theta) of each footprint per column.
    size_i, size_j : (2,) array or CasADi column
        (length, width).
    lam_ij, lam_ji : (4, K) CasADi
        Certificates (the caller bounds them >= 0), rows in the order of
        :func:`~swarmpc.model.footprint.rectangle_halfspaces`.
    d_min : float
        Required distance.
    slack : (1, K) CasADi, optional
        alpha >= 0 of the soft form (the caller bounds it and prices kappa alpha); None for the
        hard form.

    Returns
    -------
    CertificateRows
        Hard: separation >= d_min, coupling = 0, norm_sq <= 1. Soft: separation (with alpha)
        >= d_min, coupling = 0, norm_sq = 1.
    """
    normal_i, offset_i, norm_sq = _footprint_terms(pose_i, size_i, lam_ij)
    normal_j, offset_j, _ = _footprint_terms(pose_j, size_j, lam_ji)
    return _rows(-offset_i - offset_j, normal_i + normal_j, norm_sq, d_min, slack)


def footprint_polytope_rows(
    pose: Any, size: Any, G: np.ndarray, g: np.ndarray, lam_ij: Any, lam_ji: Any, d_min: float,
    slack: Any | None = None,
) -> CertificateRows:
    """OBCA rows keeping a footprint d_min away from the static polygon {y : G y <= g}.

    As :func:`footprint_pair_rows` with P_j = the obstacle: ``lam_ij`` (4, K) is the footprint's
    certificate and ``lam_ji`` (rows of G, K) the obstacle's; the norm row bounds the
    footprint's ||A_i^T lambda_ij||^2.
    """
    G_dm = ca.DM(np.atleast_2d(np.asarray(G, float)))
    g_dm = _as_column(g, G_dm.shape[0])
    normal_i, offset_i, norm_sq = _footprint_terms(pose, size, lam_ij)
    margin = -offset_i - ca.mtimes(g_dm.T, lam_ji)
    return _rows(margin, normal_i + ca.mtimes(G_dm.T, lam_ji), norm_sq, d_min, slack)
