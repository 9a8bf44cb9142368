"""Adjoint gradients of static solves vs central finite differences and Taylor tests.

The matrix of cases (tests/gradient_scenes.py) is a covering design over control types,
integrators, constitutive laws, damping, dimension and degree; test_design_covers checks it.
"""

import pytest
from gradient_scenes import (
    DYNAMIC_CASES,
    FD_TOLERANCE,
    INTEGRATORS,
    SCENES,
    STATIC_CASES,
    TAYLOR_MIN_RATE,
    check_case,
    control_kind,
)


@pytest.mark.parametrize("case", STATIC_CASES, ids=lambda c: c.id)
def test_static_gradient(case):
    check_case(case)


def test_design_covers():
    """Every control with every integrator; every physics combination; 2D plane stress/strain."""
    dynamic_kinds = {
        "shape-all", "shape-boundary", "shape-linear-map", "young-field-log", "young-cg1",
        "young-bodies", "poisson-field", "mu-field-log", "lmbda-bodies", "psi-bodies",
        "phi-field", "density-field", "traction-scale", "gravity-uniform", "initial-u0",
        "initial-v0", "rigid-velocity", "dirichlet", "dirichlet-per-step",
    }  # fmt: skip
    static_kinds = dynamic_kinds - {
        "psi-bodies",
        "phi-field",
        "initial-u0",
        "initial-v0",
        "rigid-velocity",
    }
    covered = {}
    for case in STATIC_CASES + DYNAMIC_CASES:
        family = "static" if case.integrator.startswith("static") else case.integrator
        for key in case.controls:
            covered.setdefault(family, set()).add(control_kind(key, SCENES[case.scene]))
    assert covered["static"] >= static_kinds
    for family in ("bdf1", "bdf2", "bdf3", "bdf6"):
        assert covered[family] >= dynamic_kinds, family
    dynamic = {SCENES[c.scene] for c in DYNAMIC_CASES}
    static = {SCENES[c.scene] for c in STATIC_CASES}
    combos = {(s.law, s.damping, s.dim, s.degree) for s in dynamic}
    assert len(combos) == 16
    assert len({(s.law, s.dim, s.degree) for s in static}) == 8
    two_d = [s for s in dynamic | static if s.dim == 2]
    assert {s.plane_stress for s in two_d} == {True, False}
    assert {s.lame for s in dynamic} == {True, False}
    assert set(INTEGRATORS) == {c.integrator for c in STATIC_CASES + DYNAMIC_CASES}
    assert FD_TOLERANCE <= 1e-6 and TAYLOR_MIN_RATE >= 1.9
