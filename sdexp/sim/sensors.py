"""IMUs of supplement C: the simulator's end of the sensor pipeline.

An IMU is a patch of upper-surface vertices. Its frame comes from cross products of two
in-surface directions X' and Z' (weighted sums of the patch's vertex offsets, weights = the
rest offsets along x and z), calibrated so the IMU reads the identity at rest, as a mounted
IMU is. Its gyroscope reads the patch's rigid-fit angular velocity.

The readings, the sensor layout and their decomposition into the state (s, e, p and rates) are
the observation interface, sdexp.sensing: the only thing the learning/control side sees.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from sdexp.errors import UserError
from sdexp.sensing.state import Readings, SensorLayout


@dataclass
class ImuPatches:
    idx: np.ndarray        # (k, P) vertex indices, padded by repeating the first
    w: np.ndarray          # (k, P) averaging weights (1/n, 0 on padding)
    wx: np.ndarray         # (k, P) weights of X' (3D) / the tangent (2D)
    wz: np.ndarray         # (k, P) weights of Z' (3D only)
    rest: np.ndarray       # (k, 3, 3) rest frames (3D) or (k,) rest angles (2D)


# ------------------------------------------------------------------------------ building

def build_imu_patches(points, boundary, shape, radius: float, name: str) -> tuple[ImuPatches, SensorLayout]:
    from sdexp.sim.mesh.surface import patch_faces

    dim = shape.dim
    shared = shape.frame_imus.shape == shape.imus.shape and np.allclose(shape.frame_imus, shape.imus)
    anchors = shape.imus if shared else np.r_[shape.frame_imus, shape.imus]
    normals = shape.imu_normals if shared else np.r_[shape.frame_normals, shape.imu_normals]
    lists = []
    for k, (a, n) in enumerate(zip(anchors, normals)):
        verts = np.unique(boundary[patch_faces(points, boundary, a, n, radius)])
        if len(verts) < dim:
            raise UserError(f"drone {name}: IMU {k} binds {len(verts)} vertices; raise drone.imu_radius")
        lists.append(verts)
    P = max(len(v) for v in lists)
    K = len(lists)
    idx = np.zeros((K, P), dtype=np.int64)
    w = np.zeros((K, P))
    for k, v in enumerate(lists):
        idx[k] = np.r_[v, np.full(P - len(v), v[0])]
        w[k, :len(v)] = 1.0 / len(v)
    X = points[idx]                                    # (K, P, dim)
    off = (X - np.einsum("kp,kpd->kd", w, X)[:, None]) * (w > 0)[..., None]
    if dim == 3:
        # in-surface axes at rest: x and z projected onto the tangent plane
        nrm = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        tx = np.array([1.0, 0, 0]) - nrm[:, :1] * nrm
        tx /= np.linalg.norm(tx, axis=1, keepdims=True)
        tz = np.cross(tx, nrm)
        wx = np.einsum("kpd,kd->kp", off, tx)
        wz = np.einsum("kpd,kd->kp", off, tz)
    else:
        tang = np.c_[normals[:, 1], -normals[:, 0]]    # the outward normal turned clockwise
        tang /= np.linalg.norm(tang, axis=1, keepdims=True)
        wx = np.einsum("kpd,kd->kp", off, tang)
        wz = np.zeros_like(wx)
    patches = ImuPatches(idx, w, wx, wz, np.zeros(0))
    rot = _raw_frames(points, patches)
    if dim == 3 and np.any(np.abs(np.linalg.det(rot) - 1) > 1e-6):
        raise UserError(f"drone {name}: an IMU patch is degenerate (collinear vertices); raise drone.imu_radius")
    patches.rest = rot
    n_frame = 0 if shared else len(shape.frame_imus)
    frame_idx = np.arange(len(shape.imus)) if shared else np.arange(n_frame)
    periph_idx = np.arange(n_frame, n_frame + len(shape.imus))
    center = np.asarray(shape.center, dtype=float)
    r = shape.imus - center
    if dim == 3:
        r[:, 1] = 0.0
    r_hat = r / np.maximum(np.linalg.norm(r, axis=1, keepdims=True), 1e-12)
    return patches, SensorLayout(dim, frame_idx, periph_idx, r_hat)


@nb.njit(cache=True)
def _imu_kernel(x, v, idx, w, wx, wz):
    """Per IMU patch: mean position and velocity, the raw cross-product frame (3D: columns X,
    Y, Z; 2D: the angle of X'), and the rigid-fit angular velocity solving
    (sum |r|^2 1 - r r^T) omega = sum r x (v - v_mean)."""
    K, P = idx.shape
    dim = x.shape[1]
    pos = np.zeros((K, dim)); vel = np.zeros((K, dim))
    frames = np.zeros((K, 3, 3)); angles = np.zeros(K); omega = np.zeros((K, 3))
    for k in range(K):
        for j in range(P):
            for c in range(dim):
                pos[k, c] += w[k, j] * x[idx[k, j], c]
                vel[k, c] += w[k, j] * v[idx[k, j], c]
        xp = np.zeros(3); zp = np.zeros(3); b = np.zeros(3); I = np.zeros((3, 3))
        for j in range(P):
            if w[k, j] == 0.0:
                continue
            r = np.zeros(3); dv = np.zeros(3)
            for c in range(dim):
                r[c] = x[idx[k, j], c] - pos[k, c]
                dv[c] = v[idx[k, j], c] - vel[k, c]
                xp[c] += wx[k, j] * r[c]
                zp[c] += wz[k, j] * r[c]
            b += np.cross(r, dv)
            rr = r[0] * r[0] + r[1] * r[1] + r[2] * r[2]
            for i in range(3):
                I[i, i] += rr
                for c in range(3):
                    I[i, c] -= r[i] * r[c]
        if dim == 2:
            angles[k] = np.arctan2(xp[1], xp[0])
            omega[k, 2] = b[2] / I[2, 2]
            continue
        Y = np.cross(zp, xp)
        Y /= np.sqrt(Y @ Y)
        X = xp - (xp @ Y) * Y
        X /= np.sqrt(X @ X)
        Z = np.cross(X, Y)
        for c in range(3):
            frames[k, c, 0] = X[c]; frames[k, c, 1] = Y[c]; frames[k, c, 2] = Z[c]
        omega[k] = np.linalg.solve(I, b)
    return pos, vel, frames, angles, omega


def _raw_frames(x: np.ndarray, p: ImuPatches) -> np.ndarray:
    _, _, frames, angles, _ = _imu_kernel(x, np.zeros_like(x), p.idx, p.w, p.wx, p.wz)
    return angles if x.shape[1] == 2 else frames


def read_imus(t: float, x: np.ndarray, v: np.ndarray, p: ImuPatches) -> Readings:
    """Noise-free IMU readings from the vertex positions and velocities."""
    pos, vel, frames, angles, omega = _imu_kernel(x, v, p.idx, p.w, p.wx, p.wz)
    if x.shape[1] == 2:
        return Readings(t, pos, vel, np.angle(np.exp(1j * (angles - p.rest))), omega[:, 2])
    return Readings(t, pos, vel, frames @ np.swapaxes(p.rest, 1, 2), omega)


@nb.njit(cache=True)
def _rotate_by(delta, rot):
    """exp([delta]x) @ rot for each row: Rodrigues' formula, batched."""
    out = np.empty_like(rot)
    for k in range(rot.shape[0]):
        th = np.sqrt(delta[k] @ delta[k])
        a = np.sin(th) / th if th > 1e-12 else 1.0
        b = (1.0 - np.cos(th)) / (th * th) if th > 1e-12 else 0.5
        W = np.array([[0.0, -delta[k, 2], delta[k, 1]],
                      [delta[k, 2], 0.0, -delta[k, 0]],
                      [-delta[k, 1], delta[k, 0], 0.0]])
        out[k] = (np.eye(3) + a * W + b * (W @ W)) @ rot[k]
    return out


def add_noise(r: Readings, noise, rng: np.random.Generator) -> Readings:
    """Gaussian noise at the IMU level, with the levels of supplement E (``noise`` config)."""
    if not noise.enabled:
        return r
    a, ar = np.deg2rad(noise.angle_std_deg), np.deg2rad(noise.angle_rate_std_deg)
    pos = r.pos + rng.normal(0.0, noise.position_std, r.pos.shape)
    vel = r.vel + rng.normal(0.0, noise.velocity_std, r.vel.shape)
    omega = r.omega + rng.normal(0.0, ar, np.shape(r.omega))
    if r.rot.ndim == 1:
        rot = r.rot + rng.normal(0.0, a, r.rot.shape)
    else:
        rot = _rotate_by(rng.normal(0.0, a, (len(r.rot), 3)), r.rot)
    return Readings(r.t, pos, vel, rot, omega)
