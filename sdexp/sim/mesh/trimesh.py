"""Triangle meshes of 2D drone outlines (Shewchuk's Triangle, constrained quality Delaunay)."""
from __future__ import annotations

import numpy as np
import triangle

MIN_ANGLE_DEG = 30


def _split_segments(vertices: np.ndarray, segments: np.ndarray, edge_length: float):
    """Subdivide every segment into pieces no longer than ``edge_length``.

    Triangle would split long boundary segments anyway, but only as far as the area and angle
    bounds force it; splitting up front gives the boundary the same resolution as the interior,
    which is what the rotor and IMU patches bind to.
    """
    points = [vertices]
    new_segments = []
    n = len(vertices)
    for a, b in segments:
        length = np.linalg.norm(vertices[b] - vertices[a])
        pieces = max(1, int(np.ceil(length / edge_length - 1e-9)))
        inner = vertices[a] + np.outer(np.arange(1, pieces) / pieces, vertices[b] - vertices[a])
        chain = [a, *range(n, n + len(inner)), b]
        points.append(inner)
        n += len(inner)
        new_segments.extend(zip(chain[:-1], chain[1:]))
    return np.concatenate(points), np.array(new_segments, dtype=np.int32).reshape(-1, 2)


def tri_mesh(vertices, segments, holes, edge_length: float) -> tuple[np.ndarray, np.ndarray]:
    """Mesh the region bounded by ``segments`` with triangles of edge length about ``edge_length``.

    ``holes`` holds one point inside each hole. Returns ``(points (n, 2) float64, tris (m, 3)
    int32)``, every triangle counter-clockwise and every point used by a triangle.
    """
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 2)
    segments = np.asarray(segments, dtype=np.int64).reshape(-1, 2)
    holes = np.asarray(holes, dtype=np.float64).reshape(-1, 2)
    if not edge_length > 0:
        raise ValueError(f"edge_length = {edge_length!r}: must be > 0")
    if len(segments) < 3 or segments.min() < 0 or segments.max() >= len(vertices):
        raise ValueError("segments must close a polygon: at least 3 rows of valid vertex indices")
    points, segs = _split_segments(vertices, segments, edge_length)
    pslg = {"vertices": points, "segments": segs}
    if len(holes):
        pslg["holes"] = holes
    max_area = np.sqrt(3) / 4 * edge_length ** 2
    # Fixed-point notation: Triangle's option parser does not read exponents.
    out = triangle.triangulate(pslg, f"pq{MIN_ANGLE_DEG}a{max_area:.15f}")
    if "triangles" not in out or len(out["triangles"]) == 0:
        raise ValueError("the outline encloses no area (are the hole points inside the outline?)")
    tris = out["triangles"].astype(np.int64)
    used, tris = np.unique(tris, return_inverse=True)
    tris = tris.reshape(-1, 3)
    pts = out["vertices"][used].astype(np.float64)
    a, b, c = pts[tris[:, 0]], pts[tris[:, 1]], pts[tris[:, 2]]
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    tris[cross < 0] = tris[cross < 0][:, [0, 2, 1]]
    return pts, tris.astype(np.int32)
