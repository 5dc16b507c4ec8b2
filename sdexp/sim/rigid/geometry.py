"""The drone seen as a rigid body: mass, inertia and rotor geometry from vertex positions.

This is the privileged knowledge of the paper's rigid baselines (supplement G): the rigid LQR
reads it once from the rest shape, the geometry-updating LQR from the deformed mesh at every
control step. The learned-dynamics controller never sees it.
"""
from __future__ import annotations

import numpy as np

from sdexp.sim.drone import RotorPatches
from sdexp.sim.mesh.surface import face_normals


def wrench_matrix(rotor_pos: np.ndarray, rotor_dir: np.ndarray) -> np.ndarray:
    """[M_f; M_t]: rotor thrusts -> force and torque about the origin of rotor_pos."""
    r, d = rotor_pos, rotor_dir
    torque = np.cross(r, d) if r.shape[1] == 3 else (r[:, 0] * d[:, 1] - r[:, 1] * d[:, 0])[:, None]
    return np.vstack([d.T, torque.T])


def hover_thrust(mass: float, rotor_pos: np.ndarray, rotor_dir: np.ndarray, gravity: float) -> np.ndarray:
    """Minimum-norm thrusts with a force that cancels gravity (along -y) and no roll or pitch
    torque at level attitude (exactly), and as little horizontal force and yaw torque as the
    rotors can make without waste: those are asked for only along wrench directions the rotors
    make with at least 1% of their strongest singular value. Near-vertical rotors make a
    horizontal force or yaw of a few millinewtons per newton, and cancelling that exactly had
    traded up to 13 N of thrust (the orange peel, past its 10 N limit; the quadratic flower
    4 N against a 1.1 N hover)."""
    W = wrench_matrix(rotor_pos, rotor_dir)
    target = np.zeros(W.shape[0])
    target[1] = mass * gravity
    level = [1, 3, 5] if W.shape[0] == 6 else [1, 2]
    rest = [k for k in range(W.shape[0]) if k not in level]
    u = np.linalg.lstsq(W[level], target[level], rcond=None)[0]
    _, sv, vt = np.linalg.svd(W[level])
    free = vt[int(np.sum(sv > 1e-12 * sv[0])):].T          # thrusts that leave lift and tilt alone
    if free.shape[1]:
        # least squares on the horizontal force and yaw within those, truncated absolutely
        a_u, a_s, a_vt = np.linalg.svd(W[rest] @ free, full_matrices=False)
        keep = a_s > 1e-2 * np.linalg.norm(W, 2)
        u = u - free @ (a_vt[keep].T @ ((a_u[:, keep].T @ (W[rest] @ u)) / a_s[keep]))
    return u


def rest_hover_thrust(drone, gravity: float) -> np.ndarray:
    """hover_thrust of the drone's undeformed shape."""
    fem = drone.fem
    mass, _, _, pos, dirs = rigid_body(fem.rest, fem.mass, drone.rotors, np.eye(fem.dim))
    return hover_thrust(mass, pos, dirs, gravity)


def rigid_prior(drone, gravity: float) -> dict:
    """The rest shape as a rigid body at level, as the learned model's prior (model.prior: rigid,
    sdexp.model.training.prior_maps): target -> (acceleration per newton of each rotor, constant
    acceleration): p_dot's the thrust directions over the mass and the weight's -g along y, e_dot's
    the torques about the centre of mass over the inertia and nothing (at level, whatever the
    yaw, the Euler rates are the body's angular velocity: R = Ry Rz Rx, sdexp.sensing.rotations).
    Plain arrays: the learning side never reads the drone itself."""
    fem = drone.fem
    dim = fem.dim
    mass, _, inertia, pos, dirs = rigid_body(fem.rest, fem.mass, drone.rotors, np.eye(dim))
    W = wrench_matrix(pos, dirs)
    weight = np.zeros(dim)
    weight[1] = -float(gravity)
    turn = np.linalg.solve(inertia, W[dim:])
    return {"p_dot_next": (W[:dim] / mass, weight), "e_dot_next": (turn, np.zeros(turn.shape[0]))}


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
