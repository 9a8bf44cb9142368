"""Large static shape problem: the paper's 3D beam (Fig. 7) at its Table 4 size.

The beam of ``demos/beam3d_stress.py`` (``meshes/beam3d.geo``: Neo-Hookean, on a central
support, two end loads; objective L8 von Mises stress + volume bound + boundary smoothing,
every boundary vertex but the support's and the loaded faces' a design parameter), meshed at
``--h`` with Lagrange elements of ``--degree``, static Newton with GMRES + GAMG (the rigid body
modes as near-null space). The defaults (h 0.0238, P2: 204 402 dofs, ~4 000 design vertices)
are next to the paper's 9 939 vertices and 209 409 dofs; ``--h 0.0115 --degree 1`` is 209 367
P1 dofs. Reported: set-up (mesh, forms, first forward for the objective's scale), then the
forward and the shape gradient of the functional at q = 0, against Table 4's 192.2 s and
37.3 s per simulation and gradient (PolyFEM, the paper's machine).

Run ``python tests/benchmarks/bench_static_beam.py [--h H] [--degree K]`` (also under
``mpiexec -n 2``); the last line printed is a JSON object with the numbers.
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parents[2]
PAPER = {"forward_s": 192.1587, "gradient_s": 37.2651, "dofs": 209409}


def _parse(argv):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--h", type=float, default=0.0238, help="mesh size of beam3d.geo")
    p.add_argument("--degree", type=int, default=2, help="Lagrange degree of the displacement")
    return p.parse_args(argv)


def main(argv=None) -> dict:
    args = _parse(argv)
    sys.path.insert(0, str(ROOT / "demos"))
    import beam3d_stress as demo
    import numpy as np
    from mpi4py import MPI

    import diffsolids as ds
    from diffsolids.mesh import from_geo
    from diffsolids.parallel import collective_comm, peak_rss_mb

    comm = MPI.COMM_WORLD

    class Beam(demo.Problem):
        degree = args.degree

        def solver_options(self) -> ds.SolverOptions:
            return ds.SolverOptions(rtol=1e-10, petsc_options={"pc_type": "gamg"})

    def timed(f, *a):
        comm.barrier()
        t0, c0 = time.perf_counter(), time.process_time()
        value = f(*a)
        cpu = collective_comm(comm).allreduce(time.process_time() - c0, op=MPI.MAX)
        return value, time.perf_counter() - t0, cpu

    domain, mesh_s, _ = timed(from_geo, demo.GEO, comm, None, None, {"h": args.h})
    rf, setup_s, _ = timed(Beam(), domain)
    q0 = np.zeros(rf.controls.size)
    J, forward_s, forward_cpu = timed(rf, q0)
    g, gradient_s, gradient_cpu = timed(rf.gradient, q0)
    dofs = rf.simulation.model.V.dofmap.index_map.size_global * domain.mesh.geometry.dim
    out = {
        "benchmark": "static_beam",
        "ranks": comm.size,
        "h": args.h,
        "degree": args.degree,
        "dofs": dofs,
        "parameters": int(rf.controls.size),
        "newton_its": rf.trajectory.newton_iterations(),
        "mesh_s": round(mesh_s, 2),
        "setup_s": round(setup_s, 2),
        "forward_s": round(forward_s, 2),
        "forward_cpu_s": round(forward_cpu, 2),
        "gradient_s": round(gradient_s, 2),
        "gradient_cpu_s": round(gradient_cpu, 2),
        "gradient_over_forward": round(gradient_s / forward_s, 3),
        "paper": PAPER,
        "forward_vs_paper": round(forward_s / PAPER["forward_s"], 3),
        "J": float(J),
        "gradient_norm": float(np.linalg.norm(g)),
        "peak_rss_mb": peak_rss_mb(),
    }
    if comm.rank == 0:
        print(
            f"bench_static_beam: {dofs} dofs (P{args.degree}, h {args.h}), "
            f"{out['parameters']} shape parameters, {comm.size} rank(s): set-up {setup_s:.1f} s, "
            f"forward {forward_s:.1f} s ({out['newton_its']} Newton its; paper 192.2 s), "
            f"gradient {gradient_s:.1f} s (paper 37.3 s)",
            flush=True,
        )
        print(json.dumps(out), flush=True)
    return out


if __name__ == "__main__":
    main()
