"""Experiments on top of the simulation layer: the paper's experiment set (``swarmpc reproduce``).

This package is a face, like the CLI: it imports :mod:`swarmpc.simulation`, :mod:`swarmpc.config`
and :mod:`swarmpc.plots`; nothing below it imports it.

* :mod:`swarmpc.experiments.reproduce`: the run set, running it (in parallel processes),
  collecting the run folders and writing the report;
* :mod:`swarmpc.experiments.figures`: the report's figures (paper Figs. 3-5 and the guess study);
* :mod:`swarmpc.experiments.report`: the markdown report, every number read from ``summary.json``.
"""

from swarmpc.experiments.reproduce import ReproducePlan, RunSpec, plan_runs, reproduce

__all__ = ["ReproducePlan", "RunSpec", "plan_runs", "reproduce"]
