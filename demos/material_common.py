"""Helpers of the material optimisation demos: invariants, labelled state output, field plots.

Shared by ``sine_bar``, ``bridge_material``, ``bouncing_ball_height`` and ``kangaroo_material``:
the invariants every run reports (objective decreased, no inverted element in any deformed
state, no intersection in contact scenes), writing the labelled states (with the material
fields) and the closing output, and cellwise material values for the figures.
"""

import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from dolfinx import fem

from diffsolids.io import write_trajectory

__all__ = [
    "body_cell_mask",
    "cell_values",
    "check_recovered",
    "finish_material",
    "write_states",
]


def check_recovered(report, start: dict, found: dict, true: dict, max_error: float) -> None:
    """Record the identification outcomes: each parameter within ``max_error`` of the truth.

    Args:
        report: The DemoReport.
        start: Initial value per parameter name.
        found: Recovered value per parameter name.
        true: True value per parameter name (the outcome is named after the key, "lmbda" as
            "lambda").
        max_error: Largest admissible relative error.
    """
    for name, value in true.items():
        error = abs(found[name] / value - 1.0)
        report.check(
            f"{'lambda' if name == 'lmbda' else name} relative error",
            error,
            max_error,
            error <= max_error,
            f"{start[name]:g} -> {found[name]:.6g} (truth {value:g})",
        )


def cell_values(model, name: str) -> np.ndarray:
    """Owned values of a scalar DG0 coefficient, in local cell order."""
    fn = model.coefficients[name]
    owned = model.domain.mesh.topology.index_map(model.dim).size_local
    cells = np.arange(owned, dtype=np.int32)
    return fn.x.array[fn.function_space.dofmap.list[cells, 0]]


def write_states(
    model,
    controls,
    states: dict,
    out: Path,
    name: str,
    xdmf: bool,
    fields: list[str],
) -> list[Path]:
    """Write each labelled state ``{label: (q, trajectory)}`` as a time series with its fields.

    The controls are assigned the state's parameters while writing (the material fields in
    ``fields`` are written as extra cellwise functions); the last state's parameters stay set.
    """
    suffix = ".xdmf" if xdmf else ".bp"
    extra = [model.coefficients[f] for f in fields]
    paths = []
    for label, (q, traj) in states.items():
        controls.assign(q)
        path = out / f"{name}_{label}{suffix}"
        write_trajectory(model, traj, path, extra=extra)
        paths.append(path)
    return paths


def finish_material(
    run,
    report,
    rf,
    result,
    states: dict,
    fields: list[str],
    plot: Callable[[Path], None] | None = None,
):
    """Write the labelled states, the figure and ``result.json``; print the summary.

    Args:
        run: The DemoRun (arguments ``out``, ``xdmf``, ``no_plot``; communicator; clocks).
        report: The DemoReport (its ``demo`` names the files).
        rf: The ReducedFunctional (its controls are left at the optimum).
        result: The OptimizationResult.
        states: ``{label: (q, trajectory)}`` to write.
        fields: Names of the material fields written with the states.
        plot: ``plot(path)`` drawing the demo's figure (skipped with ``--no-plot``).
    """
    args = run.args
    paths = write_states(rf.model, rf.controls, states, args.out, report.demo, args.xdmf, fields)
    rf.controls.assign(result.q)
    if plot is not None and not args.no_plot:
        plot(args.out / f"{report.demo}.png")
    report.extra["files"] = [str(p) for p in paths]
    report.extra["cpu_seconds"] = run.cpu_seconds()
    report.wall_seconds = time.perf_counter() - run.t0
    return run.finish(report)


def body_cell_mask(model, layout, body) -> np.ndarray:
    """Canonical-order mask of the cells of ``body`` for a DG0 CanonicalLayout (all ranks)."""
    tags = model.domain.cell_tags
    marker = fem.Function(layout.V)
    marker.x.array[layout.V.dofmap.list[tags.indices, 0]] = tags.values
    return layout.gather(marker.x.array) == model.domain.body_id(body)
