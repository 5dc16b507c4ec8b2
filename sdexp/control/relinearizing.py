"""Algorithm 1 of the paper: LQR on the learned dynamics, relinearised online.

    u <- 0
    every n control steps:
        x_wp   <- x + kp (x_goal - x) + kd x_dot      (waypoint)
        A, B   <- Jacobians of f = (d, g, h) at the current (x, u)
        K      <- LQR(A, B, Q, R)                      (continuous-time Riccati, SciPy)
        u_oper <- u
    every step:
        u <- -K (x - x_wp) + u_oper

How the waypoint reads. The paper writes x_wp = kp (x_goal - x) + kd x_dot and explains it:
"if we want to reach x_wp from x_curr, we pretend to be at (x_curr - x_wp) trying to reach
x_curr" -- i.e. kp (x_goal - x) + kd x_dot is the waypoint's offset from the linearisation
point x_curr, in the deviation coordinates the LQR works in. In absolute coordinates the
waypoint is therefore x + kp (x_goal - x) + kd x_dot, which is what this class stores, so that
``-K (x - x_wp)`` is exactly -K (-offset) right after a relinearisation and keeps acting on the
drift for the next n - 1 steps. x_dot is the learned f(x, u) at the linearisation point (the
Jacobian pass gives it for free). Angle differences (e) are wrapped to (-pi, pi].

The command is clipped to [-Tmax, Tmax] before it is stored as the current u, so u_oper never
winds up beyond what the rotors can give (the same clip every controller gets).

With ``relinearize=False`` (the fixed-point ablation) A, B and K are computed once at the given
operating point (x_op, u_op) and u_oper stays u_op; waypoints are still updated every n steps.

``feedforward`` (our extension, off by default): the update above is an integral controller,
u changes by K kp (x_goal - x) per relinearisation, so it stops once K (x_goal - x) = 0, and with
fewer rotors than position-like errors a bend error can stay, traded against a position offset
(measured on hover_deform: the petals stall at 7.4 deg rms error however long they are held).
With it, each relinearisation also solves the learned model for the thrust u_ff that holds the
goal's bends at rest (Gauss-Newton on the velocity rows of f(x_goal, u) = 0, warm-started), the
bends' waypoint is their goal, and u_oper = u_ff + (u - previous u_ff): the integral part
keeps what it learned about position and attitude, the bends get their thrust directly.

``waypoint_max`` (our extension, off by default): the position part of the waypoint's offset,
kp (p_goal - p), is shortened to at most this length. A waypoint at the goal (kp = 1) holds a
hover and follows a moving goal closely, but a goal a body length away then asks the LQR for
a jump it answers with a tilt past recovery (measured on the rod: 8 m trip, tilt 90 deg at
1.3 s); with the offset bounded the drone chases a point that stays near it.

A model learned with a command delay (``model.command_delay`` d > 0, our extension): the thrust
chosen now acts d steps from now, so the controller works on the state the learned model
predicts for then, from the measured state and the d commands already sent (a Smith predictor);
the rotors are idle before the first command.

``max_rate`` (our extension, off by default; rad/s): the feedback's fastest rate, the largest
|eigenvalue| of B K, is kept within it by raising R in x2 rungs (``gain``). A loop acting at rate w
through a delay tau loses w tau of phase: the Smith predictor removes the delay only where the
learned model is right, so the rate a delay tolerates bounds the gain (control.delay_phase_deg
sets max_rate = phase / (command delay x dt)). Measured at release with R = 10 (seed 0): the
octopus's feedback acts at 44 rad/s (76 deg of phase over 30 ms), the flower's at 16, the star's
19, the rod's 20, the stiff drones' 4-6.

``share_pull`` (our extension, 0 by default; a fraction per relinearisation): Algorithm 1 keeps
the thrust it reached as the next operating point, so thrust combinations the attitude and the
position hardly feel wander freely, and on the SOTA flower they drift onto the centre rotor (seed 0:
6.6 of 9.3 N, two petals pushing down, until it saturates and the flight is lost). With it, each
relinearisation moves u_oper this fraction of the way toward an even share of the total, within the
null space of the rigid rows of B (``unfelt_share``), so no attitude or position acceleration moves.

``integral`` (our extension, 1 by default = Algorithm 1): u_oper <- u makes the operating thrust
an integral of the feedback, and with the waypoint at the goal (kp = 1) it adds all of
-K (x - x_goal) every period: an integral acting within n dt (0.1 s), which costs the fastest
loop (attitude) phase it cannot spare beside the 30 ms lag. With ``integral`` < 1 the operating
thrust (with ``feedforward``: its integral part) keeps that share of what the feedback added,
u_oper <- u_oper + integral (u - u_oper): the same feedback, a slower integral, the same zero
steady-state error. hover_deform and the obstacle fly with 0.5 (docs/results.md, "Hover with active
deformation": the ~2 Hz attitude swing that took seed 0 to 8 deg is the symptom).

``regulated`` (our extension; None: every state, the paper): the indices of x the LQR regulates,
the others get no gain and no feed-forward row (sdexp.control.lqr.regulated_states: the bends
whose spread in the training data is sensor noise).
"""
from __future__ import annotations

import time
from collections import deque

import numpy as np

from sdexp.control.lqr import alike_groups, alike_rotors, alike_thrust_weights, alike_weights, lqr_gain
from sdexp.control.tasks import Task, wrap_angle
from sdexp.model.dynamics import LearnedDynamics
from sdexp.sensing import State


MAX_R_RUNGS = 12   # x2 each: R up to 4096x the configured one before the cap gives up


class RelinearizingLQR:
    name = "ours"

    def __init__(self, dyn: LearnedDynamics, q_diag: np.ndarray, r: float, kp: float, kd: float, n: int,
                 max_thrust: float, relinearize: bool = True, x_op=None, u_op=None, u0=None,
                 dt: float | None = None, feedforward: bool = False, waypoint_max: float | None = None,
                 regulated: np.ndarray | None = None, q_alike: float = 0.0, velocity_scale: float = 1.0,
                 max_rate: float | None = None, r_alike: float = 0.0, share_pull: float = 0.0,
                 integral: float = 1.0, approach_speed: float | None = None):
        if n < 1:
            raise ValueError("n must be >= 1")
        if feedforward and not relinearize:
            raise ValueError("feedforward needs relinearize=True (it re-solves at every relinearisation)")
        self.feedforward = feedforward
        if not 0 <= share_pull <= 1:
            raise ValueError(f"share_pull = {share_pull!r}: allowed 0 to 1")
        if share_pull > 0 and feedforward:
            raise ValueError("share_pull needs feedforward=False (the feed-forward sets the operating thrust itself)")
        self.share_pull = float(share_pull)
        if not 0 < integral <= 1:
            raise ValueError(f"integral = {integral!r}: allowed in (0, 1]")
        self.integral = float(integral)
        if waypoint_max is not None and not waypoint_max > 0:
            raise ValueError(f"waypoint_max = {waypoint_max!r}: allowed > 0 or None")
        self.waypoint_max = waypoint_max
        if approach_speed is not None and (not approach_speed > 0 or waypoint_max is None):
            raise ValueError(f"approach_speed = {approach_speed!r}: allowed > 0 (with waypoint_max) or None")
        self.approach_speed = approach_speed
        # the velocity rows of f: zero at rest, what equilibrium_thrust solves for
        self._rates = np.concatenate([np.arange(dyn.n)[dyn.slices[k]] for k in ("s_dot", "e_dot", "p_dot")])
        self._rigid = np.concatenate([np.arange(dyn.n)[dyn.slices[k]] for k in ("e_dot", "p_dot")])
        self.regulated = None if regulated is None else np.asarray(regulated, dtype=int)
        if self.regulated is not None:
            self._rates = np.intersect1d(self._rates, self.regulated)
        self.dyn, self.kp, self.kd, self.n, self.max_thrust = dyn, kp, kd, int(n), max_thrust
        self.Q0, self.R0 = np.diag(q_diag), r * np.eye(dyn.m)
        self.Q, self.R = self.Q0, self.R0
        # Q's cost of bends the task moves together parting (lqr.alike_weights; 0: the paper's diagonal)
        self.q_alike, self.velocity_scale = float(q_alike), float(velocity_scale)
        # R's cost of thrust differences among those bends' rotors, x r (lqr.alike_thrust_weights)
        if not r_alike >= 0:
            raise ValueError(f"r_alike = {r_alike!r}: allowed >= 0")
        self.r_alike_cost = float(r_alike) * float(r)
        self.relinearize = relinearize
        self.dt = dt   # None: continuous Riccati (the paper); a step: the sampled-data gain
        self.x_op, self.u_op = x_op, u_op
        self.u0 = np.zeros(dyn.m) if u0 is None else np.asarray(u0, dtype=float)
        self.e = dyn.slices["e"]
        self.timings: list[float] = []     # seconds per relinearisation (Jacobians + Riccati)
        if max_rate is not None and not max_rate > 0:
            raise ValueError(f"max_rate = {max_rate!r}: allowed > 0 or None")
        self.max_rate = max_rate
        self.r_scale = 1.0                 # R's multiple that keeps the feedback within max_rate

    def _diff(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        d = a - b
        d[self.e] = wrap_angle(d[self.e])
        return d

    def reset(self, task: Task) -> None:
        self.task, self.k = task, 0
        self.r_scale = 1.0
        self.timings = []
        self.Q, self.R = self.Q0, self.R0
        # only where asked: a task that moves no bends (an env's observed goal) has no bend_targets
        self.groups = alike_groups(task.bend_targets) if self.q_alike > 0 or self.r_alike_cost > 0 else []
        self.rotor_groups = None   # from the first linearisation's B (alike_rotors)
        if self.q_alike > 0:
            sizes = {"n_s": self.dyn.n_s, "n_e": self.dyn.n_e, "dim": self.dyn.dim}
            self.Q = self.Q0 + alike_weights(sizes, self.groups, self.q_alike, self.velocity_scale)
        self.u = self.u0.copy()
        self.u_oper = self.u.copy()
        self.u_ff = None
        self.u_int = np.zeros(self.dyn.m)   # with feedforward: the integral part of u_oper
        self.sent = deque([np.zeros(self.dyn.m)] * getattr(self.dyn, "delay", 0))   # sent, not yet acting (oldest first)
        if not self.relinearize:
            if self.x_op is None or self.u_op is None:
                raise ValueError("relinearize=False needs an operating point (x_op, u_op)")
            _, A, B = self.dyn.linearize(self.x_op, self.u_op)
            self.K = self.gain(A, B)
            self.u_oper = np.asarray(self.u_op, dtype=float).copy()

    def gain(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        """The LQR gain on (A, B); with ``max_rate``, R raised (or lowered back toward the
        configured R) in x2 rungs until the feedback's fastest rate, max |eig(B K)|, is within it.
        Warm-started from the last rung, so a relinearisation usually solves once or twice."""
        if self.r_alike_cost > 0 and self.rotor_groups is None:
            self.rotor_groups = alike_rotors(B[self.dyn.slices["s_dot"]], self.groups)
            self.R = self.R0 + alike_thrust_weights(self.dyn.m, self.rotor_groups, self.r_alike_cost)
        K = lqr_gain(A, B, self.Q, self.r_scale * self.R, self.dt, self.regulated)
        if self.max_rate is None:
            return K

        def rate(K):
            return float(np.abs(np.linalg.eigvals(B @ K)).max())
        while self.r_scale > 1.0:   # back down while the next rung down stays within the cap
            lower = lqr_gain(A, B, self.Q, 0.5 * self.r_scale * self.R, self.dt, self.regulated)
            if rate(lower) > self.max_rate:
                break
            self.r_scale, K = 0.5 * self.r_scale, lower
        for _ in range(MAX_R_RUNGS):
            if rate(K) <= self.max_rate:
                break
            self.r_scale *= 2.0
            K = lqr_gain(A, B, self.Q, self.r_scale * self.R, self.dt, self.regulated)
        return K

    def _keep(self, before: np.ndarray, now: np.ndarray) -> np.ndarray:
        """The operating thrust (or its integral part) for the next period: Algorithm 1 keeps all
        of the last command (``integral`` 1), less keeps that share of what the feedback added."""
        return now if self.integral == 1 else before + self.integral * (now - before)

    def equilibrium_thrust(self, x: np.ndarray, u: np.ndarray, steps: int = 2) -> np.ndarray:
        """The thrust (within +-Tmax) closest to holding state x at rest under the learned model:
        Gauss-Newton from u on the velocity rows of f(x, u) = 0 (least squares)."""
        rows = self._rates
        u = np.asarray(u, dtype=float).copy()
        for _ in range(steps):
            f0, _, B = self.dyn.linearize(x, u)
            u = np.clip(u + np.linalg.lstsq(B[rows], -f0[rows], rcond=None)[0], -self.max_thrust, self.max_thrust)
        return u

    def approach_velocity(self, clipped: np.ndarray, length: float) -> np.ndarray:
        """The waypoint's velocity toward a goal ``length`` away (beyond waypoint_max, the offset
        ``clipped`` to it): approach_speed along it from 2 waypoint_max on, ramping from zero at
        waypoint_max, so that within waypoint_max the waypoint is as without."""
        w = self.waypoint_max
        return self.approach_speed * min(1.0, (length - w) / w) * clipped / w

    def act(self, t: float, state: State) -> np.ndarray:
        x = self.dyn.predict(state.x, self.sent) if self.sent else state.x
        if self.k % self.n == 0:
            if self.relinearize:
                t0 = time.perf_counter()
                x_dot, A, B = self.dyn.linearize(x, self.u)
                self.K = self.gain(A, B)
                self.timings.append(time.perf_counter() - t0)
                self.u_oper = self._keep(self.u_oper, self.u.copy())
                if self.share_pull > 0:
                    self.u_oper += self.share_pull * unfelt_share(B[self._rigid], self.u_oper)
            else:
                x_dot = self.dyn.f(x, self.u)
            goal = self.task.goal(t).x
            offset = self.kp * self._diff(goal, x)
            if self.waypoint_max is not None:
                p = self.dyn.slices["p"]
                length = float(np.linalg.norm(offset[p]))
                if length > self.waypoint_max:
                    offset[p] *= self.waypoint_max / length
                    if self.approach_speed is not None:
                        offset[self.dyn.slices["p_dot"]] += self.approach_velocity(offset[p], length)
            self.x_wp = x + offset + self.kd * x_dot
            if self.feedforward:
                u_int = np.zeros_like(self.u) if self.u_ff is None else self._keep(self.u_int, self.u - self.u_ff)
                self.u_ff = self.equilibrium_thrust(goal, self.u if self.u_ff is None else self.u_ff)
                self.u_oper, self.u_int = self.u_ff + u_int, u_int
                for key in ("s", "s_dot"):
                    self.x_wp[self.dyn.slices[key]] = goal[self.dyn.slices[key]]
        self.k += 1
        self.u = np.clip(self.u_oper - self.K @ self._diff(x, self.x_wp), -self.max_thrust, self.max_thrust)
        if self.sent:
            self.sent.append(self.u.copy())
            self.sent.popleft()
        return self.u


def unfelt_share(B_rigid: np.ndarray, u: np.ndarray, rcond: float = 1e-6) -> np.ndarray:
    """The step from u toward an even share of its total thrust, within the thrust directions the
    rigid rows of the learned model do not feel (the null space of B_rigid): it moves no attitude
    or position acceleration to first order (nor the total, where the lift row feels it)."""
    # numpy's SVD, not scipy.linalg.null_space (the same projection through another LAPACK): the
    # committed SOTA flights were made with it, and scipy's moves their last digits
    _, S, Vt = np.linalg.svd(B_rigid, full_matrices=True)
    N = Vt[int(np.sum(S > rcond * S.max())) if S.size else 0:].T
    return N @ (N.T @ (np.full_like(u, u.mean()) - u))
