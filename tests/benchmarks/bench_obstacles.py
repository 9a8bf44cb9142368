"""Obstacle benchmark: the paper's fig21 sliding bunny with the slide as a kinematic obstacle.

Scene (``$DIFFSOLIDS_DATA/diffipc/fig21_friction_bunny/run-new.json``): the slide
(``slide.msh``, ``is_obstacle``) and the Stanford bunny scaled by 4 and translated by
(0.5, -0.13, -0.7), thrown along z at 2 m/s, gravity 9.8 m/s^2 along -y, friction 0.5,
Neo-Hookean E = 1e5, nu = 0.48, rho = 1000, BDF1. The scene's dt = 0.05 fails at its second
step in both set-ups alike (50 Newton iterations, most cut by the collision check: the bunny
moves 0.1 m per step into a dhat of 1e-3), so the default is dt = 0.02 (contact from step 3).
Two set-ups of the same contact (dhat 1e-3, the same barrier stiffness, suggested for the
obstacle set-up):

- ``obstacle``: the slide's boundary surface as an :class:`~diffsolids.contact.Obstacle`
  (no dofs; the FE system is the bunny's);
- ``clamped``: the slide as a second body of the mesh with all its nodes clamped (the former
  workaround: its dofs are assembled and factorised at every Newton iteration).

Reported per set-up: dofs, collision vertices, Newton iterations per step, seconds per Newton
iteration (wall and CPU), and the largest difference of the bunny's surface between the two
(they solve the same problem: the slide's boundary is the same collision geometry).

Run ``python tests/benchmarks/bench_obstacles.py [--steps N]`` (also under ``mpiexec -n 2``).
The last line printed is a JSON object with the numbers.
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

FIG21 = (
    Path(os.environ.get("DIFFSOLIDS_DATA", Path(__file__).resolve().parents[3] / "shared" / "data"))
    / "diffipc"
    / "fig21_friction_bunny"
)


def _parse(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=4, help="BDF1 steps")
    p.add_argument("--dt", type=float, default=0.02, help="time step (the scene: 0.05)")
    p.add_argument("--max-iterations", type=int, default=50, help="Newton iterations per step")
    p.add_argument("--data", type=Path, default=FIG21, help="the fig21 scene folder")
    return p.parse_args(argv)


def fig21_scene(
    comm, setup: str, steps: int, data: Path = FIG21, stiffness=None, dt=None, max_iterations=50
):
    """(simulation, contact) of fig21 with the slide as ``"obstacle"`` or ``"clamped"``."""
    from dolfinx import fem
    from mpi4py import MPI

    import diffsolids as ds
    from diffsolids.contact import ContactTerm, Obstacle, suggest_barrier_stiffness
    from diffsolids.mesh import combine_meshes, read_mesh

    scene = json.loads((data / "run-new.json").read_text())
    bunny_spec = scene["geometry"][1]["transformation"]
    bunny = read_mesh(
        data / "stanford-bunny.obj_.msh",
        MPI.COMM_SELF,
        scale=bunny_spec["scale"],
        translation=bunny_spec["translation"],
    )
    slide = read_mesh(data / "slide.msh", MPI.COMM_SELF)
    material = ds.NeoHookean(E=1e5, nu=0.48, density=1000.0)
    integ = ds.BDF(1, scene["time"]["dt"] if dt is None else dt, steps)
    mu = scene["contact"]["friction_coefficient"]
    if setup == "obstacle":
        domain = combine_meshes(comm, [bunny], names={"bunny": 1})
        obstacles = [Obstacle.from_domain(slide, name="slide")]
        model = ds.Model(domain, material)
    else:
        domain = combine_meshes(comm, [slide, bunny], names={"slide": 1, "bunny": 2})
        obstacles = []
        model = ds.Model(domain, material)
    model.add_gravity(9.8, axis=1)
    if setup == "clamped":
        slide_nodes = model.V.dofmap.list[domain.cell_tags.find(1)].ravel()
        model.add_dirichlet(_node_locator(model, slide_nodes), 0.0)
    if stiffness is None:
        probe = ContactTerm(model, dhat=1e-3, stiffness=1.0, obstacles=obstacles)
        stiffness = suggest_barrier_stiffness(probe, integ)
    contact = ContactTerm(
        model, dhat=1e-3, stiffness=stiffness, friction=mu, eps_v=1e-3, obstacles=obstacles
    )
    model.add_numeric_term(contact)
    v0 = fem.Function(model.V)
    thrown = model.V.dofmap.list[domain.cell_tags.find(domain.body_id("bunny"))]
    v0.x.array.reshape(-1, 3)[thrown] = scene["initial_conditions"]["velocity"][0]["value"]
    options = ds.SolverOptions(rtol=1e-8, max_iterations=max_iterations)
    sim = ds.Simulation(model, integ, options, v0=v0.x.array, progress=False)
    return sim, contact


def _node_locator(model, nodes):
    """A Dirichlet locator of the given local nodes (by their coordinates)."""
    import numpy as np

    X = model.V.tabulate_dof_coordinates()[np.unique(nodes)]
    from scipy.spatial import cKDTree

    tree = cKDTree(X)

    def locate(x):
        d, _ = tree.query(x.T[:, : X.shape[1]])
        return d < 1e-12

    return locate


def run(comm, setup: str, args, stiffness=None) -> tuple[dict, object, object]:
    """Numbers of one set-up, and (contact, trajectory) for the comparison."""
    sim, contact = fig21_scene(
        comm, setup, args.steps, args.data, stiffness, args.dt, args.max_iterations
    )
    t0, c0 = time.perf_counter(), time.process_time()
    traj = sim.run()
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    its = max(traj.newton_iterations(), 1)
    numbers = {
        "stiffness": contact.stiffness,
        "dofs": sim.model.V.dofmap.index_map.size_global * 3,
        "collision_vertices": contact.surface.num_vertices,
        "newton_iterations": [r.iterations for r in traj.records],
        "collisions": [r.num_collisions for r in contact.records],
        "run_s": wall,
        "newton_s": wall / its,
        "newton_cpu_s": cpu / its,
    }
    return numbers, contact, traj


def _bunny_surface(contact, u, body):
    import numpy as np

    surf = contact.surface
    sel = np.flatnonzero(surf.body == body)
    X = surf.rest_positions[sel]
    order = np.lexsort(X.T[::-1])
    return (X + surf.gather(u)[sel])[order]


def main(argv=None) -> dict:
    """Run both set-ups and return the numbers."""
    args = _parse(argv)
    import numpy as np
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    if not (args.data / "run-new.json").exists():
        print(f"no fig21 data in {args.data}", file=sys.stderr)
        return {}
    obstacle, c_obs, t_obs = run(comm, "obstacle", args)
    clamped, c_vol, t_vol = run(comm, "clamped", args, c_obs.stiffness)
    diff = max(
        float(np.abs(_bunny_surface(c_obs, a, 1) - _bunny_surface(c_vol, b, 2)).max())
        for a, b in zip(t_obs.u, t_vol.u, strict=True)
    )
    out = {
        "ranks": comm.size,
        "steps": args.steps,
        "dt": args.dt,
        "obstacle": obstacle,
        "clamped": clamped,
        "speedup_per_newton_iteration": clamped["newton_s"] / obstacle["newton_s"],
        "bunny_surface_difference_m": diff,
    }
    if comm.rank == 0:
        from diffsolids.parallel import peak_rss_mb

        out["peak_rss_mb"] = peak_rss_mb()  # this process's
        print(json.dumps(out))
    return out


if __name__ == "__main__":
    main(sys.argv[1:])
