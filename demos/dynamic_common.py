"""Helpers of the transient contact demos (throw, sliding friction, puzzle, shock protection).

The nodes of a body, the output of the runs, and the closing figures and summary line every
run prints.
"""

import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from diffsolids.io import write_trajectory

__all__ = [
    "body_nodes",
    "finish_transient",
    "scene_figure",
    "write_runs",
]


def body_nodes(model, body) -> np.ndarray:
    """Local nodes (block indices of the displacement space) of the cells of a body."""
    return np.unique(model.V.dofmap.list[model.domain.cells_of(body)])


def write_runs(model, runs: Mapping[str, object], args, prefix: str) -> list[Path]:
    """Write each labelled trajectory to ``<out>/<prefix>_<label>.bp`` (``.xdmf``); the paths."""
    suffix = ".xdmf" if args.xdmf else ".bp"
    paths = [args.out / f"{prefix}_{label}{suffix}" for label in runs]
    for path, traj in zip(paths, runs.values(), strict=True):
        write_trajectory(model, traj, path)
    return paths


def scene_figure(height: float, heights: tuple, widths: tuple | None, plots: int):
    """The transient demos' figure: the scene across the top, ``plots`` panels below it.

    Returns:
        (figure, the scene's axes, the list of the lower axes).
    """
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(11, height))
    grid = fig.add_gridspec(2, plots, height_ratios=list(heights), width_ratios=widths)
    scene = fig.add_subplot(grid[0, :])
    return fig, scene, [fig.add_subplot(grid[1, k]) for k in range(plots)]


def finish_transient(
    run, report, model, result, files: list, figures: dict, headline: str, plot=None
):
    """Draw a transient demo's figure, write ``result.json`` and print its summary line.

    Args:
        run: The DemoRun (arguments ``steps``, ``dt``, ``out``; communicator; clocks).
        report: The DemoReport.
        model: The Model (its dof count).
        result: The OptimizationResult.
        files: Files the run wrote (the figure is added).
        figures: The demo's own figures for ``report.extra``.
        headline: The demo's part of the summary line (the run's size and cost follow).
        plot: ``plot(path)`` drawing the figure ``<out>/<demo>.png`` (skipped with
            ``--no-plot``).
    """
    args, comm = run.args, run.comm
    if plot is not None and not args.no_plot:
        path = args.out / f"{args.demo}.png"
        plot(path)
        files.append(path)
    cpu = run.cpu_seconds()
    dofs = model.V.dofmap.index_map.size_global * model.dim
    report.extra.update(
        {"dofs": dofs, "ranks": comm.size, "steps": args.steps, "dt": args.dt, **figures}
    )
    report.extra.update(
        {
            "forward_solves": result.num_forward,
            "cpu_seconds_all_ranks": cpu,
            "files": [str(f) for f in files],
        }
    )
    report.wall_seconds = time.perf_counter() - run.t0
    run.finish(report)
    if comm.rank == 0:
        print(
            f"{headline}; {dofs} dofs, {args.steps} steps, {result.num_forward} forward solves; "
            f"CPU {cpu:.1f} s (all ranks)",
            flush=True,
        )
    return report
