"""Quadratic elements: 10-node tetrahedra (3D) and 6-node triangles (2D), co-rotated.

Why: linear tets carry a constant strain, so a plate bends only by shearing its elements and
is 1.5-2x too stiff with the two or three elements the drones have through their thickness
(README "Physics validation"). A quadratic element carries a linearly varying strain and bends
with a single layer.

Nodes (VTK order, so meshio writes them as they are): the corners first, then one node at
the middle of each edge; 3D edges (0,1) (1,2) (0,2) (0,3) (1,3) (2,3), 2D (0,1) (1,2) (0,2).
The mid-edge nodes of a mesh are numbered after all corners, so a corner keeps its index from
the linear mesh.

Shape functions in barycentric coordinates L: corner N_j = L_j (2 L_j - 1), edge
N_ij = 4 L_i L_j. Rest elements are straight-sided, so grad L_j is constant per element: the rows
of Dm^-1 (and grad L_0 = -sum). The deformation gradient at a quadrature point is then
F = sum_j y_j (x) grad L_j with  y_j = (4 L_j - 1) x_j + 4 sum_{i != j} L_i x_ij,
i.e. F = [y_1 - y_0, y_2 - y_0, y_3 - y_0] Dm^-1: the linear element's formula on "effective"
corner positions, so an element stores what a linear one does (Dm^-1, volume).
With g_j = P grad L_j the nodal forces of one point (weight w) are
corner j: -w V (4 L_j - 1) g_j,  edge ij: -w V 4 (L_i g_j + L_j g_i).

Quadrature: the 4-point (3D) and 3-point (2D) rules of degree 2, exact for the P2 stiffness
(products of linear gradients).

Rotation (co-rotation, Mueller & Gross 2004, generalised): the polar rotation of F at every
quadrature point, warm-started like the linear elements' (``ROTATION = "point"``), so the stress
is exactly frame-indifferent and the forces carry no torque; per element from the corner
nodes was measured beside it (README "Physics validation").

Mass: HRZ lumping (Hinton, Rock & Zienkiewicz 1976): the consistent mass matrix's diagonal
scaled to the element mass. Row sums of the 10-node consistent mass are negative at the
corners (-m/20) and would make an explicit step impossible; HRZ gives corners m/36 and edges
4 m/27 (3D), corners m/19 and edges 16 m/57 (2D): all positive.
"""
from __future__ import annotations

import numpy as np

ROTATION_PER_POINT = True   # see the module docstring (the kernels: sdexp.sim.physics.reference, forces.h)

EDGES_3D = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
EDGES_2D = np.array([[0, 1], [1, 2], [0, 2]])

# degree-2 rules: barycentric coordinates of the points (weights equal: 1/4 and 1/3)
_A, _B = 0.5854101966249685, 0.1381966011250105
QUAD_3D = np.array([[_A, _B, _B, _B], [_B, _A, _B, _B], [_B, _B, _A, _B], [_B, _B, _B, _A]])
QUAD_2D = np.array([[2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]])

# HRZ lumped mass of a straight element, as a fraction of its mass: corners, then edges
HRZ_3D = np.r_[np.full(4, 1 / 36), np.full(6, 4 / 27)]
HRZ_2D = np.r_[np.full(3, 1 / 19), np.full(3, 16 / 57)]


def nodes_per_element(dim: int, order: int) -> int:
    return (dim + 1) if order == 1 else (10 if dim == 3 else 6)


def quadratic_mesh(points: np.ndarray, elems: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A linear mesh (points, elems (ne, dim+1)) with a node added at the middle of every edge:
    (points + edge midpoints, elems (ne, 10 | 6)). Corners keep their indices."""
    points = np.asarray(points, dtype=np.float64)
    elems = np.asarray(elems)
    dim = points.shape[1]
    local = EDGES_3D if dim == 3 else EDGES_2D
    pairs = np.sort(elems[:, local], axis=2).reshape(-1, 2)          # (ne * n_edges, 2)
    unique, inverse = np.unique(pairs, axis=0, return_inverse=True)
    mid = 0.5 * (points[unique[:, 0]] + points[unique[:, 1]])
    edge_nodes = (len(points) + inverse.ravel()).reshape(len(elems), len(local))
    return np.vstack([points, mid]), np.ascontiguousarray(np.c_[elems, edge_nodes], dtype=np.int32)


def lumped_mass(n_nodes: int, elems: np.ndarray, element_mass: np.ndarray) -> np.ndarray:
    """HRZ-lumped nodal masses of quadratic elements (elems (ne, 10 | 6))."""
    share = HRZ_3D if elems.shape[1] == 10 else HRZ_2D
    mass = np.zeros(n_nodes)
    np.add.at(mass, elems.ravel(), (element_mass[:, None] * share[None, :]).ravel())
    return mass


def mid_nodes(elems: np.ndarray):
    """For quadratic elems (ne, 10 | 6): mid(a, b), the mid-edge nodes of the corner pairs
    (a[i], b[i]) (arrays of corner indices, either order)."""
    local = EDGES_3D if elems.shape[1] == 10 else EDGES_2D
    ends = np.sort(elems[:, local], axis=2).reshape(-1, 2)
    lookup = dict(zip(map(tuple, ends.tolist()), elems[:, local.max() + 1:].ravel().tolist()))

    def mid(a, b):
        return np.array([lookup[(min(p, q), max(p, q))] for p, q in zip(a, b)], dtype=np.asarray(a).dtype)
    return mid


def boundary_subfaces(corner_faces: np.ndarray, elems: np.ndarray) -> np.ndarray:
    """The boundary of a quadratic mesh as linear pieces through its mid-edge nodes: each corner
    triangle (a, b, c) as four (3D), each corner segment (a, b) as two (2D), orientation kept.
    Rotor normals, IMU frames and surface areas then see the mid-edge nodes too."""
    mid = mid_nodes(elems)
    if corner_faces.shape[1] == 2:
        a, b = corner_faces.T
        m = mid(a, b)
        return np.concatenate([np.c_[a, m], np.c_[m, b]])
    a, b, c = corner_faces.T
    ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
    return np.concatenate([np.c_[a, ab, ca], np.c_[ab, b, bc], np.c_[ca, bc, c], np.c_[ab, bc, ca]])
