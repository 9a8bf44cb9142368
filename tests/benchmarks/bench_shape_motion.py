"""Mesh motion and remeshing benchmark: set-up and apply costs, quality before and after.

For a 2D rectangle (``--cells2d``) and a 3D box (``--cells3d``), all boundary vertices except
one clamped side are design vertices:

* MeshMotion (elasticity extension): build (assembly + MUMPS factorisation), ``P @ q``,
  ``P.T @ g`` (transposed solve), Riesz map build and apply;
* a large smooth boundary motion (the top pushed down by up to 60 % of the height in 2D,
  40 % in 3D): minimum scaled Jacobian with the extension and with only the design vertices
  moved;
* remeshing the moved rest shape with the boundary kept: time, cells and quality.

Run ``python tests/benchmarks/bench_shape_motion.py``; works under ``mpiexec -n 2``. The last
line printed is a JSON object with the numbers.
"""

import argparse
import json
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")


def _parse():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cells2d", type=int, nargs=2, default=[128, 64])
    p.add_argument("--cells3d", type=int, nargs=3, default=[16, 16, 16])
    p.add_argument("--repeat", type=int, default=5, help="applications timed (mean reported)")
    return p.parse_args()


def _timed(fn, repeat=1):
    t0 = time.perf_counter()
    for _ in range(repeat):
        out = fn()
    return out, (time.perf_counter() - t0) / repeat


def _case(dim, cells, repeat, comm):
    import numpy as np

    from diffsolids.mesh import check_orientation, create_box, create_rectangle
    from diffsolids.mesh import min_scaled_jacobian as msj
    from diffsolids.optimize.mesh_motion import MeshMotion
    from diffsolids.optimize.remesh import gather_mesh, remesh_domain

    clamp = {1: lambda x: np.isclose(x[0], 0.0)}
    if dim == 2:
        dom = create_rectangle(comm, [[0, 0], [2, 1]], cells, facets=clamp)
    else:
        dom = create_box(comm, [[0, 0, 0], [2, 1, 1]], cells, facets=clamp)
    signs = check_orientation(dom.mesh)
    P, t_build = _timed(lambda: MeshMotion(dom, "boundary", exclude_facets=[1]))
    rng = np.random.default_rng(0)
    q = comm.bcast(rng.standard_normal(P.shape[1]), root=0)
    g = comm.bcast(rng.standard_normal(P.shape[0]), root=0)
    _, t_apply = _timed(lambda: P @ q, repeat)
    _, t_adjoint = _timed(lambda: P.T @ g, repeat)
    riesz, t_riesz_build = _timed(lambda: P.riesz_map())
    _, t_riesz = _timed(lambda: riesz(q), repeat)

    arrays = gather_mesh(dom)
    points = comm.bcast(arrays.points if comm.rank == 0 else None, root=0)
    xd = points[P.design]
    push = np.zeros_like(xd)
    top = dim - 1
    scale = 0.6 if dim == 2 else 0.4
    push[:, top] = -scale * xd[:, top] * np.sin(np.pi * xd[:, 0] / 2.0)
    push = push.ravel()
    d = (P @ push).reshape(-1, dim)
    inputs = dom.mesh.geometry.input_global_indices
    x = dom.mesh.geometry.x.copy()
    x[:, :dim] += d[inputs]
    q_ext = msj(dom.mesh, signs, x)
    only = np.zeros_like(d)
    only[P.design] = push.reshape(-1, dim)
    x_only = dom.mesh.geometry.x.copy()
    x_only[:, :dim] += only[inputs]
    q_only = msj(dom.mesh, signs, x_only)
    q_rest = msj(dom.mesh, signs)

    new, t_remesh = _timed(lambda: remesh_domain(dom, coordinates=x))
    q_new = msj(new.mesh, check_orientation(new.mesh))
    tdim = dom.mesh.topology.dim
    cells_of = lambda m: m.mesh.topology.index_map(tdim).size_global  # noqa: E731
    return {
        "vertices": int(P.num_vertices),
        "design_parameters": int(P.shape[1]),
        "motion_build_s": t_build,
        "motion_apply_s": t_apply,
        "motion_adjoint_s": t_adjoint,
        "riesz_build_s": t_riesz_build,
        "riesz_apply_s": t_riesz,
        "quality_rest": q_rest,
        "quality_moved_extension": q_ext,
        "quality_moved_boundary_only": q_only,
        "remesh_s": t_remesh,
        "cells_before": int(cells_of(dom)),
        "cells_after": int(cells_of(new)),
        "quality_after_remesh": q_new,
    }


def main():
    args = _parse()
    from mpi4py import MPI

    import diffsolids  # noqa: F401  (MPI before DOLFINx)

    comm = MPI.COMM_WORLD
    result = {"ranks": comm.size}
    result["2d"] = _case(2, args.cells2d, args.repeat, comm)
    result["3d"] = _case(3, args.cells3d, args.repeat, comm)
    if comm.rank == 0:
        for key in ("2d", "3d"):
            print(key, json.dumps(result[key], indent=1))
        from diffsolids.parallel import peak_rss_mb

        result["peak_rss_mb"] = peak_rss_mb()  # this process's
        print(json.dumps(result))


if __name__ == "__main__":
    main()
