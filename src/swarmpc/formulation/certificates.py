"""The best OBCA dual certificates of points against boxes and polytopes, in closed form.

The collision constraints of :mod:`swarmpc.formulation.ocp` certify that a point q keeps a
distance from the polytope P = {x : G x <= g} through a multiplier lambda:

    (G q - g)^T lambda >= d_min,   lambda >= 0,   ||G^T lambda||_2 <= 1   (hard; = 1 in the soft form).

For an agent pair, q = p_i - p_j and P is the box [-delta, delta] (G = [I; -I], g = [delta; delta]):
the Euclidean distance of the offset to the delta box, i.e. of the two agents' delta boxes
(``swarmpc.model.geometry.box_signed_distance``). The sequential-QP local step
(:mod:`swarmpc.solvers.qp_local`) holds lambda fixed, which makes every such constraint LINEAR in
the positions; after each QP it moves lambda to the best certificate of the new positions. This
module computes that best certificate, vectorised over horizon steps (time on the last axis).

What "best" means, and why it is safe
-------------------------------------
Projecting q onto P, min ||x - q|| s.t. G x <= g, has the Lagrange dual
max_{lambda >= 0, ||G^T lambda|| <= 1} (G q - g)^T lambda, so

* weak duality: for ANY dual-feasible lambda and ANY x in P,
  (G q - g)^T lambda <= (G q - G x)^T lambda = (q - x)^T G^T lambda <= ||q - x||,
  so a plan meeting the linear constraint with a fixed feasible lambda is >= d_min away: the
  QP's answer is safe as it stands, whatever lambda it was given;
* strong duality: for q outside P the maximum equals dist(q, P) and is attained at
  lambda* = mu / ||q - x*||, where x* is the projection and mu >= 0 its KKT multiplier
  (q - x* = G^T mu, mu_i (G_i x* - g_i) = 0), so ||G^T lambda*|| = 1 and the value is
  mu^T (G q - g) / r = mu^T G (q - x*) / r = ||G^T mu||^2 / r = r.

For q inside P no certificate is positive; under the soft form's ||G^T lambda|| = 1 the maximum is
minus the penetration depth, attained by the unit normal of the shallowest facet (for a unit n,
min {s^T lambda : G^T lambda = n, lambda >= 0} is the support of P - q in direction n, which is at
least the depth). Every certificate returned here has ||G^T lambda|| = 1 (feasible for both forms)
and value = the signed distance: the linearised constraint is tight at the given point.

Closed forms
------------
* Box (half-size h, offset q): outside, e = max(|q| - h, 0), n = sign(q) e / ||e||,
  lambda = [max(n, 0); max(-n, 0)], value = sum_a |n_a| (|q_a| - h_a) = ||e||. Inside: the axis
  of largest |q_a| - h_a, value = |q_a| - h_a = -depth.
* Polytope: by Caratheodory, mu is supported on at most d linearly independent active facets S
  (S inside the active set of some vertex when P has vertices), and on its support
  mu_S = (G_S G_S^T)^{-1} (G_S q - g_S). Each candidate S gives the feasible certificate
  lambda_S = max(mu_S, 0) / ||G_S^T max(mu_S, 0)|| (single facets: the unit facet normal, also
  inside); every candidate is a lower bound on the distance (weak duality) and the optimal one
  is among them, so the largest candidate value IS the optimum. Tolerances (which subsets are
  candidates) can cost optimality only, never feasibility: a spurious candidate loses the max. The candidate
  supports and their small inverses are computed once per polytope (:class:`PolytopeCertifier`).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

__all__ = [
    "Certificates",
    "PolytopeCertifier",
    "box_certificates",
    "box_normals",
    "certificate_values",
    "pair_rows",
    "polytope_certificates",
]

_SINGULAR = 1e-10
"""Smallest |det| of a (normalised) support's Gram matrix for the support to be a candidate."""


@dataclass(frozen=True)
class Certificates:
    """Certificates of K points: ``lam`` (m, K) with lambda >= 0 and ||G^T lambda||_2 = 1 per
    column, and ``value`` (K,) = (G q - g)^T lambda, the signed distance each one certifies."""

    lam: np.ndarray
    value: np.ndarray


def _columns(points: np.ndarray) -> tuple[np.ndarray, bool]:
    """Points as (d, K) columns; True when a single (d,) point was given."""
    array = np.asarray(points, float)
    return (array[:, None], True) if array.ndim == 1 else (array, False)


def _shaped(result: Certificates, single: bool) -> Certificates:
    return Certificates(result.lam[:, 0], result.value[0]) if single else result


def box_certificates(offsets: np.ndarray, half_size: np.ndarray) -> Certificates:
    """The best certificates of offsets (d, K) or (d,) against the box [-half, half].

    Parameters
    ----------
    offsets : (d, K) or (d,) array
        q = p_i - p_j for an agent pair (or p - centre for a box obstacle), time on the last axis.
    half_size : (d,) array, scalar, or (d, K) array
        Half-size of the box (delta; an obstacle box's half-size); (d, K): one box per column
        (the pairs of several bodies in one call).

    Returns
    -------
    Certificates
        ``lam`` (2d, K) in the row order G = [I; -I] of :func:`swarmpc.formulation.ocp.certificate_terms`
        and ``value`` (K,): the Euclidean distance of q to the box outside, minus the depth inside.
    """
    q, single = _columns(offsets)
    d, K = q.shape
    half = np.asarray(half_size, float)
    if half.ndim == 2 and half.shape[1] != 1:  # one box per column
        if half.shape != (d, K):
            raise ValueError(f"box_certificates: half_size per column must be ({d}, {K}), got {half.shape}")
    else:
        half = half.reshape(-1, 1)  # (d, 1) or (1, 1): broadcast on the columns
        if half.shape[0] not in (1, d):
            raise ValueError(f"box_certificates: half_size must be a scalar or ({d},), got {half.shape[0]} values")
    direction, value = box_normals(q, half)
    lam = np.vstack([np.maximum(direction, 0.0), np.maximum(-direction, 0.0)])
    return _shaped(Certificates(lam, value), single)


def box_normals(q: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The unit normals n (..., d, K) of :func:`box_certificates` (lambda = [max(n, 0); max(-n, 0)])
    and their values (..., K), without its checks: offsets ``q`` (..., d, K) (the point's axes
    second to last), half-sizes ``half`` of the same shape or with a 1 on any axis to
    broadcast. The local step takes its certificates this way on every round, all copies at
    once ((n, d, K) offsets against one box each, (n, d, 1)), and lays lambda out itself."""
    excess = np.abs(q) - half
    outside = np.maximum(excess, 0.0)
    gap = np.sqrt((outside * outside).sum(-2))  # the d terms in order, as einsum adds them
    is_out = gap > 0
    every = bool(is_out.all())  # all outside: the common case, dividing by gap as it stands
    divisor = gap if every else np.where(is_out, gap, 1.0)
    direction = np.copysign(outside, q) / divisor[..., None, :]  # |q| > half > 0 where it counts
    value = gap
    if not every:  # offsets inside (or on) the box: the shallowest exit axis
        *lead, inner = np.nonzero(~is_out)
        axis = np.argmax(np.moveaxis(excess, -2, -1)[(*lead, inner)], axis=1)
        direction[(*lead, slice(None), inner)] = 0.0
        exit_axis = (*lead, axis, inner)
        direction[exit_axis] = np.where(q[exit_axis] >= 0, 1.0, -1.0)
        value = gap.copy()
        value[(*lead, inner)] = excess[exit_axis]
    return direction, value


def certificate_values(points: np.ndarray, G: np.ndarray, g: np.ndarray, lam: np.ndarray) -> np.ndarray:
    """(G q - g)^T lambda per column: the distance bound of given certificates (m, K) at points (d, K)."""
    q, _ = _columns(points)
    lam2 = np.asarray(lam, float).reshape(len(g), -1)
    return np.einsum("mk,mk->k", np.asarray(G, float) @ q - np.asarray(g, float)[:, None], lam2)


def pair_rows(lam: np.ndarray, half_size: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The linear form of a pair constraint with fixed box certificates (2d, K).

    (G (p_i - p_j) - g)^T lambda = n^T (p_i - p_j) - delta^T (lambda_+ + lambda_-) with
    n = lambda_+ - lambda_-; returns n (d, K) and the constant delta^T (lambda_+ + lambda_-) (K,),
    so the constraint reads n^T (p_i - p_j) >= d_min + constant.
    """
    lam = np.asarray(lam, float)
    d = lam.shape[0] // 2
    half = np.broadcast_to(np.asarray(half_size, float).reshape(-1), (d,))
    return lam[:d] - lam[d:], half @ (lam[:d] + lam[d:])


class PolytopeCertifier:
    """Best certificates against one polytope {x : G x <= g}: candidate supports built once,
    then any number of points evaluated at once (see the module docstring for the derivation).

    Parameters
    ----------
    G : (m, d) array
        Facet normals (any positive scaling per row).
    g : (m,) array
        Offsets.
    """

    def __init__(self, G: np.ndarray, g: np.ndarray) -> None:
        self.G = np.atleast_2d(np.asarray(G, float))
        self.g = np.asarray(g, float).reshape(-1)
        self.norms = np.linalg.norm(self.G, axis=1)
        self.supports = self._groups(_candidate_supports(self.G / self.norms[:, None], self.g / self.norms))

    def _groups(self, supports: list[tuple[int, ...]]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """Per support size s: (rows (n_s, s), M (n_s, s, d), b (n_s, s)) with mu_S = M q - b."""
        groups = []
        for size in sorted({len(s) for s in supports}):
            rows = np.array([s for s in supports if len(s) == size], dtype=int)
            Gs = self.G[rows]  # (n, s, d)
            inverse = np.linalg.inv(Gs @ np.swapaxes(Gs, 1, 2))
            groups.append((rows, inverse @ Gs, np.einsum("nij,nj->ni", inverse, self.g[rows])))
        return groups

    def __call__(self, points: np.ndarray) -> Certificates:
        """Certificates ``lam`` (m, K) and their values (K,) for points (d, K) or (d,)."""
        q, single = _columns(points)
        m, K = self.g.size, q.shape[1]
        residual = self.G @ q - self.g[:, None]  # (m, K)
        best_value = np.max(residual / self.norms[:, None], axis=0)  # single facets, inside too
        best_face = np.argmax(residual / self.norms[:, None], axis=0)
        lam = np.zeros((m, K))
        lam[best_face, np.arange(K)] = 1.0 / self.norms[best_face]
        for rows, M, b in self.supports:
            if rows.shape[1] == 1:
                continue
            mu = np.maximum(np.einsum("nsd,dk->nsk", M, q) - b[:, :, None], 0.0)  # (n, s, K)
            normal = np.einsum("nsd,nsk->ndk", self.G[rows], mu)
            length = np.linalg.norm(normal, axis=1)  # (n, K)
            value = np.einsum("nsk,nsk->nk", mu, residual[rows]) / np.where(length > 0, length, 1.0)
            value = np.where(length > 0, value, -np.inf)
            pick = np.argmax(value, axis=0)
            better = value[pick, np.arange(K)] > best_value
            if not np.any(better):
                continue
            cols = np.nonzero(better)[0]
            lam[:, cols] = 0.0
            for slot in range(rows.shape[1]):
                lam[rows[pick[cols], slot], cols] = mu[pick[cols], slot, cols] / length[pick[cols], cols]
            best_value = np.where(better, value[pick, np.arange(K)], best_value)
        return _shaped(Certificates(lam, best_value), single)


def polytope_certificates(points: np.ndarray, G: np.ndarray, g: np.ndarray) -> Certificates:
    """Best certificates of points (d, K) or (d,) against {x : G x <= g} (one-off convenience;
    build a :class:`PolytopeCertifier` once to evaluate the same polytope many times)."""
    return PolytopeCertifier(G, g)(points)


def _candidate_supports(G: np.ndarray, g: np.ndarray) -> list[tuple[int, ...]]:
    """Facet subsets that may carry the optimal certificate, for unit-row G.

    Every single facet; then the linearly independent subsets of size 2..d of each vertex's
    active set when G has full column rank (every face of a pointed polyhedron holds a vertex,
    so the projection's active set lies in some vertex's); otherwise every independent subset
    of size up to rank(G).
    """
    m, d = G.shape
    rank = int(np.linalg.matrix_rank(G))
    if rank == d:
        pools = _vertex_active_sets(G, g)
    else:
        pools = [tuple(range(m))]
    supports: set[tuple[int, ...]] = {(i,) for i in range(m)}
    for pool in pools:
        for size in range(2, min(rank, len(pool)) + 1):
            for subset in itertools.combinations(pool, size):
                rows = G[list(subset)]
                if abs(np.linalg.det(rows @ rows.T)) > _SINGULAR:
                    supports.add(subset)
    return sorted(supports, key=lambda s: (len(s), s))


def _vertex_active_sets(G: np.ndarray, g: np.ndarray, tol: float = 1e-9) -> list[tuple[int, ...]]:
    """Active facet sets of the polytope's vertices (unit-row G), found among all d-subsets."""
    m, d = G.shape
    subsets = np.array(list(itertools.combinations(range(m), d)), dtype=int)
    if subsets.size == 0:
        return [tuple(range(m))]
    rows = G[subsets]
    regular = np.abs(np.linalg.det(rows)) > _SINGULAR
    subsets, rows = subsets[regular], rows[regular]
    if not len(subsets):
        return [tuple(range(m))]
    vertices = np.linalg.solve(rows, g[subsets][..., None])[..., 0]  # (n, d)
    slack = vertices @ G.T - g  # (n, m)
    scale = tol * max(1.0, float(np.max(np.abs(g))))
    feasible = np.all(slack <= scale, axis=1)
    active = {tuple(np.nonzero(np.abs(row) <= scale)[0].tolist()) for row in slack[feasible]}
    return sorted(active) if active else [tuple(range(m))]
