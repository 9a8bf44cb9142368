"""Contact scenes whose J must be a smooth function of the parameters (bench_smoothness, tests).

Each builder returns a :class:`Scene`: the reduced functional, the centre q0 of its line scan,
the scan's radius and the contact term (its records give the pairs per step). All run with
the default :class:`~diffsolids.SolverOptions` and ``formulation="convergent"`` unless told.

- ``drop``: the 3D block of issue 38 dropped flat on a ground of 1, 2 or 4 coplanar
  triangles (the same 4 m square; with 2, the shared edge runs under the block's diagonal
  vertices; with 4, the middle vertex lies under a vertex of the block), E recovered from a
  target run (log E).
- ``drop_2d``: a 2D box dropped on a ground polyline of collinear segments, one joint under a
  corner of the box and one under an inner vertex; (log E, log mu) of its landing and slide.
- ``slide``: a 3D block thrown along a ground of 8 coplanar triangles (a 2 x 2 grid, every
  diagonal the same way), across their shared edges; (log mu, initial speed), its final
  position.
- ``ridge``: the drop's block landing on a roof ridge of two triangles (a genuine pair of
  local minima per landing step: it tips to one side or the other); (log E, log mu), with the
  branch reference of :class:`~diffsolids.ReducedFunctional` at q0.
- ``wavy``: a 2D box thrown along a wavy ground, the polyline through samples of
  y = -a cos(2 pi x / w) (``demos/puzzle_initial_velocity.py``'s ground): its vertices slide
  across the polyline's kinks; (v_x, log mu), its final position.
- ``roll``: a 2D disk thrown down a polyline slope with two kinks; it lands sliding and rolls
  (its contacts stick): (v_x, v_y, spin), the squared distance of its final centre from the
  origin.
- ``damping``: PolyFEM's damping-transient test (a disk thrown along a clamped slab), (log psi,
  log phi), with the suggested barrier or PolyFEM's (``damping_polyfem``).
"""

from typing import NamedTuple

import numpy as np
from mpi4py import MPI

import diffsolids as ds
from diffsolids.contact import ContactTerm, Obstacle
from diffsolids.controls import FrictionControl, RigidVelocity
from diffsolids.objectives import center_of_mass, final_value

__all__ = [
    "SCENES",
    "Scene",
    "damping",
    "damping_polyfem",
    "drop",
    "drop_2d",
    "ridge",
    "ridge_free",
    "roll",
    "slide",
    "wavy",
]


class Scene(NamedTuple):
    """A reduced functional with the line to scan."""

    rf: ds.ReducedFunctional
    q0: np.ndarray
    radius: float
    contact: ContactTerm

    def check_gradient(self, h: float, seed: int, rtol: float) -> tuple[float, np.ndarray]:
        """Assert central differences at step h within rtol of the gradient at q0, in a random
        direction and along the gradient; returns (J(q0), the random direction)."""
        J, g = self.rf.value_and_gradient(self.q0)
        d = np.random.default_rng(seed).standard_normal(len(g))
        d /= np.linalg.norm(d)
        for u in (d, g / np.linalg.norm(g)):
            fd = ds.finite_difference_check(self.rf, self.q0, u, [h], gradient=g)
            assert fd.relative_error <= rtol, str(fd)
        return J, d


def ground_3d(triangles: int, size: float = 4.0, centre=(0.1, 0.1)) -> Obstacle:
    """A flat square ground [-1.4, -1.4 + size]^2 at z = 0 of 1 (half of it), 2 or 4 triangles.

    One triangle: the half below the square's anti-diagonal (the same bounding box).
    """
    a, b = -1.4, -1.4 + size
    corners = np.array([[a, a, 0], [b, a, 0], [b, b, 0], [a, b, 0]], float)
    if triangles == 1:
        return Obstacle(corners[[0, 1, 3]], faces=np.array([[0, 1, 2]]), name="ground")
    if triangles == 2:
        return Obstacle(corners, faces=np.array([[0, 1, 2], [0, 2, 3]]), name="ground")
    if triangles == 4:
        V = np.vstack([corners, [centre[0], centre[1], 0.0]])
        F = np.array([[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
        return Obstacle(V, faces=F, name="ground")
    raise ValueError(f"ground of {triangles} triangles: 1, 2 or 4")


def drop(
    triangles: int = 2,
    comm: MPI.Comm = MPI.COMM_WORLD,
    steps: int = 25,
    formulation: str = "ipc",
) -> Scene:
    """The block of issue 38 dropped on a ground of ``triangles`` triangles (log E)."""
    block = ds.mesh.simplex_box([[0.0, 0.0, 0.01], [0.2, 0.2, 0.11]], [4, 4, 2])
    domain = ds.combine_meshes(comm, [block], names={"block": 1})
    model = ds.Model(domain, ds.NeoHookean(E=6e4, nu=0.3, density=500.0))
    model.add_gravity(9.81)
    contact = ContactTerm(
        model, dhat=1e-3, friction=0.2, obstacles=[ground_3d(triangles)], formulation=formulation
    )
    model.add_numeric_term(contact)
    sim = ds.Simulation(model, ds.BDF(2, 0.01, steps), ds.SolverOptions(), progress=False)
    control = ds.ParameterControl(model, "E", "uniform", log=True)
    control.assign(np.array([np.log(2e4)]))
    target = sim.run()
    misfit = ds.time_integral(ds.target_trajectory(sim, target, bodies="block"), "uniform")
    rf = ds.ReducedFunctional(sim, misfit / 1e-6, control)
    return Scene(rf, np.array([np.log(6e4) + 0.02]), 0.02, contact)


def drop_2d(
    comm: MPI.Comm = MPI.COMM_WORLD,
    steps: int = 30,
    formulation: str = "ipc",
    joints: tuple[float, ...] = (0.0, 0.1, 0.237),
) -> Scene:
    """A 2D box landing with a sideways speed on a ground of collinear segments (log E, log mu).

    Ground from x = -1 to 1.5 with joints at ``joints`` (by default under the box's left corner,
    under an inner vertex and at 0.237); the box [0, 0.2] x [0.005, 0.105] starts at
    (0.3, -0.2) m/s.
    """
    box = ds.mesh.simplex_box([[0.0, 0.005], [0.2, 0.105]], [4, 2])
    domain = ds.combine_meshes(comm, [box], names={"box": 1})
    model = ds.Model(domain, ds.NeoHookean(E=5e4, nu=0.3, density=500.0))
    model.add_gravity(9.81)
    xs = np.array([-1.0, *joints, 1.5])
    ground = Obstacle(np.column_stack([xs, np.zeros_like(xs)]), name="ground")
    contact = ContactTerm(
        model, dhat=1e-3, friction=0.3, obstacles=[ground], formulation=formulation
    )
    model.add_numeric_term(contact)
    X = model.V.tabulate_dof_coordinates()
    v0 = np.tile([0.3, -0.2], (len(X), 1)).ravel()
    integrator = ds.BDF(2, 0.01, steps)
    sim = ds.Simulation(model, integrator, ds.SolverOptions(), v0=v0, progress=False)
    controls = [
        ds.ParameterControl(model, "E", "uniform", log=True),
        FrictionControl(contact, pairs=[("box", "ground")], log=True),
    ]
    com = center_of_mass(model, "box")
    objective = final_value(com[0] * 100.0 + com[1] * 1000.0)
    rf = ds.ReducedFunctional(sim, objective, controls)
    return Scene(rf, np.array([np.log(5e4), np.log(0.3)]), 0.02, contact)


def wavy(
    comm: MPI.Comm = MPI.COMM_WORLD,
    steps: int = 40,
    formulation: str = "ipc",
    spacing: float = 0.05,
) -> Scene:
    """A 2D box thrown along a wavy polyline ground (v_x, log mu).

    The ground is the polyline through x = -1, -1 + ``spacing``, ..., 1.5 on
    y = -0.03 cos(2 pi x / 0.4); the box [0, 0.16] x [0.035, 0.115] (5 mm above the crest at
    x = 0.2) starts at (1.2, -0.3) m/s.
    """
    box = ds.mesh.simplex_box([[0.0, 0.035], [0.16, 0.115]], [4, 2])
    domain = ds.combine_meshes(comm, [box], names={"box": 1})
    model = ds.Model(domain, ds.NeoHookean(E=2e5, nu=0.3, density=1000.0))
    model.add_gravity(9.81)
    xs = np.arange(-1.0, 1.5 + spacing / 2, spacing)
    ground = Obstacle(np.column_stack([xs, -0.03 * np.cos(2 * np.pi * xs / 0.4)]), name="ground")
    contact = ContactTerm(
        model, dhat=1e-3, friction=0.3, eps_v=0.01, obstacles=[ground], formulation=formulation
    )
    model.add_numeric_term(contact)
    integrator = ds.BDF(2, 0.01, steps)
    sim = ds.Simulation(model, integrator, ds.SolverOptions(), progress=False)
    controls = [
        RigidVelocity(sim, "box", angular=False),
        FrictionControl(contact, pairs=[("box", "ground")], log=True),
    ]
    com = center_of_mass(model, "box")
    objective = final_value(com[0] * 100.0 + com[1] * 1000.0)
    rf = ds.ReducedFunctional(sim, objective, controls)
    return Scene(rf, np.array([1.2, -0.3, np.log(0.3)]), 0.02, contact)


def roll(
    comm: MPI.Comm = MPI.COMM_WORLD,
    steps: int = 40,
    formulation: str = "ipc",
    solver_options: ds.SolverOptions | None = None,
) -> Scene:
    """A 2D disk (radius 0.1 m) thrown at (1, -0.5) m/s down a polyline slope with kinks.

    It lands sliding, friction (mu 0.5) spins it up until it rolls: its contacts stick, which
    the Newton steps from a sliding state overshoot (``contact.energy.stick_model``).
    Parameters (v_x, v_y, angular velocity); J the squared distance of its final centre of
    mass from the origin.
    """
    disk = ds.mesh.simplex_ball([0.0, 0.12], 0.1, 0.03)
    domain = ds.combine_meshes(comm, [disk], names={"disk": 1})
    model = ds.Model(domain, ds.NeoHookean(E=3e4, nu=0.4, density=800.0))
    model.add_gravity(9.81)
    slope = np.array([[-1.0, 0.1], [0.0, 0.0], [0.5, -0.1], [1.5, -0.12], [3.0, 0.05]])
    ground = Obstacle(slope, name="ground")
    contact = ContactTerm(
        model, dhat=1e-3, friction=0.5, obstacles=[ground], formulation=formulation
    )
    model.add_numeric_term(contact)
    options = solver_options or ds.SolverOptions()
    sim = ds.Simulation(model, ds.BDF(2, 0.01, steps), options, progress=False)
    com = center_of_mass(model, "disk")
    objective = final_value(com[0]) ** 2 + final_value(com[1]) ** 2
    rf = ds.ReducedFunctional(sim, objective, RigidVelocity(sim, "disk", angular=True))
    return Scene(rf, np.array([1.0, -0.5, 0.0]), 0.05, contact)


def slide(comm: MPI.Comm = MPI.COMM_WORLD, steps: int = 20, formulation: str = "ipc") -> Scene:
    """A block thrown along a flat ground of 8 triangles, across their shared edges.

    Parameters (log mu, the block's initial velocity): its final centre of mass along x and
    its height.
    """
    block = ds.mesh.simplex_box([[0.0, 0.0, 0.0005], [0.2, 0.2, 0.1005]], [4, 4, 2])
    domain = ds.combine_meshes(comm, [block], names={"block": 1})
    model = ds.Model(domain, ds.NeoHookean(E=1e5, nu=0.3, density=500.0))
    model.add_gravity(9.81)
    g = np.linspace(-1.0, 2.0, 3)
    gx, gy = np.meshgrid(g, g, indexing="ij")
    V = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(9)])
    F = []
    for i in range(2):
        for j in range(2):
            a, b, c, d = 3 * i + j, 3 * (i + 1) + j, 3 * (i + 1) + j + 1, 3 * i + j + 1
            F += [[a, b, c], [a, c, d]]
    ground = Obstacle(V, faces=np.array(F), name="ground")
    contact = ContactTerm(
        model, dhat=1e-3, friction=0.3, obstacles=[ground], formulation=formulation
    )
    model.add_numeric_term(contact)
    sim = ds.Simulation(model, ds.BDF(2, 0.01, steps), ds.SolverOptions(), progress=False)
    controls = [
        FrictionControl(contact, pairs=[("block", "ground")], log=True),
        ds.RigidVelocity(sim, "block", angular=False),
    ]
    com = center_of_mass(model, "block")
    rf = ds.ReducedFunctional(sim, final_value(com[0] * 10.0 + com[2] * 100.0), controls)
    return Scene(rf, np.array([np.log(0.3), 1.0, 0.0, 0.0]), 0.02, contact)


def ridge(
    comm: MPI.Comm = MPI.COMM_WORLD,
    steps: int = 12,
    formulation: str = "ipc",
    follow_branch: bool = True,
    pitch: float = 0.03,
    offset: float = 0.0,
) -> Scene:
    """The drop's block landing on a roof ridge: each landing step has two local minima.

    The ground's two triangles meet along the diagonal under the block's diagonal vertices,
    raised by ``pitch`` (m) at its ends: the block tips to one side or the other, and which one
    Newton finds is decided by round-off. Parameters (log E, log mu); J = 1e3 (x - y) of the
    final centre of mass (the side it tipped to). ``follow_branch``: the functional's branch
    reference is q0. ``offset`` (m) moves the block along x off the ridge: the side it tips to
    is then decided by the offset, not by round-off.
    """
    a, b = -1.4, 2.6
    V = np.array([[a, a, pitch], [b, a, 0], [b, b, pitch], [a, b, 0]], float)
    ground = Obstacle(V, faces=np.array([[0, 1, 2], [0, 2, 3]]), name="ground")
    box = [[offset, 0.0, 0.01 + pitch], [0.2 + offset, 0.2, 0.11 + pitch]]
    domain = ds.combine_meshes(comm, [ds.mesh.simplex_box(box, [4, 4, 2])], names={"block": 1})
    model = ds.Model(domain, ds.NeoHookean(E=6e4, nu=0.3, density=500.0))
    model.add_gravity(9.81)
    contact = ContactTerm(
        model, dhat=1e-3, friction=0.2, obstacles=[ground], formulation=formulation
    )
    model.add_numeric_term(contact)
    sim = ds.Simulation(model, ds.BDF(2, 0.01, steps), ds.SolverOptions(), progress=False)
    controls = [
        ds.ParameterControl(model, "E", "uniform", log=True),
        FrictionControl(contact, pairs=[("block", "ground")], log=True),
    ]
    q0 = np.log([6e4, 0.2])
    com = center_of_mass(model, "block")
    objective = final_value((com[0] - com[1]) * 1e3)
    reference = q0 if follow_branch else None
    rf = ds.ReducedFunctional(sim, objective, controls, branch_reference=reference)
    return Scene(rf, q0, 0.02, contact)


def damping(
    comm: MPI.Comm = MPI.COMM_WORLD,
    steps: int = 40,
    formulation: str = "ipc",
    polyfem_barrier: bool = False,
) -> Scene:
    """PolyFEM's ``damping-transient`` gradient test on meshes of our own (log psi, log phi).

    A disk (radius 0.25, centre (-1.5, 0.3)) thrown at 5 m/s along a clamped 3 x 0.02 slab
    under gravity, NeoHookean E = 1e6, nu = 0.3, rho = 1000, damping psi = phi = 10, friction
    0.5, BDF2 with dt = 0.01; J the disk's trajectory misfit to a target run at psi = 5,
    phi = 20. ``polyfem_barrier``: the scene's barrier as PolyFEM means it (kappa 1e5, pairs
    not area weighted); else the suggested stiffness with area weights.
    """
    slab = ds.mesh.simplex_box([[-1.5, -0.01], [1.5, 0.01]], [60, 1])
    disk = ds.mesh.simplex_ball([-1.5, 0.3], 0.25, 0.06)
    domain = ds.combine_meshes(comm, [slab, disk], names={"slab": 1, "disk": 2})
    material = ds.NeoHookean(E=1e6, nu=0.3, density=1000.0, damping_psi=10.0, damping_phi=10.0)
    model = ds.Model(domain, material)
    model.add_gravity(9.8)
    model.add_dirichlet(lambda x: x[1] < 0.01 + 1e-9, 0.0)
    contact = ContactTerm(
        model,
        dhat=1e-3,
        stiffness=1e5 if polyfem_barrier else None,
        friction=0.5,
        area_weighting=not polyfem_barrier,
        min_gap=1e-12,
        formulation=formulation,
    )
    model.add_numeric_term(contact)
    X = model.V.tabulate_dof_coordinates()[:, :2]
    v0 = np.zeros_like(X)
    v0[X[:, 1] > 0.02, 0] = 5.0
    integrator = ds.BDF(2, 0.01, steps)
    sim = ds.Simulation(model, integrator, ds.SolverOptions(), v0=v0.ravel(), progress=False)
    controls = [
        ds.ParameterControl(model, "damping_psi", "uniform", log=True),
        ds.ParameterControl(model, "damping_phi", "uniform", log=True),
    ]
    for control, value in zip(controls, (5.0, 20.0), strict=True):
        control.assign(np.array([np.log(value)]))
    target = sim.run()
    misfit = ds.time_integral(ds.target_trajectory(sim, target, bodies="disk"), "uniform")
    rf = ds.ReducedFunctional(sim, misfit * 1e9, controls)
    return Scene(rf, np.log([10.0, 10.0]), 0.02, contact)


def damping_polyfem(comm: MPI.Comm = MPI.COMM_WORLD, **kwargs) -> Scene:
    """:func:`damping` with PolyFEM's barrier (kappa 1e5, no area weights)."""
    return damping(comm, polyfem_barrier=True, **kwargs)


def ridge_free(comm: MPI.Comm = MPI.COMM_WORLD, **kwargs) -> Scene:
    """:func:`ridge` without the branch reference (J jumps between the two sides)."""
    return ridge(comm, follow_branch=False, **kwargs)


SCENES = {
    "drop": drop,
    "drop_2d": drop_2d,
    "slide": slide,
    "ridge": ridge,
    "ridge_free": ridge_free,
    "roll": roll,
    "damping": damping,
    "damping_polyfem": damping_polyfem,
    "wavy": wavy,
}
