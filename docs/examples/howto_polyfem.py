"""How-to: port a PolyFEM scene of the paper (fig20: a kangaroo thrown onto the ground).

``python docs/examples/howto_polyfem.py --data /work/shared/data/diffipc`` (the folder that
holds ``fig20_kangaroo/``). The scene JSON is read as PolyFEM reads it: geometry with its
transformations, materials, gravity, Dirichlet selection, initial velocity and contact.
"""

import argparse
import json
from pathlib import Path

import numpy as np
from mpi4py import MPI

import diffsolids as ds
from diffsolids.polyfem.contact import polyfem_contact_options


def build(folder: Path, steps: int, comm: MPI.Comm = MPI.COMM_WORLD) -> ds.Simulation:
    """The scene of ``folder/run-new.json`` as a Simulation of its first steps."""
    # [geometry]
    scene = json.loads((folder / "run-new.json").read_text())
    meshes, bodies = [], []
    for g in scene["geometry"]:
        t = g["transformation"]  # x' = R (s x) + t, as PolyFEM applies it
        meshes.append(
            ds.read_mesh(
                folder / g["mesh"],
                MPI.COMM_SELF,
                scale=t["scale"],
                rotation=t["rotation"],
                translation=t["translation"],
            )
        )
        bodies.append(g["volume_selection"])
    domain = ds.combine_meshes(comm, meshes, bodies=bodies, names={"ground": 3, "kangaroo": 1})
    # [physics]
    m = scene["materials"]
    nu = min(m["nu"], 0.45)  # nu = 0.5 (incompressible) is refused by ds.NeoHookean
    model = ds.Model(domain, ds.NeoHookean(E=m["E"], nu=nu, density=m["rho"]))
    model.add_gravity(scene["boundary_conditions"]["rhs"][1])  # PolyFEM's rhs: g downwards
    ground = domain.cells_of("ground")
    model.add_dirichlet(lambda x: x[1] <= 0.02 + 1e-9, 0.0)  # the ground square, clamped
    # [contact]
    options = polyfem_contact_options(scene, domain)  # dhat, kappa as written, friction, ...
    if comm.rank == 0:
        print(f"PolyFEM contact: {options}")
    integrator = ds.BDF(1, scene["time"]["dt"], steps)
    probe = ds.ContactTerm(model, **{**options, "stiffness": 1.0, "area_weighting": True})
    kappa = ds.suggest_barrier_stiffness(probe, integrator)
    contact = {**options, "stiffness": kappa, "area_weighting": True}
    model.add_numeric_term(ds.ContactTerm(model, **contact))
    # [initial]
    (v,) = scene["initial_conditions"]["velocity"]  # selection 1: the kangaroo
    v0 = np.zeros((model.V.dofmap.index_map.size_local + model.V.dofmap.index_map.num_ghosts, 2))
    v0[:] = v["value"]
    v0[np.unique(model.V.dofmap.list[ground])] = 0.0
    # [end]
    if comm.rank == 0:
        print(f"kappa suggested {kappa:.3e} (PolyFEM's as written: {options['stiffness']:.1e})")
    return ds.Simulation(
        model, integrator, ds.SolverOptions(rtol=1e-8), v0=v0.ravel(), progress=False
    )


def main(argv: list[str] | None = None) -> None:
    """Build the scene and run its first steps."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, required=True, help="folder holding fig20_kangaroo/")
    p.add_argument("--steps", type=int, default=5, help="time steps to run")
    args = p.parse_args(argv)
    sim = build(args.data / "fig20_kangaroo", args.steps)
    traj = sim.run()
    if sim.model.domain.comm.rank == 0:
        u = traj.u[-1].reshape(-1, 2)
        print(f"{traj.num_steps} steps, {traj.newton_iterations()} Newton iterations")
        print(f"largest displacement {np.abs(u).max():.4f} m")


if __name__ == "__main__":
    main()
