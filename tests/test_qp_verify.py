"""The QP path's check of a repair's kept plan (SequentialLocalQP.verified) against independent
answers: a plan is kept exactly when it flies the dynamics from the measured state within the
input box and every constrained position keeps d_min from the pinned neighbour's box (exact
distances recomputed here), and the verdict matches IPOPT's reference check
(LocalSolverLadder.verified) on the same plans."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from test_qp_accel import clearance, repair_problem, rollout

from swarmpc.solvers.admm.ladders import LocalSolverLadder, QPLocalSolverLadder
from swarmpc.solvers.admm.messages import KEPT_PLAN
from swarmpc.solvers.guesses import agent_guess_blocks, pair_guess_blocks
from swarmpc.solvers.qp_local import QPLocalLadder


def candidate(dim: int, standing_at: float, scale: float, seed: int) -> tuple:
    """A repair problem (the neighbour standing at x = ``standing_at``) and a plan driven by
    random inputs of up to ``scale`` times the acceleration limit."""
    s, params, _, pinned = repair_problem(dim, standing_at)
    inputs = np.random.default_rng(seed).uniform(-scale, scale, (dim, s.horizon))
    return s, params, pinned, rollout(s, params["x0"], inputs), inputs


@settings(max_examples=60, deadline=None)
@given(dim=st.sampled_from([2, 3]), standing_at=st.floats(0.3, 3.0), scale=st.sampled_from([0.5, 1.0, 1.2]),
       seed=st.integers(0, 2**31 - 1))
def test_a_plan_is_kept_exactly_when_it_flies_and_keeps_clear(dim, standing_at, scale, seed):
    s, params, pinned, states, inputs = candidate(dim, standing_at, scale, seed)
    kept = QPLocalLadder(s).verified(params, {"X": states, "U": inputs}, pinned, copies=1)
    expected = bool(np.all(np.abs(inputs) <= 1.0)) and clearance(s, states, pinned["C0"]) >= s.d_min - 1e-9
    assert (kept is not None) == expected
    if kept is not None:
        blocks, _ = kept
        assert np.array_equal(blocks["X"], states) and np.array_equal(blocks["C0"], pinned["C0"])


def test_a_plan_off_its_dynamics_is_not_kept():
    s, params, pinned, states, inputs = candidate(2, 3.0, 0.5, 0)
    assert QPLocalLadder(s).verified(params, {"X": states, "U": inputs}, pinned, copies=1) is not None
    states = states.copy()
    states[0, 4] += 1e-4
    assert QPLocalLadder(s).verified(params, {"X": states, "U": inputs}, pinned, copies=1) is None


def test_the_verdict_matches_the_ipopt_reference():
    """Plans kept and refused alike, by the QP path's check and by the reference NLP's."""
    verdicts = []
    for seed, (standing_at, scale) in enumerate([(3.0, 0.5), (0.4, 0.5), (1.0, 1.0), (2.0, 1.2), (0.8, 0.3)]):
        s, params, pinned, states, inputs = candidate(2, standing_at, scale, seed)
        point = agent_guess_blocks("", states.T, s)
        own = s.model.position(states.T[s.first_constrained_step:])
        point.update(pair_guess_blocks("0", own - pinned["C0"].T, params["delta"], s))
        point["U"] = inputs
        ipopt = LocalSolverLadder(s, 1, False)
        reference = ipopt.verified(params, point, pinned, copies=1)
        ladder = QPLocalSolverLadder(QPLocalLadder(s), ipopt)
        answer = ladder.verified(params, point, pinned, copies=1)
        assert (answer is None) == (reference is None)
        if answer is not None:
            assert answer.status == KEPT_PLAN and answer.success
        verdicts.append(answer is not None)
    assert any(verdicts) and not all(verdicts)
