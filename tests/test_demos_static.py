"""Smoke tests of the static shape-optimisation demos, their meshes, run_all and check_gradients.

Each demo runs in-process at its ``--tiny`` size: the objective must decrease and the
invariants hold (no accepted iterate with inverted cells or a self-intersecting boundary; in
the contact scene no intersecting rest or deformed configuration); the outcome thresholds of
the default size (stress reductions, recovery error) are not asserted here.
"""

import json
import textwrap
from pathlib import Path

import ipctk
import numpy as np
import pytest
from demo_modules import load_demo
from mpi4py import MPI

from diffsolids.errors import InvertedElementError
from diffsolids.mesh import from_geo

ROOT = Path(__file__).resolve().parents[1]
INVARIANTS = {
    "bridge_fabricated": [
        "iterates with inverted cells",
        "iterates with self-intersecting boundaries",
    ],
    "bridge_stress": ["iterates with inverted cells", "iterates with self-intersecting boundaries"],
    "beam3d_stress": ["iterates with inverted cells", "iterates with self-intersecting boundaries"],
    "interlocking": [
        "iterates with inverted cells",
        "iterates with intersecting rest shapes",
        "iterates with intersecting deformed shapes",
    ],
}


def _area(domain, facet_tag) -> float:
    """Total measure of the facets with a tag (serial mesh)."""
    import dolfinx.mesh

    mesh = domain.mesh
    fdim = mesh.topology.dim - 1
    nodes = dolfinx.mesh.entities_to_geometry(mesh, fdim, domain.facets_of(facet_tag))
    x = mesh.geometry.x[nodes]
    if fdim == 1:
        return float(np.linalg.norm(x[:, 1] - x[:, 0], axis=1).sum())
    return float(0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1).sum())


# -- the demos ---------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(INVARIANTS))
def test_static_demo_tiny(name, tmp_path):
    report = load_demo(name).main(["--tiny", "--out", str(tmp_path), "--no-plot"])
    outcomes = {o.name: o for o in report.outcomes}
    assert outcomes["objective decreased"].passed
    for required in INVARIANTS[name]:
        assert outcomes[required].passed, outcomes[required]
    assert report.final_objective < report.initial_objective
    assert report.iterations >= 1
    # the tiny size checks only the invariants: the default outcome is not claimed
    assert set(outcomes) == {"objective decreased", *INVARIANTS[name]}
    for path in report.extra["files"]:
        assert Path(path).exists(), path
    names = [Path(p).name for p in report.extra["files"]]
    assert any(n.startswith("initial") for n in names) and any(n.startswith("final") for n in names)
    saved = json.loads((tmp_path / "result.json").read_text())
    assert saved["final_objective"] == pytest.approx(report.final_objective)
    assert saved["size"] == "tiny"


# -- meshes ------------------------------------------------------------------------------------
def test_bridge_geo_tags_and_dimensions():
    domain = from_geo(ROOT / "meshes" / "bridge.geo", MPI.COMM_SELF, numbers={"h": 0.2})
    assert domain.names == {
        "bridge": 1,
        "fixed_left": 1,
        "fixed_right": 2,
        "load_1": 3,
        "load_2": 4,
        "load_3": 5,
    }
    lo, hi = domain.bounding_box()
    assert np.allclose(lo, [0.0, 0.0]) and np.allclose(hi, [10.0, 2.0])
    for side in ("fixed_left", "fixed_right"):
        assert _area(domain, side) == pytest.approx(2.0, rel=1e-12)
    x = domain.mesh.geometry.x
    centres = []
    for k in (1, 2, 3):
        load = f"load_{k}"
        assert _area(domain, load) == pytest.approx(1.0, rel=1e-12)  # segments of width 1
        import dolfinx.mesh

        nodes = dolfinx.mesh.entities_to_geometry(domain.mesh, 1, domain.facets_of(load))
        assert np.allclose(x[nodes, 1], 0.0)  # on the underside
        centres.append(x[nodes, 0].mean())
    # one load under the middle of each opening: openings 2.3 wide, verticals 0.35, ends 1.2
    assert np.allclose(centres, [2.35, 5.0, 7.65], atol=1e-9)
    # area: plate minus three 2.3 x 1.35 openings with corners rounded (r = 0.12)
    exact = 20.0 - 3 * (2.3 * 1.35 - (4 - np.pi) * 0.12**2)
    cells = domain.mesh.geometry.dofmaps[0]
    p = x[cells][:, :, :2]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()
    assert area == pytest.approx(exact, rel=5e-3)  # the arcs are polygons


def test_beam3d_geo_tags_and_support_patch():
    numbers = {"h": 0.1, "S": 0.4}
    domain = from_geo(ROOT / "meshes" / "beam3d.geo", MPI.COMM_SELF, numbers=numbers)
    assert domain.names == {"beam": 1, "support": 1, "load_left": 2, "load_right": 3}
    lo, hi = domain.bounding_box()
    assert np.allclose(lo, 0.0) and np.allclose(hi, [2.0, 0.25, 0.25])
    assert _area(domain, "support") == pytest.approx(0.4 * 0.25, rel=1e-12)
    assert _area(domain, "load_left") == pytest.approx(0.25 * 0.25, rel=1e-12)
    assert _area(domain, "load_right") == pytest.approx(0.25 * 0.25, rel=1e-12)
    import dolfinx.mesh

    nodes = dolfinx.mesh.entities_to_geometry(domain.mesh, 2, domain.facets_of("support"))
    x = domain.mesh.geometry.x[nodes]
    assert np.allclose(x[..., 2], 0.0) and np.all(np.abs(x[..., 0] - 1.0) <= 0.2 + 1e-12)


def _body_distance(domain) -> tuple[float, bool]:
    """Smallest distance between the boundaries of bodies 1 and 2, and whether they intersect."""
    from diffsolids.contact.geometry.surface import CollisionSurface
    from diffsolids.model import LinearElastic, Model

    model = Model(domain, LinearElastic(E=1.0, nu=0.3))
    surface = CollisionSurface(domain, model.V)
    X = surface.rest_positions
    edges = surface.edges[surface.primitive_body == 1]
    p = X[surface.body == 2][:, None, :]
    a, b = X[edges[:, 0]], X[edges[:, 1]]
    t = np.clip(np.sum((p - a) * (b - a), axis=2) / np.sum((b - a) ** 2, axis=1), 0, 1)
    d = np.linalg.norm(p - (a + t[..., None] * (b - a)), axis=2).min()
    return float(d), bool(ipctk.has_intersections(surface.mesh, np.asfortranarray(X)))


@pytest.mark.parametrize("gap", [0.01, 0.03])
def test_interlocking_geo_keeps_the_gap(gap):
    domain = from_geo(
        ROOT / "meshes" / "interlocking.geo", MPI.COMM_SELF, numbers={"h": 0.15, "G": gap}
    )
    assert domain.names == {"bottom": 1, "top": 2, "fixed": 1, "load": 2}
    assert domain.body_ids == [1, 2]
    distance, intersecting = _body_distance(domain)
    assert distance == pytest.approx(gap, rel=1e-9) and not intersecting
    assert _area(domain, "fixed") == pytest.approx(4.0) and _area(domain, "load") == pytest.approx(
        4.0
    )


def test_interlocking_tie_moves_the_interface_together():
    demo = load_demo("interlocking")
    domain = from_geo(ROOT / "meshes" / "interlocking.geo", MPI.COMM_SELF, numbers={"h": 0.2})
    problem = demo.Problem()
    rf = problem(domain)
    parts = problem.parts[id(rf)]
    T, tied = parts["tie"], parts["tied"]
    assert tied > 10
    rows = np.asarray(T.sum(axis=1)).ravel()
    assert np.allclose(rows, 1.0)  # every design parameter is a convex combination
    assert np.linalg.matrix_rank(T.toarray()) == T.shape[1]
    # a uniform translation of the reduced parameters translates every design vertex: the gap
    # between the parts stays what it is in the mesh
    dim = 2
    q = np.tile([0.004, -0.003], T.shape[1] // dim)
    assert np.allclose((T @ q).reshape(-1, dim), [0.004, -0.003])
    control = rf.controls.controls[0]
    before, _ = _body_distance(domain)
    control.assign(q)
    after, intersecting = _body_distance(domain)
    control.assign(np.zeros_like(q))
    assert after == pytest.approx(before, rel=1e-6) and not intersecting
    # the preconditioner is symmetric positive definite
    inner = demo.TiedInnerProduct(problem, rf)
    rng = np.random.default_rng(3)
    a, b = rng.standard_normal((2, T.shape[1]))
    assert a @ inner(b) == pytest.approx(b @ inner(a), rel=1e-8)
    assert a @ inner(a) > 0 and b @ inner(b) > 0


def test_interlocking_parts_refuse_to_overlap():
    import scipy.sparse as sp

    from diffsolids.controls import ShapeControl
    from diffsolids.model import Model, NeoHookean
    from diffsolids.optimize import BoundaryIntersection

    domain = from_geo(ROOT / "meshes" / "interlocking.geo", MPI.COMM_SELF, numbers={"h": 0.2})
    model = Model(domain, NeoHookean(E=1.0, nu=0.3))
    # one parameter: vertical rest displacement of every vertex of the top part
    cells = domain.mesh.geometry.dofmaps[0][domain.cells_of("top")]
    top = np.unique(domain.mesh.geometry.input_global_indices[np.unique(cells)])
    n = domain.mesh.geometry.index_map().size_global
    P = sp.csr_matrix((np.ones(len(top)), (2 * top + 1, np.zeros(len(top)))), shape=(2 * n, 1))
    control = ShapeControl(model, linear_map=P, refuse_intersections=True)
    control.assign(np.array([0.005]))  # up by half the gap: fine
    assert not BoundaryIntersection(model).intersects()
    with pytest.raises(InvertedElementError, match="folds the boundary"):
        control.assign(np.array([-0.05]))  # down by five gaps: the parts overlap
    control.assign(np.array([0.0]))
    assert not BoundaryIntersection(model).intersects()


# -- run_all ---------------------------------------------------------------------------------
def test_run_all_discovers_the_optimisation_demos():
    run_all = load_demo("run_all")
    names = run_all.discover()
    assert {"bridge_fabricated", "bridge_stress", "beam3d_stress", "interlocking"} <= set(names)
    assert not {"beam_swing", "common", "shape_tools", "run_all", "check_gradients"} & set(names)
    with pytest.raises(SystemExit, match="no demo named"):
        run_all.discover(["no_such_demo"])


_FAKE = """
import argparse, json, sys
from pathlib import Path

def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("--out", type=Path)
    p.add_argument("--check", action="store_true")
    p.add_argument("--tiny", action="store_true")
    args = p.parse_args(argv)
    {body}

if __name__ == "__main__":
    main()
"""


def _fake_result(passed: bool) -> str:
    result = {
        "demo": "fake",
        "initial_objective": 2.0,
        "final_objective": 1.0,
        "iterations": 3,
        "forward_seconds": 0.1,
        "gradient_seconds": 0.05,
        "outcomes": [{"name": "x", "value": 1.0, "threshold": 2.0, "passed": passed}],
    }
    code = (
        "args.out.mkdir(parents=True, exist_ok=True); "
        f"(args.out / 'result.json').write_text(json.dumps({result!r}))"
    )
    return code + ("" if passed else "; sys.exit(1)")


def test_run_all_reports_outcomes_failures_and_crashes(tmp_path, capsys):
    run_all = load_demo("run_all")
    demos = tmp_path / "demos"
    demos.mkdir()
    bodies = {
        "good": _fake_result(True),
        "short": _fake_result(False),
        "broken": "raise RuntimeError('boom')",
    }
    for name, body in bodies.items():
        (demos / f"{name}.py").write_text(textwrap.dedent(_FAKE).replace("{body}", body))
    (demos / "helpers.py").write_text("X = 1\n")  # no main: not a demo
    assert run_all.discover(directory=demos) == ["broken", "good", "short"]
    out = tmp_path / "out"
    argv = ["--demos-dir", str(demos), "--out", str(out)]
    assert run_all.main([*argv, "good"]) == 0
    assert run_all.main(argv) == 1
    text = capsys.readouterr().out
    rows = [line.split() for line in text.splitlines()]
    status = {r[0]: r[1] for r in rows if len(r) > 1 and r[0] in bodies}
    assert status == {"good": "ok", "short": "FAIL", "broken": "CRASH"}
    assert "2 of 3 demos failed" in text
    # a crash leaves no stale result behind: the old result.json of 'good' would be reported
    (out / "broken" / "result.json").write_text((out / "good" / "result.json").read_text())
    row = run_all.run_one("broken", out / "broken", [], 1, 60.0, demos)
    assert run_all.status(row) == "CRASH"


# -- check_gradients ------------------------------------------------------------------------------
def test_check_gradients_smoke(capsys):
    module = load_demo("check_gradients")
    rows = module.main(["--scene", "static-shape", "--tiny"])
    printed = capsys.readouterr().out
    assert "all rows within tolerance" in printed
    assert rows[-1].control == "along the gradient"
    assert len(rows) >= 3
    for row in rows:
        assert row.relative_error <= 1e-6, row
        assert row.taylor_rate >= 1.9, row
        assert row.adjoint != 0.0


def test_check_gradients_detects_a_wrong_gradient():
    module = load_demo("check_gradients")
    rf, sizes = module.build_scene("static-shape", MPI.COMM_SELF, tiny=True)
    derivative = rf.derivative
    rf.derivative = lambda: 1.01 * derivative()  # 1 % too large
    rows = module.check(rf, sizes)
    assert all(0.005 < r.relative_error < 0.02 for r in rows)
    assert all(r.taylor_rate < 1.5 for r in rows)  # the remainder is first order
