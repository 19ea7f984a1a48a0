"""The paper's experiment set (Section V): define it, run it, collect it, write figures and a report.

``swarmpc reproduce`` calls :func:`reproduce`. The set (docs/paper-reproduction.md): the built-in
``paper-2d`` and ``paper-3d`` swaps (M = 4, N = 10, dt = 0.1, Q = 0.1 I, R = I, Qf = I) for
Δ ∈ {0.1, 0.3, 0.5}, hard and soft OBCA, consensus ADMM, each also with the centralised solver
for reference; plus the initial-guess study at Δ = 0.3 (straight, shifted, RRT, auto). Every run
is an ordinary run folder under ``OUT/runs/``; the report reads its numbers back from those
folders' ``summary.json``, so a number in the report is always one a run wrote. Seeds are fixed
(scenario ``seed`` 0, which also seeds RRT).

Runs go to a pool of worker processes (``jobs``, :mod:`swarmpc.batch`); each run is
single-threaded, so per-step times are comparable between runs only as far as the machine is not
oversubscribed.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Sequence
from contextlib import closing
from dataclasses import asdict
from pathlib import Path
from typing import Any

from swarmpc.batch import Task, error_line, run_batch
from swarmpc.config import scenario_to_yaml
from swarmpc.experiments.figures import write_figures
from swarmpc.experiments.plan import (
    FORMS,
    GUESS_DELTA,
    GUESSES,
    MANIFEST,
    PAPER_DELTAS,
    REPORT,
    RUNS_DIR,
    SCENARIOS,
    SEED,
    Log,
    ReproducePlan,
    RunOutcome,
    RunRecord,
    RunSpec,
    plan_runs,
)
from swarmpc.experiments.report import write_report
from swarmpc.simulation.rundata import SUMMARY_FILE, read_summary

# the set's definition (experiments/plan.py) is public here too, beside the functions that run it
__all__ = [
    "FORMS", "GUESS_DELTA", "GUESSES", "MANIFEST", "PAPER_DELTAS", "REPORT", "RUNS_DIR", "SCENARIOS", "SEED",
    "Log", "ReproducePlan", "RunOutcome", "RunRecord", "RunSpec", "plan_runs",
    "collect", "default_jobs", "execute", "export_doc_figures", "load_set", "reproduce", "run_one",
]


def run_one(spec: RunSpec, folder: str) -> RunOutcome:
    """Simulate one spec and write its run folder (in a worker process); a failure becomes the
    outcome's one-line error, so the report can name it."""
    from swarmpc.simulation.loop import simulate
    from swarmpc.simulation.results import write_run

    started, cpu = time.perf_counter(), time.process_time()
    error = None
    try:
        write_run(simulate(spec.build()), folder, overwrite=True)
    except Exception as err:  # noqa: BLE001 - one failed run must not lose the others
        error = error_line(err)
    return RunOutcome(spec, folder, error, time.perf_counter() - started, time.process_time() - cpu)


def _reusable(spec: RunSpec, folder: Path) -> bool:
    """A complete run folder of exactly this scenario already exists."""
    try:
        return (folder / "summary.json").is_file() and (folder / "scenario.yaml").read_text() == scenario_to_yaml(
            spec.build()
        )
    except OSError:
        return False


def execute(
    specs: Sequence[RunSpec], runs_dir: Path, jobs: int, reuse: bool = False, log: Log | None = None
) -> list[RunOutcome]:
    """Run every spec into ``runs_dir/<name>``, ``jobs`` at a time, one progress line each as it
    finishes; outcomes in ``specs`` order. With ``reuse``, a complete folder of the same scenario
    counts as done. Ctrl-C or SIGTERM: ``KeyboardInterrupt`` once the workers are down, with the
    finished run folders in place (``reuse`` skips them next time)."""
    say = log or (lambda _line: None)
    runs_dir.mkdir(parents=True, exist_ok=True)
    outcomes: dict[str, RunOutcome] = {}
    todo = []
    for spec in specs:
        folder = runs_dir / spec.name
        if reuse and _reusable(spec, folder):
            outcomes[spec.name] = RunOutcome(spec, str(folder), None, 0.0, 0.0, reused=True)
        else:
            todo.append(spec)
    tasks = [Task(run_one, (spec, str(runs_dir / spec.name))) for spec in todo]
    with closing(run_batch(tasks, max(jobs, 1))) as finished:
        for done, result in enumerate(finished, len(outcomes) + 1):
            spec = todo[result.index]
            # run_one reports a failed run itself; this is a failed worker (it died, or could not pickle)
            outcome = result.value if result.ok else RunOutcome(spec, str(runs_dir / spec.name), result.error, 0, 0)
            outcomes[spec.name] = outcome
            status = (f"FAILED ({outcome.error})" if outcome.error
                      else f"{outcome.seconds:.0f} s ({outcome.cpu_seconds:.0f} s CPU)")
            say(f"[{done}/{len(specs)}] {spec.name}: {status}")
    return [outcomes[spec.name] for spec in specs]


def collect(out: Path, outcomes: Sequence[RunOutcome]) -> list[RunRecord]:
    """Read back the summary of every successful run (the only source of the report's numbers)."""
    records = []
    for outcome in outcomes:
        if outcome.error is not None:
            continue
        folder = Path(outcome.folder)
        summary = read_summary(folder / SUMMARY_FILE)  # a damaged file: one ValueError line naming it
        records.append(RunRecord(outcome.spec, folder.relative_to(out).as_posix(), summary))
    return records


def _loadavg() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def default_jobs() -> int:
    """One worker per core."""
    return max(1, os.cpu_count() or 1)


def reproduce(
    out: str | os.PathLike[str] = "results/reproduce",
    quick: bool = False,
    jobs: int | None = None,
    reuse: bool = False,
    animations: bool = True,
    log: Log | None = None,
) -> Path:
    """Run the paper's experiment set and write figures, ``report.md`` and ``reproduce.json``.

    Parameters
    ----------
    out : path
        Output folder; run folders go to ``out/runs/<name>``.
    quick : bool
        The small plan of :func:`plan_runs` (a smoke test of the whole pipeline).
    jobs : int, optional
        Worker processes; default one per core.
    reuse : bool
        Keep run folders whose ``scenario.yaml`` already matches instead of re-running them.
    animations : bool
        Also write GIF animations of the representative runs.
    log : callable, optional
        Receives one progress line per finished run.

    Returns
    -------
    Path
        The written ``report.md``.
    """
    say = log or (lambda _line: None)
    folder = Path(out).resolve()
    folder.mkdir(parents=True, exist_ok=True)
    plan = plan_runs(quick)
    jobs = jobs or default_jobs()
    specs = plan.specs()
    say(f"reproduce: {len(specs)} runs, {jobs} parallel jobs, into {folder}/{RUNS_DIR}/")
    load_before = _loadavg()
    started_utc = time.strftime("%Y-%m-%d %H:%M", time.gmtime())
    started = time.perf_counter()
    outcomes = execute(specs, folder / RUNS_DIR, jobs, reuse=reuse, log=say)
    runs_seconds = time.perf_counter() - started
    records = collect(folder, outcomes)
    figures = write_figures(folder, plan, records, animations=animations)
    total_seconds = time.perf_counter() - started
    manifest = {
        "quick": quick,
        "started_utc": started_utc,
        "jobs": jobs,
        "cpu_count": os.cpu_count(),
        "loadavg_before": load_before,
        "loadavg_after": _loadavg(),
        "runs_wall_time_s": runs_seconds,
        "runs_cpu_time_s": sum(o.cpu_seconds for o in outcomes),
        "wall_time_s": total_seconds,
        "plan": asdict(plan),
        "figures": figures,
        "runs": [
            {"name": o.spec.name, "folder": Path(o.folder).relative_to(folder).as_posix(),
             "spec": asdict(o.spec), "error": o.error, "seconds": o.seconds, "cpu_seconds": o.cpu_seconds,
             "reused": o.reused}
            for o in outcomes
        ],
    }
    (folder / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n")
    report = write_report(folder, plan, records, manifest)
    say(f"reproduce: wrote {report} ({total_seconds:.0f} s)")
    return report


def load_set(out: str | os.PathLike[str]) -> tuple[ReproducePlan, list[RunRecord], dict[str, Any]]:
    """Plan, records and manifest of a finished ``reproduce`` output folder (for re-rendering)."""
    folder = Path(out).resolve()
    manifest = json.loads((folder / MANIFEST).read_text())
    raw = manifest["plan"]
    plan = ReproducePlan(**{
        **raw,
        "deltas": tuple((name, tuple(deltas)) for name, deltas in raw["deltas"]),
        **{key: tuple(raw[key]) for key in ("forms", "guess_scenarios", "guesses")},
    })
    outcomes = [RunOutcome(RunSpec(**run["spec"]), str(folder / run["folder"]), run["error"], run["seconds"],
                           run.get("cpu_seconds", 0.0)) for run in manifest["runs"]]
    return plan, collect(folder, outcomes), manifest


def export_doc_figures(out: str | os.PathLike[str], dest: str | os.PathLike[str], dpi: int = 90) -> dict[str, str]:
    """Re-render a finished set's figures as small palette PNGs ``dest/repro-*.png`` (the docs copies)."""

    plan, records, _manifest = load_set(out)
    return write_figures(Path(out).resolve(), plan, records, animations=False, dest=Path(dest), prefix="repro-",
                         dpi=dpi, palette=True)
