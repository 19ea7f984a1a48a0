"""Parking probe: consensus ADMM asked at the states of the centralised closed loop, step by step.

The centralised controller flies a car built-in (``parking`` unless ``--case``); at every step the
ADMM controller (``solver.method: admm``, further ``--set KEY=VALUE`` settings) is asked for a plan
from the same measured states, with its own warm starts and multipliers carried from its earlier
answers, as it would be in its own closed loop. Each row compares the two plans: the predicted
costs (the same quadratic cost, summed over the agents), the first inputs of every agent and the
heading each car's plan ends at. Where ADMM's predicted cost is lower than the centralised one, the
two solvers found different local optima of the same problem; where it is higher, ADMM is held
in a worse one by its warm start.

    .venv/bin/python benchmarks/parking_probe.py --steps 13 --out rows.jsonl
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np


def probe(case: str, steps: int, extra: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per step of the centralised closed loop of ``case`` (see the module docstring)."""
    from swarmpc.scenarios import builtin_scenario
    from swarmpc.simulation.controller import Controller
    from swarmpc.simulation.loop import simulate

    scn = builtin_scenario(case)
    flown = simulate(scn.with_updates(**{"stop.max_steps": steps})).states
    central = Controller(scn)
    admm = Controller(scn.with_updates(**{"solver.method": "admm", **extra}))
    rows = []
    for k, x in enumerate(flown[:steps]):
        u_central, u_admm = central.step(x), admm.step(x)
        pc, pa = central.plan, admm.plan
        assert pc is not None and pa is not None
        rows.append({
            "step": k, "central_cost": pc.predicted_cost, "admm_cost": pa.predicted_cost,
            "admm_iterations": pa.admm_iterations, "repaired": bool(pa.repaired),
            "input_change": np.round(u_admm - u_central, 4).tolist(),
            "end_heading_deg": {"central": np.degrees(pc.states[:, -1, 2]).round(1).tolist(),
                                "admm": np.degrees(pa.states[:, -1, 2]).round(1).tolist()},
        })
    central.close()
    admm.close()
    return rows


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", default="parking")
    parser.add_argument("--steps", type=int, default=13)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="a setting of the ADMM arm (dotted scenario key, YAML value)")
    parser.add_argument("--out", type=Path, default=None, help="write the rows to this JSON-lines file")
    args = parser.parse_args(argv)
    import yaml

    extra = {key: yaml.safe_load(value) for key, value in (item.split("=", 1) for item in args.set)}
    rows = probe(args.case, args.steps, extra)
    for row in rows:
        print(f"{row['step']:3d}  central {row['central_cost']:9.2f}  admm {row['admm_cost']:9.2f}  "
              f"it {row['admm_iterations']:3d}  input change {row['input_change']}")
    if args.out is not None:
        args.out.write_text("".join(json.dumps(row) + "\n" for row in rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
