"""The coordinator's consensus arithmetic against its definitions, agent by agent and copy by copy."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from swarmpc.solvers.admm.consensus import average, dual_residual, held_copies, primal_residual


@st.composite
def swarms(draw: st.DrawFn) -> tuple[list[SimpleNamespace], list[tuple[int, ...]], np.ndarray]:
    """Answers of M agents (own positions and copies of their neighbours) and a consensus z."""
    M, d, K = draw(st.integers(1, 9)), draw(st.integers(2, 3)), draw(st.integers(1, 6))
    neighbours = [tuple(sorted(draw(st.sets(st.sampled_from([j for j in range(M) if j != i] or [0]), max_size=4))
                               - {i})) for i in range(M)]
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    scale = draw(st.sampled_from([1e-9, 1.0, 1e3]))
    results = [SimpleNamespace(agent=i, own=scale * rng.normal(size=(d, K)),
                               copies=scale * rng.normal(size=(len(neighbours[i]), d, K))) for i in range(M)]
    return results, neighbours, scale * rng.normal(size=(M, d, K))


@given(swarms(), st.sampled_from([1.0, 5.0]), st.sampled_from([1.0, 1.6]))
@settings(max_examples=150, deadline=None)
def test_z_is_the_weighted_mean_of_every_copy_of_each_agent(swarm, owner_weight, relaxation) -> None:
    """z_j = (w_j * own_j + sum of the copies others hold of j) / (w_j + their number), each
    relaxed towards z_prev_j; the loop over copies in the answers' order gives the same bits."""
    results, neighbours, previous = swarm
    z, weights = average(results, neighbours, owner_weight, relaxation, previous)
    for j, r in enumerate(results):
        w = owner_weight if neighbours[j] else 1.0
        own = relaxation * r.own + (1 - relaxation) * previous[j] if neighbours[j] and relaxation != 1.0 else r.own
        total, count = w * own, w
        for holder in results:
            for slot, k in enumerate(neighbours[holder.agent]):
                if k == j:
                    copy = holder.copies[slot]
                    total = total + (copy if relaxation == 1.0 else relaxation * copy + (1 - relaxation) * previous[j])
                    count += 1
        assert weights[j] == w
        np.testing.assert_array_equal(z[j], total / count)


@given(swarms())
@settings(max_examples=150, deadline=None)
def test_the_primal_residual_is_the_rms_over_own_blocks_and_copies(swarm) -> None:
    results, neighbours, z = swarm
    squared, entries = 0.0, 0
    for r in results:
        squared += float(np.sum((r.own - z[r.agent]) ** 2))
        entries += r.own.size
        for slot, j in enumerate(neighbours[r.agent]):
            squared += float(np.sum((r.copies[slot] - z[j]) ** 2))
            entries += r.copies[slot].size
    assert primal_residual(results, neighbours, z) == np.sqrt(squared / entries)


@given(swarms())
@settings(max_examples=100, deadline=None)
def test_the_dual_residual_weighs_each_block_by_its_holders(swarm) -> None:
    """rho_b-weighted RMS of z - z_prev: an own block (coupled agents only) at rho * w, one
    block per copy at rho."""
    results, neighbours, change = swarm
    weights = np.array([5.0 if n else 1.0 for n in neighbours])
    squared, blocks = 0.0, 0
    for j in range(len(results)):
        held = sum(j in n for n in neighbours)
        own = 1 if neighbours[j] else 0
        squared += (own * weights[j] ** 2 + held) * float(np.sum(change[j] ** 2))
        blocks += own + held
    expected = 2.0 * np.sqrt(squared / max(blocks * change[0].size, 1))
    np.testing.assert_allclose(dual_residual(change, weights, neighbours, 2.0), expected, rtol=1e-12)


def test_held_copies_lists_each_copy_with_the_agent_it_copies() -> None:
    own = np.zeros((2, 3))
    results = [SimpleNamespace(agent=0, own=own, copies=np.full((2, 2, 3), [[[1.0]], [[2.0]]])),
               SimpleNamespace(agent=1, own=own, copies=np.zeros((0, 2, 3))),
               SimpleNamespace(agent=2, own=own, copies=np.full((1, 2, 3), 3.0))]
    copies, holders = held_copies(results, [(1, 2), (), (0,)])
    assert holders.tolist() == [1, 2, 0]
    assert copies[:, 0, 0].tolist() == [1.0, 2.0, 3.0]
    none, nobody = held_copies(results, [(), (), ()])
    assert none.shape == (0, 2, 3) and nobody.size == 0
