"""Algorithm 1 (RelinearizingLQR) on dynamics whose truth is known: a planar two-rotor
multicopter under gravity (optionally with one damped bending mode), exactly affine or with the
full rotation nonlinearity, standing in for the learned d, g, h. Hover is never the operating
point it is handed: the algorithm starts from u = 0, where f(x, u) != 0."""
import numpy as np
import pytest
import scipy.linalg

from sdexp.control.lqr import LqrFailure, state_weights
from sdexp.control.relinearizing import RelinearizingLQR
from sdexp.control.tasks import Task
from sdexp.sensing import State

G, MASS, J, ARM = 9.81, 1.0, 0.05, 0.25
DT = 0.01
TMAX = 10.0


class PlanarCopter:
    """x = (s, s_dot, theta, theta_dot, px, py, vx, vy), u = (left, right) thrusts.

    nonlinear:  p_ddot = (u0 + u1) / m (-sin theta, cos theta) - g y,  theta_ddot = ARM (u1 - u0) / J
    affine:     p_ddot = (-g theta, (u0 + u1) / m - g): the hover linearisation, kept as the
                model everywhere (A, B constant, f(x, u) = A x + B u + c with c = -g y)
    bending:    s_ddot = -w^2 s - 2 z w s_dot + b (u0 - u1)
    The LearnedDynamics interface: n, m, n_s, n_e, dim, alpha, slices, f, linearize."""

    def __init__(self, nonlinear=True, n_s=0):
        self.nonlinear, self.n_s, self.n_e, self.dim, self.m, self.alpha = nonlinear, n_s, 1, 2, 2, DT
        sizes = [("s", n_s), ("s_dot", n_s), ("e", 1), ("e_dot", 1), ("p", 2), ("p_dot", 2)]
        self.slices, o = {}, 0
        for k, w in sizes:
            self.slices[k] = slice(o, o + w)
            o += w
        self.n = o
        self.slices["u"] = slice(o, o + 2)
        self.calls = []

    def f(self, x, u):
        x, u = np.asarray(x, float), np.asarray(u, float)
        sl = self.slices
        th, w = x[sl["e"]][0], x[sl["e_dot"]][0]
        T = u[0] + u[1]
        if self.nonlinear:
            acc = T / MASS * np.array([-np.sin(th), np.cos(th)]) - [0.0, G]
        else:
            acc = np.array([-G * th, T / MASS - G])
        out = np.zeros(self.n)
        out[sl["e"]] = w
        out[sl["e_dot"]] = ARM * (u[1] - u[0]) / J
        out[sl["p"]] = x[sl["p_dot"]]
        out[sl["p_dot"]] = acc
        if self.n_s:
            s, sd = x[sl["s"]], x[sl["s_dot"]]
            out[sl["s"]] = sd
            out[sl["s_dot"]] = -16.0 * s - 4.0 * sd + 0.5 * (u[0] - u[1])
        return out

    def linearize(self, x, u):
        self.calls.append((np.array(x, float), np.array(u, float)))
        h = 1e-6
        A = np.stack([(self.f(x + h * e, u) - self.f(x - h * e, u)) / (2 * h) for e in np.eye(self.n)], 1)
        B = np.stack([(self.f(x, u + h * e) - self.f(x, u - h * e)) / (2 * h) for e in np.eye(2)], 1)
        return self.f(x, u), A, B


def state_of(dyn, x):
    sl = dyn.slices
    return State(*(x[sl[k]].copy() for k in ("s", "e", "p", "s_dot", "e_dot", "p_dot")))


def weights(dyn):
    return state_weights({"n_s": dyn.n_s, "n_e": 1, "dim": 2}, 100.0, 100.0, 100.0, 1.0)


def care_gain(A, B, q, r):
    S = scipy.linalg.solve_continuous_are(A, B, np.diag(q), r * np.eye(B.shape[1]))
    return B.T @ S / r


def fly(dyn, ctl, x0, seconds, truth=None, state_map=None):
    """Closed loop with explicit Euler steps of DT through ``truth`` (default: the model)."""
    truth = truth or dyn
    x, X, U = np.array(x0, float), [], []
    for k in range(int(round(seconds / DT))):
        st = state_of(dyn, x if state_map is None else state_map(x))
        u = ctl.act(k * DT, st)
        U.append(u.copy())
        X.append(x.copy())
        x = x + DT * truth.f(x, u)
    return np.array(X + [x]), np.array(U)


@pytest.mark.parametrize("nonlinear", [False, True], ids=["affine", "nonlinear"])
def test_flies_to_the_goal_and_holds_it_from_zero_thrust(nonlinear):
    """The paper's gains (Q 100, R 2, kp 0.03, kd 1e-4). u starts at 0 -- gravity is not
    compensated by any operating point given in advance; u_oper accumulates it."""
    dyn = PlanarCopter(nonlinear)
    ctl = RelinearizingLQR(dyn, weights(dyn), r=2.0, kp=0.03, kd=1e-4, n=5, max_thrust=TMAX)
    target = np.array([1.0, 0.5])
    ctl.reset(Task(start=np.zeros(2), target=target, seconds=15.0, n_s=0))
    x0 = np.zeros(dyn.n)
    x0[dyn.slices["e"]] = np.deg2rad(5.0)
    X, U = fly(dyn, ctl, x0, 15.0)
    sl = dyn.slices
    np.testing.assert_array_equal(ctl.u0, 0.0)
    assert abs(U[0].sum()) < 2.0                            # far from the 9.81 N hover thrust ...
    err = np.linalg.norm(X[:, sl["p"]] - target, axis=1)
    assert err[-1] < 5e-3 and err[-1] < 0.01 * err[0]       # ... and still it gets there
    assert np.abs(X[-200:, sl["p"]] - target).max() < 1e-2  # and stays
    np.testing.assert_allclose(U[-1], [MASS * G / 2] * 2, atol=0.02)
    assert abs(X[-1, sl["e"]][0]) < 1e-3 and np.abs(X[-1, sl["p_dot"]]).max() < 1e-2


def test_bending_mode_is_held_too():
    dyn = PlanarCopter(True, n_s=1)
    ctl = RelinearizingLQR(dyn, weights(dyn), r=2.0, kp=0.03, kd=1e-4, n=5, max_thrust=TMAX)
    ctl.reset(Task(start=np.zeros(2), target=[-0.5, 0.3], seconds=12.0, n_s=1))
    x0 = np.zeros(dyn.n)
    x0[dyn.slices["s"]] = 0.2
    X, U = fly(dyn, ctl, x0, 12.0)
    assert np.linalg.norm(X[-1, dyn.slices["p"]] - [-0.5, 0.3]) < 0.02
    assert abs(X[-1, dyn.slices["s"]][0]) < 1e-3


def test_waypoint_and_command_follow_algorithm_1():
    """Right after a relinearisation at (x, u): x_wp = x + kp (x_goal - x) + kd f(x, u), and
    u = u_oper - K (x - x_wp) with K the LQR gain of (A, B) there; for the next n - 1 steps the
    same K, x_wp and u_oper act on the drift."""
    dyn = PlanarCopter(False)
    q, r, kp, kd, n = weights(dyn), 2.0, 0.3, 0.05, 4
    u0 = np.array([1.0, 2.0])
    ctl = RelinearizingLQR(dyn, q, r=r, kp=kp, kd=kd, n=n, max_thrust=TMAX, u0=u0)
    task = Task(start=np.zeros(2), target=[0.4, -0.2], seconds=1.0, n_s=0)
    ctl.reset(task)
    x = np.array([0.05, -0.1, 0.1, 0.2, 0.3, -0.1])
    goal = task.goal(0.0).x
    _, A, B = dyn.linearize(x, u0)
    K = care_gain(A, B, q, r)
    u = ctl.act(0.0, state_of(dyn, x))
    x_wp = x + kp * (goal - x) + kd * dyn.f(x, u0)
    np.testing.assert_allclose(ctl.x_wp, x_wp, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(u, u0 + K @ (kp * (goal - x) + kd * dyn.f(x, u0)), rtol=1e-9)
    # the next n - 1 steps: fixed K, x_wp, u_oper = u0
    for k in range(1, n):
        x = x + DT * dyn.f(x, u)
        u = ctl.act(k * DT, state_of(dyn, x))
        np.testing.assert_allclose(u, u0 - K @ (x - x_wp), rtol=1e-9)
    # step n: relinearised at the current x and the last command, which becomes u_oper
    u_prev = u.copy()
    x = x + DT * dyn.f(x, u)
    u = ctl.act(n * DT, state_of(dyn, x))
    np.testing.assert_allclose(ctl.u_oper, u_prev)
    np.testing.assert_allclose(ctl.x_wp, x + kp * (goal - x) + kd * dyn.f(x, u_prev), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(u, u_prev + K @ (kp * (goal - x) + kd * dyn.f(x, u_prev)), rtol=1e-9)


@pytest.mark.parametrize("n", [1, 3, 10])
def test_relinearises_every_n_steps_at_the_current_state_and_command(n):
    dyn = PlanarCopter(True)
    ctl = RelinearizingLQR(dyn, weights(dyn), r=2.0, kp=0.03, kd=1e-4, n=n, max_thrust=TMAX)
    ctl.reset(Task(start=np.zeros(2), target=[0.2, 0.1], seconds=1.0, n_s=0))
    X, U = fly(dyn, ctl, np.zeros(dyn.n), 0.25)
    steps = len(U)
    assert len(dyn.calls) == -(-steps // n) == len(ctl.timings)
    for j, (xc, uc) in enumerate(dyn.calls):
        k = j * n
        np.testing.assert_array_equal(xc, X[k])
        np.testing.assert_array_equal(uc, U[k - 1] if k else np.zeros(2))
    assert all(t >= 0 for t in ctl.timings)


def test_fixed_operating_point_ablation_never_relinearises():
    dyn = PlanarCopter(True)
    x_op, u_op = np.zeros(dyn.n), np.full(2, MASS * G / 2)
    q, r, kp, kd, n = weights(dyn), 2.0, 0.03, 1e-4, 5
    ctl = RelinearizingLQR(dyn, q, r=r, kp=kp, kd=kd, n=n, max_thrust=TMAX, relinearize=False, x_op=x_op, u_op=u_op)
    task = Task(start=np.zeros(2), target=[0.5, 0.5], seconds=1.0, n_s=0)
    ctl.reset(task)
    assert len(dyn.calls) == 1
    np.testing.assert_array_equal(dyn.calls[0][0], x_op)
    np.testing.assert_array_equal(dyn.calls[0][1], u_op)
    _, A, B = PlanarCopter(True).linearize(x_op, u_op)
    K = care_gain(A, B, q, r)
    x = np.zeros(dyn.n)
    x[dyn.slices["e"]] = 0.3                   # far from the operating point's attitude
    u_last = np.zeros(2)
    goal = task.goal(0.0).x
    for k in range(12):
        u = ctl.act(k * DT, state_of(dyn, x))
        if k % n == 0:
            x_wp = x + kp * (goal - x) + kd * dyn.f(x, u_last)
            np.testing.assert_allclose(ctl.x_wp, x_wp, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(u, np.clip(u_op - K @ (x - x_wp), -TMAX, TMAX), rtol=1e-9)
        u_last = u
        x = x + DT * dyn.f(x, u)
    assert len(dyn.calls) == 1
    np.testing.assert_array_equal(ctl.u_oper, u_op)
    with pytest.raises(ValueError):
        RelinearizingLQR(dyn, q, r=r, kp=kp, kd=kd, n=n, max_thrust=TMAX, relinearize=False).reset(task)


def test_commands_are_clipped_and_the_clip_is_what_u_oper_keeps():
    dyn = PlanarCopter(True)
    tmax = 3.0
    ctl = RelinearizingLQR(dyn, weights(dyn), r=2.0, kp=0.5, kd=0.0, n=3, max_thrust=tmax)
    ctl.reset(Task(start=np.zeros(2), target=[0.0, 100.0], seconds=1.0, n_s=0))
    X, U = fly(dyn, ctl, np.zeros(dyn.n), 0.3)
    assert np.abs(U).max() <= tmax
    assert np.any(np.abs(U) == tmax)                       # it did saturate
    for j, (_, uc) in enumerate(dyn.calls[1:], start=1):
        np.testing.assert_array_equal(uc, U[3 * j - 1])    # relinearised at the clipped command
        assert np.abs(uc).max() <= tmax
    with pytest.raises(ValueError):
        RelinearizingLQR(dyn, weights(dyn), r=2.0, kp=0.5, kd=0.0, n=0, max_thrust=tmax)


def test_attitude_differences_are_wrapped():
    """Reading theta + 2 pi instead of theta (the same attitude) changes nothing."""
    dyn, dyn2 = PlanarCopter(True), PlanarCopter(True)
    kw = dict(r=2.0, kp=0.1, kd=1e-3, n=4, max_thrust=TMAX)
    task = Task(start=np.zeros(2), target=[0.3, 0.0], seconds=1.0, n_s=0)
    a, b = RelinearizingLQR(dyn, weights(dyn), **kw), RelinearizingLQR(dyn2, weights(dyn2), **kw)
    a.reset(task)
    b.reset(task)
    x0 = np.zeros(dyn.n)
    x0[dyn.slices["e"]] = 0.2
    turn = np.zeros(dyn.n)
    turn[dyn.slices["e"]] = 2 * np.pi
    Xa, Ua = fly(dyn, a, x0, 0.2)
    Xb, Ub = fly(dyn2, b, x0, 0.2, state_map=lambda x: x + turn)
    np.testing.assert_allclose(Ub, Ua, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(Xb, Xa, rtol=1e-9, atol=1e-12)


def test_a_broken_linearisation_is_an_lqr_failure():
    class Broken(PlanarCopter):
        def linearize(self, x, u):
            f0, A, B = super().linearize(x, u)
            return f0, A * np.nan, B

    dyn = Broken(True)
    ctl = RelinearizingLQR(dyn, weights(dyn), r=2.0, kp=0.03, kd=1e-4, n=5, max_thrust=TMAX)
    ctl.reset(Task(start=np.zeros(2), target=[0.0, 0.0], seconds=1.0, n_s=0))
    with pytest.raises(LqrFailure):
        ctl.act(0.0, state_of(dyn, np.zeros(dyn.n)))


class BendingTrirotor(PlanarCopter):
    """PlanarCopter with a third, central rotor whose thrust bends the body against the outer
    two: s_ddot = -16 s - 4 s_dot + 0.5 (u0 + u1 - 2 u2). A bend s* is held at rest by
    u0 = u1 = a, u2 = c with 2 a + c = m g and a - c = 16 s*: one spare rotor for one bend."""

    def __init__(self):
        super().__init__(nonlinear=True, n_s=1)
        self.m = 3
        self.slices["u"] = slice(self.n, self.n + 3)

    def f(self, x, u):
        u = np.asarray(u, float)
        out = super().f(x, [u[0] + u[2] / 2, u[1] + u[2] / 2])
        sl = self.slices
        out[sl["s_dot"]] = -16.0 * x[sl["s"]] - 4.0 * x[sl["s_dot"]] + 0.5 * (u[0] + u[1] - 2 * u[2])
        return out

    def linearize(self, x, u):
        h = 1e-6
        A = np.stack([(self.f(x + h * e, u) - self.f(x - h * e, u)) / (2 * h) for e in np.eye(self.n)], 1)
        B = np.stack([(self.f(x, u + h * e) - self.f(x, u - h * e)) / (2 * h) for e in np.eye(3)], 1)
        return self.f(x, u), A, B


def test_feedforward_holds_a_bend_target_with_a_spare_rotor():
    dyn = BendingTrirotor()
    s_goal = 0.1
    task = Task(start=np.zeros(2), target=np.zeros(2), seconds=20.0, n_s=1, bend_times=[0.0], bend_targets=[[s_goal]])
    ctl = RelinearizingLQR(dyn, weights(dyn), r=2.0, kp=1.0, kd=0.0, n=5, max_thrust=TMAX, feedforward=True)
    ctl.reset(task)
    # the thrust that holds the bend at rest is the analytic one, and u_oper starts there
    a = (MASS * G + 16 * s_goal) / 3
    u_eq = [a, a, a - 16 * s_goal]
    np.testing.assert_allclose(ctl.equilibrium_thrust(task.goal(0.0).x, np.zeros(3)), u_eq, atol=1e-6)
    ctl.act(0.0, state_of(dyn, np.zeros(dyn.n)))
    np.testing.assert_allclose(ctl.u_oper, u_eq, atol=1e-6)
    ctl.reset(task)
    X, U = fly(dyn, ctl, np.zeros(dyn.n), 20.0)
    sl = dyn.slices
    assert abs(X[-1, sl["s"]][0] - s_goal) < 1e-3
    assert np.abs(X[-1, sl["p"]]).max() < 1e-2 and abs(X[-1, sl["e"]][0]) < 1e-3
    np.testing.assert_allclose(U[-1], u_eq, atol=0.02)
    with pytest.raises(ValueError, match="feedforward"):
        RelinearizingLQR(dyn, weights(dyn), 2.0, 1.0, 0.0, 5, TMAX, relinearize=False, feedforward=True)


@pytest.mark.parametrize("feedforward", [False, True], ids=["algorithm1", "feedforward"])
def test_integral_keeps_that_share_of_what_the_feedback_added_and_still_removes_the_offset(feedforward):
    """At a relinearisation the operating thrust (with the feed-forward: its integral part, beside
    the re-solved u_ff) keeps ``integral`` of what the feedback added over the period before;
    Algorithm 1 keeps all of it. Less is a slower integral, not a weaker one: the bending
    trirotor still settles on its goal with the analytic holding thrust."""
    dyn, n, ki = BendingTrirotor(), 5, 0.25
    s_goal = 0.1 if feedforward else 0.0
    task = Task(start=np.zeros(2), target=np.zeros(2), seconds=20.0, n_s=1, bend_times=[0.0], bend_targets=[[s_goal]])
    ctl = RelinearizingLQR(dyn, weights(dyn), r=2.0, kp=1.0, kd=0.0, n=n, max_thrust=TMAX, feedforward=feedforward,
                           integral=ki, u0=np.full(3, MASS * G / 3))
    ctl.reset(task)
    x = np.zeros(dyn.n)
    x[dyn.slices["p"]] = [0.05, -0.1]
    for k in range(n):
        u = ctl.act(k * DT, state_of(dyn, x))
    before = (ctl.u_int if feedforward else ctl.u_oper).copy()
    added = u - (ctl.u_ff if feedforward else ctl.u_oper)   # the last command, less what it started from
    ctl.act(n * DT, state_of(dyn, x))
    kept = before + ki * (added - before) if feedforward else before + ki * added
    np.testing.assert_allclose(ctl.u_int if feedforward else ctl.u_oper, kept, atol=1e-9)
    if feedforward:
        np.testing.assert_allclose(ctl.u_oper, ctl.u_ff + ctl.u_int, atol=1e-12)
    ctl.reset(task)
    X, U = fly(dyn, ctl, np.zeros(dyn.n), 20.0)
    a = (MASS * G + 16 * s_goal) / 3
    assert abs(X[-1, dyn.slices["s"]][0] - s_goal) < 1e-3 and np.abs(X[-1, dyn.slices["p"]]).max() < 1e-2
    np.testing.assert_allclose(U[-1], [a, a, a - 16 * s_goal], atol=0.02)
    for bad in (0.0, 1.5):
        with pytest.raises(ValueError, match="integral"):
            RelinearizingLQR(dyn, weights(dyn), 2.0, 1.0, 0.0, 5, TMAX, integral=bad)


def test_waypoint_max_bounds_the_position_offset_of_the_waypoint_and_nothing_else():
    """A goal 10 m away with kp = 1: the waypoint is 0.5 m toward it; the bends' and rates' parts
    of the waypoint are kp's as before; a near goal is not touched; with approach_speed the
    waypoint's velocity points at a far goal."""
    class Linear:   # x_dot = A x + B u on the (s, s_dot, e, e_dot, p, p_dot) layout of a 2D drone, n_s = 1
        n_s, n_e, dim, m, n = 1, 1, 2, 2, 8
        slices = {"s": slice(0, 1), "s_dot": slice(1, 2), "e": slice(2, 3), "e_dot": slice(3, 4),
                  "p": slice(4, 6), "p_dot": slice(6, 8)}

        def linearize(self, x, u):
            A = np.zeros((8, 8))
            A[[0, 2, 4, 5], [1, 3, 6, 7]] = 1.0
            B = np.zeros((8, 2))
            B[[1, 3, 6, 7], :] = [[1, -1], [1, -1], [0.1, 0.1], [1, 1]]
            return A @ x + B @ u, A, B

    # approach_speed 2: the waypoint's velocity points at a far goal, full from 2 waypoint_max (1 m)
    # on, half at 0.75 m, none within 0.5 m
    cases = [([10.0, 0.0], None, [0.5, 0.0], [0.0, 0.0]), ([0.3, 0.0], None, [0.3, 0.0], [0.0, 0.0]),
             ([0.0, 10.0], 2.0, [0.0, 0.5], [0.0, 2.0]), ([0.75, 0.0], 2.0, [0.5, 0.0], [1.0, 0.0]),
             ([0.3, 0.0], 2.0, [0.3, 0.0], [0.0, 0.0])]
    for goal, speed, expect, velocity in cases:
        ctl = RelinearizingLQR(Linear(), np.ones(8), 1.0, kp=1.0, kd=0.0, n=1, max_thrust=10.0, waypoint_max=0.5,
                               approach_speed=speed)
        ctl.reset(Task(start=[0.0, 0.0], target=goal, seconds=1.0, n_s=1, bend_times=[0.0], bend_targets=[[0.2]]))
        ctl.act(0.0, State(s=np.zeros(1), e=np.zeros(1), p=np.zeros(2), s_dot=np.zeros(1), e_dot=np.zeros(1),
                           p_dot=np.zeros(2)))
        np.testing.assert_allclose(ctl.x_wp[4:6], expect)
        np.testing.assert_allclose(ctl.x_wp[6:8], velocity, atol=1e-12)
        assert ctl.x_wp[0] == pytest.approx(0.2)   # the bend's waypoint: kp x its error, unbounded
    with pytest.raises(ValueError, match="waypoint_max"):
        RelinearizingLQR(Linear(), np.ones(8), 1.0, 1.0, 0.0, 1, 10.0, waypoint_max=0.0)
    with pytest.raises(ValueError, match="approach_speed"):   # it needs the waypoint bounded
        RelinearizingLQR(Linear(), np.ones(8), 1.0, 1.0, 0.0, 1, 10.0, approach_speed=0.5)


class LaggedCopter(PlanarCopter):
    """The copter whose thrust follows the command ``delay`` steps late, as a model that knows it
    (LearnedDynamics with model.command_delay) or (delay 0) one that does not."""

    def __init__(self, delay, **kw):
        super().__init__(**kw)
        self.delay = delay

    def predict(self, x, commands):
        for u in commands:
            x = x + DT * self.f(x, u)
        return x


def fly_lagged(ctl, dyn, lag, x0, seconds):
    """Closed loop through the true copter, whose rotors act ``lag`` steps after the command."""
    from collections import deque
    sent = deque([np.zeros(2)] * lag)
    x, X = np.array(x0, float), []
    for k in range(int(round(seconds / DT))):
        sent.append(ctl.act(k * DT, state_of(dyn, x)).copy())
        x = x + DT * dyn.f(x, sent.popleft())
        X.append(x.copy())
    return np.array(X)


def test_a_model_with_the_command_delay_predicts_the_state_its_command_will_meet():
    """With a lag of d steps the first relinearisation happens at the state d idle-rotor steps
    ahead (falling at g d dt), and stiff gains that shake the copter apart when the lag is ignored
    hold it when the controller predicts across it."""
    lag, target = 8, np.array([0.3, 0.0])
    known = LaggedCopter(lag, nonlinear=True)
    ctl = RelinearizingLQR(known, weights(known), r=0.05, kp=1.0, kd=0.0, n=1, max_thrust=TMAX)
    ctl.reset(Task(start=np.zeros(2), target=target, seconds=4.0, n_s=0))
    ctl.act(0.0, state_of(known, np.zeros(known.n)))
    x_lin = known.calls[0][0]
    assert x_lin[known.slices["p_dot"]][1] == pytest.approx(-G * lag * DT)
    errors = {}
    for name, model in (("predicted", known), ("ignored", LaggedCopter(0, nonlinear=True))):
        ctl = RelinearizingLQR(model, weights(model), r=0.05, kp=1.0, kd=0.0, n=1, max_thrust=TMAX)
        ctl.reset(Task(start=np.zeros(2), target=target, seconds=4.0, n_s=0))
        X = fly_lagged(ctl, model, lag, np.zeros(model.n), 4.0)
        errors[name] = np.abs(X[-100:, model.slices["p"]] - target).max()
    assert errors["predicted"] < 0.05 and errors["ignored"] > 1.0, errors


class NoiseFitBend(PlanarCopter):
    """A stiff copter's learned model: the bend channel it was given is sensor noise, and its fit
    of it an unstable mode the thrust barely reaches (s_ddot = 25 s + 0.002 (u0 - u1)); the body
    itself does not bend (the truth is PlanarCopter(n_s=1) with s held at 0 by a stiff spring)."""

    def f(self, x, u):
        out = super().f(x, u)
        sl = self.slices
        out[sl["s_dot"]] = 25.0 * np.asarray(x)[sl["s"]] + 0.002 * (u[0] - u[1])
        return out


def test_a_bend_left_out_of_the_regulated_states_gets_no_gain_and_the_copter_hovers():
    model, truth = NoiseFitBend(True, n_s=1), PlanarCopter(True, n_s=1)
    task = Task(start=np.zeros(2), target=np.zeros(2), seconds=10.0, n_s=1)
    every = RelinearizingLQR(model, weights(model), r=2.0, kp=1.0, kd=0.0, n=5, max_thrust=TMAX)
    every.reset(task)
    with pytest.raises(LqrFailure):                             # the noise fit has no usable gain ...
        every.act(0.0, state_of(model, np.zeros(model.n)))
    without = RelinearizingLQR(model, weights(model), r=2.0, kp=1.0, kd=0.0, n=5, max_thrust=TMAX,
                               regulated=np.arange(2, model.n), feedforward=True)
    without.reset(task)
    X, U = fly(model, without, np.zeros(model.n), 10.0, truth=truth)
    assert np.all(without.K[:, :2] == 0.0)                      # ... and nothing without the bend
    assert 1 not in without._rates                              # nor a feed-forward row
    sl = model.slices
    assert np.linalg.norm(X[-1, sl["p"]]) < 1e-2 and abs(X[-1, sl["e"]][0]) < 1e-3


@pytest.mark.parametrize("overrides, regulated", [
    ([], [0, 2, 4, 5, 6, 7, 8, 9]),                     # bend 1 spreads 1.5x the 0.573 deg noise: left out
    (["control.bend_snr=0"], None),                    # the paper: every bend
    (["noise=none"], None),                            # noise-free sensors: every bend is signal
])
def test_ours_regulates_the_bends_its_training_data_saw_above_the_noise(overrides, regulated):
    from sdexp.eval.controllers import ours
    from tests.conftest import make_config
    cfg = make_config(*overrides)
    dyn = PlanarCopter(True, n_s=2)
    dyn.bend_spread = np.array([0.3, 1.5 * np.radians(0.573)])
    ctl = ours(cfg, dyn, TMAX)
    assert (ctl.regulated is None) if regulated is None else ctl.regulated.tolist() == regulated


@pytest.mark.parametrize("q_alike", [0.0, 50.0])
def test_ours_weighs_the_parting_of_the_bends_a_task_moves_together(q_alike):
    from sdexp.control.lqr import alike_weights
    from sdexp.eval.controllers import ours
    from tests.conftest import make_config
    cfg = make_config(f"control.q_s_alike={q_alike}", "control.velocity_scale=0.5", "noise=none")
    dyn = PlanarCopter(True, n_s=3)
    ctl = ours(cfg, dyn, TMAX)
    diagonal = np.diag(state_weights({"n_s": 3, "n_e": 1, "dim": 2}, 100.0, 100.0, 100.0, 0.5))
    together = Task(start=np.zeros(2), target=np.zeros(2), seconds=1.0, n_s=3, bend_times=[0.0, 0.5],
                    bend_targets=[[0, 0, 0], [0.4, 0.0, 0.4]])
    ctl.reset(together)
    expect = diagonal + alike_weights({"n_s": 3, "n_e": 1, "dim": 2}, [np.array([0, 2])], q_alike, 0.5)
    np.testing.assert_allclose(ctl.Q, expect)
    ctl.reset(Task(start=np.zeros(2), target=np.zeros(2), seconds=1.0, n_s=3))   # no bend target: the diagonal
    np.testing.assert_array_equal(ctl.Q, diagonal)


class TwoWingCopter(PlanarCopter):
    """The planar copter with two bends, each raised by its own rotor's thrust."""

    def __init__(self):
        super().__init__(True, n_s=2)

    def f(self, x, u):
        out = super().f(x, u)
        sl, u = self.slices, np.asarray(u, float)
        out[sl["s_dot"]] = -16.0 * x[sl["s"]] - 4.0 * x[sl["s_dot"]] + 0.5 * u
        return out


def test_ours_prices_thrust_differences_between_the_rotors_of_bends_moved_together():
    from sdexp.control.lqr import alike_thrust_weights
    from sdexp.eval.controllers import ours
    from tests.conftest import make_config
    cfg = make_config("control.r_alike=4", "control.r=2", "noise=none")
    dyn = TwoWingCopter()
    ctl = ours(cfg, dyn, TMAX)
    hover = np.full(2, MASS * G / 2)
    x = np.zeros(dyn.n)
    ctl.reset(Task(start=np.zeros(2), target=np.zeros(2), seconds=1.0, n_s=2, bend_times=[0.0, 0.5],
                   bend_targets=[[0.0, 0.0], [0.3, 0.3]]))
    ctl.u = hover.copy()
    ctl.act(0.0, state_of(dyn, x))
    assert [g.tolist() for g in ctl.rotor_groups] == [[0, 1]]
    np.testing.assert_allclose(ctl.R, 2 * np.eye(2) + alike_thrust_weights(2, [np.array([0, 1])], 8.0))
    ctl.reset(Task(start=np.zeros(2), target=np.zeros(2), seconds=1.0, n_s=2))   # no bends moved together
    ctl.act(0.0, state_of(dyn, x))
    assert ctl.rotor_groups == [] and np.array_equal(ctl.R, 2 * np.eye(2))


@pytest.mark.parametrize("pull", [0.0, 0.25])
def test_share_pull_moves_the_operating_thrust_toward_an_even_share_only_where_the_rigid_motion_cannot_feel_it(pull):
    """The bending trirotor's rigid rows feel u1 - u0 (turn) and the total (lift); the one thrust
    direction they do not feel is (1, 1, -2). From u = (3, 3, 9) the even share (5, 5, 5) differs
    by (2, 2, -4), all of it in that direction: u_oper moves pull x (2, 2, -4)."""
    from sdexp.control.relinearizing import unfelt_share
    dyn = BendingTrirotor()
    ctl = RelinearizingLQR(dyn, weights(dyn), r=2.0, kp=1.0, kd=0.0, n=5, max_thrust=TMAX, share_pull=pull)
    ctl.reset(Task(start=np.zeros(2), target=np.zeros(2), seconds=1.0, n_s=1))
    ctl.u = np.array([3.0, 3.0, 9.0])
    ctl.act(0.0, state_of(dyn, np.zeros(dyn.n)))
    np.testing.assert_allclose(ctl.u_oper, [3 + 2 * pull, 3 + 2 * pull, 9 - 4 * pull], atol=1e-6)
    _, _, B = dyn.linearize(np.zeros(dyn.n), ctl.u_oper)
    rigid = np.r_[dyn.slices["e_dot"], dyn.slices["p_dot"]]
    step = unfelt_share(B[rigid], np.array([1.0, 4.0, 1.0]))   # uneven in a felt direction too
    np.testing.assert_allclose(B[rigid] @ step, 0, atol=1e-6)
    with pytest.raises(ValueError, match="share_pull"):
        RelinearizingLQR(dyn, weights(dyn), 2.0, 1.0, 0.0, 5, TMAX, feedforward=True, share_pull=0.2)


def test_ours_bounds_its_feedback_rate_by_the_phase_over_the_command_delay():
    from sdexp.eval.controllers import ours
    from tests.conftest import make_config
    dyn = PlanarCopter(True)
    assert ours(make_config("noise=none"), dyn, TMAX).max_rate is None            # the paper
    cfg = make_config("control.delay_phase_deg=45", "model.command_delay=3", "noise=none")
    assert ours(cfg, dyn, TMAX).max_rate == pytest.approx(np.radians(45) / 0.03)   # 26 rad/s


def test_max_rate_raises_r_by_the_fewest_rungs_that_keep_the_feedback_within_it():
    """The planar copter with stiff gains (R 0.05) turns at 320 rad/s; held to 40 rad/s, R is
    raised in x2 rungs to the first that keeps max |eig(B K)| within it, and lowered back once
    the bound leaves room."""
    dyn = PlanarCopter(True)
    x, u = np.zeros(dyn.n), np.full(2, MASS * G / 2)
    _, A, B = dyn.linearize(x, u)
    free = RelinearizingLQR(dyn, weights(dyn), r=0.05, kp=1.0, kd=0.0, n=1, max_thrust=TMAX)
    capped = RelinearizingLQR(dyn, weights(dyn), r=0.05, kp=1.0, kd=0.0, n=1, max_thrust=TMAX, max_rate=40.0)

    def rate(K):
        return np.abs(np.linalg.eigvals(B @ K)).max()
    assert rate(free.gain(A, B)) > 300.0 and free.r_scale == 1.0
    assert np.allclose(free.gain(A, B), care_gain(A, B, weights(dyn), 0.05))
    K = capped.gain(A, B)
    assert rate(K) <= 40.0 and capped.r_scale > 1.0
    assert rate(care_gain(A, B, weights(dyn), 0.5 * capped.r_scale * 0.05)) > 40.0   # one rung fewer breaks it
    capped.max_rate = 1e3                                      # room again: back to the configured R
    capped.gain(A, B)
    assert capped.r_scale == 1.0
