"""Row-wise distances of primitive pairs (numpy, vectorised over the rows)."""

import numpy as np

__all__ = ["pair_distances", "point_segment_distances"]


def point_segment_distances(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise distance from p to the segment ab."""
    e = b - a
    ee = np.maximum(np.einsum("ij,ij->i", e, e), np.finfo(float).tiny)
    t = np.clip(np.einsum("ij,ij->i", p - a, e) / ee, 0.0, 1.0)
    return np.linalg.norm(p - a - t[:, None] * e, axis=1)


def pair_distances(P: list[np.ndarray], kind: str) -> np.ndarray:
    """Row-wise distance of vertex-triangle ("fv": p, a, b, c) or edge-edge ("ee") pairs.

    The minimum over the boundary features (point-segment distances), and the distance to the
    plane (between the lines) where the closest point lies inside the triangle (inside both
    edges).
    """
    if kind == "fv":
        p, a, b, c = P
        d = np.minimum.reduce(
            [point_segment_distances(p, u, v) for u, v in ((a, b), (b, c), (c, a))]
        )
        n = np.cross(b - a, c - a)
        nn = np.einsum("ij,ij->i", n, n)
        ok = nn > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            h = np.einsum("ij,ij->i", p - a, n) / nn
            q = p - h[:, None] * n
            inside = ok.copy()
            for u, v in ((a, b), (b, c), (c, a)):
                inside &= np.einsum("ij,ij->i", np.cross(v - u, q - u), n) >= 0
            plane = np.abs(h) * np.sqrt(nn)
        return np.where(inside, np.minimum(d, plane), d)
    a0, a1, b0, b1 = P
    d = np.minimum.reduce(
        [
            point_segment_distances(a0, b0, b1),
            point_segment_distances(a1, b0, b1),
            point_segment_distances(b0, a0, a1),
            point_segment_distances(b1, a0, a1),
        ]
    )
    u, v, w = a1 - a0, b1 - b0, a0 - b0
    uu, uv, vv = (np.einsum("ij,ij->i", x, y) for x, y in ((u, u), (u, v), (v, v)))
    uw, vw = np.einsum("ij,ij->i", u, w), np.einsum("ij,ij->i", v, w)
    den = uu * vv - uv * uv
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (uv * vw - vv * uw) / den
        t = (uu * vw - uv * uw) / den
        inside = (den > 1e-14 * uu * vv) & (s >= 0) & (s <= 1) & (t >= 0) & (t <= 1)
        gap = np.linalg.norm(w + s[:, None] * u - t[:, None] * v, axis=1)
    return np.where(inside, np.minimum(d, gap), d)
