"""The QP local step's certificates and objective, taken the fast way, against the plain way.

``Certifier`` writes every copy's box certificates straight into their (n, 2d, K) layout from
:func:`swarmpc.formulation.certificates.box_normals` of all copies' offsets at once, and
``stacked_objective`` takes the copies stacked: both must give exactly (bit for bit) what the
per-copy calls give.
"""

from __future__ import annotations

import numpy as np
import pytest

from swarmpc.formulation.certificates import box_certificates, box_normals
from swarmpc.formulation.ocp import OCPSettings
from swarmpc.solvers.qp_local import Certifier, local_objective, stacked_objective


def settings(dim: int) -> OCPSettings:
    return OCPSettings(dim=dim, horizon=10, dt=0.1, discretization="euler", Q=0.1 * np.eye(2 * dim), R=np.eye(dim),
                       Qf=np.eye(2 * dim), collision="hard", d_min=0.05, kappa=1000.0, lower=None, upper=None,
                       accel=None, speed=None, obstacles=())


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("seed", range(5))
def test_box_normals_are_the_certificates_normals(dim: int, seed: int) -> None:
    """lambda = [max(n, 0); max(-n, 0)] and the values of box_certificates, points inside too."""
    rng = np.random.default_rng(seed)
    offsets, half = rng.uniform(-1.0, 1.0, (dim, 40)), rng.uniform(0.1, 0.6, (dim, 1))
    direction, value = box_normals(offsets, half)
    certs = box_certificates(offsets, half[:, 0])
    assert np.array_equal(np.vstack([np.maximum(direction, 0.0), np.maximum(-direction, 0.0)]), certs.lam)
    assert np.array_equal(value, certs.value)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("seed", range(5))
def test_box_normals_of_stacked_offsets_are_those_of_each_copy(dim: int, seed: int) -> None:
    """Offsets (n, d, K) against one box per copy (n, d, 1) give each copy's normals and values
    of its own (d, K) call, bit for bit, points inside the boxes too."""
    rng = np.random.default_rng(seed)
    offsets, half = rng.uniform(-1.0, 1.0, (4, dim, 30)), rng.uniform(0.1, 0.6, (4, dim, 1))
    direction, value = box_normals(offsets, half)
    assert direction.shape == offsets.shape and value.shape == (4, 30)
    for c in range(4):
        alone = box_normals(offsets[c], half[c])
        assert np.array_equal(direction[c], alone[0]) and np.array_equal(value[c], alone[1])
    assert np.any(value < 0) and np.any(value > 0)  # both cases taken


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("copies", [0, 1, 4])
def test_certifier_layout_equals_each_copy_on_its_own(dim: int, copies: int) -> None:
    """Every copy's certificates are those of its own box (its own Delta) called alone, and the
    rows of given certificates are the rows of the certifier's own answer."""
    s = settings(dim)
    rng = np.random.default_rng(copies)
    K = s.num_constrained
    own, others = rng.uniform(-1.0, 1.0, (dim, K)), rng.uniform(-1.0, 1.0, (copies, dim, K))
    delta = rng.uniform(0.1, 0.5, (dim, copies))
    certify = Certifier(s)
    lin = certify(own, others, delta)
    assert lin.pair_lam.shape == (copies, 2 * dim, K) and lin.pair_lam.flags["C_CONTIGUOUS"]
    for c in range(copies):
        assert np.array_equal(lin.pair_lam[c], box_certificates(own - others[c], delta[:, c]).lam)
    again = certify.rows(own, others, delta, lin.pair_lam, lin.obstacle_lam)
    for name in ("pair_normal", "pair_constant", "pair_value"):
        assert np.array_equal(getattr(again, name), getattr(lin, name))


def test_stacked_objective_equals_the_objective_of_the_blocks() -> None:
    """The objective of stacked copies, multipliers and targets is that of the named blocks."""
    s, copies = settings(3), 3
    rng = np.random.default_rng(7)
    K, N = s.num_constrained, s.horizon
    blocks = {"X": rng.normal(size=(6, N + 1)), "U": rng.normal(size=(3, N))}
    params = {"goal": rng.normal(size=6), "rho": 3.0, "owner_weight": 2.0, "Z": rng.normal(size=(3, K)),
              "Y": rng.normal(size=(3, K))}
    for c in range(copies):
        blocks[f"C{c}"], blocks[f"L{c}"] = rng.normal(size=(3, K)), rng.uniform(size=(6, K))
        params[f"Z{c}"], params[f"Y{c}"] = rng.normal(size=(3, K)), rng.normal(size=(3, K))
    stacked = tuple(np.array([source[f"{name}{c}"] for c in range(copies)])
                    for source, name in ((blocks, "C"), (params, "Y"), (params, "Z")))
    C, Y, Z = stacked
    assert stacked_objective(blocks, params, s, (C, Y, Z)) == local_objective(blocks, params, s, copies)
