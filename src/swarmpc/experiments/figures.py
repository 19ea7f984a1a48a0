"""Figures of the reproduction report: paper Figs. 3 (trajectories), 4 (ADMM convergence) and 5
(variation with Δ), a bar chart of the initial-guess study, and GIF animations.

Every figure is drawn from run folders (``trajectory.npz``, ``admm.npz``, ``summary.json``), never
from in-memory results, so the report shows what the runs wrote. Only the object-oriented
matplotlib API is used (no :mod:`matplotlib.pyplot`, no global figure registry).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from swarmpc.plots import animate, make_trajectory_figure
from swarmpc.simulation.rundata import RunData, load_run

if TYPE_CHECKING:
    from swarmpc.experiments.plan import ReproducePlan, RunRecord

PathLike = str | os.PathLike[str]

DPI = 110
FORM_COLORS = {"hard": "tab:blue", "soft": "tab:orange"}
FORM_MARKERS = {"hard": "o", "soft": "s"}
CENTRAL_MARKERS = {"hard": "x", "soft": "+"}  # thin markers: coinciding hard and soft both stay visible
GUESS_COLORS = {"straight": "tab:gray", "shifted": "tab:green", "rrt": "tab:red", "auto": "tab:purple"}

TRAJECTORY_2D = "fig-trajectories-2d.png"
TRAJECTORY_3D = "fig-trajectories-3d.png"
CONVERGENCE = "fig-convergence.png"
DELTA = "fig-delta.png"
GUESSES = "fig-guesses.png"


def _figure(width: float, height: float) -> Figure:
    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def save_png(fig: Figure, path: PathLike, dpi: int = DPI, palette: bool = False) -> Path:
    """Save a figure as PNG; ``palette`` re-encodes it with 256 colours (a much smaller file, as
    for the images under ``docs/img``)."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi, format="png")
    fig.clear()
    if palette:
        from PIL import Image

        with Image.open(out) as image:
            small = image.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT)
        small.save(out, optimize=True)
    return out


# ------------------------------------------------------------------------------ Fig. 3
def trajectory_figure(run: RunData, path: PathLike, dpi: int = DPI, palette: bool = False) -> Path:
    """Paths, start/goal markers and Δ boxes at five instants; 3D runs add top and side views."""
    return save_png(make_trajectory_figure(run, snapshots=5), path, dpi, palette)


# ------------------------------------------------------------------------------ Fig. 4
def busiest_steps(iterations: np.ndarray, count: int = 3) -> list[int]:
    """The ``count`` MPC steps with the most ADMM iterations (earliest first among ties), sorted."""
    order = np.argsort(-np.asarray(iterations, float), kind="stable")
    return sorted(int(k) for k in order[:count])


def convergence_figure(
    runs: Sequence[tuple[str, RunData]], path: PathLike, steps: int = 3, dpi: int = DPI, palette: bool = False
) -> Path:
    """Primal and dual residuals vs ADMM iteration (log scale) for the busiest MPC steps of each run,
    and the iterations of every MPC step (one row per run)."""
    rows = [(label, run) for label, run in runs if run.admm is not None and run.admm.primal.shape[0] > 0]
    if not rows:
        raise ValueError("convergence figure: no run with ADMM residuals")
    fig = _figure(12.0, 3.3 * len(rows))
    grid = fig.add_gridspec(len(rows), 3, width_ratios=[1.0, 1.0, 0.9])
    for r, (label, run) in enumerate(rows):
        admm = run.admm
        assert admm is not None
        chosen = busiest_steps(admm.iterations, steps)
        palette_rgba = colormaps["viridis"](np.linspace(0.0, 0.8, len(chosen)))
        tol = run.summary.get("admm_tol")
        ax_p = fig.add_subplot(grid[r, 0])
        ax_d = fig.add_subplot(grid[r, 1], sharey=ax_p)
        for ax, values, name in ((ax_p, admm.primal, "primal"), (ax_d, admm.dual, "dual")):
            for step, color in zip(chosen, palette_rgba, strict=True):
                row = np.where(values[step] > 0, values[step], np.nan)
                keep = np.isfinite(row)
                iters = np.arange(1, row.size + 1)
                ax.plot(iters[keep], row[keep], "-", marker=".", markersize=3, color=color,
                        label=f"MPC step {step} ({int(admm.iterations[step])} it.)")
            if tol is not None:
                ax.axhline(float(tol), color="k", linestyle="--", linewidth=1.0, label=f"tolerance {float(tol):g}")
            ax.set_yscale("log", nonpositive="mask")
            ax.set_xlabel("ADMM iteration")
            ax.set_ylabel(f"{name} residual")
            ax.set_title(f"{label}: {name} residual", fontsize=9)
            ax.grid(True, which="both", linewidth=0.4, alpha=0.4)
        ax_p.legend(fontsize=7)
        ax_it = fig.add_subplot(grid[r, 2])
        total = admm.iterations.size
        ax_it.bar(np.arange(total), admm.iterations, width=1.0, color="0.7")
        for step, color in zip(chosen, palette_rgba, strict=True):
            ax_it.bar([step], [admm.iterations[step]], width=1.0, color=color)
        ax_it.set_xlabel("MPC step")
        ax_it.set_ylabel("ADMM iterations")
        ax_it.set_title(f"{label}: iterations per MPC step", fontsize=9)
        ax_it.grid(True, axis="y", linewidth=0.4, alpha=0.4)
    fig.suptitle("ADMM convergence (paper Fig. 4): the three MPC steps with the most iterations", fontsize=10)
    return save_png(fig, path, dpi, palette)


# ------------------------------------------------------------------------------ Fig. 5
DELTA_METRICS: tuple[tuple[str, str], ...] = (
    ("cost", "closed-loop cost"),
    ("steps", "MPC steps to goal"),
    ("step_ms", "per-step compute time, median [ms]"),
    ("min_sep", r"min $\|p_i - p_j\|_\infty$ [m]"),
)


def delta_metric(summary: dict[str, Any], key: str) -> float:
    """One plotted quantity of a run, from its summary."""
    if key == "step_ms":
        return float(summary["step_time_ms"]["median"])
    if key == "min_sep":
        value = summary.get("min_separation_inf")
        return float("nan") if value is None else float(value)
    return float(summary[key])


def delta_figure(records: Sequence[RunRecord], path: PathLike, dpi: int = DPI, palette: bool = False) -> Path:
    """Cost, steps to goal, per-step time and min separation vs Δ: hard and soft on the same axes,
    ADMM solid, centralised dotted; one row per scenario. Hollow markers: not every agent reached."""
    cases = [r for r in records if r.spec.guess == "auto"]
    scenarios = sorted({r.spec.scenario for r in cases})
    if not scenarios:
        raise ValueError("delta figure: no runs")
    fig = _figure(14.0, 3.1 * len(scenarios) + 0.5)
    axes = fig.subplots(len(scenarios), len(DELTA_METRICS), squeeze=False)
    for row, scenario in enumerate(scenarios):
        for col, (key, label) in enumerate(DELTA_METRICS):
            ax = axes[row, col]
            for method, style, width in (("admm", "-", 1.8), ("centralized", ":", 1.2)):
                for form in FORM_COLORS:
                    runs = sorted((r for r in cases if r.spec.scenario == scenario and r.spec.method == method
                                   and r.spec.collision == form), key=lambda r: r.spec.delta)
                    if not runs:
                        continue
                    x = np.array([r.spec.delta for r in runs])
                    y = np.array([delta_metric(r.summary, key) for r in runs])
                    reached = np.array([bool(r.summary["all_reached"]) for r in runs])
                    color = FORM_COLORS[form]
                    ax.plot(x, y, style, color=color, linewidth=width, alpha=1.0 if method == "admm" else 0.7)
                    marker = FORM_MARKERS[form] if method == "admm" else CENTRAL_MARKERS[form]
                    ax.plot(x[reached], y[reached], marker, color=color, linestyle="", markersize=6)
                    ax.plot(x[~reached], y[~reached], marker, color=color, markerfacecolor="white",
                            linestyle="", markersize=6)
            if key == "min_sep":
                deltas = sorted({r.spec.delta for r in cases})
                ax.plot(deltas, deltas, "--", color="0.3", linewidth=1.0)
                ax.text(deltas[-1], deltas[-1], r" $=\Delta$", fontsize=8, va="top", ha="right", color="0.3")
            ax.set_xlabel("Δ [m]")
            ax.set_title(f"{scenario}: {label}", fontsize=9)
            ax.grid(True, linewidth=0.4, alpha=0.4)
            ax.set_xticks(sorted({r.spec.delta for r in cases}))
            ax.ticklabel_format(axis="y", useOffset=False)
    handles = [
        Line2D([], [], color=FORM_COLORS["hard"], marker="o", label="hard, ADMM"),
        Line2D([], [], color=FORM_COLORS["soft"], marker="s", label="soft, ADMM"),
        Line2D([], [], color=FORM_COLORS["hard"], linestyle=":", marker="x", label="hard, centralised"),
        Line2D([], [], color=FORM_COLORS["soft"], linestyle=":", marker="+", label="soft, centralised"),
        Line2D([], [], color="0.5", marker="o", markerfacecolor="white", linestyle="", label="not all reached"),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=8, frameon=False)
    fig.suptitle("Variation with Δ (paper Fig. 5)", fontsize=10)
    return save_png(fig, path, dpi, palette)


# ------------------------------------------------------------------------------ guesses
def guess_figure(records: Sequence[RunRecord], path: PathLike, dpi: int = DPI, palette: bool = False) -> Path:
    """Per-step time (median bar, p95 whisker) and mean ADMM iterations per initial-guess strategy."""
    scenarios = sorted({r.spec.scenario for r in records})
    guesses = [g for g in GUESS_COLORS if any(r.spec.guess == g for r in records)]
    if not scenarios or not guesses:
        raise ValueError("guess figure: no runs")
    fig = _figure(10.0, 3.4)
    ax_t, ax_i = fig.subplots(1, 2)
    width = 0.8 / len(guesses)
    x0 = np.arange(len(scenarios))
    for j, guess in enumerate(guesses):
        med, p95, its = [], [], []
        for scenario in scenarios:
            match = [r for r in records if r.spec.scenario == scenario and r.spec.guess == guess]
            s = match[0].summary if match else None
            med.append(np.nan if s is None else s["step_time_ms"]["median"])
            p95.append(np.nan if s is None else s["step_time_ms"]["p95"])
            iterations = None if s is None else s.get("admm_iterations")
            its.append(np.nan if not iterations else iterations["mean"])
        x = x0 - 0.4 + width * (j + 0.5)
        med_a, p95_a = np.array(med, float), np.array(p95, float)
        ax_t.bar(x, med_a, width, color=GUESS_COLORS[guess], label=guess)
        ax_t.errorbar(x, med_a, yerr=[np.zeros_like(med_a), np.maximum(p95_a - med_a, 0)], fmt="none",
                      ecolor="k", capsize=3, linewidth=0.8)
        ax_i.bar(x, its, width, color=GUESS_COLORS[guess], label=guess)
    ax_t.set_yscale("log")
    ax_t.set_ylabel("per-step time [ms]\n(bar: median, whisker: p95)")
    ax_i.set_ylabel("ADMM iterations per MPC step (mean)")
    for ax in (ax_t, ax_i):
        ax.set_xticks(x0, scenarios)
        ax.grid(True, axis="y", which="both", linewidth=0.4, alpha=0.4)
    ax_t.legend(fontsize=8, title="initial guess", title_fontsize=8)
    fig.suptitle("Initial-guess study (ADMM, hard, Δ = 0.3)", fontsize=10)
    return save_png(fig, path, dpi, palette)


# ------------------------------------------------------------------------------ all
def write_figures(
    out: Path,
    plan: ReproducePlan,
    records: Sequence[RunRecord],
    animations: bool = True,
    dest: Path | None = None,
    prefix: str = "",
    dpi: int = DPI,
    palette: bool = False,
) -> dict[str, str]:
    """Write every figure of the report into ``dest`` (default ``out``); returns {key: file name}.

    ``prefix``, ``dpi`` and ``palette`` serve the committed documentation copies
    (``docs/img/repro-*.png``, small palette PNGs).
    """
    target = dest or out
    by_name = {r.spec.name: r for r in records}
    written: dict[str, str] = {}
    representatives: list[tuple[str, RunData]] = []
    for scenario, _deltas in plan.deltas:
        spec = plan.representative(scenario)
        record = by_name.get(spec.name)
        if record is None:
            continue
        run = load_run(out / record.folder)
        label = f"{scenario}, Δ = {spec.delta:g}, hard"
        representatives.append((label, run))
        key = "trajectories_3d" if run.dim == 3 else "trajectories_2d"
        name = prefix + (TRAJECTORY_3D if run.dim == 3 else TRAJECTORY_2D)
        written[key] = trajectory_figure(run, target / name, dpi, palette).name
        if animations:
            gif = target / f"{prefix}anim-{scenario}.gif"
            written[f"animation_{scenario}"] = animate(run, gif, fmt="gif", max_frames=plan.animation_frames).name
    if representatives:
        written["convergence"] = convergence_figure(representatives, target / (prefix + CONVERGENCE), 3, dpi,
                                                    palette).name
    main = [r for r in records if r.spec.guess == "auto"]
    if main:
        written["delta"] = delta_figure(main, target / (prefix + DELTA), dpi, palette).name
    guess_runs = [r for r in records if r.spec in set(plan.guess_specs())]
    if guess_runs:
        written["guesses"] = guess_figure(guess_runs, target / (prefix + GUESSES), dpi, palette).name
    return written
