"""The rigid baselines of supplement G: Newton-Euler dynamics of a rigid multicopter in
manipulator form, linearised by autograd at the hover fixed point, and LQR on it.

    state  x = (p, e, p_dot, e_dot)            (3D: 12 entries; 2D: p in R^2, e = theta)
    m p_ddot = m g + R(e) M_f u
    J w_dot + w x J w = M_t u,   w = R^T E(e) e_dot  (body rates; E maps Euler rates to world rates)

with M_f's columns the rotor thrust directions d_i and M_t's the torques r_i x d_i (the
simulated rotors are counter-rotating pairs: no reaction torque, the b_i lambda_i term is 0).
The Euler angles are sdexp's (R = Ry Rz Rx, sdexp.sensing.rotations), so the second equation is
solved in the world frame: e_ddot = E^-1 (w_dot_world - E_dot e_dot).

:class:`RigidLQR` computes K once from a geometry (the paper's "LQR", rest shape) or, with
``update_every=1``, from the geometry its callback reports at every control step (the paper's
"geometry-updating LQR"). Both regulate to the task's goal position at level attitude with
u = u* - K (x - x_goal), u* the minimum-norm thrusts that hold the body at hover.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from sdexp.control.lqr import lqr_gain
from sdexp.control.tasks import Task, wrap_angle
from sdexp.sensing import State
from sdexp.sim.rigid.geometry import hover_thrust, wrench_matrix


@dataclass
class RigidGeometry:
    mass: float
    inertia: np.ndarray      # (3, 3) about the centre of mass, body frame; 2D: (1, 1)
    rotor_pos: np.ndarray    # (m, dim) body frame, from the centre of mass
    rotor_dir: np.ndarray    # (m, dim) unit thrust directions, body frame

    @property
    def dim(self) -> int:
        return self.rotor_pos.shape[1]

    def wrench_matrix(self) -> np.ndarray:
        """[M_f; M_t]: thrusts -> body-frame force and torque."""
        return wrench_matrix(self.rotor_pos, self.rotor_dir)

    def hover_thrust(self, gravity: float) -> np.ndarray:
        """Minimum-norm u* with zero torque and a force that cancels gravity at level attitude."""
        return hover_thrust(self.mass, self.rotor_pos, self.rotor_dir, gravity)


def _torch_rotation(e: torch.Tensor) -> torch.Tensor:
    def rot(axis, a):
        c, s = torch.cos(a), torch.sin(a)
        one, zero = torch.ones_like(a), torch.zeros_like(a)
        if axis == 0:
            rows = [[one, zero, zero], [zero, c, -s], [zero, s, c]]
        elif axis == 1:
            rows = [[c, zero, s], [zero, one, zero], [-s, zero, c]]
        else:
            rows = [[c, -s, zero], [s, c, zero], [zero, zero, one]]
        return torch.stack([torch.stack(r) for r in rows])
    return rot(1, e[1]) @ rot(2, e[2]) @ rot(0, e[0])


def _torch_rate_matrix(e: torch.Tensor) -> torch.Tensor:
    """E(e): omega_world = E e_dot (sdexp.sensing.rotations.euler_rate_matrix)."""
    cy, sy, cz, sz = torch.cos(e[1]), torch.sin(e[1]), torch.cos(e[2]), torch.sin(e[2])
    zero, one = torch.zeros_like(cy), torch.ones_like(cy)
    return torch.stack([torch.stack([cy * cz, zero, sy]),
                        torch.stack([sz, one, zero]),
                        torch.stack([-sy * cz, zero, cy])])


def rigid_dynamics(geom: RigidGeometry, gravity: float) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """f(x, u) -> x_dot of the rigid body (torch, float64, differentiable)."""
    t = lambda a: torch.as_tensor(np.asarray(a, dtype=float), dtype=torch.float64)
    W = t(geom.wrench_matrix())
    dim, m = geom.dim, geom.mass
    g = torch.zeros(dim, dtype=torch.float64)
    g[1] = -gravity
    J = t(geom.inertia)

    if dim == 2:
        def f2(x, u):
            th, c, s = x[2], torch.cos(x[2]), torch.sin(x[2])
            R = torch.stack([torch.stack([c, -s]), torch.stack([s, c])])
            wrench = W @ u
            acc = g + R @ wrench[:2] / m
            return torch.cat([x[3:6], acc, (wrench[2:] / J[0, 0])])
        return f2

    def f3(x, u):
        e, p_dot, e_dot = x[3:6], x[6:9], x[9:12]
        R, E = _torch_rotation(e), _torch_rate_matrix(e)
        wrench = W @ u
        acc = g + R @ wrench[:3] / m
        w = E @ e_dot                                        # world angular velocity
        Jw = R @ J @ R.T
        w_dot = torch.linalg.solve(Jw, R @ wrench[3:] - torch.linalg.cross(w, Jw @ w))
        E_dot = torch.func.jvp(_torch_rate_matrix, (e,), (e_dot,))[1]
        e_ddot = torch.linalg.solve(E, w_dot - E_dot @ e_dot)
        return torch.cat([p_dot, e_dot, acc, e_ddot])
    return f3


def linearize_rigid(geom: RigidGeometry, gravity: float, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) = (df/dx, df/du) of :func:`rigid_dynamics` at (x, u), by autograd."""
    f = rigid_dynamics(geom, gravity)
    xt = torch.as_tensor(x, dtype=torch.float64)
    ut = torch.as_tensor(u, dtype=torch.float64)
    A, B = torch.autograd.functional.jacobian(f, (xt, ut))
    return A.numpy(), B.numpy()


def rigid_state(state: State) -> np.ndarray:
    return np.concatenate([state.p, state.e, state.p_dot, state.e_dot])


class RigidLQR:
    """LQR on the rigid model; ``geometry()`` is asked once (rest shape) or every
    ``update_every`` control steps (deformed shape)."""

    def __init__(self, geometry: Callable[[], RigidGeometry], q_e: float, q_p: float, velocity_scale: float,
                 r: float, gravity: float, update_every: int | None = None, name: str = "rigid_lqr",
                 dt: float | None = None):
        self.geometry, self.gravity, self.update_every, self.name = geometry, gravity, update_every, name
        self.q_e, self.q_p, self.velocity_scale, self.r = q_e, q_p, velocity_scale, r
        self.K = None
        self.dt = dt   # None: continuous Riccati; a step: the sampled-data gain (sdexp.control.lqr)

    def design(self) -> None:
        """Measure the geometry, find the hover thrust, linearise, solve for K."""
        geom = self.geometry()
        dim = geom.dim
        self._ne = 3 if dim == 3 else 1
        self.u_star = geom.hover_thrust(self.gravity)
        A, B = linearize_rigid(geom, self.gravity, np.zeros(2 * (dim + self._ne)), self.u_star)
        q = np.concatenate([np.full(dim, self.q_p), np.full(self._ne, self.q_e)])
        Q = np.diag(np.concatenate([q, q * self.velocity_scale]))
        self.K = lqr_gain(A, B, Q, self.r * np.eye(len(self.u_star)), self.dt)

    def reset(self, task: Task) -> None:
        self.task, self.k = task, 0
        self.design()

    def act(self, t: float, state: State) -> np.ndarray:
        if self.update_every and self.k % self.update_every == 0 and self.k > 0:
            self.design()
        self.k += 1
        goal = self.task.goal(t)
        err = rigid_state(state) - np.concatenate([goal.p, goal.e, goal.p_dot, goal.e_dot])
        dim = len(goal.p)
        err[dim:dim + self._ne] = wrap_angle(err[dim:dim + self._ne])
        return self.u_star - self.K @ err
