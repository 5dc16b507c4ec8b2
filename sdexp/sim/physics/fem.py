"""Co-rotated linear elasticity (Mueller & Gross 2004) on tets (3D) and triangles (2D), linear
here, quadratic in sdexp.sim.physics.quadratic (``FemModel.order`` tells which a model has).

The element force is the linear-elastic force in the element's rotated frame: with
F = Ds Dm^-1, R = polar(F), eps = sym(R^T F) - I and P = R (2 mu eps + lam tr(eps) I),
the nodal forces are -V P Dm^-T. This is the warped-stiffness force -R K (R^T x - X) of the
paper's simulator, written in stress form (fewer flops than the 12x12 matrix).

Rotations come from the warm-started quaternion iteration of Mueller et al. 2016 ("A robust
method to extract the rotational part of deformations"): it stays a proper rotation for
inverted elements and, warm-started from the last substep, needs one or two iterations.

2D uses plane strain with an out-of-plane depth of 1 m; the rotation is exact.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from sdexp.sim.physics.native import library
from sdexp.sim.physics.quadratic import ROTATION_PER_POINT, p2_range_2d, p2_range_3d, rotation

POLAR_ITERATIONS = 2


@dataclass
class FemModel:
    dim: int
    rest: np.ndarray      # (nv, dim) rest positions (quadratic: corners, then mid-edge nodes)
    elems: np.ndarray     # (ne, dim+1) int32, positively oriented; quadratic (ne, 10 | 6)
    Bm: np.ndarray        # (ne, dim, dim) inverse rest edge matrix Dm^-1 of the corners
    vol: np.ndarray       # (ne,) rest volume (2D: area x 1 m depth)
    mass: np.ndarray      # (nv,) lumped mass
    mu: float
    lam: float

    @property
    def n_elems(self) -> int:
        return len(self.elems)

    @property
    def order(self) -> int:
        """1 for linear elements, 2 for quadratic ones."""
        return 1 if self.elems.shape[1] == self.dim + 1 else 2

    @property
    def n_rotations(self) -> int:
        """Warm-start quaternions the 3D kernels keep: one per element, or one per quadrature
        point of a quadratic tet."""
        return self.n_elems * (4 if self.order == 2 else 1)


def lame(youngs_modulus: float, poisson_ratio: float) -> tuple[float, float]:
    """(mu, lambda); the same formulas serve 3D and 2D plane strain."""
    E, nu = youngs_modulus, poisson_ratio
    return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))


def signed_volumes(points: np.ndarray, elems: np.ndarray) -> np.ndarray:
    d = points.shape[1]
    D = np.stack([points[elems[:, k + 1]] - points[elems[:, 0]] for k in range(d)], axis=-1)
    return np.linalg.det(D) / (6.0 if d == 3 else 2.0)


def build_fem(rest: np.ndarray, elems: np.ndarray, total_mass: float,
              youngs_modulus: float, poisson_ratio: float) -> FemModel:
    """Precompute rest quantities. Linear elements (ne, dim+1): mass lumped evenly to the
    vertices. Quadratic ones (ne, 10 | 6, quadratic.quadratic_mesh): HRZ-lumped."""
    from sdexp.sim.physics.quadratic import lumped_mass, nodes_per_element

    rest = np.ascontiguousarray(rest, dtype=np.float64)
    elems = np.ascontiguousarray(elems, dtype=np.int32)
    d = rest.shape[1]
    if elems.shape[1] not in (nodes_per_element(d, 1), nodes_per_element(d, 2)):
        raise ValueError(f"{d}D elements need {nodes_per_element(d, 1)} or {nodes_per_element(d, 2)} "
                         f"nodes, not {elems.shape[1]}")
    Dm = np.stack([rest[elems[:, k + 1]] - rest[elems[:, 0]] for k in range(d)], axis=-1)
    vol = np.linalg.det(Dm) / (6.0 if d == 3 else 2.0)
    if np.any(vol <= 0):
        raise ValueError(f"{int(np.sum(vol <= 0))} elements are inverted or degenerate at rest")
    Bm = np.ascontiguousarray(np.linalg.inv(Dm))
    density = total_mass / vol.sum()
    if elems.shape[1] == d + 1:
        mass = np.zeros(len(rest))
        np.add.at(mass, elems.ravel(), np.repeat(density * vol / (d + 1), d + 1))
    else:
        mass = lumped_mass(len(rest), elems, density * vol)
    if np.any(mass <= 0):
        raise ValueError("mesh has vertices that belong to no element")
    mu, lam = lame(youngs_modulus, poisson_ratio)
    return FemModel(d, rest, elems, Bm, vol, mass, mu, lam)


# --------------------------------------------------------------------------------------------
# Element kernels. Scalar locals only: per-element temporary arrays inside a parallel loop
# halve the speed.
# --------------------------------------------------------------------------------------------

@nb.njit(fastmath=True, cache=True, error_model="numpy")
def corotated_range_3d(x, elems, Bm, vol, mu, lam, q, f, e0, e1, real):
    """Add the nodal forces of tets [e0, e1) into f (nv, 3); update their warm-start
    quaternions q (ne, 4). Returns the number of inverted tets (det F <= 0).
    The reference for kernels.c, which runs the same arithmetic about 3x faster.
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
        inverted += corotated_range_3d(xs, el, bm, vo, mu, lam, qs, fb[t], t * chunk, min(ne, (t + 1) * chunk), real)
    return inverted


@nb.cfunc(_C_SIGNATURE, cache=True)
def corotated_cfunc_3d(x, elems, Bm, vol, mu, lam, q, fbuf, nv, ne, nt):
    """kernels.c's corotated_forces_3d in numba, behind the same C signature: the fallback
    when no compiler works (one thread; chunk t still goes to buffer t)."""
    return _linear_chunks(x, elems, Bm, vol, mu, lam, q, fbuf, nv, ne, nt, np.float64)


@nb.cfunc(_C_SIGNATURE, cache=True)
def corotated_cfunc_3d_f32(x, elems, Bm, vol, mu, lam, q, fbuf, nv, ne, nt):
    """corotated_cfunc_3d in float32 (kernels.c's corotated_forces_3d_f32): Bm, vol, q float32."""
    return _linear_chunks(x, elems, Bm, vol, mu, lam, q, fbuf, nv, ne, nt, np.float32)


@nb.njit(cache=True)
def elastic_forces_3d(kernel, x, elems, Bm, vol, mu, lam, q, fbuf):
    """Tet forces into one buffer per thread, fbuf (nt, nv, 3), by a kernel with kernels.c's
    C signature (threads inside the kernel). Returns the number of inverted tets."""
    return kernel(x.ctypes.data, elems.ctypes.data, Bm.ctypes.data, vol.ctypes.data, mu, lam,
                  q.ctypes.data, fbuf.ctypes.data, x.shape[0], elems.shape[0], fbuf.shape[0])


@nb.njit(fastmath=True, cache=True, error_model="numpy")
def corotated_range_2d(x, elems, Bm, vol, mu, lam, f, e0, e1, real):
    """Triangle version of corotated_range_3d (the 2D rotation is exact, no warm start)."""
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
def elastic_forces_2d(x, elems, Bm, vol, mu, lam, fbuf, real):
    """elastic_forces_3d for triangles (numba is fast enough here)."""
    ne = elems.shape[0]
    nt = fbuf.shape[0]
    chunk = (ne + nt - 1) // nt
    inverted = 0
    for t in nb.prange(nt):
        fbuf[t] = 0.0
        inverted += corotated_range_2d(x, elems, Bm, vol, mu, lam, fbuf[t], t * chunk, min(ne, (t + 1) * chunk), real)
    return inverted


@dataclass(frozen=True)
class Kernels:
    """The kernels that run: ``library``, the compiled kernels.c (sdexp.sim.physics.native) whose
    ``advance`` steps a whole Body, or None where it cannot be built; ``forces_3d``, the linear 3D
    force kernel with kernels.c's C signature (the compiled one, or else the numba cfunc) for
    the numba step and for elastic_forces; ``forces_3d_f32`` the same in float32."""
    library: object
    forces_3d: object
    forces_3d_f32: object

    def linear_3d(self, real):
        """The linear 3D force kernel in ``real`` (np.float64 | np.float32) arithmetic."""
        return self.forces_3d_f32 if real is np.float32 else self.forces_3d


def kernels() -> Kernels:
    """The one place that picks compiled or numba kernels (the library is built and loaded once
    per process, and logs which it is)."""
    lib = library()
    if lib is None:
        return Kernels(None, corotated_cfunc_3d.ctypes, corotated_cfunc_3d_f32.ctypes)
    return Kernels(lib, lib.corotated_forces_3d, lib.corotated_forces_3d_f32)


PRECISIONS = {"float64": np.float64, "float32": np.float32}   # sim.precision: the force arithmetic


def element_data(model: FemModel, real) -> tuple[np.ndarray, np.ndarray]:
    """(Bm, vol) in the force kernels' type ``real``: rounded once, not every substep."""
    return np.ascontiguousarray(model.Bm, dtype=real), np.ascontiguousarray(model.vol, dtype=real)


def elastic_forces(model: FemModel, x: np.ndarray, q: np.ndarray | None = None,
                   kernel=None, real=np.float64) -> np.ndarray:
    """Total elastic force on every vertex (nv, dim), for tests and the stability estimate
    (the simulator's loop fuses this with integration). ``q``: warm-start quaternions
    (model.n_rotations, 4) of type ``real``, updated. ``kernel``: a C-signature linear 3D kernel,
    by default the compiled one; quadratic elements use the numba reference (kernels.c runs
    them in the step). ``real``: the arithmetic (sim.precision)."""
    fbuf = np.zeros((1,) + x.shape)
    if model.dim == 3:
        q = rest_quaternions(model.n_rotations).astype(real) if q is None else q
    Bm, vol = element_data(model, real)
    element_forces(kernel or kernels().linear_3d(real), x, model.elems, Bm, vol,
                   model.mu, model.lam, q if model.dim == 3 else np.zeros((0, 4), real), fbuf, real)
    return fbuf[0]


@nb.njit(cache=True)
def element_forces(kernel, x, elems, Bm, vol, mu, lam, q, fbuf, real):
    """Elastic forces of any element kind into one buffer per thread (fbuf (nt, nv, dim));
    the numba step (integrator.advance) and elastic_forces call this. Linear 3D runs ``kernel``
    (C signature, of Bm's type); quadratic elements their numba reference, one chunk per buffer.
    ``real``: the arithmetic, Bm's, vol's and q's type. Returns the number of inverted elements."""
    nodes = elems.shape[1]
    if nodes == 4:
        return elastic_forces_3d(kernel, x, elems, Bm, vol, mu, lam, q, fbuf)
    if nodes == 3:
        return elastic_forces_2d(x, elems, Bm, vol, mu, lam, fbuf, real)
    ne = elems.shape[0]
    nt = fbuf.shape[0]
    chunk = (ne + nt - 1) // nt
    inverted = 0
    for t in range(nt):
        fbuf[t] = 0.0
        e0, e1 = t * chunk, min(ne, (t + 1) * chunk)
        if nodes == 10:
            inverted += p2_range_3d(x, elems, Bm, vol, mu, lam, q, fbuf[t], e0, e1,
                                    ROTATION_PER_POINT, POLAR_ITERATIONS, real)
        else:
            inverted += p2_range_2d(x, elems, Bm, vol, mu, lam, fbuf[t], e0, e1, real)
    return inverted


def rest_quaternions(n: int) -> np.ndarray:
    q = np.zeros((n, 4))
    q[:, 0] = 1.0
    return q


def stable_substep(model: FemModel, safety: float, iterations: int = 60, seed: int = 0,
                   mass: np.ndarray | None = None) -> float:
    """safety x 2 / omega_max, omega_max^2 = largest eigenvalue of M^-1 K at rest (power
    iteration on the linearised force). Symplectic Euler is stable below 2 / omega_max.
    ``mass``: the inertial mass where it is not model.mass (sim.mass_scaling)."""
    mass = model.mass if mass is None else mass
    rng = np.random.default_rng(seed)
    d = model.dim
    u = rng.standard_normal(model.rest.shape)
    lam_max = 0.0
    eps = 1e-6 * np.ptp(model.rest, axis=0).max()
    for _ in range(iterations):
        u /= np.linalg.norm(u)
        Ku = -elastic_forces(model, model.rest + eps * u) / eps
        w = Ku / mass[:, None]
        lam_max = float(np.sum(u * w))
        u = w
    del d
    return safety * 2.0 / np.sqrt(1.05 * lam_max)  # 5% margin on the power-iteration estimate
