"""The observation interface: what the learning and control side may know of the drone.

The simulator (sdexp.sim.sensors) turns the mesh into IMU ``Readings``; everything above it
sees only those readings, the ``SensorLayout`` and the decomposed ``State``. The import-linter
contracts in pyproject.toml keep model, control and discrepancy on this side of the line.

decompose(readings) -> State:
  p = mean of all IMU positions;  e = Euler angles of the frame IMU (several: Markley average);
  s_i = atan2(-y_b . r_i, y_b . Y), y_b the peripheral IMU's Y axis in the body frame and r_i
  the unit in-plane direction from the centre to the IMU at rest: the wing's bend angle, positive
  when raised towards +Y. For a radial bend this is the paper's beta * arccos(y_b . Y). The
  paper's form jumps from +a to -a whenever the tilt turns sideways (its sign comes from a
  component that passes through zero while the arccos does not): 1.9% of the channel-steps of a
  default flower dataset did, up to 1.5 rad. The projected angle is continuous, so we use it.
  (The paper takes beta from the x-entry of v x r; in its own frame that entry vanishes for IMUs
  on the X and Z axes, so the rule is stated here by what it measures.)
  2D: e is the frame IMU's angle, s_i = beta_i (theta_i - theta_c), beta_i = sign(r_x).
Rates come from the gyroscopes and the velocities by the chain rule, never by differencing.
"""
from __future__ import annotations

from dataclasses import dataclass

import numba as nb
import numpy as np

from sdexp.sensing.rotations import average_rotations, euler_and_rates


@dataclass
class SensorLayout:
    """What the learning/control side may know about the sensors."""
    dim: int
    frame_idx: np.ndarray   # IMUs whose (averaged) frame defines e
    periph_idx: np.ndarray  # IMUs that define s, in order
    r_hat: np.ndarray       # (n_periph, dim) unit in-plane direction centre -> IMU at rest

    @property
    def n_s(self) -> int:
        return len(self.periph_idx)

    @property
    def n_e(self) -> int:
        return 3 if self.dim == 3 else 1


@dataclass
class Readings:
    t: float
    pos: np.ndarray    # (k, dim)
    vel: np.ndarray    # (k, dim)
    rot: np.ndarray    # (k, 3, 3) body-to-world (3D) or (k,) angle from +x (2D)
    omega: np.ndarray  # (k, 3) angular velocity in the world frame (3D) or (k,) (2D)


@dataclass
class State:
    s: np.ndarray
    e: np.ndarray
    p: np.ndarray
    s_dot: np.ndarray
    e_dot: np.ndarray
    p_dot: np.ndarray

    @property
    def x(self) -> np.ndarray:
        """(s, s_dot, e, e_dot, p, p_dot), the state vector of the learned dynamics."""
        return np.concatenate([self.s, self.s_dot, self.e, self.e_dot, self.p, self.p_dot])


# ------------------------------------------------------------------------------ decomposing

def decompose(r: Readings, layout: SensorLayout) -> State:
    p, p_dot = r.pos.mean(axis=0), r.vel.mean(axis=0)
    fi, pi = layout.frame_idx, layout.periph_idx
    if layout.dim == 2:
        th = np.angle(np.mean(np.exp(1j * r.rot[fi])))
        w = r.omega[fi].mean()
        beta = np.where(layout.r_hat[:, 0] >= 0, 1.0, -1.0)
        s = beta * np.angle(np.exp(1j * (r.rot[pi] - th)))
        return State(s, np.array([th]), p, beta * (r.omega[pi] - w), np.array([w]), p_dot)
    Rc = r.rot[fi[0]] if len(fi) == 1 else average_rotations(r.rot[fi])
    s, s_dot, e, e_dot = _bend_and_attitude(Rc, r.omega[fi].mean(axis=0), r.rot[pi], r.omega[pi], layout.r_hat)
    return State(s, e, p, s_dot, e_dot, p_dot)


@nb.njit(cache=True)
def _bend_and_attitude(Rc, wc, rot_p, omega_p, r_hat):
    """s, s_dot of the peripheral IMUs against the body frame Rc (angular velocity wc), and the
    Euler angles and rates of Rc."""
    n = rot_p.shape[0]
    s = np.empty(n); s_dot = np.empty(n)
    Rt = np.ascontiguousarray(Rc.T)
    for i in range(n):
        yw = np.ascontiguousarray(rot_p[i, :, 1])          # peripheral Y axis in the world
        yb = Rt @ yw
        ybd = Rt @ np.cross(omega_p[i] - wc, yw)           # its rate in the body frame
        # the bend in the plane through the body's Y axis and the IMU's rest direction r_hat:
        # a > 0 when y_b tilts towards the centre (the wing is raised)
        a, c = -(yb @ r_hat[i]), yb[1]
        a_dot, c_dot = -(ybd @ r_hat[i]), ybd[1]
        s[i] = np.arctan2(a, c)
        s_dot[i] = (c * a_dot - a * c_dot) / (a * a + c * c)
    e, e_dot = euler_and_rates(Rc, wc)
    return s, s_dot, e, e_dot
