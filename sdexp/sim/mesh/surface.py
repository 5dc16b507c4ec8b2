"""Surface helpers on a volume mesh: its boundary faces, their normals, and the patch of faces
around an anchor (where a rotor pushes, where an IMU sits). The drone assembler, the mirror and
the sensors use them; they import nothing of the simulator.
"""
from __future__ import annotations

import numpy as np


def boundary_faces(elems: np.ndarray) -> np.ndarray:
    """Faces that belong to one element only, oriented outward (elements positively oriented)."""
    if elems.shape[1] == 4:
        a, b, c, d = elems.T
        faces = np.concatenate([np.c_[b, c, d], np.c_[a, d, c], np.c_[a, b, d], np.c_[a, c, b]])
    else:
        a, b, c = elems.T
        faces = np.concatenate([np.c_[a, b], np.c_[b, c], np.c_[c, a]])
    key = np.sort(faces, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inverse.ravel()] == 1]


def face_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted outward normals (3D: cross product / 2; 2D: rotated segment)."""
    if faces.shape[1] == 3:
        p0, p1, p2 = (points[faces[:, k]] for k in range(3))
        return 0.5 * np.cross(p1 - p0, p2 - p0)
    d = points[faces[:, 1]] - points[faces[:, 0]]
    return np.c_[d[:, 1], -d[:, 0]]


def patch_faces(points: np.ndarray, faces: np.ndarray, anchor: np.ndarray, normal: np.ndarray,
                radius: float) -> np.ndarray:
    """Indices of boundary faces on the anchor's side (normal within 60 deg) whose centroid
    lies within ``radius``; at least the nearest such face."""
    n = face_normals(points, faces)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    side = n @ normal > 0.5
    dist = np.linalg.norm(points[faces].mean(axis=1) - anchor, axis=1)
    pick = np.flatnonzero(side & (dist <= radius))
    if len(pick) == 0:
        cand = np.flatnonzero(side)
        pick = cand[[np.argmin(dist[cand])]] if len(cand) else np.array([], dtype=int)
    return pick


def enclosed_volume(points: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume (3D) or area (2D) a closed boundary encloses: > 0 when it faces outward."""
    return float(_moments(points, faces)[0])


def enclosed_centroid(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Centroid of the solid (3D) or region (2D) a closed, outward boundary encloses."""
    size, first = _moments(points, faces)
    return first / size


def encloses(points: np.ndarray, faces: np.ndarray, query: np.ndarray) -> bool:
    """``query`` lies inside the closed boundary: its winding number, the solid angle (3D) or
    angle (2D) the faces subtend from it over the full one, is about 1 (0 outside)."""
    corners = points[faces] - query                    # (m, dim, dim)
    if faces.shape[1] == 2:
        a, b = corners[:, 0], corners[:, 1]
        turn = np.arctan2(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0], np.einsum("ij,ij->i", a, b)).sum()
        return bool(turn > np.pi)
    a, b, c = corners[:, 0], corners[:, 1], corners[:, 2]   # Van Oosterom and Strackee's solid angle
    la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
    den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la \
        + np.einsum("ij,ij->i", c, a) * lb
    return bool(2 * np.arctan2(np.einsum("ij,ij->i", a, np.cross(b, c)), den).sum() > 2 * np.pi)


def _moments(points: np.ndarray, faces: np.ndarray) -> tuple[float, np.ndarray]:
    """Volume and first moment by the divergence theorem: a signed simplex from the origin to
    each face (a tet in 3D, a triangle in 2D), its centroid at its corners' mean."""
    corners = points[faces]                            # (m, dim, dim)
    size = np.linalg.det(corners) / (6.0 if faces.shape[1] == 3 else 2.0)
    centroid = corners.sum(axis=1) / (faces.shape[1] + 1)
    return size.sum(), (size[:, None] * centroid).sum(axis=0)
