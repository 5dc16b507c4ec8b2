"""Rotation conventions shared by the sensors, the controllers and the tests.

Euler angles e = (e_x, e_y, e_z) are angles about the x, y and z axes with

    R(e) = Ry(e_y) @ Rz(e_z) @ Rx(e_x)        (body-to-world)

so yaw about the vertical +Y axis is outermost and unbounded, and the gimbal lock sits at
|e_z| = 90 deg, a drone flipped on its side. (The usual Z-Y-X aerospace order would put the
lock at a 90 deg yaw here, because "up" is +Y.) All functions are batched over leading axes.
"""
from __future__ import annotations

import numba as nb
import numpy as np


def _rot(axis: int, a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    R = np.zeros(np.shape(a) + (3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R[..., axis, axis] = 1.0
    R[..., i, i] = c
    R[..., j, j] = c
    R[..., i, j] = -s
    R[..., j, i] = s
    return R


def matrix_from_euler(e: np.ndarray) -> np.ndarray:
    e = np.asarray(e, dtype=float)
    return _rot(1, e[..., 1]) @ _rot(2, e[..., 2]) @ _rot(0, e[..., 0])


def euler_from_matrix(R: np.ndarray) -> np.ndarray:
    ez = np.arcsin(np.clip(R[..., 1, 0], -1.0, 1.0))
    ex = np.arctan2(-R[..., 1, 2], R[..., 1, 1])
    ey = np.arctan2(-R[..., 2, 0], R[..., 0, 0])
    return np.stack([ex, ey, ez], axis=-1)


def tilt_from_euler(e: np.ndarray) -> np.ndarray:
    """The angle (rad, in [0, pi]) between the body's up axis R(e)[:, 1] and world +Y: the
    arccos of R(e)[1, 1] = cos e_x cos e_z (e_y, the yaw about +Y, does not tilt). One angle
    from all three: e_x = e_z = 180 deg is level (a yaw of 180 deg), not upside down."""
    e = np.asarray(e, dtype=float)
    return np.arccos(np.clip(np.cos(e[..., 0]) * np.cos(e[..., 2]), -1.0, 1.0))


def euler_rate_matrix(e: np.ndarray) -> np.ndarray:
    """E(e) with omega_world = E(e) @ e_dot: columns are the world axes the three angles
    turn about (x after Ry Rz, y, z after Ry)."""
    e = np.asarray(e, dtype=float)
    cy, sy = np.cos(e[..., 1]), np.sin(e[..., 1])
    cz, sz = np.cos(e[..., 2]), np.sin(e[..., 2])
    E = np.zeros(e.shape[:-1] + (3, 3))
    E[..., :, 0] = np.stack([cy * cz, sz, -sy * cz], axis=-1)
    E[..., 1, 1] = 1.0
    E[..., 0, 2] = sy
    E[..., 2, 2] = cy
    return E


def euler_rates(e: np.ndarray, omega_world: np.ndarray) -> np.ndarray:
    return np.linalg.solve(euler_rate_matrix(e), omega_world[..., None])[..., 0]


def skew(w: np.ndarray) -> np.ndarray:
    W = np.zeros(w.shape[:-1] + (3, 3))
    W[..., 0, 1], W[..., 0, 2] = -w[..., 2], w[..., 1]
    W[..., 1, 0], W[..., 1, 2] = w[..., 2], -w[..., 0]
    W[..., 2, 0], W[..., 2, 1] = -w[..., 1], w[..., 0]
    return W


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rodrigues: the rotation by angle |w| about w."""
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = th < 1e-12
    a = np.where(small, 1.0, np.sin(th) / np.where(small, 1.0, th))
    b = np.where(small, 0.5, (1 - np.cos(th)) / np.where(small, 1.0, th) ** 2)
    return np.eye(3) + a * K + b * (K @ K)


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """(w, x, y, z) via the eigenvector of Bar-Itzhack's symmetric 4x4 matrix: robust for
    every rotation and batched."""
    R = np.asarray(R)
    K = np.zeros(R.shape[:-2] + (4, 4))
    K[..., 0, 0] = R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2]
    K[..., 1, 1] = R[..., 0, 0] - R[..., 1, 1] - R[..., 2, 2]
    K[..., 2, 2] = R[..., 1, 1] - R[..., 0, 0] - R[..., 2, 2]
    K[..., 3, 3] = R[..., 2, 2] - R[..., 0, 0] - R[..., 1, 1]
    K[..., 0, 1] = K[..., 1, 0] = R[..., 2, 1] - R[..., 1, 2]
    K[..., 0, 2] = K[..., 2, 0] = R[..., 0, 2] - R[..., 2, 0]
    K[..., 0, 3] = K[..., 3, 0] = R[..., 1, 0] - R[..., 0, 1]
    K[..., 1, 2] = K[..., 2, 1] = R[..., 1, 0] + R[..., 0, 1]
    K[..., 1, 3] = K[..., 3, 1] = R[..., 0, 2] + R[..., 2, 0]
    K[..., 2, 3] = K[..., 3, 2] = R[..., 2, 1] + R[..., 1, 2]
    _, vec = np.linalg.eigh(K / 3.0)
    return vec[..., :, -1]


def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = (q[..., i] for i in range(4))
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def average_rotations(R: np.ndarray) -> np.ndarray:
    """Markley et al. 2007: the average of rotations (k, 3, 3) is the quaternion that is the
    principal eigenvector of sum q q^T (sign-invariant, so q and -q agree)."""
    q = quat_from_matrix(R)
    M = np.einsum("ki,kj->ij", q, q)
    _, vec = np.linalg.eigh(M)
    return matrix_from_quat(vec[:, -1])


@nb.njit(cache=True)
def euler_and_rates(R, omega_world):
    """euler_from_matrix(R) and euler_rates(e, omega_world) for one rotation, compiled, with
    E(e)^-1 in closed form (E's columns (cy cz, sz, -sy cz), (0, 1, 0), (sy, 0, cy))."""
    ez = np.arcsin(min(1.0, max(-1.0, R[1, 0])))
    ex = np.arctan2(-R[1, 2], R[1, 1])
    ey = np.arctan2(-R[2, 0], R[0, 0])
    cy, sy, sz = np.cos(ey), np.sin(ey), np.sin(ez)
    ex_dot = (cy * omega_world[0] - sy * omega_world[2]) / np.cos(ez)
    return (np.array([ex, ey, ez]),
            np.array([ex_dot, omega_world[1] - sz * ex_dot, sy * omega_world[0] + cy * omega_world[2]]))
