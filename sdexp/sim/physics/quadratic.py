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

import numba as nb
import numpy as np

ROTATION_PER_POINT = True   # see the module docstring

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


# --------------------------------------------------------------------------------------------
# numba reference kernels (kernels.c runs the same arithmetic; these are its fallback and the
# yardstick of its test)
# --------------------------------------------------------------------------------------------

@nb.njit(inline="always")
def rotation(qw, qx, qy, qz, real):
    """Row-major entries of the rotation matrix of a unit quaternion, in ``real`` arithmetic."""
    one, two = real(1.0), real(2.0)
    return (one - two * (qy * qy + qz * qz), two * (qx * qy - qw * qz), two * (qx * qz + qw * qy),
            two * (qx * qy + qw * qz), one - two * (qx * qx + qz * qz), two * (qy * qz - qw * qx),
            two * (qx * qz - qw * qy), two * (qy * qz + qw * qx), one - two * (qx * qx + qy * qy))


@nb.njit(inline="always")
def _polar(F, q, iterations, real):
    """Warm-started quaternion polar iteration (fem.corotated_range_3d's) on F (3, 3), q (4,)
    updated in place; returns R. In ``real`` arithmetic, as F and q are."""
    qw, qx, qy, qz = q[0], q[1], q[2], q[3]
    for _ in range(iterations):
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = rotation(qw, qx, qy, qz, real)
        wx = (r10 * F[2, 0] - r20 * F[1, 0]) + (r11 * F[2, 1] - r21 * F[1, 1]) + (r12 * F[2, 2] - r22 * F[1, 2])
        wy = (r20 * F[0, 0] - r00 * F[2, 0]) + (r21 * F[0, 1] - r01 * F[2, 1]) + (r22 * F[0, 2] - r02 * F[2, 2])
        wz = (r00 * F[1, 0] - r10 * F[0, 0]) + (r01 * F[1, 1] - r11 * F[0, 1]) + (r02 * F[1, 2] - r12 * F[0, 2])
        den = real(0.5) / (abs(r00 * F[0, 0] + r10 * F[1, 0] + r20 * F[2, 0] + r01 * F[0, 1] + r11 * F[1, 1]
                               + r21 * F[2, 1] + r02 * F[0, 2] + r12 * F[1, 2] + r22 * F[2, 2]) + real(1e-9))
        ax = wx * den; ay = wy * den; az = wz * den
        nw = qw - ax * qx - ay * qy - az * qz
        nx = qx + ax * qw + ay * qz - az * qy
        ny = qy - ax * qz + ay * qw + az * qx
        nz = qz + ax * qy - ay * qx + az * qw
        inv = real(1.0) / np.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
        qw = nw * inv; qx = nx * inv; qy = ny * inv; qz = nz * inv
    q[0] = qw; q[1] = qx; q[2] = qy; q[3] = qz
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = rotation(qw, qx, qy, qz, real)
    return np.array([[r00, r01, r02], [r10, r11, r12], [r20, r21, r22]])


@nb.njit(fastmath=True, cache=True, error_model="numpy")
def p2_range_3d(x, elems, Bm, vol, mu, lam, q, f, e0, e1, per_point, iterations, real):
    """Add the nodal forces of 10-node tets [e0, e1) into f (nv, 3). q (4 ne, 4): warm-start
    quaternions, row 4 e + k for quadrature point k (``per_point``), or row 4 e for the rotation
    of the element's corner F. ``real``: the arithmetic's type and Bm's, vol's and q's (as
    fem.corotated_range_3d). Returns the number of elements with a quadrature point at det F <= 0."""
    inverted = 0
    one, four = real(1.0), real(4.0)
    mu = real(mu); lam = real(lam)
    Ds = np.empty((3, 3), real); G = np.empty((4, 3), real); d = np.zeros((10, 3), real)
    h = np.empty((10, 3), real); eye = np.eye(3, dtype=real)
    for e in range(e0, e1):
        b = Bm[e]
        for a in range(10):
            for c in range(3):
                d[a, c] = x[elems[e, a], c] - x[elems[e, 0], c]
        wV = -real(0.25) * vol[e]
        h[:] = 0.0
        R = eye
        if not per_point:
            for c in range(3):
                for j in range(3):
                    Ds[c, j] = d[j + 1, c]
            R = _polar(Ds @ b, q[4 * e], iterations, real)
        bad = False
        for k in range(4):
            L0, L1, L2, L3 = real(QUAD_3D[k, 0]), real(QUAD_3D[k, 1]), real(QUAD_3D[k, 2]), real(QUAD_3D[k, 3])
            for c in range(3):
                y0 = four * (L1 * d[4, c] + L2 * d[6, c] + L3 * d[7, c])
                Ds[c, 0] = (four * L1 - one) * d[1, c] + four * (L0 * d[4, c] + L2 * d[5, c] + L3 * d[8, c]) - y0
                Ds[c, 1] = (four * L2 - one) * d[2, c] + four * (L0 * d[6, c] + L1 * d[5, c] + L3 * d[9, c]) - y0
                Ds[c, 2] = (four * L3 - one) * d[3, c] + four * (L0 * d[7, c] + L1 * d[8, c] + L2 * d[9, c]) - y0
            F = Ds @ b
            bad |= np.linalg.det(F) <= 0.0
            if per_point:
                R = _polar(F, q[4 * e + k], iterations, real)
            S = R.T @ F
            eps = real(0.5) * (S + S.T) - eye
            T = real(2.0) * mu * eps + lam * (eps[0, 0] + eps[1, 1] + eps[2, 2]) * eye   # np.trace would be float64
            P = wV * (R @ T)
            Gt = P @ b.T                                   # columns: g_1, g_2, g_3
            for c in range(3):
                G[1, c] = Gt[c, 0]; G[2, c] = Gt[c, 1]; G[3, c] = Gt[c, 2]
                G[0, c] = -(Gt[c, 0] + Gt[c, 1] + Gt[c, 2])
            L = (L0, L1, L2, L3)
            for j in range(4):
                for c in range(3):
                    h[j, c] += (four * L[j] - one) * G[j, c]
            for m in range(6):
                i, j = EDGES_3D[m, 0], EDGES_3D[m, 1]
                for c in range(3):
                    h[4 + m, c] += four * (L[i] * G[j, c] + L[j] * G[i, c])
        inverted += 1 if bad else 0
        for a in range(10):
            for c in range(3):
                f[elems[e, a], c] += h[a, c]
    return inverted


@nb.njit(fastmath=True, cache=True, error_model="numpy")
def p2_range_2d(x, elems, Bm, vol, mu, lam, f, e0, e1, real):
    """6-node triangles [e0, e1) into f (nv, 2), plane strain, the exact 2D polar rotation at
    every quadrature point. Returns the number of elements with a point at det F <= 0.
    ``real``: as p2_range_3d's."""
    inverted = 0
    half, one, two, four = real(0.5), real(1.0), real(2.0), real(4.0)
    mu = real(mu); lam = real(lam)
    d = np.zeros((6, 2), real); h = np.empty((6, 2), real); G = np.empty((3, 2), real)
    for e in range(e0, e1):
        b00 = Bm[e, 0, 0]; b01 = Bm[e, 0, 1]; b10 = Bm[e, 1, 0]; b11 = Bm[e, 1, 1]
        for a in range(6):
            for c in range(2):
                d[a, c] = x[elems[e, a], c] - x[elems[e, 0], c]
        wV = -vol[e] / real(3.0)
        h[:] = 0.0
        bad = False
        for k in range(3):
            L0, L1, L2 = real(QUAD_2D[k, 0]), real(QUAD_2D[k, 1]), real(QUAD_2D[k, 2])
            y0x = four * (L1 * d[3, 0] + L2 * d[5, 0]); y0y = four * (L1 * d[3, 1] + L2 * d[5, 1])
            d1x = (four * L1 - one) * d[1, 0] + four * (L0 * d[3, 0] + L2 * d[4, 0]) - y0x
            d1y = (four * L1 - one) * d[1, 1] + four * (L0 * d[3, 1] + L2 * d[4, 1]) - y0y
            d2x = (four * L2 - one) * d[2, 0] + four * (L0 * d[5, 0] + L1 * d[4, 0]) - y0x
            d2y = (four * L2 - one) * d[2, 1] + four * (L0 * d[5, 1] + L1 * d[4, 1]) - y0y
            f00 = d1x * b00 + d2x * b10; f01 = d1x * b01 + d2x * b11
            f10 = d1y * b00 + d2y * b10; f11 = d1y * b01 + d2y * b11
            bad |= f00 * f11 - f01 * f10 <= 0.0
            cs = f00 + f11; sn = f10 - f01
            inv_n = one / np.sqrt(cs * cs + sn * sn + real(1e-30))
            cs *= inv_n; sn *= inv_n
            s00 = cs * f00 + sn * f10; s11 = -sn * f01 + cs * f11
            s01 = half * ((cs * f01 + sn * f11) + (-sn * f00 + cs * f10))
            e00 = s00 - one; e11 = s11 - one
            tr = lam * (e00 + e11)
            t00 = two * mu * e00 + tr; t11 = two * mu * e11 + tr; t01 = two * mu * s01
            p00 = wV * (cs * t00 - sn * t01); p01 = wV * (cs * t01 - sn * t11)
            p10 = wV * (sn * t00 + cs * t01); p11 = wV * (sn * t01 + cs * t11)
            G[1, 0] = p00 * b00 + p01 * b01; G[1, 1] = p10 * b00 + p11 * b01
            G[2, 0] = p00 * b10 + p01 * b11; G[2, 1] = p10 * b10 + p11 * b11
            G[0, 0] = -(G[1, 0] + G[2, 0]); G[0, 1] = -(G[1, 1] + G[2, 1])
            L = (L0, L1, L2)
            for j in range(3):
                for c in range(2):
                    h[j, c] += (four * L[j] - one) * G[j, c]
            for m in range(3):
                i, j = EDGES_2D[m, 0], EDGES_2D[m, 1]
                for c in range(2):
                    h[3 + m, c] += four * (L[i] * G[j, c] + L[j] * G[i, c])
        inverted += 1 if bad else 0
        for a in range(6):
            for c in range(2):
                f[elems[e, a], c] += h[a, c]
    return inverted
