"""The ``swarmpc`` command line: run scenarios, list them, plot and animate run folders.

Bad input never produces a traceback: it is one line on stderr naming the field, exit status 2,
and no output folder. Ctrl-C outside a run's simulation loop (which stops early and still writes
an interrupted run folder) is one line ``swarmpc: interrupted``, exit status 130, nothing written.
"""

from __future__ import annotations

import signal
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from enum import StrEnum
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Annotated, Any, NoReturn

import numpy as np
import typer
import yaml

from swarmpc._interrupts import INTERRUPTED, caused_by_interrupt
from swarmpc.config import MAX_AGENTS, Scenario, ScenarioError, executor_problem, load_scenario
from swarmpc.simulation.outdir import OutputError, RunFolderTarget

if TYPE_CHECKING:
    from swarmpc.simulation.rundata import RunData

app = typer.Typer(
    add_completion=False,
    no_args_is_help=False,
    help="Distributed MPC for robot swarms (consensus ADMM + OBCA collision avoidance).",
    pretty_exceptions_enable=False,
)


class Method(StrEnum):
    admm = "admm"
    centralized = "centralized"


class Collision(StrEnum):
    hard = "hard"
    soft = "soft"


class Guess(StrEnum):
    auto = "auto"
    rrt = "rrt"
    straight = "straight"
    shifted = "shifted"


class ExecutorName(StrEnum):
    serial = "serial"
    process = "process"
    ray = "ray"


class PlantName(StrEnum):
    double_integrator = "double_integrator"
    mujoco = "mujoco"


class LocalSolver(StrEnum):
    qp = "qp"
    ipopt = "ipopt"




class Interrupted(Exception):
    """Raised by a command that explains its own interruption; :func:`main` prints the line."""


def fail(message: str) -> NoReturn:
    """One line on stderr, exit status 2."""
    typer.echo(f"swarmpc: error: {message}", err=True)
    raise typer.Exit(code=2)


def interrupted(message: str = "swarmpc: interrupted") -> NoReturn:
    """One line on stderr, exit status 130 (printed by :func:`main`)."""
    raise Interrupted(message)


def check_generator_params(seed: int | None, agents: int | None, dim: int | None) -> None:
    """Reject the built-in generators' parameters that would crash or spin them before the
    scenario's own validation sees the result (``random --seed -1``, ``random --dim 0``)."""
    if seed is not None and seed < 0:
        fail(f"seed: must be >= 0, got {seed}")
    if agents is not None and agents < 1:
        fail(f"agents: must be >= 1, got {agents}")
    if dim is not None and dim not in (2, 3):
        fail(f"dim: must be 2 or 3, got {dim}")


def resolve_scenario(name_or_file: str, **params: Any) -> Scenario:
    """A built-in scenario by name, or a YAML file by path."""
    from swarmpc.scenarios import BUILTINS, builtin_scenario

    if name_or_file in BUILTINS:
        return builtin_scenario(name_or_file, **params)
    path = Path(name_or_file)
    if path.suffix.lower() in (".yaml", ".yml") or path.exists():
        return load_scenario(path)
    raise ScenarioError(
        f"scenario: {name_or_file!r} is neither a built-in ({', '.join(BUILTINS)}) nor a file"
    )


@app.command()
def run(
    scenario: Annotated[str, typer.Argument(help="built-in name or YAML file")] = "paper-2d",
    out: Annotated[Path | None, typer.Option(help="output folder [results/<name>]")] = None,
    method: Annotated[Method | None, typer.Option(help="solver (default: the scenario's, admm)")] = None,
    collision: Annotated[Collision | None, typer.Option(help="OBCA form")] = None,
    delta: Annotated[float | None, typer.Option(help="half-size of the box around each agent")] = None,
    seed: Annotated[int | None, typer.Option(help="seed for random scenarios and RRT")] = None,
    agents: Annotated[int | None, typer.Option(help="number of agents (circle, random, spread, crossing)")] = None,
    dim: Annotated[int | None, typer.Option(help="2 or 3 (circle, random, spread)")] = None,
    rho: Annotated[float | None, typer.Option(help="ADMM penalty")] = None,
    admm_tol: Annotated[float | None, typer.Option(help="ADMM residual tolerance [m]")] = None,
    admm_max_iter: Annotated[int | None, typer.Option(help="ADMM iteration cap per step")] = None,
    plane_margin: Annotated[float | None, typer.Option(
        help="keep near, not engaged pairs apart by separating planes instead of copies [m]")] = None,
    local: Annotated[LocalSolver | None, typer.Option(
        help="ADMM agents' local step: ipopt (the NLP) or qp (convex QPs, IPOPT as fallback) "
        "(default: the scenario's; qp unless it has cars)")] = None,
    deadline: Annotated[float | None, typer.Option(
        help="ADMM critical-path budget per MPC step, in seconds: stop iterating before an overrun and end "
        "the step through the repair pass (default: the scenario's solver.deadline, none)")] = None,
    initial_guess: Annotated[Guess | None, typer.Option(help="initial-guess strategy")] = None,
    max_steps: Annotated[int | None, typer.Option(help="MPC steps at most")] = None,
    plant: Annotated[PlantName | None, typer.Option(
        help="what the inputs drive: the ideal model or MuJoCo rigid bodies (settings: the scenario's plant:)")] = None,
    executor: Annotated[
        ExecutorName | None, typer.Option(
            help="where the ADMM agents' local solves run (admm only) (default: the scenario's executor.type, "
            "serial)")
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(min=1, help="worker processes / Ray actors [the scenario's executor.workers; available "
                     "cores; Ray: the cluster's CPUs]"),
    ] = None,
    address: Annotated[
        str | None, typer.Option(help="Ray cluster to join (auto, ray://host:port) [the scenario's "
                                 "executor.address; start a local Ray]")
    ] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="no progress bar, no paragraph")] = False,
    overwrite: Annotated[bool, typer.Option(
        "--overwrite", help="replace an earlier run folder at the output path (never anything else)")] = False,
) -> None:
    """Run a scenario in closed loop and write summary.json, trajectory.npz and a figure.

    The output path is checked before the run: an existing path there is refused unless it is a
    swarmpc run folder and --overwrite is given. --executor, --workers and --address override
    the scenario's executor section."""
    check_generator_params(seed, agents, dim)
    if executor is not None:
        check_executor_options(executor.value, workers, address)
    try:
        params: dict[str, Any] = {"agents": agents, "dim": dim, "seed": seed}
        scn = resolve_scenario(scenario, **params)
        scn = scn.with_updates(
            **{
                "solver.method": method.value if method else None,
                "collision": collision.value if collision else None,
                "delta": delta,
                "seed": seed,
                "solver.rho": rho,
                "solver.tol": admm_tol,
                "solver.max_iter": admm_max_iter,
                "solver.plane_margin": plane_margin,
                "solver.local": local.value if local else None,
                "solver.deadline": deadline,
                "solver.initial_guess": initial_guess.value if initial_guess else None,
                "stop.max_steps": max_steps,
            }
        )
        if plant is not None:  # the double integrator takes none of the physics settings
            physics = {} if plant is PlantName.double_integrator else scn.plant.model_dump()
            scn = scn.with_updates(plant={**physics, "type": plant.value})
    except ScenarioError as err:
        fail(str(err))
    scn = with_executor_options(scn, executor, workers, address)
    check_plant_available(scn)
    target = reserve_output(out or Path("results") / scn.name, overwrite, scn)
    try:
        runner = build_executor(scn, "--executor" if executor is not None else "executor.type")
    except BaseException:
        target.discard()
        raise
    _run_and_write(scn, target, quiet, runner)


def check_plant_available(scn: Scenario) -> None:
    """A MuJoCo plant needs the ``mujoco`` package: one line before any work when it is missing."""
    import importlib.util

    if scn.plant.type == "mujoco" and importlib.util.find_spec("mujoco") is None:
        fail("--plant: mujoco needs the mujoco package (pip install mujoco)")


def reserve_output(path: Path, overwrite: bool, scn: Scenario) -> RunFolderTarget:
    """Check and reserve the run folder's location before any work (one line on a refusal)."""
    from swarmpc.simulation.results import expected_run_bytes

    try:
        return RunFolderTarget(path, overwrite, expected_run_bytes(scn))
    except OutputError as err:
        fail(str(err))


EXECUTOR_OPTION_NAMES = {"type": "--executor", "workers": "--workers", "address": "--address"}
"""How :func:`swarmpc.config.executor_problem` names the executor keys on the command line."""


def check_executor_options(executor: str, workers: int | None, address: str | None) -> None:
    """``--workers`` and ``--address`` only mean something with the executors that use them
    (``executor``: the type they go with, the option's or the scenario's)."""
    problem = executor_problem(executor, workers, address, EXECUTOR_OPTION_NAMES)
    if problem is not None:
        fail(problem)


def with_executor_options(
    scn: Scenario, executor: ExecutorName | None, workers: int | None, address: str | None
) -> Scenario:
    """The scenario with the command line's executor options over its ``executor`` section (the
    command line wins): ``--executor`` replaces the section; ``--workers`` or ``--address`` alone
    change that key of it. Only ADMM has local solves to distribute, so a non-serial executor with
    the centralised solver is an error, not a no-op."""
    if executor is None and workers is None and address is None:
        return scn
    kind = executor.value if executor is not None else scn.executor.type
    check_executor_options(kind, workers, address)
    if kind != "serial" and scn.solver.method != "admm":
        fail(f"--executor: {kind} only applies to solver.method admm, this run uses {scn.solver.method}")
    if executor is not None:
        section = {"type": kind, "workers": workers, "address": address}
    else:
        given = {"workers": workers, "address": address}
        section = {**scn.executor.model_dump(), **{key: value for key, value in given.items() if value is not None}}
    try:
        return scn.with_updates(executor=section)
    except ScenarioError as err:
        fail(str(err))


def build_executor(scn: Scenario, option: str = "--executor") -> _WorkersIgnoreCtrlC | None:
    """The run's executor, as the scenario's ``executor`` section says (``None``: serial, the
    solver's own). This function's caller owns it and closes it. ``option`` names the choice in a
    refusal (the command line's ``--executor`` or the scenario's ``executor.type``)."""
    from swarmpc.simulation.controller import section_executor

    kind = scn.executor.type
    if kind == "serial":
        return None
    try:
        made = section_executor(scn.executor)
    except ValueError as err:  # RayExecutor: Ray is not importable
        if kind == "ray":
            fail(f"{option}: ray needs Ray, which is not installed: pip install 'swarmpc[ray]'")
        fail(f"{option}: {str(err).splitlines()[0]}")
    return None if made is None else _WorkersIgnoreCtrlC(made, kind)


class _WorkersIgnoreCtrlC:
    """An executor whose worker processes ignore SIGINT.

    Ctrl-C in a terminal goes to the whole process group: a worker process would be interrupted
    mid-solve (failed local solves, then a dead worker and a traceback) instead of the run's clean
    stop (finish the step, write an interrupted run folder). An ignored signal stays ignored across
    the workers' exec, so SIGINT is ignored while they start; a Ctrl-C during those seconds is lost.
    Ray keeps SIGINT from its own processes itself, so its executor is left alone.
    """

    def __init__(self, inner: Any, name: str) -> None:
        self.inner = inner
        self.name = name

    def start(self, factory: Any, agent_ids: Any) -> None:
        if self.name != "process":
            self.inner.start(factory, agent_ids)
            return
        previous = {sig: signal.signal(sig, signal.SIG_IGN) for sig in (signal.SIGINT, signal.SIGTERM)}
        try:
            self.inner.start(factory, agent_ids)
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)

    def solve(self, requests: Any) -> list[Any]:
        return self.inner.solve(requests)

    def close(self) -> None:
        self.inner.close()


def _run_and_write(
    scn: Scenario, target: RunFolderTarget, quiet: bool, executor: _WorkersIgnoreCtrlC | None = None
) -> None:
    """Simulate and write the run folder. SIGINT and SIGTERM end the loop after the current step
    and the interrupted run is written whole; while the folder is written they are held off, so a
    signal never leaves half a folder."""
    from swarmpc.simulation.loop import StopFlag

    stop = StopFlag()

    def on_signal(_signum: int, _frame: FrameType | None) -> None:
        stop.requested = True

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        result = _simulate_with_progress(scn, quiet, stop, executor)
        folder = _write_with_figure(result, target)
    except BaseException:
        target.discard()
        raise
    finally:
        if executor is not None:  # this function made it, this function closes it (interrupted too)
            executor.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if not quiet:
        typer.echo(result_paragraph(result.summary, folder))


PROGRESS_LINE_EVERY_S = 5.0
"""When stderr is not a terminal, a progress line at most this often."""


class RunProgress:
    """How far a run is: steps, agents at their goals, and an estimate of the time left (from the
    larger of the step fraction and the fraction of the start-to-goal distance covered)."""

    def __init__(self, scn: Scenario) -> None:
        self.scn = scn
        self.goals = scn.goal_states()[:, : scn.dim]
        self.initial = float(np.linalg.norm(scn.start_states()[:, : scn.dim] - self.goals, axis=1).sum())
        self.started = time.monotonic()

    def describe(self, step: int, states: Any) -> tuple[str, str]:
        """('k agents at goal', 'ETA ~s') for the states after ``step`` steps."""
        gaps = np.linalg.norm(states[:, : self.scn.dim] - self.goals, axis=1)
        at_goal = int(np.sum(gaps <= self.scn.stop.goal_tolerance))
        covered = 1.0 - float(gaps.sum()) / self.initial if self.initial > 0 else 1.0
        fraction = max(step / self.scn.stop.max_steps, min(max(covered, 0.0), 1.0))
        elapsed = time.monotonic() - self.started
        eta = f"ETA ~{elapsed * (1 - fraction) / fraction:.0f} s" if fraction > 0.02 else "ETA -"
        return f"{at_goal}/{self.scn.num_agents} at goal", eta


def _simulate_with_progress(
    scn: Scenario, quiet: bool, stop: Any, executor: _WorkersIgnoreCtrlC | None
) -> Any:
    """The closed loop with a progress bar and an ETA on a terminal, or a line every few seconds
    on stderr otherwise; executor failures become one line."""
    from dataclasses import replace

    from rich.console import Console

    from swarmpc.simulation.loop import simulate
    from swarmpc.solvers.executors import ExecutorError

    console = Console(stderr=True)
    try:
        if quiet:
            result = simulate(scn, stop_flag=stop, executor=executor)
        elif console.is_terminal:
            result = _with_bar(scn, stop, executor, console)
        else:
            result = simulate(scn, progress=_progress_lines(scn), stop_flag=stop, executor=executor)
    except ExecutorError as err:
        fail(str(err).splitlines()[0])
    if scn.solver.method == "admm":
        name = executor.name if executor else "serial"
        result = replace(result, summary={**result.summary, "executor": name})
    return result


def _with_bar(scn: Scenario, stop: Any, executor: Any, console: Any) -> Any:
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from swarmpc.simulation.loop import simulate

    progress = RunProgress(scn)
    with Progress(
        TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("step {task.completed}"),
        TextColumn("{task.fields[goals]}"), TimeElapsedColumn(), TextColumn("{task.fields[eta]}"),
        console=console, transient=True,
    ) as bar:
        task = bar.add_task(f"{scn.name} ({scn.solver.method})", total=scn.stop.max_steps, goals="", eta="")

        def update(k: int, _n: int, states: Any) -> None:
            goals, eta = progress.describe(k, states)
            bar.update(task, completed=k, goals=goals, eta=eta)

        return simulate(scn, progress=update, stop_flag=stop, executor=executor)


def _progress_lines(scn: Scenario, every_s: float = PROGRESS_LINE_EVERY_S) -> Any:
    """A progress callback that writes one line to stderr at most every ``every_s`` seconds."""
    progress = RunProgress(scn)
    last = [progress.started]

    def report(k: int, n: int, states: Any) -> None:
        now = time.monotonic()
        if now - last[0] < every_s:
            return
        last[0] = now
        goals, eta = progress.describe(k, states)
        typer.echo(f"swarmpc: {scn.name}: step {k}/{n}, {goals}, {now - progress.started:.0f} s, {eta}", err=True)

    return report


def _write_with_figure(result: Any, target: RunFolderTarget) -> Path:
    from swarmpc.plots import RunDataError, load_run, plot_trajectories
    from swarmpc.simulation.results import RunResult, write_run

    def figure(run: RunResult, folder: Path) -> None:
        try:
            plot_trajectories(load_run(folder), folder / "trajectory.png")
        except RunDataError as err:  # a run whose arrays cannot be drawn is still written
            typer.echo(f"swarmpc: warning: no trajectory.png: {str(err).splitlines()[0]}", err=True)

    try:
        return write_run(result, target, extra_writers=[figure])
    except OutputError as err:
        fail(str(err))


def result_paragraph(summary: dict[str, Any], folder: Path) -> str:
    """The one-paragraph human summary printed at the end of a run."""
    reached = sum(summary["reached"])
    times = summary["step_time_ms"]
    iterations = summary.get("admm_iterations")
    admm = (
        f" ADMM took {iterations['mean']:.1f} iterations per step on average"
        f" (median {iterations['median']:.0f}, max {iterations['max']})."
        if iterations and iterations.get("mean") is not None
        else ""
    )
    sep = summary.get("min_separation_ratio")
    sep_text = f"min separation {sep:.2f} x (b_i + b_j)" if sep is not None else "min separation n/a"
    if "min_footprint_distance" in summary:  # a swarm with cars: the exact distance between footprints
        gap = summary["min_footprint_distance"]
        sep_text = f"min footprint distance {gap:.3f} m" if gap is not None else "min footprint distance n/a"
    status = "interrupted; " if summary.get("interrupted") else ""
    median = f"{times['median']:.1f}" if times["median"] is not None else "n/a"
    p95 = f"{times['p95']:.1f}" if times["p95"] is not None else "n/a"
    return (
        f"{status}{summary['scenario']} ({summary['method']}, {summary['collision']}): "
        f"{reached}/{summary['num_agents']} agents reached their goals in {summary['steps']} steps "
        f"({summary['sim_time_s']:.1f} s simulated), {summary['collisions']} collisions, "
        f"{sep_text}, closed-loop cost {summary['cost']:.1f}. "
        f"Per-step solve time {median} ms median, {p95} ms p95.{admm} "
        f"Solver failures: {summary['solver_failures']}, deadlocks resolved: {summary['deadlocks']}. "
        f"Wrote {folder}/"
    )


def check_out_file(out: Path | None, overwrite: bool) -> None:
    """A user-named output file replaces an existing file only with --overwrite."""
    from swarmpc.simulation.outdir import refuse_existing_file

    if out is None:
        return
    try:
        refuse_existing_file(out, overwrite)
    except OutputError as err:
        fail(str(err))


@contextmanager
def claimed_out_folder(out: Path, kind: str) -> Iterator[Path]:
    """The output folder of a report command, refused when it is somebody else's; a folder this
    command created is removed again when the command fails before writing into it."""
    from swarmpc.simulation.outdir import claim_folder, normalise_target, unclaim_folder

    new = not normalise_target(out).exists()
    try:
        folder = claim_folder(out, kind)
    except OutputError as err:
        fail(str(err))
    try:
        yield folder
    except BaseException:
        if new:
            unclaim_folder(folder, kind)
        raise


@app.command()
def scenarios() -> None:
    """List the built-in scenarios."""
    from swarmpc.scenarios import BUILTINS

    width = max(len(name) for name in BUILTINS)
    for name, (_factory, text) in BUILTINS.items():
        typer.echo(f"{name:<{width}}  {text}")


def loaded_run(run_dir: Path) -> RunData:
    """The run folder ``run_dir`` loaded, or one line and exit 2: a damaged folder is refused before
    the plotting libraries load (about 1 s)."""
    from swarmpc.simulation.rundata import RunDataError, load_run

    try:
        return load_run(run_dir)
    except (RunDataError, OSError) as err:
        fail(str(err).splitlines()[0])


@app.command()
def plot(run_dir: Annotated[Path, typer.Argument(help="a run folder")]) -> None:
    """Write trajectory.png (and convergence.png for ADMM runs) into a run folder."""
    from swarmpc.simulation.rundata import RunDataError

    run = loaded_run(run_dir)
    from swarmpc.plots import plot_run

    try:
        for path in plot_run(run):
            typer.echo(str(path))
    except (RunDataError, OSError) as err:
        fail(str(err).splitlines()[0])


@app.command()
def animate(
    run_dir: Annotated[Path, typer.Argument(help="a run folder")],
    format: Annotated[str, typer.Option("--format", help="gif or mp4")] = "gif",
    out: Annotated[Path | None, typer.Option(help="output file [RUN_DIR/animation.FORMAT]")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="replace an existing --out file")] = False,
) -> None:
    """Animate a run: moving agents with their delta boxes, trails and a time stamp."""
    from swarmpc.simulation.rundata import RunDataError

    if format not in ("gif", "mp4"):
        fail(f"--format: must be gif or mp4, got {format!r}")
    check_out_file(out, overwrite)
    run = loaded_run(run_dir)
    from swarmpc.plots import AnimationWriterError
    from swarmpc.plots import animate as write_animation

    try:
        path = write_animation(run, out or run_dir / f"animation.{format}", fmt=format)  # type: ignore[arg-type]
    except (RunDataError, AnimationWriterError, OSError) as err:
        fail(str(err).splitlines()[0])
    typer.echo(str(path))


@app.command()
def view(
    run_dir: Annotated[Path, typer.Argument(help="a run folder")],
    out: Annotated[Path | None, typer.Option(help="output HTML [RUN_DIR/view.html]")] = None,
    open_browser: Annotated[bool, typer.Option("--open", help="open it in the default browser")] = False,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="replace an existing --out file")] = False,
) -> None:
    """Write one self-contained interactive HTML page of a run (works offline)."""
    from swarmpc.viewer import write_view

    check_out_file(out, overwrite)
    if not (run_dir / "trajectory.npz").is_file():
        fail(f"{run_dir}: not a run folder (no trajectory.npz)")
    try:
        path = write_view(run_dir, out=out, open_browser=open_browser)
    except (ValueError, OSError) as err:
        fail(str(err).splitlines()[0])
    typer.echo(str(path))


@app.command()
def export(
    run_dir: Annotated[Path, typer.Argument(help="a run folder")],
    format: Annotated[str, typer.Option(
        "--format", help="csv (one row per agent and state) or mcap (scenes and metrics for Foxglove)")],
    out: Annotated[Path | None, typer.Option(help="output file [RUN_DIR/run.FORMAT]")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="replace an existing --out file")] = False,
) -> None:
    """Export a run for other tools: CSV, or MCAP that opens in Foxglove (see the run-folder reference)."""
    from swarmpc.export import FORMATS, export_run
    from swarmpc.simulation.rundata import RunDataError

    if format not in FORMATS:
        fail(f"--format: must be {' or '.join(FORMATS)}, got {format!r}")
    try:
        path = export_run(run_dir, format, out=out, overwrite=overwrite)
    except (RunDataError, OutputError, OSError) as err:
        fail(str(err).splitlines()[0])
    typer.echo(str(path))


@app.command()
def reproduce(
    out: Annotated[Path, typer.Option(help="output folder")] = Path("results/reproduce"),
    quick: Annotated[bool, typer.Option("--quick", help="small plan (fewer deltas, 25 steps): a smoke test")] = False,
    jobs: Annotated[int | None, typer.Option(min=1, help="runs in parallel processes [number of cores]")] = None,
    reuse: Annotated[bool, typer.Option("--reuse", help="keep run folders whose scenario already matches")] = False,
    animations: Annotated[bool, typer.Option(help="also write GIF animations")] = True,
) -> None:
    """Run the paper's experiment set; write run folders, figures and OUT/report.md."""
    from swarmpc.experiments.reproduce import reproduce as run_set

    try:
        with claimed_out_folder(out, "reproduce"):
            report = run_set(out, quick=quick, jobs=jobs, reuse=reuse, animations=animations,
                             log=lambda line: typer.echo(line, err=True))
    except KeyboardInterrupt:
        interrupted(f"swarmpc: interrupted; finished run folders are kept in {out}/runs "
                    "(--reuse skips them next time)")
    except (ValueError, OSError) as err:
        fail(str(err).splitlines()[0])
    typer.echo(str(report))


@app.command()
def bench(
    out: Annotated[Path, typer.Option(help="folder for bench.md and bench.json")] = Path("results/bench"),
    quick: Annotated[bool, typer.Option("--quick", help="M in {4, 8}, one seed: a smoke run")] = False,
    families: Annotated[
        str, typer.Option(help="comma-separated: circle, sphere, random, spread, crossing (cars; sizes "
                          "multiples of 4)")] = "circle,sphere,random",
    sizes: Annotated[str | None, typer.Option(help="comma-separated swarm sizes [4,8,16,32,64]")] = None,
    seeds: Annotated[
        int | None, typer.Option(min=1, help="seeds of the random and spread families [5; quick 1]")] = None,
    first_seed: Annotated[int, typer.Option(min=0, help="first seed of the random and spread families")] = 0,
    jobs: Annotated[
        int | None, typer.Option(min=1, help="cases side by side [cores; 1 with a parallel executor]")] = None,
    executor: Annotated[
        ExecutorName, typer.Option(help="where each ADMM case's local solves run")] = ExecutorName.serial,
    workers: Annotated[int | None, typer.Option(min=1, help="process-pool size / Ray actors")] = None,
    budget: Annotated[float, typer.Option(min=1.0, help="wall-time budget per case [s]")] = 600.0,
    central_max_agents: Annotated[int, typer.Option(min=0, help="largest M also run centralised")] = 16,
    max_steps: Annotated[int | None, typer.Option(min=1, help="override every case's step cap")] = None,
    plane_margin: Annotated[float | None, typer.Option(
        min=0.0, help="solver.plane_margin of every ADMM case [m] [the scenarios' own: off]")] = None,
    local: Annotated[str | None, typer.Option(
        help="comma-separated ADMM local steps (qp, ipopt): every ADMM case runs once with each, side by side "
        "in the table [the scenarios' own: qp, ipopt for the car families]")] = None,
    save_runs: Annotated[bool, typer.Option("--save-runs", help="keep every run's folder under OUT/runs")] = False,
    merge: Annotated[list[Path] | None, typer.Option(
        help="run nothing: one report from these earlier bench.json files or folders (repeatable)")] = None,
    settings: Annotated[list[str] | None, typer.Option(
        "--set", help="KEY=VALUE: a scenario setting of every case (repeatable; dotted key, YAML value), "
        "e.g. --set weights.Q=1 --set weights.R=0.1")] = None,
) -> None:
    """The scaling benchmark: swarms of growing size; writes OUT/bench.md and OUT/bench.json
    (rewritten after every finished run, so a long study interrupted keeps what it measured)."""
    from swarmpc.bench import FAMILIES, LOCAL_STEPS, merge_reports, run_bench

    if merge:
        try:
            with claimed_out_folder(out, "bench"):
                markdown, _ = merge_reports(merge, out)
        except (ValueError, OSError) as err:
            fail(f"--merge: {str(err).splitlines()[0]}")
        typer.echo(str(markdown))
        return

    try:
        size_list = [int(v) for v in sizes.split(",")] if sizes else None
    except ValueError:
        fail(f"--sizes: expected comma-separated integers, got {sizes!r}")
    if size_list is not None and any(not 1 <= m <= MAX_AGENTS for m in size_list):
        fail(f"--sizes: every size must be between 1 and {MAX_AGENTS}, got {sizes!r}")
    family_list = [f.strip() for f in families.split(",") if f.strip()]
    unknown = sorted(set(family_list) - set(FAMILIES))
    if unknown or not family_list:
        fail(f"--families: unknown {', '.join(unknown) or 'none given'} (choose from {', '.join(FAMILIES)})")
    local_list = [v.strip() for v in local.split(",") if v.strip()] if local is not None else None
    if local_list is not None and (not local_list or set(local_list) - set(LOCAL_STEPS)
                                   or len(set(local_list)) != len(local_list)):
        fail(f"--local: expected comma-separated local steps, each once, from {', '.join(LOCAL_STEPS)}; "
             f"got {local!r}")
    overrides = _bench_settings(settings or [])
    try:
        with claimed_out_folder(out, "bench"):
            markdown, _ = run_bench(
                out, quick=quick, families=family_list,
                sizes=size_list, seeds=seeds, jobs=jobs, executor=executor.value, workers=workers,
                budget_s=budget, central_max_agents=central_max_agents, max_steps=max_steps,
                log=lambda line: typer.echo(line, err=True), first_seed=first_seed, save_runs=save_runs,
                plane_margin=plane_margin, locals_=local_list, settings=overrides,
            )
    except typer.Exit:  # a RuntimeError too: the command's own one-line refusal
        raise
    except RuntimeError as err:  # some cases failed; the report holds the others
        fail(str(err).splitlines()[0] if str(err) else type(err).__name__)
    except ValueError as err:
        fail(f"--{str(err).splitlines()[0]}")
    typer.echo(str(markdown))


def _bench_settings(items: list[str]) -> dict[str, Any]:
    """``--set KEY=VALUE`` options as {dotted key: YAML value}; one line and exit 2 when malformed."""
    settings: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip() or any(not part for part in key.strip().split(".")):
            fail(f"--set: expected KEY=VALUE with a dotted scenario key, got {item!r}")
        try:
            settings[key.strip()] = yaml.safe_load(text)
        except yaml.YAMLError:
            fail(f"--set: {key.strip()}: the value {text!r} is not YAML")
    return settings


def _print_version(value: bool) -> None:
    """``--version``: print ``swarmpc X.Y.Z`` (the installed package's version, defined once in
    pyproject.toml) and exit 0 before any command is parsed."""
    if value:
        from swarmpc import __version__

        typer.echo(f"swarmpc {__version__}")
        raise typer.Exit()


@app.callback()
def _global_options(
    version: Annotated[bool, typer.Option(
        "--version", is_eager=True, callback=_print_version, help="print the version and exit")] = False,
) -> None:
    """Distributed MPC for robot swarms (consensus ADMM + OBCA collision avoidance)."""


def _terminate_as_interrupt(_signum: int, _frame: FrameType | None) -> None:
    """SIGTERM is handled like Ctrl-C: what was started is cleaned up, one line, status 130."""
    raise KeyboardInterrupt


def main() -> None:
    """Console entry point: usage errors also exit with status 2 and one line; Ctrl-C (outside a
    run's simulation loop) exits with status 130 and one line ``swarmpc: interrupted``."""
    reported = False
    signal.signal(signal.SIGTERM, _terminate_as_interrupt)
    try:
        # typer turns a KeyboardInterrupt inside a command into a silent exit status 130
        code = app(standalone_mode=False)
    except typer.Exit as exit_:
        code = exit_.exit_code
    except (typer.Abort, KeyboardInterrupt):
        code = INTERRUPTED
    except Interrupted as err:
        typer.echo(str(err), err=True)
        code, reported = INTERRUPTED, True
    except Exception as err:  # the CLI library's usage errors carry format_message()
        format_message = getattr(err, "format_message", None)
        if caused_by_interrupt(err):
            # a Ctrl-C inside a library's lazy import (matplotlib's, before a run) comes out as that
            # library's error, with the KeyboardInterrupt as its cause
            code = INTERRUPTED
        elif format_message is None:
            raise
        else:
            line = format_message().splitlines()[0].replace("Value error, ", "")
            typer.echo(f"swarmpc: error: {line}", err=True)
            code = 2
    if code == INTERRUPTED and not reported:
        typer.echo("swarmpc: interrupted", err=True)
    sys.exit(code if isinstance(code, int) else 0)


if __name__ == "__main__":
    main()
