"""The rigid baselines' model against rigid-body physics written independently here (rotation
matrix and body rates, no Euler angles inside), its linearisation, and RigidLQR flying that
physics in closed loop."""
import numpy as np
import pytest
import torch

from sdexp.control.rigid import (RigidGeometry, RigidLQR, _torch_rate_matrix, _torch_rotation, linearize_rigid,
                                 rigid_dynamics)
from sdexp.control.tasks import Task
from sdexp.sensing.rotations import euler_from_matrix, euler_rate_matrix, euler_rates, matrix_from_euler, skew
from sdexp.sensing import State

G = 9.81
UP3 = np.array([0.0, 1.0, 0.0])


def plus_quad(center_rotor=False, mass=1.2):
    """A flat plate in the xz plane, rotors on its top face 5 cm above the centre of mass."""
    pos = [[0.5, 0.05, 0.0], [-0.5, 0.05, 0.0], [0.0, 0.05, 0.5], [0.0, 0.05, -0.5]]
    if center_rotor:
        pos.append([0.0, 0.05, 0.0])
    return RigidGeometry(mass, np.diag([0.10, 0.19, 0.12]), np.array(pos), np.tile(UP3, (len(pos), 1)))


def lopsided():
    """No symmetry: seven rotors at odd places, all tilted (so any wrench is reachable), a full
    inertia tensor."""
    rng = np.random.default_rng(7)
    pos = rng.uniform(-0.6, 0.6, (7, 3))
    pos[:, 1] = rng.uniform(-0.05, 0.1, 7)
    d = np.tile(UP3, (7, 1)) + 0.2 * rng.normal(size=(7, 3))
    L = rng.normal(size=(3, 3))
    return RigidGeometry(0.8, L @ L.T * 0.05 + 0.05 * np.eye(3), pos, d / np.linalg.norm(d, axis=1, keepdims=True))


def rod_2d(mass=1.0, length=2.0):
    pos = np.array([[-1.0, 0.05], [-0.5, 0.05], [0.0, 0.05], [0.5, 0.05], [1.0, 0.05]]) * [length / 2, 1.0]
    return RigidGeometry(mass, np.array([[mass * length ** 2 / 12]]), pos, np.tile([0.0, 1.0], (5, 1)))


# ------------------------------------------------------------------------------ independent physics

def cross(a, b):
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def wrench(geom, u):
    """Body-frame force and torque of the thrusts: sum of u_i d_i and of u_i r_i x d_i."""
    r, d = geom.rotor_pos.T, geom.rotor_dir.T
    if geom.dim == 2:
        return d @ u, (r[0] * d[1] - r[1] * d[0]) @ u
    return d @ u, cross(r, d) @ u


def body_rhs(s, u, geom):
    """s = (p, v, R (row-major), omega_body): Newton in the world, Euler in the body frame."""
    F, tau = wrench(geom, u)
    R, w, J = s[6:15].reshape(3, 3), s[15:18], geom.inertia
    a = -G * UP3 + R @ F / geom.mass
    w_dot = np.linalg.solve(J, tau - cross(w, J @ w))
    return np.concatenate([s[3:6], a, (R @ skew(w)).ravel(), w_dot])


def rk4(rhs, s, u, geom, h):
    k1 = rhs(s, u, geom)
    k2 = rhs(s + h / 2 * k1, u, geom)
    k3 = rhs(s + h / 2 * k2, u, geom)
    k4 = rhs(s + h * k3, u, geom)
    return s + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def body_state(x):
    """(p, e, p_dot, e_dot) in sdexp's Euler convention -> (p, v, R, omega_body)."""
    p, e, v, e_dot = x[0:3], x[3:6], x[6:9], x[9:12]
    R = matrix_from_euler(e)
    return np.concatenate([p, v, R.ravel(), R.T @ euler_rate_matrix(e) @ e_dot])


def observe(s):
    R = s[6:15].reshape(3, 3)
    e = euler_from_matrix(R)
    return np.concatenate([s[0:3], e, s[3:6], euler_rates(e, R @ s[15:18])])


def true_x_dot(geom, x, u, h=1e-4):
    """x_dot of the rigid body: accelerations exact, e_ddot by central differences of the
    observed Euler rates along the true motion (+-h)."""
    s = body_state(x)
    fwd = observe(rk4(body_rhs, s, u, geom, h))
    bwd = observe(rk4(body_rhs, s, u, geom, -h))
    a = body_rhs(s, u, geom)[3:6]
    return np.concatenate([x[6:12], a, (fwd[9:12] - bwd[9:12]) / (2 * h)])


def rhs_2d(s, u, geom):
    """s = (px, py, theta, vx, vy, omega)."""
    F, tau = wrench(geom, u)
    c, sn = np.cos(s[2]), np.sin(s[2])
    a = np.array([c * F[0] - sn * F[1], sn * F[0] + c * F[1]]) / geom.mass + [0.0, -G]
    return np.concatenate([s[3:6], a, [tau / geom.inertia[0, 0]]])


def f_of(geom):
    f = rigid_dynamics(geom, G)
    return lambda x, u: f(torch.as_tensor(x, dtype=torch.float64), torch.as_tensor(u, dtype=torch.float64)).numpy()


# ------------------------------------------------------------------------------ conventions

def test_torch_rotation_and_rate_matrices_match_sdexp_rotations():
    rng = np.random.default_rng(0)
    for e in rng.uniform(-3, 3, (20, 3)):
        et = torch.as_tensor(e, dtype=torch.float64)
        np.testing.assert_allclose(_torch_rotation(et).numpy(), matrix_from_euler(e), atol=1e-14)
        np.testing.assert_allclose(_torch_rate_matrix(et).numpy(), euler_rate_matrix(e), atol=1e-14)
    # E(e) e_dot is the world angular velocity: R_dot R^T = [omega]x along a path e(t)
    e0, e_dot = np.array([0.3, -1.1, 0.4]), np.array([0.7, -0.2, 0.5])
    h = 1e-6
    R_dot = (matrix_from_euler(e0 + h * e_dot) - matrix_from_euler(e0 - h * e_dot)) / (2 * h)
    W = R_dot @ matrix_from_euler(e0).T
    w = np.array([W[2, 1], W[0, 2], W[1, 0]])
    np.testing.assert_allclose(_torch_rate_matrix(torch.tensor(e0)).numpy() @ e_dot, w, atol=1e-8)


# ------------------------------------------------------------------------------ hover

def test_hover_thrust_of_tilted_rotors_spends_no_thrust_on_what_they_barely_make():
    """Seven randomly tilted rotors: lift and roll/pitch torque exactly; the horizontal force
    and yaw they can make only along a weak direction (0.3% of the strongest) are left there
    rather than cancelled with 100 N of thrust on a 0.8 kg body (what the exact solve spent)."""
    geom = lopsided()
    u = geom.hover_thrust(G)
    F, tau = wrench(geom, u)
    assert F[1] == pytest.approx(geom.mass * G, abs=1e-12)
    np.testing.assert_allclose(tau[[0, 2]], 0.0, atol=1e-12)
    weight = geom.mass * G
    assert np.abs(u).max() < weight and np.hypot(F[0], F[2]) < 0.1 * weight


def test_hover_thrust_of_nearly_vertical_rotors_is_the_vertical_one():
    """A millirad of tilt (a curved mesh's rotor normals) changes the hover by as little."""
    geom = plus_quad()
    rng = np.random.default_rng(3)
    d = geom.rotor_dir + 1e-3 * rng.normal(size=geom.rotor_dir.shape)
    tilted = RigidGeometry(geom.mass, geom.inertia, geom.rotor_pos, d / np.linalg.norm(d, axis=1, keepdims=True))
    np.testing.assert_allclose(tilted.hover_thrust(G), geom.hover_thrust(G), rtol=1e-2)


@pytest.mark.parametrize("geom", [plus_quad(), plus_quad(True), rod_2d()], ids=["quad", "quad5", "rod2d"])
def test_hover_thrust_balances_gravity_with_no_torque(geom):
    u = geom.hover_thrust(G)
    F, tau = wrench(geom, u)
    expect_F = np.zeros(geom.dim)
    expect_F[1] = geom.mass * G
    np.testing.assert_allclose(F, expect_F, atol=1e-12)
    np.testing.assert_allclose(tau, 0.0, atol=1e-12)
    # hover is a fixed point of the model
    n = 12 if geom.dim == 3 else 6
    np.testing.assert_allclose(f_of(geom)(np.zeros(n), u), 0.0, atol=1e-12)
    # minimum norm: no component along the thrust combinations that produce no wrench
    W = geom.wrench_matrix()
    null = np.linalg.svd(W)[2][np.linalg.matrix_rank(W):]
    assert np.abs(null @ u).max() < 1e-10 * np.abs(u).max()


def test_symmetric_hover_thrust_is_shared_equally():
    for geom in (plus_quad(), plus_quad(True), rod_2d(mass=2.0)):
        u = geom.hover_thrust(G)
        np.testing.assert_allclose(u, geom.mass * G / len(u), rtol=1e-12)


def test_wrench_matrix_by_hand():
    geom = RigidGeometry(1.0, np.eye(3), np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 2.0]]), np.array([UP3, [1.0, 0, 0]]))
    # r x d: (1,0,0) x (0,1,0) = (0,0,1);  (0,0,2) x (1,0,0) = (0,2,0)
    np.testing.assert_allclose(geom.wrench_matrix(), [[0, 1], [1, 0], [0, 0], [0, 0], [0, 2], [1, 0]])
    g2 = RigidGeometry(1.0, np.eye(1), np.array([[2.0, 0.5]]), np.array([[0.0, 1.0]]))
    np.testing.assert_allclose(g2.wrench_matrix(), [[0.0], [1.0], [2.0]])


# ------------------------------------------------------------------------------ dynamics

@pytest.mark.parametrize("seed", [0, 1, 2])
def test_3d_dynamics_is_newton_euler(seed):
    """At random states away from gimbal lock, including the gyroscopic w x J w term."""
    rng = np.random.default_rng(seed)
    geom = lopsided()
    x = np.concatenate([rng.normal(size=3), rng.uniform(-1.0, 1.0, 3), rng.normal(size=3), rng.normal(size=3) * 2])
    u = rng.uniform(0.0, 5.0, 7)
    np.testing.assert_allclose(f_of(geom)(x, u), true_x_dot(geom, x, u), rtol=1e-6, atol=1e-6)


def test_2d_dynamics_by_hand():
    geom = rod_2d()
    x = np.array([0.3, -0.2, 0.4, 1.0, -2.0, 0.7])
    u = np.array([1.0, 2.0, 0.5, 3.0, 0.0])
    np.testing.assert_allclose(f_of(geom)(x, u), rhs_2d(x, u, geom), rtol=1e-13, atol=1e-13)


@pytest.mark.parametrize("geom", [lopsided(), rod_2d()], ids=["3d", "2d"])
def test_linearization_matches_central_differences(geom):
    rng = np.random.default_rng(3)
    n = 12 if geom.dim == 3 else 6
    f = f_of(geom)
    for _ in range(3):
        x = rng.uniform(-0.8, 0.8, n)
        u = rng.uniform(0.0, 4.0, geom.rotor_pos.shape[0])
        A, B = linearize_rigid(geom, G, x, u)
        h = 1e-6
        Af = np.stack([(f(x + h * e, u) - f(x - h * e, u)) / (2 * h) for e in np.eye(n)], 1)
        Bf = np.stack([(f(x, u + h * e) - f(x, u - h * e)) / (2 * h) for e in np.eye(len(u))], 1)
        np.testing.assert_allclose(A, Af, atol=1e-6 * max(1.0, np.abs(A).max()))
        np.testing.assert_allclose(B, Bf, atol=1e-6 * max(1.0, np.abs(B).max()))


def test_hover_linearization_has_the_textbook_entries():
    m, J = 1.2, np.diag([0.10, 0.19, 0.12])
    geom = plus_quad(mass=m)
    A, B = linearize_rigid(geom, G, np.zeros(12), geom.hover_thrust(G))
    # x = (p, e, p_dot, e_dot): kinematic identity blocks
    np.testing.assert_array_equal(A[0:6, 6:12], np.eye(6))
    # tilting the thrust: rolling about +x (e_x) tips +y towards +z, about +z (e_z) towards -x
    acc_e = A[6:9, 3:6]
    np.testing.assert_allclose(acc_e, [[0, 0, -G], [0, 0, 0], [G, 0, 0]], atol=1e-12)
    assert not A[6:12, 6:12].any()                          # no damping in a rigid body at hover
    # thrusts: each rotor lifts 1/m; rotor (0.5, ., 0) pitches about +z by 0.5 / J_zz, rotor
    # (0, ., 0.5) rolls about -x by 0.5 / J_xx (at e = 0 the Euler rates are the body rates)
    np.testing.assert_allclose(B[7], np.full(4, 1 / m), rtol=1e-12)
    np.testing.assert_allclose(B[6], 0.0, atol=1e-15)
    np.testing.assert_allclose(B[8], 0.0, atol=1e-15)
    np.testing.assert_allclose(B[9], [0, 0, -0.5 / J[0, 0], 0.5 / J[0, 0]], rtol=1e-12)
    np.testing.assert_allclose(B[11], [0.5 / J[2, 2], -0.5 / J[2, 2], 0, 0], rtol=1e-12)
    # no rotor reaction torque: nothing yaws the body (row e_y_ddot), and yaw moves nothing
    assert not B[10].any()
    assert not A[:, 4].any() and not A[:, 10][np.arange(12) != 4].any()


def test_2d_hover_linearization_by_hand():
    geom = rod_2d(mass=2.0, length=3.0)
    A, B = linearize_rigid(geom, G, np.zeros(6), geom.hover_thrust(G))
    Jz = 2.0 * 9.0 / 12
    expect_A = np.zeros((6, 6))
    expect_A[0:3, 3:6] = np.eye(3)
    expect_A[3, 2] = -G                    # tilting by +theta tips the thrust towards -x
    np.testing.assert_allclose(A, expect_A, atol=1e-12)
    np.testing.assert_allclose(B[4], np.full(5, 0.5), rtol=1e-12)
    np.testing.assert_allclose(B[5], geom.rotor_pos[:, 0] / Jz, rtol=1e-12)
    assert not B[:4].any()


# ------------------------------------------------------------------------------ closed loop

def controller(geom, **kw):
    return RigidLQR(lambda: geom, q_e=100.0, q_p=100.0, velocity_scale=1.0, r=2.0, gravity=G, **kw)


@pytest.mark.parametrize("geom", [plus_quad(), plus_quad(True)], ids=["quad", "quad5"])
def test_rigid_lqr_flies_the_rigid_body_to_the_goal(geom):
    """Nonlinear physics (RK4 on R and body rates), 100 Hz control, from 1.4 m off and a
    10 degree tilt (plus 5 degrees of the uncontrollable yaw)."""
    target = np.array([1.0, -0.5, 0.8])
    ctl = controller(geom)
    ctl.reset(Task(start=np.zeros(3), target=target, seconds=6.0, n_s=0))
    # no feedback on yaw: nothing could act on it
    assert np.abs(ctl.K[:, [4, 10]]).max() < 1e-9
    s = body_state(np.concatenate([np.zeros(3), np.deg2rad([10.0, 5.0, -10.0]), np.zeros(6)]))
    errs = []
    for k in range(600):
        x = observe(s)
        st = State(np.zeros(0), x[3:6], x[0:3], np.zeros(0), x[9:12], x[6:9])
        u = np.clip(ctl.act(k * 0.01, st), -10.0, 10.0)
        s = rk4(body_rhs, s, u, geom, 0.01)
        s[6:15] = (lambda U, _, Vt: (U @ Vt).ravel())(*np.linalg.svd(s[6:15].reshape(3, 3)))
        errs.append(np.linalg.norm(s[0:3] - target))
    x = observe(s)
    assert errs[99] < 0.8 * errs[0]
    assert errs[-1] < 0.01
    assert np.abs(x[[3, 5]]).max() < np.deg2rad(0.2)           # level
    assert np.abs(x[6:12]).max() < 0.02                        # at rest
    np.testing.assert_allclose(u, geom.hover_thrust(G), atol=0.02)


def test_rigid_lqr_flies_the_2d_rod_to_the_goal():
    geom = rod_2d()
    target = np.array([-0.8, 0.6])
    ctl = controller(geom)
    ctl.reset(Task(start=np.zeros(2), target=target, seconds=6.0, n_s=0))
    s = np.array([0.0, 0.0, np.deg2rad(10.0), 0.0, 0.0, 0.0])
    for k in range(600):
        st = State(np.zeros(0), s[2:3], s[0:2], np.zeros(0), s[5:6], s[3:5])
        u = np.clip(ctl.act(k * 0.01, st), -10.0, 10.0)
        s = rk4(rhs_2d, s, u, geom, 0.01)
    assert np.linalg.norm(s[0:2] - target) < 0.01
    assert abs(s[2]) < np.deg2rad(0.2) and np.abs(s[3:]).max() < 0.02


def test_rigid_lqr_command_at_the_goal_is_hover_and_yaw_turns_wrap():
    geom = plus_quad()
    ctl = controller(geom)
    ctl.reset(Task(start=np.zeros(3), target=[1.0, 2.0, 3.0], seconds=1.0, n_s=0))
    at_goal = State(np.zeros(0), np.zeros(3), np.array([1.0, 2.0, 3.0]), np.zeros(0), np.zeros(3), np.zeros(3))
    np.testing.assert_allclose(ctl.act(0.0, at_goal), geom.hover_thrust(G), rtol=1e-12)
    # a pitch of 2 pi + 0.1 is a pitch of 0.1
    a = State(np.zeros(0), np.array([0.0, 0.0, 0.1]), np.zeros(3), np.zeros(0), np.zeros(3), np.zeros(3))
    b = State(np.zeros(0), np.array([0.0, 0.0, 0.1 + 2 * np.pi]), np.zeros(3), np.zeros(0), np.zeros(3), np.zeros(3))
    np.testing.assert_allclose(ctl.act(0.0, a), ctl.act(0.0, b), rtol=1e-12)
    assert not np.allclose(ctl.act(0.0, a), geom.hover_thrust(G))


def test_geometry_updating_lqr_redesigns_on_schedule():
    calls = []
    geoms = [plus_quad(mass=1.0), plus_quad(mass=2.0)]

    def geometry():
        calls.append(1)
        return geoms[min(len(calls) - 1, 1)]

    ctl = controller(None, update_every=3)
    ctl.geometry = geometry
    ctl.reset(Task(start=np.zeros(3), target=np.zeros(3), seconds=1.0, n_s=0))
    assert len(calls) == 1
    np.testing.assert_allclose(ctl.u_star, np.full(4, G / 4))
    rest = State(np.zeros(0), np.zeros(3), np.zeros(3), np.zeros(0), np.zeros(3), np.zeros(3))
    for k in range(7):
        ctl.act(0.01 * k, rest)
    assert len(calls) == 1 + 2                          # redesigned at steps 3 and 6
    np.testing.assert_allclose(ctl.u_star, np.full(4, 2.0 * G / 4))   # from the new mass
    ctl_fixed = controller(plus_quad())
    ctl_fixed.reset(Task(start=np.zeros(3), target=np.zeros(3), seconds=1.0, n_s=0))
    K = ctl_fixed.K.copy()
    for k in range(5):
        ctl_fixed.act(0.01 * k, rest)
    np.testing.assert_array_equal(ctl_fixed.K, K)
