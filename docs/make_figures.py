"""Make the figures of docs/concepts.md: ``python docs/make_figures.py`` (about a minute).

* ``img/concept-problem.png``: a real run, ``swarmpc run paper-2d --method centralized``;
* ``img/concept-obca.png``: the OBCA certificate of a point against an agent's box, outside and inside;
* ``img/concept-admm.png``: the residual histories of a real ADMM run,
  ``swarmpc run paper-2d --max-steps 60`` (``admm.npz``).
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import FancyBboxPatch, Rectangle  # noqa: E402

from swarmpc.model.geometry import box_certificate, point_box_distance  # noqa: E402
from swarmpc.plots import load_run, make_trajectory_figure  # noqa: E402

IMG = Path(__file__).resolve().parent / "img"
DPI = 90


def swarmpc_run(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "swarmpc", "run", *args, "--quiet"], check=True)


def save(fig: Figure, name: str) -> Path:
    path = IMG / name
    fig.savefig(path, dpi=DPI, bbox_inches="tight", pad_inches=0.05)
    size = path.stat().st_size
    print(f"{path} ({size / 1024:.0f} kB)")
    if size > 150_000:
        raise SystemExit(f"{path} is {size} bytes, keep figures under 150 kB")
    return path


def problem_figure(tmp: Path) -> Path:
    out = tmp / "problem"
    swarmpc_run("paper-2d", "--method", "centralized", "--out", str(out))
    fig = make_trajectory_figure(load_run(out))
    fig.set_size_inches(7.5, 5.0)
    return save(fig, "concept-problem.png")


def obca_figure() -> Path:
    delta, d_min = np.array([0.3, 0.3]), 0.05
    fig = Figure(figsize=(6.4, 4.6), layout="constrained")
    ax = fig.add_subplot()
    ax.add_patch(Rectangle(tuple(-delta), *(2 * delta), facecolor="0.8", edgecolor="0.3",
                           label=r"agent $j$'s box $\pm\Delta$"))
    # the set the hard form keeps out of: the box grown by d_min (a rounded square)
    ax.add_patch(FancyBboxPatch(tuple(-delta), *(2 * delta), boxstyle=f"round,pad={d_min}", fill=False,
                                edgecolor="0.3", linestyle="--", label=r"box grown by $d_{min}$"))
    ax.plot(0, 0, "k+", markersize=8)
    ax.annotate(r"$p_j$", (0, 0), xytext=(0.03, -0.07), fontsize=10)

    outside = np.array([0.75, 0.55])
    dist = point_box_distance(outside, delta)
    lam = box_certificate(outside, delta)
    direction = lam[:2] - lam[2:]  # G^T lambda, a unit vector
    nearest = np.clip(outside, -delta, delta)
    ax.plot(*outside, "o", color="tab:blue", markersize=8, zorder=5)
    ax.annotate("", outside, nearest, arrowprops=dict(arrowstyle="<->", color="tab:blue"))
    ax.text(outside[0] + 0.05, outside[1] - 0.02,
            f"$p_i$ outside\ndistance {dist:.2f}\n" + r"$\max_\lambda (Gq-g)^T\lambda$" + f" = {dist:.2f}",
            color="tab:blue", fontsize=9, va="top")
    ax.annotate("", nearest + 0.25 * direction, nearest,
                arrowprops=dict(arrowstyle="-|>", color="tab:green", lw=1.8))
    ax.text(*(nearest + 0.27 * direction + np.array([-0.15, 0.03])), r"$G^T\lambda$ (unit)",
            color="tab:green", fontsize=9)

    inside = np.array([-0.12, 0.18])
    depth = -point_box_distance(inside, delta)
    lam_in = box_certificate(inside, delta)
    exit_dir = lam_in[:2] - lam_in[2:]
    exit_point = inside + depth * exit_dir
    ax.plot(*inside, "o", color="tab:red", markersize=8, zorder=5)
    ax.annotate("", exit_point, inside, arrowprops=dict(arrowstyle="->", color="tab:red"))
    ax.text(-1.05, -0.45,
            f"$p_i$ inside: penetration {depth:.2f}\n"
            r"hard form: infeasible" "\n"
            r"soft form: $\alpha \geq d_{min}$ + " f"{depth:.2f}, cost " r"$\kappa\alpha$",
            color="tab:red", fontsize=9, va="top")
    ax.annotate("", inside, (-0.55, -0.45), arrowprops=dict(arrowstyle="-", color="tab:red", lw=0.6))

    ax.set_xlim(-1.1, 1.5)
    ax.set_ylim(-0.95, 0.95)
    ax.set_aspect("equal")
    ax.set_xlabel(r"$q_x = (p_i - p_j)_x$ [m]")
    ax.set_ylabel(r"$q_y$ [m]")
    ax.grid(True, linewidth=0.4, alpha=0.4)
    ax.legend(loc="upper left", fontsize=8, frameon=False)
    ax.set_title(r"OBCA certificate of $q = p_i - p_j$ against $j$'s box "
                 rf"($\Delta$ = {delta[0]}, $d_{{min}}$ = {d_min})", fontsize=9)
    return save(fig, "concept-obca.png")


def admm_figure(tmp: Path) -> Path:
    out = tmp / "admm"
    swarmpc_run("paper-2d", "--max-steps", "60", "--out", str(out))
    with np.load(out / "admm.npz") as data:
        primal, dual, iterations = data["primal"], data["dual"], data["iterations"]
    tol = load_run(out).summary.get("admm_tol", 1e-3)
    fig = Figure(figsize=(9.0, 3.6), layout="constrained")
    ax_r, ax_i = fig.subplots(1, 2, width_ratios=[1.4, 1.0])
    coupled = np.flatnonzero(iterations > 1)
    # a quick step, a typical coupled one and the slowest
    picks = [0]
    if len(coupled):
        picks = sorted({int(coupled[0]), int(coupled[len(coupled) // 2]), int(np.argmax(iterations))})
    colors = ["tab:blue", "tab:orange", "tab:purple"]  # one per pick; picks may be fewer (repeated steps merge)
    for step, color in zip(picks, colors, strict=False):
        n = int(iterations[step])
        its = np.arange(1, n + 1)
        ax_r.semilogy(its, primal[step, :n], "-", color=color)
        ax_r.semilogy(its, dual[step, :n], "--", color=color)
    ax_r.axhline(tol, color="k", linewidth=0.8, linestyle=":")
    ax_r.set_xlabel("ADMM iteration")
    ax_r.set_ylabel("RMS residual [m]")
    ax_r.grid(True, which="both", linewidth=0.4, alpha=0.4)
    handles = [Line2D([], [], color=c, label=f"MPC step {s} ({int(iterations[s])} it.)")
               for s, c in zip(picks, colors, strict=False)]
    handles += [Line2D([], [], color="k", label=r"primal $\|v - z\|$"),
                Line2D([], [], color="k", linestyle="--", label=r"dual $\rho\|z - z_{prev}\|$"),
                Line2D([], [], color="k", linestyle=":", label=f"tol {tol:g}")]
    ax_r.legend(handles=handles, fontsize=7, ncol=3, frameon=False, loc="lower left", bbox_to_anchor=(0.0, 1.0))
    ax_i.bar(np.arange(len(iterations)), iterations, width=1.0, color="0.6")
    for step, color in zip(picks, colors, strict=False):
        ax_i.bar([step], [iterations[step]], width=1.0, color=color)
    ax_i.set_xlabel("MPC step")
    ax_i.set_ylabel("ADMM iterations")
    ax_i.set_title("iterations per MPC step (1 = no coupled pair)", fontsize=9)
    ax_i.grid(True, axis="y", linewidth=0.4, alpha=0.4)
    return save(fig, "concept-admm.png")


def main() -> None:
    IMG.mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        problem_figure(Path(tmp))
        obca_figure()
        admm_figure(Path(tmp))


if __name__ == "__main__":
    main()
