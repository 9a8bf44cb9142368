"""Helpers of the output tests: write an affine motion, read VTX/XDMF back, expected stresses."""

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

import diffsolids as ds
from diffsolids.io import TrajectoryWriter

TIMES = (0.0, 0.5, 1.0)
E, NU = 1000.0, 0.3


def gradient(dim: int) -> np.ndarray:
    """A displacement gradient G (u = s G x) with det(I + s G) > 0 for s <= 2."""
    G = np.array([[0.08, 0.03, -0.02], [-0.05, 0.1, 0.04], [0.02, -0.03, -0.06]])
    return G[:dim, :dim]


def model_on(domain, degree: int, plane_stress: bool = False) -> ds.Model:
    return ds.Model(domain, ds.NeoHookean(E=E, nu=NU), degree=degree, plane_stress=plane_stress)


def write_affine(model: ds.Model, path, extra=None) -> None:
    """u(t) = (1 + t) G x and v = G x at TIMES."""
    G = gradient(model.dim)
    u = model.fields.u
    u.interpolate(lambda x: G @ x[: model.dim])
    with TrajectoryWriter(model, path, extra) as writer:
        for t in TIMES:
            if extra:
                for f in extra:
                    f.x.array[:] = t
            writer.write(t, (1 + t) * u.x.array, u.x.array)


def expected_von_mises(dim: int, scale: float, plane_stress: bool = False) -> float:
    """Von Mises stress of the Neo-Hookean model at F = I + scale G (3x3 Cauchy stress)."""
    F = np.eye(dim) + scale * gradient(dim)
    mu = E / (2 * (1 + NU))
    if dim == 2 and plane_stress:
        lmbda = E * NU / (1 - NU**2)
    else:
        lmbda = E * NU / ((1 + NU) * (1 - 2 * NU))
    J = np.linalg.det(F)
    Finv_T = np.linalg.inv(F).T
    P = mu * (F - Finv_T) + lmbda * np.log(J) * Finv_T
    sigma = np.zeros((3, 3))
    sigma[:dim, :dim] = P @ F.T / J
    if dim == 2 and not plane_stress:
        sigma[2, 2] = lmbda * np.log(J) / J  # plane strain: F_zz = 1
    s = sigma - np.trace(sigma) / 3 * np.eye(3)
    return float(np.sqrt(1.5 * np.sum(s * s)))


def read_xdmf(path: Path) -> dict:
    """Mesh and time series of an XDMF file written by DOLFINx, via ElementTree and h5py."""
    import h5py

    root = ET.parse(path).getroot()
    domain = root.find("Domain")
    grids = domain.findall("Grid")
    mesh_grid = grids[0]

    def dataset(item):
        file_name, name = item.text.strip().split(":")
        return file_name, name

    h5_name, geometry_ds = dataset(mesh_grid.find("Geometry/DataItem"))
    _, topology_ds = dataset(mesh_grid.find("Topology/DataItem"))
    series: dict[str, dict[float, str]] = {}
    for grid in grids[1:]:
        assert grid.get("CollectionType") == "Temporal"
        for step in grid.findall("Grid"):
            t = float(step.find("Time").get("Value"))
            attribute = step.find("Attribute")
            center = attribute.get("Center")
            series.setdefault(attribute.get("Name"), {})[t] = (center, dataset(attribute[0])[1])
    with h5py.File(path.parent / h5_name, "r") as h5:
        result = {
            "geometry": h5[geometry_ds][...],
            "topology": h5[topology_ds][...],
            "fields": {
                name: {t: (center, h5[ds_][...]) for t, (center, ds_) in steps.items()}
                for name, steps in series.items()
            },
        }
    return result


def read_vtx(path: Path) -> dict:
    """Per step: time, and every variable concatenated over the writers' blocks (adios2)."""
    import adios2

    steps = []
    with adios2.FileReader(str(path)) as f:
        names = list(f.available_variables())
        for s in range(f.num_steps()):
            blocks = len(f.engine.blocks_info("geometry", s))
            data = {"time": float(np.ravel(f.read("step", step_selection=[s, 1]))[0])}
            for name in names:
                if name == "step":
                    continue
                parts = [f.read(name, block_id=b, step_selection=[s, 1]) for b in range(blocks)]
                data[name] = np.concatenate([np.atleast_1d(p) for p in parts])
            steps.append(data)
    return {"steps": steps, "names": names}
