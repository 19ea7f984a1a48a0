"""Which ADMM design choices pay off: each variant changes one setting of the default.

Closed loop on paper-2d and paper-3d (hard, delta 0.3); writes a markdown table to
``benchmarks/out/admm_ablation.md``.

    python benchmarks/admm_ablation.py
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from swarmpc.formulation.ocp import OCPSettings
from swarmpc.scenarios import builtin_scenario
from swarmpc.simulation.loop import simulate
from swarmpc.solvers.admm import ADMMConfig, ADMMSolver

OUT = Path(__file__).parent / "out"
VARIANTS: dict[str, dict[str, Any]] = {
    "default (free copies, rho 1, owner weight 5, on-demand coupling)": {},
    "copies obey the dynamics": {"dynamic_copies": True},
    "residual balancing (adaptive rho)": {"adaptive_rho": True},
    "owner weight 1 (plain consensus)": {"owner_weight": 1.0},
    "owner weight 20": {"owner_weight": 20.0},
    "rho 10": {"rho": 10.0},
    "all-to-all copies (the paper)": {"coupling_margin": None},
}


def main() -> None:
    rows = []
    for name in ("paper-2d", "paper-3d"):
        scn = builtin_scenario(name)
        central = simulate(scn.with_updates(**{"solver.method": "centralized"})).summary
        for label, change in VARIANTS.items():
            config = dataclasses.replace(ADMMConfig(), **change)
            settings = OCPSettings.from_scenario(scn)
            solver = ADMMSolver(settings, scn.num_agents, scn.delta_vector, config)
            try:
                result = simulate(scn, solver=solver)
            finally:
                solver.close()  # ours: simulate closes only what it built
            s = result.summary
            iterations = np.array([r.admm_iterations for r in result.records])
            rows.append({
                "scenario": name, "variant": label, "all_reached": s["all_reached"], "steps": s["steps"],
                "collisions": s["collisions"], "cost": s["cost"],
                "cost_vs_central_pct": 100 * (s["cost"] - central["cost"]) / central["cost"],
                "step_ms_median": s["step_time_ms"]["median"], "step_ms_p95": s["step_time_ms"]["p95"],
                "iter_median": float(np.median(iterations)), "iter_mean": float(np.mean(iterations)),
                "repairs": s["admm_repairs"], "deadlocks": s["deadlocks"],
            })
            print(rows[-1], flush=True)
    OUT.mkdir(exist_ok=True)
    (OUT / "admm_ablation.json").write_text(json.dumps(rows, indent=2))
    lines = ["| scenario | variant | all reached | steps | collisions | cost | vs central | step ms median | p95 | "
             "ADMM it. median | mean | repairs | deadlocks |", "|" + "---|" * 13]
    for r in rows:
        lines.append(
            f"| {r['scenario']} | {r['variant']} | {'yes' if r['all_reached'] else 'no'} | {r['steps']} | "
            f"{r['collisions']} | {r['cost']:.1f} | {r['cost_vs_central_pct']:+.1f}% | {r['step_ms_median']:.1f} | "
            f"{r['step_ms_p95']:.1f} | {r['iter_median']:.0f} | {r['iter_mean']:.1f} | {r['repairs']} | "
            f"{r['deadlocks']} |"
        )
    (OUT / "admm_ablation.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
