"""Static shape optimisation of a 3D Neo-Hookean beam on a central support (paper Fig. 7).

The beam (``meshes/beam3d.geo``: 2 x 0.25 x 0.25) stands on a support patch in the middle of
its underside (zero displacement there) and carries two side loads: downward tractions on its
end faces, large enough to bend the arms well into the nonlinear range. Neo-Hookean material,
one static solve (Newton) per evaluation.

Objective (paper eqs. 30, 35, 37), normalised by its initial stress value:

    J = ||sigma_vM||_L8 / s0 + w_V phi(V - V0) / V0^2 + w_S * boundary smoothing

with phi the one-sided quadratic penalty of eq. 35 (the volume may not grow). Controls: every
boundary vertex except those of the support patch and of the loaded end faces (the total load
stays fixed); the interior follows the linear-elasticity extension (MeshMotionControl),
ShapeInnerProduct is the initial inverse Hessian of L-BFGS and the interior is remeshed if
the mesh quality drops.

Checked outcome (default and --full): the maximum cellwise von Mises stress falls (by at least
a factor 1.5) while the volume grows by at most 1 %; in every run: the objective decreased, no
accepted iterate has inverted cells or a self-intersecting boundary.

Run ``python demos/beam3d_stress.py`` (default size), ``--tiny`` (smoke test), ``--full``
(paper-like resolution), or ``mpiexec -n 2 python demos/beam3d_stress.py``.
"""

from common import MESHES, DemoReport, by_size, run_demo
from mpi4py import MPI
from shape_tools import StressProblem, plot_shapes_3d, shape_run

import diffsolids as ds
from diffsolids.io import silhouette_edges
from diffsolids.mesh import from_geo
from diffsolids.optimize import MeshMotionControl

GEO = MESHES / "beam3d.geo"
SUPPORT = "support"
LOADS = ("load_left", "load_right")
TRACTION = 15.0  # downward traction on each end face (tip deflection ~ 5 % of the arm)
E, NU = 1.0e4, 0.3
SIZES = by_size(h=(0.125, 0.06, 0.025), iterations=(3, 30, 150), max_change=(0.01, 0.01, 0.005))


class Problem(StressProblem):
    """The beam on its support; the volume may not grow; figures of silhouettes."""

    smoothing_exclude = (SUPPORT,)  # w_V = 1e3, w_S = 0.05
    degree = 1  # Lagrange degree of the displacement
    remesh_threshold = 0.01
    min_reduction = 1.5  # checked: max von Mises before / after
    volume_tolerance = 0.01  # checked: (V - V0) / V0

    def model(self, domain) -> ds.Model:
        """The supported, loaded beam on a mesh."""
        model = ds.Model(domain, ds.NeoHookean(E=E, nu=NU), degree=self.degree)
        model.add_dirichlet(SUPPORT, 0.0)
        for load in LOADS:
            model.add_traction(load, [0.0, 0.0, -TRACTION])
        return model

    def control(self, model, sim) -> MeshMotionControl:
        """Every boundary vertex except those of the support patch and of the loaded faces."""
        return MeshMotionControl(model, exclude_facets=[SUPPORT, *LOADS], refuse_intersections=True)

    def outline(self, model) -> list:
        """Silhouettes seen from the side and from above."""
        return silhouette_edges(model)

    def extra(self, result) -> dict:
        """Newton iterations of the final solve."""
        return {"newton_iterations": result.functional.trajectory.newton_iterations()}

    def check(self, report, V1: float) -> None:
        """The volume grows by at most ``volume_tolerance``."""
        growth = (V1 - self.V0) / self.V0
        report.check(
            "volume growth",
            growth,
            self.volume_tolerance,
            growth <= self.volume_tolerance,
            f"(V {self.V0:.5g} -> {V1:.5g})",
        )

    def plot(self, path, before, after, result, title: str, comm) -> None:
        """Side and top silhouettes before and after."""
        plot_shapes_3d(path, before, after, result, title, comm)


def main(argv=None, comm: MPI.Comm = MPI.COMM_WORLD) -> DemoReport:
    """Run the demo on ``comm``; returns the report (printed on rank 0)."""
    run = shape_run(__doc__.splitlines()[0], "beam3d_stress", argv, comm, SIZES)
    return Problem().run(run, from_geo(GEO, comm, numbers={"h": run.args.h}))


if __name__ == "__main__":
    run_demo(main)
