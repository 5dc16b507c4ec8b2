"""The reduced model's state and its step (the numba kernel ``advance``): symplectic Euler in the
generalised speeds of sdexp.sim.reduced.model, the damping of the full model's step written in
them (the absolute damping scales every generalised speed; the deformation damping keeps ``keep``
of zd and hands the angular momentum it carried to w, as the full step's rigid fit does), and
the full model's force kernels over the cubature's sub-mesh.

``ReducedBody`` offers what the simulator reads of a full ``Body``: run, x and v (the whole mesh,
rebuilt on demand), the rotors' directions, the effects' external forces ``fext``."""
from __future__ import annotations

import ctypes

import numba as nb
import numpy as np

from sdexp.sim.physics.fem import PRECISIONS, FemModel, kernels
from sdexp.sim.physics.integrator import Body
from sdexp.sensing.rotations import matrix_from_quat, quat_from_matrix
from sdexp.sim.physics.reference import element_forces, rotation
from sdexp.sim.reduced.model import ReducedModel

# kernels.c's forces_only(Step *, reps) with the Step passed as an address, so numba can call it
_FORCES_ONLY = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_int64)


@nb.cfunc(nb.types.int32(nb.types.voidptr, nb.types.int64))
def _no_forces(step, reps):   # stands in where no compiler works (the numba kernels run instead)
    return 0


@nb.njit(inline="always")
def _cross(a, b):
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


@nb.njit(cache=True)
def quat_matrix(q):
    """The rotation matrix of the unit quaternion q (w, x, y, z): the force kernels' ``rotation``."""
    return np.array(rotation(q[0], q[1], q[2], q[3], np.float64)).reshape(3, 3)


@nb.njit(cache=True, fastmath=True)
def _mv(A, x, out):
    """out = A x, one thread, no BLAS (its threads cost more than these products take)."""
    n, k = A.shape
    for i in range(n):
        acc = 0.0
        for j in range(k):
            acc += A[i, j] * x[j]
        out[i] = acc


@nb.njit(cache=True, fastmath=True)
def _mtv(A, y, out):
    """out = A^T y from the same rows as _mv reads: one copy of the basis rows, in cache."""
    n, k = A.shape
    out[:] = 0.0
    for i in range(n):
        yi = y[i]
        for j in range(k):
            out[j] += A[i, j] * yi


@nb.njit(cache=True)
def _internal(forces, step, sub_x, sub_fbuf, kernel, z, cub_X, cub_Phi, elems, Bm, vol, mu, lam, q,
              fbuf, rho, fz, fix, real):
    """The cubature's reduced internal force at z into fz, plus the linear modes' stiffness fix
    (ReducedModel.stiffness_fix); returns the inverted elements. With a compiled ``step``
    (kernels.c's Step of the cubature's sub-mesh, as bytes) its forces_only runs on sub_x into
    sub_fbuf; else the numba kernels on q, fbuf. Rotations warm-started."""
    nc, d = cub_X.shape
    _mv(cub_Phi, z, rho)
    if step.shape[0] > 0:
        flat = sub_x.reshape(-1)
        X = cub_X.reshape(-1)
        for i in range(flat.shape[0]):
            flat[i] = X[i] + rho[i]
        inverted = forces(step.ctypes.data, 1)
        _mtv(cub_Phi, sub_fbuf[0].reshape(-1), fz)
    else:
        x = cub_X + rho.reshape(nc, d)
        inverted = element_forces(kernel, x, elems, Bm, vol, mu, lam, q, fbuf, real)
        _mtv(cub_Phi, fbuf[0].reshape(-1), fz)
    for i in range(fix.shape[0]):
        acc = 0.0
        for j in range(fix.shape[1]):
            acc += fix[i, j] * z[j]
        fz[i] += acc
    return inverted


@nb.njit(cache=True, fastmath=True)
def advance(forces, step, sub_x, sub_fbuf, kernel, n_sub, dt, c, v, quat, w, z, zd, dim, total_mass, gravity,
            scale, keep, cub_X, cub_Phi, elems, Bm, vol, mu, lam, cq, fbuf, fix,
            rot_X, rot_Phi, faces, face_ptr, verts, vert_ptr, weights, thrust, dirs,
            S0, P, Q, a, F_world, tau_ext, fz_ext, real):
    """n_sub substeps; returns (the most inverted cubature elements in a substep, the largest
    squared speed of a rotor patch's node after them; an approximation: the deformation's part of
    rho in w x rho is left out). State arrays (c, v, quat, w, z, zd) are updated in place."""
    r = z.shape[0]
    nr = rot_X.shape[0]
    worst = 0
    eye = np.eye(3)
    rho = np.empty(cub_Phi.shape[0])
    fz = np.empty(r)
    fr = np.empty(r)
    rho_r = np.empty((nr, 3))
    frot = np.zeros((nr, 3))
    T = np.empty((r, 3, 3))
    T2 = np.empty((r, 3, 3))
    B = np.empty((3, r))
    for _ in range(n_sub):
        R = quat_matrix(quat)
        worst = max(worst, _internal(forces, step, sub_x, sub_fbuf, kernel, z, cub_X, cub_Phi, elems, Bm,
                                     vol, mu, lam, cq, fbuf, rho, fz, fix, real))
        # rotors: thrust along each patch's area-weighted normal (body frame), as kernels.c
        _mv(rot_Phi, z, rho_r.reshape(-1))
        rho_r += rot_X
        frot[:] = 0.0
        Fb = np.zeros(3)
        tau = tau_ext.copy()
        for k in range(thrust.shape[0]):
            nx = 0.0; ny = 0.0; nz = 0.0
            for f in range(face_ptr[k], face_ptr[k + 1]):
                i0 = faces[f, 0]; i1 = faces[f, 1]; i2 = faces[f, 2]
                ux = rho_r[i1, 0] - rho_r[i0, 0]; uy = rho_r[i1, 1] - rho_r[i0, 1]; uz = rho_r[i1, 2] - rho_r[i0, 2]
                if dim == 3:
                    qx = rho_r[i2, 0] - rho_r[i0, 0]; qy = rho_r[i2, 1] - rho_r[i0, 1]; qz = rho_r[i2, 2] - rho_r[i0, 2]
                    nx += uy * qz - uz * qy; ny += uz * qx - ux * qz; nz += ux * qy - uy * qx
                else:   # outward normal of a counter-clockwise boundary segment
                    nx += uy; ny -= ux
            inv = 1.0 / np.sqrt(nx * nx + ny * ny + nz * nz + 1e-300)
            nx *= inv; ny *= inv; nz *= inv
            for e in range(3):
                dirs[k, e] = R[e, 0] * nx + R[e, 1] * ny + R[e, 2] * nz
            for j in range(vert_ptr[k], vert_ptr[k + 1]):
                t = thrust[k] * weights[j]
                i = verts[j]
                fx = t * nx; fy = t * ny; fzz = t * nz
                frot[i, 0] += fx; frot[i, 1] += fy; frot[i, 2] += fzz
                Fb[0] += fx; Fb[1] += fy; Fb[2] += fzz
                tau[0] += rho_r[i, 1] * fzz - rho_r[i, 2] * fy
                tau[1] += rho_r[i, 2] * fx - rho_r[i, 0] * fzz
                tau[2] += rho_r[i, 0] * fy - rho_r[i, 1] * fx
        _mtv(rot_Phi, frot.reshape(-1), fr)
        # the inertia's polynomials in z (sdexp.sim.reduced.model)
        _mv(Q, z, T.reshape(-1))
        _mv(Q, zd, T2.reshape(-1))
        S = S0.copy()
        W = np.zeros((3, 3))
        Om2 = np.outer(w, w) - (w @ w) * eye
        rhs_z = np.empty(r)
        for j in range(r):
            zj = z[j]; zdj = zd[j]
            acc = 0.0
            for p in range(3):
                for q in range(3):
                    pt = P[j, p, q] + T[j, p, q]
                    S[p, q] += zj * (pt + P[j, q, p])
                    W[p, q] += zdj * pt
                    acc += Om2[p, q] * pt
            B[0, j] = a[j, 1, 2] - a[j, 2, 1] + T[j, 2, 1] - T[j, 1, 2]
            B[1, j] = a[j, 2, 0] - a[j, 0, 2] + T[j, 0, 2] - T[j, 2, 0]
            B[2, j] = a[j, 0, 1] - a[j, 1, 0] + T[j, 1, 0] - T[j, 0, 1]
            cor = (w[0] * (T2[j, 2, 1] - T2[j, 1, 2]) + w[1] * (T2[j, 0, 2] - T2[j, 2, 0])
                   + w[2] * (T2[j, 1, 0] - T2[j, 0, 1]))
            rhs_z[j] = fz[j] + fr[j] + fz_ext[j] - acc - 2.0 * cor
        I = np.trace(S) * eye - S
        rhs_w = tau - _cross(w, I @ w) - 2.0 * (np.trace(W) * w - W @ w)
        y = rhs_w - B @ rhs_z
        if dim == 3:
            wdot = np.linalg.solve(I - B @ B.T, y)
        else:
            wdot = np.zeros(3)
            wdot[2] = y[2] / (I[2, 2] - B[2] @ B[2])
        zdd = rhs_z - B.T @ wdot
        acc3 = (R @ Fb + F_world) / total_mass
        acc3[1] -= gravity
        # kick, the absolute damping
        for k in range(3):
            v[k] = (v[k] + dt * acc3[k]) * scale
            w[k] = (w[k] + dt * wdot[k]) * scale
        for j in range(r):
            zd[j] = (zd[j] + dt * zdd[j]) * scale
        # the deformation damping: zd keeps ``keep``, the angular momentum it carried goes to w
        if keep < 1.0:
            h = B @ zd
            if dim == 3:
                w += (1.0 - keep) * np.linalg.solve(I, h)
            else:
                w[2] += (1.0 - keep) * h[2] / I[2, 2]
            zd *= keep
        # drift
        for k in range(3):
            c[k] += dt * v[k]
        th = np.sqrt(w @ w) * dt
        if th > 0.0:
            sn = np.sin(0.5 * th) / (th / dt)
            d0 = np.cos(0.5 * th); d1 = sn * w[0]; d2 = sn * w[1]; d3 = sn * w[2]
            q0 = quat[0]; q1 = quat[1]; q2 = quat[2]; q3 = quat[3]
            quat[0] = q0 * d0 - q1 * d1 - q2 * d2 - q3 * d3
            quat[1] = q0 * d1 + q1 * d0 + q2 * d3 - q3 * d2
            quat[2] = q0 * d2 - q1 * d3 + q2 * d0 + q3 * d1
            quat[3] = q0 * d3 + q1 * d2 - q2 * d1 + q3 * d0
            quat /= np.sqrt(quat @ quat)
        for j in range(r):
            z[j] += dt * zd[j]
    # the fastest rotor-patch node (the rotors sit on the extremities that move fastest)
    _mv(rot_Phi, zd, rho_r.reshape(-1))
    R = quat_matrix(quat)
    vmax2 = 0.0
    for i in range(nr):
        rel = _cross(w, rot_X[i]) + rho_r[i]
        u = v + R @ rel
        vmax2 = max(vmax2, u @ u)
    return worst, vmax2


def reduced_stiffness(model: ReducedModel, eps: float = 1e-6, iterations: int = 4) -> np.ndarray:
    """The reduced stiffness at rest (r, r) of the step's internal force, by central differences
    (one body: its element rotations stay at rest's within eps); remembered on the model."""
    if not hasattr(model, "_stiffness"):
        body = ReducedBody(model)

        def force(z):
            for _ in range(iterations):
                f, _ = body.internal(z)
            return f
        K = np.zeros((model.r, model.r))
        h = eps * np.ptp(model.X, axis=0).max()
        for j in range(model.r):
            z = np.zeros(model.r)
            z[j] = h
            K[:, j] = -(force(z) - force(-z)) / (2 * h)
        model._stiffness = 0.5 * (K + K.T)
    return model._stiffness


def frequencies(model: ReducedModel, k: int = 8) -> np.ndarray:
    """The reduced model's first k free-free frequencies (Hz) at rest."""
    lam = np.sort(np.linalg.eigvalsh(reduced_stiffness(model)))
    return np.sqrt(np.maximum(lam[:k], 0.0)) / (2 * np.pi)


def stable_substep(model: ReducedModel, safety: float) -> float:
    """safety x 2 / omega_max of the reduced stiffness at rest (symplectic Euler's limit, with
    the full model's 5% margin)."""
    return safety * 2.0 / float(np.sqrt(1.05 * max(np.linalg.eigvalsh(reduced_stiffness(model))[-1], 1e-12)))


@nb.njit(cache=True)
def _nodes(c, vel, quat, w, z, zd, X3, Phi):
    """x = c + R rho, v = vel + R (w x rho + Phi zd), rho = X3 + Phi z, for the rows X3 (n, 3)
    and Phi (n 3, r): compiled, as the readings need them every control step."""
    n = X3.shape[0]
    R = quat_matrix(quat)
    rho = np.empty(3 * n)
    rd = np.empty(3 * n)
    _mv(Phi, z, rho)
    _mv(Phi, zd, rd)
    x = np.empty((n, 3))
    v = np.empty((n, 3))
    for i in range(n):
        p0 = X3[i, 0] + rho[3 * i]; p1 = X3[i, 1] + rho[3 * i + 1]; p2 = X3[i, 2] + rho[3 * i + 2]
        u0 = w[1] * p2 - w[2] * p1 + rd[3 * i]
        u1 = w[2] * p0 - w[0] * p2 + rd[3 * i + 1]
        u2 = w[0] * p1 - w[1] * p0 + rd[3 * i + 2]
        for a in range(3):
            x[i, a] = c[a] + R[a, 0] * p0 + R[a, 1] * p1 + R[a, 2] * p2
            v[i, a] = vel[a] + R[a, 0] * u0 + R[a, 1] * u1 + R[a, 2] * u2
    return x, v


class ReducedBody:
    """The state of one reduced body and the call that advances it (integrator.Body's role)."""

    def __init__(self, model: ReducedModel, precision: str = "float64"):
        self.model = m = model
        self.fem = model.drone.fem
        self.dim = m.dim
        self.c = np.zeros(3)
        self.c[:m.dim] = m.com
        self.vel = np.zeros(3)
        self.quat = np.array([1.0, 0.0, 0.0, 0.0])
        self.w = np.zeros(3)
        self.z = np.zeros(m.r)
        self.zd = np.zeros(m.r)
        # the basis rows the step reads every substep, in single precision: half the memory traffic
        # of the products that dominate the step; the sums and the state stay in double
        self.cub_Phi = m.cub_Phi.astype(np.float32)
        self.rot_Phi = m.rot_Phi.astype(np.float32)
        self.pushed = True   # effects may write fext (the simulator says when none do)
        self.thrust = np.zeros(model.drone.num_rotors)
        self._dirs = np.zeros((model.drone.num_rotors, 3))
        self.fext = np.zeros_like(self.fem.rest)   # effects' external forces, world frame (nv, dim)
        self._kernel = kernels().linear_3d(PRECISIONS[precision])
        self._bind_forces(precision)
        self._version = 0
        self._full = (-1, None, None)

    def _bind_forces(self, precision: str) -> None:
        """The cubature's forces: kernels.c's, through a Body of the cubature's sub-mesh (its
        element data laid out as the compiled step reads them, the cubature weights in the
        volumes), or where no compiler works the numba kernels."""
        m, f = self.model, self.fem
        self.real = PRECISIONS[precision]
        sub = FemModel(m.dim, m.cub_X, m.cub_elems, m.cub_Bm, m.cub_vol, np.ones(len(m.cub_X)), f.mu, f.lam)
        self._sub = Body(sub, 1, precision=precision)
        self.cq = self._sub.q if self._sub._lib is None else np.zeros((0, 4), self.real)
        self.fbuf = self._sub.fbuf
        self._Bm, self._vol = (a.astype(self.real) for a in (m.cub_Bm, m.cub_vol))
        if self._sub._lib is None:
            self._forces, self._step = _no_forces.ctypes, np.zeros(0, np.uint8)
        else:
            self._forces = _FORCES_ONLY(ctypes.cast(self._sub._lib.forces_only, ctypes.c_void_p).value)
            self._step = np.frombuffer(self._sub._step, np.uint8)

    def internal(self, z: np.ndarray):
        """(f_z, inverted elements): the cubature's reduced internal force at z."""
        m = self.model
        fz = np.empty(m.r)
        inverted = _internal(self._forces, self._step, self._sub.x, self._sub.fbuf, self._kernel, z, m.cub_X,
                             self.cub_Phi, m.cub_elems, self._Bm, self._vol, self.fem.mu, self.fem.lam,
                             self.cq, self.fbuf, np.empty(m.cub_Phi.shape[0]), fz, m.stiffness_fix, self.real)
        return fz, inverted

    @property
    def dirs(self) -> np.ndarray:
        """Unit thrust direction of every rotor during the last substep (m, dim)."""
        return self._dirs[:, :self.dim]

    def copy_state(self) -> tuple:
        return tuple(a.copy() for a in (self.c, self.vel, self.quat, self.w, self.z, self.zd))

    def restore(self, state: tuple) -> None:
        for a, b in zip((self.c, self.vel, self.quat, self.w, self.z, self.zd), state):
            a[:] = b
        self._version += 1

    def translate(self, offset) -> None:
        self.c[:self.dim] += offset
        self._version += 1

    def outside(self) -> int:
        """The first modal coordinate outside the range the model was fitted on (x its margin),
        or -1."""
        bad = np.flatnonzero((self.z < self.model.z_lo) | (self.z > self.model.z_hi))
        return int(bad[0]) if len(bad) else -1

    # ------------------------------------------------------------------ the state as the full mesh's
    @property
    def R(self) -> np.ndarray:
        return matrix_from_quat(self.quat)

    def nodes(self, X3: np.ndarray, Phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World positions and velocities (n, dim) of the nodes with rest rows X3 (n, 3) and basis
        rows Phi (n 3, r)."""
        x, v = _nodes(self.c, self.vel, self.quat, self.w, self.z, self.zd, X3, Phi)
        return x[:, :self.dim], v[:, :self.dim]

    def _whole(self):
        if self._full[0] != self._version:
            m = self.model
            x, v = self.nodes(m.X3, m.Phi3.reshape(-1, m.r))
            self._full = (self._version, x, v)
        return self._full

    @property
    def x(self) -> np.ndarray:
        """Every node's position (nv, dim), rebuilt from the reduced state (a copy: writing into
        it moves nothing)."""
        return self._whole()[1]

    @property
    def v(self) -> np.ndarray:
        return self._whole()[2]

    def sensor_nodes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x, v, idx): positions and velocities of the IMU patches' nodes and the patches'
        indices into them: the readings without rebuilding the mesh."""
        m = self.model
        x, v = self.nodes(m.imu_X, m.imu_Phi)
        return x, v, m.imu_idx

    def set_full(self, x: np.ndarray, v: np.ndarray) -> None:
        """The reduced state nearest a full one (positions, velocities (nv, dim)): the best-fit
        frame and the mass-projected deformation; the centre of mass's velocity, and the angular
        and modal velocities that fit the rest in the mass norm."""
        m, d = self.model, self.dim
        c, R, z = m.frame_and_coordinates(np.asarray(x, float))
        mass = self.fem.mass
        vc = mass @ v / mass.sum()
        R3 = np.eye(3)
        R3[:d, :d] = R
        rel = np.zeros((len(mass), 3))
        rel[:, :d] = v - vc
        rel = rel @ R3                                               # body frame
        rho = m.X3 + m.Phi3 @ z
        cols = [np.cross(np.eye(3)[a], rho) for a in range(3)] if d == 3 else [np.cross([0.0, 0.0, 1.0], rho)]
        G = np.concatenate([np.stack(cols, axis=-1), m.Phi3], axis=-1)   # (nv, 3, k + r)
        A = np.einsum("i,iak,ial->kl", mass, G, G)
        sol = np.linalg.solve(A, np.einsum("i,iak,ia->k", mass, G, rel))
        k = len(cols)
        w = np.zeros(3)
        w[3 - k:] = sol[:k]
        self.place(c, R, z, vc, w, sol[k:])

    def place(self, c, R, z, v=None, w=None, zd=None) -> None:
        """Set the state: centre of mass c, rotation R, modal coordinates z and their rates."""
        d = self.dim
        self.c[:] = 0.0
        self.c[:d] = c
        R3 = np.eye(3)
        R3[:d, :d] = R
        self.quat[:] = quat_from_matrix(R3)
        self.z[:] = z
        self.vel[:] = 0.0 if v is None else np.r_[v, np.zeros(3 - d)]
        self.w[:] = 0.0 if w is None else w
        self.zd[:] = 0.0 if zd is None else zd
        self._version += 1

    # ------------------------------------------------------------------ the step
    def run(self, n_sub: int, dt: float, thrust=None, damping: float = 0.0, gravity: float = 0.0,
            deform_damping: float = 0.0):
        m = self.model
        self.thrust[:] = 0.0 if thrust is None else thrust
        F_world, tau, fz = self._external()
        worst, vmax2 = advance(self._forces, self._step, self._sub.x, self._sub.fbuf, self._kernel, n_sub, dt, self.c,
                               self.vel, self.quat, self.w, self.z, self.zd, m.dim, m.total_mass, gravity,
                               1.0 / (1.0 + dt * damping), 1.0 / (1.0 + dt * deform_damping),
                               m.cub_X, self.cub_Phi, m.cub_elems, self._Bm, self._vol,
                               self.fem.mu, self.fem.lam, self.cq, self.fbuf, m.stiffness_fix,
                               m.rot_X, self.rot_Phi, m.rot_faces, m.drone.rotors.face_ptr,
                               m.rot_verts, m.drone.rotors.vert_ptr, m.drone.rotors.weights, self.thrust, self._dirs,
                               m.S0, m.P, m.Q, m.a, F_world, tau, fz, self.real)
        self._version += 1
        return worst, vmax2

    def _external(self):
        """The effects' forces (fext, world, held over the control step) as a world force, a
        body-frame torque about the centre of mass and a modal force."""
        m = self.model
        r = m.r
        rows = np.flatnonzero(np.any(self.fext != 0.0, axis=1)) if self.pushed else ()
        if len(rows) == 0:
            return np.zeros(3), np.zeros(3), np.zeros(r)
        f = np.zeros((len(rows), 3))
        f[:, :self.dim] = self.fext[rows]
        fb = f @ self.R                                           # body frame: R^T f
        Phi = m.Phi3[rows]                                        # (k, 3, r)
        rho = m.X3[rows] + Phi @ self.z
        return f.sum(axis=0), np.cross(rho, fb).sum(axis=0), np.einsum("kar,ka->r", Phi, fb)
