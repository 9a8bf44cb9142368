"""Figures of the tutorial and the concepts page, drawn by the docs build (matplotlib).

``draw_all(directory)`` writes ``scene_2d.svg`` (the tutorial's block on the slab),
``barrier.svg`` (the IPC barrier and its force over the contact distance dhat) and
``data_flow.svg`` (how a script's pieces feed the forward run, the adjoint and the optimiser).
"""

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch, Rectangle

__all__ = ["draw_all"]

_SVG = {"format": "svg", "metadata": {"Date": None}}  # the same file for the same figure


def scene_2d(path: Path) -> None:
    """The tutorial's scene: a block on a clamped slab, its initial velocity, the target."""
    fig = Figure(figsize=(6.4, 2.4), layout="constrained")
    ax = fig.subplots()
    ax.add_patch(Rectangle((0.0, 0.0), 1.5, 0.1, fc="0.8", ec="k"))
    ax.add_patch(Rectangle((0.1, 0.1005), 0.3, 0.15, fc="#8fb8de", ec="k"))
    ax.text(0.9, 0.05, "slab (stiff, E = 1e6)", ha="center", va="center", fontsize=9)
    ax.text(0.25, 0.13, "block (E = 2e4)", ha="center", va="center", fontsize=8)
    ax.plot([0.0, 1.5], [0.0, 0.0], "k", lw=4, solid_capstyle="butt")
    ax.annotate("clamped", (1.2, -0.005), (1.2, -0.08), ha="center", fontsize=9)
    ax.annotate(
        "", (0.55, 0.175), (0.25, 0.175), arrowprops={"arrowstyle": "->", "lw": 2, "color": "C3"}
    )
    ax.text(0.6, 0.19, "v0 = q (the control)", color="C3", ha="left", fontsize=9)
    ax.axvline(0.5, color="C2", ls="--", lw=1)
    ax.text(0.52, 0.28, "target: centre of mass stops at x = 0.5", color="C2", fontsize=9)
    ax.annotate("", (1.35, 0.13), (1.35, 0.26), arrowprops={"arrowstyle": "->", "lw": 1.5})
    ax.text(1.38, 0.2, "g", fontsize=10)
    ax.set_xlim(-0.05, 1.55)
    ax.set_ylim(-0.1, 0.33)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    fig.savefig(path, **_SVG)


def barrier(path: Path) -> None:
    """b(d) = -(d - dhat)^2 ln(d / dhat) for d < dhat (0 beyond) and the force -b'(d)."""
    dhat = 1.0
    d = np.linspace(0.02, 1.3, 400) * dhat
    inside = d < dhat
    b = np.where(inside, -((d - dhat) ** 2) * np.log(np.where(inside, d, dhat) / dhat), 0.0)
    force = np.where(
        inside, (dhat - d) * (2 * np.log(np.where(inside, d, dhat) / dhat) - dhat / d + 1), 0.0
    )
    fig = Figure(figsize=(6.4, 2.8), layout="constrained")
    ax_b, ax_f = fig.subplots(1, 2)
    ax_b.plot(d / dhat, b, "C0")
    ax_b.set_ylim(0, 1.5)
    ax_b.set_title("barrier b(d)", fontsize=10)
    ax_f.plot(d / dhat, -force, "C3")
    ax_f.set_ylim(0, 20)
    ax_f.set_title("repulsion -b'(d)", fontsize=10)
    for ax in (ax_b, ax_f):
        ax.axvline(1.0, color="0.5", ls="--", lw=1)
        ax.text(1.02, ax.get_ylim()[1] * 0.85, "dhat", color="0.4", fontsize=9)
        ax.set_xlabel("distance d / dhat")
        ax.grid(color="0.92")
    fig.savefig(path, **_SVG)


def data_flow(path: Path) -> None:
    """A script's pieces and what flows between them in a forward run, a gradient, a step."""
    boxes = {
        "mesh": (0.0, 3.0, "Domain\n(mesh, tags)"),
        "model": (2.2, 3.0, "Model\nUFL terms, loads,\nDirichlet, ContactTerm"),
        "sim": (4.6, 3.0, "Simulation\nNewton per step\n(BDF or Static)"),
        "traj": (7.0, 3.0, "Trajectory\nu^i, v^i"),
        "controls": (2.2, 1.2, "Controls\nq -> model"),
        "objective": (7.0, 1.2, "Objective\nJ(u, v, q)"),
        "rf": (4.6, 1.2, "ReducedFunctional\nJ(q), dJ/dq"),
        "sweep": (4.6, -0.5, "BackwardSweep\nadjoint steps N..1"),
        "opt": (2.2, -0.5, "minimize\n(L-BFGS)"),
    }
    arrows = [
        ("mesh", "model"),
        ("model", "sim"),
        ("sim", "traj"),
        ("traj", "objective"),
        ("controls", "model"),
        ("objective", "rf"),
        ("rf", "sweep"),
        ("sweep", "rf"),
        ("rf", "opt"),
        ("opt", "controls"),
        ("rf", "sim"),
    ]
    fig = Figure(figsize=(7.4, 3.6), layout="constrained")
    ax = fig.subplots()
    w, h = 1.7, 0.95
    for x, y, text in boxes.values():
        ax.add_patch(
            FancyBboxPatch((x, y), w, h, boxstyle="round,pad=0.05", fc="#eef3f8", ec="0.3")
        )
        ax.text(x + w / 2, y + h / 2, text, ha="center", va="center", fontsize=8)
    for a, b in arrows:
        (xa, ya, _), (xb, yb, _) = boxes[a], boxes[b]
        ca, cb = np.array([xa + w / 2, ya + h / 2]), np.array([xb + w / 2, yb + h / 2])
        d = cb - ca
        # from the edge of one box to the edge of the other, along the line between centres
        t = min(w / 2 / abs(d[0]) if d[0] else np.inf, h / 2 / abs(d[1]) if d[1] else np.inf)
        side = 0.1 * np.array([-d[1], d[0]]) / np.linalg.norm(d)  # two-way pairs side by side
        ax.add_patch(
            FancyArrowPatch(
                ca + t * d + side,
                cb - t * d + side,
                arrowstyle="-|>",
                mutation_scale=10,
                shrinkA=3,
                shrinkB=3,
                color="0.35",
            )
        )
    ax.set_xlim(-0.2, 8.9)
    ax.set_ylim(-0.7, 4.1)
    ax.axis("off")
    fig.savefig(path, **_SVG)


def draw_all(directory: Path) -> None:
    """Write the three figures into ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    scene_2d(directory / "scene_2d.svg")
    barrier(directory / "barrier.svg")
    data_flow(directory / "data_flow.svg")
