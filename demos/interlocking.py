"""Static shape optimisation of two interlocking parts in contact (paper Fig. 8).

Two plates (``meshes/interlocking.geo``, after Tozoni et al. 2021) interlock through a dovetail:
the bottom plate is clamped on its underside, the top plate is held only by contact with it
and carries a uniform traction pointing down and to the right on its top side. The parts are
meshed with a gap of half the barrier distance between them; IPC contact (ContactTerm,
frictionless) acts between every pair of boundary primitives of the scene, no contact pairs
are declared. Neo-Hookean material, one static solve (Newton with collision-free line search)
per evaluation.

Objective (paper eqs. 30, 35, 37), normalised by its initial stress value:

    J = ||sigma_vM||_L8 / s0 + w_V phi(V - V0) / V0^2 + w_S * boundary smoothing

(the one-sided volume bound keeps the parts from simply growing). Controls: the boundary
vertices of both parts except the clamped and the loaded sides; the interior follows the
linear-elasticity extension (MeshMotion). The two faces of the interface move together: each
boundary vertex of the top part within 2.5 gaps of the bottom part follows the closest point
of the bottom part's boundary (linear interpolation along its edge), so the interlocking
surfaces change shape while the gap between them stays what it is in the mesh (the paper keeps
the contact surfaces of the two parts on top of each other in the same way). Without the tie
the optimiser moved the two faces towards each other until the rest shapes touched somewhere
and the contact term refused every further step (stopped after 12 iterations at a 1.3x stress
reduction). The Riesz map of the extension, applied through the tie, is the initial inverse
Hessian of L-BFGS; the interior is remeshed when the mesh quality drops. Trial shapes whose
rest configuration intersects (or touches) are refused by the contact term and by the boundary
check, so every accepted iterate is intersection-free; the Newton line search keeps every
deformed state intersection-free too.

Checked outcome (default and --full): the maximum cellwise von Mises stress falls by at least a
factor 2; in every run: the objective decreased, no accepted iterate has inverted cells or an
intersecting rest or deformed configuration (ipctk.has_intersections on every iterate).

Run ``python demos/interlocking.py`` (default size), ``--tiny`` (smoke test), ``--full``
(paper-like resolution), or ``mpiexec -n 2 python demos/interlocking.py``.
"""

import logging
import time

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from common import MESHES, DemoReport, demo_parser, finish, report_from, run_demo, size_name
from mpi4py import MPI
from shape_tools import (
    GuardedShapeControl,
    Invariants,
    facet_polygons_2d,
    max_von_mises,
    plot_shapes_2d,
    volume,
    write_state,
)

import diffsolids as ds
from diffsolids.contact import ContactTerm, suggest_barrier_stiffness
from diffsolids.io import configure_logging
from diffsolids.mesh import from_geo
from diffsolids.objectives import BoundarySmoothing, final_value, stress_lp_norm, volume_penalty
from diffsolids.optimize import LBFGSOptions, MeshMotion, Remesher, minimize
from diffsolids.parallel import collective_comm
from diffsolids.reduced_functional import ReducedFunctional

GEO = MESHES / "interlocking.geo"
GAP = 0.01  # between the parts, in the mesh
DHAT = 2 * GAP  # barrier activation distance
TRACTION = 2.0 * np.array([1.0, -1.0]) / np.sqrt(2.0)  # on the top side, down and to the right
E, NU = 1.0e3, 0.3
SIZES = {
    "tiny": {"h": 0.2, "iterations": 3, "max_change": 0.02},
    "default": {"h": 0.08, "iterations": 40, "max_change": 0.02},
    "full": {"h": 0.03, "iterations": 100, "max_change": 0.01},
}
WEIGHT_VOLUME = 1.0e3
WEIGHT_SMOOTHING = 5.0e-2
MIN_REDUCTION = 2.0  # checked: max von Mises before / after


def interface_tie(motion: MeshMotion, surface, max_distance: float):
    """Linear map T from reduced to full design parameters tying the top part to the bottom.

    Every design vertex of body 2 closer than ``max_distance`` to the boundary of body 1
    follows the closest point of body 1's boundary: its displacement interpolates the two
    vertices of the closest edge of body 1. All other design vertices are parameters.

    Returns:
        (T as a sparse matrix (num_design * dim, num_reduced * dim), number of tied vertices).
    """
    dim = motion.dim
    ids = surface.vertex_input_ids
    X = surface.rest_positions
    edges = surface.edges[surface.primitive_body == 1]
    top = np.flatnonzero(surface.body == 2)
    a, b = X[edges[:, 0]], X[edges[:, 1]]
    ab = b - a
    p = X[top][:, None, :]
    t = np.clip(np.sum((p - a) * ab, axis=2) / np.sum(ab * ab, axis=1), 0.0, 1.0)
    dist = np.linalg.norm(p - (a + t[..., None] * ab), axis=2)
    nearest = np.argmin(dist, axis=1)
    close = dist[np.arange(len(top)), nearest] < max_distance
    design = motion.design
    tied_ids = ids[top[close]]
    tied_ids = tied_ids[np.isin(tied_ids, design)]
    reduced = np.setdiff1d(design, tied_ids)
    rows, cols, vals = [], [], []
    slot_full = {v: k for k, v in enumerate(design)}
    slot_red = {v: k for k, v in enumerate(reduced)}
    for v in reduced:
        rows.append(slot_full[v])
        cols.append(slot_red[v])
        vals.append(1.0)
    for vertex, edge, s in zip(top[close], nearest[close], t[close, nearest[close]], strict=True):
        if ids[vertex] not in slot_full:
            continue
        for end, weight in ((0, 1.0 - s), (1, s)):
            v = ids[edges[edge, end]]
            if v in slot_red and weight > 0:  # fixed vertices of body 1 contribute nothing
                rows.append(slot_full[ids[vertex]])
                cols.append(slot_red[v])
                vals.append(weight)
    rows, cols, vals = (np.asarray(x) for x in (rows, cols, vals))
    comp = np.arange(dim)
    T = sp.csr_matrix(
        (
            np.repeat(vals, dim),
            (
                (rows[:, None] * dim + comp).ravel(),
                (cols[:, None] * dim + comp).ravel(),
            ),
        ),
        shape=(len(design) * dim, len(reduced) * dim),
    )
    return T, len(tied_ids)


class TiedInnerProduct:
    """Initial inverse Hessian of L-BFGS for the tied parameters: ``g -> T^T A^{-1} T g``.

    A^{-1} is the Riesz map of the mesh motion; the result is SPD when T has full column rank.
    After a remesh the optimiser calls :meth:`rebuild` with the new functional.
    """

    def __init__(self, problem: "Problem", rf):
        self.problem = problem
        motion, self.T = problem.parts[id(rf)]["motion"], problem.parts[id(rf)]["tie"]
        self.riesz = motion.riesz_map()

    def __call__(self, g: np.ndarray) -> np.ndarray:
        """The preconditioned gradient (collective)."""
        return self.T.T @ self.riesz(self.T @ g)

    def rebuild(self, rf) -> "TiedInnerProduct":
        """The same inner product for the functional of a new mesh."""
        return TiedInnerProduct(self.problem, rf)


class MinimumDistance:
    """Stop condition that never stops: the smallest contact distance of every accepted iterate."""

    def __init__(self):
        self.values: list[float] = []

    def __call__(self, record, optimizer) -> bool:
        """Record the minimum distance of the last step; returns False."""
        (contact,) = optimizer.rf.model.numeric_terms
        self.values.append(min(r.min_distance for r in contact.records))
        return False


class Problem:
    """Builds the scene on a mesh (also after remeshing) with fixed constants.

    The normalisation s0, the volume bound V0 and the barrier stiffness are fixed by the first
    mesh, so the objective is the same function on every mesh.
    """

    def __init__(self):
        self.s0: float | None = None
        self.V0: float | None = None
        self.kappa: float | None = None
        self.parts: dict[int, dict] = {}  # per functional: contact, motion, tie, tied vertices

    def __call__(self, domain) -> ReducedFunctional:
        """The reduced functional on a mesh."""
        model = ds.Model(domain, ds.NeoHookean(E=E, nu=NU), degree=1)
        model.add_dirichlet("fixed", 0.0)
        model.add_traction("load", TRACTION)
        integrator = ds.Static()
        if self.kappa is None:
            probe = ContactTerm(model, dhat=DHAT, stiffness=1.0)
            self.kappa = suggest_barrier_stiffness(probe, integrator)
        contact = ContactTerm(model, dhat=DHAT, stiffness=self.kappa)
        model.add_numeric_term(contact)
        sim = ds.Simulation(model, integrator, ds.SolverOptions(rtol=1e-9), progress=False)
        motion = MeshMotion(domain, exclude_facets=["fixed", "load"])
        T, tied = interface_tie(motion, contact.surface, 2.5 * GAP)
        tie = spla.aslinearoperator(T)
        control = GuardedShapeControl(model, linear_map=spla.aslinearoperator(motion) @ tie)
        control.name = "shape[tied mesh motion]"
        stress = final_value(stress_lp_norm(model, 8, "von_mises"))
        if self.s0 is None:
            self.V0 = volume(model)
            self.s0 = ReducedFunctional(sim, stress, control)(np.zeros(control.size))
        smooth = BoundarySmoothing(model, 2, exclude_facets=["fixed", "load"])
        J = (
            (1.0 / self.s0) * stress
            + (WEIGHT_VOLUME / self.V0**2) * volume_penalty(model, self.V0, "upper")
            + WEIGHT_SMOOTHING * smooth
        )
        rf = ReducedFunctional(sim, J, control)
        self.parts[id(rf)] = {"contact": contact, "motion": motion, "tie": T, "tied": tied}
        return rf


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    """Run the demo on ``comm``; returns the report (printed on rank 0)."""
    parser = demo_parser(__doc__.splitlines()[0], "interlocking")
    parser.add_argument("--h", type=float, help="mesh size")
    args = parser.parse_args(argv)
    size = size_name(args)
    setup = SIZES[size]
    h = args.h or setup["h"]
    iterations = args.iterations if args.iterations is not None else setup["iterations"]
    configure_logging(logging.INFO if args.verbose else logging.WARNING, comm)
    t0 = time.perf_counter()
    cpu0 = time.process_time()

    domain = from_geo(GEO, comm, numbers={"h": h, "G": GAP})
    problem = Problem()
    rf = problem(domain)
    V0 = problem.V0
    model = rf.model
    q0 = rf.initial_parameters()
    rf(q0)
    u0 = rf.trajectory.u[-1].copy()
    stress0 = max_von_mises(model, u0)
    suffix = ".xdmf" if args.xdmf else ".bp"
    files = write_state(model, args.out / f"initial{suffix}", u0)
    before = facet_polygons_2d(model)

    invariants = Invariants(deformed=True)
    distances = MinimumDistance()
    options = LBFGSOptions(
        max_iterations=iterations,
        gradient_rtol=1e-6,
        max_change=setup["max_change"],
        initial_step=setup["max_change"],
    )
    result = minimize(
        rf,
        q0,
        options,
        inner_product=TiedInnerProduct(problem, rf),
        remesher=Remesher(problem, threshold=0.1),
        stop_conditions=[invariants, distances],
        progress=False,
        output_dir=args.out,
        plot_every=0 if args.no_plot else max(iterations, 1),  # at the end only
    )
    rf = result.functional
    model = rf.model
    u1 = rf.trajectory.u[-1]
    stress1 = max_von_mises(model, u1)
    V1 = volume(model)
    files += write_state(model, args.out / f"final{suffix}", u1)
    after = facet_polygons_2d(model)

    report = report_from("interlocking", args, result, t0)
    reduction = stress0 / stress1
    report.extra = {
        "max_von_mises_initial": stress0,
        "max_von_mises_final": stress1,
        "reduction": reduction,
        "volume_initial": V0,
        "volume_final": V1,
        "min_contact_distance": min(distances.values),
        "barrier_distance": DHAT,
        "barrier_stiffness": problem.kappa,
        "remeshes": sum(r.remeshed for r in result.history),
        "invalid_trials": result.num_invalid_trials,
        "tied_vertices": problem.parts[id(rf)]["tied"],
        "parameters": rf.size,
        "vertices": domain.mesh.geometry.index_map().size_global,
        "newton_iterations": rf.trajectory.newton_iterations(),
        "ranks": comm.size,
        "cpu_seconds": collective_comm(comm).allreduce(time.process_time() - cpu0, op=MPI.SUM),
        "files": [str(f) for f in files],
    }
    report.check(
        "objective decreased",
        report.final_objective,
        report.initial_objective,
        report.final_objective < report.initial_objective,
    )
    report.check("iterates with inverted cells", invariants.inverted, 0, invariants.inverted == 0)
    report.check(
        "iterates with intersecting rest shapes",
        invariants.intersecting,
        0,
        invariants.intersecting == 0,
    )
    report.check(
        "iterates with intersecting deformed shapes",
        invariants.intersecting_deformed,
        0,
        invariants.intersecting_deformed == 0,
    )
    if size != "tiny":
        report.check(
            "max von Mises reduction",
            reduction,
            MIN_REDUCTION,
            reduction >= MIN_REDUCTION,
            f"({stress0:.4g} -> {stress1:.4g})",
        )
    if not args.no_plot:
        title = (
            f"max von Mises {stress0:.3g} -> {stress1:.3g} ({reduction:.2f}x), "
            f"min contact distance {min(distances.values):.2g}"
        )
        plot_shapes_2d(args.out / "interlocking.png", before, after, result, title, comm)
    return finish(report, args, comm)


if __name__ == "__main__":
    run_demo(main)
