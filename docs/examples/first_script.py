"""A first script: a cantilever sags under gravity; the gradient of its sag w.r.t. E."""

import numpy as np
from mpi4py import MPI

import diffsolids as ds

# a 2 x 0.2 beam, facet tag 1 on its left end
domain = ds.mesh.create_rectangle(
    MPI.COMM_WORLD, [[0, 0], [2, 0.2]], [20, 2], facets={1: lambda x: np.isclose(x[0], 0)}
)
model = ds.Model(domain, ds.NeoHookean(E=1e5, nu=0.3, density=10.0))
model.add_gravity(9.81)
model.add_dirichlet(1, 0.0)  # clamp the left end
sim = ds.Simulation(model, ds.Static(), ds.SolverOptions(rtol=1e-10), progress=False)

# objective: the mean vertical displacement, written in UFL
sag = ds.Integral(lambda f: -f.u[1] / 0.4 * f.dx, "sag")
rf = ds.ReducedFunctional(sim, ds.final_value(sag), ds.ParameterControl(model, "E", "uniform"))
q = rf.initial_parameters()
J, dJ = rf.value_and_gradient(q)
rate = ds.taylor_test(rf, q, np.array([100.0])).min_rate  # 2 when the gradient is right
if domain.comm.rank == 0:
    print(f"sag {J:.6e} m, dsag/dE {dJ[0]:.6e} m/Pa, Taylor rate {rate:.2f}")
