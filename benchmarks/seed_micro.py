"""How long seeding one pair's certificates takes (``swarmpc.solvers.dual_seed.pair_seed``).

Every local solve that starts from a guess seeds the OBCA certificate of each of its pairs at
every constrained step from the guessed offsets. This times that call alone: ``--pairs`` random
offset sequences of ``--steps`` steps in 3D (normal, scale 1.5 m, against a box of half-size 0.3 m,
so most offsets lie outside it and some inside), each seeded once, repeated ``--repeats`` times;
prints the microseconds per call of each repeat as JSON. Compare two checkouts by running it
under each one's source, interleaved:

    for r in 1 2 3; do for src in OLD/src NEW/src; do
        PYTHONPATH=$src .venv/bin/python benchmarks/seed_micro.py; done; done
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Sequence

import numpy as np


def main(argv: Sequence[str] | None = None) -> int:
    from swarmpc.formulation.ocp import OCPSettings
    from swarmpc.scenarios import builtin_scenario
    from swarmpc.solvers.dual_seed import pair_seed

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=2000)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    settings = OCPSettings.from_scenario(builtin_scenario("random", agents=4, dim=3, seed=0))
    rng = np.random.default_rng(0)
    offsets = [rng.normal(size=(args.steps, 3)) * 1.5 for _ in range(args.pairs)]
    half = np.full(3, 0.3)
    per_call = []
    for _ in range(args.repeats):
        start = time.perf_counter()
        for q in offsets:
            pair_seed("p", q, half, settings)
        per_call.append((time.perf_counter() - start) / args.pairs * 1e6)
    print(json.dumps({"us_per_call": np.round(per_call, 1).tolist()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
