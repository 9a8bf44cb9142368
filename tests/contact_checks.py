"""Scenes and checks shared by the contact tests: stacked boxes, a box falling on a box, a crate
on an incline, every Newton iterate watched for intersections, central differences that record
the contact pairs of each run."""

from collections.abc import Callable
from typing import NamedTuple

import ipctk
import numpy as np

import diffsolids as ds
from diffsolids.contact import ContactTerm
from diffsolids.mesh.scene import combine_meshes, simplex_box

__all__ = [
    "CentralDifference",
    "IntersectionMonitor",
    "box_falling_on_box",
    "central_differences",
    "crate_on_incline",
    "stacked_boxes",
    "turn_about_vertical",
]


def turn_about_vertical(mesh, degrees: float, shift=(0.0, 0.0)) -> None:
    """Turns a 3D mesh in place about the vertical through (0.5, 0.5), then shifts it in x, y."""
    th = np.deg2rad(degrees)
    rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    xy = mesh.geometry.x[:, :2] - 0.5
    mesh.geometry.x[:, :2] = xy @ rot.T + 0.5 + np.asarray(shift)


def stacked_boxes(dim: int, gap: float, upper_cells_2d: list[int]) -> tuple:
    """A lower box [0, 1]^(dim - 1) x [0, 0.3] and an upper box 0.3 high, ``gap`` above it.

    2D: the upper box spans [0.3137, 0.7137] (``upper_cells_2d`` cells), off the lower box's
    vertices. 3D: it spans [0.25, 0.75]^2, turned by 1 degree and shifted by (0.0137, 0.0291),
    so that its bottom edges are near-parallel to the top edges of the lower box (mollified
    edge-edge pairs active). Returns the two meshes (to combine).
    """
    if dim == 2:
        lower = simplex_box([[0, 0], [1, 0.3]], [4, 2])
        upper = simplex_box([[0.3137, 0.3 + gap], [0.7137, 0.6 + gap]], upper_cells_2d)
    else:
        lower = simplex_box([[0, 0, 0], [1, 1, 0.3]], [2, 2, 1])
        upper = simplex_box([[0.25, 0.25, 0.3 + gap], [0.75, 0.75, 0.6 + gap]], [2, 2, 1])
        turn_about_vertical(upper, 1.0, shift=(0.0137, 0.0291))
    return lower, upper


def box_falling_on_box(
    comm,
    dhat: float,
    lower_cells: list[int],
    upper_cells: list[int],
    stiffness: float,
    velocity: list[float],
    degrees: float = 0.0,
) -> tuple[ds.Model, ContactTerm, np.ndarray]:
    """A free box thrown with ``velocity`` onto a box [0, 1]^2 x [0, 0.25] clamped at its bottom.

    The free box is [0.25, 0.75]^2 x [0.25, 0.5] lifted by dhat / 2 and turned by ``degrees``
    about the vertical; both Neo-Hookean (E 1e6, nu 0.3, density 1000) under gravity, friction
    0.3 (eps_v 1e-3). Returns the model, its contact term and the initial velocity (dofs).
    """
    lower = simplex_box([[0, 0, 0], [1, 1, 0.25]], lower_cells)
    upper = simplex_box(
        [[0.25, 0.25, 0.25 + 0.5 * dhat], [0.75, 0.75, 0.5 + 0.5 * dhat]], upper_cells
    )
    if degrees:
        turn_about_vertical(upper, degrees)
    dom = combine_meshes(comm, [lower, upper])
    model = ds.Model(dom, ds.NeoHookean(E=1e6, nu=0.3, density=1000.0))
    model.add_gravity(9.81)
    model.add_dirichlet(lambda x: x[2] < 1e-9, 0.0)
    contact = ContactTerm(model, dhat=dhat, stiffness=stiffness, friction=0.3, eps_v=1e-3)
    model.add_numeric_term(contact)
    X = model.V.tabulate_dof_coordinates()
    v0 = np.zeros((len(X), 3))
    v0[X[:, 2] > 0.25 + 1e-9] = velocity
    return model, contact, v0.ravel()


def crate_on_incline(
    comm, dhat: float, crate_cells: list[int], lid_cells: list[int], steps: int
) -> tuple[ds.Model, ContactTerm, ds.Simulation]:
    """A clamped slab under 30-degree gravity, a crate sliding on it and a lid on the crate.

    Friction 0.3 between slab and crate, 0.5 between crate and lid; kappa 1e13; BDF2, dt 0.01.
    """
    theta = np.deg2rad(30.0)
    slab = simplex_box([[0, 0], [2, 0.1]], [16, 1])
    crate = simplex_box([[0.2, 0.1 + 0.5 * dhat], [0.4, 0.2 + 0.5 * dhat]], crate_cells)
    lid = simplex_box([[0.25, 0.2 + 1.2 * dhat], [0.35, 0.25 + 1.2 * dhat]], lid_cells)
    dom = combine_meshes(comm, [slab, crate, lid])
    model = ds.Model(dom, ds.NeoHookean(E=1e7, nu=0.3, density=1000.0))
    model.add_body_force(9.81 * np.array([np.sin(theta), -np.cos(theta)]), name="gravity")
    model.add_dirichlet(lambda x: x[1] < 0.1 + 1e-9, 0.0)
    contact = ContactTerm(
        model, dhat=dhat, stiffness=1e13, friction={(1, 2): 0.3, (2, 3): 0.5}, eps_v=1e-3
    )
    model.add_numeric_term(contact)
    sim = ds.Simulation(model, ds.BDF(2, 0.01, steps), ds.SolverOptions(rtol=1e-10), progress=False)
    return model, contact, sim


class IntersectionMonitor:
    """Checks every Newton iterate of the solver (SNES monitor) for intersections.

    Attributes:
        checked: How many iterates were checked.
        bad: The Newton iteration numbers at which the surface intersected itself.
    """

    def __init__(self, sim: ds.Simulation, contact: ContactTerm) -> None:
        self.surface = contact.surface
        self.checked = 0
        self.bad: list[int] = []
        sim.solver.snes.setMonitor(self)

    def __call__(self, snes: object, it: int, fnorm: float) -> None:
        s = self.surface
        x = s.rest_positions + s.gather(snes.getSolution().array_r)
        self.checked += 1
        if ipctk.has_intersections(s.mesh, np.asfortranarray(x)):
            self.bad.append(it)


class CentralDifference(NamedTuple):
    """A central difference of J at q along a unit direction, against the adjoint's g . dq."""

    direction: str  # "random" or "gradient"
    h: float
    adjoint: float
    fd: float
    error: float  # |fd - adjoint| / |adjoint|
    pairs: tuple[list[int], list[int]]  # collisions per step of the runs at q + h dq, q - h dq


def central_differences(
    rf,
    q: np.ndarray,
    g: np.ndarray,
    contact: ContactTerm,
    steps,
    seed: int,
    before_run: Callable[[], None] | None = None,
) -> tuple[list[CentralDifference], str]:
    """Central differences of ``rf`` at q along a random and the gradient's unit direction.

    Args:
        rf: The reduced functional; its last run (the base run) was at q.
        q: The parameters.
        g: The adjoint gradient at q.
        contact: The contact term whose collision counts per step each run records.
        steps: The steps h.
        seed: Seed of the random direction.
        before_run: Called before each perturbed run (e.g. to set a warm start).

    Returns:
        One :class:`CentralDifference` per direction and step, and a report (one line each,
        with the base run's pairs per step) for assertion messages.
    """
    base = [r.num_collisions for r in contact.records]
    d = np.random.default_rng(seed).normal(size=q.size)
    rows = []
    for name, dq in (("random", d / np.linalg.norm(d)), ("gradient", g / np.linalg.norm(g))):
        adjoint = float(g @ dq)
        for h in steps:
            values, pairs = [], []
            for sign in (1.0, -1.0):
                if before_run is not None:
                    before_run()
                values.append(rf(q + sign * h * dq))
                pairs.append([r.num_collisions for r in contact.records])
            fd = (values[0] - values[1]) / (2 * h)
            error = abs(fd - adjoint) / abs(adjoint)
            rows.append(CentralDifference(name, h, adjoint, fd, error, tuple(pairs)))
    report = "\n".join(
        f"{r.direction} h={r.h:g}: adjoint {r.adjoint:.12e} central differences {r.fd:.12e} "
        f"rel. error {r.error:.2e} (pairs per step {base}, +h {r.pairs[0]}, -h {r.pairs[1]})"
        for r in rows
    )
    return rows, report
