"""The paper's experiment set as data: which runs, with what settings, and what a run gave.

Kept apart from running it (:mod:`swarmpc.experiments.reproduce`) and from what is made of the
results (:mod:`~swarmpc.experiments.figures`, :mod:`~swarmpc.experiments.report`), which all
read these types.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from swarmpc.config import Scenario

SCENARIOS = ("paper-2d", "paper-3d")
PAPER_DELTAS = (0.1, 0.3, 0.5)
FORMS = ("hard", "soft")
GUESSES = ("straight", "shifted", "rrt", "auto")
GUESS_DELTA = 0.3
PAPER_LOCAL = "ipopt"
"""The agents' local step of every run: the paper solves each local problem as an NLP by IPOPT."""
SEED = 0
RUNS_DIR = "runs"
MANIFEST = "reproduce.json"
REPORT = "report.md"

Log = Callable[[str], None]


@dataclass(frozen=True)
class RunSpec:
    """One closed-loop run of the set: a built-in scenario and the settings varied around it."""

    scenario: str
    delta: float
    collision: str = "hard"
    method: str = "admm"
    guess: str = "auto"
    max_steps: int | None = None
    seed: int = SEED

    @property
    def name(self) -> str:
        """Run folder name, unique within a set (e.g. ``paper-2d_d0.3_hard_admm_auto``)."""
        return f"{self.scenario}_d{self.delta:g}_{self.collision}_{self.method}_{self.guess}"

    @property
    def dim(self) -> int:
        """Spatial dimension, from the scenario name."""
        return 3 if self.scenario.endswith("3d") else 2

    def build(self) -> Scenario:
        """The fully resolved scenario of this run."""
        from swarmpc.scenarios import builtin_scenario

        return builtin_scenario(self.scenario, delta=self.delta).with_updates(
            **{
                "collision": self.collision,
                "seed": self.seed,
                "solver.method": self.method,
                "solver.local": PAPER_LOCAL,
                "solver.admm.independent_first": False,  # the paper's iterations at every step
                "solver.initial_guess": self.guess,
                "stop.max_steps": self.max_steps,
            }
        )

    def expected_cost(self) -> float:
        """Rough relative run time, to start the longest runs first (better packing)."""
        cost = 1.0 if self.method == "centralized" else 10.0
        cost *= 1.4 if self.collision == "soft" else 1.0
        return cost * (1.2 if self.dim == 3 else 1.0)


@dataclass(frozen=True)
class ReproducePlan:
    """Which runs make up the set; :func:`plan_runs` gives the full and the quick plan."""

    quick: bool
    deltas: tuple[tuple[str, tuple[float, ...]], ...]
    forms: tuple[str, ...]
    centralized: bool
    guess_scenarios: tuple[str, ...]
    guesses: tuple[str, ...]
    guess_delta: float
    max_steps: int | None
    animation_frames: int

    def main_specs(self) -> list[RunSpec]:
        """ADMM runs over scenario x Δ x form (the paper's Figs. 3-5 and the hard/soft table)."""
        return [
            RunSpec(name, delta, form, "admm", "auto", self.max_steps)
            for name, deltas in self.deltas
            for delta in deltas
            for form in self.forms
        ]

    def centralized_specs(self) -> list[RunSpec]:
        """The same cases with the centralised solver (optimality reference)."""
        if not self.centralized:
            return []
        return [RunSpec(s.scenario, s.delta, s.collision, "centralized", "auto", s.max_steps)
                for s in self.main_specs()]

    def guess_specs(self) -> list[RunSpec]:
        """ADMM, hard form, Δ = ``guess_delta``, one run per initial-guess strategy."""
        return [RunSpec(name, self.guess_delta, "hard", "admm", guess, self.max_steps)
                for name in self.guess_scenarios for guess in self.guesses]

    def specs(self) -> list[RunSpec]:
        """Every distinct run, longest expected first."""
        unique = {s.name: s for s in [*self.main_specs(), *self.guess_specs(), *self.centralized_specs()]}
        return sorted(unique.values(), key=lambda s: -s.expected_cost())

    def representative(self, scenario: str) -> RunSpec:
        """The run shown in the trajectory and convergence figures: ADMM, hard, Δ = 0.3 if run."""
        deltas = dict(self.deltas)[scenario]
        delta = self.guess_delta if self.guess_delta in deltas else deltas[len(deltas) // 2]
        return RunSpec(scenario, delta, "hard", "admm", "auto", self.max_steps)


def plan_runs(quick: bool = False) -> ReproducePlan:
    """The paper's set; ``quick``: fewer Δ values, 25 MPC steps, a smaller guess study (a smoke test of
    the whole pipeline, not results)."""
    if quick:
        return ReproducePlan(
            quick=True,
            deltas=(("paper-2d", (0.1, 0.3)), ("paper-3d", (0.3,))),
            forms=FORMS,
            centralized=True,
            guess_scenarios=("paper-2d",),
            guesses=("straight", "rrt", "auto"),
            guess_delta=GUESS_DELTA,
            max_steps=25,
            animation_frames=20,
        )
    return ReproducePlan(
        quick=False,
        deltas=tuple((name, PAPER_DELTAS) for name in SCENARIOS),
        forms=FORMS,
        centralized=True,
        guess_scenarios=SCENARIOS,
        guesses=GUESSES,
        guess_delta=GUESS_DELTA,
        max_steps=None,
        animation_frames=150,
    )


@dataclass(frozen=True)
class RunOutcome:
    """What executing one spec gave: its folder, or the one-line error that stopped it."""

    spec: RunSpec
    folder: str
    error: str | None
    seconds: float
    cpu_seconds: float = 0.0
    reused: bool = False


@dataclass(frozen=True)
class RunRecord:
    """A finished run of the set: its spec, its folder (relative to the output folder) and summary."""

    spec: RunSpec
    folder: str
    summary: dict[str, Any]
