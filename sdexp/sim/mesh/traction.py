"""A rotor's thrust as nodal loads: a uniform traction over exactly the disc of the patch radius
about the rotor's anchor, on the surface that faces the thrust, integrated with the faces' own
shape functions (the consistent load of the elements, linear or quadratic).

Why not equal shares among the patch's vertices (the simulator until 2026-11-26): which vertices
fall inside a patch is the mesh's choice, so an equal share put the load's centroid 1-7 cm off
the anchor on the flower and moved the converged references' compliance by +-4% from one
refinement to the next; an IMU patch that shares vertices with a rotor patch then read the
local indentation under a few nodal loads (the donut's bend +38% against its converged body,
-6% under this load; docs/physics.md). This load converges with the mesh.

Why not a positive load integrated over the faces' linear pieces (tried 2026-11-26 in d22a22b,
reverted in 5da9fdc): the consistent load pulls negatively on a clipped face's corners (up to 13.5% of a
flower rotor's thrust, on light HRZ nodes), which a lumped positive load avoids, but the IMU
bend the controller reads then converges worse: the engine's reference meshes (r = 1, 1.5, 2,
3, 4 x finer) read 0.1002 / 0.1047 / 0.0907 / 0.0875 / 0.0929 deg under it against 0.1037 /
0.1083 / 0.1024 / 0.0994 / 0.0989 under this load, and its validate_fem bend error went +5.0% ->
+14.7% (the donut's bend reference stopped converging). Compliance and frequencies agree
within 0-2% between the two.
"""
from __future__ import annotations

import numpy as np

from sdexp.sim.mesh.surface import boundary_faces, face_normals, patch_faces


def faces_with_mid_nodes(elems: np.ndarray, dim: int) -> np.ndarray:
    """The corner faces of the boundary (k, 3 | 2) and, for quadratic elements, their mid-edge
    nodes after them: (a, b, c, ab, bc, ca) in 3D, (a, b, ab) in 2D."""
    faces = boundary_faces(elems[:, :dim + 1])
    if elems.shape[1] == dim + 1:
        return faces
    from sdexp.sim.physics.quadratic import mid_nodes
    mid = mid_nodes(elems)
    pairs = [(0, 1), (1, 2), (2, 0)] if dim == 3 else [(0, 1)]
    return np.c_[faces, np.stack([mid(faces[:, i], faces[:, j]) for i, j in pairs], axis=1)]


def face_shapes(dim: int, quadratic: bool, m: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """Sample points of a face (barycentric, (q, dim)), equal weights, centroids of an m-fold
    subdivision; and the face's shape functions there (q, nodes), in faces_with_mid_nodes' order.
    Sampling (not exact integration) is what clips a face at the disc's edge."""
    if dim == 3:
        bary = []
        for i in range(m):
            for j in range(m - i):
                bary.append([(i + 1 / 3) / m, (j + 1 / 3) / m])             # upright sub-triangles
                if i + j < m - 1:
                    bary.append([(i + 2 / 3) / m, (j + 2 / 3) / m])         # and the inverted ones
        bary = np.array(bary)
        lam = np.c_[1 - bary.sum(axis=1), bary]
        if not quadratic:
            return lam, lam
        return lam, np.c_[lam * (2 * lam - 1), 4 * lam[:, 0] * lam[:, 1], 4 * lam[:, 1] * lam[:, 2],
                          4 * lam[:, 2] * lam[:, 0]]
    t = (np.arange(m) + 0.5) / m
    lam = np.c_[1 - t, t]
    return lam, lam if not quadratic else np.c_[lam * (2 * lam - 1), 4 * lam[:, 0] * lam[:, 1]]


def disc_weights(points: np.ndarray, elems: np.ndarray, anchor: np.ndarray, normal: np.ndarray,
                 radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The nodes a unit thrust at ``anchor`` along ``normal`` loads and their shares (summing to 1):
    the uniform traction over the surface facing ``normal`` within ``radius`` of the anchor. A
    disc smaller than the faces around it (nothing sampled inside) loads the nearest facing face
    whole. Consistent quadratic loads put little or nothing on a face's corners and can be
    negative there on a clipped face; the shares' centroid is the disc's."""
    dim = points.shape[1]
    faces = faces_with_mid_nodes(elems, dim)
    corner_faces = faces[:, :dim]
    corners = points[corner_faces]
    reach = np.linalg.norm(corners - corners.mean(axis=1, keepdims=True), axis=2).max()
    near = patch_faces(points, corner_faces, anchor, normal, radius + reach)   # every face the disc touches
    size = np.linalg.norm(face_normals(points, corner_faces[near]), axis=1)   # area (3D), length (2D)
    lam, shape = face_shapes(dim, faces.shape[1] > dim)
    pts = np.einsum("qc,kcd->kqd", lam, corners[near])                         # (k, q, dim)
    inside = np.linalg.norm(pts - anchor, axis=2) <= radius
    if not inside.any():
        inside[np.argmin(np.linalg.norm(corners[near].mean(axis=1) - anchor, axis=1))] = True
    load = np.einsum("kq,qn->kn", inside * (size / len(lam))[:, None], shape)
    nodes, idx = np.unique(faces[near], return_inverse=True)
    w = np.bincount(idx.ravel(), load.ravel(), len(nodes))
    keep = w != 0
    return nodes[keep], w[keep] / w.sum()
