"""The coordinator's and the multipliers' whole-array arithmetic against loops over agents and
copies: the same bits, on random inputs."""

from __future__ import annotations

import functools
import operator
from dataclasses import fields, replace
from types import MappingProxyType, SimpleNamespace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from swarmpc.formulation.ocp import OCPSettings
from swarmpc.scenarios import builtin_scenario
from swarmpc.solvers.admm import ADMMConfig
from swarmpc.solvers.admm.agent import ConsensusMultipliers, matching_slots
from swarmpc.solvers.admm.consensus import (
    BlockLayout,
    Blocks,
    add_in_order,
    held_copies,
    occurrences,
    sequential_sum,
)
from swarmpc.solvers.admm.graph import CouplingGraph
from swarmpc.solvers.admm.messages import LocalRequest, StepRequests

SIGNED = st.sampled_from([-0.0, 0.0, 1e-300, -1.5, 2.0, 1e16, -1e16, 3.25e-7])
"""Values whose sums round, cancel and keep or lose the sign of zero."""


@st.composite
def scattered(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A total (M, 2), targets (C,) with repeats and values (C, 2)."""
    M = draw(st.integers(1, 6))
    C = draw(st.integers(0, 25))
    targets = np.array(draw(st.lists(st.integers(0, M - 1), min_size=C, max_size=C)), int)
    total = np.array(draw(st.lists(SIGNED, min_size=2 * M, max_size=2 * M))).reshape(M, 2)
    values = np.array(draw(st.lists(SIGNED, min_size=2 * C, max_size=2 * C))).reshape(C, 2)
    return total, targets, values


@given(scattered())
@settings(max_examples=300, deadline=None)
def test_add_in_order_adds_value_by_value_as_a_loop_does(case) -> None:
    total, targets, values = case
    expected = total.copy()
    for j, value in zip(targets, values, strict=True):
        expected[j] = expected[j] + value
    summed = add_in_order(total, targets, values, occurrences(targets))
    assert summed.tobytes() == expected.tobytes()  # the sign of a zero too
    at = total.copy()
    np.add.at(at, targets, values)
    assert summed.tobytes() == at.tobytes()


@given(st.lists(st.integers(0, 5), max_size=30))
def test_occurrences_count_the_earlier_entries_with_the_same_target(targets) -> None:
    expected = [targets[:k].count(j) for k, j in enumerate(targets)]
    assert occurrences(np.array(targets, int)).tolist() == expected


@given(st.lists(st.one_of(SIGNED, st.floats(0.0, 1e6)), min_size=1, max_size=60))
def test_sequential_sum_adds_left_to_right(values) -> None:
    expected = functools.reduce(operator.add, values)
    assert np.float64(sequential_sum(np.array(values))).tobytes() == np.float64(expected).tobytes()
    assert sequential_sum(np.zeros(0)) == 0.0


@st.composite
def answers(draw: st.DrawFn) -> tuple[list[SimpleNamespace], list[tuple[int, ...]]]:
    """Answers of M agents in a random order, with copies of their neighbours."""
    M, d, K = draw(st.integers(1, 7)), 2, draw(st.integers(1, 4))
    neighbours = [tuple(sorted(draw(st.sets(st.integers(0, M - 1), max_size=4)) - {i})) for i in range(M)]
    order = draw(st.permutations(range(M)))
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    results = [SimpleNamespace(agent=i, own=rng.normal(size=(d, K)), copies=rng.normal(size=(len(neighbours[i]), d, K)))
               for i in order]
    return results, neighbours


@given(answers())
@settings(max_examples=150, deadline=None)
def test_blocks_on_a_reused_layout_are_the_blocks_laid_out_afresh(case) -> None:
    results, neighbours = case
    copies, targets = held_copies(results, neighbours)
    layout = BlockLayout.of([r.agent for r in results], neighbours)
    blocks = Blocks.of(results, neighbours, layout)
    assert blocks.layout is layout and layout.fits(results, neighbours)
    assert blocks.copies.tobytes() == copies.tobytes() and blocks.targets.tolist() == targets.tolist()
    assert blocks.agents.tolist() == [r.agent for r in results]
    assert layout.held.tolist() == [sum(j in n for n in neighbours) for j in range(len(neighbours))]
    assert layout.coupled.tolist() == [bool(n) for n in neighbours]
    own, held = np.arange(len(results), dtype=float), -1.0 - np.arange(len(targets), dtype=float)
    expected = []
    for k in range(len(results)):  # each answer's own block, then its copies
        expected.append(own[k])
        expected += held[int(blocks.counts[:k].sum()):int(blocks.counts[: k + 1].sum())].tolist()
    assert blocks.in_order(own, held).tolist() == expected
    if len(results) > 1:
        assert not layout.fits(results[::-1], neighbours)


@given(st.lists(st.integers(0, 9), unique=True, max_size=8), st.lists(st.integers(0, 9), max_size=8))
def test_matching_slots_pair_each_wanted_agent_with_its_first_offer(wanted, offered) -> None:
    slots, sent = matching_slots(wanted, offered)
    expected = [(s, offered.index(j)) for s, j in enumerate(wanted) if j in offered]
    assert list(zip(slots, sent, strict=True)) == expected


def reference_update(multipliers: dict, previous: dict | None, request: SimpleNamespace, last: SimpleNamespace,
                     last_neighbours: tuple[int, ...]) -> dict:
    """The copies' multiplier step, neighbour by neighbour."""
    sent: dict[int, int] = {}
    for slot, j in enumerate(last_neighbours):
        sent.setdefault(j, slot)
    updated = dict(multipliers)
    for slot, j in enumerate(request.neighbours):
        if j in sent:
            answer, before = last.copies[sent[j]], (previous or {}).get(j)
            if request.relaxation != 1.0 and before is not None:
                answer = request.relaxation * answer + (1.0 - request.relaxation) * before
            updated[j] = updated.get(j, 0.0) + request.rho_previous * (answer - request.z_neighbours[slot])
    return updated


@st.composite
def multiplier_steps(draw: st.DrawFn):
    """Two requests of one step in a row, the answer to the first, and multipliers held before."""
    d, K = 2, draw(st.integers(1, 4))
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    pick = st.lists(st.integers(1, 8), unique=True, max_size=6).map(lambda n: tuple(sorted(n)))
    first, second = draw(pick), draw(st.one_of(pick, st.just(None)))
    second = first if second is None else second
    relaxation = draw(st.sampled_from([1.0, 1.6]))

    def request(neighbours: tuple[int, ...], new_step: bool) -> SimpleNamespace:
        return SimpleNamespace(z_own=rng.normal(size=(d, K)), neighbours=neighbours, new_step=new_step,
                               z_neighbours=rng.normal(size=(len(neighbours), d, K)), rho_previous=2.5,
                               relaxation=relaxation, owner_weight=5.0, carry=())

    held = {j: rng.normal(size=(d, K)) for j in draw(st.sets(st.integers(1, 8), max_size=5))}
    answer = SimpleNamespace(own=rng.normal(size=(d, K)), copies=rng.normal(size=(len(first), d, K)))
    return request(first, True), request(second, False), answer, held


@given(multiplier_steps())
@settings(max_examples=200, deadline=None)
def test_the_multiplier_step_is_the_step_neighbour_by_neighbour(case) -> None:
    first, second, answer, held = case
    multipliers = ConsensusMultipliers()
    multipliers.update(first, None, ())  # a new step: z remembered, nothing carried
    multipliers.copies = dict(held)
    multipliers.update(second, answer, first.neighbours)
    previous = dict(zip(first.neighbours, first.z_neighbours, strict=True))
    expected = reference_update(held, previous, second, answer, first.neighbours)
    assert sorted(multipliers.copies) == sorted(expected)
    for j, gamma in expected.items():
        assert multipliers.copies[j].tobytes() == np.asarray(gamma).tobytes()


SCN = builtin_scenario("paper-2d")
S = OCPSettings.from_scenario(SCN)


@given(st.integers(0, 2**31), st.booleans())
@settings(max_examples=25, deadline=None)
def test_an_iterations_requests_are_the_agents_requests(seed, planes) -> None:
    """Requests made from the first iteration's on a graph are field by field the requests posed in full."""
    rng = np.random.default_rng(seed)
    M, K = 4, S.num_constrained
    bodies = np.asarray(SCN.bodies, float)[:M]
    states, guess = rng.normal(size=(M, 2 * S.dim)), rng.normal(size=(M, S.horizon + 1, 2 * S.dim))
    requests = StepRequests(S, ADMMConfig(), bodies, states, states, guess)
    plane = (np.ones((S.dim, K)), np.zeros(K))
    mine = [MappingProxyType({3: plane} if planes and i == 2 else {}) for i in range(M)]
    graph = CouplingGraph(~np.eye(M, dtype=bool), ((1, 2), (0,), (0,), ()), tuple(mine))
    carry = [(True, False, True), (False, True), (True, True), (False,)]
    first = requests.iteration(graph, rng.normal(size=(M, S.dim, K)), 10.0, 10.0, True, carry)
    assert [r.carry for r in first] == carry
    z = rng.normal(size=(M, S.dim, K))
    later = requests.iteration(graph, z, 20.0, 10.0, False)
    for i, request in enumerate(later):
        posed = requests.request(i, graph, z, 20.0, 10.0, False)
        for f in fields(LocalRequest):
            a, b = getattr(request, f.name), getattr(posed, f.name)
            assert type(a) is type(b) and (np.array_equal(a, b) if isinstance(a, np.ndarray) else a == b), f.name


def test_with_changes_is_replace() -> None:
    z = np.arange(6.0).reshape(1, 2, 3)
    request = LocalRequest(agent=1, state=np.zeros(4), goal=np.ones(4), delta=np.zeros((1, 2)), rho=1.0,
                           rho_previous=1.0, owner_weight=5.0, new_step=True, z_own=z[0], neighbours=(0,),
                           z_neighbours=z, neighbour_states=np.zeros((1, 4)), guess=np.zeros((3, 4)))
    changed, replaced = request.with_changes(rho=2.0, new_step=False), replace(request, rho=2.0, new_step=False)
    assert changed.__dict__.keys() == replaced.__dict__.keys()
    assert all(getattr(changed, f.name) is getattr(replaced, f.name) for f in fields(LocalRequest))
    assert request.rho == 1.0 and request.new_step
    try:
        request.with_changes(nothing=1)
    except TypeError:
        pass
    else:
        raise AssertionError("an unknown field was accepted")
