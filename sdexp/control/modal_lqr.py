"""The privileged reduced-model LQR (``reduced_lqr``): an LQR on the reduced-order model's own
linearisation around the current state, relinearised every ``n`` control steps toward ours'
waypoint (Algorithm 1), observing what a real drone cannot: the frame (centre of mass, rotation)
and the modal coordinates, without noise. It is the baseline the paper's supplement sets itself
against (controllers that "observe the full state and apply model reduction", Barbic and Popovic
2008): where it flies and ours does not, the learning is the limit; where it cannot, model-based
control of that body is.

The state and its Jacobians come from callbacks (sdexp.eval.controllers builds them from the
reduced model, sdexp.sim.reduced.linear), as the geometry-updating LQR gets its geometry: this
module sees no simulator. At each design, around (x0, u0):
  * the hover it regulates to: the goal position with the body level at its current heading
    (the yaw of a drone whose rotors all point one way is not controllable), at rest, its modal
    coordinates and thrust from the linear model by static condensation (the modal rows give z
    for any thrust, the six rigid rows then the thrust change; in the thrust directions the rigid
    motion does not feel, ``u_rest``: the even share of the weight);
  * the waypoint, as ours': x + kp (x_goal - x) on position, attitude and their rates, its
    position offset at most ``waypoint_max``;
  * the design model: the rigid states but the heading (its turn about the up axis, which
    nothing but the rotors' tilt off parallel can move; 2D: the in-plane ones), the modal
    coordinates turned into the rest stiffness's eigen-coordinates, the ``slow`` softest kept,
    the others condensed (singular perturbation: their fast, damped dynamics settled). The whole model (12 + 2 r states with modes of hundreds of rad/s) makes
    the Riccati equation ill-posed once the body is bent, and no 100 Hz loop acts on such modes;
  * K = the continuous-time LQR gain (sdexp.control.lqr.lqr_gain) with Q on position and attitude
    (control.q_p, control.q_e) and their rates (x control.velocity_scale), none on the modes (the
    controller knows how they move the frame; it holds no shape), R = control.r. Continuous, not
    the sampled-data gain, whose Euler discretisation is wrong for stiff rows.
  u = u* - K (x - x_wp) on the kept states, the rotation in the chart it was designed in (the
  rotation vector).
"""
from __future__ import annotations

import time
from typing import Callable

import numpy as np

from sdexp.control.lqr import LqrFailure, lqr_gain
from sdexp.control.tasks import Task
from sdexp.sensing import State
from sdexp.sensing.rotations import euler_from_matrix, exp_so3, matrix_from_euler


class ModalLQR:
    """See the module docstring. ``observe()`` -> x (12 + 2 r: c, phi, z, v, w, zd; phi the
    rotation vector); ``linearize(x, u)`` -> (F, dF/dx, dF/du); ``modes`` (r, r): the rest
    stiffness's eigenvectors in the modal coordinates, softest first; ``offset``: the measured
    position's point (the frame IMU) from the centre of mass, body frame (the task's goal is
    that point's)."""

    def __init__(self, observe: Callable[[], np.ndarray], linearize: Callable, modes: np.ndarray, slow: int,
                 u_rest: np.ndarray, offset: np.ndarray, q_p: float, q_e: float, velocity_scale: float, r: float,
                 n: int, kp: float, waypoint_max: float | None = None, planar: bool = False,
                 name: str = "reduced_lqr"):
        self.observe, self.linearize, self.u_rest, self.offset = observe, linearize, np.asarray(u_rest, float), offset
        self.n, self.kp, self.waypoint_max, self.name, self.planar = int(n), float(kp), waypoint_max, name, planar
        rm = modes.shape[0]
        self.r_modal, self.slow = rm, min(int(slow), rm)
        self.sl = {"c": slice(0, 3), "phi": slice(3, 6), "z": slice(6, 6 + rm), "v": slice(6 + rm, 9 + rm),
                   "w": slice(9 + rm, 12 + rm), "zd": slice(12 + rm, 12 + 2 * rm)}
        # x -> y: the modal coordinates and rates in the eigen-coordinates (an orthogonal change)
        N = 12 + 2 * rm
        self.P = np.eye(N)
        self.P[self.sl["z"], self.sl["z"]] = modes.T
        self.P[self.sl["zd"], self.sl["zd"]] = modes.T
        k, c, v, w = self.slow, 0, self.sl["v"].start, self.sl["w"].start
        # the rigid states designed on: no heading (its turn about the up axis y, and its rate:
        # nothing but the rotors' tilt off parallel can turn it, and the goal keeps the heading
        # as it is), and a 2D drone's in-plane ones only (x, y, the turn about z)
        rigid = [c, c + 1, 5, v, v + 1, w + 2] if planar else [c, c + 1, c + 2, 3, 5, v, v + 1, v + 2, w, w + 2]
        self.kept = np.r_[rigid, 6:6 + k, 12 + rm:12 + rm + k]
        self.fast = np.r_[6 + k:6 + rm, 12 + rm + k:12 + 2 * rm]
        q = np.zeros(N)
        q[self.sl["c"]], q[self.sl["phi"]] = q_p, q_e
        q[self.sl["v"]], q[self.sl["w"]] = q_p * velocity_scale, q_e * velocity_scale
        self.Q = np.diag(q[self.kept])
        self.R = r * np.eye(len(self.u_rest))
        self.timings: list[float] = []

    def reset(self, task: Task) -> None:
        self.task, self.k = task, 0
        self.u_op = self.u_rest.copy()

    def _goal(self, x: np.ndarray, t: float) -> np.ndarray:
        """The goal as a state (c, phi, v; the rest zero): the task's position, level at the
        current heading."""
        goal = self.task.goal(t)
        # sdexp's yaw turns about the world's up axis, y: the level rotation at it is R_y(heading)
        heading = 0.0 if self.planar else euler_from_matrix(exp_so3(x[self.sl["phi"]]))[1]
        ref = np.zeros_like(x)
        ref[self.sl["c"]][:len(goal.p)] = goal.p
        ref[self.sl["c"]] -= matrix_from_euler(np.array([0.0, heading, 0.0])) @ self.offset
        ref[self.sl["phi"]] = _unwrapped(np.array([0.0, heading, 0.0]), x[self.sl["phi"]])
        ref[self.sl["v"]][:len(goal.p_dot)] = goal.p_dot
        return ref

    def _design(self, x: np.ndarray, t: float) -> None:
        t0 = time.perf_counter()
        f0, A, B = self.linearize(x, self.u_op)
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(B)) and np.all(np.isfinite(f0))):
            raise LqrFailure("the reduced model's linearisation is not finite")
        goal = self._goal(x, t)
        # the hover at the goal, by static condensation of F(x*, u*) = 0 on the linear model
        zs, zds = self.sl["z"], self.sl["zd"]
        rigid = np.r_[self.sl["v"].start:self.sl["w"].stop]
        zc = np.arange(zs.start, zs.stop)
        dx = goal - x
        dx[zs] = 0.0
        base = f0 + A @ dx                                     # the rates at the goal, z and u as at x0
        Kzz = A[zds, zs]
        Z_b = -np.linalg.solve(Kzz, base[zds])                 # the modal shift that zeroes the modal rows,
        Z_u = -np.linalg.solve(Kzz, B[zds])                    # and its part per thrust change
        G = B[rigid] + A[np.ix_(rigid, zc)] @ Z_u
        du = -np.linalg.lstsq(G, base[rigid] + A[np.ix_(rigid, zc)] @ Z_b, rcond=1e-10)[0]
        # the thrust the rigid motion does not feel: the rest hover's share, not wherever the
        # last designs left it (a chain of least-norm changes lets it drift onto a few rotors
        # and bend the body, as ours' operating thrust does without control.share_pull)
        _, sv, Vt = np.linalg.svd(G)
        null = Vt[int(np.sum(sv > 1e-9 * sv[0])):]
        du += null.T @ (null @ (self.u_rest - self.u_op - du))
        self.u_star = self.u_op + du
        # the waypoint, as ours' (kp of the way to the goal), the modal hover beside it
        wp = goal.copy()
        wp[zs] = x[zs] + Z_b + Z_u @ du
        for key in ("c", "phi", "v", "w"):
            s = self.sl[key]
            wp[s] = x[s] + self.kp * (goal[s] - x[s])
        if self.waypoint_max is not None:
            d = wp[self.sl["c"]] - x[self.sl["c"]]
            wp[self.sl["c"]] = x[self.sl["c"]] + d * min(1.0, self.waypoint_max / max(np.linalg.norm(d), 1e-12))
        self.wp = wp
        # the design model: slow eigen-coordinates kept, the fast ones condensed
        Ay, By = self.P @ A @ self.P.T, self.P @ B
        S, F = self.kept, self.fast
        Aff = Ay[np.ix_(F, F)]
        Ar = Ay[np.ix_(S, S)] - Ay[np.ix_(S, F)] @ np.linalg.solve(Aff, Ay[np.ix_(F, S)])
        Br = By[S] - Ay[np.ix_(S, F)] @ np.linalg.solve(Aff, By[F])
        self.K = lqr_gain(Ar, Br, self.Q, self.R, None)
        self.u_op = self.u_star
        self.timings.append(time.perf_counter() - t0)

    def act(self, t: float, state: State) -> np.ndarray:
        x = self.observe()
        if self.k % self.n == 0:
            self._design(x, t)
        self.k += 1
        err = x - self.wp
        s = self.sl["phi"]
        err[s] = x[s] - _unwrapped(self.wp[s], x[s])
        return self.u_star - self.K @ (self.P @ err)[self.kept]


def _unwrapped(phi: np.ndarray, near: np.ndarray) -> np.ndarray:
    """The rotation vector of the same rotation as ``phi`` nearest ``near`` (|phi| may pass pi)."""
    a = np.linalg.norm(phi)
    if a < 1e-12:
        return phi
    other = phi - 2 * np.pi * phi / a
    return other if np.linalg.norm(other - near) < np.linalg.norm(phi - near) else phi
