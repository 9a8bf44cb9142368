"""The linear solver of the Newton steps: a factorisation (default) or a Krylov method.

A factorisation (``pc_type`` ``lu``, MUMPS) solves each Newton system exactly and its factors
precondition the adjoint. Any other ``pc_type`` (``gamg`` above all: algebraic multigrid, whose
cost grows linearly with the unknowns and which runs on many ranks) makes the step a Krylov
solve; the Jacobian is then a scalar (AIJ) matrix, which multigrid needs, with the rigid body
modes as its near-null space, and the adjoint solves its systems with the same preconditioner.
"""

import itertools
import re
import weakref

from dolfinx import fem, la
from mpi4py import MPI
from petsc4py import PETSc

__all__ = [
    "FACTORISATIONS",
    "KRYLOV_DEFAULTS",
    "delete_options",
    "krylov_solver",
    "reason_name",
    "rigid_body_modes",
    "solver_prefix",
    "step_petsc_options",
]

_SOLVER_IDS = itertools.count()

#: The ``pc_type`` values that factorise the Newton matrix.
FACTORISATIONS = ("lu", "cholesky")

_FACTORISATION_DEFAULTS = {
    "ksp_type": "preonly",
    "pc_type": "lu",
    "pc_factor_mat_solver_type": "mumps",
}

#: Krylov defaults when ``pc_type`` is not a factorisation (each overridable).
KRYLOV_DEFAULTS = {
    "ksp_type": "gmres",
    "ksp_rtol": 1e-8,
    "ksp_max_it": 1000,
    "ksp_gmres_restart": 200,
}


def step_petsc_options(user: dict, prefix: str) -> tuple[dict, str]:
    """The linear-solver defaults for ``user``'s options and the ``pc_type`` they select.

    Args:
        user: The ``petsc_options`` of :class:`~diffsolids.solvers.SolverOptions`.
        prefix: The solver's options prefix (command-line options under it count too).

    Returns:
        (defaults, pc_type): factorisation defaults (MUMPS LU) unless ``pc_type`` (given in
        ``user`` or on the command line) is something else, then :data:`KRYLOV_DEFAULTS`.
    """
    opts = PETSc.Options(prefix)
    pc_type = user.get("pc_type") or (
        opts.getString("pc_type") if opts.hasName("pc_type") else "lu"
    )
    if pc_type in FACTORISATIONS:
        return dict(_FACTORISATION_DEFAULTS), pc_type
    return dict(KRYLOV_DEFAULTS), pc_type


def solver_prefix(owner: object, base: str, defaults: dict, user: dict) -> str:
    """A new options prefix for ``owner``'s PETSc objects, holding its own copy of the options.

    The options are ``defaults``, then those in the database under ``base`` (the command line),
    then ``user``. They stay in the database while ``owner`` lives, so that options read at
    set-up (multigrid levels are made then) find them, and no other solver sees them; they are
    removed when ``owner`` is collected.

    Args:
        owner: The solver whose lifetime the options share.
        base: The user's prefix (e.g. ``"diffsolids_"``).
        defaults: Options below the command line's.
        user: Options above it (``petsc_options`` of :class:`~diffsolids.solvers.SolverOptions`).
    """
    prefix = f"{base}s{next(_SOLVER_IDS)}_"
    solvers_own = re.compile(rf"{re.escape(base)}s\d+_")
    given = {
        k[len(base) :]: v
        for k, v in PETSc.Options().getAll().items()
        if k.startswith(base) and not solvers_own.match(k)
    }
    from_base = PETSc.Options(base)
    for k in given:  # read: the originals are used (PETSc reports unused options at exit)
        from_base.getString(k, "")
    merged = {**defaults, **given, **user}
    opts = PETSc.Options(prefix)
    for k, v in merged.items():
        opts[k] = v
    weakref.finalize(owner, delete_options, prefix, list(merged))
    return prefix


def delete_options(prefix: str, names: list[str]) -> None:
    """Remove ``names`` under ``prefix`` from the options database (if PETSc still runs)."""
    if PETSc.Sys.isFinalized():
        return
    opts = PETSc.Options(prefix)
    for k in names:
        if opts.hasName(k):
            opts.delValue(k)


def rigid_body_modes(V: fem.FunctionSpace) -> PETSc.NullSpace:
    """Orthonormal translations and rotations of the vector space ``V`` (AMG's near-null space)."""
    index_map, bs = V.dofmap.index_map, V.dofmap.index_map_bs
    x = V.tabulate_dof_coordinates()[: index_map.size_local]
    n_modes = 3 if bs == 2 else 6
    basis = [la.vector(index_map, bs=bs, dtype=PETSc.ScalarType) for _ in range(n_modes)]
    modes = [b.array[: index_map.size_local * bs].reshape(-1, bs) for b in basis]
    for k in range(bs):  # translations
        modes[k][:, k] = 1.0
    if bs == 2:
        modes[2][:, 0], modes[2][:, 1] = -x[:, 1], x[:, 0]
    else:
        for m, (i, j) in zip(modes[3:], [(0, 1), (1, 2), (2, 0)], strict=True):
            m[:, i], m[:, j] = -x[:, j], x[:, i]
    la.orthonormalize(basis)
    vecs = [la.petsc.create_vector_wrap(b) for b in basis]
    return PETSc.NullSpace().create(vectors=vecs, comm=V.mesh.comm)  # vecs own their arrays


def krylov_solver(comm: MPI.Comm, prefix: str, rtol: float, max_it: int) -> PETSc.KSP:
    """Right-preconditioned GMRES to ``rtol`` in the true residual norm.

    The preconditioner (type and options: ``pc_*``, ``mg_levels_*``, ...) is the one of the
    options under ``prefix`` (a Newton solver's, :func:`solver_prefix`); the Krylov method and
    its tolerances are set here, whatever ``ksp_*`` options the prefix holds.

    Args:
        comm: The communicator.
        prefix: Options prefix of the KSP.
        rtol: Relative tolerance on ||b - A x|| / ||b||.
        max_it: Iteration limit (restart as in :data:`KRYLOV_DEFAULTS`).
    """
    ksp = PETSc.KSP().create(comm)
    ksp.setOptionsPrefix(prefix)
    ksp.setFromOptions()
    ksp.setType("gmres")
    ksp.setGMRESRestart(KRYLOV_DEFAULTS["ksp_gmres_restart"])
    ksp.setPCSide(PETSc.PC.Side.RIGHT)
    ksp.setNormType(PETSc.KSP.NormType.UNPRECONDITIONED)
    ksp.setTolerances(rtol=rtol, atol=0.0, max_it=max_it)
    return ksp


def reason_name(reasons: type, reason: int) -> str | int:
    """The name of a converged reason (``PETSc.SNES.ConvergedReason``, ``PETSc.KSP...``)."""
    names = {v: k for k, v in vars(reasons).items() if isinstance(v, int)}
    return names.get(reason, reason)
