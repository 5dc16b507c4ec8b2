"""The reduced model's state as one vector and the Jacobians of its equations of motion: what
the privileged reduced-model LQR (sdexp.control.modal_lqr) observes and designs on.

    x = (c, phi, z, v, w, zd)      12 + 2 r entries, 2D drones alike (their out-of-plane rows are zero)

c the centre of mass (world), phi the rotation vector of the frame's rotation R (world; one chart,
singular only at a half turn), z the modal coordinates, v the centre of mass's velocity (world),
w the body-frame angular velocity, zd the modal velocities (sdexp.sim.reduced.model's equations).

The Jacobians are central differences of the step itself (``ReducedBody.run``) over one substep:
the derivative x_dot = F(x, u) is (x after one substep - x) / substep, so A and B are the
linearisation of exactly what the reduced simulator integrates (its cubature forces, damping,
rotor tractions along the deformed patches' normals), to first order in the substep.
"""
from __future__ import annotations

import numpy as np

from sdexp.sim.reduced.body import ReducedBody
from sdexp.sim.reduced.model import ReducedModel


def rotation_vector(quat: np.ndarray) -> np.ndarray:
    """phi with R = exp([phi]x), |phi| <= pi, of the unit quaternion (w, x, y, z)."""
    q = quat if quat[0] >= 0 else -quat
    s = np.linalg.norm(q[1:])
    return np.zeros(3) if s < 1e-15 else 2.0 * np.arctan2(s, q[0]) * q[1:] / s


def quaternion(phi: np.ndarray) -> np.ndarray:
    a = np.linalg.norm(phi)
    if a < 1e-15:
        return np.array([1.0, 0.5 * phi[0], 0.5 * phi[1], 0.5 * phi[2]]) / np.sqrt(1 + 0.25 * phi @ phi)
    return np.r_[np.cos(0.5 * a), np.sin(0.5 * a) * phi / a]


class Linearization:
    """The state vector of a reduced body, a full mesh's nearest one, and the Jacobians of the
    reduced equations at any (x, u), on a body of its own (the simulated one is never touched)."""

    def __init__(self, model: ReducedModel, substep: float, damping: float, deformation_damping: float,
                 gravity: float):
        self.model, self.r = model, model.r
        self.h, self.damping, self.deform_damping, self.gravity = substep, damping, deformation_damping, gravity
        self.body = ReducedBody(model)
        r = self.r
        self.slices = {"c": slice(0, 3), "phi": slice(3, 6), "z": slice(6, 6 + r), "v": slice(6 + r, 9 + r),
                       "w": slice(9 + r, 12 + r), "zd": slice(12 + r, 12 + 2 * r)}
        self.n = 12 + 2 * r
        # difference steps: a millimetre, a milliradian, a thousandth of each modal coordinate's range
        span = np.maximum(model.z_hi - model.z_lo, 1e-12)
        self.eps = np.r_[np.full(3, 1e-3), np.full(3, 1e-3), 1e-3 * span, np.full(6, 1e-3), 1e-2 * span]

    def of_body(self, body: ReducedBody) -> np.ndarray:
        """x of a reduced body."""
        return np.concatenate([body.c, rotation_vector(body.quat), body.z, body.vel, body.w, body.zd])

    def of_nodes(self, x: np.ndarray, v: np.ndarray) -> np.ndarray:
        """x nearest the full mesh's positions and velocities (nv, dim): the best-fit frame, the
        mass-projected deformation and the speeds that fit the velocities (ReducedBody.set_full)."""
        self.body.set_full(x, v)
        return self.of_body(self.body)

    def place(self, x: np.ndarray) -> None:
        """The linearisation's body at state x (ReducedBody.copy_state's order)."""
        s = self.slices
        self.body.restore((x[s["c"]], x[s["v"]], quaternion(x[s["phi"]]), x[s["w"]], x[s["z"]], x[s["zd"]]))

    def derivative(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """F(x, u): the state's rate over one substep of the reduced step."""
        self.place(x)
        self.body.run(1, self.h, u, self.damping, self.gravity, self.deform_damping)
        d = self.of_body(self.body) - x
        s = self.slices["phi"]
        if np.linalg.norm(d[s]) > np.pi:   # the chart wrapped (|phi| crossed pi): the same rotation unwrapped
            phi = d[s] + x[s]
            d[s] = phi - 2 * np.pi * phi / np.linalg.norm(phi) - x[s]
        return d / self.h

    def jacobians(self, x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(F(x, u), dF/dx, dF/du) by central differences; the element rotations of the body's
        cubature converged at x first (its polar iteration is warm-started)."""
        self.place(x)
        for _ in range(6):
            self.body.internal(self.body.z)
        f0 = self.derivative(x, u)
        A = np.empty((self.n, self.n))
        for j in range(self.n):
            e = np.zeros(self.n)
            e[j] = self.eps[j]
            A[:, j] = (self.derivative(x + e, u) - self.derivative(x - e, u)) / (2 * self.eps[j])
        m = len(u)
        B = np.empty((self.n, m))
        for j in range(m):
            e = np.zeros(m)
            e[j] = 1e-2
            B[:, j] = (self.derivative(x, u + e) - self.derivative(x, u - e)) / 2e-2
        return f0, A, B
