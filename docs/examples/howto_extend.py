"""How-to: a new material law, numeric force, objective and parameter map, one class each.

Each piece is written here and nowhere else: the solver, the adjoint and the optimiser use it
through its interface. The script checks the gradient through all four by central differences
along a random direction and along the gradient.
"""

import numpy as np
import ufl
from dolfinx import fem
from mpi4py import MPI
from petsc4py import PETSc

import diffsolids as ds
from diffsolids import forms
from diffsolids.controls.maps import ParameterMap
from diffsolids.errors import ParameterError
from diffsolids.parallel import collective_comm


# [law]
class MooneyRivlin(forms.StrainEnergy):
    """c1 (I1 - d - 2 ln J) + c2 (I2 - I2(I) - 2 (d - 1) ln J) + lambda/2 (ln J)^2.

    c1 + c2 = mu / 2, ``ratio`` = 2 c1 / mu (1: Neo-Hookean). Only the energy density is
    written: the stresses (P = dpsi/dF, sigma = P F^T / J) follow from it.
    """

    name = "mooney_rivlin"

    def __init__(self, ratio: float):
        self.ratio = ratio

    def density(self, F, lmbda, mu):
        """psi(F; lambda, mu)."""
        d = F.ufl_shape[0]
        C = F.T * F
        lnJ = ufl.ln(ufl.det(F))
        i1, i2 = ufl.tr(C), 0.5 * (ufl.tr(C) ** 2 - ufl.tr(C * C))
        c1, c2 = 0.5 * mu * self.ratio, 0.5 * mu * (1 - self.ratio)
        i2_rest = d * (d - 1) / 2
        return (
            c1 * (i1 - d - 2 * lnJ) + c2 * (i2 - i2_rest - 2 * (d - 1) * lnJ) + 0.5 * lmbda * lnJ**2
        )


# [numeric]
class GroundSpring(ds.NumericTerm):
    """k/2 |u|^2 over the owned dofs: every node tied to its rest position by a spring."""

    name = "ground spring"
    has_hessian_action = True

    def __init__(self, model: ds.Model, k: float):
        self.k, self.comm = k, model.domain.comm
        bs = model.V.dofmap.index_map_bs
        self.owned = model.V.dofmap.index_map.size_local * bs
        self.start = model.V.dofmap.index_map.local_range[0] * bs

    def _owned(self, u) -> np.ndarray:
        return (u.x.array if isinstance(u, fem.Function) else np.asarray(u))[: self.owned]

    def energy(self, u) -> float:
        """The energy (collective: the sum over the ranks)."""
        local = 0.5 * self.k * float(self._owned(u) @ self._owned(u))
        return collective_comm(self.comm).allreduce(local, op=MPI.SUM)

    def add_residual(self, u, b: PETSc.Vec) -> None:
        """Add dE/du to the owned entries of b."""
        b.array_w[: self.owned] += self.k * self._owned(u)

    def add_jacobian(self, u, A: PETSc.Mat, bc_dofs: np.ndarray, project: bool = False) -> None:
        """Add k on the diagonal of the free rows (DOLFINx set the Dirichlet rows already)."""
        diagonal = A.createVecLeft()
        diagonal.array[:] = self.k
        diagonal.array[bc_dofs[bc_dofs < self.owned]] = 0.0
        A.assemble()  # the assembled form: insertions done, nonzero pattern fixed
        A.setDiagonal(diagonal, addv=PETSc.InsertMode.ADD_VALUES)

    def add_hessian_action(self, u, direction: np.ndarray, y: PETSc.Vec) -> None:
        """Add the exact Hessian times a direction (the adjoint's matrix-free products)."""
        y.array_w[: self.owned] += self.k * np.asarray(direction)[: self.owned]


# [map]
class Sigmoid(ParameterMap):
    """p = low + (high - low) / (1 + exp(-q)): a bounded value from an unbounded parameter."""

    name = "sigmoid"

    def __init__(self, low: float, high: float):
        self.low, self.high = low, high

    def forward(self, q):
        """The value p = f(q)."""
        return self.low + (self.high - self.low) / (1.0 + np.exp(-np.asarray(q)))

    def derivative(self, q):
        """dp/dq."""
        s = 1.0 / (1.0 + np.exp(-np.asarray(q)))
        return (self.high - self.low) * s * (1.0 - s)

    def inverse(self, p):
        """The parameter of a value (refused outside (low, high))."""
        t = (np.asarray(p) - self.low) / (self.high - self.low)
        if np.any(t <= 0) or np.any(t >= 1):
            raise ParameterError(f"sigmoid map: values {p} outside ({self.low}, {self.high})")
        return np.log(t / (1.0 - t))


# [scene]
def build(comm: MPI.Comm = MPI.COMM_WORLD) -> ds.ReducedFunctional:
    """A damped cantilever of the new law on the springs, swinging for 6 BDF2 steps."""
    left = {1: lambda x: np.isclose(x[0], 0.0)}
    domain = ds.mesh.create_rectangle(comm, [[0, 0], [1, 0.2]], [10, 2], facets=left)
    law = ds.Material(MooneyRivlin(0.6), E=1e4, nu=0.3, density=10.0, damping_psi=20.0)
    model = ds.Model(domain, law)
    model.add_gravity(9.81)
    model.add_dirichlet(1, 0.0)
    model.add_numeric_term(GroundSpring(model, k=50.0))
    sim = ds.Simulation(model, ds.BDF(2, 0.05, 6), ds.SolverOptions(rtol=1e-11), progress=False)
    # [objective]
    # an objective reading the previous step too: the squared velocity estimate
    # |(u - u_prev) / dt|^2 summed over the steps 1..N ("sum": w_0 = 0, w_i = 1)
    speed2 = ds.Integral(lambda f: ufl.dot(f.u - f.u_prev, f.u - f.u_prev) / f.dt**2 * f.dx)
    objective = ds.time_integral(speed2, "sum")
    # [control]
    control = ds.ParameterControl(model, "E", "uniform", map=Sigmoid(5e3, 5e4))
    # [end]
    return ds.ReducedFunctional(sim, objective, control)


def main() -> None:
    """Central differences through the law, the spring, the objective and the map."""
    rf = build()
    q = rf.initial_parameters()
    g = rf.gradient(q)
    errors = []
    for d in (np.random.default_rng(1).standard_normal(len(q)), g / np.linalg.norm(g)):
        check = ds.finite_difference_check(rf, q, 0.1 * d, [1e-3, 1e-4], gradient=g)
        errors.append(check.relative_error)
    J = rf(q)  # collective, like every call of diffsolids: never inside `if rank == 0`
    if rf.comm.rank == 0:
        print(f"E = {rf.model.coefficients['E'].x.array[0]:.1f} Pa at q = {q[0]:.4f}")
        print(f"J = {J:.6e}, dJ/dq = {g[0]:.6e}")
        print(f"relative errors: random {errors[0]:.1e}, along the gradient {errors[1]:.1e}")


if __name__ == "__main__":
    main()
