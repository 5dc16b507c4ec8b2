"""Points put onto a body's surface: a listed rotor or IMU onto the nearest surface that faces
its way, a planar point of the placement rule straight up onto the upper surface (as the
built-in drones' anchors are lifted, sdexp.sim.mesh.shapes)."""
from __future__ import annotations

import numpy as np

from sdexp.sim.mesh.surface import face_normals, patch_faces

FACING = 0.5   # cos 60 deg: a face "faces" a direction within 60 deg of it, as a rotor patch does


def _closest_on_segments(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-300), 0.0, 1.0)
    return a + t[:, None] * d


def closest_points(points: np.ndarray, faces: np.ndarray, query: np.ndarray) -> np.ndarray:
    """The point of each face (triangle or segment) nearest to ``query``, shape (m, dim)."""
    corners = [points[faces[:, k]] for k in range(faces.shape[1])]
    q = np.broadcast_to(query, corners[0].shape)
    if faces.shape[1] == 2:
        return _closest_on_segments(q, *corners)
    a, b, c = corners
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    proj = q - np.einsum("ij,ij->i", q - a, n)[:, None] * n   # onto the plane
    inside = np.ones(len(faces), dtype=bool)
    for p0, p1 in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(p1 - p0, proj - p0), n) >= 0
    best = proj.copy()
    dist = np.where(inside, np.linalg.norm(proj - q, axis=1), np.inf)
    for p0, p1 in ((a, b), (b, c), (c, a)):   # outside the triangle: the nearest edge point
        e = _closest_on_segments(q, p0, p1)
        de = np.linalg.norm(e - q, axis=1)
        better = ~inside & (de < dist)
        best[better], dist[better] = e[better], de[better]
    return best


def snap(points: np.ndarray, faces: np.ndarray, query: np.ndarray, direction: np.ndarray,
         radius: float) -> tuple[np.ndarray, np.ndarray, float]:
    """``query`` moved onto the nearest surface that faces ``direction``: that point, the
    surface's unit outward normal there (area-weighted over the faces within ``radius``, the
    patch a rotor or IMU binds), and how far it moved. Moving to the nearest point of a face
    is moving along its normal, unless the point lies beyond the face's edge."""
    n = face_normals(points, faces)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    facing = np.flatnonzero(n @ direction > FACING)
    if len(facing) == 0:
        return query, direction, np.inf
    near = closest_points(points, faces[facing], query)
    dist = np.linalg.norm(near - query, axis=1)
    k = int(np.argmin(dist))
    anchor = near[k]
    return anchor, patch_normal(points, faces, anchor, n[facing[k]], radius), float(dist[k])


def patch_normal(points: np.ndarray, faces: np.ndarray, anchor: np.ndarray, direction: np.ndarray,
                 radius: float) -> np.ndarray:
    """Unit area-weighted normal of the faces a patch at ``anchor`` binds (sdexp.sim.mesh.surface)."""
    total = face_normals(points, faces[patch_faces(points, faces, anchor, direction, radius)]).sum(axis=0)
    return total / np.linalg.norm(total)


def lift3(points: np.ndarray, faces: np.ndarray, xz: np.ndarray) -> np.ndarray | None:
    """The highest point of the surface over the planar point ``xz`` (on an upward face), or
    None where the vertical line misses the body."""
    up = faces[face_normals(points, faces)[:, 1] > 0]
    a, b, c = (points[up[:, k]][:, [0, 2]] for k in range(3))
    det = (b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]
    r = xz - a
    u = (r[:, 0] * (c - a)[:, 1] - r[:, 1] * (c - a)[:, 0]) / det
    v = ((b - a)[:, 0] * r[:, 1] - (b - a)[:, 1] * r[:, 0]) / det
    tol = 1e-9
    hit = (u >= -tol) & (v >= -tol) & (u + v <= 1 + tol)
    if not hit.any():
        return None
    y = (1 - u - v) * points[up[:, 0], 1] + u * points[up[:, 1], 1] + v * points[up[:, 2], 1]
    return np.array([xz[0], y[hit].max(), xz[1]])
