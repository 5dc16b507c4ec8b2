"""The drone seen as a rigid body: mass, inertia and rotor geometry from vertex positions.

This is the privileged knowledge of the paper's rigid baselines (supplement G): the rigid LQR
reads it once from the rest shape, the geometry-updating LQR from the deformed mesh at every
control step. The learned-dynamics controller never sees it.
"""
from __future__ import annotations

import numpy as np

from sdexp.sim.drone import RotorPatches, face_normals


def wrench_matrix(rotor_pos: np.ndarray, rotor_dir: np.ndarray) -> np.ndarray:
    """[M_f; M_t]: rotor thrusts -> force and torque about the origin of rotor_pos."""
    r, d = rotor_pos, rotor_dir
    torque = np.cross(r, d) if r.shape[1] == 3 else (r[:, 0] * d[:, 1] - r[:, 1] * d[:, 0])[:, None]
    return np.vstack([d.T, torque.T])


def hover_thrust(mass: float, rotor_pos: np.ndarray, rotor_dir: np.ndarray, gravity: float) -> np.ndarray:
    """Minimum-norm thrusts with zero torque and a force that cancels gravity (along -y) at
    level attitude."""
    W = wrench_matrix(rotor_pos, rotor_dir)
    target = np.zeros(W.shape[0])
    target[1] = mass * gravity
    return np.linalg.lstsq(W, target, rcond=None)[0]


def rest_hover_thrust(drone, gravity: float) -> np.ndarray:
    """hover_thrust of the drone's undeformed shape."""
    fem = drone.fem
    mass, _, _, pos, dirs = rigid_body(fem.rest, fem.mass, drone.rotors, np.eye(fem.dim))
    return hover_thrust(mass, pos, dirs, gravity)


def deformation_patterns(drone) -> np.ndarray:
    """Orthonormal basis (m, k) of the rotor thrust patterns that put no net lift and no roll or
    pitch torque on the undeformed drone (3D: force y, torques x and z; 2D: force y, torque):
    they bend it and leave it level (flower: 9 rotors - 3 = 6 patterns; star 2). Horizontal force
    and yaw torque are left free: rotors on sloped surfaces have a little of both, and asking
    those to vanish too would leave no pattern on a drone with few rotors."""
    fem = drone.fem
    _, _, _, pos, dirs = rigid_body(fem.rest, fem.mass, drone.rotors, np.eye(fem.dim))
    W = wrench_matrix(pos, dirs)[[1, 3, 5] if fem.dim == 3 else [1, 2]]
    _, sv, vt = np.linalg.svd(W)
    rank = int(np.sum(sv > 1e-9 * sv[0]))
    return np.ascontiguousarray(vt[rank:].T)


def rotation_2d(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def rigid_body(points: np.ndarray, masses: np.ndarray, rotors: RotorPatches, R: np.ndarray
               ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(mass, centre of mass (world), inertia about it, rotor positions, unit thrust directions),
    the last three in the body frame R (body-to-world, dim x dim). 2D inertia is the scalar
    polar moment as a (1, 1) array."""
    mass = float(masses.sum())
    com = masses @ points / mass
    local = (points - com) @ R                      # rows R^T (x - com)
    if points.shape[1] == 3:
        inertia = np.eye(3) * np.einsum("i,ij,ij->", masses, local, local) - np.einsum("i,ij,ik->jk", masses, local, local)
    else:
        inertia = np.array([[np.einsum("i,ij,ij->", masses, local, local)]])
    faces = rotors.faces if points.shape[1] == 3 else rotors.faces[:, :2]
    normals = face_normals(points, faces) @ R
    pos, dirs = [], []
    for r in range(rotors.count):
        v = slice(rotors.vert_ptr[r], rotors.vert_ptr[r + 1])
        pos.append(rotors.weights[v] @ local[rotors.verts[v]])
        n = normals[rotors.face_ptr[r]:rotors.face_ptr[r + 1]].sum(axis=0)
        dirs.append(n / np.linalg.norm(n))
    return mass, com, inertia, np.array(pos), np.array(dirs)
