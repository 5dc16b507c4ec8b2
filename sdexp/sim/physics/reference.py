"""The numba reference of the compiled step, in the order of forces.h and kernels.c and with
their names, so the two can be read side by side:

    forces.h    POLAR_ITERATE        rotation, polar
                forces_range         forces_range               linear tets
                corotated_forces_3d  corotated_forces_3d(_f32)  the same behind the C signature
                p2_forces_blocked    p2_forces_range            10-node tets
                p2_forces_range_2d   p2_forces_range_2d         6-node triangles
                forces_range_2d      forces_range_2d            triangles
                element_forces       element_forces             any element, one buffer per thread
    kernels.c   rotor_forces         rotor_forces
                rigid_motion         rigid_motion               what the deformation damping keeps
                contact              contact
                kick                 kick                       velocities, the damping's sums
                drift                drift                      damping, positions, contacts
                advance              advance                    n_sub substeps

The compiled step runs the same arithmetic about 3x faster (its SIMD loops spell out the trees
gcc gave these scalar loops: docs/speed.md); these run where no compiler works
(sdexp.sim.physics.fem.kernels chooses) and are the yardstick of the compiled step's tests
(tests/sim/test_fem.py, test_precision.py). Outside the step, fem.elastic_forces (the statics, the
stable substep) runs element_forces here, the linear tets through the compiled kernel.

Scalar locals only in the element kernels: per-element temporary arrays inside a parallel loop
halve the speed. ``real`` (np.float64 | np.float32, sim.precision) is the force arithmetic's
type and that of Bm, vol and q; positions, velocities and force sums stay float64.
"""
from __future__ import annotations

import numba as nb
import numpy as np

from sdexp.sim.physics.quadratic import EDGES_2D, EDGES_3D, QUAD_2D, QUAD_3D, ROTATION_PER_POINT

POLAR_ITERATIONS = 2   # warm-started polar iterations a substep (forces.h POLAR_ITERATE, twice)

# the deformation damping's sums (kernels.c S_*): M, sum m r, sum m v, sum m r x v, sum m r r^T
S_M, S_R, S_P, S_L, S_S, S_LEN = 0, 1, 4, 7, 10, 16


# ============================================================================ forces.h

@nb.njit(inline="always")
def rotation(qw, qx, qy, qz, real):
    """Row-major entries of the rotation matrix of a unit quaternion, in ``real`` arithmetic."""
    one, two = real(1.0), real(2.0)
    return (one - two * (qy * qy + qz * qz), two * (qx * qy - qw * qz), two * (qx * qz + qw * qy),
            two * (qx * qy + qw * qz), one - two * (qx * qx + qz * qz), two * (qy * qz - qw * qx),
            two * (qx * qz - qw * qy), two * (qy * qz + qw * qx), one - two * (qx * qx + qy * qy))


@nb.njit(inline="always")
def polar(F, q, iterations, real):
    """Warm-started quaternion polar iteration (forces_range's) on F (3, 3), q (4,)
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
def forces_range(x, elems, Bm, vol, mu, lam, q, f, e0, e1, real):
    """Add the nodal forces of tets [e0, e1) into f (nv, 3); update their warm-start
    quaternions q (ne, 4). Returns the number of inverted tets (det F <= 0).
    ``real`` (np.float64 | np.float32, sim.precision): the type of the arithmetic and of Bm, vol
    and q; positions and f stay float64, edge vectors are rounded after the subtraction (forces.h)."""
    inverted = 0
    half, one, two, tiny = real(0.5), real(1.0), real(2.0), real(1e-9)
    mu = real(mu); lam = real(lam)
    for e in range(e0, e1):
        i0 = elems[e, 0]; i1 = elems[e, 1]; i2 = elems[e, 2]; i3 = elems[e, 3]
        x0 = x[i0, 0]; y0 = x[i0, 1]; z0 = x[i0, 2]
        d1x = real(x[i1, 0] - x0); d1y = real(x[i1, 1] - y0); d1z = real(x[i1, 2] - z0)
        d2x = real(x[i2, 0] - x0); d2y = real(x[i2, 1] - y0); d2z = real(x[i2, 2] - z0)
        d3x = real(x[i3, 0] - x0); d3y = real(x[i3, 1] - y0); d3z = real(x[i3, 2] - z0)
        b00 = Bm[e, 0, 0]; b01 = Bm[e, 0, 1]; b02 = Bm[e, 0, 2]
        b10 = Bm[e, 1, 0]; b11 = Bm[e, 1, 1]; b12 = Bm[e, 1, 2]
        b20 = Bm[e, 2, 0]; b21 = Bm[e, 2, 1]; b22 = Bm[e, 2, 2]
        # F = Ds Bm, Ds columns are the edge vectors d1, d2, d3
        f00 = d1x * b00 + d2x * b10 + d3x * b20
        f01 = d1x * b01 + d2x * b11 + d3x * b21
        f02 = d1x * b02 + d2x * b12 + d3x * b22
        f10 = d1y * b00 + d2y * b10 + d3y * b20
        f11 = d1y * b01 + d2y * b11 + d3y * b21
        f12 = d1y * b02 + d2y * b12 + d3y * b22
        f20 = d1z * b00 + d2z * b10 + d3z * b20
        f21 = d1z * b01 + d2z * b11 + d3z * b21
        f22 = d1z * b02 + d2z * b12 + d3z * b22
        det = (f00 * (f11 * f22 - f12 * f21) - f01 * (f10 * f22 - f12 * f20)
               + f02 * (f10 * f21 - f11 * f20))
        inverted += 1 if det <= 0.0 else 0
        qw = q[e, 0]; qx = q[e, 1]; qy = q[e, 2]; qz = q[e, 3]
        for _ in range(POLAR_ITERATIONS):
            r00, r01, r02, r10, r11, r12, r20, r21, r22 = rotation(qw, qx, qy, qz, real)
            # omega = sum_i R_col_i x F_col_i / |sum_i R_col_i . F_col_i|
            wx = (r10 * f20 - r20 * f10) + (r11 * f21 - r21 * f11) + (r12 * f22 - r22 * f12)
            wy = (r20 * f00 - r00 * f20) + (r21 * f01 - r01 * f21) + (r22 * f02 - r02 * f22)
            wz = (r00 * f10 - r10 * f00) + (r01 * f11 - r11 * f01) + (r02 * f12 - r12 * f02)
            den = abs(r00 * f00 + r10 * f10 + r20 * f20 + r01 * f01 + r11 * f11 + r21 * f21
                      + r02 * f02 + r12 * f12 + r22 * f22) + tiny
            wx /= den; wy /= den; wz /= den
            # q <- normalize((1, omega/2) * q): the first-order rotation update, branch- and
            # trig-free; it converges to the same fixed point (omega = 0 at the polar rotation)
            ax = half * wx; ay = half * wy; az = half * wz
            nw = qw - ax * qx - ay * qy - az * qz
            nx = qx + ax * qw + ay * qz - az * qy
            ny = qy - ax * qz + ay * qw + az * qx
            nz = qz + ax * qy - ay * qx + az * qw
            inv = one / np.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
            qw = nw * inv; qx = nx * inv; qy = ny * inv; qz = nz * inv
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = rotation(qw, qx, qy, qz, real)
        q[e, 0] = qw; q[e, 1] = qx; q[e, 2] = qy; q[e, 3] = qz
        # S = R^T F; strain = sym(S) - I
        s00 = r00 * f00 + r10 * f10 + r20 * f20
        s11 = r01 * f01 + r11 * f11 + r21 * f21
        s22 = r02 * f02 + r12 * f12 + r22 * f22
        s01 = half * ((r00 * f01 + r10 * f11 + r20 * f21) + (r01 * f00 + r11 * f10 + r21 * f20))
        s02 = half * ((r00 * f02 + r10 * f12 + r20 * f22) + (r02 * f00 + r12 * f10 + r22 * f20))
        s12 = half * ((r01 * f02 + r11 * f12 + r21 * f22) + (r02 * f01 + r12 * f11 + r22 * f21))
        e00 = s00 - one; e11 = s11 - one; e22 = s22 - one
        tr = lam * (e00 + e11 + e22)
        m2 = two * mu
        t00 = m2 * e00 + tr; t11 = m2 * e11 + tr; t22 = m2 * e22 + tr
        t01 = m2 * s01; t02 = m2 * s02; t12 = m2 * s12
        # P = R T, scaled by -V
        V = -vol[e]
        p00 = V * (r00 * t00 + r01 * t01 + r02 * t02)
        p01 = V * (r00 * t01 + r01 * t11 + r02 * t12)
        p02 = V * (r00 * t02 + r01 * t12 + r02 * t22)
        p10 = V * (r10 * t00 + r11 * t01 + r12 * t02)
        p11 = V * (r10 * t01 + r11 * t11 + r12 * t12)
        p12 = V * (r10 * t02 + r11 * t12 + r12 * t22)
        p20 = V * (r20 * t00 + r21 * t01 + r22 * t02)
        p21 = V * (r20 * t01 + r21 * t11 + r22 * t12)
        p22 = V * (r20 * t02 + r21 * t12 + r22 * t22)
        # H = P Bm^T: column j is the force on vertex j+1
        h00 = p00 * b00 + p01 * b01 + p02 * b02
        h10 = p10 * b00 + p11 * b01 + p12 * b02
        h20 = p20 * b00 + p21 * b01 + p22 * b02
        h01 = p00 * b10 + p01 * b11 + p02 * b12
        h11 = p10 * b10 + p11 * b11 + p12 * b12
        h21 = p20 * b10 + p21 * b11 + p22 * b12
        h02 = p00 * b20 + p01 * b21 + p02 * b22
        h12 = p10 * b20 + p11 * b21 + p12 * b22
        h22 = p20 * b20 + p21 * b21 + p22 * b22
        f[i1, 0] += h00; f[i1, 1] += h10; f[i1, 2] += h20
        f[i2, 0] += h01; f[i2, 1] += h11; f[i2, 2] += h21
        f[i3, 0] += h02; f[i3, 1] += h12; f[i3, 2] += h22
        f[i0, 0] -= h00 + h01 + h02
        f[i0, 1] -= h10 + h11 + h12
        f[i0, 2] -= h20 + h21 + h22
    return inverted


_ptr = nb.types.voidptr
_C_SIGNATURE = nb.types.int32(_ptr, _ptr, _ptr, _ptr, nb.types.float64, nb.types.float64, _ptr, _ptr,
                              nb.types.int64, nb.types.int64, nb.types.int64)


@nb.njit(cache=True)
def _linear_chunks(x, elems, Bm, vol, mu, lam, q, fbuf, nv, ne, nt, real):
    """The body of the cfuncs below: chunk t of the tets into buffer t, on one thread."""
    xs = nb.carray(x, (nv, 3), np.float64)
    el = nb.carray(elems, (ne, 4), np.int32)
    bm = nb.carray(Bm, (ne, 3, 3), real)
    vo = nb.carray(vol, (ne,), real)
    qs = nb.carray(q, (ne, 4), real)
    fb = nb.carray(fbuf, (nt, nv, 3), np.float64)
    chunk = (ne + nt - 1) // nt
    inverted = 0
    for t in range(nt):
        fb[t] = 0.0
        inverted += forces_range(xs, el, bm, vo, mu, lam, qs, fb[t], t * chunk, min(ne, (t + 1) * chunk), real)
    return inverted


@nb.cfunc(_C_SIGNATURE, cache=True)
def corotated_forces_3d(x, elems, Bm, vol, mu, lam, q, fbuf, nv, ne, nt):
    """kernels.c's corotated_forces_3d in numba, behind the same C signature: the fallback
    when no compiler works (one thread; chunk t still goes to buffer t)."""
    return _linear_chunks(x, elems, Bm, vol, mu, lam, q, fbuf, nv, ne, nt, np.float64)


@nb.cfunc(_C_SIGNATURE, cache=True)
def corotated_forces_3d_f32(x, elems, Bm, vol, mu, lam, q, fbuf, nv, ne, nt):
    """corotated_forces_3d in float32 (kernels.c's corotated_forces_3d_f32): Bm, vol, q float32."""
    return _linear_chunks(x, elems, Bm, vol, mu, lam, q, fbuf, nv, ne, nt, np.float32)


@nb.njit(cache=True)
def linear_forces_3d(kernel, x, elems, Bm, vol, mu, lam, q, fbuf):
    """Tet forces into one buffer per thread, fbuf (nt, nv, 3), by a kernel with kernels.c's
    C signature (threads inside the kernel). Returns the number of inverted tets."""
    return kernel(x.ctypes.data, elems.ctypes.data, Bm.ctypes.data, vol.ctypes.data, mu, lam,
                  q.ctypes.data, fbuf.ctypes.data, x.shape[0], elems.shape[0], fbuf.shape[0])


@nb.njit(fastmath=True, cache=True, error_model="numpy")
def p2_forces_range(x, elems, Bm, vol, mu, lam, q, f, e0, e1, per_point, iterations, real):
    """Add the nodal forces of 10-node tets [e0, e1) into f (nv, 3). q (4 ne, 4): warm-start
    quaternions, row 4 e + k for quadrature point k (``per_point``), or row 4 e for the rotation
    of the element's corner F. ``real``: the arithmetic's type and Bm's, vol's and q's (as
    forces_range). Returns the number of elements with a quadrature point at det F <= 0."""
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
            R = polar(Ds @ b, q[4 * e], iterations, real)
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
                R = polar(F, q[4 * e + k], iterations, real)
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
def p2_forces_range_2d(x, elems, Bm, vol, mu, lam, f, e0, e1, real):
    """6-node triangles [e0, e1) into f (nv, 2), plane strain, the exact 2D polar rotation at
    every quadrature point. Returns the number of elements with a point at det F <= 0.
    ``real``: as p2_forces_range's."""
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


@nb.njit(fastmath=True, cache=True, error_model="numpy")
def forces_range_2d(x, elems, Bm, vol, mu, lam, f, e0, e1, real):
    """Triangle version of forces_range (the 2D rotation is exact, no warm start)."""
    inverted = 0
    half, one, two = real(0.5), real(1.0), real(2.0)
    mu = real(mu); lam = real(lam)
    for e in range(e0, e1):
        i0 = elems[e, 0]; i1 = elems[e, 1]; i2 = elems[e, 2]
        d1x = real(x[i1, 0] - x[i0, 0]); d1y = real(x[i1, 1] - x[i0, 1])
        d2x = real(x[i2, 0] - x[i0, 0]); d2y = real(x[i2, 1] - x[i0, 1])
        b00 = Bm[e, 0, 0]; b01 = Bm[e, 0, 1]; b10 = Bm[e, 1, 0]; b11 = Bm[e, 1, 1]
        f00 = d1x * b00 + d2x * b10; f01 = d1x * b01 + d2x * b11
        f10 = d1y * b00 + d2y * b10; f11 = d1y * b01 + d2y * b11
        inverted += 1 if f00 * f11 - f01 * f10 <= 0.0 else 0
        # the polar rotation of a 2x2 F, exactly and without trig
        c = f00 + f11; s = f10 - f01
        inv_n = one / np.sqrt(c * c + s * s + real(1e-30))
        c *= inv_n; s *= inv_n
        # S = R^T F with R = [[c, -s], [s, c]]
        s00 = c * f00 + s * f10; s11 = -s * f01 + c * f11
        s01 = half * ((c * f01 + s * f11) + (-s * f00 + c * f10))
        e00 = s00 - one; e11 = s11 - one
        tr = lam * (e00 + e11)
        t00 = two * mu * e00 + tr; t11 = two * mu * e11 + tr; t01 = two * mu * s01
        V = -vol[e]
        p00 = V * (c * t00 - s * t01); p01 = V * (c * t01 - s * t11)
        p10 = V * (s * t00 + c * t01); p11 = V * (s * t01 + c * t11)
        h00 = p00 * b00 + p01 * b01; h10 = p10 * b00 + p11 * b01
        h01 = p00 * b10 + p01 * b11; h11 = p10 * b10 + p11 * b11
        f[i1, 0] += h00; f[i1, 1] += h10
        f[i2, 0] += h01; f[i2, 1] += h11
        f[i0, 0] -= h00 + h01; f[i0, 1] -= h10 + h11
    return inverted


@nb.njit(parallel=True, cache=True)
def forces_2d(x, elems, Bm, vol, mu, lam, fbuf, real):
    """linear_forces_3d for triangles (numba is fast enough here)."""
    ne = elems.shape[0]
    nt = fbuf.shape[0]
    chunk = (ne + nt - 1) // nt
    inverted = 0
    for t in nb.prange(nt):
        fbuf[t] = 0.0
        inverted += forces_range_2d(x, elems, Bm, vol, mu, lam, fbuf[t], t * chunk, min(ne, (t + 1) * chunk), real)
    return inverted


@nb.njit(cache=True)
def element_forces(kernel, x, elems, Bm, vol, mu, lam, q, fbuf, real):
    """Elastic forces of any element kind into one buffer per thread (fbuf (nt, nv, dim));
    advance and fem.elastic_forces call this. Linear 3D runs ``kernel``
    (C signature, of Bm's type); quadratic elements their numba reference, one chunk per buffer.
    ``real``: the arithmetic, Bm's, vol's and q's type. Returns the number of inverted elements."""
    nodes = elems.shape[1]
    if nodes == 4:
        return linear_forces_3d(kernel, x, elems, Bm, vol, mu, lam, q, fbuf)
    if nodes == 3:
        return forces_2d(x, elems, Bm, vol, mu, lam, fbuf, real)
    ne = elems.shape[0]
    nt = fbuf.shape[0]
    chunk = (ne + nt - 1) // nt
    inverted = 0
    for t in range(nt):
        fbuf[t] = 0.0
        e0, e1 = t * chunk, min(ne, (t + 1) * chunk)
        if nodes == 10:
            inverted += p2_forces_range(x, elems, Bm, vol, mu, lam, q, fbuf[t], e0, e1,
                                        ROTATION_PER_POINT, POLAR_ITERATIONS, real)
        else:
            inverted += p2_forces_range_2d(x, elems, Bm, vol, mu, lam, fbuf[t], e0, e1, real)
    return inverted


# ============================================================================ kernels.c

@nb.njit(fastmath=True, cache=True, error_model="numpy")
def rotor_forces(x, tri_ptr, tris, vert_ptr, verts, weights, thrust, ext, dirs):
    """Thrust of rotor r acts along the area-weighted normal of its bound surface triangles
    (3D) or segments (2D), spread over its bound vertices by ``weights``.
    Writes the unit directions into dirs (m, dim) and the forces into ext (patch rows only)."""
    dim = x.shape[1]
    m = thrust.shape[0]
    for r in range(m):
        for k in range(vert_ptr[r], vert_ptr[r + 1]):
            for c in range(dim):
                ext[verts[k], c] = 0.0
    for r in range(m):
        nx = 0.0; ny = 0.0; nz = 0.0
        for k in range(tri_ptr[r], tri_ptr[r + 1]):
            a = tris[k, 0]; b = tris[k, 1]
            if dim == 3:
                c = tris[k, 2]
                ux = x[b, 0] - x[a, 0]; uy = x[b, 1] - x[a, 1]; uz = x[b, 2] - x[a, 2]
                wx = x[c, 0] - x[a, 0]; wy = x[c, 1] - x[a, 1]; wz = x[c, 2] - x[a, 2]
                nx += uy * wz - uz * wy; ny += uz * wx - ux * wz; nz += ux * wy - uy * wx
            else:
                # outward normal of a counter-clockwise boundary segment a->b
                nx += x[b, 1] - x[a, 1]; ny -= x[b, 0] - x[a, 0]
        inv = 1.0 / np.sqrt(nx * nx + ny * ny + nz * nz + 1e-300)
        nx *= inv; ny *= inv; nz *= inv
        dirs[r, 0] = nx; dirs[r, 1] = ny
        if dim == 3:
            dirs[r, 2] = nz
        for k in range(vert_ptr[r], vert_ptr[r + 1]):
            i = verts[k]
            f = thrust[r] * weights[k]
            ext[i, 0] += f * nx; ext[i, 1] += f * ny
            if dim == 3:
                ext[i, 2] += f * nz


@nb.njit(cache=True)
def rigid_motion(sums, dim):
    """(c, p, w): the centre of mass (relative to the sums' reference point), its velocity and
    the angular velocity that carries the angular momentum, from kick's sums."""
    M = sums[S_M]
    c = np.zeros(3); p = np.zeros(3); w = np.zeros(3)
    for a in range(3):
        c[a] = sums[S_R + a] / M; p[a] = sums[S_P + a] / M
    # about the centre of mass: L = sum m r x v - M c x p, S = sum m r r^T - M c c^T
    L0 = sums[S_L] - M * (c[1] * p[2] - c[2] * p[1])
    L1 = sums[S_L + 1] - M * (c[2] * p[0] - c[0] * p[2])
    L2 = sums[S_L + 2] - M * (c[0] * p[1] - c[1] * p[0])
    sxx = sums[S_S] - M * c[0] * c[0]; sxy = sums[S_S + 1] - M * c[0] * c[1]; sxz = sums[S_S + 2] - M * c[0] * c[2]
    syy = sums[S_S + 3] - M * c[1] * c[1]; syz = sums[S_S + 4] - M * c[1] * c[2]; szz = sums[S_S + 5] - M * c[2] * c[2]
    if dim == 2:
        w[2] = L2 / (sxx + syy)
        return c, p, w
    # inertia I = tr(S) 1 - S, symmetric; w = I^-1 L by the adjugate
    a = syy + szz; b = -sxy; cc = -sxz; d = sxx + szz; e = -syz; f = sxx + syy
    A00 = d * f - e * e; A01 = cc * e - b * f; A02 = b * e - cc * d
    A11 = a * f - cc * cc; A12 = b * cc - a * e; A22 = a * d - b * b
    inv = 1.0 / (a * A00 + b * A01 + cc * A02)
    w[0] = inv * (A00 * L0 + A01 * L1 + A02 * L2)
    w[1] = inv * (A01 * L0 + A11 * L1 + A12 * L2)
    w[2] = inv * (A02 * L0 + A12 * L1 + A22 * L2)
    return c, p, w


@nb.njit(inline="always")
def contact(dim, ground, boxes_min, boxes_max, friction, px, py, pz, vx, vy, vz):
    """One vertex (position p, velocity v) against the ground and the static boxes: project out
    along the normal, cancel the inward normal velocity, take Coulomb friction off the
    tangential velocity. Returns the new (p, v)."""
    if py < ground:
        py = ground
        if vy < 0.0:
            vt = np.sqrt(vx * vx + vz * vz)
            keep = max(0.0, 1.0 - friction * (-vy) / (vt + 1e-12))
            vx *= keep; vz *= keep; vy = 0.0
    for b in range(boxes_min.shape[0]):
        inside = px > boxes_min[b, 0] and px < boxes_max[b, 0] and py > boxes_min[b, 1] and py < boxes_max[b, 1]
        if dim == 3:
            inside = inside and pz > boxes_min[b, 2] and pz < boxes_max[b, 2]
        if inside:
            best = 1e300; axis = 0; side = 0.0
            for c in range(dim):
                q = px if c == 0 else (py if c == 1 else pz)
                lo = q - boxes_min[b, c]; hi = boxes_max[b, c] - q
                if lo < best:
                    best = lo; axis = c; side = -1.0
                if hi < best:
                    best = hi; axis = c; side = 1.0
            vn = vx if axis == 0 else (vy if axis == 1 else vz)
            if axis == 0:
                px += side * best
            elif axis == 1:
                py += side * best
            else:
                pz += side * best
            if vn * side < 0.0:
                t2 = vx * vx + vy * vy + vz * vz - vn * vn
                keep = max(0.0, 1.0 - friction * abs(vn) / (np.sqrt(max(t2, 0.0)) + 1e-12))
                vx *= keep; vy *= keep; vz *= keep
                if axis == 0:
                    vx = 0.0
                elif axis == 1:
                    vy = 0.0
                else:
                    vz = 0.0
    return px, py, pz, vx, vy, vz


@nb.njit(fastmath=True, cache=True, error_model="numpy")
def kick(x, v, fbuf, minv, mass, ext, fext, dt, scale, gravity, gravity_share, ref, with_sums, sums):
    """Velocities from the summed forces (rotors' ``ext``, effects' ``fext``, each thread's elastic
    buffer), gravity on the physical mass (``gravity_share``: physical over inertial, sim.mass_scaling)
    and the absolute damping (``scale``); with ``with_sums`` also the damping's sums over free
    vertices, relative to ``ref`` (far from the origin they would cancel). minv = 0 pins a vertex."""
    nv, dim = x.shape
    nt = fbuf.shape[0]
    sums[:] = 0.0
    for i in range(nv):
        fx = ext[i, 0] + fext[i, 0]; fy = ext[i, 1] + fext[i, 1]; fz = 0.0
        if dim == 3:
            fz = ext[i, 2] + fext[i, 2]
        for t in range(nt):
            fx += fbuf[t, i, 0]; fy += fbuf[t, i, 1]
            if dim == 3:
                fz += fbuf[t, i, 2]
        mi = minv[i]
        g = gravity * gravity_share[i] if mi > 0.0 else 0.0
        ux = (v[i, 0] + dt * fx * mi) * scale
        uy = (v[i, 1] + dt * (fy * mi - g)) * scale
        uz = 0.0
        v[i, 0] = ux; v[i, 1] = uy
        if dim == 3:
            uz = (v[i, 2] + dt * fz * mi) * scale
            v[i, 2] = uz
        if with_sums and mi != 0.0:
            m = mass[i]
            ax = x[i, 0] - ref[0]; ay = x[i, 1] - ref[1]; az = x[i, 2] - ref[2] if dim == 3 else 0.0
            sums[S_M] += m
            sums[S_R] += m * ax; sums[S_R + 1] += m * ay; sums[S_R + 2] += m * az
            sums[S_P] += m * ux; sums[S_P + 1] += m * uy; sums[S_P + 2] += m * uz
            sums[S_L] += m * (ay * uz - az * uy); sums[S_L + 1] += m * (az * ux - ax * uz)
            sums[S_L + 2] += m * (ax * uy - ay * ux)
            sums[S_S] += m * ax * ax; sums[S_S + 1] += m * ax * ay; sums[S_S + 2] += m * ax * az
            sums[S_S + 3] += m * ay * ay; sums[S_S + 4] += m * ay * az; sums[S_S + 5] += m * az * az


@nb.njit(fastmath=True, cache=True, error_model="numpy")
def drift(x, v, minv, dt, damp, keep, ref, c, p, w, ground, boxes_min, boxes_max, friction):
    """With ``damp``, every free vertex keeps ``keep`` of its velocity relative to the rigid motion
    p + w x (x - ref - c) (implicit mass-proportional damping of the deformation velocity: it
    removes no linear or angular momentum, so a spinning or drifting body is not slowed, only its
    vibrations are: the paper's Eq. 3 is frame-indifferent); then positions, then contacts
    (``ground`` -inf: none). Returns the largest squared speed."""
    nv, dim = x.shape
    vmax2 = 0.0
    for i in range(nv):
        ux = v[i, 0]; uy = v[i, 1]; uz = v[i, 2] if dim == 3 else 0.0
        qx = x[i, 0]; qy = x[i, 1]; qz = x[i, 2] if dim == 3 else 0.0
        if damp and minv[i] != 0.0:
            ax = qx - ref[0] - c[0]; ay = qy - ref[1] - c[1]; az = qz - ref[2] - c[2] if dim == 3 else 0.0
            gx = p[0] + w[1] * az - w[2] * ay; gy = p[1] + w[2] * ax - w[0] * az
            ux = gx + keep * (ux - gx); uy = gy + keep * (uy - gy)
            if dim == 3:
                gz = p[2] + w[0] * ay - w[1] * ax
                uz = gz + keep * (uz - gz)
        qx += dt * ux; qy += dt * uy; qz += dt * uz
        qx, qy, qz, ux, uy, uz = contact(dim, ground, boxes_min, boxes_max, friction, qx, qy, qz, ux, uy, uz)
        x[i, 0] = qx; x[i, 1] = qy; v[i, 0] = ux; v[i, 1] = uy
        if dim == 3:
            x[i, 2] = qz; v[i, 2] = uz
        vmax2 = max(vmax2, ux * ux + uy * uy + uz * uz)
    return vmax2


@nb.njit(cache=True)
def advance(kernel, n_sub, dt, x, v, q, fbuf, elems, Bm, vol, mu, lam, minv, mass, damping,
            deform_damping, gravity, ground, boxes_min, boxes_max, friction, tri_ptr, tris, vert_ptr, verts,
            weights, thrust, ext, dirs, fext, gravity_share, real):
    """n_sub substeps of symplectic Euler: element forces (one buffer per thread in fbuf (nt, nv,
    dim); ``kernel``, the linear 3D force kernel with kernels.c's C signature, in ``real``), rotor
    forces, kick, the rigid motion, drift. Returns (max inverted elements seen in a substep, max
    squared speed)."""
    worst = 0
    vmax2 = 0.0
    dim = x.shape[1]
    scale = 1.0 / (1.0 + dt * damping)
    keep = 1.0 / (1.0 + dt * deform_damping)
    sums = np.zeros(S_LEN)
    ref = np.zeros(3)
    zero = np.zeros(3)
    for _ in range(n_sub):
        worst = max(worst, element_forces(kernel, x, elems, Bm, vol, mu, lam, q, fbuf, real))
        rotor_forces(x, tri_ptr, tris, vert_ptr, verts, weights, thrust, ext, dirs)
        for a in range(dim):
            ref[a] = x[0, a]
        kick(x, v, fbuf, minv, mass, ext, fext, dt, scale, gravity, gravity_share, ref, deform_damping > 0.0, sums)
        damp = deform_damping > 0.0 and sums[S_M] > 0.0
        c, p, w = rigid_motion(sums, dim) if damp else (zero, zero, zero)
        vmax2 = max(vmax2, drift(x, v, minv, dt, damp, keep, ref, c, p, w, ground, boxes_min, boxes_max, friction))
    return worst, vmax2
