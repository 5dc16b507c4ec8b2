"""A rotor's thrust as nodal loads: a uniform traction over exactly the disc of the patch radius
about the rotor's anchor, on the surface that faces the thrust, integrated over the surface's
linear pieces (a quadratic face split through its mid-edge nodes), so every nodal share is positive.

Why not the quadratic faces' consistent load (the simulator from 71629c6, 2026-11-26 16:17, to
this change): it puts nothing on a whole face's corners and negative pulls on the corners of a
face the disc clips (up to 13.5% of a flower rotor's thrust), and those corners carry the small
end of the HRZ lumped mass: an element-scale wrinkle under every rotor that the explicit step
resolves and the IMUs on rotor patches read (the rod's bend rate against its finite difference:
correlation 0.985-0.988 over seeds, 0.988-0.990 with this load). A positive load lumped like the
mass is what explicit codes use with lumped quadratic tets (Abaqus' C3D10M); both converge to the
same disc traction (validate_fem: both within 0-2% of each other, 12 of 12 within 10%).

Why not equal shares among the patch's vertices (the simulator until 2026-11-26): which vertices
fall inside a patch is the mesh's choice, so an equal share put the load's centroid 1-7 cm off
the anchor on the flower and moved the converged references' compliance by +-4% from one
refinement to the next; an IMU patch that shares vertices with a rotor patch then read the
local indentation under a few nodal loads (the donut's bend +38% against its converged body,
-6% under this load; docs/physics.md). This load converges with the mesh.
"""
from __future__ import annotations

import numpy as np

from sdexp.sim.mesh.surface import boundary_faces, face_normals, patch_faces


def load_faces(elems: np.ndarray, dim: int) -> np.ndarray:
    """The boundary faces a surface load is spread over, as linear pieces: the corner faces of a
    linear mesh; a quadratic mesh's faces split through their mid-edge nodes (four triangles per
    face in 3D, two segments per edge in 2D; quadratic.boundary_subfaces)."""
    faces = boundary_faces(elems[:, :dim + 1])
    if elems.shape[1] == dim + 1:
        return faces
    from sdexp.sim.physics.quadratic import boundary_subfaces
    return boundary_subfaces(faces, elems)


def face_samples(dim: int, m: int = 12) -> np.ndarray:
    """Sample points of a linear face (barycentric, (q, dim)), equal weights: the centroids of an
    m-fold subdivision. Sampling (not exact integration) is what clips a face at the disc's edge;
    the barycentric coordinates are the linear face's shape functions there."""
    if dim == 3:
        bary = []
        for i in range(m):
            for j in range(m - i):
                bary.append([(i + 1 / 3) / m, (j + 1 / 3) / m])             # upright sub-triangles
                if i + j < m - 1:
                    bary.append([(i + 2 / 3) / m, (j + 2 / 3) / m])         # and the inverted ones
        bary = np.array(bary)
        return np.c_[1 - bary.sum(axis=1), bary]
    t = (np.arange(m) + 0.5) / m
    return np.c_[1 - t, t]


def disc_weights(points: np.ndarray, elems: np.ndarray, anchor: np.ndarray, normal: np.ndarray,
                 radius: float) -> tuple[np.ndarray, np.ndarray]:
    """The nodes a unit thrust at ``anchor`` along ``normal`` loads and their shares (summing to 1,
    every one positive): the uniform traction over the surface facing ``normal`` within ``radius``
    of the anchor, integrated over the linear pieces of load_faces. A disc smaller than the faces
    around it (nothing sampled inside) loads the nearest facing face whole."""
    dim = points.shape[1]
    faces = load_faces(elems, dim)
    corners = points[faces]
    reach = np.linalg.norm(corners - corners.mean(axis=1, keepdims=True), axis=2).max()
    near = patch_faces(points, faces, anchor, normal, radius + reach)   # every face the disc touches
    size = np.linalg.norm(face_normals(points, faces[near]), axis=1)     # area (3D), length (2D)
    lam = face_samples(dim)
    pts = np.einsum("qc,kcd->kqd", lam, corners[near])                   # (k, q, dim)
    inside = np.linalg.norm(pts - anchor, axis=2) <= radius
    if not inside.any():
        inside[np.argmin(np.linalg.norm(corners[near].mean(axis=1) - anchor, axis=1))] = True
    load = np.einsum("kq,qn->kn", inside * (size / len(lam))[:, None], lam)
    nodes, idx = np.unique(faces[near], return_inverse=True)
    w = np.bincount(idx.ravel(), load.ravel(), len(nodes))
    keep = w > 0
    return nodes[keep], w[keep] / w.sum()
