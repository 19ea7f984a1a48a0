"""An agent's local problems, one built problem per size: the IPOPT ladder and the QP path on top of it."""

from __future__ import annotations

import threading
from dataclasses import fields, replace
from typing import Any, Protocol

import numpy as np

from swarmpc.formulation.nlp import CompiledNLP, NLPSolution
from swarmpc.formulation.ocp import OCPSettings, build_local
from swarmpc.solvers.admm.messages import KEPT_PLAN, FallbackSolution
from swarmpc.solvers.guesses import agent_guess_blocks, pair_guess_blocks
from swarmpc.solvers.qp_local import PROVEN_INFEASIBLE, QPLocalLadder, copy_deltas


class WarmStartable(Protocol):
    """A built problem that can start from a previous solve's multipliers
    (:meth:`CompiledNLP.solve`)."""

    def solve(
        self, params: dict[str, Any], guess: dict[str, np.ndarray] | np.ndarray, lam_x: np.ndarray | None = None,
        lam_g: np.ndarray | None = None, fixed: dict[str, Any] | None = None,
    ) -> NLPSolution: ...


def solve_warm_or_cold(
    nlp: WarmStartable, params: dict[str, Any], guess: dict[str, np.ndarray] | np.ndarray,
    fixed: dict[str, Any] | None, duals: tuple[np.ndarray, np.ndarray],
) -> NLPSolution:
    """``nlp`` solved from ``guess`` and the multipliers ``duals``; if that fails, solved again
    without them (the multipliers were the bad part), reporting the time of both attempts."""
    warm = nlp.solve(params, guess, *duals, fixed=fixed)
    if warm.success:
        return warm
    cold = nlp.solve(params, guess, fixed=fixed)
    return replace(cold, solve_time=warm.solve_time + cold.solve_time)


class LocalSolverLadder:
    """An agent's local NLPs, one per neighbour count 0, 1, 2, ... up to ``max_slots``.

    An agent with n neighbours solves the problem with exactly n copy slots, so its work follows
    its neighbourhood, not the swarm size, and no solve pays for idle slots (a build grows with the
    slots: evidence in docs/lab/admm.md#exact-local-sizes). Each size is built on first use and
    kept (once per shape, never rebuilt); agents in one process share the built solvers, which are
    stateless between calls (a lock guards the solver statistics under threads). Pickling drops
    the built solvers, so a worker process builds its own.
    """

    def __init__(
        self, settings: OCPSettings, max_slots: int, dynamic_copies: bool,
        plugin: str = "ipopt", options: dict[str, Any] | None = None, warm_start: bool = False,
        pair_collision: str | None = None,
    ) -> None:
        self.settings = settings
        self.max_slots = max_slots
        self.dynamic_copies = dynamic_copies
        self.plugin = plugin
        self.options = options
        self.warm_start = warm_start
        self.pair_collision = pair_collision
        self._built: dict[tuple[int, int], CompiledNLP] = {}
        self._lock = threading.Lock()

    def __getstate__(self) -> dict[str, Any]:
        return {"settings": self.settings, "max_slots": self.max_slots, "dynamic_copies": self.dynamic_copies,
                "plugin": self.plugin, "options": self.options, "warm_start": self.warm_start,
                "pair_collision": self.pair_collision}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(**state)  # type: ignore[misc]

    @property
    def built(self) -> frozenset[tuple[int, int]]:
        """(copy slots, plane slots) of every problem built so far."""
        return frozenset(self._built)

    def slots_for(self, copies: int) -> int:
        """Slot count of the problem that holds ``copies`` neighbours."""
        if copies > self.max_slots:
            raise ValueError(f"{copies} neighbours exceed the {self.max_slots} copy slots")
        return copies

    def solver(self, slots: int, planes: int = 0) -> CompiledNLP:
        """The built problem with ``slots`` copy slots and ``planes`` separating-plane slots (built
        now if this is its first use)."""
        key = (slots, planes)
        if key not in self._built:
            self._built[key] = build_local(self.settings, slots, self.dynamic_copies, self.options, self.plugin,
                                           self.warm_start, self.pair_collision, num_planes=planes)
        return self._built[key]

    def solve(
        self, params: dict[str, Any], guess: dict[str, np.ndarray] | np.ndarray, fixed: dict[str, Any] | None = None,
        *, copies: int, planes: int = 0, duals: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> NLPSolution:
        """Solve the problem sized for ``copies`` neighbours and ``planes`` separating planes (see
        :meth:`CompiledNLP.solve`); ``duals``: multipliers of the bounds and constraints (from a
        previous solve of the same problem) that start this one when the ladder warm-starts
        (:func:`solve_warm_or_cold`)."""
        with self._lock:
            nlp = self.solver(self.slots_for(copies), planes)
            if duals is None or not self.warm_start:
                return nlp.solve(params, guess, fixed=fixed)
            return solve_warm_or_cold(nlp, params, guess, fixed, duals)

    def verified(
        self, params: dict[str, Any], point: dict[str, np.ndarray], fixed: dict[str, Any], *, copies: int,
        planes: int = 0,
    ) -> NLPSolution | None:
        """``point`` with ``fixed`` pinned as a solution (status :data:`KEPT_PLAN`, no cost, no
        time) when it meets every bound and constraint of the problem sized for ``copies`` and
        ``planes`` to 1e-7; None otherwise. A repair keeps a verified current plan this way."""
        nlp = self.solver(self.slots_for(copies), planes)
        x_vec = nlp.x_layout.pack({**point, **fixed})
        if nlp.constraint_violation(x_vec, params) > 1e-7:
            return None
        return NLPSolution(
            x=nlp.x_layout.unpack(x_vec), x_vec=x_vec, lam_x=np.zeros_like(x_vec),
            lam_g=np.zeros_like(nlp.lbg), cost=np.nan, success=True, status=KEPT_PLAN,
            iterations=0, solve_time=0.0,
        )


class QPLocalSolverLadder:
    """An agent's local steps on the QP path, with IPOPT behind every call the QP path fails.

    The interface of :class:`LocalSolverLadder`. Each call goes to ``qp``
    (:class:`swarmpc.solvers.qp_local.QPLocalLadder`), whose answer is safe as it stands: its
    collision rows hold fixed dual-feasible certificates (weak duality), tightened by its margin
    against OSQP's tolerance, and the plan it returns is rebuilt exactly and checked. When it
    fails (the certificates of its start ask for a separation the plan cannot reach, OSQP gives
    up, or the check rejects the plan), the same call is solved by ``ipopt``, the reference, from
    the same start (a solution vector unpacked into named blocks, its certificates included),
    cold: multipliers do not carry across solvers. That answer is returned as
    :class:`FallbackSolution`, its solution vector laid out for the QP path so that the agent's
    next call starts the QP from it. A failed call that the QP path proves to have no feasible
    point (:data:`swarmpc.solvers.qp_local.PROVEN_INFEASIBLE`: a repair pass whose held plans
    leave the agent nowhere to go) is returned as it is: IPOPT could only spend its time on it.
    """

    def __init__(self, qp: QPLocalLadder, ipopt: LocalSolverLadder) -> None:
        self.qp = qp
        self.ipopt = ipopt
        self._soft: QPLocalLadder | None = None
        """The same problems with soft pair rows (:meth:`_elastic`), built on first use."""

    def solve(
        self, params: dict[str, Any], guess: dict[str, np.ndarray] | np.ndarray, fixed: dict[str, Any] | None = None,
        *, copies: int, planes: int = 0, duals: tuple[np.ndarray, np.ndarray] | None = None,
        handover: bool = True, restarts: bool = True,
    ) -> NLPSolution:
        """The QP path's answer if it succeeds or proves the problem infeasible, else IPOPT's
        (:class:`FallbackSolution`); with ``handover`` False the QP path's answer, failed or not.
        With ``elastic`` (a hard repair call that may be handed over), a failed call is first solved
        again with soft pair rows (:meth:`_elastic`), whose answer, when the soft plan needs no
        slack, saves the hand-over. A call that may not be handed over (a step under a deadline)
        goes without the phase, as before it: under a 0.1 s deadline the phase's answers with no
        hand-over behind them left a 64-agent swarm short of its goals in one of two runs.
        With a ``handover_slack``, a call whose soft plan falls short of d_min by more has no
        feasible plan near it and is not handed over either: IPOPT mostly spends 50-400 ms to find
        none, and the few plans it finds are costly detours. Without them a swarm's closed loop
        changed in ways ten runs could not tell from chance but one, so by default (None) every
        call the phase does not answer is handed over (evidence: docs/lab/admm.md#elastic-repair).
        ``restarts``: see :meth:`swarmpc.solvers.qp_local.SequentialLocalQP.solve`. A call of an
        ADMM iteration (copies free) takes ``iteration_rounds`` certificate rounds at most, a
        repair call (copies pinned) ``max_rounds``."""
        pinned = pins_copies(fixed)
        options = self.qp.options
        rounds = None if pinned else options.iteration_rounds
        answer = self.qp.solve(params, guess, fixed, copies=copies, planes=planes, duals=duals, restarts=restarts,
                               rounds=rounds)
        if answer.success or answer.status == PROVEN_INFEASIBLE:
            return answer
        slack = None
        if pinned and handover and options.elastic and self.qp.pair_collision == "hard":
            assert fixed is not None
            found, slack, spent = self._elastic(params, answer, fixed, copies, planes)
            answer = replace(answer, solve_time=answer.solve_time + spent)
            if found is not None:
                return replace(found, solve_time=answer.solve_time)
        far = slack is not None and options.handover_slack is not None and slack > options.handover_slack
        if not handover or far:
            return answer
        return self._handover(params, guess, fixed, answer, copies, planes)

    def _handover(
        self, params: dict[str, Any], guess: dict[str, np.ndarray] | np.ndarray, fixed: dict[str, Any] | None,
        failed: NLPSolution, copies: int, planes: int,
    ) -> FallbackSolution:
        """The call the QP path ``failed`` solved by IPOPT from the same start."""
        pinned = pins_copies(fixed)
        start = self.qp.guess_blocks(params, guess, copies=copies, planes=planes, pinned=pinned)
        reference = self.ipopt.solve(params, start, fixed, copies=copies, planes=planes)
        values = {f.name: getattr(reference, f.name) for f in fields(NLPSolution)}
        values.update(lam_x=np.zeros(0), lam_g=np.zeros(0), solve_time=failed.solve_time + reference.solve_time)
        if reference.success:
            values["x_vec"] = self.qp.solution_vector(reference.x, params, copies=copies, planes=planes, pinned=pinned)
        return FallbackSolution(**values, qp_status=failed.status)

    def _elastic(
        self, params: dict[str, Any], failed: NLPSolution, fixed: dict[str, Any], copies: int, planes: int,
    ) -> tuple[NLPSolution | None, float | None, float]:
        """A failed hard repair call solved again with soft pair rows (an exact L1 penalty, kappa per
        metre) from the failed loop's last plan: its certificate loop moves the plan towards
        feasibility where the hard rows of the failed certificates left no feasible point. A soft
        plan within the rows' margin of d_min starts the hard loop again. Returns (the hard answer
        if it succeeded, the soft plan's largest slack (None when the soft call failed), the time
        spent)."""
        if self._soft is None:
            self._soft = QPLocalLadder(self.qp.settings, "soft", self.qp.options, self.qp.backend)
        pinned = self.qp.pinned_copies(fixed, copies)
        start = self._pair_start(np.asarray(failed.x["X"]).T, pinned, params, soft=True)
        soft = self._soft.solve(params, start, fixed, copies=copies, planes=planes)
        if not soft.success:
            return None, None, soft.solve_time
        slack = max((float(np.max(soft.x[f"A{c}"])) for c in range(copies)), default=0.0)
        if slack > self.qp.options.margin:
            return None, slack, soft.solve_time
        start = self._pair_start(np.asarray(soft.x["X"]).T, pinned, params, soft=False)
        hard = self.qp.solve(params, start, fixed, copies=copies, planes=planes)
        return (hard if hard.success else None), slack, soft.solve_time + hard.solve_time

    def _pair_start(
        self, plan: np.ndarray, pinned: np.ndarray, params: dict[str, Any], soft: bool,
    ) -> dict[str, np.ndarray]:
        """The blocks of a start at state plan ``plan`` (N+1, n): its inputs and the best
        certificates (and soft slacks) of its offsets from the ``pinned`` copies (n, d, K)."""
        s = self.qp.settings
        form = replace(s, collision="soft") if soft else s
        own = s.model.position(plan[s.first_constrained_step:])  # (K, d)
        delta = copy_deltas(params["delta"], len(pinned), s.dim)  # (d, n)
        point = agent_guess_blocks("", plan, s)
        for c, other in enumerate(pinned):
            point.update(pair_guess_blocks(str(c), own - other.T, delta[:, c], form))
        return point

    def verified(
        self, params: dict[str, Any], point: dict[str, np.ndarray], fixed: dict[str, Any], *, copies: int,
        planes: int = 0,
    ) -> NLPSolution | None:
        """:meth:`LocalSolverLadder.verified` by the QP path's own exact check
        (:meth:`swarmpc.solvers.qp_local.SequentialLocalQP.verified`: dynamics, input box, the
        separations by the best certificates, the other hard claims), so that a repair on the
        QP path never builds an IPOPT problem."""
        kept = self.qp.verified(params, point, fixed, copies=copies, planes=planes)
        if kept is None:
            return None
        blocks, vector = kept
        return NLPSolution(x=blocks, x_vec=vector, lam_x=np.zeros(0), lam_g=np.zeros(0), cost=np.nan, success=True,
                           status=KEPT_PLAN, iterations=0, solve_time=0.0)


def pins_copies(fixed: dict[str, Any] | None) -> bool:
    """Whether ``fixed`` pins the copies (``C{c}``: a repair pass)."""
    return any(key.startswith("C") and key[1:].isdigit() for key in fixed or {})


AgentLadder = LocalSolverLadder | QPLocalSolverLadder
"""What an agent solves its local steps with (``ADMMConfig.local``)."""
