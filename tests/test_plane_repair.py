"""The plane pass of a deadline stop (``solver.admm.deadline_repair: planes``) and the batched
re-plans around a failed agent.

(a) :func:`splitting_planes`: any two positions that keep to their sides keep the distance the
    planes promise (recomputed as the exact distance of their offset to the pair's box), the
    plans themselves keep to their sides wherever they keep the floor, and a share of 0 holds
    the first side where it is.
(b) ``Repair._replan_around`` asks uncoupled re-plans in one batch and leaves every answer as the
    one-by-one loop gives it (checked against that loop with a stand-in for the agents).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from swarmpc.model.geometry import box_exterior_distance
from swarmpc.solvers.admm.graph import SPLIT_SPARE, splitting_planes
from swarmpc.solvers.admm.repair import Repair


def keep_to_side(point: np.ndarray, normals: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """``point`` (d, K) moved along each step's normal onto the side n_k' p >= offset_k."""
    short = np.maximum(0.0, offsets - np.einsum("dk,dk->k", normals, point))
    return point + normals * short


@settings(max_examples=200, deadline=None)
@given(seed=st.integers(0, 100_000), dim=st.sampled_from([2, 3]), share=st.sampled_from([0.0, 0.5, 1.0]))
def test_positions_on_their_sides_keep_what_the_planes_promise(seed, dim, share):
    rng = np.random.default_rng(seed)
    K, delta, clearance, floor = 6, rng.uniform(0.05, 0.4, dim), 0.05, 0.025
    first, second = rng.uniform(-0.6, 0.6, (dim, K)), rng.uniform(-0.6, 0.6, (dim, K))
    normals, mine, theirs = splitting_planes(first, second, delta, clearance, floor, share)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=0), 1.0)
    signed = box_exterior_distance(first - second, delta[:, None], axis=0)
    inside = signed <= 0.0
    depth = np.min(delta[:, None] - np.abs(first - second), axis=0)
    signed = np.where(inside, -depth, signed)
    promised = np.maximum(floor, np.minimum(clearance, signed - SPLIT_SPARE))
    for _ in range(20):
        p = keep_to_side(first + rng.normal(0, 0.3, (dim, K)), normals, mine)
        q = keep_to_side(second + rng.normal(0, 0.3, (dim, K)), -normals, theirs)
        assert np.all(box_exterior_distance(p - q, delta[:, None], axis=0) >= promised - 1e-9)
    roomy = signed >= floor + SPLIT_SPARE
    room = (np.einsum("dk,dk->k", normals, first) - mine, -np.einsum("dk,dk->k", normals, second) - theirs)
    assert np.all(room[0][roomy] >= share * SPLIT_SPARE - 1e-12)
    assert np.all(room[1][roomy] >= (1 - share) * SPLIT_SPARE - 1e-12)
    if share == 0.0:
        np.testing.assert_allclose(room[0], 0.0, atol=1e-12)


def test_plans_inside_each_others_box_are_split_along_the_nearest_exit():
    first, second = np.array([[0.1], [0.0]]), np.zeros((2, 1))
    normals, mine, theirs = splitting_planes(first, second, np.array([0.3, 0.3]), 0.05, 0.025)
    np.testing.assert_array_equal(normals[:, 0], [1.0, 0.0])  # leave along x, the shallower axis
    # the two must end at least 0.3 + 0.025 apart along x: each moves half the shortfall
    np.testing.assert_allclose(mine[0] + theirs[0], 0.325)  # p_x - q_x >= 0.325 on their sides
    np.testing.assert_allclose(mine[0] - 0.1, theirs[0] - 0.0)  # the same move for each


class Agents:
    """A stand-in for the agents: a re-plan moves the agent towards its neighbours' plans and
    succeeds unless its neighbours' plans sum to a multiple of three (both deterministic)."""

    def __init__(self, neighbours: list[tuple[int, ...]]) -> None:
        self.neighbours = neighbours
        self.batches: list[list[int]] = []

    def answer(self, i: int, plans: list[SimpleNamespace]) -> SimpleNamespace:
        around = np.mean([plans[j].own for j in self.neighbours[i]], axis=0)
        own = 0.5 * plans[i].own + 0.5 * around + 0.01 * i
        success = int(round(1000 * float(around.sum()))) % 3 != 0
        return SimpleNamespace(own=own, success=success)

    def replan_all(self, agents, graph, z, rho, plans, rescue, quick=False):  # type: ignore[no-untyped-def]
        self.batches.append(list(agents))
        return [self.answer(i, plans) for i in agents]


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 100_000), m=st.integers(2, 9))
def test_re_plans_around_failures_in_batches_give_the_one_by_one_answers(seed, m):
    rng = np.random.default_rng(seed)
    coupled = np.triu(rng.random((m, m)) < 0.5, 1)
    neighbours = [tuple(int(j) for j in np.flatnonzero(coupled[i] | coupled[:, i])) for i in range(m)]
    plans = [SimpleNamespace(own=rng.uniform(0, 1.0, (2, 3)), success=bool(rng.random() < 0.7)) for _ in range(m)]
    failures = [k for k in range(m) if not plans[k].success]
    agents = Agents(neighbours)
    repair = Repair.__new__(Repair)
    repair.safety = SimpleNamespace(settings=SimpleNamespace(d_min=0.05), largest_delta=np.full((m, m), 0.3))
    repair._replan_all = agents.replan_all  # type: ignore[method-assign]
    batched = list(plans)
    repair._replan_around(failures, SimpleNamespace(neighbours=neighbours), None, 0.0, batched)
    one_by_one = list(plans)  # the loop the batches stand in for
    for failed in failures:
        for i in neighbours[failed]:
            gap = np.max(np.abs(one_by_one[i].own - one_by_one[failed].own), axis=0).min()
            if one_by_one[i].success and gap < 0.3 + 0.05:
                one_by_one[i] = agents.answer(i, one_by_one)
    for a, b in zip(batched, one_by_one, strict=True):
        np.testing.assert_array_equal(a.own, b.own)
        assert a.success == b.success
    for batch in agents.batches:
        assert not any(j in neighbours[i] for i in batch for j in batch)
