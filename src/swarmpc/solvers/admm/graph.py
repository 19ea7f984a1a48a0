"""The coupling graph of one MPC step: which pairs can meet, which hold copies, which keep to planes.

Neighbour sets are recomputed every MPC step from the measured states. A pair that cannot come
within Delta_ij + d_min during the horizon (not a reach candidate, :func:`reach_candidates`) needs
no coupling at all. Among candidates, a pair couples up front when its guessed trajectories come
within the coupling margin (:func:`guess_neighbours`); with ``plane_margin``, a coupled pair whose
guesses stay well apart is kept apart by separating planes instead of copies
(:func:`separating_planes`). Pairs left uncoupled are checked on the agents' plans and coupled
on demand (:meth:`CouplingGraph.coupled`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from functools import cached_property
from types import MappingProxyType

import numpy as np

from swarmpc.formulation.ocp import OCPSettings
from swarmpc.model.geometry import as_bodies, largest_pair_delta
from swarmpc.solvers.admm.config import ADMMConfig

Neighbours = tuple[tuple[int, ...], ...]
"""Per agent, the sorted indices of the agents whose copies it holds."""

Planes = tuple[Mapping[int, tuple[np.ndarray, np.ndarray]], ...]
"""Per agent, partner -> (normals (d, K), offsets (K,)) of the separating planes it keeps to."""

PLANE_EXTRA = 1e-3
"""Separation [m] a plane pair keeps beyond d_min, so that a plan meeting its plane to the solver's
constraint tolerance (1e-4 here) still clears d_min."""

PLANE_GOAL_RADIUS = 0.5
"""[m] An agent this close to its goal gets no separating planes (its near pairs keep copies): a
plane lets a parked agent yield only half the spare room, which held up agents threading between
parked ones (evidence: docs/lab/admm.md#separating-planes)."""


def reach_radius(states: np.ndarray, settings: OCPSettings) -> np.ndarray:
    """Largest inf-norm displacement each agent's plan can make from ``states`` within the horizon.

    Parameters
    ----------
    states : ndarray, shape (M, n)
        Current (measured) states of the settings' agent model, the states the plans start from.
    settings : OCPSettings
        The agent model, the horizon and the limits the plans obey.

    Returns
    -------
    ndarray, shape (M,)
        Per agent, an upper bound on max_k ||p_k - p_0||_inf over the horizon T = horizon * dt
        (``inf`` when the plans are not limited).

    Notes
    -----
    The model's :meth:`~swarmpc.model.agent_model.AgentModel.reach_bound` over the horizon. For
    the double integrator, per axis, with an acceleration limit a: ``|v_axis| T + a T^2 / 2``, the
    continuous-time bound, which both discretisations stay within (Euler moves dt^2 a k(k-1)/2 in
    k steps, the zero-order hold exactly a (k dt)^2 / 2); every plan the solver emits obeys it:
    local solutions, the braking plan and the replayed previous plan of a fallback. With a speed
    limit s (a bound on the norm, so on every axis, for every planned velocity after the measured
    one): ``T max(s, |v_axis|)``, which is ``s T`` whenever the measured velocity is within the
    limit and also covers a measured velocity above it (the first step moves with it) and the
    braking plan (whose speed never grows). With both limits, the smaller bound; with neither,
    ``inf``. Not covered by the speed bound: a fallback that replays the previous plan from a
    state off that plan (its velocities shift by the offset); the conflict check therefore also
    checks every pair of an agent whose plan moved farther than this bound
    (:meth:`~swarmpc.solvers.admm.safety.SafetyChecks.checked_pairs`).
    """
    states = np.asarray(states, float)
    return settings.model.reach_bound(states, settings.horizon, settings.accel, settings.speed)


def reach_candidates(states: np.ndarray, settings: OCPSettings, delta: np.ndarray) -> np.ndarray:
    """Pairs of agents whose plans can come within Delta_ij + d_min of each other during the horizon.

    Parameters
    ----------
    states : ndarray, shape (M, n)
        Current (measured) states of the settings' agent model.
    settings : OCPSettings
        The agent model, the horizon, ``d_min`` and the limits (see :func:`reach_radius`).
    delta : array_like
        One Delta (d,) for every pair, or the agents' body half-sizes (M, d) with
        Delta_ij = b_i + b_j (:func:`swarmpc.model.geometry.as_bodies`).

    Returns
    -------
    ndarray of bool, shape (M, M)
        Symmetric; ``[i, j]`` is True when the current inf-norm gap between agents i and j is
        below ``max(Delta_ij) + d_min + reach_i + reach_j``; the diagonal is False. Without limits
        every pair (i != j) is a candidate.

    Notes
    -----
    Why: by the triangle inequality the gap at any step of the horizon is at least the current gap
    minus both agents' displacements, so a pair that is not a candidate stays at least
    ``max(Delta_ij) + d_min`` apart (inf-norm) in any plans the two can have. On that axis the
    offset is at least Delta_ij,axis + d_min, so the OBCA pair constraint holds without being
    imposed: such a pair needs no copies, no certificate and no conflict check. Recomputed every
    MPC step.
    """
    states = np.asarray(states, float)
    reach = reach_radius(states, settings)
    positions = settings.model.position(states)
    gaps = np.max(np.abs(positions[:, None, :] - positions[None, :, :]), axis=2)
    limit = largest_pair_delta(as_bodies(delta, len(states))) + settings.d_min
    candidates = gaps < limit + reach[:, None] + reach[None, :]
    np.fill_diagonal(candidates, False)
    return candidates


def guess_neighbours(
    guess: np.ndarray, settings: OCPSettings, largest_delta: np.ndarray, config: ADMMConfig,
    candidates: np.ndarray | None = None,
) -> list[tuple[int, ...]]:
    """Agents each agent couples with up front (symmetric), from the guesses (M, N+1, n).

    With ``coupling_margin`` None, every other agent (the paper's all-to-all copies). Otherwise
    only reach ``candidates`` (None: every pair) whose guessed trajectories come within
    max(Delta_ij) + d_min + margin + closing_time * closing speed (inf-norm) of each other at some
    constrained step; ``largest_delta`` (M, M) is the largest axis of each pair's Delta_ij.
    """
    M = len(guess)
    if config.coupling_margin is None:
        return [tuple(j for j in range(M) if j != i) for i in range(M)]
    model, first = settings.model, settings.first_constrained_step
    reach = largest_delta + settings.d_min + config.coupling_margin
    positions = model.position(guess[:, first:])
    gaps = np.max(np.abs(positions[:, None] - positions[None, :]), axis=3).min(axis=2)
    velocities = model.velocity(guess)
    closing = np.max(np.abs(velocities[:, None] - velocities[None, :]), axis=(2, 3))
    coupled = gaps < reach + config.closing_time * closing
    if candidates is not None:
        coupled &= candidates
    np.fill_diagonal(coupled, False)
    return [tuple(np.flatnonzero(row).tolist()) for row in coupled]


def reachable_guesses(states: np.ndarray, guess: np.ndarray, settings: OCPSettings) -> tuple[np.ndarray, np.ndarray]:
    """Which guesses a plan can follow, and their positions at the constrained steps (M, K, d).

    A guess is followable when it starts at the measured state and obeys the dynamics and the
    input box (for the double integrator, the acceleration limit) up to its second-to-last state
    (a shifted previous plan does; a straight line from rest does not): the model's
    :meth:`~swarmpc.model.agent_model.AgentModel.guess_inputs` between those states must step
    each to the next. Its last state repeats the one before; the positions returned coast there
    instead (zero input), so that a plan can be at every one of them. Planes are placed only
    between followable guesses: a plane drawn from a guess the agent cannot follow can cut its
    reachable positions off altogether."""
    s, model = settings, settings.model
    first = s.first_constrained_step
    head = guess[:, :-1]
    inputs = np.array([model.guess_inputs(states_i) for states_i in head])
    inputs = inputs.reshape(len(head), head.shape[1] - 1, model.input_dim)  # (M, N-1, m)
    predicted = model.step(head[:, :-1], inputs)
    scale = 1.0 + np.abs(guess).max(axis=(1, 2))
    ok = np.abs(predicted - head[:, 1:]).max(axis=(1, 2)) <= 1e-6 * scale
    ok &= np.abs(guess[:, 0] - states).max(axis=1) <= 1e-6 * scale
    lower, upper = model.input_bounds(s.accel, s.speed)
    within = (inputs <= _outwards(upper) + 1e-9) & (inputs >= -_outwards(-lower) - 1e-9)
    ok &= within.all(axis=(1, 2))
    coasting = guess.copy()
    coasting[:, -1] = model.step(guess[:, -2], np.zeros((len(guess), model.input_dim)))
    return ok, model.position(coasting[:, first:])


def _outwards(upper: np.ndarray) -> np.ndarray:
    """An upper bound loosened by a millionth of its size (the tolerance of a guess's inputs)."""
    upper = np.asarray(upper, float)
    return np.where(upper >= 0.0, upper * (1 + 1e-6), upper * (1 - 1e-6))


def plane_pairs(
    states: np.ndarray, guess: np.ndarray, goals: np.ndarray | None, neighbours: Iterable[tuple[int, ...]],
    settings: OCPSettings, bodies: np.ndarray, margin: float | None,
) -> tuple[list[tuple[int, int]], np.ndarray]:
    """Coupled pairs (i < j) that a separating plane keeps apart instead of copies, and the
    positions (M, K, d) the planes are drawn from. A pair qualifies when both guesses can be
    followed (:func:`reachable_guesses`) and clear the pair's Delta_ij box (``bodies`` (M, d):
    b_i + b_j) by d_min + ``margin`` on some axis at every constrained step (see
    ``ADMMConfig.plane_margin``; None: no pair), and, with ``goals``, neither agent is within
    :data:`PLANE_GOAL_RADIUS` of its goal: an agent parked at its goal keeps copies of those near
    it, so that it can move aside for them."""
    neighbours = list(neighbours)
    if margin is None or not any(neighbours):
        return [], np.empty((0,))
    followable, positions = reachable_guesses(states, guess, settings)
    if goals is not None:
        model = settings.model
        followable &= np.linalg.norm(model.position(states) - model.position(goals), axis=1) > PLANE_GOAL_RADIUS
    pairs = []
    for i, n in enumerate(neighbours):
        if not followable[i]:
            continue
        for j in n:
            if j > i and followable[j]:
                excess = (np.abs(positions[i] - positions[j]) - (bodies[i] + bodies[j])).max(axis=1).min()
                if excess >= settings.d_min + margin:
                    pairs.append((i, j))
    return pairs, positions


def separating_planes(
    first: np.ndarray, second: np.ndarray, delta: np.ndarray, clearance: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-step separating planes between two agents' guessed positions, split between the two.

    Parameters
    ----------
    first, second : ndarray, shape (d, K)
        The two agents' guessed positions at the constrained steps.
    delta : ndarray, shape (d,)
        The pair's Delta_ij per axis (b_i + b_j): the box the offset of the two keeps out of.
    clearance : float
        Distance to keep beyond the box (d_min, plus :data:`PLANE_EXTRA` in the solver).

    Returns
    -------
    normals : ndarray, shape (d, K)
        Per step, the unit axis vector n_k (pointing from ``second`` to ``first``) of the axis on
        which the guesses clear the box farthest.
    first_offsets, second_offsets : ndarray, shape (K,)
        Per step, ``first`` keeps n_k' p_k >= first_offsets[k] and ``second`` keeps
        -n_k' p_k >= second_offsets[k].

    Notes
    -----
    The guesses leave a spare room s_k = |o_a| - delta_a - clearance on that axis a (o = first -
    second); each agent may move s_k / 2 towards the other. Any two positions that keep to their
    sides then have n_k'(p - q) >= delta_a + clearance: they are at least ``clearance`` apart on
    axis a beyond the box, so the Euclidean distance of the offset to the box is at least
    ``clearance`` (OBCA's condition) whatever either agent does within its side. With s_k < 0
    the guesses themselves are too close and the sides overlap: only pairs with s_k >= 0 at every
    step are given planes.
    """
    offset = np.asarray(first, float) - np.asarray(second, float)
    half = np.asarray(delta, float).reshape(-1)
    steps = np.arange(offset.shape[1])
    axis = np.argmax(np.abs(offset) - half[:, None], axis=0)
    sign = np.where(offset[axis, steps] >= 0.0, 1.0, -1.0)
    normals = np.zeros_like(offset)
    normals[axis, steps] = sign
    spare = np.abs(offset[axis, steps]) - half[axis] - clearance
    first_offsets = sign * np.asarray(first, float)[axis, steps] - 0.5 * spare
    second_offsets = -sign * np.asarray(second, float)[axis, steps] - 0.5 * spare
    return normals, first_offsets, second_offsets


def couple(neighbours: Iterable[tuple[int, ...]], pairs: Iterable[tuple[int, int]]) -> list[tuple[int, ...]]:
    """``neighbours`` with every pair in ``pairs`` coupled (both ways)."""
    coupled = [set(n) for n in neighbours]
    for i, j in pairs:
        coupled[i].add(j)
        coupled[j].add(i)
    return [tuple(sorted(n)) for n in coupled]


def components(neighbours: list[tuple[int, ...]]) -> np.ndarray:
    """Label per agent of its connected component in the coupling graph (labels 0, 1, ...)."""
    labels = np.full(len(neighbours), -1)
    count = 0
    for start in range(len(neighbours)):
        if labels[start] >= 0:
            continue
        stack = [start]
        labels[start] = count
        while stack:
            for j in neighbours[stack.pop()]:
                if labels[j] < 0:
                    labels[j] = count
                    stack.append(j)
        count += 1
    return labels


@dataclass(frozen=True, eq=False)
class CouplingGraph:
    """Who couples with whom in one MPC step; a new graph for every change (:meth:`coupled`).

    ``candidates`` (M, M): the reach candidates of the step (:func:`reach_candidates`), the pairs
    the conflict checks examine. ``neighbours``: per agent, the agents whose copies it holds.
    ``planes``: per agent, the separating planes it keeps to, by partner.
    """

    candidates: np.ndarray
    neighbours: Neighbours
    planes: Planes

    @classmethod
    def build(
        cls, states: np.ndarray, guess: np.ndarray, goals: np.ndarray | None, settings: OCPSettings,
        bodies: np.ndarray, config: ADMMConfig,
    ) -> CouplingGraph:
        """The step's graph: candidates from the measured ``states``, copies between candidates
        whose ``guess`` trajectories come near (:func:`guess_neighbours`), and planes instead of
        copies for the pairs :func:`plane_pairs` picks (``config.plane_margin``)."""
        candidates = reach_candidates(states, settings, bodies)
        neighbours = guess_neighbours(guess, settings, largest_pair_delta(bodies), config, candidates)
        pairs, positions = plane_pairs(states, guess, goals, neighbours, settings, bodies, config.plane_margin)
        planes: list[dict[int, tuple[np.ndarray, np.ndarray]]] = [{} for _ in neighbours]
        clearance = settings.d_min + PLANE_EXTRA
        for i, j in pairs:
            normals, offsets_i, offsets_j = separating_planes(
                positions[i].T, positions[j].T, bodies[i] + bodies[j], clearance)
            planes[i][j] = (normals, offsets_i)
            planes[j][i] = (-normals, offsets_j)
        if pairs:
            dropped = set(pairs)
            neighbours = [tuple(j for j in n if (min(i, j), max(i, j)) not in dropped)
                          for i, n in enumerate(neighbours)]
        return cls(candidates, tuple(neighbours), _frozen(planes))

    def coupled(self, pairs: Iterable[tuple[int, int]]) -> CouplingGraph:
        """This graph with every pair in ``pairs`` coupled with copies; a pair that had a
        separating plane loses it (the copies and OBCA take over)."""
        pairs = list(pairs)
        if not pairs:
            return self
        unplaned = {(i, j) for i, j in pairs} | {(j, i) for i, j in pairs}
        planes = [{j: p for j, p in mine.items() if (i, j) not in unplaned} for i, mine in enumerate(self.planes)]
        return CouplingGraph(self.candidates, tuple(couple(self.neighbours, pairs)), _frozen(planes))

    def with_plane_partners(self) -> list[tuple[int, ...]]:
        """``neighbours`` plus every plane partner (pairs the plain conflict check must skip)."""
        return couple(self.neighbours, [(i, j) for i, planes in enumerate(self.planes) for j in planes])

    def plane_pairs(self) -> np.ndarray:
        """(P, 2) the pairs (i < j) kept apart by separating planes."""
        pairs = [(i, j) for i, planes in enumerate(self.planes) for j in planes if i < j]
        return np.array(pairs, int).reshape(-1, 2)

    def planes_of(self, i: int) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Agent ``i``'s planes as (normals (P, d, K), offsets (P, K)), by partner index; (None,
        None) without planes."""
        return self._stacked_planes[i]

    @cached_property
    def _stacked_planes(self) -> tuple[tuple[np.ndarray | None, np.ndarray | None], ...]:
        """:meth:`planes_of` of every agent, stacked once per graph (read-only: requests share them)."""
        stacked: list[tuple[np.ndarray | None, np.ndarray | None]] = []
        for mine in self.planes:
            partners = sorted(mine)
            if not partners:
                stacked.append((None, None))
                continue
            normals, offsets = np.array([mine[j][0] for j in partners]), np.array([mine[j][1] for j in partners])
            normals.flags.writeable = offsets.flags.writeable = False
            stacked.append((normals, offsets))
        return tuple(stacked)

    @property
    def copies(self) -> np.ndarray:
        """(M,) how many neighbours' copies each agent holds."""
        return np.array([len(n) for n in self.neighbours], int)

    @property
    def plane_counts(self) -> np.ndarray:
        """(M,) how many separating planes each agent keeps to."""
        return np.array([len(p) for p in self.planes], int)


def _frozen(planes: list[dict[int, tuple[np.ndarray, np.ndarray]]]) -> Planes:
    return tuple(MappingProxyType(p) for p in planes)
