"""Flagship demo: a soft Neo-Hookean beam, clamped at one end, swings under gravity (BDF2).

The beam (``meshes/beam.geo``, 1 x 0.1 x 0.1 m, meshed by gmsh at run time; physical groups
"beam", "clamp" and "tip") starts straight and at rest. Gravity pulls it down far into the large
deformation range and it swings back up: one period takes about 1.2 s.

Writes into ``output/beam_swing/`` (``--out``):

* ``beam_swing.bp`` (VTX: displacement, velocity) and ``beam_swing_cells.bp`` (von Mises stress),
  or ``beam_swing.xdmf`` with ``--xdmf``; open them in ParaView;
* ``tip_trajectory.csv`` and ``tip_trajectory.png``: the mean displacement of the tip face.

Run ``python demos/beam_swing.py`` (small, well under a minute), ``--full`` for a finer mesh and a
longer run, or under MPI: ``mpiexec -n 2 python demos/beam_swing.py``.
"""

import argparse
import json
import logging
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np
from mpi4py import MPI

import diffsolids as ds
from diffsolids.io import TrajectoryWriter, configure_logging
from diffsolids.mesh import from_geo
from diffsolids.parallel import collective_comm

ROOT = Path(__file__).resolve().parents[1]
GEO = ROOT / "meshes" / "beam.geo"
LENGTH, WIDTH, HEIGHT = 1.0, 0.1, 0.1

# mesh size, degree, dt and steps of the --tiny (smoke test), default and --full runs
SIZES = {
    "tiny": {"h": 0.1, "degree": 1, "dt": 0.025, "steps": 36},
    "default": {"h": 0.05, "degree": 2, "dt": 0.01, "steps": 120},
    "full": {"h": 0.02, "degree": 2, "dt": 0.005, "steps": 600},
}
# --check: the tip must fall at least this far and swing back up by at least this much [m]
MIN_DROP = 0.3


def parse_args(argv=None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    size = p.add_mutually_exclusive_group()
    size.add_argument("--tiny", action="store_true", help="smoke-test size (P1, coarse, 36 steps)")
    size.add_argument("--full", action="store_true", help="finer mesh and a longer run")
    p.add_argument("--h", type=float, help="mesh size (default 0.05, --full 0.02)")
    p.add_argument("--degree", type=int, help="Lagrange degree of u (default 2)")
    p.add_argument("--order", type=int, default=2, help="BDF order (default 2)")
    p.add_argument("--dt", type=float, help="time step (default 0.01, --full 0.005)")
    p.add_argument("--steps", type=int, help="number of steps (default 120, --full 600)")
    p.add_argument("--E", type=float, default=2e6, help="Young's modulus [Pa]")
    p.add_argument("--nu", type=float, default=0.3, help="Poisson's ratio")
    p.add_argument("--density", type=float, default=1000.0, help="density [kg/m^3]")
    p.add_argument("--xdmf", action="store_true", help="write XDMF instead of VTX")
    p.add_argument("--out", type=Path, default=ROOT / "output" / "beam_swing", help="output folder")
    p.add_argument("--no-plot", action="store_true", help="skip the PNG")
    p.add_argument("--verbose", action="store_true", help="log every step")
    p.add_argument("--check", action="store_true", help="exit 1 unless the beam swung down and up")
    args = p.parse_args(argv)
    args.size = "tiny" if args.tiny else ("full" if args.full else "default")
    for key, value in SIZES[args.size].items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    return args


def tip_dofs(model: ds.Model) -> np.ndarray:
    """Owned nodes (block indices) on the tip face x = L."""
    V = model.V
    owned = V.dofmap.index_map.size_local
    x = V.tabulate_dof_coordinates()[:owned]
    return np.flatnonzero(np.isclose(x[:, 0], LENGTH, atol=1e-8 * LENGTH))


def tip_displacement(model: ds.Model, nodes: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Mean displacement of the tip-face nodes, the same on every rank."""
    d = model.dim
    local = np.append(u.reshape(-1, d)[nodes].sum(axis=0), len(nodes))
    total = collective_comm(model.domain.comm).allreduce(local, op=MPI.SUM)
    return total[:d] / total[d]


def plot(path: Path, times: np.ndarray, tip: np.ndarray, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_t, ax_xz) = plt.subplots(1, 2, figsize=(10, 4))
    ax_t.plot(times, tip[:, 2], label="$u_z$ (vertical)")
    ax_t.plot(times, tip[:, 0], label="$u_x$ (along the beam)")
    ax_t.set_xlabel("time [s]")
    ax_t.set_ylabel("tip displacement [m]")
    ax_t.legend()
    ax_t.grid(alpha=0.3)
    ax_xz.plot(LENGTH + tip[:, 0], HEIGHT / 2 + tip[:, 2], "-", lw=1)
    ax_xz.plot([0, LENGTH], [HEIGHT / 2, HEIGHT / 2], "k--", lw=0.8, label="rest")
    ax_xz.set_xlabel("x [m]")
    ax_xz.set_ylabel("z [m]")
    ax_xz.set_aspect("equal")
    ax_xz.set_title("tip path")
    ax_xz.legend()
    ax_xz.grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> dict:
    """Run the demo on ``comm``; returns the summary (also printed as one line on rank 0)."""
    args = parse_args(argv)
    configure_logging(logging.INFO if args.verbose else logging.WARNING, comm)
    t0 = time.perf_counter()

    domain = from_geo(GEO, comm, numbers={"L": LENGTH, "W": WIDTH, "H": HEIGHT, "h": args.h})
    material = ds.NeoHookean(E=args.E, nu=args.nu, density=args.density)
    model = ds.Model(domain, material, degree=args.degree)
    model.add_gravity(9.81)
    model.add_dirichlet("clamp", 0.0)

    out = args.out
    suffix = ".xdmf" if args.xdmf else ".bp"
    writer = TrajectoryWriter(model, out / f"beam_swing{suffix}")
    integrator = ds.BDF(args.order, args.dt, args.steps)
    traj = ds.Simulation(model, integrator, output=writer).run()

    nodes = tip_dofs(model)
    times = np.asarray(traj.times)
    tip = np.array([tip_displacement(model, nodes, u) for u in traj.u])
    seconds = collective_comm(comm).allreduce(time.perf_counter() - t0, op=MPI.MAX)
    dofs = model.V.dofmap.index_map.size_global * model.dim
    low = int(np.argmin(tip[:, 2]))
    rebound = low + int(np.argmax(tip[low:, 2]))

    files = [out / f"beam_swing{suffix}", out / "tip_trajectory.csv", out / "result.json"]
    if args.xdmf:
        files.append(out / "beam_swing.h5")
    else:
        files.append(out / "beam_swing_cells.bp")
    if comm.rank == 0:
        header = "t,ux,uy,uz"
        np.savetxt(
            out / "tip_trajectory.csv", np.column_stack([times, tip]), delimiter=",", header=header
        )
        if not args.no_plot:
            title = (
                f"Neo-Hookean beam, P{args.degree}, BDF{args.order}, dt = {args.dt:g} s, "
                f"{dofs} dofs"
            )
            plot(out / "tip_trajectory.png", times, tip, title)
    if not args.no_plot:
        files.append(out / "tip_trajectory.png")
    comm.barrier()

    swung = bool(
        tip[low, 2] <= -MIN_DROP
        and 0 < low < len(tip) - 1
        and tip[rebound, 2] - tip[low, 2] >= MIN_DROP
    )
    summary = {
        "demo": "beam_swing",
        "size": args.size,
        "dofs": dofs,
        "ranks": comm.size,
        "degree": args.degree,
        "order": args.order,
        "steps": integrator.num_steps,
        "dt": args.dt,
        "newton_its": traj.newton_iterations(),
        "tip_min_z": float(tip[low, 2]),
        "t_min": float(times[low]),
        "tip_rebound_z": float(tip[rebound, 2]),
        "t_rebound": float(times[rebound]),
        "seconds": seconds,
        "swung_down_and_up": swung,
        "files": [str(f) for f in files],
    }
    if comm.rank == 0:
        (out / "result.json").write_text(json.dumps(summary, indent=2))
        print(
            f"beam_swing: {dofs} dofs (P{args.degree}, {comm.size} rank(s)), "
            f"BDF{args.order} {integrator.num_steps} x {args.dt:g} s, "
            f"{summary['newton_its']} Newton its; tip fell to z = {tip[low, 2]:+.3f} m at "
            f"t = {times[low]:.2f} s, swung back to {tip[rebound, 2]:+.3f} m at "
            f"t = {times[rebound]:.2f} s; {seconds:.1f} s; output in {os.path.relpath(out)}/",
            flush=True,
        )
    return summary | {"times": times, "tip": tip}


if __name__ == "__main__":
    argv = sys.argv[1:]
    result = main(argv)
    if "--check" in argv and not result["swung_down_and_up"]:
        sys.exit(f"beam_swing: the tip did not fall {MIN_DROP} m and swing back up")
